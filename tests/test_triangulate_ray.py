"""On Ray, the time chunks of one session as Ray tasks (``[triangulate.options] executor =
"ray"``) give the one-process parts byte for byte, and ``reprocess --executor ray`` sends a chunked
session's chunks to the cluster, nested in the session's task, with the local executor's tracks."""

from __future__ import annotations

import json
import shutil
import sys

import numpy as np
import pytest
from triangulate_helpers import killed_after_commits

from roomcap.capture.session import SessionLayout
from roomcap.core.errors import InputError
from roomcap.keypoints.detections import Detections
from roomcap.pipeline.config import PipelineConfig
from roomcap.pipeline.discover import discover
from roomcap.pipeline.executors import run_sessions
from roomcap.synthetic.render import RenderConfig, render
from roomcap.synthetic.rigs import kitchen
from roomcap.synthetic.world import SceneConfig, make_scene, write_session
from roomcap.track.greedy_stage import GreedyTrackConfig
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate import chunks as C
from roomcap.triangulate.reconstruct import TriangulateConfig
from roomcap.triangulate.stage import triangulate_session

TRI = {"chunk_s": 2.0}  # 12 s at 25 Hz: 6 chunks
TRK = {"chunk_s": 3.0}


def _triangulate_on(root, options):
    """``triangulate_session`` with its chunks run as ``options`` say (``workers``, ``executor``)."""
    from roomcap.pipeline.executors import chunk_runner

    cfg = TriangulateConfig.from_dict(options)
    return triangulate_session(root, cfg, executor=chunk_runner(cfg.stream))


def _ray():
    return pytest.importorskip("ray", reason="Ray is an optional extra: pip install 'roomcap[cluster]'")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """12 s, 4 kitchen cameras, 4 people entering and leaving; the first camera saw nobody (its detections
    are blank), for the workers' "camera without detections" bookkeeping."""
    rig, room = kitchen(4)
    scene = make_scene(room, SceneConfig(n_people=4, duration_s=12.0, fps=25.0, seed=5, enter_leave=True))
    rd = render(
        scene, rig, RenderConfig(noise_px=3.0, missed_joint_rate=0.15, false_positive_rate=0.1, seed=5)
    )
    root = tmp_path_factory.mktemp("ray") / "s"
    write_session(scene, rd, rig, root)
    lay = SessionLayout(root)
    for p in (lay.poses3d, lay.tracks):
        C.remove_output(p)
    cam = lay.detection_cameras()[0]
    d = Detections.load(lay.detections(cam))
    Detections(
        camera=d.camera,
        skeleton=d.skeleton,
        frame_index=d.frame_index,
        t_ns=d.t_ns,
        xy_px=np.full_like(d.xy_px, np.nan),
        score=np.zeros_like(d.score),
        boxes=d.boxes,
        model=d.model,
        model_sha256=d.model_sha256,
    ).save(lay.detections(cam))
    return root, cam


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def _shas(folder) -> dict:
    return {k: v["sha256"] for k, v in json.loads((folder / "index.json").read_text())["parts"].items()}


def test_without_ray_the_message_says_how_to_install(session, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails as where it is not installed
    with pytest.raises(InputError, match=r"executor = 'ray' needs ray: pip install 'roomcap\[cluster\]'"):
        _triangulate_on(_copy(session[0], tmp_path / "s"), {**TRI, "executor": "ray"})
    with pytest.raises(ValueError, match="executor must be one of"):
        _triangulate_on(tmp_path / "s", {**TRI, "executor": "dask"})


@pytest.mark.slow
def test_chunks_as_ray_tasks_equal_one_process(session, tmp_path, monkeypatch, caplog):
    """2 Ray workers (a local Ray started for the stage, stopped after) write the parts of one process
    byte for byte; a Ray run killed between parts stops its Ray, and the rerun resumes."""
    ray = _ray()
    assert not ray.is_initialized()
    one = _copy(session[0], tmp_path / "one")
    triangulate_session(one, TRI)
    want = _shas(C.parts_dir(SessionLayout(one).poses3d))
    assert len(want) == 6

    fresh = _copy(session[0], tmp_path / "fresh")
    caplog.clear()
    _triangulate_on(fresh, {**TRI, "workers": 2, "executor": "ray"})  # every chunk a Ray task
    assert not ray.is_initialized()  # the Ray started for the stage is stopped
    assert _shas(C.parts_dir(SessionLayout(fresh).poses3d)) == want
    said = [r.getMessage() for r in caplog.records if "has no detection" in r.getMessage()]
    assert len(said) == 1 and f"camera '{session[1]}'" in said[0], said  # only the blank camera

    killed = _copy(session[0], tmp_path / "killed")
    with killed_after_commits(monkeypatch, 2), pytest.raises(KeyboardInterrupt):
        _triangulate_on(killed, {**TRI, "workers": 2, "executor": "ray"})
    assert not ray.is_initialized()  # a kill between parts stops the Ray started here too
    idx = json.loads((C.parts_dir(SessionLayout(killed).poses3d) / "index.json").read_text())
    assert not idx["complete"] and len(idx["parts"]) == 2
    _triangulate_on(killed, {**TRI, "workers": 2})  # resumed by processes: the same parts
    assert _shas(C.parts_dir(SessionLayout(killed).poses3d)) == want


def test_reprocess_on_ray_sends_a_sessions_chunks_to_the_cluster(session, tmp_path):
    """Two chunked sessions on a 2-CPU Ray: both session tasks hold the 2 CPUs and wait for their chunk
    tasks (no deadlock: a blocked task lends its CPU); the tracks equal the local executor's, and the
    run is up to date for the local executor (``executor`` is not in the stage's fingerprint)."""
    ray = _ray()
    src = tmp_path / "in"
    for name in ("a", "b"):
        _copy(session[0], src / name)
    cfg = PipelineConfig(
        stages=("triangulate", "track"),
        triangulate=TriangulateConfig.from_dict(TRI),
        track=GreedyTrackConfig.from_dict(TRK),
    )
    local = run_sessions(discover([src]), tmp_path / "local", cfg, workers=1)
    assert [r.status for r in local] == ["ok", "ok"], [r.message for r in local]
    assert not ray.is_initialized()
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = run_sessions(discover([src]), tmp_path / "ray", cfg, executor="ray", workers=2)
        tasks = [e for e in ray.timeline() if e.get("name", "").endswith("_chunk_worker")]
    finally:
        ray.shutdown()
    assert [r.status for r in on_ray] == ["ok", "ok"], [r.message for r in on_ray]
    assert len({e.get("args", {}).get("task_id") for e in tasks} - {None}) >= 12  # 2 sessions x 6 chunks
    for name in ("in/a", "in/b"):
        lay_l, lay_r = SessionLayout(tmp_path / "local" / name), SessionLayout(tmp_path / "ray" / name)
        assert _shas(C.parts_dir(lay_r.poses3d)) == _shas(C.parts_dir(lay_l.poses3d))
        assert _shas(C.parts_dir(lay_r.tracks)) == _shas(C.parts_dir(lay_l.tracks))
        a, b = TrackFile.load(lay_l.tracks), TrackFile.load(lay_r.tracks)
        assert a.n_tracks >= 4 and np.array_equal(a.track_id, b.track_id)
        assert np.array_equal(a.xyz_m, b.xyz_m, equal_nan=True)
    again = run_sessions(discover([src]), tmp_path / "ray", cfg, workers=1)
    assert [r.ran for r in again] == [[], []]


def test_a_chunked_pipeline_asks_for_ray_chunks_only_on_ray():
    from roomcap.pipeline.executors import ray_for_chunks

    cfg = PipelineConfig(triangulate=TriangulateConfig.from_dict(TRI))
    assert ray_for_chunks(cfg).triangulate.stream.executor == "ray"
    mine = PipelineConfig(triangulate=TriangulateConfig.from_dict({**TRI, "workers": 2}))
    assert ray_for_chunks(mine).triangulate.stream.executor == "processes"  # the user's choice kept
    # the default chunk_s ("auto") streams a long session: its chunks may go to Ray
    assert ray_for_chunks(PipelineConfig()).triangulate.stream.executor == "ray"
    whole = PipelineConfig(triangulate=TriangulateConfig.from_dict({"chunk_s": 0}))
    assert ray_for_chunks(whole).triangulate.stream.executor == "processes"  # whole session: one task
