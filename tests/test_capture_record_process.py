"""Record -> process: the recorder's layout is read everywhere, joined into raw/<cam>.mp4, nothing is lost.

Bad input cases, one test each: an --out folder holding other files, a
disk that fills up with the free-space guard off, a camera that cannot be opened (with and without
--skip-failed-cameras), a join whose frame count does not match, ``capture-run repair``.
"""

from __future__ import annotations

import errno

import av
import numpy as np
import pytest
from conftest import need_shared
from test_capture_sources import write_video

from roomcap.capture import recorder as recorder_mod
from roomcap.capture.cli import main as capture_run
from roomcap.capture.config import parse_config
from roomcap.capture.join import count_video_packets, join_camera
from roomcap.capture.recorder import Recorder
from roomcap.capture.session import SessionLayout
from roomcap.capture.sources import read_code, read_frames_csv
from roomcap.core.fileio import load_toml
from roomcap.keypoints.video import _END, FrameReader


def _yaml(tmp_path, cams: dict[str, str], extra: str = "", copy: bool = False) -> str:
    """cams.yaml of file cameras, re-encoded unless ``copy`` (stream copy: test_capture_streamcopy.py)."""
    lines = ["cameras:"] + [
        f"  - {{name: {n}, source: '{s}', realtime: false, stream_copy: {str(copy).lower()}}}"
        for n, s in cams.items()
    ]
    p = tmp_path / "cams.yaml"
    p.write_text("\n".join(lines) + "\n" + extra)
    return str(p)


def _decode_all(path) -> list[int]:
    """Frame codes of every frame PyAV decodes from ``path`` (an ordinary decoder, not OpenCV)."""
    with av.open(str(path)) as c:
        return [read_code(f.to_ndarray(format="bgr24")) for f in c.decode(video=0)]


def _record(tmp_path, n=(40, 40), extra_args=(), codec=""):
    vids = {f"cam{i}": write_video(tmp_path / f"in{i}.mp4", n=k, fps=25) for i, k in enumerate(n)}
    extra = "recorder: {segment_s: 0.3}\n"
    cams = _yaml(tmp_path, {c: str(v) for c, v in vids.items()}, extra)
    if codec:
        text = open(cams).read().replace("stream_copy: false}", f"stream_copy: false, codec: {codec}}}")
        open(cams, "w").write(text)
    out = tmp_path / "session"
    rc = capture_run(["--cameras", cams, "--out", str(out), "--quiet", *extra_args])
    return rc, out


@pytest.mark.parametrize("codec", ["", "mjpg"])
def test_recording_is_joined_into_one_playable_video_per_camera(tmp_path, codec):
    rc, out = _record(tmp_path, codec=codec)
    assert rc == 0
    meta = load_toml(out / "session.toml")
    ext = ".avi" if codec == "mjpg" else ".mp4"
    for cam in ("cam0", "cam1"):
        video = out / "raw" / f"{cam}{ext}"
        tab = read_frames_csv(out / "raw" / f"{cam}.frames.csv")
        assert not (out / "raw" / cam).exists()  # segments removed after the check
        assert meta["cameras"][cam]["joined"] is True and meta["cameras"][cam]["video"] == f"raw/{cam}{ext}"
        assert meta["cameras"][cam]["segments_joined"] > 1  # 40 frames at 25 fps in 0.3 s segments
        assert _decode_all(video) == list(tab[:, 3]) == list(range(40))  # every frame, in order
        # timestamps of the joined file increase through the segment boundaries
        with av.open(str(video)) as c:
            pts = [f.pts for f in c.decode(video=0)]
        assert np.all(np.diff(pts) > 0)


def test_segmented_layout_is_read_by_the_keypoint_reader_and_discovery(tmp_path):
    rc, out = _record(tmp_path, extra_args=["--no-join"])
    assert rc == 0
    lay = SessionLayout(out)
    assert lay.raw_cameras() == ["cam0", "cam1"] and lay.video("cam0").is_dir()
    assert len(lay.segment_files("cam0")) > 1
    ts = {i: int(t) for i, t in read_frames_csv(lay.find_frames_csv("cam0"))[:, :2]}
    r = FrameReader(lay.video("cam0"), timestamps=ts)
    assert r.n_frames == 40 and r.size_wh == (160, 120)
    r.start()
    items = []
    while (it := r.q.get()) is not _END:
        items.append(it)
    assert [i for i, _, _ in items] == list(range(40)) and [read_code(im) for _, _, im in items] == list(
        range(40)
    )
    assert [t for _, t, _ in items] == [ts[i] for i in range(40)]
    from roomcap.pipeline.discover import discover
    from roomcap.pipeline.session_inputs import probe_videos

    (src,) = discover([out])
    assert src.videos == {"cam0": out / "raw" / "cam0", "cam1": out / "raw" / "cam1"}
    assert src.calibration_missing and "no calibration" in src.problem
    info, _ = probe_videos(src.videos)
    assert info["cam0"] == (40, 25.0)
    # repair joins what --no-join left
    assert capture_run(["repair", str(out)]) == 0
    assert (out / "raw" / "cam0.mp4").exists() and not (out / "raw" / "cam0").exists()
    assert count_video_packets(out / "raw" / "cam0.mp4") == 40
    assert load_toml(out / "session.toml")["cameras"]["cam0"]["joined"] is True


def test_old_place_of_the_timestamp_file_is_still_read(tmp_path):
    lay = SessionLayout(tmp_path)
    (tmp_path / "raw" / "cam").mkdir(parents=True)
    (tmp_path / "raw" / "cam" / "frames.csv").write_text("frame_index,t_ns,t_host_ns,sequence\n0,5,6,0\n")
    assert lay.find_frames_csv("cam") == tmp_path / "raw" / "cam" / "frames.csv"
    lay.frames_csv("cam").write_text("frame_index,t_ns,t_host_ns,sequence\n")
    assert lay.find_frames_csv("cam") == lay.frames_csv("cam")


def test_join_with_a_frame_count_mismatch_keeps_the_segments(tmp_path):
    rc, out = _record(tmp_path, extra_args=["--no-join"])
    segs = sorted((out / "raw" / "cam0").glob("seg_*"))
    res = join_camera(out / "raw", "cam0", 41, 25.0)  # the timestamp file claims one frame more
    assert not res.ok and "41 rows" in res.message and "segments are kept" in res.message
    assert sorted((out / "raw" / "cam0").glob("seg_*")) == segs
    assert not (out / "raw" / "cam0.mp4").exists() and not list((out / "raw").glob(".cam0*"))


def test_out_folder_with_other_files_is_refused_and_untouched(tmp_path, capsys):
    v = write_video(tmp_path / "in.mp4", n=10, fps=25)
    cams = _yaml(tmp_path, {"cam0": str(v)})
    out = tmp_path / "X"
    (out / "raw" / "cam0").mkdir(parents=True)
    (out / "raw" / "cam0" / "seg_000000.mp4").write_bytes(b"precious")
    (out / "raw" / "cam0.frames.csv").write_text("frame_index,t_ns,t_host_ns,sequence\n0,1,2,0\n")
    rc = capture_run(["--cameras", cams, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert (
        rc == 2
        and "already holds files" in err
        and "nothing is overwritten" in err
        and "Traceback" not in err
    )
    assert (out / "raw" / "cam0" / "seg_000000.mp4").read_bytes() == b"precious"
    assert (out / "raw" / "cam0.frames.csv").read_text().count("\n") == 2  # nothing appended
    assert not (out / "session.toml").exists()
    # an interrupted session: the message points at repair
    (out / "session.toml").write_text('schema = "session/1"\nstatus = "recording"\n')
    assert capture_run(["--cameras", cams, "--out", str(out), "--quiet"]) == 2
    assert "capture-run repair" in capsys.readouterr().err
    # an --out that is a file
    (tmp_path / "afile").write_text("x")
    assert capture_run(["--cameras", cams, "--out", str(tmp_path / "afile"), "--quiet"]) == 2
    assert "is a file" in capsys.readouterr().err
    # an empty existing folder is fine
    (tmp_path / "empty").mkdir()
    assert capture_run(["--cameras", cams, "--out", str(tmp_path / "empty"), "--quiet"]) == 0


def test_disk_full_with_the_guard_off_stops_cleanly(tmp_path, monkeypatch, capsys):
    real = recorder_mod.SegmentWriter.write

    def write(self, frame):  # the disk fills up after 15 frames of camera cam1
        if self.dir.name == "cam1" and self.frames_written + len(self._rows) >= 15:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(self, frame)

    monkeypatch.setattr(recorder_mod.SegmentWriter, "write", write)
    vids = {f"cam{i}": str(write_video(tmp_path / f"in{i}.mp4", n=60, fps=25)) for i in range(2)}
    cams = _yaml(tmp_path, vids, "recorder: {segment_s: 0.3, min_free_mb: 0}\n")
    out = tmp_path / "s"
    rc = capture_run(["--cameras", cams, "--out", str(out), "--quiet"])
    cap = capsys.readouterr()
    assert rc == 1 and "stopped early: disk full: camera cam1" in cap.err and "Traceback" not in cap.err
    meta = load_toml(out / "session.toml")
    assert meta["status"] == "stopped" and meta["stop_reason"].startswith("disk full: camera cam1")
    assert "No space left" in meta["cameras"]["cam1"]["writer_error"]
    assert not list(out.rglob(".part_*")) and not list(out.rglob(".*.join*"))
    for cam in ("cam0", "cam1"):  # closed segments match their timestamps; not joined on a full disk
        tab = read_frames_csv(out / "raw" / f"{cam}.frames.csv")
        assert meta["cameras"][cam]["joined"] is False and "disk full" in meta["cameras"][cam]["join_message"]
        codes = [c for s in SessionLayout(out).segment_files(cam) for c in _decode_all(s)]
        assert codes == list(tab[:, 3]) and len(codes) > 0
    assert 0 < len(read_frames_csv(out / "raw" / "cam1.frames.csv")) <= 15
    # after freeing space, repair joins them
    assert capture_run(["repair", str(out)]) == 0
    assert count_video_packets(out / "raw" / "cam1.mp4") == len(
        read_frames_csv(out / "raw" / "cam1.frames.csv")
    )


def test_disk_full_while_closing_the_last_segment_removes_it(tmp_path, monkeypatch):
    real = recorder_mod.SegmentWriter.close_segment
    calls = {"n": 0}

    def close_segment(self):
        if self._part is not None and self.dir.name == "a":
            calls["n"] += 1
            if calls["n"] >= 2:
                raise OSError(errno.ENOSPC, "No space left on device")
        real(self)

    monkeypatch.setattr(recorder_mod.SegmentWriter, "close_segment", close_segment)
    cfg = parse_config(
        {
            "cameras": [{"name": "a", "source": "synthetic:", "resolution": [160, 120], "fps": 30}],
            "recorder": {"segment_s": 0.3, "min_free_mb": 0},
        }
    )
    summary = Recorder(cfg, tmp_path / "s", duration_s=3, handle_signals=False).run()
    assert summary["status"] == "stopped" and "disk full" in summary["stop_reason"]
    assert not list((tmp_path / "s").rglob(".part_*"))
    n = len(read_frames_csv(tmp_path / "s" / "raw" / "a.frames.csv"))
    assert n == sum(count_video_packets(s) for s in SessionLayout(tmp_path / "s").segment_files("a")) > 0


def test_a_camera_that_cannot_be_opened(tmp_path, capsys):
    v = write_video(tmp_path / "in.mp4", n=20, fps=25)
    cams = _yaml(tmp_path, {"cam0": str(v), "gone": str(tmp_path / "missing.mp4"), "cam2": str(v)})
    out = tmp_path / "s"
    assert capture_run(["--cameras", cams, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "camera 'gone' cannot be opened" in err and "--skip-failed-cameras" in err and not out.exists()
    rc = capture_run(["--cameras", cams, "--out", str(out), "--quiet", "--skip-failed-cameras"])
    cap = capsys.readouterr()
    assert rc == 0 and "gone: NOT RECORDED" in cap.out and "1 camera(s) not recorded: gone" in cap.err
    meta = load_toml(out / "session.toml")
    assert meta["status"] == "complete" and meta["failed_cameras"] == ["gone"]
    assert (
        meta["cameras"]["gone"]["recorded"] is False and "does not exist" in meta["cameras"]["gone"]["failed"]
    )
    assert SessionLayout(out).raw_cameras() == ["cam0", "cam2"]
    assert count_video_packets(out / "raw" / "cam2.mp4") == 20
    # every camera failing is still an error
    cams = _yaml(tmp_path, {"gone": str(tmp_path / "missing.mp4")})
    assert (
        capture_run(["--cameras", cams, "--out", str(tmp_path / "t"), "--quiet", "--skip-failed-cameras"])
        == 2
    )
    assert "no camera could be opened" in capsys.readouterr().err


def test_reprocess_keypoints_of_a_recording_needs_no_calibration(tmp_path, monkeypatch):
    monkeypatch.setenv("ROOMCAP_SHARED", str(need_shared("models").parent))
    from roomcap.pipeline.cli import main as reprocess

    rc, out = _record(tmp_path, n=(6, 6), extra_args=["--no-join"])
    assert rc == 0
    assert reprocess([str(out), "--stages", "keypoints", "--workers", "1"]) == 0
    from roomcap.keypoints.detections import Detections

    tab = read_frames_csv(out / "raw" / "cam0.frames.csv")
    d = Detections.load(out / "keypoints" / "cam0.npz")
    assert d.n_frames == 6 and np.array_equal(d.t_ns, tab[:, 1])  # the recorder's timestamps
    # the 3D stages still say what they need
    assert reprocess([str(out), "--stages", "triangulate", "--workers", "1"]) == 1


def test_repair_bad_input(tmp_path, capsys):
    assert capture_run(["repair", str(tmp_path / "nope")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert capture_run(["repair", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err
    assert "no raw/ folder; this is not a recorded session" in err and "Traceback" not in err
    # a segment folder whose timestamp rows do not match its video: repair keeps the segments, exit 1
    rc, out = _record(tmp_path, n=(12, 12), extra_args=["--no-join"])
    seg_csv = sorted((out / "raw" / "cam0").glob("seg_*.frames.csv"))[0]
    seg_csv.write_text(seg_csv.read_text() + "999,1,2,999\n")
    assert capture_run(["repair", str(out)]) == 1
    cap = capsys.readouterr()
    assert "cam0: 13 frames, segments kept: not joined: the joined video has 12 frames" in cap.out
    assert (out / "raw" / "cam0").is_dir() and (out / "raw" / "cam1.mp4").exists()


def test_sync_audio_on_the_session_videos_asks_to_join_segments_first(tmp_path, capsys):
    rc, out = _record(tmp_path, n=(8, 8), extra_args=["--no-join"])
    assert capture_run(["sync", str(out), "--audio", "--dry-run"]) == 2
    assert "still segment folders" in capsys.readouterr().err
    assert capture_run(["repair", str(out)]) == 0
    capsys.readouterr()
    # joined: the recordings are read (these test videos have no audio track, which is said clearly)
    assert capture_run(["sync", str(out), "--audio", "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "no audio track" in err and "Traceback" not in err


def test_segment_writer_never_appends_or_overwrites(tmp_path):
    from roomcap.capture.segments import RecorderError, SegmentWriter
    from roomcap.capture.sources import Frame

    csv = tmp_path / "cam.frames.csv"
    csv.write_text("frame_index,t_ns,t_host_ns,sequence\n0,1,2,0\n")
    with pytest.raises(RecorderError, match="refusing to append"):
        SegmentWriter(tmp_path / "cam", csv, "mp4v", 25, 0.5)
    assert csv.read_text().count("\n") == 2
    (tmp_path / "cam2").mkdir()
    (tmp_path / "cam2" / "seg_000000.mp4").write_bytes(b"old")
    w = SegmentWriter(tmp_path / "cam2", tmp_path / "cam2.frames.csv", "mp4v", 25, 0.5)
    with pytest.raises(RecorderError, match="refusing to overwrite"):
        w.write(Frame(np.zeros((48, 64, 3), np.uint8), 1, 1, 0))
    assert (tmp_path / "cam2" / "seg_000000.mp4").read_bytes() == b"old"
