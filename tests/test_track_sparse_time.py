"""Snapshots far apart in time (a time-lapse or motion-triggered recording): frames a minute apart with
consecutive frame numbers and true timestamps. Neither tracker may make the 3D worse than the per-frame
triangulation it starts from; both say that such frames cannot be linked and keep their poses."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from roomcap.capture.session import SessionLayout
from roomcap.core.fileio import load_npz, load_toml, save_toml
from roomcap.synthetic.render import RenderConfig, render
from roomcap.synthetic.rigs import kitchen
from roomcap.synthetic.world import SceneConfig, make_scene, write_session
from roomcap.track.greedy_stage import track_session_greedy
from roomcap.track.stage import track_session_particle
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate import evaluate as ev
from roomcap.triangulate.poses3d import Poses3D
from roomcap.triangulate.stage import triangulate_session

SNAPSHOTS = 40
PARTICLE = {"n_samples": 150}


@pytest.fixture(scope="module")
def sparse(tmp_path_factory):
    """Kitchen, 6 cameras, 6 people, one frame a minute for 40 minutes (the synthetic world sampled at
    1/60 Hz: its timestamps are a minute apart); the session's nominal rate is the cameras' 25 Hz."""
    rig, room = kitchen(6)
    scene = make_scene(room, SceneConfig(n_people=6, duration_s=60.0 * SNAPSHOTS, fps=1 / 60, seed=3))
    rd = render(scene, rig, RenderConfig(noise_px=2.0, seed=3))
    root = tmp_path_factory.mktemp("sparse")
    lay = write_session(scene, rd, rig, root)
    meta = load_toml(lay.session_toml)
    save_toml(lay.session_toml, {**meta, "fps": 25.0})
    triangulate_session(root)
    gt = load_npz(root / "gt.npz")["gt_xyz_m"].astype(np.float64)
    t_ns = Poses3D.load(lay.poses3d).t_ns
    assert np.allclose(np.diff(t_ns), 60e9) and len(t_ns) == SNAPSHOTS
    return root, gt


def _scores(gt: np.ndarray, xyz: np.ndarray) -> tuple[float, float]:
    """(PCP actor average, recall = person-frames found within 0.3 m)."""
    x = xyz.astype(np.float64)
    mot = ev.mot_metrics(gt, x, threshold_m=0.3)
    return ev.pcp(gt, x).actor_average, 1.0 - mot.misses / mot.n_gt


@pytest.mark.parametrize("tracker", ["greedy", "particle"])
def test_snapshots_a_minute_apart_keep_the_per_frame_poses(sparse, tracker, caplog):
    root, gt = sparse
    lay = SessionLayout(root)
    pcp0, rec0 = _scores(gt, Poses3D.load(lay.poses3d).xyz_m)
    assert pcp0 > 0.8 and rec0 > 0.95  # the per-frame triangulation: measured 0.898, 0.988
    with caplog.at_level(logging.WARNING):
        if tracker == "greedy":
            track_session_greedy(root, {"chunk_s": 0})
        else:
            track_session_particle(root, {**PARTICLE, "chunk_s": 0})
    assert any("cannot be linked in time" in r.getMessage() for r in caplog.records)
    tf = TrackFile.load(lay.tracks)
    pcp, rec = _scores(gt, tf.xyz_m)
    # measured: greedy 0.992 / 1.000 of the per-frame PCP / recall; particle 1.07 / 0.987
    # (before: greedy dropped every track shorter than 5 frames, 0.87 / 0.88; the particle filter predicted
    # tracks across the minutes and gathered other people's detections, 0.64 / 0.64)
    assert pcp >= 0.98 * pcp0 and rec >= 0.98 * rec0, (pcp, pcp0, rec, rec0)


@pytest.mark.parametrize("tracker", ["greedy", "particle"])
def test_snapshots_streamed_equal_whole(sparse, tracker, tmp_path):
    """The streamed stages keep the same short tracks (the minimum length is judged on the whole session)."""
    import shutil

    root = tmp_path / "s"
    shutil.copytree(sparse[0], root)
    run = track_session_greedy if tracker == "greedy" else track_session_particle
    opts = {} if tracker == "greedy" else PARTICLE
    run(root, {**opts, "chunk_s": 0})
    whole = TrackFile.load(SessionLayout(root).tracks)
    run(root, {**opts, "chunk_s": 0.4})  # 10 frames per chunk: 4 parts
    parts = TrackFile.load(SessionLayout(root).tracks)
    assert np.array_equal(whole.track_id, parts.track_id)
    for k in ("xyz_m", "confidence", "std_m", "flags"):
        assert np.array_equal(getattr(whole, k), getattr(parts, k), equal_nan=True), k
