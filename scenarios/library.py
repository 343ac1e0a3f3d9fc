"""Closed-loop scenarios as data.

A :class:`Scenario` is a frozen record: initial state, reference trajectory
(given by its flat outputs: a hover point, a figure-8 or a seeded
minimum-snap path), duration, simulator options (fidelity, payload, wind, a
gust impulse), measurement noise, input delay, and a seed. Nothing in it is
code that runs a flight; :mod:`scenarios.runner` does that.

Names:

* ``hover``: start a few cm and degrees off a 1 m hover point, a gust
  impulse at 1.5 s, hold until 6 s (the settled error is measured over the
  last 2 s);
* ``figure8-slow`` (period 6 s), ``figure8-fast`` (3 s): two laps of the
  lemniscate, starting on the reference;
* the speed ladder ``figure8-2.7s``, ``figure8-2.4s``, ``figure8-2.2s``,
  ``figure8-2.0s``: shorter periods up to the rotor limits (the 2.0 s lap
  drives a rotor to 97 % of its maximum thrust);
* ``yaw-turn``: hover and turn 180 deg in 0.2 s, beyond the rotors' yaw
  torque, so the yaw torque limit binds (heading error is its measure);
* ``random-<k>``: a minimum-snap path through seeded random waypoints
  (``k`` seeds the waypoints), bounded speed and acceleration;
* each of ``hover``, ``figure8-slow`` and ``figure8-fast`` with one variant
  suffix ``+highfi``, ``+payload``, ``+wind``, ``+noise``, ``+delay``::

    from scenarios import get_scenario, scenario_names
    s = get_scenario("figure8-slow+wind")
    traj = s.reference()           # a flat trajectory; traj(times (K,)) -> (K, 12)
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np

from sim.params import DT, HIGH_FIDELITY, NOMINAL, NX, Fidelity, NoiseModel, QuadParams

from .errors import ScenarioError

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
#: Measurement noise of ``+noise`` and delay of ``+delay``: see ``docs/scenarios.md`` for how they were chosen.
NOISE = NoiseModel(position=1e-3, attitude=2e-3, body_rate=1e-2, velocity=1e-2)
DELAY_STEPS = 3
#: Yaw turn: angle (rad), duration (s) and start (s). The turn needs about 1.5 times the yaw torque that the
#: rotors give at hover, so where the yaw torque limit lies (the rotor torque coefficient kq) decides the result.
YAW_TURN_RAD = np.pi
YAW_TURN_S = 0.2
YAW_TURN_START_S = 1.0
KINDS = ("hover", "figure8", "minsnap", "yaw_turn")


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
    kind: str                                  # "hover", "figure8", "minsnap" or "yaw_turn"
    duration_s: float                          # flight time, s
    x0: tuple[float, ...]                      # (12,) initial state (state order x..vz, NED)
    height_m: float = HOVER_HEIGHT_M           # reference height, m (NED z = -height)
    period_s: float | None = None              # figure-8 period, s
    amplitude_m: float = FIGURE8_AMPLITUDE_M   # figure-8 amplitude A, m
    path_seed: int | None = None               # minimum-snap waypoint seed
    fidelity: Fidelity = NOMINAL               # unmodelled effects in the simulator
    payload_kg: float = 0.0                    # extra mass carried, kg
    wind: WindGusts | None = None              # wind acceleration, or none
    impulse: GustImpulse | None = None         # one gust impulse, or none
    noise: NoiseModel | None = None            # measurement noise on the state the controller sees
    delay_steps: int = 0                       # control periods between computing u and applying it
    seed: int = 0                              # seeds noise and gusts
    description: str = ""

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ScenarioError(f"kind must be one of {', '.join(KINDS)}; found {self.kind!r}")
        if not (np.isfinite(self.duration_s) and self.duration_s >= DT):
            raise ScenarioError(f"duration_s must be >= {DT}; found {self.duration_s}")
        if len(self.x0) != NX or not np.all(np.isfinite(self.x0)):
            raise ScenarioError(f"x0 must hold 12 finite numbers; found {len(self.x0)}")
        if self.kind == "figure8" and not (self.period_s and self.period_s > 0):
            raise ScenarioError(f"a figure8 scenario needs period_s > 0; found {self.period_s}")
        if self.kind == "minsnap" and (self.path_seed is None or self.path_seed < 0):
            raise ScenarioError(f"a minsnap scenario needs path_seed >= 0; found {self.path_seed}")
        if self.delay_steps < 0 or self.payload_kg < 0:
            raise ScenarioError("delay_steps and payload_kg must be >= 0")

    @property
    def steps(self) -> int:
        """Number of control periods."""
        return int(round(self.duration_s / DT))

    def reference(self):
        """The reference as a flat trajectory (:mod:`mpc.trajectory`); ``ref(times) -> (K, 12)``."""
        return _trajectory(self.kind, self.height_m, self.period_s, self.amplitude_m, self.path_seed)

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

    def to_dict(self) -> dict:
        """JSON-ready description (stored with every result)."""
        return {"name": self.name, "kind": self.kind, "duration_s": self.duration_s, "x0": list(self.x0),
                "height_m": self.height_m, "period_s": self.period_s, "amplitude_m": self.amplitude_m,
                "path_seed": self.path_seed, "reference": self.reference().describe(),
                "fidelity": dataclasses.asdict(self.fidelity), "payload_kg": self.payload_kg,
                "wind": None if self.wind is None else self.wind.to_dict(),
                "impulse": None if self.impulse is None else self.impulse.to_dict(),
                "noise": None if self.noise is None else dataclasses.asdict(self.noise),
                "delay_steps": self.delay_steps, "seed": self.seed, "description": self.description}


#: Standard deviations of an ensemble member's initial-state perturbation (state order: position m, attitude rad,
#: velocity m/s, body rates rad/s): small against the scenarios' own offsets, large against rounding, so that a
#: case whose outcome depends on its start shows it.
ENSEMBLE_X0_SIGMA = (0.01, 0.01, 0.01, 0.01, 0.01, 0.01, 0.02, 0.02, 0.02, 0.02, 0.02, 0.02)


@functools.lru_cache(maxsize=64)
def _trajectory(kind, height, period, amplitude, path_seed):
    from mpc.minsnap import random_minsnap
    from mpc.trajectory import Figure8, Hover, YawTurn

    if kind == "hover":
        return Hover((0.0, 0.0, -height))
    if kind == "yaw_turn":
        return YawTurn(YAW_TURN_RAD, YAW_TURN_S, YAW_TURN_START_S, (0.0, 0.0, -height))
    if kind == "figure8":
        return Figure8(amplitude, period, height)
    return random_minsnap(path_seed, n_waypoints=RANDOM_WAYPOINTS, v_max=RANDOM_V_MAX, a_max=RANDOM_A_MAX,
                          start=(0.0, 0.0, -height))


def _start(kind, height=HOVER_HEIGHT_M, period=None, path_seed=None) -> tuple[float, ...]:
    x0 = _trajectory(kind, height, period, FIGURE8_AMPLITUDE_M, path_seed)(np.array([0.0]))[0]
    return tuple(float(v) for v in x0)


def _hover() -> Scenario:
    x0 = np.array(_start("hover"))
    x0[0:3] += HOVER_START_OFFSET_M
    x0[3:6] += np.deg2rad(HOVER_START_ATTITUDE_DEG)
    off = np.linalg.norm(HOVER_START_OFFSET_M)
    imp = GustImpulse()
    return Scenario("hover", "hover", HOVER_DURATION_S, tuple(float(v) for v in x0), impulse=imp,
                    description=f"start {off * 100:.1f} cm and 3-5 deg off a 1 m hover point; a "
                                f"{imp.peak_mps2:g} m/s^2, {imp.duration_s:g} s gust impulse at {imp.start_s:g} s; "
                                f"hold to {HOVER_DURATION_S:g} s")


def _figure8(name: str, period: float) -> Scenario:
    mean, peak = _trajectory("figure8", HOVER_HEIGHT_M, period, FIGURE8_AMPLITUDE_M, None).speeds()
    return Scenario(name, "figure8", 2 * period, _start("figure8", period=period), period_s=period,
                    description=f"two laps of a figure-8 (A = {FIGURE8_AMPLITUDE_M} m, period {period:g} s, "
                                f"mean speed {mean:.2f} m/s, peak {peak:.2f} m/s), starting on the reference")


def _random(k: int) -> Scenario:
    traj = _trajectory("minsnap", HOVER_HEIGHT_M, None, FIGURE8_AMPLITUDE_M, k)
    return Scenario(f"random-{k}", "minsnap", round(traj.duration_s + 1.0, 2), _start("minsnap", path_seed=k),
                    path_seed=k,
                    description=f"minimum-snap path from the hover point through {RANDOM_WAYPOINTS - 1} seeded "
                                f"random waypoints (seed {k}) in a 2 x 2 x 1 m box, speed <= "
                                f"{RANDOM_V_MAX:g} m/s, acceleration <= {RANDOM_A_MAX:g} m/s^2, then 1 s of hover")


def _yaw_turn() -> Scenario:
    need = 7.51 * YAW_TURN_RAD / YAW_TURN_S ** 2
    return Scenario("yaw-turn", "yaw_turn", 3.0, _start("yaw_turn"),
                    description=f"hover at 1 m and turn {np.degrees(YAW_TURN_RAD):.0f} deg in {YAW_TURN_S:g} s at "
                                f"{YAW_TURN_START_S:g} s: a peak yaw acceleration of {need:.0f} rad/s^2, beyond "
                                f"what the rotors can give, so the yaw torque limit binds")


BASE = {s.name: s for s in (_hover(), _figure8("figure8-slow", 6.0), _figure8("figure8-fast", 3.0))}
LADDER = {f"figure8-{p:.1f}s": p for p in LADDER_PERIODS_S}
#: Scenarios without variants: the speed ladder and the yaw turn (the random paths are built on demand).
EXTRA = {s.name: s for s in (*(_figure8(n, p) for n, p in LADDER.items()), _yaw_turn())}


def _variant(base: Scenario, suffix: str) -> Scenario:
    name = f"{base.name}+{suffix}"
    if suffix == "highfi":
        return dataclasses.replace(base, name=name, fidelity=HIGH_FIDELITY,
                                   description=base.description + "; high-fidelity simulator (motor lag 30 ms, "
                                                                  "rotor drag, rotor gyroscopic torque)")
    if suffix == "payload":
        kg = PAYLOAD_FRACTION * QuadParams().m
        return dataclasses.replace(base, name=name, payload_kg=kg,
                                   description=base.description + f"; +{PAYLOAD_FRACTION:.0%} payload ({kg * 1e3:.1f} g)")
    if suffix == "wind":
        return dataclasses.replace(base, name=name, wind=WindGusts(flight_duration_s=base.duration_s, seed=base.seed),
                                   description=base.description + "; steady 0.4 m/s^2 wind plus 1.5 m/s^2 gusts")
    if suffix == "noise":
        n = NOISE
        return dataclasses.replace(base, name=name, noise=n,
                                   description=base.description + f"; noise on the measured state ({n.position * 1e3:g} mm, "
                                               f"{n.attitude * 1e3:g} mrad, {n.body_rate * 1e3:g} mrad/s, "
                                               f"{n.velocity * 1e3:g} mm/s)")
    if suffix == "delay":
        return dataclasses.replace(base, name=name, delay_steps=DELAY_STEPS,
                                   description=base.description + f"; input applied {DELAY_STEPS} control periods "
                                                                  f"({DELAY_STEPS * DT * 1e3:g} ms) late")
    raise ScenarioError(f"unknown scenario variant {suffix!r}; choose from {', '.join(VARIANTS)}")


VARIANTS = ("highfi", "payload", "wind", "noise", "delay")


def scenario_names() -> list[str]:
    """Every named scenario: the three bases, the speed ladder, the random paths of the main job, the variants.

    ``random-<k>`` exists for every integer ``k >= 0``; the list names those of :data:`RANDOM_SEEDS`.
    """
    return (list(BASE) + list(LADDER) + [f"random-{k}" for k in RANDOM_SEEDS] + ["yaw-turn"]
            + [f"{b}+{v}" for b in BASE for v in VARIANTS])


def ladder_names() -> list[str]:
    """The figure-8 speed ladder from slow to fast: figure8-slow, figure8-fast, then the shorter periods."""
    return ["figure8-slow", "figure8-fast", *LADDER]


def ladder_speeds() -> dict[str, float]:
    """Mean speed (lap length / period, m/s) of each rung of :func:`ladder_names`."""
    return {n: get_scenario(n).reference().speeds()[0] for n in ladder_names()}


def get_scenario(name: str, seed: int | None = None) -> Scenario:
    """The scenario called ``name`` (see :func:`scenario_names`), optionally with another seed."""
    if not isinstance(name, str):
        raise ScenarioError(f"scenario name must be a string; found {type(name).__name__}")
    base, _, suffix = name.partition("+")
    if base.startswith("random-") and base[7:].isdigit() and not suffix:
        s = _random(int(base[7:]))
    elif base in EXTRA and not suffix:
        s = EXTRA[base]
    elif base in BASE:
        s = _variant(BASE[base], suffix) if suffix else BASE[base]
    else:
        raise ScenarioError(f"unknown scenario {name!r}; choose from {', '.join(scenario_names())}, "
                            f"or random-<k> for any integer k >= 0")
    return s if seed is None else s.with_seed(seed)
