"""The runnable examples in the docstrings of the core, the camera model and the 3D stages.

Each module under ``core/``, ``calibrate/camera.py``, ``triangulate/`` and ``track/`` whose source holds
a ``>>>`` example is imported and its examples run; a failing example fails the test that names it.
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FILES = [
    *sorted((ROOT / "core").glob("*.py")),
    ROOT / "calibrate" / "camera.py",
    *sorted((ROOT / "triangulate").glob("*.py")),
    *sorted((ROOT / "track").glob("*.py")),
]
WITH_EXAMPLES = [f for f in FILES if ">>>" in f.read_text()]


def _module_name(path: Path) -> str:
    return ".".join(("roomcap", *path.relative_to(ROOT).with_suffix("").parts))


def test_examples_exist():
    assert len(WITH_EXAMPLES) >= 5, [str(f) for f in WITH_EXAMPLES]


@pytest.mark.parametrize("path", WITH_EXAMPLES, ids=_module_name)
def test_docstring_examples(path: Path):
    module = importlib.import_module(_module_name(path))
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
    tests = [t for t in finder.find(module) if t.examples]
    assert tests, f"{path.name} has '>>>' but no example was found"
    for t in tests:
        runner.run(t)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {path.name}"
