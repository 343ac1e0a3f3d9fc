"""Closed-loop scenarios written as TOML files (the format: ``docs/scenario-files.md``).

A scenario file gives exactly one reference, a hover point, waypoints flown
on a minimum-snap path in a given time, or a table of flat outputs, plus
the options of the built-in scenarios (start offsets, payload, wind, a gust
impulse, the high-fidelity plant, measurement noise, input delay, seed)::

    # five-waypoints.toml
    waypoints = [[0, 0, -1], [1, 0, -1.5], [1, 1, -1], [0, 1, -1.5], [0, 0, -1]]
    duration = 8.0                      # s: the path (the flight, duration_s, adds 1 s of hover)

    from scenarios import get_scenario
    s = get_scenario("five-waypoints.toml")          # or load_scenario_file(path)

Every problem of a file raises a one-line :class:`~scenarios.errors.ScenarioError`
that names the file and the field. What the loader checks of the path
itself holds for any quadrotor: the segment times are positive, consecutive
waypoints differ, and the reference never tilts past the crash limit of the
metrics (80 deg; if it would, the error names the shortest duration that
keeps it within). Whether a given vehicle's rotors can fly the path is a
question about that vehicle: :func:`rotor_load` answers it.
"""

from __future__ import annotations

import functools
import math
import tomllib
from pathlib import Path

import numpy as np

from sim.params import DT, NoiseModel

from ..errors import ScenarioError
from .scenario import (DURATION_LIMIT_REASON, HOVER_DURATION_S, MAX_DURATION_S, NOISE, START_MAP, GustImpulse,
                       Scenario, WindGusts)
from .metrics import CRASH_TILT_RAD

#: The references a file may give; exactly one of them.
REFERENCES = ("hover", "waypoints", "flat")
#: Every top-level key of a scenario file.
KEYS = ("name", "description", *REFERENCES, "path_duration_s", "yaw_rad", "duration_s", "start_offset_m",
        "start_attitude_deg", "payload_fraction", "high_fidelity", "wind", "gust", "noise", "delay_steps", "seed")
#: Keys of the tables ``[flat]``, ``[wind]``, ``[gust]`` and ``[noise]``.
FLAT_KEYS = ("t", "x", "y", "z", "yaw")
WIND_KEYS = ("mean_mps2", "gust_peak_mps2", "gust_duration_s", "n_gusts")
GUST_KEYS = ("start_s", "duration_s", "peak_mps2", "direction")
NOISE_KEYS = ("position", "attitude", "body_rate", "velocity")
#: Hover held after a path or table ends when the file gives no ``duration_s``, s.
HOLD_S = 1.0
#: Shortest distance between consecutive waypoints, m (the minimum-snap path needs a length to share time by).
MIN_SEGMENT_M = 1e-3
#: Grid points per segment on which the reference's tilt is checked.
TILT_SAMPLES = 256
#: Unknown keys that are near misses of real ones.
_HINTS = {"yaw": "yaw_rad",
          "path_duration": "path_duration_s", "start_offset": "start_offset_m",
          "start_attitude": "start_attitude_deg", "payload": "payload_fraction", "delay": "delay_steps",
          "highfi": "high_fidelity", "table": "[flat]", "impulse": "[gust]", "kind": "one of hover, waypoints, [flat]"}


def _show(v, width: int = 60) -> str:
    """A value as it reads in the message, on one line and at most ``width`` characters."""
    if isinstance(v, bool):
        text = "true" if v else "false"
    elif isinstance(v, dict):
        text = "a table {" + ", ".join(str(k) for k in v) + "}"
    else:
        text = repr(v)
    text = " ".join(text.split())
    return text if len(text) <= width else text[:width - 3] + "..."


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


class _Reader:
    """Checks the values of one file; every error is one line prefixed with ``where``."""

    def __init__(self, where: str):
        self.where = where

    def fail(self, message: str):
        raise ScenarioError(" ".join(f"{self.where}: {message}".split()))

    def unknown(self, table: dict, keys, label: str = ""):
        bad = [k for k in table if k not in keys]
        if not bad:
            return
        what = "unknown key" + ("s " if len(bad) > 1 else " ") + ", ".join(repr(k) for k in bad)
        hints = [k for k in bad if not label and k in _HINTS]
        hint = "".join(f" (did you mean {_HINTS[k]}?)" if len(bad) == 1 else f" ({k!r}: did you mean {_HINTS[k]}?)"
                       for k in hints)
        self.fail(f"{what}{' in ' + label if label else ''}{hint}; the keys are {', '.join(keys)}")

    def number(self, v, field: str, low: float | None = None, strict: bool = False, unit: str = "") -> float:
        u = f" {unit}" if unit else ""
        if not _is_number(v) or (low is not None and (v <= low if strict else v < low)):
            bound = "" if low is None else f" {'>' if strict else '>='} {low:g}{u}"
            self.fail(f"{field} must be a finite number{bound}; found {_show(v)}")
        return float(v)

    def integer(self, v, field: str, low: int = 0) -> int:
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            self.fail(f"{field} must be an integer >= {low}; found {_show(v)}")
        return int(v)

    def boolean(self, v, field: str) -> bool:
        if not isinstance(v, bool):
            self.fail(f"{field} must be true or false; found {_show(v)}")
        return v

    def text(self, v, field: str, empty: bool = True) -> str:
        if not isinstance(v, str) or (not empty and not v.strip()):
            self.fail(f"{field} must be a{'' if empty else ' non-empty'} string; found {_show(v)}")
        return v

    def vector3(self, v, field: str, what: str = "") -> tuple[float, float, float]:
        if not (isinstance(v, list) and len(v) == 3 and all(_is_number(e) for e in v)):
            self.fail(f"{field} must hold 3 finite numbers{what}; found {_show(v)}")
        return tuple(float(e) for e in v)

    def numbers(self, v, field: str) -> list[float]:
        if not isinstance(v, list):
            self.fail(f"{field} must be a list of finite numbers; found {_show(v)}")
        for i, e in enumerate(v):
            if not _is_number(e):
                self.fail(f"{field}[{i}] must be a finite number; found {_show(e)}")
        return [float(e) for e in v]

    def table(self, v, field: str, keys) -> dict:
        if not isinstance(v, dict):
            self.fail(f"{field} must be a table ([{field}]) with keys {', '.join(keys)}; found {_show(v)}")
        self.unknown(v, keys, f"[{field}]")
        return v


def _reference(r: _Reader, data: dict) -> tuple[str, dict]:
    """The kind and the Scenario fields of the file's one reference."""
    given = [k for k in REFERENCES if k in data]
    if len(given) != 1:
        found = "none" if not given else " and ".join(given)
        r.fail(f"give exactly one reference: hover = [x, y, z], waypoints = [[x, y, z], ...] or a [flat] table; "
               f"found {found}")
    kind = given[0]
    if "path_duration_s" in data and kind != "waypoints":
        r.fail("path_duration_s belongs with waypoints; "
               + ("a [flat] table takes its times from flat.t" if kind == "flat" else "a hover point has no path"))
    if "yaw_rad" in data and kind == "flat":
        r.fail("yaw_rad belongs with hover or waypoints; a [flat] table gives its yaw as flat.yaw")
    yaw = r.number(data["yaw_rad"], "yaw_rad", unit="rad") if "yaw_rad" in data else 0.0

    if kind == "hover":
        pos = r.vector3(data["hover"], "hover", " [x, y, z] (m, NED)")
        if pos[2] > 0:
            r.fail(f"hover is below ground (z = {pos[2]:g} m > 0; NED: z = -1 is 1 m up)")
        return "hover", {"position_m": pos, "yaw_rad": yaw, "height_m": -pos[2]}

    if kind == "waypoints":
        wps = data["waypoints"]
        if not isinstance(wps, list) or len(wps) < 2:
            r.fail(f"waypoints must be a list of at least 2 points [x, y, z] (m, NED); found {_show(wps)}")
        pts = [r.vector3(w, f"waypoints[{i}]") for i, w in enumerate(wps)]
        for i, w in enumerate(pts):
            if w[2] > 0:
                r.fail(f"waypoints[{i}] is below ground (z = {w[2]:g} m > 0; NED: z = -1 is 1 m up)")
        for i in range(1, len(pts)):
            gap = math.dist(pts[i - 1], pts[i])
            if gap < MIN_SEGMENT_M:
                r.fail(f"waypoints[{i}] is {gap:.3g} m from waypoints[{i - 1}]; consecutive waypoints must be "
                       f"at least {MIN_SEGMENT_M * 1e3:g} mm apart")
        if "path_duration_s" not in data:
            r.fail("waypoints need path_duration_s, the time (s) to fly through them")
        T = r.number(data["path_duration_s"], "path_duration_s", 0.0, strict=True, unit="s")
        return "waypoints", {"points_m": tuple(pts), "path_duration_s": T, "yaw_rad": yaw}

    flat = r.table(data["flat"], "flat", FLAT_KEYS)
    for k in ("t", "x", "y", "z"):
        if k not in flat:
            r.fail(f"[flat] needs flat.{k} (the table has t in s, x, y, z in m, optional yaw in rad)")
    t = r.numbers(flat["t"], "flat.t")
    if len(t) < 2:
        r.fail(f"flat.t must hold at least 2 times; found {_show(flat['t'])}")
    cols = {}
    for k in ("x", "y", "z", "yaw"):
        if k in flat:
            cols[k] = r.numbers(flat[k], f"flat.{k}")
            if len(cols[k]) != len(t):
                r.fail(f"flat.{k} must hold one number per time of flat.t ({len(t)}); found {len(cols[k])}")
    if t[0] < 0:
        r.fail(f"flat.t[0] must be >= 0 s; found {t[0]:g}")
    for i in range(1, len(t)):
        if not t[i] > t[i - 1]:
            r.fail(f"flat.t must increase strictly; flat.t[{i}] = {t[i]:g} follows flat.t[{i - 1}] = {t[i - 1]:g}")
    pts = tuple(zip(cols["x"], cols["y"], cols["z"]))
    yaws = None if "yaw" not in cols else tuple(cols["yaw"])
    return "table", {"points_m": pts, "times_s": tuple(t), "table_yaw_rad": yaws}


def _options(r: _Reader, data: dict, duration_s: float) -> dict:
    """Plant, sensor and seed options as Scenario fields."""
    out = {}
    seed = r.integer(data["seed"], "seed") if "seed" in data else 0
    out["seed"] = seed
    if "payload_fraction" in data:
        out["payload_fraction"] = r.number(data["payload_fraction"], "payload_fraction", 0.0)
    if "high_fidelity" in data:
        out["high_fidelity"] = r.boolean(data["high_fidelity"], "high_fidelity")
    if "delay_steps" in data:
        out["delay_steps"] = r.integer(data["delay_steps"], "delay_steps")
    if "wind" in data:
        w = r.table(data["wind"], "wind", WIND_KEYS)
        d = WindGusts()
        out["wind"] = WindGusts(
            mean=r.vector3(w["mean_mps2"], "wind.mean_mps2", " (m/s^2, NED)") if "mean_mps2" in w else d.mean,
            gust_peak=r.number(w["gust_peak_mps2"], "wind.gust_peak_mps2", 0.0) if "gust_peak_mps2" in w
            else d.gust_peak,
            gust_duration_s=r.number(w["gust_duration_s"], "wind.gust_duration_s", 0.0, strict=True, unit="s")
            if "gust_duration_s" in w else d.gust_duration_s,
            n_gusts=r.integer(w["n_gusts"], "wind.n_gusts") if "n_gusts" in w else d.n_gusts,
            flight_duration_s=duration_s, seed=seed)
    if "gust" in data:
        g = r.table(data["gust"], "gust", GUST_KEYS)
        d = GustImpulse()
        direction = d.direction
        if "direction" in g:
            v = np.array(r.vector3(g["direction"], "gust.direction", " (NED)"))
            n = float(np.linalg.norm(v))
            if n == 0.0:
                r.fail("gust.direction must not be zero; found [0, 0, 0]")
            direction = tuple(float(e) for e in v / n)
        out["impulse"] = GustImpulse(
            start_s=r.number(g["start_s"], "gust.start_s", 0.0, unit="s") if "start_s" in g else d.start_s,
            duration_s=r.number(g["duration_s"], "gust.duration_s", 0.0, strict=True, unit="s")
            if "duration_s" in g else d.duration_s,
            peak_mps2=r.number(g["peak_mps2"], "gust.peak_mps2", 0.0) if "peak_mps2" in g else d.peak_mps2,
            direction=direction)
    if "noise" in data:
        v = data["noise"]
        if isinstance(v, bool):
            out["noise"] = NOISE if v else None
        elif isinstance(v, dict):
            r.unknown(v, NOISE_KEYS, "[noise]")
            out["noise"] = NoiseModel(**{k: r.number(v.get(k, 0.0), f"noise.{k}", 0.0) for k in NOISE_KEYS})
        else:
            r.fail(f"noise must be true, false or a table [noise] with keys {', '.join(NOISE_KEYS)}; "
                   f"found {_show(v)}")
    return out


def _tilt_demand(traj, stretch: float = 1.0):
    """Tilt (rad) the reference asks for on a grid, with its time stretched by ``stretch``; ``(tilt, times)``.

    Stretching time by ``k`` divides velocities by ``k`` and accelerations by
    ``k^2``; the tilt is the angle between the thrust vector
    ``g e3 - a - c_d v|v|`` and the vertical (the ``g``, ``c_d`` of
    :data:`scenarios.closed_loop.scenario.START_MAP`, through which every scenario is built).
    """
    path = traj.path
    s = np.linspace(0.0, 1.0, TILT_SAMPLES)
    t = (path.knot_times[:-1, None] + path.durations[:, None] * s[None, :]).ravel()
    t = np.minimum(t, path.duration_s)
    d = path.derivatives(t, order=2)
    p = START_MAP
    v, a = d[1] / stretch, d[2] / stretch ** 2
    thrust = -a - p.c_d * v * np.abs(v)
    thrust[:, 2] += p.g
    norm = np.linalg.norm(thrust, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        tilt = np.arccos(np.clip(thrust[:, 2] / norm, -1.0, 1.0))
    tilt[~(norm > 0)] = np.pi
    return tilt, (t + traj.times[0]) * stretch


def _check_path(r: _Reader, kind: str, traj, path_duration: float | None):
    """The path stays above ground and within the crash tilt (else the error names the duration that fits)."""
    s = np.linspace(0.0, 1.0, TILT_SAMPLES)
    path = traj.path
    t = np.minimum((path.knot_times[:-1, None] + path.durations[:, None] * s[None, :]).ravel(), path.duration_s)
    z = path.derivatives(t, order=0)[0][:, 2]
    if np.max(z) > 0.0:
        i = int(np.argmax(z))
        r.fail(f"the path dips below ground (z = {z[i]:.3g} m at t = {t[i] + traj.times[0]:.2f} s; NED: z = -1 is "
               f"1 m up); move the {'waypoints' if kind == 'waypoints' else 'samples'} up")
    tilt, t = _tilt_demand(traj)
    if np.max(tilt) <= CRASH_TILT_RAD:
        return
    i = int(np.argmax(tilt))
    lo, hi = 1.0, 2.0
    while np.max(_tilt_demand(traj, hi)[0]) > CRASH_TILT_RAD:
        lo, hi = hi, 2 * hi
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.max(_tilt_demand(traj, mid)[0]) > CRASH_TILT_RAD else (lo, mid)
    limit = f"past the {np.degrees(CRASH_TILT_RAD):.0f} deg crash limit"
    ask = f"the reference would tilt the vehicle {np.degrees(tilt[i]):.0f} deg at t = {t[i]:.2f} s, {limit}"
    if kind == "waypoints":
        need = math.ceil(path_duration * hi * 100) / 100
        r.fail(f"path_duration_s = {path_duration:g} s is too short for these waypoints: {ask}; "
               f"path_duration_s >= {need:g} s keeps it within")
    r.fail(f"the [flat] samples are too fast: {ask}; stretching flat.t by a factor >= {math.ceil(hi * 100) / 100:g} "
           f"keeps it within")


def _describe(kind: str, fields: dict, duration_s: float, opts: dict, source: str) -> str:
    if kind == "hover":
        p = fields["position_m"]
        text = f"hover at [{p[0]:g}, {p[1]:g}, {p[2]:g}] m (NED) until {duration_s:g} s"
    elif kind == "waypoints":
        n, T = len(fields["points_m"]), fields["path_duration_s"]
        text = f"minimum-snap path through {n} waypoints in {T:g} s, then hover until {duration_s:g} s"
    else:
        n, t = len(fields["points_m"]), fields["times_s"]
        text = (f"minimum-snap path through {n} samples of flat outputs at {t[0]:g}..{t[-1]:g} s, then hover until "
                f"{duration_s:g} s")
    notes = []
    if opts.get("impulse") is not None:
        g = opts["impulse"]
        notes.append(f"a {g.peak_mps2:g} m/s^2, {g.duration_s:g} s gust impulse at {g.start_s:g} s")
    if opts.get("high_fidelity"):
        notes.append("high-fidelity simulator")
    if opts.get("payload_fraction"):
        notes.append(f"+{opts['payload_fraction']:.0%} payload (of the vehicle's mass)")
    if opts.get("wind") is not None:
        notes.append("wind and gusts")
    if opts.get("noise") is not None:
        notes.append("noise on the measured state")
    if opts.get("delay_steps"):
        notes.append(f"input applied {opts['delay_steps']} control periods late")
    return "; ".join([text, *notes] + ([f"from {source}"] if source else []))


def scenario_from_dict(data: dict, name: str = "scenario", where: str = "scenario",
                       source: str | None = None) -> Scenario:
    """The :class:`Scenario` of a parsed scenario file (a mapping of its keys).

    ``name`` is the scenario's name when ``data`` has none; ``where``
    prefixes every error message (``load_scenario_file`` gives the file);
    ``source`` (the file's name) ends the default description.
    """
    r = _Reader(where)
    if not isinstance(data, dict):
        r.fail(f"must be a table of keys; found {_show(data)}")
    if "duration" in data:      # the short name of a path's duration (the command line's documented form)
        if "path_duration_s" in data:
            r.fail("give the path's duration once: duration or path_duration_s, not both")
        data = {("path_duration_s" if k == "duration" else k): v for k, v in data.items()}
    r.unknown(data, KEYS)
    name = r.text(data["name"], "name", empty=False) if "name" in data else name
    kind, fields = _reference(r, data)
    try:
        traj = Scenario(name, kind, 1.0, (0.0,) * 12, **fields).reference()
    except (ValueError, ArithmeticError) as e:      # the path's own checks; the fields were checked above
        r.fail(f"the reference cannot be built: {e}")
    if kind != "hover":
        _check_path(r, kind, traj, fields.get("path_duration_s"))
    default = HOVER_DURATION_S if kind == "hover" else round(traj.duration_s + HOLD_S, 6)
    duration_s = r.number(data["duration_s"], "duration_s", DT, unit="s") if "duration_s" in data else default
    if duration_s > MAX_DURATION_S:
        what = (f"duration_s = {duration_s:g} s" if "duration_s" in data else
                f"the reference lasts {traj.duration_s:g} s, so the flight (with its {HOLD_S:g} s of hover after it) "
                f"would last {duration_s:g} s")
        r.fail(f"{what}; a flight may last at most {MAX_DURATION_S:g} s ({DURATION_LIMIT_REASON})")
    x0 = traj(np.array([0.0]))[0]
    if "start_offset_m" in data:
        x0[0:3] += r.vector3(data["start_offset_m"], "start_offset_m", " [dx, dy, dz] (m, NED)")
    if "start_attitude_deg" in data:
        att = r.vector3(data["start_attitude_deg"], "start_attitude_deg", " [roll, pitch, yaw] (deg)")
        if max(abs(att[0]), abs(att[1])) >= np.degrees(CRASH_TILT_RAD):
            r.fail(f"start_attitude_deg must keep roll and pitch within +-{np.degrees(CRASH_TILT_RAD):.0f} deg "
                   f"(the crash limit); found {_show(data['start_attitude_deg'])}")
        x0[3:6] += np.deg2rad(att)
    opts = _options(r, data, duration_s)
    desc = (r.text(data["description"], "description") if "description" in data
            else _describe(kind, fields, duration_s, opts, source))
    try:
        return Scenario(name, kind, duration_s, tuple(float(v) for v in x0), description=desc, **fields, **opts)
    except ScenarioError as e:
        r.fail(str(e))


@functools.lru_cache(maxsize=32)
def _load(path: str, mtime_ns: int, size: int, shown: str) -> Scenario:
    where = f"scenario file {shown!r}"
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as e:
        raise ScenarioError(" ".join(f"{where} could not be read: {e}".split())) from None
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(" ".join(f"{where} is not valid TOML: {e}".split())) from None
    return scenario_from_dict(data, name=Path(path).stem, where=where, source=Path(shown).name)


def load_scenario_file(path) -> Scenario:
    """The :class:`Scenario` of the TOML file ``path`` (format: ``docs/scenario-files.md``).

    Raises :class:`ScenarioError` (one line, naming the file and the field)
    for a missing file, invalid TOML, an unknown key or a bad value. A file
    is read again when it changes (its modification time or size).
    """
    p = Path(path)
    shown = str(path)
    if not p.is_file():
        raise ScenarioError(f"scenario file {shown!r} does not exist")
    st = p.stat()
    return _load(str(p.resolve()), st.st_mtime_ns, st.st_size, shown)


def rotor_load(scenario: Scenario, vehicle=None) -> tuple[float, float]:
    """How hard the reference drives the rotors of ``vehicle``: ``(peak, t)``.

    ``peak`` is the largest rotor thrust that the flatness wrench of the
    reference asks for over the flight (with the scenario's payload added
    to the mass), as a fraction of that rotor's maximum thrust (``n_max``);
    above 1 the vehicle cannot fly the reference as given. ``t`` is when, s.
    ``vehicle`` is a :class:`sim.vehicles.vehicle.Vehicle`, a preset name or a
    vehicle file (None: the default vehicle).
    """
    import dataclasses

    from mpc.references.trajectory import flat_state
    from sim.vehicles.rotors import allocate
    from sim.vehicles.vehicle import load_vehicle

    p = load_vehicle(vehicle).params
    lim = p.n_max_sq
    carried = dataclasses.replace(p, m=p.m * (1.0 + scenario.payload_fraction), n_max=math.sqrt(lim))
    t = np.arange(0.0, scenario.duration_s + DT / 8, DT / 4)
    _, u = flat_state(scenario.reference().flat(t), carried)
    load = allocate(u, p) / lim
    i = int(np.argmax(np.max(load, axis=1)))
    return float(np.max(load[i])), float(t[i])
