"""Closed-loop scenarios as data (DESIGN section 10).

A :class:`Scenario` is a frozen record: initial state, reference (a hover
point or a figure-8 with analytic velocities), duration, simulator options
(fidelity, payload, wind), measurement noise, input delay, and a seed.
Nothing in it is code that runs a flight; :mod:`scenarios.runner` does that.

Names (DESIGN section 13): ``hover``, ``figure8-slow``, ``figure8-fast`` and
each with one variant suffix ``+highfi``, ``+payload``, ``+wind``,
``+noise``, ``+delay``::

    from scenarios import get_scenario, scenario_names
    s = get_scenario("figure8-slow+wind")
    ref = s.reference()            # ref(times (K,)) -> (K, 12)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from sim.params import DT, HIGH_FIDELITY, NOMINAL, NX, Fidelity, NoiseModel, QuadParams

from .errors import ScenarioError

HOVER_HEIGHT_M = 1.0
FIGURE8_AMPLITUDE_M = 0.75
#: Relative payload of the ``+payload`` variant (fraction of the vehicle mass).
PAYLOAD_FRACTION = 0.2


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
    kind: str                                  # "hover" or "figure8"
    duration_s: float                          # flight time, s
    x0: tuple[float, ...]                      # (12,) initial state (DESIGN section 3 order, NED)
    height_m: float = HOVER_HEIGHT_M           # reference height, m (NED z = -height)
    period_s: float | None = None              # figure-8 period, s
    amplitude_m: float = FIGURE8_AMPLITUDE_M   # figure-8 amplitude A, m
    fidelity: Fidelity = NOMINAL               # unmodelled effects in the simulator
    payload_kg: float = 0.0                    # extra mass carried, kg
    wind: WindGusts | None = None              # wind acceleration, or none
    noise: NoiseModel | None = None            # measurement noise on the state the controller sees
    delay_steps: int = 0                       # control periods between computing u and applying it
    seed: int = 0                              # seeds noise and gusts
    description: str = ""

    def __post_init__(self):
        if self.kind not in ("hover", "figure8"):
            raise ScenarioError(f"kind must be 'hover' or 'figure8'; found {self.kind!r}")
        if not (np.isfinite(self.duration_s) and self.duration_s >= DT):
            raise ScenarioError(f"duration_s must be >= {DT}; found {self.duration_s}")
        if len(self.x0) != NX or not np.all(np.isfinite(self.x0)):
            raise ScenarioError(f"x0 must hold 12 finite numbers; found {len(self.x0)}")
        if self.kind == "figure8" and not (self.period_s and self.period_s > 0):
            raise ScenarioError(f"a figure8 scenario needs period_s > 0; found {self.period_s}")
        if self.delay_steps < 0 or self.payload_kg < 0:
            raise ScenarioError("delay_steps and payload_kg must be >= 0")

    @property
    def steps(self) -> int:
        """Number of control periods."""
        return int(round(self.duration_s / DT))

    def reference(self):
        """``ref(times) -> (K, 12)`` with analytic velocities."""
        from mpc.controller import figure8_reference, hover_reference

        if self.kind == "hover":
            return hover_reference((0.0, 0.0, -self.height_m))
        return figure8_reference(self.amplitude_m, self.period_s, self.height_m)

    def with_seed(self, seed: int) -> "Scenario":
        """The same scenario with another seed (noise and gusts redrawn)."""
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ScenarioError(f"seed must be an integer >= 0; found {seed!r}")
        wind = None if self.wind is None else dataclasses.replace(self.wind, seed=int(seed))
        return dataclasses.replace(self, seed=int(seed), wind=wind)

    def to_dict(self) -> dict:
        """JSON-ready description (stored with every result)."""
        return {"name": self.name, "kind": self.kind, "duration_s": self.duration_s, "x0": list(self.x0),
                "height_m": self.height_m, "period_s": self.period_s, "amplitude_m": self.amplitude_m,
                "fidelity": dataclasses.asdict(self.fidelity), "payload_kg": self.payload_kg,
                "wind": None if self.wind is None else self.wind.to_dict(),
                "noise": None if self.noise is None else dataclasses.asdict(self.noise),
                "delay_steps": self.delay_steps, "seed": self.seed, "description": self.description}


def _hover() -> Scenario:
    deg = np.pi / 180
    # 0.41 m off the setpoint (0.3 m north, 0.2 m west, 0.2 m low) and a few degrees off level.
    x0 = np.zeros(NX)
    x0[0:6] = [0.3, -0.2, -0.8, 3 * deg, -3 * deg, 5 * deg]
    return Scenario("hover", "hover", 5.0, tuple(float(v) for v in x0),
                    description="start 0.41 m and 3-5 deg off a 1 m hover point, hold 5 s")


def _figure8(name: str, period: float) -> Scenario:
    from mpc.controller import figure8_reference

    x0 = figure8_reference(FIGURE8_AMPLITUDE_M, period, HOVER_HEIGHT_M)(np.array([0.0]))[0]
    return Scenario(name, "figure8", 2 * period, tuple(float(v) for v in x0), period_s=period,
                    description=f"two laps of a figure-8 (A = {FIGURE8_AMPLITUDE_M} m, period {period:g} s), "
                                f"starting on the reference")


BASE = {s.name: s for s in (_hover(), _figure8("figure8-slow", 6.0), _figure8("figure8-fast", 3.0))}


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
        return dataclasses.replace(base, name=name, noise=NoiseModel(),
                                   description=base.description + "; motion-capture/IMU noise on the measured state")
    if suffix == "delay":
        return dataclasses.replace(base, name=name, delay_steps=1,
                                   description=base.description + "; input applied one control period late")
    raise ScenarioError(f"unknown scenario variant {suffix!r}; choose from {', '.join(VARIANTS)}")


VARIANTS = ("highfi", "payload", "wind", "noise", "delay")


def scenario_names() -> list[str]:
    """Every scenario name: the three bases, then each base with each variant."""
    return list(BASE) + [f"{b}+{v}" for b in BASE for v in VARIANTS]


def get_scenario(name: str, seed: int | None = None) -> Scenario:
    """The scenario called ``name`` (see :func:`scenario_names`), optionally with another seed."""
    if not isinstance(name, str):
        raise ScenarioError(f"scenario name must be a string; found {type(name).__name__}")
    base, _, suffix = name.partition("+")
    if base not in BASE:
        raise ScenarioError(f"unknown scenario {name!r}; choose from {', '.join(scenario_names())}")
    s = _variant(BASE[base], suffix) if suffix else BASE[base]
    return s if seed is None else s.with_seed(seed)
