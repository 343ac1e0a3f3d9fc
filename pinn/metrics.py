"""Accuracy metrics of a one-step model, always on the test split.

A model is any ``step(x, u) -> x_next`` on numpy arrays (B, 12), (B, 4) ->
(B, 12): a torch model wrapped by :func:`torch_step`, or an ONNX file through
onnxruntime (:func:`pinn.evaluate.onnx_step`). A model with E extra states
takes and returns (B, 12 + E); the metrics are then given the extra states
along the data (``extra``, (flights, steps, E)) and measure the rigid body's
errors. Only :func:`torch_step` imports torch, when called.
"""

from __future__ import annotations

import numpy as np

from sim.params import NX, STATE_NAMES

#: A rollout whose state leaves these bounds (or is not finite) has diverged.
FINITE_RANGE = np.repeat([1e3, 1e3, 1e4, 1e3], 3)  # m, rad, rad/s, m/s
POSITION = slice(0, 3)
#: A rollout leaves the flight envelope when its position error exceeds this (m) or it diverges.
ENVELOPE_POSITION_M = 1.0


def _with_extra(x: np.ndarray, extra) -> np.ndarray:
    return x if extra is None else np.concatenate([x, extra], axis=-1)


def one_step_mae(step, ds, split: str = "test", batch: int = 20000, extra=None) -> dict:
    """Mean absolute one-step error per state on ``split``.

    Returns
    -------
    dict
        ``{state_name: MAE}`` in the state's units, plus ``position`` (mean over x, y, z).
    """
    pairs = ds.pairs(split)
    x, u, y = pairs["x"], pairs["u"], pairs["x_next"]
    if extra is not None:       # the model's extra states at each sample, flattened as the pairs are
        sel = ds.split == ("train", "val", "test").index(split)
        x = _with_extra(x, np.asarray(extra)[sel].reshape(len(x), -1))
    err = np.empty_like(y)
    for lo in range(0, len(x), batch):
        err[lo:lo + batch] = np.abs(step(x[lo:lo + batch], u[lo:lo + batch])[:, :NX] - y[lo:lo + batch])
    mae = err.mean(axis=0)
    out = dict(zip(STATE_NAMES, map(float, mae)))
    out["position"] = float(mae[POSITION].mean())
    return out


def rollout_starts(ds, split: str, horizon: int, n_starts: int, seed: int) -> np.ndarray:
    """Seeded (trajectory, start index) pairs (n, 2) for rollouts that fit in the data."""
    traj = np.flatnonzero(ds.split == ("train", "val", "test").index(split))
    n_steps = ds.x.shape[1]
    if n_steps < horizon:
        raise ValueError(f"horizon {horizon} is longer than the trajectories ({n_steps} steps)")
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.choice(traj, n_starts), rng.integers(0, n_steps - horizon + 1, n_starts)])


def rollout_mae(step, ds, split: str = "test", horizon: int = 100, n_starts: int = 200, seed: int = 0,
                extra=None) -> dict:
    """Autoregressive ``horizon``-step rollouts with the recorded inputs.

    From ``n_starts`` seeded start points of the ``split`` trajectories, the
    model's own prediction is fed back for ``horizon`` steps. The MAE is over
    the ``horizon`` predicted steps and all rollouts, per state. A rollout
    that leaves :data:`FINITE_RANGE` (or becomes non-finite) is counted as
    diverged with its step of divergence; from that step on it keeps its
    last in-range prediction, so it stays in the MAE with a large error
    rather than being dropped.

    Returns
    -------
    dict
        Per-state MAE, ``position`` (mean over x, y, z), ``n_rollouts``,
        ``n_diverged``, ``divergence_steps`` (list, 1-based), the
        position MAE at each horizon step (``position_by_step``), and
        ``n_left_envelope``: rollouts whose position error exceeded
        :data:`ENVELOPE_POSITION_M` at some step, or that diverged.
    """
    starts = rollout_starts(ds, split, horizon, n_starts, seed)
    ti, si = starts[:, 0], starts[:, 1]
    x = _with_extra(ds.x[ti, si], None if extra is None else np.asarray(extra)[ti, si]).copy()
    err = np.zeros((len(starts), horizon, NX))
    alive = np.ones(len(starts), dtype=bool)
    div_step = np.zeros(len(starts), dtype=int)
    for k in range(horizon):
        u = ds.u[ti, si + k]
        with np.errstate(all="ignore"):
            nxt = step(x, u)
            bad = ~(np.all(np.isfinite(nxt), axis=1) & np.all(np.abs(nxt[:, :NX]) < FINITE_RANGE, axis=1))
        newly = bad & alive
        div_step[newly] = k + 1
        alive &= ~bad
        x = np.where(alive[:, None], nxt, x)
        err[:, k] = np.abs(x[:, :NX] - ds.x_next[ti, si + k])
    mae = err.mean(axis=(0, 1))
    left = ~alive | np.any(np.linalg.norm(err[:, :, POSITION], axis=2) > ENVELOPE_POSITION_M, axis=1)
    out = dict(zip(STATE_NAMES, map(float, mae)))
    out.update({
        "n_left_envelope": int(left.sum()),
        "position": float(mae[POSITION].mean()),
        "n_rollouts": int(len(starts)),
        "n_diverged": int((~alive).sum()),
        "divergence_steps": [int(s) for s in div_step[~alive]],
        "position_by_step": [float(v) for v in err[:, :, POSITION].mean(axis=(0, 2))],
        "horizon": horizon,
    })
    return out


def torch_step(model):
    """numpy ``step(x, u)`` of a torch model, evaluated in float64."""
    import copy

    import torch

    m = copy.deepcopy(model).double().eval()

    def step(x, u):
        with torch.no_grad():
            return m(torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(u, dtype=torch.float64)).numpy()
    return step


def test_metrics(model, ds) -> dict:
    """Compact test-split metrics of a torch model (stored in the ONNX metadata and the manifest)."""
    step = torch_step(model)
    extra = None
    if getattr(model, "extra_states", ()):      # a motor-lag model: its own rotor speeds along the commands
        from .train import model_rotor_speeds
        extra = model_rotor_speeds(model, ds.u)
    one = one_step_mae(step, ds, extra=extra)
    roll = rollout_mae(step, ds, extra=extra)
    return {"one_step_mae": one,
            "rollout_100_mae": {k: v for k, v in roll.items() if k not in ("position_by_step", "divergence_steps")},
            "rollout_100_divergence_steps": roll["divergence_steps"]}
