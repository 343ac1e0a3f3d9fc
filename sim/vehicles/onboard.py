"""The settings of a vehicle's onboard controller: its rate, gains and command limits (the ``[inner_loop]`` table
of a vehicle file).

A vehicle flown at the ``ctbr`` or ``ctatt`` command level (:mod:`sim.levels`) is flown through its onboard
controller (:mod:`sim.plants.inner_loop`); these are its numbers, in SI units and per unit inertia::

    [inner_loop]
    rate_hz = 500.0                  # Hz; 1000 divided by a whole number
    rate_kp = [60.0, 60.0, 30.0]     # 1/s, roll, pitch, yaw
    rate_ki = [0.0, 0.0, 0.0]        # 1/s^2
    rate_kd = [0.0, 0.0, 0.0]        # dimensionless
    rate_i_limit = [0.5, 0.5, 0.5]   # rad, largest |integral of the rate error|
    att_kp = [6.0, 6.0]              # 1/s, roll, pitch
    att_ki = [0.0, 0.0]              # 1/s^2
    att_i_limit = [0.3, 0.3]         # rad s
    max_rate = 10.0                  # rad/s, the largest rate command
    max_tilt = 0.6                   # rad, the largest roll or pitch command
    source = "where the numbers come from"
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..errors import SimInputError


def _triple(value, name: str, n: int = 3) -> tuple[float, ...]:
    """``value`` as ``n`` finite numbers >= 0, or a SimInputError naming ``name``."""
    ok = isinstance(value, (list, tuple)) and len(value) == n and all(
        not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v >= 0 for v in value)
    if not ok:
        raise SimInputError(f"{name} must be {n} finite numbers >= 0; found {value!r}")
    return tuple(float(v) for v in value)


@dataclass(frozen=True)
class InnerLoopConfig:
    """The onboard controller's rate and gains (SI units, per unit inertia).

    Attributes
    ----------
    rate_hz : float
        How often the loops run, Hz; 1000 divided by a whole number (the plant advances in 1 ms ticks).
    rate_kp, rate_ki, rate_kd : tuple of 3 float
        Rate-loop gains for roll, pitch and yaw: 1/s, 1/s^2 and dimensionless.
    rate_i_limit : tuple of 3 float
        Largest magnitude of each rate error's integral, rad (anti-windup).
    att_kp, att_ki : tuple of 2 float
        Attitude-loop gains for roll and pitch: 1/s and 1/s^2 (rate setpoint per angle error).
    att_i_limit : tuple of 2 float
        Largest magnitude of each angle error's integral, rad s.
    max_rate : float
        Largest body-rate command the loop accepts, rad/s (larger ones are clipped).
    max_tilt : float
        Largest roll or pitch command, rad (larger ones are clipped).
    source : str
        Where the numbers come from.
    """

    rate_hz: float = 500.0
    rate_kp: tuple = (60.0, 60.0, 30.0)
    rate_ki: tuple = (0.0, 0.0, 0.0)
    rate_kd: tuple = (0.0, 0.0, 0.0)
    rate_i_limit: tuple = (0.5, 0.5, 0.5)
    att_kp: tuple = (6.0, 6.0)
    att_ki: tuple = (0.0, 0.0)
    att_i_limit: tuple = (0.3, 0.3)
    max_rate: float = 10.0
    max_tilt: float = 0.6
    source: str = ""

    def __post_init__(self):
        r = self.rate_hz
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r) or r <= 0:
            raise SimInputError(f"inner_loop.rate_hz must be a number of Hz > 0; found {r!r}")
        ticks = 1000.0 / r
        if abs(ticks - round(ticks)) > 1e-9 or round(ticks) < 1:
            raise SimInputError(f"inner_loop.rate_hz must be 1000 Hz divided by a whole number (the plant advances "
                                f"in 1 ms ticks: 1000, 500, 250, 200, ... Hz); found {r!r}")
        for name, n in (("rate_kp", 3), ("rate_ki", 3), ("rate_kd", 3), ("rate_i_limit", 3), ("att_kp", 2),
                        ("att_ki", 2), ("att_i_limit", 2)):
            object.__setattr__(self, name, _triple(getattr(self, name), f"inner_loop.{name}", n))
        for name in ("max_rate", "max_tilt"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise SimInputError(f"inner_loop.{name} must be a number > 0; found {v!r}")
        if self.max_tilt >= math.pi / 2:
            raise SimInputError(f"inner_loop.max_tilt must be below pi/2 rad; found {self.max_tilt!r}")

    def to_dict(self) -> dict:
        """JSON-ready form: the ``[inner_loop]`` table's keys, gains as lists."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @property
    def period_s(self) -> float:
        """One period of the loops, s."""
        return 1.0 / self.rate_hz

    @property
    def ticks(self) -> int:
        """One period of the loops in the plant's 1 ms ticks."""
        return int(round(1000.0 / self.rate_hz))


#: Keys of a vehicle file's ``[inner_loop]`` table.
INNER_LOOP_KEYS = tuple(f.name for f in dataclasses.fields(InnerLoopConfig))


def inner_loop_from_dict(data, where: str = "inner_loop") -> InnerLoopConfig:
    """An :class:`InnerLoopConfig` from a vehicle file's ``[inner_loop]`` table; an unknown key or a bad value
    raises naming it."""
    if not isinstance(data, dict):
        raise SimInputError(f"{where}: must be a table of keys; found {type(data).__name__}")
    unknown = sorted(set(data) - set(INNER_LOOP_KEYS))
    if unknown:
        raise SimInputError(f"{where}: unknown key 'inner_loop.{unknown[0]}'; the keys are "
                            f"{', '.join(INNER_LOOP_KEYS)}")
    if not isinstance(data.get("source", ""), str):
        raise SimInputError(f"{where}: inner_loop.source must be a string; found {data['source']!r}")
    try:
        return InnerLoopConfig(**data)
    except SimInputError as e:
        raise SimInputError(f"{where}: {e}") from None
