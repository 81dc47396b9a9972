"""Pictures of a forecast (``forecast sample``): one PNG per person, beside the forecast's arrays.

Each picture holds, for one track: a skeleton strip (the last observed poses in black, the forecast samples
in blue, the truth in green where the track goes on after the forecast's start: ``forecast sample
--start-s``), seen obliquely from the person's front-left at the last observed frame, each pose centred on
its root; below it the root's path on the floor (top view, z up): observed, truth, every sample and, for a
stochastic model, the samples' mean with their 2-sigma spread every half second; and the whole scene's floor
with every person's observed path and forecast mean. Matplotlib (Agg); importing this module loads it.
"""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402

from roomcap.keypoints.skeletons import skeleton_from_names  # noqa: E402

OBS, FC, TRUTH, OTHER = "black", "tab:blue", "tab:green", "0.75"
N_OBS_POSES, N_FC_POSES = 4, 6  # poses in the strip
SLOT_M = 0.9  # metres between the strip's poses
VIEW_DEG = 35.0  # the strip's view: from the front, turned this far towards the person's left


def picture_paths(out: str | os.PathLike, track_ids) -> list[Path]:
    """``<out stem>_track<ID>.png`` beside the forecast file ``out``, one per track."""
    out = Path(out)
    return [out.with_name(f"{out.stem}_track{int(t)}.png") for t in track_ids]


def plot_forecasts(fc: dict, out: str | os.PathLike, title: str = "") -> list[Path]:
    """One picture per forecast track of ``fc`` (the dict of
    :func:`roomcap.forecast.runtime.track_forecast.forecast_tracks`) beside ``out``; -> the paths written."""
    xyz = np.asarray(fc["xyz_m"], np.float64)  # (S,H,K,J,3)
    names = [str(n) for n in fc["joint_names"]]
    sk = skeleton_from_names(names)
    lh, rh = names.index("left_hip"), names.index("right_hip")
    obs = np.asarray(fc["obs_xyz_m"], np.float64)  # (n_obs,K,J,3)
    truth = np.asarray(fc["truth_xyz_m"], np.float64)  # (H,K,J,3)
    roots = {
        "obs": 0.5 * (obs[..., lh, :] + obs[..., rh, :]),  # (n_obs,K,3)
        "fc": 0.5 * (xyz[..., lh, :] + xyz[..., rh, :]),  # (S,H,K,3)
        "truth": 0.5 * (truth[..., lh, :] + truth[..., rh, :]),  # (H,K,3)
    }
    written = []
    for k, png in zip(range(xyz.shape[2]), picture_paths(out, fc["track_id"]), strict=True):
        if not np.isfinite(xyz[:, :, k]).any():
            continue  # not seen at the forecast's start: nothing forecast
        fig = _person_figure(fc, k, obs[:, k], xyz[:, :, k], truth[:, k], roots, sk.parents, (lh, rh), title)
        png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(png, dpi=110)
        plt.close(fig)
        written.append(png)
    return written


def _person_figure(fc, k, obs, fc_k, truth, roots, parents, hips, title):
    S, H = fc_k.shape[:2]
    fps = float(fc["fps"])
    tid = int(fc["track_id"][k])
    fig = plt.figure(figsize=(13, 8.6), layout="constrained")
    gs = fig.add_gridspec(2, 2, height_ratios=[1, 1.5])
    strip = fig.add_subplot(gs[0, :])
    _strip(strip, obs, fc_k, truth, parents, hips, fps)
    _floor(fig.add_subplot(gs[1, 0]), k, roots, fps, zoom=True)
    _floor(fig.add_subplot(gs[1, 1]), k, roots, fps, zoom=False, track_ids=fc["track_id"])
    n = f"{S} samples" if S > 1 else "one forecast"
    resampled = (
        f", the track resampled from {float(fc['track_fps']):g} Hz"
        if abs(float(fc.get("track_fps", fps)) - fps) > 1e-6
        else ""
    )
    fig.suptitle(
        f"{fc['model']}: the next {H / fps:.1f} s of track {tid}, {n} at {fps:g} Hz{resampled}\n{title}",
        fontsize=11,
    )
    return fig


def _view_axis(last: np.ndarray, hips) -> np.ndarray:
    """Unit floor vector that the strip's horizontal axis follows: the hip vector (left -> right, so the
    person is seen from the front) turned by VIEW_DEG about z."""
    d = last[hips[1]] - last[hips[0]]
    th = np.arctan2(d[1], d[0]) + np.deg2rad(VIEW_DEG) if np.isfinite(d[:2]).all() else 0.0
    return np.array([np.cos(th), np.sin(th), 0.0])


def _pick(n: int, m: int) -> np.ndarray:
    """Up to ``m`` frame indices out of ``n``, evenly spaced, ending at the last."""
    if n <= 0:
        return np.zeros(0, int)
    return np.unique(np.round(np.linspace(n - 1, 0, min(m, n))[::-1] if m > 1 else [n - 1]).astype(int))


def _bones(ax, pose, parents, u, x0, **kw):
    """Draw ``pose (J,3)`` projected on (``u``, z), its root (mid-hips) at horizontal ``x0``."""
    for j, p in enumerate(parents):
        if p < 0:
            continue
        a, b = pose[j], pose[p]
        if np.isfinite(a).all() and np.isfinite(b).all():
            ax.plot([x0 + a @ u, x0 + b @ u], [a[2], b[2]], solid_capstyle="round", **kw)


def _strip(ax, obs, fc_k, truth, parents, hips, fps):
    S, H = fc_k.shape[:2]
    n_obs = len(obs)
    u = _view_axis(obs[-1], hips)
    io = _pick(n_obs, N_OBS_POSES)
    ih = np.unique(np.round(np.linspace(H / N_FC_POSES, H, N_FC_POSES)).astype(int) - 1).clip(0, H - 1)
    alpha = 1.0 if S == 1 else max(0.12, 2.0 / S)
    x, ticks, labels = 0.0, [], []

    def root_u(pose):
        r = 0.5 * (pose[hips[0]] + pose[hips[1]])
        return r @ u if np.isfinite(r).all() else np.nan

    for i in io:
        r = root_u(obs[i])
        if np.isfinite(r):
            _bones(ax, obs[i], parents, u, x - r, color=OBS, lw=2)
        ticks.append(x)
        labels.append(f"{(i - n_obs + 1) / fps:+.1f} s")
        x += SLOT_M
    x += 0.3 * SLOT_M  # a gap between the observed and the forecast
    ax.axvline(x - 0.65 * SLOT_M, color="0.6", lw=1, ls=":")
    for h in ih:
        r_t = root_u(truth[h])
        if np.isfinite(r_t):
            _bones(ax, truth[h], parents, u, x - r_t, color=TRUTH, lw=2.2, ls="--")
        for s in range(S):
            r = root_u(fc_k[s, h])
            if np.isfinite(r):
                _bones(ax, fc_k[s, h], parents, u, x - r, color=FC, lw=1.6, alpha=alpha)
        ticks.append(x)
        labels.append(f"{(h + 1) / fps:+.1f} s")
        x += SLOT_M
    ax.set_xticks(ticks, labels)
    ax.set_aspect("equal")
    ax.set_xlim(-0.6 * SLOT_M, x - 0.4 * SLOT_M)
    zs = np.concatenate([obs[..., 2].ravel(), fc_k[..., 2].ravel()])
    zs = zs[np.isfinite(zs)]
    if len(zs):
        ax.set_ylim(min(0.0, zs.min()) - 0.05, zs.max() + 0.1)
    ax.set_ylabel("height z (m)")
    for side in ("top", "right"):
        ax.spines[side].set_visible(False)
    ax.plot([], [], color=OBS, lw=2, label="observed")
    ax.plot([], [], color=FC, lw=2, label="forecast" + (f" ({S} samples)" if S > 1 else ""))
    if np.isfinite(truth).any():
        ax.plot([], [], color=TRUTH, lw=2, ls="--", label="truth")
    ax.legend(loc="lower left", fontsize=9, ncol=3, frameon=False, bbox_to_anchor=(0, 1.0))
    ax.set_title(
        f"poses, each centred on its root, seen from the front turned {VIEW_DEG:g} deg; seconds from the "
        "last observed frame",
        fontsize=9,
        loc="right",
    )


def _spread(ax, pts: np.ndarray) -> None:
    """The 2-sigma ellipse of the floor points ``pts (S,2)``."""
    pts = pts[np.isfinite(pts).all(1)]
    if len(pts) < 3:
        return
    w, v = np.linalg.eigh(np.cov(pts.T))
    w = np.sqrt(np.maximum(w, 1e-12))
    ang = np.degrees(np.arctan2(v[1, 1], v[0, 1]))
    ax.add_patch(
        Ellipse(pts.mean(0), 4 * w[1], 4 * w[0], angle=ang, fc=FC, ec=FC, alpha=0.15, lw=1)
    )  # width along the major axis (the eigenvector of the larger eigenvalue), 2 sigma each side


def _floor(ax, k, roots, fps, zoom: bool, track_ids=None):
    obs, fc, truth = roots["obs"], roots["fc"], roots["truth"]  # (n_obs,K,3), (S,H,K,3), (H,K,3)
    S, H = fc.shape[:2]
    ks = [k] if zoom else range(obs.shape[1])
    for kk in ks:
        me = kk == k
        o = obs[:, kk]
        if not me:  # the others: observed path and forecast mean, faint
            ax.plot(o[:, 0], o[:, 1], color=OTHER, lw=1.5)
            m = np.nanmean(fc[:, :, kk], 0) if np.isfinite(fc[:, :, kk]).any() else None
            if m is not None:
                ax.plot(np.r_[o[-1:, 0], m[:, 0]], np.r_[o[-1:, 1], m[:, 1]], color=FC, lw=1, alpha=0.4)
            if np.isfinite(o[-1]).all():
                ax.annotate(f"track {int(track_ids[kk])}", o[-1, :2], fontsize=8, color="0.45")
            continue
        ax.plot(o[:, 0], o[:, 1], color=OBS, lw=2, label="observed")
        if np.isfinite(truth[:, kk]).any():
            t = np.r_[o[-1:], truth[:, kk]]
            ax.plot(t[:, 0], t[:, 1], color=TRUTH, lw=2, ls="--", label="truth")
        alpha = 1.0 if S == 1 else max(0.12, 2.0 / S)
        for s in range(S):
            p = np.r_[o[-1:], fc[s, :, kk]]
            lw = 2.0 if S == 1 else 1.2
            ax.plot(p[:, 0], p[:, 1], color=FC, lw=lw, alpha=alpha, label="forecast" if s == 0 else None)
        if S > 1:
            m = np.r_[o[-1:], np.nanmean(fc[:, :, kk], 0)]
            ax.plot(m[:, 0], m[:, 1], color=FC, lw=2.5, label="mean of the samples")
            step = max(1, int(round(0.5 * fps)))
            for h in sorted({*range(step - 1, H, step), H - 1}):
                _spread(ax, fc[:, h, kk, :2])
            ax.fill([], [], color=FC, alpha=0.15, label="2-sigma spread every 0.5 s")
        ax.plot(*o[-1, :2], "o", color=OBS, ms=5)
        if not zoom and np.isfinite(o[-1]).all():
            ax.annotate(f"track {int(track_ids[kk])}", o[-1, :2], fontsize=9, weight="bold")
        if zoom:
            end = fc[:, -1, kk]
            ax.plot(end[:, 0], end[:, 1], ".", color=FC, ms=4)
    ax.set_aspect("equal", adjustable="box" if zoom else "datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    if zoom:
        pts = np.concatenate([obs[:, k, :2], fc[:, :, k, :2].reshape(-1, 2), truth[:, k, :2]])
        pts = pts[np.isfinite(pts).all(1)]
        if len(pts):
            lo, hi = pts.min(0), pts.max(0)
            c, r = 0.5 * (lo + hi), max(0.4, 0.6 * float((hi - lo).max()))
            ax.set_xlim(c[0] - r, c[0] + r)
            ax.set_ylim(c[1] - r, c[1] + r)
        ax.legend(fontsize=8, loc="best")
        ax.set_title(
            f"root (mid-hips) on the floor, top view: the last {len(obs) / fps:.1f} s and the forecast",
            fontsize=9,
        )
    else:
        ax.margins(0.15)
        ax.set_title(
            "the scene, top view: this person (black), the others' observed paths (grey) and forecasts",
            fontsize=9,
        )
