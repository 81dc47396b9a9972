"""Particle tracker cost per person-frame at 12 cameras, one thread (issue 17, item 5).

The issue's setting: ``python -m synthetic OUT --rig kitchen --cams 12 --people 16 --enter-leave
--seconds S`` written to a temporary folder, its detections loaded as the track stage loads them,
and :class:`track.particle.ParticleTracker` (default config: GRU prior, 300 samples) stepped over
the frames twice in this run: with the current code and with the reference implementation of the
per-camera-pair weights (``observation._log_phi_pairs_gather``, the previous code path, kept as
the fallback for any pair list). Both runs use the same seed and must give identical tracks
(asserted). Frames are timed after the first ``--warm`` (births of the first people excluded);
figures: CPU time of this process per frame divided by the live tracks (ms per person-frame) and
the ratio reference / current. The 1-minute load average is printed (the machine is shared).

    python bench/bench_track_particle_speed.py [--seconds 10] [--warm 50]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def run(kp, sc, P, focal, fps, warm: int) -> tuple[dict, list]:
    from track.particle import ParticleConfig, ParticleTracker

    tr = ParticleTracker(P, focal, fps, ParticleConfig())
    cpu, ks, outs = [], [], []
    for t in range(len(kp)):
        c0 = time.process_time()
        e = tr.step(kp[t], sc[t], t)
        cpu.append(time.process_time() - c0)
        ks.append(len(tr.tracks))
        outs.append((e.track_id.copy(), e.xyz_m.copy()))
    cpu_a, ks_a = np.asarray(cpu[warm:]), np.asarray(ks[warm:])
    return {
        "ms_per_frame": 1e3 * float(cpu_a.mean()),
        "ms_per_person_frame": 1e3 * float(cpu_a.sum() / max(1, ks_a.sum())),
        "mean_tracks": float(ks_a.mean()),
    }, outs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--warm", type=int, default=50)
    ap.add_argument("--people", type=int, default=16)
    ap.add_argument("--cams", type=int, default=12)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    from calibrate.camera import CameraRig
    from capture.session import SessionLayout
    from track import observation as obs
    from track.stage import focal_lengths
    from triangulate.stage import _fps, load_detections

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "kitchen"
        cmd = [sys.executable, "-m", "synthetic", str(out), "--rig", "kitchen", "--cams", str(args.cams)]
        cmd += ["--people", str(args.people), "--enter-leave", "--seconds", str(args.seconds)]
        subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True)
        lay = SessionLayout(out)
        rig = CameraRig.load(lay.rig_toml)
        sub, mv = load_detections(lay, rig)
        fps = _fps(lay, mv.t_ns)
    kp = np.moveaxis(mv.xy_px, 0, 1).astype(np.float32)
    sc = np.moveaxis(mv.score, 0, 1).astype(np.float32)
    P, focal = sub.projection_matrices(), focal_lengths(sub)
    load0 = os.getloadavg()[0]
    cur, out_cur = run(kp, sc, P, focal, fps, args.warm)
    fast = obs.log_phi_pairs

    def reference(phi, pairs, eps):
        g = int(max(1, min(8, 35 // max(1.0, -np.log10(eps)))))
        return obs._log_phi_pairs_gather(phi * phi, pairs, eps, g)

    obs.log_phi_pairs = reference
    try:
        ref, out_ref = run(kp, sc, P, focal, fps, args.warm)
    finally:
        obs.log_phi_pairs = fast
    same = all(
        np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1], equal_nan=True)
        for a, b in zip(out_cur, out_ref, strict=True)
    )
    res = {
        "frames": len(kp),
        "cams": args.cams,
        "people": args.people,
        "current": cur,
        "reference": ref,
        "ratio_ref_over_current": ref["ms_per_person_frame"] / cur["ms_per_person_frame"],
        "identical_tracks": bool(same),
        "target_ms_per_person_frame": 1.0,
        "load_1min": [load0, os.getloadavg()[0]],
    }
    print(
        f"{len(kp)} frames, {args.cams} cameras, {cur['mean_tracks']:.1f} tracks on average: "
        f"current {cur['ms_per_person_frame']:.2f} ms per person-frame, reference "
        f"{ref['ms_per_person_frame']:.2f} ms (x{res['ratio_ref_over_current']:.2f}); identical: {same}; "
        f"load {load0:.2f}"
    )
    print("BENCH " + json.dumps(res))
    if not same:
        sys.exit(1)


if __name__ == "__main__":
    main()
