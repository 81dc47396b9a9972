"""reprocess on real data: a Pose2Sim trial with OpenPose JSON and a calibration shared by the session."""

from __future__ import annotations

import json

import pytest
from conftest import need_shared

from roomcap.pipeline.cli import main as reprocess


def test_pose2sim_openpose_trial_end_to_end(tmp_path):
    trial = need_shared(
        "data", "pose2sim", "session-2024", "S00_P01_MultiParticipants", "S00_P01_T02_Participants1-2"
    )
    out = tmp_path / "out"
    assert reprocess([str(trial), "--out", str(out), "--workers", "1"]) == 0
    (s,) = json.loads((out / "reprocess_summary.json").read_text())
    # the calibration lives in ../../S00_Calibration and names cameras cam_01.., the JSON folders cam01_json..
    assert s["ran"] == ["calibration", "keypoints", "triangulate", "track", "forecast", "report"]
    assert s["cameras"] == 4 and s["frames"] == 100
    assert 2 <= s["people"] <= 3  # two participants (measured 3: a brief ghost); not 0 = the rig matched
    assert (out / trial.name / "report" / "report.html").stat().st_size > 10_000
    assert reprocess([str(trial), "--out", str(out), "--workers", "1"]) == 0
    (again,) = json.loads((out / "reprocess_summary.json").read_text())
    assert again["ran"] == []


@pytest.mark.slow
def test_real_videos_through_keypoints_few_frames(tmp_path):
    """The video path: a Pose2Sim demo trial (4 portrait 1080x1920 videos, Qualisys calibration), 5 frames
    (the greedy tracker keeps no track from 3)."""
    trial = need_shared("data", "pose2sim", "demo-wheel-0.10.49", "Demo_SinglePerson")
    out = tmp_path / "out"
    args = [str(trial), "--out", str(out), "--workers", "1", "--max-frames", "5"]
    args += ["--stages", "keypoints,triangulate,track"]
    assert reprocess(args) == 0
    (s,) = json.loads((out / "reprocess_summary.json").read_text())
    assert s["ran"] == ["calibration", "keypoints", "triangulate", "track"]
    assert s["cameras"] == 4 and s["frames"] == 5 and s["tracks"] >= 1
    assert "1088x1920" in s["message"]  # the codec-padding warning of keypoints reaches the summary
    assert reprocess(args) == 0
    assert json.loads((out / "reprocess_summary.json").read_text())[0]["ran"] == []
