"""Motion priors p(z_t | z_{t-1}) for the particle filter (seed ch. 5.2.1, eq. 5.1).

Every prior works on a flat batch of pose samples ``x (B,J,3)`` (world metres,
B = tracks x samples) with a per-sample state (a dict of arrays whose first axis
is B, so resampling is a gather along that axis):

- :class:`ZeroVelocityPrior` (:mod:`roomcap.track.priors`): x_t = x_{t-1} + N(0, sigma^2)
  (the seed's "w/o pose prediction" ablation).
- :class:`ConstantVelocityPrior`: x_t = x_{t-1} + a (x_{t-1} - x_{t-2}) + N(0, sigma^2).
- :class:`GRUPrior`: eq. 5.1, ``z_t, h_t = GRU(z_{t-1}, h_{t-1})`` with one hidden state
  per sample and dropout kept on at inference on the input of the final linear
  layer (Bayesian approximation, the samples diverge). Poses are normalised
  (eq. 5.2–5.5, :mod:`roomcap.track.normalize`) before the network and restored after.
  Besides the normalised pose the network also sees the sample's last
  displacement in the same frame (our addition: the normalisation removes the
  global motion, and the hidden state alone forgets it when the frame turns).
  It runs in numpy (:class:`roomcap.track.priors.GRUCellPrior`); the tracker loads it from the numpy copy of
  the checkpoint that :func:`save_checkpoint` writes beside it, without torch
  (:func:`roomcap.track.priors.load_gru_numpy`).

This module (training, checkpoints) imports torch; tracking with a checkpoint's numpy copy does not.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from torch import nn

from roomcap.core.errors import RoomcapError
from roomcap.core.fileio import atomic_path
from roomcap.keypoints.skeletons import CANONICAL, Skeleton
from roomcap.track.normalize import hip_frame, normalize, rotate_vectors
from roomcap.track.priors import (
    DEFAULT_MOTION_CHECKPOINT,
    GRU_WEIGHT_NAMES,
    GRUCellPrior,
    write_numpy_copy,
)

log = logging.getLogger(__name__)

CHECKPOINT_SCHEMA = "motion_gru/1"
DEFAULT_CHECKPOINT = DEFAULT_MOTION_CHECKPOINT


class CheckpointMismatch(RoomcapError, ValueError):
    """The motion-model checkpoint does not fit the skeleton (or is not a motion checkpoint)."""


class PoseGRU(nn.Module):
    """GRU cell over [normalised pose, normalised last displacement] -> next displacement (eq. 5.1)."""

    def __init__(self, n_joints: int, hidden: int, dropout: float):
        super().__init__()
        self.n_joints, self.hidden, self.dropout = n_joints, hidden, dropout
        self.cell = nn.GRUCell(2 * n_joints * 3, hidden)
        self.out = nn.Linear(hidden, n_joints * 3)

    def step(
        self, x_hat: torch.Tensor, v_hat: torch.Tensor, h: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """x_hat, v_hat: (B,J*3) normalised; h: (B,H); mask: (B,H) dropout mask already scaled, or None."""
        h = self.cell(torch.cat([x_hat, v_hat], -1), h)
        hd = h if mask is None else h * mask
        return self.out(hd), h

    def forward_sequence(self, x_hat: torch.Tensor, v_hat: torch.Tensor) -> torch.Tensor:
        """Training: x_hat, v_hat (B,T,J*3) each already in the frame of its own step -> deltas (B,T,J*3)."""
        B, T, _ = x_hat.shape
        h = x_hat.new_zeros(B, self.hidden)
        outs = []
        for t in range(T):
            h = self.cell(torch.cat([x_hat[:, t], v_hat[:, t]], -1), h)
            outs.append(self.out(nn.functional.dropout(h, self.dropout, self.training)))
        return torch.stack(outs, 1)


def step_inputs(
    x_prev: np.ndarray, x_prev2: np.ndarray, fps: float, model_fps: float, skeleton: Skeleton = CANONICAL
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Network inputs for poses x_prev (t-1) and x_prev2 (t-2), (...,J,3) world metres.

    Returns x_hat, v_hat (...,J*3) in the hip frame of x_prev (eq. 5.2), with the
    displacement expressed per model frame, and the frame (origin, theta).
    """
    origin, theta = hip_frame(x_prev, skeleton)
    x_hat = normalize(x_prev, origin, theta)
    v_hat = rotate_vectors(x_prev - x_prev2, theta) * (fps / model_fps)
    lead = x_prev.shape[:-2]
    return (x_hat.reshape(*lead, -1), v_hat.reshape(*lead, -1), origin, theta)


class GRUPrior(GRUCellPrior):
    """The learned prior of eq. 5.1 built from the torch model (:class:`roomcap.track.priors.GRUCellPrior`
    runs it in numpy). Load with :meth:`load`; ``dropout`` overrides the trained rate at inference."""

    def __init__(
        self,
        model: PoseGRU,
        model_fps: float,
        fps: float,
        skeleton: Skeleton = CANONICAL,
        dropout: float | None = None,
        sigma_m: float = 0.0,
        seed: int = 0,
    ):
        self.model = model.eval()
        cell, out = model.cell, model.out
        weights = tuple(
            t.detach().numpy()
            for t in (cell.weight_ih.T, cell.bias_ih, cell.weight_hh.T, cell.bias_hh, out.weight.T, out.bias)
        )
        super().__init__(weights, model.dropout, model_fps, fps, skeleton, dropout, sigma_m)

    @classmethod
    def load(
        cls, path: str | Path = DEFAULT_CHECKPOINT, fps: float = 25.0, skeleton: Skeleton = CANONICAL, **kw
    ) -> GRUPrior:
        model, meta = load_checkpoint(path, skeleton)
        return cls(model, meta["fps"], fps, skeleton, **kw)


def write_checkpoint(
    path: str | Path, schema: str, model: torch.nn.Module, skeleton: Skeleton, train_info: dict, **extra
) -> None:
    """Write a learned-model checkpoint of the tracker atomically (half-precision weights, the model's
    ``hidden`` and ``dropout``, the skeleton, the scalar training info); :func:`read_checkpoint` reads it."""

    payload = {
        "schema": schema,
        "skeleton": skeleton.id,
        "joint_names": list(skeleton.joint_names),
        "hidden": int(model.hidden),
        "dropout": float(model.dropout),
        **extra,
        "state_dict": {k: v.detach().clone().half() for k, v in model.state_dict().items()},
        "train": {k: v for k, v in train_info.items() if isinstance(v, (int, float, str, list))},
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def save_checkpoint(
    path: str | Path, model: PoseGRU, fps: float, skeleton: Skeleton, train_info: dict
) -> None:
    """Write a motion checkpoint and, beside it, the numpy copy of its weights that tracking loads without
    torch (:func:`roomcap.track.priors.load_gru_numpy`)."""
    write_checkpoint(path, CHECKPOINT_SCHEMA, model, skeleton, train_info, fps=float(fps))
    write_gru_numpy_copy(path)


def write_gru_numpy_copy(path: str | Path) -> Path:
    """Write the numpy copy (``.npz`` beside it) of the motion checkpoint at ``path``: its stored weights,
    transposed for ``x @ W``, as the checkpoint holds them (half precision)."""
    meta = torch.load(path, map_location="cpu", weights_only=True)
    sd = meta["state_dict"]
    weights = {
        name: sd[key].numpy().T.copy() if "weight" in key else sd[key].numpy()
        for name, key in zip(
            GRU_WEIGHT_NAMES,
            ("cell.weight_ih", "cell.bias_ih", "cell.weight_hh", "cell.bias_hh", "out.weight", "out.bias"),
            strict=True,
        )
    }
    return write_numpy_copy(path, weights, meta)


def read_checkpoint(
    path: str | Path,
    schema: str,
    skeleton: Skeleton,
    kind: str,
    train_cmd: str,
    alternative: str,
    model_cls: type[torch.nn.Module],
) -> tuple[torch.nn.Module, dict]:
    """Load a learned-model checkpoint of the tracker (weights_only=True), check its schema and skeleton and
    build ``model_cls(n_joints, hidden, dropout)`` from it (in eval mode).

    ``kind`` names the model in messages; ``train_cmd`` and ``alternative`` say what to do instead."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(
            f"{kind} checkpoint {path} not found; train one with `{train_cmd}` or {alternative}."
        )
    try:
        meta = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure means "not a checkpoint we can read"
        raise CheckpointMismatch(f"{path} is not a readable {kind} checkpoint ({e}).") from e
    if not isinstance(meta, dict) or meta.get("schema") != schema:
        got = meta.get("schema") if isinstance(meta, dict) else type(meta).__name__
        raise CheckpointMismatch(f"{path}: expected a '{schema}' checkpoint, got {got!r}.")
    names = tuple(meta["joint_names"])
    if names != tuple(skeleton.joint_names):
        raise CheckpointMismatch(
            f"{path} was trained for skeleton '{meta.get('skeleton')}' with {len(names)} joints "
            f"{list(names)}, but the tracker uses '{skeleton.id}' with {skeleton.n_joints} joints "
            f"{list(skeleton.joint_names)}. Retrain with `{train_cmd}` for that skeleton or {alternative}."
        )
    model = model_cls(len(names), int(meta["hidden"]), float(meta["dropout"]))
    model.load_state_dict({k: v.float() for k, v in meta["state_dict"].items()})
    return model.eval(), meta


def load_checkpoint(path: str | Path, skeleton: Skeleton = CANONICAL) -> tuple[PoseGRU, dict]:
    """Load a motion checkpoint (weights_only=True) and check it matches ``skeleton``."""
    return read_checkpoint(
        path,
        CHECKPOINT_SCHEMA,
        skeleton,
        "motion",
        "python -m roomcap.track.train_motion --out track/checkpoints/motion_gru.pt",
        "use the constant-velocity prior (motion = 'constant_velocity')",
        PoseGRU,
    )
