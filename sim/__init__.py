"""Reference quadrotor simulator, excitation data and Fisher information.

Public names::

    from sim import QuadParams, dynamics, Simulator
    p = QuadParams()                  # reference values; QuadParams(m=0.08) overrides
    xdot = dynamics(x, u, p)          # numpy, nominal; x (..., 12), u (..., 4) -> (..., 12)
    s = Simulator(p)                  # nominal fidelity, dt = 0.01 s, RK4 with 1 ms substeps
    x1 = s.step(x, u)                 # one control period; batched over leading axes
"""

import os as _os
import platform as _platform

# The shipped models are checked against datasets rebuilt bit for bit. OpenBLAS picks its kernels by CPU,
# and its AVX-512 kernels round differently from the AVX2 ones the datasets were made with, so on x86-64
# the AVX2 ("Haswell") kernels are used unless the user has chosen a kernel. This works only when numpy
# has not been loaded yet, so every package of this project imports sim first.
if _platform.machine().lower() in ("x86_64", "amd64"):
    _os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

from ._version import __version__  # noqa: E402, F401
from .equations.dynamics import dynamics, rk4_step  # noqa: E402
from .errors import DatasetError, SimInputError  # noqa: E402
from .params import (  # noqa: E402
    DT, HIGH_FIDELITY, INPUT_NAMES, NOMINAL, STATE_NAMES, SUBSTEPS, THETA_NAMES,
    Fidelity, NoiseModel, QuadParams,
)
from .equations.simulator import Simulator, StepResult  # noqa: E402

__all__ = [
    "DT", "HIGH_FIDELITY", "INPUT_NAMES", "NOMINAL", "STATE_NAMES", "SUBSTEPS", "THETA_NAMES",
    "DatasetError", "Fidelity", "NoiseModel", "QuadParams", "SimInputError", "Simulator", "StepResult",
    "dynamics", "rk4_step", "make_dataset", "load_dataset", "Dataset",
]


def __getattr__(name):
    # The data generator pulls in python-control; import it on first use only.
    if name in ("make_dataset", "load_dataset", "Dataset"):
        from .identification import excitation
        return getattr(excitation, name)
    raise AttributeError(f"module 'sim' has no attribute {name!r}")
