"""capture-run end to end: a minimal cams.yaml, clear errors for bad input, sync."""

from __future__ import annotations

import numpy as np
from conftest import need_shared
from test_capture_sources import write_video

from roomcap.capture.cli import main
from roomcap.capture.sources import read_frames_csv
from roomcap.core.fileio import load_toml


def test_minimal_cams_yaml_records_a_session(tmp_path, capsys):
    v1 = write_video(tmp_path / "cam01.mp4", n=15, fps=30)
    v2 = write_video(tmp_path / "cam02.mp4", n=15, fps=30)
    (tmp_path / "cams.yaml").write_text(
        f"cameras:\n  - name: cam01\n    source: {v1}\n  - name: cam02\n    source: {v2}\n"
    )
    out = tmp_path / "session"
    assert (
        main(["--cameras", str(tmp_path / "cams.yaml"), "--out", str(out), "--duration", "5", "--quiet"]) == 0
    )
    meta = load_toml(out / "session.toml")
    assert meta["status"] == "complete" and meta["stop_reason"] == "all sources ended"  # files end before 5 s
    assert "cam01" in meta["cams_yaml"] and meta["config"]["cameras"][1]["name"] == "cam02"
    for cam in ("cam01", "cam02"):
        tab = read_frames_csv(out / "raw" / f"{cam}.frames.csv")
        assert len(tab) == 15 and np.all(np.diff(tab[:, 1]) > 0)
    assert "cam01: 15 frames" in capsys.readouterr().out


def test_bad_input_is_a_clear_error_without_a_session(tmp_path, capsys):
    notvideo = tmp_path / "x.mp4"
    notvideo.write_bytes(b"\x00garbage" * 100)
    v25 = write_video(tmp_path / "v.mp4", n=3, fps=25)
    cases = {
        "dup": "cameras:\n  - {name: a, source: 'synthetic:'}\n  - {name: a, source: 'synthetic:'}\n",
        "notvideo": f"cameras:\n  - {{name: a, source: '{notvideo}'}}\n",
        "usb": "cameras:\n  - {name: a, source: 'usb:57'}\n",
        "rtsp": "cameras:\n  - {name: a, source: 'rtsp://u:pw123@127.0.0.1:9/x'}\n",
        "fps": f"cameras:\n  - {{name: a, source: '{v25}', fps: 90}}\n",
    }
    for name, text in cases.items():
        (tmp_path / f"{name}.yaml").write_text(text)
        out = tmp_path / f"out_{name}"
        rc = main(
            ["--cameras", str(tmp_path / f"{name}.yaml"), "--out", str(out), "--duration", "1", "--quiet"]
        )
        err = capsys.readouterr().err
        assert rc == 2 and "error:" in err and "Traceback" not in err, (name, err)
        assert "pw123" not in err
        assert not out.exists(), name  # never a half-written session
    assert main(["check", "--cameras", str(tmp_path / "dup.yaml")]) == 2


def test_sync_command_on_openpose_folders(tmp_path, capsys):
    root = need_shared(
        "data", "pose2sim", "session-2024", "S00_P00_SingleParticipant", "S00_P00_T01_BalancingTrial", "pose"
    )
    args = ["sync", str(tmp_path), "--fps", "60", "--max-lag-s", "0.5", "--openpose"]
    args += [f"{c}={root / (c + '_json')}" for c in ("cam01", "cam02", "cam03")]
    assert main(args) == 0
    meta = load_toml(tmp_path / "session.toml")
    assert set(meta["sync"]["cameras"]) == {"cam01", "cam02", "cam03"}
    assert "offset" in capsys.readouterr().out


def test_check_refuses_exactly_the_sources_recording_refuses(tmp_path, capsys):
    """`capture-run check` and recording parse a source's options with one parser (config.source_options):
    what recording refuses, check refuses (exit 2, one line naming the option), and the other way round."""
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    sources = {
        "seed": ("synthetic:?seed=2", "seed"),
        "frames_text": ("synthetic:?frames=abc", "frames"),
        "frames_neg": ("synthetic:?frames=-1", "frames"),
        "twice": ("synthetic:?frames=2&frames=3", "twice"),
        "not_pairs": ("synthetic:?frames", "key=value"),
        "oak_socket": ("oak:x?socket=CAM_Z", "socket"),
        "missing_file": (str(tmp_path / "nope.mp4"), "does not exist"),
        "empty_file": (str(empty), "empty"),
        "ok": ("synthetic:?frames=3&offset_ms=1.5&drop_every=0", None),
    }
    for name, (src, needle) in sources.items():
        y = tmp_path / f"{name}.yaml"
        y.write_text(f"cameras:\n  - {{name: a, source: '{src}', resolution: [64, 48], fps: 30}}\n")
        rc_check = main(["check", "--cameras", str(y)])
        err_check = capsys.readouterr().err
        want = 0 if needle is None else 2
        assert rc_check == want and "Traceback" not in err_check, (name, err_check)
        if needle is not None:
            assert needle in err_check and len(err_check.strip().splitlines()) == 1, (name, err_check)
        if name.startswith("oak") or name == "ok":
            continue  # no OAK here; "ok" is recorded below
        rc_rec = main(["--cameras", str(y), "--out", str(tmp_path / f"s_{name}"), "--quiet"])
        err_rec = capsys.readouterr().err
        assert rc_rec == 2 and needle in err_rec, (name, err_rec)
    y = tmp_path / "ok.yaml"
    assert main(["--cameras", str(y), "--out", str(tmp_path / "s_ok"), "--duration", "5", "--quiet"]) == 0
    assert len(read_frames_csv(tmp_path / "s_ok" / "raw" / "a.frames.csv")) == 3
