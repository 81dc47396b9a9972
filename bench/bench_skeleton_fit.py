"""The skeleton fit on the synthetic world: CMU mocap people -> cameras -> triangulate + track -> fit.

People play CMU BVH clips (4 s windows at 30 fps, every 2nd or 4th frame of the 60 / 120 fps mocap,
so the mocap's own rotations are known at every frame) placed by a known yaw and offset in a ring room seen
by 6 cameras (detections with 1 px noise, occlusions by the renderer); the greedy tracker's track
file is fitted (:mod:`roomcap.outputs.skeleton_fit`). Reported against the mocap:

- bone-length error: |fitted length - mocap length| (mocap: median over frames of the body19 joints'
  distances), per bone and the mean;
- position error: MPJPE of the track file and of the fitted skeleton against the mocap's joints,
  and what the fit adds (fit - track);
- joint-angle error: for the thigh, shank, upper arm and forearm (each side) and the pelvis, the
  geodesic angle between the fitted segment rotation and the mocap's own (its BVH joint's world
  rotation), after the constant offset between the two rest poses (one rotation per segment, the
  chordal mean over frames); and the knee/elbow flexion angle (angle between the two bones) error.

    .venv/bin/python bench/bench_skeleton_fit.py [--people 4] [--seconds 4] [--seed 0]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from roomcap.keypoints.skeletons import CANONICAL  # noqa: E402
from roomcap.outputs.skeleton_fit import fit_skeletons  # noqa: E402
from roomcap.synthetic import bvh as sbvh  # noqa: E402
from roomcap.synthetic import render, rigs, world  # noqa: E402
from roomcap.track.greedy_stage import track_session_greedy  # noqa: E402
from roomcap.track.trackfile import TrackFile  # noqa: E402
from roomcap.triangulate.stage import triangulate_session  # noqa: E402

SEGMENTS = ("left_hip", "right_hip", "left_knee", "right_knee", "left_shoulder", "right_shoulder",
            "left_elbow", "right_elbow")  # fmt: skip
J = {n: i for i, n in enumerate(CANONICAL.joint_names)}


def kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """R minimising |R a - b| for centred point sets (N,3)."""
    H = a.T @ b
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1, 1, d]) @ U.T


def proj_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def load_person(path: Path, T: int, fps: float, rng) -> dict | None:
    b = sbvh.read_bvh(path)
    step = int(round(b.fps / fps))
    if step < 1 or abs(b.fps / step - fps) > 0.01 * fps:
        return None
    body, _ = sbvh.bvh_to_body19(b)
    off = b.n_frames - len(body)
    n = len(body)
    if n < T * step + 1:
        return None
    a = int(rng.integers(0, n - T * step))
    fr = a + step * np.arange(T)
    xyz = body[fr]
    if np.nanmax(xyz[..., 2]) > 2.0 or np.ptp(xyz[:, J["pelvis"], :2], axis=0).max() > 1.6:
        return None
    idx = {n: sbvh._pick(b, c) for n, c in sbvh._NAME_CANDIDATES.items()}
    want = [idx[s] for s in SEGMENTS]
    hips = sbvh._pick(b, ("Hips", "hip", "CC_Base_Hip", "Hip"))
    want.append(hips if hips is not None else int(np.flatnonzero(b.parents < 0)[0]))
    P, R = b.forward_kinematics(want + [idx[n] for n in SEGMENTS], frames=fr + off)
    # the constant map from file to world axes: Kabsch between the BVH joints and the body19 joints
    pf = P[:, len(want) :].reshape(-1, 3)
    pw = xyz[:, [J[n] for n in SEGMENTS]].reshape(-1, 3)
    A = kabsch(pf - pf.mean(0), pw - pw.mean(0))
    return {"xyz": xyz, "R_world": np.einsum("ab,tkbc->tkac", A, R[:, : len(want)]), "name": path.stem}


def angle_deg(R: np.ndarray) -> np.ndarray:
    c = (np.trace(R, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def flexion(x: np.ndarray, a: int, b: int, c: int) -> np.ndarray:
    u, v = x[:, b] - x[:, a], x[:, c] - x[:, b]
    cos = (u * v).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--people", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    clips = sbvh.list_clips()
    if not clips:
        print("no CMU mocap found (ROOMCAP_SHARED/data/motion)")
        print("BENCH " + json.dumps({"skipped": True}))
        return
    t_start = time.perf_counter()
    rng = np.random.default_rng(args.seed)
    fps = 30.0
    T = int(round(args.seconds * fps))
    people = []
    for i in rng.permutation(len(clips)):
        if len(people) == args.people:
            break
        try:
            p = load_person(clips[int(i)], T, fps, rng)
        except Exception:  # a clip this reader cannot map: take another
            p = None
        if p is not None:
            people.append(p)
    spots = [(-1.1, -1.1), (1.1, 1.1), (-1.1, 1.1), (1.1, -1.1), (0.0, 0.0)]
    gt = np.full((T, len(people), 19, 3), np.nan)
    for k, p in enumerate(people):
        yaw = rng.uniform(0, 2 * np.pi)
        Y = Rotation.from_euler("z", yaw).as_matrix()
        x = p["xyz"].copy()
        c = x[:, J["pelvis"], :2].mean(0)
        x[..., :2] -= c
        x = x @ Y.T
        x[..., :2] += spots[k % len(spots)]
        gt[:, k] = x
        p["R_world"] = np.einsum("ab,tkbc->tkac", Y, p["R_world"])
    room = rigs.ring_room(3.0)
    scene = world.Scene(
        gt,
        np.arange(len(people)),
        fps,
        room,
        tuple(p["name"] for p in people),
        world.SceneConfig(n_people=len(people), duration_s=T / fps, fps=fps, seed=args.seed),
    )
    rig = rigs.ring_rig(6, 3.0, seed=args.seed)
    rend = render.render(scene, rig, render.RenderConfig(noise_px=1.0, seed=args.seed))
    tmp = Path(tempfile.mkdtemp(prefix="bench_skelfit_"))
    world.write_session(scene, rend, rig, tmp / "S")
    triangulate_session(tmp / "S")
    track_session_greedy(tmp / "S")
    tf = TrackFile.load(tmp / "S" / "track" / "tracks.npz")
    t_fit = time.perf_counter()
    fit = fit_skeletons(tf, skip_unfittable=True)
    fit_s = time.perf_counter() - t_fit
    P = fit.joint_positions()
    Gs = {k: fit.global_rotations(k) for k in range(len(fit.track_id))}
    rows = []
    for g, p in enumerate(people):
        # the track of this person: nearest pelvis over the frames both have
        pel = J["pelvis"]
        d = [
            np.nanmean(
                np.linalg.norm(tf.xyz_m[:, tf.track_id.tolist().index(t), pel] - gt[:, g, pel], axis=-1)
            )
            for t in fit.track_id.tolist()
        ]
        if not d or np.nanmin(d) > 0.3:
            continue
        kf = int(np.nanargmin(d))
        kt = tf.track_id.tolist().index(int(fit.track_id[kf]))
        span = fit.span[:, kf] & np.isfinite(gt[:, g]).all((-1, -2))
        x_gt = gt[span, g]
        x_tr = tf.xyz_m[span, kt].astype(np.float64)
        x_fit = P[span, kf]
        e_tr = np.nanmean(np.linalg.norm(x_tr - x_gt, axis=-1))
        e_fit = np.nanmean(np.linalg.norm(x_fit - x_gt, axis=-1))
        known = np.isfinite(x_tr).all(-1)
        e_fit_same = np.mean(np.linalg.norm(x_fit - x_gt, axis=-1)[known])
        e_tr_same = np.mean(np.linalg.norm(x_tr - x_gt, axis=-1)[known])
        bl = []
        for j, par in enumerate(CANONICAL.parents):
            if par < 0:
                continue
            L_gt = np.median(np.linalg.norm(x_gt[:, j] - x_gt[:, par], axis=-1))
            bl.append(abs(fit.bone_length_m[kf, fit.track_joints[j]] - L_gt))
        seg_err = {}
        G = Gs[kf][span]
        Rm = p["R_world"][span]
        for s, name in enumerate((*SEGMENTS, "pelvis")):
            Gf = G[:, fit.track_joints[J[name]]]
            C = proj_so3(np.einsum("tba,tbc->ac", Rm[:, s], Gf))  # mean of Rm^T Gf
            err = angle_deg(np.einsum("tba,tbc->tac", Rm[:, s] @ C, Gf))
            seg_err[name] = float(np.median(err))
        flex = {}
        for a, b, c in (
            ("left_hip", "left_knee", "left_ankle"),
            ("right_hip", "right_knee", "right_ankle"),
            ("left_shoulder", "left_elbow", "left_wrist"),
            ("right_shoulder", "right_elbow", "right_wrist"),
        ):
            fg = flexion(x_gt, J[a], J[b], J[c])
            ff = flexion(x_fit, J[a], J[b], J[c])
            flex[b] = float(np.median(np.abs(ff - fg)))
        rows.append(
            {
                "clip": p["name"],
                "track": int(fit.track_id[kf]),
                "frames": int(span.sum()),
                "mpjpe_track_mm": round(1000 * e_tr, 1),
                "mpjpe_fit_mm": round(1000 * e_fit, 1),
                "mpjpe_fit_minus_track_mm_same_joints": round(1000 * (e_fit_same - e_tr_same), 1),
                "bone_length_err_mean_mm": round(1000 * float(np.mean(bl)), 1),
                "bone_length_err_max_mm": round(1000 * float(np.max(bl)), 1),
                "segment_angle_err_median_deg": {k: round(v, 1) for k, v in seg_err.items()},
                "flexion_err_median_deg": {k: round(v, 1) for k, v in flex.items()},
            }
        )
    for r in rows:
        seg = np.median(list(r["segment_angle_err_median_deg"].values()))
        flx = np.median(list(r["flexion_err_median_deg"].values()))
        print(
            f"{r['clip']:>16s} track {r['track']:3d} {r['frames']:4d} fr | MPJPE track "
            f"{r['mpjpe_track_mm']:5.1f} fit {r['mpjpe_fit_mm']:5.1f} mm (fit adds "
            f"{r['mpjpe_fit_minus_track_mm_same_joints']:+.1f}) | bone err mean "
            f"{r['bone_length_err_mean_mm']:4.1f} max {r['bone_length_err_max_mm']:4.1f} mm | segment angle "
            f"median {seg:4.1f} deg | flexion {flx:4.1f} deg"
        )
    seg_all = [v for r in rows for v in r["segment_angle_err_median_deg"].values()]
    flex_all = [v for r in rows for v in r["flexion_err_median_deg"].values()]
    out = {
        "people": len(people),
        "matched": len(rows),
        "frames": T,
        "fps": fps,
        "fit_s": round(fit_s, 2),
        "fit_ms_per_person_frame": round(1000 * fit_s / max(1, int(fit.span.sum())), 2),
        "mpjpe_track_mm": round(float(np.mean([r["mpjpe_track_mm"] for r in rows])), 1),
        "mpjpe_fit_mm": round(float(np.mean([r["mpjpe_fit_mm"] for r in rows])), 1),
        "fit_adds_mm": round(float(np.mean([r["mpjpe_fit_minus_track_mm_same_joints"] for r in rows])), 1),
        "bone_length_err_mean_mm": round(float(np.mean([r["bone_length_err_mean_mm"] for r in rows])), 1),
        "segment_angle_err_median_deg": round(float(np.median(seg_all)), 1),
        "flexion_err_median_deg": round(float(np.median(flex_all)), 1),
        "per_person": rows,
        "seconds": round(time.perf_counter() - t_start, 1),
    }
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
