"""OAK (depthai v3): config, device selection, sensor modes, timestamps: all without a device."""

from __future__ import annotations

import datetime as dt
import types

import numpy as np
import pytest

from roomcap.capture.config import parse_config
from roomcap.capture.factory import make_source
from roomcap.capture.oak import OakSource, check_sensor_mode, frame_from_message, oak_config, select_device
from roomcap.capture.segments import SegmentWriter
from roomcap.capture.sources import SourceError, host_now_ns, mono_to_host_ns, read_frames_csv


def _cam(source="oak:", **kw):
    return parse_config({"cameras": [{"name": "oak1", "source": source, **kw}]}).cameras[0]


def test_oak_config_from_cams_yaml():
    c = oak_config(
        _cam("oak:1844301041B2A0F500?socket=cam_a&sync=master", fps=60, codec="h265", resolution=[1280, 720]),
        segment_s=0.5,
    )
    assert (c.device, c.socket, c.sync, c.codec, c.fps) == (
        "1844301041B2A0F500",
        "CAM_A",
        "master",
        "h265",
        60,
    )
    assert c.keyframe_every == 30 and c.on_device_encoding  # a keyframe per 0.5 s segment
    d = oak_config(_cam("oak:"))
    assert (
        d.device is None and d.codec == "h264" and d.resolution == (1920, 1080)
    )  # default: encode on device
    from roomcap.capture.config import CameraConfig, ConfigError

    for src, needle in (("oak:x?speed=1", "valid"), ("oak:x?socket=CAM_Z", "CAM_A")):
        with pytest.raises(ConfigError, match=needle):  # cams.yaml (and capture-run check) refuse it
            _cam(src)
        with pytest.raises(SourceError, match=needle):  # the source too, by the same parser
            oak_config(CameraConfig("oak1", src))


def test_device_selection_messages():
    avail = [("1844301041B2A0F500", "1.2.3"), ("14442C10D13EABCE00", "192.168.1.44")]
    assert select_device(avail, None, "c") == "1844301041B2A0F500"
    assert select_device(avail, "192.168.1.44", "c") == "14442C10D13EABCE00"
    with pytest.raises(SourceError, match="not found; connected: 1844"):
        select_device(avail, "nope", "c")
    with pytest.raises(SourceError, match="no OAK device found"):
        select_device([], None, "c")


def test_no_device_attached_is_a_clear_error():
    import depthai as dai

    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK is attached")
    with pytest.raises(SourceError, match="no OAK device found"):
        make_source(_cam("oak:")).open()


def test_fps_the_sensor_cannot_deliver():
    mode = types.SimpleNamespace(width=1920, height=1080, minFps=1.0, maxFps=60.0)
    feat = types.SimpleNamespace(socket="CameraBoardSocket.CAM_A", sensorName="IMX378", configs=[mode])
    check_sensor_mode([feat], "CAM_A", (1920, 1080), 30, "c")
    with pytest.raises(SourceError, match="cannot deliver 1920x1080 at 120 fps; its modes: 1920x1080@1-60"):
        check_sensor_mode([feat], "CAM_A", (1920, 1080), 120, "c")
    with pytest.raises(SourceError, match="no camera on socket CAM_B"):
        check_sensor_mode([feat], "CAM_B", (1920, 1080), 30, "c")


def test_message_timestamps_map_to_the_host_clock_and_encoded_segments_are_written(tmp_path):
    import depthai as dai

    mono_ns = 5_000_123_456_000
    msgs = []
    for i in range(6):  # recorded metadata: an I frame then P frames, 30 fps
        m = dai.EncodedFrame()
        m.setTimestamp(dt.timedelta(microseconds=(mono_ns + i * 33_333_000) // 1000))
        m.setSequenceNum(100 + i)
        m.setData(
            np.frombuffer(b"\x00\x00\x00\x01" + bytes([0x65 if i % 3 == 0 else 0x41]) + b"xx", np.uint8)
        )
        m.setFrameType(dai.EncodedFrame.FrameType.I if i % 3 == 0 else dai.EncodedFrame.FrameType.P)
        msgs.append(m)
    frames = [frame_from_message(m, encoded=True) for m in msgs]
    assert frames[0].t_ns == mono_to_host_ns(mono_ns) and frames[1].t_ns - frames[0].t_ns == 33_333_000
    assert [f.keyframe for f in frames] == [True, False, False, True, False, False]
    assert [f.sequence for f in frames] == list(range(100, 106))
    assert abs(frames[0].t_host_ns - host_now_ns()) < 5e9
    w = SegmentWriter(tmp_path / "oak1", tmp_path / "oak1.frames.csv", "h264", 30, segment_s=0.05)
    for f in frames:
        w.write(f)
    w.close()
    segs = sorted((tmp_path / "oak1").glob("seg_*.h264"))
    assert len(segs) == 2  # cut only at keyframes, never inside a GOP
    assert segs[0].read_bytes().startswith(b"\x00\x00\x00\x01\x65")
    tab = read_frames_csv(tmp_path / "oak1.frames.csv")
    assert list(tab[:, 3]) == list(range(100, 106))
    img = dai.ImgFrame()
    img.setTimestamp(dt.timedelta(seconds=2))
    img.setSequenceNum(9)
    img.setCvFrame(np.full((4, 6, 3), 7, np.uint8), dai.ImgFrame.Type.BGR888i)
    f = frame_from_message(img, encoded=False)
    assert f.image.shape == (4, 6, 3) and f.t_ns == mono_to_host_ns(2_000_000_000) and f.sequence == 9


def test_only_oak_module_imports_depthai():
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    pat = re.compile(r"^\s*(import depthai|from depthai)\b", re.M)
    pkgs = ("capture", "calibrate", "keypoints", "triangulate", "track", "forecast", "pipeline", "synthetic")
    offenders = [
        str(p.relative_to(root))
        for pkg in pkgs
        for p in (root / pkg).rglob("*.py")
        if p.name != "oak.py" and pat.search(p.read_text())
    ]
    assert offenders == []


@pytest.mark.hardware
def test_oak_device_records_with_device_timestamps():
    import depthai as dai

    if not dai.Device.getAllAvailableDevices():
        pytest.skip("no OAK device attached")
    src = OakSource(_cam("oak:", fps=30, resolution=[1280, 720]))
    info = src.open()
    try:
        frames = [src.read() for _ in range(30)]
    finally:
        src.close()
    assert info.fps == 30
    dt_ms = np.diff([f.t_ns for f in frames]) / 1e6
    assert abs(np.median(dt_ms) - 33.3) < 2
    assert all(0 <= (f.t_host_ns - f.t_ns) / 1e6 < 200 for f in frames)  # device clock synced to host
    assert any(f.keyframe for f in frames)


def test_the_devices_mjpeg_frames_are_jpegs_written_as_they_came(tmp_path):
    """codec: mjpeg on an OAK: its encoder's frames become ``Frame.jpeg`` (decoded on the host only where the
    live loop takes one), recorded as they came into .avi segments."""
    import cv2

    dai = pytest.importorskip("depthai")
    from roomcap.capture.streamcopy import recording_mode

    cam = parse_config({"cameras": [{"name": "o", "source": "oak:", "codec": "mjpeg"}]}).cameras[0]
    assert oak_config(cam).on_device_encoding and "JPEGs written as they come" in recording_mode(cam)
    frames = []
    for i in range(4):
        img = np.full((48, 64, 3), 40 * i, np.uint8)
        m = dai.EncodedFrame()
        m.setTimestamp(dt.timedelta(microseconds=5_000_000 + i * 33_333))
        m.setSequenceNum(i)
        m.setData(np.frombuffer(cv2.imencode(".jpg", img)[1].tobytes(), np.uint8))
        frames.append(frame_from_message(m, encoded=True, jpeg=True))
    assert all(f.image is None and f.jpeg[:2] == b"\xff\xd8" for f in frames)
    assert frames[2].decoded().shape == (48, 64, 3)
    w = SegmentWriter(tmp_path / "o", tmp_path / "o.frames.csv", "mjpeg", 30, segment_s=10)
    for f in frames:
        w.write(f)
    w.close()
    (seg,) = sorted((tmp_path / "o").glob("seg_*.avi"))
    av = pytest.importorskip("av")
    with av.open(str(seg)) as c:
        assert [bytes(p) for p in c.demux(c.streams.video[0]) if p.size] == [f.jpeg for f in frames]
