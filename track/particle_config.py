"""The particle tracker's settings (:class:`ParticleConfig`, the only copy of each default) and the motion
prior they name (:func:`make_prior`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from roomcap.core.config import bounded, config_from_dict
from roomcap.keypoints.skeletons import CANONICAL, Skeleton
from roomcap.track.greedy import (
    SEED_SIGMA_FRAMES,
)
from roomcap.track.priors import (
    DEFAULT_MOTION_CHECKPOINT,
    ConstantVelocityPrior,
    MotionPrior,
    ZeroVelocityPrior,
    load_gru_numpy,
)

MOTIONS = ("gru", "constant_velocity", "zero_velocity")
BIRTHS = ("gaussian", "learned")


@dataclass(frozen=True)
class ParticleConfig:
    """Settings of the particle tracker (the only copy of each default).

    n_samples: pose samples per person (seed: 300).
    motion: 'gru' (eq. 5.1, the shipped checkpoint), 'constant_velocity' or 'zero_velocity'.
    motion_checkpoint: path of a GRU checkpoint ('' = the shipped one).
    motion_dropout: dropout at inference for the GRU (negative = the trained rate; 0 = the
      "prior without dropout" ablation).
    motion_sigma_m: per-frame Gaussian noise at 25 fps of the velocity priors (scaled by sqrt(25/fps)),
      and added to the GRU's output (``gru_sigma_m``).
    resample: per-camera-pair stochastic universal resampling (off = the "w/o resampling" ablation).
    refine: joint refinement (off = the "w/o joint refinement" ablation); refine_candidates = M
      positions per joint including the current one; refine_sigma_m their spread; refine_guided of them
      are drawn around the point the track's detections put the joint at (0 = the seed's purely random
      candidates).
    exact_output_weights: the output weights (sec. 5.2.4) by eq. 5.7 over all cameras in an extra pass;
      by default the refinement's per-joint scores summed over all cameras are reused (product over joints).
    obs_sigma_m / obs_sigma_px: keypoint likelihood tolerance (metres at the joint's depth, and pixels).
    eps: epsilon of eq. 5.7 (per limb).
    min_score: 2D joints below this score are ignored.
    assoc_tol_m / assoc_gate / assoc_min_joints: track-detection association (median joint distance in
      units of assoc_tol_m must stay below assoc_gate, on at least assoc_min_joints joints).
    init_*: birth of tracks (at least init_min_joints triangulated joints seen by init_min_views
      cameras; no live track's pelvis within init_exclusion_m); samples spread init_sigma_m around
      the candidate and init_fill_sigma_m around template-filled joints.
    end_after_s: a track without any associated detection for this long ends.
    max_people: at most this many tracks at once (0 = no limit), for a recording whose number of people
      is known: with as many tracks, no new identity is born (a coasting track is still re-anchored).
    reid_*: a new candidate takes an ended identity when its pelvis lies within
      reid_dist_m + reid_speed_mps * gap of the predicted one and the mean bone-length difference is
      below reid_bone_tol_m, for gaps up to reid_max_gap_s.
    min_track_s: shorter tracks are dropped from the output; trim_coast: frames after a track's last
      evidence are dropped when it ends (offline output); smooth_sigma_s: offline NaN-aware Gaussian
      smoothing of the output in time, in seconds (0 = off; None = the seed's 2 frames at the session's
      rate, as its evaluation does, sec. 5.3.1 from ch. 4), never across two frames more than max_gap_s
      apart; smooth_sigma_frames: the same width in frames (converted at the
      frame rate by :meth:`at_fps`).
    max_gap_s: two consecutive frames further apart than this (+ one frame) are a pause of the recorder:
      the tracks' clock counts it as one frame (termination, re-identification), the motion prior moves
      once across it, and association, re-anchoring and re-identification allow pause_gate_m more distance
      for each pause since the track's last evidence (how far a person may have moved while nothing was
      recorded); shorter gaps (dropped frames) are predicted one motion step per missed frame.
    use_maps: the stage weighs samples with the confidence maps + PAFs (eq. 5.8) stored in the
      detection files by a bottom-up model (keypoints ``keep_maps``); off or absent = keypoints + scores.
    birth: how a new track's samples are drawn (sec. 5.2.3): 'gaussian' = Gaussian noise around the
      candidate, missing joints from the median mocap pose; 'learned' = the generator g of
      :mod:`roomcap.track.birth` (dropout network that fills missing joints, run N times with dropout on);
      birth_checkpoint: its checkpoint ('' = the shipped one).
    threads: parts of a frame's batch computed at once (:class:`roomcap.track.split.Split`; the same tracks
      bit for bit whatever the number and whatever BLAS's kernels: the matrix products run over a fixed
      partition of the batch, BLAS at one thread): 0 = one per available core, up to 4 and up to
      ``OMP_NUM_THREADS`` when set; 1 = one thread.
    seed: random seed.
    """

    n_samples: int = 300
    motion: str = "gru"
    motion_checkpoint: str = ""
    motion_dropout: float = -1.0
    motion_sigma_m: float = 0.01
    gru_sigma_m: float = 0.003
    resample: bool = True
    refine: bool = True
    refine_candidates: int = 3
    refine_sigma_m: float = 0.03
    refine_guided: int = 1
    exact_output_weights: bool = False
    obs_sigma_m: float = 0.05
    obs_sigma_px: float = 3.0
    eps: float = 0.01
    min_score: float = 0.1
    assoc_tol_m: float = 0.1
    assoc_gate: float = 3.0
    assoc_min_joints: int = 3
    init_min_joints: int = 8
    init_min_views: int = 2
    init_exclusion_m: float = 0.5
    init_sigma_m: float = 0.03
    init_fill_sigma_m: float = 0.1
    init_theta_px: float = 40.0
    end_after_s: float = 1.0
    max_people: int = bounded(0, 0, 10_000)
    reid_max_gap_s: float = 10.0
    reid_dist_m: float = 0.5
    reid_speed_mps: float = 1.0
    reid_bone_tol_m: float = 0.05
    min_track_s: float = 0.2
    trim_coast: bool = True
    smooth_sigma_s: float | None = None  # None: the seed's 2 frames at the session's frame rate
    max_gap_s: float = 0.4
    pause_gate_m: float = 0.5
    smooth_sigma_frames: float | None = None  # the old key (frames)
    use_maps: bool = True
    birth: str = "gaussian"
    birth_checkpoint: str = ""
    threads: int = bounded(0, 0, 64)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.motion not in MOTIONS:
            raise ValueError(f"ParticleConfig.motion must be one of {MOTIONS}, got {self.motion!r}.")
        if self.birth not in BIRTHS:
            raise ValueError(f"ParticleConfig.birth must be one of {BIRTHS}, got {self.birth!r}.")
        if self.n_samples < 1:
            raise ValueError(f"ParticleConfig.n_samples must be >= 1, got {self.n_samples}.")
        if self.refine_candidates < 1:
            raise ValueError(f"ParticleConfig.refine_candidates must be >= 1, got {self.refine_candidates}.")
        if self.max_gap_s < 0 or self.pause_gate_m < 0 or self.end_after_s <= 0:
            raise ValueError("ParticleConfig: end_after_s must be positive, max_gap_s and pause_gate_m >= 0.")
        if any(v is not None and v < 0 for v in (self.smooth_sigma_s, self.smooth_sigma_frames)):
            raise ValueError("ParticleConfig: smooth_sigma_s and smooth_sigma_frames must be >= 0.")

    def at_fps(self, fps: float) -> ParticleConfig:
        """The config with the smoothing width given in frames converted to seconds at ``fps`` (as
        :meth:`roomcap.track.greedy.TrackerConfig.at_fps`), the seed's 2 frames when none is set."""
        if self.smooth_sigma_frames is not None:
            return replace(self, smooth_sigma_s=self.smooth_sigma_frames / fps, smooth_sigma_frames=None)
        if self.smooth_sigma_s is None:
            return replace(self, smooth_sigma_s=SEED_SIGMA_FRAMES / fps)
        return self

    def result_settings(self) -> ParticleConfig:
        """The settings the tracks depend on: this config without ``threads`` (how a batch was computed,
        which gives the same bits)."""
        return replace(self, threads=0)

    @classmethod
    def from_dict(cls, d: dict) -> ParticleConfig:
        return config_from_dict(cls, d)


def make_prior(config: ParticleConfig, fps: float, skeleton: Skeleton = CANONICAL) -> MotionPrior:
    """The motion prior named by ``config.motion``; 'gru' from the checkpoint's numpy copy when it has an
    up-to-date one (:func:`roomcap.track.priors.load_gru_numpy`), else from the checkpoint itself (imports
    torch)."""
    sigma = config.motion_sigma_m * float(np.sqrt(25.0 / fps))
    if config.motion == "zero_velocity":
        return ZeroVelocityPrior(sigma, skeleton.n_joints)
    if config.motion == "constant_velocity":
        return ConstantVelocityPrior(sigma, n_joints=skeleton.n_joints)
    path = config.motion_checkpoint or DEFAULT_MOTION_CHECKPOINT
    kw = {
        "dropout": None if config.motion_dropout < 0 else config.motion_dropout,
        "sigma_m": config.gru_sigma_m * float(np.sqrt(25.0 / fps)),
    }
    prior = load_gru_numpy(path, fps, skeleton, **kw)  # the checkpoint's numpy copy: no torch
    if prior is not None:
        return prior
    from roomcap.track.motion import GRUPrior  # lazy: loads torch

    return GRUPrior.load(path, fps=fps, skeleton=skeleton, seed=config.seed, **kw)
