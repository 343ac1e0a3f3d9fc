"""Command levels: what a controller sends and a plant takes each control period.

========  =======================================  ==========================  ==============================
level     input (4,)                               units                       who takes it
========  =======================================  ==========================  ==============================
wrench    collective thrust, body torques          N, N m, N m, N m            the rotors through the mixer
ctbr      collective thrust, body rates            N, rad/s, rad/s, rad/s      an onboard rate loop
ctatt     collective thrust, roll, pitch, yaw rate N, rad, rad, rad/s          an onboard attitude loop
========  =======================================  ==========================  ==============================

Rates are in the FRD body frame, angles are the state's ZYX Euler angles in NED/FRD, and the yaw of ``ctatt`` is a
rate, as the Crazyflie's ``send_setpoint`` takes it. ``wrench`` is the default: every model file, result and
command line that names no level flies at it.
"""

from __future__ import annotations

import numpy as np

from .errors import SimInputError
from .params import DT, INPUT_NAMES

#: The command levels, the default first.
LEVELS = ("wrench", "ctbr", "ctatt")
#: The level of a model, a run or a plant that names none.
DEFAULT_LEVEL = "wrench"
#: The levels an excitation dataset is flown and logged at (``pinnmpc data --level``).
DATA_LEVELS = ("wrench", "ctbr")
#: The names of the four inputs at each level (a model file's ``input_names`` metadata).
LEVEL_INPUTS = {
    "wrench": INPUT_NAMES,
    "ctbr": ("T", "p_cmd", "q_cmd", "r_cmd"),
    "ctatt": ("T", "phi_cmd", "theta_cmd", "r_cmd"),
}
#: Their units.
LEVEL_UNITS = {
    "wrench": ("N", "N m", "N m", "N m"),
    "ctbr": ("N", "rad/s", "rad/s", "rad/s"),
    "ctatt": ("N", "rad", "rad", "rad/s"),
}


def check_level(level, name: str = "level") -> str:
    """``level`` when it is one of :data:`LEVELS`, else a :class:`sim.errors.SimInputError` naming ``name``."""
    if not isinstance(level, str) or level not in LEVELS:
        raise SimInputError(f"{name} must be one of {', '.join(LEVELS)}; found {level!r}")
    return level


def rate_dither_std(torque_std, params) -> np.ndarray:
    """The body-rate dither (3,) at ``ctbr`` that shakes a vehicle about as much as the torque dither ``torque_std``
    (3,) at the wrench level: the change of each rate that torque makes in one control period on the vehicle's
    inertia, ``std_tau / J * dt`` (rad/s; ``params`` a :class:`sim.params.QuadParams`)."""
    return np.asarray(torque_std, dtype=float) / np.array([params.Jxx, params.Jyy, params.Jzz]) * DT
