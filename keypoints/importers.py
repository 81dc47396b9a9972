"""Other tools' 2D keypoints into detections files (``keypoints import PATH --out SESSION/keypoints``).

Read here:

- caliscope's ``xy_<tracker>.csv`` (one row per camera, synchronised frame and point: ``sync_index``,
  ``port``, ``frame_index``, ``frame_time``, ``point_id``, ``img_loc_x``, ``img_loc_y``, and the unused
  ``obj_loc_x``, ``obj_loc_y``): one detections file per port, camera ``cam_<port>`` (the names
  :func:`roomcap.calibrate.formats.caliscope.read_caliscope` gives the cameras of its ``config.toml``),
  ``frame_index`` = ``sync_index`` (caliscope's synchronised frame: the cameras' frames line up by it), the
  camera's own frame number kept as ``source_frame_index`` and ``t_ns`` from ``frame_time`` (seconds, one
  clock for every camera; 0 is the earliest time of the file). Point ids (MediaPipe Holistic, as caliscope
  numbers them): 0-32 the MediaPipe Pose landmarks (``blazepose33``: the same names as the project's body
  joints where they correspond, so nose, eyes, ears, shoulders ... ankles map to ``body19`` and the heels and
  foot tips to the feet), 100 + k the **right** hand's landmark k, 200 + k the **left** hand's (MediaPipe
  hand order, :data:`~roomcap.keypoints.skeletons.HAND_RIGHT`), 500 and up face mesh points (not kept).
  The layout is ``blazepose33_hands``; caliscope writes no confidence, so a point it wrote has score 1.
  With ``hand_sides="body"`` (the default) each view's hands are put on the side of the body's nearer wrist
  and a hand that both of Holistic's hand models found is kept once (:func:`~roomcap.keypoints.hands.
  hands_by_body_side`); ``"model"`` keeps the ids' sides as written.
- OpenPose JSON folders (:func:`~roomcap.keypoints.openpose_json.read_openpose_folder`): one folder of
  ``*.json`` (one camera) or a folder of ``<camera>_json`` folders (Pose2Sim's ``pose/`` layout), frame
  numbers from the file names; with OpenPose's hand keypoints (``--hand``) when the files have them
  (layout ``<body layout>_hands``).
"""

from __future__ import annotations

import csv
import logging
import os
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError, InputError
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.hands import hands_by_body_side
from roomcap.keypoints.openpose_json import read_openpose_folder
from roomcap.keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)

CALISCOPE_SKELETON = "blazepose33_hands"
_CALISCOPE_NEED = ("sync_index", "port", "point_id", "img_loc_x", "img_loc_y")
_CALISCOPE_KNOWN = (*_CALISCOPE_NEED, "frame_index", "frame_time", "obj_loc_x", "obj_loc_y", "")
_FACE_FIRST = 500  # caliscope's face mesh ids start here


def caliscope_point_index(point_id: np.ndarray) -> np.ndarray:
    """Joint index in ``blazepose33_hands`` of caliscope Holistic point ids; -1 for face points (>= 500),
    -2 for ids that are none of body (0-32), right hand (100-120), left hand (200-220) or face."""
    pid = np.asarray(point_id, np.int64)
    out = np.full(pid.shape, -2, np.int64)
    out[(pid >= 0) & (pid <= 32)] = pid[(pid >= 0) & (pid <= 32)]
    left0, right0 = 33, 33 + 21  # blazepose33 then HAND_LEFT then HAND_RIGHT
    r = (pid >= 100) & (pid <= 120)
    out[r] = right0 + pid[r] - 100
    left = (pid >= 200) & (pid <= 220)
    out[left] = left0 + pid[left] - 200
    out[pid >= _FACE_FIRST] = -1
    return out


def _read_csv_columns(path: Path) -> dict[str, np.ndarray]:
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as e:
        raise FormatError(
            path, None, f"cannot be read as CSV ({e}).", "Pass caliscope's xy_<tracker>.csv."
        ) from None
    if not rows:
        raise FormatError(path, None, "is empty.", "Pass caliscope's xy_<tracker>.csv.")
    header = [h.strip() for h in rows[0]]
    unknown = [h for h in header if h not in _CALISCOPE_KNOWN and not h.startswith("Unnamed")]
    if unknown:
        raise FormatError(
            path,
            None,
            f"unknown columns {unknown}; a caliscope xy file has {list(_CALISCOPE_KNOWN[:-1])}.",
            "Pass caliscope's xy_<tracker>.csv (not the xyz_ 3D file).",
        )
    missing = [h for h in _CALISCOPE_NEED if h not in header]
    if missing:
        raise FormatError(
            path, None, f"columns {missing} are missing (has {header}).", "Pass caliscope's xy_<tracker>.csv."
        )
    body = rows[1:]
    bad = [k + 2 for k, r in enumerate(body) if len(r) != len(header)]
    if bad:
        raise FormatError(path, None, f"line {bad[0]} has a different number of fields than the header.")
    cols: dict[str, np.ndarray] = {}
    for name in ("sync_index", "port", "point_id", "frame_index", "frame_time", "img_loc_x", "img_loc_y"):
        if name not in header:
            continue
        k = header.index(name)
        try:
            vals = np.array([float(r[k]) if r[k] != "" else np.nan for r in body], np.float64)
        except ValueError as e:
            raise FormatError(path, name, f"holds a value that is not a number ({e}).") from None
        if name in ("sync_index", "port", "point_id", "frame_index") and not np.isfinite(vals).all():
            line = int(np.flatnonzero(~np.isfinite(vals))[0]) + 2
            raise FormatError(path, name, f"is empty on line {line}.")
        cols[name] = vals
    return cols


def read_caliscope_xy(path: str | os.PathLike, hand_sides: str = "body") -> dict[str, Detections]:
    """caliscope ``xy_<tracker>.csv`` -> one :class:`Detections` per camera ``cam_<port>`` (module doc)."""
    path = Path(path)
    if hand_sides not in ("body", "model"):
        raise InputError(f"hand_sides must be 'body' or 'model', got {hand_sides!r}.")
    if not path.is_file():
        raise FormatError(
            path, None, "does not exist.", "Pass caliscope's recordings/<rec>/<TRACKER>/xy_*.csv."
        )
    c = _read_csv_columns(path)
    pid = c["point_id"].astype(np.int64)
    j = caliscope_point_index(pid)
    if (j == -2).any():
        bad = sorted({int(v) for v in pid[j == -2]})
        raise FormatError(
            path,
            "point_id",
            f"point ids {bad[:10]}{' ...' if len(bad) > 10 else ''} are not caliscope Holistic ids "
            "(0-32 body, 100-120 right hand, 200-220 left hand, 500+ face).",
            "Import the HOLISTIC (or POSE / HAND) tracker's xy file.",
        )
    n_face = int((j == -1).sum())
    if n_face:
        log.info("%s: %d face points (ids >= %d) are not kept", path, n_face, _FACE_FIRST)
    keep = j >= 0
    sync = c["sync_index"].astype(np.int64)[keep]
    port = c["port"].astype(np.int64)[keep]
    j = j[keep]
    xy = np.stack([c["img_loc_x"][keep], c["img_loc_y"][keep]], -1)
    src_fi = c["frame_index"].astype(np.int64)[keep] if "frame_index" in c else None
    ftime = c.get("frame_time")
    ftime = ftime[keep] if ftime is not None else None
    t0 = np.nanmin(ftime) if ftime is not None and np.isfinite(ftime).any() else None
    skel = get_skeleton(CALISCOPE_SKELETON)
    out: dict[str, Detections] = {}
    for p in np.unique(port):
        m = port == p
        frames, row = np.unique(sync[m], return_inverse=True)
        T = len(frames)
        dup = np.unique(row * skel.n_joints + j[m], return_counts=True)[1]
        if (dup > 1).any():
            raise FormatError(path, "point_id", f"port {p}: a point appears twice in one sync_index.")
        xy_px = np.full((T, 1, skel.n_joints, 2), np.nan, np.float32)
        xy_px[row, 0, j[m]] = xy[m]
        score = np.where(np.isfinite(xy_px).all(-1), 1.0, 0.0).astype(np.float32)
        xy_px[score == 0] = np.nan
        if hand_sides == "body":
            xy_px, score, n = hands_by_body_side(xy_px, score, CALISCOPE_SKELETON)
            if any(n.values()):
                log.info(
                    "%s port %d: hands put on the body's side: %d swapped, %d moved, %d found twice "
                    "(kept once)",
                    path.name,
                    p,
                    n["swapped"],
                    n["moved"],
                    n["duplicates"],
                )
        t_ns = np.zeros(T, np.int64)
        if t0 is not None:
            ft = np.full(T, np.nan)
            ft[row] = ftime[m]
            t_ns = np.where(np.isfinite(ft), np.round((ft - t0) * 1e9), 0).astype(np.int64)
        extra = {}
        if src_fi is not None:
            sf = np.full(T, -1, np.int64)
            sf[row] = src_fi[m]
            extra["source_frame_index"] = sf
        out[f"cam_{p}"] = Detections(
            camera=f"cam_{p}",
            skeleton=CALISCOPE_SKELETON,
            frame_index=frames,
            t_ns=t_ns,
            xy_px=xy_px,
            score=score,
            boxes=_boxes(xy_px, score),
            model=f"caliscope:{path.stem.removeprefix('xy_')}",
            model_sha256="",
            extra=extra,
        )
    if not out:
        raise FormatError(path, None, "holds no body or hand point.", "Check the tracker's output.")
    return out


def _boxes(xy: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Each person's box (T,P,5): the present joints' extent and mean score; NaN for nobody."""
    ok = score > 0
    boxes = np.full(xy.shape[:2] + (5,), np.nan, np.float32)
    anyp = ok.any(-1)
    if anyp.any():
        v = np.where(ok[..., None], xy, np.nan)[anyp]
        boxes[anyp, :2] = np.nanmin(v, 1)
        boxes[anyp, 2:4] = np.nanmax(v, 1)
        boxes[anyp, 4] = np.where(ok, score, 0).sum(-1)[anyp] / ok.sum(-1)[anyp]
    return boxes


def _openpose_folders(path: Path) -> dict[str, Path]:
    """One camera's json folder, or a folder of ``<camera>_json`` (or other) folders holding .json files."""
    if any(path.glob("*.json")):
        return {path.name.removesuffix("_json"): path}
    subs = sorted(d for d in path.iterdir() if d.is_dir() and any(d.glob("*.json")))
    return {d.name.removesuffix("_json"): d for d in subs}


def import_2d(
    path: str | os.PathLike,
    out_dir: str | os.PathLike,
    fmt: str = "auto",
    skeleton: str | None = None,
    fps: float | None = None,
    cameras: list[str] | None = None,
    hand_sides: str = "body",
) -> dict[str, Path]:
    """Write ``<out_dir>/<camera>.npz`` from another tool's 2D at ``path``; returns the files by camera.

    ``fmt``: ``caliscope`` (an ``xy_*.csv``, or a folder holding one), ``openpose`` (a json folder or a
    folder of them), or ``auto`` (decided by what ``path`` is). ``skeleton`` and ``fps`` are passed to the
    OpenPose reader; ``cameras`` keeps only these; ``hand_sides`` to the caliscope reader."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist.")
    if fmt not in ("auto", "caliscope", "openpose"):
        raise InputError(f"unknown import format '{fmt}'; valid: auto, caliscope, openpose.")
    csvs = [path] if path.is_file() else sorted(path.glob("xy_*.csv"))
    if fmt == "auto":
        fmt = "caliscope" if path.suffix == ".csv" or (path.is_dir() and csvs) else "openpose"
    if fmt == "caliscope":
        if len(csvs) != 1:
            raise InputError(
                f"{path}: expected one caliscope xy_<tracker>.csv, found {[c.name for c in csvs]}; "
                "pass the file."
            )
        dets = read_caliscope_xy(csvs[0], hand_sides=hand_sides)
    else:
        if not path.is_dir():
            raise InputError(
                f"{path}: OpenPose JSON is read from a folder of .json files (or of such folders)."
            )
        folders = _openpose_folders(path)
        if not folders:
            raise FormatError(
                path, None, "holds no .json files nor folders of them.", "Pass OpenPose's output."
            )
        dets = {
            c: read_openpose_folder(f, camera=c, skeleton=skeleton, fps=fps, hands=None)
            for c, f in folders.items()
        }
    if cameras:
        unknown = [c for c in cameras if c not in dets]
        if unknown:
            raise InputError(f"cameras {unknown} are not in {path}; it has {sorted(dets)}.")
        dets = {c: d for c, d in dets.items() if c in cameras}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for cam, d in dets.items():
        p = out / f"{cam}.npz"
        d.save(p)
        paths[cam] = p
    return paths
