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

import numpy as np

from roomcap.capture.offline_sync import POSE2SIM_OUTPUT
from roomcap.capture.session import SessionLayout
from roomcap.core.cli import describe_os_error, interrupted
from roomcap.core.fileio import atomic_write_text, load_npz
from roomcap.pipeline.config import PipelineConfig
from roomcap.pipeline.discover import SessionSource
from roomcap.pipeline.lock import SessionLocked, holder, lock_path, session_lock
from roomcap.pipeline.provenance import ProvenanceStore, StageRecord, stage_version
from roomcap.pipeline.report import warnings_path
from roomcap.pipeline.session_inputs import StageError, stage_file
from roomcap.pipeline.stages import STAGES, Session, Stage, StageWork
from roomcap.triangulate.chunks import ChunkRunner, PartStore, StreamConfig

log = logging.getLogger(__name__)


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


def output_root(source: SessionSource, out: Path | None) -> Path:
    """Where a session's outputs go: ``out/<name>``, or in place for this project's own layout."""
    if out is not None:
        return Path(out) / source.name
    if source.layout == "roomcap":
        return source.root
    return source.root / POSE2SIM_OUTPUT


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


# ----------------------------------------------------------------------------- running


def _summary_path(root: Path) -> Path:
    return root / ".roomcap" / "summary.json"


def _summarise(lay: SessionLayout, result: SessionResult) -> None:
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


def _stage_list(config: PipelineConfig, source: SessionSource | None = None) -> tuple[Stage, ...]:
    """The stages to run: calibration always (it only imports) when there is one, keypoints also when
    it only copies detections made elsewhere, then the configured ones in graph order."""
    extra = {"calibration"} if source is None or source.calibration is not None else set()
    if source is not None and source.detections and not source.videos and not source.openpose_json:
        extra.add("keypoints")
    return tuple(s for s in STAGES if s.name in extra or s.name in config.stages)


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


SUMMARY_KEYS = (
    "cameras",
    "frames",
    "people",
    "tracks",
    "warnings",
    "skipped_cameras",
)  # kept in summary.json


def check_session(source: SessionSource, out: Path | None, config: PipelineConfig) -> SessionResult | None:
    """The result of a session whose every stage is up to date (without running anything), else None."""
    if _blocking_problem(source, config):
        return None
    root = output_root(source, out)
    try:
        if holder(root) is not None:  # another run is writing it: process_session refuses or waits
            return None
        saved = json.loads(_summary_path(root).read_text())
        session = Session(source, SessionLayout(root), ProvenanceStore(root))
        for stage in _stage_list(config, source):
            work = stage.plan(session, stage.config(config))
            if work is None:
                continue
            if not all(p.exists() for p in work.inputs):
                return None
            if _staleness(session, stage.name, work)[0]:
                return None
    except Exception:  # anything unusual: let the full run look at it (and report it)
        return None
    res = SessionResult(source.name, str(root))
    for k in SUMMARY_KEYS:
        if k in saved:
            setattr(res, k, saved[k])
    if res.skipped_cameras:
        res.status = "partial"
    if res.warnings:  # the stages' warnings, as when they ran
        res.message = "warning: " + "; ".join(res.warnings)
    res.stage_s = {s.name: 0.0 for s in _stage_list(config)}
    return res


def _staleness(session: Session, name: str, work: StageWork) -> tuple[str, str]:
    """``(what, why)`` a stage's outputs are stale for ('' when they are current)."""
    store = session.store
    inputs = store.fingerprint_inputs(work.inputs)
    version = stage_version(name, store.stat_cache)
    return store.why_stale(name, inputs, work.settings, work.model_sha256, work.outputs, version)


def process_session(
    source: SessionSource,
    out: Path | None,
    config: PipelineConfig,
    force: bool = False,
    threads: int | None = None,
    wait: bool = False,
    chunks: Callable[[StreamConfig], ChunkRunner | None] | None = None,
) -> SessionResult:
    """Run the configured stages of one session under its lock (``pipeline.lock``); never raises (failures
    are in the result). Another run holding the session: status ``locked`` (or, with ``wait``, wait).
    ``chunks``: what runs a stage's independent chunks (``pipeline.executors.chunk_runner``); None: the
    stage's own process."""
    root = output_root(source, out)
    if _blocking_problem(source, config):  # nothing will be written: no lock (nor folder) to make
        return _process_session(source, out, config, force, threads, chunks)
    try:
        with session_lock(root, wait=wait) as lock:
            result = _process_session(source, out, config, force, threads, chunks)
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
    force: bool,
    threads: int | None,
    chunks: Callable[[StreamConfig], ChunkRunner | None] | None,
) -> SessionResult:
    root = output_root(source, out)
    result = SessionResult(source.name, str(root))
    if threads:
        _limit_threads(threads)
    stage_name = "discovery"
    done: list[str] = []
    collect = _WarningsTo(result.warnings)
    logging.getLogger().addHandler(collect)
    try:
        if _blocking_problem(source, config):
            raise StageError(source.problem)
        for tmp in (root / ".roomcap").rglob(".*"):  # temporaries of bookkeeping writes a kill interrupted
            if tmp.is_file():
                tmp.unlink(missing_ok=True)
        session = Session(source, SessionLayout(root), ProvenanceStore(root), result.warnings)
        for stage in _stage_list(config, source):
            stage_name = stage.name
            if _run_stage(session, stage, config, force, chunks, result):
                result.ran.append(stage.name)
            done.append(stage.name)
        stage_name = "summary"
        _write_summary(session.layout, result)
    except Exception as e:  # isolate the session: the others go on, the summary reports it
        if interrupted(e):  # a Ctrl-C that native code handed back as another error: stop, not "failed"
            raise KeyboardInterrupt from e
        result.status = "failed"
        result.failed_stage = stage_name
        result.message = (
            str(e)
            if isinstance(e, StageError) and stage_name == "discovery"
            else _explain(stage_name, e, root, done)
        )
        log.debug("session %s failed:\n%s", source.name, traceback.format_exc())
    finally:
        logging.getLogger().removeHandler(collect)
    if result.status == "ok" and result.skipped_cameras:
        result.status = "partial"
    if result.status != "failed" and result.warnings:
        result.message = "warning: " + "; ".join(result.warnings)
    return result


def _run_stage(
    session: Session,
    stage: Stage,
    config: PipelineConfig,
    force: bool,
    chunks: Callable[[StreamConfig], ChunkRunner | None] | None,
    result: SessionResult,
) -> bool:
    """One stage of the session, unless its outputs are current; True when it ran."""
    t0 = time.perf_counter()
    stage_config = stage.config(config)
    work = stage.plan(session, stage_config)
    if work is None:
        return False
    for cam, why in work.skipped.items():
        if cam not in result.skipped_cameras:
            result.skipped_cameras[cam] = why
            result.warnings.append(f"camera '{cam}' skipped ({why}); processed the other cameras")
    missing = [p for p in work.inputs if not p.exists()]
    if missing:
        raise StageError(
            f"needs {[str(p) for p in missing]}; run the stages before it (or drop --stages to run them all)."
        )
    root, store, name = session.layout.root, session.store, stage.name
    what, why = _staleness(session, name, work)
    if not force and not what:
        result.stage_s[name] = round(time.perf_counter() - t0, 3)
        _keep_warnings(result.warnings, stored_warnings(root, name))
        return False
    if what == "outputs" and not force:  # not what the stage wrote: never trusted, and said
        log.warning("stage '%s' reruns: its outputs are not what it wrote (%s)", name, why)
    else:
        log.info("%s: stage '%s' reruns: %s", session.source.name, name, why)
    store.invalidate(name)
    _remove_stale_temporaries(work.outputs)
    log.info("%s: running %s", session.source.name, name)
    n_warn = len(result.warnings)
    stream = getattr(stage_config, "stream", None)
    stage.run(session, stage_config, None, chunks(stream) if chunks and stream else None)
    # what this stage logged, kept with its outputs for the report (replaced when it reruns)
    atomic_write_text(warnings_path(root, name), json.dumps(result.warnings[n_warn:]))
    store.record(
        StageRecord(
            name,
            store.fingerprint_inputs(work.inputs),
            work.settings,
            work.model_sha256,
            stage_version(name, store.stat_cache),
            store.fingerprint_outputs(work.outputs),
            store.output_files(work.outputs),
        )
    )
    result.stage_s[name] = round(time.perf_counter() - t0, 3)
    return True


def _write_summary(lay: SessionLayout, result: SessionResult) -> None:
    _summarise(lay, result)
    if result.people == 0 and (stage_file(lay.poses3d).exists() or stage_file(lay.tracks).exists()):
        result.warnings.append(
            "0 people in the result: nobody was reconstructed. See the warnings above; check that the "
            "calibration is of these cameras and in metres, and that the videos show people."
        )
    summary = {k: getattr(result, k) for k in SUMMARY_KEYS}
    atomic_write_text(_summary_path(Path(result.out)), json.dumps(summary))


def _limit_threads(n: int) -> None:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "ROOMCAP_ORT_THREADS"):
        os.environ[var] = str(n)
    if "torch" in sys.modules:  # importing torch just to limit it costs seconds
        sys.modules["torch"].set_num_threads(n)
