"""The main job reuses an open-loop evaluation only when its models and code are those it would evaluate now."""

import json
import shutil
from pathlib import Path

import pytest

from pinn.evaluate import EFFECT_SPECS, evaluate_dir, evaluation_key
from scenarios.campaign import IDENTIFICATION_DIR, SHIPPED_EVALUATION, reusable_evaluation

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
FOLDERS = [MODELS, MODELS / IDENTIFICATION_DIR]
#: Relative tolerance of a fresh evaluation against the shipped one (the same code on another machine may round
#: differently in its last digits).
TOL = {"rel": 1e-9}
#: Fields of an evaluation that measure this machine's wall time (not compared).
TIMING_KEYS = ("seconds",)


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


@pytest.mark.slow
def test_the_shipped_evaluation_is_what_the_evaluation_computes_again():
    """The reuse rests on the evaluation being deterministic: computed again (about 100 s), it is the shipped one."""
    stored = json.loads((MODELS / SHIPPED_EVALUATION).read_text())
    again = json.loads(json.dumps(evaluate_dir(FOLDERS, jobs=2, extra_specs=EFFECT_SPECS)))
    stored.pop("inputs_sha256")

    def compare(a, b, where):
        if isinstance(a, dict):
            assert set(a) == set(b), where
            for k in a:
                if k not in TIMING_KEYS:
                    compare(a[k], b[k], f"{where}.{k}")
        elif isinstance(a, list):
            assert len(a) == len(b), where
            for i, (x, y) in enumerate(zip(a, b)):
                compare(x, y, f"{where}[{i}]")
        elif isinstance(a, float):
            assert a == pytest.approx(b, rel=TOL["rel"], abs=1e-300), where
        else:
            assert a == b, where

    compare(again, stored, "evaluation")
