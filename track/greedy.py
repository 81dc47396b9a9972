"""The chapter-4 tracker (seed sec. 4.2.2): greedy bipartite matching in time, gap filling, smoothing.

Each frame's 3D poses are matched to the tracks alive at the previous frames by the Hungarian
method; the cost is the mean Euclidean distance over the joints both poses have, or, when they
share none, the distance of their mean joints projected on the ground plane (z up). A match
below tau (200 mm) continues the track; every other pose starts a new one. A track that was not
matched for ``max_gap_s`` seconds ends; the allowed distance grows with the time since the track was
last seen (``max_speed_m_s``), so a briefly lost person is picked up again. Missing joints inside a
track are filled by linear interpolation in time (gaps up to ``max_gap_s``) and every joint
trajectory is smoothed by a Gaussian kernel of ``sigma_s`` seconds (default: sec. 4.3.4's sigma =
2 frames at the frame rate), NaN-aware (normalised convolution).

Every duration is on the clock: the frames' times come from ``t_ns`` (from
``frame_index / fps`` where the timestamps are missing or not increasing), so dropped frames,
jittered timestamps and pauses of the recorder count as the time they last. Nothing is interpolated
or smoothed across a gap between two frames longer than ``max_gap_s``, and the allowed distance
never grows past the one of a ``max_gap_s`` gap. On frames at a regular rate the results equal a
frame-count computation at that rate.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from roomcap.core.config import config_from_dict
from roomcap.core.timebase import gap_statistics
from roomcap.track.trackfile import INTERPOLATED, OBSERVED, PREDICTED, SMOOTHED, TrackFile
from roomcap.triangulate.reconstruct import flip_index

log = logging.getLogger(__name__)

SEED_SIGMA_FRAMES = 2.0  # sec. 4.3.4: Gaussian smoothing of sigma = 2 frames


@dataclass(frozen=True)
class TrackerConfig:
    """tau_m: match threshold (sec. 4.2.2: 200 mm); max_gap_s: seconds a track may be unseen, the
    longest gap filled and the longest gap between frames that smoothing bridges; max_speed_m_s: extra
    allowed distance per unseen second; sigma_s: Gaussian smoothing in seconds (0 = off; default the
    seed's 2 frames at the session's frame rate, a filter defined on samples);
    min_track_frames: shorter tracks are dropped; min_joints: poses with fewer joints are ignored;
    constant_velocity: compare a frame's poses with each track's last pose moved by the track's
    mean-joint velocity (False = the seed's last pose); occlusion_fill_s: longer gaps of a joint (up to
    this many seconds, 0 = off) are filled kinematically: the joint keeps its offset from its parent
    joint, interpolated between the frames around the gap (held at the track's ends); flagged
    PREDICTED, std = the parent's + 5 cm; fix_mirrored: a pose whose left/right-swapped version fits
    the track better joins swapped; stitch: after the frame-by-frame pass, a track that starts while
    another has just ended (within ``max_gap_s``) continues it when one of its poses in that window is
    within the limit the pass itself would have allowed the lost track (``stitch_tracks``);
    pause_gate_m: a pause of the recorder (two consecutive frames more than ``max_gap_s`` apart) counts
    as one frame for the tracks, which may continue across it by this much more distance (how far a
    person may have moved while nothing was recorded); nothing is filled or smoothed across it.

    ``max_gap``, ``sigma`` and ``occlusion_fill`` are the same durations in frames, as earlier
    versions took them; given, they are converted at the session's frame rate (:meth:`at_fps`)."""

    tau_m: float = 0.2
    max_gap_s: float = 0.4  # 10 frames at 25 Hz
    max_speed_m_s: float = 1.5
    sigma_s: float | None = None  # None: sec. 4.3.4's 2 frames, at the session's frame rate
    min_track_frames: int = 5
    min_joints: int = 5
    constant_velocity: bool = True
    occlusion_fill_s: float = 2.0  # 50 frames at 25 Hz
    fix_mirrored: bool = True
    stitch: bool = True
    pause_gate_m: float = 0.5
    max_gap: int | None = None
    sigma: float | None = None
    occlusion_fill: int | None = None

    def __post_init__(self) -> None:
        if self.tau_m <= 0 or self.max_gap_s < 0 or (self.sigma_s or 0) < 0 or self.occlusion_fill_s < 0:
            raise ValueError(
                "TrackerConfig: tau_m must be positive, max_gap_s, sigma_s and occlusion_fill_s non-negative."
            )
        if any(v is not None and v < 0 for v in (self.max_gap, self.sigma, self.occlusion_fill)):
            raise ValueError(
                "TrackerConfig: max_gap, sigma and occlusion_fill (frames) must be non-negative."
            )

    @classmethod
    def from_dict(cls, d: dict) -> TrackerConfig:
        return config_from_dict(cls, d)

    def at_fps(self, fps: float) -> TrackerConfig:
        """The config with the durations given in frames converted to seconds at ``fps``, and the
        smoothing width the seed gives in frames (sec. 4.3.4: sigma = 2) when none is set."""
        conv = {
            f"{k}_s": getattr(self, k) / fps
            for k in ("max_gap", "sigma", "occlusion_fill")
            if getattr(self, k) is not None
        }
        if self.sigma_s is None and "sigma_s" not in conv:
            conv["sigma_s"] = SEED_SIGMA_FRAMES / fps
        if not conv and self.max_gap is None and self.occlusion_fill is None:
            return self
        return replace(self, **conv, max_gap=None, sigma=None, occlusion_fill=None)


def frame_times_s(frame_index: np.ndarray, t_ns: np.ndarray | None, fps: float) -> np.ndarray:
    """(T,) seconds of each frame from its start: ``t_ns`` when every frame has one and they increase,
    else ``frame_index / fps`` (timestamps missing, or not usable)."""
    fi = np.asarray(frame_index, np.float64)
    if t_ns is not None and len(t_ns) == len(fi) and len(fi):
        t = np.asarray(t_ns, np.int64)
        if (np.diff(t) > 0).all() and (len(t) == 1 or t[-1] > 0):
            return (t - t[0]) / 1e9
    return (fi - (fi[0] if len(fi) else 0.0)) / fps


def pose_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Sec. 4.2.2 cost between poses A (K,J,3) and B (P,J,3): mean distance over shared joints,
    ground-plane distance of the mean joints where none is shared. Returns (K,P) metres."""
    va, vb = np.isfinite(A).all(-1), np.isfinite(B).all(-1)
    a, b = np.nan_to_num(A), np.nan_to_num(B)
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)  # (K,P,J)
    shared = va[:, None] & vb[None]
    n = shared.sum(-1)
    mean = np.where(shared, d, 0).sum(-1) / np.maximum(n, 1)
    ca = np.nanmean(np.where(va[..., None], A, np.nan), axis=1)[:, :2] if len(A) else np.zeros((0, 2))
    cb = np.nanmean(np.where(vb[..., None], B, np.nan), axis=1)[:, :2] if len(B) else np.zeros((0, 2))
    ground = np.linalg.norm(ca[:, None] - cb[None], axis=-1)
    return np.where(n > 0, mean, np.nan_to_num(ground, nan=np.inf))


def associate(
    xyz_m: np.ndarray, config: TrackerConfig | None = None, fps: float = 25.0, t_s: np.ndarray | None = None
) -> np.ndarray:
    """Greedy tracking. xyz_m: (T,P,J,3) per-frame poses (NaN padding); t_s (T,) frame times in seconds
    (default: regular at ``fps``). Returns track index (T,P) or -1."""
    return associate_mirrored(xyz_m, config, fps, None, t_s=t_s)[0]


def nominal_dt(fps: float) -> float:
    """One frame interval at the nominal rate, plus a little for jittered timestamps."""
    return 1.0 / fps + 1e-6


def pause_clock(t_s: np.ndarray, max_gap_s: float, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """The tracks' clock: (T,) times with every pause of the recorder (consecutive frames more than
    ``max_gap_s`` apart) shortened to one frame, and (T,) the number of pauses before each frame."""
    d = np.diff(np.asarray(t_s, np.float64))
    pause = d > max_gap_s + nominal_dt(fps)
    active = np.concatenate([[0.0], np.cumsum(np.where(pause, 1.0 / fps, d))])
    return active, np.concatenate([[0], np.cumsum(pause)])


def segment_frames(pauses: np.ndarray) -> np.ndarray:
    """(T,) the number of frames of the stretch without a pause of the recorder that each frame lies in
    (``pauses`` (T,) from :func:`pause_clock`): 1 for every frame of a time-lapse."""
    pauses = np.asarray(pauses, np.int64)
    return np.bincount(pauses)[pauses] if len(pauses) else np.zeros(0, np.int64)


def long_enough(frames: np.ndarray, room: np.ndarray, min_frames: int) -> np.ndarray:
    """(K,) bool: tracks of ``frames`` (K,) frames kept by the minimum length ``min_frames``, which a
    track need not reach where the recorder never ran that long around it: ``room`` (K,) is the longest
    stretch without a pause (:func:`segment_frames`) among the track's frames. Poses between pauses (a
    time-lapse, snapshots far apart) stay as short tracks; the tracker never drops them as too short."""
    return np.asarray(frames) >= np.minimum(min_frames, np.maximum(np.asarray(room), 1))


def sparse_time_warning(
    pauses: np.ndarray, max_gap_s: float, min_frames: int, t_s: np.ndarray | None = None
) -> str | None:
    """A warning when most frames lie in stretches between pauses of the recorder too short to link
    (fewer than ``min_frames`` frames): snapshots far apart in time (a time-lapse, a motion-triggered
    recording), whose per-frame poses are kept as short tracks. With the frames' times ``t_s``, it
    begins with their gaps' statistics."""
    if not len(pauses) or pauses[-1] == 0:
        return None
    short = int((segment_frames(pauses) < min_frames).sum())
    if short * 2 < len(pauses):
        return None
    head = f"snapshots, not a video: {gap_statistics(t_s)}; " if t_s is not None else ""
    return head + (
        f"{short} of {len(pauses)} frames lie between pauses of the recorder (consecutive frames more than "
        f"{max_gap_s:g} s apart, {int(pauses[-1])} pauses): snapshots this far apart cannot be linked in "
        "time, so they are kept as short tracks of their per-frame poses; identities across a pause are "
        "guesses by position"
    )


def facing_joints(joint_names) -> tuple[int, int, int] | None:
    """(nose, left_shoulder, right_shoulder) indices for :func:`labels_face_forward`, None where missing."""
    idx = {n: i for i, n in enumerate(joint_names)}
    if not {"nose", "left_shoulder", "right_shoulder"} <= idx.keys():
        return None
    return idx["nose"], idx["left_shoulder"], idx["right_shoulder"]


def labels_face_forward(
    pose: np.ndarray, facing: tuple[int, int, int] | None, margin_m: float = 0.03
) -> bool:
    """Whether pose (J,3) (world, z up) has its nose at least ``margin_m`` in front of its shoulders, front
    being (left - right shoulder) x up: left/right labels a mirror could not have (mirrored, the nose is
    behind). False where a joint is missing or the skeleton has none (``facing`` None)."""
    if facing is None:
        return False
    nose, left, right = pose[list(facing)]
    across = left - right
    front = np.array([across[1], -across[0], 0.0])
    norm = float(np.hypot(front[0], front[1]))
    if not (np.isfinite(nose).all() and np.isfinite(front).all()) or norm < 1e-6:
        return False
    return float((nose - 0.5 * (left + right)) @ front) / norm > margin_m


def join_mirrored(
    pose: np.ndarray, track_pose: np.ndarray, flip: np.ndarray, facing: tuple[int, int, int] | None
) -> tuple[np.ndarray, np.ndarray, bool]:
    """A pose (J,3) that fits the track's last pose better left/right swapped joins the track: returns the
    pose as joined, the track's last pose and whether the pose was swapped. Where the pose's own labels
    face forward (:func:`labels_face_forward`; ``facing``: :func:`facing_joints`) the track is the mirrored
    one (it took a mirrored pose earlier, or was born from one) and is turned back, so that one mirrored
    frame does not mirror every correct pose after it (the 60-minute synthetic session, BENCHMARKS.md);
    otherwise the pose is swapped."""
    if labels_face_forward(pose, facing):
        return pose, track_pose[flip], False
    return pose[flip], track_pose, True


class FrameLinker:
    """The greedy tracker's linking step, one frame at a time (:meth:`step`): each alive track's pose,
    predicted at constant velocity, is matched to the frame's poses by the Hungarian method on the mean
    joint distance, gated by ``tau_m + max_speed_m_s`` x the unseen time (+ ``pause_gate_m`` across a
    pause of the recorder); a pose that joins no track starts one. Labels are track numbers by first
    appearance. Only the tracks seen within ``max_gap_s`` on the tracks' clock are kept, so the state does
    not grow with the session.

    ``clock (T,)``, ``pauses (T,)``: :func:`pause_clock` of the session's frame times. ``flip`` (J,)
    (left/right joint permutation): a pose may also join a track mirrored, when its left/right-swapped
    version is closer; ``facing``: see :func:`join_mirrored`. The hooks :meth:`_joined` and
    :meth:`_retired` let :class:`roomcap.track.greedy_chunked.StreamLinker` keep what stitching needs."""

    def __init__(
        self,
        cfg: TrackerConfig,
        fps: float,
        flip: np.ndarray | None,
        clock: np.ndarray,
        pauses: np.ndarray,
        facing: tuple[int, int, int] | None,
    ) -> None:
        self.cfg, self.fps, self.flip, self.facing = cfg, fps, flip, facing
        self.clock, self.pauses = clock, pauses
        self.window = cfg.max_gap_s + nominal_dt(fps)
        self.n_tracks = 0
        self.active: list[int] = []  # alive tracks, increasing
        self.pose: dict[int, np.ndarray] = {}  # last pose, joints the track had but a frame lacked kept
        self.last_clock: dict[int, float] = {}  # seconds on the tracks' clock (pauses shortened)
        self.last_pause: dict[int, int] = {}  # pauses of the recorder before the track's last frame
        self.vel: dict[int, np.ndarray] = {}  # (3,) mean-joint velocity, m/s

    def _joined(self, k: int, t: int, raw: np.ndarray, born: bool) -> None:
        """Hook: the (mirror-corrected) pose ``raw`` joined track ``k`` at frame ``t`` (``born``: new)."""

    def _retired(self, k: int) -> None:
        """Hook: track ``k`` can no longer continue (before its state is dropped)."""

    def retire(self, now: float, final: bool = False) -> None:
        """Drop the tracks that can no longer continue at clock time ``now`` (all with ``final``)."""
        keep = []
        for k in self.active:
            if final or now - self.last_clock[k] > self.window:
                self._retired(k)
                for d in (self.pose, self.last_clock, self.last_pause, self.vel):
                    d.pop(k, None)
            else:
                keep.append(k)
        self.active = keep

    def step(self, t: int, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``t`` (session position) with poses (P,J,3): returns labels (P,) (-1 none), mirrored (P,)."""
        cfg, flip = self.cfg, self.flip
        P = len(poses)
        out = np.full(P, -1, np.int64)
        mirrored = np.zeros(P, bool)
        now = self.clock[t]
        self.retire(now)
        ok = np.flatnonzero(np.isfinite(poses).all(-1).sum(-1) >= cfg.min_joints)
        if len(ok) == 0:
            return out, mirrored
        alive = self.active
        assigned = np.zeros(len(ok), bool)
        if alive:
            since = now - np.asarray([self.last_clock[k] for k in alive])  # (A,) seconds since last seen
            pred = np.stack([self.pose[k] + since[n] * self.vel[k] for n, k in enumerate(alive)])
            cost = pose_distance(pred, poses[ok])
            # a track last seen before a pause of the recorder: its pose is from another moment, so it can
            # neither say the new pose is mirrored nor give it a velocity (a time-lapse's snapshots)
            paused = self.pauses[t] > np.asarray([self.last_pause[k] for k in alive])
            mir = np.zeros(cost.shape, bool)
            if flip is not None:
                cost_m = pose_distance(pred, poses[ok][:, flip])
                mir = (cost_m < cost) & ~paused[:, None]
                cost = np.where(mir, cost_m, cost)
            # unseen time beyond one frame; bounded, as alive tracks were seen within max_gap_s
            gap_s = np.clip(since - 1.0 / self.fps, 0.0, cfg.max_gap_s)
            limit = cfg.tau_m + cfg.max_speed_m_s * gap_s + cfg.pause_gate_m * paused
            # gate before the assignment: a pair above the limit must not pull a valid pair apart
            rows, cols = linear_sum_assignment(np.where(cost < limit[:, None], cost, 1e9))
            for r, c in zip(rows, cols, strict=True):
                if cost[r, c] < limit[r]:
                    k = alive[r]
                    out[ok[c]] = k
                    # keep joints the track had but this frame lacks, so the next cost has them
                    pose = poses[ok[c]].copy()
                    if mir[r, c]:
                        pose, self.pose[k], mirrored[ok[c]] = join_mirrored(
                            pose, self.pose[k], flip, self.facing
                        )
                    self._joined(k, t, pose, born=False)
                    miss = ~np.isfinite(pose).all(-1)
                    if paused[r]:
                        self.vel[k] = np.zeros(3)
                    elif cfg.constant_velocity:
                        both = ~miss & np.isfinite(self.pose[k]).all(-1)
                        if both.any():
                            v = (pose[both] - self.pose[k][both]).mean(0) / max(since[r], 1e-9)
                            self.vel[k] = 0.5 * self.vel[k] + 0.5 * v
                    pose[miss] = self.pose[k][miss] + since[r] * self.vel[k]
                    self.pose[k], self.last_clock[k], self.last_pause[k] = pose, now, int(self.pauses[t])
                    assigned[c] = True
        for c in np.flatnonzero(~assigned):
            k = self.n_tracks
            self.n_tracks += 1
            out[ok[c]] = k
            self._joined(k, t, poses[ok[c]], born=True)
            self.pose[k] = poses[ok[c]].copy()
            self.last_clock[k], self.last_pause[k], self.vel[k] = now, int(self.pauses[t]), np.zeros(3)
            self.active.append(k)
        return out, mirrored


def associate_mirrored(
    xyz_m: np.ndarray,
    config: TrackerConfig | None = None,
    fps: float = 25.0,
    flip: np.ndarray | None = None,
    *,
    t_s: np.ndarray | None = None,
    facing: tuple[int, int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`associate` with :class:`FrameLinker`'s mirrored joins (``flip``, ``facing``) over the whole
    session, then :func:`stitch_tracks`. Returns assign (T,P) and mirrored (T,P)."""
    cfg = (config or TrackerConfig()).at_fps(fps)
    T, P = xyz_m.shape[:2]
    t_s = np.arange(T) / fps if t_s is None else np.asarray(t_s, np.float64)
    clock, pauses = pause_clock(t_s, cfg.max_gap_s, fps)
    linker = FrameLinker(cfg, fps, flip, clock, pauses, facing)
    out = np.full((T, P), -1, dtype=np.int64)
    mirrored = np.zeros((T, P), bool)
    for t in range(T):
        out[t], mirrored[t] = linker.step(t, xyz_m[t])
    if cfg.stitch:
        out = stitch_tracks(xyz_m, out, mirrored, cfg, fps, flip, t_s=t_s)  # on the same clock
    return out, mirrored


def stitch_tracks(
    xyz_m: np.ndarray,
    assign: np.ndarray,
    mirrored: np.ndarray | None = None,
    config: TrackerConfig | None = None,
    fps: float = 25.0,
    flip: np.ndarray | None = None,
    *,
    t_s: np.ndarray | None = None,
) -> np.ndarray:
    """Join track fragments the frame-by-frame pass split. Returns the relabelled assign (T,P).

    The pass starts a new track for a pose that is too far from every track (e.g. a few badly
    triangulated frames of a person seen by two cameras only) and that young track then competes
    with the lost one for the person's next poses: the Hungarian step gives them to whichever is
    closer, often the young one, and the old track ends. Here a track b that begins after track a
    ended, within ``max_gap_s``, continues a when one of b's poses in that window lies within
    the limit the pass would have allowed a (``tau_m + max_speed_m_s * gap``, sec. 4.2.2's
    distance to a's last pose, missing joints held from a's earlier frames). Candidate links are
    taken greedily by distance, each track continuing at most one and continued by at most one.
    """
    cfg = (config or TrackerConfig()).at_fps(fps)
    T = len(assign)
    t_s = np.arange(T) / fps if t_s is None else np.asarray(t_s, np.float64)
    t_s, pauses = pause_clock(t_s, cfg.max_gap_s, fps)  # the tracks' clock, as in the pass
    window = cfg.max_gap_s + nominal_dt(fps)
    t_idx, p_idx = np.nonzero(assign >= 0)
    if len(t_idx) == 0:
        return assign
    X = xyz_m[t_idx, p_idx]  # (n,J,3) every assigned pose, in time order
    if mirrored is not None and flip is not None:
        m = mirrored[t_idx, p_idx]
        X[m] = X[m][:, flip]
    k_idx = assign[t_idx, p_idx]
    K = int(k_idx.max()) + 1
    first, last = np.full(K, T), np.full(K, -1)
    np.minimum.at(first, k_idx, t_idx)
    np.maximum.at(last, k_idx, t_idx)
    by_track = np.argsort(k_idx, kind="stable")  # each track's rows, in time order
    bounds = np.searchsorted(k_idx[by_track], np.arange(K + 1))
    cands = []
    for a in range(K):
        if last[a] < 0:
            continue
        first_s = t_s[np.minimum(first, T - 1)]
        later = np.flatnonzero((first > last[a]) & (first_s - t_s[last[a]] <= window))
        if len(later) == 0:
            continue
        rows = by_track[bounds[a] : bounds[a + 1]]
        end = X[rows[-1]].copy()  # a's last pose, joints it lacks held from a's earlier frames
        for r in rows[::-1][1:]:
            miss = ~np.isfinite(end).all(-1)
            if not miss.any():
                break
            end[miss] = X[r][miss]
        for b in later:
            sel = by_track[bounds[b] : bounds[b + 1]]
            since = t_s[t_idx[sel]] - t_s[last[a]]
            sel, since = sel[since <= window], since[since <= window]
            d = pose_distance(end[None], X[sel])[0]
            limit = cfg.tau_m + cfg.max_speed_m_s * np.clip(since - 1.0 / fps, 0.0, cfg.max_gap_s)
            limit = limit + cfg.pause_gate_m * (pauses[t_idx[sel]] > pauses[last[a]])
            hit = np.flatnonzero(d < limit)
            if len(hit):
                cands.append((float(d[hit[0]]), a, int(b)))
    if not cands:
        return assign
    succ, pred = np.full(K, -1), np.full(K, -1)
    for _, a, b in sorted(cands):
        if succ[a] < 0 and pred[b] < 0:
            succ[a], pred[b] = b, a
    root = np.arange(K)
    for k in np.argsort(first, kind="stable"):  # chains in time order: a -> b -> c share a's label
        if pred[k] >= 0:
            root[k] = root[pred[k]]
    out = assign.copy()
    out[t_idx, p_idx] = root[k_idx]
    return out


def _interp_gaps(
    x: np.ndarray, t_s: np.ndarray, max_gap_s: float, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation in time over NaN runs of x (T,D) between two samples at most ``max_gap_s``
    (+ one frame) apart. Returns x, filled (T,)."""
    valid = np.isfinite(x).all(-1)
    filled = np.zeros(len(x), bool)
    idx = np.flatnonzero(valid)
    if len(idx) < 2 or max_gap_s <= 0:
        return x, filled
    x = x.copy()
    for i0, i1 in zip(idx[:-1], idx[1:], strict=True):
        if i1 - i0 > 1 and t_s[i1] - t_s[i0] <= max_gap_s + dt:
            a = ((t_s[i0 + 1 : i1] - t_s[i0]) / (t_s[i1] - t_s[i0]))[:, None]
            x[i0 + 1 : i1] = (1 - a) * x[i0] + a * x[i1]
            filled[i0 + 1 : i1] = True
    return x, filled


def smooth_segments(
    x: np.ndarray, t_s: np.ndarray, sigma_s: float, max_gap_s: float, fps: float
) -> np.ndarray:
    """NaN-aware Gaussian smoothing of x (T,...) in time: weights exp(-dt^2 / 2 sigma_s^2) over the
    samples within 3 sigma (the taps ``gaussian_filter1d`` uses at ``fps``), never across two frames
    more than ``max_gap_s`` (+ one frame) apart. On regular frames it equals ``gaussian_filter1d``
    (mode constant, truncate 3) with sigma = sigma_s * fps, up to float rounding."""
    T = len(x)
    if sigma_s <= 0 or T < 2:
        return x
    radius_s = int(3.0 * sigma_s * fps + 0.5) / fps + 1e-6
    segment = np.concatenate([[0], np.cumsum(np.diff(t_s) > max_gap_s + nominal_dt(fps))])
    reach = int((np.searchsorted(t_s, t_s + radius_s, side="right") - np.arange(T)).max())
    valid = np.isfinite(x)
    xv = np.where(valid, x, 0.0)
    num = np.zeros(x.shape)
    den = np.zeros(x.shape)
    extra = (1,) * (x.ndim - 1)
    for k in range(-reach, reach + 1):
        i = np.arange(max(0, -k), min(T, T - k))  # samples whose neighbour i + k exists
        d = t_s[i + k] - t_s[i]
        w = np.exp(-0.5 * (d / sigma_s) ** 2) * (np.abs(d) <= radius_s) * (segment[i + k] == segment[i])
        w = w.reshape(-1, *extra)
        num[i] += w * xv[i + k]
        den[i] += w * valid[i + k]
    return np.where(valid, num / np.maximum(den, 1e-12), np.nan)


def _kinematic_fill(
    X: np.ndarray, parents: np.ndarray, t_s: np.ndarray, max_fill_s: float, dt: float
) -> np.ndarray:
    """Fill joint gaps of one track X (T,J,3) in place by the offset from the parent joint.

    Parents are filled first (order of a walk from the root). The offset is linearly interpolated in
    time between the observations around a gap of at most ``max_fill_s``; elsewhere (before the first /
    after the last observation, and inside a longer gap) it is held from the nearest observation up to
    half of ``max_fill_s`` away, and the middle of a longer gap stays NaN. Each filled value depends
    only on the observations within ``max_fill_s`` (the rule is local in time, so a chunked run
    equals the whole session's). Returns the (T,J) mask of filled entries.
    """
    T, J = X.shape[:2]
    filled = np.zeros((T, J), bool)
    alive = np.flatnonzero(np.isfinite(X).all(-1).any(-1))
    if len(alive) == 0:
        return filled
    t0, t1 = alive[0], alive[-1] + 1
    order, seen = [], set()
    while len(order) < J:
        for j in range(J):
            if j not in seen and (parents[j] < 0 or parents[j] in seen):
                order.append(j)
                seen.add(j)
    tt = np.arange(T)
    for j in order:
        p = parents[j]
        if p < 0:
            continue
        have_j = np.isfinite(X[:, j]).all(-1)
        have_p = np.isfinite(X[:, p]).all(-1)
        both = np.flatnonzero(have_j & have_p)
        need = np.flatnonzero(~have_j & have_p & (tt >= t0) & (tt < t1))
        if len(both) == 0 or len(need) == 0:
            continue
        # the observations of the offset around each needed frame
        right = np.searchsorted(both, need)
        has_lo, has_hi = right > 0, right < len(both)
        lo, hi = both[np.maximum(right - 1, 0)], both[np.minimum(right, len(both) - 1)]
        d_lo = np.where(has_lo, t_s[need] - t_s[lo], np.inf)
        d_hi = np.where(has_hi, t_s[hi] - t_s[need], np.inf)
        # a gap of at most max_fill_s between two observations: interpolated
        inside = has_lo & has_hi & (t_s[hi] - t_s[lo] <= max_fill_s + dt)
        # else held from the nearer observation, up to max_fill_s / 2 away
        held = ~inside & (np.minimum(d_lo, d_hi) <= max_fill_s / 2 + dt)
        run_ok = inside | held
        if not run_ok.any():
            continue
        off = X[both, j] - X[both, p]
        o = np.full((len(need), 3), np.nan)
        ii = np.flatnonzero(inside)
        if len(ii):
            o[ii] = np.stack([np.interp(t_s[need[ii]], t_s[both], off[:, k]) for k in range(3)], 1)
        hh = np.flatnonzero(held)
        if len(hh):
            o[hh] = (
                X[np.where(d_lo[hh] <= d_hi[hh], lo[hh], hi[hh]), j]
                - X[np.where(d_lo[hh] <= d_hi[hh], lo[hh], hi[hh]), p]
            )
        need, o = need[run_ok], o[run_ok]
        X[need, j] = X[need, p] + o
        filled[need, j] = True
    return filled


def build_tracks(
    xyz_m: np.ndarray,
    assign: np.ndarray,
    confidence: np.ndarray | None = None,
    std_m: np.ndarray | None = None,
    config: TrackerConfig | None = None,
    parents: np.ndarray | None = None,
    mirrored: np.ndarray | None = None,
    flip: np.ndarray | None = None,
    *,
    fps: float = 25.0,
    t_s: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dense tracks from per-frame poses and assignments, with gap filling and smoothing.

    xyz_m (T,P,J,3), assign (T,P) from :func:`associate`, confidence/std_m (T,P,J), t_s (T,) frame
    times in seconds (default: regular at ``fps``).
    Returns track ids (K,), xyz (T,K,J,3), confidence (T,K,J), std (T,K,J), flags (T,K,J) uint8.
    """
    cfg = (config or TrackerConfig()).at_fps(fps)
    T, P, J = xyz_m.shape[:3]
    t_s = np.arange(T) / fps if t_s is None else np.asarray(t_s, np.float64)
    dt = nominal_dt(fps)
    conf = np.ones((T, P, J)) if confidence is None else confidence
    std = np.full((T, P, J), np.nan) if std_m is None else std_m
    if mirrored is not None and flip is not None and mirrored.any():
        xyz_m, conf, std = xyz_m.copy(), np.array(conf, copy=True), np.array(std, copy=True)
        xyz_m[mirrored] = xyz_m[mirrored][:, flip]
        conf[mirrored] = conf[mirrored][:, flip]
        std[mirrored] = std[mirrored][:, flip]
    ids = np.unique(assign[assign >= 0])
    counts = np.array([(assign == k).any(1).sum() for k in ids], dtype=np.int64)
    run = segment_frames(pause_clock(t_s, cfg.max_gap_s, fps)[1])
    room = np.array([run[(assign == k).any(1)].max() for k in ids], dtype=np.int64)
    ids = ids[long_enough(counts, room, cfg.min_track_frames)]
    K = len(ids)
    X = np.full((T, K, J, 3), np.nan)
    Cf = np.zeros((T, K, J))
    S = np.full((T, K, J), np.nan)
    Fl = np.zeros((T, K, J), np.uint8)
    for n, k in enumerate(ids):
        t, p = np.nonzero(assign == k)
        X[t, n], Cf[t, n], S[t, n] = xyz_m[t, p], conf[t, p], std[t, p]
        obs = np.isfinite(X[:, n]).all(-1)
        Fl[:, n][obs] |= OBSERVED
        for j in range(J):
            x, filled = _interp_gaps(X[:, n, j], t_s, cfg.max_gap_s, dt)
            if filled.any():
                X[filled, n, j] = x[filled]
                s_f, _ = _interp_gaps(
                    np.where(obs[:, j], S[:, n, j], np.nan)[:, None], t_s, cfg.max_gap_s, dt
                )
                c_f, _ = _interp_gaps(
                    np.where(obs[:, j], Cf[:, n, j], np.nan)[:, None], t_s, cfg.max_gap_s, dt
                )
                S[filled, n, j] = s_f[filled, 0]
                Cf[filled, n, j] = 0.5 * np.nan_to_num(c_f[filled, 0])
                Fl[filled, n, j] |= INTERPOLATED
        if cfg.occlusion_fill_s > 0 and parents is not None:
            kin = _kinematic_fill(X[:, n], np.asarray(parents), t_s, cfg.occlusion_fill_s, dt)
            if kin.any():
                # std of a predicted joint: its parent's std plus 5 cm (the offset is a guess)
                # (a parent of unknown std counts as 5 cm: a constant, so a chunk needs no whole-track
                # statistic)
                known = np.isfinite(S[:, n])
                s_par = np.where(known, S[:, n], 0.05)
                pj = np.maximum(np.asarray(parents), 0)
                S[:, n] = np.where(kin, s_par[:, pj] + 0.05, S[:, n])
                Cf[:, n] = np.where(kin, 0.25 * Cf[:, n, pj], Cf[:, n])
                Fl[:, n][kin] |= PREDICTED
        if cfg.sigma_s > 0:
            have = np.isfinite(X[:, n]).all(-1)
            X[:, n] = np.where(
                have[..., None], smooth_segments(X[:, n], t_s, cfg.sigma_s, cfg.max_gap_s, fps), np.nan
            )
            Fl[:, n][have] |= SMOOTHED
    return ids, X, Cf, S, Fl


def track_poses(
    xyz_m: np.ndarray,
    frame_index: np.ndarray,
    t_ns: np.ndarray,
    fps: float,
    joint_names: tuple[str, ...],
    parents: np.ndarray,
    confidence: np.ndarray | None = None,
    std_m: np.ndarray | None = None,
    config: TrackerConfig | None = None,
    calibration_sha256: str = "",
    source: str = "track.greedy (greedy, ch. 4)",
) -> TrackFile:
    """Per-frame poses (T,P,J,3) -> :class:`TrackFile` (track ids 0..K-1 by first appearance)."""
    cfg = (config or TrackerConfig()).at_fps(fps)
    flip = flip_index(joint_names) if cfg.fix_mirrored else None
    t_s = frame_times_s(frame_index, t_ns, fps)
    warn = sparse_time_warning(
        pause_clock(t_s, cfg.max_gap_s, fps)[1], cfg.max_gap_s, cfg.min_track_frames, t_s
    )
    if warn:
        log.warning("greedy tracker: %s", warn)
    assign, mirrored = associate_mirrored(xyz_m, cfg, fps, flip, t_s=t_s, facing=facing_joints(joint_names))
    ids, X, Cf, S, Fl = build_tracks(
        xyz_m, assign, confidence, std_m, cfg, parents, mirrored, flip, fps=fps, t_s=t_s
    )
    return TrackFile(
        fps=fps,
        frame_index=frame_index,
        t_ns=t_ns,
        track_id=np.arange(len(ids)),
        joint_names=joint_names,
        parents=parents,
        xyz_m=X,
        confidence=np.clip(Cf, 0, 1),
        std_m=S,
        flags=Fl,
        calibration_sha256=calibration_sha256,
        source=source,
    )
