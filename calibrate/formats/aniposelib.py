"""aniposelib / Pose2Sim ``Calib*.toml``: reader and writer (the conventions:
:mod:`roomcap.calibrate.formats`)."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.calibrate.camera import (
    CameraRig,
    rotation_from_rvec,
)
from roomcap.calibrate.formats._common import (
    ImportOptions,
    _array,
    _camera,
    _load_toml,
    _need,
    _nonempty,
    _size,
    pad_dist,
)
from roomcap.core.errors import FormatError
from roomcap.core.fileio import save_toml

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------- aniposelib / Pose2Sim

_ANIPOSE_NAMES = {
    "K": "matrix",
    "dist": "distortions",
    "R": "rotation",
    "t": "translation",
    "size_wh": "size",
    "model": "fisheye",
}


def read_aniposelib(path: Path, opts: ImportOptions | None = None) -> CameraRig:
    """aniposelib / Pose2Sim TOML: Rodrigues ``rotation`` + ``translation`` = cam_from_world."""
    opts = opts or ImportOptions()
    data = _load_toml(path)
    cams = []
    for key, tab in data.items():
        if key == "metadata" or not isinstance(tab, Mapping):
            continue
        where = f"[{key}]"
        fix = "Every camera table needs name, size, matrix, distortions, rotation and translation."
        K = _array(_need(tab, "matrix", path, where, fix), (3, 3), path, f"{where}.matrix")
        size = _size(_need(tab, "size", path, where, fix), path, f"{where}.size")
        rot = np.array(_need(tab, "rotation", path, where, fix), dtype=np.float64)
        if rot.shape == (3, 3):
            R = rot
        elif rot.size == 3:
            R = rotation_from_rvec(rot.reshape(3))
        else:
            raise FormatError(
                path,
                f"{where}.rotation",
                f"has shape {rot.shape}; expected a Rodrigues vector (3,) or a 3x3 matrix.",
                "Write the cam_from_world rotation.",
            )
        t = (
            _array(_need(tab, "translation", path, where, fix), (3,), path, f"{where}.translation")
            * opts.scale_to_m
        )
        fisheye = bool(tab.get("fisheye", False))
        dist = np.asarray(tab.get("distortions", []), dtype=np.float64).reshape(-1)
        if not fisheye:
            dist = pad_dist(dist)
        cams.append(
            _camera(
                path,
                where,
                _ANIPOSE_NAMES,
                name=str(tab.get("name", key)),
                size_wh=size,
                K=K,
                dist=dist,
                model="fisheye" if fisheye else "pinhole",
                R=R,
                t=t,
            )
        )
    return _nonempty(cams, path, "no tables with a camera matrix")


def write_aniposelib(rig: CameraRig, path: str | os.PathLike) -> None:
    """aniposelib TOML (Pose2Sim reads it too). Keys ``cam_0..`` are zero-padded so that aniposelib,
    which sorts the keys, keeps the rig's order."""
    width = len(str(max(len(rig) - 1, 0)))
    out: dict[str, Any] = {}
    for i, c in enumerate(rig):
        out[f"cam_{i:0{width}d}"] = {
            "name": c.name,
            "size": [int(c.size_wh[0]), int(c.size_wh[1])],
            "matrix": c.K.tolist(),
            "distortions": c.dist.tolist() if c.dist.size else [0.0, 0.0, 0.0, 0.0, 0.0],
            "rotation": c.rvec.tolist(),
            "translation": c.t.tolist(),
            "fisheye": c.model == "fisheye",
        }
    out["metadata"] = {"adjusted": False, "error": 0.0}
    save_toml(
        path,
        out,
        header="aniposelib / Pose2Sim calibration written by roomcap.\n"
        "rotation = Rodrigues vector and translation (metres) of cam_from_world: x_cam = R x_world + t.",
    )
