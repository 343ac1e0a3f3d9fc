"""The ``pinnmpc`` command line.

Each package contributes its own subcommands through a ``register(subparsers)``
function; heavy imports happen inside the command handlers, so ``pinnmpc
--help`` is fast and commands that fly ONNX models never import torch.
"""

from __future__ import annotations

import argparse
import sys

from mpc import cli as mpc_cli
from pinn import cli as pinn_cli
from sim import cli as sim_cli

from . import commands as scenario_cli

PACKAGES = (sim_cli, pinn_cli, mpc_cli, scenario_cli)


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every package's subcommands."""
    parser = argparse.ArgumentParser(
        prog="pinnmpc",
        description="PINN-identified quadrotor dynamics flown by model predictive control.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for pkg in PACKAGES:
        pkg.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``pinnmpc`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except ValueError as e:  # every user-input error of the packages is a ValueError subclass
        print(f"pinnmpc {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"pinnmpc {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
