"""Tiny hand-made fixtures for the triangulate tests: a ring of pinhole cameras and body19 people, and a
run killed after some of its chunk parts."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from roomcap.triangulate import chunks as C


@contextmanager
def killed_after_commits(monkeypatch, n: int, kind: str | None = None):
    """Inside, a streamed run is killed (``KeyboardInterrupt``) when it commits its part after the first
    ``n`` parts of ``kind`` (any kind: None); the real ``PartStore.commit`` is back on leaving."""
    real = C.PartStore.commit
    done = {"n": 0}

    def dying(self, i):
        if kind is None or self.kind == kind:
            if done["n"] == n:
                raise KeyboardInterrupt
            done["n"] += 1
        real(self, i)

    monkeypatch.setattr(C.PartStore, "commit", dying)
    try:
        yield
    finally:
        monkeypatch.setattr(C.PartStore, "commit", real)


# body19 (COCO-17 + pelvis + neck) standing template, metres, facing +x, z up, left = +y
TEMPLATE = np.array(
    [
        [0.08, 0.00, 1.62],
        [0.06, 0.03, 1.66],
        [0.06, -0.03, 1.66],
        [0.00, 0.07, 1.63],
        [0.00, -0.07, 1.63],
        [0.00, 0.18, 1.42],
        [0.00, -0.18, 1.42],
        [0.02, 0.21, 1.13],
        [0.02, -0.21, 1.13],
        [0.08, 0.21, 0.87],
        [0.08, -0.21, 0.87],
        [0.00, 0.10, 0.95],
        [0.00, -0.10, 0.95],
        [0.03, 0.10, 0.52],
        [0.03, -0.10, 0.52],
        [0.00, 0.10, 0.08],
        [0.00, -0.10, 0.08],
        [0.00, 0.00, 0.95],
        [0.00, 0.00, 1.42],
    ]
)


# whole-body joints beyond body19: offsets from the parent joint (metres, world z up) of a person facing +x
FOOT_HEAD_OFFSETS = {
    "left_big_toe": ("left_ankle", (0.16, 0.02, -0.07)),
    "left_small_toe": ("left_ankle", (0.13, 0.06, -0.07)),
    "left_heel": ("left_ankle", (-0.06, 0.0, -0.07)),
    "right_big_toe": ("right_ankle", (0.16, -0.02, -0.07)),
    "right_small_toe": ("right_ankle", (0.13, -0.06, -0.07)),
    "right_heel": ("right_ankle", (-0.06, 0.0, -0.07)),
    "upper_neck": ("neck", (0.0, 0.0, 0.10)),
    "head_top": ("neck", (0.0, 0.0, 0.30)),
}


def ring_P(
    n: int,
    radius: float = 4.0,
    f: float = 1000.0,
    wh=(1920, 1080),
    height: float = 2.5,
    jitter: float = 0.0,
    rng=None,
) -> np.ndarray:
    """(n,3,4) projection matrices of cameras on a circle looking at (0,0,1)."""
    Ps = []
    for i in range(n):
        a = 2 * np.pi * i / n + (0 if rng is None else rng.uniform(-jitter, jitter))
        c = np.array([radius * np.cos(a), radius * np.sin(a), height])
        fwd = np.array([0, 0, 1.0]) - c
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])
        K = np.array([[f, 0, wh[0] / 2], [0, f, wh[1] / 2], [0, 0, 1]])
        Ps.append(K @ np.c_[R, -R @ c])
    return np.asarray(Ps)


def people(rng, n: int, spread: float = 2.0, min_dist: float = 0.7) -> np.ndarray:
    """(n,19,3) people at random positions/headings, at least ``min_dist`` apart."""
    pos: list[np.ndarray] = []
    while len(pos) < n:
        p = rng.uniform(-spread, spread, 2)
        if all(np.linalg.norm(p - q) >= min_dist for q in pos):
            pos.append(p)
    out = []
    for p in pos:
        a = rng.uniform(0, 2 * np.pi)
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        out.append(TEMPLATE @ R.T + [p[0], p[1], 0])
    return np.asarray(out)


def project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """X (...,3) -> (C,...,2)."""
    sh = X.shape[:-1]
    Xf = X.reshape(-1, 3)
    p = np.einsum("cab,nb->cna", P[:, :, :3], Xf) + P[:, None, :, 3]
    return (p[..., :2] / p[..., 2:3]).reshape((len(P),) + sh + (2,))


def observe(rng, P, X, noise_px=2.0, shuffle=True):
    """2D detections (C,N,J,2) + scores with noise, each camera's people in a random order."""
    xy = project(P, X) + rng.normal(0, noise_px, (len(P),) + X.shape[:-1] + (2,))
    perms = []
    if shuffle:
        for c in range(len(P)):
            perm = rng.permutation(X.shape[0])
            xy[c] = xy[c, perm]
            perms.append(perm)
    score = np.full(xy.shape[:-1], 0.9)
    return xy, score, perms
