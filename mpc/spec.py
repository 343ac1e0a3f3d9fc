"""What a controller may know about the vehicle besides its prediction model.

A controller never reads the plant's :class:`sim.QuadParams`. It gets its
prediction model and a :class:`VehicleSpec`: the numbers a user has from the
vehicle's datasheet (arm length, rotor speed limit) plus the mass and rotor
coefficients the model identified, when it carries them (``theta`` in the
ONNX metadata). Everything else (hover trim, feed-forward) comes from the
model itself (:mod:`mpc.feedforward`).

The datasheet numbers are those of the Parrot Rolling Spider, written here
as constants; the identified ones replace them where a model has its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ConfigurationError

#: Datasheet values (Parrot Rolling Spider): what a user of this vehicle knows without identification.
DATASHEET = {
    "m": 0.068,            # mass, kg
    "Jxx": 6.86e-5,        # inertias, kg m^2 (only an initial guess of the feed-forward fit)
    "Jyy": 9.20e-5,
    "Jzz": 1.366e-4,
    "kt": 0.0100,          # rotor thrust coefficient, N / RU^2
    "kq": 7.83e-4,         # rotor torque coefficient, N m / RU^2
    "d": 0.0624,           # arm length, m (X layout)
    "n_max": 5.7752922,    # rotor speed limit, RU (four rotors at n_max give 2 m g)
    "g": 9.81,             # gravity, m/s^2
    "c_d": 0.05,           # quadratic drag of the nominal model, 1/m (a known constant, not identified)
}


@dataclass(frozen=True)
class VehicleSpec:
    """Vehicle numbers a controller may use (units in comments).

    Build one with :meth:`from_model`; fields are validated finite and > 0.
    """

    m: float = DATASHEET["m"]          # mass, kg
    Jxx: float = DATASHEET["Jxx"]      # kg m^2
    Jyy: float = DATASHEET["Jyy"]      # kg m^2
    Jzz: float = DATASHEET["Jzz"]      # kg m^2
    kt: float = DATASHEET["kt"]        # N / RU^2
    kq: float = DATASHEET["kq"]        # N m / RU^2
    d: float = DATASHEET["d"]          # arm length, m
    n_max: float = DATASHEET["n_max"]  # rotor speed limit, RU
    g: float = DATASHEET["g"]          # m/s^2
    c_d: float = DATASHEET["c_d"]      # 1/m
    source: str = "datasheet"          # where m, J, kt, kq came from

    def __post_init__(self):
        for name in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "d", "n_max", "g", "c_d"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                    or not (math.isfinite(v) and v > 0):
                raise ConfigurationError(f"VehicleSpec.{name} must be a finite number > 0; found {v!r}")
            object.__setattr__(self, name, float(v))

    @classmethod
    def from_model(cls, model) -> "VehicleSpec":
        """The datasheet, with ``m, J, kt, kq`` replaced by the model's identified ``theta`` if it has one.

        An :class:`mpc.models.AnalyticModel` (the oracle, or the nominal
        equations with other parameters) carries its parameters as ``theta``.
        """
        theta = getattr(model, "theta", None)
        if theta is None:
            return cls()
        theta = np.asarray(theta, dtype=float).reshape(-1)
        if theta.shape != (6,):
            raise ConfigurationError(f"model theta must have 6 entries (m, Jxx, Jyy, Jzz, kt, kq); found {theta.shape}")
        m, Jxx, Jyy, Jzz, kt, kq = (float(v) for v in theta)
        return cls(m=m, Jxx=Jxx, Jyy=Jyy, Jzz=Jzz, kt=kt, kq=kq, source=f"theta of {getattr(model, 'name', 'model')}")

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
