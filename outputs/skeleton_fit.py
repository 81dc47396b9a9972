"""One skeleton per person: constant bone lengths, joint rotations by inverse kinematics.

The fit of a track file is kept in a versioned companion file ``<session>/track/skeleton_fit.npz``
beside ``tracks.npz`` (the track file itself is unchanged, so every reader of it keeps working):

- ``schema`` = ``"skeleton_fit/1"``, ``tracks_sha256`` (of the tracks.npz it was fitted on; a fit of
  another track file is refused), ``fps``, ``frame_index (T,)``, ``track_id (K,)``,
  ``joint_names (J,)``, ``parents (J,)`` (the track file's skeleton)
- ``bone_length_m (K,J)``: length of the bone parent(j) -> j, constant per person; NaN for the root
- ``rest_offset_m (K,J,3)``: offset of j from its parent in the rest pose (world axes, z up)
- ``root_xyz_m (T,K,3)``: root joint position; ``rotation_xyzw (T,K,J,4)``: rotation of joint j relative
  to its parent's frame, from the rest pose (quaternion x, y, z, w; BVH's local rotation). NaN outside
  the person's span (the frames from its first to its last known joint).
- ``fit_error_m (T,K,J)``: distance of the fitted joint to the track file's position (NaN where the
  track file does not know the joint); ``held (T,K,J)`` bool: the rotation was held from the previous
  frame (the joint's children unknown even after filling short gaps).

Method (the seeds are silent here; the choices are the usual ones of marker-based pipelines):

1. short gaps (<= ``max_gap`` frames) are filled by linear interpolation, as for the TRC;
2. bone lengths: the median over the frames in which both ends are OBSERVED with confidence >=
   ``min_confidence`` (all frames with both ends known when fewer than 5 are), then the mean of the
   left and right sides (``symmetric``);
3. rest pose: the bone directions of the person's most confident frame with every joint known
   (after filling), scaled to the bone lengths; the root's rotation is the identity there;
4. inverse kinematics per frame, top down from the root: each joint's rotation aligns its rest
   child offsets (and, for a joint with one child, the grandchild offsets at a quarter of the weight,
   which fixes the twist) with the observed directions from the fitted joint position (weighted
   Wahba/Kabsch); knees and elbows are hinges about their rest-pose bend axis with flexion limited to
   [-10, 150] degrees (the usual clinical range, hyperextension included), so a stretched limb never
   bends backwards; a joint with a single leaf child keeps the previous frame's twist;
5. refinement (``refine``, default on): weighted least squares over the root position and every
   rotation at once (residuals: fitted - tracked joint / max(std_m, 1 cm), as in OpenSim's IK; a
   prior of 0.5 rad on the change from step 4; hinge angles bounded), a few trust-region steps per
   frame; about 50-70 ms per person-frame on this machine.

Hands (the 42 joints of a whole-body track, :data:`roomcap.keypoints.skeletons.HANDS`) hang off the wrists,
4 bones per finger from the hand root. They are often unseen, so they are fitted beside the body, not as
part of it: the rest pose needs every BODY joint in one frame, and each hand's rest shape comes from that
hand's own best frame (most joints known), turned with the forearm onto the body's rest pose (a finger
joint unseen there continues its parent bone); a hand never seen keeps zero-length bones (NaN in
``bone_length_m``) and the identity. Per frame the refinement (5) runs on the body only, then the hand
joints (and a wrist whose only children are hand joints) are solved top down (4) from the refined wrist.
A track without hand joints fits exactly as before.

:func:`roomcap.outputs.bvh.write_bvh` writes the fit as BVH.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from roomcap.core.errors import FormatError
from roomcap.keypoints.skeletons import HANDS
from roomcap.outputs.skeleton_fit_file import FitError, SkeletonFit, file_sha256, fit_path, topological_order
from roomcap.track.trackfile import OBSERVED, TrackFile, track_index

# ----------------------------------------------------------------------------- gap filling


def person_span(tf: TrackFile, k: int) -> np.ndarray:
    """(T,) bool: frames in which track ``k`` has at least one known joint."""
    return tf.mask[:, k].any(-1)


def fill_gaps(xyz: np.ndarray, std: np.ndarray, max_gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation over interior NaN runs of at most ``max_gap`` frames, per joint.

    ``xyz (T,J,3)``, ``std (T,J)`` -> (filled xyz, filled std, ``filled (T,J)`` bool)."""
    xyz, std = xyz.copy(), std.copy()
    T, J = xyz.shape[:2]
    filled = np.zeros((T, J), bool)
    known = np.isfinite(xyz).all(-1)
    t = np.arange(T)
    for j in range(J):
        idx = np.flatnonzero(known[:, j])
        if len(idx) < 2:
            continue
        gaps = np.flatnonzero(np.diff(idx) > 1)
        for g in gaps:
            a, b = idx[g], idx[g + 1]
            if b - a - 1 > max_gap:
                continue
            tt = t[a + 1 : b]
            w = ((tt - a) / (b - a))[:, None]
            xyz[a + 1 : b, j] = (1 - w) * xyz[a, j] + w * xyz[b, j]
            sa, sb = std[a, j], std[b, j]
            std[a + 1 : b, j] = (1 - w[:, 0]) * sa + w[:, 0] * sb if np.isfinite(sa + sb) else np.nan
            filled[a + 1 : b, j] = True
    return xyz, std, filled


log = logging.getLogger(__name__)

HINGES = ("left_knee", "right_knee", "left_elbow", "right_elbow")
HINGE_LIMITS_DEG = (-10.0, 150.0)
# file axes of BVH and TRC: y up
YUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class FitOptions:
    max_gap: int = 10  # frames filled by interpolation before the fit
    min_confidence: float = 0.3
    symmetric: bool = True
    twist_weight: float = 0.25
    hinge_limits_deg: tuple[float, float] = HINGE_LIMITS_DEG
    refine: bool = True  # weighted least squares over all joint rotations after the top-down solution
    min_std_m: float = 0.01  # floor of the per-joint uncertainty weighting the refinement
    prior_rad: float = 0.5  # spread of the refinement's prior around the top-down rotations


def _children(parents) -> list[list[int]]:
    ch: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(np.asarray(parents).tolist()):
        if p >= 0:
            ch[p].append(j)
    return ch


def _mirror(name: str) -> str:
    return name.replace("left_", "\0").replace("right_", "left_").replace("\0", "right_")


# A child that moves against its parent's other children (the trunk against the hips, the head against
# the shoulders) hangs from a joint of its own at the parent's position (zero offset), named here.
ARTICULATED = {
    ("pelvis", "neck"): "spine",
    ("neck", "nose"): "head",
    ("neck", "head"): "head_neck",
    ("neck", "upper_neck"): "cervical",
}


def fit_skeleton(names, parents) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """The skeleton the fit and the BVH use: the track file's, plus a zero-offset joint between a
    multi-child joint and each child in :data:`ARTICULATED`.

    Returns ``(fit names (J',), fit parents (J',), index (J,) of each track joint in the fit)``."""
    names, parents = tuple(names), np.asarray(parents)
    n_children = np.bincount(parents[parents >= 0], minlength=len(names))
    out_names, out_parents, index = [], [], {}
    for j in topological_order(parents):
        p = int(parents[j])
        if p >= 0 and n_children[p] > 1 and (names[p], names[j]) in ARTICULATED:
            v = ARTICULATED[(names[p], names[j])]
            v = v if v not in names else f"{names[p]}_{names[j]}"
            out_names.append(v)
            out_parents.append(index[p])
            index[("v", j)] = len(out_names) - 1
            p_fit = index[("v", j)]
        else:
            p_fit = -1 if p < 0 else index[p]
        out_names.append(names[j])
        out_parents.append(p_fit)
        index[j] = len(out_names) - 1
    return (
        tuple(out_names),
        np.asarray(out_parents, np.int64),
        np.asarray([index[j] for j in range(len(names))]),
    )


# ----------------------------------------------------------------------------- rotations


def wahba(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray | None:
    """Rotation R minimising sum w |R a_i - b_i|^2 (a, b (N,3) unit vectors); None when degenerate."""
    H = (w[:, None, None] * a[:, :, None] * b[:, None, :]).sum(0)  # sum w a b^T
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-6 * max(S[0], 1e-12):
        return None
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction a to direction b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        return Rotation.from_rotvec(np.pi * perp / np.linalg.norm(perp)).as_matrix()
    return Rotation.from_rotvec(v / s * np.arctan2(s, c)).as_matrix()


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 1e-12, n, 1.0)


# ----------------------------------------------------------------------------- the fit


def _bone_lengths(tf: TrackFile, k: int, X: np.ndarray, rows: np.ndarray, opt: FitOptions) -> np.ndarray:
    J = len(tf.joint_names)
    L = np.full(J, np.nan)
    good = ((tf.flags[rows, k] & OBSERVED) > 0) & (tf.confidence[rows, k] >= opt.min_confidence)
    good &= np.isfinite(tf.xyz_m[rows, k]).all(-1)
    known = np.isfinite(X).all(-1)
    for j, p in enumerate(tf.parents.tolist()):
        if p < 0:
            continue
        both = good[:, j] & good[:, p]
        if both.sum() < 5:
            both = known[:, j] & known[:, p]
        if both.any():
            L[j] = float(np.median(np.linalg.norm(X[both, j] - X[both, p], axis=-1)))
    if opt.symmetric:
        idx = {n: i for i, n in enumerate(tf.joint_names)}
        sym = L.copy()
        for j, n in enumerate(tf.joint_names):
            m = idx.get(_mirror(n))
            if m is not None and m != j:
                vals = [v for v in (L[j], L[m]) if np.isfinite(v)]
                sym[j] = np.mean(vals) if vals else np.nan
        L = sym
    return L


def fit_track(tf: TrackFile, track: int, options: FitOptions = FitOptions()) -> dict[str, np.ndarray]:
    """Fit one person; returns arrays over the whole track file and the fit skeleton (module docstring)."""
    opt = options
    k = track_index(tf, track)
    T = tf.n_frames
    names, parents, jidx = fit_skeleton(tf.joint_names, tf.parents)
    F = len(names)
    real = np.zeros(F, bool)
    real[jidx] = True
    hand_t = np.isin(np.asarray(tf.joint_names), HANDS)  # (J,) hand joints of the track file
    rows, Xt, St, full = _complete_rows(tf, k, track, opt, need=~hand_t)
    Lt = _bone_lengths(tf, k, Xt, rows, opt)
    bad = [
        tf.joint_names[j]
        for j in range(len(tf.joint_names))
        if tf.parents[j] >= 0 and not np.isfinite(Lt[j]) and not hand_t[j]
    ]
    if bad:
        raise FitError(f"track {track}: no length for the bones to {bad}.")
    for side in ("left_", "right_"):  # a hand never seen gets no length from the other hand
        hs = hand_t & np.char.startswith(np.asarray(tf.joint_names), side)
        if hs.any() and not np.isfinite(Xt[:, hs]).any():
            Lt[hs] = np.nan
    X = np.full((len(rows), F, 3), np.nan)
    X[:, jidx] = Xt
    L = np.zeros(F)
    L[jidx] = np.nan_to_num(Lt)
    # rest pose: the most confident frame with every body joint known; virtual joints sit on their parent;
    # each hand from its own best frame, turned with the forearm
    conf = np.where(full, tf.confidence[rows, k][:, ~hand_t].sum(-1), -np.inf)  # the body's own confidence
    r0 = int(np.argmax(conf))
    Xr = X[r0].copy()
    hand = np.zeros(F, bool)
    hand[jidx[hand_t]] = True
    if hand.any():
        C = np.zeros((len(rows), F))
        C[:, jidx] = np.nan_to_num(tf.confidence[rows, k].astype(np.float64))
        Xr = _hand_rest(X, C, r0, Xr, names, parents)
    rest = _rest_offsets(Xr, L, parents, real)
    skel = _Skeleton(names, parents, real, rest, L, opt, hand)
    sig_rows = np.full((len(rows), F), np.inf)
    sig_rows[:, jidx] = np.maximum(np.nan_to_num(St, nan=opt.min_std_m), opt.min_std_m)
    rot, root_xyz, held = _fit_frames(skel, X, sig_rows)
    out_rot = np.full((T, F, 4), np.nan)
    out_root = np.full((T, 3), np.nan)
    out_held = np.zeros((T, F), bool)
    out_rot[rows], out_root[rows], out_held[rows] = rot, root_xyz, held
    L_out = L.copy()
    L_out[jidx[hand_t & ~np.isfinite(Lt)]] = np.nan  # a finger never seen: no length
    return {
        "bone_length_m": L_out,
        "rest_offset_m": rest,
        "root_xyz_m": out_root,
        "rotation_xyzw": out_rot,
        "held": out_held,
    }


def _complete_rows(tf: TrackFile, k: int, track: int, opt: FitOptions, need: np.ndarray | None = None):
    """The track's frames from its first to its last known joint, gaps filled: ``(rows, X, std, full)``;
    ``full``: the frames with every joint of ``need`` (default all) known; an error when there is none
    (the rest pose needs one)."""
    span = np.flatnonzero(person_span(tf, k))
    if not len(span):
        raise FitError(f"track {track} has no known joint in any frame; there is nothing to fit.")
    rows = np.arange(span[0], span[-1] + 1)
    Xt, St, _ = fill_gaps(
        tf.xyz_m[rows, k].astype(np.float64), tf.std_m[rows, k].astype(np.float64), opt.max_gap
    )
    need = np.ones(len(tf.joint_names), bool) if need is None else np.asarray(need, bool)
    known_t = np.isfinite(Xt).all(-1)
    full = known_t[:, need].all(-1)
    if not full.any():
        miss = np.where(need, (~known_t).mean(0), -1.0)
        worst = np.argsort(-miss)[:4]
        raise FitError(
            f"track {track} has no frame in which all {int(need.sum())} {'' if need.all() else 'body '}"
            f"joints are known, even after filling gaps of up to {opt.max_gap} frames (missing most often: "
            + ", ".join(f"{tf.joint_names[j]} {miss[j]:.0%}" for j in worst if miss[j] > 0)
            + "); the skeleton fit needs one for the rest pose. Export TRC/CSV/JSON instead, or track with "
            "a skeleton of the joints the cameras see."
        )
    return rows, Xt, St, full


def _hand_rest(X: np.ndarray, C: np.ndarray, r0: int, Xr: np.ndarray, names, parents) -> np.ndarray:
    """``Xr`` (the body's rest frame ``X[r0]``) with each hand's joints replaced by the hand's shape in its
    best frame (most joints known, then most confident: ``X (T,F,3)``, ``C (T,F)``), turned by the
    smallest rotation taking that frame's forearm (elbow -> wrist) to the rest frame's and moved onto
    the rest frame's wrist; a joint unknown there continues its parent bone (a palm bone: the forearm),
    a hand never seen collapses onto the wrist (zero-length bones)."""
    idx = {n: i for i, n in enumerate(names)}
    Xr = Xr.copy()
    known = np.isfinite(X).all(-1)
    for side in ("left", "right"):
        hj = [idx[n] for n in HANDS if n.startswith(f"{side}_") and n in idx]
        if not hj:
            continue
        w, e, root = idx.get(f"{side}_wrist"), idx.get(f"{side}_elbow"), idx.get(f"{side}_hand_root")
        if known[r0, hj].all():
            continue  # the body's rest frame sees this hand whole
        score = known[:, hj].sum(1) + 1e-3 * C[:, hj].sum(1)
        th = int(np.argmax(score))
        anchor = w if w is not None else parents[hj[0]]
        if not known[th, hj].any() or not known[th, anchor]:
            Xr[hj] = Xr[anchor]  # never seen: zero-length bones at the wrist
            continue
        R = np.eye(3)
        fore_r = Xr[w] - Xr[e] if w is not None and e is not None else np.zeros(3)
        if w is not None and e is not None and known[th, e] and np.linalg.norm(fore_r) > 1e-9:
            R = min_rotation(X[th, w] - X[th, e], fore_r)
        fore_dir = _unit(fore_r) if np.linalg.norm(fore_r) > 1e-9 else np.array([0.0, 0.0, -1.0])
        for j in topological_order(parents):
            if j not in hj:
                continue
            p = parents[j]
            if known[th, j] and known[th, p]:
                Xr[j] = Xr[p] + R @ (X[th, j] - X[th, p])
            elif j == root:
                Xr[j] = Xr[p]
            else:  # unseen in that frame: straight on from the parent bone (a palm bone: the forearm)
                gp = parents[p]
                d = Xr[p] - Xr[gp] if names[p] != f"{side}_hand_root" else fore_dir
                Xr[j] = Xr[p] + 0.03 * _unit(d if np.linalg.norm(d) > 1e-9 else fore_dir)
    return Xr


def _rest_offsets(Xr: np.ndarray, L: np.ndarray, parents: np.ndarray, real: np.ndarray) -> np.ndarray:
    """Each joint's offset from its parent in the rest pose ``Xr`` at its bone length (virtual joints,
    which sit on their parent, and the root: zero)."""
    Xr = Xr.copy()
    for j in topological_order(parents):
        if not real[j]:
            Xr[j] = Xr[parents[j]]
    root = int(np.flatnonzero(parents < 0)[0])
    rest = np.zeros((len(parents), 3))
    for j in range(len(parents)):
        if j != root and real[j]:
            rest[j] = L[j] * _unit(Xr[j] - Xr[parents[j]])
    return rest


class _Skeleton:
    """The fit skeleton: its joints, rest offsets, bone lengths, joint order and hinge axes."""

    def __init__(self, names, parents, real, rest, L, opt: FitOptions, hand=None) -> None:
        self.parents, self.real, self.rest, self.opt = parents, real, rest, opt
        self.root = int(np.flatnonzero(parents < 0)[0])
        self.children = _children(parents)
        self.order = topological_order(parents)
        # hand joints, and the joints solved with them after the body's refinement (a wrist whose only
        # children are hand joints)
        self.hand = np.zeros(len(parents), bool) if hand is None else np.asarray(hand, bool)
        self.after = self.hand | np.array([bool(c) and bool(self.hand[c].all()) for c in self.children])
        self.body_order = [j for j in self.order if not self.hand[j]]
        self.hinge_axis = {}
        for j in range(len(names)):
            if names[j] in HINGES and len(self.children[j]) == 1:
                ax = np.cross(rest[j], rest[self.children[j][0]])
                if np.linalg.norm(ax) > 1e-3 * L[j] * L[self.children[j][0]]:
                    self.hinge_axis[j] = ax / np.linalg.norm(ax)
        self.limits = tuple(np.deg2rad(opt.hinge_limits_deg))


def _fit_frames(skel: _Skeleton, X: np.ndarray, sig_rows: np.ndarray):
    """Every frame's root position and joint rotations, each frame starting from the previous one's:
    ``(rotation_xyzw (T,F,4), root_xyz (T,3), held (T,F))``."""
    opt, root, F = skel.opt, skel.root, len(skel.parents)
    known = np.isfinite(X).all(-1)
    Tn = len(X)
    rot = np.full((Tn, F, 4), np.nan)
    root_xyz = np.full((Tn, 3), np.nan)
    held = np.zeros((Tn, F), bool)
    Lprev = np.tile(np.eye(3), (F, 1, 1))
    root_prev = None
    for t in range(Tn):
        x, kn = X[t], known[t]
        P = np.empty((F, 3))
        P[root] = x[root] if kn[root] else (root_prev if root_prev is not None else np.nan)
        Lcur = _frame_rotations(skel, x, kn, P, Lprev, held[t])
        if not np.isfinite(P[root]).all():
            continue
        kb = kn & ~skel.hand
        if opt.refine and kb.sum() >= 3:
            P[root], Lcur = _refine(x, kb, sig_rows[t], P[root], Lcur, skel.rest, skel.parents,
                                    skel.body_order, skel.children, skel.hinge_axis, skel.limits,
                                    opt.prior_rad, frozen=skel.after)  # fmt: skip
            if skel.after.any():  # the hands, top down from the refined wrists
                held[t, skel.after] = False
                Lcur = _frame_rotations(skel, x, kn, P, Lprev, held[t], start=Lcur, only=skel.after)
        root_prev = P[root].copy()
        Lprev = Lcur
        root_xyz[t] = P[root]
        rot[t] = Rotation.from_matrix(Lcur).as_quat()
    first = np.flatnonzero(np.isfinite(root_xyz).all(-1))
    if len(first) and first[0] > 0:  # frames before the root was first known: the first fitted pose
        root_xyz[: first[0]] = root_xyz[first[0]]
        rot[: first[0]] = rot[first[0]]
        held[: first[0]] = True
    return rot, root_xyz, held


def _frame_rotations(
    skel: _Skeleton,
    x: np.ndarray,
    kn: np.ndarray,
    P: np.ndarray,
    Lprev: np.ndarray,
    held: np.ndarray,
    start: np.ndarray | None = None,
    only: np.ndarray | None = None,
) -> np.ndarray:
    """One frame's local rotations, root to leaves: each joint turned so its children point at the
    observed ones (a hinge about its axis within its limits); ``P`` gets the joints' positions, ``held``
    the joints kept at the previous frame's rotation. With ``only`` (F,) bool, the other joints keep
    their rotation in ``start``."""
    parents, rest, children, real = skel.parents, skel.rest, skel.children, skel.real
    lo, hi = skel.limits
    Lcur = (Lprev if start is None else start).copy()
    G = np.empty((len(parents), 3, 3))
    for j in skel.order:
        p = parents[j]
        Gp = np.eye(3) if p < 0 else G[p]
        if p >= 0:
            P[j] = P[p] + Gp @ rest[j]
        if only is not None and not only[j]:
            G[j] = Gp @ Lcur[j]
            continue
        ch = children[j]
        a, b, w = [], [], []
        for c in ch:
            if kn[c]:
                a.append(rest[c])
                b.append(Gp.T @ (x[c] - P[j]))
                w.append(1.0)
            if len(ch) == 1 or not real[c]:  # grandchildren fix the twist / the tilt
                for g in children[c]:
                    if kn[g]:
                        a.append(rest[c] + rest[g])
                        b.append(Gp.T @ (x[g] - P[j]))
                        w.append(skel.opt.twist_weight)
        R = None
        hinge = j in skel.hinge_axis and kn[ch[0]]
        if hinge:
            ax, o, u = skel.hinge_axis[j], rest[ch[0]], b[0]
            u_p, o_p = u - ax * (ax @ u), o - ax * (ax @ o)
            if np.linalg.norm(u_p) > 1e-9:
                phi0 = np.arctan2(ax @ np.cross(rest[j], o), rest[j] @ o)
                theta = np.arctan2(ax @ np.cross(o_p, u_p), o_p @ u_p)
                theta = np.clip(phi0 + theta, lo, hi) - phi0
                R = Rotation.from_rotvec(ax * theta).as_matrix()
        else:  # a zero-length bone (a hand root on its wrist) or a child on the joint gives no direction
            keep = [k for k in range(len(a)) if np.linalg.norm(a[k]) > 1e-9 and np.linalg.norm(b[k]) > 1e-9]
            a, b, w = [a[k] for k in keep], [b[k] for k in keep], [w[k] for k in keep]
        if not hinge and len(a) >= 2:
            R = wahba(_unit(np.asarray(a)), _unit(np.asarray(b)), np.asarray(w))
        if R is None and len(a) >= 1:  # one direction: swing from the previous frame's rotation
            R = min_rotation(Lprev[j] @ a[0], b[0]) @ Lprev[j]
        if R is None:
            held[j] = bool(ch)
            R = Lprev[j]
        Lcur[j] = R
        G[j] = Gp @ R
    return Lcur


def _rodrigues(v: np.ndarray) -> np.ndarray:
    """Rotation vectors (...,3) -> matrices (...,3,3)."""
    th = np.linalg.norm(v, axis=-1)[..., None, None]
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0, np.sin(ths) / ths)
    B = np.where(small, 0.5, (1 - np.cos(ths)) / ths**2)
    return np.eye(3) + A * K + B * (K @ K)


def _refine(
    x, kn, sig, root_p, L0, rest, parents, order, children, hinge_axis, limits, prior_rad, frozen=None
):
    """Weighted least squares (positions / sigma, plus a prior on the change of each rotation) over
    the root position and every rotating joint (but ``frozen``), from the top-down solution; hinges keep
    one angle inside ``limits`` (flexion). ``order``: the joints the positions are computed for (their
    parents first), those observed in ``kn`` the residuals. Returns (root position, local rotations
    (F,3,3))."""
    F = len(parents)
    layout, x0, lb, ub = _refine_parameters(root_p, L0, rest, order, children, hinge_axis, limits, frozen)
    n = len(x0)
    hinge = {j: hinge_axis[j] for j, _, m, _ in layout if m == 1}
    obs = np.flatnonzero(kn & np.isfinite(sig))
    w = 1.0 / sig[obs]

    j3 = [j for j, _, m, _ in layout if m == 3]
    c3 = np.asarray([[a, a + 1, a + 2] for _, a, m, _ in layout if m == 3], np.int64).reshape(-1, 3)
    j1 = [j for j, _, m, _ in layout if m == 1]
    c1 = np.asarray([a for _, a, m, _ in layout if m == 1], np.int64)
    ax1 = np.asarray([hinge[j] for j in j1]).reshape(-1, 3)

    def locals_(q: np.ndarray) -> np.ndarray:  # q (B,n) -> (B,F,3,3)
        B = len(q)
        L = np.broadcast_to(L0, (B, F, 3, 3)).copy()
        if j3:
            L[:, j3] = L0[j3] @ _rodrigues(q[:, c3])
        if j1:
            L[:, j1] = _rodrigues(q[:, c1, None] * ax1)
        return L

    def fk(q: np.ndarray) -> np.ndarray:  # (B,n) -> (B,F,3)
        L = locals_(q)
        B = len(q)
        G = np.empty((B, F, 3, 3))
        P = np.empty((B, F, 3))
        for j in order:
            p = parents[j]
            if p < 0:
                G[:, j], P[:, j] = L[:, j], q[:, :3]
            else:
                P[:, j] = P[:, p] + G[:, p] @ rest[j]
                G[:, j] = G[:, p] @ L[:, j]
        return P

    def prior(q: np.ndarray) -> np.ndarray:
        d = [q[:, a : a + m] - (x0[a : a + m] if m == 1 else 0.0) for _, a, m, _ in layout]
        return np.concatenate(d, 1) / prior_rad

    def res_batch(q: np.ndarray) -> np.ndarray:
        P = fk(q)
        r = ((P[:, obs] - x[obs]) * w[None, :, None]).reshape(len(q), -1)
        return np.concatenate([r, prior(q)], 1)

    def fun(q):
        return res_batch(q[None])[0]

    def jac(q):
        h = 1e-6
        Q = np.repeat(q[None], n + 1, 0)
        Q[1:] += np.eye(n) * h
        R = res_batch(Q)
        return ((R[1:] - R[0]) / h).T

    sol = least_squares(fun, x0, jac=jac, bounds=(lb, ub), method="trf", max_nfev=8, x_scale=1.0)
    L = locals_(sol.x[None])[0]
    return sol.x[:3].copy(), L


def _refine_parameters(root_p, L0, rest, order, children, hinge_axis, limits, frozen=None):
    """The parameters of :func:`_refine`: the root position, then per rotating joint (of ``order``, not
    ``frozen``) a hinge angle (bounded by ``limits`` about its rest angle) or a rotation vector;
    ``(layout, x0, lower, upper)`` with ``layout`` rows ``(joint, first parameter, count, rest angle)``."""
    lo, hi = limits
    layout, n = [], 3
    x0, lb, ub = list(root_p), [-np.inf] * 3, [np.inf] * 3
    for j in (j for j in order if children[j] and (frozen is None or not frozen[j])):
        if j in hinge_axis:
            c = children[j][0]
            ax, o = hinge_axis[j], rest[c]
            phi0 = np.arctan2(ax @ np.cross(rest[j], o), rest[j] @ o)
            th0 = Rotation.from_matrix(L0[j]).as_rotvec() @ ax
            layout.append((j, n, 1, phi0))
            x0.append(th0)
            lb.append(lo - phi0 - 1e-9)
            ub.append(hi - phi0 + 1e-9)
            n += 1
        else:
            layout.append((j, n, 3, 0.0))
            x0 += [0.0, 0.0, 0.0]
            lb += [-np.inf] * 3
            ub += [np.inf] * 3
            n += 3
    x0 = np.clip(np.asarray(x0), np.asarray(lb) + 1e-12, np.asarray(ub) - 1e-12)
    return layout, x0, lb, ub


def fit_skeletons(
    tf: TrackFile,
    track_ids: list[int] | None = None,
    options: FitOptions = FitOptions(),
    tracks_sha256: str = "",
    skip_unfittable: bool = False,
) -> SkeletonFit:
    """Fit every track (or ``track_ids``) of ``tf``; :class:`FitError` names a track that cannot be fitted
    (with ``skip_unfittable`` such a track is left out and named in ``notes``)."""
    ids = tf.track_id.tolist() if track_ids is None else [int(i) for i in track_ids]
    names, parents, jidx = fit_skeleton(tf.joint_names, tf.parents)
    T, F = tf.n_frames, len(names)
    res, kept, notes = [], [], []
    for i in ids:
        try:
            res.append(fit_track(tf, i, options))
            kept.append(i)
        except FitError as e:
            if not skip_unfittable:
                raise
            notes.append(str(e))
    ids, K = kept, len(kept)

    def stack(key, axis, shape):
        return np.stack([r[key] for r in res], axis) if K else np.zeros(shape)

    fit = SkeletonFit(
        fps=tf.fps,
        frame_index=tf.frame_index.copy(),
        track_id=np.asarray(ids, np.int64),
        joint_names=names,
        parents=parents,
        track_joints=jidx,
        bone_length_m=stack("bone_length_m", 0, (0, F)),
        rest_offset_m=stack("rest_offset_m", 0, (0, F, 3)),
        root_xyz_m=stack("root_xyz_m", 1, (T, 0, 3)),
        rotation_xyzw=stack("rotation_xyzw", 1, (T, 0, F, 4)),
        fit_error_m=np.zeros((T, K, len(jidx))),
        held=stack("held", 1, (T, 0, F)).astype(bool),
        tracks_sha256=tracks_sha256,
        notes=tuple(notes),
    )
    ks = [track_index(tf, i) for i in ids]
    err = np.linalg.norm(fit.joint_positions() - tf.xyz_m[:, ks].astype(np.float64), axis=-1)
    object.__setattr__(fit, "fit_error_m", err)
    return fit


def load_or_fit(
    tracks_path: str | os.PathLike, tf: TrackFile | None = None, track_ids: list[int] | None = None
) -> tuple[SkeletonFit, bool]:
    """The companion fit of ``tracks_path`` if it is there, current and has ``track_ids``, else a fit
    (of ``track_ids``, default all) made now. Returns (fit, made_now)."""
    tracks_path = Path(tracks_path)
    sha = file_sha256(tracks_path)
    comp = fit_path(tracks_path)
    if comp.exists():
        try:
            fit = SkeletonFit.load(comp, tracks_sha256=sha)
            if track_ids is None or set(track_ids) <= set(fit.track_id.tolist()):
                return fit, False
        except FormatError as e:
            log.warning("%s; fitting again", e)
    tf = tf or TrackFile.load(tracks_path)
    return fit_skeletons(tf, track_ids=track_ids, tracks_sha256=sha, skip_unfittable=track_ids is None), True
