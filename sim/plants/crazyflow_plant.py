"""A Crazyflie simulated by others: ``crazyflow``'s first-principles model with its Mellinger onboard loops.

``crazyflow`` (PyPI 0.4.0, MIT; optional extra ``crazyflow``: JAX, MuJoCo and Flax) simulates the Crazyflies of
``drone-models`` in JAX. Its first-principles model integrates the rigid body with rotor dynamics (a first-order
response of each rotor's speed), a thrust and a torque quadratic in the speed, and the drone's mixer; its onboard
controllers are the Crazyflie firmware's Mellinger loops, with gains per drone:

* at ``ctbr`` the body-rate loop (``Control.body_rate``: body rates and collective thrust in, rotor speeds out);
* at ``ctatt`` the attitude loop (``Control.attitude``: roll, pitch, yaw and collective thrust in).

Both run at :data:`LOOP_HZ` (the firmware's 500 Hz) inside the plant's 1 ms tick (:data:`SIM_HZ`). Nothing of its
model or its loops is rewritten here; what this module adds is the boundary:

* frames: crazyflow is z-up with an FLU body and ``R = Rz(yaw) Ry(pitch) Rx(roll)``, its attitude a quaternion
  (x, y, z, w); with ``F = diag(1, -1, -1)`` positions and velocities convert as ``F v``, body rates as ``F w`` and
  the angles as ``(phi, -theta, -psi)`` (:mod:`sim.plants.zup_frames`, as for RotorPy and drone-models). Its
  floor stops a drone at height 0, so this plant flies :data:`ALTITUDE_OFFSET_M` above it (our scenarios fly near
  the origin);
* the command: ours at ``ctbr`` is ``[T, p, q, r]``; at ``ctatt`` ``[T, phi, theta, r]`` with a yaw *rate*, which
  crazyflow takes as a yaw *angle*, so the yaw-rate command is integrated, from the yaw at :meth:`reset`, at every
  tick. Rate commands are clipped to the vehicle's ``max_rate`` and tilt commands to its ``max_tilt`` (as the other
  plants' loops do);
* a wind (a world-frame acceleration) enters as crazyflow's disturbance force, mass times acceleration; a payload is
  added to the model's mass (its controllers keep theirs).

crazyflow needs SciPy in its array-API mode, set before SciPy's first import, which this project does not set; so
it runs in a child process of the plant (:mod:`sim.plants.crazyflow_worker`), in double precision
(``jax_enable_x64``). Starting it and compiling its pipeline take a few seconds per plant. The vehicle must be one of crazyflow's drones with a vehicle file
of this project (:data:`DRONES`), so that the controllers' nominal models can be built; the model's own mass and
thrust curve are crazyflow's, not the vehicle file's (``describe()`` records both masses). Rotor speeds are
reported in rad/s in crazyflow's rotor order, which is not this project's, so telemetry gets NaN; the realized
wrench is the thrust of the rotor speeds, with NaN torques, and nothing is reported saturated.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
import subprocess
import sys
import tempfile
import weakref
from pathlib import Path

import numpy as np

from ..errors import PlantUnavailableError, SimInputError
from ..levels import check_level
from ..vehicles.vehicle import Vehicle
from .plant import PLANT_TICK_S, Plant, PlantOutput, WindFn, plant_time
from .zup_frames import FLIP, euler_from_quat, quat_from_euler, unwrap_euler

#: crazyflow's drones that have a vehicle file here.
DRONES = ("cf2x_L250",)
#: The levels flown, and crazyflow's control mode of each.
CONTROL_AT = {"ctbr": "body_rate", "ctatt": "attitude"}
#: Integration rate of crazyflow's dynamics, Hz (one step per tick of :meth:`Plant.advance`).
SIM_HZ = int(round(1.0 / PLANT_TICK_S))
#: Rate of its onboard loops, Hz (the firmware's).
LOOP_HZ = 500
#: Height of our origin above crazyflow's floor, m.
ALTITUDE_OFFSET_M = 100.0

_UNAVAILABLE = "plant 'crazyflow' needs the crazyflow package: python -m pip install -e '.[crazyflow]'"


def _start_worker(drone: str, control: str, payload_kg: float) -> subprocess.Popen:
    """crazyflow's process (:mod:`sim.plants.crazyflow_worker`), with SciPy's array-API mode set for it alone."""
    root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "SCIPY_ARRAY_API": "1", "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": os.pathsep.join([root] + [p for p in [os.environ.get("PYTHONPATH")] if p])}
    return subprocess.Popen([sys.executable, "-m", "sim.plants.crazyflow_worker", drone, control, str(SIM_HZ),
                             str(LOOP_HZ), repr(float(payload_kg))], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, env=env, cwd=tempfile.gettempdir())   # MuJoCo logs to its cwd


def _stop_worker(proc: subprocess.Popen) -> None:
    """Ask crazyflow's process to end, and make sure it does."""
    try:
        pickle.dump(("close",), proc.stdin)
        proc.stdin.close()
        proc.wait(timeout=5)
    except Exception:           # noqa: BLE001 - a process already gone, a broken pipe
        proc.kill()


def crazyflow_available() -> bool:
    """True when crazyflow is installed (nothing is imported)."""
    return importlib.util.find_spec("crazyflow") is not None


class CrazyflowPlant(Plant):
    """crazyflow's first-principles Crazyflie with its Mellinger loop at ``ctbr`` or ``ctatt`` (see the module
    docstring). crazyflow runs in a child process (:mod:`sim.plants.crazyflow_worker`), closed with the plant.

    Parameters
    ----------
    vehicle : Vehicle or name
        One of :data:`DRONES`.
    level : str
        ``ctbr`` or ``ctatt`` (``wrench`` is refused: crazyflow's loops take rates or attitudes).
    payload_kg : float
        Added to the model's mass, kg.
    wind : callable, optional
        ``wind(t) -> (3,)``: a world-frame (NED) acceleration, m/s^2, held over each call.

    Raises
    ------
    PlantUnavailableError
        crazyflow is not installed, or does not start.
    SimInputError
        Another level or vehicle.
    """

    def __init__(self, vehicle: Vehicle | str, level: str = "ctbr", *, payload_kg: float = 0.0,
                 wind: WindFn | None = None):
        super().__init__(vehicle, payload_kg=payload_kg, wind=wind)
        check_level(level)
        if level not in CONTROL_AT:
            raise SimInputError(f"plant 'crazyflow' takes commands at the {' or '.join(map(repr, CONTROL_AT))} level "
                                f"(its onboard loops take body rates or attitudes); found level {level!r}")
        if self.vehicle.name not in DRONES:
            raise SimInputError(f"plant 'crazyflow' flies the drones it models that have a vehicle file here "
                                f"({', '.join(DRONES)}); found vehicle {self.vehicle.name!r}")
        if not crazyflow_available():
            raise PlantUnavailableError(_UNAVAILABLE)
        self.level, self.name = level, "crazyflow"
        self.loop = self.vehicle.inner_loop_at(level)
        self._control = CONTROL_AT[level]
        self._proc = _start_worker(self.vehicle.name, self._control, self.payload_kg)
        self._finalizer = weakref.finalize(self, _stop_worker, self._proc)
        ready = self._answer()
        if ready[0] != "ready":
            self.close()
            raise PlantUnavailableError(f"plant 'crazyflow' did not start: {ready[1]}")
        _, self.model_mass, self._rpm2thrust, gravity = ready
        self._hover = (self.model_mass + self.payload_kg) * float(-gravity[2])
        self._yaw_ref = 0.0
        self._rpm = np.zeros(4)

    def close(self) -> None:
        """Stop crazyflow's process (also done when the plant is collected)."""
        self._finalizer()

    def _request(self, *msg):
        """Send one request; the answer's state, or a RuntimeError with the child's message."""
        pickle.dump(msg, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self._proc.stdin.flush()
        answer = self._answer()
        if answer[0] != "ok":
            raise RuntimeError(f"plant 'crazyflow': {answer[1]}")
        return answer[1:]

    def _answer(self):
        try:
            return pickle.load(self._proc.stdout)
        except EOFError:
            return ("error", f"its process ended (exit code {self._proc.wait()})")

    @property
    def hover_input(self) -> np.ndarray:
        """The command that holds the model still: its own weight (crazyflow's mass), level."""
        return np.array([self._hover, 0.0, 0.0, 0.0])

    def _hover_rpm(self) -> float:
        c0, c1, c2 = self._rpm2thrust
        per_rotor = self._hover / 4.0
        return float((-c1 + np.sqrt(c1 * c1 - 4.0 * c2 * (c0 - per_rotor))) / (2.0 * c2))

    def _reset(self, x0, rotor_speed):
        quat = quat_from_euler(*x0[3:6])
        pos = x0[0:3] * FLIP + np.array([0.0, 0.0, ALTITUDE_OFFSET_M])
        state = self._request("reset", pos, quat, x0[9:12] * FLIP, x0[6:9] * FLIP, np.full(4, self._hover_rpm()))
        self._rpm = state[4]
        self._yaw_ref = float(x0[5])
        return self._output(np.array(x0, dtype=float))

    def _output(self, x) -> PlantOutput:
        c0, c1, c2 = self._rpm2thrust
        rpm = self._rpm
        thrust = float(np.sum(c0 + c1 * rpm + c2 * rpm * rpm))
        return PlantOutput(x, np.full(4, np.nan), np.array([thrust, np.nan, np.nan, np.nan]), np.zeros(4, dtype=bool))

    def _advance(self, u, ticks):
        c = self.loop
        force = np.zeros(3) if self.wind is None else \
            (self.model_mass + self.payload_kg) * FLIP * np.asarray(self.wind(plant_time(self._ticks)), dtype=float)
        if self._control == "body_rate":
            rates = np.clip(u[1:4], -c.max_rate, c.max_rate) * FLIP
            state = self._request("body_rate", np.array([rates[0], rates[1], rates[2], u[0]]), ticks, force)
        else:
            tilt = np.clip(u[1:3], -c.max_tilt, c.max_tilt)
            r = float(np.clip(u[3], -c.max_rate, c.max_rate))
            yaws = -(self._yaw_ref + r * PLANT_TICK_S * np.arange(1, ticks + 1))
            self._yaw_ref += r * PLANT_TICK_S * ticks
            state = self._request("attitude", float(tilt[0]), float(-tilt[1]), yaws, float(u[0]), force)
        pos, quat, vel, ang_vel, self._rpm = state
        x = np.empty(12)
        x[0:3] = (pos - np.array([0.0, 0.0, ALTITUDE_OFFSET_M])) * FLIP
        x[3:6] = unwrap_euler(euler_from_quat(quat), self.x[3:6])    # continuous, never wrapped
        x[6:9] = ang_vel * FLIP
        x[9:12] = vel * FLIP
        return self._output(x)

    def describe(self) -> dict:
        from importlib import metadata

        try:
            version = metadata.version("crazyflow")
        except metadata.PackageNotFoundError:   # pragma: no cover
            version = "unknown"
        return {**super().describe(), "level": self.level, "crazyflow": version, "model": "first_principles",
                "onboard": f"Mellinger {self._control} loop at {LOOP_HZ} Hz", "model_mass_kg": self.model_mass,
                "integrator": {"rate_hz": SIM_HZ}}
