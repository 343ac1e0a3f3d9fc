"""Closed-loop scenarios as data.

A :class:`Scenario` is a frozen record: initial state, reference trajectory
(given by its flat outputs: a hover point, a figure-8 or a seeded
minimum-snap path), duration, plant options (the vehicle's high-fidelity
effects, a payload as a fraction of the vehicle's mass, wind, a gust
impulse), measurement noise, input delay, and a seed. Nothing in it is
code that runs a flight; :mod:`scenarios.closed_loop.runner` does that.

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
  suffix ``+highfi``, ``+payload``, ``+wind``, ``+steadywind``, ``+noise``, ``+delay``;
* the path of a scenario file (``*.toml``, :mod:`scenarios.closed_loop.scenario_file`,
  ``docs/scenario-files.md``): a hover point, a minimum-snap path through
  given waypoints, or a table of flat outputs, with the options above::

    from scenarios import get_scenario, scenario_names
    s = get_scenario("figure8-slow+wind")
    traj = s.reference()           # a flat trajectory; traj(times (K,)) -> (K, 12)
    mine = get_scenario("scenarios/examples/five-waypoints.toml")
"""


from __future__ import annotations

import dataclasses
import os

import numpy as np

from sim.params import DT

from ..errors import ScenarioError
from .scenario import (  # noqa: F401  (re-exported: the record and the shared defaults)
    DELAY_STEPS,
    ENSEMBLE_X0_SIGMA,
    FIGURE8_AMPLITUDE_M,
    GustImpulse,
    HOVER_DURATION_S,
    HOVER_HEIGHT_M,
    HOVER_START_ATTITUDE_DEG,
    HOVER_START_OFFSET_M,
    KINDS,
    LADDER_PERIODS_S,
    NOISE,
    PAYLOAD_FRACTION,
    POINT_KINDS,
    RANDOM_A_MAX,
    RANDOM_SEEDS,
    RANDOM_V_MAX,
    RANDOM_WAYPOINTS,
    Scenario,
    WindGusts,
    YAW_TURN_RAD,
    YAW_TURN_S,
    YAW_TURN_START_S,
    _trajectory,
)


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
#: Scenarios without variants: the speed ladder and the yaw turn (the random paths are built on demand). The
#: ladder's rungs have one: ``+highfi`` (the speed ladder on the high-fidelity plant; not in the main job's list).
EXTRA = {s.name: s for s in (*(_figure8(n, p) for n, p in LADDER.items()), _yaw_turn())}


def _variant(base: Scenario, suffix: str) -> Scenario:
    name = f"{base.name}+{suffix}"
    if suffix == "highfi":
        return dataclasses.replace(base, name=name, high_fidelity=True,
                                   description=base.description + "; high-fidelity simulator (the vehicle's motor "
                                                                  "lag, rotor drag, rotor gyroscopic torque)")
    if suffix == "payload":
        return dataclasses.replace(base, name=name, payload_fraction=PAYLOAD_FRACTION,
                                   description=base.description + f"; +{PAYLOAD_FRACTION:.0%} payload (of the "
                                                                  f"vehicle's mass)")
    if suffix == "wind":
        return dataclasses.replace(base, name=name, wind=WindGusts(flight_duration_s=base.duration_s, seed=base.seed),
                                   description=base.description + "; steady 0.4 m/s^2 wind plus 1.5 m/s^2 gusts")
    if suffix == "steadywind":
        return dataclasses.replace(base, name=name, wind=WindGusts(flight_duration_s=base.duration_s, seed=base.seed,
                                                                   n_gusts=0),
                                   description=base.description + "; steady 0.4 m/s^2 wind, no gusts")
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


VARIANTS = ("highfi", "payload", "wind", "steadywind", "noise", "delay")


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
    """The scenario called ``name`` (see :func:`scenario_names`), optionally with another seed.

    A ``name`` ending in ``.toml`` is the path of a scenario file
    (:func:`scenarios.closed_loop.scenario_file.load_scenario_file`; a ``seed`` given here
    replaces the file's).
    """
    if isinstance(name, os.PathLike):
        name = os.fspath(name)
    if not isinstance(name, str):
        raise ScenarioError(f"scenario name must be a string; found {type(name).__name__}")
    if name.lower().endswith(".toml"):
        from .scenario_file import load_scenario_file
        s = load_scenario_file(name)
        return s if seed is None else s.with_seed(seed)
    base, _, suffix = name.partition("+")
    if base.startswith("random-") and base[7:].isdigit() and not suffix:
        s = _random(int(base[7:]))
    elif base in EXTRA and not suffix:
        s = EXTRA[base]
    elif base in LADDER and suffix == "highfi":
        s = _variant(EXTRA[base], suffix)
    elif base in BASE:
        s = _variant(BASE[base], suffix) if suffix else BASE[base]
    else:
        raise ScenarioError(f"unknown scenario {name!r}; choose from {', '.join(scenario_names())}, "
                            f"random-<k> for any integer k >= 0, or a rung of the speed ladder with +highfi")
    return s if seed is None else s.with_seed(seed)
