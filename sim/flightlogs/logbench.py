"""Open-loop prediction error on imported flights: the nano-drone benchmark's protocol.

From every window start ``i`` of a flight whose state was measured, a model
predicts ``h`` steps ahead from the logged state ``x[i]`` with the logged
(delay-aligned) inputs ``u[i], ..., u[i + h - 1]``, feeding back its own
predictions. At each horizon ``h`` in :data:`HORIZONS` the error against the
logged state ``x[i + h]`` (where it was measured) is, per window:

* position and velocity: the Euclidean norm of the difference (m, m/s);
* rotation: the angle of the relative rotation (rad);
* angular velocity: the Euclidean norm of the body-rate difference (rad/s);

and the table holds each mean over windows. These are the benchmark's
"MAE" (its notebook takes these norms, not per-axis absolute errors). The
norms and the angle do not depend on the frames, so they compare directly
with the benchmark's figures in its z-up / FLU frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..equations.dynamics import rates, rk4_step, rotation_matrix
from .attitudeloop import AttitudeLoop
from .flightlog import rotation_vector
from ..params import DT, QuadParams

#: Horizons of the table, in 10 ms steps.
HORIZONS = (1, 10, 50)
QUANTITIES = ("position", "velocity", "rotation", "angular_velocity")
#: The goal at h=50 in each column (m, m/s, rad, rad/s): below every model the benchmark published.
GOAL_H50 = {"position": 0.07, "velocity": 0.40, "rotation": 0.15, "angular_velocity": 0.40}


def goal_score(errors: dict) -> float:
    """Mean over the four columns of the h=50 error over its goal (:data:`GOAL_H50`; 1 = the goal, lower is better).

    ``errors``: ``{"position": [..., h50], ...}`` (:meth:`PredictionErrors.to_dict`)."""
    return float(np.mean([errors[q][-1] / g for q, g in GOAL_H50.items()]))


@dataclass(frozen=True)
class PredictionErrors:
    """Mean errors at each horizon of :data:`HORIZONS` (SI units), and how many windows each mean has."""

    position: tuple[float, ...]           # m
    velocity: tuple[float, ...]           # m/s
    rotation: tuple[float, ...]           # rad
    angular_velocity: tuple[float, ...]   # rad/s
    windows: tuple[int, ...]

    def to_dict(self) -> dict:
        """``{"position": [h1, h10, h50], ...}`` (the ``realdata.json`` layout)."""
        return {q: [float(v) for v in getattr(self, q)] for q in QUANTITIES}


def rotation_angle(e_pred: np.ndarray, e_true: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation between two attitudes given as ZYX Euler angles (..., 3)."""
    Rp = rotation_matrix(e_pred[..., 0], e_pred[..., 1], e_pred[..., 2])
    Rt = rotation_matrix(e_true[..., 0], e_true[..., 1], e_true[..., 2])
    return np.linalg.norm(rotation_vector(np.swapaxes(Rp, -1, -2) @ Rt), axis=-1)


def prediction_errors(step, flights, horizons=HORIZONS, batch: int = 4096, start=None,
                      stride: int = 1) -> PredictionErrors:
    """Mean open-loop errors of ``step`` on ``flights`` at ``horizons`` (all windows of all flights pooled).

    Parameters
    ----------
    step : callable
        ``step(x (B, 12), u (B, 4)) -> x_next (B, 12)``: one 10 ms prediction, batched.
    flights : sequence
        Objects with ``x`` (n, 12), ``u`` (n, 4), ``x_ok`` (n,) bool (imported flights,
        :class:`sim.flightlogs.flightlog.Flight`).
    horizons : tuple of int
        Steps ahead at which errors are taken (the longest sets the window).
    start : callable, optional
        ``start(flight, idx) -> (B, 12 + E)``: the model's state at the window starts ``idx`` for a model with
        extra states (a register of past periods); default: the logged state ``x[idx]``. Errors use the first 12.
    stride : int
        Keep every ``stride``-th window start (1: all, the protocol; more: a cheaper estimate).
    """
    H = max(horizons)
    sums = {q: np.zeros(len(horizons)) for q in QUANTITIES}
    counts = np.zeros(len(horizons), dtype=np.int64)
    for f in flights:
        x, u, ok = np.asarray(f.x), np.asarray(f.u), np.asarray(f.x_ok)
        starts = np.flatnonzero(ok[: len(x) - H])[::stride]
        for b in range(0, len(starts), batch):
            i = starts[b:b + batch]
            xp = x[i].copy() if start is None else np.asarray(start(f, i), dtype=float)
            for k in range(1, H + 1):
                xp = step(xp, u[i + k - 1])
                if k in horizons:
                    j = horizons.index(k)
                    keep = ok[i + k]
                    xt = x[i + k][keep]
                    xk = xp[keep]
                    sums["position"][j] += np.linalg.norm(xk[:, 0:3] - xt[:, 0:3], axis=1).sum()
                    sums["velocity"][j] += np.linalg.norm(xk[:, 9:12] - xt[:, 9:12], axis=1).sum()
                    sums["rotation"][j] += rotation_angle(xk[:, 3:6], xt[:, 3:6]).sum()
                    sums["angular_velocity"][j] += np.linalg.norm(xk[:, 6:9] - xt[:, 6:9], axis=1).sum()
                    counts[j] += int(keep.sum())
    means = {q: tuple(float(s) for s in sums[q] / np.maximum(counts, 1)) for q in QUANTITIES}
    return PredictionErrors(**means, windows=tuple(int(c) for c in counts))


def _body_drag(x, k, c, b) -> np.ndarray:
    """World-frame acceleration (B, 3) of the body-frame terms ``-k v - c v |v| + b`` at states ``x`` (B, 12)."""
    R = rotation_matrix(x[:, 3], x[:, 4], x[:, 5])
    vb = np.einsum("nji,nj->ni", R, x[:, 9:12])
    return np.einsum("nij,nj->ni", R, -k * vb - c * vb * np.abs(vb) + b)


def physics_step(p: QuadParams, hold_rates: bool = False, linear_drag=(0.0, 0.0, 0.0),
                 quadratic_drag=(0.0, 0.0, 0.0), accel_bias=(0.0, 0.0, 0.0), wrench_gain=(1.0, 1.0, 1.0, 1.0),
                 substeps: int = 10, attitude_loop: AttitudeLoop | None = None):
    """A batched one-step predictor of the rigid-body equations with parameters ``p``.

    ``wrench_gain`` multiplies the logged wrench ``u`` (computed from the rotor speeds with the vehicle file's
    ``kt`` and ``kq``) before it enters the equations: an identified ``kt`` gives ``kt_identified / kt_stated`` for
    the thrust and the roll and pitch torques.

    ``hold_rates`` keeps the body rates constant (the angular acceleration set to zero, as the benchmark's Physics
    model does). In the body frame, per axis, ``-linear_drag * v - quadratic_drag * v |v| + accel_bias`` (1/s,
    1/m, m/s^2) is added to the acceleration. RK4 with ``substeps`` substeps over the 10 ms period.

    ``attitude_loop`` replaces Euler's equations (and ``hold_rates``) by the onboard attitude loop's model
    (:class:`sim.flightlogs.attitudeloop.AttitudeLoop`); the states are then (B, 16), the window starts
    ``attitude_loop.start(x)``, and the loop is given the (scaled) logged torques and the inertias of ``p``.
    """
    k, c, b = (np.asarray(a, dtype=float) for a in (linear_drag, quadratic_drag, accel_bias))
    gain = np.asarray(wrench_gain, dtype=float)
    scaled = bool(np.any(gain != 1.0))
    extra = bool(np.any(k) or np.any(c) or np.any(b))
    inertia = np.array([p.Jxx, p.Jyy, p.Jzz])

    def f(x, u):
        if attitude_loop is not None:
            d = np.zeros_like(x)
            body = x[:, :12]
            d[:, :12] = rates(body, u, p, accel=_body_drag(body, k, c, b) if extra else None)
            d[:, 6:9] = attitude_loop.angular_acceleration(x, u[:, 1:4], inertia)
            return d
        d = rates(x, u, p, accel=_body_drag(x, k, c, b) if extra else None)
        if hold_rates:
            d[:, 6:9] = 0.0
        return d

    def step(x, u):
        if scaled:
            u = u * gain
        return rk4_step(lambda z: f(z, u), x, DT / substeps, substeps)

    return step


# ------------------------------------------------------------------ the ctbr level: thrust and body rates as inputs
def ctbr_inputs(flight) -> np.ndarray:
    """The inputs (n, 4) of ``flight`` at the ``ctbr`` level: the logged (delay-aligned) collective thrust, N, and
    the body rates the onboard loop achieved by the end of each period (the next sample's), rad/s.

    A log holds no rate setpoint, so the achieved rates stand for the command: a model at this level is asked how
    the vehicle moves given the rates it reached, which is not the benchmark's question (its models are given the
    rotor speeds and must predict the rates too). The last row repeats the last rates.
    """
    x, u = np.asarray(flight.x, dtype=float), np.asarray(flight.u, dtype=float)
    out = np.empty((len(x), 4))
    out[:, 0] = u[:, 0]
    out[:-1, 1:] = x[1:, 6:9]
    out[-1, 1:] = x[-1, 6:9]
    return out


def ctbr_physics_step(p: QuadParams, linear_drag=(0.0, 0.0, 0.0), quadratic_drag=(0.0, 0.0, 0.0),
                      accel_bias=(0.0, 0.0, 0.0), thrust_gain: float = 1.0, substeps: int = 10):
    """A batched one-step predictor at the ``ctbr`` level: ``step(x (B, 12), u (B, 4)) -> x_next (B, 12)``.

    ``u`` is the collective thrust (N, the logged one, scaled by ``thrust_gain``) and the body rates reached at the
    period's end (rad/s): within the period the rates move from the state's to the input's at a constant angular
    acceleration, so the next state's rates are the input's exactly, and the attitude integrates that path. The
    translational equations are those of :func:`physics_step` (mass and gravity of ``p``, its world-frame drag
    ``p.c_d``, and the body-frame drags and bias). RK4 with ``substeps`` substeps over the 10 ms period.
    """
    k, c, b = (np.asarray(a, dtype=float) for a in (linear_drag, quadratic_drag, accel_bias))
    extra = bool(np.any(k) or np.any(c) or np.any(b))

    def step(x, u):
        u = np.asarray(u, dtype=float)
        alpha = (u[:, 1:4] - x[:, 6:9]) / DT
        thrust = np.zeros_like(u)
        thrust[:, 0] = thrust_gain * u[:, 0]

        def f(z):
            d = rates(z, thrust, p, accel=_body_drag(z, k, c, b) if extra else None)
            d[:, 6:9] = alpha
            return d

        return rk4_step(f, x, DT / substeps, substeps)

    return step
