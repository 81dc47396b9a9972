"""What each stage output was made from, so reruns skip what is up to date.

Every stage writes ``<out>/.roomcap/provenance/<stage>.json`` after its outputs:
the input files' fingerprints, the stage configuration, the model sha256 and
the package version, and the fingerprints of the outputs. A stage is up to
date when that record matches what it would be made from now and its outputs
are unchanged. The record is written last (atomically), so a run killed
mid-stage leaves no record and the stage reruns.

Fingerprints are sha256 of the file (for large files: of the size plus the
first and last 4 MiB). A stat cache (size, mtime) in the record saves hashing
unchanged files again, which keeps a no-op rerun of many sessions fast.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from capture.fileio import atomic_write_text

_FULL_HASH_LIMIT = 64 << 20
_EDGE = 4 << 20


def package_version() -> str:
    try:
        return metadata.version("roomcap")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def file_fingerprint(path: Path) -> str:
    h = hashlib.sha256()
    size = path.stat().st_size
    with open(path, "rb") as f:
        if size <= _FULL_HASH_LIMIT:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        else:
            h.update(str(size).encode())
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
    st = path.stat()
    key = str(path.resolve())
    stamp = [st.st_size, st.st_mtime_ns]
    if stat_cache is not None:
        hit = stat_cache.get(key)
        if hit and hit[0] == stamp:
            return hit[1]
    fp = file_fingerprint(path)
    if stat_cache is not None:
        stat_cache[key] = [stamp, fp]
    return fp


@dataclass(frozen=True)
class StageRecord:
    stage: str
    inputs: dict[str, str]  # path -> fingerprint
    config: dict[str, Any]
    model_sha256: str
    version: str
    outputs: dict[str, str]  # path relative to the session output -> fingerprint

    def to_json(self) -> dict[str, Any]:
        return {
            "stage": self.stage,
            "inputs": self.inputs,
            "config": self.config,
            "model_sha256": self.model_sha256,
            "version": self.version,
            "outputs": self.outputs,
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
    ) -> bool:
        rec = self.load(stage)
        if rec is None:
            return False
        want = {
            "inputs": inputs,
            "config": json.loads(json.dumps(config)),
            "model_sha256": model_sha256,
            "version": package_version(),
        }
        if any(rec.get(k) != v for k, v in want.items()):
            return False
        if not all(p.exists() for p in outputs):
            return False
        return rec.get("outputs") == self.fingerprint_outputs(outputs)

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
