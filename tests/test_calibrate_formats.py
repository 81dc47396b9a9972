"""Importers/exporters: a round trip per format, the peers' own readers, bad input, the CLI."""

from __future__ import annotations

import numpy as np
import pytest
import tomli_w

from roomcap.calibrate.camera import Camera, CameraRig, rotation_from_rvec
from roomcap.calibrate.cli import main
from roomcap.calibrate.formats import (
    ImportOptions,
    _rotate_image_cw,
    detect_format,
    export_rig,
    import_rig,
    pad_dist,
)
from roomcap.core.errors import FormatError


def random_rig(rng, n: int = 4, dists=(5, 8, 4, 14, 0, 12), fisheye: bool = False) -> CameraRig:
    cams = []
    for i in range(n):
        nd = dists[i % len(dists)]
        model = "fisheye" if fisheye and i == n - 1 else "pinhole"
        d = rng.normal(0, 0.01, 4 if model == "fisheye" else nd)
        K = np.array(
            [
                [rng.uniform(800, 1200), 0, rng.uniform(600, 700)],
                [0, rng.uniform(800, 1200), rng.uniform(300, 400)],
                [0, 0, 1.0],
            ]
        )
        R = rotation_from_rvec(rng.normal(0, 0.4, 3))
        cams.append(
            Camera(f"cam_{i}", (1280, 720), K, d, model, R, np.array([0, 0, 3.5]) + rng.normal(0, 0.3, 3))
        )
    return CameraRig(tuple(cams))


def assert_same_rig(a: CameraRig, b: CameraRig, atol: float = 1e-12, dist_len_may_grow: bool = False):
    assert a.names == b.names
    for x, y in zip(a, b, strict=True):
        assert x.size_wh == y.size_wh and x.model == y.model
        np.testing.assert_allclose(x.K, y.K, atol=atol)
        np.testing.assert_allclose(x.R, y.R, atol=atol)
        np.testing.assert_allclose(x.t, y.t, atol=atol)
        if dist_len_may_grow:
            np.testing.assert_allclose(
                pad_dist(x.dist)[: y.dist.size], y.dist[: max(x.dist.size, 4)], atol=atol
            )
            assert not y.dist[x.dist.size :].any()
        else:
            np.testing.assert_allclose(x.dist, y.dist, atol=atol)


# ----------------------------------------------------------------------------- aniposelib / Pose2Sim


def test_aniposelib_round_trip(tmp_path, rng):
    rig = random_rig(rng, 4, fisheye=True)
    p = tmp_path / "calibration.toml"
    export_rig(rig, p, "aniposelib")
    assert detect_format(p) == "aniposelib"
    back = import_rig(p)
    # cameras without distortion are written with 5 zeros
    assert_same_rig(rig, back, atol=1e-12, dist_len_may_grow=True)
    X = rng.uniform(-1, 1, (100, 3))
    assert np.abs(rig.project(X) - back.project(X)).max() < 1e-9


@pytest.mark.slow
def test_aniposelib_library_reads_our_export(tmp_path, rng):
    """aniposelib itself loads the file, keeps the order for 12 cameras and projects identically."""
    cameras = pytest.importorskip("aniposelib.cameras")
    rig = random_rig(rng, 12, dists=(5,), fisheye=True)
    p = tmp_path / "calibration.toml"
    export_rig(rig, p, "aniposelib")
    cg = cameras.CameraGroup.load(str(p))
    assert cg.get_names() == rig.names  # keys cam_00..cam_11: aniposelib sorts them
    X = rng.uniform(-1, 1, (100, 3))
    assert np.abs(cg.project(X) - rig.project(X)).max() < 1e-6  # measured 1e-12 px


def test_pose2sim_style_toml(tmp_path):
    """Pose2Sim writes floats for size, 4 distortions, Rodrigues rotation and a fisheye flag."""
    text = """[cam_1]
name = "cam_01"
size = [ 1088.0, 1920.0]
matrix = [ [ 1681.2, 0.0, 532.9], [ 0.0, 1681.0, 948.1], [ 0.0, 0.0, 1.0]]
distortions = [ -0.0007, 0.002, 9.5e-06, 1.0e-05]
rotation = [ 1.68, 1.04, -0.41]
translation = [ 0.32, 0.95, 2.89]
fisheye = false

[metadata]
adjusted = false
error = 0.0
"""
    p = tmp_path / "Calib.toml"
    p.write_text(text)
    rig = import_rig(p)
    c = rig["cam_01"]
    assert c.size_wh == (1088, 1920) and c.dist.size == 4 and c.model == "pinhole"
    np.testing.assert_allclose(c.R, rotation_from_rvec([1.68, 1.04, -0.41]))
    mm = import_rig(p, options=ImportOptions(scale_to_m=0.001))
    np.testing.assert_allclose(mm[0].t, c.t / 1000)


@pytest.mark.parametrize(
    "edit,field",
    [
        (lambda t: t.pop("matrix"), "[cam_0].matrix"),
        (lambda t: t.update(matrix=[[1.0, 0.0], [0.0, 1.0]]), "[cam_0].matrix"),
        (lambda t: t.update(rotation=[0.1, 0.2]), "[cam_0].rotation"),
        (lambda t: t.update(rotation=[[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]]), "[cam_0].rotation"),
        (lambda t: t.update(size=[1280.5, 720]), "[cam_0].size"),
        (lambda t: t.update(distortions=[0.0] * 15), "[cam_0].distortions"),
        (lambda t: t.pop("translation"), "[cam_0].translation"),
    ],
)
def test_aniposelib_bad_input(tmp_path, rng, edit, field):
    p = tmp_path / "calibration.toml"
    export_rig(random_rig(rng, 2), p, "aniposelib")
    import tomllib

    data = tomllib.loads(p.read_text())
    edit(data["cam_0"])
    p.write_text(tomli_w.dumps(data))
    with pytest.raises(FormatError) as ei:
        import_rig(p, "aniposelib")
    assert ei.value.path == str(p) and ei.value.field == field, str(ei.value)


# ----------------------------------------------------------------------------- Qualisys


def qca_text(
    rig: CameraRig, left: int = 16, top: int = 8, viewrotation: int = 0, truncate: bool = False
) -> str:
    """A QTM calibration for ``rig`` (the inverse of read_qualisys' conventions)."""
    cams = []
    for c in rig:
        M = (np.diag([1.0, -1.0, -1.0]) @ c.R).tolist()  # rows: camera axes (x right, y up, along -z)
        pos = (c.center * 1000.0).tolist()
        w, h = c.size_wh
        k1, k2, p1, p2, k3 = np.r_[pad_dist(c.dist), 0.0][:5].tolist()
        fx, fy, cx, cy = (float(v) for v in (c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]))
        rs = " ".join(f'r{i + 1}{j + 1}="{M[i][j]!r}"' for i in range(3) for j in range(3))
        cams.append(
            f'<camera active="1" model="Miqus Video" serial="{c.name}" viewrotation="{viewrotation}">'
            f'<fov_video left="{left}" top="{top}" right="{left + w - 1}" bottom="{top + h - 1}"/>'
            f'<transform x="{pos[0]!r}" y="{pos[1]!r}" z="{pos[2]!r}" {rs}/>'
            f'<intrinsic focalLengthU="{fx * 64!r}" focalLengthV="{fy * 64!r}" '
            f'centerPointU="{(cx + left) * 64!r}" centerPointV="{(cy + top) * 64!r}" '
            f'radialDistortion1="{k1!r}" radialDistortion2="{k2!r}" radialDistortion3="{k3!r}" '
            f'tangentalDistortion1="{p1!r}" tangentalDistortion2="{p2!r}" skew="0"/></camera>'
        )
    cams.append(
        '<camera active="1" model="Miqus M3" serial="marker1"><fov_video left="0" top="0" right="9" '
        'bottom="9"/></camera>'
    )
    text = (
        "<?xml version='1.0' encoding='ASCII'?>\n<calibration><cameras>"
        + "".join(cams)
        + "</cameras></calibration>"
    )
    return text[: len(text) // 2] if truncate else text


def test_qualisys_round_trip(tmp_path, rng):
    rig = random_rig(rng, 3, dists=(5,))
    p = tmp_path / "Calib.qca.txt"
    p.write_text(qca_text(rig))
    assert detect_format(p) == "qualisys"
    back = import_rig(p)  # the marker camera is skipped
    assert_same_rig(rig, back, atol=1e-9)
    with_markers = pytest.raises(FormatError)  # the marker camera has no intrinsics
    with with_markers:
        import_rig(p, options=ImportOptions(include_marker_cameras=True))


def test_qualisys_distortion_scale_and_video_size(tmp_path, rng):
    rig = random_rig(rng, 2, dists=(5,))
    p = tmp_path / "c.qca.txt"
    p.write_text(qca_text(rig))
    pose2sim_like = import_rig(p, options=ImportOptions(distortion_scale=1 / 64))
    np.testing.assert_allclose(pose2sim_like[0].dist, rig[0].dist / 64)
    cropped = import_rig(p, options=ImportOptions(image_size_wh=(1272, 720)))
    assert cropped[0].size_wh == (1272, 720)
    np.testing.assert_array_equal(cropped[0].K, import_rig(p)[0].K)
    per_cam = import_rig(p, options=ImportOptions(image_size_wh={"cam_1": (1272, 720)}))
    assert [c.size_wh for c in per_cam] == [(1280, 720), (1272, 720)]
    with pytest.raises(FormatError, match="cam_9"):
        import_rig(p, options=ImportOptions(image_size_wh={"cam_9": (1272, 720)}))


@pytest.mark.parametrize("quarter_turns", [1, 2, 3])
def test_rotate_image_cw(rng, quarter_turns):
    """The rotated camera sees exactly the rotated image: (u, v) -> (h-1-v, u) per clockwise turn."""
    cam = random_rig(rng, 1, dists=(5,))[0]
    X = rng.uniform(-0.5, 0.5, (100, 3))
    uv = cam.project(X)
    w, h = cam.size_wh
    for _ in range(quarter_turns):
        uv = np.stack([h - 1 - uv[:, 1], uv[:, 0]], axis=1)
        w, h = h, w
    rot = _rotate_image_cw(cam, quarter_turns)
    assert rot.size_wh == (w, h)
    assert np.abs(rot.project(X) - uv).max() < 1e-8
    np.testing.assert_allclose(rot.center, cam.center, atol=1e-12)


def test_qualisys_viewrotation(tmp_path, rng):
    rig = random_rig(rng, 1, dists=(5,))
    p = tmp_path / "c.qca.txt"
    p.write_text(qca_text(rig, viewrotation=90))
    assert_same_rig(rig, import_rig(p), atol=1e-9)  # default: sensor orientation, like Pose2Sim
    applied = import_rig(p, options=ImportOptions(view_rotation="apply"))
    assert applied[0].size_wh == (720, 1280)
    assert_same_rig(CameraRig((_rotate_image_cw(rig[0], 1),)), applied, atol=1e-9)


def test_qualisys_bad_input(tmp_path, rng):
    rig = random_rig(rng, 1, dists=(5,))
    p = tmp_path / "c.qca.txt"
    p.write_text(qca_text(rig, truncate=True))
    with pytest.raises(FormatError, match="not valid XML") as ei:
        import_rig(p)
    assert ei.value.path == str(p)
    p.write_text(qca_text(rig).replace(' r11="', ' rXX="', 1))
    with pytest.raises(FormatError) as ei:
        import_rig(p)
    assert ei.value.field == "camera[0] (cam_0).transform.r11"
    p.write_text(qca_text(rig).replace(' r11="', ' r11="2', 1))
    with pytest.raises(FormatError, match="not a rotation") as ei:
        import_rig(p)
    assert ei.value.field == "camera[0] (cam_0).transform.r11..r33"


# ----------------------------------------------------------------------------- caliscope


def caliscope_tables(rig: CameraRig, old: bool) -> dict:
    out = {}
    for i, c in enumerate(rig):
        tab = {
            "size": list(c.size_wh),
            "matrix": c.K.tolist(),
            "distortions": c.dist.tolist(),
            "rotation": c.R.tolist(),
            "translation": c.t.tolist(),
            "rotation_count": 0,
            "ignore": False,
        }
        if old:
            out[f"cam_{i}"] = tab | {"port": i}
        else:
            out[str(i)] = tab | {"cam_id": i}
    return out if old else {"cameras": out}


@pytest.mark.parametrize("old", [False, True])
def test_caliscope_round_trip(tmp_path, rng, old):
    rig = random_rig(rng, 3, dists=(5,))
    data = caliscope_tables(rig, old)
    if old:
        data = {"fps_recording": 24, **data, "charuco": {"columns": 4}}
    p = tmp_path / ("config.toml" if old else "camera_array.toml")
    p.write_text(tomli_w.dumps(data))
    assert detect_format(p) == "caliscope"
    assert_same_rig(rig, import_rig(p), atol=0)


def test_caliscope_ignored_and_bad(tmp_path, rng):
    rig = random_rig(rng, 3, dists=(5,))
    data = caliscope_tables(rig, old=False)
    data["cameras"]["1"]["ignore"] = True
    p = tmp_path / "camera_array.toml"
    p.write_text(tomli_w.dumps(data))
    assert import_rig(p).names == ["cam_0", "cam_2"]
    data["cameras"]["2"]["rotation"] = (np.array(data["cameras"]["2"]["rotation"]) * 1.01).tolist()
    p.write_text(tomli_w.dumps(data))
    with pytest.raises(FormatError, match="not a rotation") as ei:
        import_rig(p)
    assert ei.value.field == "[cameras.2].rotation"
    del data["cameras"]["2"]["translation"]
    p.write_text(tomli_w.dumps(data))
    with pytest.raises(FormatError, match="extrinsic calibration") as ei:
        import_rig(p)
    assert ei.value.field == "[cameras.2].translation"


# ----------------------------------------------------------------------------- EasyMocap


def test_easymocap_round_trip(tmp_path, rng):
    rig = random_rig(rng, 4)
    written = export_rig(rig, tmp_path / "calib", "easymocap")
    assert [w.name for w in written] == ["intri.yml", "extri.yml"]
    for src in (tmp_path / "calib", written[0], written[1]):
        assert detect_format(src) == "easymocap"
        assert_same_rig(rig, import_rig(src), atol=1e-15, dist_len_may_grow=True)


def test_easymocap_rodrigues_only_and_missing_size(tmp_path, rng):
    import cv2

    rig = random_rig(rng, 2, dists=(5,))
    fi = cv2.FileStorage(str(tmp_path / "intri.yml"), cv2.FILE_STORAGE_WRITE)
    fe = cv2.FileStorage(str(tmp_path / "extri.yml"), cv2.FILE_STORAGE_WRITE)
    for fs in (fi, fe):
        fs.write("names", rig.names)
    for c in rig:
        fi.write(f"K_{c.name}", c.K)
        fi.write(f"dist_{c.name}", c.dist.reshape(1, -1))
        fe.write(f"R_{c.name}", cv2.Rodrigues(c.R)[0])
        fe.write(f"T_{c.name}", c.t.reshape(3, 1))
    fi.release()
    fe.release()
    back = import_rig(tmp_path / "intri.yml", options=ImportOptions(image_size_wh=(1280, 720)))
    assert_same_rig(rig, back, atol=1e-12)
    guessed = import_rig(tmp_path / "intri.yml")
    assert guessed[0].size_wh == (round(2 * rig[0].K[0, 2]), round(2 * rig[0].K[1, 2]))


def test_easymocap_bad_input(tmp_path, rng):
    rig = random_rig(rng, 2, dists=(5,))
    export_rig(rig, tmp_path, "easymocap")
    text = (tmp_path / "extri.yml").read_text()
    start = text.index("T_cam_1:")
    (tmp_path / "extri.yml").write_text(text[:start])
    with pytest.raises(FormatError) as ei:
        import_rig(tmp_path)
    assert ei.value.field == "T_cam_1" and ei.value.path == str(tmp_path / "extri.yml")
    (tmp_path / "extri.yml").unlink()
    with pytest.raises(FormatError, match="same folder"):
        import_rig(tmp_path / "intri.yml")
    with pytest.raises(ValueError, match="fisheye"):
        export_rig(random_rig(rng, 2, fisheye=True), tmp_path / "fe", "easymocap")
    assert not (tmp_path / "fe" / "intri.yml").exists()


# ----------------------------------------------------------------------------- rig, detection, CLI


def test_rig_format_and_detection(tmp_path, rng):
    rig = random_rig(rng, 2)
    p = tmp_path / "rig.toml"
    export_rig(rig, p, "rig")
    assert detect_format(p) == "rig" and import_rig(p) == rig
    junk = tmp_path / "junk.toml"
    junk.write_text('title = "no cameras"\n')
    with pytest.raises(FormatError, match="--format"):
        detect_format(junk)
    with pytest.raises(ValueError, match="valid"):
        import_rig(p, "colmap")
    with pytest.raises(ValueError, match="valid"):
        ImportOptions.from_dict({"scale": 2})


def test_pad_dist():
    assert pad_dist([0.1]).tolist() == [0.1, 0, 0, 0]
    assert pad_dist(np.ones(6)).size == 8 and pad_dist(np.ones(13)).size == 14
    assert pad_dist(np.ones(5)).size == 5 and pad_dist([]).size == 0


def test_cli_import_export(tmp_path, rng, capsys):
    rig = random_rig(rng, 3, dists=(5,))
    qca = tmp_path / "Calib.qca.txt"
    qca.write_text(qca_text(rig))
    out = tmp_path / "session" / "calib" / "rig.toml"
    assert main(["import", str(qca), "--out", str(out)]) == 0
    back = CameraRig.load(out)
    assert_same_rig(rig, back, atol=1e-9)
    assert "qualisys" in out.read_text()  # the source is recorded
    anip = tmp_path / "anipose.toml"
    assert main(["export", str(out), "--format", "aniposelib", "--out", str(anip)]) == 0
    assert_same_rig(back, import_rig(anip), atol=1e-12)
    assert main(["export", str(out), "--format", "easymocap", "--out", str(tmp_path / "em")]) == 0
    assert (
        main(["import", str(tmp_path / "em"), "--format", "easymocap", "--out", str(tmp_path / "r2.toml")])
        == 0
    )
    assert main(["import", str(anip), "--out", str(tmp_path / "r3.toml"), "--image-size", "1280x720"]) == 0
    args = ["--image-size", "1270x720", "--image-size", "cam_2=1272x720"]
    assert main(["import", str(qca), "--out", str(tmp_path / "r4.toml"), *args]) == 0
    assert [c.size_wh for c in CameraRig.load(tmp_path / "r4.toml")] == [
        (1270, 720),
        (1270, 720),
        (1272, 720),
    ]
    capsys.readouterr()


def test_cli_bad_input_writes_nothing(tmp_path, rng, capsys):
    rig = random_rig(rng, 1, dists=(5,))
    qca = tmp_path / "Calib.qca.txt"
    qca.write_text(qca_text(rig, truncate=True))
    out = tmp_path / "rig.toml"
    assert main(["import", str(qca), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(qca) in err and "not valid XML" in err
    assert not out.exists() and list(tmp_path.iterdir()) == [qca]
    with pytest.raises(SystemExit):
        main(["import", str(qca), "--out", str(out), "--image-size", "big"])
    capsys.readouterr()


def test_cli_subcommands_are_pluggable():
    from roomcap.calibrate import cli

    names = [f.__name__ for f in cli.SUBCOMMANDS]
    assert names[:2] == ["_add_import", "_add_export"]
    sub = cli.build_parser()._subparsers._group_actions[0]
    assert {"import", "export"} <= set(sub.choices)
