"""Running the stages of one session as a small graph, cached and resumable.

calibration ─► keypoints ─► triangulate ─► track ─► forecast ─► report

Each stage declares its inputs and outputs; it runs only when its provenance
record (``pipeline/provenance.py``) says its outputs are stale or missing.
Every output is written atomically by the stage that owns it and the record
is written last, so a run killed at any point resumes where it stopped and
ends with the same files as an uninterrupted run. This module wires stages
together; the algorithms live in the stage packages.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capture.session import SessionLayout
from pipeline.config import PipelineConfig
from pipeline.discover import SessionSource
from pipeline.provenance import ProvenanceStore, StageRecord, package_version

log = logging.getLogger(__name__)


@dataclass
class SessionResult:
    name: str
    out: str
    status: str = "ok"  # ok | failed | skipped
    message: str = ""
    cameras: int = 0
    frames: int = 0
    people: int = 0
    tracks: int = 0
    stage_s: dict[str, float] = field(default_factory=dict)
    ran: list[str] = field(default_factory=list)  # stages that did work (the rest were up to date)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class StagePlan:
    name: str
    inputs: list[Path]
    outputs: list[Path]
    config: dict[str, Any]
    run: Callable[[], None]
    model_sha256: str = ""


def output_root(source: SessionSource, out: Path | None) -> Path:
    """Where a session's outputs go: ``out/<name>``, or in place for this project's own layout."""
    if out is not None:
        return Path(out) / source.name
    if source.layout == "roomcap":
        return source.root
    return source.root / "roomcap"


# ----------------------------------------------------------------------------- stage plans


def _plan_calibration(src: SessionSource, lay: SessionLayout, cfg: PipelineConfig) -> StagePlan | None:
    target = lay.calib_dir / "rig.toml"
    if src.calibration is None:
        raise FileNotFoundError(src.problem or f"session {src.name} has no calibration")
    if src.calibration.resolve() == target.resolve():
        return None  # the session's own rig is the input of later stages

    def run() -> None:
        from calibrate.formats import import_calibration

        rig = import_calibration(src.calibration)
        missing = [c for c in src.cameras if c not in rig.names]
        if missing:
            raise ValueError(f"{src.calibration}: cameras {missing} of the recording are not in the calibration "
                             f"(it has {list(rig.names)}). Use a calibration of these cameras.")
        rig.save(target)

    return StagePlan("calibration", [src.calibration], [target], {}, run)


def _plan_keypoints(src: SessionSource, lay: SessionLayout, cfg: PipelineConfig) -> StagePlan | None:
    if src.videos:
        cams = sorted(src.videos)
        outputs = [lay.detections(c) for c in cams]
        kcfg = dataclasses.asdict(cfg.keypoints)

        from keypoints.video import model_set_sha256, run_videos

        def run() -> None:
            run_videos({c: src.videos[c] for c in cams}, lay.keypoints_dir, model_set=cfg.keypoints.model_set,
                       max_frames=cfg.keypoints.max_frames, rig_path=lay.rig_toml, progress=False)

        return StagePlan("keypoints", [src.videos[c] for c in cams], outputs, kcfg, run,
                         model_set_sha256(cfg.keypoints.model_set))
    if src.openpose_json:
        cams = sorted(src.openpose_json)
        outputs = [lay.detections(c) for c in cams]

        def run_json() -> None:
            from keypoints.openpose_json import read_openpose_folder

            for c in cams:
                read_openpose_folder(src.openpose_json[c], camera=c).save(lay.detections(c))

        return StagePlan("keypoints", [src.openpose_json[c] for c in cams], outputs, {"from": "openpose_json"},
                         run_json)
    return None  # detections made elsewhere are the input


def _detection_paths(lay: SessionLayout) -> list[Path]:
    return [lay.detections(c) for c in lay.detection_cameras()]


def _plan_triangulate(src: SessionSource, lay: SessionLayout, cfg: PipelineConfig) -> StagePlan:
    def run() -> None:
        from triangulate.stage import triangulate_session

        triangulate_session(lay.root, cfg.triangulate.options)

    return StagePlan("triangulate", [lay.rig_toml, *_detection_paths(lay)], [lay.poses3d],
                     dataclasses.asdict(cfg.triangulate), run)


def _plan_track(src: SessionSource, lay: SessionLayout, cfg: PipelineConfig) -> StagePlan:
    def run() -> None:
        if cfg.track.tracker == "greedy":
            from triangulate.stage import track_session_greedy

            track_session_greedy(lay.root, cfg.track.options)
        else:
            from track.stage import track_session_particle

            track_session_particle(lay.root, cfg.track.options)

    inputs = [lay.rig_toml, *_detection_paths(lay)]
    if cfg.track.tracker == "greedy":
        inputs.append(lay.poses3d)
    return StagePlan("track", inputs, [lay.tracks], dataclasses.asdict(cfg.track), run)


def _forecast_path(lay: SessionLayout) -> Path:
    return lay.root / "forecast" / "preview.npz"


def _plan_forecast(src: SessionSource, lay: SessionLayout, cfg: PipelineConfig) -> StagePlan:
    def run() -> None:
        from forecast.preview import write_preview

        write_preview(lay.tracks, _forecast_path(lay), horizon_s=cfg.forecast.horizon_s, model=cfg.forecast.model)

    return StagePlan("forecast", [lay.tracks], [_forecast_path(lay)], dataclasses.asdict(cfg.forecast), run)


def _plan_report(src: SessionSource, lay: SessionLayout, cfg: PipelineConfig) -> StagePlan:
    inputs = [p for p in (lay.rig_toml, *_detection_paths(lay), lay.poses3d, lay.tracks, _forecast_path(lay))
              if p.exists()]

    def run() -> None:
        from pipeline.report import write_report

        write_report(lay, title=src.name)

    return StagePlan("report", inputs, [lay.report_html], {}, run)


_PLANNERS = {"calibration": _plan_calibration, "keypoints": _plan_keypoints, "triangulate": _plan_triangulate,
             "track": _plan_track, "forecast": _plan_forecast, "report": _plan_report}


# ----------------------------------------------------------------------------- running


def _summarise(lay: SessionLayout, result: SessionResult) -> None:
    import numpy as np

    from capture.fileio import load_npz

    cams = lay.detection_cameras()
    result.cameras = len(cams)
    if cams:
        d = load_npz(lay.detections(cams[0]))
        result.frames = int(len(d["frame_index"]))
    if lay.poses3d.exists():
        xyz = load_npz(lay.poses3d)["xyz_m"]
        result.people = int(np.isfinite(xyz[..., 0]).any(-1).sum(-1).max(initial=0))
    if lay.tracks.exists():
        result.tracks = int(len(load_npz(lay.tracks)["track_id"]))


def process_session(source: SessionSource, out: Path | None, config: PipelineConfig, force: bool = False,
                    threads: int | None = None) -> SessionResult:
    """Run the configured stages of one session; never raises (failures are in the result)."""
    root = output_root(source, out)
    result = SessionResult(source.name, str(root))
    if threads:
        _limit_threads(threads)
    try:
        if source.problem:
            raise RuntimeError(source.problem)
        lay = SessionLayout(root)
        store = ProvenanceStore(root)
        stages = ("calibration", *config.stages) if "calibration" not in config.stages else config.stages
        for name in stages:
            t0 = time.perf_counter()
            plan = _PLANNERS[name](source, lay, config)
            if plan is None:
                continue
            missing = [p for p in plan.inputs if not p.exists()]
            if missing:
                raise FileNotFoundError(f"stage '{name}' needs {[str(p) for p in missing]}; run the stages "
                                        "before it (or drop --stages to run them all).")
            inputs = store.fingerprint_inputs(plan.inputs)
            if not force and store.is_current(name, inputs, plan.config, plan.model_sha256, plan.outputs):
                result.stage_s[name] = round(time.perf_counter() - t0, 3)
                continue
            store.invalidate(name)
            log.info("%s: running %s", source.name, name)
            plan.run()
            store.record(StageRecord(name, inputs, plan.config, plan.model_sha256, package_version(),
                                     store.fingerprint_outputs(plan.outputs)))
            result.ran.append(name)
            result.stage_s[name] = round(time.perf_counter() - t0, 3)
        _summarise(lay, result)
    except Exception as e:  # isolate the session: the others go on, the summary reports it
        result.status = "failed"
        result.message = f"{type(e).__name__}: {e}"
        log.debug("session %s failed:\n%s", source.name, traceback.format_exc())
    return result


def _limit_threads(n: int) -> None:
    import os

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "ROOMCAP_ORT_THREADS"):
        os.environ[var] = str(n)
    try:
        import torch

        torch.set_num_threads(n)
    except ImportError:
        pass
