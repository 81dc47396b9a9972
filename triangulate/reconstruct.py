"""Per-frame 3D poses from multi-view 2D poses: association (Algorithm 1) then robust DLT (sec. 4.2.1)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from roomcap.core.config import config_from_dict
from roomcap.triangulate.chunks import StreamConfig, split_stream_keys
from roomcap.triangulate.dlt import (
    _NVIEWS,
    _PER_VIEW,
    _REPROJ,
    _SCORE,
    _STD,
    DLTConfig,
    Triangulator,
    _limb_pairs,
    limb_outliers,
)
from roomcap.triangulate.geometry import check_shape, fundamental_from_P
from roomcap.triangulate.matching import MatchConfig, Matcher, finite_xy


def _mean_joint_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``evaluate.mean_joint_distance`` (same arithmetic, same bits) on coordinate planes:
    A (3,...,J), B (3,...,J) broadcast against each other -> (...) (all pairs of (3,G,J) and (3,K,J)
    poses: ``A[:, :, None]``, ``B[:, None]``)."""
    d = A - B  # (3,...,J)
    d *= d
    d2 = d[0] + d[1]
    d2 += d[2]
    d = np.sqrt(d2)  # = np.linalg.norm(A - B, axis=-1) of (G,K,J,3) arrays, NaN where either is missing
    ok = d == d
    n = np.count_nonzero(ok, -1)
    d[~ok] = 0.0
    return np.where(n > 0, np.add.reduce(d, -1) / np.maximum(n, 1), np.inf)


def flip_index(joint_names: tuple[str, ...]) -> np.ndarray:
    """(J,) permutation that swaps left_* and right_* joints."""
    idx = {n: i for i, n in enumerate(joint_names)}
    out = []
    for n in joint_names:
        m = n.replace("left_", "\0").replace("right_", "left_").replace("\0", "right_")
        out.append(idx.get(m, idx[n]))
    return np.asarray(out)


@dataclass(frozen=True)
class TriangulateConfig:
    """Settings of the triangulate stage.

    match / dlt: see :class:`MatchConfig`, :class:`DLTConfig`.
    min_joints_3d: 3D poses with fewer triangulated joints are dropped.
    limb_check: drop joints that make a limb implausibly short or long (``dlt.LIMB_BOUNDS_M``).
    fix_flips: let the matching mirror a 2D pose whose left/right labels are swapped (sec. 4.3.5).
    merge_dist_m: two 3D poses closer than this (mean joint distance) are one person seen as two
      hypotheses: with disjoint cameras they are merged and re-triangulated, else the one with
      fewer views is dropped (0 = off).
    skeleton: the 3D joints: ``body19`` (the default), or ``whole_body``: body19 plus every joint the
      detections' 2D layouts provide beyond it (feet, BODY_25B's upper neck and head top, BlazePose's
      hand points; :func:`roomcap.keypoints.skeletons.whole_body`), or the path of a skeleton TOML (a lab's
      own joints, animals included: :func:`roomcap.keypoints.skeletons.load_skeleton_toml`). The greedy
      tracker carries any of them; the particle tracker and forecasting work on body19.
    stream: the session in time chunks (:class:`roomcap.triangulate.chunks.StreamConfig`; the TOML's flat
      ``chunk_s``, ``workers`` and ``executor`` keys go there): frames are independent here, so ``workers``
      processes (or Ray tasks) triangulate chunks at once and the parts are those of one process.
    """

    match: MatchConfig = field(default_factory=MatchConfig)
    dlt: DLTConfig = field(default_factory=DLTConfig)
    min_joints_3d: int = 5
    limb_check: bool = True
    fix_flips: bool = True
    merge_dist_m: float = 0.25
    skeleton: str = "body19"
    stream: StreamConfig = field(default_factory=StreamConfig)

    def __post_init__(self) -> None:
        if self.skeleton not in ("body19", "whole_body") and not str(self.skeleton).endswith(".toml"):
            raise ValueError(
                f"TriangulateConfig.skeleton must be 'body19', 'whole_body' or a skeleton TOML file "
                f"(keypoints.skeletons.load_skeleton_toml), got {self.skeleton!r}."
            )

    @classmethod
    def from_dict(cls, d: dict) -> TriangulateConfig:
        own, stream = split_stream_keys(d)  # the match, dlt and stream sections by their dataclasses
        return config_from_dict(cls, {**own, "stream": stream} if stream else own)


@dataclass(frozen=True)
class FramePoses:
    """3D poses of one frame (M people, J joints, C cameras)."""

    xyz_m: np.ndarray  # (M,J,3)
    score: np.ndarray  # (M,J)
    reproj_err_px: np.ndarray  # (M,J)
    n_views: np.ndarray  # (M,J)
    std_m: np.ndarray  # (M,J)
    members: np.ndarray  # (M,C) pose index per camera or -1
    mirrored: np.ndarray  # (M,C) bool: the 2D pose was used left/right swapped
    reproj_err_cam_px: np.ndarray | None = (
        None  # (M,J,C) per camera, NaN = view not used (mean = reproj_err_px)
    )

    @classmethod
    def empty(cls, J: int, C: int) -> FramePoses:
        return cls(
            np.zeros((0, J, 3)),
            np.zeros((0, J)),
            np.zeros((0, J)),
            np.zeros((0, J), np.int16),
            np.zeros((0, J)),
            np.zeros((0, C), np.int64),
            np.zeros((0, C), bool),
            np.zeros((0, J, C)),
        )


class FrameReconstructor:
    """Holds a rig's precomputed P, F and normalisation; ``__call__`` reconstructs one frame.

    P: (C,3,4) projection matrices for undistorted pixels; F: (C,C,3,3) or None (computed from P);
    order: camera indices visited by the matching (default 0..C-1); joint_names: for the limb check.
    """

    def __init__(
        self,
        P: np.ndarray,
        F: np.ndarray | None = None,
        config: TriangulateConfig | None = None,
        order: np.ndarray | None = None,
        joint_names: tuple[str, ...] | None = None,
    ):
        self.config = config or TriangulateConfig()
        self.P = np.asarray(P, dtype=np.float64)
        check_shape("P", self.P, (None, 3, 4))
        if len(self.P) < 2:
            raise ValueError(f"triangulation needs at least 2 cameras, the rig has {len(self.P)}.")
        self.F = fundamental_from_P(self.P) if F is None else np.asarray(F, dtype=np.float64)
        check_shape("F", self.F, (len(self.P), len(self.P), 3, 3))
        self.order = order
        self.joint_names = joint_names
        self.tri = Triangulator(self.P, self.config.dlt)
        self.flip = None if joint_names is None else flip_index(joint_names)
        self.matcher = Matcher(self.F, self.config.match, order, self.flip if self.config.fix_flips else None)
        self._cams_col = np.arange(len(self.P))[:, None]
        self._arJ = None if joint_names is None else np.arange(len(joint_names))
        self._upper: dict[int, np.ndarray] = {}  # (M,M) strict upper-triangle masks by M
        self._c4 = self.tri.c.T[:, :, None, None]  # (2,C,1,1) principal points, for ``_planes``
        self._s4 = self.tri.s[:, None, None]  # (C,1,1) focal scales
        self._limbs = _limb_pairs(tuple(joint_names)) if self.config.limb_check and joint_names else None
        self._fill = np.full((_PER_VIEW + len(self.P), 1, 1), np.nan)  # what a dropped joint reads in V
        self._fill[[_SCORE, _NVIEWS]] = 0.0

    def _planes(self, xy: np.ndarray, score: np.ndarray, finite: np.ndarray) -> np.ndarray:
        """(4,C,P,J) per-frame planes the DLT reads: normalised x, y, confidence, seen (1/0), where
        finite = all coordinates finite; each hypothesis then gathers its rows in one indexing step
        (the DLT ignores the values of unseen joints)."""
        Z = np.empty((4,) + finite.shape)
        np.subtract(xy[..., 0], self._c4[0], out=Z[0])
        np.subtract(xy[..., 1], self._c4[1], out=Z[1])
        Z[:2] /= self._s4
        Z[2] = score
        np.logical_and(finite, score >= self.config.dlt.min_score, out=Z[3], casting="unsafe")
        Z[3] *= np.isfinite(score)
        return Z

    def _triangulate(self, Z: np.ndarray, H: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Triangulate hypotheses H (M,C) with mirror flags S (M,C) from the planes Z (``_planes``).
        Returns V (8+C,M,J) (rows of ``Triangulator.solve_raw``) and keep (M,J): the joints that
        passed the DLT's checks and the limb check."""
        C, J = len(self.P), Z.shape[-1]
        M = len(H)
        sel = np.maximum(H, 0).T[..., None]  # (C,M,1)
        if self.flip is not None and S.any():  # a mirrored pose reads its joints left/right swapped
            g = Z[:, self._cams_col[..., None], sel, np.where(S.T[..., None], self.flip, self._arJ)]
        else:
            g = Z[:, self._cams_col, sel[..., 0]]  # (4,C,M,J)
        g = g.reshape(4, C, M * J)
        seen = g[3] > 0
        seen &= (H >= 0).T.repeat(J, 1)
        V, ok, _ = self.tri.solve_raw(g[:2], np.where(seen, g[2], 0.0), seen)
        V, ok = V.reshape(len(V), M, J), ok.reshape(M, J)
        if self._limbs is not None:
            drop = limb_outliers(np.where(ok, V[:3], np.nan), V[_REPROJ], self._limbs)
            if drop is not None:
                ok[drop] = False
        return V, ok

    def _merge_duplicates(self, Z, H, S, V, keep):
        """Sec. 4.2.1 leaves a person split over two hypotheses when one view did not join; merge them."""
        X = np.where(keep, V[:3], np.nan)  # (3,M,J)
        M = len(H)
        # a mean joint distance below merge_dist_m needs a shared joint closer than that, so the
        # two poses' boxes (over their joints, any orientation) overlap within it on every axis
        lo, hi = np.fmin.reduce(X, axis=2), np.fmax.reduce(X, axis=2)  # (3,M), NaN for no joints
        gap = np.maximum(lo[:, None] - hi[:, :, None], lo[:, :, None] - hi[:, None])  # (3,M,M)
        cand = (gap < self.config.merge_dist_m).all(0)
        upper = self._upper.get(M)
        if upper is None:
            upper = self._upper[M] = np.triu(np.ones((M, M), bool), 1)
        cand &= upper  # pairs a < b only
        if not cand.any():
            return H, S, V, keep
        a_idx, b_idx = np.nonzero(cand)
        Xa, Xb = X[:, a_idx], X[:, b_idx]
        D = _mean_joint_distance(Xa, Xb)
        if self.flip is not None:  # the same person with left/right swapped (a mirrored hypothesis)
            Dm = _mean_joint_distance(Xa, Xb[:, :, self.flip])
            mirror = Dm < D
            D = np.minimum(D, Dm)
        else:
            mirror = np.zeros(D.shape, bool)
        close = D < self.config.merge_dist_m
        if not close.any():
            return H, S, V, keep
        a_idx, b_idx, D, mirror = a_idx[close], b_idx[close], D[close], mirror[close]
        alive = np.ones(len(H), bool)
        changed = np.zeros(len(H), bool)
        views = np.where(keep, V[_NVIEWS], 0).sum(1)
        for k in np.argsort(D):
            a, b = a_idx[k], b_idx[k]
            if not (alive[a] and alive[b]):
                continue
            ca, cb = H[a] >= 0, H[b] >= 0
            if not (ca & cb).any():
                H[a, cb], S[a, cb] = H[b, cb], S[b, cb] ^ mirror[k]
                alive[b], changed[a] = False, True
            else:
                alive[b if views[b] < views[a] else a] = False
        if changed.any():
            idx = np.flatnonzero(changed & alive)
            V[:, idx], keep[idx] = self._triangulate(Z, H[idx], S[idx])
        return H[alive], S[alive], V[:, alive], keep[alive]

    def __call__(self, xy_px: np.ndarray, score: np.ndarray) -> FramePoses:
        """xy_px: (C,P,J,2) undistorted pixels, NaN = missing; score: (C,P,J)."""
        xy = np.asarray(xy_px, dtype=np.float64)
        score = np.asarray(score, dtype=np.float64)
        C = len(self.P)
        check_shape("xy_px", xy, (C, None, None, 2))
        check_shape("score", score, xy.shape[:3])
        J = xy.shape[2]
        finite = finite_xy(xy)
        H, S = self.matcher.match(xy, score, finite)
        if len(H) == 0:
            return FramePoses.empty(J, C)
        Z = self._planes(xy, score, finite)
        V, keep = self._triangulate(Z, H, S)
        if self.config.merge_dist_m > 0 and len(H) > 1:
            H, S, V, keep = self._merge_duplicates(Z, H, S, V, keep)
        good = np.count_nonzero(keep, 1) >= self.config.min_joints_3d
        W = np.where(keep[good], V[:, good], self._fill)  # (8+C,M',J): NaN (0 for score, views) if dropped
        return FramePoses(
            xyz_m=W[:3].transpose(1, 2, 0),
            score=W[_SCORE],
            reproj_err_px=W[_REPROJ],
            n_views=W[_NVIEWS].astype(np.int16),
            std_m=W[_STD],
            members=H[good],
            mirrored=S[good],
            reproj_err_cam_px=W[_PER_VIEW:].transpose(1, 2, 0),
        )
