"""What each stage output was made from, so reruns skip what is up to date.

Every stage writes ``<out>/.roomcap/provenance/<stage>.json`` after its outputs:
the input files' fingerprints, the stage configuration, the model sha256 and
the package version, and the fingerprints of the outputs. A stage is up to
date when that record matches what it would be made from now and its outputs
are unchanged. The record is written last (atomically), so a run killed
mid-stage leaves no record and the stage reruns.

Input fingerprints are sha256 of the file (for large files: of the size plus
the first and last 4 MiB). Outputs are recorded by the size and the full sha256
of each file (a parts folder: of each of its files), and a stage is trusted
only while its outputs still have them; otherwise it reruns and says which
file changed and how. A stat cache (size, mtime, inode, ctime) saves hashing
unchanged files again, which keeps a no-op rerun of many sessions fast; any
write, rename or replacement of a file changes its ctime (which programs cannot
set back), so a changed file is always hashed again.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from roomcap.core.fileio import atomic_write_text, sha256_file

_FULL_HASH_LIMIT = 64 << 20
_EDGE = 4 << 20


def package_version() -> str:
    try:
        return metadata.version("roomcap")
    except metadata.PackageNotFoundError:
        return "0+unknown"


# The stages in graph order (each reads only what the ones before it wrote).
STAGES = ("calibration", "keypoints", "triangulate", "track", "forecast", "report")

# What each stage's output depends on: the modules that run it (their import closure within the project is
# fingerprinted, :func:`code_files`) and the data files its code reads (globs relative to the repository). A
# change there reruns the stage even while the package version stays the same (development checkouts, patched
# installs); a change anywhere else reruns nothing.
STAGE_CODE: dict[str, tuple[str, ...]] = {
    "calibration": ("roomcap.calibrate.formats", "roomcap.pipeline.session_inputs"),
    "keypoints": (
        "roomcap.keypoints.video",
        "roomcap.keypoints.registry",
        "roomcap.keypoints.runtime",
        "roomcap.keypoints.openpose_json",
        "roomcap.pipeline.session_inputs",
    ),
    "triangulate": ("roomcap.triangulate.stage", "roomcap.pipeline.session_inputs"),
    "track": ("roomcap.track.stage", "roomcap.track.greedy_stage", "roomcap.pipeline.session_inputs"),
    "forecast": ("roomcap.forecast.runtime.preview",),
    "report": ("roomcap.pipeline.report",),
}
STAGE_DATA: dict[str, tuple[str, ...]] = {
    "keypoints": ("keypoints/models/*.toml",),
    "track": ("track/checkpoints/*",),
    "forecast": ("forecast/configs/*.toml",),
    "report": (
        "pipeline/report_assets/*.html",
        "pipeline/report_assets/*.css",
        "pipeline/report_assets/*.js",
    ),
}
_ROOT = Path(__file__).resolve().parents[1]
_code_cache: dict[str, str] = {}


def _module_file(name: str, root: Path) -> Path | None:
    """The source file of project module ``name`` (``roomcap.a.b`` -> ``a/b.py`` or ``a/b/__init__.py``)."""
    rel = Path(*name.split(".")[1:])
    for f in (
        (root / rel / "__init__.py", (root / rel).with_suffix(".py")) if rel.parts else [root / "__init__.py"]
    ):
        if f.is_file():
            return f
    return None


def _imported(tree: ast.AST) -> set[str]:
    """The ``roomcap`` modules a module's source imports anywhere (inside functions too), with the packages
    above them (importing ``roomcap.a.b`` runs ``roomcap/a/__init__.py``); ``from roomcap.a import b`` names
    ``roomcap.a.b`` as a candidate, kept by the caller when it is a module."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names if a.name.split(".")[0] == "roomcap")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "roomcap":
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    with_parents = set()
    for n in names:
        parts = n.split(".")
        with_parents.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
    return with_parents


def code_files(stage: str, root: Path | None = None) -> list[Path]:
    """The source files a stage runs (the import closure of its modules in :data:`STAGE_CODE`) and the data
    files of :data:`STAGE_DATA` under ``root`` (the installed package's folder by default), sorted; [] for
    unknown stages."""
    root = root or _ROOT
    todo = list(STAGE_CODE.get(stage, ()))
    seen: dict[str, Path] = {}
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        f = _module_file(name, root)
        if f is None:  # a name imported from a module, not a module
            continue
        seen[name] = f
        todo.extend(_imported(ast.parse(f.read_bytes(), str(f))) - set(seen))
    data = [f for pattern in STAGE_DATA.get(stage, ()) for f in root.glob(pattern) if f.is_file()]
    return sorted(set(seen.values()) | set(data))


def code_fingerprint(stage: str, stat_cache: dict[str, Any] | None = None) -> str:
    """sha256 (12 hex digits) of the files a stage's output depends on (:func:`code_files`); "" for unknown
    stages."""
    if stage in _code_cache:
        return _code_cache[stage]
    h = hashlib.sha256()
    for f in code_files(stage, _ROOT):
        h.update(f.relative_to(_ROOT).as_posix().encode())
        h.update(path_fingerprint(f, stat_cache).encode())
    fp = h.hexdigest()[:12] if stage in STAGE_CODE else ""
    _code_cache[stage] = fp
    return fp


def stage_version(stage: str, stat_cache: dict[str, Any] | None = None) -> str:
    """The package version and the stage's code fingerprint, e.g. ``0.1.0+code.3f2a9c01b7de``."""
    code = code_fingerprint(stage, stat_cache)
    return f"{package_version()}+code.{code}" if code else package_version()


def file_fingerprint(path: Path) -> str:
    """sha256 of the file; of a file over ``_FULL_HASH_LIMIT``, of its size and its first and last ``_EDGE``
    bytes."""
    size = path.stat().st_size
    if size <= _FULL_HASH_LIMIT:
        return sha256_file(path)
    h = hashlib.sha256(str(size).encode())
    with open(path, "rb") as f:
        h.update(f.read(_EDGE))
        f.seek(size - _EDGE)
        h.update(f.read(_EDGE))
    return h.hexdigest()


def path_fingerprint(path: Path, stat_cache: dict[str, Any] | None = None) -> str:
    """Fingerprint of a file or a folder (its files, by relative name)."""
    path = Path(path)
    if path.is_dir():
        h = hashlib.sha256()
        for p in sorted(q for q in path.rglob("*") if q.is_file() and not q.name.startswith(".")):
            h.update(p.relative_to(path).as_posix().encode())
            h.update(path_fingerprint(p, stat_cache).encode())
        return h.hexdigest()
    return _cached(path, file_fingerprint, "", stat_cache)


def _stamp(st: os.stat_result) -> list[int]:
    """What changes when a file is written, renamed over or replaced (ctime cannot be set by a program)."""
    return [st.st_size, st.st_mtime_ns, st.st_ino, st.st_ctime_ns]


def _cached(path: Path, fn: Any, kind: str, stat_cache: dict[str, Any] | None) -> str:
    st = path.stat()
    key = kind + str(path.resolve())
    stamp = _stamp(st)
    if stat_cache is not None:
        hit = stat_cache.get(key)
        if hit and hit[0] == stamp:
            return str(hit[1])
    fp = str(fn(path))
    if stat_cache is not None:
        stat_cache[key] = [stamp, fp]
    return fp


def output_files(outputs: list[Path], out_root: Path, stat_cache: dict[str, Any] | None = None) -> dict:
    """``{path relative to out_root: {"size": bytes, "sha256": hex}}`` of every file of ``outputs`` (a folder:
    each of its files but dot-files, which are temporaries)."""
    out: dict[str, dict[str, Any]] = {}
    for p in outputs:
        files = (
            sorted(q for q in p.rglob("*") if q.is_file() and not q.name.startswith("."))
            if p.is_dir()
            else [p]
        )
        for f in files:
            out[f.relative_to(out_root).as_posix()] = {
                "size": f.stat().st_size,
                "sha256": _cached(f, sha256_file, "sha256 ", stat_cache),
            }
    return out


def output_changes(recorded: dict[str, dict[str, Any]], now: dict[str, dict[str, Any]]) -> str:
    """How the outputs differ from what the stage recorded, as a sentence ('' when they are the same)."""
    said = []
    for name in sorted(set(recorded) | set(now)):
        a, b = recorded.get(name), now.get(name)
        if a == b:
            continue
        if b is None:
            said.append(f"{name} is missing")
        elif a is None:
            said.append(f"{name} was not written by the stage")
        elif a.get("size") != b["size"]:
            said.append(f"{name} has {b['size']} bytes, the stage wrote {a.get('size')}")
        else:
            said.append(f"{name} has other content than the stage wrote (sha256 differs, same size)")
    return "; ".join(said[:3]) + (f" (and {len(said) - 3} more)" if len(said) > 3 else "")


@dataclass(frozen=True)
class StageRecord:
    stage: str
    inputs: dict[str, str]  # path -> fingerprint
    config: dict[str, Any]
    model_sha256: str
    version: str
    outputs: dict[str, str]  # path relative to the session output -> fingerprint
    # each output file (a folder's files), relative to the session output -> {"size", "sha256"}
    output_files: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "stage": self.stage,
            "inputs": self.inputs,
            "config": self.config,
            "model_sha256": self.model_sha256,
            "version": self.version,
            "outputs": self.outputs,
            "output_files": self.output_files,
        }


class ProvenanceStore:
    """The records of one session output folder."""

    def __init__(self, out_root: Path):
        self.out_root = Path(out_root)
        self.dir = self.out_root / ".roomcap" / "provenance"
        self._stat_path = self.out_root / ".roomcap" / "stat_cache.json"
        try:
            self.stat_cache: dict[str, Any] = json.loads(self._stat_path.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            self.stat_cache = {}

    def fingerprint_inputs(self, inputs: list[Path]) -> dict[str, str]:
        return {str(p): path_fingerprint(p, self.stat_cache) for p in inputs}

    def fingerprint_outputs(self, outputs: list[Path]) -> dict[str, str]:
        return {
            p.relative_to(self.out_root).as_posix(): path_fingerprint(p, self.stat_cache) for p in outputs
        }

    def output_files(self, outputs: list[Path]) -> dict[str, dict[str, Any]]:
        return output_files(outputs, self.out_root, self.stat_cache)

    def load(self, stage: str) -> dict[str, Any] | None:
        try:
            return json.loads((self.dir / f"{stage}.json").read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def is_current(
        self,
        stage: str,
        inputs: dict[str, str],
        config: dict[str, Any],
        model_sha256: str,
        outputs: list[Path],
        version: str | None = None,
    ) -> bool:
        return not self.why_stale(stage, inputs, config, model_sha256, outputs, version)[0]

    def why_stale(
        self,
        stage: str,
        inputs: dict[str, str],
        config: dict[str, Any],
        model_sha256: str,
        outputs: list[Path],
        version: str | None = None,
    ) -> tuple[str, str]:
        """``("", "")`` when the stage's record matches what it would be made from now and its outputs are
        the files it wrote (size and sha256); else (what differs: ``record``, ``inputs``, ``config``,
        ``model_sha256``, ``version`` or ``outputs``, a sentence)."""
        rec = self.load(stage)
        if rec is None:
            return "record", "no record of a finished run"
        want = {
            "inputs": inputs,
            "config": json.loads(json.dumps(config)),
            "model_sha256": model_sha256,
            "version": version or package_version(),
        }
        for k, v in want.items():
            if rec.get(k) != v:
                return k, f"its {k} changed"
        missing = [p.relative_to(self.out_root).as_posix() for p in outputs if not p.exists()]
        if missing:
            return "outputs", f"{', '.join(missing)} {'is' if len(missing) == 1 else 'are'} missing"
        if "output_files" not in rec:  # a record from before sizes and full hashes were kept
            same = rec.get("outputs") == self.fingerprint_outputs(outputs)
            return ("", "") if same else ("outputs", "its outputs changed since the stage wrote them")
        changes = output_changes(rec["output_files"], self.output_files(outputs))
        return ("outputs", changes) if changes else ("", "")

    def record(self, rec: StageRecord) -> None:
        atomic_write_text(self.dir / f"{rec.stage}.json", json.dumps(rec.to_json(), indent=1, sort_keys=True))
        self.save_stat_cache()

    def invalidate(self, stage: str) -> None:
        try:
            os.unlink(self.dir / f"{stage}.json")
        except FileNotFoundError:
            pass

    def save_stat_cache(self) -> None:
        atomic_write_text(self._stat_path, json.dumps(self.stat_cache))
