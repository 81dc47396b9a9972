"""Small multi-view geometry helpers on plain arrays (no Camera class needed).

Everything here works on *undistorted* pixels and projection matrices
``P = K [R | t]`` with ``cam_from_world`` extrinsics (seed sec. 3.2.1, eq. 3.12).
"""

from __future__ import annotations

import numpy as np


def check_shape(name: str, arr: np.ndarray, shape: tuple[int | None, ...]) -> None:
    """Raise ValueError unless ``arr.shape`` matches ``shape`` (None = any size).

    >>> check_shape("P", np.zeros((4, 3, 4)), (None, 3, 4))
    >>> check_shape("P", np.zeros((3, 4)), (None, 3, 4))
    Traceback (most recent call last):
    ValueError: P: expected shape (*, 3, 4), got (3, 4).
    """
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape, strict=False))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(arr.shape)}.")


def camera_centers(P: np.ndarray) -> np.ndarray:
    """Camera centres (C,3) from projection matrices P (C,3,4): the right null vector of P (eq. 3.14).

    >>> K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    >>> P = np.stack([K @ np.hstack([np.eye(3), [[dx], [0], [2]]]) for dx in (0.0, -0.5)])
    >>> camera_centers(P) + 0.0
    array([[ 0. ,  0. , -2. ],
           [ 0.5,  0. , -2. ]])
    """
    P = np.asarray(P, dtype=np.float64)
    check_shape("P", P, (None, 3, 4))
    M, p4 = P[:, :, :3], P[:, :, 3]
    return -np.linalg.solve(M, p4[..., None])[..., 0]


def _skew(v: np.ndarray) -> np.ndarray:
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def fundamental_from_P(P: np.ndarray) -> np.ndarray:
    """All pairwise fundamental matrices F (C,C,3,3) with ``x_j^T F[i,j] x_i = 0`` (eq. 3.15).

    ``F[i,j] = [e_j]_x P_j P_i^+`` with ``e_j = P_j C_i``; the diagonal is zero. Each F is
    scaled to unit Frobenius norm (the epipolar distance below normalises lines anyway).

    >>> K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    >>> P = np.stack([K @ np.hstack([np.eye(3), [[dx], [0], [2]]]) for dx in (0.0, -0.5)])
    >>> x = np.concatenate([project(P, np.array([[0.1, -0.2, 0.3]]))[:, 0], np.ones((2, 1))], 1)
    >>> abs(float(x[1] @ fundamental_from_P(P)[0, 1] @ x[0])) < 1e-9
    True
    """
    P = np.asarray(P, dtype=np.float64)
    check_shape("P", P, (None, 3, 4))
    C = len(P)
    centers = np.concatenate([camera_centers(P), np.ones((C, 1))], 1)  # (C,4)
    pinv = np.linalg.pinv(P)  # (C,4,3)
    e = np.einsum("jab,ib->ija", P, centers)  # e[i,j] = P_j C_i, (C,C,3)
    F = np.einsum("ijab,jbc,icd->ijad", _skew(e), P, pinv)
    n = np.linalg.norm(F, axis=(-2, -1), keepdims=True)
    F = np.where(n > 0, F / np.where(n > 0, n, 1.0), 0.0)
    F[np.arange(C), np.arange(C)] = 0.0
    return F


def project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Project X (N,3) with P (C,3,4) to undistorted pixels (C,N,2); NaN passes through.

    >>> K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    >>> P = np.stack([K @ np.hstack([np.eye(3), [[dx], [0], [2]]]) for dx in (0.0, -0.5)])
    >>> project(P, np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]]))
    array([[[320., 240.],
            [ nan,  nan]],
    <BLANKLINE>
           [[195., 240.],
            [ nan,  nan]]])
    """
    X = np.asarray(X, dtype=np.float64)
    check_shape("X", X, (None, 3))
    p = np.einsum("cab,nb->cna", P[:, :, :3], X) + P[:, None, :, 3]
    return p[..., :2] / p[..., 2:3]
