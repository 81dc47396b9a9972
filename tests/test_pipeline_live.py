"""pipeline.live (issue 17 item 4, issue 16): the live track stage steps the particle filter once per frame
set, never renumbers an identity, appends whole parts to track/live/, and costs the same late as early."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
from track_helpers import walkers

from capture.config import parse_config
from capture.live import LiveStep
from capture.session import SessionLayout
from capture.sources import Frame
from capture.sync import FrameSet
from pipeline.live import STAGES, LiveContext, _track, live_dir, load_live_tracks
from synthetic.rigs import ring_rig
from track.particle import ParticleConfig

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


def test_track_stage_steps_the_filter_and_appends_whole_parts(tmp_path):
    rig = ring_rig(4, radius_m=4.0)
    names = [c.name for c in rig.cameras]
    cfg = parse_config({"cameras": [{"name": n, "source": "synthetic:", "fps": 25} for n in names]})
    lay = SessionLayout(tmp_path)
    stage = _track(LiveContext(cfg, lay, rig, FAST, chunk_frames=10))
    X = walkers(2, 55, seed=3)
    per_frame_ids = []
    first_part = None
    for step in _steps(rig, X):
        stage(step)
        per_frame_ids.append(sorted(int(i) for i in step.outputs["tracks"].track_id))
        if step.frameset.index == 20:
            first_part = (live_dir(lay) / "part_000000.npz").read_bytes()
    index = json.loads((live_dir(lay) / "index.json").read_text())
    assert [p["frames"] for p in index["parts"]] == [10, 10, 10, 10, 10, 5]  # the last part at the final set
    assert (live_dir(lay) / "part_000000.npz").read_bytes() == first_part  # a part is never rewritten
    tf = load_live_tracks(live_dir(lay))
    assert tf.n_frames == 55 and tf.n_tracks == 2 and list(tf.frame_index) == list(range(55))
    # identities never renumbered: the ids the filter gave each frame are the file's, the same ids all along
    assert all(ids == [0, 1] for ids in per_frame_ids)
    for k in range(2):  # each id follows one person throughout
        d = np.linalg.norm(tf.xyz_m[:, k, None].astype(np.float64) - X, axis=-1).mean(-1)  # (T,P)
        assert len(set(d.argmin(1))) == 1 and d.min(1).max() < 0.05
    assert len(stage.tracker.tracks) == 2 and len(stage.writer._rows) == 0  # bounded state: nothing buffered


def test_the_runner_closes_the_track_stage_so_the_last_part_is_written(tmp_path):
    """A recording that ends on a non-final set (the runner skips sets when it falls behind) still gets its
    last frames: LiveRunner calls the stage's close() at the end."""
    from capture.live import LiveRunner

    rig = ring_rig(3, radius_m=4.0)
    names = [c.name for c in rig.cameras]
    cfg = parse_config({"cameras": [{"name": n, "source": "synthetic:", "fps": 25} for n in names]})
    lay = SessionLayout(tmp_path)
    stage = _track(LiveContext(cfg, lay, rig, FAST, chunk_frames=50))
    runner = LiveRunner(cfg, tmp_path, stages={"track": stage})
    for step in _steps(rig, walkers(1, 12, seed=1)):
        step.outputs["final"] = False
        stage(step)
    assert not (live_dir(lay) / "index.json").exists()  # 12 < 50 frames: nothing written yet
    runner.start()
    runner.stop()
    assert load_live_tracks(live_dir(lay)).n_frames == 12 and runner.summary()["errors"] == {}
