"""Normalisation (Tanke eq. 3.5-3.8) and clips: what forecasting a track needs from the data side.

A *clip* is ``xyz_m (T,P,J,3)`` world metres, z up, NaN where unknown, at ``fps``, in a named skeleton
(``body19`` by default); a track file (``track.trackfile``) reads as one. Normalisation follows the code's
version (CONTRACTS.md): root = mid-hips, the hip vector (left_hip -> right_hip) is rotated onto +x about z
(z up). The datasets, windows and adapters are :mod:`roomcap.forecast.lab.data`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError, InputError
from roomcap.keypoints.skeletons import get_skeleton
from roomcap.track.trackfile import TrackFile  # the contract with the tracker

LHIP, RHIP = 11, 12  # body19
TARGET_FPS = 25.0  # the seed's rate for forecasting (ch. 6-8)


# ----------------------------------------------------------------------------- normalisation (eq. 3.5-3.8)


def hip_indices(joint_names: tuple[str, ...] | list[str]) -> tuple[int, int]:
    names = list(joint_names)
    try:
        return names.index("left_hip"), names.index("right_hip")
    except ValueError:
        raise InputError(f"normalisation needs 'left_hip' and 'right_hip'; joints are {names}") from None


def norm_frame(pose: np.ndarray, lhip: int, rhip: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (...,3,3) and root (...,3) of eq. 3.5/3.6 for pose (...,J,3).

    R maps world into the canonical frame: root at the origin, hip vector (left->right) on +x, z up.
    """
    root = 0.5 * (pose[..., lhip, :] + pose[..., rhip, :])
    d = pose[..., rhip, :] - pose[..., lhip, :]
    theta = np.arctan2(d[..., 1], d[..., 0])
    c, s = np.cos(theta), np.sin(theta)
    z, o = np.zeros_like(c), np.ones_like(c)
    R = np.stack([np.stack([c, s, z], -1), np.stack([-s, c, z], -1), np.stack([z, z, o], -1)], -2)
    return R, root


def normalize(seq: np.ndarray, R: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Eq. 3.8: R (x - root) for seq (...,T,J,3) with R (...,3,3), root (...,3)."""
    return np.einsum("...ij,...tkj->...tki", R, seq - root[..., None, None, :])


def denormalize(seq: np.ndarray, R: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Eq. 3.7, the inverse: R^T y + root."""
    return np.einsum("...ji,...tkj->...tki", R, seq) + root[..., None, None, :]


@dataclass(frozen=True)
class Clip:
    """One recording: ``xyz_m (T,P,J,3)`` (NaN = unknown) at ``fps`` in ``skeleton``."""

    name: str
    xyz_m: np.ndarray
    fps: float
    skeleton: str = "body19"

    def __post_init__(self) -> None:
        x = np.asarray(self.xyz_m, dtype=np.float32)
        if x.ndim == 3:
            x = x[:, None]
        J = get_skeleton(self.skeleton).n_joints
        if x.ndim != 4 or x.shape[2:] != (J, 3):
            raise InputError(
                f"clip '{self.name}': xyz_m must be (T,P,{J},3) for '{self.skeleton}', got {x.shape}"
            )
        object.__setattr__(self, "xyz_m", x)

    @property
    def n_frames(self) -> int:
        return self.xyz_m.shape[0]

    def resampled(self, fps: float) -> Clip:
        """Linear resampling to ``fps`` (NaN stays NaN where either neighbour is NaN)."""
        if abs(fps - self.fps) < 1e-6:
            return self
        T = self.n_frames
        t_new = np.arange(0, (T - 1) / self.fps + 1e-9, 1.0 / fps)
        pos = t_new * self.fps
        i0 = np.clip(np.floor(pos).astype(int), 0, T - 1)
        i1 = np.clip(i0 + 1, 0, T - 1)
        w = (pos - i0)[:, None, None, None].astype(np.float32)
        x = (1 - w) * self.xyz_m[i0] + w * self.xyz_m[i1]
        return Clip(self.name, x, fps, self.skeleton)


def clip_from_trackfile(path: str | os.PathLike) -> Clip:
    """A track file (``tracks/1``) as a clip; raises ``FormatError``/``SchemaError`` for bad files."""
    tf = TrackFile.load(path)
    sk = _skeleton_for(tf.joint_names, path)
    return Clip(clip_name(path), tf.xyz_m, tf.fps, sk)


def clip_name(path: str | os.PathLike) -> str:
    """A track file's clip name: the session for ``<session>/track/tracks.npz``, the folder for
    ``<folder>/tracks.npz``, the file stem otherwise."""
    p = Path(path)
    if p.stem != "tracks":
        return p.stem
    return p.parent.parent.name if p.parent.name == "track" else p.parent.name


def _skeleton_for(joint_names: tuple[str, ...], path) -> str:
    for sid in ("body19", "smpl29"):
        if tuple(get_skeleton(sid).joint_names) == tuple(joint_names):
            return sid
    raise FormatError(
        path,
        "joint_names",
        f"joints {list(joint_names)} match no forecasting skeleton (body19, smpl29).",
        "Convert the track file to body19 (keypoints.skeletons.convert).",
    )


def fill(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Fill unknown frames per (person, joint) with the last known value, before the first with the first."""
    T = x.shape[0]
    idx = np.where(m, np.arange(T)[:, None, None], -1)
    idx = np.maximum.accumulate(idx, axis=0)
    first = np.argmax(m, axis=0)  # first known frame (0 if none)
    idx = np.where(idx < 0, first[None], idx)
    out = np.take_along_axis(x, idx[..., None], axis=0)
    return np.where(np.isfinite(out), out, 0.0).astype(np.float32)
