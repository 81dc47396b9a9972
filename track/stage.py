"""The track stage's ``particle`` tracker: detections + rig -> ``track/tracks.npz`` (seed ch. 5).

``track_session_particle(session_dir, config)`` reads ``calib/rig.toml`` and every
``keypoints/<cam>.npz`` (aligned on a common frame axis, converted to ``body19`` and undistorted by
:func:`roomcap.triangulate.stage.load_detections`), runs :class:`roomcap.track.particle.ParticleTracker` over
the frames and writes the track file. The videos are never needed. With ``skeleton = "whole_body"`` (or a
skeleton TOML; ``reprocess`` passes ``[triangulate.options] skeleton``) the joints beyond body19 (feet,
head top, ...) are triangulated per track after tracking (:mod:`roomcap.track.extra_joints`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import SessionLayout, require
from roomcap.core.config import as_config, config_from_dict
from roomcap.core.errors import FormatError
from roomcap.core.progress import Progress
from roomcap.track.extra_joints import ExtraJointsConfig, attach_session_joints
from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_chunked import track_session_particle_chunked
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_io import focal_lengths, load_maps, source_of, track_arrays_to_file
from roomcap.track.particle_offline import track_sequence
from roomcap.triangulate.chunks import AUTO, StreamConfig, remove_output, split_stream_keys
from roomcap.triangulate.multiview import load_detections, session_chunk_s, session_fps

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ParticleTrackConfig:
    """The particle track stage: the filter's settings (:class:`ParticleConfig`), the 3D joints and how
    it walks the session (:class:`roomcap.triangulate.chunks.StreamConfig`; streamed by
    :mod:`roomcap.track.particle_chunked`, one
    tracks/1 part per chunk with global track ids and the filter's state per chunk in
    ``track/particle_raw.parts/``, equal to the whole session's result bit for bit; its chunks carry the
    filter's state, so they run in order in one process). ``"auto"`` runs whole with ``skeleton`` other
    than body19, which the streamed tracker does not carry."""

    particle: ParticleConfig = field(default_factory=ParticleConfig)
    # the 3D joints, as the triangulate option: body19 (the filter's state), "whole_body" or a skeleton
    # TOML; the joints beyond body19 are attached to the tracks afterwards (track.extra_joints)
    skeleton: str = "body19"
    extra_joints: ExtraJointsConfig = field(default_factory=ExtraJointsConfig)
    stream: StreamConfig = field(default_factory=StreamConfig)

    def __post_init__(self) -> None:
        if self.skeleton not in ("body19", "whole_body") and not str(self.skeleton).endswith(".toml"):
            raise FormatError(
                None,
                "skeleton",
                f"must be 'body19', 'whole_body' or a skeleton TOML file (.toml), got {self.skeleton!r}.",
            )
        self.stream.check_in_order()
        if self.stream.chunk_s != AUTO and float(self.stream.chunk_s) > 0 and self.skeleton != "body19":
            raise FormatError(
                None,
                "skeleton",
                f"the streamed particle tracker (chunk_s > 0) tracks body19 only, not {self.skeleton!r}.",
                "Set chunk_s = 0 for the whole-body joints, or use the greedy tracker, which streams them.",
            )

    @classmethod
    def from_dict(cls, d: dict) -> ParticleTrackConfig:
        """From ``[track.options]``: the filter's keys flat (or under ``particle``), the stage's beside."""
        own, stream = split_stream_keys(d)
        stage = {k: own.pop(k) for k in ("skeleton", "extra_joints") if k in own}
        particle = own.pop("particle") if "particle" in own else own
        if "particle" in d and own:
            config_from_dict(cls, own)  # names the unknown keys
        return config_from_dict(cls, {**stage, "particle": particle, "stream": stream})


def stream_chunk_s(lay: SessionLayout, stage: ParticleTrackConfig) -> float:
    """Seconds per chunk of the stage on this session (0 = whole), as
    :func:`roomcap.triangulate.stage.session_chunk_s` decides; ``"auto"`` with joints beyond body19 runs
    whole."""
    if stage.stream.chunk_s == AUTO and stage.skeleton != "body19":
        return 0.0
    return session_chunk_s(lay, stage.stream)


def track_session_particle(
    session_dir: str | os.PathLike,
    config: ParticleTrackConfig | dict | None = None,
    progress: Progress | None = None,
) -> Path:
    """Run the particle filter on a session's detections; writes and returns ``track/tracks.npz``."""
    stage = as_config(ParticleTrackConfig, config)
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
