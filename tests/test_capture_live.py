"""--live: every synchronised frame set passes through the stages in order; latency is reported."""

from __future__ import annotations

import os
import signal
import threading
import time

from roomcap.capture.config import parse_config
from roomcap.capture.live import LiveRunner
from roomcap.capture.recorder import Recorder
from roomcap.capture.sources import host_now_ns, read_code


def test_live_path_with_synthetic_sources_runs_every_stage(tmp_path):
    cfg = parse_config(
        {
            "cameras": [
                {
                    "name": f"c{i}",
                    "source": f"synthetic:?offset_ms={2 * i}",
                    "resolution": [160, 120],
                    "fps": 30,
                }
                for i in range(3)
            ]
        }
    )
    calls = []

    def fake_keypoints(step):  # stands in for keypoints.pipeline: reads the barcode of each view
        step.outputs["detections"] = {c: read_code(f.image) for c, f in step.frameset.frames.items() if f}
        calls.append("k")

    def fake_triangulate(step):  # a "3D pose" per set: all views agree on the frame number
        seqs = set(step.outputs["detections"].values())
        step.outputs["poses3d"] = seqs
        calls.append("t")

    def fake_track(step):
        calls.append("r")

    live = LiveRunner(
        cfg,
        tmp_path / "s",
        stages={"keypoints": fake_keypoints, "triangulate": fake_triangulate, "track": fake_track},
    )
    seen = []
    live.on_step = lambda step: seen.append(step.outputs["poses3d"])
    live.start()
    Recorder(cfg, tmp_path / "s", duration_s=1.5, frameset_sink=live.queue, handle_signals=False).run()
    live.stop()
    s = live.summary()
    assert s["processed"] >= 35  # 1.5 s at 30 fps = 45 sets (measured 45-47)
    assert calls[:3] == ["k", "t", "r"] and len(calls) == 3 * s["processed"]
    assert all(len(x) == 1 for x in seen[:-1])  # each set holds the same instant from every camera
    assert s["complete"] >= s["processed"] - 2
    assert 0 <= s["latency_ms_median"] < 200  # measured ~20 ms (max_wait + scheduling)
    assert s["errors"] == {}


def test_live_without_the_pipeline_stages_says_where_to_go(tmp_path, capsys):
    """capture.cli alone has no 3D stages (they sit above capture in the stage order): --live is refused with
    a message naming the entry that has them (pipeline.live)."""
    from roomcap.capture.cli import main

    (tmp_path / "cams.yaml").write_text("cameras:\n  - {name: a, source: 'synthetic:', fps: 10}\n")
    rc = main(["--cameras", str(tmp_path / "cams.yaml"), "--out", str(tmp_path / "s"), "--live", "--quiet"])
    assert rc == 2 and "pipeline.live" in capsys.readouterr().err


def test_cli_live_runs_the_real_keypoint_stage_on_synthetic_cameras(tmp_path, capsys):
    from conftest import need_shared

    from roomcap.pipeline.live import main

    need_shared("models")
    (tmp_path / "cams.yaml").write_text(
        "cameras:\n"
        "  - {name: a, source: 'synthetic:', resolution: [320, 240], fps: 10}\n"
        "  - {name: b, source: 'synthetic:', resolution: [320, 240], fps: 10}\n"
        "live: {stages: [keypoints]}\n"
    )
    rc = main(
        [
            "--cameras",
            str(tmp_path / "cams.yaml"),
            "--out",
            str(tmp_path / "s"),
            "--duration",
            "3",
            "--live",
            "--quiet",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0
    line = next(x for x in out.splitlines() if x.strip().startswith("live:"))
    n = int(line.split("live:")[1].split()[0])
    # the models load and warm on the live thread while the cameras already record (0.5-2.6 s here), the
    # sets before that are dropped: at least one set through the real model, whatever the machine's load
    assert n >= 1 and "keypoints" in line


SLOW_S = 0.4  # a deliberately slow stage: far slower than the cameras' 30 fps on any machine


def _slow_cfg(tmp_path):
    cams = "".join(
        f"  - {{name: c{i}, source: 'synthetic:?offset_ms={i}', resolution: [160, 120], fps: 30}}\n"
        for i in range(2)
    )
    (tmp_path / "cams.yaml").write_text("cameras:\n" + cams)
    return tmp_path / "cams.yaml"


def _slow_stages(seen):
    def slow(step):
        seen.append(
            (step.frameset.index, host_now_ns(), min(f.t_host_ns for f in step.frameset.frames.values()))
        )
        time.sleep(SLOW_S)

    return lambda cfg, layout: ({"slow": slow}, {})


def test_a_slow_stage_takes_the_newest_set_and_duration_exits_promptly(tmp_path, capsys):
    """capture-run --duration 3 --live with a stage 12x slower than the cameras: the live loop takes the
    newest set (the stale ones dropped and counted, never queued), and the command exits within 4.5 s of
    starting (before: every queued set was processed after the stop)."""
    from roomcap.capture.cli import make_main

    seen: list[int] = []
    main = make_main(build_live=_slow_stages(seen))
    t0 = time.monotonic()
    rc = main(
        [
            "--cameras",
            str(_slow_cfg(tmp_path)),
            "--out",
            str(tmp_path / "s"),
            "--duration",
            "3",
            "--live",
            "--quiet",
        ]
    )
    wall_s = time.monotonic() - t0
    out = capsys.readouterr().out
    assert rc == 0, out
    assert wall_s < 4.5, wall_s  # 3 s + the set in hand (0.4 s) + the join; measured 3.4 s
    line = next(x for x in out.splitlines() if x.strip().startswith("live:"))
    n, dropped = int(line.split()[1]), int(line.split("(")[1].split()[0])
    assert n == len(seen) and n <= 3 / SLOW_S + 1 and dropped >= 5 * n, line  # ~30 sets/s arrive, 2.5 done
    index = [i for i, _, _ in seen]
    assert all(b - a >= 5 for a, b in zip(index, index[1:], strict=False)), index  # the newest, not the next
    # nothing after the stop: every set was taken within the 3 s of frames (before: the queued ones after)
    t_first_frame = seen[0][2]
    assert max((t - t_first_frame) / 1e9 for _, t, _ in seen) < 3.0 + 0.3, seen
    # and each was the newest when taken: at most one set's processing (plus the sync's wait) old
    assert max((t - f) / 1e9 for _, t, f in seen) < SLOW_S + 0.3, seen


def test_ctrl_c_ends_the_live_loop_within_a_second(tmp_path):
    from roomcap.capture.config import load_config
    from roomcap.capture.recorder import Recorder

    seen: list[int] = []
    cfg = load_config(_slow_cfg(tmp_path))
    live = LiveRunner(cfg, tmp_path / "s", build_stages=_slow_stages(seen))
    rec = Recorder(cfg, tmp_path / "s", frameset_sink=live.queue)  # no duration: until Ctrl-C
    live.watch(rec.stop_event)
    sent = {}

    def ctrl_c():
        time.sleep(2.0)
        sent["ns"] = host_now_ns()
        os.kill(os.getpid(), signal.SIGINT)  # the recorder's handler stops it, as Ctrl-C does

    threading.Thread(target=ctrl_c, daemon=True).start()
    live.start()
    summary = rec.run()
    live.stop()
    assert summary["stop_reason"] == "signal SIGINT"
    assert live.ended_ns is not None and (live.ended_ns - sent["ns"]) / 1e9 < 1.0  # measured SLOW_S at most
    assert 0 < live.stats.processed <= 2.0 / SLOW_S + 1 and live.stats.skipped > live.stats.processed
    assert live.queue.maxsize <= 8 * len(cfg.cameras)  # bounded: a few frames per camera
