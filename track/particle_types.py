"""What the particle tracker keeps per person and returns per frame: a track's samples and state
(:class:`Track`), an ended identity kept for re-identification (:class:`LostTrack`) and the frame's
estimates (:class:`FrameEstimate`)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np


@dataclass
class FrameEstimate:
    """Output of one frame for the K live tracks (sec. 5.2.4)."""

    track_id: np.ndarray  # (K,)
    xyz_m: np.ndarray  # (K,J,3)
    std_m: np.ndarray  # (K,J)
    confidence: np.ndarray  # (K,J)
    n_views: np.ndarray  # (K,J)
    flags: np.ndarray  # (K,J) uint8
    evidence: np.ndarray  # (K,) bool: the track had an associated detection this frame


@dataclass
class Track:
    id: int
    x: np.ndarray  # (N,J,3)
    state: dict
    born: int
    last_seen: int
    last_seen_s: float = 0.0  # the tracks' clock (pauses of the recorder shortened to one frame)
    pauses_seen: int = 0  # pauses of the recorder before the last evidence
    n_seen: int = 1
    mean: np.ndarray | None = None  # (J,3) last estimate
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))  # pelvis m/s
    bones: np.ndarray | None = None  # (L,) running mean bone lengths


@dataclass
class LostTrack:
    id: int
    end: int
    pelvis: np.ndarray
    velocity: np.ndarray
    bones: np.ndarray | None
    end_s: float = 0.0  # the tracks' clock at the last evidence
    pauses: int = 0  # pauses of the recorder before it


def empty_estimate(J: int) -> FrameEstimate:
    return FrameEstimate(
        np.zeros(0, np.int64),
        np.zeros((0, J, 3), np.float32),
        np.zeros((0, J), np.float32),
        np.zeros((0, J), np.float32),
        np.zeros((0, J), np.int64),
        np.zeros((0, J), np.uint8),
        np.zeros(0, bool),
    )


def concat_estimates(a: FrameEstimate, b: FrameEstimate) -> FrameEstimate:
    """Concatenate, a re-anchored track in b replacing its entry in a."""
    keep = ~np.isin(a.track_id, b.track_id)
    return FrameEstimate(
        *(np.concatenate([getattr(a, f.name)[keep], getattr(b, f.name)]) for f in fields(FrameEstimate))
    )
