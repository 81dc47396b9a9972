"""The live 3D wiring of ``capture-run --live``: every synchronised frame set is a batch of one frame.

``capture`` records and synchronises (``capture.live.LiveRunner`` runs stages on each frame set); the
stages themselves use the later stages' functions, so they live here, on top of the stage order:
``capture-run`` is :func:`main` of this module (``capture.cli`` with these stages injected),
``python -m roomcap.pipeline.live`` the same.

Stages (``STAGES``, one line each, built by the same functions the batch stages call):

- ``keypoints``: :class:`roomcap.keypoints.pipeline.KeypointPipeline` on the frame set's images;
- ``triangulate``: the detections converted to ``body19`` and undistorted (``step.outputs["kp_px"]``,
  ``["kp_score"]``, shared with the tracker) and :class:`roomcap.triangulate.reconstruct.FrameReconstructor`
  (``poses3d``);
- ``track``: one step of the recursive particle filter (seed ch. 5,
  :class:`roomcap.track.particle.ParticleTracker`) per frame set, at the set's time ``t_ns``: a track's
  identity is given once and never changed; its state is what the next step needs, so the cost of a
  step does not grow with the session's length. Estimates are appended to the live track file in
  chunks of ``CHUNK_FRAMES`` frames. A source that jumps in time (:func:`jump_reason`: a looping file
  camera starts again, the time goes back, the frame set index restarts) starts a new segment: the
  tracker's clock starts again at the set's time and the people found after it keep their ids where they
  are the same (:mod:`roomcap.track.particle_jumps`); the jump is recorded in the track file's index
  (``meta["clock_jumps"]``, :func:`load_live_jumps`), the runner's summary line and the live page. A set
  less than ``LATE_SET_S`` behind the last one came late, out of order: skipped.

The live track file is ``track/live.npz`` (``SessionLayout.live_tracks``), written in the chunked layout
of the streamed batch stages (:mod:`roomcap.triangulate.chunks`, schema ``parts/1``) as an appendable store::

    track/live.parts/index.json      {"schema": "parts/1", "kind": "tracks", "key", "appendable": true,
                                      "chunks": [[0, 50], [50, 100], ...],
                                      "parts": {"<i>": {"file", "size", "sha256"}}, "meta", "complete"}
                                     meta["clock_jumps"]: [{"frame_set", "row", "t_ns_before",
                                      "t_ns_after", "why", "loops"}, ...] (absent: no jump, older files)
    track/live.parts/part_00000.npz  a whole ``tracks/1`` file of the chunk's frame sets

Each part is written atomically and never rewritten, then entered (its chunk, size and sha256) in one
atomic rewrite of the index, so a reader always sees whole, listed files; ``complete`` is set when the
recording ends (:meth:`LiveTrackWriter.close`). The common loaders read it like a streamed batch track:
``TrackFile.load("track/live.npz")``, ``iter_parts`` part by part, a part that does not match the index
is an error naming it (a live part cannot be rebuilt). It is kept apart from ``track/tracks.npz`` /
``track/tracks.parts/``, which the batch track stage owns and replaces: a later ``reprocess`` of the
session leaves the live result as it was. Sessions recorded in the older layout hold
``track/live/index.json`` (schema ``live_tracks/1``) and ``part_NNNNNN.npz``; :func:`load_live_tracks`
still reads them.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from roomcap.capture.cli import make_main
from roomcap.capture.config import CaptureConfig, auto_reduce
from roomcap.capture.live import LiveStep, Stage
from roomcap.capture.session import SessionLayout
from roomcap.capture.sources import full_res_px, jpeg_size
from roomcap.capture.streamcopy import delivers_jpeg
from roomcap.core.errors import FormatError
from roomcap.core.memory import TRIM_EVERY, release_free_memory
from roomcap.pipeline.live_outputs import Outputs, load_rig
from roomcap.triangulate.chunks import PartStore, hash_key, parts_dir

# the stages' packages (the 2D models, scipy and numba under the tracker: about 1 s of imports here) are
# imported where a stage is built, which capture-run does on the live thread while the cameras already
# record (capture.live.LiveRunner), so that a short recording is not held up by them
if TYPE_CHECKING:
    from roomcap.calibrate.camera import CameraRig
    from roomcap.keypoints.pipeline import KeypointPipeline
    from roomcap.track.particle_config import ParticleConfig
    from roomcap.track.trackfile import TrackFile

log = logging.getLogger(__name__)

CHUNK_FRAMES = 50  # frame sets per part of the live track file (2 s at 25 Hz)
LIVE_DIR = "live.parts"  # under the session's track folder: the parts of SessionLayout.live_tracks
LEGACY_LIVE_DIR = "live"  # the live track folder of sessions recorded before the parts/1 layout
LEGACY_SCHEMA = "live_tracks/1"
SOURCE = "pipeline.live (track.particle, one step per frame set)"
# a set whose time lies behind the last one's by less than this, from no restarted source, came late (out of
# order under load); a clock that goes back further jumped (a camera restarted, its clock reset)
LATE_SET_S = 1.0
JUMPS_KEY = "clock_jumps"  # the index meta's list of the clock's jumps (absent in older files: none)


@dataclass
class LiveContext:
    cfg: CaptureConfig
    layout: SessionLayout
    rig: CameraRig | None  # when cams.yaml names a calibration
    particle: ParticleConfig | None = None  # the live tracker's settings (default ParticleConfig())
    chunk_frames: int = CHUNK_FRAMES
    keypoint_workers: int = 0  # the 2D stage's worker threads, each taking the next camera (0 = the cores)


def live_dir(layout: SessionLayout) -> Path:
    """The live track's parts folder, ``track/live.parts/`` (the track file path is
    ``layout.live_tracks``, ``track/live.npz``)."""
    return parts_dir(layout.live_tracks)


def legacy_live_dir(layout: SessionLayout) -> Path:
    """``track/live/``: where sessions recorded in the older layout hold their live track."""
    return layout.tracks.parent / LEGACY_LIVE_DIR


# ----------------------------------------------------------------------------- stages (batch functions)


def warm_keypoints(pipe: KeypointPipeline, size_wh: tuple[int, int]) -> None:
    """Run the pipeline's whole chain once on a blank image of the cameras' size before the first frame set:
    the detector, the crop/pyramid code and the pose model on one box (onnxruntime's and OpenCV's first
    calls allocate and pick kernels: the first live set cost 1.4 s instead of 0.9 s, measured). The
    streams and timings are reset after."""
    w, h = size_wh
    img = np.full((h, w, 3), 127, np.uint8)
    pipe([img])
    pipe.pose_on_boxes([img], [np.array([[0.4 * w, 0.2 * h, 0.6 * w, 0.9 * h, 1.0]])])
    pipe.reset_streams()
    pipe.stage_s.clear()
    pipe.n_detected = pipe.n_tracked = 0
    for m in pipe.models:
        m.run_s, m.run_cpu_s, m.n_runs = 0.0, 0.0, 0


def scale_result(res, reduce: int):
    """A 2D result (``FrameResult``: boxes (P,5), xy_px (P,J,2)) found on an image decoded at 1/``reduce``
    size, in the full-size image's pixels (:func:`roomcap.capture.sources.full_res_px`)."""
    if reduce == 1:
        return res
    boxes = np.array(res.boxes, np.float32, copy=True)
    if boxes.size:
        boxes[:, :4] = full_res_px(boxes[:, :4], reduce)
    return replace(res, boxes=boxes, xy_px=full_res_px(np.asarray(res.xy_px), reduce).astype(np.float32))


def _keypoints(ctx: LiveContext) -> Stage:
    """The batch keypoints stage's loop (keypoints.video) on one frame set: cams.yaml's live preset, the
    cameras as streams (each person's crop follows from the last processed set, the detector every
    ``detect_every`` sets and when someone is lost), the cameras spread over the cores in groups, each with
    its own pipeline and share of the onnxruntime threads; every pipeline warmed before the first set.
    A camera that hands out JPEGs (MJPEG) has only the frames taken here decoded, each group decoding its
    own, at 1/``live.decode_reduce`` size (:func:`roomcap.capture.config.auto_reduce`); the keypoints are
    mapped back to full-size pixels (:func:`scale_result`)."""
    import cv2

    from roomcap.keypoints.pipeline import KeypointPipeline
    from roomcap.pipeline.config import KeypointsConfig

    try:
        settings = KeypointsConfig(preset=ctx.cfg.live.preset, skeleton="body19")
    except FormatError as e:
        raise FormatError(ctx.cfg.path, "live.preset", str(e).split(": ", 2)[-1]) from None
    conf = settings.detector
    cams = list(ctx.cfg.names)
    n_workers = max(1, min(ctx.keypoint_workers or os.cpu_count() or 1, len(cams)))
    if n_workers > 1:  # each worker's share of the onnxruntime threads, as the batch stage
        threads = max(1, (conf.runtime.threads or os.cpu_count() or 1) // n_workers)
        conf = replace(conf, runtime=replace(conf.runtime, threads=threads))
        # OpenCV's own pool on top of the workers' threads made its small calls slower (keypoints.video)
        cv2.setNumThreads(1)
    # one pipeline per camera (it follows that camera's people), run by n_workers threads: a worker that is
    # done with a camera takes the next, the cameras that took longest in the last set first, so neither
    # core waits on the other while a busy camera is still running (fixed groups of cameras did)
    pipes = {c: KeypointPipeline(conf) for c in cams}
    last_s = dict.fromkeys(cams, 0.0)
    sizes = [c.resolution for c in ctx.cfg.cameras if c.resolution]
    w, h = sizes[0] if sizes else (1920, 1080)
    setting = ctx.cfg.live.decode_reduce
    # warmed at the size the 2D will see: JPEG cameras' frames are decoded reduced, decoded ones taken as
    # they are (or shrunk when decode_reduce is set)
    r = auto_reduce(w, h, setting) if any(delivers_jpeg(c) for c in ctx.cfg.cameras) else setting or 1
    for pipe in pipes.values():
        warm_keypoints(pipe, (-(-w // r), -(-h // r)))
    pool = ThreadPoolExecutor(n_workers, thread_name_prefix="live-keypoints") if n_workers > 1 else None
    reduce_of: dict[str, int] = {}  # camera -> the factor its JPEGs are decoded at (from its first frame)
    decode_ms = [0.0, 0]  # decoding the taken frames: ms in all, frames

    def reduce_for(cam: str, f) -> int:
        if f.jpeg is None or f.image is not None:  # already decoded (a file's H.264): taken as it is
            return setting or 1
        if cam not in reduce_of:
            reduce_of[cam] = auto_reduce(*jpeg_size(f.jpeg), setting)
        return reduce_of[cam]

    def run_camera(cam: str, step: LiveStep):
        f = step.frameset.frames[cam]
        t0 = time.perf_counter()
        k = reduce_for(cam, f)
        img = f.decoded(k)
        decode_ms[0] += (time.perf_counter() - t0) * 1e3
        decode_ms[1] += 1
        step.outputs["decoded"][cam] = (k, img)
        (res,) = pipes[cam]([img], streams=[cam])
        last_s[cam] = time.perf_counter() - t0
        return scale_result(res, k)

    def stage(step: LiveStep) -> None:
        frames = step.frameset.frames
        present = [c for c in cams if frames.get(c) is not None and frames[c].has_image]
        present.sort(key=last_s.__getitem__, reverse=True)
        # the decoded images, for the live view's camera previews (no second decoding of the same JPEG)
        step.outputs["decoded"] = {}
        if pool is None:
            dets = {c: run_camera(c, step) for c in present}
        else:
            dets = dict(zip(present, pool.map(run_camera, present, [step] * len(present)), strict=True))
        step.outputs["detections"] = {c: dets[c] for c in step.cameras if c in dets}

    def close() -> None:
        if pool is not None:
            pool.shutdown(wait=False)

    stage.pipes = list(pipes.values())  # type: ignore[attr-defined]  # the bench reads their timings
    stage.close = close  # type: ignore[attr-defined]
    stage.decode_ms = decode_ms  # type: ignore[attr-defined]  # [ms decoding taken frames, frames]
    stage.reduce_of = reduce_of  # type: ignore[attr-defined]
    return stage


def _rig(ctx: LiveContext, what: str) -> CameraRig:
    if ctx.rig is None:
        raise RuntimeError(f"{what} needs a calibration: set 'calibration: path/to/rig.toml' in cams.yaml")
    return ctx.rig.subset(list(ctx.cfg.names))


def frame_arrays(step: LiveStep, rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
    """The frame set's detections as body19, undistorted: kp (C,P,J,2) px (NaN = missing), sc (C,P,J).
    Computed once per step (``step.outputs["kp_px"]``, ``["kp_score"]``)."""
    if "kp_px" in step.outputs:
        return step.outputs["kp_px"], step.outputs["kp_score"]
    from roomcap.keypoints.skeletons import CANONICAL, convert

    dets = step.outputs.get("detections", {})
    J = CANONICAL.n_joints
    P = max([len(d.xy_px) for d in dets.values()], default=0)
    C = len(step.cameras)
    xy = np.full((C, P, J, 2), np.nan, np.float32)
    sc = np.zeros((C, P, J), np.float32)
    for c, cam in enumerate(step.cameras):
        d = dets.get(cam)
        if d is None or not len(d.xy_px):
            continue
        dxy, dsc = np.asarray(d.xy_px), np.asarray(d.score)
        skel = getattr(d, "skeleton", CANONICAL.id)
        if skel != CANONICAL.id:
            dxy, dsc = convert(dxy, dsc, skel, CANONICAL)
        xy[c, : len(dxy)] = rig[cam].undistort_px(dxy)
        sc[c, : len(dxy)] = dsc
    step.outputs["kp_px"], step.outputs["kp_score"] = xy, sc
    return xy, sc


def _triangulate(ctx: LiveContext) -> Stage:
    from roomcap.keypoints.skeletons import CANONICAL
    from roomcap.triangulate.reconstruct import FrameReconstructor

    rig = _rig(ctx, "triangulation")
    rec = FrameReconstructor(
        rig.projection_matrices(), rig.fundamental_matrices(), None, None, CANONICAL.joint_names
    )

    def stage(step: LiveStep) -> None:
        xy, sc = frame_arrays(step, rig)
        step.outputs["poses3d"] = rec(xy.astype(np.float64), sc)

    return stage


class LiveTrackWriter:
    """Appends per-frame estimates to the live track ``path`` (``track/live.npz``) as the parts of an
    appendable :class:`roomcap.triangulate.chunks.PartStore` in ``track/live.parts/`` (see the module doc).
    Only the open part's frames are held in memory; the folder is started at the first part."""

    def __init__(
        self, path: Path, fps: float, calibration_sha256: str = "", chunk_frames: int = CHUNK_FRAMES
    ):
        from roomcap.track.trackfile import SCHEMA

        self.path, self.fps, self.sha = Path(path), float(fps), calibration_sha256
        self.folder = parts_dir(self.path)
        self.chunk = max(1, int(chunk_frames))
        self.store = PartStore(self.folder, SCHEMA)
        self.started = False
        self.n_frames = 0
        self._rows: list[tuple] = []  # (frame index, t_ns, track.particle_types.FrameEstimate)
        self.jumps: list[dict] = []  # the clock's jumps (JUMPS_KEY of the index's meta)

    def add_jump(self, jump: dict) -> None:
        """Record a jump of the clock before the next frame added (its ``row`` in the track file is set
        here); entered in the index with the part that holds that row."""
        self.jumps.append({**jump, "row": self.n_frames + len(self._rows)})

    def add(self, frame_index: int, t_ns: int, est) -> None:
        self._rows.append((int(frame_index), int(t_ns), est))
        if len(self._rows) >= self.chunk:
            self.flush()

    def _start(self) -> None:
        key = hash_key(["live", self.fps, self.sha, self.chunk, time.time_ns()])  # one key per recording
        meta = {"fps": self.fps, "chunk_frames": self.chunk, "source": SOURCE}
        self.store.start_appending(key, meta)
        self.started = True

    def flush(self) -> None:
        """Write the open part (if any), then enter it in the index."""
        if not self._rows:
            return
        from roomcap.keypoints.skeletons import CANONICAL
        from roomcap.track.trackfile import TrackFile

        rows, self._rows = self._rows, []
        ids = sorted({int(i) for _, _, e in rows for i in e.track_id})
        col = {tid: k for k, tid in enumerate(ids)}
        T, K, J = len(rows), len(ids), CANONICAL.n_joints
        xyz = np.full((T, K, J, 3), np.nan, np.float32)
        std = np.full((T, K, J), np.nan, np.float32)
        conf = np.zeros((T, K, J), np.float32)
        flags = np.zeros((T, K, J), np.uint8)
        for t, (_, _, e) in enumerate(rows):
            if len(e.track_id):
                ks = np.asarray([col[int(i)] for i in e.track_id])
                xyz[t, ks], std[t, ks], conf[t, ks], flags[t, ks] = e.xyz_m, e.std_m, e.confidence, e.flags
        tf = TrackFile(
            fps=self.fps,
            frame_index=np.asarray([r[0] for r in rows], np.int64),
            t_ns=np.asarray([r[1] for r in rows], np.int64),
            track_id=np.asarray(ids, np.int64),
            joint_names=CANONICAL.joint_names,
            parents=np.asarray(CANONICAL.parents),
            xyz_m=xyz,
            confidence=conf,
            std_m=std,
            flags=flags,
            calibration_sha256=self.sha,
            source=SOURCE,
        )
        if not self.started:
            self._start()
        tf.save(self.store.next_part_path)  # atomic; listed in the index only once whole
        self.store.append(T, {JUMPS_KEY: list(self.jumps)} if self.jumps else None)
        self.n_frames += T

    def close(self) -> None:
        """The recording ended: the open part written and the index marked complete."""
        self.flush()
        if self.started:
            self.store.finish({"n_frames": self.n_frames})


def load_live_tracks(path: str | Path) -> TrackFile:
    """The live track file: a session folder, ``track/live.npz`` or its folder ``track/live.parts/`` (read by
    :meth:`TrackFile.load`, parts checked against their size and sha256), or the ``track/live/`` folder
    of a session recorded by an earlier version (``index.json`` schema ``live_tracks/1``: its parts
    joined in time, columns = every track id, sorted). A part missing or unreadable raises a clear error
    (a reader never sees a partial part)."""
    from roomcap.track.trackfile import TrackFile

    path = Path(path)
    if (path / "track").is_dir():  # a session folder: its live track, else an older session's folder
        lay = SessionLayout(path)
        new = lay.live_tracks.exists() or live_dir(lay).is_dir() or not legacy_live_dir(lay).is_dir()
        path = lay.live_tracks if new else legacy_live_dir(lay)
    idx_path = path / "index.json"
    if path.is_dir() and path.suffix != ".parts":
        if not idx_path.exists():
            raise FileNotFoundError(
                f"{idx_path} not found: no live track parts written yet (run capture-run --live)"
            )
        try:
            index = json.loads(idx_path.read_text(encoding="utf-8"))
            files = [str(p["file"]) for p in index["parts"]] if index.get("schema") == LEGACY_SCHEMA else None
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise FormatError(idx_path, None, f"cannot read the live track index ({e}).") from None
        if files is None:
            raise FormatError(
                idx_path,
                "schema",
                f"expected {LEGACY_SCHEMA!r} (an older live track folder), got {index.get('schema')!r}.",
            )
        if not files:
            raise FormatError(idx_path, "parts", "lists no parts.")
        return TrackFile.concat([TrackFile.load(path / f) for f in files])
    if path.suffix == ".parts":
        path = path.with_suffix(".npz")
    if not path.exists() and not parts_dir(path).is_dir():
        raise FileNotFoundError(
            f"{path} not found (nor {parts_dir(path)}): no live track parts written yet "
            "(run capture-run --live)"
        )
    return TrackFile.load(path)


def jump_reason(clock: dict, fs) -> str:
    """Why the frame set ``fs`` does not continue the live track's clock (``clock``: the last set's
    ``last`` time, ``index`` and ``loops``), or ``""``: its index restarted (the synchroniser started
    again), a source started again from its beginning (a looping file camera: its timestamps go on, its
    scene does not), or its time went back; ``"late"`` when its time lies behind the last set's by less
    than :data:`LATE_SET_S` with none of these: a late set out of order (an incomplete set a slow camera's
    frame made after the newer set), skipped."""
    if clock["last"] is None:
        return ""
    if clock["index"] is not None and fs.index < clock["index"]:
        return "frame index restarted"
    if fs.loops > clock["loops"]:
        return "a source looped"
    if fs.t_ns <= clock["last"]:
        return "late" if clock["last"] - fs.t_ns < LATE_SET_S * 1e9 else "time went back"
    return ""


def load_live_jumps(path: str | Path) -> list[dict]:
    """The jumps of the clock the live track recorded (a session folder, ``track/live.npz`` or its
    ``track/live.parts/``): one dict per jump, ``frame_set`` (the first set after it), ``row`` (its row in
    the live track file), ``t_ns_before``, ``t_ns_after`` and ``why``; ``[]`` for a track without jumps or
    written before they were recorded (older files, the ``track/live/`` layout)."""
    path = Path(path)
    if (path / "track").is_dir():
        path = SessionLayout(path).live_tracks
    folder = path if path.suffix == ".parts" else parts_dir(path)
    try:
        index = json.loads((folder / "index.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        return []
    except (OSError, ValueError) as e:
        raise FormatError(folder / "index.json", None, f"cannot read the live track index ({e}).") from None
    jumps = (index.get("meta") or {}).get(JUMPS_KEY, [])
    return [dict(j) for j in jumps] if isinstance(jumps, list) else []


def _track(ctx: LiveContext) -> Stage:
    from roomcap.track.particle import ParticleTracker
    from roomcap.track.particle_io import focal_lengths

    rig = _rig(ctx, "tracking")
    fps = max(c.fps or 30.0 for c in ctx.cfg.cameras)
    tracker = ParticleTracker(rig.projection_matrices(), focal_lengths(rig), fps, ctx.particle)
    writer = LiveTrackWriter(ctx.layout.live_tracks, fps, rig.sha256(), ctx.chunk_frames)
    clock = {"t0": None, "last": None, "index": None, "loops": 0, "n": 0, "late": 0}

    def stage(step: LiveStep) -> None:
        fs = step.frameset
        t_ns = int(fs.t_ns)
        if clock["t0"] is None:
            clock["t0"] = t_ns
        why = jump_reason(clock, fs)
        if why == "late":
            clock["late"] += 1
            log.info(
                "live track: frame set %d lies %.3f s behind the last one (late, out of order); skipped",
                fs.index,
                (clock["last"] - t_ns) / 1e9,
            )
            return
        if why:  # a new segment: the tracker's clock starts again here, identities carried over
            jump = {
                "frame_set": int(fs.index),
                "t_ns_before": clock["last"],
                "t_ns_after": t_ns,
                "why": why,
                "loops": int(fs.loops),
            }
            log.warning(
                "live track: the clock jumped before frame set %d (%s, %+.3f s); a new track segment",
                fs.index,
                why,
                (t_ns - clock["last"]) / 1e9,
            )
            tracker.new_segment(clock["n"])
            writer.add_jump(jump)
            step.outputs["jump"] = jump
            clock["t0"] = t_ns
        clock["last"], clock["index"] = t_ns, int(fs.index)
        clock["loops"] = max(clock["loops"], fs.loops)
        xy, sc = frame_arrays(step, rig)
        est = tracker.step(xy, sc, clock["n"], t_s=(t_ns - clock["t0"]) / 1e9)
        clock["n"] += 1
        if clock["n"] % TRIM_EVERY == 0:  # hours of steps: the fragmented heap's free pages back
            release_free_memory()
        writer.add(fs.index, t_ns, est)
        step.outputs["tracks"] = est
        if step.outputs.get("final"):
            writer.close()

    stage.writer = writer  # type: ignore[attr-defined]  # the bench and tests read the parts it wrote
    stage.tracker = tracker  # type: ignore[attr-defined]
    stage.clock = clock  # type: ignore[attr-defined]  # "late": late sets out of order, skipped
    stage.close = writer.close  # type: ignore[attr-defined]  # the runner calls it when the recording ends
    return stage


# the live pipeline: one line per stage, same functions as the batch stages
STAGES: dict[str, Callable[[LiveContext], Stage]] = {
    "keypoints": _keypoints,
    "triangulate": _triangulate,
    "track": _track,
}


def build_stages(cfg: CaptureConfig, layout: SessionLayout) -> tuple[dict[str, Stage], dict[str, str]]:
    """The stages ``cfg.live.stages`` names, for :class:`roomcap.capture.live.LiveRunner`; a stage that
    cannot be
    built (no calibration, a package missing) is left out with a warning. Returns (stages, errors)."""
    ctx = LiveContext(cfg, layout, load_rig(cfg))
    out: dict[str, Stage] = {}
    errors: dict[str, str] = {}
    for name in cfg.live.stages:
        try:
            out[name] = STAGES[name](ctx)
        except Exception as e:  # noqa: BLE001 - any failure to build a stage: skip it, say why
            log.warning("live: stage %r is not available (%s); skipping it", name, e)
            errors[name] = str(e)
    return out, errors


def _load_detections(path):
    """``keypoints/<cam>.npz`` for ``capture-run sync`` (keypoints.detections.Detections.load, imported
    when asked)."""
    from roomcap.keypoints.detections import Detections

    return Detections.load(path)


_main = make_main(build_stages, Outputs(), _load_detections)


def main(argv: list[str] | None = None) -> int:
    """``capture-run``. Run as the command (``argv`` None: the console script, ``python -m``), it leaves
    without the interpreter's teardown once everything is written and closed (the recorder's segments and
    session.toml, the live track, the outputs): unloading the 2D models' sessions and the tracker's
    compiled kernels took 0.6-0.9 s of a 3 s recording's exit, measured."""
    code = _main(argv)
    if argv is None:
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
