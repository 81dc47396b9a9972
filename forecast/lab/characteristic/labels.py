"""Characteristic-pose labels (sec. 3.6, Fig. 3.2) and the samples built from them (sec. 3.6); the rules are
in the package docstring (:mod:`roomcap.forecast.lab.characteristic`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks

from roomcap.core.errors import InputError
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab.clips import mirror
from roomcap.keypoints.skeletons import get_skeleton

END_EFFECTORS = ("left_wrist", "right_wrist", "left_ankle", "right_ankle")


@dataclass(frozen=True)
class AnnotatorConfig:
    smooth_s: float = 0.08  # Gaussian smoothing of effector tracks (sigma, seconds)
    prominence_m: float = 0.15  # articulation must rise this much above the valleys on both sides
    window_s: float = 1.0  # how far to look for those valleys and for the approach speed
    cusp_speed_ratio: float = 0.5  # speed at the label <= ratio * peak speed within +-window (a cusp)
    min_sep_s: float = 0.8  # labels at least this far apart


def _smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return x
    return gaussian_filter1d(x, sigma, axis=0, mode="nearest")


def articulation(xyz: np.ndarray, joint_names, fps: float, cfg: AnnotatorConfig = AnnotatorConfig()):
    """Articulation A(t) (m) and effector speed v(t) (m/s) of one person's clip xyz (T,J,3), world metres."""
    names = list(joint_names)
    lh, rh = fdata.hip_indices(names)
    eff = [names.index(n) for n in END_EFFECTORS]
    x = np.asarray(xyz, np.float64)
    if x.ndim != 3 or x.shape[1:] != (len(names), 3):
        raise InputError(f"annotate: expected xyz (T,{len(names)},3), got {x.shape}")
    R, root = fdata.norm_frame(x, lh, rh)  # eq. 3.8 at every frame: the hip-centred body frame
    q = np.einsum("tij,tkj->tki", R, x[:, eff] - root[:, None])
    q = _smooth(q, cfg.smooth_s * fps)
    rest = np.median(q, axis=0)
    A = np.linalg.norm(q - rest, axis=-1).sum(-1)
    v = np.linalg.norm(np.gradient(q, axis=0), axis=-1).sum(-1) * fps
    return A, v


def annotate(
    xyz: np.ndarray, joint_names, fps: float, cfg: AnnotatorConfig = AnnotatorConfig()
) -> np.ndarray:
    """Characteristic frames (sorted int array) of one person's clip xyz (T,J,3) (rule in the module
    docstring)."""
    x = np.asarray(xyz, np.float64)
    if not np.isfinite(x).all():
        raise InputError("annotate: xyz has NaN/inf; fill or cut the gaps first")
    A, v = articulation(x, joint_names, fps, cfg)
    T = len(A)
    w = max(1, int(round(cfg.window_s * fps)))
    # prominence within +-window on both sides: find_peaks' prominence uses the higher of the two valleys
    peaks, props = find_peaks(A, prominence=cfg.prominence_m, wlen=2 * w + 1)
    keep = []
    for p, prom in zip(peaks, props["prominences"], strict=True):
        lo, hi = max(0, p - w), min(T, p + w + 1)
        if v[p] <= cfg.cusp_speed_ratio * v[lo:hi].max():
            keep.append((prom, int(p)))
    sep = cfg.min_sep_s * fps
    chosen: list[int] = []
    for _, p in sorted(keep, reverse=True):
        if all(abs(p - c) >= sep for c in chosen):
            chosen.append(p)
    return np.asarray(sorted(chosen), dtype=np.int64)


# ----------------------------------------------------------------------------- samples (sec. 3.6)


@dataclass(frozen=True)
class Labelled:
    """One person's clip ``x (T,J,3)`` world metres with its characteristic frames ``labels``."""

    name: str
    x: np.ndarray
    labels: np.ndarray


def label_clips(
    clips: list[fdata.Clip], cfg: AnnotatorConfig = AnnotatorConfig()
) -> tuple[list[Labelled], dict]:
    """Annotate every person of every clip; people with unknown joints (NaN) are skipped and counted."""
    out, skipped = [], {"person_with_missing_joints": 0}
    for c in clips:
        names = get_skeleton(c.skeleton).joint_names
        for p in range(c.xyz_m.shape[1]):
            x = c.xyz_m[:, p]
            if not np.isfinite(x).all():
                skipped["person_with_missing_joints"] += 1
                continue
            out.append(
                Labelled(
                    c.name if c.xyz_m.shape[1] == 1 else f"{c.name}/{p}", x, annotate(x, names, c.fps, cfg)
                )
            )
    return out, skipped


def segments(items: list[Labelled], n_obs: int) -> np.ndarray:
    """(S,3) rows (item, segment start, characteristic frame): the observation may start anywhere from the
    previous label (or the clip start) to ``n_obs`` frames before the label (sec. 3.6)."""
    rows = []
    for i, it in enumerate(items):
        prev = 0
        for c in it.labels.tolist():
            if c - n_obs >= prev:
                rows.append((i, prev, c))
            prev = c
    return np.asarray(rows, np.int64).reshape(-1, 3)


def eval_starts(segs: np.ndarray, n_obs: int, n_starts: int = 5) -> np.ndarray:
    """(W,4) rows (item, start, characteristic frame, start index 0..n_starts-1): ``n_starts`` observation
    starts evenly spread from the segment start to ``n_obs`` frames before the label (sec. 3.6, Fig. 3.9)."""
    rows = []
    for i, s0, c in segs.tolist():
        for k, s in enumerate(np.linspace(s0, c - n_obs, n_starts).round().astype(int).tolist()):
            rows.append((i, s, c, k))
    return np.asarray(rows, np.int64).reshape(-1, 4)


def make_pairs(
    items: list[Labelled], rows: np.ndarray, n_obs: int, joint_names
) -> tuple[np.ndarray, np.ndarray]:
    """rows (item, start, characteristic frame, ...) -> observations (B,N,J,3) normalised at their last frame
    (eq. 3.8) and targets (B,J,3): the characteristic pose rotated by the same rotation and centred at its
    own hips (hip-centred poses, sec. 3.6)."""
    lh, rh = fdata.hip_indices(joint_names)
    obs = np.stack([items[i].x[s : s + n_obs] for i, s in rows[:, :2].tolist()]).astype(np.float64)
    tgt = np.stack([items[i].x[c] for i, c in rows[:, [0, 2]].tolist()]).astype(np.float64)
    R, root = fdata.norm_frame(obs[:, -1], lh, rh)
    obs_n = fdata.normalize(obs, R, root)
    troot = 0.5 * (tgt[:, lh] + tgt[:, rh])
    tgt_n = fdata.normalize(tgt[:, None], R, troot)[:, 0]
    return obs_n.astype(np.float32), tgt_n.astype(np.float32)


def mirror_pairs(obs: np.ndarray, tgt: np.ndarray, flip) -> tuple[np.ndarray, np.ndarray]:
    """Left/right mirror of normalised pairs (``forecast.clips.mirror``): doubles the data, keeps eq. 3.8."""
    B, N, J, _ = obs.shape
    seq = np.concatenate([obs, tgt[:, None]], 1).reshape(B, N + 1, 3 * J)
    m, _ = mirror(seq, np.ones((B, N + 1, J), bool), np.asarray(flip))
    m = m.reshape(B, N + 1, J, 3)
    return m[:, :N], m[:, N]
