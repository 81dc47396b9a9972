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

When the recording ends (and in ``repair_session``) each camera's segments are joined into one
``raw/<cam>.mp4`` (``.avi`` for MJPEG) by stream copy (``capture.join``); the segments are removed
only after the joined file's frame count matched ``raw/<cam>.frames.csv``.

Nothing lost: the recorder writes only into a new or empty folder (never over segments or onto an old
frames.csv); a writer error (a full disk, also with the free-space guard off) stops every camera
cleanly with ``status = "stopped"`` and the reason in ``stop_reason``, the open segment finalised or
removed; with ``skip_failed_cameras`` a camera that cannot be opened is left out and listed in
``failed_cameras``.
"""

from __future__ import annotations

import datetime as _dt
import errno
import logging
import os
import platform
import queue
import shutil
import signal
import threading
import time
from pathlib import Path

import numpy as np

from roomcap.capture.config import CaptureConfig, redact_url
from roomcap.capture.factory import make_source
from roomcap.capture.grabber import Gap, Grabber
from roomcap.capture.join import JoinResult, count_video_packets, join_camera, remove_segments
from roomcap.capture.oak import depthai_version
from roomcap.capture.segments import (
    CSV_HEADER,
    PART_PREFIX,
    RecorderError,
    SegmentWriter,
    WriterThread,
    write_ffconcat,
)
from roomcap.capture.session import SESSION_SCHEMA, SESSION_VERSION, SessionLayout
from roomcap.capture.sources import (
    FrameSource,
    SourceError,
    SourceInfo,
    host_now_ns,
    read_frames_csv,
)
from roomcap.capture.streamcopy import recording_mode
from roomcap.capture.sync import timing_report
from roomcap.core.fileio import atomic_write_text, load_toml, save_toml
from roomcap.core.redact import redact

log = logging.getLogger(__name__)

_DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
STALL_MIN_S = 1.0  # a camera without a frame this long (and 10 frame periods) is reported as stalling


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
        v["depthai"] = depthai_version()
    return v


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
        skip_failed_cameras: bool = False,
        join: bool = True,
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
        self.skip_failed_cameras = skip_failed_cameras
        self.join = join
        self.failed_cameras: dict[str, str] = {}  # camera -> why it could not be opened
        self.joins: dict = {}  # camera -> capture.join.JoinResult

    @property
    def active(self) -> list:
        """The cameras being recorded (cams.yaml order): all but those skipped at start."""
        return [c for c in self.cfg.cameras if c.name not in self.failed_cameras]

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
                if g.stats.stalls:
                    d["stalls"] = [{k: v for k, v in st.items() if v is not None} for st in g.stats.stalls]
            if c.name not in self.failed_cameras:
                d["recording"] = recording_mode(c, g.source if g is not None else None)
            if w is not None:
                d.update(frames_written=w.writer.frames_written, segments=w.writer.segments)
                if w.writer.copy_tail_dropped:
                    d["copy_tail_dropped"] = w.writer.copy_tail_dropped
                if w.writer.copy_head_dropped:
                    d["copy_head_dropped"] = w.writer.copy_head_dropped
                if w.error:
                    d["writer_error"] = w.error
            if c.name in self.failed_cameras:
                d.update(recorded=False, failed=redact(self.failed_cameras[c.name]))
            if c.name in self.joins:
                d.update(self.joins[c.name].to_dict())
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
        if self.failed_cameras:
            meta["failed_cameras"] = sorted(self.failed_cameras)
        if self.cams_yaml_text is not None:
            meta["cams_yaml"] = redact(self.cams_yaml_text)
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
                try:
                    src = self._given_sources.get(c.name) or make_source(
                        c, epoch_ns=self.t0_ns, segment_s=self.cfg.recorder.segment_s
                    )
                    self.infos[c.name] = src.open()
                except SourceError as e:
                    if not self.skip_failed_cameras:
                        raise RecorderError(
                            f"camera '{c.name}' cannot be opened: {e} Nothing was recorded; to record the "
                            "other cameras without it, pass --skip-failed-cameras."
                        ) from None
                    self.failed_cameras[c.name] = str(e)
                    log.error("%s: skipped, cannot be opened: %s", c.name, redact(str(e)))
                    continue
                opened[c.name] = src
                log.info("%s: opened %s", c.name, redact_url(self.infos[c.name].description))
        except BaseException:
            for s in opened.values():
                s.close()
            raise
        if not opened:
            raise RecorderError(
                "no camera could be opened ("
                + "; ".join(redact(m) for m in self.failed_cameras.values())
                + "). Nothing was recorded."
            )
        return opened

    def run(self) -> dict:
        """Record until the duration, the sources' end, a stop or a failure; join; the session summary."""
        self._check_out_folder()
        sources = self.open_sources()
        self.started_utc = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        self._make_threads(sources)
        self._record()
        names = [c.name for c in self.active]
        tables = {c: read_frames_csv(self.layout.frames_csv(c)) for c in names}

        timing = timing_report(
            tables,
            {c: self.infos[c].fps for c in names},
            self.cfg.sync.tolerance_ns(max(i.fps or 30.0 for i in self.infos.values()))
            if self.cfg.sync.tolerance_ms is not None
            else None,
        )
        status = self._status()
        if self.join:
            self._join_all(tables)
        try:
            self.write_meta(status, _finite(timing))
        except OSError as e:
            raise RecorderError(
                f"the recording stopped ({self.stop_reason}) but session.toml could not be updated ({e}). "
                f"Free some space, then run `capture-run repair {self.layout.root}`; the closed segments are "
                "kept."
            ) from None
        return self._meta(status, timing)

    def _check_out_folder(self) -> None:
        """Refuse a folder that is a file or holds anything, and a disk below ``recorder.min_free_mb``."""
        root = self.layout.root
        if root.exists() and not root.is_dir():
            raise RecorderError(f"--out {root} is a file, not a folder. Choose a new --out folder.")
        if root.is_dir() and any(root.iterdir()):
            held = sorted(p.name for p in root.iterdir())
            what = "a session (session.toml exists)" if self.layout.session_toml.exists() else "files"
            raise RecorderError(
                f"{root} already holds {what}: {', '.join(held[:5])}{' ...' if len(held) > 5 else ''}. "
                "The recorder writes only into a new or empty folder, so that nothing is overwritten. "
                "Choose a new --out folder"
                + (
                    f", or run `capture-run repair {root}` if a recording there was interrupted."
                    if self.layout.session_toml.exists()
                    else "."
                )
            )
        if not self._check_disk():
            raise RecorderError(
                f"only {self.disk_free_bytes(self._disk_probe()) / 2**20:.0f} MB free under "
                f"{self._disk_probe()}, below recorder.min_free_mb = {self.cfg.recorder.min_free_mb:g}."
                " Free some space or record elsewhere."
            )

    def _make_threads(self, sources: dict[str, FrameSource]) -> None:
        """Write the first session.toml and make each camera's writer and grabber (closing the sources on
        an error)."""
        rc = self.cfg.recorder
        try:
            self.layout.raw_dir.mkdir(parents=True, exist_ok=True)
            self.write_meta("recording")  # metadata first: never a session without it
            for c in self.active:
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

    def _record(self) -> None:
        """Run the threads until :meth:`_wait` ends the recording, then join them."""
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

    def _status(self) -> str:
        """``"complete"``, or ``"stopped"`` after a full disk or a writer failure (which becomes the
        stop reason)."""
        failure = self._writer_failure()
        if failure and not self.stop_reason.startswith(failure.split(":")[0]):
            # a writer failed while the recording was ending anyway: that is the reason that matters
            log.error("recording incomplete: %s (was: %s)", failure, self.stop_reason)
            self.stop_reason = failure
        return "stopped" if self.stop_reason.startswith("disk") or failure else "complete"

    def _join_all(self, tables: dict) -> None:
        """Join each camera's segments into raw/<cam>.mp4 (capture.join), unless the disk is full."""

        disk_full = any(w.errno in _DISK_FULL for w in self.writers.values()) or self.stop_reason.startswith(
            "disk"
        )
        for c in self.active:
            n = len(tables[c.name])
            if disk_full:
                self.joins[c.name] = JoinResult(
                    c.name,
                    False,
                    f"raw/{c.name}",
                    n,
                    -1,
                    self.writers[c.name].writer.segments,
                    f"not joined (disk full); free space and run `capture-run repair {self.layout.root}`",
                )
                continue
            self.joins[c.name] = join_camera(
                self.layout.raw_dir,
                c.name,
                n,
                self.infos[c.name].fps,
                int(self.cfg.recorder.min_free_mb * 2**20),
            )

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
            failure = self._writer_failure()
            if failure:
                self.stop_reason = self.stop_reason or failure
                log.error("stopping: %s", self.stop_reason)
                break
            for g in self.grabbers.values():  # a camera that stopped sending without an error: said
                g.check_stall(self._stall_s(g))
            self.stop_event.wait(0.1)

    def _stall_s(self, g: Grabber) -> float:
        """How long without a frame a camera stalls: 10 frame periods, at least ``STALL_MIN_S``."""
        fps = g.info.fps or 30.0
        return max(STALL_MIN_S, 10.0 / fps)

    def _writer_failure(self) -> str:
        """'disk full: camera X: ...' (or 'writer failed: ...') once a writer thread failed, else ''."""
        for cam, w in self.writers.items():
            if w.failed.is_set():
                kind = "disk full" if w.errno in _DISK_FULL else "writer failed"
                return f"{kind}: camera {cam}: {w.error}"
        return ""

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


# ----------------------------------------------------------------------------- repair


def repair_session(root: str | os.PathLike, join: bool = True) -> dict[str, int]:
    """:func:`repair` returning camera -> frames only."""
    return repair(root, join)[0]


def repair(root: str | os.PathLike, join: bool = True) -> tuple[dict[str, int], dict]:
    """After a kill (or a recording whose join was skipped): make every camera one playable video.

    Per camera folder ``raw/<cam>/``: drop unfinished segments, rebuild ``raw/<cam>.frames.csv`` from
    the per-segment rows, then (``join``) join the segments into ``raw/<cam>.mp4`` (``capture.join``;
    segments are kept when the frame count does not match). Returns (camera -> frames, camera ->
    ``capture.join.JoinResult``). Sets
    ``status = "recovered"`` in a session.toml left at ``recording`` and records each join.
    """

    layout = SessionLayout(root)
    if not layout.raw_dir.is_dir():
        raise RecorderError(f"{layout.root}: no raw/ folder; this is not a recorded session.")
    counts: dict[str, int] = {}
    joins = {}
    meta = load_toml(layout.session_toml) if layout.session_toml.exists() else {}
    for cam_dir in sorted(p for p in layout.raw_dir.iterdir() if p.is_dir() and not p.name.startswith(".")):
        cam = cam_dir.name
        for part in cam_dir.glob(f"{PART_PREFIX}*"):
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
        if not names:
            continue
        tab = np.concatenate(rows) if rows else np.zeros((0, 4), np.int64)
        tab[:, 0] = np.arange(len(tab))
        counts[cam] = len(tab)
        joined = [layout.raw_dir / f"{cam}{ext}" for ext in (".mp4", ".avi", ".mkv")]
        done = [p for p in joined if p.exists()]
        if done and count_video_packets(done[0]) == len(tab):
            remove_segments(cam_dir)  # killed after the join's rename, before the segments went
            continue
        write_ffconcat(cam_dir, names)
        atomic_write_text(
            layout.frames_csv(cam),
            CSV_HEADER + "".join(",".join(str(int(x)) for x in r) + "\n" for r in tab),
        )
        if join:
            fps = meta.get("cameras", {}).get(cam, {}).get("fps_nominal") or 0.0
            joins[cam] = join_camera(layout.raw_dir, cam, len(tab), float(fps))
    if layout.session_toml.exists():
        if meta.get("status") == "recording":
            meta["status"] = "recovered"
            meta["stop_reason"] = meta.get("stop_reason") or "interrupted (repaired by capture-run repair)"
        for cam, n in counts.items():
            cm = meta.setdefault("cameras", {}).setdefault(cam, {})
            cm["frames_written"] = n
            if cam in joins:
                cm.update(joins[cam].to_dict())
        save_toml(layout.session_toml, meta)
    return counts, joins
