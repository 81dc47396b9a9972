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
from keypoints.decoders import OPENPOSE_LIMBS
from keypoints.detections import Detections
from keypoints.registry import get_spec
from keypoints.skeletons import CANONICAL, get_skeleton
from track import observation as obs
from track.extra_joints import ExtraJointsConfig, attach_session_joints
from track.particle import ParticleConfig, ParticleTracker, TrackArrays, track_sequence
from track.trackfile import TrackFile
from triangulate.chunks import AUTO, NpzRows, parse_chunk_s, remove_output
from triangulate.stage import _fps, load_detections, session_chunk_s

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


def source_of(cfg: ParticleConfig) -> str:
    """The track file's ``source`` for the particle tracker with ``cfg``."""
    return f"track.particle (particle filter, ch. 5) motion={cfg.motion} n_samples={cfg.n_samples}"


def focal_lengths(rig) -> np.ndarray:
    """(C,) mean focal length in pixels per camera."""
    return np.asarray([0.5 * (c.K[0, 0] + c.K[1, 1]) for c in rig.cameras], np.float32)


def _distorter(cam):
    """Undistorted px (...,2) -> image px of ``cam`` (the maps live in image px)."""
    if cam.model != "fisheye" and not np.any(cam.dist):
        return None
    K = np.asarray(cam.K, np.float64)

    def distort(uv: np.ndarray) -> np.ndarray:
        x = (uv[..., 0] - K[0, 2]) / K[0, 0]
        y = (uv[..., 1] - K[1, 2]) / K[1, 1]
        xd, yd = cam.distort_normalized(x, y)
        return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], -1).astype(np.float32)

    return distort


def load_maps(lay: SessionLayout, rig, frames: np.ndarray):
    """The bottom-up model's confidence maps + PAFs stored in ``keypoints/<cam>.npz`` (``maps_f16``,
    ``maps_to_img``; keypoints ``PipelineConfig(keep_maps=True)``) as ``maps_at(t) -> [CameraMaps | None]
    * C`` on the common frame axis ``frames``, or None when no camera has maps."""

    coco18 = get_skeleton("coco18")
    limbs = obs.paf_limbs_in(CANONICAL, coco18.joint_names, OPENPOSE_LIMBS)
    heat_idx = np.asarray([CANONICAL.index(n) for n in coco18.joint_names])
    per_cam = []
    for cam in rig.cameras:
        with NpzRows(lay.detections(cam.name)) as r:  # the member names only: no array is read
            has_maps = {"maps_f16", "maps_to_img"} <= r.names
        if not has_maps:
            per_cam.append(None)
            continue
        det = Detections.load(lay.detections(cam.name))
        try:
            dec = get_spec(det.model).decoder
        except Exception as e:  # noqa: BLE001 - an unknown model: its map layout is unknown
            log.warning("camera %s: maps of unknown model %r ignored (%s)", cam.name, det.model, e)
            per_cam.append(None)
            continue
        n = dec.n_parts
        chans = [c for pair in dec.paf_channels for c in pair] or list(range(2 * len(OPENPOSE_LIMBS)))
        row = np.full(len(frames), -1, np.int64)
        pos = np.searchsorted(frames, det.frame_index)
        row[pos] = np.arange(len(det.frame_index))
        per_cam.append((det.extra["maps_f16"], det.extra["maps_to_img"], n, chans, row, _distorter(cam)))
    if all(p is None for p in per_cam):
        return None

    def maps_at(t: int):
        out = []
        for p in per_cam:
            if p is None or p[4][t] < 0:
                out.append(None)
                continue
            m16, to_img, n, chans, row, distort = p
            m = m16[row[t]].astype(np.float32)  # (h,w,C)
            heat = np.zeros((CANONICAL.n_joints,) + m.shape[:2], np.float32)
            heat[heat_idx] = m[..., :n].transpose(2, 0, 1)
            paf = m[..., n + 1 :][..., chans].reshape(m.shape[0], m.shape[1], -1, 2).transpose(2, 3, 0, 1)
            A = np.vstack([np.asarray(to_img[row[t]], np.float64), [0, 0, 1]])
            out.append(obs.CameraMaps(heat, np.ascontiguousarray(paf), limbs, np.linalg.inv(A)[:2], distort))
        return out

    return maps_at


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
        from track.stream import track_session_particle_chunked  # lazy: track.stream imports this module

        return track_session_particle_chunked(lay, rig, cfg, chunk_s, progress)
    sub, mv = load_detections(lay, rig)
    fps = _fps(lay, mv.t_ns)
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
