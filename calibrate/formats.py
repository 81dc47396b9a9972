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
"""

from __future__ import annotations

import functools
import logging
import math
import os
import re
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from calibrate.camera import (
    PINHOLE_DIST_SIZES,
    Camera,
    CameraRig,
    _validated,
    rotation_from_rvec,
)
from capture.fileio import FormatError, atomic_path, save_toml
from core.config import check_keys

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
            raise ValueError(f"ImportOptions.scale_to_m must be a positive number, got {self.scale_to_m}")
        if self.view_rotation not in ("sensor", "apply"):
            raise ValueError(
                f"ImportOptions.view_rotation must be 'sensor' or 'apply', got {self.view_rotation!r}"
            )
        if self.image_size_wh is not None:
            sizes = self.image_size_wh
            items = sizes.items() if isinstance(sizes, Mapping) else [("*", sizes)]
            norm = {}
            for name, size in items:
                wh = tuple(int(v) for v in size)
                if len(wh) != 2 or min(wh) <= 0:
                    raise ValueError(f"ImportOptions.image_size_wh must be (width, height), got {size}")
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
    return Camera(**_validated(path=path, where=where, names=names, **kw))


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
        raise ValueError(f"unknown calibration format {fmt!r}; valid: {list(IMPORT_FORMATS)}")
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
    raise ValueError(f"unknown export format {fmt!r}; valid: {list(EXPORT_FORMATS)}")


# ----------------------------------------------------------------------------- aniposelib / Pose2Sim

_ANIPOSE_NAMES = {
    "K": "matrix",
    "dist": "distortions",
    "R": "rotation",
    "t": "translation",
    "size_wh": "size",
    "model": "fisheye",
}


def read_aniposelib(path: Path, opts: ImportOptions = ImportOptions()) -> CameraRig:
    """aniposelib / Pose2Sim TOML: Rodrigues ``rotation`` + ``translation`` = cam_from_world."""
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


# ----------------------------------------------------------------------------- Qualisys


def _attr(el: ET.Element, key: str, path: Any, where: str) -> float:
    v = el.get(key)
    if v is None:
        raise FormatError(
            path, f"{where}.{key}", "attribute is missing.", "Export the calibration again from QTM."
        )
    try:
        return float(v)
    except ValueError:
        raise FormatError(path, f"{where}.{key}", f"is not a number ({v!r}).", "") from None


def _rotate_image_cw(cam: Camera, quarter_turns: int) -> Camera:
    """The same camera for an image rotated clockwise by 90 degrees ``quarter_turns`` times.

    One turn: pixel (u, v) -> (h-1-v, u); camera axes x' = -y, y' = x; fx' = fy, cx' = h-1-cy,
    fy' = fx, cy' = cx; tangential (p1, p2) -> (p2, -p1) (the vector (p2, p1) turns with the image)."""
    c = cam
    for _ in range(quarter_turns % 4):
        if c.dist.size > 5 or c.model != "pinhole":
            raise ValueError("image rotation supports pinhole cameras with at most 5 coefficients")
        w, h = c.size_wh
        K = c.K
        Kn = np.array([[K[1, 1], 0.0, h - 1 - K[1, 2]], [0.0, K[0, 0], K[0, 2]], [0.0, 0.0, 1.0]])
        Q = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        d = c.dist.copy()
        if d.size >= 4:
            d[2], d[3] = c.dist[3], -c.dist[2]
        c = Camera(c.name, (h, w), Kn, d, "pinhole", Q @ c.R, Q @ c.t)
    return c


def read_qualisys(path: Path, opts: ImportOptions = ImportOptions()) -> CameraRig:
    """Qualisys QTM ``.qca.txt`` (see the module docstring for the conventions)."""
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise FormatError(path, None, "file does not exist.") from None
    except ET.ParseError as e:
        raise FormatError(
            path, None, f"is not valid XML ({e}).", "Check that the file is complete."
        ) from None
    cams = []
    for i, el in enumerate(root.findall("cameras/camera")):
        name = el.get("serial") or f"cam_{i}"
        where = f"camera[{i}] ({name})"
        model = (el.get("model") or "none").lower()
        if not opts.include_marker_cameras and not ("video" in model or model == "none"):
            log.info("%s: skipping marker camera %s (model %r)", path, name, model)
            continue
        fov, intr, tr = el.find("fov_video"), el.find("intrinsic"), el.find("transform")
        for tag, node in (("fov_video", fov), ("intrinsic", intr), ("transform", tr)):
            if node is None:
                raise FormatError(
                    path, f"{where}.{tag}", "element is missing.", "Export the calibration again from QTM."
                )
        left, top = (
            _attr(fov, "left", path, f"{where}.fov_video"),
            _attr(fov, "top", path, f"{where}.fov_video"),
        )
        w = int(_attr(fov, "right", path, f"{where}.fov_video") - left + 1)
        h = int(_attr(fov, "bottom", path, f"{where}.fov_video") - top + 1)
        a = functools.partial(_attr, intr, path=path, where=f"{where}.intrinsic")
        if abs(float(intr.get("skew", 0) or 0)) > 0:
            raise FormatError(
                path,
                f"{where}.intrinsic.skew",
                f"is {intr.get('skew')}; skew is not supported.",
                "Recalibrate without skew.",
            )
        # focal length and principal point in 1/64 pixel of the full sensor; shift by the video window
        K = np.array(
            [
                [a("focalLengthU") / 64.0, 0.0, a("centerPointU") / 64.0 - left],
                [0.0, a("focalLengthV") / 64.0, a("centerPointV") / 64.0 - top],
                [0.0, 0.0, 1.0],
            ]
        )
        dist = np.array(
            [
                a("radialDistortion1"),
                a("radialDistortion2"),
                a("tangentalDistortion1"),
                a("tangentalDistortion2"),
                float(intr.get("radialDistortion3", 0) or 0),
            ]
        )
        dist *= opts.distortion_scale
        M = np.array(
            [[_attr(tr, f"r{r}{c}", path, f"{where}.transform") for c in (1, 2, 3)] for r in (1, 2, 3)]
        )
        pos_m = np.array([_attr(tr, k, path, f"{where}.transform") for k in "xyz"]) / 1000.0
        # rows of M = camera axes in world (Qualisys camera: x right, y up, looking along -z)
        R = np.diag([1.0, -1.0, -1.0]) @ M
        cam = _camera(
            path,
            where,
            {"R": "transform.r11..r33", "K": "intrinsic", "dist": "intrinsic"},
            name=name,
            size_wh=(w, h),
            K=K,
            dist=dist,
            model="pinhole",
            R=R,
            t=-R @ pos_m,
        )
        vr = int(float(el.get("viewrotation", 0) or 0))
        if vr % 90:
            raise FormatError(
                path, f"{where}.viewrotation", f"is {vr}; only multiples of 90 exist in QTM.", ""
            )
        if vr % 360 and opts.view_rotation == "apply":
            cam = _rotate_image_cw(cam, (vr // 90) % 4)
        elif vr % 360:
            log.warning(
                "%s: camera %s has viewrotation=%d; kept in the sensor's orientation "
                "(use view_rotation='apply' if your videos are rotated for display)",
                path,
                name,
                vr,
            )
        video_wh = opts.size_for(name)
        if video_wh is not None and video_wh != cam.size_wh:
            log.warning(
                "%s: camera %s is calibrated for %dx%d, videos are %dx%d: taking the image as "
                "cropped/padded at the right/bottom (principal point unchanged)",
                path,
                name,
                *cam.size_wh,
                *video_wh,
            )
            cam = cam.replace(size_wh=video_wh)
        cams.append(cam)
    _check_size_names(opts, cams, path)
    return _nonempty(cams, path, "no <cameras>/<camera> elements for video cameras")


# ----------------------------------------------------------------------------- caliscope

_CALISCOPE_NAMES = {
    "K": "matrix",
    "dist": "distortions",
    "R": "rotation",
    "t": "translation",
    "size_wh": "size",
}


def read_caliscope(path: Path, opts: ImportOptions = ImportOptions()) -> CameraRig:
    """caliscope ``camera_array.toml`` ([cameras.N]) or ``config.toml`` ([cam_N] with ``port``)."""
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


def read_easymocap(path: Path, opts: ImportOptions = ImportOptions()) -> CameraRig:
    """EasyMocap / OpenCV FileStorage ``intri.yml`` + ``extri.yml`` (cam_from_world, metres)."""
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
