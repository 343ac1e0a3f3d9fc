"""The four PINN architectures.

All predict the next state in the residual form

    x_{t+1} = x_t + s * NN(features(x_t, u_t))

with the input normalization and the output scale ``s`` stored as buffers,
so the exported graph contains them. Positions are not features: the
dynamics are invariant to translation, and a network that saw positions
would have to extrapolate as soon as the vehicle flies somewhere new. All
four architectures share this choice.

Every model carries learnable physical parameters ``theta = (m, Jxx, Jyy,
Jzz, kt, kq)``, positive through a log parameterization.

Besides ``forward``, every model has ``forward_jacobian`` returning the
exact ``A = dx_next/dx`` and ``B = dx_next/du`` computed with plain tensor
operations (forward-mode tangents through the layers), so that it exports
to ONNX next to the model.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from sim.params import NU, NX, THETA_NAMES, QuadParams

from .physics import lagged_rotor_increment, rk4_increment, rk4_increment_tangent, rotor_command_torch

ARCHITECTURES = ("baseline", "modular", "fourier", "proposed")
#: State columns fed to the networks: phi, theta, psi, p, q, r, vx, vy, vz.
FEATURE_STATES = tuple(range(3, 12))
ANGLE_STATES = (3, 4, 5)
TRANSLATION_STATES = (0, 1, 2, 9, 10, 11)
ROTATION_STATES = (3, 4, 5, 6, 7, 8)
N_FEATURES = len(FEATURE_STATES) + NU
#: Defaults of the zoo's variant settings (see :class:`ResidualPINN`); the shipped models use these.
VARIANT_DEFAULTS = {"activation": "tanh", "gain": 1.0, "fourier_max": 8, "coupled": True}


#: Hidden-layer activations. tanh (every shipped model) bounds each step's correction; softplus (a smooth relu)
#: does not, which is one honest way for a learned model to diverge in a rollout. (relu itself is not offered: its
#: kinks make the derivative graph disagree with the finite differences the model contract checks it against.)
ACTIVATIONS = ("tanh", "softplus")
#: Names of the learnable physical parameters among a model's parameters (not network weights).
PHYSICAL = ("log_theta", "log_tau", "aero_coef")


def _softplus(z: torch.Tensor) -> torch.Tensor:
    """log(1 + exp(z)), written with operations onnxruntime runs in float64 (it has no float64 Softplus)."""
    return torch.clamp(z, min=0.0) + torch.log(1.0 + torch.exp(-torch.abs(z)))


class MLP(nn.Module):
    """Multilayer perceptron (tanh or softplus) with optional dropout and forward-mode tangents."""

    def __init__(self, n_in: int, n_out: int, hidden: int, layers: int, dropout: float = 0.0,
                 activation: str = "tanh"):
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {', '.join(ACTIVATIONS)}; found {activation!r}")
        self.softplus = activation == "softplus"
        sizes = [n_in] + [hidden] * layers
        self.hidden = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.out = nn.Linear(hidden, n_out)
        self.dropout = nn.Dropout(dropout) if dropout > 0 else None
        # Small last layer: the network starts near "no correction".
        nn.init.zeros_(self.out.bias)
        with torch.no_grad():
            self.out.weight.mul_(0.1)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        for lin in self.hidden:
            h = _softplus(lin(h)) if self.softplus else torch.tanh(lin(h))
            if self.dropout is not None:
                h = self.dropout(h)
        return self.out(h)

    def forward_tangent(self, h: torch.Tensor, T: torch.Tensor):
        """Value and tangent: ``T`` (B, n_in, k) -> (B, n_out, k). Evaluation mode only."""
        for lin in self.hidden:
            if self.softplus:
                z = lin(h)
                h = _softplus(z)
                slope = torch.sigmoid(z)
            else:
                h = torch.tanh(lin(h))
                slope = 1.0 - h * h
            T = slope.unsqueeze(-1) * torch.matmul(lin.weight, T)
        return self.out(h), torch.matmul(self.out.weight, T)


class ResidualPINN(nn.Module):
    """Base class: normalization, residual form, learnable parameters.

    Parameters
    ----------
    stats : dict of torch.Tensor
        ``in_mean``, ``in_std`` (13,) feature normalization and ``out_scale``
        (12,) residual scale, from the training split.
    theta_init : sequence of float
        Initial ``(m, Jxx, Jyy, Jzz, kt, kq)`` (a biased guess).
    hidden, layers : int
        Width and number of hidden layers.
    dropout : float
        Dropout probability between hidden layers (0 = none).
    variant : dict, optional
        Departures from the shipped design (keys of :data:`VARIANT_DEFAULTS`), used by the model zoo:
        ``activation`` of the hidden layers, ``gain`` multiplying the residual scale ``s``,
        ``fourier_max`` (Fourier: highest frequency 2**fourier_max rad^-1), ``coupled`` (Modular: False
        hides the rotational states from the translation module).
    """

    arch = "base"

    def __init__(self, stats: dict, theta_init, hidden: int = 128, layers: int = 5, dropout: float = 0.0,
                 variant: dict | None = None):
        super().__init__()
        variant = dict(variant or {})
        unknown = set(variant) - set(VARIANT_DEFAULTS)
        if unknown:
            raise ValueError(f"variant keys must be among {', '.join(VARIANT_DEFAULTS)}; found {sorted(unknown)}")
        self.variant = {k: v for k, v in variant.items() if v != VARIANT_DEFAULTS[k]}
        self.opt = {**VARIANT_DEFAULTS, **variant}
        gain = float(self.opt["gain"])
        if not gain > 0:
            raise ValueError(f"variant gain must be > 0; found {gain}")
        self.register_buffer("in_mean", torch.as_tensor(stats["in_mean"], dtype=torch.float32).clone())
        self.register_buffer("in_std", torch.as_tensor(stats["in_std"], dtype=torch.float32).clone())
        self.register_buffer("out_scale", gain * torch.as_tensor(stats["out_scale"], dtype=torch.float32).clone())
        theta0 = torch.as_tensor(theta_init, dtype=torch.float32)
        if theta0.shape != (6,) or not bool(torch.all(theta0 > 0)):
            raise ValueError(f"theta_init must be 6 positive values {THETA_NAMES}; found {theta_init}")
        self.log_theta = nn.Parameter(theta0.log())
        self.hidden_size, self.layers, self.dropout_p = hidden, layers, dropout
        self.build(hidden, layers, dropout)

    # -- to be provided by each architecture --------------------------------
    def build(self, hidden: int, layers: int, dropout: float) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def network(self, f: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        """Normalized features (B, 13) -> raw increment (B, 12) before scaling."""
        raise NotImplementedError

    def network_tangent(self, f: torch.Tensor, T: torch.Tensor):  # pragma: no cover - abstract
        """Like :meth:`network`, also mapping the feature tangent T (B, 13, 16) to (B, 12, 16)."""
        raise NotImplementedError

    # -- shared ---------------------------------------------------------------
    @property
    def theta(self) -> torch.Tensor:
        """Identified parameters ``(m, Jxx, Jyy, Jzz, kt, kq)``, always positive."""
        return self.log_theta.exp()

    def features(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Normalized features (B, 13): (phi .. vz, T, tau) minus mean over std."""
        raw = torch.cat([x[..., 3:12], u], dim=-1)
        return (raw - self.in_mean) / self.in_std

    def increment(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Predicted ``x_{t+1} - x_t`` (B, 12)."""
        return self.out_scale * self.network(self.features(x, u))

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Next state (B, 12) from state (B, 12) and wrench (B, 4)."""
        return x + self.increment(x, u)

    def forward_jacobian(self, x: torch.Tensor, u: torch.Tensor):
        """Next state (B, 12), ``A = dx_next/dx`` (B, 12, 12) and ``B = dx_next/du`` (B, 12, 4).

        Exact (forward-mode through every layer), written with plain tensor
        operations so that it exports to ONNX with a dynamic batch.
        """
        f = self.features(x, u)
        n = x.shape[0]
        # d features / d (x, u): feature i is column c_i scaled by 1 / std_i.
        sel = torch.zeros(N_FEATURES, NX + NU, dtype=x.dtype, device=x.device)
        for i, c in enumerate(list(FEATURE_STATES) + [NX + k for k in range(NU)]):
            sel[i, c] = 1.0
        T0 = (sel / self.in_std.unsqueeze(-1)).expand(n, N_FEATURES, NX + NU)
        y, T = self.network_tangent(f, T0)
        eye = torch.eye(NX, dtype=x.dtype, device=x.device).expand(n, NX, NX)
        J = self.out_scale.unsqueeze(-1) * T
        return x + self.out_scale * y, eye + J[..., :NX], J[..., NX:]

    def describe(self) -> dict:
        """Architecture settings (for configs and metadata); ``variant`` only when it departs from the default."""
        out = {"arch": self.arch, "hidden": self.hidden_size, "layers": self.layers, "dropout": self.dropout_p,
               "parameters": sum(p.numel() for n, p in self.named_parameters() if n not in PHYSICAL)}
        if self.variant:
            out["variant"] = dict(self.variant)
        return out


class Baseline(ResidualPINN):
    """Monolithic tanh MLP, 5 hidden layers."""

    arch = "baseline"

    def build(self, hidden, layers, dropout):
        self.mlp = MLP(N_FEATURES, NX, hidden, layers, dropout, self.opt["activation"])

    def network(self, f):
        return self.mlp(f)

    def network_tangent(self, f, T):
        return self.mlp.forward_tangent(f, T)


class Proposed(Baseline):
    """The baseline network; differs in training (curriculum, scheduled sampling, dropout, energy, smoothness)."""

    arch = "proposed"


class Modular(ResidualPINN):
    """Separate translation (x, y, z, vx, vy, vz) and rotation (phi .. r) subnetworks.

    Each subnetwork sees all features; they share no weights and no gradient.
    Widths are chosen so the total size is close to the baseline's. With the
    variant ``coupled=False`` (the paper's design) each module sees only its
    own states and the inputs: the translation module cannot see the attitude
    that tilts the thrust.
    """

    arch = "modular"

    def build(self, hidden, layers, dropout):
        sub = max(8, int(round(hidden / math.sqrt(2.0))))
        act = self.opt["activation"]
        if self.opt["coupled"]:
            t_idx = r_idx = list(range(N_FEATURES))
        else:
            inputs = list(range(len(FEATURE_STATES), N_FEATURES))
            t_idx = [FEATURE_STATES.index(i) for i in (9, 10, 11)] + inputs
            r_idx = [FEATURE_STATES.index(i) for i in ROTATION_STATES] + inputs
        self.register_buffer("t_idx", torch.tensor(t_idx, dtype=torch.long), persistent=False)
        self.register_buffer("r_idx", torch.tensor(r_idx, dtype=torch.long), persistent=False)
        self.trans = MLP(len(t_idx), len(TRANSLATION_STATES), sub, layers, dropout, act)
        self.rot = MLP(len(r_idx), len(ROTATION_STATES), sub, layers, dropout, act)
        perm = torch.empty(NX, dtype=torch.long)
        perm[list(TRANSLATION_STATES)] = torch.arange(6)
        perm[list(ROTATION_STATES)] = torch.arange(6, 12)
        self.register_buffer("perm", perm)

    def _views(self, f):
        if self.opt["coupled"]:
            return f, f
        return f[..., self.t_idx], f[..., self.r_idx]

    def network(self, f):
        ft, fr = self._views(f)
        return torch.cat([self.trans(ft), self.rot(fr)], dim=-1)[..., self.perm]

    def network_tangent(self, f, T):
        ft, fr = self._views(f)
        Tt_in, Tr_in = (T, T) if self.opt["coupled"] else (T[..., self.t_idx, :], T[..., self.r_idx, :])
        yt, Tt = self.trans.forward_tangent(ft, Tt_in)
        yr, Tr = self.rot.forward_tangent(fr, Tr_in)
        return torch.cat([yt, yr], dim=-1)[..., self.perm], torch.cat([Tt, Tr], dim=-2)[..., self.perm, :]


class Fourier(ResidualPINN):
    """Angles encoded as [sin(w_k a), cos(w_k a)] with log-spaced w_k = 1 .. 256 rad^-1.

    The other features (rates, velocities, inputs) are normalized as usual.
    The variant ``fourier_max=n`` sets the highest frequency to 2**n rad^-1.
    """

    arch = "fourier"
    FREQS = tuple(2.0 ** k for k in range(9))  # 1, 2, ..., 256

    def build(self, hidden, layers, dropout):
        freqs = tuple(2.0 ** k for k in range(int(self.opt["fourier_max"]) + 1))
        self.register_buffer("freqs", torch.tensor(freqs, dtype=torch.float32))
        n_enc = len(ANGLE_STATES) * len(freqs) * 2
        self.mlp = MLP(n_enc + N_FEATURES - len(ANGLE_STATES), NX, hidden, layers, dropout, self.opt["activation"])

    def _encode(self, f):
        # f[..., 0:3] are normalized angles; recover radians for the encoding.
        ang = f[..., 0:3] * self.in_std[0:3] + self.in_mean[0:3]
        wa = ang.unsqueeze(-1) * self.freqs                       # (B, 3, K)
        enc = torch.cat([torch.sin(wa), torch.cos(wa)], dim=-1)   # (B, 3, 2K)
        return torch.cat([enc.flatten(-2), f[..., 3:]], dim=-1), wa

    def network(self, f):
        return self.mlp(self._encode(f)[0])

    def network_tangent(self, f, T):
        h, wa = self._encode(f)
        # d enc / d f_angle = std * w * [cos, -sin]
        scale = self.in_std[0:3].unsqueeze(-1) * self.freqs                                   # (3, K)
        d = torch.cat([torch.cos(wa) * scale, -torch.sin(wa) * scale], dim=-1)               # (B, 3, 2K)
        T_enc = (d.unsqueeze(-1) * T[..., 0:3, :].unsqueeze(-2)).flatten(-3, -2)             # (B, 3*2K, k)
        return self.mlp.forward_tangent(h, torch.cat([T_enc, T[..., 3:, :]], dim=-2))


class Absolute(ResidualPINN):
    """An MLP that outputs the next state itself, not an increment (a zoo variant, not a shipped design).

    ``x_next = mu_y + sigma_y * NN((x, u) normalized)``: every state, positions
    included, is a feature, and the output is scaled by the spread of the
    next states rather than of their increments. This is the form the
    residual design avoids: a one-step error is now a fraction of the state's
    range, and the network must learn the identity.
    """

    arch = "absolute"

    def __init__(self, stats: dict, theta_init, hidden: int = 128, layers: int = 5, dropout: float = 0.0,
                 variant: dict | None = None):
        super().__init__(stats, theta_init, hidden, layers, dropout, variant)
        for key, n in (("abs_in_mean", NX + NU), ("abs_in_std", NX + NU), ("abs_out_mean", NX), ("abs_out_std", NX)):
            if key not in stats:
                raise ValueError(f"the absolute-state model needs the training statistic {key!r} ({n} values)")
            self.register_buffer(key, torch.as_tensor(stats[key], dtype=torch.float32).clone())

    def build(self, hidden, layers, dropout):
        self.mlp = MLP(NX + NU, NX, hidden, layers, dropout, self.opt["activation"])

    def forward(self, x, u):
        f = (torch.cat([x, u], dim=-1) - self.abs_in_mean) / self.abs_in_std
        return self.abs_out_mean + self.abs_out_std * self.mlp(f)

    def increment(self, x, u):
        return self.forward(x, u) - x

    def forward_jacobian(self, x, u):
        f = (torch.cat([x, u], dim=-1) - self.abs_in_mean) / self.abs_in_std
        n = x.shape[0]
        # diag(1 / std) as the identity scaled by columns (the TorchScript exporter has no aten::diag)
        T0 = (torch.eye(NX + NU, dtype=f.dtype) / self.abs_in_std).expand(n, NX + NU, NX + NU)
        y, T = self.mlp.forward_tangent(f, T0)
        J = self.abs_out_std.unsqueeze(-1) * T
        return self.abs_out_mean + self.abs_out_std * y, J[..., :NX], J[..., NX:]


class Hybrid(Baseline):
    """Physics plus network: an RK4 step of the nominal equations under theta-hat, plus a network residual.

    ``x_next = x + RK4(x, u; theta-hat) + s * NN(features)``. The learnable
    parameters enter the prediction itself, so the data fit identifies them
    directly; in the other four architectures they enter only through the
    physics loss. The residual network is the Baseline's MLP, started at
    zero (the model starts as the nominal equations under the initial guess).
    The physics integrates the period in :data:`PHYSICS_SUBSTEPS` RK4 steps;
    gravity and the drag coefficient are known constants (the training
    statistic ``physics`` = ``(g, c_d)``), stored in the model.
    """

    arch = "hybrid"

    def __init__(self, stats: dict, theta_init, hidden: int = 128, layers: int = 5, dropout: float = 0.0,
                 variant: dict | None = None):
        super().__init__(stats, theta_init, hidden, layers, dropout, variant)
        if "physics" not in stats:
            raise ValueError("the physics-plus-network model needs the training statistic 'physics' "
                             "(gravity in m/s^2 and the drag coefficient in 1/m)")
        g, c_d = (float(v) for v in torch.as_tensor(stats["physics"], dtype=torch.float64).reshape(-1)[:2])
        # float64, so that a float32 copy of the constants never reaches the float64 export
        self.register_buffer("physics", torch.tensor([g, c_d], dtype=torch.float64))
        self.g, self.c_d = g, c_d
        self._constants = QuadParams(g=g, c_d=c_d)
        with torch.no_grad():
            self.mlp.out.weight.zero_()

    def _physics(self, x, u):
        return rk4_increment_tangent(x, u, self.theta.to(x.dtype), self.g, self.c_d, substeps=PHYSICS_SUBSTEPS)

    def physics_increment(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The nominal equations' increment under theta-hat (B, 12)."""
        return rk4_increment(x, u, self.theta.to(x.dtype), self._constants, substeps=PHYSICS_SUBSTEPS)

    def residual(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The network's part of the increment (B, 12): what the nominal equations under theta-hat miss."""
        return self.out_scale * self.network(self.features(x, u))

    def increment(self, x, u):
        return self.physics_increment(x, u) + self.residual(x, u)

    def forward_jacobian(self, x, u):
        x_net, A_net, B_net = super().forward_jacobian(x, u)
        inc, A, B = self._physics(x, u)
        return x_net + inc, A_net + A, B_net + B


#: Names of the rotor-speed states of :class:`HybridLag` (as the high-fidelity oracle's).
ROTOR_STATES = ("n1", "n2", "n3", "n4")
#: Initial guess of the motor time constant, s (as the lag-aware classical estimator's).
TAU_INIT = 0.05


class HybridLag(Hybrid):
    """Physics plus network with the motor lag: the four rotor speeds as extra states and ``tau_m`` learnable.

    State ``z = (x, n)`` (16): the rigid body and the rotor speeds (RU). One period is
    :func:`pinn.physics.lagged_rotor_increment` under theta-hat and tau-hat (the rotors follow the
    command through the lag, exactly; the rigid body feels ``M(kt, kq) n(t)^2``), plus a network residual
    on the twelve rigid-body states. The network sees the rotor speeds too (normalized), so that effects
    that scale with them (rotor drag, gyroscopic torque) are within its reach. Training needs the
    statistics ``n_mean``, ``n_std`` (rotor telemetry) and ``rotor`` = ``(n_max_sq, lever)``.

    ``aero`` adds aerodynamic terms of :mod:`sim.identification.aero` to the physics (name -> initial coefficients,
    in the library's order and units): they act at every RK4 stage with that stage's rotor speeds and thrust, and
    their coefficients are learnable physical parameters like theta-hat (each stored relative to the magnitude of
    its initial value, so that one learning rate suits coefficients of every unit).
    """

    arch = "hybrid_lag"
    extra_states = ROTOR_STATES

    def __init__(self, stats: dict, theta_init, hidden: int = 128, layers: int = 5, dropout: float = 0.0,
                 variant: dict | None = None, tau_init: float = TAU_INIT, aero: dict | None = None):
        for key in ("n_mean", "n_std", "rotor"):
            if key not in stats:
                raise ValueError(f"the motor-lag model needs the training statistic {key!r}")
        super().__init__(stats, theta_init, hidden, layers, dropout, variant)
        for key in ("n_mean", "n_std"):
            self.register_buffer(key, torch.as_tensor(stats[key], dtype=torch.float32).clone())
        n_max_sq, lever = (float(v) for v in torch.as_tensor(stats["rotor"], dtype=torch.float64).reshape(-1)[:2])
        self.register_buffer("rotor", torch.tensor([n_max_sq, lever], dtype=torch.float64))
        from sim.vehicles.rotors import mixer
        unit = torch.tensor(mixer(1.0, 1.0, lever), dtype=torch.float64)
        self.register_buffer("mixer_unit", unit)
        self.register_buffer("mixer_unit_inv", torch.linalg.inv(unit))   # (the exporter has no matrix inverse)
        if not tau_init > 0:
            raise ValueError(f"tau_init must be > 0 s; found {tau_init}")
        self.log_tau = nn.Parameter(torch.tensor(math.log(tau_init), dtype=torch.float32))
        self.aero_terms = _aero_terms(aero)
        #: The terms' identification before training (coefficient -> value, low, high: :func:`aero_record`), when
        #: the training identified them.
        self.aero_identified: dict = {}
        if self.aero_terms:
            c0 = torch.tensor([float(c) for n in self.aero_terms for c in aero[n]], dtype=torch.float64)
            scale = torch.where(c0.abs() > 0, c0.abs(), torch.ones_like(c0))
            self.register_buffer("aero_scale", scale)
            self.aero_coef = nn.Parameter((c0 / scale).to(torch.float32))

    @property
    def aero(self) -> dict:
        """The aerodynamic terms' coefficients: name -> tensor (k,) in the library's units (empty without terms)."""
        if not self.aero_terms:
            return {}
        from sim.identification.aero import TERMS

        c = self.aero_scale.to(self.aero_coef.dtype) * self.aero_coef
        out, i = {}, 0
        for n in self.aero_terms:
            k = len(TERMS[n].coefficients)
            out[n] = c[i:i + k]
            i += k
        return out

    def _aero(self, dtype):
        return {n: c.to(dtype) for n, c in self.aero.items()}

    def aero_values(self) -> dict:
        """:attr:`aero` as plain floats: name -> list of coefficients (for records)."""
        return {n: [float(v) for v in c.detach()] for n, c in self.aero.items()}

    def build(self, hidden, layers, dropout):
        self.mlp = MLP(N_FEATURES + 4, NX, hidden, layers, dropout, self.opt["activation"])

    @property
    def tau(self) -> torch.Tensor:
        """Identified motor time constant, s."""
        return self.log_tau.exp()

    def _consts(self, dtype):
        return {"g": self.physics[0].to(dtype), "c_d": self.physics[1].to(dtype),
                "mixer_unit": self.mixer_unit.to(dtype), "mixer_unit_inv": self.mixer_unit_inv.to(dtype),
                "n_max_sq": self.rotor[0].to(dtype)}

    def features(self, z, u):
        raw = torch.cat([z[..., 3:12], u], dim=-1)
        f = (raw - self.in_mean) / self.in_std
        return torch.cat([f, (z[..., 12:16] - self.n_mean) / self.n_std], dim=-1)

    def physics_increment(self, z, u):
        inc_x, inc_n = lagged_rotor_increment(z[..., :12], z[..., 12:16], u, self.theta.to(z.dtype),
                                              self.tau.to(z.dtype), self._consts(z.dtype), substeps=PHYSICS_SUBSTEPS,
                                              aero=self._aero(z.dtype))
        return torch.cat([inc_x, inc_n], dim=-1)

    def residual(self, z, u):
        r = self.out_scale * self.network(self.features(z, u))
        return torch.cat([r, torch.zeros_like(r[..., :4])], dim=-1)

    def rotor_speeds_after(self, u_hist: torch.Tensor) -> torch.Tensor:
        """Rotor speeds (W, 4) the model's lag gives after the commands ``u_hist`` (W, J, 4), from the first one's.

        ``n_J = a^J c_0 + (1 - a) sum_j a^(J-1-j) c_j`` with ``a = exp(-dt / tau)``: the lag's exact recursion
        ``n_{k+1} = c_k + (n_k - c_k) a`` from ``n_0 = c_0``. Differentiable in theta-hat and tau-hat.
        """
        from sim.params import DT

        c, _ = rotor_command_torch(u_hist, self.theta.to(u_hist.dtype), self._consts(u_hist.dtype))
        J = u_hist.shape[1]
        a = torch.exp(-DT / self.tau.to(u_hist.dtype))
        powers = a ** torch.arange(J - 1, -1, -1, dtype=u_hist.dtype)          # a^(J-1-j)
        return a ** J * c[:, 0] + (1.0 - a) * torch.einsum("j,wjk->wk", powers, c)

    def forward_jacobian(self, z, u):
        n = z.shape[0]
        f = self.features(z, u)
        # d features / d (z, u): rigid-body and input columns as the other models, then the rotor speeds.
        cols = list(FEATURE_STATES) + [16 + k for k in range(NU)] + [12 + k for k in range(4)]
        std = torch.cat([self.in_std, self.n_std]).to(z.dtype)
        sel = torch.zeros(len(cols), 20, dtype=z.dtype, device=z.device)
        for i, c in enumerate(cols):
            sel[i, c] = 1.0
        y, T = self.network_tangent(f, (sel / std.unsqueeze(-1)).expand(n, len(cols), 20))
        inc_x, inc_n, A, B = lagged_rotor_increment(z[..., :12], z[..., 12:16], u, self.theta.to(z.dtype),
                                                    self.tau.to(z.dtype), self._consts(z.dtype),
                                                    substeps=PHYSICS_SUBSTEPS, tangent=True, aero=self._aero(z.dtype))
        J = self.out_scale.unsqueeze(-1) * T                                   # (B, 12, 20)
        J = torch.cat([J, torch.zeros_like(J[:, :4])], dim=1)                  # (B, 16, 20)
        eye = torch.eye(16, dtype=z.dtype, device=z.device).expand(n, 16, 16)
        nxt = z + torch.cat([inc_x + self.out_scale * y, inc_n], dim=-1)
        return nxt, eye + A + J[..., :16], B + J[..., 16:]

    def describe(self) -> dict:
        out = {**super().describe(), "extra_states": list(self.extra_states)}
        if self.aero_terms:
            out["aero"] = self.aero_values()
            if self.aero_identified:
                out["aero_identified"] = dict(self.aero_identified)
        return out


def _aero_terms(aero) -> tuple[str, ...]:
    """The names of ``aero`` (name -> coefficients), checked against the library, in its order."""
    from sim.identification.aero import TERMS

    aero = dict(aero or {})
    for n, c in aero.items():
        if n not in TERMS:
            raise ValueError(f"aero term must be one of {', '.join(TERMS)}; found {n!r}")
        if len(c) != len(TERMS[n].coefficients) or not all(math.isfinite(float(v)) for v in c):
            raise ValueError(f"aero term {n!r} needs {len(TERMS[n].coefficients)} finite coefficients "
                             f"{TERMS[n].coefficients}; found {list(c)}")
    return tuple(n for n in TERMS if n in aero)


#: RK4 steps per period in the physics of :class:`Hybrid`. One step of 10 ms is within 2e-8 (1e-5 relative) of the
#: simulator's ten steps of 1 ms on states of 0.3 rad and 0.3 rad/s, far below the data's noise; two steps would be
#: within 1.5e-9 but make the exported derivative graph a third slower (3.4 against 2.5 ms for 30 stages).
PHYSICS_SUBSTEPS = 1


_CLASSES = {"baseline": Baseline, "modular": Modular, "fourier": Fourier, "proposed": Proposed, "absolute": Absolute,
            "hybrid": Hybrid, "hybrid_lag": HybridLag}
#: Every class :func:`build_model` knows: the four architectures and the zoo's absolute-state variant.
ALL_ARCHITECTURES = tuple(_CLASSES)


def build_model(arch: str, stats: dict, theta_init, hidden: int = 128, layers: int = 5,
                dropout: float = 0.0, variant: dict | None = None, aero: dict | None = None) -> ResidualPINN:
    """Instantiate an architecture by name (one of :data:`ALL_ARCHITECTURES`); ``aero`` (aerodynamic terms, name ->
    initial coefficients) only for the motor-lag model."""
    if arch not in _CLASSES:
        raise ValueError(f"arch must be one of {', '.join(ALL_ARCHITECTURES)}; found {arch!r}")
    if aero:
        if arch != "hybrid_lag":
            raise ValueError(f"aerodynamic terms are carried by the motor-lag model (hybrid_lag); found arch {arch!r}")
        return HybridLag(stats, theta_init, hidden, layers, dropout, variant, aero=aero)
    return _CLASSES[arch](stats, theta_init, hidden, layers, dropout, variant)


def aero_record(model) -> dict:
    """What a model file records of its aerodynamic terms: the terms, each coefficient's trained value and unit, and
    (when the training identified them first) the identified value with its 95 % interval."""
    from sim.identification.aero import TERMS

    out = {"terms": list(model.aero_terms), "coefficients": {}, "units": {}}
    for n, c in model.aero.items():
        for name, unit, v in zip(TERMS[n].coefficients, TERMS[n].units, c.detach()):
            out["coefficients"][name] = float(v)
            out["units"][name] = unit
    if model.aero_identified:
        out["identified"] = dict(model.aero_identified)
    return out

