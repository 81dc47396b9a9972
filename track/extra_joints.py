"""Whole-body joints for the particle tracker: the joints its body19 state lacks, attached after tracking.

The particle filter (:mod:`roomcap.track.particle`) samples body19 poses. The greedy tracker carries every
joint
the triangulate stage's skeleton has (``[triangulate.options] skeleton = "whole_body"``: feet, BODY_25B's
upper neck and head top, BlazePose's hand points; or a skeleton TOML). :func:`attach_joints` gives the
particle tracker's track file the same skeleton, once identities are assigned:

1. per frame and camera, each track's body19 joints are projected and the camera's detection slots are
   assigned to the tracks (Hungarian, cost = median pixel distance over the body19 joints both know,
   gated at ``gate_frac`` of the projected person's size, at least ``gate_min_px``);
2. each joint the body19 state lacks is triangulated from the views assigned to its track (the robust
   DLT of :mod:`roomcap.triangulate.dlt`, the triangulate stage's settings: score threshold, reprojection
   rejection), with its positional uncertainty ``std_m`` and the mean 2D score as ``confidence``;
   a point farther than ``max_bone_m`` from its parent joint is dropped;
3. a Gaussian smoothing over time (``smooth_sigma_s``, within runs of observed frames, weighted by
   1/std^2, as the particle tracker smooths its own joints); flags ``OBSERVED | SMOOTHED``.

The body19 joints stay those of the particle filter; a joint of the skeleton that the detections never
give stays unknown (NaN).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from roomcap.core.config import config_from_dict
from roomcap.track.trackfile import OBSERVED, SMOOTHED, TrackFile
from roomcap.triangulate.dlt import DLTConfig, Triangulator
from roomcap.triangulate.geometry import project
from roomcap.triangulate.multiview import load_detections

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExtraJointsConfig:
    """Settings of :func:`attach_joints` (module docstring)."""

    min_score: float = 0.3  # 2D joints with a lower score are unseen (Pose2Sim's likelihood threshold)
    gate_frac: float = 0.25  # assignment gate: fraction of the projected person's bounding-box diagonal
    gate_min_px: float = 20.0
    min_joints: int = 4  # body19 joints a detection must share with the track to be assigned
    max_bone_m: float = 0.5  # a triangulated joint farther from its parent is dropped
    smooth_sigma_s: float = 0.02  # temporal Gaussian smoothing (0: none)
    dlt: DLTConfig = DLTConfig()

    @classmethod
    def from_dict(cls, d: dict) -> ExtraJointsConfig:
        return config_from_dict(cls, d)


def assign_views(
    P: np.ndarray, X: np.ndarray, xy: np.ndarray, score: np.ndarray, cfg: ExtraJointsConfig
) -> np.ndarray:
    """Detection slot of each track in each camera, one frame.

    ``P (C,3,4)``, ``X (K,Jb,3)`` the tracks' body19 joints (NaN unknown), ``xy (C,S,Jb,2)`` and
    ``score (C,S,Jb)`` the detections' same joints. Returns ``(C,K)`` slot index, -1 where none."""
    C, S = xy.shape[:2]
    K = len(X)
    out = np.full((C, K), -1, np.int64)
    known = np.isfinite(X).all(-1)  # (K,Jb)
    live = known.sum(1) >= cfg.min_joints
    if not live.any() or S == 0:
        return out
    Xf = np.where(known[..., None], X, 0.0)
    seen = np.isfinite(xy).all(-1) & (score >= cfg.min_score)  # (C,S,Jb)
    for c in range(C):
        uv = project(P[c][None], Xf.reshape(-1, 3))[0].reshape(K, -1, 2)  # (K,Jb,2)
        d = np.linalg.norm(uv[:, None] - xy[c][None], axis=-1)  # (K,S,Jb)
        both = known[:, None] & seen[c][None]
        cost = np.full((K, S), np.inf)
        n_both = both.sum(-1)
        for k in np.flatnonzero(live):
            lo, hi = np.nanmin(uv[k, known[k]], 0), np.nanmax(uv[k, known[k]], 0)
            gate = max(cfg.gate_frac * float(np.linalg.norm(hi - lo)), cfg.gate_min_px)
            for s in range(S):
                if n_both[k, s] >= cfg.min_joints:
                    m = float(np.median(d[k, s][both[k, s]]))
                    if m <= gate:
                        cost[k, s] = m
        ok_rows = np.isfinite(cost).any(1)
        if not ok_rows.any():
            continue
        sub = np.where(np.isfinite(cost), cost, 1e9)
        r, s = linear_sum_assignment(sub)
        for k, si in zip(r, s, strict=True):
            if np.isfinite(cost[k, si]):
                out[c, k] = si
    return out


def _smooth(xyz: np.ndarray, std: np.ndarray, sigma_frames: float) -> np.ndarray:
    """Gaussian smoothing over time of ``xyz (T,3)`` within runs of known frames, weights 1/std^2."""
    if sigma_frames <= 0:
        return xyz
    out = xyz.copy()
    known = np.isfinite(xyz).all(-1) & np.isfinite(std)
    r = max(int(np.ceil(3 * sigma_frames)), 1)
    offs = np.arange(-r, r + 1)
    g = np.exp(-0.5 * (offs / sigma_frames) ** 2)
    idx = np.flatnonzero(known)
    if not len(idx):
        return out
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    for run in runs:
        x, w = xyz[run], 1.0 / np.maximum(std[run], 1e-3) ** 2
        n = len(run)
        for i in range(n):
            lo, hi = max(i - r, 0), min(i + r + 1, n)
            ww = g[lo - i + r : hi - i + r] * w[lo:hi]
            out[run[i]] = (ww[:, None] * x[lo:hi]).sum(0) / ww.sum()
    return out


def attach_joints(
    tf: TrackFile,
    P: np.ndarray,
    xy_px: np.ndarray,
    score: np.ndarray,
    joint_names: tuple[str, ...],
    parents,
    config: ExtraJointsConfig | None = None,
) -> TrackFile:
    """The track file ``tf`` (body19, the particle tracker's) with the skeleton ``joint_names`` /
    ``parents``: its own joints copied by name, the others triangulated per track (module docstring).

    ``P (C,3,4)`` the rig's projection matrices; ``xy_px (C,T,S,J,2)`` undistorted pixels and
    ``score (C,T,S,J)`` the detections in the skeleton's layout on ``tf``'s frame axis."""
    cfg = config or ExtraJointsConfig()
    joint_names = tuple(joint_names)
    parents = np.asarray(parents, np.int64)
    C, T, S, J = score.shape
    if T != tf.n_frames or J != len(joint_names):
        raise ValueError(
            f"attach_joints: detections of {T} frames x {J} joints for a track file of {tf.n_frames} "
            f"frames and a skeleton of {len(joint_names)} joints"
        )
    K = tf.n_tracks
    own = {n: i for i, n in enumerate(tf.joint_names)}
    shared = [j for j, n in enumerate(joint_names) if n in own]  # joints the tracker has
    extra = [j for j, n in enumerate(joint_names) if n not in own]
    if extra and len(shared) < cfg.min_joints:
        raise ValueError(
            f"the skeleton {list(joint_names)} shares {len(shared)} joints with the tracks' "
            f"{list(tf.joint_names)}; the particle tracker places the other joints from at least "
            f"{cfg.min_joints} shared ones. Use the greedy tracker (--tracker greedy) for this skeleton."
        )
    xyz = np.full((T, K, J, 3), np.nan, np.float32)
    conf = np.zeros((T, K, J), np.float32)
    std = np.full((T, K, J), np.nan, np.float32)
    flags = np.zeros((T, K, J), np.uint8)
    src = [own[joint_names[j]] for j in shared]
    xyz[:, :, shared] = tf.xyz_m[:, :, src]
    conf[:, :, shared] = tf.confidence[:, :, src]
    std[:, :, shared] = tf.std_m[:, :, src]
    flags[:, :, shared] = tf.flags[:, :, src]
    if extra and K:
        out = (xyz, conf, std, flags)
        _triangulate_extra(tf, P, xy_px, score, shared, extra, src, cfg, out)
        _drop_far_from_parent(parents, extra, cfg.max_bone_m, out)
        sigma = cfg.smooth_sigma_s * tf.fps
        if sigma > 0:
            for k in range(K):
                for j in extra:
                    xyz[:, k, j] = _smooth(xyz[:, k, j].astype(np.float64), std[:, k, j], sigma)
            flags[:, :, extra] |= np.where(flags[:, :, extra] > 0, SMOOTHED, 0).astype(np.uint8)
        n_obs = int((flags[:, :, extra] > 0).sum())
        log.info(
            "particle tracker: %d joints beyond body19 (%s) attached, %d of %d track-frame-joints known",
            len(extra),
            ", ".join(joint_names[j] for j in extra[:8]) + (" ..." if len(extra) > 8 else ""),
            n_obs,
            int(tf.mask.any(-1).sum()) * len(extra),
        )
    return replace(
        tf,
        joint_names=joint_names,
        parents=parents,
        xyz_m=xyz,
        confidence=conf,
        std_m=std,
        flags=flags,
        source=tf.source + " + extra joints triangulated (track.extra_joints)",
    )


def _triangulate_extra(tf, P, xy_px, score, shared, extra, src, cfg: ExtraJointsConfig, out) -> None:
    """Per frame, each track's views (:func:`assign_views` by its shared joints) and the joints ``extra``
    triangulated from them into ``out = (xyz, conf, std, flags)``."""
    xyz, conf, std, flags = out
    C, T = score.shape[:2]
    K, E = tf.n_tracks, len(extra)
    tri = Triangulator(P, cfg.dlt)
    for t in range(T):
        slot = assign_views(P, tf.xyz_m[t][:, src], xy_px[:, t][:, :, shared], score[:, t][:, :, shared], cfg)
        have = slot >= 0  # (C,K)
        if not have.any():
            continue
        sl = np.where(have, slot, 0)
        cams = np.arange(C)[:, None]
        pts = xy_px[cams, t, sl][:, :, extra]  # (C,K,E,2)
        w = score[cams, t, sl][:, :, extra]  # (C,K,E)
        pts = np.where(have[:, :, None, None], pts, np.nan)
        w = np.where(have[:, :, None] & (w >= cfg.min_score), w, 0.0)
        r = tri(pts.reshape(C, K * E, 2), w.reshape(C, K * E))
        X = r.xyz_m.reshape(K, E, 3)
        ok = np.isfinite(X).all(-1)
        xyz[t][:, extra] = np.where(ok[..., None], X, np.nan)
        conf[t][:, extra] = np.where(ok, r.score.reshape(K, E), 0.0)
        std[t][:, extra] = np.where(ok, r.std_m.reshape(K, E), np.nan)
        flags[t][:, extra] = np.where(ok, OBSERVED, 0)


def _drop_far_from_parent(parents: np.ndarray, extra: list[int], max_bone_m: float, out) -> None:
    """A point farther than ``max_bone_m`` from its parent belongs to someone else (or to nobody)."""
    xyz, conf, std, flags = out
    for j in extra:
        p = int(parents[j])
        if p < 0:
            continue
        far = np.linalg.norm(xyz[:, :, j] - xyz[:, :, p], axis=-1) > max_bone_m
        xyz[:, :, j][far] = np.nan
        conf[:, :, j][far], std[:, :, j][far], flags[:, :, j][far] = 0.0, np.nan, 0


def attach_session_joints(
    lay, rig, sub, tf: TrackFile, skeleton: str, config: ExtraJointsConfig
) -> TrackFile:
    """:func:`attach_joints` for a session: the detections read again in the layout of ``skeleton``
    (``whole_body`` or a skeleton TOML, as the triangulate option) on the particle tracker's frame axis;
    ``sub`` is the rig the tracker ran on (the cameras with detections)."""
    sub2, mv = load_detections(lay, rig, skeleton=skeleton)
    if tuple(sub2.names) != tuple(sub.names) or not np.array_equal(mv.frame_index, tf.frame_index):
        raise ValueError(
            f"attach_session_joints: the {skeleton} detections are of cameras {list(sub2.names)} and "
            f"{len(mv.frame_index)} frames, the tracks of cameras {list(sub.names)} and {tf.n_frames} frames"
        )
    if tuple(mv.joint_names) == tuple(tf.joint_names):
        log.info("particle tracker: the detections' layouts add no joint to %s", skeleton)
        return tf
    return attach_joints(
        tf, sub.projection_matrices(), mv.xy_px, mv.score, tuple(mv.joint_names), mv.parents, config
    )
