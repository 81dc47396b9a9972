"""Hands in 3D: the 42 hand joints of a ``*_hands`` 2D layout triangulated with the body (``whole_body``),
a hand joint seen by one view stays 2D-only; hands put on the body's side per view; the caliscope holistic
recording against caliscope's own 3D."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import need_shared
from triangulate_helpers import people

from roomcap.calibrate.formats import import_rig
from roomcap.capture.session import SessionLayout
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.hands import hands_by_body_side
from roomcap.keypoints.importers import import_2d
from roomcap.keypoints.skeletons import CANONICAL, FINGERS, HAND_BONES, HANDS, get_skeleton, whole_body
from roomcap.synthetic.rigs import ring_rig
from roomcap.track.greedy_stage import track_session_greedy
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate.poses3d import Poses3D
from roomcap.triangulate.stage import triangulate_session

SK = get_skeleton("blazepose33_hands")


def _hand(wrist: np.ndarray, elbow: np.ndarray, rng) -> np.ndarray:
    """(21,3) a flat open hand beyond the wrist along the forearm: palm bones 4-8 cm, phalanges 2-3 cm."""
    u = (wrist - elbow) / np.linalg.norm(wrist - elbow)
    v = np.cross(u, [0, 0, 1.0])
    v /= np.linalg.norm(v)
    out = [wrist + 0.01 * u]
    for k in range(len(FINGERS)):
        base = out[0] + (0.04 + 0.01 * (k > 0)) * u + (k - 2) * 0.02 * v
        out.append(base)
        for _ in range(3):
            out.append(out[-1] + 0.025 * u + rng.normal(0, 0.002, 3))
    return np.asarray(out)


def _person_with_hands(rng) -> np.ndarray:
    """(75,3) one person in the blazepose33_hands layout (body joints by name; others NaN)."""
    X19 = people(rng, 1, spread=0.5)[0]
    X = np.full((SK.n_joints, 3), np.nan)
    for j, n in enumerate(CANONICAL.joint_names):
        if n in SK.joint_names:
            X[SK.index(n)] = X19[j]
    for side in ("left", "right"):
        w, e = X19[CANONICAL.index(f"{side}_wrist")], X19[CANONICAL.index(f"{side}_elbow")]
        X[[SK.index(f"{side}_{n.split('_', 1)[1]}") for n in HANDS[:21]]] = _hand(w, e, rng)
    return X


def test_hands_triangulate_and_one_view_stays_2d(tmp_path, rng):
    X = _person_with_hands(rng)
    rig = ring_rig(4, radius_m=3.0)
    lay = SessionLayout(tmp_path)
    rig.save(lay.calib_dir / "rig.toml")
    T = 6
    lone = [SK.index(n) for n in ("left_thumb4", "right_pinky_finger2", "right_hand_root")]
    for c, cam in enumerate(rig):
        xy = cam.project(np.nan_to_num(X)).astype(np.float32)
        xy[np.isnan(X[:, 0])] = np.nan
        if c > 0:
            xy[lone] = np.nan  # these hand joints are seen by camera 0 only
        xy = np.repeat(xy[None, None], T, 0)
        Detections(
            camera=cam.name,
            skeleton="blazepose33_hands",
            frame_index=np.arange(T),
            t_ns=np.arange(T) * 40_000_000,
            xy_px=xy,
            score=np.where(np.isfinite(xy[..., 0]), 0.9, 0.0),
            boxes=np.full((T, 1, 5), np.nan),
        ).save(lay.detections(cam.name))
    p = Poses3D.load(triangulate_session(lay.root, {"skeleton": "whole_body"}))
    wb = whole_body(["blazepose33_hands"])
    assert p.joint_names == wb.joint_names and p.joint_names[-42:] == HANDS
    got = p.xyz_m[0, 0]
    for j, n in enumerate(wb.joint_names):
        if n not in HANDS:
            continue
        if SK.index(n) in lone:
            # one view: no 3D point, no view counted
            assert np.isnan(got[j]).all() and p.n_views[0, 0, j] == 0, n
        else:
            assert np.linalg.norm(got[j] - X[SK.index(n)]) < 2e-3, n
            assert p.n_views[0, 0, j] == 4 and p.reproj_err_px[0, 0, j] < 0.5
    # the hand bones hang from the body's wrist in the 3D skeleton and the greedy track carries them
    par = {p.joint_names[c]: p.joint_names[q] for c, q in enumerate(p.parents) if q >= 0}
    assert par["right_hand_root"] == "right_wrist" and all(par[c] == q for q, c in HAND_BONES)
    tf = TrackFile.load(track_session_greedy(lay.root))
    assert tf.joint_names == wb.joint_names
    k = wb.index("left_forefinger3")
    assert np.linalg.norm(tf.xyz_m[2, 0, k] - X[SK.index("left_forefinger3")]) < 5e-3


def _hands_2d(offset_right: float) -> tuple[np.ndarray, np.ndarray]:
    xy = np.full((1, SK.n_joints, 2), np.nan, np.float32)
    xy[0, SK.index("left_wrist")] = [100, 100]
    xy[0, SK.index("right_wrist")] = [300, 100]
    hand = np.stack([np.linspace(0, 40, 21), np.linspace(0, 60, 21)], -1)
    xy[0, [SK.index(n) for n in HANDS[:21]]] = hand + [300, 105]  # the "left" hand at the right wrist
    xy[0, [SK.index(n) for n in HANDS[21:]]] = hand + [300 + offset_right, 105]
    return xy, np.where(np.isfinite(xy[..., 0]), 1.0, 0.0)


def test_hands_by_body_side():
    L = [SK.index(n) for n in HANDS[:21]]
    R = [SK.index(n) for n in HANDS[21:]]
    # one hand found by both hand models: kept once, on the side of the nearer wrist (right)
    xy, sc = _hands_2d(1.0)
    out, osc, n = hands_by_body_side(xy, sc, SK.id)
    assert n == {"swapped": 0, "duplicates": 1, "moved": 0}
    assert np.isnan(out[0, L]).all() and (osc[0, L] == 0).all()
    np.testing.assert_array_equal(out[0, R], xy[0, R])
    # two hands, labelled the wrong way round: swapped
    xy, sc = _hands_2d(-200.0)
    out, _, n = hands_by_body_side(xy, sc, SK.id)
    assert n["swapped"] == 1
    np.testing.assert_array_equal(out[0, R], xy[0, L])
    np.testing.assert_array_equal(out[0, L], xy[0, R])
    # one hand at the right wrist labelled left: moved to the right
    xy, sc = _hands_2d(0.0)
    xy[0, R], sc[0, R] = np.nan, 0
    out, osc, n = hands_by_body_side(xy, sc, SK.id)
    assert n["moved"] == 1 and np.isnan(out[0, L]).all() and (osc[0, R] == 1).all()
    # without both wrists nothing changes
    xy, sc = _hands_2d(1.0)
    xy[0, SK.index("left_wrist")] = np.nan
    sc[0, SK.index("left_wrist")] = 0
    out, _, n = hands_by_body_side(xy, sc, SK.id)
    assert not any(n.values())
    np.testing.assert_array_equal(out, xy)


def _bone_std_mm(X, names) -> float:
    idx = {n: i for i, n in enumerate(names)}
    stds = []
    for p, c in HAND_BONES:
        L = np.linalg.norm(X[:, idx[p]] - X[:, idx[c]], axis=-1)
        if np.isfinite(L).sum() >= 10:
            stds.append(np.nanstd(L))
    return float(np.median(stds) * 1e3)


def test_caliscope_holistic_hands_in_3d(tmp_path):
    root = need_shared("data", "caliscope", "4_cam_recording_holistic_2d3d")
    xy_csv = root / "recordings" / "recording_1" / "HOLISTIC" / "xy_HOLISTIC.csv"
    lay = SessionLayout(tmp_path)
    import_2d(xy_csv, lay.keypoints_dir)
    import_rig(root / "config.toml").save(lay.calib_dir / "rig.toml")
    with np.errstate(all="ignore"):
        p = Poses3D.load(triangulate_session(lay.root, {"skeleton": "whole_body"}))
    assert p.cameras == ("cam_0", "cam_1", "cam_2", "cam_3") and p.n_frames == 267
    H = [p.joint_names.index(n) for n in HANDS]
    X = p.xyz_m[:, 0][:, H]
    have = np.isfinite(X[..., 0])
    assert have.sum() > 3000  # hand joints in 3D (of about 8700 seen by two views or more)
    assert (p.n_views[:, 0][:, H][have] >= 2).all()
    # our hand joints reproject far better than caliscope's 17-35 px median per camera
    assert np.nanmedian(p.reproj_err_px[:, 0][:, H]) < 8.0
    # the hand roots sit at the body's wrists
    for side in ("left", "right"):
        d = np.linalg.norm(
            p.xyz_m[:, 0, p.joint_names.index(f"{side}_hand_root")]
            - p.xyz_m[:, 0, p.joint_names.index(f"{side}_wrist")],
            axis=-1,
        )
        assert np.nanmedian(d) < 0.06, side
    # finger bones steadier than caliscope's own 3D (8.4 mm median std)
    assert _bone_std_mm(X, HANDS) < 7.0


@pytest.mark.parametrize("bad", ["nope.csv"])
def test_import_missing_path(tmp_path, bad):
    from roomcap.core.errors import InputError

    with pytest.raises(InputError, match="does not exist"):
        import_2d(tmp_path / bad, tmp_path / "k")


def _hand_track():
    """One walker with both hands (fingers fanned off the wrists) and a short gap in one finger joint."""
    from track_helpers import walkers

    from roomcap.track.trackfile import OBSERVED

    sk = get_skeleton("body19_hands")
    body = walkers(1, 30).astype(np.float64)  # (T,1,19,3)
    T = body.shape[0]
    xyz = np.full((T, 1, sk.n_joints, 3), np.nan)
    xyz[:, :, :19] = body
    for k, n in enumerate(HANDS):
        side = n.split("_", 1)[0]
        w = body[:, :, CANONICAL.index(f"{side}_wrist")]
        xyz[:, :, sk.index(n)] = w + [0.004 * (k % 21), 0.002 * (k % 21), -0.003 * (k % 21)]
    xyz[5:8, 0, sk.index("right_ring_finger3")] = np.nan  # a short gap: filled in the TRC
    known = np.isfinite(xyz).all(-1)
    tf = TrackFile(
        fps=25.0,
        frame_index=np.arange(T),
        t_ns=np.arange(T) * 40_000_000,
        track_id=np.array([1]),
        joint_names=sk.joint_names,
        parents=np.asarray(sk.parents),
        xyz_m=xyz,
        confidence=np.where(known, 0.9, 0.0),
        std_m=np.where(known, 0.01, np.nan),
        flags=np.where(known, OBSERVED, 0).astype(np.uint8),
        source="test",
    )
    return sk, xyz, tf


def test_exports_carry_hand_markers(tmp_path):
    """A track with hands: TRC (and C3D where ezc3d is installed), CSV and JSON name the hand markers as
    COCO-WholeBody does; the BVH has a JOINT per hand joint, the fingers hanging off the wrists."""
    from roomcap.outputs.export import ExportOptions, export_tracks, read_csv
    from roomcap.track.trackfile import read_json, read_trc, yup_to_world

    sk, xyz, tf = _hand_track()
    T = xyz.shape[0]
    formats = ("trc", "csv", "json", "bvh")
    try:
        import ezc3d  # noqa: F401

        formats += ("c3d",)
    except ImportError:
        pass
    rep = export_tracks(tf, tmp_path, "s", ExportOptions(formats=formats))
    got = sorted(p.suffix for p in rep.files if p.name.startswith("s_1."))
    assert got == sorted(f".{f}" for f in formats)
    names, pts, _, frame_no = read_trc(tmp_path / "s_1.trc")
    assert names[-42:] == list(HANDS) and "LWrist" in names and len(frame_no) == T
    assert np.isfinite(pts).all()
    j = names.index("left_middle_finger2")
    np.testing.assert_allclose(yup_to_world(pts[:, j]), xyz[:, 0, sk.index("left_middle_finger2")], atol=2e-6)
    back = read_csv(tmp_path / "s_1.csv", sk.joint_names)
    np.testing.assert_allclose(back["xyz_m"][:, 0], xyz[:, 0], atol=1e-6)
    assert read_json(tmp_path / "s_1.json").joint_names == sk.joint_names
    bvh = (tmp_path / "s_1.bvh").read_text()
    assert "JOINT right_pinky_finger4" in bvh and bvh.count("JOINT left_") > 21
    assert bvh.index("JOINT left_wrist") < bvh.index("JOINT left_hand_root") < bvh.index("JOINT left_thumb1")
    if "c3d" in formats:
        import ezc3d

        c = ezc3d.c3d(str(tmp_path / "s_1.c3d"))
        assert c["parameters"]["POINT"]["LABELS"]["value"][-1] == "right_pinky_finger4"


def test_opensim_reads_the_trc_with_hand_markers(tmp_path):
    """OpenSim's own TRC reader takes the whole-body TRC: every hand marker by its COCO-WholeBody name, at
    the exported position."""
    opensim = pytest.importorskip(
        "opensim", reason="OpenSim is an optional extra: pip install 'roomcap[opensim]'"
    )
    from roomcap.outputs.export import ExportOptions, export_tracks
    from roomcap.track.trackfile import read_trc

    sk, xyz, tf = _hand_track()
    export_tracks(tf, tmp_path, "s", ExportOptions(formats=("trc",)))
    table = opensim.TimeSeriesTableVec3(str(tmp_path / "s_1.trc"))  # OpenSim's TRCFileAdapter
    labels = list(table.getColumnLabels())
    assert labels[-42:] == list(HANDS) and table.getNumRows() == xyz.shape[0]
    names, pts, _, _ = read_trc(tmp_path / "s_1.trc")  # file axes and units, as OpenSim reads them
    for name in ("left_middle_finger2", "right_thumb4", "right_hand_root"):
        v = table.getDependentColumnAtIndex(labels.index(name))[10]
        np.testing.assert_allclose([v.get(0), v.get(1), v.get(2)], pts[10, names.index(name)], atol=1e-6)


def test_a_hand_seen_by_one_view_is_never_a_3d_point_downstream(tmp_path, rng):
    """Hand joints one camera sees (the others do not) keep their 2D and get no 3D anywhere: the poses
    (NaN, 0 views), the greedy and the particle track files (NaN, flags 0: neither observed, nor filled,
    nor predicted), while the joints every camera sees are there in both."""
    from roomcap.track.stage import track_session_particle
    from roomcap.track.trackfile import OBSERVED

    X = _person_with_hands(rng)
    rig = ring_rig(4, radius_m=3.0)
    lay = SessionLayout(tmp_path)
    rig.save(lay.calib_dir / "rig.toml")
    T = 12
    right = [SK.index(n) for n in HANDS[21:]]  # the whole right hand: camera 0 only
    for c, cam in enumerate(rig):
        xy = np.stack([cam.project(np.nan_to_num(X + [0.01 * t, 0, 0])) for t in range(T)])[:, None]
        xy = xy.astype(np.float32)
        xy[:, :, np.isnan(X[:, 0])] = np.nan
        if c > 0:
            xy[:, :, right] = np.nan
        Detections(
            camera=cam.name,
            skeleton=SK.id,
            frame_index=np.arange(T),
            t_ns=np.arange(T) * 40_000_000,
            xy_px=xy,
            score=np.where(np.isfinite(xy[..., 0]), 0.9, 0.0),
            boxes=np.full((T, 1, 5), np.nan),
        ).save(lay.detections(cam.name))
    assert np.isfinite(Detections.load(lay.detections("cam00")).xy_px[:, 0, right]).all()  # the 2D stays
    p = Poses3D.load(triangulate_session(lay.root, {"skeleton": "whole_body"}))
    wb = whole_body([SK.id])
    R3 = [wb.index(n) for n in HANDS[21:]]
    L3 = [wb.index(n) for n in HANDS[:21]]
    assert np.isnan(p.xyz_m[:, 0, R3]).all() and (p.n_views[:, 0, R3] == 0).all()
    greedy = TrackFile.load(track_session_greedy(lay.root))
    particle = TrackFile.load(
        track_session_particle(lay.root, {"skeleton": "whole_body", "n_samples": 200, "chunk_s": 0})
    )
    for tf in (greedy, particle):
        assert tf.joint_names == wb.joint_names
        k = 0
        assert np.isnan(tf.xyz_m[:, k, R3]).all() and (tf.flags[:, k, R3] == 0).all(), tf.source
        seen = (tf.flags[:, k, L3] & OBSERVED) > 0
        assert seen.mean() > 0.8, tf.source  # the left hand, seen by every camera, is tracked
