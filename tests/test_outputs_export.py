"""Exports of the track file (TRC, C3D, CSV, JSON, BVH), the skeleton fit, and the ``tracks`` command."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.keypoints.skeletons import CANONICAL
from roomcap.outputs.bvh import write_bvh
from roomcap.outputs.cli import main as tracks_main
from roomcap.outputs.export import (
    ExportError,
    ExportOptions,
    export_tracks,
    fill_gaps,
    marker_table,
    parse_formats,
    read_csv,
    write_c3d,
    write_trc,
)
from roomcap.outputs.skeleton_fit import SkeletonFit, file_sha256, fit_skeleton, fit_skeletons
from roomcap.track.trackfile import OBSERVED, TrackFile, read_json, read_trc, world_to_yup, yup_to_world


def _walkers(n_people=2, T=60, seed=0):
    from tests.track_helpers import walkers

    return walkers(n_people, T, seed=seed).astype(np.float64)


def _trackfile(xyz, rng=None, std=0.01, skeleton=CANONICAL, std_max_m=0.03) -> TrackFile:
    """A track file of ``xyz (T,K,J,3)`` in ``skeleton``'s layout (NaN: unknown), random confidences and
    std (0.005 to ``std_max_m``) where known."""
    T, K, J = xyz.shape[:3]
    rng = rng or np.random.default_rng(0)
    known = np.isfinite(xyz).all(-1)
    return TrackFile(
        fps=25.0,
        frame_index=np.arange(T) + 100,
        t_ns=np.arange(T) * 40_000_000 + 5_000_000_000,
        track_id=np.arange(K) + 3,
        joint_names=skeleton.joint_names,
        parents=np.asarray(skeleton.parents),
        xyz_m=xyz,
        confidence=np.where(known, rng.uniform(0.5, 1.0, (T, K, J)), 0.0),
        std_m=np.where(known, rng.uniform(0.005, std_max_m, (T, K, J)), np.nan),
        flags=np.where(known, OBSERVED, 0).astype(np.uint8),
        source="test",
    )


def test_axes_round_trip_and_proper_rotation(rng):
    x = rng.normal(size=(5, 3))
    np.testing.assert_allclose(yup_to_world(world_to_yup(x)), x)
    M = world_to_yup(np.eye(3))
    assert np.linalg.det(M) == pytest.approx(1.0)
    assert world_to_yup(np.array([0.0, 0.0, 1.0]))[1] == 1.0  # world up is file y


def test_fill_gaps_short_only():
    T = 30
    x = np.zeros((T, 2, 3))
    x[:, :, 0] = np.arange(T)[:, None]
    x[5:8, 0] = np.nan  # 3 frames: filled
    x[10:25, 1] = np.nan  # 15 frames: kept unknown
    s = np.ones((T, 2))
    f, fs, filled = fill_gaps(x, s, max_gap=10)
    np.testing.assert_allclose(f[5:8, 0, 0], [5, 6, 7])
    assert filled[5:8, 0].all() and not filled[:5, 0].any()
    assert np.isnan(f[10:25, 1]).all() and not filled[:, 1].any()


def test_trc_pose2sim_names_no_blank_cells_gaps_flagged(tmp_path):
    xyz = _walkers(1, 80)
    xyz[10:14, 0, CANONICAL.index("left_wrist")] = np.nan  # short gap: filled + flagged
    xyz[40:60, 0, CANONICAL.index("right_knee")] = np.nan  # long gap: frames left out
    xyz[:, 0, CANONICAL.index("left_ear")] = np.nan  # never seen: marker left out
    xyz[:5, 0] = np.nan  # person enters at frame 5
    tf = _trackfile(xyz)
    mt = write_trc(tf, 3, tmp_path / "s_3.trc")
    names, pts, time_s, frame_no = read_trc(tmp_path / "s_3.trc")
    assert "LWrist" in names and "RKnee" in names and "Hip" in names and "Neck" in names
    assert "LEar" not in names and "LEar" in mt.dropped_markers
    assert np.isfinite(pts).all(), "TRC must have no blank cells"
    text = (tmp_path / "s_3.trc").read_text().splitlines()
    assert all("\t\t" not in ln.rstrip("\t") for ln in text[6:])
    assert len(pts) == 75 - 20 and 41 not in frame_no  # 20 frames with the knee unknown left out
    assert frame_no[0] == 6 and time_s[0] == pytest.approx(5 / 25)
    j = names.index("LShoulder")
    t = list(frame_no).index(20)
    np.testing.assert_allclose(
        yup_to_world(pts[t, j]), xyz[19, 0, CANONICAL.index("left_shoulder")], atol=2e-6
    )
    filled = (tmp_path / "s_3.filled.csv").read_text().splitlines()
    assert filled[0] == "frame,time_s,marker" and len(filled) == 1 + 4 and filled[1].endswith(",LWrist")


def test_person_without_a_complete_frame_is_a_clear_error():
    # the nose is unknown in the first half, the right knee in the second: each known in 50 % of the
    # frames (kept as markers), never both, and the gaps are too long to fill
    xyz = _walkers(1, 40)
    xyz[:20, 0, CANONICAL.index("nose")] = np.nan
    xyz[20:, 0, CANONICAL.index("right_knee")] = np.nan
    tf = _trackfile(xyz)
    with pytest.raises(ExportError, match=r"track 3 has no frame in which all its markers are known"):
        marker_table(tf, 3, max_gap=5)
    from roomcap.outputs.skeleton_fit_file import FitError

    with pytest.raises(FitError, match=r"track 3 has no frame in which all 19 joints are known"):
        fit_skeletons(tf)


def test_unknown_format_and_person():
    with pytest.raises(ExportError, match=r"unknown export format \['fbx'\].*trc,c3d,bvh,csv,json"):
        parse_formats("trc,fbx")
    tf = _trackfile(_walkers(1, 10))
    from roomcap.core.errors import FormatError

    with pytest.raises(FormatError, match=r"no track 9; the file has tracks \[3\]"):
        marker_table(tf, 9)


def test_c3d_second_reader_equals_trc(tmp_path):
    pytest.importorskip("ezc3d", reason="C3D export needs ezc3d (pip install 'roomcap[c3d]')")
    c3d = pytest.importorskip("c3d", reason="the second C3D reader is the c3d package (pip install c3d)")
    import ezc3d

    xyz = _walkers(1, 50)
    xyz[10:13, 0, CANONICAL.index("left_wrist")] = np.nan
    xyz[30:45, 0, CANONICAL.index("right_knee")] = np.nan
    tf = _trackfile(xyz)
    mt = write_trc(tf, 3, tmp_path / "s.trc")
    write_c3d(tf, 3, tmp_path / "s.c3d", mt)
    names, trc, _, frame_no = read_trc(tmp_path / "s.trc")
    with open(tmp_path / "s.c3d", "rb") as f:
        r = c3d.Reader(f)
        labels = [lab.strip() for lab in r.point_labels]
        assert r.point_rate == pytest.approx(25.0)
        frames = np.stack([p[:, :3] for _, p, _ in r.read_frames()])  # (T,M,3)
    assert labels == names
    rows = frame_no - 1 - mt.rows[0]
    np.testing.assert_allclose(frames[rows], trc, atol=1e-4)  # 0.1 mm
    # residuals (ezc3d reads the residual word as it writes it): std_m in mm steps, 0 filled, -1 unknown
    res = ezc3d.c3d(str(tmp_path / "s.c3d"))["data"]["meta_points"]["residuals"][0].T  # (T,M)
    lw, rk = names.index("LWrist"), names.index("RKnee")
    assert (res[10:13, lw] == 0).all()
    assert (res[30:45, rk] == -1).all()
    ok = ~mt.filled & np.isfinite(mt.std_m)
    np.testing.assert_allclose(res[ok], np.clip(mt.std_m[ok], 0.001, 0.255), atol=5.01e-4)


def test_csv_and_json_round_trip(tmp_path):
    xyz = _walkers(2, 30)
    xyz[3:9, 1, 4] = np.nan
    tf = _trackfile(xyz)
    opts = ExportOptions(formats=("csv", "json"))
    rep = export_tracks(tf, tmp_path, "sess", opts)
    assert sorted(p.name for p in rep.files) == ["sess_3.csv", "sess_3.json", "sess_4.csv", "sess_4.json"]
    back = read_csv(tmp_path / "sess_4.csv", CANONICAL.joint_names)
    assert back["person"].tolist() == [4] and back["frame"][0] == 100
    np.testing.assert_allclose(back["xyz_m"][:, 0], tf.xyz_m[:, 1], atol=1e-6)
    np.testing.assert_allclose(back["std_m"][:, 0], tf.std_m[:, 1], atol=1e-6)
    np.testing.assert_allclose(back["confidence"][:, 0], tf.confidence[:, 1], atol=1e-4)
    np.testing.assert_allclose(back["time_s"], np.arange(30) * 0.04, atol=1e-6)
    js = read_json(tmp_path / "sess_4.json")
    assert js.track_id.tolist() == [4] and js.joint_names == CANONICAL.joint_names
    np.testing.assert_allclose(js.xyz_m[:, 0], tf.xyz_m[:, 1], atol=1e-5)
    np.testing.assert_allclose(js.std_m[:, 0], tf.std_m[:, 1], atol=1e-5)
    np.testing.assert_array_equal(js.flags[:, 0], tf.flags[:, 1])


# ----------------------------------------------------------------------------- skeleton fit + BVH


def test_fit_skeleton_tree_adds_trunk_and_head_joints():
    names, parents, idx = fit_skeleton(CANONICAL.joint_names, CANONICAL.parents)
    assert names[parents[names.index("neck")]] == "spine" and names[parents[names.index("spine")]] == "pelvis"
    assert names[parents[names.index("nose")]] == "head" and names[parents[names.index("head")]] == "neck"
    assert [names[i] for i in idx] == list(CANONICAL.joint_names)


def test_fit_constant_bones_small_error_and_limits(rng):
    xyz = _walkers(2, 80)
    noisy = xyz + rng.normal(0, 0.005, xyz.shape)
    tf = _trackfile(noisy)
    fit = fit_skeletons(tf)
    P = fit.positions()
    names = fit.joint_names
    for k in range(2):
        for j, p in enumerate(fit.parents):
            if p >= 0:
                d = np.linalg.norm(P[:, k, j] - P[:, k, p], axis=-1)
                assert np.ptp(d) < 1e-6  # constant bone lengths
    gt_len = np.linalg.norm(xyz[:, 0, 13] - xyz[:, 0, 11], axis=-1).mean()  # left hip -> knee
    assert fit.bone_length_m[0, names.index("left_knee")] == pytest.approx(gt_len, abs=0.01)
    err = np.linalg.norm(fit.joint_positions() - xyz, axis=-1)
    assert np.median(err) < 0.02 and np.nanmedian(fit.fit_error_m) < 0.02
    # knees and elbows stay inside the hinge limits
    for h in ("left_knee", "right_elbow"):
        j = names.index(h)
        c = next(i for i, p in enumerate(fit.parents) if p == j)
        a = P[:, 0, j] - P[:, 0, fit.parents[j]]
        b = P[:, 0, c] - P[:, 0, j]
        ang = np.degrees(
            np.arccos(
                np.clip((a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1), -1, 1)
            )
        )
        assert ang.max() <= 150.5


def test_fit_save_load_and_stale(tmp_path, rng):
    tf = _trackfile(_walkers(1, 20))
    tf.save(tmp_path / "tracks.npz")
    sha = file_sha256(tmp_path / "tracks.npz")
    fit = fit_skeletons(tf, tracks_sha256=sha)
    fit.save(tmp_path / "skeleton_fit.npz")
    back = SkeletonFit.load(tmp_path / "skeleton_fit.npz", tracks_sha256=sha)
    np.testing.assert_allclose(back.positions(), fit.positions(), atol=1e-9)
    from roomcap.core.errors import FormatError

    with pytest.raises(FormatError, match="another version of the track file"):
        SkeletonFit.load(tmp_path / "skeleton_fit.npz", tracks_sha256="0" * 64)


def test_bvh_forward_kinematics_equals_fit(tmp_path, rng):
    from roomcap.synthetic.bvh import read_bvh

    xyz = _walkers(2, 40) + rng.normal(0, 0.005, (40, 2, 19, 3))
    xyz[:10, 1] = np.nan  # second person enters later
    tf = _trackfile(xyz)
    fit = fit_skeletons(tf)
    P = fit.positions()
    write_bvh(fit, tmp_path / "one.bvh", track_ids=[4])
    b = read_bvh(tmp_path / "one.bvh")
    assert b.n_frames == 30 and b.fps == pytest.approx(25.0)
    joints = [b.index(n) for n in fit.joint_names]
    pos, _ = b.forward_kinematics(joints)
    np.testing.assert_allclose(yup_to_world(pos), P[10:, 1], atol=1e-5)
    write_bvh(fit, tmp_path / "all.bvh")
    b2 = read_bvh(tmp_path / "all.bvh")
    assert b2.n_frames == 40 and "left_knee_3" in b2.names and "left_knee_4" in b2.names
    pos2, _ = b2.forward_kinematics([b2.index(f"{n}_3") for n in fit.joint_names])
    np.testing.assert_allclose(yup_to_world(pos2), P[:, 0], atol=1e-5)


# ----------------------------------------------------------------------------- the command


def _session(tmp_path, xyz):
    tf = _trackfile(xyz)
    (tmp_path / "S01" / "track").mkdir(parents=True)
    tf.save(tmp_path / "S01" / "track" / "tracks.npz")
    return tmp_path / "S01"


def test_cli_export_all_formats(tmp_path, capsys):
    pytest.importorskip("ezc3d", reason="C3D export needs ezc3d")
    sess = _session(tmp_path, _walkers(2, 30))
    rc = tracks_main(
        ["export", str(sess), "--format", "trc,c3d,bvh,csv,json", "--out", str(tmp_path / "o"), "--multi"]
    )
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "fitted the skeletons now" in out  # no rotations in the track file: fit on the fly
    got = sorted(p.name for p in (tmp_path / "o").iterdir())
    for tid in (3, 4):
        for ext in ("trc", "c3d", "bvh", "csv", "json"):
            assert f"S01_{tid}.{ext}" in got
    assert "S01_all.bvh" in got
    assert tracks_main(["fit", str(sess)]) == 0
    assert (sess / "track" / "skeleton_fit.npz").exists()
    capsys.readouterr()
    rc = tracks_main(
        [
            "export",
            str(sess / "track" / "tracks.npz"),
            "--format",
            "bvh",
            "--person",
            "4",
            "--out",
            str(tmp_path / "p"),
        ]
    )
    assert rc == 0 and "fitted the skeletons now" not in capsys.readouterr().out
    assert [p.name for p in (tmp_path / "p").iterdir()] == ["S01_4.bvh"]


def test_cli_bad_input_messages(tmp_path, capsys):
    sess = _session(tmp_path, _walkers(1, 10))
    assert tracks_main(["export", str(sess), "--format", "fbx", "--out", str(tmp_path / "o")]) == 2
    assert "unknown export format ['fbx']" in capsys.readouterr().err
    assert tracks_main(["export", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert tracks_main(["export", str(sess), "--person", "12", "--out", str(tmp_path / "o")]) == 2
    assert "no track 12" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert tracks_main(["export", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    assert "has no track file" in capsys.readouterr().err


def test_cli_bvh_of_unfittable_person_says_why(tmp_path, capsys):
    xyz = _walkers(2, 40)
    xyz[:20, 1, CANONICAL.index("nose")] = np.nan
    xyz[20:, 1, CANONICAL.index("right_knee")] = np.nan
    sess = _session(tmp_path, xyz)
    # every person: the one without a complete frame is skipped with a note, the other exported
    assert tracks_main(["export", str(sess), "--format", "bvh", "--out", str(tmp_path / "o")]) == 0
    out = capsys.readouterr().out
    assert "BVH left out: track 4 has no frame in which all 19 joints are known" in out
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["S01_3.bvh"]
    # that person asked for by id: an error that says why
    assert (
        tracks_main(["export", str(sess), "--format", "bvh", "--person", "4", "--out", str(tmp_path / "q")])
        == 2
    )
    assert "track 4 has no frame in which all 19 joints are known" in capsys.readouterr().err


def test_reprocess_export_rejects_unknown_format(tmp_path, capsys):
    from roomcap.pipeline.cli import main as reprocess_main

    assert reprocess_main([str(tmp_path), "--export", "trc,obj"]) == 2
    assert "unknown export format ['obj']" in capsys.readouterr().err


def test_reprocess_export_writes_files_per_person(tmp_path, capsys):
    from roomcap.pipeline.cli import main as reprocess_main
    from roomcap.pipeline.synth import make_sessions

    make_sessions(tmp_path / "syn", 1, duration_s=1.0)
    sess = next(p for p in (tmp_path / "syn").iterdir() if p.is_dir())
    out = tmp_path / "out"
    rc = reprocess_main(
        [
            str(sess),
            "--out",
            str(out),
            "--stages",
            "triangulate,track",
            "--workers",
            "1",
            "--export",
            "trc,csv",
        ]
    )
    assert rc == 0, capsys.readouterr()
    exp = out / sess.name / "export"
    tf = TrackFile.load(out / sess.name / "track" / "tracks.npz")
    csvs = sorted(p.name for p in exp.glob("*.csv") if not p.name.endswith(".filled.csv"))
    assert csvs == sorted(f"{sess.name}_{t}.csv" for t in tf.track_id.tolist())
    for trc in exp.glob("*.trc"):
        assert np.isfinite(read_trc(trc)[1]).all()
    assert any(exp.glob("*.trc"))


def test_lowpass_as_pose2sim_filters(tmp_path, capsys):
    from roomcap.outputs.export import lowpass
    from roomcap.track.trackfile import SMOOTHED

    T, fps = 120, 25.0
    t = np.arange(T) / fps
    xyz = np.full((T, 1, len(CANONICAL.joint_names), 3), np.nan)
    slow, fast = 0.3 * np.sin(2 * np.pi * 1.0 * t), 0.01 * np.sin(2 * np.pi * 10.0 * t)
    xyz[:, 0, :, 0] = (slow + fast)[:, None]
    xyz[:, 0, :, 1:] = 1.0
    xyz[50:53, 0, 2] = np.nan  # a gap: both runs filtered, the gap stays
    xyz[:8, 0, 4] = np.nan
    xyz[12:, 0, 4] = np.nan  # a 4-frame run, too short to filter: as it is
    tf = _trackfile(xyz)
    f = lowpass(tf, 6.0)
    x = f.xyz_m[:, 0, 0, 0].astype(np.float64)
    mid = slice(15, T - 15)
    assert np.abs(x - slow)[mid].max() < 0.003  # the 10 Hz wobble (10 mm) is gone, the 1 Hz motion kept
    assert np.abs(tf.xyz_m[:, 0, 0, 0] - slow)[mid].max() > 0.009
    assert np.isnan(f.xyz_m[50:53, 0, 2]).all() and np.isfinite(f.xyz_m[53:, 0, 2]).all()
    np.testing.assert_array_equal(f.xyz_m[8:12, 0, 4], tf.xyz_m[8:12, 0, 4])
    assert (f.flags[:, 0, 0] & SMOOTHED).all() and not (f.flags[8:12, 0, 4] & SMOOTHED).any()
    with pytest.raises(ExportError, match="below half the frame rate"):
        lowpass(tf, 13.0)
    # through the command: the TRC is the filtered one
    (tmp_path / "S" / "track").mkdir(parents=True)
    tf.save(tmp_path / "S" / "track" / "tracks.npz")
    args = ["export", str(tmp_path / "S"), "--format", "trc", "--out", str(tmp_path / "o")]
    assert tracks_main([*args, "--lowpass", "6"]) == 0
    assert "low-pass filtered (Butterworth, order 4, zero phase, 6 Hz)" in capsys.readouterr().out
    names, trc, _, _ = read_trc(tmp_path / "o" / "S_3.trc")
    np.testing.assert_allclose(yup_to_world(trc)[:, names.index("Nose"), 0], x[:T], atol=1e-5)
    assert tracks_main([*args, "--lowpass", "-1"]) == 2


def test_cli_fit_lists_finger_bones(tmp_path, capsys):
    """``tracks fit`` of a whole-body track: per person the finger bone lengths (held constant, near the
    synthetic hand's) and the track's own steadiness; a person whose right hand is never seen still fits
    (its right fingers NaN, "not seen"); a body-only track prints no finger line."""
    from hands_helpers import _ALONG, _PHALANX, SK, wholebody_trackfile, wholebody_xyz

    from roomcap.keypoints.skeletons import FINGERS, HANDS

    xyz = wholebody_xyz(2, 30) + np.random.default_rng(3).normal(0, 0.002, (30, 2, SK.n_joints, 3))
    xyz[:, 1, [SK.index(n) for n in HANDS[21:]]] = np.nan  # person 4: right hand never seen
    sess = tmp_path / "S02"
    (sess / "track").mkdir(parents=True)
    wholebody_trackfile(xyz).save(sess / "track" / "tracks.npz")
    assert tracks_main(["fit", str(sess)]) == 0
    out = capsys.readouterr().out
    assert "track 3: left hand bones (mm, root to tip): thumb" in out
    assert "track 4: right hand bones (mm, root to tip): not seen" in out
    assert "track 3: finger bones in the track: 40 seen" in out
    assert "track 4: finger bones in the track: 20 seen" in out
    fit = SkeletonFit.load(sess / "track" / "skeleton_fit.npz")
    for k in (0, 1):
        fl = fit.finger_lengths_m(k)
        assert sorted(fl) == sorted(f"{s}_{f}" for s in ("left", "right") for f in FINGERS)
        np.testing.assert_allclose(fl["left_middle_finger"][1:], _PHALANX, atol=2e-3)
        assert abs(fl["left_forefinger"][0] - np.hypot(_ALONG[1], 0.01)) < 3e-3  # the palm bone
    assert np.isfinite(fit.finger_lengths_m(0)["right_pinky_finger"]).all()
    assert np.isnan(fit.finger_lengths_m(1)["right_pinky_finger"]).all()
    # body-only: as before, no finger lines
    sess1 = _session(tmp_path / "b", _walkers(1, 20))
    assert tracks_main(["fit", str(sess1)]) == 0
    assert "hand bones" not in capsys.readouterr().out


def test_fit_with_hands_leaves_the_body_as_the_body_only_fit():
    """The hands are fitted beside the body: the body joints of a whole-body fit are the body-only fit's
    (same rest pose, same per-frame solution), and the fingers follow the track within a few mm."""
    from hands_helpers import SK, wholebody_trackfile, wholebody_xyz

    from roomcap.keypoints.skeletons import HANDS

    xyz = wholebody_xyz(1, 20) + np.random.default_rng(4).normal(0, 0.002, (20, 1, SK.n_joints, 3))
    tf = wholebody_trackfile(xyz)
    body = TrackFile(
        fps=tf.fps, frame_index=tf.frame_index, t_ns=tf.t_ns, track_id=tf.track_id,
        joint_names=CANONICAL.joint_names, parents=np.asarray(CANONICAL.parents), xyz_m=tf.xyz_m[:, :, :19],
        confidence=tf.confidence[:, :, :19], std_m=tf.std_m[:, :, :19], flags=tf.flags[:, :, :19], source="t",
    )  # fmt: skip
    fb, fh = fit_skeletons(body), fit_skeletons(tf)
    np.testing.assert_allclose(fh.joint_positions()[:, :, :19], fb.joint_positions(), atol=1e-9)
    H = [SK.index(n) for n in HANDS]
    e = fh.fit_error_m[:, 0, H]
    assert np.median(e) < 0.005 and e.max() < 0.02, (np.median(e), e.max())
