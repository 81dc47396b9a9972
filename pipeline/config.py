"""The pipeline configuration: one TOML, loaded once into typed dataclasses.

Each dataclass holds the only copy of its defaults; unknown keys are rejected
with the list of valid ones. Example ``pipeline.toml``::

    stages = ["keypoints", "triangulate", "track", "forecast", "report"]
    [keypoints]
    preset = "balanced"     # fast | balanced | accurate | feet | legacy
    [track]
    tracker = "particle"    # the default: the ch. 5 particle filter; or "greedy" (ch. 4)
    [forecast]
    horizon_s = 2.0
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from core.config import config_from_dict
from core.errors import FormatError
from core.fileio import load_toml
from keypoints.registry import presets
from track.stage import ParticleTrackConfig
from triangulate.reconstruct import TriangulateConfig as TriangulateOptions
from triangulate.stage import GreedyTrackConfig

STAGES = ("calibration", "keypoints", "triangulate", "track", "forecast", "report")
TRACKERS = ("greedy", "particle")


@dataclass(frozen=True)
class KeypointsConfig:
    # speed/accuracy preset of the 2D stage (keypoints/models/sets.toml [presets]). "" = the default preset,
    # or, when ``model_set`` is given, "legacy" (the chain of configurations written before presets existed)
    preset: str = ""
    model_set: str = ""  # "" = the preset's
    max_frames: int | None = None  # process only the first N frames (demos, smoke tests)
    # layout of the detections files: body19, or "model" (the model's own, e.g. BlazePose's feet for
    # [triangulate] options.skeleton = "whole_body"); "" = the preset's (body19; "model" for "feet")
    skeleton: str = ""

    def __post_init__(self) -> None:
        _, table = presets()
        if self.preset and self.preset not in table:
            raise FormatError(
                None, "keypoints.preset", f"'{self.preset}' is not a preset; valid: {sorted(table)}."
            )

    def settings(self) -> tuple[str, dict[str, Any]]:
        """The preset's name and its ``keypoints.pipeline.PipelineConfig`` settings with this section's
        overrides."""
        default, table = presets()
        name = self.preset or ("legacy" if self.model_set else default)
        settings = dict(table[name])
        if self.model_set:
            settings["model_set"] = self.model_set
        if self.skeleton:
            settings["skeleton"] = self.skeleton
        return name, settings

    @property
    def model_set_name(self) -> str:
        return str(self.settings()[1].get("model_set", "default"))

    def provenance(self) -> dict[str, Any]:
        """The settings a keypoints run depends on. A plain model set (the legacy chain) is recorded as it
        was before presets existed (``skeleton`` only when not body19), so those sessions stay current."""
        name, settings = self.settings()
        if set(settings) <= {"model_set", "skeleton"}:
            d: dict[str, Any] = {"model_set": self.model_set_name, "max_frames": self.max_frames}
            if settings.get("skeleton", "body19") != "body19":
                d["skeleton"] = settings["skeleton"]
            return d
        return {"preset": name, "settings": settings, "max_frames": self.max_frames}


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
    """The track stage. ``tracker``: ``particle`` (the default: seed ch. 5's per-person particle filter,
    identities and per-joint uncertainty from its samples; on Pose2Sim's real two-participant trial
    14 mm from Pose2Sim's own triangulation against 26 mm for the greedy tracker, BENCHMARKS.md
    "Tracker by default") or ``greedy`` (ch. 4: matching in time of the per-frame triangulation, about
    3x faster and with less memory)."""

    tracker: str = "particle"
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
