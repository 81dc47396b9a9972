"""Record -> calibrate -> process on real videos: the Pose2Sim multi-person demo.

``capture-run`` replays the demo's 4 videos as file cameras, ``calibrate-run import`` reads its Qualisys
calibration into the session, ``reprocess`` runs every stage. Checks: each raw/<cam>.mp4 decodes in
PyAV (an ordinary FFmpeg decoder, not the recorder's OpenCV) with every recorded frame, and the track
file holds both participants. Keypoints on the CPU take about 11 s per frame set here (4 portrait
1088x1920 views, 2 shared cores), so the test processes the first ``ROOMCAP_DEMO_FRAMES`` (default
20) frames; ``ROOMCAP_DEMO_FRAMES=0`` runs all 100 (measured 19 min; BENCHMARKS.md figures).
"""

from __future__ import annotations

import json
import os
import time

import av
import numpy as np
import pytest
from conftest import need_shared

from roomcap.calibrate.cli import main as calibrate_run
from roomcap.capture.cli import main as capture_run
from roomcap.capture.sources import read_frames_csv
from roomcap.core.fileio import load_toml
from roomcap.track.trackfile import TrackFile

CAMS = ("cam01", "cam02", "cam03", "cam04")


@pytest.mark.slow
def test_capture_run_calibrate_import_reprocess_on_the_pose2sim_demo(tmp_path, monkeypatch):
    demo = need_shared("data", "pose2sim", "demo-wheel-0.10.49", "Demo_MultiPerson")
    monkeypatch.setenv("ROOMCAP_SHARED", str(need_shared("models").parent))
    from roomcap.pipeline.cli import main as reprocess

    yaml = tmp_path / "cams.yaml"
    yaml.write_text(
        "cameras:\n"
        + "".join(
            f"  - {{name: {c}, source: '{demo / 'videos' / (c + '.mp4')}', realtime: false}}\n" for c in CAMS
        )
    )
    s = tmp_path / "S"
    t0 = time.perf_counter()
    assert capture_run(["--cameras", str(yaml), "--out", str(s), "--quiet"]) == 0
    t_record = time.perf_counter() - t0
    meta = load_toml(s / "session.toml")
    assert meta["status"] == "complete"
    for c in CAMS:
        rows = len(read_frames_csv(s / "raw" / f"{c}.frames.csv"))
        with av.open(str(s / "raw" / f"{c}.mp4")) as f:
            decoded = sum(1 for _ in f.decode(video=0))
        assert rows == decoded == 100 == meta["cameras"][c]["frames_written"]  # the demo's 100 frames
        assert not (s / "raw" / c).exists()
    assert (
        calibrate_run(
            ["import", str(demo / "calibration" / "Calib.qca.txt"), "--out", str(s / "calib" / "rig.toml")]
        )
        == 0
    )
    n = int(os.environ.get("ROOMCAP_DEMO_FRAMES", "20")) or 100
    t1 = time.perf_counter()
    args = [str(s), "--workers", "1", "--out", str(tmp_path / "out")]
    assert reprocess(args + (["--max-frames", str(n)] if n < 100 else [])) == 0
    t_process = time.perf_counter() - t1
    (summary,) = json.loads((tmp_path / "out" / "reprocess_summary.json").read_text())
    assert summary["status"] == "ok" and summary["cameras"] == 4 and summary["frames"] == n
    tf = TrackFile.load(tmp_path / "out" / "S" / "track" / "tracks.npz")
    present = np.isfinite(tf.xyz_m[..., 0]).any(-1)  # (T, N)
    long_tracks = int((present.sum(0) >= n // 2).sum())  # tracks seen for at least half the frames
    assert summary["people"] >= 2 and long_tracks >= 2, (summary, present.sum(0))
    print(
        f"DEMO recorded frames/camera=100 processed={n} tracks={tf.n_tracks} long_tracks={long_tracks} "
        f"people={summary['people']} "
        f"record_s={t_record:.1f} reprocess_s={t_process:.1f} stages={summary['stage_s']}"
    )
