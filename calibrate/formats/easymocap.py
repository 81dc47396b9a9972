"""EasyMocap / OpenCV FileStorage ``intri.yml`` + ``extri.yml``: reader and writer (the conventions:
:mod:`roomcap.calibrate.formats`)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from roomcap.calibrate.camera import (
    CameraRig,
    rotation_from_rvec,
)
from roomcap.calibrate.formats._common import (
    ImportOptions,
    _camera,
    _check_size_names,
    _nonempty,
    pad_dist,
)
from roomcap.core.errors import FormatError
from roomcap.core.fileio import atomic_path

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------- EasyMocap / OpenCV YAML


def _easymocap_paths(path: Path) -> tuple[Path, Path]:
    folder = path if path.is_dir() else path.parent
    intri, extri = folder / "intri.yml", folder / "extri.yml"
    if not path.is_dir() and "extri" not in path.name and "intri" not in path.name:
        raise FormatError(
            path,
            None,
            "an OpenCV YAML calibration must be named intri.yml or extri.yml.",
            "Pass the folder holding intri.yml and extri.yml.",
        )
    for p in (intri, extri):
        if not p.exists():
            raise FormatError(
                p,
                None,
                "file does not exist (EasyMocap calibrations are intri.yml + extri.yml in one folder).",
                "Put both files in the same folder.",
            )
    return intri, extri


def _fs_open(path: Path):
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise FormatError(
            path, None, f"cannot be read by OpenCV FileStorage ({e}).", "Check that the file is complete."
        ) from None
    if not fs.isOpened():
        raise FormatError(path, None, "cannot be opened by OpenCV FileStorage.", "")
    return fs


def _fs_names(fs, path: Path) -> list[str]:
    node = fs.getNode("names")
    if node.empty():
        raise FormatError(path, "names", "is missing.", "EasyMocap files list the cameras under 'names'.")
    return [node.at(i).string() for i in range(node.size())]


def _fs_mat(fs, key: str, path: Path, required: bool = True) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty():
        if required:
            raise FormatError(path, key, "is missing.", "Every camera in 'names' needs this entry.")
        return None
    if node.isInt() or node.isReal():
        return np.array(node.real())
    m = node.mat()
    if m is None:
        raise FormatError(path, key, "is not an OpenCV matrix.", "")
    return np.asarray(m, dtype=np.float64)


def read_easymocap(path: Path, opts: ImportOptions | None = None) -> CameraRig:
    """EasyMocap / OpenCV FileStorage ``intri.yml`` + ``extri.yml`` (cam_from_world, metres)."""
    opts = opts or ImportOptions()
    intri, extri = _easymocap_paths(path)
    fi, fe = _fs_open(intri), _fs_open(extri)
    try:
        names = _fs_names(fi, intri)
        missing = [n for n in names if n not in _fs_names(fe, extri)]
        if missing:
            raise FormatError(
                extri,
                "names",
                f"cameras {missing} of intri.yml are missing.",
                "Write the extrinsics of every camera.",
            )
        cams = []
        for n in names:
            K = _fs_mat(fi, f"K_{n}", intri)
            dist = _fs_mat(fi, f"dist_{n}", intri, required=False)
            if dist is None:
                dist = _fs_mat(fi, f"D_{n}", intri)
            H, W = _fs_mat(fi, f"H_{n}", intri, False), _fs_mat(fi, f"W_{n}", intri, False)
            if H is not None and W is not None:
                size = (int(W.item()), int(H.item()))
            elif opts.size_for(n) is not None:
                size = opts.size_for(n)
            else:
                size = (int(round(2 * K[0, 2])), int(round(2 * K[1, 2])))
                log.warning(
                    "%s: no H_%s/W_%s; image size taken as twice the principal point %s "
                    "(give image_size_wh to set it)",
                    intri,
                    n,
                    n,
                    size,
                )
            Rm = _fs_mat(fe, f"Rot_{n}", extri, required=False)
            if Rm is None:
                rv = _fs_mat(fe, f"R_{n}", extri)
                if rv.size == 9:
                    Rm = rv.reshape(3, 3)
                elif rv.size == 3:
                    Rm = rotation_from_rvec(rv.reshape(3))
                else:
                    raise FormatError(extri, f"R_{n}", f"has {rv.size} values; expected a Rodrigues 3x1.", "")
            T = _fs_mat(fe, f"T_{n}", extri)
            if T.size != 3:
                raise FormatError(extri, f"T_{n}", f"has {T.size} values; expected 3.", "")
            cams.append(
                _camera(
                    extri,
                    n,
                    {"K": f"K_{n}", "dist": f"dist_{n}", "R": f"Rot_{n}", "t": f"T_{n}"},
                    name=n,
                    size_wh=size,
                    K=K,
                    dist=pad_dist(dist),
                    model="pinhole",
                    R=Rm.reshape(3, 3),
                    t=T.reshape(3) * opts.scale_to_m,
                )
            )
    finally:
        fi.release()
        fe.release()
    _check_size_names(opts, cams, intri)
    return _nonempty(cams, intri, "'names' is empty")


def write_easymocap(rig: CameraRig, folder: str | os.PathLike) -> list[Path]:
    """Write ``folder/intri.yml`` and ``folder/extri.yml`` (OpenCV FileStorage, as EasyMocap does).

    Both are written to temporary files first and renamed only when both succeeded."""
    import cv2

    folder = Path(folder)
    if folder.suffix in (".yml", ".yaml"):
        folder = folder.parent
    bad = [c.name for c in rig if c.model != "pinhole"]
    if bad:
        raise ValueError(f"EasyMocap YAML has no fisheye model; cameras {bad} are fisheye")
    folder.mkdir(parents=True, exist_ok=True)
    targets = [folder / "intri.yml", folder / "extri.yml"]
    with atomic_path(targets[0]) as ti, atomic_path(targets[1]) as te:
        fi = cv2.FileStorage(str(ti), cv2.FILE_STORAGE_WRITE)
        fe = cv2.FileStorage(str(te), cv2.FILE_STORAGE_WRITE)
        for fs in (fi, fe):
            fs.startWriteStruct("names", cv2.FileNode_SEQ)
            for c in rig:
                fs.write("", c.name)
            fs.endWriteStruct()
        for c in rig:
            fi.write(f"K_{c.name}", c.K)
            fi.write(f"dist_{c.name}", (c.dist if c.dist.size else np.zeros(5)).reshape(1, -1))
            fi.write(f"H_{c.name}", int(c.size_wh[1]))
            fi.write(f"W_{c.name}", int(c.size_wh[0]))
            fe.write(f"R_{c.name}", c.rvec.reshape(3, 1))
            fe.write(f"Rot_{c.name}", c.R)
            fe.write(f"T_{c.name}", c.t.reshape(3, 1))
        fi.release()
        fe.release()
    return targets
