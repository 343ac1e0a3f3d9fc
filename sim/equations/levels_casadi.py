"""One control period at the ``ctbr`` and ``ctatt`` command levels (:mod:`sim.levels`), CasADi backend.

Two kinds of model take a command at these levels:

* **nominal** (:func:`level_step_function`): the rigid body of :func:`sim.equations.dynamics_casadi.dynamics_casadi`
  whose body rates answer the command as the closed inner loop is assumed to
  (:meth:`sim.vehicles.onboard.InnerLoopConfig.response`): each rate a first-order lag of time constant ``tau`` to
  its command (``ctbr``); roll and pitch a second-order response of natural frequency ``wn`` and damping ``zeta``
  to theirs, ``p' = wn^2 (phi_cmd - phi) - 2 zeta wn p``, and yaw the rate lag (``ctatt``). The torque is whatever
  gives that angular acceleration; the thrust passes through.
* **exact** (:func:`inner_loop_step_function`): the plant's own inner loop, :class:`sim.plants.inner_loop.InnerLoop`,
  stepped at its own rate inside the period, each of its wrenches realized by the rotors as the plant does
  (:func:`sim.vehicles.rotors.realize`: each rotor's ``n^2`` clipped to ``[0, n_max^2]``) and held over its loop
  period on the rigid body (RK4, 1 ms steps). The loop's memory (the integrals, the last rate error) is carried as
  extra states after the rigid body's: the oracle of a plant flown through its inner loop.
"""

from __future__ import annotations

import casadi as ca

from ..levels import LEVELS, check_level
from ..params import DT, NU, NX, SUBSTEPS, THETA_NAMES, QuadParams
from .dynamics_casadi import _memo, allocate_casadi, dynamics_casadi, rk4_casadi, wrench_from_rotor_sq_casadi


def _values(p: QuadParams, theta=None) -> dict:
    vals = {n: getattr(p, n) for n in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "g", "c_d", "d")}
    if theta is not None:
        vals.update({n: theta[i] for i, n in enumerate(THETA_NAMES)})
    return vals


def torque_for(x, alpha, vals):
    """The body torque (3, 1), N m, that gives the body-rate derivative ``alpha`` (3, 1), rad/s^2, in state ``x``
    (the rigid body's Euler equations solved for the torque)."""
    p, q, r = x[6], x[7], x[8]
    Jxx, Jyy, Jzz = vals["Jxx"], vals["Jyy"], vals["Jzz"]
    return ca.vertcat(Jxx * alpha[0] - (Jyy - Jzz) * q * r,
                      Jyy * alpha[1] - (Jzz - Jxx) * p * r,
                      Jzz * alpha[2] - (Jxx - Jyy) * p * q)


def level_acceleration(x, u, level: str, response):
    """The body-rate derivative (3, 1), rad/s^2, of the nominal response at ``level`` to the command ``u`` (4, 1).

    ``response``: a :class:`sim.vehicles.onboard.LoopResponse` (``rate_tau``, ``att_wn``, ``att_zeta``).
    """
    tau = response.rate_tau
    if level == "ctbr":
        return ca.vertcat(*[(u[1 + i] - x[6 + i]) / tau[i] for i in range(3)])
    wn, z = response.att_wn, response.att_zeta
    return ca.vertcat(wn[0] ** 2 * (u[1] - x[3]) - 2.0 * z[0] * wn[0] * x[6],
                      wn[1] ** 2 * (u[2] - x[4]) - 2.0 * z[1] * wn[1] * x[7],
                      (u[3] - x[8]) / tau[2])


def _check(level: str) -> str:
    check_level(level)
    if level == LEVELS[0]:
        raise ValueError("the wrench level's step is sim.equations.dynamics_casadi.step_function")
    return level


@_memo
def level_step_function(p: QuadParams, level: str, response, *, symbolic_theta: bool = False,
                        dt: float = DT, substeps: int = SUBSTEPS) -> ca.Function:
    """The nominal model of ``level`` for one control period: ``F(x (12), u (4)[, theta (6)]) -> x_next (12)``.

    Parameters
    ----------
    p : QuadParams
        The rigid body's parameters (``m``, ``g``, ``c_d``; the inertia only sets the torque, which cancels).
    level : str
        ``ctbr`` or ``ctatt``.
    response : sim.vehicles.onboard.LoopResponse
        The assumed closed-loop response of the body rates (and of roll and pitch).
    symbolic_theta : bool
        Take ``theta = (m, Jxx, Jyy, Jzz, kt, kq)`` as a third argument.
    """
    _check(level)
    x, u = ca.SX.sym("x", NX), ca.SX.sym("u", NU)
    args, names = [x, u], ["x", "u"]
    theta = None
    if symbolic_theta:
        theta = ca.SX.sym("theta", len(THETA_NAMES))
        args.append(theta)
        names.append("theta")
    vals = _values(p, theta)

    def rates(s):
        w = ca.vertcat(u[0], torque_for(s, level_acceleration(s, u, level, response), vals))
        return dynamics_casadi(s, w, vals)

    x_next = rk4_casadi(rates, x, dt / substeps, substeps)
    return ca.Function(f"step_{level}", args, [x_next], names, ["x_next"])


def _clip(v, lo, hi):
    return ca.fmin(ca.fmax(v, lo), hi)


def realized_wrench_casadi(w, vals, n_max_sq):
    """The wrench (4, 1) the rotors realize for the command ``w`` (4, 1), as :func:`sim.vehicles.rotors.realize`:
    allocated, each ``n^2`` clipped to ``[0, n_max_sq]``, recomputed."""
    return wrench_from_rotor_sq_casadi(_clip(allocate_casadi(w, vals), 0.0, n_max_sq), vals)


def inner_loop_extra_names(config, level: str) -> tuple[str, ...]:
    """The names of the loop's memory that the exact model carries after the rigid body: the rate errors'
    integrals (``i_p, i_q, i_r``, rad) where a rate ``ki`` is not zero, the angle errors' integrals (``i_phi,
    i_theta``, rad s) at ``ctatt`` where an attitude ``ki`` is not zero, the last rate errors (``e_p, e_q, e_r``,
    rad/s) where a ``kd`` is not zero."""
    names = []
    if any(config.rate_ki):
        names += ["i_p", "i_q", "i_r"]
    if level == "ctatt" and any(config.att_ki):
        names += ["i_phi", "i_theta"]
    if any(config.rate_kd):
        names += ["e_p", "e_q", "e_r"]
    return tuple(names)


#: Which of the exact model's extra states integrate (they have no rest value of their own: held where they are).
INTEGRATOR_NAMES = ("i_p", "i_q", "i_r", "i_phi", "i_theta")


def _loop_period(z, u, vals, config, level: str, extra: tuple, n_max_sq: float, h: float):
    """The full state (12 + memory) after one period of the inner loop from ``z`` under the command ``u``."""
    lp = config.period_s
    idx = {n: NX + i for i, n in enumerate(extra)}

    def state(name):
        return z[idx[name]] if name in idx else 0.0

    x = z[:NX]
    i_rate = [state(n) for n in ("i_p", "i_q", "i_r")]
    i_att = [state(n) for n in ("i_phi", "i_theta")]
    e_prev = [state(n) for n in ("e_p", "e_q", "e_r")]
    kp, ki, kd, il = config.rate_kp, config.rate_ki, config.rate_kd, config.rate_i_limit
    if level == "ctbr":
        sp = [u[1], u[2], u[3]]
    else:
        sp = []
        for a in range(2):
            e_a = _clip(u[1 + a], -config.max_tilt, config.max_tilt) - x[3 + a]
            i_att[a] = _clip(i_att[a] + e_a * lp, -config.att_i_limit[a], config.att_i_limit[a])
            sp.append(config.att_kp[a] * e_a + config.att_ki[a] * i_att[a])
        sp.append(u[3])
    sp = [_clip(v, -config.max_rate, config.max_rate) for v in sp]
    err = [sp[a] - x[6 + a] for a in range(3)]
    i_rate = [_clip(i_rate[a] + err[a] * lp, -il[a], il[a]) for a in range(3)]
    alpha = ca.vertcat(*[kp[a] * err[a] + ki[a] * i_rate[a] + kd[a] * (err[a] - e_prev[a]) / lp for a in range(3)])
    J = ca.vertcat(vals["Jxx"], vals["Jyy"], vals["Jzz"])
    w = realized_wrench_casadi(ca.vertcat(u[0], J * alpha), vals, n_max_sq)
    x = rk4_casadi(lambda s: dynamics_casadi(s, w, vals), x, h, config.ticks)
    memory = {"i_p": i_rate[0], "i_q": i_rate[1], "i_r": i_rate[2], "i_phi": i_att[0], "i_theta": i_att[1],
              "e_p": err[0], "e_q": err[1], "e_r": err[2]}
    return ca.vertcat(x, *[memory[n] for n in extra])


@_memo
def inner_loop_step_function(p: QuadParams, level: str, config, *, symbolic_theta: bool = False,
                             dt: float = DT, substeps: int = SUBSTEPS, composed: bool = False) -> ca.Function:
    """The plant with its inner loop for one control period: ``F(z, u[, theta]) -> z_next``.

    ``z`` is the rigid-body state (12) followed by :func:`inner_loop_extra_names` (the loop's memory); ``u`` the
    command at ``level``. Each of the loop's periods (``config.ticks`` of the ``substeps`` RK4 steps; a whole number
    of them in ``dt``) computes the wrench as :meth:`sim.plants.inner_loop.InnerLoop.update` does from the state at
    its start, the rotors realize it, and the rigid body flies it. The first period after the loop starts has no
    last error (its derivative term is zero); this model takes the ``e_*`` it is given.

    ``composed``: the period as calls of one loop-period function (an MX graph) instead of one expanded
    expression: the same arithmetic, whose derivatives compile to a fraction of the C code.
    """
    _check(level)
    n_loop = substeps // config.ticks
    if n_loop * config.ticks != substeps:
        raise ValueError(f"the inner loop's period ({config.ticks} ms) must divide the control period's "
                         f"{substeps} ms")
    extra = inner_loop_extra_names(config, level)
    nz = NX + len(extra)
    h = dt / substeps
    names = ["x", "u", "theta"][:3 if symbolic_theta else 2]
    z, u = ca.SX.sym("z", nz), ca.SX.sym("u", NU)
    theta = ca.SX.sym("theta", len(THETA_NAMES)) if symbolic_theta else None
    vals = _values(p, theta)
    args = [z, u] + ([theta] if symbolic_theta else [])
    if not composed:
        zz = z
        for _ in range(n_loop):
            zz = _loop_period(zz, u, vals, config, level, extra, p.n_max_sq, h)
        return ca.Function(f"step_{level}_inner_loop", args, [zz], names, ["x_next"])
    sub = ca.Function(f"{level}_loop_period", args, [_loop_period(z, u, vals, config, level, extra, p.n_max_sq, h)])
    Z, U = ca.MX.sym("z", nz), ca.MX.sym("u", NU)
    more = [ca.MX.sym("theta", len(THETA_NAMES))] if symbolic_theta else []
    zz = Z
    for _ in range(n_loop):
        zz = sub(zz, U, *more)
    return ca.Function(f"step_{level}_inner_loop", [Z, U, *more], [zz], names, ["x_next"])
