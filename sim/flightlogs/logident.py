"""Identification from real flights: what the motion of imported flights can tell about a vehicle.

From motion alone (positions, attitudes, velocities, rates and rotor speeds)
a vehicle's absolute parameters are not identifiable: multiplying the mass,
the inertias and both rotor coefficients by one number changes no motion.
What the flights determine are ratios, fitted here by least squares on the
equations of motion, one equation at a time, on every usable sample (state,
rotor speeds and next state measured), with the accelerations taken as
forward differences over one period:

* along the body z axis, ``a_z = -(kt/m) sum n^2 - k_z v_z - c_z v_z |v_z| + b_z``;
  along body x and y, ``a = -k v - c v |v| + b`` (body-frame velocity, linear
  drag ``k`` in 1/s, quadratic drag ``c`` in 1/m, bias ``b`` in m/s^2);
* about each body axis, ``w' = g tau~ + c_gyro w_j w_k + b``: ``g`` is
  ``kt/Jxx``, ``kt/Jyy`` or ``kq/Jzz`` (``tau~`` is the torque per unit
  ``kt`` or ``kq`` from the rotor layout), ``c_gyro`` the inertia ratio of
  Euler's equations and ``b`` a torque bias per unit inertia.

Each coefficient gets its pooled estimate, the per-flight estimates and a
95 % interval of the pooled estimate from a jackknife over flights (the
pooled fit repeated with each flight left out; a t interval of that spread
around the pooled value, which stays honest when residuals are correlated
in time within a flight), and each equation its share of explained
variance. :func:`fisher_table` asks the
paper's Table II of the real flights: the Fisher information of the six
absolute parameters (m, Jxx, Jyy, Jzz, kt, kq) in these equations, whose
smallest eigenvalue is zero (the common scale), and the Cramer-Rao bounds
once the mass is fixed from the vehicle file.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..equations.dynamics import rotation_matrix
from ..params import DT, GRAVITY
from ..identification.jackknife import half_width
from ..vehicles.rotors import ROTOR_X, ROTOR_Y, SPIN
from .attitudeloop import AttitudeLoop
from .logbench import GOAL_H50, physics_step, rotation_angle

EQUATIONS = ("a_x", "a_y", "a_z", "p_dot", "q_dot", "r_dot")
PARAMS = ("m", "Jxx", "Jyy", "Jzz", "kt", "kq")


@dataclass(frozen=True)
class Coefficient:
    """One fitted coefficient: pooled value, per-flight values and a 95 % interval of the pooled value."""

    name: str
    unit: str
    value: float              # pooled least squares over every flight
    per_flight: tuple         # one value per flight
    low: float                # 95 % interval of the pooled value: value -+ t * jackknife standard error over
    high: float               # flights (NaN with one flight)

    @property
    def relative_spread(self) -> float:
        """Standard deviation over flights relative to the pooled value."""
        return float(np.std(self.per_flight, ddof=1) / abs(self.value)) if len(self.per_flight) > 1 else math.nan


@dataclass(frozen=True)
class RealIdentification:
    """What the flights determine (see the module docstring)."""

    coefficients: dict        # name -> Coefficient
    explained: dict           # equation -> share of its variance the fit explains (pooled)
    samples: int
    flights: tuple            # names
    delays: tuple             # samples, per flight (from the import)

    def value(self, name: str) -> float:
        """Pooled value of a coefficient."""
        return self.coefficients[name].value


def _regressors(f, layout_lever: float):
    """Targets and regressors of the six equations on the usable samples of one flight.

    The accelerations are forward differences over the period ``[k, k + 1]``, so the state-dependent regressors
    are the means of their values at ``k`` and ``k + 1`` (the rotor speeds are held over the period): that leaves a
    bias of second order in the period instead of first.
    """
    x, n2 = np.asarray(f.x), np.asarray(f.rotor_speed) ** 2
    ok = np.asarray(f.x_ok)
    rok = np.asarray(f.rotor_ok)
    k = np.flatnonzero(ok[:-1] & ok[1:] & rok[:-1])
    R0 = rotation_matrix(x[k, 3], x[k, 4], x[k, 5])
    R1 = rotation_matrix(x[k + 1, 3], x[k + 1, 4], x[k + 1, 5])
    Rm = 0.5 * (R0 + R1)
    acc = (x[k + 1, 9:12] - x[k, 9:12]) / DT - np.array([0.0, 0.0, GRAVITY])
    a_b = np.linalg.solve(Rm, acc[:, :, None])[:, :, 0]      # specific force in the period's mean body frame
    v_b0 = np.einsum("nji,nj->ni", R0, x[k, 9:12])
    v_b1 = np.einsum("nji,nj->ni", R1, x[k + 1, 9:12])
    w0, w1 = x[k, 6:9], x[k + 1, 6:9]
    wdot = (w1 - w0) / DT
    s = n2[k].sum(axis=1)
    tx = n2[k] @ (-layout_lever * ROTOR_Y)
    ty = n2[k] @ (layout_lever * ROTOR_X)
    tz = n2[k] @ SPIN
    one = np.ones(len(k))

    def mean(g):
        return 0.5 * (g(v_b0) + g(v_b1))

    rows = {}
    for j, axis in enumerate("xy"):
        rows[f"a_{axis}"] = (a_b[:, j], np.stack([-mean(lambda v: v[:, j]),
                                                  -mean(lambda v: v[:, j] * np.abs(v[:, j])), one], -1))
    rows["a_z"] = (a_b[:, 2], np.stack([-s, -mean(lambda v: v[:, 2]), -mean(lambda v: v[:, 2] * np.abs(v[:, 2])),
                                        one], -1))
    gyro = [0.5 * (w0[:, i] * w0[:, j] + w1[:, i] * w1[:, j]) for i, j in ((1, 2), (0, 2), (0, 1))]
    rows["p_dot"] = (wdot[:, 0], np.stack([tx, gyro[0], one], -1))
    rows["q_dot"] = (wdot[:, 1], np.stack([ty, gyro[1], one], -1))
    rows["r_dot"] = (wdot[:, 2], np.stack([tz, gyro[2], one], -1))
    return rows


#: Coefficient names (and units) of each equation's regressors, in order.
_COEFS = {
    "a_x": (("k_x", "1/s"), ("c_x", "1/m"), ("b_x", "m/s^2")),
    "a_y": (("k_y", "1/s"), ("c_y", "1/m"), ("b_y", "m/s^2")),
    "a_z": (("kt/m", "m/s^2 per (rad/s)^2"), ("k_z", "1/s"), ("c_z", "1/m"), ("b_z", "m/s^2")),
    "p_dot": (("kt/Jxx", "1/s^2 per (rad/s)^2 m"), ("(Jyy-Jzz)/Jxx", "1"), ("b_p", "rad/s^2")),
    "q_dot": (("kt/Jyy", "1/s^2 per (rad/s)^2 m"), ("(Jzz-Jxx)/Jyy", "1"), ("b_q", "rad/s^2")),
    "r_dot": (("kq/Jzz", "1/s^2 per (rad/s)^2"), ("(Jxx-Jyy)/Jzz", "1"), ("b_r", "rad/s^2")),
}


def identify(flights, vehicle) -> RealIdentification:
    """Fit the ratios, drags and biases of the module docstring on ``flights`` (imported, rotor speeds in rad/s).

    ``vehicle`` gives the rotor layout's lever (``d / sqrt(2)``); its ``kt``, ``kq``, mass and inertias are not used.
    """
    lever = vehicle.d / math.sqrt(2.0)
    per = [_regressors(f, lever) for f in flights]
    coefficients, explained = {}, {}
    for eq, names in _COEFS.items():
        y = np.concatenate([p[eq][0] for p in per])
        A = np.concatenate([p[eq][1] for p in per])
        pooled, *_ = np.linalg.lstsq(A, y, rcond=None)
        explained[eq] = float(1.0 - np.var(y - A @ pooled) / np.var(y))
        each = np.array([np.linalg.lstsq(p[eq][1], p[eq][0], rcond=None)[0] for p in per])
        half = half_width([(p[eq][1], p[eq][0]) for p in per])
        for j, (name, unit) in enumerate(names):
            coefficients[name] = Coefficient(name=name, unit=unit, value=float(pooled[j]),
                                             per_flight=tuple(float(v) for v in each[:, j]),
                                             low=float(pooled[j] - half[j]), high=float(pooled[j] + half[j]))
    return RealIdentification(coefficients=coefficients, explained=explained,
                              samples=int(sum(len(p["a_z"][0]) for p in per)),
                              flights=tuple(f.name for f in flights),
                              delays=tuple(int(f.report.delay_samples) for f in flights))


def _bounds(info: np.ndarray) -> np.ndarray:
    """Cramer-Rao standard deviation of each parameter from the information ``info`` (n x n).

    A direction whose eigenvalue is at most ``1e-10`` of the largest is one the data do not see: a parameter
    with a part in such a direction has no finite bound (infinity; null in JSON), as when the flights never
    excite a torque. The others are bounded by the pseudo-inverse, which for them equals the inverse.
    """
    lam, vec = np.linalg.eigh(info)
    seen = lam > 1e-10 * max(lam[-1], 0.0)
    var = np.einsum("ij,j,ij->i", vec[:, seen], 1.0 / lam[seen], vec[:, seen])
    blind = np.abs(vec[:, ~seen]).max(axis=1, initial=0.0) > 1e-6
    return np.where(blind, np.inf, np.sqrt(var))


def fisher_table(flights, vehicle, ident: RealIdentification) -> dict:
    """Fisher information of (m, Jxx, Jyy, Jzz, kt, kq) in the z-force and the three rotational equations.

    The parameters enter as the ratios the equations hold (``kt/m``, ``kt/Jxx``, ``kt/Jyy``, ``kq/Jzz`` and the
    inertia ratios of Euler's equations), evaluated at the vehicle file's values, with each equation's residual
    variance taken from the fit ``ident``. Returns the eigenvalues of the information in relative parameters
    (``d theta / theta``, smallest first), the direction of the smallest, and the Cramer-Rao bound (relative
    standard deviation) of each parameter with the mass fixed, infinite for one the flights cannot bound.
    """
    lever = vehicle.d / math.sqrt(2.0)
    theta0 = np.array([vehicle.m, vehicle.Jxx, vehicle.Jyy, vehicle.Jzz, vehicle.kt, vehicle.kq])
    per = [_regressors(f, lever) for f in flights]

    def predict(theta, eq, A):
        m, jx, jy, jz, kt, kq = theta
        if eq == "a_z":
            return -kt / m * A[:, 0]
        if eq == "p_dot":
            return kt / jx * A[:, 0] + (jy - jz) / jx * A[:, 1]
        if eq == "q_dot":
            return kt / jy * A[:, 0] + (jz - jx) / jy * A[:, 1]
        return kq / jz * A[:, 0] + (jx - jy) / jz * A[:, 1]

    F = np.zeros((6, 6))
    for eq in ("a_z", "p_dot", "q_dot", "r_dot"):
        y = np.concatenate([p[eq][0] for p in per])
        A = np.concatenate([p[eq][1] for p in per])
        names = [c for c, _ in _COEFS[eq]]
        coef = np.array([ident.value(c) for c in names])
        sigma2 = float(np.var(y - A @ coef))
        S = np.empty((len(y), 6))
        for i in range(6):                       # sensitivities to relative parameter changes, central differences
            h = 1e-6
            up, dn = theta0.copy(), theta0.copy()
            up[i] *= 1 + h
            dn[i] *= 1 - h
            S[:, i] = (predict(up, eq, A) - predict(dn, eq, A)) / (2 * h)
        F += S.T @ S / sigma2
    evals, evecs = np.linalg.eigh(F)
    null = evecs[:, 0] * np.sign(evecs[np.argmax(np.abs(evecs[:, 0])), 0])
    crlb = _bounds(F[1:, 1:])
    return {
        "parameters": list(PARAMS),
        "eigenvalues": [float(e) for e in evals],
        "weakest_direction": [float(v) for v in null],
        "crlb_relative_with_m_fixed": dict(zip(PARAMS[1:], (float(c) for c in crlb))),
        "residual_note": "one-step equation error; samples treated as independent (bounds are optimistic when "
                         "residuals are correlated in time)",
    }


def identified_model(ident: RealIdentification, vehicle, hold_rates: bool = True) -> dict:
    """Keyword arguments of :func:`sim.flightlogs.logbench.physics_step` for the identified vehicle.

    The mass is the vehicle file's (the flights cannot tell it); ``kt`` follows from ``kt/m``, ``Jxx`` and ``Jyy``
    from ``kt/Jxx`` and ``kt/Jyy``, and ``Jzz`` from ``kq/Jzz`` with the vehicle file's ``kq``. The drags and the
    z bias are the fitted ones (x and y biases too). The inertia ratios of the fit are not used: the rigid body's
    own are. The logged wrench was computed with the vehicle file's ``kt``: ``wrench_gain`` rescales its thrust and
    roll and pitch torques to the identified ``kt`` (the yaw torque keeps the file's ``kq``).
    """
    v = ident.value
    kt = v("kt/m") * vehicle.m
    p = dataclasses.replace(vehicle.params, kt=kt, Jxx=kt / v("kt/Jxx"), Jyy=kt / v("kt/Jyy"),
                            Jzz=vehicle.kq / v("kq/Jzz"), c_d=0.0)
    g = kt / vehicle.kt
    return {"p": p, "hold_rates": hold_rates, "wrench_gain": (g, g, g, 1.0),
            "linear_drag": (v("k_x"), v("k_y"), v("k_z")),
            "quadratic_drag": (v("c_x"), v("c_y"), v("c_z")), "accel_bias": (v("b_x"), v("b_y"), v("b_z"))}


def identified_vehicle(ident, vehicle):
    """The vehicle file's vehicle with the identified rigid body: ``kt`` from ``kt/m`` (mass fixed), ``Jxx`` and
    ``Jyy`` from the torque gains, ``Jzz`` from ``kq/Jzz`` with the file's ``kq``. The fitted drags are left out
    (:func:`with_identified_drag` puts the horizontal one on a vehicle as rotor drag)."""
    p = identified_model(ident, vehicle)["p"]
    return vehicle.replace(name=f"{vehicle.name}-identified", kt=p.kt, Jxx=p.Jxx, Jyy=p.Jyy, Jzz=p.Jzz,
                           source=f"{vehicle.name} with kt, Jxx, Jyy and Jzz identified from real flights "
                                  f"(pinnmpc realdata); m and kq as stated")


def rotor_drag_for(linear_drag: float, vehicle) -> float:
    """The in-plane rotor drag per rotor (``rotor_drag``, N s / (m RU)) that gives ``vehicle`` at its hover rotor
    speed the horizontal body drag ``linear_drag`` (1/s, as an acceleration per unit body velocity).

    The plants' rotor drag is ``F = -rotor_drag * (n_1 + ... + n_4) * (v_bx, v_by, 0)``: at hover, with four rotors
    at ``n_hover``, a linear drag ``4 rotor_drag n_hover / m``.
    """
    if not math.isfinite(linear_drag) or linear_drag < 0:
        raise ValueError(f"linear_drag must be finite and >= 0 (1/s); found {linear_drag!r}")
    return float(linear_drag) * vehicle.m / (4.0 * vehicle.params.n_hover)


def with_identified_drag(vehicle, ident: RealIdentification):
    """``vehicle`` with the horizontal linear body drag identified from its flights, as rotor drag
    (:func:`rotor_drag_for` of the mean of ``k_x`` and ``k_y``; none when that mean is negative); everything else as
    in the file.

    The rest of the fitted drag stays out: the vertical drag ``k_z``, because our plant's rotor drag is in-plane (only
    RotorPy's ``k_z`` could carry it, and both plants are to fly the same vehicle), and the quadratic drags, which
    neither plant has in this form (fitted negative on the nano-drone benchmark: they trim the linear drag at speed).
    """
    k = 0.5 * (ident.value("k_x") + ident.value("k_y"))
    if not math.isfinite(k):
        raise ValueError(f"the identified horizontal drag (k_x, k_y) is not finite ({k!r}): the flights cannot tell it")
    return vehicle.replace(name=f"{vehicle.name}-drag", rotor_drag=rotor_drag_for(max(k, 0.0), vehicle),
                           source=f"{vehicle.name} as stated, with the horizontal linear drag identified from real "
                                  f"flights (k_x, k_y mean {k:.4g} 1/s; pinnmpc realdata) as rotor drag at hover")


@dataclass(frozen=True)
class AttitudeLoopFit:
    """The onboard attitude loop fitted to open-loop predictions (:func:`fit_attitude_loop`)."""

    loop: AttitudeLoop
    cost: float               # mean of the squared goal-normalized errors at the fitted horizons
    initial_cost: float       # the same for the initial coefficients
    evaluations: int          # predictions of every window made by the fit
    windows: int              # window starts used
    converged: bool           # the optimizer met a tolerance before its evaluation budget


#: The fit's horizons (steps) and every how many window starts it uses.
LOOP_HORIZONS = (10, 25, 50)
LOOP_STRIDE = 20
#: RK4 substeps a period of the attitude loop's predictions, in its fit and wherever the fitted loop predicts: its
#: coefficients belong to this integration (the yaw damping fitted on the benchmark's logs, 268 1/s, is near one
#: RK4 step's stability limit; with ten substeps the same coefficients give other yaw rates at short horizons).
LOOP_SUBSTEPS = 1
#: The fit's initial coefficients: damped, mildly stiff, no torque, no lead.
LOOP_INITIAL = AttitudeLoop(damping=(2.0, 2.0, 2.0), stiffness=(10.0, 10.0), torque_gain=(0.0, 0.0, 0.0))
#: Typical sizes of the coefficients (the optimizer's scaling), in :meth:`AttitudeLoop.vector` order.
_LOOP_SCALE = np.array([1.0, 1.0, 1.0, 10.0, 10.0, 0.05, 0.2, 0.2, 1.0, 0.5, 0.5, 0.5, 0.05])
#: The fit reports its progress every this many predictions of the windows.
LOOP_PROGRESS_EVERY = 200
#: An error that is not finite (a prediction that diverged) counts as this many goals.
_DIVERGED = 10.0


def fit_attitude_loop(flights, physics_kw: dict, initial: AttitudeLoop = LOOP_INITIAL, fixed=(),
                      horizons=LOOP_HORIZONS, stride: int = LOOP_STRIDE, max_evaluations: int = 150,
                      progress=None) -> AttitudeLoopFit:
    """Fit the onboard attitude loop's coefficients to open-loop predictions of ``flights``.

    The model is :func:`sim.flightlogs.logbench.physics_step` with ``physics_kw`` (the identified rigid body and
    drags) and an :class:`~sim.flightlogs.attitudeloop.AttitudeLoop`. From every ``stride``-th measured window start
    of each flight it predicts ``max(horizons)`` steps with the logged inputs, and the fit minimizes (trust-region
    least squares, finite-difference Jacobian) the sum over windows and ``horizons`` of the squared position,
    velocity, rotation and body-rate errors, each over its goal (:data:`sim.flightlogs.logbench.GOAL_H50`): the
    benchmark's own score, asked of the training flights. The damping and stiffness are kept at or above zero.
    The predictions take :data:`LOOP_SUBSTEPS` RK4 substeps a period: predict with the fitted loop as it was fitted.
    The fields named in ``fixed`` (say ``("velocity_gain",)``) keep their ``initial`` value.
    ``progress``, if given, is called with a line every :data:`LOOP_PROGRESS_EVERY` predictions of the windows.
    """
    from scipy.optimize import least_squares

    horizons = tuple(int(h) for h in horizons)
    if stride < 1 or not horizons or min(horizons) < 1:
        raise ValueError(f"stride must be >= 1 and horizons non-empty; found {stride!r}, {horizons!r}")
    H = max(horizons)
    x0, us, targets, oks = [], [], [], []           # every window of every flight in one batch
    for f in flights:
        x, u, ok = np.asarray(f.x, dtype=float), np.asarray(f.u, dtype=float), np.asarray(f.x_ok, dtype=bool)
        i = np.flatnonzero(ok[: max(len(x) - H, 0)])[::stride]
        if len(i):
            x0.append(x[i])
            us.append(u[i[:, None] + np.arange(H)])
            targets.append(x[i[:, None] + np.asarray(horizons)])
            oks.append(ok[i[:, None] + np.asarray(horizons)])
    if not x0:
        raise ValueError(f"no flight has a measured window of {H} steps to fit the attitude loop on")
    x0, us, targets, oks = (np.concatenate(a) for a in (x0, us, targets, oks))
    kw = {k: v for k, v in physics_kw.items() if k not in ("hold_rates", "substeps")}
    goals = np.array([GOAL_H50[q] for q in ("position", "velocity", "rotation", "angular_velocity")])

    v0 = initial.vector()
    if set(fixed) - set(AttitudeLoop.SIZES) or set(fixed) >= set(AttitudeLoop.SIZES):
        raise ValueError(f"fixed must name some of the fields {tuple(AttitudeLoop.SIZES)}; found {tuple(fixed)!r}")
    free = np.concatenate([np.full(n, name not in fixed) for name, n in AttitudeLoop.SIZES.items()])

    def full(w):
        v = v0.copy()
        v[free] = w
        return v

    calls = [0]

    def residuals(w):
        calls[0] += 1
        if progress is not None and calls[0] % LOOP_PROGRESS_EVERY == 0:
            progress(f"  attitude loop: {calls[0]} predictions of {len(x0)} windows")
        loop = AttitudeLoop.from_vector(full(w))
        step = physics_step(**kw, substeps=LOOP_SUBSTEPS, attitude_loop=loop)
        out = []
        z = loop.start(x0)
        for k in range(1, H + 1):
            z = step(z, us[:, k - 1])
            if k in horizons:
                j = horizons.index(k)
                keep = oks[:, j]
                xt, zp = targets[keep, j], z[keep]
                out.append(np.linalg.norm(zp[:, 0:3] - xt[:, 0:3], axis=1) / goals[0])
                out.append(np.linalg.norm(zp[:, 9:12] - xt[:, 9:12], axis=1) / goals[1])
                out.append(rotation_angle(zp[:, 3:6], xt[:, 3:6]) / goals[2])
                out.append(np.linalg.norm(zp[:, 6:9] - xt[:, 6:9], axis=1) / goals[3])
        r = np.concatenate(out)
        return np.nan_to_num(r, nan=_DIVERGED, posinf=_DIVERGED, neginf=_DIVERGED) / math.sqrt(len(r))

    lower = np.full(len(v0), -np.inf)
    lower[:5] = 0.0                                        # damping and stiffness
    with np.errstate(all="ignore"):
        cost0 = float(np.sum(residuals(v0[free]) ** 2))
        sol = least_squares(residuals, np.maximum(v0, lower)[free], bounds=(lower[free], np.inf),
                            x_scale=_LOOP_SCALE[free], diff_step=1e-3, max_nfev=max_evaluations)
    return AttitudeLoopFit(loop=AttitudeLoop.from_vector(full(sol.x)), cost=float(2.0 * sol.cost), initial_cost=cost0,
                           evaluations=int(sol.nfev + sol.njev * int(free.sum())),
                           windows=len(x0), converged=bool(sol.status > 0))
