"""Scenarios as TOML files (scenarios.closed_loop.scenario_file, get_scenario("path.toml"))."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mpc.references.minsnap import FlatTable, minsnap_through
from mpc.references.trajectory import Hover
from scenarios import get_scenario, scenario_names
from scenarios.errors import ScenarioError
from scenarios.closed_loop.library import (HOVER_START_ATTITUDE_DEG, HOVER_START_OFFSET_M, NOISE, GustImpulse, Scenario,
                                           WindGusts)
from scenarios.closed_loop.runner import RunSpec, fly
from scenarios.closed_loop.scenario_file import load_scenario_file, rotor_load

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "scenarios" / "examples"

TOL = {
    "waypoint_m": 1e-9,          # reference position at a waypoint's time vs the waypoint
    "rest": 1e-9,                # velocity (m/s), acceleration (m/s^2), jerk (m/s^3) at the path's ends
    "fd_rel": 1e-6,              # central difference (h = 1e-5 s) of derivative k vs derivative k + 1, relative to
                                 # the latter's peak; a jump of any derivative up to snap at a knot would show here
    "x0_abs": 1e-15,             # initial state vs reference(0) + offsets
    "table_m": 1e-9,             # table reference at the sample times vs the samples (m; rad for yaw)
    "rotor_load_abs": 0.005,     # figure8-2.0s rotor load vs the 97 % the docs state
    "lqr_rmse_m": 1e-5,          # oracle + LQR on the five-waypoint file: measured 3.2e-6 m
    "sqp_rmse_m": 5e-6,          # oracle + SQP on the same: measured 1.2e-6 m
}

#: Five waypoints, segments of unequal length (2.06, 1.12, 2.10, 1.58 m) so that the time shares differ.
WAYPOINTS = [[0.0, 0.0, -1.0], [2.0, 0.0, -1.5], [2.0, 1.0, -1.0], [0.0, 1.5, -1.5], [0.0, 0.0, -1.0]]
PATH_S = 8.0
OFFSET_M = [0.02, -0.01, 0.03]
ATTITUDE_DEG = [2.0, -1.0, 4.0]

FIVE = f"""
name = "five"
waypoints = {WAYPOINTS}
path_duration_s = {PATH_S}
yaw_rad = 0.3
start_offset_m = {OFFSET_M}
start_attitude_deg = {ATTITUDE_DEG}
"""

TABLE_T = [0.0, 1.0, 2.2, 3.0, 4.5]
TABLE_X = [0.0, 0.5, 0.9, 1.0, 1.0]
TABLE_Y = [0.0, 0.1, 0.5, 0.8, 1.0]
TABLE_Z = [-1.0, -1.2, -1.2, -1.1, -1.0]
TABLE_YAW = [0.0, 0.2, 0.5, 0.6, 0.6]
TABLE = f"""
[flat]
t = {TABLE_T}
x = {TABLE_X}
y = {TABLE_Y}
z = {TABLE_Z}
yaw = {TABLE_YAW}
"""


def _write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def five_file(tmp_path_factory) -> Path:
    return _write(tmp_path_factory.mktemp("five"), FIVE, "five.toml")


@pytest.fixture(scope="module")
def five_on_path(tmp_path_factory) -> Path:
    """The five waypoints, starting on the reference (no offsets): what is measured is the tracking."""
    text = "\n".join(line for line in FIVE.splitlines() if not line.startswith("start_"))
    return _write(tmp_path_factory.mktemp("five"), text, "five-on-path.toml")


# --------------------------------------------------------------------------- waypoints

def test_five_waypoints_pass_at_their_times_from_rest_to_rest(five_file):
    s = get_scenario(str(five_file))
    assert (s.name, s.kind, s.path_duration_s, s.yaw_rad) == ("five", "waypoints", PATH_S, 0.3)
    assert s.duration_s == PATH_S + 1.0                       # default: 1 s of hover after the path
    # Times proportional to segment length, computed here independently of the library.
    w = np.array(WAYPOINTS)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(w, axis=0), axis=1))])
    knots = PATH_S * cum / cum[-1]
    ref = s.reference()
    f = ref.flat(knots)
    assert np.max(np.abs(f.pos - w)) <= TOL["waypoint_m"]
    np.testing.assert_array_equal(f.yaw, 0.3)
    for arr in (f.vel, f.acc, f.jerk):
        assert np.max(np.abs(arr[[0, -1]])) <= TOL["rest"]
    x = ref(knots)
    np.testing.assert_array_equal(x[:, 5], 0.3)
    assert np.max(np.abs(x[[0, -1], 3:5])) <= TOL["rest"] and np.max(np.abs(x[[0, -1], 6:])) <= TOL["rest"]
    # After the path: the last waypoint, held.
    np.testing.assert_array_equal(ref.flat([PATH_S + 0.5]).pos[0], w[-1])


def test_five_waypoint_reference_is_smooth_to_snap(five_file):
    ref = get_scenario(str(five_file)).reference()
    w = np.array(WAYPOINTS)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(w, axis=0), axis=1))])
    knots = PATH_S * cum / cum[-1]
    # A fine grid plus every interior knot: a central difference across a knot sees any jump.
    t = np.union1d(np.linspace(0.01, PATH_S - 0.01, 1601), knots[1:-1])
    h = 1e-5
    lo, mid, hi = ref.flat(t - h), ref.flat(t), ref.flat(t + h)
    names = ("pos", "vel", "acc", "jerk", "snap")
    for k in range(4):
        fd = (getattr(hi, names[k]) - getattr(lo, names[k])) / (2 * h)
        exact = getattr(mid, names[k + 1])
        scale = np.max(np.abs(exact))
        assert np.max(np.abs(fd - exact)) <= TOL["fd_rel"] * scale, names[k + 1]
    # The state's velocity (what the controllers track) is the derivative of its position.
    xs_lo, xs, xs_hi = ref(t - h), ref(t), ref(t + h)
    fd = (xs_hi[:, 0:3] - xs_lo[:, 0:3]) / (2 * h)
    assert np.max(np.abs(fd - xs[:, 9:12])) <= TOL["fd_rel"] * np.max(np.abs(xs[:, 9:12]))


def test_the_start_is_the_reference_plus_the_offsets(five_file):
    s = get_scenario(str(five_file))
    want = s.reference()(np.array([0.0]))[0]
    want[0:3] += OFFSET_M
    want[3:6] += np.deg2rad(ATTITUDE_DEG)
    np.testing.assert_allclose(np.array(s.x0), want, rtol=0, atol=TOL["x0_abs"])
    assert np.linalg.norm(np.array(s.x0[:3]) - WAYPOINTS[0]) == pytest.approx(np.linalg.norm(OFFSET_M))


def test_a_file_scenario_is_a_scenario_like_the_others(five_file):
    s = get_scenario(str(five_file))
    assert get_scenario(five_file) == s                     # a Path works as well as a str
    assert s.reference() is s.reference()                   # the trajectory is cached by the hashable fields
    d = json.loads(json.dumps(s.to_dict()))
    assert d["kind"] == "waypoints" and d["points_m"] == WAYPOINTS and d["path_duration_s"] == PATH_S
    assert d["reference"]["kind"] == "flat_table" and d["reference"]["duration_s"] == PATH_S
    m = s.member(2)
    assert m.seed == 2 and m.x0 != s.x0 and m.points_m == s.points_m
    np.testing.assert_array_equal(m.reference()(np.linspace(0, 9, 50)), s.reference()(np.linspace(0, 9, 50)))
    assert get_scenario(str(five_file), seed=7).seed == 7
    assert str(five_file) not in scenario_names() and "five" not in scenario_names()
    # Built-in records carry none of the new fields.
    assert "points_m" not in get_scenario("hover").to_dict()
    assert "points_m" not in get_scenario("random-1").to_dict()


def test_minsnap_through_shares_time_by_length():
    path = minsnap_through([[0, 0, -1], [3, 0, -1], [3, 1, -1]], 8.0, yaw=0.2)
    np.testing.assert_allclose(path.times, [0.0, 6.0, 8.0], rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="apart"):
        minsnap_through([[0, 0, -1], [0, 0, -1], [3, 1, -1]], 8.0)


# --------------------------------------------------------------------------- table and hover point

def test_flat_table_reproduces_its_samples(tmp_path):
    s = get_scenario(str(_write(tmp_path, TABLE)))
    assert s.kind == "table" and s.duration_s == TABLE_T[-1] + 1.0
    f = s.reference().flat(TABLE_T)
    np.testing.assert_allclose(f.pos, np.column_stack([TABLE_X, TABLE_Y, TABLE_Z]), rtol=0, atol=TOL["table_m"])
    np.testing.assert_allclose(f.yaw, TABLE_YAW, rtol=0, atol=TOL["table_m"])
    for arr in (f.vel, f.acc, f.jerk):
        assert np.max(np.abs(arr[[0, -1]])) <= TOL["rest"]
    np.testing.assert_array_equal(s.x0, s.reference()(np.array([0.0]))[0])


def test_a_table_that_starts_late_holds_its_first_sample(tmp_path):
    text = TABLE.replace(f"t = {TABLE_T}", f"t = {[v + 2.0 for v in TABLE_T]}")
    s = get_scenario(str(_write(tmp_path, text)))
    f = s.reference().flat([0.0, 1.0, 2.0, 4.2])
    np.testing.assert_array_equal(f.pos[0], [TABLE_X[0], TABLE_Y[0], TABLE_Z[0]])
    np.testing.assert_array_equal(f.vel[:2], 0.0)
    np.testing.assert_allclose(f.pos[3], [TABLE_X[2], TABLE_Y[2], TABLE_Z[2]], rtol=0, atol=TOL["table_m"])


def test_a_hover_file_equals_the_built_in_hover(tmp_path):
    text = f"""hover = [0.0, 0.0, -1.0]
start_offset_m = {list(HOVER_START_OFFSET_M)}
start_attitude_deg = {list(HOVER_START_ATTITUDE_DEG)}
[gust]
"""
    s, b = get_scenario(str(_write(tmp_path, text))), get_scenario("hover")
    t = np.linspace(0.0, 6.0, 301)
    np.testing.assert_array_equal(s.reference()(t), b.reference()(t))
    np.testing.assert_allclose(s.x0, b.x0, rtol=0, atol=TOL["x0_abs"])
    assert (s.duration_s, s.impulse, s.wind, s.noise, s.delay_steps) == (b.duration_s, b.impulse, None, None, 0)
    # At another point and heading: the built-in hover reference there.
    s = get_scenario(str(_write(tmp_path, "hover = [0.5, -0.5, -1.5]\nyaw_rad = 0.3\n", "p.toml")))
    np.testing.assert_array_equal(s.reference()(t), Hover((0.5, -0.5, -1.5), 0.3)(t))
    np.testing.assert_array_equal(s.x0, Hover((0.5, -0.5, -1.5), 0.3)(np.array([0.0]))[0])


def test_options_map_to_the_scenario_fields(tmp_path):
    text = """hover = [0, 0, -1]
duration_s = 4.0
payload_fraction = 0.25
high_fidelity = true
delay_steps = 2
seed = 3
[wind]
mean_mps2 = [0.1, 0.2, 0.0]
n_gusts = 2
[gust]
start_s = 1.0
direction = [0, 2, 0]
[noise]
position = 0.002
"""
    s = get_scenario(str(_write(tmp_path, text)))
    assert (s.duration_s, s.payload_fraction, s.high_fidelity, s.delay_steps, s.seed) == (4.0, 0.25, True, 2, 3)
    assert s.wind == WindGusts(mean=(0.1, 0.2, 0.0), n_gusts=2, flight_duration_s=4.0, seed=3)
    assert s.impulse == GustImpulse(start_s=1.0, direction=(0.0, 1.0, 0.0))
    assert (s.noise.position, s.noise.attitude, s.noise.body_rate, s.noise.velocity) == (0.002, 0.0, 0.0, 0.0)
    assert get_scenario(str(_write(tmp_path, "hover = [0, 0, -1]\nnoise = true\n", "n.toml"))).noise == NOISE
    assert get_scenario(str(_write(tmp_path, text, "w.toml")), seed=5).wind.seed == 5


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.toml")), ids=lambda p: p.name)
def test_shipped_examples_load(path):
    s = load_scenario_file(path)
    assert isinstance(s, Scenario) and s.name == path.stem and s.description
    x = s.reference()(np.arange(0.0, s.duration_s, 0.01))
    assert np.all(np.isfinite(x))


def test_shipped_examples_are_the_three_kinds():
    kinds = {load_scenario_file(p).kind for p in EXAMPLES.glob("*.toml")}
    assert kinds == {"hover", "waypoints", "table"}


def test_rotor_load_of_the_fastest_ladder_rung_and_of_a_payload():
    peak, _ = rotor_load(get_scenario("figure8-2.0s"))
    assert peak == pytest.approx(0.97, abs=TOL["rotor_load_abs"])          # docs/scenarios.md: 97 %
    assert rotor_load(get_scenario("hover"))[0] == pytest.approx(0.5, abs=1e-12)   # thrust-to-weight 2
    assert rotor_load(get_scenario("hover+payload"))[0] == pytest.approx(0.6, abs=1e-12)


# --------------------------------------------------------------------------- errors

GOOD_WP = "waypoints = [[0, 0, -1], [1, 0, -1], [1, 1, -1]]\npath_duration_s = 4.0\n"
BROKEN = {
    "no-reference": ("duration_s = 5.0\n", "one reference"),
    "two-references": ("hover = [0, 0, -1]\n" + GOOD_WP, "hover and waypoints"),
    "short-waypoint": ("waypoints = [[0, 0, -1], [1, 0, -1], [1, 2]]\npath_duration_s = 4.0\n", "waypoints[2]"),
    "one-waypoint": ("waypoints = [[0, 0, -1]]\npath_duration_s = 4.0\n", "waypoints"),
    "repeated-waypoint": ("waypoints = [[0, 0, -1], [1, 0, -1], [1, 0, -1]]\npath_duration_s = 4.0\n",
                          "waypoints[2]"),
    "no-path-duration": ("waypoints = [[0, 0, -1], [1, 0, -1]]\n", "path_duration_s"),
    "zero-path-duration": ("waypoints = [[0, 0, -1], [1, 0, -1]]\npath_duration_s = 0\n", "path_duration_s"),
    "too-fast": ("waypoints = [[0, 0, -1], [3, 0, -1], [3, 3, -1]]\npath_duration_s = 0.5\n", "path_duration_s"),
    "underground": ("waypoints = [[0, 0, -1], [1, 0, 0.5]]\npath_duration_s = 4.0\n", "waypoints[1]"),
    "unknown-key": (GOOD_WP + "speed = 2.0\n", "'speed'"),
    "two-durations": ("waypoints = [[0, 0, -1], [1, 0, -1]]\nduration = 4.0\npath_duration_s = 4.0\n",
                      "duration or path_duration_s"),
    "flat-missing-z": ("[flat]\nt = [0, 1]\nx = [0, 1]\ny = [0, 0]\n", "flat.z"),
    "flat-t-not-increasing": ("[flat]\nt = [0, 1, 1]\nx = [0, 1, 2]\ny = [0, 0, 0]\nz = [-1, -1, -1]\n", "flat.t"),
    "flat-short-column": ("[flat]\nt = [0, 1, 2]\nx = [0, 1]\ny = [0, 0, 0]\nz = [-1, -1, -1]\n", "flat.x"),
    "flat-with-yaw-rad": ("yaw_rad = 1.0\n[flat]\nt = [0, 2]\nx = [0, 1]\ny = [0, 0]\nz = [-1, -1]\n", "yaw_rad"),
    "flat-unknown-column": ("[flat]\nt = [0, 2]\nx = [0, 1]\ny = [0, 0]\nz = [-1, -1]\nvx = [0, 0]\n", "'vx'"),
    "hover-two-numbers": ("hover = [0, -1]\n", "hover"),
    "bad-offset": (GOOD_WP + "start_offset_m = [0.1, 0.0]\n", "start_offset_m"),
    "short-flight": (GOOD_WP + "duration_s = 0.0\n", "duration_s"),
    "negative-payload": (GOOD_WP + "payload_fraction = -0.1\n", "payload_fraction"),
    "fractional-delay": (GOOD_WP + "delay_steps = 1.5\n", "delay_steps"),
    "negative-seed": (GOOD_WP + "seed = -1\n", "seed"),
    "highfi-number": (GOOD_WP + "high_fidelity = 1\n", "high_fidelity"),
    "noise-word": (GOOD_WP + 'noise = "yes"\n', "noise"),
    "wind-negative-gusts": (GOOD_WP + "[wind]\nn_gusts = -1\n", "wind.n_gusts"),
    "gust-unknown-key": (GOOD_WP + "[gust]\nstrength = 3.0\n", "[gust]"),
    "gust-zero-direction": (GOOD_WP + "[gust]\ndirection = [0, 0, 0]\n", "gust.direction"),
    "empty-name": (GOOD_WP + 'name = ""\n', "name"),
    "invalid-toml": ("waypoints = [[0, 0, -1],\npath_duration_s 4\n", "not valid TOML"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_a_broken_file_names_the_file_and_the_field_on_one_line(tmp_path, case):
    text, field = BROKEN[case]
    path = _write(tmp_path, text, f"{case}.toml")
    with pytest.raises(ScenarioError) as err:
        get_scenario(str(path))
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"scenario file {str(path)!r}"), msg
    assert field in msg, msg
    assert isinstance(err.value, ValueError)


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(ScenarioError, match="nowhere.toml' does not exist"):
        get_scenario(str(tmp_path / "nowhere.toml"))


def test_too_fast_names_a_duration_that_flies(tmp_path):
    text = BROKEN["too-fast"][0]
    with pytest.raises(ScenarioError, match=r"path_duration_s >= ([0-9.]+) s") as err:
        get_scenario(str(_write(tmp_path, text)))
    need = float(err.value.args[0].rsplit("path_duration_s >= ", 1)[1].split(" s")[0])
    assert 0.5 < need < 5.0
    get_scenario(str(_write(tmp_path, text.replace("= 0.5", f"= {need}"), "ok.toml")))       # within the limit
    with pytest.raises(ScenarioError, match="too short"):
        get_scenario(str(_write(tmp_path, text.replace("= 0.5", f"= {0.97 * need}"), "no.toml")))


def test_the_file_is_read_again_when_it_changes(tmp_path):
    path = _write(tmp_path, GOOD_WP)
    assert get_scenario(str(path)).path_duration_s == 4.0
    path.write_text(GOOD_WP.replace("4.0", "6.25"))
    assert get_scenario(str(path)).path_duration_s == 6.25


def test_the_scenario_record_checks_its_point_fields():
    with pytest.raises(ScenarioError, match="path_duration_s"):
        Scenario("w", "waypoints", 5.0, (0.0,) * 12, points_m=((0.0, 0.0, -1.0), (1.0, 0.0, -1.0)))
    with pytest.raises(ScenarioError, match="times_s"):
        Scenario("t", "table", 5.0, (0.0,) * 12, points_m=((0.0, 0.0, -1.0), (1.0, 0.0, -1.0)), times_s=(0.0,))
    with pytest.raises(ScenarioError, match="does not belong"):
        Scenario("h", "hover", 5.0, (0.0,) * 12, path_duration_s=3.0)
    assert isinstance(FlatTable([0.0, 1.0], [[0, 0, -1], [1, 0, -1]]).describe(), dict)


# --------------------------------------------------------------------------- flown

@pytest.mark.parametrize("controller", ["lqr", "sqp"])
def test_a_waypoint_file_flies_on_the_oracle(five_on_path, controller, monkeypatch):
    import mpc.references.minsnap as minsnap

    solved = []

    def counted(*args, **kwargs):
        solved.append(args)
        return through(*args, **kwargs)

    through = minsnap.minsnap_through
    monkeypatch.setattr(minsnap, "minsnap_through", counted)
    result, trace = fly(RunSpec(str(five_on_path), controller, "oracle"))
    assert result["error"] is None and not result["crashed"]
    assert result["steps"] == round((PATH_S + 1.0) / 0.01)
    assert result["rmse_position_m"] <= TOL[f"{controller}_rmse_m"], result["rmse_position_m"]
    # The path is solved at most once a run (files are read once a process), not once a period.
    assert len(solved) <= 1, len(solved)
    # The run followed the file's reference.
    s = get_scenario(str(five_on_path))
    np.testing.assert_array_equal(trace["x_ref"], s.reference()(0.01 * np.arange(s.steps + 1)))


def test_duration_is_the_short_name_of_the_paths_duration(tmp_path):
    path = tmp_path / "short.toml"
    path.write_text("waypoints = [[0, 0, -1], [1, 0, -1], [1, 1, -1]]\nduration = 5.0\n")
    s = get_scenario(str(path))
    assert s.path_duration_s == 5.0 and s.duration_s == 6.0      # the flight: the path plus 1 s of hover
    with pytest.raises(ScenarioError, match="duration_s must be"):
        path.write_text("waypoints = [[0, 0, -1], [1, 0, -1]]\nduration = 4.0\nduration_s = -1\n")
        get_scenario(str(path))
