"""Helpers for the Pose2Sim benchmarks: reading Pose2Sim's triangulated markers (``pose-3d/*.trc``).

Pose2Sim writes TRC y-up (``zup2yup``: TRC (X, Y, Z) = world (y, z, x)); ``trc_to_world`` undoes that.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from roomcap.keypoints.skeletons import CANONICAL

TRC_TO_BODY19 = {
    "RHip": "right_hip",
    "RKnee": "right_knee",
    "RAnkle": "right_ankle",
    "LHip": "left_hip",
    "LKnee": "left_knee",
    "LAnkle": "left_ankle",
    "Nose": "nose",
    "RShoulder": "right_shoulder",
    "RElbow": "right_elbow",
    "RWrist": "right_wrist",
    "LShoulder": "left_shoulder",
    "LElbow": "left_elbow",
    "LWrist": "left_wrist",
}


def read_trc(path: Path) -> tuple[list[str], np.ndarray]:
    """-> (marker names, (T,M,3) in TRC axes; NaN where a value is empty)."""
    lines = path.read_text().splitlines()
    names = [n for n in lines[3].split("\t")[2:] if n]
    rows = [ln.split("\t") for ln in lines[5:] if ln.strip()]
    T = len(rows)
    out = np.full((T, len(names), 3), np.nan)
    for t, r in enumerate(rows):
        vals = [float(v) if v not in ("", "nan", "NaN") else np.nan for v in r[2 : 2 + 3 * len(names)]]
        vals += [np.nan] * (3 * len(names) - len(vals))
        out[t] = np.asarray(vals).reshape(len(names), 3)
    return names, out


def trc_to_world(xyz: np.ndarray) -> np.ndarray:
    """Pose2Sim zup2yup inverse: TRC (X, Y, Z) = world (y, z, x)."""
    return np.stack([xyz[..., 2], xyz[..., 0], xyz[..., 1]], -1)


def read_trc_body19(path: Path) -> np.ndarray:
    """Pose2Sim TRC -> (T,19,3) world metres in body19 order, NaN for joints the TRC lacks."""
    names, xyz = read_trc(path)
    world = trc_to_world(xyz)
    out = np.full((len(xyz), CANONICAL.n_joints, 3), np.nan)
    for i, n in enumerate(names):
        if n in TRC_TO_BODY19:
            out[:, CANONICAL.index(TRC_TO_BODY19[n])] = world[:, i]
    return out
