"""The first guess of a rig's extrinsics: each camera's board pose per frame (PnP), the relative pose of
every pair of cameras that saw the board together (a robust mean), and the pose graph's spanning tree from
the best-linked camera (the reference). :mod:`roomcap.calibrate.extrinsics` refines it by bundle adjustment.

Transforms are 4x4 matrices named ``a_from_b`` (``x_a = T @ x_b``); metres.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from roomcap.calibrate.boards import Board, CalibrationError
from roomcap.calibrate.camera import Camera
from roomcap.calibrate.detect import CameraDetections

# ----------------------------------------------------------------------------- small geometry


def transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4x4 transform of rotation ``R`` and translation ``t``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """The inverse of a rigid 4x4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    return transform(R.T, -R.T @ t)


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle of rotation ``R``, degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``M`` (SVD; a reflection flipped)."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


# ----------------------------------------------------------------------------- per-camera board poses


def board_poses(
    board: Board, cam: Camera, det: CameraDetections, min_points: int = 6
) -> dict[int, tuple[np.ndarray, float, int]]:
    """cam_from_board (4,4) of every frame with >= min_points points (PnP on undistorted points,
    IPPE then Levenberg-Marquardt). Returns frame -> (T, rms_px, n_points)."""
    import cv2

    obj = board.object_points()
    out = {}
    for k, f in enumerate(det.frames):
        seen = np.isfinite(det.xy_px[k, :, 0])
        if seen.sum() < min_points:
            continue
        und = cam.undistort_px(det.xy_px[k, seen])
        o = obj[seen].astype(np.float64)
        ok, rv, tv = cv2.solvePnP(o, und, cam.K, None, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            continue
        rv, tv = cv2.solvePnPRefineLM(o, und, cam.K, None, rv, tv)
        R = cv2.Rodrigues(rv)[0]
        if tv[2, 0] <= 0:
            continue
        T = transform(R, tv.ravel())
        proj = cam.replace(R=R, t=tv.ravel()).project(o)
        rms = float(np.sqrt(np.mean(np.sum((proj - det.xy_px[k, seen]) ** 2, 1))))
        out[int(f)] = (T, rms, int(seen.sum()))
    return out


# ----------------------------------------------------------------------------- pose graph


def _robust_mean(
    Ts: list[np.ndarray], rot_tol_deg: float = 5.0, rel_t_tol: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Robust average of rigid transforms: the medoid (least summed rotation + translation distance),
    then the mean of those within tolerance of it. Returns (T, inlier mask)."""
    n = len(Ts)
    R = np.stack([T[:3, :3] for T in Ts])
    t = np.stack([T[:3, 3] for T in Ts])
    scale = max(float(np.median(np.linalg.norm(t, axis=1))), 1e-3)
    # pairwise chordal rotation distance and relative translation distance
    dR = np.linalg.norm((R[:, None] - R[None]).reshape(n, n, 9), axis=2)
    dt = np.linalg.norm(t[:, None] - t[None], axis=2) / scale
    med = int(np.argmin((dR + dt).sum(1)))
    ang = np.array([rotation_angle_deg(R[med].T @ R[i]) for i in range(n)])
    inl = (ang < rot_tol_deg) & (np.linalg.norm(t - t[med], axis=1) < rel_t_tol * scale + 0.01)
    Rm = nearest_rotation(R[inl].sum(0))
    tm = t[inl].mean(0)
    return transform(Rm, tm), inl


def board_symmetry(board: Board) -> np.ndarray | None:
    """For a checkerboard, the 180-degree turn about the board normal that maps point k to point N-1-k
    (4,4): its corner order is ambiguous, so two cameras may number the same corners in opposite orders.
    None for boards with unique ids (ChArUco, ArUco grid)."""
    if board.kind != "checkerboard":
        return None
    W = (board.grid[0] - 1) * board.square_size_m
    H = (board.grid[1] - 1) * board.square_size_m
    return np.array([[-1.0, 0, 0, W], [0, -1.0, 0, H], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])


def pairwise_links(
    poses: Sequence[Mapping[int, tuple]], max_per_pair: int = 200, sym: np.ndarray | None = None
) -> tuple[np.ndarray, dict[tuple[int, int], np.ndarray]]:
    """Relative poses from frames where two cameras see the board at once.
    Returns links (C,C): consistent frames per pair, and (i,j) -> cam_i_from_cam_j (4,4) for i<j.
    With a board symmetry ``sym`` each frame gives two candidates (camera j's numbering as is or turned);
    the consistent one of each frame joins the robust mean, the other is an outlier."""
    C = len(poses)
    links = np.zeros((C, C), np.int64)
    rel = {}
    for i in range(C):
        for j in range(i + 1, C):
            common = sorted(set(poses[i]) & set(poses[j]))
            if not common:
                continue
            if len(common) > max_per_pair:
                common = [common[k] for k in np.linspace(0, len(common) - 1, max_per_pair).astype(int)]
            Ts = [poses[i][f][0] @ inverse(poses[j][f][0]) for f in common]
            if sym is not None:
                Ts += [poses[i][f][0] @ inverse(poses[j][f][0] @ sym) for f in common]
            T, inl = _robust_mean(Ts)
            if sym is not None:
                inl = inl[: len(common)] | inl[len(common) :]
            links[i, j] = links[j, i] = int(inl.sum())
            rel[(i, j)] = T
    return links, rel


def _components(C: int, links: np.ndarray) -> list[list[int]]:
    parent = list(range(C))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i in range(C):
        for j in range(i + 1, C):
            if links[i, j] > 0:
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(C):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values(), key=lambda g: (-len(g), g))


def initial_poses(
    names: Sequence[str], links: np.ndarray, rel: Mapping[tuple[int, int], np.ndarray], n_seen: Sequence[int]
) -> tuple[int, list[np.ndarray]]:
    """cam_from_ref (4,4) per camera by composing relative poses along the maximum spanning tree of the
    link graph (weights = consistent shared frames), rooted at the best-linked camera. Unlinked cameras
    raise CalibrationError naming the groups and what to record."""
    C = len(names)
    groups = _components(C, links)
    if len(groups) > 1:
        never = [names[i] for i in range(C) if n_seen[i] == 0]
        gtxt = "; ".join("[" + ", ".join(names[i] for i in g) + "]" for g in groups)
        main = groups[0]
        others = [names[i] for g in groups[1:] for i in g]
        msg = (
            f"The cameras form {len(groups)} groups that never saw the board at the same time: {gtxt}. "
            f"The extrinsics of {others} relative to {[names[i] for i in main]} cannot be found. "
        )
        if never:
            msg += (
                f"Cameras {never} never saw the board at all: check they point at the capture area and the "
                "board is large enough in their image (or pass --exclude to leave them out). "
            )
        msg += (
            "Record a clip where the board is visible to a camera of each group at once (hold it where their "
            "views overlap, turned towards both), then calibrate again with both recordings."
        )
        raise CalibrationError(msg)
    root = int(np.argmax(links.sum(1)))
    cam_from_ref: list[np.ndarray | None] = [None] * C
    cam_from_ref[root] = np.eye(4)
    in_tree = {root}
    while len(in_tree) < C:
        best = None
        for i in in_tree:
            for j in range(C):
                if j not in in_tree and links[i, j] > 0 and (best is None or links[i, j] > best[2]):
                    best = (i, j, links[i, j])
        assert best is not None
        i, j, _ = best
        i_from_j = rel[(i, j)] if i < j else inverse(rel[(j, i)])
        cam_from_ref[j] = inverse(i_from_j) @ cam_from_ref[i]
        in_tree.add(j)
    return root, [T for T in cam_from_ref]  # type: ignore[misc]
