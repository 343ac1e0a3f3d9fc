"""The settings of a vehicle's onboard controller: its rate, gains and command limits (the ``[inner_loop]`` table
of a vehicle file).

A vehicle flown at the ``ctbr`` or ``ctatt`` command level (:mod:`sim.levels`) is flown through its onboard
controller (:mod:`sim.plants.inner_loop`); these are its numbers, in SI units and per unit inertia::

    [inner_loop]
    rate_hz = 500.0                  # Hz: 1000, 500, 200 or 100 (a whole number of runs per 10 ms period)
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
    # optional: the response the nominal prediction models of the ctbr and ctatt levels assume
    rate_tau = [0.02, 0.02, 0.04]    # s, first-order time constant of each body rate's response
    att_wn = [20.0, 20.0]            # rad/s, natural frequency of the roll and pitch response
    att_zeta = [0.8, 0.8]            # damping ratio of the roll and pitch response
    response_source = "where the response comes from"

``rate_hz`` and ``rate_kp`` are required: a table without them is refused. Without ``rate_tau``, ``att_wn`` and
``att_zeta`` the response is derived from the gains (:meth:`InnerLoopConfig.response`).
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
class LoopResponse:
    """The closed inner loop as the nominal models of the ``ctbr`` and ``ctatt`` levels see it.

    Attributes
    ----------
    rate_tau : tuple of 3 float
        First-order time constant of each body rate's response to its command (roll, pitch, yaw), s.
    att_wn, att_zeta : tuple of 2 float
        Natural frequency (rad/s) and damping ratio of roll's and pitch's second-order response to their commands.
    source : str
        Where the numbers come from.
    """

    rate_tau: tuple
    att_wn: tuple
    att_zeta: tuple
    source: str

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {"rate_tau": list(self.rate_tau), "att_wn": list(self.att_wn), "att_zeta": list(self.att_zeta),
                "source": self.source}


#: The loop's period in the plant's 1 ms ticks: a whole number of periods in the 10 ms control period.
LOOP_TICKS = (1, 2, 5, 10)


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
    rate_tau : tuple of 3 float or None
        Time constant of each body rate's first-order response to its command, s (the ``ctbr`` nominal model);
        None: derived from the gains.
    att_wn, att_zeta : tuple of 2 float or None
        Natural frequency (rad/s) and damping ratio of the roll and pitch responses to their commands (the
        ``ctatt`` nominal model); None: derived from the gains.
    response_source : str
        Where ``rate_tau``, ``att_wn`` and ``att_zeta`` come from, when given.
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
    rate_tau: tuple | None = None
    att_wn: tuple | None = None
    att_zeta: tuple | None = None
    response_source: str = ""

    def __post_init__(self):
        r = self.rate_hz
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r) or r <= 0:
            raise SimInputError(f"inner_loop.rate_hz must be a number of Hz > 0; found {r!r}")
        ticks = 1000.0 / r
        if abs(ticks - round(ticks)) > 1e-9 or round(ticks) not in LOOP_TICKS:
            raise SimInputError(f"inner_loop.rate_hz must run the loop a whole number of times in each 10 ms control "
                                f"period, on the plant's 1 ms ticks: one of {', '.join(f'{1000 // t}' for t in LOOP_TICKS)} "
                                f"Hz; found {r!r}")
        for name, n in (("rate_kp", 3), ("rate_ki", 3), ("rate_kd", 3), ("rate_i_limit", 3), ("att_kp", 2),
                        ("att_ki", 2), ("att_i_limit", 2)):
            object.__setattr__(self, name, _triple(getattr(self, name), f"inner_loop.{name}", n))
        for name in ("max_rate", "max_tilt"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise SimInputError(f"inner_loop.{name} must be a number > 0; found {v!r}")
        if self.max_tilt >= math.pi / 2:
            raise SimInputError(f"inner_loop.max_tilt must be below pi/2 rad; found {self.max_tilt!r}")
        for name, n in (("rate_tau", 3), ("att_wn", 2), ("att_zeta", 2)):
            v = getattr(self, name)
            if v is not None:
                v = _triple(v, f"inner_loop.{name}", n)
                if min(v) <= 0:
                    raise SimInputError(f"inner_loop.{name} must be {n} numbers > 0; found {list(v)!r}")
                object.__setattr__(self, name, v)
        for name in ("source", "response_source"):
            if not isinstance(getattr(self, name), str):
                raise SimInputError(f"inner_loop.{name} must be a string; found {getattr(self, name)!r}")

    def response(self) -> "LoopResponse":
        """The response the nominal models of the ``ctbr`` and ``ctatt`` levels assume (:class:`LoopResponse`).

        Given in the table, or derived from the gains. Derived: each rate loop, a PD on the inertia,
        ``(1 + kd) w' = kp (w_cmd - w)``, is a first-order lag ``tau = (1 + kd) / kp`` plus half a loop period
        (the command is held over the period); the attitude loop, a P of gain ``att_kp`` over that lag,
        ``tau phi'' + phi' = att_kp (phi_cmd - phi)``, is second order with ``wn = sqrt(att_kp / tau)`` and
        ``zeta = 1 / (2 wn tau)``. The integrals are left out (they act on errors that last).
        """
        derived = []
        tau = self.rate_tau
        if tau is None:
            if min(self.rate_kp) <= 0:
                raise SimInputError("inner_loop.rate_kp must be > 0 on every axis for a rate response to be derived "
                                    "from it; give inner_loop.rate_tau instead")
            tau = tuple((1.0 + kd) / kp + 0.5 * self.period_s for kp, kd in zip(self.rate_kp, self.rate_kd))
            derived.append("rate_tau")
        wn, zeta = self.att_wn, self.att_zeta
        if wn is None or zeta is None:
            if min(self.att_kp) <= 0:
                raise SimInputError("inner_loop.att_kp must be > 0 on roll and pitch for an attitude response to be "
                                    "derived from it; give inner_loop.att_wn and att_zeta instead")
            wn_d = tuple(math.sqrt(k / t) for k, t in zip(self.att_kp, tau[:2]))
            zeta_d = tuple(1.0 / (2.0 * w * t) for w, t in zip(wn_d, tau[:2]))
            if wn is None:
                wn = wn_d
                derived.append("att_wn")
            if zeta is None:
                zeta = zeta_d
                derived.append("att_zeta")
        given = [n for n in ("rate_tau", "att_wn", "att_zeta") if n not in derived]
        parts = []
        if given:
            parts.append(f"{', '.join(given)}: {self.response_source or 'given in the vehicle file'}")
        if derived:
            parts.append(f"{', '.join(derived)}: derived from the loop's gains")
        return LoopResponse(tuple(tau), tuple(wn), tuple(zeta), "; ".join(parts))

    def to_dict(self) -> dict:
        """JSON-ready form: the ``[inner_loop]`` table's keys, gains as lists (a response not given left out)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()
                if v is not None}

    @property
    def period_s(self) -> float:
        """One period of the loops, s."""
        return 1.0 / self.rate_hz

    @property
    def ticks(self) -> int:
        """One period of the loops in the plant's 1 ms ticks."""
        return int(round(1000.0 / self.rate_hz))


#: Keys of a vehicle file's ``[inner_loop]`` table, and those it must give.
INNER_LOOP_KEYS = tuple(f.name for f in dataclasses.fields(InnerLoopConfig))
REQUIRED_INNER_LOOP_KEYS = ("rate_hz", "rate_kp")


def inner_loop_from_dict(data, where: str = "inner_loop") -> InnerLoopConfig:
    """An :class:`InnerLoopConfig` from a vehicle file's ``[inner_loop]`` table; an unknown key or a bad value
    raises naming it."""
    if not isinstance(data, dict):
        raise SimInputError(f"{where}: must be a table of keys; found {type(data).__name__}")
    unknown = sorted(set(data) - set(INNER_LOOP_KEYS))
    if unknown:
        raise SimInputError(f"{where}: unknown key 'inner_loop.{unknown[0]}'; the keys are "
                            f"{', '.join(INNER_LOOP_KEYS)}")
    missing = [k for k in REQUIRED_INNER_LOOP_KEYS if k not in data]
    if missing:
        raise SimInputError(f"{where}: inner_loop.{missing[0]} is missing: an [inner_loop] table must give the "
                            f"loop's {' and '.join(REQUIRED_INNER_LOOP_KEYS)}")
    try:
        return InnerLoopConfig(**data)
    except SimInputError as e:
        raise SimInputError(f"{where}: {e}") from None
