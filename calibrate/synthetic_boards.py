"""Synthetic board recordings with known cameras, for tests and benchmarks.

The printed board (``Board.render``) is warped into each virtual camera through its lens model:
every output pixel is undistorted to a ray, the ray meets the board plane (a homography), and the
board image is sampled there (2x supersampled, then area-averaged), then blurred and given sensor
noise. Only the printed side is drawn (a camera behind the board sees the blank back).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.calibrate.boards import Board
from roomcap.calibrate.camera import Camera, CameraRig
from roomcap.calibrate.detect import CameraDetections

__all__ = [
    "BoardRenderer",
    "look_at",
    "ring_rig",
    "board_trajectory",
    "write_recording",
    "SceneTruth",
    "views_near_camera",
    "project_detections",
]


def look_at(
    center_m: np.ndarray, target_m: np.ndarray, up: Sequence[float] = (0, 0, 1)
) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of a camera at center_m looking at target_m
    (OpenCV axes: x right, y down, z ahead)."""
    c = np.asarray(center_m, float)
    z = np.asarray(target_m, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ c


def ring_rig(
    n_cams: int,
    radius_m: float = 2.0,
    height_m: float = 1.5,
    size_wh: tuple[int, int] = (640, 480),
    focal_px: float = 600.0,
    dist: Sequence[float] = (-0.12, 0.05, 0.0, 0.0, 0.0),
    rng=None,
) -> CameraRig:
    """n_cams cameras on a circle looking at (0,0,1), with slightly different focal lengths."""
    rng = rng or np.random.default_rng(0)
    cams = []
    w, h = size_wh
    for i in range(n_cams):
        a = 2 * np.pi * i / n_cams
        R, t = look_at([radius_m * np.cos(a), radius_m * np.sin(a), height_m], [0, 0, 1.0])
        f = focal_px * (1 + rng.uniform(-0.05, 0.05))
        K = np.array([[f, 0, w / 2 + rng.uniform(-8, 8)], [0, f, h / 2 + rng.uniform(-8, 8)], [0, 0, 1]])
        cams.append(Camera(f"cam{i:02d}", size_wh, K, np.asarray(dist, float), "pinhole", R, t))
    return CameraRig(tuple(cams))


def _rot(axis: str, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def board_trajectory(
    board: Board,
    n_frames: int,
    rng: np.random.Generator,
    center_m=(0, 0, 1.0),
    spread_m: float = 0.6,
    tilt_deg: float = 35.0,
    yaw_range=(0.0, 2 * np.pi),
) -> np.ndarray:
    """(F,4,4) world_from_board poses of a board held upright near center_m, turning about the vertical
    (yaw swept over yaw_range) with random tilts; the board centre is at the given position."""
    w, h = board.extent_m()
    out = np.zeros((n_frames, 4, 4))
    for k in range(n_frames):
        yaw = yaw_range[0] + (yaw_range[1] - yaw_range[0]) * (k + rng.uniform(0, 1)) / n_frames
        # upright board facing +x of its yaw: board x horizontal, y down, z into the board
        base = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: board x, y, z
        Rw = (
            _rot("z", yaw)
            @ base
            @ _rot("x", np.radians(rng.uniform(-tilt_deg, tilt_deg)))
            @ _rot("y", np.radians(rng.uniform(-tilt_deg, tilt_deg)))
            @ _rot("z", np.radians(rng.uniform(-20, 20)))
        )
        c = np.asarray(center_m, float) + rng.uniform(-spread_m, spread_m, 3) * np.array([1, 1, 0.5])
        t = c - Rw @ np.array([w / 2, h / 2, 0])
        out[k, :3, :3] = Rw
        out[k, :3, 3] = t
        out[k, 3, 3] = 1
    return out


def views_near_camera(
    board: Board,
    cam: Camera,
    n_frames: int,
    rng: np.random.Generator,
    depth_m: tuple[float, float] = (0.8, 1.3),
    tilt_deg: float = 45.0,
) -> np.ndarray:
    """(F,4,4) world_from_board poses of a board held in front of one camera (as for an intrinsic
    calibration): centred on a random image point, at a random depth, facing the camera with random tilts."""
    w, h = board.extent_m()
    out = np.zeros((n_frames, 4, 4))
    for k in range(n_frames):
        u = rng.uniform(0.2, 0.8) * cam.size_wh[0]
        v = rng.uniform(0.2, 0.8) * cam.size_wh[1]
        ray = np.linalg.solve(cam.K, [u, v, 1.0])
        c_cam = ray / ray[2] * rng.uniform(*depth_m)
        # board facing the camera: board z along the camera's z (into the board), x right, y down
        Rc = (
            _rot("x", np.radians(rng.uniform(-tilt_deg, tilt_deg)))
            @ _rot("y", np.radians(rng.uniform(-tilt_deg, tilt_deg)))
            @ _rot("z", np.radians(rng.uniform(-30, 30)))
        )
        t_cam = c_cam - Rc @ np.array([w / 2, h / 2, 0])
        # world_from_board = world_from_cam @ cam_from_board
        Rw = cam.R.T @ Rc
        tw = cam.R.T @ (t_cam - cam.t)
        out[k, :3, :3], out[k, :3, 3], out[k, 3, 3] = Rw, tw, 1
    return out


class BoardRenderer:
    """Renders one board (with a white margin of half a square) into cameras.
    px_per_m: resolution of the printed board image; supersample: per axis."""

    def __init__(
        self, board: Board, px_per_m: float = 3000.0, supersample: int = 2, margin_m: float | None = None
    ):
        self.board = board
        self.ppm = px_per_m
        self.ss = supersample
        self.margin_m = 0.5 * (board.square_size_m or board.marker_size_m) if margin_m is None else margin_m
        self.margin_px = round(self.margin_m * px_per_m)
        self.img = board.render(px_per_m, self.margin_px).astype(np.float32)
        self._rays: dict[str, np.ndarray] = {}

    def _camera_rays(self, cam: Camera, step: int = 4) -> np.ndarray:
        """Normalised undistorted coordinates (Hs,Ws,2) of the supersampled pixel grid (undistortion on a
        coarse grid, linear in between: the lens model is smooth)."""
        import cv2

        key = (cam.size_wh, cam.model, cam.K.tobytes(), cam.dist.tobytes())
        if key not in self._rays:
            w, h = cam.size_wh
            s = self.ss
            nx, ny = -(-(w * s) // step), -(-(h * s) // step)
            # coarse samples at fine indices k*step + (step-1)/2, so that cv2.resize (pixel-centre aligned,
            # float weights for float input) interpolates them linearly onto the fine grid
            U = ((np.arange(nx) * step + (step - 1) / 2) + 0.5) / s - 0.5
            V = ((np.arange(ny) * step + (step - 1) / 2) + 0.5) / s - 0.5
            uu, vv = np.meshgrid(U, V)
            und = cam.undistort_px(np.stack([uu, vv], -1))
            coarse = np.stack(
                [(und[..., 0] - cam.K[0, 2]) / cam.K[0, 0], (und[..., 1] - cam.K[1, 2]) / cam.K[1, 1]], -1
            )
            fine = cv2.resize(coarse, (nx * step, ny * step), interpolation=cv2.INTER_LINEAR)
            self._rays[key] = fine[: h * s, : w * s].astype(np.float32)
        return self._rays[key]

    def _outline_world(self, world_from_board: np.ndarray) -> np.ndarray:
        w, h = self.board.extent_m()
        m = self.margin_m - self.board.image_origin_m()
        w, h = w + 2 * self.board.image_origin_m(), h + 2 * self.board.image_origin_m()
        t = np.linspace(0, 1, 16)
        xs = np.concatenate(
            [-m + t * (w + 2 * m), np.full(16, w + m), w + m - t * (w + 2 * m), np.full(16, -m)]
        )
        ys = np.concatenate(
            [np.full(16, -m), -m + t * (h + 2 * m), np.full(16, h + m), h + m - t * (h + 2 * m)]
        )
        P = np.stack([xs, ys, np.zeros_like(xs)], 1)
        return (world_from_board[:3, :3] @ P.T).T + world_from_board[:3, 3]

    def visible(self, cam: Camera, world_from_board: np.ndarray, min_fraction: float = 0.5) -> bool:
        """Printed side faces the camera and most board points project inside the image."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cam.R, cam.t
        cfb = T @ world_from_board
        c_b = -cfb[:3, :3].T @ cfb[:3, 3]
        if c_b[2] >= 0:
            return False
        X = (world_from_board[:3, :3] @ self.board.object_points().T).T + world_from_board[:3, 3]
        p = cam.project(X)
        w, h = cam.size_wh
        inside = np.isfinite(p[:, 0]) & (p[:, 0] > 2) & (p[:, 0] < w - 3) & (p[:, 1] > 2) & (p[:, 1] < h - 3)
        return bool(inside.mean() > min_fraction)

    def render(
        self,
        cam: Camera,
        world_from_board: np.ndarray,
        rng: np.random.Generator,
        noise: float = 2.0,
        blur_sigma_px: float = 0.6,
        background: float = 110.0,
    ) -> np.ndarray:
        """Gray image (H,W) uint8 of the board seen by cam (world_from_board: (4,4))."""
        import cv2

        w, h = cam.size_wh
        s = self.ss
        out = np.full((h * s, w * s), background, np.float32)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cam.R, cam.t
        cfb = T @ world_from_board
        # region of the image where the board (with margin) can appear
        po = cam.project(self._outline_world(world_from_board))
        po = po[np.isfinite(po[:, 0])]
        if len(po):
            x0, y0 = np.clip(np.floor(po.min(0) * s) - 4 * s, 0, [w * s, h * s]).astype(int)
            x1, y1 = np.clip(np.ceil(po.max(0) * s) + 4 * s, 0, [w * s, h * s]).astype(int)
        else:
            x0 = y0 = x1 = y1 = 0
        if x1 > x0 and y1 > y0:
            rays = self._camera_rays(cam)[y0:y1, x0:x1]
            H = np.column_stack([cfb[:3, 0], cfb[:3, 1], cfb[:3, 3]])  # board (x,y,1) -> camera ray
            Hi = np.linalg.inv(H).astype(np.float32)
            x, y = rays[..., 0], rays[..., 1]
            bx = Hi[0, 0] * x + Hi[0, 1] * y + Hi[0, 2]
            by = Hi[1, 0] * x + Hi[1, 1] * y + Hi[1, 2]
            bw = Hi[2, 0] * x + Hi[2, 1] * y + Hi[2, 2]
            ok = (bw * np.sign(np.linalg.det(H))) > 0  # the ray meets the plane in front of the camera
            bw = np.where(ok, bw, 1.0)
            k = np.float32(self.ppm)
            o = self.margin_px - self.board.image_origin_m() * self.ppm - 0.5
            mx = np.where(ok, bx / bw * k + o, -1e6).astype(np.float32)
            my = np.where(ok, by / bw * k + o, -1e6).astype(np.float32)
            out[y0:y1, x0:x1] = cv2.remap(
                self.img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=background
            )
        img = cv2.resize(out, (w, h), interpolation=cv2.INTER_AREA) if s > 1 else out
        if blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
        if noise > 0:
            img = img + rng.normal(0, noise, img.shape).astype(np.float32)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class SceneTruth:
    rig: CameraRig
    world_from_board: np.ndarray  # (F,4,4)
    n_views: np.ndarray  # (C,) frames rendered per camera


def write_recording(
    board: Board,
    rig: CameraRig,
    world_from_board: np.ndarray,
    out_dir: str | os.PathLike,
    rng: np.random.Generator,
    *,
    visible_mask: np.ndarray | None = None,
    noise: float = 2.0,
    blur_sigma_px: float = 0.6,
    px_per_m: float = 3000.0,
) -> SceneTruth:
    """Write ``out_dir/<camera>/frame_<k>.png`` for every frame where the board is visible to that camera
    (and visible_mask (C,F), if given, allows it). Returns the truth."""
    import cv2

    out = Path(out_dir)
    r = BoardRenderer(board, px_per_m)
    n = np.zeros(len(rig), np.int64)
    for c, cam in enumerate(rig.cameras):
        d = out / cam.name
        d.mkdir(parents=True, exist_ok=True)
        for k, T in enumerate(world_from_board):
            if visible_mask is not None and not visible_mask[c, k]:
                continue
            if not r.visible(cam, T):
                continue
            cv2.imwrite(str(d / f"frame_{k:05d}.png"), r.render(cam, T, rng, noise, blur_sigma_px))
            n[c] += 1
    return SceneTruth(rig, world_from_board, n)


def project_detections(
    board: Board,
    rig: CameraRig,
    world_from_board: np.ndarray,
    rng: np.random.Generator,
    noise_px: float = 0.2,
    visible_mask: np.ndarray | None = None,
    min_points: int = 6,
) -> dict:
    """Detections without rendering: exact projections plus Gaussian noise (noise_px per axis), for
    frames where the printed side faces the camera; points outside the image are NaN.
    visible_mask: (C,F) optional extra restriction. Returns camera name -> CameraDetections."""

    r = BoardRenderer.__new__(BoardRenderer)  # visibility test only: no board image needed
    r.board = board
    obj = board.object_points()
    out = {}
    for c, cam in enumerate(rig.cameras):
        frames, xys = [], []
        w, h = cam.size_wh
        for k, T in enumerate(world_from_board):
            if visible_mask is not None and not visible_mask[c, k]:
                continue
            if not r.visible(cam, T, min_fraction=0.3):
                continue
            p = cam.project(obj @ T[:3, :3].T + T[:3, 3]) + rng.normal(0, noise_px, (len(obj), 2))
            p[~((p[:, 0] >= 0) & (p[:, 1] >= 0) & (p[:, 0] <= w - 1) & (p[:, 1] <= h - 1))] = np.nan
            if np.isfinite(p[:, 0]).sum() < min_points:
                continue
            frames.append(k)
            xys.append(p)
        xy = np.stack(xys) if xys else np.zeros((0, len(obj), 2))
        out[cam.name] = CameraDetections(
            cam.name, cam.size_wh, np.asarray(frames, np.int64), xy, len(world_from_board), 1
        )
    return out
