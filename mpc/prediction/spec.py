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
    None)."""
    from sim.vehicles.vehicle import load_vehicle

    v = load_vehicle(vehicle)
    p = v.params
    return {"m": p.m, "Jxx": p.Jxx, "Jyy": p.Jyy, "Jzz": p.Jzz, "kt": p.kt, "kq": p.kq, "d": p.d,
            "n_max": v.n_max_value, "g": p.g, "c_d": p.c_d}


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

    def __post_init__(self):
        missing = [n for n in SPEC_FIELDS if getattr(self, n) is None]
        if missing:
            sheet = datasheet()
            for n in missing:
                object.__setattr__(self, n, sheet[n])
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
