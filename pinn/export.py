"""ONNX export of trained models.

``export_model`` writes, in float64 (IPOPT needs exact derivatives; a float32
model made it fail):

* ``<name>.onnx``: ``x`` [B, 12], ``u`` [B, 4] -> ``x_next`` [B, 12] with the
  normalization inside, a dynamic batch and the metadata of the contract (a
  motor-lag model's state is [B, 16], its rotor speeds named in ``extra_states``,
  its identified time constant in ``motor_tau``);
* ``<name>.jac.onnx``: the same inputs -> ``x_next``, ``A = dx_next/dx``
  [B, 12, 12], ``B = dx_next/du`` [B, 12, 4], from the models' exact
  forward-mode Jacobian written with plain tensor operations;
* ``<name>.pt``: the torch weights, stats and config (for retraining checks
  and torch/onnxruntime parity tests).

Both ONNX files keep their weights inside (no external data files).
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import logging
import warnings
from pathlib import Path

import torch

from mpc.prediction.contract import CONTRACT_VERSION, config_hash, jacobian_path
from sim import __version__ as code_version
from sim.files import json_ready
from sim.params import DT, INPUT_NAMES, STATE_NAMES, THETA_NAMES

from .models import aero_record, build_model


class _Next(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, x, u):
        return self.model(x, u)


class _Jac(torch.nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, x, u):
        return self.model.forward_jacobian(x, u)


def _export(module, path: Path, outputs: list[str], nx: int = 12) -> None:
    # torch's TorchScript-based exporter: about a second per graph, where the dynamo exporter took 8-40 s (most of a
    # quick training's time). It keeps the float64 constants (the graphs match torch to rounding; the physics avoids
    # arithmetic between 0-dim tensors, which this exporter would compute in float32).
    x = torch.zeros(3, nx, dtype=torch.float64)
    u = torch.zeros(3, 4, dtype=torch.float64)
    logging.getLogger("torch.onnx").setLevel(logging.ERROR)
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")     # the exporter's deprecation notice
        torch.onnx.export(module, (x, u), str(path), input_names=["x", "u"], output_names=outputs,
                          dynamic_axes={name: {0: "batch"} for name in ("x", "u", *outputs)}, dynamo=False)
    # This exporter leaves the outputs' other dimensions symbolic where the graph reshapes; the contract states them.
    import onnx

    with torch.no_grad():
        found = module(x, u)
    found = found if isinstance(found, tuple) else (found,)
    m = onnx.load(str(path))
    for out, value in zip(m.graph.output, found):
        for dim, size in zip(out.type.tensor_type.shape.dim[1:], value.shape[1:]):
            dim.ClearField("dim_param")
            dim.dim_value = int(size)
    onnx.save(m, str(path))


def _set_metadata(path: Path, meta: dict) -> None:
    import onnx

    m = onnx.load(str(path))
    del m.metadata_props[:]
    for k, v in meta.items():
        e = m.metadata_props.add()
        e.key, e.value = k, v
    onnx.save(m, str(path))


def export_model(model, out_dir, name: str, training_config: dict, dataset_seed: int, test_metrics: dict,
                 stats: dict | None = None, torch_file: bool = True) -> dict:
    """Write ``<name>.onnx``, ``<name>.jac.onnx`` and ``<name>.pt`` into ``out_dir``.

    Parameters
    ----------
    model : pinn.models.ResidualPINN
        Trained model (any dtype; exported as a float64 copy in evaluation mode).
    out_dir : path
        Target folder (created).
    name : str
        File stem.
    training_config : dict
        Everything that defines the run (training settings and data); hashed.
    dataset_seed : int
        Seed of the training data.
    test_metrics : dict
        Test-split metrics to store in the metadata.
    stats : dict, optional
        Normalization statistics, stored in the ``.pt`` file.
    torch_file : bool
        Write the ``.pt`` file (the zoo does not: its command retrains a model in seconds).

    Returns
    -------
    dict
        Paths written: ``onnx``, ``jacobian``, ``torch`` (if written).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    m64 = copy.deepcopy(model).double().eval()
    theta = m64.theta.detach().numpy()
    meta = {
        "pinnmpc.contract": CONTRACT_VERSION,
        "architecture": m64.arch,
        "dt": repr(DT),
        "state_names": json.dumps(list(STATE_NAMES)),
        "input_names": json.dumps(list(INPUT_NAMES)),
        "theta": json.dumps({n: float(v) for n, v in zip(THETA_NAMES, theta)}),
        "training_config": json.dumps(training_config, sort_keys=True),
        "config_hash": config_hash(training_config),
        "dataset_seed": str(int(dataset_seed)),
        "code_version": code_version,
        "test_metrics": json.dumps(test_metrics, sort_keys=True),
        "torch_version": torch.__version__,
    }
    extra = tuple(getattr(m64, "extra_states", ()))
    if extra:
        meta["extra_states"] = json.dumps(list(extra))
    if hasattr(m64, "tau"):
        meta["motor_tau"] = repr(float(m64.tau.detach()))
    if getattr(m64, "aero_terms", ()):
        # strict JSON: an interval the identification could not give (one training flight) is null, not NaN
        meta["aero_terms"] = json.dumps(json_ready(aero_record(m64)), sort_keys=True, allow_nan=False)
    path = out_dir / f"{name}.onnx"
    jac = jacobian_path(path)
    _export(_Next(m64), path, ["x_next"], 12 + len(extra))
    _export(_Jac(m64), jac, ["x_next", "A", "B"], 12 + len(extra))
    _set_metadata(path, meta)
    _set_metadata(jac, {k: meta[k] for k in ("pinnmpc.contract", "architecture", "config_hash")})
    if not torch_file:
        return {"onnx": path, "jacobian": jac}
    pt = out_dir / f"{name}.pt"
    torch.save({"arch": model.arch, "describe": model.describe(), "state_dict": model.state_dict(),
                "training_config": training_config,
                "stats": {k: torch.as_tensor(v) for k, v in (stats or {}).items()}}, pt)
    return {"onnx": path, "jacobian": jac, "torch": pt}


def load_torch_model(path):
    """Rebuild a model saved by :func:`export_model` (float32, evaluation mode)."""
    blob = torch.load(path, map_location="cpu", weights_only=False)
    d = blob["describe"]
    sd = blob["state_dict"]
    stats = {"in_mean": sd["in_mean"], "in_std": sd["in_std"], "out_scale": sd["out_scale"]}
    stats.update({k: sd[k] for k in ("abs_in_mean", "abs_in_std", "abs_out_mean", "abs_out_std", "physics",
                                      "n_mean", "n_std", "rotor") if k in sd})
    model = build_model(blob["arch"], stats, sd["log_theta"].exp(), d["hidden"], d["layers"], d["dropout"],
                        d.get("variant"), d.get("aero"))
    model.load_state_dict(sd)
    if d.get("aero_identified"):
        model.aero_identified = dict(d["aero_identified"])
    return model.eval(), blob
