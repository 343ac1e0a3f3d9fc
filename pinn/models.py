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

from sim.params import NU, NX, THETA_NAMES

ARCHITECTURES = ("baseline", "modular", "fourier", "proposed")
#: State columns fed to the networks: phi, theta, psi, p, q, r, vx, vy, vz.
FEATURE_STATES = tuple(range(3, 12))
ANGLE_STATES = (3, 4, 5)
TRANSLATION_STATES = (0, 1, 2, 9, 10, 11)
ROTATION_STATES = (3, 4, 5, 6, 7, 8)
N_FEATURES = len(FEATURE_STATES) + NU


class MLP(nn.Module):
    """Tanh multilayer perceptron with optional dropout and forward-mode tangents."""

    def __init__(self, n_in: int, n_out: int, hidden: int, layers: int, dropout: float = 0.0):
        super().__init__()
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
            h = torch.tanh(lin(h))
            if self.dropout is not None:
                h = self.dropout(h)
        return self.out(h)

    def forward_tangent(self, h: torch.Tensor, T: torch.Tensor):
        """Value and tangent: ``T`` (B, n_in, k) -> (B, n_out, k). Evaluation mode only."""
        for lin in self.hidden:
            h = torch.tanh(lin(h))
            T = (1.0 - h * h).unsqueeze(-1) * torch.matmul(lin.weight, T)
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
    """

    arch = "base"

    def __init__(self, stats: dict, theta_init, hidden: int = 128, layers: int = 5, dropout: float = 0.0):
        super().__init__()
        self.register_buffer("in_mean", torch.as_tensor(stats["in_mean"], dtype=torch.float32).clone())
        self.register_buffer("in_std", torch.as_tensor(stats["in_std"], dtype=torch.float32).clone())
        self.register_buffer("out_scale", torch.as_tensor(stats["out_scale"], dtype=torch.float32).clone())
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
        """Architecture settings (for configs and metadata)."""
        return {"arch": self.arch, "hidden": self.hidden_size, "layers": self.layers, "dropout": self.dropout_p,
                "parameters": sum(p.numel() for n, p in self.named_parameters() if n != "log_theta")}


class Baseline(ResidualPINN):
    """Monolithic tanh MLP, 5 hidden layers."""

    arch = "baseline"

    def build(self, hidden, layers, dropout):
        self.mlp = MLP(N_FEATURES, NX, hidden, layers, dropout)

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
    Widths are chosen so the total size is close to the baseline's.
    """

    arch = "modular"

    def build(self, hidden, layers, dropout):
        sub = max(8, int(round(hidden / math.sqrt(2.0))))
        self.trans = MLP(N_FEATURES, len(TRANSLATION_STATES), sub, layers, dropout)
        self.rot = MLP(N_FEATURES, len(ROTATION_STATES), sub, layers, dropout)
        perm = torch.empty(NX, dtype=torch.long)
        perm[list(TRANSLATION_STATES)] = torch.arange(6)
        perm[list(ROTATION_STATES)] = torch.arange(6, 12)
        self.register_buffer("perm", perm)

    def network(self, f):
        return torch.cat([self.trans(f), self.rot(f)], dim=-1)[..., self.perm]

    def network_tangent(self, f, T):
        yt, Tt = self.trans.forward_tangent(f, T)
        yr, Tr = self.rot.forward_tangent(f, T)
        return torch.cat([yt, yr], dim=-1)[..., self.perm], torch.cat([Tt, Tr], dim=-2)[..., self.perm, :]


class Fourier(ResidualPINN):
    """Angles encoded as [sin(w_k a), cos(w_k a)] with log-spaced w_k = 1 .. 256 rad^-1.

    The other features (rates, velocities, inputs) are normalized as usual.
    """

    arch = "fourier"
    FREQS = tuple(2.0 ** k for k in range(9))  # 1, 2, ..., 256

    def build(self, hidden, layers, dropout):
        self.register_buffer("freqs", torch.tensor(self.FREQS, dtype=torch.float32))
        n_enc = len(ANGLE_STATES) * len(self.FREQS) * 2
        self.mlp = MLP(n_enc + N_FEATURES - len(ANGLE_STATES), NX, hidden, layers, dropout)

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


_CLASSES = {"baseline": Baseline, "modular": Modular, "fourier": Fourier, "proposed": Proposed}


def build_model(arch: str, stats: dict, theta_init, hidden: int = 128, layers: int = 5,
                dropout: float = 0.0) -> ResidualPINN:
    """Instantiate an architecture by name (one of :data:`ARCHITECTURES`)."""
    if arch not in _CLASSES:
        raise ValueError(f"arch must be one of {', '.join(ARCHITECTURES)}; found {arch!r}")
    return _CLASSES[arch](stats, theta_init, hidden, layers, dropout)
