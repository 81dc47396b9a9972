"""The triangulate stage and the greedy (chapter-4) track stage on a session folder.

``triangulate_session(session)`` reads ``calib/rig.toml`` and ``keypoints/<cam>.npz`` (any
detector, any skeleton :mod:`keypoints.skeletons` can convert to ``body19``) and writes
``triangulate/poses3d.npz``. ``track_session_greedy(session)`` reads that file and writes
``track/tracks.npz``. Both accept a typed config, a plain dict (unknown keys are rejected with
the list of valid ones) or None for the defaults.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibrate.camera import CameraRig
from capture.fileio import FormatError
from capture.session import SessionLayout, require
from keypoints.detections import Detections
from keypoints.skeletons import CANONICAL, convert
from triangulate.dlt import _reject_unknown
from triangulate.poses3d import Poses3D
from triangulate.reconstruct import FrameReconstructor, TriangulateConfig
from triangulate.tracker import TrackerConfig, track_poses

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class GreedyTrackConfig:
    """The greedy track stage: the tracker's settings (see :class:`TrackerConfig`)."""

    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    @classmethod
    def from_dict(cls, d: dict) -> GreedyTrackConfig:
        d = dict(d)
        if "tracker" in d:
            inner = d.pop("tracker")
            _reject_unknown(cls, {"tracker": None, **d})
            return cls(tracker=TrackerConfig.from_dict(inner) if isinstance(inner, dict) else inner)
        return cls(tracker=TrackerConfig.from_dict(d))  # flat dict of tracker keys


def _as_config(cls, config):
    if config is None:
        return cls()
    if isinstance(config, cls):
        return config
    if isinstance(config, dict):
        return cls.from_dict(config)
    raise TypeError(f"expected {cls.__name__}, a dict or None, got {type(config).__name__}")


@dataclass(frozen=True)
class MultiViewDetections:
    """Detections of C cameras on a common frame axis, converted to body19 and undistorted."""

    cameras: tuple[str, ...]
    frame_index: np.ndarray  # (T,)
    t_ns: np.ndarray  # (T,)
    xy_px: np.ndarray  # (C,T,P,J,2) undistorted pixels, NaN = missing
    score: np.ndarray  # (C,T,P,J)


def load_detections(layout: SessionLayout, rig: CameraRig) -> tuple[CameraRig, MultiViewDetections]:
    """Read every ``keypoints/<cam>.npz``, check it against the rig, align frames, convert and undistort.

    Returns the rig restricted to the cameras with detections (in rig order) and the detections.
    """
    kp_cams = layout.detection_cameras()
    if not kp_cams:
        raise FormatError(
            layout.keypoints_dir,
            None,
            "no detection files (keypoints/<cam>.npz) found.",
            "Run the keypoints stage or write one Detections file per camera.",
        )
    unknown = [c for c in kp_cams if c not in rig.names]
    if unknown:
        raise FormatError(
            layout.keypoints_dir,
            None,
            f"detections for cameras {unknown} have no calibration: the rig has {rig.names}.",
            "Name each keypoints/<cam>.npz after a camera of calib/rig.toml (or recalibrate).",
        )
    cams = [c for c in rig.names if c in kp_cams]
    missing = [c for c in rig.names if c not in kp_cams]
    if missing:
        log.warning("cameras %s of the rig have no detections; using %s", missing, cams)
    if len(cams) < 2:
        raise FormatError(
            layout.keypoints_dir,
            None,
            f"triangulation needs detections from at least 2 calibrated cameras, got {cams}.",
            "Add detections of another camera of the rig.",
        )
    dets = []
    for c in cams:
        d = Detections.load(layout.detections(c))
        if d.camera != c:
            raise FormatError(
                layout.detections(c),
                "camera",
                f"the file says camera '{d.camera}' but is named after '{c}'.",
                "Rename the file or fix its 'camera' field.",
            )
        dets.append(d)
    frames = np.unique(np.concatenate([d.frame_index for d in dets]))
    T = len(frames)
    P = max(d.max_people for d in dets)
    J = CANONICAL.n_joints
    xy = np.full((len(cams), T, P, J, 2), np.nan)
    sc = np.zeros((len(cams), T, P, J))
    t_ns = np.zeros(T, np.int64)
    have_t = np.zeros(T, bool)
    sub = rig.subset(cams)
    for ci, d in enumerate(dets):
        pos = np.searchsorted(frames, d.frame_index)
        b19, s19 = convert(d.xy_px, d.score, d.skeleton, "body19")
        s19 = np.where(np.isfinite(s19), s19, 0.0)
        xy[ci, pos, : d.max_people] = sub[ci].undistort_px(b19)
        sc[ci, pos, : d.max_people] = s19
        new = ~have_t[pos] & (d.t_ns != 0)
        t_ns[pos[new]] = d.t_ns[new]
        have_t[pos[new]] = True
    return sub, MultiViewDetections(tuple(cams), frames, t_ns, xy, sc)


def _fps(layout: SessionLayout, t_ns: np.ndarray) -> float:
    if layout.session_toml.exists():
        try:
            fps = layout.read_meta().get("fps")
            if fps:
                return float(fps)
        except FormatError as e:
            log.warning("session.toml unreadable (%s); estimating fps from timestamps", e)
    dt = np.diff(t_ns[t_ns > 0])
    dt = dt[dt > 0]
    return float(1e9 / np.median(dt)) if len(dt) else 25.0


def reconstruct_all(
    rig: CameraRig, mv: MultiViewDetections, config: TriangulateConfig, progress: Progress | None = None
) -> dict[str, np.ndarray]:
    """Run association + triangulation on every frame. Returns padded (T,P3,J,...) arrays."""
    order = None
    if config.match.camera_order is not None:
        bad = [c for c in config.match.camera_order if c not in mv.cameras]
        if bad:
            raise ValueError(
                f"match.camera_order names cameras {bad} that have no detections; cameras: {list(mv.cameras)}"
            )
        order = np.asarray([mv.cameras.index(c) for c in config.match.camera_order])
    rec = FrameReconstructor(
        rig.projection_matrices(), rig.fundamental_matrices(), config, order, CANONICAL.joint_names
    )
    T = len(mv.frame_index)
    out = []
    for t in range(T):
        out.append(rec(mv.xy_px[:, t], mv.score[:, t]))
        if progress is not None:
            progress(t + 1, T)
    J = CANONICAL.n_joints
    P3 = max([len(f.xyz_m) for f in out], default=0)
    res = {
        "xyz_m": np.full((T, P3, J, 3), np.nan),
        "score": np.zeros((T, P3, J)),
        "reproj_err_px": np.full((T, P3, J), np.nan),
        "n_views": np.zeros((T, P3, J), np.int16),
        "std_m": np.full((T, P3, J), np.nan),
        "reproj_err_cam_px": np.full((T, P3, J, len(mv.cameras)), np.nan),
    }
    for t, f in enumerate(out):
        m = len(f.xyz_m)
        for k in res:
            res[k][t, :m] = getattr(f, k)
    return res


def triangulate_session(
    session_dir: str | os.PathLike,
    config: TriangulateConfig | dict | None = None,
    progress: Progress | None = None,
) -> Path:
    """Association (Alg. 1) + robust DLT for every frame of a session; writes ``triangulate/poses3d.npz``."""
    cfg = _as_config(TriangulateConfig, config)
    lay = SessionLayout(session_dir)
    rig_path = require(
        lay.rig_toml, "the calibration calib/rig.toml", "Calibrate the rig or import a calibration."
    )
    rig = CameraRig.load(rig_path)
    if len(rig) < 2:
        raise FormatError(
            rig_path,
            "cameras",
            f"triangulation needs at least 2 cameras, the rig has {len(rig)}.",
            "Calibrate at least two cameras.",
        )
    sub, mv = load_detections(lay, rig)
    res = reconstruct_all(sub, mv, cfg, progress)
    fps = _fps(lay, mv.t_ns)
    poses = Poses3D(
        fps=fps,
        frame_index=mv.frame_index,
        t_ns=mv.t_ns,
        joint_names=CANONICAL.joint_names,
        calibration_sha256=rig.sha256(),
        cameras=tuple(sub.names),
        **res,
    )
    poses.save(lay.poses3d)
    n = np.isfinite(res["xyz_m"]).all(-1).any(-1).sum(1)
    log.info(
        "triangulated %d frames from %d cameras: %.2f people per frame (max %d)",
        len(n),
        len(sub),
        float(n.mean()) if len(n) else 0.0,
        int(n.max()) if len(n) else 0,
    )
    return lay.poses3d


def track_session_greedy(
    session_dir: str | os.PathLike, config: GreedyTrackConfig | TrackerConfig | dict | None = None
) -> Path:
    """The chapter-4 tracker on ``triangulate/poses3d.npz``; writes ``track/tracks.npz``."""
    if isinstance(config, TrackerConfig):
        config = GreedyTrackConfig(tracker=config)
    cfg = _as_config(GreedyTrackConfig, config)
    lay = SessionLayout(session_dir)
    path = require(lay.poses3d, "triangulate/poses3d.npz", "Run the triangulate stage first.")
    p = Poses3D.load(path)
    tf = track_poses(
        p.xyz_m.astype(np.float64),
        p.frame_index,
        p.t_ns,
        p.fps,
        p.joint_names,
        np.asarray(CANONICAL.parents),
        confidence=p.score,
        std_m=p.std_m,
        config=cfg.tracker,
        calibration_sha256=p.calibration_sha256,
    )
    tf.save(lay.tracks)
    log.info("greedy tracker: %d tracks over %d frames", tf.n_tracks, tf.n_frames)
    return lay.tracks
