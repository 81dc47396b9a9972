"""Small hand-made worlds for the track tests: look-at cameras and people from the procedural walker."""

from __future__ import annotations

import numpy as np


def look_at_P(center, target=(0.0, 0.0, 1.0), f_px: float = 1000.0, size_wh=(1280, 720)) -> np.ndarray:
    c = np.asarray(center, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    K = np.array([[f_px, 0, size_wh[0] / 2], [0, f_px, size_wh[1] / 2], [0, 0, 1.0]])
    return K @ np.hstack([R, (-R @ c)[:, None]])


def ring_P(n_cams: int, radius_m: float = 4.0, height_m: float = 2.5) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n_cams, endpoint=False)
    return np.stack([look_at_P([radius_m * np.cos(t), radius_m * np.sin(t), height_m]) for t in a])


def walkers(n_people: int, n_frames: int, fps: float = 25.0, seed: int = 0) -> np.ndarray:
    """(T,P,19,3) people from the synthetic procedural walker, kept inside a 3 m square."""
    from roomcap.synthetic.rigs import ring_room
    from roomcap.synthetic.world import SceneConfig, make_scene

    scene = make_scene(
        ring_room(2.4),
        SceneConfig(n_people=n_people, duration_s=n_frames / fps, fps=fps, seed=seed, motion="procedural"),
    )
    return scene.gt_xyz_m[:n_frames].astype(np.float32)


def render_kp(
    P: np.ndarray, X: np.ndarray, noise_px: float = 1.0, seed: int = 0, drop: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Project people X (T,P,J,3) into cameras P (C,3,4): kp (T,C,P,J,2) shuffled per frame, sc (T,C,P,J)."""
    rng = np.random.default_rng(seed)
    T, Pn = X.shape[:2]
    h = np.einsum("cab,tpjb->tcpja", P[:, :, :3], X) + P[None, :, None, None, :, 3]
    kp = h[..., :2] / h[..., 2:] + rng.normal(0, noise_px, h[..., :2].shape)
    sc = np.full(kp.shape[:-1], 0.9)
    miss = (rng.random(sc.shape) < drop) | ~np.isfinite(kp).all(-1)
    kp[miss] = np.nan
    sc[miss] = 0.0
    for t in range(T):
        for c in range(len(P)):
            perm = rng.permutation(Pn)
            kp[t, c], sc[t, c] = kp[t, c, perm], sc[t, c, perm]
    return kp.astype(np.float32), sc.astype(np.float32)


def render_maps(
    P: np.ndarray, X: np.ndarray, size_wh=(1280, 720), stride: int = 8, sigma_map: float = 1.0, uv_px=None
):
    """OpenPose-style maps of people X (P,J,3) body19 in cameras P (C,3,4): per camera a CameraMaps with
    Gaussian blobs at the projected coco18 joints and unit vectors along the projected PAF limbs.
    ``uv_px`` (C,P,J,2): the image points to draw instead of the pinhole projections (lens distortion)."""
    from roomcap.keypoints.decoders import OPENPOSE_LIMBS
    from roomcap.keypoints.skeletons import CANONICAL, get_skeleton
    from roomcap.track import observation as obs

    coco18 = get_skeleton("coco18")
    limbs = obs.paf_limbs_in(CANONICAL, coco18.joint_names, OPENPOSE_LIMBS)  # (L,2) body19 indices
    W, H = size_wh[0] // stride, size_wh[1] // stride
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    has = np.zeros(CANONICAL.n_joints, bool)
    has[[CANONICAL.index(n) for n in coco18.joint_names]] = True
    to_map = np.float32([[1 / stride, 0, 0], [0, 1 / stride, 0]])
    out = []
    for c in range(len(P)):
        if uv_px is None:
            h = np.einsum("ab,pjb->pja", P[c, :, :3], X) + P[c, :, 3]
            uv = h[..., :2] / h[..., 2:] / stride  # (P,J,2) map px
        else:
            uv = np.asarray(uv_px[c]) / stride
        heat = np.zeros((CANONICAL.n_joints, H, W), np.float32)
        paf = np.zeros((len(limbs), 2, H, W), np.float32)
        for p in range(len(X)):
            for j in np.flatnonzero(has):
                g = np.exp(-((xx - uv[p, j, 0]) ** 2 + (yy - uv[p, j, 1]) ** 2) / (2 * sigma_map**2))
                heat[j] = np.maximum(heat[j], g)
            for li, (a, b) in enumerate(limbs):
                d = uv[p, b] - uv[p, a]
                n = float(np.linalg.norm(d))
                if n < 1e-6:
                    continue
                e = d / n
                rx, ry = xx - uv[p, a, 0], yy - uv[p, a, 1]
                along = rx * e[0] + ry * e[1]
                across = np.abs(-rx * e[1] + ry * e[0])
                band = (along >= -1) & (along <= n + 1) & (across <= 1.0)
                paf[li, 0][band], paf[li, 1][band] = e[0], e[1]
        out.append(obs.CameraMaps(heat, paf, limbs, to_map))
    return out
