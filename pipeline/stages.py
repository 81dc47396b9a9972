"""The stages of a session, one small object each, listed once in :data:`STAGES`.

calibration ─► keypoints ─► triangulate ─► track ─► forecast ─► report

A stage object knows its section of the :class:`~roomcap.pipeline.config.PipelineConfig` (:meth:`config`,
a typed config), what it reads and writes on one session and the settings its outputs depend on
(:meth:`plan`, a :class:`StageWork`, or None when the session needs nothing of it), and does its job
with :meth:`run` ``(session, config, progress, executor)``. The runner (:mod:`roomcap.pipeline.runner`) walks
the tuple, decides from the provenance records which stages are stale, and runs those; the algorithms live in
the stage packages.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from roomcap.calibrate.camera import CameraRig
from roomcap.calibrate.formats import import_calibration
from roomcap.capture.session import SessionLayout
from roomcap.core.fileio import atomic_write_bytes
from roomcap.core.progress import Progress
from roomcap.forecast.runtime.preview import forecast_model, write_preview
from roomcap.keypoints.openpose_json import read_openpose_folder
from roomcap.keypoints.registry import get_model_set, resolve
from roomcap.keypoints.runtime import RuntimeConfig
from roomcap.keypoints.video import run_videos
from roomcap.pipeline.config import (
    ForecastConfig,
    KeypointsConfig,
    PipelineConfig,
    TrackerChoice,
    tracker_name,
)
from roomcap.pipeline.discover import SessionSource
from roomcap.pipeline.provenance import ProvenanceStore, path_fingerprint
from roomcap.pipeline.report import report_inputs, write_report
from roomcap.pipeline.session_inputs import (
    StageError,
    carry_sync,
    detection_paths,
    match_camera_names,
    pose2sim_frame_rate,
    readable_videos,
    stage_file,
    sync_table,
    video_checks,
)
from roomcap.track.greedy_stage import GreedyTrackConfig, track_session_greedy
from roomcap.track.stage import ParticleTrackConfig, stream_chunk_s, track_session_particle
from roomcap.triangulate.chunks import ChunkRunner, parts_dir
from roomcap.triangulate.multiview import session_chunk_s
from roomcap.triangulate.reconstruct import TriangulateConfig
from roomcap.triangulate.stage import triangulate_session


@dataclass
class Session:
    """One session as the stages see it: where its inputs come from, where its outputs go, its cache
    records, and the warnings its stages log for the summary."""

    source: SessionSource
    layout: SessionLayout
    store: ProvenanceStore
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class StageWork:
    """What a stage reads and writes on one session, and the settings its outputs depend on."""

    inputs: list[Path]
    outputs: list[Path]
    settings: dict[str, Any]  # recorded with the outputs; a change reruns the stage
    model_sha256: str = ""
    skipped: dict[str, str] = field(default_factory=dict)  # cameras the stage leaves out, and why


class Stage(Protocol):
    name: str

    def config(self, pipeline: PipelineConfig) -> Any: ...

    def plan(self, session: Session, config: Any) -> StageWork | None: ...

    def run(
        self, session: Session, config: Any, progress: Progress | None, executor: ChunkRunner | None
    ) -> None: ...


def model_set_sha256(
    model_set: str, store: ProvenanceStore | None = None, extra: tuple[str, ...] = ()
) -> str:
    """sha256 of the model files of a keypoints model set (detector+pose) and the ``extra`` models (the hand
    landmark model and palm detector of a hands preset), via the stat cache."""
    ms = get_model_set(model_set)
    names = [n for n in (ms.detector, ms.pose, *extra) if n]
    cache = store.stat_cache if store is not None else None
    return "+".join(path_fingerprint(resolve(n, verify=False), cache) for n in names)


def _result_settings(config: TriangulateConfig | TrackerChoice) -> dict[str, Any]:
    """A 3D stage's settings without how its chunks ran (``stream.workers``, ``stream.executor``) or how
    the particle filter computed its batch (``particle.threads``)."""
    if isinstance(config, ParticleTrackConfig):
        config = dataclasses.replace(config, particle=config.particle.result_settings())
    return {**dataclasses.asdict(config), "stream": config.stream.result_settings()}


class CalibrationStage:
    """Imports the session's calibration (any format :func:`roomcap.calibrate.formats.import_calibration`
    reads) into ``calib/rig.toml``, with the recording's camera names."""

    name = "calibration"

    def config(self, pipeline: PipelineConfig) -> None:
        return None

    def plan(self, session: Session, config: None) -> StageWork | None:
        src, target = session.source, session.layout.rig_toml
        if src.calibration is None:
            raise FileNotFoundError(src.problem or f"session {src.name} has no calibration")
        if src.calibration.resolve() == target.resolve():
            return None  # the session's own rig is the input of later stages
        return StageWork([src.calibration], [target], {})

    def run(
        self, session: Session, config: None, progress: Progress | None, executor: ChunkRunner | None
    ) -> None:
        src = session.source
        assert src.calibration is not None
        rig = match_camera_names(import_calibration(src.calibration), src.cameras)
        missing = [c for c in src.cameras if c not in rig.names]
        if missing:
            raise ValueError(
                f"{src.calibration}: cameras {missing} of the recording are not in the calibration "
                f"(it has {list(rig.names)}). Use a calibration of these cameras."
            )
        rig.save(session.layout.rig_toml)


class KeypointsStage:
    """The 2D stage: videos -> ``keypoints/<cam>.npz`` with the ``[keypoints]`` preset; or OpenPose JSON
    folders read, or detections made elsewhere copied into the output session."""

    name = "keypoints"

    def config(self, pipeline: PipelineConfig) -> KeypointsConfig:
        return pipeline.keypoints

    def plan(self, session: Session, config: KeypointsConfig) -> StageWork | None:
        src, lay = session.source, session.layout
        if src.videos:
            readable, skipped, _ = readable_videos(src.videos)
            if not readable:
                raise StageError(
                    "no camera's video can be read: " + " ".join(skipped.values())
                    if len(skipped) > 1
                    else next(iter(skipped.values()))
                )
            frames_csv = self._frames_csv(src, sorted(readable))
            return StageWork(
                [readable[c] for c in sorted(readable)] + sorted(frames_csv.values()),
                [lay.detections(c) for c in sorted(readable)],
                config.provenance(),
                model_set_sha256(
                    config.model_set_name, session.store, (config.detector.hands, config.detector.palm)
                ),
                skipped,
            )
        if src.openpose_json:
            cams = sorted(src.openpose_json)
            return StageWork(
                [src.openpose_json[c] for c in cams],
                [lay.detections(c) for c in cams],
                {"from": "openpose_json"},
            )
        if (
            src.detections
        ):  # detections made elsewhere: copied into the output session (unless it is the input)
            cams = sorted(src.detections)
            if all(src.detections[c].resolve() == lay.detections(c).resolve() for c in cams):
                return None
            return StageWork(
                [src.detections[c] for c in cams], [lay.detections(c) for c in cams], {"from": "detections"}
            )
        return None

    @staticmethod
    def _frames_csv(src: SessionSource, cams: list[str]) -> dict[str, Path]:
        """The recorder's per-frame timestamps (``t_ns`` in the detections) of a roomcap session."""
        if src.layout != "roomcap":
            return {}
        src_lay = SessionLayout(src.root)
        return {c: p for c in cams if (p := src_lay.find_frames_csv(c)) is not None}

    def run(
        self,
        session: Session,
        config: KeypointsConfig,
        progress: Progress | None,
        executor: ChunkRunner | None,
    ) -> None:
        src, lay = session.source, session.layout
        if src.videos:
            self._run_videos(session, config)
        elif src.openpose_json:
            fps = pose2sim_frame_rate(src.root)
            for c in sorted(src.openpose_json):
                read_openpose_folder(src.openpose_json[c], camera=c, fps=fps).save(lay.detections(c))
        else:
            for c in sorted(src.detections):
                atomic_write_bytes(lay.detections(c), src.detections[c].read_bytes())

    def _run_videos(self, session: Session, config: KeypointsConfig) -> None:
        src, lay = session.source, session.layout
        readable, _, info = readable_videos(src.videos)
        session.warnings.extend(video_checks(info))
        rig = CameraRig.load(lay.rig_toml) if lay.rig_toml.exists() else None
        # the executor's share of the cores (set per worker by the runner); 0 = onnxruntime's default
        threads = int(os.environ.get("ROOMCAP_ORT_THREADS", "0") or 0)
        detector = dataclasses.replace(config.detector, runtime=RuntimeConfig(threads=threads))
        frames_csv = self._frames_csv(src, sorted(readable))
        rep = run_videos(
            readable,
            lay.keypoints_dir,
            detector,
            rig=rig,
            max_frames=config.max_frames,
            timestamps=frames_csv or None,
            # one camera group per core of this worker, one onnxruntime thread each: 1.3x the frames
            # per second of one group with two threads on 2 cores (bench_keypoints_throughput.py)
            camera_groups=threads or os.cpu_count() or 1,
        )
        for c, (fi, msg) in sorted(rep.decode_errors.items()):
            session.warnings.append(f"camera '{c}': {msg}; kept the {fi} frames before it")


class TriangulateStage:
    """Association and robust DLT per frame: ``triangulate/poses3d.npz`` (or its parts, streamed)."""

    name = "triangulate"

    def config(self, pipeline: PipelineConfig) -> TriangulateConfig:
        return pipeline.triangulate

    def plan(self, session: Session, config: TriangulateConfig) -> StageWork:
        lay = session.layout
        streamed = session_chunk_s(lay, config.stream) > 0
        return StageWork(
            [lay.rig_toml, *detection_paths(lay)],
            [parts_dir(lay.poses3d) if streamed else lay.poses3d],
            # new sync offsets: rerun
            {
                "options": _result_settings(config),
                "sync": sync_table(session.source),
            },
        )

    def run(
        self,
        session: Session,
        config: TriangulateConfig,
        progress: Progress | None,
        executor: ChunkRunner | None,
    ) -> None:
        carry_sync(session.source, session.layout)
        triangulate_session(session.layout.root, config, progress, executor)


class TrackStage:
    """The tracker ``[track] tracker`` chooses: the particle filter on the detections (ch. 5) or the
    greedy tracker on the per-frame 3D poses (ch. 4); ``track/tracks.npz`` (or its parts, streamed)."""

    name = "track"

    def config(self, pipeline: PipelineConfig) -> TrackerChoice:
        return pipeline.track

    def plan(self, session: Session, config: TrackerChoice) -> StageWork:
        lay = session.layout
        inputs = [lay.rig_toml, *detection_paths(lay)]
        settings: dict[str, Any] = {
            "tracker": tracker_name(config),
            "options": _result_settings(config),
        }
        if isinstance(config, GreedyTrackConfig):
            inputs.append(stage_file(lay.poses3d))  # the file or a streamed run's parts
            streamed = session_chunk_s(lay, config.stream) > 0
        else:  # the particle tracker reads the detections (and their sync offsets) itself
            settings["sync"] = sync_table(session.source)
            streamed = stream_chunk_s(lay, config) > 0
        return StageWork(inputs, [parts_dir(lay.tracks) if streamed else lay.tracks], settings)

    def run(
        self, session: Session, config: TrackerChoice, progress: Progress | None, executor: ChunkRunner | None
    ) -> None:
        carry_sync(session.source, session.layout)
        if isinstance(config, ParticleTrackConfig):
            track_session_particle(session.layout.root, config, progress)
        else:
            track_session_greedy(session.layout.root, config)


def forecast_path(lay: SessionLayout) -> Path:
    return lay.root / "forecast" / "preview.npz"


class ForecastStage:
    """The next ``horizon_s`` of every track present at the last frame: ``forecast/preview.npz``."""

    name = "forecast"

    def config(self, pipeline: PipelineConfig) -> ForecastConfig:
        return pipeline.forecast

    def plan(self, session: Session, config: ForecastConfig) -> StageWork:
        kind, checkpoint = forecast_model(config.model)
        sha = path_fingerprint(checkpoint, session.store.stat_cache) if checkpoint else ""
        return StageWork(
            [stage_file(session.layout.tracks)],
            [forecast_path(session.layout)],
            {**dataclasses.asdict(config), "kind": kind},
            sha,
        )

    def run(
        self,
        session: Session,
        config: ForecastConfig,
        progress: Progress | None,
        executor: ChunkRunner | None,
    ) -> None:
        lay = session.layout
        write_preview(lay.tracks, forecast_path(lay), config.horizon_s, config.model, config.samples)


class ReportStage:
    """The session's HTML report: ``report/report.html``."""

    name = "report"

    def config(self, pipeline: PipelineConfig) -> None:
        return None

    def plan(self, session: Session, config: None) -> StageWork:
        lay = session.layout
        return StageWork(report_inputs(lay), [lay.report_html], {"title": session.source.name})

    def run(
        self, session: Session, config: None, progress: Progress | None, executor: ChunkRunner | None
    ) -> None:
        write_report(session.layout, title=session.source.name)


STAGES: tuple[Stage, ...] = (
    CalibrationStage(),
    KeypointsStage(),
    TriangulateStage(),
    TrackStage(),
    ForecastStage(),
    ReportStage(),
)
