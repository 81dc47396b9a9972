"""Per-frame 3D poses from multi-view 2D poses: association (Algorithm 1) then robust DLT (sec. 4.2.1)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from triangulate.dlt import DLTConfig, Triangulator, _reject_unknown, limb_check
from triangulate.geometry import check_shape, fundamental_from_P
from triangulate.matching import MatchConfig, Matcher


def _mean_joint_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``evaluate.mean_joint_distance`` (same arithmetic, same bits) with fewer temporaries."""
    d = A[:, None] - B[None]
    d *= d
    d = np.sqrt(np.add.reduce(d, axis=-1))  # (G,K,J) = np.linalg.norm(A - B, axis=-1)
    ok = np.isfinite(d)
    n = ok.sum(-1)
    d[~ok] = 0.0
    return np.where(n > 0, d.sum(-1) / np.maximum(n, 1), np.inf)


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
    """

    match: MatchConfig = field(default_factory=MatchConfig)
    dlt: DLTConfig = field(default_factory=DLTConfig)
    min_joints_3d: int = 5
    limb_check: bool = True
    fix_flips: bool = True
    merge_dist_m: float = 0.25

    @classmethod
    def from_dict(cls, d: dict) -> TriangulateConfig:
        d = dict(_reject_unknown(cls, d))
        if "match" in d and isinstance(d["match"], dict):
            d["match"] = MatchConfig.from_dict(d["match"])
        if "dlt" in d and isinstance(d["dlt"], dict):
            d["dlt"] = DLTConfig.from_dict(d["dlt"])
        return cls(**d)


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

    @classmethod
    def empty(cls, J: int, C: int) -> FramePoses:
        return cls(np.zeros((0, J, 3)), np.zeros((0, J)), np.zeros((0, J)), np.zeros((0, J), np.int16),
                   np.zeros((0, J)), np.zeros((0, C), np.int64), np.zeros((0, C), bool))


class FrameReconstructor:
    """Holds a rig's precomputed P, F and normalisation; ``__call__`` reconstructs one frame.

    P: (C,3,4) projection matrices for undistorted pixels; F: (C,C,3,3) or None (computed from P);
    order: camera indices visited by the matching (default 0..C-1); joint_names: for the limb check.
    """

    def __init__(self, P: np.ndarray, F: np.ndarray | None = None, config: TriangulateConfig | None = None,
                 order: np.ndarray | None = None, joint_names: tuple[str, ...] | None = None):
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

    def _planes(self, xy: np.ndarray, score: np.ndarray) -> np.ndarray:
        """(4,C,P,J) per-frame planes the DLT reads: normalised x, y (0 where unseen), confidence
        (0 where unseen), seen (1/0); each hypothesis then gathers its rows in one indexing step."""
        seen = np.isfinite(xy).all(-1) & (score >= self.config.dlt.min_score) & np.isfinite(score)
        Z = np.empty((4,) + seen.shape)
        np.copyto(Z[:2], self.tri.normalised(xy))
        Z[:2][:, ~seen] = 0.0
        np.copyto(Z[2], np.where(seen, score, 0.0))
        Z[3] = seen
        return Z

    def _triangulate(self, Z: np.ndarray, H: np.ndarray, S: np.ndarray) -> dict:
        """Triangulate hypotheses H (M,C) with mirror flags S (M,C) from the planes Z (``_planes``);
        returns (M,...) arrays and keep (M,J)."""
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
        r = self.tri.solve(g[:2], np.where(seen, g[2], 0.0), seen)
        out = {"xyz_m": r.xyz_m.reshape(M, J, 3), "reproj_err_px": r.reproj_err_px.reshape(M, J),
               "score": r.score.reshape(M, J), "n_views": r.n_views.reshape(M, J),
               "std_m": r.std_m.reshape(M, J)}
        keep = out["n_views"] > 0  # = np.isfinite(xyz_m).all(-1): a kept joint has >= min_views views
        if self.config.limb_check and self.joint_names is not None:
            keep &= limb_check(out["xyz_m"], out["reproj_err_px"], self.joint_names)
        out["keep"] = keep
        return out

    def _merge_duplicates(self, Z, H, S, res):
        """Sec. 4.2.1 leaves a person split over two hypotheses when one view did not join; merge them."""
        X = np.where(res["keep"][..., None], res["xyz_m"], np.nan)
        M = len(X)
        if self.flip is not None:  # the same person with left/right swapped (a mirrored hypothesis)
            D2 = _mean_joint_distance(X, np.concatenate([X, X[:, self.flip]], 0))  # one pass for both
            D, Dm = D2[:, :M], D2[:, M:]
            mirror = Dm < D
            D = np.minimum(D, Dm)
        else:
            D = _mean_joint_distance(X, X)
            mirror = np.zeros(D.shape, bool)
        close = D < self.config.merge_dist_m
        upper = self._upper.get(M)
        if upper is None:
            upper = self._upper[M] = np.triu(np.ones((M, M), bool), 1)
        close &= upper  # pairs a < b only
        if not close.any():
            return H, S, res
        D[np.arange(M), np.arange(M)] = np.inf
        a_idx, b_idx = np.nonzero(close)
        alive = np.ones(len(H), bool)
        changed = np.zeros(len(H), bool)
        views = np.where(res["keep"], res["n_views"], 0).sum(1)
        for k in np.argsort(D[a_idx, b_idx]):
            a, b = a_idx[k], b_idx[k]
            if not (alive[a] and alive[b]):
                continue
            ca, cb = H[a] >= 0, H[b] >= 0
            if not (ca & cb).any():
                H[a, cb], S[a, cb] = H[b, cb], S[b, cb] ^ mirror[a, b]
                alive[b], changed[a] = False, True
            else:
                alive[b if views[b] < views[a] else a] = False
        if changed.any():
            idx = np.flatnonzero(changed & alive)
            sub = self._triangulate(Z, H[idx], S[idx])
            for k, v in sub.items():
                res[k][idx] = v
        return H[alive], S[alive], {k: v[alive] for k, v in res.items()}

    def __call__(self, xy_px: np.ndarray, score: np.ndarray) -> FramePoses:
        """xy_px: (C,P,J,2) undistorted pixels, NaN = missing; score: (C,P,J)."""
        xy = np.asarray(xy_px, dtype=np.float64)
        score = np.asarray(score, dtype=np.float64)
        C = len(self.P)
        check_shape("xy_px", xy, (C, None, None, 2))
        J = xy.shape[2]
        H, S = self.matcher(xy, score)
        if len(H) == 0:
            return FramePoses.empty(J, C)
        Z = self._planes(xy, score)
        res = self._triangulate(Z, H, S)
        if self.config.merge_dist_m > 0 and len(H) > 1:
            H, S, res = self._merge_duplicates(Z, H, S, res)
        keep = res["keep"]
        good = keep.sum(1) >= self.config.min_joints_3d
        keep &= good[:, None]
        nan = np.float64(np.nan)
        return FramePoses(
            xyz_m=np.where(keep[..., None], res["xyz_m"], nan)[good],
            score=np.where(keep, res["score"], 0)[good],
            reproj_err_px=np.where(keep, res["reproj_err_px"], nan)[good],
            n_views=np.where(keep, res["n_views"], 0).astype(np.int16, copy=False)[good],
            std_m=np.where(keep, res["std_m"], nan)[good], members=H[good], mirrored=S[good])
