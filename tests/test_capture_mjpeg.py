"""MJPEG sources handed on as JPEGs (``Frame.jpeg``): recorded as they came (stream copy: every frame's bytes
identical, its timestamp row kept, segments and join as for every recording), decoded only where asked, at a
reduced size with the keypoints mapped back to full-size pixels; a USB camera that does not stream MJPEG is
re-encoded and says so."""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np
import pytest

from roomcap.capture.config import ConfigError, auto_reduce, parse_config
from roomcap.capture.recorder import Recorder
from roomcap.capture.sources import (
    Frame,
    FrameSource,
    OpenCVSource,
    SourceInfo,
    decode_jpeg,
    full_res_px,
    jpeg_size,
    read_frames_csv,
)
from roomcap.capture.streamcopy import recording_mode

av = pytest.importorskip("av", reason="PyAV not installed")


def _jpeg(i: int, w: int = 160, h: int = 120) -> bytes:
    img = np.zeros((h, w, 3), np.uint8)
    img[:, (i * 7) % w] = 255
    img[(i * 5) % h, :, 1] = 200
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return buf.tobytes()


def _packets(path) -> list[bytes]:
    with av.open(str(path)) as c:
        return [bytes(p) for p in c.demux(c.streams.video[0]) if p.size]


class JpegCamera(FrameSource):
    """A stand-in for a USB camera streaming MJPEG: ``n`` JPEGs at ``fps``, host-clock timestamps."""

    name = "usb"

    def __init__(self, n: int = 45, fps: float = 30.0):
        self.n, self.fps, self.i, self.t0 = n, fps, 0, 0
        self.sent: list[tuple[bytes, int]] = []

    def open(self) -> SourceInfo:
        self.t0 = time.time_ns()
        return SourceInfo(160, 120, self.fps, "usb", "a JPEG camera")

    def read(self) -> Frame | None:
        if self.i >= self.n:
            return None
        data, t = _jpeg(self.i), self.t0 + int(self.i * 1e9 / self.fps)
        self.sent.append((data, t))
        self.i += 1
        return Frame(None, t, t, self.i - 1, jpeg=data)

    def close(self) -> None:
        pass

    @property
    def live(self) -> bool:
        return False

    @property
    def waits_for_consumers(self) -> bool:
        return True


def test_a_usb_cameras_jpegs_are_recorded_as_they_came_with_their_timestamps(tmp_path):
    cfg = parse_config({"cameras": [{"name": "usb", "source": "usb:0"}], "recorder": {"segment_s": 0.3}})
    cam = JpegCamera()
    summary = Recorder(cfg, tmp_path / "S", duration_s=30, sources={"usb": cam}, handle_signals=False).run()
    c = summary["cameras"]["usb"]
    assert c["frames_written"] == 45 and c["segments"] > 1 and c["joined"], c  # several kill-safe segments
    assert c["video"].endswith(".avi")
    assert _packets(tmp_path / "S" / c["video"]) == [d for d, _ in cam.sent]  # byte for byte, in order
    rows = read_frames_csv(tmp_path / "S" / "raw" / "usb.frames.csv")
    assert rows[:, 0].tolist() == list(range(45)) and rows[:, 1].tolist() == [t for _, t in cam.sent]
    with av.open(str(tmp_path / "S" / c["video"])) as v:  # a playable video of the same frames (FFmpeg's
        first = next(v.decode(video=0)).to_ndarray(format="bgr24")  # and libjpeg's chroma upsampling differ)
    assert np.abs(first.astype(int) - decode_jpeg(cam.sent[0][0]).astype(int)).mean() < 2


def test_an_mjpeg_file_hands_on_its_jpegs_undecoded(tmp_path):
    from roomcap.capture.sources import FileReplaySource

    src = tmp_path / "m.avi"
    with av.open(str(src), "w") as c:
        s = c.add_stream("mjpeg", rate=30)
        s.width, s.height, s.pix_fmt = 160, 120, "yuvj420p"
        for i in range(12):
            for p in s.encode(av.VideoFrame.from_ndarray(decode_jpeg(_jpeg(i)), format="bgr24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    rep = FileReplaySource("a", src, realtime=False)
    rep.open()
    frames = [rep.read() for _ in range(12)]
    assert rep.read() is None
    assert all(f.image is None and f.keyframe and f.packets for f in frames)  # nothing decoded
    assert [f.jpeg for f in frames] == _packets(src)
    assert frames[3].decoded().shape == (120, 160, 3) and frames[3].decoded(2).shape == (60, 80, 3)


def test_reduced_decoding_and_the_map_back_to_full_size_pixels():
    """A smooth blob at a known full-size position, JPEG-encoded, decoded at 1/1, 1/2, 1/4: its centroid in
    the reduced image mapped back (full_res_px) lands on the full-size position."""
    h, w = 480, 640
    yy, xx = np.mgrid[0:h, 0:w]
    x0, y0 = 301.0, 187.0
    blob = 255 * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * 8.0**2))
    img = np.repeat(blob[..., None], 3, axis=2).astype(np.uint8)
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    assert jpeg_size(data) == (w, h)
    for r in (1, 2, 4):
        small = decode_jpeg(data, r)[..., 1].astype(float)
        assert small.shape == (h // r, w // r)
        wgt = np.where(small > 40, small, 0.0)
        sy, sx = np.mgrid[0 : small.shape[0], 0 : small.shape[1]]
        cx, cy = (wgt * sx).sum() / wgt.sum(), (wgt * sy).sum() / wgt.sum()
        back = full_res_px(np.array([cx, cy]), r)
        assert np.abs(back - [x0, y0]).max() < 0.35, (r, back)
    # the map itself: reduced pixel x covers full pixels r*x .. r*x + r-1; NaN stays NaN
    np.testing.assert_array_equal(full_res_px(np.array([0.0, 10.0, np.nan]), 2), [0.5, 20.5, np.nan])


def test_scale_result_maps_boxes_and_keypoints_back():
    from roomcap.keypoints.pipeline_config import FrameResult
    from roomcap.pipeline.live import scale_result

    res = FrameResult(
        np.array([[10, 20, 30, 40, 0.9]], np.float32),
        np.array([[[5.0, 6.0], [np.nan, np.nan]]], np.float32),
        np.array([[0.8, 0.0]], np.float32),
    )
    out = scale_result(res, 4)
    np.testing.assert_allclose(out.boxes, [[41.5, 81.5, 121.5, 161.5, 0.9]])
    np.testing.assert_allclose(out.xy_px, [[[21.5, 25.5], [np.nan, np.nan]]])
    np.testing.assert_array_equal(out.score, res.score)
    assert scale_result(res, 1) is res


def test_decode_reduce_is_checked_and_auto_keeps_720_px():
    assert auto_reduce(1088, 1920) == 2 and auto_reduce(640, 480) == 1 and auto_reduce(3840, 2160) == 4
    assert parse_config({"cameras": [{"name": "a", "source": "synthetic:"}], "live": {"decode_reduce": 4}})
    with pytest.raises(ConfigError, match="decode_reduce"):
        parse_config({"cameras": [{"name": "a", "source": "synthetic:"}], "live": {"decode_reduce": 3}})


class FakeCapture:
    """cv2.VideoCapture of a USB camera: with CONVERT_RGB off, its driver's buffers (a JPEG, or YUYV)."""

    def __init__(self, jpeg: bool):
        self.jpeg, self.convert, self.reads = jpeg, 1, 0

    def isOpened(self):
        return True

    def set(self, prop, value):
        if prop == cv2.CAP_PROP_CONVERT_RGB:
            self.convert = value
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_FOURCC:
            return float(cv2.VideoWriter_fourcc(*("MJPG" if self.jpeg else "YUYV")))
        return {cv2.CAP_PROP_FRAME_WIDTH: 160, cv2.CAP_PROP_FRAME_HEIGHT: 120, cv2.CAP_PROP_FPS: 30}.get(
            prop, 0
        )

    def read(self):
        self.reads += 1
        if self.convert:
            return True, np.zeros((120, 160, 3), np.uint8)
        if self.jpeg:
            return True, np.frombuffer(_jpeg(self.reads), np.uint8).reshape(1, -1)
        return True, np.zeros((1, 160 * 120 * 2), np.uint8)  # YUYV bytes

    def release(self):
        pass


@pytest.mark.parametrize("streams_mjpeg", [True, False])
def test_a_usb_camera_gives_jpegs_or_is_reencoded_and_says_so(monkeypatch, streams_mjpeg, capsys, tmp_path):
    cfg = parse_config({"cameras": [{"name": "a", "source": "usb:0"}]})
    cam = cfg.cameras[0]
    fake = FakeCapture(streams_mjpeg)
    monkeypatch.setattr(OpenCVSource, "_capture", staticmethod(lambda *a: fake))
    src = OpenCVSource(cam)
    info = src.open()
    assert (info.width, info.height) == (160, 120)
    f1, f2 = src.read(), src.read()
    if streams_mjpeg:
        assert src.jpeg and f1.image is None and jpeg_size(f1.jpeg) == (160, 120) and f2.jpeg != f1.jpeg
        assert recording_mode(cam, src).startswith("stream copy of the camera's MJPEG frames")
    else:
        assert not src.jpeg and f1.jpeg is None and f1.image.shape == (120, 160, 3)
        assert "re-encoded: the camera delivers YUYV frames, not MJPEG" in recording_mode(cam, src)
        assert recording_mode(cam, src).endswith("as mp4v")
    # what `check` says before opening it
    from roomcap.capture.cli import main

    (tmp_path / "cams.yaml").write_text("cameras:\n  - {name: a, source: 'usb:0'}\n")
    assert main(["check", "--cameras", str(tmp_path / "cams.yaml")]) == 0
    assert "MJPEG asked of the camera: its JPEGs written as they come" in capsys.readouterr().out


def test_the_live_stages_are_built_on_the_live_thread_while_the_cameras_start(tmp_path):
    """``build_in_background``: the runner takes sets only once the stages are built (on its own thread);
    of the sets that came meanwhile only the newest is kept, the others dropped and counted."""
    from roomcap.capture.live import LiveRunner
    from roomcap.capture.sync import FrameSet

    cfg = parse_config(
        {"cameras": [{"name": "a", "source": "synthetic:"}], "live": {"stages": ["keypoints"]}}
    )
    built = threading.Event()
    seen = []

    def build(cfg_, layout):
        assert threading.current_thread().name == "live"
        time.sleep(0.3)
        built.set()
        return {"keypoints": lambda step: seen.append(step.frameset.index)}, {}

    live = LiveRunner(cfg, tmp_path / "S", build_stages=build, build_in_background=True)
    assert live.stages == {} and live.planned == ("keypoints",)
    live.start()
    for i in range(3):  # offered while the stages are built: never processed
        live._offer(FrameSet(i, i, {"a": Frame(None, i, i, i)}))
    assert built.wait(5)
    deadline = time.monotonic() + 5
    while live.stats.processed == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    live.stop()
    # the newest set offered while the stages were built is the first processed; the older ones dropped
    assert seen == [2] and live.stats.skipped == 2 and live.stages_ready_ns is not None


def test_the_live_2d_on_half_size_jpegs_finds_the_full_size_keypoints(tmp_path):
    """The demo's frames as JPEGs through the live keypoints stage decoded at 1/2 (the auto factor for
    1088x1920) and at full size: the same people, keypoints within a few pixels in full-size pixels (measured
    median 0.9 px over 12 sets; a missing map back would put them 480+ px off)."""
    from dataclasses import replace

    from conftest import need_shared

    from roomcap.capture.live import LiveStep
    from roomcap.capture.session import SessionLayout
    from roomcap.capture.sync import FrameSet
    from roomcap.pipeline.live import LiveContext, _keypoints

    need_shared("models")
    videos = need_shared("data", "pose2sim", "demo-wheel-0.10.49", "Demo_MultiPerson", "videos")
    cams = ["cam01", "cam02"]
    jpegs = {}
    for c in cams:
        cap = cv2.VideoCapture(str(videos / f"{c}.mp4"))
        ok, img = cap.read()
        cap.release()
        assert ok
        jpegs[c] = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    cfg = parse_config({"cameras": [{"name": c, "source": str(videos / f"{c}.mp4")} for c in cams]})
    found = {}
    for r in (1, 2):
        stage = _keypoints(
            LiveContext(replace(cfg, live=replace(cfg.live, decode_reduce=r)), SessionLayout(tmp_path), None)
        )
        try:
            step = LiveStep(
                FrameSet(0, 0, {c: Frame(None, 0, 0, 0, jpeg=jpegs[c]) for c in cams}), tuple(cams)
            )
            stage(step)
        finally:
            stage.close()
        found[r] = step.outputs["detections"]
        assert stage.reduce_of == {} or set(stage.reduce_of.values()) == {r}
    d = []
    for c in cams:
        a, b = found[1][c], found[2][c]
        assert len(a.xy_px) >= 2 and len(b.xy_px) == len(a.xy_px)  # two participants (and the bystander)
        for i in range(len(a.xy_px)):
            ca = np.nanmean(a.xy_px[i], 0)
            j = int(np.argmin([np.linalg.norm(np.nanmean(p, 0) - ca) for p in b.xy_px]))
            ok = (a.score[i] > 0.3) & (b.score[j] > 0.3)
            d.extend(np.linalg.norm(a.xy_px[i][ok] - b.xy_px[j][ok], axis=1))
    assert len(d) > 20 and np.median(d) < 4.0, np.median(d)


class StallingCamera(JpegCamera):
    """Paced at ``fps``; after frame ``at`` its read blocks ``for_s`` (a camera that stops sending, no
    error), then it goes on."""

    def __init__(self, n, fps, at=None, for_s=0.0):
        super().__init__(n, fps)
        self.at, self.for_s = at, for_s

    def read(self):
        if self.i == self.at:
            time.sleep(self.for_s)
        time.sleep(1.0 / self.fps)
        return super().read()


def test_a_stalling_camera_is_reported_and_the_others_go_on(tmp_path, capsys):
    from roomcap.capture.cli import _print_summary

    cfg = parse_config({"cameras": [{"name": "a", "source": "usb:0"}, {"name": "b", "source": "usb:1"}]})
    a, b = StallingCamera(40, 20.0, at=10, for_s=1.6), StallingCamera(40, 20.0)
    rec = Recorder(cfg, tmp_path / "S", duration_s=30, sources={"a": a, "b": b}, handle_signals=False)
    summary = rec.run()
    cams = summary["cameras"]
    assert len(cams["a"]["stalls"]) == 1 and 1.0 <= cams["a"]["stalls"][0]["seconds"] < 5.0
    assert "stalls" not in cams["b"]
    assert cams["a"]["frames_written"] == cams["b"]["frames_written"] == 40  # b went on meanwhile
    _print_summary(tmp_path / "S", rec, summary, [], None)
    out = capsys.readouterr().out
    part_a, part_b = out.split("  a: ")[1].split("  b: ")
    assert "stalled 1 time(s): no frame for up to" in part_a and "stalled" not in part_b


def test_the_live_outputs_default_port_is_the_servers():
    """live_outputs keeps its own copy of the page's port so that capture-run does not import the server
    (aiohttp) unless --view asks for it."""
    from roomcap.pipeline.live_outputs import DEFAULT_PORT
    from roomcap.pipeline.liveview.server import DEFAULT_PORT as SERVER_PORT

    assert DEFAULT_PORT == SERVER_PORT


def test_capture_run_as_a_command_flushes_its_output_and_keeps_its_exit_code(tmp_path):
    """``python -m roomcap.pipeline.live`` leaves without the interpreter's teardown (os._exit): what it
    printed is flushed first, the exit code is the command's."""
    import subprocess
    import sys

    (tmp_path / "cams.yaml").write_text("cameras:\n  - {name: a, source: 'synthetic:'}\n")
    (tmp_path / "bad.yaml").write_text("cameras: 3\n")
    cmd = [sys.executable, "-m", "roomcap.pipeline.live", "check", "--cameras"]
    ok = subprocess.run([*cmd, str(tmp_path / "cams.yaml")], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "a: synthetic" in ok.stdout and "recording: re-encoded as mp4v" in ok.stdout
    bad = subprocess.run([*cmd, str(tmp_path / "bad.yaml")], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "capture-run: error:" in bad.stderr


def test_the_2d_of_the_next_set_overlaps_the_3d_of_the_last_in_order(tmp_path):
    """Pipelined live loop: the first stage runs on ``live``, the others on ``live-3d``, every set through
    both in the order taken, the second stage never sees a set the first has not finished."""
    from roomcap.capture.live import LiveRunner
    from roomcap.capture.sync import FrameSet

    cfg = parse_config({"cameras": [{"name": "a", "source": "synthetic:"}]})
    log = []

    def first(step):
        time.sleep(0.02)
        log.append(("2d", step.frameset.index, threading.current_thread().name))
        step.outputs["seen"] = True

    def second(step):
        assert step.outputs.get("seen")
        time.sleep(0.03)
        log.append(("3d", step.frameset.index, threading.current_thread().name))

    live = LiveRunner(cfg, tmp_path / "S", stages={"keypoints": first, "track": second})
    live.start()
    for i in range(12):
        live._offer(FrameSet(i, i, {"a": Frame(None, i, i, i)}))
        time.sleep(0.025)
    time.sleep(0.2)
    live.stop()
    d2 = [i for k, i, _ in log if k == "2d"]
    d3 = [i for k, i, _ in log if k == "3d"]
    assert d2 == sorted(d2) and d3 == sorted(d3) and set(d3) <= set(d2) and len(d3) >= 2
    assert {t for k, _, t in log if k == "2d"} == {"live"} and {t for k, _, t in log if k == "3d"} == {
        "live-3d"
    }
    assert live.stats.processed == len(d3)
