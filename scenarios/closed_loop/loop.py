"""The closed loop on one screen: plant, sensor, controller, clock.

Each part is a small object with one job, and each can be replaced::

    plant      sim.plants.plant.Plant           advance(u, duration) -> the true state
    sensor     StateSensor               measure(x) -> what the controller sees
    estimator  Estimator (optional)      sensors and a filter: the controller sees its estimate instead
    controller a pinn-mpc controller     controller(x_measured, t) -> (u, info); applied(u_mean)
    clock      IdealClock | RealtimeClock when each computed input takes effect

Per control period ``k`` (``t = k dt``): if the controller is idle, the
sensor reads the plant, the controller is called and timed, it may then
prepare the next period (``prepare_next``, timed too), and the clock is
told when its input takes effect and how long the controller was busy;
then the clock flies the plant through the period with whatever input is
in effect, and the controller is told
the command that entered the actuators during the period (its time average,
when it changed mid-way; before any input delay, which is the plant's): a
controller whose model has actuator or history states carries them with
it; an estimator is told the input in effect (after the delay: what drove
the plant); then the crash test. The loop records everything in a :class:`Trace`.

With an :class:`Estimator` the controller never sees the state: at every
period boundary the estimator collects what the sensors delivered, and when
the controller is called the filter catches up (one prediction and update
per period since its last call) inside the timed call, so the real-time
clock charges the estimator's time too. The controller gets the estimate
(with the model's extra states) and, if it can use one, the disturbance
estimate.

In real time a controller that can keep a deadline (``set_deadline``: the
MPCs on OSQP) is told, at the start of each call, that its input must be
out :data:`DEADLINE_MARGIN_S` before the period ends; the filter's time
counts against the same deadline. A controller that sees it cannot make a
plan in time sends its fallback's input instead (status ``"deadline"``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mpc.controllers.controller import Controller
from sim.params import DT, NU, NX, SUBSTEPS
from sim.plants.plant import Plant

from .metrics import crash_reason

#: In real time, a controller's input must be out this long before the period ends, s: the time its last step
#: (after its last look at the clock) and the loop's own bookkeeping may take.
DEADLINE_MARGIN_S = 0.001
#: The control period and the plant's time resolution, ms (the resolution of real-time latencies).
PERIOD_MS = int(round(DT * 1e3))
SUBSTEP_MS = PERIOD_MS // SUBSTEPS


class Sensor(Protocol):
    """What the controller sees of the plant when no estimator runs (:class:`StateSensor`)."""

    def measure(self, x: np.ndarray) -> np.ndarray:
        """The measured state (12,) for the true state ``x`` (12,)."""


class Clock(Protocol):
    """When a computed input takes effect (:class:`IdealClock`, :class:`RealtimeClock`).

    Attributes
    ----------
    realtime : bool
        True when the controller's compute time is charged (it is then told a deadline).
    sent, in_effect : ndarray (4,)
        The command that entered the actuators, and the input in effect after any delay, over the last period.
    """

    realtime: bool
    sent: np.ndarray
    in_effect: np.ndarray

    def idle(self, k: int) -> bool:
        """True when the controller may be called at the start of period ``k``."""

    def command(self, k: int, u: np.ndarray, latency_s: float, load_s: float | None = None) -> None:
        """The input ``u`` (4,) computed at period ``k``, out after ``latency_s`` seconds of wall time; the
        controller busy for ``load_s`` s in all (its work for the next period included; None: ``latency_s``)."""

    def fly_period(self, plant, k: int) -> np.ndarray:
        """Advance ``plant`` (:class:`sim.plants.plant.Plant`) through period ``k``; the input in effect at its
        end (4,)."""


class StateEstimator(Protocol):
    """Sensors read through the plant and a filter (:class:`Estimator`), in the order the loop calls them.

    Attributes
    ----------
    ekf : mpc.estimators.estimator.DisturbanceEKF
        The filter; its ``nx`` and ``nz`` size the trace's estimate fields.
    sensors : sim.plants.sensors.SensorSuite
        The sensors; their true biases are recorded beside the estimated ones.
    """

    ekf: object
    sensors: object

    def collect(self, t: float) -> None:
        """At a period boundary ``t`` (s): take what the sensors delivered."""

    def estimate(self):
        """The estimate now (:class:`mpc.estimators.estimator.Estimate`: ``x``, ``std``, ``disturbance``, biases,
        ``P``); raises :class:`mpc.errors.EstimatorError` when the state is lost."""

    def applied(self, u: np.ndarray) -> None:
        """The input (4,) in effect during the period just flown."""


class StateSensor:
    """The full state plus white Gaussian noise (or exactly, with no noise model).

    Parameters
    ----------
    noise : sim.params.NoiseModel or None
        Standard deviations per state; None: the true state.
    rng : numpy.random.Generator
        Draws the noise (one (12,) draw per reading).
    """

    def __init__(self, noise=None, rng: np.random.Generator | None = None):
        self.noise = noise
        self._std = None if noise is None else noise.state_std
        self.rng = np.random.default_rng() if rng is None else rng

    def measure(self, x: np.ndarray) -> np.ndarray:
        """What the controller sees of the true state ``x`` (12,)."""
        if self._std is None:
            return x
        return x + self._std * self.rng.standard_normal(x.shape)


class Estimator:
    """Sensors read through the plant and a filter on the controller's model (:mod:`mpc.estimators.estimator`).

    Parameters
    ----------
    sensors : sim.plants.sensors.SensorSuite
        The suite the (sensed) plant feeds.
    ekf : mpc.estimators.estimator.DisturbanceEKF
    guess : ndarray (12,), optional
        Where the flight is meant to start (the filter's first velocity).
    """

    def __init__(self, sensors, ekf, guess=None):
        self.sensors, self.ekf, self.guess = sensors, ekf, guess
        self._queue: list = []
        self._u = None
        self.last = None

    def collect(self, t: float) -> None:
        """At a period boundary ``t`` (s): take what the sensors delivered (not timed)."""
        self._queue.append((t, self.sensors.read(t), self._u))

    def applied(self, u) -> None:
        """The input (4,) in effect during the period just flown."""
        self._u = np.array(u, dtype=float)

    def estimate(self):
        """The estimate now: the filter run through every period collected since the last call."""
        for t, r, u in self._queue:
            self.last = self.ekf.step(r, t, u, guess=self.guess)
        self._queue = []
        return self.last



def make_estimator(ctrl, model, plant, sensors, guess=None, config=None):
    """``(sensed plant, Estimator)`` of a run with the state estimator: ``plant`` read through ``sensors`` (a
    :class:`sim.plants.sensors.SensorSuite`) and an extended Kalman filter on the controller's ``model``, its
    extra states started as ``ctrl`` starts them.

    ``guess`` (12,): the reference at take-off (the filter's first velocity); ``config``: an
    :class:`mpc.estimators.estimator.EKFConfig` (None: the default tuning).
    """
    from mpc.estimators.estimator import DisturbanceEKF, EKFConfig
    from sim.plants.sensors import SensedPlant

    start = ctrl.start_extra
    ekf = DisturbanceEKF(model, sensors.mocap, sensors.imu, config=EKFConfig() if config is None else config,
                         extra_start=lambda x: start(x, 0.0), g=plant.vehicle.params.g)
    return SensedPlant(plant, sensors), Estimator(sensors, ekf, guess)

class IdealClock:
    """Each input takes effect at the start of its period (``delay_steps`` periods later with a delay).

    The controller is called every period; its compute time is not charged.
    Before the first (delayed) input arrives, ``hover`` holds the vehicle.
    """

    realtime = False

    def __init__(self, hover: np.ndarray, delay_steps: int = 0):
        self._pending = [np.asarray(hover, dtype=float)] * int(delay_steps)
        self.u = np.asarray(hover, dtype=float)
        #: The command that entered the actuators in the last period flown (before the plant's delay).
        self.sent = self.u
        #: The input in effect (after the delay) over the last period flown.
        self.in_effect = self.u

    def idle(self, k: int) -> bool:
        return True

    def command(self, k: int, u: np.ndarray, latency_s: float, load_s: float | None = None) -> None:
        self._pending.append(u)
        self.u = self._pending.pop(0)
        self.sent = u

    def fly_period(self, plant, k: int) -> np.ndarray:
        """Advance the plant through period ``k``; the input in effect at its end."""
        plant.advance(self.u, DT)
        self.in_effect = self.u
        return self.u


def _whole_ms(seconds: float) -> int:
    """``seconds`` of wall time rounded up to the plant's resolution (whole ms, at least one), ms."""
    return max(SUBSTEP_MS, int(np.ceil(seconds * 1e3 / SUBSTEP_MS - 1e-9)) * SUBSTEP_MS)


class RealtimeClock:
    """When each computed input takes effect under real-time timing.

    The controller is called at a period boundary ``k dt`` only when it is
    idle. A call that took ``L`` seconds of wall time returns ``ceil(L / 1 ms)``
    ms later; its input takes effect from then on (plus the delay periods).
    The controller is idle again once the work that followed (the real-time
    iteration's preparation of the next period) is done too, its whole load
    rounded up the same way. Until then the previous input stays applied
    (before the first one, ``hover``). A period whose input changes mid-way is
    flown in pieces of whole milliseconds.
    """

    realtime = True

    def __init__(self, hover: np.ndarray, delay_steps: int = 0):
        self.delay_ms = PERIOD_MS * int(delay_steps)
        self.u = np.asarray(hover, dtype=float)
        self.events: list[tuple[int, np.ndarray]] = []    # (time the input takes effect, ms; input)
        self.busy_until_ms = 0
        self._sent_now = self.u                            # the command at the actuators' input (before the delay)
        self._sent_events: list[tuple[int, np.ndarray]] = []
        #: Time average of the command that entered the actuators in the last period flown (before the delay).
        self.sent = self.u
        #: Time average of the input in effect (after the delay) over the last period flown.
        self.in_effect = self.u

    def idle(self, k: int) -> bool:
        return self.busy_until_ms <= PERIOD_MS * k

    def command(self, k: int, u: np.ndarray, latency_s: float, load_s: float | None = None) -> None:
        out_ms = PERIOD_MS * k + _whole_ms(latency_s)
        self.busy_until_ms = max(out_ms, PERIOD_MS * k + _whole_ms(latency_s if load_s is None else load_s))
        self.events.append((out_ms + self.delay_ms, np.array(u, dtype=float)))
        self._sent_events.append((out_ms, np.array(u, dtype=float)))

    def fly_period(self, plant, k: int) -> np.ndarray:
        """Advance the plant through period ``k`` in pieces; the input in effect at its end."""
        now, t1 = PERIOD_MS * k, PERIOD_MS * (k + 1)
        effect = np.zeros_like(self.u)
        while now < t1:
            while self.events and self.events[0][0] <= now:
                self.u = self.events.pop(0)[1]
            nxt = t1 if not self.events else min(t1, self.events[0][0])
            plant.advance(self.u, (nxt - now) * 1e-3)
            effect += (nxt - now) * self.u
            now = nxt
        self.in_effect = effect / PERIOD_MS
        # The command at the actuators' input over the same period, before the delay, averaged over time.
        now, total = PERIOD_MS * k, np.zeros_like(self.u)
        while now < t1:
            while self._sent_events and self._sent_events[0][0] <= now:
                self._sent_now = self._sent_events.pop(0)[1]
            nxt = t1 if not self._sent_events else min(t1, self._sent_events[0][0])
            total += (nxt - now) * self._sent_now
            now = nxt
        self.sent = total / PERIOD_MS
        return self.u


@dataclass
class Trace:
    """Arrays of one flight (K planned periods; units in comments)."""

    x: np.ndarray             # (K + 1, 12) true states
    x_measured: np.ndarray    # (K, 12) what the controller saw (NaN where it was not called)
    u: np.ndarray             # (K, 4) input in effect at the end of each period
    u_command: np.ndarray     # (K, 4) the controller's output (NaN where it was not called)
    solve_s: np.ndarray       # (K,) the controller's own solve time (and its preparation of the next period), s
    latency_s: np.ndarray     # (K,) wall time of the call, s: from the measurement to the input out (NaN where not
    #                           called)
    load_s: np.ndarray        # (K,) wall time of the period's work: the call and what followed it, s (NaN where not
    #                           called)
    called: np.ndarray        # (K,) bool: the controller was called this period
    iterations: np.ndarray    # (K,)
    status: np.ndarray        # (K,) the controller's status string
    solver_failed: np.ndarray  # (K,) bool: a fallback produced the input
    lqr_fallback: np.ndarray  # (K,) bool: the LQR fallback produced it
    rotor_speed: np.ndarray | None = None     # (K + 1, 4) the plant's rotor speeds at each period boundary, RU
    load_cpu_s: np.ndarray | None = None      # (K,) load_s's span on the controller thread's CPU clock, s: its own
    #                                           work, not the time the machine gave the core away (NaN where not called)
    steps: int = 0            # periods flown
    # With an estimator (else None): its output where the controller was called (NaN elsewhere).
    x_estimate: np.ndarray | None = None      # (K, nx) the model's state as estimated
    estimate_std: np.ndarray | None = None    # (K, nx + 12) standard deviations of (x, d, gyro and accel. biases)
    disturbance: np.ndarray | None = None     # (K, 6) m/s^2 (NED) and rad/s^2 (body)
    gyro_bias: np.ndarray | None = None       # (K, 3) estimated, rad/s
    gyro_bias_true: np.ndarray | None = None  # (K, 3) the IMU's own, rad/s
    accel_bias: np.ndarray | None = None      # (K, 3) estimated, m/s^2
    accel_bias_true: np.ndarray | None = None  # (K, 3) the IMU's own, m/s^2
    nees: np.ndarray | None = None            # (K,) normalized estimation error squared of the 12 rigid-body states
    estimator_s: np.ndarray | None = None     # (K,) the filter's time in the call, s
    crash_step: int | None = None
    crash_reason: str | None = None

    @classmethod
    def empty(cls, K: int) -> "Trace":
        return cls(x=np.full((K + 1, NX), np.nan), x_measured=np.full((K, NX), np.nan),
                   u=np.full((K, NU), np.nan), u_command=np.full((K, NU), np.nan), solve_s=np.zeros(K),
                   latency_s=np.full(K, np.nan), load_s=np.full(K, np.nan), load_cpu_s=np.full(K, np.nan),
                   called=np.zeros(K, dtype=bool),
                   iterations=np.zeros(K, dtype=np.int64), status=np.full(K, "", dtype="<U40"),
                   solver_failed=np.zeros(K, dtype=bool), lqr_fallback=np.zeros(K, dtype=bool),
                   rotor_speed=np.full((K + 1, 4), np.nan))


def _estimate_fields(tr: Trace, steps: int, nx: int, nz: int) -> None:
    tr.x_estimate, tr.estimate_std = np.full((steps, nx), np.nan), np.full((steps, nz), np.nan)
    tr.disturbance, tr.gyro_bias = np.full((steps, 6), np.nan), np.full((steps, 3), np.nan)
    tr.gyro_bias_true, tr.nees, tr.estimator_s = np.full((steps, 3), np.nan), np.full(steps, np.nan), \
        np.full(steps, np.nan)
    tr.accel_bias, tr.accel_bias_true = np.full((steps, 3), np.nan), np.full((steps, 3), np.nan)


def nees(x_true: np.ndarray, x_est: np.ndarray, P: np.ndarray) -> float:
    """Normalized estimation error squared of the 12 rigid-body states (angles wrapped)."""
    e = x_est[:NX] - x_true[:NX]
    e[3:6] = np.pi - np.mod(np.pi - e[3:6], 2.0 * np.pi)
    try:
        return float(e @ np.linalg.solve(P[:NX, :NX], e))
    except np.linalg.LinAlgError:
        return float("nan")


def fly_loop(plant: Plant, sensor: Sensor, controller: Controller, clock: Clock, x_ref: np.ndarray, steps: int,
             progress=None, estimator: StateEstimator | None = None, wall=time.perf_counter,
             cpu=time.thread_time) -> Trace:
    """Fly ``steps`` control periods from the plant's current state; the :class:`Trace`.

    ``x_ref`` (steps + 1, 12): the reference at each period boundary (the
    crash test's). ``progress``: an optional wrapper of the period range
    (for example ``tqdm``). ``estimator``: the controller sees its estimate
    (``sensor`` is then unused). The loop ends early at a crash, and when the
    estimator loses the state (:class:`mpc.errors.EstimatorError`: the run is
    recorded as crashed at that period, its reason ``"estimator failed: ..."``).
    ``wall``: the wall clock the calls are timed on, s (``time.perf_counter``; a test passes a fake one); ``cpu``:
    the controller thread's CPU clock on which the same span is timed (``time.thread_time``): where a period's
    load is long and its CPU time short, the machine held the controller up.
    """
    from mpc.controllers.controller import collector_paused
    from mpc.errors import EstimatorError

    tr = Trace.empty(steps)
    tr.x[0] = plant.x
    tr.rotor_speed[0] = plant.rotor_speed
    if estimator is not None:
        _estimate_fields(tr, steps, estimator.ekf.nx, estimator.ekf.nz)
    periods = range(steps) if progress is None else progress(range(steps))
    for k in periods:
        t = k * DT
        if estimator is not None:
            estimator.collect(t)
        if clock.idle(k):
            if estimator is None:
                xm = sensor.measure(plant.x)
                tr.x_measured[k] = xm
            # In real time the garbage collector waits until the call has returned: a collection triggered
            # by the plant's allocations is not the controller's time.
            with collector_paused(clock.realtime):
                c0, p0 = wall(), cpu()
                if clock.realtime:      # a controller that can keep a deadline (the MPCs on OSQP) keeps this one
                    controller.set_deadline(c0 + DT - DEADLINE_MARGIN_S)
                if estimator is not None:
                    try:
                        est = estimator.estimate()
                    except EstimatorError as e:   # the state is lost: the flight ends here, recorded as a crash
                        tr.crash_step, tr.crash_reason = k, f"estimator failed: {e}"
                        break
                    xm = est.x
                    controller.set_disturbance(est.disturbance, est.x)
                c1 = wall()
                u_cmd, info = controller(xm, t)
                tr.latency_s[k] = wall() - c0
                # Once the input is out, the controller may prepare the next period (the real-time iteration),
                # by the next measurement: charged to the period's load, not to the input's latency.
                controller.prepare_next(c0 + DT - DEADLINE_MARGIN_S if clock.realtime else None)
                tr.load_s[k] = wall() - c0
                tr.load_cpu_s[k] = cpu() - p0
            if estimator is not None:
                tr.estimator_s[k] = c1 - c0
                tr.x_measured[k] = xm[:NX]
                tr.x_estimate[k], tr.estimate_std[k] = xm, est.std
                tr.disturbance[k], tr.gyro_bias[k] = est.disturbance, est.gyro_bias
                tr.gyro_bias_true[k] = estimator.sensors.gyro_bias
                tr.accel_bias[k], tr.accel_bias_true[k] = est.accel_bias, estimator.sensors.accel_bias
                tr.nees[k] = nees(plant.x, xm, est.P)
            tr.called[k] = True
            tr.u_command[k] = u_cmd
            tr.solve_s[k] = info.solve_time_s + (tr.load_s[k] - tr.latency_s[k])    # the preparation's time too
            tr.iterations[k] = info.iterations
            tr.status[k] = info.status
            tr.solver_failed[k] = info.fallback is not None
            tr.lqr_fallback[k] = info.fallback == "lqr"
            clock.command(k, u_cmd, tr.latency_s[k], tr.load_s[k])
        tr.u[k] = clock.fly_period(plant, k)
        controller.applied(clock.sent)
        if estimator is not None:
            # The filter predicts with what drove the plant: after an actuation delay, the command sent that many
            # periods ago (a flight computer knows its own delay), not the one sent in this period.
            estimator.applied(clock.in_effect)
        x = plant.x
        tr.x[k + 1] = x
        tr.rotor_speed[k + 1] = plant.rotor_speed
        tr.steps = k + 1
        why = crash_reason(x, x_ref[k + 1])
        if why is not None:
            tr.crash_step, tr.crash_reason = k + 1, why
            break
    return tr


__all__ = ["DEADLINE_MARGIN_S", "Estimator", "IdealClock", "PERIOD_MS", "RealtimeClock", "StateSensor", "Trace",
           "fly_loop", "nees"]
