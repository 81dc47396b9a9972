"""Seeded multi-person scenes: people playing CMU mocap clips (or a procedural walk) in a room.

``make_scene(room, SceneConfig(...))`` returns a :class:`Scene` with ground truth
``gt_xyz_m (T,P,19,3)`` (canonical ``body19``, metres, z up; NaN while a person is absent) and
stable identities ``person_ids (P,)``. Rendering to per-camera detections is in
:mod:`roomcap.synthetic.render`; :func:`write_session` writes a session folder the 3D stages can run on.

Choices made here:

- each person plays a distinct clip when the pool allows (clips of climbing, where the head goes
  above 2.0 m, are left out). Clips at least as long as the scene are tried first (their
  duration read from the BVH header); such a clip contributes a random window. A shorter clip is
  played forwards then backwards (ping-pong) so positions stay continuous.
- placement: the clip's floor track is centred, rotated by a random yaw and translated so the
  whole body stays ``wall_margin_m`` inside the walls; among ``placement_tries`` random
  placements the one with the fewest frames inside furniture (grown by 0.25 m) or closer than
  ``min_separation_m`` to already placed people wins. With many people in a small room some
  overlap may remain (it is logged).
- entering/leaving: with ``enter_leave``, a fraction of the people appear after the start and/or
  disappear before the end (at least ``min_present_s`` on stage); ``return_fraction`` of them
  leave mid-scene and come back later with the same id (identity-recovery tests).
- procedural fallback (no mocap folder, or ``motion="procedural"``): people walk between random
  waypoints around the furniture with swinging arms and legs, pausing in between.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import SessionLayout
from roomcap.core.config import config_from_dict
from roomcap.core.errors import FormatError
from roomcap.core.fileio import check_schema, load_npz, npz_str, save_npz, save_toml, schema_tag
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.synthetic import bvh
from roomcap.synthetic.rigs import Room

log = logging.getLogger(__name__)

J19 = {n: i for i, n in enumerate(CANONICAL.joint_names)}
GT_SCHEMA = "synthetic_gt"
GT_VERSION = 1


@dataclass(frozen=True)
class SceneConfig:
    """Scene generation parameters (all seeded by ``seed``)."""

    n_people: int = 4
    duration_s: float = 10.0
    fps: float = 25.0
    seed: int = 0
    motion: str = "auto"  # "auto" (mocap if found, else procedural) | "mocap" | "procedural"
    mocap_root: str | None = None
    clip_filter: tuple[str, ...] = ()  # keep clips whose path contains any of these substrings
    # leave out clips under these folders of the mocap root: cmu-more is the forecasting collection, and
    # the world (its benchmarks and the bounds its tests measured) is made of the clips before it
    clip_exclude: tuple[str, ...] = ("cmu-more",)
    enter_leave: bool = False
    enter_leave_fraction: float = 0.5
    return_fraction: float = 0.0
    min_present_s: float = 2.0
    min_separation_m: float = 0.6
    wall_margin_m: float = 0.3
    placement_tries: int = 40
    max_head_height_m: float = 2.0

    def __post_init__(self) -> None:
        if self.n_people < 0:
            raise ValueError(f"SceneConfig.n_people must be >= 0, got {self.n_people}")
        if not (self.duration_s > 0 and self.fps > 0):
            raise ValueError(
                f"SceneConfig: duration_s and fps must be > 0, got {self.duration_s}, {self.fps}"
            )
        if self.motion not in ("auto", "mocap", "procedural"):
            raise ValueError(
                f"SceneConfig.motion must be 'auto', 'mocap' or 'procedural', got {self.motion!r}"
            )

    @classmethod
    def from_dict(cls, d: dict) -> SceneConfig:
        return config_from_dict(cls, d)

    @property
    def n_frames(self) -> int:
        return int(round(self.duration_s * self.fps))


@dataclass(frozen=True)
class Scene:
    """Ground truth of a scene: ``gt_xyz_m (T,P,19,3)`` (NaN = absent), ``person_ids (P,)``."""

    gt_xyz_m: np.ndarray
    person_ids: np.ndarray
    fps: float
    room: Room
    clip_names: tuple[str, ...]
    config: SceneConfig

    def __post_init__(self) -> None:
        g = np.asarray(self.gt_xyz_m, dtype=np.float64)
        if g.ndim != 4 or g.shape[2:] != (19, 3):
            raise ValueError(f"Scene.gt_xyz_m must be (T,P,19,3), got {g.shape}")
        if len(self.person_ids) != g.shape[1] or len(self.clip_names) != g.shape[1]:
            raise ValueError("Scene: person_ids and clip_names must have one entry per person")
        object.__setattr__(self, "gt_xyz_m", g)
        object.__setattr__(self, "person_ids", np.asarray(self.person_ids, dtype=np.int64))

    @property
    def n_frames(self) -> int:
        return self.gt_xyz_m.shape[0]

    @property
    def n_people(self) -> int:
        return self.gt_xyz_m.shape[1]

    @property
    def present(self) -> np.ndarray:
        """(T,P) bool: the person is on stage."""
        return np.isfinite(self.gt_xyz_m[..., 0]).all(-1)

    @property
    def t_s(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.fps


# ---------------------------------------------------------------------------------------------
# motion sources


def _clip_pool(cfg: SceneConfig) -> list[Path]:
    files = [f for f in bvh.list_clips(cfg.mocap_root) if not set(cfg.clip_exclude) & set(f.parts)]
    if cfg.clip_filter:
        files = [f for f in files if any(s in str(f) for s in cfg.clip_filter)]
    return files


def _usable(xyz: np.ndarray, cfg: SceneConfig) -> bool:
    return xyz.shape[0] >= max(2.0 * cfg.fps, 8) and float(np.percentile(xyz[..., 2].max(1), 95)) <= (
        cfg.max_head_height_m
    )


def _pingpong_window(n: int, T: int, rng: np.random.Generator) -> np.ndarray:
    """Frame indices (T,) into a clip of n frames: a random window, or forward-backward repeats."""
    if n >= T:
        s = int(rng.integers(0, n - T + 1))
        return np.arange(s, s + T)
    period = 2 * (n - 1)
    k = (np.arange(T) + int(rng.integers(0, period))) % period
    return np.where(k < n, k, period - k)


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _place(
    motion: np.ndarray, room: Room, placed: list[np.ndarray], cfg: SceneConfig, rng: np.random.Generator
) -> tuple[np.ndarray, int] | None:
    """Rotate/translate ``motion (T,19,3)`` into the room. Returns (placed motion, violations) or None."""
    x0, x1, y0, y1 = room.bounds_m
    m = cfg.wall_margin_m
    pel = J19["pelvis"]
    centre = np.nanmean(motion[:, pel, :2], axis=0)
    base = motion.copy()
    base[..., :2] -= centre
    best = None
    for _ in range(cfg.placement_tries):
        R = _yaw(rng.uniform(0, 2 * np.pi))
        cand = base @ R.T
        lo, hi = np.nanmin(cand[..., :2], axis=(0, 1)), np.nanmax(cand[..., :2], axis=(0, 1))
        tx_lo, tx_hi = x0 + m - lo[0], x1 - m - hi[0]
        ty_lo, ty_hi = y0 + m - lo[1], y1 - m - hi[1]
        if tx_lo > tx_hi or ty_lo > ty_hi:
            continue
        cand[..., 0] += rng.uniform(tx_lo, tx_hi)
        cand[..., 1] += rng.uniform(ty_lo, ty_hi)
        p_xy = cand[:, pel, :2]
        bad = np.zeros(len(cand), dtype=bool)
        for box in room.boxes:
            bad |= box.contains_xy(p_xy, 0.25)
        for other in placed:
            d = np.linalg.norm(other[:, pel, :2] - p_xy, axis=-1)
            bad |= d < cfg.min_separation_m  # NaN (absent) compares False
        v = int(bad.sum())
        if best is None or v < best[1]:
            best = (cand, v)
            if v == 0:
                break
    return best


def _walk_path(
    n_frames: int, dt: float, room: Room, rng: np.random.Generator, margin_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The walker's path between random free waypoints (pausing at each): position (T,2), heading (T,)
    and speed (T,) per frame."""
    x0, x1, y0, y1 = room.bounds_m

    def free_point() -> np.ndarray:
        for _ in range(100):
            p = np.array(
                [rng.uniform(x0 + margin_m, x1 - margin_m), rng.uniform(y0 + margin_m, y1 - margin_m)]
            )
            if not any(b.contains_xy(p, 0.35) for b in room.boxes):
                return p
        return p

    speed = rng.uniform(0.8, 1.3)
    pos = free_point()
    goal = free_point()
    heading = rng.uniform(0, 2 * np.pi)
    pause = 0.0
    P = np.zeros((n_frames, 2))
    H = np.zeros(n_frames)
    V = np.zeros(n_frames)
    for k in range(n_frames):
        d = goal - pos
        dist = np.linalg.norm(d)
        v = 0.0
        if pause > 0:
            pause -= dt
        elif dist < 0.1:
            pause = rng.uniform(0.0, 2.0)
            goal = free_point()
        else:
            v = min(speed, dist / dt)
            want = np.arctan2(d[1], d[0])
            dh = (want - heading + np.pi) % (2 * np.pi) - np.pi
            heading += np.clip(dh, -3.0 * dt, 3.0 * dt)  # turn at most 3 rad/s
            pos = pos + v * dt * np.array([np.cos(heading), np.sin(heading)]) * max(np.cos(dh), 0.2)
        P[k], H[k], V[k] = pos, heading, v
    return P, H, V


def procedural_walk(
    n_frames: int, fps: float, room: Room, rng: np.random.Generator, margin_m: float = 0.4
) -> np.ndarray:
    """A person walking between random waypoints with swinging limbs: ``(T,19,3)`` metres, z up."""
    dt = 1.0 / fps
    P, H, V = _walk_path(n_frames, dt, room, rng, margin_m)
    V = np.convolve(np.pad(V, 2, mode="edge"), np.ones(5) / 5, mode="valid")  # smooth, same length
    amp = np.clip(V / 1.0, 0, 1)
    phase = np.cumsum(2 * np.pi * 0.9 * amp * dt * np.maximum(V, 0.3) / 1.0)
    s = rng.uniform(0.92, 1.08)  # body scale
    thigh, shin, uarm, farm = 0.45 * s, 0.43 * s, 0.29 * s, 0.26 * s
    a_leg = 0.45 * amp * np.sin(phase)
    knee_flex = 0.5 * amp * np.maximum(np.sin(phase + 1.2), 0)
    a_arm = 0.35 * amp * np.sin(phase)
    out = np.zeros((n_frames, 19, 3))  # local frame: x forward, y left, z up
    pel = np.stack([np.zeros(n_frames), np.zeros(n_frames), 0.94 * s + 0.015 * np.cos(2 * phase)], 1)
    out[:, J19["pelvis"]] = pel
    for side, sgn, al, aa in (("left", 1.0, a_leg, -a_arm), ("right", -1.0, -a_leg, a_arm)):
        kf = knee_flex if side == "left" else 0.5 * amp * np.maximum(np.sin(phase + np.pi + 1.2), 0)
        hip = pel + np.array([0.0, sgn * 0.1 * s, 0.0])
        knee = hip + thigh * np.stack([np.sin(al), 0 * al, -np.cos(al)], 1)
        ankle = knee + shin * np.stack([np.sin(al - kf), 0 * al, -np.cos(al - kf)], 1)
        sh = pel + np.array([0.0, sgn * 0.18 * s, 0.52 * s])
        elbow = sh + uarm * np.stack([np.sin(aa), 0 * aa, -np.cos(aa)], 1)
        wrist = elbow + farm * np.stack([np.sin(aa + 0.3), 0 * aa, -np.cos(aa + 0.3)], 1)
        for n, v in (
            ("hip", hip),
            ("knee", knee),
            ("ankle", ankle),
            ("shoulder", sh),
            ("elbow", elbow),
            ("wrist", wrist),
        ):
            out[:, J19[f"{side}_{n}"]] = v
    neck = 0.5 * (out[:, J19["left_shoulder"]] + out[:, J19["right_shoulder"]])
    out[:, J19["neck"]] = neck
    head = neck + np.array([0.0, 0.0, 0.1 * s])
    for n, (f, lft, u) in bvh.FACE_OFFSETS_M.items():
        out[:, J19[n]] = head + np.array([f, lft, u])
    # feet on the floor: lowest ankle at ~8 cm
    out[..., 2] += 0.08 - out[:, [J19["left_ankle"], J19["right_ankle"]], 2].min()
    # rotate by heading and translate along the path
    c, sn = np.cos(H)[:, None], np.sin(H)[:, None]
    x, y = out[..., 0].copy(), out[..., 1].copy()
    out[..., 0] = c * x - sn * y + P[:, None, 0]
    out[..., 1] = sn * x + c * y + P[:, None, 1]
    return out


def _presence(T: int, cfg: SceneConfig, rng: np.random.Generator) -> np.ndarray:
    """(T,) bool presence of one person (all True unless enter/leave is on and drawn for them)."""
    present = np.ones(T, dtype=bool)
    if not cfg.enter_leave or rng.random() >= cfg.enter_leave_fraction:
        return present
    min_len = min(int(cfg.min_present_s * cfg.fps), T)
    start = int(rng.integers(0, T - min_len + 1))
    end = int(rng.integers(start + min_len, T + 1))
    present[:] = False
    present[start:end] = True
    if rng.random() < cfg.return_fraction and end - start >= 3 * min_len // 2 + 2:
        g0 = int(rng.integers(start + min_len // 2, end - min_len // 2 - 1))
        g1 = min(end - 1, g0 + max(int(rng.integers(min_len // 2, min_len + 1)), 1))
        g1 = min(g1, g0 + (end - start) - min_len)  # the absence leaves min_present_s on stage in all
        present[g0 : max(g0, g1)] = False
    return present


def make_scene(room: Room, config: SceneConfig | None = None, **overrides) -> Scene:
    """Generate a seeded scene of ``config.n_people`` people in ``room`` (see the module docstring)."""
    cfg = config or SceneConfig()
    if overrides:
        cfg = dataclasses.replace(cfg, **overrides)
    rng = np.random.default_rng(cfg.seed)
    T, P = cfg.n_frames, cfg.n_people
    pool = [] if cfg.motion == "procedural" else _clip_pool(cfg)
    if cfg.motion == "mocap" and not pool:
        raise FileNotFoundError(
            "SceneConfig(motion='mocap'): no BVH clips found; set ROOMCAP_MOCAP or ROOMCAP_SHARED "
            "(expects <shared>/data/motion) or use motion='procedural'."
        )
    long_enough = np.array([bvh.clip_duration_s(f) >= cfg.duration_s for f in pool], dtype=bool)
    perm = rng.permutation(len(pool)) if pool else np.zeros(0, np.int64)
    order = [int(i) for i in perm if long_enough[i]] + [int(i) for i in perm if not long_enough[i]]
    gt = np.full((T, P, 19, 3), np.nan)
    names: list[str] = []
    placed: list[np.ndarray] = []
    total_bad = 0
    for p in range(P):
        result, name = None, "procedural"
        tries = 0
        while pool and result is None and tries < max(3 * len(pool), 10):
            if not order:  # every clip used: reuse them in a new order
                order = list(rng.permutation(len(pool)))
            path = pool[order.pop(0)]
            tries += 1
            xyz = bvh.load_bvh_body19(path, cfg.fps)
            if not _usable(xyz, cfg):
                continue
            motion = xyz[_pingpong_window(len(xyz), T, rng)]
            result = _place(motion, room, placed, cfg, rng)
            name = path.stem
        if result is None:
            motion = procedural_walk(T, cfg.fps, room, rng)
            result, name = (motion, 0), "procedural"
        m, bad = result
        total_bad += bad
        m = m.copy()
        m[~_presence(T, cfg, rng)] = np.nan
        placed.append(m)
        gt[:, p] = m
        names.append(name)
    if total_bad:
        log.info(
            "scene seed %d: %d person-frames inside furniture or too close to another person",
            cfg.seed,
            total_bad,
        )
    return Scene(gt, np.arange(P), cfg.fps, room, tuple(names), cfg)


# ---------------------------------------------------------------------------------------------
# session folders


def write_session_toml(lay: SessionLayout, scene: Scene, rig: CameraRig, writer: str) -> None:
    """The synthetic session's ``session.toml``; ``writer`` names the function that wrote the session."""
    save_toml(
        lay.session_toml,
        {
            "schema": "session/1",
            "cameras": list(rig.names),
            "fps": float(scene.fps),
            "synthetic": True,
            "seed": int(scene.config.seed),
            "n_people": int(scene.n_people),
        },
        header=f"synthetic session ({writer})",
    )


def write_session(scene: Scene, rendering, rig: CameraRig, root: str | os.PathLike) -> SessionLayout:
    """Write a session folder the 3D stages can run on.

    ``calib/rig.toml``, ``keypoints/<cam>.npz`` (one :class:`~roomcap.keypoints.detections.Detections` per
    camera), ``session.toml`` and ``gt.npz`` (schema ``synthetic_gt/1``: ``gt_xyz_m (T,P,19,3)``,
    ``person_ids (P,)``, ``fps``, ``clip_names (P,)``, ``cameras (C,)``, ``time_offsets_frames (C,)``,
    ``time_drifts_ppm (C,)``, ``visible (C,T,P,19)`` and ``gt_index_<cam> (T,P_c)`` = the scene person
    of each detection row, -1 for a false positive, -2 for padding).
    """
    lay = SessionLayout(root)
    lay.calib_dir.mkdir(parents=True, exist_ok=True)
    lay.keypoints_dir.mkdir(parents=True, exist_ok=True)
    rig.save(lay.calib_dir / "rig.toml", source="synthetic")
    for det in rendering.detections:
        det.save(lay.detections(det.camera))
    write_session_toml(lay, scene, rig, "synthetic.world.write_session")
    arrays = {
        "schema": schema_tag(GT_SCHEMA, GT_VERSION),
        "gt_xyz_m": scene.gt_xyz_m.astype(np.float64),
        "person_ids": scene.person_ids,
        "fps": np.float64(scene.fps),
        "clip_names": np.array(scene.clip_names),
        "cameras": np.array(rig.names),
        "time_offsets_frames": rendering.time_offsets_frames,
        "time_drifts_ppm": rendering.time_drifts_ppm,
        "visible": rendering.visible,
    }
    for name, gi in zip(rig.names, rendering.gt_index, strict=True):
        arrays[f"gt_index_{name}"] = gi
    save_npz(lay.root / "gt.npz", arrays)
    return lay


def load_gt(root: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read ``<session>/gt.npz`` written by :func:`write_session` (checks the schema)."""
    path = Path(root) / "gt.npz"
    data = load_npz(path, required=("schema", "gt_xyz_m", "person_ids", "fps"))
    check_schema(npz_str(data, "schema"), GT_SCHEMA, (GT_VERSION,), path)
    if data["gt_xyz_m"].ndim != 4:
        raise FormatError(path, "gt_xyz_m", f"expected (T,P,19,3), got {data['gt_xyz_m'].shape}.", "")
    return data
