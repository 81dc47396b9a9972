"""The track stage's ``particle`` tracker: detections + rig -> ``track/tracks.npz`` (seed ch. 5).

``track_session_particle(session_dir, config)`` reads ``calib/rig.toml`` and every
``keypoints/<cam>.npz`` (aligned on a common frame axis, converted to ``body19`` and undistorted by
:func:`triangulate.stage.load_detections`), runs :class:`track.particle.ParticleTracker` over the
frames and writes the track file. The videos are never needed.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from capture.fileio import FormatError
from capture.session import SessionLayout, require
from keypoints.skeletons import CANONICAL
from track.particle import ParticleConfig, ParticleTracker, TrackArrays, track_sequence
from track.trackfile import TrackFile

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class ParticleTrackConfig:
    """The particle track stage: the filter's settings (see :class:`ParticleConfig`)."""

    particle: ParticleConfig = field(default_factory=ParticleConfig)

    @classmethod
    def from_dict(cls, d: dict) -> ParticleTrackConfig:
        d = dict(d)
        if "particle" in d:
            inner = d.pop("particle")
            if d:
                raise ValueError(
                    f"ParticleTrackConfig: unknown keys {sorted(d)}; valid keys: ['particle'] "
                    f"or the particle keys {sorted(f.name for f in fields(ParticleConfig))}"
                )
            return cls(particle=ParticleConfig.from_dict(inner) if isinstance(inner, dict) else inner)
        return cls(particle=ParticleConfig.from_dict(d))  # flat dict of particle keys


def _as_config(config) -> ParticleConfig:
    if config is None:
        return ParticleConfig()
    if isinstance(config, ParticleConfig):
        return config
    if isinstance(config, ParticleTrackConfig):
        return config.particle
    if isinstance(config, dict):
        return ParticleTrackConfig.from_dict(config).particle
    raise TypeError(
        f"expected ParticleConfig, ParticleTrackConfig, a dict or None, got {type(config).__name__}"
    )


def focal_lengths(rig) -> np.ndarray:
    """(C,) mean focal length in pixels per camera."""
    return np.asarray([0.5 * (c.K[0, 0] + c.K[1, 1]) for c in rig.cameras], np.float32)


def track_arrays_to_file(
    res: TrackArrays,
    frame_index: np.ndarray,
    t_ns: np.ndarray,
    fps: float,
    calibration_sha256: str = "",
    source: str = "track.particle",
) -> TrackFile:
    return TrackFile(
        fps=fps,
        frame_index=frame_index,
        t_ns=t_ns,
        track_id=res.track_id,
        joint_names=CANONICAL.joint_names,
        parents=np.asarray(CANONICAL.parents),
        xyz_m=res.xyz_m,
        confidence=res.confidence,
        std_m=res.std_m,
        flags=res.flags,
        calibration_sha256=calibration_sha256,
        source=source,
    )


def track_session_particle(
    session_dir: str | os.PathLike,
    config: ParticleConfig | ParticleTrackConfig | dict | None = None,
    progress: Progress | None = None,
) -> Path:
    """Run the particle filter on a session's detections; writes and returns ``track/tracks.npz``."""
    from calibrate.camera import CameraRig
    from triangulate.stage import _fps, load_detections

    cfg = _as_config(config)
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
    sub, mv = load_detections(lay, rig)
    fps = _fps(lay, mv.t_ns)
    tracker = ParticleTracker(sub.projection_matrices(), focal_lengths(sub), fps, cfg)
    kp = np.moveaxis(mv.xy_px, 0, 1).astype(np.float32)  # (T,C,P,J,2)
    sc = np.moveaxis(mv.score, 0, 1).astype(np.float32)
    T = len(mv.frame_index)

    def prog(it):
        for i in it:
            yield i
            if progress is not None:
                progress(i + 1, T)

    res = track_sequence(tracker, kp, sc, mv.frame_index, progress=prog)
    tf = track_arrays_to_file(
        res,
        mv.frame_index,
        mv.t_ns,
        fps,
        rig.sha256(),
        f"track.particle motion={cfg.motion} n_samples={cfg.n_samples}",
    )
    lay.tracks.parent.mkdir(parents=True, exist_ok=True)
    tf.save(lay.tracks)
    log.info(
        "particle tracker: %d tracks over %d frames from %d cameras (%.1f ms per frame)",
        tf.n_tracks,
        tf.n_frames,
        len(sub),
        1e3 * float(res.time_s.mean()) if T else 0.0,
    )
    return lay.tracks
