"""Every output of the user-facing runs, hashed, so a refactor can show it changed no byte.

    python bench/check_outputs.py record DIR [--scenarios demo,greedy,particle,streamed] [--seconds 120]
    python bench/check_outputs.py compare BEFORE/manifest.json AFTER/manifest.json
    python bench/check_outputs.py rehash DIR      # an earlier record hashed again by this version

``record`` runs each scenario as a user would, with the commands of the README, in ``DIR``:

* ``demo``: ``python -m roomcap.pipeline.demo`` on the Pose2Sim multi-person demo (keypoints to report);
* ``greedy`` / ``particle``: ``reprocess SESSION --stages triangulate,track --tracker T`` on a synthetic
  12-camera, 16-person kitchen session of ``--seconds`` (people entering and leaving), made once by
  ``python -m roomcap.synthetic`` and copied for each run;
* ``streamed``: the same session and the greedy tracker, with both 3D stages in 30 s chunks (a pipeline
  TOML setting ``chunk_s``).

It writes ``DIR/manifest.json``: per scenario, each output file's sha256 (the cache records under
``.roomcap/`` and the run summaries hold times and paths, and are left out; a parts index is hashed without
its ``key``, which hashes the input files' mtimes; the report without the stages' code fingerprints),
and the wall time.
``compare`` lists the files that differ (an npz file with the arrays that differ), are missing or are new,
and exits 1 when any does. Ends with one
line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("ROOMCAP_SHARED", REPO.parent / "shared"))
DEMO = SHARED / "data" / "pose2sim" / "demo-wheel-0.10.49" / "Demo_MultiPerson"
SCENARIOS = ("demo", "greedy", "particle", "streamed")
STREAMED_TOML = """\
[triangulate.options]
chunk_s = 30.0
[track.options]
chunk_s = 30.0
"""


def _volatile(rel: Path) -> bool:
    """Files that hold times or absolute paths by design, not results."""
    return ".roomcap" in rel.parts or rel.name.startswith("reprocess_summary") or rel.suffix == ".log"


def _content(p: Path) -> bytes:
    """A file's bytes; a parts index without its ``key`` (a hash of the input files' sizes and mtimes, which
    differ between two copies of a session, not a result); the report without the stages' code
    fingerprints in its provenance table (``0.1.0+code.<sha>``: the hash of the stage's source files,
    which any change of the code changes by design)."""
    data = p.read_bytes()
    if p.name == "report.html":
        data = re.sub(rb"\+code\.[0-9a-f]{12}", b"+code.*", data)
    if p.name == "index.json" and p.parent.name.endswith(".parts"):
        index = json.loads(data)
        index.pop("key", None)
        data = json.dumps(index, sort_keys=True).encode()
    return data


def digest(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if p.is_file() and not _volatile(rel):
            out[rel.as_posix()] = hashlib.sha256(_content(p)).hexdigest()
    return out


def _run(cmd: list[str], log: Path) -> float:
    t0 = time.perf_counter()
    with open(log, "w") as f:
        rc = subprocess.run(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        raise SystemExit(f"{' '.join(cmd)} exited {rc}; see {log}")
    return time.perf_counter() - t0


def record(work: Path, scenarios: list[str], seconds: float) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    result: dict = {"seconds": seconds, "scenarios": {}}
    source = work / "kitchen_source"
    if set(scenarios) - {"demo"} and not source.exists():
        gen = [
            py,
            "-m",
            "roomcap.synthetic",
            str(source),
            "--rig",
            "kitchen",
            "--cams",
            "12",
            "--people",
            "16",
        ]
        _run([*gen, "--enter-leave", "--seconds", f"{seconds:g}"], work / "synthetic.log")
    for name in scenarios:
        folder = work / name
        if folder.exists():
            shutil.rmtree(folder)
        if name == "demo":
            if not DEMO.exists():
                raise SystemExit(f"the Pose2Sim demo is not at {DEMO}; set ROOMCAP_SHARED")
            wall = _run(
                [py, "-m", "roomcap.pipeline.demo", "--recording", str(DEMO), "--out", str(folder)],
                work / "demo.log",
            )
        else:
            shutil.copytree(source, folder)
            cmd = [py, "-m", "roomcap.pipeline.cli", str(folder), "--stages", "triangulate,track"]
            cmd += ["--tracker", "particle" if name == "particle" else "greedy"]
            if name == "streamed":
                toml = work / "streamed.toml"
                toml.write_text(STREAMED_TOML)
                cmd += ["--config", str(toml)]
            wall = _run(cmd, work / f"{name}.log")
        files = digest(folder)
        result["scenarios"][name] = {"wall_s": round(wall, 1), "files": files}
        print(f"{name:>9}: {len(files)} files, {wall:.1f} s", flush=True)
    (work / "manifest.json").write_text(json.dumps(result, indent=1, sort_keys=True))
    return result


def rehash(work: Path) -> dict:
    """The manifest of a record made earlier, its files hashed again as :func:`digest` does now."""
    manifest = json.loads((work / "manifest.json").read_text())
    for name, scenario in manifest["scenarios"].items():
        scenario["files"] = digest(work / name)
    (work / "manifest.json").write_text(json.dumps(manifest, indent=1, sort_keys=True))
    return manifest


def npz_differences(a: Path, b: Path) -> list[str]:
    """The arrays of two npz files that differ (by name)."""
    import numpy as np

    with np.load(a) as x, np.load(b) as y:
        names = sorted(set(x.files) | set(y.files))
        return [
            n
            for n in names
            if n not in x.files
            or n not in y.files
            or not np.array_equal(x[n], y[n], equal_nan=x[n].dtype.kind in "fc")
        ]


def compare(before: dict, after: dict, dirs: tuple[Path, Path] | None = None) -> dict:
    """Per scenario the files that differ, are only before or only after; with the records' folders
    ``dirs``, a differing npz file is listed with the arrays that differ."""
    report: dict = {}
    for name in sorted(set(before["scenarios"]) | set(after["scenarios"])):
        a = before["scenarios"].get(name, {}).get("files")
        b = after["scenarios"].get(name, {}).get("files")
        if a is None or b is None:
            report[name] = {"missing_scenario": "before" if a is None else "after"}
            continue
        differ = sorted(k for k in a.keys() & b.keys() if a[k] != b[k])
        if dirs is not None:
            differ = [
                f"{k} ({', '.join(npz_differences(dirs[0] / name / k, dirs[1] / name / k))})"
                if k.endswith(".npz") and (dirs[0] / name / k).exists() and (dirs[1] / name / k).exists()
                else k
                for k in differ
            ]
        report[name] = {
            "files": len(a),
            "differ": differ,
            "only_before": sorted(a.keys() - b.keys()),
            "only_after": sorted(b.keys() - a.keys()),
        }
    return report


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="run the scenarios and write DIR/manifest.json")
    r.add_argument("dir", type=Path)
    r.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated (default: all)")
    r.add_argument(
        "--seconds", type=float, default=120.0, help="length of the synthetic session (default: 120)"
    )
    h = sub.add_parser("rehash", help="hash the outputs of an earlier record again, as this version does")
    h.add_argument("dir", type=Path)
    c = sub.add_parser("compare", help="compare two manifests")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    a = ap.parse_args()
    if a.cmd == "record":
        names = [s for s in a.scenarios.split(",") if s]
        unknown = sorted(set(names) - set(SCENARIOS))
        if unknown:
            ap.error(f"unknown scenarios {unknown}; valid: {list(SCENARIOS)}")
        res = record(a.dir.resolve(), names, a.seconds)
        summary = {n: {"files": len(s["files"]), "wall_s": s["wall_s"]} for n, s in res["scenarios"].items()}
        print("BENCH " + json.dumps({"bench": "check_outputs", "mode": "record", **summary}))
        return 0
    if a.cmd == "rehash":
        res = rehash(a.dir.resolve())
        print("BENCH " + json.dumps({"bench": "check_outputs", "mode": "rehash", "dir": str(a.dir)}))
        return 0
    report = compare(
        json.loads(a.before.read_text()),
        json.loads(a.after.read_text()),
        (a.before.resolve().parent, a.after.resolve().parent),
    )
    same = True
    for name, r_ in report.items():
        bad = {k: v for k, v in r_.items() if k != "files" and v}
        same &= not bad
        print(f"{name:>9}: " + ("identical" if not bad else json.dumps(bad)))
    counts = {
        n: {k: (len(v) if isinstance(v, list) else v) for k, v in r_.items()} for n, r_ in report.items()
    }
    print("BENCH " + json.dumps({"bench": "check_outputs", "mode": "compare", "identical": same, **counts}))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
