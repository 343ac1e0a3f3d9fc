"""LQR about hover: baseline controller, MPC terminal cost, fallback.

The hover linearization comes from a prediction model (the analytic one
unless another is given) at that model's own hover trim; the gain and the
Riccati solution from python-control's ``dlqr``. The applied input is the
model's feed-forward minus the state feedback, projected onto the
rotor-feasible wrench set of the vehicle spec (allocation, per-rotor
clipping, realized wrench), so every input the controller returns can be flown.
"""

from __future__ import annotations

import numpy as np

from sim.params import DT, NU, NX

from .controller import ControlInfo, ControllerBase, Timer, check_measured
from ..errors import ConfigurationError
from ..references.feedforward import FeedForward
from ..prediction.models import AnalyticModel, PredictionModel
from ..prediction.spec import THRUST_SCALE_FRACTION, VehicleSpec

#: Default weights as 1 / (acceptable deviation)^2: position 0.1 m, roll/pitch 0.2 rad,
#: yaw 0.3 rad, body rates 1 rad/s, velocity 0.5 m/s; thrust 0.2 m g, torques the vehicle's
#: :attr:`mpc.prediction.spec.VehicleSpec.torque_scale` (2e-3 N m for the Rolling Spider).
DEFAULT_STATE_SCALE = np.array([0.1, 0.1, 0.1, 0.2, 0.2, 0.3, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
DEFAULT_INPUT_SCALE_FRAC_T = THRUST_SCALE_FRACTION


def default_weights(spec=None, level: str = "wrench") -> tuple[np.ndarray, np.ndarray]:
    """Diagonal state and input weights ``Q`` (12, 12), ``R`` (4, 4) at command level ``level``; the thrust scale is
    0.2 m g of ``spec`` (:func:`input_scale`)."""
    spec = VehicleSpec() if spec is None else spec
    Q = np.diag(1.0 / DEFAULT_STATE_SCALE ** 2)
    R = np.diag(1.0 / input_scale(spec, level) ** 2)
    return Q, R


def input_scale(spec=None, level: str = "wrench") -> np.ndarray:
    """Acceptable input deviations (4,) at command level ``level``: thrust 0.2 m g (N), then torques the spec's
    ``torque_scale`` (N m), or the rates' and angles' of :class:`mpc.prediction.spec.InputSet`.

    ``spec``: a :class:`mpc.prediction.spec.VehicleSpec`, or (at the wrench level) any object with ``m, g, kt, d`` and
    ``n_max_sq`` (such as a :class:`sim.QuadParams`), whose torque scale is then computed as a VehicleSpec's.
    """
    import math

    from ..prediction.spec import torque_scale

    spec = VehicleSpec() if spec is None else spec
    if isinstance(spec, VehicleSpec):
        return spec.inputs(level).scale
    if level != "wrench":
        raise ConfigurationError(f"the input scales at the {level!r} level need a VehicleSpec (its largest rate and "
                                 f"tilt commands); found {type(spec).__name__}")
    ts = torque_scale(spec.kt, math.sqrt(spec.n_max_sq), spec.d)
    return np.array([DEFAULT_INPUT_SCALE_FRAC_T * spec.m * spec.g] + [ts] * 3)


def hover_point(spec=None, position=(0.0, 0.0, -1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Hover state (12,) at ``position`` and the spec's nominal hover input (4,) = (m g, 0, 0, 0).

    A convenience for building test models; the controllers use their
    model's own trim (:class:`mpc.references.feedforward.FeedForward`) instead.
    """
    spec = VehicleSpec() if spec is None else spec
    x = np.zeros(NX)
    x[0:3] = position
    return x, np.array([spec.m * spec.g, 0.0, 0.0, 0.0])


def hover_linearization(model: PredictionModel | None = None, spec=None):
    """Discrete ``(A (12, 12), B (12, 4))`` of one control period at the model's own hover trim."""
    model = AnalyticModel() if model is None else model
    spec = VehicleSpec.from_model(model) if spec is None else spec
    return FeedForward(model, None, spec, 1.0 / DEFAULT_STATE_SCALE ** 2, input_scale(spec)).hover_linearization()[1:]


def _check_weights(Q, R, nx: int = NX):
    Q, R = np.asarray(Q, dtype=float), np.asarray(R, dtype=float)
    if Q.shape != (nx, nx):
        raise ConfigurationError(f"Q must have shape ({nx}, {nx}); found {Q.shape}")
    if R.shape != (NU, NU):
        raise ConfigurationError(f"R must have shape (4, 4); found {R.shape}")
    if not np.allclose(Q, Q.T) or np.min(np.linalg.eigvalsh(Q)) < 0:
        raise ConfigurationError("Q must be symmetric positive semidefinite")
    if not np.allclose(R, R.T) or np.min(np.linalg.eigvalsh(R)) <= 0:
        raise ConfigurationError("R must be symmetric positive definite")
    return Q, R


#: A Riccati solution is accepted when its smallest eigenvalue is at least -RICCATI_PSD_TOL times its largest
#: magnitude, and the closed loop ``A - B K`` has a spectral radius below 1.
RICCATI_PSD_TOL = 1e-9


def extended_weights(Q, n_extra: int) -> np.ndarray:
    """The state weight (12 + n_extra, 12 + n_extra) of a model with extra states: ``Q`` on the rigid body, 0 on the
    extra states (they are tracked only through what they do to the rigid body, and through the terminal cost)."""
    Q = np.asarray(Q, dtype=float)
    if n_extra == 0:
        return Q
    out = np.zeros((NX + n_extra, NX + n_extra))
    out[:NX, :NX] = Q
    return out


#: Body-rate rows of A^k B below this share of its largest entry, for every k: no input turns the model.
HELD_RATES_TOL = 1e-9


def _reaches_rates(A, B) -> bool:
    """Whether some input reaches the body rates within ``nx`` periods (rows 6:9 of some ``A^k B``, k < nx).

    Through ``A`` because a model with extra states (a register of past commands) reaches them only later.
    """
    A, M = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
    for _ in range(A.shape[0]):
        scale = np.max(np.abs(M))
        if not scale > 0 or not np.isfinite(scale):
            return True        # nothing to tell (the Riccati solution's own checks speak)
        if np.max(np.abs(M[6:9])) > HELD_RATES_TOL * scale:
            return True
        M = A @ M / scale
    return False


def lqr(A, B, Q, R) -> tuple[np.ndarray, np.ndarray]:
    """Gain ``K`` (4, nx) and Riccati solution ``P`` (nx, nx) from ``control.dlqr`` (nx = 12 plus extra states).

    The control law is ``u = u_hover - K (x - x_ref)``. The solution is
    checked: for a pair that is not stabilizable (a mode the inputs cannot
    move, such as a learned model whose torques do not reach its attitude)
    ``control.dlqr`` may return a ``P`` that is not positive semidefinite
    and a closed loop that is not stable, without an error. Then, and when
    it fails outright, a :class:`ConfigurationError` says so.
    """
    import control

    Q, R = _check_weights(Q, R, np.shape(A)[0])
    if not _reaches_rates(A, B):
        raise ConfigurationError(
            "no LQR gain for this hover linearization: no input changes the body rates (the model's angular "
            "acceleration does not depend on the rotors, as in a model that holds its rates with omega-dot = 0); "
            "it cannot turn, so no controller can fly it")
    try:
        K, P, _ = control.dlqr(A, B, Q, R)
    except Exception as e:  # python-control raises several types for a non-stabilizable pair
        raise ConfigurationError(f"no LQR gain for this hover linearization (control.dlqr: {e})") from e
    K, P = np.asarray(K), np.asarray(P)
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(P))):
        raise ConfigurationError("no LQR gain for this hover linearization: the Riccati solution is not finite")
    ev = np.linalg.eigvalsh(0.5 * (P + P.T))
    rho = float(np.max(np.abs(np.linalg.eigvals(A - B @ K))))
    if ev[0] < -RICCATI_PSD_TOL * np.max(np.abs(ev)) or not rho < 1.0:
        raise ConfigurationError(
            f"no LQR gain for this hover linearization: it is not stabilizable (the Riccati solution's eigenvalues "
            f"span {ev[0]:.3g} to {ev[-1]:.3g}, the closed loop's spectral radius is {rho:.10f}); the model says "
            f"some mode at hover cannot be moved by the inputs")
    return K, P


class LQRController(ControllerBase):
    """LQR about the prediction model's own hover trim, with the model's feed-forward along the reference.

    ``u = u_ff(t) - K (x - x_ref(t))``, projected onto the rotor-feasible set
    of the vehicle spec. The gain comes from the model's hover linearization.
    For a model with extra states (:mod:`mpc.prediction.extended`) ``x`` and ``x_ref``
    include them: the controller carries them from period to period, told the
    applied input by :meth:`applied`.

    Parameters
    ----------
    reference : FlatTrajectory or callable, optional
        Flat trajectory or ``reference(times) -> (K, 12)``; hover at 1 m when omitted.
    model : PredictionModel, optional
        Prediction model (the analytic oracle when omitted). Its hover
        linearization gives the gain, its trim and feed-forward the input.
    Q, R : array_like, optional
        Weights (:func:`default_weights` of the spec when omitted).
    spec : VehicleSpec, optional
        What the controller knows (:meth:`VehicleSpec.from_model` when omitted).
    """

    def __init__(self, reference=None, model: PredictionModel | None = None, Q=None, R=None, spec=None):
        if model is not None and not isinstance(model, PredictionModel):
            raise ConfigurationError(f"model must be a PredictionModel; found {type(model).__name__}")
        self.model = AnalyticModel() if model is None else model
        self.spec = VehicleSpec.from_model(self.model) if spec is None else spec
        if not isinstance(self.spec, VehicleSpec):
            raise ConfigurationError(f"spec must be a VehicleSpec; found {type(self.spec).__name__}")
        #: What the controller may command at its model's level (:class:`mpc.prediction.spec.InputSet`).
        self.inputs = self.spec.inputs(self.model.level)
        Qd, Rd = default_weights(self.spec, self.model.level)
        Q, self.R = _check_weights(Qd if Q is None else Q, Rd if R is None else R)
        self.ff = FeedForward(self.model, reference, self.spec, np.diag(Q), self.inputs.scale)
        #: State weight over the model's whole state (the rigid body's ``Q``, zero on extra states).
        self.Q = extended_weights(Q, self.model.n_extra)
        self.u_hover, self.A, self.B = self.ff.hover_linearization()
        if not (np.all(np.isfinite(self.A)) and np.all(np.isfinite(self.B)) and np.all(np.isfinite(self.u_hover))):
            raise ConfigurationError("the model's hover linearization is not finite; cannot compute an LQR gain")
        self.K, self.P = lqr(self.A, self.B, self.Q, self.R)
        self.reference = self.ff.states
        from ..prediction.extended import ExtraStateTracker

        #: The model's extra states in flight (a no-op for a model without them).
        self.tracker = ExtraStateTracker(self.model, self.start_extra)
        self._start_memo = None     # (x, t, extra states) of the last start_extra

    def start_extra(self, x: np.ndarray, t: float = 0.0) -> np.ndarray:
        """The model's extra states (n_extra,) at the first period, at time ``t`` (s), measured state ``x`` (12,).

        A model that gives its own reference (:meth:`mpc.prediction.models.PredictionModel.reference_states`) starts
        from the
        reference's extra states at ``t`` (a vehicle that starts on its reference has its rotors at the reference's
        speeds); any other from its extra states at rest at ``x`` under the feed-forward input at ``t``.
        """
        from ..prediction.extended import extra_equilibrium

        tt = np.array([t])
        if self.ff.model_reference:
            return self.ff.full_states(tt)[0, NX:]
        # The last answer is kept (until the next prepare): the plan made before take-off and the first period's
        # tracker ask for the same start, and its Newton iteration costs milliseconds a model with history.
        x = np.array(x, dtype=float)
        memo = self._start_memo
        if memo is not None and memo[1] == t and np.array_equal(memo[0], x):
            return memo[2].copy()
        e = extra_equilibrium(self.model, x[None], self.ff.inputs(tt), self.ff.trim_extra[None])[0]
        self._start_memo = (x, t, e.copy())
        return e

    def prepare(self, t_end: float, x0=None) -> None:
        """Compute the reference and feed-forward up to ``t_end`` (s) before a flight (``x0`` is not needed)."""
        self.ff.prepare(t_end)
        self.tracker.reset()
        self._start_memo = None

    def input(self, x: np.ndarray, x_ref: np.ndarray, u_ff: np.ndarray | None = None) -> np.ndarray:
        """Feasible input (4,) for state ``x``, desired state ``x_ref`` and feed-forward ``u_ff`` (no checks)."""
        u = (self.u_hover if u_ff is None else u_ff) - self.K @ (x - x_ref)
        return self.inputs.project(u)

    def __call__(self, x, t: float):
        """Input (4,) and :class:`ControlInfo` for the measured state ``x`` at time ``t`` (s)."""
        x = check_measured(x, self.model)
        with Timer() as tm:
            z = self.tracker.full(x, t)
            X, U = self.ff.horizon(np.array([t, t + DT]))
            u = self.input(z, X[0], U[0])
        return u, ControlInfo(solve_time_s=tm.elapsed, status="lqr")
