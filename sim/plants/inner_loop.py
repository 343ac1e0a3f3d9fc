"""The onboard controller of a vehicle flown at the ``ctbr`` or ``ctatt`` command level.

A real flight stack does not take a wrench from an external controller: it takes collective thrust and body rates
(``ctbr``) or thrust, roll, pitch and a yaw rate (``ctatt``, what the Crazyflie's ``send_setpoint`` takes), and its
own loops, running faster than the external controller, turn that into torques. :class:`InnerLoop` is that
controller, one period of its own clock per :meth:`InnerLoop.update`:

* the rate loop, a PID on the body-rate error per axis (roll, pitch, yaw), its integral clamped (anti-windup);
* with ``ctatt``, before it, the attitude loop: a PI on the roll and pitch error that gives the roll and pitch rate
  setpoints (the yaw rate is commanded directly).

Gains are per unit inertia, so that one set means the same bandwidth on every vehicle: the torque about axis i is
``J_i (kp_i e_i + ki_i integral(e_i) + kd_i de_i/dt)`` with ``kp`` in 1/s, ``ki`` in 1/s^2 and ``kd`` dimensionless
(RotorPy's ``cmd_ctbr`` is this loop with ``kp = k_w`` and no integral or derivative). The thrust passes through.
Like the Crazyflie's PID, the attitude error is taken in the Euler angles and given to the rate loop as body rates,
and the derivative is of the error (a setpoint step kicks it).
"""

from __future__ import annotations

import numpy as np

from ..errors import SimInputError
from ..levels import LEVELS, check_level
from ..vehicles.onboard import InnerLoopConfig
from .plant import PLANT_TICK_S, Plant


class InnerLoop:
    """The onboard controller at one command level (``ctbr`` or ``ctatt``): command and state in, wrench out.

    Parameters
    ----------
    config : InnerLoopConfig
    level : str
        ``ctbr`` or ``ctatt`` (:data:`sim.levels.LEVELS`; the wrench level has no inner loop).
    inertia : array_like, shape (3,)
        ``Jxx, Jyy, Jzz``, kg m^2: the torques are the gains' angular accelerations times these.
    """

    def __init__(self, config: InnerLoopConfig, level: str, inertia):
        check_level(level)
        if level == LEVELS[0]:
            raise SimInputError("the wrench level has no inner loop: its command is the wrench itself")
        self.config, self.level = config, level
        self.inertia = np.asarray(inertia, dtype=float).reshape(3)
        self._kp, self._ki, self._kd = (np.asarray(v) for v in (config.rate_kp, config.rate_ki, config.rate_kd))
        self._i_limit = np.asarray(config.rate_i_limit)
        self._akp, self._aki = np.asarray(config.att_kp), np.asarray(config.att_ki)
        self._ai_limit = np.asarray(config.att_i_limit)
        self.reset()

    def reset(self) -> None:
        """Integrals and the previous error to zero (a vehicle standing still, its loops just started)."""
        self._rate_int = np.zeros(3)
        self._rate_prev = None
        self._att_int = np.zeros(2)

    def rate_setpoint(self, command: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The body-rate setpoint (3,), rad/s, of ``command`` (4,) in state ``x`` (12,); advances the attitude
        loop's integral by one period with ``ctatt``."""
        c = self.config
        if self.level == "ctbr":
            w = np.asarray(command[1:4], dtype=float)
        else:
            dt = c.period_s
            tilt = np.clip(np.asarray(command[1:3], dtype=float), -c.max_tilt, c.max_tilt)
            e = tilt - x[3:5]
            self._att_int = np.clip(self._att_int + e * dt, -self._ai_limit, self._ai_limit)
            w = np.concatenate([self._akp * e + self._aki * self._att_int, [float(command[3])]])
        return np.clip(w, -c.max_rate, c.max_rate)

    def update(self, command, x) -> np.ndarray:
        """One period of the loops: the wrench (4,) ``[T, tau_x, tau_y, tau_z]`` (N, N m) to hold for
        :attr:`InnerLoopConfig.period_s` given the ``command`` (4,) at this level and the state ``x`` (12,)."""
        command, x = np.asarray(command, dtype=float), np.asarray(x, dtype=float)
        dt = self.config.period_s
        e = self.rate_setpoint(command, x) - x[6:9]
        self._rate_int = np.clip(self._rate_int + e * dt, -self._i_limit, self._i_limit)
        de = np.zeros(3) if self._rate_prev is None else (e - self._rate_prev) / dt
        self._rate_prev = e
        alpha = self._kp * e + self._ki * self._rate_int + self._kd * de
        return np.concatenate([[command[0]], self.inertia * alpha])


class InnerLoopPlant(Plant):
    """A plant flown through its onboard controller: it takes commands at ``level`` and runs :class:`InnerLoop`
    at its own rate inside each call, holding the loop's wrench on the wrapped plant between its periods.

    The loop's clock starts at :meth:`reset` and keeps its phase across calls, so a period flown in pieces (the
    real-time clock's) is the same flight as one call. The wrapped plant's wind is evaluated at the start of each
    of its calls, that is every loop period here.

    Parameters
    ----------
    plant : Plant
        The plant that takes the wrench (its mixer, saturation and motor lag stay as they are).
    config : InnerLoopConfig
    level : str
        ``ctbr`` or ``ctatt``.
    """

    def __init__(self, plant: Plant, config: InnerLoopConfig, level: str):
        if not isinstance(plant, Plant):
            raise SimInputError(f"plant must be a Plant; found {type(plant).__name__}")
        p = plant.vehicle.params
        self.loop = InnerLoop(config, level, (p.Jxx, p.Jyy, p.Jzz))
        super().__init__(plant.vehicle, payload_kg=plant.payload_kg, wind=plant.wind)
        self.plant, self.level, self.name = plant, level, plant.name
        self._phase = 0
        self._wrench = None

    @property
    def hover_input(self) -> np.ndarray:
        """Hover at this level: the weight's thrust and no rate (``ctbr``) or no tilt and no yaw rate (``ctatt``)."""
        return self.plant.hover_input

    def _reset(self, x0, rotor_speed):
        self.loop.reset()
        self._phase, self._wrench = 0, None
        return self.plant.reset(x0, rotor_speed=rotor_speed)

    def _advance(self, u, ticks):
        out = None
        while ticks > 0:
            if self._phase == 0:
                self._wrench = self.loop.update(u, self.plant.x)
            n = min(ticks, self.loop.config.ticks - self._phase)
            out = self.plant.advance(self._wrench, n * PLANT_TICK_S)
            self._phase = (self._phase + n) % self.loop.config.ticks
            ticks -= n
        return out

    def describe(self) -> dict:
        return {**self.plant.describe(), "level": self.level, "inner_loop": self.loop.config.to_dict()}
