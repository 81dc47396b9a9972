"""``tracks`` console script: from the track file to the user's next tool.

SESSION is a session folder (its ``track/tracks.npz``, else the live track ``track/live.npz``), a
track file, or a chunked track's parts folder (``tracks.parts/``, ``live.parts/``).

tracks export SESSION|tracks.npz --format trc,c3d,bvh,csv,json [--person ID] --out DIR
    one file per person and format, ``<session>_<track id>.<ext>`` (see outputs/export.py)
tracks fit SESSION|tracks.npz
    one skeleton per person: writes track/skeleton_fit.npz beside the track file (beside the live track
    track/live.npz: live_skeleton_fit.npz); a whole-body track's finger bone lengths are listed per person
tracks opensim SESSION|tracks.npz [--setup DIR] [--person ID] --out DIR
    Pose2Sim's OpenSim model scaled and inverse kinematics on the TRC (needs the opensim extra)
tracks stream SESSION|tracks.npz --stream lsl,osc [--osc-to HOST:PORT] [--speed 1]
    replay the track at its own clock to the Lab Streaming Layer and/or OSC (outputs/lsl_osc.py)
tracks view SESSION --rrd FILE.rrd
    the session as a Rerun recording: cameras, frames, 2D detections, 3D tracks (outputs/rerun_recording.py)

Also runnable as ``python -m roomcap.outputs.cli``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from roomcap.core.cli import Parser, guarded
from roomcap.core.errors import RoomcapError
from roomcap.outputs import lsl_osc, rerun_recording
from roomcap.outputs.export import ExportOptions, export_tracks, parse_formats
from roomcap.outputs.opensim_ik import default_setup_dir, run_opensim
from roomcap.outputs.skeleton_fit import FitError, file_sha256, fit_path, fit_skeletons, load_or_fit
from roomcap.track.trackfile import TrackFile, resolve_track_file

log = logging.getLogger(__name__)


class UsageError(RoomcapError, ValueError):
    pass


def resolve_tracks(path: str | Path) -> tuple[Path, str]:
    """A session folder, a track file or its parts folder -> (track file path, session name)
    (:func:`roomcap.track.trackfile.resolve_track_file`)."""
    return resolve_track_file(path)


def _persons(text: str | None) -> list[int] | None:
    if not text:
        return None
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UsageError(f"--person takes track ids (integers, comma-separated), got {text!r}.") from None


def _export(args) -> int:

    fmts = parse_formats(args.format)
    path, session = resolve_tracks(args.tracks)
    tf = TrackFile.load(path)
    persons = _persons(args.person)
    unknown = sorted(set(persons or ()) - set(tf.track_id.tolist()))
    if unknown:
        raise UsageError(
            f"--person: there is no track {','.join(map(str, unknown))} in {path} (its tracks: "
            f"{tf.track_id.tolist()}); nothing was written."
        )
    fit = None
    if "bvh" in fmts:
        fit, made = load_or_fit(path, tf, persons)
        if made:
            print(
                f"note: {path} has no current skeleton fit beside it (tracks fit); fitted the skeletons now."
            )
    opts = ExportOptions(
        formats=fmts,
        max_gap=args.max_gap,
        min_coverage=args.min_coverage,
        multi_bvh=args.multi,
        lowpass_hz=args.lowpass,
    )
    rep = export_tracks(tf, args.out, args.session or session, opts, persons=persons, fit=fit)
    for n in rep.notes:
        print(f"note: {n}")
    for f in rep.files:
        print(f)
    return 0


def _fit(args) -> int:

    path, _ = resolve_tracks(args.tracks)
    tf = TrackFile.load(path)
    fit = fit_skeletons(tf, tracks_sha256=file_sha256(path), skip_unfittable=True)
    for n in fit.notes:
        print(f"note: left out: {n}")
    if not len(fit.track_id):
        raise FitError("no track could be fitted (see the notes above).")
    out = fit_path(path)
    fit.save(out)
    import numpy as np

    for k, tid in enumerate(fit.track_id):
        e = fit.fit_error_m[:, k]
        print(
            f"track {tid}: {int(fit.span[:, k].sum())} frames, fit error median "
            f"{1000 * np.nanmedian(e):.1f} mm, p95 {1000 * np.nanpercentile(e, 95):.1f} mm"
        )
        for line in finger_lines(fit, k, tf):
            print(f"track {tid}: {line}")
    print(out)
    return 0


def finger_lines(fit, k: int, tf: TrackFile) -> list[str]:
    """The fit's finger bone lengths of track index ``k``, one line per hand (mm, hand root to tip, per
    finger), and how steady the track's own finger bones are (median over the bones seen in 5 frames or
    more of the std over time of their length, frames where both ends are observed); none without hands."""
    import numpy as np

    from roomcap.keypoints.skeletons import FINGERS, finger_bones
    from roomcap.track.trackfile import OBSERVED, track_index

    fl = fit.finger_lengths_m(k)
    if not fl:
        return []
    lines = []
    for side in ("left", "right"):
        parts = [
            f"{f.replace('_finger', '')} " + "/".join(f"{1000 * v:.0f}" for v in fl[f"{side}_{f}"])
            for f in FINGERS
            if f"{side}_{f}" in fl and np.isfinite(fl[f"{side}_{f}"]).all()
        ]
        lines.append(f"{side} hand bones (mm, root to tip): " + (", ".join(parts) if parts else "not seen"))
    kt = track_index(tf, int(fit.track_id[k]))
    X = tf.xyz_m[:, kt].astype(np.float64)
    obs = (tf.flags[:, kt] & OBSERVED) > 0
    lengths, stds = [], []
    for bones in finger_bones(tf.joint_names).values():
        for p, c in bones:
            both = obs[:, p] & obs[:, c] & np.isfinite(X[:, p]).all(-1) & np.isfinite(X[:, c]).all(-1)
            if both.sum() >= 5:
                d = np.linalg.norm(X[both, c] - X[both, p], axis=-1)
                lengths.append(np.median(d))
                stds.append(np.std(d))
    if stds:
        lines.append(
            f"finger bones in the track: {len(stds)} seen in 5 frames or more, length median "
            f"{1000 * np.median(lengths):.1f} mm, std over time median {1000 * np.median(stds):.1f} mm"
        )
    return lines


def _opensim(args) -> int:

    path, session = resolve_tracks(args.tracks)
    tf = TrackFile.load(path)
    setup = Path(args.setup) if args.setup else default_setup_dir()
    results = run_opensim(
        tf,
        Path(args.out),
        args.session or session,
        setup,
        persons=_persons(args.person),
        markerset=args.markerset,
        max_gap=args.max_gap,
    )
    for r in results:
        for n in r.notes:
            print(f"note: {n}")
        print(
            f"track {r.track_id}: {r.n_frames} frames, markers {len(r.markers)}; marker error RMS median "
            f"{1000 * r.rms_median_m:.1f} mm, max per frame median {1000 * r.max_median_m:.1f} mm"
        )
        print(r.mot)
        print(r.errors_csv)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="tracks", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-v", "--verbose", action="store_true", help="log progress messages")
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="TRC / C3D / BVH / CSV / JSON, one file per person and format")
    e.add_argument("tracks", help="session folder or tracks.npz")
    e.add_argument("--format", default="trc", help="comma-separated: trc,c3d,bvh,csv,json (default trc)")
    e.add_argument("--person", help="track id(s), comma-separated (default: every track)")
    e.add_argument("--out", type=Path, required=True, help="output folder")
    e.add_argument("--session", help="name used in the file names (default: the session folder's name)")
    e.add_argument(
        "--max-gap", type=int, default=10, help="TRC/C3D/BVH: fill gaps up to N frames (default 10)"
    )
    e.add_argument(
        "--min-coverage",
        type=float,
        default=0.5,
        help="TRC/C3D: leave out markers known in fewer than this share of the person's frames (default 0.5)",
    )
    e.add_argument("--multi", action="store_true", help="BVH: also one file with every person")
    e.add_argument(
        "--lowpass",
        type=float,
        default=0.0,
        metavar="HZ",
        help="TRC/C3D/CSV/JSON: zero-phase Butterworth low-pass, order 4, at HZ (Pose2Sim's default 6); "
        "default: none (the trackers smooth already)",
    )
    e.set_defaults(func=_export)
    f = sub.add_parser("fit", help="one skeleton per person -> track/skeleton_fit.npz")
    f.add_argument("tracks", help="session folder or tracks.npz")
    f.set_defaults(func=_fit)
    o = sub.add_parser("opensim", help="scale Pose2Sim's model and run inverse kinematics (opensim extra)")
    o.add_argument("tracks", help="session folder or tracks.npz")
    o.add_argument(
        "--setup", help="folder with the model, marker sets and setups (default: Pose2Sim's, shared)"
    )
    o.add_argument(
        "--markerset", default="Body25b", help="Body25b | Halpe26 | Coco17 | Blazepose (default Body25b)"
    )
    o.add_argument("--person", help="track id(s), comma-separated (default: every track)")
    o.add_argument("--out", type=Path, required=True, help="output folder (scaled model, motion files, logs)")
    o.add_argument("--session", help="name used in the file names (default: the session folder's name)")
    o.add_argument("--max-gap", type=int, default=10, help="fill gaps up to N frames before IK")
    o.set_defaults(func=_opensim)
    lsl_osc.add_parser(sub, resolve_tracks)
    rerun_recording.add_parser(sub, resolve_tracks)
    return p


def _main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    return args.func(args)  # UsageError, ExportError, FitError, OpenSimError, FormatError: RoomcapErrors


main = guarded("tracks", _main)  # one message and exit 2 for bad input, 130 for Ctrl-C (core.cli)


if __name__ == "__main__":
    sys.exit(main())
