"""Real data: the particle tracker on Pose2Sim's two-participant trial (OpenPose BODY_25B JSON, 4 cameras).

Tracks ``S00_P01_T02_Participants1-2`` (100 frames, 60 fps; the raw ``pose/`` JSON, bystander
included) with the default GRU prior and with the constant-velocity prior, and reports: tracks and
their frame counts (identity stability: the two participants must be single tracks over the whole
clip), the largest frame-to-frame pelvis jump, per-joint uncertainty ``std_m`` against the number of
cameras that see the joint, the reprojection error of the output into every camera, and the distance
to Pose2Sim's own triangulation (``pose-3d/*.trc``) for the matching participant. A figure
(``--figure PATH``, PNG) shows std vs views and the tracks' pelvis paths from above.

    .venv/bin/python bench/bench_track_pose2sim.py [--shared ../shared] [--figure track_pose2sim.png]
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
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _pose2sim_trc import read_trc_body19  # noqa: E402
from test_track_realdata import make_pose2sim_session  # noqa: E402

from roomcap.calibrate.camera import CameraRig  # noqa: E402
from roomcap.keypoints.skeletons import CANONICAL  # noqa: E402
from roomcap.track.particle import ParticleTracker  # noqa: E402
from roomcap.track.particle_config import ParticleConfig  # noqa: E402
from roomcap.track.particle_io import focal_lengths  # noqa: E402
from roomcap.track.particle_offline import track_sequence  # noqa: E402
from roomcap.triangulate.multiview import load_detections  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
    )
    ap.add_argument("--figure", default="")
    args = ap.parse_args()
    base = Path(args.shared) / "data/pose2sim/session-2024"
    if not base.exists():
        print(f"Pose2Sim data not found at {base}; pass --shared")
        print("BENCH " + json.dumps({"skipped": True}))
        return
    import torch

    torch.set_num_threads(1)
    trial = base / "S00_P01_MultiParticipants" / "S00_P01_T02_Participants1-2"
    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        lay = make_pose2sim_session(trial, base / "S00_Calibration/Calib_qualisys.toml", Path(d) / "s")
        rig = CameraRig.load(lay.rig_toml)
        sub, mv = load_detections(lay, rig)
    kp, sc = np.moveaxis(mv.xy_px, 0, 1), np.moveaxis(mv.score, 0, 1)
    trc_files = sorted((trial / "pose-3d").glob("*.trc"))
    trc = [read_trc_body19(p) for p in trc_files]
    results = {}
    for motion in ("gru", "constant_velocity"):
        tr = ParticleTracker(
            sub.projection_matrices(), focal_lengths(sub), 60.0, ParticleConfig(motion=motion)
        )
        t0 = time.perf_counter()
        res = track_sequence(tr, kp, sc)
        dt = time.perf_counter() - t0
        frames = np.isfinite(res.xyz_m).all(-1).any(-1).sum(0)
        full = frames == len(kp)
        pel = res.xyz_m[:, full, CANONICAL.index("pelvis")]
        jump = float(np.nanmax(np.linalg.norm(np.diff(pel, axis=0), axis=-1))) if full.any() else float("nan")
        ok = np.isfinite(res.std_m)
        by_views = {
            int(v): 1e3 * float(np.nanmedian(res.std_m[ok & (res.n_views == v)]))
            for v in range(len(sub) + 1)
            if (ok & (res.n_views == v)).any()
        }
        # reprojection error of the output to the detection it explains best (score >= 0.3), per camera
        reproj = []
        for c in range(len(sub)):
            X = res.xyz_m.reshape(-1, 3).astype(np.float64)
            good = np.isfinite(X).all(-1)
            uv = np.full((len(X), 2), np.nan)
            uv[good] = sub[c].project(X[good])
            uv = uv.reshape(res.xyz_m.shape[:-1] + (2,))  # (T,K,J,2)
            # detections are undistorted already (load_detections); project() distorts, so undistort it back
            det = np.where((mv.score[c] >= 0.3)[..., None], mv.xy_px[c], np.nan)  # (T,P,J,2)
            uv_u = sub[c].undistort_px(uv)
            e = np.linalg.norm(uv_u[:, :, None] - det[:, None], axis=-1)  # (T,K,P,J)
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                per = np.nanmean(e, -1)
                best = np.nanargmin(np.where(np.isfinite(per), per, np.inf), -1)
            reproj.append(np.take_along_axis(e, best[..., None, None], 2)[:, :, 0])
        reproj = np.concatenate([r[np.isfinite(r)] for r in reproj])
        # Pose2Sim's own triangulation of each participant: distance to our closest full-length track
        dist = []
        for y in trc:
            n = min(len(y), len(kp))
            dd = [
                np.nanmedian(np.linalg.norm(res.xyz_m[:n, k] - y[:n], axis=-1)) for k in np.flatnonzero(full)
            ]
            dist.append(1e3 * float(np.nanmin(dd)) if dd else float("nan"))
        dist = dict(zip([p.name for p in trc_files], dist, strict=True))
        results[motion] = res
        out[motion] = {
            "tracks": int(len(res.track_id)),
            "frames_per_track": frames.tolist(),
            "full_length_tracks": int(full.sum()),
            "max_pelvis_jump_m": jump,
            "median_std_mm_by_views": by_views,
            "reproj_median_px": float(np.median(reproj)),
            "to_pose2sim_trc_median_mm": dist,
            "ms_per_frame": 1e3 * dt / len(kp),
        }
        print(
            f"{motion}: {len(res.track_id)} tracks, frames per track {frames.tolist()}, "
            f"max pelvis jump {1e3 * jump:.1f} mm/frame, {1e3 * dt / len(kp):.1f} ms/frame"
        )
        print(
            "   median std_m by cameras seeing the joint: "
            + ", ".join(f"{v} views {s:.1f} mm" for v, s in by_views.items())
        )
        print(
            f"   reprojection median {np.median(reproj):.2f} px; median distance to Pose2Sim's TRC per "
            f"participant: {', '.join(f'{n}: {x:.0f} mm' for n, x in dist.items())}"
        )
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        res = results["gru"]
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        ok = np.isfinite(res.std_m)
        vs = sorted(set(res.n_views[ok].tolist()))
        ax[0].boxplot(
            [1e3 * res.std_m[ok & (res.n_views == v)] for v in vs],
            tick_labels=[str(v) for v in vs],
            showfliers=False,
        )
        ax[0].set_yscale("log")
        ax[0].set_xlabel("cameras seeing the joint")
        ax[0].set_ylabel("std_m per joint [mm]")
        ax[0].set_title("uncertainty vs views (Pose2Sim, GRU prior)")
        for k, tid in enumerate(res.track_id):
            p = res.xyz_m[:, k, CANONICAL.index("pelvis")]
            ax[1].plot(p[:, 0], p[:, 1], label=f"track {tid}")
        ax[1].set_aspect("equal")
        ax[1].legend()
        ax[1].set_title("pelvis paths from above [m]")
        fig.tight_layout()
        fig.savefig(args.figure, dpi=100)
        print(f"figure: {args.figure}")
    ok = all(out[m]["full_length_tracks"] >= 2 and out[m]["max_pelvis_jump_m"] < 0.1 for m in out)
    out["stable_identities"] = bool(ok)
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
