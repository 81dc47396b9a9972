"""The page: everything collected into one self-contained HTML file, and ``python -m
roomcap.pipeline.report``."""

from __future__ import annotations

import argparse
import html
import json
import logging
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.capture.session import SessionLayout
from roomcap.core.errors import FormatError
from roomcap.core.fileio import atomic_write_text, load_npz, load_toml
from roomcap.core.redact import redact
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.pipeline.provenance import STAGES
from roomcap.pipeline.report.figures import _detection_rates, _quality, _rig_data, _tracks_data
from roomcap.pipeline.report.inputs import ReportConfig, _load, _r
from roomcap.pipeline.report.overlay_video import write_overlay_videos
from roomcap.pipeline.report.problems import _problems, _warnings
from roomcap.pipeline.report.views import _video_paths, _views_data
from roomcap.triangulate.chunks import parts_dir

log = logging.getLogger(__name__)


_ASSETS = Path(__file__).resolve().parents[1] / "report_assets"


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


def _floor_roots(xyz: np.ndarray, names: list[str]) -> np.ndarray:
    """The floor point (x, y) under each pose's root of ``xyz (...,J,3)``: the pelvis, else the mean of the
    hips, else of the seen joints (report.js ``rootOf`` alike); NaN where none is seen."""
    for pick in (["pelvis"], ["left_hip", "right_hip"]):
        if all(n in names for n in pick):
            r = xyz[..., [names.index(n) for n in pick], :2].mean(-2)
            break
    else:
        r = np.full(xyz.shape[:-2] + (2,), np.nan)
    ok = np.isfinite(xyz).all(-1, keepdims=True)
    n = ok.sum(-2)
    mean = np.where(n > 0, np.where(ok, xyz, 0).sum(-2) / np.maximum(n, 1), np.nan)[..., :2]
    return np.where(np.isfinite(r), r, mean)


def _forecast_data(lay: SessionLayout) -> dict[str, Any] | None:
    """``forecast/preview.npz``: the forecast poses (the ghosts), and for the floor map each track's path
    (``path (K,H,2)``, the floor point under its root), and where the model is stochastic (``stochastic``;
    None for a file of an older version that does not say) the paths of its S samples
    (``sample_paths (K,S,H,2)``) and their spread ``spread_m (K,H)``: the RMS distance of the samples'
    floor points from their mean."""
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
    names = [str(n) for n in d["joint_names"]] if "joint_names" in d else []
    out = {
        "xyz": _r(xyz),
        "track_id": d["track_id"].tolist(),
        "start_index": int(d["start_index"]),
        "model": str(d.get("model", "")),
        "fps": float(d["fps"]) if "fps" in d else None,
        "stochastic": bool(d["stochastic"]) if "stochastic" in d else None,
        "path": _r(_floor_roots(xyz, names), 3) if names else None,
        "sample_paths": None,
        "spread_m": None,
    }
    S = d.get("samples_xyz_m")
    if S is not None and names and S.ndim == 5 and S.shape[1:] == xyz.shape:
        roots = np.moveaxis(_floor_roots(S.astype(np.float64), names), 0, 1)  # (K,S,H,2)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a track not forecast: all NaN
            dev = roots - np.nanmean(roots, axis=1, keepdims=True)
            spread = np.sqrt(np.nanmean((dev**2).sum(-1), axis=1))
        out["sample_paths"] = _r(roots, 3)
        out["spread_m"] = _r(spread, 3)
    return out


def _parents_by_name(names: list[str]) -> list[int]:
    """The parent of each of ``names`` in the body19 skeleton, as an index into ``names`` (the nearest
    ancestor that is among them; -1 for none)."""
    ref = list(CANONICAL.joint_names)
    out = []
    for n in names:
        j = ref.index(n) if n in ref else -1
        p = CANONICAL.parents[j] if j >= 0 else -1
        while p >= 0 and ref[p] not in names:
            p = CANONICAL.parents[p]
        out.append(names.index(ref[p]) if p >= 0 else -1)
    return out


def _behaviour_data(lay: SessionLayout) -> dict[str, Any] | None:
    """``forecast/behaviour.npz`` (``forecast behaviour sample``): per person the observed steps (labels,
    characteristic times and, where the file has them, the label ranges ``step_start_s``/``step_end_s``
    (K,N)), the next M actions with the probability of every label (``probs (K,M,A)``, ``labels (A,)``) and
    the forecast characteristic poses ``poses (K,M,J,3)`` in the room with their ``joint_names`` and
    ``parents``, or None."""
    path = lay.root / "forecast" / "behaviour.npz"
    if not path.exists():
        return None
    try:
        d = load_npz(path, required=("track_id", "actions", "probs", "poses_m"))
    except FormatError as e:
        log.warning("behaviour forecast not shown: %s", e)
        return None
    K = len(d["track_id"])
    p = d["probs"].max(-1)
    obs = d["observed"].tolist() if "observed" in d else [[] for _ in d["track_id"]]
    names = [str(n) for n in d["joint_names"]] if "joint_names" in d else []
    poses = d["poses_m"]
    ok_poses = bool(names) and poses.ndim == 4 and poses.shape[2] == len(names) and poses.shape[-1] == 3
    A = d["probs"].shape[-1]
    labels = [str(x) for x in d["labels"]] if "labels" in d and len(d["labels"]) == A else []

    def steps(key: str) -> Any:
        return _r(d[key]) if key in d and d[key].shape[:1] == (K,) else None

    return {
        "track_id": d["track_id"].tolist(),
        "observed": obs,
        "actions": d["actions"].tolist(),
        "prob": _r(p),
        "model": str(d["model"]) if "model" in d else "",
        "labels": labels,
        "probs": _r(d["probs"]) if labels else None,
        "step_time_s": steps("step_time_s"),
        "step_start_s": steps("step_start_s"),
        "step_end_s": steps("step_end_s"),
        "poses": _r(poses) if ok_poses else None,
        "joint_names": names if ok_poses else [],
        "parents": _parents_by_name(names) if ok_poses else [],
    }


def report_inputs(lay: SessionLayout) -> list[Path]:
    """Every file the report reads, of those that exist now (the report stage's plan: a change of any of them
    reruns it): session.toml, the rig and its calibration report, the detections, the 3D poses, the tracks
    (the live track's parts too), the forecast preview and ``forecast/behaviour.npz`` (``forecast behaviour
    sample``), and the videos of the filmstrips and overlays."""
    cams = sorted(set(lay.detection_cameras()) | set(lay.raw_cameras()))
    files = [
        lay.session_toml,
        lay.rig_toml,
        lay.rig_toml.parent / "report" / "report.toml",
        *(lay.detections(c) for c in cams),
    ]
    for path in (lay.poses3d, lay.tracks, lay.live_tracks):  # a single file, or a streamed run's parts
        files += [path, parts_dir(path)]
    files += [lay.root / "forecast" / "preview.npz", lay.root / "forecast" / "behaviour.npz"]
    files += _video_paths(lay, cams).values()
    return [p for p in dict.fromkeys(files) if p.exists()]


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
        "behaviour": _behaviour_data(lay),
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


# ----------------------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m roomcap.pipeline.report",
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
