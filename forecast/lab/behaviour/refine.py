"""Pose refinement after decoding: a named variant BEYOND ch. 4, taken from the seed's own ch. 3.

Diller ch. 3 (sec. "Pose Refinement", eq. 3.2) refines each predicted characteristic pose ``x`` by minimising

    E_R = w_e |x_e - e|_2 + w_b |bonelengths(x) - b|_1 + w_a |angles(x) - theta|_1 + w_c |x - x_0|_1
          + w_h sum_i (1 - H_i)

with ``b`` and ``theta`` the bone lengths and joint angles of the initially observed skeleton and ``x_0`` the
last input skeleton (w_e 0.2, w_b 1, w_a 0.4, w_c 0.1, w_h 0.1). Ch. 4's forecaster has no end-effector
samples and no heatmaps (the ``w_e`` and ``w_h`` terms drop) and observes 2D only, so what stands in here:

- ``b``: the person's skeleton as the forecast reads it, the bone lengths of its FIRST forecast step (the
  step next to the observation, whose bones are nearly the database's: later steps shrink as the forecast
  grows uncertain) with each left and right bone given their mean (a person's skeleton is symmetric; the
  seed's observed skeletons are mocap skeletons, symmetric to the millimetre) -- ``bones="first"``; or
  the 3D database's mean proportions scaled to the first step's size -- ``bones="database"``; or the
  database's mean skeleton as it is -- ``bones="database_mean"``;
- ``theta``: the joint angles (between each bone and its parent bone, and between two bones leaving one
  joint) of that first step -- ``angles="first"``; or only the angles that a skeleton holds whatever the pose
  (the hips in line through the pelvis, the shoulders through the neck, the face), found as those that do not
  vary over the 3D database's poses, at the database's value -- ``angles="rigid"`` (a forecast five steps out
  has other joint angles than the first step, but the same skeleton);
- ``x_0``: the decoder's raw pose itself (keeps the refined pose where the forecast put it).

Each forecast pose of every step is refined alike (Adam on the joints, the L1 terms summed as eq. 3.2 writes
them, the learning rate decaying linearly to 0 as ``forecast.lab.characteristic.network.refine_pose``, ch. 3's
refinement with its heatmap and end-effector terms, which ch. 4's forecaster lacks).
The protocol's figures stay those of the raw poses; ``forecast behaviour eval --refine`` adds the refined
ones beside them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from roomcap.core.config import config_from_dict as _config_from_dict
from roomcap.forecast.lab.behaviour.data import JOINTS
from roomcap.forecast.lab.behaviour.model import bones

BONE_SOURCES = ("first", "database", "database_mean")
ANGLE_SOURCES = ("first", "rigid")


@dataclass(frozen=True)
class RefineConfig:
    """Eq. 3.2's weights (the seed's values), the sources of ``b`` and ``theta`` and the optimiser's settings.
    The defaults are the choice on the validation split (``bench_forecast_behaviour_refine``): of the
    sources that keep the person's size, database proportions and the rigid angles gave the highest quality
    at the least 2D cost on both scripts."""

    w_b: float = 1.0  # bone lengths
    w_a: float = 0.4  # joint angles
    w_c: float = 0.1  # closeness to the raw pose
    bones: str = "database"  # first | database | database_mean: where ``b`` comes from (module docstring)
    angles: str = "rigid"  # first | rigid: where ``theta`` comes from and which angles it holds (docstring)
    rigid_deg: float = 1.0  # rigid: the angles whose spread over the database's poses is below this (deg)
    iters: int = 300
    lr: float = 0.005  # metres per Adam step at the start, decaying linearly to 0 (as ch. 3's refinement)

    def __post_init__(self) -> None:
        if self.bones not in BONE_SOURCES:
            raise ValueError(f"refine bones must be one of {BONE_SOURCES}, got {self.bones!r}")
        if self.angles not in ANGLE_SOURCES:
            raise ValueError(f"refine angles must be one of {ANGLE_SOURCES}, got {self.angles!r}")
        if min(self.w_b, self.w_a, self.w_c) < 0 or self.iters < 1 or self.lr <= 0:
            raise ValueError("refine: weights must be >= 0, iters >= 1 and lr > 0")


def refine_config_from_dict(d: dict) -> RefineConfig:
    return _config_from_dict(RefineConfig, d, "refine config")


def angle_pairs(bone_idx: np.ndarray) -> np.ndarray:
    """(a,2) index pairs into ``bone_idx``'s rows, the joint angles of eq. 3.2: each bone with its parent
    bone, then each two bones leaving one joint (the hips at the pelvis, the shoulders at the neck)."""
    child_of = {int(c): i for i, (c, _) in enumerate(bone_idx)}
    out = [(i, child_of[int(p)]) for i, (_, p) in enumerate(bone_idx) if int(p) in child_of]
    n = len(bone_idx)
    out += [(i, j) for i in range(n) for j in range(i + 1, n) if bone_idx[i, 1] == bone_idx[j, 1]]
    return np.asarray(out, np.int64).reshape(-1, 2)


def _lengths(X: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (X[..., b[:, 0], :] - X[..., b[:, 1], :]).norm(dim=-1)


def _angles(X: torch.Tensor, b: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    v = X[..., b[:, 0], :] - X[..., b[:, 1], :]
    u, w = v[..., pairs[:, 0], :], v[..., pairs[:, 1], :]
    cr = torch.linalg.cross(u, w)
    return torch.atan2(((cr * cr).sum(-1) + 1e-12).sqrt(), (u * w).sum(-1))  # no NaN gradient at 0


def symmetric(lengths: np.ndarray, bone_idx: np.ndarray, names) -> np.ndarray:
    """Bone lengths (...,b) with each left bone and its right twin set to their mean."""
    key = [
        names[c].replace("left_", "").replace("right_", "")
        + "|"
        + names[p].replace("left_", "").replace("right_", "")
        for c, p in bone_idx
    ]
    out = lengths.copy()
    for k in set(key):
        idx = [i for i, kk in enumerate(key) if kk == k]
        if len(idx) > 1:
            out[..., idx] = lengths[..., idx].mean(-1, keepdims=True)
    return out


def reference_bones(P: np.ndarray, names, cfg: RefineConfig, db: np.ndarray | None = None) -> np.ndarray:
    """``b`` of eq. 3.2 per sequence (S,b) from forecasts P (S,m,J,3) (``cfg.bones``; ``database`` needs
    the database poses ``db`` (N,19,3))."""
    b = bones(tuple(names))
    first = np.linalg.norm(P[:, 0, b[:, 0]] - P[:, 0, b[:, 1]], axis=-1)  # (S,b)
    if cfg.bones == "first":
        return symmetric(first, b, names)
    if db is None:
        raise ValueError("refine bones='database' needs the database poses")
    jidx = [JOINTS.index(n) for n in names]
    D = db[:, jidx]
    mean_db = np.linalg.norm(D[:, b[:, 0]] - D[:, b[:, 1]], axis=-1).mean(0)  # (b,)
    if cfg.bones == "database_mean":
        return np.repeat(mean_db[None], len(P), 0)
    size = first.sum(1, keepdims=True) / mean_db.sum()
    return size * mean_db[None]


def reference_angles(
    P: np.ndarray, names, cfg: RefineConfig, db: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``theta`` of eq. 3.2 and the angles it holds: (pairs (a,2) into ``bones(names)``, theta (S or 1, a)
    radians). ``first``: every angle at the first forecast step's value; ``rigid``: the angles a skeleton
    holds in every pose, those whose spread over the database's poses ``db`` is below ``cfg.rigid_deg``
    (the hips in line through the pelvis, the shoulders through the neck, the face), at their median."""
    b = torch.as_tensor(bones(tuple(names)))
    pairs = angle_pairs(b.numpy())
    if cfg.angles == "first":
        return pairs, _angles(
            torch.as_tensor(np.asarray(P[:, 0], np.float32)), b, torch.as_tensor(pairs)
        ).numpy()
    if db is None:
        raise ValueError("refine angles='rigid' needs the database poses")
    D = torch.as_tensor(np.asarray(db[:, [JOINTS.index(n) for n in names]], np.float32))
    A = _angles(D, b, torch.as_tensor(pairs)).numpy()
    keep = np.degrees(A.std(0)) < cfg.rigid_deg
    return pairs[keep], np.median(A[:, keep], 0)[None]


def refine(
    P: np.ndarray, names, cfg: RefineConfig = RefineConfig(), db: np.ndarray | None = None
) -> np.ndarray:
    """Eq. 3.2 (adapted as the module docstring says) on every forecast pose P (S,m,J,3) -> (S,m,J,3)."""
    names = tuple(names)
    b_np = bones(names)
    b = torch.as_tensor(b_np)
    X0 = torch.as_tensor(np.asarray(P, np.float32))
    ref_len = torch.as_tensor(reference_bones(np.asarray(P), names, cfg, db), dtype=torch.float32)[:, None]
    pairs_np, theta = reference_angles(np.asarray(P), names, cfg, db) if cfg.w_a > 0 else (None, None)
    if pairs_np is not None:
        pairs = torch.as_tensor(pairs_np)
        ref_ang = torch.as_tensor(theta, dtype=torch.float32)[:, None]  # (S or 1, 1, a)
    X = X0.clone().requires_grad_(True)
    opt = torch.optim.Adam([X], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 1 - i / cfg.iters)
    for _ in range(cfg.iters):
        e = cfg.w_b * (_lengths(X, b) - ref_len).abs().sum(-1) + cfg.w_c * (X - X0).abs().sum((-1, -2))
        if pairs_np is not None:
            e = e + cfg.w_a * (_angles(X, b, pairs) - ref_ang).abs().sum(-1)
        opt.zero_grad()
        e.sum().backward()
        opt.step()
        sched.step()
    return X.detach().numpy()
