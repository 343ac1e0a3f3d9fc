"""Training references for learning from flown data: seeded, within their limits, and never an evaluation reference."""

import numpy as np
import pytest

from scenarios.errors import ScenarioError
from scenarios.studies.training_refs import (SPEED_LEVELS_MS, WINDOW, accel_limit, check_held_out,
                                             evaluation_references, fingerprints, reference_positions,
                                             training_references)

#: Tolerances: the peaks of a reference against its level, relative (the min-snap limits hold on the path's own
#: peak grid, checked here on a finer one).
TOL = {"speed_rel": 2e-3, "accel_rel": 2e-2,
       "offset_start": 1e-15,       # a perturbation's velocity at t = 0 (rounding of the cosines' sum), m/s
       "order_rel": 1e-2}           # central differences' error ratio for step h against h / 2 (4 at 2nd order)
ITERATIONS = 4


def _positions(refs):
    return {r.name: reference_positions(r.trajectory, r.duration_s) for r in refs}


def test_each_iteration_draws_its_own_seeded_references():
    a, b = training_references(1, per_level=2, seed=3), training_references(1, per_level=2, seed=3)
    assert len(a) == 2 * len(SPEED_LEVELS_MS) * 2 and [r.name for r in a] == [r.name for r in b]
    pa, pb = _positions(a), _positions(b)
    assert all(np.array_equal(pa[n], pb[n]) for n in pa)
    other = _positions(training_references(2, per_level=2, seed=3))
    assert not (set().union(*map(fingerprints, pa.values())) & set().union(*map(fingerprints, other.values())))
    assert {r.family for r in a} == {"minsnap", "orbit"}


def test_references_stay_within_their_speed_and_acceleration():
    for r in training_references(0, per_level=2):
        f = r.trajectory.flat(np.linspace(0.0, r.duration_s, 20001))
        v = np.max(np.linalg.norm(f.vel, axis=1))
        a = np.max(np.linalg.norm(f.acc, axis=1))
        assert v <= r.level_ms * (1 + TOL["speed_rel"]), r.name
        assert a <= accel_limit(r.level_ms) * (1 + TOL["accel_rel"]), r.name
        if r.family == "minsnap":      # a min-snap path is timed for its level
            assert v >= r.level_ms * (1 - TOL["speed_rel"]), r.name


def test_no_training_reference_repeats_an_evaluation_reference():
    held = evaluation_references()
    assert set(held) >= {"figure8-fast", "figure8-2.0s", "figure8-slow"}
    for it in range(ITERATIONS):
        check_held_out(_positions(training_references(it, per_level=2)), held)


def test_a_renamed_copy_and_a_piece_of_an_evaluation_reference_are_caught():
    held = evaluation_references()
    with pytest.raises(ScenarioError, match="'my-path'.*'figure8-fast'"):
        check_held_out({"my-path": held["figure8-fast"].copy()}, held)
    # One second of the 2.4 s lap inside a training path, on the same grid: caught by name.
    path = reference_positions(training_references(0)[0].trajectory, training_references(0)[0].duration_s)
    spliced = np.vstack([path[:200], held["figure8-2.4s"][100:200], path[200:]])
    with pytest.raises(ScenarioError, match="'spliced'.*'figure8-2.4s'"):
        check_held_out({"spliced": spliced}, held)
    # A window is WINDOW samples: a piece shorter than that is not a repeated window.
    short = np.vstack([path[:200], held["figure8-2.4s"][100:100 + WINDOW - 1], path[200:]])
    check_held_out({"short": short}, {"figure8-2.4s": held["figure8-2.4s"]})


def test_standing_still_is_not_a_shared_window():
    hover = np.tile([0.0, 0.0, -1.0], (300, 1))
    assert fingerprints(hover) == set()
    start = np.vstack([hover, evaluation_references()["figure8-fast"][:1] + 0.5])
    check_held_out({"hover": start}, {"hover-too": hover})


@pytest.mark.parametrize("kwargs, match", [({"iteration": -1}, "iteration must be an integer >= 0"),
                                           ({"iteration": 0, "per_level": 0}, "per_level must be an integer >= 1"),
                                           ({"iteration": 0, "seed": 1.5}, "seed must be an integer >= 0")])
def test_bad_arguments_are_named(kwargs, match):
    with pytest.raises(ScenarioError, match=match):
        training_references(**kwargs)
    with pytest.raises(ScenarioError, match=r"positions must have shape \(K, 3\)"):
        fingerprints(np.zeros((10, 12)))


def test_a_perturbed_reference_is_the_path_plus_an_offset_with_exact_derivatives():
    from scenarios.studies.training_refs import PERTURB_M, Perturbed

    ref = training_references(0)[1]
    p = Perturbed(ref.trajectory, PERTURB_M, seed=4)
    t = np.linspace(0.0, ref.duration_s, 301)
    base, mine = ref.trajectory.flat(t), p.flat(t)
    for order, name in enumerate(("pos", "vel", "acc", "jerk", "snap")):
        assert np.array_equal(getattr(mine, name), getattr(base, name) + p.offset(t, order))
    assert np.array_equal(mine.yaw, base.yaw)
    # Starts on the path, at rest relative to it; stays within the amplitude on each axis.
    assert np.array_equal(p.offset([0.0]), np.zeros((1, 3)))
    assert np.max(np.abs(p.offset([0.0], 1))) <= TOL["offset_start"]
    assert np.all(np.max(np.abs(p.offset(np.linspace(0, 60, 6001))), axis=0) <= PERTURB_M * (1 + 1e-12))
    # Each derivative is the derivative of the one before: central differences converge at second order.
    for order in range(4):
        errs = [np.max(np.abs((p.offset(t + h, order) - p.offset(t - h, order)) / (2 * h) - p.offset(t, order + 1)))
                for h in (1e-2, 5e-3)]
        assert errs[0] / errs[1] == pytest.approx(4.0, rel=TOL["order_rel"])
    # Seeded; and a perturbed training reference is still no evaluation reference.
    assert np.array_equal(Perturbed(ref.trajectory, PERTURB_M, seed=4).offset(t), p.offset(t))
    assert not np.array_equal(Perturbed(ref.trajectory, PERTURB_M, seed=5).offset(t), p.offset(t))
    check_held_out({"perturbed": reference_positions(p, ref.duration_s)})
    with pytest.raises(ScenarioError, match="amplitude_m must be a finite number >= 0"):
        Perturbed(ref.trajectory, -0.1)
