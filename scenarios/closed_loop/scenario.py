"""The closed-loop scenario as a record, and the defaults every scenario shares.

A :class:`Scenario` is frozen data: initial state, reference trajectory
(given by its flat outputs), duration, plant options, noise, delay and a
seed. The named scenarios are built in :mod:`scenarios.closed_loop.library`; scenario
files are read by :mod:`scenarios.closed_loop.scenario_file`. Both build this record.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np

from sim.params import DT, NX, NoiseModel

from ..errors import ScenarioError

#: The flatness map through which a scenario's start state ``x0`` is its reference at t = 0 (plus its offsets):
#: the default vehicle's numbers, taken once when the scenarios are built. A run on a vehicle or plant with other
#: gravity or drag keeps the offsets and takes the reference part through its own map
#: (:meth:`Scenario.start_state`).
def _start_map():
    from mpc.prediction.spec import VehicleSpec

    return VehicleSpec()


START_MAP = _start_map()

HOVER_HEIGHT_M = 1.0
FIGURE8_AMPLITUDE_M = 0.75
#: Relative payload of the ``+payload`` variant (fraction of the vehicle mass).
PAYLOAD_FRACTION = 0.2
#: Periods of the figure-8 speed ladder beyond figure8-fast, s (2.0 s drives a rotor to 97 % of its maximum thrust).
LADDER_PERIODS_S = (2.7, 2.4, 2.2, 2.0)
#: Random minimum-snap paths flown by the main job (waypoint seeds).
RANDOM_SEEDS = (0, 1, 2)
#: Waypoints of a random path (the first is the hover point), and its bounds: speed (m/s), acceleration (m/s^2).
RANDOM_WAYPOINTS = 4
RANDOM_V_MAX = 1.5
RANDOM_A_MAX = 4.0
#: Hover scenario: start offset (m, NED; 4.1 cm) and attitude offset (deg), gust impulse, length.
HOVER_START_OFFSET_M = (0.03, -0.02, 0.02)
HOVER_START_ATTITUDE_DEG = (3.0, -3.0, 5.0)
HOVER_DURATION_S = 6.0
#: The longest flight a scenario may ask for, s. A small quadrotor's battery lasts 5-10 minutes; a flight's trace
#: holds about 1 kB per 10 ms period (60 MB for 600 s, kept in memory until written), and each period costs a few
#: milliseconds of computing (600 s of flight take 5-20 minutes to fly here).
MAX_DURATION_S = 600.0
DURATION_LIMIT_REASON = ("a small quadrotor's battery lasts 5-10 minutes, and a flight's trace (about 1 kB per "
                         "10 ms period) is kept in memory until it is written")
#: Measurement noise of ``+noise`` and delay of ``+delay``: see ``docs/scenarios.md`` for how they were chosen.
NOISE = NoiseModel(position=1e-3, attitude=2e-3, body_rate=1e-2, velocity=1e-2)
DELAY_STEPS = 3
#: Yaw turn: angle (rad), duration (s) and start (s). The turn needs about 1.5 times the yaw torque that the
#: rotors give at hover, so where the yaw torque limit lies (the rotor torque coefficient kq) decides the result.
YAW_TURN_RAD = np.pi
YAW_TURN_S = 0.2
YAW_TURN_START_S = 1.0
KINDS = ("hover", "figure8", "minsnap", "yaw_turn", "waypoints", "table")
#: Kinds whose reference is given point by point (scenario files): a path through waypoints, a table of flat outputs.
POINT_KINDS = ("waypoints", "table")


@dataclass(frozen=True)
class GustImpulse:
    """A single horizontal 1 - cos gust, as a world-frame acceleration (units in comments).

    ``a(t) = peak (1 - cos(2 pi (t - start) / duration)) / 2 * direction`` for
    ``start <= t < start + duration``, else 0.
    """

    start_s: float = 1.5                          # s
    duration_s: float = 0.2                       # s
    peak_mps2: float = 3.0                        # m/s^2
    direction: tuple[float, float, float] = (0.6, 0.8, 0.0)   # unit vector, NED

    def __call__(self, t: float) -> np.ndarray:
        """World-frame acceleration (3,) at time ``t`` (s), m/s^2."""
        s = (t - self.start_s) / self.duration_s
        if 0.0 <= s < 1.0:
            return self.peak_mps2 * 0.5 * (1 - np.cos(2 * np.pi * s)) * np.asarray(self.direction, dtype=float)
        return np.zeros(3)

    def to_dict(self) -> dict:
        return {"start_s": self.start_s, "duration_s": self.duration_s, "peak_mps2": self.peak_mps2,
                "direction": list(self.direction)}


@dataclass(frozen=True)
class WindGusts:
    """Wind as a world-frame acceleration: a steady part plus seeded 1 - cos gusts.

    ``a(t) = mean + sum_i g_i (1 - cos(2 pi (t - t_i) / T_i)) / 2`` for
    ``t_i <= t < t_i + T_i``. Gust start times are evenly spread over the
    flight with a seeded jitter; directions are horizontal, seeded.
    """

    mean: tuple[float, float, float] = (0.4, 0.0, 0.0)   # steady acceleration, m/s^2 (NED)
    gust_peak: float = 1.5                                # peak gust acceleration, m/s^2
    gust_duration_s: float = 0.8                          # length of one gust, s
    n_gusts: int = 3                                      # gusts per flight
    flight_duration_s: float = 5.0                        # span the gusts are spread over, s
    seed: int = 0
    _starts: np.ndarray = field(init=False, repr=False, compare=False)
    _dirs: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        rng = np.random.default_rng([int(self.seed), 0x91D])
        slots = np.linspace(0.0, self.flight_duration_s, self.n_gusts + 1)[:-1]
        width = self.flight_duration_s / max(self.n_gusts, 1)
        starts = slots + rng.uniform(0.1, 0.6, self.n_gusts) * width
        angle = rng.uniform(0.0, 2 * np.pi, self.n_gusts)
        dirs = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
        object.__setattr__(self, "_starts", starts)
        object.__setattr__(self, "_dirs", dirs)

    def __call__(self, t: float) -> np.ndarray:
        """World-frame acceleration (3,) at time ``t`` (s), m/s^2."""
        a = np.array(self.mean, dtype=float)
        s = (t - self._starts) / self.gust_duration_s
        on = (s >= 0) & (s < 1)
        if np.any(on):
            shape = self.gust_peak * 0.5 * (1 - np.cos(2 * np.pi * s[on]))   # (n_on,)
            a = a + shape @ self._dirs[on]
        return a

    def to_dict(self) -> dict:
        return {"mean_mps2": list(self.mean), "gust_peak_mps2": self.gust_peak,
                "gust_duration_s": self.gust_duration_s, "n_gusts": self.n_gusts,
                "gust_starts_s": [float(v) for v in self._starts], "seed": self.seed}


@dataclass(frozen=True)
class Scenario:
    """One closed-loop flight, as data (units in comments)."""

    name: str
    kind: str                                  # one of KINDS
    duration_s: float                          # flight time, s
    x0: tuple[float, ...]                      # (12,) initial state (state order x..vz, NED)
    height_m: float = HOVER_HEIGHT_M           # reference height, m (NED z = -height)
    period_s: float | None = None              # figure-8 period, s
    amplitude_m: float = FIGURE8_AMPLITUDE_M   # figure-8 amplitude A, m
    path_seed: int | None = None               # minimum-snap waypoint seed
    high_fidelity: bool = False                # the vehicle's motor lag, rotor drag, gyro torque in our simulator
    payload_fraction: float = 0.0              # extra mass carried, fraction of the vehicle's mass
    wind: WindGusts | None = None              # wind acceleration, or none
    impulse: GustImpulse | None = None         # one gust impulse, or none
    noise: NoiseModel | None = None            # measurement noise on the state the controller sees
    delay_steps: int = 0                       # control periods between computing u and applying it
    seed: int = 0                              # seeds noise and gusts
    description: str = ""
    # The references given point by point (scenario files); None where a kind does not use them.
    position_m: tuple[float, float, float] | None = None   # "hover": the point, m (NED); None: (0, 0, -height_m)
    yaw_rad: float = 0.0                       # "hover", "waypoints": constant yaw, rad; "table" without yaw samples
    points_m: tuple[tuple[float, float, float], ...] | None = None   # "waypoints": waypoints; "table": positions, m
    path_duration_s: float | None = None       # "waypoints": time to fly through the waypoints, s
    times_s: tuple[float, ...] | None = None   # "table": sample times, s
    table_yaw_rad: tuple[float, ...] | None = None   # "table": yaw samples, rad (None: yaw_rad throughout)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ScenarioError(f"kind must be one of {', '.join(KINDS)}; found {self.kind!r}")
        if not (np.isfinite(self.duration_s) and self.duration_s >= DT):
            raise ScenarioError(f"duration_s must be >= {DT}; found {self.duration_s}")
        if self.duration_s > MAX_DURATION_S:
            raise ScenarioError(f"duration_s must be at most {MAX_DURATION_S:g} s ({DURATION_LIMIT_REASON}); "
                                f"found {self.duration_s:g}")
        if len(self.x0) != NX or not np.all(np.isfinite(self.x0)):
            raise ScenarioError(f"x0 must hold 12 finite numbers; found {len(self.x0)}")
        if self.kind == "figure8" and not (self.period_s and self.period_s > 0):
            raise ScenarioError(f"a figure8 scenario needs period_s > 0; found {self.period_s}")
        if self.kind == "minsnap" and (self.path_seed is None or self.path_seed < 0):
            raise ScenarioError(f"a minsnap scenario needs path_seed >= 0; found {self.path_seed}")
        if self.delay_steps < 0 or not self.payload_fraction >= 0:
            raise ScenarioError("delay_steps and payload_fraction must be >= 0")
        self._check_points()

    def _check_points(self):
        """Shapes of the point-by-point reference fields (their values are checked when the path is built)."""
        def finite(v, n=None):
            return (isinstance(v, tuple) and (n is None or len(v) == n)
                    and all(isinstance(e, (int, float)) and not isinstance(e, bool) and np.isfinite(e) for e in v))

        if not (isinstance(self.yaw_rad, (int, float)) and np.isfinite(self.yaw_rad)):
            raise ScenarioError(f"yaw_rad must be finite; found {self.yaw_rad!r}")
        if self.position_m is not None and not (self.kind == "hover" and finite(self.position_m, 3)):
            raise ScenarioError(f"position_m belongs to a hover scenario and holds 3 finite numbers; found "
                                f"{self.position_m!r} in a {self.kind} scenario")
        given = {"points_m": self.points_m, "path_duration_s": self.path_duration_s, "times_s": self.times_s,
                 "table_yaw_rad": self.table_yaw_rad}
        need = {"waypoints": ("points_m", "path_duration_s"), "table": ("points_m", "times_s")}.get(self.kind, ())
        allowed = need + (("table_yaw_rad",) if self.kind == "table" else ())
        for k, v in given.items():
            if v is None and k in need:
                raise ScenarioError(f"a {self.kind} scenario needs {k}")
            if v is not None and k not in allowed:
                raise ScenarioError(f"{k} does not belong to a {self.kind} scenario")
        if self.kind not in POINT_KINDS:
            return
        pts = self.points_m
        if not (isinstance(pts, tuple) and len(pts) >= 2 and all(finite(p, 3) for p in pts)):
            raise ScenarioError("points_m must be a tuple of at least 2 tuples of 3 finite numbers")
        if self.kind == "waypoints" and not (isinstance(self.path_duration_s, (int, float))
                                             and np.isfinite(self.path_duration_s) and self.path_duration_s > 0):
            raise ScenarioError(f"path_duration_s must be finite and > 0; found {self.path_duration_s!r}")
        if self.kind == "table":
            if not finite(self.times_s, len(pts)):
                raise ScenarioError(f"times_s must be a tuple of {len(pts)} finite numbers, one per point")
            if self.table_yaw_rad is not None and not finite(self.table_yaw_rad, len(pts)):
                raise ScenarioError(f"table_yaw_rad must be a tuple of {len(pts)} finite numbers, one per point")

    @property
    def steps(self) -> int:
        """Number of control periods."""
        return int(round(self.duration_s / DT))

    def reference(self):
        """The reference as a flat trajectory (:mod:`mpc.references.trajectory`); ``ref(times) -> (K, 12)``."""
        return _trajectory(self.kind, self.height_m, self.period_s, self.amplitude_m, self.path_seed,
                           self.position_m, self.yaw_rad, self.points_m, self.path_duration_s, self.times_s,
                           self.table_yaw_rad)

    def with_seed(self, seed: int) -> "Scenario":
        """The same scenario with another seed (noise and gusts redrawn; the path stays)."""
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ScenarioError(f"seed must be an integer >= 0; found {seed!r}")
        wind = None if self.wind is None else dataclasses.replace(self.wind, seed=int(seed))
        return dataclasses.replace(self, seed=int(seed), wind=wind)

    def member(self, k: int) -> "Scenario":
        """Ensemble member ``k``: seed ``k`` (noise and gusts redrawn) and the initial state moved by a seeded draw.

        The draw is normal with the standard deviations
        :data:`ENSEMBLE_X0_SIGMA`, seeded by ``k`` alone, so member ``k`` of
        a scenario is the same in every sweep; the path stays.
        """
        sc = self.with_seed(k)
        rng = np.random.default_rng([int(k), 0xE45])
        x0 = np.asarray(self.x0, dtype=float) + np.asarray(ENSEMBLE_X0_SIGMA) * rng.standard_normal(NX)
        return dataclasses.replace(sc, x0=tuple(float(v) for v in x0))

    def disturbance(self):
        """The scenario's wind and gust impulse as one acceleration function of time, or None without either."""
        parts = [w for w in (self.wind, self.impulse) if w is not None]
        if not parts:
            return None
        if len(parts) == 1:
            return parts[0]
        return lambda t: parts[0](t) + parts[1](t)

    def plant(self, name: str, vehicle, level: str = "wrench"):
        """The plant ``name`` (:data:`sim.plants.named.PLANTS`) flying ``vehicle`` with this scenario's
        high-fidelity set-up, payload and disturbances, taking commands at ``level`` (:mod:`sim.levels`; at ``ctbr``
        and ``ctatt`` through the vehicle's inner loop)."""
        from sim.plants.named import make_plant

        return make_plant(name, vehicle, high_fidelity=self.high_fidelity,
                          payload_kg=self.payload_fraction * vehicle.m, wind=self.disturbance(), level=level)

    def start_state(self, spec, x_ref0: np.ndarray | None = None) -> np.ndarray:
        """The initial state (12,) on the reference the plant flies.

        ``x0`` is the reference at t = 0 (through :data:`START_MAP`, the default vehicle's) plus the scenario's
        offsets; the offsets are kept and the reference part is replaced by the plant's: ``x_ref0`` (12,) where
        the plant has a map of its own (the high-fidelity plant's,
        :func:`mpc.references.trajectory.flown_reference`), else the flatness map of ``spec`` (a
        :class:`mpc.prediction.spec.VehicleSpec`), so that a vehicle with other drag starts on its own feasible
        reference. Unchanged for the default vehicle on the nominal plant.
        """
        from mpc.references.trajectory import reference_states

        x0 = np.array(self.x0, dtype=float)
        ref, t0 = self.reference(), np.array([0.0])
        if x_ref0 is None:
            if (spec.g, spec.c_d) == (START_MAP.g, START_MAP.c_d):   # the only numbers the map's states depend on
                return x0
            x_ref0 = reference_states(ref, t0, spec)[0]
        return x0 + x_ref0 - reference_states(ref, t0, START_MAP)[0]

    def sensor_suite(self):
        """The sensors of a run with the state estimator (:class:`sim.plants.sensors.SensorSuite`): the default
        lab's, with this scenario's noise where it sets one.

        A scenario with measurement noise (``+noise``) sets the motion capture's position and attitude noise and
        the gyroscope's white noise to its position, attitude and body-rate standard deviations.
        """
        from sim.plants.sensors import ImuConfig, MocapConfig, SensorSuite

        mocap, imu = MocapConfig(), ImuConfig()
        if self.noise is not None:
            mocap = dataclasses.replace(mocap, position_std=self.noise.position, attitude_std=self.noise.attitude)
            imu = dataclasses.replace(imu, gyro_std=self.noise.body_rate)
        return SensorSuite(mocap=mocap, imu=imu, rng=np.random.default_rng([self.seed, 0x5E75]))

    def to_dict(self) -> dict:
        """JSON-ready description (stored with every result).

        The point-by-point fields (``position_m``, ``yaw_rad``, ``points_m``,
        ``path_duration_s``, ``times_s``, ``table_yaw_rad``) appear when the
        scenario uses them, so the record of a built-in scenario is unchanged.
        """
        out = {"name": self.name, "kind": self.kind, "duration_s": self.duration_s, "x0": list(self.x0),
                "height_m": self.height_m, "period_s": self.period_s, "amplitude_m": self.amplitude_m,
                "path_seed": self.path_seed, "reference": self.reference().describe(),
                "high_fidelity": self.high_fidelity, "payload_fraction": self.payload_fraction,
                "wind": None if self.wind is None else self.wind.to_dict(),
                "impulse": None if self.impulse is None else self.impulse.to_dict(),
                "noise": None if self.noise is None else dataclasses.asdict(self.noise),
                "delay_steps": self.delay_steps, "seed": self.seed, "description": self.description}
        if self.kind in POINT_KINDS or self.position_m is not None or self.yaw_rad != 0.0:
            out.update({"position_m": None if self.position_m is None else list(self.position_m),
                        "yaw_rad": self.yaw_rad,
                        "points_m": None if self.points_m is None else [list(p) for p in self.points_m],
                        "path_duration_s": self.path_duration_s,
                        "times_s": None if self.times_s is None else list(self.times_s),
                        "table_yaw_rad": None if self.table_yaw_rad is None else list(self.table_yaw_rad)})
        return out


#: Standard deviations of an ensemble member's initial-state perturbation (state order: position m, attitude rad,
#: velocity m/s, body rates rad/s): small against the scenarios' own offsets, large against rounding, so that a
#: case whose outcome depends on its start shows it.
ENSEMBLE_X0_SIGMA = (0.01, 0.01, 0.01, 0.01, 0.01, 0.01, 0.02, 0.02, 0.02, 0.02, 0.02, 0.02)


@functools.lru_cache(maxsize=64)
def _trajectory(kind, height, period, amplitude, path_seed, position=None, yaw=0.0, points=None,
                path_duration=None, times=None, table_yaw=None):
    from mpc.references.minsnap import FlatTable, minsnap_through, random_minsnap
    from mpc.references.trajectory import Figure8, Hover, YawTurn

    if kind == "hover":
        return Hover((0.0, 0.0, -height) if position is None else position, yaw)
    if kind == "waypoints":
        return minsnap_through(points, path_duration, yaw)
    if kind == "table":
        return FlatTable(times, points, yaw if table_yaw is None else table_yaw)
    if kind == "yaw_turn":
        return YawTurn(YAW_TURN_RAD, YAW_TURN_S, YAW_TURN_START_S, (0.0, 0.0, -height))
    if kind == "figure8":
        return Figure8(amplitude, period, height)
    return random_minsnap(path_seed, n_waypoints=RANDOM_WAYPOINTS, v_max=RANDOM_V_MAX, a_max=RANDOM_A_MAX,
                          start=(0.0, 0.0, -height))
