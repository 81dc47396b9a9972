"""Per camera filmstrips for the page: video frames (JPEG) with the detections and the reprojected tracks.

Hands (a 2D layout ``*_hands``, a whole-body track with the 42 hand joints): each overlay frame also has
``hdet`` / ``hproj``, per person the 44 points of :data:`HAND2D` (the two wrists, then the hands'
joints), drawn with ``hand_parents`` (the hand roots hang from the wrists); absent without hands.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.capture.session import VIDEO_SUFFIXES, SessionLayout
from roomcap.keypoints.skeletons import CANONICAL, HAND_BONES, HANDS, convert, get_skeleton
from roomcap.pipeline.report.inputs import ReportConfig, _f, _Inputs
from roomcap.triangulate.dlt import DLTConfig


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


HAND2D = ("left_wrist", "right_wrist") + HANDS
_HP = {c: p for p, c in HAND_BONES} | {"left_hand_root": "left_wrist", "right_hand_root": "right_wrist"}
HAND2D_PARENTS = [HAND2D.index(_HP[n]) if n in _HP else -1 for n in HAND2D]


def _pick(a: np.ndarray, names, wanted) -> np.ndarray:
    """``a (..., J, D)`` in the layout ``names`` -> ``(..., len(wanted), D)``, NaN for a name it lacks."""
    idx = [list(names).index(n) if n in names else -1 for n in wanted]
    out = np.asarray(a, np.float64)[..., [max(i, 0) for i in idx], :]
    out[..., [k for k, i in enumerate(idx) if i < 0], :] = np.nan
    return out


def _has_hands(names) -> bool:
    return all(n in names for n in HANDS)


class _Overlay:
    """2D detections (body19, as detected: distorted pixels) and the tracks reprojected into each camera
    (with the lens model), per session frame; detections take the colour of the track they match."""

    def __init__(self, inp: _Inputs, cfg: ReportConfig):

        self.cfg = cfg
        self.rig = inp.rig
        self.cams = [c for c in (inp.rig.names if inp.rig is not None else []) if c in inp.detections]
        self.cams += [c for c in inp.detections if c not in self.cams]
        self.det = {}
        self.hdet: dict[str, np.ndarray] = {}  # cam -> (F,P,44,2) wrists and hands (HAND2D)
        min_score = DLTConfig().min_score  # the joints the triangulation would use
        for cam in self.cams:
            d = inp.detections[cam]
            xy, sc = convert(d.xy_px, d.score, d.skeleton, "body19")
            xy = np.where((sc >= min_score)[..., None], xy, np.nan)
            self.det[cam] = ({int(f): i for i, f in enumerate(d.frame_index)}, xy)
            names2d = get_skeleton(d.skeleton).joint_names
            if _has_hands(names2d):  # the hands of the same people, with their wrists
                hxy = np.where((np.asarray(d.score) >= min_score)[..., None], np.asarray(d.xy_px), np.nan)
                self.hdet[cam] = _pick(hxy, names2d, HAND2D)
        self.parents = list(CANONICAL.parents)
        tf = inp.tracks
        self.untracked = tf is None
        body = CANONICAL.joint_names
        self.hxyz = None
        if tf is not None and all(n in tf.joint_names for n in body):  # body19, or a whole body by name
            X = np.asarray(tf.xyz_m, np.float64)
            self.xyz, self.fi, self.ids = _pick(X, tf.joint_names, body), np.asarray(tf.frame_index), None
            if _has_hands(tf.joint_names):
                self.hxyz = _pick(X, tf.joint_names, HAND2D)
        elif inp.poses is not None:  # no track file: the per-frame 3D poses, colour by slot
            p = inp.poses
            X = np.asarray(p.xyz_m, np.float64)
            names = tuple(p.joint_names)
            self.xyz = X if names == body else _pick(X, names, body)
            self.fi = np.asarray(p.frame_index)
            if _has_hands(names):
                self.hxyz = _pick(X, names, HAND2D)
            self.untracked = True
        else:
            self.xyz, self.fi = np.zeros((0, 0, len(CANONICAL.joint_names), 3)), np.zeros(0, np.int64)
        self.hands = bool(self.hdet) or self.hxyz is not None
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

    def project(self, cam: str, frames: np.ndarray, hands: bool = False) -> np.ndarray:
        """(n,K,J,2) pixels of the 3D at ``frames`` in ``cam`` (``hands``: of the 44 :data:`HAND2D` points);
        NaN where unknown or behind the camera."""
        src = self.hxyz if hands else self.xyz
        if src is None:
            src = np.zeros(self.xyz.shape[:2] + (len(HAND2D), 3))
        K, J = src.shape[1:3]
        out = np.full((len(frames), K, J, 2), np.nan)
        if self.rig is None or cam not in self.rig.names or K == 0:
            return out
        rows = np.asarray([self.row.get(int(f), -1) for f in frames])
        have = rows >= 0
        if have.any():
            X = src[rows[have]].reshape(-1, 3)
            out[have] = self.rig[cam].project(X).reshape(int(have.sum()), K, J, 2)
        return out

    def detections(self, cam: str, frame: int, hands: bool = False) -> np.ndarray:
        """(P,19,2) the people detected in ``cam`` at ``frame`` (those with a body joint); ``hands``: their
        (P,44,2) :data:`HAND2D` points instead (NaN for a layout without hands)."""
        idx, xy = self.det[cam]
        i = idx.get(int(frame))
        if i is None:
            return np.zeros((0, len(HAND2D) if hands else xy.shape[2], 2))
        d = xy[i]
        keep = np.isfinite(d[..., 0]).any(-1)
        if not hands:
            return d[keep]
        h = self.hdet.get(cam)
        return h[i][keep] if h is not None else np.full((int(keep.sum()), len(HAND2D), 2), np.nan)

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


def _frame_overlay(
    ov: _Overlay, cam: str, frame: int, proj: np.ndarray, hproj: np.ndarray | None = None
) -> dict[str, Any]:
    det = ov.detections(cam, frame)
    who = ov.match(det, proj)
    P = [[int(k), _flat(d)] for k, d in zip(who, det, strict=True)]
    R = [[k, _flat(p)] for k, p in enumerate(proj) if np.isfinite(p[..., 0]).any()]
    out = {"det": P, "proj": R, "err": ov.frame_error(cam, frame)}
    if ov.hands:  # a hand shows where one of its joints is known (the wrists alone are the body's)
        hd = ov.detections(cam, frame, hands=True)
        seen = [np.isfinite(h[2:, 0]).any() for h in hd]
        out["hdet"] = [[int(k), _flat(h)] for k, h, s in zip(who, hd, seen, strict=True) if s]
        hp = ov.project(cam, np.asarray([frame]), hands=True)[0] if hproj is None else hproj
        out["hproj"] = [[k, _flat(h)] for k, h in enumerate(hp) if np.isfinite(h[2:, 0]).any()]
    return out


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
        hp = ov.project(cam, probe, hands=True) if ov.hands else [None] * len(probe)
        coord_bytes += sum(
            len(json.dumps(_frame_overlay(ov, cam, int(f), pr[i], hp[i]))) for i, f in enumerate(probe)
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
    if ov.hands:
        out["hand_names"] = list(HAND2D)
        out["hand_parents"] = HAND2D_PARENTS
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
        hp = ov.project(cam, sample, hands=True) if ov.hands else [None] * len(sample)
        view["overlays"] = [_frame_overlay(ov, cam, int(f), pr[i], hp[i]) for i, f in enumerate(sample)]
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
