"""Prediction models behind one small interface.

A prediction model maps one control period, batched over samples::

    x_next = model.step(x, u)                 # (N, nx), (N, 4) -> (N, nx)
    x_next, A, B = model.linearize(x, u)      # A (N, nx, nx) = dx_next/dx, B (N, nx, 4) = dx_next/du

``nx`` is 12 (the rigid-body state) plus the model's extra states
(:attr:`PredictionModel.extra_names`): actuator states such as rotor speeds,
or a window of past states and inputs. The controllers plan over all ``nx``
and carry the extra states from period to period (:mod:`mpc.prediction.extended`).

Implementations:

* :class:`AnalyticModel`: the nominal equations of :mod:`sim` (CasADi, RK4
  over 10 x 1 ms), with the reference parameters ("oracle") or with the
  parameters identified by a PINN (:meth:`AnalyticModel.from_onnx_theta`);
  given a :class:`sim.params.Fidelity`, the high-fidelity simulator's
  equations instead, with the rotor speeds as extra states when the motors lag;
* :class:`OnnxModel`: any ONNX file that passes the model contract and has
  its derivative graph beside it, evaluated by onnxruntime (one session per
  file, thread count set). No torch anywhere.
"""

from __future__ import annotations

import numpy as np

from sim._validate import as_batch, broadcast_batch
from sim.params import NU, NX, SUBSTEPS, THETA_NAMES, QuadParams

from ..errors import ModelContractError


def _batch(x, u, nx: int = NX) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 arrays (N, nx), (N, 4) with broadcast batch axes."""
    x, u = broadcast_batch(as_batch(x, "x", nx), as_batch(u, "u", NU))
    return np.ascontiguousarray(x.reshape(-1, nx)), np.ascontiguousarray(u.reshape(-1, NU))


class PredictionModel:
    """Interface of a one-period prediction model (see the module docstring)."""

    #: Short name used in results (``oracle``, ``baseline``, ...).
    name: str = "model"
    #: Parameters the model stands for, ``(m, Jxx, Jyy, Jzz, kt, kq)``, if known.
    theta: np.ndarray | None = None
    #: Names of the states beyond the 12 rigid-body ones, in the order they follow them (empty: none).
    extra_names: tuple[str, ...] = ()
    #: Acceptable deviations of the extra states (n_extra,), in their own units, or None to derive them from the
    #: model's hover equilibrium (:func:`mpc.prediction.extended.extra_scale`). They measure steps and defects only.
    extra_scale: np.ndarray | None = None
    #: The command level of the input ``u`` (:data:`sim.levels.LEVELS`): what the model takes each period.
    level: str = "wrench"
    #: Names of extra states that integrate (an inner loop's integral): they have no rest value of their own, so
    #: an equilibrium holds them where they are (:func:`mpc.prediction.extended.extra_equilibrium`).
    integrators: tuple[str, ...] = ()

    @property
    def n_extra(self) -> int:
        """Number of extra (actuator or history) states."""
        return len(self.extra_names)

    @property
    def nx(self) -> int:
        """Length of the model's state: 12 plus its extra states."""
        return NX + len(self.extra_names)

    def step(self, x, u) -> np.ndarray:  # pragma: no cover - interface
        """Next states (N, nx) for states (N, nx) and wrenches (N, 4)."""
        raise NotImplementedError

    def linearize(self, x, u):  # pragma: no cover - interface
        """``(x_next (N, nx), A (N, nx, nx), B (N, nx, 4))``, exact derivatives."""
        raise NotImplementedError

    def reference_states(self, trajectory, times) -> np.ndarray | None:
        """The model's own reference states (K, nx) along a flat trajectory, or None (the default: the controllers'
        flatness map gives the rigid-body states, and the extra states are the model's own along them)."""
        return None

    def linearize_single(self, x, u):
        """As :meth:`linearize`, but ``A`` and ``B`` may be computed in single precision.

        ``x_next`` stays exact. The QP-based controllers use this (their
        Jacobians need about 7 significant digits); models without a faster
        path return :meth:`linearize`.
        """
        return self.linearize(x, u)

    def jacobians(self, x, u):
        """``(A (N, nx, nx), B (N, nx, 4))`` as :meth:`linearize_single` gives them, without the model's step (for
        a controller that has the step already); models without a faster path drop it from
        :meth:`linearize_single`."""
        return self.linearize_single(x, u)[1:]


class AnalyticModel(PredictionModel):
    """The simulator's equations in CasADi, RK4 over one control period.

    Parameters
    ----------
    params : QuadParams, optional
        Parameters (reference values, the "oracle", when omitted).
    name : str
        Name used in results.
    fidelity : sim.params.Fidelity, optional
        The high-fidelity simulator's effects to include (motor lag, rotor
        drag, gyroscopic torque). None or nominal: the nominal rigid-body
        equations. With a motor lag the model has four extra states, the
        rotor speeds ``n1 .. n4`` (RU), and its input is still the wrench
        command, turned into rotor commands as the plant does.
    substeps : int
        RK4 steps per control period (default 10, the simulator's 1 ms). Only the nominal rigid-body equations at
        the wrench level take another number: 1 is one RK4 step of a whole period, the discretization of acados'
        default integrator, which the benchmark's comparison with it flies.

    Notes
    -----
    Where the equations compile to C (:mod:`sim.equations.compiled`), :meth:`step` and :meth:`linearize` call the
    compiled function at every point in one C call; elsewhere CasADi evaluates them. The numbers are the same.
    """

    def __init__(self, params: QuadParams | None = None, name: str = "oracle", fidelity=None, *,
                 level: str = "wrench", inner_loop=None, exact_loop: bool = False, substeps: int = SUBSTEPS):
        import casadi as ca

        from sim.equations.compiled import Pointwise
        from sim.equations.dynamics_casadi import actuated_step_function, step_function
        from sim.levels import DEFAULT_LEVEL, check_level
        from sim.params import Fidelity

        self.params = QuadParams() if params is None else params
        if not isinstance(self.params, QuadParams):
            raise ModelContractError(f"params must be a QuadParams; found {type(params).__name__}")
        if fidelity is not None and not isinstance(fidelity, Fidelity):
            raise ModelContractError(f"fidelity must be a sim.params.Fidelity or None; found {type(fidelity).__name__}")
        self.fidelity = None if fidelity is None or fidelity.is_nominal else fidelity
        self.name = name
        self.theta = self.params.theta
        self.level = check_level(level)
        if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
            raise ModelContractError(f"substeps must be a positive integer; found {substeps!r}")
        self.substeps = int(substeps)
        if self.substeps != SUBSTEPS and (self.fidelity is not None or self.level != DEFAULT_LEVEL):
            found = "high-fidelity effects" if self.fidelity is not None else f"level {level!r}"
            raise ModelContractError(f"substeps other than {SUBSTEPS} are for the nominal equations at the wrench "
                                     f"level; found substeps={substeps} with {found}")
        #: The onboard controller a ``ctbr`` or ``ctatt`` model stands for (None at the wrench level), and whether the
        #: model is that loop exactly (the oracle) or its nominal response.
        self.inner_loop, self.exact_loop = inner_loop, bool(exact_loop)
        if self.level != DEFAULT_LEVEL:
            self._level_model()
        else:
            if self.fidelity is not None and self.fidelity.motor_tau > 0.0:
                self.extra_names = ROTOR_STATE_NAMES
                self.extra_scale = np.full(4, 0.1 * self.params.n_hover)
            #: CasADi function ``F(x, u) -> x_next`` (column vectors), for symbolic use (NMPC).
            self.casadi_step = step_function(self.params, substeps=self.substeps) if self.fidelity is None else \
                actuated_step_function(self.params, self.fidelity)
        self._theta = ca.DM(self.params.theta)
        self._theta_values = np.array(self.params.theta, dtype=float)
        self._step, self._lin, libs = _numeric_functions(self.params, self.fidelity, self._level_key(), self.substeps)
        #: The compiled step and Jacobian called at every point at once (None where they did not compile).
        self._points = tuple(None if f is None else Pointwise(g, f) for g, f in zip((self._step, self._lin), libs))
        self._maps: dict = {}

    def _level_model(self) -> None:
        """Set up the ``ctbr`` or ``ctatt`` model: the nominal response of :attr:`inner_loop`, or the loop exactly."""
        from sim.equations.levels_casadi import (INTEGRATOR_NAMES, inner_loop_extra_names, inner_loop_step_function,
                                                 level_step_function)
        from sim.vehicles.onboard import InnerLoopConfig

        if not isinstance(self.inner_loop, InnerLoopConfig):
            raise ModelContractError(f"a model at the {self.level!r} level needs the vehicle's inner loop (an "
                                     f"InnerLoopConfig); found {type(self.inner_loop).__name__}")
        if self.fidelity is not None:
            raise ModelContractError(f"the equations at the {self.level!r} level are the nominal rigid body's; the "
                                     f"high-fidelity effects are not modelled at this level")
        if self.exact_loop:
            self.extra_names = inner_loop_extra_names(self.inner_loop, self.level)
            self.integrators = tuple(n for n in self.extra_names if n in INTEGRATOR_NAMES)
            if self.extra_names:
                #: Integrals 0.05 rad (rad s), errors 1 rad/s: what the loop's memory may be off by.
                self.extra_scale = np.array([0.05 if n.startswith("i_") else 1.0 for n in self.extra_names])
            self.casadi_step = inner_loop_step_function(self.params, self.level, self.inner_loop)
        else:
            #: The assumed response of the closed inner loop (:class:`sim.vehicles.onboard.LoopResponse`).
            self.response = self.inner_loop.response()
            self.casadi_step = level_step_function(self.params, self.level, self.response)

    def _level_key(self):
        """What selects the compiled equations besides the rigid body's numbers (None at the wrench level)."""
        if self.level == "wrench":
            return None
        return (self.level, self.inner_loop if self.exact_loop else self.response, self.exact_loop)

    def reference_states(self, trajectory, times) -> np.ndarray | None:
        """The model's own reference (K, nx) along a flat ``trajectory`` at ``times`` (K,), or None.

        With high-fidelity effects, the flatness map of these equations
        (:func:`mpc.references.trajectory.actuated_flat_state`: rotor drag tilts the
        thrust, the gyroscopic torque adds to the torques) and the rotor speeds
        that make the wrench; the controllers then follow a reference their
        model can fly exactly. None for the nominal equations (the
        controllers' own flatness map is theirs).
        """
        if self.fidelity is None:
            return None
        from ..references.trajectory import actuated_flat_state

        x, n, _ = actuated_flat_state(trajectory, times, self.params, self.fidelity)
        return np.hstack([x, n]) if self.n_extra else x

    @classmethod
    def from_onnx_theta(cls, path) -> "AnalyticModel":
        """The analytic model with the parameters identified in an ONNX model's metadata."""
        from .contract import check_model

        info = check_model(path)
        if info.theta is None:
            raise ModelContractError(f"{path}: declares no identified parameters (metadata 'theta'); the analytic "
                                     f"model needs them")
        params = QuadParams().with_theta([info.theta[n] for n in THETA_NAMES])
        return cls(params, name=f"analytic[{info.architecture}]")

    def _mapped(self, fn: str, n: int):
        key = (fn, n)
        if key not in self._maps:
            base = self._step if fn == "step" else self._lin
            self._maps[key] = base.map(n, "serial")
        return self._maps[key]

    def step(self, x, u) -> np.ndarray:
        """Next states (N, nx)."""
        x, u = _batch(x, u, self.nx)
        if self._points[0] is not None:
            return self._points[0](x, u, self._theta_values)[0]
        n = len(x)
        return np.asarray(self._mapped("step", n)(x.T, u.T, self._theta)).T   # theta broadcast over the map

    def linearize(self, x, u):
        """``(x_next, A, B)`` by CasADi's automatic differentiation (compiled, see :mod:`sim.equations.compiled`)."""
        nx = self.nx
        x, u = _batch(x, u, nx)
        n = len(x)
        if self._points[1] is not None:
            xn, A, B = self._points[1](x, u, self._theta_values)     # each matrix flattened column by column
            # row-major copies: the products downstream then round as they did on CasADi's own (row-major) result
            return (xn, np.ascontiguousarray(A.reshape(n, nx, nx).transpose(0, 2, 1)),
                    np.ascontiguousarray(B.reshape(n, NU, nx).transpose(0, 2, 1)))
        xn, A, B = self._mapped("lin", n)(x.T, u.T, self._theta)
        A = np.asarray(A).reshape(nx, n, nx).transpose(1, 0, 2)
        B = np.asarray(B).reshape(nx, n, NU).transpose(1, 0, 2)
        return np.asarray(xn).T, A, B


#: Names of the rotor-speed states of an analytic model with motor lag (RU), rotors in the order of
#: :mod:`sim.vehicles.rotors`.
ROTOR_STATE_NAMES = ("n1", "n2", "n3", "n4")

_NUMERIC: dict = {}


def _numeric_functions(params: QuadParams, fidelity=None, level=None, substeps: int = SUBSTEPS):
    """Compiled ``step(x, u, theta)`` and ``lin(x, u, theta) -> (x_next, A, B)`` of the equations, and their
    libraries (None where they did not compile).

    ``theta`` is an input, so one compiled library serves every parameter
    set that differs only in ``(m, Jxx, Jyy, Jzz, kt, kq)``; ``fidelity`` (a
    non-nominal :class:`sim.params.Fidelity`) selects the high-fidelity equations; ``level``, None at the wrench
    level, else ``(level, response or inner-loop config, exact)`` (:meth:`AnalyticModel._level_key`), the equations
    at a command level.
    """
    from sim.equations.compiled import compiled_library

    key = tuple(getattr(params, n) for n in ("g", "c_d", "d")) + (substeps,)
    if fidelity is not None:
        key += (params.n_max_sq, fidelity.motor_tau, fidelity.rotor_drag, fidelity.rotor_gyro)
    if level is not None:
        key += (params.n_max_sq, level)
    if key not in _NUMERIC:
        (step, step_lib), (lin, lin_lib) = (compiled_library(f) for f in numeric_sources(params, fidelity, level,
                                                                                          substeps))
        _NUMERIC[key] = (step, lin, (step_lib, lin_lib))
    return _NUMERIC[key]


def numeric_sources(params: QuadParams, fidelity=None, level=None, substeps: int = SUBSTEPS):
    """The CasADi ``step`` and ``lin`` of :func:`_numeric_functions` before compilation (to precompile them);
    ``substeps``: RK4 steps per period of the nominal equations (:class:`AnalyticModel`)."""
    import casadi as ca

    from sim.equations.dynamics_casadi import actuated_step_function, step_function

    sym = ca.SX
    if level is not None:
        from sim.equations.levels_casadi import inner_loop_step_function, level_step_function

        lv, how, exact = level
        if exact:
            # Composed of loop-period calls (MX): its Jacobian's C code is a fraction of the expanded one's.
            F = inner_loop_step_function(params, lv, how, symbolic_theta=True, composed=True)
            name, sym = f"pinnmpc_{lv}_loop", ca.MX
        else:
            F, name = level_step_function(params, lv, how, symbolic_theta=True), f"pinnmpc_{lv}"
    elif fidelity is None or fidelity.is_nominal:
        F = step_function(params, symbolic_theta=True, substeps=substeps)
        name = "pinnmpc" if substeps == SUBSTEPS else f"pinnmpc_rk{substeps}"
    else:
        # Composed of substep calls: the expanded form's Jacobian is 3 MB of C and takes about 50 s to compile; this
        # one 0.7 MB and 4 s, and a 30-stage linearization takes 3.8 ms instead of 2.9 (one run, this machine).
        F, name = actuated_step_function(params, fidelity, symbolic_theta=True, composed=True), "pinnmpc_actuated"
        sym = ca.MX
    nx = F.size1_in(0)
    xs, us, th = sym.sym("x", nx), sym.sym("u", NU), sym.sym("theta", len(THETA_NAMES))
    xn = F(xs, us, th)
    step = ca.Function(f"{name}_step", [xs, us, th], [xn])
    # dense Jacobians: the point loop then writes every entry, structural zeros included
    lin = ca.Function(f"{name}_lin", [xs, us, th],
                      [xn, ca.densify(ca.jacobian(xn, xs)), ca.densify(ca.jacobian(xn, us))])
    return step, lin


#: How an ONNX model's A and B are obtained: its derivative graph, or central differences of the model.
DERIVATIVE_PATHS = ("derivative graph", "central differences")


class OnnxModel(PredictionModel):
    """An ONNX dynamics model through onnxruntime, with its derivative graph or central differences.

    Parameters
    ----------
    path : path
        Model file; it must pass :func:`mpc.prediction.contract.check_model`. With a
        derivative graph ``<stem>.jac.onnx`` beside it, A and B come from that
        graph; without one, from batched central differences of the model
        (:func:`mpc.prediction.contract.central_differences`: one onnxruntime call per
        linearization, 33 model evaluations per point).
    threads : int
        onnxruntime intra-op threads per session (default 1).

    Attributes
    ----------
    derivatives : str
        One of :data:`DERIVATIVE_PATHS`.
    theta : ndarray (6,) or None
        The model's declared ``(m, Jxx, Jyy, Jzz, kt, kq)``, None when the file gives none (the vehicle spec
        then uses the datasheet).

    Raises
    ------
    ModelContractError
        If the file violates the contract.
    """

    def __init__(self, path, threads: int = 1):
        from .contract import check_model, open_session

        self.info = check_model(path)
        self.path = self.info.path
        self.name = self.path.stem
        self.theta = None if self.info.theta is None else np.array([self.info.theta[n] for n in THETA_NAMES])
        self.extra_names = tuple(self.info.extra_states)
        self.extra_scale = None if self.info.extra_scale is None else np.array(self.info.extra_scale)
        self.level = self.info.level
        self.dtype = self.info.dtype
        self._model = open_session(self.path, threads)
        if self.info.jacobian is None:
            self.derivatives = DERIVATIVE_PATHS[1]
            self._jac = self._jac_single = None
        else:
            self.derivatives = DERIVATIVE_PATHS[0]
            self._jac = open_session(self.info.jacobian, threads)
            self._jac_single = self._single_precision_session(threads)

    def step(self, x, u) -> np.ndarray:
        """Next states (N, nx)."""
        x, u = _batch(x, u, self.nx)
        out = self._model.run(["x_next"], {"x": x.astype(self.dtype), "u": u.astype(self.dtype)})[0]
        return out.astype(float)

    def linearize(self, x, u):
        """``(x_next, A, B)`` from the derivative graph (or central differences), one onnxruntime call for the batch."""
        x, u = _batch(x, u, self.nx)
        if self._jac is None:
            from .contract import central_differences

            def run(xx, uu):
                return self._model.run(["x_next"], {"x": xx, "u": uu})[0]
            return central_differences(run, x, u, self.dtype)
        xn, A, B = self._jac.run(["x_next", "A", "B"], {"x": x.astype(self.dtype), "u": u.astype(self.dtype)})
        return xn.astype(float), A.astype(float), B.astype(float)

    def linearize_single(self, x, u):
        """``(x_next, A, B)``: ``x_next`` from the model as exported, ``A``, ``B`` from a float32 copy of its derivative graph.

        Two onnxruntime calls for the whole batch. For a float64 model the
        float32 derivative graph is 1.5-2.3x faster than the float64 one
        (5x128 networks, 30 stages, one thread) and agrees with it to about
        1e-6 relative (:data:`SINGLE_PRECISION_RTOL` is checked when the model
        is loaded, else the float64 graph is used).
        """
        if self._jac_single is None:
            return self.linearize(x, u)     # float32 model, no derivative graph, or a float32 copy that disagrees
        x, u = _batch(x, u, self.nx)
        xn = self._model.run(["x_next"], {"x": x.astype(self.dtype), "u": u.astype(self.dtype)})[0]
        A, B = self._jac_single.run(["A", "B"], {"x": x.astype(np.float32), "u": u.astype(np.float32)})
        return xn.astype(float), A.astype(float), B.astype(float)

    def jacobians(self, x, u):
        """``(A, B)`` from the float32 derivative graph (or the float64 one, or central differences, as
        :meth:`linearize_single`), one onnxruntime call, no step of the model."""
        if self._jac_single is None:
            return self.linearize_single(x, u)[1:]
        x, u = _batch(x, u, self.nx)
        A, B = self._jac_single.run(["A", "B"], {"x": x.astype(np.float32), "u": u.astype(np.float32)})
        return A.astype(float), B.astype(float)

    def _single_precision_session(self, threads: int):
        """A float32 session of the derivative graph, or None (float32 model, or the copy disagrees)."""
        import warnings

        from .contract import _probe_batch, _with_extra_at_rest, open_session, single_precision

        if self.dtype == np.float32:
            return None   # the derivative graph is float32 already
        try:
            session = open_session(self.info.jacobian, threads, graph=single_precision(self.info.jacobian))
            x, u = _probe_batch(8, np.float64, seed=1)
            x = _with_extra_at_rest(self._model, x, u, self.extra_names, str(self.path), "hover-like")
            _, A, B = self._jac.run(["x_next", "A", "B"], {"x": x, "u": u})
            A1, B1 = session.run(["A", "B"], {"x": x.astype(np.float32), "u": u.astype(np.float32)})
        except ModelContractError as e:
            warnings.warn(f"{self.path}: no float32 derivative graph, the QP controllers use the float64 one ({e})",
                          stacklevel=3)
            return None
        err = max(float(np.max(np.abs(A1 - A))) / max(float(np.max(np.abs(A))), 1e-300),
                  float(np.max(np.abs(B1 - B))) / max(float(np.max(np.abs(B))), 1e-300))
        if not err <= SINGLE_PRECISION_RTOL:
            warnings.warn(f"{self.info.jacobian}: its float32 copy differs from it by {err:.1e} (relative, more than "
                          f"{SINGLE_PRECISION_RTOL:g}); the QP controllers use the float64 graph", stacklevel=3)
            return None
        return session


#: Largest relative difference (max |error| over max |entry|) of the float32 derivative graph's A and B from the
#: float64 one, on hover-like probe states, for :meth:`OnnxModel.linearize_single` to use it. The shipped models
#: agree to 5e-8 .. 7e-7.
SINGLE_PRECISION_RTOL = 1e-5


def parse_analytic(spec: str) -> dict[str, float]:
    """Scale factors of ``"analytic:NAME*F,NAME*F,..."`` (NAME one of m, Jxx, Jyy, Jzz, kt, kq; F > 0).

    ``"analytic:Jxx*1.3,Jyy*1.3,Jzz*1.3"`` is the nominal equations with every
    inertia 30 % too high: a deliberately wrong prediction model.
    """
    import re

    body = spec[len("analytic:"):]
    factors: dict[str, float] = {}
    for part in body.split(","):
        m = re.fullmatch(r"\s*(m|Jxx|Jyy|Jzz|kt|kq)\s*\*\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*", part)
        if m is None:
            raise ModelContractError(f"model {spec!r}: each part must be NAME*FACTOR with NAME in {', '.join(THETA_NAMES)} "
                                     f"and FACTOR > 0; found {part!r}")
        name, f = m.group(1), float(m.group(2))
        if not f > 0 or name in factors:
            raise ModelContractError(f"model {spec!r}: {name} needs one factor > 0; found {part!r}")
        factors[name] = f
    return factors


def analytic_name(factors: dict[str, float]) -> str:
    """File-name-safe name of a scaled analytic model, e.g. ``analytic-Jxx1.3-Jyy1.3``."""
    return "analytic-" + "-".join(f"{k}{v:g}" for k, v in factors.items())


def load_model(spec: str, threads: int = 1) -> PredictionModel:
    """A prediction model from its name.

    ``"oracle"``: the nominal equations with the reference parameters;
    ``"analytic:NAME*F,..."``: the nominal equations with parameters scaled
    (:func:`parse_analytic`); anything else: the path of an ONNX file.
    """
    if spec == "oracle":
        return AnalyticModel()
    if spec.startswith("analytic:"):
        factors = parse_analytic(spec)
        p = QuadParams()
        theta = [getattr(p, n) * factors.get(n, 1.0) for n in THETA_NAMES]
        return AnalyticModel(p.with_theta(theta), name=analytic_name(factors))
    return OnnxModel(spec, threads)


#: Model names that stand for equations rather than a file: the plant's own equations where they are known
#: (``oracle``), and the nominal rigid-body equations with the vehicle's values (``nominal``).
EQUATION_MODELS = ("oracle", "nominal")


def is_equation_model(model: str) -> bool:
    """True when the model name ``model`` stands for equations (:data:`EQUATION_MODELS`, ``analytic:...``) rather
    than an ONNX file."""
    return model in EQUATION_MODELS or model.startswith("analytic:")


def model_name(model: str) -> str:
    """The name a model has in results: ``oracle``, ``nominal``, ``analytic-<factors>``, or a file's stem."""
    from pathlib import Path

    if model.startswith("analytic:"):
        return analytic_name(parse_analytic(model))
    return model if model in EQUATION_MODELS else Path(model).stem


def model_params(model: str, plant: str, vehicle) -> QuadParams:
    """The parameters of the equation model ``model`` on ``plant`` (a name of :data:`sim.plants.named.PLANTS`)
    flying ``vehicle`` (a :class:`sim.vehicles.vehicle.Vehicle`).

    ``oracle``: the plant's own equations: on ``sim``, the equations
    with the vehicle's values (on a ``+highfi`` scenario with the vehicle's
    high-fidelity effects too, :func:`flown_model`); on ``rotorpy-ideal``, the same with no drag (that set-up has
    none); ``rotorpy`` (motor lag and aerodynamics) has no known equations
    and refuses it. ``nominal`` and ``analytic:...``: the nominal equations
    with the vehicle's values (scaled).
    """
    from sim.plants.named import known_equations

    from ..errors import ConfigurationError

    p = vehicle.params
    if model == "oracle":
        own = known_equations(plant, p)
        if own is None:
            raise ConfigurationError(f"plant {plant!r} has no known equations, so it has no oracle; fly --model "
                                     f"nominal (the rigid-body equations with the vehicle's values) or a learned "
                                     f"model")
        return own
    if model == "nominal":
        return p
    factors = parse_analytic(model)
    return p.with_theta([getattr(p, n) * factors.get(n, 1.0) for n in THETA_NAMES])


def flown_model(model: str, plant: str, vehicle, high_fidelity: bool = False,
                level: str = "wrench") -> PredictionModel:
    """The prediction model ``model`` flown on ``plant`` with ``vehicle`` at command level ``level``: an equation
    model (:data:`EQUATION_MODELS`, ``analytic:...``; :func:`model_params`) or the ONNX file ``model``.

    ``high_fidelity``: the equation model is the plant's high-fidelity equations, the vehicle's motor lag (four
    rotor-speed states), rotor drag and gyroscopic torque with the rigid body.

    At ``ctbr`` or ``ctatt`` (:mod:`sim.levels`) the equations take the command at that level: ``oracle`` is the
    plant's equations with the vehicle's inner loop exactly (its discrete controller stepped inside the period, its
    memory as extra states: :func:`sim.equations.levels_casadi.inner_loop_step_function`); ``nominal`` and
    ``analytic:...`` the rigid body with the loop's assumed response (:meth:`sim.vehicles.onboard.InnerLoopConfig.response`).
    An ONNX file must declare the level (its metadata ``level``).

    Raises
    ------
    ConfigurationError
        The file's level is another, or the oracle is asked at ``ctbr`` or ``ctatt`` of a plant whose loop is not
        this project's or of the high-fidelity set-up (:func:`check_level_oracle`).
    sim.errors.SimInputError
        At ``ctbr`` or ``ctatt``, the vehicle has no inner loop.
    """
    from sim.levels import DEFAULT_LEVEL, check_level

    from ..errors import ConfigurationError

    try:
        check_level(level)
    except Exception as e:
        raise ConfigurationError(str(e)) from None
    if not is_equation_model(model):
        loaded = load_model(model)
        if loaded.level != level:
            raise ConfigurationError(f"model {model!r} takes commands at the {loaded.level!r} level (metadata 'level'); "
                                     f"this run flies at {level!r}: a model flies only at the level it declares "
                                     f"(--level {loaded.level})")
        return loaded
    if level == DEFAULT_LEVEL:
        return AnalyticModel(model_params(model, plant, vehicle), name=model_name(model),
                             fidelity=vehicle.fidelity if high_fidelity else None)
    loop = vehicle.inner_loop_at(level)
    exact = model == "oracle"
    if exact:
        check_level_oracle(plant, level, high_fidelity)
    return AnalyticModel(model_params(model, plant, vehicle), name=model_name(model), level=level,
                         inner_loop=loop, exact_loop=exact)


def level_oracle_exists(plant: str, level: str, high_fidelity: bool = False) -> bool:
    """False where the oracle at ``level`` does not exist: at ``ctbr`` and ``ctatt`` it is this project's simulator
    with its own inner loop, so only on plant ``sim`` without the high-fidelity set-up (at the wrench level this
    says nothing: there the plant's known equations decide, :func:`model_params`)."""
    return level == "wrench" or (plant == "sim" and not high_fidelity)


def check_level_oracle(plant: str, level: str, high_fidelity: bool = False) -> None:
    """Raise :class:`ConfigurationError` where the oracle at ``level`` does not exist (:func:`level_oracle_exists`)."""
    from ..errors import ConfigurationError

    if not level_oracle_exists(plant, level, high_fidelity):
        raise ConfigurationError(
            f"the oracle at the {level!r} level is this project's plant with its own inner loop, nominal set-up: "
            f"{'the high-fidelity set-up' if plant == 'sim' else f'plant {plant!r}'} has no such equations here; "
            f"fly --model nominal (the rigid body with the loop's assumed response)")


class LinearModel(PredictionModel):
    """Affine model ``x_next = x0 + A (x - x0) + B (u - u0)`` (for example the hover linearization).

    Parameters
    ----------
    A : array_like, shape (12, 12)
    B : array_like, shape (12, 4)
    x0 : array_like, shape (12,)
    u0 : array_like, shape (4,)
    """

    def __init__(self, A, B, x0, u0, name: str = "linear"):
        self.A, self.B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
        self.x0, self.u0 = np.asarray(x0, dtype=float), np.asarray(u0, dtype=float)
        if self.A.shape != (NX, NX) or self.B.shape != (NX, NU):
            raise ModelContractError(f"A must be (12, 12) and B (12, 4); found {self.A.shape} and {self.B.shape}")
        self.name = name

    def step(self, x, u) -> np.ndarray:
        """Next states (N, 12)."""
        x, u = _batch(x, u)
        return self.x0 + (x - self.x0) @ self.A.T + (u - self.u0) @ self.B.T

    def linearize(self, x, u):
        """``(x_next, A, B)`` with the constant matrices repeated over the batch."""
        x, u = _batch(x, u)
        n = len(x)
        return self.step(x, u), np.repeat(self.A[None], n, 0), np.repeat(self.B[None], n, 0)
