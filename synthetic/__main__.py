"""Write a synthetic session folder: ``python -m roomcap.synthetic OUT [--rig kitchen|ring] [--cams 12] ...``.

The folder holds ``calib/rig.toml``, ``keypoints/<cam>.npz``, ``session.toml`` and ``gt.npz`` (ground
truth), ready for ``reprocess OUT --stages triangulate,track``.
"""

from __future__ import annotations

import argparse
import sys

from roomcap.core.cli import guarded, nonnegative_int, positive_float, positive_int
from roomcap.synthetic import render as R
from roomcap.synthetic import rigs, world
from roomcap.synthetic.chunked import write_session_chunked


def _main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m roomcap.synthetic", description=__doc__.splitlines()[0])
    ap.add_argument("out", help="session folder to write")
    ap.add_argument("--rig", choices=("kitchen", "ring"), default="kitchen")
    ap.add_argument("--cams", type=positive_int, default=12)
    ap.add_argument("--people", type=nonnegative_int, default=8)
    ap.add_argument("--seconds", type=positive_float, default=10.0)
    ap.add_argument("--fps", type=positive_float, default=25.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--motion", choices=("auto", "mocap", "procedural"), default="auto")
    ap.add_argument("--enter-leave", action="store_true", help="people appear and disappear")
    ap.add_argument("--skeleton", default="body19")
    ap.add_argument("--noise-px", type=float, default=3.0)
    ap.add_argument("--missed-joints", type=float, default=0.1)
    ap.add_argument("--flips", type=float, default=0.02)
    ap.add_argument("--false-positives", type=float, default=0.1, help="per camera and frame")
    ap.add_argument("--missed-detections", type=float, default=0.02)
    ap.add_argument("--time-offset-std-frames", type=float, default=0.0)
    ap.add_argument("--time-drift-std-ppm", type=float, default=0.0)
    ap.add_argument(
        "--chunk-s",
        type=float,
        default=None,
        help="render and write in time chunks of this many seconds (bounded memory; default 60 for "
        "sessions over 5 minutes without time offsets, else 0 = at once)",
    )
    a = ap.parse_args(argv)
    if a.rig == "kitchen":
        rig, room = rigs.kitchen_rig(a.cams, seed=a.seed), rigs.kitchen_room()
    else:
        rig, room = rigs.ring_rig(a.cams, 3.0, seed=a.seed), rigs.ring_room(3.0)
    scene = world.make_scene(
        room,
        world.SceneConfig(
            n_people=a.people,
            duration_s=a.seconds,
            fps=a.fps,
            seed=a.seed,
            motion=a.motion,
            enter_leave=a.enter_leave,
        ),
    )
    cfg = R.RenderConfig(
        skeleton=a.skeleton,
        noise_px=a.noise_px,
        missed_joint_rate=a.missed_joints,
        flip_rate=a.flips,
        false_positive_rate=a.false_positives,
        missed_detection_rate=a.missed_detections,
        time_offset_std_frames=a.time_offset_std_frames,
        time_drift_std_ppm=a.time_drift_std_ppm,
        seed=a.seed,
    )
    chunk_s = a.chunk_s
    if chunk_s is None:
        plain = not (a.time_offset_std_frames or a.time_drift_std_ppm)
        chunk_s = 60.0 if a.seconds > 300 and plain else 0.0
    if chunk_s > 0:
        lay = write_session_chunked(scene, rig, cfg, a.out, chunk_s)
    else:
        lay = world.write_session(scene, R.render(scene, rig, cfg), rig, a.out)
    print(
        f"wrote {lay.root}: {len(rig)} cameras, {scene.n_people} people ({', '.join(scene.clip_names)}), "
        f"{scene.n_frames} frames at {scene.fps:g} fps"
    )
    return 0


main = guarded("python -m roomcap.synthetic", _main)


if __name__ == "__main__":
    sys.exit(main())
