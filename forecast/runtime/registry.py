"""The trainable forecasting models behind one interface: name -> typed config class, build, forecast.

``MODELS`` is the only place that maps a model's name (the ``kind`` of its checkpoints, ``forecast train
--model``'s choices) to what it is; the command line, the checkpoint loader, the forecast
(:func:`forecast.runtime.predict.forecast_world`) and the evaluation read it. The config class selects the
model, as lerobot's policy configs do. Importing this module does not load torch: building a model does.

A :class:`ModelSpec` holds the model's ``config`` class (``forecast.config``, the only copy of its defaults),
``build(config, n_joints, state)`` (the module, with the buffers a state may fill: k-means centres, feature
statistics), how it forecasts and trains (``scene``: the whole scene at once, Social Diffusion, ch. 7;
otherwise each person alone, normalised at its last observed frame, eq. 3.8) and whether it learns intentions
against discriminators (``intentions``, ch. 6); ``forecast.train`` reads these instead of the model's name.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from roomcap.core import config as core_config
from roomcap.core.errors import InputError
from roomcap.forecast.runtime.config import N_GLOBAL, DiffusionConfig, GRUConfig, IntentionConfig

# the training-only weights left out of checkpoints (the intention model's discriminators)
DISCRIMINATOR_PREFIXES = ("D_pose.", "D_label.")


@dataclass(frozen=True)
class ModelSpec:
    name: str
    config: type
    build: Callable[[Any, int, Mapping | None], Any]  # (config, n_joints, state) -> torch module
    scene: bool  # True: forecasts (and trains on) the scene at once; False: each person alone (eq. 3.8)
    intentions: bool  # trained on k-means intention labels, against discriminators (Tanke ch. 6)
    summary: str


def _build_gru(config: GRUConfig, n_joints: int, state: Mapping | None):
    from roomcap.forecast.runtime.models import Seq2SeqGRU  # lazy: loads torch

    return Seq2SeqGRU(3 * n_joints, config.hidden, config.dropout)


def intention_model(config: IntentionConfig, dim: int, state: Mapping | None = None):
    """The intention model over ``dim`` values a frame (3 a joint; the angle benchmark's used values)."""
    import numpy as np

    from roomcap.forecast.runtime.models import IntentionModel  # lazy: loads torch

    centres = np.zeros((config.n_clusters, dim), np.float32) if state is None else state["centres"].numpy()
    merge = np.zeros(config.n_clusters, np.int64) if state is None else state["merge"].numpy()
    return IntentionModel(
        dim,
        centres,
        merge,
        config.n_intentions,
        config.hidden,
        config.layers,
        config.z_dim,
        gamma=config.gamma,
        f_dim=config.f_dim,
        label_temp=config.label_temp,
        z_scale=config.z_scale,
    )


def _build_diffusion(config: DiffusionConfig, n_joints: int, state: Mapping | None):
    from roomcap.forecast.runtime.models import SocialDiffusion  # lazy: loads torch

    if config.root_vel and not config.anchor:
        raise InputError(
            "root_vel = true needs anchor = true (displacements are summed from the anchor frame)"
        )
    m = SocialDiffusion(
        3 * n_joints + N_GLOBAL,
        config.n_frames,
        config.channels,
        config.T,
        anchored=config.anchor,
        lag_stats=config.lag_stats,
    )
    m.n_obs, m.sample_steps, m.sample_eta = config.n_obs, config.sample_steps, config.sample_eta
    m.sample_dct, m.sample_temp = config.sample_dct, config.sample_temp
    m.n_obs_clean = config.n_obs if config.clean_obs else 0
    m.anchor = config.n_obs - 1 if config.anchor else None
    m.root_vel = config.root_vel
    m.lag_hold = bool(config.lag_hold)
    return m


MODELS: dict[str, ModelSpec] = {
    s.name: s
    for s in (
        ModelSpec(
            "gru",
            GRUConfig,
            _build_gru,
            scene=False,
            intentions=False,
            summary="seq2seq GRU, deterministic (Martinez et al. 2017)",
        ),
        ModelSpec(
            "intention",
            IntentionConfig,
            lambda config, n_joints, state: intention_model(config, 3 * n_joints, state),
            scene=False,
            intentions=True,
            summary="the intention model, stochastic (Tanke ch. 6)",
        ),
        ModelSpec(
            "social_diffusion",
            DiffusionConfig,
            _build_diffusion,
            scene=True,
            intentions=False,
            summary="Social Diffusion, the scene at once, stochastic (Tanke ch. 7)",
        ),
    )
}
NAMES = tuple(MODELS)


@dataclass(frozen=True)
class Family:
    """A family of checkpoints in the one format (``forecast-checkpoint/2``): its ``model`` name, what it is
    and which command reads and trains it. The track models (:data:`MODELS`) are built here; the lab's
    families (the CMU 8-action DCT + MLP, the characteristic-pose and behaviour models) build themselves from
    what the one reader returns."""

    name: str
    what: str
    reads_it: str
    train: str


_TRACK_USE = "`forecast sample --checkpoint PATH` and `forecast eval --checkpoints PATH` read it"
_ANGLE_USE = "`forecast eval --protocol cmu8 --metric angle --checkpoints PATH` scores it"
FAMILIES: dict[str, Family] = {
    f.name: f
    for f in (
        *(Family(m.name, m.summary, _TRACK_USE, f"forecast train --model {m.name}") for m in MODELS.values()),
        Family(
            "characteristic",
            "a characteristic-3D-pose model (Diller ch. 3)",
            "`forecast characteristic eval --checkpoint PATH` reads it",
            "forecast characteristic train --out PATH",
        ),
        Family(
            "cmu8_dct_mlp",
            "a DCT + MLP (or the mean of several) of the CMU 8-action benchmark (its own 3D points at 60 Hz)",
            "`forecast eval --protocol cmu8 --checkpoints PATH` scores it",
            "forecast cmu8 train | ensemble",
        ),
        Family(
            "cmu8_angle_dct_mlp",
            "a DCT + MLP (or the mean of several) of the CMU 8-action benchmark's exponential maps",
            _ANGLE_USE,
            "forecast cmu8 train --angles | ensemble",
        ),
        Family(
            "cmu8_angle_intention",
            "the intention model (Tanke ch. 6) of the CMU 8-action benchmark's exponential maps (Table 6.7)",
            _ANGLE_USE,
            "forecast cmu8 train --angles --model intention",
        ),
        Family(
            "behaviour",
            "a behaviour model (next actions and their poses, Diller ch. 4)",
            "`forecast behaviour sample|eval --checkpoint PATH` reads it",
            "forecast behaviour train --out PATH",
        ),
        Family(
            "behaviour_quality",
            "a behaviour pose-quality classifier (Diller ch. 4)",
            "`forecast behaviour eval --quality-classifier PATH` reads it",
            "forecast behaviour quality --out PATH",
        ),
    )
}


@dataclass(frozen=True)
class Baseline:
    """A checkpoint-free forecaster: ``moves`` the last pose along the root's velocity (constant velocity) or
    not; ``module(lhip, rhip)`` its torch module (lazy: loads torch)."""

    name: str
    aliases: tuple[str, ...]
    moves: bool
    module: Callable[[int, int], Any]


def _zero(lhip: int, rhip: int):
    from roomcap.forecast.runtime.models import ZeroVelocity  # lazy: loads torch

    return ZeroVelocity()


def _const(lhip: int, rhip: int):
    from roomcap.forecast.runtime.models import ConstantVelocity  # lazy: loads torch

    return ConstantVelocity()


def _slide(lhip: int, rhip: int):
    from roomcap.forecast.runtime.models import SlideLastPose  # lazy: loads torch

    return SlideLastPose(lhip, rhip)


# Tanke 2024 sec. 6.4.4's controls
BASELINES: dict[str, Baseline] = {
    b.name: b
    for b in (
        Baseline("zero_velocity", ("zero",), False, _zero),
        Baseline("constant_velocity", ("const",), True, _const),
        Baseline("slide", (), False, _slide),
    )
}


def baseline(name: str) -> Baseline:
    """The baseline called ``name`` (or one of its aliases); an unknown name is an InputError listing them."""
    for b in BASELINES.values():
        if name == b.name or name in b.aliases:
            return b
    raise InputError(f"unknown baseline '{name}'; baselines: {tuple(BASELINES)}")


def spec(name: str) -> ModelSpec:
    """The model called ``name``; an unknown name is an :class:`InputError` listing the known ones."""
    if name not in MODELS:
        raise InputError(f"unknown model '{name}'; trainable models: {sorted(MODELS)}")
    return MODELS[name]


def spec_of(model) -> ModelSpec | None:
    """The spec of a built model (by its ``kind``); None for the baselines and other forecasters."""
    return MODELS.get(getattr(model, "kind", ""))


def forecasts_the_scene(model) -> bool:
    """Whether ``model`` forecasts the whole scene at once (else each person alone)."""
    s = spec_of(model)
    return s is not None and s.scene


def config_from_dict(name: str, d: Mapping[str, Any] | None = None) -> Any:
    """Typed config of model ``name`` from a dict (e.g. a TOML table); unknown keys are an error."""
    return core_config.config_from_dict(spec(name).config, dict(d or {}), where=f"{name} config")


def build_model(name: str, config, n_joints: int, state: dict | None = None):
    """Model ``name`` for ``n_joints`` joints from its ``config``, with the weights of ``state`` (a state dict
    without the training-only discriminators) when given; a state that does not fit is an InputError saying
    so."""
    m = spec(name).build(config, n_joints, state)
    if state is not None:
        try:
            missing, unexpected = m.load_state_dict(state, strict=False)
        except RuntimeError as e:  # shape mismatches: torch lists every tensor, the first says enough
            lines = [ln.strip() for ln in str(e).splitlines() if "mismatch" in ln]
            first = lines[0] if lines else str(e).splitlines()[0]
            raise InputError(
                f"the {name} state does not fit the checkpoint's config ({len(lines)} tensors differ; first: "
                f"{first}). The config or the weights were changed after training: retrain with "
                "`forecast train`, or use the original file."
            ) from None
        missing = [k for k in missing if not k.startswith(DISCRIMINATOR_PREFIXES)]
        if missing or unexpected:
            raise InputError(
                f"{name} state does not fit the config: missing {missing}, unexpected {unexpected}"
            )
    m.n_obs = config.n_obs
    m.continuity = bool(config.continuity)  # read by predict.forecast_world
    return m
