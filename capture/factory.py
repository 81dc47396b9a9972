"""The frame source for a cams.yaml entry: the one place that knows every kind of camera.

Apart from ``capture.sources`` (the base types, OpenCV, file replay, synthetic) and ``capture.oak``
(which imports ``depthai`` only when an OAK camera opens), so neither imports the other's module.
"""

from __future__ import annotations

from roomcap.capture.config import CameraConfig, redact_url
from roomcap.capture.oak import OakSource
from roomcap.capture.sources import FileReplaySource, FrameSource, OpenCVSource, SourceError, SyntheticSource


def make_source(
    cam: CameraConfig, epoch_ns: int | None = None, timeout_s: float = 5.0, segment_s: float = 0.5
) -> FrameSource:
    """The FrameSource for one cams.yaml entry (nothing is opened yet)."""
    kind = cam.kind
    if kind == "synthetic":
        return SyntheticSource.from_config(cam, epoch_ns)
    if kind == "file":
        return FileReplaySource(
            cam.name,
            cam.source,
            realtime=cam.realtime,
            loop=cam.loop,
            epoch_ns=epoch_ns,
            fps=cam.fps,
            drop_late=cam.drop_late,
            stream_copy=cam.stream_copy,
        )
    if kind == "oak":
        return OakSource(cam, segment_s=segment_s, timeout_s=timeout_s)
    if kind == "rtsp" and cam.stream_copy and _has_pyav():  # its packets recorded as they come
        from roomcap.capture.avstream import AVStreamSource

        return AVStreamSource(cam, open_timeout_s=timeout_s, read_timeout_s=timeout_s)
    if kind in ("usb", "device", "rtsp"):
        return OpenCVSource(cam, open_timeout_s=timeout_s, read_timeout_s=timeout_s)
    raise SourceError(f"{cam.name}: unknown source kind {kind!r} for {redact_url(cam.source)}")


def _has_pyav() -> bool:
    import importlib.util

    return importlib.util.find_spec("av") is not None


def check_source(cam: CameraConfig) -> FrameSource:
    """What ``capture-run check`` asks of a camera: the source recording would build (its options parsed by
    the same code) and what it refuses before opening (a missing file); nothing is opened. Raises
    :class:`SourceError`."""
    src = make_source(cam)
    src.check()
    return src
