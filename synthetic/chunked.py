"""Long synthetic sessions in bounded memory: rendered in time chunks, written as stream.

:func:`write_session_chunked` renders the scene chunk by chunk (each chunk and camera seeded by its
own generator, so a chunked session is a different random draw from
:func:`roomcap.synthetic.world.write_session`'s
but the same files: ``keypoints/<cam>.npz`` detections/1, ``gt.npz`` synthetic_gt/1). Each chunk's
arrays go to a scratch folder, then every output npz is assembled member by member with the rows
streamed from the scratch files (people slots padded to the widest chunk), so memory is one chunk's.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import SessionLayout
from roomcap.core.fileio import atomic_path, schema_tag
from roomcap.synthetic import render as R
from roomcap.synthetic.world import GT_SCHEMA, GT_VERSION, Scene, write_session_toml


class _Member:
    """A member of the npz being assembled: rows from a list of scratch .npy files, padded on axis 1."""

    def __init__(self, files: list[Path], width: int | None, fill, shape_tail=None, dtype=None) -> None:
        self.files, self.width, self.fill = files, width, fill
        heads = [np.load(f, mmap_mode="r") for f in files]
        self.dtype = np.dtype(dtype or heads[0].dtype)
        T = sum(h.shape[0] for h in heads)
        tail = list(heads[0].shape[1:]) if shape_tail is None else list(shape_tail)
        if width is not None:
            tail[0] = width
        self.shape = (T, *tail)

    def write(self, f) -> None:
        np.lib.format.write_array_header_2_0(
            f,
            {"descr": np.lib.format.dtype_to_descr(self.dtype), "fortran_order": False, "shape": self.shape},
        )
        for p in self.files:
            a = np.load(p, mmap_mode="r")
            if self.width is not None and a.shape[1] < self.width:
                pad = [(0, 0), (0, self.width - a.shape[1])] + [(0, 0)] * (a.ndim - 2)
                a = np.pad(a, pad, constant_values=self.fill)
            f.write(np.ascontiguousarray(a, self.dtype).tobytes())


def _write_npz_stream(path: Path, members: dict[str, np.ndarray | _Member]) -> None:
    """An npz written member by member to disk (deflated, fixed stamps as ``save_npz``), atomically."""
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for key, m in members.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                if isinstance(m, _Member):
                    m.write(f)
                else:
                    np.lib.format.write_array(f, np.asarray(m), allow_pickle=False)


def _slice_scene(scene: Scene, a: int, b: int) -> Scene:
    return dataclasses.replace(scene, gt_xyz_m=scene.gt_xyz_m[a:b])


def write_session_chunked(
    scene: Scene, rig: CameraRig, cfg: R.RenderConfig, root: str | os.PathLike, chunk_s: float = 60.0
) -> SessionLayout:
    """Render ``scene`` in chunks of ``chunk_s`` seconds and write the session folder (see module doc).

    Camera time offsets and drifts need the whole time axis: they are refused here."""
    if cfg.time_offset_std_frames or cfg.time_drift_std_ppm:
        raise ValueError("chunked rendering does not model camera time offsets or drifts; use chunk_s = 0")
    lay = SessionLayout(root)
    lay.calib_dir.mkdir(parents=True, exist_ok=True)
    lay.keypoints_dir.mkdir(parents=True, exist_ok=True)
    scratch = lay.root / ".synthetic_chunks"
    if scratch.exists():
        shutil.rmtree(scratch)
    scratch.mkdir()
    T, C = scene.n_frames, len(rig)
    step = max(int(round(chunk_s * scene.fps)), 1)
    chunks = [(a, min(a + step, T)) for a in range(0, T, step)]
    names = ("xy_px", "score", "boxes", "gt_index")
    files: dict[tuple[int, str], list[Path]] = {(c, n): [] for c in range(C) for n in names}
    vis_files: list[Path] = []
    width = [0] * C
    for i, (a, b) in enumerate(chunks):
        sub = _slice_scene(scene, a, b)
        vis = []
        for c in range(C):
            crng = np.random.default_rng([cfg.seed, int(scene.config.seed), c + 1, i])
            det, gi, v, _ = R.render_camera(sub, rig, c, cfg, 0.0, 0.0, crng)
            width[c] = max(width[c], det.max_people)
            for n, arr in zip(names, (det.xy_px, det.score, det.boxes, gi), strict=True):
                p = scratch / f"c{c}_{n}_{i:05d}.npy"
                np.save(p, arr)
                files[(c, n)].append(p)
            vis.append(v)
        p = scratch / f"visible_{i:05d}.npy"
        np.save(p, np.stack(vis, 1))  # (n,C,P,19): time first, for streaming
        vis_files.append(p)
        del vis
    frame_index = np.arange(T)
    t_ns = np.round(np.arange(T) / scene.fps * 1e9).astype(np.int64)
    for c, cam in enumerate(rig.cameras):
        _write_npz_stream(
            lay.detections(cam.name),
            {
                "schema": np.asarray(schema_tag("detections", 1)),
                "camera": np.asarray(cam.name),
                "skeleton": np.asarray(cfg.skeleton),
                "frame_index": frame_index,
                "t_ns": t_ns,
                "xy_px": _Member(files[(c, "xy_px")], width[c], np.nan),
                "score": _Member(files[(c, "score")], width[c], 0.0),
                "boxes": _Member(files[(c, "boxes")], width[c], np.nan),
                "model": np.asarray(cfg.model),
                "model_sha256": np.asarray(""),
                "image_size_wh": np.asarray(cam.size_wh, np.int64),
            },
        )
    rig.save(lay.calib_dir / "rig.toml", source="synthetic")
    write_session_toml(lay, scene, rig, "synthetic.chunked.write_session_chunked")
    gt_members: dict[str, np.ndarray | _Member] = {
        "schema": np.asarray(schema_tag(GT_SCHEMA, GT_VERSION)),
        "gt_xyz_m": scene.gt_xyz_m,
        "person_ids": scene.person_ids,
        "fps": np.float64(scene.fps),
        "clip_names": np.array(scene.clip_names),
        "cameras": np.array(rig.names),
        "time_offsets_frames": np.zeros(C),
        "time_drifts_ppm": np.zeros(C),
        "visible_tcp": _Member(vis_files, None, False),  # (T,C,P,19): ``visible`` with time first
    }
    for c, name in enumerate(rig.names):
        gt_members[f"gt_index_{name}"] = _Member(files[(c, "gt_index")], width[c], -2)
    _write_npz_stream(lay.root / "gt.npz", gt_members)
    shutil.rmtree(scratch)
    return lay
