"""Stochastic motion forecasting from intention (Tanke ch. 6).

- Intention labels (sec. 6.2.3): the nearest of the k-means centres the training fitted
  (``forecast.lab.intention_labels``), merged into ``n_intentions`` labels.
- Intention forecaster (sec. 6.2.1): GRU encoder e_l and autoregressive GRU decoder d_l (16 units),
  cross-entropy L_sym (6.4, teacher forced) + adversarial L_sym^adv (6.5) with a one-hidden-layer
  discriminator over 25 stacked label vectors (free-running, straight-through Gumbel-softmax).
- Pose forecaster (sec. 6.2.2): GRU encoder e_p, multi-layer GRU decoder d_p with hidden states
  h ⊕ z (z ~ N(0, I) concatenated to every layer), input x_{τ-1} ⊕ f(c_τ..c_{τ-1+γ}) where f is a
  temporal convolution with kernel γ (look-ahead), losses L_rec (6.8, weight fading linearly from 1 to 0
  over τ_rec frames) and L_adv (6.7) with a feed-forward discriminator over 25 stacked poses.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

ADV_WINDOW = 25  # frames stacked for both discriminators (sec. 6.2.4)


# ----------------------------------------------------------------------------- labels (sec. 6.2.3)


def assign(centres: np.ndarray, poses: np.ndarray) -> np.ndarray:
    d = ((poses[:, None].astype(np.float64) - centres[None]) ** 2).sum(-1)
    return d.argmin(1)


# ----------------------------------------------------------------------------- networks


class _MLPD(nn.Module):
    """Feed-forward discriminator over ADV_WINDOW stacked frames (sigmoid in the loss)."""

    def __init__(self, dim: int, hidden: int, layers: int = 1):
        super().__init__()
        mods: list[nn.Module] = []
        d = dim * ADV_WINDOW
        for _ in range(layers):
            mods += [nn.Linear(d, hidden), nn.ReLU()]
            d = hidden
        mods.append(nn.Linear(d, 1))
        self.net = nn.Sequential(*mods)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B,W,D) -> (B,)
        return self.net(x.flatten(1))[:, 0]


class IntentionModel(nn.Module):
    kind = "intention"
    stochastic = True

    def __init__(
        self,
        dim: int,
        centres: np.ndarray | torch.Tensor,
        merge: np.ndarray | torch.Tensor,
        n_intentions: int = 8,
        hidden: int = 256,
        layers: int = 2,
        z_dim: int = 32,
        label_hidden: int = 16,
        gamma: int = 10,
        f_dim: int = 16,
        dropout: float = 0.1,
        label_temp: float = 1.0,
        z_scale: float = 1.0,
    ):
        super().__init__()
        self.label_temp = label_temp  # sampling: temperature of d_l's label distribution (sample)
        self.z_scale = z_scale  # sampling: the noise z ~ N(0, z_scale^2 I) (ours; training draws N(0, I))
        self.dim, self.C, self.gamma, self.z_dim, self.layers = dim, n_intentions, gamma, z_dim, layers
        self.register_buffer("centres", torch.as_tensor(np.asarray(centres), dtype=torch.float32))
        self.register_buffer("merge", torch.as_tensor(np.asarray(merge), dtype=torch.long))
        # intention forecaster e_l, d_l (6.3)
        self.e_l = nn.GRU(dim, label_hidden, batch_first=True)
        self.d_l = nn.GRUCell(n_intentions, label_hidden)
        self.l_out = nn.Linear(label_hidden, n_intentions)
        self.D_label = _MLPD(n_intentions, 32, 1)
        # pose forecaster e_p, d_p (6.6)
        self.e_p = nn.GRU(dim, hidden, batch_first=True)
        self.f = nn.Conv1d(n_intentions, f_dim, kernel_size=gamma)
        self.d_p = nn.ModuleList(
            [nn.GRUCell(dim + f_dim if i == 0 else hidden + z_dim, hidden + z_dim) for i in range(layers)]
        )
        self.drop = nn.Dropout(dropout)
        self.p_out = nn.Linear(hidden + z_dim, dim)
        nn.init.zeros_(self.p_out.weight)
        nn.init.zeros_(self.p_out.bias)
        self.D_pose = _MLPD(dim, 256, 1)

    # -- labels
    def labels(self, poses_local: torch.Tensor) -> torch.Tensor:
        """Intention label of hip-normalised poses (...,D) -> (...,) long."""
        d = torch.cdist(poses_local.reshape(-1, self.dim), self.centres)
        return self.merge[d.argmin(1)].view(poses_local.shape[:-1])

    # -- intention forecaster
    def _label_init(self, obs):
        _, h = self.e_l(obs)
        return h[0]

    def label_logits_teacher(self, obs: torch.Tensor, c_prev: torch.Tensor) -> torch.Tensor:
        """Teacher forced: c_prev (B,L) labels of the frames before each target -> logits (B,L,C)."""
        h = self._label_init(obs)
        out = []
        onehot = F.one_hot(c_prev, self.C).float()
        for i in range(c_prev.shape[1]):
            h = self.d_l(onehot[:, i], h)
            out.append(self.l_out(h))
        return torch.stack(out, 1)

    def label_rollout(
        self, obs: torch.Tensor, c_last: torch.Tensor, n: int, temp: float = 1.0
    ) -> torch.Tensor:
        """Free running: one-hot labels (B,n,C) of d_l (6.3) at temperature temp (ours; Gumbel-softmax)."""
        h = self._label_init(obs)
        c = F.one_hot(c_last, self.C).float()
        out = []
        for _ in range(n):
            h = self.d_l(c, h)
            c = F.gumbel_softmax(self.l_out(h) / temp, hard=True)
            out.append(c)
        return torch.stack(out, 1)

    # -- pose forecaster
    def decode(self, obs: torch.Tensor, c_future: torch.Tensor, n_pred: int, z: torch.Tensor) -> torch.Tensor:
        """obs (B,T,D), c_future (B,n_pred+γ-1,C) label vectors of frames t+1.., z (B,Z) -> (B,n_pred,D)."""
        _, hp = self.e_p(obs[:, :-1])
        zero = torch.zeros_like(hp[0])
        h = [torch.cat([hp[0] if i == 0 else zero, z], -1) for i in range(self.layers)]
        fc = self.f(c_future.transpose(1, 2)).transpose(1, 2)  # (B,n_pred,f): f(c_τ .. c_{τ-1+γ})
        x, outs = obs[:, -1], []
        for tau in range(n_pred):
            inp = torch.cat([x, fc[:, tau]], -1)
            for i, cell in enumerate(self.d_p):
                h[i] = cell(inp if i == 0 else self.drop(h[i - 1]), h[i])
            x = x + self.p_out(h[-1])
            outs.append(x)
        return torch.stack(outs, 1)

    @torch.no_grad()
    def sample(
        self, obs: torch.Tensor, n_pred: int, n_samples: int = 1, obs_local: torch.Tensor | None = None, **_
    ) -> torch.Tensor:
        """obs (B,T,D) normalised at the last frame; obs_local (B,T,D) per-frame hip-normalised poses (for the
        last observed label; derived from obs when absent) -> (B,S,n_pred,D). Labels at ``label_temp``, z
        scaled by ``z_scale``."""
        B, T, D = obs.shape
        c_last = self.labels((local_poses(obs) if obs_local is None else obs_local)[:, -1])
        o, c0 = obs.repeat_interleave(n_samples, 0), c_last.repeat_interleave(n_samples, 0)
        c = self.label_rollout(o, c0, n_pred + self.gamma - 1, self.label_temp)
        z = self.z_scale * torch.randn(B * n_samples, self.z_dim, device=obs.device)
        y = self.decode(o, c, n_pred, z)
        return y.view(B, n_samples, n_pred, D)

    def generator_parameters(self):
        skip = {id(p) for p in list(self.D_pose.parameters()) + list(self.D_label.parameters())}
        return [p for p in self.parameters() if id(p) not in skip]

    def discriminator_parameters(self):
        return list(self.D_pose.parameters()) + list(self.D_label.parameters())


def local_poses(x: torch.Tensor, lhip: int = 11, rhip: int = 12) -> torch.Tensor:
    """Per-frame hip normalisation (eq. 3.5) of flattened poses (...,D=3J) -> (...,D) (torch)."""
    p = x.view(*x.shape[:-1], -1, 3)
    root = 0.5 * (p[..., lhip, :] + p[..., rhip, :])
    d = p[..., rhip, :] - p[..., lhip, :]
    th = torch.atan2(d[..., 1], d[..., 0])
    c, s = torch.cos(th), torch.sin(th)
    q = p - root[..., None, :]
    xr = c[..., None] * q[..., 0] + s[..., None] * q[..., 1]
    yr = -s[..., None] * q[..., 0] + c[..., None] * q[..., 1]
    return torch.stack([xr, yr, q[..., 2]], -1).reshape(x.shape)
