"""Speed of association (Alg. 1) + robust triangulation per frame, one core, 2D inference excluded.

Frames come from the synthetic world (``synthetic.render`` with the default faults: 3 px noise,
10% missed joints, 2% flips, false-positive people), already converted to body19 and
undistorted, exactly what ``FrameReconstructor`` gets inside ``triangulate_session``. Threads are
pinned to one (OMP/OpenBLAS/MKL) before numpy loads. Figures, median over frames: CPU time of
this process (``time.process_time``), wall time, and the best of 5 wall times per frame (timeit's
convention; on a shared machine the least disturbed figure). The 1-minute load average is printed.

(1) two operating points on the kitchen with CMU motion: 4 people x 5 cameras and
16 x 12. (2) a table over people 1..32 x cameras 2..32 (ring rig in a round room, procedural
walkers so 32 people fit). (3) Pose2Sim 0.10.49's multi-person association (Plucker-line affinity
+ matchSVT + proposals) plus its triangulation (``triangulation_from_best_cameras`` per
keypoint) on the same frames, if Pose2Sim is importable (``--pose2sim-site DIR``: a folder from
``pip install --target DIR --no-deps pose2sim anytree rtoml c3d``; its full dependency list pulls
opensim, PySide6, openvino, rtmlib and caliscope, so it is not a project extra).

    .venv/bin/python bench/bench_triangulate_speed.py [--frames 40] [--pose2sim-site DIR]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.calibrate.camera import CameraRig  # noqa: E402
from roomcap.keypoints.skeletons import CANONICAL, convert  # noqa: E402
from roomcap.synthetic.render import RenderConfig, render  # noqa: E402
from roomcap.synthetic.rigs import kitchen, ring_rig, ring_room  # noqa: E402
from roomcap.synthetic.world import SceneConfig, make_scene  # noqa: E402
from roomcap.triangulate.reconstruct import FrameReconstructor  # noqa: E402

FAULTS = dict(noise_px=3.0, missed_joint_rate=0.10, flip_rate=0.02, false_positive_rate=0.05)


def frames_for(rig: CameraRig, scene, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(F,C,P,J,2) undistorted body19 pixels and (F,C,P,J) scores of the first n frames."""
    rd = render(scene, rig, RenderConfig(seed=seed, **FAULTS))
    P = max(d.max_people for d in rd.detections)
    C, J = len(rig), CANONICAL.n_joints
    xy = np.full((n, C, max(P, 1), J, 2), np.nan)
    sc = np.zeros((n, C, max(P, 1), J))
    for c, d in enumerate(rd.detections):
        b, s = convert(d.xy_px[:n], d.score[:n], d.skeleton, "body19")
        xy[:, c, : d.max_people] = rig[c].undistort_px(b)
        sc[:, c, : d.max_people] = np.nan_to_num(s)
    return xy, sc


def time_ours(rig: CameraRig, xy: np.ndarray, sc: np.ndarray, repeat: int = 5) -> dict:
    """Median over frames of: CPU time (mean of ``repeat`` runs), wall time, and the best of ``repeat``
    wall times (timeit's convention: the minimum is the least disturbed by other load)."""
    rec = FrameReconstructor(
        rig.projection_matrices(), rig.fundamental_matrices(), joint_names=CANONICAL.joint_names
    )
    rec(xy[0], sc[0])  # warm-up
    cpu, wall, best, found = [], [], [], []
    for f in range(len(xy)):
        w = []
        c0 = time.process_time()
        for _ in range(repeat):
            w0 = time.perf_counter()
            out = rec(xy[f], sc[f])
            w.append(time.perf_counter() - w0)
        cpu.append((time.process_time() - c0) / repeat)
        wall.append(float(np.median(w)))
        best.append(min(w))
        found.append(len(out.xyz_m))
    return {
        "cpu_ms": 1e3 * float(np.median(cpu)),
        "wall_ms": 1e3 * float(np.median(wall)),
        "best_ms": 1e3 * float(np.median(best)),
        "people_found": float(np.mean(found)),
    }


def time_pose2sim(site: str, rig: CameraRig, xy: np.ndarray, sc: np.ndarray) -> dict | None:
    """Pose2Sim's association + triangulation on the same frames (same undistorted pixels)."""
    if site:
        sys.path.insert(0, site)
    try:
        import logging

        import matplotlib

        matplotlib.use("Agg")
        logging.disable(logging.WARNING)
        from Pose2Sim import personAssociation as pa  # type: ignore
        from Pose2Sim import triangulation as pt  # type: ignore
        from Pose2Sim.common import retrieve_calib_params  # type: ignore

        logging.disable(logging.NOTSET)
    except Exception as e:  # noqa: BLE001 - report why the comparison is missing
        print(f"Pose2Sim not importable ({type(e).__name__}: {e}); skipping the comparison")
        return None
    from roomcap.calibrate.formats import export_rig

    und = rig  # our frames are undistorted already: give Pose2Sim the same cameras without distortion
    und = CameraRig(tuple(c.replace(dist=np.zeros(4)) for c in rig))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "Calib.toml"
        export_rig(und, path, "aniposelib")
        calib = retrieve_calib_params(path)  # a Path: rtoml reads a str as TOML text
    P_all = [np.asarray(p) for p in und.projection_matrices()]
    flip = np.asarray(CANONICAL.flip_index)
    cfg = {
        "triangulation": {
            "reproj_error_threshold_triangulation": 15,
            "min_cameras_for_triangulation": 2,
            "handle_LR_swap": False,
            "undistort_points": False,
        }
    }
    C = len(rig)
    cpu = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for f in range(len(xy)):
            frame = []
            for c in range(C):
                people = []
                for p in range(xy.shape[2]):
                    if np.isfinite(xy[f, c, p]).any():
                        k = np.concatenate([np.nan_to_num(xy[f, c, p], nan=0.0), sc[f, c, p, :, None]], -1)
                        people.append(k.reshape(-1).tolist())
                frame.append(people)
            c0 = time.process_time()
            cum = np.cumsum([0] + [len(v) for v in frame])
            aff = pa.compute_affinity(frame, calib, cum, reconstruction_error_threshold=0.1)
            circ = pa.circular_constraint(cum)
            aff = aff * circ
            aff = pa.matchSVT(aff, cum, circ, max_iter=20, w_rank=50, tol=1e-4, w_sparse=0.1)
            aff[aff < 0.2] = 0
            proposals = pa.person_index_per_cam(aff, cum, 2)
            for prop in proposals:
                for j in range(CANONICAL.n_joints):
                    coords = np.full((3, C), np.nan)
                    coords_sw = np.full((3, C), np.nan)
                    for c in range(C):
                        if np.isnan(prop[c]):
                            continue
                        k = int(prop[c])
                        coords[:, c] = frame[c][k][3 * j : 3 * j + 3]
                        coords_sw[:, c] = frame[c][k][3 * flip[j] : 3 * flip[j] + 3]
                    coords[2] = np.where(coords[2] > 0, coords[2], 0.0)
                    pt.triangulation_from_best_cameras(cfg, coords, coords_sw, P_all, calib)
            cpu.append(time.process_time() - c0)
    return {"cpu_ms": 1e3 * float(np.median(cpu))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--people", default="1,2,4,8,16,32")
    ap.add_argument("--cams", default="2,4,8,12,16,32")
    ap.add_argument("--pose2sim-site", default="", help="folder holding an importable Pose2Sim (see doc)")
    args = ap.parse_args()
    out: dict = {}
    print("(1) kitchen, CMU motion, default faults: association + triangulation per frame, one core")
    print(
        f"{'people':>6} {'cams':>5} {'cpu ms':>8} {'wall ms':>8} {'best ms':>8} {'found':>6} "
        f"{'Pose2Sim cpu ms':>16} {'ratio':>6}"
    )
    heads = {}
    for n_people, n_cams in ((4, 5), (16, 12)):
        rig, room = kitchen(n_cams)
        scene = make_scene(
            room,
            SceneConfig(n_people=n_people, duration_s=max(args.frames / 25, 0.2) + 0.2, fps=25.0, seed=1),
        )
        xy, sc = frames_for(rig, scene, args.frames)
        r = time_ours(rig, xy, sc)
        p2s = (
            time_pose2sim(args.pose2sim_site, rig, xy[: min(args.frames, 10)], sc[: min(args.frames, 10)])
            if (args.pose2sim_site or _p2s_available())
            else None
        )
        if p2s:
            r["pose2sim_cpu_ms"] = p2s["cpu_ms"]
            r["speedup_vs_pose2sim"] = p2s["cpu_ms"] / r["cpu_ms"]
        heads[f"{n_people}x{n_cams}"] = r
        p2 = f"{r['pose2sim_cpu_ms']:16.1f} {r['speedup_vs_pose2sim']:6.0f}" if p2s else f"{'-':>16} {'-':>6}"
        print(
            f"{n_people:>6} {n_cams:>5} {r['cpu_ms']:8.2f} {r['wall_ms']:8.2f} {r['best_ms']:8.2f} "
            f"{r['people_found']:6.1f} {p2}",
            flush=True,
        )
    out["kitchen"] = heads

    people = [int(v) for v in args.people.split(",")]
    cams = [int(v) for v in args.cams.split(",")]
    print("\n(2) cpu ms per frame, ring rig (radius 6 m) in a round room, procedural walkers, default faults")
    print("people\\cams " + "".join(f"{c:>8}" for c in cams))
    grid = {}
    room = ring_room(5.0)
    scenes = {
        n: make_scene(
            room,
            SceneConfig(
                n_people=n,
                duration_s=args.frames / 25 + 0.2,
                fps=25.0,
                seed=2,
                motion="procedural",
                min_separation_m=0.5,
            ),
        )
        for n in people
    }
    for n in people:
        line = f"{n:>11} "
        for c in cams:
            rig = ring_rig(c, radius_m=6.0, height_m=2.5, fov_h_deg=90.0)
            xy, sc = frames_for(rig, scenes[n], min(args.frames, 20))
            r = time_ours(rig, xy, sc, repeat=3)
            grid[f"{n}x{c}"] = {"cpu_ms": round(r["cpu_ms"], 3), "best_ms": round(r["best_ms"], 3)}
            line += f"{r['cpu_ms']:8.2f}"
        print(line, flush=True)
    out["grid_cpu_ms"] = grid
    out["target_4x5_ms"] = heads["4x5"]["cpu_ms"]
    out["target_16x12_ms"] = heads["16x12"]["cpu_ms"]
    out["target_4x5_best_ms"] = heads["4x5"]["best_ms"]
    out["target_16x12_best_ms"] = heads["16x12"]["best_ms"]
    out["load_avg_1min"] = os.getloadavg()[0]
    print(f"load average (1 min) at the end: {out['load_avg_1min']:.1f} on {os.cpu_count()} cores")
    print("BENCH " + json.dumps(out))


def _p2s_available() -> bool:
    try:
        import importlib.util

        return importlib.util.find_spec("Pose2Sim") is not None
    except Exception:  # noqa: BLE001
        return False


if __name__ == "__main__":
    main()
