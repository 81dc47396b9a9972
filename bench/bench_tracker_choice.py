"""Which tracker by default: both trackers on Pose2Sim's real two-participant trial, as the stages run them.

    python bench/bench_tracker_choice.py [--shared ../shared]

``S00_P01_T02_Participants1-2`` (4 cameras, 100 frames at 60 fps, OpenPose BODY_25B from the trial's
``pose/`` JSON, the bystander included) made into a session; then, each in its own process (peak
resident memory = ru_maxrss), the greedy tracker (``triangulate_session`` + ``track_session_greedy``) and
the particle tracker (``track_session_particle``), default settings. Against Pose2Sim's own triangulation
of each participant (``pose-3d/*_P1_0-100.trc``, ``*_P2_0-100.trc``, the 13 markers body19 shares with
it) as the reference:
- PCP (upper/lower arms and legs of the shared markers, alpha 0.5) and MPJPE of the nearest track per frame;
- per participant, the frames covered (a track within 0.1 m mean marker distance) and the track ids that
  cover them (one id over the 100 frames = a stable identity);
- the stage's wall time (the particle tracker's first process also compiles its kernels unless cached:
  each tracker is timed twice, the second run in a fresh process with the cache warm) and peak memory.
Ends with ``BENCH {json}``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

TRIAL = ("S00_P01_MultiParticipants", "S00_P01_T02_Participants1-2")


def _child(tracker: str, folder: str) -> None:
    import torch

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    if tracker == "greedy":
        from roomcap.track.greedy_stage import track_session_greedy
        from roomcap.triangulate.stage import triangulate_session

        triangulate_session(folder)
        track_session_greedy(folder)
    else:
        from roomcap.track.stage import track_session_particle

        track_session_particle(folder)
    wall = time.perf_counter() - t0
    print(json.dumps({"wall_s": wall, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def _run(tracker: str, folder: Path) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, "--child", tracker, str(folder)], capture_output=True, text=True, cwd=ROOT
    )
    if out.returncode:
        raise SystemExit(out.stderr[-3000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def _score(xyz: np.ndarray, ref: np.ndarray) -> dict:
    """xyz (T,K,J,3) tracks, ref (T,G,J,3) the reference participants (NaN = marker absent)."""
    from roomcap.triangulate import evaluate as ev

    T = min(len(xyz), len(ref))
    x, g = xyz[:T].astype(np.float64), ref[:T]
    shared = np.isfinite(g).all(-1).any((0, 1))  # the markers the reference has
    x = np.where(shared[None, None, :, None], x, np.nan)
    pcp = ev.pcp(g, x)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d = np.nanmean(np.linalg.norm(x[:, :, None] - g[:, None], axis=-1), -1)  # (T,K,G)
    per = {}
    errs = []
    for gi in range(g.shape[1]):
        dk = np.where(np.isfinite(d[:, :, gi]), d[:, :, gi], np.inf)
        best = dk.argmin(1)
        dist = dk[np.arange(T), best]
        cov = dist < 0.1
        errs.append(dist[cov])
        per[f"P{gi + 1}"] = {
            "frames_covered": int(cov.sum()),
            "track_ids": sorted({int(b) for b in best[cov]}),
            "median_mm": round(1e3 * float(np.median(dist[cov])), 1) if cov.any() else None,
        }
    all_err = np.concatenate(errs)
    return {
        "pcp": round(pcp.actor_average, 4),
        "pcp_per_actor": [round(float(p), 4) for p in pcp.per_actor],
        "mean_marker_error_mm": round(1e3 * float(all_err.mean()), 1) if len(all_err) else None,
        "participants": per,
        "tracks": int(xyz.shape[1]),
    }


def main() -> None:
    if "--child" in sys.argv:
        i = sys.argv.index("--child")
        _child(sys.argv[i + 1], sys.argv[i + 2])
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shared", default=os.environ.get("ROOMCAP_SHARED", str(ROOT.parent / "shared")))
    a = ap.parse_args()
    base = Path(a.shared) / "data" / "pose2sim" / "session-2024"
    if not base.exists():
        print(f"Pose2Sim data not found at {base}; pass --shared")
        print("BENCH " + json.dumps({"skipped": True}))
        return
    from _pose2sim_trc import read_trc_body19
    from test_track_realdata import make_pose2sim_session

    from roomcap.track.trackfile import TrackFile

    trial = base.joinpath(*TRIAL)
    ref = np.stack(
        [read_trc_body19(p) for p in sorted((trial / "pose-3d").glob("*_P[12]_0-100.trc"))], 1
    )  # (T,2,J,3)
    out: dict = {"load_before": round(os.getloadavg()[0], 2)}
    with tempfile.TemporaryDirectory() as d:
        for tracker in ("greedy", "particle"):
            runs = []
            for i in range(2):  # the second process finds the first one's compiled kernels cached
                lay = make_pose2sim_session(
                    trial, base / "S00_Calibration" / "Calib_qualisys.toml", Path(d) / f"{tracker}{i}"
                )
                runs.append(_run(tracker, lay.root))
            tf = TrackFile.load(lay.tracks)
            r = _score(tf.xyz_m, ref)
            r.update(
                wall_s_first=round(runs[0]["wall_s"], 2),
                wall_s=round(runs[1]["wall_s"], 2),
                ms_per_frame=round(1e3 * runs[1]["wall_s"] / tf.n_frames, 1),
                peak_mb=round(runs[1]["peak_mb"], 1),
                source=tf.source,
            )
            out[tracker] = r
            print(
                f"{tracker:>8}: PCP {r['pcp']:.3f} (per participant {r['pcp_per_actor']}), mean marker error "
                f"{r['mean_marker_error_mm']} mm, {r['tracks']} tracks; "
                + "; ".join(
                    f"{p}: {v['frames_covered']} frames by ids {v['track_ids']}, {v['median_mm']} mm"
                    for p, v in r["participants"].items()
                )
                + f"; {r['wall_s']:.2f} s ({r['wall_s_first']:.2f} s first), {r['peak_mb']:.0f} MB"
            )
    out["load_after"] = round(os.getloadavg()[0], 2)
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
