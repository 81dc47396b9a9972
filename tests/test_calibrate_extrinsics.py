"""Extrinsics + bundle adjustment on synthetic rigs with known cameras (projected board corners with
noise, so the test is fast; the rendered-image path is tested in test_calibrate_board*.py and the
bench renders the full 12-camera ring)."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.calibrate.boards import Board, CalibrationError
from roomcap.calibrate.camera import CameraRig
from roomcap.calibrate.extrinsics import ExtrinsicsConfig, calibrate_extrinsics
from roomcap.calibrate.intrinsics import IntrinsicsConfig, calibrate_intrinsics
from roomcap.calibrate.synthetic_boards import (
    board_trajectory,
    look_at,
    project_detections,
    ring_rig,
    views_near_camera,
)

BOARD = Board("charuco", (7, 5), 0.1, 0.075, "DICT_4X4_50")


def rig_errors(est: CameraRig, truth: CameraRig) -> tuple[float, float, float]:
    """Max focal error (fraction), rotation error (deg), centre error (m) after the best rigid alignment
    of the estimated world to the true one (rotation: chordal mean; translation: mean of centres)."""
    Ms = [truth[i].R.T @ est[i].R for i in range(len(truth))]  # world_t_from_world_e rotations
    U, _, Vt = np.linalg.svd(sum(Ms))
    R = U @ Vt
    ce, ct = est.centers(), truth.centers()
    t = (ct - ce @ R.T).mean(0)
    rot = [
        np.degrees(np.arccos(np.clip((np.trace((truth[i].R @ R).T @ est[i].R) - 1) / 2, -1, 1)))
        for i in range(len(truth))
    ]
    f = [abs(est[i].K[0, 0] / truth[i].K[0, 0] - 1) for i in range(len(truth))]
    return max(f), max(rot), float(np.linalg.norm(ce @ R.T + t - ct, axis=1).max())


def calibrate(board, rig, dets, refine="all", model="pinhole4", **kw):
    cams = [calibrate_intrinsics(board, dets[c.name], IntrinsicsConfig(model=model)).camera() for c in rig]
    return calibrate_extrinsics(board, cams, dets, ExtrinsicsConfig(refine_intrinsics=refine, **kw))


@pytest.mark.slow
def test_ring_of_12_cameras(rng):
    rig = ring_rig(12, radius_m=2.0, rng=rng)
    T = np.concatenate(
        [board_trajectory(BOARD, 40, rng, spread_m=0.6)]
        + [views_near_camera(BOARD, c, 20, rng, tilt_deg=60) for c in rig]
    )
    dets = project_detections(BOARD, rig, T, rng, noise_px=0.2)
    ext = calibrate(BOARD, rig, dets)
    f, rot, c = rig_errors(ext.rig, rig)
    assert f < 0.003  # measured 0.0003
    assert rot < 0.1  # measured 0.057 deg
    assert c < 0.005  # measured 0.5 mm
    assert ext.final_rms_px < 0.35  # noise 0.2 px per axis -> 0.28 px RMS; measured 0.28
    assert ext.links[0, 1] > 10 * max(
        1, ext.links[0, 6]
    )  # opposite cameras (almost) never see the printed side together


def four_camera_rig(rng) -> CameraRig:
    from roomcap.calibrate.camera import Camera

    cams = []
    for i, (pos, tgt) in enumerate(
        [
            ([2.0, -1.5, 1.6], [0, 0, 1]),
            ([2.0, 1.5, 1.6], [0, 0, 1]),
            ([0.0, -2.2, 1.8], [0, 0, 1]),
            ([-2.2, 2.2, 1.4], [-0.5, 1.2, 1.0]),
        ]
    ):
        R, t = look_at(pos, tgt)
        f = 900 * (1 + 0.03 * i)
        K = np.array([[f, 0, 640 + 3 * i], [0, f, 360 - 2 * i], [0, 0, 1]])
        cams.append(Camera(f"c{i}", (1280, 720), K, np.array([-0.1, 0.04, 0.0, 0.0]), "pinhole", R, t))
    return CameraRig(tuple(cams))


def test_four_cameras_one_weakly_linked(rng):
    """c3 sees the board together with another camera in 3 frames only."""
    rig = four_camera_rig(rng)
    shared = board_trajectory(BOARD, 30, rng, spread_m=0.4, yaw_range=(-0.6, 0.6))  # faces c0, c1, c2
    # 3 frames between c3 and c1, and c3's own views for its intrinsics
    link = board_trajectory(
        BOARD, 3, rng, center_m=(0.0, 0.8, 1.0), spread_m=0.3, tilt_deg=30, yaw_range=(1.6, 2.2)
    )
    T = np.concatenate([shared, link] + [views_near_camera(BOARD, c, 20, rng, tilt_deg=60) for c in rig])
    dets = project_detections(BOARD, rig, T, rng, noise_px=0.2)
    ext = calibrate(BOARD, rig, dets)
    links3 = ext.links[3, :3]
    assert 1 <= links3.max() <= 6, links3  # weakly linked; measured [0 5 5]
    f, rot, c = rig_errors(ext.rig, rig)
    assert f < 0.003  # measured 0.0003
    assert rot < 0.1  # measured 0.057 deg (c3: pose from 5+5 shared frames)
    assert c < 0.005  # measured 1.7 mm


def test_unlinked_cameras_name_the_groups(rng):
    rig = four_camera_rig(rng)
    shared = board_trajectory(BOARD, 20, rng, spread_m=0.4, yaw_range=(-0.6, 0.6))
    T = np.concatenate([shared] + [views_near_camera(BOARD, c, 12, rng, tilt_deg=60) for c in rig])
    mask = np.ones((4, len(T)), bool)
    mask[3, :56] = False  # c3 sees only its own close-up views: never together with the others
    mask[:3, 20 + 36 :] = False
    dets = project_detections(BOARD, rig, T, rng, visible_mask=mask)
    with pytest.raises(CalibrationError) as e:
        calibrate(BOARD, rig, dets, refine="none")
    msg = str(e.value)
    assert "[c0, c1, c2]" in msg and "[c3]" in msg and "Record a clip" in msg


def test_world_frame_from_floor_board(rng):
    rig = four_camera_rig(rng)
    shared = board_trajectory(BOARD, 25, rng, spread_m=0.4, yaw_range=(-0.6, 0.6))
    # frame 25: the board lies face up on the floor, seen from above by c0..c2
    floor = np.eye(4)
    floor[:3, :3] = np.diag([1.0, -1.0, -1.0])
    floor[:3, 3] = [-0.3, 0.2, 0.0]
    T = np.concatenate(
        [shared, floor[None]] + [views_near_camera(BOARD, c, 15, rng, tilt_deg=60) for c in rig]
    )
    dets = project_detections(BOARD, rig, T, rng, noise_px=0.2)
    assert 25 in dets["c0"].frames
    ext = calibrate(BOARD, rig, dets, world="board:25")
    # world = board on the floor: origin at the board's first corner, z up -> equals the true world shifted
    shift = floor[:3, 3]
    err = np.linalg.norm(ext.rig.centers() - (rig.centers() - shift), axis=1).max()
    assert err < 0.01  # measured 2 mm
    assert ext.world == "board:25"


def test_opencv_stereo_pairs_match_stereo_calibrate(tmp_path):
    """OpenCV's stereo chessboard pairs (9x6; corner order differs between left and right in 2 pairs):
    with the same intrinsics, our extrinsics equal cv2.stereoCalibrate's (CALIB_FIX_INTRINSIC)."""
    import cv2
    from conftest import need_shared

    from roomcap.calibrate.detect import detect_all, discover_recording

    d = need_shared("data", "opencv", "stereo_chessboard")
    board = Board("checkerboard", (9, 6), 1.0)  # in squares, as OpenCV's sample
    dets = detect_all(board, [s for s in discover_recording(d) if s.name in ("left", "right")], tmp_path)
    intr = {
        n: calibrate_intrinsics(board, dets[n], IntrinsicsConfig(min_frames=4)).camera()
        for n in ("left", "right")
    }
    ext = calibrate_extrinsics(
        board, [intr["left"], intr["right"]], dets, ExtrinsicsConfig(world="camera:left")
    )
    assert ext.links[0, 1] == 13 and ext.final_rms_px < 0.3  # measured 0.217 px, all 13 pairs consistent
    # reference: stereoCalibrate on the same corners, the right view renumbered where our rig says so
    obj = board.object_points().astype(np.float32).reshape(1, -1, 3)
    L, R_ = [], []
    right = ext.rig["right"]
    for f in sorted(set(dets["left"].seen_frames()) & set(dets["right"].seen_frames())):
        xl = dets["left"].xy_px[list(dets["left"].frames).index(f)]
        xr = dets["right"].xy_px[list(dets["right"].frames).index(f)]
        _, rv, tv = cv2.solvePnP(obj, xl.astype(np.float32), intr["left"].K, intr["left"].dist)
        X = obj.reshape(-1, 3) @ cv2.Rodrigues(rv)[0].T + tv.ravel()  # in the left (= world) frame
        if (
            np.linalg.norm(right.project(X) - xr, axis=1).mean()
            > np.linalg.norm(right.project(X[::-1]) - xr, axis=1).mean()
        ):
            xr = xr[::-1].copy()
        L.append(xl.astype(np.float32).reshape(1, -1, 2))
        R_.append(xr.astype(np.float32).reshape(1, -1, 2))
    rms, *_, R, T, _, _ = cv2.stereoCalibrate(
        [obj] * len(L),
        L,
        R_,
        intr["left"].K.copy(),
        intr["left"].dist.copy(),
        intr["right"].K.copy(),
        intr["right"].dist.copy(),
        (640, 480),
        None,
        None,
        flags=cv2.CALIB_FIX_INTRINSIC,
    )
    dR = np.degrees(np.arccos(np.clip((np.trace(R.T @ right.R) - 1) / 2, -1, 1)))
    assert dR < 0.05  # measured 0.000 deg
    assert (
        abs(np.linalg.norm(right.t) / np.linalg.norm(T) - 1) < 0.002
    )  # measured 0.000 %; baseline 3.33 squares
