"""Where does a PINN's identified theta come from? Refit it against the trained network and against the data.

Run ``python -m pinn.refit models/proposed.pt models/baseline.pt [--samples 20000] [--json FILE]``.

During training theta-hat is fitted to the network's own prediction (the physics residual on data points, with
the network held fixed; see :mod:`pinn.train`). This diagnostic takes a trained model and the training split it
was trained on (regenerated from the data description in the ``.pt`` file), and fits (m, Jxx, Jyy, Jzz) three
ways with the same residual (RK4 step of the nominal model under theta, over the model's residual scale):

* against the network's evaluation-mode prediction from the measured states (what training identifies against);
* against the mean of 64 training-mode (dropout) predictions (differs only for recipes with dropout);
* against the measured increments ``x_next - x`` (no network: an equation-error fit of the same data).

If the first two land where the model's theta-hat is and the third near the truth, theta-hat's error is the
network's fitting error carried into the parameters, not a property of the data. kt and kq are left at the
model's values (they are identified from the rotor telemetry, not from the network). Prints a table and writes
JSON; no assertions.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from sim.files import write_json

FITTED = ("m", "Jxx", "Jyy", "Jzz")
DROPOUT_SAMPLES = 64


def _fit(target, X, U, theta_model, scale, p) -> np.ndarray:
    """(m, Jxx, Jyy, Jzz) minimizing the mean squared scaled residual against ``target`` (L-BFGS, float64)."""
    import torch

    from .physics import rk4_increment

    log_t = torch.tensor(np.log(theta_model[:4]), dtype=torch.float64, requires_grad=True)
    rest = torch.tensor(theta_model[4:], dtype=torch.float64)
    opt = torch.optim.LBFGS([log_t], lr=1.0, max_iter=200, tolerance_grad=1e-14, tolerance_change=1e-16,
                            line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        r = (target - rk4_increment(X, U, torch.cat([log_t.exp(), rest]), p)) / scale
        loss = (r * r).mean()
        loss.backward()
        return loss
    for _ in range(3):
        opt.step(closure)
    return np.exp(log_t.detach().numpy())


def refit(path, samples: int = 20000, seed: int = 0) -> dict:
    """The three refits of one ``.pt`` model (see the module docstring); errors in % of the true values."""
    import torch

    from sim.params import QuadParams

    from .evaluate import regenerate
    from .export import load_torch_model

    model, blob = load_torch_model(path)
    spec = (blob.get("training_config") or {}).get("data")
    if not isinstance(spec, dict):
        raise ValueError(f"{path}: no data description in its training_config; cannot regenerate its data")
    ds = regenerate(spec)
    truth = QuadParams(**ds.meta["params"])
    tr = ds.split == 0
    n_all = int(tr.sum()) * ds.x.shape[1]
    idx = np.random.default_rng(seed).choice(n_all, min(samples, n_all), replace=False)
    X = torch.as_tensor(ds.x[tr].reshape(-1, 12)[idx])
    U = torch.as_tensor(ds.u[tr].reshape(-1, 4)[idx])
    Y = torch.as_tensor(ds.x_next[tr].reshape(-1, 12)[idx])
    scale = model.out_scale.double()
    theta_model = model.theta.detach().double().numpy()
    with torch.no_grad():
        m32 = model.float().eval()
        targets = {"network (evaluation mode)": m32.increment(X.float(), U.float()).double()}
        if any(isinstance(mod, torch.nn.Dropout) and mod.p > 0 for mod in m32.modules()):
            m32.train()
            torch.manual_seed(seed)
            targets[f"network (mean of {DROPOUT_SAMPLES} dropout samples)"] = torch.stack(
                [m32.increment(X.float(), U.float()).double() for _ in range(DROPOUT_SAMPLES)]).mean(0)
            m32.eval()
        targets["measured increments (no network)"] = Y - X
    t = truth.theta[:4]
    out = {"model": Path(path).stem, "samples": int(len(idx)),
           "theta_hat_err_pct": dict(zip(FITTED, map(float, 100 * (theta_model[:4] - t) / t))), "refits": {}}
    for name, target in targets.items():
        th = _fit(target, X, U, theta_model, scale, truth)
        out["refits"][name] = dict(zip(FITTED, map(float, 100 * (th - t) / t)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m pinn.refit", description=__doc__.split("\n\n")[0])
    ap.add_argument("models", nargs="+", type=Path, help="trained models (.pt files written by pinnmpc train)")
    ap.add_argument("--samples", type=int, default=20000, help="training transitions used (default 20000)")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    rows = []
    for path in args.models:
        if not path.is_file():
            print(f"error: {path} does not exist", file=sys.stderr)
            return 2
        r = refit(path, args.samples)
        rows.append(r)
        print(f"\n{r['model']} ({r['samples']} training transitions), error % of the truth:")
        print(f"  {'fitted against':<42}" + "".join(f"{n:>9}" for n in FITTED))
        print(f"  {'(theta-hat of the model)':<42}" + "".join(f"{r['theta_hat_err_pct'][n]:>+9.3f}" for n in FITTED))
        for name, err in r["refits"].items():
            print(f"  {name:<42}" + "".join(f"{err[n]:>+9.3f}" for n in FITTED))
    if args.json:
        write_json(args.json, {"rows": rows})
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
