"""Hip-centred, facing-normalised pose frames (seed ch. 5.2.1, eq. 5.2–5.5). numpy only.

Before forecasting, every pose sample is moved so that its hip centre (pelvis)
sits at the origin and rotated about z (z up) so that the vector from the left
to the right hip points along +x (the code's convention, CONTRACTS.md; the
thesis text says "y"). After forecasting the inverse transform restores world
coordinates.

    x_hat_j = R (x_j - x_hip)                         (5.2)
    R = [[cos t, sin t, 0], [-sin t, cos t, 0], [0, 0, 1]]   (5.3)
    t = atan2(y_rhip - y_lhip, x_rhip - x_lhip)       (5.4)
    x_j = R^T x_hat_j + x_hip                         (5.5)
"""

from __future__ import annotations

import numpy as np

from roomcap.keypoints.skeletons import CANONICAL, Skeleton


def hip_indices(skeleton: Skeleton = CANONICAL) -> tuple[int, int, int]:
    """(pelvis, left_hip, right_hip) joint indices of ``skeleton``."""
    return skeleton.index("pelvis"), skeleton.index("left_hip"), skeleton.index("right_hip")


def hip_frame(x: np.ndarray, skeleton: Skeleton = CANONICAL) -> tuple[np.ndarray, np.ndarray]:
    """Origin and facing angle of poses. x: (...,J,3) -> origin (...,3), theta (...,) (eq. 5.4).

    The origin is the pelvis joint (mid-hips where the pelvis is NaN); a pose
    whose hips are unknown gets theta = 0.
    """
    x = np.asarray(x)
    if x.ndim < 2 or x.shape[-2:] != (skeleton.n_joints, 3):
        raise ValueError(f"poses must have shape (...,{skeleton.n_joints},3), got {x.shape}")
    ip, il, ir = hip_indices(skeleton)
    origin = x[..., ip, :]
    mid = 0.5 * (x[..., il, :] + x[..., ir, :])
    origin = np.where(np.isfinite(origin), origin, mid)
    d = x[..., ir, :] - x[..., il, :]
    theta = np.arctan2(d[..., 1], d[..., 0])
    theta = np.where(np.isfinite(theta), theta, 0.0)
    return origin, theta


def _rot(v: np.ndarray, theta: np.ndarray, sign: float) -> np.ndarray:
    """R(theta) v (sign=+1) or R(theta)^T v (sign=-1) for v (...,J,3), theta (...,), without matrices."""
    c = np.cos(theta).astype(v.dtype, copy=False)[..., None]
    s = (sign * np.sin(theta)).astype(v.dtype, copy=False)[..., None]
    out = np.empty_like(v)
    out[..., 0] = c * v[..., 0] + s * v[..., 1]
    out[..., 1] = c * v[..., 1] - s * v[..., 0]
    out[..., 2] = v[..., 2]
    return out


def normalize(x: np.ndarray, origin: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Eq. 5.2. x: (...,J,3), origin: (...,3), theta: (...,) -> (...,J,3)."""
    return _rot(x - origin[..., None, :].astype(x.dtype, copy=False), theta, 1.0)


def denormalize(x_hat: np.ndarray, origin: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Eq. 5.5, the inverse of :func:`normalize`."""
    return _rot(x_hat, theta, -1.0) + origin[..., None, :].astype(x_hat.dtype, copy=False)


def rotate_vectors(v: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Apply R(theta) of eq. 5.3 to vectors (no translation). v: (...,J,3), theta: (...,)."""
    return _rot(v, theta, 1.0)


def unrotate_vectors(v: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Apply R(theta)^T to vectors (no translation)."""
    return _rot(v, theta, -1.0)
