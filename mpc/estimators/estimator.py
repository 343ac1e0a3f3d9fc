"""State estimation for any contract model: an extended Kalman filter with disturbance states.

The controllers of a flight computer see an estimate, not the state. This
filter estimates, once per control period, from motion capture and the IMU
(:mod:`sim.plants.sensors`)::

    z = (x, d, b)      x: the model's state (12 rigid-body states and any extra states it declares)
                       d: a disturbance (6,): an acceleration (3, m/s^2, world NED) and an angular
                          acceleration (3, rad/s^2, body FRD), constant over a period; the angular
                          part only at the wrench level (zero at ctbr and ctatt, where the onboard
                          loop rejects torques)
                       b: the gyroscope's bias (3, rad/s) and the accelerometer's (3, m/s^2)

**Prediction** is the model itself, with the input that was in effect
during the period (what the actuators received)::

    x+ = f(x, u) + G(eta) d,     d+ = d + w_d,     b+ = b + w_b

``G`` adds the disturbance as the rigid body feels it over one period
(velocity ``dt a``, position ``dt^2 a / 2``, body rates ``dt alpha``, Euler
angles ``dt^2 W(eta) alpha / 2``); ``d`` and ``b`` are random walks. The
covariance is propagated with the model's own Jacobians, the ones the MPCs
use (:meth:`mpc.prediction.models.PredictionModel.linearize`).

**Update** with every motion-capture sample that arrived in the period, each
at its own age ``tau`` (its latency plus the time since it was taken): the
sample is compared with the estimate carried back by ``tau`` (a second-order
Taylor step with the period's mean acceleration); and with the period's mean
gyroscope reading, against the body rates at the readings' mean age plus
the bias; and with the period's mean accelerometer reading, turned to the
world frame and less gravity and the model's own mean acceleration over the
period: what is left is the disturbance's acceleration plus the
accelerometer's bias, measured directly (the way a force observer works).
Motion capture tells the two apart: a disturbance moves the vehicle, a bias
does not.

The disturbance estimate is what makes a controller offset-free: a constant
force the model lacks (payload, steady wind, a learned model's bias) is
estimated, and the controllers add it to their prediction and their
steady-state target.

The filter's process noise (:class:`EKFConfig`) is tuned once for the
default sensors and documented in ``docs/estimation.md``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from sim.equations.dynamics import rotation_matrix
from sim.params import DT, GRAVITY, NX
from sim.plants.sensors import wrap_angle as wrap

from ..errors import ConfigurationError, EstimatorError
from ..controllers.offset_free import disturbance_matrix, euler_rate_matrix

#: Lengths of the disturbance and bias parts of the filter's state.
ND, NB = 6, 3
#: Offsets of the gyroscope and accelerometer biases after the model's state and the disturbance.
GB, AB = ND, ND + NB


@dataclass(frozen=True)
class EKFConfig:
    """The filter's tuning: process noise per period and the spread of its first estimate.

    The model-error terms are standard deviations per control period; the
    disturbance's are random-walk intensities per sqrt(s). Extra states get
    ``extra_rel`` of their scale (:func:`mpc.prediction.extended.extra_scale`) per period.

    The model-error terms say how far one period of a learned model may be
    off, beyond what the disturbance states take (a force and a torque held
    over the period): a learned model's error changes along a flight, and a
    filter that believed its prediction exactly would follow the model
    instead of the sensors (on the zoo's marginal models it crashed every
    flight). The attitude term also lets a model whose attitude kinematics
    are slightly off (it needs a small body rate to hold a level attitude)
    settle at once instead of through the slow gyroscope-bias estimate.
    With the model-error terms and the disturbance walks at zero the filter
    is consistent on the plant its model is exact for (a test measures it).
    """

    position: float = 1e-4          # m per period
    attitude: float = 1e-4          # rad per period
    rate: float = 3e-2              # rad/s per period
    velocity: float = 3e-3          # m/s per period
    extra_rel: float = 0.0          # of each extra state's scale, per period
    force_walk: float = 0.5         # m/s^2 per sqrt(s)
    torque_walk: float = 5.0        # rad/s^2 per sqrt(s)
    # First estimate: position and attitude from the first motion-capture sample, rates from the gyroscope,
    # velocity from the guess (the reference at take-off) or zero.
    init_velocity: float = 0.3      # m/s
    init_rate: float = 0.05         # rad/s (besides the gyro bias)
    init_force: float = 2.0         # m/s^2
    init_torque: float = 5.0        # rad/s^2
    accelerometer: bool = True      # use the accelerometer (the disturbance's acceleration, directly)

    def __post_init__(self):
        for name, value in self.__dict__.items():
            if not (np.isfinite(value) and value >= 0.0):
                raise ConfigurationError(f"EKFConfig.{name} must be a finite number >= 0; found {value!r}")


@dataclass
class Estimate:
    """The filter's output at one period boundary (units in :mod:`mpc.estimators.estimator`'s docstring)."""

    x: np.ndarray               # (nx,) the model's state
    disturbance: np.ndarray     # (6,) acceleration (m/s^2, NED) and angular acceleration (rad/s^2, body)
    gyro_bias: np.ndarray       # (3,) rad/s
    accel_bias: np.ndarray      # (3,) m/s^2
    P: np.ndarray               # (nx + 12, nx + 12) covariance of (x, d, gyro bias, accelerometer bias)
    solve_time_s: float = 0.0
    measurements: int = 0       # scalar measurements used in this update

    @property
    def std(self) -> np.ndarray:
        """Standard deviations (nx + 12,) of the estimate."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))


@dataclass
class DisturbanceEKF:
    """Extended Kalman filter on a prediction model, with disturbance and gyroscope-bias states.

    Parameters
    ----------
    model : PredictionModel
        The controllers' model (its extra states are estimated too).
    mocap : sim.plants.sensors.MocapConfig or None
        The motion-capture system's noise (a datasheet's); None: not fitted.
    imu : sim.plants.sensors.ImuConfig or None
        The IMU's noise and bias drift; None: no gyroscope.
    config : EKFConfig
    g : float
        Gravity, m/s^2 (what the accelerometer reads at rest).
    extra_start : callable, optional
        ``extra_start(x (12,)) -> e (n_extra,)``: the first estimate of the
        extra states (needed for a model that has them; a controller's
        ``lqr.start_extra`` gives the model's own).
    """

    model: object
    mocap: object = None
    imu: object = None
    config: EKFConfig = field(default_factory=EKFConfig)
    extra_start: object = None
    g: float = GRAVITY

    def __post_init__(self):
        if self.mocap is None:
            raise ConfigurationError("the estimator needs motion capture (position and attitude); mocap is None")
        nx = self.model.nx
        self.nx, self.nz = nx, nx + ND + 2 * NB
        #: Whether the angular part of the disturbance is estimated: only at the wrench level. At ``ctbr`` and
        #: ``ctatt`` the onboard loop closes the body rates with integral action, so a torque held on the airframe
        #: leaves no lasting rate error for the model to carry; what the rates' channel would absorb instead is the
        #: inner loop's transient lag, which changes with every command and, fed back as an offset, drives the
        #: loop (a model whose rates follow the command at once crashed the logged melon flight through it).
        self.angular = self.model.level == "wrench"
        c = self.config
        q = np.zeros(self.nz)
        q[0:3], q[3:6], q[6:9], q[9:12] = c.position, c.attitude, c.rate, c.velocity
        if self.model.n_extra:
            q[NX:nx] = c.extra_rel * self._extra_scale()
        q[nx:nx + 3] = c.force_walk * np.sqrt(DT)
        q[nx + 3:nx + 6] = c.torque_walk * np.sqrt(DT) if self.angular else 0.0
        q[nx + GB:nx + GB + NB] = 0.0 if self.imu is None else self.imu.gyro_bias_walk * np.sqrt(DT)
        q[nx + AB:] = 0.0 if self.imu is None else self.imu.accel_bias_walk * np.sqrt(DT)
        self.Q = np.diag(q ** 2)
        self.reset()

    def _extra_scale(self) -> np.ndarray:
        from ..prediction.extended import extra_scale
        return extra_scale(self.model, self._extra_at(self._hover_state()))

    @staticmethod
    def _hover_state() -> np.ndarray:
        from ..references.feedforward import HOVER_STATE
        return HOVER_STATE.copy()

    def _extra_at(self, x12: np.ndarray) -> np.ndarray:
        if self.extra_start is None:
            raise ConfigurationError(f"model {getattr(self.model, 'name', '?')!r} has extra states "
                                     f"{self.model.extra_names}: the estimator needs extra_start(x) for their "
                                     f"first estimate")
        return np.asarray(self.extra_start(x12), dtype=float).reshape(-1)

    def reset(self) -> None:
        """Forget the flight: the next :meth:`step` starts a new estimate from its readings."""
        self.z: np.ndarray | None = None
        self.P: np.ndarray | None = None
        self._x_prev: np.ndarray | None = None

    # -- the filter ------------------------------------------------------------------------------------------

    def _G(self, eta: np.ndarray) -> np.ndarray:
        return disturbance_matrix(eta, self.nx)

    def _start(self, r, guess=None) -> None:
        c, nx = self.config, self.nx
        x = self._hover_state() if guess is None else np.array(guess[:NX], dtype=float)
        x[0:6] = r.mocap[-1]
        if len(r.gyro):
            x[6:9] = r.gyro.mean(axis=0)
        z = np.zeros(self.nz)
        z[:NX] = x
        if self.model.n_extra:
            z[NX:nx] = self._extra_at(x)
        p = np.zeros(self.nz)
        p[0:3] = max(self.mocap.position_std, 1e-6)
        p[3:6] = max(self.mocap.attitude_std, 1e-6)
        gyro_std = 0.0 if self.imu is None else np.hypot(self.imu.gyro_std, self.imu.gyro_bias_std)
        p[6:9] = np.hypot(c.init_rate, gyro_std)
        p[9:12] = c.init_velocity
        if self.model.n_extra:
            p[NX:nx] = self._extra_scale()
        p[nx:nx + 3], p[nx + 3:nx + 6] = c.init_force, (c.init_torque if self.angular else 0.0)
        p[nx + GB:nx + GB + NB] = 0.0 if self.imu is None else max(self.imu.gyro_bias_std, 1e-6)
        p[nx + AB:] = 0.0 if self.imu is None else max(self.imu.accel_bias_std, 1e-6)
        self.z, self.P = z, np.diag(p ** 2)
        self._x_prev = z[:nx].copy()

    def _predict(self, u: np.ndarray) -> None:
        nx = self.nx
        x, d = self.z[:nx], self.z[nx:nx + ND]
        xn, A, B = self.model.linearize(x[None], np.asarray(u, dtype=float)[None])
        G = self._G(x[3:6])
        F = np.eye(self.nz)
        F[:nx, :nx] = A[0]
        F[:nx, nx:nx + ND] = G
        self._x_prev = x.copy()
        self._a_model = (xn[0, 9:12] - x[9:12]) / DT     # the model's mean acceleration, without the disturbance
        z = self.z.copy()
        z[:nx] = xn[0] + G @ d
        self.z = z
        self.P = F @ self.P @ F.T + self.Q

    def _update(self, r, t: float) -> int:
        nx, z = self.nx, self.z
        x, xp = z[:nx], self._x_prev
        rows, res, var = [], [], []
        # Mean accelerations over the last period (known numbers in the linearization).
        acc = (x[9:12] - xp[9:12]) / DT
        W, Wp = euler_rate_matrix(x[3:6]), euler_rate_matrix(xp[3:6])
        eta_dot = W @ x[6:9]
        eta_acc = (eta_dot - Wp @ xp[6:9]) / DT
        for ts, m in zip(r.mocap_t, r.mocap):
            tau = max(t - ts, 0.0)
            Hp = np.zeros((3, self.nz))
            Hp[:, 0:3] = np.eye(3)
            Hp[:, 9:12] = -tau * np.eye(3)
            pred_p = x[0:3] - tau * x[9:12] + 0.5 * tau * tau * acc
            He = np.zeros((3, self.nz))
            He[:, 3:6] = np.eye(3)
            He[:, 6:9] = -tau * W
            pred_e = x[3:6] - tau * eta_dot + 0.5 * tau * tau * eta_acc
            rows += [Hp, He]
            res += [m[0:3] - pred_p, wrap(m[3:6] - pred_e)]
            var += [np.full(3, self.mocap.position_std ** 2), np.full(3, self.mocap.attitude_std ** 2)]
        if self.imu is not None and len(r.gyro):
            tau = max(t - float(np.mean(r.imu_t)), 0.0)
            rate_acc = (x[6:9] - xp[6:9]) / DT
            Hg = np.zeros((3, self.nz))
            Hg[:, 6:9] = np.eye(3)
            Hg[:, nx + GB:nx + GB + NB] = np.eye(3)
            pred = x[6:9] - tau * rate_acc + z[nx + GB:nx + GB + NB]
            rows.append(Hg)
            res.append(r.gyro.mean(axis=0) - pred)
            var.append(np.full(3, self.imu.gyro_std ** 2 / len(r.gyro)))
        if self.imu is not None and self.config.accelerometer and len(r.accel):
            # The period's mean specific force, turned to the world frame at the period's middle attitude, plus
            # gravity, less the model's own mean acceleration: the disturbance's acceleration plus the bias.
            Rm = rotation_matrix(*(0.5 * (x[3:6] + xp[3:6])))
            y = Rm @ r.accel.mean(axis=0) + np.array([0.0, 0.0, self.g]) - self._a_model
            Ha = np.zeros((3, self.nz))
            Ha[:, nx:nx + 3] = np.eye(3)
            Ha[:, nx + AB:] = Rm
            rows.append(Ha)
            res.append(y - (z[nx:nx + 3] + Rm @ z[nx + AB:]))
            var.append(np.full(3, self.imu.accel_std ** 2 / len(r.accel)))
        if not rows:
            return 0
        H, y = np.vstack(rows), np.concatenate(res)
        Rm = np.diag(np.maximum(np.concatenate(var), 1e-18))
        PHt = self.P @ H.T
        S = H @ PHt + Rm
        K = np.linalg.solve(S, PHt.T).T
        self.z = z + K @ y
        I_KH = np.eye(self.nz) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ Rm @ K.T      # Joseph form: stays symmetric and positive
        self.P = 0.5 * (self.P + self.P.T)
        return len(y)

    def step(self, readings, t: float, u_applied=None, guess=None) -> Estimate:
        """The estimate at time ``t`` (s) from the readings that arrived since the last call.

        Parameters
        ----------
        readings : sim.plants.sensors.Readings
        t : float
            The period boundary, s.
        u_applied : ndarray (4,), optional
            The input in effect during the period just flown (N, N m); None
            at the first call.
        guess : ndarray (12,), optional
            At the first call, where the vehicle is meant to be (the
            reference at take-off): its velocity starts the estimate (a flight
            that starts at speed); position and attitude come from motion
            capture, the body rates from the gyroscope, whatever the guess.
        """
        c0 = time.perf_counter()
        n = 0
        if self.z is None:
            if len(readings.mocap) == 0:
                raise ConfigurationError(f"the estimator has no motion-capture sample at t = {t:g} s to start "
                                         f"from (latency longer than the first period?)")
            self._start(readings, guess)
        else:
            if u_applied is None:
                raise ConfigurationError("u_applied is needed after the first call: the input of the last period")
            self._predict(u_applied)
            if not np.all(np.isfinite(self.z)):
                raise EstimatorError(f"the filter's prediction through the model is not finite at t = {t:g} s")
            n = self._update(readings, t)
            if not (np.all(np.isfinite(self.z)) and np.all(np.isfinite(self.P))):
                raise EstimatorError(f"the filter's update is not finite at t = {t:g} s")
        nx = self.nx
        return Estimate(x=self.z[:nx].copy(), disturbance=self.z[nx:nx + ND].copy(),
                        gyro_bias=self.z[nx + GB:nx + GB + NB].copy(), accel_bias=self.z[nx + AB:].copy(),
                        P=self.P.copy(),
                        solve_time_s=time.perf_counter() - c0, measurements=n)


__all__ = ["DisturbanceEKF", "EKFConfig", "Estimate", "euler_rate_matrix"]
