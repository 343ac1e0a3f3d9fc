"""Flight-log import: real flight logs (CSV, Parquet) to this project's dataset.

One log is one flight. :func:`read_flight` turns it into a :class:`Flight`
on the 10 ms grid, in this project's conventions (NED world, FRD body, ZYX
Euler angles, rotor speeds in rad/s renumbered to ``sim.vehicles.rotors``' layout),
and :func:`flights_to_dataset` stacks flights into a :class:`~sim.identification.excitation.Dataset`.
Its steps, in order, each reported in :class:`ImportReport`:

1. **Read** the columns the format file names (:mod:`sim.flightlogs.logformat`); a
   missing or all-empty column, or time that goes backwards, is an error.
2. **Clean** each signal group (position, attitude, velocity, rates,
   rotors): a row with a NaN, a row *held* (exactly equal to the row before:
   telemetry that was not refreshed) and, for the rotors, a *spike* (a speed
   below 0 or above ``max_rotor_over_n_max`` times the vehicle's ``n_max``)
   is masked, not guessed; so is an attitude row whose quaternion has a zero
   or non-finite norm, and a position *glitch* (a row farther than
   ``max_position_jump_m`` from the running median of the rows around it: a
   logger's row of zeros). A row is held when each column equals that column's
   last clean value (a NaN or a spike in the row before does not hide it).
   Rows with a repeated timestamp are dropped; a log whose median row interval
   is outside :data:`ROW_INTERVAL_S` is refused (its time unit is wrong).
3. **Resample** onto the 10 ms grid when the log is not on it (another rate,
   or jittered timestamps): linear interpolation between the two rows around
   each grid time (normalized for a quaternion); a grid sample is valid only
   if both rows are, and if each is within :data:`GAP_PERIODS` median log
   periods of it (a sample inside a gap of the log is invented, not measured).
4. **Convert** frames once, to NED and FRD, and the attitude to continuous
   ZYX Euler angles.
5. **Cut** to the airborne part: from the first to the last sample of the
   longest stretch where the rotors carry ``min_thrust_to_weight`` of the
   weight (and the log's flying flag, if the format names one; dips shorter
   than :data:`BRIDGE_S` do not end it), less ``margin_s`` at each end.
6. **Delay**: the motor-to-state delay ``d`` (samples) is the shift of the
   rotor speeds that best explains the measured thrust (the specific force
   along the body z axis, from the velocity's differences) by ``sum n^2``,
   in least squares over the format's search range; the rotor speeds are
   shifted by it (``rotor[k] = logged[k - d]``) and ``d`` is stored.
7. **Check** the conversion: logged velocity against differentiated
   position, logged body rates against rates derived from the attitude (a
   slope per axis; a negative one means a column's sign is wrong), and the
   thrust the motion shows against the vehicle's ``kt sum n^2 / m`` (a
   negative slope means the body frame is wrong; far from 1, the rotor unit
   or the vehicle), and the angular accelerations the body rates show against
   those the rotor speeds' torques give through the vehicle's inertia (a
   negative slope means the rotor positions or spins are wrong).

Masked samples are filled by linear interpolation in time (so every array
is finite) and flagged invalid in the dataset's ``valid`` array.
"""

from __future__ import annotations

import csv
import fnmatch
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..equations.dynamics import rotation_matrix
from ..errors import FlightLogError
from .logformat import LogFormat
from ..params import DT, GRAVITY
from ..vehicles.rotors import mixer_matrix
from ..vehicles.vehicle import Vehicle

#: Grid times closer than this to a log row (in periods) take that row as it is.
ON_GRID_TOL = 1e-3
#: Dips of the rotor thrust below the airborne threshold shorter than this (s) do not end a flight (a fast descent).
BRIDGE_S = 1.0
#: Samples of the centred mean that smooths both sides of the delay fit.
DELAY_SMOOTH = 5
#: Fewest airborne samples a flight must keep.
MIN_SAMPLES = 100
GROUPS = ("position", "attitude", "velocity", "rates", "rotors")
#: A grid sample farther than this many median log periods from the log row on either side of it lies in a gap of
#: the log: it is filled, and flagged invalid.
GAP_PERIODS = 1.5
#: Median interval between log rows (s) that a flight log can have; outside it the time unit is wrong.
ROW_INTERVAL_S = (1e-4, 1.0)
#: A quaternion shorter than this is no attitude (a logger's zeros): its row is masked.
MIN_QUATERNION_NORM = 1e-3
#: Rotor rows with a spike, as a share of the rows whose rotors turn, above which the log is refused (the rotor unit
#: is wrong: every speed is out of range).
MAX_SPIKE_SHARE = 0.5
#: Half-width of the running median a position row is compared with, s (at least 2 rows each side).
GLITCH_HALF_WINDOW_S = 0.05
#: Share of an axis' angular acceleration the rotor torques must explain for the report not to call the check weak.
WEAK_TORQUE_EXPLAINED = 0.5


@dataclass(frozen=True)
class ImportReport:
    """What the import did to one log (plain numbers, for JSON)."""

    name: str
    source: str
    rows: int                       # rows in the log
    duplicate_times: int            # rows dropped for a repeated timestamp
    nan_rows: dict                  # group -> rows with a NaN
    held_rows: dict                 # group -> rows equal to the row before
    spikes: int                     # rotor rows outside [0, max_rotor_over_n_max n_max]
    position_glitches: int          # position rows off the running median by more than max_position_jump_m
    invalid_attitude_rows: int      # rows whose quaternion has a zero or non-finite norm (masked)
    resampling: str                 # how the log was brought onto the 10 ms grid
    log_period_s: float             # median period of the log
    airborne_s: tuple               # (start, end) kept, s from the log's first row
    samples: int                    # samples kept (on the grid)
    valid_state_fraction: float     # kept samples whose state is measured (not filled)
    valid_rotor_fraction: float     # kept samples whose rotor speeds are measured
    gap_samples: int                # kept samples inside a gap of the log (filled, invalid)
    nonfinite_samples: int          # kept samples whose converted state or wrench was not finite (invalid)
    delay_samples: int              # motor-to-state delay applied (rotor[k] = logged[k - d])
    delay_rss_ratio: float          # residual of the best delay over that of the next best (< 1: clear)
    velocity_check: dict            # slope per axis of logged velocity on differentiated position, rms
    rates_check: dict               # slope per axis of logged rates on attitude-derived rates, rms
    thrust_check: dict              # slope of measured thrust on kt sum n^2 (at the delay), intercept m/s^2
    torque_check: dict              # slope per axis of angular acceleration on the rotor torques' (J^-1 tau),
    #                                 share of its variance explained

    def lines(self) -> list[str]:
        """The report as short human-readable lines."""
        held = ", ".join(f"{g} {100.0 * n / max(self.rows, 1):.0f} %" for g, n in self.held_rows.items())
        nans = sum(self.nan_rows.values())
        vs, rs = self.velocity_check["slope"], self.rates_check["slope"]
        ts = self.thrust_check["slope"]
        qs, qe = self.torque_check["slope"], self.torque_check["explained"]
        weak = [a for a, e in zip("xyz", qe) if not e >= WEAK_TORQUE_EXPLAINED]
        invented = ""
        if self.gap_samples or self.nonfinite_samples:
            invented = (f"; invalid: {self.gap_samples} samples in gaps of the log (farther than {GAP_PERIODS:g} "
                        f"log periods from a row), {self.nonfinite_samples} not finite after conversion")
        return [
            f"{self.name}: {self.rows} rows, {self.samples} kept ({self.airborne_s[0]:.2f}-{self.airborne_s[1]:.2f} s "
            f"airborne); {self.resampling}",
            f"  held rows: {held}; NaN rows {nans}; rotor spikes {self.spikes}; position glitches "
            f"{self.position_glitches}; invalid quaternions {self.invalid_attitude_rows}; duplicate times "
            f"{self.duplicate_times}",
            f"  valid: state {100 * self.valid_state_fraction:.1f} %, rotors {100 * self.valid_rotor_fraction:.1f} %"
            f"{invented}; motor-to-state delay {self.delay_samples} samples (residual ratio "
            f"{self.delay_rss_ratio:.2f})",
            f"  checks: velocity / d(position)/dt slope {vs[0]:.3f} {vs[1]:.3f} {vs[2]:.3f}; "
            f"rates / attitude-derived slope {rs[0]:.3f} {rs[1]:.3f} {rs[2]:.3f}; "
            f"thrust from motion / kt sum n^2 slope {ts:.3f}",
            f"  angular acceleration / rotor torques' slope {qs[0]:.3f} {qs[1]:.3f} {qs[2]:.3f}, explaining "
            f"{100 * qe[0]:.0f} {100 * qe[1]:.0f} {100 * qe[2]:.0f} % (x y z)"
            + (f": weak about {' '.join(weak)} (the rotor speeds explain little of the rotation there)"
               if weak else ""),
        ]

    def warnings(self) -> list[str]:
        """Lines for checks that point at a wrong frame, unit or rotor mapping (a velocity, rates or thrust slope
        outside 0.5-2; a negative torque slope)."""
        out = []
        for what, check in (("velocity against differentiated position", self.velocity_check),
                            ("body rates against attitude-derived rates", self.rates_check)):
            for axis, s in zip("xyz", check["slope"]):
                if not (0.5 <= s <= 2.0):
                    out.append(f"{self.name}: {what}, axis {axis}: slope {s:.3f} (a frame, sign or unit may be "
                               f"wrong in the format file)")
        s = self.thrust_check["slope"]
        if not (0.5 <= s <= 2.0):
            out.append(f"{self.name}: thrust from motion against the vehicle's kt sum n^2 / m: slope {s:.3f} (the "
                       f"body frame, the rotor unit or the vehicle's kt / m may be wrong)")
        for axis, s in zip("xyz", self.torque_check["slope"]):
            if s < 0:
                out.append(f"{self.name}: angular acceleration about {axis} against the rotor speeds' torque: slope "
                           f"{s:.3f} (negative: the rotor positions or spins in the format file may be wrong)")
        return out


@dataclass(frozen=True)
class Flight:
    """One imported flight on the 10 ms grid (n samples), in this project's conventions."""

    name: str
    t: np.ndarray             # (n,) s from the log's first row
    x: np.ndarray             # (n, 12) state, NED / FRD / ZYX Euler; masked samples filled
    rotor_speed: np.ndarray   # (n, 4) rad/s, project rotor order, shifted by the delay; masked filled
    u: np.ndarray             # (n, 4) wrench from the rotor speeds, N and N m
    x_ok: np.ndarray          # (n,) bool, state measured (not filled)
    rotor_ok: np.ndarray      # (n,) bool, rotor speeds measured (not filled)
    reference: np.ndarray | None   # (n, 3) position reference, NED, m (if the format names one)
    report: ImportReport = field(repr=False)
    # (n, 4) the wrench command in effect from each sample to the next, N and N m (a flight of this project's
    # plants, :func:`flown_flight`; a log has none): the dataset's input, with ``u`` its realized wrench
    command: np.ndarray | None = None


# ------------------------------------------------------------------ reading
def read_table(path, columns) -> dict[str, np.ndarray]:
    """The named columns of a CSV or Parquet file as float64 arrays (empty cells and nulls NaN, booleans 0/1).

    Raises
    ------
    FlightLogError
        If the file is missing or unreadable, or lacks a column (the message names the file and the column).
    """
    path = Path(path)
    where = f"log {str(path)!r}"
    if not path.is_file():
        raise FlightLogError(f"{where} does not exist")
    columns = list(dict.fromkeys(columns))
    suffix = path.suffix.lower()
    if suffix == ".parquet":
        return _read_parquet(path, columns, where)
    if suffix not in (".csv", ".txt"):
        raise FlightLogError(f"{where} is neither .csv nor .parquet")
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise FlightLogError(f"{where} is empty")
            index = {name.strip(): i for i, name in enumerate(header)}
            _require(columns, index, where)
            idx = [index[c] for c in columns]
            rows = [[r[i] if i < len(r) else "" for i in idx] for r in reader if r]
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise FlightLogError(f"{where} could not be read: {e}") from None
    out = {}
    for j, c in enumerate(columns):
        col = np.empty(len(rows))
        for i, r in enumerate(rows):
            col[i] = _cell(r[j], where, c, i)
        out[c] = col
    return out


def _cell(text: str, where: str, column: str, row: int) -> float:
    s = text.strip()
    if s == "" or s.lower() in ("nan", "null", "none", "na"):
        return math.nan
    low = s.lower()
    if low == "true":
        return 1.0
    if low == "false":
        return 0.0
    try:
        return float(s)
    except ValueError:
        raise FlightLogError(f"{where}: column {column!r} holds {s!r} at row {row + 1}, not a number") from None


def _read_parquet(path: Path, columns: list[str], where: str) -> dict[str, np.ndarray]:
    try:
        import pyarrow as pa
        import pyarrow.compute as pc
        import pyarrow.parquet as pq
    except ImportError:
        raise FlightLogError(f"{where}: reading Parquet needs pyarrow: python -m pip install -e \".[logs]\"") \
            from None
    try:
        names = pq.read_schema(path).names
        _require(columns, {n: i for i, n in enumerate(names)}, where)
        table = pq.read_table(path, columns=columns)
        return {c: pc.cast(table.column(c), pa.float64()).to_numpy(zero_copy_only=False).astype(float)
                for c in columns}
    except FlightLogError:
        raise
    except (OSError, ValueError, pa.ArrowException) as e:
        raise FlightLogError(f"{where} could not be read as Parquet: {' '.join(str(e).split())}") from None


def _require(columns, index, where):
    for c in columns:
        if c not in index:
            shown = ", ".join(list(index)[:12]) + (", ..." if len(index) > 12 else "")
            raise FlightLogError(f"{where}: column {c!r} is missing (the log has {len(index)} columns: {shown})")


# ------------------------------------------------------------------ maths
def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of unit quaternions (n, 4) in w, x, y, z order (body to world)."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def euler_matrix(e: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of ZYX Euler angles (n, 3) = (roll, pitch, yaw), body to world."""
    return rotation_matrix(e[:, 0], e[:, 1], e[:, 2])


def matrix_euler(R: np.ndarray) -> np.ndarray:
    """ZYX Euler angles (n, 3) of rotation matrices (n, 3, 3); yaw in (-pi, pi]."""
    phi = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    theta = -np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0))
    psi = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    return np.stack([phi, theta, psi], -1)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3): the angle from ``atan2``, accurate near 0."""
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = 0.5 * np.linalg.norm(v, axis=-1)                                   # sin(angle)
    ang = np.arctan2(s, (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0)
    scale = np.where(s > 1e-12, ang / (2.0 * np.where(s > 1e-12, s, 1.0)), 0.5)
    return v * scale[..., None]


def _held(a: np.ndarray, clean: np.ndarray | None = None) -> np.ndarray:
    """Rows (n,) of ``a`` (n, w) that repeat the last clean value of every column: telemetry not refreshed.

    ``clean`` (n, w) marks the cells that can be repeated (finite, not a spike; default: finite). Each column is
    compared with its value in the last row before where it was clean, so a NaN or a spike in the row before does
    not hide a held row. A column with no clean value before a row makes that row fresh (so is the first row).
    """
    n, w = a.shape
    clean = np.isfinite(a) if clean is None else clean
    rows = np.arange(n)[:, None]
    last = np.maximum.accumulate(np.where(clean, rows, -1), axis=0)      # last clean row up to and including r
    before = np.vstack([np.full((1, w), -1), last[:-1]])                # ... strictly before r
    prev = np.take_along_axis(a, np.maximum(before, 0), axis=0)
    return np.all((before >= 0) & (a == prev), axis=1)


def _position_glitches(pos: np.ndarray, period: float, limit: float) -> np.ndarray:
    """Rows (n,) of positions ``pos`` (n, 3), m, farther than ``limit`` (m) from the running median (per coordinate,
    over :data:`GLITCH_HALF_WINDOW_S` each side, at least 2 rows, over the finite rows) of the rows around them.

    The median of a smooth path's neighbouring samples is the path itself (exactly, where a coordinate is
    monotonic), so only a row off the path stands out: a logger's row of zeros, a wild value. A run of up to
    ``half`` such rows in a row is found.
    """
    from scipy.ndimage import median_filter

    out = np.zeros(len(pos), dtype=bool)
    finite = np.all(np.isfinite(pos), axis=1)
    if finite.sum() < 3:
        return out
    half = max(2, int(round(GLITCH_HALF_WINDOW_S / period)))
    p = pos[finite]
    med = median_filter(p, size=(2 * half + 1, 1), mode="nearest")
    with np.errstate(over="ignore", invalid="ignore"):
        out[finite] = ~(np.linalg.norm(p - med, axis=1) <= limit)
    return out


def _fill(t: np.ndarray, a: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``a`` (n, w) with the rows where ``ok`` is False replaced by linear interpolation in ``t`` (nearest at ends)."""
    out = a.copy()
    if ok.all():
        return out
    if not ok.any():
        raise ValueError("no valid row to fill from")
    for j in range(a.shape[1]):
        out[~ok, j] = np.interp(t[~ok], t[ok], a[ok, j])
    return out


def _slope(measured: np.ndarray, derived: np.ndarray) -> list[float]:
    """Least-squares slope per column of ``measured`` on ``derived`` (through the origin)."""
    den = np.sum(derived ** 2, axis=0)
    return [float(s) for s in np.where(den > 0, np.sum(measured * derived, axis=0) / np.where(den > 0, den, 1), 0)]


# ------------------------------------------------------------------ one flight
def read_flight(path, fmt: LogFormat, vehicle: Vehicle, name: str | None = None) -> Flight:
    """Import one flight log (see the module docstring for the steps).

    Parameters
    ----------
    path : str or Path
        A ``.csv`` or ``.parquet`` log, one row per sample.
    fmt : LogFormat
        Which column holds what (:func:`sim.flightlogs.logformat.load_format`).
    vehicle : Vehicle
        Rotor coefficients (``kt``, ``kq``, ``d``; ``kt`` per (rad/s)^2), mass and ``n_max`` (rad/s).
    name : str, optional
        The flight's name (default: the file's stem).

    Raises
    ------
    FlightLogError
        For a missing or all-empty column, time that goes backwards or holds a NaN, or a log with no airborne
        part; the message names the file and the column.
    """
    path = Path(path)
    where = f"log {str(path)!r}"
    name = name or path.stem
    cols = fmt.columns()
    table = read_table(path, [c for group in cols.values() for c in group])
    rows = len(table[fmt.time_column])
    if rows == 0:
        raise FlightLogError(f"{where} has a header but no data rows")
    for group, names in cols.items():
        for c in names:
            if not np.any(np.isfinite(table[c])):
                raise FlightLogError(f"{where}: column {c!r} ({group}) holds no number (every row empty or NaN)")
    if rows < 2:
        raise FlightLogError(f"{where}: {rows} row(s); a flight needs many")
    t = table[fmt.time_column] * fmt.time_scale
    if not np.all(np.isfinite(t)):
        i = int(np.argmax(~np.isfinite(t)))
        raise FlightLogError(f"{where}: column {fmt.time_column!r} (time) is empty or NaN at row {i + 1}")
    dt = np.diff(t)
    if np.any(dt < 0):
        i = int(np.argmax(dt < 0)) + 1
        raise FlightLogError(f"{where}: column {fmt.time_column!r} (time) goes backwards at row {i + 1} "
                             f"({t[i]:.6g} s after {t[i - 1]:.6g} s)")
    keep = np.concatenate([[True], dt > 0])
    duplicates = int(np.sum(~keep))
    t = t[keep] - t[keep][0]
    if len(t) < 2:
        raise FlightLogError(f"{where}: column {fmt.time_column!r} (time) holds one time in every row")
    period = float(np.median(np.diff(t)))
    lo_s, hi_s = ROW_INTERVAL_S
    if not lo_s <= period <= hi_s:
        raise FlightLogError(f"{where}: column {fmt.time_column!r} (time, unit {fmt.time_unit!r}) gives rows "
                             f"{period:.3g} s apart (median) and a log {t[-1]:.3g} s long; a flight log's rows are "
                             f"{1e3 * lo_s:g} ms to {hi_s:g} s apart: is [time] unit right?")
    groups = {g: np.stack([table[c][keep] for c in cols[g]], -1) for g in GROUPS}
    rot = groups["rotors"] * fmt.rotor_scale
    n_max = vehicle.n_max_value
    clean = {g: np.isfinite(a) for g, a in groups.items()}
    with np.errstate(invalid="ignore"):
        spike_cell = (rot < 0) | (rot > fmt.max_rotor_over_n_max * n_max)
    clean["rotors"] &= ~spike_cell
    glitch = _position_glitches(groups["position"] * fmt.position_scale, period, fmt.max_position_jump_m)
    clean["position"] &= ~glitch[:, None]
    spike = np.any(spike_cell, axis=1)
    turning = np.any(np.nan_to_num(rot) > 0, axis=1)
    if spike.sum() > MAX_SPIKE_SHARE * max(int(turning.sum()), 1):
        raise FlightLogError(
            f"{where}: rotor speeds in columns {', '.join(repr(c) for c in cols['rotors'])} exceed "
            f"{fmt.max_rotor_over_n_max:g} x n_max ({fmt.max_rotor_over_n_max * n_max:.4g} rad/s) in "
            f"{100 * spike.sum() / max(int(turning.sum()), 1):.0f} % of the rows where the rotors turn (median "
            f"{np.nanmedian(rot[turning]) if turning.any() else 0.0:.4g} rad/s): is [rotors] unit "
            f"{fmt.rotor_unit!r} right, and the vehicle's n_max?")
    nan_rows = {g: int(np.sum(~np.all(np.isfinite(a), axis=1))) for g, a in groups.items()}
    held = {g: _held(a, clean[g]) for g, a in groups.items()}
    ok = {g: np.all(clean[g], axis=1) & ~held[g] for g in GROUPS}
    invalid_attitude = np.zeros(len(t), dtype=bool)
    if fmt.quaternion is not None:
        with np.errstate(invalid="ignore", over="ignore"):
            qn = np.linalg.norm(groups["attitude"], axis=1)
        invalid_attitude = (np.all(np.isfinite(groups["attitude"]), axis=1)
                            & ~(np.isfinite(qn) & (qn >= MIN_QUATERNION_NORM)))
        ok["attitude"] &= ~invalid_attitude
    flag = None
    if fmt.airborne_column is not None:
        flag = table[fmt.airborne_column][keep]
    ref = None
    if fmt.reference is not None:
        ref = np.stack([table[c][keep] for c in fmt.reference], -1)

    # --- onto the 10 ms grid
    n_grid = int(math.floor(t[-1] / DT + ON_GRID_TOL)) + 1
    tg = np.arange(n_grid) * DT
    in_gap = np.zeros(n_grid, dtype=bool)
    if len(t) == n_grid and np.max(np.abs(t - tg)) <= ON_GRID_TOL * DT:
        resampling = "on the 10 ms grid already"
        grid, grid_ok = groups, ok
    else:
        jitter = float(np.std(np.diff(t)))
        resampling = (f"resampled from a {1e3 * period:.3g} ms median period (jitter {1e3 * jitter:.2g} ms rms) "
                      f"onto 10 ms by linear interpolation")
        j = np.clip(np.searchsorted(t, tg, side="right") - 1, 0, len(t) - 2)
        w = (tg - t[j]) / (t[j + 1] - t[j])
        exact0, exact1 = w <= ON_GRID_TOL, w >= 1.0 - ON_GRID_TOL
        # a sample between two rows farther apart than the limit on either side is invented: flagged, still filled
        limit = GAP_PERIODS * period
        in_gap = ~exact0 & ~exact1 & ((tg - t[j] > limit) | (t[j + 1] - tg > limit))
        grid, grid_ok = {}, {}
        for g, a in groups.items():
            a0, a1 = a[j], a[j + 1]
            if g == "attitude" and fmt.quaternion is not None:
                a1 = np.where(np.sum(a0 * a1, axis=1, keepdims=True) < 0, -a1, a1)
            grid[g] = np.where(exact0[:, None], a0, np.where(exact1[:, None], a1,
                                                            a0 + w[:, None] * (a1 - a0)))
            grid_ok[g] = np.where(exact0, ok[g][j], np.where(exact1, ok[g][j + 1], ok[g][j] & ok[g][j + 1]))
            grid_ok[g] &= ~in_gap
        if flag is not None:
            flag = np.where(w < 0.5, flag[j], flag[j + 1])
        if ref is not None:
            ref = ref[j] + w[:, None] * (ref[j + 1] - ref[j])
        rot = grid["rotors"] * fmt.rotor_scale
    x_ok = grid_ok["position"] & grid_ok["attitude"] & grid_ok["velocity"] & grid_ok["rates"]
    rot_ok = grid_ok["rotors"]
    if not x_ok.any() or not rot_ok.any():
        raise FlightLogError(f"{where}: no row has every state column measured and fresh" if not x_ok.any() else
                             f"{where}: no row has every rotor column measured and fresh")

    # --- frames, once
    Cw, Cb = fmt.world_matrix, fmt.body_matrix
    att = np.where(x_ok[:, None], grid["attitude"], 0.0)
    if fmt.quaternion is not None:
        att[~x_ok, 0] = 1.0                                  # identity where unmeasured (filled below)
        R_log = quaternion_matrix(att / np.linalg.norm(att, axis=1, keepdims=True))
    else:
        R_log = euler_matrix(att * fmt.angle_scale)
    R = Cw @ R_log @ Cb.T
    eul = matrix_euler(R)
    pos = grid["position"] * fmt.position_scale @ Cw.T
    vel = grid["velocity"] * fmt.velocity_scale
    vel = vel @ Cw.T if fmt.velocity_frame == "world" else np.einsum("nij,nj->ni", R, vel @ Cb.T)
    rates = grid["rates"] * fmt.rate_scale @ Cb.T
    x = np.concatenate([pos, eul, rates, vel], axis=1)
    # nothing that is not finite is ever flagged measured (an overflow in a scale, a rotation of huge numbers)
    x_finite, rot_finite = np.all(np.isfinite(x), axis=1), np.all(np.isfinite(rot), axis=1)
    nonfinite = (x_ok & ~x_finite) | (rot_ok & ~rot_finite)
    x_ok &= x_finite
    rot_ok &= rot_finite
    if not x_ok.any() or not rot_ok.any():
        raise FlightLogError(f"{where}: no sample is finite once converted to this project's units and frames")
    # continuous angles: unwrap over the measured samples, then fill between them
    for k in range(3):
        x[x_ok, 3 + k] = np.unwrap(x[x_ok, 3 + k])
    x = _fill(tg, np.where(x_ok[:, None], x, 0.0), x_ok)
    rot = _fill(tg, np.where(rot_ok[:, None], rot, 0.0), rot_ok)
    if ref is not None:
        ref = ref * fmt.position_scale @ Cw.T

    # --- airborne part
    weight = vehicle.m * GRAVITY
    ratio = vehicle.kt * np.sum(rot ** 2, axis=1) / weight
    air = ratio >= fmt.min_thrust_to_weight
    if flag is not None:
        air &= np.nan_to_num(flag) > 0.5
    start, stop = _longest_run(_bridge(air, int(round(BRIDGE_S / DT))))
    margin = int(round(fmt.margin_s / DT))
    start, stop = start + margin, stop - margin
    if stop - start < MIN_SAMPLES:
        raise FlightLogError(f"{where}: no airborne part of at least {MIN_SAMPLES * DT:g} s (rotor thrust "
                             f">= {fmt.min_thrust_to_weight:g} x weight"
                             + (f" and column {fmt.airborne_column!r} set" if flag is not None else "")
                             + f", less {fmt.margin_s:g} s at each end)")

    # --- motor-to-state delay
    d, rss_ratio, coef = estimate_delay(x, x_ok, rot, start, stop, fmt.delay_search)
    shifted = np.full_like(rot, np.nan)
    shifted_ok = np.zeros_like(rot_ok)
    lo, hi = max(0, d), min(len(rot), len(rot) + d)
    shifted[lo:hi] = rot[lo - d:hi - d]
    shifted_ok[lo:hi] = rot_ok[lo - d:hi - d]
    sl = slice(start, stop)
    x, x_ok, tg = x[sl], x_ok[sl], tg[sl]
    rot, rot_ok = shifted[sl], shifted_ok[sl]
    if not rot_ok.any():
        raise FlightLogError(f"{where}: no airborne row has every rotor column measured and fresh")
    rot = _fill(tg, np.where(rot_ok[:, None], rot, 0.0), rot_ok)
    M = mixer_matrix(vehicle.params)
    M[3] *= fmt.yaw_sign
    u = rot ** 2 @ M.T
    if ref is not None:
        ref = ref[sl]

    report = ImportReport(
        name=name, source=str(path), rows=rows, duplicate_times=duplicates, nan_rows=nan_rows,
        held_rows={g: int(h.sum()) for g, h in held.items()}, spikes=int(spike.sum()),
        position_glitches=int(glitch.sum()), invalid_attitude_rows=int(invalid_attitude.sum()), resampling=resampling,
        log_period_s=period, airborne_s=(float(tg[0]), float(tg[-1])), samples=int(len(tg)),
        valid_state_fraction=float(x_ok.mean()), valid_rotor_fraction=float(rot_ok.mean()),
        gap_samples=int(in_gap[sl].sum()), nonfinite_samples=int(nonfinite[sl].sum()),
        delay_samples=int(d), delay_rss_ratio=float(rss_ratio),
        velocity_check=_velocity_check(x, x_ok), rates_check=_rates_check(x, x_ok),
        thrust_check={"slope": float(coef[0] * vehicle.m / vehicle.kt), "intercept_m_s2": float(coef[1])},
        torque_check=_torque_check(x, x_ok, u, rot_ok, vehicle))
    return Flight(name=name, t=tg, x=x, rotor_speed=rot, u=u, x_ok=x_ok, rotor_ok=rot_ok, reference=ref,
                  report=report)


def _bridge(mask: np.ndarray, gap: int) -> np.ndarray:
    """``mask`` with each run of False shorter than ``gap`` samples between two runs of True set True."""
    out = mask.copy()
    edges = np.diff(np.concatenate([[1], mask.astype(np.int8), [1]]))
    for a, b in zip(np.flatnonzero(edges == -1), np.flatnonzero(edges == 1)):
        if 0 < a and b < len(mask) and b - a < gap:
            out[a:b] = True
    return out


def _longest_run(mask: np.ndarray) -> tuple[int, int]:
    """(start, stop) of the longest run of True in ``mask`` ((0, 0) if none)."""
    if not mask.any():
        return 0, 0
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    i = int(np.argmax(stops - starts))
    return int(starts[i]), int(stops[i])


def estimate_delay(x, x_ok, rot, start, stop, search) -> tuple[int, float, np.ndarray]:
    """Motor-to-state delay (samples) that best explains the measured thrust by the rotor speeds.

    The measured thrust per unit mass is ``-z_b . (dv/dt - g e3)`` with
    ``dv/dt`` the forward difference of the velocity over one period and
    ``z_b`` the body z axis; for each delay ``d`` in ``search`` it is fitted
    (least squares, with an intercept) by ``sum n^2`` taken ``d`` samples
    earlier. Both sides are smoothed alike (a centred mean over
    :data:`DELAY_SMOOTH` samples, which keeps the delay and averages out the
    noise a difference of velocities has) on the filled series of
    ``[start, stop)`` (the rotor speeds filled where masked: requiring every
    shift measured would drop most samples of a real log), and the residual
    is summed over the samples whose state and next state were measured. Returns the delay with the least
    residual, the ratio of that residual to the next best one (near 1: the
    data hardly tell the delays apart), and the fit at that delay (slope in
    m/s^2 per rad^2/s^2, intercept in m/s^2).
    """
    lo_d, hi_d = search
    n = len(x)
    k = np.arange(max(start, hi_d, 0), min(stop, n - 1, n + lo_d))
    nothing = 0, math.nan, np.array([math.nan, math.nan])
    if len(k) < 10 * DELAY_SMOOTH:
        return nothing
    ker = np.ones(DELAY_SMOOTH) / DELAY_SMOOTH
    half = DELAY_SMOOTH // 2
    use = (x_ok[k] & x_ok[k + 1])[half:len(k) - half]
    if use.sum() < 10:
        return nothing
    R = euler_matrix(x[k, 3:6])
    acc = (x[k + 1, 9:12] - x[k, 9:12]) / DT - np.array([0.0, 0.0, GRAVITY])
    y = np.convolve(-np.einsum("ni,ni->n", R[:, :, 2], acc), ker, "valid")[use]
    rss, fits = [], []
    for d in range(lo_d, hi_d + 1):
        s = np.convolve(np.sum(rot[k - d] ** 2, axis=1), ker, "valid")[use]
        A = np.stack([s, np.ones_like(s)], -1)
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        rss.append(float(np.sum((y - A @ coef) ** 2)))
        fits.append(coef)
    order = np.argsort(rss)
    best = int(order[0])
    ratio = rss[best] / rss[int(order[1])] if len(rss) > 1 and rss[int(order[1])] > 0 else 0.0
    return lo_d + best, ratio, fits[best]


def _velocity_check(x, ok) -> dict:
    k = np.flatnonzero(ok[1:-1] & ok[:-2] & ok[2:]) + 1
    if len(k) < 3:
        return {"slope": [math.nan] * 3, "rms_m_s": math.nan}
    dp = (x[k + 1, 0:3] - x[k - 1, 0:3]) / (2 * DT)
    v = x[k, 9:12]
    return {"slope": _slope(v, dp), "rms_m_s": float(np.sqrt(np.mean((v - dp) ** 2)))}


def _rates_check(x, ok) -> dict:
    k = np.flatnonzero(ok[:-1] & ok[1:])
    if len(k) < 3:
        return {"slope": [math.nan] * 3, "rms_rad_s": math.nan}
    R0, R1 = euler_matrix(x[k, 3:6]), euler_matrix(x[k + 1, 3:6])
    derived = rotation_vector(np.swapaxes(R0, 1, 2) @ R1) / DT
    measured = 0.5 * (x[k, 6:9] + x[k + 1, 6:9])
    return {"slope": _slope(measured, derived), "rms_rad_s": float(np.sqrt(np.mean((measured - derived) ** 2)))}


def _torque_check(x, x_ok, u, u_ok, vehicle: Vehicle) -> dict:
    """Angular acceleration the body rates show against the one the torques give, per body axis.

    Over each period ``[k, k + 1]`` with the state measured at both ends and the wrench ``u[k]`` (n, 4) measured
    (``u_ok[k]``), the measured ``(w[k+1] - w[k]) / dt`` is fitted (least squares, with an intercept) by
    ``J^-1 (tau[k] - w x J w)`` (``w`` the period's mean rate, ``J`` the vehicle's inertia). Returns the slope
    per axis (1 for consistent rotor positions, spins and inertia; negative for a swapped pair of rotors or
    reversed spins) and the share of the variance it explains (a real vehicle's noisy rotor speeds explain
    little).
    """
    k = np.flatnonzero(x_ok[:-1] & x_ok[1:] & u_ok[:-1])
    if len(k) < 10:
        return {"slope": [math.nan] * 3, "explained": [math.nan] * 3}
    J = np.array([vehicle.Jxx, vehicle.Jyy, vehicle.Jzz])
    w = 0.5 * (x[k, 6:9] + x[k + 1, 6:9])
    measured = (x[k + 1, 6:9] - x[k, 6:9]) / DT
    given = (u[k, 1:4] - np.cross(w, J * w)) / J
    slope, explained = [], []
    for a in range(3):
        dg, dm = given[:, a] - given[:, a].mean(), measured[:, a] - measured[:, a].mean()
        sgg, smm = float(dg @ dg), float(dm @ dm)
        slope.append(float(dg @ dm) / sgg if sgg > 0 else math.nan)
        explained.append(float(dg @ dm) ** 2 / (sgg * smm) if sgg > 0 and smm > 0 else math.nan)
    return {"slope": slope, "explained": explained}


def finite_samples(x, rotor_speed) -> int:
    """Samples before the first with a non-finite state (n, 12) or rotor speed (n, 4): all n if there is none."""
    finite = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(rotor_speed), axis=1)
    return len(finite) if finite.all() else int(np.argmin(finite))


def flown_flight(name: str, t, x, rotor_speed, vehicle: Vehicle, command=None, reference=None,
                 source: str = "a flight of this project's plants") -> Flight:
    """A flight flown here (a closed-loop run's trace) as a :class:`Flight`, as the import would give it.

    The samples are already on the 10 ms grid, in this project's conventions, with nothing held, missing or
    delayed, so the import's cleaning, resampling and delay search have nothing to do; its checks (velocity,
    rates, thrust) are made and reported as for a log. A flight that crashed is cut before its first
    non-finite state.

    Parameters
    ----------
    name : str
        The flight's name (its split is chosen by name, as for logs).
    t : array_like, shape (n,)
        Times, s, every 10 ms.
    x : array_like, shape (n, 12)
        States (NED, FRD, ZYX Euler angles).
    rotor_speed : array_like, shape (n, 4)
        Rotor speeds at each sample, in the vehicle's rotor unit.
    vehicle : Vehicle
        Gives the wrench from the rotor speeds (``u``) and the thrust check.
    command : array_like, shape (n - 1, 4) or (n, 4), optional
        The wrench command in effect over each period, N and N m (the dataset's input).
    reference : array_like, shape (n, 3) or (n, 12), optional
        The reference; its positions are kept.
    source : str
        Said in the report.

    Returns
    -------
    Flight
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    rot = np.asarray(rotor_speed, dtype=float)
    n = len(t)
    if x.shape != (n, 12) or rot.shape != (n, 4):
        raise FlightLogError(f"{name}: x must have shape ({n}, 12) and rotor_speed ({n}, 4) for {n} times; found "
                             f"{x.shape} and {rot.shape}")
    if n > 1 and not np.allclose(np.diff(t), DT, rtol=0.0, atol=1e-9):
        raise FlightLogError(f"{name}: the samples must be {DT:g} s apart")
    keep = finite_samples(x, rot)
    if keep < MIN_SAMPLES:
        raise FlightLogError(f"{name}: fewer than {MIN_SAMPLES} finite samples ({keep})")
    t, x, rot = t[:keep], x[:keep], rot[:keep]
    if command is not None:
        command = np.asarray(command, dtype=float)
        if command.shape not in ((n - 1, 4), (n, 4)):
            raise FlightLogError(f"{name}: command must have shape ({n - 1}, 4) or ({n}, 4); found {command.shape}")
        command = np.vstack([command, command[-1:]])[:keep] if len(command) == n - 1 else command[:keep]
    if reference is not None:
        reference = np.asarray(reference, dtype=float)[:keep, 0:3]
    ok = np.ones(keep, dtype=bool)
    u = rot ** 2 @ mixer_matrix(vehicle.params).T
    _, _, coef = estimate_delay(x, ok, rot, 0, keep, (0, 0))
    report = ImportReport(
        name=name, source=source, rows=n, duplicate_times=0, nan_rows={}, held_rows={}, spikes=0,
        position_glitches=0, invalid_attitude_rows=0, resampling="none: on the 10 ms grid", log_period_s=DT,
        airborne_s=(float(t[0]), float(t[-1])), samples=int(keep), valid_state_fraction=1.0,
        valid_rotor_fraction=1.0, gap_samples=0, nonfinite_samples=0, delay_samples=0,
        delay_rss_ratio=0.0, velocity_check=_velocity_check(x, ok), rates_check=_rates_check(x, ok),
        thrust_check={"slope": float(coef[0] * vehicle.m / vehicle.kt), "intercept_m_s2": float(coef[1])},
        # its rotors answer each period's command within the period: period k's torque is that of sample k + 1
        torque_check=_torque_check(x, ok, np.vstack([u[1:], u[-1:]]), np.r_[ok[1:], False], vehicle))
    return Flight(name=name, t=t, x=x, rotor_speed=rot, u=u, x_ok=ok, rotor_ok=ok.copy(), reference=reference,
                  report=report, command=command)


# ------------------------------------------------------------------ many flights
def assign_splits(names: list[str], splits: dict[str, list[str]]) -> dict[str, str]:
    """Each flight's split: the split whose pattern (``fnmatch``) matches its name, ``train`` if none does.

    Raises
    ------
    FlightLogError
        For an unknown split name, or a flight that two splits claim.
    """
    from ..identification.excitation import SPLIT_NAMES

    out = {}
    for split, patterns in splits.items():
        if split not in SPLIT_NAMES:
            raise FlightLogError(f"split {split!r} is not known; choose from {', '.join(SPLIT_NAMES)}")
        for n in names:
            if any(fnmatch.fnmatchcase(n, p) for p in patterns):
                if n in out and out[n] != split:
                    raise FlightLogError(f"flight {n!r} matches both split {out[n]!r} and split {split!r}")
                out[n] = split
    return {n: out.get(n, "train") for n in names}


def flights_to_dataset(flights: list[Flight], vehicle: Vehicle, splits: dict[str, str],
                       fmt: LogFormat | None = None):
    """Stack flights into a :class:`~sim.identification.excitation.Dataset` (padded to the longest; padding invalid).

    ``valid[i, k]`` holds (state at k measured, rotor speeds at k measured, state at k + 1 measured); a sample is
    a usable one-step pair when all three are True. The input ``u`` is each flight's command where it has one
    (:func:`flown_flight`), else its wrench from the rotor speeds; ``wrench`` is always the latter. The rotor speeds
    of sample k are a log's at sample k, and a flown flight's at the end of period k (sample k + 1), as the
    simulator's datasets log them. ``fmt``: the logs' format (None for flights flown here).
    """
    from .. import __version__
    from ..identification.excitation import FORMAT_VERSION, SPLIT_NAMES, Dataset

    n_steps = max(len(f.t) for f in flights) - 1
    n = len(flights)
    x = np.zeros((n, n_steps, 12))
    x_next = np.zeros((n, n_steps, 12))
    u = np.zeros((n, n_steps, 4))
    wrench = np.zeros((n, n_steps, 4))
    rs = np.zeros((n, n_steps, 4))
    valid = np.zeros((n, n_steps, 3), dtype=bool)
    for i, f in enumerate(flights):
        m = len(f.t) - 1
        cmd = f.u if f.command is None else f.command
        # A log's rotor speeds at sample k go with sample k. A flight flown here commands each period and its rotors
        # answer within it: its sample k gets the speeds at the period's end, as the simulator's datasets log them
        # (the telemetry a motor-lag model is trained against).
        rot = f.rotor_speed[:-1] if f.command is None else f.rotor_speed[1:]
        x[i, :m], x_next[i, :m], rs[i, :m] = f.x[:-1], f.x[1:], rot
        u[i, :m], wrench[i, :m] = cmd[:-1], f.u[:-1]
        x[i, m:], x_next[i, m:], rs[i, m:] = f.x[-1], f.x[-1], f.rotor_speed[-1]
        u[i, m:], wrench[i, m:] = cmd[-1], f.u[-1]
        valid[i, :m] = np.stack([f.x_ok[:-1], f.rotor_ok[:-1], f.x_ok[1:]], -1)
    meta = {
        "format_version": FORMAT_VERSION, "regime": "flight logs", "source": "flight logs",
        "log_format": None if fmt is None else fmt.name, "vehicle": vehicle.to_dict(), "dt": DT,
        "version": __version__,
        "flights": [asdict(f.report) for f in flights],
        "flight_names": [f.name for f in flights],
        "flight_samples": [int(len(f.t)) for f in flights],
        "delay_samples": [f.report.delay_samples for f in flights],
        "envelope_deg": [0.0, 90.0],
        "valid_columns": ["state", "rotors", "next state"],
    }
    return Dataset(x=x, u=u, rotor_speed=rs, x_next=x_next, wrench=wrench,
                   saturated=rs >= vehicle.n_max_value,
                   split=np.array([SPLIT_NAMES.index(splits[f.name]) for f in flights], dtype=np.int8),
                   meta=meta, valid=valid)
