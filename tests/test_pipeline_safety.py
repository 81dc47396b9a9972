"""Safe by default: one run per session (the lock), outputs checked against the cache's record, warnings
kept with the stages' outputs, Ctrl-C, and the smaller faults of everyday use.

The session is a synthetic detections-only one (``pipeline.synth``, 4 cameras, 4 people, 20 s at 25 fps);
the particle tracker with 1,000 samples makes one run hold the lock for about 7 s on an idle machine, long
enough for a second run started 2 s later (and its own start-up, about 1.5 s) to meet the first.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pipeline_helpers import stage_outputs

from roomcap.pipeline.cli import main as reprocess
from roomcap.pipeline.config import PipelineConfig
from roomcap.pipeline.discover import discover
from roomcap.pipeline.executors import run_sessions
from roomcap.pipeline.lock import LockHolder, holder, lock_path, session_lock
from roomcap.pipeline.synth import make_session
from roomcap.track.greedy_stage import GreedyTrackConfig

REPO = Path(__file__).resolve().parents[1]
PARTICLE = '[track]\ntracker = "particle"\n[track.options]\nn_samples = 1000\n'


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    return make_session(tmp_path_factory.mktemp("in") / "S1", seed=1, n_people=4, duration_s=20.0)


@pytest.fixture(scope="module")
def config_toml(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cfg") / "particle.toml"
    p.write_text(PARTICLE)
    return p


@pytest.fixture(scope="module")
def reference(session, config_toml, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ref")
    assert reprocess([str(session), "--out", str(out), "--workers", "1", "--config", str(config_toml)]) == 0
    return out


def _start(session: Path, out: Path, cfg: Path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "roomcap.pipeline.cli", str(session), "--out", str(out), "--workers", "1"]
    return subprocess.Popen(
        [*cmd, "--config", str(cfg), *extra],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.parametrize("delay_s, wait", [(0.5, False), (2.0, False), (2.0, True)])
def test_two_concurrent_runs_on_one_session(session, config_toml, reference, tmp_path, delay_s, wait):
    """A double-click or a cron job overlapping a manual run: the second run refuses (exit 2, naming the
    first run's pid and start time) or, with --wait, waits; the outputs equal a single run's."""
    out = tmp_path / "out"
    first = _start(session, out, config_toml)
    deadline = time.monotonic() + 60.0  # the delay counts from the first run holding the lock
    while holder(out / "S1") is None and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(delay_s)
    second = _start(session, out, config_toml, *(["--wait"] if wait else []))
    (_, e1), (o2, e2) = first.communicate(timeout=120), second.communicate(timeout=120)
    assert first.returncode == 0, e1
    if wait:
        assert second.returncode == 0, e2
        assert "waiting" in e2 and f"pid {first.pid}" in e2  # it said whom it waited for
        summary = json.loads((out / "reprocess_summary.json").read_text())
        assert summary[0]["ran"] == []  # the first run's outputs were current when the lock came free
    else:
        assert second.returncode == 2, (o2, e2)
        assert f"LOCKED S1: {out / 'S1'} is being processed by another run: pid {first.pid}" in e2
        assert "started 20" in e2 and "--wait" in e2
    got, want = stage_outputs(out), stage_outputs(reference)
    assert sorted(got) == sorted(want)
    assert [k for k in want if got[k] != want[k]] == []
    assert holder(out / "S1") is None  # released


def test_stale_lock_of_a_killed_run_is_taken_over(session, tmp_path, caplog):
    """A run killed with SIGKILL leaves its lock file; the kernel freed its flock, so the next run takes
    it over and says so."""
    out = tmp_path / "out"
    cfg = PipelineConfig(stages=("triangulate",))
    code = (
        "import sys, time; from pipeline.lock import session_lock\n"
        "with session_lock(sys.argv[1]):\n    print('locked', flush=True); time.sleep(60)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(out / "S1")], cwd=REPO, stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "locked"
    held = holder(out / "S1")
    assert held is not None and held.pid == proc.pid and held.host == socket.gethostname()
    (r,) = run_sessions(discover([session]), out, cfg, workers=1)
    assert r.status == "locked" and f"pid {proc.pid}" in r.message
    proc.kill()
    proc.wait()
    assert json.loads(lock_path(out / "S1").read_text())["pid"] == proc.pid  # the file stays
    assert holder(out / "S1") is None  # but nobody holds it
    (r,) = run_sessions(discover([session]), out, cfg, workers=1)
    assert r.status == "ok", r.message
    assert any("took over the lock" in w and f"pid {proc.pid}" in w for w in r.warnings), r.warnings


def test_lock_in_one_process_and_wait(tmp_path):
    """Two holders in one process conflict as well (flock is per open file); wait=True waits."""
    import threading

    from roomcap.pipeline.lock import SessionLocked

    with session_lock(tmp_path) as lock:
        assert holder(tmp_path) == lock.holder
        with pytest.raises(SessionLocked, match=f"pid {os.getpid()}"):
            with session_lock(tmp_path):
                pass
        said: list[str] = []
        got: list[LockHolder] = []

        def waiter():
            with session_lock(tmp_path, wait=True, on_wait=said.append) as lk:
                got.append(lk.holder)

        t = threading.Thread(target=waiter)
        t.start()
        time.sleep(0.5)
        assert not got and said and "waiting" in said[0]
    t.join(5)
    assert got and holder(tmp_path) is None


# ----------------------------------------------------------------------------- the cache's record


@pytest.mark.parametrize("change", ["truncate", "same_size", "delete_part"])
def test_outputs_that_are_not_what_the_stage_wrote_are_not_trusted(session, tmp_path, caplog, change):
    """Each output's size and sha256 are in the stage's record; an output changed behind the cache's back
    (even with its size and mtime kept) reruns the stage, which says which file and how."""
    out = tmp_path / "out"
    cfg = PipelineConfig(stages=("triangulate", "track"))
    if change == "delete_part":  # a streamed track: a folder of parts
        cfg = cfg.replace(track=GreedyTrackConfig.from_dict({"chunk_s": 1.0}))
    (first,) = run_sessions(discover([session]), out, cfg, workers=1)
    assert first.status == "ok", first.message
    s = out / "S1"
    want = stage_outputs(s)
    target = s / "track" / "tracks.npz"
    if change == "truncate":
        target.write_bytes(target.read_bytes()[:100])
    elif change == "same_size":
        st = target.stat()
        data = bytearray(target.read_bytes())
        data[len(data) // 2] ^= 0xFF
        target.write_bytes(bytes(data))
        os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))  # the same size and mtime
    else:
        parts = sorted((s / "track" / "tracks.parts").glob("*.npz"))
        assert len(parts) >= 2
        parts[-1].unlink()
    caplog.clear()
    (second,) = run_sessions(discover([session]), out, cfg, workers=1)
    assert second.status == "ok" and second.ran == ["track"], (second.ran, second.message)
    said = [r.getMessage() for r in caplog.records if "reruns" in r.getMessage()]
    assert said and "not what it wrote" in said[0], said
    assert {"truncate": "bytes, the stage wrote", "same_size": "sha256 differs", "delete_part": "is missing"}[
        change
    ] in said[0]
    assert stage_outputs(s) == want  # restored byte for byte
    (third,) = run_sessions(discover([session]), out, cfg, workers=1)
    assert third.ran == []


def test_record_holds_size_and_sha256_of_each_output(session, tmp_path):
    import hashlib

    out = tmp_path / "out"
    run_sessions(discover([session]), out, PipelineConfig(stages=("triangulate",)), workers=1)
    rec = json.loads((out / "S1" / ".roomcap" / "provenance" / "triangulate.json").read_text())
    f = out / "S1" / "triangulate" / "poses3d.npz"
    assert rec["output_files"] == {
        "triangulate/poses3d.npz": {
            "size": f.stat().st_size,
            "sha256": hashlib.sha256(f.read_bytes()).hexdigest(),
        }
    }


# ----------------------------------------------------------------------------- warnings kept


def test_warnings_survive_cached_reruns(session, tmp_path):
    """A kilometre-wide rig is warned on the first run and again, from the stage's record, on every cached
    or partly cached rerun: in the summary table, the summary file and the report."""
    import shutil

    import numpy as np

    from roomcap.calibrate.camera import CameraRig
    from roomcap.capture.session import SessionLayout
    from roomcap.pipeline.report.problems import _warnings

    src = tmp_path / "in" / "wide"
    shutil.copytree(session, src)
    rig = CameraRig.load(src / "calib" / "rig.toml")  # translations in millimetres
    cams = [
        type(c)(c.name, c.size_wh, c.K, c.dist, c.model, c.R, np.asarray(c.t) * 1000) for c in rig.cameras
    ]
    CameraRig(tuple(cams)).save(src / "calib" / "rig.toml")
    out = tmp_path / "out"
    args = [str(src), "--out", str(out), "--workers", "1"]
    for stages in ("triangulate,track", "triangulate,track", "triangulate,track,forecast,report", "report"):
        assert reprocess([*args, "--stages", stages]) == 0
        (r,) = json.loads((out / "reprocess_summary.json").read_text())
        assert any("km), wider than any room" in w for w in r["warnings"]), (stages, r["warnings"])
        assert "km), wider than any room" in r["message"], (stages, r["message"])
        assert "warning: " in (out / "reprocess_summary.txt").read_text()  # in the table too
    shown = [w["message"] for w in _warnings(SessionLayout(out / "wide"))]
    assert any("km), wider than any room" in m for m in shown), shown


# ----------------------------------------------------------------------------- Ctrl-C


def test_ctrl_c_says_stopping_and_ends_within_2_s_keeping_finished_stages(
    session, config_toml, reference, tmp_path
):
    out = tmp_path / "out"
    proc = _start(session, out, config_toml)
    poses = out / "S1" / "triangulate" / "poses3d.npz"
    deadline = time.time() + 60
    while not poses.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    time.sleep(0.3)  # inside the track stage (about 3 s)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    t0 = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    dt = time.perf_counter() - t0
    assert proc.returncode == 130, err
    assert err.startswith("reprocess: stopping…"), err
    assert dt < 2.0, f"took {dt:.2f} s to stop"  # measured 0.1-0.3 s
    assert reprocess([str(session), "--out", str(out), "--workers", "1", "--config", str(config_toml)]) == 0
    (r,) = json.loads((out / "reprocess_summary.json").read_text())
    assert r["ran"][0] == "track" and "triangulate" not in r["ran"]  # the finished stage was kept
    got, want = stage_outputs(out), stage_outputs(reference)
    assert sorted(got) == sorted(want) and [k for k in want if got[k] != want[k]] == []


def test_a_command_that_does_not_stop_is_ended_after_the_grace(tmp_path):
    """Work that ignores the interrupt (a thread pool draining its queue, a native call): the guard's
    watchdog ends the process with 130 within STOP_GRACE_S of the first Ctrl-C."""
    code = (
        "import time\nfrom core.cli import guarded\n"
        "def main(argv):\n"
        "    while True:\n"
        "        try:\n            print('ready', flush=True)\n            time.sleep(30)\n"
        "        except KeyboardInterrupt:\n            pass  # keeps working\n"
        "raise SystemExit(guarded('stubborn', main)([]))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    t0 = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    dt = time.perf_counter() - t0
    assert proc.returncode == 130 and "stubborn: stopping…" in err and "stubborn: stopped" in err, err
    assert dt < 2.0, f"{dt:.2f} s"


def test_ray_tasks_take_the_same_lock(session, tmp_path, monkeypatch):
    """A session run as a Ray task (a stand-in for ray runs the task here) meets the lock like a local run."""
    import types

    from roomcap.pipeline import executors

    fake = types.SimpleNamespace(
        is_initialized=lambda: True,
        remote=lambda **kw: lambda f: types.SimpleNamespace(remote=lambda *a: f(*a)),
        wait=lambda pending, num_returns: (pending[:1], pending[1:]),
        get=lambda r: r,
    )
    monkeypatch.setitem(sys.modules, "ray", fake)
    cfg = PipelineConfig(stages=("triangulate",))
    out = tmp_path / "out"
    with session_lock(out / "S1") as lock:
        (r,) = executors.run_ray(discover([session]), out, cfg, False, 1, None)
    assert r.status == "locked" and f"pid {lock.holder.pid}" in r.message
    (r,) = executors.run_ray(discover([session]), out, cfg, False, 1, None)
    assert r.status == "ok" and r.ran == ["calibration", "keypoints", "triangulate"], (r.ran, r.message)


def test_a_ctrl_c_that_native_code_hands_back_as_another_error_still_stops(session, tmp_path, monkeypatch):
    """The SIGINT handler's KeyboardInterrupt, raised while a numba kernel dispatched, came back as
    SystemError ("returned a result with an exception set"): the run must stop as interrupted (130), not
    report the stage failed (CI saw it once)."""
    from roomcap.pipeline import runner

    def stage_hit_by_ctrl_c(*a, **k):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise SystemError("CPUDispatcher(gru_gates) returned a result with an exception set") from ki

    monkeypatch.setattr(runner, "_run_stage", stage_hit_by_ctrl_c)
    (src,) = discover([session])
    with pytest.raises(KeyboardInterrupt):
        runner.process_session(src, tmp_path / "out", PipelineConfig())
    monkeypatch.setattr(runner, "_run_stage", lambda *a, **k: (_ for _ in ()).throw(SystemError("a bug")))
    res = runner.process_session(src, tmp_path / "out", PipelineConfig())
    assert res.status == "failed" and "SystemError: a bug" in res.message  # a real error still reads as one
