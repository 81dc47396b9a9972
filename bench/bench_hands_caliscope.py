"""Hands in 3D on real data a peer processed: caliscope's 4-camera MediaPipe Holistic recording.

``../shared/data/caliscope/4_cam_recording_holistic_2d3d`` holds caliscope's 2D (``xy_HOLISTIC.csv``), its
calibration (``config.toml``) and its own triangulation (``xyz_HOLISTIC.csv``). This script imports the 2D
(``keypoints import``), writes a session with caliscope's calibration, triangulates it with ours
(``skeleton = "whole_body"``: body19, the feet and both hands' 21 joints; robust DLT, limb check with hand
bones) and compares, on the hand joints (``left_hand_root`` ... ``right_pinky_finger4``):

- reprojection error (px): ours over the views our DLT kept (what ``poses3d.npz`` reports) against
  caliscope's over every view that saw the point (its DLT keeps all); and both 3D points against the same
  2D observations (every view's point, where both methods have the joint);
- the median distance between our and caliscope's 3D per finger (mm);
- finger bone lengths over time: per bone (40: root to each finger's first joint, then the phalanges) the
  std of its length over the frames where both ends are in 3D (seen by >= 2 views), median over bones (mm);
- how many hand joints that one view alone saw got a 3D point (must be 0: they stay 2D-only).

Ends with one line ``BENCH {json}``. A few seconds on one core.

    PYTHONPATH=.pp python bench/bench_hands_caliscope.py [--shared DIR] [--out DIR] [--raw-sides]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from roomcap.calibrate.formats import import_rig
from roomcap.capture.session import SessionLayout
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.importers import caliscope_point_index, import_2d
from roomcap.keypoints.skeletons import FINGERS, HAND_BONES, HANDS, get_skeleton
from roomcap.track.greedy_stage import track_session_greedy
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate.poses3d import Poses3D
from roomcap.triangulate.stage import triangulate_session

REC = Path("data", "caliscope", "4_cam_recording_holistic_2d3d")


def caliscope_xyz(path: Path, frames: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """caliscope's 3D (T,J,3) on our frames and joints (``xyz_<tracker>.csv``: sync_index, point_id,
    x, y, z)."""
    src = get_skeleton("blazepose33_hands").joint_names
    col = {n: i for i, n in enumerate(names)}
    out = np.full((len(frames), len(names), 3), np.nan)
    row_of = {int(f): i for i, f in enumerate(frames)}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            j = int(caliscope_point_index(np.array([int(r["point_id"])]))[0])
            t = row_of.get(int(r["sync_index"]))
            if j < 0 or t is None or src[j] not in col:
                continue
            out[t, col[src[j]]] = [float(r["x_coord"]), float(r["y_coord"]), float(r["z_coord"])]
    return out


def raw_2d(lay: SessionLayout, cams, frames: np.ndarray, names) -> np.ndarray:
    """The imported 2D (C,T,J,2) in distorted pixels on the frames and joints of ``names``."""
    out = np.full((len(cams), len(frames), len(names), 2), np.nan)
    for c, cam in enumerate(cams):
        d = Detections.load(lay.detections(cam))
        s = get_skeleton(d.skeleton)
        take = [s.joint_names.index(n) if n in s.joint_names else -1 for n in names]
        pos = np.searchsorted(frames, d.frame_index)
        ok = (pos < len(frames)) & (frames[np.minimum(pos, len(frames) - 1)] == d.frame_index)
        for j, k in enumerate(take):
            if k >= 0:
                out[c, pos[ok], j] = d.xy_px[ok, 0, k]
    return out


def reproject(rig, X: np.ndarray) -> np.ndarray:
    """(C,T,J,2) projections of X (T,J,3) with distortion."""
    T, J = X.shape[:2]
    return rig.project(X.reshape(-1, 3)).reshape(len(rig), T, J, 2)


def bone_std_mm(X: np.ndarray, names) -> tuple[float, float, int]:
    """Median over hand bones of the std of the bone's length over time, the median length (mm), and the
    number of bones used."""
    idx = {n: i for i, n in enumerate(names)}
    stds, lens = [], []
    for p, c in HAND_BONES:
        L = np.linalg.norm(X[:, idx[p]] - X[:, idx[c]], axis=-1)
        L = L[np.isfinite(L)]
        if len(L) >= 10:
            stds.append(L.std())
            lens.append(np.median(L))
    return float(np.median(stds) * 1e3), float(np.median(lens) * 1e3), len(stds)


def run(root: Path, out: Path, fix_sides: bool) -> dict:
    xy_csv = root / "recordings" / "recording_1" / "HOLISTIC" / "xy_HOLISTIC.csv"
    lay = SessionLayout(out / "session")
    import_2d(xy_csv, lay.keypoints_dir, hand_sides="body" if fix_sides else "model")
    rig = import_rig(root / "config.toml")
    rig.save(lay.calib_dir / "rig.toml")
    triangulate_session(lay.root, {"skeleton": "whole_body"})
    P = Poses3D.load(lay.poses3d)
    names = tuple(P.joint_names)
    cams = list(P.cameras)
    rig = rig.subset(cams)
    T = P.n_frames
    X = np.full((T, len(names), 3), np.nan)  # one person: the 3D pose with the most joints
    nv = np.zeros((T, len(names)), int)
    err_cam = np.full((T, len(names), len(cams)), np.nan)
    for t in range(T):
        if P.xyz_m.shape[1] == 0:
            break
        k = int(np.argmax(np.isfinite(P.xyz_m[t, :, :, 0]).sum(-1)))
        X[t], nv[t], err_cam[t] = P.xyz_m[t, k], P.n_views[t, k], P.reproj_err_cam_px[t, k]
    Xc = caliscope_xyz(
        root / "recordings" / "recording_1" / "HOLISTIC" / "xyz_HOLISTIC.csv", P.frame_index, names
    )
    # the 2D as caliscope wrote it (the sides of its ids): what both 3D are compared against
    raw_lay = SessionLayout(out / "raw")
    import_2d(xy_csv, raw_lay.keypoints_dir, hand_sides="model")
    raw = raw_2d(raw_lay, cams, P.frame_index, names)
    hand = np.array([n in HANDS for n in names])
    H = np.flatnonzero(hand)
    seen = np.isfinite(raw[..., 0])  # (C,T,J)
    n_seen = seen.sum(0)  # (T,J)
    # our reprojection error on the views used; caliscope's on every view that saw the point
    ours_used = err_cam[:, H][np.isfinite(err_cam[:, H])]
    e_ours = np.linalg.norm(reproject(rig, X) - raw, axis=-1)  # (C,T,J)
    e_cal = np.linalg.norm(reproject(rig, Xc) - raw, axis=-1)
    both = np.isfinite(X[..., 0]) & np.isfinite(Xc[..., 0])  # (T,J)
    cal_all = e_cal[:, :, H][np.isfinite(e_cal[:, :, H])]
    same = both[None, :, H] & seen[:, :, H]
    per_cam = {
        cam: {
            "ours_used_px": float(np.nanmedian(err_cam[:, H, c])),
            "caliscope_px": float(np.nanmedian(e_cal[c][:, H])),
        }
        for c, cam in enumerate(cams)
    }
    # distance to caliscope per finger (both sides together)
    d = np.linalg.norm(X - Xc, axis=-1) * 1e3  # (T,J) mm
    per_finger = {}
    for f in ("hand_root",) + FINGERS:
        cols = [i for i, n in enumerate(names) if n in HANDS and (n.endswith(f) or n[:-1].endswith(f))]
        v = d[:, cols][both[:, cols]]
        per_finger[f] = float(np.median(v)) if len(v) else float("nan")
    body = np.arange(19)
    res = {
        "frames": int(T),
        "hand_joints_seen_2plus_views": int((n_seen[:, H] >= 2).sum()),
        "hand_joints_3d_ours": int(np.isfinite(X[:, H, 0]).sum()),
        "hand_joints_3d_caliscope": int(np.isfinite(Xc[:, H, 0]).sum()),
        "one_view_hand_joints_with_3d": int((np.isfinite(X[:, H, 0]) & (n_seen[:, H] < 2)).sum()),
        "frames_with_15plus_hand_joints_ours": int(
            (np.isfinite(X[:, H, 0]).reshape(T, 2, 21).sum(-1) >= 15).any(-1).sum()
        ),
        "reproj_hands_ours_used_px": float(np.median(ours_used)),
        "reproj_hands_caliscope_px": float(np.median(cal_all)),
        "reproj_hands_same_obs_ours_px": float(np.median(e_ours[:, :, H][same])),
        "reproj_hands_same_obs_caliscope_px": float(np.median(e_cal[:, :, H][same])),
        "reproj_body_ours_used_px": float(np.nanmedian(err_cam[:, body])),
        "reproj_per_camera": per_cam,
        "dist_to_caliscope_mm_per_finger": per_finger,
    }
    s, m, n = bone_std_mm(X, names)
    sc, mc, nc = bone_std_mm(Xc, names)
    # the greedy track (ch. 4; it carries every whole-body joint, gaps filled and smoothed): the particle
    # tracker finds nobody here, caliscope's world has x up (cam_1's frame) and the filter assumes z up
    tf = TrackFile.load(track_session_greedy(lay.root))
    k = int(np.argmax(np.isfinite(tf.xyz_m[..., 0]).sum((0, 2)))) if tf.n_tracks else None
    if k is not None:
        st, _, _ = bone_std_mm(tf.xyz_m[:, k], tuple(tf.joint_names))
        res["bone_std_greedy_track_mm"] = st
    res.update(
        bone_std_ours_mm=s,
        bone_len_ours_mm=m,
        bones_ours=n,
        bone_std_caliscope_mm=sc,
        bone_len_caliscope_mm=mc,
    )
    return res


def table(r: dict) -> str:
    """The figures as a markdown table (ours against caliscope's own 3D on the same 2D)."""
    rows = [
        (
            "hand joints in 3D (of those seen by >= 2 views)",
            r["hand_joints_3d_ours"],
            r["hand_joints_3d_caliscope"],
        ),
        ("hand joints seen by one view given a 3D point", r["one_view_hand_joints_with_3d"], "-"),
        (
            "hand reprojection, median px (views used)",
            r["reproj_hands_ours_used_px"],
            r["reproj_hands_caliscope_px"],
        ),
        (
            "hand reprojection on the same 2D observations, median px",
            r["reproj_hands_same_obs_ours_px"],
            r["reproj_hands_same_obs_caliscope_px"],
        ),
        (
            "finger bone length std over time, median over bones, mm",
            r["bone_std_ours_mm"],
            r["bone_std_caliscope_mm"],
        ),
        ("finger bone length, median, mm", r["bone_len_ours_mm"], r["bone_len_caliscope_mm"]),
        ("  the same std on our greedy track, mm", r.get("bone_std_greedy_track_mm", float("nan")), "-"),
    ]
    rows += [
        (f"  {cam} hand reprojection, median px", v["ours_used_px"], v["caliscope_px"])
        for cam, v in r["reproj_per_camera"].items()
    ]
    out = ["| figure | ours | caliscope |", "|---|---|---|"]
    out += [
        f"| {a} | {b:.2f} | {c if isinstance(c, str) else f'{c:.2f}'} |"
        if isinstance(b, float)
        else f"| {a} | {b} | {c} |"
        for a, b, c in rows
    ]
    out += ["", "| finger | distance ours - caliscope, median mm |", "|---|---|"]
    out += [f"| {f} | {d:.1f} |" for f, d in r["dist_to_caliscope_mm_per_finger"].items()]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None, help="work folder (default: a temporary one)")
    ap.add_argument(
        "--raw-sides",
        action="store_true",
        help="keep MediaPipe's left/right hand labels as caliscope wrote them (default: the body's side)",
    )
    ap.add_argument(
        "--shared",
        default=os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared")),
        help="the shared data folder (default: $ROOMCAP_SHARED, else ../shared)",
    )
    args = ap.parse_args(argv)
    root = Path(args.shared) / REC
    if not root.is_dir():
        print(f"caliscope recording not found at {root}; pass --shared or set ROOMCAP_SHARED")
        print("BENCH " + json.dumps({"skipped": True}))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        res = run(root, Path(args.out or tmp), not args.raw_sides)
    print(table(res))
    print("BENCH " + json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
