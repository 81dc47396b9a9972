"""``forecast behaviour sample``: the next M actions and their characteristic 3D poses of every labelled
person of a session.

For each track named in the label file, its labelled actions are the observed steps. A step's
characteristic frame is the frame of greatest articulation inside its label's time range (the quantity the
ch. 3 annotation rule peaks on, ``forecast.characteristic.labels.articulation``, on the track's 3D). The
observed 2D pose of a step is the detection, in the observing camera, nearest to the track's projection at
that frame (the camera that sees the person's steps best, unless ``--camera`` names one). The anchor is the
floor point under the track's pelvis at the last observed step; the forecast poses are written in the room's
frame (metres) by the viewer frame of that anchor, each moved up or down to stand on the floor
(``stand_on_floor``).

Output ``behaviour.npz`` (schema ``behaviour/1``): ``track_id (K,)``, ``labels (A,)``, ``actions (K,M)``
label strings, ``probs (K,M,A)``, ``poses_m (K,M,J,3)``, ``joint_names (J,)``, ``camera (K,)``,
``observed (K,N)`` the labels of the observed steps (``""`` where a track has fewer than N),
``step_time_s (K,N)`` their characteristic times, ``step_start_s``/``step_end_s (K,N)`` their label
ranges (NaN where a track has fewer than N; the report's timeline draws them), ``model``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import SessionLayout
from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import save_npz, schema_tag
from roomcap.forecast.lab.behaviour.data import ACTIONS, JOINTS
from roomcap.forecast.lab.behaviour.geometry import (
    ANKLE_HEIGHT_M,
    make_view,
    plane_features,
    room_context,
    to_world,
)
from roomcap.forecast.lab.behaviour.labels import LabelRow, read_labels
from roomcap.forecast.lab.behaviour.model import SHIPPED, load_checkpoint, rollout
from roomcap.forecast.lab.behaviour.training import Prepared
from roomcap.forecast.lab.characteristic.labels import articulation
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import convert
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate.chunks import parts_dir

log = logging.getLogger(__name__)

SCHEMA, VERSION = "behaviour", 1
MATCH_PX = 80.0  # a detection further than this (mean over joints) from the track's projection is not it


def _session(session) -> tuple[SessionLayout, CameraRig, TrackFile, dict[str, Detections]]:
    lay = SessionLayout(session)
    if not lay.root.is_dir():
        raise InputError(f"{lay.root}: no such session folder")
    if not lay.rig_toml.exists():
        raise InputError(
            f"{lay.root}: the session has no rig ({lay.rig_toml} is missing); the forecast needs the "
            "cameras' calibration: calibrate (`calibrate-run`) or import one (`calibrate-run import`) first"
        )
    rig = CameraRig.load(lay.rig_toml)
    if not lay.tracks.exists() and not parts_dir(lay.tracks).is_dir():
        raise InputError(
            f"{lay.root}: no track file ({lay.tracks}); run the track stage first "
            "(`reprocess SESSION --stages triangulate,track`), then "
            "`forecast behaviour sample SESSION --labels FILE`"
        )
    tracks = TrackFile.load(lay.tracks)
    dets = {}
    for cam in lay.detection_cameras():
        if cam in rig.names:
            dets[cam] = Detections.load(lay.detections(cam))
    if not dets:
        raise InputError(f"{lay.root}: no detections (keypoints/<cam>.npz) of the rig's cameras {rig.names}")
    return lay, rig, tracks, dets


def _lines(rows: list[LabelRow]) -> str:
    """'line 3' or 'lines 3, 5' (the first few, then how many more)."""
    ls = [str(r.line) for r in rows]
    more = f" and {len(ls) - 4} more" if len(ls) > 4 else ""
    return ("line " if len(ls) == 1 else "lines ") + ", ".join(ls[:4]) + more


def _check_labels(rows: list[LabelRow], tracks: TrackFile, known: tuple[str, ...], path) -> None:
    """Every row names a track of the session, a label the model knows, and times where its track has 3D;
    a row that does not gets an InputError naming its line (the file's own checks, ``read_labels``, have
    already named overlapping rows)."""
    ids = set(tracks.track_id.tolist())
    if not ids:
        raise InputError(
            f"{path}: the session's track file holds no tracks; run the track stage first "
            "(`reprocess SESSION --stages triangulate,track`), then "
            "`forecast behaviour sample SESSION --labels FILE`"
        )
    bad = [r for r in rows if r.track_id not in ids]
    if bad:
        raise InputError(
            f"{path}, {_lines(bad)}: track id {bad[0].track_id} matches no track of the session (its "
            f"tracks: {sorted(ids)}); use the ids of track/tracks.npz"
        )
    unknown = [r for r in rows if r.label not in known]
    if unknown:
        raise InputError(
            f"{path}, {_lines(unknown)}: label {unknown[0].label!r} is unknown to the model, which knows "
            f"{list(known)}; rename it to the nearest of these (the action set is the training data's, "
            "forecast.behaviour.data.ACTIONS)"
        )
    t_s = (tracks.t_ns - tracks.t_ns[0]) / 1e9
    for r in rows:
        k = int(np.flatnonzero(tracks.track_id == r.track_id)[0])
        inside = (t_s >= r.start_s) & (t_s <= r.end_s) & np.isfinite(tracks.xyz_m[:, k, 0, 0])
        if not inside.any():
            raise InputError(
                f"{path}, line {r.line}: track {r.track_id} has no 3D between {r.start_s} and {r.end_s} s "
                f"(the session spans 0 .. {t_s[-1]:.2f} s; the track is seen "
                f"{_span(t_s, tracks.xyz_m[:, k, 0, 0])}); fix the times"
            )


def _span(t_s: np.ndarray, x: np.ndarray) -> str:
    ok = np.flatnonzero(np.isfinite(x))
    return "never" if len(ok) == 0 else f"{t_s[ok[0]]:.2f} .. {t_s[ok[-1]]:.2f} s"


def _char_frame(xyz: np.ndarray, names, fps: float, frames: np.ndarray) -> int:
    """The frame of greatest articulation among ``frames`` of one track xyz (T,J,3) (gaps filled)."""
    x = xyz[frames].astype(np.float64)
    ok = np.isfinite(x).all((1, 2))
    if ok.sum() < 3:
        return int(frames[np.flatnonzero(ok)[-1]]) if ok.any() else int(frames[-1])
    idx = np.flatnonzero(ok)
    x = x[idx]
    A, _ = articulation(x, names, fps)
    return int(frames[idx[int(np.argmax(A))]])


def _detection_near(det: Detections, cam, frame: int, X: np.ndarray) -> np.ndarray | None:
    """The body19 2D pose (19,2) in ``det`` at track frame index ``frame`` nearest to the projection of
    X (19,3), or None."""
    hit = np.flatnonzero(det.frame_index == frame)
    if len(hit) == 0:
        return None
    xy, _ = convert(det.xy_px[hit[0]], None, det.skeleton, "body19")  # (P,19,2)
    ok = np.isfinite(X).all(1)
    if not ok.any():
        return None
    proj = np.full((19, 2), np.nan)
    proj[ok] = cam.project(X[ok])
    dist = np.linalg.norm(xy - proj[None], axis=-1)  # (P,19)
    n = np.isfinite(dist).sum(1)
    d = np.where(n > 0, np.nansum(np.nan_to_num(dist, nan=0.0), 1) / np.maximum(n, 1), np.nan)
    if len(d) == 0 or not np.isfinite(d).any() or np.nanmin(d) > MATCH_PX:
        return None
    return xy[int(np.nanargmin(d))]


@dataclass(frozen=True)
class TrackSteps:
    """One person's labelled steps: ``rows`` (sorted), characteristic ``frames`` (track frame rows), the
    matched detections ``xy_px`` ((19,2) body19 distorted px, or None) in ``camera``, and the track's
    ``xyz_m (T,19,3)``."""

    rows: list[LabelRow]
    frames: list[int]
    xy_px: list[np.ndarray | None]
    camera: str
    xyz_m: np.ndarray


def track_steps(
    tracks: TrackFile,
    dets: dict[str, Detections],
    rig: CameraRig,
    rows: list[LabelRow],
    camera: str | None = None,
    last: int | None = None,
) -> TrackSteps:
    """The steps of one track's label rows (the ``last`` ones): characteristic frames, and the detections in
    the camera that sees them best (or ``camera``)."""
    tj = list(tracks.joint_names)
    k = int(np.flatnonzero(tracks.track_id == rows[0].track_id)[0])
    xyz = tracks.xyz_m[:, k][:, [tj.index(n) for n in JOINTS]]
    t_s = (tracks.t_ns - tracks.t_ns[0]) / 1e9
    mine = sorted(rows, key=lambda r: r.start_s)
    mine = mine[-last:] if last else mine
    frames = [
        _char_frame(xyz, JOINTS, tracks.fps, np.flatnonzero((t_s >= r.start_s) & (t_s <= r.end_s)))
        for r in mine
    ]
    cand = [camera] if camera else sorted(dets)
    found = {
        c: [_detection_near(dets[c], rig[c], int(tracks.frame_index[f]), xyz[f]) for f in frames]
        for c in cand
    }
    best = max(cand, key=lambda c: sum(int(np.isfinite(p).all(1).sum()) for p in found[c] if p is not None))
    return TrackSteps(mine, frames, found[best], best, xyz)


def session_windows(session, labels, n_obs: int, m: int, names: tuple[str, ...] = JOINTS) -> Prepared:
    """Training / evaluation windows from a user's session and its label file: every run of n_obs + m
    consecutive labelled steps of one track, observed in that track's best camera; the targets' 2D are
    the detections, the 3D (evaluation only) the track file's."""
    lay, rig, tracks, dets = _session(session)
    rows = read_labels(labels)
    _check_labels(rows, tracks, ACTIONS, labels)
    pel = JOINTS.index("pelvis")
    jidx = [JOINTS.index(n) for n in names]
    L = n_obs + m
    parts: list[tuple] = []
    for tid in sorted({r.track_id for r in rows}):
        st = track_steps(tracks, dets, rig, [r for r in rows if r.track_id == tid])
        if len(st.rows) < L:
            continue
        cam = rig[st.camera]
        und = np.stack(
            [cam.undistort_px(p) if p is not None else np.full((19, 2), np.nan) for p in st.xy_px]
        ).astype(np.float64)
        for a in range(len(st.rows) - L + 1):
            f = st.frames[a : a + L]
            g = np.array([st.xyz_m[f[n_obs - 1], pel, 0], st.xyz_m[f[n_obs - 1], pel, 1], 0.0])
            parts.append(
                (cam, g, und[a : a + L], [ACTIONS.index(r.label) for r in st.rows[a : a + L]], st.xyz_m[f])
            )
    if not parts:
        raise InputError(f"{labels}: no track has {L} labelled steps (n_obs {n_obs} + M {m}); label more")
    K = np.stack([p[0].K for p in parts])
    R = np.stack([p[0].R for p in parts])
    t = np.stack([p[0].t for p in parts])
    view = make_view(K, R, t, np.stack([p[1] for p in parts]))
    und = np.stack([p[2] for p in parts])
    feats = plane_features(view, und[:, :n_obs])[:, :, jidx]
    X = np.stack([p[4] for p in parts])[:, n_obs:][:, :, jidx] - view.g[:, None, None]
    return Prepared(
        tuple(names),
        view,
        np.nan_to_num(feats).astype(np.float32),
        np.isfinite(feats).all(-1),
        und[:, :n_obs][:, :, jidx].astype(np.float32),
        np.asarray([p[3] for p in parts], np.int64),
        und[:, n_obs:][:, :, jidx].astype(np.float32),
        np.einsum("sij,smnj->smni", view.V, X).astype(np.float32),
    )


def stand_on_floor(W: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """Poses (...,J,3) in the room moved up or down so that the lower ankle is at ``ANKLE_HEIGHT_M``: the
    2D loss is neck-centred (the seed's translation removal), so it leaves a forecast pose's height above
    the floor free, and only the critic (which sees it) holds it. Without ankles (the 9-joint setting) the
    poses are returned as they are."""
    if "left_ankle" not in names or "right_ankle" not in names:
        return W
    ank = W[..., [names.index("left_ankle"), names.index("right_ankle")], 2].min(-1)
    out = W.copy()
    out[..., 2] += (ANKLE_HEIGHT_M - ank)[..., None]
    return out


def _model(checkpoint, model: str):
    """The variant ``model`` of the checkpoint and its config, or a clear error."""
    try:
        gens, cfgs, _ = load_checkpoint(checkpoint)
    except FileNotFoundError:
        raise InputError(
            f"{checkpoint}: no such checkpoint; train one with `forecast behaviour train`"
        ) from None
    except FormatError as e:
        raise InputError(str(e)) from None
    if model not in gens:
        raise InputError(f"--model {model!r}: the checkpoint holds {sorted(gens)}")
    return gens[model], cfgs[model]


@dataclass
class Observed:
    """The model's inputs for K tracks (``ids``): the last N labelled steps, right-aligned (a track with
    fewer keeps "unknown" actions and unseen poses before its first), and each track's view and camera."""

    ids: list[int]
    feats: np.ndarray  # (K,N,J,2) plane features, 0 unseen
    seen: np.ndarray  # (K,N,J) bool
    acts: np.ndarray  # (K,N) action indices, len(ACTIONS) = unknown
    observed: np.ndarray  # (K,N) label strings, "" before a track's first
    step_t: np.ndarray  # (K,N) characteristic times (s), NaN before a track's first
    views: list
    cams: list[str]
    step_start: np.ndarray | None = None  # (K,N) the label ranges (s), NaN before a track's first
    step_end: np.ndarray | None = None


def _observe_tracks(tracks, dets, rig, rows, camera, n_obs: int, names: tuple[str, ...]) -> Observed:
    """The observed steps of every labelled track: characteristic frames, matched detections in the best
    camera (or ``camera``) as plane features of the viewer frame anchored under the last step's pelvis."""
    t_s = (tracks.t_ns - tracks.t_ns[0]) / 1e9
    N = n_obs
    jidx = [JOINTS.index(n) for n in names]
    pel = JOINTS.index("pelvis")
    ids = sorted({r.track_id for r in rows})
    K = len(ids)
    ob = Observed(
        ids,
        np.zeros((K, N, len(names), 2), np.float32),
        np.zeros((K, N, len(names)), bool),
        np.full((K, N), len(ACTIONS), np.int64),  # "unknown" where a track has fewer than N labels
        np.full((K, N), "", dtype=object),
        np.full((K, N), np.nan),
        [],
        [],
        np.full((K, N), np.nan),
        np.full((K, N), np.nan),
    )
    for i, tid in enumerate(ids):
        st = track_steps(tracks, dets, rig, [r for r in rows if r.track_id == tid], camera, last=N)
        cam = rig[st.camera]
        last = st.xyz_m[st.frames[-1]]
        view = make_view(cam.K[None], cam.R[None], cam.t[None], np.array([[last[pel, 0], last[pel, 1], 0.0]]))
        off = N - len(st.rows)
        for s, (r, f, p) in enumerate(zip(st.rows, st.frames, st.xy_px, strict=True)):
            ob.acts[i, off + s] = ACTIONS.index(r.label)
            ob.observed[i, off + s] = r.label
            ob.step_t[i, off + s] = t_s[f]
            ob.step_start[i, off + s], ob.step_end[i, off + s] = r.start_s, r.end_s
            if p is None:
                continue
            pf = plane_features(view, cam.undistort_px(p)[None, None])[0, 0][jidx]
            ok = np.isfinite(pf).all(1)
            ob.feats[i, off + s][ok] = pf[ok]
            ob.seen[i, off + s] = ok
        ob.views.append(view)
        ob.cams.append(st.camera)
    return ob


def _forecast(gen, cfg, ob: Observed) -> tuple[np.ndarray, np.ndarray]:
    """The rollout of M steps -> action probabilities (K,M,A), poses (K,M,J,3) in the room, on the floor."""
    V = np.concatenate([v.V for v in ob.views])
    G = np.concatenate([v.g for v in ob.views])
    C = np.concatenate([v.c for v in ob.views])
    Vt, Gt = torch.as_tensor(V, dtype=torch.float32), torch.as_tensor(G, dtype=torch.float32)
    with torch.no_grad():
        lg, P = rollout(
            gen,
            torch.from_numpy(ob.feats),
            torch.from_numpy(ob.acts),
            torch.from_numpy(ob.seen),
            torch.as_tensor(C, dtype=torch.float32),
            cfg.m,
            feed_pose=cfg.use_pose,
            feed_action=cfg.use_action,
            room=room_context(Vt, Gt),  # the floor under the track's pelvis, in the rig's frame
        )
        probs = torch.softmax(lg, -1).numpy()
        W = to_world(P, Vt, Gt).numpy()
    return probs, stand_on_floor(W, cfg.joint_names)


def run_sample(
    session, labels, out=None, *, checkpoint=SHIPPED, camera: str | None = None, model: str = "full"
) -> Path:
    """Forecast every labelled track of ``session`` and write ``behaviour.npz`` (the module's schema)."""
    gen, cfg = _model(checkpoint, model)
    lay, rig, tracks, dets = _session(session)
    if camera is not None and camera not in dets:
        raise InputError(f"--camera {camera!r}: the session has detections of {sorted(dets)}")
    rows = read_labels(labels)
    _check_labels(rows, tracks, ACTIONS, labels)
    missing = [n for n in JOINTS if n not in list(tracks.joint_names)]
    if missing:
        raise InputError(f"{lay.tracks}: the tracks lack the joints {missing}; the forecaster needs body19")
    ob = _observe_tracks(tracks, dets, rig, rows, camera, cfg.n_obs, cfg.joint_names)
    probs, W = _forecast(gen, cfg, ob)
    out = Path(out) if out else lay.root / "forecast" / "behaviour.npz"
    out.parent.mkdir(parents=True, exist_ok=True)
    save_npz(
        out,
        {
            "schema": schema_tag(SCHEMA, VERSION),
            "track_id": np.asarray(ob.ids, np.int64),
            "labels": np.asarray(ACTIONS),
            "actions": np.asarray([[ACTIONS[j] for j in row] for row in probs.argmax(-1)]),
            "probs": probs.astype(np.float32),
            "poses_m": W.astype(np.float32),
            "joint_names": np.asarray(cfg.joint_names),
            "camera": np.asarray(ob.cams),
            "observed": ob.observed.astype(str),
            "step_time_s": ob.step_t,
            "step_start_s": ob.step_start,
            "step_end_s": ob.step_end,
            "model": np.asarray(f"{Path(checkpoint).name}:{model}"),
        },
    )
    return out
