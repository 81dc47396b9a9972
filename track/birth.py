"""The learned birth generator g of seed sec. 5.2.3: a small network with dropout that fills missing joints.

A new track starts from a triangulated candidate pose with some joints missing. The generator takes the
candidate in its hip frame (eq. 5.2–5.5, :mod:`roomcap.track.normalize`) with a mask of the joints it has and
outputs a full pose; run N times with dropout kept on (plus Gaussian noise) it gives the N initial samples
of the track (instead of Gaussian noise around the candidate with template-filled joints). Joints the
candidate has keep their triangulated position plus ``sigma_obs_m`` noise; the generator's spread
fills the others.

This module imports torch (a learned module, like :mod:`roomcap.track.motion`). Train with
``python -m roomcap.track.train_birth --out track/checkpoints/birth_mlp.pt``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from roomcap.keypoints.skeletons import CANONICAL, Skeleton
from roomcap.track.motion import read_checkpoint, write_checkpoint
from roomcap.track.normalize import denormalize, hip_frame, normalize

CHECKPOINT_SCHEMA = "birth_mlp/1"
DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "birth_mlp.pt"


class BirthNet(nn.Module):
    """MLP [masked normalised pose (J*3), mask (J)] -> full normalised pose; dropout after each layer."""

    def __init__(self, n_joints: int, hidden: int, dropout: float):
        super().__init__()
        self.n_joints, self.hidden, self.dropout = n_joints, hidden, dropout
        self.l1 = nn.Linear(4 * n_joints, hidden)
        self.l2 = nn.Linear(hidden, hidden)
        self.out = nn.Linear(hidden, 3 * n_joints)

    def forward(self, x_hat: torch.Tensor, mask: torch.Tensor, mc: bool | None = None) -> torch.Tensor:
        """x_hat: (B,J,3) normalised (anything where masked), mask: (B,J) 1 = observed -> (B,J,3).
        ``mc``: dropout on (default: in training mode)."""
        on = self.training if mc is None else mc
        B = len(x_hat)
        inp = torch.cat([(x_hat * mask[..., None]).reshape(B, -1), mask], -1)
        h = nn.functional.dropout(torch.relu(self.l1(inp)), self.dropout, on)
        h = nn.functional.dropout(torch.relu(self.l2(h)), self.dropout, on)
        return self.out(h).reshape(B, self.n_joints, 3) + x_hat * mask[..., None]


def save_checkpoint(path: str | Path, model: BirthNet, skeleton: Skeleton, train_info: dict) -> None:
    write_checkpoint(path, CHECKPOINT_SCHEMA, model, skeleton, train_info)


def load_checkpoint(
    path: str | Path = DEFAULT_CHECKPOINT, skeleton: Skeleton = CANONICAL
) -> tuple[BirthNet, dict]:
    """Load a birth-generator checkpoint (weights_only=True) and check it matches ``skeleton``."""
    return read_checkpoint(
        path,
        CHECKPOINT_SCHEMA,
        skeleton,
        "birth",
        "python -m roomcap.track.train_birth --out track/checkpoints/birth_mlp.pt",
        "use birth = 'gaussian'",
        BirthNet,
    )


class BirthGenerator:
    """Samples of a new track from a candidate pose (sec. 5.2.3). Load with :meth:`load`."""

    def __init__(
        self,
        model: BirthNet,
        skeleton: Skeleton = CANONICAL,
        sigma_obs_m: float = 0.03,
        sigma_fill_m: float = 0.02,
    ):
        self.model = model.eval()
        self.skeleton = skeleton
        self.sigma_obs_m, self.sigma_fill_m = float(sigma_obs_m), float(sigma_fill_m)

    @classmethod
    def load(cls, path: str | Path = "", skeleton: Skeleton = CANONICAL, **kw) -> BirthGenerator:
        model, _ = load_checkpoint(path or DEFAULT_CHECKPOINT, skeleton)
        return cls(model, skeleton, **kw)

    def frame(self, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Hip frame (origin (3,), theta ()) of a candidate (J,3) with NaN joints; None without hips."""
        sk = self.skeleton
        ip, il, ir = sk.index("pelvis"), sk.index("left_hip"), sk.index("right_hip")
        ok = np.isfinite(cand).all(-1)
        if not ok[ip] and not (ok[il] and ok[ir]):
            return None
        origin, theta = hip_frame(cand[None], sk)
        if not (ok[il] and ok[ir]):  # facing from the shoulders (they are parallel to the hips), else 0
            ls, rs = sk.index("left_shoulder"), sk.index("right_shoulder")
            d = cand[rs] - cand[ls]
            theta = np.array([np.arctan2(d[1], d[0]) if np.isfinite(d).all() else 0.0])
        return origin[0], theta[0]

    def sample(self, cand: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray | None:
        """N samples (n,J,3) around candidate ``cand`` (J,3) (NaN = missing); sample 0 is the dropout-free
        prediction with the observed joints exact. None when the candidate has no hips."""
        fr = self.frame(cand)
        if fr is None:
            return None
        origin, theta = fr
        ok = np.isfinite(cand).all(-1)
        x_hat = normalize(np.nan_to_num(cand)[None], origin[None], np.atleast_1d(theta))[0].astype(np.float32)
        xb = torch.from_numpy(np.repeat(x_hat[None], n, 0))
        mb = torch.from_numpy(np.repeat(ok[None].astype(np.float32), n, 0))
        with torch.no_grad():
            out = self.model(xb, mb, mc=True).numpy()  # (n,J,3) MC dropout: the samples diverge
            out[0] = self.model(xb[:1], mb[:1], mc=False).numpy()[0]
        J = len(cand)
        sig = np.where(ok, self.sigma_obs_m, self.sigma_fill_m).astype(np.float32)
        noise = rng.standard_normal((n, J, 3)).astype(np.float32) * sig[:, None]
        noise[0] = 0.0
        out = denormalize(out, np.repeat(origin[None], n, 0), np.full(n, theta))
        out = np.where(ok[None, :, None], cand[None], out) + noise
        return out.astype(np.float32)
