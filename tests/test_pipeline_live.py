"""pipeline.live: the live track stage steps the particle filter once per frame
set, never renumbers an identity, appends whole parts to track/live.parts/ (the parts/1 layout of the
streamed batch stages, read by TrackFile.load("track/live.npz") and iter_parts), and costs the same late
as early. Sessions of earlier versions (track/live/, live_tracks/1) still load."""

from __future__ import annotations

import json
import logging
from types import SimpleNamespace

import numpy as np
import pytest
from track_helpers import walkers

from roomcap.capture.config import parse_config
from roomcap.capture.live import LiveStep
from roomcap.capture.session import SessionLayout
from roomcap.capture.sources import Frame
from roomcap.capture.sync import FrameSet
from roomcap.core.errors import FormatError
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.outputs.cli import resolve_tracks
from roomcap.pipeline.live import STAGES, LiveContext, _track, legacy_live_dir, live_dir, load_live_tracks
from roomcap.synthetic.rigs import ring_rig
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.trackfile import TrackFile, iter_parts
from roomcap.triangulate.chunks import PartStore, parts_dir, remove_output

FAST = ParticleConfig(motion="constant_velocity", n_samples=100)


def test_stage_registry_is_one_line_per_batch_stage():
    assert list(STAGES) == ["keypoints", "triangulate", "track"]


def _steps(rig, X, fps=25.0):
    names = tuple(c.name for c in rig.cameras)
    for t in range(len(X)):
        t_ns = int(round(t / fps * 1e9))
        uv = rig.project(X[t].reshape(-1, 3)).reshape(len(names), *X.shape[1:3], 2)  # (C,P,J,2)
        dets = {
            n: SimpleNamespace(xy_px=uv[c], score=np.full(uv.shape[1:3], 0.9), skeleton="body19")
            for c, n in enumerate(names)
        }
        fs = FrameSet(t, t_ns, {n: Frame(None, t_ns, 0, t) for n in names})
        yield LiveStep(fs, names, {"detections": dets, "final": t == len(X) - 1})


def _record(tmp_path, n_frames=55, chunk=10, at=None):
    """The live track stage over ``n_frames`` synthetic frame sets of two walkers. Returns (layout, stage,
    walkers, what each step returned, ``at(step)``'s results)."""
    rig = ring_rig(4, radius_m=4.0)
    names = [c.name for c in rig.cameras]
    cfg = parse_config({"cameras": [{"name": n, "source": "synthetic:", "fps": 25} for n in names]})
    lay = SessionLayout(tmp_path)
    stage = _track(LiveContext(cfg, lay, rig, FAST, chunk_frames=chunk))
    X = walkers(2, n_frames, seed=3)
    returned, seen = [], {}
    for step in _steps(rig, X):
        stage(step)
        e = step.outputs["tracks"]
        returned.append((np.asarray(e.track_id).copy(), np.asarray(e.xyz_m, np.float32).copy()))
        if at is not None:
            seen[step.frameset.index] = at(step)
    return lay, stage, X, returned, seen


def test_track_stage_steps_the_filter_and_appends_whole_parts(tmp_path):
    def at(step):
        if step.frameset.index == 20:
            return (live_dir(SessionLayout(tmp_path)) / "part_00000.npz").read_bytes()

    lay, stage, X, returned, seen = _record(tmp_path, at=at)
    index = json.loads((live_dir(lay) / "index.json").read_text())
    assert index["schema"] == "parts/1" and index["kind"] == "tracks" and index["appendable"]
    assert index["chunks"] == [
        [a, min(a + 10, 55)] for a in range(0, 55, 10)
    ]  # the last part at the final set
    assert index["complete"] and sorted(index["parts"], key=int) == [str(i) for i in range(6)]
    assert (live_dir(lay) / "part_00000.npz").read_bytes() == seen[20]  # a part is never rewritten
    tf = TrackFile.load(lay.live_tracks)
    assert tf.n_frames == 55 and tf.n_tracks == 2 and list(tf.frame_index) == list(range(55))
    # identities never renumbered: the ids the filter gave each frame are the file's, the same ids all along
    assert all(sorted(ids.tolist()) == [0, 1] for ids, _ in returned)
    for k in range(2):  # each id follows one person throughout
        d = np.linalg.norm(tf.xyz_m[:, k, None].astype(np.float64) - X, axis=-1).mean(-1)  # (T,P)
        assert len(set(d.argmin(1))) == 1 and d.min(1).max() < 0.05
    assert len(stage.tracker.tracks) == 2 and len(stage.writer._rows) == 0  # bounded state: nothing buffered


def test_live_folder_read_by_the_common_loaders_equals_what_each_step_returned(tmp_path):
    lay, _, _, returned, _ = _record(tmp_path, n_frames=37, chunk=8)
    tf = TrackFile.load(lay.live_tracks)  # track/live.npz: only its parts folder exists
    assert not lay.live_tracks.exists() and live_dir(lay) == parts_dir(lay.live_tracks)
    assert tf.n_frames == len(returned) == 37
    for t, (ids, xyz) in enumerate(returned):
        ks = np.searchsorted(tf.track_id, ids)
        assert np.array_equal(tf.track_id[ks], ids)
        np.testing.assert_array_equal(tf.xyz_m[t, ks], xyz)  # bit for bit
        others = np.setdiff1d(np.arange(tf.n_tracks), ks)
        assert np.isnan(tf.xyz_m[t, others]).all()  # no estimate where the step returned none
    parts = list(iter_parts(lay.live_tracks))
    assert [p.n_frames for p in parts] == [8, 8, 8, 8, 5]
    joined = TrackFile.concat(parts)
    np.testing.assert_array_equal(joined.xyz_m, tf.xyz_m)
    np.testing.assert_array_equal(joined.t_ns, tf.t_ns)
    # the public name reads the same, from the file path, the parts folder or the session
    for where in (lay.live_tracks, live_dir(lay), tmp_path):
        np.testing.assert_array_equal(load_live_tracks(where).xyz_m, tf.xyz_m)
    assert resolve_tracks(tmp_path) == (lay.live_tracks, tmp_path.name)  # the tracks CLI finds it
    assert resolve_tracks(live_dir(lay))[0] == lay.live_tracks


def test_a_reader_during_the_recording_sees_only_whole_listed_parts(tmp_path, caplog):
    def at(step):
        if step.frameset.index == 24:  # 3 parts of 8 written, the 25th frame set buffered
            with caplog.at_level(logging.WARNING):
                return TrackFile.load(SessionLayout(tmp_path).live_tracks).n_frames

    lay, *_, seen = _record(tmp_path, n_frames=30, chunk=8, at=at)
    assert seen[24] == 24 and "not complete" in caplog.text
    assert TrackFile.load(lay.live_tracks).n_frames == 30


def test_reprocess_leaves_the_live_track_alone(tmp_path):
    """The batch track stage owns track/tracks.npz and tracks.parts/ (removed or replaced on a rerun);
    the live parts are elsewhere."""
    lay, *_ = _record(tmp_path, n_frames=20, chunk=10)
    before = {p.name: p.read_bytes() for p in live_dir(lay).iterdir()}
    remove_output(lay.tracks)
    store = PartStore(parts_dir(lay.tracks), "tracks")
    store.open("another key", [(0, 5)])
    TrackFile.empty(np.arange(5), np.arange(5) * 40_000_000, 25.0).save(store.part_path(0))
    store.commit(0)
    store.finish()
    store.open("a third key", [(0, 5)])  # a rerun with other settings: the batch parts folder is rmtree'd
    assert {p.name: p.read_bytes() for p in live_dir(lay).iterdir()} == before
    assert TrackFile.load(lay.live_tracks).n_frames == 20


def test_a_part_with_a_wrong_hash_or_truncated_is_an_error_naming_it(tmp_path):
    lay, *_ = _record(tmp_path, n_frames=30, chunk=10)
    part = live_dir(lay) / "part_00001.npz"
    good = part.read_bytes()
    bad = bytearray(good)
    bad[len(bad) // 2] ^= 0xFF  # same size, another hash
    part.write_bytes(bytes(bad))
    for read in (lambda: TrackFile.load(lay.live_tracks), lambda: list(iter_parts(lay.live_tracks))):
        with pytest.raises(FormatError, match=r"part_00001\.npz.*sha256.*not read.*cannot be rebuilt"):
            read()
    part.write_bytes(good[: len(good) // 2])  # truncated
    with pytest.raises(FormatError, match=r"part_00001\.npz.*size and sha256"):
        load_live_tracks(lay.live_tracks)
    part.unlink()
    with pytest.raises(FormatError, match=r"part_00001\.npz.*missing"):
        TrackFile.load(lay.live_tracks)
    part.write_bytes(good)
    assert TrackFile.load(lay.live_tracks).n_frames == 30


def _part(frames, ids, value):
    T, K, J = len(frames), len(ids), CANONICAL.n_joints
    return TrackFile(
        fps=25.0,
        frame_index=np.asarray(frames),
        t_ns=np.asarray(frames) * 40_000_000,
        track_id=np.asarray(ids),
        joint_names=CANONICAL.joint_names,
        parents=np.asarray(CANONICAL.parents),
        xyz_m=np.full((T, K, J, 3), value, np.float32) + np.arange(K, dtype=np.float32)[None, :, None, None],
        confidence=np.full((T, K, J), 0.5, np.float32),
        std_m=np.full((T, K, J), 0.01, np.float32),
        flags=np.ones((T, K, J), np.uint8),
        source="pipeline.live (track.particle, one step per frame set)",
    )


def test_an_older_live_tracks_1_folder_still_loads(tmp_path):
    """A session recorded by an earlier version: track/live/index.json (live_tracks/1) + part_NNNNNN.npz."""
    lay = SessionLayout(tmp_path)
    old = legacy_live_dir(lay)
    old.mkdir(parents=True)
    _part(range(0, 4), [0, 1], 1.0).save(old / "part_000000.npz")
    _part(range(4, 7), [1, 2], 2.0).save(old / "part_000001.npz")
    parts = [{"file": "part_000000.npz", "first_frame": 0, "frames": 4}]
    parts.append({"file": "part_000001.npz", "first_frame": 4, "frames": 3})
    (old / "index.json").write_text(json.dumps({"schema": "live_tracks/1", "fps": 25.0, "parts": parts}))
    for where in (old, tmp_path):
        tf = load_live_tracks(where)
        assert tf.n_frames == 7 and tf.track_id.tolist() == [0, 1, 2]
        assert list(tf.frame_index) == list(range(7))
        assert (
            (tf.xyz_m[:4, 0] == 1.0).all()
            and (tf.xyz_m[:4, 1] == 2.0).all()
            and np.isnan(tf.xyz_m[:4, 2]).all()
        )
        assert (
            np.isnan(tf.xyz_m[4:, 0]).all()
            and (tf.xyz_m[4:, 1] == 2.0).all()
            and (tf.xyz_m[4:, 2] == 3.0).all()
        )
    (old / "part_000001.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(FormatError, match=r"part_000001\.npz"):
        load_live_tracks(old)
    (old / "index.json").write_text(json.dumps({"schema": "something/9", "parts": []}))
    with pytest.raises(FormatError, match="live_tracks/1"):
        load_live_tracks(old)


def test_the_runner_closes_the_track_stage_so_the_last_part_is_written(tmp_path):
    """A recording that ends on a non-final set (the runner skips sets when it falls behind) still gets its
    last frames: LiveRunner calls the stage's close() at the end."""
    from roomcap.capture.live import LiveRunner

    rig = ring_rig(3, radius_m=4.0)
    names = [c.name for c in rig.cameras]
    cfg = parse_config({"cameras": [{"name": n, "source": "synthetic:", "fps": 25} for n in names]})
    lay = SessionLayout(tmp_path)
    stage = _track(LiveContext(cfg, lay, rig, FAST, chunk_frames=50))
    runner = LiveRunner(cfg, tmp_path, stages={"track": stage})
    for step in _steps(rig, walkers(1, 12, seed=1)):
        step.outputs["final"] = False
        stage(step)
    assert not live_dir(lay).exists()  # 12 < 50 frames: nothing written yet
    runner.start()
    runner.stop()
    assert TrackFile.load(lay.live_tracks).n_frames == 12 and runner.summary()["errors"] == {}
    assert json.loads((live_dir(lay) / "index.json").read_text())["complete"]  # the recording ended


def test_downstream_reads_a_live_session_like_a_batch_one(tmp_path, capsys):
    """The tracks CLI and the report read a session that only has the live track, through the common
    loader; the skeleton fit of the live track does not take the batch track's companion name."""
    from roomcap.outputs.cli import main as tracks_main
    from roomcap.pipeline.report.inputs import _load

    sess = tmp_path / "S07"
    lay, *_ = _record(sess, n_frames=30, chunk=10)
    rc = tracks_main(["export", str(sess), "--format", "csv,json", "--out", str(tmp_path / "o")])
    assert rc == 0, capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [
        "S07_0.csv",
        "S07_0.json",
        "S07_1.csv",
        "S07_1.json",
    ]
    assert tracks_main(["fit", str(lay.live_tracks)]) == 0
    assert (lay.live_tracks.parent / "live_skeleton_fit.npz").exists()
    assert not (lay.live_tracks.parent / "skeleton_fit.npz").exists()  # the batch track's fit's name
    inp = _load(lay)
    assert inp.tracks is not None and not inp.tracks_error and inp.tracks.n_frames == 30
    assert inp.tracks_name == "live.npz"


def test_live_keypoints_run_each_camera_in_its_own_warmed_pipeline(tmp_path, monkeypatch):
    """The live 2D stage: each camera its own pipeline (its own crop-following stream), run by a pool of
    workers (2 here) that take the cameras slowest first; every pipeline run once on a blank image of the
    cameras' size before the first set; a camera without a frame is left out."""
    import cv2
    from conftest import need_shared

    import roomcap.pipeline.live as live_mod

    need_shared("models")
    videos = need_shared("data", "pose2sim", "demo-wheel-0.10.49", "Demo_MultiPerson", "videos")
    cams = ["cam01", "cam02", "cam03"]
    images = {}
    for c in cams:
        cap = cv2.VideoCapture(str(videos / f"{c}.mp4"))
        ok, images[c] = cap.read()
        cap.release()
        assert ok
    h, w = images["cam01"].shape[:2]
    cfg = parse_config(
        {"cameras": [{"name": c, "source": str(videos / f"{c}.mp4"), "resolution": [w, h]} for c in cams]}
    )
    warmed = []
    real_warm = live_mod.warm_keypoints
    monkeypatch.setattr(
        live_mod, "warm_keypoints", lambda pipe, size: warmed.append(size) or real_warm(pipe, size)
    )
    stage = live_mod._keypoints(LiveContext(cfg, SessionLayout(tmp_path), None, keypoint_workers=2))
    try:
        assert len(stage.pipes) == 3 and warmed == [(w, h)] * 3
        assert all(p.n_detected == 0 and not p._seeds for p in stage.pipes)  # the warm-up left nothing
        for t, missing in enumerate((None, "cam02")):
            frames = {c: None if c == missing else Frame(images[c], t, t, t) for c in cams}
            step = LiveStep(FrameSet(t, t, frames), tuple(cams))
            stage(step)
            dets = step.outputs["detections"]
            assert sorted(dets) == sorted(c for c in cams if c != missing)
            assert all(len(d.xy_px) >= 2 for d in dets.values())  # two participants in every view
        # each pipeline follows its own camera's people; cam02, missing from the second set, was not followed
        assert [set(p._seeds) for p in stage.pipes] == [{"cam01"}, {"cam02"}, {"cam03"}]
        assert [p.n_tracked for p in stage.pipes] == [1, 0, 1]  # the second set: crops from the first
    finally:
        stage.close()


def _looped_steps(rig, X, kinds, fps=25.0, late_at=None):
    """The scene ``X`` (T,P,J,3) replayed once, then once more after each jump in ``kinds``: "back" (its
    time starts again at 0), "loop" (a looping file camera: the time goes on, the frames say the source
    looped), "restart" (the frame set index starts again at 0, the time goes on). ``late_at``: after this
    frame of the first replay, a set 0.1 s behind it (a late set out of order)."""
    names = tuple(c.name for c in rig.cameras)
    T = len(X)
    index, t0, loops = 0, 0, 0
    for seg, kind in enumerate([None, *kinds]):
        if kind == "back":
            t0 = 0
        elif kind == "loop":
            loops += 1
        elif kind == "restart":
            index = 0
        for t in range(T):
            t_ns = t0 + int(round(t / fps * 1e9))
            uv = rig.project(X[t].reshape(-1, 3)).reshape(len(names), *X.shape[1:3], 2)
            dets = {
                n: SimpleNamespace(xy_px=uv[c], score=np.full(uv.shape[1:3], 0.9), skeleton="body19")
                for c, n in enumerate(names)
            }
            fs = FrameSet(index, t_ns, {n: Frame(None, t_ns, 0, index, loops=loops) for n in names})
            final = seg == len(kinds) and t == T - 1
            yield LiveStep(fs, names, {"detections": dets, "final": final})
            index += 1
            if seg == 0 and t == late_at:
                late = FrameSet(index, t_ns - 100_000_000, fs.frames)
                yield LiveStep(late, names, {"detections": dets, "final": False})
                index += 1
        t0 += int(round(T / fps * 1e9))


def test_a_source_that_jumps_back_starts_a_segment_and_keeps_each_persons_id(tmp_path):
    """A looping or restarting source: the scene starts again 3 times (time back to 0, a file camera's
    loop, the frame index restarting). Each jump starts a new segment of the live track (nothing skipped),
    is recorded in the track file and the runner's summary, and the people found after it take back the
    ids they had (matched by place, bone lengths and pose): as many identities as people."""
    from roomcap.capture.live import LiveRunner
    from roomcap.pipeline.live import load_live_jumps

    rig = ring_rig(4, radius_m=4.0)
    names = [c.name for c in rig.cameras]
    cfg = parse_config({"cameras": [{"name": n, "source": "synthetic:", "fps": 25} for n in names]})
    lay = SessionLayout(tmp_path)
    stage = _track(LiveContext(cfg, lay, rig, FAST, chunk_frames=16))
    X = walkers(3, 40, seed=5)  # 1.6 s: the people end the scene far from where it starts
    assert np.linalg.norm(X[-1, :, 0, :2] - X[0, :, 0, :2], axis=-1).max() > 0.5
    kinds = ["back", "loop", "restart"]
    steps = list(_looped_steps(rig, X, kinds, late_at=20))
    dets = {id(s.frameset): s.outputs["detections"] for s in steps}
    runner = LiveRunner(
        cfg,
        tmp_path,
        stages={"keypoints": lambda s: s.outputs.update(detections=dets[id(s.frameset)]), "track": stage},
    )
    for step in steps:
        runner.process(step.frameset, final=step.outputs["final"])
    tf = TrackFile.load(lay.live_tracks)
    assert tf.n_frames == len(steps) - 1 == 4 * 40  # no frame set skipped but the late one
    assert stage.clock["late"] == 1 and not steps[21].outputs.get("jump")  # late, out of order: not a jump
    assert len(tf.track_id) == 3, tf.track_id  # one identity per person across the 3 jumps
    for k in range(3):  # each id follows one person in every segment
        d = np.linalg.norm(tf.xyz_m[:, k, None].astype(np.float64) - np.tile(X, (4, 1, 1, 1)), axis=-1)
        d = d.mean(-1)  # (T,P)
        seen = np.isfinite(d).all(1)
        assert seen.sum() > 0.9 * tf.n_frames and len(set(d[seen].argmin(1))) == 1
    jumps = load_live_jumps(tmp_path)
    assert [j["why"] for j in jumps] == ["time went back", "a source looped", "frame index restarted"]
    assert [j["row"] for j in jumps] == [40, 80, 120]
    assert [j["frame_set"] for j in jumps] == [41, 81, 0]
    assert jumps[0]["t_ns_after"] == 0 and jumps[0]["t_ns_before"] == int(round(39 / 25 * 1e9))
    assert [len(r.carried) for r in stage.tracker.jumps] == [3, 3, 3]
    assert "the clock jumped 3 times" in runner.summary_line()
    assert load_live_jumps(tmp_path / "nowhere") == []  # a track without the record: no jumps
