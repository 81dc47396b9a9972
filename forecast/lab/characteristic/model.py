"""The characteristic-pose model's config, the two networks (the heatmap model and the Deterministic
ablation) and their checkpoint (family ``characteristic`` of the one format, ``runtime.checkpoint``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from roomcap.core import config as core_config
from roomcap.core.errors import FormatError, InputError
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab.characteristic.labels import AnnotatorConfig
from roomcap.forecast.lab.characteristic.network import CharacteristicPoseNet, DeterministicCharacteristic
from roomcap.forecast.runtime.checkpoint import read_checkpoint, write_checkpoint
from roomcap.keypoints.skeletons import get_skeleton

FAMILY = "characteristic"  # the registry's family of these checkpoints
SHIPPED = Path(__file__).resolve().parents[2] / "checkpoints" / "characteristic_cmuall.pt"


@dataclass(frozen=True)
class CharConfig:
    n_obs: int = 10  # N (sec. 3.6)
    hidden: int = 128  # GRU hidden size
    dim: int = 64  # attention / joint feature size
    heads: int = 4
    grid: int = 16  # voxels per axis (seed: 16)
    span: float = 2.0  # metres covered by the grid (seed: 2 m)
    n_discr: int = 10  # heatmap bins (seed: 10)
    channels: int = 16
    n_rest_train: int = 4  # 'rest' joints trained per step (random subset; all are used at sampling)
    w_offset: float = 1.0
    batch: int = 32
    steps: int = 1500
    det_steps: int = 1500  # the Deterministic ablation (trained in the same run)
    lr: float = 1e-3  # sec. 3.4.1: Adam, lr 1e-3, weight decay 1e-3, linear warm-up
    weight_decay: float = 1e-3
    warmup: int = 100
    temperature: float = 0.025  # sec. 3.4.1
    k: int = 10  # hypotheses (sec. 3.6)
    refine_iters: int = 60
    refine_angles_from: str = "last"  # eq. 3.2's theta: joint angles of the "first" or "last" observed pose
    val_every: int = 250  # model selection on the validation split (best-of-k MPJPE); 0 = keep the last
    time_limit_s: float = 0.0  # stop the heatmap model's training after this much process CPU time (0 = none)
    seed: int = 0


def config_from_dict(d: Mapping[str, Any] | None = None) -> CharConfig:
    """Typed config from a dict (``core.config``): unknown keys are an error listing the valid ones."""
    return core_config.config_from_dict(CharConfig, dict(d or {}), where="characteristic config")


def _order(joint_names) -> tuple[int, int]:
    names = list(joint_names)
    try:
        return names.index("right_wrist"), names.index("left_wrist")
    except ValueError:
        raise InputError(
            f"the characteristic model needs 'right_wrist' and 'left_wrist'; joints are {names}"
        ) from None


def build_models(cfg: CharConfig, skeleton: str = "body19"):
    sk = get_skeleton(skeleton)
    bones = [(p, j) for j, p in enumerate(sk.parents) if p >= 0]
    net = CharacteristicPoseNet(
        sk.n_joints,
        _order(sk.joint_names),
        bones,
        cfg.n_obs,
        cfg.hidden,
        cfg.dim,
        cfg.heads,
        cfg.grid,
        cfg.span,
        cfg.n_discr,
        cfg.channels,
    )
    det = DeterministicCharacteristic(sk.n_joints, cfg.n_obs, cfg.hidden, cfg.dim, cfg.heads)
    return net, det


NORMALISATION = (
    "observation: eq. 3.8 at the last observed frame (root = mid-hips, hip vector left->right on +x, z up); "
    "target: the same rotation, centred at its own mid-hips"
)


def save_checkpoint(
    path,
    net,
    det,
    cfg: CharConfig,
    avg_pose: np.ndarray,
    *,
    skeleton: str = "body19",
    fps: float = fdata.TARGET_FPS,
    extra: dict | None = None,
) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_checkpoint(
        path,
        FAMILY,
        config=cfg,
        weights={"model": net.state_dict(), "det": det.state_dict()},
        extra=extra,
        skeleton=skeleton,
        joint_names=list(get_skeleton(skeleton).joint_names),
        fps=fps,
        normalisation=NORMALISATION,
        annotator=dataclasses.asdict(AnnotatorConfig()),
        avg_pose=torch.as_tensor(np.asarray(avg_pose, np.float32)),
    )


def load_checkpoint(path, skeleton: str | None = None):
    """-> (heatmap model, deterministic model, meta). ``skeleton``: the caller's data skeleton; a mismatch is
    a clear error (``FormatError``)."""
    path = Path(path)
    blob = read_checkpoint(path, FAMILY, skeleton)
    if list(get_skeleton(blob["skeleton"]).joint_names) != list(blob["joint_names"]):
        raise FormatError(
            path,
            "joint_names",
            f"the joints differ from skeleton '{blob['skeleton']}' of this version.",
            "Retrain the model.",
        )
    cfg = config_from_dict(blob["config"])
    net, det = build_models(cfg, blob["skeleton"])
    try:
        net.load_state_dict(blob["weights"]["model"])
        det.load_state_dict(blob["weights"]["det"])
    except RuntimeError as e:
        raise FormatError(
            path, "weights", f"the weights do not fit the stored config: {e}", "Retrain."
        ) from None
    net.eval()
    det.eval()
    meta = {k: v for k, v in blob.items() if k != "weights"}
    meta["config"] = cfg
    meta["avg_pose"] = blob["avg_pose"].numpy()
    return net, det, meta
