"""Evaluation protocols and the report (tables + one plot per metric over the horizon).

- ``evaluate_single``: test-split single-person windows (observe ``n_obs``, forecast ``n_pred`` frames at
  25 Hz), 50 samples per stochastic model by default (DLow, Tanke Table 6.2). Per model:
  MPJPE(t) in world coordinates; NDMS(t) (eq. 6.9-6.12, every sample scored, then averaged, as Z in
  eq. 6.9; motion words of root-centred poses with the heading kept, ``metrics.motion_words``) against a
  database D of the held-out clips *of the query's activity* (sec. 6.3.2; CMU clips grouped by their
  ``index.csv`` description, ``clips.clip_activities``) that contains the query's own clip, so the real
  future scores 1 (``ndms``, the seed's protocol); the stricter ``ndms_loo`` drops the query's own clip from
  D (windows whose activity has no other held-out clip are left out of it and counted in
  ``n_windows_loo``); ``ndms_word_first_frame`` is ``ndms`` with words normalised at their first frame
  only (the root's motion inside the word counts). APD, ADE, FDE, MMADE, MMFDE (DLow) on root-centred
  poses, the root trajectory's own best-of-S ADE/FDE (``root_ade``, ``root_fde``) and NPSS (reference code,
  root-centred poses, first sample) beside them; none of them changes when the data are moved. NDMS at
  0.4/1/2/3/4 s comes with 95 % intervals from a bootstrap that resamples whole clips, and each model's
  paired difference to a reference.
- ``evaluate_social``: two-person scenes, a long horizon (10 s), NDMS(t) per person (same database rule)
  and the SSCP distance (sec. 7.3): scenes composed from held-out single-person clips, and beside them the
  real multi-person clips (``real_scenes``: the CMU two-person take, multi-person track files).

``results.json`` layout (``RESULTS_LAYOUT`` is written into it): ``fps``, ``n_obs``, ``n_pred``, ...,
``models.<name>.<metric>``: per-frame lists for ``mpjpe`` (m), ``ndms``, ``ndms_loo`` and ``apd_t`` (m),
scalars for the rest, and ``ndms_at`` / ``ndms_loo_at`` / ``ndms_diff_at`` = {t_s: [mean, lo, hi]}.
"""

from __future__ import annotations

import logging
import os
import time
import zlib
from pathlib import Path

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.core.progress import Progress
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab import metrics as M
from roomcap.forecast.lab import protocol
from roomcap.forecast.lab.clips import clip_activities, composed_batch
from roomcap.forecast.lab.protocol import Table, results
from roomcap.forecast.runtime.predict import diffusion_rollout, forecast_world
from roomcap.forecast.runtime.registry import forecasts_the_scene
from roomcap.forecast.runtime.samples import write_samples
from roomcap.keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)

RESULTS_LAYOUT = {
    "fps": "frame rate of every per-frame list (Hz); entry i is forecast frame i + 1",
    "models.<name>.mpjpe": "per-frame MPJPE (m), world coordinates, mean over joints, windows and samples",
    "models.<name>.mpjpe_best_of_k": "per-frame MPJPE (m) of the model's sample closest to the truth in each "
    "window up to that frame, as ADE chooses it, mean over windows (Tanke Table 6.8's best-of-k; a "
    "deterministic model: its MPJPE)",
    "models.<name>.ndms": "per-frame NDMS, D = held-out clips of the query's activity incl. its own clip",
    "models.<name>.ndms_loo": "per-frame NDMS with the query's own clip left out of D",
    "models.<name>.ndms_word_first_frame": "per-frame NDMS, words normalised at their first frame only",
    "models.<name>.apd_t": "per-frame APD (m) between samples, root-centred",
    "models.<name>.apd|ade|fde|mmade|mmfde": "DLow's scalars (m) on root-centred poses, best of S samples",
    "models.<name>.root_ade|root_fde": "best-of-S ADE/FDE (m) of the root (mid-hip) trajectory alone",
    "models.<name>.npss": "NPSS (reference code) on root-centred poses, first sample",
    "models.<name>.ndms_mean|ndms_loo_mean": "mean of the per-frame curve",
    "models.<name>.ndms_at|ndms_loo_at|ndms_word_first_frame_at": "{t_s: [mean, 2.5 %, 97.5 %]}, mean over "
    "the 0.2 s before t, clip bootstrap",
    "models.<name>.ndms_diff_at|ndms_loo_diff_at": "paired difference to `reference`, same bootstrap",
}

BASELINES = ("real", "zero", "const", "slide", "fool")
BASELINE_ALIASES = {"zero_velocity": "zero", "constant_velocity": "const"}
DEFAULT_SAMPLES = 50


def check_baselines(names: list[str]) -> list[str]:
    """Canonical baseline names (``zero_velocity`` -> ``zero``, ...); unknown names are a ValueError."""
    out = []
    for n in names:
        c = BASELINE_ALIASES.get(n, n)
        if c not in BASELINES:
            raise InputError(f"unknown baseline '{n}'; choose from {', '.join(BASELINES)}")
        if c not in out:
            out.append(c)
    return out


class Real:
    """The real future as a 'forecast' (reference row)."""

    kind = "real"
    stochastic = False


def clip_group(name: str) -> int:
    """Stable integer id of a clip name (groups in the NDMS database)."""
    return zlib.crc32(name.encode()) & 0x7FFFFFFF


def _complete_runs(x: np.ndarray, kappa: int):
    ok = np.isfinite(x).all((1, 2))
    edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(int), 0]))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if b - a >= kappa:
            yield x[a:b]


def ndms_scorer_for(
    clips: list[fdata.Clip],
    kappa: int = 8,
    activities: dict[str, str] | None = None,
    min_words: int = M.MIN_GROUP_WORDS,
    word_form: str = "root_centred",
) -> M.NDMSScorer:
    """Database of motion words from clips (every complete run of every person); a word's group is its clip
    (``clip_group(name)``) and its activity ``activities[name]`` (None: one pool, activity ``all``);
    ``word_form``: ``metrics.WORD_FORMS``."""
    seqs, groups, acts = [], [], []
    for c in clips:
        for p in range(c.xyz_m.shape[1]):
            for run in _complete_runs(c.xyz_m[:, p], kappa):
                seqs.append(run)
                groups.append(clip_group(c.name))
                acts.append("all" if activities is None else activities.get(c.name, fdata.UNLABELLED))
    return M.NDMSScorer(
        seqs,
        get_skeleton(clips[0].skeleton).joint_names,
        kappa,
        groups,
        activities=acts,
        min_words=min_words,
        word_form=word_form,
    )


def evaluate_single(
    models: dict[str, object],
    test_clips: list[fdata.Clip],
    *,
    n_obs: int = 50,
    n_pred: int = 100,
    n_samples: int = DEFAULT_SAMPLES,
    stride: int = 5,
    max_windows: int = 400,
    seed: int = 0,
    progress: Progress | None = None,
    ndms_database: list[fdata.Clip] | None = None,
    reference: str | None = None,
    n_boot: int = 2000,
    activities: dict[str, str] | None = None,
    mm_threshold_m: float = 0.5,
    samples_dir: str | os.PathLike | None = None,
) -> dict:
    """``samples_dir``: write ``samples_<model>.npz`` there per model (:mod:`forecast.runtime.samples`).
    ``ndms_database``: clips for the NDMS database (default: the held-out clips); ``activities``: clip
    name -> activity (default ``clips.clip_activities``: CMU by ``index.csv``, others one group). The query's
    own clip is in D for ``ndms`` and left out for ``ndms_loo``. ``mm_threshold_m``: DLow's multi-modal
    ground-truth threshold on the last observed root-centred pose (0.5 as in DLow).

    -> {"fps", "layout", "models": {name: {"mpjpe": [H], "ndms": [H], "ndms_loo": [H], "apd_t": [H], "apd",
    "ade", "fde", "mmade", "mmfde", "root_ade", "root_fde", "npss", "ndms_at": {t: [mean, lo, hi]}, ...}},
    "n_windows", "n_windows_loo", "n_clips", "skipped", "wall_s"}."""
    t0 = time.perf_counter()
    ws = fdata.make_windows(test_clips, n_obs, n_pred, stride, persons="each")
    if len(ws) == 0:
        raise InputError(f"no test windows of {n_obs + n_pred} frames (skipped {ws.skipped})")
    db_clips = ndms_database or test_clips
    acts = clip_activities(list(test_clips) + list(db_clips)) if activities is None else activities
    sel = np.sort(np.random.default_rng(seed).choice(len(ws), min(max_windows, len(ws)), replace=False))
    x, mask = ws.x[sel, :, 0], ws.mask[sel, :, 0]
    names_sel = [test_clips[c].name for c in ws.clip[sel]]
    groups = np.array([clip_group(n) for n in names_sel])
    wact = [acts.get(n, fdata.UNLABELLED) for n in names_sel]
    obs, gt = x[:, :n_obs], x[:, n_obs:]
    scorer, scorer_ff = _ndms_scorers(db_clips, acts, set(wact))
    names = get_skeleton(test_clips[0].skeleton).joint_names
    lh, rh = fdata.hip_indices(names)
    gt_rc = M.root_centred(gt, lh, rh)
    mm_gt = M.multimodal_gt(M.root_centred(obs[:, -1], lh, rh), gt_rc, mm_threshold_m)
    out: dict = {
        "fps": ws.fps,
        "layout": RESULTS_LAYOUT,
        "n_obs": n_obs,
        "n_pred": n_pred,
        "n_samples": n_samples,
        "n_windows": len(sel),
        "skipped": ws.skipped,
        "activities": {n: acts.get(n, fdata.UNLABELLED) for n in sorted(set(names_sel))},
        "mm_threshold_m": mm_threshold_m,
        "mm_gt_mean": float(np.mean([len(g) for g in mm_gt])),
        "models": {},
    }
    out["n_clips"] = int(len(np.unique(groups)))
    per_window, per_window_loo, per_window_ff = {}, {}, {}
    for i, (name, model) in enumerate(models.items()):
        _report(progress, "eval models", i, len(models), name)
        tm = time.perf_counter()
        y = _forecast(model, obs, gt, n_pred, n_samples, seed)
        if samples_dir is not None:
            write_samples(samples_dir, name, y, obs, gt, ws.fps, names, wact, names_sel)
        r, per_window[name], per_window_loo[name] = _single_metrics(
            y, gt, obs, mask[:, n_obs:], groups, wact, scorer, (lh, rh), mm_gt
        )
        per_window_ff[name] = _ndms_per_window(scorer_ff, obs, y, wact)
        r["ndms_word_first_frame"] = per_window_ff[name].mean(0).tolist()
        r["wall_s"] = time.perf_counter() - tm
        if forecasts_the_scene(model):
            r["rollout"] = diffusion_rollout(model, n_pred)
        out["models"][name] = r
    _report(progress, "eval models", len(models), len(models))
    _add_ndms_intervals(
        out, per_window, per_window_loo, per_window_ff, groups, ws.fps, n_pred, n_boot, seed, reference
    )
    out["wall_s"] = time.perf_counter() - t0
    return out


def _ndms_scorers(db_clips: list[fdata.Clip], acts: dict[str, str], queried: set[str]) -> tuple:
    """The NDMS scorers (per frame, and with the word of the first frame) over the database clips of the
    activities queried (a short clip of another activity is not needed)."""
    db_clips = [c for c in db_clips if acts.get(c.name, fdata.UNLABELLED) in queried]
    scorer = ndms_scorer_for(db_clips, activities=acts)
    scorer_ff = ndms_scorer_for(db_clips, activities=acts, word_form="word_first_frame")
    return scorer, scorer_ff


def _ndms_per_window(scorer, obs: np.ndarray, y: np.ndarray, wact: list[str]) -> np.ndarray:
    """NDMS (B,H) of each window's forecasts ``y`` (B,S,H,J,3) against the windows' activities."""
    return np.stack([scorer.score_forecast(obs[b], y[b], None, wact[b]) for b in range(len(y))])


def _forecast(model, obs: np.ndarray, gt: np.ndarray, n_pred: int, n_samples: int, seed: int) -> np.ndarray:
    """A model's forecasts (B,S,H,J,3) of the windows ``obs`` (B,T,J,3) (``Real``: the ground truth ``gt``),
    with the same sampling noise on every run."""
    if isinstance(model, Real):
        return gt[:, None]
    S = n_samples if getattr(model, "stochastic", False) else 1
    torch.manual_seed(seed)  # the same sampling noise on every run
    return forecast_world(model, obs[:, :, None], None, n_pred, S)[:, :, :, 0]  # (B,S,H,J,3)


def _add_ndms_intervals(
    out: dict,
    per_window: dict[str, np.ndarray],
    per_window_loo: dict[str, np.ndarray],
    per_window_ff: dict[str, np.ndarray],
    groups: np.ndarray,
    fps: float,
    n_pred: int,
    n_boot: int,
    seed: int,
    reference: str | None,
) -> None:
    """Add to each model's results the NDMS at ``NDMS_CI_S`` with cluster-bootstrap intervals (by clip),
    leave-one-out and word-first-frame too, and the paired differences to ``reference``."""
    loo_ok = np.isfinite(next(iter(per_window_loo.values()))).all(1) if per_window_loo else np.zeros(0, bool)
    out["n_windows_loo"] = int(loo_ok.sum())
    boot = _cluster_bootstrap_index(groups, n_boot, seed)
    boot_loo = _cluster_bootstrap_index(groups[loo_ok], n_boot, seed) if loo_ok.any() else None
    ref = reference if reference in per_window else None
    out["reference"] = ref
    ts = [t for t in NDMS_CI_S if t * fps <= n_pred]
    for name in per_window:
        r = out["models"][name]
        w, wl = per_window[name], per_window_loo[name][loo_ok]
        r["ndms_at"] = {f"{t:g}": _ci(ndms_at(w, fps, t), boot) for t in ts}
        r["ndms_word_first_frame_at"] = {
            f"{t:g}": _ci(ndms_at(per_window_ff[name], fps, t), boot) for t in ts
        }
        if boot_loo is not None:
            r["ndms_loo_at"] = {f"{t:g}": _ci(ndms_at(wl, fps, t), boot_loo) for t in ts}
        if ref is not None and name != ref:
            r["ndms_diff_at"] = {
                f"{t:g}": _ci(ndms_at(w, fps, t) - ndms_at(per_window[ref], fps, t), boot) for t in ts
            }
            if boot_loo is not None:
                wr = per_window_loo[ref][loo_ok]
                r["ndms_loo_diff_at"] = {
                    f"{t:g}": _ci(ndms_at(wl, fps, t) - ndms_at(wr, fps, t), boot_loo) for t in ts
                }


NDMS_CI_S = (0.4, 1.0, 2.0, 3.0, 4.0)


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


def _single_metrics(y, gt, obs, mask_fut, groups, wact, scorer, hips, mm_gt):
    """y (B,S,H,J,3) world -> (metrics, per-window NDMS (B,H), per-window leave-clip-out NDMS (B,H))."""
    B, S, H = y.shape[:3]
    lh, rh = hips
    mp = M.mpjpe(y, np.broadcast_to(gt[:, None], y.shape), np.broadcast_to(mask_fut[:, None], y.shape[:-1]))
    mp_best = M.mpjpe_best_of_k(y, gt, mask_fut)
    nd_w = np.stack([scorer.score_forecast(obs[b], y[b], None, wact[b]) for b in range(B)])
    loo_w = np.stack([scorer.score_forecast(obs[b], y[b], int(groups[b]), wact[b]) for b in range(B)])
    apd_t = np.zeros(H)
    apd, ade, fde, mmade, mmfde, rade, rfde = (np.zeros(B) for _ in range(7))
    first_rc = np.empty((B, H, *y.shape[3:]))
    for b in range(B):
        yc = M.root_centred(y[b], lh, rh)  # (S,H,J,3)
        gc = M.root_centred(gt[b], lh, rh)
        first_rc[b] = yc[0]
        if S > 1:
            flat = yc.reshape(S, H, -1)
            iu = np.triu_indices(S, 1)
            apd_t += np.linalg.norm(flat[iu[0]] - flat[iu[1]], axis=-1).mean(0) / B
            apd[b] = M.apd(yc)
        ade[b], fde[b] = M.ade(yc, gc), M.fde(yc, gc)
        mmade[b], mmfde[b] = M.mmade(yc, mm_gt[b]), M.mmfde(yc, mm_gt[b])
        yr, gr = M.root_trajectory(y[b], lh, rh), M.root_trajectory(gt[b], lh, rh)
        rade[b], rfde[b] = M.ade(yr, gr), M.fde(yr, gr)
    npss = M.npss(first_rc, M.root_centred(gt, lh, rh))
    with np.errstate(invalid="ignore"):
        nd_loo = np.nanmean(loo_w, 0) if np.isfinite(loo_w).any() else np.full(H, np.nan)
    nd = nd_w.mean(0)
    return (
        {
            "mpjpe": mp.tolist(),
            "mpjpe_best_of_k": mp_best.tolist(),
            "ndms": nd.tolist(),
            "ndms_loo": nd_loo.tolist(),
            "apd_t": apd_t.tolist(),
            "apd": float(apd.mean()),
            "ade": float(ade.mean()),
            "fde": float(fde.mean()),
            "mmade": float(mmade.mean()),
            "mmfde": float(mmfde.mean()),
            "root_ade": float(rade.mean()),
            "root_fde": float(rfde.mean()),
            "npss": npss,
            "ndms_mean": float(nd.mean()),
            "ndms_loo_mean": float(np.nanmean(nd_loo)) if np.isfinite(nd_loo).any() else float("nan"),
        },
        nd_w,
        loo_w,
    )


def evaluate_social(
    models: dict[str, object],
    test_clips: list[fdata.Clip],
    *,
    n_obs: int = 32,
    n_pred: int = 250,
    n_scenes: int = 24,
    seed: int = 0,
    progress: Progress | None = None,
    ndms_database: list[fdata.Clip] | None = None,
    real_scenes: list[fdata.Clip] | None = None,
    activities: dict[str, str] | None = None,
) -> dict:
    """Two-person scenes composed from the held-out single-person clips (``models``) and, beside them, the
    real multi-person clips among ``test_clips`` plus ``real_scenes`` (``real.models``, e.g. the CMU
    two-person take): long-horizon NDMS(t) per person (D = held-out clips of the person's activity, own clip
    included) and SSCP against the real scenes of the same kind."""
    t0 = time.perf_counter()
    single = [c for c in test_clips if c.xyz_m.shape[1] == 1]
    multi = [c for c in test_clips if c.xyz_m.shape[1] >= 2] + list(real_scenes or [])
    db_clips = list(ndms_database or single or test_clips) + multi  # the real scenes' own motion too
    acts = clip_activities(list(test_clips) + db_clips + multi) if activities is None else activities
    scorer = ndms_scorer_for(db_clips, activities=acts)
    names = get_skeleton(test_clips[0].skeleton).joint_names
    sscp = M.SSCP(lambda X: M.default_social_state(X, names), M.N_DEFAULT_STATES)
    out: dict = {
        "fps": fdata.TARGET_FPS,
        "layout": RESULTS_LAYOUT,
        "n_obs": n_obs,
        "n_pred": n_pred,
        "models": {},
        "scenes": "composed from single-person clips",
    }
    rng = np.random.default_rng(seed)
    if single:
        L = min(n_obs + n_pred, max(c.n_frames for c in single))
        sw = fdata.make_windows(single, n_obs, 0, stride=8, persons="each")
        obs, idx = composed_batch(sw.x[:, :, 0], 2, n_scenes, rng, return_index=True)  # (B,n_obs,2,J,3)
        act = [[acts.get(single[sw.clip[i]].name, fdata.UNLABELLED) for i in row] for row in idx]
        longw = fdata.make_windows(single, L, 0, stride=max(L // 2, 1), persons="each")
        real = list(composed_batch(longw.x[:, :, 0], 2, n_scenes, rng)) if len(longw) else None
        out["n_scenes"] = len(obs)
        out["sscp_real_frames"] = int(L)
        out["models"] = _social_models(models, obs, act, scorer, sscp, real, n_pred, L, seed, progress)
    if multi:
        mw = fdata.make_windows(multi, n_obs, 0, stride=8, persons="all", min_persons=2, max_persons=2)
        if len(mw):
            act = [[acts.get(multi[c].name, fdata.UNLABELLED)] * 2 for c in mw.clip]
            real = [c.xyz_m[:, :2] for c in multi if np.isfinite(c.xyz_m[:, :2]).all()]
            Lr = n_obs + n_pred if not real else min(n_obs + n_pred, min(len(r) for r in real))
            out["real"] = {
                "clips": [c.name for c in multi],
                "n_scenes": len(mw),
                "sscp_real_frames": int(Lr),
                "models": _social_models(
                    models, mw.x, act, scorer, sscp, real or None, n_pred, Lr, seed, None, mw.person_mask
                ),
            }
    out["wall_s"] = time.perf_counter() - t0
    return out


def _social_models(models, obs, act, scorer, sscp, real, n_pred, L, seed, progress, person_mask=None):
    B = len(obs)
    pm = np.ones((B, 2), bool) if person_mask is None else person_mask
    res = {}
    for i, (name, model) in enumerate(models.items()):
        _report(progress, "eval models", i, len(models), name)
        if isinstance(model, Real):
            continue
        torch.manual_seed(seed)  # the same sampling noise on every run
        y = forecast_world(model, obs, pm, n_pred, 1)[:, 0]  # (B,H,2,J,3)
        nd = np.stack(
            [
                scorer.score_forecast(obs[b, :, p], y[b, None, :, p], None, act[b][p])
                for b in range(B)
                for p in range(2)
                if pm[b, p]
            ]
        ).mean(0)
        entry = {"ndms": nd.tolist(), "ndms_mean": float(nd.mean())}
        if forecasts_the_scene(model):
            entry["rollout"] = diffusion_rollout(model, n_pred)
        if real is not None:
            gen = [np.concatenate([obs[b], y[b]], 0)[:L] for b in range(B)]
            entry["sscp_jsd"] = sscp.distance([r[:L] for r in real], gen)
        res[name] = entry
    _report(progress, "eval models", len(models), len(models))
    return res


def _report(progress: Progress | None, task: str, done: int, total: int, name: str | None = None) -> None:
    """``done`` of ``total`` models scored (the progress protocol); the next one's name goes to the log."""
    if progress is not None:
        progress(task, done, total)
    if name is not None:
        log.info("%s: %s (%d of %d)", task, name, done + 1, total)


# ----------------------------------------------------------------------------- report

_MPJPE_MS = (80, 160, 400, 560, 1000)
_NDMS_S = (0.4, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 10.0)


def _at(curve: list[float], fps: float, t_s: float) -> float | None:
    i = int(round(t_s * fps)) - 1
    return float(curve[i]) if 0 <= i < len(curve) else None


def _nanmean(a) -> float:
    a = np.asarray(a, float)
    return float(a[np.isfinite(a)].mean()) if np.isfinite(a).any() else float("nan")


def _f(v, fmt=".3f") -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, fmt)


def _ndms_table(title: str, models: dict, fps: float, n_pred: int, key: str = "ndms") -> Table:
    """NDMS (or its variant ``key``) at each whole second, its mean, and SSCP where scored."""
    horizon = n_pred / fps
    ts = [t for t in _NDMS_S if t <= horizon + 1e-9]
    has_sscp = any("sscp_jsd" in r for r in models.values())
    label = {"ndms": "NDMS", "ndms_loo": "NDMS loo", "ndms_word_first_frame": "NDMS ff"}.get(key, key)
    columns = ["model", *(f"{label} {t:g} s" for t in ts), "mean", *(["SSCP JSD"] if has_sscp else [])]
    win = max(1, int(0.2 * fps))
    rows = []
    for name, r in models.items():
        if key not in r:
            continue
        c = np.asarray(r[key], float)
        vals = [_nanmean(c[max(0, int(round(t * fps)) - win) : int(round(t * fps))]) for t in ts]
        rows.append(
            [name, *(_f(v) for v in vals), _f(_nanmean(c))] + ([_f(r.get("sscp_jsd"))] if has_sscp else [])
        )
    return Table(title, columns, rows)


NDMS_NOTE = (
    "NDMS at t = mean over the 0.2 s before t (motion words of κ = 8 frames); ndms: D = held-out clips of "
    "the query's activity incl. its own clip, words of root-centred poses with the heading kept; ndms_loo: "
    "the query's own clip left out; NDMS ff (ndms_word_first_frame): words normalised at their first frame."
)


def _report_parts(res: dict) -> tuple[list[str], list[Table], list[str]]:
    """The report's notes, tables (MPJPE and the distribution metrics, NDMS and its variants, the real
    multi-person clips, the intervals and paired differences) and footnotes."""
    fps, notes, tables = res["fps"], [], []
    footer = [NDMS_NOTE]
    if "n_windows" in res:
        notes.append(
            f"{res['n_windows']} windows ({res.get('n_clips', '?')} clips), observe {res['n_obs']} / "
            f"forecast {res['n_pred']} frames at {fps:g} Hz, {res['n_samples']} samples per stochastic "
            f"model; leave-clip-out NDMS on {res.get('n_windows_loo', '?')} windows; "
            f"skipped: {res['skipped']}; evaluation {res.get('wall_s', float('nan')):.0f} s"
        )
        keys = ("apd", "ade", "fde", "mmade", "mmfde", "root_ade", "root_fde", "npss")
        columns = ["model", *(f"MPJPE {ms} ms (mm)" for ms in _MPJPE_MS)]
        columns += ["APD (m)", "ADE (m)", "FDE (m)", "MMADE (m)", "MMFDE (m)", "root ADE (m)", "root FDE (m)"]
        rows = []
        for name, r in res["models"].items():
            mp = [_at(r["mpjpe"], fps, ms / 1000) for ms in _MPJPE_MS]
            rows.append(
                [name, *("-" if v is None else f"{1000 * v:.1f}" for v in mp), *(_f(r.get(k)) for k in keys)]
            )
        tables.append(Table("MPJPE and the distribution metrics", [*columns, "NPSS"], rows))
        k = res["n_samples"]
        best = [
            [
                name,
                *(
                    "-" if v is None else f"{1000 * v:.1f}"
                    for v in (_at(r["mpjpe_best_of_k"], fps, ms / 1000) for ms in _MPJPE_MS)
                ),
            ]
            for name, r in res["models"].items()
            if "mpjpe_best_of_k" in r
        ]
        if best:
            tables.append(
                Table(
                    f"Best-of-{k} MPJPE",
                    ["model", *(f"best-of-{k} MPJPE {ms} ms (mm)" for ms in _MPJPE_MS)],
                    best,
                )
            )
        footer.insert(
            0,
            "APD/ADE/FDE/MMADE/MMFDE/NPSS on root-centred poses; MPJPE in world coordinates (mean over "
            "samples; best-of-k: per window the sample closest to the truth up to t, as ADE chooses, Tanke "
            "Table 6.8).",
        )
    tables.append(_ndms_table("NDMS", res["models"], fps, res["n_pred"], "ndms"))
    for extra in ("ndms_loo", "ndms_word_first_frame"):
        if any(extra in r for r in res["models"].values()):
            tables.append(_ndms_table(extra, res["models"], fps, res["n_pred"], extra))
    if "real" in res:
        rr = res["real"]
        title = (
            f"Real multi-person clips ({', '.join(rr['clips'])}; {rr['n_scenes']} scenes; SSCP against their "
            f"{rr['sscp_real_frames']} real frames)"
        )
        tables.append(_ndms_table(title, rr["models"], fps, res["n_pred"], "ndms"))
    ref = res.get("reference")
    for key in ("ndms", "ndms_loo", "ndms_word_first_frame"):
        if not any(f"{key}_at" in r for r in res["models"].values()):
            continue
        ts = sorted({t for r in res["models"].values() for t in r.get(f"{key}_at", {})}, key=float)
        title = f"{key} with 95 % intervals (bootstrap over the test clips)"
        title += f"; Δ = paired difference to {ref} (same windows, same resampled clips)" if ref else ""
        columns = ["model", *(f"{key} {t} s" for t in ts), *((f"Δ {t} s" for t in ts) if ref else ())]
        rows = []
        for name, r in res["models"].items():
            if f"{key}_at" not in r:
                continue
            row = [name, *(f"{m:.3f} [{lo:.3f}, {hi:.3f}]" for m, lo, hi in (r[f"{key}_at"][t] for t in ts))]
            if ref:
                d = r.get(f"{key}_diff_at", {})
                row += ["-" if t not in d else f"{d[t][0]:+.3f} [{d[t][1]:+.3f}, {d[t][2]:+.3f}]" for t in ts]
            rows.append(row)
        tables.append(Table(title, columns, rows))
    return notes, tables, footer


def as_results(res: dict, title: str = "Forecast evaluation") -> dict:
    """An evaluation's dict (:func:`evaluate_single`, :func:`evaluate_social`) in the one results schema."""
    return results("cmu", title, *_report_parts(res), **res)


def write_report(res: dict, out_dir: str | os.PathLike, title: str = "Forecast evaluation") -> Path:
    """Write ``results.json`` and ``report.md`` (the one schema and renderer, :mod:`lab.protocol`) and
    ``<metric>.png`` (metric over the horizon) to out_dir."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    protocol.write(as_results(res, title), out)
    fps = res["fps"]
    plots = [
        ("mpjpe", "MPJPE (m)"),
        ("ndms", "NDMS"),
        ("ndms_loo", "NDMS, own clip left out"),
        ("apd_t", "APD (m)"),
    ]
    for metric, label in plots:
        if not any(metric in r for r in res["models"].values()):
            continue
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for name, r in res["models"].items():
            if metric in r:
                t = np.arange(1, len(r[metric]) + 1) / fps
                ax.plot(t, r[metric], label=name)
        if metric == "ndms" and "real" in res:
            for name, r in res["real"]["models"].items():
                t = np.arange(1, len(r["ndms"]) + 1) / fps
                ax.plot(t, r["ndms"], "--", label=f"{name} (real two-person)")
        ax.set_xlabel("forecast horizon (s)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / f"{metric}.png", dpi=100)
        plt.close(fig)
    return out / "report.md"
