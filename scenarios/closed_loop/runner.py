"""Closed-loop runs: scenario x controller x prediction model x plant x vehicle.

One run flies a plant (by default the reference simulator at 1 kHz) with
control at 100 Hz::

    from scenarios.closed_loop.runner import RunSpec, fly
    result, trace = fly(RunSpec("figure8-slow", "ltv", "models/proposed.onnx"))
    result, trace = fly(RunSpec("figure8-fast", "sqp", "oracle", plant="rotorpy-ideal"))

``result`` is the run's record (:class:`scenarios.closed_loop.record.RunRecord`, read like the JSON of
``pinnmpc fly --json``) and ``trace`` a dict of arrays (saved as ``.npz``). A
crash ends the run and is recorded; a run that cannot start (for example a
model whose hover linearization has no LQR gain) is recorded with its
``error``. :func:`scenarios.sweeps.sweep.sweep` runs many specs in a process pool or on Ray.

The loop itself (plant, sensor, controller, clock) is :mod:`scenarios.closed_loop.loop`.
Per control period ``k`` (``t = k dt``): the controller sees the measured
state (the true state, plus noise in ``+noise`` scenarios) and returns
``u``; with ``delay_steps = d`` the plant applies the input computed
``d`` periods earlier (hover input before that); the plant carries
rotor speeds across periods (motor lag).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mpc.controllers.factory import CONTROLLERS, DEFAULT_QP, HORIZON, QP_CONTROLLERS, make_controller
from mpc.prediction.models import EQUATION_MODELS, check_level_oracle, flown_model, model_name, model_params
from mpc.references.trajectory import flown_reference, reference_spec
from sim.params import DT
from sim.levels import DEFAULT_LEVEL, check_level
from sim.plants.named import PLANTS

from ..errors import ScenarioError
from .library import get_scenario
from .metrics import closed_loop_metrics, own_work_misses
from .record import NOT_FLOWN, RunRecord, input_hashes, not_flown

#: Longest MPC horizon a run accepts, steps (5 s): five times the 1 s over which the models' open-loop error is
#: measured, so well past where a learned model's prediction means anything; an SQP period at 500 stages takes
#: about 30 ms here (three control periods), and the QP's size, time and memory grow in proportion beyond.
MAX_HORIZON = 500


def check_horizon(horizon, name: str = "horizon") -> int:
    """``horizon`` as an int in 1..:data:`MAX_HORIZON` steps, or a :class:`ScenarioError` naming ``name``."""
    if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or not 1 <= horizon <= MAX_HORIZON:
        raise ScenarioError(f"{name} must be an integer number of 10 ms steps from 1 to {MAX_HORIZON} (5 s); "
                            f"found {horizon!r}")
    return int(horizon)
#: How compute time enters a run: ``ideal`` applies each input at once (deterministic); ``realtime`` applies it
#: after the call's measured wall time, rounded up to the simulator's 1 ms substep (see :func:`fly`).
TIMINGS = ("ideal", "realtime")
#: What the controllers see: ``none``, the true state (plus the scenario's noise); ``ekf``, the estimate of an
#: extended Kalman filter on their own model from motion capture and an IMU (:mod:`mpc.estimators.estimator`).
ESTIMATORS = ("none", "ekf")


def high_fidelity_equations(model: str, plant: str, scenario) -> bool:
    """True when ``model`` stands for the high-fidelity equations: the ``oracle`` on a ``+highfi`` scenario of the
    reference simulator, where the vehicle's motor lag, rotor drag and gyroscopic torque are the plant's true
    equations. Every other equation model is the nominal rigid-body equations."""
    return model == "oracle" and plant == "sim" and bool(scenario.high_fidelity)


def load_run_model(spec: "RunSpec"):
    """The prediction model of ``spec``: an equation model on its plant and vehicle, or its ONNX file.

    The ``oracle`` of a ``+highfi`` scenario on the reference simulator is the high-fidelity equations with the
    vehicle's motor lag (four rotor-speed states), rotor drag and gyroscopic torque.
    """
    hifi = spec.model == "oracle" and high_fidelity_equations(spec.model, spec.plant, get_scenario(spec.scenario))
    return flown_model(spec.model, spec.plant, spec.vehicle_data, high_fidelity=hifi, level=spec.level)


@dataclass(frozen=True)
class RunSpec:
    """What to fly: a scenario, a controller, a prediction model, a plant and a vehicle.

    ``scenario`` is a scenario name or a scenario file (``.toml``);
    ``model`` is ``"oracle"``, ``"nominal"``, ``"analytic:..."`` or an ONNX
    path; ``plant`` one of :data:`sim.plants.named.PLANTS`; ``vehicle`` a shipped
    vehicle's name or a vehicle file (None: the default vehicle); ``qp`` the
    QP solver of the LTV-MPC and the SQP (:data:`mpc.controllers.dense_qp.QP_SOLVERS`: ``"osqp"``
    or ``"daqp"``, the dense path), which the other controllers have no use
    for (see :attr:`qp_solver`); ``level`` the command level (:data:`sim.levels.LEVELS`): at ``ctbr`` and ``ctatt``
    the controller sends that command and the plant flies it through the vehicle's inner loop.
    """

    scenario: str
    controller: str
    model: str = "oracle"
    seed: int | None = None       # None: the scenario's own seed
    horizon: int = HORIZON        # MPC horizon, steps
    timing: str = "ideal"         # "ideal" (input applied at once) or "realtime" (after the measured compute time)
    member: int | None = None     # ensemble member (Scenario.member: its seed and a perturbed start); None: none
    plant: str = "sim"            # the plant flown
    vehicle: str | None = None    # vehicle name or file; None: the default vehicle
    estimator: str = "none"       # "none" (the state, plus the scenario's noise) or "ekf" (sensors and a filter)
    qp: str = DEFAULT_QP          # QP solver of the LTV-MPC and the SQP: "osqp" or "daqp"
    level: str = DEFAULT_LEVEL    # command level: "wrench", "ctbr" or "ctatt"
    # The SQP's scheme: "sqp" (it iterates) or "rti" (the real-time iteration: one prepared QP a period); None: the
    # timing's own (rti in real time, sqp in ideal timing).
    scheme: str | None = None

    def __post_init__(self):
        from sim.vehicles.vehicle import load_vehicle

        if self.plant not in PLANTS:
            raise ScenarioError(f"plant must be one of {', '.join(PLANTS)}; found {self.plant!r}")
        if self.vehicle is not None and not isinstance(self.vehicle, str):
            raise ScenarioError(f"vehicle must be a vehicle name or a .toml file; found {self.vehicle!r}")
        object.__setattr__(self, "_vehicle", load_vehicle(self.vehicle))   # raises naming a bad key or file
        if self.member is not None:
            if isinstance(self.member, bool) or not isinstance(self.member, int) or self.member < 0:
                raise ScenarioError(f"member must be an integer >= 0; found {self.member!r}")
            if self.seed is not None:
                raise ScenarioError("an ensemble member has its own seed; give member or seed, not both")
        if self.controller not in CONTROLLERS:
            raise ScenarioError(f"controller must be one of {', '.join(CONTROLLERS)}; found {self.controller!r}")
        check_horizon(self.horizon)
        if self.timing not in TIMINGS:
            raise ScenarioError(f"timing must be one of {', '.join(TIMINGS)}; found {self.timing!r}")
        if self.estimator not in ESTIMATORS:
            raise ScenarioError(f"estimator must be one of {', '.join(ESTIMATORS)}; found {self.estimator!r}")
        from mpc.controllers.dense_qp import QP_SOLVERS

        if self.qp not in QP_SOLVERS:
            raise ScenarioError(f"qp must be one of {', '.join(QP_SOLVERS)}; found {self.qp!r}")
        if self.scheme is not None:
            from mpc.controllers.sqp import SCHEMES

            if self.scheme not in SCHEMES:
                raise ScenarioError(f"scheme must be one of {', '.join(SCHEMES)} or None; found {self.scheme!r}")
            if self.controller != "sqp":
                raise ScenarioError(f"scheme is the SQP's; controller {self.controller!r} has none (found "
                                    f"scheme {self.scheme!r})")
        check_level(self.level)
        if self.level != DEFAULT_LEVEL:
            self._vehicle.inner_loop_at(self.level)       # raises naming the missing table
        sc = get_scenario(self.scenario)  # raises for an unknown name or a bad scenario file
        object.__setattr__(self, "_scenario_name", sc.name)
        if sc.high_fidelity and self.plant != "sim":
            hint = ("RotorPy's own motor lag and aerodynamics are already on with --plant rotorpy: fly the scenario "
                    "without its high-fidelity set-up" if self.plant == "rotorpy" else
                    "fly --plant rotorpy for RotorPy's motor lag and aerodynamics, or --plant sim for ours")
            raise ScenarioError(f"scenario {sc.name!r} asks for the reference simulator's high-fidelity set-up, which "
                                f"plant {self.plant!r} does not have ({hint})")
        if not isinstance(self.model, str) or not self.model:
            raise ScenarioError(f"model must be 'oracle', 'nominal' or the path of an .onnx file; found {self.model!r}")
        if self.model.startswith("analytic:"):
            from mpc.prediction.models import parse_analytic
            parse_analytic(self.model)
        elif self.model not in EQUATION_MODELS:
            path = Path(self.model)
            if path.suffix != ".onnx":
                raise ScenarioError(f"model must be 'oracle', 'nominal' or the path of an .onnx file; "
                                    f"found {self.model!r}")
            if not path.is_file():
                raise ScenarioError(f"model file {self.model!r} does not exist")
        elif self.model == "oracle":
            model_params(self.model, self.plant, self._vehicle)   # raises where the plant has no known equations
            check_level_oracle(self.plant, self.level, sc.high_fidelity)

    @property
    def model_name(self) -> str:
        return model_name(self.model)

    @property
    def qp_solver(self) -> str | None:
        """The QP solver the run's controller uses: :attr:`qp` for the LTV-MPC and the SQP, None for the others
        (the NMPC's IPOPT and the LQR solve no QP), so that their runs are the same whatever ``qp`` says."""
        return self.qp if self.controller in QP_CONTROLLERS else None

    @property
    def own_scheme(self) -> str | None:
        """:attr:`scheme` where it is not the timing's own (None there, and for the other controllers)."""
        from mpc.controllers.factory import timing_scheme

        return None if self.scheme in (None, timing_scheme(self.timing)) else self.scheme

    @property
    def vehicle_data(self):
        """The :class:`sim.vehicles.vehicle.Vehicle` flown."""
        return self._vehicle

    @property
    def scenario_name(self) -> str:
        """The scenario's name (a scenario file's own name, or its stem)."""
        return self._scenario_name

    @property
    def run_id(self) -> str:
        """File-name-safe identifier ``<scenario>__<controller>__<model>``.

        ``__s<seed>`` is appended for an explicit seed, ``__m<k>`` for ensemble member k, ``__realtime`` for
        that timing, ``__<plant>`` for a plant other than ``sim``, ``__<vehicle>`` for a vehicle other than
        the default, ``__ekf`` with the estimator and ``__<qp>`` for a QP solver other than OSQP (the LTV-MPC's
        and the SQP's runs only, :attr:`qp_solver`), so that runs by either solver can share a results folder.
        """
        from sim.vehicles.vehicle import DEFAULT_VEHICLE

        base = f"{self.scenario_name}__{self.controller}__{self.model_name}"
        if self.plant != "sim":
            base += f"__{self.plant}"
        if self._vehicle.name != DEFAULT_VEHICLE:
            base += f"__{self._vehicle.name}"
        if self.seed is not None:
            base += f"__s{self.seed}"
        if self.member is not None:
            base += f"__m{self.member}"
        if self.estimator != "none":
            base += f"__{self.estimator}"
        if self.qp_solver not in (None, DEFAULT_QP):
            base += f"__{self.qp_solver}"
        if self.level != DEFAULT_LEVEL:
            base += f"__{self.level}"
        if self.own_scheme is not None:
            base += f"__{self.own_scheme}"
        return base if self.timing == "ideal" else f"{base}__{self.timing}"


def plant_reference(spec: "RunSpec", sc, times: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The reference of scenario ``sc`` as ``spec``'s plant and vehicle can fly it: states (K, 12) at ``times``
    (K,), s, and the rotor speeds at the first time (4,) where the plant's motors lag (else None); see
    :func:`mpc.references.trajectory.flown_reference` (the high-fidelity map on a ``+highfi`` scenario of the
    reference simulator)."""
    return flown_reference(sc.reference(), times, spec.plant, spec.vehicle_data,
                           high_fidelity=high_fidelity_equations("oracle", spec.plant, sc))


#: The feed-forward a run prepared, for the next run of this process with the same key (:func:`_feedforward_key`).
_PREPARED: dict = {}


def _feedforward_key(spec: "RunSpec", sc, inputs: dict, K: int, sqp) -> str | None:
    """What a run's feed-forward depends on, as one string: the spec but its member and seed, the scenario but its
    start and seed, the files read (by content), the steps flown and the SQP settings; None if that cannot be
    written as JSON."""
    import dataclasses

    ident = {"spec": asdict(dataclasses.replace(spec, member=None, seed=None)), "inputs": inputs, "steps": K,
             "sqp": sqp, "scenario": {k: v for k, v in sc.to_dict().items() if k not in ("x0", "seed")}}
    try:
        return json.dumps(ident, sort_keys=True, default=repr)
    except (TypeError, ValueError):
        return None


def flown_qp(spec: "RunSpec", sqp: dict | None = None) -> str | None:
    """The QP solver a run of ``spec`` flies with: :attr:`RunSpec.qp_solver`, or for the SQP the ``"qp"`` of the
    other settings ``sqp`` (:func:`fly`) when they give one; None for a controller without a QP."""
    if spec.controller == "sqp" and sqp and "qp" in sqp:
        return sqp["qp"]
    return spec.qp_solver


def fly(spec: RunSpec, progress: bool = False, scenario=None, model=None, ekf_config=None,
        sqp: dict | None = None) -> tuple[RunRecord, dict]:
    """Fly one closed-loop run; ``(record, trace)``: its :class:`scenarios.closed_loop.record.RunRecord` and a dict
    of arrays.

    The run is composed top-down from its parts, each built where it is owned: the scenario
    (:func:`run_scenario`), the prediction model (:func:`load_run_model`), the plant with the scenario's
    disturbances (:meth:`Scenario.plant`), the reference the plant can fly (:func:`plant_reference`) and the start
    on it (:meth:`Scenario.start_state`), the controller (:func:`mpc.controllers.factory.make_controller`), the
    estimator (:func:`scenarios.closed_loop.loop.make_estimator`), then the loop
    (:func:`scenarios.closed_loop.loop.fly_loop`) and the record.

    Raises only for bad input (unknown names, a model that fails the
    contract); everything that happens in flight is recorded.

    ``scenario`` (a :class:`scenarios.closed_loop.library.Scenario`) replaces the named
    scenario's data, for example with a perturbed initial state; ``model`` (a
    loaded :class:`mpc.prediction.models.PredictionModel`) saves loading ``spec.model`` again. ``ekf_config`` (an
    :class:`mpc.estimators.estimator.EKFConfig`) replaces the estimator's default tuning. ``sqp``: other
    :class:`mpc.controllers.sqp.SQPSettings` values for the SQP (:func:`mpc.controllers.factory.make_controller`;
    benchmarks compare its paths).

    The result's ``qp`` names the QP solver the controller used (:func:`flown_qp`): ``spec.qp`` for the LTV-MPC
    and the SQP (or the ``"qp"`` of ``sqp``), None for the NMPC and the LQR.
    """
    from mpc.controllers.ltv import DEADLINE_STATUS
    from mpc.controllers.sqp import SQPMPC
    from mpc.controllers.timing import period_stats

    from .loop import IdealClock, RealtimeClock, StateSensor, Trace, fly_loop, make_estimator

    sc = run_scenario(spec, scenario)
    inputs = input_hashes(spec)           # what is flown: taken as the run starts, stored in its result
    own = scenario is None and model is None      # all that is flown comes from the spec (and its files)
    if model is None:
        model = load_run_model(spec)      # contract errors raise here, before anything flies
    if model.level != spec.level:
        raise ScenarioError(f"model {model.name!r} takes commands at the {model.level!r} level; the run flies at "
                            f"{spec.level!r}")
    vehicle = spec.vehicle_data
    plant = sc.plant(spec.plant, vehicle, spec.level)  # a missing RotorPy raises here, before anything flies
    K = sc.steps
    t_all = DT * np.arange(K + 1)
    # The scenario's offsets from its reference at t = 0 are kept; the reference part of its start is the one this
    # plant can fly (with its motors at the reference's speeds where they lag).
    X_ref, n0 = plant_reference(spec, sc, t_all)
    own_map = high_fidelity_equations("oracle", spec.plant, sc)
    x0 = sc.start_state(reference_spec(spec.plant, vehicle), X_ref[0] if own_map else None)
    error = None
    t0 = time.perf_counter()
    realtime = spec.timing == "realtime"
    try:
        if spec.scheme is not None:
            sqp = {"scheme": spec.scheme, **(sqp or {})}      # the settings given win
        ctrl = make_controller(spec.controller, model, sc.reference(), spec.horizon, spec.timing, vehicle,
                               spec.estimator, sqp=sqp, qp=spec.qp)
        # The reference is known before take-off: its feed-forward is fitted now (or taken from this process's
        # last run of the same model and reference: an ensemble's members differ only in their start and seed),
        # and a controller that plans ahead (the SQP) makes its first plan from the state the vehicle stands in.
        ff_key = _feedforward_key(spec, sc, inputs, K, sqp) if own else None
        if ff_key is not None and ff_key in _PREPARED:
            ctrl.ff.adopt(_PREPARED[ff_key])
        ctrl.prepare(K * DT, x0=x0.copy())
        if ff_key is not None and ff_key not in _PREPARED:
            _PREPARED.clear()                  # one entry: runs of a sweep come model by model
            _PREPARED[ff_key] = ctrl.ff.prepared()
    except ValueError as e:  # e.g. no LQR gain for this model's hover linearization
        error = f"{type(e).__name__}: {e}"
        ctrl = None
    if ctrl is not None:
        estimator = None
        if spec.estimator == "ekf":
            plant, estimator = make_estimator(ctrl, model, plant, sc.sensor_suite(), X_ref[0], ekf_config)
        plant.reset(x0, rotor_speed=n0)
        sensor = StateSensor(sc.noise, np.random.default_rng([sc.seed, 0x5EED]))
        # Before the first (delayed or computed) command arrives, the vehicle's own hover thrust holds it.
        clock = (RealtimeClock if realtime else IdealClock)(plant.hover_input, sc.delay_steps)
        bar = None
        if progress:
            from tqdm import tqdm

            def bar(r):
                return tqdm(r, desc=spec.run_id, unit="step", leave=False)
        tr = fly_loop(plant, sensor, ctrl, clock, X_ref, K, progress=bar, estimator=estimator)
    else:
        tr = Trace.empty(K)
    k_end = tr.steps
    wall = time.perf_counter() - t0
    # With an estimator, the time charged per call is the filter's plus the controller's.
    charged_s = tr.solve_s if tr.estimator_s is None else tr.solve_s + np.nan_to_num(tr.estimator_s)
    if error is None:
        metrics = closed_loop_metrics(tr.x[:k_end + 1], X_ref[:k_end + 1], charged_s[:k_end],
                                      tr.solver_failed[:k_end], tr.lqr_fallback[:k_end], tr.crash_step,
                                      tr.crash_reason,
                                      impulse_start_s=None if sc.impulse is None else sc.impulse.start_s,
                                      planned_steps=K, called=tr.called[:k_end] if realtime else None)
    else:
        metrics = dict(NOT_FLOWN)
    pre = None if ctrl is None else ctrl.preflight    # the SQP's plan before take-off: what it did, and how long
    # the SQP's real-time iteration is named (the iterating SQP's records stay as they were)
    scheme = {"scheme": ctrl.s.scheme} if isinstance(ctrl, SQPMPC) and ctrl.s.scheme != "sqp" else {}
    failed, lqr_fb = tr.solver_failed[:k_end], tr.lqr_fallback[:k_end]
    # Real time: periods whose plan could not be made before the deadline (the fallback's input went out).
    late = int(np.sum(failed & (tr.status[:k_end] == DEADLINE_STATUS))) if realtime and error is None else None
    causes = {}                            # why the solver failed, most frequent first
    for status in tr.status[:k_end][failed]:
        causes[str(status)] = causes.get(str(status), 0) + 1
    causes = dict(sorted(causes.items(), key=lambda kv: (-kv[1], kv[0])))
    estimated = {}
    if tr.x_estimate is not None:
        est_ms = 1e3 * tr.estimator_s[:k_end][tr.called[:k_end]]
        nees_k = tr.nees[:k_end]
        estimated = {"estimator_ms": {"median": float(np.median(est_ms)), "max": float(np.max(est_ms))}
                     if est_ms.size else None,
                     "nees_mean": float(np.nanmean(nees_k)) if np.any(np.isfinite(nees_k)) else None}
    sha = inputs.get("model")
    record = RunRecord(
        run_id=spec.run_id, scenario=sc.name, controller=spec.controller, model=spec.model_name,
        model_file=None if sha is None else str(spec.model), model_sha256=sha, seed=sc.seed, member=spec.member,
        horizon=spec.horizon, timing=spec.timing, plant=spec.plant, vehicle=vehicle.name, estimator=spec.estimator,
        qp=flown_qp(spec, sqp), **scheme, level=spec.level, inputs_sha256=inputs, **metrics,
        latency_ms=period_stats(tr.latency_s[:k_end]) if error is None else None,
        own_work_misses=own_work_misses(tr.load_cpu_s[:k_end], tr.called[:k_end]) if error is None else None,
        shifted_plan=int(np.sum(failed & ~lqr_fb)), deadline_fallbacks=late, failure_causes=causes,
        preflight=None if pre is None else {"iterations": int(pre.iterations), "status": pre.status},
        preflight_ms=None if pre is None else 1e3 * pre.solve_time_s, error=error, wall_time_s=wall,
        scenario_spec=sc.to_dict(), plant_spec=plant.describe(), vehicle_spec=vehicle.to_dict(), **estimated)
    trace = {"t": t_all[:k_end + 1], "x": tr.x[:k_end + 1], "x_ref": X_ref[:k_end + 1],
             "x_measured": tr.x_measured[:k_end], "u": tr.u[:k_end], "u_command": tr.u_command[:k_end],
             "solve_s": tr.solve_s[:k_end], "latency_s": tr.latency_s[:k_end], "load_s": tr.load_s[:k_end],
             "load_cpu_s": tr.load_cpu_s[:k_end],
             "called": tr.called[:k_end],
             "iterations": tr.iterations[:k_end], "status": tr.status[:k_end], "solver_failed": failed,
             "lqr_fallback": lqr_fb, "rotor_speed": tr.rotor_speed[:k_end + 1]}
    if tr.x_estimate is not None:
        for name in ("x_estimate", "estimate_std", "disturbance", "gyro_bias", "gyro_bias_true", "accel_bias",
                     "accel_bias_true", "nees", "estimator_s"):
            trace[name] = getattr(tr, name)[:k_end]
    return record, trace


def run_scenario(spec: RunSpec, scenario=None):
    """The scenario ``spec`` flies: ``scenario`` when given, else the named one (its ensemble member, or with
    ``spec.seed``)."""
    if scenario is not None:
        return scenario
    if spec.member is not None:
        return get_scenario(spec.scenario).member(spec.member)
    return get_scenario(spec.scenario, spec.seed)


def fly_for_sweep(spec: RunSpec) -> tuple[RunRecord, dict]:
    """``fly(spec)`` for a sweep (:mod:`scenarios.sweeps.sweep`): a run that cannot fly is recorded (its error) and
    the sweep goes on.

    This is the unit of work of every engine (a process-pool task, a Ray
    task); the sweep stamps the result with its :func:`cache_key`.
    """
    try:
        return fly(spec)
    except Exception as e:  # noqa: BLE001 - a run that cannot fly is recorded and the sweep goes on
        return not_flown(spec, f"{type(e).__name__}: {e}"), {}


def spec_dict(spec: RunSpec) -> dict:
    """JSON-ready form of a :class:`RunSpec`."""
    return asdict(spec)
