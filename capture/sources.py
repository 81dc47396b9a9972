"""Frame sources behind one small interface, and ``open_recording`` to read what the recorder wrote.

``FrameSource``: ``open()``, ``read() -> Frame | None`` (None = end of stream; raises
``SourceDisconnected`` when a live camera goes away), ``close()``, ``info``. Implementations:

- ``OpenCVSource``: USB index, ``/dev/videoN``, RTSP/HTTP streams (short open/read timeouts);
- ``FileReplaySource``: a video file, a segment folder or a recorded session's camera, played
  back at its own timestamps (the test double of every camera);
- ``SyntheticSource``: a generated moving texture with the sequence number stamped as a
  barcode (``read_code``), an ideal device clock with optional offset/drift, and a simulated
  disconnect;
- OAK cameras live in ``capture.oak`` (the only module importing depthai).

Timestamps are integers in ns on one host clock: ``host_now_ns()`` is CLOCK_MONOTONIC shifted
by a fixed offset measured at import so the values read as UNIX time but never jump. Each frame
carries ``t_ns`` (the device/source timestamp on that clock), ``t_host_ns`` (when the host
received it) and ``sequence`` (the source's own frame counter; gaps = drops at the source).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.capture.config import CameraConfig, SourceOptionError, source_options
from roomcap.capture.session import VIDEO_SUFFIXES
from roomcap.core.errors import FormatError, RoomcapError

log = logging.getLogger(__name__)

_MONO_TO_WALL_NS = time.time_ns() - time.monotonic_ns()


def host_now_ns() -> int:
    """Host clock in ns: monotonic, offset to read as UNIX time (fixed for the process)."""
    return time.monotonic_ns() + _MONO_TO_WALL_NS


def mono_to_host_ns(mono_ns: int) -> int:
    """CLOCK_MONOTONIC / std::chrono::steady_clock ns (depthai's host-synced stamps) -> host_now_ns."""
    return int(mono_ns) + _MONO_TO_WALL_NS


class SourceError(RoomcapError, RuntimeError):
    """A source cannot be opened or delivers something impossible; the message says what to do."""


class SourceDisconnected(SourceError):
    """A live source stopped delivering frames (cable pulled, stream dropped); the grabber retries."""


@dataclass(frozen=True, slots=True)
class Frame:
    """One frame. image: (H,W,3) uint8 BGR, or None when only ``encoded`` bytes exist (on-device codec)."""

    image: np.ndarray | None
    t_ns: int
    t_host_ns: int
    sequence: int
    encoded: bytes | None = None  # on-device encoded packet (H.264/H.265 Annex B)
    keyframe: bool = True  # for encoded packets: a segment may start here
    # stream copy (capture.streamcopy): the file whose packets are copied, and on the first frame of each
    # group of pictures that group's packets (decode order; the other frames None)
    copy_from: str | None = None
    packets: list | None = None
    loops: int = 0  # times the source started again from its beginning (a looping file's wraps)
    # an intra-coded source (MJPEG: a USB camera's, an MJPEG file's): the frame's JPEG, written as it is and
    # decoded only where a consumer asks for the image (:meth:`decoded`); ``image`` is None then
    jpeg: bytes | None = None

    @property
    def has_image(self) -> bool:
        """Whether an image can be had: a decoded one or a JPEG to decode."""
        return self.image is not None or self.jpeg is not None

    def decoded(self, reduce: int = 1) -> np.ndarray | None:
        """The frame's (H,W,3) BGR image at 1/``reduce`` of its size (``reduce`` 1, 2, 4 or 8): a JPEG is
        decoded here (libjpeg's DCT scaling for ``reduce`` > 1: it decodes fewer coefficients, so a
        smaller image costs less, :func:`decode_jpeg`), a decoded image is shrunk by area averaging.
        Stateless, so several threads may ask. Pixel ``x`` of the result covers full-size pixels
        ``reduce*x .. reduce*x + reduce - 1`` (:func:`full_res_px` maps its coordinates back)."""
        if self.jpeg is not None and self.image is None:
            return decode_jpeg(self.jpeg, reduce)
        if self.image is None or reduce == 1:
            return self.image
        import cv2

        h, w = self.image.shape[:2]
        size = (-(-w // reduce), -(-h // reduce))  # libjpeg's size: rounded up
        return cv2.resize(self.image, size, interpolation=cv2.INTER_AREA)


REDUCED_FLAGS = {
    1: "IMREAD_COLOR",
    2: "IMREAD_REDUCED_COLOR_2",
    4: "IMREAD_REDUCED_COLOR_4",
    8: "IMREAD_REDUCED_COLOR_8",
}


def decode_jpeg(data: bytes, reduce: int = 1) -> np.ndarray:
    """A JPEG's (H,W,3) BGR image at 1/``reduce`` of its size (1, 2, 4, 8). libjpeg scales in the DCT
    domain (``scale_denom``, through OpenCV's IMREAD_REDUCED_COLOR_*): each 8x8 block is inverse-transformed
    at 8/reduce points, so the decode costs less (1088x1920 here: 4.0 ms full, 1.8 ms at 1/2, 1.2 ms at
    1/4) and the image is already low-passed (no aliasing). Raises :class:`SourceError` for bytes that are
    not a decodable JPEG."""
    import cv2

    if reduce not in REDUCED_FLAGS:
        raise ValueError(f"reduce must be one of {sorted(REDUCED_FLAGS)}, got {reduce!r}")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), getattr(cv2, REDUCED_FLAGS[reduce]))
    if img is None:
        raise SourceError(f"a frame's {len(data)} bytes are not a decodable JPEG")
    return img


def full_res_px(xy: np.ndarray, reduce: int) -> np.ndarray:
    """Pixel coordinates in an image reduced by ``reduce`` (:meth:`Frame.decoded`) -> the full-size image's.
    Pixel centres at integers (OpenCV's convention): reduced pixel ``x`` averages full-size pixels
    ``reduce*x .. reduce*x + reduce-1``, whose centre is ``reduce*x + (reduce-1)/2``. NaN stays NaN."""
    if reduce == 1:
        return xy
    return np.asarray(xy) * reduce + (reduce - 1) / 2.0


def jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's start-of-frame marker (no decoding); raises :class:`SourceError` when
    there is none."""
    i, n = 2, len(data)
    if data[:2] != b"\xff\xd8":
        raise SourceError("not a JPEG (no start-of-image marker)")
    while i + 9 < n:
        if data[i] != 0xFF:
            i += 1
            continue
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
            i += 1 if marker == 0xFF else 2
            continue
        seg = int.from_bytes(data[i + 2 : i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            h = int.from_bytes(data[i + 5 : i + 7], "big")
            w = int.from_bytes(data[i + 7 : i + 9], "big")
            return w, h
        i += 2 + seg
    raise SourceError("a JPEG without a start-of-frame marker (no size)")


def is_jpeg(buf) -> bool:
    """Whether ``buf`` (bytes or a uint8 array) starts like a JPEG (SOI marker, then another marker)."""
    b = bytes(np.asarray(buf, np.uint8).ravel()[:3]) if not isinstance(buf, bytes) else buf[:3]
    return b[:2] == b"\xff\xd8" and len(b) == 3 and b[2] == 0xFF


@dataclass(frozen=True)
class SourceInfo:
    width: int
    height: int
    fps: float
    kind: str
    description: str  # safe to log: no credentials


class FrameSource(ABC):
    """One camera. Not thread-safe: one grabbing thread owns it."""

    name: str

    @abstractmethod
    def open(self) -> SourceInfo: ...

    @abstractmethod
    def read(self) -> Frame | None: ...

    @abstractmethod
    def close(self) -> None: ...

    @property
    def live(self) -> bool:
        """A live source is retried after a disconnect; a file just ends."""
        return True

    def check(self) -> None:  # noqa: B027 - most sources have nothing to check before opening
        """Raise the :class:`SourceError` that ``open`` would raise for what can be known without opening
        the device (``capture-run check``); the default: nothing."""

    @property
    def waits_for_consumers(self) -> bool:
        """True for a file that must record every frame (the grabber blocks instead of dropping)."""
        return False

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc):
        self.close()


# ----------------------------------------------------------------------------- barcode


def _block(width: int) -> int:
    return int(max(4, min(24, width // 40)))


def stamp_code(image: np.ndarray, value: int, bits: int = 32) -> None:
    """Write ``value`` as ``bits`` black/white blocks into the top-left of (H,W,3) ``image``, in place."""
    b = _block(image.shape[1])
    for i in range(bits):
        image[0:b, i * b : (i + 1) * b] = 255 if (value >> i) & 1 else 0


def read_code(image: np.ndarray, bits: int = 32) -> int:
    """Decode the value ``stamp_code`` wrote (robust to lossy compression: reads block centres)."""
    b = _block(image.shape[1])
    c0, c1 = b // 4, b - b // 4
    value = 0
    for i in range(bits):
        if image[c0:c1, i * b + c0 : i * b + c1].mean() > 127:
            value |= 1 << i
    return value


# ----------------------------------------------------------------------------- synthetic


_TEXTURES: dict[tuple[int, int], np.ndarray] = {}
_TEX_LOCK = threading.Lock()
_TEX_STEP = 8
_TEX_FRAMES = 32


def _texture(w: int, h: int) -> np.ndarray:
    """A smooth random texture (H, W + 32*8, 3) shared by all synthetic sources of that size."""
    import cv2

    with _TEX_LOCK:
        tex = _TEXTURES.get((w, h))
        if tex is None:
            rng = np.random.default_rng(w * 7919 + h)
            small = rng.integers(
                0, 256, (max(2, h // 16), max(2, (w + _TEX_STEP * _TEX_FRAMES) // 16), 3), dtype=np.uint8
            )
            tex = cv2.resize(small, (w + _TEX_STEP * _TEX_FRAMES, h), interpolation=cv2.INTER_CUBIC)
            _TEXTURES[(w, h)] = tex
        return tex


class SyntheticSource(FrameSource):
    """A generated camera: moving texture, barcode = sequence number, ideal or drifting clock.

    Options (``synthetic:?key=value&...`` in cams.yaml): ``offset_ms`` (device clock offset),
    ``drift_ppm`` (device clock rate error), ``disconnect_at_s`` / ``disconnect_for_s`` (simulated
    cable pull, seconds after open), ``frames`` (end after this many frames), ``drop_every``
    (skip every n-th sequence number: a source-side drop).
    """

    BUFFER_FRAMES = 4

    def __init__(
        self,
        name: str,
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        realtime: bool = True,
        epoch_ns: int | None = None,
        offset_ms: float = 0.0,
        drift_ppm: float = 0.0,
        disconnect_at_s: float | None = None,
        disconnect_for_s: float = 0.0,
        frames: int | None = None,
        drop_every: int = 0,
    ):
        if fps <= 0 or fps > 1000:
            raise SourceError(f"{name}: synthetic fps {fps} is impossible; use 0 < fps <= 1000.")
        self.name = name
        self.w, self.h, self.fps = int(width), int(height), float(fps)
        self.realtime = realtime
        self.epoch_ns = epoch_ns
        self.offset_ns = int(offset_ms * 1e6)
        self.drift = drift_ppm * 1e-6
        self.disconnect_at_s = disconnect_at_s
        self.disconnect_for_s = disconnect_for_s
        self.max_frames = frames
        self.drop_every = int(drop_every)
        self._seq = 0
        self._start_mono: int | None = None
        self._opened = False
        self._disconnected_once = False

    @classmethod
    def from_config(cls, cam: CameraConfig, epoch_ns: int | None = None) -> SyntheticSource:
        try:  # cams.yaml's parser of the options (capture-run check uses the same)
            kw = source_options(cam.source, "synthetic")
        except SourceOptionError as e:
            raise SourceError(f"{cam.name}: {e}") from None
        w, h = cam.resolution or (640, 480)
        return cls(cam.name, w, h, cam.fps or 30.0, realtime=cam.realtime, epoch_ns=epoch_ns, **kw)

    def open(self) -> SourceInfo:
        now = time.monotonic_ns()
        if self._start_mono is None:
            _texture(self.w, self.h)
            now = time.monotonic_ns()
            self._start_mono = now
            # the device clock starts when the camera is opened (a fixed epoch only for non-realtime replays)
            if self.realtime or self.epoch_ns is None:
                self.epoch_ns = mono_to_host_ns(now)
        elif self._in_disconnect(now):
            raise SourceDisconnected(f"{self.name}: synthetic camera is unplugged")
        self._opened = True
        return SourceInfo(self.w, self.h, self.fps, "synthetic", f"synthetic {self.w}x{self.h}@{self.fps:g}")

    def _in_disconnect(self, now_mono: int) -> bool:
        if self.disconnect_at_s is None or self._start_mono is None:
            return False
        t = (now_mono - self._start_mono) / 1e9
        return self.disconnect_at_s <= t < self.disconnect_at_s + self.disconnect_for_s

    def _frame_time_mono(self, seq: int) -> int:
        return self._start_mono + int(round(seq * 1e9 / self.fps))

    def read(self) -> Frame | None:
        if not self._opened:
            raise SourceError(f"{self.name}: read() before open()")
        if self.max_frames is not None and self._seq >= self.max_frames:
            return None
        if self.realtime:
            due = self._frame_time_mono(self._seq)
            wait = due - time.monotonic_ns()
            if wait > 0:
                time.sleep(wait / 1e9)
            now = time.monotonic_ns()
            if self._in_disconnect(now):
                self._opened = False
                # the camera produced nothing while unplugged: skip those sequence numbers
                end = self._start_mono + int((self.disconnect_at_s + self.disconnect_for_s) * 1e9)
                self._seq = int(np.ceil((end - self._start_mono) * self.fps / 1e9))
                raise SourceDisconnected(f"{self.name}: synthetic camera unplugged")
            # a late reader (host slower than fps) gets the frames a driver keeps (BUFFER_FRAMES, like
            # V4L2's ring of buffers); older ones the sensor overwrote: dropped at the source
            late = (now - due) * self.fps / 1e9
            if late > self.BUFFER_FRAMES:
                self._seq += int(late) - self.BUFFER_FRAMES
        seq = self._seq
        self._seq += 1
        if self.drop_every and seq % self.drop_every == self.drop_every - 1:
            seq = self._seq
            self._seq += 1
        ideal_ns = int(round(seq * 1e9 / self.fps))
        t_ns = self.epoch_ns + self.offset_ns + int(round(ideal_ns * (1.0 + self.drift)))
        tex = _texture(self.w, self.h)
        k = seq % _TEX_FRAMES
        img = np.ascontiguousarray(tex[:, k * _TEX_STEP : k * _TEX_STEP + self.w])
        stamp_code(img, seq)
        return Frame(img, t_ns, host_now_ns(), seq)

    def close(self) -> None:
        self._opened = False


# ----------------------------------------------------------------------------- OpenCV devices and streams


class OpenCVSource(FrameSource):
    """USB camera (``usb:N``), V4L2 device path or network stream through cv2.VideoCapture."""

    def __init__(self, cam: CameraConfig, open_timeout_s: float = 5.0, read_timeout_s: float = 5.0):
        self.name = cam.name
        self.cam = cam
        self.open_timeout_s = open_timeout_s
        self.read_timeout_s = read_timeout_s
        self._cap = None
        self._seq = 0
        self._fps = 0.0
        # a USB camera or V4L2 device: its MJPEG written by stream copy (stream_copy: true, the default)
        self._wants_jpeg = cam.stream_copy and cam.kind in ("usb", "device")
        self.jpeg = False  # set by open(): the camera hands out JPEGs (Frame.jpeg), not decoded images
        self.copy: str | None = None  # set by open(): how the recording is written (capture.streamcopy)

    @staticmethod
    def _capture(target, backend, params):
        """cv2.VideoCapture (a seam for tests: a fake capture stands in for a device)."""
        import cv2

        return cv2.VideoCapture(target, backend, params)

    def _first_jpeg_or_decoded(self, cap, buf):
        """The first read with conversion off: a JPEG (the camera streams MJPEG: kept as bytes, stream copy)
        or anything else (YUYV, a decoded image): conversion on again and the frame read again, re-encoded
        as ``codec`` (said in ``self.copy``)."""
        import cv2

        if is_jpeg(buf):
            self.jpeg = True
            self.copy = "stream copy of the camera's MJPEG frames into .avi segments (no re-encoding)"
            return bytes(np.asarray(buf, np.uint8).ravel())
        fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
        name = "".join(chr((fourcc >> 8 * i) & 0xFF) for i in range(4)).strip("\x00 ") or "raw"
        self.copy = (
            f"re-encoded: the camera delivers {name} frames, not MJPEG, which a stream copy needs "
            f"(set its format to MJPEG, or stream_copy: false to silence this)"
        )
        log.warning("%s: recording %s", self.name, self.copy)
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 1)
        ok, img = cap.read()
        return img if ok else None

    def _describe(self) -> str:
        return f"{self.cam.kind} {self.cam.source_redacted}"

    def open(self) -> SourceInfo:
        import cv2

        cam, kind = self.cam, self.cam.kind
        if kind == "usb":
            target: int | str = int(cam.source[4:])
            params = []
        else:
            target = cam.source
            params = [
                cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
                int(self.open_timeout_s * 1000),
                cv2.CAP_PROP_READ_TIMEOUT_MSEC,
                int(self.read_timeout_s * 1000),
            ]
        if kind in ("usb", "device") and isinstance(target, str) and not os.path.exists(target):
            raise SourceError(
                f"{self.name}: device {target} does not exist. Plug the camera in or list devices "
                "with `v4l2-ctl --list-devices`."
            )
        backend = cv2.CAP_FFMPEG if kind == "rtsp" else cv2.CAP_ANY
        cap = self._capture(target, backend, params)
        if not cap.isOpened():
            cap.release()
            if kind == "rtsp":
                raise SourceDisconnected(
                    f"{self.name}: cannot reach stream {self._describe()} within "
                    f"{self.open_timeout_s:g} s. Check the address, port, credentials and "
                    "network, and that the camera streams."
                )
            raise SourceError(
                f"{self.name}: cannot open {self._describe()}: missing, busy (opened by another "
                "program) or not a camera. Close other programs using it or pick another index."
            )
        if cam.resolution is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, cam.resolution[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cam.resolution[1])
        if cam.fps is not None:
            cap.set(cv2.CAP_PROP_FPS, cam.fps)
        if cam.exposure_us is not None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual
            cap.set(cv2.CAP_PROP_EXPOSURE, cam.exposure_us / 100.0)  # V4L2 units of 100 us
        if self._wants_jpeg:
            # ask a USB camera for MJPEG and for its buffers as they come (V4L2: CONVERT_RGB off hands out
            # the driver's bytes): the JPEGs are written as they are, decoded only for the live loop
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*"MJPG"))
            cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        ok, img = cap.read()
        if ok and img is not None and self._wants_jpeg:
            img = self._first_jpeg_or_decoded(cap, img)
        if not ok or img is None:
            cap.release()
            raise SourceError(
                f"{self.name}: {self._describe()} opened but delivers no frames (busy or not a video source)."
            )
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if isinstance(img, bytes):
            w, h = jpeg_size(img)
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        check_delivery(self.name, cam, w, h, fps)
        self._cap = cap
        self._fps = fps or (cam.fps or 30.0)
        self._pending = img
        return SourceInfo(w, h, self._fps, cam.kind, self._describe())

    def read(self) -> Frame | None:
        if self._cap is None:
            raise SourceError(f"{self.name}: read() before open()")
        img, self._pending = self._pending, None
        if img is None:
            ok, img = self._cap.read()
            if not ok or img is None:
                self.close()
                raise SourceDisconnected(f"{self.name}: {self._describe()} stopped delivering frames")
            if self.jpeg:
                img = bytes(np.asarray(img, np.uint8).ravel())
        now = host_now_ns()
        # OpenCV exposes no device clock for V4L2/RTSP that is comparable across cameras: the host stamp
        # at grab is the best estimate (latency is constant per camera and removed by offline sync).
        seq = self._seq
        self._seq += 1
        if isinstance(img, bytes):
            return Frame(None, now, now, seq, jpeg=img)
        return Frame(img, now, now, seq)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def check_delivery(name: str, cam: CameraConfig, w: int, h: int, fps: float) -> None:
    """Reject a device that does not deliver the requested resolution/fps, listing what it gives."""
    if cam.resolution is not None and (w, h) != tuple(cam.resolution):
        raise SourceError(
            f"{name}: requested {cam.resolution[0]}x{cam.resolution[1]} but the device delivers "
            f"{w}x{h}. Set resolution: [{w}, {h}] (or null) in cams.yaml."
        )
    if cam.fps is not None and fps > 0 and abs(fps - cam.fps) > 0.01 * cam.fps + 0.5:
        raise SourceError(
            f"{name}: requested {cam.fps:g} fps but the device delivers {fps:g} fps at {w}x{h}. "
            f"Set fps: {fps:g} (or null), or a resolution at which it reaches {cam.fps:g}."
        )


# ----------------------------------------------------------------------------- files and recordings


SEGMENT_GLOB = "seg_*"


def _segments(folder: Path) -> list[Path]:

    ok = VIDEO_SUFFIXES + (".h264", ".h265")
    return sorted(p for p in folder.glob(SEGMENT_GLOB) if p.suffix.lower() in ok)


def read_frames_csv(path: str | os.PathLike) -> np.ndarray:
    """``raw/<cam>.frames.csv`` -> (T,4) int64 array: frame_index, t_ns, t_host_ns, sequence.

    A last line without its newline (a write cut by a kill) is ignored, never half-parsed.
    """

    path = Path(path)
    text = path.read_text()
    lines = text.split("\n")
    if lines and lines[-1] != "":
        lines = lines[:-1]  # unterminated: not a complete row
    lines = [ln for ln in lines if ln.strip()]
    if not lines:
        return np.zeros((0, 4), np.int64)
    header = lines[0].strip().split(",")
    if header[:4] != ["frame_index", "t_ns", "t_host_ns", "sequence"]:
        raise FormatError(path, "header", f"expected frame_index,t_ns,t_host_ns,sequence, got {header}.")
    try:
        rows = [[int(x) for x in ln.split(",")[:4]] for ln in lines[1:]]
    except ValueError as e:
        raise FormatError(path, None, f"holds a malformed row ({e}).", "Run `capture-run repair`.") from None
    return np.asarray(rows, np.int64).reshape(-1, 4)


class Recording:
    """Frames and timestamps of one recorded camera: a video file or a segment folder ``raw/<cam>/``.

    ``for frame_index, t_ns, image in Recording(path)`` iterates every frame in order. Timestamps come
    from ``raw/<cam>.frames.csv`` beside it when present (t_ns, the device clock), else from the
    container (CAP_PROP_POS_MSEC, first frame = 0). ``Recording(SessionLayout(s).video(cam))``.
    """

    def __init__(self, path: str | os.PathLike, frames_csv: str | os.PathLike | None = None):
        import cv2

        self.path = Path(path)
        if self.path.suffix == ".ffconcat":  # the recorder's index of a segment folder
            self.path = self.path.parent
        if self.path.is_dir():
            self.files = _segments(self.path)
            if not self.files:
                raise SourceError(f"{self.path}: no video segments (seg_*.mp4/.avi) in this folder.")
            default_csv = self.path.parent / f"{self.path.name}.frames.csv"
        elif self.path.exists():
            self.files = [self.path]
            default_csv = self.path.with_name(self.path.stem + ".frames.csv")
        else:
            raise SourceError(f"{self.path}: no such video file or segment folder.")
        csv_path = Path(frames_csv) if frames_csv else default_csv
        self.table = read_frames_csv(csv_path) if csv_path.exists() else None
        cap = cv2.VideoCapture(str(self.files[0]))
        if not cap.isOpened():
            raise SourceError(
                f"{self.files[0]}: not a video OpenCV can decode (wrong format or corrupt). "
                "Pass a .mp4/.avi/.mkv video or a recorded session's raw/<cam>."
            )
        self.fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        cap.release()

    def __len__(self) -> int:
        if self.table is not None:
            return len(self.table)
        import cv2

        n = 0
        for f in self.files:
            cap = cv2.VideoCapture(str(f))
            n += int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            cap.release()
        return n

    def timestamps_ns(self) -> np.ndarray | None:
        """(T,) t_ns from frames.csv, or None when the recording has no timestamp file."""
        return None if self.table is None else self.table[:, 1].copy()

    def __iter__(self) -> Iterator[tuple[int, int, np.ndarray]]:
        return self.iter_frames()

    def iter_frames(self, skip=None) -> Iterator[tuple[int, int, np.ndarray | None]]:
        """Like ``iter(self)``; ``skip(t_ns) -> bool`` may ask to not convert a frame (yields image None)."""
        import cv2

        i = 0
        base_ms = 0.0
        for f in self.files:
            cap = cv2.VideoCapture(str(f))
            if not cap.isOpened():
                raise SourceError(f"{f}: cannot be decoded (corrupt segment?).")
            last_ms = 0.0
            try:
                while cap.grab():
                    if self.table is not None:
                        if i >= len(self.table):
                            log.warning(
                                "%s: more frames than rows in the timestamp file; stopping at %d", f, i
                            )
                            return
                        t_ns = int(self.table[i, 1])
                    else:
                        last_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
                        t_ns = int(round((base_ms + last_ms) * 1e6))
                    img = None
                    if skip is None or not skip(t_ns):
                        ok, img = cap.retrieve()
                        if not ok:
                            break
                    yield i, t_ns, img
                    i += 1
            finally:
                cap.release()
            base_ms += last_ms + (1000.0 / self.fps if self.fps else 0.0)


def open_recording(path: str | os.PathLike) -> Recording:
    """Iterate ``(frame_index, t_ns, image)`` over a recorded video file or segment folder."""
    return Recording(path)


class FileReplaySource(FrameSource):
    """A video (file or recorded segment folder) replayed as a camera at its own timestamps.

    ``t_ns = epoch_ns + (file timestamp - first file timestamp)``; with ``loop`` the timestamps keep
    increasing by one frame period across the wrap, and each frame says how many wraps precede it
    (``Frame.loops``: the scene starts again there, which the live tracker treats as a jump).
    ``realtime=False`` delivers frames as fast as the reader takes them (tests, benchmarks) with the same
    timestamps.
    """

    def __init__(
        self,
        name: str,
        path: str | os.PathLike,
        realtime: bool = True,
        loop: bool = False,
        epoch_ns: int | None = None,
        fps: float | None = None,
        drop_late: bool = False,
        stream_copy: bool = True,
    ):
        self.name = name
        self.path = Path(path)
        self.stream_copy = stream_copy
        self.realtime = realtime
        self.loop = loop
        self.epoch_ns = epoch_ns
        self.want_fps = fps
        self._it: Iterator | None = None
        self._rec: Recording | None = None
        self._seq = 0
        self._t0_file: int | None = None
        self._wrap_ns = 0
        self._loops = 0
        self._last_rel = 0
        self._start_mono: int | None = None
        self._skipped_in_row = 0
        self._max_skip = 60
        self.drop_late = drop_late
        self.copy: str | None = None  # set by open(): how the recording is written (capture.streamcopy)
        self._copy_ext: str | None = None
        self._fps = 0.0

    @property
    def live(self) -> bool:
        return False

    @property
    def waits_for_consumers(self) -> bool:
        return not self.drop_late

    def check(self) -> None:
        """What ``open`` refuses before reading anything: a path that is missing or an empty file."""
        if not self.path.exists():
            raise SourceError(
                f"{self.name}: video file {self.path} does not exist. Fix the source path in cams.yaml."
            )
        if self.path.is_file() and self.path.stat().st_size == 0:
            raise SourceError(f"{self.name}: {self.path} is empty, not a video.")

    def _frames(
        self, rec: Recording | None
    ) -> Iterator[tuple[int, int, np.ndarray | None, list | None, bytes | None]]:
        """(index, file time ns, image, packets to copy or None, JPEG or None) per frame: by stream copy
        (PyAV; an inter-coded stream has every frame decoded, as it needs every packet; an MJPEG file none:
        each frame's JPEG is handed on, decoded only where the live loop takes it) or by OpenCV (late frames
        not converted)."""
        if rec is None:
            from roomcap.capture.streamcopy import PacketReader

            reader = PacketReader(self.path)
            try:
                if reader.intra_jpeg:
                    for i, (t_ns, p) in enumerate(reader.jpegs()):
                        yield i, t_ns, None, [p], bytes(p)
                else:
                    for i, (t_ns, img, packets) in enumerate(reader):
                        yield i, t_ns, img, packets, None
            finally:
                reader.close()
        else:
            for i, t_ns, img in rec.iter_frames(self._late):
                yield i, t_ns, img, None, None

    def open(self) -> SourceInfo:
        self.check()
        from roomcap.capture.streamcopy import copy_plan

        self._copy_ext, self.copy = copy_plan(self.path, self.drop_late, self.stream_copy)
        if self._copy_ext is None and not self.path.is_dir():
            log.info("%s: recording %s: %s", self.name, self.path.name, self.copy)
        rec = Recording(self.path)
        it = self._frames(None if self._copy_ext is not None else rec)
        try:
            first = next(it)
        except StopIteration:
            raise SourceError(
                f"{self.name}: {self.path} holds no decodable frames (not a video, or corrupt)."
            ) from None
        if rec.fps <= 0 and rec.table is None:
            raise SourceError(f"{self.name}: {self.path} has no frame rate or timestamps; cannot replay it.")
        if (
            self.want_fps is not None
            and rec.fps > 0
            and abs(rec.fps - self.want_fps) > 0.01 * self.want_fps + 0.5
        ):
            raise SourceError(
                f"{self.name}: {self.path} is {rec.fps:g} fps but cams.yaml asks for "
                f"{self.want_fps:g} fps. A file replays at its own rate: set fps: {rec.fps:g} or null."
            )
        self._rec, self._it, self._pending = rec, it, first
        self._fps = rec.fps
        if self.epoch_ns is None:
            self.epoch_ns = host_now_ns()
        self._start_mono = None  # pacing starts at the first read, so a slow start drops nothing
        self._t0_file = first[1]
        return SourceInfo(rec.width, rec.height, rec.fps or 0.0, "file", f"file {self.path.name}")

    def read(self) -> Frame | None:
        if self._it is None:
            raise SourceError(f"{self.name}: read() before open()")
        while True:
            item, self._pending = self._pending, None
            if item is None:
                item = next(self._it, None)
                if item is None:
                    if not self.loop:
                        return None
                    period = int(round(1e9 / self._rec.fps)) if self._rec.fps else 0
                    self._wrap_ns = self._last_rel + period
                    self._loops += 1
                    self._it = self._frames(None if self._copy_ext is not None else self._rec)
                    item = next(self._it, None)
                    if item is None:
                        return None
                    self._t0_file = item[1]
            _, t_file, img, packets, jpeg = item
            rel = self._wrap_ns + (t_file - self._t0_file)
            self._last_rel = rel
            seq = self._seq
            self._seq += 1
            if img is None and jpeg is None and self._skipped_in_row < self._max_skip:
                # like a camera, a replay does not wait for a slow host: late frames are dropped
                # (a gap in the sequence numbers); bounded so a very slow host still gets frames
                self._skipped_in_row += 1
                continue
            if img is None and jpeg is None:  # skipped too many in a row: deliver this one
                img = self._decode_again(item)
            self._skipped_in_row = 0
            if self.realtime:
                if self._start_mono is None:
                    self._start_mono = time.monotonic_ns() - rel
                wait = self._start_mono + rel - time.monotonic_ns()
                if wait > 0:
                    time.sleep(wait / 1e9)
            if self._copy_ext is not None:
                return Frame(
                    img,
                    self.epoch_ns + rel,
                    host_now_ns(),
                    seq,
                    keyframe=packets is not None,
                    copy_from=str(self.path),
                    packets=packets,
                    loops=self._loops,
                    jpeg=jpeg,
                )
            return Frame(img, self.epoch_ns + rel, host_now_ns(), seq, loops=self._loops)

    def _late(self, t_file_ns: int) -> bool:
        """Whether the frame at file time ``t_file_ns`` is already more than 2 frame periods late."""
        if not (self.realtime and self.drop_late) or self._start_mono is None or self._t0_file is None:
            return False
        if not self._rec.fps:
            return False
        if self._skipped_in_row >= self._max_skip:
            return False
        rel = self._wrap_ns + (t_file_ns - self._t0_file)
        return time.monotonic_ns() - (self._start_mono + rel) > 2e9 / self._rec.fps

    def _decode_again(self, item):  # only reached if _late said skip but the bound was hit meanwhile
        raise SourceError(f"{self.name}: internal: frame {item[0]} was not decoded")

    def close(self) -> None:
        self._it = None
        self._rec = None


# ----------------------------------------------------------------------------- factory
