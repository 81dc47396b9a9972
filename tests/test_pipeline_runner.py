"""The session runner on detections-only synthetic sessions: caching, resuming, failure isolation, executors.

Sessions come from ``synthetic.world`` (via ``pipeline.synth``): a 4-camera ring, 1-3 people, 1 s at
25 fps, so each runs triangulate -> track -> forecast -> report in well under a second.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pipeline_helpers import stage_outputs

from roomcap.pipeline.cli import main as reprocess
from roomcap.pipeline.config import PipelineConfig
from roomcap.pipeline.discover import SessionSource, discover
from roomcap.pipeline.executors import run_sessions
from roomcap.pipeline.synth import make_sessions

REPO = Path(__file__).resolve().parents[1]
STAGES = "triangulate,track,forecast,report"
CFG = PipelineConfig(stages=tuple(STAGES.split(",")))


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sessions") / "syn"
    make_sessions(root, 4, duration_s=1.0)
    return root


@pytest.fixture(scope="module")
def reference(sessions, tmp_path_factory) -> Path:
    """One uninterrupted run (local executor, one worker) to compare the others with."""
    out = tmp_path_factory.mktemp("ref")
    assert reprocess([str(sessions), "--out", str(out), "--stages", STAGES, "--workers", "1"]) == 0
    return out


def test_rerun_does_nothing_and_is_fast(sessions, reference, capsys):
    t0 = time.perf_counter()
    results = run_sessions(discover([sessions]), reference, CFG, workers=2)
    dt = time.perf_counter() - t0
    assert all(r.status == "ok" and r.ran == [] for r in results), [(r.name, r.ran) for r in results]
    assert [r.tracks for r in results] == [1, 2, 3, 1]  # the saved summary, not recomputed
    assert dt < 5.0, f"no-op rerun of 4 sessions took {dt:.2f} s"  # measured 0.05 s


def test_new_calibration_reruns_triangulation_not_keypoints(tmp_path):
    make_sessions(tmp_path / "in", 1, duration_s=1.0)
    out = tmp_path / "out"
    cfg = PipelineConfig(stages=("triangulate", "track"))
    (first,) = run_sessions(discover([tmp_path / "in"]), out, cfg, workers=1)
    assert first.ran == ["calibration", "keypoints", "triangulate", "track"]
    rig_path = tmp_path / "in" / "syn_00" / "calib" / "rig.toml"
    from roomcap.calibrate.camera import CameraRig

    rig = CameraRig.load(rig_path)  # a recalibration: every camera 1 cm off
    cams = [
        type(c)(c.name, c.size_wh, c.K, c.dist, c.model, c.R, np.asarray(c.t) + [0.01, 0, 0])
        for c in rig.cameras
    ]
    CameraRig(tuple(cams)).save(rig_path)
    (second,) = run_sessions(discover([tmp_path / "in"]), out, cfg, workers=1)
    assert second.status == "ok", second.message
    assert second.ran == ["calibration", "triangulate", "track"]  # detections were up to date


@pytest.mark.slow
def test_killed_run_resumes_to_identical_outputs(sessions, reference, tmp_path):
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-m",
        "roomcap.pipeline.cli",
        str(sessions),
        "--out",
        str(out),
        "--stages",
        STAGES,
        "--workers",
        "1",
    ]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    # kill while the second session is being processed
    while time.time() < deadline and not (out / "syn" / "syn_01" / "triangulate" / "poses3d.npz").exists():
        if proc.poll() is not None:
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    n_reports = len(list(out.rglob("report.html")))
    assert n_reports < 4, "the run finished before it could be killed"
    assert reprocess([str(sessions), "--out", str(out), "--stages", STAGES, "--workers", "1"]) == 0
    summary = json.loads((out / "reprocess_summary.json").read_text())
    assert [s["ran"] for s in summary][0] == []  # the session done before the kill was not redone
    got, want = stage_outputs(out), stage_outputs(reference)
    assert sorted(got) == sorted(want)
    assert [k for k in want if got[k] != want[k]] == []


def test_corrupt_session_fails_alone(sessions, tmp_path, capsys):
    import shutil

    src = tmp_path / "in"
    shutil.copytree(sessions, src)
    (src / "syn_02" / "keypoints" / "cam01.npz").write_bytes(b"PK\x03\x04 this is not a zip archive")
    rc = reprocess([str(src), "--out", str(tmp_path / "out"), "--stages", STAGES, "--workers", "1"])
    assert rc == 1
    summary = {s["name"]: s for s in json.loads((tmp_path / "out" / "reprocess_summary.json").read_text())}
    bad = summary.pop("in/syn_02")
    assert bad["status"] == "failed" and bad["failed_stage"] == "triangulate"
    assert "cam01.npz" in bad["message"], bad["message"]
    assert all(s["status"] == "ok" and s["tracks"] > 0 for s in summary.values())
    err = capsys.readouterr().err
    assert "FAILED in/syn_02" in err


def test_disk_full_keeps_finished_stages(tmp_path, monkeypatch):
    from roomcap.pipeline.stages import TrackStage

    make_sessions(tmp_path / "in", 1, duration_s=1.0)
    out = tmp_path / "out"

    def full_disk(self, session, config, progress, executor):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(TrackStage, "run", full_disk)
    (r,) = run_sessions(discover([tmp_path / "in"]), out, CFG, workers=1)
    assert r.status == "failed" and r.failed_stage == "track"
    assert "disk is full" in r.message and "Free space" in r.message and "triangulate" in r.message
    poses = out / "in" / "syn_00" / "triangulate" / "poses3d.npz"
    assert poses.exists()
    monkeypatch.undo()
    (r2,) = run_sessions(discover([tmp_path / "in"]), out, CFG, workers=1)
    assert r2.status == "ok" and r2.ran == ["track", "forecast", "report"]


def test_newer_schema_and_missing_calibration_are_reported(sessions, tmp_path):
    import shutil

    src = tmp_path / "in"
    shutil.copytree(sessions / "syn_00", src / "newer")
    shutil.copytree(sessions / "syn_01", src / "nocalib")
    shutil.copytree(sessions / "syn_02", src / "good")
    toml = src / "newer" / "session.toml"
    toml.write_text(toml.read_text().replace('schema = "session/1"', 'schema = "session/7"'))
    (src / "nocalib" / "calib" / "rig.toml").unlink()
    results = {r.name: r for r in run_sessions(discover([src]), tmp_path / "out", CFG, workers=1)}
    assert results["in/good"].status == "ok"
    assert results["in/newer"].status == "failed" and "version 7" in results["in/newer"].message
    assert "Upgrade roomcap" in results["in/newer"].message
    assert results["in/nocalib"].status == "failed" and "no calibration" in results["in/nocalib"].message


@pytest.mark.slow
def test_local_and_ray_executors_give_identical_outputs(sessions, reference, tmp_path):
    ray = pytest.importorskip("ray")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        results = run_sessions(discover([sessions])[:2], tmp_path / "ray", CFG, executor="ray", workers=2)
    finally:
        ray.shutdown()
    assert all(r.status == "ok" for r in results), [r.message for r in results]
    got = stage_outputs(tmp_path / "ray")
    want = {k: v for k, v in stage_outputs(reference).items() if k.split("/")[1] in ("syn_00", "syn_01")}
    assert sorted(got) == sorted(want)
    assert [k for k in want if got[k] != want[k]] == []


def test_ray_tasks_ask_for_a_gpu_when_onnxruntime_has_cuda(monkeypatch, sessions, tmp_path):
    """Without a GPU here: a stand-in for ray records what the tasks ask for."""
    import types

    from roomcap.pipeline import executors

    asked = []
    fake = types.SimpleNamespace(
        is_initialized=lambda: True,
        remote=lambda **kw: asked.append(kw) or (lambda f: types.SimpleNamespace(remote=lambda *a: f(*a))),
        wait=lambda pending, num_returns: (pending[:1], pending[1:]),
        get=lambda r: r,
    )
    monkeypatch.setitem(sys.modules, "ray", fake)
    src = discover([sessions])[:1]
    for cuda, stages, want in [
        (True, ("keypoints", "triangulate"), 1),
        (True, ("triangulate",), 0),
        (False, ("keypoints",), 0),
    ]:
        monkeypatch.setattr(executors, "_cuda_available", lambda c=cuda: c)
        list(executors.run_ray(src, tmp_path, PipelineConfig(stages=stages), False, 1, None))
        assert asked[-1] == {"num_cpus": 1, "num_gpus": want}


@dataclasses.dataclass(frozen=True)
class _Crashing(SessionSource):
    """A session whose worker process dies on arrival (as a native crash in a decoder would)."""

    def __reduce__(self):
        return (os._exit, (3,))


@pytest.mark.slow
def test_a_crashing_worker_takes_down_only_its_session(sessions, tmp_path):
    srcs = discover([sessions])[:2]
    crash = _Crashing(**{f.name: getattr(srcs[1], f.name) for f in dataclasses.fields(SessionSource)})
    results = run_sessions([srcs[0], crash], tmp_path, CFG, workers=2)
    assert [r.status for r in results] == ["ok", "failed"], [r.message for r in results]
    assert results[1].failed_stage == "worker" and "worker process" in results[1].message


def test_in_place_session_with_only_rig_and_detections(sessions, tmp_path):
    """CONTRACTS.md: `reprocess S --stages triangulate,track` on calib/rig.toml + keypoints/*.npz only."""
    import shutil

    s = tmp_path / "S1"
    for sub in ("calib", "keypoints"):
        shutil.copytree(sessions / "syn_01" / sub, s / sub)
    assert reprocess([str(s), "--stages", "triangulate,track", "--workers", "1"]) == 0
    assert (s / "track" / "tracks.npz").exists() and not (s / "report").exists()
    assert sorted(p.name for p in s.iterdir()) == [".roomcap", "calib", "keypoints", "track", "triangulate"]


def test_changed_stage_code_reruns_that_stage_only(tmp_path, monkeypatch):
    from roomcap.pipeline import runner

    make_sessions(tmp_path / "in", 1, duration_s=1.0)
    (first,) = run_sessions(discover([tmp_path / "in"]), tmp_path / "out", CFG, workers=1)
    assert first.status == "ok"
    real = runner.stage_version
    monkeypatch.setattr(
        runner, "stage_version", lambda s, c=None: real(s, c) + ("-patched" if s == "track" else "")
    )
    (second,) = run_sessions(discover([tmp_path / "in"]), tmp_path / "out", CFG, workers=1)
    # the tracker's code changed; its output did not, so forecast and report stay up to date
    assert second.ran == ["track"]


@pytest.mark.parametrize("tracker", ["greedy", "particle"])
def test_reprocess_with_chunk_s_streams_end_to_end(sessions, tmp_path, tracker):
    """`reprocess` with chunk_s > 0: the 3D stages write their parts folders, the runner caches
    and fingerprints them, forecast and report read them, and the tracks equal the whole-session run's."""
    from roomcap.track.trackfile import TrackFile

    src = sessions / "syn_02"  # 3 people
    stages = "triangulate,track,forecast,report" if tracker == "greedy" else "track,forecast,report"
    opts = "[triangulate.options]\nchunk_s = 0.3\n" if tracker == "greedy" else ""
    extra = "\nn_samples = 60" if tracker == "particle" else ""
    (tmp_path / "c.toml").write_text(
        f'{opts}[track]\ntracker = "{tracker}"\n[track.options]\nchunk_s = 0.4{extra}\n'
    )
    (tmp_path / "w.toml").write_text(
        f'[track]\ntracker = "{tracker}"\n' + ("[track.options]\nn_samples = 60\n" if extra else "")
    )
    chunked, whole = tmp_path / "chunked", tmp_path / "whole"
    args = [str(src), "--stages", stages, "--workers", "1"]
    assert reprocess([*args, "--out", str(chunked), "--config", str(tmp_path / "c.toml")]) == 0
    assert reprocess([*args, "--out", str(whole), "--config", str(tmp_path / "w.toml")]) == 0
    s = chunked / "syn_02"
    assert (
        not (s / "track" / "tracks.npz").exists() and (s / "track" / "tracks.parts" / "index.json").exists()
    )
    if tracker == "greedy":
        assert (s / "triangulate" / "poses3d.parts" / "index.json").exists()
    assert (s / "forecast" / "preview.npz").exists() and (s / "report" / "report.html").exists()
    from roomcap.capture.session import SessionLayout
    from roomcap.pipeline.report.inputs import _load

    inp = _load(SessionLayout(s))  # what the report reads: the parts joined
    assert inp.tracks is not None and not inp.tracks_error and inp.tracks.n_tracks == 3
    assert tracker == "particle" or (inp.poses is not None and not inp.poses_error)
    a, b = (
        TrackFile.load(s / "track" / "tracks.npz"),
        TrackFile.load(whole / "syn_02" / "track" / "tracks.npz"),
    )
    assert np.array_equal(a.track_id, b.track_id) and a.n_tracks == 3
    assert np.array_equal(a.xyz_m, b.xyz_m, equal_nan=True)
    summary = json.loads((s / ".roomcap" / "summary.json").read_text())
    assert summary["tracks"] == 3 and summary["people"] == 3
    # a rerun finds every stage current (the parts folders are fingerprinted), nothing runs
    cfg = dataclasses.replace(PipelineConfig.load(tmp_path / "c.toml"), stages=tuple(stages.split(",")))
    res = run_sessions(discover([src]), chunked, cfg, workers=1)
    assert res[0].status == "ok" and res[0].ran == [], res[0].ran


@pytest.mark.parametrize("tracker", ["greedy", "particle"])
def test_long_sessions_stream_by_default(sessions, tmp_path, tracker, monkeypatch):
    """chunk_s = "auto" (the default): a session longer than STREAM_ABOVE_FRAMES is streamed in chunks of
    STREAM_CHUNK_FRAMES, a shorter one is not; the runner plans the outputs the stages write (a rerun runs
    nothing) and the tracks equal the whole-session run's bit for bit. The thresholds are lowered here so
    that a small session is "long"."""
    from roomcap.track.trackfile import TrackFile
    from roomcap.triangulate import chunks

    src = sessions / "syn_02"
    n = max(int(np.load(f)["frame_index"].shape[0]) for f in (src / "keypoints").glob("*.npz"))
    monkeypatch.setattr(chunks, "STREAM_ABOVE_FRAMES", n - 1)
    monkeypatch.setattr(chunks, "STREAM_CHUNK_FRAMES", max(n // 3, 1))
    samples = "n_samples = 60\n" if tracker == "particle" else ""
    (tmp_path / "auto.toml").write_text(f'[track]\ntracker = "{tracker}"\n[track.options]\n{samples}')
    (tmp_path / "whole.toml").write_text(
        "[triangulate.options]\nchunk_s = 0\n"
        f'[track]\ntracker = "{tracker}"\n[track.options]\nchunk_s = 0\n{samples}'
    )
    args = [str(src), "--stages", "triangulate,track", "--workers", "1"]
    auto, whole = tmp_path / "auto", tmp_path / "whole"
    assert reprocess([*args, "--out", str(auto), "--config", str(tmp_path / "auto.toml")]) == 0
    assert reprocess([*args, "--out", str(whole), "--config", str(tmp_path / "whole.toml")]) == 0
    s = auto / "syn_02"
    assert (s / "track" / "tracks.parts" / "index.json").exists() and not (
        s / "track" / "tracks.npz"
    ).exists()
    assert (s / "triangulate" / "poses3d.parts" / "index.json").exists()
    assert len(json.loads((s / "track" / "tracks.parts" / "index.json").read_text())["chunks"]) >= 3
    assert (whole / "syn_02" / "track" / "tracks.npz").is_file()
    a, b = (
        TrackFile.load(s / "track" / "tracks.npz"),
        TrackFile.load(whole / "syn_02" / "track" / "tracks.npz"),
    )
    assert np.array_equal(a.track_id, b.track_id) and a.n_tracks > 0
    for k in ("xyz_m", "confidence", "std_m", "flags"):
        assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True), k
    cfg = dataclasses.replace(PipelineConfig.load(tmp_path / "auto.toml"), stages=("triangulate", "track"))
    res = run_sessions(discover([src]), auto, cfg, workers=1)
    assert res[0].status == "ok" and res[0].ran == [], res[0].ran
    # one frame fewer than the threshold's session: whole, into the single files
    monkeypatch.setattr(chunks, "STREAM_ABOVE_FRAMES", n)
    short = tmp_path / "short"
    assert reprocess([*args, "--out", str(short), "--config", str(tmp_path / "auto.toml")]) == 0
    assert (short / "syn_02" / "track" / "tracks.npz").is_file()
    assert (short / "syn_02" / "triangulate" / "poses3d.npz").is_file()


def test_a_stage_fingerprints_the_code_it_imports_not_whole_folders():
    from roomcap.pipeline.provenance import _ROOT, code_files

    def rel(stage):
        return {f.relative_to(_ROOT).as_posix() for f in code_files(stage)}

    forecast, track, report = rel("forecast"), rel("track"), rel("report")
    assert "forecast/runtime/preview.py" in forecast and "track/trackfile.py" in forecast
    assert not {
        f for f in forecast if f.startswith("forecast/lab/")
    }  # the runtime imports nothing of the lab
    assert (
        "track/particle.py" in track
        and "track/kernels.py" in track
        and "track/checkpoints/motion_gru.pt" in track
    )
    assert not {f for f in track if f.startswith(("outputs/", "forecast/", "pipeline/report/"))}
    assert {"pipeline/report/page.py", "pipeline/report_assets/report.js"} <= report
    assert "__init__.py" in track and "track/__init__.py" in track  # packages run on import count too


def _copy_sources(dst: Path) -> Path:
    """The project's sources and the data files the stages read, copied to ``dst`` (a tree to edit)."""
    from roomcap.pipeline.provenance import _ROOT, STAGE_DATA

    packages = [
        d for d in _ROOT.iterdir() if (d / "__init__.py").is_file() and d.name not in {"build", "tests"}
    ]
    for f in [_ROOT / "__init__.py", *(f for d in packages for f in d.rglob("*.py"))]:
        rel = f.relative_to(_ROOT)
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        (dst / rel).write_bytes(f.read_bytes())
    for pattern in (p for globs in STAGE_DATA.values() for p in globs):
        for f in _ROOT.glob(pattern):
            (dst / f.relative_to(_ROOT)).parent.mkdir(parents=True, exist_ok=True)
            (dst / f.relative_to(_ROOT)).write_bytes(f.read_bytes())
    return dst


def test_editing_code_outside_a_stage_reruns_nothing_and_inside_reruns_it(tmp_path, monkeypatch):
    from roomcap.pipeline import provenance

    src = _copy_sources(tmp_path / "src")
    monkeypatch.setattr(provenance, "_ROOT", src)
    monkeypatch.setattr(provenance, "_code_cache", {})
    make_sessions(tmp_path / "in", 1, duration_s=1.0)
    (first,) = run_sessions(discover([tmp_path / "in"]), tmp_path / "out", CFG, workers=1)
    assert first.status == "ok" and {"triangulate", "track", "report"} <= set(first.ran)
    # the behaviour trainer, the LSL/OSC streams and a benchmark are outside every stage's imports
    for f in ("forecast/lab/behaviour/training.py", "outputs/lsl_osc.py", "forecast/lab/benchmark_cmu8.py"):
        (src / f).write_text((src / f).read_text() + "\n# edited\n")
    monkeypatch.setattr(provenance, "_code_cache", {})
    (second,) = run_sessions(discover([tmp_path / "in"]), tmp_path / "out", CFG, workers=1)
    assert second.status == "ok" and second.ran == []
    # the particle filter's observation model is inside the track stage's: it reruns, and as its tracks come
    # out the same, the forecast and the report stay up to date
    f = src / "track" / "observation.py"
    f.write_text(f.read_text() + "\n# edited\n")
    monkeypatch.setattr(provenance, "_code_cache", {})
    (third,) = run_sessions(discover([tmp_path / "in"]), tmp_path / "out", CFG, workers=1)
    assert third.ran == ["track"]


def test_a_behaviour_forecast_marks_the_report_stale_and_the_rerun_shows_it(tmp_path):
    from roomcap.capture.session import SessionLayout
    from roomcap.forecast.lab.behaviour.sample import run_sample
    from roomcap.pipeline.report import collect
    from roomcap.track.trackfile import TrackFile

    make_sessions(tmp_path / "in", 1, duration_s=2.0)
    (first,) = run_sessions(discover([tmp_path / "in"]), tmp_path / "out", CFG, workers=1)
    assert first.status == "ok"
    lay = SessionLayout(next((tmp_path / "out").rglob("report.html")).parents[1])
    before = lay.report_html.read_bytes()
    ids = TrackFile.load(lay.tracks).track_id.tolist()
    labels = tmp_path / "labels.csv"
    labels.write_text("track_id,start_s,end_s,label\n" + "".join(f"{i},0,1.9,walk\n" for i in ids))
    run_sample(lay.root, labels)  # writes SESSION/forecast/behaviour.npz with the shipped checkpoint
    (second,) = run_sessions(discover([tmp_path / "in"]), tmp_path / "out", CFG, workers=1)
    assert second.ran == ["report"]
    assert lay.report_html.read_bytes() != before
    assert collect(lay, "t")["behaviour"]["track_id"] == ids
