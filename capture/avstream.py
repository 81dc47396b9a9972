"""A network stream (RTSP, HTTP, ...) read with PyAV: its compressed packets recorded as they come (stream
copy) and every frame decoded for the live loop (an inter-coded H.264/H.265 stream needs every packet
decoded).

:class:`AVStreamSource` demuxes the stream, decodes each packet at once (no group of pictures read ahead: a
live stream's frames go on as they arrive) and hands each decoded frame on with *its own* packet (matched by
its presentation time), ``keyframe`` where that packet is one. The writer
(:class:`roomcap.capture.segments.SegmentWriter`) keeps a group of pictures' packets until the next keyframe,
then muxes them in decode order into the segment, which is cut only there: a segment holds exactly the
packets of its timestamp rows, as for a replayed file (:mod:`roomcap.capture.streamcopy`). The group open
when the recording ends is left out (said, ``copy_tail_dropped``), as is a group with a frame missing (a
frame the writer's queue dropped: its packets would not decode). A codec the segment containers cannot take
(:data:`roomcap.capture.streamcopy.COPY_CODECS`), or ``stream_copy: false``, is re-encoded from the decoded
frames, and ``self.copy`` says why (the session summary shows it).

Timestamps: the host's at receipt (``t_ns = t_host_ns``), as for OpenCV streams; a stream's own clock is not
comparable across cameras.
"""

from __future__ import annotations

import itertools
import logging
from typing import Any

from roomcap.capture.config import CameraConfig
from roomcap.capture.sources import (
    Frame,
    FrameSource,
    SourceDisconnected,
    SourceError,
    SourceInfo,
    host_now_ns,
)
from roomcap.capture.streamcopy import COPY_CODECS, STREAM_TEMPLATES

log = logging.getLogger(__name__)

_KEYS = itertools.count()


class AVStreamSource(FrameSource):
    """A stream URL (or, as a stand-in in tests and benches, a local video file: ``live`` False, its frames
    delivered at its frame rate as a stream's arrive, ending at its end) read with PyAV; see the module
    doc."""

    def __init__(
        self,
        cam: CameraConfig,
        url: str | None = None,
        open_timeout_s: float = 5.0,
        read_timeout_s: float = 5.0,
        live: bool = True,
    ):
        self.name = cam.name
        self.cam = cam
        self.url = url or cam.source
        self.open_timeout_s, self.read_timeout_s = open_timeout_s, read_timeout_s
        self._live = live
        self._c: Any = None
        self._demux: Any = None
        self._ready: list = []
        self._by_pts: dict[int, Any] = {}
        self._seq = 0
        self._key: str | None = None
        self.copy: str | None = None

    @property
    def live(self) -> bool:
        return self._live

    @property
    def waits_for_consumers(self) -> bool:
        return not self._live  # a file stand-in records every frame, as a replayed file does

    def _describe(self) -> str:
        return f"stream {self.cam.source_redacted}" if self._live else f"stream stand-in {self.url}"

    def open(self) -> SourceInfo:
        import av

        opts = {"rtsp_transport": "tcp"} if self.url.lower().startswith("rtsp") else {}
        try:
            self._c = av.open(self.url, options=opts, timeout=(self.open_timeout_s, self.read_timeout_s))
        except Exception as e:  # noqa: BLE001 - unreachable, refused, not a stream: retried by the grabber
            raise SourceDisconnected(
                f"{self.name}: cannot reach {self._describe()} within {self.open_timeout_s:g} s "
                f"({type(e).__name__}). Check the address, port, credentials and network."
            ) from None
        if not self._c.streams.video:
            self._c.close()
            raise SourceError(f"{self.name}: {self._describe()} holds no video stream.")
        stream = self._c.streams.video[0]
        name = stream.codec_context.name
        ext = COPY_CODECS.get(name)
        if not self.cam.stream_copy:
            self.copy, ext = "re-encoded: stream_copy is false in cams.yaml", None
        elif ext is None:
            self.copy = (
                f"re-encoded: its {name} video cannot be stream-copied into the recorder's segments "
                f"(copied: {', '.join(sorted(COPY_CODECS))})"
            )
            log.warning("%s: recording %s as %s", self.name, self.copy, self.cam.codec)
        else:
            self.copy = f"stream copy of its {name} packets into {ext} segments (no re-encoding)"
        # one key per opening: a reconnect may bring other codec parameters, so a new segment starts; the
        # container stays open for the writer's segments until the writer closes (release_templates)
        self._key = f"stream:{self.name}:{next(_KEYS)}" if ext is not None else None
        if self._key is not None:
            STREAM_TEMPLATES[self._key] = (stream, ext, self._c)
        self._demux = self._c.demux(stream)
        self._ready, self._by_pts = [], {}
        first = self._next_frame()
        if first is None:
            raise SourceError(f"{self.name}: {self._describe()} delivers no decodable frame.")
        self._ready.insert(0, first)
        fps = float(stream.average_rate or stream.guessed_rate or 0.0) or (self.cam.fps or 30.0)
        self._fps, self._t0 = fps, None
        return SourceInfo(first[0].shape[1], first[0].shape[0], fps, self.cam.kind, self._describe())

    def _next_frame(self) -> tuple[Any, Any] | None:
        """(image, its packet or None) of the next decoded frame; None at the end of a file stand-in."""
        while not self._ready:
            try:
                p = next(self._demux, None)
            except Exception as e:  # noqa: BLE001 - the stream broke (timeout, reset)
                raise SourceDisconnected(
                    f"{self.name}: {self._describe()} stopped delivering ({type(e).__name__})"
                ) from None
            if p is None or (not p.size and p.pts is None and p.dts is None):
                if p is not None:
                    for f in p.decode():  # the decoder's flush at the end of a file
                        self._ready.append((f.to_ndarray(format="bgr24"), self._by_pts.pop(f.pts, None)))
                    continue
                return None
            if self._key is not None and p.pts is not None:
                self._by_pts[int(p.pts)] = p
            for f in p.decode():
                self._ready.append((f.to_ndarray(format="bgr24"), self._by_pts.pop(f.pts, None)))
        return self._ready.pop(0)

    def read(self) -> Frame | None:
        if self._c is None:
            raise SourceError(f"{self.name}: read() before open()")
        item = self._next_frame()
        if item is None:
            if self._live:
                self.close()
                raise SourceDisconnected(f"{self.name}: {self._describe()} ended")
            return None
        img, packet = item
        if not self._live:  # a file standing in for a stream: its frames arrive at the stream's rate
            import time

            if self._t0 is None:
                self._t0 = time.monotonic()
            wait = self._t0 + self._seq / self._fps - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        now = host_now_ns()
        seq = self._seq
        self._seq += 1
        if self._key is None or packet is None:
            return Frame(img, now, now, seq)
        return Frame(
            img, now, now, seq, keyframe=bool(packet.is_keyframe), copy_from=self._key, packets=[packet]
        )

    def close(self) -> None:
        """Stop reading. A stream-copied container is closed by the writer, once it wrote its segments
        (:func:`roomcap.capture.streamcopy.release_templates`): its stream is their template."""
        if self._c is not None:
            if self._key is None:
                try:
                    self._c.close()
                except Exception:  # noqa: BLE001 - closing a broken stream
                    pass
            self._c = None
