"""What the stages read from a session's inputs: video probes, calibration names, frame rates, sync.

Helpers of the stage objects (:mod:`roomcap.pipeline.stages`), one job each: probing the videos before the 2D
stage (:func:`probe_videos`), matching a calibration's camera names to the recording's
(:func:`match_camera_names`), reading a Pose2Sim trial's frame rate (:func:`pose2sim_frame_rate`) and
carrying ``capture-run sync``'s offsets into the output session (:func:`carry_sync`).
"""

from __future__ import annotations

import dataclasses
import logging
import re
from pathlib import Path

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import SESSION_SCHEMA, SESSION_VERSION, SessionLayout
from roomcap.core.errors import RoomcapError
from roomcap.core.fileio import load_toml, save_toml
from roomcap.pipeline.discover import SEGMENT_SUFFIXES, SessionSource
from roomcap.triangulate.chunks import parts_dir

log = logging.getLogger(__name__)

FPS_TOLERANCE = 0.01  # relative frame-rate difference between cameras of one session that is still "the same"


class StageError(RoomcapError, RuntimeError):
    """A stage failed; the message names the stage, what went wrong and what to do."""


def _name_key(name: str) -> str:
    """``cam_01``, ``Cam01``, ``cam-1`` -> ``cam1``: spelling differences between tools, not other cameras."""
    return re.sub(r"\d+", lambda m: str(int(m.group())), re.sub(r"[^0-9a-z]", "", name.lower()))


def match_camera_names(rig: CameraRig, cameras: list[str]) -> CameraRig:
    """The rig with its cameras renamed to the recording's names where they differ only in spelling
    (Pose2Sim's ``cam_01`` calibration for ``cam01_json``); matched by name, never by order."""
    if all(c in rig.names for c in cameras):
        return rig
    keys = {_name_key(n): n for n in rig.names}
    if len(keys) != len(rig.names):
        return rig
    rename = {keys[_name_key(c)]: c for c in cameras if _name_key(c) in keys}
    if len(set(rename.values())) != len(rename):
        return rig
    log.info("calibration camera names %s matched to the recording's %s", list(rename), list(rename.values()))
    return type(rig)(
        tuple(dataclasses.replace(cam, name=rename.get(cam.name, cam.name)) for cam in rig.cameras)
    )


def probe_videos(videos: dict[str, Path]) -> tuple[dict[str, tuple[int, float]], list[str]]:
    """Frame count and rate of each camera's video; raises on unreadable videos or mixed frame rates.

    Returns ``({cam: (n_frames, fps)}, warnings)``; videos of different lengths are a warning (the frames
    are aligned by index, the tail of the longer videos is seen by fewer cameras).
    """
    info = {cam: _probe_video(cam, path) for cam, path in sorted(videos.items())}
    return info, video_checks(info)


def _probe_video(cam: str, path: Path) -> tuple[int, float]:
    """Frame count and rate of one camera's video (a file, or a folder of segments); raises when a file
    cannot be read."""
    import cv2

    files = (
        sorted(p for p in path.glob("seg_*") if p.suffix.lower() in SEGMENT_SUFFIXES)
        or sorted(
            p for p in path.iterdir() if not p.name.startswith(".") and p.suffix.lower() in SEGMENT_SUFFIXES
        )
        if path.is_dir()
        else [path]
    )
    n, fps = 0, 0.0
    for f in files:
        cap = cv2.VideoCapture(str(f))
        ok = cap.isOpened()
        ok = ok and cap.read()[0]
        count, rate = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), float(cap.get(cv2.CAP_PROP_FPS))
        cap.release()
        if not ok:
            raise StageError(
                f"camera '{cam}': video {f} cannot be read (not a video, truncated or an "
                "unsupported codec). Replace it, or move it out of the session to run without "
                "this camera."
            )
        n, fps = n + max(count, 0), fps or rate
    return n, fps


def video_checks(info: dict[str, tuple[int, float]]) -> list[str]:
    """The checks across the cameras of :func:`probe_videos`' ``info``: mixed frame rates raise, videos
    of different lengths are a warning (returned)."""
    rates = {c: r for c, (_, r) in info.items() if r > 0}
    if rates and (max(rates.values()) - min(rates.values())) > FPS_TOLERANCE * max(rates.values()):
        raise StageError(
            "the cameras' videos have different frame rates ("
            + ", ".join(f"{c} {r:g} fps" for c, r in rates.items())
            + "). Frames cannot be matched by index: re-encode them at one rate or record "
            "with synchronised cameras."
        )
    warnings = []
    counts = {c: n for c, (n, _) in info.items()}
    if counts and max(counts.values()) != min(counts.values()):
        warnings.append(
            "videos differ in length ("
            + ", ".join(f"{c} {n}" for c, n in counts.items())
            + " frames); frames are matched by index from the start, later frames have fewer views"
        )
    return warnings


def readable_videos(
    videos: dict[str, Path],
) -> tuple[dict[str, Path], dict[str, str], dict[str, tuple[int, float]]]:
    """Split ``{cam: video}`` into the readable ones and ``{cam: why not}``, each video probed once;
    also the readable ones' ``{cam: (n_frames, fps)}`` for :func:`video_checks`."""
    ok, bad, info = {}, {}, {}
    for cam, path in sorted(videos.items()):
        try:
            info[cam] = _probe_video(cam, path)
            ok[cam] = path
        except StageError as e:
            bad[cam] = str(e)
    return ok, bad, info


def pose2sim_frame_rate(trial: Path) -> float | None:
    """``[project] frame_rate`` of the nearest Pose2Sim ``Config.toml`` (trial, then parents)."""

    for folder in (trial, *trial.parents[:3]):
        cfg = folder / "Config.toml"
        if cfg.exists():
            try:
                rate = load_toml(cfg).get("project", {}).get("frame_rate")
            except Exception:  # a Config.toml we cannot read says nothing about the rate
                continue
            if isinstance(rate, (int, float)) and rate > 0:
                return float(rate)
    return None


def detection_paths(lay: SessionLayout) -> list[Path]:
    return [lay.detections(c) for c in lay.detection_cameras()]


def sync_table(src: SessionSource) -> dict:
    """The ``[sync]`` table (``capture-run sync``) of the input session's session.toml, or {}."""
    toml = SessionLayout(src.root).session_toml
    if not toml.exists():
        return {}

    sync = load_toml(toml).get("sync")
    return sync if isinstance(sync, dict) else {}


def carry_sync(src: SessionSource, lay: SessionLayout) -> None:
    """Outputs written elsewhere (--out, Pose2Sim layout): copy the input's [sync] into the output's
    session.toml, where the 3D stages (``triangulate.stage.load_detections``) read it."""
    sync = sync_table(src)
    if not sync or lay.session_toml.resolve() == SessionLayout(src.root).session_toml.resolve():
        return

    meta = (
        load_toml(lay.session_toml)
        if lay.session_toml.exists()
        else {"schema": f"{SESSION_SCHEMA}/{SESSION_VERSION}", "status": "imported"}
    )
    if meta.get("sync") != sync:
        meta["sync"] = sync
        save_toml(lay.session_toml, meta)


def stage_file(path: Path) -> Path:
    """A 3D stage's output as it was written: the single file, else its parts folder (a streamed run,
    ``chunk_s`` > 0: ``poses3d.parts/``, ``tracks.parts/``), else the file's path (missing)."""
    if path.exists():
        return path
    d = parts_dir(path)
    return d if d.is_dir() else path
