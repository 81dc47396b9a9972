"""Frame sources: synthetic barcodes, file replay at its own timestamps, bad inputs with clear errors."""

from __future__ import annotations

import socket
import time

import cv2
import numpy as np
import pytest

from roomcap.capture.config import parse_config
from roomcap.capture.factory import make_source
from roomcap.capture.sources import (
    FileReplaySource,
    SourceError,
    SyntheticSource,
    open_recording,
    read_code,
    stamp_code,
)


def _cam(source, **kw):
    return parse_config({"cameras": [{"name": "c", "source": source, **kw}]}).cameras[0]


def write_video(path, n=20, fps=25.0, size=(160, 120), fourcc="mp4v"):
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, size)
    assert w.isOpened()
    for i in range(n):
        img = np.full((size[1], size[0], 3), 40 + (i * 7) % 200, np.uint8)
        stamp_code(img, i)
        w.write(img)
    w.release()
    return path


def test_barcode_round_trip_survives_compression(tmp_path):
    p = write_video(tmp_path / "v.mp4", n=12)
    got = [read_code(img) for _, _, img in open_recording(p)]
    assert got == list(range(12))


def test_synthetic_source_frames_and_clock():
    src = SyntheticSource("s", 320, 240, fps=50, realtime=False, epoch_ns=10**18, drift_ppm=100, frames=5)
    src.open()
    frames = [src.read() for _ in range(6)]
    assert frames[-1] is None
    assert [read_code(f.image) for f in frames[:5]] == [0, 1, 2, 3, 4]
    dt = np.diff([f.t_ns for f in frames[:5]])
    assert np.all(dt == round(20_000_000 * (1 + 100e-6)))  # 50 fps with +100 ppm drift


def test_file_replay_timestamps_follow_the_file(tmp_path):
    p = write_video(tmp_path / "v.mp4", n=10, fps=25)
    src = FileReplaySource("f", p, realtime=True, epoch_ns=5_000_000_000)
    info = src.open()
    assert (info.width, info.height, info.fps) == (160, 120, 25.0)
    t0 = time.monotonic()
    frames = []
    while (f := src.read()) is not None:
        frames.append(f)
    elapsed = time.monotonic() - t0
    assert len(frames) == 10
    assert [f.t_ns - 5_000_000_000 for f in frames] == [i * 40_000_000 for i in range(10)]
    assert elapsed > 0.3  # paced at 25 fps: 9 intervals = 0.36 s (measured 0.36)


def test_file_replay_loops_with_increasing_timestamps(tmp_path):
    p = write_video(tmp_path / "v.mp4", n=4, fps=25)
    src = FileReplaySource("f", p, realtime=False, loop=True, epoch_ns=0)
    src.open()
    frames = [src.read() for _ in range(10)]
    assert [f.t_ns for f in frames] == [i * 40_000_000 for i in range(10)]
    # each frame says how often the file started again before it (the live tracker's new segment)
    assert [f.loops for f in frames] == [0] * 4 + [1] * 4 + [2] * 2


def test_not_a_video_file(tmp_path):
    p = tmp_path / "notes.mp4"
    p.write_text("this is not a video\n" * 50)
    with pytest.raises(SourceError, match="not a video|no decodable frames|cannot decode"):
        make_source(_cam(str(p))).open()
    with pytest.raises(SourceError, match="does not exist"):
        make_source(_cam(str(tmp_path / "missing.mp4"))).open()


def test_file_fps_the_file_cannot_deliver(tmp_path):
    p = write_video(tmp_path / "v.mp4", n=3, fps=25)
    with pytest.raises(SourceError, match="25 fps but cams.yaml asks for 60"):
        make_source(_cam(str(p), fps=60)).open()


def test_unreachable_rtsp_fails_fast_without_leaking_credentials():
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cam = _cam(f"rtsp://user:topsecret@127.0.0.1:{port}/live")
    t0 = time.monotonic()
    with pytest.raises(SourceError) as e:
        make_source(cam, timeout_s=1.0).open()
    assert time.monotonic() - t0 < 5  # connection refused is immediate (measured ~0.01 s)
    assert "topsecret" not in str(e.value) and "cannot reach" in str(e.value)


def test_missing_usb_camera():
    with pytest.raises(SourceError, match="cannot open|does not exist"):
        make_source(_cam("usb:63")).open()
    with pytest.raises(SourceError, match="does not exist"):
        make_source(_cam("/dev/video63")).open()


def test_synthetic_options_are_validated():
    from roomcap.capture.config import CameraConfig, ConfigError

    with pytest.raises(ConfigError, match="valid"):  # cams.yaml refuses them (capture-run check too)
        _cam("synthetic:?speed=3")
    with pytest.raises(SourceError, match="valid"):  # and so does the source, by the same parser
        make_source(CameraConfig("c", "synthetic:?speed=3"))


def test_frames_csv_ignores_an_unterminated_last_row(tmp_path):
    from roomcap.capture.sources import read_frames_csv

    p = tmp_path / "c.frames.csv"
    p.write_text("frame_index,t_ns,t_host_ns,sequence\n0,10,11,0\n1,20,21,1\n2,30,3")
    assert read_frames_csv(p).tolist() == [[0, 10, 11, 0], [1, 20, 21, 1]]


def test_device_that_cannot_deliver_the_requested_mode():
    from roomcap.capture.sources import check_delivery

    cam = _cam("usb:0", fps=60, resolution=[1920, 1080])
    check_delivery("c", cam, 1920, 1080, 60.0)
    with pytest.raises(SourceError, match="requested 60 fps but the device delivers 30 fps"):
        check_delivery("c", cam, 1920, 1080, 30.0)
    with pytest.raises(SourceError, match="delivers 640x480"):
        check_delivery("c", cam, 640, 480, 60.0)


@pytest.mark.parametrize("drop_late", [False, True])
def test_file_replay_on_a_slow_host(tmp_path, drop_late):
    p = write_video(tmp_path / "v.mp4", n=20, fps=50)
    src = FileReplaySource("f", p, realtime=True, epoch_ns=0, drop_late=drop_late)
    src.open()
    seqs = []
    while (f := src.read()) is not None:
        seqs.append(f.sequence)
        time.sleep(0.06)  # the host takes 3 frame periods per frame
    if drop_late:
        assert len(seqs) < 12 and seqs[-1] >= 17  # like a camera: late frames are gone (measured 7 of 20)
    else:
        assert seqs == list(range(20))  # every frame, late


def test_grabber_waits_for_the_writer_when_a_file_must_be_recorded_whole(tmp_path):
    import queue
    import threading

    from roomcap.capture.grabber import Grabber

    p = write_video(tmp_path / "v.mp4", n=30, fps=30)
    src = FileReplaySource("f", p, realtime=False, epoch_ns=0)
    info = src.open()
    q: queue.Queue = queue.Queue(maxsize=2)
    g = Grabber("f", src, info, {"writer": q}, threading.Event())
    g.start()
    got = []
    time.sleep(0.2)  # a slow writer: the queue is full for a while
    while (f := q.get(timeout=5)) is not None:
        got.append(f.sequence)
    g.join()
    assert got == list(range(30)) and g.stats.dropped_queue["writer"] == 0
