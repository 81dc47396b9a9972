"""Round trips and bad input for the file contracts: detections, poses3d, tracks, skeletons, atomic IO."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.core.errors import FormatError, SchemaError
from roomcap.core.fileio import atomic_write_text, load_npz, save_npz
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import CANONICAL, SKELETONS, convert, get_skeleton
from roomcap.track.trackfile import OBSERVED, PREDICTED, TrackFile, export_json, export_trc, load_dense
from roomcap.triangulate.poses3d import Poses3D


def _tracks(rng, T=5, K=2, J=19):
    xyz = rng.normal(size=(T, K, J, 3))
    xyz[1, 0, 3] = np.nan
    flags = np.full((T, K, J), OBSERVED)
    flags[2, 1] |= PREDICTED
    return TrackFile(
        fps=25.0,
        frame_index=np.arange(T),
        t_ns=np.arange(T) * 40_000_000,
        track_id=np.array([3, 7]),
        joint_names=CANONICAL.joint_names,
        parents=np.asarray(CANONICAL.parents),
        xyz_m=xyz,
        confidence=rng.uniform(size=(T, K, J)),
        std_m=rng.uniform(0, 0.05, (T, K, J)),
        flags=flags,
        calibration_sha256="abc",
        source="test",
    )


def test_trackfile_round_trip_and_dense(tmp_path, rng):
    tf = _tracks(rng)
    tf.save(tmp_path / "tracks.npz")
    back = TrackFile.load(tmp_path / "tracks.npz")
    np.testing.assert_array_equal(back.xyz_m, tf.xyz_m)
    np.testing.assert_array_equal(back.flags, tf.flags)
    assert back.joint_names == CANONICAL.joint_names and back.source == "test" and back.fps == 25.0
    dense = load_dense(tmp_path / "tracks.npz")
    assert dense["joint_mask"].shape == (5, 2, 19) and not dense["joint_mask"][1, 0, 3]
    assert np.isfinite(dense["xyz_m"]).all()


def test_trackfile_rejects_unknown_version_and_truncation(tmp_path, rng):
    tf = _tracks(rng)
    p = tmp_path / "tracks.npz"
    tf.save(p)
    data = load_npz(p)
    data["schema"] = np.asarray("tracks/99")
    save_npz(tmp_path / "new.npz", data)
    with pytest.raises(SchemaError, match=r"new\.npz.*version 99.*Upgrade"):
        TrackFile.load(tmp_path / "new.npz")
    raw = p.read_bytes()
    (tmp_path / "cut.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(FormatError, match=r"cut\.npz.*truncated"):
        TrackFile.load(tmp_path / "cut.npz")


def test_trackfile_shape_error_names_field(rng):
    tf = _tracks(rng)
    with pytest.raises(FormatError, match="std_m"):
        TrackFile(**{**tf.__dict__, "std_m": np.zeros((5, 2))})


def test_trc_and_json_export(tmp_path, rng):
    tf = _tracks(rng)
    export_trc(tf, tmp_path / "t.trc", track=3)
    lines = (tmp_path / "t.trc").read_text().splitlines()
    assert lines[2].split("\t")[3] == "19" and len(lines) == 6 + 5
    row = lines[6].split("\t")
    # y-up: file (X, Y, Z) = world (x, z, -y)
    assert float(row[2]) == pytest.approx(tf.xyz_m[0, 0, 0, 0], abs=1e-5)
    assert float(row[3]) == pytest.approx(tf.xyz_m[0, 0, 0, 2], abs=1e-5)
    assert float(row[4]) == pytest.approx(-tf.xyz_m[0, 0, 0, 1], abs=1e-5)
    export_json(tf, tmp_path / "t.json")
    assert '"track_id": 7' in (tmp_path / "t.json").read_text()


def test_detections_round_trip_and_errors(tmp_path, rng):
    T, P, J = 4, 3, 17
    d = Detections(
        camera="cam01",
        skeleton="coco17",
        frame_index=np.arange(T),
        t_ns=np.arange(T),
        xy_px=rng.uniform(0, 100, (T, P, J, 2)),
        score=rng.uniform(size=(T, P, J)),
        boxes=np.full((T, P, 5), np.nan),
        model="m",
        model_sha256="00",
        image_size_wh=(640, 480),
    )
    d.save(tmp_path / "cam01.npz")
    back = Detections.load(tmp_path / "cam01.npz")
    assert back.camera == "cam01" and back.image_size_wh == (640, 480)
    np.testing.assert_allclose(back.xy_px, d.xy_px, rtol=1e-6)
    with pytest.raises(FormatError, match="xy_px.*expected shape"):
        Detections(
            camera="c",
            skeleton="coco17",
            frame_index=np.arange(T),
            t_ns=np.arange(T),
            xy_px=np.zeros((T, P, 18, 2)),
            score=np.zeros((T, P, J)),
            boxes=np.zeros((T, P, 5)),
        )


def test_poses3d_round_trip(tmp_path, rng):
    T, P, J = 3, 2, 19
    p = Poses3D(
        fps=30,
        frame_index=np.arange(T),
        t_ns=np.zeros(T),
        joint_names=CANONICAL.joint_names,
        xyz_m=rng.normal(size=(T, P, J, 3)),
        score=np.ones((T, P, J)),
        reproj_err_px=np.ones((T, P, J)),
        n_views=np.full((T, P, J), 3),
    )
    p.save(tmp_path / "p.npz")
    back = Poses3D.load(tmp_path / "p.npz")
    np.testing.assert_allclose(back.xyz_m, p.xyz_m, rtol=1e-6)
    assert back.n_views.dtype == np.int16


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    p = tmp_path / "a.txt"
    atomic_write_text(p, "old")

    class Boom(Exception):
        pass

    from roomcap.core.fileio import atomic_path

    with pytest.raises(Boom):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise Boom
    assert p.read_text() == "old"
    assert [f.name for f in tmp_path.iterdir()] == ["a.txt"]


def test_save_npz_refuses_object_arrays(tmp_path):
    with pytest.raises(TypeError, match="object array"):
        save_npz(tmp_path / "x.npz", {"a": np.array([{"x": 1}], dtype=object)})


@pytest.mark.parametrize("sid", sorted(SKELETONS))
def test_skeleton_trees_are_valid(sid):
    s = get_skeleton(sid)
    assert len(set(s.joint_names)) == s.n_joints
    roots = [j for j, p in enumerate(s.parents) if p < 0]
    assert len(roots) == 1, (sid, [s.joint_names[r] for r in roots])
    # every joint reaches the root without cycles
    for j in range(s.n_joints):
        seen = set()
        while j >= 0:
            assert j not in seen
            seen.add(j)
            j = s.parents[j]
    flip = s.flip_index
    assert (flip[flip] == np.arange(s.n_joints)).all()


@pytest.mark.parametrize("src", ["coco17", "coco18", "body25", "body25b", "halpe26", "blazepose33"])
def test_convert_to_body19_keeps_names_and_derives_pelvis_neck(src, rng):
    s = get_skeleton(src)
    xy = rng.uniform(0, 100, (2, s.n_joints, 2))
    sc = rng.uniform(0.5, 1, (2, s.n_joints))
    out, osc = convert(xy, sc, src, "body19")
    for j, name in enumerate(CANONICAL.joint_names):
        if name in s.joint_names:
            np.testing.assert_allclose(out[:, j], xy[:, s.index(name)])
    lh, rh = s.index("left_hip"), s.index("right_hip")
    if "pelvis" not in s.joint_names:
        np.testing.assert_allclose(out[:, CANONICAL.index("pelvis")], 0.5 * (xy[:, lh] + xy[:, rh]))
    assert np.isfinite(out).all() and (osc > 0).all()


def test_convert_nan_gives_zero_score():
    xy = np.full((17, 2), np.nan)
    out, sc = convert(xy, np.ones(17), "coco17")
    assert np.isnan(out).all() and (sc == 0).all()


def test_save_npz_is_byte_identical_across_runs(tmp_path, rng):
    import time

    arrays = {"a": rng.normal(size=(10, 3)), "s": np.asarray("x")}
    save_npz(tmp_path / "1.npz", arrays)
    time.sleep(2.1)  # zip timestamps have 2 s resolution
    save_npz(tmp_path / "2.npz", arrays)
    assert (tmp_path / "1.npz").read_bytes() == (tmp_path / "2.npz").read_bytes()
    np.testing.assert_array_equal(load_npz(tmp_path / "2.npz")["a"], arrays["a"])


def test_atomic_writes_get_normal_permissions(tmp_path):
    import os

    atomic_write_text(tmp_path / "a.txt", "x")
    mode = (tmp_path / "a.txt").stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask
