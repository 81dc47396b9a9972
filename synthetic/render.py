"""Render a :class:`~roomcap.synthetic.world.Scene` to per-camera 2D detections with realistic faults.

``render(scene, rig, RenderConfig(...))`` → :class:`Rendering`: one
:class:`roomcap.keypoints.detections.Detections` per camera plus the ground truth needed to score them
(which scene person each detection row is, which joints were visible, the true time offsets).

Per camera, in this order:

1. **time**: camera ``c`` shows, at its frame ``k``, the world at fractional scene frame
   ``k·(1 + drift_c·1e-6) + offset_c`` (linear interpolation of the ground truth; NaN outside the
   scene). Its timestamps ``t_ns`` are the nominal ``k/fps`` — the offset is what a sync test
   has to find.
2. **projection** with the camera's distortion (``Camera.project``); joints behind the camera or
   outside the image are dropped.
3. **occlusion by furniture**: the ray camera→joint hits a furniture box (slab test).
   **occlusion by people**: the joint falls inside another person's silhouette — capsules around
   torso, head, arms and legs projected to the image (radius ``f·r/depth``) — at a smaller depth.
   Self-occlusion is not modelled. With ``occluded_guess_rate`` an occluded joint is still
   reported, far off and with a low score (detectors do guess hidden joints).
4. **faults**: missed joints (``missed_joint_rate``), pixel noise (σ = ``noise_px`` scaled per joint
   by a log-normal factor), left/right flips of whole detections (``flip_rate``), whole missed
   detections (``missed_detection_rate``), false-positive people (``false_positive_rate`` per
   camera and frame: a real pose from the scene placed elsewhere in the room, seen by this camera
   only). Detections with fewer than ``min_visible_joints`` joints are dropped.
5. **scores** fall with the joint's pixel error (``0.97·exp(-e²/2·(8 px)²)`` minus a small random
   term) and are lower for guessed joints and false positives; box score = mean joint score.
6. rows are shuffled per frame (never ground-truth order) and padded with NaN.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import numpy as np

from roomcap.calibrate.camera import Camera, CameraRig
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import CANONICAL, convert, get_skeleton
from roomcap.synthetic.world import J19, Scene, config_from_dict, procedural_walk

FLIP19 = CANONICAL.flip_index
# Capsules (joint a, joint b, radius key) approximating a body's silhouette.
_CAPSULES = (
    ("neck", "pelvis", "torso"),
    ("left_shoulder", "right_hip", "torso_side"),
    ("right_shoulder", "left_hip", "torso_side"),
    ("neck", "nose", "head"),
    ("left_shoulder", "left_elbow", "limb"),
    ("left_elbow", "left_wrist", "limb"),
    ("right_shoulder", "right_elbow", "limb"),
    ("right_elbow", "right_wrist", "limb"),
    ("left_hip", "left_knee", "limb"),
    ("left_knee", "left_ankle", "limb"),
    ("right_hip", "right_knee", "limb"),
    ("right_knee", "right_ankle", "limb"),
)
_CAP_A = np.array([J19[a] for a, _, _ in _CAPSULES])
_CAP_B = np.array([J19[b] for _, b, _ in _CAPSULES])


@dataclass(frozen=True)
class RenderConfig:
    """Rendering faults and their rates; every default is fault-free except occlusion."""

    skeleton: str = "body19"
    noise_px: float = 0.0
    missed_joint_rate: float = 0.0
    occlusion_people: bool = True
    occlusion_furniture: bool = True
    occluded_guess_rate: float = 0.0
    flip_rate: float = 0.0
    false_positive_rate: float = 0.0
    missed_detection_rate: float = 0.0
    min_visible_joints: int = 3
    time_offset_std_frames: float = 0.0
    time_drift_std_ppm: float = 0.0
    time_offsets_frames: tuple[float, ...] | None = None
    time_drifts_ppm: tuple[float, ...] | None = None
    limb_radius_m: float = 0.06
    torso_radius_m: float = 0.13
    head_radius_m: float = 0.10
    shuffle: bool = True
    seed: int = 0
    model: str = "synthetic"

    def __post_init__(self) -> None:
        get_skeleton(self.skeleton)
        for k in ("missed_joint_rate", "occluded_guess_rate", "flip_rate", "missed_detection_rate"):
            v = getattr(self, k)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"RenderConfig.{k} must be in [0, 1], got {v}")
        if self.noise_px < 0 or self.false_positive_rate < 0:
            raise ValueError("RenderConfig: noise_px and false_positive_rate must be >= 0")

    @classmethod
    def from_dict(cls, d: dict) -> RenderConfig:
        return config_from_dict(cls, d)

    def replace(self, **kw) -> RenderConfig:
        return dataclasses.replace(self, **kw)


@dataclass(frozen=True)
class Rendering:
    """Detections per camera with their ground truth.

    ``gt_index[c] (T,P_c)``: scene person of each detection row, -1 false positive, -2 padding.
    ``visible (C,T,P,19)``: the ground-truth joint was in the image and not occluded (before the
    random faults). ``gt_xy_px (C,T,P,19,2)``: noise-free projections at the camera's true time.
    """

    detections: tuple[Detections, ...]
    gt_index: tuple[np.ndarray, ...]
    visible: np.ndarray
    gt_xy_px: np.ndarray
    time_offsets_frames: np.ndarray
    time_drifts_ppm: np.ndarray
    config: RenderConfig

    def __getitem__(self, cam: int) -> Detections:
        return self.detections[cam]


def sample_times(gt: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``gt (T,...)`` at fractional frames ``s (K,)``; NaN outside [0, T-1]."""
    T = gt.shape[0]
    i0 = np.floor(s).astype(np.int64)
    w = s - i0
    ok = (s >= -1e-9) & (s <= T - 1 + 1e-9)
    i0c = np.clip(i0, 0, max(T - 2, 0))
    w = np.where(i0 >= T - 1, 1.0, w) if T > 1 else np.zeros_like(w)
    i1c = np.minimum(i0c + 1, T - 1)
    wr = w.reshape((-1,) + (1,) * (gt.ndim - 1))
    out = (1 - wr) * gt[i0c] + wr * gt[i1c]
    out[~ok] = np.nan
    return out


def furniture_hidden(center: np.ndarray, X: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) bool: the segment from ``center (3,)`` to ``X (N,3)`` passes through a box ``lo/hi (B,3)``
    (slab test; a joint inside a box counts as hidden). NaN points are not hidden."""
    hit = np.zeros(len(X), dtype=bool)
    ok = np.isfinite(X).all(-1)
    if len(lo) == 0 or not ok.any():
        return hit
    d = X[ok] - center
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)  # parallel to a slab: huge but finite parameters
    inv = 1.0 / d
    tmin = np.full((len(d), len(lo)), -np.inf)
    tmax = np.full((len(d), len(lo)), np.inf)
    for k in range(3):  # slabs, one axis at a time on (N,B) arrays
        t1 = np.outer(inv[:, k], lo[:, k] - center[k])
        t2 = np.outer(inv[:, k], hi[:, k] - center[k])
        np.maximum(tmin, np.minimum(t1, t2), out=tmin)
        np.minimum(tmax, np.maximum(t1, t2), out=tmax)
    hit[ok] = ((tmax >= np.maximum(tmin, 0.0)) & (tmin < 1.0 - 1e-6)).any(-1)
    return hit


def people_hidden(
    xy: np.ndarray, depth: np.ndarray, f_px: float, radii_m: np.ndarray, margin_m: float = 0.05
) -> np.ndarray:
    """(T,P,J) bool: joint ``xy (T,P,J,2)`` at ``depth (T,P,J)`` lies in another person's capsules at a
    smaller depth. Capsule radius in pixels is ``f_px * radius_m / depth``. Only joints inside the
    other person's image box (grown by its largest capsule radius) are tested."""
    T, P, J, _ = xy.shape
    hidden = np.zeros((T, P, J), dtype=bool)
    if P < 2:
        return hidden
    zA, zB = depth[:, :, _CAP_A], depth[:, :, _CAP_B]  # (T,Q,L)
    zmid = np.maximum(0.5 * (zA + zB), 1e-3)
    r_px = f_px * radii_m[None, None, :] / zmid  # (T,Q,L)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # absent people: all-NaN
        rmax = np.nanmax(r_px, axis=2)[..., None]  # (T,Q,1)
        lo = np.nanmin(xy, axis=2) - rmax  # (T,Q,2)
        hi = np.nanmax(xy, axis=2) + rmax
        zmin = np.nanmin(depth, axis=2)  # (T,Q)
        zmax = np.nanmax(depth, axis=2)
    ok = np.isfinite(lo[..., 0]) & np.isfinite(zmin)
    ov = (
        (lo[:, :, None, 0] <= hi[:, None, :, 0])
        & (hi[:, :, None, 0] >= lo[:, None, :, 0])
        & (lo[:, :, None, 1] <= hi[:, None, :, 1])
        & (hi[:, :, None, 1] >= lo[:, None, :, 1])
    )
    ov &= ok[:, :, None] & ok[:, None, :] & (zmin[:, None, :] < zmax[:, :, None] - margin_m)
    ov &= ~np.eye(P, dtype=bool)[None]
    t, p, q = np.nonzero(ov)  # person p possibly behind person q at frame t
    if len(t) == 0:
        return hidden
    pts = xy[t, p]  # (M,J,2)
    lq, hq = lo[t, q][:, None], hi[t, q][:, None]  # (M,1,2)
    with np.errstate(invalid="ignore"):
        inb = (
            (pts[..., 0] >= lq[..., 0])
            & (pts[..., 0] <= hq[..., 0])
            & (pts[..., 1] >= lq[..., 1])
            & (pts[..., 1] <= hq[..., 1])
            & (depth[t, p] > zmin[t, q][:, None] + margin_m)
        )  # (M,J); NaN -> False
    m, j = np.nonzero(inb)
    if len(m) == 0:
        return hidden
    tm, pm, qm = t[m], p[m], q[m]
    tq = tm * P + qm
    # capsule end points per (frame, person) as (T*P, L) component arrays; explicit x/y arithmetic
    # (numpy reductions over a trailing axis of size 2 are slow)
    flat = xy.reshape(T * P, J, 2).astype(np.float32)
    ax, ay = flat[:, _CAP_A, 0][tq], flat[:, _CAP_A, 1][tq]  # (N,L)
    abx, aby = flat[:, _CAP_B, 0][tq] - ax, flat[:, _CAP_B, 1][tq] - ay
    px, py = flat[tm * P + pm, j, 0][:, None], flat[tm * P + pm, j, 1][:, None]  # (N,1)
    za = zA.reshape(T * P, -1)[tq]
    dz = zB.reshape(T * P, -1)[tq] - za
    with np.errstate(invalid="ignore", divide="ignore"):
        dx, dy = px - ax, py - ay
        u = np.clip((dx * abx + dy * aby) / np.maximum(abx * abx + aby * aby, 1e-9), 0.0, 1.0)  # (N,L)
        ex, ey = dx - u * abx, dy - u * aby
        r2 = r_px.reshape(T * P, -1)[tq] ** 2
        occ = ((ex * ex + ey * ey < r2) & (za + u * dz < depth[tm, pm, j][:, None] - margin_m)).any(-1)
    hidden[tm[occ], pm[occ], j[occ]] = True
    return hidden


def _capsule_radii(cfg: RenderConfig) -> np.ndarray:
    table = {
        "torso": cfg.torso_radius_m,
        "torso_side": 0.8 * cfg.torso_radius_m,
        "head": cfg.head_radius_m,
        "limb": cfg.limb_radius_m,
    }
    return np.array([table[k] for _, _, k in _CAPSULES])


def _scores(err_px: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return np.clip(0.97 * np.exp(-0.5 * (err_px / 8.0) ** 2) - rng.uniform(0, 0.08, err_px.shape), 0.05, 1.0)


def _camera_times(
    rig: CameraRig, cfg: RenderConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    C = len(rig)
    off = (
        np.asarray(cfg.time_offsets_frames, float)
        if cfg.time_offsets_frames is not None
        else rng.normal(0, cfg.time_offset_std_frames, C)
        if cfg.time_offset_std_frames > 0
        else np.zeros(C)
    )
    drift = (
        np.asarray(cfg.time_drifts_ppm, float)
        if cfg.time_drifts_ppm is not None
        else rng.normal(0, cfg.time_drift_std_ppm, C)
        if cfg.time_drift_std_ppm > 0
        else np.zeros(C)
    )
    if off.shape != (C,) or drift.shape != (C,):
        raise ValueError(
            f"RenderConfig: time_offsets_frames/time_drifts_ppm need {C} values "
            f"(one per camera), got {off.shape} and {drift.shape}"
        )
    return off, drift


def _clip_to_image(cam: Camera, xy: np.ndarray) -> np.ndarray:
    """Copy of ``xy (...,2)`` with points outside the image set to NaN."""
    w, h = cam.size_wh
    out = ~((xy[..., 0] >= -0.5) & (xy[..., 0] <= w - 0.5) & (xy[..., 1] >= -0.5) & (xy[..., 1] <= h - 0.5))
    xy = xy.copy()
    xy[out] = np.nan
    return xy


def _project(cam: Camera, X: np.ndarray, clip: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (...,2) (NaN behind the camera, and outside the image with ``clip``) and depth (...,)
    of world points X (...,3)."""
    flat = X.reshape(-1, 3)
    xy = cam.project(flat).reshape(X.shape[:-1] + (2,))
    depth = (flat @ cam.R[2] + cam.t[2]).reshape(X.shape[:-1])
    return (_clip_to_image(cam, xy) if clip else xy), depth


def render_camera(
    scene: Scene,
    rig: CameraRig,
    c: int,
    cfg: RenderConfig,
    offset_frames: float,
    drift_ppm: float,
    rng: np.random.Generator,
) -> tuple[Detections, np.ndarray, np.ndarray, np.ndarray]:
    """One camera: (Detections, gt_index (T,P_c), visible (T,P,19), gt_xy_px (T,P,19,2))."""
    cam = rig[c]
    gt = scene.gt_xyz_m
    T, P = gt.shape[:2]
    s = np.arange(T) * (1.0 + drift_ppm * 1e-6) + offset_frames
    X = sample_times(gt, s) if (offset_frames or drift_ppm) else gt
    xy_all, depth = _project(cam, X, clip=False)  # (T,P,19,2), (T,P,19)
    xy = _clip_to_image(cam, xy_all)
    seen = np.isfinite(xy[..., 0])
    hidden = np.zeros((T, P, 19), dtype=bool)
    if cfg.occlusion_furniture and scene.room.boxes:
        lo, hi = scene.room.boxes_array()
        Xs = np.where(seen[..., None], X, np.nan).reshape(-1, 3)  # only joints in the image
        hidden |= furniture_hidden(cam.center, Xs, lo, hi).reshape(T, P, 19)
    if cfg.occlusion_people and P > 1:
        hidden |= people_hidden(xy_all, depth, float(cam.K[0, 0]), _capsule_radii(cfg))
    visible = seen & ~hidden
    gt_xy = xy
    det_xy, score, row_ok = _detected_people(xy, seen, hidden, visible, cfg, rng)
    fp_xy, fp_score, fp_ok = _false_positives(scene, cam, cfg, rng)
    out_xy, out_score, out_ok, gt_index = _rows(det_xy, score, row_ok, fp_xy, fp_score, fp_ok, cfg, rng)
    if cfg.skeleton != "body19":
        out_xy, out_score = convert(out_xy, out_score, "body19", cfg.skeleton)
    boxes = _boxes(out_xy, out_score, out_ok, cam.size_wh)
    det = Detections(
        camera=cam.name,
        skeleton=cfg.skeleton,
        frame_index=np.arange(T),
        t_ns=np.round(np.arange(T) / scene.fps * 1e9).astype(np.int64),
        xy_px=out_xy,
        score=out_score,
        boxes=boxes,
        model=cfg.model,
        image_size_wh=cam.size_wh,
    )
    return det, gt_index, visible, gt_xy


def _detected_people(
    xy: np.ndarray,
    seen: np.ndarray,
    hidden: np.ndarray,
    visible: np.ndarray,
    cfg: RenderConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ground-truth people with the detector's faults: missed joints, guessed occluded joints, pixel
    noise, left/right flips, missed detections. Returns xy (T,P,19,2), score (T,P,19), row_ok (T,P)."""
    T, P = xy.shape[:2]
    report = visible & (rng.random((T, P, 19)) >= cfg.missed_joint_rate)
    guess = seen & hidden & (rng.random((T, P, 19)) < cfg.occluded_guess_rate)
    sig = cfg.noise_px * np.exp(rng.normal(0, 0.3, (T, P, 19)))
    noise = rng.normal(size=(T, P, 19, 2)) * sig[..., None]
    guess_noise = rng.normal(size=(T, P, 19, 2)) * (3 * cfg.noise_px + 8.0)
    det_xy = np.where(guess[..., None], xy + guess_noise, xy + noise)
    err = np.linalg.norm(det_xy - xy, axis=-1)
    score = _scores(err, rng) * np.where(guess, 0.4, 1.0)
    keep_j = report | guess
    det_xy[~keep_j] = np.nan
    score[~keep_j] = 0.0
    flip = rng.random((T, P)) < cfg.flip_rate
    det_xy = np.where(flip[..., None, None], det_xy[:, :, FLIP19], det_xy)
    score = np.where(flip[..., None], score[:, :, FLIP19], score)
    row_ok = (keep_j.sum(-1) >= cfg.min_visible_joints) & (rng.random((T, P)) >= cfg.missed_detection_rate)
    return det_xy, score, row_ok


def _false_positives(
    scene: Scene, cam, cfg: RenderConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """False positives: a scene pose placed elsewhere in the room, seen by this camera only (a Poisson
    number per frame). Returns xy (T,K,19,2), score (T,K,19), ok (T,K)."""
    gt = scene.gt_xyz_m
    T = gt.shape[0]
    n_fp = rng.poisson(cfg.false_positive_rate, T) if cfg.false_positive_rate > 0 else np.zeros(T, np.int64)
    K = int(n_fp.max()) if T else 0
    fp_xy = np.full((T, K, 19, 2), np.nan)
    fp_score = np.zeros((T, K, 19))
    fp_ok = np.zeros((T, K), dtype=bool)
    if K:
        poses = gt[scene.present]  # (N,19,3) real poses of the scene, else a procedural walker
        if not len(poses):
            poses = procedural_walk(50, scene.fps, scene.room, np.random.default_rng(0))
        tt, kk = np.nonzero(np.arange(K)[None] < n_fp[:, None])
        pose = poses[rng.integers(0, len(poses), len(tt))]  # (N,19,3)
        pose = pose - pose[:, J19["pelvis"]][:, None] * np.array([1.0, 1.0, 0.0])
        a = rng.uniform(0, 2 * np.pi, len(tt))
        ca, sa = np.cos(a)[:, None], np.sin(a)[:, None]
        px, py = pose[..., 0].copy(), pose[..., 1].copy()
        x0, x1, y0, y1 = scene.room.bounds_m
        pose[..., 0] = ca * px - sa * py + rng.uniform(x0, x1, len(tt))[:, None]
        pose[..., 1] = sa * px + ca * py + rng.uniform(y0, y1, len(tt))[:, None]
        fxy, _ = _project(cam, pose)
        fxy = fxy + rng.normal(size=fxy.shape) * (cfg.noise_px + 2.0)
        fs = _scores(np.abs(rng.normal(0, 6.0, fxy.shape[:2])), rng) * 0.6
        fs[np.isnan(fxy[..., 0])] = 0.0
        fp_xy[tt, kk], fp_score[tt, kk] = fxy, fs
        fp_ok[tt, kk] = np.isfinite(fxy[..., 0]).sum(-1) >= max(cfg.min_visible_joints, 5)
    return fp_xy, fp_score, fp_ok


def _rows(
    det_xy: np.ndarray,
    score: np.ndarray,
    row_ok: np.ndarray,
    fp_xy: np.ndarray,
    fp_score: np.ndarray,
    fp_ok: np.ndarray,
    cfg: RenderConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kept people and false positives of each frame as the file's rows (shuffled with
    ``cfg.shuffle``). Returns xy, score, ok and the ground-truth index of each row (-1: a false positive,
    -2: padding)."""
    T, P = row_ok.shape
    K = fp_ok.shape[1]
    all_xy = np.concatenate([det_xy, fp_xy], 1)
    all_score = np.concatenate([score, fp_score], 1)
    all_ok = np.concatenate([row_ok, fp_ok], 1)
    all_id = np.concatenate([np.broadcast_to(np.arange(P), (T, P)), np.full((T, K), -1)], 1)
    key = (~all_ok) * 2.0 + (rng.random(all_ok.shape) if cfg.shuffle else np.arange(P + K) / (P + K + 1.0))
    order = np.argsort(key, axis=1, kind="stable")
    n_max = int(all_ok.sum(1).max()) if T else 0
    order = order[:, :n_max]
    take = np.take_along_axis
    out_ok = take(all_ok, order, 1)
    out_xy = take(all_xy, order[..., None, None], 1)
    out_score = take(all_score, order[..., None], 1)
    gt_index = np.where(out_ok, take(all_id, order, 1), -2)
    out_xy[~out_ok] = np.nan
    out_score[~out_ok] = 0.0
    return out_xy, out_score, out_ok, gt_index


def _boxes(out_xy: np.ndarray, out_score: np.ndarray, out_ok: np.ndarray, size_wh) -> np.ndarray:
    """Each row's box: the joints' extent padded by 10 % and clipped to the image, and their mean score."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows (padding)
        lo = np.nanmin(out_xy, axis=2)
        hi = np.nanmax(out_xy, axis=2)
    pad = 0.1 * (hi - lo)
    w, h = size_wh
    lo = np.clip(lo - pad, 0, [w - 1, h - 1])
    hi = np.clip(hi + pad, 0, [w - 1, h - 1])
    n_j = np.maximum((out_score > 0).sum(-1), 1)
    box_score = out_score.sum(-1) / n_j
    boxes = np.concatenate([lo, hi, box_score[..., None]], -1)
    boxes[~out_ok] = np.nan
    return boxes


def render(scene: Scene, rig: CameraRig, config: RenderConfig | None = None, **overrides) -> Rendering:
    """Render ``scene`` into every camera of ``rig`` (see the module docstring); seeded by ``config.seed``."""
    cfg = config or RenderConfig()
    if overrides:
        cfg = dataclasses.replace(cfg, **overrides)
    rng = np.random.default_rng([cfg.seed, int(scene.config.seed)])
    off, drift = _camera_times(rig, cfg, rng)
    dets, gidx, vis, gxy = [], [], [], []
    for c in range(len(rig)):
        crng = np.random.default_rng([cfg.seed, int(scene.config.seed), c + 1])
        d, g, v, xy = render_camera(scene, rig, c, cfg, float(off[c]), float(drift[c]), crng)
        dets.append(d)
        gidx.append(g)
        vis.append(v)
        gxy.append(xy)
    return Rendering(tuple(dets), tuple(gidx), np.stack(vis), np.stack(gxy), off, drift, cfg)


render_scene = render  # the name exported by the package (``synthetic.render`` is this module)
