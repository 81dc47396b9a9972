"""``make demo``: the whole chain on a Pose2Sim-style recording (default: its multi-person demo).

Imports the recording's calibration, extracts 2D keypoints, triangulates,
tracks (with ``reprocess``'s default tracker, the particle filter; ``--tracker greedy`` for the
chapter-4 tracker), previews forecasts and writes the HTML report::

    python -m roomcap.pipeline.demo --out out/demo \
        --recording ../shared/data/pose2sim/demo-wheel-0.10.49/Demo_MultiPerson
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from roomcap.core.cli import Parser, guarded
from roomcap.pipeline.cli import main as reprocess_main
from roomcap.pipeline.config import DEFAULT_TRACKER, TRACKERS


def default_recording() -> Path:
    shared = Path(os.environ.get("ROOMCAP_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))
    return shared / "data" / "pose2sim" / "demo-wheel-0.10.49" / "Demo_MultiPerson"


def _main(argv: list[str] | None = None) -> int:
    p = Parser(
        prog="python -m roomcap.pipeline.demo",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--recording",
        type=Path,
        default=default_recording(),
        help="a folder with videos/ and calibration/ (Pose2Sim layout) or a roomcap session",
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    p.add_argument(
        "--tracker",
        choices=TRACKERS,
        help=f"the track stage's tracker (default: reprocess's, {DEFAULT_TRACKER})",
    )
    args = p.parse_args(argv)
    if not args.recording.exists():
        print(
            f"demo: recording {args.recording} not found. Set ROOMCAP_SHARED to the shared/ folder or pass "
            "--recording.",
            file=sys.stderr,
        )
        return 2
    tracker = ["--tracker", args.tracker] if args.tracker else []
    rc = reprocess_main([str(args.recording), "--out", str(args.out), *tracker, "--workers", "1"])
    report = args.out / args.recording.name / "report" / "report.html"
    if rc == 0 and report.exists():
        print(f"report: {report.resolve()}")
    return rc


main = guarded("make demo", _main)


if __name__ == "__main__":
    sys.exit(main())
