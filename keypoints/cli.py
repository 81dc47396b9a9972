"""``keypoints`` console script.

keypoints list                              model descriptions, where each file is, model sets
keypoints fetch NAME [--model-dir DIR]      download a model into the cache and check its sha256
keypoints run SESSION                       raw/<cam>.* -> keypoints/<cam>.npz
keypoints run VIDEO... --out DIR            explicit videos (camera name = file stem, or cam=path)
keypoints run TRIAL/videos --out DIR        every video in a folder (Pose2Sim demo layout)
keypoints import PATH --out SESSION/keypoints   other tools' 2D (caliscope xy_*.csv, OpenPose JSON)
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

from roomcap.calibrate.formats import import_rig
from roomcap.capture.session import videos_in
from roomcap.core.cli import Parser, guarded, nonnegative_int, output_folder, positive_int
from roomcap.core.errors import InputError
from roomcap.core.fileio import sha256_file
from roomcap.core.progress import Bars
from roomcap.keypoints import registry
from roomcap.keypoints.registry import ModelError


def _list(args) -> int:
    specs = registry.list_specs(args.model_dir)
    print(f"{'name':24s} {'role':9s} {'skeleton':12s} status")
    for name, s in sorted(specs.items()):
        try:
            where = str(registry.resolve(s, args.model_dir, verify=False))
        except ModelError:
            where = "not downloaded" + (f" (keypoints fetch {name})" if s.urls else "")
        print(f"{name:24s} {s.role:9s} {s.skeleton or '-':12s} {where}")
    print("\nmodel sets:")
    for name, ms in registry.model_sets().items():
        print(f"  {name:14s} {ms.detector + ' + ' if ms.detector else ''}{ms.pose}  {ms.description}")
    print("\npresets (keypoints run --preset; [keypoints] preset in pipeline.toml):")
    default_preset, table = registry.presets()
    for name, settings in table.items():
        default = " (default)" if name == default_preset else ""
        print(f"  {name:10s} {', '.join(f'{k}={v}' for k, v in settings.items())}{default}")
    print(f"\nsearch path: {[str(d) for d in registry.model_dirs(args.model_dir)]}")
    return 0


def _fetch(args) -> int:
    with Bars(unit="B") as bars:
        path = registry.fetch(args.name, args.model_dir, force=args.force, progress=bars)
    sha = sha256_file(path)
    spec = registry.get_spec(args.name, args.model_dir)
    if spec.sha256:
        print(f"{args.name}: {path} (sha256 {sha}, as its description says)")
    else:
        print(
            f"{args.name}: {path} (sha256 {sha}). Its description has no checksum: this one is recorded in "
            f"{registry.lock_file(path.parent)} and every later load is checked against it."
        )
    return 0


def _parse_videos(items: list[str]) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for it in items:
        if "=" in it and not Path(it).exists():
            cam, p = it.split("=", 1)
            out[cam] = Path(p)
        elif Path(it).is_dir():
            out.update(videos_in(it))
        else:
            out[Path(it).stem] = Path(it)
    return out


def _run(args) -> int:
    from roomcap.keypoints import presets, runtime, video  # lazy: loads onnxruntime

    over: dict = {"runtime": runtime.RuntimeConfig(threads=args.threads, model_dir=args.model_dir or "")}
    if args.models:
        over["model_set"] = args.models
    if args.refine_passes is not None:
        over["refine_passes"] = args.refine_passes
    cfg = presets.preset_config(args.preset, **over)
    first = Path(args.inputs[0])
    if len(args.inputs) == 1 and first.is_dir() and (first / "raw").is_dir():
        with Bars(unit="fr") as bars:
            paths = video.run_session(
                first,
                cameras=args.cameras,
                config=cfg,
                progress=bars,
                max_frames=args.max_frames,
                camera_groups=args.camera_groups or os.cpu_count() or 1,
            )
    else:
        if not args.out:
            raise InputError("--out DIR is needed for explicit videos (or give one session folder).")
        output_folder(args.out)
        videos = _parse_videos(args.inputs)
        if args.cameras:
            videos = {c: p for c, p in videos.items() if c in args.cameras}
        missing = [f"{c}={p}" for c, p in videos.items() if not p.is_file()]
        if missing:  # checked before the models load, so a typo is found at once
            raise InputError(f"these videos do not exist: {', '.join(missing)}. Check the paths.")
        rig = None
        if (
            args.calib
        ):  # any format calibrate reads (rig.toml, Pose2Sim/aniposelib TOML, Qualisys .qca.txt, ...)
            rig = import_rig(args.calib)
            missing = [c for c in videos if c not in rig.names]
            if missing:
                print(
                    f"keypoints run: cameras {missing} are not in {args.calib} ({rig.names})", file=sys.stderr
                )
                return 1
        with Bars(unit="fr") as bars:
            rep = video.run_videos(
                videos,
                args.out,
                cfg,
                rig=rig,
                progress=bars,
                max_frames=args.max_frames,
                camera_groups=args.camera_groups or os.cpu_count() or 1,
            )
        for c, (fi, msg) in rep.decode_errors.items():
            print(f"WARNING camera {c}: {msg}; kept frames before {fi}", file=sys.stderr)
        paths = rep.paths
    for c, p in paths.items():
        print(f"{c}: {p}")
    return 0


def _import(args) -> int:
    from roomcap.keypoints.importers import import_2d

    if not Path(args.path).exists():
        raise InputError(f"{args.path} does not exist.")
    output_folder(args.out)
    paths = import_2d(
        args.path,
        args.out,
        fmt=args.format,
        skeleton=args.skeleton,
        fps=args.fps,
        cameras=args.cameras,
        hand_sides="model" if args.model_hand_sides else "body",
    )
    for c, p in paths.items():
        print(f"{c}: {p}")
    return 0


def _main(argv: list[str] | None = None) -> int:
    ap = Parser(prog="keypoints", description="2D multi-person keypoints through ONNX models")
    ap.add_argument(
        "--model-dir",
        default=None,
        help="folder with model files / descriptions (default: $ROOMCAP_MODELS, else <shared>/models)",
    )
    ap.add_argument("-v", "--verbose", action="store_true", help="log progress messages")
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="list model descriptions and sets")
    f = sub.add_parser("fetch", help="download a model and check its sha256")
    f.add_argument("name", help="model name (keypoints list)")
    f.add_argument("--force", action="store_true", help="download again even when the file is there")
    r = sub.add_parser("run", help="detect keypoints in a session or in videos")
    r.add_argument(
        "inputs", nargs="+", help="a session folder, videos (cam=path allowed) or a folder of videos"
    )
    r.add_argument(
        "--out", default=None, help="output folder for explicit videos (default: a session's keypoints/)"
    )
    r.add_argument(
        "--calib",
        default=None,
        help="calibration to check camera names and video sizes against (default: a session's "
        "calib/rig.toml)",
    )
    r.add_argument(
        "--preset",
        default="",
        help="speed/accuracy preset: fast, balanced (the default), accurate, feet, hands, feet_hands, legacy "
        "(`keypoints list`)",
    )
    r.add_argument(
        "--models", default=None, help="model set (keypoints list) or 'detector+pose'; default: the preset's"
    )
    r.add_argument("--cameras", nargs="*", default=None, help="only these cameras (default: every camera)")
    r.add_argument(
        "--max-frames",
        type=positive_int,
        default=None,
        help="only the first N frames of each video (default: all)",
    )
    r.add_argument(
        "--threads", type=nonnegative_int, default=0, help="onnxruntime threads (0 = onnxruntime's choice)"
    )
    r.add_argument(
        "--camera-groups",
        type=nonnegative_int,
        default=0,
        help="cameras split over this many threads, each with its own models (0 = one per core)",
    )
    r.add_argument(
        "--refine-passes",
        type=nonnegative_int,
        default=None,
        help="top-down: extra pose passes on upright crops from the previous pass (0 = faster; default: "
        "KeypointPipelineConfig's, 2)",
    )
    im = sub.add_parser(
        "import", help="other tools' 2D keypoints into detections files (caliscope xy_*.csv, OpenPose JSON)"
    )
    im.add_argument(
        "path",
        help="caliscope xy_<tracker>.csv (or its folder), an OpenPose json folder or a folder of them",
    )
    im.add_argument("--out", required=True, help="output folder, usually SESSION/keypoints")
    im.add_argument(
        "--format", default="auto", choices=("auto", "caliscope", "openpose"), help="input format"
    )
    im.add_argument(
        "--skeleton", default=None, help="OpenPose layout (body25b, body25, coco18, ...; default: guessed)"
    )
    im.add_argument("--fps", type=float, default=None, help="OpenPose: frame rate for timestamps")
    im.add_argument("--cameras", nargs="*", default=None, help="only these cameras (default: every one)")
    im.add_argument(
        "--model-hand-sides",
        action="store_true",
        help="caliscope: keep the hand model's left/right labels (default: each hand on the side of the "
        "body's nearer wrist, a hand found twice kept once)",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s"
    )
    return {"list": _list, "fetch": _fetch, "run": _run, "import": _import}[args.cmd](args)


main = guarded("keypoints", _main)


if __name__ == "__main__":
    sys.exit(main())
