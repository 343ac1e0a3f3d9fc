"""The process that runs crazyflow for :class:`sim.plants.crazyflow_plant.CrazyflowPlant`.

crazyflow needs SciPy in its array-API mode (``SCIPY_ARRAY_API=1``), which must be set before SciPy is first
imported and which this project's processes do not set. So the plant starts this module as a child process with
that setting (``python -m sim.plants.crazyflow_worker``) and talks to it over its standard input and output: one
pickled request, one pickled answer. Anything the child's libraries print goes to its standard error, never into
the answers. Requests (arrays in crazyflow's frames and units):

* ``("reset", pos, quat, vel, ang_vel, rpm)``: reset the simulation and its controllers, set the state;
* ``("body_rate", cmd (4,), ticks, force (3,))``: hold the body-rate command ``[wx, wy, wz, thrust]`` and the
  disturbance force for ``ticks`` steps;
* ``("attitude", roll, pitch, yaws (ticks,), thrust, force (3,))``: one step per yaw angle, each with that yaw;
* ``("close",)``.

Each answer is ``("ok", pos, quat, vel, ang_vel, rpm)`` or ``("error", message)``; the first answer, after start,
is ``("ready", mass, rpm2thrust, gravity)`` or an error.
"""

from __future__ import annotations

import os
import pickle
import sys


def _state(sim):
    import numpy as np

    s = sim.data.states
    return tuple(np.asarray(a[0, 0], dtype=float) for a in (s.pos, s.quat, s.vel, s.ang_vel, s.rotor_vel))


def serve(drone: str, control: str, sim_hz: int, loop_hz: int, payload_kg: float, inp, out) -> None:
    """Answer requests from ``inp`` on ``out`` (binary files) until ``close`` or the end of ``inp``."""
    import numpy as np

    def send(msg):
        pickle.dump(msg, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()

    try:
        import jax

        jax.config.update("jax_enable_x64", True)
        from crazyflow.control import Control
        from crazyflow.drones import Drone
        from crazyflow.dynamics import Dynamics
        from crazyflow.sim import Sim

        sim = Sim(n_worlds=1, n_drones=1, drone=Drone(drone), dynamics=Dynamics.first_principles,
                  control=Control(control), freq=sim_hz, attitude_freq=loop_hz, body_rate_freq=loop_hz,
                  force_torque_freq=loop_hz)
        sim.reset()
        params = sim.data.params
        mass = float(np.asarray(params.mass).ravel()[0])
        # A reset restores crazyflow's own parameters: the payload is added again after each.
        flown = params.replace(mass=params.mass + payload_kg) if payload_kg else params
        send(("ready", mass, np.asarray(params.rpm2thrust, dtype=float).ravel(),
              np.asarray(params.gravity_vec, dtype=float).ravel()))
    except Exception as e:      # noqa: BLE001 - whatever stops crazyflow is reported to the plant
        send(("error", f"{type(e).__name__}: {e}"))
        return
    while True:
        try:
            msg = pickle.load(inp)
        except EOFError:
            return
        try:
            op = msg[0]
            if op == "close":
                return
            s = sim.data.states
            if op == "reset":
                pos, quat, vel, ang_vel, rpm = msg[1:]
                sim.reset()
                s = sim.data.states
                sim.data = sim.data.replace(params=flown, states=s.replace(
                    pos=s.pos.at[0, 0].set(pos), quat=s.quat.at[0, 0].set(quat), vel=s.vel.at[0, 0].set(vel),
                    ang_vel=s.ang_vel.at[0, 0].set(ang_vel), rotor_vel=s.rotor_vel.at[0, 0].set(rpm)))
            elif op == "body_rate":
                cmd, ticks, force = msg[1:]
                sim.data = sim.data.replace(states=s.replace(force=s.force.at[0, 0].set(force)))
                sim.body_rate_control(np.asarray(cmd, dtype=float).reshape(1, 1, 4))
                sim.step(int(ticks))
            elif op == "attitude":
                roll, pitch, yaws, thrust, force = msg[1:]
                sim.data = sim.data.replace(states=s.replace(force=s.force.at[0, 0].set(force)))
                for yaw in yaws:
                    sim.attitude_control(np.array([[[roll, pitch, yaw, thrust]]], dtype=float))
                    sim.step(1)
            else:
                raise ValueError(f"unknown request {op!r}")
            send(("ok", *_state(sim)))
        except Exception as e:  # noqa: BLE001
            send(("error", f"{type(e).__name__}: {e}"))


def main() -> None:
    """Entry point of the child: its arguments are those of :func:`serve` but the files."""
    out = os.fdopen(os.dup(1), "wb")     # the answers keep the original standard output ...
    os.dup2(2, 1)                        # ... and whatever the libraries print goes to standard error
    drone, control, sim_hz, loop_hz, payload = sys.argv[1:6]
    serve(drone, control, int(sim_hz), int(loop_hz), float(payload), sys.stdin.buffer, out)


if __name__ == "__main__":
    main()
