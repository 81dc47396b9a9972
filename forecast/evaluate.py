"""Evaluation protocols and the report (tables + one plot per metric over the horizon).

- ``evaluate_single``: test-split single-person windows (observe ``n_obs``, forecast ``n_pred`` frames at
  25 Hz); MPJPE(t), NDMS(t) (eq. 6.9-6.12: every sample scored, then averaged over samples, as Z in eq. 6.9;
  database = motion words of the test clips, the query's own clip excluded), APD(t) and APD, best-of-S
  ADE/FDE, NPSS. Sampling noise is seeded per model, so re-evaluating a checkpoint gives the same figures.
  NDMS at 2/3/4 s comes with a 95 % bootstrap interval that resamples whole clips (windows of one clip
  overlap and are correlated, so resampling windows would understate the spread), and each model's
  paired difference to a reference model (the GRU) over the same windows and the same resampled clips.
- ``evaluate_social``: two-person scenes composed from held-out clips, a long horizon (10 s), NDMS(t)
  per person and the SSCP distance (sec. 7.3) against real composed scenes.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from capture.fileio import atomic_write_text
from forecast import data as fdata
from forecast import metrics as M
from forecast.predict import forecast_world
from keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)


class Real:
    """The real future as a 'forecast' (reference row)."""

    kind = "real"
    stochastic = False


def ndms_scorer_for(clips: list[fdata.Clip], kappa: int = 8) -> M.NDMSScorer:
    """Database of motion words from clips; a word's group is its clip (``clip_group(name)``)."""
    seqs, groups = [], []
    for c in clips:
        i = clip_group(c.name)
        for p in range(c.xyz_m.shape[1]):
            x = c.xyz_m[:, p]
            ok = np.isfinite(x).all((1, 2))
            # split at gaps: each complete run is a sequence
            edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(int), 0]))
            for a, b in zip(edges[::2], edges[1::2], strict=True):
                if b - a >= kappa:
                    seqs.append(x[a:b])
                    groups.append(i)
    return M.NDMSScorer(seqs, get_skeleton(clips[0].skeleton).joint_names, kappa, groups)


def clip_group(name: str) -> int:
    """Stable integer id of a clip name (groups in the NDMS database)."""
    import zlib

    return zlib.crc32(name.encode()) & 0x7FFFFFFF


def evaluate_single(
    models: dict[str, object],
    test_clips: list[fdata.Clip],
    n_obs: int = 50,
    n_pred: int = 100,
    n_samples: int = 10,
    stride: int = 5,
    max_windows: int = 400,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    ndms_database: list[fdata.Clip] | None = None,
    reference: str | None = None,
    n_boot: int = 2000,
) -> dict:
    """``ndms_database``: clips for the NDMS database (default: the held-out clips; the query's own clip
    is always excluded).

    -> {"fps", "horizon_s", "models": {name: {"mpjpe": [H], "ndms": [H], "apd_t": [H], "apd", "ade", "fde",
    "npss", "ndms_at": {t: [mean, lo, hi]}, "ndms_diff_at": {t: [mean, lo, hi]} (minus ``reference``),
    ...}}, "n_windows", "n_clips", "skipped"}."""

    ws = fdata.make_windows(test_clips, n_obs, n_pred, stride, persons="each")
    if len(ws) == 0:
        raise ValueError(f"no test windows of {n_obs + n_pred} frames (skipped {ws.skipped})")
    rng = np.random.default_rng(seed)
    sel = np.sort(rng.choice(len(ws), min(max_windows, len(ws)), replace=False))
    x, mask = ws.x[sel, :, 0], ws.mask[sel, :, 0]
    groups = np.array([clip_group(test_clips[c].name) for c in ws.clip[sel]])
    obs, gt = x[:, :n_obs], x[:, n_obs:]
    scorer = ndms_scorer_for(ndms_database or test_clips)
    out: dict = {
        "fps": ws.fps,
        "n_obs": n_obs,
        "n_pred": n_pred,
        "n_samples": n_samples,
        "n_windows": len(sel),
        "skipped": ws.skipped,
        "models": {},
    }
    out["n_clips"] = int(len(np.unique(groups)))
    per_window = {}
    for name, model in models.items():
        if progress:
            progress(name)
        if isinstance(model, Real):
            y = gt[:, None]
        else:
            S = n_samples if getattr(model, "stochastic", False) else 1
            torch.manual_seed(seed)  # the same sampling noise on every run
            y = forecast_world(model, obs[:, :, None], None, n_pred, S)[:, :, :, 0]  # (B,S,H,J,3)
        out["models"][name], per_window[name] = _single_metrics(y, gt, obs, mask[:, n_obs:], groups, scorer)
    boot = _cluster_bootstrap_index(groups, n_boot, seed)
    ref = reference if reference in per_window else None
    out["reference"] = ref
    for name, w in per_window.items():
        r = out["models"][name]
        r["ndms_at"] = {f"{t:g}": _ci(ndms_at(w, ws.fps, t), boot) for t in NDMS_CI_S if t * ws.fps <= n_pred}
        if ref is not None and name != ref:
            r["ndms_diff_at"] = {
                f"{t:g}": _ci(ndms_at(w, ws.fps, t) - ndms_at(per_window[ref], ws.fps, t), boot)
                for t in NDMS_CI_S
                if t * ws.fps <= n_pred
            }
    return out


NDMS_CI_S = (1.0, 2.0, 3.0, 4.0)


def ndms_at(per_window: np.ndarray, fps: float, t_s: float) -> np.ndarray:
    """Per-window NDMS at t: mean over the 0.2 s before t (the report's convention). (B,H) -> (B,)."""
    win = max(1, int(0.2 * fps))
    i = int(round(t_s * fps))
    return per_window[:, max(0, i - win) : i].mean(1)


def _cluster_bootstrap_index(groups: np.ndarray, n_boot: int, seed: int) -> list[np.ndarray]:
    """Bootstrap replicates that resample whole clips (with replacement): window indices per replicate."""
    rng = np.random.default_rng(seed + 1)
    ids = np.unique(groups)
    members = [np.flatnonzero(groups == g) for g in ids]
    return [np.concatenate([members[k] for k in rng.integers(0, len(ids), len(ids))]) for _ in range(n_boot)]


def _ci(values: np.ndarray, boot: list[np.ndarray]) -> list[float]:
    """[mean, 2.5 %, 97.5 %] of the window mean under the clip bootstrap."""
    means = np.array([values[b].mean() for b in boot])
    return [float(values.mean()), float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))]


def _single_metrics(y, gt, obs, mask_fut, groups, scorer) -> tuple[dict, np.ndarray]:
    B, S, H = y.shape[:3]
    mp = M.mpjpe(y, np.broadcast_to(gt[:, None], y.shape), np.broadcast_to(mask_fut[:, None], y.shape[:-1]))
    nd_w = np.stack([scorer.score_forecast(obs[b], y[b], exclude_group=int(groups[b])) for b in range(B)])
    nd = nd_w.mean(0)
    if S > 1:
        flat = y.reshape(B, S, H, -1)
        d = np.linalg.norm(flat[:, :, None] - flat[:, None], axis=-1)  # (B,S,S,H)
        iu = np.triu_indices(S, 1)
        apd_t = d[:, iu[0], iu[1]].mean((0, 1))
        apd = float(np.mean([M.apd(y[b]) for b in range(B)]))
    else:
        apd_t, apd = np.zeros(H), 0.0
    ade = float(np.mean([M.ade(y[b], gt[b]) for b in range(B)]))
    fde = float(np.mean([M.fde(y[b], gt[b]) for b in range(B)]))
    npss = M.npss(y[:, 0], gt)
    return {
        "mpjpe": mp.tolist(),
        "ndms": nd.tolist(),
        "apd_t": apd_t.tolist(),
        "apd": apd,
        "ade": ade,
        "fde": fde,
        "npss": npss,
        "ndms_mean": float(nd.mean()),
    }, nd_w


def evaluate_social(
    models: dict[str, object],
    test_clips: list[fdata.Clip],
    n_obs: int = 32,
    n_pred: int = 250,
    n_scenes: int = 24,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    ndms_database: list[fdata.Clip] | None = None,
) -> dict:
    """Two-person scenes from held-out clips (real ones where the clips hold two people, else composed);
    long-horizon NDMS(t) and SSCP."""
    from forecast.train import composed_batch

    rng = np.random.default_rng(seed)
    L = min(n_obs + n_pred, max(c.n_frames for c in test_clips))
    multi = [c for c in test_clips if c.xyz_m.shape[1] >= 2]
    if multi:  # real two-person scenes (e.g. track files): observe them, SSCP against their real future
        mw = fdata.make_windows(multi, n_obs, 0, stride=8, persons="all", min_persons=2, max_persons=2)
        pick = rng.choice(len(mw), min(n_scenes, len(mw)), replace=False)
        obs = mw.x[pick]
        longm = fdata.make_windows(
            multi, L, 0, stride=max(L // 4, 1), persons="all", min_persons=2, max_persons=2
        )
        real = longm.x if len(longm) else None
        source = "real multi-person clips"
    else:  # compose two-person scenes from single-person clips
        single = fdata.make_windows(test_clips, n_obs, 0, stride=8, persons="each")
        obs = composed_batch(single.x[:, :, 0], 2, n_scenes, rng)  # (B,n_obs,2,J,3)
        longw = fdata.make_windows(test_clips, L, 0, stride=max(L // 2, 1), persons="each")
        real = composed_batch(longw.x[:, :, 0], 2, n_scenes, rng) if len(longw) else None
        source = "composed from single-person clips"
    n_scenes = len(obs)
    scorer = ndms_scorer_for(ndms_database or test_clips)
    names = get_skeleton(test_clips[0].skeleton).joint_names
    sscp = M.SSCP(lambda X: M.default_social_state(X, names), M.N_DEFAULT_STATES)
    out: dict = {
        "fps": fdata.TARGET_FPS,
        "n_obs": n_obs,
        "n_pred": n_pred,
        "n_scenes": n_scenes,
        "models": {},
        "sscp_real_frames": int(L),
        "scenes": source,
    }
    for name, model in models.items():
        if progress:
            progress(name)
        torch.manual_seed(seed)  # the same sampling noise on every run
        y = forecast_world(model, obs, np.ones((n_scenes, 2), bool), n_pred, 1)[:, 0]  # (B,H,2,J,3)
        nd = np.stack(
            [scorer.score_forecast(obs[b, :, p], y[b, None, :, p]) for b in range(n_scenes) for p in range(2)]
        ).mean(0)
        entry = {"ndms": nd.tolist(), "ndms_mean": float(nd.mean())}
        if real is not None:
            gen = [np.concatenate([obs[b], y[b]], 0)[:L] for b in range(n_scenes)]
            entry["sscp_jsd"] = sscp.distance(list(real), gen)
        out["models"][name] = entry
    return out


# ----------------------------------------------------------------------------- report

_MPJPE_MS = (80, 160, 400, 560, 1000)
_NDMS_S = (0.4, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 10.0)


def _at(curve: list[float], fps: float, t_s: float) -> float | None:
    i = int(round(t_s * fps)) - 1
    return float(curve[i]) if 0 <= i < len(curve) else None


def report_markdown(res: dict, title: str) -> str:
    fps = res["fps"]
    lines = [f"# {title}", ""]
    if "n_windows" in res:
        lines.append(
            f"{res['n_windows']} windows, observe {res['n_obs']} / forecast {res['n_pred']} frames at "
            f"{fps:g} Hz, {res['n_samples']} samples per stochastic model; skipped: {res['skipped']}"
        )
        lines += [
            "",
            "| model | "
            + " | ".join(f"MPJPE {ms} ms (mm)" for ms in _MPJPE_MS)
            + " | APD (m) | ADE (m) | FDE (m) | NPSS |",
            "|" + "---|" * (len(_MPJPE_MS) + 5),
        ]
        for name, r in res["models"].items():
            mp = [_at(r["mpjpe"], fps, ms / 1000) for ms in _MPJPE_MS]
            lines.append(
                f"| {name} | "
                + " | ".join("-" if v is None else f"{1000 * v:.1f}" for v in mp)
                + f" | {r['apd']:.3f} | {r['ade']:.3f} | {r['fde']:.3f} | {r['npss']:.3f} |"
            )
        lines.append("")
    horizon = res["n_pred"] / fps
    ts = [t for t in _NDMS_S if t <= horizon + 1e-9]
    lines += [
        "| model | "
        + " | ".join(f"NDMS {t:g} s" for t in ts)
        + " | NDMS mean |"
        + (" SSCP JSD |" if any("sscp_jsd" in r for r in res["models"].values()) else ""),
        "|" + "---|" * (len(ts) + 2 + any("sscp_jsd" in r for r in res["models"].values())),
    ]
    for name, r in res["models"].items():
        win = max(1, int(0.2 * fps))
        vals = [np.mean(r["ndms"][max(0, int(t * fps) - win) : int(t * fps)]) for t in ts]
        row = f"| {name} | " + " | ".join(f"{v:.3f}" for v in vals) + f" | {r['ndms_mean']:.3f} |"
        if "sscp_jsd" in r:
            row += f" {r['sscp_jsd']:.3f} |"
        lines.append(row)
    lines += ["", "NDMS at t = mean over the 0.2 s before t (motion words of κ = 8 frames)."]
    if any("ndms_at" in r for r in res["models"].values()):
        ts = sorted({t for r in res["models"].values() for t in r.get("ndms_at", {})}, key=float)
        ref = res.get("reference")
        lines += [
            "",
            f"NDMS with 95 % intervals (bootstrap over the {res.get('n_clips', '?')} test clips)"
            + (f"; Δ = paired difference to {ref} (same windows, same resampled clips)" if ref else ""),
            "",
            "| model | "
            + " | ".join(f"NDMS {t} s" for t in ts)
            + (" | " + " | ".join(f"Δ {t} s" for t in ts) if ref else "")
            + " |",
            "|" + "---|" * (1 + len(ts) * (2 if ref else 1)),
        ]
        for name, r in res["models"].items():
            if "ndms_at" not in r:
                continue
            cells = [f"{m:.3f} [{lo:.3f}, {hi:.3f}]" for m, lo, hi in (r["ndms_at"][t] for t in ts)]
            if ref:
                d = r.get("ndms_diff_at", {})
                cells += [
                    "-" if t not in d else f"{d[t][0]:+.3f} [{d[t][1]:+.3f}, {d[t][2]:+.3f}]" for t in ts
                ]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_report(res: dict, out_dir: str | os.PathLike, title: str = "Forecast evaluation") -> Path:
    """Write ``results.json``, ``report.md`` and ``<metric>.png`` (metric over the horizon) to out_dir."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(res, indent=1))
    atomic_write_text(out / "report.md", report_markdown(res, title))
    fps = res["fps"]
    for metric, label in (("mpjpe", "MPJPE (m)"), ("ndms", "NDMS"), ("apd_t", "APD (m)")):
        if not any(metric in r for r in res["models"].values()):
            continue
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for name, r in res["models"].items():
            if metric in r:
                t = np.arange(1, len(r[metric]) + 1) / fps
                ax.plot(t, r[metric], label=name)
        ax.set_xlabel("forecast horizon (s)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / f"{metric}.png", dpi=100)
        plt.close(fig)
    return out / "report.md"
