"""The triangulate stage and the greedy (chapter-4) track stage on a session folder.

``triangulate_session(session)`` reads ``calib/rig.toml`` and ``keypoints/<cam>.npz`` (any
detector, any skeleton :mod:`keypoints.skeletons` can convert to ``body19``, or ``whole_body``
or a skeleton TOML with the option ``skeleton``) and writes
``triangulate/poses3d.npz``. ``track_session_greedy(session)`` reads that file and writes
``track/tracks.npz``. Both accept a typed config, a plain dict (unknown keys are rejected with
the list of valid ones) or None for the defaults.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calibrate.camera import CameraRig
from calibrate.checks import rig_warnings
from capture.fileio import FormatError
from capture.session import SessionLayout, require
from core.config import config_from_dict
from core.progress import Progress
from keypoints.detections import Detections
from keypoints.skeletons import (
    CANONICAL,
    convert,
    get_skeleton,
    load_skeleton_toml,
    skeleton_from_names,
    whole_body,
)
from triangulate.checks import check_frame_order, detection_warnings
from triangulate.poses3d import Poses3D
from triangulate.reconstruct import FrameReconstructor, TriangulateConfig
from triangulate.tracker import TrackerConfig, track_poses

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GreedyTrackConfig:
    """The greedy track stage: the tracker's settings (see :class:`TrackerConfig`)."""

    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    @classmethod
    def from_dict(cls, d: dict) -> GreedyTrackConfig:
        if "tracker" in d:
            return config_from_dict(cls, d)
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
    offsets_frames: dict[str, float] = field(default_factory=dict)  # sync offsets applied (session.toml)
    joint_names: tuple[str, ...] = CANONICAL.joint_names  # the 3D skeleton's joints (J,)
    parents: tuple[int, ...] = CANONICAL.parents  # (J,)


@dataclass(frozen=True)
class FrameShift:
    """A camera's frame axis against the reference camera's (``capture-run sync``, session.toml [sync]).

    Camera frame ``f`` shows the instant of reference frame ``f + offset_frames + drift * (f - f0)``
    (the convention of ``capture.offline_sync``; ``drift`` in frames per frame = drift_ppm * 1e-6).
    """

    offset_frames: float = 0.0
    drift: float = 0.0

    def map(self, frame_index: np.ndarray) -> np.ndarray:
        f = np.asarray(frame_index, np.float64)
        f0 = f[0] if len(f) else 0.0
        return f + self.offset_frames + self.drift * (f - f0)


def sync_shifts(layout: SessionLayout, cams: list[str], fps: float | None) -> dict[str, FrameShift]:
    """The per-camera frame shifts that ``capture-run sync`` wrote into session.toml (none: {}).

    Keypoint sync stores ``offset_frames`` (+ ``drift_ppm``); audio sync ``offset_s``, turned into
    frames with the session's frame rate. A reference camera other than the session's cameras, or an
    entry that cannot be read, is a clear error rather than silently unsynchronised 3D.
    """
    if not layout.session_toml.exists():
        return {}
    meta = layout.read_meta()
    sync = meta.get("sync")
    if not sync:
        return {}
    entries = sync.get("cameras", {}) if isinstance(sync, dict) else {}
    where = f"{layout.session_toml} [sync]"
    out: dict[str, FrameShift] = {}
    for cam in cams:
        e = entries.get(cam)
        if e is None:
            continue
        try:
            if "offset_frames" in e:
                off = float(e["offset_frames"])
            else:
                rate = float(sync.get("fps") or fps or 0.0)
                if rate <= 0:
                    raise ValueError("offset_s without a frame rate")
                off = float(e["offset_s"]) * rate
            drift = float(e.get("drift_ppm", 0.0)) * 1e-6
        except (TypeError, ValueError, KeyError) as err:
            raise FormatError(
                layout.session_toml,
                f"sync.cameras.{cam}",
                f"cannot read the sync offset ({err}).",
                "Rerun `capture-run sync` or remove the [sync] table.",
            ) from None
        if not (np.isfinite(off) and np.isfinite(drift)):
            raise FormatError(
                layout.session_toml,
                f"sync.cameras.{cam}",
                "the offset is not finite.",
                "Rerun capture-run sync.",
            )
        if off or drift:
            out[cam] = FrameShift(off, drift)
    missing = [c for c in cams if c not in entries]
    if entries and missing:
        log.warning(
            "%s has no offset for cameras %s; they are taken as in sync with the reference", where, missing
        )
    return out


def load_detections(
    layout: SessionLayout, rig: CameraRig, apply_sync: bool = True, skeleton: str = "body19"
) -> tuple[CameraRig, MultiViewDetections]:
    """Read every ``keypoints/<cam>.npz``, check it against the rig, align frames, convert and undistort.

    Frames are matched across cameras by frame index after the sync offsets of session.toml
    (``capture-run sync``, :func:`sync_shifts`) are applied (``apply_sync``): each camera's frames are
    moved onto the reference camera's frame axis, to the nearest frame (the residual is under half a
    frame; detections are not interpolated, their person slots are not identities). Frames that land
    before reference frame 0 are dropped. ``skeleton``: the 3D joints, ``body19``, ``whole_body``
    (body19 plus the joints the cameras' layouts add) or a skeleton TOML. Returns the rig restricted
    to the cameras with detections (in rig order) and the detections.
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
    # a skeleton TOML registers its 2D layouts before any detections file loads
    custom = load_skeleton_toml(skeleton) if str(skeleton).endswith(".toml") else None
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
        check_frame_order(d, layout.detections(c))
        dets.append(d)
    for w in detection_warnings(dets):
        log.warning("%s", w)
    shifts = {}
    if apply_sync:
        fps_hint = None
        dt = np.diff(dets[0].t_ns)
        dt = dt[dt > 0]
        if len(dt):
            fps_hint = float(1e9 / np.median(dt))
        shifts = sync_shifts(layout, cams, fps_hint)
    keep, mapped = [], []
    for c, d in zip(cams, dets, strict=True):
        if c not in shifts:
            keep.append(np.ones(d.n_frames, bool))
            mapped.append(d.frame_index)
            continue
        target_f = shifts[c].map(d.frame_index)
        target = np.rint(target_f).astype(np.int64)
        ok = target >= 0
        # drift can send two frames to one reference frame: keep the nearer one
        order = np.argsort(np.abs(target_f - target), kind="stable")
        order = order[ok[order]]
        _, first = np.unique(target[order], return_index=True)
        k = np.zeros(d.n_frames, bool)
        k[order[first]] = True
        keep.append(k)
        mapped.append(target)
        log.info(
            "camera %s: sync offset %+.2f frames (drift %+.0f ppm) applied; %d of %d frames on the "
            "reference axis",
            c,
            shifts[c].offset_frames,
            shifts[c].drift * 1e6,
            int(k.sum()),
            d.n_frames,
        )
    frames = np.unique(np.concatenate([m[k] for m, k in zip(mapped, keep, strict=True)]))
    T = len(frames)
    P = max(d.max_people for d in dets)
    if custom is not None:
        skel = custom
    elif skeleton == "whole_body":
        skel = whole_body([d.skeleton for d in dets])
    else:
        skel = get_skeleton(skeleton)
    J = skel.n_joints
    xy = np.full((len(cams), T, P, J, 2), np.nan)
    sc = np.zeros((len(cams), T, P, J))
    t_ns = np.zeros(T, np.int64)
    have_t = np.zeros(T, bool)
    sub = rig.subset(cams)
    # timestamps: unshifted cameras first (the reference's clock), then shifted ones moved onto it
    order = sorted(range(len(cams)), key=lambda i: cams[i] in shifts)
    for ci in order:
        d, k = dets[ci], keep[ci]
        pos = np.searchsorted(frames, mapped[ci][k])
        b19, s19 = convert(d.xy_px[k], d.score[k], d.skeleton, skel)
        s19 = np.where(np.isfinite(s19), s19, 0.0)
        xy[ci, pos, : d.max_people] = sub[ci].undistort_px(b19)
        sc[ci, pos, : d.max_people] = s19
        t_c = d.t_ns[k]
        if cams[ci] in shifts and len(t_c) > 1:
            period_ns = float(np.median(np.diff(d.t_ns))) if d.n_frames > 1 else 0.0
            t_c = np.where(t_c != 0, t_c + np.rint((mapped[ci][k] - d.frame_index[k]) * period_ns), 0)
        new = ~have_t[pos] & (t_c != 0)
        t_ns[pos[new]] = t_c[new]
        have_t[pos[new]] = True
    offsets = {c: shifts[c].offset_frames for c in shifts}
    return sub, MultiViewDetections(
        tuple(cams), frames, t_ns, xy, sc, offsets, skel.joint_names, skel.parents
    )


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
        rig.projection_matrices(), rig.fundamental_matrices(), config, order, mv.joint_names
    )
    T = len(mv.frame_index)
    out = []
    for t in range(T):
        out.append(rec(mv.xy_px[:, t], mv.score[:, t]))
        if progress is not None:
            progress("triangulate", t + 1, T)
    J = len(mv.joint_names)
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
    for w in rig_warnings(rig, str(rig_path)):
        log.warning("%s", w)
    sub, mv = load_detections(lay, rig, skeleton=cfg.skeleton)
    res = reconstruct_all(sub, mv, cfg, progress)
    fps = _fps(lay, mv.t_ns)
    poses = Poses3D(
        fps=fps,
        frame_index=mv.frame_index,
        t_ns=mv.t_ns,
        joint_names=mv.joint_names,
        parents=np.asarray(mv.parents),
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
    if len(n) and n.max() == 0:
        log.warning(
            "nobody was triangulated in %d frames of %d cameras: check that the calibration belongs to "
            "these cameras and is in metres (calibrate-run import --scale-to-m), and that the detections "
            "are of this recording",
            len(n),
            len(sub),
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
        np.asarray(skeleton_from_names(p.joint_names).parents if p.parents is None else p.parents),
        confidence=p.score,
        std_m=p.std_m,
        config=cfg.tracker,
        calibration_sha256=p.calibration_sha256,
    )
    tf.save(lay.tracks)
    log.info("greedy tracker: %d tracks over %d frames", tf.n_tracks, tf.n_frames)
    return lay.tracks
