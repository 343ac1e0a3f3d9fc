"""LQR about hover (DESIGN section 9): baseline controller, MPC terminal cost, fallback.

The hover linearization comes from a prediction model (the analytic one
unless another is given: exact derivatives of one RK4 control period); the gain and the Riccati solution from
python-control's ``dlqr``. The applied input is projected onto the
rotor-feasible wrench set (allocation, per-rotor clipping, realized wrench),
so every input the controller returns can be flown.
"""

from __future__ import annotations

import numpy as np

from sim.params import NU, NX, QuadParams
from sim.rotors import realize

from .controller import ControlInfo, Reference, Timer, check_state, hover_reference
from .errors import ConfigurationError
from .models import AnalyticModel, PredictionModel

#: Default weights as 1 / (acceptable deviation)^2: position 0.1 m, roll/pitch 0.2 rad,
#: yaw 0.3 rad, body rates 1 rad/s, velocity 0.5 m/s; thrust 0.2 m g, torques 2e-3 N m.
DEFAULT_STATE_SCALE = np.array([0.1, 0.1, 0.1, 0.2, 0.2, 0.3, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
DEFAULT_INPUT_SCALE_FRAC_T = 0.2
DEFAULT_TORQUE_SCALE = 2e-3


def default_weights(p: QuadParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal state and input weights ``Q`` (12, 12), ``R`` (4, 4)."""
    p = QuadParams() if p is None else p
    Q = np.diag(1.0 / DEFAULT_STATE_SCALE ** 2)
    R = np.diag(1.0 / np.array([DEFAULT_INPUT_SCALE_FRAC_T * p.m * p.g] + [DEFAULT_TORQUE_SCALE] * 3) ** 2)
    return Q, R


def hover_point(p: QuadParams | None = None, position=(0.0, 0.0, -1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Hover state (12,) at ``position`` and hover input (4,) = (m g, 0, 0, 0)."""
    p = QuadParams() if p is None else p
    x = np.zeros(NX)
    x[0:3] = position
    return x, np.array([p.m * p.g, 0.0, 0.0, 0.0])


def hover_linearization(model: PredictionModel | None = None, p: QuadParams | None = None):
    """Discrete ``(A (12, 12), B (12, 4))`` of one control period at hover."""
    model = AnalyticModel(p) if model is None else model
    x, u = hover_point(p)
    _, A, B = model.linearize(x, u)
    return A[0], B[0]


def _check_weights(Q, R):
    Q, R = np.asarray(Q, dtype=float), np.asarray(R, dtype=float)
    if Q.shape != (NX, NX):
        raise ConfigurationError(f"Q must have shape (12, 12); found {Q.shape}")
    if R.shape != (NU, NU):
        raise ConfigurationError(f"R must have shape (4, 4); found {R.shape}")
    if not np.allclose(Q, Q.T) or np.min(np.linalg.eigvalsh(Q)) < 0:
        raise ConfigurationError("Q must be symmetric positive semidefinite")
    if not np.allclose(R, R.T) or np.min(np.linalg.eigvalsh(R)) <= 0:
        raise ConfigurationError("R must be symmetric positive definite")
    return Q, R


def lqr(A, B, Q, R) -> tuple[np.ndarray, np.ndarray]:
    """Gain ``K`` (4, 12) and Riccati solution ``P`` (12, 12) from ``control.dlqr``.

    The control law is ``u = u_hover - K (x - x_ref)``.
    """
    import control

    Q, R = _check_weights(Q, R)
    try:
        K, P, _ = control.dlqr(A, B, Q, R)
    except Exception as e:  # python-control raises several types for a non-stabilizable pair
        raise ConfigurationError(f"no LQR gain for this hover linearization (control.dlqr: {e})") from e
    return np.asarray(K), np.asarray(P)


class LQRController:
    """Hover LQR on the analytic model, input projected onto the rotor-feasible set.

    Parameters
    ----------
    reference : callable, optional
        ``reference(times) -> (K, 12)`` desired states; hover at 1 m when omitted.
    p : QuadParams, optional
        Parameters of the analytic model (reference values when omitted).
    Q, R : array_like, optional
        Weights (:func:`default_weights` when omitted).
    model : PredictionModel, optional
        Model whose hover linearization gives the gain (the analytic model
        with ``p`` when omitted). The MPCs pass their own prediction model, so
        a PINN-based controller never uses the true equations.
    """

    def __init__(self, reference: Reference | None = None, p: QuadParams | None = None, Q=None, R=None,
                 model: PredictionModel | None = None):
        self.p = QuadParams() if p is None else p
        if model is not None and not isinstance(model, PredictionModel):
            raise ConfigurationError(f"model must be a PredictionModel; found {type(model).__name__}")
        Qd, Rd = default_weights(self.p)
        self.Q, self.R = _check_weights(Qd if Q is None else Q, Rd if R is None else R)
        self.A, self.B = hover_linearization(AnalyticModel(self.p) if model is None else model, self.p)
        if not (np.all(np.isfinite(self.A)) and np.all(np.isfinite(self.B))):
            raise ConfigurationError("the model's hover linearization is not finite; cannot compute an LQR gain")
        self.K, self.P = lqr(self.A, self.B, self.Q, self.R)
        self.u_hover = hover_point(self.p)[1]
        self.reference = hover_reference() if reference is None else reference

    def input(self, x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
        """Feasible input (4,) for state ``x`` and desired state ``x_ref`` (no checks; used as fallback)."""
        u = self.u_hover - self.K @ (x - x_ref)
        return realize(u, self.p).wrench

    def __call__(self, x, t: float):
        """Input (4,) and :class:`ControlInfo` for the measured state ``x`` at time ``t`` (s)."""
        x = check_state(x)
        with Timer() as tm:
            u = self.input(x, self.reference(np.array([t]))[0])
        return u, ControlInfo(solve_time_s=tm.elapsed, status="lqr")
