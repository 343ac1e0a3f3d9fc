"""Training references for learning from flown data, and the check that keeps the evaluation references out.

A model that learns from the flights a controller flies must never see the
references it is judged on. This module gives the references it may fly
(:func:`training_references`) and a check by content, not by name
(:func:`check_held_out`): every window of a reference's positions on the
10 ms grid is hashed, so a renamed copy, or a piece of an evaluation
reference inside a longer path, is caught.

Families (each drawn afresh for each iteration of a learning loop, seeded):

* ``minsnap``: minimum-snap paths through :data:`MINSNAP_WAYPOINTS` random
  waypoints in the 2 x 2 x 1 m box of the ``random-<k>`` scenarios, one per
  speed level of :data:`SPEED_LEVELS_MS` (peak speed at most the level, peak
  acceleration at most :func:`accel_limit` of it);
* ``orbit``: :data:`ORBIT_LAPS` laps of a random ellipse (semi-axes in
  :data:`ORBIT_AXES_M`, height in :data:`ORBIT_HEIGHT_M`), a minimum-snap path
  through :data:`ORBIT_POINTS` points per lap, timed so that its peak speed
  is each level or its peak acceleration :func:`accel_limit` of it, whichever
  is slower: loops of one sense, no figure-8.

The evaluation references (:func:`evaluation_references`) are ``figure8-fast``
and the figure-8 speed ladder.

:class:`Perturbed` adds a seeded smooth offset (at most :data:`PERTURB_M` per
axis) to a reference: excitation that the controller follows, so that the
flown inputs are not a function of the state alone.
"""

from __future__ import annotations

import hashlib
from typing import NamedTuple

import numpy as np

from mpc.references.trajectory import FlatTrajectory
from sim.params import DT

from ..errors import ScenarioError

#: Families of the training references, in the order :func:`training_references` gives them.
FAMILIES = ("minsnap", "orbit")
#: Speed levels of the training references: their peak speed, m/s. ``figure8-fast`` peaks at 2.2 m/s (7 m/s^2),
#: the ladder's fastest lap at 3.3 m/s (16 m/s^2, a rotor at 97 % of its thrust).
SPEED_LEVELS_MS = (1.0, 2.0, 3.0)
#: Waypoints of a training min-snap path (the first at the start point, 1 m above the origin).
MINSNAP_WAYPOINTS = 6
#: Peak acceleration of a min-snap path at 1.5 m/s, m/s^2 (scaled with the square of the level, at most ACCEL_CAP).
ACCEL_AT_1_5 = 4.0
ACCEL_CAP = 12.0
#: Orbits: laps, points per lap, ranges of the semi-axes (north, east) and of the height, m.
ORBIT_LAPS = 2
ORBIT_POINTS = 8
ORBIT_AXES_M = ((0.6, 1.0), (0.3, 0.8))
ORBIT_HEIGHT_M = (0.8, 1.2)
#: Seeds of the training min-snap paths start here (the scenarios ``random-<k>`` of the main job use 0, 1, 2).
SEED_BASE = 100_000
#: Samples per hashed window (0.25 s), and the least motion (m) within a window for it to count: windows of a
#: reference standing still (a hover before or after a path) are left out, since every reference has them.
WINDOW = 25
MIN_MOTION_M = 1e-3
#: Positions are rounded to this (m) before hashing; two computations of one reference agree far closer.
ROUND_M = 1e-6


class TrainingReference(NamedTuple):
    """One reference a learning loop may fly."""

    name: str             # e.g. "it2-minsnap-1.5-0"
    family: str           # "minsnap" or "orbit"
    level_ms: float       # speed level, m/s
    trajectory: object    # a flat trajectory (mpc.references.trajectory.FlatTrajectory); trajectory(times) -> (K, 12)
    duration_s: float     # length of the path, s


def accel_limit(level_ms: float) -> float:
    """Peak acceleration (m/s^2) of a training min-snap path of speed level ``level_ms`` (m/s)."""
    return min(ACCEL_CAP, ACCEL_AT_1_5 * (level_ms / 1.5) ** 2)


def references_per_iteration(per_level: int) -> int:
    """How many references :func:`training_references` gives for ``per_level`` of each family and speed level."""
    return len(FAMILIES) * len(SPEED_LEVELS_MS) * per_level


def training_references(iteration: int, per_level: int = 1, seed: int = 0) -> list[TrainingReference]:
    """The references of one iteration of a learning loop: ``per_level`` of each family and speed level.

    Parameters
    ----------
    iteration : int
        Iteration number (>= 0); each draws other references.
    per_level : int
        References per family and speed level (>= 1).
    seed : int
        Seed of the whole loop (>= 0); the same arguments give the same references.

    Returns
    -------
    list of TrainingReference
        :func:`references_per_iteration` references (``len(FAMILIES) * len(SPEED_LEVELS_MS) * per_level``),
        min-snap paths first.
    """
    from mpc.references.minsnap import minsnap_through, random_minsnap

    for name, v in (("iteration", iteration), ("per_level", per_level), ("seed", seed)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (1 if name == "per_level" else 0):
            raise ScenarioError(f"{name} must be an integer >= {1 if name == 'per_level' else 0}; found {v!r}")
    out = []
    for j, level in enumerate(SPEED_LEVELS_MS):
        for k in range(per_level):
            path_seed = SEED_BASE + ((seed * 1000 + iteration) * len(SPEED_LEVELS_MS) + j) * 1000 + k
            traj = random_minsnap(path_seed, n_waypoints=MINSNAP_WAYPOINTS, v_max=level, a_max=accel_limit(level))
            out.append(TrainingReference(f"it{iteration}-minsnap-{level:g}-{k}", "minsnap", level, traj,
                                         float(traj.duration_s)))
    for j, level in enumerate(SPEED_LEVELS_MS):
        for k in range(per_level):
            rng = np.random.default_rng([seed, iteration, j, k, 0x0B17])
            a, b = (rng.uniform(*r) for r in ORBIT_AXES_M)
            height = rng.uniform(*ORBIT_HEIGHT_M)
            phase = np.linspace(0.0, 2.0 * np.pi * ORBIT_LAPS, ORBIT_LAPS * ORBIT_POINTS + 1)
            # From the start point above the origin out to the ellipse, round it, and back.
            ring = np.stack([a * np.cos(phase), b * np.sin(phase), np.full_like(phase, -height)], -1)
            points = np.vstack([[0.0, 0.0, -1.0], ring, [0.0, 0.0, -1.0]])
            # Timed for the level as its peak speed and accel_limit(level) as its peak acceleration, whichever is
            # slower: flown k times slower, a path's speeds are 1/k and its accelerations 1/k^2 of what they were.
            v_peak, a_peak = _peaks(minsnap_through(points, 1.0), 1.0)
            traj = minsnap_through(points, max(v_peak / level, np.sqrt(a_peak / accel_limit(level))))
            out.append(TrainingReference(f"it{iteration}-orbit-{level:g}-{k}", "orbit", level, traj,
                                         float(traj.duration_s)))
    return out


def _peaks(trajectory, duration_s: float, samples: int = 2001) -> tuple[float, float]:
    """Largest speed (m/s) and acceleration (m/s^2) of a flat trajectory at ``samples`` times in ``[0, duration_s]``."""
    f = trajectory.flat(np.linspace(0.0, duration_s, samples))
    return float(np.max(np.linalg.norm(f.vel, axis=-1))), float(np.max(np.linalg.norm(f.acc, axis=-1)))


#: Reference perturbation (:class:`Perturbed`): at most this far from the path, m, per axis, as PERTURB_TERMS
#: raised-cosine terms per axis with frequencies in PERTURB_HZ.
PERTURB_M = 0.1
PERTURB_TERMS = 3
PERTURB_HZ = (0.2, 0.8)


class Perturbed(FlatTrajectory):
    """A flat trajectory plus a seeded smooth offset of its position: excitation the controller must follow.

    Each axis gets ``sum_j a_j (1 - cos(w_j t)) / 2`` with :data:`PERTURB_TERMS` terms, frequencies drawn in
    :data:`PERTURB_HZ` and amplitudes summing to at most ``amplitude_m``; the offset and its velocity are zero at
    t = 0, so the flight starts on the path. Its derivatives up to snap are exact, so the flatness map gives a
    feasible reference. The yaw is the path's.

    Parameters
    ----------
    base : FlatTrajectory
        The path.
    amplitude_m : float
        Largest offset per axis, m (>= 0).
    seed : int
        Seeds the frequencies, amplitudes and nothing else.
    """

    def __init__(self, base, amplitude_m: float = PERTURB_M, seed: int = 0):
        if not isinstance(base, FlatTrajectory):
            raise ScenarioError(f"base must be a flat trajectory; found {type(base).__name__}")
        if not (isinstance(amplitude_m, (int, float)) and np.isfinite(amplitude_m) and amplitude_m >= 0):
            raise ScenarioError(f"amplitude_m must be a finite number >= 0; found {amplitude_m!r}")
        rng = np.random.default_rng([int(seed), 0x9E27])
        self.base = base
        self.duration_s = base.duration_s
        self.omega = 2.0 * np.pi * rng.uniform(*PERTURB_HZ, size=(PERTURB_TERMS, 3))      # rad/s
        share = rng.uniform(0.5, 1.0, size=(PERTURB_TERMS, 3))
        self.amp = amplitude_m * share / share.sum(axis=0)                                  # m, summing to it

    def offset(self, times, order: int = 0) -> np.ndarray:
        """The ``order``-th time derivative (0 to 4) of the offset at ``times`` (K,): (K, 3), m/s^order."""
        t = np.asarray(times, dtype=float)[:, None, None]
        w = self.omega[None]
        if order == 0:
            terms = 0.5 * (1.0 - np.cos(w * t))
        else:   # d^n/dt^n of -cos(w t) / 2 is -w^n cos(w t + n pi / 2) / 2
            terms = -0.5 * w ** order * np.cos(w * t + 0.5 * np.pi * order)
        return np.sum(self.amp[None] * terms, axis=1)

    def flat(self, times):
        f = self.base.flat(times)
        return f._replace(pos=f.pos + self.offset(times, 0), vel=f.vel + self.offset(times, 1),
                          acc=f.acc + self.offset(times, 2), jerk=f.jerk + self.offset(times, 3),
                          snap=f.snap + self.offset(times, 4))

    def describe(self) -> dict:
        return {"kind": "Perturbed", "base": self.base.describe(), "amplitude_m": float(self.amp.sum(axis=0).max())}


def reference_positions(trajectory, duration_s: float) -> np.ndarray:
    """Positions (K, 3), m (NED), of a flat trajectory on the 10 ms grid from 0 to ``duration_s``."""
    times = np.arange(int(round(duration_s / DT)) + 1) * DT
    return np.asarray(trajectory(times), dtype=float)[:, 0:3]


def fingerprints(positions) -> set[str]:
    """Hashes of every :data:`WINDOW`-sample window of ``positions`` (K, 3) that moves (see :data:`MIN_MOTION_M`)."""
    p = np.asarray(positions, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ScenarioError(f"positions must have shape (K, 3); found {p.shape}")
    q = np.round(p / ROUND_M).astype(np.int64)
    out = set()
    for k in range(len(p) - WINDOW + 1):
        w = p[k:k + WINDOW]
        if np.max(np.linalg.norm(w - w[0], axis=1)) < MIN_MOTION_M:
            continue
        out.add(hashlib.sha256(q[k:k + WINDOW].tobytes()).hexdigest())
    return out


def evaluation_references() -> dict[str, np.ndarray]:
    """Positions (K, 3) on the 10 ms grid of each evaluation reference: ``figure8-fast`` and the speed ladder."""
    from ..closed_loop.library import get_scenario, ladder_names

    out = {}
    for name in ["figure8-fast"] + [n for n in ladder_names() if n != "figure8-fast"]:
        sc = get_scenario(name)
        out[name] = reference_positions(sc.reference(), sc.steps * DT)
    return out


def check_held_out(training: dict[str, np.ndarray], held_out: dict[str, np.ndarray] | None = None) -> None:
    """Raise :class:`ScenarioError` if any training reference shares a moving window with a held-out one.

    Parameters
    ----------
    training : dict of str to ndarray (K, 3)
        Reference positions (m, NED, on the 10 ms grid) of the flights that would enter training, by name.
    held_out : dict of str to ndarray (K, 3), optional
        The references kept out (default: :func:`evaluation_references`).
    """
    held_out = evaluation_references() if held_out is None else held_out
    prints = {name: fingerprints(p) for name, p in held_out.items()}
    for name, p in training.items():
        mine = fingerprints(p)
        for other, theirs in prints.items():
            shared = mine & theirs
            if shared:
                raise ScenarioError(f"training reference {name!r} repeats {len(shared)} windows of {WINDOW * DT:g} s "
                                    f"of the held-out reference {other!r}: it must not enter training")


__all__ = ["FAMILIES", "Perturbed", "SPEED_LEVELS_MS", "TrainingReference", "accel_limit", "check_held_out",
           "evaluation_references", "fingerprints", "reference_positions", "references_per_iteration",
           "training_references"]
