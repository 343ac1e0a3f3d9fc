"""Learning from flown flights (scenarios.studies.learn): held-out references, the flights' dataset, resume."""

from __future__ import annotations

import functools
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from scenarios.studies import learn
from scenarios.errors import ScenarioError
from scenarios.studies.learn import FlightJob, LearnSettings, flights_dataset, load_flights, save_flights
from scenarios.closed_loop.library import get_scenario
from scenarios.studies.training_refs import reference_positions
from sim.params import DT

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / learn.LEARN_DIR

# Tolerances and budgets of this module.
TOL = {
    "pieces_exact": 0.0,         # the dataset's pieces are the flights' samples, bit for bit
    "hover_thrust_rel": 1e-5,    # hover rotor speeds' thrust against m g (their noise: 1e-3 rad/s of about 1800)
    "mass_rel": 1e-12,           # a loaded model's mass against the vehicle file's
    "stage_s": 0.05,             # a stage's seconds against the work on its clock (they are kept to 0.1 s)
}
#: Size budget of the shipped study on each plant (its summary, models and flown data), bytes.
SHIPPED_BYTES_PER_PLANT = 17e6
#: Fields of learn.json that are timings (a resumed run differs there only).
TIMING_FIELDS = ("stage_seconds", "study_seconds", "wall_time_s", "date")
#: Fields of a real study's learn.json that measure compute time (a training's seconds, the SQP's per period).
MEASURED_TIMES = ("training_seconds", "solve_ms_median")
#: Seconds of work each stand-in of the fast resume tests stands for, on their stage clock: a flight, a training, a
#: curve row, an open-loop excitation flight, a run of the evaluation.
FAKE_WORK_S = {"fly": 1.0, "train": 10.0, "curve": 3.0, "open_loop": 0.5, "evaluation_run": 2.0}
#: Runs the stand-in evaluation flies.
FAKE_EVALUATION_RUNS = 4


def _hover_flight(name: str, n: int, seed: int, ref=None, vehicle=None) -> dict:
    """A synthetic flown flight of ``n`` samples of ``vehicle``: hover with small seeded noise (rotor speeds exactly
    at hover but for 1e-3 of noise), hover thrust commanded."""
    from sim.vehicles.vehicle import load_vehicle

    v = load_vehicle(vehicle)
    rng = np.random.default_rng(seed)
    x = np.zeros((n, 12))
    x[:, 2] = -1.0
    x += 1e-3 * rng.standard_normal(x.shape)
    n_hover = np.sqrt(v.m * v.params.g / (4.0 * v.kt))
    rot = n_hover + 1e-3 * rng.standard_normal((n, 4))
    cmd = np.tile([v.m * v.params.g, 0.0, 0.0, 0.0], (n - 1, 1))
    ref = x[:, 0:3] * 0.0 + np.array([0.0, 0.0, -1.0]) if ref is None else ref
    return {"name": name, "t": DT * np.arange(n), "x": x, "rotor_speed": rot, "command": cmd, "reference": ref,
            "rmse_m": 0.0, "crashed": False, "crash_reason": None, "seconds": (n - 1) * DT, "solve_ms": 1.0}


# ------------------------------------------------------------------ held-out references
def test_no_training_reference_of_the_default_study_is_an_evaluation_reference():
    from scenarios.studies.training_refs import check_held_out

    s = LearnSettings()
    refs = {}
    for i in range(s.iterations):
        for k in range(len(learn.training_refs_of(s, i))):
            name, traj, dur = FlightJob(s, "train", i, k, "nominal").reference()
            refs[name] = reference_positions(traj, dur)
    assert len(refs) == s.iterations * 6 * s.per_level
    check_held_out(refs)            # raises if any window is shared


def test_a_renamed_or_embedded_evaluation_reference_is_refused_before_training():
    sc = get_scenario("figure8-2.2s")
    fig8 = reference_positions(sc.reference(), sc.steps * DT)
    renamed = _hover_flight("it0-orbit-1-0", len(fig8), 1, ref=fig8)
    with pytest.raises(ScenarioError, match="figure8-2.2s"):
        learn._check_held_out([_hover_flight("it0-minsnap-1-0", 500, 0), renamed])
    # a piece of one second of figure8-fast inside a longer path
    fast = get_scenario("figure8-fast")
    piece = reference_positions(fast.reference(), fast.steps * DT)[200:300]
    path = np.vstack([np.tile(piece[0], (150, 1)), piece, np.tile(piece[-1], (150, 1))])
    with pytest.raises(ScenarioError, match="figure8-fast"):
        learn._check_held_out([_hover_flight("it1-orbit-2-0", len(path), 2, ref=path)])


def test_the_loop_refuses_to_train_on_flights_of_an_evaluation_reference(tmp_path, monkeypatch):
    """A flight whose recorded reference is figure8-fast under a training name stops the study before training.

    Its reference as drawn passes the check before flying; the refusal is the check of the flown flights, with its
    own message. Every later stage is a stand-in that works without files, so that the study would end without an
    error (and the test fail) if that check were gone.
    """
    import re

    fast = get_scenario("figure8-fast")
    fig8 = reference_positions(fast.reference(), fast.steps * DT)
    s = LearnSettings(iterations=1, per_level=1, controls=False)
    culprit = learn.training_refs_of(s, 0)[1].name
    trained, evaluated = [], []

    def fake_fly(job):
        ref = fig8 if job.index == 1 else None
        return _hover_flight(job.reference()[0], len(fig8), job.seed, ref=ref)

    monkeypatch.setattr(learn, "fly_flight", fake_fly)
    monkeypatch.setattr(learn, "_curve_row", lambda *a, **k: {"iteration": a[2]})
    monkeypatch.setattr(learn, "train_model", lambda *a, **k: trained.append(a) or {})
    monkeypatch.setattr(learn, "_evaluate", lambda *a, **k: evaluated.append(a) or {"label": "fake"})
    refusal = (rf"^training reference {re.escape(repr(culprit))} repeats \d+ windows of 0.25 s of the held-out "
               rf"reference 'figure8-fast': it must not enter training$")
    with pytest.raises(ScenarioError, match=refusal):
        learn.run_learn(s, tmp_path, jobs=1, progress=None)
    study = tmp_path / "highfi"
    assert [f["name"] for f in load_flights(study / "it0" / "flights.npz")][1] == culprit    # flown, then refused
    assert trained == [] and evaluated == [] and not (study / "it1" / "data.npz").exists()


# ------------------------------------------------------------------ flights as data
def test_flights_round_trip_and_become_pieces_of_equal_length(tmp_path):
    L = learn.PIECE_STEPS
    lengths = [L + 1, 2 * L + 51, L // 2, 3 * L + 1, L + 7, L + 2]   # one too short to make a piece
    flights = [_hover_flight(f"f{i}", n, i) for i, n in enumerate(lengths)]
    save_flights(tmp_path / "f.npz", flights)
    back = load_flights(tmp_path / "f.npz")
    for a, b in zip(flights, back):
        assert a.keys() == b.keys()
        for k in learn.FLIGHT_ARRAYS:
            np.testing.assert_array_equal(a[k], b[k])
    ds = flights_dataset(back)
    # pieces per flight: m // L, plus one ending at the flight's end where L does not divide m; the flight too short
    # for a piece is left out, and the splits go by position among the flights kept
    expect, kept = [], [i for i, n in enumerate(lengths) if n - 1 >= L]
    for j, i in enumerate(kept):
        m = lengths[i] - 1
        starts = list(range(0, m - L + 1, L))
        expect += [(i, j, k) for k in starts + ([m - L] if starts[-1] != m - L else [])]
    assert ds.x.shape == (len(expect), L, 12) and ds.valid is None
    for row, (i, j, k) in enumerate(expect):
        f = flights[i]
        assert np.max(np.abs(ds.x[row] - f["x"][k:k + L])) <= TOL["pieces_exact"]
        assert np.max(np.abs(ds.x_next[row] - f["x"][k + 1:k + L + 1])) <= TOL["pieces_exact"]
        assert np.max(np.abs(ds.u[row] - f["command"][k:k + L])) <= TOL["pieces_exact"]
        # the rotor speeds at the end of each period (the simulator's datasets' telemetry)
        assert np.max(np.abs(ds.rotor_speed[row] - f["rotor_speed"][k + 1:k + L + 1])) <= TOL["pieces_exact"]
        # split of the whole flight: the fifth of every SPLIT_EVERY kept to validation, the sixth to test
        assert ds.split[row] == {4: 1, 5: 2}.get(j % learn.SPLIT_EVERY, 0)
    assert ds.meta["pieces"] == {"steps": L, "count": len(expect), "flights": len(kept)}


def test_a_crashed_flight_is_left_out_and_never_empties_the_validation_or_test_split():
    """A crash cuts a flight short of one piece: it is left out, and the splits go by position among the flights
    kept, so validation and test still get theirs; flights added later never move an earlier flight's split."""
    L = learn.PIECE_STEPS
    flights = [_hover_flight(f"f{i}", L + 1, i) for i in range(7)]
    early = _hover_flight("early", L + 1, 9)
    early["x"][60:] = np.nan                        # 0.6 s of finite samples: too few for a log
    late = _hover_flight("late", L + 1, 10)
    late["x"][L // 2:] = np.nan                     # a log, but shorter than a piece
    ds_all = flights_dataset(flights)
    ds = flights_dataset(flights[:2] + [early] + flights[2:4] + [late] + flights[4:])
    np.testing.assert_array_equal(ds.x, ds_all.x)
    np.testing.assert_array_equal(ds.split, ds_all.split)
    assert list(ds.split) == [0, 0, 0, 0, 1, 2, 0]
    # more flights after: the first seven keep their splits
    more = flights_dataset(flights + [_hover_flight(f"g{i}", L + 1, 20 + i) for i in range(3)])
    np.testing.assert_array_equal(more.split[:7], ds_all.split)


# ------------------------------------------------------------------ the ctbr level
def test_ctbr_flights_keep_the_flights_and_splits_of_the_wrench_dataset():
    """The ctbr learner's flights are the wrench dataset's (the same left out, the same split by position), each
    cut before its first non-finite state, with the command in effect from every sample (the last repeated)."""
    L = learn.PIECE_STEPS
    flights = [_hover_flight(f"f{i}", L + 1 + 37 * i, i) for i in range(7)]
    late = _hover_flight("late", L + 1, 10)
    late["x"][L // 2:] = np.nan                     # a log, but shorter than a piece: left out
    cut = _hover_flight("cut", 2 * L, 11)
    cut["x"][L + 20:] = np.nan                      # a piece and more before its crash: kept, cut there
    fl = flights[:3] + [late] + flights[3:5] + [cut] + flights[5:]
    got = learn.ctbr_flights(fl)
    ds = flights_dataset(fl)
    kept = [f for f in fl if f is not late]
    by_split = {"train": [], "val": [], "test": []}
    for j, f in enumerate(kept):
        by_split[{4: "val", 5: "test"}.get(j % learn.SPLIT_EVERY, "train")].append(f["name"])
    assert {k: [f.name for f in v] for k, v in got.items()} == by_split
    assert sorted(set(ds.split.tolist())) == [0, 1, 2]
    c = next(f for f in got["train"] + got["val"] + got["test"] if f.name == "cut")
    assert len(c.x) == L + 20 and c.x_ok.all() and np.all(np.isfinite(c.x))
    f0 = got["train"][0]
    np.testing.assert_array_equal(f0.u[:-1], flights[0]["command"])
    np.testing.assert_array_equal(f0.u[-1], flights[0]["command"][-1])


def test_the_ctbr_dither_shakes_the_rates_as_the_torque_dither_does():
    """Each rate's standard deviation is the rate change the torque dither makes in one period on the vehicle's
    inertia; the thrust's is the wrench level's; the wrench level's is dither_std itself."""
    from scenarios.closed_loop.dither import dither_std, level_dither_std
    from sim.vehicles.vehicle import load_vehicle

    for name in ("crazyflie", None):
        p = load_vehicle(name).params
        w = dither_std(p)
        np.testing.assert_array_equal(level_dither_std(p, "wrench"), w)
        got = level_dither_std(p, "ctbr", 2.0)
        assert got[0] == pytest.approx(2.0 * w[0], rel=1e-15)
        np.testing.assert_allclose(got[1:], 2.0 * w[1:] * DT / np.array([p.Jxx, p.Jyy, p.Jzz]), rtol=1e-15)
    with pytest.raises(ScenarioError, match="^level must be 'wrench' or 'ctbr'"):
        level_dither_std(p, "ctatt")


def test_a_ctbr_study_has_its_own_folder_and_names_and_an_old_study_still_resumes():
    """At ctbr the study goes in PLANT_ctbr with its models named after it; at the wrench level the settings are
    stored as before the level existed (a study written then matches its settings.json)."""
    s = LearnSettings(plant="rotorpy", level="ctbr")
    assert s.tag == "rotorpy_ctbr" and s.record()["level"] == "ctbr"
    w = LearnSettings(plant="rotorpy")
    shipped = json.loads((SHIPPED / "rotorpy" / "learn.json").read_text())["settings"]
    assert w.tag == "rotorpy" and "level" not in w.record() and w.record() == shipped
    assert json.loads((SHIPPED / "rotorpy_ctbr" / "learn.json").read_text())["settings"] == s.record()
    assert learn.study_tag({"plant": "rotorpy"}) == "rotorpy"
    assert learn.study_tag({"plant": "rotorpy", "level": "ctbr"}) == "rotorpy_ctbr"
    with pytest.raises(ScenarioError, match="^--level must be one of wrench, ctbr"):
        LearnSettings(level="ctatt")


def test_the_aerodynamic_terms_are_a_setting_of_the_wrench_level_only():
    """The terms are selected by default at the wrench level and stored with the settings; at ctbr (whose model has
    no rotor speeds for them to read) the default is none, and asking for them there, or another mode, is refused
    naming the option. A study trained without them (``--aero none``) stores its settings as before the option."""
    assert LearnSettings(plant="rotorpy").record()["aero"] == "select"
    assert LearnSettings(plant="rotorpy", level="ctbr").aero == "none"
    assert "aero" not in LearnSettings(plant="rotorpy", aero="none").record()
    with pytest.raises(ScenarioError, match="^--aero must be one of none, select; found 'all'"):
        LearnSettings(aero="all")
    with pytest.raises(ScenarioError, match="^--aero select needs the wrench level"):
        LearnSettings(level="ctbr", aero="select")


def test_the_ctbr_learner_trains_on_flown_flights_and_writes_a_ctbr_model(tmp_path):
    """Nine synthetic flights become a model file at ctbr with the register of its history and its derivative graph,
    trained on the training flights and scored on the test one; the split counts and the physics' time constants
    (the vehicle file's response) are recorded."""
    from mpc.prediction.contract import check_model
    from pinn.ctbr import CTBR_HISTORY
    from pinn.flights import register_names

    L = learn.PIECE_STEPS
    flights = [_hover_flight(f"f{i}", L + 1, i) for i in range(9)]
    s = LearnSettings(plant="highfi", level="ctbr", profile="smoke")
    rec = learn.train_ctbr_model(s, flights, tmp_path, "m", 1, {"flights": 9})
    info = check_model(tmp_path / "m.onnx")
    assert info.level == "ctbr" and info.jacobian is not None
    assert tuple(info.extra_states) == register_names(CTBR_HISTORY, "ctbr")
    assert rec["flights"] == {"train": 7, "val": 1, "test": 1} and rec["level"] == "ctbr"
    physics, theta = learn.ctbr_physics(s)
    from sim.vehicles.vehicle import load_vehicle

    response = load_vehicle(None).inner_loop_at("ctbr").response()
    assert rec["rate_tau_s"] == pytest.approx(list(response.rate_tau), rel=1e-12)
    assert json.loads((tmp_path / "m.json").read_text()) == rec
    with pytest.raises(ScenarioError, match="no test flight"):
        learn.train_ctbr_model(s, flights[:5], tmp_path, "m2", 1, {})


def test_the_ctbr_open_loop_control_trains_on_an_excitation_flown_at_ctbr(tmp_path):
    """The same-minutes control at ctbr: an excitation dataset flown through the inner loop (its file's path) is
    trained with the dataset's own splits; the plant's best open-loop model at ctbr is the one trained at ctbr."""
    from mpc.prediction.contract import check_model
    from sim.identification.excitation import make_dataset

    ds = make_dataset("small", 8, 2.0, 0, level="ctbr")
    path = ds.save(tmp_path / "openloop_data.npz")
    s = LearnSettings(plant="highfi", level="ctbr", profile="smoke")
    rec = learn.train_ctbr_model(s, path, tmp_path, "open", 1, {"flights": 8})
    assert rec["flights"] == {k: int(np.sum(ds.split == i)) for i, k in enumerate(("train", "val", "test"))}
    assert check_model(tmp_path / "open.onnx").level == "ctbr"
    p = learn.LEARN_PLANTS["highfi"]
    assert p.best_open_loop_at("wrench") == p.best_open_loop and "ctbr" not in p.best_open_loop
    assert p.best_open_loop_at("ctbr").startswith("versus/ctbr/")
    assert learn.LEARN_PLANTS["crazyflie"].best_open_loop_at("ctbr") is None


def test_training_data_without_a_validation_or_test_flight_is_refused_by_name(tmp_path):
    flights = [_hover_flight(f"f{i}", learn.PIECE_STEPS + 1, i) for i in range(5)]    # no sixth: no test flight
    path = tmp_path / "data.npz"
    flights_dataset(flights).save(path)
    with pytest.raises(ScenarioError, match="no test flight"):
        learn.train_model(LearnSettings(profile="smoke"), path, tmp_path, "m", 1, {})


def test_the_crazyflie_study_flies_and_learns_its_own_vehicle():
    """The Crazyflie plant's flights become data with the Crazyflie's constants, and its runs fly the Crazyflie."""
    from sim.vehicles.vehicle import load_vehicle

    cf = load_vehicle("crazyflie")
    p = LearnSettings(plant="crazyflie").spec
    assert (p.plant, p.vehicle, p.best_open_loop) == ("rotorpy", "crazyflie", None)
    flights = [_hover_flight(f"f{i}", learn.PIECE_STEPS + 1, i, vehicle="crazyflie") for i in range(3)]
    ds = flights_dataset(flights, "crazyflie")
    assert ds.meta["vehicle"]["name"] == "crazyflie"
    # the rotors' thrust at hover speed, with the Crazyflie's kt, is its weight (the noise is 1e-3 rad/s of ~1800)
    thrust = ds.wrench[..., 0]
    assert np.max(np.abs(thrust / (cf.m * cf.params.g) - 1.0)) < TOL["hover_thrust_rel"]
    nominal = learn._load("nominal", p)
    assert nominal.params.m == pytest.approx(cf.m, rel=TOL["mass_rel"])
    from scenarios.studies.versus import versus_specs

    runs = versus_specs(p.versus, ["nominal"], members=2, ladder_members=1)
    assert {r.vehicle for r in runs["ensemble"]["nominal"]} == {"crazyflie"}
    assert {r.vehicle for rung in runs["ladder"]["nominal"].values() for r in rung} == {"crazyflie"}


def test_bad_settings_name_the_setting():
    """By its option of pinnmpc learn where it has one (the error reaches the command line as it is)."""
    for kw, word in (({"plant": "moon"}, "--plant"), ({"iterations": 0}, "--iterations"),
                     ({"per_level": 1.5}, "--per-level"), ({"dither": -1.0}, "dither"),
                     ({"profile": "long"}, "--profile"), ({"seed": -2}, "--seed"),
                     ({"curve_members": 0}, "--curve-members"), ({"members": 0}, "--members"),
                     ({"ladder_members": True}, "--ladder-members"),
                     ({"perturb_m": float("nan")}, "perturb_m")):
        with pytest.raises(ScenarioError, match=f"^{word} must be "):
            LearnSettings(**kw)


def test_the_settings_options_are_the_learn_command_s():
    """Each setting named by an option in its errors is that option of pinnmpc learn, stored in that setting."""
    from scenarios.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command").choices["learn"]
    options = {o: a.dest for a in sub._actions for o in a.option_strings}
    for name, option in learn.SETTING_OPTIONS.items():
        assert option in options and name in LearnSettings.__dataclass_fields__
        assert options[option] == ("no_controls" if name == "controls" else name)


@pytest.mark.parametrize("args,option", [
    (["--per-level", "0"], "--per-level"), (["--iterations", "0"], "--iterations"), (["--members", "0"], "--members"),
    (["--curve-members", "0"], "--curve-members"), (["--ladder-members", "0"], "--ladder-members"),
    (["--seed=-1"], "--seed"),
])
def test_bad_learn_options_are_a_one_line_error_naming_the_option(tmp_path, capsys, args, option):
    from scenarios.cli import main

    out = tmp_path / "study"
    code = main(["learn", "--plant", "highfi", "--out", str(out), "--models", str(tmp_path / "models"), *args])
    std = capsys.readouterr()
    lines = std.err.splitlines()
    assert code == 2 and len(lines) == 1 and std.out == ""
    assert lines[0].startswith(f"pinnmpc learn: error: {option} must be ") and "found" in lines[0]
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ resume (the loop's stages, fast)
class _Fakes:
    """Flying, training, the curve and the evaluation replaced by deterministic stand-ins that count their calls.

    With a ``clock`` (:class:`_WorkClock`), each stand-in moves it by its share of :data:`FAKE_WORK_S` for the work
    it does: the evaluation flies its :data:`FAKE_EVALUATION_RUNS` runs once and finds them flown after that, as the
    evaluation's sweep does.
    """

    def __init__(self, kill_at_training: int | None = None, fly_s: float = 0.0, clock=None):
        self.calls = {"fly": 0, "train": 0}
        self.kill = kill_at_training
        self.fly_s = fly_s
        self.clock = clock

    def _work(self, what: str, n: int = 1) -> None:
        if self.clock is not None:
            self.clock.t += n * FAKE_WORK_S[what]

    def fly(self, job):
        self.calls["fly"] += 1
        self._work("fly")
        time.sleep(self.fly_s)
        rng = np.random.default_rng(job.seed)
        f = _hover_flight(job.reference()[0], 450 + int(rng.integers(0, 200)), job.seed)
        f["model_flown"] = Path(job.model).name
        return f

    def train(self, settings, data_path, folder, name, threads, data):
        self.calls["train"] += 1
        self._work("train")
        if self.kill is not None and name.endswith(f"_it{self.kill}"):
            raise KeyboardInterrupt        # the study is killed while it trains this iteration
        from sim.identification.excitation import load_dataset

        ds = load_dataset(data_path)
        rec = {"name": name, "data": data, "x_sum": float(np.sum(ds.x)), "pieces": int(ds.x.shape[0])}
        (Path(folder) / f"{name}.json").write_text(json.dumps(rec))       # as train_model writes its record
        return rec

    def curve(self, settings, out, i, model, flights, jobs, progress):
        self._work("curve")
        return {"iteration": i, "model": Path(model).stem, "flights": len(flights),
                "x_sum": float(sum(np.sum(f["x"]) for f in flights))}

    def open_loop(self, regime, n, duration, seed, **kw):
        """``sim.identification.excitation.make_dataset``'s stand-in: ``n`` hover flights of ``duration`` s."""
        self._work("open_loop", n)
        return flights_dataset([_hover_flight(f"open-{k}", int(round(duration / DT)) + 1, seed + k)
                                for k in range(n)])

    def evaluate(self, s, out, models_dir, final, controls, jobs, progress, on_result=None):
        flown = out / "evaluation" / "fake_runs.json"
        if not flown.is_file():
            for k in range(FAKE_EVALUATION_RUNS):
                self._work("evaluation_run")
                if on_result is not None:
                    on_result({"run_id": f"fake-{k}"})
            flown.parent.mkdir(parents=True, exist_ok=True)
            flown.write_text(json.dumps(FAKE_EVALUATION_RUNS))
        return {"label": "fake", "final": Path(final).stem, "controls": sorted(controls)}

    def install(self, monkeypatch):
        import sim.identification.excitation

        monkeypatch.setattr(learn, "fly_flight", self.fly)
        monkeypatch.setattr(learn, "train_model", self.train)
        monkeypatch.setattr(learn, "_curve_row", self.curve)
        monkeypatch.setattr(learn, "_evaluate", self.evaluate)
        monkeypatch.setattr(sim.identification.excitation, "make_dataset", self.open_loop)
        if self.clock is not None:
            monkeypatch.setattr(learn, "_StageTimes", functools.partial(learn._StageTimes, clock=self.clock))


class _WorkClock:
    """A stage clock (seconds) that only the stand-ins of :class:`_Fakes` move, by the work they do."""

    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _without_timing(d: dict) -> dict:
    return {k: v for k, v in d.items() if k not in TIMING_FIELDS}


def test_a_study_killed_in_iteration_2_resumes_to_the_same_results(tmp_path, monkeypatch):
    s = LearnSettings(iterations=3, per_level=1, controls=False)
    whole = _Fakes()
    whole.install(monkeypatch)
    ref = learn.run_learn(s, tmp_path / "whole", jobs=1, progress=None)
    assert whole.calls == {"fly": 18, "train": 3}

    killed = _Fakes(kill_at_training=2, fly_s=0.05)     # its flights take 0.3 s per iteration
    killed.install(monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        learn.run_learn(s, tmp_path / "resumed", jobs=1, progress=None)
    assert killed.calls == {"fly": 12, "train": 2}
    before = json.loads((tmp_path / "resumed" / "highfi" / learn.STAGE_TIMES).read_text())
    assert list(before) == ["curve 0", "fly 0", "train 1", "curve 1", "fly 1"] and before["fly 1"] >= 0.3
    again = _Fakes()
    again.install(monkeypatch)
    out = learn.run_learn(s, tmp_path / "resumed", jobs=1, progress=None)
    assert again.calls == {"fly": 6, "train": 2}          # iterations 0 and 1 were not flown or trained again
    # the stages done before the kill keep the seconds of the run that did them; the study's time is their sum
    assert {k: out["stage_seconds"][k] for k in before} == before
    assert out["study_seconds"] == pytest.approx(sum(out["stage_seconds"].values()), abs=0.05)
    assert out["study_seconds"] > out["wall_time_s"]
    assert _without_timing(out) == _without_timing(ref)
    a = json.loads((tmp_path / "whole" / "highfi" / "learn.json").read_text())
    b = json.loads((tmp_path / "resumed" / "highfi" / "learn.json").read_text())
    assert _without_timing(a) == _without_timing(b)
    # the data each model learned from are the same bytes
    for i in (1, 2, 3):
        assert (tmp_path / "whole" / "highfi" / f"it{i}" / "data.npz").read_bytes() == \
            (tmp_path / "resumed" / "highfi" / f"it{i}" / "data.npz").read_bytes()


def test_a_rerun_of_a_finished_study_keeps_every_stage_s_seconds(tmp_path, monkeypatch):
    """Each stage of the first run records the work it did; a rerun that finds it all done (the evaluation too, whose
    runs it finds flown) keeps those seconds, in the summary and in the stage file."""
    s = LearnSettings(iterations=2, per_level=1)
    clock = _WorkClock()
    first = _Fakes(clock=clock)
    first.install(monkeypatch)
    out = learn.run_learn(s, tmp_path, jobs=1, progress=None)
    n_refs = len(learn.training_refs_of(s, 0))
    n_open = math.ceil(sum(f["seconds"] for i in range(s.iterations)
                           for f in load_flights(tmp_path / "highfi" / f"it{i}" / "flights.npz"))
                       / learn.OPEN_LOOP_FLIGHT_S - 1e-9)
    w = FAKE_WORK_S
    expect = {"curve 0": w["curve"], "fly 0": n_refs * w["fly"], "train 1": w["train"], "curve 1": w["curve"],
              "fly 1": n_refs * w["fly"], "train 2": w["train"], "curve 2": w["curve"],
              "controls": n_open * w["open_loop"] + n_refs * w["fly"] + 2 * w["train"],
              "evaluation": FAKE_EVALUATION_RUNS * w["evaluation_run"]}
    assert out["stage_seconds"] == pytest.approx(expect, abs=TOL["stage_s"])
    again = _Fakes(clock=clock)
    again.install(monkeypatch)
    rerun = learn.run_learn(s, tmp_path, jobs=1, progress=None)
    assert again.calls == {"fly": 0, "train": 0}
    assert rerun["stage_seconds"] == out["stage_seconds"]
    assert json.loads((tmp_path / "highfi" / learn.STAGE_TIMES).read_text()) == out["stage_seconds"]
    assert rerun["study_seconds"] == out["study_seconds"]


def test_stage_times_keep_a_finished_stage_and_time_one_that_works(tmp_path):
    """On a clock that moves only when work is done: a stage found done (by its file, or by finding all its work
    saved) keeps the seconds recorded for it; a stage that works records its own seconds, even if its file exists."""
    clock = _WorkClock()
    done = tmp_path / "done.json"
    done.write_text("{}")
    t = learn._StageTimes(tmp_path, clock=clock)
    for name, work in (("a", 5.0), ("b", 7.0), ("c", 11.0)):
        t.start(name, None)
        clock.t += work
        t.stop()
    first = dict(t.seconds)
    assert first == pytest.approx({"a": 5.0, "b": 7.0, "c": 11.0}, abs=TOL["stage_s"])
    t = learn._StageTimes(tmp_path, clock=clock)       # a rerun: "a" by its file, "b" finding its work saved
    t.start("a", done)
    clock.t += 0.3
    t.stop()
    t.start("b", None)
    clock.t += 0.3
    t.stop(found_done=True)
    t.start("c", None)                                 # redone: this run's seconds
    clock.t += 2.0
    t.stop()
    t.start("d", done)                                 # done, but never timed: this run's seconds
    clock.t += 3.0
    t.stop(found_done=True)
    assert t.seconds == pytest.approx({"a": first["a"], "b": first["b"], "c": 2.0, "d": 3.0}, abs=TOL["stage_s"])
    assert json.loads((tmp_path / learn.STAGE_TIMES).read_text()) == t.seconds


def test_learn_help_says_how_many_flights_of_figure8_fast_the_upper_bound_adds(tmp_path, monkeypatch, capsys):
    """The help's count of the upper bound's flights of figure8-fast, and of an iteration's flights, are what the code
    flies at the default --per-level."""
    import re

    from scenarios.cli import build_parser, main

    with pytest.raises(SystemExit) as e:
        main(["learn", "--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    m = re.search(r"figure8-fast itself, as many as an iteration flies, (\d+) at the default --per-level (\d+)\)",
                  text)
    assert m is not None, text
    n_upper, per_level = int(m.group(1)), int(m.group(2))
    assert build_parser().parse_args(["learn", "--plant", "highfi"]).per_level == per_level
    s = LearnSettings(per_level=per_level)
    assert f"(default {per_level}: {len(learn.training_refs_of(s, 0))} flights)" in text
    fakes = _Fakes()
    fakes.install(monkeypatch)
    flights = [_hover_flight(f"f{i}", learn.PIECE_STEPS + 1, i) for i in range(2)]
    learn._controls(s, tmp_path, flights, str(tmp_path / "final.onnx"), 1, None)
    assert fakes.calls["fly"] == n_upper == len(load_flights(tmp_path / "controls" / "upper_flights.npz"))


def test_the_curve_flies_all_members_for_the_nominal_and_final_models_and_fewer_between(tmp_path, monkeypatch):
    """The first and last rows are the evaluation's own runs (``members``); the rows between fly the first
    ``curve_members`` of those members, so that every row's runs are a prefix of the same ensemble."""
    import scenarios.sweeps.sweep

    flown = {}

    def fake_sweep(specs, out, jobs=1, progress=False):
        flown[len(flown)] = [sp.member for sp in specs]
        return [{"run_id": str(k), "rmse_position_m": 0.01 * (k + 1), "crashed": False, "error": None,
                 "solve_ms": {"median": 1.0}} for k in range(len(specs))]

    monkeypatch.setattr(scenarios.sweeps.sweep, "sweep", fake_sweep)
    s = LearnSettings(iterations=3, members=6, curve_members=4)
    rows = [learn._curve_row(s, tmp_path, i, "nominal", [], 1, None) for i in range(4)]
    assert [flown[i] for i in range(4)] == [list(range(6)), list(range(4)), list(range(4)), list(range(6))]
    assert [r["ensemble"]["runs"] for r in rows] == [6, 4, 4, 6]
    # curve_members above members flies members
    learn._curve_row(LearnSettings(iterations=3, members=3, curve_members=5), tmp_path, 1, "nominal", [], 1, None)
    assert flown[4] == [0, 1, 2]


def test_a_rerun_with_other_settings_is_refused(tmp_path, monkeypatch):
    _Fakes().install(monkeypatch)
    learn.run_learn(LearnSettings(iterations=1, per_level=1, controls=False), tmp_path, jobs=1, progress=None)
    with pytest.raises(ScenarioError, match="other settings"):
        learn.run_learn(LearnSettings(iterations=1, per_level=2, controls=False), tmp_path, jobs=1, progress=None)


# ------------------------------------------------------------------ resume (the real command, killed)
def _learn_cmd(out: Path) -> list[str]:
    return [sys.executable, "-m", "scenarios.cli", "learn", "--plant", "highfi", "--out", str(out), "--iterations",
            "1", "--per-level", "1", "--members", "2", "--curve-members", "1", "--ladder-members", "1", "--profile",
            "smoke", "--no-controls", "--jobs", "2"]


def _run_until(cmd: list[str], env: dict, line_start: str) -> None:
    """Run ``cmd`` and SIGKILL its whole process group as it prints a line starting with ``line_start``."""
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    for line in proc.stdout:
        if line.startswith(line_start):
            os.killpg(proc.pid, signal.SIGKILL)
            break
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, f"never printed {line_start!r}"
    time.sleep(1.0)


@pytest.mark.slow
def test_pinnmpc_learn_killed_twice_and_rerun_equals_an_uninterrupted_run(tmp_path):
    """The real command (one iteration, the smoke profile: about 5 minutes of two processes), killed with SIGKILL
    as iteration 1's training starts (the rerun trains on the flights already flown), then again as the evaluation
    starts (the rerun reuses the trained model and the curve), and run to the end. The same kill points with more
    iterations are held by the faked study above."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    subprocess.run(_learn_cmd(tmp_path / "whole"), check=True, cwd=ROOT, env=env, capture_output=True)
    killed, folder = _learn_cmd(tmp_path / "killed"), tmp_path / "killed" / "highfi"
    done = []
    for line_start, stages in (("iteration 1: training", ["curve 0", "fly 0"]),
                               ("evaluation:", ["curve 0", "fly 0", "train 1", "curve 1"])):
        _run_until(killed, env, line_start)
        assert not (folder / "learn.json").exists()
        done.append(json.loads((folder / learn.STAGE_TIMES).read_text()))
        assert list(done[-1]) == stages
    subprocess.run(killed, check=True, cwd=ROOT, env=env, capture_output=True)
    a = json.loads((tmp_path / "whole" / "highfi" / "learn.json").read_text())
    b = json.loads((tmp_path / "killed" / "highfi" / "learn.json").read_text())

    def strip(d):
        """Without the fields that time something (wall times, compute times per period)."""
        if isinstance(d, dict):
            return {k: strip(v) for k, v in d.items() if k not in TIMING_FIELDS + MEASURED_TIMES}
        return [strip(v) for v in d] if isinstance(d, list) else d

    assert strip(a) == strip(b)
    assert strip(a)["curve"][1]["ensemble"]["median"] is not None
    # each rerun kept the stages done before its kill (their seconds are those of the run that did them)
    assert {k: b["stage_seconds"][k] for k in done[1]} == done[1]
    assert {k: done[1][k] for k in done[0]} == done[0]


# ------------------------------------------------------------------ the report's section
def _ens(median, lo, hi, runs=10, crashes=0):
    return {"runs": runs, "crashes": crashes, "median": median, "median_ci95": [lo, hi]}


def _study(final_mm: float, apart: bool) -> dict:
    frac = 1.0 - final_mm / 40.0
    ladder = {"max_speed": {"speed_mps": 2.29}}
    return {
        "plant": "highfi", "settings": {"members": 10}, "wall_time_s": 1800.0, "date": "2026-11-26",
        "curve": [{"iteration": 0, "model": "nominal", "flights": 0, "flight_minutes": 0.0,
                   "ensemble": _ens(0.040, 0.039, 0.041)},
                  {"iteration": 1, "model": "learn_highfi_it1", "flights": 18, "flight_minutes": 3.2,
                   "ensemble": _ens(1e-3 * final_mm, 1e-3 * final_mm - 1e-3, 1e-3 * final_mm + 1e-3)}],
        "evaluation": {
            "label": "our high-fidelity plant", "scenario": "figure8-fast+highfi",
            "roles": {"nominal": "nominal equations", "learn_highfi_it1": "final learned model"},
            "models": {"nominal": {"ensemble": _ens(0.040, 0.039, 0.041), "versus_nominal": None, "ladder": ladder},
                       "learn_highfi_it1": {"ensemble": _ens(1e-3 * final_mm, 0.0, 1.0), "ladder": ladder,
                                            "versus_nominal": {"fraction": frac, "fraction_ci95": [frac - 0.01,
                                                                                                   frac + 0.01],
                                                               "apart": apart}}},
            "verdict": {"model": "learn_highfi_it1", "fraction": frac, "fraction_ci95": [frac - 0.01, frac + 0.01],
                        "apart": apart, "goal": 0.5, "max_speed_mps": 2.29, "nominal_max_speed_mps": 2.29,
                        "ladder_ok": True, "met": bool(frac >= 0.5 and apart)}}}


def test_the_report_section_states_the_goal_with_its_numbers(tmp_path):
    from reports.build import _figure_md
    from reports.sections.learn import learn_section

    met = learn_section({"highfi": _study(18.0, True)}, tmp_path, _figure_md)
    assert "18.0 mm against 40.0 mm, 55 % better" in met and "20.0 mm with the intervals apart, is met" in met
    assert (tmp_path / "figures" / "learning_curve.png").is_file()
    missed = learn_section({"highfi": _study(24.0, True)}, tmp_path, _figure_md)
    assert "24.0 mm against 40.0 mm, 40 % better" in missed and "is missed" in missed
    assert "| 1 | `learn_highfi_it1` | 18 | 3.2 | 24.0 (23.0–25.0) | 0/10 |" in missed
    assert "(`figure8-fast+highfi`; 10 members, 30 min on two cores" in missed
    # a study whose middle rows flew fewer members says so, with its ladder's members
    st = _study(24.0, True)
    st["settings"] = {"members": 10, "curve_members": 5, "ladder_members": 3, "iterations": 3}
    text = learn_section({"highfi": st}, tmp_path, _figure_md)
    assert "(`figure8-fast+highfi`; 10 members (5 for the models between), 3 per ladder rung, 30 min" in text


def test_the_report_states_the_final_models_aerodynamic_terms(tmp_path):
    """A study trained with the term library names its final model's terms, each trained value beside the identified
    one and its interval; one whose selection claimed none says so; one trained without the library says nothing."""
    from reports.build import _figure_md
    from reports.sections.learn import learn_section

    st = {**_study(18.0, True), "final_model": "learn_highfi_it1"}
    assert "Aerodynamic terms" not in learn_section({"highfi": st}, tmp_path, _figure_md)
    aero = {"validation_rmse_none": 0.7183, "validation_rmse": 0.7031, "terms": ["rotor_drag"],
            "coefficients": {"k_r": 0.018181}, "units": {"k_r": "1/(s RU)"},
            "identified": {"k_r": {"value": 0.017641, "low": 0.017621, "high": 0.017662}}}
    st["trainings"] = [{"name": "learn_highfi_it1", "aero": aero}]
    text = learn_section({"highfi": st}, tmp_path, _figure_md)
    assert ("Aerodynamic terms of `learn_highfi_it1` (rotor_drag; selected on its validation flights, one-step "
            "acceleration error 0.718 → 0.703 m/s²): k_r 0.01818 1/(s RU) (identified 0.01764, 95 % "
            "0.01762–0.01766).") in text
    one_flight = {**aero, "identified": {"k_r": {"value": 0.017641, "low": None, "high": None}}}
    st["trainings"] = [{"name": "learn_highfi_it1", "aero": one_flight}]
    assert "k_r 0.01818 1/(s RU) (identified 0.01764, no interval)." in learn_section({"highfi": st}, tmp_path,
                                                                                      _figure_md)
    st["trainings"] = [{"name": "learn_highfi_it1", "aero": {**aero, "terms": []}}]
    assert "the selection claimed none (validation error 0.718 m/s² with none)" in learn_section(
        {"highfi": st}, tmp_path, _figure_md)


def test_the_report_reads_a_ctbr_study_beside_the_wrench_one_and_names_its_level(tmp_path):
    """Two studies of one plant at two levels are two studies in the report (keyed by folder name), the ctbr one
    named with its level."""
    from reports.build import _figure_md
    from reports.inputs import LEARN_KEYS
    from reports.sections.learn import learn_section

    wrench, ctbr = _study(24.0, True), {**_study(18.0, True), "level": "ctbr"}
    assert all(k in wrench for k in LEARN_KEYS)
    for name, st in (("learn_highfi.json", wrench), ("learn_highfi_ctbr.json", ctbr)):
        (tmp_path / name).write_text(json.dumps(st))
    learned = {}
    for path in sorted(tmp_path.glob("learn_*.json")):     # as the report's inputs key them
        st = json.loads(path.read_text())
        learned[learn.study_tag(st)] = st
    assert sorted(learned) == ["highfi", "highfi_ctbr"]
    text = learn_section(learned, tmp_path, _figure_md)
    assert text.count("**our high-fidelity plant**, at the `ctbr` level") == 1
    assert text.count("**our high-fidelity plant** (") == 1


# ------------------------------------------------------------------ the shipped study
SHIPPED_PLANTS = ("highfi", "rotorpy", "crazyflie", "rotorpy_ctbr", "highfi_ctbr")


@pytest.mark.parametrize("plant", SHIPPED_PLANTS)
def test_the_shipped_study_learned_from_training_references_only(plant):
    """Every flight the shipped models learned from has a reference that shares no window with an evaluation one,
    and the summary holds the curve of every iteration."""
    from mpc.prediction.contract import check_model
    from scenarios.studies.training_refs import check_held_out

    d = SHIPPED / plant
    st = json.loads((d / "learn.json").read_text())
    its = st["settings"]["iterations"]
    assert its >= 3 and [r["iteration"] for r in st["curve"]] == list(range(its + 1))
    flights = [f for i in range(its) for f in load_flights(d / f"flights_it{i}.npz")]
    assert len(flights) == its * 6 * st["settings"]["per_level"]
    # the minutes each model learned from are the flights shipped
    seconds = np.cumsum([sum(f["seconds"] for f in load_flights(d / f"flights_it{i}.npz")) for i in range(its)])
    assert [r["flight_minutes"] for r in st["curve"][1:]] == pytest.approx(list(seconds / 60.0), rel=1e-12)
    check_held_out({f["name"]: np.asarray(f["reference"], dtype=float) for f in flights})
    level = st.get("level", "wrench")
    assert learn.study_tag(st) == plant and plant == (st["plant"] if level == "wrench" else f"{st['plant']}_{level}")
    for i in range(1, its + 1):
        info = check_model(d / f"learn_{plant}_it{i}.onnx")
        assert info.jacobian is not None and info.level == level


@pytest.mark.parametrize("plant", SHIPPED_PLANTS)
def test_the_shipped_study_fits_its_size_budget(plant):
    size = sum(p.stat().st_size for p in (SHIPPED / plant).rglob("*") if p.is_file())
    assert size < SHIPPED_BYTES_PER_PLANT


def test_the_goal_line_is_half_the_nominal_rmse_in_mm():
    from reports.sections.learn import goal_mm

    assert goal_mm(_study(18.0, True)) == pytest.approx(20.0, rel=1e-12)
