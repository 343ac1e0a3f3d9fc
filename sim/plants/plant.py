"""Plants: what a closed loop flies. One small interface, several simulators behind it.

A plant holds the true state of one vehicle and advances it under a
wrench command held constant::

    plant = make_plant("sim", vehicle)           # sim.plants.named; or "rotorpy", "rotorpy-ideal"
    out = plant.reset(x0)                        # state (12,), NED, ZYX Euler angles
    out = plant.advance(u, DT)                   # hold u = [T, tau_x, tau_y, tau_z] for one period
    out.x, out.rotor_speed, out.wrench           # the true state and what telemetry may read

``advance`` takes any whole number of milliseconds (the real-time clock
flies a period in pieces). Disturbances are options of the plant: a payload
(kg, the rotor limits stay the vehicle's) and a wind given as a world-frame
acceleration ``wind(t) -> (3,)`` (m/s^2), evaluated at the start of each
call to ``advance``.

``advance_ticks(u, duration)`` flies the same as ``advance(u, 1 ms)`` once
per millisecond and returns the state after every millisecond (what sensors
sampled every millisecond read, :mod:`sim.plants.sensors`): any plant makes those
calls, the reference simulator flies them in one call with the same numbers.

Names (:data:`sim.plants.named.PLANTS`, built by :func:`sim.plants.named.make_plant`):

* ``sim``: the reference simulator of this package (:class:`SimPlant`),
  nominal or with the vehicle's high-fidelity effects;
* ``rotorpy``: RotorPy's ``Multirotor`` with the vehicle's motor lag and
  RotorPy's aerodynamics (rotor drag, induced inflow, translational lift,
  flapping, parasitic drag);
* ``rotorpy-ideal``: RotorPy with instant motors and no aerodynamics, no
  drag at all: the rigid-body equations, integrated by another code.

RotorPy is an optional dependency (``pip install -e '.[rotorpy]'``); see
:mod:`sim.plants.rotorpy_plant`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._validate import as_batch, nonnegative_finite
from ..errors import SimInputError
from ..params import DT, NOMINAL, NU, NX, SUBSTEPS, Fidelity
from ..equations.simulator import WindFn
from ..vehicles.vehicle import Vehicle, load_vehicle


#: Resolution of :meth:`Plant.advance`, s (the reference simulator's RK4 substep).
PLANT_TICK_S = DT / SUBSTEPS


class PlantOutput(NamedTuple):
    """The plant after a call (units in comments)."""

    x: np.ndarray            # (12,) true state, NED, ZYX Euler angles (continuous, never wrapped)
    rotor_speed: np.ndarray  # (4,) rotor speeds, RU (telemetry), rotors in this project's order
    wrench: np.ndarray       # (4,) wrench the rotors realized at the start of the call, N and N m
    saturated: np.ndarray    # (4,) bool: rotor command clipped at 0 or at n_max


class TickTrace(NamedTuple):
    """The plant after every tick of a call of :meth:`Plant.advance_ticks` (K ticks; units in comments)."""

    x: np.ndarray            # (K + 1, 12) true state at the start of the call and after each tick
    rotor_speed: np.ndarray  # (K, 4) rotor speeds after each tick, RU
    out: PlantOutput         # the plant after the last tick (what advance returns)


def plant_time(ticks: int) -> float:
    """Time after ``ticks`` ticks from t = 0, s: whole periods exactly as ``k * DT`` (the wind of a period is
    evaluated at that time), plus the ticks of the period begun."""
    return (ticks // SUBSTEPS) * DT + (ticks % SUBSTEPS) * PLANT_TICK_S


class Plant:
    """Interface of a plant (see the module docstring).

    Attributes
    ----------
    name : str
        One of :data:`PLANTS` (or a user's own).
    vehicle : Vehicle
        The vehicle flown.
    t : float
        Time of the current state, s (0 after :meth:`reset`).
    """

    name: str = "plant"

    def __init__(self, vehicle: Vehicle | None = None, *, payload_kg: float = 0.0, wind: WindFn | None = None):
        self.vehicle = load_vehicle(vehicle)
        self.payload_kg = nonnegative_finite(payload_kg, "payload_kg")
        if wind is not None and not callable(wind):
            raise SimInputError(f"wind must be a callable wind(t) -> acceleration (3,); found {type(wind).__name__}")
        self.wind = wind
        self.t = 0.0
        self._out: PlantOutput | None = None

    @property
    def x(self) -> np.ndarray:
        """The true state (12,)."""
        if self._out is None:
            raise SimInputError(f"plant {self.name!r}: call reset(x0) before reading its state")
        return self._out.x

    @property
    def hover_input(self) -> np.ndarray:
        """The vehicle's hover wrench ``[m g, 0, 0, 0]`` (without payload): what holds it before a first command."""
        p = self.vehicle.params
        return np.array([p.m * p.g, 0.0, 0.0, 0.0])

    def reset(self, x0, rotor_speed=None) -> PlantOutput:
        """Put the vehicle in state ``x0`` (12,) at t = 0, rotors at ``rotor_speed`` (4,) RU.

        ``rotor_speed`` None: the plant's default (hover speed; in the
        reference simulator, the first command's speed).
        """
        x0 = as_batch(x0, "x0", NX)
        if x0.shape != (NX,):
            raise SimInputError(f"x0 must be one state of shape (12,); found {x0.shape}")
        if rotor_speed is not None:
            rotor_speed = as_batch(rotor_speed, "rotor_speed", 4).reshape(4).copy()
        self._ticks = 0
        self.t = 0.0
        self._out = self._reset(x0.copy(), rotor_speed)
        return self._out

    @property
    def rotor_speed(self) -> np.ndarray:
        """Rotor speeds (4,) now, RU: after the last call (at a reset, the plant's start value)."""
        if self._out is None:
            raise SimInputError(f"plant {self.name!r}: call reset(x0) before reading its rotor speeds")
        return self._out.rotor_speed

    def advance(self, u, duration_s: float = DT) -> PlantOutput:
        """Hold the wrench command ``u`` (4,) for ``duration_s`` (a whole number of ms); the plant after it."""
        u, ticks = self._call(u, duration_s)
        self._out = self._advance(u, ticks)
        self._ticks += ticks
        self.t = plant_time(self._ticks)
        return self._out

    def advance_ticks(self, u, duration_s: float = DT) -> TickTrace:
        """Hold ``u`` (4,) for ``duration_s`` as ``advance(u, tick)`` once per tick (1 ms); the plant after each.

        The plant ends exactly as after those calls (state, time, rotor speeds, last output), and the states
        are theirs. A plant may fly them faster than one call per tick (the reference simulator flies them in
        one); the others make the calls.

        Parameters
        ----------
        u : array_like, shape (4,)
            Wrench command ``[T, tau_x, tau_y, tau_z]``, N and N m.
        duration_s : float
            A whole number of ticks, s.

        Returns
        -------
        TickTrace
            The states (K + 1, 12) at the start and after each of the K ticks, the rotor speeds (K, 4) after
            each, and the last output.
        """
        u, ticks = self._call(u, duration_s)
        return self._advance_ticks(u, ticks)

    def _call(self, u, duration_s: float) -> tuple[np.ndarray, int]:
        """The checked command (4,) and number of ticks of a call of :meth:`advance`."""
        if self._out is None:
            raise SimInputError(f"plant {self.name!r}: call reset(x0) before advance")
        u = np.asarray(u, dtype=float)
        if u.shape != (NU,):
            raise SimInputError(f"u must have shape (4,); found {u.shape}")
        ticks = int(round(duration_s / PLANT_TICK_S))
        if ticks < 1 or abs(ticks * PLANT_TICK_S - duration_s) > 1e-12:
            raise SimInputError(f"duration_s must be a whole number of {PLANT_TICK_S * 1e3:g} ms; found {duration_s}")
        return u, ticks

    def step(self, u) -> PlantOutput:
        """One control period: ``advance(u, DT)``."""
        return self.advance(u, DT)

    def describe(self) -> dict:
        """JSON-ready description stored with results: name, vehicle, disturbances, set-up."""
        return {"plant": self.name, "vehicle": self.vehicle.name, "payload_kg": self.payload_kg}

    # Implementations provide these two.
    def _reset(self, x0: np.ndarray, rotor_speed: np.ndarray | None) -> PlantOutput:  # pragma: no cover - interface
        raise NotImplementedError

    def _advance(self, u: np.ndarray, ticks: int) -> PlantOutput:  # pragma: no cover - interface
        raise NotImplementedError

    def _advance_ticks(self, u: np.ndarray, ticks: int) -> TickTrace:
        """``ticks`` calls of ``advance(u, tick)`` (any plant); an implementation may do the same faster."""
        xs, ns = [self.x], []
        for _ in range(ticks):
            out = self.advance(u, PLANT_TICK_S)
            xs.append(out.x)
            ns.append(out.rotor_speed)
        return TickTrace(np.array(xs), np.array(ns), out)


class SimPlant(Plant):
    """The reference simulator (:class:`sim.Simulator`) behind the plant interface.

    Parameters
    ----------
    vehicle : Vehicle or name, optional
        The Rolling Spider when omitted.
    fidelity : Fidelity
        Effects beyond the nominal equations (nominal by default; the
        vehicle's own are :attr:`Vehicle.fidelity`).
    payload_kg, wind
        As in :class:`Plant`.
    """

    name = "sim"

    def __init__(self, vehicle: Vehicle | None = None, fidelity: Fidelity = NOMINAL, *, payload_kg: float = 0.0,
                 wind: WindFn | None = None):
        super().__init__(vehicle, payload_kg=payload_kg, wind=wind)
        if not isinstance(fidelity, Fidelity):
            raise SimInputError(f"fidelity must be a Fidelity; found {type(fidelity).__name__}")
        self.fidelity = fidelity
        self._sims: dict[int, object] = {}
        self._n = None

    def _sim(self, ticks: int):
        from ..equations.simulator import Simulator

        if ticks not in self._sims:
            self._sims[ticks] = Simulator(self.vehicle.params, self.fidelity, dt=ticks * PLANT_TICK_S,
                                          substeps=ticks, payload_kg=self.payload_kg, wind=self.wind)
        return self._sims[ticks]

    def _reset(self, x0, rotor_speed):
        # Without motor lag the rotors run at the commanded speed; with it they carry over from call to call, and
        # (rotor_speed None) start at the first command's speed.
        self._n = rotor_speed
        n = np.full(4, self.vehicle.params.n_hover) if rotor_speed is None else rotor_speed
        return PlantOutput(x0, n, np.full(4, np.nan), np.zeros(4, dtype=bool))

    def _advance(self, u, ticks):
        with np.errstate(all="ignore"):     # a diverging flight is the crash test's business, not an error
            res = self._sim(ticks).step_full(self.x, u, rotor_speed=self._n, t=self.t)
        self._n = res.rotor_speed
        return PlantOutput(res.x, res.rotor_speed, res.wrench, res.saturated)

    def _advance_ticks(self, u, ticks):
        # The one-tick step chained `ticks` times in one CasADi call: the numbers of `ticks` calls of advance(u,
        # tick), without their checks and Python work per tick. Where those calls would stop with an error (a
        # command, state or rotor speed that is not finite, a wind that fails), they are made instead, and fail
        # where they failed.
        x0, n0 = self.x, self._n
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(x0)) and (n0 is None or np.all(np.isfinite(n0)))):
            return super()._advance_ticks(u, ticks)
        sim = self._sim(1)
        try:
            accel = sim._wind_accels([plant_time(self._ticks + j) for j in range(ticks)])
        except Exception:  # noqa: BLE001 - a wind that fails: the ticks one at a time raise it at its tick
            return super()._advance_ticks(u, ticks)
        with np.errstate(all="ignore"):     # a diverging flight is the crash test's business, not an error
            xs, ns, res = sim._step_chain(x0, u, accel, n0)
        if not (np.all(np.isfinite(xs[:-1])) and np.all(np.isfinite(ns[:-1]))):
            return super()._advance_ticks(u, ticks)    # a tick would start from a state that is not finite
        self._n = res.rotor_speed
        self._out = PlantOutput(res.x, res.rotor_speed, res.wrench, res.saturated)
        self._ticks += ticks
        self.t = plant_time(self._ticks)
        return TickTrace(np.concatenate([x0[None], xs]), ns, self._out)

    def describe(self) -> dict:
        import dataclasses

        return {**super().describe(), "fidelity": dataclasses.asdict(self.fidelity)}
