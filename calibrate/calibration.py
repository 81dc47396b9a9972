"""Board recording of many cameras -> ``rig.toml`` + report: the orchestration behind
``calibrate-run calibrate`` / ``make calibrate``.

Output folder (the folder of ``rig.toml``)::

    rig.toml              the calibrated rig (calibrate/camera.py format)
    detections/<cam>.npz  cached detections (reused when the videos and the board's pattern are unchanged)
    report/report.toml    per-camera intrinsic/extrinsic RMS, frames used, coverage, pair links, BA
    report/layout.png     cameras and board poses in 3D
    report/coverage.png   where the board was seen in each camera
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roomcap.calibrate.boards import Board, CalibrationError, load_board
from roomcap.calibrate.camera import Camera, CameraRig
from roomcap.calibrate.detect import (
    CameraDetections,
    detect_all,
    diagnose_board,
    diagnose_grid,
    discover_recording,
)
from roomcap.calibrate.extrinsics import LOSSES, ExtrinsicsConfig, ExtrinsicsResult, calibrate_extrinsics
from roomcap.calibrate.intrinsics import MODELS, IntrinsicsConfig, IntrinsicsResult, calibrate_intrinsics
from roomcap.calibrate.report import report_dict, summary_text, write_report
from roomcap.core.progress import Progress

log = logging.getLogger(__name__)

__all__ = ["CalibrationConfig", "CalibrationOutcome", "calibrate_recording"]


@dataclass(frozen=True)
class CalibrationConfig:
    model: str = "pinhole"  # intrinsics model, see calibrate/intrinsics.py
    refine_intrinsics: str = "none"  # in the bundle adjustment: "none" | "focal_pp" | "all"
    detect_max_frames: int = 1000  # frames examined per camera (evenly spaced)
    intrinsic_frames: int = 40
    extrinsic_frames: int = 300
    min_frames: int = 6
    loss: str = "soft_l1"
    world: str = ""  # "" (first camera) | "camera:NAME" | "board:FRAME"
    exclude: tuple[str, ...] = ()
    intrinsics_from: str = ""  # rig.toml whose cameras' intrinsics are used as given
    workers: int = 0  # detection threads (0: one per camera)

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"model {self.model!r} is not one of {list(MODELS)}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss {self.loss!r} is not one of {list(LOSSES)}")


@dataclass(frozen=True)
class CalibrationOutcome:
    rig: CameraRig
    detections: dict[str, CameraDetections]
    intrinsics: dict[str, IntrinsicsResult | None]
    extrinsics: ExtrinsicsResult | None
    report: dict[str, Path]
    timings_s: dict[str, float] = field(default_factory=dict)
    summary: str = ""


def _stage(progress: Progress | None, stage: str) -> Progress | None:
    """Prefix the tasks a step reports (a camera, a bundle adjustment phase) with the stage's name."""
    if progress is None:
        return None
    return lambda item, done, total: progress(f"{stage} {item}", done, total)


def calibrate_recording(
    recording: str | os.PathLike,
    board: Board | str | os.PathLike,
    out_rig: str | os.PathLike,
    config: CalibrationConfig | None = None,
    progress: Progress | None = None,
) -> CalibrationOutcome:
    """Detect, calibrate intrinsics and extrinsics, write rig.toml and the report (see module doc)."""
    cfg = config or CalibrationConfig()
    board_path = None
    if not isinstance(board, Board):
        board_path = Path(board)
        board = load_board(board_path)
    out_rig = Path(out_rig)
    out_dir = out_rig.parent
    timings: dict[str, float] = {}
    sources = _sources(recording, cfg)
    log.info("calibrating %d camera(s) %s with %s", len(sources), [s.name for s in sources], board.describe())

    t0 = time.perf_counter()
    dets = detect_all(
        board,
        sources,
        out_dir / "detections",
        cfg.detect_max_frames,
        workers=cfg.workers or None,
        progress=_stage(progress, "detect"),
    )
    timings["detect_s"] = time.perf_counter() - t0
    _check_board_seen(board, board_path, recording, sources, dets, cfg, out_dir, progress)

    t0 = time.perf_counter()
    intr, cams = _intrinsics(board, dets, cfg, progress)
    timings["intrinsics_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ext, rig = _extrinsics(board, cams, dets, cfg, progress)
    timings["extrinsics_s"] = time.perf_counter() - t0

    src = (
        f"calibrate-run calibrate {Path(recording).name} ({board.describe()}; model {cfg.model}, "
        f"refine_intrinsics {cfg.refine_intrinsics}, world {ext.world if ext else '-'})"
    )
    rig.save(out_rig, source=src)
    report = write_report(
        out_dir / "report",
        board,
        rig,
        dets,
        intr,
        ext,
        extra={
            "timings_s": timings,
            "recording": str(Path(recording).resolve()),
            "rig": str(out_rig.resolve()),
        },
    )

    text = summary_text(report_dict(board, rig, dets, intr, ext))
    return CalibrationOutcome(rig, dets, intr, ext, report, timings, text)


def _sources(recording: str | os.PathLike, cfg: CalibrationConfig) -> list:
    """The recording's cameras less ``cfg.exclude`` (each excluded name must be one of them)."""
    sources = [s for s in discover_recording(recording) if s.name not in cfg.exclude]
    unknown = sorted(set(cfg.exclude) - {s.name for s in discover_recording(recording)})
    if unknown:
        raise CalibrationError(f"--exclude {unknown}: no such camera in {recording}.")
    if not sources:
        raise CalibrationError(f"No camera left to calibrate in {recording}.")
    return sources


def _check_board_seen(
    board: Board,
    board_path: Path | None,
    recording: str | os.PathLike,
    sources: list,
    dets: dict,
    cfg: CalibrationConfig,
    out_dir: Path,
    progress: Progress | None,
) -> None:
    """Stop with a diagnosis when the board was seen in too few frames (a wrong grid or board file, or no
    board at all)."""
    seen = {k: len(v.seen_frames()) for k, v in dets.items()}
    if not cfg.intrinsics_from and all(n < cfg.min_frames for n in seen.values()):
        wrong_grid = diagnose_grid(board, sources)  # few views: a board file whose grid is not the print's?
        if wrong_grid:
            fix = f"Edit {board_path}" if board_path else "Change the board"
            raise CalibrationError(
                f"The board ({board.describe()}) was found in too few frames ({seen}). Diagnosis: "
                f"{wrong_grid}. {fix} accordingly and run again."
            )
    if all(n < 2 for n in seen.values()):  # nothing anywhere: the board file does not match the board
        diag = diagnose_board(board, sources)
        where = f"Edit {board_path}" if board_path else "Change the board"
        if diag.board is not None and diag.board.detection_key() != board.detection_key():
            # detect with the matching settings now, so the run after fixing the file reuses the cache
            detect_all(
                diag.board,
                sources,
                out_dir / "detections",
                cfg.detect_max_frames,
                workers=cfg.workers or None,
                progress=_stage(progress, "detect (diagnosis)"),
            )
            raise CalibrationError(
                f"The board ({board.describe()}) was found in no camera ({seen}). Diagnosis: {diag.message}. "
                f"{where} accordingly and run again; the detections with the matching settings are cached in "
                f"{out_dir / 'detections'}, so the next run will not detect again."
            )
        if diag.board is None and not diag.markers_by_dictionary:  # not a setting: nothing board-like at all
            raise CalibrationError(
                f"No board was seen at all in the {len(sources)} camera(s) of {recording}: {diag.message}. "
                "Check that the recording shows the board (in view, in focus, lit, its markers or squares "
                f"at least about 20 px wide); the board settings ({board.describe()}) cannot be checked "
                "before something of a board is seen."
            )
        raise CalibrationError(
            f"The board ({board.describe()}) was found in no camera ({seen}). Diagnosis: {diag.message}. "
            "Check the board file (squares, dictionary, marker size) against the printed board, and that the "
            "board is in focus and large enough in the images."
        )


def _intrinsics(
    board: Board, dets: dict, cfg: CalibrationConfig, progress: Progress | None
) -> tuple[dict[str, IntrinsicsResult | None], list[Camera]]:
    """Each camera's intrinsics, calibrated or taken from ``cfg.intrinsics_from`` (result None), at R = I,
    t = 0; every camera's problem in one error."""
    given: dict[str, Camera] = {}
    if cfg.intrinsics_from:
        known = CameraRig.load(cfg.intrinsics_from)
        given = {c.name: c for c in known.cameras if c.name in dets}
    intr: dict[str, IntrinsicsResult | None] = {}
    cams: list[Camera] = []
    problems = []
    icfg = IntrinsicsConfig(model=cfg.model, max_frames=cfg.intrinsic_frames, min_frames=cfg.min_frames)
    for k, (name, d) in enumerate(dets.items()):
        if name in given:
            g = given[name]
            if tuple(g.size_wh) != tuple(d.size_wh):
                problems.append(
                    f"Camera '{name}': --intrinsics gives {g.size_wh} but the recording is {d.size_wh}."
                )
                continue
            intr[name] = None
            cams.append(g.replace(R=np.eye(3), t=np.zeros(3)))
        else:
            try:
                r = calibrate_intrinsics(board, d, icfg)
            except CalibrationError as e:
                problems.append(str(e))
                continue
            intr[name] = r
            cams.append(r.camera())
        if progress is not None:
            progress("intrinsics", k + 1, len(dets))
    if problems:
        ok = [c.name for c in cams]
        raise CalibrationError(
            "\n".join(problems)
            + (
                f"\n(Cameras {ok} are fine; their detections are cached. To calibrate without the others, "
                f"pass --exclude {' '.join(n for n in dets if n not in ok)}.)"
                if ok
                else ""
            )
        )
    return intr, cams


def _extrinsics(
    board: Board, cams: list[Camera], dets: dict, cfg: CalibrationConfig, progress: Progress | None
) -> tuple[ExtrinsicsResult | None, CameraRig]:
    """The bundle-adjusted rig of two or more cameras (and the extrinsics result), or the one camera."""
    ext = None
    if len(cams) >= 2:
        ecfg = ExtrinsicsConfig(
            loss=cfg.loss,
            refine_intrinsics=cfg.refine_intrinsics,
            max_frames=cfg.extrinsic_frames,
            world=cfg.world,
        )
        ext = calibrate_extrinsics(board, cams, dets, ecfg, progress=_stage(progress, "bundle adjustment"))
        rig = ext.rig
    else:
        rig = CameraRig(tuple(cams))
    return ext, rig
