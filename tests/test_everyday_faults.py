"""The smaller faults of everyday use, one test each: ``~`` in path options, two cameras on one source,
forecasting a too-short track, a calibration recording without any board, ``capture-run sync`` on a
Pose2Sim trial, ``partial`` sessions' exit code, ``tracks export --person 99``, ``calibrate-run export``
onto its own input, and every command's ``--help`` naming each option's default.

(Ctrl-C, the lock and the warnings of cached reruns are in ``test_pipeline_safety.py``.)
"""

from __future__ import annotations

import argparse
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from roomcap.pipeline.cli import main as reprocess
from roomcap.pipeline.synth import make_session


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    return make_session(tmp_path_factory.mktemp("in") / "S1", seed=2, n_people=2, duration_s=1.0)


@pytest.fixture(scope="module")
def tracked(session, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("out")
    assert (
        reprocess([str(session), "--out", str(out), "--stages", "triangulate,track", "--workers", "1"]) == 0
    )
    return out / "S1"


# ----------------------------------------------------------------------------- ~ in path options


@pytest.mark.parametrize("form", ["--out=~/exports", "--out ~/exports"])
def test_tilde_in_out_is_the_home_folder(session, tmp_path, monkeypatch, capsys, form):
    home, cwd = tmp_path / "home", tmp_path / "cwd"
    home.mkdir()
    cwd.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(cwd)
    rc = reprocess([str(session), *form.split(" "), "--stages", "triangulate", "--workers", "1"])
    assert rc == 0, capsys.readouterr().err
    assert (home / "exports" / "S1" / "triangulate" / "poses3d.npz").exists()
    assert not (cwd / "~").exists() and list(cwd.iterdir()) == []


def test_tilde_in_other_commands(tracked, tmp_path, monkeypatch):
    from roomcap.calibrate.cli import main as calibrate_run
    from roomcap.outputs.cli import main as tracks

    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    rig = tracked / "calib" / "rig.toml"
    assert calibrate_run(["export", str(rig), "--format", "aniposelib", "--out=~/c/calibration.toml"]) == 0
    assert (tmp_path / "c" / "calibration.toml").exists()
    assert tracks(["export", str(tracked), "--format", "csv", "--out", "~/t"]) == 0
    assert list((tmp_path / "t").glob("*.csv")) and not (tmp_path / "~").exists()


# ----------------------------------------------------------------------------- two cameras, one source


def test_two_cameras_on_one_source_are_warned(tmp_path, capsys):
    from test_capture_sources import write_video

    from roomcap.capture.cli import main as capture_run

    v = write_video(tmp_path / "cam.mp4", n=10, fps=25)
    cams = tmp_path / "cams.yaml"
    cams.write_text(
        f"cameras:\n  - {{name: a, source: '{v}'}}\n  - {{name: b, source: '{tmp_path}/./cam.mp4'}}\n"
    )
    assert capture_run(["check", "--cameras", str(cams)]) == 1
    err = capsys.readouterr().err
    assert (
        "capture-run check: warning: cameras 'a', 'b' all read" in err and "Give each camera its own" in err
    )
    rc = capture_run(["--cameras", str(cams), "--out", str(tmp_path / "s"), "--duration", "2", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0 and err.count("cameras 'a', 'b' all read") == 2  # at the start and beside the skew
    ok = tmp_path / "ok.yaml"
    w = write_video(tmp_path / "cam2.mp4", n=10, fps=25)
    ok.write_text(f"cameras:\n  - {{name: a, source: '{v}'}}\n  - {{name: b, source: '{w}'}}\n")
    assert capture_run(["check", "--cameras", str(ok)]) == 0


# ----------------------------------------------------------------------------- forecast a short track


def test_forecast_of_a_too_short_track_says_how_long_it_must_be(tracked, tmp_path, capsys):
    import dataclasses

    from roomcap.forecast.cli import main as forecast
    from roomcap.track.trackfile import TrackFile

    tf = TrackFile.load(tracked / "track" / "tracks.npz")
    keys = ("frame_index", "t_ns", "xyz_m", "confidence", "std_m", "flags")
    short = dataclasses.replace(tf, **{k: getattr(tf, k)[:1] for k in keys})
    short.save(tmp_path / "short.npz")
    assert (
        forecast(["sample", "--tracks", str(tmp_path / "short.npz"), "--out", str(tmp_path / "f.npz")]) == 2
    )
    err = capsys.readouterr().err
    assert "is too short to forecast: it holds 1 frame (0.04 s at 25 Hz)" in err, err
    assert "looks at the last 50 frames (2.0 s" in err and "must be at least 2.0 s long (50 frames" in err
    assert not (tmp_path / "f.npz").exists()
    gone = dataclasses.replace(tf, **{k: getattr(tf, k)[:10].copy() for k in keys})
    gone.xyz_m[-1] = np.nan  # nobody at the last frame
    gone.save(tmp_path / "gone.npz")
    args = ["sample", "--tracks", str(tmp_path / "gone.npz"), "--obs-s", "0.4", "--out", str(tmp_path / "f")]
    assert forecast(args) == 2
    assert "is seen (both hips) in its last frame" in capsys.readouterr().err


# ----------------------------------------------------------------------------- calibration without a board


def test_calibration_recording_without_any_board_says_so_first(tmp_path, capsys):
    import cv2

    from roomcap.calibrate.boards import Board, save_board
    from roomcap.calibrate.cli import main as calibrate_run

    rng = np.random.default_rng(0)
    for cam in ("cam_a", "cam_b"):
        (tmp_path / "rec" / cam).mkdir(parents=True)
        for k in range(6):  # a room without a board: smooth noise
            img = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), np.uint8), (9, 9), 3)
            cv2.imwrite(str(tmp_path / "rec" / cam / f"frame_{k:05d}.png"), img)
    save_board(tmp_path / "board.toml", Board("charuco", (7, 5), 0.1, 0.075, "DICT_4X4_50"))
    rc = calibrate_run(
        [
            "calibrate",
            str(tmp_path / "rec"),
            "--board",
            str(tmp_path / "board.toml"),
            "--out",
            str(tmp_path / "r.toml"),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("calibrate-run: error: No board was seen at all in the 2 camera(s)"), (
        err
    )
    assert "no ArUco marker of any predefined dictionary" in err and "Traceback" not in err


# ----------------------------------------------------------------------------- sync of a Pose2Sim trial


def test_sync_reads_a_pose2sim_trials_detections_where_reprocess_wrote_them(session, tmp_path, capsys):
    from roomcap.core.fileio import load_toml
    from roomcap.pipeline.live import main as capture_run

    trial = tmp_path / "Trial"  # a Pose2Sim trial after `reprocess Trial`: <trial>/roomcap/keypoints
    (trial / "videos").mkdir(parents=True)
    shutil.copytree(session / "keypoints", trial / "roomcap" / "keypoints")
    assert capture_run(["sync", str(trial)]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert "cam00" in out and "reference" in out
    assert "cameras" in load_toml(trial / "session.toml")["sync"]  # where reprocess reads it (_sync_table)
    empty = tmp_path / "Empty"
    (empty / "videos").mkdir(parents=True)
    assert capture_run(["sync", str(empty)]) == 2
    assert "roomcap/keypoints, where reprocess writes a Pose2Sim trial's" in capsys.readouterr().err


# ----------------------------------------------------------------------------- partial sessions exit 1


def test_partial_session_exits_1(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ROOMCAP_SHARED", str(need_shared("models").parent))
    from test_pipeline_badinput import _session

    _session(tmp_path / "in" / "broken")
    (tmp_path / "in" / "broken" / "raw" / "cam01.avi").write_bytes(b"RIFF\x00\x00not really a video")
    rc = reprocess(
        [str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--stages", "keypoints", "--workers", "1"]
    )
    captured = capsys.readouterr()
    assert rc == 1, captured.err
    assert "0 sessions ok, 1 partial, 0 failed" in captured.out
    assert "PARTIAL in/broken: cameras ['cam01'] left out" in captured.err


# ----------------------------------------------------------------------------- exports


def test_export_of_an_unknown_person_makes_no_folder(tracked, tmp_path, capsys):
    from roomcap.outputs.cli import main as tracks

    out = tmp_path / "x" / "exports"
    assert tracks(["export", str(tracked), "--person", "99", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert (
        "--person: there is no track 99 in" in err and "(its tracks: [" in err and "Traceback" not in err
    ), err
    assert not (tmp_path / "x").exists()


def test_calibration_export_or_import_onto_its_own_input_is_refused(tracked, tmp_path, capsys):
    from roomcap.calibrate.cli import main as calibrate_run

    rig = tmp_path / "rig.toml"
    shutil.copy(tracked / "calib" / "rig.toml", rig)
    before = rig.read_bytes()
    for argv in (
        ["export", str(rig), "--format", "aniposelib", "--out", str(rig)],
        ["export", str(rig), "--format", "aniposelib", "--out", str(tmp_path / "." / "rig.toml")],
        ["import", str(rig), "--out", str(rig)],
    ):
        assert calibrate_run(argv) == 2
        err = capsys.readouterr().err
        assert "is the input file" in err and "nothing was written" in err, err
    assert rig.read_bytes() == before


# ----------------------------------------------------------------------------- --help


class _Parsed(BaseException):
    def __init__(self, parser):
        self.parser = parser


def _parsers(monkeypatch) -> list[argparse.ArgumentParser]:
    """Every command's parser and its subcommands' (captured when the command parses its arguments)."""
    from roomcap.calibrate.cli import main as calibrate_run
    from roomcap.forecast.cli import main as forecast
    from roomcap.keypoints.cli import main as keypoints
    from roomcap.outputs.cli import main as tracks
    from roomcap.pipeline.demo import main as demo
    from roomcap.pipeline.live import main as capture_run

    def grab(self, *a, **k):
        raise _Parsed(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", grab)
    monkeypatch.setattr(argparse.ArgumentParser, "parse_known_args", grab)
    found: list[argparse.ArgumentParser] = []

    def walk(p):
        found.append(p)
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sp in a.choices.values():
                    walk(sp)

    runs = [(reprocess, []), (tracks, []), (calibrate_run, []), (keypoints, []), (forecast, [])]
    runs += [(forecast, ["characteristic"]), (demo, [])]
    runs += [(capture_run, [c]) for c in ("record", "check", "sync", "repair")]
    for main, argv in runs:
        with pytest.raises(_Parsed) as got:
            main(argv)
        walk(got.value.parser)
    return found


def test_every_option_of_every_command_is_described_with_its_default(monkeypatch):
    parsers = _parsers(monkeypatch)
    assert len(parsers) >= 20
    missing = []
    for p in parsers:
        fmt = p._get_formatter()
        for a in p._actions:
            if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            name = "/".join(a.option_strings) or a.dest
            if not a.help or a.help == argparse.SUPPRESS:
                missing.append(f"{p.prog} {name}: no help")
            elif a.option_strings and a.nargs != 0 and not a.required:
                text = fmt._get_help_string(a) or ""
                if "default" not in text.lower():
                    missing.append(f"{p.prog} {name}: no default")
        p.format_help()  # renders (a stray % in a help text would fail here)
    assert missing == []
    assert "(default: local)" in " ".join(parsers[0].format_help().split())


# ----------------------------------------------------------------------------- README


def _block(text: str, heading: str, lang: str) -> str:
    part = text[text.index(heading) :]
    start = part.index(f"```{lang}\n") + len(lang) + 4
    return part[start : part.index("```", start)]


def test_readme_examples_are_valid_and_complete():
    """The README's cams.yaml and pipeline TOML parse with the project's own loaders; the TOML has every
    section of PipelineConfig; the README says where a Pose2Sim trial's outputs go and how long make test
    takes."""
    import dataclasses
    import tomllib

    import yaml

    from roomcap.capture.config import parse_config
    from roomcap.pipeline.config import PipelineConfig, tracker_name

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    cams = parse_config(yaml.safe_load(_block(text, "## A `cams.yaml`", "yaml")))
    assert cams.names == ("cam01", "cam02", "cam03")
    data = tomllib.loads(_block(text, "## A pipeline TOML", "toml"))
    assert set(data) == {f.name for f in dataclasses.fields(PipelineConfig)}  # every section
    cfg = PipelineConfig.from_dict(data)
    assert tracker_name(cfg.track) == "particle" and cfg.triangulate.match.theta_px == 40.0
    assert "`<trial>/roomcap/`" in text
    assert re.search(r"\d+ tests in about \d+ min", text), "README: make test's count and duration"
