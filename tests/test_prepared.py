"""A run that takes its feed-forward from the previous run of its process flies bit for bit as one that fits it.

An ensemble's members differ only in their start and seed, so a process flying them one after another fits the
feed-forward once (:meth:`mpc.references.feedforward.FeedForward.adopt`); everything flown must stay exactly equal.
"""

from pathlib import Path

import numpy as np
import pytest

import scenarios.closed_loop.runner as runner
from mpc.references.feedforward import FeedForward
from mpc.errors import ConfigurationError
from scenarios.closed_loop.metrics import TIMING_FIELDS, TRACE_TIMING_FIELDS
from scenarios.closed_loop.runner import RunSpec, fly

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "models" / "baseline.onnx")
LAG_MODEL = str(ROOT / "models" / "learn" / "highfi" / "learn_highfi_it3.onnx")
#: Members of one ensemble (the second adopts the first's feed-forward), per model kind.
CASES = {
    "sqp-onnx": [RunSpec("figure8-fast", "sqp", BASELINE, member=k) for k in range(2)],
    "lqr-equations-rotor-states": [RunSpec("hover+highfi", "lqr", "oracle", member=k) for k in range(2)],
    "sqp-onnx-rotor-states": [RunSpec("hover+highfi", "sqp", LAG_MODEL, member=k) for k in range(2)],
    "ltv-equations": [RunSpec("hover", "ltv", "nominal", member=k) for k in range(2)],
}
#: Cases left to the slow run (the first two cover both feed-forward paths: input Jacobians and extra states).
SLOW_CASES = ("sqp-onnx-rotor-states", "ltv-equations")


def _fly_all(specs, reuse: bool, monkeypatch):
    adopted = []
    real = FeedForward.adopt

    def counting(self, prepared):
        adopted.append(prepared.t_end)
        return real(self, prepared)

    monkeypatch.setattr(FeedForward, "adopt", counting)
    out = []
    for s in specs:
        if not reuse:
            runner._PREPARED.clear()
        out.append(fly(s))
    monkeypatch.setattr(FeedForward, "adopt", real)
    return out, adopted


@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.slow) if c in SLOW_CASES else c for c in CASES])
def test_members_flown_with_an_adopted_feedforward_equal_members_that_fit_their_own(case, monkeypatch):
    specs = CASES[case]
    runner._PREPARED.clear()
    own, adopted_none = _fly_all(specs, False, monkeypatch)
    runner._PREPARED.clear()
    reused, adopted = _fly_all(specs, True, monkeypatch)
    assert adopted_none == [] and len(adopted) == len(specs) - 1       # the later members did adopt
    for (ra, ta), (rb, tb) in zip(own, reused):
        assert ra.get("error") is None
        assert {k: v for k, v in ra.items() if k not in TIMING_FIELDS} == \
               {k: v for k, v in rb.items() if k not in TIMING_FIELDS}
        assert set(ta) == set(tb)
        for k in set(ta) - set(TRACE_TIMING_FIELDS):
            np.testing.assert_array_equal(ta[k], tb[k], err_msg=f"{ra['run_id']}: {k}")


def test_a_run_of_another_model_or_scenario_fits_its_own(monkeypatch):
    runner._PREPARED.clear()
    _, adopted = _fly_all([RunSpec("hover", "lqr", "oracle"), RunSpec("hover", "lqr", "nominal"),
                           RunSpec("hover", "lqr", "nominal", seed=3), RunSpec("figure8-slow", "lqr", "nominal")],
                          True, monkeypatch)
    assert len(adopted) == 1                         # only the seed changed between the second and the third


def test_adopt_is_refused_once_something_was_computed():
    from scenarios.closed_loop.runner import load_run_model
    from mpc.controllers.factory import make_controller

    spec = RunSpec("hover", "lqr", "nominal")
    ctrl = make_controller("lqr", load_run_model(spec), None)
    with pytest.raises(ConfigurationError, match="prepare"):
        ctrl.ff.prepared()
    ctrl.prepare(1.0)
    other = make_controller("lqr", load_run_model(spec), None)
    other.ff.states([0.0])
    with pytest.raises(ConfigurationError, match="computed nothing"):
        other.ff.adopt(ctrl.ff.prepared())
