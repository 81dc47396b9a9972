"""The triangulate stage on a session folder.

``triangulate_session(session)`` reads ``calib/rig.toml`` and ``keypoints/<cam>.npz`` (any
detector, any skeleton :mod:`roomcap.keypoints.skeletons` can convert to ``body19``, or ``whole_body``
or a skeleton TOML with the option ``skeleton``) and writes
``triangulate/poses3d.npz`` (or its parts, CONTRACTS.md); the greedy track stage that reads it is
:func:`roomcap.track.greedy_stage.track_session_greedy`. It accepts a typed config, a plain dict (unknown
keys are rejected with the list of valid ones) or None for the defaults.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from contextlib import closing
from dataclasses import replace
from pathlib import Path

import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.calibrate.checks import rig_warnings
from roomcap.capture.session import SessionLayout, require
from roomcap.core.config import as_config
from roomcap.core.errors import FormatError
from roomcap.core.progress import Progress
from roomcap.triangulate.checks import no_detection_warning
from roomcap.triangulate.chunks import (
    ChunkRunner,
    PartStore,
    StreamConfig,
    file_stamp,
    hash_key,
    parts_dir,
    remove_output,
)
from roomcap.triangulate.multiview import (
    MultiViewDetections,
    load_detections,
    plan_detections,
    session_chunk_s,
    session_fps,
)
from roomcap.triangulate.poses3d import Poses3D
from roomcap.triangulate.reconstruct import FrameReconstructor, TriangulateConfig

log = logging.getLogger(__name__)


def _reconstructor(rig: CameraRig, cameras: tuple[str, ...], joint_names, config: TriangulateConfig):
    order = None
    if config.match.camera_order is not None:
        bad = [c for c in config.match.camera_order if c not in cameras]
        if bad:
            raise ValueError(
                f"match.camera_order names cameras {bad} that have no detections; cameras: {list(cameras)}"
            )
        order = np.asarray([cameras.index(c) for c in config.match.camera_order])
    return FrameReconstructor(
        rig.projection_matrices(), rig.fundamental_matrices(), config, order, joint_names
    )


def reconstruct_all(
    rig: CameraRig,
    mv: MultiViewDetections | Iterable[MultiViewDetections],
    config: TriangulateConfig,
    progress: Progress | None = None,
    rec: FrameReconstructor | None = None,
    done: int = 0,
    total: int | None = None,
) -> dict[str, np.ndarray]:
    """Run association + triangulation on every frame of ``mv`` (or of consecutive blocks of frames, read
    one at a time). Returns padded (T,P3,J,...) arrays."""
    blocks = [mv] if isinstance(mv, MultiViewDetections) else mv
    out: list = []
    cameras, J = (), 0
    for b in blocks:
        cameras, J = b.cameras, len(b.joint_names)
        rec = rec or _reconstructor(rig, b.cameras, b.joint_names, config)
        for t in range(len(b.frame_index)):
            out.append(rec(b.xy_px[:, t], b.score[:, t]))
            if progress is not None:
                progress("triangulate", done + len(out), total or len(b.frame_index))
    T = len(out)
    P3 = max([len(f.xyz_m) for f in out], default=0)
    res = {
        "xyz_m": np.full((T, P3, J, 3), np.nan),
        "score": np.zeros((T, P3, J)),
        "reproj_err_px": np.full((T, P3, J), np.nan),
        "n_views": np.zeros((T, P3, J), np.int16),
        "std_m": np.full((T, P3, J), np.nan),
        "reproj_err_cam_px": np.full((T, P3, J, len(cameras)), np.nan),
    }
    for t, f in enumerate(out):
        m = len(f.xyz_m)
        for k in res:
            res[k][t, :m] = getattr(f, k)
        out[t] = None  # each frame's arrays are freed once copied
    return res


def _people_log(xyz_m: np.ndarray) -> np.ndarray:
    return np.isfinite(xyz_m).all(-1).any(-1).sum(1)


def _nobody_warning(n_frames: int, n_cams: int) -> None:
    log.warning(
        "nobody was triangulated in %d frames of %d cameras: check that the calibration belongs to "
        "these cameras and is in metres (calibrate-run import --scale-to-m), and that the detections "
        "are of this recording",
        n_frames,
        n_cams,
    )


def triangulate_session(
    session_dir: str | os.PathLike,
    config: TriangulateConfig | dict | None = None,
    progress: Progress | None = None,
    executor: ChunkRunner | None = None,
) -> Path:
    """Association (Alg. 1) + robust DLT for every frame of a session; writes ``triangulate/poses3d.npz``
    (streamed: ``triangulate/poses3d.parts/``, resumable; ``Poses3D.load`` of ``poses3d.npz`` reads
    either). ``executor`` runs the chunks ``config.stream.workers`` at a time
    (``pipeline.executors.chunk_runner``: processes or Ray); without one they run in this process."""
    cfg = as_config(TriangulateConfig, config)
    lay = SessionLayout(session_dir)
    rig_path = require(
        lay.rig_toml, "the calibration calib/rig.toml", "Calibrate the rig or import a calibration."
    )
    rig = CameraRig.load(rig_path)
    if len(rig) < 2:
        raise FormatError(
            rig_path,
            "cameras",
            f"triangulation needs at least 2 cameras, the rig has {len(rig)}.",
            "Calibrate at least two cameras.",
        )
    for w in rig_warnings(rig, str(rig_path)):
        log.warning("%s", w)
    cfg = replace(cfg, stream=replace(cfg.stream, chunk_s=session_chunk_s(lay, cfg.stream)))
    if cfg.stream.chunk_s > 0:
        return _triangulate_chunked(lay, rig, cfg, progress, executor)
    sub, mv = load_detections(lay, rig, skeleton=cfg.skeleton)
    res = reconstruct_all(sub, mv, cfg, progress)
    poses = _poses3d(
        res,
        session_fps(lay, mv.t_ns),
        rig,
        sub.names,
        frame_index=mv.frame_index,
        t_ns=mv.t_ns,
        joint_names=mv.joint_names,
        parents=mv.parents,
    )
    remove_output(lay.poses3d)
    poses.save(lay.poses3d)
    n = _people_log(res["xyz_m"])
    log.info(
        "triangulated %d frames from %d cameras: %.2f people per frame (max %d)",
        len(n),
        len(sub),
        float(n.mean()) if len(n) else 0.0,
        int(n.max()) if len(n) else 0,
    )
    if len(n) and n.max() == 0:
        _nobody_warning(len(n), len(sub))
    return lay.poses3d


def _poses3d(
    res: dict, fps: float, rig: CameraRig, cameras, *, frame_index, t_ns, joint_names, parents
) -> Poses3D:
    """The per-frame poses of frames ``frame_index`` from ``reconstruct_all``'s arrays ``res``."""
    return Poses3D(
        fps=fps,
        frame_index=frame_index,
        t_ns=t_ns,
        joint_names=joint_names,
        parents=np.asarray(parents),
        calibration_sha256=rig.sha256(),
        cameras=tuple(cameras),
        **res,
    )


def _triangulate_chunked(
    lay: SessionLayout,
    rig: CameraRig,
    cfg: TriangulateConfig,
    progress: Progress | None,
    executor: ChunkRunner | None,
) -> Path:
    """The streaming form: one poses3d part per ``cfg.stream.chunk_s`` of frames, resumable."""
    plan = plan_detections(lay, rig, skeleton=cfg.skeleton, stream=True)
    try:
        fps = session_fps(lay, plan.t_ns)
        step = max(int(round(cfg.stream.chunk_s * fps)), 1)
        T = plan.n_frames
        chunks = [(a, min(a + step, T)) for a in range(0, T, step)] or [(0, 0)]
        key = hash_key(
            [
                "poses3d",
                repr(_without_run_settings(cfg)),  # the result depends on neither the processes nor Ray
                rig.sha256(),
                [file_stamp(m.path) for m in plan.metas],
                lay.session_toml.read_bytes() if lay.session_toml.exists() else b"",
            ]
        )
        if lay.poses3d.exists():
            lay.poses3d.unlink()
        store = PartStore(parts_dir(lay.poses3d), "poses3d")
        todo = set(store.open(key, chunks, {"fps": fps, "n_frames": T}))
        if len(todo) < len(chunks):
            log.info(
                "triangulate: resuming, %d of %d chunks already done", len(chunks) - len(todo), len(chunks)
            )
        n_sum, n_max, n_frames = 0, 0, 0
        # closing: a kill (Ctrl-C) between parts stops the workers now (queued chunks cancelled, a Ray
        # started here shut down), not when the generator is collected
        parts = _triangulate_chunks(lay, plan, rig, cfg, chunks, todo, store, fps, key, progress, executor)
        with closing(parts):
            for i, n in parts:
                store.commit(i)
                n_sum, n_max, n_frames = (
                    n_sum + int(n.sum()),
                    max(n_max, int(n.max(initial=0))),
                    n_frames + len(n),
                )
        store.finish()
        for m in plan.metas:
            if not m.seen and len(todo) == len(chunks):
                log.warning("%s", no_detection_warning(m.camera, m.n_frames))
        log.info(
            "triangulated %d frames (%d new) from %d cameras in %d chunks: %.2f people per frame (max %d)",
            T,
            n_frames,
            len(plan.cameras),
            len(chunks),
            n_sum / max(n_frames, 1),
            n_max,
        )
        if n_frames and n_max == 0 and len(todo) == len(chunks):
            _nobody_warning(n_frames, len(plan.cameras))
    finally:
        plan.close()
    return lay.poses3d


def _without_run_settings(cfg: TriangulateConfig) -> TriangulateConfig:
    """``cfg`` with ``workers`` and ``executor`` at their defaults: how the chunks ran, not what they are."""
    return replace(cfg, stream=StreamConfig(chunk_s=cfg.stream.chunk_s))


def _triangulate_chunks(lay, plan, rig, cfg, chunks, todo, store, fps, key, progress, executor):
    """Triangulate the chunks ``todo`` into their part files; yields (chunk, people per frame) as each is
    written: in this process, or with ``executor`` (worker processes or Ray tasks, each worker planning
    the session once, ``_chunk_worker``)."""
    T = plan.n_frames
    for i, (_, b) in enumerate(chunks):
        if i not in todo and progress is not None:
            progress("triangulate", b, T)
    if len(todo) <= 1 or executor is None:
        rec = _reconstructor(plan.rig, plan.cameras, plan.skel.joint_names, cfg)
        for i in sorted(todo):
            yield i, _triangulate_chunk(plan, rig, cfg, rec, chunks[i], fps, store.part_path(i), progress)
        return
    jobs = {i: (str(lay.root), cfg, chunks[i], fps, str(store.part_path(i)), key) for i in sorted(todo)}
    done = sum(b - a for i, (a, b) in enumerate(chunks) if i not in todo)
    with closing(executor(_chunk_worker, jobs, cfg.stream.workers)) as results:
        for i, (n, seen) in results:
            for m, s in zip(plan.metas, seen, strict=True):  # for the "camera without detections" check
                m.seen = m.seen or s
            done += chunks[i][1] - chunks[i][0]
            if progress is not None:
                progress("triangulate", done, T)
            yield i, n


BLOCK_FRAMES = 250  # frames of detections read at a time within a chunk


def _triangulate_chunk(plan, rig, cfg, rec, chunk, fps: float, part: Path, progress=None) -> np.ndarray:
    """Frames [a, b) of the plan triangulated into the part file ``part``; returns the people per frame."""
    a, b = chunk
    # the detections are read in blocks of BLOCK_FRAMES: their padded arrays (cameras x frames x the
    # session's most people x joints) would otherwise be most of the stage's memory
    blocks = (plan.chunk(f, min(f + BLOCK_FRAMES, b)) for f in range(a, max(b, a + 1), BLOCK_FRAMES))
    res = reconstruct_all(plan.rig, blocks, cfg, progress, rec, done=a, total=plan.n_frames)
    skel = plan.skel
    _poses3d(
        res,
        fps,
        rig,
        plan.cameras,
        frame_index=plan.frames[a:b],
        t_ns=plan.t_ns[a:b],
        joint_names=skel.joint_names,
        parents=skel.parents,
    ).save(part)
    return _people_log(res["xyz_m"])


_WORKER_PLAN: dict = {}  # per worker process: the session's detection plan and reconstructor


def _chunk_worker(
    session_dir: str, cfg: TriangulateConfig, chunk, fps: float, part: str, key: str = ""
) -> tuple[np.ndarray, list[bool]]:
    """One chunk in a worker process: triangulate frames [a, b) and write its part; returns the people
    per frame and, per camera, whether it has had a detection in this process.

    The plan is kept for the next chunk of the same run (``key``: the parts' key, which changes with the
    detection files, the rig and the settings); a Ray worker outlives the run, so another run or changed
    files plan anew (the old files closed)."""
    run = (session_dir, key, repr(cfg))
    if _WORKER_PLAN.get("key") != run:
        if "plan" in _WORKER_PLAN:
            _WORKER_PLAN.pop("plan").close()
        _WORKER_PLAN.clear()
        lay = SessionLayout(session_dir)
        rig = CameraRig.load(lay.rig_toml)
        plan = plan_detections(lay, rig, skeleton=cfg.skeleton, stream=True)
        rec = _reconstructor(plan.rig, plan.cameras, plan.skel.joint_names, cfg)
        _WORKER_PLAN.update(key=run, rig=rig, plan=plan, rec=rec)
    plan = _WORKER_PLAN["plan"]
    n = _triangulate_chunk(plan, _WORKER_PLAN["rig"], cfg, _WORKER_PLAN["rec"], chunk, fps, Path(part))
    return n, [m.seen for m in plan.metas]
