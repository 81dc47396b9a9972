"""The session folder layout (CONTRACTS.md), one place that knows where each file lives.

::

    <session>/
      session.toml                 schema "session/1": cameras, fps, calibration pointer, sync offsets
      raw/<cam>.mp4 | raw/<cam>/   video per camera; raw/<cam>/seg_*.mp4 + index.ffconcat while recording
                                   (joined into raw/<cam>.mp4 when the recording ends, capture.join)
      raw/<cam>.frames.csv         per-frame timestamps: frame_index,t_ns,t_host_ns,sequence
                                   (older sessions: raw/<cam>/frames.csv, still read)
      calib/rig.toml               the rig (or ``calibration = "<path>"`` in session.toml)
      keypoints/<cam>.npz          2D detections per camera
      triangulate/poses3d.npz      per-frame 3D poses
      track/tracks.npz             the track file (a streamed run: track/tracks.parts/, same reader)
      track/live.npz               the track of ``capture-run --live``, written as track/live.parts/
                                   (parts + index.json, read as this path; older sessions:
                                   track/live/, read by pipeline.live.load_live_tracks)
      report/report.html           the session report
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from roomcap.core.errors import FormatError
from roomcap.core.fileio import check_schema, load_toml

SESSION_SCHEMA = "session"
SESSION_VERSION = 1
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm")


@dataclass(frozen=True)
class SessionLayout:
    root: Path

    def __init__(self, root: str | os.PathLike):
        object.__setattr__(self, "root", Path(root))

    @property
    def session_toml(self) -> Path:
        return self.root / "session.toml"

    @property
    def raw_dir(self) -> Path:
        return self.root / "raw"

    def video(self, cam: str) -> Path:
        """The camera's video: ``raw/<cam>.<ext>`` if present, else the segment folder ``raw/<cam>/``."""
        for suffix in VIDEO_SUFFIXES:
            p = self.raw_dir / f"{cam}{suffix}"
            if p.exists():
                return p
        return self.raw_dir / cam

    def video_file(self, cam: str) -> Path:
        """A path ``cv2.VideoCapture`` opens: ``raw/<cam>.<ext>``, or a segment folder's ``index.ffconcat``.

        The recorder keeps ``index.ffconcat`` listing every closed segment; ``capture.sources.open_recording``
        reads both forms with the timestamps of ``frames.csv``.
        """
        v = self.video(cam)
        return v / "index.ffconcat" if v.is_dir() else v

    def frames_csv(self, cam: str) -> Path:
        """Where the recorder writes the camera's timestamps (the README layout)."""
        return self.raw_dir / f"{cam}.frames.csv"

    def find_frames_csv(self, cam: str) -> Path | None:
        """The camera's timestamp file if there is one: ``raw/<cam>.frames.csv``, else the older place
        ``raw/<cam>/frames.csv``."""
        for p in (self.frames_csv(cam), self.raw_dir / cam / "frames.csv"):
            if p.is_file():
                return p
        return None

    def segment_files(self, cam: str) -> list[Path]:
        """The closed segments of ``raw/<cam>/`` in recording order (empty once joined)."""
        d = self.raw_dir / cam
        if not d.is_dir():
            return []
        ok = VIDEO_SUFFIXES + (".h264", ".h265")
        return sorted(p for p in d.glob("seg_*") if p.suffix.lower() in ok)

    @property
    def calib_dir(self) -> Path:
        return self.root / "calib"

    @property
    def rig_toml(self) -> Path:
        """The rig this session uses: its own ``calib/rig.toml`` or the one session.toml points to."""
        own = self.calib_dir / "rig.toml"
        if own.exists() or not self.session_toml.exists():
            return own
        meta = self.read_meta()
        pointer = meta.get("calibration")
        if isinstance(pointer, dict):
            pointer = pointer.get("rig")
        if pointer:
            p = Path(pointer)
            return p if p.is_absolute() else (self.root / p)
        return own

    @property
    def keypoints_dir(self) -> Path:
        return self.root / "keypoints"

    def detections(self, cam: str) -> Path:
        return self.keypoints_dir / f"{cam}.npz"

    @property
    def poses3d(self) -> Path:
        return self.root / "triangulate" / "poses3d.npz"

    @property
    def tracks(self) -> Path:
        return self.root / "track" / "tracks.npz"

    @property
    def live_tracks(self) -> Path:
        """The live track (``capture-run --live``): its parts are ``track/live.parts/``, the loaders read
        them through this path. Apart from :attr:`tracks`, so a reprocess never touches it."""
        return self.root / "track" / "live.npz"

    @property
    def report_html(self) -> Path:
        return self.root / "report" / "report.html"

    def read_meta(self) -> dict:
        meta = load_toml(self.session_toml)
        check_schema(meta.get("schema"), SESSION_SCHEMA, (SESSION_VERSION,), self.session_toml)
        return meta

    def raw_cameras(self) -> list[str]:
        """Camera names with a video under raw/ (sorted by name, never by file order)."""
        if not self.raw_dir.is_dir():
            return []
        names = set()
        for p in self.raw_dir.iterdir():
            if p.name.startswith("."):  # temporaries (a join in progress, unfinished segments)
                continue
            if p.suffix.lower() in VIDEO_SUFFIXES:
                names.add(p.stem)
            elif p.is_dir():
                names.add(p.name)
        return sorted(names)

    def detection_cameras(self) -> list[str]:
        if not self.keypoints_dir.is_dir():
            return []
        return sorted(p.stem for p in self.keypoints_dir.glob("*.npz") if not p.name.startswith("."))


def videos_in(folder: str | os.PathLike) -> dict[str, Path]:
    """``{stem: path}`` for the videos in a folder (the Pose2Sim layout ``<trial>/videos/camNN.mp4``)."""
    folder = Path(folder)
    out = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES}
    if not out:
        raise FileNotFoundError(f"no videos ({', '.join(VIDEO_SUFFIXES)}) in {folder}.")
    return out


def require(path: Path, what: str, fix: str) -> Path:
    if not path.exists():
        raise FormatError(path, None, f"{what} is missing.", fix)
    return path
