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
   triangulated with the chapter-4 engine (:class:`roomcap.triangulate.reconstruct.FrameReconstructor`);
   each candidate (best first) either re-anchors a coasting track, revives a lost identity
   (position, velocity, body proportions agree) or starts a new track. Samples are drawn
   around the candidate; joints it lacks are filled from a mocap template with a larger spread
   (``birth='gaussian'``, the default) or all N samples come from the seed's dropout network g
   (``birth='learned'``, :mod:`roomcap.track.birth`: run N times with dropout on, it fills the missing
   joints).

A live source that jumps in time (a looping file camera, a restarted camera, a clock reset) is not a frame
time that goes back: the caller starts a new segment (:meth:`ParticleTracker.new_segment`,
:mod:`roomcap.track.particle_jumps`) and the people found after it keep their ids where they are the same.

No Python loop runs over samples; loops run over tracks (gathers, refinement blocks of joints),
cameras (association) and new candidates (initialisation) only.

With a bottom-up model's confidence maps + part affinity fields for a frame (``step(..., maps=)``, the
stage reads them from the detection files), the resampling weights of eq. 5.6–5.7 use eq. 5.8 on the maps
of those cameras (:func:`roomcap.track.observation.map_limb_scores`, all samples at once); association, joint
refinement and the output weights still use the associated keypoints.

Not implemented from the seed: the confidence-subtraction network of sec. 5.2.3.
"""

from __future__ import annotations

import json
import logging

import numpy as np

from roomcap.keypoints.skeletons import CANONICAL, Skeleton
from roomcap.track import kernels
from roomcap.track import observation as obs
from roomcap.track.greedy import (
    nominal_dt,
)
from roomcap.track.normalize import hip_frame
from roomcap.track.particle_births import SNAPSHOT_MIN_JOINTS, Births
from roomcap.track.particle_config import ParticleConfig, make_prior
from roomcap.track.particle_jumps import Jumps
from roomcap.track.particle_types import FrameEstimate, LostTrack, Track, concat_estimates, empty_estimate
from roomcap.track.priors import (
    TEMPLATE_BODY19_M,
    MotionPrior,
    concat_states,
    standard_normals,
)
from roomcap.track.split import Split
from roomcap.track.trackfile import OBSERVED, PREDICTED
from roomcap.triangulate.matching import MatchConfig
from roomcap.triangulate.reconstruct import FrameReconstructor, TriangulateConfig

log = logging.getLogger(__name__)

_GUIDED_LAM = 0.01  # the guided targets' pull towards the sample's own joint (observation.guided_targets)


STATE_SCHEMA = "particle_state/1"


class ParticleTracker(Births, Jumps):
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
        self.split = Split(cfg.threads)  # parts of the batch computed at once
        self.prior = prior if prior is not None else make_prior(cfg, fps, skeleton)
        self.tracks: list[Track] = []
        self.n_map_scores = 0  # update steps whose weights came from confidence maps + PAFs
        self._batch: tuple | None = None  # the last step's (X, state, the tracks' views of them)
        self.lost: list[LostTrack] = []
        self.ended: list[tuple[int, int, int]] = []  # (id, born, last_seen) of ended track segments
        self.next_id = 0
        self.end_after = max(1, int(round(cfg.end_after_s * fps)))
        self.t_s: float | None = None  # time of the last frame stepped (s)
        self.clock_s = 0.0  # the tracks' clock: time with every pause shortened to one frame
        self.pauses = 0  # pauses of the recorder so far
        self.after_pause = False  # whether the frame being stepped follows a pause
        self.dt_s = 1.0 / self.fps  # the last step on the tracks' clock
        self._init_jumps()  # a live source that jumps back in time: new segments (particle_jumps)
        self.reconstructor = None
        if C >= 2:
            tcfg = TriangulateConfig(
                match=MatchConfig(theta_px=cfg.init_theta_px, min_score=cfg.min_score),
                min_joints_3d=min(cfg.init_min_joints, SNAPSHOT_MIN_JOINTS),  # more after no pause
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
            from roomcap.track.birth import BirthGenerator  # lazy: loads torch

            self.birth = BirthGenerator.load(
                cfg.birth_checkpoint, skeleton, sigma_obs_m=cfg.init_sigma_m, sigma_fill_m=cfg.init_sigma_m
            )

    # ------------------------------------------------------------------ state (resume)

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Everything the next :meth:`step` needs, as plain arrays (npz, no pickle): the tracks (samples,
        motion state, bookkeeping), the lost identities, the clock and the random generator's state.
        :meth:`load_state_arrays` on a tracker built with the same rig and config continues bit for bit
        (a streamed run resumes from it, :mod:`roomcap.track.particle_chunked`)."""
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
                    Track(
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
                LostTrack(
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
        sequence of C :class:`roomcap.track.observation.CameraMaps` or None per camera (a bottom-up model's
        confidence maps + PAFs); with any, the update weights use eq. 5.8 on the maps for those cameras
        (keypoints for the others)."""
        with self.split.blas_single():
            return self._step(kp, sc, frame, maps, t_s)

    def _step(self, kp, sc, frame: int, maps, t_s: float | None) -> FrameEstimate:
        cfg = self.config
        kp, sc = self._check_frame(kp, sc)
        pauses_before = self.pauses
        n_pred = self._advance_clock(frame, t_s)
        now = self.clock_s
        # the frame after a pause of the recorder (a time-lapse's every snapshot): births need no more
        # joints than the per-frame triangulation (particle_births.SNAPSHOT_MIN_JOINTS)
        self.after_pause = self.pauses > pauses_before
        if self.after_pause:
            self._end_at_pause()
        if self.jump_refs:
            self._expire_refs()
        maps = self._checked_maps(maps)
        C, D, J = kp.shape[:3]
        K, N = len(self.tracks), cfg.n_samples
        out = None
        assigned = np.full((C, 0), -1, np.int64)
        if K:
            X, state = self._batch_of_tracks()  # (K,N,J,3), the motion state of the K*N samples
            # 1. prediction (eq. 5.1), all tracks and samples in one batch; one step per frame interval
            Xf = X.reshape(K * N, J, 3)
            for _ in range(n_pred):  # > 1 only over dropped frames
                Xf, state = self.prior.predict(Xf, state, self.rng, split=self.split)
            X = Xf.reshape(K, N, J, 3)
            # tracks whose last evidence precedes a pause of the recorder: wider gates, fresh motion state
            paused = np.asarray([self.pauses - t.pauses_seen for t in self.tracks], np.float64)
            # 2. association on the predicted means
            assigned, akp, asc = self._associate(X, kp, sc, paused)
            ev_k = (assigned >= 0).any(0)
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
            mean, std = self._output_pose(X, rays, asc, score_u, u, ev_k)
            n_views = (asc > 0).sum(1)  # (K,J)
            conf_out = np.clip(asc.sum(1) / np.maximum(n_views, 1) * np.minimum(n_views, 2) / 2.0, 0, 1)
            flags = np.where(n_views > 0, OBSERVED, PREDICTED).astype(np.uint8)
            self._remember(X, state, mean, n_views, paused, ev_k, frame, now)
            out = FrameEstimate(
                np.array([t.id for t in self.tracks], np.int64), mean, std, conf_out, n_views, flags, ev_k
            )
            # 5. termination
            self._terminate(now)
        # 6. initialisation from the detections no track explains
        born = self._initialise(kp, sc, assigned, frame)
        if born:
            est = self._estimate_new(born)
            out = est if out is None else concat_estimates(out, est)
        if out is None:
            out = empty_estimate(J)
        self._note_places(out)  # where each track begins its segment: a loop of the source returns there
        return out

    def _checked_maps(self, maps):
        """The frame's confidence maps as a list of one entry per camera, or None when there are none."""
        if maps is None:
            return None
        maps = list(maps)
        if len(maps) != len(self.P):
            raise ValueError(
                f"maps must have one entry (CameraMaps or None) per camera ({len(self.P)}), got {len(maps)}"
            )
        return None if all(m is None for m in maps) else maps

    def _associate(self, X: np.ndarray, kp: np.ndarray, sc: np.ndarray, paused: np.ndarray):
        """Each camera's detection of each track (on the predicted means; gates wider after a pause):
        ``(assigned (C,K), keypoints (K,C,J,2), scores (K,C,J))``, unassigned NaN / 0."""
        cfg = self.config
        C = kp.shape[0]
        muv, mz = obs.project(self.P, X.mean(1))  # (C,K,J,2), (C,K,J)
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
        return assigned, akp, asc

    def _output_pose(self, X, rays, asc, score_u, u, ev_k) -> tuple[np.ndarray, np.ndarray]:
        """Sec. 5.2.4: the samples' mean and spread weighted over all cameras; by default with the
        refinement's scores of the kept joints (summed over cameras, product over joints)."""
        cfg = self.config
        K, N, J = X.shape[:3]
        if cfg.exact_output_weights or score_u is None:
            conf = obs.joint_scores(
                X, self.centers, rays, asc, self.focal, cfg.obs_sigma_m, cfg.obs_sigma_px
            )  # (K,C,J,N)
            lp = obs.log_phi_all(obs.limb_scores(conf, self.limbs, 2), cfg.eps)
            return obs.weighted_stats(X, lp)
        score = np.zeros((K, J, N), np.float32)
        score[u] = score_u
        parts = self.split.map(
            lambda lo, hi: kernels.output_stats(X[lo:hi], score[lo:hi], ev_k[lo:hi], cfg.eps), K
        )
        return _joined(parts)

    def _remember(self, X, state, mean, n_views, paused, ev_k, frame: int, now: float) -> None:
        """The tracks keep their samples, motion state and estimate; their pelvis velocity, and, where seen,
        the time of their last evidence and their bone lengths (a running mean)."""
        K, N = X.shape[:2]
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

    def _terminate(self, now: float) -> None:
        """Tracks without evidence for ``end_after_s`` (on the clock, a whole number of frames at the
        nominal rate) end; they are kept for re-identification."""
        keep = []
        for t in self.tracks:
            if now - t.last_seen_s >= (self.end_after - 0.5) / self.fps:
                self.ended.append((t.id, t.born, t.last_seen))
                self.lost.append(
                    LostTrack(
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
                LostTrack(t.id, t.last_seen, self._pelvis(t.mean), t.velocity.copy(), t.bones, t.last_seen_s,
                      t.pauses_seen)
            )  # fmt: skip
        self.tracks = []

    def _phi(self, X: np.ndarray, rays: np.ndarray, asc: np.ndarray, Y: np.ndarray, maps) -> np.ndarray:
        """phi(c,l,s) (K,C,L,N) of eq. 5.8: from the confidence maps + PAFs of the cameras that have them
        (:func:`roomcap.track.observation.map_limb_scores`, the limbs are then the maps' PAF limbs for every
        camera), else from the associated keypoints."""
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
        if len(u) == K:  # each part of the tracks gathers its own rows of the state
            X, _, score_u, state = self._update(X, rays, asc, maps, state)
            return X, state, score_u
        X[u], idx, score_u, _ = self._update(X[u], rays[u], asc[u], maps)
        flat = np.arange(K * N).reshape(K, N)
        flat[u] = u[:, None] * N + idx
        return X, kernels.gather_state(state, flat.ravel()), score_u

    def _update(self, X: np.ndarray, rays: np.ndarray, asc: np.ndarray, maps=None, state=None):
        """Eq. 5.6–5.7, resampling per camera pair, joint refinement. X: (K,N,J,3) -> X', indices (K,N),
        the refined joints' summed confidence (K,J,N) (None without refinement) and, given the K tracks'
        motion ``state``, its resampled rows (else None).

        Keypoint evidence: compiled kernels (:mod:`roomcap.track.kernels`) fuse the weights' numpy chain (ray
        coordinates, joint and limb scores, eq. 5.7 per pair), the resampling, the gather and the
        refinement, over parts of the tracks at once (:attr:`split`); with confidence maps the weights come
        from :meth:`_phi` (numpy)."""
        cfg = self.config
        K, N, J = X.shape[:3]
        V = len(self.pairs)
        phi = None  # the weights' numpy path (confidence maps, or eq. 5.7 out of float64's range)
        if cfg.resample and not (maps is None and self._phi_in_range):
            Y = obs.ray_coords(X, self.centers, rays)  # (K,J,3C,N)
            lpv = obs.log_phi_pairs(self._phi(X, rays, asc, Y, maps), self.pairs, cfg.eps)
            phi = np.exp(lpv - lpv.max(-1, keepdims=True), dtype=np.float64)
        # the random draws for all tracks first (as one pass would draw them), then the parts
        u = self.rng.random(K * V) if cfg.resample else np.zeros(0)
        refine = cfg.refine and cfg.refine_candidates > 1
        R = cfg.refine_candidates - 1 if refine else 0
        noise = (
            standard_normals(self.rng, (K, J, 3, R, N)) if refine else np.zeros((K, J, 3, 0, N), np.float32)
        )
        counts = obs.pair_sizes(N, V)

        def tracks(lo: int, hi: int):
            if not cfg.resample:
                idx = np.broadcast_to(np.arange(N), (hi - lo, N))
            else:
                phi_p = (
                    kernels.pair_weights(
                        X[lo:hi],
                        self.centers,
                        rays[lo:hi],
                        asc[lo:hi],
                        focal=self.focal,
                        sigma_m=cfg.obs_sigma_m,
                        sigma_px=cfg.obs_sigma_px,
                        eps=cfg.eps,
                        limbs=self.limbs,
                        pairs=self.pairs,
                    )  # (k,V,N): Phi(v,s) of eq. 5.7
                    if phi is None
                    else phi[lo:hi]
                )
                idx = kernels.sus_indices(phi_p, counts, u[lo * V : hi * V])
            Xp, score = kernels.refine_resampled(
                X[lo:hi],
                np.ascontiguousarray(idx),
                self.centers,
                rays[lo:hi],
                asc[lo:hi],
                self.focal,
                sigma_m=cfg.obs_sigma_m,
                sigma_px=cfg.obs_sigma_px,
                noise=noise[lo:hi],
                scales=obs.refine_scales(cfg.refine_candidates, cfg.refine_sigma_m)[1:],
                n_guided=cfg.refine_guided,
                lam=_GUIDED_LAM,
                refine=refine,
            )
            if state is None:
                return Xp, idx, score
            rows = (idx + (np.arange(lo, hi) * N)[:, None]).ravel()
            return Xp, idx, score, *kernels.gather_state(state, rows).values()

        X, idx, score, *columns = _joined(self.split.map(tracks, K))
        resampled = dict(zip(state, columns, strict=True)) if state is not None else None
        return X, idx, score if refine else None, resampled

    # ------------------------------------------------------------------ birth


def _joined(parts: list[tuple]) -> tuple:
    """The parts' results (tuples of arrays over tracks) joined along the tracks."""
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate(a) for a in zip(*parts, strict=True))
