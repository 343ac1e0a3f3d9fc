"""The stated interfaces: every controller the runner builds offers all of
:class:`mpc.controllers.controller.Controller`, and
the LQR and the MPCs share its hooks by one definition."""

import inspect

import numpy as np
import pytest

from mpc.controllers.base import MPCBase
from mpc.controllers.controller import Controller, ControllerBase
from mpc.controllers.lqr import LQRController
from mpc.controllers.ltv import LTVMPC
from mpc.prediction.models import AnalyticModel
from scenarios.closed_loop.library import get_scenario
from mpc.controllers.factory import make_controller

HOOKS = ("applied", "set_deadline", "set_disturbance")


def _members(protocol) -> set[str]:
    own = {n for n in vars(protocol) if not n.startswith("_")} | set(protocol.__annotations__)
    return own | {"__call__"}


@pytest.mark.parametrize("kind", ["lqr", "ltv", "sqp", "nmpc"])
def test_every_controller_offers_the_whole_interface(kind):
    sc = get_scenario("hover")
    ctrl = make_controller(kind, AnalyticModel(), sc.reference())
    assert isinstance(ctrl, ControllerBase)
    for name in _members(Controller):
        assert hasattr(ctrl, name), (kind, name)
        if name != "preflight":
            assert callable(getattr(ctrl, name)), (kind, name)
    sig = inspect.signature(ctrl.set_disturbance)
    assert list(sig.parameters) == ["d", "x"], kind
    ctrl.prepare(0.1, x0=np.array(sc.x0))
    assert ctrl.start_extra(np.array(sc.x0)).shape == (0,)
    assert (ctrl.preflight is None) == (kind != "sqp")


def test_the_lqr_and_the_mpcs_share_their_hooks_by_one_definition():
    for name in HOOKS:
        assert name not in vars(LQRController) and name not in vars(MPCBase), name
    assert "set_deadline" in vars(LTVMPC)          # the one controller that keeps a deadline overrides it
