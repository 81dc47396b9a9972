"""Synthetic sessions for tests and benchmarks: detections-only roomcap sessions from ``synthetic.world``.

``make_sessions(root, n)`` writes ``root/syn_00 .. syn_<n-1>``, each a ring rig with seeded people walking
(``calib/rig.toml``, ``keypoints/<cam>.npz``, ``session.toml``, ``gt.npz``); the stages triangulate, track,
forecast and report run on them without videos or models.
"""

from __future__ import annotations

import os
from pathlib import Path

from roomcap.synthetic import render, rigs, world


def make_session(
    root: str | os.PathLike,
    seed: int = 0,
    n_people: int = 2,
    duration_s: float = 2.0,
    fps: float = 25.0,
    n_cams: int = 4,
    noise_px: float = 1.0,
) -> Path:

    rig = rigs.ring_rig(n_cams, 3.0, seed=seed)
    scene = world.make_scene(
        rigs.ring_room(3.0), world.SceneConfig(n_people=n_people, duration_s=duration_s, fps=fps, seed=seed)
    )
    r = render.render(scene, rig, render.RenderConfig(noise_px=noise_px, seed=seed))
    return world.write_session(scene, r, rig, root).root


def make_sessions(root: str | os.PathLike, n: int, **kw) -> list[Path]:
    root = Path(root)
    return [make_session(root / f"syn_{i:02d}", seed=i, n_people=1 + i % 3, **kw) for i in range(n)]
