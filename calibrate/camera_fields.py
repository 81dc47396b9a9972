"""The checks of a camera's fields (name, image size, model, K, dist, R, t), shared by
:class:`roomcap.calibrate.camera.Camera` and the calibration importers: each error names the file and the
field."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from roomcap.core.errors import FormatError

PINHOLE_DIST_SIZES = (0, 4, 5, 8, 12, 14)
FISHEYE_DIST_SIZES = (4,)
MODELS = ("pinhole", "fisheye")
ROTATION_TOL = 1e-6


def _check_model(model: Any, path: Any, where: str) -> None:
    """The camera model is one of ``MODELS``."""
    if model not in MODELS:
        raise FormatError(
            path,
            where,
            f"unknown camera model {model!r}; valid: {list(MODELS)}.",
            "Use 'pinhole' (OpenCV 0/4/5/8/12/14 coefficients) or 'fisheye' (cv2.fisheye, 4).",
        )


def _check_size(size_wh: Any, path: Any, where: str) -> tuple[int, ...]:
    """The image size as two positive integers ``(width, height)``."""
    try:
        wh = tuple(int(v) for v in size_wh)
        ok = (
            len(wh) == 2
            and all(v > 0 for v in wh)
            and all(float(a) == b for a, b in zip(size_wh, wh, strict=True))
        )
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise FormatError(
            path,
            where,
            f"must be two positive integers [width, height], got {size_wh!r}.",
            "Write the image size in pixels as [width, height].",
        )
    return wh


def _check_K(K: Any, path: Any, where: str) -> np.ndarray:
    """The OpenCV camera matrix: positive focal lengths, last rows ``[0, fy, cy], [0, 0, 1]``, no skew."""
    K_ = _as_matrix(
        K, (3, 3), path, where, "Write K as the 3x3 OpenCV camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]]."
    )
    if not (K_[0, 0] > 0 and K_[1, 1] > 0):
        raise FormatError(
            path,
            where,
            f"focal lengths must be positive, got fx={K_[0, 0]}, fy={K_[1, 1]}.",
            "Check the camera matrix.",
        )
    if K_[1, 0] != 0 or K_[2, 0] != 0 or K_[2, 1] != 0 or K_[2, 2] != 1:
        raise FormatError(
            path,
            where,
            f"last two rows must be [0, fy, cy] and [0, 0, 1], got {K_[1:].tolist()}.",
            "Normalise K so that K[2,2] = 1.",
        )
    if abs(K_[0, 1]) > 1e-9 * K_[0, 0]:
        raise FormatError(
            path,
            where,
            f"has skew K[0,1]={K_[0, 1]}, which OpenCV's distortion model ignores.",
            "Recalibrate without skew (OpenCV does) or set K[0,1] = 0.",
        )
    K_[0, 1] = 0.0
    return K_


def _check_dist(dist: Any, model: str, path: Any, where: str) -> np.ndarray:
    """The distortion coefficients: finite, as many as the model takes."""
    try:
        dist_ = np.array([] if dist is None else dist, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise FormatError(path, where, f"is not a numeric vector ({e}).", "") from None
    sizes = PINHOLE_DIST_SIZES if model == "pinhole" else FISHEYE_DIST_SIZES
    if dist_.size not in sizes:
        raise FormatError(
            path,
            where,
            f"has {dist_.size} coefficients; a {model} camera takes {list(sizes)}.",
            "Give the OpenCV distortion coefficients in OpenCV order (pad with zeros to a valid length)."
            if model == "pinhole"
            else "Give the 4 cv2.fisheye coefficients k1..k4.",
        )
    if not np.all(np.isfinite(dist_)):
        raise FormatError(path, where, "contains NaN or infinite values.", "")
    return dist_


def _check_R(R: Any, path: Any, where: str) -> np.ndarray:
    """A rotation matrix (orthonormal, determinant 1, within ``ROTATION_TOL``)."""
    R_ = _as_matrix(R, (3, 3), path, where, "Write R as a 3x3 rotation matrix (cam_from_world).")
    err = float(np.abs(R_ @ R_.T - np.eye(3)).max())
    det = float(np.linalg.det(R_))
    if err > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
        raise FormatError(
            path,
            where,
            f"is not a rotation (max |R R^T - I| = {err:.3g}, det = {det:.9g}; tolerance {ROTATION_TOL}).",
            "Write the full-precision cam_from_world rotation; if it is a Rodrigues vector "
            "or the transpose (world_from_cam) or has a reflection, convert it first.",
        )
    return R_


def _as_matrix(value: Any, shape: tuple[int, ...], path: Any, fld: str, fix: str) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise FormatError(path, fld, f"is not a numeric array of shape {shape} ({e}).", fix) from None
    if arr.shape != shape:
        raise FormatError(path, fld, f"has shape {arr.shape}, expected {shape}.", fix)
    if not np.all(np.isfinite(arr)):
        raise FormatError(path, fld, "contains NaN or infinite values.", fix)
    return arr


def validated_fields(
    name: Any,
    size_wh: Any,
    K: Any,
    dist: Any,
    model: Any,
    R: Any,
    t: Any,
    *,
    path: str | os.PathLike[str] | None = None,
    where: str | None = None,
    names: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """Check and normalise camera fields; errors name ``path`` and ``where.<field>``.

    ``names`` maps this module's field names (K, dist, R, t, size_wh, model) to the names a
    source file uses (e.g. ``{"K": "matrix"}``), so importer errors name the file's own field."""
    if not isinstance(name, str) or not name:
        raise FormatError(
            path,
            f"{where}.name" if where else "name",
            f"camera name must be a non-empty string, got {name!r}.",
            "Give every camera a name.",
        )
    nm = dict(names or {})
    w0 = where or f"camera '{name}'"

    def fld(key: str) -> str:
        return f"{w0}.{nm.get(key, key)}"

    _check_model(model, path, fld("model"))
    wh = _check_size(size_wh, path, fld("size_wh"))
    K_ = _check_K(K, path, fld("K"))
    dist_ = _check_dist(dist, model, path, fld("dist"))
    R_ = _check_R(R, path, fld("R"))
    t_ = _as_matrix(t, (3,), path, fld("t"), "Write t as 3 numbers in metres (cam_from_world translation).")
    for a in (K_, dist_, R_, t_):
        a.setflags(write=False)
    return {"name": name, "size_wh": wh, "K": K_, "dist": dist_, "model": model, "R": R_, "t": t_}
