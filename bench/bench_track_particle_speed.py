"""Particle tracker cost per person-frame at 12 cameras, BLAS at one thread.

The setting: ``python -m roomcap.synthetic OUT --rig kitchen --cams 12 --people 16 --enter-leave
--seconds S`` written to a temporary folder, its detections loaded as the track stage loads them,
and :class:`roomcap.track.particle.ParticleTracker` (default config: GRU prior, 300 samples) stepped over
the frames with this tree's code and, in the same run, with the code of ``--baseline REV`` (a git
revision of this repository, extracted with ``git archive`` into a temporary folder and run there in a
subprocess on the same detections). Both use the same seed; the bench reports whether the tracks are
identical (ids and positions bit for bit) and fails if they are not, unless ``--allow-different`` (or
the tolerance below).
Frames are timed after the first ``--warm`` (births of the first people excluded); figures: CPU time of
the stepping process per frame divided by the live tracks (ms per person-frame), the ratio
baseline / current, and the wall time per person-frame (the filter computes its batch in parts by
threads, ``ParticleConfig.threads``, so its wall time can be below its CPU time). Runs alternate
(current, baseline, current, ...) ``--repeats`` times and the best of each is reported (the machine is
shared). The 1-minute load average is printed.

The first baseline run also writes the filter's state before every 10th frame (from frame 5; a
revision without ``ParticleTracker.state_arrays`` writes none), and this tree's filter steps once from
each: the difference one step makes from the same state, before any divergence builds up. With
``--atol-m TOL`` the tracks need not be identical: the bench passes when every such step gives the
baseline's track ids and no position differs by more than TOL (metres). Either way it reports, for the
whole runs, the first frame whose ids differ, whose positions differ at all and by more than TOL, the
largest position difference before that, over the frames with the same ids and over the tracks with
evidence in both runs (an associated detection; a coasting track drifts its own way), and both runs' raw
per-frame estimates against the session's ground truth (MOTA, IDF1 at 0.3 m, MPJPE). A particle filter
is chaotic: one weight that differs in its last bit can move one resampling index, and from then on the
two runs' samples differ by the filter's Monte-Carlo noise, though both runs track equally well.

    python bench/bench_track_particle_speed.py [--seconds 8] [--warm 50] [--baseline REV] [--repeats 2]
        [--atol-m TOL]
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
if "--worker" in sys.argv:  # the tracker of the tree linked as roomcap in the folder after --worker (git's)
    sys.path.insert(0, sys.argv[sys.argv.index("--worker") + 1])
else:
    sys.path.insert(0, str(ROOT))


def _setup(session: Path):
    """The session's detections (kp, sc) and a function that builds the default tracker for its rig."""
    import torch

    torch.set_num_threads(1)
    from roomcap.calibrate.camera import CameraRig
    from roomcap.capture.session import SessionLayout
    from roomcap.track.particle import ParticleTracker
    from roomcap.track.particle_config import ParticleConfig
    from roomcap.track.particle_io import focal_lengths
    from roomcap.triangulate.multiview import load_detections, session_fps

    lay = SessionLayout(session)
    rig = CameraRig.load(lay.rig_toml)
    sub, mv = load_detections(lay, rig)
    fps = session_fps(lay, mv.t_ns)
    kp = np.moveaxis(mv.xy_px, 0, 1).astype(np.float32)
    sc = np.moveaxis(mv.score, 0, 1).astype(np.float32)
    cfg = ParticleConfig()
    if hasattr(cfg, "threads"):  # the parts a user's run computes at once (this bench's OMP_NUM_THREADS=1
        from roomcap.track.split import MAX_AUTO_THREADS, available_cores  # is for BLAS, not for them)

        cfg = ParticleConfig(threads=min(available_cores(), MAX_AUTO_THREADS))
    return kp, sc, lambda: ParticleTracker(sub.projection_matrices(), focal_lengths(sub), fps, cfg)


def run_tracker(session: Path, warm: int, record: Path | None = None, every: int = 10) -> dict:
    """Step the default particle tracker over the session's frames with the code on sys.path. With
    ``record``, the filter's state before every ``every``-th frame (from frame every // 2) is written there
    (untimed; skipped by a revision without ``state_arrays``)."""
    kp, sc, make = _setup(session)
    tr = make()
    cpu, wall, ks, ids, xyz, seen = [], [], [], [], [], []
    for t in range(len(kp)):
        if record is not None and t % every == every // 2 and hasattr(tr, "state_arrays"):
            np.savez(record / f"state_{t}.npz", **tr.state_arrays())
        c0, w0 = time.process_time(), time.perf_counter()
        e = tr.step(kp[t], sc[t], t)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
        ks.append(len(tr.tracks))
        ids.append(e.track_id.copy())
        xyz.append(e.xyz_m.copy())
        seen.append(np.asarray(getattr(e, "evidence", np.ones(len(e.track_id), bool)), bool).copy())
    cpu_a, ks_a = np.asarray(cpu[warm:]), np.asarray(ks[warm:])
    return {
        "frames": len(kp),
        "ms_per_frame": 1e3 * float(cpu_a.mean()),
        "ms_per_person_frame": 1e3 * float(cpu_a.sum() / max(1, ks_a.sum())),
        "wall_ms_per_person_frame": 1e3 * float(np.sum(wall[warm:]) / max(1, ks_a.sum())),
        "mean_tracks": float(ks_a.mean()),
        "ids": ids,
        "xyz": xyz,
        "seen": seen,
    }


def replay(session: Path, record: Path, base: dict) -> dict:
    """One step of this tree's filter from each state the baseline recorded, against the baseline's own
    step from it: the difference one step makes, before any divergence can build up."""
    kp, sc, make = _setup(session)
    diffs, same = [], True
    for f in sorted(record.glob("state_*.npz"), key=lambda p: int(p.stem.split("_")[1])):
        t = int(f.stem.split("_")[1])
        tr = make()
        with np.load(f) as z:
            tr.load_state_arrays(z)
        e = tr.step(kp[t], sc[t], t)
        ok = np.array_equal(e.track_id, base["ids"][t]) and e.xyz_m.shape == base["xyz"][t].shape
        same &= bool(ok)
        if ok and e.xyz_m.size:
            diffs.append(float(np.nanmax(np.abs(e.xyz_m.astype(np.float64) - base["xyz"][t]), initial=0.0)))
    d = np.asarray(diffs)
    return {
        "steps": len(diffs),
        "same_ids": same,
        "max_diff_m": float(d.max()) if len(d) else None,
        "median_diff_m": float(np.median(d)) if len(d) else None,
    }


def _worker(tree: str, session: str, out: str, warm: int, record: str) -> None:
    import roomcap

    assert Path(roomcap.__file__).resolve().parent == (Path(tree) / "roomcap").resolve(), roomcap.__file__
    r = run_tracker(Path(session), warm, Path(record) if record else None)
    arrays = {f"ids_{t}": a for t, a in enumerate(r.pop("ids"))}
    arrays.update({f"xyz_{t}": a for t, a in enumerate(r.pop("xyz"))})
    arrays.update({f"seen_{t}": a for t, a in enumerate(r.pop("seen"))})
    np.savez(out, meta=json.dumps(r), **arrays)


def run_baseline(tree: Path, session: Path, warm: int, tmp: Path, record: Path | None = None) -> dict:
    out = tmp / "baseline.npz"
    # the tree is the package roomcap (its root maps to it): a folder with a link of that name imports it,
    # ahead of the installed checkout and of any PYTHONPATH (which would run this tree's code twice)
    link = tmp / "baseline_pp"
    if not (link / "roomcap").exists():
        link.mkdir(exist_ok=True)
        (link / "roomcap").symlink_to(tree, target_is_directory=True)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(link), str(session), str(out)]
    cmd += ["--warm", str(warm)] + (["--record", str(record)] if record is not None else [])
    env = {**os.environ, "PYTHONPATH": str(link)}
    subprocess.run(cmd, check=True, cwd=tree, env=env)
    with np.load(out) as z:
        r = json.loads(str(z["meta"]))
        T = r["frames"]
        r["ids"] = [z[f"ids_{t}"] for t in range(T)]
        r["xyz"] = [z[f"xyz_{t}"] for t in range(T)]
        r["seen"] = [z[f"seen_{t}"] for t in range(T)]
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


def compare(a: dict, b: dict, atol_m: float) -> dict:
    """Frame by frame: the first frame whose ids differ, the first whose ids differ or whose positions
    differ by more than ``atol_m``, the first whose positions differ at all, the largest position difference
    over the frames with the same ids and before the first frame beyond ``atol_m``."""
    first_ids, first_beyond, first_any, worst, worst_before, n_same = None, None, None, 0.0, 0.0, 0
    worst_seen = 0.0  # over the tracks with evidence (an associated detection) in both runs
    T = max(len(a["ids"]), len(b["ids"]))
    for t in range(T):
        if t >= min(len(a["ids"]), len(b["ids"])):
            ok, d = False, float("inf")
        else:
            ia, ib, xa, xb = a["ids"][t], b["ids"][t], a["xyz"][t], b["xyz"][t]
            ok = np.array_equal(ia, ib) and xa.shape == xb.shape
            d = float(np.nanmax(np.abs(xa.astype(np.float64) - xb), initial=0.0)) if ok and xa.size else 0.0
        if not ok:
            first_ids = t if first_ids is None else first_ids
            first_beyond = t if first_beyond is None else first_beyond
            continue
        n_same += 1
        worst = max(worst, d)
        both = a["seen"][t] & b["seen"][t]
        if both.any():
            dd = np.abs(xa[both].astype(np.float64) - xb[both])
            worst_seen = max(worst_seen, float(np.nanmax(dd, initial=0.0)))
        if d > 0 and first_any is None:
            first_any = t
        if d > atol_m and first_beyond is None:
            first_beyond = t
        if first_beyond is None:
            worst_before = max(worst_before, d)
    return {
        "frames_same_ids": n_same,
        "first_frame_ids_differ": first_ids,
        "first_frame_beyond_atol": first_beyond,
        "first_frame_positions_differ": first_any,
        "max_position_diff_same_ids_m": worst,
        "max_position_diff_seen_m": worst_seen,
        "max_position_diff_before_beyond_m": worst_before,
        "within_atol": first_beyond is None,
    }


def gt_metrics(run: dict, gt: np.ndarray) -> dict:
    """The run's raw per-frame estimates (no clean-up) against the ground truth gt (T,G,J,3)."""
    from roomcap.triangulate import evaluate as ev

    ids = sorted({int(i) for e in run["ids"] for i in e})
    col = {tid: k for k, tid in enumerate(ids)}
    T, J = len(run["ids"]), gt.shape[2]
    x = np.full((T, len(ids), J, 3), np.nan)
    for t, (ia, xa) in enumerate(zip(run["ids"], run["xyz"], strict=True)):
        if len(ia):
            x[t, [col[int(i)] for i in ia]] = xa
    m = ev.mot_metrics(gt, x, threshold_m=0.3)
    return {"mota": m.mota, "idf1": m.idf1, "mpjpe_mm": 1e3 * ev.mpjpe(gt, x)["mpjpe_m"], "tracks": len(ids)}


def main() -> None:
    if "--worker" in sys.argv:
        i = sys.argv.index("--worker")
        tree, session, out = sys.argv[i + 1 : i + 4]
        warm = int(sys.argv[sys.argv.index("--warm") + 1]) if "--warm" in sys.argv else 50
        record = sys.argv[sys.argv.index("--record") + 1] if "--record" in sys.argv else ""
        _worker(tree, session, out, warm, record)
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--warm", type=int, default=50)
    ap.add_argument("--people", type=int, default=16)
    ap.add_argument("--cams", type=int, default=12)
    ap.add_argument("--baseline", default="", help="git revision to compare with ('' = none)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--allow-different", action="store_true")
    ap.add_argument(
        "--atol-m",
        type=float,
        default=None,
        help="pass when the ids are the same in every frame and positions within this many metres",
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        session = tmp / "kitchen"
        cmd = [
            sys.executable,
            "-m",
            "roomcap.synthetic",
            str(session),
            "--rig",
            "kitchen",
            "--cams",
            str(args.cams),
        ]
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
        with np.load(session / "gt.npz") as z:
            gt = z["gt_xyz_m"].astype(np.float64)
        load0 = os.getloadavg()[0]
        cur, base, steps = None, None, None
        record = tmp / "states"
        record.mkdir()
        for i in range(max(1, args.repeats)):
            r = run_tracker(session, args.warm)
            cur = r if cur is None or r["ms_per_frame"] < cur["ms_per_frame"] else cur
            if tree is not None:
                r = run_baseline(tree, session, args.warm, tmp, record if i == 0 else None)
                base = r if base is None or r["ms_per_frame"] < base["ms_per_frame"] else base
        if base is not None:  # the seeds, detections and states are the same in every run
            steps = replay(session, record, base)
    assert cur is not None
    res: dict = {
        "frames": cur["frames"],
        "cams": args.cams,
        "people": args.people,
        "current": {k: v for k, v in cur.items() if k not in ("ids", "xyz", "seen")},
        "target_ms_per_person_frame": 1.0,
    }
    line = (
        f"{cur['frames']} frames, {args.cams} cameras, {cur['mean_tracks']:.1f} tracks on average: "
        f"current {cur['ms_per_person_frame']:.2f} ms CPU per person-frame "
        f"({cur['wall_ms_per_person_frame']:.2f} ms wall)"
    )
    same = True
    if base is not None:
        same, _ = identical(cur, base)
        cmp = compare(cur, base, 0.0 if args.atol_m is None else args.atol_m)
        res["baseline"] = {k: v for k, v in base.items() if k not in ("ids", "xyz", "seen")}
        res["baseline_rev"] = args.baseline
        res["ratio_baseline_over_current"] = base["ms_per_person_frame"] / cur["ms_per_person_frame"]
        res["identical_tracks"], res["max_position_diff_m"] = same, cmp["max_position_diff_same_ids_m"]
        res["atol_m"], res["compare"], res["one_step"] = args.atol_m, cmp, steps
        res["gt_current"], res["gt_baseline"] = gt_metrics(cur, gt), gt_metrics(base, gt)
        line += (
            f", baseline {args.baseline} {base['ms_per_person_frame']:.2f} ms CPU "
            f"(x{res['ratio_baseline_over_current']:.2f}; {base['wall_ms_per_person_frame']:.2f} ms wall); "
            f"identical: {same}"
        )
        if not same:
            line += (
                f"\n  same ids in {cmp['frames_same_ids']} of {cur['frames']} frames (first differ: "
                f"{cmp['first_frame_ids_differ']}); positions first differ at frame "
                f"{cmp['first_frame_positions_differ']}, by more than {args.atol_m or 0} m at frame "
                f"{cmp['first_frame_beyond_atol']} (max diff before: "
                f"{cmp['max_position_diff_before_beyond_m']:.2g} m); max diff over frames with the same ids "
                f"{cmp['max_position_diff_same_ids_m']:.2g} m, over tracks seen in both "
                f"{cmp['max_position_diff_seen_m']:.2g} m"
            )
        if steps and steps["steps"]:
            line += (
                f"\n  one step from each of {steps['steps']} baseline states: same ids {steps['same_ids']}, "
                f"max diff {steps['max_diff_m']:.2g} m (median {steps['median_diff_m']:.2g} m)"
            )
        g0, g1 = res["gt_current"], res["gt_baseline"]
        line += (
            f"\n  raw estimates against the ground truth: current MOTA {g0['mota']:.4f} IDF1 "
            f"{g0['idf1']:.4f} MPJPE {g0['mpjpe_mm']:.2f} mm ({g0['tracks']} ids); baseline MOTA "
            f"{g1['mota']:.4f} IDF1 {g1['idf1']:.4f} MPJPE {g1['mpjpe_mm']:.2f} mm ({g1['tracks']} ids)"
        )
    res["load_1min"] = [load0, os.getloadavg()[0]]
    print(line + f"; load {load0:.2f}")
    print("BENCH " + json.dumps(res))
    if args.atol_m is not None and base is not None:  # one step within the tolerance, from every state
        ok = bool(steps and steps["steps"] and steps["same_ids"] and steps["max_diff_m"] <= args.atol_m)
        if not ok and not args.allow_different:
            sys.exit(1)
    elif not same and not args.allow_different:
        sys.exit(1)


if __name__ == "__main__":
    main()
