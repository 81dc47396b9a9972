"""The particle tracker's session IO: the focal lengths and confidence maps it reads beside the
detections, and its result as a track file."""

from __future__ import annotations

import logging

import numpy as np

from roomcap.capture.session import SessionLayout
from roomcap.keypoints.decoders import OPENPOSE_LIMBS
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.registry import get_spec
from roomcap.keypoints.skeletons import CANONICAL, get_skeleton
from roomcap.track import observation as obs
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_offline import TrackArrays
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate.chunks import NpzRows

log = logging.getLogger(__name__)


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
