"""Motion priors in numpy: zero- and constant-velocity, the GRU of eq. 5.1 from its weights, the protocol.

Every prior works on a flat batch of pose samples ``x (B,J,3)`` (world metres,
B = tracks x samples) with a per-sample state: a dict of arrays whose first axis
is B, so resampling is a gather along that axis (:func:`gather_state`). The
learned GRU prior of eq. 5.1 is trained and saved by :mod:`roomcap.track.motion` (torch); it runs here in
numpy (:class:`GRUCellPrior`), and :func:`load_gru_numpy` reads the numpy copy of its weights that
:func:`roomcap.track.motion.save_checkpoint` writes beside the checkpoint, so tracking needs no torch.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from roomcap.core.fileio import save_npz, sha256_file
from roomcap.keypoints.skeletons import CANONICAL, Skeleton
from roomcap.track import kernels_gru
from roomcap.track.normalize import hip_indices
from roomcap.track.split import BLAS_BLOCK_ROWS, Split, blas_single, blocked_matmul

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

    def predict(
        self, x: np.ndarray, state: State, rng: np.random.Generator, split: Split | None = None
    ) -> tuple[np.ndarray, State]:
        """The next samples and state; ``split`` may cut the batch into parts computed at once (the same
        bits as the whole batch)."""
        ...


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

    def predict(self, x, state, rng, split=None):
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

    def predict(self, x, state, rng, split=None):
        x = check_batch(x, self.n_joints)
        v = x - state["prev"]
        new = x + self.damping * v + normal_noise(rng, x.shape, self.sigma_m)
        return new, {"prev": x}


DEFAULT_MOTION_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "motion_gru.pt"
GRU_WEIGHT_NAMES = ("w_ih", "b_ih", "w_hh", "b_hh", "w_out", "b_out")
NUMPY_COPY_SCHEMA = "motion_gru_numpy/1"


class GRUCellPrior:
    """The learned prior of eq. 5.1 in numpy: ``z_t, h_t = GRU(z_{t-1}, h_{t-1})`` with one hidden state per
    sample and MC dropout on the final linear layer's input (the samples diverge). ``weights``: the cell's
    and the output layer's weights as float32 arrays transposed for ``x @ W`` (``GRU_WEIGHT_NAMES``: w_ih
    (2·J·3, 3H), b_ih (3H,), w_hh (H, 3H), b_hh (3H,), w_out (H, J·3), b_out (J·3,)); ``trained_dropout``:
    the rate it was trained with, used unless ``dropout`` overrides it.
    :class:`roomcap.track.motion.GRUPrior` is this prior built from the torch model."""

    name = "gru"

    def __init__(
        self,
        weights: tuple[np.ndarray, ...],
        trained_dropout: float,
        model_fps: float,
        fps: float,
        skeleton: Skeleton = CANONICAL,
        dropout: float | None = None,
        sigma_m: float = 0.0,
    ):
        self._np_weights = tuple(np.ascontiguousarray(w, np.float32) for w in weights)
        w_ih, b_ih, w_hh, b_hh, w_out, b_out = self._np_weights
        self.hidden = H = w_hh.shape[0]
        J3 = 3 * skeleton.n_joints
        if w_ih.shape != (2 * J3, 3 * H) or w_hh.shape != (H, 3 * H) or w_out.shape != (H, J3):
            raise ValueError(
                f"GRU weights do not fit {skeleton.n_joints} joints: w_ih {w_ih.shape}, w_hh {w_hh.shape}, "
                f"w_out {w_out.shape}"
            )
        self.model_fps, self.fps, self.skeleton = float(model_fps), float(fps), skeleton
        self.dropout = float(trained_dropout) if dropout is None else float(dropout)
        self.sigma_m = float(sigma_m)
        self.block_rows = BLAS_BLOCK_ROWS  # the products' fixed partition of a batch (track/split.py)

    def init_state(self, x: np.ndarray) -> State:
        x = check_batch(x, self.skeleton.n_joints)
        return {"prev": x.copy(), "h": np.zeros((len(x), self.hidden), np.float32)}

    def _mask(self, rng: np.random.Generator, B: int, H: int) -> np.ndarray:
        """MC-dropout mask (B,H), entries 0 or 1/(1-p) (keep with probability 1-p): a contiguous slice at a
        random offset of a fixed Bernoulli block (no per-step draws or conversions, as ``normal_noise``)."""
        n = B * H
        bank = getattr(self, "_mask_bank", None)
        if bank is None or len(bank) < n:
            size = max(1 << 21, 2 * n)
            keep = np.random.default_rng(54321).random(size) >= self.dropout
            bank = self._mask_bank = keep.astype(np.float32) * np.float32(1.0 / (1.0 - self.dropout))
        start = int(rng.integers(0, len(bank) - n + 1))
        return bank[start : start + n].reshape(B, H)

    def _weights(self) -> tuple[np.ndarray, ...]:
        return self._np_weights

    def predict(self, x, state, rng, split: Split | None = None):
        x = check_batch(x, self.skeleton.n_joints)
        B, H = len(x), self.hidden
        prev = np.ascontiguousarray(state["prev"], np.float32)
        h_prev = np.ascontiguousarray(state["h"], np.float32)
        # the random draws for the whole batch first, so that any cut of it gives the same bits
        mask = self._mask(rng, B, H) if 0 < self.dropout < 1 else np.zeros((0, 0), np.float32)
        noise = standard_normals(rng, x.shape) if self.sigma_m > 0 else np.zeros((0, 0, 3), np.float32)

        def rows(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
            return self._predict_rows(
                x[lo:hi], prev[lo:hi], h_prev[lo:hi], mask[lo:hi], noise[lo:hi] if len(noise) else noise
            )

        # threads take whole blocks of the products' fixed partition, BLAS at one thread (track/split.py)
        with blas_single():
            parts = split.map(rows, B, block=self.block_rows) if split is not None else [rows(0, B)]
        new = parts[0][0] if len(parts) == 1 else np.concatenate([p[0] for p in parts])
        h = parts[0][1] if len(parts) == 1 else np.concatenate([p[1] for p in parts])
        return new, {"prev": x, "h": h}

    def _predict_rows(self, x, prev, h_prev, mask, noise) -> tuple[np.ndarray, np.ndarray]:
        """Rows of :meth:`predict` with their random draws given: the new poses and hidden states."""
        ip, il, ir = hip_indices(self.skeleton)
        # [pose - origin, last displacement] rotated into the hip frame in one pass: the normalised pose
        # (eq. 5.2-5.4) and the normalised displacement
        inp, cs = kernels_gru.gru_inputs(x, prev, ip, il, ir, self.fps / self.model_fps)
        w_ih, b_ih, w_hh, b_hh, w_out, b_out = self._weights()
        blk = self.block_rows
        # the GRU cell's two products (B,3H) (gates r, z, n), then its gates and the dropout compiled
        # (in blocks of the batch's fixed partition: the same bits for any cut of the batch)
        h, hd = kernels_gru.gru_gates(
            blocked_matmul(inp, w_ih, blk), b_ih, blocked_matmul(h_prev, w_hh, blk), b_hh, h_prev, mask
        )
        new = kernels_gru.gru_outputs(
            blocked_matmul(hd, w_out, blk), b_out, cs, x, self.model_fps / self.fps, noise, self.sigma_m
        )  # eq. 5.5 for the displacement, plus the noise
        return new, h


def numpy_copy_path(checkpoint: str | Path) -> Path:
    """Where the numpy copy of a GRU checkpoint's weights lies: beside it, suffix ``.npz``."""
    return Path(checkpoint).with_suffix(".npz")


def write_numpy_copy(checkpoint: str | Path, weights: dict[str, np.ndarray], meta: dict) -> Path:
    """Write the numpy copy of the GRU checkpoint ``checkpoint`` (already written): ``weights`` by
    ``GRU_WEIGHT_NAMES`` (as stored, e.g. float16), ``meta`` (joint_names, dropout, fps) and the sha256
    of the checkpoint's bytes, so that a changed checkpoint never pairs with a stale copy."""

    info = {
        "schema": NUMPY_COPY_SCHEMA,
        "source_sha256": sha256_file(checkpoint),
        "joint_names": list(meta["joint_names"]),
        "dropout": float(meta["dropout"]),
        "fps": float(meta["fps"]),
    }
    path = numpy_copy_path(checkpoint)
    save_npz(path, {"meta": np.asarray(json.dumps(info)), **{k: weights[k] for k in GRU_WEIGHT_NAMES}})
    return path


def load_gru_numpy(
    checkpoint: str | Path, fps: float, skeleton: Skeleton = CANONICAL, **kw
) -> GRUCellPrior | None:
    """The GRU prior of ``checkpoint`` from its numpy copy (:func:`write_numpy_copy`), without torch; None
    when there is no copy, or it was made from other bytes or for another skeleton (the caller then loads
    the checkpoint itself with :meth:`roomcap.track.motion.GRUPrior.load`, which says what is wrong with
    it)."""
    path = numpy_copy_path(checkpoint)
    if not (path.is_file() and Path(checkpoint).is_file()):
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            info = json.loads(str(z["meta"]))
            weights = tuple(np.asarray(z[k]).astype(np.float32) for k in GRU_WEIGHT_NAMES)
    except (OSError, KeyError, ValueError):
        return None
    if (
        info.get("schema") != NUMPY_COPY_SCHEMA
        or info.get("source_sha256") != sha256_file(checkpoint)
        or tuple(info.get("joint_names", ())) != tuple(skeleton.joint_names)
    ):
        return None
    return GRUCellPrior(weights, info["dropout"], info["fps"], fps, skeleton, **kw)
