"""Named presets of the 2D stage: a model set and the pipeline settings that trade speed for accuracy.

The presets are data, in the ``[presets]`` table of ``keypoints/models/sets.toml`` (read by
``keypoints.registry.presets``), each chosen by measurement on both Pose2Sim demos
(``bench/bench_keypoints_presets.py``; figures in BENCHMARKS.md, "2D keypoints").
"""

from __future__ import annotations

import dataclasses
from typing import Any

from roomcap.core.config import check_keys, config_from_dict
from roomcap.core.errors import UnknownNameError
from roomcap.keypoints.pipeline_config import KeypointPipelineConfig
from roomcap.keypoints.registry import presets


@dataclasses.dataclass(frozen=True)
class ResolvedPreset:
    """A preset looked up once: its name, its table with the overrides, and the typed settings."""

    name: str
    settings: dict[str, Any]
    config: KeypointPipelineConfig


def resolve_preset(name: str = "", model_set: str = "", **overrides: Any) -> ResolvedPreset:
    """The preset ``name`` ("" = the default preset, or "legacy" when only ``model_set`` is given) with
    ``model_set`` and the other ``KeypointPipelineConfig`` fields in ``overrides`` laid over it."""
    default, table = presets()
    name = name or ("legacy" if model_set else default)
    if name not in table:
        raise UnknownNameError(f"unknown keypoint preset {name!r}; known: {sorted(table)}.")
    over = {**({"model_set": model_set} if model_set else {}), **overrides}
    check_keys(over, [f.name for f in dataclasses.fields(KeypointPipelineConfig)], "keypoint settings", None)
    cfg = config_from_dict(KeypointPipelineConfig, table[name], f"presets.{name}")
    return ResolvedPreset(name, {**table[name], **over}, dataclasses.replace(cfg, **over))


def preset_config(name: str = "", **overrides: Any) -> KeypointPipelineConfig:
    """The 2D stage's settings for a preset ("" = the default preset), with ``KeypointPipelineConfig`` fields
    overridden by ``overrides``."""
    return resolve_preset(name, **overrides).config


def settings_for(name: str) -> KeypointPipelineConfig:
    """The settings a name stands for: a preset's, else a model set's with every other default."""
    return preset_config(name) if name in presets()[1] else KeypointPipelineConfig(model_set=name)
