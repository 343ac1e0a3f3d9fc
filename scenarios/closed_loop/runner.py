"""Closed-loop runs: scenario x controller x prediction model x plant x vehicle.

One run flies a plant (by default the reference simulator at 1 kHz) with
control at 100 Hz::

    from scenarios.closed_loop.runner import RunSpec, fly
    result, trace = fly(RunSpec("figure8-slow", "ltv", "models/proposed.onnx"))
    result, trace = fly(RunSpec("figure8-fast", "sqp", "oracle", plant="rotorpy-ideal"))

``result`` is a JSON-ready dict with the fields of ``pinnmpc fly --json`` and ``trace`` a dict of arrays (saved as ``.npz``). A
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

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sim.params import DT
from sim.plants.named import PLANTS

from ..errors import ScenarioError
from .library import get_scenario
from .metrics import closed_loop_metrics

CONTROLLERS = ("nmpc", "sqp", "ltv", "lqr")
#: Metrics of a run that never flew (its controller could not be built, or the run raised).
NOT_FLOWN = {"rmse_position_m": None, "max_position_error_m": None, "settled_error_m": None, "rmse_yaw_rad": None,
             "crashed": False, "crash_time_s": None,
             "crash_reason": None, "solve_ms": None, "deadline_misses": 0, "solver_failures": 0, "fallbacks": 0,
             "steps": 0}
#: MPC horizon of every run unless stated, steps of DT.
HORIZON = 30
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
#: Model names that stand for equations rather than a file: the plant's own equations where they are known, and
#: the nominal rigid-body equations with the vehicle's values.
EQUATION_MODELS = ("oracle", "nominal")
#: The controllers that solve a QP each period, and so take a QP solver (:attr:`RunSpec.qp`).
QP_CONTROLLERS = ("ltv", "sqp")
#: The QP solver of a run unless stated (the solver of a run's record and cache key before the choice existed).
DEFAULT_QP = "osqp"


def model_name(model: str) -> str:
    """The name a model has in results: ``oracle``, ``nominal``, ``analytic-<factors>``, or a file's stem."""
    if model.startswith("analytic:"):
        from mpc.prediction.models import analytic_name, parse_analytic
        return analytic_name(parse_analytic(model))
    return model if model in EQUATION_MODELS else Path(model).stem


def model_params(model: str, plant: str, vehicle):
    """The parameters (:class:`sim.QuadParams`) of an equation model on ``plant`` flying ``vehicle``.

    ``oracle``: the plant's own equations: on ``sim``, the equations
    with the vehicle's values (on a ``+highfi`` scenario with the vehicle's
    high-fidelity effects too, :func:`high_fidelity_equations`); on ``rotorpy-ideal``, the same with no drag (that set-up has
    none); ``rotorpy`` (motor lag and aerodynamics) has no known equations
    and refuses it. ``nominal`` and ``analytic:...``: the nominal equations
    with the vehicle's values (scaled).
    """
    from mpc.prediction.models import parse_analytic
    from sim.params import THETA_NAMES
    from sim.plants.named import known_equations

    p = vehicle.params
    if model == "oracle":
        own = known_equations(plant, p)
        if own is None:
            raise ScenarioError(f"plant {plant!r} has no known equations, so it has no oracle; fly --model nominal "
                                f"(the rigid-body equations with the vehicle's values) or a learned model")
        return own
    if model == "nominal":
        return p
    factors = parse_analytic(model)
    return p.with_theta([getattr(p, n) * factors.get(n, 1.0) for n in THETA_NAMES])


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
    from mpc.prediction.models import AnalyticModel, load_model

    if spec.model in EQUATION_MODELS or spec.model.startswith("analytic:"):
        fidelity = None
        if high_fidelity_equations(spec.model, spec.plant, get_scenario(spec.scenario)):
            fidelity = spec.vehicle_data.fidelity
        return AnalyticModel(model_params(spec.model, spec.plant, spec.vehicle_data), name=spec.model_name,
                             fidelity=fidelity)
    return load_model(spec.model)


@dataclass(frozen=True)
class RunSpec:
    """What to fly: a scenario, a controller, a prediction model, a plant and a vehicle.

    ``scenario`` is a scenario name or a scenario file (``.toml``);
    ``model`` is ``"oracle"``, ``"nominal"``, ``"analytic:..."`` or an ONNX
    path; ``plant`` one of :data:`sim.plants.named.PLANTS`; ``vehicle`` a shipped
    vehicle's name or a vehicle file (None: the default vehicle); ``qp`` the
    QP solver of the LTV-MPC and the SQP (:data:`mpc.controllers.dense_qp.QP_SOLVERS`: ``"osqp"``
    or ``"daqp"``, the dense path), which the other controllers have no use
    for (see :attr:`qp_solver`).
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

    @property
    def model_name(self) -> str:
        return model_name(self.model)

    @property
    def qp_solver(self) -> str | None:
        """The QP solver the run's controller uses: :attr:`qp` for the LTV-MPC and the SQP, None for the others
        (the NMPC's IPOPT and the LQR solve no QP), so that their runs are the same whatever ``qp`` says."""
        return self.qp if self.controller in QP_CONTROLLERS else None

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
        return base if self.timing == "ideal" else f"{base}__{self.timing}"


def _sha256(path: str) -> str | None:
    if path in EQUATION_MODELS or path.startswith("analytic:"):
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def input_files(spec: "RunSpec") -> dict[str, Path]:
    """The files a run reads, by role: ``model`` (an ONNX file) and ``jacobian`` (its derivative graph, read when it
    exists: without it the controllers take central differences), ``vehicle`` and ``scenario`` (when given as
    files). Equation models and shipped names read no file of their own."""
    from mpc.prediction.contract import jacobian_path

    files = {}
    if spec.model not in EQUATION_MODELS and not spec.model.startswith("analytic:"):
        files["model"] = Path(spec.model)
        files["jacobian"] = jacobian_path(spec.model)
    for role, name in (("vehicle", spec.vehicle), ("scenario", spec.scenario)):
        if isinstance(name, str) and name.endswith(".toml"):
            files[role] = Path(name)
    return files


def input_hashes(spec: "RunSpec") -> dict[str, str | None]:
    """SHA-256 of each of :func:`input_files` now, by role (None: the file is absent, as a model without a
    derivative graph is)."""
    out = {}
    for role, path in input_files(spec).items():
        try:
            out[role] = hashlib.sha256(path.read_bytes()).hexdigest()
        except FileNotFoundError:
            out[role] = None
    return out


#: With the state estimator in real time, the SQP's wall-clock budget (8 ms per period alone) leaves this much of the
#: period to the filter (its time, median 0.4-0.9 ms, spikes to 2-6 ms, is charged to the same deadline).
ESTIMATOR_RESERVE_S = 0.003


def make_controller(kind: str, model, reference, horizon: int = HORIZON, timing: str = "ideal", vehicle=None,
                    estimator: str = "none", sqp: dict | None = None, qp: str = DEFAULT_QP):
    """The controller ``kind`` (``nmpc``, ``sqp``, ``ltv``, ``lqr``) on prediction ``model`` following ``reference``.

    The controller gets the model, the reference and the vehicle's datasheet
    only: its vehicle spec comes from the model and the datasheet of
    ``vehicle`` (:meth:`mpc.prediction.spec.VehicleSpec.from_model`; the default vehicle
    when None), never from the plant. With ``ideal`` timing the SQP runs
    without its wall-clock budget (at most its iteration limit), so that the
    run is reproducible bit for bit; with ``realtime`` timing the budget applies, less
    :data:`ESTIMATOR_RESERVE_S` with a state ``estimator`` (its time counts against the same period).
    ``sqp``: other :class:`mpc.controllers.sqp.SQPSettings` values for the SQP (for example ``{"jacobian_refresh":
    "full"}``;
    a ``"qp"`` there wins over ``qp``). ``qp``: the QP solver of the LTV-MPC and the SQP (``"osqp"`` or
    ``"daqp"``, :attr:`mpc.controllers.ltv.LTVSettings.qp`); the NMPC and the LQR have none.
    """
    from mpc.controllers.lqr import LQRController
    from mpc.controllers.ltv import LTVMPC, LTVSettings
    from mpc.controllers.nmpc import NMPC, NMPCSettings
    from mpc.prediction.spec import VehicleSpec

    spec = VehicleSpec.from_model(model, vehicle)
    if kind == "nmpc":
        return NMPC(model, reference, NMPCSettings(horizon=horizon), spec=spec)
    if kind == "sqp":
        import dataclasses

        from mpc.controllers.sqp import SQPMPC, SQPSettings
        other = {"qp": qp, **(sqp or {})}
        if timing == "ideal":
            return SQPMPC(model, reference, SQPSettings(horizon=horizon, time_budget_s=None, cold_start_budget_s=None,
                                                        **other), spec=spec)
        st = SQPSettings(horizon=horizon, **other)
        if estimator != "none":
            st = dataclasses.replace(st, time_budget_s=st.time_budget_s - ESTIMATOR_RESERVE_S,
                                     cold_start_budget_s=st.cold_start_budget_s - ESTIMATOR_RESERVE_S)
        return SQPMPC(model, reference, st, spec=spec)
    if kind == "ltv":
        return LTVMPC(model, reference, LTVSettings(horizon=horizon, qp=qp), spec=spec)
    if kind == "lqr":
        return LQRController(reference, model, spec=spec)
    raise ScenarioError(f"controller must be one of {', '.join(CONTROLLERS)}; found {kind!r}")


def _wind(sc):
    """The scenario's wind and gust impulse as one acceleration function (or None)."""
    parts = [w for w in (sc.wind, sc.impulse) if w is not None]
    if not parts:
        return None
    if len(parts) == 1:
        return parts[0]
    return lambda t: parts[0](t) + parts[1](t)


def reference_spec(plant: str, vehicle):
    """The vehicle numbers of the flatness map that makes a reference feasible on ``plant`` flying ``vehicle``:
    the vehicle's, with the drag of the plant's own equations where they are known (none on ``rotorpy-ideal``)."""
    import dataclasses

    from mpc.prediction.spec import VehicleSpec
    from sim.plants.named import known_equations

    spec = VehicleSpec.from_vehicle(vehicle)
    own = known_equations(plant, vehicle.params)
    return spec if own is None or own.c_d == spec.c_d else dataclasses.replace(spec, c_d=own.c_d)


def reference_states(ref, times: np.ndarray, spec) -> np.ndarray:
    """The reference states (K, 12) of flat trajectory ``ref`` at ``times`` (K,), s, through the flatness map of
    ``spec`` (its gravity and drag enter the attitude; the positions are the flat outputs themselves)."""
    from mpc.references.trajectory import flat_state

    return flat_state(ref.flat(times), spec)[0]


def plant_reference(spec: "RunSpec", sc, times: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The reference the plant itself can fly: states (K, 12) at ``times`` (K,), s, and its rotor speeds at the
    first time (4,) where the plant's motors lag (else None).

    On a ``+highfi`` scenario of the reference simulator this is the flatness map of the high-fidelity equations
    (:func:`mpc.references.trajectory.actuated_flat_state`: rotor drag tilts the thrust); elsewhere the flatness map
    of the
    plant's own rigid-body equations (:func:`reference_spec`). Positions and yaw are the flat outputs either way.
    """
    ref, v = sc.reference(), spec.vehicle_data
    if high_fidelity_equations("oracle", spec.plant, sc):
        from mpc.references.trajectory import actuated_flat_state

        x, n, _ = actuated_flat_state(ref, times, v.params, v.fidelity)
        return x, (n[0] if v.fidelity.motor_tau > 0.0 else None)
    return reference_states(ref, times, reference_spec(spec.plant, v)), None


def start_state(sc, spec, x_ref0: np.ndarray | None = None) -> np.ndarray:
    """The scenario's initial state (12,) on the reference the plant flies.

    A scenario's ``x0`` is its reference at t = 0 (through
    :data:`scenarios.closed_loop.scenario.START_MAP`, the default vehicle's) plus its offsets; the offsets are kept
    and the
    reference part is replaced by the plant's: ``x_ref0`` (12,) where the plant has a map of its own (the
    high-fidelity plant's, :func:`plant_reference`), else ``spec``'s flatness map, so that a vehicle with other
    drag starts on its own feasible reference. Unchanged for the default vehicle on the nominal plant.
    """
    from .scenario import START_MAP

    x0 = np.array(sc.x0, dtype=float)
    ref, t0 = sc.reference(), np.array([0.0])
    if x_ref0 is None:
        if (spec.g, spec.c_d) == (START_MAP.g, START_MAP.c_d):     # the only numbers the map's states depend on
            return x0
        x_ref0 = reference_states(ref, t0, spec)[0]
    return x0 + x_ref0 - reference_states(ref, t0, START_MAP)[0]


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


def make_run_plant(spec: "RunSpec", sc):
    """The plant of a run: ``spec.plant`` flying ``spec``'s vehicle with the scenario's disturbances."""
    from sim.plants.named import make_plant

    v = spec.vehicle_data
    return make_plant(spec.plant, v, high_fidelity=sc.high_fidelity, payload_kg=sc.payload_fraction * v.m,
                      wind=_wind(sc))


def fly(spec: RunSpec, progress: bool = False, scenario=None, model=None, ekf_config=None,
        sqp: dict | None = None) -> tuple[dict, dict]:
    """Fly one closed-loop run; ``(result, trace)``.

    Raises only for bad input (unknown names, a model that fails the
    contract); everything that happens in flight is recorded.

    ``scenario`` (a :class:`scenarios.closed_loop.library.Scenario`) replaces the named
    scenario's data, for example with a perturbed initial state; ``model`` (a
    loaded :class:`mpc.prediction.models.PredictionModel`) saves loading ``spec.model`` again. ``ekf_config`` (an
    :class:`mpc.estimators.estimator.EKFConfig`) replaces the estimator's default tuning. ``sqp``: other
    :class:`mpc.controllers.sqp.SQPSettings` values for the SQP (:func:`make_controller`; benchmarks compare its paths).

    The result's ``qp`` names the QP solver the controller used (:func:`flown_qp`): ``spec.qp`` for the LTV-MPC
    and the SQP (or the ``"qp"`` of ``sqp``), None for the NMPC and the LQR.
    """
    from .loop import IdealClock, RealtimeClock, StateSensor, Trace, fly_loop

    if scenario is not None:
        sc = scenario
    elif spec.member is not None:
        sc = get_scenario(spec.scenario).member(spec.member)
    else:
        sc = get_scenario(spec.scenario, spec.seed)
    inputs = input_hashes(spec)           # what is flown: taken as the run starts, stored in its result
    own = scenario is None and model is None      # all that is flown comes from the spec (and its files)
    if model is None:
        model = load_run_model(spec)      # contract errors raise here, before anything flies
    vehicle = spec.vehicle_data
    plant = make_run_plant(spec, sc)      # a missing RotorPy raises here, before anything flies
    ref = sc.reference()
    K = sc.steps
    t_all = DT * np.arange(K + 1)
    # The scenario's offsets from its reference at t = 0 are kept; the reference part of its start is the one this
    # plant can fly (with its motors at the reference's speeds where they lag).
    X_ref, n0 = plant_reference(spec, sc, t_all)
    own_map = high_fidelity_equations("oracle", spec.plant, sc)
    x0 = start_state(sc, reference_spec(spec.plant, vehicle), X_ref[0] if own_map else None)
    error = None
    sha = inputs.get("model")
    base = {"run_id": spec.run_id, "scenario": sc.name, "controller": spec.controller,
            "model": spec.model_name, "model_file": None if sha is None else str(spec.model),
            "model_sha256": sha, "seed": sc.seed, "member": spec.member, "horizon": spec.horizon,
            "timing": spec.timing, "plant": spec.plant, "vehicle": vehicle.name, "estimator": spec.estimator,
            "qp": flown_qp(spec, sqp), "inputs_sha256": inputs}
    t0 = time.perf_counter()
    realtime = spec.timing == "realtime"
    try:
        ctrl = make_controller(spec.controller, model, ref, spec.horizon, spec.timing, vehicle, spec.estimator,
                               sqp=sqp, qp=spec.qp)
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
            plant, estimator = make_estimator(ctrl, model, plant, sc, X_ref[0], ekf_config)
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
    preflight = None if pre is None else {"iterations": int(pre.iterations), "status": pre.status}
    failed, lqr_fb = tr.solver_failed[:k_end], tr.lqr_fallback[:k_end]
    # Real time: periods whose plan could not be made before the deadline (the fallback's input went out).
    from mpc.controllers.ltv import DEADLINE_STATUS

    late = int(np.sum(failed & (tr.status[:k_end] == DEADLINE_STATUS))) if realtime and error is None else None
    causes = {}                            # why the solver failed, most frequent first
    for status in tr.status[:k_end][failed]:
        causes[str(status)] = causes.get(str(status), 0) + 1
    causes = dict(sorted(causes.items(), key=lambda kv: (-kv[1], kv[0])))
    result = {**base, **metrics, "shifted_plan": int(np.sum(failed & ~lqr_fb)), "deadline_fallbacks": late,
              "failure_causes": causes,
              "preflight": preflight, "preflight_ms": None if pre is None else 1e3 * pre.solve_time_s,
              "error": error, "wall_time_s": wall, "scenario_spec": sc.to_dict(), "plant_spec": plant.describe(),
              "vehicle_spec": vehicle.to_dict()}
    trace = {"t": t_all[:k_end + 1], "x": tr.x[:k_end + 1], "x_ref": X_ref[:k_end + 1],
             "x_measured": tr.x_measured[:k_end], "u": tr.u[:k_end], "u_command": tr.u_command[:k_end],
             "solve_s": tr.solve_s[:k_end], "latency_s": tr.latency_s[:k_end], "called": tr.called[:k_end],
             "iterations": tr.iterations[:k_end], "status": tr.status[:k_end], "solver_failed": failed,
             "lqr_fallback": lqr_fb, "rotor_speed": tr.rotor_speed[:k_end + 1]}
    if tr.x_estimate is not None:
        est_ms = 1e3 * tr.estimator_s[:k_end][tr.called[:k_end]]
        result["estimator_ms"] = {"median": float(np.median(est_ms)), "max": float(np.max(est_ms))} \
            if est_ms.size else None
        nees_k = tr.nees[:k_end]
        result["nees_mean"] = float(np.nanmean(nees_k)) if np.any(np.isfinite(nees_k)) else None
        for name in ("x_estimate", "estimate_std", "disturbance", "gyro_bias", "gyro_bias_true", "accel_bias",
                     "accel_bias_true", "nees", "estimator_s"):
            trace[name] = getattr(tr, name)[:k_end]
    return result, trace


def estimator_sensors(sc):
    """The sensors of a run with the estimator: the default lab's, with the scenario's noise where it sets one.

    A scenario with measurement noise (``+noise``) sets the motion capture's position and attitude noise and
    the gyroscope's white noise to its position, attitude and body-rate standard deviations.
    """
    import dataclasses

    from sim.plants.sensors import ImuConfig, MocapConfig, SensorSuite

    mocap, imu = MocapConfig(), ImuConfig()
    if sc.noise is not None:
        mocap = dataclasses.replace(mocap, position_std=sc.noise.position, attitude_std=sc.noise.attitude)
        imu = dataclasses.replace(imu, gyro_std=sc.noise.body_rate)
    return SensorSuite(mocap=mocap, imu=imu, rng=np.random.default_rng([sc.seed, 0x5E75]))


def make_estimator(ctrl, model, plant, sc, guess=None, config=None):
    """``(sensed plant, Estimator)`` of a run with ``--estimator ekf``: the filter runs on the controller's model.

    ``guess`` (12,): the reference at take-off (the filter's first velocity)."""
    from mpc.estimators.estimator import DisturbanceEKF
    from sim.plants.sensors import SensedPlant

    from .loop import Estimator

    suite = estimator_sensors(sc)
    start = ctrl.start_extra
    from mpc.estimators.estimator import EKFConfig

    ekf = DisturbanceEKF(model, suite.mocap, suite.imu, config=EKFConfig() if config is None else config,
                         extra_start=lambda x: start(x, 0.0), g=plant.vehicle.params.g)
    return SensedPlant(plant, suite), Estimator(suite, ekf, guess)


def save_run(result: dict, trace: dict, out_dir: Path) -> dict:
    """Write ``runs/<id>.json`` and ``traces/<id>.npz`` under ``out_dir``; the result with its trace path."""
    out_dir = Path(out_dir)
    (out_dir / "runs").mkdir(parents=True, exist_ok=True)
    (out_dir / "traces").mkdir(parents=True, exist_ok=True)
    from sim.files import write_npz, write_text

    rel = None
    if trace:
        rel = f"traces/{result['run_id']}.npz"
        write_npz(out_dir / rel, trace)
    result = {**result, "trace": rel}
    # Both files are written whole (a temporary file renamed), the JSON last: a run interrupted while saving leaves
    # no result, and is flown again.
    write_text(out_dir / "runs" / f"{result['run_id']}.json", json.dumps(result, indent=2, sort_keys=True) + "\n")
    return result


_CODE_VERSION: str | None = None


def code_version() -> str:
    """SHA-256 (first 16 hex digits) of the package version and the source of the packages that fly a run.

    Any change to the Python source of ``sim``, ``mpc`` or ``scenarios`` (or
    the version) makes a new code version, and so invalidates every cached
    run. Data files are not code: the CI bounds (``scenarios/studies/bounds.toml``)
    do not change a flight, and a run's vehicle and scenario enter its
    :func:`cache_key` by their content.
    """
    global _CODE_VERSION
    if _CODE_VERSION is None:
        from sim.files import source_digest

        root = Path(__file__).resolve().parents[2]
        _CODE_VERSION = source_digest(("sim", "mpc", "scenarios"), root).hexdigest()[:16]
    return _CODE_VERSION


def cache_key(spec: RunSpec, inputs: dict | None = None) -> str:
    """Identity of a run's result: its spec, its seed, the SHA-256 of every file it reads and the code version.

    The QP solver (:attr:`RunSpec.qp_solver`) is part of it: a run flown with one solver is never reused for
    the other. It enters only where it is not OSQP, so an OSQP run's key is made as before the choice existed.

    ``inputs``: those hashes (:func:`input_hashes`) as a run recorded them when it started flying; None: the
    files as they are now. A saved result is reused only when the two agree, so a run flown with a file that was
    replaced since (or replaced during the sweep) is flown again.
    """
    sc = get_scenario(spec.scenario)
    seed = sc.seed if spec.seed is None else spec.seed
    inputs = input_hashes(spec) if inputs is None else inputs
    # The model by name and content, not by path: a results folder stays valid when the models move. The vehicle
    # and a scenario file by content too.
    ident = {"scenario": sc.to_dict(), "controller": spec.controller, "model": spec.model_name,
             "model_sha256": inputs.get("model"), "inputs": inputs, "seed": seed, "member": spec.member,
             "horizon": spec.horizon,
             "timing": spec.timing, "plant": spec.plant, "vehicle": spec.vehicle_data.to_dict(),
             "estimator": spec.estimator, "code": code_version()}
    if spec.qp_solver not in (None, DEFAULT_QP):
        # Only where it is not OSQP, the solver of every run before the choice: an OSQP run keeps its identity.
        ident["qp"] = spec.qp_solver
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()


def cached_result(spec: RunSpec, out_dir, key: str | None = None) -> dict | None:
    """The saved result of ``spec`` under ``out_dir`` if it was flown with the same cache key, else None.

    ``key``: the spec's :func:`cache_key`, if already computed. A saved run
    that could not start (its ``error`` is set, for example a model file that
    failed the contract) is not reused.
    """
    path = Path(out_dir) / "runs" / f"{spec.run_id}.json"
    if not path.is_file():
        return None
    try:
        result = json.loads(path.read_text())
        if not isinstance(result, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as e:
        _say(f"{path}: damaged ({e}); flying {spec.run_id} again")
        return None
    if result.get("cache_key") != (cache_key(spec) if key is None else key) or result.get("error"):
        return None     # another spec, file or code; or a run that could not start (tried again)
    if result.get("trace"):
        why = trace_damage(Path(out_dir) / result["trace"])
        if why is not None:
            _say(f"{Path(out_dir) / result['trace']}: {why}; flying {spec.run_id} again")
            return None
    return result


def _say(line: str) -> None:
    import sys

    print(line, file=sys.stderr, flush=True)


def trace_damage(path: Path) -> str | None:
    """Why the trace file ``path`` cannot be trusted (missing, not a readable ``.npz``, an array that fails its
    checksum, no ``t`` and ``x``), or None when it reads back whole."""
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}     # reading every array checks its CRC
    except FileNotFoundError:
        return "missing"
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        return f"damaged ({type(e).__name__}: {e})"
    if "t" not in arrays or "x" not in arrays or len(arrays["t"]) != len(arrays["x"]):
        return "damaged (no time and state arrays of one length)"
    return None


def fly_for_sweep(spec: RunSpec) -> tuple[dict, dict]:
    """``fly(spec)`` for a sweep (:mod:`scenarios.sweeps.sweep`): a run that cannot fly is recorded (its error) and
    the sweep goes on.

    This is the unit of work of every engine (a process-pool task, a Ray
    task); the sweep stamps the result with its :func:`cache_key`.
    """
    try:
        return fly(spec)
    except Exception as e:  # noqa: BLE001 - a run that cannot fly is recorded and the sweep goes on
        return not_flown(spec, f"{type(e).__name__}: {e}"), {}


def not_flown(spec: RunSpec, error: str) -> dict:
    """The result of a run that did not fly: its metrics null, ``error`` the reason (one line)."""
    return {"run_id": spec.run_id, "scenario": spec.scenario_name, "controller": spec.controller,
            "model": spec.model_name, "plant": spec.plant, "vehicle": spec.vehicle_data.name, "qp": spec.qp_solver,
            **NOT_FLOWN,
            "error": error, "inputs_sha256": input_hashes(spec)}


def spec_dict(spec: RunSpec) -> dict:
    """JSON-ready form of a :class:`RunSpec`."""
    return asdict(spec)
