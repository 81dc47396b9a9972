"""Calibration conventions proven on real data, not only by round trips.

(a) Pose2Sim demo (``../shared/data/pose2sim``): the Qualisys calibration imported by
    ``calibrate.formats.read_qualisys``; Pose2Sim's own triangulated markers (TRC, OpenSim y-up:
    TRC (X, Y, Z) = world (y, z, x), see Pose2Sim's ``zup2yup``) projected into the 4 cameras and
    compared with the OpenPose BODY_25B detections of the same trial. TRC ``Frame#`` k (1-based)
    is JSON file k-1 (measured below: offset -1 fits best). The session's calibration is
    ``S00_Calibration`` (its own ``Calib.qca.txt``, identical to the demo's but for the camera
    serials, and Pose2Sim's conversion ``Calib_qualisys.toml``); both are checked.
(b) caliscope ``4_cam_recording_holistic_2d3d``: its triangulated 3D points (xyz_HOLISTIC.csv)
    projected with its calibration (config.toml) against its 2D points (xy_HOLISTIC.csv), and our
    own DLT of its 2D points against its 3D points.

The residuals are dominated by the 2D detector and by Pose2Sim's / caliscope's own triangulation
(Pose2Sim drops a camera when its reprojection error exceeds 15 px); a wrong convention gives
hundreds of pixels or points behind the cameras, which the negative controls show.
"""

from __future__ import annotations

import glob
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import need_shared

from roomcap.calibrate.camera import Camera, CameraRig
from roomcap.calibrate.formats import ImportOptions, detect_format, import_rig

SESSION = ("data", "pose2sim", "session-2024")
TRIAL = "S00_P00_SingleParticipant/S00_P00_T01_BalancingTrial"
# Pose2Sim's BODY_25B marker names -> OpenPose BODY_25B keypoint index
BODY25B = dict(
    Nose=0,
    LShoulder=5,
    RShoulder=6,
    LElbow=7,
    RElbow=8,
    LWrist=9,
    RWrist=10,
    LHip=11,
    RHip=12,
    LKnee=13,
    RKnee=14,
    LAnkle=15,
    RAnkle=16,
    Neck=17,
    Head=18,
    LBigToe=19,
    LSmallToe=20,
    LHeel=21,
    RBigToe=22,
    RSmallToe=23,
    RHeel=24,
)
MIN_SCORE = 0.3


def read_trc_zup(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Pose2Sim TRC -> (marker names, Frame# (T,), xyz_m (T,M,3) in the z-up world of the calibration)."""
    lines = path.read_text().splitlines()
    assert lines[2].split("\t")[4] == "m", "TRC units must be metres"
    names = [n for n in lines[3].split("\t")[2:] if n.strip()]
    rows = [[float(v) if v.strip() else np.nan for v in ln.split("\t")] for ln in lines[5:] if ln.strip()]
    data = np.array([r[: 2 + 3 * len(names)] for r in rows])
    xyz_yup = data[:, 2:].reshape(len(data), len(names), 3)
    # OpenSim y-up: TRC (X, Y, Z) = world (y, z, x)  =>  world (x, y, z) = TRC (Z, X, Y)
    return names, data[:, 0].astype(int), xyz_yup[..., [2, 0, 1]]


def read_openpose(folder: Path) -> list[list[np.ndarray]]:
    """Per JSON file (sorted): the people's (25,3) keypoints (x, y, score), score 0 = missing."""
    out = []
    for f in sorted(folder.glob("*.json")):
        people = json.loads(f.read_text())["people"]
        # Pose2Sim's association leaves {} where it found nobody
        out.append(
            [
                np.array(p["pose_keypoints_2d"], dtype=float).reshape(-1, 3)
                for p in people
                if p.get("pose_keypoints_2d")
            ]
        )
    return out


def pose2sim_errors(
    rig: CameraRig,
    trial: Path,
    pose_dir: str = "pose-associated",
    frame_offset: int = -1,
    trc_glob: str = "*_0-100.trc",
) -> dict[str, np.ndarray]:
    """Per camera: distances (px) between projected TRC markers and detections (score > MIN_SCORE).

    With several people in a JSON file, the one closest (median over joints) to the projection is used."""
    trc = [p for p in sorted((trial / "pose-3d").glob(trc_glob)) if "filt" not in p.name]
    assert len(trc) >= 1, trc
    names, frames, X = read_trc_zup(trc[0])
    idx = [BODY25B[n] for n in names]
    out = {}
    for cam in rig:
        dets = read_openpose(trial / pose_dir / f"{cam.name.replace('_', '')}_json")
        errs = []
        for k, f in enumerate(frames):
            j = f + frame_offset
            if not 0 <= j < len(dets):
                continue
            proj = cam.project(X[k])
            best = None
            for kp in dets[j]:
                ok = kp[idx, 2] > MIN_SCORE
                if ok.sum() < 5:
                    continue
                e = np.linalg.norm(kp[idx, :2][ok] - proj[ok], axis=1)
                if best is None or np.median(e) < np.median(best):
                    best = e
            if best is not None:
                errs.append(best)
        out[cam.name] = np.concatenate(errs) if errs else np.array([np.nan])
    return out


def pooled_median(errs: dict[str, np.ndarray]) -> float:
    return float(np.nanmedian(np.concatenate(list(errs.values()))))


@pytest.fixture(scope="module")
def p2s():
    root = need_shared(*SESSION)
    return root, import_rig(root / "S00_Calibration" / "Calib.qca.txt")


def test_pose2sim_qualisys_projects_onto_openpose(p2s):
    root, rig = p2s
    assert rig.names == ["cam_01", "cam_02", "cam_03", "cam_04"]
    assert all(c.size_wh == (1088, 1920) for c in rig)  # portrait, as calibrated (fov_video 0..1087)
    errs = pose2sim_errors(rig, root / TRIAL)
    med = {k: float(np.median(v)) for k, v in errs.items()}
    # measured: cam_01 11.4, cam_02 8.1, cam_03 17.2, cam_04 9.4 px; pooled 10.8 px (n = 8065 joints)
    assert pooled_median(errs) < 15.0, med
    assert max(med.values()) < 20.0, med
    assert min(len(v) for v in errs.values()) > 1000


def test_pose2sim_frame_correspondence(p2s):
    """TRC Frame# 1 is JSON file 0: offset -1 fits better than 0 or -2."""
    root, rig = p2s
    m = {off: pooled_median(pose2sim_errors(rig, root / TRIAL, frame_offset=off)) for off in (-2, -1, 0)}
    # measured: -2: 12.6, -1: 10.8, 0: 12.4 px (+1: 14.8)
    assert m[-1] < m[0] and m[-1] < m[-2], m


def test_pose2sim_negative_controls(p2s):
    """Wrong conventions are caught: TRC left in y-up, or the Qualisys rotation transposed."""
    root, rig = p2s
    names, frames, X = read_trc_zup(next((root / TRIAL / "pose-3d").glob("*_0-100.trc")))
    assert np.nanmedian(X[..., 2]) > 0.5  # z up: markers stand above the floor (measured 0.77 m)
    # left in y-up: projections land far away (or behind the cameras)
    yup = X[..., [1, 2, 0]]
    proj = rig.project(yup.reshape(-1, 3))
    good = rig.project(X.reshape(-1, 3))
    d = np.linalg.norm(proj - good, axis=-1)
    assert np.nanmedian(np.where(np.isnan(d), np.inf, d)) > 200  # measured 800 px
    # transposed rotation (world_from_cam read as cam_from_world)
    bad = CameraRig(
        tuple(Camera(c.name, c.size_wh, c.K, c.dist, c.model, c.R.T, -c.R.T @ c.center) for c in rig)
    )
    e = bad.project(X.reshape(-1, 3))
    d = np.linalg.norm(e - good, axis=-1)
    assert np.nanmedian(np.where(np.isnan(d), np.inf, d)) > 200  # measured: half behind, median 5100 px


def test_pose2sim_own_toml_matches_qualisys_import(p2s):
    """Pose2Sim's conversion of the same file (Calib_qualisys.toml) = our Qualisys import with its
    distortion / 64: same K, R (to 1e-12 from Rodrigues), t; and the same reprojection figures."""
    root, rig = p2s
    toml_path = root / "S00_Calibration" / "Calib_qualisys.toml"
    assert detect_format(toml_path) == "aniposelib"
    theirs = import_rig(toml_path)
    ours = import_rig(
        root / "S00_Calibration" / "Calib.qca.txt", options=ImportOptions(distortion_scale=1 / 64)
    )
    for a, b in zip(ours, theirs, strict=True):
        assert a.name == b.name and a.size_wh == b.size_wh
        np.testing.assert_allclose(a.K, b.K, atol=1e-9)
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)  # measured 7e-16
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)  # measured 6e-16
        np.testing.assert_allclose(a.dist[:4], b.dist, atol=1e-15)
    m_ours = pooled_median(pose2sim_errors(rig, root / TRIAL))
    m_theirs = pooled_median(pose2sim_errors(theirs, root / TRIAL))
    # measured: 10.78 px (distortion as written) vs 10.73 px (Pose2Sim's distortion / 64)
    assert abs(m_ours - m_theirs) < 1.0


def test_pose2sim_demo_calibration_is_the_sessions(p2s):
    """The demo's Calib.qca.txt (serials cam01..) is the session's (serials cam_01..) camera for camera."""
    root, rig = p2s
    demo = need_shared(
        "data", "pose2sim", "demo-wheel-0.10.49", "Demo_SinglePerson", "calibration", "Calib.qca.txt"
    )
    d = import_rig(demo)
    assert d.names == ["cam01", "cam02", "cam03", "cam04"]
    for a, b in zip(d, rig, strict=True):
        assert a.to_dict() | {"name": ""} == b.to_dict() | {"name": ""}


def test_pose2sim_1080_wide_videos(p2s):
    """The calibration declares 1088-wide images; some demo videos are 1080 wide. Importing with the
    video size keeps K (crop at the right: pixel origin stays top-left) and records the size. The
    alternative reading (a centred crop, cx - 4) fits the detections worse on this trial."""
    root, rig = p2s
    r1080 = import_rig(
        root / "S00_Calibration" / "Calib.qca.txt", options=ImportOptions(image_size_wh=(1080, 1920))
    )
    assert all(c.size_wh == (1080, 1920) for c in r1080)
    for a, b in zip(r1080, rig, strict=True):
        np.testing.assert_array_equal(a.K, b.K)
    centred = CameraRig(
        tuple(c.replace(K=c.K - np.array([[0, 0, 4.0], [0, 0, 0], [0, 0, 0]])) for c in r1080)
    )
    m_right, m_centre = (
        pooled_median(pose2sim_errors(r1080, root / TRIAL)),
        pooled_median(pose2sim_errors(centred, root / TRIAL)),
    )
    # measured: right crop 10.8 px, centred crop 12.0 px (cx - 8: 14.5 px)
    assert m_right < m_centre + 0.5


def test_pose2sim_two_person_trial(p2s):
    """Both participants of the two-person trial, each from its own TRC (closest detection per file)."""
    root, rig = p2s
    trial = root / "S00_P01_MultiParticipants" / "S00_P01_T02_Participants1-2"
    meds = {}
    for p in ("P1", "P2"):
        meds[p] = pooled_median(pose2sim_errors(rig, trial, pose_dir="pose", trc_glob=f"*_{p}_0-100.trc"))
    # measured: P1 12.0 px, P2 10.8 px
    assert max(meds.values()) < 15.0, meds


# ----------------------------------------------------------------------------- caliscope


def _caliscope():
    root = need_shared("data", "caliscope", "4_cam_recording_holistic_2d3d")
    rec = root / "recordings" / "recording_1" / "HOLISTIC"
    rig = import_rig(root / "config.toml")
    xy = np.genfromtxt(
        rec / "xy_HOLISTIC.csv", delimiter=",", skip_header=1
    )  # sync, port, frame, t, id, x, y
    xyz = np.genfromtxt(rec / "xyz_HOLISTIC.csv", delimiter=",", skip_header=1)  # row, sync, id, x, y, z
    sync = np.unique(xy[:, 0]).astype(int)
    pid = np.unique(xy[:, 4]).astype(int)
    si = {s: i for i, s in enumerate(sync)}
    pi = {p: i for i, p in enumerate(pid)}
    obs = np.full((len(rig), len(sync), len(pid), 2), np.nan)
    for r in xy:
        obs[rig.index(f"cam_{int(r[1])}"), si[int(r[0])], pi[int(r[4])]] = r[5:7]
    X = np.full((len(sync), len(pid), 3), np.nan)
    for r in xyz:
        if int(r[1]) in si and int(r[2]) in pi:
            X[si[int(r[1])], pi[int(r[2])]] = r[3:6]
    return rig, obs, X


def _dlt(P: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Linear triangulation. P: (C,3,4); xy: (C,...,2) undistorted px, NaN = unseen -> (...,3)."""
    C = P.shape[0]
    A = np.zeros(xy.shape[1:-1] + (2 * C, 4))
    for c in range(C):
        A[..., 2 * c, :] = xy[c, ..., 0:1] * P[c, 2] - P[c, 0]
        A[..., 2 * c + 1, :] = xy[c, ..., 1:2] * P[c, 2] - P[c, 1]
    seen = np.isfinite(xy[..., 0]).sum(0)
    A = np.where(np.isfinite(A), A, 0.0)
    _, _, vt = np.linalg.svd(A)
    X = vt[..., -1, :3] / vt[..., -1, 3:]
    X[seen < 2] = np.nan
    return X


def test_caliscope_projection_and_triangulation():
    rig, obs, X = _caliscope()
    assert (
        detect_format(need_shared("data", "caliscope", "4_cam_recording_holistic_2d3d", "config.toml"))
        == "caliscope"
    )
    proj = rig.project(X.reshape(-1, 3)).reshape(obs.shape)
    e = np.linalg.norm(proj - obs, axis=-1)
    per_cam = [float(np.nanmedian(e[c])) for c in range(len(rig))]
    # measured: cam_0 19.4, cam_1 17.3, cam_2 19.4, cam_3 12.0 px; pooled 17.2 px (n = 62790) --
    # caliscope's own residuals (webcams at 24 fps; our own DLT below reprojects at 16.0 px)
    assert np.nanmedian(e) < 25.0, per_cam
    # our undistortion + DLT with the imported rig reproduces caliscope's 3D points
    Xh = _dlt(rig.projection_matrices(), rig.undistort_px(obs))
    d = np.linalg.norm(Xh - X, axis=-1)
    assert np.nanmedian(d) < 0.01  # measured 4.5 mm (n = 18315 points)
    # negative control: the pose read as world_from_cam. cam_1 is caliscope's anchor (identity pose),
    # which no inversion changes; the other three move far away.
    inv = CameraRig(tuple(c.replace(R=c.R.T, t=-c.R.T @ c.t) for c in rig))
    eb = np.linalg.norm(inv.project(X.reshape(-1, 3)).reshape(obs.shape) - obs, axis=-1)
    eb = np.where(np.isnan(eb) & np.isfinite(obs[..., 0]), np.inf, eb)
    moved = [float(np.nanmedian(eb[rig.index(n)])) for n in ("cam_0", "cam_2", "cam_3")]
    assert min(moved) > 50, moved  # measured 501, 79, 258 px


def test_caliscope_camera_array_files_import():
    for folder in ("charuco_calibration", "4_cam_recording"):
        p = need_shared("data", "caliscope", folder, "camera_array.toml")
        assert detect_format(p) == "caliscope"
        rig = import_rig(p)
        assert rig.names == ["cam_0", "cam_1", "cam_2", "cam_3"]
        assert all(c.size_wh == (1280, 720) and c.dist.size == 5 for c in rig)
        # cameras a metre or two apart, around the board: metres, cam_from_world
        span = np.ptp(rig.centers(), axis=0).max()
        assert 0.3 < span < 5.0, span


def test_shared_files_all_detected():
    root = need_shared("data")
    for p in glob.glob(str(root / "pose2sim" / "**" / "*.qca.txt"), recursive=True):
        assert detect_format(p) == "qualisys"
