"""Bad recordings: each problem is reported for its session, with what to do, and nothing computed is lost."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import need_shared

from roomcap.pipeline.config import PipelineConfig
from roomcap.pipeline.discover import discover
from roomcap.pipeline.executors import run_sessions
from roomcap.pipeline.session_inputs import probe_videos

SIZE = (64, 48)


def _video(path, n_frames: int, fps: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, SIZE)
    assert w.isOpened()
    for i in range(n_frames):
        w.write(np.full((SIZE[1], SIZE[0], 3), 20 * i % 255, np.uint8))
    w.release()


def _session(root, frames=(5, 5), rates=(25.0, 25.0)):
    from roomcap.synthetic.rigs import ring_rig

    ring_rig(2, size_wh=SIZE).save(root / "calib" / "rig.toml")
    for i, (n, fps) in enumerate(zip(frames, rates, strict=True)):
        _video(root / "raw" / f"cam{i:02d}.avi", n, fps)
    return root


@pytest.fixture(autouse=True)
def _models(monkeypatch):
    monkeypatch.setenv("ROOMCAP_SHARED", str(need_shared("models").parent))


@pytest.mark.slow
def test_mixed_frame_rates_fail_with_the_rates(tmp_path):
    _session(tmp_path / "in" / "mixed", rates=(25.0, 30.0))
    _session(tmp_path / "in" / "fine")
    cfg = PipelineConfig(stages=("keypoints",))
    res = {r.name: r for r in run_sessions(discover([tmp_path / "in"]), tmp_path / "out", cfg, workers=1)}
    bad = res["in/mixed"]
    assert bad.status == "failed" and bad.failed_stage == "keypoints"
    assert "different frame rates" in bad.message and "cam01 30 fps" in bad.message, bad.message
    assert "(calibration)" in bad.message  # finished stages are kept and said so
    assert (tmp_path / "out" / "in" / "mixed" / "calib" / "rig.toml").exists()
    assert res["in/fine"].status == "ok", res["in/fine"].message


def test_unreadable_video_and_different_lengths(tmp_path):
    _session(tmp_path / "in" / "broken")
    (tmp_path / "in" / "broken" / "raw" / "cam01.avi").write_bytes(b"RIFF\x00\x00not really a video")
    _session(tmp_path / "in" / "ragged", frames=(5, 3))
    cfg = PipelineConfig(stages=("keypoints",))
    res = {r.name: r for r in run_sessions(discover([tmp_path / "in"]), tmp_path / "out", cfg, workers=1)}
    # one unreadable camera: the others are processed, and the summary says which was left out
    assert res["in/broken"].status == "partial", res["in/broken"].message
    assert "cam01" in res["in/broken"].message and "cannot be read" in res["in/broken"].message
    assert list(res["in/broken"].skipped_cameras) == ["cam01"]
    assert (tmp_path / "out" / "in" / "broken" / "keypoints" / "cam00.npz").exists()
    assert not (tmp_path / "out" / "in" / "broken" / "keypoints" / "cam01.npz").exists()
    ragged = res["in/ragged"]
    assert ragged.status == "ok", ragged.message
    assert (
        "differ in length" in ragged.message and "cam00 5" in ragged.message and "cam01 3" in ragged.message
    )
    assert ragged.frames == 5


def test_probe_reports_counts_and_rates(tmp_path):
    _video(tmp_path / "a.avi", 4, 25.0)
    _video(tmp_path / "b.avi", 4, 25.0)
    info, warnings = probe_videos({"a": tmp_path / "a.avi", "b": tmp_path / "b.avi"})
    assert info == {"a": (4, 25.0), "b": (4, 25.0)} and warnings == []
