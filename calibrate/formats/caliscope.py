"""caliscope ``camera_array.toml`` / ``config.toml``: reader (the conventions:
:mod:`roomcap.calibrate.formats`)."""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping
from pathlib import Path

from roomcap.calibrate.camera import (
    CameraRig,
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

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------- caliscope

_CALISCOPE_NAMES = {
    "K": "matrix",
    "dist": "distortions",
    "R": "rotation",
    "t": "translation",
    "size_wh": "size",
}


def read_caliscope(path: Path, opts: ImportOptions | None = None) -> CameraRig:
    """caliscope ``camera_array.toml`` ([cameras.N]) or ``config.toml`` ([cam_N] with ``port``)."""
    opts = opts or ImportOptions()
    data = _load_toml(path)
    if isinstance(data.get("cameras"), Mapping):
        items = [(f"cameras.{k}", v) for k, v in data["cameras"].items()]
    else:
        items = [(k, v) for k, v in data.items() if re.fullmatch(r"cam_\d+", k) and isinstance(v, Mapping)]
    cams = []
    for key, tab in items:
        where = f"[{key}]"
        if tab.get("ignore", False):
            log.info("%s: camera %s has ignore = true; skipped", path, key)
            continue
        cid = tab.get("cam_id", tab.get("port", key.rsplit(".", 1)[-1].removeprefix("cam_")))
        fix = "Run caliscope's extrinsic calibration so every camera has rotation and translation."
        K = _array(_need(tab, "matrix", path, where, fix), (3, 3), path, f"{where}.matrix")
        R = _array(
            _need(tab, "rotation", path, where, fix),
            (3, 3),
            path,
            f"{where}.rotation",
            "caliscope stores the 3x3 cam_from_world rotation matrix.",
        )
        t = _array(_need(tab, "translation", path, where, fix), (3,), path, f"{where}.translation")
        size = _size(_need(tab, "size", path, where, fix), path, f"{where}.size")
        cams.append(
            _camera(
                path,
                where,
                _CALISCOPE_NAMES,
                name=f"cam_{cid}",
                size_wh=size,
                K=K,
                dist=pad_dist(tab.get("distortions", [])),
                model="pinhole",
                R=R,
                t=t * opts.scale_to_m,
            )
        )
    return _nonempty(cams, path, "no [cameras.N] or [cam_N] tables")
