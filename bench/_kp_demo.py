"""Helpers for the keypoints benchmarks: Qualisys .qca.txt fallback reader and plain-DLT reprojection error.

Uses ``calibrate.formats`` when it can read Qualisys files; otherwise a minimal reader here
(focal lengths and principal point in 1/64 sensor units minus the video field-of-view offset;
the ``transform`` is the camera pose in the world, millimetres).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np


def read_qca(path: str | Path) -> dict[str, dict]:
    """-> {serial: dict(size_wh, K, dist (k1,k2,p1,p2,k3), R cam_from_world, t metres)}."""
    try:  # the project's importer once it exists
        from roomcap.calibrate import formats  # noqa: F401

        rig = formats.read_qualisys(path)  # type: ignore[attr-defined]
        return {c.name: dict(size_wh=c.size_wh, K=c.K, dist=c.dist, R=c.R, t=c.t) for c in rig.cameras}
    except Exception:
        pass
    out = {}
    for cam in ET.parse(path).getroot().iter("camera"):
        fov = cam.find("fov_video").attrib
        left, top = float(fov["left"]), float(fov["top"])
        w = int(fov["right"]) - int(left) + 1
        h = int(fov["bottom"]) - int(top) + 1
        i = {k: float(v) for k, v in cam.find("intrinsic").attrib.items()}
        K = np.array(
            [
                [i["focalLengthU"] / 64, 0, i["centerPointU"] / 64 - left],
                [0, i["focalLengthV"] / 64, i["centerPointV"] / 64 - top],
                [0, 0, 1],
            ]
        )
        dist = np.array(
            [
                i["radialDistortion1"],
                i["radialDistortion2"],
                i["tangentalDistortion1"],
                i["tangentalDistortion2"],
                i["radialDistortion3"],
            ]
        )
        tr = {k: float(v) for k, v in cam.find("transform").attrib.items()}
        R_wc = np.array([[tr[f"r{a}{b}"] for b in (1, 2, 3)] for a in (1, 2, 3)])  # camera axes in world
        C = np.array([tr["x"], tr["y"], tr["z"]]) / 1000.0
        R = R_wc.T
        out[cam.attrib["serial"]] = dict(size_wh=(w, h), K=K, dist=dist, R=R, t=-R @ C)
    return out


def undistort(cam: dict, xy: np.ndarray) -> np.ndarray:
    """xy (...,2) px -> ideal pinhole px with the same K (NaN passes through)."""
    shp = xy.shape
    pts = xy.reshape(-1, 1, 2).astype(np.float64)
    ok = np.isfinite(pts[:, 0, 0])
    out = np.full_like(pts, np.nan)
    if ok.any():
        out[ok] = cv2.undistortPoints(pts[ok], cam["K"], cam["dist"], P=cam["K"])
    return out.reshape(shp)


def project(cam: dict, X: np.ndarray) -> np.ndarray:
    """X (N,3) -> (N,2) distorted px; NaN rows pass through."""
    out = np.full((len(X), 2), np.nan)
    ok = np.isfinite(X).all(1)
    if ok.any():
        rvec = cv2.Rodrigues(cam["R"])[0]
        out[ok] = cv2.projectPoints(X[ok].astype(np.float64), rvec, cam["t"], cam["K"], cam["dist"])[0][:, 0]
    return out


def dlt(Ps: np.ndarray, xy: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Plain (weighted) DLT. Ps (C,3,4); xy (C,N,2) undistorted px (NaN = unseen) -> X (N,3)."""
    C, N = xy.shape[:2]
    w = np.ones((C, N)) if w is None else w
    X = np.full((N, 3), np.nan)
    for n in range(N):
        rows = []
        for c in range(C):
            if np.isfinite(xy[c, n]).all() and w[c, n] > 0:
                x, y = xy[c, n]
                rows += [w[c, n] * (x * Ps[c, 2] - Ps[c, 0]), w[c, n] * (y * Ps[c, 2] - Ps[c, 1])]
        if len(rows) >= 4:
            _, _, vt = np.linalg.svd(np.asarray(rows))
            X[n] = vt[-1, :3] / vt[-1, 3]
    return X


def reprojection_errors(cams: list[dict], xy: np.ndarray, score: np.ndarray, min_score: float = 0.3):
    """xy (C,T,J,2) distorted px, score (C,T,J) -> per-camera reprojection errors (C,T,J) px (NaN unseen)."""
    C, T, J = score.shape
    Ps = np.stack([c["K"] @ np.hstack([c["R"], c["t"][:, None]]) for c in cams])
    und = np.stack([undistort(c, xy[i]) for i, c in enumerate(cams)])
    und[score < min_score] = np.nan
    X = dlt(Ps, und.reshape(C, T * J, 2), np.where(score >= min_score, score, 0).reshape(C, T * J))
    err = np.full((C, T * J), np.nan)
    for i, c in enumerate(cams):
        pr = project(c, X)
        seen = np.isfinite(und[i].reshape(-1, 2)).all(1)
        e = np.linalg.norm(pr - xy[i].reshape(-1, 2), axis=1)
        err[i] = np.where(seen, e, np.nan)
    return err.reshape(C, T, J), X.reshape(T, J, 3)
