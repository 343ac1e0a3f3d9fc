"""A plant identified from real flights: the Crazyflie models of the ``drone-models`` package, flown at ``ctatt``.

``drone-models`` (PyPI 0.1.0, MIT; optional extra ``drone-models``) ships Crazyflie models fitted to flight data at
the attitude level: the rigid body's translation driven by a collective thrust, and the roll, pitch and yaw each a
second-order linear response to its command, ``a'' = c_a a + c_r a' + c_c a_cmd`` (coefficients fitted per drone).
Its variants (:data:`PHYSICS`):

* ``so_rpy``: the thrust acts at once;
* ``so_rpy_rotor``: the thrust follows its command with a first-order lag;
* ``so_rpy_rotor_drag`` (the default): that, plus a drag linear in the body-frame velocity.

:class:`DroneModelsPlant` integrates the package's own CasADi equations (``symbolic_dynamics_euler`` of each
variant, with the parameters of ``load_params``) by fourth-order Runge-Kutta at the plant's 1 ms tick. Nothing of
its model is rewritten here; what this module adds is the boundary:

* frames: drone-models is z-up with an FLU body and ``R = Rz(yaw) Ry(pitch) Rx(roll)``; with ``F = diag(1, -1, -1)``
  positions and velocities convert as ``F v`` and the angles as ``(phi, -theta, -psi)`` (as for RotorPy,
  :mod:`sim.plants.rotorpy_plant`); its state holds Euler-angle rates, ours body rates, converted by the ZYX
  kinematics;
* the command: ours at ``ctatt`` is ``[T, phi, theta, r]`` with a yaw *rate*; drone-models takes a yaw *angle*,
  so the yaw rate command is integrated, from the yaw at :meth:`reset`, at every tick. Roll and pitch commands are
  clipped to the vehicle's ``max_tilt`` and the yaw rate to its ``max_rate`` (as the other plants' loops do).

Only ``ctatt`` is flown: the models were identified from attitude commands. The vehicle must be one of the drones
the models were fitted to (:data:`DRONES`, each a vehicle file of this project holding the package's physical
values, so that the controllers' nominal models can be built). The plant has no rotors: its rotor speeds are NaN,
its realized wrench is the thrust force with NaN torques, and nothing saturates.

``drone-models`` refuses to be imported after SciPy unless ``SCIPY_ARRAY_API=1`` was set first (for its array-API
numerics). The symbolic equations used here need neither, so the package's modules are loaded without running its
top-level ``__init__``, and SciPy's mode in this process is left as it was.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import sys
import types

import numpy as np

from ..errors import PlantUnavailableError, SimInputError
from ..levels import check_level
from ..vehicles.vehicle import Vehicle
from .plant import PLANT_TICK_S, Plant, PlantOutput, WindFn, plant_time
from .zup_frames import FLIP

#: The package's model variants this plant flies, and the default.
PHYSICS = ("so_rpy", "so_rpy_rotor", "so_rpy_rotor_drag")
DEFAULT_PHYSICS = "so_rpy_rotor_drag"
#: The drones with fitted parameters in drone-models 0.1.0 (a vehicle file of this project each, where shipped).
DRONES = ("cf2x_L250", "cf2x_P250", "cf2x_T350", "cf21B_500")

_UNAVAILABLE = "plant 'drone-models' needs the drone-models package: python -m pip install -e '.[drone-models]'"


def drone_models_available() -> bool:
    """True when the drone-models package is installed (nothing is imported)."""
    return importlib.util.find_spec("drone_models") is not None


def _module(name: str):
    """``drone_models.<name>``, loaded without running the package's ``__init__`` (see the module docstring)."""
    if "drone_models" not in sys.modules:
        spec = importlib.util.find_spec("drone_models")
        if spec is None:
            raise PlantUnavailableError(_UNAVAILABLE)
        pkg = types.ModuleType("drone_models")
        pkg.__path__ = list(spec.submodule_search_locations)
        pkg.__file__, pkg.__spec__ = spec.origin, spec
        sys.modules["drone_models"] = pkg
    return importlib.import_module(f"drone_models.{name}")


def parse_plant_name(name: str) -> str:
    """The physics of a plant name ``drone-models`` or ``drone-models:PHYSICS``, or a SimInputError."""
    base, _, physics = name.partition(":")
    if base != "drone-models":
        raise SimInputError(f"not a drone-models plant: {name!r}")
    physics = physics or DEFAULT_PHYSICS
    if physics not in PHYSICS:
        raise SimInputError(f"plant drone-models:PHYSICS takes one of {', '.join(PHYSICS)}; found {physics!r}")
    return physics


def body_rates_from_euler_rates(angles, rates) -> np.ndarray:
    """Body rates (p, q, r) (3,) of ZYX Euler angles (3,) and their rates (3,), rad and rad/s."""
    phi, theta, _ = angles
    dphi, dtheta, dpsi = rates
    return np.array([dphi - dpsi * math.sin(theta),
                     dtheta * math.cos(phi) + dpsi * math.sin(phi) * math.cos(theta),
                     -dtheta * math.sin(phi) + dpsi * math.cos(phi) * math.cos(theta)])


def euler_rates_from_body_rates(angles, w) -> np.ndarray:
    """ZYX Euler-angle rates (3,) of the angles (3,) and body rates (3,) (the inverse of
    :func:`body_rates_from_euler_rates`; singular at theta = +-pi/2)."""
    phi, theta, _ = angles
    p, q, r = w
    s = q * math.sin(phi) + r * math.cos(phi)
    return np.array([p + s * math.tan(theta), q * math.cos(phi) - r * math.sin(phi), s / math.cos(theta)])


class DroneModelsPlant(Plant):
    """drone-models' fitted Crazyflie model behind the plant interface, at the ``ctatt`` level (see the module
    docstring).

    Parameters
    ----------
    vehicle : Vehicle or name
        One of :data:`DRONES` (a vehicle file named after the drone).
    physics : str
        One of :data:`PHYSICS` (default :data:`DEFAULT_PHYSICS`).
    level : str
        ``ctatt`` (the others are refused).
    payload_kg : float
        Added to the model's mass, kg.
    wind : callable, optional
        ``wind(t) -> (3,)``: a world-frame (NED) acceleration, m/s^2, held over each tick.

    Raises
    ------
    PlantUnavailableError
        drone-models is not installed.
    SimInputError
        Another level, physics or vehicle.
    """

    def __init__(self, vehicle: Vehicle | str, physics: str = DEFAULT_PHYSICS, level: str = "ctatt", *,
                 payload_kg: float = 0.0, wind: WindFn | None = None):
        super().__init__(vehicle, payload_kg=payload_kg, wind=wind)
        check_level(level)
        if level != "ctatt":
            raise SimInputError(f"plant 'drone-models' takes commands at the 'ctatt' level only (its models were "
                                f"identified from attitude commands); found level {level!r}")
        if physics not in PHYSICS:
            raise SimInputError(f"physics must be one of {', '.join(PHYSICS)}; found {physics!r}")
        if self.vehicle.name not in DRONES:
            raise SimInputError(f"plant 'drone-models' flies the drones its models were fitted to ({', '.join(DRONES)});"
                                f" found vehicle {self.vehicle.name!r}")
        self.level, self.physics = level, physics
        self.name = "drone-models" if physics == DEFAULT_PHYSICS else f"drone-models:{physics}"
        self.loop = self.vehicle.inner_loop_at(level)
        import casadi as ca

        params = {k: np.asarray(v, dtype=float) for k, v in
                  _module("core").load_params(physics, self.vehicle.name).items()}
        self.model_params = params
        model = _module(f"{physics}.model")
        kwargs = {k: params[k] for k in ("mass", "gravity_vec", "J", "J_inv", "acc_coef", "cmd_f_coef", "rpy_coef",
                                         "rpy_rates_coef", "cmd_rpy_coef", "thrust_time_coef", "drag_matrix")
                  if k in _keyword_names(model.symbolic_dynamics_euler)}
        kwargs["mass"] = float(params["mass"]) + self.payload_kg
        self._rotor = physics != "so_rpy"
        if self._rotor:
            kwargs["model_rotor_vel"] = True
        x_dot, X, U, _ = model.symbolic_dynamics_euler(**kwargs)
        a = ca.MX.sym("a", 3)     # the wind, an extra acceleration (z-up)
        f = ca.Function("f", [X, U, a], [x_dot + ca.vertcat(ca.MX.zeros(6), a, ca.MX.zeros(X.shape[0] - 9))])
        h = PLANT_TICK_S
        k1 = f(X, U, a)
        k2 = f(X + 0.5 * h * k1, U, a)
        k3 = f(X + 0.5 * h * k2, U, a)
        k4 = f(X + h * k3, U, a)
        self._step = ca.Function("rk4", [X, U, a], [X + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)])
        self._nx = X.shape[0]
        self._hover_thrust = (float(params["mass"]) * float(-params["gravity_vec"][2])
                              - float(params["acc_coef"])) / float(params["cmd_f_coef"])

    def _to_model(self, x: np.ndarray, thrust: float | None) -> np.ndarray:
        angles = x[3:6]
        ours = np.concatenate([x[0:3] * FLIP, angles * FLIP, x[9:12] * FLIP,
                               euler_rates_from_body_rates(angles, x[6:9]) * FLIP])
        if self._rotor:
            ours = np.concatenate([ours, np.full(self._nx - 12, thrust)])
        return ours

    @staticmethod
    def _from_model(X: np.ndarray) -> np.ndarray:
        x = np.empty(12)
        x[0:3] = X[0:3] * FLIP
        x[3:6] = X[3:6] * FLIP
        x[9:12] = X[6:9] * FLIP
        x[6:9] = body_rates_from_euler_rates(x[3:6], X[9:12] * FLIP)
        return x

    @property
    def hover_input(self) -> np.ndarray:
        """The command that holds the model still: its hover thrust (the fitted thrust gain's, not ``m g``), level."""
        return np.array([self._hover_thrust, 0.0, 0.0, 0.0])

    def _reset(self, x0, rotor_speed):
        self._X = self._to_model(x0, self._hover_thrust)
        self._yaw_ref = float(x0[5])
        return self._output(x0)

    def _output(self, x) -> PlantOutput:
        thrust = float(self.model_params["acc_coef"] + self.model_params["cmd_f_coef"] *
                       (self._X[12] if self._rotor else self._hover_thrust))
        return PlantOutput(x, np.full(4, np.nan), np.array([thrust, np.nan, np.nan, np.nan]), np.zeros(4, dtype=bool))

    def _advance(self, u, ticks):
        c = self.loop
        tilt = np.clip(u[1:3], -c.max_tilt, c.max_tilt)
        r = float(np.clip(u[3], -c.max_rate, c.max_rate))
        X = self._X
        for k in range(ticks):
            self._yaw_ref += r * PLANT_TICK_S
            cmd = np.array([tilt[0], -tilt[1], -self._yaw_ref, u[0]])
            a = np.zeros(3) if self.wind is None else FLIP * np.asarray(self.wind(plant_time(self._ticks + k)),
                                                                         dtype=float)
            with np.errstate(all="ignore"):
                X = np.asarray(self._step(X, cmd, a)).ravel()
        self._X = X
        return self._output(self._from_model(X))

    def describe(self) -> dict:
        from importlib import metadata

        try:
            version = metadata.version("drone-models")
        except metadata.PackageNotFoundError:   # pragma: no cover
            version = "unknown"
        return {**super().describe(), "level": self.level, "physics": self.physics, "drone_models": version,
                "integrator": {"method": "RK4", "step_s": PLANT_TICK_S}}


def _keyword_names(fn) -> set:
    import inspect

    return {n for n, p in inspect.signature(fn).parameters.items()
            if p.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)}
