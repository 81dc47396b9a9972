"""Session video pipeline: chunked writing that resumes after a kill, a video that stops decoding mid-way,
video size against the calibration, run_session on a session folder. Tiny ONNX models keep it fast."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from keypoints_tiny import make_dets_model, make_simcc_model

from roomcap.core.errors import FormatError
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.pipeline import KeypointPipeline, KeypointPipelineConfig
from roomcap.keypoints.video import check_size, run_session, run_videos

W, H = 160, 120


@pytest.fixture
def tiny_set(tmp_path, monkeypatch):
    d = tmp_path / "models"
    d.mkdir()
    monkeypatch.setenv("ROOMCAP_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("ROOMCAP_MODELS", str(d))
    kp = np.stack([np.arange(17) * 8 + 20, np.arange(17) * 10 + 30], 1).astype(np.float32)
    make_simcc_model(d, kp)
    make_dets_model(d, np.array([[40, 40, 200, 400, 0.9]], np.float32), np.array([0]))
    return KeypointPipelineConfig(model_set="tiny_det+tiny_simcc", refine_passes=0, min_box_px=1)


def write_video(path, n, size=(W, H), seed=0):
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, size)
    rng = np.random.default_rng(seed)
    for _ in range(n):
        w.write(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    w.release()
    return path


class Killed(Exception):
    pass


class DiesAfter:
    """A pipeline that is killed at its n-th call (as if the process died)."""

    def __init__(self, pipe, n):
        self.pipe, self.n = pipe, n

    def __getattr__(self, k):
        return getattr(self.pipe, k)

    def __call__(self, imgs, streams=None):
        self.n -= 1
        if self.n < 0:
            raise Killed
        return self.pipe(imgs, streams)


def test_killed_run_resumes_after_last_chunk(tmp_path, tiny_set):
    vids = {c: write_video(tmp_path / f"{c}.avi", 9, seed=i) for i, c in enumerate(["cam01", "cam02"])}
    ref = run_videos(vids, tmp_path / "ref", tiny_set, chunk_frames=2)
    pipe = KeypointPipeline(tiny_set)
    with pytest.raises(Killed):
        run_videos(vids, tmp_path / "out", tiny_set, chunk_frames=2, pipeline=DiesAfter(pipe, 5))
    assert not (tmp_path / "out" / "cam01.npz").exists()
    assert len(list((tmp_path / "out" / ".cam01.parts").glob("*.npz"))) == 2  # frames 0-3 survived
    rep = run_videos(vids, tmp_path / "out", tiny_set, chunk_frames=2, pipeline=pipe)
    assert rep.resumed_from == {"cam01": 4, "cam02": 4}
    assert not (tmp_path / "out" / ".cam01.parts").exists()
    for c in vids:
        a, b = Detections.load(ref.paths[c]), Detections.load(rep.paths[c])
        assert a.frame_index.tolist() == b.frame_index.tolist() == list(range(9))
        np.testing.assert_array_equal(a.xy_px, b.xy_px)
        assert b.skeleton == "body19" and b.model == "tiny_det+tiny_simcc" and len(b.model_sha256) == 129
        assert b.image_size_wh == (W, H)
        assert np.isfinite(b.xy_px[:, 0]).all() and np.allclose(b.t_ns[1] - b.t_ns[0], 1e8)


def test_chunks_of_another_model_are_not_reused(tmp_path, tiny_set):
    vids = {"cam01": write_video(tmp_path / "cam01.avi", 4)}
    pipe = KeypointPipeline(tiny_set)
    with pytest.raises(Killed):
        run_videos(vids, tmp_path / "out", tiny_set, chunk_frames=2, pipeline=DiesAfter(pipe, 3))
    other = KeypointPipelineConfig(
        model_set=tiny_set.model_set, skeleton="model", refine_passes=0, min_box_px=1
    )
    rep = run_videos(vids, tmp_path / "out", other, chunk_frames=2)
    assert rep.resumed_from == {} and Detections.load(rep.paths["cam01"]).skeleton == "coco17"


def test_video_that_stops_decoding_keeps_the_frames_done(tmp_path, tiny_set, caplog):
    good = write_video(tmp_path / "cam01.avi", 12)
    bad = tmp_path / "cam02.avi"
    data = write_video(tmp_path / "tmp.avi", 12, seed=1).read_bytes()
    bad.write_bytes(data[: len(data) // 2])  # truncated: the header still announces 12 frames
    with caplog.at_level(logging.WARNING):
        rep = run_videos({"cam01": good, "cam02": bad}, tmp_path / "out", tiny_set, chunk_frames=4)
    fi, msg = rep.decode_errors["cam02"]
    assert 0 < fi < 12 and "frame" in msg
    assert any("cam02" in r.message and str(fi) in r.message for r in caplog.records)
    d2 = Detections.load(rep.paths["cam02"])
    assert d2.n_frames == fi and int(d2.extra["decode_error_frame"]) == fi
    assert Detections.load(rep.paths["cam01"]).n_frames == 12  # the other camera goes on to the end


def test_video_size_against_calibration(tmp_path, caplog):
    check_size("cam01", (1080, 1920), (1080, 1920), tmp_path)
    with caplog.at_level(logging.WARNING):
        check_size("cam01", (1080, 1920), (1088, 1920), tmp_path)  # the Pose2Sim demo: codec padding
    assert "1088x1920" in caplog.text
    with pytest.raises(FormatError, match="rotated"):
        check_size("cam01", (1920, 1080), (1080, 1920), tmp_path)
    with pytest.raises(FormatError, match=r"video is 640x480 but the calibration says 1280x720"):
        check_size("cam01", (640, 480), (1280, 720), tmp_path)


def test_run_session_reads_raw_and_writes_keypoints(tmp_path, tiny_set):
    root = tmp_path / "session"
    (root / "raw").mkdir(parents=True)
    write_video(root / "raw" / "cam02.avi", 3)
    write_video(root / "raw" / "cam01.avi", 3)
    (root / "raw" / "cam01.frames.csv").write_text(
        "frame_index,t_ns,t_host_ns,sequence\n0,1000,0,0\n1,2000,0,1\n2,3000,0,2\n"
    )
    with pytest.raises(FormatError, match="calibration says"):
        run_session(root, config=tiny_set, progress=None, rig={"cam01": (640, 480), "cam02": (W, H)})
    paths = run_session(root, config=tiny_set, progress=None)
    assert sorted(paths) == ["cam01", "cam02"]
    assert paths["cam01"] == root / "keypoints" / "cam01.npz"
    assert Detections.load(paths["cam01"]).t_ns.tolist() == [1000, 2000, 3000]


@pytest.mark.parametrize(
    "rows,match",
    [
        (
            "0,1000\n1,3000\n2,2000\n3,4000\n4,1500",
            r"camera 'cam01': timestamps go backwards at frame 2 "
            r"\(2000 ns, after frame 1 at 3000 ns\) and at 1 more frame \(4\)",
        ),
        ("0,1000\n1,2000\n1,2500\n2,3000", r"camera 'cam01': frame 1 is listed twice"),
        ("0,1000\n2,2000\n1,3000", r"camera 'cam01': frame 1 comes after frame 2"),
    ],
)
def test_frames_csv_going_back_in_time_is_refused_naming_camera_and_frames(tmp_path, tiny_set, rows, match):
    """A camera's frames.csv that goes back in time (or lists a frame twice, or out of order) stops the
    keypoints stage before any frame is decoded, naming the camera and the frames; no row is dropped."""
    root = tmp_path / "session"
    (root / "raw").mkdir(parents=True)
    write_video(root / "raw" / "cam01.avi", 5)
    body = "".join(f"{r},0,{k}\n" for k, r in enumerate(rows.split("\n")))
    (root / "raw" / "cam01.frames.csv").write_text("frame_index,t_ns,t_host_ns,sequence\n" + body)
    with pytest.raises(FormatError, match=match):
        run_session(root, config=tiny_set, progress=None)
    assert not (root / "keypoints" / "cam01.npz").exists()


@pytest.mark.slow
def test_bottom_up_maps_are_kept_for_the_tracker(tmp_path, monkeypatch):
    from conftest import need_shared

    need_shared("models", "openpose_mobilenetv2_368x432.onnx")
    monkeypatch.setenv("ROOMCAP_CACHE", str(tmp_path / "cache"))
    vids = {"cam01": write_video(tmp_path / "cam01.avi", 3, size=(320, 240))}
    cfg = KeypointPipelineConfig(model_set="openpose", keep_maps=True)
    d = Detections.load(run_videos(vids, tmp_path / "out", cfg, chunk_frames=2).paths["cam01"])
    assert d.extra["maps_f16"].shape == (3, 46, 54, 57) and d.extra["maps_f16"].dtype == np.float16
    assert d.extra["maps_to_img"].shape == (3, 2, 3)
    # map px -> image px: 8 px stride in the 432x368 input, letterbox ratio 432/320 = 1.35
    assert d.extra["maps_to_img"][0, 0, 0] == pytest.approx(8 / 1.35)


def test_cli_run_on_explicit_videos(tmp_path, tiny_set, capsys):
    from roomcap.keypoints.cli import main

    v = write_video(tmp_path / "camA.avi", 2)
    args = ["run", f"cam07={v}", "--out", str(tmp_path / "kp"), "--models", tiny_set.model_set]
    assert main(args + ["--refine-passes", "0"]) == 0
    assert Detections.load(tmp_path / "kp" / "cam07.npz").camera == "cam07"
    assert main(["run", str(tmp_path / "nope.mp4"), "--out", str(tmp_path / "kp")]) == 2
    assert "do not exist" in capsys.readouterr().err


def _write_av(path, pts_ms, size=(W, H), rotate_deg=0):
    """An mp4 whose frames sit at ``pts_ms`` (milliseconds); ``rotate_deg`` 90 writes portrait rotation
    metadata (the track header's display matrix, as phones do)."""
    import struct

    import av

    with av.open(str(path), "w") as c:
        s = c.add_stream("mpeg4", rate=1000)
        s.width, s.height, s.pix_fmt = size[0], size[1], "yuv420p"
        s.codec_context.time_base = s.time_base = __import__("fractions").Fraction(1, 1000)
        rng = np.random.default_rng(1)
        for t in pts_ms:
            f = av.VideoFrame.from_ndarray(
                rng.integers(0, 255, (size[1], size[0], 3), np.uint8), format="rgb24"
            )
            f.pts = int(t)
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    if rotate_deg:
        b = bytearray(path.read_bytes())
        i = b.find(b"tkhd")
        off = i + 4 + 4 + (32 if b[i + 4] == 1 else 20) + 16  # version/flags, times, id, duration; layer..
        b[off : off + 36] = struct.pack(">9i", 0, 65536, 0, -65536, 0, 0, 0, 0, 1 << 30)
        path.write_bytes(bytes(b))
    return path


def test_variable_frame_rate_video_keeps_its_own_timestamps(tmp_path, tiny_set, caplog):
    """A phone-style variable-frame-rate video: the detections carry the container's frame times, not
    index / fps, and a warning says so."""
    pts = [0, 33, 67, 100, 400, 433, 467, 800, 833, 867]  # 30 fps with two stalls of ~0.3 s
    v = _write_av(tmp_path / "cam01.mp4", pts)
    with caplog.at_level(logging.WARNING):
        rep = run_videos({"cam01": v}, tmp_path / "kp", tiny_set)
    d = Detections.load(rep.paths["cam01"])
    np.testing.assert_allclose(d.t_ns / 1e6, pts, atol=1.5)
    assert bool(d.extra["variable_frame_rate"]) and "variable frame rate" in caplog.text
    cfr = write_video(tmp_path / "cam02.avi", 6)  # a steady frame rate: index / fps
    d2 = Detections.load(run_videos({"cam02": cfr}, tmp_path / "kp2", tiny_set).paths["cam02"])
    assert not bool(d2.extra["variable_frame_rate"])
    np.testing.assert_array_equal(
        d2.t_ns, np.round(np.arange(6) / float(d2.extra["fps"]) * 1e9).astype(np.int64)
    )


def test_portrait_rotation_metadata_is_read_upright_and_named_when_it_misfits(tmp_path, tiny_set):
    v = _write_av(tmp_path / "cam01.mp4", [0, 40, 80], size=(W, H), rotate_deg=90)
    rep = run_videos({"cam01": v}, tmp_path / "kp", tiny_set, rig={"cam01": (H, W)})  # upright: portrait
    d = Detections.load(rep.paths["cam01"])
    assert tuple(d.image_size_wh) == (H, W) and int(d.extra["rotation_deg"]) == 90
    with pytest.raises(FormatError, match=r"rotation metadata says 90 degrees"):
        run_videos(
            {"cam01": v}, tmp_path / "kp2", tiny_set, rig={"cam01": (W, H)}
        )  # calibrated on the sensor


def test_4k_video_runs(tmp_path, tiny_set):
    v = write_video(tmp_path / "cam01.avi", 3, size=(3840, 2160))
    d = Detections.load(run_videos({"cam01": v}, tmp_path / "kp", tiny_set).paths["cam01"])
    assert d.n_frames == 3 and tuple(d.image_size_wh) == (3840, 2160)
    assert np.isfinite(d.xy_px).any()


def test_camera_groups_give_the_same_detections(tmp_path, tiny_set):
    """The cameras spread over threads (one pipeline per group) write what one pipeline writes."""
    vids = {
        c: write_video(tmp_path / f"{c}.avi", 6, seed=k) for k, c in enumerate(("cam01", "cam02", "cam03"))
    }
    one = run_videos(vids, tmp_path / "one", tiny_set)
    two = run_videos(vids, tmp_path / "two", tiny_set, camera_groups=2)
    for c in vids:
        a, b = Detections.load(one.paths[c]), Detections.load(two.paths[c])
        np.testing.assert_array_equal(a.xy_px, b.xy_px)
        np.testing.assert_array_equal(a.t_ns, b.t_ns)
    assert two.frames == one.frames == dict.fromkeys(vids, 6)
