"""A small whole-body track for the output tests: the synthetic walkers (body19) with both hands (the 42
joints of ``body19_hands``), fingers of constant bone lengths curling and opening over time."""

from __future__ import annotations

import numpy as np

from roomcap.keypoints.skeletons import CANONICAL, FINGERS, HANDS, get_skeleton
from roomcap.track.trackfile import TrackFile

SK = get_skeleton("body19_hands")
# per finger: palm bone offset along the hand (m) and across it (finger slots), phalanx lengths (m)
_ALONG = (0.03, 0.08, 0.085, 0.08, 0.07)
_PHALANX = (0.032, 0.025, 0.02)


def hand_pose(wrist, elbow, across, curl: float) -> np.ndarray:
    """(21,3) one hand beyond ``wrist`` along the forearm (``elbow`` -> ``wrist``), fingers spread along
    ``across`` (a vector roughly across the hand), every finger joint bent by ``curl`` radians towards
    the palm."""
    u = (wrist - elbow) / np.linalg.norm(wrist - elbow)
    v = across - u * (across @ u)
    v /= np.linalg.norm(v)
    n = np.cross(u, v)
    root = wrist + 0.012 * u
    out = [root]
    for k in range(len(FINGERS)):
        base = root + _ALONG[k] * u + (k - 1.5) * 0.02 * v
        out.append(base)
        x, ang = base, 0.0
        for s in range(3):
            ang += curl * (0.6 if k == 0 else 1.0)
            x = x + _PHALANX[s] * (np.cos(ang) * u + np.sin(ang) * n)
            out.append(x)
    return np.asarray(out)


def wholebody_xyz(n_people: int = 1, T: int = 30, seed: int = 0) -> np.ndarray:
    """(T,P,61,3) walkers in the ``body19_hands`` layout, hands curling 0..70 degrees and back."""
    from track_helpers import walkers

    body = walkers(n_people, T, seed=seed).astype(np.float64)
    xyz = np.full((T, n_people, SK.n_joints, 3), np.nan)
    xyz[:, :, :19] = body
    curl = np.deg2rad(35.0) * (1 - np.cos(np.linspace(0, 2 * np.pi, T)))
    ls, rs = CANONICAL.index("left_shoulder"), CANONICAL.index("right_shoulder")
    for t in range(T):
        for p in range(n_people):
            across = body[t, p, rs] - body[t, p, ls]
            for side, H in (("left", HANDS[:21]), ("right", HANDS[21:])):
                w = body[t, p, CANONICAL.index(f"{side}_wrist")]
                e = body[t, p, CANONICAL.index(f"{side}_elbow")]
                xyz[t, p, [SK.index(n) for n in H]] = hand_pose(w, e, across, curl[t])
    return xyz


def wholebody_trackfile(xyz: np.ndarray, seed: int = 0) -> TrackFile:
    """A track file of ``xyz (T,P,61,3)`` in the ``body19_hands`` layout (NaN: unknown)."""
    from tests.test_outputs_export import _trackfile

    return _trackfile(xyz, np.random.default_rng(seed), skeleton=SK, std_max_m=0.02)


def wholebody_session(
    root, T: int = 20, n_people: int = 1, cams: int = 4, noise_px: float = 0.5, seed: int = 0
):
    """A small whole-body session: a ring rig, every camera's 2D in ``body19_hands`` (the walkers with their
    hands projected, a little noise), triangulated with the ``whole_body`` skeleton and tracked (greedy).
    Returns (layout, ground truth xyz (T,P,61,3))."""
    from roomcap.capture.session import SessionLayout
    from roomcap.keypoints.detections import Detections
    from roomcap.synthetic.rigs import ring_rig
    from roomcap.track.greedy_stage import track_session_greedy
    from roomcap.triangulate.stage import triangulate_session

    rng = np.random.default_rng(seed)
    X = wholebody_xyz(n_people, T, seed=seed)
    lay = SessionLayout(root)
    rig = ring_rig(cams, radius_m=3.0)
    rig.save(lay.calib_dir / "rig.toml")
    for cam in rig:
        xy = cam.project(X.reshape(-1, 3)).reshape(T, n_people, SK.n_joints, 2)
        xy = (xy + rng.normal(0, noise_px, xy.shape)).astype(np.float32)
        Detections(
            camera=cam.name,
            skeleton=SK.id,
            frame_index=np.arange(T),
            t_ns=np.arange(T) * 40_000_000,
            xy_px=xy,
            score=np.full(xy.shape[:3], 0.9, np.float32),
            boxes=np.full((T, n_people, 5), np.nan),
        ).save(lay.detections(cam.name))
    triangulate_session(lay.root, {"skeleton": "whole_body"})
    track_session_greedy(lay.root)
    return lay, X
