"""Whole-body 3D: the triangulate and greedy track stages carry the joints the 2D layout adds (feet,
BODY_25B's upper neck and head top) with ``skeleton = "whole_body"``; body19 stays the default."""

from __future__ import annotations

import numpy as np
import pytest
from triangulate_helpers import FOOT_HEAD_OFFSETS, people  # noqa: F401

from roomcap.capture.session import SessionLayout
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import CANONICAL, SKELETONS, convert, load_skeleton_toml, whole_body
from roomcap.outputs.export import marker_table
from roomcap.synthetic.rigs import ring_rig
from roomcap.track.greedy_stage import track_session_greedy
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate.poses3d import Poses3D
from roomcap.triangulate.reconstruct import TriangulateConfig
from roomcap.triangulate.stage import triangulate_session


def _body25b_people(rng, n=2):
    X = people(rng, n, spread=0.8)  # (n,19,3) body19
    B = SKELETONS["body25b"]
    out = np.full((n, B.n_joints, 3), np.nan)
    for j, name in enumerate(B.joint_names):
        if name in CANONICAL.joint_names:
            out[:, j] = X[:, CANONICAL.index(name)]
        else:
            par, off = FOOT_HEAD_OFFSETS[name]
            out[:, j] = X[:, CANONICAL.index(par)] + off
    return out


def _session(tmp_path, X, skeleton="body25b", T=8):
    rig = ring_rig(4, radius_m=4.0)
    lay = SessionLayout(tmp_path)
    rig.save(lay.calib_dir / "rig.toml")
    J = X.shape[1]
    for c, cam in enumerate(rig):
        xy = rig.project(X.reshape(-1, 3))[c].reshape(X.shape[0], J, 2)
        xy = np.repeat(xy[None], T, 0)
        Detections(
            camera=cam.name,
            skeleton=skeleton,
            frame_index=np.arange(T),
            t_ns=np.arange(T) * 40_000_000,
            xy_px=xy,
            score=np.full(xy.shape[:-1], 0.9),
            boxes=np.full(xy.shape[:2] + (5,), np.nan),
        ).save(lay.detections(cam.name))
    return lay


def test_whole_body_skeleton_of_layouts():
    assert whole_body(["coco17"]) is CANONICAL
    wb = whole_body(["body25b"])
    assert wb.joint_names[:19] == CANONICAL.joint_names
    assert wb.joint_names[19:] == (
        "left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe", "right_heel",
        "upper_neck", "head_top",
    )  # fmt: skip
    assert wb.joint_names[wb.parents[wb.index("left_heel")]] == "left_ankle"
    assert wb.joint_names[wb.parents[wb.index("head_top")]] == "upper_neck"
    bp = whole_body(["blazepose33"])
    assert "left_foot_index" in bp.joint_names and "left_thumb" in bp.joint_names
    xy, sc = convert(np.zeros((3, 25, 2)), np.ones((3, 25)), "body25b", wb)
    assert xy.shape == (3, 27, 2) and np.isfinite(xy).all()  # pelvis and neck derived


def test_triangulate_and_track_carry_the_feet(tmp_path, rng):
    X = _body25b_people(rng)
    lay = _session(tmp_path, X)
    p = Poses3D.load(triangulate_session(lay.root, {"skeleton": "whole_body"}))
    wb = whole_body(["body25b"])
    assert p.joint_names == wb.joint_names
    B = SKELETONS["body25b"]
    for name in ("left_heel", "right_big_toe", "head_top", "left_knee"):
        got = p.xyz_m[0, :, wb.index(name)]
        want = X[:, B.index(name)]
        d = np.linalg.norm(got[:, None] - want[None], axis=-1).min(1)
        assert (d < 0.01).all(), name
    tf = TrackFile.load(track_session_greedy(lay.root))
    assert tf.joint_names == wb.joint_names and tf.parents.tolist() == list(wb.parents)
    mt = marker_table(tf, int(tf.track_id[0]))
    assert {"LBigToe", "LSmallToe", "LHeel", "RHeel", "Head", "Neck"} <= set(mt.names)
    # Pose2Sim's Neck is BODY_25B's detected upper neck, not body19's mid-shoulder point
    assert tf.joint_names[mt.joints[mt.names.index("Neck")]] == "upper_neck"
    # the default stays body19 (the file format forecasting reads)
    p19 = Poses3D.load(triangulate_session(lay.root))
    assert p19.joint_names == CANONICAL.joint_names


def test_unknown_skeleton_option():
    with pytest.raises(ValueError, match="'body19', 'whole_body' or a skeleton TOML file"):
        TriangulateConfig.from_dict({"skeleton": "feet"})


MOUSE_TOML = """
[skeleton]
id = "mouse"
joints = ["snout", "left_ear", "right_ear", "neck", "spine_mid", "tail_base"]
parents = ["neck", "snout", "snout", "", "neck", "spine_mid"]

[layouts.dlc_mouse]
joints = ["nose", "earL", "earR", "neck", "back", "tailbase"]
map = { snout = "nose", left_ear = "earL", right_ear = "earR", spine_mid = "back", tail_base = "tailbase" }
"""


def test_custom_skeleton_from_toml(tmp_path, rng):
    (tmp_path / "mouse.toml").write_text(MOUSE_TOML)
    # two animals on the floor, 2D detections in the lab's own layout
    base = np.array(
        [
            [0.12, 0, 0.05],
            [0.09, 0.02, 0.07],
            [0.09, -0.02, 0.07],
            [0.05, 0, 0.06],
            [0.0, 0, 0.05],
            [-0.06, 0, 0.04],
        ]
    )
    X = np.stack([base * 4 + [0.5, 0.3, 0], base * 4 @ np.diag([-1, -1, 1]) + [-0.6, -0.4, 0]])
    load_skeleton_toml(tmp_path / "mouse.toml")  # registers the 2D layout (to write its detections here)
    lay = _session(tmp_path / "S", X, skeleton="dlc_mouse")
    cfg = {"skeleton": str(tmp_path / "mouse.toml"), "min_joints_3d": 4}
    p = Poses3D.load(triangulate_session(lay.root, cfg))
    assert p.joint_names == ("snout", "left_ear", "right_ear", "neck", "spine_mid", "tail_base")
    assert p.parents.tolist() == [3, 0, 0, -1, 3, 4]
    got = p.xyz_m[0]
    d = np.linalg.norm(got[:, None] - X[None], axis=-1).mean(-1).min(1)
    assert (d < 0.005).all()
    tf = TrackFile.load(track_session_greedy(lay.root, {"min_joints": 4}))
    assert tf.n_tracks == 2 and tf.parents.tolist() == [3, 0, 0, -1, 3, 4]
    from roomcap.core.errors import FormatError

    (tmp_path / "bad.toml").write_text(MOUSE_TOML.replace('"neck", "spine_mid"]', '"neck", "hip"]'))
    with pytest.raises(FormatError, match=r"bad\.toml.*parent 'hip' of 'tail_base' is not a joint"):
        triangulate_session(lay.root, {"skeleton": str(tmp_path / "bad.toml")})
