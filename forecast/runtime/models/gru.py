"""Deterministic sequence-to-sequence GRU (Martinez et al. [132], the seed's 'Seq2Seq' baseline).

Encoder GRU over the observed poses; decoder GRU cell fed its own previous output, predicting a
residual velocity (x_t = x_{t-1} + W h_t). Rolled out autoregressively for any horizon.
"""

from __future__ import annotations

import torch
from torch import nn


class Seq2SeqGRU(nn.Module):
    kind = "gru"
    stochastic = False

    def __init__(self, dim: int, hidden: int = 256, dropout: float = 0.0):
        super().__init__()
        self.encoder = nn.GRU(dim, hidden, batch_first=True)
        self.decoder = nn.GRUCell(dim, hidden)
        self.drop = nn.Dropout(dropout)
        self.out = nn.Linear(hidden, dim)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, obs: torch.Tensor, n_pred: int) -> torch.Tensor:
        """obs (B,T,D) -> (B,n_pred,D)."""
        _, h = self.encoder(obs[:, :-1])
        h = h[0]
        x = obs[:, -1]
        outs = []
        for _ in range(n_pred):
            h = self.decoder(x, h)
            x = x + self.out(self.drop(h))
            outs.append(x)
        return torch.stack(outs, 1)

    def sample(self, obs: torch.Tensor, n_pred: int, n_samples: int = 1, **_) -> torch.Tensor:
        y = self.forward(obs, n_pred)
        return y[:, None].expand(-1, n_samples, -1, -1).clone()
