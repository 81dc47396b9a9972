"""Exports of the track file for the user's next tool: TRC (OpenSim), C3D, CSV, JSON and BVH.

One file per person and format, named ``<session>_<track id>.<ext>`` (:func:`export_tracks`).

- **TRC** (OpenSim / Pose2Sim): metres, OpenSim's axes (y up: world (x, y, z) -> file (x, z, -y)),
  Pose2Sim's marker names (``Nose``, ``Neck``, ``LShoulder`` ... ``LBigToe``, ``LSmallToe``, ``LHeel``;
  :data:`POSE2SIM_NAMES`; with a ``whole_body`` track from BODY_25B, ``Neck`` and ``Head`` are its
  detected upper neck and head top, as in Pose2Sim, not body19's mid-shoulder point; hand joints keep their
  COCO-WholeBody names, ``left_hand_root``, ``left_thumb1`` ... ``right_pinky_finger4``). OpenSim refuses
  blank cells, so: interior gaps of a joint up to
  ``max_gap`` frames (Pose2Sim's ``interp_if_gap_smaller_than``, 10) are filled by linear
  interpolation and **flagged** (a ``<name>.filled.csv`` list of frame, time and marker beside the
  TRC; residual 0, C3D's "modelled" value, in the C3D); markers known in fewer than ``min_coverage`` of the
  person's frames after filling are left out of the file (named in the report); then frames in which a
  remaining marker is still unknown are **left out** (the file is not split: Frame# keeps the track
  file's frame number and Time its time, so the left-out frames show as jumps; OpenSim's IK takes
  frames by their time).
- **C3D** through ezc3d: the same markers, labels and coordinates as the TRC over every frame of the
  person's span; the residual of a point is its positional uncertainty ``std_m`` in metres
  (``POINT:SCALE`` -0.001, so 1 mm steps up to 0.255 m), 0 for points filled by interpolation (C3D's
  "modelled" value) and -1 for unknown points (C3D's "invalid"). ezc3d writes the header scale as -1
  whatever POINT:SCALE says; spec readers (the ``c3d`` package) reject that mismatch, so the header
  word is set to POINT:SCALE after writing.
- **CSV** and **JSON** carry the track file as it is (no filling; its ``flags`` bits say observed /
  interpolated / predicted / smoothed).
- **CSV** tidy, one row per known joint and frame: ``frame, time_s, person, joint, x, y, z,
  confidence, std_m, flags`` (world metres, z up, as the track file); :func:`read_csv` reads it back.
- **JSON**: :func:`roomcap.track.trackfile.export_json` for one track (confidence, std_m, flags).
- **BVH**: the fitted skeleton (:mod:`roomcap.outputs.skeleton_fit`), written by
:func:`roomcap.outputs.bvh.write_bvh`; a whole-body track's fingers are bones hanging off the wrists
(4 per finger from the hand root, COCO-WholeBody names).

``ExportOptions(lowpass_hz=6)`` (``tracks export --lowpass 6``) low-pass filters the positions first, as
Pose2Sim filters its 3D before OpenSim (:func:`lowpass`: Butterworth, order 4, zero phase). Off by
default: both trackers already smooth their output (on Pose2Sim's balancing trial it changed OpenSim's
marker errors by under 0.5 mm; BENCHMARKS.md).
"""

from __future__ import annotations

import csv
import io
import logging
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError, RoomcapError
from roomcap.core.fileio import atomic_path, atomic_write_text
from roomcap.keypoints.skeletons import HANDS
from roomcap.outputs.bvh import write_bvh
from roomcap.outputs.skeleton_fit import fill_gaps, fit_skeletons, person_span
from roomcap.outputs.skeleton_fit_file import FitError
from roomcap.track.trackfile import (
    SMOOTHED,
    TrackFile,
    export_json,
    track_index,
    world_to_yup,
    write_trc_table,
)

log = logging.getLogger(__name__)


# Track file joint name -> Pose2Sim marker name (Pose2Sim's skeletons.py / Markers_*.xml).
POSE2SIM_NAMES = {
    "nose": "Nose",
    "neck": "Neck",
    "pelvis": "Hip",
    "head": "Head",
    "head_top": "Head",
    "upper_neck": "Neck",
    "left_foot_index": "LBigToe",
    "right_foot_index": "RBigToe",
    "left_eye": "LEye",
    "right_eye": "REye",
    "left_ear": "LEar",
    "right_ear": "REar",
    "left_shoulder": "LShoulder",
    "right_shoulder": "RShoulder",
    "left_elbow": "LElbow",
    "right_elbow": "RElbow",
    "left_wrist": "LWrist",
    "right_wrist": "RWrist",
    "left_hip": "LHip",
    "right_hip": "RHip",
    "left_knee": "LKnee",
    "right_knee": "RKnee",
    "left_ankle": "LAnkle",
    "right_ankle": "RAnkle",
    "left_big_toe": "LBigToe",
    "left_small_toe": "LSmallToe",
    "left_heel": "LHeel",
    "right_big_toe": "RBigToe",
    "right_small_toe": "RSmallToe",
    "right_heel": "RHeel",
}


# Joints that take a Pose2Sim name over another joint with the same name: OpenPose BODY_25B's detected
# upper neck and head top are Pose2Sim's Neck and Head (body19's neck is the mid-shoulder point).
PREFERRED = ("upper_neck", "head_top")


class ExportError(RoomcapError, ValueError):
    """Input that cannot be exported as asked; the message says what is wrong and what to do."""


def marker_name(joint: str) -> str:
    """Pose2Sim's name of a joint; hand joints as COCO-WholeBody names them (``left_thumb1``,
    ``right_pinky_finger4``: :data:`roomcap.keypoints.skeletons.HANDS`, as RTMW / Pose2Sim's whole-body
    layouts write them); others in CamelCase with L/R prefixes (``left_pinky`` -> ``LPinky``)."""
    if joint in POSE2SIM_NAMES:
        return POSE2SIM_NAMES[joint]
    if joint in HANDS:
        return joint
    side = ""
    for pre, s in (("left_", "L"), ("right_", "R")):
        if joint.startswith(pre):
            side, joint = s, joint[len(pre) :]
    return side + "".join(w.capitalize() for w in joint.split("_"))


def parse_formats(text: str) -> tuple[str, ...]:
    fmts = tuple(f.strip().lower().lstrip(".") for f in text.split(",") if f.strip())
    bad = [f for f in fmts if f not in EXPORTERS]
    if bad or not fmts:
        raise ExportError(
            f"unknown export format {bad or repr(text)}; choose from {','.join(EXPORTERS)} "
            "(comma-separated, e.g. --format trc,bvh)."
        )
    return tuple(dict.fromkeys(fmts))


@dataclass
class MarkerTable:
    """One person's markers ready for TRC/C3D: ``xyz_m (T,M,3)`` world, over the person's span ``rows``."""

    track_id: int
    joints: list[int]  # track file joint index per marker
    names: list[str]
    rows: np.ndarray  # (T',) track file row index of the person's span
    xyz_m: np.ndarray  # (T',M,3) world, NaN where unknown after filling
    std_m: np.ndarray  # (T',M)
    filled: np.ndarray  # (T',M) bool
    complete: np.ndarray  # (T',) bool: every marker known (the TRC frames)
    dropped_markers: dict[str, float] = field(default_factory=dict)  # name -> coverage


def marker_table(
    tf: TrackFile, track: int, max_gap: int = 10, min_coverage: float = 0.5, joints: list[str] | None = None
) -> MarkerTable:
    """Select, name and fill one person's markers (module docstring: the TRC rules)."""
    k = track_index(tf, track)
    span = np.flatnonzero(person_span(tf, k))
    if not len(span):
        raise ExportError(f"track {track} has no known joint in any frame; nothing to export.")
    rows = np.arange(span[0], span[-1] + 1)
    want = list(range(len(tf.joint_names))) if joints is None else [tf.joint_names.index(n) for n in joints]
    xyz, std, filled = fill_gaps(tf.xyz_m[rows, k][:, want], tf.std_m[rows, k][:, want], max_gap)
    known = np.isfinite(xyz).all(-1)
    cover = known[np.isin(rows, span)].mean(0)
    names_all = [marker_name(tf.joint_names[j]) for j in want]
    keep = [i for i in range(len(want)) if cover[i] >= min_coverage]
    # two joints with one Pose2Sim name: the detected one (upper_neck, head_top) over the derived
    # or coarser one (body19's mid-shoulder neck, head), else the better covered
    seen: dict[str, int] = {}
    for i in sorted(keep, key=lambda i: (tf.joint_names[want[i]] not in PREFERRED, -cover[i])):
        seen.setdefault(names_all[i], i)
    dup = [i for i in keep if seen[names_all[i]] != i]
    keep = sorted(seen.values())
    dropped = {names_all[i]: float(cover[i]) for i in range(len(want)) if i not in keep and i not in dup}
    complete = known[:, keep].all(-1) if keep else np.zeros(len(rows), bool)
    if not keep or not complete.any():
        worst = sorted((float(cover[i]), names_all[i]) for i in range(len(want)))[:5]
        raise ExportError(
            f"track {track} has no frame in which all its markers are known, even after filling gaps of up "
            f"to {max_gap} frames (least covered: "
            + ", ".join(f"{n} {c:.0%}" for c, n in worst)
            + "). Export fewer markers (--min-coverage higher), fill longer gaps (--max-gap), or use "
            "CSV/JSON, which keep unknown joints as empty."
        )
    return MarkerTable(
        track_id=int(track),
        joints=[want[i] for i in keep],
        names=[names_all[i] for i in keep],
        rows=rows,
        xyz_m=xyz[:, keep],
        std_m=std[:, keep],
        filled=filled[:, keep],
        complete=complete,
        dropped_markers=dropped,
    )


def _time_s(tf: TrackFile) -> np.ndarray:
    if tf.t_ns.any():
        return (tf.t_ns - tf.t_ns[0]) / 1e9
    return np.arange(tf.n_frames) / tf.fps


# ----------------------------------------------------------------------------- writers


def write_trc(
    tf: TrackFile, track: int, path: str | os.PathLike, table: MarkerTable | None = None
) -> MarkerTable:
    """OpenSim TRC of one person (module docstring); returns the table it wrote."""
    mt = table or marker_table(tf, track)
    sel = mt.complete
    rows = mt.rows[sel]
    write_trc_table(path, mt.names, world_to_yup(mt.xyz_m[sel]), tf.fps, _time_s(tf)[rows], rows + 1)
    fill = np.argwhere(mt.filled[sel])
    flag_path = Path(path).with_suffix(".filled.csv")
    if len(fill):
        lines = ["frame,time_s,marker"] + [
            f"{rows[t] + 1},{_time_s(tf)[rows[t]]:.6f},{mt.names[m]}" for t, m in fill
        ]
        atomic_write_text(flag_path, "\n".join(lines) + "\n")
    elif flag_path.exists():
        flag_path.unlink()
    return mt


C3D_SCALE = -0.001  # POINT:SCALE: residuals in 1 mm steps (float points are not scaled)


def write_c3d(
    tf: TrackFile, track: int, path: str | os.PathLike, table: MarkerTable | None = None
) -> MarkerTable:
    """C3D of one person via ezc3d (module docstring: residuals carry ``std_m``)."""
    try:
        import ezc3d
    except ImportError:
        raise ExportError(
            "C3D export needs ezc3d: pip install 'roomcap[c3d]' (or pip install ezc3d)."
        ) from None
    mt = table or marker_table(tf, track)
    T, M = mt.xyz_m.shape[:2]
    pts = world_to_yup(mt.xyz_m)  # (T,M,3)
    known = np.isfinite(pts).all(-1)
    # ezc3d truncates residual / scale to an integer: half a step up makes that the nearest millimetre
    steps = np.round(np.clip(np.nan_to_num(mt.std_m, nan=0.255), 0.001, 0.255) / -C3D_SCALE)
    res = np.where(known, (steps + 0.5) * -C3D_SCALE, -1.0)
    res = np.where(known & mt.filled, 0.0, res)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [tf.fps]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(mt.names)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    c.add_parameter("POINT", "SCALE", [C3D_SCALE])
    c.add_parameter("POINT", "DESCRIPTIONS", tuple(f"{tf.joint_names[j]} (y up, metres)" for j in mt.joints))
    c.add_parameter("ROOMCAP", "TRACK_ID", [int(mt.track_id)])
    c.add_parameter("ROOMCAP", "FIRST_FRAME", [int(mt.rows[0])])
    data = np.ones((4, M, T))
    data[:3] = np.where(known[..., None], pts, np.nan).transpose(2, 1, 0)
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = res.T[None].astype(np.float64)
    with atomic_path(path) as tmp:
        c.write(str(tmp))
        with open(tmp, "r+b") as f:  # header words 7-8: the scale factor (ezc3d writes -1)
            f.seek(12)
            f.write(struct.pack("<f", C3D_SCALE))
    return mt


CSV_COLUMNS = ("frame", "time_s", "person", "joint", "x", "y", "z", "confidence", "std_m", "flags")


def write_csv(tf: TrackFile, track: int, path: str | os.PathLike) -> int:
    """Tidy CSV of one person (world metres, z up); returns the number of rows."""
    k = track_index(tf, track)
    t_s = _time_s(tf)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    ts, js = np.nonzero(tf.mask[:, k])
    for t, j in zip(ts.tolist(), js.tolist(), strict=True):
        x, y, z = tf.xyz_m[t, k, j].tolist()
        s = tf.std_m[t, k, j]
        w.writerow(
            [
                int(tf.frame_index[t]),
                f"{t_s[t]:.6f}",
                int(track),
                tf.joint_names[j],
                f"{x:.6f}",
                f"{y:.6f}",
                f"{z:.6f}",
                f"{tf.confidence[t, k, j]:.4f}",
                "" if not np.isfinite(s) else f"{s:.6f}",
                int(tf.flags[t, k, j]),
            ]
        )
    atomic_write_text(path, buf.getvalue())
    return len(ts)


def read_csv(path: str | os.PathLike, joint_names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """Read a tidy CSV back: ``frame (T,)``, ``time_s (T,)``, ``person (K,)``, ``joint_names (J,)``,
    ``xyz_m (T,K,J,3)``, ``confidence``, ``std_m``, ``flags`` (T,K,J); NaN / 0 where no row."""
    path = Path(path)
    with open(path, newline="") as f:
        r = csv.DictReader(f)
        if tuple(r.fieldnames or ())[: len(CSV_COLUMNS) - 1] != CSV_COLUMNS[:-1]:
            raise FormatError(path, None, f"expected columns {list(CSV_COLUMNS)}, got {r.fieldnames}.")
        rows = list(r)
    frames = sorted({int(x["frame"]) for x in rows})
    people = sorted({int(x["person"]) for x in rows})
    names = list(joint_names or dict.fromkeys(x["joint"] for x in rows))
    fi = {v: i for i, v in enumerate(frames)}
    pi = {v: i for i, v in enumerate(people)}
    ji = {v: i for i, v in enumerate(names)}
    T, K, J = len(frames), len(people), len(names)
    out = {
        "frame": np.asarray(frames),
        "time_s": np.zeros(T),
        "person": np.asarray(people),
        "joint_names": np.asarray(names),
        "xyz_m": np.full((T, K, J, 3), np.nan),
        "confidence": np.zeros((T, K, J)),
        "std_m": np.full((T, K, J), np.nan),
        "flags": np.zeros((T, K, J), np.uint8),
    }
    for x in rows:
        t, k, j = fi[int(x["frame"])], pi[int(x["person"])], ji[x["joint"]]
        out["time_s"][t] = float(x["time_s"])
        out["xyz_m"][t, k, j] = (float(x["x"]), float(x["y"]), float(x["z"]))
        out["confidence"][t, k, j] = float(x["confidence"])
        out["std_m"][t, k, j] = float(x["std_m"]) if x["std_m"] else np.nan
        out["flags"][t, k, j] = int(x.get("flags") or 0)
    return out


# ----------------------------------------------------------------------------- one command


@dataclass
class ExportOptions:
    formats: tuple[str, ...] = ("trc",)
    max_gap: int = 10  # frames
    min_coverage: float = 0.5
    multi_bvh: bool = False  # also one BVH with every person
    lowpass_hz: float = 0.0  # > 0: TRC/C3D/CSV/JSON low-pass filtered (:func:`lowpass`); BVH is the fit's


def lowpass(tf: TrackFile, cutoff_hz: float, order: int = 4) -> TrackFile:
    """The track file low-pass filtered as Pose2Sim filters its 3D (``[filtering.butterworth]``, order 4,
    cut-off 6 Hz by default there): a Butterworth of ``order / 2`` run forwards and backwards (zero
    phase, ``order`` in all), per track and joint, over each run of known frames; runs shorter than the
    filter's padding (3 * (order / 2 + 1) frames + 1) are left as they are. Filtered joints get the
    ``SMOOTHED`` flag; unknown joints stay unknown."""
    from scipy.signal import butter, filtfilt  # lazy: only the filter needs scipy.signal

    nyq = tf.fps / 2
    if not (0 < cutoff_hz < nyq):
        raise ExportError(
            f"low-pass cut-off {cutoff_hz} Hz: must be above 0 and below half the frame rate "
            f"({nyq:g} Hz at {tf.fps:g} fps); Pose2Sim uses 6 Hz."
        )
    if order < 2 or order % 2:
        raise ExportError(f"low-pass order {order}: must be even and >= 2 (forwards + backwards).")
    b, a = butter(order // 2, cutoff_hz / nyq, "low")
    pad = 3 * max(len(a), len(b))
    xyz = tf.xyz_m.astype(np.float64)
    flags = tf.flags.copy()
    known = np.isfinite(xyz).all(-1)
    for k in range(tf.n_tracks):
        for j in range(len(tf.joint_names)):
            idx = np.flatnonzero(known[:, k, j])
            for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
                if len(run) > pad:
                    xyz[run, k, j] = filtfilt(b, a, xyz[run, k, j], axis=0, padlen=pad)
                    flags[run, k, j] |= SMOOTHED
    return replace(tf, xyz_m=xyz.astype(np.float32), flags=flags)


@dataclass
class ExportReport:
    files: list[Path] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def export_tracks(
    tf: TrackFile,
    out_dir: str | os.PathLike,
    session: str,
    options: ExportOptions | None = None,
    persons: list[int] | None = None,
    fit=None,
) -> ExportReport:
    """Write ``<out_dir>/<session>_<track id>.<ext>`` for every person and format.

    ``fit`` is a :class:`roomcap.outputs.skeleton_fit.SkeletonFit` of ``tf`` (BVH); fitted on the fly when
    None."""
    options = options or ExportOptions()
    out_dir = Path(out_dir)
    ids = tf.track_id.tolist() if persons is None else [int(p) for p in persons]
    for p in ids:  # an unknown id is refused before anything is made
        track_index(tf, p)
    rep = ExportReport()
    if not ids:
        rep.notes.append("the track file has no tracks; nothing written.")
        return rep
    fmts = options.formats
    if options.lowpass_hz:
        tf = lowpass(tf, options.lowpass_hz)
        rep.notes.append(
            f"positions low-pass filtered (Butterworth, order 4, zero phase, {options.lowpass_hz:g} Hz)"
            + ("; the BVH is the skeleton fit's, not filtered" if "bvh" in fmts else "")
        )
    strict = persons is not None  # every track: one that cannot be exported is skipped with a note
    if "bvh" in fmts and fit is None:
        rep.notes.append(f"no skeleton fit was given: fitted the skeletons of tracks {ids} now")
        fit = fit_skeletons(tf, track_ids=ids, skip_unfittable=not strict)
    if "bvh" in fmts:
        rep.notes.extend(f"BVH left out: {n}" for n in fit.notes)

    made = [d for d in (out_dir, *out_dir.parents) if not d.exists()]  # removed again if nothing is written
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        for p in ids:
            try:
                rep.files.extend(_export_person(tf, p, out_dir / f"{session}_{p}", options, fit, rep))
            except (ExportError, FitError) as e:
                if strict:
                    raise
                rep.notes.append(f"track {p} skipped: {e}")
        if not rep.files:
            raise ExportError("nothing could be exported: " + "; ".join(rep.notes))
    except BaseException:
        for d in made:  # the folders this call made, innermost first, while they are empty
            try:
                d.rmdir()
            except OSError:
                break
        raise
    if "bvh" in fmts and options.multi_bvh and len(fit.track_id) > 1:
        path = out_dir / f"{session}_all.bvh"
        write_bvh(fit, path, track_ids=fit.track_id.tolist())
        rep.files.append(path)
    return rep


@dataclass(frozen=True)
class PersonExport:
    """What the exporters of one person share: the track file, the person's track id, the gap-filled marker
    table (when a format uses it) and the skeleton fit (when a format uses it)."""

    tf: TrackFile
    person: int
    table: MarkerTable | None
    fit: object | None


@dataclass(frozen=True)
class Exporter:
    """One output format: ``write(job, path)`` writes one person's file; ``uses_markers``: the format takes
    the gap-filled marker table (:func:`marker_table`); ``uses_fit``: the skeleton fit, and a person the fit
    left out (named in its notes) gets no file of this format."""

    write: Callable[[PersonExport, Path], object]
    uses_markers: bool = False
    uses_fit: bool = False


# The formats in the order ``tracks export --format`` lists them; a new format is one entry here.
EXPORTERS: dict[str, Exporter] = {
    "trc": Exporter(lambda job, path: write_trc(job.tf, job.person, path, job.table), uses_markers=True),
    "c3d": Exporter(lambda job, path: write_c3d(job.tf, job.person, path, job.table), uses_markers=True),
    "bvh": Exporter(lambda job, path: write_bvh(job.fit, path, track_ids=[job.person]), uses_fit=True),
    "csv": Exporter(lambda job, path: write_csv(job.tf, job.person, path)),
    "json": Exporter(lambda job, path: export_json(job.tf, path, track=job.person)),
}


def _export_person(
    tf: TrackFile, p: int, stem: Path, options: ExportOptions, fit, rep: ExportReport
) -> list[Path]:
    fmts = options.formats
    table = None
    if any(EXPORTERS[f].uses_markers for f in fmts):
        table = marker_table(tf, p, options.max_gap, options.min_coverage)
        if table.dropped_markers:
            rep.notes.append(
                f"track {p}: left out markers known in < {options.min_coverage:.0%} of its frames: "
                + ", ".join(f"{n} ({c:.0%})" for n, c in table.dropped_markers.items())
            )
        n_out = int((~table.complete).sum())
        if n_out:
            rep.notes.append(
                f"track {p}: {n_out} of {len(table.rows)} frames left out of the TRC (a marker unknown "
                f"after filling gaps of up to {options.max_gap} frames)"
            )
    job = PersonExport(tf, p, table, fit)
    files = []
    for fmt in fmts:
        exporter = EXPORTERS[fmt]
        if exporter.uses_fit and p not in fit.track_id.tolist():
            continue  # named in the fit's notes
        path = stem.with_suffix(f".{fmt}")
        exporter.write(job, path)
        files.append(path)
    return files
