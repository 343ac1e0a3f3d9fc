"""The onboard attitude loop as a prediction model: a logged vehicle's body rates, given its state and rotor speeds.

A logged vehicle flies under its own controller. Over half a second its body
rates are not what the logged rotor speeds' torques give through the stated
inertia (on the nano-drone benchmark's logs those torques explain 0 to 42 % of
the angular acceleration), nor constant (the benchmark's Physics model holds
them): they are what the onboard loop makes of its setpoint. This model says
so with a few coefficients, one set for the vehicle:

* roll and pitch are pulled towards a setpoint with a stiffness ``K`` (1/s^2)
  and damped with ``D`` (1/s); yaw is damped only;
* the setpoint is not logged. It is taken as held over the prediction, from
  the window's first state: ``eta_sp = eta_0 + T_lead * omega_0`` (roll and
  pitch, rad; ``T_lead`` in s), moved by a velocity loop with gain ``K_v``
  (rad per m/s): pitch up as the heading-frame forward velocity grows past its
  start value, roll left as the rightward one does;
* the logged torques enter with a gain per axis ``G`` on ``J^-1 tau`` (1 for
  the stated inertia), plus a bias ``b`` (rad/s^2):

  ``omega_dot = -D omega - K (eta - eta_sp) + J^-1 (G tau - omega x J omega) + b``

  (with ``D = K = b = 0`` and ``G = 1``, Euler's equations).

The setpoint and the start velocity are four extra states carried through a
prediction (:data:`EXTRA_STATES`), filled by :meth:`AttitudeLoop.start`. The
coefficients are fitted to open-loop predictions of the training flights
(:func:`sim.flightlogs.logident.fit_attitude_loop`), not to one-step
differences: a closed loop's one-step response says little about its
half-second one.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

#: Why a model with the attitude loop is not flown: its extra states are a prediction's construct, not a vehicle's.
NOT_FLYABLE = ("its roll and pitch are pulled to a setpoint held from the prediction's start, which no controller "
               "sets: it predicts a logged closed loop, it does not say what a torque does")
#: Extra states after the 12 of the rigid body: the held roll and pitch setpoints (rad) and the heading-frame
#: horizontal velocity at the window's start (forward, right; m/s).
EXTRA_STATES = ("roll setpoint", "pitch setpoint", "start forward velocity", "start right velocity")


def heading_velocity(x: np.ndarray) -> np.ndarray:
    """Horizontal velocity (..., 2) of states ``x`` (..., >= 12) in the heading frame: forward and right, m/s."""
    c, s = np.cos(x[..., 5]), np.sin(x[..., 5])
    return np.stack([c * x[..., 9] + s * x[..., 10], -s * x[..., 9] + c * x[..., 10]], -1)


@dataclass(frozen=True)
class AttitudeLoop:
    """Coefficients of the onboard attitude loop (module docstring); every field a tuple of floats or a float."""

    damping: tuple = (0.0, 0.0, 0.0)          # D per body axis, 1/s
    stiffness: tuple = (0.0, 0.0)             # K for roll and pitch, 1/s^2
    lead: float = 0.0                         # T_lead, s
    torque_gain: tuple = (1.0, 1.0, 1.0)      # G per body axis, 1 = the stated inertia
    bias: tuple = (0.0, 0.0, 0.0)             # b per body axis, rad/s^2
    velocity_gain: float = 0.0                # K_v, rad per m/s

    #: Units of each field, for records.
    UNITS = {"damping": "1/s", "stiffness": "1/s^2", "lead": "s", "torque_gain": "1", "bias": "rad/s^2",
             "velocity_gain": "rad/(m/s)"}
    #: How many numbers each field holds, in :meth:`vector` order.
    SIZES = {"damping": 3, "stiffness": 2, "lead": 1, "torque_gain": 3, "bias": 3, "velocity_gain": 1}

    def vector(self) -> np.ndarray:
        """All coefficients as one vector (13,), in the order of :data:`SIZES`."""
        return np.concatenate([np.atleast_1d(np.asarray(getattr(self, n), dtype=float)) for n in self.SIZES])

    @classmethod
    def from_vector(cls, v) -> "AttitudeLoop":
        """The inverse of :meth:`vector`."""
        v = np.asarray(v, dtype=float)
        out, i = {}, 0
        for name, size in cls.SIZES.items():
            part = tuple(float(a) for a in v[i:i + size])
            out[name] = part[0] if size == 1 else part
            i += size
        return cls(**out)

    def to_dict(self) -> dict:
        """``{field: value}`` with plain floats (the study's JSON)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def start(self, x: np.ndarray) -> np.ndarray:
        """States (B, 16) at window starts ``x`` (B, 12): the logged state and the :data:`EXTRA_STATES`."""
        x = np.asarray(x, dtype=float)
        sp = x[:, 3:5] + self.lead * x[:, 6:8]
        return np.concatenate([x, sp, heading_velocity(x)], axis=1)

    def angular_acceleration(self, z: np.ndarray, torque: np.ndarray, inertia) -> np.ndarray:
        """Body angular acceleration (B, 3), rad/s^2, at states ``z`` (B, 16), with the logged torques ``torque``
        (B, 3), N m, and the principal inertias ``inertia`` (3,), kg m^2. The rigid body's gyroscopic coupling
        ``-J^-1 (omega x J omega)`` is part of it: with no damping, stiffness, bias or velocity gain and gains of 1
        these are Euler's equations."""
        J = np.asarray(inertia, dtype=float)
        w = z[:, 6:9]
        dv = heading_velocity(z) - z[:, 14:16]
        target = np.stack([z[:, 12] - self.velocity_gain * dv[:, 1], z[:, 13] + self.velocity_gain * dv[:, 0]], -1)
        out = (np.asarray(self.torque_gain) * torque - np.cross(w, w * J)) / J
        out += -np.asarray(self.damping) * w + np.asarray(self.bias)
        out[:, 0:2] -= np.asarray(self.stiffness) * (z[:, 3:5] - target)
        return out
