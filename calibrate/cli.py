"""``calibrate-run``: board calibration, and import/export of other tools' calibrations.

    calibrate-run calibrate RECORDING --board board.toml --out rig.toml   (what `make calibrate` runs)
    calibrate-run import FILE --out rig.toml [--format qualisys] [--scale-to-m 0.001] ...
    calibrate-run export rig.toml --format aniposelib --out calibration.toml

One small function per subcommand: ``_add_<name>(subparsers)`` registers its arguments and sets
``func`` to ``_run_<name>(args) -> int``. To add a subcommand, write those two functions and append
the registrar to ``SUBCOMMANDS``.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from roomcap.calibrate.boards import CalibrationError
from roomcap.calibrate.calibration import CalibrationConfig, calibrate_recording
from roomcap.calibrate.camera import CameraRig
from roomcap.calibrate.checks import rig_warnings
from roomcap.calibrate.extrinsics import LOSSES
from roomcap.calibrate.formats import (
    EXPORT_FORMATS,
    IMPORT_FORMATS,
    ImportOptions,
    detect_format,
    export_rig,
    import_rig,
)
from roomcap.calibrate.intrinsics import MODELS
from roomcap.core.cli import Parser, RawDescriptionHelpFormatter, guarded, positive_float
from roomcap.core.errors import FormatError, InputError
from roomcap.core.progress import Bars

log = logging.getLogger("roomcap.calibrate")


def _size_arg(text: str) -> tuple[str, tuple[int, int]]:
    """``WxH`` (every camera) or ``NAME=WxH`` (one camera) -> (name or "*", (w, h))."""
    name, _, size = text.rpartition("=")
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT or CAMERA=WIDTHxHEIGHT such as 1080x1920 or cam01=1080x1920, got {text!r}"
        ) from None
    return name or "*", (w, h)


# ----------------------------------------------------------------------------- import


def _add_import(sub: argparse._SubParsersAction) -> None:

    p = sub.add_parser(
        "import",
        help="convert a calibration file into rig.toml",
        description="Read a calibration (format detected from the file or given with --format) "
        "and write rig.toml (cam_from_world, metres, OpenCV pixels).",
    )
    p.add_argument(
        "file", type=Path, help="calibration file (EasyMocap: intri.yml, extri.yml or their folder)"
    )
    p.add_argument("--out", type=Path, required=True, help="rig.toml to write")
    p.add_argument("--format", choices=IMPORT_FORMATS, default=None, help="input format (default: detect)")
    p.add_argument(
        "--scale-to-m",
        type=positive_float,
        default=1.0,
        help="multiply translations by this to get metres (e.g. 0.001 for an aniposelib file in mm)",
    )
    p.add_argument(
        "--image-size",
        type=_size_arg,
        action="append",
        default=None,
        metavar="[CAM=]WxH",
        help="video size, for all cameras or one (repeat). Qualisys: when it differs from the calibrated "
        "window, the image is taken as cropped/padded at right/bottom; EasyMocap: when intri.yml lacks H_/W_",
    )
    p.add_argument(
        "--distortion-scale",
        type=positive_float,
        default=1.0,
        help="Qualisys: multiply distortion coefficients (1/64 = 0.015625 reproduces Pose2Sim)",
    )
    p.add_argument(
        "--view-rotation",
        choices=("sensor", "apply"),
        default="sensor",
        help="Qualisys: keep the sensor orientation or apply each camera's viewrotation",
    )
    p.add_argument(
        "--include-marker-cameras", action="store_true", help="Qualisys: import marker cameras too"
    )
    p.set_defaults(func=_run_import)


def _not_the_input(out: Path, given: Path, what: str, example: str) -> None:
    """Refuse an ``--out`` that is the input file: the write would replace it."""
    same = out.resolve() == given.resolve() or (out.exists() and given.exists() and out.samefile(given))
    if same:
        raise InputError(
            f"--out {out} is the input file {given}: writing it would replace the {what}. Give --out "
            f"another file name (e.g. {example} in another folder); nothing was written."
        )


def _run_import(args: argparse.Namespace) -> int:

    _not_the_input(args.out, args.file, "file being imported", "rig.toml")
    fmt = args.format or detect_format(args.file)
    opts = ImportOptions(
        scale_to_m=args.scale_to_m,
        image_size_wh=dict(args.image_size) if args.image_size else None,
        distortion_scale=args.distortion_scale,
        view_rotation=args.view_rotation,
        include_marker_cameras=args.include_marker_cameras,
    )
    rig = import_rig(args.file, fmt, opts)
    src = args.file
    digest = hashlib.sha256(src.read_bytes()).hexdigest()[:16] if src.is_file() else "folder"
    rig.save(args.out, source=f"calibrate-run import --format {fmt} {src.name} (sha256 {digest})")
    print(f"{args.out}: {len(rig)} cameras {rig.names} from {fmt} file {src}")
    for c in rig:
        print(
            f"  {c.name}: {c.size_wh[0]}x{c.size_wh[1]} {c.model} f=({c.K[0, 0]:.1f}, {c.K[1, 1]:.1f}) "
            f"centre_m={[round(float(v), 3) for v in c.center]}"
        )

    for w in rig_warnings(rig, str(args.out)):
        print(f"WARNING {w}", file=sys.stderr)
    return 0


# ----------------------------------------------------------------------------- export


def _add_export(sub: argparse._SubParsersAction) -> None:

    p = sub.add_parser(
        "export",
        help="write rig.toml in another tool's format",
        description="Write a rig.toml as aniposelib/Pose2Sim TOML or EasyMocap intri.yml/extri.yml.",
    )
    p.add_argument("rig", type=Path, help="rig.toml")
    p.add_argument("--format", choices=EXPORT_FORMATS, required=True, help="the other tool's format")
    p.add_argument("--out", type=Path, required=True, help="output file (easymocap: a folder)")
    p.set_defaults(func=_run_export)


def _run_export(args: argparse.Namespace) -> int:

    _not_the_input(args.out, args.rig, "rig being exported", "calibration.toml")
    rig = CameraRig.load(args.rig)
    written = export_rig(rig, args.out, args.format)
    print(f"wrote {', '.join(str(p) for p in written)} ({args.format}, {len(rig)} cameras)")
    return 0


# ----------------------------------------------------------------------------- calibrate (calibration.py)


_CALIBRATE_HELP = """Calibrate a multi-camera rig from a recording of a calibration board.

RECORDING is a folder with one video per camera (cam_0.mp4, cam_1.mp4, ...; the file name is the camera
name), or one folder of images per camera, or a flat folder of images named <camera><frame number>
(left01.jpg, right01.jpg). Frames with the same index are taken as simultaneous.

Move the board through the whole image of every camera, tilted in all directions, and make sure that
neighbouring cameras see it at the same time. The output folder (that of --out) receives rig.toml, the
cached detections and a report (report/report.toml, layout.png, coverage.png).

Example:
  calibrate-run calibrate recordings/calib --board charuco.toml --out calib/rig.toml
  calibrate-run calibrate recordings/calib --board charuco.toml --out calib/rig.toml --world board:120
"""


def _calibrate_arguments(p: argparse.ArgumentParser) -> None:
    p.description = _CALIBRATE_HELP
    p.formatter_class = RawDescriptionHelpFormatter
    p.add_argument("recording", type=Path, help="folder of per-camera videos or image folders")
    p.add_argument(
        "--board",
        type=Path,
        required=True,
        help='board file: roomcap board TOML (schema="board/1") or caliscope\'s charuco.toml',
    )
    p.add_argument("--out", type=Path, required=True, help="rig.toml to write (its folder gets the report)")
    p.add_argument(
        "--model",
        choices=MODELS,
        default="pinhole",
        help="lens model: pinhole (k1,k2,p1,p2,k3), pinhole4 (k1,k2,p1,p2), rational (8), "
        "fisheye (4) (default: pinhole)",
    )
    p.add_argument(
        "--refine-intrinsics",
        choices=("none", "focal_pp", "all"),
        default="none",
        help="let the bundle adjustment refine the intrinsics too (default: none = keep the "
        "per-camera calibration)",
    )
    p.add_argument(
        "--world",
        default="",
        help="world frame: camera:NAME (that camera's frame; default: the first camera) or "
        "board:FRAME (the board lying on the floor in that frame: origin at the board, z up)",
    )
    p.add_argument(
        "--intrinsics",
        default="",
        metavar="RIG_TOML",
        help="use the intrinsics of these cameras (same names) instead of calibrating them",
    )
    p.add_argument("--exclude", nargs="*", default=[], metavar="CAMERA", help="cameras to leave out")
    p.add_argument("--loss", choices=LOSSES, default="soft_l1", help="robust loss of the bundle adjustment")
    p.add_argument("--max-frames", type=int, default=1000, help="frames examined per camera (default 1000)")
    p.add_argument(
        "--intrinsic-frames",
        type=int,
        default=40,
        help="frames per camera for the intrinsics, chosen for coverage and diversity (default 40)",
    )
    p.add_argument(
        "--extrinsic-frames", type=int, default=300, help="board poses in the bundle adjustment (default 300)"
    )


def _run_calibrate(args: argparse.Namespace) -> int:
    """The CLI action: progress bars on stderr, summary on stdout, errors as 'what happened, what to do'."""
    try:
        cfg = CalibrationConfig(
            model=args.model,
            refine_intrinsics=args.refine_intrinsics,
            world=args.world,
            intrinsics_from=args.intrinsics,
            exclude=tuple(args.exclude),
            loss=args.loss,
            detect_max_frames=args.max_frames,
            intrinsic_frames=args.intrinsic_frames,
            extrinsic_frames=args.extrinsic_frames,
        )
        with Bars(unit="step") as progress:  # log lines above the bars, not through them
            out = calibrate_recording(args.recording, args.board, args.out, cfg, progress)
    except (CalibrationError, ValueError) as e:  # said as the other subcommands say it
        raise CalibrationError(str(e)) from None
    print(out.summary)
    print(f"wrote {args.out} and the report in {out.report['report'].parent}")
    return 0


def _add_calibrate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="calibrate a rig from a board recording of all cameras")
    _calibrate_arguments(p)
    p.set_defaults(func=_run_calibrate)


# ----------------------------------------------------------------------------- main

SUBCOMMANDS: list[Callable[[argparse._SubParsersAction], None]] = [_add_import, _add_export, _add_calibrate]


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="calibrate-run", description=__doc__.split("\n")[0].split(": ", 1)[1])
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in SUBCOMMANDS:
        add(sub)
    return parser


def _main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        return int(args.func(args) or 0)
    except FormatError as e:
        print(f"calibrate-run {args.command}: error: {e}", file=sys.stderr)
        return 2


main = guarded("calibrate-run", _main)


if __name__ == "__main__":
    sys.exit(main())
