"""Session discovery over folders of recordings."""

from __future__ import annotations

import pytest

from roomcap.core.errors import FormatError
from roomcap.pipeline.config import PipelineConfig
from roomcap.pipeline.discover import discover


def test_discovers_both_layouts_and_reports_missing_calibration(tmp_path):
    # this project's layout
    (tmp_path / "a" / "S1" / "keypoints").mkdir(parents=True)
    (tmp_path / "a" / "S1" / "keypoints" / "cam1.npz").write_bytes(b"x")
    (tmp_path / "a" / "S1" / "calib").mkdir()
    (tmp_path / "a" / "S1" / "calib" / "rig.toml").write_text("")
    # a Pose2Sim batch: two trials sharing the parent's calibration
    for trial in ("Trial_1", "Trial_2"):
        (tmp_path / "a" / "Batch" / trial / "videos").mkdir(parents=True)
        for cam in ("cam02", "cam01"):
            (tmp_path / "a" / "Batch" / trial / "videos" / f"{cam}.mp4").write_bytes(b"")
    (tmp_path / "a" / "Batch" / "calibration").mkdir()
    (tmp_path / "a" / "Batch" / "calibration" / "Calib.qca.txt").write_text("")
    # a trial without calibration anywhere
    (tmp_path / "a" / "Lost" / "videos").mkdir(parents=True)
    (tmp_path / "a" / "Lost" / "videos" / "cam01.avi").write_bytes(b"")
    found = {s.name: s for s in discover([tmp_path / "a"])}
    assert sorted(found) == ["a/Batch/Trial_1", "a/Batch/Trial_2", "a/Lost", "a/S1"]
    assert (
        found["a/S1"].layout == "roomcap" and found["a/S1"].cameras == ["cam1"] and not found["a/S1"].problem
    )
    t1 = found["a/Batch/Trial_1"]
    assert t1.layout == "pose2sim" and t1.cameras == ["cam01", "cam02"]
    assert t1.calibration.name == "Calib.qca.txt"
    assert "no calibration" in found["a/Lost"].problem


def test_missing_path_is_a_failed_session(tmp_path):
    (s,) = discover([tmp_path / "nope"])
    assert "does not exist" in s.problem


def test_config_rejects_unknown_keys_and_stages():
    with pytest.raises(FormatError, match="valid keys"):
        PipelineConfig.from_dict({"track": {"trackr": "greedy"}})
    with pytest.raises(FormatError, match="unknown stages"):
        PipelineConfig.from_dict({"stages": ["keypoints", "magic"]})
    cfg = PipelineConfig.from_dict({"stages": ["track", "triangulate"]})
    assert cfg.stages == ("triangulate", "track")


def test_keypoints_skeleton_option_reaches_the_2d_stage_without_rerunning_old_sessions():
    """[keypoints] skeleton = "model" keeps the model's own layout (BlazePose's feet for whole-body 3D);
    the default is left out of the stage's recorded settings, so sessions made before it stay current."""
    from roomcap.pipeline.config import KeypointsConfig

    default = PipelineConfig.from_dict({"keypoints": {"model_set": "default"}})
    assert default.keypoints.provenance() == {"model_set": "default", "max_frames": None}
    feet = PipelineConfig.from_dict(
        {"keypoints": {"model_set": "blazepose_heavy", "skeleton": "model"},
         "triangulate": {"options": {"skeleton": "whole_body"}}}
    )  # fmt: skip
    assert feet.keypoints == KeypointsConfig(model_set="blazepose_heavy", skeleton="model")
    assert feet.keypoints.provenance()["skeleton"] == "model"


def test_keypoint_presets_resolve_and_are_recorded():
    """The default preset is "balanced" (tracked crops); a named preset's settings are what the stage records,
    so changing a preset re-runs keypoints; an unknown preset fails when the config loads."""
    from roomcap.keypoints.presets import preset_config

    kp = PipelineConfig().keypoints
    assert kp.preset_name == "balanced" and kp.settings["detect_every"] > 1
    assert kp.detector.detect_every == kp.settings["detect_every"]
    assert kp.detector == preset_config("balanced")  # the typed config, built once from the preset
    cfg = PipelineConfig.from_dict({"keypoints": {"preset": "feet"}})
    prov = cfg.keypoints.provenance()
    assert prov["preset"] == "feet" and prov["settings"]["skeleton"] == "model"
    assert preset_config("feet").skeleton == "model" and preset_config("legacy").detect_every == 1
    with pytest.raises(FormatError, match="not a preset.*balanced"):
        PipelineConfig.from_dict({"keypoints": {"preset": "quick"}})


def test_stage_options_are_checked_when_the_config_loads(tmp_path, capsys):
    """A typo in a stage's options is found before any session runs, not when it is reached."""
    with pytest.raises(FormatError, match=r"triangulate.options.*thetta_px.*valid keys"):
        PipelineConfig.from_dict({"triangulate": {"options": {"match": {"thetta_px": 3}}}})
    with pytest.raises(FormatError, match=r"track.options.*'tau'"):
        PipelineConfig.from_dict({"track": {"tracker": "greedy", "options": {"tau": 0.2}}})
    with pytest.raises(FormatError, match=r"track.options.*n_particle"):
        PipelineConfig.from_dict({"track": {"tracker": "particle", "options": {"n_particle": 3}}})
    from roomcap.pipeline.cli import main

    (tmp_path / "p.toml").write_text('[track]\ntracker = "greedy"\n[track.options]\nsigmaa = 2\n')
    assert main([str(tmp_path), "--config", str(tmp_path / "p.toml")]) == 2
    assert "sigmaa" in capsys.readouterr().err


def test_stage_options_are_parsed_once_not_on_every_replace(monkeypatch):
    """The options are parsed when the config is made, into the stages' own typed configs; replace() of
    other fields does not parse them again, and another tracker is checked against its own keys."""
    import roomcap.pipeline.config as pc
    from roomcap.track.greedy_stage import GreedyTrackConfig

    cfg = PipelineConfig.from_dict(
        {
            "triangulate": {"options": {"match": {"theta_px": 30}}},
            "track": {"tracker": "greedy", "options": {"sigma_s": 0.1}},
        }
    )
    assert isinstance(cfg.track, GreedyTrackConfig) and cfg.track.greedy.sigma_s == 0.1
    assert cfg.triangulate.match.theta_px == 30.0
    calls = []
    monkeypatch.setattr(pc.TriangulateOptions, "from_dict", lambda d: calls.append(d))
    monkeypatch.setattr(pc.GreedyTrackConfig, "from_dict", lambda d: calls.append(d))
    assert cfg.replace(stages=("triangulate", "track")).stages == ("triangulate", "track")
    assert calls == []
    monkeypatch.undo()
    with pytest.raises(FormatError, match=r"track.options.*sigma_s"):
        PipelineConfig.from_dict({"track": {"tracker": "particle", "options": {"sigma_s": 0.1}}})


def test_reprocess_on_a_path_that_does_not_exist_exits_2_with_one_line(tmp_path, capsys):
    """A typo is bad input (exit 2, one line naming the path), not a failed session (exit 1), and nothing
    runs: the folder that does exist is not processed either."""
    from roomcap.pipeline.cli import main

    (tmp_path / "real").mkdir()
    out = tmp_path / "out"
    assert main([str(tmp_path / "real"), str(tmp_path / "nope"), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "nope does not exist" in err[0] and "real" not in err[0]
    assert "Traceback" not in captured.err and not out.exists()
