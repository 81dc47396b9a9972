"""Per-camera intrinsics from board detections: frame selection, OpenCV calibration, bad-frame rejection.

Models (``model``):
- ``"pinhole"``: OpenCV k1, k2, p1, p2, k3 (k3 fixed at 0 with fewer than ``k3_min_frames`` frames);
- ``"pinhole4"``: k1, k2, p1, p2 (COLMAP's OPENCV model: the bundle adjustment can refine it exactly);
- ``"rational"``: OpenCV rational model, 8 coefficients (k1..k6, p1, p2);
- ``"fisheye"``: ``cv2.fisheye`` (Kannala-Brandt) k1..k4.

RMS is OpenCV's: sqrt(mean over points of the squared reprojection distance), in pixels.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from roomcap.calibrate.boards import Board, CalibrationError
from roomcap.calibrate.camera import Camera
from roomcap.calibrate.detect import CameraDetections

log = logging.getLogger(__name__)

__all__ = [
    "IntrinsicsConfig",
    "IntrinsicsResult",
    "calibrate_intrinsics",
    "select_frames",
    "coverage_grid",
    "MODELS",
]

MODELS = ("pinhole", "pinhole4", "rational", "fisheye")


@dataclass(frozen=True)
class IntrinsicsConfig:
    model: str = "pinhole"
    max_frames: int = 40  # frames given to the solver, chosen for coverage and diversity
    min_frames: int = 6  # fewer -> CalibrationError (record more)
    min_points: int = 6  # per frame
    reject_factor: float = 3.0  # a frame is rejected above max(reject_factor * median, reject_floor_px)
    reject_floor_px: float = 1.0
    k3_min_frames: int = 15
    point_reject_factor: float = 6.0  # a corner is dropped above max(factor * median point error, floor)

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"intrinsics model {self.model!r} is not one of {list(MODELS)}")


@dataclass(frozen=True)
class IntrinsicsResult:
    """One camera's intrinsics. frames_used: (U,) frame indices; per_frame_rms_px: (U,);
    board_from... rvecs/tvecs: (U,3) cam_from_board of each used frame; coverage: (GY,GX) corner counts."""

    name: str
    size_wh: tuple[int, int]
    model: str
    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    frames_used: np.ndarray
    frames_rejected: np.ndarray
    per_frame_rms_px: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    coverage: np.ndarray
    n_frames_seen: int

    @property
    def coverage_fraction(self) -> float:
        return float((self.coverage > 0).mean())

    def camera(self) -> Camera:
        return Camera(
            self.name, self.size_wh, self.K, self.dist, "fisheye" if self.model == "fisheye" else "pinhole"
        )


def coverage_grid(xy_px: np.ndarray, size_wh: tuple[int, int], gx: int = 16) -> np.ndarray:
    """Counts of points per image cell. xy_px: (...,2) (NaN ignored); returns (GY,GX)."""
    w, h = size_wh
    gy = max(1, round(gx * h / w))
    p = xy_px.reshape(-1, 2)
    p = p[np.isfinite(p).all(1)]
    H, _, _ = np.histogram2d(p[:, 1], p[:, 0], bins=(gy, gx), range=((0, h), (0, w)))
    return H.astype(np.int64)


def _descriptor(xy: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """Where the board is and how it looks in the image: centroid, log area, elongation, orientation."""
    w, h = size_wh
    p = xy[np.isfinite(xy[:, 0])]
    c = p.mean(0) / np.array([w, h])
    cov = np.cov((p / max(w, h)).T) + 1e-12 * np.eye(2)
    ev, evec = np.linalg.eigh(cov)
    ang = np.arctan2(evec[1, 1], evec[0, 1])
    return np.array(
        [
            c[0],
            c[1],
            0.25 * np.log(ev.prod()) / 2,
            0.5 * np.log(ev[1] / ev[0]) / 2,
            0.2 * np.cos(2 * ang),
            0.2 * np.sin(2 * ang),
        ]
    )


def select_frames(xy_px: np.ndarray, size_wh: tuple[int, int], max_frames: int) -> np.ndarray:
    """Greedy choice of at most max_frames frames of (F,N,2) that cover the image and differ in pose:
    each step takes the frame adding most uncovered cells plus distance (in position, scale, shape)
    to the frames already chosen. Returns indices into F (sorted)."""
    F = xy_px.shape[0]
    if F <= max_frames:
        return np.arange(F)
    cells = [set(np.flatnonzero(coverage_grid(xy_px[i], size_wh, 12).ravel())) for i in range(F)]
    desc = np.stack([_descriptor(xy_px[i], size_wh) for i in range(F)])
    covered: set[int] = set()
    chosen: list[int] = []
    dmin = np.full(F, 1.0)
    n_cells = 12 * max(1, round(12 * size_wh[1] / size_wh[0]))
    for _ in range(max_frames):
        gain = np.array([len(cells[i] - covered) for i in range(F)], float) / max(1, n_cells) * 10
        score = gain + dmin
        score[chosen] = -np.inf
        k = int(np.argmax(score))
        chosen.append(k)
        covered |= cells[k]
        dmin = np.minimum(dmin, np.linalg.norm(desc - desc[k], axis=1))
    return np.sort(np.array(chosen))


def _calibrate(
    obj: list[np.ndarray], img: list[np.ndarray], size_wh, model: str, n_frames_total: int, k3_min: int
):
    import cv2

    if model == "fisheye":
        # OpenCV 5 moved the fisheye flags to the top level (cv2.fisheye.CALIB_* in 4.x)
        fl = lambda n: getattr(cv2.fisheye, n, None) or getattr(cv2, n)
        flags = fl("CALIB_RECOMPUTE_EXTRINSIC") | fl("CALIB_FIX_SKEW")
        crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-9)
        o = [p.reshape(1, -1, 3).astype(np.float64) for p in obj]  # (1,N,3): OpenCV 5 rejects (N,1,3) here
        i = [p.reshape(1, -1, 2).astype(np.float64) for p in img]
        rms, K, D, rv, tv = cv2.fisheye.calibrate(
            o, i, tuple(size_wh), None, None, flags=flags, criteria=crit
        )
        return K, D.ravel(), np.array(rv).reshape(-1, 3), np.array(tv).reshape(-1, 3)
    flags = 0
    if model == "rational":
        flags |= cv2.CALIB_RATIONAL_MODEL
    elif model == "pinhole4" or n_frames_total < k3_min:
        flags |= cv2.CALIB_FIX_K3
    o = [p.astype(np.float32) for p in obj]
    i = [p.astype(np.float32) for p in img]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    rms, K, D, rv, tv = cv2.calibrateCamera(o, i, tuple(size_wh), None, None, flags=flags, criteria=crit)
    D = D.ravel()
    D = D[:8] if model == "rational" else D[:4] if model == "pinhole4" else D[:5]
    return K, D, np.array(rv).reshape(-1, 3), np.array(tv).reshape(-1, 3)


def _project(model: str, obj: np.ndarray, rvec, tvec, K, D) -> np.ndarray:
    import cv2

    if model == "fisheye":
        p, _ = cv2.fisheye.projectPoints(
            obj.reshape(-1, 1, 3).astype(np.float64), rvec.reshape(3, 1), tvec.reshape(3, 1), K, D
        )
    else:
        p, _ = cv2.projectPoints(obj.astype(np.float64), rvec, tvec, K, D)
    return p.reshape(-1, 2)


def calibrate_intrinsics(
    board: Board, det: CameraDetections, config: IntrinsicsConfig | None = None
) -> IntrinsicsResult:
    """Intrinsics of one camera from its detections (see module doc); rejects frames whose RMS is far
    above the median and calibrates again."""
    cfg = config or IntrinsicsConfig()
    obj_all = board.object_points()
    ok = _usable_frames(det, cfg)
    sel = ok[select_frames(det.xy_px[ok], det.size_wh, cfg.max_frames)]
    rejected: list[int] = []
    # per-point mask: single corners far off (a mis-refined corner) are dropped, not their whole frame
    keep = {int(i): np.isfinite(det.xy_px[i, :, 0]) for i in sel}
    n_dropped = 0
    for _ in range(5):
        sel = np.array([i for i in sel if keep[int(i)].sum() >= cfg.min_points], dtype=np.int64)
        obj = [obj_all[keep[int(i)]] for i in sel]
        img = [det.xy_px[i][keep[int(i)]] for i in sel]
        K, D, rv, tv, perr = _fit(det, cfg, obj, img)
        errs = np.array([np.sqrt(np.mean(e**2)) for e in perr])
        thr = max(cfg.reject_factor * float(np.median(errs)), cfg.reject_floor_px)
        bad = errs > thr
        pthr = max(cfg.point_reject_factor * float(np.median(np.concatenate(perr))), cfg.reject_floor_px)
        n_bad_pts = _drop_corners(sel, perr, bad, keep, pthr)
        if (not bad.any() and not n_bad_pts) or len(sel) - bad.sum() < cfg.min_frames:
            break
        n_dropped += n_bad_pts
        if bad.any():
            rejected.extend(det.frames[sel[bad]].tolist())
            log.info("camera %s: rejecting %d frame(s) with RMS above %.2f px", det.name, int(bad.sum()), thr)
        sel = sel[~bad]
    if n_dropped:
        log.info("camera %s: dropped %d single corner(s) above their frame's fit", det.name, n_dropped)
    n_pts = np.array([len(p) for p in img])
    rms = float(np.sqrt(np.sum(errs**2 * n_pts) / n_pts.sum()))
    cov = coverage_grid(det.xy_px[sel], det.size_wh)
    log.info(
        "camera %s: %s f=(%.1f, %.1f) c=(%.1f, %.1f) RMS %.3f px from %d frames, coverage %.0f%%",
        det.name,
        cfg.model,
        K[0, 0],
        K[1, 1],
        K[0, 2],
        K[1, 2],
        rms,
        len(sel),
        100 * float((cov > 0).mean()),
    )
    return IntrinsicsResult(
        det.name,
        det.size_wh,
        cfg.model,
        np.asarray(K, float),
        np.asarray(D, float),
        rms,
        det.frames[sel],
        np.asarray(rejected, np.int64),
        errs,
        rv,
        tv,
        cov,
        int(len(ok)),
    )


def _usable_frames(det: CameraDetections, cfg: IntrinsicsConfig) -> np.ndarray:
    """The frames with at least ``cfg.min_points`` corners; an error when fewer than ``cfg.min_frames``."""
    ok = np.flatnonzero(det.n_points_seen >= cfg.min_points)
    if len(ok) < cfg.min_frames:
        raise CalibrationError(
            f"Camera '{det.name}': the board was seen (>= {cfg.min_points} points) in only {len(ok)} of "
            f"{det.n_frames_read} frames read; intrinsics need at least {cfg.min_frames}. Record the board "
            "again "
            "in front of this camera, moving it over the whole image and tilting it (about 20-40 views), "
            "or give known intrinsics (--intrinsics rig.toml)."
        )
    return ok


def _fit(det: CameraDetections, cfg: IntrinsicsConfig, obj: list, img: list) -> tuple:
    """One OpenCV calibration of the kept corners: K, dist, the board poses and each frame's per-corner
    reprojection errors (px)."""
    import cv2

    try:
        K, D, rv, tv = _calibrate(obj, img, det.size_wh, cfg.model, len(obj), cfg.k3_min_frames)
    except cv2.error as e:  # ill-conditioned input
        raise CalibrationError(
            f"Camera '{det.name}': OpenCV could not calibrate from {len(obj)} frames ({e}). "
            "Record more views of the board with more tilt, or use a simpler model "
            "(--model pinhole)."
        ) from e
    perr = [
        np.linalg.norm(_project(cfg.model, o, r, t, K, D) - p, axis=1)
        for o, p, r, t in zip(obj, img, rv, tv, strict=True)
    ]
    return K, D, rv, tv, perr


def _drop_corners(sel: np.ndarray, perr: list, bad: np.ndarray, keep: dict, pthr: float) -> int:
    """Unmark in ``keep`` the corners above ``pthr`` px in the frames that are kept; how many."""
    n_bad_pts = 0
    for i, e, b in zip(sel, perr, bad, strict=True):
        if not b and (e > pthr).any():
            idx = np.flatnonzero(keep[int(i)])
            keep[int(i)][idx[e > pthr]] = False
            n_bad_pts += int((e > pthr).sum())
    return n_bad_pts
