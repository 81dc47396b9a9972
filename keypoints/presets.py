"""Named presets of the 2D stage: a model set and the pipeline settings that trade speed for accuracy.

The presets are data, in the ``[presets]`` table of ``keypoints/models/sets.toml`` (read by
``keypoints.registry.presets``), each chosen by measurement on both Pose2Sim demos
(``bench/bench_keypoints_presets.py``; figures in BENCHMARKS.md, "2D presets").
"""

from __future__ import annotations

import dataclasses
from typing import Any

from core.config import check_keys, config_from_dict
from core.errors import UnknownNameError
from keypoints.pipeline_config import KeypointPipelineConfig
from keypoints.registry import presets


def preset_config(name: str = "", **overrides: Any) -> KeypointPipelineConfig:
    """The 2D stage's settings for a preset ("" = the default preset), with ``KeypointPipelineConfig`` fields
    overridden by ``overrides``."""
    default, table = presets()
    name = name or default
    if name not in table:
        raise UnknownNameError(f"unknown keypoint preset {name!r}; known: {sorted(table)}.")
    check_keys(
        overrides, [f.name for f in dataclasses.fields(KeypointPipelineConfig)], "keypoint settings", None
    )
    cfg = config_from_dict(KeypointPipelineConfig, table[name], f"presets.{name}")
    return dataclasses.replace(cfg, **overrides)
