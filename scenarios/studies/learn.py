"""Learning from the flights it flies: fly, learn from the flights, fly the learned model, again.

``pinnmpc learn --plant highfi|rotorpy [--iterations 3] [--out results/learn]`` runs, on one plant:

* **iteration 0** flies the nominal equations with the SQP on fresh training references
  (:func:`scenarios.studies.training_refs.training_references`: min-snap paths and orbits at three speed levels, never a
  figure-8), each perturbed (:class:`scenarios.studies.training_refs.Perturbed`) and with input dither
  (:class:`scenarios.closed_loop.dither.Dithered`), and logs them as flights
  (:func:`sim.flightlogs.flightlog.flown_flight`, with the
  motion-capture noise of the open-loop data added);
* **iteration i >= 1** trains physics plus network with the rotor speeds as states (``hybrid_lag``) on every flight
  so far, with the aerodynamic terms the flights select (``--aero select``, the default: the term library of
  :mod:`sim.identification.aero` identified first, then trained jointly), and flies that model on the next
  iteration's references (the last iteration's model flies only its evaluation);
* each iteration's model flies the held-out ``figure8-fast`` (``members`` ensemble members for the nominal
  equations and the final model, ``curve_members`` for the models between): one row of the learning curve (RMSE
  against iteration and against the minutes of flight it learned from);
* two **controls** are trained the same way: the same minutes of open-loop excitation (``pinnmpc data``'s
  random references flown by the hover LQR with dither), and an **upper bound** from the final model's flights
  plus an iteration's worth of flights of the evaluation reference itself (never a result: it has seen the test);
* the **evaluation** flies the nominal equations, the plant's best open-loop model shipped in ``models/``, the
  final model and the controls on ``figure8-fast`` and the figure-8 speed ladder (a resumable sweep).

Every stage writes its files as it ends (``it<i>/flights.npz``, ``it<i>/<model>.onnx``, ``it<i>/curve.json``,
``controls/...``), and a rerun reuses what is there: killed anywhere, the study resumes and ends with the same
results. Before anything enters training, :func:`scenarios.studies.training_refs.check_held_out` checks by content
that no
evaluation reference is among the flown references.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.files import write_json
from sim.params import DT

from pinn.ctbr import CTBR_ARCH, FlownSeries  # torch-free at import

from ..errors import ScenarioError
from ..sweeps.lock import locks_out_dir

#: Settle time flown after a training path ends (hover at its last point), s.
HOLD_S = 1.0
#: Architecture learned (physics plus network, rotor speeds as states, tau_m learnable) and its budget.
LEARN_ARCH = "hybrid_lag"
#: Seconds of each open-loop excitation flight of the same-data control (``pinnmpc data``'s default).
OPEN_LOOP_FLIGHT_S = 10.0
#: Splits of the flown flights, by their order: of every SPLIT_EVERY flights, the fifth is for validation and the sixth
#: for test (counted among the flights long enough to give a piece; at the default settings about one of each per
#: iteration's 12).
SPLIT_EVERY = 9
#: Periods per piece of a flown flight in its dataset (4 s; see :func:`flights_dataset`).
PIECE_STEPS = 400
LEARN_DIR = "learn"
#: What each control is, as the report says it.
CONTROL_ROLES = {"openloop": "control: same minutes of open-loop excitation",
                 "upper": "upper bound: the final model's flights plus flights of figure8-fast itself"}
#: File of a study's stage times, kept across resumed runs.
STAGE_TIMES = "stage_seconds.json"
#: Training budgets: a profile of :data:`pinn.train.PROFILES` and settings changed from it. ``smoke`` is for tests of
#: the loop itself (seconds; its models are not meant to fly well).
#: ``scaled`` (the default) is the ``full`` profile of the shipped models in 20 epochs, with as many steps as make
#: :data:`PASSES` passes over the training samples (at most the ``full`` profile's steps): a fixed budget of 6,000
#: steps of 1,024 windows overfits the first iterations' few minutes of flight (measured on our high-fidelity plant,
#: 3.5 min of flights: validation loss 0.171 against 0.153, figure8-fast 44 mm against 25 mm flown once).
LEARN_PROFILES = {"scaled": ("full", {"epochs": 20}), "full": ("full", {}), "quick": ("quick", {}),
                  "smoke": ("quick", {"epochs": 2, "steps_per_epoch": 4, "batch": 128, "n_colloc": 64})}
#: Passes over the training samples of the ``scaled`` profile (the shipped models' open-loop trainings make 60-90).
PASSES = 60
#: Most steps per epoch of the ``scaled`` profile (twice the ``full`` profile's 150 in its 20 epochs: its total).
PROFILE_STEPS_CAP = 300


@dataclass(frozen=True)
class LearnPlant:
    """A plant of the learning study: where it flies, the open-loop data it is compared with, its best open-loop model.

    ``versus`` is the key of the plant in :data:`scenarios.studies.versus.VERSUS_PLANTS` (its scenario suffix, label and
    vehicle); ``open_loop`` the excitation regime of the same-data control; ``best_open_loop`` the path (under the
    models folder) of the best model trained on open-loop excitation of this plant (None: there is none), and
    ``best_open_loop_ctbr`` that of the best one trained on excitation flown at ``ctbr``.
    """

    key: str
    high_fidelity: bool
    versus: str
    open_loop: str
    best_open_loop: str | None
    best_open_loop_ctbr: str | None = None

    def best_open_loop_at(self, level: str) -> str | None:
        """The best open-loop model at ``level`` (a path under the models folder; None: there is none)."""
        return self.best_open_loop_ctbr if level == "ctbr" else self.best_open_loop

    @property
    def plant(self) -> str:
        """The plant flown (:data:`sim.plants.named.PLANTS`)."""
        from .versus import VERSUS_PLANTS

        return VERSUS_PLANTS[self.versus].plant

    @property
    def vehicle(self) -> str | None:
        """The vehicle flown (a shipped vehicle's name; None: the default vehicle)."""
        from .versus import VERSUS_PLANTS

        return VERSUS_PLANTS[self.versus].vehicle


LEARN_PLANTS = {
    "highfi": LearnPlant("highfi", True, "highfi", "aggressive", "versus/hybrid_lag_aggressive_highfi.onnx",
                         "versus/ctbr/ctbr_aggressive_highfi.onnx"),
    "rotorpy": LearnPlant("rotorpy", False, "rotorpy", "small", "versus/hybrid_lag_rotorpy.onnx",
                          "versus/ctbr/ctbr_aggressive_rotorpy.onnx"),
    "crazyflie": LearnPlant("crazyflie", False, "crazyflie", "small", None),
}


#: The option of ``pinnmpc learn`` that sets each setting of :class:`LearnSettings` (the others have none): an invalid
#: setting's error names its option as typed, since that is where the value came from on the command line.
SETTING_OPTIONS = {"plant": "--plant", "iterations": "--iterations", "per_level": "--per-level", "seed": "--seed",
                   "profile": "--profile", "members": "--members", "curve_members": "--curve-members",
                   "ladder_members": "--ladder-members", "controls": "--no-controls", "level": "--level",
                   "aero": "--aero"}
#: The command levels the study learns at: the wrench (:data:`LEARN_ARCH`, the rotor speeds as states) and ``ctbr``
#: (:data:`CTBR_ARCH`). At ``ctatt`` no learner is written.
LEARN_LEVELS = ("wrench", "ctbr")


@dataclass(frozen=True)
class LearnSettings:
    """What defines a learning study (stored in ``learn.json``; a rerun into the same folder must match).

    Raises
    ------
    ScenarioError
        For an invalid setting, named by its option of ``pinnmpc learn`` (:data:`SETTING_OPTIONS`:
        ``--per-level must be an integer >= 1; found 0`` for ``per_level=0``), or by its field where it has none
        (``dither``, ``perturb_m``).
    """

    plant: str = "highfi"
    iterations: int = 3          # models trained on flown data (>= 1)
    per_level: int = 2           # training references per family and speed level, per iteration
    seed: int = 0
    dither: float = 1.0          # scale of scenarios.closed_loop.dither.dither_std
    perturb_m: float = 0.1       # reference perturbation, m (scenarios.studies.training_refs.Perturbed)
    profile: str = "scaled"      # training budget (LEARN_PROFILES)
    members: int = 10            # ensemble members on figure8-fast: the evaluation, and the curve's first and last rows
    curve_members: int = 5       # ensemble members of the curve's other rows (the models between first and final)
    ladder_members: int = 3      # members per rung of the speed ladder in the evaluation
    controls: bool = True        # train and fly the two controls (at ctbr the upper bound only)
    level: str = "wrench"        # command level flown and learned (LEARN_LEVELS)
    aero: str | None = None      # aerodynamic terms (sim.identification.aero.AERO_MODES); None: select at the wrench
                                 # level, none at ctbr (whose model has no rotor speeds for the terms to read)

    def __post_init__(self):
        def named(name: str) -> str:
            return SETTING_OPTIONS.get(name, name)

        if self.plant not in LEARN_PLANTS:
            raise ScenarioError(f"{named('plant')} must be one of {', '.join(LEARN_PLANTS)}; found {self.plant!r}")
        for name in ("iterations", "per_level", "members", "curve_members", "ladder_members"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ScenarioError(f"{named(name)} must be an integer >= 1; found {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ScenarioError(f"{named('seed')} must be an integer >= 0; found {self.seed!r}")
        for name in ("dither", "perturb_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ScenarioError(f"{named(name)} must be a finite number >= 0; found {v!r}")
        if self.profile not in LEARN_PROFILES:
            raise ScenarioError(f"{named('profile')} must be one of {', '.join(LEARN_PROFILES)}; "
                                f"found {self.profile!r}")
        from sim.identification.aero import AERO_MODES

        if self.aero is None:
            object.__setattr__(self, "aero", "select" if self.level == "wrench" else "none")
        if self.aero not in AERO_MODES:
            raise ScenarioError(f"{named('aero')} must be one of {', '.join(AERO_MODES)}; found {self.aero!r}")
        if self.aero != "none" and self.level != "wrench":
            raise ScenarioError(f"{named('aero')} {self.aero} needs the wrench level, whose model carries the rotor "
                                f"speeds the terms read; found {named('level')} {self.level}")
        if self.level not in LEARN_LEVELS:
            raise ScenarioError(f"{named('level')} must be one of {', '.join(LEARN_LEVELS)} (no learner is written "
                                f"for the other levels); found {self.level!r}")

    @property
    def spec(self) -> LearnPlant:
        return LEARN_PLANTS[self.plant]

    @property
    def tag(self) -> str:
        """The study's folder and model-name stem (:func:`study_tag`)."""
        return study_tag({"plant": self.plant, "level": self.level})

    def record(self) -> dict:
        """The settings as stored in ``settings.json`` and ``learn.json`` (the level only where it is not the
        wrench, so that the studies written before it existed resume)."""
        out = dataclasses.asdict(self)
        if self.level == "wrench":
            del out["level"]
        if self.aero == "none":
            del out["aero"]
        return out


# ------------------------------------------------------------------ one training flight
@dataclass(frozen=True)
class FlightJob:
    """One flight of a learning study, as data a worker process can rebuild it from.

    ``kind`` is ``"train"`` (reference ``index`` of :func:`training_references` for ``iteration``) or ``"upper"``
    (the evaluation reference ``figure8-fast`` itself, for the upper-bound control; ``index`` is the flight's
    number). ``model`` is ``"nominal"`` or an ONNX path.
    """

    settings: LearnSettings
    kind: str
    iteration: int
    index: int
    model: str

    @property
    def seed(self) -> int:
        """Seeds this flight's perturbation, dither and measurement noise."""
        s = self.settings
        return ((s.seed * 1000 + self.iteration) * 1000 + self.index) * 2 + (self.kind == "upper")

    def reference(self) -> tuple[str, object, float]:
        """``(name, flat trajectory, duration_s)`` of the perturbed reference flown."""
        from .training_refs import Perturbed, training_references

        s = self.settings
        if self.kind == "train":
            r = training_references(self.iteration, s.per_level, s.seed)[self.index]
            name, base, duration = r.name, r.trajectory, r.duration_s + HOLD_S
        else:
            from ..closed_loop.library import get_scenario

            sc = get_scenario("figure8-fast")
            name, base, duration = f"upper-figure8-fast-{self.index}", sc.reference(), sc.steps * DT
        return name, Perturbed(base, s.perturb_m, seed=self.seed), duration


def fly_flight(job: FlightJob) -> dict:
    """Fly one flight of a study: the SQP on ``job.model`` along the perturbed reference, with dither.

    Returns
    -------
    dict
        ``name``; ``t`` (n,), s; ``x`` (n, 12) and ``rotor_speed`` (n, 4), RU, as measured (the open-loop data's
        motion-capture and telemetry noise, :class:`sim.params.NoiseModel`, added to the plant's); ``command``
        (n - 1, 4), the command sent at the study's level (dither included): the wrench, N and N m, or at ``ctbr``
        the collective thrust, N, and the body rates, rad/s; ``reference`` (n, 3), the perturbed reference's
        positions, m; and the flight's ``rmse_m`` (true position against that reference), ``crashed``,
        ``crash_reason``, ``seconds`` flown and ``solve_ms`` (median per period).
    """
    from sim.params import NoiseModel
    from sim.plants.named import make_plant
    from sim.vehicles.vehicle import load_vehicle

    from ..closed_loop.dither import Dithered, level_dither_std
    from ..closed_loop.loop import IdealClock, StateSensor, fly_loop
    from mpc.controllers.factory import make_controller
    from mpc.references.trajectory import reference_spec, reference_states

    p = job.settings.spec
    name, traj, duration = job.reference()
    level = job.settings.level
    vehicle = load_vehicle(p.vehicle)
    plant = make_plant(p.plant, vehicle, high_fidelity=p.high_fidelity, level=level)
    K = int(round(duration / DT))
    times = DT * np.arange(K + 1)
    n0 = None
    if p.high_fidelity:
        from mpc.references.trajectory import actuated_flat_state

        x_ref, n_ref, _ = actuated_flat_state(traj, times, vehicle.params, vehicle.fidelity)
        n0 = n_ref[0] if vehicle.fidelity.motor_tau > 0.0 else None
    else:
        x_ref = reference_states(traj, times, reference_spec(p.plant, vehicle))
    model = _load(job.model, p, level)
    ctrl = make_controller("sqp", model, traj, timing="ideal", vehicle=vehicle)
    std = level_dither_std(vehicle.params, level)
    ctrl.prepare(K * DT, x0=x_ref[0].copy())
    plant.reset(x_ref[0].copy(), rotor_speed=n0)
    rng = np.random.default_rng([job.seed, 0x1EA2])
    tr = fly_loop(plant, StateSensor(None, rng), Dithered(ctrl, job.settings.dither * std, seed=job.seed),
                  IdealClock(plant.hover_input, 0), x_ref, K)
    n = tr.steps + 1
    x, rot = tr.x[:n].copy(), tr.rotor_speed[:n].copy()
    noise = NoiseModel()
    meas = np.random.default_rng([job.seed, 0x4015E])
    x_m = x + noise.state_std * meas.standard_normal(x.shape)
    rot_m = rot + noise.rotor_speed * meas.standard_normal(rot.shape)
    err = np.linalg.norm(x[:, 0:3] - x_ref[:n, 0:3], axis=1)
    solve = tr.solve_s[:n - 1][tr.called[:n - 1]]
    return {"name": name, "t": times[:n], "x": x_m, "rotor_speed": rot_m, "command": tr.u_command[:n - 1].copy(),
            "reference": x_ref[:n, 0:3].copy(), "rmse_m": float(np.sqrt(np.nanmean(err ** 2))),
            "crashed": tr.crash_step is not None, "crash_reason": tr.crash_reason, "seconds": float((n - 1) * DT),
            "solve_ms": float(1e3 * np.median(solve)) if solve.size else None}


def _load(model: str, p: LearnPlant, level: str = "wrench"):
    """The prediction model ``model`` (``"nominal"`` or an ONNX path) as a run on plant ``p`` at ``level`` would load
    it."""
    from ..closed_loop.runner import RunSpec, load_run_model

    scenario = "figure8-fast" + ("+highfi" if p.high_fidelity else "")
    return load_run_model(RunSpec(scenario, "sqp", model, plant=p.plant, vehicle=p.vehicle, level=level))


FLIGHT_ARRAYS = ("t", "x", "rotor_speed", "command", "reference")


def save_flights(path: Path, flights: list[dict]) -> Path:
    """Write flights (:func:`fly_flight`'s records) to one ``.npz``: arrays per flight, the rest as JSON."""
    from sim.files import write_npz

    arrays = {f"{k}_{i}": np.asarray(f[k]) for i, f in enumerate(flights) for k in FLIGHT_ARRAYS}
    arrays["records"] = np.array(json.dumps([{k: v for k, v in f.items() if k not in FLIGHT_ARRAYS}
                                             for f in flights]))
    return write_npz(path, arrays)


def load_flights(path: Path) -> list[dict]:
    """Flights written by :func:`save_flights`, as they were."""
    with np.load(path, allow_pickle=False) as z:
        records = json.loads(str(z["records"]))
        return [{**r, **{k: z[f"{k}_{i}"] for k in FLIGHT_ARRAYS}} for i, r in enumerate(records)]


def flights_dataset(flights: list[dict], vehicle=None):
    """A :class:`sim.identification.excitation.Dataset` of flown flights, through the flight logs' path, in pieces of
    equal length.

    Each flight goes through :func:`sim.flightlogs.flightlog.flown_flight` and
    :func:`sim.flightlogs.flightlog.flights_to_dataset` (as a
    log would) and is split as a whole by :data:`SPLIT_EVERY`, in the order given (so adding flights never moves an
    earlier one to another split). The flights are then cut into pieces of :data:`PIECE_STEPS` periods (the last
    piece of a flight ends at its end, overlapping the one before; a flight shorter than one piece is left out), so
    that every trajectory of the dataset is measured throughout: the motor-lag model trains only on such data.
    ``vehicle`` is the vehicle flown (a name, file or :class:`sim.vehicles.vehicle.Vehicle`; None: the default vehicle).
    """
    from sim.identification.excitation import Dataset
    from sim.flightlogs.flightlog import flights_to_dataset, flown_flight
    from sim.vehicles.vehicle import load_vehicle

    vehicle = load_vehicle(vehicle)
    L = PIECE_STEPS
    # A flight cut by a crash before one piece's length gives no piece (and one shorter than the logs' least length,
    # MIN_SAMPLES, is no log): it is left out here. Splits go by position among the flights kept, so that a crash
    # never leaves the validation or test split empty, and a flight added later never moves a kept one.
    fl, splits = [], {}
    for f in _kept(flights):
        j = len(fl)
        fl.append(flown_flight(f["name"], f["t"], f["x"], f["rotor_speed"], vehicle, command=f["command"],
                               reference=f["reference"]))
        splits[f["name"]] = _split_of(j)
    if not fl:
        raise ScenarioError(f"no flown flight is {L * DT:g} s long: nothing to learn from")
    ds = flights_to_dataset(fl, vehicle, splits)
    rows = []
    for i, f in enumerate(fl):
        m = len(f.t) - 1                        # one-step pairs of flight i, all measured: at least L (kept above)
        starts = list(range(0, m - L + 1, L))
        if starts[-1] != m - L:
            starts.append(m - L)
        rows += [(i, k) for k in starts]
    take = {name: np.stack([getattr(ds, name)[i, k:k + L] for i, k in rows])
            for name in ("x", "u", "rotor_speed", "x_next", "wrench", "saturated")}
    split = np.array([ds.split[i] for i, _ in rows])
    meta = {**ds.meta, "pieces": {"steps": L, "count": len(rows), "flights": len(fl)}}
    return Dataset(**take, split=split, meta=meta)


def _kept(flights: list[dict]) -> list[dict]:
    """The flights long enough to learn from: at least one piece (:data:`PIECE_STEPS` one-step pairs) and the logs'
    least length of finite samples (a flight cut short by a crash gives less)."""
    from sim.flightlogs.flightlog import MIN_SAMPLES, finite_samples

    return [f for f in flights
            if finite_samples(f["x"], f["rotor_speed"]) >= max(PIECE_STEPS + 1, MIN_SAMPLES)]


def _split_of(j: int) -> str:
    """The split of the ``j``-th flight kept: of every :data:`SPLIT_EVERY`, the fifth for validation, the sixth for
    test."""
    return {4: "val", 5: "test"}.get(j % SPLIT_EVERY, "train")


def ctbr_flights(flights: list[dict]) -> dict[str, list[FlownSeries]]:
    """The flown flights by split (``train``, ``val``, ``test``) for the ``ctbr`` learner.

    The flights kept and their splits are :func:`flights_dataset`'s: a flight with fewer finite samples than one
    piece (:data:`PIECE_STEPS`) and the logs' least length is left out, and of every :data:`SPLIT_EVERY` flights
    kept, in the order given, the fifth is for validation and the sixth for test.
    """
    out: dict[str, list[FlownSeries]] = {"train": [], "val": [], "test": []}
    kept = _kept(flights)
    for j, f in enumerate(kept):
        x = np.asarray(f["x"], dtype=float)
        bad = np.flatnonzero(~np.all(np.isfinite(x), axis=1))
        n = len(x) if bad.size == 0 else int(bad[0])
        cmd = np.asarray(f["command"], dtype=float)[:n]
        u = np.concatenate([cmd, cmd[-1:]])[:n] if len(cmd) < n else cmd[:n]
        out[_split_of(j)].append(FlownSeries(f["name"], x[:n].copy(), u, np.ones(n, dtype=bool)))
    if not kept:
        raise ScenarioError(f"no flown flight is {PIECE_STEPS * DT:g} s long: nothing to learn from")
    return out


def ctbr_physics(settings: "LearnSettings"):
    """The ``ctbr`` nominal model of the study's plant and vehicle in torch (:func:`pinn.ctbr.ctbr_physics`) and the
    vehicle's ``theta`` written into the model file."""
    from pinn.ctbr import ctbr_physics as physics_of
    from sim.vehicles.vehicle import load_vehicle

    return physics_of(settings.spec.plant, load_vehicle(settings.spec.vehicle))


def train_ctbr_model(settings: LearnSettings, flights, folder, name: str, threads: int, data: dict) -> dict:
    """Train :data:`CTBR_ARCH` on ``flights`` (:func:`fly_flight`'s records at ``ctbr``, or the path of an excitation
    dataset flown at ``ctbr``: its trajectories and splits, :func:`pinn.ctbr.dataset_series`) and export it as
    ``folder/name.onnx`` (level ``ctbr``, with its derivative graph); its record, also written to
    ``folder/name.json``: the settings, the epoch kept, the validation scores and the test flights' open-loop
    errors at h = 1, 10 and 50."""
    import torch

    from pinn.ctbr import train_ctbr
    from pinn.flights import export_flight_model
    from sim.vehicles.vehicle import load_vehicle

    torch.set_num_threads(threads)
    if isinstance(flights, (str, Path)):
        from pinn.ctbr import dataset_series
        from sim.identification.excitation import load_dataset

        split = dataset_series(load_dataset(flights))
    else:
        split = ctbr_flights(flights)
    for k, what in (("train", "training"), ("val", "validation"), ("test", "test")):
        if not split[k]:
            raise ScenarioError(f"training {name}: its data have no {what} flight; six or more flights of at least "
                                f"{PIECE_STEPS * DT:g} s are needed (fly more references: --per-level)")
    t = train_ctbr(split, settings.spec.plant, load_vehicle(settings.spec.vehicle), settings.seed, settings.profile)
    res = t.result
    export_flight_model(res.model, Path(folder) / f"{name}.onnx", t.theta, CTBR_ARCH, level="ctbr")
    rec = {"name": name, "onnx": f"{name}.onnx", "data": data, "recipe": CTBR_ARCH, "level": "ctbr",
           "train": dataclasses.asdict(t.config), "flights": {k: len(v) for k, v in split.items()},
           "best_epoch": res.best_epoch, "validation_scores": [float(v) for v in res.scores],
           "test_errors": t.test_errors, "rate_tau_s": t.rate_tau_s, "training_seconds": round(res.seconds, 1),
           "threads": threads}
    write_json(Path(folder) / f"{name}.json", rec)
    return rec


# ------------------------------------------------------------------ stages
def _say(progress, line: str) -> None:
    if progress is not None:
        progress(line)


def _check_held_out(flights: list[dict]) -> None:
    """Raise if any flight's reference repeats a window of an evaluation reference (content, not names)."""
    from .training_refs import check_held_out

    check_held_out({f["name"]: np.asarray(f["reference"]) for f in flights})


def _fly_all(jobs_list: list[FlightJob], workers: int, progress, what: str) -> list[dict]:
    """Fly ``jobs_list`` on ``workers`` processes; the records in the order given."""
    out: dict[int, dict] = {}
    t0 = time.perf_counter()

    def done(item, rec):
        out[item[0]] = rec
        _say(progress, f"  {what}: flew {rec['name']} ({rec['seconds']:.1f} s, RMSE {1e3 * rec['rmse_m']:.1f} mm"
                       f"{', crashed' if rec['crashed'] else ''}) [{len(out)}/{len(jobs_list)}, "
                       f"{time.perf_counter() - t0:.0f} s]")

    def failed(item, reason):
        raise ScenarioError(f"flight {item[1].kind} {item[1].iteration}/{item[1].index}: {reason}")

    items = list(enumerate(jobs_list))
    if workers <= 1 or len(items) == 1:
        for item in items:
            done(item, _fly_item(item))
    else:
        from ..sweeps.pool import run_pool

        run_pool(_fly_item, items, workers, done, failed)
    return [out[i] for i in range(len(jobs_list))]


def _fly_item(item):
    return fly_flight(item[1])


def _train_item(item):
    """Train one model (a pool task): ``(settings, dataset, folder, name, threads, data)``; its record. The dataset is
    a dataset file's path at the wrench level, the flights themselves at ``ctbr``."""
    settings, dataset, folder, name, threads, data = item
    if settings.level == "ctbr":
        return train_ctbr_model(settings, dataset, folder, name, threads, data)
    return train_model(settings, dataset, folder, name, threads, data)


def train_model(settings: LearnSettings, data_path, folder, name: str, threads: int, data: dict) -> dict:
    """Train :data:`LEARN_ARCH` on the dataset at ``data_path`` and export it as ``folder/name.onnx``; its record.

    The record (also written to ``folder/name.json``) holds the training's settings, identified parameters,
    losses, test metrics and time.
    """
    import torch

    from mpc.prediction.contract import config_hash
    from pinn.export import export_model
    from pinn.metrics import test_metrics
    from pinn.train import make_config, train
    from sim.identification.excitation import load_dataset
    from sim.params import THETA_NAMES

    torch.set_num_threads(threads)
    ds = load_dataset(data_path)
    for k, what in enumerate(("training", "validation", "test")):
        if not np.any(ds.split == k):
            raise ScenarioError(f"training {name}: its data have no {what} flight; six or more flights of at least "
                                f"{PIECE_STEPS * DT:g} s are needed (fly more references: --per-level)")
    base, changed = LEARN_PROFILES[settings.profile]
    if settings.profile == "scaled":
        cfg = make_config(LEARN_ARCH, base, settings.seed, threads=threads, **changed)
        n_train = int(ds.usable[ds.split == 0].sum())
        steps = math.ceil(PASSES * n_train / (cfg.epochs * cfg.batch))
        changed = {**changed, "steps_per_epoch": max(10, min(PROFILE_STEPS_CAP, steps))}
    if settings.aero != "none":
        changed = {**changed, "aero": settings.aero}
    cfg = make_config(LEARN_ARCH, base, settings.seed, threads=threads, **changed)
    res = train(ds, cfg)
    last = res.history[-1]
    if not (np.isfinite(last["val"]) and np.all(np.isfinite(last["theta"]))):
        raise ScenarioError(f"training {name} ended with a non-finite validation loss ({last['val']}) or parameters")
    metrics = test_metrics(res.model, ds)
    training_config = {"name": name, "recipe": LEARN_ARCH, "train": res.config.to_dict(), "data": data}
    export_model(res.model, folder, name, training_config, settings.seed, metrics, res.stats, torch_file=False)
    rec = {"name": name, "onnx": f"{name}.onnx", "data": data, "config_hash": config_hash(training_config),
           "theta": dict(zip(THETA_NAMES, [float(v) for v in last["theta"]])),
           "tau_m_s": float(res.model.tau.detach()), "final_losses": {k: last[k] for k in ("data", "phys", "rotor",
                                                                                          "val")},
           "metrics": metrics, "training_seconds": round(res.seconds, 1), "threads": threads,
           "steps": cfg.epochs * cfg.steps_per_epoch, "batch": cfg.batch}
    if res.aero_selection is not None:
        from pinn.train import aero_summary

        rec["aero"] = aero_summary(res.aero_selection, res.model)
    write_json(Path(folder) / f"{name}.json", rec)
    return rec


def _dataset_file(path: Path, flights: list[dict], vehicle) -> Path:
    """The dataset of ``flights`` of ``vehicle`` at ``path`` (written once; the same flights give the same bytes)."""
    if not path.is_file():
        flights_dataset(flights, vehicle).save(path)
    return path


def _curve_row(settings: LearnSettings, out: Path, iteration: int, model: str, flights: list[dict], jobs: int,
               progress) -> dict:
    """Fly ``model`` on the held-out ``figure8-fast``: one row of the learning curve.

    The first row (the nominal equations) and the last (the final model) fly ``settings.members`` members, the
    evaluation's own runs, which it then finds flown; the rows between fly the first ``settings.curve_members``
    (at most ``members``).
    """
    from .stats import summarize
    from ..sweeps.sweep import sweep
    from .versus import versus_specs

    members = settings.members if iteration in (0, settings.iterations) else min(settings.curve_members,
                                                                                settings.members)
    specs = versus_specs(settings.spec.versus, [model], members, ladder_members=1,
                         level=settings.level)["ensemble"][model]
    results = sweep(specs, out / "evaluation", jobs=jobs, progress=False)
    _no_errors(results)
    s = summarize(results)
    seconds = float(sum(f["seconds"] for f in flights))
    row = {"iteration": iteration, "model": "nominal" if model == "nominal" else Path(model).stem,
           "flights": len(flights), "flight_minutes": seconds / 60.0, "ensemble": s,
           "members_rmse_m": [None if r.get("crashed") else r.get("rmse_position_m") for r in results],
           "solve_ms_median": _median([r["solve_ms"]["median"] for r in results
                                       if isinstance(r.get("solve_ms"), dict)])}
    med = "–" if s["median"] is None else f"{1e3 * s['median']:.1f} mm"
    _say(progress, f"  curve: iteration {iteration} ({row['model']}, {seconds / 60:.1f} min of flights): "
                   f"figure8-fast {med}, crashes {s['crashes']}/{s['runs']}")
    return row


def _no_errors(results: list[dict]) -> None:
    """Raise for a run that did not fly (its error), so that no stage is written from it; a crash is a result."""
    bad = [r for r in results if r.get("error")]
    if bad:
        raise ScenarioError(f"{len(bad)} of {len(results)} runs did not fly; the first, {bad[0].get('run_id')}: "
                            f"{bad[0]['error']}")


def _median(v):
    v = [x for x in v if x is not None]
    return float(np.median(v)) if v else None


def _stage(path: Path, make):
    """The JSON at ``path`` if a previous run wrote it, else ``make()`` written there."""
    if path.is_file():
        return json.loads(path.read_text())
    value = make()
    write_json(path, value)
    return value


def _flights_stage(settings: LearnSettings, path: Path, jobs_list: list[FlightJob], workers: int, progress,
                   what: str, held_out: bool = True) -> list[dict]:
    """The flights of ``jobs_list``: read from ``path`` if a previous run wrote them, else flown and written."""
    if not path.is_file():
        if held_out:     # before anything flies: no reference to be flown for training is an evaluation reference
            from .training_refs import check_held_out, reference_positions

            check_held_out({n: reference_positions(tr, d) for n, tr, d in (j.reference() for j in jobs_list)})
        save_flights(path, _fly_all(jobs_list, workers, progress, what))
    return load_flights(path)    # as written, so that a resumed study trains on the same bytes


class _StageTimes:
    """Seconds of each stage of a study, kept in ``OUT/PLANT/stage_seconds.json`` across resumed runs.

    A stage that a rerun finds done keeps the seconds of the run that did it, so that a study's total
    (``study_seconds``) is the compute it took however often it was resumed, and rerunning a finished study changes
    none of its stage times. A stage is found done by its file (``done`` of :meth:`start`), or, for the evaluation,
    whose sweep resumes run by run and has no file of its own, by flying no run (:meth:`stop`'s ``found_done``). A
    stage a rerun redoes, or part-redoes, counts that rerun's seconds. A study summarized before this file existed
    keeps the stage times of its ``learn.json``.

    Parameters
    ----------
    out : Path
        The plant's study folder.
    clock : callable, optional
        Seconds, monotonic (default :func:`time.perf_counter`).
    """

    def __init__(self, out: Path, clock=time.perf_counter):
        self.path = out / STAGE_TIMES
        self.seconds: dict[str, float] = {}
        if self.path.is_file():
            self.seconds = json.loads(self.path.read_text())
        elif (out / "learn.json").is_file():
            self.seconds = dict(json.loads((out / "learn.json").read_text()).get("stage_seconds", {}))
        self._clock = clock
        self._name, self._t0, self._done = None, 0.0, False

    def start(self, name: str, done: Path | None) -> None:
        """Time stage ``name``; ``done`` is the file it writes as it ends (None: it has none)."""
        self._name, self._t0 = name, self._clock()
        self._done = done is not None and done.is_file()

    def stop(self, found_done: bool = False) -> None:
        """End the stage started last: record its seconds, s, unless it was found done and has seconds recorded.

        ``found_done``: the stage found all its work saved though it has no file of its own (the evaluation flew no
        run).
        """
        if (self._done or found_done) and self._name in self.seconds:
            return
        self.seconds[self._name] = round(self._clock() - self._t0, 1)
        write_json(self.path, self.seconds)


@locks_out_dir
def run_learn(settings: LearnSettings, out_dir="results/learn", models_dir="models", jobs: int = 2,
              progress=print) -> dict:
    """Run the learning study on one plant (see the module docstring); the summary, also in ``OUT/learn.json``.

    Parameters
    ----------
    settings : LearnSettings
    out_dir : path
        Results folder (the plant's study goes in ``out_dir/<plant>``); a rerun resumes what is there.
    models_dir : path
        Where the plant's best open-loop model is (:attr:`LearnPlant.best_open_loop`; left out if absent).
    jobs : int
        Processes flying at once (and trainings of the controls at once).
    progress : callable, optional
        Called with one line per step done.
    """
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ScenarioError(f"jobs must be an integer >= 1; found {jobs!r}")
    s, p = settings, settings.spec
    out = Path(out_dir) / s.tag
    out.mkdir(parents=True, exist_ok=True)
    recorded = out / "settings.json"
    mine = s.record()
    if recorded.is_file() and json.loads(recorded.read_text()) != mine:
        raise ScenarioError(f"{str(out)!r} holds a study with other settings ({recorded.read_text().strip()}); "
                            f"give another --out, or remove it")
    write_json(recorded, mine)
    t_start = time.perf_counter()
    timer = _StageTimes(out)
    flights: list[dict] = []
    curve: list[dict] = []
    trainings: list[dict] = []
    model = "nominal"
    for i in range(s.iterations + 1):
        it = out / f"it{i}"
        if i > 0:
            name = f"learn_{s.tag}_it{i}"
            timer.start(f"train {i}", it / f"{name}.json")
            _check_held_out(flights)          # what enters training, by content
            data = {"flights": len(flights), "flight_minutes": sum(f["seconds"] for f in flights) / 60.0,
                    "kind": "closed loop", "iterations": list(range(i))}
            dataset = flights if s.level == "ctbr" else _dataset_file(it / "data.npz", flights, p.vehicle)
            _say(progress, f"iteration {i}: training {name} on {len(flights)} flights "
                           f"({data['flight_minutes']:.1f} min)")
            rec = _stage(it / f"{name}.json", lambda: _train_item((s, dataset, it, name, min(jobs, 2), data)))
            trainings.append(rec)
            model = str(it / f"{name}.onnx")
            timer.stop()
        timer.start(f"curve {i}", it / "curve.json")
        curve.append(_stage(it / "curve.json", lambda: _curve_row(s, out, i, model, flights, jobs, progress)))
        timer.stop()
        if i < s.iterations:
            timer.start(f"fly {i}", it / "flights.npz")
            n_refs = len(training_refs_of(s, i))
            _say(progress, f"iteration {i}: flying {n_refs} training references with "
                           f"{'the nominal equations' if model == 'nominal' else Path(model).stem}")
            jobs_i = [FlightJob(s, "train", i, k, model) for k in range(n_refs)]
            flights = flights + _flights_stage(s, it / "flights.npz", jobs_i, jobs, progress, f"iteration {i}")
            timer.stop()
    final = model
    controls = {}
    if s.controls:
        timer.start("controls", out / "controls" / f"learn_{s.tag}_upper.json")
        controls = _controls(s, out, flights, final, jobs, progress)
        timer.stop()
    timer.start("evaluation", None)
    flown: list[dict] = []
    evaluation = _evaluate(s, out, models_dir, final, controls, jobs, progress, on_result=flown.append)
    timer.stop(found_done=not flown)      # a rerun that flies none of its runs finds the evaluation done
    summary = {"plant": p.key, "level": s.level, "label": evaluation["label"], "settings": mine, "curve": curve,
               "trainings": trainings, "controls": {k: v["record"] for k, v in controls.items()},
               "evaluation": evaluation, "final_model": Path(final).stem,
               "stage_seconds": dict(timer.seconds), "study_seconds": round(sum(timer.seconds.values()), 1),
               "wall_time_s": round(time.perf_counter() - t_start, 1), "date": time.strftime("%Y-%m-%d")}
    write_json(out / "learn.json", summary)
    return summary


def study_tag(summary: dict) -> str:
    """The folder name of a study's summary (``learn.json``): its plant, with ``_<level>`` beside the wrench level
    (:attr:`LearnSettings.tag`)."""
    level = summary.get("level", "wrench")
    return summary["plant"] if level == "wrench" else f"{summary['plant']}_{level}"


def training_refs_of(settings: LearnSettings, iteration: int):
    """The training references of one iteration (:func:`scenarios.studies.training_refs.training_references`)."""
    from .training_refs import training_references

    return training_references(iteration, settings.per_level, settings.seed)


def upper_flights(per_level: int) -> int:
    """Flights of ``figure8-fast`` the upper-bound control adds to the final model's: as many as an iteration flies
    at ``per_level`` references per family and speed level."""
    from .training_refs import references_per_iteration

    return references_per_iteration(per_level)


def _controls(s: LearnSettings, out: Path, flights: list[dict], final: str, jobs: int, progress) -> dict:
    """The two controls (two trainings at once): as many minutes of open-loop excitation as the final model flew, and
    the upper bound, trained on the final model's flights plus as many flights of ``figure8-fast`` as an
    iteration flies."""
    from sim.identification.excitation import make_dataset
    from sim.params import NoiseModel
    from sim.vehicles.vehicle import load_vehicle

    from ..sweeps.pool import run_pool

    p = s.spec
    c = out / "controls"
    seconds = sum(f["seconds"] for f in flights)
    todo = {}
    # Same minutes of open-loop excitation: pinnmpc data's flights on this plant, in the regime of its best model,
    # flown at the study's level (at ctbr through the plant's inner loop, pinnmpc data --level ctbr).
    n_open = max(2, math.ceil(seconds / OPEN_LOOP_FLIGHT_S - 1e-9))
    open_path = c / "openloop_data.npz"
    if not open_path.is_file():
        _say(progress, f"controls: {n_open} open-loop excitation flights of {OPEN_LOOP_FLIGHT_S:g} s "
                       f"({p.open_loop})")
        vehicle = load_vehicle(p.vehicle)
        ds = make_dataset(p.open_loop, n_open, OPEN_LOOP_FLIGHT_S, s.seed, noise=NoiseModel(),
                          fidelity=vehicle.named_fidelity("high" if p.high_fidelity else "nominal"),
                          plant=p.plant, vehicle=vehicle, workers=jobs, level=s.level)
        ds.save(open_path)
    todo["openloop"] = (open_path, {"flights": n_open, "flight_minutes": n_open * OPEN_LOOP_FLIGHT_S / 60.0,
                                    "kind": f"open-loop excitation ({p.open_loop})"})
    # The upper bound: the final model's flights plus one iteration's worth of flights of the evaluation reference
    # itself (perturbed, dithered), flown with the final model: what the loop would reach had it been allowed to fly
    # the test.
    n_up = upper_flights(s.per_level)
    _say(progress, f"controls: {n_up} flights of figure8-fast itself with {Path(final).stem} (upper bound only)")
    up = _flights_stage(s, c / "upper_flights.npz", [FlightJob(s, "upper", 0, k, final) for k in range(n_up)],
                        jobs, progress, "upper bound", held_out=False)
    up_data = flights + up if s.level == "ctbr" else _dataset_file(c / "upper_data.npz", flights + up, p.vehicle)
    todo["upper"] = (up_data, {"flights": len(flights) + len(up),
                               "flight_minutes": sum(f["seconds"] for f in flights + up) / 60.0,
                               "kind": f"the final model's flights plus {len(up)} of the evaluation reference "
                                       f"(upper bound)"})
    recs = {}
    items = []
    for k, (path, data) in todo.items():
        name = f"learn_{s.tag}_{k}"
        if (c / f"{name}.json").is_file():
            recs[k] = json.loads((c / f"{name}.json").read_text())
        else:
            items.append((k, (s, path, c, name, 1, data)))
    if items:
        _say(progress, f"controls: training {', '.join(f'learn_{s.tag}_{k}' for k, _ in items)}")

        def failed(item, reason):
            raise ScenarioError(f"training control {item[0]}: {reason}")

        if jobs > 1 and len(items) > 1:
            run_pool(_control_item, items, min(jobs, 2), lambda item, rec: recs.__setitem__(item[0], rec), failed)
        else:
            for item in items:
                recs[item[0]] = _control_item(item)
    return {k: {"record": recs[k], "model": str(c / f"learn_{s.tag}_{k}.onnx")} for k in todo}


def _control_item(item):
    return _train_item(item[1])


def _evaluate(s: LearnSettings, out: Path, models_dir, final: str, controls: dict, jobs: int, progress,
              on_result=None) -> dict:
    """Nominal, the best open-loop model, the final model and the controls on figure8-fast and the ladder.

    ``on_result`` is called with each run the evaluation's sweep flies (not with those it finds flown).
    """
    from ..closed_loop.library import ladder_speeds
    from ..sweeps.sweep import sweep
    from .versus import VERSUS_SCENARIO, WIN_FRACTION, summarize_plant, versus_specs

    from mpc.prediction.contract import declared_level

    models = ["nominal"]
    best = s.spec.best_open_loop_at(s.level)
    best = None if best is None else Path(models_dir) / best
    if best is not None and not (best.is_file() and declared_level(str(best)) == s.level):
        best = None             # absent, or at another level
    if best is not None:
        models.append(str(best))
    models.append(final)
    models += [c["model"] for c in controls.values()]
    # Every model on figure8-fast; the ladder for the nominal equations and the final model (the goal's rung test).
    ens = versus_specs(s.spec.versus, models, s.members, s.ladder_members, level=s.level)["ensemble"]
    lad = versus_specs(s.spec.versus, ["nominal", final], s.members, s.ladder_members, level=s.level)["ladder"]
    specs, tags = [], []
    for m, runs in ens.items():
        specs += runs
        tags += [(m, None)] * len(runs)
    for m, rungs in lad.items():
        for rung, runs in rungs.items():
            if rung != VERSUS_SCENARIO:
                specs += runs
                tags += [(m, rung)] * len(runs)
    _say(progress, f"evaluation: {len(specs)} runs ({len(models)} models on {VERSUS_SCENARIO} and the ladder)")
    results = sweep(specs, out / "evaluation", jobs=jobs, progress=progress is not None, on_result=on_result)
    _no_errors(results)
    mine = {i: {**r, "_model": m, "_rung": rung} for i, ((m, rung), r) in enumerate(zip(tags, results))}
    summary = summarize_plant(s.spec.versus, models, mine, ladder_speeds(), level=s.level)
    # The verdict is the final model's (summarize_plant's best could be a control, and the upper bound has seen the
    # evaluation reference): at least WIN_FRACTION below the nominal equations with the medians' intervals apart, and
    # the fastest rung flown at least the nominal equations'.
    rows = summary["models"]
    for row in rows.values():      # the study's own models by their path in its folder: the summary moves with it
        if row.get("path") and Path(row["path"]).is_relative_to(out):
            row["path"] = Path(row["path"]).relative_to(out).as_posix()
    fin, nom = rows[Path(final).stem], rows["nominal"]
    v = fin["versus_nominal"]
    sp_f, sp_n = fin["ladder"]["max_speed"]["speed_mps"], nom["ladder"]["max_speed"]["speed_mps"]
    ladder_ok = sp_n is None or (sp_f is not None and sp_f >= sp_n)
    summary["verdict"] = None if v is None else {
        "model": Path(final).stem, "fraction": v["fraction"], "fraction_ci95": v["fraction_ci95"], "apart": v["apart"],
        "goal": WIN_FRACTION, "max_speed_mps": sp_f, "nominal_max_speed_mps": sp_n, "ladder_ok": bool(ladder_ok),
        "met": bool(v["fraction"] >= WIN_FRACTION and v["apart"] and ladder_ok)}
    summary["roles"] = {Path(m).stem if m != "nominal" else m: role for m, role in
                        [("nominal", "nominal equations")]
                        + [(str(best), "best open-loop model")] * (best is not None)
                        + [(final, "final learned model")]
                        + [(c["model"], CONTROL_ROLES[k]) for k, c in controls.items()]}
    return summary


def format_learn(out: dict) -> str:
    """A study's summary as plain text: the learning curve, the controls and the evaluation's verdict."""
    from .versus import _mm

    level = out.get("level", "wrench")
    lines = [f"learning from flown flights on {out['label']}" + ("" if level == "wrench" else f", at the {level} level"),
             "learning curve (figure8-fast, median RMSE, mm):"]
    for r in out["curve"]:
        s = r["ensemble"]
        ci = s["median_ci95"]
        lines.append(f"  iteration {r['iteration']} ({r['model']}, {r['flight_minutes']:.1f} min of flights): "
                     f"{_mm(s['median'])}" + ("" if ci is None else f" ({_mm(ci[0])}-{_mm(ci[1])})")
                     + f", crashes {s['crashes']}/{s['runs']}")
    ev = out["evaluation"]
    lines.append("evaluation (figure8-fast; fastest ladder rung flown):")
    for name, row in ev["models"].items():
        s, v = row["ensemble"], row["versus_nominal"]
        role = ev["roles"].get(name, "")
        sp = None if row["ladder"] is None else row["ladder"]["max_speed"]["speed_mps"]
        vs = "" if v is None else f", {100 * v['fraction']:+.0f} % vs nominal"
        lines.append(f"  {name} [{role}]: {_mm(s['median'])} mm{vs}, crashes {s['crashes']}/{s['runs']}, "
                     f"max speed {'–' if sp is None else f'{sp:.2f} m/s'}")
    v = ev.get("verdict")
    if v is None:
        lines.append("  no verdict: the final model or the nominal equations lack two members with an RMSE")
    else:
        lines.append(f"  final model {v['model']}: {100 * v['fraction']:.0f} % better than nominal (goal "
                     f"{100 * v['goal']:.0f} %, intervals {'apart' if v['apart'] else 'overlap'}, ladder "
                     f"{'kept' if v['ladder_ok'] else 'lost speed'}): {'met' if v['met'] else 'missed'}")
    total = out.get("study_seconds", out["wall_time_s"])
    lines.append(f"study time {total / 60:.1f} min (this run {out['wall_time_s'] / 60:.1f} min)")
    return "\n".join(lines)


def publish_learn(study_dir, models_dir="models") -> Path:
    """Copy a finished study's ``learn.json``, its models' ONNX files and its flown flights (measurements in single
    precision) into ``models_dir/learn/<plant>``.

    The summary names its models by file stem (``final_model``), so that the main job finds the copies
    beside it (:func:`scenarios.studies.campaign.learned_models`).
    """
    import shutil

    study_dir = Path(study_dir)
    summary_path = study_dir / "learn.json"
    if not summary_path.is_file():
        raise ScenarioError(f"{str(study_dir)!r} holds no finished study (no learn.json)")
    out = json.loads(summary_path.read_text())
    dest = Path(models_dir) / LEARN_DIR / study_tag(out)
    dest.mkdir(parents=True, exist_ok=True)
    for onnx in sorted(study_dir.glob("it*/*.onnx")) + sorted(study_dir.glob("controls/*.onnx")):
        shutil.copyfile(onnx, dest / onnx.name)
    # The measured arrays in single precision (half the size, far finer than their noise); the references as they
    # were, so that the held-out check on the shipped flights hashes the same numbers as on the flown ones.
    for it in sorted(study_dir.glob("it*/flights.npz")):
        flights = [{**f, **{k: np.asarray(f[k], dtype=np.float32) for k in ("x", "rotor_speed", "command")}}
                   for f in load_flights(it)]
        save_flights(dest / f"flights_{it.parent.name}.npz", flights)
    write_json(dest / "learn.json", out)
    return dest
