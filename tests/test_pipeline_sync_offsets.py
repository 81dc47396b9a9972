"""Sync offsets in session.toml (``capture-run sync``) are applied by the 3D stages.

A synthetic world rendered with known per-camera time offsets (camera frame k shows scene time
k + offset_c, synthetic.render): without the offsets in session.toml the cameras disagree and the 3D
is wrong by decimetres; with them the tracks are as good as an unshifted recording.
"""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.capture.session import SessionLayout
from roomcap.core.errors import FormatError
from roomcap.core.fileio import load_toml, save_toml
from roomcap.synthetic.render import RenderConfig, render
from roomcap.synthetic.rigs import kitchen
from roomcap.synthetic.world import SceneConfig, make_scene, write_session
from roomcap.track.greedy_stage import track_session_greedy
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate import evaluate as ev
from roomcap.triangulate.multiview import FrameShift, load_detections, sync_shifts
from roomcap.triangulate.stage import triangulate_session

OFFSETS = (0.0, 0.0, 6.0, -4.0)  # cam02 started 6 frames late, cam03 4 frames early


@pytest.fixture(scope="module")
def world():
    rig, room = kitchen(4)
    scene = make_scene(room, SceneConfig(n_people=2, duration_s=3.0, fps=25.0, seed=5))
    return rig, scene


def _session(root, world, offsets, drifts=None, sync=None):
    rig, scene = world
    rd = render(
        scene, rig, RenderConfig(noise_px=2.0, seed=5, time_offsets_frames=offsets, time_drifts_ppm=drifts)
    )
    write_session(scene, rd, rig, root)
    if sync is not None:
        meta = load_toml(root / "session.toml")
        meta["sync"] = {"method": "keypoint-speed-xcorr", "reference": "cam00", "fps": 25.0, "cameras": sync}
        save_toml(root / "session.toml", meta)
    return root


def _scores(root, scene):
    triangulate_session(root)
    tf = TrackFile.load(track_session_greedy(root))
    x = tf.xyz_m.astype(np.float64)
    assert tf.frame_index[0] == 0  # the reference camera's frame axis
    T = min(len(x), scene.n_frames)
    gt = scene.gt_xyz_m[:T]
    return ev.mpjpe(gt, x[:T])["mpjpe_m"], ev.mot_metrics(gt, x[:T]).mota, tf.n_tracks


def test_shifted_cameras_are_recovered_with_the_offsets_and_worse_without(tmp_path, world):
    rig, scene = world
    base = _scores(_session(tmp_path / "unshifted", world, (0.0,) * 4), scene)
    without = _scores(_session(tmp_path / "nosync", world, OFFSETS), scene)
    sync = {c: {"offset_frames": o, "correlation": 0.9} for c, o in zip(rig.names, OFFSETS, strict=True)}
    with_ = _scores(_session(tmp_path / "sync", world, OFFSETS, sync=sync), scene)
    # measured: unshifted 0.015 m / MOTA 1.0 / 2 tracks; no offsets 0.159 m / 0.55 / 4 tracks;
    # offsets applied 0.015 m / 1.0 / 2 tracks
    assert base[0] < 0.03 and base[1] > 0.95 and base[2] == 2
    assert (
        without[0] > 3 * base[0]
    )  # (MOTA without: 0.55 with CMU mocap people, 0.94 with procedural walkers)
    assert with_[0] < base[0] + 0.005 and with_[1] > 0.95 and with_[2] == 2


def test_drift_is_applied_too(tmp_path, world):
    rig, scene = world
    drifts = (0.0, 100_000.0, 0.0, 0.0)  # cam01 runs 10 % fast: 7.5 frames off after 75 frames
    without = _scores(_session(tmp_path / "nodrift", world, (0.0,) * 4, drifts), scene)
    sync = {c: {"offset_frames": 0.0, "drift_ppm": d} for c, d in zip(rig.names, drifts, strict=True)}
    with_ = _scores(_session(tmp_path / "drift", world, (0.0,) * 4, drifts, sync=sync), scene)
    # measured: 0.041 m without the drift, 0.015 m with it (procedural walkers, no CMU mocap: 0.026 / 0.017)
    assert with_[0] < 0.02 and with_[0] < without[0] - 0.007


def test_frame_shift_mapping_and_bad_sync_tables(tmp_path, world):
    s = FrameShift(2.4, 0.01)
    assert np.allclose(s.map(np.array([10, 20, 110])), [12.4, 22.5, 113.4])
    root = _session(tmp_path / "s", world, OFFSETS, sync={"cam02": {"offset_frames": 6.0}})
    lay = SessionLayout(root)
    rig, _ = world
    sub, mv = load_detections(lay, rig)
    assert mv.offsets_frames == {"cam02": 6.0}
    _, raw = load_detections(lay, rig, apply_sync=False)
    assert raw.offsets_frames == {} and mv.frame_index[-1] == raw.frame_index[-1] + 6
    # audio sync stores seconds: turned into frames with the session's rate
    meta = load_toml(root / "session.toml")
    meta["sync"] = {"method": "audio-envelope-xcorr", "fps": 25.0, "cameras": {"cam02": {"offset_s": 0.24}}}
    save_toml(root / "session.toml", meta)
    assert sync_shifts(lay, list(rig.names), None)["cam02"].offset_frames == pytest.approx(6.0)
    meta["sync"] = {"cameras": {"cam02": {"offset_frames": "six"}}}
    save_toml(root / "session.toml", meta)
    with pytest.raises(FormatError, match="sync.cameras.cam02.*Rerun"):
        triangulate_session(root)


def test_reprocess_carries_the_offsets_to_out_and_reruns_when_they_change(tmp_path, world):
    from roomcap.pipeline.config import PipelineConfig
    from roomcap.pipeline.discover import discover
    from roomcap.pipeline.executors import run_sessions

    rig, scene = world
    sync = {c: {"offset_frames": o} for c, o in zip(rig.names, OFFSETS, strict=True)}
    src = _session(tmp_path / "in" / "S", world, OFFSETS, sync=sync)
    cfg = PipelineConfig(stages=("triangulate", "track"))  # the greedy tracker (default)
    (r,) = run_sessions(discover([src]), tmp_path / "out", cfg, workers=1)
    assert r.status == "ok", r.message
    out = tmp_path / "out" / "S"
    assert load_toml(out / "session.toml")["sync"]["cameras"]["cam02"]["offset_frames"] == 6.0
    tf = TrackFile.load(out / "track" / "tracks.npz")
    T = min(tf.n_frames, scene.n_frames)
    assert ev.mpjpe(scene.gt_xyz_m[:T], tf.xyz_m[:T].astype(np.float64))["mpjpe_m"] < 0.03
    (again,) = run_sessions(discover([src]), tmp_path / "out", cfg, workers=1)
    assert again.ran == []
    meta = load_toml(src / "session.toml")
    meta["sync"]["cameras"]["cam02"]["offset_frames"] = 5.0
    save_toml(src / "session.toml", meta)
    (third,) = run_sessions(discover([src]), tmp_path / "out", cfg, workers=1)
    assert third.ran == ["triangulate", "track"]
