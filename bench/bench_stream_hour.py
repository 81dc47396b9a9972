"""The streamed 3D stages on a long synthetic kitchen session, in bounded memory.

    python bench/bench_stream_hour.py [--minutes 60] [--base-minutes 5] [--metric-minutes 2]
        [--cams 12] [--people 16] [--chunk-s 60] [--work DIR] [--tracker greedy|particle]

Three sessions of the same setup (``python -m roomcap.synthetic OUT --rig kitchen --cams 12 --people 16
--enter-leave --seconds N``): the long one, the memory baseline (``--base-minutes``) and the metric
baseline (``--metric-minutes``). Each runs triangulation and the greedy tracker streamed
(``chunk_s``), every stage in its own process, whose peak resident memory (ru_maxrss) and wall time
are reported. With ``--tracker particle`` the particle tracker (default config, streamed by
:mod:`roomcap.track.particle_chunked`) replaces triangulation + the greedy tracker (it reads the detections
itself). Against the ground truth: MOTA, IDF1 (threshold 0.3 m), PCP (actor average) and MPJPE
on consecutive 60-second windows (the windowed IDF1 counts identity per minute), frame-weighted.
Then the memory-baseline session is run again killed (SIGKILL) at a random moment of each stage
and rerun: the parts must equal the uninterrupted run's byte for byte. Ends with ``BENCH {json}``:
peak memory long / baseline and the metric differences long - short.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _child(args: list[str]) -> dict:
    """Run this file's ``--stage`` in a fresh process; returns its JSON report."""
    out = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), *args], cwd=ROOT, capture_output=True, text=True
    )
    if out.returncode != 0:
        raise SystemExit(f"stage {args} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _stage(name: str, folder: str, chunk_s: float, extra: list[str], tracker: str = "greedy") -> None:
    import numpy as np

    t0 = time.perf_counter()
    rep: dict = {}
    if name == "synthetic":
        from roomcap.synthetic.__main__ import _main

        _main([folder, *extra])
    elif name == "triangulate":
        from roomcap.triangulate.stage import triangulate_session

        triangulate_session(folder, {"chunk_s": chunk_s})
    elif name == "track" and tracker == "particle":
        import torch

        torch.set_num_threads(1)
        from roomcap.track.stage import track_session_particle

        track_session_particle(folder, {"chunk_s": chunk_s})
    elif name == "track":
        from roomcap.track.greedy_stage import track_session_greedy

        track_session_greedy(folder, {"chunk_s": chunk_s})
    elif name == "evaluate":
        rep = _evaluate(folder, np)
        print(_window_table(rep["windows"]), file=sys.stderr)
    rep.update(
        wall_s=time.perf_counter() - t0, peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    )
    print(json.dumps(rep))


def _evaluate(folder: str, np) -> dict:
    """Metrics on 60 s windows of the track parts against gt.npz (both read window by window); ``windows``
    has one row per window (people present per frame, tracks seen, tracks born, identity switches, IDF1,
    MPJPE): where a longer session's metrics differ, it shows when, and with how many people in view."""
    from roomcap.core.fileio import load_npz
    from roomcap.track.trackfile import iter_parts
    from roomcap.triangulate import evaluate as ev

    gt_all = load_npz(Path(folder) / "gt.npz", required=("gt_xyz_m",))["gt_xyz_m"]
    sums = {"mota": 0.0, "idf1": 0.0, "pcp": 0.0, "mpjpe_mm": 0.0}
    n_w, t, tracks, windows = 0.0, 0, set(), []
    for tf in iter_parts(Path(folder) / "track" / "tracks.npz"):
        for a in range(0, tf.n_frames, 1500):
            b = min(a + 1500, tf.n_frames)
            gt = gt_all[t + a : t + b]
            x = tf.xyz_m[a:b].astype(np.float64)
            keep = np.isfinite(x).all(-1).any((0, 2))
            x = x[:, keep]
            ids = set(tf.track_id[keep].tolist())
            born = len(ids - tracks)
            tracks |= ids
            gpres = np.isfinite(gt).all(-1).any(-1)
            if not gpres.any():
                continue
            w = float(gpres.sum())
            m = ev.mot_metrics(gt, x, threshold_m=0.3)
            row = {
                "mota": m.mota,
                "idf1": m.idf1,
                "pcp": ev.pcp(gt, x).actor_average,
                "mpjpe_mm": 1e3 * ev.mpjpe(gt, x)["mpjpe_m"],
            }
            for k, v in row.items():
                sums[k] += w * v
            n_w += w
            windows.append(
                {
                    "start_s": (t + a) / 25.0,
                    "people": w / (b - a),
                    "people_max": int(gpres.sum(1).max()),
                    "tracks": len(ids),
                    "born": born,
                    "id_switches": m.id_switches,
                    **{k: round(v, 4) for k, v in row.items()},
                }
            )
        t += tf.n_frames
    out: dict = {k: v / max(n_w, 1.0) for k, v in sums.items()}
    out["tracks"] = len(tracks)
    out["gt_people"] = int(np.isfinite(gt_all).all(-1).any(-1).any(0).sum())
    out["frames"] = int(t)
    out["windows"] = windows
    return out


def _window_table(windows: list[dict]) -> str:
    """The per-window rows as a table, and IDF1's correlation with the people in view."""
    lines = ["  start  people (max)  tracks  born  id sw   MOTA   IDF1  MPJPE mm"]
    for w in windows:
        lines.append(
            f"{w['start_s'] / 60:5.0f}m  {w['people']:6.1f} ({w['people_max']:2d})  {w['tracks']:6d}"
            f"  {w['born']:4d}  {w['id_switches']:5d}  {w['mota']:.3f}  {w['idf1']:.3f}  {w['mpjpe_mm']:8.1f}"
        )
    if len(windows) > 2:
        import numpy as np

        r = np.corrcoef([w["people"] for w in windows], [w["idf1"] for w in windows])[0, 1]
        lines.append(f"correlation of IDF1 with the people in view, over {len(windows)} windows: {r:+.2f}")
    for lo, hi in CROWDING:  # sessions compared at the same crowding (a longer one has busier minutes)
        sel = [w for w in windows if lo <= w["people"] < hi]
        if sel:
            m = {k: sum(w[k] for w in sel) / len(sel) for k in ("mota", "idf1", "mpjpe_mm")}
            lines.append(
                f"{lo:g}-{hi:g} people in view: {len(sel)} windows, MOTA {m['mota']:.3f} "
                f"IDF1 {m['idf1']:.3f} MPJPE {m['mpjpe_mm']:.1f} mm"
            )
    return "\n".join(lines)


CROWDING = ((0.0, 10.0), (10.0, 12.0), (12.0, 99.0))  # people in view per frame, bins of the window table


def _parts_digest(folder: Path) -> dict:
    idx = json.loads((folder / "index.json").read_text())
    return {k: v["sha256"] for k, v in sorted(idx["parts"].items())}


def _killed_rerun(
    src: Path, dst: Path, stage: str, chunk_s: float, wall_s: float, rng, tracker: str = "greedy"
) -> dict:
    """Run ``stage`` on a copy, SIGKILL it at a random moment, rerun; compare its parts with src's."""
    sub = {"triangulate": ("triangulate", "poses3d.parts"), "track": ("track", "tracks.parts")}[stage]
    target = dst / sub[0] / sub[1]
    for t in (target, dst / "track" / "particle_raw.parts"):
        if t.exists():
            shutil.rmtree(t)
    at = rng.uniform(0.3, 0.8) * wall_s
    p = subprocess.Popen(
        [
            sys.executable,
            str(Path(__file__).resolve()),
            "--stage",
            stage,
            str(dst),
            "--chunk-s",
            str(chunk_s),
            "--tracker",
            tracker,
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    time.sleep(at)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    idx = json.loads((target / "index.json").read_text()) if (target / "index.json").exists() else {}
    done_before = len(idx.get("parts", {}))
    raw = dst / "track" / "particle_raw.parts" / "index.json"
    raw_done = len(json.loads(raw.read_text())["parts"]) if raw.exists() else None
    rerun = _child(["--stage", stage, str(dst), "--chunk-s", str(chunk_s), "--tracker", tracker])
    same = _parts_digest(target) == _parts_digest(src / sub[0] / sub[1])
    return {
        "killed_after_s": round(at, 1),
        "parts_done_at_kill": done_before,
        "filter_parts_done_at_kill": raw_done,
        "parts": len(json.loads((target / "index.json").read_text())["chunks"]),
        "rerun_s": round(rerun["wall_s"], 1),
        "equal": same,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", nargs=2, metavar=("NAME", "FOLDER"), help=argparse.SUPPRESS)
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--base-minutes", type=float, default=5.0)
    ap.add_argument("--metric-minutes", type=float, default=2.0)
    ap.add_argument("--cams", type=int, default=12)
    ap.add_argument("--people", type=int, default=16)
    ap.add_argument("--chunk-s", type=float, default=60.0)
    ap.add_argument("--work", default="/tmp/roomcap_bench_stream")
    ap.add_argument("--no-kill", action="store_true")
    ap.add_argument("--tracker", choices=("greedy", "particle"), default="greedy")
    ap.add_argument("--synthetic", default="[]", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.stage:
        _stage(a.stage[0], a.stage[1], a.chunk_s, json.loads(a.synthetic), a.tracker)
        return 0
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    rng = random.Random(17)
    res: dict = {}
    for label, minutes in (("metric", a.metric_minutes), ("base", a.base_minutes), ("long", a.minutes)):
        folder = work / f"{label}_{minutes:g}min"
        if folder.exists():
            shutil.rmtree(folder)
        gen = [
            "--rig", "kitchen", "--cams", str(a.cams), "--people", str(a.people), "--enter-leave",
            "--seconds", str(60 * minutes), "--chunk-s", str(a.chunk_s),
        ]  # fmt: skip
        r = {"minutes": minutes, "frames": int(round(60 * minutes * 25))}
        # the generator's options after "--synthetic", so this parser does not take --cams/--people
        r["synthetic"] = _child(["--stage", "synthetic", str(folder), "--synthetic", json.dumps(gen)])
        if a.tracker == "greedy":
            r["triangulate"] = _child(["--stage", "triangulate", str(folder), "--chunk-s", str(a.chunk_s)])
        else:  # the particle tracker reads the detections
            r["triangulate"] = {"wall_s": 0.0, "peak_mb": 0.0}
        r["track"] = _child(
            ["--stage", "track", str(folder), "--chunk-s", str(a.chunk_s), "--tracker", a.tracker]
        )
        r["metrics"] = _child(["--stage", "evaluate", str(folder)])
        res[label] = r
        print(_window_table(r["metrics"].pop("windows")), flush=True)
        print(
            f"{label:>6} {minutes:5.1f} min: synthetic {r['synthetic']['wall_s']:7.1f} s "
            f"{r['synthetic']['peak_mb']:6.0f} MB | triangulate {r['triangulate']['wall_s']:7.1f} s "
            f"{r['triangulate']['peak_mb']:6.0f} MB | track {r['track']['wall_s']:6.1f} s "
            f"{r['track']['peak_mb']:6.0f} MB | MOTA {r['metrics']['mota']:.3f} "
            f"IDF1 {r['metrics']['idf1']:.3f} "
            f"PCP {r['metrics']['pcp']:.3f} MPJPE {r['metrics']['mpjpe_mm']:.1f} mm",
            flush=True,
        )
    if not a.no_kill:
        base = work / f"base_{a.base_minutes:g}min"
        copy = work / "killed"
        if copy.exists():
            shutil.rmtree(copy)
        shutil.copytree(base, copy)
        res["killed"] = {
            st: _killed_rerun(base, copy, st, a.chunk_s, res["base"][st]["wall_s"], rng, a.tracker)
            for st in (("triangulate", "track") if a.tracker == "greedy" else ("track",))
        }
        print("killed and rerun:", json.dumps(res["killed"]), flush=True)
    long_, base_, metric = res["long"], res["base"], res["metric"]
    stage_peak = {
        k: max(r["triangulate"]["peak_mb"], r["track"]["peak_mb"]) for k, r in res.items() if k != "killed"
    }
    summary = {
        "bench": "stream_hour",
        "minutes": a.minutes,
        "cams": a.cams,
        "people": a.people,
        "chunk_s": a.chunk_s,
        "tracker": a.tracker,
        "peak_mb_long": round(stage_peak["long"], 1),
        "peak_mb_base": round(stage_peak["base"], 1),
        "peak_ratio_long_over_base": round(stage_peak["long"] / stage_peak["base"], 3),
        "synthetic_peak_mb_long": round(long_["synthetic"]["peak_mb"], 1),
        "wall_s_long": {k: round(long_[k]["wall_s"], 1) for k in ("synthetic", "triangulate", "track")},
        "ms_per_frame_long": {
            k: round(1e3 * long_[k]["wall_s"] / long_["frames"], 2) for k in ("triangulate", "track")
        },
        "metrics_long": {k: round(v, 4) for k, v in long_["metrics"].items()},
        "metrics_short": {k: round(v, 4) for k, v in metric["metrics"].items()},
        "metric_diff_long_minus_short": {
            k: round(long_["metrics"][k] - metric["metrics"][k], 4)
            for k in ("mota", "idf1", "pcp", "mpjpe_mm")
        },
        "killed": res.get("killed"),
        "base_peak_mb": {k: round(base_[k]["peak_mb"], 1) for k in ("triangulate", "track")},
    }
    print("BENCH " + json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
