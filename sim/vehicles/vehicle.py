"""Vehicles as data: one description feeds the plant, the excitation data and the controllers.

A vehicle is a TOML file of plain numbers (SI units; rotor speed in rotor
units, RU, whatever unit the rotor coefficients ``kt`` and ``kq`` are given
in)::

    name = "my-quad"
    m = 1.2            # kg
    Jxx = 1.1e-2       # kg m^2
    ...

Its keys are the field names of :class:`Vehicle`. Every key left out takes
the Rolling Spider's value (the reference values of :class:`sim.QuadParams`
and of the high-fidelity plant), except ``n_max``, which defaults to the
rotor speed at which four rotors give twice the vehicle's weight. An unknown
key is an error that names it, and so is a vehicle whose rotors cannot lift
:data:`MIN_THRUST_TO_WEIGHT` times its weight.

Four presets ship with the package (``sim/vehicles/*.toml``):
``rolling-spider`` (the default; the paper's vehicle), ``hummingbird`` and
``crazyflie`` (RotorPy's presets of the AscTec Hummingbird and the Bitcraze
Crazyflie 2.0), and ``crazyflie-brushless`` (the values a real-flight
benchmark states for its Crazyflie 2.1 Brushless). ``load_vehicle(NAME or PATH)`` reads either.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from .._validate import nonnegative_finite, positive_finite
from ..errors import SimInputError
from ..files import read_named_toml
from ..params import GRAVITY, HIGH_FIDELITY, Fidelity, QuadParams
from .onboard import InnerLoopConfig, inner_loop_from_dict

#: The least maximum thrust a vehicle may have, as a multiple of its weight: below it the rotors cannot hover it and
#: still turn it (at 1.2 a hover uses 83 % of the thrust and leaves 17 % for attitude control).
MIN_THRUST_TO_WEIGHT = 1.2
#: Folder of the shipped vehicle files.
VEHICLE_DIR = Path(__file__).resolve().parent
#: The vehicle of every command that is given none.
DEFAULT_VEHICLE = "rolling-spider"
#: RotorPy's aerodynamic coefficients beyond the high-fidelity plant's rotor drag, for the Rolling Spider. RotorPy
#: ships no such vehicle: the induced-inflow drag is taken equal to the in-plane rotor drag, and the translational
#: lift is the Hummingbird preset's (3.39e-3 N/(m/s)^2 at 0.5 kg) scaled to this vehicle's weight (x 0.068 / 0.5), so
#: that it lifts the same share of the weight at any airspeed.
_ROLLING_SPIDER_K_Z = HIGH_FIDELITY.rotor_drag   # N s / (m RU) per rotor, induced inflow (RotorPy k_z)
_ROLLING_SPIDER_K_H = 4.6104e-4                  # N / (m/s)^2 per rotor, translational lift (RotorPy k_h)


@dataclass(frozen=True)
class Vehicle:
    """One quadrotor, as data (SI units, rotor speeds in RU; units in comments).

    The rigid body and rotors are those of :class:`sim.QuadParams`; the rest
    describes what the nominal equations leave out: the motor lag and the
    aerodynamic coefficients of the high-fidelity plant and of RotorPy.
    Build one with :func:`load_vehicle` or ``Vehicle(m=..., ...)``; every
    field is validated finite (and > 0 where a zero has no meaning).
    """

    name: str = DEFAULT_VEHICLE
    # Rigid body and rotors (QuadParams' field names).
    m: float = QuadParams.m                   # mass, kg
    Jxx: float = QuadParams.Jxx               # roll inertia, kg m^2
    Jyy: float = QuadParams.Jyy               # pitch inertia, kg m^2
    Jzz: float = QuadParams.Jzz               # yaw inertia, kg m^2
    kt: float = QuadParams.kt                 # rotor thrust coefficient, N / RU^2
    kq: float = QuadParams.kq                 # rotor reaction-torque coefficient, N m / RU^2
    d: float = QuadParams.d                   # arm length (centre to rotor), m; X layout
    c_d: float = QuadParams.c_d               # quadratic drag as an acceleration, 1/m (a = c_d v|v|); 0: none
    n_max: float | None = None                # rotor speed limit, RU; None: four rotors give 2 m g
    # What the nominal equations leave out.
    motor_tau: float = HIGH_FIDELITY.motor_tau    # first-order motor time constant, s
    rotor_drag: float = HIGH_FIDELITY.rotor_drag  # in-plane rotor drag per rotor, N s / (m RU) (RotorPy k_d)
    rotor_gyro: float = HIGH_FIDELITY.rotor_gyro  # rotor gyroscopic coefficient, N m s / RU (our plant only)
    k_z: float = _ROLLING_SPIDER_K_Z          # induced-inflow drag per rotor, N s / (m RU) (RotorPy only)
    k_h: float = _ROLLING_SPIDER_K_H          # translational lift per rotor, N / (m/s)^2 (RotorPy only)
    k_flap: float = 0.0                       # flapping moment per rotor, N m s / (m RU) (RotorPy only)
    source: str = ""                          # where the numbers come from
    # The onboard controller of the ctbr and ctatt command levels (the [inner_loop] table); None: none given.
    inner_loop: InnerLoopConfig | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise SimInputError(f"vehicle name must be a non-empty string; found {self.name!r}")
        if not isinstance(self.source, str):
            raise SimInputError(f"vehicle source must be a string; found {self.source!r}")
        if self.inner_loop is not None and not isinstance(self.inner_loop, InnerLoopConfig):
            raise SimInputError(f"vehicle {self.name!r}: inner_loop must be an InnerLoopConfig; found "
                                f"{type(self.inner_loop).__name__}")
        for f in dataclasses.fields(self):
            if f.name in ("name", "source", "inner_loop") or (f.name == "n_max" and self.n_max is None):
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool):
                raise SimInputError(f"vehicle {self.name!r}: {f.name} must be a number; found {v!r}")
            check = positive_finite if f.name in _POSITIVE else nonnegative_finite
            object.__setattr__(self, f.name, check(v, f"vehicle {self.name!r}: {f.name}"))
        p = self.params   # validates the rigid body as QuadParams does
        ratio = 4.0 * p.kt * p.n_max_sq / (p.m * p.g)
        if not ratio >= MIN_THRUST_TO_WEIGHT:
            raise SimInputError(
                f"vehicle {self.name!r}: its four rotors at n_max lift {ratio:.3g} times its weight "
                f"(4 kt n_max^2 = {4.0 * p.kt * p.n_max_sq:.4g} N against m g = {p.m * p.g:.4g} N); "
                f"a vehicle must lift at least {MIN_THRUST_TO_WEIGHT} times its weight to hover and be controlled "
                f"(check kt, n_max and m, and that kt is in the unit of n_max)")

    @property
    def params(self) -> QuadParams:
        """The rigid body and rotors as :class:`sim.QuadParams` (what the nominal equations and our plant use)."""
        return QuadParams(**{n: getattr(self, n) for n in _PARAM_KEYS}, g=GRAVITY)

    @property
    def fidelity(self) -> Fidelity:
        """This vehicle's high-fidelity effects on our plant (motor lag, rotor drag, rotor gyroscopic torque)."""
        return Fidelity(motor_tau=self.motor_tau, rotor_drag=self.rotor_drag, rotor_gyro=self.rotor_gyro)

    def named_fidelity(self, name: str) -> Fidelity:
        """The fidelity ``name`` (a key of :data:`sim.params.FIDELITIES`) with this vehicle's coefficients.

        ``nominal``: none; ``high``: all three effects; ``motor-lag``, ``rotor-drag``, ``rotor-gyro``: one.
        """
        full = self.fidelity
        named = {"nominal": Fidelity(), "high": full, "motor-lag": Fidelity(motor_tau=full.motor_tau),
                 "rotor-drag": Fidelity(rotor_drag=full.rotor_drag), "rotor-gyro": Fidelity(rotor_gyro=full.rotor_gyro)}
        if name not in named:
            raise SimInputError(f"fidelity must be one of {', '.join(named)}; found {name!r}")
        return named[name]

    @property
    def n_max_value(self) -> float:
        """The rotor speed limit, RU (``n_max`` or its default)."""
        return math.sqrt(self.params.n_max_sq)

    @property
    def parasitic_drag(self) -> float:
        """The drag ``c_d`` as RotorPy's parasitic drag coefficient ``m c_d``, N / (m/s)^2 (isotropic, body frame)."""
        return self.m * self.c_d

    def inner_loop_at(self, level: str) -> InnerLoopConfig:
        """The onboard controller that flies commands at ``level`` (``ctbr`` or ``ctatt``, :mod:`sim.levels`).

        Raises
        ------
        SimInputError
            The vehicle has no ``[inner_loop]`` table: one line naming the missing key.
        """
        if self.inner_loop is None:
            raise SimInputError(f"vehicle {self.name!r} has no inner loop: its file gives no [inner_loop] table "
                                f"(inner_loop.rate_kp is missing), so it cannot be flown at the {level!r} level")
        return self.inner_loop

    def to_dict(self) -> dict:
        """JSON-ready description (stored with every result and dataset): every field, ``n_max`` resolved, and
        ``inner_loop`` (a table) only where the vehicle has one."""
        out = dataclasses.asdict(self)
        out["n_max"] = self.n_max_value
        if self.inner_loop is None:
            del out["inner_loop"]
        else:
            out["inner_loop"] = self.inner_loop.to_dict()
        return out

    def replace(self, **changes) -> "Vehicle":
        """A copy with fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)

    def in_rotor_unit(self, old_per_new: float, name: str | None = None) -> "Vehicle":
        """The same vehicle with rotor speeds counted in another unit: one new unit is ``old_per_new`` of the present
        ones (``2 pi / 60`` turns rad/s into RPM; :meth:`normalized` uses ``n_max``).

        Every coefficient per rotor unit is converted (``kt``, ``kq`` by the square, ``rotor_drag``, ``k_z``,
        ``k_flap``, ``rotor_gyro`` by the factor), so thrusts, torques and forces are unchanged.
        """
        s = positive_finite(old_per_new, "old_per_new")
        return dataclasses.replace(self, name=name or self.name, kt=self.kt * s * s, kq=self.kq * s * s,
                                   n_max=self.n_max_value / s, rotor_drag=self.rotor_drag * s, k_z=self.k_z * s,
                                   k_flap=self.k_flap * s, rotor_gyro=self.rotor_gyro * s)

    def normalized(self) -> "Vehicle":
        """The same vehicle with rotor speeds in units of its limit (``n_max`` = 1)."""
        return self.in_rotor_unit(self.n_max_value, name=f"{self.name}-normalized")

    def to_toml(self) -> str:
        """The vehicle as a vehicle file's text (:func:`load_vehicle` reads it back to the same vehicle)."""
        def value(v):
            if isinstance(v, str):
                return '"""' + v.replace("\\", "\\\\").replace('"', '\\"') + '"""'
            if isinstance(v, list):
                return "[" + ", ".join(repr(float(x)) for x in v) + "]"
            return repr(float(v))

        d = self.to_dict()
        table = d.pop("inner_loop", None)
        text = "".join(f"{k} = {value(v)}\n" for k, v in d.items())
        if table is not None:
            text += "\n[inner_loop]\n" + "".join(f"{k} = {value(v)}\n" for k, v in table.items())
        return text


#: Fields that must be > 0 (the rest may be 0: an effect switched off).
_POSITIVE = frozenset(("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "d", "n_max"))
#: Fields passed to QuadParams.
_PARAM_KEYS = ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "d", "c_d", "n_max")
#: Keys of a vehicle file (plain values), and its one table.
VEHICLE_KEYS = tuple(f.name for f in dataclasses.fields(Vehicle) if f.name != "inner_loop")
VEHICLE_TABLES = ("inner_loop",)


def vehicle_names() -> list[str]:
    """Names of the shipped vehicle files."""
    return sorted(p.stem for p in VEHICLE_DIR.glob("*.toml"))


def vehicle_from_dict(data: dict, where: str = "vehicle") -> Vehicle:
    """A :class:`Vehicle` from a mapping of vehicle-file keys; unknown keys and bad values raise naming them."""
    if not isinstance(data, dict):
        raise SimInputError(f"{where}: must be a table of keys; found {type(data).__name__}")
    unknown = sorted(set(data) - set(VEHICLE_KEYS) - set(VEHICLE_TABLES))
    if unknown:
        raise SimInputError(f"{where}: unknown key {unknown[0]!r}; the keys are {', '.join(VEHICLE_KEYS)}, and the "
                            f"table [{'], ['.join(VEHICLE_TABLES)}]")
    data = dict(data)
    if "inner_loop" in data:
        data["inner_loop"] = inner_loop_from_dict(data["inner_loop"], where)
    for k, v in data.items():
        if k == "inner_loop":
            continue
        if k in ("name", "source"):
            if not isinstance(v, str):
                raise SimInputError(f"{where}: {k} must be a string; found {v!r}")
        elif isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SimInputError(f"{where}: {k} must be a number; found {v!r}")
    try:
        return Vehicle(**data)
    except SimInputError as e:
        raise SimInputError(f"{where}: {e}") from None


def load_vehicle(spec: "str | Path | Vehicle | None" = None) -> Vehicle:
    """The vehicle named ``spec`` (a shipped preset, see :func:`vehicle_names`) or read from a TOML file.

    ``None`` gives the default vehicle (the Rolling Spider); a :class:`Vehicle` is returned as it is. A file
    without ``name`` is named after its stem.
    """
    if spec is None:
        spec = DEFAULT_VEHICLE
    if isinstance(spec, Vehicle):
        return spec
    data, path = read_named_toml(spec, VEHICLE_DIR, "vehicle", "vehicle")
    data.setdefault("name", path.stem)
    return vehicle_from_dict(data, where=f"vehicle file {str(path)!r}")

