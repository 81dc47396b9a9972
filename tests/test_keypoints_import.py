"""Other tools' 2D into detections files: caliscope's xy_<tracker>.csv (MediaPipe Holistic point ids to
body and hands) and OpenPose JSON folders (``keypoints import``); the hand skeletons."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import need_shared

from roomcap.core.errors import FormatError
from roomcap.keypoints.cli import main as keypoints_main
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.importers import import_2d, read_caliscope_xy
from roomcap.keypoints.skeletons import (
    CANONICAL,
    HAND_BONES,
    HAND_LEFT,
    HAND_RIGHT,
    convert,
    finger_bones,
    get_skeleton,
    skeleton_from_names,
    whole_body,
)

HEADER = "sync_index,port,frame_index,frame_time,point_id,img_loc_x,img_loc_y,obj_loc_x,obj_loc_y\n"


def test_hand_joint_names_follow_coco_wholebody_in_mediapipe_order():
    assert HAND_LEFT[:6] == (
        "left_hand_root",
        "left_thumb1",
        "left_thumb2",
        "left_thumb3",
        "left_thumb4",
        "left_forefinger1",
    )
    assert HAND_RIGHT[9] == "right_middle_finger1" and HAND_RIGHT[20] == "right_pinky_finger4"
    assert HAND_LEFT[13] == "left_ring_finger1" and len(HAND_LEFT) == len(HAND_RIGHT) == 21
    sk = get_skeleton("body19_hands")
    assert sk.joint_names == CANONICAL.joint_names + HAND_LEFT + HAND_RIGHT
    par = {sk.joint_names[c]: sk.joint_names[p] for p, c in sk.limbs}
    assert par["left_hand_root"] == "left_wrist" and par["right_thumb1"] == "right_hand_root"
    assert par["left_pinky_finger4"] == "left_pinky_finger3" and par["right_forefinger1"] == "right_hand_root"
    assert len(HAND_BONES) == 40
    # the mirror swaps the hands
    assert sk.joint_names[sk.flip_index[sk.index("left_ring_finger2")]] == "right_ring_finger2"
    fb = finger_bones(sk.joint_names)
    assert sorted(fb) == sorted(
        f"{s}_{f}"
        for s in ("left", "right")
        for f in ("thumb", "forefinger", "middle_finger", "ring_finger", "pinky_finger")
    )
    assert fb["right_thumb"][0] == (sk.index("right_hand_root"), sk.index("right_thumb1"))


def test_whole_body_with_hands_and_older_layouts_unchanged():
    wb = whole_body(["blazepose33_hands"])
    assert wb.joint_names[:19] == CANONICAL.joint_names and wb.joint_names[-42:] == HAND_LEFT + HAND_RIGHT
    # layouts without hands keep their whole-body skeleton (older 3D files read as before)
    old = whole_body(["body25b"])
    assert not set(HAND_LEFT) & set(old.joint_names)
    assert skeleton_from_names(old.joint_names).joint_names == old.joint_names
    assert skeleton_from_names(CANONICAL.joint_names) is CANONICAL
    assert skeleton_from_names(wb.joint_names).id == "whole_body"
    # MediaPipe pose landmarks map to the body joints by name (pelvis, neck derived)
    s = get_skeleton("blazepose33_hands")
    xy = np.arange(s.n_joints * 2, dtype=float).reshape(s.n_joints, 2)
    out, _ = convert(xy, np.ones(s.n_joints), s, wb)
    assert (out[wb.index("left_wrist")] == xy[15]).all() and (out[wb.index("right_ankle")] == xy[28]).all()
    assert (out[wb.index("right_hand_root")] == xy[33 + 21]).all()
    np.testing.assert_allclose(out[wb.index("pelvis")], 0.5 * (xy[23] + xy[24]))


def _csv(tmp_path, rows, header=HEADER):
    p = tmp_path / "xy_HOLISTIC.csv"
    p.write_text(header + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    return p


def test_caliscope_csv_to_detections(tmp_path):
    rows = [
        # sync, port, frame, time, point, x, y, obj_x, obj_y
        (5, 0, 10, 100.0, 0, 11, 12, "", ""),  # nose
        (5, 0, 10, 100.0, 15, 21, 22, "", ""),  # left wrist (MediaPipe pose 15)
        (5, 0, 10, 100.0, 100, 31, 32, "", ""),  # right hand wrist landmark
        (5, 0, 10, 100.0, 208, 41, 42, "", ""),  # left hand index tip
        (5, 0, 10, 100.0, 504, 51, 52, "", ""),  # a face point: not kept
        (7, 0, 12, 100.1, 0, 13, 14, "", ""),
        (5, 1, 3, 100.02, 120, 61, 62, "", ""),  # right pinky tip, port 1
    ]
    dets = read_caliscope_xy(_csv(tmp_path, rows))
    assert sorted(dets) == ["cam_0", "cam_1"]
    d = dets["cam_0"]
    s = get_skeleton(d.skeleton)
    assert d.skeleton == "blazepose33_hands"
    assert d.frame_index.tolist() == [5, 7]  # the synchronised frame numbers kept
    assert d.extra["source_frame_index"].tolist() == [10, 12]
    assert d.t_ns.tolist() == [0, 100_000_000]
    assert d.xy_px[0, 0, s.index("nose")].tolist() == [11, 12]
    assert d.xy_px[0, 0, s.index("left_wrist")].tolist() == [21, 22]
    assert d.xy_px[0, 0, s.index("right_hand_root")].tolist() == [31, 32]
    assert d.xy_px[0, 0, s.index("left_forefinger4")].tolist() == [41, 42]
    assert np.isfinite(d.xy_px[0, 0, :, 0]).sum() == 4 and d.score[0, 0].sum() == 4
    assert np.isnan(d.xy_px[1, 0, s.index("left_wrist")]).all() and d.score[1, 0, s.index("left_wrist")] == 0
    assert dets["cam_1"].xy_px[0, 0, s.index("right_pinky_finger4")].tolist() == [61, 62]
    assert dets["cam_1"].t_ns.tolist() == [20_000_000]
    # written and read back through the CLI
    out = tmp_path / "sess" / "keypoints"
    assert keypoints_main(["import", str(tmp_path / "xy_HOLISTIC.csv"), "--out", str(out)]) == 0
    back = Detections.load(out / "cam_0.npz")
    np.testing.assert_array_equal(back.xy_px, d.xy_px)
    assert back.frame_index.tolist() == [5, 7]


def test_caliscope_bad_input_is_named(tmp_path, capsys):
    p = _csv(tmp_path, [(0, 0, 0, 1.0, 0, 1, 2, "", "", 9)], HEADER.strip() + ",confidence\n")
    with pytest.raises(FormatError, match=r"unknown columns \['confidence'\]"):
        read_caliscope_xy(p)
    p = _csv(tmp_path, [(0, 0, 0, 1.0, 0, 1, 2, "", ""), (0, 0, 0, 1.0, 350, 1, 2, "", "")])
    with pytest.raises(FormatError, match=r"point ids \[350\]"):
        read_caliscope_xy(p)
    assert keypoints_main(["import", str(p), "--out", str(tmp_path / "k")]) == 2
    assert "350" in capsys.readouterr().err
    p = _csv(tmp_path, [(0, 0, 1, 0, 1)], "sync_index,port,frame_index,point_id,img_loc_x\n")
    with pytest.raises(FormatError, match=r"columns \['img_loc_y'\] are missing"):
        read_caliscope_xy(p)
    assert keypoints_main(["import", str(tmp_path / "nothing.csv"), "--out", str(tmp_path / "k")]) == 2


def test_openpose_json_folders_import_with_frame_numbers(tmp_path):
    J = 25
    for cam in ("cam1", "cam2"):
        f = tmp_path / "pose" / f"{cam}_json"
        f.mkdir(parents=True)
        for fr in (3, 4, 6):
            kp = np.zeros((J, 3))
            kp[:, 0], kp[:, 1], kp[:, 2] = np.arange(J) + fr, 2 * np.arange(J), 0.8
            kp[1] = [50, 50, 0.8]  # BODY_25B's left eye: not the mid-shoulder point
            (f / f"{cam}.{fr:06d}.json").write_text(
                json.dumps({"people": [{"pose_keypoints_2d": kp.ravel().tolist()}]})
            )
    paths = import_2d(tmp_path / "pose", tmp_path / "s" / "keypoints", skeleton="body25b")
    assert sorted(paths) == ["cam1", "cam2"]
    d = Detections.load(paths["cam2"])
    assert d.skeleton == "body25b" and d.frame_index.tolist() == [3, 4, 5, 6]
    assert d.xy_px[3, 0, 0, 0] == 6 and np.isnan(d.xy_px[2]).all()


def test_caliscope_holistic_recording_imports(tmp_path):
    csv_path = need_shared(
        "data",
        "caliscope",
        "4_cam_recording_holistic_2d3d",
        "recordings",
        "recording_1",
        "HOLISTIC",
        "xy_HOLISTIC.csv",
    )
    dets = read_caliscope_xy(csv_path)
    assert sorted(dets) == ["cam_0", "cam_1", "cam_2", "cam_3"]
    s = get_skeleton("blazepose33_hands")
    for d in dets.values():
        assert d.frame_index.min() == 0 and d.frame_index.max() == 266
        hands = np.isfinite(d.xy_px[:, 0, 33:, 0]).any(-1)
        assert 100 <= hands.sum() <= d.n_frames  # hands in a good part of the frames
        # the right hand's landmarks sit at the body's right side more often than at its left (ids 100+)
        xy = d.xy_px[:, 0]
        rh = xy[:, s.index("right_hand_root")]
        near = np.linalg.norm(rh - xy[:, s.index("right_wrist")], axis=-1)
        assert np.nanmedian(near) < 60  # pixels, 1280x720 images


def test_openpose_json_with_hands(tmp_path):
    f = tmp_path / "c0_json"
    f.mkdir()
    kp = np.zeros((25, 3))
    kp[:, 0], kp[:, 1], kp[:, 2] = np.arange(25), np.arange(25), 0.9
    kp[1] = [50, 50, 0.9]
    hl = np.zeros((21, 3))
    hl[:, 0], hl[:, 1], hl[:, 2] = 100 + np.arange(21), 5, 0.7
    person = {"pose_keypoints_2d": kp.ravel().tolist(), "hand_left_keypoints_2d": hl.ravel().tolist(),
              "hand_right_keypoints_2d": []}  # fmt: skip
    for fr in (0, 1):
        (f / f"c0_{fr:012d}_keypoints.json").write_text(json.dumps({"people": [person]}))
    paths = import_2d(f, tmp_path / "k", skeleton="body25b")
    d = Detections.load(paths["c0"])
    s = get_skeleton(d.skeleton)
    assert d.skeleton == "body25b_hands" and s.n_joints == 25 + 42
    assert d.xy_px[1, 0, s.index("left_thumb2")].tolist() == [102, 5]
    assert np.isnan(d.xy_px[:, 0, s.index("right_hand_root")]).all()
    # the reader's default (the other stages' callers) leaves hands out
    from roomcap.keypoints.openpose_json import read_openpose_folder

    assert read_openpose_folder(f, skeleton="body25b").skeleton == "body25b"
    bad = dict(person, hand_right_keypoints_2d=[1.0, 2.0])
    (f / "c0_000000000002_keypoints.json").write_text(json.dumps({"people": [bad]}))
    with pytest.raises(FormatError, match="hand_right_keypoints_2d"):
        import_2d(f, tmp_path / "k2")
