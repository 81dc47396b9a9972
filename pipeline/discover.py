"""Finding sessions under folders of recordings.

A session is a folder with camera videos (or detections made elsewhere) and a
calibration, its own or one it points to. Two layouts are recognised:

* this project's (``capture/session.py``): ``raw/<cam>.<ext>`` and/or
  ``keypoints/<cam>.npz``, calibration in ``calib/rig.toml`` or where
  ``session.toml`` points;
* Pose2Sim's: ``videos/<cam>.<ext>`` (or ``pose/<cam>_json/`` OpenPose JSON),
  calibration file (``*.qca.txt``, ``Calib*.toml``, ``camera_array.toml``,
  ``rig.toml``) in ``calibration/`` of the trial or of a parent folder, so
  batch folders whose trials share one calibration work as they are.

Cameras are named from file names, never from file order.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from roomcap.capture.session import VIDEO_SUFFIXES, SessionLayout
from roomcap.core.errors import RoomcapError

SEGMENT_SUFFIXES = (*VIDEO_SUFFIXES, ".h264", ".h265")  # the recorder's raw/<cam>/seg_* files
CALIBRATION_PATTERNS = (
    "rig.toml",
    "*.qca.txt",
    "Calib*.toml",
    "calib*.toml",
    "camera_array.toml",
    "intri.yml",
)


class SessionError(RoomcapError, RuntimeError):
    """A session folder that cannot be processed; the message says what is missing."""


@dataclass(frozen=True)
class SessionSource:
    """Where a session's inputs are. Outputs go to ``out`` (a SessionLayout root)."""

    name: str  # relative name used for output folders and the summary
    root: Path  # the input folder
    layout: str  # "roomcap" | "pose2sim"
    videos: dict[str, Path] = field(default_factory=dict)  # camera -> video file or segment folder
    detections: dict[str, Path] = field(default_factory=dict)  # camera -> existing detections npz
    openpose_json: dict[str, Path] = field(default_factory=dict)  # camera -> folder of OpenPose JSON
    calibration: Path | None = None  # rig.toml or a foreign calibration file
    problem: str = ""  # why this session cannot run (reported, the others still run)
    calibration_missing: bool = False  # the problem is only the missing calibration (keypoints can run)

    @property
    def cameras(self) -> list[str]:
        return sorted(set(self.videos) | set(self.detections) | set(self.openpose_json))


def _videos_in(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        return {}
    out = {}
    for p in sorted(folder.iterdir()):
        if p.name.startswith("."):
            continue
        if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
            out[p.stem] = p
        elif p.is_dir() and any(q.suffix.lower() in SEGMENT_SUFFIXES for q in p.iterdir()):
            out.setdefault(p.name, p)  # a folder of recorded segments (a joined raw/<cam>.mp4 wins)
    return out


def _find_calibration(folder: Path, levels: int = 2) -> Path | None:
    """The calibration of a Pose2Sim-style trial: ``calibration/`` (or ``*_Calibration/``, Pose2Sim's
    session layout) here or in a parent."""
    here = folder
    for _ in range(levels + 1):
        named = sorted(p for p in here.glob("*alibration") if p.name.lower().endswith("_calibration"))
        for cal_dir in (here / "calibration", here / "calib", *named):
            if cal_dir.is_dir():
                for pattern in CALIBRATION_PATTERNS:
                    hits = sorted(cal_dir.glob(pattern))
                    if hits:
                        return hits[0]
        here = here.parent
    return None


def inspect_folder(folder: Path, name: str) -> SessionSource | None:
    """A SessionSource if ``folder`` is a session, else None."""
    layout = SessionLayout(folder)
    raw = _videos_in(layout.raw_dir)
    dets = (
        {p.stem: p for p in sorted(layout.keypoints_dir.glob("*.npz")) if not p.name.startswith(".")}
        if layout.keypoints_dir.is_dir()
        else {}
    )
    if raw or dets or layout.session_toml.exists():
        try:
            if layout.session_toml.exists():
                layout.read_meta()  # a newer or broken session.toml stops the session, not the run
            rig = layout.rig_toml
        except Exception as e:  # a broken session.toml: reported for this session only
            return SessionSource(name, folder, "roomcap", raw, dets, problem=str(e))
        problem = (
            ""
            if rig.exists()
            else (
                f"no calibration: {rig} does not exist. Put the rig in calib/rig.toml (calibrate-run "
                "calibrate or calibrate-run import) or point session.toml's 'calibration' at one."
            )
        )
        only_calib = bool(problem)
        if not raw and not dets:
            only_calib = False
            problem = (
                problem or f"no videos under {layout.raw_dir} and no detections under {layout.keypoints_dir}."
            )
        return SessionSource(
            name,
            folder,
            "roomcap",
            raw,
            dets,
            calibration=rig if rig.exists() else None,
            problem=problem,
            calibration_missing=only_calib,
        )
    videos = _videos_in(folder / "videos")
    pose_dir = folder / "pose"
    jsons = {}
    if pose_dir.is_dir():
        for p in sorted(pose_dir.iterdir()):
            if p.is_dir() and any(p.glob("*.json")):
                jsons[p.name.removesuffix("_json")] = p
    if not videos and not jsons:
        return None
    cal = _find_calibration(folder)
    problem = (
        ""
        if cal
        else (
            f"no calibration found in {folder}/calibration or its parents. Add the calibration file "
            "(Calib.qca.txt, Calib*.toml, camera_array.toml or rig.toml) there."
        )
    )
    return SessionSource(
        name, folder, "pose2sim", videos, {}, jsons, cal, problem, calibration_missing=not cal
    )


def discover(paths: list[str | os.PathLike]) -> list[SessionSource]:
    """All sessions under the given folders (a folder that is a session is not searched further)."""
    found: list[SessionSource] = []
    for top in map(Path, paths):
        if not top.exists():
            found.append(SessionSource(top.name, top, "missing", problem=f"{top} does not exist."))
            continue
        top = top.resolve()
        stack = [top]
        while stack:
            folder = stack.pop()
            rel = folder.relative_to(top)
            name = top.name if str(rel) == "." else f"{top.name}/{rel.as_posix()}"
            src = inspect_folder(folder, name)
            if src is not None:
                found.append(src)
                continue
            children = [
                p
                for p in sorted(folder.iterdir())
                if p.is_dir()
                and not p.name.startswith(".")
                and p.name not in ("calibration", "calib", "roomcap")
                and not p.name.lower().endswith("_calibration")
            ]
            stack.extend(reversed(children))
    names = [s.name for s in found]
    if len(set(names)) != len(names):
        raise SessionError(
            f"two sessions share a name: {sorted(n for n in names if names.count(n) > 1)}; "
            "pass folders with distinct names."
        )
    return found
