"""A synthetic replica of a motion-triggered recording: snapshots at irregular times (hundredths of a second
to days apart), 3 cameras, 1-3 people present, a detector that misses people and joints, no session.toml
(the detections carry only their timestamps). Shared by the time-lapse tests."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from roomcap.capture.session import SessionLayout
from roomcap.keypoints.detections import Detections
from roomcap.synthetic.render import RenderConfig, render
from roomcap.synthetic.rigs import kitchen
from roomcap.synthetic.world import SceneConfig, make_scene, write_session

SCENE_FPS = 100.0  # the world's clock: gaps down to 0.01 s are one of its frames


def snapshot_times(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,) seconds of the snapshots from the first, and (n,) the world frame each shows: gaps drawn
    log-normally about 75 s (from 0.01 s to 3 days), some in bursts a fraction of a second apart; the
    world advances by the gap where it is short (up to 2 s: the same people moving) and by 2-6 s where it
    is long (whoever is there minutes or days later)."""
    rng = np.random.default_rng(seed)
    gaps = np.clip(np.exp(rng.normal(np.log(75.0), 2.5, n - 1)), 0.01, 3 * 86400.0)
    burst = rng.random(n - 1) < 0.15  # some triggers fire again within a fraction of a second
    gaps[burst] = rng.choice([0.01, 0.04, 0.1, 0.25], burst.sum())
    world = np.where(gaps <= 2.0, gaps, rng.uniform(2.0, 6.0, n - 1))
    t = np.concatenate([[0.0], np.cumsum(gaps)])
    frames = np.concatenate([[0], np.cumsum(np.round(world * SCENE_FPS).astype(np.int64))])
    return t, frames


def make_replica(root: Path, n_snapshots: int = 60, seed: int = 5) -> tuple[Path, np.ndarray, np.ndarray]:
    """Write the replica session at ``root``; returns (root, gt (n,P,19,3), t_s (n,))."""
    t_s, frames = snapshot_times(n_snapshots, seed)
    rig, room = kitchen(3)
    duration = (frames[-1] + 1) / SCENE_FPS
    scene = make_scene(
        room,
        SceneConfig(
            n_people=3,
            duration_s=duration,
            fps=SCENE_FPS,
            seed=seed,
            enter_leave=True,
            enter_leave_fraction=0.34,
            motion="procedural",
        ),
    )
    snap = dataclasses.replace(scene, gt_xyz_m=scene.gt_xyz_m[frames])
    rd = render(
        snap,
        rig,
        RenderConfig(noise_px=2.0, missed_detection_rate=0.1, missed_joint_rate=0.05, seed=seed),
    )
    lay = write_session(snap, rd, rig, root)
    lay.session_toml.unlink()  # no nominal rate anywhere
    t_ns = (1_700_000_000 * 10**9 + np.round(t_s * 1e9)).astype(np.int64)
    for cam in lay.detection_cameras():
        d = Detections.load(lay.detections(cam))
        dataclasses.replace(d, t_ns=t_ns).save(lay.detections(cam))
    return root, snap.gt_xyz_m.astype(np.float64), t_s


def arm_pcp(gt: np.ndarray, xyz: np.ndarray) -> float:
    """PCP of the upper and lower arms (actor average; seed sec. 4.3's metric on the arms alone)."""
    from roomcap.triangulate import evaluate as ev

    r = ev.pcp(gt, xyz.astype(np.float64))
    arms = [v for k, v in r.per_actor_limb.items() if "arm" in k]
    per_actor = np.nanmean(np.stack(arms), 0)
    return float(np.nanmean(per_actor[r.n_frames > 0]))


def recall(gt: np.ndarray, xyz: np.ndarray) -> float:
    """Person-frames of the ground truth found within 0.3 m."""
    from roomcap.triangulate import evaluate as ev

    mot = ev.mot_metrics(gt, xyz.astype(np.float64), threshold_m=0.3)
    return 1.0 - mot.misses / mot.n_gt


__all__ = ["SessionLayout", "arm_pcp", "make_replica", "recall", "snapshot_times"]
