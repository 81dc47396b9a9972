"""Motion priors without learning (numpy only): zero- and constant-velocity, and the prior protocol.

Every prior works on a flat batch of pose samples ``x (B,J,3)`` (world metres,
B = tracks x samples) with a per-sample state: a dict of arrays whose first axis
is B, so resampling is a gather along that axis (:func:`gather_state`). The
learned GRU prior of eq. 5.1 lives in :mod:`track.motion` (torch).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from keypoints.skeletons import CANONICAL

State = dict[str, np.ndarray]

# Median body19 pose of the CMU mocap in the normalised hip frame (eq. 5.2–5.5: pelvis at the origin,
# hips along +x, z up), used to fill joints a new track has not triangulated (sec. 5.2.3).
TEMPLATE_BODY19_M = np.array(
    [
        [0.011, 0.147, 0.586],
        [-0.018, 0.148, 0.625],
        [0.044, 0.148, 0.623],
        [-0.059, 0.078, 0.651],
        [0.086, 0.075, 0.646],
        [-0.172, 0.01, 0.485],
        [0.188, 0.008, 0.469],
        [-0.206, -0.033, 0.265],
        [0.223, -0.011, 0.244],
        [-0.226, 0.086, 0.078],
        [0.236, 0.108, 0.115],
        [-0.097, 0.0, -0.001],
        [0.097, 0.0, 0.001],
        [-0.1, 0.124, -0.442],
        [0.091, 0.127, -0.442],
        [-0.088, -0.07, -0.87],
        [0.077, -0.065, -0.873],
        [0.0, 0.0, 0.0],
        [0.007, 0.005, 0.478],
    ],
    np.float32,
)


class MotionPrior(Protocol):
    name: str

    def init_state(self, x: np.ndarray) -> State: ...

    def predict(self, x: np.ndarray, state: State, rng: np.random.Generator) -> tuple[np.ndarray, State]: ...


def gather_state(state: State, idx: np.ndarray) -> State:
    """Resampling: keep the states of samples ``idx (B',)``."""
    return {k: v[idx] for k, v in state.items()}


def concat_states(states: list[State]) -> State:
    if not states:
        return {}
    return {k: np.concatenate([s[k] for s in states], 0) for k in states[0]}


_BANK: dict[int, np.ndarray] = {}


def standard_normals(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """N(0, 1) float32 noise of ``shape``: a view (not to be written) of a contiguous slice at a random
    offset of a fixed block of standard normals (drawing fresh normals costs more than the rest of a
    prediction step); fresh draws when the block is too small."""
    if 0 not in _BANK:
        _BANK[0] = np.random.default_rng(12345).standard_normal(1 << 21, dtype=np.float32)
    bank = _BANK[0]
    n = math.prod(shape)
    if n > len(bank):
        return rng.standard_normal(shape, dtype=np.float32)
    start = int(rng.integers(0, len(bank) - n + 1))
    return bank[start : start + n].reshape(shape)


def normal_noise(rng: np.random.Generator, shape: tuple[int, ...], sigma: float) -> np.ndarray:
    """N(0, sigma^2) float32 noise of ``shape`` (a new array), from :func:`standard_normals`."""
    return standard_normals(rng, shape) * np.float32(sigma)


def check_batch(x: np.ndarray, n_joints: int) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    if x.ndim != 3 or x.shape[1:] != (n_joints, 3):
        raise ValueError(f"pose samples must have shape (B,{n_joints},3), got {x.shape}")
    return x


@dataclass
class ZeroVelocityPrior:
    """x_t = x_{t-1} + N(0, sigma_m^2) per joint and axis (the seed's 'w/o pose prediction')."""

    sigma_m: float = 0.01
    n_joints: int = CANONICAL.n_joints
    name: str = "zero_velocity"

    def init_state(self, x: np.ndarray) -> State:
        return {}

    def predict(self, x, state, rng):
        x = check_batch(x, self.n_joints)
        return x + normal_noise(rng, x.shape, self.sigma_m), state


@dataclass
class ConstantVelocityPrior:
    """x_t = x_{t-1} + damping * (x_{t-1} - x_{t-2}) + N(0, sigma_m^2)."""

    sigma_m: float = 0.01
    damping: float = 0.8
    n_joints: int = CANONICAL.n_joints
    name: str = "constant_velocity"

    def init_state(self, x: np.ndarray) -> State:
        return {"prev": check_batch(x, self.n_joints).copy()}

    def predict(self, x, state, rng):
        x = check_batch(x, self.n_joints)
        v = x - state["prev"]
        new = x + self.damping * v + normal_noise(rng, x.shape, self.sigma_m)
        return new, {"prev": x}
