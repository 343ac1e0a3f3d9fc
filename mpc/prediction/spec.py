"""What a controller may know about the vehicle besides its prediction model.

A controller never reads the plant's :class:`sim.QuadParams`. It gets its
prediction model and a :class:`VehicleSpec`: the numbers a user has from the
vehicle's datasheet (arm length, rotor speed limit) plus the mass and rotor
coefficients the model identified, when it carries them (``theta`` in the
ONNX metadata). Everything else (hover trim, feed-forward) comes from the
model itself (:mod:`mpc.references.feedforward`).

The datasheet numbers come from a vehicle description
(:class:`sim.vehicles.vehicle.Vehicle`, a TOML file): the one the run flies, or the
default vehicle (the Parrot Rolling Spider) when none is given.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigurationError

#: The controllers' acceptable torque deviation (the scale of their input weight) as a fraction of the largest roll
#: torque the rotors give (two rotors at the limit, two stopped), rounded to one significant figure: 2e-3 N m for
#: the Rolling Spider, 0.2 N m for the Hummingbird.
TORQUE_SCALE_FRACTION = 0.07


def torque_scale(kt: float, n_max: float, d: float) -> float:
    """:data:`TORQUE_SCALE_FRACTION` of the largest roll torque ``2 kt n_max^2 d / sqrt(2)`` (N m), one significant figure.

    Taken from the datasheet when a spec is built, so that a model's identified ``kt`` does not move the weights.
    """
    v = TORQUE_SCALE_FRACTION * 2.0 * kt * n_max ** 2 * d / math.sqrt(2.0)
    return float(f"{v:.0e}")


#: The numbers a VehicleSpec holds, in order.
SPEC_FIELDS = ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "d", "n_max", "g", "c_d")


def datasheet(vehicle=None) -> dict:
    """The datasheet values of ``vehicle`` (a :class:`sim.vehicles.vehicle.Vehicle`, name or file; default vehicle if
    None), with its largest rate and tilt commands where it has an inner loop."""
    import sim.vehicles.vehicle as vehicles

    if vehicle is None:
        return dict(_default_datasheet(vehicles.DEFAULT_VEHICLE))
    return _sheet(vehicles.load_vehicle(vehicle))


@functools.lru_cache(maxsize=4)
def _default_datasheet(name: str) -> dict:
    """The datasheet of the default vehicle ``name``, read once per process: it is a file shipped with the package,
    and every ``VehicleSpec()`` (a reference's flatness map without a spec, at each call) would parse it again
    (0.5 ms)."""
    from sim.vehicles.vehicle import load_vehicle

    return _sheet(load_vehicle(name))


def _sheet(v) -> dict:
    """:func:`datasheet` of a loaded vehicle."""
    p = v.params
    loop = v.inner_loop
    return {"m": p.m, "Jxx": p.Jxx, "Jyy": p.Jyy, "Jzz": p.Jzz, "kt": p.kt, "kq": p.kq, "d": p.d,
            "n_max": v.n_max_value, "g": p.g, "c_d": p.c_d,
            "max_rate": None if loop is None else loop.max_rate, "max_tilt": None if loop is None else loop.max_tilt}


@dataclass(frozen=True)
class VehicleSpec:
    """Vehicle numbers a controller may use (units in comments).

    Build one with :meth:`from_model` or :meth:`from_vehicle`; a field left
    None takes the default vehicle's datasheet value. Fields are validated
    finite and > 0 (``c_d`` >= 0).
    """

    m: float | None = None        # mass, kg
    Jxx: float | None = None      # kg m^2 (only an initial guess of the feed-forward fit)
    Jyy: float | None = None      # kg m^2
    Jzz: float | None = None      # kg m^2
    kt: float | None = None       # rotor thrust coefficient, N / RU^2
    kq: float | None = None       # rotor torque coefficient, N m / RU^2
    d: float | None = None        # arm length, m (X layout)
    n_max: float | None = None    # rotor speed limit, RU
    g: float | None = None        # m/s^2
    c_d: float | None = None      # quadratic drag of the nominal model, 1/m (a known constant, not identified)
    source: str = "datasheet"     # where m, J, kt, kq came from
    vehicle: str = ""             # the vehicle whose datasheet filled the rest
    torque_scale: float | None = None  # acceptable torque deviation of the controllers' weights, N m (see below)
    max_rate: float | None = None   # largest body-rate command of the vehicle's inner loop, rad/s (None: no loop)
    max_tilt: float | None = None   # largest roll or pitch command of the vehicle's inner loop, rad (None: no loop)

    def __post_init__(self):
        missing = [n for n in SPEC_FIELDS if getattr(self, n) is None]
        if missing:
            sheet = datasheet()
            for n in missing:
                object.__setattr__(self, n, sheet[n])
            if len(missing) == len(SPEC_FIELDS) and self.max_rate is None and self.max_tilt is None:
                object.__setattr__(self, "max_rate", sheet["max_rate"])
                object.__setattr__(self, "max_tilt", sheet["max_tilt"])
            if not self.vehicle:
                from sim.vehicles.vehicle import DEFAULT_VEHICLE
                object.__setattr__(self, "vehicle", DEFAULT_VEHICLE)
        for name in SPEC_FIELDS:
            v = getattr(self, name)
            low_ok = name == "c_d"
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                    or not (math.isfinite(v) and (v > 0 or (low_ok and v == 0))):
                bound = ">= 0" if low_ok else "> 0"
                raise ConfigurationError(f"VehicleSpec.{name} must be a finite number {bound}; found {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("max_rate", "max_tilt"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                                  or v <= 0):
                raise ConfigurationError(f"VehicleSpec.{name} must be None or a finite number > 0; found {v!r}")
        if self.torque_scale is None:
            object.__setattr__(self, "torque_scale", torque_scale(self.kt, self.n_max, self.d))
        elif not (isinstance(self.torque_scale, (int, float)) and math.isfinite(self.torque_scale)
                  and self.torque_scale > 0):
            raise ConfigurationError(f"VehicleSpec.torque_scale must be a finite number > 0; found {self.torque_scale!r}")

    @classmethod
    def from_vehicle(cls, vehicle) -> "VehicleSpec":
        """The datasheet of ``vehicle`` (a :class:`sim.vehicles.vehicle.Vehicle`, name or file)."""
        from sim.vehicles.vehicle import load_vehicle

        v = load_vehicle(vehicle)
        return cls(**datasheet(v), vehicle=v.name)

    @classmethod
    def from_model(cls, model, vehicle=None) -> "VehicleSpec":
        """The datasheet of ``vehicle``, with ``m, J, kt, kq`` replaced by the model's identified ``theta`` if it has one.

        An :class:`mpc.prediction.models.AnalyticModel` (the oracle, or the nominal
        equations with other parameters) carries its parameters as ``theta``,
        and its drag ``c_d`` (for example none, as the oracle of a plant without
        drag) as ``params.c_d``.
        ``vehicle`` None: the default vehicle.
        """
        base = cls.from_vehicle(vehicle)
        params = getattr(model, "params", None)       # equations (an AnalyticModel) know their own drag
        if params is not None and getattr(params, "c_d", None) is not None and params.c_d != base.c_d:
            base = dataclasses.replace(base, c_d=params.c_d)
        theta = getattr(model, "theta", None)
        if theta is None:
            return base
        theta = np.asarray(theta, dtype=float).reshape(-1)
        if theta.shape != (6,):
            raise ConfigurationError(f"model theta must have 6 entries (m, Jxx, Jyy, Jzz, kt, kq); found {theta.shape}")
        m, Jxx, Jyy, Jzz, kt, kq = (float(v) for v in theta)
        return dataclasses.replace(base, m=m, Jxx=Jxx, Jyy=Jyy, Jzz=Jzz, kt=kt, kq=kq,
                                   source=f"theta of {getattr(model, 'name', 'model')}")

    @property
    def lever(self) -> float:
        """Rotor lever arm about roll and pitch, m (X layout: d / sqrt(2))."""
        return self.d / math.sqrt(2.0)

    @property
    def n_max_sq(self) -> float:
        """Per-rotor limit of n^2, RU^2."""
        return self.n_max ** 2

    @property
    def weight(self) -> float:
        """m g, N (scales the thrust weight and the thrust variable of the NMPC)."""
        return self.m * self.g

    def inputs(self, level: str = "wrench") -> "InputSet":
        """The inputs a controller may command at ``level`` (:data:`sim.levels.LEVELS`): :class:`InputSet`."""
        return InputSet(self, level)


#: The controllers' acceptable thrust deviation (the scale of their input weight) as a share of the weight m g.
THRUST_SCALE_FRACTION = 0.2
#: Share of the rotors' total thrust a controller may command at the ``ctbr`` and ``ctatt`` levels: the rest is left
#: to the inner loop's torques.
THRUST_HEADROOM = 0.9
#: Acceptable deviations of the commanded rates (rad/s) and angles (rad): those of the states they command (the
#: default state weights').
RATE_SCALE, TILT_SCALE = 1.0, 0.2


class InputSet:
    """What a controller may command at one level: ``lower <= matrix @ u <= upper``, its projection and its scales.

    * ``wrench``: the rotor-feasible set, each rotor's load ``n_i^2 / n_max^2`` between 0 and 1
      (:func:`sim.vehicles.rotors.load_matrix`); the projection is the rotors' own (:func:`sim.vehicles.rotors.realize`).
    * ``ctbr``: thrust from 0 to :data:`THRUST_HEADROOM` of the rotors' total, each rate within the vehicle's
      ``max_rate``; ``ctatt``: the same thrust, roll and pitch within ``max_tilt``, the yaw rate within ``max_rate``.
      The projection clips each input.

    Parameters
    ----------
    spec : VehicleSpec
    level : str

    Attributes
    ----------
    matrix : ndarray (4, 4)
    lower, upper : ndarray (4,)
    scale : ndarray (4,)
        Acceptable deviations of each input (the controllers' input weights are ``1 / scale^2``): thrust
        :data:`THRUST_SCALE_FRACTION` of m g;
        torques the spec's ``torque_scale``; rates :data:`RATE_SCALE`, angles :data:`TILT_SCALE`.

    Raises
    ------
    ConfigurationError
        At ``ctbr`` or ``ctatt`` for a vehicle that states no ``max_rate`` (or ``max_tilt``): no inner loop.
    """

    def __init__(self, spec: VehicleSpec, level: str = "wrench"):
        from sim.levels import check_level
        from sim.vehicles.rotors import load_matrix

        try:
            self.level = check_level(level)
        except Exception as e:
            raise ConfigurationError(str(e)) from None
        self.spec = spec
        thrust_scale = THRUST_SCALE_FRACTION * spec.m * spec.g
        if level == "wrench":
            self.matrix, self.lower, self.upper = load_matrix(spec), np.zeros(4), np.ones(4)
            self.scale = np.array([thrust_scale] + [spec.torque_scale] * 3)
            return
        need = ("max_rate",) if level == "ctbr" else ("max_rate", "max_tilt")
        for name in need:
            if getattr(spec, name) is None:
                raise ConfigurationError(f"vehicle {spec.vehicle!r} has no inner loop (its file gives no [inner_loop] table with "
                          f"inner_loop.rate_kp and inner_loop.{name}), so it cannot be flown at the {level!r} level")
        t_max = THRUST_HEADROOM * 4.0 * spec.kt * spec.n_max_sq
        limits = (np.array([t_max, spec.max_rate, spec.max_rate, spec.max_rate]) if level == "ctbr" else
                  np.array([t_max, spec.max_tilt, spec.max_tilt, spec.max_rate]))
        self.matrix = np.diag(1.0 / limits)
        self.lower, self.upper = np.array([0.0, -1.0, -1.0, -1.0]), np.ones(4)
        self.scale = (np.array([thrust_scale, RATE_SCALE, RATE_SCALE, RATE_SCALE]) if level == "ctbr" else
                      np.array([thrust_scale, TILT_SCALE, TILT_SCALE, RATE_SCALE]))
        self._low, self._high = limits * self.lower, limits * self.upper

    def project(self, u) -> np.ndarray:
        """``u`` (4,) if it may be commanded, else its projection onto the set."""
        u = np.asarray(u, dtype=float)
        if self.level == "wrench":
            from sim.vehicles.rotors import realize

            return realize(u, self.spec).wrench
        return np.clip(u, self._low, self._high)

    def contains(self, u, tol: float = 1e-9) -> bool:
        """True when ``u`` (4,) lies in the set (within ``tol`` of each row's bounds)."""
        r = self.matrix @ np.asarray(u, dtype=float)
        return bool(np.all(r >= self.lower - tol) and np.all(r <= self.upper + tol))
