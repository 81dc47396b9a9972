"""Bundle adjustment: ours (pycolmap/Ceres, rigid board) against aniposelib's (scipy least_squares) on the
same detections and the same starting cameras, in the same run.

Problems: the caliscope 4-camera ChArUco recording (real detections) and a synthetic 12-camera ring
(projected board corners + 0.3 px noise). Both methods start from our intrinsics and our pose-graph
initialisation and keep the intrinsics fixed. Reported per method: wall time of the adjustment and the
final RMS reprojection error, measured the same two ways for every rig: "RMS" triangulates every board
corner seen by >= 2 cameras with the rig and reprojects it (aniposelib's criterion: free 3D points);
"board-fit" fits the rigid board to every frame with the rig's cameras held fixed (our model).

    .venv/bin/python bench/bench_calibrate_ba.py [--shared PATH] [--skip-real]

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

from roomcap.calibrate.boards import Board, load_board  # noqa: E402
from roomcap.calibrate.camera import Camera, CameraRig  # noqa: E402
from roomcap.calibrate.detect import detect_all, discover_recording  # noqa: E402
from roomcap.calibrate.extrinsics import ExtrinsicsConfig, board_fit_rms, calibrate_extrinsics  # noqa: E402
from roomcap.calibrate.intrinsics import calibrate_intrinsics  # noqa: E402
from roomcap.calibrate.pose_graph import board_poses, initial_poses, pairwise_links  # noqa: E402
from roomcap.calibrate.synthetic_boards import (  # noqa: E402
    board_trajectory,
    project_detections,
    ring_rig,
    views_near_camera,
)


def initial_rig(board, cams, dets) -> tuple[list[Camera], list[int]]:
    """Our pose-graph initialisation (the common starting point). Also returns frames seen by >= 2 cameras."""
    poses = [board_poses(board, c, dets[c.name]) for c in cams]
    links, rel = pairwise_links(poses)
    _, cfr = initial_poses([c.name for c in cams], links, rel, [len(p) for p in poses])
    cfr0 = cfr[0]
    out = []
    for c, T in zip(cams, cfr, strict=True):
        Tw = T @ np.linalg.inv(cfr0)  # world = first camera
        out.append(c.replace(R=Tw[:3, :3], t=Tw[:3, 3]))
    count: dict[int, int] = {}
    for p in poses:
        for f in p:
            count[f] = count.get(f, 0) + 1
    return out, sorted(f for f, n in count.items() if n >= 2)


def p2ds_of(board, cams, dets, frames) -> np.ndarray:
    """(C, P, 2) board corners of the given frames, NaN = unseen; only points seen by >= 2 cameras."""
    N = board.n_points
    C = len(cams)
    out = np.full((C, len(frames) * N, 2), np.nan)
    for c, cam in enumerate(cams):
        d = dets[cam.name]
        idx = {int(f): k for k, f in enumerate(d.frames)}
        for j, f in enumerate(frames):
            if f in idx:
                out[c, j * N : (j + 1) * N] = d.xy_px[idx[f]]
    keep = np.isfinite(out[..., 0]).sum(0) >= 2
    return out[:, keep]


def to_anipose(cams: list[Camera]):
    from aniposelib.cameras import Camera as ACam
    from aniposelib.cameras import CameraGroup

    return CameraGroup(
        [
            ACam(matrix=c.K, dist=c.dist, size=list(c.size_wh), rvec=c.rvec, tvec=c.t, name=c.name)
            for c in cams
        ]
    )


def from_anipose(group, cams: list[Camera]) -> list[Camera]:
    out = []
    for a, c in zip(group.cameras, cams, strict=True):
        import cv2

        R = cv2.Rodrigues(np.asarray(a.get_rotation(), float).reshape(3))[0]
        out.append(
            c.replace(
                R=R,
                t=np.asarray(a.get_translation(), float).reshape(3),
                K=np.asarray(a.get_camera_matrix(), float),
                dist=np.asarray(a.get_distortions(), float).reshape(-1)[: c.dist.size],
            )
        )
    return out


def common_rms(cams: list[Camera], p2ds: np.ndarray) -> float:
    """Triangulate each point with the rig (aniposelib's DLT on undistorted points), reproject, RMS px."""
    g = to_anipose(cams)
    p3 = g.triangulate(p2ds, progress=False)
    err = g.reprojection_error(p3, p2ds, mean=False)  # (C, P, 2)
    e = np.linalg.norm(err, axis=-1)
    return float(np.sqrt(np.nanmean(e**2)))


def run_problem(name: str, board: Board, cams: list[Camera], dets: dict, log: dict) -> None:
    init, frames = initial_rig(board, cams, dets)
    p2ds = p2ds_of(board, cams, dets, frames)
    res: dict = {
        "cameras": len(cams),
        "frames": len(frames),
        "points": int(p2ds.shape[1]),
        "observations": int(np.isfinite(p2ds[..., 0]).sum()),
        "rms_initial_px": common_rms(init, p2ds),
    }
    # ours: the whole extrinsics stage (PnP, pose graph, 2 BA passes) and the BA alone
    t0 = time.perf_counter()
    ext = calibrate_extrinsics(
        board, cams, dets, ExtrinsicsConfig(refine_intrinsics="none", max_frames=10**6)
    )
    res["ours_total_s"] = time.perf_counter() - t0
    res["ours_ba_s"] = ext.ba_time_s
    res["ours_rms_px"] = common_rms(list(ext.rig.cameras), p2ds)
    res["ours_board_rms_px"] = board_fit_rms(board, ext.rig, dets)
    # ours with a plain least-squares loss and no outlier rejection: minimises what the RMS figures measure
    ext2 = calibrate_extrinsics(
        board, cams, dets, ExtrinsicsConfig(loss="trivial", outlier_px=1e9, max_frames=10**6)
    )
    res["ours_l2_ba_s"] = ext2.ba_time_s
    res["ours_l2_rms_px"] = common_rms(list(ext2.rig.cameras), p2ds)
    res["ours_l2_board_rms_px"] = board_fit_rms(board, ext2.rig, dets)
    # aniposelib, iterative robust BA (its calibrate() default), extrinsics only as ours
    g = to_anipose(init)
    t0 = time.perf_counter()
    g.bundle_adjust_iter(p2ds, only_extrinsics=True, verbose=False)
    res["anipose_iter_s"] = time.perf_counter() - t0
    res["anipose_iter_rms_px"] = common_rms(from_anipose(g, init), p2ds)
    res["anipose_iter_board_rms_px"] = board_fit_rms(board, CameraRig(tuple(from_anipose(g, init))), dets)
    # aniposelib, one robust BA over all points (the same data as ours)
    g = to_anipose(init)
    t0 = time.perf_counter()
    g.bundle_adjust(p2ds, loss="soft_l1", threshold=1.0, only_extrinsics=True, verbose=False)
    res["anipose_full_s"] = time.perf_counter() - t0
    res["anipose_full_rms_px"] = common_rms(from_anipose(g, init), p2ds)
    res["anipose_full_board_rms_px"] = board_fit_rms(board, CameraRig(tuple(from_anipose(g, init))), dets)
    res["speedup_vs_iter"] = res["anipose_iter_s"] / res["ours_ba_s"]
    res["speedup_vs_full"] = res["anipose_full_s"] / res["ours_ba_s"]
    res["speedup_l2_vs_full"] = res["anipose_full_s"] / res["ours_l2_ba_s"]
    log[name] = res
    print(f"== {name}: {res['cameras']} cameras, {res['frames']} frames, {res['observations']} observations")
    print(f"   initial RMS {res['rms_initial_px']:.3f} px")
    print(
        f"   ours (pycolmap/Ceres)        BA {res['ours_ba_s']:.2f} s (extrinsics stage "
        f"{res['ours_total_s']:.2f} s)"
        f"  RMS {res['ours_rms_px']:.3f} px, board-fit {res['ours_board_rms_px']:.3f} px"
    )
    print(
        f"   ours, L2 loss, no rejection    BA {res['ours_l2_ba_s']:.2f} s  "
        f"RMS {res['ours_l2_rms_px']:.3f} px, "
        f"board-fit {res['ours_l2_board_rms_px']:.3f} px"
    )
    print(
        f"   aniposelib bundle_adjust_iter   {res['anipose_iter_s']:.2f} s  RMS "
        f"{res['anipose_iter_rms_px']:.3f} px, board-fit {res['anipose_iter_board_rms_px']:.3f} px"
        f"  -> ours {res['speedup_vs_iter']:.1f}x faster"
    )
    print(
        f"   aniposelib bundle_adjust (all)  {res['anipose_full_s']:.2f} s  RMS "
        f"{res['anipose_full_rms_px']:.3f} px, board-fit {res['anipose_full_board_rms_px']:.3f} px"
        f"  -> ours {res['speedup_vs_full']:.1f}x faster"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
    )
    ap.add_argument("--skip-real", action="store_true")
    ap.add_argument("--ring-frames", type=int, default=30, help="shared board poses of the synthetic ring")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    log: dict = {}
    rec = Path(args.shared) / "data" / "caliscope" / "charuco_calibration"
    if not args.skip_real and rec.exists():
        board = load_board(rec / "charuco.toml")
        with tempfile.TemporaryDirectory() as tmp:
            dets = detect_all(board, discover_recording(rec / "calibration" / "extrinsic"), Path(tmp))
        cams = [calibrate_intrinsics(board, d).camera() for d in dets.values()]
        run_problem("caliscope_4cam", board, cams, dets, log)
    else:
        print(f"(caliscope recording not found at {rec}: real problem skipped)")
    rng = np.random.default_rng(0)
    board = Board("charuco", (7, 5), 0.1, 0.075, "DICT_4X4_50")
    rig = ring_rig(12, 2.0, rng=rng)
    T = np.concatenate(
        [board_trajectory(board, args.ring_frames, rng, spread_m=0.6)]
        + [views_near_camera(board, c, 8, rng, tilt_deg=60) for c in rig]
    )
    dets = project_detections(board, rig, T, rng, noise_px=0.3)
    cams = [calibrate_intrinsics(board, dets[c.name]).camera() for c in rig]
    run_problem("synthetic_ring_12cam", board, cams, dets, log)
    print(
        "BENCH "
        + json.dumps(
            {
                "bench": "calibrate_ba",
                **{
                    k: {kk: round(vv, 4) if isinstance(vv, float) else vv for kk, vv in v.items()}
                    for k, v in log.items()
                },
            }
        )
    )


if __name__ == "__main__":
    main()
