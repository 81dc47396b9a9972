"""The per-person recursive Bayesian filter of seed ch. 5 (Kwon, Tanke, Gall), one frame at a time.

Each tracked person is a set of N 3D pose samples (``body19``, world metres). Per
frame (:meth:`ParticleTracker.step`), for all tracks at once (arrays (K,N,J,3)):

1. **predict** (sec. 5.2.1, eq. 5.1): the motion prior moves every sample
   (GRU with dropout on, or constant/zero velocity), one state per sample;
2. **associate**: every camera's detections are assigned to tracks (Hungarian on the
   reprojected predicted mean); a track only scores against its own detection, so two
   people close together do not pull on each other's samples (our addition: the seed
   scores against the full confidence maps and separates people only at birth);
3. **update** (sec. 5.2.2): importance weights per camera pair (eq. 5.6–5.7), stochastic
   universal resampling of N/V samples per pair, then joint refinement (M candidate
   positions per joint, the best-scoring kept). Our addition: besides random candidates around
   the joint, ``refine_guided`` candidates are drawn around the point the track's detections put
   the joint at (triangulated from its views, or moved onto the single view's ray), so a fast
   joint is caught in one frame with M = 3 instead of the seed's 50 random candidates;
4. **inference** (sec. 5.2.4): weighted mean over all cameras, per-joint spread
   ``std_m``, OBSERVED (seen by >= 1 camera) / PREDICTED (carried through occlusion) flags;
   offline, :func:`track_sequence` also drops trailing coasting frames, short tracks, and
   smooths in time (sigma 2 frames, as the seed's evaluation does, flag SMOOTHED);
5. **termination**: a track with no associated detection for ``end_after_s`` ends; its
   identity is kept for re-identification for ``reid_max_gap_s``;
6. **initialisation** (sec. 5.2.3): the detections no track explains are matched and
   triangulated with the chapter-4 engine (:class:`triangulate.reconstruct.FrameReconstructor`);
   each candidate (best first) either re-anchors a coasting track, revives a lost identity
   (position, velocity, body proportions agree) or starts a new track. Samples are drawn
   around the candidate; joints it lacks are filled from a mocap template with a larger spread
   (``birth='gaussian'``, the default) or all N samples come from the seed's dropout network g
   (``birth='learned'``, :mod:`track.birth`: run N times with dropout on, it fills the missing joints).

No Python loop runs over samples; loops run over tracks (gathers, refinement blocks of joints),
cameras (association) and new candidates (initialisation) only.

With a bottom-up model's confidence maps + part affinity fields for a frame (``step(..., maps=)``, the
stage reads them from the detection files), the resampling weights of eq. 5.6–5.7 use eq. 5.8 on the maps
of those cameras (:func:`track.observation.map_limb_scores`, all samples at once); association, joint
refinement and the output weights still use the associated keypoints.

Not implemented from the seed: the confidence-subtraction network of sec. 5.2.3.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, fields, replace

import numpy as np

from core.config import bounded, config_from_dict
from core.progress import Progress
from keypoints.skeletons import CANONICAL, Skeleton
from track import kernels
from track import observation as obs
from track.greedy import (
    SEED_SIGMA_FRAMES,
    frame_times_s,
    long_enough,
    nominal_dt,
    pause_clock,
    segment_frames,
    smooth_segments,
    sparse_time_warning,
)
from track.normalize import denormalize, hip_frame
from track.priors import (
    DEFAULT_MOTION_CHECKPOINT,
    TEMPLATE_BODY19_M,
    ConstantVelocityPrior,
    MotionPrior,
    ZeroVelocityPrior,
    concat_states,
    load_gru_numpy,
    standard_normals,
)
from track.trackfile import OBSERVED, PREDICTED, SMOOTHED
from triangulate.matching import MatchConfig
from triangulate.reconstruct import FrameReconstructor, TriangulateConfig

log = logging.getLogger(__name__)

_GUIDED_LAM = 0.01  # the guided targets' pull towards the sample's own joint (observation.guided_targets)


STATE_SCHEMA = "particle_state/1"
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
      apart; smooth_sigma_frames: the same width in frames, as earlier versions took it (converted at the
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
      :mod:`track.birth` (dropout network that fills missing joints, run N times with dropout on);
      birth_checkpoint: its checkpoint ('' = the shipped one).
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
        :meth:`track.greedy.TrackerConfig.at_fps`), the seed's 2 frames when none is set."""
        if self.smooth_sigma_frames is not None:
            return replace(self, smooth_sigma_s=self.smooth_sigma_frames / fps, smooth_sigma_frames=None)
        if self.smooth_sigma_s is None:
            return replace(self, smooth_sigma_s=SEED_SIGMA_FRAMES / fps)
        return self

    @classmethod
    def from_dict(cls, d: dict) -> ParticleConfig:
        return config_from_dict(cls, d)


def make_prior(config: ParticleConfig, fps: float, skeleton: Skeleton = CANONICAL) -> MotionPrior:
    """The motion prior named by ``config.motion``; 'gru' from the checkpoint's numpy copy when it has an
    up-to-date one (:func:`track.priors.load_gru_numpy`), else from the checkpoint itself (imports torch)."""
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
    from track.motion import GRUPrior  # lazy: loads torch

    return GRUPrior.load(path, fps=fps, skeleton=skeleton, seed=config.seed, **kw)


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
class _Track:
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
class _Lost:
    id: int
    end: int
    pelvis: np.ndarray
    velocity: np.ndarray
    bones: np.ndarray | None
    end_s: float = 0.0  # the tracks' clock at the last evidence
    pauses: int = 0  # pauses of the recorder before it


class ParticleTracker:
    """The filter over a rig. P: (C,3,4) projection matrices (undistorted px); focal_px: (C,).

    ``step(kp, sc, frame, t_s=)`` takes one frame of undistorted detections ``kp (C,D,J,2)`` (NaN =
    missing) and scores ``sc (C,D,J)`` at time ``t_s`` (seconds, increasing; default ``frame / fps``) and
    returns a :class:`FrameEstimate`. Durations are in seconds on the tracks' clock (see
    ``ParticleConfig.max_gap_s``): dropped frames, jittered times and pauses of the recorder are handled.
    """

    def __init__(
        self,
        P: np.ndarray,
        focal_px: np.ndarray,
        fps: float,
        config: ParticleConfig | None = None,
        skeleton: Skeleton = CANONICAL,
        prior: MotionPrior | None = None,
    ):
        self.config = cfg = (config or ParticleConfig()).at_fps(float(fps))
        self.P = np.asarray(P, np.float32)
        if self.P.ndim != 3 or self.P.shape[1:] != (3, 4):
            raise ValueError(f"P must have shape (C,3,4), got {self.P.shape}")
        C = len(self.P)
        self.focal = np.asarray(focal_px, np.float32).reshape(C)
        self.fps = float(fps)
        self.skeleton = skeleton
        self.limbs = np.asarray(skeleton.limbs, np.int64)
        self.pairs = obs.camera_pairs(C)
        # eq. 5.7's product over limbs in float64 (kernels.pair_weights): each factor >= eps, so it stays
        # above float64's smallest normal when eps^L does; else the weights take the numpy path in logs
        self._phi_in_range = len(self.limbs) * -np.log10(min(cfg.eps, 1.0)) < 290
        self.centers, self.Minv = obs.camera_rays(self.P)
        self.rng = np.random.default_rng(cfg.seed)
        self.prior = prior if prior is not None else make_prior(cfg, fps, skeleton)
        self.tracks: list[_Track] = []
        self.n_map_scores = 0  # update steps whose weights came from confidence maps + PAFs
        self._batch: tuple | None = None  # the last step's (X, state, the tracks' views of them)
        self.lost: list[_Lost] = []
        self.ended: list[tuple[int, int, int]] = []  # (id, born, last_seen) of ended track segments
        self.next_id = 0
        self.end_after = max(1, int(round(cfg.end_after_s * fps)))
        self.t_s: float | None = None  # time of the last frame stepped (s)
        self.clock_s = 0.0  # the tracks' clock: time with every pause shortened to one frame
        self.pauses = 0  # pauses of the recorder so far
        self.dt_s = 1.0 / self.fps  # the last step on the tracks' clock
        self.reconstructor = None
        if C >= 2:
            tcfg = TriangulateConfig(
                match=MatchConfig(theta_px=cfg.init_theta_px, min_score=cfg.min_score),
                min_joints_3d=cfg.init_min_joints,
            )
            self.reconstructor = FrameReconstructor(
                self.P.astype(np.float64), config=tcfg, joint_names=skeleton.joint_names
            )
        else:
            log.warning(
                "a single camera cannot start tracks (sec. 5.2.3 triangulates); only existing tracks run"
            )
        self._tmpl = TEMPLATE_BODY19_M if skeleton.id == "body19" else None
        self.birth = None
        if cfg.birth == "learned":  # imports torch (a learned module)
            from track.birth import BirthGenerator  # lazy: loads torch

            self.birth = BirthGenerator.load(
                cfg.birth_checkpoint, skeleton, sigma_obs_m=cfg.init_sigma_m, sigma_fill_m=cfg.init_sigma_m
            )

    # ------------------------------------------------------------------ state (resume)

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Everything the next :meth:`step` needs, as plain arrays (npz, no pickle): the tracks (samples,
        motion state, bookkeeping), the lost identities, the clock and the random generator's state.
        :meth:`load_state_arrays` on a tracker built with the same rig and config continues bit for bit
        (a streamed run resumes from it, :mod:`track.stream`)."""
        meta = {
            "schema": STATE_SCHEMA,
            "rng": self.rng.bit_generator.state,
            "next_id": self.next_id,
            "t_s": self.t_s,
            "clock_s": self.clock_s,
            "pauses": self.pauses,
            "dt_s": self.dt_s,
            "n_map_scores": self.n_map_scores,
            "ended": [list(map(int, e)) for e in self.ended],
            "tracks": [],
            "lost": [],
        }
        out: dict[str, np.ndarray] = {}
        for i, t in enumerate(self.tracks):
            meta["tracks"].append(
                {
                    "id": t.id,
                    "born": t.born,
                    "last_seen": t.last_seen,
                    "last_seen_s": t.last_seen_s,
                    "pauses_seen": t.pauses_seen,
                    "n_seen": t.n_seen,
                    "state": sorted(t.state),
                    "mean": t.mean is not None,
                    "bones": t.bones is not None,
                }
            )
            out[f"track{i}_x"], out[f"track{i}_velocity"] = t.x, t.velocity
            for k, v in t.state.items():
                out[f"track{i}_state_{k}"] = v
            if t.mean is not None:
                out[f"track{i}_mean"] = t.mean
            if t.bones is not None:
                out[f"track{i}_bones"] = t.bones
        for i, lt in enumerate(self.lost):
            meta["lost"].append(
                {
                    "id": lt.id,
                    "end": lt.end,
                    "end_s": lt.end_s,
                    "pauses": lt.pauses,
                    "bones": lt.bones is not None,
                }
            )
            out[f"lost{i}_pelvis"], out[f"lost{i}_velocity"] = lt.pelvis, lt.velocity
            if lt.bones is not None:
                out[f"lost{i}_bones"] = lt.bones
        out["state_meta"] = np.asarray(json.dumps(meta))
        return out

    def load_state_arrays(self, d) -> None:
        """Restore the state written by :meth:`state_arrays` (``d``: a mapping of its arrays)."""
        try:
            meta = json.loads(str(d["state_meta"]))
            if meta.get("schema") != STATE_SCHEMA:
                raise ValueError(f"schema {meta.get('schema')!r}, expected {STATE_SCHEMA!r}")
            self.rng.bit_generator.state = meta["rng"]
            self.next_id, self.t_s, self.clock_s = int(meta["next_id"]), meta["t_s"], float(meta["clock_s"])
            self.pauses, self.dt_s = int(meta["pauses"]), float(meta["dt_s"])
            self.n_map_scores = int(meta["n_map_scores"])
            self.ended = [tuple(e) for e in meta["ended"]]
            self.tracks = []
            self._batch = None
            for i, m in enumerate(meta["tracks"]):
                self.tracks.append(
                    _Track(
                        int(m["id"]),
                        np.asarray(d[f"track{i}_x"]),
                        {k: np.asarray(d[f"track{i}_state_{k}"]) for k in m["state"]},
                        int(m["born"]),
                        int(m["last_seen"]),
                        float(m["last_seen_s"]),
                        int(m["pauses_seen"]),
                        int(m["n_seen"]),
                        np.asarray(d[f"track{i}_mean"]) if m["mean"] else None,
                        np.asarray(d[f"track{i}_velocity"]),
                        np.asarray(d[f"track{i}_bones"]) if m["bones"] else None,
                    )
                )
            self.lost = [
                _Lost(
                    int(m["id"]),
                    int(m["end"]),
                    np.asarray(d[f"lost{i}_pelvis"]),
                    np.asarray(d[f"lost{i}_velocity"]),
                    np.asarray(d[f"lost{i}_bones"]) if m["bones"] else None,
                    float(m["end_s"]),
                    int(m["pauses"]),
                )
                for i, m in enumerate(meta["lost"])
            ]
        except (KeyError, ValueError, TypeError) as e:
            raise ValueError(f"not a particle tracker state ({e})") from None

    # ------------------------------------------------------------------ helpers

    def _check_frame(self, kp: np.ndarray, sc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        C, J = len(self.P), self.skeleton.n_joints
        kp = np.asarray(kp, np.float32)
        sc = np.asarray(sc, np.float32)
        if kp.ndim != 4 or kp.shape[0] != C or kp.shape[2:] != (J, 2):
            raise ValueError(f"kp must have shape (C={C},D,J={J},2), got {kp.shape}")
        if sc.shape != kp.shape[:3]:
            raise ValueError(f"sc must have shape {kp.shape[:3]} (C,D,J), got {sc.shape}")
        bad = ~np.isfinite(kp).all(-1) | ~np.isfinite(sc) | (sc < self.config.min_score)
        kp = np.where(bad[..., None], np.nan, kp)
        sc = np.where(bad, 0.0, sc).astype(np.float32)
        return kp, sc

    def _bones(self, x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(x[..., self.limbs[:, 0], :] - x[..., self.limbs[:, 1], :], axis=-1)

    def _pelvis(self, x: np.ndarray) -> np.ndarray:
        origin, _ = hip_frame(x[None], self.skeleton)
        return origin[0]

    def _batch_of_tracks(self) -> tuple[np.ndarray, dict]:
        """The live tracks' samples (K,N,J,3) and motion state as one batch: the last step's batch itself
        when the tracks still hold its views (no track born, ended or re-anchored since), else stacked."""
        if self._batch is not None:
            X, state, views = self._batch
            self._batch = None
            if len(views) == len(self.tracks) and all(
                t.x is x and t.state is st for t, (x, st) in zip(self.tracks, views, strict=True)
            ):
                return X, state
        return np.stack([t.x for t in self.tracks]), concat_states([t.state for t in self.tracks])

    # ------------------------------------------------------------------ the step

    def _advance_clock(self, frame: int, t_s: float | None) -> int:
        """Move the tracks' clock to the frame at ``t_s`` (default ``frame / fps``); returns the motion
        steps to predict: 1 per nominal frame interval elapsed, 1 across a pause (an unknown motion)."""
        t = float(frame) / self.fps if t_s is None else float(t_s)
        if not np.isfinite(t):
            raise ValueError(f"frame {frame}: its time {t_s!r} is not a finite number of seconds")
        if self.t_s is None:
            self.t_s, self.dt_s = t, 1.0 / self.fps
            return 1
        dt = t - self.t_s
        if dt <= 0:
            raise ValueError(
                f"frame {frame}: time {t:.6f} s does not follow the previous frame's {self.t_s:.6f} s; "
                "frame times must increase (check the recording's timestamps)"
            )
        self.t_s = t
        if dt > self.config.max_gap_s + nominal_dt(self.fps):  # a pause of the recorder: one frame
            self.pauses += 1
            self.dt_s = 1.0 / self.fps
            self.clock_s += self.dt_s
            return 1
        self.dt_s = dt
        self.clock_s += dt
        return max(1, int(round(dt * self.fps)))

    def step(
        self, kp: np.ndarray, sc: np.ndarray, frame: int, maps=None, t_s: float | None = None
    ) -> FrameEstimate:
        """One frame at time ``t_s`` (seconds, increasing; default ``frame / fps``). ``maps``: optional
        sequence of C :class:`track.observation.CameraMaps` or None per camera (a bottom-up model's
        confidence maps + PAFs); with any, the update weights use eq. 5.8 on the maps for those cameras
        (keypoints for the others)."""
        cfg = self.config
        kp, sc = self._check_frame(kp, sc)
        pauses_before = self.pauses
        n_pred = self._advance_clock(frame, t_s)
        now = self.clock_s
        if self.pauses > pauses_before:
            self._end_at_pause()
        if maps is not None:
            maps = list(maps)
            if len(maps) != len(self.P):
                raise ValueError(
                    f"maps must have one entry (CameraMaps or None) per camera ({len(self.P)}), "
                    f"got {len(maps)}"
                )
            if all(m is None for m in maps):
                maps = None
        C, D, J = kp.shape[:3]
        K, N = len(self.tracks), cfg.n_samples
        ev_k = np.zeros(K, bool)
        out = None
        assigned = np.full((C, 0), -1, np.int64)
        if K:
            X, state = self._batch_of_tracks()  # (K,N,J,3), the motion state of the K*N samples
            # 1. prediction (eq. 5.1), all tracks and samples in one batch; one step per frame interval
            Xf = X.reshape(K * N, J, 3)
            for _ in range(n_pred):  # > 1 only over dropped frames
                Xf, state = self.prior.predict(Xf, state, self.rng)
            X = Xf.reshape(K, N, J, 3)
            # tracks whose last evidence precedes a pause of the recorder: wider gates, fresh motion state
            paused = np.asarray([self.pauses - t.pauses_seen for t in self.tracks], np.float64)
            # 2. association on the predicted means
            mean_pred = X.mean(1)
            muv, mz = obs.project(self.P, mean_pred)  # (C,K,J,2), (C,K,J)
            assigned = obs.associate(
                muv,
                mz,
                kp,
                sc,
                self.focal,
                cfg.assoc_tol_m,
                cfg.assoc_gate + paused * (cfg.pause_gate_m / cfg.assoc_tol_m),
                cfg.assoc_min_joints,
                cfg.min_score,
            )  # (C,K)
            has = assigned >= 0
            sel = np.maximum(assigned, 0)
            akp = np.where(has[..., None, None], kp[np.arange(C)[:, None], sel], np.nan)  # (C,K,J,2)
            asc = np.where(has[..., None], sc[np.arange(C)[:, None], sel], 0.0)  # (C,K,J)
            akp = np.ascontiguousarray(np.moveaxis(akp, 0, 1))  # (K,C,J,2)
            asc = np.ascontiguousarray(np.moveaxis(asc, 0, 1)).astype(np.float32)  # (K,C,J)
            ev_k = has.any(0)
            score_u, u = None, np.zeros(0, np.int64)
            rays = kernels.ray_basis(self.Minv, akp)  # (K,J,3C,3), as obs.ray_basis
            # 3. update for the tracks with evidence
            if ev_k.any():
                u = np.flatnonzero(ev_k)
                X, state, score_u = self._update_seen(X, state, u, rays, asc, maps)
                resume = np.flatnonzero(ev_k & (paused > 0))
                if len(resume):  # the motion before a pause says nothing about the motion after it
                    rows = (resume[:, None] * N + np.arange(N)).ravel()
                    fresh = self.prior.init_state(X[resume].reshape(-1, J, 3))
                    state = {kk: v.copy() for kk, v in state.items()}
                    for kk, v in fresh.items():
                        state[kk][rows] = v
            # 4. inference (sec. 5.2.4): weighted mean over all cameras
            if cfg.exact_output_weights or score_u is None:
                conf = obs.joint_scores(
                    X, self.centers, rays, asc, self.focal, cfg.obs_sigma_m, cfg.obs_sigma_px
                )  # (K,C,J,N)
                lp = obs.log_phi_all(obs.limb_scores(conf, self.limbs, 2), cfg.eps)
                mean, std = obs.weighted_stats(X, lp)
            else:  # the refinement's scores of the kept joints, summed over all cameras, product over joints
                score = np.zeros((K, J, N), np.float32)
                score[u] = score_u
                mean, std = kernels.output_stats(X, score, ev_k, cfg.eps)
            n_views = (asc > 0).sum(1)  # (K,J)
            conf_out = np.clip(asc.sum(1) / np.maximum(n_views, 1) * np.minimum(n_views, 2) / 2.0, 0, 1)
            flags = np.where(n_views > 0, OBSERVED, PREDICTED).astype(np.uint8)
            states = [{kk: v[k * N : (k + 1) * N] for kk, v in state.items()} for k in range(K)]  # views
            pel_now = hip_frame(mean, self.skeleton)[0]  # (K,3)
            had = [t.mean is not None for t in self.tracks]
            pel_before = np.zeros((K, 3), np.float32)  # the pelvis of each track's last estimate
            if any(had):
                prev = np.stack([t.mean for t in self.tracks if t.mean is not None])
                pel_before[had] = hip_frame(prev, self.skeleton)[0]
            bones_now = np.where(n_views[:, self.limbs].min(2) > 0, self._bones(mean), np.nan)  # (K,L)
            for k, t in enumerate(self.tracks):
                t.x, t.state = X[k], states[k]
            self._batch = (X, state, [(t.x, t.state) for t in self.tracks])
            for k, t in enumerate(self.tracks):
                if had[k] and paused[k] == 0:
                    v = (pel_now[k] - pel_before[k]) / self.dt_s
                    t.velocity = (0.8 * t.velocity + 0.2 * v).astype(np.float32)
                elif paused[k] > 0 and ev_k[k]:
                    t.velocity = np.zeros(3, np.float32)
                t.mean = mean[k]
                if ev_k[k]:
                    t.last_seen, t.last_seen_s, t.pauses_seen = frame, now, self.pauses
                    t.n_seen += 1
                    b = bones_now[k]
                    if t.bones is None:
                        t.bones = b
                    else:
                        t.bones = np.where(
                            np.isfinite(b),
                            np.where(np.isfinite(t.bones), 0.9 * t.bones + 0.1 * b, b),
                            t.bones,
                        )
            out = FrameEstimate(
                np.array([t.id for t in self.tracks], np.int64), mean, std, conf_out, n_views, flags, ev_k
            )
            # 5. termination
            keep = []
            for (
                t
            ) in self.tracks:  # on the clock: end_after_s, as a whole number of frames at the nominal rate
                if now - t.last_seen_s >= (self.end_after - 0.5) / self.fps:
                    self.ended.append((t.id, t.born, t.last_seen))
                    self.lost.append(
                        _Lost(
                            t.id,
                            t.last_seen,
                            self._pelvis(t.mean),
                            t.velocity.copy(),
                            t.bones,
                            t.last_seen_s,
                            t.pauses_seen,
                        )
                    )
                else:
                    keep.append(t)
            self.tracks = keep
        # 6. initialisation from the detections no track explains
        born = self._initialise(kp, sc, assigned, frame)
        if born:
            est = self._estimate_new(born)
            out = est if out is None else _concat_estimates(out, est)
        if out is None:
            out = _empty_estimate(J)
        return out

    def _end_at_pause(self) -> None:
        """A pause of the recorder (``max_gap_s``): no motion model bridges an unknown stretch of time, so
        every track ends here; a person found again after it takes their identity back by
        re-identification (position within ``pause_gate_m`` more, body proportions), else a new one.
        Without this, tracks predicted across snapshots far apart in time gathered other people's
        detections (a time-lapse's frames a minute apart: duplicated, mixed poses)."""
        for t in self.tracks:
            if t.mean is None:
                continue
            self.ended.append((t.id, t.born, t.last_seen))
            self.lost.append(
                _Lost(t.id, t.last_seen, self._pelvis(t.mean), t.velocity.copy(), t.bones, t.last_seen_s,
                      t.pauses_seen)
            )  # fmt: skip
        self.tracks = []

    def _phi(self, X: np.ndarray, rays: np.ndarray, asc: np.ndarray, Y: np.ndarray, maps) -> np.ndarray:
        """phi(c,l,s) (K,C,L,N) of eq. 5.8: from the confidence maps + PAFs of the cameras that have them
        (:func:`track.observation.map_limb_scores`, the limbs are then the maps' PAF limbs for every camera),
        else from the associated keypoints."""
        cfg = self.config
        limbs = self.limbs
        if maps is not None:
            limbs = next(m for m in maps if m is not None).limbs
        conf = obs.joint_scores(
            X, self.centers, rays, asc, self.focal, cfg.obs_sigma_m, cfg.obs_sigma_px, Y
        )  # (K,C,J,N)
        phi = obs.limb_scores(conf, limbs, 2)  # (K,C,L,N)
        if maps is not None:
            self.n_map_scores += 1
            for c, m in enumerate(maps):  # loop over cameras only; all samples at once inside
                if m is not None:
                    if not np.array_equal(m.limbs, limbs):
                        raise ValueError("every camera's maps must score the same limbs")
                    phi[:, c] = obs.map_limb_scores(X, self.P[c], m)
        return phi

    def _update_seen(
        self, X: np.ndarray, state: dict, u: np.ndarray, rays: np.ndarray, asc: np.ndarray, maps
    ):
        """:meth:`_update` for the tracks ``u`` with evidence (all of them without a copy): X (K,N,J,3) and
        the motion state with their samples resampled and refined (X in place), the refined joints' scores."""
        K, N = X.shape[:2]
        if len(u) == K:
            X, idx, score_u = self._update(X, rays, asc, maps)
            flat = idx + (np.arange(K) * N)[:, None]
        else:
            X[u], idx, score_u = self._update(X[u], rays[u], asc[u], maps)
            flat = np.arange(K * N).reshape(K, N)
            flat[u] = u[:, None] * N + idx
        return X, kernels.gather_state(state, flat.ravel()), score_u

    def _update(self, X: np.ndarray, rays: np.ndarray, asc: np.ndarray, maps=None):
        """Eq. 5.6–5.7, resampling per camera pair, joint refinement. X: (K,N,J,3) -> X', indices (K,N) and
        the refined joints' summed confidence (K,J,N) (None without refinement).

        Keypoint evidence: compiled kernels (:mod:`track.kernels`) fuse the weights' numpy chain (ray
        coordinates, joint and limb scores, eq. 5.7 per pair), the resampling, the gather and the
        refinement; with confidence maps the weights come from :meth:`_phi` (numpy)."""
        cfg = self.config
        K, N, J = X.shape[:3]
        if cfg.resample:
            if maps is None and self._phi_in_range:
                phi = kernels.pair_weights(
                    X,
                    self.centers,
                    rays,
                    asc,
                    focal=self.focal,
                    sigma_m=cfg.obs_sigma_m,
                    sigma_px=cfg.obs_sigma_px,
                    eps=cfg.eps,
                    limbs=self.limbs,
                    pairs=self.pairs,
                )  # (K,V,N): Phi(v,s) of eq. 5.7
            else:
                Y = obs.ray_coords(X, self.centers, rays)  # (K,J,3C,N)
                lpv = obs.log_phi_pairs(self._phi(X, rays, asc, Y, maps), self.pairs, cfg.eps)
                phi = np.exp(lpv - lpv.max(-1, keepdims=True), dtype=np.float64)
            V = len(self.pairs)
            idx = kernels.sus_indices(phi, obs.pair_sizes(N, V), self.rng.random(K * V))
        else:
            idx = np.broadcast_to(np.arange(N), (K, N))
        refine = cfg.refine and cfg.refine_candidates > 1
        R = cfg.refine_candidates - 1 if refine else 0
        noise = (
            standard_normals(self.rng, (K, J, 3, R, N)) if refine else np.zeros((K, J, 3, 0, N), np.float32)
        )
        X, score = kernels.refine_resampled(
            X,
            np.ascontiguousarray(idx),
            self.centers,
            rays,
            asc,
            self.focal,
            sigma_m=cfg.obs_sigma_m,
            sigma_px=cfg.obs_sigma_px,
            noise=noise,
            scales=obs.refine_scales(cfg.refine_candidates, cfg.refine_sigma_m)[1:],
            n_guided=cfg.refine_guided,
            lam=_GUIDED_LAM,
            refine=refine,
        )
        return X, idx, score if refine else None

    # ------------------------------------------------------------------ birth

    def _initialise(self, kp: np.ndarray, sc: np.ndarray, assigned: np.ndarray, frame: int) -> list[_Track]:
        cfg = self.config
        if self.reconstructor is None:
            return []
        C, D = kp.shape[:2]
        free = np.ones((C, D), bool)
        for c in range(C):
            a = assigned[c][assigned[c] >= 0] if assigned.size else []
            free[c, a] = False
        free &= (sc > 0).sum(-1) >= cfg.assoc_min_joints
        if (free.sum(1) > 0).sum() < cfg.init_min_views:
            return []
        scf = np.where(free[..., None], sc, 0.0)
        if not self._enough_views(scf):
            return []
        # the matching sees only the free detections: each camera's first, in their order (the others after
        # them are all NaN), and no more rows per camera than the most free detections of one camera
        rows = np.argsort(~free, axis=1, kind="stable")[:, : free.sum(1).max()]  # (C,P')
        kpf = np.where(free[..., None, None], kp, np.nan)
        kpf = np.take_along_axis(kpf, rows[..., None, None], 1)
        poses = self.reconstructor(kpf.astype(np.float64), np.take_along_axis(scf, rows[..., None], 1))
        if len(poses.xyz_m) == 0:
            return []
        good = (poses.n_views >= cfg.init_min_views) & np.isfinite(poses.xyz_m).all(-1)
        n_good = good.sum(1)
        order = np.argsort(-(n_good + poses.score.sum(1) * 1e-3))  # best candidate first
        born: list[_Track] = []
        live = [t for t in self.tracks if frame - t.last_seen == 0]
        coasting = [t for t in self.tracks if frame - t.last_seen > 0]
        # with no track at all (the first frame, the frame after a pause) the candidates are the frame's
        # people as the reconstructor separated them (its merge_dist_m joins one person seen twice): none
        # excludes another, so people closer than init_exclusion_m are not lost to each other
        near_born = bool(self.tracks)
        n_new = 0
        for m in order:
            if n_good[m] < cfg.init_min_joints:
                continue
            cand = np.where(good[m][:, None], poses.xyz_m[m], np.nan).astype(np.float32)
            if (
                self.birth is not None
            ):  # the learned generator g (sec. 5.2.3): sample 0 = its dropout-free fill
                samples = self.birth.sample(cand, cfg.n_samples, self.rng)
                if samples is None:
                    continue
                filled, missing = samples[0], ~np.isfinite(cand).all(-1)
            else:
                filled, missing = self._fill(cand)
                if filled is None:
                    continue
            pel = self._pelvis(filled)
            if any(
                np.linalg.norm(pel[:2] - self._pelvis(t.mean)[:2]) < cfg.init_exclusion_m
                for t in live + (born if near_born else [])
            ):
                continue
            if self.birth is None:
                samples = self._samples(filled, missing)
            bones = np.where(np.isfinite(self._bones(cand)), self._bones(filled), np.nan)
            # a coasting track of this person? re-anchor it (keeps the identity)
            t = self._match_coasting(coasting, pel, bones)
            if t is not None:
                coasting.remove(t)
                t.x, t.state, t.last_seen = samples, self.prior.init_state(samples), frame
                t.last_seen_s, t.pauses_seen = self.clock_s, self.pauses
                t.n_seen += 1
                t.mean = filled
                born.append(t)
                continue
            if cfg.max_people and len(self.tracks) + n_new >= cfg.max_people:
                continue
            n_new += 1
            tid = self._reidentify(pel, bones, frame)
            t = _Track(
                tid,
                samples,
                self.prior.init_state(samples),
                frame,
                frame,
                self.clock_s,
                self.pauses,
                mean=filled,
                bones=bones,
            )
            self.tracks.append(t)
            born.append(t)
        return born

    def _enough_views(self, scf: np.ndarray) -> bool:
        """Whether the free detections' scores ``scf`` (C,D,J) could give any candidate: it needs
        ``init_min_joints`` joints seen by ``init_min_views`` cameras, and a joint's views are at most the
        cameras with a free detection of it (or of its left/right twin, which a mirrored pose reads), so
        with fewer such joints the matching would find none (skipped: the same result)."""
        cfg = self.config
        cams = (scf > 0).any(1)  # (C,J)
        flip = self.reconstructor.flip if self.reconstructor is not None else None
        if flip is not None:
            cams = cams | cams[:, flip]
        return int((cams.sum(0) >= cfg.init_min_views).sum()) >= cfg.init_min_joints

    def _fill(self, cand: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """Fill joints the candidate lacks from the template aligned at the hips. cand: (J,3), NaN =
        missing."""
        missing = ~np.isfinite(cand).all(-1)
        if not missing.any():
            return cand, missing
        if self._tmpl is None:
            return None, missing
        ip, il, ir = (self.skeleton.index(n) for n in ("pelvis", "left_hip", "right_hip"))
        if missing[[il, ir]].any() and missing[ip]:
            return None, missing
        origin, theta = hip_frame(cand[None], self.skeleton)
        if missing[[il, ir]].any():  # no facing: use the shoulders, else the template's default
            sh = [self.skeleton.index("left_shoulder"), self.skeleton.index("right_shoulder")]
            d = cand[sh[1]] - cand[sh[0]]
            theta = np.array([np.arctan2(d[1], d[0]) if np.isfinite(d).all() else 0.0])
        tmpl = denormalize(self._tmpl[None], origin, theta)[0]
        return np.where(missing[:, None], tmpl, cand).astype(np.float32), missing

    def _samples(self, pose: np.ndarray, missing: np.ndarray) -> np.ndarray:
        cfg = self.config
        sig = np.where(missing, cfg.init_fill_sigma_m, cfg.init_sigma_m).astype(np.float32)
        noise = self.rng.normal(0.0, 1.0, (cfg.n_samples, len(pose), 3)).astype(np.float32) * sig[:, None]
        noise[0] = 0.0
        return pose[None] + noise

    def _bone_diff(self, a: np.ndarray | None, b: np.ndarray | None) -> float:
        if a is None or b is None:
            return 0.0
        ok = np.isfinite(a) & np.isfinite(b)
        return float(np.abs(a[ok] - b[ok]).mean()) if ok.sum() >= 3 else 0.0

    def _match_coasting(self, coasting: list[_Track], pel: np.ndarray, bones) -> _Track | None:
        cfg = self.config
        best, best_d = None, np.inf
        for t in coasting:
            gap = self.clock_s - t.last_seen_s
            pred = self._pelvis(t.mean)
            d = float(np.linalg.norm(pel[:2] - pred[:2]))
            if (
                d
                < cfg.reid_dist_m
                + cfg.reid_speed_mps * gap
                + cfg.pause_gate_m * (self.pauses - t.pauses_seen)
                and self._bone_diff(bones, t.bones) < cfg.reid_bone_tol_m
                and d < best_d
            ):
                best, best_d = t, d
        return best

    def _reidentify(self, pel: np.ndarray, bones, frame: int) -> int:
        """An ended identity whose predicted position and body proportions agree, else a new id."""
        cfg = self.config
        self.lost = [lt for lt in self.lost if self.clock_s - lt.end_s <= cfg.reid_max_gap_s + 1e-9]
        best, best_cost = None, np.inf
        for lt in self.lost:
            gap = self.clock_s - lt.end_s
            v = lt.velocity[:2]
            speed = float(np.linalg.norm(v))
            if speed > 2.0:
                v = v * (2.0 / speed)
            pred = lt.pelvis[:2] + v * min(gap, 1.0)
            d = float(np.linalg.norm(pel[:2] - pred))
            bd = self._bone_diff(bones, lt.bones)
            reach = cfg.reid_dist_m + cfg.reid_speed_mps * gap + cfg.pause_gate_m * (self.pauses - lt.pauses)
            if d < reach and bd < cfg.reid_bone_tol_m:
                cost = d + 10.0 * bd
                if cost < best_cost:
                    best, best_cost = lt, cost
        if best is not None:
            self.lost.remove(best)
            log.debug("re-identified track %d after %d frames", best.id, frame - best.end)
            return best.id
        tid = self.next_id
        self.next_id += 1
        return tid

    def _estimate_new(self, born: list[_Track]) -> FrameEstimate:
        J = self.skeleton.n_joints
        X = np.stack([t.x for t in born])
        mean, std = X.mean(1), np.sqrt(((X - X.mean(1, keepdims=True)) ** 2).sum(-1).mean(1) / 3.0)
        for t, m in zip(born, mean, strict=True):
            t.mean = m
        K = len(born)
        return FrameEstimate(
            np.array([t.id for t in born], np.int64),
            mean,
            std,
            np.full((K, J), 0.5, np.float32),
            np.full((K, J), 2, np.int64),
            np.full((K, J), OBSERVED, np.uint8),
            np.ones(K, bool),
        )


def _empty_estimate(J: int) -> FrameEstimate:
    return FrameEstimate(
        np.zeros(0, np.int64),
        np.zeros((0, J, 3), np.float32),
        np.zeros((0, J), np.float32),
        np.zeros((0, J), np.float32),
        np.zeros((0, J), np.int64),
        np.zeros((0, J), np.uint8),
        np.zeros(0, bool),
    )


def _concat_estimates(a: FrameEstimate, b: FrameEstimate) -> FrameEstimate:
    """Concatenate, a re-anchored track in b replacing its entry in a."""
    keep = ~np.isin(a.track_id, b.track_id)
    return FrameEstimate(
        *(np.concatenate([getattr(a, f.name)[keep], getattr(b, f.name)]) for f in fields(FrameEstimate))
    )


@dataclass
class TrackArrays:
    """Dense output of a sequence: T frames, K tracks (columns sorted by id)."""

    track_id: np.ndarray  # (K,)
    xyz_m: np.ndarray  # (T,K,J,3) NaN where unknown
    std_m: np.ndarray  # (T,K,J)
    confidence: np.ndarray  # (T,K,J)
    flags: np.ndarray  # (T,K,J) uint8
    n_views: np.ndarray  # (T,K,J)
    time_s: np.ndarray  # (T,) seconds spent in step() per frame


def check_times(frames: np.ndarray, t_ns: np.ndarray | None) -> None:
    """Timestamps ``t_ns`` (T,) must increase (all zeros = none: times from the frame numbers); the error
    names the first frame whose time does not follow the previous frame's."""
    T = len(frames)
    if t_ns is not None and T > 1 and np.any(t_ns) and not (np.diff(np.asarray(t_ns, np.int64)) > 0).all():
        bad = int(np.flatnonzero(np.diff(np.asarray(t_ns, np.int64)) <= 0)[0]) + 1
        raise ValueError(
            f"frame {int(frames[bad])}: its timestamp does not follow the previous frame's; "
            "t_ns must increase (all zeros = no timestamps: times from the frame numbers)"
        )


def warn_sparse_time(t_s: np.ndarray, cfg: ParticleConfig, fps: float) -> None:
    """Say so when the frames are snapshots too far apart to link (``sparse_time_warning``)."""
    warn = sparse_time_warning(
        pause_clock(t_s, cfg.max_gap_s, fps)[1], cfg.max_gap_s, min_evidence_frames(cfg, fps)
    )
    if warn:
        log.warning("particle tracker: %s", warn)


def track_sequence(
    tracker: ParticleTracker,
    kp: np.ndarray,
    sc: np.ndarray,
    frames: np.ndarray | None = None,
    progress: Progress | None = None,
    maps_at=None,
    t_ns: np.ndarray | None = None,
) -> TrackArrays:
    """Run the filter over a sequence. kp: (T,C,D,J,2) undistorted px (NaN = missing), sc: (T,C,D,J).
    ``maps_at(t)``: optional, the C :class:`track.observation.CameraMaps` (or None) of frame t. Frame
    times come from ``t_ns`` (T,), else from the frame numbers ``frames`` at the tracker's rate
    (:func:`track.greedy.frame_times_s`); smoothing never bridges a pause (``max_gap_s``).

    Applies the offline clean-up of the config: coasting frames after a track's last evidence are dropped
    (``trim_coast``) and tracks with less evidence than ``min_track_s`` are removed.
    """
    import time

    cfg = tracker.config
    T = len(kp)
    frames = np.arange(T) if frames is None else np.asarray(frames)
    if len(frames) != T or (t_ns is not None and len(t_ns) != T):
        raise ValueError(f"frames and t_ns must have one entry per frame ({T})")
    check_times(frames, t_ns)
    t_s = frame_times_s(frames, t_ns, tracker.fps)
    warn_sparse_time(t_s, cfg, tracker.fps)
    J = tracker.skeleton.n_joints
    per_frame: list[FrameEstimate] = []
    times = np.zeros(T)
    for t in range(T):
        t0 = time.perf_counter()
        per_frame.append(
            tracker.step(kp[t], sc[t], t, None if maps_at is None else maps_at(t), float(t_s[t]))
        )
        times[t] = time.perf_counter() - t0
        if progress is not None:
            progress("track", t + 1, T)
    raw = gather_estimates(per_frame, J)
    return finish_tracks(raw, t_s, cfg, tracker.fps, times=times)


@dataclass
class RawEstimates:
    """The filter's per-frame output on a dense (T,K) grid before the offline clean-up (``seen`` (T,K):
    the track had evidence; columns sorted by id)."""

    track_id: np.ndarray  # (K,)
    xyz_m: np.ndarray  # (T,K,J,3)
    std_m: np.ndarray  # (T,K,J)
    confidence: np.ndarray  # (T,K,J)
    flags: np.ndarray  # (T,K,J) uint8
    n_views: np.ndarray  # (T,K,J)
    seen: np.ndarray  # (T,K) bool


def gather_estimates(per_frame: list[FrameEstimate], J: int) -> RawEstimates:
    """The per-frame estimates of T frames on one grid of the ids they contain."""
    T = len(per_frame)
    ids = sorted({int(i) for e in per_frame for i in e.track_id})
    col = {tid: k for k, tid in enumerate(ids)}
    K = len(ids)
    xyz = np.full((T, K, J, 3), np.nan, np.float32)
    std = np.full((T, K, J), np.nan, np.float32)
    conf = np.zeros((T, K, J), np.float32)
    flags = np.zeros((T, K, J), np.uint8)
    nv = np.zeros((T, K, J), np.int16)
    seen = np.zeros((T, K), bool)
    for t, e in enumerate(per_frame):
        if len(e.track_id) == 0:
            continue
        ks = np.array([col[int(i)] for i in e.track_id])
        xyz[t, ks], std[t, ks], conf[t, ks], flags[t, ks], nv[t, ks] = (
            e.xyz_m,
            e.std_m,
            e.confidence,
            e.flags,
            e.n_views,
        )
        seen[t, ks] = e.evidence
    return RawEstimates(np.asarray(ids, np.int64), xyz, std, conf, flags, nv, seen)


def min_evidence_frames(cfg: ParticleConfig, fps: float) -> int:
    """``min_track_s`` in frames at ``fps``: a track with less evidence is dropped (:func:`finish_tracks`)."""
    return max(1, int(round(cfg.min_track_s * fps)))


def finish_tracks(
    raw: RawEstimates,
    t_s: np.ndarray,
    cfg: ParticleConfig,
    fps: float,
    times: np.ndarray | None = None,
    evidence_frames: np.ndarray | None = None,
    room_frames: np.ndarray | None = None,
) -> TrackArrays:
    """The offline clean-up of :func:`track_sequence` on the raw estimates of T frames at times ``t_s``
    (T,) (seconds, the session's clock): frames coasted across a pause are removed, then trailing coasting
    frames (``trim_coast``), then the smoothing (``smooth_sigma_s``), then tracks with less evidence than
    ``min_track_s`` (:func:`track.greedy.long_enough`: not where the recorder paused sooner).
    ``evidence_frames`` (K,) and ``room_frames`` (K,): each track's evidence frames over the whole session
    and the longest stretch without a pause among them, when ``raw`` is a window of it (default: from
    ``raw``). Each value depends only on the frames within
    ``end_after_s`` (on the tracks' clock) plus the smoothing radius of it, so a window with that margin
    gives its middle frames exactly as the whole session does (:mod:`track.stream`). Changes ``raw``'s
    arrays in place."""
    xyz, std, conf, flags = raw.xyz_m, raw.std_m, raw.confidence, raw.flags  # changed in place
    nv, seen, ids = raw.n_views, raw.seen, raw.track_id
    T, K = seen.shape
    # frames coasted after a pause of the recorder (no evidence since before it): the filter's guess across
    # an unknown stretch of time, never output (as the greedy tracker never fills across a pause)
    _, pauses = pause_clock(t_s, cfg.max_gap_s, fps)
    last_ev = np.maximum.accumulate(np.where(seen, np.arange(T)[:, None], -1), axis=0)  # (T,K)
    across = ~seen & (last_ev >= 0) & (pauses[:, None] != pauses[np.maximum(last_ev, 0)])
    xyz[across], std[across], conf[across], flags[across] = np.nan, np.nan, 0, 0
    if cfg.trim_coast:
        for k in range(K):  # drop every frame after the last evidence of each contiguous segment
            alive = np.isfinite(xyz[:, k]).all(-1).any(-1)
            t = 0
            while t < T:
                if not alive[t]:
                    t += 1
                    continue
                s = t
                while t < T and alive[t]:
                    t += 1
                ev = np.flatnonzero(seen[s:t, k])
                cut = s + (ev[-1] + 1 if len(ev) else 0)
                xyz[cut:t, k], std[cut:t, k], conf[cut:t, k], flags[cut:t, k] = np.nan, np.nan, 0, 0
    sigma_s = cfg.smooth_sigma_s or 0.0
    if sigma_s > 0:
        known = np.isfinite(xyz).all(-1)
        xyz = smooth_segments(xyz, t_s, sigma_s, cfg.max_gap_s, fps).astype(np.float32)
        flags = np.where(known, flags | SMOOTHED, flags).astype(np.uint8)
    n_ev = seen.sum(0) if evidence_frames is None else np.asarray(evidence_frames)
    if room_frames is None:
        room_frames = np.where(seen, segment_frames(pauses)[:, None], 0).max(0, initial=0)
    keep = long_enough(n_ev, room_frames, min_evidence_frames(cfg, fps))
    return TrackArrays(
        ids[keep],
        xyz[:, keep],
        std[:, keep],
        conf[:, keep],
        flags[:, keep],
        nv[:, keep],
        np.zeros(T) if times is None else times,
    )
