"""One camera's video on disk while it records: closed, playable segments and the timestamp rows.

``SegmentWriter`` writes ``raw/<cam>/seg_NNNNNN.<ext>`` under a hidden name (``PART_PREFIX``), closes,
fsyncs and renames it, then appends its rows to ``raw/<cam>.frames.csv`` (the kill safety described in
:mod:`roomcap.capture.recorder`); ``WriterThread`` feeds it from the camera's queue.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
from pathlib import Path

from roomcap.capture.grabber import END
from roomcap.capture.join import FFCONCAT
from roomcap.capture.sources import Frame, SourceError
from roomcap.core.errors import RoomcapError
from roomcap.core.fileio import atomic_write_text

log = logging.getLogger(__name__)


class RecorderError(RoomcapError, RuntimeError):
    """The session cannot start (bad source, no disk space); nothing was written."""


CSV_HEADER = "frame_index,t_ns,t_host_ns,sequence\n"
_FOURCC = {"mp4v": ("mp4v", ".mp4"), "mjpg": ("MJPG", ".avi"), "xvid": ("XVID", ".avi")}
PART_PREFIX = ".part_"


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
        self._mux = None  # capture.streamcopy.CopyMuxer: a compressed source's packets as they are
        self._copy_ext: dict[str, str | None] = {}
        # stream copy: the open group of pictures (its packets, its frames' rows), written only once every
        # frame of it came, so that a segment holds exactly the packets of its rows
        self._gop: tuple[list, list[tuple[int, int, int]]] | None = None
        self.copy_tail_dropped = 0  # frames of a group of pictures the recording ended within (not written)
        self.copy_head_dropped = 0  # a live stream's frames before its first keyframe (not decodable alone)
        self._streams: set[str] = set()  # the live streams whose packets were copied (their inputs released)
        self._key: str | None = None  # the live stream the open segment copies
        self._last_seq = -1
        self._part: Path | None = None
        self._final: Path | None = None
        self._rows: list[str] = []
        self._seg_t0 = 0
        self._shape = None
        self._mode = ""  # what the open segment takes: "image", "jpeg", "encoded" or "copy" (_mode)
        self._closed: list[str] = []
        if self.frames_csv.exists():  # the recorder only writes into folders it created
            raise RecorderError(f"{self.frames_csv} already exists; refusing to append to an old recording.")
        atomic_write_text(self.frames_csv, CSV_HEADER)

    def _open_segment(self, frame: Frame) -> None:
        import cv2

        k = self.segments
        if any(self.dir.glob(f"seg_{k:06d}.*")):
            raise RecorderError(f"{self.dir}: seg_{k:06d} already exists; refusing to overwrite a recording.")
        if frame.copy_from is not None:  # stream copy (capture.streamcopy): starts at a GOP's first frame
            from roomcap.capture.streamcopy import STREAM_TEMPLATES, CopyMuxer, copy_plan

            if frame.packets is None:
                raise SourceError(f"{self.dir.name}: a stream-copied segment must start at a keyframe")
            if frame.copy_from not in self._copy_ext:
                live = STREAM_TEMPLATES.get(frame.copy_from)
                self._copy_ext[frame.copy_from] = live[1] if live else copy_plan(frame.copy_from)[0]
            ext = self._copy_ext[frame.copy_from] or ".mkv"
            self._final = self.dir / f"seg_{k:06d}{ext}"
            self._part = self.dir / f"{PART_PREFIX}seg_{k:06d}{ext}"
            self._mux = CopyMuxer(self._part, frame.copy_from)
        elif frame.jpeg is not None:  # a USB camera's MJPEG: each JPEG written as it came
            from roomcap.capture.sources import jpeg_size
            from roomcap.capture.streamcopy import JpegMuxer

            self._final = self.dir / f"seg_{k:06d}.avi"
            self._part = self.dir / f"{PART_PREFIX}seg_{k:06d}.avi"
            w, h = jpeg_size(frame.jpeg)
            self._mux = JpegMuxer(self._part, w, h, self.fps)
            self._shape = (h, w)
        elif frame.encoded is not None:
            ext = ".h265" if self.codec == "h265" else ".h264"  # Annex B elementary stream from the device
            self._final = self.dir / f"seg_{k:06d}{ext}"
            self._part = self.dir / f"{PART_PREFIX}seg_{k:06d}{ext}"
            self._raw = open(self._part, "wb")
        else:
            fourcc, ext = _FOURCC[self.codec]
            h, w = frame.image.shape[:2]
            self._final = self.dir / f"seg_{k:06d}{ext}"
            self._part = self.dir / f"{PART_PREFIX}seg_{k:06d}{ext}"
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
        self._mode = _mode(frame)

    def _write_copy(self, frame: Frame) -> None:
        """Stream copy (capture.streamcopy): a group of pictures starts with the frame that carries its
        packets; they are muxed, and its rows kept, when its last frame came. A segment is cut only there."""
        if frame.packets is not None:
            self._drop_open_gop()
            need_new = self._part is None or (
                frame.t_ns - self._seg_t0 >= self.segment_ns or not self._mux.follows(frame.packets)
            )
            if need_new:
                self.close_segment()
                self._open_segment(frame)
            self._gop = (list(frame.packets), [])
        elif self._gop is None:
            raise SourceError(f"{self.dir.name}: a stream-copied frame without its group of pictures")
        packets, rows = self._gop
        rows.append((frame.t_ns, frame.t_host_ns, frame.sequence))
        if len(rows) == len(packets):  # the group is whole: its packets and rows into the segment
            self._mux.write(packets)
            for t_ns, t_host, seq in rows:
                self._rows.append(f"{self.frames_written + len(self._rows)},{t_ns},{t_host},{seq}\n")
            self._gop = None

    def _write_stream_copy(self, frame: Frame) -> None:
        """A live stream's frames (capture.avstream), each with its own packet: a group of pictures is kept
        until the next keyframe, then its packets muxed in decode order and its rows (in the order the
        frames came) kept; a segment is cut only there. Frames before the first keyframe cannot be
        decoded from the segment: left out; a group with a frame missing (a gap in the sequence numbers: the
        writer's queue dropped it) is left out whole."""
        if self._gop is not None and frame.sequence != self._last_seq + 1:
            self._drop_open_gop()
        self._last_seq = frame.sequence
        if frame.keyframe:
            self._flush_stream_gop()
            if (
                self._part is None
                or frame.t_ns - self._seg_t0 >= self.segment_ns
                or frame.copy_from != self._key
            ):
                self.close_segment()
                self._open_segment(frame)
                self._key = frame.copy_from
            self._gop = ([], [])
        if self._gop is None:
            self.copy_head_dropped += 1
            return
        self._gop[0].extend(frame.packets)
        self._gop[1].append((frame.t_ns, frame.t_host_ns, frame.sequence))

    def _flush_stream_gop(self) -> None:
        if self._gop is None:
            return
        packets, rows = self._gop
        self._gop = None
        self._mux.write(sorted(packets, key=lambda p: p.dts if p.dts is not None else p.pts))
        for t_ns, t_host, seq in rows:
            self._rows.append(f"{self.frames_written + len(self._rows)},{t_ns},{t_host},{seq}\n")

    def _drop_open_gop(self) -> None:
        if self._gop is not None:
            n = len(self._gop[1])
            self.copy_tail_dropped += n
            log.warning(
                "%s: %d frame(s) of a group of pictures not written: its other frames never came (stream "
                "copy writes whole groups)",
                self.dir.name,
                n,
            )
            self._gop = None

    def write(self, frame: Frame) -> None:
        if frame.copy_from is not None:
            from roomcap.capture.streamcopy import STREAM_TEMPLATES

            if frame.copy_from in STREAM_TEMPLATES:
                self._streams.add(frame.copy_from)
                self._write_stream_copy(frame)
            else:
                self._write_copy(frame)
            return
        need_new = self._part is None
        if not need_new and frame.t_ns - self._seg_t0 >= self.segment_ns:
            # on-device streams can only be cut at a keyframe
            need_new = frame.encoded is None or frame.keyframe
        if not need_new and frame.image is not None and frame.image.shape != self._shape:
            need_new = True
        if not need_new and _mode(frame) != self._mode:
            need_new = True  # a camera that switched between decoded frames and JPEGs (after a reconnect)
        if not need_new and frame.jpeg is not None:
            from roomcap.capture.sources import jpeg_size

            need_new = jpeg_size(frame.jpeg)[::-1] != self._shape
        if need_new:
            self.close_segment()
            self._open_segment(frame)
        if frame.jpeg is not None and self._mux is not None:
            self._mux.write_jpeg(frame.jpeg)
        elif frame.encoded is not None:
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
        if self._mux is not None:
            mux, self._mux = self._mux, None
            mux.close()
            if not self._rows:  # a stream-copied segment whose only group never completed: nothing to keep
                self._part.unlink(missing_ok=True)
                self._part = self._final = None
                return
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
        self._drop_open_gop()
        try:
            self.close_segment()
        finally:
            if self._streams:
                from roomcap.capture.streamcopy import release_templates

                release_templates(self._streams)

    def abort(self) -> None:
        """After a write error: keep the open segment if it still closes cleanly, else remove it."""
        try:
            self.close_segment()
        except Exception as e:  # e.g. the disk is full: a half-written segment is not kept
            log.error("%s: could not finalise %s (%s); removing it", self.dir.name, self._part, e)
            for obj in (self._writer, self._raw, self._mux):
                try:
                    if obj is not None:
                        obj.release() if hasattr(obj, "release") else obj.close()
                except Exception:
                    pass
            self._writer = self._raw = self._mux = None
            if self._part is not None:
                self._part.unlink(missing_ok=True)
            self._part = self._final = None
            self._rows = []


def _mode(frame: Frame) -> str:
    """How a frame is written: its file's packets copied, its JPEG as it came, a device's encoded packet
    as it came, or its decoded image encoded."""
    if frame.copy_from is not None:
        return "copy"
    if frame.jpeg is not None:
        return "jpeg"
    return "encoded" if frame.encoded is not None else "image"


def write_ffconcat(cam_dir: Path, segments: list[str]) -> None:
    """``raw/<cam>/index.ffconcat``: the closed segments as one video for FFmpeg/OpenCV.

    ``cv2.VideoCapture(str(cam_dir / "index.ffconcat"))`` decodes every segment in order.
    """
    atomic_write_text(
        Path(cam_dir) / FFCONCAT, "ffconcat version 1.0\n" + "".join(f"file {n}\n" for n in segments)
    )


class WriterThread(threading.Thread):
    """Writes one camera's queued frames until ``END``; on an error, records it and keeps draining."""

    def __init__(self, cam: str, q: queue.Queue, writer: SegmentWriter):
        super().__init__(name=f"write-{cam}", daemon=True)
        self.cam, self.q, self.writer = cam, q, writer
        self.error: str = ""
        self.errno: int | None = None
        self.failed = threading.Event()

    def run(self) -> None:
        try:
            while True:
                frame = self.q.get()
                if frame is END:
                    break
                self.writer.write(frame)
        except Exception as e:
            log.error("%s: writer failed: %s", self.cam, e)
            self.error = f"{type(e).__name__}: {e}"
            self.errno = getattr(e, "errno", None)
            self.failed.set()
            self.writer.abort()
            while self.q.get() is not END:  # keep draining so the grabber never blocks
                pass
        else:
            try:
                self.writer.close()
            except Exception as e:  # the last segment could not be finalised (disk full at the end)
                self.error = f"{type(e).__name__}: {e}"
                self.errno = getattr(e, "errno", None)
                self.failed.set()
                self.writer.abort()
