"""Physics-informed training with parameter identification.

Loss per optimizer step::

    L = L_data + lambda_p (L_phys,data + L_phys,colloc) + lambda_r L_rotor
        + lambda_E L_energy + lambda_S L_smooth

* ``L_data``: squared error of the predicted next state, per state divided
  by the residual scale ``s``, over a training rollout of ``K`` steps
  (``K = 1`` without curriculum).
* ``L_phys``: the network's increment against an RK4 step (10 x 1 ms) of
  the nominal equations under theta-hat, on the rollout's inputs and on
  unlabeled collocation points drawn uniformly from the training envelope.
* ``L_rotor``: the rotor-speed residual. The commanded wrench is exact and
  the logged rotor speeds are noisy, so the comparison is made on the
  rotors' side: ``n^2`` that kt-hat, kq-hat allocate for the command
  against the logged ``n^2``, over its spread. (Comparing on the wrench
  side, ``M(kt-hat, kq-hat) n_log^2`` against the command, puts the noise
  in the regressor and biases kq-hat low: errors in variables.)
* ``L_energy`` (paper Eq. 12): the predicted change of mechanical energy
  over one step against the trapezoidal integral of thrust, torque and
  drag power, over ``m g`` times 1 m/s (theta-hat held fixed: it regularizes
  the network, it does not identify).
* ``L_smooth`` (paper Eq. 13): ``ReLU(|dx/dt| - v_max)^2`` of predicted
  steps, ``v_max`` 1.2 times the largest rate seen in the training data.

Curriculum (paper Eq. 11, scaled to the epoch budget): the rollout horizon
is 5, 10, 25, 50 in four equal quarters of the epochs. Scheduled sampling:
inside the rollout each sample's next input is its own prediction with
probability ``p(e)``, rising linearly from 0 (first epoch) to 0.3 (last),
else the measured state.

Every configuration processes the same number of transitions per optimizer
step (``batch``; a rollout of ``K`` steps uses ``batch // K`` windows) and
the same number of steps, so the budgets are equal.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from sim.identification.aero import AERO_MODES
from sim.params import DT, THETA_NAMES, QuadParams

from .models import ALL_ARCHITECTURES, PHYSICAL, VARIANT_DEFAULTS, build_model
from .physics import mechanical_energy, power_balance, rk4_increment, rotor_sq_from_wrench

CURRICULUM_HORIZONS = (5, 10, 25, 50)
#: Motor-lag models: periods at the start of each flight no training window starts in (the rotors' model starts
#: at the first command's speed; as the lag-aware classical estimator), and the number of past commands from which
#: a window's starting rotor speeds are computed (exp(-60 dt / tau) < 1e-6 for tau up to 70 ms).
SETTLE_PERIODS = 20
ROTOR_HISTORY = 60
SS_MAX = 0.3
THETA_BIAS = 0.30  # initial guess: every parameter 30 % above the reference value


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run (hashed into the model's metadata)."""

    arch: str = "baseline"
    profile: str = "quick"
    seed: int = 0
    epochs: int = 10
    steps_per_epoch: int = 60
    batch: int = 1024            # transitions per optimizer step
    n_colloc: int = 512          # collocation points per step
    lr: float = 2e-3             # network learning rate (cosine decay to lr / 20)
    lr_theta: float = 2e-2       # learning rate of log(theta)
    lambda_p: float = 1.0        # physics residual weight
    lambda_rotor: float = 1.0    # rotor residual weight
    hidden: int = 128
    layers: int = 5
    dropout: float = 0.0
    dropout_until: float = 1.0   # fraction of the epochs with dropout on (1 = throughout), then off
    curriculum: bool = False
    scheduled_sampling: bool = False
    energy: float = 0.0          # weight of the energy-conservation loss (0 = off)
    smooth: float = 0.0          # weight of the smoothness loss (0 = off)
    theta_bias: float = THETA_BIAS
    theta_warmup: float = 0.2    # fraction of the steps before theta-hat starts to move
    threads: int = 1
    # Zoo variants (pinn.models.VARIANT_DEFAULTS): left out of to_dict() at their defaults, so the
    # shipped models' recorded configurations and hashes are unchanged.
    activation: str = "tanh"     # hidden-layer activation: tanh or softplus
    gain: float = 1.0            # multiplies the residual scale s
    fourier_max: int = 8         # Fourier: highest frequency 2**fourier_max rad^-1
    coupled: bool = True         # Modular: False hides the rotational states from the translation module
    # Aerodynamic terms in the physics (motor-lag model only): "none", or "select" (the library's selection on the
    # training and validation flights, then trained jointly from the identified coefficients; see AERO_MODES).
    aero: str = "none"

    def variant(self) -> dict:
        """The zoo variant settings that depart from the shipped design."""
        return {k: getattr(self, k) for k, v in VARIANT_DEFAULTS.items() if getattr(self, k) != v}

    def to_dict(self) -> dict:
        """Plain dict (for JSON and hashing); variant settings only where they depart from the default."""
        d = dataclasses.asdict(self)
        for k, v in {**VARIANT_DEFAULTS, **OMITTED_AT_DEFAULT}.items():
            if d[k] == v:
                del d[k]
        return d


#: Training settings added after the shipped models were trained: left out of to_dict() at these defaults, so
#: the recorded configurations and hashes of those models stay as they were.
OMITTED_AT_DEFAULT = {"dropout_until": 1.0, "aero": "none"}


#: Budget per profile: quick is for CI (< 60 s on 2 cores), full for the shipped models.
PROFILES = {
    "quick": {"epochs": 8, "steps_per_epoch": 40, "batch": 512, "n_colloc": 256, "lr": 3e-3, "lr_theta": 5e-3},
    "full": {"epochs": 40, "steps_per_epoch": 150, "batch": 1024, "n_colloc": 512, "lr": 2e-3, "lr_theta": 2e-3},
}

#: What each architecture / ablation row switches on (Table III adds them one at a time).
RECIPES = {
    "baseline": {},
    "modular": {},
    "fourier": {},
    "baseline+curriculum": {"curriculum": True},
    "baseline+curriculum+ss": {"curriculum": True, "scheduled_sampling": True},
    "baseline+curriculum+ss+dropout": {"curriculum": True, "scheduled_sampling": True, "dropout": 0.02},
    "proposed": {"curriculum": True, "scheduled_sampling": True, "dropout": 0.02, "energy": 0.1, "smooth": 0.1},
}
ABLATION = ("baseline", "baseline+curriculum", "baseline+curriculum+ss", "baseline+curriculum+ss+dropout", "proposed")


def make_config(arch: str, profile: str = "quick", seed: int = 0, recipe: str | None = None, **overrides) -> TrainConfig:
    """Config for an architecture (and optionally an ablation recipe) under a budget profile."""
    if arch not in ALL_ARCHITECTURES:
        raise ValueError(f"arch must be one of {', '.join(ALL_ARCHITECTURES)}; found {arch!r}")
    if profile not in PROFILES:
        raise ValueError(f"profile must be one of {', '.join(PROFILES)}; found {profile!r}")
    recipe = (arch if arch in RECIPES else "baseline") if recipe is None else recipe
    if recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {', '.join(RECIPES)}; found {recipe!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0; found {seed!r}")
    aero = overrides.get("aero", "none")
    if aero not in AERO_MODES:
        raise ValueError(f"aero must be one of {', '.join(AERO_MODES)}; found {aero!r}")
    if aero != "none" and arch != "hybrid_lag":
        raise ValueError(f"aero={aero!r} needs the motor-lag model (hybrid_lag); found arch {arch!r}")
    return TrainConfig(arch=arch, profile=profile, seed=seed, **{**PROFILES[profile], **RECIPES[recipe], **overrides})


def set_dropout(model: torch.nn.Module, p: float) -> None:
    """Set the drop probability of every dropout layer of ``model`` (0 switches dropout off)."""
    for mod in model.modules():
        if isinstance(mod, torch.nn.Dropout):
            mod.p = p


def curriculum_horizon(epoch: int, epochs: int) -> int:
    """Rollout horizon K(e): 5, 10, 25, 50 over four equal quarters of the epochs (paper Eq. 11)."""
    quarter = min(len(CURRICULUM_HORIZONS) - 1, (4 * epoch) // max(1, epochs))
    return CURRICULUM_HORIZONS[quarter]


def sampling_probability(epoch: int, epochs: int) -> float:
    """Scheduled-sampling probability p(e), linear from 0 at the first epoch to 0.3 at the last."""
    return SS_MAX * epoch / max(1, epochs - 1)


# --------------------------------------------------------------------- data
def dataset_params(ds) -> QuadParams:
    """The parameters a dataset was made with: the simulator's (``meta["params"]``), or for imported flight logs
    the vehicle file's stated values (``meta["vehicle"]``). Training takes only g, c_d, d and n_max from them, and
    the stated values as the prior of theta-hat."""
    if "params" in ds.meta:
        return QuadParams(**ds.meta["params"])
    from sim.vehicles.vehicle import vehicle_from_dict

    return vehicle_from_dict(ds.meta["vehicle"], "dataset metadata 'vehicle'").params


def training_stats(ds) -> dict:
    """Normalization and scales from the training split (numpy float64 arrays); only measured samples count."""
    tr = ds.split == 0
    x, u, xn = ds.x[tr], ds.u[tr], ds.x_next[tr]
    n_all = ds.rotor_speed[tr]
    if ds.valid is None:
        n_inc = np.diff(n_all, axis=1).reshape(-1, 4)
    else:     # imported flight logs: the usable samples only (state, rotors and next state measured)
        use = ds.usable[tr]
        n_inc = np.diff(n_all, axis=1)[use[:, 1:] & use[:, :-1]]
        x, u, xn, n_all = x[use], u[use], xn[use], n_all[use]
    feats = np.concatenate([x[..., 3:12], u], axis=-1).reshape(-1, 13)
    dx = (xn - x).reshape(-1, 12)
    xu = np.concatenate([x, u], axis=-1).reshape(-1, 16)
    y = xn.reshape(-1, 12)
    n_log = n_all.reshape(-1, 4)
    p = dataset_params(ds)
    return {
        "in_mean": feats.mean(0), "in_std": feats.std(0) + 1e-8,
        # for the zoo's absolute-state variant: every state and input, and the next state itself
        "abs_in_mean": xu.mean(0), "abs_in_std": xu.std(0) + 1e-8,
        "abs_out_mean": y.mean(0), "abs_out_std": y.std(0) + 1e-8,
        "out_scale": dx.std(0) + 1e-8,
        "feat_min": feats.min(0), "feat_max": feats.max(0),
        "n_sq_scale": (n_log ** 2).std(0) + 1e-12,
        "rate_max": 1.2 * np.abs(dx).max(0) / DT,
        # known constants of the physics-plus-network model: gravity (m/s^2) and the drag coefficient (1/m)
        "physics": np.array([p.g, p.c_d], dtype=float),
        # ... with the motor lag: the rotor telemetry's spread and increments (RU), the rotor limit and lever arm
        "n_mean": n_log.mean(0), "n_std": n_log.std(0) + 1e-8,
        "n_inc_scale": n_inc.std(0) + 1e-8,
        "rotor": np.array([p.n_max_sq, p.lever]),
    }


class _TrainData:
    """Training trajectories as float32 tensors and window sampling.

    Imported flight logs (a dataset with ``valid``) carry which states were measured: a window then starts only
    at a sample whose state and rotor speeds were measured, and :meth:`windows` returns the mask of its measured
    states, which the rollout and the data loss use (an unmeasured state is neither an input nor a target).
    """

    def __init__(self, ds, gen: torch.Generator):
        tr = ds.split == 0
        if not tr.any():
            raise ValueError("dataset has no training trajectories (need n_traj >= 1 with a train split)")
        # Trajectory states x_0 .. x_T: x plus the last x_next.
        states = np.concatenate([ds.x[tr], ds.x_next[tr][:, -1:]], axis=1)
        self.states = torch.as_tensor(states, dtype=torch.float32)
        self.u = torch.as_tensor(ds.u[tr], dtype=torch.float32)
        self.n = torch.as_tensor(ds.rotor_speed[tr], dtype=torch.float32)
        self.n_traj, self.n_steps = self.u.shape[:2]
        self.gen = gen
        self.ok = self.starts_ok = None
        if ds.valid is not None:
            v = ds.valid[tr]
            ok = np.concatenate([v[:, :, 0], v[:, -1:, 2]], axis=1)      # state k measured, k = 0 .. T
            self.ok = torch.as_tensor(ok)
            self.starts_ok = v[:, :, 0] & v[:, :, 1]                      # a window may start here
            self._starts = {}

    def _start_table(self, lo: int, horizon: int):
        key = (lo, horizon)
        if key not in self._starts:
            allowed = self.starts_ok.copy()
            allowed[:, :lo] = False
            allowed[:, self.n_steps - horizon + 1:] = False
            t, s = np.nonzero(allowed)
            if not len(t):
                raise ValueError(f"no training window of {horizon} steps starts at a measured sample")
            self._starts[key] = (torch.as_tensor(t), torch.as_tensor(s))
        return self._starts[key]

    def windows(self, count: int, horizon: int, history: int = 0):
        """``count`` random windows: states (count, K+1, 12), inputs and rotor speeds (count, K, 4), the
        ``history`` commands before each window (count, history, 4) or None, and which states were measured
        (count, K+1) bool or None (a simulated dataset: all).

        With ``history`` > 0 the windows start after :data:`SETTLE_PERIODS`, the first command repeated before a
        flight's start (the rotors start at its speed).
        """
        lo = SETTLE_PERIODS if history else 0
        if self.ok is None:
            ti = torch.randint(0, self.n_traj, (count,), generator=self.gen)
            si = torch.randint(lo, self.n_steps - horizon + 1, (count,), generator=self.gen)
        else:
            t, s = self._start_table(lo, horizon)
            j = torch.randint(0, len(t), (count,), generator=self.gen)
            ti, si = t[j], s[j]
        idx = si[:, None] + torch.arange(horizon + 1)
        states = self.states[ti[:, None], idx]
        ok = None if self.ok is None else self.ok[ti[:, None], idx]
        hist = None
        if history:
            past = torch.clamp(si[:, None] + torch.arange(-history, 0), min=0)
            hist = self.u[ti[:, None], past]
        return states, self.u[ti[:, None], idx[:, :-1]], self.n[ti[:, None], idx[:, :-1]], hist, ok


@dataclass
class TrainResult:
    """A trained model with its history."""

    model: torch.nn.Module
    config: TrainConfig
    history: list = field(default_factory=list)
    seconds: float = 0.0
    stats: dict = field(default_factory=dict)
    #: {epoch count: evaluation-mode copy of the model after that many epochs} for the requested checkpoints
    checkpoints: dict = field(default_factory=dict)
    #: The aerodynamic terms' selection before training (:class:`sim.identification.aero.TermSelection`), with
    #: ``aero="select"``
    aero_selection: object = None


def theta_errors_pct(theta: np.ndarray, truth: np.ndarray) -> dict:
    """``{name: 100 (theta - truth) / truth}``."""
    return {n: float(100.0 * (t - r) / r) for n, t, r in zip(THETA_NAMES, theta, truth)}


def validation_loss(model, ds, stats) -> float:
    """One-step data loss (normalized MSE) on the validation split, evaluation mode, no grad."""
    va = ds.split == 1
    if not va.any():
        va = ds.split == 0
    xs, us_, ys = ds.x[va], ds.u[va], ds.x_next[va]
    if ds.valid is not None:
        use = ds.usable[va]
        xs, us_, ys = xs[use], us_[use], ys[use]
    x = torch.as_tensor(xs.reshape(-1, 12), dtype=torch.float32)
    u = torch.as_tensor(us_.reshape(-1, 4), dtype=torch.float32)
    y = torch.as_tensor(ys.reshape(-1, 12), dtype=torch.float32)
    was = model.training
    model.eval()
    with torch.no_grad():
        if getattr(model, "extra_states", ()):
            # the rotor speeds the model's own lag gives along each flight's commands
            x = torch.cat([x, torch.as_tensor(model_rotor_speeds(model, ds.u[va]).reshape(-1, 4),
                                              dtype=torch.float32)], dim=-1)
        r = (model.increment(x, u)[:, :12] - (y - x[:, :12])) / model.out_scale
        out = float((r * r).mean())
    model.train(was)
    return out


def model_rotor_speeds(model, u: np.ndarray) -> np.ndarray:
    """Rotor speeds (F, K, 4) at the start of each period that a motor-lag model gives along commands ``u`` (F, K, 4),
    from the first command's speed, with its own theta-hat and tau-hat
    (:func:`sim.identification.motor_lag.rotor_trajectory`)."""
    from sim.identification.motor_lag import rotor_trajectory

    theta7 = np.r_[model.theta.detach().double().numpy(), float(model.tau.detach())]
    p = QuadParams(n_max=float(np.sqrt(float(model.rotor[0]))), d=float(model.rotor[1]) * math.sqrt(2.0))
    return rotor_trajectory(np.asarray(u, dtype=float), theta7, p)[0][:, :-1]


def physics_residual(increment: torch.Tensor, x: torch.Tensor, u: torch.Tensor, theta: torch.Tensor,
                     p: QuadParams, scale: torch.Tensor) -> torch.Tensor:
    """Per-state residual (B, 12) of a predicted increment against an RK4 step under ``theta``.

    ``(increment - RK4(x, u; theta) + x) / scale``, with the RK4 step of
    :func:`pinn.physics.rk4_increment` (10 substeps of 1 ms, as the simulator).
    """
    return (increment - rk4_increment(x, u, theta, p)) / scale


def _rollout(model, start, states, us, p_ss: float, gen, ok=None):
    """Autoregressive rollout over a window (teacher forcing mixed with the model's own predictions).

    ``start`` (W, 12 + E) is the first input; each next input is the measured rigid-body state, or with
    probability ``p_ss`` the model's own prediction of it, followed by the model's own extra states. Where ``ok``
    (W, K + 1) says a state was not measured, the model's own prediction takes its place. Returns the
    inputs and predictions, step-major (K W, 12 + E).
    """
    K = us.shape[1]
    inp = start
    inputs, preds = [], []
    for k in range(K):
        pred = model(inp, us[:, k])
        inputs.append(inp)
        preds.append(pred)
        if k + 1 < K:
            nxt = states[:, k + 1]
            if p_ss > 0:
                own = torch.rand(nxt.shape[0], 1, generator=gen) < p_ss
                nxt = torch.where(own, pred[:, :12], nxt)
            if ok is not None:
                nxt = torch.where(ok[:, k + 1, None], nxt, pred[:, :12])
            inp = torch.cat([nxt, pred[:, 12:]], dim=-1)
    return torch.cat(inputs), torch.cat(preds)


def step_losses(model, states, us, ns, p_ss: float, colloc: torch.Tensor, p: QuadParams, scales: dict,
                config: TrainConfig, gen: torch.Generator, ok: torch.Tensor | None = None) -> dict:
    """Loss terms of one optimizer step (see the module docstring).

    Parameters
    ----------
    states : torch.Tensor, shape (W, K + 1, 12)
        Measured states of ``W`` windows of ``K`` steps.
    us, ns : torch.Tensor, shape (W, K, 4)
        Wrench commands and logged rotor speeds.
    p_ss : float
        Scheduled-sampling probability.
    colloc : torch.Tensor, shape (C, 13)
        Collocation features (phi .. vz, T, tau) in physical units.
    ok : torch.Tensor, shape (W, K + 1), optional
        Which states were measured (imported flight logs): the others are not targets of the data loss, and the
        rollout goes on from its own prediction there. None: all.

    Returns
    -------
    dict of scalar tensors: data, phys, theta, rotor, energy, smooth.
    """
    if getattr(model, "extra_states", ()):
        return _lag_step_losses(model, states, us, ns, p_ss, colloc, scales, gen)
    K = us.shape[1]
    s = model.out_scale
    theta = model.theta
    X, P = _rollout(model, states[:, 0], states, us, p_ss, gen, ok)     # step-major: (K W, 12)
    U = us.transpose(0, 1).reshape(-1, 4)
    Y = states[:, 1:].transpose(0, 1).reshape(-1, 12)
    inc = P - X
    r = (P - Y) / s
    if ok is None:
        out = {"data": (r * r).mean()}
    else:
        w = ok[:, 1:].transpose(0, 1).reshape(-1, 1)
        r = torch.where(w, r, torch.zeros_like(r))
        out = {"data": (r * r).sum() / (12.0 * w.sum().clamp(min=1))}

    # Physics: one RK4 evaluation for the rollout's points and the collocation points.
    xc = torch.zeros(colloc.shape[0], 12)
    xc[:, 3:12] = colloc[:, :9]
    uc = colloc[:, 9:]
    phys = rk4_increment(torch.cat([X, xc]), torch.cat([U, uc]), theta, p)
    n = X.shape[0]
    inc_c = model.increment(xc, uc)
    # The residual on data points is used twice with its gradient routed: it identifies
    # theta-hat against the network's prediction (held fixed; the data anchor it), and
    # it pulls the network toward the physics under theta-hat (held fixed). Letting both
    # move through one term lets an untrained network drag theta-hat anywhere. On the
    # collocation points only the network learns.
    if model.dropout_p > 0:
        # Identify against the deterministic (evaluation-mode) prediction: dropout noise
        # in the target would bias theta-hat.
        model.eval()
        with torch.no_grad():
            target = model.increment(X, U)
        model.train()
    else:
        target = inc.detach()
    rp = (target - phys[:n]) / s
    if hasattr(model, "residual"):
        # Physics plus network: the physics residual is the network's own output, and it trains the network
        # only (theta-hat, inside the prediction, would otherwise be pulled back toward its current value).
        rn = torch.cat([model.residual(X, U), model.residual(xc, uc)]) / s
    else:
        rn = (torch.cat([inc, inc_c]) - phys.detach()) / s
    out["theta"] = (rp * rp).mean()
    out["phys"] = (rn[:n] * rn[:n]).mean() + (rn[n:] * rn[n:]).mean()

    rw = (rotor_sq_from_wrench(us[:, 0], theta, p) - ns[:, 0] ** 2) / scales["n_sq"]
    out["rotor"] = (rw * rw).mean()

    zero = torch.zeros(())
    if config.energy > 0:
        # A regularizer of the network's predictions: theta-hat is held fixed in it.
        th = theta.detach()
        dE = (mechanical_energy(P, th, p.g) - mechanical_energy(X, th, p.g)) / DT
        pw = 0.5 * (power_balance(X, U, th, p.g, p.c_d) + power_balance(P, U, th, p.g, p.c_d))
        out["energy"] = (((dE - pw) / scales["power"]) ** 2).mean()
    else:
        out["energy"] = zero
    if config.smooth > 0:
        over = torch.relu((inc / DT).abs() - scales["rate_max"]) / scales["rate_max"]
        out["smooth"] = (over * over).mean()
    else:
        out["smooth"] = zero
    return out


def _lag_step_losses(model, states, us, ns, p_ss, colloc, scales, gen) -> dict:
    """Loss terms of one optimizer step of a motor-lag model (:class:`pinn.models.HybridLag`).

    ``us`` carries the window's commands after its ``ROTOR_HISTORY`` past ones: (W, H + K, 4). The rotor speeds
    at each window's start are the model's own along those past commands; inside the window they are its
    predictions (the telemetry is never an input: its noise would bias the parameters, errors in variables).
    The terms: ``data`` (the rigid-body states, as the other models), ``rotor`` (the rotor telemetry against
    the predicted rotor speeds, over the spread of the telemetry's increments), ``phys`` (the network residual
    on the data and on collocation points, which trains the network only); theta-hat and tau-hat are inside the
    prediction and are identified by ``data`` and ``rotor``.
    """
    K = states.shape[1] - 1
    hist, us = us[:, :-K], us[:, -K:]
    s = model.out_scale
    Z, P = _rollout(model, torch.cat([states[:, 0], model.rotor_speeds_after(hist)], dim=-1), states, us, p_ss, gen)
    U = us.transpose(0, 1).reshape(-1, 4)
    Y = states[:, 1:].transpose(0, 1).reshape(-1, 12)
    Nlog = ns.transpose(0, 1).reshape(-1, 4)           # telemetry at the end of each period
    r = (P[:, :12] - Y) / s
    rn = (P[:, 12:] - Nlog) / scales["n_inc"]
    zc = torch.zeros(colloc.shape[0], 16)
    zc[:, 3:12] = colloc[:, :9]
    zc[:, 12:] = colloc[:, 13:]
    res = torch.cat([model.residual(Z, U)[:, :12], model.residual(zc, colloc[:, 9:13])[:, :12]]) / s
    zero = torch.zeros(())
    return {"data": (r * r).mean(), "rotor": (rn * rn).mean(), "phys": (res * res).mean(), "theta": zero,
            "energy": zero, "smooth": zero}


def train(ds, config: TrainConfig, progress: bool = False, truth: QuadParams | None = None,
          checkpoints=()) -> TrainResult:
    """Train one model on a :class:`sim.identification.excitation.Dataset`.

    Parameters
    ----------
    ds : Dataset
        Training data (its train split is used; validation split for the
        validation loss).
    config : TrainConfig
    progress : bool
        Show a progress bar (epoch, losses, horizon, theta-hat errors).
    truth : QuadParams, optional
        True parameters, only to display theta-hat errors (default: the
        dataset's). Training never uses them.
    checkpoints : sequence of int
        Epoch counts (1 .. epochs) after which a copy of the model is kept
        in :attr:`TrainResult.checkpoints` (the zoo's early-epoch models).
    """
    checkpoints = sorted({int(c) for c in checkpoints})
    if checkpoints and not (1 <= checkpoints[0] and checkpoints[-1] <= config.epochs):
        raise ValueError(f"checkpoints must lie in 1 .. {config.epochs} epochs; found {checkpoints}")
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    # The dataset's parameters: training takes only the known constants g, c_d and d from
    # them (inside the physics); theta-hat never sees m, J, kt, kq, which serve only to
    # display theta-hat errors.
    p = dataset_params(ds) if truth is None else truth
    # The stated prior: the data's vehicle's datasheet values (the reference values for the Rolling Spider's data),
    # biased by config.theta_bias, so that data from another vehicle starts from that vehicle's datasheet.
    ref = dataset_params(ds)
    theta0 = ref.theta * (1.0 + config.theta_bias)

    st = training_stats(ds)
    selection = None
    if config.aero == "select":
        selection = select_aero_terms(ds, ref)
    model = build_model(config.arch, st, theta0, config.hidden, config.layers, config.dropout, config.variant(),
                        selection.fit.coefficients() if selection is not None else None)
    if selection is not None and selection.terms:
        f = selection.fit
        model.aero_identified = {c: {"value": f.values[c], "low": f.low[c], "high": f.high[c]} for c in f.values}
    data = _TrainData(ds, gen)
    T = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    lag = bool(getattr(model, "extra_states", ()))
    if lag and ds.valid is not None:
        raise ValueError(f"arch {config.arch!r} (the motor-lag model) trains on simulated datasets only: its rotor "
                         f"telemetry loss does not skip the samples a real log did not measure")
    feat_lo, feat_hi = T(st["feat_min"]), T(st["feat_max"])
    if lag:     # collocation points over the rotor telemetry's range too
        n_log = ds.rotor_speed[ds.split == 0].reshape(-1, 4)
        feat_lo, feat_hi = torch.cat([feat_lo, T(n_log.min(0))]), torch.cat([feat_hi, T(n_log.max(0))])
    scales = {"n_sq": T(st["n_sq_scale"]), "rate_max": T(st["rate_max"]), "power": ref.m * ref.g * 1.0,
              "n_inc": T(st["n_inc_scale"])}

    physical = [q for n, q in model.named_parameters() if n in PHYSICAL]
    net_params = [q for n, q in model.named_parameters() if n not in PHYSICAL]
    opt = torch.optim.Adam([{"params": net_params, "lr": config.lr},
                            {"params": physical, "lr": config.lr_theta}])
    total = config.epochs * config.steps_per_epoch
    warm = int(config.theta_warmup * total)
    # Network: cosine decay to lr / 20. theta-hat: frozen during the warm-up, while the
    # network is still far from the data (its physics residual would push theta-hat
    # anywhere), then the same cosine decay over the remaining steps (a constant rate
    # left theta-hat jittering by about 1 % at the end of the Proposed run).
    def cosine(k, start, end):
        return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * (k - start) / max(1, end - start)))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, [lambda k: cosine(k, 0, total), lambda k: 0.0 if k < warm else cosine(k, warm, total)])

    history = []
    kept = {}
    epochs = range(config.epochs)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = epochs = tqdm(epochs, desc=f"train {config.arch}", unit="epoch")
    t0 = time.perf_counter()
    model.train()
    for e in epochs:
        if config.dropout > 0 and e == math.ceil(config.dropout_until * config.epochs):
            set_dropout(model, 0.0)
        K = curriculum_horizon(e, config.epochs) if config.curriculum else 1
        p_ss = sampling_probability(e, config.epochs) if config.scheduled_sampling else 0.0
        sums = {"data": 0.0, "phys": 0.0, "theta": 0.0, "rotor": 0.0, "energy": 0.0, "smooth": 0.0}
        for _ in range(config.steps_per_epoch):
            states, us, ns, hist, ok = data.windows(max(1, config.batch // K), K,
                                                    history=ROTOR_HISTORY if lag else 0)
            if lag:
                us = torch.cat([hist, us], dim=1)
            f = feat_lo + (feat_hi - feat_lo) * torch.rand(config.n_colloc, len(feat_lo), generator=gen)
            losses = step_losses(model, states, us, ns, p_ss, f, p, scales, config, gen, ok)
            loss = (losses["data"] + config.lambda_p * (losses["phys"] + losses["theta"])
                    + config.lambda_rotor * losses["rotor"] + config.energy * losses["energy"]
                    + config.smooth * losses["smooth"])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net_params, 10.0)
            opt.step()
            sched.step()
            for k_ in sums:
                sums[k_] += float(losses[k_].detach())
        th = model.theta.detach().numpy().astype(float)
        rec = {"epoch": e, "horizon": K, "sampling_p": p_ss,
               **{k_: v / config.steps_per_epoch for k_, v in sums.items()},
               "val": validation_loss(model, ds, st), "theta": th.tolist(),
               "theta_err_pct": theta_errors_pct(th, p.theta)}
        if lag:
            rec["tau_m"] = float(model.tau.detach())
            if model.aero_terms:
                rec["aero"] = model.aero_values()
            tau_true = float(ds.meta.get("fidelity", {}).get("motor_tau", 0.0))
            if tau_true > 0:
                rec["theta_err_pct"]["tau_m"] = 100.0 * (rec["tau_m"] - tau_true) / tau_true
        history.append(rec)
        if e + 1 in checkpoints:
            kept[e + 1] = copy.deepcopy(model).eval()
        if bar is not None:
            worst = max(rec["theta_err_pct"].items(), key=lambda kv: abs(kv[1]))
            bar.set_postfix_str(f"K={K} p={p_ss:.2f} data={rec['data']:.2e} phys={rec['phys']:.2e} "
                                f"val={rec['val']:.2e} worst theta {worst[0]} {worst[1]:+.2f}%")
    model.eval()
    return TrainResult(model=model, config=config, history=history, seconds=time.perf_counter() - t0, stats=st,
                       checkpoints=kept, aero_selection=selection)


def aero_samples(ds, p: QuadParams, split: int) -> list:
    """The library's samples (:class:`sim.identification.aero.TermSamples`) of a simulated dataset's flights of
    ``split`` (0 train, 1 validation), the rigid body ``p`` explaining thrust and gravity.

    The rotor telemetry is the speed at each period's end; a period's speed is taken as the mean of its two ends (the
    first period's as its end), which the motor lag makes closer to the period's mean than either end.
    """
    from sim.identification.aero import flight_samples

    out = []
    for i in np.flatnonzero(ds.split == split):
        n_end = np.asarray(ds.rotor_speed[i], dtype=float)
        n_mid = 0.5 * (n_end + np.concatenate([n_end[:1], n_end[:-1]]))
        x = np.concatenate([ds.x[i], ds.x_next[i, -1:]])
        out.append(flight_samples(f"flight {i}", x, n_mid, p))
    return out


def select_aero_terms(ds, p: QuadParams):
    """The library's selection on a dataset: fitted on its training flights, judged on its validation flights (the
    training flights where it has none)."""
    from sim.identification.aero import select_terms

    if ds.valid is not None:
        raise ValueError("aero='select' trains on simulated datasets only (the motor-lag model's limit)")
    train_ = aero_samples(ds, p, 0)
    val = aero_samples(ds, p, 1) or train_
    return select_terms(train_, val)


def aero_summary(selection, model) -> dict:
    """A training's aerodynamic terms for its record: what the selection claimed (validation error before and after,
    m/s^2, and every step tried) and the model's record of them (:func:`pinn.models.aero_record`; empty terms when
    none was claimed)."""
    from .models import aero_record

    return {"validation_rmse_none": selection.validation_rmse_none, "validation_rmse": selection.validation_rmse,
            "steps": [dataclasses.asdict(s) for s in selection.steps],
            **(aero_record(model) if model.aero_terms else {"terms": []})}

