"""The track stage's ``particle`` tracker: detections + rig -> ``track/tracks.npz`` (seed ch. 5).

``track_session_particle(session_dir, config)`` reads ``calib/rig.toml`` and every
``keypoints/<cam>.npz`` (aligned on a common frame axis, converted to ``body19`` and undistorted by
:func:`triangulate.stage.load_detections`), runs :class:`track.particle.ParticleTracker` over the
frames and writes the track file. The videos are never needed. With ``skeleton = "whole_body"`` (or a
skeleton TOML; ``reprocess`` passes ``[triangulate.options] skeleton``) the joints beyond body19 (feet,
head top, ...) are triangulated per track after tracking (:mod:`track.extra_joints`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calibrate.camera import CameraRig
from capture.session import SessionLayout, require
from core.config import config_from_dict
from core.errors import FormatError
from core.progress import Progress
from track.extra_joints import ExtraJointsConfig, attach_session_joints
from track.particle import ParticleConfig, ParticleTracker, track_sequence
from track.particle_io import focal_lengths, load_maps, source_of, track_arrays_to_file
from track.stream import track_session_particle_chunked
from triangulate.chunks import AUTO, parse_chunk_s, remove_output
from triangulate.stage import load_detections, session_chunk_s, session_fps

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ParticleTrackConfig:
    """The particle track stage: the filter's settings (see :class:`ParticleConfig`).

    chunk_s: stream the session in time chunks of this many seconds (:mod:`track.stream`): bounded
    memory, output ``track/tracks.parts/`` (one tracks/1 file per chunk, global track ids, an index with
    sizes and hashes; the filter's raw output and state per chunk in ``track/particle_raw.parts/``), a
    killed run resumes at the last complete chunk; the result equals the whole session's bit for bit.
    0 = at once into ``tracks.npz``; ``"auto"`` (the default) = streamed when the session is long
    (:func:`triangulate.stage.session_chunk_s`; whole with ``skeleton`` other than body19, which the
    streamed tracker does not carry)."""

    particle: ParticleConfig = field(default_factory=ParticleConfig)
    # the 3D joints, as the triangulate option: body19 (the filter's state), "whole_body" or a skeleton
    # TOML; the joints beyond body19 are attached to the tracks afterwards (track.extra_joints)
    skeleton: str = "body19"
    extra_joints: ExtraJointsConfig = field(default_factory=ExtraJointsConfig)
    chunk_s: float | str = AUTO

    def __post_init__(self) -> None:
        if self.skeleton not in ("body19", "whole_body") and not str(self.skeleton).endswith(".toml"):
            raise FormatError(
                None,
                "skeleton",
                f"must be 'body19', 'whole_body' or a skeleton TOML file (.toml), got {self.skeleton!r}.",
            )
        object.__setattr__(self, "chunk_s", parse_chunk_s(self.chunk_s, "ParticleTrackConfig.chunk_s"))
        if self.chunk_s != AUTO and float(self.chunk_s) > 0 and self.skeleton != "body19":
            raise FormatError(
                None,
                "skeleton",
                f"the streamed particle tracker (chunk_s > 0) tracks body19 only, not {self.skeleton!r}.",
                "Set chunk_s = 0 for the whole-body joints, or use the greedy tracker, which streams them.",
            )

    @classmethod
    def from_dict(cls, d: dict) -> ParticleTrackConfig:
        if "particle" in d:
            return config_from_dict(cls, d)
        stage = {k: d[k] for k in ("skeleton", "extra_joints", "chunk_s") if k in d}
        flat = {k: v for k, v in d.items() if k not in stage}  # flat dict of particle keys
        return replace(config_from_dict(cls, stage), particle=ParticleConfig.from_dict(flat))


def _as_stage_config(config) -> ParticleTrackConfig:
    if config is None:
        return ParticleTrackConfig()
    if isinstance(config, ParticleConfig):
        return ParticleTrackConfig(particle=config)
    if isinstance(config, ParticleTrackConfig):
        return config
    if isinstance(config, dict):
        return ParticleTrackConfig.from_dict(config)
    raise TypeError(
        f"expected ParticleConfig, ParticleTrackConfig, a dict or None, got {type(config).__name__}"
    )


def stream_chunk_s(lay: SessionLayout, stage: ParticleTrackConfig) -> float:
    """Seconds per chunk of the stage on this session (0 = whole): ``chunk_s`` as
    :func:`triangulate.stage.session_chunk_s` resolves it; ``"auto"`` with joints beyond body19 runs
    whole (the streamed tracker carries body19 only)."""
    if stage.chunk_s == AUTO and stage.skeleton != "body19":
        return 0.0
    return session_chunk_s(lay, stage.chunk_s)


def track_session_particle(
    session_dir: str | os.PathLike,
    config: ParticleConfig | ParticleTrackConfig | dict | None = None,
    progress: Progress | None = None,
) -> Path:
    """Run the particle filter on a session's detections; writes and returns ``track/tracks.npz``."""

    stage = _as_stage_config(config)
    cfg = stage.particle
    lay = SessionLayout(session_dir)
    rig_path = require(
        lay.rig_toml, "the calibration calib/rig.toml", "Calibrate the rig or import a calibration."
    )
    rig = CameraRig.load(rig_path)
    if len(rig) < 2:
        raise FormatError(
            rig_path,
            "cameras",
            f"the particle tracker needs at least 2 cameras to start tracks, the rig has {len(rig)}.",
            "Calibrate at least two cameras.",
        )
    chunk_s = stream_chunk_s(lay, stage)
    if chunk_s > 0:
        return track_session_particle_chunked(lay, rig, cfg, chunk_s, progress)
    sub, mv = load_detections(lay, rig)
    fps = session_fps(lay, mv.t_ns)
    tracker = ParticleTracker(sub.projection_matrices(), focal_lengths(sub), fps, cfg)
    kp = np.moveaxis(mv.xy_px, 0, 1).astype(np.float32)  # (T,C,P,J,2)
    sc = np.moveaxis(mv.score, 0, 1).astype(np.float32)
    T = len(mv.frame_index)

    maps_at = load_maps(lay, sub, mv.frame_index) if cfg.use_maps else None
    if maps_at is not None:
        log.info("particle tracker: weighing samples with the stored confidence maps + PAFs (eq. 5.8)")
    res = track_sequence(tracker, kp, sc, mv.frame_index, progress=progress, maps_at=maps_at, t_ns=mv.t_ns)
    tf = track_arrays_to_file(
        res,
        mv.frame_index,
        mv.t_ns,
        fps,
        rig.sha256(),
        source_of(cfg),
    )
    if stage.skeleton != "body19":
        tf = attach_session_joints(lay, rig, sub, tf, stage.skeleton, stage.extra_joints)
    lay.tracks.parent.mkdir(parents=True, exist_ok=True)
    remove_output(lay.tracks)  # and a streamed run's parts
    tf.save(lay.tracks)
    log.info(
        "particle tracker: %d tracks over %d frames from %d cameras (%.1f ms per frame)",
        tf.n_tracks,
        tf.n_frames,
        len(sub),
        1e3 * float(res.time_s.mean()) if T else 0.0,
    )
    return lay.tracks
