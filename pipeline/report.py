"""The session report: one self-contained HTML file (no network needed to open it).

Sections: a plain-language list of problems with what to do about each; the 3D viewer of the
tracks (playback, per-person colours, cameras, forecasts as faded skeletons); per camera a
filmstrip of the video with the 2D detections and the tracks reprojected into it, coloured by
identity, on a frame slider shared with the viewer; the reprojection error per camera and per
joint as the triangulation wrote it (table, camera x joint matrix, plot over time), the views per
joint; track timelines with the frames a track was carried without observations and suspected
identity swaps; the room from above with each camera's field of view; detection rates; the
calibration (and its own figures when its report is there); the warnings the pipeline logged.

Everything is embedded: data as JSON, video frames as JPEG data URIs sized to a byte budget
(``ReportConfig``: a 4-camera, 2-minute session stays under about 30 MB; longer ones sample
frames evenly). The page is plain canvas JavaScript (``report_assets/``); script errors are
collected into ``#errors`` so tests (and people) see them.

``write_overlay_videos`` draws the same overlays on every frame of every camera's video (MP4);
``python -m pipeline.report SESSION [--overlay]`` writes the report (and those videos) for a
session folder without running the pipeline.
"""

from __future__ import annotations

import argparse
import base64
import html
import json
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capture.fileio import FormatError, atomic_path, atomic_write_text, load_npz, load_toml
from capture.session import VIDEO_SUFFIXES, SessionLayout
from core.progress import Progress
from core.redact import redact
from keypoints.detections import Detections
from keypoints.skeletons import CANONICAL, convert
from pipeline.config import STAGES
from track.trackfile import INTERPOLATED, OBSERVED, PREDICTED
from triangulate.chunks import parts_dir
from triangulate.dlt import DLTConfig

log = logging.getLogger(__name__)

_ASSETS = Path(__file__).resolve().parent / "report_assets"
_MAX_FRAMES = 2000  # frames embedded in the viewer (subsampled beyond); ReportConfig.max_viewer_frames


@dataclass(frozen=True)
class ReportConfig:
    """What the report embeds and what it calls a problem.

    max_viewer_frames: 3D frames embedded (evenly subsampled beyond).
    image_budget_bytes: JPEG bytes of the filmstrips, all cameras together (base64 adds a third);
      frames are sampled evenly over the session to fit.
    overlay_budget_bytes: JSON bytes of the 2D overlays of the sampled frames, all cameras together.
    image_max_side_px, jpeg_quality: size of the embedded frames.
    max_film_frames / min_film_frames: sampled frames per camera, at most / at least.
    jump_m, jump_speed_m_s: a track's root moving farther than ``jump_m + jump_speed_m_s * dt`` between
      two frames it is present in is a sudden jump (a walking person moves ~1.5 m/s);
    swap_radius_m: ... and a suspected identity swap when another track was within this of where it
      landed the frame before.
    match_px_frac: a 2D detection takes a track's colour when its mean joint distance to the track's
      reprojection is below this fraction of the reprojection's box diagonal (else it is drawn grey).
    """

    max_viewer_frames: int = _MAX_FRAMES
    image_budget_bytes: int = 18_000_000
    overlay_budget_bytes: int = 4_000_000
    image_max_side_px: int = 480
    jpeg_quality: int = 70
    max_film_frames: int = 600
    min_film_frames: int = 8
    jump_m: float = 0.35
    jump_speed_m_s: float = 2.5
    swap_radius_m: float = 0.35
    match_px_frac: float = 0.35


def _r(a: np.ndarray, nd: int = 3) -> Any:
    """Round and turn NaN into None for JSON."""
    a = np.round(np.asarray(a, dtype=np.float64), nd)
    return np.where(np.isfinite(a), a, None).tolist()


def _f(x: Any, nd: int = 3) -> float | None:
    x = float(x)
    return round(x, nd) if np.isfinite(x) else None


# ----------------------------------------------------------------------------- loading


@dataclass
class _Inputs:
    """What the report reads, loaded once; a file that cannot be read is a problem, not a crash."""

    lay: SessionLayout
    rig: Any = None
    rig_error: str = ""
    tracks: Any = None
    tracks_error: str = ""
    tracks_name: str = "tracks.npz"  # live.npz where only the live track exists
    poses: Any = None
    poses_error: str = ""
    detections: dict[str, Any] | None = None
    detections_error: dict[str, str] | None = None


def _load(lay: SessionLayout) -> _Inputs:
    inp = _Inputs(lay, detections={}, detections_error={})
    if lay.rig_toml.exists():
        try:
            from calibrate.camera import CameraRig

            inp.rig = CameraRig.load(lay.rig_toml)
        except Exception as e:  # the report shows what it can
            inp.rig_error = str(e)
    # the batch track (the file or a streamed run's parts), else the live one (capture-run --live): the
    # same loader reads both layouts
    for path in (lay.tracks, lay.live_tracks):
        if not (path.exists() or parts_dir(path).is_dir()):
            continue
        inp.tracks_name = path.name
        try:
            from track.trackfile import TrackFile

            inp.tracks = TrackFile.load(path)
        except Exception as e:
            inp.tracks_error = str(e)
        break
    if lay.poses3d.exists() or parts_dir(lay.poses3d).is_dir():
        try:
            from triangulate.poses3d import Poses3D

            inp.poses = Poses3D.load(lay.poses3d)
        except Exception as e:
            inp.poses_error = str(e)

    for cam in lay.detection_cameras():
        try:
            inp.detections[cam] = Detections.load(lay.detections(cam))
        except Exception as e:
            inp.detections_error[cam] = str(e)
    return inp


# ----------------------------------------------------------------------------- calibration


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


# ----------------------------------------------------------------------------- overlays


def _video_paths(lay: SessionLayout, cams: list[str]) -> dict[str, Path]:
    """Each camera's video: the session's ``raw/<cam>.*``, else the video the keypoints stage read
    (its provenance record: a Pose2Sim trial's ``videos/<cam>.mp4`` when the outputs went elsewhere)."""
    out: dict[str, Path] = {}
    inputs: list[str] = []
    try:
        inputs = list(
            json.loads((lay.root / ".roomcap" / "provenance" / "keypoints.json").read_text())["inputs"]
        )
    except (OSError, json.JSONDecodeError, KeyError, TypeError):
        pass

    for cam in cams:
        if lay.video(cam).exists():
            out[cam] = lay.video_file(cam)
            continue
        for src in inputs:
            p = Path(src)
            if p.stem == cam and p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES:
                out[cam] = p
                break
    return out


class _Overlay:
    """2D detections (body19, as detected: distorted pixels) and the tracks reprojected into each camera
    (with the lens model), per session frame; detections take the colour of the track they match."""

    def __init__(self, inp: _Inputs, cfg: ReportConfig):

        self.cfg = cfg
        self.rig = inp.rig
        self.cams = [c for c in (inp.rig.names if inp.rig is not None else []) if c in inp.detections]
        self.cams += [c for c in inp.detections if c not in self.cams]
        self.det = {}
        min_score = DLTConfig().min_score  # the joints the triangulation would use
        for cam in self.cams:
            d = inp.detections[cam]
            xy, sc = convert(d.xy_px, d.score, d.skeleton, "body19")
            xy = np.where((sc >= min_score)[..., None], xy, np.nan)
            self.det[cam] = ({int(f): i for i, f in enumerate(d.frame_index)}, xy)
        self.parents = list(CANONICAL.parents)
        tf = inp.tracks
        self.untracked = tf is None
        if tf is not None and list(tf.joint_names) == list(CANONICAL.joint_names):
            self.xyz, self.fi, self.ids = np.asarray(tf.xyz_m, np.float64), np.asarray(tf.frame_index), None
        elif inp.poses is not None:  # no track file: the per-frame 3D poses, colour by slot
            p = inp.poses
            self.xyz, self.fi = np.asarray(p.xyz_m, np.float64), np.asarray(p.frame_index)
            self.untracked = True
        else:
            self.xyz, self.fi = np.zeros((0, 0, len(CANONICAL.joint_names), 3)), np.zeros(0, np.int64)
        self.row = {int(f): i for i, f in enumerate(self.fi)}
        self.err = {}
        if inp.poses is not None and inp.poses.cameras is not None:
            ec = np.asarray(inp.poses.reproj_err_cam_px, np.float64)
            prow = {int(f): i for i, f in enumerate(inp.poses.frame_index)}
            for c, name in enumerate(inp.poses.cameras):
                e = ec[..., c]
                with np.errstate(all="ignore"):
                    m = np.isfinite(e)
                    pf = np.where(m.any((1, 2)), np.where(m, e, 0).sum((1, 2)) / m.sum((1, 2)), np.nan)
                self.err[str(name)] = (prow, pf)

    def frames(self) -> np.ndarray:
        """The session frames overlays exist for: the track file's, else all detected frames."""
        if len(self.fi):
            return np.asarray(self.fi)
        allf = [np.asarray(list(self.det[c][0])) for c in self.cams]
        return np.unique(np.concatenate(allf)) if allf else np.zeros(0, np.int64)

    def project(self, cam: str, frames: np.ndarray) -> np.ndarray:
        """(n,K,J,2) pixels of the 3D at ``frames`` in ``cam``; NaN where unknown or behind the camera."""
        K, J = self.xyz.shape[1:3]
        out = np.full((len(frames), K, J, 2), np.nan)
        if self.rig is None or cam not in self.rig.names or K == 0:
            return out
        rows = np.asarray([self.row.get(int(f), -1) for f in frames])
        have = rows >= 0
        if have.any():
            X = self.xyz[rows[have]].reshape(-1, 3)
            out[have] = self.rig[cam].project(X).reshape(int(have.sum()), K, J, 2)
        return out

    def detections(self, cam: str, frame: int) -> np.ndarray:
        idx, xy = self.det[cam]
        i = idx.get(int(frame))
        if i is None:
            return np.zeros((0, xy.shape[2], 2))
        d = xy[i]
        return d[np.isfinite(d[..., 0]).any(-1)]

    def match(self, det: np.ndarray, proj: np.ndarray) -> np.ndarray:
        """(P,) the track index each detection (P,J,2) belongs to among the reprojections (K,J,2), or -1:
        the assignment of least mean joint distance, kept below ``match_px_frac`` of the box diagonal."""
        from scipy.optimize import linear_sum_assignment

        P, K = len(det), len(proj)
        out = np.full(P, -1)
        if P == 0 or K == 0:
            return out
        d = np.linalg.norm(det[:, None] - proj[None], axis=-1)  # (P,K,J)
        ok = np.isfinite(d)
        n = ok.sum(-1)
        import warnings

        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a track not in this frame: all NaN
            cost = np.where(n >= 3, np.where(ok, d, 0).sum(-1) / np.maximum(n, 1), np.inf)
            lo, hi = np.nanmin(proj, axis=1), np.nanmax(proj, axis=1)  # (K,2)
            diag = np.linalg.norm(hi - lo, axis=-1)
        limit = np.maximum(np.where(np.isfinite(diag), diag, 0) * self.cfg.match_px_frac, 15.0)
        good = np.isfinite(cost) & (cost < limit[None])
        if not good.any():
            return out
        r, c = linear_sum_assignment(np.where(good, cost, 1e9))
        for a, b in zip(r, c, strict=True):
            if good[a, b]:
                out[a] = b
        return out

    def frame_error(self, cam: str, frame: int) -> float | None:
        if cam not in self.err:
            return None
        prow, pf = self.err[cam]
        i = prow.get(int(frame))
        return None if i is None else _f(pf[i], 2)


def _shown_path(p: Path, lay: SessionLayout) -> str:
    """A path as the page shows it: relative to the session when inside it (the same outputs in another
    folder give the same report), else as given."""
    try:
        return Path(p).resolve().relative_to(lay.root.resolve()).as_posix()
    except ValueError:
        return str(p)


def _flat(xy: np.ndarray) -> list[int | None]:
    """(J,2) pixels -> [x0, y0, x1, y1, ...] rounded, None for missing."""
    v = np.round(xy.reshape(-1)).astype(np.float64)
    return [int(a) if np.isfinite(a) else None for a in v]


def _frame_overlay(ov: _Overlay, cam: str, frame: int, proj: np.ndarray) -> dict[str, Any]:
    det = ov.detections(cam, frame)
    who = ov.match(det, proj)
    P = [[int(k), _flat(d)] for k, d in zip(who, det, strict=True)]
    R = [[k, _flat(p)] for k, p in enumerate(proj) if np.isfinite(p[..., 0]).any()]
    return {"det": P, "proj": R, "err": ov.frame_error(cam, frame)}


def _read_frames(path: Path, wanted: list[int]) -> dict[int, np.ndarray]:
    """The frames ``wanted`` (sorted indices) of a video: decoded in order (grab() over the others,
    exact where seeking is not); a video that ends early gives what it has."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    out: dict[int, np.ndarray] = {}
    if not cap.isOpened():
        return out
    want = set(wanted)
    last = max(wanted) if wanted else -1
    i = 0
    try:
        while i <= last:
            if i in want:
                ok, img = cap.read()
                if not ok:
                    break
                out[i] = img
            elif not cap.grab():
                break
            i += 1
    finally:
        cap.release()
    return out


def _encode_jpeg(img: np.ndarray, cfg: ReportConfig) -> tuple[str, list[int]]:
    import cv2

    h, w = img.shape[:2]
    s = min(1.0, cfg.image_max_side_px / max(h, w))
    if s < 1.0:
        img = cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii"), [
        int(img.shape[1]),
        int(img.shape[0]),
    ]


def _views_data(inp: _Inputs, cfg: ReportConfig) -> dict[str, Any] | None:
    """Per camera the filmstrip: sampled frames (the same for every camera) with their JPEG (when the
    video is found) and the overlays of that frame."""
    if not inp.detections:
        return None
    ov = _Overlay(inp, cfg)
    cand = ov.frames()
    if not len(cand) or not ov.cams:
        return None
    videos = _video_paths(inp.lay, ov.cams)
    # estimate the bytes one sampled frame costs (all cameras), on a few evenly spaced frames
    probe = cand[np.unique(np.linspace(0, len(cand) - 1, min(5, len(cand))).round().astype(int))]
    coord_bytes = 0
    for cam in ov.cams:
        pr = ov.project(cam, probe)
        coord_bytes += sum(
            len(json.dumps(_frame_overlay(ov, cam, int(f), pr[i]))) for i, f in enumerate(probe)
        )
    coord_bytes = max(1.0, coord_bytes / len(probe))
    img_bytes = 0.0
    first = {}
    for cam, path in videos.items():
        imgs = _read_frames(path, [int(cand[0])])
        if imgs:
            uri, _ = _encode_jpeg(imgs[int(cand[0])], cfg)
            first[cam] = len(uri)
            img_bytes += len(uri) * 3 / 4
    n = min(cfg.max_film_frames, int(cfg.overlay_budget_bytes / coord_bytes))
    if img_bytes:
        n = min(n, int(cfg.image_budget_bytes / img_bytes))
    n = int(min(len(cand), max(cfg.min_film_frames, n)))
    sample = cand[np.unique(np.linspace(0, len(cand) - 1, n).round().astype(int))]
    out: dict[str, Any] = {"parents": ov.parents, "frames": sample.astype(int).tolist(), "cameras": []}
    out["untracked"] = ov.untracked
    out["sampled_every"] = round(len(cand) / max(1, len(sample)), 2)
    for cam in ov.cams:
        size = inp.rig[cam].size_wh if inp.rig is not None and cam in inp.rig.names else None
        d = inp.detections[cam]
        if size is None:
            size = d.image_size_wh
        if size is None:
            xy = d.xy_px[np.isfinite(d.xy_px)]
            size = (
                (int(np.nanmax(d.xy_px[..., 0]) + 1), int(np.nanmax(d.xy_px[..., 1]) + 1))
                if xy.size
                else (640, 480)
            )
        view: dict[str, Any] = {
            "name": cam,
            "size_wh": [int(size[0]), int(size[1])],
            "video": _shown_path(videos[cam], inp.lay) if cam in videos else None,
            "images": [],
            "image_wh": None,
        }
        pr = ov.project(cam, sample)
        view["overlays"] = [_frame_overlay(ov, cam, int(f), pr[i]) for i, f in enumerate(sample)]
        if cam in videos:
            imgs = _read_frames(videos[cam], sample.astype(int).tolist())
            enc = []
            for f in sample:
                img = imgs.get(int(f))
                if img is None:
                    enc.append(None)
                    continue
                uri, wh = _encode_jpeg(img, cfg)
                enc.append(uri)
                view["image_wh"] = wh
                view["video_wh"] = [int(img.shape[1]), int(img.shape[0])]
            view["images"] = enc
            if not imgs:
                view["note"] = f"video {view['video']} could not be read: detections on a blank canvas"
        else:
            view["note"] = "no video found for this camera: detections and reprojections on a blank canvas"
        out["cameras"].append(view)
    return out


# ----------------------------------------------------------------------------- warnings and problems


def warnings_path(root: Path, stage: str) -> Path:
    """Where the runner keeps the warnings a stage logged when it last ran (a JSON list of strings)."""
    return Path(root) / ".roomcap" / "warnings" / f"{stage}.json"


def _warnings(lay: SessionLayout) -> list[dict[str, str]]:
    """The warnings the pipeline logged while making the current outputs, by stage (the runner saves
    them per stage; sessions processed before that show the last run's summary)."""

    out: list[dict[str, str]] = []
    seen = set()
    for stage in STAGES:
        try:
            msgs = json.loads(warnings_path(lay.root, stage).read_text())
        except (OSError, json.JSONDecodeError):
            continue
        for m in msgs if isinstance(msgs, list) else []:
            if str(m) not in seen:
                seen.add(str(m))
                out.append({"stage": stage, "message": str(m)})
    if not out:
        try:
            for m in json.loads((lay.root / ".roomcap" / "summary.json").read_text()).get("warnings", []):
                if str(m) not in seen:
                    seen.add(str(m))
                    out.append({"stage": "", "message": str(m)})
        except (OSError, json.JSONDecodeError, AttributeError):
            pass
    return out


def _problem(level: str, title: str, detail: str, action: str) -> dict[str, str]:
    return {"level": level, "title": title, "detail": detail, "action": action}


def _problems(data: dict[str, Any], inp: _Inputs) -> list[dict[str, str]]:
    """A plain-language list of what looks wrong in this session and what to do about each."""
    P: list[dict[str, str]] = []
    rig, T, Q, V = data["rig"], data["tracks"], data["quality"], data["views"]
    if rig is None:
        P.append(
            _problem(
                "error",
                "No calibration",
                "calib/rig.toml is missing.",
                "Calibrate the rig or import a calibration.",
            )
        )
    elif rig.get("error"):
        P.append(_problem("error", "Calibration unreadable", rig["error"], "Fix or replace calib/rig.toml."))
    for cam, msg in (inp.detections_error or {}).items():
        P.append(_problem("error", f"Detections of {cam} unreadable", msg, "Rerun the keypoints stage."))
    if not inp.detections:
        P.append(
            _problem(
                "error", "No 2D detections", "keypoints/ has no detection files.", "Run the keypoints stage."
            )
        )
    for name, err in (("poses3d.npz", inp.poses_error), (inp.tracks_name, inp.tracks_error)):
        if err:
            P.append(
                _problem("error", f"{name} unreadable", err, "Rerun the stage that writes it (--force).")
            )
    if T is None and not inp.tracks_error:
        P.append(
            _problem(
                "error", "No tracks", "track/tracks.npz is missing.", "Run the triangulate and track stages."
            )
        )
    # detection rates: a camera that rarely finds anyone while the others do
    rates = {
        c: float(np.mean(np.asarray(d["people"]) > 0)) if d["people"] else 0.0
        for c, d in data["detections"].items()
    }
    if len(rates) > 1:
        best = max(rates.values())
        for c, r in rates.items():
            if best > 0.3 and r < 0.5 * best:
                P.append(
                    _problem(
                        "warning",
                        f"{c} rarely sees anyone",
                        f"people were detected in {100 * r:.0f}% of its frames (best camera: "
                        f"{100 * best:.0f}%).",
                        f"Look at {c}'s filmstrip: if the room is outside its view, aim it at the capture "
                        "area; if people "
                        "are visible but not detected, check focus, exposure and that the lens is not "
                        "covered.",
                    )
                )
    if Q and not Q.get("error"):
        cams = [c for c in Q["cameras"] if c["mean_px"] is not None]
        if cams:
            med = float(np.median([c["mean_px"] for c in cams]))
            for c in cams:
                others = [o["mean_px"] for o in cams if o is not c]
                ref = float(np.median(others)) if others else med
                if c["mean_px"] > 8.0 or (c["mean_px"] > 4.0 and c["mean_px"] > 2.0 * ref):
                    P.append(
                        _problem(
                            "warning",
                            f"{c['name']}: large reprojection error",
                            f"the 3D lands {c['mean_px']:.1f} px from {c['name']}'s detections on average "
                            f"(other cameras {ref:.1f} px).",
                            "Compare the dots (reprojection) with the skeletons (detections) in "
                            f"{c['name']}'s filmstrip: "
                            "a steady offset means the camera moved or its calibration is off (recalibrate "
                            "it); an "
                            "offset that follows the motion means its video is out of sync (fix the sync "
                            "offset).",
                        )
                    )
            for c in Q["cameras"]:
                if len(Q["cameras"]) > 2 and (c["share"] or 0) < 0.2 and Q["n_joints_3d"] > 0:
                    P.append(
                        _problem(
                            "warning",
                            f"{c['name']} is rarely used",
                            f"its view went into {100 * (c['share'] or 0):.0f}% of the triangulated joints.",
                            "It may see little of the capture area, or its detections disagree with the "
                            "other cameras "
                            "(calibration or sync): check its filmstrip.",
                        )
                    )
        if Q.get("per_camera_note"):
            P.append(_problem("info", "No per-camera errors", Q["per_camera_note"], "Rerun triangulate."))
        pv = [v for v in Q["per_joint_views"] if v is not None]
        if pv and float(np.mean(pv)) < 2.5 and len(Q["cameras"]) > 2:
            P.append(
                _problem(
                    "info",
                    "Joints seen by few cameras",
                    f"a triangulated joint was seen by {float(np.mean(pv)):.1f} cameras on average.",
                    "Two views give little redundancy against a wrong detection: add cameras or aim them "
                    "so each "
                    "part of the room is seen by three or more.",
                )
            )
        pj = Q["per_joint_mean_px"]
        vals = [v for v in pj if v is not None]
        if vals:
            m = float(np.mean(vals))
            worst = [Q["joint_names"][j] for j, v in enumerate(pj) if v is not None and v > max(2.0 * m, 6.0)]
            if worst:
                P.append(
                    _problem(
                        "info",
                        "Some joints fit worse than the rest",
                        f"{', '.join(worst)}: more than twice the mean error ({m:.1f} px).",
                        "Usual for fast or often occluded joints (wrists, ankles); if it is a hip or "
                        "shoulder, the 2D "
                        "model may confuse left and right or the skeleton definitions differ between views.",
                    )
                )
    if T is not None:
        ev = T["events"]
        fps_full = T["fps"] * T["step"]
        for k, tid in enumerate(T["track_id"]):
            pres, un = ev["present_frames"][k], ev["unobserved_frames"][k]
            if pres and un / pres > 0.1 and un / fps_full >= 0.5:
                P.append(
                    _problem(
                        "info",
                        f"id {tid} carried without being seen",
                        f"{un / fps_full:.1f} s of its {pres / fps_full:.1f} s ({100 * un / pres:.0f}%) "
                        "were predicted or "
                        "interpolated, not observed.",
                        "Its positions there are guesses (hatched in the timeline): if it was in view, the "
                        "detections "
                        "missed it (occlusion, low light); if not, more camera coverage would help.",
                    )
                )
        jumps = ev["jumps"]
        if jumps:
            swaps = [j for j in jumps if j["swap_with"] is not None]
            where = ", ".join(
                f"id {j['id']} at frame {j['frame']} ({j['dist_m']:.2f} m"
                + (f", to where id {j['swap_with']} was" if j["swap_with"] is not None else "")
                + ")"
                for j in jumps[:6]
            )
            P.append(
                _problem(
                    "warning",
                    f"{len(jumps)} sudden jump{'s' if len(jumps) > 1 else ''}"
                    + (
                        f", {len(swaps)} suspected identity swap{'s' if len(swaps) > 1 else ''}"
                        if swaps
                        else ""
                    ),
                    where + (" …" if len(jumps) > 6 else "") + ".",
                    "Check those frames in the filmstrips (red marks on the timeline): if two people "
                    "crossed, their "
                    "identities may have been exchanged; the particle tracker (--tracker particle) keeps "
                    "identities "
                    "better through crossings. A jump of one person alone is usually a wrong 3D pose (bad "
                    "association).",
                )
            )
        people = (
            max((sum(1 for v in col if v) for col in zip(*T["present"], strict=True)), default=0)
            if T["present"]
            else 0
        )
        if people and len(T["track_id"]) > 2 * people + 1:
            P.append(
                _problem(
                    "info",
                    "Identities fragmented",
                    f"{len(T['track_id'])} tracks for at most {people} people at once.",
                    "People lost and found again get new ids: check the timeline for short tracks; longer "
                    "occlusion "
                    "handling (tracker options) or more coverage helps.",
                )
            )
    figs = (rig or {}).get("figures") or {}
    if figs.get("unit") == "px":
        for cam, f in figs.get("cameras", {}).items():
            for key in ("intrinsic_rms_px", "extrinsic_rms_px"):
                if key in f and f[key] > 1.0:
                    P.append(
                        _problem(
                            "warning",
                            f"{cam}: calibration {key.split('_')[0]} RMS {f[key]:.2f} px",
                            "above 1 px, its 3D will be less accurate.",
                            "Recalibrate with more board views covering the whole image.",
                        )
                    )
    size = [
        w["message"] for w in data["warnings"] if "calibration" in w["message"] and "video" in w["message"]
    ]
    if size:
        P.append(
            _problem(
                "warning",
                "Video size differs from the calibration"
                + (f" ({len(size)} cameras)" if len(size) > 1 else ""),
                "; ".join(size),
                "The keypoints are used as they are (codec padding). If the overlays look shifted or "
                "scaled, recalibrate at the video's resolution.",
            )
        )
    for w in data["warnings"]:
        if "differ in length" in w["message"]:
            P.append(
                _problem(
                    "warning",
                    "Videos of different length",
                    w["message"],
                    "Check the sync: trim the videos to a common start.",
                )
            )
    if V:
        for c in V["cameras"]:
            if c.get("note") and c["note"].startswith("video") and "could not be read" in c["note"]:
                P.append(
                    _problem("info", f"{c['name']}: video unreadable", c["note"], "Check the video file.")
                )
    return P


# ----------------------------------------------------------------------------- the page


def _provenance(lay: SessionLayout) -> list[dict[str, Any]]:

    rows = []
    for stage in STAGES:
        p = lay.root / ".roomcap" / "provenance" / f"{stage}.json"
        if not p.exists():
            continue
        try:
            rec = json.loads(p.read_text())
            rows.append(
                {
                    "stage": rec["stage"],
                    "version": rec["version"],
                    "model_sha256": rec.get("model_sha256", "")[:12],
                    "inputs": len(rec["inputs"]),
                }
            )
        except (json.JSONDecodeError, KeyError):
            continue
    return rows


def _forecast_data(lay: SessionLayout) -> dict[str, Any] | None:
    path = lay.root / "forecast" / "preview.npz"
    if not path.exists():
        return None
    try:
        d = load_npz(path)
    except Exception:
        return None
    keys = {"xyz_m", "track_id", "start_index"}
    if not keys <= set(d):
        return None
    xyz = d["xyz_m"]
    if xyz.ndim != 4:  # (K,H,J,3) expected
        return None
    return {
        "xyz": _r(xyz),
        "track_id": d["track_id"].tolist(),
        "start_index": int(d["start_index"]),
        "model": str(d.get("model", "")),
        "fps": float(d["fps"]) if "fps" in d else None,
    }


def collect(lay: SessionLayout, title: str, config: ReportConfig | None = None) -> dict[str, Any]:
    """Everything the page shows, as plain data (the JSON embedded in the page)."""
    cfg = config or ReportConfig()
    t0 = time.perf_counter()
    meta = {}
    if lay.session_toml.exists():
        try:
            meta = load_toml(lay.session_toml)
        except Exception:
            meta = {}
    inp = _load(lay)
    data: dict[str, Any] = {
        "title": title,
        "rig": _rig_data(inp),
        "detections": _detection_rates(inp),
        "tracks": _tracks_data(inp, cfg),
        "quality": _quality(inp, cfg),
        "forecast": _forecast_data(lay),
        "provenance": _provenance(lay),
        "warnings": _warnings(lay),
        # redacted again: a session recorded by an older version may hold a camera URL with its password
        "session": {
            k: redact(v) if isinstance(v, str) else v
            for k, v in meta.items()
            if isinstance(v, (str, int, float))
        },
    }
    t1 = time.perf_counter()
    data["views"] = _views_data(inp, cfg)
    data["problems"] = _problems(data, inp)
    # (no timings in the page: the same outputs make the same report, byte for byte)
    log.info("report data %.2f s, camera views %.2f s", t1 - t0, time.perf_counter() - t1)
    return data


def _asset(name: str) -> str:
    return (_ASSETS / name).read_text(encoding="utf-8")


def render(data: dict[str, Any]) -> str:
    payload = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    return (
        _asset("report.html")
        .replace("__TITLE__", html.escape(data["title"]))
        .replace("__STYLE__", _asset("report.css"))
        .replace(
            "__SCRIPT__", (_asset("viewer3d.js") + _asset("report.js")).replace("</script", "<\\/script")
        )
        .replace("__DATA__", payload)
    )


def write_report(lay: SessionLayout, title: str = "", config: ReportConfig | None = None) -> Path:
    """Write ``report/report.html`` (atomically); returns its path."""
    atomic_write_text(lay.report_html, render(collect(lay, title or lay.root.name, config)))
    return lay.report_html


# ----------------------------------------------------------------------------- overlay videos


def _bgr(k: int) -> tuple[int, int, int]:
    h = _COLORS[k % len(_COLORS)].lstrip("#")
    r, g, b = (int(h[i : i + 2], 16) for i in (0, 2, 4))
    return (b, g, r)


# the page's identity colours (report.js COLORS), the same track gets the same colour in the videos
_COLORS = (
    "#e6194b #3cb44b #4363d8 #f58231 #911eb4 #42d4f4 #f032e6 #bfef45 #fabed4 #469990 #dcbeff #9a6324 "
    "#fffac8 #800000 #aaffc3 #808000"
).split()


def draw_overlay(img: np.ndarray, det: np.ndarray, who: np.ndarray, proj: np.ndarray, parents) -> np.ndarray:
    """Draw detections (P,J,2) as thick skeletons in their track's colour (grey: no track) and the
    reprojected tracks (K,J,2) as thin white-edged skeletons with dots, on a BGR image (in place)."""
    import cv2

    def pt(p):
        return (int(round(p[0])), int(round(p[1])))

    s = max(1, round(max(img.shape[:2]) / 700))
    for d, k in zip(det, who, strict=True):
        col = _bgr(int(k)) if k >= 0 else (170, 170, 170)
        for j, p in enumerate(parents):
            if p >= 0 and np.isfinite(d[j]).all() and np.isfinite(d[p]).all():
                cv2.line(img, pt(d[j]), pt(d[p]), col, 3 * s, cv2.LINE_AA)
    for k, q in enumerate(proj):
        col = _bgr(k)
        for j, p in enumerate(parents):
            if p >= 0 and np.isfinite(q[j]).all() and np.isfinite(q[p]).all():
                cv2.line(img, pt(q[j]), pt(q[p]), (255, 255, 255), 1 * s + 1, cv2.LINE_AA)
        for j in range(len(q)):
            if np.isfinite(q[j]).all():
                cv2.circle(img, pt(q[j]), 2 * s + 1, col, -1, cv2.LINE_AA)
                cv2.circle(img, pt(q[j]), 2 * s + 1, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def write_overlay_videos(
    lay: SessionLayout,
    out_dir: Path | None = None,
    config: ReportConfig | None = None,
    progress: Progress | None = None,
) -> list[Path]:
    """Every camera's video with the detections and the reprojected tracks drawn on every frame, as
    ``report/overlay/<cam>.mp4`` (MP4V; a camera without a video: on a dark canvas of its image size).
    Returns the paths written."""
    import cv2

    cfg = config or ReportConfig()
    inp = _load(lay)
    if not inp.detections:
        raise FormatError(
            lay.keypoints_dir, None, "no detection files to draw.", "Run the keypoints stage first."
        )
    ov = _Overlay(inp, cfg)
    frames = ov.frames()
    videos = _video_paths(lay, ov.cams)
    out_dir = Path(out_dir) if out_dir is not None else lay.report_html.parent / "overlay"
    out_dir.mkdir(parents=True, exist_ok=True)
    fps = float(inp.tracks.fps) if inp.tracks is not None else 25.0
    written = []
    total = len(ov.cams) * len(frames)
    done = 0
    for cam in ov.cams:
        cap = cv2.VideoCapture(str(videos[cam])) if cam in videos else None
        if cap is not None and cap.isOpened():
            fps = float(cap.get(cv2.CAP_PROP_FPS)) or fps
            size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        else:
            cap = None
            size = (
                tuple(inp.rig[cam].size_wh) if inp.rig is not None and cam in inp.rig.names else (1280, 720)
            )
        path = out_dir / f"{cam}.mp4"
        with atomic_path(path, suffix=".mp4") as tmp:
            wr = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
            if not wr.isOpened():
                raise OSError(f"cannot write {path}: OpenCV has no MP4 writer here")
            try:
                i = 0
                for start in range(0, len(frames), 256):
                    chunk = frames[start : start + 256]
                    proj = ov.project(cam, chunk)
                    for n, f in enumerate(chunk):
                        f = int(f)
                        img = None
                        if cap is not None:
                            while i < f and cap.grab():
                                i += 1
                            ok, img = cap.read() if i == f else (False, None)
                            i += 1 if ok else 0
                            if not ok:
                                img = None
                        if img is None:
                            img = np.full((size[1], size[0], 3), 24, np.uint8)
                        det = ov.detections(cam, f)
                        draw_overlay(img, det, ov.match(det, proj[n]), proj[n], ov.parents)
                        cv2.putText(
                            img,
                            f"{cam}  frame {f}",
                            (12, 32),
                            cv2.FONT_HERSHEY_SIMPLEX,
                            0.9,
                            (255, 255, 255),
                            2,
                        )
                        wr.write(img)
                        done += 1
                        if progress is not None:
                            progress("overlay videos", done, total)
            finally:
                wr.release()
        if cap is not None:
            cap.release()
        written.append(path)
        log.info("overlay video %s: %d frames", path, len(frames))
    return written


# ----------------------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m pipeline.report",
        description="Write report/report.html for a session folder (and, with --overlay, an overlay video "
        "per camera in report/overlay/) from the outputs already there.",
    )
    p.add_argument("session", type=Path, help="a session output folder (calib/, keypoints/, track/ ...)")
    p.add_argument("--title", default="")
    p.add_argument("--overlay", action="store_true", help="also write report/overlay/<cam>.mp4")
    p.add_argument("--budget-mb", type=float, help="JPEG megabytes of the filmstrips (default 18)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not args.session.is_dir():
        print(f"report: {args.session} is not a folder; pass a session output folder.", file=sys.stderr)
        return 2
    lay = SessionLayout(args.session)
    cfg = (
        ReportConfig()
        if args.budget_mb is None
        else ReportConfig(image_budget_bytes=int(args.budget_mb * 1e6))
    )
    t0 = time.perf_counter()
    try:
        path = write_report(lay, args.title, cfg)
        print(f"report: {path} ({path.stat().st_size / 1e6:.1f} MB, {time.perf_counter() - t0:.1f} s)")
        if args.overlay:
            paths = write_overlay_videos(lay, config=cfg)
            print(f"overlay videos: {', '.join(str(q) for q in paths)}")
    except (FormatError, OSError, ValueError) as e:
        print(f"report: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
