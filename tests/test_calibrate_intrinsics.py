"""Intrinsics: synthetic round trips per lens model, the too-few-frames message, and real recordings
(caliscope ChArUco against caliscope's own RMS, Pose2Sim checkerboards against Qualisys), plus the
calibrate-run CLI end to end on a small rendered recording."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from conftest import need_shared

from roomcap.calibrate.boards import Board, CalibrationError, load_board
from roomcap.calibrate.camera import Camera, CameraRig
from roomcap.calibrate.detect import detect_all, discover_recording
from roomcap.calibrate.intrinsics import IntrinsicsConfig, calibrate_intrinsics, select_frames
from roomcap.calibrate.synthetic_boards import look_at, project_detections, views_near_camera

BOARD = Board("charuco", (7, 5), 0.1, 0.075, "DICT_4X4_50")


@pytest.mark.parametrize(
    ("model", "dist"),
    [
        ("pinhole", [-0.2, 0.08, 0.001, -0.001, -0.01]),
        ("rational", [0.3, -0.1, 0.0005, 0.0005, 0.01, 0.5, -0.05, 0.02]),
        ("fisheye", [0.05, -0.02, 0.01, -0.003]),
    ],
)
def test_intrinsics_round_trip(model, dist, rng):
    R, t = look_at([0, -2, 1], [0, 0, 1])
    K = np.array([[700.0, 0, 652], [0, 700.0, 358], [0, 0, 1]])
    cam = Camera("c", (1280, 720), K, np.array(dist), "fisheye" if model == "fisheye" else "pinhole", R, t)
    T = views_near_camera(BOARD, cam, 30, rng, tilt_deg=50)
    det = project_detections(BOARD, CameraRig((cam,)), T, rng, noise_px=0.2)["c"]
    r = calibrate_intrinsics(BOARD, det, IntrinsicsConfig(model=model))
    assert abs(r.K[0, 0] / 700 - 1) < 0.003  # measured 0.0002-0.0009
    assert np.abs(r.K[:2, 2] - K[:2, 2]).max() < 3.0  # measured 0.3-1.2 px
    assert r.rms_px < 0.35  # 0.2 px per axis -> 0.28 px; measured 0.27
    assert 0.2 < r.coverage_fraction <= 1.0
    assert r.camera().model == ("fisheye" if model == "fisheye" else "pinhole")


def test_frame_selection_spreads_over_the_image(rng):
    xy = np.full((50, 4, 2), np.nan)
    xy[:40] = rng.uniform([600, 300], [680, 380], (40, 4, 2))  # many frames in the centre
    xy[40:] = rng.uniform([0, 0], [1280, 720], (10, 4, 2))  # a few spread out
    sel = select_frames(xy, (1280, 720), 12)
    assert len(sel) == 12 and (sel >= 40).sum() >= 8  # the spread-out frames are chosen first


def test_too_few_frames_says_what_to_record(rng):
    R, t = look_at([0, -2, 1], [0, 0, 1])
    cam = Camera(
        "c", (1280, 720), np.array([[700.0, 0, 640], [0, 700, 360], [0, 0, 1]]), np.zeros(5), "pinhole", R, t
    )
    det = project_detections(BOARD, CameraRig((cam,)), views_near_camera(BOARD, cam, 3, rng), rng)["c"]
    with pytest.raises(CalibrationError, match=r"only 3 of .*at least 6.*Record the board again"):
        calibrate_intrinsics(BOARD, det)


@pytest.mark.slow
def test_caliscope_recording_rms_no_worse_than_caliscope(tmp_path):
    rec = need_shared("data", "caliscope", "charuco_calibration")
    board = load_board(rec / "charuco.toml")
    ref = tomllib.loads((rec / "camera_array.toml").read_text())["cameras"]
    # every 3rd frame keeps the test short; the bench runs the whole recording
    dets = detect_all(board, discover_recording(rec / "calibration" / "extrinsic"), tmp_path, max_frames=37)
    for name, d in dets.items():
        r = calibrate_intrinsics(board, d, IntrinsicsConfig(min_frames=6))
        assert r.rms_px <= ref[name.split("_")[1]]["error"], name  # measured 0.10-0.25 vs 0.33-0.54
        assert abs(r.K[0, 0] / ref[name.split("_")[1]]["matrix"][0][0] - 1) < 0.05  # measured < 2 %


@pytest.mark.slow
def test_pose2sim_checkerboard_against_qualisys(tmp_path):
    from roomcap.calibrate.formats import import_rig

    d = need_shared("data", "pose2sim", "demo-wheel-0.10.49", "Demo_SinglePerson", "calibration")
    q = import_rig(d / "Calib.qca.txt", "qualisys")
    board = Board("checkerboard", (4, 7), 0.06)
    src = [s for s in discover_recording(d / "intrinsics") if s.name == "int_cam04_img"]
    det = detect_all(board, src, tmp_path)["int_cam04_img"]
    assert det.size_wh == (1088, 1920) == q["cam04"].size_wh  # portrait, as the Qualisys field of view
    r = calibrate_intrinsics(board, det, IntrinsicsConfig(min_frames=4))
    assert abs(r.K[0, 0] / q["cam04"].K[0, 0] - 1) < 0.005  # measured 0.02 % (all four cameras: <= 0.24 %)
    assert r.rms_px < 1.0  # measured 0.58


@pytest.mark.slow
def test_cli_calibrates_a_rendered_recording(tmp_path, capsys):
    from roomcap.calibrate.boards import save_board
    from roomcap.calibrate.cli import main
    from roomcap.calibrate.synthetic_boards import board_trajectory, write_recording

    rng = np.random.default_rng(3)
    cams = []
    for i, a in enumerate((-0.7, 0.0, 0.7)):  # three cameras on an arc, all looking at the board area
        R, t = look_at([1.8 * np.cos(a), 1.8 * np.sin(a), 1.5], [0, 0, 1])
        cams.append(
            Camera(
                f"cam{i:02d}",
                (640, 480),
                np.array([[560.0 + 10 * i, 0, 322], [0, 560.0 + 10 * i, 238], [0, 0, 1]]),
                np.array([-0.1, 0.03, 0, 0, 0]),
                "pinhole",
                R,
                t,
            )
        )
    rig = CameraRig(tuple(cams))
    T = np.concatenate(
        [board_trajectory(BOARD, 10, rng, spread_m=0.3, yaw_range=(-0.5, 0.5), tilt_deg=30)]
        + [views_near_camera(BOARD, c, 8, rng, tilt_deg=45) for c in rig]
    )
    write_recording(BOARD, rig, T, tmp_path / "rec", rng)
    save_board(tmp_path / "board.toml", BOARD)
    out = tmp_path / "calib" / "rig.toml"
    code = main(
        [
            "calibrate",
            str(tmp_path / "rec"),
            "--board",
            str(tmp_path / "board.toml"),
            "--out",
            str(out),
            "--world",
            "camera:cam00",
        ]
    )
    assert code == 0
    est = CameraRig.load(out)
    assert est.names == rig.names
    for f in ("report.toml", "layout.png", "coverage.png"):
        assert (tmp_path / "calib" / "report" / f).stat().st_size > 1000
    rep = tomllib.loads((tmp_path / "calib" / "report" / "report.toml").read_text())
    assert rep["bundle_adjustment"]["final_rms_px"] < 1.0 and len(rep["pairs"]) == 3
    # relative geometry: distance between cameras 0 and 1 (true 1.23 m)
    d_est = np.linalg.norm(est.centers()[0] - est.centers()[1])
    d_true = np.linalg.norm(rig.centers()[0] - rig.centers()[1])
    assert abs(d_est - d_true) < 0.03  # measured 3 mm
    assert "int.RMS" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    assert "RECORDING is a folder" in capsys.readouterr().out
