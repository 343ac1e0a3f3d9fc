"""An aerodynamic term library: generic forms, each with physical coefficients to identify, and their selection.

The rigid body explains the thrust and gravity; what it leaves of the translational acceleration, in the body frame
(FRD), is fitted as a sum of terms, each linear in its coefficients. Every term is written once, in
:func:`term_columns`, with array operations that numpy arrays and torch tensors share (``*``, ``abs``, indexing), so
the same source serves a numpy fit and a torch model.

The terms (``v`` the body-frame velocity in m/s, ``S = n1 + n2 + n3 + n4`` the rotor speeds' sum in RU, ``T/m`` the
collective thrust over the mass in m/s^2; each row is the acceleration per unit coefficient):

======================  ==================  ======================================================  ===============
term                    coefficients        acceleration (body frame)                               unit
======================  ==================  ======================================================  ===============
``linear_drag``         k_x, k_y, k_z       ``-k_i v_i`` on axis i                                  1/s
``quadratic_drag``      c_x, c_y, c_z       ``-c_i v_i |v_i|`` on axis i                            1/m
``rotor_drag``          k_r                 ``-k_r S (v_x, v_y, 0)``                                1/(s RU)
``thrust_loss``         k_w, k_h            ``(T/m) (-k_w v_z + k_h (v_x^2 + v_y^2))`` on z          s/m, s^2/m^2
``thrust_bias``         b                   ``b`` on z                                              m/s^2
======================  ==================  ======================================================  ===============

Sources of the forms (none of these projects' code is used):

- linear body drag per axis: the blade-flapping / induced drag that makes a multirotor's drag linear in its
  velocity, the usual first-order model (Mahony, Kumar and Corke, IEEE RAM 2012);
- quadratic body drag: parasitic drag of the frame, ``1/2 rho C_d A v|v|``;
- rotor drag: each rotor's in-plane drag proportional to its speed times the in-plane air velocity (Faessler,
  Franchi and Scaramuzza, RA-L 2018; RotorPy's ``k_d``);
- thrust loss: a rotor's thrust falls with the climb speed (momentum theory's inflow) and changes with the in-plane
  speed (translational lift; RotorPy's ``k_z`` and ``k_h``), here as a fraction of the thrust;
- thrust bias: a constant error of the thrust map away from the ground.

In FRD a climb is ``v_z < 0``: a positive ``k_w`` loses thrust in a climb, and a lost thrust is an acceleration
along +z (down). A positive ``k_h`` loses thrust with in-plane speed; translational lift makes it negative.

:func:`fit_terms` fits a set of terms by least squares on flights' samples, with 95 % intervals from a jackknife
over flights. :func:`select_terms` adds terms one at a time, on the validation flights, and claims a term only when
it lowers the validation error by a stated share, its coefficients have their physical sign, and the slowest and
the fastest third of the training samples give it the same acceleration (a physical coefficient does not change
with the speed; a term that only bends the fit toward a form the library lacks does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import SimInputError
from .jackknife import half_width


@dataclass(frozen=True)
class AeroTerm:
    """One term of the library: its coefficients' names, units and signs (+1: physically non-negative; 0: either)."""

    name: str
    coefficients: tuple[str, ...]
    units: tuple[str, ...]
    signs: tuple[int, ...]
    description: str


#: The library, in the order a selection tries them when their gains tie.
TERMS = {
    "linear_drag": AeroTerm("linear_drag", ("k_x", "k_y", "k_z"), ("1/s",) * 3, (1, 1, 1),
                            "linear body drag per axis"),
    "quadratic_drag": AeroTerm("quadratic_drag", ("c_x", "c_y", "c_z"), ("1/m",) * 3, (1, 1, 1),
                               "quadratic body drag per axis"),
    "rotor_drag": AeroTerm("rotor_drag", ("k_r",), ("1/(s RU)",), (1,),
                           "rotor drag: the rotor speeds' sum times the in-plane body velocity"),
    "thrust_loss": AeroTerm("thrust_loss", ("k_w", "k_h"), ("s/m", "s^2/m^2"), (0, 0),
                            "thrust lost with the climb speed and with the in-plane speed squared"),
    "thrust_bias": AeroTerm("thrust_bias", ("b",), ("m/s^2",), (0,), "a constant thrust error, away from the ground"),
}


def term_columns(name: str, v, rotor_sum, thrust_m) -> list[tuple]:
    """The acceleration per unit coefficient of term ``name``: one ``(a_x, a_y, a_z)`` per coefficient.

    Parameters
    ----------
    name : str
        A key of :data:`TERMS`.
    v : array (N, 3)
        Body-frame velocity, m/s (numpy array or torch tensor).
    rotor_sum : array (N,)
        Sum of the four rotor speeds, RU.
    thrust_m : array (N,)
        Collective thrust over the mass, m/s^2.

    Returns
    -------
    list of tuple
        Per coefficient, the three body-frame components, each an array (N,) of the input's kind.
    """
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    zero = 0.0 * vx
    if name == "linear_drag":
        return [(-vx, zero, zero), (zero, -vy, zero), (zero, zero, -vz)]
    if name == "quadratic_drag":
        return [(-vx * abs(vx), zero, zero), (zero, -vy * abs(vy), zero), (zero, zero, -vz * abs(vz))]
    if name == "rotor_drag":
        return [(-rotor_sum * vx, -rotor_sum * vy, zero)]
    if name == "thrust_loss":
        return [(zero, zero, -thrust_m * vz), (zero, zero, thrust_m * (vx * vx + vy * vy))]
    if name == "thrust_bias":
        return [(zero, zero, zero + 1.0)]
    raise SimInputError(f"aerodynamic term must be one of {', '.join(TERMS)}; found {name!r}")


def term_acceleration(terms: dict, v, rotor_sum, thrust_m) -> tuple:
    """The body-frame acceleration ``(a_x, a_y, a_z)`` of ``terms`` (name -> coefficients, in
    :data:`TERMS` order), each component an array (N,) of the input's kind."""
    total = [0.0 * v[..., 0]] * 3
    for name, coefs in terms.items():
        cols = term_columns(name, v, rotor_sum, thrust_m)
        if len(coefs) != len(cols):
            raise SimInputError(f"term {name!r} has {len(cols)} coefficients; found {len(coefs)}")
        for c, col in zip(coefs, cols):
            total = [t + c * a for t, a in zip(total, col)]
    return tuple(total)


def term_acceleration_tangent(terms: dict, v, rotor_sum, thrust_m, dv, d_sum, d_thrust) -> tuple[tuple, tuple]:
    """:func:`term_acceleration` and its derivative along ``k`` tangent directions (forward mode, written out by
    hand so that a torch model's derivative exports as plain operations; a test holds it to finite differences).

    Parameters
    ----------
    terms, v, rotor_sum, thrust_m
        As in :func:`term_acceleration`: ``v`` (N, 3), ``rotor_sum`` and ``thrust_m`` (N,).
    dv : array (N, 3, k)
        Tangent of the body velocity, m/s per direction.
    d_sum, d_thrust : array (N, k)
        Tangents of the rotor speeds' sum (RU) and of the thrust over the mass (m/s^2).

    Returns
    -------
    a : tuple of 3 arrays (N,)
        The body-frame acceleration, m/s^2.
    da : tuple of 3 arrays (N, k)
        Its derivative along each direction.
    """
    a = term_acceleration(terms, v, rotor_sum, thrust_m)
    vx, vy, vz = v[..., 0:1], v[..., 1:2], v[..., 2:3]            # (N, 1): broadcast against the directions
    s, tm = rotor_sum[..., None], thrust_m[..., None]
    dvx, dvy, dvz = dv[..., 0, :], dv[..., 1, :], dv[..., 2, :]
    zero = 0.0 * dvx
    da = (zero, zero, zero)
    for name, c in terms.items():
        if name == "linear_drag":
            parts = (-c[0] * dvx, -c[1] * dvy, -c[2] * dvz)
        elif name == "quadratic_drag":
            parts = (-2.0 * c[0] * abs(vx) * dvx, -2.0 * c[1] * abs(vy) * dvy, -2.0 * c[2] * abs(vz) * dvz)
        elif name == "rotor_drag":
            parts = (-c[0] * (d_sum * vx + s * dvx), -c[0] * (d_sum * vy + s * dvy), zero)
        elif name == "thrust_loss":
            parts = (zero, zero, d_thrust * (-c[0] * vz + c[1] * (vx * vx + vy * vy))
                     + tm * (-c[0] * dvz + 2.0 * c[1] * (vx * dvx + vy * dvy)))
        elif name == "thrust_bias":
            parts = (zero, zero, zero)
        else:
            raise SimInputError(f"aerodynamic term must be one of {', '.join(TERMS)}; found {name!r}")
        da = tuple(d + q for d, q in zip(da, parts))
    return a, da


@dataclass(frozen=True)
class TermSamples:
    """One flight's samples for the library: what the rigid body leaves of the acceleration, and what the terms read.

    ``v`` (N, 3) body velocity, m/s; ``rotor_sum`` (N,) RU; ``thrust_m`` (N,) m/s^2; ``residual`` (N, 3) the
    body-frame acceleration the rigid body does not explain, m/s^2.
    """

    name: str
    v: np.ndarray
    rotor_sum: np.ndarray
    thrust_m: np.ndarray
    residual: np.ndarray

    def __post_init__(self):
        n = len(self.v)
        shapes = {"v": (np.shape(self.v), (n, 3)), "rotor_sum": (np.shape(self.rotor_sum), (n,)),
                  "thrust_m": (np.shape(self.thrust_m), (n,)), "residual": (np.shape(self.residual), (n, 3))}
        for what, (found, expected) in shapes.items():
            if found != expected:
                raise SimInputError(f"flight {self.name!r}: {what} must have shape {expected}; found {found}")
        for what in shapes:
            bad = int(np.sum(~np.isfinite(np.asarray(getattr(self, what), dtype=float))))
            if bad:
                raise SimInputError(f"flight {self.name!r}: {what} holds {bad} non-finite values (leave those samples "
                                    f"out: flight_samples does)")

    def subset(self, keep) -> "TermSamples":
        """The samples where ``keep`` (N,) is true."""
        keep = np.asarray(keep, dtype=bool)
        return TermSamples(self.name, self.v[keep], self.rotor_sum[keep], self.thrust_m[keep], self.residual[keep])


def speed_bands(flights) -> tuple[list, list]:
    """Every flight's samples in the slowest and in the fastest third of the body speeds of them all:
    ``(slower, faster)``, flight by flight (a flight without samples in a band is left out of it)."""
    speeds = [np.linalg.norm(np.asarray(f.v), axis=1) for f in flights]
    low, high = np.quantile(np.concatenate(speeds), [1 / 3, 2 / 3])
    slow = [f.subset(s <= low) for f, s in zip(flights, speeds)]
    fast = [f.subset(s >= high) for f, s in zip(flights, speeds)]
    return [f for f in slow if len(f.v)], [f for f in fast if len(f.v)]


def _design(flight: TermSamples, names) -> tuple[np.ndarray, np.ndarray]:
    """Stacked rows (3N, p) and targets (3N,) of ``names`` on ``flight`` (axis-major)."""
    cols = [np.concatenate(col) for n in names for col in term_columns(n, flight.v, flight.rotor_sum,
                                                                     flight.thrust_m)]
    A = np.stack(cols, axis=1) if cols else np.zeros((3 * len(flight.v), 0))
    return A, np.concatenate([flight.residual[:, 0], flight.residual[:, 1], flight.residual[:, 2]])


@dataclass(frozen=True)
class TermFit:
    """Least-squares coefficients of a set of terms, with 95 % intervals (a jackknife over flights,
    :mod:`sim.identification.jackknife`; NaN with one flight) and the root-mean-square residual of every axis on the
    fitted flights (m/s^2)."""

    terms: tuple[str, ...]
    values: dict                     # coefficient name -> value
    low: dict
    high: dict
    rmse: float

    def coefficients(self) -> dict:
        """Term name -> tuple of its coefficients, as :func:`term_acceleration` takes them."""
        return {n: tuple(self.values[c] for c in TERMS[n].coefficients) for n in self.terms}


def fit_terms(flights, names) -> TermFit:
    """Fit the terms ``names`` on ``flights`` (:class:`TermSamples`) by least squares."""
    names = tuple(names)
    for n in names:
        if n not in TERMS:
            raise SimInputError(f"aerodynamic term must be one of {', '.join(TERMS)}; found {n!r}")
    if not flights:
        raise SimInputError("fit_terms needs at least one flight")
    per = [_design(f, names) for f in flights]
    A = np.concatenate([a for a, _ in per])
    y = np.concatenate([b for _, b in per])
    coef = np.linalg.lstsq(A, y, rcond=None)[0] if A.shape[1] else np.zeros(0)
    rmse = float(np.sqrt(np.mean((y - A @ coef) ** 2)))
    half = half_width(per)
    names_c = [c for n in names for c in TERMS[n].coefficients]
    return TermFit(terms=names, values=dict(zip(names_c, map(float, coef))),
                   low={c: float(v - h) for c, v, h in zip(names_c, coef, half)},
                   high={c: float(v + h) for c, v, h in zip(names_c, coef, half)}, rmse=rmse)


def residual_rmse(fit: TermFit, flights) -> float:
    """Root-mean-square of what ``fit`` leaves of the residual acceleration on ``flights``, m/s^2."""
    err = []
    for f in flights:
        a = term_acceleration(fit.coefficients(), f.v, f.rotor_sum, f.thrust_m)
        err.append(np.asarray(f.residual) - np.stack(a, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))


#: How a training may use the library (``pinnmpc train --aero``, ``pinnmpc learn --aero``): ``none`` carries no term;
#: ``select`` first selects and identifies terms by least squares on the training flights, judged on the validation
#: flights (:func:`select_terms`), then trains the network on what they leave, with their coefficients learnable
#: beside the physical parameters from the identified values.
AERO_MODES = ("none", "select")

#: A term is claimed when it lowers the validation error by at least this share of it.
MIN_GAIN = 0.02
#: ... and, fitted on the slowest and on the fastest third of the training samples, it gives the same acceleration
#: on every training sample within this share of the larger (root-mean-square over the samples). Judged on the
#: acceleration, not on each coefficient: a coefficient near zero (a drag a plant lacks on one axis) differs by a
#: large share between two fits of noise yet changes nothing. (And not within the intervals: a form the data do not
#: follow widens the jackknife's spread over flights, and would pass.)
AGREE_RTOL = 0.25
#: Forward, candidates are ranked by their validation error times ``1 + COEF_PENALTY k`` (``k`` coefficients): of
#: two terms that explain the same, the one with fewer coefficients goes first (rotor drag before the linear drag
#: per axis at nearly constant rotor speeds). The gain a term must bring is judged on the plain error.
COEF_PENALTY = 0.002


@dataclass(frozen=True)
class SelectionStep:
    """One step of :func:`select_terms`: a candidate tried forward (its validation error, m/s^2, and whether it was
    taken, or why not), or a taken term dropped by the speed check (``validation_rmse`` NaN, ``taken`` False, the
    reason)."""

    term: str
    validation_rmse: float
    taken: bool
    reason: str


@dataclass(frozen=True)
class TermSelection:
    """The terms :func:`select_terms` claimed, their fit on all the training flights, the validation error before
    any term and after the claimed ones, and every step tried."""

    terms: tuple[str, ...]
    fit: TermFit
    validation_rmse_none: float
    validation_rmse: float
    steps: list = field(default_factory=list)


def _stacked(flights) -> TermSamples:
    return TermSamples("all", np.concatenate([f.v for f in flights]), np.concatenate([f.rotor_sum for f in flights]),
                       np.concatenate([f.thrust_m for f in flights]), np.concatenate([f.residual for f in flights]))


def _disagreement(chosen, slow, fast, everything: TermSamples) -> tuple[str, float, str]:
    """The term of ``chosen`` whose acceleration the slow and the fast samples' fits (each of all of ``chosen``)
    disagree on most over ``everything``, beyond :data:`AGREE_RTOL` of the larger: ``(term, relative difference,
    why)``; ``("", 0, "")`` when they agree on all."""
    a, b = fit_terms(slow, chosen), fit_terms(fast, chosen)
    worst = ("", 0.0, "")
    for name in chosen:
        acc = [np.stack(term_acceleration({name: f.coefficients()[name]}, everything.v, everything.rotor_sum,
                                          everything.thrust_m), axis=1) for f in (a, b)]
        scale = max(float(np.sqrt(np.mean(q ** 2))) for q in acc)
        rel = float(np.sqrt(np.mean((acc[0] - acc[1]) ** 2))) / scale if scale > 0 else 0.0
        if rel > AGREE_RTOL and rel > worst[1]:
            coefs = ", ".join(f"{c} {a.values[c]:.4g} against {b.values[c]:.4g}" for c in TERMS[name].coefficients)
            worst = (name, rel, f"its acceleration differs by {100 * rel:.0f} % between the fits on the slowest and "
                                f"on the fastest third of the samples ({coefs}): it changes with the speed")
    return worst


def select_terms(train, val, candidates=tuple(TERMS), min_gain: float = MIN_GAIN) -> TermSelection:
    """Select aerodynamic terms: fitted on ``train``, judged on ``val`` (lists of :class:`TermSamples`).

    First forward: each round fits every candidate not yet taken beside the taken ones and tries them best first
    (lowest validation error, with a small penalty per coefficient: :data:`COEF_PENALTY`); a term is taken when it lowers the validation error by at least ``min_gain`` of it and
    each of its coefficients has its physical sign (:attr:`AeroTerm.signs`). The rounds stop when none is taken.

    Then the speed check, backward: fitted together on the slowest and on the fastest third of the training samples
    (:func:`speed_bands`), the taken terms must give the same acceleration (:data:`AGREE_RTOL`); the term that
    disagrees most is dropped, and the check repeats on the rest. What is left is claimed. (Forward, one term at a
    time, a term the plant has would look speed-dependent while another it has is still missing.)
    """
    for what, flights in (("training", train), ("validation", val)):
        if not sum(len(f.v) for f in flights):
            raise SimInputError(f"select_terms needs {what} samples; the {what} flights have none")
    for n in candidates:
        if n not in TERMS:
            raise SimInputError(f"aerodynamic term must be one of {', '.join(TERMS)}; found {n!r}")
    slow, fast = speed_bands(train)
    everything = _stacked(train)
    chosen: list[str] = []
    current = none = residual_rmse(fit_terms(train, []), val)
    steps = []
    while True:
        tried = sorted(((residual_rmse(fit := fit_terms(train, chosen + [n]), val), n, fit)
                        for n in candidates if n not in chosen),
                       key=lambda t: t[0] * (1.0 + COEF_PENALTY * len(TERMS[t[1]].coefficients)))
        taken = False
        for err, n, fit in tried:
            gain = 1.0 - err / current if current > 0 else 0.0
            wrong = [c for c, s in zip(TERMS[n].coefficients, TERMS[n].signs) if s > 0 and fit.values[c] < 0]
            if gain < min_gain:
                reason = f"lowers the validation error by {100 * gain:.1f} %, under {100 * min_gain:g} %"
            elif wrong:
                reason = f"{', '.join(wrong)} negative, which is not physical"
            else:
                reason = ""
            steps.append(SelectionStep(n, err, not reason, reason))
            if not reason:
                chosen.append(n)
                current = err
                taken = True
                break
        if not taken:
            break
    while chosen:
        name, _, why = _disagreement(chosen, slow, fast, everything)
        if not name:
            break
        chosen.remove(name)
        steps.append(SelectionStep(name, math.nan, False, why))
    fit = fit_terms(train, chosen)
    return TermSelection(terms=tuple(chosen), fit=fit, validation_rmse_none=none,
                         validation_rmse=residual_rmse(fit, val), steps=steps)


def flight_samples(name: str, x, rotor_speed, p, ok=None) -> TermSamples:
    """A flight's :class:`TermSamples` from its states and rotor speeds, the rigid body ``p`` (:class:`sim.QuadParams`)
    explaining the thrust ``kt sum n^2``, gravity and the nominal model's own drag ``-c_d v|v|`` (NED, per axis).

    Parameters
    ----------
    name : str
        The flight's name.
    x : array (N + 1, 12)
        States at the period boundaries (NED, FRD; :mod:`sim` order).
    rotor_speed : array (N, 4)
        Rotor speeds held over each period, RU.
    p : QuadParams
        Mass, ``kt``, gravity and ``c_d``.
    ok : array (N + 1,) of bool, optional
        Which states are measured; a period is used when both its ends are measured and finite and its rotor speeds
        finite (the others are left out).

    The acceleration is the forward difference of the velocity over each period, so the terms read the means of the
    body velocity at its two ends (a bias of second order in the period rather than first).
    """
    from ..equations.dynamics import rotation_matrix
    from ..params import DT

    x = np.asarray(x, dtype=float)
    n = np.asarray(rotor_speed, dtype=float)
    if x.ndim != 2 or x.shape[1] != 12 or n.shape != (len(x) - 1, 4):
        raise SimInputError(f"flight {name!r}: x must be (N + 1, 12) and rotor_speed (N, 4); found {x.shape} and "
                            f"{n.shape}")
    ok = np.ones(len(x), dtype=bool) if ok is None else np.asarray(ok, dtype=bool)
    ok = ok & np.all(np.isfinite(x), axis=1)
    k = np.flatnonzero(ok[:-1] & ok[1:] & np.all(np.isfinite(n), axis=1))
    R0 = rotation_matrix(x[k, 3], x[k, 4], x[k, 5])
    R1 = rotation_matrix(x[k + 1, 3], x[k + 1, 4], x[k + 1, 5])
    v_mid = 0.5 * (x[k, 9:12] + x[k + 1, 9:12])
    acc = (x[k + 1, 9:12] - x[k, 9:12]) / DT - np.array([0.0, 0.0, p.g]) + p.c_d * v_mid * np.abs(v_mid)
    a_b = np.linalg.solve(0.5 * (R0 + R1), acc[:, :, None])[:, :, 0]
    v_b = 0.5 * (np.einsum("nji,nj->ni", R0, x[k, 9:12]) + np.einsum("nji,nj->ni", R1, x[k + 1, 9:12]))
    thrust_m = p.kt * np.sum(n[k] ** 2, axis=1) / p.m
    residual = a_b - np.stack([0.0 * thrust_m, 0.0 * thrust_m, -thrust_m], axis=1)
    return TermSamples(name, v_b, np.sum(n[k], axis=1), thrust_m, residual)
