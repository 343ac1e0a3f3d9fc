"""Sensors of a flight computer: motion capture and an IMU, read from any plant.

A controller on a real vehicle never sees the state. It sees a motion-capture
system's position and attitude, late and noisy, and an IMU's body rates and
specific force, fast, noisy and biased. This module makes those readings from
the true state of any plant (:mod:`sim.plants.plant`), so that an estimator can be
flown against either the reference simulator or RotorPy::

    suite = SensorSuite(rng=np.random.default_rng(0))        # the default lab
    plant = SensedPlant(make_plant("sim"), suite)             # a plant that feeds its sensors
    plant.reset(x0)
    plant.advance(u, DT)                                      # samples the sensors every millisecond
    r = suite.read(plant.t)                                   # the readings that arrived since the last read

:class:`SensedPlant` advances the plant one millisecond (its time
resolution) at a time and hands each tick to the sensors (the reference
simulator flies a call's ticks in one, and the sensors take them together,
with the numbers of one tick at a time):

* **IMU** (1 kHz by default): the gyroscope reads the body rates at the end
  of the tick plus a bias and white noise; the accelerometer reads the
  specific force ``R^T (dv/dt - g e_z)`` in body axes (FRD), with ``dv/dt``
  the mean acceleration over the tick, plus its own bias and noise. A
  vehicle at rest or in hover therefore reads ``-g`` along body z, as a real
  IMU does (it measures the rotors' push, not gravity). Each bias starts at a
  seeded draw (the residual of the power-on calibration) and drifts as a
  random walk.
* **Motion capture** (200 Hz by default): position and ZYX Euler angles
  (each wrapped to (-pi, pi], as a tracking system reports them) plus white
  noise, taken at the tick and delivered ``latency_s`` later.

Latencies are whole milliseconds; a rate whose period is not (400 Hz) takes
each sample at the first millisecond tick at or after its time. The default values
(:class:`MocapConfig`, :class:`ImuConfig`) are those of an indoor
motion-capture lab with a small vehicle's MEMS IMU; ``docs/estimation.md``
gives their sources.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from .._validate import nonnegative_finite, positive_finite
from ..equations.dynamics import rotation_matrix
from ..errors import SimInputError
from ..params import DT, NX, SUBSTEPS
from .plant import Plant, TickTrace

#: The plant's time resolution and the sensors' clock, s.
TICK_S = DT / SUBSTEPS
TICK_MS = int(round(TICK_S * 1e3))


def _whole_ms(value: float, name: str, minimum: int) -> int:
    ms = value * 1e3
    n = int(round(ms))
    if abs(ms - n) > 1e-9 or n < minimum:
        raise SimInputError(f"{name} must be a whole number of milliseconds >= {minimum} ms; found {value!r} s")
    return n


def _samples_by(t_ms, rate_hz: float):
    """Samples of a clock at ``rate_hz`` started at 0 whose times are at or before ``t_ms`` (ms).

    ``t_ms`` an int, or an int array (K,): the count of each, the same numbers.
    """
    if np.ndim(t_ms):
        return np.floor(t_ms * rate_hz / 1e3 + 1e-9).astype(np.int64)
    return int(np.floor(t_ms * rate_hz / 1e3 + 1e-9))


@dataclass(frozen=True)
class MocapConfig:
    """A motion-capture system: rate, latency and noise (standard deviations).

    Defaults: 200 Hz; 7 ms from the exposure to the flight computer; 0.5 mm
    position and 3 mrad (0.17 deg) attitude noise per axis.
    """

    rate_hz: float = 200.0          # Hz, up to 1000 (a sample is taken at the first tick at or after its time)
    latency_s: float = 0.007        # s, whole ms
    position_std: float = 0.5e-3    # m
    attitude_std: float = 3e-3      # rad, on each Euler angle

    def __post_init__(self):
        positive_finite(self.rate_hz, "MocapConfig.rate_hz")
        nonnegative_finite(self.latency_s, "MocapConfig.latency_s")
        nonnegative_finite(self.position_std, "MocapConfig.position_std")
        nonnegative_finite(self.attitude_std, "MocapConfig.attitude_std")
        if self.rate_hz > 1e3 / TICK_MS:
            raise SimInputError(f"MocapConfig.rate_hz must be at most {1e3 / TICK_MS:g} Hz (the plant's resolution "
                                f"is {TICK_MS} ms); found {self.rate_hz!r}")
        _whole_ms(self.latency_s, "MocapConfig.latency_s", 0)

    def due(self, t_ms):
        """True when a sample is taken at tick ``t_ms`` (ms): the sample clock passed a sample time in it.

        ``t_ms`` an int, or an int array (K,) of ticks: a bool array (K,).
        """
        return _samples_by(t_ms, self.rate_hz) > _samples_by(t_ms - TICK_MS, self.rate_hz)

    @property
    def latency_ms(self) -> int:
        return _whole_ms(self.latency_s, "MocapConfig.latency_s", 0)


@dataclass(frozen=True)
class ImuConfig:
    """A MEMS IMU: rate, white noise per sample, bias at power-on and bias drift.

    Defaults: 1 kHz; gyroscope 1.4 mrad/s per sample (0.005 deg/s/sqrt(Hz)
    over a 256 Hz bandwidth), bias 8.7 mrad/s (0.5 deg/s) at power-on,
    drifting 1e-4 rad/s per sqrt(s); accelerometer 0.063 m/s^2 per sample
    (400 micro-g/sqrt(Hz) over 256 Hz), bias 0.05 m/s^2, drifting 1e-3 m/s^2
    per sqrt(s).
    """

    rate_hz: float = 1000.0
    gyro_std: float = 1.4e-3             # rad/s, white noise per sample
    gyro_bias_std: float = 8.7e-3        # rad/s, bias at power-on (per axis)
    gyro_bias_walk: float = 1e-4         # rad/s per sqrt(s)
    accel_std: float = 0.063             # m/s^2, white noise per sample
    accel_bias_std: float = 0.05         # m/s^2, bias at power-on (per axis)
    accel_bias_walk: float = 1e-3        # m/s^2 per sqrt(s)

    def __post_init__(self):
        for f in fields(self):
            (positive_finite if f.name == "rate_hz" else nonnegative_finite)(getattr(self, f.name),
                                                                           f"ImuConfig.{f.name}")
        _whole_ms(1.0 / self.rate_hz, "ImuConfig's period 1 / rate_hz", 1)

    @property
    def period_ms(self) -> int:
        return _whole_ms(1.0 / self.rate_hz, "ImuConfig's period", 1)


@dataclass
class Readings:
    """The sensor samples that arrived in an interval (units in comments; M, I samples).

    Times are when each sample was *taken* (a motion-capture sample arrives
    its latency later).
    """

    mocap_t: np.ndarray     # (M,) s
    mocap: np.ndarray       # (M, 6) position (m, NED) and ZYX Euler angles (rad, wrapped to (-pi, pi])
    imu_t: np.ndarray       # (I,) s
    gyro: np.ndarray        # (I, 3) rad/s, body FRD
    accel: np.ndarray       # (I, 3) m/s^2, specific force in body FRD

    @classmethod
    def empty(cls) -> "Readings":
        return cls(np.zeros(0), np.zeros((0, 6)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))


def wrap_angle(a):
    """Angles wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2.0 * np.pi)


def specific_force(x0: np.ndarray, x1: np.ndarray, dt: float, g: float) -> np.ndarray:
    """Mean specific force in body axes over intervals of ``dt`` s from states ``x0`` to ``x1``.

    ``R^T (dv/dt - g e_z)`` with the mean acceleration ``dv/dt`` (NED) and the
    attitude halfway (the mean of the two ends' Euler angles).

    Parameters
    ----------
    x0, x1 : numpy.ndarray, shape (12,) or (K, 12)
        States at the start and at the end of each interval.
    dt : float
        Length of the intervals, s.
    g : float
        Gravity, m/s^2.

    Returns
    -------
    numpy.ndarray, shape (3,) or (K, 3)
        Specific force, m/s^2, body FRD. A stack of intervals gives each the numbers it gets alone.
    """
    if np.ndim(x0) == 1:
        a = (x1[9:12] - x0[9:12]) / dt
        eta = 0.5 * (x0[3:6] + x1[3:6])
        R = rotation_matrix(*eta)
        return R.T @ (a - np.array([0.0, 0.0, g]))
    a = (x1[:, 9:12] - x0[:, 9:12]) / dt
    eta = 0.5 * (x0[:, 3:6] + x1[:, 3:6])
    R = rotation_matrix(eta[:, 0], eta[:, 1], eta[:, 2])
    # One matrix-vector product per interval, as above (the same product on each, not a reordered sum).
    return np.matmul(R.transpose(0, 2, 1), (a - np.array([0.0, 0.0, g]))[:, :, None])[:, :, 0]


@dataclass
class SensorSuite:
    """Motion capture and IMU on one vehicle (either may be None: not fitted).

    Parameters
    ----------
    mocap : MocapConfig or None
    imu : ImuConfig or None
    rng : numpy.random.Generator
        Draws every noise sample and the biases at power-on (two suites with
        equal seeds read exactly the same).
    g : float
        Gravity, m/s^2 (the accelerometer's reading at rest).
    """

    mocap: MocapConfig | None = field(default_factory=MocapConfig)
    imu: ImuConfig | None = field(default_factory=ImuConfig)
    rng: np.random.Generator | None = None
    g: float = 9.81

    def __post_init__(self):
        if self.mocap is not None and not isinstance(self.mocap, MocapConfig):
            raise SimInputError(f"mocap must be a MocapConfig or None; found {type(self.mocap).__name__}")
        if self.imu is not None and not isinstance(self.imu, ImuConfig):
            raise SimInputError(f"imu must be an ImuConfig or None; found {type(self.imu).__name__}")
        if self.rng is None:
            self.rng = np.random.default_rng()
        self.reset(0, np.full(NX, np.nan))

    def reset(self, t_ms: int, x: np.ndarray) -> None:
        """Power on at time ``t_ms`` (ms) with the vehicle in state ``x`` (12,): new biases, empty queues."""
        imu = self.imu
        self.gyro_bias = np.zeros(3) if imu is None else imu.gyro_bias_std * self.rng.standard_normal(3)
        self.accel_bias = np.zeros(3) if imu is None else imu.accel_bias_std * self.rng.standard_normal(3)
        self._mocap: list[tuple[int, float, np.ndarray]] = []    # (arrival ms, time taken s, sample)
        self._imu: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._t_ms = int(t_ms)
        if self.mocap is not None and np.all(np.isfinite(x)):
            # The vehicle has stood in x since long before: its picture at power-on is already there.
            self._take_mocap(int(t_ms), x)
            self._mocap[-1] = (int(t_ms), *self._mocap[-1][1:])

    def _take_mocap(self, t_ms: int, x: np.ndarray) -> None:
        c = self.mocap
        z = np.concatenate([x[0:3] + c.position_std * self.rng.standard_normal(3),
                            wrap_angle(x[3:6] + c.attitude_std * self.rng.standard_normal(3))])
        self._mocap.append((t_ms + c.latency_ms, t_ms * 1e-3, z))

    def tick(self, x0: np.ndarray, x1: np.ndarray) -> None:
        """One millisecond of flight from state ``x0`` to ``x1`` (12,): take the samples due at its end."""
        self._t_ms += TICK_MS
        t_ms = self._t_ms
        imu = self.imu
        if imu is not None:
            # The biases drift every tick, whatever the IMU's output rate.
            s = np.sqrt(TICK_S)
            self.gyro_bias = self.gyro_bias + imu.gyro_bias_walk * s * self.rng.standard_normal(3)
            self.accel_bias = self.accel_bias + imu.accel_bias_walk * s * self.rng.standard_normal(3)
            if t_ms % imu.period_ms == 0:
                gyro = x1[6:9] + self.gyro_bias + imu.gyro_std * self.rng.standard_normal(3)
                f = specific_force(x0, x1, TICK_S, self.g)
                accel = f + self.accel_bias + imu.accel_std * self.rng.standard_normal(3)
                self._imu.append((t_ms * 1e-3, gyro, accel))
        if self.mocap is not None and self.mocap.due(t_ms):
            self._take_mocap(t_ms, x1)

    def tick_all(self, states: np.ndarray) -> None:
        """The ticks of flight through ``states``: ``tick(states[i], states[i + 1])`` for each i, at once.

        The same samples, biases and random numbers as those calls: the normals
        of all ticks come from one call of the generator, in the order the
        calls draw them (a generator gives the same numbers in one draw as in
        consecutive draws of the same total).

        Parameters
        ----------
        states : array_like, shape (K + 1, 12)
            The state at the start of the first tick and at the end of each of
            the K ticks (1 ms each).
        """
        xs = np.asarray(states, dtype=float)
        if xs.ndim != 2 or xs.shape[1] != NX or len(xs) < 1:
            raise SimInputError(f"states must have shape (K + 1, {NX}); found {xs.shape}")
        k = len(xs) - 1
        if k == 0:
            return
        imu, mocap = self.imu, self.mocap
        t = self._t_ms + TICK_MS * np.arange(1, k + 1)                 # each tick's end, ms
        imu_due = np.zeros(k, dtype=bool) if imu is None else t % imu.period_ms == 0
        mocap_due = np.zeros(k, dtype=bool) if mocap is None else mocap.due(t)
        # Each tick draws rows of three normals, in this order: the gyroscope's and the accelerometer's bias
        # steps, their noise when the IMU samples, the position's and the attitude's noise when motion capture does.
        walk_rows = 0 if imu is None else 2
        rows = walk_rows + 2 * imu_due + 2 * mocap_due
        first = np.cumsum(rows) - rows
        z = self.rng.standard_normal(3 * int(rows.sum())).reshape(-1, 3)
        t_list = t.tolist()
        x0, x1 = xs[:-1], xs[1:]
        if imu is not None:
            s = np.sqrt(TICK_S)
            # The random walk: an accumulation adds one step at a time, in order, as tick does.
            gyro_bias = np.cumsum(np.vstack([self.gyro_bias, imu.gyro_bias_walk * s * z[first]]), axis=0)[1:]
            accel_bias = np.cumsum(np.vstack([self.accel_bias, imu.accel_bias_walk * s * z[first + 1]]), axis=0)[1:]
            self.gyro_bias, self.accel_bias = gyro_bias[-1].copy(), accel_bias[-1].copy()
            due = np.flatnonzero(imu_due)
            if len(due):
                noise = first[due] + 2
                gyro = x1[due, 6:9] + gyro_bias[due] + imu.gyro_std * z[noise]
                f = specific_force(x0[due], x1[due], TICK_S, self.g)
                accel = f + accel_bias[due] + imu.accel_std * z[noise + 1]
                self._imu.extend(zip([t_list[i] * 1e-3 for i in due.tolist()], gyro, accel))
        taken = np.flatnonzero(mocap_due)
        if len(taken):
            c = mocap
            seen = first[taken] + walk_rows + 2 * imu_due[taken]
            pos = x1[taken, 0:3] + c.position_std * z[seen]
            att = wrap_angle(x1[taken, 3:6] + c.attitude_std * z[seen + 1])
            latency = c.latency_ms
            when = [t_list[i] for i in taken.tolist()]
            self._mocap.extend(zip([w + latency for w in when], [w * 1e-3 for w in when],
                                   np.concatenate([pos, att], axis=1)))
        self._t_ms = t_list[-1]

    def read(self, t: float) -> Readings:
        """The samples that have arrived by time ``t`` (s) and were not read before."""
        t_ms = int(round(t * 1e3))
        mocap = [m for m in self._mocap if m[0] <= t_ms]
        self._mocap = [m for m in self._mocap if m[0] > t_ms]
        imu, self._imu = self._imu, []
        r = Readings.empty()
        if mocap:
            r.mocap_t = np.array([m[1] for m in mocap])
            r.mocap = np.array([m[2] for m in mocap])
        if imu:
            r.imu_t = np.array([s[0] for s in imu])
            r.gyro = np.array([s[1] for s in imu])
            r.accel = np.array([s[2] for s in imu])
        return r


class SensedPlant:
    """A plant whose sensors are sampled every millisecond of flight.

    It has the plant interface (:class:`sim.plants.plant.Plant`: ``reset``,
    ``advance``, ``x``, ``t``, ``hover_input``, ``describe``) and flies the
    wrapped plant as in 1 ms calls, handing each to the :class:`SensorSuite`.
    Flying in 1 ms pieces is the same flight for the reference simulator up
    to the wind, which is then evaluated every millisecond instead of at the
    start of each call.
    """

    def __init__(self, plant, sensors: SensorSuite):
        if not isinstance(sensors, SensorSuite):
            raise SimInputError(f"sensors must be a SensorSuite; found {type(sensors).__name__}")
        self.plant = plant
        self.sensors = sensors
        self.sensors.g = plant.vehicle.params.g

    def __getattr__(self, name):
        return getattr(self.plant, name)

    @property
    def x(self) -> np.ndarray:
        return self.plant.x

    def reset(self, x0, rotor_speed=None):
        out = self.plant.reset(x0, rotor_speed=rotor_speed)
        self.sensors.reset(int(round(self.plant.t * 1e3)), out.x)
        return out

    def advance(self, u, duration_s: float = DT):
        """Hold ``u`` (4,) for ``duration_s`` (whole ms), sampling the sensors every millisecond; the plant after it.

        The plant's :class:`sim.plants.plant.PlantOutput` after the last millisecond; see :meth:`advance_ticks`.
        """
        return self.advance_ticks(u, duration_s).out

    def advance_ticks(self, u, duration_s: float = DT) -> TickTrace:
        """:meth:`advance`, returning the plant after every millisecond (:meth:`sim.plants.plant.Plant.advance_ticks`).

        A :class:`sim.plants.plant.Plant` flies the ticks with its ``advance_ticks`` (the reference simulator in one
        call) and the sensors take them all at once (:meth:`SensorSuite.tick_all`); any other plant is advanced
        one tick at a time, each handed to :meth:`SensorSuite.tick`. Either way the states, samples and random
        numbers are those of one ``advance(u, 1 ms)`` and one ``tick`` per millisecond. When the plant raises
        partway through a call, the sensors have not sampled its ticks.

        Parameters
        ----------
        u : array_like, shape (4,)
            Wrench command ``[T, tau_x, tau_y, tau_z]``, N and N m.
        duration_s : float
            A whole number of milliseconds, s.

        Returns
        -------
        sim.plants.plant.TickTrace
            States (K + 1, 12) at the start and after each of the K ticks, rotor speeds (K, 4) after each, and
            the plant's output after the last.
        """
        ticks = int(round(duration_s / TICK_S))
        if ticks < 1 or abs(ticks * TICK_S - duration_s) > 1e-12:
            raise SimInputError(f"duration_s must be a whole number of {TICK_S * 1e3:g} ms; found {duration_s}")
        if isinstance(self.plant, Plant):
            trace = self.plant.advance_ticks(u, duration_s)
            self.sensors.tick_all(trace.x)
            return trace
        xs, ns, out = [self.plant.x], [], None
        for _ in range(ticks):
            x0 = self.plant.x
            out = self.plant.advance(u, TICK_S)
            self.sensors.tick(x0, out.x)
            xs.append(out.x)
            ns.append(out.rotor_speed)
        return TickTrace(np.array(xs), np.array(ns), out)

    def step(self, u):
        return self.advance(u, DT)

    def describe(self) -> dict:
        import dataclasses

        s = self.sensors
        return {**self.plant.describe(),
                "sensors": {"mocap": None if s.mocap is None else dataclasses.asdict(s.mocap),
                            "imu": None if s.imu is None else dataclasses.asdict(s.imu)}}


__all__ = ["ImuConfig", "MocapConfig", "Readings", "SensedPlant", "SensorSuite", "TICK_S", "specific_force",
           "wrap_angle"]
