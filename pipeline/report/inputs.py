"""What the report reads from a session folder, and the settings of what it embeds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import SessionLayout
from roomcap.keypoints.detections import Detections
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate.chunks import parts_dir
from roomcap.triangulate.poses3d import Poses3D

_MAX_FRAMES = 2000  # frames embedded in the viewer (subsampled beyond); ReportConfig.max_viewer_frames


@dataclass(frozen=True)
class ReportConfig:
    """What the report embeds and what it calls a problem.

    max_viewer_frames: 3D frames embedded (evenly subsampled beyond).
    image_budget_bytes: JPEG bytes of the filmstrips, all cameras together (base64 adds a third);
      frames are sampled evenly over the session to fit.
    overlay_budget_bytes: JSON bytes of the 2D overlays of the sampled frames, all cameras together.
    image_max_side_px, jpeg_quality: size of the embedded frames.
    max_film_frames / min_film_frames: sampled frames per camera, at most / at least.
    jump_m, jump_speed_m_s: a track's root moving farther than ``jump_m + jump_speed_m_s * dt`` between
      two frames it is present in is a sudden jump (a walking person moves ~1.5 m/s);
    swap_radius_m: ... and a suspected identity swap when another track was within this of where it
      landed the frame before.
    match_px_frac: a 2D detection takes a track's colour when its mean joint distance to the track's
      reprojection is below this fraction of the reprojection's box diagonal (else it is drawn grey).
    """

    max_viewer_frames: int = _MAX_FRAMES
    image_budget_bytes: int = 18_000_000
    overlay_budget_bytes: int = 4_000_000
    image_max_side_px: int = 480
    jpeg_quality: int = 70
    max_film_frames: int = 600
    min_film_frames: int = 8
    jump_m: float = 0.35
    jump_speed_m_s: float = 2.5
    swap_radius_m: float = 0.35
    match_px_frac: float = 0.35


def _r(a: np.ndarray, nd: int = 3) -> Any:
    """Round and turn NaN into None for JSON."""
    a = np.round(np.asarray(a, dtype=np.float64), nd)
    return np.where(np.isfinite(a), a, None).tolist()


def _f(x: Any, nd: int = 3) -> float | None:
    x = float(x)
    return round(x, nd) if np.isfinite(x) else None


@dataclass
class _Inputs:
    """What the report reads, loaded once; a file that cannot be read is a problem, not a crash."""

    lay: SessionLayout
    rig: Any = None
    rig_error: str = ""
    tracks: Any = None
    tracks_error: str = ""
    tracks_name: str = "tracks.npz"  # live.npz where only the live track exists
    poses: Any = None
    poses_error: str = ""
    detections: dict[str, Any] | None = None
    detections_error: dict[str, str] | None = None


def _load(lay: SessionLayout) -> _Inputs:
    inp = _Inputs(lay, detections={}, detections_error={})
    if lay.rig_toml.exists():
        try:
            inp.rig = CameraRig.load(lay.rig_toml)
        except Exception as e:  # the report shows what it can
            inp.rig_error = str(e)
    # the batch track (the file or a streamed run's parts), else the live one (capture-run --live): the
    # same loader reads both layouts
    for path in (lay.tracks, lay.live_tracks):
        if not (path.exists() or parts_dir(path).is_dir()):
            continue
        inp.tracks_name = path.name
        try:
            inp.tracks = TrackFile.load(path)
        except Exception as e:
            inp.tracks_error = str(e)
        break
    if lay.poses3d.exists() or parts_dir(lay.poses3d).is_dir():
        try:
            inp.poses = Poses3D.load(lay.poses3d)
        except Exception as e:
            inp.poses_error = str(e)

    for cam in lay.detection_cameras():
        try:
            inp.detections[cam] = Detections.load(lay.detections(cam))
        except Exception as e:
            inp.detections_error[cam] = str(e)
    return inp
