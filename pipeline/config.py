"""The pipeline configuration: one TOML, loaded once into typed dataclasses.

Each dataclass holds the only copy of its defaults; unknown keys are rejected
with the list of valid ones. Example ``pipeline.toml``::

    stages = ["keypoints", "triangulate", "track", "forecast", "report"]
    [keypoints]
    model_set = "default"
    [track]
    tracker = "greedy"      # or "particle"
    [forecast]
    horizon_s = 2.0
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capture.fileio import FormatError, config_from_dict, load_toml
from track.stage import ParticleTrackConfig
from triangulate.reconstruct import TriangulateConfig as TriangulateOptions
from triangulate.stage import GreedyTrackConfig

STAGES = ("calibration", "keypoints", "triangulate", "track", "forecast", "report")
TRACKERS = ("greedy", "particle")


@dataclass(frozen=True)
class KeypointsConfig:
    model_set: str = "default"
    max_frames: int | None = None  # process only the first N frames (demos, smoke tests)
    # layout of the detections files: body19, or "model" (the model's own, e.g. BlazePose's feet for
    # [triangulate] options.skeleton = "whole_body"); see keypoints.pipeline.PipelineConfig.skeleton
    skeleton: str = "body19"

    def provenance(self) -> dict[str, Any]:
        """The settings a keypoints run depends on; ``skeleton`` only when it is not the default, so
        sessions made before the key existed are not run again."""
        d = dataclasses.asdict(self)
        if self.skeleton == "body19":
            d.pop("skeleton")
        return d


def _parse_options(where: str, options: dict[str, Any], parse: Any) -> None:
    """Parse a stage's options with its typed config now, so that a typo in ``reprocess --config`` is
    reported when the config loads, before any session runs, not when that stage is reached."""
    if not options:
        return
    try:
        parse(dict(options))
    except (ValueError, TypeError) as e:
        raise FormatError(None, where, str(e).removeprefix("<input>: ")) from None


@dataclass(frozen=True)
class TriangulateConfig:
    options: dict[str, Any] = field(default_factory=dict)  # passed to triangulate's own config

    def __post_init__(self) -> None:  # once per section: PipelineConfig.replace() keeps the sections
        _parse_options("triangulate.options", self.options, TriangulateOptions.from_dict)


@dataclass(frozen=True)
class TrackConfig:
    tracker: str = "greedy"
    options: dict[str, Any] = field(default_factory=dict)  # passed to the tracker's own config

    def __post_init__(self) -> None:
        if self.tracker not in TRACKERS:
            raise FormatError(
                None, "track.tracker", f"'{self.tracker}' is not a tracker; valid: {list(TRACKERS)}."
            )
        parse = GreedyTrackConfig.from_dict if self.tracker == "greedy" else ParticleTrackConfig.from_dict
        _parse_options("track.options", self.options, parse)


@dataclass(frozen=True)
class ForecastConfig:
    horizon_s: float = 2.0
    model: str = "default"


@dataclass(frozen=True)
class PipelineConfig:
    stages: tuple[str, ...] = STAGES
    keypoints: KeypointsConfig = field(default_factory=KeypointsConfig)
    triangulate: TriangulateConfig = field(default_factory=TriangulateConfig)
    track: TrackConfig = field(default_factory=TrackConfig)
    forecast: ForecastConfig = field(default_factory=ForecastConfig)

    def __post_init__(self) -> None:
        bad = [s for s in self.stages if s not in STAGES]
        if bad:
            raise FormatError(None, "stages", f"unknown stages {bad}; valid: {list(STAGES)}.")
        object.__setattr__(self, "stages", tuple(s for s in STAGES if s in self.stages))  # graph order
        # the stage options were parsed when their sections were made (TriangulateConfig, TrackConfig)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PipelineConfig:
        sections = {
            "keypoints": KeypointsConfig,
            "triangulate": TriangulateConfig,
            "track": TrackConfig,
            "forecast": ForecastConfig,
        }
        kw: dict[str, Any] = {}
        for key, value in data.items():
            if key in sections:
                kw[key] = config_from_dict(sections[key], value, key)
            elif key == "stages":
                kw[key] = tuple(value)
            else:
                raise FormatError(None, key, f"unknown key; valid: {['stages', *sections]}.")
        return cls(**kw)

    @classmethod
    def load(cls, path: str | Path) -> PipelineConfig:
        try:
            return cls.from_dict(load_toml(path))
        except FormatError as e:
            raise FormatError(path, e.field, str(e).split(": ", 2)[-1]) from e

    def replace(self, **kw) -> PipelineConfig:
        """A copy with ``kw`` changed; sections not given are kept as they are (not parsed again)."""
        return dataclasses.replace(self, **kw)
