"""Importers and exporters between ``rig.toml`` and the calibration formats users arrive with.

Every reader returns a ``CameraRig`` in this project's convention (``calibrate.camera.CONVENTION``:
cam_from_world, metres, OpenCV pixels). What each source format means, and how it is converted:

``aniposelib`` (also Pose2Sim's ``Calib*.toml``)
    One table per camera (``[cam_0]``, ``[cam_1]``, ... or any name; ``[metadata]`` is skipped) with
    ``name``, ``size = [width, height]``, ``matrix`` (3x3 K), ``distortions`` (OpenCV order),
    ``rotation`` (Rodrigues vector of cam_from_world; a 3x3 matrix is accepted too), ``translation``
    (cam_from_world, in the unit of the calibration board: metres for Pose2Sim, whatever unit the
    board was given in for aniposelib -- pass ``scale_to_m`` e.g. 0.001 for millimetres), and
    ``fisheye = true`` for cv2.fisheye cameras (Pose2Sim writes the flag). Cameras keep file order.
``qualisys`` (``.qca.txt``, XML written by QTM)
    Per ``<camera>``: ``<transform>`` holds the camera *position* ``x, y, z`` in millimetres and a
    rotation ``r11..r33`` whose rows are the camera's axes in world coordinates, in Qualisys'
    camera frame (x right, y up, looking along -z). So ``R = diag(1,-1,-1) @ M`` (flip to OpenCV's
    y down, z forward -- Pose2Sim's ``rotate_cam(ang_x=pi)``) and ``t = -R @ position / 1000``.
    ``<intrinsic>`` gives focal lengths and principal point in *sub-pixel units* (1/64 px) of the
    full sensor; the principal point is shifted by the ``fov_video`` ``left``/``top`` offsets; the
    image size is ``right - left + 1`` by ``bottom - top + 1`` (1088 x 1920 in Pose2Sim's demo while
    some of its videos are 1080 wide: see ``ImportOptions.image_size_wh``). Distortion
    ``radialDistortion1..3``, ``tangentalDistortion1..2`` -> OpenCV ``(k1, k2, p1, p2, k3)``. They
    are dimensionless; Pose2Sim divides them by 64 as well (``distortion_scale = 1/64`` reproduces
    Pose2Sim exactly; on the demo the two differ by < 0.3 px in reprojection). ``viewrotation``
    (0/90/180/270, clockwise) says how QTM rotates the video for display; the calibration is in the
    sensor's orientation. By default it is kept so (as Pose2Sim does); ``view_rotation="apply"``
    rotates the camera so that it matches videos rotated for display. Only video cameras
    (``model`` containing "video", or "none") are imported unless ``include_marker_cameras``.
``caliscope`` (``camera_array.toml`` with ``[cameras.N]``, or the older ``config.toml`` with
    ``[cam_N]`` and ``port``)
    ``size``, ``matrix``, ``distortions`` (OpenCV order), ``rotation`` (3x3 cam_from_world) and
    ``translation`` (cam_from_world, metres). Names are ``cam_<id>``. ``rotation_count`` only turns
    the preview; calibration and caliscope's 2D points are in the unrotated sensor image.
    Cameras with ``ignore = true`` are skipped.
``easymocap`` (OpenCV FileStorage ``intri.yml`` + ``extri.yml``, as EasyMocap writes them)
    ``names``; per camera ``K_<name>``, ``dist_<name>`` (or ``D_<name>``; OpenCV order; all
    coefficients kept -- Pose2Sim drops the last one), optional ``H_<name>``/``W_<name>`` (image
    size); ``Rot_<name>`` (3x3) or ``R_<name>`` (Rodrigues) and ``T_<name>`` (3x1), cam_from_world,
    metres. Without ``H_``/``W_`` the size comes from ``image_size_wh`` or else is taken as twice
    the principal point (logged).
``rig``
    This project's own ``rig.toml``.

Exporters: ``aniposelib`` (readable by aniposelib and Pose2Sim), ``easymocap`` and ``rig``.
Every write is atomic; a failed import writes nothing.

Modules: one per format (``aniposelib``, ``qualisys``, ``caliscope``, ``easymocap``) and ``_common`` (the
options and the value checks they share); every public name is importable from ``calibrate.formats``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.calibrate.formats._common import (
    EXPORT_FORMATS,
    IMPORT_FORMATS,
    ImportOptions,
    _load_toml,
    pad_dist,
)
from roomcap.calibrate.formats.aniposelib import read_aniposelib, write_aniposelib
from roomcap.calibrate.formats.caliscope import read_caliscope
from roomcap.calibrate.formats.easymocap import read_easymocap, write_easymocap
from roomcap.calibrate.formats.qualisys import _rotate_image_cw as _rotate_image_cw  # the tests use it
from roomcap.calibrate.formats.qualisys import read_qualisys
from roomcap.core.errors import FormatError, InputError

__all__ = [
    "EXPORT_FORMATS",
    "IMPORT_FORMATS",
    "ImportOptions",
    "detect_format",
    "export_rig",
    "import_calibration",
    "import_rig",
    "pad_dist",
    "read_aniposelib",
    "read_caliscope",
    "read_easymocap",
    "read_qualisys",
    "write_aniposelib",
    "write_easymocap",
]

# ----------------------------------------------------------------------------- detection


def detect_format(path: str | os.PathLike) -> str:
    """Guess the format of a calibration file (or an EasyMocap folder) from its name and content."""
    p = Path(path)
    if p.is_dir():
        if (p / "intri.yml").exists() or (p / "extri.yml").exists():
            return "easymocap"
        raise FormatError(
            p,
            None,
            "is a folder without intri.yml/extri.yml.",
            "Pass the calibration file itself, or give --format.",
        )
    if not p.exists():
        raise FormatError(p, None, "file does not exist.")
    name = p.name.lower()
    if name.endswith((".qca.txt", ".qca")):
        return "qualisys"
    if p.suffix.lower() in (".yml", ".yaml"):
        return "easymocap"
    head = p.read_bytes()[:4096].lstrip()
    if head.startswith(b"<?xml") or head.startswith(b"<calibration"):
        if b"<calibration" in head:
            return "qualisys"
        return "easymocap"  # OpenCV FileStorage XML
    if head.startswith(b"%YAML"):
        return "easymocap"
    data = _load_toml(p)
    if isinstance(data.get("schema"), str) and data["schema"].startswith("rig/"):
        return "rig"
    if isinstance(data.get("cameras"), Mapping):
        return "caliscope"
    tables = {k: v for k, v in data.items() if isinstance(v, Mapping) and "matrix" in v}
    if not tables:
        raise FormatError(
            p,
            None,
            "is TOML but no camera tables (with a 'matrix') were found.",
            f"Give --format (one of {list(IMPORT_FORMATS)}).",
        )
    first = next(iter(tables.values()))
    if "port" in first or np.shape(first.get("rotation")) == (3, 3):
        return "caliscope"
    return "aniposelib"


def import_rig(
    path: str | os.PathLike, fmt: str | None = None, options: ImportOptions | None = None
) -> CameraRig:
    """Read a calibration in ``fmt`` (detected when None) into a CameraRig."""
    opts = options or ImportOptions()
    fmt = fmt or detect_format(path)
    readers = {
        "aniposelib": read_aniposelib,
        "qualisys": read_qualisys,
        "caliscope": read_caliscope,
        "easymocap": read_easymocap,
        "rig": lambda p, o: CameraRig.load(p),
    }
    if fmt not in readers:
        raise InputError(f"unknown calibration format {fmt!r}; valid: {list(IMPORT_FORMATS)}")
    return readers[fmt](Path(path), opts)


def import_calibration(
    path: str | os.PathLike, fmt: str | None = None, options: ImportOptions | None = None
) -> CameraRig:
    """Alias of ``import_rig`` (the name ``pipeline.runner`` uses)."""
    return import_rig(path, fmt, options)


def export_rig(rig: CameraRig, path: str | os.PathLike, fmt: str) -> list[Path]:
    """Write ``rig`` in ``fmt``; returns the files written (EasyMocap: ``path`` is a folder)."""
    p = Path(path)
    if fmt == "aniposelib":
        write_aniposelib(rig, p)
        return [p]
    if fmt == "easymocap":
        return write_easymocap(rig, p)
    if fmt == "rig":
        rig.save(p)
        return [p]
    raise InputError(f"unknown export format {fmt!r}; valid: {list(EXPORT_FORMATS)}")
