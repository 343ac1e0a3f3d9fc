"""Excitation data: a stabilizing controller flies seeded random references.

Each trajectory has its own random generator spawned from
the dataset seed, so trajectory ``i`` is the same whatever ``n_traj`` is.
The closed loop runs on the true state; the logged states and rotor speeds
then get measurement noise from an independent stream, so a noise-free
dataset of the same seed holds the true trajectories of a noisy one.

Controller (vectorized over trajectories):

* outer loop: position LQR on each axis (double integrator, gains from
  ``control.dlqr``) giving a desired acceleration, turned into thrust and a
  desired roll and pitch (clipped to the regime's outer limit);
* excitation: smooth random attitude excursions (filtered random steps)
  added to the outer loop's attitude, the sum clipped to the regime's
  command limit; a random smooth yaw reference;
* inner loop: feedback linearization of the Euler-angle dynamics with LQR
  gains (``control.dlqr``) on each angle;
* input dither: white Gaussian noise on thrust and torques.

At the ``ctbr`` level (:mod:`sim.levels`) the same flights are flown through the vehicle's inner loop: the
controller sends collective thrust and body rates (the attitude error through a P gain, :data:`ATTITUDE_RATE_GAIN`,
plus the reference model's rate, turned into body rates), the plant's onboard rate loop makes the torques, and the
dither falls on the rates (the torque dither's change of rate in one period, ``std_tau / J * dt``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import control
import numpy as np
from scipy.linalg import expm

from .._version import __version__
from .._validate import choice, positive_finite, positive_int
from ..errors import DatasetError, SimInputError
from ..levels import DATA_LEVELS, DEFAULT_LEVEL, check_level, rate_dither_std
from ..params import DT, INPUT_LOGS, NOMINAL, Fidelity, NoiseModel, QuadParams
from ..plants.named import PLANTS, known_equations, make_plant
from ..equations.simulator import Simulator
from ..vehicles.vehicle import load_vehicle

FORMAT_VERSION = 1
SPLIT_NAMES = ("train", "val", "test")
SPLIT_FRACTIONS = (0.70, 0.15, 0.15)


@dataclass(frozen=True)
class Regime:
    """Excitation settings of one regime (angles in degrees)."""

    name: str
    envelope_deg: tuple[float, float]  # the max |roll|, |pitch| a dataset must reach: (at least, at most)
    command_limit_deg: float           # clip of the total roll / pitch command
    outer_limit_deg: float             # clip of the position loop's roll / pitch
    excitation_deg: float              # amplitude of the attitude excursions
    position_amplitude_m: float        # horizontal reference amplitude
    altitude_amplitude_m: float        # vertical reference amplitude around 1 m height
    yaw_amplitude_deg: float           # amplitude of the yaw reference steps


REGIMES = {
    "small": Regime("small", (15.0, 20.0), 17.5, 10.0, 17.0, 1.0, 0.3, 60.0),
    "aggressive": Regime("aggressive", (45.0, 60.0), 53.0, 30.0, 52.0, 1.5, 0.3, 60.0),
}

# Input dither standard deviations (white, held over each control period).
DITHER_THRUST_FRAC = 0.03      # fraction of m g
DITHER_TORQUE_XY = 1.0e-4      # N m
DITHER_TORQUE_Z = 1.0e-4       # N m

# Closed-loop design: LQR weights on (error, error rate) per axis, R = 1.
INNER_Q = (2.0e4, 180.0)       # about 12 rad/s, damping 0.9
OUTER_Q = (5.0, 3.0)           # about 1.5 rad/s, damping 0.9
EXCITATION_FILTER_RAD_S = 8.0  # critically damped filter on the attitude steps
YAW_FILTER_RAD_S = 3.0
#: At ``ctbr``: the Euler-angle rate commanded per radian of attitude error, 1/s (the wrench level's inner LQR has a
#: proportional-to-derivative ratio of about 6.6 1/s).
ATTITUDE_RATE_GAIN = 8.0
STEP_HOLD_S = (0.5, 1.5)       # hold time of each random step


def double_integrator_gain(q: tuple[float, float], dt: float = DT) -> np.ndarray:
    """LQR gain (2,) of a zero-order-hold double integrator (python-control ``dlqr``)."""
    A = np.array([[1.0, dt], [0.0, 1.0]])
    B = np.array([[0.5 * dt * dt], [dt]])
    K, _, _ = control.dlqr(A, B, np.diag(q), np.array([[1.0]]))
    return np.asarray(K).reshape(2)


# ---------------------------------------------------------------- references
def _random_steps(rng, n_steps: int, dt: float, amplitude: float, min_frac: float) -> np.ndarray:
    """Piecewise-constant random levels (n_steps,), each held 0.5-1.5 s.

    Level magnitudes lie in ``[min_frac, 1] * amplitude`` with random sign.
    """
    levels = np.empty(n_steps)
    i = 0
    while i < n_steps:
        hold = int(round(rng.uniform(*STEP_HOLD_S) / dt))
        levels[i:i + hold] = amplitude * rng.uniform(min_frac, 1.0) * rng.choice((-1.0, 1.0))
        i += hold
    return levels


def _multisine(rng, t: np.ndarray, amplitude: float, n: int = 3, f_range=(0.05, 0.3)):
    """Sum of ``n`` sines with total amplitude ``amplitude``; position, velocity, acceleration."""
    amps = rng.uniform(0.3, 1.0, n)
    amps *= amplitude / amps.sum()
    w = 2 * np.pi * rng.uniform(*f_range, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    arg = np.outer(t, w) + ph
    return (np.sin(arg) @ amps, np.cos(arg) @ (amps * w), -np.sin(arg) @ (amps * w * w))


@dataclass
class _References:
    pos: np.ndarray       # (B, K, 3) m, NED
    vel: np.ndarray       # (B, K, 3)
    acc: np.ndarray       # (B, K, 3)
    att: np.ndarray       # (B, K, 3) roll / pitch excursion and yaw reference levels, rad
    dither: np.ndarray    # (B, K, 4) N, N m


def _references(rngs, n_steps: int, regime: Regime, p: QuadParams, level: str = DEFAULT_LEVEL) -> _References:
    B = len(rngs)
    t = np.arange(n_steps) * DT
    out = _References(*(np.zeros((B, n_steps, 3)) for _ in range(4)), np.zeros((B, n_steps, 4)))
    exc = math.radians(regime.excitation_deg)
    for i, rng in enumerate(rngs):
        for ax, amp in enumerate((regime.position_amplitude_m, regime.position_amplitude_m,
                                  regime.altitude_amplitude_m)):
            out.pos[i, :, ax], out.vel[i, :, ax], out.acc[i, :, ax] = _multisine(rng, t, amp)
        out.pos[i, :, 2] -= 1.0  # 1 m height, NED
        out.att[i, :, 0] = _random_steps(rng, n_steps, DT, exc, 0.3)
        out.att[i, :, 1] = _random_steps(rng, n_steps, DT, exc, 0.3)
        out.att[i, :, 2] = _random_steps(rng, n_steps, DT, math.radians(regime.yaw_amplitude_deg), 0.0)
        out.dither[i] = rng.standard_normal((n_steps, 4)) * dither_std(p, level)
    return out


def dither_std(p: QuadParams, level: str = DEFAULT_LEVEL) -> np.ndarray:
    """Standard deviations (4,) of the excitation's input dither at ``level``: thrust (N) and torques (N m) at the
    wrench level; at ``ctbr`` thrust and body rates (rad/s), each rate's the change the torque's makes in one period
    on the vehicle's inertia."""
    std = np.array([DITHER_THRUST_FRAC * p.m * p.g, DITHER_TORQUE_XY, DITHER_TORQUE_XY, DITHER_TORQUE_Z])
    return std if level == DEFAULT_LEVEL else np.r_[std[0], rate_dither_std(std[1:], p)]


# ---------------------------------------------------------------- controller
class ExcitationController:
    """Cascaded position / attitude controller used to fly the excitation.

    The attitude command (position loop's roll and pitch plus the random
    excursion, clipped to the regime's limit; the yaw level) passes through
    a critically damped second-order reference model, whose output never
    leaves the range of its input, so the commanded attitude stays inside
    the limit and the inner loop gets smooth rate and acceleration
    feed-forward.

    Parameters
    ----------
    p : QuadParams
        Parameters the controller assumes (the true ones for data).
    regime : Regime
        Attitude limits.
    x0 : numpy.ndarray, shape (B, 12)
        Initial states; the reference model starts at their attitude, at rest.
    level : {"wrench", "ctbr"}
        What it sends: the wrench (N, N m), or collective thrust and body rates (N, rad/s) for an onboard rate loop,
        the rates clipped to ``max_rate``.
    max_rate : float
        At ``ctbr``, the largest body-rate command, rad/s.
    """

    def __init__(self, p: QuadParams, regime: Regime, x0: np.ndarray, level: str = DEFAULT_LEVEL,
                 max_rate: float = math.inf):
        self.p = p
        self.regime = regime
        self.level = level
        self.max_rate = max_rate
        self.k_in = double_integrator_gain(INNER_Q)
        self.k_out = double_integrator_gain(OUTER_Q)
        self.J = np.array([p.Jxx, p.Jyy, p.Jzz])
        self.omega_f = np.array([EXCITATION_FILTER_RAD_S, EXCITATION_FILTER_RAD_S, YAW_FILTER_RAD_S])
        self._Ad, self._Bd = zip(*(_critically_damped(w, DT) for w in self.omega_f))
        # Reference-model state per axis: value (B, 3) and rate (B, 3).
        self.eta_f = np.array(x0[:, 3:6], dtype=float, copy=True)
        self.eta_f_dot = np.zeros_like(self.eta_f)

    def __call__(self, x: np.ndarray, pos_ref, vel_ref, acc_ref, att_level) -> np.ndarray:
        """Command (B, 4) at the controller's level for states ``x`` (B, 12) and the references of one step.

        Advances the reference model by one control period.
        """
        p, reg = self.p, self.regime
        phi, th = x[:, 3], x[:, 4]
        psi = x[:, 5]
        omega = x[:, 6:9]
        v = x[:, 9:12]
        drag = p.c_d * v * np.abs(v)

        # Outer loop: desired acceleration -> thrust direction t = (T/m) b.
        a_d = acc_ref + self.k_out[0] * (pos_ref - x[:, 0:3]) + self.k_out[1] * (vel_ref - v)
        t = -a_d - drag
        t[:, 2] += p.g
        c, s = np.cos(psi), np.sin(psi)
        th_x = c * t[:, 0] + s * t[:, 1]
        th_y = -s * t[:, 0] + c * t[:, 1]
        norm = np.linalg.norm(t, axis=1)
        lim_o = math.radians(reg.outer_limit_deg)
        phi_o = np.clip(np.arcsin(np.clip(-th_y / norm, -1, 1)), -lim_o, lim_o)
        th_o = np.clip(np.arctan2(th_x, t[:, 2]), -lim_o, lim_o)

        lim = math.radians(reg.command_limit_deg)
        target = np.column_stack([np.clip(phi_o + att_level[:, 0], -lim, lim),
                                  np.clip(th_o + att_level[:, 1], -lim, lim), att_level[:, 2]])
        eta_c, eta_c_dot = self.eta_f, self.eta_f_dot
        eta_c_dd = self.omega_f ** 2 * (target - eta_c) - 2.0 * self.omega_f * eta_c_dot
        self._advance(target)

        # Euler rates from body rates.
        sphi, cphi, sth, cth = np.sin(phi), np.cos(phi), np.sin(th), np.cos(th)
        qs_rc = omega[:, 1] * sphi + omega[:, 2] * cphi
        eta_dot = np.stack([omega[:, 0] + qs_rc * sth / cth,
                            omega[:, 1] * cphi - omega[:, 2] * sphi, qs_rc / cth], axis=1)
        eta = x[:, 3:6]
        thrust = p.m * (p.g - a_d[:, 2] - drag[:, 2]) / np.maximum(cphi * cth, 0.3)
        thrust = np.clip(thrust, 0.05 * p.m * p.g, 2.0 * p.m * p.g)
        if self.level == "ctbr":
            # Euler rates that close the attitude error, as body rates: w = W(eta) eta'.
            de = eta_c_dot + ATTITUDE_RATE_GAIN * (eta_c - eta)
            rates = np.stack([de[:, 0] - sth * de[:, 2],
                              cphi * de[:, 1] + sphi * cth * de[:, 2],
                              -sphi * de[:, 1] + cphi * cth * de[:, 2]], axis=1)
            return np.column_stack([thrust, np.clip(rates, -self.max_rate, self.max_rate)])
        eta_dd = eta_c_dd - self.k_in[0] * (eta - eta_c) - self.k_in[1] * (eta_dot - eta_c_dot)

        # Body angular acceleration for that Euler acceleration: w' = W eta'' + W' eta'.
        dphi, dth, dpsi = eta_dot[:, 0], eta_dot[:, 1], eta_dot[:, 2]
        ddphi, ddth, ddpsi = eta_dd[:, 0], eta_dd[:, 1], eta_dd[:, 2]
        wd = np.stack([
            ddphi - sth * ddpsi - cth * dth * dpsi,
            cphi * ddth + sphi * cth * ddpsi - sphi * dphi * dth + cphi * cth * dphi * dpsi
            - sphi * sth * dth * dpsi,
            -sphi * ddth + cphi * cth * ddpsi - cphi * dphi * dth - sphi * cth * dphi * dpsi
            - cphi * sth * dth * dpsi,
        ], axis=1)
        torque = self.J * wd + np.cross(omega, self.J * omega)
        return np.column_stack([thrust, torque])

    def _advance(self, target: np.ndarray) -> None:
        new_val = np.empty_like(self.eta_f)
        new_rate = np.empty_like(self.eta_f)
        for ax in range(3):
            A, B = self._Ad[ax], self._Bd[ax]
            y, yd, r = self.eta_f[:, ax], self.eta_f_dot[:, ax], target[:, ax]
            new_val[:, ax] = A[0, 0] * y + A[0, 1] * yd + B[0] * r
            new_rate[:, ax] = A[1, 0] * y + A[1, 1] * yd + B[1] * r
        self.eta_f, self.eta_f_dot = new_val, new_rate


def _critically_damped(omega: float, dt: float):
    """Exact discretization (A (2, 2), B (2,)) of y'' = w^2 (r - y) - 2 w y', r held over dt."""
    Ac = np.array([[0.0, 1.0], [-omega ** 2, -2.0 * omega]])
    Bc = np.array([[0.0], [omega ** 2]])
    M = expm(np.block([[Ac, Bc], [np.zeros((1, 3))]]) * dt)
    return M[:2, :2], M[:2, 2]


# ------------------------------------------------------------------ dataset
@dataclass(frozen=True)
class Dataset:
    """Excitation dataset; arrays are (n_traj, n_steps, width).

    Sample ``[i, k]`` holds the measured state ``x`` at ``t_k``, the
    command ``u`` applied during ``[t_k, t_k + dt)`` (the wrench, or at the
    dataset's :attr:`level` that level's command), the measured rotor
    speeds during that period and the measured state ``x_next`` at
    ``t_k + dt`` (so ``x_next[i, k] == x[i, k + 1]``).
    """

    x: np.ndarray            # measured state at t_k, (n_traj, n_steps, 12)
    u: np.ndarray            # command at the level: wrench (N, N m) or ctbr (N, rad/s), (n_traj, n_steps, 4)
    rotor_speed: np.ndarray  # measured rotor speeds, RU, (n_traj, n_steps, 4)
    x_next: np.ndarray       # measured state at t_k + dt, (n_traj, n_steps, 12)
    wrench: np.ndarray       # realized wrench (noise-free), (n_traj, n_steps, 4)
    saturated: np.ndarray    # rotor clipped (bool), (n_traj, n_steps, 4)
    split: np.ndarray        # 0 train, 1 validation, 2 test, (n_traj,)
    meta: dict               # regime, seed, noise, fidelity, params, versions
    valid: np.ndarray | None = None   # (n_traj, n_steps, 3) bool: x, rotor speeds, x_next measured; None: all

    ARRAYS = ("x", "u", "rotor_speed", "x_next", "wrench", "saturated", "split")
    #: Arrays a dataset may lack (``valid``: only imported flight logs have samples that were not measured).
    OPTIONAL = ("valid",)

    def __post_init__(self):
        if self.valid is not None:
            v = np.asarray(self.valid)
            if v.dtype != bool or v.shape != (*self.x.shape[:2], 3):
                raise ValueError(f"valid must be a bool array of shape {(*self.x.shape[:2], 3)}; "
                                 f"found {v.dtype} {v.shape}")

    @property
    def usable(self) -> np.ndarray:
        """(n_traj, n_steps) bool: samples whose state, rotor speeds and next state were all measured."""
        if self.valid is None:
            return np.ones(self.x.shape[:2], dtype=bool)
        return np.all(self.valid, axis=-1)

    @property
    def level(self) -> str:
        """The command level of ``u`` (:mod:`sim.levels`): ``meta["level"]``, the wrench where it names none."""
        return self.meta.get("level", DEFAULT_LEVEL)

    @property
    def n_traj(self) -> int:
        """Number of trajectories."""
        return self.x.shape[0]

    def pairs(self, split: str = "train") -> dict[str, np.ndarray]:
        """Flattened samples of one split: ``x, u, rotor_speed, x_next`` as (n, width)."""
        idx = SPLIT_NAMES.index(choice(split, "split", SPLIT_NAMES))
        sel = self.split == idx
        use = self.usable[sel].reshape(-1)
        return {k: getattr(self, k)[sel].reshape(-1, getattr(self, k).shape[-1])[use]
                for k in ("x", "u", "rotor_speed", "x_next")}

    def summary(self) -> dict:
        """Samples, envelope reached and saturation, as plain numbers."""
        ang = np.degrees(np.abs(self.x[..., 3:5]))
        lo, hi = self.meta["envelope_deg"]
        max_roll, max_pitch = float(ang[..., 0].max()), float(ang[..., 1].max())
        psi = np.degrees(self.x[..., 5])
        return {
            "regime": self.meta["regime"],
            "samples": int(self.x.shape[0] * self.x.shape[1]),
            "trajectories": {n: int(np.sum(self.split == i)) for i, n in enumerate(SPLIT_NAMES)},
            "max_abs_roll_deg": max_roll,
            "max_abs_pitch_deg": max_pitch,
            "yaw_range_deg": [float(psi.min()), float(psi.max())],
            "max_abs_body_rate_rad_s": float(np.abs(self.x[..., 6:9]).max()),
            "max_speed_m_s": float(np.linalg.norm(self.x[..., 9:12], axis=-1).max()),
            "saturation_fraction": float(np.mean(np.any(self.saturated, axis=-1))),
            "envelope_deg": [lo, hi],
            "envelope_reached": bool(min(max_roll, max_pitch) >= lo and max(max_roll, max_pitch) <= hi),
        }

    def subset(self, traj) -> "Dataset":
        """Dataset of the trajectories selected by ``traj`` (boolean mask or indices over n_traj)."""
        idx = np.arange(self.n_traj)[traj]
        return dataclasses.replace(self, **{k: getattr(self, k)[idx] for k in self.ARRAYS},
                                   valid=None if self.valid is None else self.valid[idx],
                                   meta={**self.meta, "subset_of_n_traj": self.n_traj})

    def fingerprint(self) -> str:
        """sha256 of the data arrays (not of the file), so a regenerated dataset has the same value."""
        h = hashlib.sha256()
        for k in self.ARRAYS + (("valid",) if self.valid is not None else ()):
            a = np.ascontiguousarray(getattr(self, k))
            h.update(f"{k}:{a.dtype.str}:{a.shape}".encode())
            h.update(a.tobytes())
        return h.hexdigest()

    def save(self, path) -> Path:
        """Write a ``.npz`` file, whole or not at all; the same dataset always gives the same bytes."""
        from ..files import _replace_from_temp

        path = Path(path)
        if path.suffix != ".npz":
            raise SimInputError(f"out must end in .npz; found {str(path)!r}")
        items = {k: getattr(self, k) for k in self.ARRAYS}
        if self.valid is not None:
            items["valid"] = self.valid
        items["meta"] = np.array(json.dumps(self.meta, sort_keys=True))

        def write(f):
            with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED) as zf:
                for name, arr in items.items():
                    info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                    with zf.open(info, "w", force_zip64=True) as fh:
                        np.lib.format.write_array(fh, np.asarray(arr), allow_pickle=False)

        return _replace_from_temp(path, write)


def load_dataset(path) -> Dataset:
    """Read a dataset written by :meth:`Dataset.save`.

    Raises
    ------
    DatasetError
        If the file is missing, not an ``.npz`` archive, truncated or otherwise unreadable, lacks a field, has an
        unknown format version, or holds a non-finite value in its state, input or rotor-speed arrays (the message
        names the file, the array and where the first such value sits).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"dataset file {str(path)!r} does not exist")
    if path.suffix != ".npz":
        raise DatasetError(f"dataset file {str(path)!r} is not an .npz file (pinnmpc data writes one)")
    if not zipfile.is_zipfile(path):
        raise DatasetError(f"dataset file {str(path)!r} is not an .npz archive (truncated, or not written by "
                           f"pinnmpc data)")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in (*Dataset.ARRAYS, "meta") if k not in z.files]
            if missing:
                raise DatasetError(f"dataset file {str(path)!r} is not a pinn-mpc dataset: missing "
                                   f"{', '.join(missing)}")
            meta = json.loads(str(z["meta"][()]))
            if not isinstance(meta, dict) or meta.get("format_version") != FORMAT_VERSION:
                found = meta.get("format_version") if isinstance(meta, dict) else None
                raise DatasetError(f"dataset file {str(path)!r} has format_version {found}, "
                                   f"this code reads {FORMAT_VERSION}")
            arrays = {k: z[k] for k in Dataset.ARRAYS}
            arrays.update({k: z[k] for k in Dataset.OPTIONAL if k in z.files})
    except DatasetError:
        raise
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zipfile.LargeZipFile) as e:
        # np.load's errors on a damaged archive: BadZipFile, EOFError or ValueError on a truncated member, ...
        reason = " ".join(str(e).split()) or type(e).__name__
        raise DatasetError(f"dataset file {str(path)!r} cannot be read (truncated or not a pinn-mpc dataset): "
                           f"{reason}") from None
    for k in ("x", "u", "rotor_speed", "x_next"):
        a = arrays[k]
        if not np.issubdtype(a.dtype, np.number):
            raise DatasetError(f"dataset file {str(path)!r}: array {k} holds {a.dtype}, not numbers")
        bad = ~np.isfinite(a)
        if np.any(bad):
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            raise DatasetError(f"dataset file {str(path)!r}: array {k} holds {int(bad.sum())} non-finite "
                               f"value(s), the first at index {first}; a model cannot be trained on them")
    try:
        return Dataset(**arrays, meta=meta)
    except (TypeError, ValueError) as e:
        raise DatasetError(f"dataset file {str(path)!r} is not a consistent pinn-mpc dataset: "
                           f"{' '.join(str(e).split())}") from None


def _split(n: int, rng: np.random.Generator) -> np.ndarray:
    """Trajectory split 70/15/15 (at least one val and test trajectory when n >= 3)."""
    n_val = n_test = max(1, round(SPLIT_FRACTIONS[1] * n)) if n >= 3 else 0
    labels = np.zeros(n, dtype=np.int8)
    perm = rng.permutation(n)
    labels[perm[:n_val]] = 1
    labels[perm[n_val:n_val + n_test]] = 2
    return labels


def _step_plants(plants, u):
    """One period of one plant per trajectory (plants that are not batched): a StepResult of the stacked outputs."""
    from ..equations.simulator import StepResult

    outs = [pl.step(ui) for pl, ui in zip(plants, u)]
    return StepResult(*(np.stack([getattr(o, f) for o in outs]) for f in ("x", "rotor_speed", "wrench", "saturated")))


def _fly_slice(item):
    """:func:`_fly_rows` of a worker process: ``(job, lo, hi)``."""
    job, lo, hi = item
    return _fly_rows(job, lo, hi, False)


def _trajectory_plants(plant: str, veh, p: QuadParams, fidelity: Fidelity, level: str, x0: np.ndarray):
    """One plant per trajectory, each reset to its row of ``x0``: ``plant`` flying ``veh`` with the parameters ``p``
    at ``level`` (at ``ctbr`` on our simulator: the simulator of ``fidelity`` behind the vehicle's inner loop)."""
    veh = veh.replace(**{k: getattr(p, k) for k in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "d", "c_d", "n_max")})
    if plant == "sim":
        from ..plants.inner_loop import InnerLoopPlant
        from ..plants.plant import SimPlant

        plants = [InnerLoopPlant(SimPlant(veh, fidelity), veh.inner_loop_at(level), level) for _ in x0]
    else:
        plants = [make_plant(plant, veh, level=level) for _ in x0]
    for pl, xi in zip(plants, x0):
        pl.reset(xi)
    return plants


def _fly_rows(job: tuple, lo: int, hi: int, progress: bool):
    """Fly trajectories ``lo .. hi - 1`` of :func:`make_dataset`'s ``job`` = ``(regime, seed, n_traj, n_steps, params,
    fidelity, plant, vehicle, level)``; each trajectory is the same whichever slice flies it (its own random stream).

    Returns ``(x_true (n, n_steps + 1, 12), u, rotor_speed, wrench, saturated (n, n_steps, 4))`` for ``n = hi - lo``.
    """
    regime, seed, n_traj, n_steps, p, fidelity, plant, veh, level = job
    reg = REGIMES[regime]
    flight_root = np.random.SeedSequence(seed).spawn(3)[0]
    rngs = [np.random.default_rng(s) for s in flight_root.spawn(n_traj)[lo:hi]]
    n = hi - lo
    refs = _references(rngs, n_steps, reg, p, level)
    sim = Simulator(p, fidelity)
    x_true = np.zeros((n, n_steps + 1, 12))
    x0 = np.zeros((n, 12))
    x0[:, 0:3] = refs.pos[:, 0]
    plants = None
    if plant != "sim" or level != DEFAULT_LEVEL:
        # one plant per trajectory (RotorPy flies one vehicle; an inner loop keeps its own state), each at its x0
        plants = _trajectory_plants(plant, veh, p, fidelity, level, x0)
    x_true[:, 0] = x0
    max_rate = veh.inner_loop_at(level).max_rate if level != DEFAULT_LEVEL else math.inf
    ctrl = ExcitationController(p, reg, x0, level, max_rate)
    u = np.zeros((n, n_steps, 4))
    n_log = np.zeros((n, n_steps, 4))
    wrench = np.zeros((n, n_steps, 4))
    sat = np.zeros((n, n_steps, 4), dtype=bool)
    rotor = None
    steps = range(n_steps)
    if progress:
        from tqdm import tqdm
        steps = tqdm(steps, desc=f"data {reg.name}", unit="step", leave=False)
    x = x0
    for k in steps:
        uk = ctrl(x, refs.pos[:, k], refs.vel[:, k], refs.acc[:, k], refs.att[:, k])
        uk = uk + refs.dither[:, k]
        if plants is None:
            res = sim._step(x, uk, rotor, k * DT)
        else:
            res = _step_plants(plants, uk)
        rotor = res.rotor_speed
        u[:, k], n_log[:, k], wrench[:, k], sat[:, k] = uk, res.rotor_speed, res.wrench, res.saturated
        x = res.x
        x_true[:, k + 1] = x
    return x_true, u, n_log, wrench, sat


def make_dataset(regime: str = "small", n_traj: int = 100, duration: float = 10.0, seed: int = 0, *,
                 noise: NoiseModel | None = None, fidelity: Fidelity = NOMINAL,
                 params: QuadParams | None = None, inputs: str = "commanded", progress: bool = False,
                 with_clean: bool = False, plant: str = "sim", vehicle=None, workers: int = 1,
                 level: str = DEFAULT_LEVEL):
    """Fly seeded excitation trajectories and log them.

    Parameters
    ----------
    regime : {"small", "aggressive"}
        Attitude envelope: |roll|, |pitch| up to 20 deg, or 45-60 deg.
    n_traj : int
        Number of trajectories (>= 1).
    duration : float
        Length of each trajectory, s (> 0); rounded to whole 10 ms steps.
    seed : int
        Seed (>= 0). The same arguments always give the same dataset.
    noise : NoiseModel, optional
        Measurement noise on logged states and rotor speeds; ``NoiseModel()``
        (the stated default) when omitted, ``NoiseModel.none()`` for none.
    fidelity : Fidelity
        Simulator fidelity (nominal by default).
    params : QuadParams, optional
        True parameters; the vehicle's (reference values) when omitted.
    plant : str
        What flies the excitation: ``"sim"`` (this package's simulator, batched over the trajectories; default),
        ``"rotorpy"`` or ``"rotorpy-ideal"`` (RotorPy, one vehicle at a time: about ten times slower; see
        :mod:`sim.plants.plant`). RotorPy's set-ups are their own, so ``fidelity`` must then be nominal.
    vehicle : Vehicle, name or file, optional
        The vehicle flown (:mod:`sim.vehicles.vehicle`); its parameters are the true ones and its limits the excitation
        controller's. The default vehicle (the Rolling Spider) when omitted.
    inputs : {"commanded", "realized"}
        What ``u`` logs: the controller's wrench command (default; where a
        rotor saturates it is not the wrench applied), or the wrench the
        rotors realized, i.e. a command kept inside the rotor limits. The
        flights are the same either way; only the logged input differs.
        ``"realized"`` needs a simulator without motor lag (with lag the
        wrench changes within a period).
    progress : bool
        Show a progress bar on stderr (with one process).
    workers : int
        Processes flying at once where the plant flies one vehicle at a time (RotorPy, or any plant at ``ctbr``);
        the dataset is the same for any number. Our simulator flies the wrench level's trajectories in one batch and
        ignores it.
    with_clean : bool
        Also return the same flights without measurement noise (what the Fisher information is evaluated on),
        without flying them again.
    level : {"wrench", "ctbr"}
        What the excitation commands and ``u`` logs: the wrench (default), or collective thrust and body rates
        flown through the vehicle's inner loop (the vehicle file's ``[inner_loop]``; one plant per trajectory, about
        five times slower on our simulator). The dataset's ``meta["level"]`` names a level other than the wrench.

    Returns
    -------
    Dataset, or (Dataset, Dataset) with ``with_clean``: the measured one and its noise-free twin.
    """
    reg = REGIMES[choice(regime, "regime", REGIMES)]
    n_traj = positive_int(n_traj, "n_traj")
    duration = positive_finite(duration, "duration")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SimInputError(f"seed must be an integer >= 0; found {seed!r}")
    noise = NoiseModel() if noise is None else noise
    if not isinstance(noise, NoiseModel):
        raise SimInputError(f"noise must be a NoiseModel; found {type(noise).__name__}")
    inputs = choice(inputs, "inputs", INPUT_LOGS)
    level = check_level(level)
    if level not in DATA_LEVELS:
        raise SimInputError(f"level must be one of {', '.join(DATA_LEVELS)} for an excitation (none is written for "
                            f"the others); found {level!r}")
    if level != DEFAULT_LEVEL and inputs == "realized":
        raise SimInputError(f"inputs='realized' logs a realized wrench, which is not a {level} command; log the "
                            f"commands (inputs='commanded') at level {level!r}")
    if not isinstance(fidelity, Fidelity):
        raise SimInputError(f"fidelity must be a Fidelity; found {type(fidelity).__name__}")
    if inputs == "realized" and fidelity.motor_tau > 0:
        raise SimInputError("inputs='realized' needs a simulator without motor lag (fidelity.motor_tau = 0); "
                            f"found motor_tau {fidelity.motor_tau} s")
    veh = load_vehicle(vehicle)
    if params is not None and vehicle is not None and params != veh.params:
        raise SimInputError("give params or vehicle, not both (a vehicle carries its parameters)")
    if level != DEFAULT_LEVEL:
        veh.inner_loop_at(level)     # a vehicle without an inner loop is refused before anything flies
    p = veh.params if params is None else params
    if plant not in PLANTS:
        raise SimInputError(f"plant must be one of {', '.join(PLANTS)}; found {plant!r}")
    if plant != "sim" and not fidelity.is_nominal:
        raise SimInputError(f"fidelity is a set-up of the reference simulator (plant 'sim'); plant {plant!r} has its "
                            f"own: give a nominal fidelity")
    p = known_equations(plant, p) or p      # the truth is the plant's own equations where they are known
    if inputs == "realized" and plant == "rotorpy":
        raise SimInputError("inputs='realized' needs a plant without motor lag; plant 'rotorpy' has the vehicle's")
    n_steps = int(round(duration / DT))
    if n_steps < 1:
        raise SimInputError(f"duration must be at least one control period ({DT} s); found {duration}")

    # Independent streams per trajectory (flight and noise), so trajectory i
    # is the same whatever n_traj is.
    _, noise_root, split_root = np.random.SeedSequence(int(seed)).spawn(3)
    noise_rngs = [np.random.default_rng(s) for s in noise_root.spawn(n_traj)]
    split_rng = np.random.default_rng(split_root)
    workers = positive_int(workers, "workers")
    job = (reg.name, int(seed), n_traj, n_steps, p, fidelity, plant, veh, level)
    if (plant == "sim" and level == DEFAULT_LEVEL) or workers == 1 or n_traj == 1:
        x_true, u, n_log, wrench, sat = _fly_rows(job, 0, n_traj, progress)
    else:      # plants flown one vehicle at a time: slices of the trajectories in worker processes
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import get_context

        cuts = np.linspace(0, n_traj, min(workers, n_traj) + 1).round().astype(int)
        with ProcessPoolExecutor(len(cuts) - 1, mp_context=get_context("spawn")) as ex:
            parts = list(ex.map(_fly_slice, [(job, int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:])]))
        x_true, u, n_log, wrench, sat = (np.concatenate(a) for a in zip(*parts))
    if not np.all(np.isfinite(x_true)):
        raise RuntimeError("excitation flight diverged (non-finite state); "
                           "this is a bug in sim.identification.excitation")

    if noise.is_zero:
        meas, n_meas = x_true, n_log
    else:
        meas = np.empty_like(x_true)
        n_meas = np.empty_like(n_log)
        for i, rng in enumerate(noise_rngs):
            meas[i] = x_true[i] + noise.state_std * rng.standard_normal(x_true.shape[1:])
            n_meas[i] = n_log[i] + noise.rotor_speed * rng.standard_normal(n_log.shape[1:])

    meta = {
        "format_version": FORMAT_VERSION,
        "code_version": __version__,
        "regime": reg.name,
        "envelope_deg": list(reg.envelope_deg),
        "n_traj": n_traj,
        "duration_s": n_steps * DT,
        "dt_s": DT,
        "seed": int(seed),
        "noise": dataclasses.asdict(noise),
        "fidelity": dataclasses.asdict(fidelity),
        "inputs": inputs,
        "params": dataclasses.asdict(p),
        "plant": plant,
        "vehicle": veh.name,
        "split_fractions": list(SPLIT_FRACTIONS),
    }
    if level != DEFAULT_LEVEL:        # named only off the wrench, so that a wrench dataset's meta is as it was
        meta["level"] = level
    if inputs == "realized":
        u = wrench.copy()
    split = _split(n_traj, split_rng)
    ds = Dataset(x=meas[:, :-1].copy(), u=u, rotor_speed=n_meas, x_next=meas[:, 1:].copy(),
                 wrench=wrench, saturated=sat, split=split, meta=meta)
    if not with_clean:
        return ds
    clean = Dataset(x=x_true[:, :-1].copy(), u=u, rotor_speed=n_log, x_next=x_true[:, 1:].copy(), wrench=wrench,
                    saturated=sat, split=split.copy(),
                    meta={**meta, "noise": dataclasses.asdict(NoiseModel.none())})
    return ds, clean
