"""`tracks view SESSION --rrd FILE` (track.rerun_export): the session written as a Rerun recording and read
back with Rerun's own reader (rerun.chunk.RrdReader): the entity paths, every track's frames and positions
equal the session's; `capture-run --live --rerun` logs the live steps the same way. Skips without rerun-sdk
(the rerun extra)."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from roomcap.capture.session import SessionLayout
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.synthetic.rigs import ring_rig
from roomcap.track.trackfile import TrackFile

J = CANONICAL.n_joints


def _session(root, T=10):
    """A small session: 2 cameras, their videos, 2D detections, a track file of two people (id 7 absent at
    frames 4-5)."""
    lay = SessionLayout(root)
    rig = ring_rig(2, radius_m=4.0)
    lay.calib_dir.mkdir(parents=True)
    rig.save(lay.rig_toml)
    rng = np.random.default_rng(0)
    xyz = np.zeros((T, 2, J, 3), np.float32)
    xyz[..., 2] = np.linspace(0.1, 1.7, J)
    xyz[:, 0, :, 0] = np.linspace(-1, 1, T)[:, None]
    xyz[:, 1, :, 1] = 0.5
    xyz += rng.normal(0, 0.01, xyz.shape).astype(np.float32)
    xyz[4:6, 1] = np.nan
    t_ns = 5 * 10**9 + np.arange(T) * 40_000_000
    tf = TrackFile(
        fps=25.0,
        frame_index=np.arange(T),
        t_ns=t_ns,
        track_id=np.array([3, 7]),
        joint_names=CANONICAL.joint_names,
        parents=np.asarray(CANONICAL.parents),
        xyz_m=xyz,
        confidence=np.ones((T, 2, J), np.float32),
        std_m=np.full((T, 2, J), 0.03, np.float32),
        flags=np.ones((T, 2, J), np.uint8),
        source="test",
    )
    lay.tracks.parent.mkdir(parents=True)
    tf.save(lay.tracks)
    lay.raw_dir.mkdir()
    lay.keypoints_dir.mkdir()
    for cam in rig.cameras:
        vw = cv2.VideoWriter(
            str(lay.raw_dir / f"{cam.name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25, cam.size_wh
        )
        for t in range(T):
            vw.write(np.full((cam.size_wh[1], cam.size_wh[0], 3), 20 * t, np.uint8))
        vw.release()
        uv = cam.project(np.nan_to_num(xyz, nan=0).reshape(-1, 3)).reshape(T, 2, J, 2)
        Detections(
            cam.name, "body19", np.arange(T), t_ns, uv, np.full((T, 2, J), 0.9), np.zeros((T, 2, 5))
        ).save(lay.detections(cam.name))
    return lay, rig, tf


def _read(path):
    """entity path -> list of (frame, record-batch row as dict), from Rerun's own reader."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for c in RrdReader(path).stream().to_chunks():
        rb = c.to_record_batch()
        cols = {n: rb.column(n).to_pylist() for n in rb.schema.names}
        for i in range(rb.num_rows):
            out.setdefault(str(c.entity_path), []).append({n: v[i] for n, v in cols.items()})
    return out


def test_tracks_view_writes_a_recording_rerun_reads_back_equal(tmp_path, capsys):
    pytest.importorskip("rerun", reason="rerun-sdk not installed: pip install 'roomcap[rerun]'")
    from roomcap.outputs.cli import main as tracks

    lay, rig, tf = _session(tmp_path / "S")
    rrd = tmp_path / "S.rrd"
    assert tracks(["view", str(lay.root), "--rrd", str(rrd)]) == 0, capsys.readouterr().err
    assert "10 frames, 2 tracks, 20 images, 20 detection sets" in capsys.readouterr().out
    got = _read(rrd)
    for cam in rig.names:
        for ent in ("", "/image", "/image/detections", "/image/detections/bones"):
            assert f"/world/cameras/{cam}{ent}" in got
        pin = [r for r in got[f"/world/cameras/{cam}/image"] if r.get("Pinhole:resolution")]
        assert pin and pin[0]["Pinhole:resolution"] == [[540, round(720 * 540 / 1280)]]
        imgs = [r["frame"] for r in got[f"/world/cameras/{cam}/image"] if r.get("EncodedImage:blob")]
        assert imgs == list(range(10))
    present = np.isfinite(tf.xyz_m).all(-1).any(-1)
    for k, tid in enumerate(tf.track_id):
        rows = [r for r in got[f"/world/tracks/{tid}"] if r.get("Points3D:positions") is not None]
        frames = [r["frame"] for r in rows]
        assert frames == np.flatnonzero(present[:, k]).tolist()  # one row per frame the track is present
        for r in rows:
            np.testing.assert_array_equal(
                np.asarray(r["Points3D:positions"], np.float32), tf.xyz_m[r["frame"], k]
            )
            np.testing.assert_allclose(r["Points3D:radii"], tf.std_m[r["frame"], k], rtol=1e-6)
    cleared = [r["frame"] for r in got["/world/tracks/7"] if r.get("Clear:is_recursive")]
    assert cleared == [4]  # absent at frame 4: cleared, back at frame 6


def test_live_steps_are_logged_by_their_own_thread(tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk not installed: pip install 'roomcap[rerun]'")
    from roomcap.capture.live import LiveStep
    from roomcap.capture.sources import Frame
    from roomcap.capture.sync import FrameSet
    from roomcap.outputs.rerun_recording import LiveRerun

    rig = ring_rig(2, radius_m=4.0)
    lr = LiveRerun(tmp_path / "live.rrd", SessionLayout(tmp_path / "S"), rig, image_hz=1000)
    X = np.zeros((1, J, 3), np.float32)
    X[..., 2] = np.linspace(0.1, 1.7, J)
    for t in range(6):
        img = np.zeros((720, 1280, 3), np.uint8)
        fs = FrameSet(t, t * 40_000_000, {n: Frame(img, t * 40_000_000, 0, t) for n in rig.names})
        est = SimpleNamespace(track_id=np.array([2]), xyz_m=X + t, std_m=np.full((1, J), 0.02))
        lr.offer(LiveStep(fs, tuple(rig.names), {"tracks": est}))
    lr.close()
    got = _read(tmp_path / "live.rrd")
    rows = [r for r in got["/world/tracks/2"] if r.get("Points3D:positions") is not None]
    assert lr.dropped == 0 and [r["frame"] for r in rows] == list(range(6))
    np.testing.assert_array_equal(
        np.asarray(rows[-1]["Points3D:positions"], np.float32), X[0] + rows[-1]["frame"]
    )


def test_without_rerun_the_command_names_the_extra(monkeypatch, tmp_path, capsys):
    from roomcap.outputs.cli import main as tracks

    lay, _, _ = _session(tmp_path / "S", T=3)
    monkeypatch.setitem(sys.modules, "rerun", None)
    assert tracks(["view", str(lay.root), "--rrd", str(tmp_path / "x.rrd")]) == 2
    assert "pip install 'roomcap[rerun]'" in capsys.readouterr().err


def test_capture_run_live_rerun_writes_the_file_as_it_records(tmp_path):
    """capture-run's path (Recorder -> LiveRunner -> Outputs.open with --rerun): the file holds the cameras'
    frames and the live tracks."""
    pytest.importorskip("rerun", reason="rerun-sdk not installed: pip install 'roomcap[rerun]'")
    import argparse

    from roomcap.capture.config import load_config
    from roomcap.capture.live import LiveRunner
    from roomcap.capture.recorder import Recorder
    from roomcap.pipeline.live_outputs import Outputs

    rig = ring_rig(2, radius_m=4.0)
    rig.save(tmp_path / "rig.toml")
    cams = "".join(
        f"  - {{name: {n}, source: 'synthetic:', resolution: [320, 240], fps: 20}}\n" for n in rig.names
    )
    (tmp_path / "cams.yaml").write_text("calibration: rig.toml\ncameras:\n" + cams)
    cfg = load_config(tmp_path / "cams.yaml")
    X = np.zeros((1, J, 3), np.float32)
    X[..., 2] = np.linspace(0.1, 1.7, J)

    def one_person(step):
        step.outputs["tracks"] = SimpleNamespace(track_id=np.array([4]), xyz_m=X, std_m=np.full((1, J), 0.02))

    live = LiveRunner(cfg, tmp_path / "S", stages={"track": one_person})
    rec = Recorder(cfg, tmp_path / "S", duration_s=1.5, frameset_sink=live.queue, handle_signals=False)
    outputs = Outputs()
    p = argparse.ArgumentParser()
    outputs.add_arguments(p)
    close = outputs.open(p.parse_args(["--rerun", str(tmp_path / "live.rrd")]), live, rec)
    live.start()
    rec.run()
    live.stop()
    close()
    got = _read(tmp_path / "live.rrd")
    rows = [r for r in got["/world/tracks/4"] if r.get("Points3D:positions") is not None]
    assert (
        len(rows) == live.stats.processed - outputs.feed.rerun.dropped >= 15
    )  # 1.5 s at 20 fps (measured 30)
    for cam in rig.names:
        assert any(r.get("EncodedImage:blob") for r in got[f"/world/cameras/{cam}/image"])


def test_a_live_tracks_rows_find_their_video_frames_by_time(tmp_path):
    """A live track's rows are frame sets (their own numbering): with the camera's frames.csv the frames are
    matched by timestamp."""
    pytest.importorskip("rerun", reason="rerun-sdk not installed: pip install 'roomcap[rerun]'")
    from roomcap.capture.recorder import CSV_HEADER
    from roomcap.outputs.rerun_recording import write_session_rrd

    lay, rig, tf = _session(tmp_path / "S")
    for cam in rig.names:  # the recorder's timestamps: frame k at the track's k-th t_ns
        rows = "".join(f"{k},{t},{t},{k}\n" for k, t in enumerate(tf.t_ns))
        lay.frames_csv(cam).write_text(CSV_HEADER + rows)
    shifted = TrackFile(**{**tf.__dict__, "frame_index": tf.frame_index + 100})
    shifted.save(tmp_path / "live.npz")
    counts = write_session_rrd(lay.root, tmp_path / "live.npz", tmp_path / "x.rrd", max_width_px=64)
    assert counts["images"] == 2 * tf.n_frames
    got = _read(tmp_path / "x.rrd")
    frames = [r["frame"] for r in got["/world/cameras/cam00/image"] if r.get("EncodedImage:blob")]
    assert frames == list(range(100, 110))


def test_a_track_with_hands_logs_them(tmp_path):
    """A whole-body session (body19 and both hands, 2D in ``body19_hands``): the track's body entity keeps
    the body joints, ``.../hands`` holds the hand joints equal to the file (a frame without the right
    hand: the left hand's 21 joints), the hand bones hang off the wrists; the 2D hands are logged too."""
    pytest.importorskip("rerun", reason="rerun-sdk not installed: pip install 'roomcap[rerun]'")
    from hands_helpers import SK, wholebody_trackfile, wholebody_xyz

    from roomcap.keypoints.skeletons import HANDS
    from roomcap.outputs.rerun_recording import write_session_rrd

    T = 5
    xyz = wholebody_xyz(1, T).astype(np.float32)
    right = [SK.index(n) for n in HANDS[21:]]
    xyz[3:, 0, right] = np.nan
    tf = wholebody_trackfile(xyz)
    lay = SessionLayout(tmp_path / "W")
    rig = ring_rig(2, radius_m=4.0)
    lay.calib_dir.mkdir(parents=True)
    rig.save(lay.rig_toml)
    lay.tracks.parent.mkdir(parents=True)
    tf.save(lay.tracks)
    lay.keypoints_dir.mkdir(parents=True)
    for cam in rig.cameras:
        uv = cam.project(np.nan_to_num(xyz).reshape(-1, 3)).reshape(T, 1, SK.n_joints, 2)
        uv[~np.isfinite(xyz).all(-1)] = np.nan
        sc = np.where(np.isfinite(uv[..., 0]), 0.9, 0.0)
        Detections(cam.name, "body19_hands", tf.frame_index, tf.t_ns, uv, sc, np.zeros((T, 1, 5))).save(
            lay.detections(cam.name)
        )
    rrd = tmp_path / "W.rrd"
    counts = write_session_rrd(lay.root, lay.tracks, rrd, images=False)
    assert counts["frames"] == T and counts["detections"] == 2 * T
    got = _read(rrd)
    H = [SK.index(n) for n in HANDS]
    body = [r for r in got["/world/tracks/3"] if r.get("Points3D:positions") is not None]
    assert len(body) == T and all(len(r["Points3D:positions"]) == 19 for r in body)
    hands = [r for r in got["/world/tracks/3/hands"] if r.get("Points3D:positions") is not None]
    assert [len(r["Points3D:positions"]) for r in hands] == [42, 42, 42, 21, 21]
    for r in hands:
        ids = np.asarray(r["Points3D:keypoint_ids"])
        assert set(ids.tolist()) <= set(H)
        want = xyz[r["frame"] - 100, 0, ids]  # the track file's frames start at 100
        np.testing.assert_array_equal(np.asarray(r["Points3D:positions"], np.float32), want)
    bones = [r for r in got["/world/tracks/3/hands/bones"] if r.get("LineStrips3D:strips") is not None]
    assert [len(r["LineStrips3D:strips"]) for r in bones] == [42, 42, 42, 21, 21]  # 2 x (wrist + 20)
    for cam in rig.names:
        h2 = [r for r in got[f"/world/cameras/{cam}/image/detections/hands"] if r.get("Points2D:positions")]
        assert [len(r["Points2D:positions"]) for r in h2] == [42, 42, 42, 21, 21]
