"""Import boundaries (ARCHITECTURE.md): ``calibrate`` and ``triangulate`` import with torch, depthai blocked.

A fresh interpreter installs a meta-path finder that refuses ``torch`` and ``depthai`` (and their
submodules), then imports every module of those packages found on disk, so modules added later
are covered without editing this test.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("calibrate", "triangulate")
REQUIRED = tuple(
    f"roomcap.{m}"
    for m in ("calibrate", "calibrate.camera", "calibrate.formats", "calibrate.cli", "triangulate")
)
BLOCKED = ("torch", "depthai")

CHILD = r"""
import importlib, importlib.abc, json, sys, traceback

BLOCKED = {blocked!r}

class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"import of {{name!r}} is blocked by test_import_boundaries")
        return None

sys.meta_path.insert(0, Block())
result = {{"failed": {{}}, "imported": [], "blocker_works": False}}
try:
    import torch  # noqa: F401
except ImportError:
    result["blocker_works"] = True
for mod in {modules!r}:
    try:
        importlib.import_module(mod)
        result["imported"].append(mod)
    except BaseException:
        result["failed"][mod] = traceback.format_exc(limit=-3)
result["leaked"] = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
print(json.dumps(result))
"""


def package_modules(package: str) -> list[str]:
    """``roomcap.<package>`` and every module below it found on disk (sub-packages included)."""
    root = REPO / package
    mods = [f"roomcap.{package}"]
    for f in sorted(root.rglob("*.py")):
        rel = f.relative_to(REPO).with_suffix("")
        if rel.name == "__init__":
            rel = rel.parent
        if any(part.startswith(".") or part == "__pycache__" for part in rel.parts):
            continue
        name = ".".join(("roomcap", *rel.parts))
        if name not in mods and name != f"roomcap.{package}.__main__":
            mods.append(name)
    return mods


def import_blocked(modules: list[str], extra_path: Path | None = None) -> dict:
    """Import ``modules`` in a fresh interpreter with torch and depthai blocked; report per module."""
    code = CHILD.format(blocked=BLOCKED, modules=modules)
    paths = ([str(extra_path)] if extra_path else []) + [os.environ.get("PYTHONPATH", "")]
    env = os.environ | {"PYTHONPATH": os.pathsep.join(p for p in paths if p)}
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_calibrate_and_triangulate_import_without_torch_and_depthai():
    modules = list(REQUIRED)
    for pkg in PACKAGES:
        modules += [m for m in package_modules(pkg) if m not in modules]
    result = import_blocked(modules)
    assert result["blocker_works"], "the import blocker did not block torch"
    assert not result["failed"], "\n\n".join(f"{m}:\n{tb}" for m, tb in result["failed"].items())
    assert result["leaked"] == []
    assert set(REQUIRED) <= set(result["imported"])
    assert len(result["imported"]) == len(modules)


def test_module_discovery_finds_this_stage():
    mods = package_modules("calibrate")
    assert {"roomcap.calibrate", "roomcap.calibrate.camera", "roomcap.calibrate.formats"} <= set(mods)
    assert package_modules("triangulate")[0] == "roomcap.triangulate"


def test_the_check_catches_a_torch_import(tmp_path):
    """A module that imports torch (directly or through a dependency) is reported."""
    (tmp_path / "uses_torch.py").write_text("import numpy\nfrom torch import nn\n")
    (tmp_path / "uses_dai.py").write_text("import depthai.node\n")
    result = import_blocked(["uses_torch", "uses_dai", "roomcap.calibrate.camera"], extra_path=tmp_path)
    assert sorted(result["failed"]) == ["uses_dai", "uses_torch"]
    assert "blocked by test_import_boundaries" in result["failed"]["uses_torch"]
    assert result["imported"] == ["roomcap.calibrate.camera"]


LEARNED = {f"roomcap.track.{m}" for m in ("motion", "birth", "train_motion", "train_birth")}


def test_other_stages_import_without_torch_and_depthai():
    """ARCHITECTURE.md: the non-learned parts of track, the keypoints inference path, the pipeline and
    capture (but its OAK source) need neither torch nor depthai."""
    modules = [
        m
        for pkg in ("track", "keypoints", "capture", "pipeline", "synthetic")
        for m in package_modules(pkg)
        if m not in LEARNED and m != "roomcap.capture.oak"
    ]
    result = import_blocked(modules)
    assert not result["failed"], "\n\n".join(f"{m}:\n{tb}" for m, tb in result["failed"].items())
    assert len(result["imported"]) == len(modules)
