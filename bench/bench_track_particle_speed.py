"""Particle tracker cost per person-frame at 12 cameras, one thread (issue 17, item 5).

The issue's setting: ``python -m synthetic OUT --rig kitchen --cams 12 --people 16 --enter-leave
--seconds S`` written to a temporary folder, its detections loaded as the track stage loads them,
and :class:`track.particle.ParticleTracker` (default config: GRU prior, 300 samples) stepped over
the frames with this tree's code and, in the same run, with the code of ``--baseline REV`` (a git
revision of this repository, extracted with ``git archive`` into a temporary folder and run there in a
subprocess on the same detections). Both use the same seed; the bench reports whether the tracks are
identical (ids and positions bit for bit) and fails if they are not, unless ``--allow-different``.
Frames are timed after the first ``--warm`` (births of the first people excluded); figures: CPU time of
the stepping process per frame divided by the live tracks (ms per person-frame) and the ratio
baseline / current. Runs alternate (current, baseline, current, ...) ``--repeats`` times and the best
of each is reported (the machine is shared). The 1-minute load average is printed.

    python bench/bench_track_particle_speed.py [--seconds 8] [--warm 50] [--baseline REV] [--repeats 2]
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
if "--worker" in sys.argv:  # run the tracker of the tree named after --worker (a baseline extracted by git)
    sys.path.insert(0, sys.argv[sys.argv.index("--worker") + 1])
else:
    sys.path.insert(0, str(ROOT))


def run_tracker(session: Path, warm: int) -> dict:
    """Step the default particle tracker over the session's frames with the code on sys.path."""
    import torch

    torch.set_num_threads(1)
    from calibrate.camera import CameraRig
    from capture.session import SessionLayout
    from track.particle import ParticleConfig, ParticleTracker
    from track.stage import focal_lengths
    from triangulate.stage import _fps, load_detections

    lay = SessionLayout(session)
    rig = CameraRig.load(lay.rig_toml)
    sub, mv = load_detections(lay, rig)
    fps = _fps(lay, mv.t_ns)
    kp = np.moveaxis(mv.xy_px, 0, 1).astype(np.float32)
    sc = np.moveaxis(mv.score, 0, 1).astype(np.float32)
    tr = ParticleTracker(sub.projection_matrices(), focal_lengths(sub), fps, ParticleConfig())
    cpu, ks, ids, xyz = [], [], [], []
    for t in range(len(kp)):
        c0 = time.process_time()
        e = tr.step(kp[t], sc[t], t)
        cpu.append(time.process_time() - c0)
        ks.append(len(tr.tracks))
        ids.append(e.track_id.copy())
        xyz.append(e.xyz_m.copy())
    cpu_a, ks_a = np.asarray(cpu[warm:]), np.asarray(ks[warm:])
    return {
        "frames": len(kp),
        "ms_per_frame": 1e3 * float(cpu_a.mean()),
        "ms_per_person_frame": 1e3 * float(cpu_a.sum() / max(1, ks_a.sum())),
        "mean_tracks": float(ks_a.mean()),
        "ids": ids,
        "xyz": xyz,
    }


def _worker(tree: str, session: str, out: str, warm: int) -> None:
    r = run_tracker(Path(session), warm)
    arrays = {f"ids_{t}": a for t, a in enumerate(r.pop("ids"))}
    arrays.update({f"xyz_{t}": a for t, a in enumerate(r.pop("xyz"))})
    np.savez(out, meta=json.dumps(r), **arrays)


def run_baseline(tree: Path, session: Path, warm: int, tmp: Path) -> dict:
    out = tmp / "baseline.npz"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(tree), str(session), str(out)]
    cmd += ["--warm", str(warm)]
    subprocess.run(cmd, check=True, cwd=tree)
    with np.load(out) as z:
        r = json.loads(str(z["meta"]))
        T = r["frames"]
        r["ids"] = [z[f"ids_{t}"] for t in range(T)]
        r["xyz"] = [z[f"xyz_{t}"] for t in range(T)]
    return r


def identical(a: dict, b: dict) -> tuple[bool, float]:
    """Same ids in every frame and the same positions bit for bit; also the largest position difference."""
    same, worst = len(a["ids"]) == len(b["ids"]), 0.0
    for ia, ib, xa, xb in zip(a["ids"], b["ids"], a["xyz"], b["xyz"], strict=False):
        if not np.array_equal(ia, ib) or xa.shape != xb.shape:
            return False, float("inf")
        if xa.size:
            worst = max(worst, float(np.nanmax(np.abs(xa.astype(np.float64) - xb), initial=0.0)))
        same &= np.array_equal(xa, xb, equal_nan=True)
    return bool(same), worst


def main() -> None:
    if "--worker" in sys.argv:
        i = sys.argv.index("--worker")
        tree, session, out = sys.argv[i + 1 : i + 4]
        warm = int(sys.argv[sys.argv.index("--warm") + 1]) if "--warm" in sys.argv else 50
        _worker(tree, session, out, warm)
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--warm", type=int, default=50)
    ap.add_argument("--people", type=int, default=16)
    ap.add_argument("--cams", type=int, default=12)
    ap.add_argument("--baseline", default="", help="git revision to compare with ('' = none)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--allow-different", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        session = tmp / "kitchen"
        cmd = [sys.executable, "-m", "synthetic", str(session), "--rig", "kitchen", "--cams", str(args.cams)]
        cmd += ["--people", str(args.people), "--enter-leave", "--seconds", str(args.seconds)]
        subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True)
        tree = None
        if args.baseline:
            tree = tmp / "baseline_tree"
            tree.mkdir()
            arch = subprocess.run(
                ["git", "archive", args.baseline], cwd=ROOT, check=True, capture_output=True
            ).stdout
            subprocess.run(["tar", "-x", "-C", str(tree)], input=arch, check=True)
        load0 = os.getloadavg()[0]
        cur, base = None, None
        for _ in range(max(1, args.repeats)):
            r = run_tracker(session, args.warm)
            cur = r if cur is None or r["ms_per_frame"] < cur["ms_per_frame"] else cur
            if tree is not None:
                r = run_baseline(tree, session, args.warm, tmp)
                base = r if base is None or r["ms_per_frame"] < base["ms_per_frame"] else base
    assert cur is not None
    res: dict = {
        "frames": cur["frames"],
        "cams": args.cams,
        "people": args.people,
        "current": {k: v for k, v in cur.items() if k not in ("ids", "xyz")},
        "target_ms_per_person_frame": 1.0,
    }
    line = (
        f"{cur['frames']} frames, {args.cams} cameras, {cur['mean_tracks']:.1f} tracks on average: "
        f"current {cur['ms_per_person_frame']:.2f} ms per person-frame"
    )
    same = True
    if base is not None:
        same, worst = identical(cur, base)
        res["baseline"] = {k: v for k, v in base.items() if k not in ("ids", "xyz")}
        res["baseline_rev"] = args.baseline
        res["ratio_baseline_over_current"] = base["ms_per_person_frame"] / cur["ms_per_person_frame"]
        res["identical_tracks"], res["max_position_diff_m"] = same, worst
        line += (
            f", baseline {args.baseline} {base['ms_per_person_frame']:.2f} ms "
            f"(x{res['ratio_baseline_over_current']:.2f}); identical: {same} (max diff {worst:.2g} m)"
        )
    res["load_1min"] = [load0, os.getloadavg()[0]]
    print(line + f"; load {load0:.2f}")
    print("BENCH " + json.dumps(res))
    if not same and not args.allow_different:
        sys.exit(1)


if __name__ == "__main__":
    main()
