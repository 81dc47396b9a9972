"""Per-frame 3D poses from multi-view 2D poses: association (Algorithm 1) then robust DLT (sec. 4.2.1)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from triangulate.dlt import DLTConfig, Triangulator, _reject_unknown, limb_check
from triangulate.geometry import check_shape, fundamental_from_P
from triangulate.matching import MatchConfig, match_frame


@dataclass(frozen=True)
class TriangulateConfig:
    """Settings of the triangulate stage.

    match / dlt: see :class:`MatchConfig`, :class:`DLTConfig`.
    min_joints_3d: 3D poses with fewer triangulated joints are dropped.
    limb_check: drop joints that make a limb implausibly short or long (``dlt.LIMB_BOUNDS_M``).
    """

    match: MatchConfig = field(default_factory=MatchConfig)
    dlt: DLTConfig = field(default_factory=DLTConfig)
    min_joints_3d: int = 5
    limb_check: bool = True

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

    @classmethod
    def empty(cls, J: int, C: int) -> FramePoses:
        return cls(np.zeros((0, J, 3)), np.zeros((0, J)), np.zeros((0, J)), np.zeros((0, J), np.int16),
                   np.zeros((0, J)), np.zeros((0, C), np.int64))


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

    def __call__(self, xy_px: np.ndarray, score: np.ndarray) -> FramePoses:
        """xy_px: (C,P,J,2) undistorted pixels, NaN = missing; score: (C,P,J)."""
        xy = np.asarray(xy_px, dtype=np.float64)
        C = len(self.P)
        check_shape("xy_px", xy, (C, None, None, 2))
        J = xy.shape[2]
        H = match_frame(xy, score, self.F, self.config.match, self.order)
        M = len(H)
        if M == 0:
            return FramePoses.empty(J, C)
        sel = np.maximum(H, 0).T  # (C,M)
        xy_h = xy[np.arange(C)[:, None], sel]  # (C,M,J,2)
        sc_h = np.asarray(score, dtype=np.float64)[np.arange(C)[:, None], sel]  # (C,M,J)
        miss = (H < 0).T
        xy_h[miss] = np.nan
        sc_h[miss] = 0.0
        r = self.tri(xy_h.reshape(C, M * J, 2), sc_h.reshape(C, M * J))
        xyz = r.xyz_m.reshape(M, J, 3)
        reproj = r.reproj_err_px.reshape(M, J)
        keep = np.isfinite(xyz).all(-1)
        if self.config.limb_check and self.joint_names is not None:
            keep &= limb_check(xyz, reproj, self.joint_names)
        good = keep.sum(1) >= self.config.min_joints_3d
        keep &= good[:, None]
        nan = np.float64(np.nan)
        return FramePoses(
            xyz_m=np.where(keep[..., None], xyz, nan)[good],
            score=np.where(keep, r.score.reshape(M, J), 0)[good],
            reproj_err_px=np.where(keep, reproj, nan)[good],
            n_views=np.where(keep, r.n_views.reshape(M, J), 0).astype(np.int16)[good],
            std_m=np.where(keep, r.std_m.reshape(M, J), nan)[good], members=H[good])
