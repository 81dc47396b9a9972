"""Real data: Pose2Sim's session-2024 trials (OpenPose BODY_25B JSON, 4 cameras, 60 fps, Qualisys calib).

Runs our triangulate + greedy track stages on the raw OpenPose JSON (``pose/``, bystanders
included) and compares with Pose2Sim's own triangulated TRC of the same input (the unfiltered
``pose-3d/*_0-100.trc``): median distance per marker, and the reprojection error of both 3D results
into every camera (against the nearest 2D detection, score >= 0.3). Pose2Sim's TRC is y-up
(``zup2yup``: TRC (X, Y, Z) = world (y, z, x)); the axis map is also checked by a fit over all 48
signed permutations. The two-participant trial is checked for two identities without switches.

    .venv/bin/python bench/bench_triangulate_pose2sim.py [--shared ../shared]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _pose2sim_trc import TRC_TO_BODY19, read_trc, trc_to_world  # noqa: E402

from roomcap.calibrate.camera import CameraRig  # noqa: E402
from roomcap.calibrate.formats import import_rig  # noqa: E402
from roomcap.capture.session import SessionLayout  # noqa: E402
from roomcap.core.fileio import save_toml  # noqa: E402
from roomcap.keypoints.openpose_json import read_openpose_folder  # noqa: E402
from roomcap.keypoints.skeletons import CANONICAL, convert  # noqa: E402
from roomcap.track.greedy_stage import track_session_greedy  # noqa: E402
from roomcap.track.trackfile import TrackFile  # noqa: E402
from roomcap.triangulate.poses3d import Poses3D  # noqa: E402
from roomcap.triangulate.stage import triangulate_session  # noqa: E402


def best_axis_map(ours: np.ndarray, trc: np.ndarray) -> tuple[str, float]:
    best = ("", np.inf)
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            m = np.stack([signs[i] * trc[..., perm[i]] for i in range(3)], -1)
            d = np.nanmedian(np.linalg.norm(ours - m, axis=-1))
            if d < best[1]:
                axes = ", ".join(("-" if s < 0 else "") + "XYZ"[p] for p, s in zip(perm, signs, strict=True))
                best = (f"world = ({axes})", d)
    return best


def make_session(trial: Path, rig: CameraRig, root: Path, fps: float = 60.0) -> SessionLayout:
    lay = SessionLayout(root)
    json_dirs = sorted((trial / "pose").glob("cam*_json"))
    names = [d.name.replace("_json", "") for d in json_dirs]
    # explicit map by camera number: pose/cam01_json <-> [cam_01] of the calibration
    rig = CameraRig(tuple(rig[f"cam_{n[3:]}"].replace(name=n) for n in names))
    rig.save(lay.calib_dir / "rig.toml", source="pose2sim Calib_qualisys.toml")
    for d, n in zip(json_dirs, names, strict=True):
        read_openpose_folder(d, camera=n, skeleton="body25b", fps=fps).save(lay.detections(n))
    save_toml(lay.session_toml, {"schema": "session/1", "cameras": names, "fps": fps})
    return lay


def reprojection(rig: CameraRig, lay: SessionLayout, X: np.ndarray) -> np.ndarray:
    """X (T,J,3) body19 world -> per camera/frame/joint error to the nearest 2D detection (score >= .3)."""
    errs = []
    for ci, cam in enumerate(rig.names):
        from roomcap.keypoints.detections import Detections

        d = Detections.load(lay.detections(cam))
        xy, sc = convert(d.xy_px, d.score, d.skeleton, "body19")
        xy = np.where((sc >= 0.3)[..., None], xy, np.nan)  # (T,P,J,2)
        proj = rig[ci].project(X.reshape(-1, 3)).reshape(X.shape[:-1] + (2,))  # (T,J,2)
        e = np.linalg.norm(xy - proj[:, None], axis=-1)  # (T,P,J)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            person = np.nanmean(e, -1)
        person = np.where(np.isfinite(person), person, np.inf)
        k = np.argmin(person, 1)
        errs.append(e[np.arange(len(k)), k])
    return np.stack(errs)  # (C,T,J)


def run_trial(trial: Path, rig: CameraRig, tmp: Path) -> dict:
    lay = make_session(trial, rig, tmp / trial.name)
    t0 = time.perf_counter()
    triangulate_session(lay.root)
    t_tri = time.perf_counter() - t0
    track_session_greedy(lay.root)
    p = Poses3D.load(lay.poses3d)
    tf = TrackFile.load(lay.tracks)
    return {
        "lay": lay,
        "poses": p,
        "tracks": tf,
        "t_tri_s": t_tri,
        "rig": CameraRig.load(lay.calib_dir / "rig.toml"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    default = os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared"))
    ap.add_argument("--shared", default=default)
    args = ap.parse_args()
    base = Path(args.shared) / "data/pose2sim/session-2024"
    if not base.exists():
        print(f"Pose2Sim data not found at {base}; pass --shared")
        print("BENCH " + json.dumps({"skipped": True}))
        return
    rig = import_rig(base / "S00_Calibration/Calib_qualisys.toml")
    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        # --- single participant
        trial = base / "S00_P00_SingleParticipant/S00_P00_T01_BalancingTrial"
        r = run_trial(trial, rig, Path(tmp))
        tf = r["tracks"]
        lengths = np.isfinite(tf.xyz_m).all(-1).any(-1).sum(0)
        main_k = int(np.argmax(lengths))
        ours = tf.xyz_m[:, main_k].astype(np.float64)  # smoothed track of the participant
        raw = r["poses"].xyz_m.astype(np.float64)
        names, trc = read_trc(trial / "pose-3d" / f"{trial.name}_0-100.trc")
        trc_w = trc_to_world(trc)
        j19 = {n: i for i, n in enumerate(CANONICAL.joint_names)}
        cols = [names.index(m) for m in TRC_TO_BODY19]
        js = [j19[b] for b in TRC_TO_BODY19.values()]
        T = min(len(ours), len(trc_w))
        # per frame, the raw pose closest to the TRC (our unsmoothed result for the same person)
        raw_sel = np.full((T, len(js), 3), np.nan)
        for t in range(T):
            d = np.nanmean(np.linalg.norm(raw[t][:, js] - trc_w[t, cols][None], axis=-1), -1)
            if np.isfinite(d).any():
                raw_sel[t] = raw[t, int(np.nanargmin(d)), js]
        axis_map, d_fit = best_axis_map(ours[:T, js], trc[:T, cols])
        dist_s = np.linalg.norm(ours[:T, js] - trc_w[:T, cols], axis=-1)
        dist_r = np.linalg.norm(raw_sel - trc_w[:T, cols], axis=-1)
        print(
            f"single participant ({trial.name}, {T} frames, {len(r['rig'])} cameras): {tf.n_tracks} tracks,"
            f" triangulation {1e3 * r['t_tri_s'] / T:.1f} ms/frame"
        )
        print(f"axis map fitted: {axis_map} (median {1e3 * d_fit:.1f} mm); used: world = (Z, X, Y)")
        print(f"{'marker':<11}{'ours raw':>10}{'ours smooth':>13}   median distance to Pose2Sim [mm]")
        per_marker = {}
        for i, m in enumerate(TRC_TO_BODY19):
            per_marker[m] = float(np.nanmedian(dist_s[:, i]) * 1e3)
            print(f"{m:<11}{1e3 * np.nanmedian(dist_r[:, i]):10.1f}{per_marker[m]:13.1f}")
        print(f"{'all':<11}{1e3 * np.nanmedian(dist_r):10.1f}{1e3 * np.nanmedian(dist_s):13.1f}")
        # reprojection error of both results (body19 joints the TRC has)
        X_trc = np.full((T, 19, 3), np.nan)
        X_trc[:, js] = trc_w[:T, cols]
        X_our_raw = np.full((T, 19, 3), np.nan)
        X_our_raw[:, js] = raw_sel
        X_our_s = np.full((T, 19, 3), np.nan)
        X_our_s[:, js] = ours[:T, js]
        rp = {}
        for name, X in (("pose2sim", X_trc), ("ours_raw", X_our_raw), ("ours_smoothed", X_our_s)):
            e = reprojection(r["rig"], r["lay"], X)[:, :, js]
            rp[name] = (float(np.nanmean(e)), float(np.nanmedian(e)))
            print(f"reprojection error {name:<14} mean {rp[name][0]:6.2f} px  median {rp[name][1]:6.2f} px")
        out["single"] = {
            "median_mm_raw": float(1e3 * np.nanmedian(dist_r)),
            "median_mm_smoothed": float(1e3 * np.nanmedian(dist_s)),
            "per_marker_mm": per_marker,
            "reproj_px": rp,
            "tracks": int(tf.n_tracks),
            "axis_map_fit": axis_map,
        }

        # --- two participants
        trial = base / "S00_P01_MultiParticipants/S00_P01_T02_Participants1-2"
        r = run_trial(trial, rig, Path(tmp))
        tf = r["tracks"]
        present = np.isfinite(tf.xyz_m).all(-1).any(-1)  # (T,K)
        lengths = present.sum(0)
        print(
            f"\ntwo participants ({trial.name}, {tf.n_frames} frames): {tf.n_tracks} tracks, "
            f"frames per track {lengths.tolist()}"
        )
        gts = []
        for pid in ("P1", "P2"):
            n2, trc2 = read_trc(trial / "pose-3d" / f"{trial.name}_{pid}_0-100.trc")
            w = np.full((len(trc2), 19, 3), np.nan)
            c2 = [n2.index(m) for m in TRC_TO_BODY19]
            w[:, js] = trc_to_world(trc2)[:, c2]
            gts.append(w)
        G = np.stack(gts, 1)[: tf.n_frames]  # (T,2,19,3)
        from roomcap.triangulate.evaluate import mean_joint_distance, mot_metrics

        mot = mot_metrics(G, tf.xyz_m[: len(G)].astype(np.float64), threshold_m=0.3)
        per_gt = []
        for g in range(2):
            ids = set()
            for t in range(len(G)):
                d = mean_joint_distance(G[t, g : g + 1], tf.xyz_m[t].astype(np.float64))[0]
                if np.isfinite(d).any() and d.min() < 0.3:
                    ids.add(int(tf.track_id[int(np.argmin(d))]))
            per_gt.append(sorted(ids))
        print(
            f"tracks matched to Pose2Sim's P1, P2 (within 0.3 m): {per_gt}; MOTA {mot.mota:.3f}, "
            f"IDF1 {mot.idf1:.3f}, ID switches {mot.id_switches}, misses {mot.misses}, "
            f"FP {mot.false_positives}"
            " (FP: the bystander, whom Pose2Sim's multi-person output leaves out)"
        )
        out["multi"] = {
            "tracks": int(tf.n_tracks),
            "ids_per_participant": per_gt,
            "mota": mot.mota,
            "idf1": mot.idf1,
            "id_switches": mot.id_switches,
            "frames_per_track": lengths.tolist(),
        }
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
