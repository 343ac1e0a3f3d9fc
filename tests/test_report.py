"""The report (reports.build_report) from a small synthetic results folder.

The folder is written here with known numbers in the layout ``pinnmpc run``
saves (results.json, traces/*.npz, evaluation.json, fisher.json,
provenance.json; no ablation.json), then report.md and report.html are parsed.
"""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from reports import ReportError, build_report

# ---- constants of this module ----------------------------------------------------------------
#: Section headings the report must have, in order.
HEADINGS = (
    "Dose-response: open-loop error against closed-loop failure",
    "Maximum trackable speed of the zoo",
    "Which open-loop number predicts failure",
    "The model zoo",
    "Dose-response with the state estimator",
    "Summary",
    "Table I: one-step and 100-step accuracy",
    "Table II: parameter identification and Cramér-Rao bounds",
    "Table III: ablation",
    "Table VI: identification under model mismatch",
    "Closed-loop results",
    "High-fidelity plant: models trained on its own data",
    "Learned against nominal on plants with unmodelled physics",
    "Command levels: wrench, ctbr and ctatt side by side",
    "Learning from flown flights",
    "Other plants and vehicles",
    "Real flights: the nano-drone benchmark",
    "State estimation and offset-free control",
    "Hover: settled error and gust recovery",
    "Speed ladder: maximum trackable speed",
    "Ensembles: crash probability and RMSE with intervals",
    "Real-time timing: compute time charged",
    "Headline: open-loop error against closed-loop error",
    "Trajectories and tracking error",
    "Rollout error growth",
    "Fisher information spectrum",
    "Solve time",
    "Provenance",
)
#: How the closed-loop table writes an RMSE (m) and a missing number.
RMSE_FORMAT = "{:.4f}"
MISSING = "–"
#: The closed-loop table's header starts with these cells.
TABLE_HEAD = ("scenario", "controller", "model", "RMSE (m)")
#: Control period (s) and trace lengths (periods) of the synthetic runs.
DT = 0.01
STEPS = 200
CRASH_STEP = 123
#: PNG file signature.
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: Inline base64 image tag of the HTML, and the relative reference it must not contain.
HTML_IMG = '<img src="data:image/png;base64,'
HTML_REL = 'src="figures/'
#: Required input files (a missing one raises ReportError naming it).
REQUIRED = ("results.json", "evaluation.json", "fisher.json")
#: The synthetic runs: (scenario, controller, model, rmse m, crashed, error).
RUNS = (
    ("hover", "ltv", "oracle", 0.0123, False, None),
    ("hover", "ltv", "alpha", 0.0456, False, None),
    ("hover", "ltv", "beta", 0.0789, False, None),
    ("hover", "nmpc", "oracle", 0.0111, False, None),
    ("hover", "nmpc", "alpha", 0.0222, False, None),
    ("hover", "nmpc", "beta", None, False, "ValueError: model beta | has no hover trim"),
    ("figure8-slow", "ltv", "oracle", 0.0333, False, None),
    ("figure8-slow", "ltv", "alpha", 0.0555, False, None),
    ("figure8-slow", "ltv", "beta", 1.2345, True, None),
    ("figure8-slow", "nmpc", "oracle", 0.0444, False, None),
    ("figure8-slow", "nmpc", "alpha", 0.0666, False, None),
    ("hover+wind", "ltv", "alpha", 0.0777, False, None),
)
#: 100-step open-loop position MAE of the learned models, m.
OPEN_LOOP = {"alpha": 0.004, "beta": 0.03}
#: Order of the rows in the closed-loop table (scenario, controller, model).
ROW_ORDER = [(s, c, m) for s in ("hover", "figure8-slow", "hover+wind") for c in ("nmpc", "ltv")
             for m in ("oracle", "alpha", "beta")]
CONTROLLER_LABELS = {"nmpc": "NMPC", "ltv": "LTV-MPC"}
#: The synthetic zoo study: model -> (100-step MAE m, {controller: (crashes of 10, median RMSE m or None)}, max speed).
STUDY_MODELS = {
    "fine": (0.009, {"ltv": (0, 0.03), "sqp": (0, 0.028)}, 1.69),
    "fair": (0.05, {"ltv": (2, 0.2), "sqp": (0, 0.15)}, 0.76),
    "poor": (0.07, {"ltv": (8, 0.5), "sqp": (1, 0.3)}, None),
    "bad": (0.3, {"ltv": (10, None), "sqp": (10, None)}, None),
    "awful": (2.0, {"ltv": (10, None), "sqp": (10, None)}, None),
}
#: Its predictor scores: controller -> [(candidate, AUC, AUC interval, Spearman, Spearman interval)].
STUDY_SCORES = {
    "ltv": [("rollout_100_mae_m", 0.83, [0.5, 1.0], 0.5, [-1.0, 1.0]),
            ("hover_chordal_distance", 0.97, [0.8, 1.0], 1.0, [1.0, 1.0])],
    "sqp": [("rollout_100_mae_m", 0.875, [0.6, 1.0], 1.0, [0.2, 1.0]),
            ("jacobian_error", 0.61, [0.3, 0.9], None, None)],
}


# ---- synthetic results folder ----------------------------------------------------------------
def _trace(scenario: str, rmse: float, steps: int, rng) -> dict:
    t = DT * np.arange(steps + 1)
    x_ref = np.zeros((steps + 1, 12))
    x_ref[:, 2] = -1.0
    if scenario.startswith("figure8"):
        w = 2 * np.pi / 6.0
        x_ref[:, 0] = 0.75 * np.sin(w * t)
        x_ref[:, 1] = 0.75 * np.sin(w * t) * np.cos(w * t)
    x = x_ref.copy()
    x[:, 0:3] += rmse * rng.standard_normal((steps + 1, 3)) / np.sqrt(3.0)
    return {"t": t, "x": x, "x_ref": x_ref, "x_measured": x[:-1], "u": np.zeros((steps, 4)),
            "u_command": np.zeros((steps, 4)), "solve_s": np.full(steps, 0.004),
            "iterations": np.ones(steps, dtype=np.int64), "status": np.full(steps, "optimal", dtype="<U24"),
            "solver_failed": np.zeros(steps, dtype=bool), "lqr_fallback": np.zeros(steps, dtype=bool)}


def _result(scenario, controller, model, rmse, crashed, error) -> dict:
    run_id = f"{scenario}__{controller}__{model}"
    r = {"run_id": run_id, "scenario": scenario, "controller": controller, "model": model, "error": error,
         "crashed": crashed, "crash_time_s": CRASH_STEP * DT if crashed else None,
         "crash_reason": "tilt > 80 deg" if crashed else None, "rmse_position_m": rmse,
         "max_position_error_m": None if rmse is None else 3 * rmse,
         "solve_ms": None if error else {"median": 4.0, "p95": 7.5, "max": 12.0},
         "deadline_misses": 0 if error else 2, "solver_failures": 0, "fallbacks": 0, "shifted_plan": 0,
         "steps": 0 if error else (CRASH_STEP if crashed else STEPS), "wall_time_s": 1.0, "scenario_spec": {}}
    if not error:
        r["trace"] = f"traces/{run_id}.npz"
    return r


def _evaluation() -> dict:
    models = []
    for name, pos in OPEN_LOOP.items():
        by_step = list(pos * np.linspace(0.05, 2.0, 100))
        states = ("x", "y", "z", "phi", "theta", "psi", "p", "q", "r", "vx", "vy", "vz")
        theta_true = {"m": 0.068, "Jxx": 6.86e-5, "Jyy": 9.2e-5, "Jzz": 1.366e-4, "kt": 0.01, "kq": 7.83e-4}
        models.append({
            "name": name, "architecture": "proposed" if name == "alpha" else "baseline", "recipe": name,
            "regime": "small",
            "one_step": {**{s: 1e-3 for s in states}, "position": 1e-3},
            "rollout_100": {**{s: pos for s in states}, "position": pos, "n_rollouts": 20, "n_diverged": 0,
                            "position_by_step": by_step, "horizon": 100},
            "theta": theta_true, "theta_true": theta_true,
            "theta_err_pct": {k: 0.1 for k in theta_true}, "crlb_std": {k: 1e-3 * v for k, v in theta_true.items()},
            "err_over_crlb": {k: 1.0 for k in theta_true}})
    paper = {"table1": {"proposed": {"z_1": 0.026, "phi_1": 0.0002, "z_100": 0.029, "phi_100": 0.001}},
             "table2_err_pct": {"m": 0.0, "kt": 0.0, "kq": 0.0, "Jxx": 5.0, "Jyy": 5.0, "Jzz": 5.0},
             "table3_position_mae_m": {"proposed": 0.029}}
    return {"models": models, "paper": paper}


def _fisher() -> dict:
    names = ["m", "Jxx", "Jyy", "Jzz", "kt", "kq"]
    full = {"regime": "small", "inputs": "wrench", "n_samples": 1000, "rank": 6, "parameters": names,
            "eigenvalues": [1e3, 1e4, 1e5, 1e5, 1e6, 1e7], "condition_number": 1e4,
            "crlb_pct": {n: 0.1 for n in names}}
    deficient = {"regime": "small", "inputs": "motor", "n_samples": 1000, "rank": 5, "parameters": names,
                 "eigenvalues": [0.0, 1e4, 1e5, 1e5, 1e6, 1e7], "condition_number": 1e20,
                 "crlb_pct": {n: None for n in names}}
    return {"settings": {"n_traj": 2, "duration_s": 5.0, "seed": 0, "noise": {"position": 0.001}},
            "cases": [full, deficient]}


@pytest.fixture
def results_dir(tmp_path):
    """A small results folder: 12 runs (one crashed, one that could not start), 3 scenarios."""
    rng = np.random.default_rng(7)
    d = tmp_path / "results"
    (d / "traces").mkdir(parents=True)
    runs = []
    for spec in RUNS:
        r = _result(*spec)
        runs.append(r)
        if "trace" in r:
            steps = CRASH_STEP if r["crashed"] else STEPS
            np.savez_compressed(d / r["trace"], **_trace(r["scenario"], r["rmse_position_m"], steps, rng))
    rng.shuffle(runs)   # the report must sort them itself
    (d / "results.json").write_text(json.dumps({"plan": {"full": False}, "runs": runs}))
    (d / "evaluation.json").write_text(json.dumps(_evaluation()))
    (d / "fisher.json").write_text(json.dumps(_fisher()))
    (d / "provenance.json").write_text(json.dumps({"git_commit": "0123456789abcdef", "model_sha256": {
        "alpha": "a" * 64}, "stage_seconds": {"report": 1.5}}))
    return d


def _study() -> dict:
    from scenarios.studies.stats import wilson_interval

    models = {}
    for name, (mae, ens, speed) in STUDY_MODELS.items():
        e = {}
        for c, (k, med) in ens.items():
            e[c] = {"runs": 10, "crashes": k, "crash_probability": k / 10, "crash_probability_ci95":
                    list(wilson_interval(k, 10)), "metric": "rmse_position_m", "flown": 10 - k, "median": med,
                    "median_ci95": None if med is None else [0.9 * med, 1.1 * med], "min": med, "max": med,
                    "errors": 0}
        models[name] = {"run": name, "why": f"the {name} one", "epochs": 8, "architecture": "baseline",
                        "candidates": {"rollout_100_mae_m": mae, "envelope_exit_fraction": 0.1},
                        "ensembles": e, "max_speed": {"controller": "ltv", "speed_mps": speed, "scenario": None,
                                                      "failed_at": None, "complete": True, "rungs": {}}}
    scores = {c: [{"candidate": n, "description": n, "models": 5, "crashed": 2, "auc": a, "auc_ci95": ai,
                   "spearman": sp, "spearman_ci95": si} for n, a, ai, sp, si in rows]
              for c, rows in STUDY_SCORES.items()}
    return {"scenario": "figure8-fast", "members": 10, "controllers": ["ltv", "sqp"],
            "ladder": {"controller": "ltv", "rungs": ["figure8-slow", "figure8-fast"],
                       "speeds_mps": {"figure8-slow": 0.76, "figure8-fast": 1.52}, "rmse_bound_m": 0.1},
            "candidates": {"rollout_100_mae_m": "100-step MAE"}, "kstep": 30, "oracle_run": "o",
            "oracle_rmse_m": 4e-5, "models": models, "scores": scores, "runs": 123, "code_version": "x",
            "command": "pinnmpc study --members 10", "wall_time_s": 600.0, "date": "2026-11-23",
            "refused": {"stuck": {"why": "the stuck one", "reason": "no LQR gain", "rollout_100_mae_m": 0.23}}}


# ---- parsing helpers ---------------------------------------------------------------------------
def _section(md: str, heading: str) -> str:
    body = md.split(f"\n## {heading}\n", 1)[1]
    return body.split("\n## ", 1)[0]


def _cells(line: str) -> list[str]:
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line.strip()[1:-1])]


def _closed_loop_rows(md: str) -> list[list[str]]:
    lines = [ln for ln in _section(md, "Closed-loop results").splitlines() if ln.startswith("|")]
    head = _cells(lines[0])
    assert tuple(head[:len(TABLE_HEAD)]) == TABLE_HEAD
    return [_cells(ln) for ln in lines[2:]]


# ---- tests -------------------------------------------------------------------------------------
def test_report_contents(results_dir):
    out = build_report(results_dir)
    assert out == results_dir / "report.md"
    md = out.read_text(encoding="utf-8")
    page = (results_dir / "report.html").read_text(encoding="utf-8")

    # every section, exactly these, in this order (pytest's diff of the lists names a missing or moved one)
    assert re.findall(r"^## (.+)$", md, flags=re.M) == list(HEADINGS)
    assert re.findall(r"<h2>(.+?)</h2>", page) == list(HEADINGS)

    # one row per run, in report order, RMSE as saved, the crash and the error visible
    rows = _closed_loop_rows(md)
    assert len(rows) == len(RUNS)
    by_key = {(s, c, m): (rmse, crashed, err) for s, c, m, rmse, crashed, err in RUNS}
    expected_order = [k for k in ROW_ORDER if k in by_key]
    got_order = [(r[0], next(c for c, lab in CONTROLLER_LABELS.items() if lab == r[1]), r[2]) for r in rows]
    assert got_order == expected_order
    for key, row in zip(got_order, rows):
        rmse, crashed, err = by_key[key]
        assert row[3] == (MISSING if rmse is None else RMSE_FORMAT.format(rmse)), key
        if crashed:
            assert row[6].startswith("crashed"), row
            assert f"{CRASH_STEP * DT:.2f} s" in row[6]
        elif err:
            assert err in row[6], row
        else:
            assert row[6] == "no", row

    # summary counts equal the input's
    summary = _section(md, "Summary")
    n_crashed = sum(1 for *_, crashed, err in RUNS if crashed and not err)
    n_error = sum(1 for *_, err in RUNS if err)
    assert int(re.search(r"Runs: (\d+)", summary).group(1)) == len(RUNS)
    assert int(re.search(r"crashed: (\d+)", summary).group(1)) == n_crashed
    assert int(re.search(r"could not start: (\d+)", summary).group(1)) == n_error

    # figures: every referenced PNG exists; the HTML embeds the same number, none by path
    refs = re.findall(r"!\[[^\]]*\]\((figures/[^)]+\.png)\)", md)
    assert len(refs) == md.count("![")
    assert "figures/headline.png" in refs
    for rel in refs:
        p = results_dir / rel
        assert p.is_file(), rel
        assert p.read_bytes()[:8] == PNG_MAGIC, rel
    assert page.count(HTML_IMG) == len(refs)
    assert HTML_REL not in page
    assert "Table III is not shown" in _section(md, "Table III: ablation")


@pytest.mark.slow
def test_report_is_deterministic(results_dir):
    build_report(results_dir)
    first = {p.name: p.read_bytes() for p in [results_dir / "report.md", results_dir / "report.html"]}
    build_report(results_dir)
    assert first == {p.name: p.read_bytes() for p in [results_dir / "report.md", results_dir / "report.html"]}


def test_trajectory_figures_drawn_by_two_processes_are_those_drawn_by_one(results_dir, monkeypatch):
    import reports.figures as figures
    from reports.inputs import load_inputs

    inputs = load_inputs(results_dir)
    monkeypatch.setattr(figures, "POOL_MIN_FIGURES", 1)
    drawn = {}
    for jobs in (1, 2):
        out = results_dir / f"jobs{jobs}"
        figs, notes = figures.trajectory_figures(inputs, out, jobs=jobs)
        drawn[jobs] = ([f.path for f in figs], notes, {f.path: (out / f.path).read_bytes() for f in figs})
    assert len(drawn[1][0]) == 2 and drawn[1] == drawn[2]


def test_missing_optional_pieces(results_dir):
    """One scenario, no NMPC, no traces, no provenance: the report still builds."""
    data = json.loads((results_dir / "results.json").read_text())
    data["runs"] = [r for r in data["runs"] if r["scenario"] == "hover" and r["controller"] == "ltv"]
    (results_dir / "results.json").write_text(json.dumps(data))
    shutil.rmtree(results_dir / "traces")
    (results_dir / "provenance.json").unlink()
    md = build_report(results_dir).read_text(encoding="utf-8")
    for h in HEADINGS:
        assert f"\n## {h}\n" in md, h
    assert len(_closed_loop_rows(md)) == len(data["runs"])
    assert "not found" in _section(md, "Trajectories and tracking error")


@pytest.mark.parametrize("name", REQUIRED)
def test_missing_required_file_names_it(results_dir, name):
    (results_dir / name).unlink()
    with pytest.raises(ReportError, match=re.escape(name)) as info:
        build_report(results_dir)
    assert isinstance(info.value, ValueError)


def test_ensemble_members_get_their_own_table_and_stay_out_of_the_others(results_dir):
    from scenarios.studies.stats import wilson_interval

    data = json.loads((results_dir / "results.json").read_text())
    rmse = [0.050, 0.052, 0.049, 0.051, None]          # the last member crashed
    for k, v in enumerate(rmse):
        r = _result("hover", "ltv", "alpha", v if v is not None else 0.9, v is None, None)
        r.update(run_id=f"{r['run_id']}__m{k}", member=k)
        r.pop("trace")
        data["runs"].append(r)
    (results_dir / "results.json").write_text(json.dumps(data))
    md = build_report(results_dir).read_text(encoding="utf-8")
    assert len(_closed_loop_rows(md)) == len(RUNS)       # the members are not closed-loop rows
    rows = [_cells(ln) for ln in _section(md, "Ensembles: crash probability and RMSE with intervals").splitlines()
            if ln.startswith("| hover")]
    assert len(rows) == 1
    lo, hi = wilson_interval(1, 5)
    assert rows[0][4:7] == ["5", "1", f"0.20 ({lo:.2f}–{hi:.2f})"]
    assert rows[0][7].startswith("50.5 (") and rows[0][8] == "49.0–52.0"


def test_the_zoo_study_leads_the_report(results_dir):
    (results_dir / "study.json").write_text(json.dumps(_study()))
    md = build_report(results_dir).read_text(encoding="utf-8")
    assert md.index("\n## Dose-response") < md.index("\n## Summary")
    lead = _section(md, HEADINGS[0])
    assert "figures/dose_response.png" in lead and "pinnmpc study --members 10" in lead and "123 closed-loop" in lead
    # answer: bands under 35 mm (fine) and from 80 mm (bad, awful); the best crash predictor and its AUC
    assert "The 1 model under 35 mm crashed with probability 0.00 each" in lead
    assert "the 2 models at 80 mm or more with 1.00 each" in lead
    assert "hover chordal distance (nu-gap bound): AUC 0.97 (95 % 0.80–1.00), against 0.83 for the 100-step MAE" \
        in lead
    assert "Its interval includes 0.5" not in lead.split("**SQP.**")[0]
    assert "100-step position MAE: AUC 0.88 (95 % 0.60–1.00)" in lead       # the SQP's best
    for f in ("figures/dose_response.png", "figures/max_speed.png"):
        assert (results_dir / f).read_bytes()[:8] == PNG_MAGIC
    # predictor table: the exact numbers of the file
    rows = [_cells(ln) for ln in _section(md, HEADINGS[2]).splitlines() if ln.startswith("| ")][1:]
    assert [r[4] for r in rows] == ["0.83 (0.50–1.00)", "0.97 (0.80–1.00)", "0.88 (0.60–1.00)", "0.61 (0.30–0.90)"]
    assert rows[0][5] == "+0.50 (-1.00 to +1.00)" and rows[3][5] == "undefined"
    # zoo table: sorted by open-loop error, crash probabilities and speeds as given
    rows = [_cells(ln) for ln in _section(md, HEADINGS[3]).splitlines() if ln.startswith("| ")][1:]
    assert [r[0] for r in rows] == sorted(STUDY_MODELS, key=lambda n: STUDY_MODELS[n][0])
    poor = next(r for r in rows if r[0] == "poor")
    assert poor[4].startswith("0.8 (") and poor[5] == "500 (450–550)" and poor[-1] == "none"
    assert next(r for r in rows if r[0] == "fine")[-1] == "1.69"
    assert "Not flown: 1 trained models" in _section(md, HEADINGS[3]) and "stuck (the stuck one" in md


@pytest.mark.slow
def test_the_threshold_with_the_estimator_sits_beside_the_one_without(results_dir):
    from scenarios.studies.stats import wilson_interval

    heading = "Dose-response with the state estimator"
    md = build_report(results_dir).read_text(encoding="utf-8")
    assert "pinnmpc study --estimator ekf" in _section(md, heading)
    study = _study()
    (results_dir / "study.json").write_text(json.dumps(study))
    ekf = _study()
    ekf["models"] = {n: ekf["models"][n] for n in ("fine", "fair", "poor", "bad")}
    e = ekf["models"]["poor"]["ensembles"]["ltv"]          # 8 of 10 crash without the estimator, 3 with it
    e.update(crashes=3, crash_probability=0.3, crash_probability_ci95=list(wilson_interval(3, 10)), median=0.25)
    ekf["command"] = "pinnmpc study --estimator ekf --select fine,fair,poor,bad"
    (results_dir / "study_ekf.json").write_text(json.dumps(ekf))
    text = _section(build_report(results_dir).read_text(encoding="utf-8"), heading)
    rows = [_cells(ln) for ln in text.splitlines() if ln.startswith("| ")][1:]
    assert [r[0] for r in rows] == ["fine", "fair", "poor", "bad"]
    lo, hi = wilson_interval(3, 10)
    assert rows[2][:6] == ["poor", "70.0", "0.8 (0.49–0.94)", f"0.3 ({lo:.2f}–{hi:.2f})", "500.0", "250.0"]
    # LTV-MPC: no crash up to 9 mm (fair crashes 2 of 10) both ways; every member crashes from 300 mm without and with.
    assert "**LTV-MPC.** No crash up to 9 mm of open-loop error without the estimator, 9 mm with it; every member " \
           "crashes from 300 mm without, 300 mm with." in text
    assert "4 models of the zoo" in text and "--select fine,fair,poor,bad" in text


def test_without_a_study_the_lead_says_how_to_make_one(results_dir):
    md = build_report(results_dir).read_text(encoding="utf-8")
    for h in HEADINGS[:4]:
        assert "pinnmpc zoo" in _section(md, h) and "pinnmpc study" in _section(md, h)


def test_a_malformed_study_is_named(results_dir):
    (results_dir / "study.json").write_text(json.dumps({"scenario": "figure8-fast"}))
    with pytest.raises(ReportError, match="study.json"):
        build_report(results_dir)
    (results_dir / "study.json").write_text("{not json")
    with pytest.raises(ReportError, match="study.json"):
        build_report(results_dir)


def _versus() -> dict:
    ladder = {"rungs": ["figure8-slow", "figure8-fast"], "speeds_mps": {"figure8-slow": 0.76, "figure8-fast": 1.52},
              "rmse_bound_m": 0.1}

    def row(arch, extra, med, ci, crashes, vs, speed):
        return {"architecture": arch, "extra_states": extra,
                "ensemble": {"runs": 10, "crashes": crashes, "median": med, "median_ci95": ci},
                "versus_nominal": vs, "ladder": {"max_speed": {"speed_mps": speed}}}

    models = {"nominal": row("equations", [], 0.0385, [0.0383, 0.0386], 0, None, 1.52),
              "lagged": row("hybrid_lag", ["n1", "n2", "n3", "n4"], 0.0275, [0.0272, 0.0277], 0,
                            {"fraction": 0.286, "fraction_ci95": [0.28, 0.29], "apart": True}, 0.76)}
    plant = {"label": "a lagging plant", "scenario": "figure8-fast+highfi", "models": models,
             "verdict": {"best": "lagged", "fraction": 0.286, "fraction_ci95": [0.28, 0.29], "apart": True,
                         "goal": 0.5, "met": False}}
    return {"scenario": "figure8-fast", "controller": "sqp", "members": 10, "ladder_members": 10, "ladder": ladder,
            "goal": 0.5, "plants": {"highfi": plant}, "runs": 40, "wall_time_s": 600.0, "date": "2026-11-24",
            "command": "pinnmpc versus --members 10"}


@pytest.mark.slow
def test_learned_against_nominal_section_reads_versus_json(results_dir):
    h = "Learned against nominal on plants with unmodelled physics"
    assert "pinnmpc versus" in _section(build_report(results_dir).read_text(encoding="utf-8"), h)   # how to make one
    (results_dir / "versus.json").write_text(json.dumps(_versus()))
    sec = _section(build_report(results_dir).read_text(encoding="utf-8"), h)
    rows = [_cells(ln) for ln in sec.splitlines() if ln.startswith("| `")]
    assert rows[0] == ["`nominal`", "equations", "none", "38.5 (38.3–38.6)", "0/10", "–", "1.52"]
    assert rows[1] == ["`lagged`", "hybrid_lag", "n1, n2, n3, n4", "27.5 (27.2–27.7)", "0/10",
                       "+29 % (+28 to +29)", "0.76"]
    assert "29 % below the nominal equations' RMSE (bootstrap 95 % 28 to 29 %)" in sec
    assert "the 50 % goal is missed by 21 points" in sec and "40 closed-loop runs in 10 min" in sec
    (results_dir / "versus.json").write_text(json.dumps({"scenario": "figure8-fast"}))
    with pytest.raises(ReportError, match="versus.json"):
        build_report(results_dir)


def test_runs_on_other_plants_have_their_own_section_and_stay_out_of_the_others():
    from reports.sections.plants import NO_RUNS, plants_section, split_by_plant

    def run(model, rmse, plant=None, vehicle=None, crashed=False):
        r = _result("figure8-fast", "sqp", model, rmse, crashed, None)
        if plant:
            r["plant"] = plant
        if vehicle:
            r["vehicle"] = vehicle
        return r

    runs = [run("oracle", 1e-5), run("alpha", 0.030),            # results written before plants existed
            run("oracle", 2e-5, "rotorpy-ideal"), run("alpha", 0.0303, "rotorpy-ideal"),
            run("nominal", 0.045, "rotorpy"), run("alpha", 0.040, "rotorpy"),
            run("nominal", 0.002, "sim", "hummingbird"), run("nominal", None, "rotorpy", "crazyflie", crashed=True)]
    mine, others = split_by_plant(runs, {"full": False})
    assert [r["model"] for r in mine] == ["oracle", "alpha"] and len(others) == 6
    text = plants_section(mine, others)
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in text.splitlines() if line.startswith("| ") and "model" not in line}
    assert rows["oracle"] == ["0.01", "0.02", "–"] and rows["alpha"] == ["30", "30.3", "40"]
    assert rows["nominal"] == ["0.01", "–", "45"]           # on our simulator the nominal equations are the oracle
    assert "1 learned model(s) do better: alpha" in text and "within 1.0 %" in text
    assert "| crazyflie | figure8-fast | SQP | nominal | – | – | crashed at" in text
    assert "| hummingbird | figure8-fast | SQP | nominal | 2 | – | – |" in text
    # Every run is named with its plant and vehicle, and its compute time stands beside its RMSE.
    assert "our simulator with the rolling-spider (2 runs)" in text and "RotorPy, motor lag and aerodynamics with " \
        "the rolling-spider (2 runs)" in text and "with the crazyflie (1 run)" in text
    assert "| RotorPy, motor lag and aerodynamics | rolling-spider | figure8-fast | SQP | alpha | 40 | 4.00 | 12.00 | " \
        "2 / 200 | – |" in text
    # A run flown with the real-time iteration says so, with its input latency beside its load.
    rti = {**run("alpha", 0.040, "rotorpy"), "scheme": "rti",
           "latency_ms": {"median": 0.934, "p95": 1.0, "p99": 1.172, "max": 1.8}}
    assert "| SQP (real-time iteration) | alpha | 40 | 4.00 | 12.00 | 2 / 200 | 0.93 / 1.17 |" in \
        plants_section(mine, [rti])
    # ... and, where the controller thread's CPU time was measured, how many of its long periods were its own work
    assert "| SQP (real-time iteration) | alpha | 40 | 4.00 | 12.00 | 2 / 200 (0) | 0.93 / 1.17 |" in \
        plants_section(mine, [{**rti, "own_work_misses": 0}])
    alone = plants_section(mine, [])
    assert alone.startswith("All 2 runs here flew on our simulator with the rolling-spider.") and NO_RUNS in alone
    # A folder flown on another plant: its own runs are those, ours the others.
    mine, others = split_by_plant(runs, {"plant": "rotorpy"})
    assert {r["model"] for r in mine} == {"nominal", "alpha"} and len(others) == 6
    # ... and a folder whose every run is on RotorPy names it (it never says "no run on another plant" alone).
    rp = [run("oracle", 2e-5, "rotorpy-ideal"), run("alpha", 0.0303, "rotorpy-ideal")]
    mine, others = split_by_plant(rp, {"plant": "rotorpy-ideal"})
    assert plants_section(mine, others).startswith(
        "All 2 runs here flew on RotorPy, ideal (instant motors, no drag) with the rolling-spider.")


def test_runs_with_the_estimator_have_their_own_section_beside_their_twins():
    from reports.sections.estimation import NO_ESTIMATOR_RUNS, estimation_section, split_by_estimator

    def run(scenario, model, rmse, settled, estimator=None, crashed=False):
        r = _result(scenario, "sqp", model, rmse, crashed, None)
        r["settled_error_m"] = settled
        if estimator:
            r.update(estimator=estimator, estimator_ms={"median": 0.5432, "max": 1.0}, nees_mean=12.3)
        return r

    runs = [run("hover+payload", "oracle", 0.1022, 0.1038), run("hover+payload", "oracle", 0.0144, 0.0018, "ekf"),
            run("hover+payload", "alpha", 0.0156, 0.0023, "ekf"), run("figure8-fast", "alpha", 0.03, None),
            run("figure8-fast+wind", "alpha", 0.2, None, "ekf", crashed=True)]
    without, with_est = split_by_estimator(runs)
    assert len(without) == 2 and len(with_est) == 3
    text = estimation_section(without, with_est)
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in text.splitlines()
            if line.startswith("| ") and "scenario" not in line]
    assert rows[0] == ["figure8-fast+wind", "SQP", "alpha", "–", "crashed at 1.23 s (tilt > 80 deg)", "–", "–",
                       "0.54", "12.3"]
    assert rows[1] == ["hover+payload", "SQP", "oracle", "102.2", "14.4", "103.8", "1.8", "0.54", "12.3"]
    assert rows[2][:7] == ["hover+payload", "SQP", "alpha", "–", "15.6", "–", "2.3"]
    assert estimation_section(without, []) == NO_ESTIMATOR_RUNS


def test_realtime_table_says_why_an_ideal_run_is_missing():
    from reports.tables import realtime_table

    rt = {"scenario": "figure8-fast", "controller": "nmpc", "model": "oracle", "timing": "realtime",
          "rmse_position_m": 0.1, "crashed": False, "solve_ms": {"median": 150.0, "p95": 200.0, "max": 230.0}}
    alone = realtime_table([rt])
    assert "| not flown |" in alone and "`--full`" in alone
    both = realtime_table([rt, {**rt, "timing": "ideal", "rmse_position_m": 1e-5}])
    assert "not flown" not in both.lower() and "| 1e-05 |" in both


def test_realtime_table_counts_deadline_fallbacks_where_a_run_has_them():
    from reports.tables import realtime_table

    base = {"scenario": "figure8-fast", "model": "oracle", "timing": "realtime", "rmse_position_m": 0.1,
            "crashed": False, "solve_ms": {"median": 4.0, "p95": 6.0, "max": 9.5}, "deadline_misses": 0,
            "skipped_periods": 0, "solver_failures": 7, "fallbacks": 1}
    table = realtime_table([{**base, "controller": "sqp", "deadline_fallbacks": 4},
                            {**base, "controller": "nmpc"}])     # the NMPC keeps no deadline: no count
    lines = table.splitlines()
    head = [c.strip() for c in lines[-4].strip("|").split("|")]
    rows = {line.split("|")[2].strip(): [c.strip() for c in line.strip("|").split("|")] for line in lines[-2:]}
    col = head.index("deadline fallbacks")
    assert rows["SQP"][col] == "4" and rows["NMPC"][col] == "–"


def test_realtime_table_shows_the_input_latency_and_the_load_and_names_the_real_time_iteration():
    from reports.tables import realtime_table

    r = {"scenario": "figure8-fast", "model": "oracle", "timing": "realtime", "controller": "sqp", "scheme": "rti",
         "rmse_position_m": 0.1, "crashed": False, "solve_ms": {"median": 1.2, "p95": 1.5, "max": 2.6},
         "latency_ms": {"median": 0.25, "p95": 0.3, "p99": 0.41, "max": 0.5}, "deadline_misses": 0}
    table = realtime_table([r, {**r, "controller": "ltv", "scheme": None, "latency_ms": None}])
    lines = table.splitlines()
    head = [c.strip() for c in lines[-4].strip("|").split("|")]
    rows = {line.split("|")[2].strip(): [c.strip() for c in line.strip("|").split("|")] for line in lines[-2:]}
    sqp = rows["SQP (real-time iteration)"]
    assert sqp[head.index("input latency median / p99 (ms)")] == "0.25 / 0.41"
    assert sqp[head.index("load median / p95 / max (ms)")] == "1.2 / 1.5 / 2.6"
    assert rows["LTV-MPC"][head.index("input latency median / p99 (ms)")] == "-"
