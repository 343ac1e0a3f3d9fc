"""Input dither: seeded white noise on a controller's output, for identification from closed-loop flights.

In closed loop the input is a function of the state, so data flown by a
controller alone cannot tell the model's response to the input from its
response to the state. :class:`Dithered` adds independent noise to every
command a controller sends (standard deviations :func:`dither_std`), which
breaks that dependence; the controller is told what was sent, dither
included, as it is told of any applied input.
"""

from __future__ import annotations

import numpy as np

from ..errors import ScenarioError

#: Dither standard deviations: thrust as a share of the weight, the roll and pitch torques as a share of the weight
#: times the arm length, the yaw torque as a share of the weight times kq / kt (the yaw torque per newton of thrust).
DITHER_THRUST = 0.02
DITHER_TORQUE = 0.005


def dither_std(params, scale: float = 1.0) -> np.ndarray:
    """Standard deviations (4,) of the dither on ``[T, tau_x, tau_y, tau_z]``, N and N m, for a vehicle.

    Parameters
    ----------
    params : sim.params.QuadParams
        The vehicle's parameters (``m``, ``g``, ``d``, ``kt``, ``kq``).
    scale : float
        Multiplies every standard deviation (>= 0; 0: no dither).
    """
    if not (isinstance(scale, (int, float)) and np.isfinite(scale) and scale >= 0):
        raise ScenarioError(f"scale must be a finite number >= 0; found {scale!r}")
    weight = params.m * params.g
    return scale * np.array([DITHER_THRUST * weight, DITHER_TORQUE * weight * params.d,
                             DITHER_TORQUE * weight * params.d, DITHER_TORQUE * weight * params.kq / params.kt])


def level_dither_std(params, level: str, scale: float = 1.0) -> np.ndarray:
    """Standard deviations (4,) of the dither on a command at ``level``: at ``ctbr`` ``[T, p, q, r]``, N and rad/s.

    The thrust's is :func:`dither_std`'s; each body rate's is the change of that rate the torque dither of
    :func:`dither_std` makes in one control period on the vehicle's inertia (``std_tau / J * dt``: 0.044 rad/s on
    roll for the Crazyflie, 0.030 for the default vehicle), so that a flight dithered at either level is shaken by
    about as much.

    Parameters
    ----------
    params : sim.params.QuadParams
        The vehicle's parameters.
    level : str
        ``"wrench"`` (:func:`dither_std` itself) or ``"ctbr"``.
    scale : float
        Multiplies every standard deviation (>= 0; 0: no dither).
    """
    from sim.levels import rate_dither_std

    std = dither_std(params, scale)
    if level == "wrench":
        return std
    if level != "ctbr":
        raise ScenarioError(f"level must be 'wrench' or 'ctbr' for a dither; found {level!r}")
    return np.r_[std[0], rate_dither_std(std[1:], params)]


class Dithered:
    """A controller whose every output gets seeded Gaussian noise of standard deviations ``std``.

    Called as the controller is (``u, info = controller(x, t)``); every other attribute is the controller's
    (its deadline, its disturbance input, what it is told was applied).

    Parameters
    ----------
    controller : callable
        The controller: ``controller(x, t) -> (u (4,), info)``.
    std : array_like, shape (4,)
        Standard deviations, N and N m (:func:`dither_std`).
    seed : int
        Seeds the noise: two flights with equal seeds get the same dither.
    """

    def __init__(self, controller, std, seed: int = 0):
        std = np.asarray(std, dtype=float)
        if std.shape != (4,) or not np.all(np.isfinite(std)) or np.any(std < 0):
            raise ScenarioError(f"std must be 4 finite numbers >= 0; found {std!r}")
        if not callable(controller):
            raise ScenarioError(f"controller must be callable; found {type(controller).__name__}")
        self.controller = controller
        self.std = std
        self.rng = np.random.default_rng([int(seed), 0xD17E])

    def __call__(self, x, t):
        u, info = self.controller(x, t)
        return np.asarray(u, dtype=float) + self.std * self.rng.standard_normal(4), info

    def __getattr__(self, name):
        if name == "controller":      # not set yet (unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.controller, name)


__all__ = ["DITHER_THRUST", "DITHER_TORQUE", "Dithered", "dither_std", "level_dither_std"]
