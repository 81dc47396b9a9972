"""The pipeline configuration: one TOML, loaded once into typed dataclasses.

Each dataclass holds the only copy of its defaults; unknown keys are rejected
with the list of valid ones. Example ``pipeline.toml``::

    stages = ["keypoints", "triangulate", "track", "forecast", "report"]
    [keypoints]
    preset = "balanced"     # fast | balanced | accurate | feet | hands | feet_hands | legacy
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

from roomcap.core.config import check_keys, config_from_dict
from roomcap.core.errors import FormatError, UnknownNameError
from roomcap.core.fileio import load_toml
from roomcap.keypoints.pipeline_config import KeypointPipelineConfig
from roomcap.keypoints.presets import resolve_preset
from roomcap.keypoints.registry import presets
from roomcap.pipeline.provenance import STAGES
from roomcap.track.greedy_stage import GreedyTrackConfig
from roomcap.track.stage import ParticleTrackConfig
from roomcap.triangulate.reconstruct import TriangulateConfig as TriangulateOptions


@dataclass(frozen=True)
class KeypointsConfig:
    """The ``[keypoints]`` section, resolved once: the preset's name, its settings and the 2D stage's
    typed config (:class:`roomcap.keypoints.pipeline_config.KeypointPipelineConfig`) are computed when the
    section is made."""

    # speed/accuracy preset of the 2D stage (keypoints/models/sets.toml [presets]). "" = the default preset,
    # or, when ``model_set`` is given, "legacy" (the chain of configurations written before presets existed)
    preset: str = ""
    model_set: str = ""  # "" = the preset's
    max_frames: int | None = None  # process only the first N frames (demos, smoke tests)
    # layout of the detections files: body19, or "model" (the model's own, e.g. BlazePose's feet for
    # [triangulate] options.skeleton = "whole_body"); "" = the preset's (body19; "model" for "feet")
    skeleton: str = ""
    preset_name: str = field(init=False, repr=False, compare=False)
    settings: dict[str, Any] = field(init=False, repr=False, compare=False)  # the preset's, with overrides
    detector: KeypointPipelineConfig = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        overrides = {"skeleton": self.skeleton} if self.skeleton else {}
        try:
            resolved = resolve_preset(self.preset, self.model_set, **overrides)
        except UnknownNameError:
            valid = sorted(presets()[1])
            raise FormatError(
                None, "keypoints.preset", f"'{self.preset}' is not a preset; valid: {valid}."
            ) from None
        object.__setattr__(self, "preset_name", resolved.name)
        object.__setattr__(self, "settings", resolved.settings)
        object.__setattr__(self, "detector", resolved.config)

    @property
    def model_set_name(self) -> str:
        return self.detector.model_set

    def provenance(self) -> dict[str, Any]:
        """The settings a keypoints run depends on. A plain model set (the legacy chain) is recorded by its
        name (``skeleton`` only when not body19)."""
        if set(self.settings) <= {"model_set", "skeleton"}:
            d: dict[str, Any] = {"model_set": self.model_set_name, "max_frames": self.max_frames}
            if self.settings.get("skeleton", "body19") != "body19":
                d["skeleton"] = self.settings["skeleton"]
            return d
        return {"preset": self.preset_name, "settings": self.settings, "max_frames": self.max_frames}


# the trackers by the name ``[track] tracker`` and ``--tracker`` give; nothing after parsing sees the name
TRACKER_CONFIGS: dict[str, type[GreedyTrackConfig] | type[ParticleTrackConfig]] = {
    "greedy": GreedyTrackConfig,
    "particle": ParticleTrackConfig,
}
TRACKERS = tuple(TRACKER_CONFIGS)
TrackerChoice = GreedyTrackConfig | ParticleTrackConfig


DEFAULT_TRACKER = "particle"


def tracker_name(track: TrackerChoice) -> str:
    """The name a user writes for the tracker ``track`` configures (``[track] tracker``)."""
    return next(name for name, cls in TRACKER_CONFIGS.items() if isinstance(track, cls))


def _stage_options(where: str, options: Any, parse: Any) -> Any:
    """A stage's ``options`` table parsed by its typed config, errors naming the section and the key."""
    if not isinstance(options, dict):
        raise FormatError(None, where, f"expected a table of settings, got {options!r}.")
    try:
        return parse(dict(options))
    except FormatError as e:
        field_name = f"{where}.{e.field}" if e.field and not e.field.startswith(where) else where
        raise FormatError(None, field_name, str(e).split(": ", 2)[-1]) from None
    except (ValueError, TypeError) as e:
        raise FormatError(None, where, str(e).removeprefix("<input>: ")) from None


def _track_section(data: Any, triangulate: TriangulateOptions) -> TrackerChoice:
    """``[track] tracker`` and ``[track.options]`` as the chosen tracker's typed config. The particle
    tracker's joints follow ``[triangulate.options] skeleton`` unless its options name their own."""
    if not isinstance(data, dict):
        raise FormatError(None, "track", f"expected a table of settings, got {data!r}.")
    check_keys(data, ("tracker", "options"), "track", None)
    name = data.get("tracker", DEFAULT_TRACKER)
    if name not in TRACKER_CONFIGS:
        raise FormatError(None, "track.tracker", f"'{name}' is not a tracker; valid: {list(TRACKERS)}.")
    options = dict(data.get("options", {}))
    if name == "particle" and "skeleton" not in options and triangulate.skeleton != "body19":
        options["skeleton"] = triangulate.skeleton
    return _stage_options("track.options", options, TRACKER_CONFIGS[name].from_dict)


@dataclass(frozen=True)
class ForecastConfig:
    """``[forecast]``: ``horizon_s`` ahead, by ``model`` (see ``forecast.preview.forecast_model``);
    ``samples``: how many forecasts a stochastic model draws (the report draws their spread; a
    deterministic model writes its one forecast)."""

    horizon_s: float = 2.0
    model: str = "default"
    samples: int = 16

    def __post_init__(self) -> None:
        if not isinstance(self.samples, int) or self.samples < 1:
            raise FormatError(None, "forecast.samples", f"must be a whole number >= 1, got {self.samples!r}.")


@dataclass(frozen=True)
class PipelineConfig:
    """Every section of ``pipeline.toml``, each parsed once into its stage's own typed config:
    ``[triangulate.options]`` -> :class:`roomcap.triangulate.reconstruct.TriangulateConfig`; ``[track]
    tracker``
    with ``[track.options]`` -> the tracker's config (:data:`TrackerChoice`: the type is the choice)."""

    stages: tuple[str, ...] = STAGES
    keypoints: KeypointsConfig = field(default_factory=KeypointsConfig)
    triangulate: TriangulateOptions = field(default_factory=TriangulateOptions)
    track: TrackerChoice = field(default_factory=lambda: TRACKER_CONFIGS[DEFAULT_TRACKER]())
    forecast: ForecastConfig = field(default_factory=ForecastConfig)

    def __post_init__(self) -> None:
        bad = [s for s in self.stages if s not in STAGES]
        if bad:
            raise FormatError(None, "stages", f"unknown stages {bad}; valid: {list(STAGES)}.")
        object.__setattr__(self, "stages", tuple(s for s in STAGES if s in self.stages))  # graph order

    @classmethod
    def from_dict(cls, data: dict[str, Any], path: str | Path | None = None) -> PipelineConfig:
        """The config of a parsed TOML (``path`` named in errors), each section checked here, once."""
        try:
            return cls._from_dict(data)
        except FormatError as e:
            raise FormatError(path, e.field, str(e).split(": ", 2)[-1]) from None

    @classmethod
    def _from_dict(cls, data: dict[str, Any]) -> PipelineConfig:
        check_keys(
            data, ("stages", "keypoints", "triangulate", "track", "forecast"), None, None, name_key=True
        )
        kw: dict[str, Any] = {}
        if "stages" in data:
            kw["stages"] = tuple(data["stages"])
        for key, section in (("keypoints", KeypointsConfig), ("forecast", ForecastConfig)):
            if key in data:
                kw[key] = config_from_dict(section, data[key], key)
        tri = data.get("triangulate", {})
        if not isinstance(tri, dict):
            raise FormatError(None, "triangulate", f"expected a table with the key options, got {tri!r}.")
        check_keys(tri, ("options",), "triangulate", None)
        options = tri.get("options", {})
        kw["triangulate"] = _stage_options("triangulate.options", options, TriangulateOptions.from_dict)
        kw["track"] = _track_section(data.get("track", {}), kw["triangulate"])
        return cls(**kw)

    @classmethod
    def load(cls, path: str | Path, overrides: dict[str, Any] | None = None) -> PipelineConfig:
        """``path``'s TOML with the command line's ``overrides`` (``{section: {key: value}}``) merged in
        before it is parsed."""
        return cls.from_dict(merge_sections(load_toml(path), overrides or {}), path)

    def replace(self, **kw) -> PipelineConfig:
        """A copy with ``kw`` changed; sections not given are kept as they are (not parsed again)."""
        return dataclasses.replace(self, **kw)


def merge_sections(data: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """``data`` with ``overrides`` merged in, one level of tables deep (``{"track": {"tracker": "greedy"}}``).

    >>> merge_sections({"track": {"tracker": "particle", "options": {}}}, {"track": {"tracker": "greedy"}})
    {'track': {'tracker': 'greedy', 'options': {}}}
    """
    out = dict(data)
    for key, value in overrides.items():
        out[key] = (
            {**out[key], **value} if isinstance(value, dict) and isinstance(out.get(key), dict) else value
        )
    return out
