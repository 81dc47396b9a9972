"""`reprocess` with default settings, as a user runs it: peak memory of the process tree and the stage times.

    python bench/bench_reprocess_defaults.py SESSION... [--trackers greedy,particle] [--work DIR]
        [--whole] [--cold] [--stages S] [--tree CHECKOUT]

Each SESSION is a folder with ``calib/rig.toml`` and ``keypoints/<cam>.npz`` (e.g. ``python -m
roomcap.synthetic
OUT --rig kitchen --cams 12 --people 16 --enter-leave --seconds 300``). For each session and tracker the
bench links the session's inputs into a fresh folder under ``--work`` and runs

    reprocess COPY --stages triangulate,track --tracker T

in a subprocess with no other setting (``chunk_s`` at its default ``"auto"``), sampling the resident
memory of the whole process tree every 0.2 s (psutil); it reports the peak of the tree's sum, the wall
time, the ``triangulate_s`` and ``track_s`` of the summary table, the output's layout (single file or
parts), the track's person-frames (track present in a frame) and ``track_s`` per person-frame.

``--whole``: the same session again with ``chunk_s = 0`` for both stages (``--config``), and the two
track files compared array by array (ids, positions, confidence, spread, flags), bit for bit.
``--cold``: the particle stage is run twice, first with an empty numba cache (``NUMBA_CACHE_DIR`` a new
folder: every kernel compiles), then again on a fresh copy of the session with that cache warm (a rerun
on the same output would find the streamed parts done and run nothing).
Besides the wall times each run reports the CPU time of the whole ``reprocess`` process (user + system,
``cpu_s``; with ``--stages track`` that is the track stage plus the command's start-up) and it per
person-frame: on a shared machine the CPU time says what the code costs, the wall time what the load
made of it.
``--tree``: run the code of another checkout (e.g. a worktree of an earlier revision) for a before/after.
Ends with ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from roomcap.track.trackfile import TrackFile, iter_parts  # noqa: E402

REPROCESS = [sys.executable, "-c", "import sys; from pipeline.cli import main; sys.exit(main())"]


def link_session(src: Path, dst: Path) -> None:
    """The session's inputs (rig, detections, session.toml, gt.npz) hard-linked (copied across disks)."""
    if dst.exists():
        shutil.rmtree(dst)
    for rel in ["calib", "keypoints"]:
        (dst / rel).mkdir(parents=True)
        for f in (src / rel).iterdir():
            if f.is_file():
                try:
                    os.link(f, dst / rel / f.name)
                except OSError:
                    shutil.copy2(f, dst / rel / f.name)
    for name in ("session.toml", "gt.npz"):
        if (src / name).exists():
            try:
                os.link(src / name, dst / name)
            except OSError:
                shutil.copy2(src / name, dst / name)


def _children_cpu_s() -> float:
    """User + system CPU seconds of this process's finished (waited-for) children so far."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_tree(cmd: list[str], env: dict, cwd: Path = ROOT) -> tuple[int, str, float, float, float]:
    """Run ``cmd``; returns (exit code, stdout, wall s, peak MB of the resident memory of its tree, CPU s of
    the tree: user + system of the process and the children it waited for)."""
    c0 = _children_cpu_s()
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=cwd, text=True)
        root = psutil.Process(proc.pid)
        peak, shown = 0, t0
        while proc.poll() is None:
            if time.perf_counter() - shown > 60:  # a long run: the peak so far, in case it is stopped
                shown = time.perf_counter()
                print(f"  {shown - t0:.0f} s: peak so far {peak / 2**20:.0f} MB", file=sys.stderr, flush=True)
            try:
                procs = [root, *root.children(recursive=True)]
                rss = 0
                for p in procs:
                    try:
                        rss += p.memory_info().rss
                    except psutil.Error:
                        pass
                peak = max(peak, rss)
            except psutil.Error:
                pass
            time.sleep(0.2)
        wall = time.perf_counter() - t0
        out.seek(0)
        text = out.read()
    return proc.returncode, text, wall, peak / 2**20, _children_cpu_s() - c0


def stage_seconds(text: str, name: str) -> dict[str, float]:
    """``<stage>_s`` columns of the summary table's row of session ``name``."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("session ") and "_s" in line:
            head = line.split()
            for row in lines[i + 1 :]:
                cells = row.split()
                if cells and cells[0] == name:
                    return {
                        h[:-2]: float(c)
                        for h, c in zip(head, cells, strict=False)
                        if h.endswith("_s") and re.fullmatch(r"[0-9.]+", c)
                    }
    return {}


def person_frames(tracks: Path) -> int:
    return int(sum(np.isfinite(tf.xyz_m).any((2, 3)).sum() for tf in iter_parts(tracks)))


def same_tracks(a: Path, b: Path) -> bool:
    ta, tb = TrackFile.load(a), TrackFile.load(b)
    if not (np.array_equal(ta.track_id, tb.track_id) and np.array_equal(ta.frame_index, tb.frame_index)):
        return False
    return all(
        np.array_equal(getattr(ta, k), getattr(tb, k), equal_nan=True)
        for k in ("xyz_m", "confidence", "std_m", "flags")
    )


def run_one(src: Path, work: Path, tracker: str, env: dict, extra: list[str], tag: str, stages: str) -> dict:
    dst = work / f"{src.name}-{tracker}{tag}"
    link_session(src, dst)
    cmd = [*REPROCESS, str(dst), "--stages", stages, "--tracker", tracker, *extra]
    code, text, wall, peak, cpu = run_tree(cmd, env, Path(env["PYTHONPATH"]))
    if code != 0:
        raise SystemExit(f"reprocess failed ({code}):\n{text[-3000:]}")
    tracks = dst / "track" / "tracks.npz"
    layout = "parts" if tracks.with_suffix(".parts").is_dir() else "file"
    st = stage_seconds(text, dst.name)
    pf = person_frames(tracks)
    r = {
        "session": src.name,
        "tracker": tracker,
        "tag": tag,
        "layout": layout,
        "peak_mb": round(peak, 1),
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "cpu_ms_per_person_frame": round(1e3 * cpu / max(pf, 1), 3),
        "triangulate_s": st.get("triangulate"),
        "track_s": st.get("track"),
        "person_frames": pf,
        "track_ms_per_person_frame": round(1e3 * st["track"] / max(pf, 1), 3) if "track" in st else None,
        "load": round(os.getloadavg()[0], 2),
        "dir": str(dst),
    }
    print(json.dumps(r), flush=True)
    return r


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--trackers", default="greedy,particle")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "roomcap_bench_defaults")
    ap.add_argument("--whole", action="store_true")
    ap.add_argument("--cold", action="store_true")
    ap.add_argument("--stages", default="triangulate,track", help="the stages reprocess runs")
    ap.add_argument(
        "--tree", type=Path, default=ROOT, help="the checkout whose code reprocess runs (default: this one)"
    )
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    a.tree = a.tree.resolve()
    env = {**os.environ, "PYTHONPATH": str(a.tree)}
    rows = []
    for src in a.sessions:
        for tracker in a.trackers.split(","):
            run_env = dict(env)
            if a.cold and tracker == "particle":
                run_env["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="numba_cold_", dir=a.work)
            r = run_one(src.resolve(), a.work, tracker, run_env, [], "", a.stages)
            rows.append(r)
            if a.cold and tracker == "particle":  # the same stage again, its kernels now cached
                # into a fresh copy: a rerun on the same output would find the streamed parts done
                w = run_one(src.resolve(), a.work, tracker, run_env, [], "-warm", a.stages)
                for k in (
                    "track_s",
                    "track_ms_per_person_frame",
                    "peak_mb",
                    "cpu_s",
                    "cpu_ms_per_person_frame",
                ):
                    r["warm_" + k] = w[k]
                r["warm_load"] = w["load"]
                print(json.dumps({k: r[k] for k in r if k.startswith("warm")}), flush=True)
            if a.whole:
                cfg = a.work / "whole.toml"
                cfg.write_text("[triangulate.options]\nchunk_s = 0\n[track.options]\nchunk_s = 0\n")
                w = run_one(src.resolve(), a.work, tracker, env, ["--config", str(cfg)], "-whole", a.stages)
                r["whole_peak_mb"], r["whole_layout"] = w["peak_mb"], w["layout"]
                r["whole_track_s"] = w["track_s"]
                r["tracks_equal_whole"] = same_tracks(
                    Path(r["dir"]) / "track" / "tracks.npz", Path(w["dir"]) / "track" / "tracks.npz"
                )
                print(json.dumps({k: r[k] for k in r if "whole" in k}), flush=True)
    head = ("session", "tracker", "layout", "peak MB", "wall s", "track s", "ms/pf")
    print(" ".join(f"{h:>10}" for h in head))
    for r in rows:
        cells = (r["session"], r["tracker"], r["layout"], f"{r['peak_mb']:.0f}", f"{r['wall_s']:.1f}")
        print(
            " ".join(f"{c:>10}" for c in cells),
            f"{r['track_s'] or 0:10.1f} {r['track_ms_per_person_frame'] or 0:10.3f}",
        )
    print("BENCH " + json.dumps(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
