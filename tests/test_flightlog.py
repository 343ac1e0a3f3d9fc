"""Flight-log import: a flight of our own plant, written in a foreign layout with a real log's faults, comes back.

The foreign layout is the one real Crazyflie logs use: z-up world, FLU body,
xyzw quaternions, motor speeds in eRPM (6 pole pairs) in another rotor order,
3 samples of motor-to-state delay, 10 % held rows in each signal group, NaN
rows and eRPM spikes.
"""

import csv
import json
import math
import tomllib

import numpy as np
import pytest

from scenarios.cli import main
from sim import NoiseModel
from sim.errors import FlightLogError
from sim.identification.excitation import load_dataset, make_dataset
from sim.flightlogs.flightlog import read_flight
from sim.flightlogs.logformat import load_format, parse_format
from sim.params import DT
from sim.vehicles.rotors import mixer_matrix
from sim.vehicles.vehicle import load_vehicle

from foreign_logs import quat_xyzw, rot_zyx

# tolerances and fixed figures of this module
STATE_TOL = 1e-9          # imported state against the plant's, on every kept sample
WRENCH_RTOL = 1e-9        # wrench from the imported rotor speeds against the plant's, relative to its size
MIN_KEPT = 0.85           # kept measured states, as a fraction of the plant's samples
DELAY = 3                 # samples the foreign log's motors lead the state
FLOWN_SLOPE_TOL = 2e-3    # a flown flight's velocity and rates checks: slopes off 1 by at most this
ROTOR_RTOL = 1e-12        # a run's recorded rotor speeds against those allocated again from its inputs
ERPM_PER_RAD_S = 360.0 / (2.0 * math.pi)   # 6 pole pairs
T0 = 12.5                 # the foreign log's time at its first row, s
TORQUE_SLOPE_TOL = 5e-3   # torque check of a noise-free log: slopes off +-1 and explained shares off 1 by at most this

LAYOUT = """
name = "foreign-test"
[time]
column = "time_ms"
unit = "ms"
[frames]
world = "z-up"
body = "flu"
[position]
columns = ["px", "py", "pz"]
unit = "m"
[attitude]
quaternion = ["qx", "qy", "qz", "qw"]
order = "xyzw"
[velocity]
columns = ["vx", "vy", "vz"]
unit = "m/s"
frame = "world"
[rates]
columns = ["gx", "gy", "gz"]
unit = "rad/s"
[rotors]
columns = ["m1", "m2", "m3", "m4"]
unit = "erpm"
pole_pairs = 6
positions = ["front-left", "front-right", "rear-right", "rear-left"]
spin = ["cw", "ccw", "cw", "ccw"]
[airborne]
margin_s = 0.2
[delay]
search = [-5, 10]
"""
#: Log column m1..m4 holds the project's rotor 4, 1, 2, 3.
LOG_ROTOR = [3, 0, 1, 2]


@pytest.fixture(scope="module")
def plant_flight():
    """20 s of our plant flying RotorPy's Crazyflie (rotor speeds in rad/s), noise-free."""
    ds = make_dataset("small", 1, 20.0, 11, noise=NoiseModel.none(), vehicle="crazyflie")
    states = np.concatenate([ds.x[0], ds.x_next[0, -1:]])
    rotors = np.concatenate([ds.rotor_speed[0], ds.rotor_speed[0, -1:]])
    wrench = np.concatenate([ds.wrench[0], ds.wrench[0, -1:]])
    return states, rotors, wrench


def write_foreign(path, states, rotors, seed=0, held=0.10, delay=DELAY, faults=True):
    """Write the plant's flight as a foreign log; return the rows (log index) whose state was held or NaN."""
    rng = np.random.default_rng(seed)
    n = len(states)
    flip = np.array([1.0, -1.0, -1.0])
    pos, vel, rates = states[:, 0:3] * flip, states[:, 9:12] * flip, states[:, 6:9] * flip
    R_log = flip[:, None] * rot_zyx(states[:, 3:6]) * flip[None, :]     # diag(flip) R diag(flip)
    q = quat_xyzw(R_log)
    lead = np.concatenate([rotors[delay:], np.repeat(rotors[-1:], delay, axis=0)])  # logged[k] = rotor[k + d]
    erpm = lead[:, LOG_ROTOR] * ERPM_PER_RAD_S
    state = np.concatenate([pos, q, vel, rates], axis=1)
    bad_state = np.zeros(n, dtype=bool)
    if faults:
        for block, is_state in ((state, True), (erpm, False)):
            rows = np.sort(rng.choice(np.arange(1, n), int(held * n), replace=False))
            for r in rows:
                block[r] = block[r - 1]
            if is_state:
                bad_state[rows] = True
        nan_state = rng.choice(np.arange(1, n), 3, replace=False)
        state[nan_state, 3] = np.nan
        bad_state[nan_state] = True
        erpm[rng.choice(np.arange(1, n), 5, replace=False)] = np.nan
        spikes = rng.choice(np.arange(1, n), 4, replace=False)
        erpm[spikes, rng.integers(0, 4, 4)] = 6e6
    t_ms = (T0 + np.arange(n) * DT) * 1e3
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_ms", "px", "py", "pz", "qx", "qy", "qz", "qw", "vx", "vy", "vz", "gx", "gy", "gz",
                    "m1", "m2", "m3", "m4", "battery"])
        for k in range(n):
            w.writerow([repr(float(t_ms[k])), *("" if np.isnan(v) else repr(float(v)) for v in state[k]),
                        *("" if np.isnan(v) else repr(float(v)) for v in erpm[k]), "4.0"])
    return bad_state


@pytest.fixture(scope="module")
def layout(tmp_path_factory):
    path = tmp_path_factory.mktemp("fmt") / "foreign.toml"
    path.write_text(LAYOUT)
    return load_format(path)


@pytest.fixture(scope="module")
def round_trip(plant_flight, layout, tmp_path_factory):
    states, rotors, wrench = plant_flight
    path = tmp_path_factory.mktemp("logs") / "flight_a.csv"
    bad = write_foreign(path, states, rotors)
    flight = read_flight(path, layout, load_vehicle("crazyflie"))
    return flight, bad, path


def test_round_trip_recovers_the_delay_exactly(round_trip):
    flight, _, _ = round_trip
    assert flight.report.delay_samples == DELAY
    assert flight.report.delay_rss_ratio < 0.5     # the held rotor rows are filled, so the best fit is not exact


def test_round_trip_recovers_the_plant_states(round_trip, plant_flight):
    flight, bad, _ = round_trip
    states = plant_flight[0]
    idx = np.rint(flight.t / DT).astype(int)          # the log's first row is the plant's sample 0
    kept = flight.x_ok
    assert np.array_equal(kept, ~bad[idx]), "exactly the held and NaN rows are masked"
    err = np.max(np.abs(flight.x[kept] - states[idx[kept]]))
    assert err <= STATE_TOL
    assert kept.sum() >= MIN_KEPT * len(states)


def test_round_trip_rotor_speeds_give_the_plant_wrench(round_trip, plant_flight):
    flight, _, _ = round_trip
    _, rotors, wrench = plant_flight
    idx = np.rint(flight.t / DT).astype(int)
    ok = flight.rotor_ok
    assert np.max(np.abs(flight.rotor_speed[ok] - rotors[idx[ok]])) <= 1e-9 * rotors.max()
    scale = np.abs(wrench).max(axis=0)
    assert np.all(np.abs(flight.u[ok] - wrench[idx[ok]]) <= WRENCH_RTOL * scale)
    assert flight.report.spikes == 4


def test_round_trip_conversion_checks_are_near_one(round_trip):
    rep = round_trip[0].report
    assert np.allclose(rep.velocity_check["slope"], 1.0, atol=2e-3)
    assert np.allclose(rep.rates_check["slope"], 1.0, atol=2e-2)
    assert rep.warnings() == []


def test_a_wrong_frame_shows_in_the_checks(plant_flight, tmp_path):
    """Read with an FRD body, the FLU log is self-consistent in rates and attitude, but its thrust points the wrong
    way: the thrust check's slope is negative. A logger that flips one rate's sign shows in the rates check."""
    states, rotors, _ = plant_flight
    path = tmp_path / "f.csv"
    write_foreign(path, states, rotors, faults=False)
    clean = read_flight(path, parse_format(tomllib.loads(LAYOUT)), load_vehicle("crazyflie")).report
    assert clean.delay_samples == DELAY and clean.delay_rss_ratio < 1e-2
    assert abs(clean.thrust_check["slope"] - 1.0) < 1e-3
    fmt = parse_format(tomllib.loads(LAYOUT.replace('body = "flu"', 'body = "frd"')))
    rep = read_flight(path, fmt, load_vehicle("crazyflie")).report
    assert rep.thrust_check["slope"] < 0
    assert any("thrust" in w for w in rep.warnings())
    flipped = states.copy()
    flipped[:, 7] *= -1.0                          # the logger's pitch rate has the wrong sign
    write_foreign(path, flipped, rotors, faults=False)
    rep = read_flight(path, parse_format(tomllib.loads(LAYOUT)), load_vehicle("crazyflie")).report
    assert rep.rates_check["slope"][1] < -0.9
    assert rep.rates_check["slope"][0] > 0.99 and rep.rates_check["slope"][2] > 0.99
    assert any("axis y" in w for w in rep.warnings())


def test_jittered_log_is_resampled(plant_flight, layout, tmp_path):
    """Dropping every third row (a 15 ms average period): the grid samples between rows are interpolated, with an
    error of second order in the gap."""
    states, rotors, _ = plant_flight
    path = tmp_path / "full.csv"
    write_foreign(path, states, rotors, faults=False)
    lines = path.read_text().splitlines()
    thin = tmp_path / "thin.csv"
    thin.write_text("\n".join([lines[0]] + [ln for i, ln in enumerate(lines[1:]) if i % 3 != 1]) + "\n")
    flight = read_flight(thin, layout, load_vehicle("crazyflie"))
    assert "resampled" in flight.report.resampling
    idx = np.rint(flight.t / DT).astype(int)
    on_row = idx % 3 != 1
    assert np.max(np.abs(flight.x[on_row, :3] - states[idx[on_row], :3])) <= STATE_TOL
    assert np.max(np.abs(flight.x[:, :3] - states[idx, :3])) <= 1e-3    # 2 cm/s^2-ish curvature over 10 ms


# ------------------------------------------------------------------ bad logs on the command line
BAD_CASES = {
    "missing column": (lambda s: s.replace("gz", "gzz", 1), None, "'gz'"),
    "unknown unit": (None, lambda f: f.replace('unit = "erpm"', 'unit = "krpm"'), "unit"),
    "time backwards": ("swap", None, "'time_ms'"),
    "all-NaN column": ("nan_m3", None, "'m3'"),
    "unknown format key": (None, lambda f: f.replace("[delay]", "[delay]\nwindow = 3"), "'window'"),
    "header only": ("header_only", None, "no data rows"),
    # a log in ms declared as s: rows 10 s apart (it once became a thousand times more samples, all "valid")
    "ms declared as s": (None, lambda f: f.replace('unit = "ms"', 'unit = "s"'), "'time_ms' (time, unit 's')"),
    # a log in ms declared as us: 10 us apart, 4 ms long (it once said only that there was no airborne part)
    "ms declared as us": (None, lambda f: f.replace('unit = "ms"', 'unit = "us"'), "'time_ms' (time, unit 'us')"),
    # eRPM declared as rad/s: every speed far above n_max (it once said no row was "measured and fresh")
    "rotor unit": (None, lambda f: f.replace('unit = "erpm"\npole_pairs = 6', 'unit = "rad/s"'),
                   "unit 'rad/s' right"),
    # one column for all four rotors: a slope of 0.6 and no warning, once
    "one column for four rotors": (None, lambda f: f.replace('columns = ["m1", "m2", "m3", "m4"]',
                                                             'columns = ["m1", "m1", "m1", "m1"]'),
                                   "'m1' is named twice in [rotors]"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_logs_give_one_line_and_write_nothing(case, plant_flight, tmp_path, capsys):
    states, rotors, _ = plant_flight
    log = tmp_path / "flight.csv"
    write_foreign(log, states[:400], rotors[:400], faults=False)
    edit_log, edit_fmt, needle = BAD_CASES[case]
    lines = log.read_text().splitlines()
    if edit_log == "swap":
        lines[200], lines[201] = lines[201], lines[200]
    elif edit_log == "nan_m3":
        head = lines[0].split(",")
        j = head.index("m3")
        lines = [lines[0]] + [",".join("" if i == j else v for i, v in enumerate(ln.split(","))) for ln in lines[1:]]
    elif edit_log == "header_only":
        lines = lines[:1]
    elif edit_log is not None:
        lines[0] = edit_log(lines[0])
    log.write_text("\n".join(lines) + "\n")
    fmt = tmp_path / "fmt.toml"
    fmt.write_text(edit_fmt(LAYOUT) if edit_fmt else LAYOUT)
    out = tmp_path / "out" / "data.npz"
    code = main(["import", str(log), "--format", str(fmt), "--vehicle", "crazyflie", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1
    assert needle in err
    assert (str(log) in err) or (str(fmt) in err)
    assert not out.exists() and not out.parent.exists()


def _strict_json(text: str):
    """JSON as a strict parser reads it: a bare NaN or Infinity is an error."""
    def refuse(token):
        raise ValueError(f"not strict JSON: {token}")

    return json.loads(text, parse_constant=refuse)


def _import(tmp_path, log, *extra, layout=LAYOUT):
    fmt = tmp_path / "fmt.toml"
    fmt.write_text(layout)
    return main(["import", str(log), "--format", str(fmt), "--vehicle", "crazyflie", *extra])


def _edit_rows(path, edit):
    """Rewrite a CSV log with ``edit(header, rows)`` (rows as lists of cells) -> rows."""
    lines = path.read_text().splitlines()
    head = lines[0].split(",")
    rows = edit(head, [ln.split(",") for ln in lines[1:]])
    path.write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")


def test_zero_quaternion_rows_are_masked_and_nothing_non_finite_is_valid(plant_flight, tmp_path, capsys):
    """Ten rows of qx = qy = qz = qw = 0 once turned every later Euler angle into NaN, 1,641 of them flagged valid,
    and a report of bare NaN: now exactly those rows are masked, the rest of the flight is the plant's."""
    states, rotors, _ = plant_flight
    log = tmp_path / "zeros.csv"
    write_foreign(log, states, rotors, faults=False)
    zero = np.arange(500, 510)

    def zero_quaternion(head, rows):
        for r in zero:
            for c in ("qx", "qy", "qz", "qw"):
                rows[r][head.index(c)] = "0"
        return rows

    _edit_rows(log, zero_quaternion)
    out, rep = tmp_path / "d.npz", tmp_path / "r.json"
    assert _import(tmp_path, log, "--out", str(out), "--json", str(rep)) == 0, capsys.readouterr().err
    ds = load_dataset(out)
    assert all(np.all(np.isfinite(getattr(ds, k))) for k in ("x", "x_next", "u", "rotor_speed", "wrench"))
    f = _strict_json(rep.read_text())["flights"][0]
    assert f["invalid_attitude_rows"] == len(zero) and f["nonfinite_samples"] == 0
    flight = read_flight(log, parse_format(tomllib.loads(LAYOUT)), load_vehicle("crazyflie"))
    idx = np.rint(flight.t / DT).astype(int)
    assert np.array_equal(flight.x_ok, ~np.isin(idx, zero))
    assert np.max(np.abs(flight.x[flight.x_ok] - states[idx[flight.x_ok]])) <= STATE_TOL
    assert "invalid quaternions 10" in capsys.readouterr().out


def test_a_gap_in_the_timestamps_is_flagged_not_invented(plant_flight, layout, tmp_path):
    """3 s of rows removed: the grid samples inside the gap are filled but flagged invalid and counted (they were
    once "valid: state 100 %", 63 mm off, and moved the delay estimate), every valid sample is the plant's own, and
    the delay is still found."""
    states, rotors, _ = plant_flight
    log = tmp_path / "gap.csv"
    write_foreign(log, states, rotors, faults=False)
    _edit_rows(log, lambda head, rows: rows[:800] + rows[1100:])          # rows 800-1099: 8.0 s to 10.99 s
    flight = read_flight(log, layout, load_vehicle("crazyflie"))
    idx = np.rint(flight.t / DT).astype(int)
    inside = (idx >= 800) & (idx < 1100)
    assert flight.report.gap_samples == inside.sum() == 300
    rotor_inside = (idx - DELAY >= 800) & (idx - DELAY < 1100)           # rotor[k] = logged[k - d]
    assert np.array_equal(flight.x_ok, ~inside) and np.array_equal(flight.rotor_ok, ~rotor_inside)
    assert np.max(np.abs(flight.x[flight.x_ok] - states[idx[flight.x_ok]])) <= STATE_TOL
    assert flight.report.delay_samples == DELAY
    assert flight.report.valid_state_fraction == pytest.approx(1 - 300 / len(idx), abs=1e-12)
    assert "300 samples in gaps of the log" in "\n".join(flight.report.lines())


def test_unwritable_outputs_are_refused_before_any_log_is_read(plant_flight, tmp_path, capsys):
    """A folder that cannot be made (a file is in the way): one line naming the option, exit 2, nothing written;
    with a writable --out and an unwritable --json the dataset is not written either (it once was)."""
    states, rotors, _ = plant_flight
    log = tmp_path / "flight.csv"
    write_foreign(log, states[:400], rotors[:400], faults=False)
    blocker = tmp_path / "ro"
    blocker.write_text("a file, not a folder")
    ok = tmp_path / "ok.npz"
    for extra, option in ((["--out", str(blocker / "d.npz")], "--out"),
                          (["--out", str(ok), "--json", str(blocker / "r.json")], "--json")):
        capsys.readouterr()
        assert _import(tmp_path, log, *extra) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith("pinnmpc import: error:") and option in err, err
        assert not ok.exists()


def test_swapped_rotors_and_reversed_spins_show_in_the_torque_check(plant_flight, tmp_path):
    """The torque check fits the angular acceleration by the rotor speeds' torques: 1 on every axis for the right
    mapping; swapping the columns of rotors 1 and 2 and of 3 and 4 (front right with rear right, rear left with
    front left) reverses pitch and yaw, and stating every spin the other way reverses yaw. Both once gave a report
    identical to the right one."""
    states, rotors, _ = plant_flight
    log = tmp_path / "f.csv"
    write_foreign(log, states, rotors, faults=False)
    v = load_vehicle("crazyflie")
    right = read_flight(log, parse_format(tomllib.loads(LAYOUT)), v).report
    assert np.allclose(right.torque_check["slope"], 1.0, atol=TORQUE_SLOPE_TOL)
    assert min(right.torque_check["explained"]) > 1 - TORQUE_SLOPE_TOL and right.warnings() == []
    # the format's positions are front-left, front-right, rear-right, rear-left for m1..m4
    swapped = LAYOUT.replace('columns = ["m1", "m2", "m3", "m4"]', 'columns = ["m4", "m3", "m2", "m1"]')
    rep = read_flight(log, parse_format(tomllib.loads(swapped)), v).report
    assert rep.torque_check["slope"][0] == pytest.approx(1.0, abs=TORQUE_SLOPE_TOL)
    assert np.allclose(rep.torque_check["slope"][1:], -1.0, atol=TORQUE_SLOPE_TOL)
    assert [w.split("about ")[1][0] for w in rep.warnings()] == ["y", "z"]
    reversed_spins = LAYOUT.replace('spin = ["cw", "ccw", "cw", "ccw"]', 'spin = ["ccw", "cw", "ccw", "cw"]')
    rep = read_flight(log, parse_format(tomllib.loads(reversed_spins)), v).report
    assert np.allclose(rep.torque_check["slope"], [1.0, 1.0, -1.0], atol=TORQUE_SLOPE_TOL)


def test_a_log_with_reversed_spins_gets_its_yaw_torque_reversed(plant_flight, tmp_path):
    """A vehicle whose every rotor turns the other way (front right clockwise), logged and declared so: its rotor
    speeds are the ones that give the plant's wrench with the yaw torque reversed, and the import must give back
    the plant's wrench, yaw sign included (dropping the format's yaw sign passed every test once)."""
    states, rotors, wrench = plant_flight
    v = load_vehicle("crazyflie")
    M = mixer_matrix(v.params)
    M_reversed = M * np.array([1.0, 1.0, 1.0, -1.0])[:, None]
    n_sq = np.linalg.solve(M_reversed, wrench.T).T             # the speeds that fly the plant's wrench
    log = tmp_path / "reversed.csv"
    write_foreign(log, states, np.sqrt(n_sq), faults=False)
    fmt = parse_format(tomllib.loads(LAYOUT.replace('spin = ["cw", "ccw", "cw", "ccw"]',
                                                    'spin = ["ccw", "cw", "ccw", "cw"]')))
    assert fmt.yaw_sign == -1.0
    flight = read_flight(log, fmt, v)
    idx = np.rint(flight.t / DT).astype(int)
    scale = np.abs(wrench).max(axis=0)
    assert np.all(np.abs(flight.u - wrench[idx]) <= WRENCH_RTOL * scale)
    assert np.corrcoef(flight.u[:, 3], wrench[idx, 3])[0, 1] > 0.99
    assert flight.report.torque_check["slope"][2] == pytest.approx(1.0, abs=TORQUE_SLOPE_TOL)


def test_a_row_of_zeros_in_the_position_is_a_glitch_and_a_fast_smooth_path_is_not(plant_flight, layout, tmp_path):
    """A logger's rows of zeros in the position (the real logs have such rows, and height jumps of 0.3-0.5 m in one
    sample) once imported as measured: they are masked and counted as glitches, the rest of the flight is the
    plant's. The plant's own flight, and a fast circle at 3 m/s logged at 100 Hz and at 10 Hz, have none."""
    from sim.flightlogs.flightlog import _position_glitches

    states, rotors, _ = plant_flight
    log = tmp_path / "zeros.csv"
    write_foreign(log, states, rotors, faults=False)
    bad = [700, 1300, 1301]

    def zero_position(head, rows):
        for r in bad:
            for c in ("px", "py", "pz"):
                rows[r][head.index(c)] = "0.0"
        return rows

    _edit_rows(log, zero_position)
    flight = read_flight(log, layout, load_vehicle("crazyflie"))
    assert flight.report.position_glitches == len(bad)
    idx = np.rint(flight.t / DT).astype(int)
    assert np.array_equal(flight.x_ok, ~np.isin(idx, bad))
    assert np.max(np.abs(flight.x[flight.x_ok] - states[idx[flight.x_ok]])) <= STATE_TOL
    assert not _position_glitches(states[:, 0:3], DT, 0.2).any()
    for period in (0.01, 0.1):
        t = np.arange(0.0, 10.0, period)
        circle = np.c_[1.5 * np.cos(2.0 * t), 1.5 * np.sin(2.0 * t), -1.0 + 0.3 * np.sin(5.0 * t)]   # 3 m/s
        assert not _position_glitches(circle, period, 0.2).any(), period


def test_a_held_row_after_a_spike_or_a_nan_is_still_held(plant_flight, layout, tmp_path):
    """Telemetry not refreshed repeats its last values; a spike or a NaN in one column of the row before once hid it
    (the row was compared with the corrupted one). Each held row is compared with every column's last clean
    value."""
    states, rotors, _ = plant_flight
    log = tmp_path / "held.csv"
    write_foreign(log, states, rotors, faults=False)
    before = read_flight(log, layout, load_vehicle("crazyflie")).report.held_rows["rotors"]   # the log's last rows
    spike_row, nan_row = 600, 900

    def corrupt(head, rows):
        motors = slice(head.index("m1"), head.index("m4") + 1)
        for r, bad in ((spike_row, "6000000.0"), (nan_row, "")):
            rows[r][motors] = rows[r - 1][motors]        # held ...
            rows[r][head.index("m3")] = bad              # ... but for one corrupted column
            rows[r + 1][motors] = rows[r - 1][motors]    # and held again: the row to be found
        return rows

    _edit_rows(log, corrupt)
    flight = read_flight(log, layout, load_vehicle("crazyflie"))
    assert flight.report.held_rows["rotors"] == before + 2     # rows 601 and 901 repeat the last clean speeds
    assert flight.report.spikes == 1 and flight.report.nan_rows["rotors"] == 1
    idx = np.rint(flight.t / DT).astype(int)
    d = flight.report.delay_samples
    for r in (spike_row, nan_row):
        assert not flight.rotor_ok[np.flatnonzero(idx == r + 1 + d)].any()


def test_import_command_writes_a_dataset_with_validity(plant_flight, tmp_path, capsys):
    states, rotors, wrench = plant_flight
    for name, seed in (("square_1", 1), ("melon_1", 2)):
        write_foreign(tmp_path / f"{name}.csv", states, rotors, seed=seed)
    fmt = tmp_path / "fmt.toml"
    fmt.write_text(LAYOUT)
    out = tmp_path / "real.npz"
    code = main(["import", str(tmp_path / "square_1.csv"), str(tmp_path / "melon_1.csv"), "--format", str(fmt),
                 "--vehicle", "crazyflie", "--out", str(out), "--split", "test=melon*"])
    assert code == 0, capsys.readouterr().err
    ds = load_dataset(out)
    assert ds.meta["flight_names"] == ["square_1", "melon_1"]
    assert ds.split.tolist() == [0, 2]
    assert ds.meta["delay_samples"] == [DELAY, DELAY]
    pairs = ds.pairs("train")
    n_usable = int(ds.usable[0].sum())
    assert len(pairs["x"]) == n_usable
    # every usable pair is a true one-step pair of the plant: x_next is the state one period after x
    k = np.array([int(np.argmin(np.abs(states[:, 0] - xi[0]) + np.abs(states[:, 1] - xi[1]))) for xi in pairs["x"][:50]])
    assert np.max(np.abs(pairs["x_next"][:50] - states[k + 1])) <= STATE_TOL
    u_true = wrench[k]
    assert np.all(np.abs(pairs["u"][:50] - u_true) <= WRENCH_RTOL * np.abs(wrench).max(axis=0))
    assert "delay 3 samples" in capsys.readouterr().out
    # training on it is refused in one line until the training windows skip masked samples
    code = main(["train", "--arch", "proposed", "--data", str(out), "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "imported flight logs" in err
    assert not (tmp_path / "m").exists()


def test_a_split_that_matches_no_flight_is_refused(plant_flight, tmp_path, capsys):
    """--split test=melon* with no melon log once gave a dataset with 0 test flights and exit 0."""
    states, rotors, _ = plant_flight
    log = tmp_path / "square_1.csv"
    write_foreign(log, states[:400], rotors[:400], faults=False)
    out = tmp_path / "d.npz"
    assert _import(tmp_path, log, "--out", str(out), "--split", "test=melon*") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--split test=melon* matches no flight" in err and "square_1" in err
    assert not out.exists()


def test_mixer_of_reversed_spins_flips_yaw_only():
    """A log whose front-right rotor turns clockwise gets the yaw torque reversed and nothing else."""
    fmt = parse_format(tomllib.loads(LAYOUT.replace('spin = ["cw", "ccw", "cw", "ccw"]',
                                                                 'spin = ["ccw", "cw", "ccw", "cw"]')))
    assert fmt.yaw_sign == -1.0
    for name in ("nanodrone-raw", "nanodrone-processed"):          # the spins the benchmark's logs bear out
        assert load_format(name).rotors[0].startswith("m1") and load_format(name).yaw_sign == 1.0
    M = mixer_matrix(load_vehicle("crazyflie").params)
    assert M[3, 0] > 0


def test_format_errors_name_the_key():
    with pytest.raises(FlightLogError, match="'colums'"):
        parse_format(tomllib.loads(LAYOUT.replace('columns = ["px"', 'colums = ["px"')))
    with pytest.raises(FlightLogError, match="does not alternate"):
        parse_format(tomllib.loads(LAYOUT.replace('spin = ["cw", "ccw", "cw", "ccw"]',
                                                  'spin = ["cw", "cw", "ccw", "ccw"]')))


# ------------------------------------------------------------------ the real benchmark, on demand
BENCH = __import__("os").environ.get("PINNMPC_NANODRONE")


@pytest.mark.slow
@pytest.mark.skipif(not BENCH, reason="set PINNMPC_NANODRONE to a clone of nanodrone-sysid-benchmark (model_export)")
def test_the_benchmarks_raw_flights_import_as_documented(tmp_path):
    """Figures of docs/real-flights.md, from the benchmark's commit ac439dbc."""
    import json
    from pathlib import Path

    logs = sorted((Path(BENCH) / "data" / "real" / "raw" / "parquets").glob("*.parquet"))
    assert len(logs) == 21
    out = tmp_path / "real.npz"
    code = main(["import", *map(str, logs), "--format", "nanodrone-raw", "--vehicle", "crazyflie-brushless",
                 "--out", str(out), "--split", "test=melon*", "--json", str(tmp_path / "r.json")])
    assert code == 0
    rep = {f["name"].replace("_20251017", ""): f for f in json.loads((tmp_path / "r.json").read_text())["flights"]}
    assert rep["melon_run1"]["rows"] == 6995
    assert rep["multisine_run1"]["spikes"] == 2 and rep["multisine_run4"]["spikes"] == 3
    assert all(f["spikes"] == 0 for n, f in rep.items() if n not in ("multisine_run1", "multisine_run4"))
    assert all(-5 <= f["delay_samples"] <= 5 for f in rep.values())
    assert all(0.85 <= f["thrust_check"]["slope"] <= 1.2 for f in rep.values())
    ds = load_dataset(out)
    assert ds.split.tolist().count(2) == 4


# ------------------------------------------------------------------ flights flown here


def _flown(fidelity, periods=300, nan_from=None):
    """A flight of our simulator under a varying command: times, states, rotor speeds, commands."""
    from sim.params import Fidelity
    from sim.plants.plant import SimPlant

    v = load_vehicle(None)
    plant = SimPlant(v, Fidelity(**fidelity))
    x0 = np.zeros(12)
    x0[2] = -1.0
    plant.reset(x0)
    hover = plant.hover_input
    xs, ns, us = [plant.x], [plant.rotor_speed], []
    for k in range(periods):
        s = k * DT
        u = hover * np.array([1.0 + 0.05 * np.sin(3.0 * s), 0.0, 0.0, 0.0]) + np.array(
            [0.0, 2e-4 * np.sin(5.0 * s), 2e-4 * np.cos(4.0 * s), 1e-4 * np.sin(2.0 * s)])
        out = plant.advance(u)
        xs.append(out.x)
        ns.append(out.rotor_speed)
        us.append(u)
    x = np.array(xs)
    if nan_from is not None:
        x[nan_from:] = np.nan
    return v, np.arange(periods + 1) * DT, x, np.array(ns), np.array(us)


def test_a_flown_flight_becomes_a_dataset_sample_for_sample():
    from sim.flightlogs.flightlog import flights_to_dataset, flown_flight
    from sim.vehicles.rotors import wrench_from_rotor_sq

    v, t, x, n, u = _flown({"motor_tau": 0.03})
    f = flown_flight("lagged", t, x, n, v, command=u, reference=x)
    v2, t2, x2, n2, u2 = _flown({}, nan_from=150)
    g = flown_flight("crashed", t2, x2, n2, v2, command=u2)
    assert len(f.t) == len(t) and len(g.t) == 150           # cut before the first non-finite state
    for check in (f.report.velocity_check, f.report.rates_check):
        assert np.allclose(check["slope"], 1.0, atol=FLOWN_SLOPE_TOL)
    ds = flights_to_dataset([f, g], v, {"lagged": "train", "crashed": "test"})
    m = len(t) - 1
    assert np.array_equal(ds.x[0, :m], x[:-1]) and np.array_equal(ds.x_next[0, :m], x[1:])
    assert np.array_equal(ds.u[0, :m], u) and np.array_equal(ds.rotor_speed[0, :m], n[1:])  # period's end
    realized = wrench_from_rotor_sq(n[:-1] ** 2, v.params)
    assert np.max(np.abs(ds.wrench[0, :m] - realized)) <= WRENCH_RTOL * np.max(np.abs(realized))
    # With the motors lagging, the command is not the wrench the rotors give: both are kept.
    assert np.max(np.abs(ds.u[0, :m, 0] - ds.wrench[0, :m, 0])) > 1e-3 * np.max(np.abs(realized[:, 0]))
    assert ds.valid[0, :m].all() and ds.valid[1, :149].all() and not ds.valid[1, 149:].any()
    assert list(ds.split) == [0, 2] and ds.meta["flight_names"] == ["lagged", "crashed"]
    assert ds.meta["log_format"] is None and ds.meta["delay_samples"] == [0, 0]


def test_a_flown_flight_with_wrong_shapes_or_times_is_refused():
    from sim.flightlogs.flightlog import flown_flight

    v, t, x, n, u = _flown({}, periods=120)
    with pytest.raises(FlightLogError, match="bad: x must have shape"):
        flown_flight("bad", t, x[:, :6], n, v)
    with pytest.raises(FlightLogError, match="bad: the samples must be 0.01 s apart"):
        flown_flight("bad", t * 2.0, x, n, v)
    with pytest.raises(FlightLogError, match="bad: command must have shape"):
        flown_flight("bad", t, x, n, v, command=u[:, :3])
    with pytest.raises(FlightLogError, match="fewer than 100 finite samples"):
        flown_flight("bad", t, np.where(np.arange(len(t))[:, None] < 50, x, np.nan), n, v)


def test_a_runs_trace_keeps_the_plants_rotor_speeds_for_its_flight():
    from scenarios.closed_loop.runner import RunSpec, fly
    from sim.vehicles.rotors import realize

    _, tr = fly(RunSpec("hover", "lqr", "oracle"))
    p = load_vehicle(None).params
    assert tr["rotor_speed"].shape == (len(tr["t"]), 4)
    assert np.allclose(tr["rotor_speed"][0], p.n_hover, rtol=1e-12, atol=0.0)
    # Without a motor lag the rotors run at the speeds the command in effect asks for (allocated here for all
    # periods at once, which may round the last bit otherwise).
    assert np.allclose(tr["rotor_speed"][1:], np.sqrt(realize(tr["u"], p).n_sq), rtol=ROTOR_RTOL, atol=0.0)
