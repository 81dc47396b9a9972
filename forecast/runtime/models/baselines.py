"""Baselines: zero velocity, constant velocity, the rigidly sliding last pose, and the clustered-static-poses
'fool' (sec. 6.4.4)."""

from __future__ import annotations

import torch
from torch import nn


class ZeroVelocity(nn.Module):
    """Repeat the last observed pose."""

    kind = "zero_velocity"
    stochastic = False

    def sample(self, obs: torch.Tensor, n_pred: int, n_samples: int = 1, **_) -> torch.Tensor:
        """obs (B,T,D) -> (B,S,n_pred,D)."""
        last = obs[:, -1]
        return last[:, None, None].expand(-1, n_samples, n_pred, -1).clone()


class ConstantVelocity(nn.Module):
    """Extrapolate the last observed velocity (mean over ``n_vel`` frames)."""

    kind = "constant_velocity"
    stochastic = False

    def __init__(self, n_vel: int = 1):
        super().__init__()
        self.n_vel = n_vel

    def sample(self, obs: torch.Tensor, n_pred: int, n_samples: int = 1, **_) -> torch.Tensor:
        v = (obs[:, -1] - obs[:, -1 - self.n_vel]) / self.n_vel
        steps = torch.arange(1, n_pred + 1, dtype=obs.dtype, device=obs.device)
        out = obs[:, -1, None] + steps[None, :, None] * v[:, None]
        return out[:, None].expand(-1, n_samples, -1, -1).clone()


class SlideLastPose(nn.Module):
    """The last observed pose carried rigidly along the last observed root velocity on the floor (xy; z up):
    a control for NDMS, which rewards coherent translation of every joint; it is no plausible motion."""

    kind = "slide"
    stochastic = False

    def __init__(self, lhip: int = 11, rhip: int = 12):  # body19 hips
        super().__init__()
        self.lhip, self.rhip = lhip, rhip

    def sample(self, obs: torch.Tensor, n_pred: int, n_samples: int = 1, **_) -> torch.Tensor:
        B, D = obs.shape[0], obs.shape[-1]
        p = obs[:, -2:].reshape(B, 2, D // 3, 3)
        root = 0.5 * (p[:, :, self.lhip] + p[:, :, self.rhip])  # (B,2,3)
        v = root[:, 1] - root[:, 0]
        v = torch.cat([v[:, :2], torch.zeros_like(v[:, 2:])], 1)  # along the floor
        steps = torch.arange(1, n_pred + 1, dtype=obs.dtype, device=obs.device)
        out = p[:, 1, None] + steps[None, :, None, None] * v[:, None, None]  # (B,H,J,3)
        return out.reshape(B, n_pred, D)[:, None].expand(-1, n_samples, -1, -1).clone()


class FoolClusters(nn.Module):
    """The 'fool' (sec. 6.4.4): S-2 static cluster-mean poses of the training data (independent of the
    observation, hence high diversity) plus the last observed pose twice. Poses are hip-centric,
    so they are placed at the last observed root. Shows that best-of-S ADE/FDE reward this while NDMS
    does not."""

    kind = "fool"
    stochastic = True

    def __init__(self, centers: torch.Tensor):
        super().__init__()
        self.register_buffer("centers", torch.as_tensor(centers, dtype=torch.float32))  # (K,D) hip-centric

    def sample(self, obs: torch.Tensor, n_pred: int, n_samples: int = 50, **_) -> torch.Tensor:
        B, D = obs.shape[0], obs.shape[-1]
        last = obs[:, -1]
        root = last.view(B, -1, 3)[:, [11, 12]].mean(1)  # body19 hips 11, 12
        K = self.centers.shape[0]
        idx = torch.arange(max(n_samples - 2, 0), device=obs.device) % K
        c = self.centers[idx].view(1, -1, D // 3, 3) + root[:, None, None]
        poses = torch.cat([last[:, None].expand(-1, min(2, n_samples), -1), c.view(B, -1, D)], 1)[
            :, :n_samples
        ]
        return poses[:, :, None].expand(-1, -1, n_pred, -1).clone()
