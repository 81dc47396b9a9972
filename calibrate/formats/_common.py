"""What the calibration readers and writers share: the import options and the checks of a file's values
(package-internal; the public names are re-exported by :mod:`roomcap.calibrate.formats`)."""

from __future__ import annotations

import logging
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.calibrate.camera import Camera, CameraRig
from roomcap.calibrate.camera_fields import PINHOLE_DIST_SIZES, validated_fields
from roomcap.core.config import check_keys
from roomcap.core.errors import FormatError, InputError

log = logging.getLogger(__name__)

IMPORT_FORMATS = ("aniposelib", "qualisys", "caliscope", "easymocap", "rig")
EXPORT_FORMATS = ("aniposelib", "easymocap", "rig")


@dataclass(frozen=True)
class ImportOptions:
    """Options for ``import_rig``; each applies to the formats named.

    scale_to_m: multiply translations by this (aniposelib/caliscope/easymocap in another unit).
    image_size_wh: (width, height) of the videos the rig will be used with, for every camera, or
        a mapping ``{camera name: (width, height)}`` (``"*"`` = the others). Qualisys: when it
        differs from the calibrated field of view (1080 vs 1088 wide in Pose2Sim's demo) the image
        is taken as cropped/padded at the right/bottom (origin stays top-left, K unchanged) and a
        warning is logged. EasyMocap: the size when ``intri.yml`` has no ``H_``/``W_``.
    distortion_scale: Qualisys only; multiply the distortion coefficients (1/64 reproduces Pose2Sim).
    view_rotation: Qualisys only; "sensor" keeps the sensor orientation (default, like Pose2Sim),
        "apply" rotates each camera by its ``viewrotation`` (clockwise degrees).
    include_marker_cameras: Qualisys only; also import marker-only cameras.
    """

    scale_to_m: float = 1.0
    image_size_wh: tuple[int, int] | Mapping[str, tuple[int, int]] | None = None
    distortion_scale: float = 1.0
    view_rotation: str = "sensor"
    include_marker_cameras: bool = False

    def __post_init__(self) -> None:
        if not (self.scale_to_m > 0 and math.isfinite(self.scale_to_m)):
            raise InputError(f"ImportOptions.scale_to_m must be a positive number, got {self.scale_to_m}")
        if self.view_rotation not in ("sensor", "apply"):
            raise InputError(
                f"ImportOptions.view_rotation must be 'sensor' or 'apply', got {self.view_rotation!r}"
            )
        if self.image_size_wh is not None:
            sizes = self.image_size_wh
            items = sizes.items() if isinstance(sizes, Mapping) else [("*", sizes)]
            norm = {}
            for name, size in items:
                wh = tuple(int(v) for v in size)
                if len(wh) != 2 or min(wh) <= 0:
                    raise InputError(f"ImportOptions.image_size_wh must be (width, height), got {size}")
                norm[str(name)] = wh
            object.__setattr__(self, "image_size_wh", norm["*"] if list(norm) == ["*"] else norm)

    def size_for(self, camera: str) -> tuple[int, int] | None:
        """The video size given for ``camera`` (or for all cameras), else None."""
        s = self.image_size_wh
        if s is None or not isinstance(s, Mapping):
            return s
        return s.get(camera, s.get("*"))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ImportOptions:
        check_keys(d, [f.name for f in fields(cls)], "import options", None)
        return cls(**d)


# ----------------------------------------------------------------------------- helpers


def pad_dist(dist: Any) -> np.ndarray:
    """Pad a pinhole distortion vector with zeros to the next length OpenCV accepts (4/5/8/12/14).

    Exact: OpenCV treats absent trailing coefficients as zero."""
    d = np.asarray(dist, dtype=np.float64).reshape(-1)
    if d.size in PINHOLE_DIST_SIZES:
        return d
    for n in PINHOLE_DIST_SIZES:
        if n > d.size:
            return np.concatenate([d, np.zeros(n - d.size)])
    return d  # too long: validation reports it


def _need(table: Mapping[str, Any], key: str, path: Any, where: str, fix: str) -> Any:
    if key not in table:
        raise FormatError(path, f"{where}.{key}", f"is missing (present: {sorted(table)}).", fix)
    return table[key]


def _array(value: Any, shape: tuple[int, ...], path: Any, fld: str, fix: str = "") -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise FormatError(path, fld, f"is not numeric ({e}).", fix) from None
    if a.shape != shape:
        raise FormatError(path, fld, f"has shape {a.shape}, expected {shape}.", fix)
    return a


def _size(value: Any, path: Any, fld: str) -> tuple[int, int]:
    try:
        w, h = (float(v) for v in value)
    except (TypeError, ValueError):
        raise FormatError(path, fld, f"must be [width, height], got {value!r}.", "") from None
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise FormatError(
            path, fld, f"must be two positive whole numbers [width, height], got {value!r}.", ""
        )
    return int(w), int(h)


def _camera(path: Any, where: str, names: Mapping[str, str], **kw: Any) -> Camera:
    return Camera(**validated_fields(path=path, where=where, names=names, **kw))


def _load_toml(path: Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise FormatError(path, None, "file does not exist.") from None
    except tomllib.TOMLDecodeError as e:
        raise FormatError(path, None, f"is not valid TOML ({e}).", "Check the file is complete.") from None
    except UnicodeDecodeError:
        raise FormatError(
            path,
            None,
            "is a binary file, not a calibration this tool reads.",
            f"Give a calibration file of one of {list(IMPORT_FORMATS)} (see calibrate-run import --help).",
        ) from None


def _check_size_names(opts: ImportOptions, cams: list[Camera], path: Any) -> None:
    sizes = opts.image_size_wh
    if isinstance(sizes, Mapping):
        unknown = sorted(set(sizes) - {"*"} - {c.name for c in cams})
        if unknown:
            raise FormatError(
                path,
                None,
                f"image sizes were given for cameras {unknown}, which it does not have "
                f"(cameras: {[c.name for c in cams]}).",
                "Check the camera names.",
            )


def _nonempty(cams: list[Camera], path: Any, what: str) -> CameraRig:
    if not cams:
        raise FormatError(path, None, f"no cameras found ({what}).", "Check that this is a calibration file.")
    names = [c.name for c in cams]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise FormatError(path, "name", f"camera names repeat: {dup}.", "Give every camera a unique name.")
    return CameraRig(tuple(cams))
