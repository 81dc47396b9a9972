"""Shared fixtures: where the real data and models are, and a seeded RNG.

The real recordings, models and mocap live in ``../shared`` beside the checkout
(or wherever ``ROOMCAP_SHARED`` points). Tests that need them skip with a
clear reason when they are absent; CI has them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_root() -> Path:
    return Path(os.environ.get("ROOMCAP_SHARED", REPO.parent / "shared")).resolve()


def need_shared(*parts: str) -> Path:
    """Path under the shared folder, or skip the test saying what is missing and how to provide it."""
    p = shared_root().joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real data not found at {p}; set ROOMCAP_SHARED to the shared/ folder")
    return p


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def shared() -> Path:
    return need_shared()
