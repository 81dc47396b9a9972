"""``capture-run``: record cameras into a session, synchronise recordings offline, repair after a kill.

::

    capture-run --cameras cams.yaml --out DIR [--duration S] [--live]    record (Ctrl-C stops cleanly)
    capture-run check --cameras cams.yaml                                validate cams.yaml, open nothing
    capture-run sync SESSION [--keypoints DIR] [--max-lag-s 2] [--drift]  offsets from 2D keypoint speeds
    capture-run repair SESSION                                           after kill -9: fix timestamps
"""

from __future__ import annotations

import argparse
import functools
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path

from roomcap.capture.config import ConfigError, load_config, shared_sources
from roomcap.capture.factory import check_source
from roomcap.capture.live import BuildStages, LiveOutputs, LiveRunner
from roomcap.capture.offline_sync import LoadKeypoints, sync_audio, sync_session
from roomcap.capture.recorder import Recorder, RecorderError, repair
from roomcap.capture.session import SessionLayout
from roomcap.capture.sources import SourceError
from roomcap.capture.streamcopy import recording_mode
from roomcap.core.cli import Parser, guarded, positive_float
from roomcap.core.errors import FormatError
from roomcap.core.redact import redact

log = logging.getLogger("roomcap.capture")

_SUBCOMMANDS = ("record", "check", "sync", "repair")


def _record_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="capture-run",
        description="Record cameras from cams.yaml into a session folder (subcommands: check, sync, repair).",
    )
    p.add_argument("--cameras", required=True, help="cams.yaml (see capture/config.py for the schema)")
    p.add_argument("--out", help="session folder to create (default: 'out' in cams.yaml)")
    p.add_argument(
        "--duration",
        type=positive_float,
        default=None,
        help="seconds to record (default: until Ctrl-C or until every file source ends)",
    )
    p.add_argument(
        "--live", action="store_true", help="run keypoints/triangulation/tracking on every frame set"
    )
    p.add_argument(
        "--skip-failed-cameras",
        action="store_true",
        help="record the cameras that open; the ones that do not are reported and listed in session.toml",
    )
    p.add_argument(
        "--no-join",
        action="store_true",
        help="keep raw/<cam>/seg_* instead of joining them into raw/<cam>.mp4 (join later: repair)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    return p


def _record(
    argv: list[str], build_live: BuildStages | None = None, outputs: LiveOutputs | None = None
) -> int:

    parser = _record_parser()
    if outputs is not None:
        outputs.add_arguments(parser)
    args = parser.parse_args(argv)
    cfg = load_config(args.cameras)
    out = args.out or cfg.out
    if not out:
        print("capture-run: no output folder: pass --out DIR or set 'out' in cams.yaml.", file=sys.stderr)
        return 2
    if args.duration is not None and args.duration <= 0:
        print(f"capture-run: --duration must be positive, got {args.duration}.", file=sys.stderr)
        return 2
    text = Path(args.cameras).read_text(encoding="utf-8")
    shared = shared_sources(cfg)
    for w in shared:
        print(f"capture-run: warning: {redact(w)}", file=sys.stderr)
    live_on = args.live or cfg.live.enabled
    live = None
    if live_on:
        if build_live is None:
            print(
                "capture-run: live processing (--live, or live.enabled in cams.yaml) needs the pipeline's "
                "live "
                "stages: run `capture-run` (entry point pipeline.live:main; after an update reinstall with "
                "`pip install -e .`) or `python -m roomcap.pipeline.live`.",
                file=sys.stderr,
            )
            return 2
        # the stages are built on the live thread while the cameras start (their imports and the 2D
        # models' warm-up took about 1.5 s before a recording could start)
        live = LiveRunner(cfg, out, build_stages=build_live, build_in_background=True)
    rec = Recorder(
        cfg,
        out,
        duration_s=args.duration,
        frameset_sink=live.queue if live else None,
        cams_yaml_text=text,
        skip_failed_cameras=args.skip_failed_cameras,
        join=not args.no_join,
    )
    close_outputs = outputs.open(args, live, rec) if outputs is not None else None
    if live:
        live.watch(rec.stop_event)  # --duration, Ctrl-C or the sources' end stop the live loop at once
        live.start()
    stop_bar = _start_bar(args.duration, len(cfg.cameras)) if not args.quiet and args.duration else None
    try:
        summary = rec.run()
    finally:
        if stop_bar:
            stop_bar()
        if live:
            live.stop()
        if close_outputs is not None:
            close_outputs()
    return _print_summary(out, rec, summary, shared, live)


def _start_bar(duration_s: float, n_cameras: int) -> Callable[[], None]:
    """Show a bar of the seconds recorded, ticked once a second by a thread; returns what closes it."""
    import threading

    from tqdm import tqdm

    bar = tqdm(total=round(duration_s), unit="s", desc=f"recording {n_cameras} cameras")
    stop_bar = threading.Event()

    def tick():
        t0 = time.monotonic()
        while not stop_bar.wait(1.0):
            bar.n = min(round(time.monotonic() - t0), bar.total)
            bar.refresh()

    threading.Thread(target=tick, daemon=True).start()

    def close() -> None:
        stop_bar.set()
        bar.close()

    return close


def _print_summary(out, rec: Recorder, summary: dict, shared: list[str], live: LiveRunner | None) -> int:
    """Print what was recorded per camera, the skew and the warnings; the exit code (1: stopped early)."""
    print(f"session: {out} ({summary['status']}; {rec.stop_reason})")
    for name, c in summary["cameras"].items():
        if c.get("recorded") is False:
            print(f"  {name}: NOT RECORDED (skipped: {c.get('failed', '')})")
            continue
        gaps = c.get("gaps", [])
        print(
            f"  {name}: {c.get('frames_written', 0)} frames, dropped {c.get('dropped_queue', 0)} (queue) + "
            f"{c.get('dropped_source', 0)} (source), {len(gaps)} gap(s), ended: {c.get('ended', '')}"
        )
        if c.get("stalls"):
            st = c["stalls"]
            print(f"    stalled {len(st)} time(s): no frame for up to {max(x['seconds'] for x in st):.1f} s")
        if "joined" in c:
            print(
                f"    -> {c['video']} ({c['frames_in_video']} frames)"
                if c["joined"]
                else f"    -> segments kept in raw/{name}/: {c.get('join_message', '')}"
            )
        if c.get("recording"):
            tail = c.get("copy_tail_dropped", 0)
            more = f"; the last {tail} frame(s), an unfinished group of pictures, not written" if tail else ""
            head = c.get("copy_head_dropped", 0)
            more += f"; {head} frame(s) before the stream's first keyframe not written" if head else ""
            print(f"    recording: {redact(c['recording'])}{more}")
    t = summary.get("timing", {})
    if "skew_ms_median" in t:
        print(
            f"  skew between cameras: median {t['skew_ms_median']:.2f} ms, p95 {t['skew_ms_p95']:.2f} ms; "
            f"{t['complete_sets']}/{t['sets']} complete frame sets"
        )
    for w in shared:  # again beside the skew it makes meaningless
        print(f"capture-run: warning: {redact(w)}", file=sys.stderr)
    if live:
        print("  live: " + redact(live.summary_line()))
    if summary.get("failed_cameras"):
        print(
            f"capture-run: warning: {len(summary['failed_cameras'])} camera(s) not recorded: "
            f"{', '.join(summary['failed_cameras'])} (listed in session.toml failed_cameras)",
            file=sys.stderr,
        )
    if summary["status"] != "complete":
        print(f"capture-run: recording stopped early: {rec.stop_reason}", file=sys.stderr)
        return 1
    return 0


def _check(argv: list[str]) -> int:

    p = Parser(
        prog="capture-run check",
        description="Parse cams.yaml and list its cameras. Exit 0 when it is usable, 1 when it parses but "
        "something is probably wrong (two cameras reading one source; said on stderr), 2 when it is "
        "invalid.",
    )
    p.add_argument("--cameras", required=True, help="cams.yaml to check")
    args = p.parse_args(argv)
    cfg = load_config(args.cameras)  # the parser recording uses: a source it refuses fails here
    for c in cfg.cameras:
        check_source(c)  # the source recording would build, checked without opening it
        print(f"{c.name}: {c.kind} {c.source_redacted} resolution={c.resolution} fps={c.fps} codec={c.codec}")
        print(f"  recording: {redact(recording_mode(c))}")
    problems = shared_sources(cfg)
    for w in problems:
        print(f"capture-run check: warning: {redact(w)}", file=sys.stderr)
    return 1 if problems else 0


def _sync_parser() -> argparse.ArgumentParser:
    """The arguments of ``capture-run sync``."""
    p = Parser(
        prog="capture-run sync",
        description="Estimate per-camera time offsets (and "
        "drift) from 2D keypoint speeds and write them into session.toml [sync].",
    )
    p.add_argument("session", help="session folder (keypoints/<cam>.npz or --openpose folders)")
    p.add_argument("--reference", help="camera the others are aligned to (default: the first by name)")
    p.add_argument("--max-lag-s", type=positive_float, default=2.0, help="largest offset searched, seconds")
    p.add_argument("--drift", action="store_true", help="also estimate a linear drift (long recordings)")
    p.add_argument(
        "--openpose",
        nargs="*",
        default=None,
        metavar="CAM=DIR",
        help="read OpenPose JSON folders instead of keypoints/<cam>.npz",
    )
    p.add_argument(
        "--audio",
        nargs="*",
        default=None,
        metavar="CAM=VIDEO",
        help="sync by the audio tracks of these videos instead of keypoints (no CAM=VIDEO: the "
        "session's raw/<cam>.mp4)",
    )
    p.add_argument(
        "--fps",
        type=positive_float,
        default=None,
        help="frame rate when the session has none (default: from the detections' timestamps)",
    )
    p.add_argument("--dry-run", action="store_true", help="print, do not write session.toml")
    return p


def _sync(argv: list[str], load_keypoints: LoadKeypoints | None = None) -> int:
    """``capture-run sync``: offsets from the audio tracks (``--audio``) or from 2D keypoint speeds."""
    args = _sync_parser().parse_args(argv)
    if args.audio is not None:
        return _sync_by_audio(args)
    openpose = None
    if args.openpose is not None:
        openpose = {}
        for item in args.openpose:
            cam, _, d = item.partition("=")
            if not d:
                print(f"capture-run sync: --openpose expects CAM=DIR, got {item!r}", file=sys.stderr)
                return 2
            openpose[cam] = d
    res = sync_session(
        args.session,
        reference=args.reference,
        max_lag_s=args.max_lag_s,
        drift=args.drift,
        openpose_dirs=openpose,
        fps=args.fps,
        write=not args.dry_run,
        load_keypoints=load_keypoints,
    )
    for cam, r in res["cameras"].items():
        print(
            f"  {cam}: offset {r['offset_frames']:+.2f} frames ({r['offset_s'] * 1e3:+.1f} ms), "
            f"drift {r.get('drift_ppm', 0.0):+.0f} ppm, {_trust_text(r)}"
        )
    print(TRUST_LEGEND)
    return 0


def _sync_by_audio(args: argparse.Namespace) -> int:
    """``capture-run sync --audio``: offsets from the videos' audio tracks (default: the session's own)."""
    videos = dict(item.partition("=")[::2] for item in args.audio)
    if not videos:  # the session's own recordings
        lay = SessionLayout(args.session)
        videos = {c: str(lay.video(c)) for c in lay.raw_cameras()}
        unjoined = [c for c, v in videos.items() if Path(v).is_dir()]
        if unjoined:
            print(
                f"capture-run sync: cameras {unjoined} are still segment folders; join them first "
                f"(capture-run repair {args.session}) or pass --audio CAM=VIDEO",
                file=sys.stderr,
            )
            return 2
        if len(videos) < 2:
            print(
                f"capture-run sync: {lay.raw_dir} holds {len(videos)} videos; --audio needs two",
                file=sys.stderr,
            )
            return 2
    if any(not v for v in videos.values()):
        print("capture-run sync: --audio expects CAM=VIDEO pairs", file=sys.stderr)
        return 2
    res = sync_audio(
        args.session, videos, reference=args.reference, max_lag_s=args.max_lag_s, write=not args.dry_run
    )
    for cam, r in res["cameras"].items():
        print(f"  {cam}: offset {r['offset_s'] * 1e3:+.1f} ms (audio), {_trust_text(r)}")
    print(TRUST_LEGEND)
    return 0


TRUST_LEGEND = (
    "  trust: good = correlation >= 0.2 and peak >= 2x any other lag's; fair = >= 0.1 and >= 1.3x; "
    "poor = check before use (a clap or jump seen by all cameras, or --audio)"
)


def _trust_text(r: dict) -> str:
    if r.get("trust") == "reference":
        return "reference"
    ratio = r.get("peak_ratio", float("nan"))
    ratio_s = "no other peak" if ratio >= 99 else (">10" if ratio >= 10 else f"{ratio:.2f}")
    return f"correlation {r['correlation']:.2f}, peak ratio {ratio_s}: trust {r.get('trust', '?')}"


def _repair(argv: list[str]) -> int:

    p = Parser(
        prog="capture-run repair",
        description="After a kill (or --no-join): drop unfinished segments, rebuild the timestamp files and "
        "join each camera's segments into raw/<cam>.mp4 (stream copy, frame count checked).",
    )
    p.add_argument("session", help="session folder (raw/<cam>/seg_*)")
    p.add_argument("--no-join", action="store_true", help="only fix the timestamps, keep the segments")
    args = p.parse_args(argv)
    if not Path(args.session).is_dir():
        print(f"capture-run repair: {args.session} is not a folder.", file=sys.stderr)
        return 2
    counts, joins = repair(args.session, join=not args.no_join)
    if not counts:
        print(f"  nothing to repair in {args.session} (no segment folders under raw/)")
    kept = 0
    for cam, n in counts.items():
        j = joins.get(cam)
        if j is None:
            print(f"  {cam}: {n} frames")
        elif j.ok:
            print(f"  {cam}: {n} frames -> {j.video}")
        else:
            kept += 1
            print(f"  {cam}: {n} frames, segments kept: {j.message}")
    return 1 if kept else 0


def _main(
    argv: list[str] | None = None,
    build_live: BuildStages | None = None,
    outputs: LiveOutputs | None = None,
    load_keypoints: LoadKeypoints | None = None,
) -> int:

    argv = list(sys.argv[1:] if argv is None else argv)
    verbose = "-v" in argv or "--verbose" in argv
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    cmd = argv[0] if argv and argv[0] in _SUBCOMMANDS else "record"
    rest = argv[1:] if argv and argv[0] in _SUBCOMMANDS else argv
    try:
        if cmd == "record":
            return _record(rest, build_live, outputs)
        if cmd == "sync":
            return _sync(rest, load_keypoints)
        return {"check": _check, "repair": _repair}[cmd](rest)
    except (ConfigError, FormatError, SourceError, RecorderError, ValueError) as e:
        print(f"capture-run: error: {redact(str(e))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("capture-run: interrupted", file=sys.stderr)
        return 130


def make_main(
    build_live: BuildStages | None = None,
    outputs: LiveOutputs | None = None,
    load_keypoints: LoadKeypoints | None = None,
) -> Callable[..., int]:
    """``capture-run``'s entry with the live stages ``build_live``
    (:func:`roomcap.pipeline.live.build_stages`:
    the installed ``capture-run`` is ``pipeline.live:main``), what the live run sends out
    (``outputs``: :class:`roomcap.pipeline.live_outputs.Outputs`) and the reader of ``keypoints/<cam>.npz``
    for ``sync`` (``load_keypoints``: ``keypoints.detections.Detections.load``); without them ``--live`` and
    ``sync`` from keypoints say where to go."""
    return guarded(
        "capture-run",
        functools.partial(_main, build_live=build_live, outputs=outputs, load_keypoints=load_keypoints),
    )


main = make_main()


if __name__ == "__main__":
    sys.exit(main())
