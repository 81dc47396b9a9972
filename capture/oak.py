"""Luxonis OAK cameras through depthai (v3 API). The ONLY module of the project that imports depthai.

``oak:`` (the first device found) or ``oak:<mxid-or-serial-or-ip>`` in cams.yaml, with options
``?socket=CAM_A&sync=master|slave|auto``. The pipeline per device:

- ``dai.node.Camera`` on the colour socket (CAM_A), ``requestOutput((w, h), fps=...)``;
- with ``codec: h264|h265``, ``dai.node.VideoEncoder`` on the device (keyframe every
  ``recorder.segment_s`` so the recorder can cut playable segments at keyframes; the host never
  re-encodes); with a host codec, NV12/BGR frames come to the host and the recorder encodes them;
- timestamps: ``msg.getTimestamp()`` is the device clock already synchronised by depthai to the
  host's steady clock (CLOCK_MONOTONIC), converted with ``sources.mono_to_host_ns``; the raw
  device clock (``getTimestampDevice``) is kept for drift diagnosis;
- hardware frame sync: ``Device.setExternalFrameSyncRole(MASTER/SLAVE)`` on devices with an
  FSYNC line (OAK-FFC, OAK-D-Pro/PoE with the M8 sync connector); ``auto`` lets depthai detect.

Everything that needs no device is a pure function here (device selection, fps validation
against the sensor's feature list, message -> Frame conversion) and is tested without one.
"""

from __future__ import annotations

import datetime as _dt
import logging
from dataclasses import dataclass

from roomcap.capture.config import (
    OAK_SOCKETS,
    OAK_SYNC_ROLES,
    CameraConfig,
    SourceOptionError,
    source_options,
)
from roomcap.capture.sources import (
    Frame,
    FrameSource,
    SourceDisconnected,
    SourceError,
    SourceInfo,
    host_now_ns,
    mono_to_host_ns,
)

log = logging.getLogger(__name__)

SYNC_ROLES = OAK_SYNC_ROLES
SOCKETS = OAK_SOCKETS


def _dai():
    try:
        import depthai as dai
    except ImportError as e:  # pragma: no cover - depthai is a dependency
        raise SourceError("OAK cameras need the 'depthai' package (pip install depthai>=3).") from e
    return dai


def depthai_version() -> str:
    return str(_dai().__version__)


@dataclass(frozen=True)
class OakConfig:
    name: str
    device: str | None  # mxid / serial / IP; None = first device
    socket: str = "CAM_A"
    resolution: tuple[int, int] = (1920, 1080)
    fps: float = 30.0
    codec: str = "h264"  # h264 | h265 | mjpeg on the device, or a host codec (frames to the host)
    keyframe_every: int = 15
    quality: int = 80
    exposure_us: int | None = None
    sync: str = "off"

    @property
    def on_device_encoding(self) -> bool:
        return self.codec in ("h264", "h265", "mjpeg")


def oak_config(cam: CameraConfig, segment_s: float = 0.5) -> OakConfig:
    """cams.yaml entry -> OakConfig (validates the ``oak:...?socket=&sync=`` options)."""
    rest = cam.source.split(":", 1)[1] if ":" in cam.source else ""
    dev = rest.partition("?")[0]
    try:  # cams.yaml's parser of the options (capture-run check uses the same)
        opts = source_options(cam.source, "oak")
    except SourceOptionError as e:
        raise SourceError(f"{cam.name}: {e}") from None
    socket = opts.get("socket", "CAM_A")
    sync = opts.get("sync", "off")
    fps = cam.fps or 30.0
    return OakConfig(
        name=cam.name,
        device=dev.strip() or None,
        socket=socket,
        resolution=tuple(cam.resolution) if cam.resolution else (1920, 1080),
        fps=fps,
        codec=cam.codec if cam.codec != "mp4v" else "h264",
        keyframe_every=max(1, int(round(fps * segment_s))),
        quality=cam.quality,
        exposure_us=cam.exposure_us,
        sync=sync,
    )


def select_device(available: list[tuple[str, str]], wanted: str | None, cam: str) -> str:
    """Pick a device id from ``available`` [(device_id, name)] (mxid, serial or IP ``name``)."""
    if not available:
        raise SourceError(
            f"{cam}: no OAK device found. Plug one in (USB3 cable) or check PoE networking; "
            "in a container pass --device-cgroup-rule='c 189:* rmw' -v /dev/bus/usb:/dev/bus/usb."
        )
    if wanted is None:
        return available[0][0]
    for dev_id, name in available:
        if wanted in (dev_id, name):
            return dev_id
    listed = ", ".join(f"{d} ({n})" for d, n in available)
    raise SourceError(
        f"{cam}: OAK device {wanted!r} not found; connected: {listed}. Fix the mxid in cams.yaml."
    )


def check_sensor_mode(features, socket: str, resolution: tuple[int, int], fps: float, cam: str) -> None:
    """Reject a resolution/fps the sensor on ``socket`` cannot deliver (features: device camera features)."""
    feats = [f for f in features if str(f.socket).split(".")[-1] == socket]
    if not feats:
        have = [str(f.socket).split(".")[-1] for f in features]
        raise SourceError(f"{cam}: no camera on socket {socket}; the device has {have}.")
    f = feats[0]
    w, h = resolution
    configs = list(getattr(f, "configs", []) or [])
    if not configs:  # no mode list: trust the ISP to scale
        return
    ok = [c for c in configs if c.width >= w and c.height >= h and c.minFps <= fps <= c.maxFps + 1e-6]
    if not ok:
        modes = ", ".join(f"{c.width}x{c.height}@{c.minFps:g}-{c.maxFps:g}" for c in configs)
        raise SourceError(
            f"{cam}: sensor {getattr(f, 'sensorName', '?')} on {socket} cannot deliver {w}x{h} at "
            f"{fps:g} fps; its modes: {modes}. Lower fps or resolution in cams.yaml."
        )


def _td_ns(td: _dt.timedelta) -> int:
    return (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000


def frame_from_message(msg, encoded: bool, jpeg: bool = False) -> Frame:
    """A depthai ImgFrame/EncodedFrame -> Frame (t_ns on the host clock, sequence = the device's counter).
    ``jpeg``: the device's MJPEG encoder: each frame one JPEG (``Frame.jpeg``), written as it came and
    decoded on the host only where the live loop takes it, like a USB camera's MJPEG."""
    t_ns = mono_to_host_ns(_td_ns(msg.getTimestamp()))
    seq = int(msg.getSequenceNum())
    if encoded and jpeg:
        return Frame(None, t_ns, host_now_ns(), seq, jpeg=bytes(msg.getData()))
    if encoded:
        dai = _dai()
        data = bytes(msg.getData())
        key = msg.getFrameType() == dai.EncodedFrame.FrameType.I
        return Frame(None, t_ns, host_now_ns(), seq, encoded=data, keyframe=key)
    return Frame(msg.getCvFrame(), t_ns, host_now_ns(), seq)


class OakSource(FrameSource):
    """One OAK device (one colour socket) as a FrameSource."""

    def __init__(self, cam: CameraConfig, segment_s: float = 0.5, timeout_s: float = 5.0):
        self.name = cam.name
        self.cam = cam
        self.cfg = oak_config(cam, segment_s)
        self.timeout_s = timeout_s
        self._pipeline = None
        self._queue = None
        self._device = None

    def open(self) -> SourceInfo:
        dai = _dai()
        c = self.cfg
        avail = [(d.getDeviceId(), d.name) for d in dai.Device.getAllAvailableDevices()]
        dev_id = select_device(avail, c.device, self.name)
        try:
            self._device = dai.Device(dai.DeviceInfo(dev_id))
        except RuntimeError as e:
            raise SourceError(f"{self.name}: cannot open OAK {dev_id}: {e} (busy in another program?)") from e
        check_sensor_mode(self._device.getConnectedCameraFeatures(), c.socket, c.resolution, c.fps, self.name)
        if c.sync != "off":
            role = {
                "auto": dai.ExternalFrameSyncRole.AUTO_DETECT,
                "master": dai.ExternalFrameSyncRole.MASTER,
                "slave": dai.ExternalFrameSyncRole.SLAVE,
            }[c.sync]
            ok, why = self._device.setExternalFrameSyncRole(role)
            if not ok:
                raise SourceError(
                    f"{self.name}: hardware frame sync ({c.sync}) not available on {dev_id}: {why}"
                )
        p = dai.Pipeline(self._device)
        node = p.create(dai.node.Camera).build(getattr(dai.CameraBoardSocket, c.socket), sensorFps=c.fps)
        if c.exposure_us is not None:
            node.initialControl.setManualExposure(int(c.exposure_us), 100)
        if c.on_device_encoding:
            out = node.requestOutput(c.resolution, dai.ImgFrame.Type.NV12, fps=c.fps)
            profile = {
                "h265": dai.VideoEncoderProperties.Profile.H265_MAIN,
                "mjpeg": dai.VideoEncoderProperties.Profile.MJPEG,
            }.get(c.codec, dai.VideoEncoderProperties.Profile.H264_MAIN)
            enc = p.create(dai.node.VideoEncoder).build(
                out, frameRate=c.fps, profile=profile, keyframeFrequency=c.keyframe_every, quality=c.quality
            )
            self._queue = enc.out.createOutputQueue(maxSize=8, blocking=False)
        else:
            out = node.requestOutput(c.resolution, dai.ImgFrame.Type.BGR888i, fps=c.fps)
            self._queue = out.createOutputQueue(maxSize=8, blocking=False)
        p.start()
        self._pipeline = p
        return SourceInfo(c.resolution[0], c.resolution[1], c.fps, "oak", f"oak {dev_id} {c.socket}")

    def read(self) -> Frame | None:
        if self._queue is None:
            raise SourceError(f"{self.name}: read() before open()")
        try:
            msg = self._queue.get(timeout=_dt.timedelta(seconds=self.timeout_s))
        except Exception as e:  # XLink errors when the cable is pulled
            self.close()
            raise SourceDisconnected(f"{self.name}: OAK stopped delivering ({e})") from e
        if msg is None:
            self.close()
            raise SourceDisconnected(f"{self.name}: no frame from the OAK within {self.timeout_s:g} s")
        return frame_from_message(msg, self.cfg.on_device_encoding, jpeg=self.cfg.codec == "mjpeg")

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except Exception:
                log.debug("%s: pipeline stop failed", self.name, exc_info=True)
            self._pipeline = None
        if self._device is not None:
            try:
                self._device.close()
            except Exception:
                log.debug("%s: device close failed", self.name, exc_info=True)
            self._device = None
        self._queue = None
