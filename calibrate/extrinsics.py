"""Extrinsics: from the first guess of :mod:`roomcap.calibrate.pose_graph` (board poses per camera, pairwise
relative poses, a robust pose graph), a global bundle adjustment over all cameras and board poses with
pycolmap's Ceres bundle adjuster, outliers dropped, then the world frame.

The bundle adjustment is set up as a COLMAP *rig*: every camera is a sensor with ``cam_from_rig``
(the rig frame is the reference camera's), every time instant is a frame whose ``rig_from_world``
is the board pose (``ref_from_board``), and the board points are constant 3D points in the board
frame. So the board stays rigid, its size fixes the scale, and the residuals are exactly
``project_c(cam_from_ref_c @ ref_from_board_f @ X_k) - x_ckf``.

Transforms are 4x4 matrices named ``a_from_b`` (``x_a = T @ x_b``); metres.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from roomcap.calibrate.boards import Board, CalibrationError
from roomcap.calibrate.camera import Camera, CameraRig
from roomcap.calibrate.detect import CameraDetections
from roomcap.calibrate.pose_graph import (
    board_poses,
    board_symmetry,
    initial_poses,
    inverse,
    nearest_rotation,
    pairwise_links,
    rotation_angle_deg,
    transform,
)
from roomcap.core.progress import Progress

log = logging.getLogger(__name__)

__all__ = [
    "ExtrinsicsConfig",
    "ExtrinsicsResult",
    "calibrate_extrinsics",
    "board_fit_rms",
    "bundle_adjust",
    "LOSSES",
    "FLIP_BOARD_Z_UP",
]

LOSSES = ("trivial", "soft_l1", "cauchy", "huber")
# board frame (x right, y down the print, z into the board) -> world with z up when the board lies face up
FLIP_BOARD_Z_UP = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class ExtrinsicsConfig:
    loss: str = "soft_l1"  # robust loss of the bundle adjustment
    loss_scale_px: float = 1.0
    refine_intrinsics: str = "none"  # "none" | "focal_pp" | "all"
    max_frames: int = 300  # time instants (seen by >= 2 cameras) given to the adjustment
    min_points: int = 6
    outlier_px: float = 4.0  # observations above max(outlier_px, 5 x median) are dropped, BA rerun
    max_iterations: int = 100
    world: str = ""  # "" = first camera; "camera:NAME"; "board:FRAME" (board on the floor)
    single_view_frames: int = 40  # per camera, frames only it saw, added when refining intrinsics
    function_tolerance: float = 1e-6  # Ceres: stop when the cost changes by less than this fraction
    linear_solver: str = "sparse_normal_cholesky"  # or "auto" (COLMAP's choice), "dense_normal_cholesky", ...

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss {self.loss!r} is not one of {list(LOSSES)}")
        if self.refine_intrinsics not in ("none", "focal_pp", "all"):
            raise ValueError(
                f"refine_intrinsics {self.refine_intrinsics!r} is not one of ['none','focal_pp','all']"
            )
        if self.world and not (self.world.startswith("camera:") or self.world.startswith("board:")):
            raise ValueError(f"world {self.world!r} must be '', 'camera:NAME' or 'board:FRAME'")


@dataclass(frozen=True)
class ExtrinsicsResult:
    """rig: calibrated cameras in the world frame. frames: (B,) time instants used; world_from_board: (B,4,4).
    links: (C,C) number of frames both cameras saw the board (consistent ones, after outlier rejection).
    per_camera_rms_px / per_camera_obs: (C,) after the adjustment."""

    rig: CameraRig
    frames: np.ndarray
    world_from_board: np.ndarray
    links: np.ndarray
    per_camera_rms_px: np.ndarray
    per_camera_obs: np.ndarray
    per_camera_frames: np.ndarray
    initial_rms_px: float
    final_rms_px: float
    ba_time_s: float
    ba_iterations: int
    n_outliers: int
    world: str
    residuals_px: dict = field(default_factory=dict, repr=False)  # camera -> (M,) final errors


# ----------------------------------------------------------------------------- bundle adjustment


def _colmap_camera(cam: Camera, camera_id: int):
    import pycolmap

    K, d = cam.K, cam.dist
    f = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    if cam.model == "fisheye":
        model, params = "OPENCV_FISHEYE", f + list(d)
    elif d.size == 0:
        model, params = "PINHOLE", f
    elif d.size == 4 or (d.size == 5 and d[4] == 0.0):
        model, params = "OPENCV", f + list(d[:4])  # k3 = 0: COLMAP's OPENCV model is exact
    elif d.size in (5, 8):
        dd = np.zeros(8)
        dd[: d.size] = d
        model, params = "FULL_OPENCV", f + list(dd)
    else:
        raise CalibrationError(
            f"Camera '{cam.name}': {d.size} distortion coefficients (thin-prism/tilted) are not "
            "supported by the bundle adjustment; calibrate the intrinsics with --model pinhole "
            "or rational."
        )
    return pycolmap.Camera(
        camera_id=camera_id, model=model, width=cam.size_wh[0], height=cam.size_wh[1], params=params
    )


def _camera_from_colmap(cam: Camera, cc) -> Camera:
    p = np.asarray(cc.params, float)
    K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
    d = p[4:]
    if cam.model == "pinhole" and cam.dist.size == 5:
        d = np.append(d, 0.0) if d.size == 4 else d[:5] if np.all(d[5:] == 0) else d
    return cam.replace(K=K, dist=d)


@dataclass
class _Obs:
    cam: int
    frame: int
    ids: np.ndarray  # (M,) board point ids
    xy: np.ndarray  # (M,2)


def bundle_adjust(
    board: Board,
    cams: Sequence[Camera],
    cam_from_ref: Sequence[np.ndarray],
    ref_index: int,
    *,
    frames: Sequence[int],
    ref_from_board: Mapping[int, np.ndarray],
    obs: Sequence[_Obs],
    cfg: ExtrinsicsConfig,
    refine_cameras: bool = True,
) -> tuple[list[Camera], list[np.ndarray], dict[int, np.ndarray], dict]:
    """One pycolmap/Ceres bundle adjustment (see module doc). Returns cameras (intrinsics possibly
    refined), cam_from_ref, ref_from_board and a summary dict."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    sensor = _add_rig(rec, cams, cam_from_ref, ref_index)
    pids, frame_ids = _add_frames(rec, board, frames, ref_from_board, obs)
    opts = _ba_options(cfg, refine_cameras)
    ba_cfg = pycolmap.BundleAdjustmentConfig()
    for iid in rec.reg_image_ids():
        ba_cfg.add_image(iid)
    for pid in pids:
        if rec.point3D(pid).track.length() > 0:
            ba_cfg.add_constant_point(pid)
    t0 = time.perf_counter()
    adj = pycolmap.create_default_bundle_adjuster(opts, ba_cfg, rec)
    summary = adj.solve()
    dt = time.perf_counter() - t0
    cs = summary.ceres_summary if hasattr(summary, "ceres_summary") else summary
    C = len(cams)
    r = rec.rig(1)
    new_cams = [_camera_from_colmap(cams[c], rec.camera(c + 1)) for c in range(C)]
    new_cfr = []
    for c in range(C):
        if c == ref_index:
            new_cfr.append(np.eye(4))
        else:
            s = r.sensor_from_rig(sensor[c])
            new_cfr.append(transform(s.rotation.matrix(), s.translation))
    new_rfb = {
        f: transform(
            rec.frame(fid).rig_from_world.rotation.matrix(), rec.frame(fid).rig_from_world.translation
        )
        for f, fid in frame_ids.items()
    }
    info = {
        "time_s": dt,
        "iterations": int(cs.num_successful_steps + cs.num_unsuccessful_steps),
        "termination": str(cs.termination_type),
        "n_residuals": int(cs.num_residuals),
    }
    return new_cams, new_cfr, new_rfb, info


def _add_rig(rec, cams: Sequence[Camera], cam_from_ref: Sequence[np.ndarray], ref_index: int) -> list:
    """Add the cameras and the rig (the reference camera and each other's pose in it) to ``rec``; the
    sensors, one per camera."""
    import pycolmap

    rig = pycolmap.Rig()
    rig.rig_id = 1
    C = len(cams)
    for c in range(C):
        rec.add_camera(_colmap_camera(cams[c], c + 1))
    sensor = [pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=c + 1) for c in range(C)]
    rig.add_ref_sensor(sensor[ref_index])
    for c in range(C):
        if c != ref_index:
            T = cam_from_ref[c]
            rig.add_sensor(sensor[c], pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3]))
    rec.add_rig(rig)
    return sensor


def _add_frames(
    rec, board: Board, frames: Sequence[int], ref_from_board: Mapping[int, np.ndarray], obs: Sequence[_Obs]
) -> tuple[list, dict[int, int]]:
    """Add the board points and, per frame with observations, the rig pose and one image per camera that saw
    the board; the point ids and ``{frame: COLMAP frame id}``."""
    import pycolmap

    obj = board.object_points()
    pids = [rec.add_point3D(o, pycolmap.Track()) for o in obj]
    by_frame: dict[int, list[_Obs]] = {}
    for o in obs:
        by_frame.setdefault(o.frame, []).append(o)
    image_id = 1
    frame_ids = {}
    for fi, f in enumerate(frames):
        if f not in by_frame:
            continue
        T = ref_from_board[f]
        fr = pycolmap.Frame()
        fr.frame_id = fi + 1
        fr.rig_id = 1
        fr.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3])
        images = []
        for o in by_frame[f]:
            im = pycolmap.Image(
                name=f"{o.cam}_{f}", keypoints=o.xy.astype(np.float64), camera_id=o.cam + 1, image_id=image_id
            )
            im.frame_id = fi + 1
            image_id += 1
            fr.add_data_id(im.data_id)
            images.append((im, o))
        rec.add_frame(fr)
        for im, o in images:
            rec.add_image(im)
            for k, pid in enumerate(o.ids):
                rec.add_observation(pids[int(pid)], pycolmap.TrackElement(im.image_id, k))
        rec.register_frame(fi + 1)
        frame_ids[f] = fi + 1
    return pids, frame_ids


def _ba_options(cfg: ExtrinsicsConfig, refine_cameras: bool):
    """pycolmap's bundle adjustment options from the config: what is refined, the loss, the solver."""
    import pycolmap

    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = cfg.refine_intrinsics != "none"
    opts.refine_principal_point = cfg.refine_intrinsics != "none"
    opts.refine_extra_params = cfg.refine_intrinsics == "all"
    opts.refine_sensor_from_rig = refine_cameras
    opts.refine_rig_from_world = True
    opts.print_summary = False
    opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, cfg.loss.upper())
    opts.ceres.loss_function_scale = cfg.loss_scale_px
    so = opts.ceres.solver_options
    so.max_num_iterations = cfg.max_iterations
    so.function_tolerance = cfg.function_tolerance  # COLMAP's default 0 runs to max iterations on noisy data
    if cfg.linear_solver != "auto":
        # the board points are constant, so there is nothing for a Schur complement to eliminate: the
        # normal equations over poses (+ intrinsics) are small and dense-ish
        opts.ceres.auto_select_solver_type = False
        so.linear_solver_type = getattr(type(so.linear_solver_type), cfg.linear_solver.upper())
    opts.ceres.solver_options = so
    return opts


def _residuals(board: Board, cams, cam_from_ref, ref_from_board, obs: Sequence[_Obs]) -> list[np.ndarray]:
    obj = board.object_points()
    out = []
    for o in obs:
        T = cam_from_ref[o.cam] @ ref_from_board[o.frame]
        p = cams[o.cam].replace(R=T[:3, :3], t=T[:3, 3]).project(obj[o.ids])
        out.append(np.linalg.norm(p - o.xy, axis=1))
    return out


# ----------------------------------------------------------------------------- orchestration


def _choose_frames(poses: Sequence[Mapping[int, tuple]], max_frames: int) -> list[int]:
    """Time instants seen by >= 2 cameras; at most max_frames, keeping those seen by most cameras and
    spreading the rest over the recording."""
    count: dict[int, int] = {}
    for p in poses:
        for f in p:
            count[f] = count.get(f, 0) + 1
    multi = sorted(f for f, n in count.items() if n >= 2)
    if len(multi) <= max_frames:
        return multi
    # every camera pair keeps a share of its frames (a weakly linked pair keeps all), the rest spread in time
    C = len(poses)
    pair_frames = [sorted(set(poses[i]) & set(poses[j])) for i in range(C) for j in range(i + 1, C)]
    pair_frames = [pf for pf in pair_frames if pf]
    share = max(1, max_frames // (2 * max(1, len(pair_frames))))
    chosen: set[int] = set()
    for pf in pair_frames:
        chosen.update(pf[k] for k in np.unique(np.linspace(0, len(pf) - 1, min(share, len(pf))).astype(int)))
    rest = [f for f in multi if f not in chosen]
    n_more = max(0, max_frames - len(chosen))
    if rest and n_more:
        chosen.update(
            rest[k] for k in np.unique(np.linspace(0, len(rest) - 1, min(n_more, len(rest))).astype(int))
        )
    return sorted(chosen)


def calibrate_extrinsics(
    board: Board,
    cameras: Sequence[Camera],
    dets: Mapping[str, CameraDetections],
    config: ExtrinsicsConfig | None = None,
    progress: Progress | None = None,
) -> ExtrinsicsResult:
    """Cameras (intrinsics known) + detections -> calibrated rig in the world frame (see module doc)."""
    cfg = config or ExtrinsicsConfig()
    names = [c.name for c in cameras]
    C = len(cameras)
    if C < 2:
        raise CalibrationError(f"Extrinsics need at least 2 cameras, got {names}.")
    step = [0]

    def tick(what: str, total: int = 5) -> None:
        step[0] += 1
        log.info("extrinsics: %s", what)
        if progress is not None:
            progress(what, step[0], total)

    poses = [board_poses(board, cameras[c], dets[names[c]], cfg.min_points) for c in range(C)]
    tick("board poses per camera")
    sym = board_symmetry(board)
    links, rel = pairwise_links(poses, sym=sym)
    ref, cam_from_ref = initial_poses(names, links, rel, [len(p) for p in poses])
    tick("pose graph")
    frames = _choose_frames(poses, cfg.max_frames)
    if cfg.refine_intrinsics != "none":
        frames = _with_single_views(poses, frames, cfg.single_view_frames)
    ref_from_board, obs = _observations(board, names, dets, poses, cam_from_ref, frames, sym)
    cams = list(cameras)
    r0 = np.concatenate(_residuals(board, cams, cam_from_ref, ref_from_board, obs))
    initial_rms = float(np.sqrt(np.mean(r0**2)))
    cams, cam_from_ref, ref_from_board, info = bundle_adjust(
        board, cams, cam_from_ref, ref, frames=frames, ref_from_board=ref_from_board, obs=obs, cfg=cfg
    )
    tick("bundle adjustment")
    cams, cam_from_ref, ref_from_board, obs, res, n_out = _drop_outliers(
        board, cams, cam_from_ref, ref, frames, ref_from_board, obs, cfg, info
    )
    tick("outlier rejection")
    per_cam = [
        np.concatenate([r for o, r in zip(obs, res, strict=False) if o.cam == c] or [np.zeros(0)])
        for c in range(C)
    ]
    final_rms = float(np.sqrt(np.mean(np.concatenate(res) ** 2)))
    # world frame
    world = cfg.world or f"camera:{names[0]}"
    ref_from_world = _ref_from_world(world, names, cam_from_ref, ref_from_board, poses)
    out_cams = []
    for c in range(C):
        T = cam_from_ref[c] @ ref_from_world
        out_cams.append(cams[c].replace(R=nearest_rotation(T[:3, :3]), t=T[:3, 3]))
    world_from_ref = inverse(ref_from_world)
    bf = np.array(sorted(ref_from_board))
    wfb = np.stack([world_from_ref @ ref_from_board[f] for f in bf]) if len(bf) else np.zeros((0, 4, 4))
    frames_per_cam = np.array([len({o.frame for o in obs if o.cam == c}) for c in range(C)])
    tick("world frame")
    return ExtrinsicsResult(
        rig=CameraRig(tuple(out_cams)),
        frames=bf,
        world_from_board=wfb,
        links=links,
        per_camera_rms_px=np.array([float(np.sqrt(np.mean(r**2))) if r.size else np.nan for r in per_cam]),
        per_camera_obs=np.array([r.size for r in per_cam]),
        per_camera_frames=frames_per_cam,
        initial_rms_px=initial_rms,
        final_rms_px=final_rms,
        ba_time_s=info["time_s"],
        ba_iterations=info["iterations"],
        n_outliers=n_out,
        world=world,
        residuals_px={names[c]: per_cam[c] for c in range(C)},
    )


def _with_single_views(poses: list[dict], frames: list[int], per_camera: int) -> list[int]:
    """``frames`` plus up to ``per_camera`` frames each camera saw the board in alone, spread over its
    recording: when intrinsics are refined they constrain each lens too (without them a weakly linked
    camera's lens would rest on its few shared frames only)."""
    count: dict[int, int] = {}
    for p in poses:
        for f in p:
            count[f] = count.get(f, 0) + 1
    extra = []
    for p in poses:
        solo = sorted(f for f in p if count[f] == 1)
        k = np.unique(np.linspace(0, len(solo) - 1, min(per_camera, len(solo))).astype(int))
        extra += [solo[i] for i in k] if solo else []
    return sorted(set(frames) | set(extra))


def _observations(
    board: Board,
    names: list[str],
    dets: Mapping[str, CameraDetections],
    poses: list[dict],
    cam_from_ref: list[np.ndarray],
    frames: list[int],
    sym: np.ndarray | None,
) -> tuple[dict[int, np.ndarray], list[_Obs]]:
    """Each frame's initial board pose in the reference camera, and every camera's corner observations in
    it (numbered like the best camera's on a symmetric board)."""
    C = len(names)
    ref_from_board = {}
    obs: list[_Obs] = []
    for f in frames:
        # initial board pose from the camera that sees it best (most points, then lowest PnP error)
        best = min((c for c in range(C) if f in poses[c]), key=lambda c: (-poses[c][f][2], poses[c][f][1]))
        ref_from_board[f] = inverse(cam_from_ref[best]) @ poses[best][f][0]
        for c in range(C):
            if f in poses[c]:
                k = int(np.flatnonzero(dets[names[c]].frames == f)[0])
                xy = dets[names[c]].xy_px[k]
                ids = np.flatnonzero(np.isfinite(xy[:, 0]))
                if sym is not None and c != best:
                    # number this camera's corners like the best camera's: turned if that agrees better
                    A = inverse(cam_from_ref[c]) @ poses[c][f][0]
                    B = ref_from_board[f]
                    if rotation_angle_deg((A @ sym)[:3, :3].T @ B[:3, :3]) < rotation_angle_deg(
                        A[:3, :3].T @ B[:3, :3]
                    ):
                        ids = board.n_points - 1 - ids
                obs.append(_Obs(c, f, ids, xy[np.flatnonzero(np.isfinite(xy[:, 0]))]))
    return ref_from_board, obs


def _drop_outliers(
    board: Board,
    cams: list[Camera],
    cam_from_ref: list[np.ndarray],
    ref: int,
    frames: list[int],
    ref_from_board: dict[int, np.ndarray],
    obs: list[_Obs],
    cfg: ExtrinsicsConfig,
    info: dict,
) -> tuple[list[Camera], list[np.ndarray], dict[int, np.ndarray], list[_Obs], list[np.ndarray], int]:
    """Drop the corners whose residual exceeds ``max(cfg.outlier_px, 5 x the median)`` and adjust again
    (adding to ``info``'s time and iterations); the results, the residuals and the number dropped."""
    res = _residuals(board, cams, cam_from_ref, ref_from_board, obs)
    allr = np.concatenate(res)
    thr = max(cfg.outlier_px, 5 * float(np.median(allr)))
    n_out = int((allr > thr).sum())
    if n_out:
        log.info("extrinsics: dropping %d observation(s) above %.2f px and adjusting again", n_out, thr)
        kept = []
        for o, r in zip(obs, res, strict=False):
            m = r <= thr
            if m.sum() >= 4:
                kept.append(_Obs(o.cam, o.frame, o.ids[m], o.xy[m]))
        obs = kept
        cams, cam_from_ref, ref_from_board, info2 = bundle_adjust(
            board, cams, cam_from_ref, ref, frames=frames, ref_from_board=ref_from_board, obs=obs, cfg=cfg
        )
        info["time_s"] += info2["time_s"]
        info["iterations"] += info2["iterations"]
        res = _residuals(board, cams, cam_from_ref, ref_from_board, obs)
    return cams, cam_from_ref, ref_from_board, obs, res, n_out


def _ref_from_world(
    world: str,
    names: list[str],
    cam_from_ref: list[np.ndarray],
    ref_from_board: dict[int, np.ndarray],
    poses: list[dict],
) -> np.ndarray:
    """The world frame in the reference camera: a camera's (``camera:<name>``) or the board's in a frame
    where it lies on the floor (``board:<frame>``, z up)."""
    C = len(names)
    if world.startswith("camera:"):
        wname = world.split(":", 1)[1]
        if wname not in names:
            raise CalibrationError(f"--world {world}: no camera named {wname!r}; cameras: {names}.")
        ref_from_world = inverse(cam_from_ref[names.index(wname)])
    else:
        try:
            wf = int(world.split(":", 1)[1])
        except ValueError:
            raise CalibrationError(
                f"--world {world}: give the frame number of a frame where the board lies on the "
                "floor, e.g. board:0."
            ) from None
        if wf in ref_from_board:
            rfb = ref_from_board[wf]
        else:
            seen = [c for c in range(C) if wf in poses[c]]
            if not seen:
                raise CalibrationError(
                    f"--world {world}: no camera saw the board in frame {wf}. Pick a frame where "
                    "the board lies on the floor and at least one camera sees it."
                )
            c = max(seen, key=lambda c: poses[c][wf][2])
            rfb = inverse(cam_from_ref[c]) @ poses[c][wf][0]
        ref_from_world = rfb @ FLIP_BOARD_Z_UP
    return ref_from_world


def board_fit_rms(
    board: Board,
    rig: CameraRig,
    dets: Mapping[str, CameraDetections],
    min_points: int = 6,
    loss: str = "soft_l1",
) -> float:
    """RMS (px) of the rigid board fitted to every frame seen by >= 2 cameras with the cameras of ``rig``
    held fixed (only the board poses are adjusted): a way to score any rig, e.g. another tool's, on the
    board model."""
    cams = list(rig.cameras)
    names = rig.names
    poses = [board_poses(board, c, dets[c.name], min_points) for c in cams]
    T0 = transform(cams[0].R, cams[0].t)
    cam_from_ref = [transform(c.R, c.t) @ inverse(T0) for c in cams]
    frames = _choose_frames(poses, 10**9)
    ref_from_board, obs = {}, []
    for f in frames:
        best = min((c for c in range(len(cams)) if f in poses[c]), key=lambda c: -poses[c][f][2])
        ref_from_board[f] = inverse(cam_from_ref[best]) @ poses[best][f][0]
        for c in range(len(cams)):
            if f in poses[c]:
                k = int(np.flatnonzero(dets[names[c]].frames == f)[0])
                xy = dets[names[c]].xy_px[k]
                ids = np.flatnonzero(np.isfinite(xy[:, 0]))
                obs.append(_Obs(c, f, ids, xy[ids]))
    cfg = ExtrinsicsConfig(loss=loss)
    _, cfr, rfb, _ = bundle_adjust(
        board,
        cams,
        cam_from_ref,
        0,
        frames=frames,
        ref_from_board=ref_from_board,
        obs=obs,
        cfg=cfg,
        refine_cameras=False,
    )
    r = np.concatenate(_residuals(board, cams, cfr, rfb, obs))
    return float(np.sqrt(np.mean(r**2)))
