"""Synthetic camera rigs and rooms: a ring of cameras, and a kitchen-like room with furniture.

World frame: metres, z up, floor at z = 0. Cameras are ``calibrate.camera.Camera`` with
``cam_from_world`` poses built by :func:`look_at` (camera x right, y down, z forward, as OpenCV).

- :func:`ring_rig` — ``n_cams`` on a circle looking at the centre (the seed's Shelf/Campus-like set-ups).
- :func:`kitchen_rig` + :func:`kitchen_room` — an 8 m × 6 m room, cameras on the walls and in the
  corners at ~2.5 m looking into the room, mild lens distortion, and axis-aligned furniture boxes
  (island, counters, table, tall cupboard, fridge) that occlude people. ``linkage="weak"`` points
  the cameras at the two halves of the room so the halves share few views (calibration tests).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from roomcap.calibrate.camera import Camera, CameraRig

__all__ = [
    "Box",
    "Room",
    "look_at",
    "make_camera",
    "ring_rig",
    "ring_room",
    "kitchen_rig",
    "kitchen_room",
    "kitchen",
]


def look_at(center_m, target_m, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` (R (3,3), t (3,)) of a camera at ``center_m`` looking at ``target_m``.

    The image's up direction is as close to ``up`` as the viewing direction allows."""
    c = np.asarray(center_m, dtype=np.float64)
    z = np.asarray(target_m, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return R, -R @ c


def make_camera(
    name: str,
    center_m,
    target_m,
    size_wh=(1280, 720),
    fov_h_deg: float = 80.0,
    dist=None,
    roll_deg: float = 0.0,
) -> Camera:
    """A pinhole camera at ``center_m`` looking at ``target_m``, horizontal field of view ``fov_h_deg``."""
    w, h = int(size_wh[0]), int(size_wh[1])
    f = 0.5 * w / np.tan(np.deg2rad(fov_h_deg) / 2)
    K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    R, t = look_at(center_m, target_m)
    if roll_deg:
        a = np.deg2rad(roll_deg)
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        R, t = Rz @ R, Rz @ t
    d = np.zeros(0) if dist is None else np.asarray(dist, float)
    return Camera(name=name, size_wh=(w, h), K=K, dist=d, model="pinhole", R=R, t=t)


@dataclass(frozen=True)
class Box:
    """An axis-aligned box (furniture): ``min_m``/``max_m`` (3,) world corners, metres."""

    name: str
    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]

    def contains_xy(self, xy: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        """Mask (...,) of floor points ``xy (...,2)`` inside the box footprint grown by ``margin_m``."""
        lo, hi = np.asarray(self.min_m[:2]) - margin_m, np.asarray(self.max_m[:2]) + margin_m
        return np.all((xy >= lo) & (xy <= hi), axis=-1)


@dataclass(frozen=True)
class Room:
    """Floor rectangle ``bounds_m = (x0, x1, y0, y1)``, ceiling height, furniture boxes."""

    name: str
    bounds_m: tuple[float, float, float, float]
    height_m: float = 2.8
    boxes: tuple[Box, ...] = field(default_factory=tuple)

    def boxes_array(self) -> tuple[np.ndarray, np.ndarray]:
        """(B,3) lower and (B,3) upper corners."""
        if not self.boxes:
            return np.zeros((0, 3)), np.zeros((0, 3))
        lo = np.array([b.min_m for b in self.boxes], float)
        return lo, np.array([b.max_m for b in self.boxes], float)


def ring_room(radius_m: float = 3.0) -> Room:
    """An empty square floor inscribed in the ring (people stay inside the cameras' circle)."""
    h = radius_m / np.sqrt(2) * 0.9
    return Room("ring", (-h, h, -h, h))


def _mild_distortion(rng: np.random.Generator) -> np.ndarray:
    k1 = rng.uniform(-0.12, -0.04)
    return np.array([k1, rng.uniform(0.0, 0.03), rng.normal(0, 5e-4), rng.normal(0, 5e-4), 0.0])


def ring_rig(
    n_cams: int = 6,
    radius_m: float = 3.0,
    *,
    height_m: float = 2.0,
    size_wh=(1280, 720),
    fov_h_deg: float = 70.0,
    target_m=(0.0, 0.0, 1.0),
    distortion: bool = False,
    jitter_m: float = 0.0,
    seed: int = 0,
) -> CameraRig:
    """``n_cams`` cameras evenly on a circle of ``radius_m`` at ``height_m``, all looking at ``target_m``.

    ``distortion`` adds mild radial/tangential distortion; ``jitter_m`` perturbs centres and
    targets (seeded) so the rig is not perfectly symmetric.
    """
    if n_cams < 1:
        raise ValueError(f"ring_rig: n_cams must be >= 1, got {n_cams}")
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n_cams):
        a = 2 * np.pi * i / n_cams
        c = np.array([radius_m * np.cos(a), radius_m * np.sin(a), height_m]) + rng.normal(0, jitter_m, 3)
        tgt = np.asarray(target_m, float) + rng.normal(0, jitter_m, 3)
        dist = _mild_distortion(rng) if distortion else None
        cams.append(make_camera(f"cam{i:02d}", c, tgt, size_wh, fov_h_deg, dist))
    return CameraRig(tuple(cams))


# Kitchen: x in [-4, 4], y in [-3, 3]. Furniture chosen so that every region has some occluder.
_KITCHEN_BOXES = (
    Box("island", (-1.0, -0.45, 0.0), (1.0, 0.45, 0.92)),
    Box("counter_north", (-3.9, 2.35, 0.0), (-0.5, 2.95, 0.92)),
    Box("counter_east", (3.35, -1.2, 0.0), (3.95, 1.6, 0.92)),
    Box("fridge", (3.2, 2.2, 0.0), (3.95, 2.95, 2.0)),
    Box("tall_cupboard", (-2.6, -1.2, 0.0), (-2.1, -0.6, 2.05)),
    Box("table", (1.4, -2.1, 0.0), (2.8, -1.1, 0.76)),
)

# Camera mounting points (x, y) at ~2.5 m, in an order that spreads the first k cameras around the room.
_KITCHEN_MOUNTS = (
    (-3.9, -2.9),
    (3.9, 2.9),
    (3.9, -2.9),
    (-3.9, 2.9),  # corners
    (0.0, -2.95),
    (0.0, 2.95),
    (-3.95, 0.0),
    (3.95, 0.0),  # wall centres
    (-2.0, -2.95),
    (2.0, 2.95),
    (2.0, -2.95),
    (-2.0, 2.95),  # along the long walls
    (-3.95, -1.5),
    (3.95, 1.5),
    (3.95, -1.5),
    (-3.95, 1.5),  # along the short walls
)


def kitchen_room() -> Room:
    """The 8 m × 6 m kitchen-like room with its furniture boxes."""
    return Room("kitchen", (-4.0, 4.0, -3.0, 3.0), 2.8, _KITCHEN_BOXES)


def kitchen_rig(
    n_cams: int = 12,
    size_wh=(1280, 720),
    fov_h_deg: float = 85.0,
    height_m: float = 2.5,
    distortion: bool = True,
    linkage: str = "full",
    seed: int = 0,
) -> CameraRig:
    """Up to 16 wall/corner cameras at ~``height_m`` looking into the kitchen (see :func:`kitchen_room`).

    ``linkage="full"``: every camera looks near the room centre (targets jittered ±1 m), so all
    cameras share the middle of the room. ``linkage="weak"``: cameras on the west half look at the
    west half, the others at the east half, with a narrower field of view: the two groups share
    few views (for calibration tests). Mild distortion (k1 in [-0.12, -0.04]) when ``distortion``.
    """
    if not 1 <= n_cams <= len(_KITCHEN_MOUNTS):
        raise ValueError(f"kitchen_rig: n_cams must be in 1..{len(_KITCHEN_MOUNTS)}, got {n_cams}")
    if linkage not in ("full", "weak"):
        raise ValueError(f"kitchen_rig: linkage must be 'full' or 'weak', got {linkage!r}")
    rng = np.random.default_rng(seed)
    cams = []
    for i, (x, y) in enumerate(_KITCHEN_MOUNTS[:n_cams]):
        c = np.array([x, y, height_m + rng.uniform(-0.15, 0.15)])
        if linkage == "full":
            tgt = np.array([rng.uniform(-1, 1), rng.uniform(-0.7, 0.7), 0.9])
            fov = fov_h_deg
        else:
            side = -2.0 if x < 0 or (x == 0 and i % 2 == 0) else 2.0
            tgt = np.array([side + rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 0.9])
            fov = min(fov_h_deg, 60.0)
        dist = _mild_distortion(rng) if distortion else None
        cams.append(make_camera(f"cam{i:02d}", c, tgt, size_wh, fov, dist, roll_deg=rng.normal(0, 1.0)))
    return CameraRig(tuple(cams))


def kitchen(n_cams: int = 12, **kw) -> tuple[CameraRig, Room]:
    """``(kitchen_rig(n_cams, **kw), kitchen_room())``."""
    return kitchen_rig(n_cams, **kw), kitchen_room()
