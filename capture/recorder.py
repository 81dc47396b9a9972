"""The recorder: one grabbing thread and one writer thread per camera, a session that survives a kill.

Layout written (see ``capture.session``)::

    <out>/session.toml                  written before the first frame (status "recording"),
                                        rewritten at the end (status "complete", timing, gaps)
    <out>/raw/<cam>/seg_000000.mp4      closed segments of ``segment_s`` seconds, each playable
    <out>/raw/<cam>/seg_000000.frames.csv  that segment's rows (the repair source)
    <out>/raw/<cam>/index.ffconcat      the closed segments as one video: cv2.VideoCapture opens it
    <out>/raw/<cam>.frames.csv          frame_index,t_ns,t_host_ns,sequence for every frame in the
                                        closed segments, appended as each segment closes

Kill safety: a segment is written under a hidden name, closed, fsynced, its rows written, then
renamed to ``seg_*`` and its rows appended to ``<cam>.frames.csv``. A ``kill -9`` therefore leaves
closed segments whose frames match the timestamp file exactly, and at most ``segment_s`` (plus the
queued frames) of video lost. ``repair_session`` removes the unfinished segment and rebuilds the
timestamp files from the per-segment rows.
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
import platform
import queue
import shutil
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from capture.config import CaptureConfig, redact_url
from capture.fileio import atomic_write_text, save_toml
from capture.grabber import END, Gap, Grabber
from capture.session import SESSION_SCHEMA, SESSION_VERSION, SessionLayout
from capture.sources import (
    Frame,
    FrameSource,
    SourceError,
    SourceInfo,
    host_now_ns,
    make_source,
    read_frames_csv,
)
from core.errors import RoomcapError
from core.redact import redact

log = logging.getLogger(__name__)

CSV_HEADER = "frame_index,t_ns,t_host_ns,sequence\n"
_FOURCC = {"mp4v": ("mp4v", ".mp4"), "mjpg": ("MJPG", ".avi"), "xvid": ("XVID", ".avi")}
_PART_PREFIX = ".part_"


class RecorderError(RoomcapError, RuntimeError):
    """The session cannot start (bad source, no disk space); nothing was written."""


# ----------------------------------------------------------------------------- segment writer


class SegmentWriter:
    """Writes one camera as closed, playable segments plus the per-frame timestamp file."""

    def __init__(
        self, cam_dir: Path, frames_csv: Path, codec: str, fps: float, segment_s: float, quality: int = 80
    ):
        self.dir = Path(cam_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.frames_csv = Path(frames_csv)
        self.codec = codec
        self.fps = float(fps) if fps and fps > 0 else 30.0
        self.segment_ns = int(segment_s * 1e9)
        self.quality = quality
        self.frames_written = 0
        self.segments = 0
        self._writer = None
        self._raw = None  # file object for on-device encoded streams
        self._part: Path | None = None
        self._final: Path | None = None
        self._rows: list[str] = []
        self._seg_t0 = 0
        self._shape = None
        self._closed: list[str] = []
        if not self.frames_csv.exists():
            atomic_write_text(self.frames_csv, CSV_HEADER)

    def _open_segment(self, frame: Frame) -> None:
        import cv2

        k = self.segments
        if frame.encoded is not None:
            ext = ".h265" if self.codec == "h265" else ".h264"  # Annex B elementary stream from the device
            self._final = self.dir / f"seg_{k:06d}{ext}"
            self._part = self.dir / f"{_PART_PREFIX}seg_{k:06d}{ext}"
            self._raw = open(self._part, "wb")
        else:
            fourcc, ext = _FOURCC[self.codec]
            h, w = frame.image.shape[:2]
            self._final = self.dir / f"seg_{k:06d}{ext}"
            self._part = self.dir / f"{_PART_PREFIX}seg_{k:06d}{ext}"
            if self.codec == "mjpg":  # OpenCV's own MJPEG writer honours the quality setting
                api, params = cv2.CAP_OPENCV_MJPEG, [cv2.VIDEOWRITER_PROP_QUALITY, self.quality]
            else:
                api, params = cv2.CAP_FFMPEG, []
            self._writer = cv2.VideoWriter(
                str(self._part), api, cv2.VideoWriter_fourcc(*fourcc), self.fps, (w, h), params
            )
            if not self._writer.isOpened():
                raise SourceError(
                    f"cannot open a {self.codec} video writer for {w}x{h} at {self.fps:g} fps "
                    f"({self._part}); pick another codec in cams.yaml ({list(_FOURCC)})."
                )
            self._shape = frame.image.shape
        self._seg_t0 = frame.t_ns
        self._rows = []

    def write(self, frame: Frame) -> None:
        need_new = self._part is None
        if not need_new and frame.t_ns - self._seg_t0 >= self.segment_ns:
            # on-device streams can only be cut at a keyframe
            need_new = frame.encoded is None or _is_keyframe(frame)
        if not need_new and frame.image is not None and frame.image.shape != self._shape:
            need_new = True
        if need_new:
            self.close_segment()
            self._open_segment(frame)
        if frame.encoded is not None:
            self._raw.write(frame.encoded)
        else:
            self._writer.write(frame.image)
        self._rows.append(
            f"{self.frames_written + len(self._rows)},{frame.t_ns},{frame.t_host_ns},{frame.sequence}\n"
        )

    def close_segment(self) -> None:
        if self._part is None:
            return
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._raw is not None:
            self._raw.close()
            self._raw = None
        with open(self._part, "rb+") as f:
            os.fsync(f.fileno())
        rows = "".join(self._rows)
        atomic_write_text(self._final.with_suffix(".frames.csv"), CSV_HEADER + rows)
        os.replace(self._part, self._final)
        self._closed.append(self._final.name)
        write_ffconcat(self.dir, self._closed)
        fd = os.open(self.frames_csv, os.O_WRONLY | os.O_APPEND)
        try:
            os.write(fd, rows.encode())  # one write: a kill leaves whole rows or none
            os.fsync(fd)
        finally:
            os.close(fd)
        self.frames_written += len(self._rows)
        self.segments += 1
        self._rows = []
        self._part = self._final = None

    def close(self) -> None:
        self.close_segment()


FFCONCAT = "index.ffconcat"


def write_ffconcat(cam_dir: Path, segments: list[str]) -> None:
    """``raw/<cam>/index.ffconcat``: the closed segments as one video for FFmpeg/OpenCV.

    ``cv2.VideoCapture(str(cam_dir / "index.ffconcat"))`` decodes every segment in order.
    """
    atomic_write_text(
        Path(cam_dir) / FFCONCAT, "ffconcat version 1.0\n" + "".join(f"file {n}\n" for n in segments)
    )


def _is_keyframe(frame: Frame) -> bool:
    return frame.keyframe


class WriterThread(threading.Thread):
    def __init__(self, cam: str, q: queue.Queue, writer: SegmentWriter):
        super().__init__(name=f"write-{cam}", daemon=True)
        self.cam, self.q, self.writer = cam, q, writer
        self.error: str = ""

    def run(self) -> None:
        try:
            while True:
                frame = self.q.get()
                if frame is END:
                    break
                self.writer.write(frame)
        except Exception as e:
            log.exception("%s: writer failed", self.cam)
            self.error = f"{type(e).__name__}: {e}"
            while self.q.get() is not END:  # keep draining so the grabber never blocks
                pass
        finally:
            self.writer.close()


# ----------------------------------------------------------------------------- recorder


def _versions(cfg: CaptureConfig) -> dict[str, str]:
    import cv2

    v = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "platform": platform.platform(),
    }
    try:
        from importlib.metadata import version

        v["roomcap"] = version("roomcap")
    except Exception:  # not installed (running from a checkout)
        v["roomcap"] = "unknown"
    if any(c.kind == "oak" for c in cfg.cameras):
        from capture.oak import depthai_version

        v["depthai"] = depthai_version()
    return v


@dataclass
class CameraResult:
    info: SourceInfo
    frames: int = 0
    dropped_queue: int = 0
    dropped_source: int = 0
    gaps: list[Gap] = field(default_factory=list)
    ended: str = ""
    writer_error: str = ""


class Recorder:
    """Record every camera of ``cfg`` into ``out``; ``run()`` returns the session summary dict.

    ``frameset_sink``: optional callable receiving (cam, frame) for the live path (see capture.live).
    """

    def __init__(
        self,
        cfg: CaptureConfig,
        out: str | os.PathLike,
        duration_s: float | None = None,
        frameset_sink: queue.Queue | None = None,
        handle_signals: bool = True,
        sources: dict[str, FrameSource] | None = None,
        cams_yaml_text: str | None = None,
    ):
        self.cfg = cfg
        self.layout = SessionLayout(out)
        self.duration_s = duration_s
        self.sink = frameset_sink
        self.handle_signals = handle_signals
        self.stop_event = threading.Event()
        self.stop_reason = ""
        self._given_sources = sources or {}
        self.cams_yaml_text = cams_yaml_text
        self.disk_free_bytes = lambda p: shutil.disk_usage(p).free  # replaceable in tests
        self.grabbers: dict[str, Grabber] = {}
        self.writers: dict[str, WriterThread] = {}
        self.infos: dict[str, SourceInfo] = {}
        self.t0_ns = 0
        self.started_utc = ""
        self._meta_lock = threading.Lock()

    # -- metadata
    def _meta(self, status: str, timing: dict | None = None) -> dict:
        cams = {}
        for c in self.cfg.cameras:
            info = self.infos.get(c.name)
            g = self.grabbers.get(c.name)
            w = self.writers.get(c.name)
            d = {
                "source": c.source_redacted,
                "kind": c.kind,
                "codec": c.codec,
                "video": f"raw/{c.name}",
                "frames_csv": f"raw/{c.name}.frames.csv",
            }
            if info is not None:
                d.update(
                    width=info.width,
                    height=info.height,
                    fps_nominal=info.fps,
                    description=redact_url(info.description),
                )
            if g is not None:
                d.update(
                    frames_grabbed=g.stats.frames,
                    dropped_queue=g.stats.dropped_queue.get("writer", 0),
                    dropped_live=g.stats.dropped_queue.get("live", 0),
                    dropped_source=g.stats.dropped_source,
                    ended=g.stats.ended,
                    gaps=[gap.to_dict() for gap in g.stats.gaps],
                )
            if w is not None:
                d.update(frames_written=w.writer.frames_written, segments=w.writer.segments)
                if w.error:
                    d["writer_error"] = w.error
            cams[c.name] = d
        meta = {
            "schema": f"{SESSION_SCHEMA}/{SESSION_VERSION}",
            "status": status,
            "created_utc": self.started_utc,
            "t0_ns": self.t0_ns,
            "clock": "t_ns/t_host_ns: host CLOCK_MONOTONIC + a fixed offset to UNIX time, ns",
            "stop_reason": self.stop_reason or None,
            "calibration": self.cfg.calibration,
            "versions": _versions(self.cfg),
            "cameras": cams,
            "config": self.cfg.to_dict(),
        }
        if self.cams_yaml_text is not None:
            meta["cams_yaml"] = redact_text(self.cams_yaml_text)
        if timing is not None:
            meta["timing"] = timing
        return meta

    def write_meta(self, status: str, timing: dict | None = None) -> None:
        with self._meta_lock:
            save_toml(
                self.layout.session_toml,
                self._meta(status, timing),
                header="roomcap capture session (capture-run); schema session/1",
            )

    # -- lifecycle
    def _check_disk(self) -> bool:
        free_mb = self.disk_free_bytes(self._disk_probe()) / 2**20
        return free_mb >= self.cfg.recorder.min_free_mb

    def _disk_probe(self) -> Path:
        p = self.layout.root
        while not p.exists():
            p = p.parent
        return p

    def open_sources(self) -> dict[str, FrameSource]:
        """Open every source before anything is written: bad input fails here with nothing on disk."""
        self.t0_ns = host_now_ns()
        opened: dict[str, FrameSource] = {}
        try:
            for c in self.cfg.cameras:
                src = self._given_sources.get(c.name) or make_source(
                    c, epoch_ns=self.t0_ns, segment_s=self.cfg.recorder.segment_s
                )
                self.infos[c.name] = src.open()
                opened[c.name] = src
                log.info("%s: opened %s", c.name, redact_url(self.infos[c.name].description))
        except BaseException:
            for s in opened.values():
                s.close()
            raise
        return opened

    def run(self) -> dict:
        root = self.layout.root
        if self.layout.session_toml.exists():
            raise RecorderError(
                f"{root} already holds a session (session.toml exists). Choose a new --out folder."
            )
        if not self._check_disk():
            raise RecorderError(
                f"only {self.disk_free_bytes(self._disk_probe()) / 2**20:.0f} MB free under "
                f"{self._disk_probe()}, below recorder.min_free_mb = {self.cfg.recorder.min_free_mb:g}."
                " Free some space or record elsewhere."
            )
        sources = self.open_sources()
        self.started_utc = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        rc = self.cfg.recorder
        try:
            self.layout.raw_dir.mkdir(parents=True, exist_ok=True)
            self.write_meta("recording")  # metadata first: never a session without it
            for c in self.cfg.cameras:
                wq: queue.Queue = queue.Queue(maxsize=rc.queue_frames)
                sinks: dict = {"writer": wq}
                if self.sink is not None:
                    sinks["live"] = _Tagged(self.sink, c.name)
                writer = SegmentWriter(
                    self.layout.raw_dir / c.name,
                    self.layout.frames_csv(c.name),
                    c.codec,
                    self.infos[c.name].fps,
                    rc.segment_s,
                    c.quality,
                )
                self.writers[c.name] = WriterThread(c.name, wq, writer)
                self.grabbers[c.name] = Grabber(
                    c.name,
                    sources[c.name],
                    self.infos[c.name],
                    sinks,
                    self.stop_event,
                    rc.reconnect_initial_s,
                    rc.reconnect_max_s,
                    rc.reconnect_give_up_s,
                    on_gap=self._on_gap,
                )
        except BaseException:
            for s in sources.values():
                s.close()
            raise
        old_handlers = self._install_signals()
        try:
            for w in self.writers.values():
                w.start()
            for g in self.grabbers.values():
                g.start()
            self._wait()
        finally:
            self.stop_event.set()
            for g in self.grabbers.values():
                g.join()
            for w in self.writers.values():
                w.join()
            self._restore_signals(old_handlers)
        tables = {c: read_frames_csv(self.layout.frames_csv(c)) for c in self.cfg.names}
        from capture.sync import timing_report

        timing = timing_report(
            tables,
            {c: self.infos[c].fps for c in self.cfg.names},
            self.cfg.sync.tolerance_ns(max(i.fps or 30.0 for i in self.infos.values()))
            if self.cfg.sync.tolerance_ms is not None
            else None,
        )
        status = "complete" if not self.stop_reason.startswith("disk") else "stopped"
        self.write_meta(status, _finite(timing))
        return self._meta(status, timing)

    def _wait(self) -> None:
        t_end = None if self.duration_s is None else time.monotonic() + self.duration_s
        while not self.stop_event.is_set():
            if t_end is not None and time.monotonic() >= t_end:
                self.stop_reason = self.stop_reason or "duration reached"
                break
            if not any(g.is_alive() for g in self.grabbers.values()):
                self.stop_reason = self.stop_reason or "all sources ended"
                break
            if not self._check_disk():
                self.stop_reason = (
                    f"disk space below recorder.min_free_mb = {self.cfg.recorder.min_free_mb:g} MB"
                )
                log.error("stopping: %s", self.stop_reason)
                break
            self.stop_event.wait(0.1)

    def stop(self, reason: str = "stopped") -> None:
        self.stop_reason = self.stop_reason or reason
        self.stop_event.set()

    def _on_gap(self, cam: str, gap: Gap) -> None:
        try:
            self.write_meta("recording")  # a kill after a disconnect still leaves the gap on disk
        except Exception:
            log.exception("could not update session.toml after a gap")

    def _install_signals(self):
        if not self.handle_signals or threading.current_thread() is not threading.main_thread():
            return None
        old = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.getsignal(sig)
            signal.signal(sig, lambda s, _f: self.stop(f"signal {signal.Signals(s).name}"))
        return old

    def _restore_signals(self, old) -> None:
        if old:
            for sig, h in old.items():
                signal.signal(sig, h)


class _Tagged:
    """Queue adapter: the live path's single queue receives (cam, frame)."""

    def __init__(self, q: queue.Queue, cam: str):
        self.q, self.cam = q, cam

    def put_nowait(self, frame):
        self.q.put_nowait((self.cam, frame))

    def put(self, frame):
        self.q.put((self.cam, frame))


def _finite(d):
    if isinstance(d, dict):
        return {k: _finite(v) for k, v in d.items() if not (isinstance(v, float) and not np.isfinite(v))}
    return d


redact_text = redact  # the one redaction (core.redact), kept under this name for callers


# ----------------------------------------------------------------------------- repair


def repair_session(root: str | os.PathLike) -> dict[str, int]:
    """After a kill: drop unfinished segments, rebuild ``raw/<cam>.frames.csv`` from the segment rows.

    Returns camera -> frames. Sets ``status = "recovered"`` in session.toml.
    """
    from capture.fileio import load_toml

    layout = SessionLayout(root)
    counts = {}
    for cam_dir in sorted(p for p in layout.raw_dir.iterdir() if p.is_dir()):
        for part in cam_dir.glob(f"{_PART_PREFIX}*"):
            part.unlink()
        rows, names = [], []
        for seg_csv in sorted(cam_dir.glob("seg_*.frames.csv")):
            video = [p for p in cam_dir.glob(seg_csv.name.replace(".frames.csv", ".*")) if p != seg_csv]
            if not video:
                seg_csv.unlink()
                continue
            tab = read_frames_csv(seg_csv)
            rows.append(tab)
            names.append(video[0].name)
        write_ffconcat(cam_dir, names)
        tab = np.concatenate(rows) if rows else np.zeros((0, 4), np.int64)
        tab[:, 0] = np.arange(len(tab))
        atomic_write_text(
            layout.frames_csv(cam_dir.name),
            CSV_HEADER + "".join(",".join(str(int(x)) for x in r) + "\n" for r in tab),
        )
        counts[cam_dir.name] = len(tab)
    if layout.session_toml.exists():
        meta = load_toml(layout.session_toml)
        if meta.get("status") == "recording":
            meta["status"] = "recovered"
            for cam, n in counts.items():
                meta.setdefault("cameras", {}).setdefault(cam, {})["frames_written"] = n
            save_toml(layout.session_toml, meta)
    return counts
