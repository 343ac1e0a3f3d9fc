"""RotorPy as a plant: its ``Multirotor`` flies our wrench commands, in our frames.

:class:`RotorPyPlant` puts RotorPy's numpy ``Multirotor`` (RotorPy 3.x,
``rotorpy/vehicles/multirotor.py``) behind the :class:`sim.plants.plant.Plant`
interface, so a closed loop can fly a vehicle integrated by a code this
project did not write::

    plant = RotorPyPlant(vehicle, motor_lag=True, aero=True)   # make_plant("rotorpy", vehicle)
    out = plant.reset(x0)                   # x0 (12,): NED, FRD, ZYX Euler angles
    out = plant.advance(u, 0.01)            # u (4,) = [T, tau_x, tau_y, tau_z], N and N m

Set-ups (:attr:`RotorPyPlant.name`):

* ``rotorpy`` (``motor_lag=True, aero=True``): RotorPy's first-order motor
  lag (the vehicle's ``motor_tau``) and its aerodynamics: parasitic drag
  (``m c_d``, isotropic in the body frame and quadratic in the airspeed
  *norm*), rotor drag (``rotor_drag`` as ``k_d``), induced inflow
  (``k_z``), translational lift (``k_h``) and flapping (``k_flap``).
* ``rotorpy-ideal`` (``motor_lag=False, aero=False``): instant motors and
  no aerodynamic force at all (no drag either): the rigid-body equations of
  :mod:`sim.equations.dynamics` with ``c_d = 0``, integrated by RotorPy. It agrees
  with the reference simulator to about 2e-12 m per period (the tests hold it
  to 1e-8 m).
* ``rotorpy-custom``: either effect alone.

Conventions. RotorPy's world frame is z-up and its body frame FLU; ours
are NED and FRD. With ``F = diag(1, -1, -1)`` (a half turn about x) every
vector converts as ``F v`` in both frames (position, velocity, body rates,
torques, wind acceleration), the attitude as ``R_rp = F R F``, and the
thrust is unchanged. Our rotors 1-4 (:mod:`sim.vehicles.rotors`) are RotorPy's
``r2, r3, r4, r1`` (:data:`ROTORPY_INDEX`), placed at
``d (+-1/sqrt(2), +-1/sqrt(2), 0)``, our lever exactly (RotorPy's presets
write 0.70710678118, 9.3e-12 relative short). The rotor coefficients are
passed in our rotor units (``k_eta = kt``, ``k_m = kq``, speeds limited to
``[0, n_max]``), so RotorPy's "rad/s" are our RU. RotorPy's quaternion is
converted back to ZYX Euler angles unwrapped against the previous state,
so the angles stay continuous (``psi`` through +-pi and beyond).

Commands go through RotorPy's ``cmd_ctbm`` abstraction: its own allocation
to rotor thrusts, ``n = sign(f) sqrt(|f| / k_eta)``, clipped to
``[0, n_max]`` (equal to our clipping of ``n^2`` to ``[0, n_max^2]``).
RotorPy's rotors always carry a first-order lag; for instant motors the
rotor speeds are set to the clipped command at the start of every call, so
the lag term is exactly zero throughout it.

Disturbances: the payload is added to RotorPy's mass (the rotor limits stay
the vehicle's); the wind, a world-frame acceleration ``wind(t)`` (NED,
m/s^2) evaluated at the start of each call, is added to RotorPy's velocity
derivative by a subclass of ``Multirotor`` (RotorPy's own wind, an air
velocity, stays zero). RotorPy's gravity is fixed at 9.81 m/s^2. RotorPy draws its motor noise
(zero here) from numpy's global random generator at every step; the plant
restores that generator's state, so flying it changes no other draw.

Integration is ``scipy.integrate.solve_ivp`` over each call (RotorPy's
``Multirotor.step``), with tolerances per set-up (:data:`INTEGRATORS`),
both DOP853: over a 10 ms period it is a single step of 12 evaluations
where RK45 at 100 times looser tolerances takes as many and is 1000 times
less accurate. Measured on the Rolling Spider (RotorPy 3.0.0, scipy 1.17, a
shared two-core machine, so times vary by up to 2x):

* every set-up: 14 to 15 evaluations of RotorPy's derivative per 10 ms
  period (about 0.1 ms each): 1.3 ms per period for the ideal set-up,
  1.7 ms with motor lag and aero (up to twice that on a busy machine); the
  reference simulator's compiled step takes 0.13 ms;
* ideal set-up (rtol 1e-11, atol 1e-12): 1.8e-12 m from the reference
  simulator after one period (states within 2.2e-10);
* motor lag and aero (rtol 1e-8, atol 1e-10): within 1.3e-13 m of a
  rtol 1e-13 integration after 10 periods.

A vehicle whose motor lag is shorter than the period costs more: the
Hummingbird (``motor_tau`` 5 ms) takes about 60 evaluations, 7 to 13 ms per
period, with motor lag (5e-11 m from the tight integration after 10
periods).
"""

from __future__ import annotations

import contextlib
import io
import math
import warnings

import numpy as np

from .._validate import as_batch
from ..errors import PlantUnavailableError, SimInputError
from ..params import NX
from .plant import PLANT_TICK_S, Plant, PlantOutput, WindFn
from ..vehicles.rotors import wrench_from_rotor_sq
from ..vehicles.vehicle import Vehicle

#: RotorPy's index (0-based) of our rotor i: our rotors 1-4 are RotorPy's r2, r3, r4, r1. For an array ``a`` in our
#: order, ``rp = np.empty(4); rp[ROTORPY_INDEX] = a`` is RotorPy's order; ``rp[ROTORPY_INDEX]`` is ours again.
ROTORPY_INDEX = np.array([1, 2, 3, 0])
#: The frame flip ``diag(F)``: NED <-> z-up world, FRD <-> FLU body.
FLIP = np.array([1.0, -1.0, -1.0])
#: RotorPy's gravity, m/s^2 (fixed in ``Multirotor``).
ROTORPY_G = 9.81
#: ``solve_ivp`` settings per set-up (``ideal``: no motor lag and no aerodynamics; ``physics``: any effect on).
#: The ideal set-up is held to the reference simulator to 1e-8 m per period (it agrees to about 2e-12 m); the
#: other keeps its physics to about 1e-12 m per period (one DOP853 step per 10 ms on the Rolling Spider).
INTEGRATORS = {
    "ideal": {"method": "DOP853", "rtol": 1e-11, "atol": 1e-12},
    "physics": {"method": "DOP853", "rtol": 1e-8, "atol": 1e-10},
}

_UNAVAILABLE = "plant 'rotorpy' needs RotorPy: pip install -e '.[rotorpy]'"
_WindMultirotor = None   # the Multirotor subclass, built on first use (RotorPy is imported lazily)


@contextlib.contextmanager
def _without_torch():
    """Import RotorPy without torch: its module tries torch for its batched vehicle (not used here) and carries
    on without it, which keeps the flying processes free of torch (2 s and 660 MB). A torch already imported stays."""
    import sys

    blocked = "torch" not in sys.modules
    if blocked:
        sys.modules["torch"] = None     # makes "import torch" raise ImportError
    try:
        yield
    finally:
        if blocked and sys.modules.get("torch", 0) is None:
            del sys.modules["torch"]


def _multirotor_class():
    """The ``Multirotor`` subclass with an extra world acceleration (imports RotorPy on first call)."""
    global _WindMultirotor
    if _WindMultirotor is not None:
        return _WindMultirotor
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), _without_torch():
            warnings.simplefilter("ignore")
            from rotorpy.vehicles.multirotor import Multirotor
    except ImportError as e:
        raise PlantUnavailableError(_UNAVAILABLE) from e

    class WindMultirotor(Multirotor):
        """RotorPy's ``Multirotor`` plus a constant world-frame acceleration ``accel`` (z-up, m/s^2)."""

        accel = np.zeros(3)

        def _s_dot_fn(self, t, s, cmd_rotor_speeds):
            s_dot = super()._s_dot_fn(t, s, cmd_rotor_speeds)
            s_dot[3:6] += self.accel
            return s_dot

    _WindMultirotor = WindMultirotor
    return WindMultirotor


def rotorpy_params(vehicle: Vehicle, payload_kg: float = 0.0, tau_m: float | None = None) -> dict:
    """RotorPy's ``quad_params`` dictionary of ``vehicle`` (in our rotor units).

    Parameters
    ----------
    vehicle : Vehicle
        The vehicle.
    payload_kg : float
        Added to the mass, kg.
    tau_m : float, optional
        Motor time constant, s (the vehicle's ``motor_tau`` when omitted; RotorPy needs one > 0).

    Returns
    -------
    dict
        Mass (kg), inertias (kg m^2), rotor positions (m, FLU, RotorPy's ``r1..r4``), rotor directions, rotor
        coefficients (``k_eta = kt`` N/RU^2, ``k_m = kq`` N m/RU^2), speed limits ``[0, n_max]`` (RU), motor lag,
        drag and lift coefficients, no motor noise.
    """
    d = vehicle.d
    c = math.sqrt(0.5)   # our lever d / sqrt(2) exactly (RotorPy's presets write 0.70710678118)
    cd = vehicle.parasitic_drag
    return {
        "mass": vehicle.m + payload_kg,
        "Ixx": vehicle.Jxx, "Iyy": vehicle.Jyy, "Izz": vehicle.Jzz, "Ixy": 0.0, "Ixz": 0.0, "Iyz": 0.0,
        "num_rotors": 4,
        "rotor_pos": {"r1": d * np.array([c, c, 0.0]), "r2": d * np.array([c, -c, 0.0]),
                      "r3": d * np.array([-c, -c, 0.0]), "r4": d * np.array([-c, c, 0.0])},
        "rotor_directions": np.array([1, -1, 1, -1]),
        "c_Dx": cd, "c_Dy": cd, "c_Dz": cd,
        "k_eta": vehicle.kt, "k_m": vehicle.kq,
        "k_d": vehicle.rotor_drag, "k_z": vehicle.k_z, "k_h": vehicle.k_h, "k_flap": vehicle.k_flap,
        "tau_m": vehicle.motor_tau if tau_m is None else tau_m,
        "rotor_speed_min": 0.0, "rotor_speed_max": vehicle.n_max_value,
        "motor_noise_std": 0.0,
    }


def _quat_from_euler(phi: float, theta: float, psi: float) -> np.ndarray:
    """RotorPy's quaternion (xyzw) of our ZYX Euler angles: ``R_rp = F R F = Rz(-psi) Ry(-theta) Rx(phi)``."""
    cr, sr = math.cos(0.5 * phi), math.sin(0.5 * phi)
    cp, sp = math.cos(-0.5 * theta), math.sin(-0.5 * theta)
    cy, sy = math.cos(-0.5 * psi), math.sin(-0.5 * psi)
    return np.array([sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy,
                     cr * cp * cy + sr * sp * sy])


def _euler_from_quat(q: np.ndarray) -> np.ndarray:
    """Our ZYX Euler angles (phi, theta, psi) of RotorPy's quaternion (xyzw), |theta| <= pi/2, others in [-pi, pi]."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    # Rotation matrix of the z-up/FLU attitude; ours is F R F: R[i, j] * F_i * F_j.
    r00 = 1.0 - 2.0 * (y * y + z * z)
    r10 = 2.0 * (x * y + z * w)
    r20 = 2.0 * (x * z - y * w)
    r21 = 2.0 * (y * z + x * w)
    r22 = 1.0 - 2.0 * (x * x + y * y)
    # Ours: R00 = r00, R10 = -r10, R20 = -r20, R21 = r21, R22 = r22.
    phi = math.atan2(r21, r22)
    theta = math.atan2(r20, math.hypot(r21, r22))
    psi = math.atan2(-r10, r00)
    return np.array([phi, theta, psi])


def unwrap_euler(angles, previous) -> np.ndarray:
    """The ZYX Euler angles of the attitude ``angles`` (3,) nearest to ``previous`` (3,), rad.

    Both representations of one attitude, ``(phi, theta, psi)`` and ``(phi + pi, pi - theta, psi + pi)``, are
    shifted by whole turns towards ``previous``; the nearer one is returned, so angles integrated through +-pi
    (and beyond) stay continuous.
    """
    a = np.asarray(angles, dtype=float)
    prev = np.asarray(previous, dtype=float)
    best, best_d = None, math.inf
    for cand in (a, np.array([a[0] + math.pi, math.pi - a[1], a[2] + math.pi])):
        shifted = cand + 2.0 * math.pi * np.round((prev - cand) / (2.0 * math.pi))
        dist = float(np.sum((shifted - prev) ** 2))
        if dist < best_d:
            best, best_d = shifted, dist
    return best


def to_rotorpy_state(x, rotor_speed) -> dict:
    """RotorPy's state dictionary of our state ``x`` (12,) and rotor speeds (4,) in our order, RU.

    Returns
    -------
    dict
        ``x`` (3,) m and ``v`` (3,) m/s in the z-up world frame, ``q`` (4,) xyzw, ``w`` (3,) rad/s in FLU,
        ``wind`` zeros (3,), ``rotor_speeds`` (4,) RU in RotorPy's order.
    """
    x = as_batch(x, "x", NX)
    if x.shape != (NX,):
        raise SimInputError(f"x must be one state of shape (12,); found {x.shape}")
    n = as_batch(rotor_speed, "rotor_speed", 4)
    if n.shape != (4,):
        raise SimInputError(f"rotor_speed must have shape (4,); found {n.shape}")
    return _to_rotorpy(x, n)


def _to_rotorpy(x: np.ndarray, n: np.ndarray) -> dict:
    """Unchecked :func:`to_rotorpy_state` (a diverging flight's non-finite state passes through)."""
    n_rp = np.empty(4)
    n_rp[ROTORPY_INDEX] = n
    return {"x": FLIP * x[0:3], "v": FLIP * x[9:12], "q": _quat_from_euler(x[3], x[4], x[5]),
            "w": FLIP * x[6:9], "wind": np.zeros(3), "rotor_speeds": n_rp}


def from_rotorpy_state(state: dict, previous) -> tuple[np.ndarray, np.ndarray]:
    """Our state (12,) and rotor speeds (4,) (our order, RU) of RotorPy's state dictionary.

    The Euler angles are unwrapped against those of ``previous`` (our state (12,) before the step), see
    :func:`unwrap_euler`.
    """
    x = np.empty(NX)
    x[0:3] = FLIP * np.asarray(state["x"], dtype=float)
    x[3:6] = unwrap_euler(_euler_from_quat(state["q"]), np.asarray(previous, dtype=float)[3:6])
    x[6:9] = FLIP * np.asarray(state["w"], dtype=float)
    x[9:12] = FLIP * np.asarray(state["v"], dtype=float)
    n = np.asarray(state["rotor_speeds"], dtype=float)[ROTORPY_INDEX]
    return x, n


class RotorPyPlant(Plant):
    """RotorPy's ``Multirotor`` flying our wrench commands (see the module docstring).

    Parameters
    ----------
    vehicle : Vehicle or name, optional
        The Rolling Spider when omitted. Its gravity must be RotorPy's 9.81 m/s^2.
    motor_lag : bool
        RotorPy's first-order motor lag with the vehicle's ``motor_tau`` (s); off: instant motors. The rotors
        start at hover speed (or at ``reset``'s ``rotor_speed``) and carry their speeds from call to call. A
        vehicle with ``motor_tau = 0`` has instant motors either way.
    aero : bool
        RotorPy's aerodynamics (parasitic drag, rotor drag, induced inflow, translational lift, flapping); off:
        no aerodynamic force at all.
    payload_kg : float
        Extra mass, kg (the rotor limits stay the vehicle's).
    wind : callable, optional
        ``wind(t) -> (3,)``: a world-frame (NED) acceleration, m/s^2, evaluated at the start of each call.
    rtol, atol : float, optional
        ``solve_ivp`` tolerances replacing those of the set-up (:data:`INTEGRATORS`).

    Raises
    ------
    PlantUnavailableError
        If RotorPy is not installed.
    SimInputError
        For a bad argument or a vehicle whose gravity is not RotorPy's.
    """

    def __init__(self, vehicle: Vehicle | None = None, *, motor_lag: bool = True, aero: bool = True,
                 payload_kg: float = 0.0, wind: WindFn | None = None, rtol: float | None = None,
                 atol: float | None = None):
        super().__init__(vehicle, payload_kg=payload_kg, wind=wind)
        for flag, value in (("motor_lag", motor_lag), ("aero", aero)):
            if not isinstance(value, (bool, np.bool_)):
                raise SimInputError(f"{flag} must be True or False; found {value!r}")
        self.motor_lag, self.aero = bool(motor_lag), bool(aero)
        self.name = ("rotorpy" if self.motor_lag and self.aero else
                     "rotorpy-ideal" if not (self.motor_lag or self.aero) else "rotorpy-custom")
        kwargs = dict(INTEGRATORS["physics" if (self.motor_lag or self.aero) else "ideal"])
        for key, value in (("rtol", rtol), ("atol", atol)):
            if value is not None:
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < value < 1.0:
                    raise SimInputError(f"{key} must be a number in (0, 1); found {value!r}")
                kwargs[key] = float(value)
        self.integrator_kwargs = kwargs
        p = self.vehicle.params
        if p.g != ROTORPY_G:
            raise SimInputError(f"plant {self.name!r}: RotorPy's gravity is {ROTORPY_G} m/s^2; vehicle "
                                f"{self.vehicle.name!r} has g = {p.g}")
        # Instant motors: RotorPy still integrates a lag; any tau > 0 does, as its term is held at exactly zero.
        self._instant = not self.motor_lag or self.vehicle.motor_tau == 0.0
        tau = self.vehicle.motor_tau if not self._instant else (self.vehicle.motor_tau or 1.0)
        cls = _multirotor_class()
        self._mr = cls(rotorpy_params(self.vehicle, self.payload_kg, tau_m=tau),
                       control_abstraction="cmd_ctbm", aero=self.aero, enable_ground=False,
                       integrator_kwargs=kwargs)
        if self._mr.g != p.g:   # RotorPy's constant changed under us
            raise SimInputError(f"plant {self.name!r}: RotorPy's gravity is {self._mr.g} m/s^2; vehicle "
                                f"{self.vehicle.name!r} has g = {p.g}")
        self._mr.accel = np.zeros(3)
        self._n = None   # rotor speeds, our order, RU

    def _reset(self, x0, rotor_speed):
        n = np.full(4, self.vehicle.params.n_hover) if rotor_speed is None else rotor_speed
        self._n = n.copy()
        return PlantOutput(x0, n.copy(), np.full(4, np.nan), np.zeros(4, dtype=bool))

    def _wind_accel(self) -> np.ndarray:
        """The wind acceleration at ``self.t`` in RotorPy's frame (3,), m/s^2."""
        if self.wind is None:
            return np.zeros(3)
        a = np.asarray(self.wind(self.t), dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise SimInputError(f"wind(t) must return a finite acceleration of shape (3,); found {a.shape} "
                                f"at t={self.t}")
        return FLIP * a

    def _advance(self, u, ticks):
        mr = self._mr
        control = {"cmd_thrust": float(u[0]), "cmd_moment": FLIP * u[1:4]}
        state = _to_rotorpy(self.x, self._n)
        n_cmd = mr.get_cmd_motor_speeds(state, control)            # RotorPy's order, signed
        n_clip = np.clip(n_cmd, mr.rotor_speed_min, mr.rotor_speed_max)
        saturated = ((n_cmd < mr.rotor_speed_min) | (n_cmd > mr.rotor_speed_max))[ROTORPY_INDEX]
        if self._instant:
            state["rotor_speeds"] = n_clip.copy()                  # the lag term is exactly zero
        n0 = state["rotor_speeds"][ROTORPY_INDEX]
        wrench = wrench_from_rotor_sq(n0 * n0, self.vehicle.params)
        mr.accel = self._wind_accel()
        # RotorPy's step draws its motor noise (zero here) from numpy's global generator: leave that one as found.
        rng_state = np.random.get_state()
        try:
            with np.errstate(all="ignore"):     # a diverging flight is the crash test's business, not an error
                new = mr.step(state, control, ticks * PLANT_TICK_S)
        finally:
            np.random.set_state(rng_state)
        x, n = from_rotorpy_state(new, self.x)
        self._n = n.copy()
        return PlantOutput(x, n, wrench, saturated)

    def describe(self) -> dict:
        """JSON-ready description: name, vehicle, payload, set-up, integrator and RotorPy's version."""
        from importlib import metadata

        try:
            version = metadata.version("rotorpy")
        except metadata.PackageNotFoundError:   # pragma: no cover - run from a source tree
            version = "unknown"
        return {**super().describe(), "motor_lag": self.motor_lag, "aero": self.aero,
                "integrator": dict(self.integrator_kwargs), "rotorpy": version}
