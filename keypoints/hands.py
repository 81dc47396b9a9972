"""Hands on the body's side: which hand is left and which is right comes from the body's wrists, not from the
hand model's handedness guess.

A hand model's handedness is a guess that a mirrored view flips, and MediaPipe Holistic runs its left and
right hand models from the pose's wrists: in a view where the two wrists are close, or one hand is hidden,
both models can land on the same hand (caliscope's 4-camera holistic recording: in three of its four views
the left and right hand landmarks coincide within a few pixels in most frames). Triangulated as they are,
such a view puts one hand's points into the other hand's 3D. :func:`hands_by_body_side` fixes the 2D of a
``<layout>_hands`` skeleton (:mod:`roomcap.keypoints.skeletons`) per view, frame and person:

- the same hand twice (the two hands' corresponding joints closer than ``dup_frac`` of the hand's size, median
  over the joints both have): kept once, on the side whose body wrist is nearer to its root;
- two distinct hands: swapped when the hand roots are nearer to the opposite wrists (sum of the two
  distances);
- one hand: moved to the side of the nearer body wrist.

Where the body's wrists are not both seen nothing changes.
"""

from __future__ import annotations

import numpy as np

from roomcap.keypoints.skeletons import HAND_LEFT, HAND_RIGHT, get_skeleton


def hands_by_body_side(
    xy: np.ndarray, score: np.ndarray, skeleton: str, dup_frac: float = 0.25
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """xy (...,J,2) and score (...,J) of a layout with both hands and both wrists -> fixed copies and the
    counts ``{"swapped": n, "duplicates": n, "moved": n}`` (module doc)."""
    s = get_skeleton(skeleton)
    names = s.joint_names
    if not (set(HAND_LEFT) | set(HAND_RIGHT) | {"left_wrist", "right_wrist"}) <= set(names):
        return xy, score, {"swapped": 0, "duplicates": 0, "moved": 0}
    L = np.array([names.index(n) for n in HAND_LEFT])
    R = np.array([names.index(n) for n in HAND_RIGHT])
    wl, wr = names.index("left_wrist"), names.index("right_wrist")
    shape = xy.shape
    xy = np.array(xy, copy=True).reshape(-1, shape[-2], 2)
    score = np.array(score).reshape(-1, shape[-2])
    ok = np.isfinite(xy).all(-1) & (score > 0)
    counts = {"swapped": 0, "duplicates": 0, "moved": 0}
    has_l, has_r = ok[:, L].any(-1), ok[:, R].any(-1)
    wrists = ok[:, wl] & ok[:, wr]
    for i in np.flatnonzero((has_l | has_r) & wrists):
        hl, hr = _anchor(xy[i, L], ok[i, L]), _anchor(xy[i, R], ok[i, R])
        a, b = xy[i, wl], xy[i, wr]
        if has_l[i] and has_r[i]:
            both = ok[i, L] & ok[i, R]
            size = max(_size(xy[i, L], ok[i, L]), _size(xy[i, R], ok[i, R]), 1e-6)
            gap = (
                np.median(np.linalg.norm(xy[i, L][both] - xy[i, R][both], axis=-1)) if both.any() else np.inf
            )
            if gap < dup_frac * size:  # one hand seen twice: keep it on its wrist's side
                keep_left = np.linalg.norm(hl - a) <= np.linalg.norm(hl - b)
                drop = R if keep_left else L
                xy[i, drop], score[i, drop] = np.nan, 0.0
                counts["duplicates"] += 1
                continue
            keep = np.linalg.norm(hl - a) + np.linalg.norm(hr - b)
            swap = np.linalg.norm(hl - b) + np.linalg.norm(hr - a)
            if swap < keep:
                _swap(xy, score, i, L, R)
                counts["swapped"] += 1
        else:
            h = hl if has_l[i] else hr
            nearer_left = np.linalg.norm(h - a) <= np.linalg.norm(h - b)
            if nearer_left != bool(has_l[i]):
                _swap(xy, score, i, L, R)
                counts["moved"] += 1
    return xy.reshape(shape), score.reshape(shape[:-1]), counts


def _anchor(h: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """The hand's root where seen, else the mean of its seen joints (NaN for no joint)."""
    if ok[0]:
        return h[0]
    return h[ok].mean(0) if ok.any() else np.full(2, np.nan)


def _size(h: np.ndarray, ok: np.ndarray) -> float:
    """The diagonal of the box of the hand's seen joints."""
    if ok.sum() < 2:
        return 0.0
    v = h[ok]
    return float(np.linalg.norm(v.max(0) - v.min(0)))


def _swap(xy, score, i, L, R) -> None:
    xy[i, L], xy[i, R] = xy[i, R].copy(), xy[i, L].copy()
    score[i, L], score[i, R] = score[i, R].copy(), score[i, L].copy()
