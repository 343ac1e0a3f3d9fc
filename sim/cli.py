"""``pinnmpc data``, ``pinnmpc import`` and ``pinnmpc fisher``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .files import check_writable, write_json
from .levels import DATA_LEVELS
from .params import FIDELITIES, INPUT_LOGS, THETA_NAMES


def add_plant_options(p, plant_help: str = "") -> None:
    """``--plant`` and ``--vehicle``, as every command that flies or simulates has them."""
    from .plants.named import PLANTS
    from .vehicles.vehicle import vehicle_names

    p.add_argument("--plant", choices=PLANTS, default="sim",
                   help="what flies: sim, this project's simulator (default); rotorpy, RotorPy with the vehicle's "
                        "motor lag and its aerodynamics; rotorpy-ideal, RotorPy with instant motors and no drag "
                        "(pip install -e '.[rotorpy]')" + plant_help)
    p.add_argument("--vehicle", default=None, metavar="NAME|FILE.toml",
                   help=f"the vehicle: {', '.join(vehicle_names())} (default rolling-spider), or a vehicle file "
                        f"(docs/plants.md)")


def register(sub) -> None:
    """Add this package's subcommands to the ``pinnmpc`` parser."""
    p = sub.add_parser("data", help="generate a seeded excitation dataset (.npz)",
                       description="Fly seeded random references with a stabilizing controller and log "
                                   "states, wrench commands, rotor speeds and next states.")
    p.add_argument("--regime", required=True, help="small (|roll|, |pitch| <= 20 deg) or aggressive (45-60 deg)")
    p.add_argument("--n-traj", type=int, default=100, help="number of trajectories (default 100)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds per trajectory (default 10)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--noise", choices=("default", "none"), default="default",
                   help="measurement noise: the stated default (1 mm, 1 mrad, 5 mrad/s, 5 mm/s, 0.01 RU) or none")
    p.add_argument("--fidelity", choices=tuple(FIDELITIES), default="nominal",
                   help="simulator fidelity: high adds motor lag, rotor drag and rotor gyroscopic torque; "
                        "motor-lag, rotor-drag, rotor-gyro add one of them")
    p.add_argument("--inputs", choices=INPUT_LOGS, default="commanded",
                   help="log the wrench command (default) or the wrench the rotors realized (a command kept "
                        "inside the rotor limits; not with motor lag)")
    p.add_argument("--out", required=True, type=Path, help="output file, .npz")
    p.add_argument("--json", type=Path, default=None, help="also write the summary as JSON")
    p.add_argument("--jobs", type=int, default=1,
                   help="processes flying at once on a plant that flies one vehicle at a time (RotorPy, or any "
                        "plant at --level ctbr; default 1); the dataset is the same for any number")
    p.add_argument("--level", choices=DATA_LEVELS, default="wrench",
                   help="what the excitation commands and the dataset logs: wrench (thrust and torques, default) or "
                        "ctbr (thrust and body rates, flown through the vehicle's inner loop; docs/levels.md)")
    add_plant_options(p, " ; --fidelity applies to sim only")
    p.set_defaults(handler=cmd_data)

    p = sub.add_parser("import", help="turn real flight logs (CSV, Parquet) into a dataset (.npz)",
                       description="Read flight logs through a format file (which column holds what, in which "
                                   "frame and unit), clean them (held rows, NaN, spikes), bring them onto the 10 ms "
                                   "grid, convert frames, cut to the airborne part, estimate each flight's "
                                   "motor-to-state delay and write one dataset (docs/real-flights.md).")
    p.add_argument("logs", nargs="+", type=Path, metavar="LOG", help="flight logs, one flight each (.csv, .parquet)")
    p.add_argument("--format", required=True, metavar="NAME|FILE.toml",
                   help="the logs' format: nanodrone-raw, nanodrone-processed, or a format file")
    p.add_argument("--vehicle", required=True, metavar="NAME|FILE.toml",
                   help="the vehicle whose rotor coefficients turn rotor speeds (rad/s) into the wrench, "
                        "e.g. crazyflie-brushless")
    p.add_argument("--out", required=True, type=Path, help="output dataset, .npz")
    p.add_argument("--split", action="append", default=[], metavar="SPLIT=PATTERN[,PATTERN]",
                   help="put the flights whose name (the file's stem) matches a pattern into SPLIT (train, val, "
                        "test); repeatable; unmatched flights are train")
    p.add_argument("--json", type=Path, default=None, help="also write the import report as JSON")
    p.set_defaults(handler=cmd_import)

    p = sub.add_parser("fisher", help="Fisher information and Cramer-Rao bounds of the six parameters",
                       description="Compare regimes (small, aggressive) and input parameterizations "
                                   "(wrench command, motor-level command) by their Fisher information.")
    p.add_argument("--n-traj", type=int, default=20, help="trajectories per regime (default 20)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds per trajectory (default 10)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--json", type=Path, default=None, help="write the table as JSON")
    p.set_defaults(handler=cmd_fisher)


def cmd_data(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc data``."""
    from .identification.excitation import make_dataset
    from .params import NoiseModel
    from .vehicles.vehicle import load_vehicle

    if args.out.suffix != ".npz":
        raise ValueError(f"--out must end in .npz; found {str(args.out)!r}")
    if args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1; found {args.jobs}")
    check_writable(args.out, "--out")               # before the flights, so that a refusal costs nothing
    if args.json:
        check_writable(args.json, "--json")
    vehicle = load_vehicle(args.vehicle)
    ds = make_dataset(args.regime, args.n_traj, args.duration, args.seed,
                      noise=NoiseModel() if args.noise == "default" else NoiseModel.none(),
                      fidelity=vehicle.named_fidelity(args.fidelity), inputs=args.inputs,
                      progress=sys.stderr.isatty(), plant=args.plant, vehicle=vehicle, workers=args.jobs,
                      level=args.level)
    ds.save(args.out)
    s = ds.summary()
    lo, hi = s["envelope_deg"]
    print(f"wrote {args.out}: {s['samples']} samples, {args.n_traj} trajectories x {ds.meta['duration_s']:g} s "
          + ("" if ds.level == "wrench" else f"at the {ds.level} level ")
          + f"(train/val/test {s['trajectories']['train']}/{s['trajectories']['val']}/{s['trajectories']['test']})")
    print(f"  regime {s['regime']}: max |roll| {s['max_abs_roll_deg']:.1f} deg, max |pitch| "
          f"{s['max_abs_pitch_deg']:.1f} deg (target {lo:g}-{hi:g}: "
          f"{'reached' if s['envelope_reached'] else 'NOT reached'}), yaw {s['yaw_range_deg'][0]:.0f} to "
          f"{s['yaw_range_deg'][1]:.0f} deg")
    print(f"  max |body rate| {s['max_abs_body_rate_rad_s']:.2f} rad/s, max speed {s['max_speed_m_s']:.2f} m/s, "
          f"samples with a saturated rotor {100 * s['saturation_fraction']:.2f} %")
    if args.json:
        write_json(args.json, {"out": str(args.out), **s})
    return 0


def _parse_splits(items: list[str]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for item in items:
        split, sep, patterns = item.partition("=")
        if not sep or not split or not patterns:
            raise ValueError(f"--split must be SPLIT=PATTERN[,PATTERN]; found {item!r}")
        out.setdefault(split.strip(), []).extend(p.strip() for p in patterns.split(",") if p.strip())
    return out


def cmd_import(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc import``: every log is read and checked before anything is written."""
    import dataclasses

    from .flightlogs.flightlog import assign_splits, flights_to_dataset, read_flight
    from .flightlogs.logformat import load_format
    from .vehicles.vehicle import load_vehicle

    if args.out.suffix != ".npz":
        raise ValueError(f"--out must end in .npz; found {str(args.out)!r}")
    if args.json is not None and args.json.suffix != ".json":
        raise ValueError(f"--json must end in .json; found {str(args.json)!r}")
    check_writable(args.out, "--out")
    if args.json is not None:
        check_writable(args.json, "--json")
    fmt = load_format(args.format)
    vehicle = load_vehicle(args.vehicle)
    names = [p.stem for p in args.logs]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"two logs are named {dup!r} (a flight is named by its file's stem)")
    patterns = _parse_splits(args.split)
    splits = assign_splits(names, patterns)
    for split, pats in patterns.items():
        if not any(s == split for s in splits.values()):
            raise ValueError(f"--split {split}={','.join(pats)} matches no flight (the flights: "
                             f"{', '.join(names[:8])}{', ...' if len(names) > 8 else ''})")
    flights = []
    for i, path in enumerate(args.logs):
        if sys.stderr.isatty():
            print(f"[{i + 1}/{len(args.logs)}] {path}", file=sys.stderr, flush=True)
        flights.append(read_flight(path, fmt, vehicle))
    ds = flights_to_dataset(flights, vehicle, splits, fmt)
    report = None if args.json is None else {
        "out": str(args.out), "format": fmt.name, "vehicle": vehicle.name, "splits": splits,
        "flights": [dataclasses.asdict(f.report) for f in flights]}
    existed = args.out.exists()
    ds.save(args.out)                  # whole or not at all
    if report is not None:
        try:
            write_json(args.json, report)
        except OSError as e:           # both files or neither
            if not existed:
                args.out.unlink(missing_ok=True)
            raise ValueError(f"--json {str(args.json)!r} could not be written: {e.strerror or e}") from None
    for f in flights:
        print("\n".join(f.report.lines()))
        for w in f.report.warnings():
            print(f"warning: {w}", file=sys.stderr)
    counts = {s: sum(1 for n in names if splits[n] == s) for s in ("train", "val", "test")}
    print(f"wrote {args.out}: {len(flights)} flights ({counts['train']} train, {counts['val']} val, "
          f"{counts['test']} test), {int(ds.usable.sum())} usable one-step samples of {ds.usable.size}")
    return 0


def format_fisher_table(table: dict) -> str:
    """Human-readable form of :func:`sim.identification.fisher.fisher_table`."""
    st = table["settings"]
    n = st["noise"]
    lines = [
        f"Fisher information, {st['n_traj']} trajectories x {st['duration_s']:g} s per regime, seed {st['seed']}",
        f"noise (1 sigma): position {n['position']:g} m, attitude {n['attitude']:g} rad, body rate "
        f"{n['body_rate']:g} rad/s, velocity {n['velocity']:g} m/s, rotor speed {n['rotor_speed']:g} RU",
        "CRLB standard deviation in % of the true value (inf: not identifiable)",
        "",
    ]
    head = f"{'regime':<11}{'inputs':<8}{'rank':>5}{'cond':>10}" + "".join(f"{t:>9}" for t in THETA_NAMES)
    lines += [head, "-" * len(head)]
    for c in table["cases"]:
        cond = c["condition_number"]
        row = f"{c['regime']:<11}{c['inputs']:<8}{c['rank']:>5}{(f'{cond:.1e}' if cond else 'inf'):>10}"
        for t in THETA_NAMES:
            v = c["crlb_pct"][t]
            row += f"{('inf' if v is None else f'{v:.3g}'):>9}"
        lines.append(row)
    lines += ["", "weakest direction (eigenvector of the smallest eigenvalue, relative coordinates):"]
    for c in table["cases"]:
        d = c["weakest_direction_relative"]
        vec = " ".join(f"{d[t]:+.3f}" for t in THETA_NAMES)
        lines.append(f"  {c['regime']:<11}{c['inputs']:<8}[{vec}]  lambda_min/lambda_max "
                     f"{c['eigenvalues'][0] / c['eigenvalues'][-1]:.1e}  |cos| to scale direction "
                     f"{c['weakest_vs_scale_direction_abs_cos']:.4f}")
    return "\n".join(lines)


def cmd_fisher(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc fisher``."""
    from .identification.fisher import fisher_table

    table = fisher_table(args.n_traj, args.duration, args.seed, progress=sys.stderr.isatty())
    print(format_fisher_table(table))
    if args.json:
        write_json(args.json, table)
        print(f"\nwrote {args.json}")
    return 0
