"""Flight-log format files: which column of a real log holds which quantity, in which frame and unit.

A format file is TOML. Every table but ``[attitude]``'s alternatives is
required unless marked optional; an unknown table or key is an error that
names it::

    name = "my-logger"                       # optional, defaults to the file's stem
    description = "..."                      # optional

    [time]
    column = "t"
    unit = "s"                               # s, ms, us, ns

    [frames]
    world = "z-up"                           # ned, enu, z-up (x forward, y left, z up)
    body = "flu"                             # frd, flu

    [position]
    columns = ["x", "y", "z"]
    unit = "m"                               # m, cm, mm

    [attitude]                               # either a quaternion ...
    quaternion = ["qx", "qy", "qz", "qw"]
    order = "xyzw"                           # xyzw or wxyz: the order of the columns above
    # euler = ["roll", "pitch", "yaw"]       # ... or ZYX Euler angles
    # unit = "rad"                           # rad, deg (Euler angles only)

    [velocity]
    columns = ["vx", "vy", "vz"]
    unit = "m/s"                             # m/s, mm/s
    frame = "world"                          # world, body

    [rates]
    columns = ["wx", "wy", "wz"]             # body rates, in the body frame above
    unit = "rad/s"                           # rad/s, deg/s

    [rotors]
    columns = ["m1", "m2", "m3", "m4"]
    unit = "erpm"                            # rad/s, rpm, erpm (then pole_pairs)
    pole_pairs = 6
    positions = ["front-right", "rear-right", "rear-left", "front-left"]
    spin = ["ccw", "cw", "ccw", "cw"]        # seen from above

    [airborne]                               # optional
    column = "is_flying"                     # optional flag column (non-zero = flying)
    min_thrust_to_weight = 0.5               # rotor thrust / weight that counts as flying
    margin_s = 0.5                           # cut this much after take-off and before landing

    [delay]                                  # optional
    search = [-5, 10]                        # motor-to-state delays tried, in samples

    [clean]                                  # optional
    max_rotor_over_n_max = 1.5               # a rotor speed above this multiple of n_max is a spike
    max_position_jump_m = 0.2                # a position this far from the running median around it is a glitch

    [reference]                              # optional: the flight's position reference
    columns = ["x_r", "y_r", "z_r"]          # same world frame and unit as [position]

Frames are converted once, to this project's NED world and FRD body. The
rotors are renumbered to the project's layout (``sim.vehicles.rotors``: front right,
rear right, rear left, front left) and their spins checked against it: the
project's front-right rotor turns counter-clockwise seen from above, so a
log whose front-right rotor turns clockwise has its yaw torque reversed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FlightLogError
from ..files import read_named_toml

#: Folder of the shipped format files.
FORMAT_DIR = Path(__file__).resolve().parent / "formats"

#: Log world frame -> NED (v_ned = C v_log).
WORLD_FRAMES = {
    "ned": np.eye(3),
    "enu": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    "z-up": np.diag([1.0, -1.0, -1.0]),
}
#: Log body frame -> FRD (v_frd = C v_log).
BODY_FRAMES = {"frd": np.eye(3), "flu": np.diag([1.0, -1.0, -1.0])}
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
SPEED_UNITS = {"m/s": 1.0, "mm/s": 1e-3}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
RATE_UNITS = {"rad/s": 1.0, "deg/s": math.pi / 180.0}
ROTOR_UNITS = ("rad/s", "rpm", "erpm")
#: Rotor positions in the project's order (rotor 1 to 4 of ``sim.vehicles.rotors``).
POSITIONS = ("front-right", "rear-right", "rear-left", "front-left")
#: Spin of the project's rotors 1 to 4 seen from above (reaction torque +z FRD for counter-clockwise).
PROJECT_SPIN = ("ccw", "cw", "ccw", "cw")

_KEYS = {
    "": ("name", "description", "time", "frames", "position", "attitude", "velocity", "rates", "rotors",
         "airborne", "delay", "clean", "reference"),
    "time": ("column", "unit"),
    "frames": ("world", "body"),
    "position": ("columns", "unit"),
    "attitude": ("quaternion", "order", "euler", "unit"),
    "velocity": ("columns", "unit", "frame"),
    "rates": ("columns", "unit"),
    "rotors": ("columns", "unit", "pole_pairs", "positions", "spin"),
    "airborne": ("column", "min_thrust_to_weight", "margin_s"),
    "delay": ("search",),
    "clean": ("max_rotor_over_n_max", "max_position_jump_m"),
    "reference": ("columns",),
}
_REQUIRED = ("time", "frames", "position", "attitude", "velocity", "rates", "rotors")


@dataclass(frozen=True)
class LogFormat:
    """A parsed format file (see the module docstring); column names as in the log, units as scale factors."""

    name: str
    path: str
    time_column: str
    time_scale: float              # s per log unit
    time_unit: str                 # the log's time unit, as the format file names it
    world: str                     # ned, enu, z-up
    body: str                      # frd, flu
    position: tuple[str, ...]
    position_scale: float          # m per log unit
    quaternion: tuple[str, ...] | None   # in w, x, y, z order (re-ordered from the file)
    euler: tuple[str, ...] | None        # roll, pitch, yaw
    angle_scale: float             # rad per log unit (Euler angles)
    velocity: tuple[str, ...]
    velocity_scale: float          # m/s per log unit
    velocity_frame: str            # world, body
    rates: tuple[str, ...]
    rate_scale: float              # rad/s per log unit
    rotors: tuple[str, ...]        # log columns in the project's rotor order (1 to 4)
    rotor_scale: float             # rad/s per log unit
    rotor_unit: str
    yaw_sign: float                # +1 if the log's spins are the project's, -1 if all are reversed
    airborne_column: str | None
    min_thrust_to_weight: float
    margin_s: float
    delay_search: tuple[int, int]
    max_rotor_over_n_max: float
    max_position_jump_m: float     # a position row farther than this (m) from the running median around it is masked
    reference: tuple[str, ...] | None

    @property
    def world_matrix(self) -> np.ndarray:
        """(3, 3) log world -> NED."""
        return WORLD_FRAMES[self.world]

    @property
    def body_matrix(self) -> np.ndarray:
        """(3, 3) log body -> FRD."""
        return BODY_FRAMES[self.body]

    def columns(self) -> dict[str, tuple[str, ...]]:
        """The log columns this format reads, by quantity (the group names of the import's report)."""
        out = {"time": (self.time_column,), "position": self.position,
               "attitude": self.quaternion if self.quaternion is not None else self.euler,
               "velocity": self.velocity, "rates": self.rates, "rotors": self.rotors}
        if self.airborne_column is not None:
            out["airborne"] = (self.airborne_column,)
        if self.reference is not None:
            out["reference"] = self.reference
        return out


def format_names() -> list[str]:
    """Names of the shipped format files."""
    return sorted(p.stem for p in FORMAT_DIR.glob("*.toml"))


def load_format(spec) -> LogFormat:
    """The format named ``spec`` (a shipped one, see :func:`format_names`) or read from a ``.toml`` file.

    Raises
    ------
    FlightLogError
        For a missing or unreadable file, an unknown table or key, a unit or frame that is not known, or a value
        of the wrong kind; the message names the file and the key.
    """
    data, path = read_named_toml(spec, FORMAT_DIR, "format", "log format", FlightLogError)
    where = f"format file {str(path)!r}"
    return parse_format(data, where=where, name=path.stem, path=str(path))


def parse_format(data: dict, where: str = "format", name: str = "format", path: str = "") -> LogFormat:
    """A :class:`LogFormat` from the mapping of a format file (``where`` starts every error message)."""
    _check_keys(data, "", where)
    for table in _REQUIRED:
        if table not in data:
            raise FlightLogError(f"{where}: table [{table}] is missing")
    for table in _KEYS[""][2:]:
        if table in data:
            if not isinstance(data[table], dict):
                raise FlightLogError(f"{where}: {table} must be a table [{table}]; found {data[table]!r}")
            _check_keys(data[table], table, where)

    def get(table, key, default=None, required=True):
        t = data.get(table, {})
        if key not in t:
            if required and default is None:
                raise FlightLogError(f"{where}: [{table}] {key} is missing")
            return default
        return t[key]

    def string(table, key, default=None, required=True):
        v = get(table, key, default, required)
        if v is not None and (not isinstance(v, str) or not v):
            raise FlightLogError(f"{where}: [{table}] {key} must be a non-empty string; found {v!r}")
        return v

    def unit(table, key, units, default=None):
        v = string(table, key, default)
        if v not in units:
            raise FlightLogError(f"{where}: [{table}] {key} {v!r} is not a known unit; choose from "
                                 f"{', '.join(units)}")
        return v

    def columns(table, key="columns", n=3, required=True):
        v = get(table, key, None, required)
        if v is None:
            return None
        if (not isinstance(v, list) or len(v) != n or not all(isinstance(c, str) and c for c in v)):
            raise FlightLogError(f"{where}: [{table}] {key} must be a list of {n} column names; found {v!r}")
        return tuple(v)

    def number(table, key, default, lo=0.0):
        v = get(table, key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < lo:
            raise FlightLogError(f"{where}: [{table}] {key} must be a number >= {lo:g}; found {v!r}")
        return float(v)

    for key in ("name", "description"):
        if key in data and not isinstance(data[key], str):
            raise FlightLogError(f"{where}: {key} must be a string; found {data[key]!r}")
    world = string("frames", "world")
    if world not in WORLD_FRAMES:
        raise FlightLogError(f"{where}: [frames] world {world!r} is not a known frame; choose from "
                             f"{', '.join(WORLD_FRAMES)}")
    body = string("frames", "body")
    if body not in BODY_FRAMES:
        raise FlightLogError(f"{where}: [frames] body {body!r} is not a known frame; choose from "
                             f"{', '.join(BODY_FRAMES)}")

    att = data["attitude"]
    quat = euler = None
    angle_scale = 1.0
    if ("quaternion" in att) == ("euler" in att):
        raise FlightLogError(f"{where}: [attitude] needs exactly one of quaternion or euler")
    if "quaternion" in att:
        if "unit" in att:
            raise FlightLogError(f"{where}: [attitude] unit applies to euler angles only, not to a quaternion")
        cols = columns("attitude", "quaternion", 4)
        order = string("attitude", "order")
        if order not in ("xyzw", "wxyz"):
            raise FlightLogError(f"{where}: [attitude] order {order!r} is not known; choose from xyzw, wxyz")
        quat = cols if order == "wxyz" else (cols[3], cols[0], cols[1], cols[2])
    else:
        if "order" in att:
            raise FlightLogError(f"{where}: [attitude] order applies to a quaternion only")
        euler = columns("attitude", "euler", 3)
        angle_scale = ANGLE_UNITS[unit("attitude", "unit", ANGLE_UNITS)]

    rotor_unit = unit("rotors", "unit", ROTOR_UNITS)
    if rotor_unit == "erpm":
        pole_pairs = get("rotors", "pole_pairs")
        if isinstance(pole_pairs, bool) or not isinstance(pole_pairs, int) or pole_pairs < 1:
            raise FlightLogError(f"{where}: [rotors] pole_pairs must be a whole number >= 1; found {pole_pairs!r}")
        rotor_scale = 2.0 * math.pi / 60.0 / pole_pairs
    else:
        if "pole_pairs" in data["rotors"]:
            raise FlightLogError(f"{where}: [rotors] pole_pairs applies to unit 'erpm' only")
        rotor_scale = 1.0 if rotor_unit == "rad/s" else 2.0 * math.pi / 60.0
    rotor_cols = columns("rotors", "columns", 4)
    positions = columns("rotors", "positions", 4)
    if sorted(positions) != sorted(POSITIONS):
        raise FlightLogError(f"{where}: [rotors] positions must name each of {', '.join(POSITIONS)} once; "
                             f"found {list(positions)}")
    spin = columns("rotors", "spin", 4)
    if any(s not in ("cw", "ccw") for s in spin):
        raise FlightLogError(f"{where}: [rotors] spin must be 'cw' or 'ccw' for each rotor; found {list(spin)}")
    by_position = {p: i for i, p in enumerate(positions)}
    ordered = tuple(rotor_cols[by_position[p]] for p in POSITIONS)
    spins = tuple(spin[by_position[p]] for p in POSITIONS)
    if spins == PROJECT_SPIN:
        yaw_sign = 1.0
    elif spins == tuple("cw" if s == "ccw" else "ccw" for s in PROJECT_SPIN):
        yaw_sign = -1.0
    else:
        raise FlightLogError(f"{where}: [rotors] spin {list(spin)} does not alternate: diagonal rotors of a "
                             f"quadrotor turn the same way and neighbours opposite ways")

    search = get("delay", "search", [-5, 10])
    if (not isinstance(search, list) or len(search) != 2 or not all(isinstance(s, int) and not isinstance(s, bool)
                                                                      for s in search) or search[0] > search[1]):
        raise FlightLogError(f"{where}: [delay] search must be [lowest, highest] whole samples; found {search!r}")
    time_unit = unit("time", "unit", TIME_UNITS)
    velocity_frame = string("velocity", "frame", "world")
    if velocity_frame not in ("world", "body"):
        raise FlightLogError(f"{where}: [velocity] frame {velocity_frame!r} is not known; choose from world, body")
    fmt = LogFormat(
        name=data.get("name", name), path=path,
        time_column=string("time", "column"), time_scale=TIME_UNITS[time_unit], time_unit=time_unit,
        world=world, body=body,
        position=columns("position"), position_scale=LENGTH_UNITS[unit("position", "unit", LENGTH_UNITS)],
        quaternion=quat, euler=euler, angle_scale=angle_scale,
        velocity=columns("velocity"), velocity_scale=SPEED_UNITS[unit("velocity", "unit", SPEED_UNITS)],
        velocity_frame=velocity_frame,
        rates=columns("rates"), rate_scale=RATE_UNITS[unit("rates", "unit", RATE_UNITS)],
        rotors=ordered, rotor_scale=rotor_scale, rotor_unit=rotor_unit, yaw_sign=yaw_sign,
        airborne_column=string("airborne", "column", None, required=False),
        min_thrust_to_weight=number("airborne", "min_thrust_to_weight", 0.5),
        margin_s=number("airborne", "margin_s", 0.5),
        delay_search=(int(search[0]), int(search[1])),
        max_rotor_over_n_max=number("clean", "max_rotor_over_n_max", 1.5, lo=1.0),
        max_position_jump_m=number("clean", "max_position_jump_m", 0.2, lo=1e-6),
        reference=columns("reference", required=False) if "reference" in data else None,
    )
    seen: dict[str, str] = {}
    for table, names in fmt.columns().items():
        for c in names:
            if c in seen:
                twice = f"twice in [{table}]" if seen[c] == table else f"in [{seen[c]}] and in [{table}]"
                raise FlightLogError(f"{where}: column {c!r} is named {twice}; each quantity needs a column of its "
                                     f"own")
            seen[c] = table
    return fmt


def _check_keys(table: dict, name: str, where: str) -> None:
    known = _KEYS[name]
    for key in table:
        if key not in known:
            place = f"[{name}]" if name else "at the top level"
            raise FlightLogError(f"{where}: unknown key {key!r} {place}; the keys are {', '.join(known)}")
