"""Qualisys QTM ``.qca.txt``: reader (the conventions: :mod:`roomcap.calibrate.formats`)."""

from __future__ import annotations

import functools
import logging
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.calibrate.camera import (
    Camera,
    CameraRig,
)
from roomcap.calibrate.formats._common import (
    ImportOptions,
    _camera,
    _check_size_names,
    _nonempty,
)
from roomcap.core.errors import FormatError

log = logging.getLogger(__name__)

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


def read_qualisys(path: Path, opts: ImportOptions | None = None) -> CameraRig:
    """Qualisys QTM ``.qca.txt`` (see the module docstring for the conventions)."""
    opts = opts or ImportOptions()
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
        cam = _qualisys_camera(el, name, where, path, opts)
        cams.append(_oriented(cam, el, name, where, path, opts))
    _check_size_names(opts, cams, path)
    return _nonempty(cams, path, "no <cameras>/<camera> elements for video cameras")


def _qualisys_camera(el: ET.Element, name: str, where: str, path: Path, opts: ImportOptions) -> Camera:
    """One ``<camera>`` element as a camera in the sensor's orientation: the video window's size, K and
    dist from ``<intrinsic>``, the pose from ``<transform>``."""
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
    M = np.array([[_attr(tr, f"r{r}{c}", path, f"{where}.transform") for c in (1, 2, 3)] for r in (1, 2, 3)])
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
    return cam


def _oriented(cam: Camera, el: ET.Element, name: str, where: str, path: Path, opts: ImportOptions) -> Camera:
    """The camera turned by its ``viewrotation`` (with ``view_rotation='apply'``) and given the videos' size
    when the options name one."""
    vr = int(float(el.get("viewrotation", 0) or 0))
    if vr % 90:
        raise FormatError(path, f"{where}.viewrotation", f"is {vr}; only multiples of 90 exist in QTM.", "")
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
    return cam
