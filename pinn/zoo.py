"""The model zoo: learned models from millimetres of open-loop error to divergence.

The shipped models are all good: their 100-step position errors lie within
a decade. To see how open-loop error becomes closed-loop failure, the zoo
spans the whole range by honest means, each recorded in its manifest entry:

* early checkpoints of each architecture (one training run, copies kept
  after 1, 2, 4 ... epochs);
* smaller networks, fewer trajectories, noisier data;
* variants that reproduce the failure modes the paper reports:
  a Fourier encoding of the angles up to 4096 rad^-1 (``fourier_hf``), a
  modular network whose translation module does not see the attitude
  (``modular_decoupled``), a network that outputs the next state itself
  instead of an increment, trained on one-step loss (``absolute``);
* unbounded (softplus) hidden layers, with a large residual scale, with which
  a model can leave any bound in a rollout.

Every zoo model is trained on the small-regime excitation data and measured
on the same test split (the default dataset's, seed 0); variants with less or
noisier data train on other seeds (seed 1), so no test trajectory is seen in
training. ``pinnmpc zoo`` trains them all and writes ``models/zoo``:
``NAME.onnx`` and ``NAME.jac.onnx`` (float64, flown by every controller) and
``manifest.json`` (command, seed, settings and test metrics of each file).

A trained model that no controller can be built on is not flown: when its
hover linearization is not stabilizable (the LQR behind every MPC's terminal
cost and fallback has no solution) it is recorded, with the reason and its
metrics, in ``refused.json`` instead of the manifest, and its files are removed.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

#: Training budget of the zoo: the quick profile (8 epochs of 40 steps).
ZOO_PROFILE = "quick"
#: Test data of every zoo model: the default small-regime dataset (its test split).
TEST_DATA = {"regime": "small", "n_traj": 100, "duration_s": 10.0, "seed": 0, "noise_mult": 1.0}


@dataclass(frozen=True)
class ZooRun:
    """One training run of the zoo, and the models it yields.

    Parameters
    ----------
    name : str
        Stem of the run; each kept checkpoint is ``NAME_eK`` (K epochs), or
        ``NAME`` alone when the run keeps only its last epoch.
    arch : str
        Architecture (``pinn.models.ALL_ARCHITECTURES``).
    checkpoints : tuple of int
        Epoch counts to keep (the last must be the profile's epochs to keep the final model).
    overrides : dict
        TrainConfig fields (width, depth, variant settings, budget).
    n_traj : int
        Training trajectories of 10 s (100 = the default dataset).
    noise_mult : float
        Multiplies every measurement-noise standard deviation of the data.
    data_seed : int
        Seed of the training data (0 = the default dataset, also the test data).
    why : str
        What this run adds to the zoo.
    """

    name: str
    arch: str
    checkpoints: tuple = (8,)
    overrides: dict = field(default_factory=dict)
    n_traj: int = 100
    noise_mult: float = 1.0
    data_seed: int = 0
    profile: str = ZOO_PROFILE
    why: str = ""

    def model_names(self) -> list[str]:
        """Names of the models this run yields, one per checkpoint."""
        if len(self.checkpoints) == 1:
            return [self.name]
        return [f"{self.name}_e{k}" for k in self.checkpoints]

    def data_spec(self) -> dict:
        return {"regime": "small", "n_traj": self.n_traj, "duration_s": 10.0, "seed": self.data_seed,
                "noise_mult": self.noise_mult}


#: The zoo, run by run.
RUNS = (
    ZooRun("baseline", "baseline", (1, 2, 4, 8), why="checkpoints of the Baseline recipe"),
    ZooRun("proposed", "proposed", (1, 2, 4, 8), why="checkpoints of the Proposed recipe (curriculum)"),
    ZooRun("fourier", "fourier", (2, 8), why="checkpoints of the Fourier architecture (up to 256 rad^-1)"),
    ZooRun("modular", "modular", (2, 8), why="checkpoints of the Modular architecture (coupled modules)"),
    ZooRun("baseline_long", "baseline", (40,), {"epochs": 40, "steps_per_epoch": 60, "batch": 1024},
           why="a longer Baseline run: the accurate end of the zoo"),
    ZooRun("small_h16", "baseline", (8,), {"hidden": 16, "layers": 2}, why="a small network (16 x 2)"),
    ZooRun("small_h8", "baseline", (8,), {"hidden": 8, "layers": 1}, why="a tiny network (8 x 1)"),
    ZooRun("data_5traj", "baseline", (8,), n_traj=5, data_seed=1, why="5 training trajectories instead of 100"),
    ZooRun("data_noise10", "baseline", (8,), noise_mult=10.0, data_seed=1, why="10x the measurement noise"),
    ZooRun("data_noise30_20traj", "baseline", (8,), n_traj=20, noise_mult=30.0, data_seed=1,
           why="20 trajectories with 30x the measurement noise"),
    ZooRun("fourier_hf", "fourier", (2, 8), {"fourier_max": 12},
           why="paper failure mode II: angles encoded up to 4096 rad^-1"),
    ZooRun("modular_decoupled", "modular", (2, 8), {"coupled": False},
           why="paper failure mode I: the translation module does not see the rotational states"),
    ZooRun("absolute", "absolute", (2, 8), why="next state as output (no residual form), one-step loss"),
    ZooRun("softplus_gain10", "baseline", (8,), {"activation": "softplus", "gain": 10.0},
           why="unbounded softplus layers with a 10x residual scale"),
    ZooRun("fourier_softplus", "fourier", (2, 8), {"activation": "softplus"},
           why="the Fourier architecture (up to 256 rad^-1) with unbounded softplus layers, beside fourier_hf_softplus"),
    ZooRun("fourier_hf_softplus", "fourier", (2, 8), {"fourier_max": 12, "activation": "softplus"},
           why="paper failure mode II with unbounded softplus layers"),
    ZooRun("absolute_softplus", "absolute", (2, 8), {"activation": "softplus"},
           why="next state as output with unbounded softplus layers"),
)


def zoo_names(runs=RUNS) -> list[str]:
    """Every zoo model name, in run order."""
    return [n for r in runs for n in r.model_names()]


def run_command(run: ZooRun, out: Path) -> str:
    """The command that trains ``run`` alone (and writes its models and manifest entries)."""
    return f"pinnmpc zoo --only {run.name} --out {out}"


def _dataset(spec: dict):
    from sim.identification.excitation import make_dataset
    from sim.params import NoiseModel

    base = NoiseModel()
    noise = NoiseModel(**{f.name: getattr(base, f.name) * spec["noise_mult"] for f in dataclasses.fields(base)})
    return make_dataset(spec["regime"], spec["n_traj"], spec["duration_s"], spec["seed"], noise=noise)


def train_run(run: ZooRun, out: Path, test_ds=None, threads: int = 1, progress: bool = False) -> dict:
    """Train one zoo run, export each kept checkpoint and return their manifest entries ``{name: entry}``."""
    import torch

    from mpc.prediction.contract import config_hash
    from sim.params import THETA_NAMES

    from .metrics import test_metrics
    from .export import export_model
    from .train import make_config, train

    cfg = make_config(run.arch, run.profile, 0, threads=threads, **run.overrides)
    if run.checkpoints[-1] != cfg.epochs:
        raise ValueError(f"zoo run {run.name}: the last checkpoint must be the final epoch {cfg.epochs}; "
                         f"found {run.checkpoints}")
    spec = run.data_spec()
    ds = _dataset(spec)
    test_ds = _dataset(TEST_DATA) if test_ds is None else test_ds
    res = train(ds, cfg, progress=progress, checkpoints=run.checkpoints)
    spec = {**spec, "fingerprint": ds.fingerprint()}
    entries = {}
    for name, epochs in zip(run.model_names(), run.checkpoints):
        model = res.checkpoints[epochs]
        metrics = test_metrics(model, test_ds)
        training_config = {"name": name, "recipe": run.arch if run.arch != "absolute" else "baseline",
                           "train": cfg.to_dict(), "data": spec, "zoo": {"run": run.name, "epochs": epochs}}
        paths = export_model(model, out, name, training_config, spec["seed"], metrics, res.stats, torch_file=False)
        hist = res.history[epochs - 1]
        entries[name] = {
            "files": {k: Path(v).name for k, v in paths.items()},
            "command": run_command(run, out),
            "run": run.name, "why": run.why, "epochs": epochs, "seed": 0,
            "architecture": run.arch, "profile": run.profile, "settings": cfg.to_dict(),
            "data": spec, "test_data": TEST_DATA,
            "config_hash": config_hash(training_config),
            "metrics": metrics,
            "theta": dict(zip(THETA_NAMES, hist["theta"])),
            "theta_err_pct": hist["theta_err_pct"],
            "training_seconds": round(res.seconds, 1),
            "torch_version": torch.__version__,
        }
    return entries


def flight_check(path) -> str | None:
    """None when every controller can fly the model at ``path``, else the reason none can: the check of
    ``pinnmpc check-model`` (:func:`mpc.controllers.readiness.readiness`, the LQR about the model's hover trim)."""
    from mpc.prediction.models import load_model
    from mpc.controllers.readiness import readiness

    why = [r.reason for r in readiness(load_model(str(path))).values() if not r.flies]
    return why[0] if why else None


def sort_refused(out, names) -> dict:
    """Move the models of ``names`` that fail :func:`flight_check` from ``out/manifest.json`` to ``out/refused.json``.

    Their ONNX files are removed (nothing flies them); their entries keep the
    command, settings and metrics, plus the ``reason``. Returns the refused entries.
    """
    import json

    from .manifest import update_manifest

    out = Path(out)
    manifest = json.loads((out / "manifest.json").read_text())
    refused = {}
    for name in names:
        entry = manifest.get(name)
        if entry is None:
            continue
        why = flight_check(out / entry["files"]["onnx"])
        if why is None:
            continue
        for f in entry["files"].values():
            (out / f).unlink(missing_ok=True)
        refused[name] = {**{k: v for k, v in entry.items() if k != "files"}, "reason": why}
        del manifest[name]
    if refused:
        (out / "manifest.json").write_text(json.dumps(dict(sorted(manifest.items())), indent=2) + "\n")
        for name, entry in refused.items():
            update_manifest(out, name, entry, file="refused.json")
    return refused


def _job(args):
    run, out = args
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    return train_run(run, out)


def train_zoo(out, runs=RUNS, jobs: int = 1, progress: bool = True) -> dict:
    """Train ``runs`` (``jobs`` at a time, one torch thread each) into ``out``; update ``out/manifest.json``.

    Returns
    -------
    dict
        The manifest entries written, by model name.
    """
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    from .manifest import update_manifest

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be an integer >= 1; found {jobs!r}")
    written = {}
    bar = tqdm(total=len(runs), desc="zoo", unit="run", disable=not progress)
    t0 = time.perf_counter()

    def record(entries):
        for name, entry in entries.items():
            update_manifest(out, name, entry)
            written[name] = entry
        bar.update()

    if jobs == 1:
        test_ds = _dataset(TEST_DATA)
        for r in runs:
            record(train_run(r, out, test_ds))
    else:
        with ProcessPoolExecutor(jobs) as ex:
            for entries in ex.map(_job, [(r, out) for r in runs]):
                record(entries)
    bar.close()
    refused = sort_refused(out, list(written))
    for name in refused:
        written[name] = {**written[name], "refused": refused[name]["reason"]}
    written["_seconds"] = time.perf_counter() - t0
    return written
