"""Every command ends bad input with one message and exit code 2, Ctrl-C with 130, never a traceback."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from roomcap.core.cli import EXIT_INPUT, EXIT_INTERRUPTED, guarded
from roomcap.core.errors import InputError, RoomcapError, UnknownNameError

REPO = Path(__file__).resolve().parents[1]


def _raiser(exc: BaseException):
    def main(argv=None):
        raise exc

    return guarded("prog", main)


@pytest.mark.parametrize(
    "exc,text",
    [
        (InputError("--x is wrong; give y"), "prog: error: --x is wrong; give y"),
        (UnknownNameError("unknown set 'a'; known: ['b']"), "prog: error: unknown set 'a'; known: ['b']"),
        (OSError(errno.ENOSPC, "No space left on device", "/data/x.npz"), "the disk is full"),
        (PermissionError(errno.EACCES, "Permission denied", "/ro/out"), "check the permissions"),
        (ValueError("rtsp://u:pw@cam/x is not a camera"), "rtsp://***@cam/x"),
    ],
)
def test_errors_are_one_line_and_exit_2(exc, text, capsys):
    assert _raiser(exc)([]) == EXIT_INPUT
    err = capsys.readouterr().err
    assert text in err and "Traceback" not in err and err.count("\n") == 1


def test_interrupt_exits_130_and_bugs_keep_their_traceback(capsys):
    assert _raiser(KeyboardInterrupt())([]) == EXIT_INTERRUPTED
    assert "interrupted" in capsys.readouterr().err
    with pytest.raises(ZeroDivisionError):
        _raiser(ZeroDivisionError("a bug"))([])


def test_project_errors_share_one_base_and_keep_their_builtin_parents():
    from roomcap.calibrate.boards import CalibrationError
    from roomcap.capture.recorder import RecorderError
    from roomcap.capture.sources import SourceError
    from roomcap.core.errors import FormatError
    from roomcap.keypoints.registry import ModelError
    from roomcap.keypoints.video import VideoDecodeError
    from roomcap.outputs.cli import UsageError
    from roomcap.outputs.export import ExportError
    from roomcap.outputs.opensim_ik import OpenSimError
    from roomcap.outputs.skeleton_fit_file import FitError
    from roomcap.pipeline.discover import SessionError
    from roomcap.pipeline.session_inputs import StageError
    from roomcap.track.motion import CheckpointMismatch

    parents = {
        CalibrationError: RuntimeError, FormatError: ValueError, RecorderError: RuntimeError,
        SourceError: RuntimeError, ModelError: FileNotFoundError, VideoDecodeError: RuntimeError,
        SessionError: RuntimeError, StageError: RuntimeError, CheckpointMismatch: ValueError,
        UsageError: ValueError, ExportError: ValueError, FitError: ValueError, OpenSimError: ValueError,
    }  # fmt: skip
    for cls, builtin in parents.items():
        assert issubclass(cls, RoomcapError) and issubclass(cls, builtin), cls


def _bad_inputs(tmp: Path) -> list[tuple[str, list[str], str]]:
    (tmp / "bin.toml").write_bytes(bytes(range(256)) * 8)
    (tmp / "text.npz").write_text("not an archive")
    (tmp / "afile").write_text("x")
    return [
        ("reprocess", ["x", "--max-frames", "-5"], "out of range"),
        ("reprocess", [str(tmp), "--out", str(tmp / "afile")], "is a file; give a folder"),
        ("forecast", ["sample", "--tracks", "t.npz", "--out", "o", "--horizon-s", "-1"], "out of range"),
        ("forecast", ["eval", "--samples", "0", "--out", "o"], "out of range"),
        ("forecast", ["sample", "--tracks", f"{tmp}/text.npz", "--out", f"{tmp}/o.npz"], "not an npz"),
        ("keypoints", ["run", str(tmp / "nope.mp4"), "--out", str(tmp / "kp")], "do not exist"),
        ("keypoints", ["run", f"{tmp}/afile", "--out", f"{tmp}/kp", "--models", "nosuchset"], "known:"),
        ("calibrate-run", ["import", str(tmp / "bin.toml"), "--out", str(tmp / "r.toml")], "binary file"),
    ]  # fmt: skip


def test_every_command_answers_bad_input_with_a_message(tmp_path, capsys):
    from roomcap.calibrate.cli import main as calibrate_main
    from roomcap.forecast.cli import main as forecast_main
    from roomcap.keypoints.cli import main as keypoints_main
    from roomcap.pipeline.cli import main as reprocess_main

    mains = {"reprocess": reprocess_main, "forecast": forecast_main, "keypoints": keypoints_main,
             "calibrate-run": calibrate_main}  # fmt: skip
    for prog, argv, text in _bad_inputs(tmp_path):
        try:
            code = mains[prog](argv)
        except SystemExit as e:  # argparse's usage errors
            code = e.code
        err = capsys.readouterr().err
        assert code == 2, (prog, argv, err)
        assert text in err and "Traceback" not in err, (prog, argv, err)


@pytest.mark.slow
def test_ctrl_c_during_reprocess_is_one_line_and_a_rerun_resumes(tmp_path):
    from roomcap.pipeline.synth import make_session

    root = make_session(tmp_path / "s", n_people=4, duration_s=40.0, n_cams=6)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # as the `reprocess` console script runs it (under `python -m`, runpy sometimes turns the handled
    # interrupt into a SIGINT exit at shutdown)
    script = "import sys; from pipeline.cli import main; sys.exit(main())"
    cmd = [sys.executable, "-c", script, str(root), "--stages", "triangulate,track", "--workers", "1"]
    proc = subprocess.Popen(
        [*cmd, "-v"],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # pytest-xdist workers ignore SIGINT, and an ignored signal stays ignored in a child: restore it
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    seen = []
    for line in proc.stderr:  # wait until the triangulation runs (seconds of work for 1000 frames)
        seen.append(line)
        if "running triangulate" in line:
            break
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    err = "".join(seen) + err
    assert proc.returncode == 130, (out, err)
    assert "interrupted" in err and "Traceback" not in err, err
    rerun = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr
    assert np.load(root / "track" / "tracks.npz")["xyz_m"].shape[0] == 1000
