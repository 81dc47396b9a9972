"""The 3D stages streamed in time chunks equal the whole session's, resume after a
kill, and rebuild damaged parts; bad input (timestamps back, lengths, rates, nobody) is said."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from triangulate_helpers import killed_after_commits

from roomcap.capture.session import SessionLayout
from roomcap.core.errors import FormatError
from roomcap.keypoints.detections import Detections
from roomcap.synthetic.render import RenderConfig, render
from roomcap.synthetic.rigs import kitchen
from roomcap.synthetic.world import SceneConfig, make_scene, write_session
from roomcap.track.greedy import TrackerConfig, frame_times_s, track_poses
from roomcap.track.greedy_chunked import build_chunks, link_chunks
from roomcap.track.greedy_stage import track_session_greedy
from roomcap.track.trackfile import TrackFile, iter_parts
from roomcap.triangulate import chunks as C
from roomcap.triangulate import stage
from roomcap.triangulate.poses3d import Poses3D
from roomcap.triangulate.reconstruct import TriangulateConfig
from roomcap.triangulate.stage import triangulate_session

TRI = {"chunk_s": 2.0}
TRK = {"chunk_s": 3.0}


def _triangulate_on(root, options):
    """``triangulate_session`` with its chunks run as ``options`` say (``workers``, ``executor``)."""
    from roomcap.pipeline.executors import chunk_runner

    cfg = TriangulateConfig.from_dict(options)
    return triangulate_session(root, cfg, executor=chunk_runner(cfg.stream))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    rig, room = kitchen(4)
    scene = make_scene(room, SceneConfig(n_people=4, duration_s=12.0, fps=25.0, seed=5, enter_leave=True))
    rd = render(
        scene, rig, RenderConfig(noise_px=3.0, missed_joint_rate=0.15, false_positive_rate=0.1, seed=5)
    )
    root = tmp_path_factory.mktemp("stream")
    write_session(scene, rd, rig, root)
    triangulate_session(root)
    whole_p = Poses3D.load(SessionLayout(root).poses3d)
    track_session_greedy(root)
    whole_t = TrackFile.load(SessionLayout(root).tracks)
    return root, whole_p, whole_t


def _copy(session, tmp_path):
    dst = tmp_path / "s"
    shutil.copytree(session[0], dst)
    return dst


def _same_poses(a: Poses3D, b: Poses3D) -> None:
    P = max(a.xyz_m.shape[1], b.xyz_m.shape[1])
    for k in ("xyz_m", "score", "std_m", "reproj_err_cam_px"):
        x, y = getattr(a, k), getattr(b, k)
        pad = [(0, 0), (0, P - x.shape[1])] + [(0, 0)] * (x.ndim - 2)
        pad2 = [(0, 0), (0, P - y.shape[1])] + [(0, 0)] * (y.ndim - 2)
        assert np.array_equal(
            np.pad(x, pad, constant_values=np.nan), np.pad(y, pad2, constant_values=np.nan), equal_nan=True
        ), k


def _same_tracks(a: TrackFile, b: TrackFile) -> None:
    assert np.array_equal(a.track_id, b.track_id) and np.array_equal(a.frame_index, b.frame_index)
    for k in ("xyz_m", "confidence", "std_m", "flags", "t_ns"):
        assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True), k


def test_chunked_equals_whole_session(session, tmp_path):
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    triangulate_session(root, TRI)
    assert not lay.poses3d.exists() and (C.parts_dir(lay.poses3d) / "index.json").exists()
    idx = json.loads((C.parts_dir(lay.poses3d) / "index.json").read_text())
    assert len(idx["chunks"]) == 6 and idx["complete"]
    _same_poses(Poses3D.load(lay.poses3d), session[1])  # bit for bit
    track_session_greedy(root, TRK)
    assert not lay.tracks.exists()
    tf = TrackFile.load(lay.tracks)
    assert tf.n_tracks >= 4
    _same_tracks(tf, session[2])
    parts = list(iter_parts(lay.tracks))
    assert len(parts) == 4 and sum(p.n_frames for p in parts) == tf.n_frames
    assert all(p.n_tracks <= tf.n_tracks for p in parts)


def test_chunks_in_two_processes_equal_one(session, tmp_path, monkeypatch, caplog):
    """The chunks of one session triangulated by 2 worker processes give the one-process
    parts bit for bit, so the (sequential, streamed) tracker's identities are the single worker's; a run
    killed with one worker resumes with two."""
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    with killed_after_commits(monkeypatch, 2), pytest.raises(KeyboardInterrupt):
        triangulate_session(root, TRI)
    _triangulate_on(root, {**TRI, "workers": 2})
    idx = json.loads((C.parts_dir(lay.poses3d) / "index.json").read_text())
    assert idx["complete"] and len(idx["parts"]) == 6
    _same_poses(Poses3D.load(lay.poses3d), session[1])
    track_session_greedy(root, TRK)
    _same_tracks(TrackFile.load(lay.tracks), session[2])
    fresh = tmp_path / "fresh"
    shutil.copytree(session[0], fresh)
    caplog.clear()
    _triangulate_on(fresh, {**TRI, "workers": 2})  # every chunk in the workers
    assert "has no detection" not in caplog.text  # the workers say which cameras they saw
    _same_poses(Poses3D.load(SessionLayout(fresh).poses3d), session[1])


def test_killed_run_resumes_and_equals(session, tmp_path, monkeypatch):
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    rng = np.random.default_rng(17)
    kill_at = int(rng.integers(1, 5))  # a random chunk of the 6
    with killed_after_commits(monkeypatch, kill_at), pytest.raises(KeyboardInterrupt):
        triangulate_session(root, TRI)  # the run is killed after kill_at parts
    with pytest.raises(FormatError, match="incomplete"):
        Poses3D.load(lay.poses3d)
    built = []
    real_rec = stage.reconstruct_all

    def counting(*a, **k):
        built.append(k.get("done"))
        return real_rec(*a, **k)

    monkeypatch.setattr(stage, "reconstruct_all", counting)
    triangulate_session(root, TRI)
    assert len(built) == 6 - kill_at  # resumed from the last complete chunk
    _same_poses(Poses3D.load(lay.poses3d), session[1])
    # the tracker, killed after one part, then rerun
    with killed_after_commits(monkeypatch, 1), pytest.raises(KeyboardInterrupt):
        track_session_greedy(root, TRK)
    track_session_greedy(root, TRK)
    _same_tracks(TrackFile.load(lay.tracks), session[2])


def test_damaged_parts_are_rebuilt_never_trusted(session, tmp_path):
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    triangulate_session(root, TRI)
    folder = C.parts_dir(lay.poses3d)
    p1, p3 = folder / "part_00001.npz", folder / "part_00003.npz"
    data = p1.read_bytes()
    p1.write_bytes(data[: len(data) // 2])  # truncated
    p3.unlink()  # missing
    with pytest.raises(FormatError, match="part_00001.*size and sha256"):
        Poses3D.load(lay.poses3d)
    # same size, other bytes: the hash catches it
    p1.write_bytes(data[:-8] + b"\0" * 8)
    with pytest.raises(FormatError, match="sha256"):
        Poses3D.load(lay.poses3d)
    triangulate_session(root, TRI)
    _same_poses(Poses3D.load(lay.poses3d), session[1])
    track_session_greedy(root, TRK)
    tp = C.parts_dir(lay.tracks) / "part_00002.npz"
    tp.write_bytes(tp.read_bytes()[:100])
    with pytest.raises(FormatError, match="part_00002"):
        TrackFile.load(lay.tracks)
    track_session_greedy(root, TRK)
    _same_tracks(TrackFile.load(lay.tracks), session[2])
    # other settings: the old parts are not reused (another key, every part written anew)
    key0 = json.loads((C.parts_dir(lay.tracks) / "index.json").read_text())["key"]
    stamp0 = (C.parts_dir(lay.tracks) / "part_00000.npz").stat().st_mtime_ns
    track_session_greedy(root, {"chunk_s": 3.0, "tau_m": 0.3})
    idx = json.loads((C.parts_dir(lay.tracks) / "index.json").read_text())
    assert idx["complete"] and idx["key"] != key0
    assert (C.parts_dir(lay.tracks) / "part_00000.npz").stat().st_mtime_ns != stamp0
    # a whole-session run replaces the parts
    track_session_greedy(root)
    assert lay.tracks.exists() and not C.parts_dir(lay.tracks).exists()


def test_stream_tracker_equals_batch_on_a_paused_irregular_recording(session):
    """Dropped frames, jittered stamps and a 30 s pause: the streamed pass equals track_poses."""
    p = session[1]
    rng = np.random.default_rng(3)
    keep = np.sort(rng.choice(p.n_frames, int(0.95 * p.n_frames), replace=False))
    t_ns = p.t_ns[keep].astype(np.int64) + rng.integers(-3_000_000, 3_000_000, len(keep))
    t_ns = np.sort(t_ns)
    t_ns[len(t_ns) // 2 :] += 30_000_000_000  # a pause, frame numbers consecutive
    fi = np.arange(len(keep))
    xyz, conf, std = p.xyz_m[keep].astype(np.float64), p.score[keep], p.std_m[keep]
    parents = np.asarray(p.parents)
    cfg = TrackerConfig().at_fps(p.fps)
    whole = track_poses(xyz, fi, t_ns, p.fps, p.joint_names, parents, conf, std, cfg)
    t_s = frame_times_s(fi, t_ns, p.fps)
    from roomcap.track.greedy import facing_joints
    from roomcap.triangulate.reconstruct import flip_index

    flip = flip_index(p.joint_names)
    for step in (7, 40, 1000):
        chunks = [(a, min(a + step, len(fi))) for a in range(0, len(fi), step)]

        def read(a, b):
            return xyz[a:b], conf[a:b], std[a:b]

        labels, mirrored, final = link_chunks(
            read, chunks, cfg, p.fps, flip, t_s, facing_joints(p.joint_names)
        )
        built = list(build_chunks(read, chunks, labels, mirrored, final, cfg, parents, flip, p.fps, t_s))
        assert int(final.max()) + 1 == whole.n_tracks
        for _, ch in built:
            k = np.searchsorted(whole.track_id, ch.track_id)
            assert np.array_equal(ch.xyz_m.astype(np.float32), whole.xyz_m[ch.a : ch.b][:, k], equal_nan=True)
            assert np.array_equal(ch.flags, whole.flags[ch.a : ch.b][:, k])
            rest = np.setdiff1d(np.arange(whole.n_tracks), k)
            assert not np.isfinite(whole.xyz_m[ch.a : ch.b][:, rest]).any()


def _rewrite(root, cam, **changes):
    lay = SessionLayout(root)
    d = Detections.load(lay.detections(cam))
    fields = {
        f: getattr(d, f) for f in ("camera", "skeleton", "frame_index", "t_ns", "xy_px", "score", "boxes")
    }
    fields.update(changes)
    Detections(**fields, model=d.model, model_sha256=d.model_sha256).save(lay.detections(cam))
    return d


def test_bad_input_streamed(session, tmp_path):
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    cams = lay.detection_cameras()
    d = Detections.load(lay.detections(cams[1]))
    t = d.t_ns.copy()
    t[100] = t[98]
    _rewrite(root, cams[1], t_ns=t)
    with pytest.raises(
        FormatError, match=rf"camera '{cams[1]}'.*backwards at frame {int(d.frame_index[100])}"
    ):
        triangulate_session(root, TRI)
    _rewrite(root, cams[1], t_ns=d.t_ns)
    # another frame rate (timestamps of a 30 Hz camera)
    _rewrite(root, cams[2], t_ns=(np.arange(d.n_frames) * (1e9 / 30)).astype(np.int64) + 1)
    with pytest.raises(FormatError, match="different frame rates"):
        triangulate_session(root, TRI)
    _rewrite(root, cams[2], t_ns=d.t_ns)
    # arrays of different lengths within a file (written by another tool)
    dd = Detections.load(lay.detections(cams[3]))
    from roomcap.core.fileio import save_npz

    save_npz(
        lay.detections(cams[3]),
        {
            "schema": "detections/1",
            "camera": cams[3],
            "skeleton": dd.skeleton,
            "frame_index": dd.frame_index,
            "t_ns": dd.t_ns[:-5],
            "xy_px": dd.xy_px,
            "score": dd.score,
            "boxes": dd.boxes,
            "model": "x",
            "model_sha256": "",
        },
    )
    with pytest.raises(
        FormatError, match=rf"camera '{cams[3]}'.*t_ns.*expected shape|t_ns.*camera '{cams[3]}'"
    ):
        triangulate_session(root, TRI)


def test_an_hour_of_nobody_is_empty_not_an_error(session, tmp_path, caplog):
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    for cam in lay.detection_cameras():
        d = Detections.load(lay.detections(cam))
        _rewrite(root, cam, xy_px=np.full_like(d.xy_px, np.nan), score=np.zeros_like(d.score))
    triangulate_session(root, TRI)
    p = Poses3D.load(lay.poses3d)
    assert p.n_frames == session[1].n_frames and not np.isfinite(p.xyz_m).any()
    assert "nobody was triangulated" in caplog.text and "has no detection" in caplog.text
    track_session_greedy(root, TRK)
    tf = TrackFile.load(lay.tracks)
    assert tf.n_tracks == 0 and tf.n_frames == p.n_frames
