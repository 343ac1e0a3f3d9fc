"""Physical parameters, simulator fidelity and measurement noise.

All three are frozen dataclasses: build a variant with
``dataclasses.replace(p, m=0.08)`` or ``QuadParams(m=0.08)``.
Reference values are those of the Parrot Rolling Spider.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ._validate import nonnegative_finite, positive_finite

#: Names of the six identifiable parameters, in the order used everywhere
#: (Fisher information, PINN theta-hat, ONNX metadata).
THETA_NAMES = ("m", "Jxx", "Jyy", "Jzz", "kt", "kq")

#: State and input names: NED world frame, ZYX Euler angles.
STATE_NAMES = ("x", "y", "z", "phi", "theta", "psi", "p", "q", "r", "vx", "vy", "vz")
INPUT_NAMES = ("T", "tau_x", "tau_y", "tau_z")
NX = 12
NU = 4

#: Standard gravity, m/s^2 (every vehicle's; RotorPy's too).
GRAVITY = 9.81

#: Control period (s) and RK4 substeps per period (1 kHz integration).
DT = 0.01
SUBSTEPS = 10


@dataclass(frozen=True)
class QuadParams:
    """Quadrotor parameters (SI units; rotor speed in rotor units, RU).

    Every field must be finite and > 0; a bad value raises
    :class:`sim.errors.SimInputError` (a ``ValueError``) naming the field.
    """

    m: float = 0.068          # mass, kg
    Jxx: float = 6.86e-5      # roll inertia, kg m^2
    Jyy: float = 9.20e-5      # pitch inertia, kg m^2
    Jzz: float = 1.366e-4     # yaw inertia, kg m^2
    kt: float = 0.0100        # rotor thrust coefficient, N / RU^2
    kq: float = 7.83e-4       # rotor reaction-torque coefficient, N m / RU^2
    d: float = 0.0624         # arm length, m (X layout, lever arm d / sqrt(2))
    g: float = GRAVITY        # gravity, m / s^2
    c_d: float = 0.05         # quadratic drag, 1/m (acceleration = c_d v|v|); 0 for none
    n_max: float | None = None  # rotor speed limit, RU; None: four rotors at n_max give 2 m g

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "n_max" and v is None:
                continue
            check = nonnegative_finite if f.name == "c_d" else positive_finite
            object.__setattr__(self, f.name, check(v, f"QuadParams.{f.name}"))

    @property
    def theta(self) -> np.ndarray:
        """The identifiable parameters ``(m, Jxx, Jyy, Jzz, kt, kq)``, shape (6,)."""
        return np.array([getattr(self, n) for n in THETA_NAMES])

    def with_theta(self, theta) -> "QuadParams":
        """Copy with ``(m, Jxx, Jyy, Jzz, kt, kq)`` replaced by ``theta`` (6,)."""
        theta = np.asarray(theta, dtype=float).reshape(-1)
        if theta.shape != (6,):
            from .errors import SimInputError
            raise SimInputError(f"theta must have shape (6,) for {THETA_NAMES}; found {theta.shape}")
        return dataclasses.replace(self, **{n: float(v) for n, v in zip(THETA_NAMES, theta)})

    @property
    def hover_thrust(self) -> float:
        """Thrust that balances gravity, N."""
        return self.m * self.g

    @property
    def lever(self) -> float:
        """Rotor lever arm about the roll and pitch axes, m (X layout: d / sqrt(2))."""
        return self.d / math.sqrt(2.0)

    @property
    def n_max_sq(self) -> float:
        """Per-rotor limit of n^2, RU^2: ``n_max^2``, or (``n_max`` None) the value where four rotors give 2 m g."""
        if self.n_max is not None:
            return self.n_max ** 2
        return 2.0 * self.m * self.g / (4.0 * self.kt)

    @property
    def n_hover(self) -> float:
        """Rotor speed at hover, RU."""
        return math.sqrt(self.m * self.g / (4.0 * self.kt))


@dataclass(frozen=True)
class Fidelity:
    """Unmodelled effects of the high-fidelity simulator; each 0 means off.

    No learned model or MPC prediction model contains these effects: they
    exist for mismatch studies. ``Fidelity()`` is the nominal simulator and
    :data:`HIGH_FIDELITY` switches all three on at typical magnitudes.
    """

    # First-order motor lag: n' = (n_cmd - n) / motor_tau, s. Typical 0.02-0.05 s.
    motor_tau: float = 0.0
    # Rotor drag (blade flapping): body-frame horizontal force
    # F_b = -rotor_drag * (sum_i n_i) * (v_bx, v_by, 0), N s / (m RU).
    # 1.2e-3 gives about 0.3 1/s of linear drag per unit mass at hover.
    rotor_drag: float = 0.0
    # Rotor gyroscopic torque: tau_g = -rotor_gyro * (sum_i s_i n_i) * (q, -p, 0),
    # N m s / RU (rotor inertia times the RU -> rad/s scale; s_i the spin signs).
    rotor_gyro: float = 0.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, nonnegative_finite(getattr(self, f.name), f"Fidelity.{f.name}"))

    @property
    def is_nominal(self) -> bool:
        """True when every unmodelled effect is switched off."""
        return self.motor_tau == 0.0 and self.rotor_drag == 0.0 and self.rotor_gyro == 0.0


NOMINAL = Fidelity()
HIGH_FIDELITY = Fidelity(motor_tau=0.03, rotor_drag=1.2e-3, rotor_gyro=5e-6)
#: Named fidelities (command-line ``--fidelity`` and the data description stored with a trained model): nominal,
#: high (all three effects) and each effect of the high-fidelity simulator alone.
FIDELITIES = {"nominal": NOMINAL, "high": HIGH_FIDELITY,
              "motor-lag": Fidelity(motor_tau=HIGH_FIDELITY.motor_tau),
              "rotor-drag": Fidelity(rotor_drag=HIGH_FIDELITY.rotor_drag),
              "rotor-gyro": Fidelity(rotor_gyro=HIGH_FIDELITY.rotor_gyro)}
#: What a dataset's ``u`` can log: the wrench command, or the wrench the rotors realized
#: (``sim.identification.excitation.make_dataset(inputs=...)``).
INPUT_LOGS = ("commanded", "realized")


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise (standard deviations) of the logged data.

    Defaults are those of an indoor motion-capture system plus an IMU and
    rotor-speed telemetry: 1 mm position, 1 mrad (0.057 deg) attitude,
    5 mrad/s gyro, 5 mm/s velocity, 0.01 RU rotor speed (0.25 % of hover).
    ``NoiseModel.none()`` is noise-free.
    """

    position: float = 1e-3        # m
    attitude: float = 1e-3        # rad
    body_rate: float = 5e-3       # rad / s
    velocity: float = 5e-3        # m / s
    rotor_speed: float = 1e-2     # RU

    def __post_init__(self):
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, nonnegative_finite(getattr(self, f.name), f"NoiseModel.{f.name}"))

    @classmethod
    def none(cls) -> "NoiseModel":
        """Noise-free measurements."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def state_std(self) -> np.ndarray:
        """Per-state standard deviation in state order, shape (12,)."""
        return np.repeat([self.position, self.attitude, self.body_rate, self.velocity], 3)

    @property
    def is_zero(self) -> bool:
        """True when every standard deviation is zero."""
        return not np.any(self.state_std) and self.rotor_speed == 0.0
