"""The particle tracker's initialisation step (sec. 5.2.3): the detections no track explains are matched
and triangulated; each candidate re-anchors a coasting track, revives a lost identity or starts a track.
:class:`Births` is the part of :class:`roomcap.track.particle.ParticleTracker` that does it."""

from __future__ import annotations

import logging

import numpy as np

from roomcap.track.normalize import denormalize, hip_frame
from roomcap.track.particle_types import FrameEstimate, Track
from roomcap.track.trackfile import OBSERVED

log = logging.getLogger(__name__)

# Births in the frame after a pause of the recorder need no more triangulated joints than the per-frame
# triangulation keeps (TriangulateConfig.min_joints_3d): in a video a person seen partly is born a few
# frames later, when better seen, but a snapshot has no later frame (a time-lapse, a motion-triggered
# recording), and a well-supported per-frame pose must not be lost for it.
SNAPSHOT_MIN_JOINTS = 5


class Births:
    """The births of :class:`roomcap.track.particle.ParticleTracker` (its ``config``, ``tracks``, ``lost``,
    ``reconstructor``, ``prior`` and random state)."""

    def _free_poses(self, kp: np.ndarray, sc: np.ndarray, assigned: np.ndarray):
        """The 3D poses triangulated from the detections no track explains (None when they cannot give
        a candidate: too few cameras with free detections)."""
        cfg = self.config
        if self.reconstructor is None:
            return None
        C, D = kp.shape[:2]
        free = np.ones((C, D), bool)
        for c in range(C):
            a = assigned[c][assigned[c] >= 0] if assigned.size else []
            free[c, a] = False
        free &= (sc > 0).sum(-1) >= cfg.assoc_min_joints
        if (free.sum(1) > 0).sum() < cfg.init_min_views:
            return None
        scf = np.where(free[..., None], sc, 0.0)
        if not self._enough_views(scf):
            return None
        # the matching sees only the free detections: each camera's first, in their order (the others after
        # them are all NaN), and no more rows per camera than the most free detections of one camera
        rows = np.argsort(~free, axis=1, kind="stable")[:, : free.sum(1).max()]  # (C,P')
        kpf = np.where(free[..., None, None], kp, np.nan)
        kpf = np.take_along_axis(kpf, rows[..., None, None], 1)
        poses = self.reconstructor(kpf.astype(np.float64), np.take_along_axis(scf, rows[..., None], 1))
        return poses if len(poses.xyz_m) else None

    def _initialise(self, kp: np.ndarray, sc: np.ndarray, assigned: np.ndarray, frame: int) -> list[Track]:
        cfg = self.config
        poses = self._free_poses(kp, sc, assigned)
        if poses is None:
            return []
        good = (poses.n_views >= cfg.init_min_views) & np.isfinite(poses.xyz_m).all(-1)
        n_good = good.sum(1)
        order = np.argsort(-(n_good + poses.score.sum(1) * 1e-3))  # best candidate first
        born: list[Track] = []
        live = [t for t in self.tracks if frame - t.last_seen == 0]
        coasting = [t for t in self.tracks if frame - t.last_seen > 0]
        # with no track at all (the first frame, the frame after a pause) the candidates are the frame's
        # people as the reconstructor separated them (its merge_dist_m joins one person seen twice): none
        # excludes another, so people closer than init_exclusion_m are not lost to each other
        near_born = bool(self.tracks)
        n_new = 0
        min_joints = self._birth_min_joints()
        # after a jump of the clock the people born are matched to those alive before it all at once
        # (particle_jumps): their ids are given after the loop
        carry = bool(getattr(self, "jump_refs", None))
        fresh: list[Track] = []
        for m in order:
            if n_good[m] < min_joints:
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
            tid = -1 if carry else self._reidentify(pel, bones, frame)
            t = Track(
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
            fresh.append(t)
        if carry:
            self._carry_over(fresh, frame)
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
        return int((cams.sum(0) >= cfg.init_min_views).sum()) >= self._birth_min_joints()

    def _birth_min_joints(self) -> int:
        """``init_min_joints``, or in the frame after a pause of the recorder at most
        :data:`SNAPSHOT_MIN_JOINTS`."""
        n = self.config.init_min_joints
        return min(n, SNAPSHOT_MIN_JOINTS) if getattr(self, "after_pause", False) else n

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
            # a video starts the person when the hips show; a snapshot (after a pause) has no later frame
            return (
                self._fill_by_fit(cand, missing) if getattr(self, "after_pause", False) else (None, missing)
            )
        origin, theta = hip_frame(cand[None], self.skeleton)
        if missing[[il, ir]].any():  # no facing: use the shoulders, else the template's default
            sh = [self.skeleton.index("left_shoulder"), self.skeleton.index("right_shoulder")]
            d = cand[sh[1]] - cand[sh[0]]
            theta = np.array([np.arctan2(d[1], d[0]) if np.isfinite(d).all() else 0.0])
        tmpl = denormalize(self._tmpl[None], origin, theta)[0]
        return np.where(missing[:, None], tmpl, cand).astype(np.float32), missing

    def _fill_by_fit(self, cand: np.ndarray, missing: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """:meth:`_fill` for a candidate without hips (seen from the waist up, or one side of it): the
        template turned to the facing of the first left/right pair it has (shoulders, hips, ears, eyes)
        and moved onto its joints (the least-squares shift); None without such a pair."""
        theta = None
        for a, b in (
            ("left_shoulder", "right_shoulder"),
            ("left_hip", "right_hip"),
            ("left_ear", "right_ear"),
            ("left_eye", "right_eye"),
        ):
            ia, ib = self.skeleton.index(a), self.skeleton.index(b)
            if not (missing[ia] or missing[ib]):
                d = cand[ib] - cand[ia]
                theta = np.array([np.arctan2(d[1], d[0])])
                break
        if theta is None:
            return None, missing
        tmpl = denormalize(self._tmpl[None], np.zeros((1, 3), np.float32), theta)[0]
        tmpl = tmpl + (cand[~missing] - tmpl[~missing]).mean(0)
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

    def _match_coasting(self, coasting: list[Track], pel: np.ndarray, bones) -> Track | None:
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

    def _estimate_new(self, born: list[Track]) -> FrameEstimate:
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
