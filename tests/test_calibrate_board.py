"""Boards, detection on rendered images, the diagnosis of wrong board files, the detection cache and
the messages for bad recordings."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from conftest import need_shared

from roomcap.calibrate import detect as detect_mod
from roomcap.calibrate.boards import Board, CalibrationError, load_board, save_board
from roomcap.calibrate.calibration import CalibrationConfig, calibrate_recording
from roomcap.calibrate.detect import detect_all, detect_frame, diagnose_board, discover_recording
from roomcap.calibrate.synthetic_boards import BoardRenderer, board_trajectory, ring_rig, write_recording
from roomcap.core.errors import FormatError

CHARUCO = Board("charuco", (7, 5), 0.1, 0.075, "DICT_4X4_50")


def test_board_toml_round_trip_and_errors(tmp_path):
    for b in (
        CHARUCO,
        Board("checkerboard", (9, 6), 0.025),
        Board("aruco_grid", (4, 3), 0.05, 0.05, marker_separation_m=0.01),
        CHARUCO.replace(legacy_pattern=True, inverted=True),
    ):
        save_board(tmp_path / "b.toml", b)
        assert load_board(tmp_path / "b.toml") == b
    (tmp_path / "bad.toml").write_text(
        'schema = "board/1"\nkind = "charuco"\nsquares = [5, 7]\nsquare_size_m = 0.04\n'
        'marker_size_m = 0.03\ndictionary = "DICT_4X4_50"\ncolour = "red"\n'
    )
    with pytest.raises(FormatError, match="unknown keys"):
        load_board(tmp_path / "bad.toml")
    (tmp_path / "bad2.toml").write_text(
        'schema = "board/1"\nkind = "charuco"\nsquares = [5, 7]\nsquare_size_m = 0.04\n'
        'marker_size_m = 0.03\ndictionary = "DICT_4X4_51"\n'
    )
    with pytest.raises(FormatError, match="unknown dictionary"):
        load_board(tmp_path / "bad2.toml")


def test_reads_caliscope_charuco_toml():
    b = load_board(need_shared("data", "caliscope", "charuco_calibration", "charuco.toml"))
    assert (b.kind, b.grid, b.dictionary, b.inverted) == ("charuco", (4, 5), "DICT_4X4_1000", True)
    assert b.square_size_m == pytest.approx(0.054) and b.marker_size_m == pytest.approx(0.0405)
    assert b.n_points == 12


def _views(board, n, rng, size=(640, 480)):
    rig = ring_rig(3, radius_m=1.6, size_wh=size, rng=rng)
    T = board_trajectory(board, n, rng, spread_m=0.3, yaw_range=(-0.4, 0.4))
    return rig[0], T


@pytest.mark.parametrize(
    ("board", "bound_px"),
    [
        (CHARUCO, 0.3),  # measured median 0.08 px
        (Board("checkerboard", (8, 5), 0.08), 0.3),  # measured 0.05 px
        # marker corners are L-corners, biased by blur: measured 0.39 px
        (Board("aruco_grid", (4, 3), 0.12, 0.12, "DICT_5X5_100", marker_separation_m=0.03), 0.6),
    ],
    ids=["charuco", "checkerboard", "aruco_grid"],
)
def test_detection_on_rendered_views_is_subpixel(board, bound_px, rng):
    cam, T = _views(board, 6, rng)
    r = BoardRenderer(board)
    errs, n_det = [], 0
    for Tk in T:
        if not r.visible(cam, Tk):
            continue
        xy = detect_frame(board, r.render(cam, Tk, rng))
        p = cam.project(board.object_points() @ Tk[:3, :3].T + Tk[:3, 3])
        m = np.isfinite(xy[:, 0])
        n_det += m.any()
        errs.append(np.linalg.norm(xy[m] - p[m], axis=1))
    e = np.concatenate(errs)
    assert n_det >= 4
    assert np.median(e) < bound_px


def test_legacy_pattern_and_inverted_colours_are_diagnosed(tmp_path, rng):
    printed = Board("charuco", (5, 6), 0.1, 0.075, "DICT_4X4_50", legacy_pattern=True, inverted=True)
    cam, T = _views(printed, 4, rng)
    r = BoardRenderer(printed)
    (tmp_path / "cam").mkdir()
    for k, Tk in enumerate(T):
        cv2.imwrite(str(tmp_path / "cam" / f"f{k}.png"), r.render(cam, Tk, rng))
    declared = printed.replace(legacy_pattern=False, inverted=False)
    src = discover_recording(tmp_path)
    img = cv2.imread(str(tmp_path / "cam" / "f0.png"), 0)
    assert np.isfinite(detect_frame(printed, img)[:, 0]).sum() > 10
    assert not np.isfinite(detect_frame(declared, img)[:, 0]).any()
    d = diagnose_board(declared, src)
    assert d.board is not None and d.board.legacy_pattern and d.board.inverted
    assert "legacy_pattern" in d.message and "inverted" in d.message


def _recording(tmp_path, board, n_cams=3, n_frames=10, rng=None, size=(640, 480)):
    rng = rng or np.random.default_rng(1)
    rig = ring_rig(n_cams, radius_m=1.8, size_wh=size, rng=rng)
    T = board_trajectory(
        board,
        n_frames,
        rng,
        spread_m=0.35,
        yaw_range=(-0.5, 2 * np.pi / n_cams * (n_cams - 1) + 0.5),
        tilt_deg=30,
    )
    write_recording(board, rig, T, tmp_path / "rec", rng)
    return rig


@pytest.mark.slow
def test_wrong_dictionary_is_diagnosed_and_detections_are_cached(tmp_path, monkeypatch, caplog):
    printed = Board("charuco", (5, 7), 0.08, 0.06, "DICT_5X5_100")
    _recording(tmp_path, printed, n_cams=2, n_frames=8)
    wrong = tmp_path / "board.toml"
    save_board(wrong, printed.replace(dictionary="DICT_4X4_50"))
    out = tmp_path / "out" / "rig.toml"
    with pytest.raises(CalibrationError) as e:
        calibrate_recording(tmp_path / "rec", wrong, out, CalibrationConfig(min_frames=3))
    msg = str(e.value)
    assert "DICT_5X5_" in msg and "run again" in msg and "cached" in msg
    # the user fixes the board file: the next run must not detect again
    save_board(wrong, printed)
    calls = []
    real = detect_mod.detect_camera
    monkeypatch.setattr(detect_mod, "detect_camera", lambda *a, **k: calls.append(a) or real(*a, **k))
    with caplog.at_level(logging.INFO):
        dets = detect_all(printed, discover_recording(tmp_path / "rec"), out.parent / "detections")
    assert calls == [] and "loaded from cache" in caplog.text
    assert all(len(d.seen_frames()) > 0 for d in dets.values())


def test_bad_recordings_say_what_to_do(tmp_path, rng):
    board = CHARUCO
    _recording(tmp_path, board, n_cams=2, n_frames=12)
    rec = tmp_path / "rec"
    # a camera that never sees the board
    (rec / "cam_blind").mkdir()
    for k in range(12):
        cv2.imwrite(str(rec / "cam_blind" / f"frame_{k:05d}.png"), np.full((480, 640), 90, np.uint8))
    with pytest.raises(CalibrationError) as e:
        calibrate_recording(rec, board, tmp_path / "o1" / "rig.toml", CalibrationConfig(min_frames=3))
    assert "cam_blind" in str(e.value) and "--exclude cam_blind" in str(e.value)
    # ... and excluding it works past that point (too few frames for the others here: a clear message too)
    with pytest.raises(CalibrationError) as e:
        calibrate_recording(
            rec, board, tmp_path / "o1" / "rig.toml", CalibrationConfig(exclude=("cam_blind",), min_frames=30)
        )
    assert (
        "only" in str(e.value) and "at least 30" in str(e.value) and "Record the board again" in str(e.value)
    )
    # resolution changing mid-recording
    cv2.imwrite(str(rec / "cam_blind" / "frame_00003.png"), np.full((240, 320), 90, np.uint8))
    with pytest.raises(CalibrationError, match="resolution changed mid-recording.*640x480 to 320x240"):
        detect_all(board, [s for s in discover_recording(rec) if s.name == "cam_blind"], tmp_path / "c")


def test_unopenable_video_keeps_the_other_cameras(tmp_path, rng):
    rec = tmp_path / "rec"
    rec.mkdir()
    cam, T = _views(CHARUCO, 3, rng)
    r = BoardRenderer(CHARUCO)
    vw = cv2.VideoWriter(str(rec / "good.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480), False)
    for Tk in T:
        vw.write(r.render(cam, Tk, rng))
    vw.release()
    (rec / "broken.mp4").write_bytes(b"this is not a video")
    with pytest.raises(CalibrationError) as e:
        detect_all(CHARUCO, discover_recording(rec), tmp_path / "cache")
    assert (
        "cannot open video" in str(e.value)
        and "ffmpeg" in str(e.value)
        and "['good'] are cached" in str(e.value)
    )
    assert (tmp_path / "cache" / "good.npz").exists()


def test_wrong_grid_points_at_the_board_file(tmp_path):
    """A board file declaring fewer squares than the print said 'record the board again'."""
    printed = Board("charuco", (5, 7), 0.08, 0.06, "DICT_5X5_100")
    _recording(tmp_path, printed, n_cams=2, n_frames=8)
    wrong = tmp_path / "board.toml"
    save_board(wrong, printed.replace(grid=(4, 5)))
    with pytest.raises(CalibrationError) as e:
        calibrate_recording(
            tmp_path / "rec", wrong, tmp_path / "out" / "rig.toml", CalibrationConfig(min_frames=6)
        )
    msg = str(e.value)
    assert "more squares than the board file says" in msg and str(wrong) in msg, msg
    assert "Record the board again" not in msg
