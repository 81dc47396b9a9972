"""The Humans-in-Kitchens benchmark of Tanke ch. 8.3 as one command: ``forecast eval --protocol hik DATA``.

Protocol (sec. 8.3): kitchens A-C are for training, D is the test kitchen. Six activities: the motion
activities *walking* and *sitting down* and the human-object interactions with the *whiteboard*, *sink*,
*cupboard* and *coffee machine* (every HiK activity that names the object). Every onset of an activity of
a person in D is one test case, and only that person is scored: for the object interactions the last
observed frame t is the onset, for the motion activities t = onset + 10 "such that a few frames of the
motion are already observed". 50 frames (2 s at 25 Hz) are observed; short-term: 25 frames forecast, MPJPE
at frames 5/15/25; long-term: 250 frames forecast, NDMS (κ = 8) at frames 1/25/100/200/250. Cases where the
person is not tracked on every frame of the window are skipped and counted.

NDMS database per activity: the real windows (observation and the 250 real future frames) of every test
case of that activity, so D holds the query's own ground truth (``ndms``, the seed's rule); ``ndms_loo``
leaves out the query person's own file. Poses stay in the HiK ``smpl29`` skeleton; models must be
``smpl29`` checkpoints (trained on A-C) - the body19 CMU checkpoints are refused with a clear message.
"""

from __future__ import annotations

import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab import metrics as M
from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.protocol import Table, results
from roomcap.forecast.runtime.predict import forecast_world
from roomcap.forecast.runtime.samples import write_samples
from roomcap.keypoints.skeletons import get_skeleton

N_OBS, N_SHORT, N_LONG, MOTION_LEAD = 50, 25, 250, 10
MPJPE_FRAMES = (5, 15, 25)
NDMS_FRAMES = (1, 25, 100, 200, 250)


def _dense(p: fdata.KitchenPerson) -> tuple[int, np.ndarray, np.ndarray]:
    """-> (first frame, poses (F,29,3) NaN where absent, activity flags (F,82) bool) on the frame axis."""
    f0 = int(p.frames.min())
    F = int(p.frames.max()) - f0 + 1
    x = np.full((F, 29, 3), np.nan, np.float32)
    a = np.zeros((F, p.act.shape[1]), bool)
    x[p.frames - f0] = p.poses3d
    a[p.frames - f0] = p.act > 0.5
    return f0, x, a


def kitchen_cases(people: list[fdata.KitchenPerson]) -> tuple[dict, Counter]:
    """Test cases of kitchen D: {activity: [(person name, obs (50,29,3), future (≤250,29,3))]}, skip counts.
    ``future`` holds the 250 real frames when the person is tracked throughout, else the first 25 (short-term
    only) - cases without 25 tracked future frames are skipped."""
    cases: dict = {a: [] for a in fdata.HIK_ACTIVITIES}
    skipped: Counter[str] = Counter()
    for p in people:
        if p.kitchen != fdata.HIK_TEST_KITCHEN:
            continue
        _, x, act = _dense(p)
        ok = np.isfinite(x).all((1, 2))
        for name, (cue, cols) in fdata.HIK_ACTIVITIES.items():
            flag = act[:, list(cols)].any(1)
            onsets = np.flatnonzero(flag & ~np.r_[False, flag[:-1]])
            for o in onsets:
                t = int(o) + (MOTION_LEAD if cue == "motion" else 0)
                a, b = t - N_OBS + 1, t + 1
                if a < 0 or b + N_SHORT > len(x) or not ok[a : b + N_SHORT].all():
                    skipped[f"{name}: person not tracked on the observed and first 25 frames"] += 1
                    continue
                n_fut = N_LONG if b + N_LONG <= len(x) and ok[b : b + N_LONG].all() else N_SHORT
                cases[name].append((p.name, x[a:b], x[b : b + n_fut]))
    return cases, skipped


def evaluate_hik(
    folder,
    baselines: list[str],
    checkpoints: list[str] = (),
    n_samples: int = 50,
    seed: int = 0,
    samples_dir=None,
) -> dict:
    """Run the ch. 8.3 protocol on the HiK person files under folder -> results (``lab.protocol``).
    ``samples_dir``: write the short-horizon forecasts there, ``samples_<model>.npz``
    (:mod:`roomcap.forecast.runtime.samples`; activity = the case's activity, clip = its person file)."""
    t0 = time.perf_counter()
    people = fdata.load_kitchen_people(folder)
    kitchens = sorted({p.kitchen for p in people})
    if fdata.HIK_TEST_KITCHEN not in kitchens:
        raise InputError(f"no person files of the test kitchen D under {folder} (kitchens found: {kitchens})")
    names = get_skeleton("smpl29").joint_names
    lh, rh = fdata.hip_indices(names)
    train_names = {p.name for p in people if p.kitchen in fdata.HIK_TRAIN_KITCHENS}
    test_names = {p.name for p in people if p.kitchen == fdata.HIK_TEST_KITCHEN}
    models = _hik_models(baselines, checkpoints, (lh, rh), test_names)
    cases, skipped = kitchen_cases(people)
    out: dict = {
        "fps": fdata.KITCHEN_FPS,
        "design": "Tanke ch. 8.3: train A-C, test D, 50 in, 25 out (MPJPE), 250 out (NDMS)",
        "n_train_files": len(train_names),
        "n_test_files": len(test_names),
        "n_samples": n_samples,
        "skipped": dict(skipped),
        "activities": {},
    }
    kept: dict[str, list] = {}
    for act, cs in cases.items():
        if not cs:
            out["activities"][act] = {"n_cases": 0, "models": {}}
            continue
        long_cases = [c for c in cs if len(c[2]) >= N_LONG]
        entry: dict = {"n_cases": len(cs), "n_cases_long": len(long_cases), "models": {}}
        scorer = None
        if long_cases:
            db = [np.concatenate([o, f], 0) for _, o, f in long_cases]
            scorer = M.NDMSScorer(
                db, names, 8, groups=[E.clip_group(n) for n, _, _ in long_cases], activities=[act] * len(db)
            )
        obs = np.stack([o for _, o, _ in cs])
        gt_s = np.stack([f[:N_SHORT] for _, _, f in cs])
        for mname, model in models.items():
            S = n_samples if getattr(model, "stochastic", False) else 1
            if isinstance(model, E.Real):
                y_s = gt_s[:, None]
            else:
                torch.manual_seed(seed)
                y_s = forecast_world(model, obs[:, :, None], None, N_SHORT, S, hips=(lh, rh))[:, :, :, 0]
            if samples_dir is not None:
                kept.setdefault(mname, []).append((y_s, obs, gt_s, [act] * len(obs), [n for n, _, _ in cs]))
            mp = M.mpjpe(y_s, np.broadcast_to(gt_s[:, None], y_s.shape))
            r = {"mpjpe": mp.tolist(), "mpjpe_at": {str(f): float(mp[f - 1]) for f in MPJPE_FRAMES}}
            if scorer is not None:
                r.update(_long_ndms(model, scorer, long_cases, act, S, seed, (lh, rh)))
            entry["models"][mname] = r
        out["activities"][act] = entry
    _write_kept_samples(kept, samples_dir, names)
    out["wall_s"] = time.perf_counter() - t0
    return results("hik", "Humans in Kitchens (Tanke ch. 8.3)", *_report(out), **out)


def _hik_models(
    baselines: list[str], checkpoints, hips: tuple[int, int], test_names: set[str]
) -> dict[str, object]:
    """The baselines (but the body19 fool) and the smpl29 checkpoints, none trained on a test-kitchen file."""
    lh, rh = hips
    models: dict = {}
    for b in baselines:
        if b == "real":
            models["real"] = E.Real()
        elif b == "fool":
            continue  # the fool's clusters are body19 (train.fool_model); not part of the ch. 8.3 tables
        else:
            models[b] = T.baseline(b, lh, rh)
    for ck in checkpoints:
        try:
            m, meta = T.load_checkpoint(ck, skeleton="smpl29")
        except Exception as e:  # the checkpoint reader's message says what is wrong
            raise InputError(f"{ck}: {e}") from None
        leak = sorted(set(meta["extra"].get("train_clips", [])) & test_names)
        if leak:
            raise InputError(f"{ck} was trained on test-kitchen files {leak[:5]}; train on kitchens A-C only")
        models[Path(ck).stem] = m
    return models


def _long_ndms(
    model, scorer: M.NDMSScorer, long_cases: list, act: str, S: int, seed: int, hips: tuple[int, int]
) -> dict:
    """NDMS over the long horizon of the long cases (with the query's own clip and leave-one-out), per
    frame and at ``NDMS_FRAMES``."""
    lh, rh = hips
    r: dict = {}
    lo = np.stack([o for _, o, _ in long_cases])
    if isinstance(model, E.Real):
        y_l = np.stack([f for _, _, f in long_cases])[:, None]
    else:
        torch.manual_seed(seed)
        y_l = forecast_world(model, lo[:, :, None], None, N_LONG, S, hips=(lh, rh))[:, :, :, 0]
    nd = np.stack([scorer.score_forecast(lo[i], y_l[i], None, act) for i in range(len(lo))])
    loo = np.stack(
        [scorer.score_forecast(lo[i], y_l[i], E.clip_group(long_cases[i][0]), act) for i in range(len(lo))]
    )
    with np.errstate(invalid="ignore"):
        loo_c = np.nanmean(loo, 0) if np.isfinite(loo).any() else np.full(N_LONG, np.nan)
    r["ndms"] = nd.mean(0).tolist()
    r["ndms_loo"] = loo_c.tolist()
    r["ndms_at"] = {str(f): float(nd.mean(0)[f - 1]) for f in NDMS_FRAMES}
    r["ndms_loo_at"] = {str(f): float(loo_c[f - 1]) for f in NDMS_FRAMES}
    return r


def _write_kept_samples(kept: dict[str, list], samples_dir, names) -> None:
    """Write each model's short-horizon forecasts of every activity as ``samples_<model>.npz``."""
    for mname, parts in kept.items():
        pred = np.concatenate([p[0] for p in parts])
        obs_k = np.concatenate([p[1] for p in parts])
        gt_k = np.concatenate([p[2] for p in parts])
        acts = [a for p in parts for a in p[3]]
        clips = [c for p in parts for c in p[4]]
        write_samples(samples_dir, mname, pred, obs_k, gt_k, fdata.KITCHEN_FPS, names, acts, clips)


def _report(res: dict) -> tuple[list[str], list[Table]]:
    """The report's note (design, files, skips) and its one table: per activity and model, MPJPE at the short
    horizons and NDMS (own clip in and left out) at the long ones."""
    notes = [
        f"{res['design']}; {res['n_train_files']} training files (A-C), {res['n_test_files']} test files "
        f"(D); skipped: {res['skipped']}; {res['wall_s']:.1f} s"
    ]
    columns = ["activity", "cases (long)", "model", *(f"MPJPE {f} (cm)" for f in MPJPE_FRAMES)]
    columns += [f"NDMS {f}" for f in NDMS_FRAMES] + [f"ndms_loo {f}" for f in NDMS_FRAMES]
    rows = []
    for act, e in res["activities"].items():
        for m, r in e["models"].items():
            row = [act, f"{e['n_cases']} ({e.get('n_cases_long', 0)})", m]
            row += [f"{100 * r['mpjpe_at'][str(f)]:.1f}" for f in MPJPE_FRAMES]
            for key in ("ndms_at", "ndms_loo_at"):
                d = r.get(key, {})
                row += [
                    "-" if str(f) not in d or not np.isfinite(d[str(f)]) else f"{d[str(f)]:.3f}"
                    for f in NDMS_FRAMES
                ]
            rows.append(row)
        if not e["models"]:
            rows.append([act, "0", "-", *["-"] * (len(MPJPE_FRAMES) + 2 * len(NDMS_FRAMES))])
    return notes, [Table("", columns, rows)]
