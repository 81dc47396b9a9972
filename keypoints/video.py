"""2D keypoints over the videos of a session: threaded decoding, batched inference, resumable writing.

``run_session(session_dir)`` reads ``raw/<cam>.*`` (``capture.session.SessionLayout``) and writes
``keypoints/<cam>.npz`` (``keypoints.detections.Detections``, body19). ``run_videos({cam: path}, out_dir)``
does the same for explicit videos, e.g. the Pose2Sim demo layout ``<trial>/videos/cam01.mp4`` (camera name
= file stem, which matches the Qualisys ``serial`` names ``cam01``..).

- one decoding thread per camera feeds a small queue (OpenCV releases the GIL while decoding);
- each step takes the next frame of every camera and runs them as one batch through the pipeline (one
  detector run over all cameras, one pose run over all person crops);
- results are written every ``chunk_frames`` frames to ``keypoints/.<cam>.parts/NNNNNNNN.npz`` (atomic);
  a killed run resumes after the last complete chunk (same model set and sha256, else it starts over);
  at the end the chunks are merged into ``<cam>.npz`` and removed;
- a video that stops decoding before its announced frame count keeps the frames done; the frame that
  failed is logged, returned in ``RunReport.decode_errors`` and saved as ``decode_error_frame``;
- a video whose size differs from the calibration's: a difference of at most 16 px (codec padding,
  e.g. 1080 vs 1088) is logged, anything else (or width and height swapped: a rotated video) raises;
- bottom-up models run with ``KeypointPipelineConfig(keep_maps=True)`` also store their confidence maps and
  PAFs for the tracker's observation model: ``maps_f16 (T,h,w,C)`` float16 and ``maps_to_img (T,2,3)``
  (map px -> image px) as extra keys of the detections file.
"""

from __future__ import annotations

import csv
import logging
import os
import queue
import shutil
import threading
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import VIDEO_SUFFIXES, SessionLayout
from roomcap.core.errors import FormatError, RoomcapError
from roomcap.core.fileio import load_npz, save_npz
from roomcap.core.progress import Progress
from roomcap.core.timebase import timestamps_backwards
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.pipeline import KeypointPipeline
from roomcap.keypoints.pipeline_config import FrameResult, KeypointPipelineConfig
from roomcap.keypoints.presets import settings_for
from roomcap.keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)

SIZE_TOLERANCE_PX = 16
_END = object()


@dataclass
class RunReport:
    paths: dict[str, Path] = field(default_factory=dict)
    frames: dict[str, int] = field(default_factory=dict)
    decode_errors: dict[str, tuple[int, str]] = field(default_factory=dict)
    resumed_from: dict[str, int] = field(default_factory=dict)
    stage_s: dict[str, float] = field(default_factory=dict)
    model_s: float = 0.0
    # CPU time of the pipelines' threads: in their calls, and in session.run within them (the work itself,
    # without the waits of threads that share the cores; all of session.run's when it runs on one thread)
    pipeline_cpu_s: float = 0.0
    model_cpu_s: float = 0.0
    wall_s: float = 0.0


class VideoDecodeError(RoomcapError, RuntimeError):
    pass


# ----------------------------------------------------------------------------- reading


def read_frames_csv(path: Path) -> dict[int, int]:
    """``raw/<cam>.frames.csv`` -> {frame_index: t_ns}. A frame listed twice, or frames out of order or
    stamped back in time, are a :class:`FormatError` naming the camera and the frames (before any frame
    is decoded), never a row silently dropped or a clock that runs backwards into the detections."""
    path = Path(path)
    cam = path.name.removesuffix(".frames.csv")
    out: dict[int, int] = {}
    prev = None
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            i = int(row["frame_index"])
            if prev is not None and i <= prev:
                what = "is listed twice" if i in out else f"comes after frame {prev}"
                raise FormatError(
                    path,
                    "frame_index",
                    f"camera '{cam}': frame {i} {what}; the rows must number the video's frames in order.",
                    "Run `capture-run repair` on the session, or sort the file by frame_index.",
                )
            out[i] = int(row["t_ns"])
            prev = i
    back = timestamps_backwards(
        np.fromiter(out, np.int64, len(out)), np.fromiter(out.values(), np.int64, len(out))
    )
    if back is not None:
        raise FormatError(
            path,
            "t_ns",
            f"camera '{cam}': {back}.",
            "Fix the camera's clock in this file (a clock reset or a restarted camera?), or set its t_ns "
            "to 0 to align the cameras by frame number.",
        )
    return out


def session_segments(path: Path) -> list[Path]:
    """The video segments of a recorder's camera folder ``raw/<cam>/`` (or its ``index.ffconcat``)."""
    path = Path(path)
    if path.suffix == ".ffconcat":
        path = path.parent
    if not path.is_dir():
        return []
    ok = VIDEO_SUFFIXES + (".h264", ".h265")
    return sorted(p for p in path.glob("seg_*") if p.suffix.lower() in ok)


class SegmentCapture:
    """``cv2.VideoCapture`` over a recorder's segment folder ``raw/<cam>/seg_*.mp4``, as one video.

    Only the calls FrameReader makes: isOpened, get (FRAME_COUNT summed over segments; FPS, size of
    the first), grab, read, release.
    """

    def __init__(self, files: list[Path]):
        self.files = list(files)
        self._k = 0
        self._cap = cv2.VideoCapture(str(self.files[0])) if self.files else None
        self._first = {}
        if self._cap is not None and self._cap.isOpened():
            for prop in (cv2.CAP_PROP_FPS, cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
                self._first[prop] = self._cap.get(prop)
            n = 0
            for f in self.files:
                c = cv2.VideoCapture(str(f))
                n += max(int(c.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
                c.release()
            self._first[cv2.CAP_PROP_FRAME_COUNT] = float(n)

    def isOpened(self) -> bool:  # noqa: N802 (the cv2 name)
        return self._cap is not None and self._cap.isOpened()

    def get(self, prop: int) -> float:
        return float(self._first.get(prop, 0.0))

    def _advance(self) -> bool:
        self._cap.release()
        self._k += 1
        if self._k >= len(self.files):
            self._cap = None
            return False
        self._cap = cv2.VideoCapture(str(self.files[self._k]))
        if not self._cap.isOpened():
            raise VideoDecodeError(f"{self.files[self._k]}: segment cannot be opened (corrupt?)")
        return True

    def grab(self) -> bool:
        while self._cap is not None:
            if self._cap.grab():
                return True
            if not self._advance():
                return False
        return False

    def read(self):
        while self._cap is not None:
            ok, img = self._cap.read()
            if ok:
                return ok, img
            if not self._advance():
                break
        return False, None

    def release(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def open_capture(path: Path):
    """A ``cv2.VideoCapture`` for a video file, or a :class:`SegmentCapture` for a segment folder."""
    segs = session_segments(path)
    if segs:
        return SegmentCapture(segs)
    if Path(path).is_dir():
        raise VideoDecodeError(
            f"{path}: a folder without recorded segments (seg_*.mp4); pass a video file or a "
            "session's raw/<cam>/ segment folder."
        )
    return cv2.VideoCapture(str(path))


class FrameReader(threading.Thread):
    """Decodes one video in a thread into a bounded queue of (frame_index, t_ns, image).

    Ends with ``_END``; a decoding failure before the announced frame count puts ``("error", index, msg)``.
    """

    def __init__(
        self,
        path: Path,
        start: int = 0,
        stop: int | None = None,
        timestamps: dict[int, int] | None = None,
        maxsize: int = 4,
    ):
        super().__init__(daemon=True)
        self.path = Path(path)
        self.cap = open_capture(self.path)
        if not self.cap.isOpened():
            raise VideoDecodeError(
                f"{path}: cannot be opened as a video (missing codec or not a video file)."
            )
        self.n_frames = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT)) or None
        self.fps = float(self.cap.get(cv2.CAP_PROP_FPS)) or 30.0
        self.size_wh = (
            int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        )
        # rotation metadata (a phone's portrait video): OpenCV turns the frames upright and reports the
        # upright size; check_size names it when that size does not fit the calibration
        rot = float(self.cap.get(cv2.CAP_PROP_ORIENTATION_META) or 0.0)
        self.rotation_deg = int(rot) % 360 if np.isfinite(rot) and abs(rot) <= 360 else 0
        self.variable_rate = False  # set when the container's timestamps depart from index / fps
        self.start_index = start
        self.stop_index = stop
        self.timestamps = timestamps
        self.q: queue.Queue = queue.Queue(maxsize)
        self.decode_s = 0.0
        self._halt = threading.Event()

    def run(self) -> None:
        i = 0
        try:
            while i < self.start_index:  # grab() skips without converting; exact where seeking is not
                if not self.cap.grab():
                    break
                i += 1
            while not self._halt.is_set() and (self.stop_index is None or i < self.stop_index):
                t = time.perf_counter()
                ok, img = self.cap.read()
                self.decode_s += time.perf_counter() - t
                if not ok:
                    if self.n_frames is not None and i < self.n_frames:
                        self.q.put(("error", i, f"decoding stopped at frame {i} of {self.n_frames}"))
                    break
                if self.timestamps:
                    t_ns = self.timestamps.get(i, -1)
                else:
                    t_ns = self._container_t_ns(i)
                self.q.put((i, t_ns, img))
                i += 1
        except Exception as e:  # report any decoder failure as the frame it happened at
            self.q.put(("error", i, f"{type(e).__name__}: {e}"))
        finally:
            self.q.put(_END)
            self.cap.release()

    def _container_t_ns(self, i: int) -> int:
        """The frame's time from the container (relative to the first frame read), which is index / fps
        for a constant frame rate. A variable-frame-rate video (phones, screen recorders) departs from that
        by more than half a frame: its own timestamps are used and a warning says so once."""
        nominal = int(round(i / self.fps * 1e9))
        pos_ms = self.cap.get(cv2.CAP_PROP_POS_MSEC)
        if not np.isfinite(pos_ms) or (pos_ms <= 0 and i > 0):
            return nominal
        if not hasattr(self, "_t0_ns"):
            self._t0_ns = int(round(pos_ms * 1e6)) - nominal
        t_ns = int(round(pos_ms * 1e6)) - self._t0_ns
        if abs(t_ns - nominal) > 0.5e9 / self.fps:
            if not self.variable_rate:
                log.warning(
                    "%s: variable frame rate (frame %d at %.3f s, %.3f s at the nominal %.2f fps); "
                    "using the video's own timestamps",
                    self.path,
                    i,
                    t_ns / 1e9,
                    nominal / 1e9,
                    self.fps,
                )
            self.variable_rate = True
        return t_ns if self.variable_rate else nominal

    def halt(self) -> None:
        self._halt.set()
        while True:  # unblock a put() waiting on a full queue
            try:
                self.q.get_nowait()
            except queue.Empty:
                break


# ----------------------------------------------------------------------------- chunks


class ChunkWriter:
    """Accumulates per-frame results of one camera and writes them in atomic chunk files."""

    def __init__(
        self, out_dir: Path, cam: str, skeleton: str, model: str, model_sha256: str, chunk_frames: int
    ):
        self.dir = out_dir / f".{cam}.parts"
        self.cam, self.skeleton, self.model, self.sha = cam, skeleton, model, model_sha256
        self.chunk_frames = chunk_frames
        self.J = get_skeleton(skeleton).n_joints
        self.buf: list[tuple[int, int, FrameResult]] = []
        self.write_s = 0.0

    def existing(self) -> list[Path]:
        """Chunks from an earlier run of the same models; others are removed."""
        if not self.dir.is_dir():
            return []
        parts = sorted(self.dir.glob("[0-9]*.npz"))
        good = []
        for p in parts:
            try:
                d = load_npz(p)
                same = (
                    str(d["model"]) == self.model
                    and str(d["model_sha256"]) == self.sha
                    and str(d["skeleton"]) == self.skeleton
                )
            except (FormatError, KeyError):
                same = False
            if not same:
                log.info("%s: discarding chunks of another run (%s)", self.cam, p)
                shutil.rmtree(self.dir)
                return []
            good.append(p)
        return good

    def next_frame(self) -> int:
        parts = self.existing()
        if not parts:
            return 0
        return int(load_npz(parts[-1])["frame_index"][-1]) + 1

    def add(self, frame_index: int, t_ns: int, res: FrameResult) -> None:
        self.buf.append((frame_index, t_ns, res))
        if len(self.buf) >= self.chunk_frames:
            self.flush()

    def flush(self) -> None:
        if not self.buf:
            return
        t = time.perf_counter()
        P = max([len(r.boxes) for _, _, r in self.buf] + [1])
        T = len(self.buf)
        xy = np.full((T, P, self.J, 2), np.nan, np.float32)
        sc = np.zeros((T, P, self.J), np.float32)
        bx = np.full((T, P, 5), np.nan, np.float32)
        for k, (_, _, r) in enumerate(self.buf):
            n = len(r.boxes)
            xy[k, :n], sc[k, :n], bx[k, :n] = r.xy_px, r.score, r.boxes
        fi = np.array([f for f, _, _ in self.buf], np.int64)
        maps = {}
        if all(r.maps is not None for _, _, r in self.buf):  # bottom-up with keep_maps: for the tracker
            maps = {
                "maps_f16": np.stack([r.maps for _, _, r in self.buf]).astype(np.float16),
                "maps_to_img": np.stack([r.maps_to_img for _, _, r in self.buf]),
            }
        save_npz(
            self.dir / f"{fi[0]:08d}.npz",
            {
                **maps,
                "frame_index": fi,
                "t_ns": np.array([t for _, t, _ in self.buf], np.int64),
                "xy_px": xy,
                "score": sc,
                "boxes": bx,
                "model": self.model,
                "model_sha256": self.sha,
                "skeleton": self.skeleton,
            },
            compress=False,
        )
        self.buf = []
        self.write_s += time.perf_counter() - t

    def merge(self, dest: Path, image_size_wh, extra: dict) -> Detections:
        self.flush()
        parts = [load_npz(p) for p in sorted(self.dir.glob("[0-9]*.npz"))] if self.dir.is_dir() else []
        if not parts:
            det = Detections.empty(self.cam, self.skeleton, 0, 0, model=self.model, model_sha256=self.sha)
        else:
            P = max(p["xy_px"].shape[1] for p in parts)

            def pad(a, fill):
                width = [(0, 0)] * a.ndim
                width[1] = (0, P - a.shape[1])
                return np.pad(a, width, constant_values=fill)

            det = Detections(
                camera=self.cam,
                skeleton=self.skeleton,
                frame_index=np.concatenate([p["frame_index"] for p in parts]),
                t_ns=np.concatenate([p["t_ns"] for p in parts]),
                xy_px=np.concatenate([pad(p["xy_px"], np.nan) for p in parts]),
                score=np.concatenate([pad(p["score"], 0) for p in parts]),
                boxes=np.concatenate([pad(p["boxes"], np.nan) for p in parts]),
                model=self.model,
                model_sha256=self.sha,
                image_size_wh=image_size_wh,
                extra={
                    **extra,
                    **{
                        k: np.concatenate([p[k] for p in parts])
                        for k in ("maps_f16", "maps_to_img")
                        if all(k in p for p in parts)
                    },
                },
            )
        t = time.perf_counter()
        det.save(dest)
        self.write_s += time.perf_counter() - t
        if self.dir.is_dir():
            shutil.rmtree(self.dir)
        return det


# ----------------------------------------------------------------------------- checks


def check_size(
    cam: str, video_wh: tuple[int, int], calib_wh: tuple[int, int] | None, path: Path, rotation_deg: int = 0
) -> None:
    """Compare a video's frame size with its camera's calibrated size (see the module docstring).
    ``rotation_deg``: the video's rotation metadata (its frames are decoded upright)."""
    if calib_wh is None:
        return
    vw, vh = video_wh
    cw, ch = int(calib_wh[0]), int(calib_wh[1])
    if (vw, vh) == (cw, ch):
        return
    if abs(vw - cw) <= SIZE_TOLERANCE_PX and abs(vh - ch) <= SIZE_TOLERANCE_PX:
        log.warning(
            "camera %s: video %s is %dx%d, calibration %dx%d; within codec padding, keypoints are used "
            "as is (the origin is the top-left pixel in both)",
            cam,
            path,
            vw,
            vh,
            cw,
            ch,
        )
        return
    rotated = (
        f" Its rotation metadata says {rotation_deg} degrees, and its frames are read turned upright: "
        "calibrate from frames read the same way (or strip the metadata)."
        if rotation_deg % 180
        else ""
    )
    hint = (
        " Width and height are swapped: the video is rotated relative to the calibration; rotate it back "
        "or recalibrate." + rotated
        if (vw, vh) == (ch, cw)
        else " Record at the calibrated resolution, or recalibrate (or scale K) for this resolution."
    )
    raise FormatError(
        path, "size", f"camera '{cam}': video is {vw}x{vh} but the calibration says {cw}x{ch}.", hint.strip()
    )


def _calib_sizes(rig) -> dict[str, tuple[int, int]]:
    if rig is None:
        return {}
    if isinstance(rig, dict):
        return {k: tuple(v) for k, v in rig.items()}
    return {c.name: tuple(c.size_wh) for c in rig.cameras}


# ----------------------------------------------------------------------------- running


def run_videos(
    videos: dict[str, str | os.PathLike],
    out_dir: str | os.PathLike,
    config: KeypointPipelineConfig | str = "default",
    *,
    rig=None,
    chunk_frames: int = 50,
    max_frames: int | None = None,
    progress: Progress | None = None,
    timestamps: dict[str, Path] | None = None,
    pipeline: KeypointPipeline | None = None,
    camera_groups: int = 1,
) -> RunReport:
    """Run the 2D pipeline over videos ``{camera name: path}`` and write ``out_dir/<cam>.npz``.

    ``rig``: a ``CameraRig`` or ``{cam: (w, h)}`` to check video sizes against. ``max_frames``: stop after
    this many frames per camera. ``timestamps``: ``{cam: frames.csv}`` with per-frame ``t_ns``.
    ``camera_groups``: split the cameras into this many groups, each run by its own thread and pipeline with
    its share of the onnxruntime threads (the cameras spread over the cores).
    """
    t_wall = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if isinstance(config, str):
        config = settings_for(config)
    cams = list(videos)
    n_groups = 1 if pipeline is not None else max(1, min(camera_groups, len(cams)))
    if n_groups > 1:  # each group's share of the onnxruntime threads
        threads = max(1, (config.runtime.threads or os.cpu_count() or 1) // n_groups)
        config = replace(config, runtime=replace(config.runtime, threads=threads))
    pipe = pipeline or KeypointPipeline(config)
    pipe.reset_streams()
    for c in cams:
        if not Path(videos[c]).exists():
            raise FileNotFoundError(f"camera '{c}': video {videos[c]} does not exist.")
    writers = {
        c: ChunkWriter(out_dir, c, pipe.skeleton, pipe.model_id, pipe.model_sha256, chunk_frames)
        for c in cams
    }
    report = RunReport()
    readers = _open_readers(videos, writers, rig, timestamps, max_frames, report)
    totals = {
        c: readers[c].n_frames if max_frames is None else min(max_frames, readers[c].n_frames or max_frames)
        for c in cams
    }
    run = _GroupRun(
        videos, readers, writers, report, totals, {c: readers[c].start_index for c in cams}, progress
    )
    # the cameras spread over the cores: groups of cameras, each stepped by its own thread and pipeline
    # (onnxruntime, OpenCV and numpy release the GIL while they compute)
    groups = [cams[g::n_groups] for g in range(n_groups)]
    pipes = [pipe] + [KeypointPipeline(config) for _ in groups[1:]]
    run.run_all(groups, pipes)
    _merge_chunks(videos, readers, writers, report, out_dir, config.model_set)
    _stage_times(report, pipes, readers, writers)
    report.wall_s = time.perf_counter() - t_wall
    return report


def _open_readers(
    videos: dict[str, str | os.PathLike],
    writers: dict[str, ChunkWriter],
    rig,
    timestamps: dict[str, Path] | None,
    max_frames: int | None,
    report: RunReport,
) -> dict[str, FrameReader]:
    """A reader per camera, from the frame its written chunks end at (a resumed run), its size checked
    against the rig."""
    sizes = _calib_sizes(rig)
    readers: dict[str, FrameReader] = {}
    for c in videos:
        start = writers[c].next_frame()
        ts = read_frames_csv(Path(timestamps[c])) if timestamps and c in timestamps else None
        r = FrameReader(Path(videos[c]), start=start, stop=max_frames, timestamps=ts)
        check_size(c, r.size_wh, sizes.get(c), Path(videos[c]), r.rotation_deg)
        if start:
            log.info("camera %s: resuming at frame %d", c, start)
            report.resumed_from[c] = start
        readers[c] = r
    return readers


@dataclass
class _GroupRun:
    """What the camera groups share while they run: the readers and writers, the report, the progress."""

    videos: dict[str, str | os.PathLike]
    readers: dict[str, FrameReader]
    writers: dict[str, ChunkWriter]
    report: RunReport
    totals: dict[str, int | None]
    done: dict[str, int]
    progress: Progress | None
    lock: threading.Lock = field(default_factory=threading.Lock)  # the progress callback and the report
    stop: threading.Event = field(default_factory=threading.Event)  # set on an interruption: groups end

    def run_group(self, group: list[str], gpipe: KeypointPipeline) -> None:
        """Step one group's cameras a frame each per batch through its pipeline until their videos end."""
        live = list(group)
        while live and not self.stop.is_set():
            batch_cams, imgs, meta = [], [], []
            for c in list(live):
                item = self.readers[c].q.get()
                if item is _END:
                    live.remove(c)
                    continue
                if item[0] == "error":
                    _, fi, msg = item
                    with self.lock:
                        self.report.decode_errors[c] = (fi, msg)
                    log.warning(
                        "camera %s: %s (%s); keeping the %d frames before it", c, msg, self.videos[c], fi
                    )
                    continue
                batch_cams.append(c)
                imgs.append(item[2])
                meta.append(item[:2])
            if not imgs:
                continue
            results = gpipe(imgs, streams=batch_cams)
            for c, (fi, t_ns), res in zip(batch_cams, meta, results, strict=True):
                self.writers[c].add(fi, t_ns, res)
                self.done[c] += 1
                if self.progress is not None:
                    with self.lock:
                        self.progress(c, self.done[c], self.totals[c])

    def run_all(self, groups: list[list[str]], pipes: list[KeypointPipeline]) -> None:
        """Run every group in its own thread; Ctrl-C or a failed group stops the others (finished chunks
        stay)."""
        # OpenCV's own thread pool, on top of the groups' threads, made its small calls (pyrDown, warpAffine)
        # up to 4x slower on this 2-core machine: one OpenCV thread per group while they run
        n_groups = len(groups)
        cv_threads = cv2.getNumThreads()
        if n_groups > 1:
            cv2.setNumThreads(1)
        for r in self.readers.values():
            r.start()
        try:
            with ThreadPoolExecutor(n_groups) as pool:
                try:
                    for f in [
                        pool.submit(self.run_group, g, gp) for g, gp in zip(groups, pipes, strict=True)
                    ]:
                        f.result()
                except BaseException:  # Ctrl-C or a failed group: the other groups stop too
                    self.stop.set()
                    for r in self.readers.values():
                        r.halt()
                    raise
        finally:
            for r in self.readers.values():
                r.halt()
            cv2.setNumThreads(cv_threads)


def _merge_chunks(
    videos: dict[str, str | os.PathLike],
    readers: dict[str, FrameReader],
    writers: dict[str, ChunkWriter],
    report: RunReport,
    out_dir: Path,
    model_set: str,
) -> None:
    """Merge each camera's chunks into ``out_dir/<cam>.npz`` with the video's facts; the paths and frame
    counts into the report."""
    for c in videos:
        err = report.decode_errors.get(c, (-1, ""))
        extra = {
            "decode_error_frame": np.int64(err[0]),
            "video": str(videos[c]),
            "fps": np.float64(readers[c].fps),
            "model_set": model_set,
            "variable_frame_rate": np.bool_(readers[c].variable_rate),
            "rotation_deg": np.int64(readers[c].rotation_deg),
        }
        det = writers[c].merge(out_dir / f"{c}.npz", readers[c].size_wh, extra)
        report.paths[c] = out_dir / f"{c}.npz"
        report.frames[c] = det.n_frames


def _stage_times(
    report: RunReport,
    pipes: list[KeypointPipeline],
    readers: dict[str, FrameReader],
    writers: dict[str, ChunkWriter],
) -> None:
    """The report's times: seconds per stage (summed over the groups' pipelines), in decoding, writing and
    the models."""
    st: defaultdict[str, float] = defaultdict(float)
    for gp in pipes:
        for k, v in gp.stage_s.items():
            st[k] += v
    st["decode"] = sum(r.decode_s for r in readers.values())
    st["write"] = sum(w.write_s for w in writers.values())
    report.stage_s = dict(st)
    report.model_s = sum(gp.model_run_s() for gp in pipes)
    report.model_cpu_s = sum(gp.model_run_cpu_s() for gp in pipes)
    report.pipeline_cpu_s = sum(gp.call_cpu_s for gp in pipes)


def run_session(
    session_dir: str | os.PathLike,
    model_set: str = "default",
    cameras: list[str] | None = None,
    progress: Progress | None = None,
    config: KeypointPipelineConfig | None = None,
    rig=None,
    **kw,
) -> dict[str, Path]:
    """Keypoints for a session folder: ``raw/<cam>.*`` -> ``keypoints/<cam>.npz``. Returns ``{cam: path}``.

    The rig (``calib/rig.toml`` or the one session.toml points to) is loaded, when present and readable,
    to check video sizes; timestamps come from ``raw/<cam>.frames.csv`` when present.
    """
    lay = SessionLayout(session_dir)
    cams = cameras or lay.raw_cameras()
    if not cams:
        raise FileNotFoundError(f"no camera videos under {lay.raw_dir}; expected raw/<cam>.mp4.")
    videos = {c: lay.video(c) for c in cams}
    if rig is None and lay.rig_toml.exists():
        rig = CameraRig.load(lay.rig_toml)
    if rig is not None and not isinstance(rig, dict):
        missing = [c for c in cams if c not in rig.names]
        if missing:
            raise FormatError(
                lay.rig_toml,
                "cameras",
                f"cameras {missing} have videos but no calibration (rig cameras: {list(rig.names)}).",
                "Name videos raw/<rig camera name>.mp4.",
            )
    ts = {c: lay.find_frames_csv(c) for c in cams if lay.find_frames_csv(c) is not None}
    cfg = config or KeypointPipelineConfig(model_set=model_set)
    rep = run_videos(videos, lay.keypoints_dir, cfg, rig=rig, progress=progress, timestamps=ts, **kw)
    return rep.paths
