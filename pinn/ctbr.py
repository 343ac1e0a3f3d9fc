"""Learning at the ``ctbr`` level: the level's nominal model plus a network, from flights commanded in collective
thrust and body rates.

The model (:data:`CTBR_ARCH`) is :class:`pinn.flights.LaggedCtbrPhysics` (the rigid body whose body rates follow
their commands as first-order lags with the vehicle file's time constants) plus a network on the body rates and the
velocity, with a register of the last :data:`CTBR_HISTORY` commands and rates, trained on open-loop rollouts
(:func:`pinn.flights.train_flight_model`). Two sources of flights feed it:

* the flights the learning study flies (:mod:`scenarios.studies.learn`, ``pinnmpc learn --level ctbr``);
* an excitation dataset flown at ``ctbr`` (``pinnmpc data --level ctbr``, :func:`dataset_series`), trained by
  ``pinnmpc train --arch ctbr``: the open-loop learned model of the level.

This module imports torch only when it trains, so that the studies read its settings without it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Periods of commands and body rates in the model's register. Its period costs the SQP, on RotorPy's figure8-fast
#: (one run each, idle machine): 9.2 ms with none, 14.8 with 1, 18.8 with 2, 31.8 with 4 (the nominal model 7.3):
#: 2 is the longest memory the learning study can fly at about the wrench level's pace.
CTBR_HISTORY = 2
#: What is learned at ``ctbr`` (stored as the model file's ``architecture``).
CTBR_ARCH = f"nominal ctbr physics + network, history {CTBR_HISTORY}"
#: Training budgets by profile: :class:`pinn.flights.FlightTrainConfig` settings changed from its own.
CTBR_PROFILES = {"scaled": {"epochs": 12}, "full": {"epochs": 12}, "quick": {},
                 "smoke": {"epochs": 2, "steps_per_epoch": 4, "windows": 32, "hidden": 16, "layers": 2}}


@dataclass(frozen=True)
class FlownSeries:
    """A flown flight as the ``ctbr`` learner takes it (:func:`pinn.flights.train_flight_model`'s flights).

    ``x`` (n, 12) the measured states; ``u`` (n, 4) the command in effect from each sample to the next (the last row
    repeats the one before); ``x_ok`` (n,) the finite samples (a crashed flight's are cut before its first
    non-finite state).
    """

    name: str
    x: np.ndarray
    u: np.ndarray
    x_ok: np.ndarray


def dataset_series(ds) -> dict[str, list[FlownSeries]]:
    """The trajectories of an excitation dataset (:class:`sim.identification.excitation.Dataset`) as flights, by
    split (``train``, ``val``, ``test``, the dataset's own).

    Trajectory ``i`` becomes ``traj{i}``: its measured states ``x`` then the last ``x_next`` (n_steps + 1 samples),
    its commands ``u`` with the last repeated. Every sample of a simulated dataset is measured.
    """
    from sim.identification.excitation import SPLIT_NAMES

    out: dict[str, list[FlownSeries]] = {k: [] for k in SPLIT_NAMES}
    for i in range(ds.n_traj):
        x = np.concatenate([ds.x[i], ds.x_next[i, -1:]])
        u = np.concatenate([ds.u[i], ds.u[i, -1:]])
        out[SPLIT_NAMES[int(ds.split[i])]].append(FlownSeries(f"traj{i}", x, u, np.ones(len(x), dtype=bool)))
    return out


def ctbr_physics(plant: str, vehicle):
    """The ``ctbr`` nominal model in torch (:class:`pinn.flights.LaggedCtbrPhysics`) of ``vehicle`` (a
    :class:`sim.vehicles.vehicle.Vehicle`) on ``plant``, and the vehicle's ``theta`` written into the model file."""
    from mpc.prediction.models import model_params

    from .flights import LaggedCtbrPhysics

    params = model_params("nominal", plant, vehicle)
    response = vehicle.inner_loop_at("ctbr").response()
    theta = {k: float(getattr(params, k)) for k in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq")}
    return LaggedCtbrPhysics(params.m, params.g, params.c_d, response.rate_tau), theta


@dataclass
class CtbrTraining:
    """What :func:`train_ctbr` gives: the trained result (:class:`pinn.flights.FlightTrainResult`), the physics it
    started from, the vehicle's ``theta``, the config and the test flights' open-loop errors at h = 1, 10 and 50
    (:meth:`sim.flightlogs.logbench.PredictionErrors.to_dict`)."""

    result: object
    physics: object
    theta: dict
    config: object
    test_errors: dict

    @property
    def rate_tau_s(self) -> list[float]:
        """The physics' rate time constants, s."""
        return [float(1.0 / v) for v in self.physics.inv_tau]


def train_ctbr(split: dict, plant: str, vehicle, seed: int = 0, profile: str = "full", progress=None
               ) -> CtbrTraining:
    """Train :data:`CTBR_ARCH` on ``split`` (``{"train", "val", "test"}``: lists of :class:`FlownSeries` at ``ctbr``)
    for ``vehicle`` flown on ``plant``; the epoch with the best validation score is kept, the test flights scored.

    The caller sets torch's thread count. Raises ``ValueError`` naming the split that is empty.
    """
    from sim.flightlogs.logbench import prediction_errors

    from .flights import FlightTrainConfig, flight_step, train_flight_model

    for k, what in (("train", "training"), ("val", "validation"), ("test", "test")):
        if not split.get(k):
            raise ValueError(f"the flights have no {what} flight: the ctbr learner needs one of each split")
    if profile not in CTBR_PROFILES:
        raise ValueError(f"profile must be one of {', '.join(CTBR_PROFILES)}; found {profile!r}")
    physics, theta = ctbr_physics(plant, vehicle)
    cfg = FlightTrainConfig(history=CTBR_HISTORY, seed=seed, **CTBR_PROFILES[profile])
    res = train_flight_model(split["train"], split["val"], None, cfg, physics=physics, progress=progress)
    step, start = flight_step(res.model, np.ones(4))
    test = prediction_errors(step, split["test"], start=start).to_dict()
    return CtbrTraining(res, physics, theta, cfg, test)
