"""Rigid-body quadrotor dynamics, CasADi backend.

The same nominal model as :func:`sim.equations.dynamics.dynamics`, written with CasADi
operations so that it can be differentiated (Fisher information, MPC).
Parameters may be numbers or CasADi symbols.
"""

from __future__ import annotations

from collections.abc import Mapping

import casadi as ca

from ..params import DT, NU, NX, SUBSTEPS, THETA_NAMES, QuadParams
from ..vehicles.rotors import SPIN, mixer


def _get(p, name):
    return p[name] if isinstance(p, Mapping) else getattr(p, name)


def dynamics_casadi(x, u, p=None, accel=None, torque=None):
    """Symbolic ``dx/dt`` of the nominal model.

    Parameters
    ----------
    x : casadi.SX or casadi.MX, shape (12, 1)
        State in the order of :data:`sim.params.STATE_NAMES`.
    u : casadi.SX or casadi.MX, shape (4, 1)
        Wrench ``[T, tau_x, tau_y, tau_z]`` in N, N m.
    p : QuadParams or mapping, optional
        Parameters; a mapping may hold CasADi symbols for any of ``m, Jxx,
        Jyy, Jzz, kt, kq, g, c_d, d``. Reference values when omitted.
    accel : casadi expression, shape (3, 1), optional
        Extra world-frame acceleration (wind, rotor drag), m/s^2.
    torque : casadi expression, shape (3, 1), optional
        Extra body-frame torque (rotor gyroscopic torque), N m.

    Returns
    -------
    casadi expression, shape (12, 1)
    """
    p = QuadParams() if p is None else p
    phi, th, psi = x[3], x[4], x[5]
    wp, wq, wr = x[6], x[7], x[8]
    vx, vy, vz = x[9], x[10], x[11]
    thrust, tx, ty, tz = u[0], u[1], u[2], u[3]
    if torque is not None:
        tx, ty, tz = tx + torque[0], ty + torque[1], tz + torque[2]
    m, Jxx, Jyy, Jzz = _get(p, "m"), _get(p, "Jxx"), _get(p, "Jyy"), _get(p, "Jzz")
    g, c_d = _get(p, "g"), _get(p, "c_d")

    sphi, cphi = ca.sin(phi), ca.cos(phi)
    sth, cth = ca.sin(th), ca.cos(th)
    spsi, cpsi = ca.sin(psi), ca.cos(psi)

    qs_rc = wq * sphi + wr * cphi
    phid = wp + qs_rc * (sth / cth)
    thd = wq * cphi - wr * sphi
    psid = qs_rc / cth

    pd = ((Jyy - Jzz) * wq * wr + tx) / Jxx
    qd = ((Jzz - Jxx) * wp * wr + ty) / Jyy
    rd = ((Jxx - Jyy) * wp * wq + tz) / Jzz

    tm = thrust / m
    ax = -tm * (cpsi * sth * cphi + spsi * sphi) - c_d * vx * ca.fabs(vx)
    ay = -tm * (spsi * sth * cphi - cpsi * sphi) - c_d * vy * ca.fabs(vy)
    az = g - tm * (cth * cphi) - c_d * vz * ca.fabs(vz)
    if accel is not None:
        ax, ay, az = ax + accel[0], ay + accel[1], az + accel[2]
    return ca.vertcat(vx, vy, vz, phid, thd, psid, pd, qd, rd, ax, ay, az)


def wrench_from_rotor_sq_casadi(n_sq, p=None):
    """Symbolic wrench (4, 1) from rotor speeds squared (4, 1), with ``kt, kq`` from ``p``."""
    p = QuadParams() if p is None else p
    lever = _get(p, "d") / 2.0 ** 0.5
    rows = mixer(_get(p, "kt"), _get(p, "kq"), lever)
    return ca.vertcat(*[sum(r[i] * n_sq[i] for i in range(4)) for r in rows])


#: Built step functions by their arguments (see :func:`_memo`), at most MEMO_SIZE (then forgotten at once).
_BUILT: dict = {}
MEMO_SIZE = 128


def _memo(build):
    """``build`` (a function of hashable arguments returning a CasADi function) remembered per process.

    A period's step takes 0.1-0.3 s to build and every flight builds its plant's and its model's; CasADi
    functions are immutable, so flights with the same vehicle share one. Arguments that cannot be hashed build
    anew.
    """
    import functools

    @functools.wraps(build)
    def remembered(*args, **kwargs):
        key = (build.__name__, args, tuple(sorted(kwargs.items())))
        try:
            hash(key)
        except TypeError:
            return build(*args, **kwargs)
        if key not in _BUILT:
            if len(_BUILT) >= MEMO_SIZE:
                _BUILT.clear()
            _BUILT[key] = build(*args, **kwargs)
        return _BUILT[key]
    return remembered


def rk4_casadi(f, x, h, n):
    """``n`` classical RK4 steps of size ``h`` of ``x' = f(x)`` (symbolic)."""
    for _ in range(n):
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.5 * h * k2)
        k4 = f(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


@_memo
def step_function(p: QuadParams | None = None, *, symbolic_theta: bool = False,
                  inputs: str = "wrench", dt: float = DT, substeps: int = SUBSTEPS,
                  accel_input: bool = False) -> ca.Function:
    """CasADi function for one control period of the nominal model.

    Parameters
    ----------
    p : QuadParams, optional
        Fixed parameters (reference values when omitted).
    symbolic_theta : bool
        If True the function takes a third argument ``theta`` (6,) with
        ``(m, Jxx, Jyy, Jzz, kt, kq)``; otherwise ``theta`` comes from ``p``.
    inputs : {"wrench", "motor"}
        ``"wrench"``: ``u`` is the wrench (4,). ``"motor"``: ``u`` is the
        rotor speeds squared (4,), RU^2, turned into a wrench with ``kt, kq``.
    dt : float
        Control period, s (input held constant over it).
    substeps : int
        RK4 substeps per period.
    accel_input : bool
        If True the function takes a last argument ``accel`` (3,): a world-frame
        acceleration (wind), m/s^2, held over the period.

    Returns
    -------
    casadi.Function
        ``F(x, u[, theta][, accel]) -> x_next``.
    """
    p = QuadParams() if p is None else p
    x = ca.SX.sym("x", NX)
    u = ca.SX.sym("u", NU)
    args = [x, u]
    vals = {n: getattr(p, n) for n in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "g", "c_d", "d")}
    if symbolic_theta:
        theta = ca.SX.sym("theta", 6)
        vals.update({n: theta[i] for i, n in enumerate(THETA_NAMES)})
        args.append(theta)
    if inputs == "motor":
        w = wrench_from_rotor_sq_casadi(u, vals)
    elif inputs == "wrench":
        w = u
    else:
        raise ValueError(f"inputs must be 'wrench' or 'motor'; found {inputs!r}")
    names = ["x", "u", "theta"][:len(args)]
    a = None
    if accel_input:
        a = ca.SX.sym("accel", 3)
        args.append(a)
        names.append("accel")
    x_next = rk4_casadi(lambda s: dynamics_casadi(s, w, vals, a), x, dt / substeps, substeps)
    return ca.Function("step", args, [x_next], names, ["x_next"])


def rotation_matrix_casadi(phi, theta, psi):
    """Symbolic body-to-world rotation R = Rz(psi) Ry(theta) Rx(phi) (3, 3), as
    :func:`sim.equations.dynamics.rotation_matrix`."""
    sphi, cphi = ca.sin(phi), ca.cos(phi)
    sth, cth = ca.sin(theta), ca.cos(theta)
    spsi, cpsi = ca.sin(psi), ca.cos(psi)
    return ca.vertcat(
        ca.horzcat(cpsi * cth, cpsi * sth * sphi - spsi * cphi, cpsi * sth * cphi + spsi * sphi),
        ca.horzcat(spsi * cth, spsi * sth * sphi + cpsi * cphi, spsi * sth * cphi - cpsi * sphi),
        ca.horzcat(-sth, cth * sphi, cth * cphi))


def high_fidelity_rates_casadi(x, w, n, p, fidelity, accel=None):
    """Symbolic ``dx/dt`` of the high-fidelity simulator's rigid body (12, 1), as ``Simulator._rates_hifi``.

    ``w`` is the wrench (4, 1) acting now, ``n`` the rotor speeds (4, 1, RU) that drive rotor drag and the
    gyroscopic torque, ``fidelity`` a :class:`sim.params.Fidelity` (its motor lag is the caller's).
    """
    torque = None
    m = _get(p, "m")
    if fidelity.rotor_drag > 0.0:
        R = rotation_matrix_casadi(x[3], x[4], x[5])
        v_b = R.T @ x[9:12]
        k = -fidelity.rotor_drag * ca.sum1(n)
        f_b = ca.vertcat(k * v_b[0], k * v_b[1], 0.0)
        a_drag = (R @ f_b) / m
        accel = a_drag if accel is None else a_drag + accel
    if fidelity.rotor_gyro > 0.0:
        omega_r = sum(float(SPIN[i]) * n[i] for i in range(4))
        torque = ca.vertcat(-fidelity.rotor_gyro * omega_r * x[7], fidelity.rotor_gyro * omega_r * x[6], 0.0)
    return dynamics_casadi(x, w, p, accel, torque)


def lagged_rates_casadi(z, n_cmd, p, fidelity, tau, accel=None):
    """Symbolic ``dz/dt`` (16, 1) of the rigid body and its four lagging rotors, ``z = (x, n)``.

    The wrench comes from the rotor speeds ``n`` (RU), which follow their commands ``n_cmd`` through a first-order
    lag of time constant ``tau`` (s; a number or a symbol); the rigid body feels the high-fidelity effects of
    ``fidelity`` (:func:`high_fidelity_rates_casadi`; none for the nominal fidelity) and the extra acceleration
    ``accel``. The plant's step, the high-fidelity prediction model and the lag-aware estimator all use it.
    """
    x, n = z[:NX], z[NX:]
    w_now = wrench_from_rotor_sq_casadi(n * n, p)
    return ca.vertcat(high_fidelity_rates_casadi(x, w_now, n, p, fidelity, accel), (n_cmd - n) / tau)


@_memo
def high_fidelity_step_function(p: QuadParams, fidelity, *, dt: float = DT, substeps: int = SUBSTEPS) -> ca.Function:
    """CasADi function for one period of the high-fidelity simulator (one vehicle), as ``Simulator.step_full``.

    ``F(x (12), n0 (4), n_cmd (4), w (4), accel (3)) -> (x_next (12), n_next (4))``: with a motor lag the rotors
    start at ``n0`` and follow ``n_cmd`` (RU) through the first-order lag, and the wrench comes from their speeds
    (``w`` is unused); without one they run at ``n_cmd`` and ``w`` (N, N m) acts, and ``n_next = n_cmd``.
    ``accel`` (m/s^2) is the wind; ``p``'s mass should include a payload.
    """
    x, n0, n_cmd = ca.SX.sym("x", NX), ca.SX.sym("n0", 4), ca.SX.sym("n_cmd", 4)
    w, a = ca.SX.sym("w", NU), ca.SX.sym("accel", 3)
    vals = {k: getattr(p, k) for k in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "g", "c_d", "d")}
    h = dt / substeps
    tau = fidelity.motor_tau
    if tau > 0.0:
        z = rk4_casadi(lambda s: lagged_rates_casadi(s, n_cmd, vals, fidelity, tau, a), ca.vertcat(x, n0), h, substeps)
        x_next, n_next = z[:NX], z[NX:]
    else:
        x_next = rk4_casadi(lambda s: high_fidelity_rates_casadi(s, w, n_cmd, vals, fidelity, a), x, h, substeps)
        n_next = n_cmd
    return ca.Function("step_high_fidelity", [x, n0, n_cmd, w, a], [x_next, n_next],
                       ["x", "n0", "n_cmd", "w", "accel"], ["x_next", "n_next"])


def rotor_command_casadi(u, p, n_max_sq):
    """Symbolic rotor speeds (4, 1, RU) the rotor layer commands for the wrench ``u`` (4, 1), as
    :func:`sim.vehicles.rotors.realize`.

    Each ``n_i^2`` of the allocation is clipped to ``[0, n_max_sq]``, as in the plant; the lower bound is
    lifted to ``1e-9 n_max_sq`` so that the square root stays differentiable (a rotor asked for less than
    3e-5 of its top speed, which the controllers never do).
    """
    n_sq = ca.fmin(ca.fmax(allocate_casadi(u, p), 1e-9 * n_max_sq), n_max_sq)
    return ca.sqrt(n_sq)


def allocate_casadi(w, p):
    """Symbolic unclipped ``n^2`` (4, 1), RU^2, that produces the wrench ``w`` (4, 1), as
    :func:`sim.vehicles.rotors.allocate`, with ``kt, kq, d`` from ``p``."""
    kt, kq, lever = _get(p, "kt"), _get(p, "kq"), _get(p, "d") / 2.0 ** 0.5
    rows = mixer(kt, kq, lever)
    # The mixer's rows are orthogonal, so its inverse is its transpose with each row divided by its squared norm.
    norms = [4.0 * kt * kt, 4.0 * (kt * lever) ** 2, 4.0 * (kt * lever) ** 2, 4.0 * kq * kq]
    return ca.vertcat(*[sum(rows[r][i] * w[r] / norms[r] for r in range(4)) for i in range(4)])


@_memo
def actuated_step_function(p: QuadParams, fidelity, *, symbolic_theta: bool = False, dt: float = DT,
                           substeps: int = SUBSTEPS, composed: bool = False) -> ca.Function:
    """One control period of the high-fidelity simulator's equations as a prediction model (CasADi).

    ``F(z, u[, theta]) -> z_next``. ``u`` is the wrench command (4,), N and N m, turned into rotor commands
    as the plant does (:func:`rotor_command_casadi`). With a motor lag (``fidelity.motor_tau > 0``) the state
    ``z`` (16,) is the rigid-body state followed by the four rotor speeds (RU), which follow their commands
    through the lag; without one ``z`` is the rigid-body state (12,) and the rotors run at their commands.
    Rotor drag and gyroscopic torque act as in :meth:`sim.Simulator.step_full`. With ``symbolic_theta`` the
    function takes ``theta = (m, Jxx, Jyy, Jzz, kt, kq)`` (6,) as its third argument.

    ``composed``: the period as ``substeps`` calls of one RK4 substep function (an MX graph) instead of one
    expanded expression. The same arithmetic; its derivatives generate about a tenth of the C code, which
    compiles in seconds instead of a minute.
    """
    vals = {k: getattr(p, k) for k in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "g", "c_d", "d")}
    lag = fidelity.motor_tau > 0.0
    nz = NX + 4 if lag else NX
    z, u = ca.SX.sym("z", nz), ca.SX.sym("u", NU)
    args_extra, names_extra = [], []
    if symbolic_theta:
        theta = ca.SX.sym("theta", 6)
        vals.update({n: theta[i] for i, n in enumerate(THETA_NAMES)})
        args_extra, names_extra = [theta], ["theta"]
    n_cmd = rotor_command_casadi(u, vals, p.n_max_sq)
    h = dt / substeps
    tau = fidelity.motor_tau
    if lag:
        def f(s):
            return lagged_rates_casadi(s, n_cmd, vals, fidelity, tau)
    else:
        w = wrench_from_rotor_sq_casadi(n_cmd * n_cmd, vals)

        def f(s):
            return high_fidelity_rates_casadi(s, w, n_cmd, vals, fidelity)
    if not composed:
        z_next = rk4_casadi(f, z, h, substeps)
        return ca.Function("step_actuated", [z, u, *args_extra], [z_next], ["x", "u", *names_extra], ["x_next"])
    sub = ca.Function("actuated_substep", [z, u, *args_extra], [rk4_casadi(f, z, h, 1)])
    Z, U = ca.MX.sym("z", nz), ca.MX.sym("u", NU)
    extra = [ca.MX.sym("theta", 6)] if symbolic_theta else []
    zz = Z
    for _ in range(substeps):
        zz = sub(zz, U, *extra)
    return ca.Function("step_actuated", [Z, U, *extra], [zz], ["x", "u", *names_extra], ["x_next"])
