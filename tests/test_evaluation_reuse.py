"""The main job reuses an open-loop evaluation or a Fisher table only when its inputs are those it would use now."""

import json
import shutil
from pathlib import Path

import pytest

from pinn.evaluate import EFFECT_SPECS, evaluate_dir, evaluation_key
from scenarios.studies.campaign import (IDENTIFICATION_DIR, SHIPPED_EVALUATION, SHIPPED_FISHER, fisher_key,
                                        reusable_evaluation, reusable_fisher)

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
FOLDERS = [MODELS, MODELS / IDENTIFICATION_DIR]
#: Relative tolerance of a fresh evaluation against the shipped one (the same code on another machine may round
#: differently in its last digits).
TOL = {"rel": 1e-9}
#: Fields of an evaluation that measure this machine's wall time (not compared).
TIMING_KEYS = ("seconds",)
#: Fields that hold a spectrum (eigenvalues, compared within a share of the largest).
SPECTRA = ("eigenvalues",)


def test_the_shipped_evaluation_is_current():
    stored = json.loads((MODELS / SHIPPED_EVALUATION).read_text())
    assert stored["inputs_sha256"] == evaluation_key(FOLDERS, EFFECT_SPECS), (
        "models/evaluation.json was computed from other models or code: run `pinnmpc run` and copy "
        "results/main/evaluation.json to models/ (or `pinnmpc run --fresh` if it reused the stale one)")
    assert reusable_evaluation(ROOT / "no-such-folder", MODELS, FOLDERS)[0] == MODELS / SHIPPED_EVALUATION


def model_folder(tmp_path, name="baseline"):
    d = tmp_path / "models"
    d.mkdir()
    for f in (f"{name}.onnx", f"{name}.jac.onnx"):
        shutil.copy(MODELS / f, d / f)
    return d


def test_an_evaluation_is_reused_only_for_the_same_model_files(tmp_path):
    d = model_folder(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    key = evaluation_key([d], EFFECT_SPECS)
    (out / "evaluation.json").write_text(json.dumps({"models": [], "inputs_sha256": key}))
    assert reusable_evaluation(out, d, [d])[0] == out / "evaluation.json"
    # Another derivative graph (the controllers' derivatives change) is another evaluation's input.
    shutil.copy(MODELS / "proposed.jac.onnx", d / "baseline.jac.onnx")
    assert evaluation_key([d], EFFECT_SPECS) != key and reusable_evaluation(out, d, [d]) is None
    # No key (an evaluation from `pinnmpc evaluate`), or a damaged file: not reused.
    (out / "evaluation.json").write_text(json.dumps({"models": []}))
    assert reusable_evaluation(out, d, [d]) is None
    (out / "evaluation.json").write_text('{"models": [')
    assert reusable_evaluation(out, d, [d]) is None


def test_the_key_covers_the_evaluations_code_and_extra_datasets(tmp_path, monkeypatch):
    d = model_folder(tmp_path)
    key = evaluation_key([d], EFFECT_SPECS)
    assert evaluation_key([d], ()) != key
    import pinn.evaluate as ev

    code = tmp_path / "code"
    (code / "pinn").mkdir(parents=True)
    (code / "pinn" / "metrics.py").write_text("x = 1\n")
    monkeypatch.setattr(ev, "EVALUATION_CODE", ("pinn",))
    monkeypatch.setattr(ev, "__file__", str(code / "pinn" / "evaluate.py"))
    one = evaluation_key([d], EFFECT_SPECS)
    (code / "pinn" / "metrics.py").write_text("x = 2\n")
    assert evaluation_key([d], EFFECT_SPECS) != one


def test_the_shipped_fisher_table_is_current():
    stored = json.loads((MODELS / SHIPPED_FISHER).read_text())
    assert stored["inputs_sha256"] == fisher_key(), (
        "models/fisher.json was computed from other code: run `pinnmpc run --fresh` and copy "
        "results/main/fisher.json to models/")
    assert reusable_fisher(ROOT / "no-such-folder", MODELS)[0] == MODELS / SHIPPED_FISHER


def test_a_fisher_table_is_reused_only_with_the_key_of_this_code(tmp_path):
    out, models = tmp_path / "out", tmp_path / "models"
    out.mkdir()
    models.mkdir()
    assert reusable_fisher(out, models) is None
    (models / SHIPPED_FISHER).write_text(json.dumps({"cases": [1], "inputs_sha256": fisher_key()}))
    assert reusable_fisher(out, models)[0] == models / SHIPPED_FISHER
    # The results folder's own table comes first; one of other code, without a key or damaged is not reused.
    (out / "fisher.json").write_text(json.dumps({"cases": [2], "inputs_sha256": fisher_key()}))
    assert reusable_fisher(out, models) == (out / "fisher.json", {"cases": [2], "inputs_sha256": fisher_key()})
    for text in (json.dumps({"cases": [], "inputs_sha256": "0" * 64}), json.dumps({"cases": []}), '{"cases": ['):
        (out / "fisher.json").write_text(text)
        (models / SHIPPED_FISHER).write_text(text)
        assert reusable_fisher(out, models) is None


@pytest.mark.slow
def test_the_shipped_fisher_table_is_what_the_table_computes_again():
    """The reuse rests on the table being deterministic: computed again (about 12 s), it is the shipped one."""
    from sim.identification.fisher import fisher_table

    stored = json.loads((MODELS / SHIPPED_FISHER).read_text())
    stored.pop("inputs_sha256")
    _compare(json.loads(json.dumps(fisher_table())), stored, "fisher")


def _compare(a, b, where, scale=0.0):
    """``a`` equal to ``b`` (nested) within ``TOL["rel"]`` of each value, or of ``scale`` where larger.

    The eigenvalues of a spectrum are compared within ``TOL["rel"]`` of its largest: a rank-deficient information
    matrix's zero eigenvalue is rounding (-1.4e-9 here, -8.9e-10 on another CPU, against 8.7e6), which no relative
    tolerance of its own can compare.
    """
    if isinstance(a, dict):
        assert set(a) == set(b), where
        for k in a:
            if k not in TIMING_KEYS:
                spectrum = k in SPECTRA and isinstance(b[k], list) and all(isinstance(v, float) for v in b[k])
                _compare(a[k], b[k], f"{where}.{k}", max(map(abs, b[k])) if spectrum and b[k] else scale)
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _compare(x, y, f"{where}[{i}]", scale)
    elif isinstance(a, float):
        assert a == pytest.approx(b, rel=TOL["rel"], abs=max(TOL["rel"] * scale, 1e-300), nan_ok=True), where
    else:
        assert a == b, where


#: The models evaluated again by the determinism check, one per path through the evaluation: each architecture (the
#: Fourier encoding, the modular network, the hybrids with and without the motor lag), both regimes, both plant
#: fidelities, commanded and realized inputs; with one extra dataset (the motor lag's estimator). Four of the eight
#: datasets, about half the full evaluation's time.
AGAIN_MODELS = {"": ("fourier", "modular"),
                IDENTIFICATION_DIR: ("hybrid", "proposed_aggressive_realized", "hybrid_lag_highfi")}
AGAIN_EXTRA = ("motor-lag",)


@pytest.mark.slow
def test_the_shipped_evaluation_is_what_the_evaluation_computes_again(tmp_path):
    """The reuse rests on the evaluation being deterministic: computed again for :data:`AGAIN_MODELS` (about 150 s),
    every model row and every dataset summary equals the shipped one."""
    stored = json.loads((MODELS / SHIPPED_EVALUATION).read_text())
    folders = []
    for sub, names in AGAIN_MODELS.items():
        d = tmp_path / (sub or "models")
        d.mkdir()
        for name in names:
            for f in (f"{name}.onnx", f"{name}.jac.onnx"):
                shutil.copy(MODELS / sub / f, d / f)
        folders.append(d)
    extra = [s for s in EFFECT_SPECS if s["fidelity"] in AGAIN_EXTRA]
    again = json.loads(json.dumps(evaluate_dir(folders, jobs=2, extra_specs=extra)))
    rows = {m["name"]: m for m in stored["models"]}
    assert sorted(m["name"] for m in again["models"]) == sorted(n for names in AGAIN_MODELS.values() for n in names)
    for m in again["models"]:
        _compare(m, rows[m["name"]], f"models[{m['name']}]")

    def key(d):
        return d["regime"], d["fidelity"], d["inputs"]

    datasets = {key(d): d for d in stored["datasets"]}
    assert len(again["datasets"]) == 4
    for d in again["datasets"]:
        where = f"datasets[{key(d)}]"
        assert set(d["models"]) <= set(datasets[key(d)]["models"]), where
        _compare({k: v for k, v in d.items() if k != "models"},
                 {k: v for k, v in datasets[key(d)].items() if k != "models"}, where)


def test_the_keys_leave_out_only_code_the_evaluation_and_the_fisher_table_never_import():
    """Every project module the evaluation or the Fisher table can import (inside functions too, with the packages
    that hold them) is under the keys: none lies in what they leave out."""
    from pinn.evaluate import KEY_EXCLUDES
    from test_layout import import_graph

    graph = import_graph(ROOT)
    reached, todo = set(), ["pinn.evaluate", "sim.identification.fisher", "sim.identification.excitation"]
    while todo:
        m = todo.pop()
        if m in reached:
            continue
        reached.add(m)
        parts = m.split(".")
        todo += [".".join(parts[:k]) for k in range(1, len(parts))] + list(graph.get(m, {}))
    left_out = [e.removesuffix(".py").replace("/", ".") for e in KEY_EXCLUDES]
    assert {"pinn.evaluate", "sim.identification.fisher", "mpc.prediction.contract"} <= reached
    assert not [m for m in reached if any(m == e or m.startswith(e + ".") for e in left_out)]
