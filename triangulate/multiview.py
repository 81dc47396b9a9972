"""A session's detections on one frame axis: the detection loader of the 3D stages and the session's rate.

:func:`plan_detections` checks every ``keypoints/<cam>.npz`` against the rig and puts the cameras' frames
on one axis (``capture-run sync``'s offsets applied); :func:`load_detections` reads them whole as a
:class:`MultiViewDetections` (converted to the 3D skeleton and undistorted), :func:`iter_detection_chunks`
chunk by chunk. :func:`session_fps` is the session's frame rate and :func:`session_chunk_s` the chunk
length the 3D stages use on it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import SessionLayout
from roomcap.core.errors import FormatError
from roomcap.core.fileio import check_schema, npz_str
from roomcap.core.timebase import clock_fps, frame_rate_hz
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import (
    CANONICAL,
    Skeleton,
    convert,
    get_skeleton,
    load_skeleton_toml,
    whole_body,
)
from roomcap.triangulate.checks import check_frame_order, detection_warnings, span_warnings
from roomcap.triangulate.chunks import (
    AUTO,
    NpzRows,
    PartStore,
    StreamConfig,
    parts_dir,
)

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
        stamped = m.t_ns != 0
        if stamped.sum() > 2 and (np.diff(m.frame_index[stamped]) > 0).all():
            rate = frame_rate_hz(m.t_ns, m.frame_index)
            if rate is not None:
                rates[m.camera] = rate
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
    cams = _calibrated_cameras(layout, rig)
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
        shifts = sync_shifts(layout, cams, frame_rate_hz(metas[0].t_ns))
    keep, mapped = _frames_on_reference_axis(cams, metas, shifts)
    frames = np.unique(np.concatenate([m[k] for m, k in zip(mapped, keep, strict=True)]))
    T = len(frames)
    if custom is not None:
        skel = custom
    elif skeleton == "whole_body":
        skel = whole_body([d.skeleton for d in metas])
    else:
        skel = get_skeleton(skeleton)
    rows_l, pos_l = [], []
    small = np.int32 if max(T, *(m.n_frames for m in metas)) < 2**31 else np.int64  # an hour: 4 MB per camera
    for ci in range(len(cams)):
        r = np.flatnonzero(keep[ci])
        rows_l.append(r.astype(small))
        pos_l.append(np.searchsorted(frames, mapped[ci][r]).astype(small))
    t_ns = _reference_times(cams, metas, shifts, keep, mapped, pos_l, T)
    offsets = {c: shifts[c].offset_frames for c in shifts}
    if stream:  # the rows and positions above replace the files' frame numbers and times (an hour: 17 MB)
        for m in metas:
            m.frame_index = m.t_ns = np.zeros(0, np.int64)
    P = max(d.n_people for d in metas)
    return DetectionPlan(tuple(cams), rig.subset(cams), metas, skel, frames, t_ns, rows_l, pos_l, offsets, P)


def _calibrated_cameras(layout: SessionLayout, rig: CameraRig) -> list[str]:
    """The cameras with both detections and a calibration, in the rig's order (at least two)."""
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
    return cams


def _frames_on_reference_axis(
    cams: list[str], metas: list[_CameraMeta], shifts: dict[str, FrameShift]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per camera, which of its frames are kept and the reference frame each shows (its sync shift)."""
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
    return keep, mapped


def _reference_times(cams, metas, shifts, keep, mapped, pos_l, T: int) -> np.ndarray:
    """``t_ns`` of the reference frames: unshifted cameras first (the reference's clock), then shifted
    ones moved onto it."""
    t_ns = np.zeros(T, np.int64)
    have_t = np.zeros(T, bool)
    for ci in sorted(range(len(cams)), key=lambda i: cams[i] in shifts):
        d, k, pos = metas[ci], keep[ci], pos_l[ci]
        t_c = d.t_ns[k]
        if cams[ci] in shifts and len(t_c) > 1:
            period_ns = float(np.median(np.diff(d.t_ns))) if d.n_frames > 1 else 0.0
            t_c = np.where(t_c != 0, t_c + np.rint((mapped[ci][k] - d.frame_index[k]) * period_ns), 0)
        new = ~have_t[pos] & (t_c != 0)
        t_ns[pos[new]] = t_c[new]
        have_t[pos[new]] = True
    return t_ns


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


def session_rate(layout: SessionLayout, t_ns: np.ndarray) -> float:
    """The session's frame rate: stated in ``session.toml``, else estimated from the timestamps (the
    median interval), else 25."""
    if layout.session_toml.exists():
        try:
            fps = layout.read_meta().get("fps")
            if fps:
                return float(fps)
        except FormatError as e:
            log.warning("session.toml unreadable (%s); estimating fps from timestamps", e)
    return frame_rate_hz(t_ns[t_ns > 0]) or 25.0


def session_fps(layout: SessionLayout, t_ns: np.ndarray) -> float:
    """The rate of the 3D stages' clock (:func:`session_rate`; for snapshots, a rate below
    ``SPARSE_BELOW_HZ``, ``SNAPSHOT_CLOCK_FPS``: a time-lapse is a sparse clock, not a slow camera, and
    its gaps in seconds say what can be linked, :func:`roomcap.core.timebase.clock_fps`)."""
    return clock_fps(session_rate(layout, t_ns))


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
