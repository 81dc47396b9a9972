"""Read an OpenPose JSON folder (one ``<name>.<frame>.json`` or ``<name>_<frame>_keypoints.json`` per
frame, as OpenPose, Pose2Sim and RTMlib write them) into :class:`~roomcap.keypoints.detections.Detections`.

Each file holds ``{"people": [{"pose_keypoints_2d": [x0, y0, c0, x1, y1, c1, ...]}, ...]}``. A
keypoint with confidence 0 (OpenPose's "not detected", written as 0, 0, 0) becomes NaN. The frame
number is the last group of digits in the file name; frames are sorted by it (never by file order),
and missing numbers become empty frames.

With ``hands`` (``None``: when a file has them) OpenPose's ``hand_left_keypoints_2d`` and
``hand_right_keypoints_2d`` (21 points each, in MediaPipe's order) are appended: the layout is then
``<body layout>_hands`` (:data:`~roomcap.keypoints.skeletons.HANDS`); a person without hand arrays has them
missing.

The layout has to be known: ``skeleton`` names it (``body25b`` for Pose2Sim's demo, ``body25``,
``coco18``, ``coco17``, ``halpe26``). With ``skeleton=None`` it is decided from the number of
keypoints and, for 25 keypoints, from the geometry: in BODY_25 keypoint 1 is the neck, the midpoint
of the shoulders (2, 5); in BODY_25B keypoint 1 is the left eye. The choice is logged.
"""

from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)

_FRAME = re.compile(r"(\d+)(?!.*\d)")
_BY_COUNT = {17: "coco17", 18: "coco18", 26: "halpe26", 33: "blazepose33"}


def _frame_number(path: Path) -> int:
    m = _FRAME.search(path.stem)
    if m is None:
        raise FormatError(
            path,
            None,
            "the file name has no frame number.",
            "Name files <camera>.<frame>.json or <camera>_<frame>_keypoints.json.",
        )
    return int(m.group(1))


def _guess_25(xy: np.ndarray, score: np.ndarray) -> str:
    """BODY_25 (neck at 1 = mid-shoulders 2, 5) or BODY_25B (left eye at 1)."""
    ok = (score[..., 1] > 0) & (score[..., 2] > 0) & (score[..., 5] > 0)
    if not ok.any():
        return "body25b"
    mid = 0.5 * (xy[..., 2, :] + xy[..., 5, :])
    width = np.linalg.norm(xy[..., 2, :] - xy[..., 5, :], axis=-1)
    rel = np.linalg.norm(xy[..., 1, :] - mid, axis=-1)[ok] / np.maximum(width[ok], 1.0)
    return "body25" if np.median(rel) < 0.2 else "body25b"


def read_openpose_folder(
    folder: str | os.PathLike,
    camera: str | None = None,
    skeleton: str | None = None,
    fps: float | None = None,
    max_people: int | None = None,
    image_size_wh: tuple[int, int] | None = None,
    hands: bool | None = False,
) -> Detections:
    """OpenPose JSON folder -> Detections for ``camera`` (default: the folder name without ``_json``).

    ``fps`` sets ``t_ns = frame / fps`` (else 0); ``max_people`` keeps the most confident people.
    """
    folder = Path(folder)
    files = _json_files(folder)
    camera = camera or re.sub(r"_json$", "", folder.name)
    frames = _frame_numbers(files, folder)
    people, n_kp, any_hand = _read_people(files, folder)
    with_hands = bool(hands) or (hands is None and any_hand)
    if not with_hands:
        people = [p[:, :n_kp] for p in people]
    raw = _frames_array(frames, people, n_kp + 42 * with_hands, max_people)
    T = raw.shape[0]
    score = raw[..., 2]
    xy = np.where((score > 0)[..., None], raw[..., :2], np.nan)
    base = skeleton.removesuffix("_hands") if skeleton else None
    skeleton = _skeleton(folder, base, xy[..., :n_kp, :], score[..., :n_kp], n_kp)
    if with_hands:
        skeleton = f"{skeleton}_hands"
    frame_index = np.arange(frames.min(), frames.max() + 1, dtype=np.int64)
    t_ns = np.round(frame_index * 1e9 / fps).astype(np.int64) if fps else np.zeros(T, np.int64)
    present, boxes = _boxes(xy, score)
    return Detections(
        camera=camera,
        skeleton=skeleton,
        frame_index=frame_index,
        t_ns=t_ns,
        xy_px=xy,
        score=np.where(present, score, 0.0),
        boxes=boxes,
        model="openpose-json",
        model_sha256="",
        image_size_wh=image_size_wh,
    )


def _json_files(folder: Path) -> list[Path]:
    """The folder's ``*.json`` files in frame order."""
    if not folder.is_dir():
        raise FormatError(
            folder, None, "is not a folder of OpenPose JSON files.", "Pass the camera's json folder."
        )
    files = sorted(folder.glob("*.json"), key=_frame_number)
    if not files:
        raise FormatError(
            folder, None, "holds no .json files.", "Run OpenPose with --write_json on this camera."
        )
    return files


def _frame_numbers(files: list[Path], folder: Path) -> np.ndarray:
    """The frame number of each file (unique)."""
    frames = np.array([_frame_number(f) for f in files], dtype=np.int64)
    if len(np.unique(frames)) != len(frames):
        raise FormatError(folder, None, "two files have the same frame number.", "Keep one JSON per frame.")
    return frames


def _read_people(files: list[Path], folder: Path) -> tuple[list[np.ndarray], int, bool]:
    """Per file the people's keypoints (P,J+42,3) x, y, confidence (the body's J, then the left and right
    hands' 21, zero where absent), J (the same in every file) and whether any hand point was detected."""
    people: list[np.ndarray] = []
    n_kp = None
    any_hand = False
    for f in files:
        try:
            data = json.loads(f.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise FormatError(
                f, None, f"cannot be read as JSON ({e}).", "Re-export the OpenPose JSON."
            ) from e
        rows = []
        for p in data.get("people", []):
            kp = np.asarray(p.get("pose_keypoints_2d", []), dtype=np.float64)
            if kp.size == 0:
                continue
            if kp.size % 3:
                raise FormatError(f, "pose_keypoints_2d", f"has {kp.size} values, not a multiple of 3.")
            n = kp.size // 3
            if n_kp is None:
                n_kp = n
            elif n != n_kp:
                raise FormatError(f, "pose_keypoints_2d", f"has {n} keypoints, earlier files {n_kp}.")
            hand = np.zeros((42, 3))
            for h, key in enumerate(("hand_left_keypoints_2d", "hand_right_keypoints_2d")):
                v = np.asarray(p.get(key) or [], dtype=np.float64)
                if v.size not in (0, 63):
                    raise FormatError(f, key, f"has {v.size} values, not 21 keypoints x 3.")
                if v.size:
                    hand[21 * h : 21 * h + 21] = v.reshape(21, 3)
            any_hand |= bool((hand[:, 2] > 0).any())
            rows.append(np.concatenate([kp.reshape(n, 3), hand]))
        people.append(np.stack(rows) if rows else np.zeros((0, (n_kp or 0) + 42, 3)))
    if n_kp is None:
        raise FormatError(folder, None, "no person was detected in any file.", "Check the OpenPose run.")
    return people, n_kp, any_hand


def _frames_array(
    frames: np.ndarray, people: list[np.ndarray], n_kp: int, max_people: int | None
) -> np.ndarray:
    """(T,P,J,3) over every frame from the first to the last (missing frames zero), keeping the
    ``max_people`` most confident people of a frame."""
    T = int(frames.max() - frames.min() + 1)
    P = max(len(p) for p in people)
    if max_people is not None:
        P = min(P, max_people)
    raw = np.zeros((T, P, n_kp, 3))
    for f_no, p in zip(frames, people, strict=True):
        p = p.reshape(-1, n_kp, 3)
        if max_people is not None and len(p) > max_people:
            p = p[np.argsort(-p[..., 2].mean(-1))[:max_people]]
        raw[f_no - frames.min(), : len(p)] = p
    return raw


def _skeleton(folder: Path, skeleton: str | None, xy: np.ndarray, score: np.ndarray, n_kp: int) -> str:
    """The skeleton given (checked against J), else the one the keypoint count (and, for 25, their
    positions) points to."""
    if skeleton is None:
        skeleton = _guess_25(xy, score) if n_kp == 25 else _BY_COUNT.get(n_kp)
        if skeleton is None:
            raise FormatError(
                folder,
                "pose_keypoints_2d",
                f"{n_kp} keypoints match no known layout.",
                "Pass skeleton= explicitly.",
            )
        log.info("%s: %d keypoints read as skeleton '%s'", folder, n_kp, skeleton)
    if get_skeleton(skeleton).n_joints != n_kp:
        raise FormatError(
            folder,
            "skeleton",
            f"'{skeleton}' has {get_skeleton(skeleton).n_joints} joints, the files have {n_kp}.",
            "Pass the skeleton the files were written with.",
        )
    return skeleton


def _boxes(xy: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which joints are present (T,P), and each person's box (T,P,5): the present joints' extent and their
    mean score (NaN for nobody)."""
    T, P = xy.shape[:2]
    present = np.isfinite(xy).all(-1)
    boxes = np.full((T, P, 5), np.nan)
    any_p = present.any(-1)
    if any_p.any():
        lo = np.nanmin(np.where(present[..., None], xy, np.nan)[any_p], axis=1)
        hi = np.nanmax(np.where(present[..., None], xy, np.nan)[any_p], axis=1)
        mean_sc = np.where(present, score, 0).sum(-1)[any_p] / np.maximum(present.sum(-1)[any_p], 1)
        boxes[any_p] = np.concatenate([lo, hi, mean_sc[:, None]], 1)
    return present, boxes
