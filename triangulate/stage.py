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
from collections.abc import Iterable
from contextlib import closing
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calibrate.camera import CameraRig
from calibrate.checks import rig_warnings
from capture.session import SessionLayout, require
from core.config import as_config
from core.errors import FormatError
from core.progress import Progress
from keypoints.detections import Detections
from keypoints.skeletons import (
    CANONICAL,
    Skeleton,
    convert,
    get_skeleton,
    load_skeleton_toml,
    whole_body,
)
from triangulate.checks import check_frame_order, detection_warnings, no_detection_warning, span_warnings
from triangulate.chunks import (
    AUTO,
    ChunkRunner,
    NpzRows,
    PartStore,
    StreamConfig,
    file_stamp,
    hash_key,
    parts_dir,
    remove_output,
)
from triangulate.poses3d import Poses3D
from triangulate.reconstruct import FrameReconstructor, TriangulateConfig

log = logging.getLogger(__name__)


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


@dataclass
class _CameraMeta:
    """What the 3D stages need of one camera's detections file before reading its rows."""

    camera: str
    path: Path
    skeleton: str
    frame_index: np.ndarray  # (n,)
    t_ns: np.ndarray  # (n,)
    n_people: int
    n_joints: int
    reader: NpzRows | None = None
    det: Detections | None = None  # the whole file, where it was loaded whole
    seen: bool = False  # any detection read so far
    n_frames: int = -1  # rows of the file (frame_index and t_ns are released once a streamed plan is made)

    def __post_init__(self) -> None:
        if self.n_frames < 0:
            self.n_frames = len(self.frame_index)

    def rows(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """xy_px (b-a,P,J,2) and score (b-a,P,J) of rows [a, b) as float32."""
        if self.det is not None:
            return self.det.xy_px[a:b], self.det.score[a:b]
        assert self.reader is not None
        xy = self.reader.rows("xy_px", a, b).astype(np.float32, copy=False)
        return xy, self.reader.rows("score", a, b).astype(np.float32, copy=False)


def _camera_meta(path: Path, cam: str, stream: bool) -> _CameraMeta:
    """Read one detections file's header arrays (streamed) or the whole file; check names and shapes."""
    if not stream:
        d = Detections.load(path)
        meta = _CameraMeta(
            d.camera, path, d.skeleton, d.frame_index, d.t_ns, d.max_people, d.xy_px.shape[2], det=d
        )
    else:
        from core.fileio import check_schema, npz_str

        r = NpzRows(path)
        need = ("schema", "camera", "skeleton", "frame_index", "t_ns", "xy_px", "score")
        missing = [k for k in need if k not in r.names]
        if missing:
            r.close()
            raise FormatError(
                path,
                missing[0],
                f"required keys {missing} are missing.",
                "See keypoints/detections.py for the detections file layout.",
            )
        check_schema(r.full("schema"), "detections", (1,), path)
        small = {k: r.full(k) for k in ("camera", "skeleton")}
        fi = np.asarray(r.full("frame_index"), np.int64)
        t = np.asarray(r.full("t_ns"), np.int64)
        xy_shape, _ = r.header("xy_px")
        sc_shape, _ = r.header("score")
        try:
            J = get_skeleton(npz_str(small, "skeleton")).n_joints
        except KeyError as e:
            r.close()
            raise FormatError(path, "skeleton", str(e)) from None
        T = len(fi)
        cam_name = npz_str(small, "camera")
        for name, shape, want in (
            ("t_ns", t.shape, (T,)),
            ("xy_px", xy_shape, (T, None, J, 2)),
            ("score", sc_shape, (T, None, J)),
        ):
            ok = len(shape) == len(want) and all(
                w is None or w == s for w, s in zip(want, shape, strict=True)
            )
            if not ok or (len(shape) > 1 and shape[1] != xy_shape[1]):
                r.close()
                wants = tuple("P" if w is None else w for w in want)
                raise FormatError(
                    path,
                    name,
                    f"camera '{cam_name}': expected shape {wants} (T={T} frames), got {tuple(shape)}.",
                    "Every array of a detections file has one row per frame; rewrite the file.",
                )
        meta = _CameraMeta(cam_name, path, npz_str(small, "skeleton"), fi, t, int(xy_shape[1]), J, reader=r)
    if meta.camera != cam:
        raise FormatError(
            path,
            "camera",
            f"the file says camera '{meta.camera}' but is named after '{cam}'.",
            "Rename the file or fix its 'camera' field.",
        )
    check_frame_order(meta, path)  # type: ignore[arg-type]  # frame_index, t_ns, camera
    return meta


@dataclass
class DetectionPlan:
    """How the cameras' detection rows land on the common frame axis (:func:`plan_detections`).

    ``frames (T,)`` the reference frame numbers, ``t_ns (T,)`` their times; per camera ``rows[c]``
    the file rows used and ``pos[c]`` their positions on the axis (both increasing)."""

    cameras: tuple[str, ...]
    rig: CameraRig
    metas: list[_CameraMeta]
    skel: Skeleton
    frames: np.ndarray
    t_ns: np.ndarray
    rows: list[np.ndarray]
    pos: list[np.ndarray]
    offsets_frames: dict[str, float]
    n_people: int

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    def close(self) -> None:
        for m in self.metas:
            if m.reader is not None:
                m.reader.close()

    def chunk(self, a: int, b: int) -> MultiViewDetections:
        """The detections of axis positions [a, b): converted, undistorted, (C,b-a,P,J,...)."""
        C, J = len(self.cameras), self.skel.n_joints
        xy = np.full((C, b - a, self.n_people, J, 2), np.nan)
        sc = np.zeros((C, b - a, self.n_people, J))
        for ci, m in enumerate(self.metas):
            lo, hi = np.searchsorted(self.pos[ci], [a, b])
            if hi <= lo:
                continue
            rows = self.rows[ci][lo:hi]
            r0, r1 = int(rows[0]), int(rows[-1]) + 1
            bxy, bsc = m.rows(r0, r1)
            bxy, bsc = bxy[rows - r0], bsc[rows - r0]
            b19, s19 = convert(bxy, bsc, m.skeleton, self.skel)
            s19 = np.where(np.isfinite(s19), s19, 0.0)
            p = self.pos[ci][lo:hi] - a
            xy[ci, p, : m.n_people] = self.rig[ci].undistort_px(b19)
            sc[ci, p, : m.n_people] = s19
            if not m.seen:
                m.seen = bool((np.isfinite(bxy[..., 0]) & (np.nan_to_num(bsc) > 0)).any())
        return MultiViewDetections(
            self.cameras,
            self.frames[a:b],
            self.t_ns[a:b],
            xy,
            sc,
            self.offsets_frames,
            self.skel.joint_names,
            self.skel.parents,
        )


def _check_rates(metas: list[_CameraMeta]) -> None:
    """Cameras with timestamps at different frame rates cannot be matched by frame number."""
    rates = {}
    for m in metas:
        t = m.t_ns[m.t_ns != 0]
        if len(t) > 2 and (np.diff(m.frame_index[m.t_ns != 0]) > 0).all():
            per_frame = np.diff(t) / np.diff(m.frame_index[m.t_ns != 0])
            rates[m.camera] = 1e9 / float(np.median(per_frame))
    if len(rates) > 1:
        lo, hi = min(rates.values()), max(rates.values())
        if hi > 1.05 * lo:
            raise FormatError(
                metas[0].path.parent,
                None,
                "the cameras run at different frame rates ("
                + ", ".join(f"{c} {r:.2f} fps" for c, r in rates.items())
                + "): frames are matched by frame number, which would pair different instants.",
                "Resample the detections to one frame rate (or record at one rate) before the 3D stages.",
            )


def plan_detections(
    layout: SessionLayout,
    rig: CameraRig,
    apply_sync: bool = True,
    skeleton: str = "body19",
    stream: bool = True,
) -> DetectionPlan:
    """Check every ``keypoints/<cam>.npz`` against the rig and put the cameras' frames on one axis.

    With ``stream`` only the frame numbers and timestamps are read now; :meth:`DetectionPlan.chunk`
    reads the rows of a time chunk (memory bounded by the chunk, not the session). See
    :func:`load_detections` for the alignment."""
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
    metas = [_camera_meta(layout.detections(c), c, stream) for c in cams]
    if stream:  # a camera with no detection at all is said once its rows were read (empty_camera_warnings)
        warns = span_warnings(metas)  # type: ignore[arg-type]
    else:
        warns = detection_warnings([m.det for m in metas if m.det is not None])
    for w in warns:
        log.warning("%s", w)
    _check_rates(metas)
    shifts = {}
    if apply_sync:
        fps_hint = None
        dt = np.diff(metas[0].t_ns)
        dt = dt[dt > 0]
        if len(dt):
            fps_hint = float(1e9 / np.median(dt))
        shifts = sync_shifts(layout, cams, fps_hint)
    keep, mapped = [], []
    for c, d in zip(cams, metas, strict=True):
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
    P = max(d.n_people for d in metas)
    if custom is not None:
        skel = custom
    elif skeleton == "whole_body":
        skel = whole_body([d.skeleton for d in metas])
    else:
        skel = get_skeleton(skeleton)
    t_ns = np.zeros(T, np.int64)
    have_t = np.zeros(T, bool)
    rows_l, pos_l = [], []
    small = np.int32 if max(T, *(m.n_frames for m in metas)) < 2**31 else np.int64  # an hour: 4 MB per camera
    for ci in range(len(cams)):
        r = np.flatnonzero(keep[ci])
        rows_l.append(r.astype(small))
        pos_l.append(np.searchsorted(frames, mapped[ci][r]).astype(small))
    # timestamps: unshifted cameras first (the reference's clock), then shifted ones moved onto it
    for ci in sorted(range(len(cams)), key=lambda i: cams[i] in shifts):
        d, k, pos = metas[ci], keep[ci], pos_l[ci]
        t_c = d.t_ns[k]
        if cams[ci] in shifts and len(t_c) > 1:
            period_ns = float(np.median(np.diff(d.t_ns))) if d.n_frames > 1 else 0.0
            t_c = np.where(t_c != 0, t_c + np.rint((mapped[ci][k] - d.frame_index[k]) * period_ns), 0)
        new = ~have_t[pos] & (t_c != 0)
        t_ns[pos[new]] = t_c[new]
        have_t[pos[new]] = True
    offsets = {c: shifts[c].offset_frames for c in shifts}
    if stream:  # the rows and positions above replace the files' frame numbers and times (an hour: 17 MB)
        for m in metas:
            m.frame_index = m.t_ns = np.zeros(0, np.int64)
    return DetectionPlan(tuple(cams), rig.subset(cams), metas, skel, frames, t_ns, rows_l, pos_l, offsets, P)


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

    The whole session in memory; :func:`plan_detections` + :meth:`DetectionPlan.chunk` read it in
    time chunks (:func:`iter_detection_chunks`).
    """
    plan = plan_detections(layout, rig, apply_sync, skeleton, stream=False)
    return plan.rig, plan.chunk(0, plan.n_frames)


def iter_detection_chunks(
    layout: SessionLayout,
    rig: CameraRig,
    chunk_frames: int,
    apply_sync: bool = True,
    skeleton: str = "body19",
):
    """Yield ``(rig, MultiViewDetections)`` of consecutive time chunks of ``chunk_frames`` frames, each
    read from the files as it is needed (the streaming form of :func:`load_detections`, for trackers
    that step frame by frame)."""
    plan = plan_detections(layout, rig, apply_sync, skeleton, stream=True)
    try:
        for a in range(0, plan.n_frames, max(int(chunk_frames), 1)):
            yield plan.rig, plan.chunk(a, min(a + chunk_frames, plan.n_frames))
    finally:
        plan.close()


def session_fps(layout: SessionLayout, t_ns: np.ndarray) -> float:
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


def session_chunk_s(layout: SessionLayout, stream: StreamConfig) -> float:
    """Seconds per chunk a 3D stage walking as ``stream`` says uses on this session (0 = the whole
    session into the single file). ``"auto"`` streams a session of more than ``STREAM_ABOVE_FRAMES``
    frames (:meth:`StreamConfig.seconds`), counted in the detections files (the camera with the most
    frames; ``triangulate/poses3d`` where there are none), so every stage and the runner, which must know
    the output's path before the stage runs, decide the same for one session."""
    if stream.chunk_s != AUTO:
        return float(stream.chunk_s)
    n, t_ns = 0, np.zeros(0, np.int64)
    files = [layout.detections(c) for c in layout.detection_cameras()]
    if not files and layout.poses3d.exists():
        files = [layout.poses3d]
    for f in files:
        try:
            with NpzRows(f) as r:
                rows = r.header("frame_index")[0][0]
                if rows > n:
                    n, t_ns = rows, r.full("t_ns")
        except (FormatError, KeyError):  # the stage itself reports an unreadable file
            continue
    if not files and parts_dir(layout.poses3d).is_dir():
        index = PartStore(parts_dir(layout.poses3d), "poses3d").load_index()
        meta = index.get("meta", {})
        return stream.seconds(int(meta.get("n_frames", 0)), float(meta.get("fps", 0.0)))
    return stream.seconds(n, session_fps(layout, t_ns))


def _reconstructor(rig: CameraRig, cameras: tuple[str, ...], joint_names, config: TriangulateConfig):
    order = None
    if config.match.camera_order is not None:
        bad = [c for c in config.match.camera_order if c not in cameras]
        if bad:
            raise ValueError(
                f"match.camera_order names cameras {bad} that have no detections; cameras: {list(cameras)}"
            )
        order = np.asarray([cameras.index(c) for c in config.match.camera_order])
    return FrameReconstructor(
        rig.projection_matrices(), rig.fundamental_matrices(), config, order, joint_names
    )


def reconstruct_all(
    rig: CameraRig,
    mv: MultiViewDetections | Iterable[MultiViewDetections],
    config: TriangulateConfig,
    progress: Progress | None = None,
    rec: FrameReconstructor | None = None,
    done: int = 0,
    total: int | None = None,
) -> dict[str, np.ndarray]:
    """Run association + triangulation on every frame of ``mv`` (or of consecutive blocks of frames, read
    one at a time). Returns padded (T,P3,J,...) arrays."""
    blocks = [mv] if isinstance(mv, MultiViewDetections) else mv
    out: list = []
    cameras, J = (), 0
    for b in blocks:
        cameras, J = b.cameras, len(b.joint_names)
        rec = rec or _reconstructor(rig, b.cameras, b.joint_names, config)
        for t in range(len(b.frame_index)):
            out.append(rec(b.xy_px[:, t], b.score[:, t]))
            if progress is not None:
                progress("triangulate", done + len(out), total or len(b.frame_index))
    T = len(out)
    P3 = max([len(f.xyz_m) for f in out], default=0)
    res = {
        "xyz_m": np.full((T, P3, J, 3), np.nan),
        "score": np.zeros((T, P3, J)),
        "reproj_err_px": np.full((T, P3, J), np.nan),
        "n_views": np.zeros((T, P3, J), np.int16),
        "std_m": np.full((T, P3, J), np.nan),
        "reproj_err_cam_px": np.full((T, P3, J, len(cameras)), np.nan),
    }
    for t, f in enumerate(out):
        m = len(f.xyz_m)
        for k in res:
            res[k][t, :m] = getattr(f, k)
        out[t] = None  # each frame's arrays are freed once copied
    return res


def _people_log(xyz_m: np.ndarray) -> np.ndarray:
    return np.isfinite(xyz_m).all(-1).any(-1).sum(1)


def _nobody_warning(n_frames: int, n_cams: int) -> None:
    log.warning(
        "nobody was triangulated in %d frames of %d cameras: check that the calibration belongs to "
        "these cameras and is in metres (calibrate-run import --scale-to-m), and that the detections "
        "are of this recording",
        n_frames,
        n_cams,
    )


def triangulate_session(
    session_dir: str | os.PathLike,
    config: TriangulateConfig | dict | None = None,
    progress: Progress | None = None,
    executor: ChunkRunner | None = None,
) -> Path:
    """Association (Alg. 1) + robust DLT for every frame of a session; writes ``triangulate/poses3d.npz``
    (streamed: ``triangulate/poses3d.parts/``, resumable; ``Poses3D.load`` of ``poses3d.npz`` reads
    either). ``executor`` runs the chunks ``config.stream.workers`` at a time
    (``pipeline.executors.chunk_runner``: processes or Ray); without one they run in this process."""
    cfg = as_config(TriangulateConfig, config)
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
    cfg = replace(cfg, stream=replace(cfg.stream, chunk_s=session_chunk_s(lay, cfg.stream)))
    if cfg.stream.chunk_s > 0:
        return _triangulate_chunked(lay, rig, cfg, progress, executor)
    sub, mv = load_detections(lay, rig, skeleton=cfg.skeleton)
    res = reconstruct_all(sub, mv, cfg, progress)
    poses = _poses3d(
        res,
        session_fps(lay, mv.t_ns),
        rig,
        sub.names,
        frame_index=mv.frame_index,
        t_ns=mv.t_ns,
        joint_names=mv.joint_names,
        parents=mv.parents,
    )
    remove_output(lay.poses3d)
    poses.save(lay.poses3d)
    n = _people_log(res["xyz_m"])
    log.info(
        "triangulated %d frames from %d cameras: %.2f people per frame (max %d)",
        len(n),
        len(sub),
        float(n.mean()) if len(n) else 0.0,
        int(n.max()) if len(n) else 0,
    )
    if len(n) and n.max() == 0:
        _nobody_warning(len(n), len(sub))
    return lay.poses3d


def _poses3d(
    res: dict, fps: float, rig: CameraRig, cameras, *, frame_index, t_ns, joint_names, parents
) -> Poses3D:
    """The per-frame poses of frames ``frame_index`` from ``reconstruct_all``'s arrays ``res``."""
    return Poses3D(
        fps=fps,
        frame_index=frame_index,
        t_ns=t_ns,
        joint_names=joint_names,
        parents=np.asarray(parents),
        calibration_sha256=rig.sha256(),
        cameras=tuple(cameras),
        **res,
    )


def _triangulate_chunked(
    lay: SessionLayout,
    rig: CameraRig,
    cfg: TriangulateConfig,
    progress: Progress | None,
    executor: ChunkRunner | None,
) -> Path:
    """The streaming form: one poses3d part per ``cfg.stream.chunk_s`` of frames, resumable."""
    plan = plan_detections(lay, rig, skeleton=cfg.skeleton, stream=True)
    try:
        fps = session_fps(lay, plan.t_ns)
        step = max(int(round(cfg.stream.chunk_s * fps)), 1)
        T = plan.n_frames
        chunks = [(a, min(a + step, T)) for a in range(0, T, step)] or [(0, 0)]
        key = hash_key(
            [
                "poses3d",
                repr(_without_run_settings(cfg)),  # the result depends on neither the processes nor Ray
                rig.sha256(),
                [file_stamp(m.path) for m in plan.metas],
                lay.session_toml.read_bytes() if lay.session_toml.exists() else b"",
            ]
        )
        if lay.poses3d.exists():
            lay.poses3d.unlink()
        store = PartStore(parts_dir(lay.poses3d), "poses3d")
        todo = set(store.open(key, chunks, {"fps": fps, "n_frames": T}))
        if len(todo) < len(chunks):
            log.info(
                "triangulate: resuming, %d of %d chunks already done", len(chunks) - len(todo), len(chunks)
            )
        n_sum, n_max, n_frames = 0, 0, 0
        # closing: a kill (Ctrl-C) between parts stops the workers now (queued chunks cancelled, a Ray
        # started here shut down), not when the generator is collected
        parts = _triangulate_chunks(lay, plan, rig, cfg, chunks, todo, store, fps, key, progress, executor)
        with closing(parts):
            for i, n in parts:
                store.commit(i)
                n_sum, n_max, n_frames = (
                    n_sum + int(n.sum()),
                    max(n_max, int(n.max(initial=0))),
                    n_frames + len(n),
                )
        store.finish()
        for m in plan.metas:
            if not m.seen and len(todo) == len(chunks):
                log.warning("%s", no_detection_warning(m.camera, m.n_frames))
        log.info(
            "triangulated %d frames (%d new) from %d cameras in %d chunks: %.2f people per frame (max %d)",
            T,
            n_frames,
            len(plan.cameras),
            len(chunks),
            n_sum / max(n_frames, 1),
            n_max,
        )
        if n_frames and n_max == 0 and len(todo) == len(chunks):
            _nobody_warning(n_frames, len(plan.cameras))
    finally:
        plan.close()
    return lay.poses3d


def _without_run_settings(cfg: TriangulateConfig) -> TriangulateConfig:
    """``cfg`` with ``workers`` and ``executor`` at their defaults: how the chunks ran, not what they are."""
    return replace(cfg, stream=StreamConfig(chunk_s=cfg.stream.chunk_s))


def _triangulate_chunks(lay, plan, rig, cfg, chunks, todo, store, fps, key, progress, executor):
    """Triangulate the chunks ``todo`` into their part files; yields (chunk, people per frame) as each is
    written: in this process, or with ``executor`` (worker processes or Ray tasks, each worker planning
    the session once, ``_chunk_worker``)."""
    T = plan.n_frames
    for i, (_, b) in enumerate(chunks):
        if i not in todo and progress is not None:
            progress("triangulate", b, T)
    if len(todo) <= 1 or executor is None:
        rec = _reconstructor(plan.rig, plan.cameras, plan.skel.joint_names, cfg)
        for i in sorted(todo):
            yield i, _triangulate_chunk(plan, rig, cfg, rec, chunks[i], fps, store.part_path(i), progress)
        return
    jobs = {i: (str(lay.root), cfg, chunks[i], fps, str(store.part_path(i)), key) for i in sorted(todo)}
    done = sum(b - a for i, (a, b) in enumerate(chunks) if i not in todo)
    with closing(executor(_chunk_worker, jobs, cfg.stream.workers)) as results:
        for i, (n, seen) in results:
            for m, s in zip(plan.metas, seen, strict=True):  # for the "camera without detections" check
                m.seen = m.seen or s
            done += chunks[i][1] - chunks[i][0]
            if progress is not None:
                progress("triangulate", done, T)
            yield i, n


BLOCK_FRAMES = 250  # frames of detections read at a time within a chunk


def _triangulate_chunk(plan, rig, cfg, rec, chunk, fps: float, part: Path, progress=None) -> np.ndarray:
    """Frames [a, b) of the plan triangulated into the part file ``part``; returns the people per frame."""
    a, b = chunk
    # the detections are read in blocks of BLOCK_FRAMES: their padded arrays (cameras x frames x the
    # session's most people x joints) would otherwise be most of the stage's memory
    blocks = (plan.chunk(f, min(f + BLOCK_FRAMES, b)) for f in range(a, max(b, a + 1), BLOCK_FRAMES))
    res = reconstruct_all(plan.rig, blocks, cfg, progress, rec, done=a, total=plan.n_frames)
    skel = plan.skel
    _poses3d(
        res,
        fps,
        rig,
        plan.cameras,
        frame_index=plan.frames[a:b],
        t_ns=plan.t_ns[a:b],
        joint_names=skel.joint_names,
        parents=skel.parents,
    ).save(part)
    return _people_log(res["xyz_m"])


_WORKER_PLAN: dict = {}  # per worker process: the session's detection plan and reconstructor


def _chunk_worker(
    session_dir: str, cfg: TriangulateConfig, chunk, fps: float, part: str, key: str = ""
) -> tuple[np.ndarray, list[bool]]:
    """One chunk in a worker process: triangulate frames [a, b) and write its part; returns the people
    per frame and, per camera, whether it has had a detection in this process.

    The plan is kept for the next chunk of the same run (``key``: the parts' key, which changes with the
    detection files, the rig and the settings); a Ray worker outlives the run, so another run or changed
    files plan anew (the old files closed)."""
    run = (session_dir, key, repr(cfg))
    if _WORKER_PLAN.get("key") != run:
        if "plan" in _WORKER_PLAN:
            _WORKER_PLAN.pop("plan").close()
        _WORKER_PLAN.clear()
        lay = SessionLayout(session_dir)
        rig = CameraRig.load(lay.rig_toml)
        plan = plan_detections(lay, rig, skeleton=cfg.skeleton, stream=True)
        rec = _reconstructor(plan.rig, plan.cameras, plan.skel.joint_names, cfg)
        _WORKER_PLAN.update(key=run, rig=rig, plan=plan, rec=rec)
    plan = _WORKER_PLAN["plan"]
    n = _triangulate_chunk(plan, _WORKER_PLAN["rig"], cfg, _WORKER_PLAN["rec"], chunk, fps, Path(part))
    return n, [m.seen for m in plan.metas]
