"""Recording a compressed source without re-encoding it: its packets copied into the recorder's segments.

A video file replayed as a camera (``FileReplaySource``) already holds compressed packets; decoding every
frame and encoding it again (mp4v) cost more than this machine's two cores on the Pose2Sim demo's 4 x
1088x1920 at 60 Hz. Where the file's codec fits a segment container (:data:`COPY_CODECS`),
the source reads it with PyAV (:class:`PacketReader`) and hands each frame to the recorder with the
packets to write: the writer (:class:`roomcap.capture.segments.SegmentWriter`) muxes them as they are
(stream copy), and only the live loop's frames are decoded images.

Frames come in presentation order, packets in decode order (B-frames). The reader demuxes one group of
pictures (GOP: a keyframe and the packets up to the next one) ahead, and the first frame of each GOP
carries the whole GOP's packets (``Frame.packets``; ``keyframe`` True only there), so a segment, which
may only start at a keyframe, holds exactly the packets of the frames whose rows it has: the per-frame
timestamps (``raw/<cam>.frames.csv``, one row per frame), the kill-safe segments and the join
(:mod:`roomcap.capture.join`, which checks packets == rows) are unchanged. A codec the containers cannot
take, or a source that gives raw frames (USB, synthetic), is re-encoded as before; ``capture-run check``
says which (:func:`copy_plan`).
"""

from __future__ import annotations

import logging
from collections import deque
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

# the codecs whose packets go into segments as they are, and the segment container for each (an
# extension the join (capture.join.JOINED_EXT) and the readers (capture.sources.Recording) know)
COPY_CODECS = {"h264": ".mp4", "hevc": ".mp4", "mpeg4": ".mp4", "mjpeg": ".avi"}


# a live stream's open input (capture.avstream): copy_from key -> (its video stream, the segment extension,
# the container); the writer's segments take the stream as their template and release it when done
STREAM_TEMPLATES: dict[str, tuple[Any, str, Any]] = {}


def release_templates(keys: Any) -> None:
    """Close the live streams' containers ``keys`` names (the writer of their segments is done)."""
    for k in keys:
        entry = STREAM_TEMPLATES.pop(k, None)
        if entry is not None:
            try:
                entry[2].close()
            except Exception:  # noqa: BLE001 - a broken stream: nothing left to write from it
                pass


def copy_plan(path: str | Path, drop_late: bool = False, wanted: bool = True) -> tuple[str | None, str]:
    """How a video file replayed as a camera is recorded: ``(segment extension, description)`` for a stream
    copy, ``(None, why it is re-encoded)`` otherwise. Reads the container's header, decodes nothing.
    ``drop_late`` (the camera's option): late frames are left out, as a camera's would be, which a copy of
    the packets cannot do. ``wanted`` False (the camera's ``stream_copy: false``): re-encoded."""
    path = Path(path)
    if not wanted:
        return None, "re-encoded: stream_copy is false in cams.yaml"
    if drop_late:
        return None, "re-encoded: drop_late leaves late frames out, which a stream copy cannot"
    if path.is_dir():
        return None, "re-encoded: a recorded segment folder is replayed frame by frame"
    try:
        import av
    except ImportError:
        return None, "re-encoded: PyAV (package 'av') is not installed, which stream copy needs"
    try:
        with av.open(str(path)) as c:
            if not c.streams.video:
                return None, "re-encoded: the file holds no video stream PyAV can read"
            name = c.streams.video[0].codec_context.name
    except Exception as e:  # noqa: BLE001 - any container PyAV cannot read: the OpenCV path as before
        return None, f"re-encoded: PyAV cannot read the file ({type(e).__name__}: {e})"
    ext = COPY_CODECS.get(name)
    if ext is None:
        return None, (
            f"re-encoded: its {name} video cannot be stream-copied into the recorder's segments "
            f"(copied: {', '.join(sorted(COPY_CODECS))})"
        )
    return ext, f"stream copy of its {name} packets into {ext} segments (no re-encoding)"


def recording_mode(cam: Any, source: Any = None) -> str:
    """How camera ``cam`` (a ``CameraConfig``) is recorded, in words, for ``capture-run check`` and the
    session summary: a file replayed by stream copy or re-encoded (and why), an OAK's on-device stream as it
    comes, or the host encoder for a source that gives decoded frames. ``source``: the opened source (a
    file replay says what it chose at open)."""
    from roomcap.capture.config import DEVICE_CODECS

    chosen = getattr(source, "copy", None)
    if chosen:
        return chosen if chosen.startswith("stream copy") else f"{chosen} as {cam.codec}"
    if cam.kind == "file":
        ext, why = copy_plan(cam.source, cam.drop_late, cam.stream_copy)
        return why if ext is not None else f"{why} as {cam.codec}"
    if cam.kind == "oak" and cam.codec == "mjpeg":
        return (
            "the device's JPEGs written as they come (no re-encoding), decoded on the host only for the "
            "frames the live loop takes"
        )
    if cam.kind == "oak" and cam.codec in DEVICE_CODECS:
        return (
            f"the device's {cam.codec} stream written as it comes (no re-encoding); the live loop gets no "
            "images from it (codec: mjpeg gives them)"
        )
    if cam.kind in ("usb", "device") and cam.stream_copy:
        return (
            "MJPEG asked of the camera: its JPEGs written as they come (stream copy, no re-encoding); "
            f"a camera that delivers another format is re-encoded as {cam.codec} (said when it opens)"
        )
    if cam.kind == "rtsp" and cam.stream_copy:
        return (
            "the stream's packets written as they come (stream copy, PyAV) when its codec is one of "
            f"{', '.join(sorted(COPY_CODECS))}; another codec is re-encoded as {cam.codec} "
            "(said when it opens)"
        )
    return f"re-encoded as {cam.codec}: this source gives decoded frames"


def delivers_jpeg(cam: Any) -> bool:
    """Whether camera ``cam`` (a ``CameraConfig``) is expected to hand out JPEGs (``Frame.jpeg``), decoded
    only where the live loop takes them: an MJPEG file replayed by stream copy, a USB camera or V4L2 device
    asked for MJPEG (whether it gives it is known when it opens). Reads a file's header only."""
    if not cam.stream_copy:
        return False
    if cam.kind in ("usb", "device"):
        return True
    if cam.kind != "file" or cam.drop_late:
        return False
    try:
        import av

        with av.open(str(cam.source)) as c:
            return bool(c.streams.video) and c.streams.video[0].codec_context.name == "mjpeg"
    except Exception:  # noqa: BLE001 - unreadable here: the source says why when it opens
        return False


class PacketReader:
    """``(t_file_ns, image BGR, packets | None)`` per frame of a video file, in presentation order; the first
    frame of each GOP carries the GOP's packets (decode order), the others None. ``t_file_ns``: the
    frame's presentation time in the file (its pts)."""

    def __init__(self, path: str | Path):
        import av  # lazy: PyAV

        self.path = str(path)
        self.container = av.open(self.path)
        self.stream = self.container.streams.video[0]
        self.stream.thread_type = "AUTO"
        self.codec = self.stream.codec_context
        self.tb = self.stream.time_base
        self.fps = float(self.stream.average_rate or self.stream.guessed_rate or 0.0)
        self.width, self.height = int(self.codec.width), int(self.codec.height)
        self._demux = self.container.demux(self.stream)
        self._held: Any = None  # the keyframe that starts the next GOP, read ahead
        self._demux_done = False
        self._flushed = False
        self._feed: deque[Any] = deque()  # packets not yet given to the decoder
        self._ready: deque[Any] = deque()  # decoded frames not yet returned
        self._gops: deque[list[Any]] = deque()  # [packets, frames left, packets handed out]

    def _next_packet(self) -> Any:
        for p in self._demux:
            if p.size:  # the demuxer's flush packet has none
                return p
        self._demux_done = True
        return None

    def _read_gop(self) -> list[Any] | None:
        first = self._held if self._held is not None else (None if self._demux_done else self._next_packet())
        self._held = None
        if first is None:
            return None
        gop = [first]
        while not self._demux_done:
            p = self._next_packet()
            if p is None:
                break
            if p.is_keyframe:
                self._held = p
                break
            gop.append(p)
        return gop

    def __iter__(self) -> PacketReader:
        return self

    def __next__(self) -> tuple[int, Any, list[Any] | None]:
        while not self._ready:
            if self._feed:
                self._ready.extend(self.codec.decode(self._feed.popleft()))
                continue
            gop = self._read_gop()
            if gop is not None:
                self._gops.append([gop, len(gop), False])
                self._feed.extend(gop)
                continue
            if not self._flushed:
                self._flushed = True
                self._ready.extend(self.codec.decode(None))
                continue
            raise StopIteration
        frame = self._ready.popleft()
        packets = None
        if self._gops:
            g = self._gops[0]
            if not g[2]:
                packets, g[2] = g[0], True
            g[1] -= 1
            if g[1] <= 0:
                self._gops.popleft()
        t_ns = int(round(float(frame.pts * self.tb) * 1e9)) if frame.pts is not None else 0
        return t_ns, frame.to_ndarray(format="bgr24"), packets

    @property
    def intra_jpeg(self) -> bool:
        """Whether every packet is a whole JPEG picture (MJPEG): then :meth:`jpegs` decodes nothing."""
        return self.codec.name == "mjpeg"

    def jpegs(self) -> Any:
        """``(t_file_ns, packet)`` per frame of an MJPEG file, nothing decoded: each packet is one frame's
        JPEG (a keyframe), copied into the segments as it is and decoded only where the live loop takes the
        frame (``Frame.decoded``)."""
        for p in self.container.demux(self.stream):
            if p.size:
                yield (int(round(float(p.pts * self.tb) * 1e9)) if p.pts is not None else 0), p

    def close(self) -> None:
        self.container.close()


class CopyMuxer:
    """One segment written by stream copy: the packets of :class:`PacketReader` frames muxed into ``path``
    (timestamps shifted so that the segment starts at 0, as the recorder's other segments do and the join
    expects), with the source file's stream as the template."""

    def __init__(self, path: Path, template: str):
        import av  # lazy: PyAV

        if template in STREAM_TEMPLATES:  # a live stream's (capture.avstream): its open input stream
            self._tmpl, stream = None, STREAM_TEMPLATES[template][0]
        else:
            self._tmpl = av.open(template)
            stream = self._tmpl.streams.video[0]
        self.out = av.open(str(path), "w")
        self.ost = self.out.add_stream_from_template(stream)
        self._shift: int | None = None
        self.last_dts: int | None = None  # in the source's ticks, before the shift

    def follows(self, packets: list[Any]) -> bool:
        """Whether ``packets`` continue this segment's timeline (a looping file starts again at 0)."""
        p = packets[0]
        return self.last_dts is None or p.dts is None or p.dts > self.last_dts

    def write(self, packets: list[Any]) -> None:
        for p in packets:
            if self._shift is None:
                self._shift = int(p.pts if p.pts is not None else (p.dts or 0))
            if p.dts is not None:
                self.last_dts = int(p.dts)
            q = _copy_packet(p)
            if q.pts is not None:
                q.pts -= self._shift
            if q.dts is not None:
                q.dts -= self._shift
            q.stream = self.ost
            self.out.mux(q)

    def close(self) -> None:
        try:
            self.out.close()
        finally:
            if self._tmpl is not None:
                self._tmpl.close()


class JpegMuxer:
    """One segment of a source whose frames come as JPEGs without a file behind them (a USB camera
    streaming MJPEG, :class:`roomcap.capture.sources.OpenCVSource`): each JPEG muxed as one packet of an
    MJPEG stream in an AVI (the recorder's MJPEG container), byte for byte; the frames' times are in the
    timestamp rows, the packets numbered at the camera's nominal rate. Same interface as
    :class:`CopyMuxer`."""

    def __init__(self, path: Path, width: int, height: int, fps: float):
        from fractions import Fraction

        import av  # lazy: PyAV

        self.out = av.open(str(path), "w", format="avi")
        rate = Fraction(fps).limit_denominator(1001) if fps and fps > 0 else Fraction(30)
        self.ost = self.out.add_stream("mjpeg", rate=rate)
        self.ost.width, self.ost.height, self.ost.pix_fmt = int(width), int(height), "yuvj420p"
        self.ost.time_base = 1 / rate
        self._n = 0
        self.last_dts: int | None = None

    def follows(self, packets: list[Any]) -> bool:
        return True

    def write_jpeg(self, data: bytes) -> None:
        import av

        q = av.Packet(data)
        q.pts = q.dts = self._n
        q.is_keyframe = True
        q.time_base = self.ost.time_base
        q.stream = self.ost
        self.out.mux(q)
        self._n += 1

    def close(self) -> None:
        self.out.close()


def _copy_packet(p: Any) -> Any:
    """A packet with ``p``'s bytes, timestamps, time base and flags (the reader's packet is left as it is:
    a looping source and the live loop may still hold it)."""
    import av

    q = av.Packet(bytes(p))
    q.pts, q.dts, q.time_base = p.pts, p.dts, p.time_base
    if p.duration:
        q.duration = p.duration
    q.is_keyframe = p.is_keyframe
    return q
