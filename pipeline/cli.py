"""``reprocess PATH...``: find sessions under folders and run the pipeline on each.

Examples::

    reprocess recordings/                       # every session under recordings/, all stages
    reprocess S01 --stages triangulate,track --tracker greedy   # the ch. 4 tracker (default: particle)
    reprocess day1/ day2/ --out results/ --executor ray --address auto
    reprocess S01 --export trc,bvh               # then <session>/export/<session>_<track id>.trc|.bvh

One run at a time per session: a run holds <session output>/.roomcap/lock; another run on that session
refuses it (LOCKED, naming the holder's pid, host, start time and command) or, with --wait, waits. A lock
left by a killed run is taken over. Before a stage's outputs are trusted, their sizes and sha256 are checked
against the stage's record; outputs changed since are made again.

Exit codes: 0 every session ok; 1 a session failed, or is partial (a camera left out: its video could not
be read); 2 bad input, or a session locked by another run; 130 Ctrl-C (finished stages are kept).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from tqdm import tqdm

from roomcap.capture.session import SessionLayout
from roomcap.core.cli import Parser, guarded, output_folder, positive_int
from roomcap.core.errors import FormatError
from roomcap.core.fileio import atomic_write_text
from roomcap.outputs.export import ExportError, ExportOptions, export_tracks, parse_formats
from roomcap.outputs.skeleton_fit_file import FitError
from roomcap.pipeline.config import DEFAULT_TRACKER, STAGES, TRACKERS, PipelineConfig
from roomcap.pipeline.discover import SessionError, discover
from roomcap.pipeline.executors import EXECUTORS, run_sessions
from roomcap.pipeline.report import write_overlay_videos
from roomcap.pipeline.runner import SessionResult
from roomcap.track.trackfile import TrackFile


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="reprocess", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", help="session folders or folders containing sessions")
    p.add_argument(
        "--out",
        type=Path,
        help="write outputs to OUT/<session> (default: in place for roomcap "
        "sessions, <session>/roomcap for other layouts)",
    )
    p.add_argument("--stages", help=f"comma-separated subset of {','.join(STAGES)} (default: all)")
    p.add_argument(
        "--tracker",
        choices=TRACKERS,
        help=f"track stage: particle (ch. 5 particle filter) or greedy (ch. 4 matching in time); default: "
        f"{DEFAULT_TRACKER} (or [track] tracker of --config)",
    )
    p.add_argument(
        "--config", type=Path, help="pipeline TOML (see README, 'A pipeline TOML'; default: every default)"
    )
    p.add_argument(
        "--max-frames",
        type=positive_int,
        help="keypoints: process only the first N frames of each video (default: all)",
    )
    p.add_argument("--force", action="store_true", help="rerun stages even when their outputs are up to date")
    p.add_argument(
        "--wait",
        action="store_true",
        help="when another run is processing a session (it holds <session output>/.roomcap/lock), wait for "
        "it to finish, then go on (default: refuse that session, naming the other run, and exit 2)",
    )
    p.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="local",
        help="local: worker processes on this machine; ray: tasks on a Ray cluster (pip install "
        "'roomcap[cluster]')",
    )
    p.add_argument("--address", help="Ray cluster address (with --executor ray); default: start a local Ray")
    p.add_argument(
        "--workers", type=positive_int, help="sessions processed at once (default: half the cores)"
    )
    p.add_argument(
        "--export",
        help="after the stages, write the track file as FORMATS (comma-separated: trc,c3d,bvh,csv,json) "
        "to <session output>/export/ (see: tracks export --help; default: no export)",
    )
    p.add_argument(
        "--overlay",
        action="store_true",
        help="also write <session>/report/overlay/<cam>.mp4: each video with the detections and tracks drawn",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log what each stage does")
    return p


def export_results(results: list[SessionResult], formats: tuple[str, ...]) -> list[str]:
    """``tracks export`` of every session that ran; returns one error line per session that failed."""

    errors = []
    for r in results:
        if r.status != "ok":
            continue
        path = Path(r.out) / "track" / "tracks.npz"
        try:
            rep = export_tracks(TrackFile.load(path), Path(r.out) / "export", r.name, ExportOptions(formats))
        except (ExportError, FitError, FormatError, OSError) as e:
            errors.append(f"{r.name}: export failed: {e}")
            continue
        for n in rep.notes:
            print(f"{r.name}: note: {n}")
        print(f"{r.name}: exported {len(rep.files)} files to {Path(r.out) / 'export'}")
    return errors


def make_config(args: argparse.Namespace) -> PipelineConfig:
    """The pipeline config of ``--config`` with the command line's options in it, parsed once."""
    overrides: dict = {}
    if args.stages:
        overrides["stages"] = [s.strip() for s in args.stages.split(",") if s.strip()]
    if args.tracker:
        overrides["track"] = {"tracker": args.tracker}
    if args.max_frames:
        overrides["keypoints"] = {"max_frames": args.max_frames}
    if args.config:
        return PipelineConfig.load(args.config, overrides)
    return PipelineConfig.from_dict(overrides)


def format_table(results: list[SessionResult], stages: tuple[str, ...]) -> str:
    head = [
        "session",
        "status",
        "cameras",
        "frames",
        "people",
        "tracks",
        *[f"{s}_s" for s in stages],
        "message",
    ]
    rows = [head]
    for r in results:
        rows.append(
            [
                r.name,
                r.status,
                str(r.cameras),
                str(r.frames),
                str(r.people),
                str(r.tracks),
                *[f"{r.stage_s[s]:.2f}" if s in r.stage_s else "-" for s in stages],
                r.message[:160],
            ]
        )
    widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in rows)


def _inputs(args: argparse.Namespace) -> tuple[PipelineConfig, list, tuple[str, ...]] | str:
    """The config, the sessions and the export formats the command line names, or what is wrong."""
    export_formats: tuple[str, ...] = ()
    if args.export:
        try:
            export_formats = parse_formats(args.export)
        except ExportError as e:
            return f"--export: {e}"
    missing = [str(p) for p in args.paths if not Path(p).exists()]
    if missing:  # a typo is bad input, not a failed session (exit 2 before anything runs)
        return (
            f"{', '.join(missing)} {'does' if len(missing) == 1 else 'do'} not exist; pass session folders "
            "or folders of sessions."
        )
    if args.out is not None:
        output_folder(args.out)
    try:
        cfg = make_config(args)
        sources = discover(args.paths)
    except (FormatError, SessionError) as e:
        return str(e)
    if not sources:
        return (
            f"no sessions found under {args.paths}. A session is a folder with raw/ videos or "
            "keypoints/*.npz and calib/rig.toml, or a Pose2Sim trial (videos/ + calibration/)."
        )
    return cfg, sources, export_formats


def _run_with_bar(args: argparse.Namespace, cfg: PipelineConfig, sources: list) -> list[SessionResult]:
    bar = tqdm(total=len(sources), desc="sessions", unit="session", disable=None)

    def done(r: SessionResult) -> None:
        bar.update(1)
        bar.set_postfix_str(f"{r.name}: {r.status}")

    try:
        return run_sessions(
            sources,
            args.out,
            cfg,
            force=args.force,
            executor=args.executor,
            workers=args.workers,
            address=args.address,
            on_result=done,
            wait=args.wait,
        )
    finally:
        bar.close()


def _write_overlays(results: list[SessionResult]) -> None:
    for r in results:
        if r.status == "ok":
            try:
                print(f"{r.name}: overlay videos in {write_overlay_videos(SessionLayout(r.out))[0].parent}")
            except (FormatError, OSError, ValueError) as e:
                print(f"reprocess: {r.name}: no overlay videos ({e})", file=sys.stderr)


def _print_outcome(results: list[SessionResult], seconds: float) -> None:
    """One line of counts, then a line per session that is locked, partial or failed."""
    by = {k: [r for r in results if r.status == k] for k in ("failed", "partial", "locked")}
    print(
        f"{len(results) - sum(len(v) for v in by.values())} sessions ok, "
        + (f"{len(by['partial'])} partial, " if by["partial"] else "")
        + (f"{len(by['locked'])} locked, " if by["locked"] else "")
        + f"{len(by['failed'])} failed in {seconds:.1f} s"
    )
    for r in by["locked"]:  # another run holds the session
        print(f"LOCKED {r.name}: {r.message}", file=sys.stderr)
    for r in by["partial"]:  # ran without some cameras (skipped_cameras)
        print(f"PARTIAL {r.name}: cameras {sorted(r.skipped_cameras)} left out: {r.message}", file=sys.stderr)
    for r in by["failed"]:
        print(f"FAILED {r.name}: {r.message}", file=sys.stderr)


def _write_summaries(out: Path, results: list[SessionResult], table: str) -> bool:
    try:
        atomic_write_text(
            out / "reprocess_summary.json", json.dumps([r.to_dict() for r in results], indent=1)
        )
        atomic_write_text(out / "reprocess_summary.txt", table + "\n")
    except OSError as e:  # e.g. the disk filled up: the table above is the summary
        print(f"reprocess: could not write the summary files to {out} ({e}).", file=sys.stderr)
        return False
    return True


def _main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    inputs = _inputs(args)
    if isinstance(inputs, str):
        print(f"reprocess: {inputs}", file=sys.stderr)
        return 2
    cfg, sources, export_formats = inputs
    t0 = time.perf_counter()
    results = _run_with_bar(args, cfg, sources)
    if args.overlay:
        _write_overlays(results)
    table = format_table(results, tuple(s for s in STAGES if any(s in r.stage_s for r in results)))
    print(table)
    _print_outcome(results, time.perf_counter() - t0)
    export_errors = export_results(results, export_formats) if export_formats else []
    for e in export_errors:
        print(f"FAILED {e}", file=sys.stderr)
    if args.out and not _write_summaries(args.out, results, table):
        return 1
    if any(r.status == "locked" for r in results):
        return 2
    # partial: a camera could not be used, so some of the work failed (exit 1, as a failed session)
    return 1 if export_errors or any(r.status in ("failed", "partial") for r in results) else 0


main = guarded("reprocess", _main)


if __name__ == "__main__":
    sys.exit(main())
