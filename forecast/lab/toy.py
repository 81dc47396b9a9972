"""A toy walker on body19 (no mocap needed): for tests, examples and smoke runs.

Limbs swing sinusoidally with a gait period, the root moves along a heading; z up, metres.
"""

from __future__ import annotations

import numpy as np

from roomcap.keypoints.skeletons import get_skeleton

# rest pose, person facing +y (right hip towards +x), metres
_REST = {
    "nose": (0, 0.08, 1.62),
    "left_eye": (-0.03, 0.06, 1.66),
    "right_eye": (0.03, 0.06, 1.66),
    "left_ear": (-0.07, 0.0, 1.63),
    "right_ear": (0.07, 0.0, 1.63),
    "left_shoulder": (-0.18, 0, 1.42),
    "right_shoulder": (0.18, 0, 1.42),
    "left_elbow": (-0.2, 0, 1.12),
    "right_elbow": (0.2, 0, 1.12),
    "left_wrist": (-0.21, 0, 0.85),
    "right_wrist": (0.21, 0, 0.85),
    "left_hip": (-0.1, 0, 0.92),
    "right_hip": (0.1, 0, 0.92),
    "left_knee": (-0.1, 0, 0.5),
    "right_knee": (0.1, 0, 0.5),
    "left_ankle": (-0.1, 0, 0.08),
    "right_ankle": (0.1, 0, 0.08),
    "pelvis": (0, 0, 0.92),
    "neck": (0, 0, 1.42),
}
_SWING = {
    "left_wrist": 0.25,
    "right_wrist": -0.25,
    "left_elbow": 0.1,
    "right_elbow": -0.1,
    "left_knee": -0.15,
    "right_knee": 0.15,
    "left_ankle": -0.3,
    "right_ankle": 0.3,
}


def walker(
    n_frames: int,
    fps: float = 25.0,
    *,
    speed_mps: float = 1.2,
    period_s: float = 1.0,
    heading_rad: float = 0.0,
    start=(0.0, 0.0),
    phase: float = 0.0,
    turn_rps: float = 0.0,
    sway_rad: float = 0.0,
) -> np.ndarray:
    """(T,19,3) toy walking motion. ``sway_rad``: the hips and the shoulders turn about the vertical body axis
    against each other with the gait (amplitude in radians); 0 keeps the torso rigid, so that relative to its
    root only the limbs move."""
    names = get_skeleton("body19").joint_names
    rest = np.array([_REST[n] for n in names], np.float64)
    t = np.arange(n_frames) / fps
    w = 2 * np.pi * t / period_s + phase
    local = np.repeat(rest[None], n_frames, 0)
    for n, a in _SWING.items():
        local[:, names.index(n), 1] += a * np.sin(w)
    local[:, :, 2] += 0.02 * np.cos(2 * w)[:, None]
    for group, sign in (("hip", 1.0), ("shoulder", -1.0)):
        ang = sign * sway_rad * np.sin(w)
        for side in ("left", "right"):
            j = names.index(f"{side}_{group}")
            x0, y0 = local[:, j, 0].copy(), local[:, j, 1].copy()
            local[:, j, 0] = np.cos(ang) * x0 - np.sin(ang) * y0
            local[:, j, 1] = np.sin(ang) * x0 + np.cos(ang) * y0
    head = heading_rad + turn_rps * t
    step = speed_mps / fps * np.stack([-np.sin(head), np.cos(head)], -1)  # facing +y rotated by heading
    pos = np.asarray(start, np.float64) + np.cumsum(step, 0) - step[0]
    c, s = np.cos(head), np.sin(head)
    x = c[:, None] * local[..., 0] - s[:, None] * local[..., 1] + pos[:, None, 0]
    y = s[:, None] * local[..., 0] + c[:, None] * local[..., 1] + pos[:, None, 1]
    return np.stack([x, y, local[..., 2]], -1).astype(np.float32)
