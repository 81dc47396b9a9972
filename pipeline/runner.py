"""Running the stages of one session as a small graph, cached and resumable.

calibration ─► keypoints ─► triangulate ─► track ─► forecast ─► report

Each stage declares its inputs, outputs, configuration and model sha256; it
runs only when its provenance record (``pipeline/provenance.py``) says its
outputs are stale or missing. A new calibration changes the inputs of
triangulate and track (and what follows), not of keypoints, so only those
rerun. Every output is written atomically by the stage that owns it and the
record is written last, so a run killed at any point resumes where it stopped
and ends with the same files as an uninterrupted run (temporary files a kill
left behind are removed before a stage reruns). This module wires stages
together; the algorithms live in the stage packages.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import os
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calibrate.camera import CameraRig
from calibrate.formats import import_calibration
from capture.fileio import atomic_write_bytes, atomic_write_text, load_npz, load_toml, save_toml
from capture.offline_sync import POSE2SIM_OUTPUT
from capture.session import SESSION_SCHEMA, SESSION_VERSION, SessionLayout
from core.cli import describe_os_error
from core.errors import RoomcapError
from keypoints.registry import get_model_set, resolve
from pipeline.config import STAGES, PipelineConfig
from pipeline.discover import SEGMENT_SUFFIXES, SessionSource
from pipeline.glue import forecast_model, track_particle, write_preview
from pipeline.lock import SessionLocked, holder, lock_path, session_lock
from pipeline.provenance import ProvenanceStore, StageRecord, path_fingerprint, stage_version
from pipeline.report import warnings_path, write_report
from track.stage import ParticleTrackConfig, stream_chunk_s
from triangulate.chunks import PartStore, parts_dir
from triangulate.reconstruct import RUN_SETTINGS
from triangulate.reconstruct import TriangulateConfig as TriangulateOptions
from triangulate.stage import GreedyTrackConfig, session_chunk_s, track_session_greedy, triangulate_session

log = logging.getLogger(__name__)

FPS_TOLERANCE = 0.01  # relative frame-rate difference between cameras of one session that is still "the same"


class StageError(RoomcapError, RuntimeError):
    """A stage failed; the message names the stage, what went wrong and what to do."""


@dataclass
class SessionResult:
    name: str
    out: str
    # ok | partial (some cameras were skipped, see skipped_cameras) | failed | locked (another run holds it)
    status: str = "ok"
    message: str = ""
    cameras: int = 0
    frames: int = 0
    people: int = 0
    tracks: int = 0
    stage_s: dict[str, float] = field(default_factory=dict)
    ran: list[str] = field(default_factory=list)  # stages that did work (the rest were up to date)
    warnings: list[str] = field(default_factory=list)
    failed_stage: str = ""
    skipped_cameras: dict[str, str] = field(default_factory=dict)  # camera -> why it was left out

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class StagePlan:
    name: str
    inputs: list[Path]
    outputs: list[Path]
    config: dict[str, Any]
    run: Callable[[list[str]], None]  # gets the session's warning list to append to
    model_sha256: str = ""
    skipped: dict[str, str] = field(default_factory=dict)  # cameras this stage leaves out, and why


def output_root(source: SessionSource, out: Path | None) -> Path:
    """Where a session's outputs go: ``out/<name>``, or in place for this project's own layout."""
    if out is not None:
        return Path(out) / source.name
    if source.layout == "roomcap":
        return source.root
    return source.root / POSE2SIM_OUTPUT


# ----------------------------------------------------------------------------- stage plans


def _plan_calibration(
    src: SessionSource, lay: SessionLayout, cfg: PipelineConfig, store: ProvenanceStore
) -> StagePlan | None:
    target = lay.calib_dir / "rig.toml"
    if src.calibration is None:
        raise FileNotFoundError(src.problem or f"session {src.name} has no calibration")
    if src.calibration.resolve() == target.resolve():
        return None  # the session's own rig is the input of later stages

    def run(warnings: list[str]) -> None:
        rig = _match_camera_names(import_calibration(src.calibration), src.cameras)
        missing = [c for c in src.cameras if c not in rig.names]
        if missing:
            raise ValueError(
                f"{src.calibration}: cameras {missing} of the recording are not in the calibration "
                f"(it has {list(rig.names)}). Use a calibration of these cameras."
            )
        rig.save(target)

    return StagePlan("calibration", [src.calibration], [target], {}, run)


def _name_key(name: str) -> str:
    """``cam_01``, ``Cam01``, ``cam-1`` -> ``cam1``: spelling differences between tools, not other cameras."""
    import re

    return re.sub(r"\d+", lambda m: str(int(m.group())), re.sub(r"[^0-9a-z]", "", name.lower()))


def _match_camera_names(rig, cameras: list[str]):
    """The rig with its cameras renamed to the recording's names where they differ only in spelling
    (Pose2Sim's ``cam_01`` calibration for ``cam01_json``); matched by name, never by order."""
    import dataclasses as dc

    if all(c in rig.names for c in cameras):
        return rig
    keys = {_name_key(n): n for n in rig.names}
    if len(keys) != len(rig.names):
        return rig
    rename = {keys[_name_key(c)]: c for c in cameras if _name_key(c) in keys}
    if len(set(rename.values())) != len(rename):
        return rig
    log.info("calibration camera names %s matched to the recording's %s", list(rename), list(rename.values()))
    return type(rig)(tuple(dc.replace(cam, name=rename.get(cam.name, cam.name)) for cam in rig.cameras))


def model_set_sha256(model_set: str, store: ProvenanceStore | None = None) -> str:
    """sha256 of the model files of a keypoints model set (detector+pose), via the stat cache."""

    ms = get_model_set(model_set)
    names = [n for n in (ms.detector, ms.pose) if n]
    cache = store.stat_cache if store is not None else None
    return "+".join(path_fingerprint(resolve(n, verify=False), cache) for n in names)


def probe_videos(videos: dict[str, Path]) -> tuple[dict[str, tuple[int, float]], list[str]]:
    """Frame count and rate of each camera's video; raises on unreadable videos or mixed frame rates.

    Returns ``({cam: (n_frames, fps)}, warnings)``; videos of different lengths are a warning (the frames
    are aligned by index, the tail of the longer videos is seen by fewer cameras).
    """
    import cv2

    info: dict[str, tuple[int, float]] = {}
    for cam, path in sorted(videos.items()):
        files = (
            sorted(p for p in path.glob("seg_*") if p.suffix.lower() in SEGMENT_SUFFIXES)
            or sorted(
                p
                for p in path.iterdir()
                if not p.name.startswith(".") and p.suffix.lower() in SEGMENT_SUFFIXES
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
        info[cam] = (n, fps)
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
    return info, warnings


def readable_videos(videos: dict[str, Path]) -> tuple[dict[str, Path], dict[str, str]]:
    """Split ``{cam: video}`` into the readable ones and ``{cam: why not}`` (probe_videos per camera)."""
    ok, bad = {}, {}
    for cam, path in sorted(videos.items()):
        try:
            probe_videos({cam: path})
            ok[cam] = path
        except StageError as e:
            bad[cam] = str(e)
    return ok, bad


def _plan_keypoints(
    src: SessionSource, lay: SessionLayout, cfg: PipelineConfig, store: ProvenanceStore
) -> StagePlan | None:
    if src.videos:
        readable, skipped = readable_videos(src.videos)
        if not readable:
            raise StageError(
                "no camera's video can be read: " + " ".join(skipped.values())
                if len(skipped) > 1
                else next(iter(skipped.values()))
            )
        cams = sorted(readable)
        outputs = [lay.detections(c) for c in cams]
        kcfg = cfg.keypoints.provenance()
        frames_csv = {}
        if src.layout == "roomcap":  # the recorder's per-frame timestamps (t_ns in the detections)
            src_lay = SessionLayout(src.root)
            frames_csv = {c: p for c in cams if (p := src_lay.find_frames_csv(c)) is not None}

        def run(warnings: list[str]) -> None:
            from keypoints.video import run_videos  # lazy: loads onnxruntime

            _, warn = probe_videos({c: src.videos[c] for c in cams})
            warnings.extend(warn)
            rig = None
            if lay.rig_toml.exists():
                rig = CameraRig.load(lay.rig_toml)
            from keypoints.presets import preset_config  # lazy: loads onnxruntime
            from keypoints.runtime import RuntimeConfig  # lazy: loads onnxruntime

            # the executor's share of the cores (set per worker by _limit_threads); 0 = onnxruntime's default
            threads = int(os.environ.get("ROOMCAP_ORT_THREADS", "0") or 0)
            preset, settings = cfg.keypoints.settings()
            kp_cfg = preset_config(preset, **settings, runtime=RuntimeConfig(threads=threads))
            rep = run_videos(
                {c: src.videos[c] for c in cams},
                lay.keypoints_dir,
                kp_cfg,
                rig=rig,
                max_frames=cfg.keypoints.max_frames,
                timestamps=frames_csv or None,
                # one camera group per core of this worker, one onnxruntime thread each: 1.3x the frames
                # per second of one group with two threads on 2 cores (bench_keypoints_throughput.py)
                camera_groups=threads or os.cpu_count() or 1,
            )
            for c, (fi, msg) in sorted(rep.decode_errors.items()):
                warnings.append(f"camera '{c}': {msg}; kept the {fi} frames before it")

        return StagePlan(
            "keypoints",
            [src.videos[c] for c in cams] + sorted(frames_csv.values()),
            outputs,
            kcfg,
            run,
            model_set_sha256(cfg.keypoints.model_set_name, store),
            skipped,
        )
    if src.openpose_json:
        cams = sorted(src.openpose_json)
        outputs = [lay.detections(c) for c in cams]

        def run_json(warnings: list[str]) -> None:
            try:
                from keypoints.openpose_json import read_openpose_folder
            except ImportError:
                raise StageError(
                    "reading OpenPose JSON folders needs keypoints.openpose_json, which this "
                    "build lacks; run the keypoints stage on the videos instead."
                ) from None
            fps = _pose2sim_frame_rate(src.root)
            for c in cams:
                read_openpose_folder(src.openpose_json[c], camera=c, fps=fps).save(lay.detections(c))

        return StagePlan(
            "keypoints", [src.openpose_json[c] for c in cams], outputs, {"from": "openpose_json"}, run_json
        )
    if src.detections:  # detections made elsewhere: copied into the output session (unless it is the input)
        cams = sorted(src.detections)
        if all(src.detections[c].resolve() == lay.detections(c).resolve() for c in cams):
            return None

        def run_copy(warnings: list[str]) -> None:
            for c in cams:
                atomic_write_bytes(lay.detections(c), src.detections[c].read_bytes())

        return StagePlan(
            "keypoints",
            [src.detections[c] for c in cams],
            [lay.detections(c) for c in cams],
            {"from": "detections"},
            run_copy,
        )
    return None


def _pose2sim_frame_rate(trial: Path) -> float | None:
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


def _detection_paths(lay: SessionLayout) -> list[Path]:
    return [lay.detections(c) for c in lay.detection_cameras()]


def _sync_table(src: SessionSource) -> dict:
    """The ``[sync]`` table (``capture-run sync``) of the input session's session.toml, or {}."""
    toml = SessionLayout(src.root).session_toml
    if not toml.exists():
        return {}

    sync = load_toml(toml).get("sync")
    return sync if isinstance(sync, dict) else {}


def _carry_sync(src: SessionSource, lay: SessionLayout) -> None:
    """Outputs written elsewhere (--out, Pose2Sim layout): copy the input's [sync] into the output's
    session.toml, where the 3D stages (``triangulate.stage.load_detections``) read it."""
    sync = _sync_table(src)
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


def _output_file(lay: SessionLayout, cfg: PipelineConfig, stage: str) -> Path:
    """What a 3D stage writes on this session: its file, or its parts folder where it streams (``chunk_s``
    > 0, or ``"auto"`` on a long session: the stage decides by the same rule, ``session_chunk_s``)."""
    if stage == "triangulate":
        path, chunk_s = (
            lay.poses3d,
            session_chunk_s(lay, TriangulateOptions.from_dict(cfg.triangulate.options).chunk_s),
        )
    elif cfg.track.tracker == "greedy":
        path, chunk_s = (
            lay.tracks,
            session_chunk_s(lay, GreedyTrackConfig.from_dict(cfg.track.options).chunk_s),
        )
    else:
        path, chunk_s = lay.tracks, stream_chunk_s(lay, ParticleTrackConfig.from_dict(particle_options(cfg)))
    return parts_dir(path) if chunk_s > 0 else path


def _stage_xyz(path: Path, kind: str):
    """(track ids or None, xyz_m) of each part of a 3D stage's output (one for a single file), read one
    part at a time."""
    p = stage_file(path)
    files = (
        [p] if p.is_file() else [f for _, _, f in PartStore(p, kind).checked_parts()] if p.is_dir() else []
    )
    for f in files:
        d = load_npz(f)
        yield d.get("track_id"), d["xyz_m"]


def _plan_triangulate(
    src: SessionSource, lay: SessionLayout, cfg: PipelineConfig, store: ProvenanceStore
) -> StagePlan:
    def run(warnings: list[str]) -> None:
        _carry_sync(src, lay)
        triangulate_session(lay.root, cfg.triangulate.options or None)

    return StagePlan(
        "triangulate",
        [lay.rig_toml, *_detection_paths(lay)],
        [_output_file(lay, cfg, "triangulate")],
        {
            **_without_run_settings(dataclasses.asdict(cfg.triangulate)),
            "sync": _sync_table(src),
        },  # new offsets: rerun
        run,
    )


def _without_run_settings(d: dict) -> dict:
    """A stage's config without ``options.workers`` and ``options.executor`` (how many processes or which
    executor ran it, not what it computed)."""
    opts = d.get("options") or {}
    if not any(k in opts for k in RUN_SETTINGS):
        return d
    return {**d, "options": {k: v for k, v in opts.items() if k not in RUN_SETTINGS}}


def _plan_track(
    src: SessionSource, lay: SessionLayout, cfg: PipelineConfig, store: ProvenanceStore
) -> StagePlan:
    def run(warnings: list[str]) -> None:
        _carry_sync(src, lay)
        if cfg.track.tracker == "greedy":
            track_session_greedy(lay.root, cfg.track.options or None)
        else:
            track_particle(lay, particle_options(cfg))

    inputs = [lay.rig_toml, *_detection_paths(lay)]
    if cfg.track.tracker == "greedy":
        inputs.append(stage_file(lay.poses3d))  # the file or a streamed run's parts
    config = dataclasses.asdict(cfg.track)
    if cfg.track.tracker != "greedy":  # the particle tracker reads the detections (and offsets) itself
        config["sync"] = _sync_table(src)
        config["options"] = particle_options(cfg)
    return StagePlan("track", inputs, [_output_file(lay, cfg, "track")], config, run)


def particle_options(cfg: PipelineConfig) -> dict:
    """The particle tracker's options: ``[track] options``, with the 3D joints of ``[triangulate.options]
    skeleton`` (whole_body, a skeleton TOML) unless the track options name their own ``skeleton``."""
    opts = dict(cfg.track.options or {})
    skel = (cfg.triangulate.options or {}).get("skeleton")
    if skel and skel != "body19":
        opts.setdefault("skeleton", skel)
    return opts


def forecast_path(lay: SessionLayout) -> Path:
    return lay.root / "forecast" / "preview.npz"


def _plan_forecast(
    src: SessionSource, lay: SessionLayout, cfg: PipelineConfig, store: ProvenanceStore
) -> StagePlan:

    kind, checkpoint = forecast_model(cfg.forecast.model)
    sha = path_fingerprint(checkpoint, store.stat_cache) if checkpoint else ""

    def run(warnings: list[str]) -> None:
        write_preview(lay.tracks, forecast_path(lay), cfg.forecast.horizon_s, cfg.forecast.model)

    return StagePlan(
        "forecast",
        [stage_file(lay.tracks)],
        [forecast_path(lay)],
        {**dataclasses.asdict(cfg.forecast), "kind": kind},
        run,
        sha,
    )


def _plan_report(
    src: SessionSource, lay: SessionLayout, cfg: PipelineConfig, store: ProvenanceStore
) -> StagePlan:
    inputs = [
        p
        for p in (
            lay.rig_toml,
            *_detection_paths(lay),
            stage_file(lay.poses3d),
            stage_file(lay.tracks),
            forecast_path(lay),
        )
        if p.exists()
    ]

    def run(warnings: list[str]) -> None:
        write_report(lay, title=src.name)

    return StagePlan("report", inputs, [lay.report_html], {"title": src.name}, run)


_PLANNERS = {
    "calibration": _plan_calibration,
    "keypoints": _plan_keypoints,
    "triangulate": _plan_triangulate,
    "track": _plan_track,
    "forecast": _plan_forecast,
    "report": _plan_report,
}


# ----------------------------------------------------------------------------- running


def _summary_path(root: Path) -> Path:
    return root / ".roomcap" / "summary.json"


def _summarise(lay: SessionLayout, result: SessionResult) -> None:
    import numpy as np

    cams = lay.detection_cameras()
    result.cameras = len(cams)
    if cams:
        result.frames = max(int(len(load_npz(lay.detections(c))["frame_index"])) for c in cams)

    def most_at_once(xyz) -> int:
        return int(np.isfinite(xyz[..., 0]).any(-1).sum(-1).max(initial=0))

    if stage_file(lay.poses3d).exists():  # the file or a streamed run's parts, one part at a time
        result.people = max((most_at_once(x) for _, x in _stage_xyz(lay.poses3d, "poses3d")), default=0)
    if stage_file(lay.tracks).exists():  # people = most tracks present at once (as the report shows)
        ids: set[int] = set()
        result.people = 0
        for tid, xyz in _stage_xyz(lay.tracks, "tracks"):
            result.people = max(result.people, most_at_once(xyz))
            ids.update(np.asarray(tid).tolist())
        result.tracks = len(ids)


def _remove_stale_temporaries(outputs: list[Path]) -> None:
    """Temporary files (``.<name>.*``) an atomic write left when the process was killed."""
    for p in outputs:
        if p.parent.is_dir():
            for tmp in p.parent.glob(f".{p.name}.*"):
                if tmp.is_file():
                    tmp.unlink(missing_ok=True)


NEEDS_CALIBRATION = ("triangulate", "track", "forecast")


def _blocking_problem(source: SessionSource, config: PipelineConfig) -> str:
    """Why the session cannot run these stages ('' if it can): a missing calibration only matters to
    the stages that use it (``reprocess --stages keypoints`` runs without one)."""
    if source.problem and source.calibration_missing and not set(config.stages) & set(NEEDS_CALIBRATION):
        return ""
    return source.problem


def _stage_list(config: PipelineConfig, source: SessionSource | None = None) -> tuple[str, ...]:
    """The stages to run: calibration always (it only imports) when there is one, keypoints also when
    it only copies detections made elsewhere, then the configured ones in graph order."""
    extra = {"calibration"} if source is None or source.calibration is not None else set()
    if source is not None and source.detections and not source.videos and not source.openpose_json:
        extra.add("keypoints")

    return tuple(s for s in STAGES if s in extra or s in config.stages)


def _explain(stage: str, e: BaseException, root: Path, done: list[str]) -> str:
    kept = f" Finished stages are kept ({', '.join(done)}); a rerun resumes from '{stage}'." if done else ""
    if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
        return (
            f"stage '{stage}': the disk is full ({e}). Free space on the disk holding {root} (or pass "
            f"--out on another disk) and rerun.{kept}"
        )
    return f"stage '{stage}': {type(e).__name__}: {e}{kept}"


class _WarningsTo(logging.Handler):
    """Collects the WARNING records logged while a session runs into its result (shown in the summary)."""

    def __init__(self, sink: list[str]):
        super().__init__(logging.WARNING)
        self.sink = sink

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = record.getMessage()
        except Exception:  # a broken log call must not fail the session
            return
        if msg not in self.sink:
            self.sink.append(msg)


def stored_warnings(root: Path, stage: str) -> list[str]:
    """The warnings a stage logged when it made its current outputs (kept beside its record)."""
    try:
        msgs = json.loads(warnings_path(root, stage).read_text())
    except (OSError, json.JSONDecodeError):
        return []
    return [str(m) for m in msgs] if isinstance(msgs, list) else []


def _keep_warnings(sink: list[str], msgs: list[str]) -> None:
    sink.extend(m for m in msgs if m not in sink)


def check_session(source: SessionSource, out: Path | None, config: PipelineConfig) -> SessionResult | None:
    """The result of a session whose every stage is up to date (without running anything), else None."""
    if _blocking_problem(source, config):
        return None
    root = output_root(source, out)
    try:
        if holder(root) is not None:  # another run is writing it: process_session refuses or waits
            return None
        saved = json.loads(_summary_path(root).read_text())
        lay, store = SessionLayout(root), ProvenanceStore(root)
        for name in _stage_list(config, source):
            plan = _PLANNERS[name](source, lay, config, store)
            if plan is None:
                continue
            if not all(p.exists() for p in plan.inputs):
                return None
            inputs = store.fingerprint_inputs(plan.inputs)
            version = stage_version(name, store.stat_cache)
            if not store.is_current(name, inputs, plan.config, plan.model_sha256, plan.outputs, version):
                return None
    except Exception:  # anything unusual: let the full run look at it (and report it)
        return None
    res = SessionResult(source.name, str(root))
    for k in ("cameras", "frames", "people", "tracks", "warnings", "skipped_cameras"):
        if k in saved:
            setattr(res, k, saved[k])
    if res.skipped_cameras:
        res.status = "partial"
    if res.warnings:  # the stages' warnings, as when they ran
        res.message = "warning: " + "; ".join(res.warnings)
    res.stage_s = {s: 0.0 for s in _stage_list(config)}
    return res


def process_session(
    source: SessionSource,
    out: Path | None,
    config: PipelineConfig,
    force: bool = False,
    threads: int | None = None,
    wait: bool = False,
) -> SessionResult:
    """Run the configured stages of one session under its lock (``pipeline.lock``); never raises (failures
    are in the result). Another run holding the session: status ``locked`` (or, with ``wait``, wait)."""
    root = output_root(source, out)
    if _blocking_problem(source, config):  # nothing will be written: no lock (nor folder) to make
        return _process_session(source, out, config, force, threads)
    try:
        with session_lock(root, wait=wait) as lock:
            result = _process_session(source, out, config, force, threads)
        if lock.took_over is not None:
            result.warnings.insert(0, lock.took_over_message(root))
            if result.status != "failed":
                result.message = "warning: " + "; ".join(result.warnings)
        return result
    except SessionLocked as e:
        return SessionResult(source.name, str(root), status="locked", failed_stage="lock", message=str(e))
    except OSError as e:
        return SessionResult(
            source.name,
            str(root),
            status="failed",
            failed_stage="lock",
            message=f"cannot take the session's lock {lock_path(root)}: {describe_os_error(e)}",
        )


def _process_session(
    source: SessionSource,
    out: Path | None,
    config: PipelineConfig,
    force: bool = False,
    threads: int | None = None,
) -> SessionResult:
    root = output_root(source, out)
    result = SessionResult(source.name, str(root))
    if threads:
        _limit_threads(threads)
    stage = "discovery"
    done: list[str] = []
    collect = _WarningsTo(result.warnings)
    logging.getLogger().addHandler(collect)
    try:
        if _blocking_problem(source, config):
            raise StageError(source.problem)
        lay = SessionLayout(root)
        for tmp in (root / ".roomcap").rglob(".*"):  # temporaries of bookkeeping writes a kill interrupted
            if tmp.is_file():
                tmp.unlink(missing_ok=True)
        store = ProvenanceStore(root)
        for name in _stage_list(config, source):
            stage = name
            t0 = time.perf_counter()
            plan = _PLANNERS[name](source, lay, config, store)
            if plan is None:
                continue
            for cam, why in plan.skipped.items():
                if cam not in result.skipped_cameras:
                    result.skipped_cameras[cam] = why
                    result.warnings.append(f"camera '{cam}' skipped ({why}); processed the other cameras")
            missing = [p for p in plan.inputs if not p.exists()]
            if missing:
                raise StageError(
                    f"needs {[str(p) for p in missing]}; run the stages before it (or drop --stages "
                    "to run them all)."
                )
            inputs = store.fingerprint_inputs(plan.inputs)
            version = stage_version(name, store.stat_cache)
            what, why = store.why_stale(name, inputs, plan.config, plan.model_sha256, plan.outputs, version)
            if not force and not what:
                result.stage_s[name] = round(time.perf_counter() - t0, 3)
                done.append(name)
                _keep_warnings(result.warnings, stored_warnings(root, name))
                continue
            if what == "outputs" and not force:  # not what the stage wrote: never trusted, and said
                log.warning("stage '%s' reruns: its outputs are not what it wrote (%s)", name, why)
            else:
                log.info("%s: stage '%s' reruns: %s", source.name, name, why)
            store.invalidate(name)
            _remove_stale_temporaries(plan.outputs)
            log.info("%s: running %s", source.name, name)
            n_warn = len(result.warnings)
            plan.run(result.warnings)
            # what this stage logged, kept with its outputs for the report (replaced when it reruns)
            atomic_write_text(warnings_path(root, name), json.dumps(result.warnings[n_warn:]))
            store.record(
                StageRecord(
                    name,
                    inputs,
                    plan.config,
                    plan.model_sha256,
                    version,
                    store.fingerprint_outputs(plan.outputs),
                    store.output_files(plan.outputs),
                )
            )
            result.ran.append(name)
            done.append(name)
            result.stage_s[name] = round(time.perf_counter() - t0, 3)
        stage = "summary"
        _summarise(lay, result)
        if result.people == 0 and (stage_file(lay.poses3d).exists() or stage_file(lay.tracks).exists()):
            result.warnings.append(
                "0 people in the result: nobody was reconstructed. See the warnings above; check that the "
                "calibration is of these cameras and in metres, and that the videos show people."
            )
        atomic_write_text(
            _summary_path(root),
            json.dumps(
                {
                    k: getattr(result, k)
                    for k in ("cameras", "frames", "people", "tracks", "warnings", "skipped_cameras")
                }
            ),
        )
    except Exception as e:  # isolate the session: the others go on, the summary reports it
        result.status = "failed"
        result.failed_stage = stage
        result.message = (
            str(e) if isinstance(e, StageError) and stage == "discovery" else _explain(stage, e, root, done)
        )
        log.debug("session %s failed:\n%s", source.name, traceback.format_exc())
    finally:
        logging.getLogger().removeHandler(collect)
    if result.status == "ok" and result.skipped_cameras:
        result.status = "partial"
    if result.status != "failed" and result.warnings:
        result.message = "warning: " + "; ".join(result.warnings)
    return result


def _limit_threads(n: int) -> None:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "ROOMCAP_ORT_THREADS"):
        os.environ[var] = str(n)
    if "torch" in sys.modules:  # importing torch just to limit it costs seconds
        sys.modules["torch"].set_num_threads(n)
