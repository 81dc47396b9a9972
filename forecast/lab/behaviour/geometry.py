"""The camera geometry of the behaviour forecaster: the person's viewer frame, camera-independent 2D
features, and the differentiable projection of eq. 4.2.

The seed learns from one fixed kitchen camera and centres 2D poses at the neck. A room of cameras has many,
so the forecaster works in a frame that any camera gives:

- the **anchor** ``g (3,)``: the floor point under the person, from the 2D ankles' rays met with the
  plane at ankle height (or from the track's 3D at sample time);
- the **viewer frame** ``V (3,3)`` (rows: right, forward, up in world coordinates): world z up, forward the
  horizontal direction from the camera to the anchor;
- the **plane features** of a 2D pose: each joint's ray met with the vertical plane through the anchor,
  facing the camera, in metres (x right, z up, relative to the anchor). Near the person they are the
  pose's 2D shape at metric scale, whatever the camera's focal length, distance and height.

A 3D pose ``P (J,3)`` in the viewer frame (metres, relative to the anchor) goes to the world as
``P V + g`` and to pixels by eq. 4.2, ``x = K (R X + t)`` (undistorted pixels).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from roomcap.core.errors import InputError

ANKLE_HEIGHT_M = 0.08  # the ankle joint's height above the floor when standing


@dataclass(frozen=True)
class View:
    """Per sequence (S): ``K (S,3,3)``, ``R (S,3,3)``, ``t (S,3)`` cam_from_world; anchor ``g (S,3)``;
    viewer frame ``V (S,3,3)``; camera centre in the viewer frame ``c (S,3)``."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    g: np.ndarray
    V: np.ndarray
    c: np.ndarray

    def take(self, idx) -> View:
        return View(*(np.asarray(getattr(self, f))[idx] for f in ("K", "R", "t", "g", "V", "c")))

    def torch(self) -> dict[str, torch.Tensor]:
        return {
            f: torch.as_tensor(np.asarray(getattr(self, f)), dtype=torch.float32)
            for f in ("K", "R", "t", "g", "V", "c")
        }


def rays(K: np.ndarray, R: np.ndarray, t: np.ndarray, xy_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (S,3) and world ray directions (S,...,3) of undistorted pixels xy_px (S,...,2)."""
    S = len(K)
    flat = xy_px.reshape(S, -1, 2)
    h = np.concatenate([flat, np.ones(flat.shape[:2] + (1,))], -1)
    d_cam = np.einsum("sij,snj->sni", np.linalg.inv(K), h)
    d = np.einsum("sji,snj->sni", R, d_cam)  # R^T d_cam
    C = -np.einsum("sji,sj->si", R, t)
    return C, d.reshape(xy_px.shape[:-1] + (3,))


def anchor_from_2d(K, R, t, xy_px: np.ndarray, ankles: tuple[int, int]) -> np.ndarray:
    """Floor point (S,3) under each person from undistorted 2D poses xy_px (S,J,2): the mean of the
    ankles' rays met with the plane z = ANKLE_HEIGHT_M; NaN where no ankle is seen or the ray misses."""
    C, d = rays(K, R, t, xy_px[:, list(ankles)])
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (ANKLE_HEIGHT_M - C[:, None, 2]) / d[..., 2]
        P = C[:, None] + s[..., None] * d
    P[~(s > 0)] = np.nan
    n = np.isfinite(P[..., 0]).sum(1)
    g = np.where(
        n[:, None] > 0, np.nansum(np.nan_to_num(P, nan=0.0), axis=1) / np.maximum(n, 1)[:, None], np.nan
    )
    g[:, 2] = 0.0
    return g


def make_view(K, R, t, g) -> View:
    """The viewer frame of anchors g (S,3) seen by cameras K, R, t (S,...)."""
    K, R, t, g = (np.asarray(a, np.float64) for a in (K, R, t, g))
    if not np.isfinite(g).all():
        raise InputError("make_view: an anchor is NaN; give every person a floor point")
    C = -np.einsum("sji,sj->si", R, t)
    f = g - C
    f[:, 2] = 0.0
    n = np.linalg.norm(f, axis=1, keepdims=True)
    f = np.where(n > 1e-6, f / np.maximum(n, 1e-9), np.array([0.0, 1.0, 0.0]))
    up = np.broadcast_to(np.array([0.0, 0.0, 1.0]), f.shape)
    right = np.cross(f, up)
    V = np.stack([right, f, up], 1)
    c = np.einsum("sij,sj->si", V, C - g)
    return View(K, R, t, g, V, c)


ROOM_SCALE_M = 2.0  # room coordinates are given to the model divided by this


def room_context(V: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The person's place in the room for the context encoder (B,4): the anchor's floor position x, y (room
    frame, / ``ROOM_SCALE_M``) and the viewer frame's forward direction in the room (so a heading seen in
    the plane features can be turned into the room's). Both come from the 2D and the rig's calibration (the
    anchor) or from the track's 3D at sample time."""
    return torch.cat([g[:, :2] / ROOM_SCALE_M, V[:, 1, :2]], 1)


def plane_features(view: View, xy_px: np.ndarray) -> np.ndarray:
    """Undistorted 2D poses xy_px (S,L,J,2) (NaN = unseen) -> plane features (S,L,J,2) metres (x right,
    z up, relative to the anchor); NaN where unseen."""
    S = xy_px.shape[0]
    _, d = rays(view.K, view.R, view.t, xy_px.reshape(S, -1, 2))
    dv = np.einsum("sij,snj->sni", view.V, d)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = -view.c[:, None, 1] / dv[..., 1]
        P = view.c[:, None] + s[..., None] * dv
    P[~(s > 0)] = np.nan
    return P[..., [0, 2]].reshape(xy_px.shape).astype(np.float32)


def plane_of_3d(P: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Plane features (B,J,2) of 3D poses P (B,J,3) in the viewer frame, seen from camera centre c (B,3):
    the perspective of each joint onto the plane y = 0 (differentiable)."""
    cc = c[:, None]
    s = -cc[..., 1] / (P[..., 1] - cc[..., 1]).clamp(min=0.2)
    Q = cc + s[..., None] * (P - cc)
    return Q[..., [0, 2]]


def to_world(P: torch.Tensor, V: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Viewer-frame poses P (B,...,J,3) -> world metres (X = P V + g)."""
    shape = P.shape
    Pf = P.reshape(shape[0], -1, 3)
    return (torch.einsum("bnk,bkw->bnw", Pf, V) + g[:, None]).reshape(shape)


def project(X: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Eq. 4.2: world points X (B,...,3) -> undistorted pixels (B,...,2), x = K (R X + t)."""
    shape = X.shape
    Xf = X.reshape(shape[0], -1, 3)
    xc = torch.einsum("bij,bnj->bni", R, Xf) + t[:, None]
    uv = torch.einsum("bij,bnj->bni", K, xc)
    z = uv[..., 2:].clamp(min=1e-3)
    return (uv[..., :2] / z).reshape(shape[:-1] + (2,))
