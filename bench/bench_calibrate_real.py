"""Calibration on real recordings and a rendered synthetic ring, end to end, against references.

1. caliscope ``charuco_calibration`` (4 cameras, ChArUco): ``calibrate_recording`` from the videos alone
   (fresh detection); per-camera intrinsic RMS against caliscope's ``error`` in ``camera_array.toml``;
   camera centres against caliscope's after a similarity (Umeyama) alignment.
2. Pose2Sim ``Demo_SinglePerson/calibration/intrinsics`` (checkerboard 4x7 inner corners, 60 mm, 1088x1920
   portrait images): intrinsics against the Qualisys calibration ``Calib.qca.txt`` (imported with
   calibrate.formats; its field of view is 1088x1920 like the images, so no crop correction applies).
3. OpenCV's stereo chessboard pairs (the image list of ``stereo_calib.xml``; 9x6 inner corners; the file
   holds no calibration, so the reference is OpenCV's own ``stereoCalibrate`` on the same corners, as the
   stereo_calib sample does): focal lengths, baseline and relative rotation, ours vs OpenCV's.
4. Synthetic 12-camera ring rendered to images (ChArUco warped through each lens, blur, noise), full
   pipeline from the images: focal, rotation and centre errors.

    .venv/bin/python bench/bench_calibrate_real.py [--shared PATH] [--skip-synthetic]

Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.calibrate.boards import Board  # noqa: E402
from roomcap.calibrate.calibration import CalibrationConfig, calibrate_recording  # noqa: E402
from roomcap.calibrate.camera import CameraRig  # noqa: E402
from roomcap.calibrate.detect import detect_all, discover_recording  # noqa: E402
from roomcap.calibrate.extrinsics import ExtrinsicsConfig, calibrate_extrinsics  # noqa: E402
from roomcap.calibrate.intrinsics import IntrinsicsConfig, calibrate_intrinsics  # noqa: E402


def umeyama(X: np.ndarray, Y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising |s R X + t - Y|^2 (Umeyama 1991). X, Y: (N,3)."""
    mx, my = X.mean(0), Y.mean(0)
    Xc, Yc = X - mx, Y - my
    U, S, Vt = np.linalg.svd(Yc.T @ Xc / len(X))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (Xc**2).sum() * len(X))
    return s, R, my - s * R @ mx


def rig_errors(est: CameraRig, truth: CameraRig) -> dict:
    Ms = [truth[i].R.T @ est[i].R for i in range(len(truth))]
    U, _, Vt = np.linalg.svd(sum(Ms))
    R = U @ Vt
    ce, ct = est.centers(), truth.centers()
    t = (ct - ce @ R.T).mean(0)
    rot = [
        float(np.degrees(np.arccos(np.clip((np.trace((truth[i].R @ R).T @ est[i].R) - 1) / 2, -1, 1))))
        for i in range(len(truth))
    ]
    f = [abs(est[i].K[0, 0] / truth[i].K[0, 0] - 1) * 100 for i in range(len(truth))]
    c = np.linalg.norm(ce @ R.T + t - ct, axis=1) * 1000
    return {
        "focal_err_pct_max": max(f),
        "rot_err_deg_max": max(rot),
        "center_err_mm_max": float(c.max()),
        "focal_err_pct_median": float(np.median(f)),
        "rot_err_deg_median": float(np.median(rot)),
        "center_err_mm_median": float(np.median(c)),
    }


def caliscope(shared: Path, out: dict) -> None:
    from roomcap.calibrate.formats import import_rig

    rec = shared / "data" / "caliscope" / "charuco_calibration"
    if not rec.exists():
        print(f"(skipping caliscope: {rec} not found)")
        return
    ref = import_rig(rec / "camera_array.toml", "caliscope")
    import tomllib

    ref_err = {
        f"cam_{k}": v["error"]
        for k, v in tomllib.loads((rec / "camera_array.toml").read_text())["cameras"].items()
    }
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        res = calibrate_recording(
            rec / "calibration" / "extrinsic",
            rec / "charuco.toml",
            Path(tmp) / "rig.toml",
            CalibrationConfig(),
        )
        total = time.perf_counter() - t0
    rig = res.rig
    s, R, t = umeyama(rig.centers(), ref.subset(rig.names).centers())
    aligned = s * rig.centers() @ R.T + t
    dist = np.linalg.norm(aligned - ref.subset(rig.names).centers(), axis=1) * 1000
    rows = {}
    print("== caliscope charuco_calibration: calibrate_recording from the videos alone")
    print(
        f"   {'camera':<8}{'ours RMS':>10}{'caliscope':>11}{'frames':>8}{'f ours':>9}"
        f"{'f calisc.':>10}{'pos err mm':>11}"
    )
    for i, name in enumerate(rig.names):
        r = res.intrinsics[name]
        rows[name] = {
            "intrinsic_rms_px": r.rms_px,
            "caliscope_error_px": ref_err[name],
            "frames_used": len(r.frames_used),
            "focal_px": float(rig[name].K[0, 0]),
            "caliscope_focal_px": float(ref[name].K[0, 0]),
            "position_err_mm": float(dist[i]),
        }
        print(
            f"   {name:<8}{r.rms_px:>10.3f}{ref_err[name]:>11.3f}{len(r.frames_used):>8}"
            f"{rig[name].K[0, 0]:>9.1f}"
            f"{ref[name].K[0, 0]:>10.1f}{dist[i]:>11.1f}"
        )
    ext = res.extrinsics
    print(
        f"   similarity alignment to caliscope: scale {s:.4f}, camera position error mean "
        f"{dist.mean():.1f} mm, "
        f"max {dist.max():.1f} mm (camera spread {np.ptp(ref.centers(), 0).max():.2f} m)"
    )
    print(
        f"   BA RMS {ext.initial_rms_px:.3f} -> {ext.final_rms_px:.3f} px in {ext.ba_time_s:.2f} s; "
        f"end to end {total:.1f} s (detect {res.timings_s['detect_s']:.1f} s)"
    )
    out["caliscope"] = {
        "cameras": rows,
        "intrinsic_rms_all_le_caliscope": all(
            v["intrinsic_rms_px"] <= v["caliscope_error_px"] for v in rows.values()
        ),
        "umeyama_scale": s,
        "position_err_mm_mean": float(dist.mean()),
        "position_err_mm_max": float(dist.max()),
        "ba_rms_px": ext.final_rms_px,
        "ba_time_s": ext.ba_time_s,
        "end_to_end_s": total,
        "detect_s": res.timings_s["detect_s"],
    }


def pose2sim(shared: Path, out: dict) -> None:
    from roomcap.calibrate.formats import import_rig

    d = shared / "data" / "pose2sim" / "demo-wheel-0.10.49" / "Demo_SinglePerson" / "calibration"
    if not d.exists():
        print(f"(skipping pose2sim: {d} not found)")
        return
    q = import_rig(d / "Calib.qca.txt", "qualisys")
    board = Board("checkerboard", (4, 7), 0.06)
    with tempfile.TemporaryDirectory() as tmp:
        dets = detect_all(board, discover_recording(d / "intrinsics"), Path(tmp))
    print("== Pose2Sim Demo_SinglePerson intrinsics (checkerboard 4x7, 60 mm) vs Qualisys Calib.qca.txt")
    print(
        f"   {'camera':<8}{'views':>6}{'RMS':>7}{'f ours':>9}{'f QTM':>9}{'df %':>7}"
        f"{'cx,cy ours':>16}{'cx,cy QTM':>16}{'dc px':>14}"
    )
    rows = {}
    for name, det in dets.items():
        qn = "cam" + name.split("cam")[1][:2]
        qc = q[qn]
        r = calibrate_intrinsics(board, det, IntrinsicsConfig(min_frames=4))
        df = (r.K[0, 0] / qc.K[0, 0] - 1) * 100
        dc = r.K[:2, 2] - qc.K[:2, 2]
        rows[qn] = {
            "views": len(r.frames_used),
            "rms_px": r.rms_px,
            "focal_px": float(r.K[0, 0]),
            "qualisys_focal_px": float(qc.K[0, 0]),
            "focal_diff_pct": float(df),
            "pp_diff_px": dc.tolist(),
            "size_wh": list(det.size_wh),
            "qualisys_size_wh": list(qc.size_wh),
        }
        print(
            f"   {qn:<8}{len(r.frames_used):>6}{r.rms_px:>7.3f}{r.K[0, 0]:>9.1f}{qc.K[0, 0]:>9.1f}{df:>7.2f}"
            f"{r.K[0, 2]:>8.1f},{r.K[1, 2]:<7.1f}{qc.K[0, 2]:>8.1f},{qc.K[1, 2]:<7.1f}"
            f"{dc[0]:>7.1f},{dc[1]:<6.1f}"
        )
    out["pose2sim"] = {
        "cameras": rows,
        "focal_diff_pct_max_abs": max(abs(v["focal_diff_pct"]) for v in rows.values()),
        "pp_diff_px_max_abs": max(max(abs(x) for x in v["pp_diff_px"]) for v in rows.values()),
    }


def stereo(shared: Path, out: dict) -> None:
    import cv2

    d = shared / "data" / "opencv" / "stereo_chessboard"
    if not d.exists():
        print(f"(skipping stereo: {d} not found)")
        return
    board = Board("checkerboard", (9, 6), 1.0)  # sizes in squares, as the OpenCV sample
    fs = cv2.FileStorage(str(d / "stereo_calib.xml"), cv2.FILE_STORAGE_READ)
    listed = [fs.getNode("imagelist").at(i).string() for i in range(fs.getNode("imagelist").size())]
    fs.release()
    srcs = discover_recording(d)
    srcs = [s for s in srcs if s.name in ("left", "right")]
    assert sorted(p.name for s in srcs for p in s.paths) == sorted(listed), (
        "image list differs from stereo_calib.xml"
    )
    with tempfile.TemporaryDirectory() as tmp:
        dets = detect_all(board, srcs, Path(tmp))
    cams = [calibrate_intrinsics(board, dets[n], IntrinsicsConfig(min_frames=4)) for n in ("left", "right")]
    ext = calibrate_extrinsics(board, [c.camera() for c in cams], dets, ExtrinsicsConfig(world="camera:left"))
    R_ours, t_ours = ext.rig["right"].R, ext.rig["right"].t
    # OpenCV's reference: stereoCalibrate on the same corners (frames seen by both), as stereo_calib.cpp
    common = sorted(set(dets["left"].seen_frames(54)) & set(dets["right"].seen_frames(54)))
    obj = board.object_points().astype(np.float32)
    ip = {
        n: [dets[n].xy_px[int(np.flatnonzero(dets[n].frames == f)[0])].astype(np.float32) for f in common]
        for n in ("left", "right")
    }
    # a checkerboard's corner order is ambiguous (180 degrees): number the right view's corners like the
    # left's, per frame, by which order gives the relative rotation agreeing with the others (independent of
    # our pipeline: OpenCV's single-camera calibrations and solvePnP)
    Ks = {}
    for n in ("left", "right"):
        _, K, D, _, _ = cv2.calibrateCamera([obj] * len(common), ip[n], (640, 480), None, None)
        Ks[n] = (K, D)
    cands = []
    for k in range(len(common)):
        per = []
        for order in (ip["right"][k], ip["right"][k][::-1].copy()):
            _, rl, _ = cv2.solvePnP(obj, ip["left"][k], *Ks["left"])
            _, rr, _ = cv2.solvePnP(obj, order, *Ks["right"])
            per.append(cv2.Rodrigues(rr)[0] @ cv2.Rodrigues(rl)[0].T)
        cands.append(per)
    allR = [R for per in cands for R in per]
    med = min(allR, key=lambda A: sum(np.linalg.norm(A - B) for B in allR))
    n_turned = 0
    for k, per in enumerate(cands):
        if np.linalg.norm(per[1] - med) < np.linalg.norm(per[0] - med):
            ip["right"][k] = ip["right"][k][::-1].copy()
            n_turned += 1
    # the sample's flags (aspect ratio fixed, no tangential, same focal, rational k1,k2,k6), initial K from
    # initCameraMatrix2D as in the sample
    flags = (
        cv2.CALIB_FIX_ASPECT_RATIO
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_SAME_FOCAL_LENGTH
        | cv2.CALIB_RATIONAL_MODEL
        | cv2.CALIB_FIX_K3
        | cv2.CALIB_FIX_K4
        | cv2.CALIB_FIX_K5
    )
    objs = [obj.reshape(-1, 1, 3)] * len(common)
    K0 = cv2.initCameraMatrix2D(objs, [p.reshape(-1, 1, 2) for p in ip["left"]], (640, 480), 0)
    K0b = cv2.initCameraMatrix2D(objs, [p.reshape(-1, 1, 2) for p in ip["right"]], (640, 480), 0)
    rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(
        objs,
        [p.reshape(-1, 1, 2) for p in ip["left"]],
        [p.reshape(-1, 1, 2) for p in ip["right"]],
        K0,
        np.zeros(8),
        K0b,
        np.zeros(8),
        (640, 480),
        flags=flags,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-5),
    )
    dR = float(np.degrees(np.arccos(np.clip((np.trace(R.T @ R_ours) - 1) / 2, -1, 1))))
    # and with our intrinsics held fixed, so that only the extrinsics are compared
    c0, c1 = cams[0].camera(), cams[1].camera()
    rms_fix, *_, Rf, Tf, _, _ = cv2.stereoCalibrate(
        objs,
        [p.reshape(-1, 1, 2) for p in ip["left"]],
        [p.reshape(-1, 1, 2) for p in ip["right"]],
        c0.K.copy(),
        c0.dist.copy(),
        c1.K.copy(),
        c1.dist.copy(),
        (640, 480),
        None,
        None,
        flags=cv2.CALIB_FIX_INTRINSIC,
    )
    dR_fix = float(np.degrees(np.arccos(np.clip((np.trace(Rf.T @ R_ours) - 1) / 2, -1, 1))))
    db_fix = float(np.linalg.norm(t_ours) / np.linalg.norm(Tf) - 1) * 100
    b_ours, b_cv = float(np.linalg.norm(t_ours)), float(np.linalg.norm(T))
    res = {
        "pairs": len(common),
        "right_views_renumbered": n_turned,
        "ours_f_px": [float(c.K[0, 0]) for c in cams],
        "opencv_f_px": [float(K1[0, 0]), float(K2[0, 0])],
        "ours_intrinsic_rms_px": [c.rms_px for c in cams],
        "ours_ba_rms_px": ext.final_rms_px,
        "opencv_stereo_rms_px": float(rms),
        "baseline_squares_ours": b_ours,
        "baseline_squares_opencv": b_cv,
        "relative_rotation_diff_deg": dR,
        "fixed_intrinsics_rotation_diff_deg": dR_fix,
        "fixed_intrinsics_baseline_diff_pct": db_fix,
        "fixed_intrinsics_opencv_rms_px": float(rms_fix),
        "baseline_direction_diff_deg": float(
            np.degrees(np.arccos(np.clip(t_ours @ T.ravel() / b_ours / b_cv, -1, 1)))
        ),
    }
    print(
        "== OpenCV stereo chessboard (stereo_calib.xml image list, 9x6): ours vs cv2.stereoCalibrate "
        "(sample flags)"
    )
    print(
        f"   pairs {len(common)}; focal ours {res['ours_f_px'][0]:.1f}/{res['ours_f_px'][1]:.1f} vs OpenCV "
        f"{res['opencv_f_px'][0]:.1f}/{res['opencv_f_px'][1]:.1f} px; RMS ours {ext.final_rms_px:.3f} vs "
        f"OpenCV {rms:.3f} px"
    )
    print(
        f"   baseline {b_ours:.3f} vs {b_cv:.3f} squares; relative rotation differs by {dR:.3f} deg, "
        f"baseline direction by {res['baseline_direction_diff_deg']:.3f} deg"
    )
    print(
        f"   with our intrinsics fixed in stereoCalibrate: rotation differs by {dR_fix:.3f} deg, baseline by "
        f"{db_fix:.3f} % (OpenCV RMS {rms_fix:.3f} px)"
    )
    out["stereo"] = res


def _rendered(out: dict, key: str, title: str, board: Board, rig: CameraRig, T: np.ndarray, rng) -> None:
    """Render the board poses T into the rig, calibrate from the images, compare with the truth."""
    from roomcap.calibrate.synthetic_boards import write_recording

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_recording(board, rig, T, Path(tmp) / "rec", rng, noise=2.0, blur_sigma_px=0.7)
        t_render = time.perf_counter() - t0
        res = {}
        for model, refine in (("pinhole4", "all"), ("pinhole", "none")):
            t0 = time.perf_counter()
            r = calibrate_recording(  # same output folder: the detections are reused
                Path(tmp) / "rec",
                board,
                Path(tmp) / "out" / f"rig_{model}_{refine}.toml",
                CalibrationConfig(model=model, refine_intrinsics=refine),
            )
            e = rig_errors(r.rig, rig)
            e["time_s"] = time.perf_counter() - t0
            e["ba_rms_px"] = r.extrinsics.final_rms_px
            e["links"] = r.extrinsics.links.tolist()
            res[f"{model}/{refine}"] = e
    w, h = rig[0].size_wh
    print(
        f"== {title}, rendered ({len(T)} board poses, {w}x{h}, blur 0.7 px, noise 2 gray levels; "
        f"render {t_render:.0f} s)"
    )
    for k, e in res.items():
        print(
            f"   {k:<18} focal err max {e['focal_err_pct_max']:.3f} %  rotation max "
            f"{e['rot_err_deg_max']:.3f} deg  "
            f"centre max {e['center_err_mm_max']:.2f} mm  (BA RMS {e['ba_rms_px']:.3f} px, "
            f"{e['time_s']:.0f} s)"
        )
    out[key] = res


def synthetic_ring(out: dict, n_frames: int) -> None:
    from roomcap.calibrate.synthetic_boards import board_trajectory, ring_rig, views_near_camera

    rng = np.random.default_rng(0)
    board = Board("charuco", (7, 5), 0.1, 0.075, "DICT_4X4_50")
    rig = ring_rig(12, 2.0, size_wh=(960, 720), focal_px=800.0, rng=rng)
    T = np.concatenate(
        [board_trajectory(board, n_frames, rng, spread_m=0.6)]
        + [views_near_camera(board, c, 12, rng, tilt_deg=60) for c in rig]
    )
    _rendered(out, "synthetic_ring_rendered", "synthetic 12-camera ring", board, rig, T, rng)


def synthetic_weak_link(out: dict) -> None:
    """4 cameras; c3 sees the board together with the others in 3 frames only (plus its own close-ups)."""
    from roomcap.calibrate.camera import Camera
    from roomcap.calibrate.synthetic_boards import board_trajectory, look_at, views_near_camera

    rng = np.random.default_rng(1)
    board = Board("charuco", (7, 5), 0.1, 0.075, "DICT_4X4_50")
    cams = []
    places = [
        ([2.0, -1.5, 1.6], [0, 0, 1]),
        ([2.0, 1.5, 1.6], [0, 0, 1]),
        ([0.0, -2.2, 1.8], [0, 0, 1]),
        ([-2.2, 2.2, 1.4], [-0.5, 1.2, 1.0]),
    ]
    for i, (pos, tgt) in enumerate(places):
        R, t = look_at(pos, tgt)
        f = 700 * (1 + 0.03 * i)
        K = np.array([[f, 0, 480 + 3 * i], [0, f, 360 - 2 * i], [0, 0, 1]])
        cams.append(Camera(f"c{i}", (960, 720), K, np.array([-0.1, 0.04, 0.0, 0.0]), "pinhole", R, t))
    rig = CameraRig(tuple(cams))
    shared = board_trajectory(board, 30, rng, spread_m=0.4, yaw_range=(-0.6, 0.6))
    link = board_trajectory(
        board, 4, rng, center_m=(0.0, 1.0, 1.1), spread_m=0.2, tilt_deg=10, yaw_range=(1.3, 1.5)
    )
    T = np.concatenate([shared, link] + [views_near_camera(board, c, 20, rng, tilt_deg=60) for c in rig])
    _rendered(
        out, "synthetic_weak_link_rendered", "synthetic 4 cameras, c3 weakly linked", board, rig, T, rng
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
    )
    ap.add_argument("--skip-synthetic", action="store_true")
    ap.add_argument("--ring-frames", type=int, default=30)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    shared = Path(args.shared)
    out: dict = {}
    caliscope(shared, out)
    pose2sim(shared, out)
    stereo(shared, out)
    if not args.skip_synthetic:
        synthetic_ring(out, args.ring_frames)
        synthetic_weak_link(out)

    def r4(x):
        if isinstance(x, float):
            return round(x, 4)
        if isinstance(x, dict):
            return {k: r4(v) for k, v in x.items()}
        if isinstance(x, list):
            return [r4(v) for v in x]
        return x

    print("BENCH " + json.dumps({"bench": "calibrate_real", **r4(out)}))


if __name__ == "__main__":
    main()
