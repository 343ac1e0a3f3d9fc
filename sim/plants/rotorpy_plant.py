"""RotorPy as a plant: its ``Multirotor`` flies our commands (wrench, or through its own onboard controllers), in
our frames.

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

Command levels (:mod:`sim.levels`). At ``ctbr`` and ``ctatt`` the plant flies
RotorPy's own onboard controllers, ``cmd_ctbr`` and ``cmd_ctatt``
(``Multirotor.get_cmd_motor_speeds``), at the vehicle's inner-loop rate
(``[inner_loop] rate_hz``): the motor speeds they give at the start of a
loop period are held through it (also when a call of :meth:`advance` ends
inside one). Their laws are RotorPy's, not the reference simulator's loop
(:mod:`sim.plants.inner_loop`); their gains come from the vehicle's
``[inner_loop]`` table (:func:`rotorpy_loop_gains`):

* ``ctbr``: a P loop on the body rates, ``J k_w (w_cmd - w)``, with
  ``k_w = rate_kp`` per axis; no integral and no derivative;
* ``ctatt``: a PD loop on the attitude error on SO(3), plus the gyroscopic
  term, ``J (-kp_att e_R - kd_att w) + w x J w``, with roll and pitch
  ``kp_att = att_kp rate_kp`` and ``kd_att = rate_kp`` (the cascade of the
  two P loops), and yaw ``kd_att = rate_kp``, ``kp_att = min(att_kp)
  rate_kp`` (as if the yaw angle had the attitude loop's smaller gain; a
  critically damped yaw, ``rate_kp^2 / 4``, diverged on the Crazyflie with
  its 72 ms motor lag). RotorPy takes a whole attitude: roll and pitch are
  the command's, the yaw the command's yaw rate integrated over each loop
  period from the yaw at :meth:`reset`.

Rate commands are clipped to ``max_rate`` and tilt commands to ``max_tilt``,
as the reference simulator's loop does.

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
from .plant import PLANT_TICK_S, Plant, PlantOutput, WindFn, plant_time
from ..levels import DEFAULT_LEVEL, check_level
from ..vehicles.onboard import InnerLoopConfig
from ..vehicles.rotors import wrench_from_rotor_sq
from ..vehicles.vehicle import Vehicle
from .zup_frames import FLIP, euler_from_quat, quat_from_euler, unwrap_euler

#: RotorPy's index (0-based) of our rotor i: our rotors 1-4 are RotorPy's r2, r3, r4, r1. For an array ``a`` in our
#: order, ``rp = np.empty(4); rp[ROTORPY_INDEX] = a`` is RotorPy's order; ``rp[ROTORPY_INDEX]`` is ours again.
ROTORPY_INDEX = np.array([1, 2, 3, 0])
#: RotorPy's gravity, m/s^2 (fixed in ``Multirotor``).
ROTORPY_G = 9.81
#: ``solve_ivp`` settings per set-up (``ideal``: no motor lag and no aerodynamics; ``physics``: any effect on).
#: The ideal set-up is held to the reference simulator to 1e-8 m per period (it agrees to about 2e-12 m); the
#: other keeps its physics to about 1e-12 m per period (one DOP853 step per 10 ms on the Rolling Spider).
INTEGRATORS = {
    "ideal": {"method": "DOP853", "rtol": 1e-11, "atol": 1e-12},
    "physics": {"method": "DOP853", "rtol": 1e-8, "atol": 1e-10},
}

#: RotorPy's control abstraction that takes the commands of each level.
ABSTRACTIONS = {"wrench": "cmd_ctbm", "ctbr": "cmd_ctbr", "ctatt": "cmd_ctatt"}

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


def rotorpy_loop_gains(config: InnerLoopConfig) -> dict:
    """RotorPy's onboard-controller gains for the vehicle's ``[inner_loop]`` ``config`` (see the module docstring).

    Returns
    -------
    dict
        ``k_w`` (3,) 1/s, the rate loop's P gain per body axis; ``kp_att`` (3,) 1/s^2 and ``kd_att`` (3,) 1/s, the
        attitude loop's PD gains per axis (roll, pitch, yaw), in RotorPy's FLU body frame (the same per axis).
    """
    kp = np.asarray(config.rate_kp, dtype=float)
    att = np.asarray(config.att_kp, dtype=float)
    return {"k_w": kp.copy(), "kp_att": np.array([att[0] * kp[0], att[1] * kp[1], att.min() * kp[2]]),
            "kd_att": kp.copy()}


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
    return {"x": FLIP * x[0:3], "v": FLIP * x[9:12], "q": quat_from_euler(x[3], x[4], x[5]),
            "w": FLIP * x[6:9], "wind": np.zeros(3), "rotor_speeds": n_rp}


def from_rotorpy_state(state: dict, previous) -> tuple[np.ndarray, np.ndarray]:
    """Our state (12,) and rotor speeds (4,) (our order, RU) of RotorPy's state dictionary.

    The Euler angles are unwrapped against those of ``previous`` (our state (12,) before the step), see
    :func:`unwrap_euler`.
    """
    x = np.empty(NX)
    x[0:3] = FLIP * np.asarray(state["x"], dtype=float)
    x[3:6] = unwrap_euler(euler_from_quat(state["q"]), np.asarray(previous, dtype=float)[3:6])
    x[6:9] = FLIP * np.asarray(state["w"], dtype=float)
    x[9:12] = FLIP * np.asarray(state["v"], dtype=float)
    n = np.asarray(state["rotor_speeds"], dtype=float)[ROTORPY_INDEX]
    return x, n


class RotorPyPlant(Plant):
    """RotorPy's ``Multirotor`` flying our commands at one level (see the module docstring).

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
    level : str
        The command it takes (:mod:`sim.levels`): ``wrench`` (the default), ``ctbr`` or ``ctatt``.
    inner_loop : InnerLoopConfig, optional
        The onboard controller's rate and gains at ``ctbr`` and ``ctatt`` (the vehicle's ``[inner_loop]`` when
        omitted; a vehicle without one is refused).

    Raises
    ------
    PlantUnavailableError
        If RotorPy is not installed.
    SimInputError
        For a bad argument or a vehicle whose gravity is not RotorPy's.
    """

    def __init__(self, vehicle: Vehicle | None = None, *, motor_lag: bool = True, aero: bool = True,
                 payload_kg: float = 0.0, wind: WindFn | None = None, rtol: float | None = None,
                 atol: float | None = None, level: str = DEFAULT_LEVEL, inner_loop: InnerLoopConfig | None = None):
        super().__init__(vehicle, payload_kg=payload_kg, wind=wind)
        self.level = check_level(level)
        self.loop = None
        if self.level != DEFAULT_LEVEL:
            self.loop = self.vehicle.inner_loop_at(level) if inner_loop is None else inner_loop
            if not isinstance(self.loop, InnerLoopConfig):
                raise SimInputError(f"inner_loop must be an InnerLoopConfig; found {type(inner_loop).__name__}")
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
        params = rotorpy_params(self.vehicle, self.payload_kg, tau_m=tau)
        if self.loop is not None:
            params.update(rotorpy_loop_gains(self.loop))
        # One Multirotor integrates; at ctbr and ctatt a second one, at the level's abstraction, is RotorPy's
        # onboard controller (its motor speeds are held over a loop period, so they are computed apart).
        self._mr = cls(params, control_abstraction="cmd_ctbm" if self.loop is None else "cmd_motor_speeds",
                       aero=self.aero, enable_ground=False, integrator_kwargs=kwargs)
        self._onboard = None if self.loop is None else cls(
            params, control_abstraction=ABSTRACTIONS[self.level], aero=self.aero, enable_ground=False,
            integrator_kwargs=kwargs)
        if self._mr.g != p.g:   # RotorPy's constant changed under us
            raise SimInputError(f"plant {self.name!r}: RotorPy's gravity is {self._mr.g} m/s^2; vehicle "
                                f"{self.vehicle.name!r} has g = {p.g}")
        self._mr.accel = np.zeros(3)
        self._n = None   # rotor speeds, our order, RU

    def _reset(self, x0, rotor_speed):
        n = np.full(4, self.vehicle.params.n_hover) if rotor_speed is None else rotor_speed
        self._n = n.copy()
        self._phase, self._held, self._yaw_ref = 0, None, float(x0[5])
        return PlantOutput(x0, n.copy(), np.full(4, np.nan), np.zeros(4, dtype=bool))

    def _wind_accel(self, t: float) -> np.ndarray:
        """The wind acceleration at time ``t`` (s) in RotorPy's frame (3,), m/s^2."""
        if self.wind is None:
            return np.zeros(3)
        a = np.asarray(self.wind(t), dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise SimInputError(f"wind(t) must return a finite acceleration of shape (3,); found {a.shape} "
                                f"at t={t}")
        return FLIP * a

    def _level_control(self, u) -> dict:
        """RotorPy's control dictionary of the command ``u`` (4,) at this plant's level, clipped as the reference
        simulator's loop clips it; at ``ctatt`` the yaw setpoint advances by one loop period of the yaw rate."""
        c = self.loop
        if self.level == "ctbr":
            w = np.clip(u[1:4], -c.max_rate, c.max_rate)
            return {"cmd_thrust": float(u[0]), "cmd_w": FLIP * w}
        tilt = np.clip(u[1:3], -c.max_tilt, c.max_tilt)
        self._yaw_ref += float(np.clip(u[3], -c.max_rate, c.max_rate)) * c.period_s
        return {"cmd_thrust": float(u[0]), "cmd_q": quat_from_euler(tilt[0], tilt[1], self._yaw_ref)}

    def _advance(self, u, ticks):
        if self.loop is None:
            return self._advance_held(u, ticks, self.t)
        out, done = None, 0
        while done < ticks:     # the onboard controller runs at the start of each of its periods
            if self._phase == 0:
                state = _to_rotorpy(self.x, self._n)
                self._held = self._onboard.get_cmd_motor_speeds(state, self._level_control(u))
            n = min(ticks - done, self.loop.ticks - self._phase)
            out = self._advance_held(self._held, n, plant_time(self._ticks + done), motor_speeds=True)
            self._phase = (self._phase + n) % self.loop.ticks
            done += n
            self._out = out      # the next piece starts from this one's state
        return out

    def _advance_held(self, u, ticks, t: float, motor_speeds: bool = False):
        """Integrate ``ticks`` ticks from time ``t`` (s) holding ``u``: the wrench (4,), or with ``motor_speeds``
        RotorPy's signed commanded motor speeds (4,) in its order."""
        mr = self._mr
        state = _to_rotorpy(self.x, self._n)
        if motor_speeds:
            n_cmd, control = u, {"cmd_motor_speeds": u}
        else:
            control = {"cmd_thrust": float(u[0]), "cmd_moment": FLIP * u[1:4]}
            n_cmd = mr.get_cmd_motor_speeds(state, control)        # RotorPy's order, signed
        n_clip = np.clip(n_cmd, mr.rotor_speed_min, mr.rotor_speed_max)
        saturated = ((n_cmd < mr.rotor_speed_min) | (n_cmd > mr.rotor_speed_max))[ROTORPY_INDEX]
        if self._instant:
            state["rotor_speeds"] = n_clip.copy()                  # the lag term is exactly zero
        n0 = state["rotor_speeds"][ROTORPY_INDEX]
        wrench = wrench_from_rotor_sq(n0 * n0, self.vehicle.params)
        mr.accel = self._wind_accel(t)
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
        out = {**super().describe(), "motor_lag": self.motor_lag, "aero": self.aero,
               "integrator": dict(self.integrator_kwargs), "rotorpy": version}
        if self.loop is not None:
            out["level"] = self.level
            out["inner_loop"] = {**self.loop.to_dict(), "rotorpy_abstraction": ABSTRACTIONS[self.level],
                                 **{k: v.tolist() for k, v in rotorpy_loop_gains(self.loop).items()}}
        return out
