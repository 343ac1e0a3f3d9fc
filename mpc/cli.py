"""``pinnmpc check-model``."""

from __future__ import annotations

import argparse
from pathlib import Path

from sim.files import check_writable, write_json
from sim.levels import DEFAULT_LEVEL, LEVEL_INPUTS, LEVELS


def register(sub) -> None:
    """Add this package's subcommands to the ``pinnmpc`` parser."""
    p = sub.add_parser("check-model", help="validate an ONNX dynamics model and say which controllers can fly it",
                       description="Check inputs x [B, 12] and u [B, 4], output x_next [B, 12], dynamic batch, "
                                   "the metadata 'dt' (the only required key; the others are checked where given), "
                                   "a test evaluation with onnxruntime, and the derivative graph <stem>.jac.onnx "
                                   "when present (against central differences, across the flight envelope). Then "
                                   "print, for each controller, whether it can fly the model and how it gets the "
                                   "model's derivatives; pinnmpc fly refuses exactly what this refuses. Exit 0 "
                                   "when the file is valid and some controller can fly it; exit 1 when it is "
                                   "valid but no controller can fly it (a last line on stderr says why); exit 2 "
                                   "with a message naming the defect when the file is not valid.")
    p.add_argument("file", metavar="FILE", type=Path, help="the .onnx model file")
    p.add_argument("--json", metavar="FILE", type=Path, default=None, help="write what the model declares as JSON")
    p.add_argument("--level", metavar="LEVEL", choices=LEVELS, default=None,
                   help=f"refuse the file unless it declares this command level ({', '.join(LEVELS)}; a file "
                        f"without the metadata 'level' is at {DEFAULT_LEVEL})")
    p.set_defaults(handler=cmd_check_model)


def format_model_info(info, ready=None) -> str:
    """Short human-readable summary of a :class:`mpc.prediction.contract.ModelInfo` and, if given, the controllers'
    readiness."""
    def opt(v, text=str):
        return "(not given)" if v is None else text(v)

    theta = opt(info.theta, lambda t: " ".join(f"{k}={v:.4g}" for k, v in t.items()))
    if info.theta is None:
        theta += " -> the vehicle spec uses the datasheet's m, J, kt, kq"
    jac = str(info.jacobian) if info.jacobian is not None else "none (A and B by central differences of the model)"
    lines = [
        f"{info.path}: valid (contract {info.metadata.get('pinnmpc.contract', '2, minimal')})",
        f"  architecture    {info.architecture}",
        f"  dtype           {info.dtype.name}",
        f"  dt              {info.dt:g} s",
        f"  level           {info.level} (u = {', '.join(LEVEL_INPUTS[info.level])})",
        f"  theta           {theta}",
        f"  jacobian graph  {jac}",
        f"  extra states    " + ("none (the 12 rigid-body states)" if not info.extra_states else
                                 f"{len(info.extra_states)}: {', '.join(info.extra_states)} (state length "
                                 f"{info.nx}; the controllers carry them from period to period)"),
        f"  provenance      dataset seed {opt(info.dataset_seed)}, config hash "
        f"{opt(info.config_hash, lambda h: h[:12])}, code {opt(info.code_version)}",
        f"  test metrics    {opt(info.test_metrics, lambda m: ', '.join(m) or '(none)')}",
    ]
    if ready:
        lines.append("  controllers")
        for r in ready.values():
            lines.append(f"    {r.controller:<5} " + (f"flies: derivatives by {r.derivatives} ({r.reason})" if r.flies
                                                      else f"cannot fly: {r.reason}"))
            if r.warning:
                lines.append(f"          warning: {r.warning}")
    return "\n".join(lines)


def cmd_check_model(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc check-model``: 0 when some controller can fly the file, 1 when none can (a valid file,
    but nothing here flies it), and an invalid file raises (the command line's exit 2)."""
    import sys

    from .controllers.readiness import readiness
    from .errors import ModelContractError
    from .prediction.models import OnnxModel

    if args.json is not None:
        check_writable(args.json, "--json")             # before the check, so that a refusal writes nothing
    model = OnnxModel(args.file)
    if args.level is not None and model.level != args.level:
        given = "" if "level" in model.info.metadata else ", absent"
        raise ModelContractError(f"{args.file}: the model is at the command level {model.level!r} (metadata "
                                 f"'level'{given}); --level {args.level} asks for a model at {args.level!r}")
    ready = readiness(model)
    print(format_model_info(model.info, ready))
    if args.json:
        write_json(args.json, {**model.info.to_dict(),
                               "controllers": {c: {"flies": r.flies, "derivatives": r.derivatives, "reason": r.reason,
                                                   "warning": r.warning}
                                               for c, r in ready.items()}})
        print(f"wrote {args.json}")
    if not any(r.flies for r in ready.values()):
        why = "; ".join(dict.fromkeys(r.reason for r in ready.values()))
        print(f"pinnmpc check-model: no controller can fly {args.file}: {why}", file=sys.stderr)
        return 1
    return 0
