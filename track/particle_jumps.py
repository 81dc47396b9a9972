"""A live source that jumps back in time (a looping file camera, a camera that restarts, a clock reset): the
particle tracker starts a new segment of its clock and carries identities over by re-identification.

:class:`Jumps` is the part of :class:`roomcap.track.particle.ParticleTracker` that does it.
:meth:`Jumps.new_segment` is called by the caller that sees the jump (the live track stage,
:mod:`roomcap.pipeline.live`) before the first frame after it: every track ends there (no motion model bridges
a jump of the clock) and is kept as a *reference* of the person: where they stood just before the jump and
where their segment began (a loop returns there), their bone lengths and the appearance of their pose
(the pose in its own hip frame, eq. 5.2); so is each identity lost shortly before it (its last place and
where its segment began). The people born after the jump are matched to the references in
one assignment per frame (Hungarian, :func:`scipy.optimize.linear_sum_assignment`, on a cost of place, bone
lengths and pose, gated on place and bone lengths), so the same person keeps the same id across the jump;
a person matched to no reference takes an ended identity (the usual re-identification) or a new id.
References are kept for ``JUMP_KEEP_S`` (60 s, at least ``reid_max_gap_s``) on the tracks' clock.

The batch tracker never jumps: its frame times must increase (:meth:`ParticleTracker.step` says so).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from roomcap.track.normalize import hip_frame, normalize
from roomcap.track.particle_types import FrameEstimate, Track

log = logging.getLogger(__name__)

# The assignment's gates and scales (our choice; no seed covers a clock that jumps). A person may be anywhere
# within JUMP_PLACE_GATE_M of where they were seen (on the floor) and their mean bone length must agree within
# JUMP_BONE_GATE_M (the live estimates' running mean spreads more than a batch's, hence wider than
# reid_bone_tol_m); the pose's appearance only ranks candidates within the gates.
JUMP_PLACE_GATE_M = 1.5
JUMP_BONE_GATE_M = 0.08
JUMP_POSE_SCALE_M = 0.3  # mean joint distance of two poses in their hip frames at which its cost is 1
JUMP_POSE_WEIGHT = 0.5
# how long (on the tracks' clock) a person is kept for the assignment after their last evidence: across a jump
# time says little (a looping source shows the same people again each loop, one may be missed for a few
# loops), so longer than the usual reid_max_gap_s; the gates keep a newcomer from taking an old id
JUMP_KEEP_S = 60.0


@dataclass
class JumpRef:
    """A person alive just before a jump of the clock, kept to be found again after it."""

    id: int
    places: np.ndarray  # (M,2) floor positions (m): just before the jump, where their segment began
    bones: np.ndarray | None  # (L,) mean bone lengths
    pose: np.ndarray | None  # (J,3) the last pose in its hip frame (eq. 5.2)
    clock_s: float  # the tracks' clock at the jump


@dataclass
class JumpRecord:
    """One jump: the frame after it, the time before it (s, the frame times the caller gave), the ids
    carried over (matched to a reference) and the new ones given to people found after it."""

    frame: int
    t_before_s: float | None
    carried: list[int] = field(default_factory=list)
    new: list[int] = field(default_factory=list)


class Jumps:
    """New segments and carried-over identities of :class:`roomcap.track.particle.ParticleTracker` (its
    ``tracks``, ``config``, clock and births)."""

    jump_refs: list[JumpRef]
    jumps: list[JumpRecord]
    _seg_first: dict[int, np.ndarray]

    def _init_jumps(self) -> None:
        self.jump_refs = []
        self.jumps = []
        self._seg_first = {}  # track id -> floor position of its first estimate in this segment

    def new_segment(self, frame: int) -> JumpRecord:
        """The clock jumps before ``frame`` (its time goes back, or the source restarted): the next
        :meth:`step` starts the clock again from its own time; every track ends, kept as a reference for
        re-identification (see the module doc). Returns the jump's record (filled as people are found)."""
        refs = []
        for t in self.tracks:
            if t.mean is None:
                continue
            pel = self._pelvis(t.mean)
            places = [pel[:2]]
            if t.id in self._seg_first:
                places.append(self._seg_first[t.id])
            origin, theta = hip_frame(t.mean[None], self.skeleton)
            pose = normalize(t.mean[None], origin, theta)[0]
            refs.append(JumpRef(t.id, np.asarray(places, np.float32), t.bones, pose, self.clock_s))
            self.ended.append((t.id, t.born, t.last_seen))
        # the identities lost shortly before the jump too (a person missed in the last frames): their last
        # place and where their segment began; they leave the usual re-identification for the assignment
        for lt in self.lost:
            places = [lt.pelvis[:2]] + ([self._seg_first[lt.id]] if lt.id in self._seg_first else [])
            refs.append(JumpRef(lt.id, np.asarray(places, np.float32), lt.bones, None, lt.end_s))
        self.lost = []
        self.tracks = []
        self._batch = None
        self.jump_refs = [r for r in self.jump_refs if r.id not in {x.id for x in refs}] + refs
        self._seg_first = {}
        rec = JumpRecord(int(frame), self.t_s)
        self.jumps.append(rec)
        # the clock starts again from the next frame's time; the tracks' clock (termination,
        # re-identification) goes on, one frame later, and counts the jump as a pause (unknown motion)
        self.t_s = None
        self.clock_s += 1.0 / self.fps
        self.pauses += 1
        log.info("tracks: the clock jumped before frame %d; %d identities kept for re-identification", frame,
                 len(refs))  # fmt: skip
        return rec

    def _note_places(self, est: FrameEstimate) -> None:
        """Where each track was first seen in this segment (a loop of the source returns there)."""
        for k, tid in enumerate(np.asarray(est.track_id).tolist()):
            if tid not in self._seg_first and np.isfinite(est.xyz_m[k]).all(-1).any():
                pel = self._pelvis(np.asarray(est.xyz_m[k], np.float32))
                if np.isfinite(pel).all():
                    self._seg_first[tid] = pel[:2].astype(np.float32)

    def _expire_refs(self) -> None:
        gap = max(self.config.reid_max_gap_s, JUMP_KEEP_S)
        self.jump_refs = [r for r in self.jump_refs if self.clock_s - r.clock_s <= gap + 1e-9]

    def _carry_over(self, new: list[Track], frame: int) -> None:
        """The ids of the tracks ``new`` born in this frame (id -1 until here): one assignment of them to the
        references of the people alive before the last jumps (cost of place, bone lengths and pose, gated),
        the others re-identified as usual or new."""
        refs = self.jump_refs
        matched: dict[int, JumpRef] = {}
        if refs and new:
            cost = np.full((len(new), len(refs)), np.inf)
            for i, t in enumerate(new):
                pel = self._pelvis(t.mean)[:2]
                origin, theta = hip_frame(t.mean[None], self.skeleton)
                pose = normalize(t.mean[None], origin, theta)[0]
                for j, r in enumerate(refs):
                    d_place = float(np.linalg.norm(r.places - pel, axis=1).min())
                    d_bone = self._bone_diff(t.bones, r.bones)
                    if d_place > JUMP_PLACE_GATE_M or d_bone > JUMP_BONE_GATE_M:
                        continue
                    d_pose = 1.0
                    if r.pose is not None:
                        dj = np.linalg.norm(pose - r.pose, axis=-1)
                        if np.isfinite(dj).sum() >= 3:
                            d_pose = min(float(np.nanmean(dj)) / JUMP_POSE_SCALE_M, 1.0)
                    cost[i, j] = (
                        d_place / JUMP_PLACE_GATE_M + d_bone / JUMP_BONE_GATE_M + JUMP_POSE_WEIGHT * d_pose
                    )
            big = 1e6
            rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, big))
            for i, j in zip(rows, cols, strict=True):
                if np.isfinite(cost[i, j]):
                    matched[i] = refs[j]
        rec = self.jumps[-1] if self.jumps else None
        for i, t in enumerate(new):
            if i in matched:
                t.id = matched[i].id
                self.jump_refs.remove(matched[i])
                if rec is not None:
                    rec.carried.append(t.id)
                log.debug("re-identified track %d across the jump before frame %d", t.id, frame)
            else:
                t.id = self._reidentify(self._pelvis(t.mean), t.bones, frame)
                if rec is not None:
                    rec.new.append(t.id)
