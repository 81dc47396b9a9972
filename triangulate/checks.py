"""Plausibility of the detections that enter the 3D stages what is probably wrong is said.

Errors (the 3D would be wrong by metres): frame numbers that are not strictly increasing in a camera's
file, timestamps that go backwards. Warnings (the run goes on, the summary and report show them): a
camera with no detection at all, cameras that cover different frame ranges with no timestamps to align
them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError
from roomcap.core.timebase import timestamps_backwards
from roomcap.keypoints.detections import Detections


def check_frame_order(det: Detections, path: Path) -> None:
    """Raise when ``frame_index`` is not strictly increasing or ``t_ns`` (where set) goes backwards."""
    fi = np.asarray(det.frame_index)
    step = np.diff(fi)
    if (step <= 0).any():
        k = int(np.argmax(step <= 0)) + 1
        what = "repeats" if step[k - 1] == 0 else "goes back to"
        raise FormatError(
            path,
            "frame_index",
            f"camera '{det.camera}': frame_index is not strictly increasing: row {k} {what} frame "
            f"{int(fi[k])} after frame {int(fi[k - 1])}.",
            "Sort the file's rows by frame_index and drop duplicates, or rerun the keypoints stage.",
        )
    back = timestamps_backwards(fi, det.t_ns)
    if back is not None:
        raise FormatError(
            path,
            "t_ns",
            f"camera '{det.camera}': {back}.",
            "Fix the camera's frames.csv (the recorder's clock jumped?) or drop the timestamps (t_ns = 0) "
            "to align the cameras by frame number.",
        )


def no_detection_warning(camera: str, n_frames: int) -> str:
    return (
        f"camera '{camera}' has no detection in its {n_frames} frames: check its video "
        "(covered, dark, pointing away) and its keypoints file; the 3D uses the other cameras."
    )


def span_warnings(dets: Sequence[Detections]) -> list[str]:
    """Cameras covering different frames with no timestamps (needs ``camera``, ``frame_index``, ``t_ns``)."""
    out = []
    spans = {d.camera: (int(d.frame_index[0]), int(d.frame_index[-1])) for d in dets if len(d.frame_index)}
    timed = all((np.asarray(d.t_ns) != 0).any() for d in dets if len(d.frame_index))
    if len(set(spans.values())) > 1 and not timed:
        out.append(
            "cameras cover different frames ("
            + ", ".join(f"{c} {a}-{b}" for c, (a, b) in spans.items())
            + ") and have no timestamps to align them: frames are matched by frame number, which is right "
            "only if every camera started together. Record with timestamps or run `capture-run sync`."
        )
    return out


def detection_warnings(dets: Sequence[Detections]) -> list[str]:
    """What looks wrong across the cameras' detections (no detection at all, unalignable lengths)."""
    out = []
    for d in dets:
        seen = np.isfinite(np.asarray(d.xy_px)[..., 0]) & (np.nan_to_num(np.asarray(d.score)) > 0)
        if len(d.frame_index) == 0 or not seen.any():
            out.append(no_detection_warning(d.camera, len(d.frame_index)))
    return out + span_warnings(dets)
