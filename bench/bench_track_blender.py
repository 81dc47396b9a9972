"""Headless Blender imports the BVH export of a session (default: the multi-person demo's output).

Fits the session's track file (``tracks fit``), writes one BVH per person (``tracks export --format
bvh``), imports them with Blender's own BVH importer (``blender -b``, see tests/blender_bvh_probe.py)
and checks: one armature per person, frame count and rate, bone heads within 1 cm of the fitted
joints, bone lengths (parent head to child head) constant to < 1 mm.

    python -m roomcap.pipeline.demo --out OUT  # the multi-person demo by default
    .venv/bin/python bench/bench_track_blender.py OUT/Demo_MultiPerson
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_outputs_blender import blender_import, check_armatures  # noqa: E402

from roomcap.outputs.cli import main as tracks  # noqa: E402
from roomcap.outputs.cli import resolve_tracks  # noqa: E402
from roomcap.outputs.skeleton_fit import SkeletonFit, file_sha256  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("session", type=Path, help="a session output folder with track/tracks.npz")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    if shutil.which("blender") is None:
        print("blender not installed (apt-get install -y blender)")
        print("BENCH " + json.dumps({"skipped": True}))
        return
    t0 = time.perf_counter()
    path, session = resolve_tracks(args.session)
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_blender_"))
    assert tracks(["fit", str(path)]) == 0
    fit = SkeletonFit.load(path.with_name("skeleton_fit.npz"), tracks_sha256=file_sha256(path))
    assert tracks(["export", str(path), "--format", "bvh", "--multi", "--out", str(out)]) == 0
    files = {t: out / f"{session}_{t}.bvh" for t in fit.track_id.tolist()}
    t1 = time.perf_counter()
    got = blender_import(list(files.values()), out / "probe.json")
    blender_s = time.perf_counter() - t1
    worst = check_armatures(fit, files, got)
    rep = {
        "session": session,
        "persons": len(files),
        "armatures": got["n_armatures"],
        "frames": {str(t): int(fit.span[:, k].sum()) for k, t in enumerate(fit.track_id.tolist())},
        "fps": fit.fps,
        "head_err_max_mm": round(1000 * worst["head_err_max_m"], 3),
        "bone_length_ptp_max_mm": round(1000 * worst["bone_length_ptp_max_m"], 4),
        "fit_error_median_mm": round(1000 * float(__import__("numpy").nanmedian(fit.fit_error_m)), 1),
        "blender_s": round(blender_s, 1),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    print(
        f"{rep['persons']} persons -> {rep['armatures']} armatures; heads within {rep['head_err_max_mm']} mm "
        f"of the fit; bone lengths vary by at most {rep['bone_length_ptp_max_mm']} mm"
    )
    print("BENCH " + json.dumps(rep))


if __name__ == "__main__":
    main()
