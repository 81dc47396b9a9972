"""Calibration report: ``report.toml`` (figures per camera and per pair), ``layout.png`` (cameras and board
poses in 3D) and ``coverage.png`` (where the board was seen in each camera's image). matplotlib Agg."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.calibrate.boards import Board
from roomcap.calibrate.camera import CameraRig
from roomcap.calibrate.detect import CameraDetections
from roomcap.calibrate.extrinsics import ExtrinsicsResult
from roomcap.calibrate.intrinsics import IntrinsicsResult, coverage_grid
from roomcap.core.fileio import atomic_path, save_toml, schema_tag

log = logging.getLogger(__name__)

__all__ = ["report_dict", "write_report", "summary_text", "plot_layout", "plot_coverage"]

REPORT_SCHEMA = "calibration_report"
REPORT_VERSION = 1


def report_dict(
    board: Board,
    rig: CameraRig,
    dets: Mapping[str, CameraDetections],
    intr: Mapping[str, IntrinsicsResult | None],
    ext: ExtrinsicsResult | None,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Everything a user needs to judge the calibration, as plain data."""
    cams = []
    for i, cam in enumerate(rig.cameras):
        d = dets.get(cam.name)
        r = intr.get(cam.name)
        e: dict[str, Any] = {
            "name": cam.name,
            "size_wh": list(cam.size_wh),
            "model": cam.model,
            "focal_px": [float(cam.K[0, 0]), float(cam.K[1, 1])],
            "principal_point_px": [float(cam.K[0, 2]), float(cam.K[1, 2])],
            "dist": cam.dist.tolist(),
            "center_m": cam.center.tolist(),
        }
        if d is not None:
            e["frames_read"] = int(d.n_frames_read)
            e["frames_with_board"] = int(len(d.seen_frames()))
            e["coverage_fraction"] = float((coverage_grid(d.xy_px, d.size_wh) > 0).mean())
        if r is not None:
            e["intrinsic_rms_px"] = float(r.rms_px)
            e["intrinsic_frames_used"] = int(len(r.frames_used))
            e["intrinsic_frames_rejected"] = r.frames_rejected.tolist()
            e["intrinsic_model"] = r.model
        else:
            e["intrinsics"] = "given (not calibrated here)"
        if ext is not None:
            e["extrinsic_rms_px"] = float(ext.per_camera_rms_px[i])
            e["extrinsic_observations"] = int(ext.per_camera_obs[i])
            e["extrinsic_frames"] = int(ext.per_camera_frames[i])
        cams.append(e)
    out: dict[str, Any] = {
        "schema": schema_tag(REPORT_SCHEMA, REPORT_VERSION),
        "board": board.to_dict(),
        "cameras": cams,
    }
    if ext is not None:
        names = rig.names
        pairs = []
        for i in range(len(names)):
            for j in range(i + 1, len(names)):
                pairs.append({"cameras": [names[i], names[j]], "shared_frames": int(ext.links[i, j])})
        out["pairs"] = pairs
        out["bundle_adjustment"] = {
            "initial_rms_px": ext.initial_rms_px,
            "final_rms_px": ext.final_rms_px,
            "time_s": ext.ba_time_s,
            "iterations": ext.ba_iterations,
            "observations_dropped": ext.n_outliers,
            "board_poses": int(len(ext.frames)),
            "world": ext.world,
        }
    if extra:
        out.update(extra)
    return out


def summary_text(rep: Mapping[str, Any]) -> str:
    """A short table for the terminal."""
    lines = [
        f"{'camera':<12} {'size':>10} {'f_px':>8} {'int.RMS':>8} {'frames':>7} {'used':>5} "
        f"{'cover':>6} {'ext.RMS':>8}"
    ]
    for c in rep["cameras"]:
        size = f"{c['size_wh'][0]}x{c['size_wh'][1]}"
        irms = f"{c['intrinsic_rms_px']:.3f}" if "intrinsic_rms_px" in c else "given"
        erms = f"{c['extrinsic_rms_px']:.3f}" if "extrinsic_rms_px" in c else "-"
        lines.append(
            f"{c['name']:<12} {size:>10} {c['focal_px'][0]:>8.1f} {irms:>8} "
            f"{c.get('frames_with_board', 0):>7} {c.get('intrinsic_frames_used', 0):>5} "
            f"{100 * c.get('coverage_fraction', 0):>5.0f}% {erms:>8}"
        )
    if "bundle_adjustment" in rep:
        ba = rep["bundle_adjustment"]
        lines.append(
            f"bundle adjustment: RMS {ba['initial_rms_px']:.3f} -> {ba['final_rms_px']:.3f} px in "
            f"{ba['time_s']:.2f} s ({ba['iterations']} iterations, {ba['board_poses']} board poses, "
            f"{ba['observations_dropped']} observations dropped); world: {ba['world']}"
        )
        weak = [p for p in rep["pairs"] if 0 < p["shared_frames"] < 5]
        if weak:
            lines.append(
                "weak links (fewer than 5 shared frames): "
                + ", ".join(f"{a}-{b} ({p['shared_frames']})" for p in weak for a, b in [p["cameras"]])
            )
    return "\n".join(lines)


def plot_layout(
    path: str | os.PathLike, rig: CameraRig, board: Board, world_from_board: np.ndarray, max_boards: int = 60
) -> None:
    """PNG of the cameras (centre, viewing direction, name) and the board poses in 3D."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(111, projection="3d")
    C = rig.centers()
    span = max(float(np.ptp(C, axis=0).max()) if len(C) > 1 else 1.0, 0.5)
    w, h = board.extent_m()
    outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0], [0, 0, 0]], float)
    idx = (
        np.linspace(0, len(world_from_board) - 1, min(max_boards, len(world_from_board))).astype(int)
        if len(world_from_board)
        else []
    )
    for k in idx:
        T = world_from_board[k]
        P = outline @ T[:3, :3].T + T[:3, 3]
        ax.plot(P[:, 0], P[:, 1], P[:, 2], color="tab:orange", lw=0.6, alpha=0.6)
    for cam in rig.cameras:
        c = cam.center
        z = cam.R[2] * 0.15 * span
        ax.scatter(*c, color="tab:blue", s=25)
        ax.plot([c[0], c[0] + z[0]], [c[1], c[1] + z[1]], [c[2], c[2] + z[2]], color="tab:blue")
        ax.text(c[0], c[1], c[2], f" {cam.name}", fontsize=8)
    allp = np.concatenate([C] + ([world_from_board[:, :3, 3]] if len(world_from_board) else []))
    mid = allp.mean(0)
    r = max(float(np.ptp(allp, axis=0).max()) / 2, 0.25)
    ax.set_xlim(mid[0] - r, mid[0] + r)
    ax.set_ylim(mid[1] - r, mid[1] + r)
    ax.set_zlim(mid[2] - r, mid[2] + r)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(f"{len(rig)} cameras (blue: centre and viewing direction), {len(idx)} board poses (orange)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def plot_coverage(
    path: str | os.PathLike, dets: Mapping[str, CameraDetections], intr: Mapping[str, IntrinsicsResult | None]
) -> None:
    """PNG with one heatmap per camera: board points detected per image cell (all frames)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dets)
    n = len(names)
    cols = min(4, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.8 * rows), squeeze=False)
    for k, name in enumerate(names):
        ax = axes[k // cols][k % cols]
        d = dets[name]
        H = coverage_grid(d.xy_px, d.size_wh, gx=32)
        ax.imshow(H, extent=(0, d.size_wh[0], d.size_wh[1], 0), cmap="viridis", interpolation="nearest")
        r = intr.get(name)
        frac = (H > 0).mean() * 100
        ax.set_title(
            f"{name}: {len(d.seen_frames())} frames, {frac:.0f}% of image"
            + (f", RMS {r.rms_px:.2f}px" if r is not None else ""),
            fontsize=8,
        )
        ax.set_xticks([])
        ax.set_yticks([])
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    fig.suptitle("Board coverage per camera (points per cell; aim for the whole image)", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def write_report(
    folder: str | os.PathLike,
    board: Board,
    rig: CameraRig,
    dets: Mapping[str, CameraDetections],
    intr: Mapping[str, IntrinsicsResult | None],
    ext: ExtrinsicsResult | None,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Path]:
    """Write report.toml, layout.png and coverage.png into folder; returns their paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rep = report_dict(board, rig, dets, intr, ext, extra)
    paths = {
        "report": folder / "report.toml",
        "layout": folder / "layout.png",
        "coverage": folder / "coverage.png",
    }
    save_toml(paths["report"], rep, header="roomcap calibration report\n" + summary_text(rep))
    wfb = ext.world_from_board if ext is not None else np.zeros((0, 4, 4))
    plot_layout(paths["layout"], rig, board, wfb)
    plot_coverage(paths["coverage"], dets, intr)
    log.info("report written to %s", folder)
    return paths
