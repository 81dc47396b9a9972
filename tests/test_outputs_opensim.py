"""``tracks opensim``: Pose2Sim's model scaled and inverse kinematics on our TRC (needs the opensim extra)."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from roomcap.outputs.cli import main as tracks_main
from roomcap.outputs.opensim_ik import (
    OpenSimError,
    find_setup,
    foot_index_note,
    neck_mismatch,
    run_opensim,
    setup_marker_names,
)
from tests.conftest import need_shared
from tests.test_outputs_export import _trackfile, _walkers

pytest.importorskip("opensim", reason="OpenSim is an optional extra: pip install 'roomcap[opensim]'")


@pytest.fixture(scope="module")
def setup_dir():
    return need_shared("data", "opensim-pose2sim")


def test_scaling_and_ik_on_a_walker(tmp_path, setup_dir):
    tf = _trackfile(_walkers(1, 12), std=0.01)
    (r,) = run_opensim(tf, tmp_path, "S", setup_dir, markerset="Body25b")
    assert r.mot.exists() and r.model.exists() and r.errors_csv.exists()
    lines = r.mot.read_text().splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.strip() == "endheader")
    cols = lines[head + 1].split("\t")
    assert "knee_angle_r" in cols and "hip_flexion_l" in cols
    assert len(lines) - head - 2 == 12
    assert r.n_frames == 12 and np.isfinite(r.rms_m).all() and (r.max_m >= r.rms_m).all()
    assert r.rms_median_m < 0.08  # a procedural walker, not a human: the model fits it to a few cm
    csv_head = r.errors_csv.read_text().splitlines()[0].split(",")
    assert csv_head[:3] == ["time_s", "rms_m", "max_m"] and "LKnee_m" in csv_head
    # BODY_25B names the head and feet, which a body19 track lacks: said, and left out
    assert set(r.missing) == {"Head", "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel"}
    assert any("names markers the track lacks" in n and "LHeel" in n for n in r.notes)
    # BODY_25B's Neck is the upper neck, body19's neck the mid-shoulder point: same name, not the same
    # point, so it takes no part (Pose2Sim's COCO-17 set has its Neck at shoulder height: it stays)
    assert "Neck" not in r.markers and "LShoulder" in r.markers
    assert any(n.startswith("Neck left out") and "mid-shoulder" in n for n in r.notes)
    assert neck_mismatch(tf, find_setup(setup_dir, "Coco17")) is None
    wb = dataclasses.replace(
        tf, joint_names=tuple("upper_neck" if n == "nose" else n for n in tf.joint_names)
    )
    assert neck_mismatch(wb, find_setup(setup_dir, "Body25b")) is None  # a detected upper neck matches
    bp = dataclasses.replace(
        tf, joint_names=tuple("left_foot_index" if n == "nose" else n for n in tf.joint_names)
    )
    note = foot_index_note(bp, find_setup(setup_dir, "Body25b"))
    assert note and "foot index" in note and "mm from Markers_BlazePose.xml" in note
    assert (
        foot_index_note(bp, find_setup(setup_dir, "Blazepose")) is None
        and foot_index_note(tf, find_setup(setup_dir, "Body25b")) is None
    )


def test_setup_naming_missing_markers_and_too_few(tmp_path, setup_dir):
    custom = tmp_path / "setup"
    shutil.copytree(setup_dir, custom)
    ik = custom / "IK_Setup_Pose2Sim_Coco17.xml"
    ik.write_text(ik.read_text().replace('<IKMarkerTask name="Nose">', '<IKMarkerTask name="LMidFoot">', 1))
    assert "LMidFoot" in setup_marker_names(find_setup(custom, "Coco17"))
    tf = _trackfile(_walkers(1, 6))
    (r,) = run_opensim(tf, tmp_path / "o", "S", custom, markerset="Coco17")
    assert r.missing == ["LMidFoot"] and "Neck" in r.markers
    with pytest.raises(OpenSimError, match=r"only 2 of the setup's markers.*at least 6"):
        run_opensim(tf, tmp_path / "o2", "S", custom, markerset="Coco17", markers=["LKnee", "RKnee"])
    with pytest.raises(OpenSimError, match=r"has no Markers_Nope.xml"):
        find_setup(custom, "Nope")


def test_cli_opensim_messages(tmp_path, capsys, setup_dir):
    tf = _trackfile(_walkers(1, 6))
    (tmp_path / "S" / "track").mkdir(parents=True)
    tf.save(tmp_path / "S" / "track" / "tracks.npz")
    rc = tracks_main(
        ["opensim", str(tmp_path / "S"), "--setup", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]
    )
    assert rc == 2 and "setup folder" in capsys.readouterr().err
    rc = tracks_main(
        ["opensim", str(tmp_path / "S"), "--setup", str(setup_dir), "--out", str(tmp_path / "o")]
    )
    out = capsys.readouterr().out
    assert rc == 0 and "names markers the track lacks" in out and "marker error RMS" in out
