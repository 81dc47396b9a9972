"""One installed top-level name: ``roomcap``. The stage folders stay at the repository's top and the packaging
maps them into the namespace (``pyproject.toml`` ``[tool.setuptools] package-dir``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _repo_packages() -> set[str]:
    """Every folder of the repository that is a Python package, as its ``roomcap.*`` name."""
    found = {"roomcap"}
    for init in REPO.rglob("__init__.py"):
        rel = init.parent.relative_to(REPO)
        if rel.parts and not any(p.startswith(".") or p in {"build", "tests", "bench"} for p in rel.parts):
            found.add(".".join(("roomcap", *rel.parts)))
    return found


def test_the_packaging_lists_every_package_folder():
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    assert listed == _repo_packages()


@pytest.mark.slow
def test_the_wheel_installs_roomcap_and_nothing_else_at_the_top(tmp_path):
    code = (
        "import sys; from setuptools import build_meta as b; "
        f"sys.stdout.write(b.build_wheel({str(tmp_path)!r}))"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=600)
    shutil.rmtree(REPO / "build" / "lib", ignore_errors=True)  # setuptools' staging copy of the sources
    assert proc.returncode == 0, proc.stderr[-3000:]
    wheel = tmp_path / proc.stdout.strip().splitlines()[-1]
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == {"roomcap"}
    # every package and the data the runtime reads travel with it
    for pkg in _repo_packages():
        assert f"{pkg.replace('.', '/')}/__init__.py" in names, pkg
    for data in (
        "roomcap/keypoints/models/sets.toml",
        "roomcap/pipeline/report_assets/report.js",
        "roomcap/pipeline/liveview/live.js",
        "roomcap/track/checkpoints/motion_gru.pt",
        "roomcap/forecast/configs/gru.toml",
    ):
        assert data in names, data
    top_level = next(n for n in names if n.endswith(".dist-info/top_level.txt"))
    assert zipfile.ZipFile(wheel).read(top_level).decode().split() == ["roomcap"]


def test_the_editable_install_resolves_roomcap_not_the_bare_folders(tmp_path):
    """Outside the checkout (no folder of it on sys.path), ``roomcap.core`` is the checkout's core/ and
    ``core`` is nothing."""
    code = (
        "import importlib.util, roomcap.core, roomcap.track.trackfile; "
        "print(roomcap.core.__file__); print(importlib.util.find_spec('core')); "
        "print(importlib.util.find_spec('pipeline'))"
    )
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    core_file, core_spec, pipeline_spec = proc.stdout.split()
    assert Path(core_file) == REPO / "core" / "__init__.py"
    assert core_spec == "None" and pipeline_spec == "None"
