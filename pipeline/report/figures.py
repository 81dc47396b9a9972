"""The report's figures from the session's data: the rig and calibration, detection rates, track
timelines and events, the reprojection quality."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.capture.session import SessionLayout
from roomcap.core.fileio import load_toml
from roomcap.pipeline.report.inputs import ReportConfig, _f, _Inputs, _r
from roomcap.pipeline.report.views import _shown_path
from roomcap.track.trackfile import INTERPOLATED, OBSERVED, PREDICTED


def _footprint(cam, height_m: float = 0.9, range_m: float = 12.0, n: int = 24) -> list[list[float]]:
    """The part of the horizontal plane at ``height_m`` (a standing person's hips) the camera sees:
    rays through its image border intersected with the plane, or cut at ``range_m`` (horizontal)
    where they miss it; (N,2) world x, y. Lens distortion is ignored (a few pixels at the border)."""
    w, h = cam.size_wh
    t = np.linspace(0, 1, n, endpoint=False)
    border = np.concatenate(
        [
            np.stack([t * w, np.zeros(n)], 1),
            np.stack([np.full(n, w), t * h], 1),
            np.stack([(1 - t) * w, np.full(n, h)], 1),
            np.stack([np.zeros(n), (1 - t) * h], 1),
        ]
    )
    rays = np.linalg.inv(cam.K) @ np.vstack([border.T, np.ones(len(border))])  # (3,N) camera frame
    d = (cam.R.T @ rays).T  # (N,3) world directions
    c = cam.center
    pts = []
    for di in d:
        horiz = float(np.hypot(di[0], di[1]))
        s = (height_m - c[2]) / di[2] if abs(di[2]) > 1e-9 else -1.0
        if s <= 0 or s * horiz > range_m:  # the ray misses the plane in front, or meets it far away
            s = range_m / max(horiz, 1e-9)
        p = c + s * di
        pts.append([round(float(p[0]), 3), round(float(p[1]), 3)])
    return pts


def _calibration_figures(lay: SessionLayout) -> dict[str, Any] | None:
    """The calibration's own figures: roomcap's ``report/report.toml`` next to the rig (intrinsic /
    extrinsic RMS, bundle adjustment), or the per-camera residuals of an imported Qualisys file."""
    rep = lay.rig_toml.parent / "report" / "report.toml"
    if rep.exists():
        try:
            d = load_toml(rep)
            cams = {}
            for c in d.get("cameras", []):
                cams[str(c.get("name"))] = {
                    k: c[k]
                    for k in (
                        "intrinsic_rms_px",
                        "extrinsic_rms_px",
                        "frames_with_board",
                        "coverage_fraction",
                        "intrinsic_frames_used",
                    )
                    if k in c
                }
            ba = d.get("bundle_adjustment", {})
            return {
                "source": _shown_path(rep, lay),
                "unit": "px",
                "cameras": cams,
                "bundle_adjustment": {k: v for k, v in ba.items() if isinstance(v, (int, float, str))},
            }
        except Exception as e:
            return {"source": _shown_path(rep, lay), "error": str(e), "cameras": {}}
    prov = lay.root / ".roomcap" / "provenance" / "calibration.json"
    try:
        inputs = list(json.loads(prov.read_text())["inputs"])
    except (OSError, json.JSONDecodeError, KeyError, TypeError):
        return None
    for src in inputs:
        p = Path(src)
        if p.name.lower().endswith((".qca.txt", ".qca")) and p.exists():
            try:
                import xml.etree.ElementTree as ET

                root = ET.parse(p).getroot()
                cams = {}
                for c in root.iter("camera"):
                    if c.get("avg-residual") is not None:
                        cams[str(c.get("serial"))] = {"avg_residual": float(c.get("avg-residual"))}
                if cams:
                    return {"source": str(p), "unit": "mm (Qualisys marker residual)", "cameras": cams}
            except Exception:  # a file we cannot parse says nothing about the calibration
                return None
    return None


def rig_cameras_data(rig) -> list[dict[str, Any]]:
    """Each camera of ``rig`` as the 3D viewer draws it (report.js and the live view's page): image size,
    focal length, field of view, centre and axes in metres (world, z up)."""
    cams = []
    for cam in rig.cameras:
        R = np.asarray(cam.R)
        w, h = cam.size_wh
        fx, fy = float(cam.K[0, 0]), float(cam.K[1, 1])
        cams.append(
            {
                "name": cam.name,
                "size_wh": list(cam.size_wh),
                "f_px": _r([fx, fy], 1),
                "c_px": _r([cam.K[0, 2], cam.K[1, 2]], 1),
                "model": cam.model,
                "fov_deg": _r(np.degrees(2 * np.arctan([w / (2 * fx), h / (2 * fy)])), 1),
                "center_m": _r(cam.center),
                "axis": _r(R[2]),
                "right": _r(R[0]),
                "up": _r(-R[1]),
                "footprint_m": _footprint(cam),
            }
        )
    return cams


def _rig_data(inp: _Inputs) -> dict[str, Any] | None:
    if inp.rig_error:
        return {"error": inp.rig_error, "cameras": []}
    if inp.rig is None:
        return None
    return {
        "cameras": rig_cameras_data(inp.rig),
        "sha256": inp.rig.sha256(),
        "figures": _calibration_figures(inp.lay),
    }


def _detection_rates(inp: _Inputs) -> dict[str, Any]:
    out = {}
    for cam, d in inp.detections.items():
        xy = d.xy_px
        T = len(d.frame_index)
        people = np.isfinite(xy[..., 0]).any(-1).sum(-1) if xy.size else np.zeros(T)
        joints = np.isfinite(xy[..., 0]).sum((-1, -2)) if xy.size else np.zeros(T)
        out[cam] = {"people": people.astype(int).tolist(), "joints": joints.astype(int).tolist()}
    return out


# ----------------------------------------------------------------------------- tracks


def _roots(xyz: np.ndarray, joint_names: tuple[str, ...]) -> np.ndarray:
    """(T,K,3) a root point per track and frame: the pelvis, else the hips' mean, else all joints'."""
    import warnings

    names = list(joint_names)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: no root there
        out = np.nanmean(xyz, axis=2) if xyz.shape[2] else np.full(xyz.shape[:2] + (3,), np.nan)
        hips = [names.index(n) for n in ("left_hip", "right_hip") if n in names]
        if hips:
            h = xyz[:, :, hips]
            hm = np.where(np.isfinite(h).all(-1, keepdims=True), h, np.nan)
            mh = np.nanmean(hm, axis=2)
            out = np.where(np.isfinite(mh), mh, out)
        if "pelvis" in names:
            p = xyz[:, :, names.index("pelvis")]
            out = np.where(np.isfinite(p).all(-1, keepdims=True), p, out)
    return out


def _segments(mask: np.ndarray) -> list[list[int]]:
    """[[start, end_inclusive], ...] of the runs of True in a (T,) mask."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    return [[int(a), int(b)] for a, b in zip(starts, ends, strict=True)]


def track_events(tf, cfg: ReportConfig) -> dict[str, Any]:
    """Per track: frames carried without an observation (track file flags) and sudden jumps of the root,
    with the track that was where it landed (a suspected identity swap). Frames are track-file rows."""

    xyz = np.asarray(tf.xyz_m, np.float64)
    T, K = xyz.shape[:2]
    present = np.isfinite(xyz[..., 0]).any(-1)  # (T,K)
    fl = np.asarray(tf.flags)
    observed = ((fl & OBSERVED) > 0).any(-1)
    unobserved = present & ~observed
    interp = unobserved & ((fl & INTERPOLATED) > 0).any(-1)
    pred = unobserved & ~interp & ((fl & PREDICTED) > 0).any(-1)
    roots = _roots(xyz, tf.joint_names)
    fps = float(tf.fps) or 25.0
    fi = np.asarray(tf.frame_index)
    jumps = []
    for k in range(K):
        idx = np.flatnonzero(np.isfinite(roots[:, k]).all(-1))
        if len(idx) < 2:
            continue
        a, b = idx[:-1], idx[1:]
        dt = (fi[b] - fi[a]) / fps
        dist = np.linalg.norm(roots[b, k] - roots[a, k], axis=-1)
        bad = np.flatnonzero((dist > cfg.jump_m + cfg.jump_speed_m_s * dt) & (b - a <= 3))
        for i in bad:
            t0, t1 = int(a[i]), int(b[i])
            other = None
            d_other = np.linalg.norm(roots[t0] - roots[t1, k], axis=-1)  # (K,) others' roots before
            d_other[k] = np.inf
            d_other = np.where(np.isfinite(d_other), d_other, np.inf)
            if K > 1 and d_other.min() < cfg.swap_radius_m:
                other = int(np.asarray(tf.track_id)[int(d_other.argmin())])
            jumps.append(
                {
                    "track": k,
                    "id": int(np.asarray(tf.track_id)[k]),
                    "t": t1,
                    "frame": int(fi[t1]),
                    "dist_m": round(float(dist[i]), 3),
                    "speed_m_s": round(float(dist[i] / max(dt[i], 1e-9)), 2),
                    "swap_with": other,
                }
            )
    jumps.sort(key=lambda j: (j["t"], j["id"]))
    return {
        "unobserved": [_segments(unobserved[:, k]) for k in range(K)],
        "unobserved_frames": unobserved.sum(0).astype(int).tolist(),
        "interpolated_frames": interp.sum(0).astype(int).tolist(),
        "predicted_frames": pred.sum(0).astype(int).tolist(),
        "present_frames": present.sum(0).astype(int).tolist(),
        "jumps": jumps,
    }


def _tracks_data(inp: _Inputs, cfg: ReportConfig) -> dict[str, Any] | None:
    tf = inp.tracks
    if tf is None:
        return None
    xyz = np.asarray(tf.xyz_m)
    T = xyz.shape[0]
    step = max(1, int(np.ceil(T / cfg.max_viewer_frames)))
    sel = np.arange(0, T, step)
    std = np.asarray(tf.std_m)
    present = np.isfinite(xyz[..., 0]).any(-1)  # (T,K)
    ok = np.isfinite(std)
    mean_std = np.where(ok.any(-1), np.where(ok, std, 0).sum(-1) / np.maximum(ok.sum(-1), 1), np.nan)
    ev = track_events(tf, cfg)
    return {
        "fps": float(tf.fps) / step,
        "frame_index": np.asarray(tf.frame_index)[sel].tolist(),
        "track_id": np.asarray(tf.track_id).tolist(),
        "joint_names": list(tf.joint_names),
        "parents": np.asarray(tf.parents).tolist(),
        "xyz": _r(xyz[sel]),
        "present": present.astype(int).T.tolist(),
        "mean_std_m": _r(mean_std.T, 4) if std.size else [],
        "source": str(tf.source),
        "step": step,
        "events": ev,
    }


# ----------------------------------------------------------------------------- reprojection quality


def reprojection_figures(poses) -> dict[str, Any]:
    """The triangulation's reprojection errors summarised (the arrays of ``triangulate/poses3d.npz``).

    per camera: mean / median / 90th percentile over the joints that camera's view was used for
    (``reproj_err_cam_px``), that count and the share of all triangulated joints; per joint: the mean of
    ``reproj_err_px`` (the mean over the views used) and the mean ``n_views``; the camera x joint matrix
    of means; per frame: the mean error per camera and overall (NaN = nothing triangulated).
    """
    err = np.asarray(poses.reproj_err_px, np.float64)  # (T,P,J)
    nv = np.asarray(poses.n_views)
    ok = np.isfinite(err) & (nv > 0)
    J = err.shape[2]
    with np.errstate(all="ignore"):
        per_joint = np.where(ok.any((0, 1)), np.nansum(np.where(ok, err, 0), (0, 1)) / ok.sum((0, 1)), np.nan)
        views_joint = np.where(ok.any((0, 1)), np.where(ok, nv, 0).sum((0, 1)) / ok.sum((0, 1)), np.nan)
        per_frame = np.where(ok.any((1, 2)), np.where(ok, err, 0).sum((1, 2)) / ok.sum((1, 2)), np.nan)
    n_ok = int(ok.sum())
    hist = np.bincount(nv[ok].astype(int), minlength=1).tolist() if n_ok else []
    out: dict[str, Any] = {
        "joint_names": list(poses.joint_names),
        "frame_index": np.asarray(poses.frame_index).tolist(),
        "n_joints_3d": n_ok,
        "mean_px": _f(err[ok].mean()) if n_ok else None,
        "median_px": _f(np.median(err[ok])) if n_ok else None,
        "per_joint_mean_px": _r(per_joint),
        "per_joint_views": _r(views_joint),
        "views_hist": hist,
        "per_frame_mean_px": _r(per_frame),
        "cameras": [],
    }
    if poses.cameras is None:
        out["per_camera_note"] = (
            "poses3d.npz was written before per-camera errors were kept: rerun the triangulate stage "
            "(reprocess SESSION --stages triangulate --force) to see them."
        )
        return out
    ec = np.asarray(poses.reproj_err_cam_px, np.float64)  # (T,P,J,C)
    cams = []
    for c, name in enumerate(poses.cameras):
        e = ec[..., c]
        m = np.isfinite(e) & ok
        v = e[m]
        with np.errstate(all="ignore"):
            pj = np.where(m.any((0, 1)), np.where(m, e, 0).sum((0, 1)) / m.sum((0, 1)), np.nan)
            pf = np.where(m.any((1, 2)), np.where(m, e, 0).sum((1, 2)) / m.sum((1, 2)), np.nan)
        cams.append(
            {
                "name": str(name),
                "n": int(m.sum()),
                "share": _f(m.sum() / max(n_ok, 1)),
                "mean_px": _f(v.mean()) if len(v) else None,
                "median_px": _f(np.median(v)) if len(v) else None,
                "p90_px": _f(np.percentile(v, 90)) if len(v) else None,
                "per_joint_mean_px": _r(pj),
                "per_frame_mean_px": _r(pf),
            }
        )
    out["cameras"] = cams
    out["J"] = J
    return out


def _binned(series: list, n_bin: int) -> list:
    """Mean of each run of ``n_bin`` values (None = missing) for the plots of long sessions."""
    if n_bin <= 1:
        return series
    a = np.asarray([np.nan if v is None else v for v in series], np.float64)
    pad = (-len(a)) % n_bin
    a = np.concatenate([a, np.full(pad, np.nan)]).reshape(-1, n_bin)
    ok = np.isfinite(a)
    with np.errstate(all="ignore"):
        m = np.where(ok.any(1), np.where(ok, a, 0).sum(1) / ok.sum(1), np.nan)
    return _r(m)


def _quality(inp: _Inputs, cfg: ReportConfig) -> dict[str, Any] | None:
    if inp.poses_error:
        return {"error": inp.poses_error}
    if inp.poses is None:
        return None
    q = reprojection_figures(inp.poses)
    fi = q.pop("frame_index")
    n_bin = max(1, int(np.ceil(len(fi) / cfg.max_viewer_frames)))
    q["frame_index0"] = int(fi[0]) if fi else 0
    q["per_frame_bin"] = n_bin
    q["per_frame_mean_px"] = _binned(q["per_frame_mean_px"], n_bin)
    for c in q["cameras"]:
        c["per_frame_mean_px"] = _binned(c["per_frame_mean_px"], n_bin)
    return q
