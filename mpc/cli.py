"""``pinnmpc check-model``."""

from __future__ import annotations

import argparse
from pathlib import Path

from sim.files import write_json


def register(sub) -> None:
    """Add this package's subcommands to the ``pinnmpc`` parser."""
    p = sub.add_parser("check-model", help="validate an ONNX dynamics model against the model contract",
                       description="Check inputs x [B, 12] and u [B, 4], output x_next [B, 12], dynamic batch, "
                                   "required metadata, a test evaluation with onnxruntime, and the derivative "
                                   "graph <stem>.jac.onnx when present. Exit 0 when valid; otherwise exit 2 "
                                   "with a message naming the defect.")
    p.add_argument("file", metavar="FILE", type=Path, help="the .onnx model file")
    p.add_argument("--json", metavar="FILE", type=Path, default=None, help="write what the model declares as JSON")
    p.set_defaults(handler=cmd_check_model)


def format_model_info(info) -> str:
    """Short human-readable summary of a :class:`mpc.contract.ModelInfo`."""
    theta = " ".join(f"{k}={v:.4g}" for k, v in info.theta.items())
    metrics = ", ".join(info.test_metrics) if info.test_metrics else "(none)"
    jac = str(info.jacobian) if info.jacobian is not None else "none (derivatives by CasADi import or differencing)"
    return "\n".join([
        f"{info.path}: valid (contract {info.metadata.get('pinnmpc.contract')})",
        f"  architecture    {info.architecture}",
        f"  dtype           {info.dtype.name}",
        f"  dt              {info.dt:g} s",
        f"  theta           {theta}",
        f"  jacobian graph  {jac}",
        f"  dataset seed    {info.dataset_seed}, config hash {info.config_hash[:12]}, code {info.code_version}",
        f"  test metrics    {metrics}",
    ])


def cmd_check_model(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc check-model``."""
    from .contract import check_model

    info = check_model(args.file)
    print(format_model_info(info))
    if args.json:
        write_json(args.json, info.to_dict())
        print(f"wrote {args.json}")
    return 0
