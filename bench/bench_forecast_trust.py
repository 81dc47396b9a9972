"""Why the seed's models (intention, GRU, Social Diffusion) do or do not beat zero velocity at 400 ms: the
measurements behind the diagnosis, on the CMU windows of ``forecast eval --data cmu`` (observe 2 s, forecast
4 s at 25 Hz, stride 5, at most ``--windows`` windows drawn with ``--seed``), on the validation split by
default (``--split test`` for the one test run).

Per model (mean over windows; a stochastic model's ``--samples`` samples):

- rate: the checkpoint's frame rate against the data's (the evaluation resamples the data to 25 Hz);
- MPJPE at 40 / 80 / 160 / 400 / 1000 ms, mean over samples and best-of-k (per window the sample closest to
  the truth over the forecast up to that horizon, as ADE chooses it: Tanke Table 6.8's protocol,
  ``metrics.closest_sequence_error``), and zero velocity's beside it;
- root handling: the 400 ms error split into the root's (mid-hip) error and the root-centred pose error;
- continuity: the first forecast frame's displacement from the last observed pose (mm per joint) against
  the real one and against the last observed frame-to-frame displacement, and the velocity jump
  ``|(y_1 - x_0) - (x_0 - x_-1)|``;
- damping: the forecast's mean joint speed over the first 0.4 s, 0.4-1 s and 1-2 s relative to the real
  future's;
- anatomy: how far the limb bones (upper arm, forearm, thigh, shank) are from their length in the last
  observed frame over 0-1, 1-2 and 2-4 s (mm; real motion: 0).

    PYTHONPATH=WT/.pp python bench/bench_forecast_trust.py forecast/checkpoints/intention_cmuall.pt ... \
        [--split val|test] [--data cmu|cmu-all] [--windows 200] [--samples 10] [--seed 0] [--ndms]

A checkpoint may carry sampler settings to try: ``CKPT.pt:sample_temp=1.2,sample_dct=24`` (model attributes
set after loading). ``--ndms``: NDMS at 2 / 4 s too, own clip in D, left out (windows of activities with
another clip of the split) and with clips weighted equally (``evaluate.ndms_scorer_for``, the split's clips
as D).

``--rescore-cmu8 SAMPLES_DIR``: the body19 variant of the CMU 8-action benchmark (``forecast eval --protocol
cmu8 --save-samples DIR``) rescored from its ``samples_<model>@body19.npz``: mean over samples (as the
protocol reports) and best-of-k, at the protocol's horizons, in its units, per action and averaged.

``--keep-bones``: each model also with its forecast's bones set to their length in the last observed frame
(directions kept), to see what NDMS makes of a forecast that keeps its body.

``--table RESULTS.json [RESULTS.json ...]``: the controls-against-models table of ``forecast eval`` runs
(MPJPE 80 / 400 / 1000 ms, mean over samples and best-of-k; ndms, ndms_loo and the word-first-frame form at
2 / 4 s), one row per model and run, nothing else computed.

Found with it (Social Diffusion's root, ``models.diffusion``'s ``lag_hold``): the seed standardises each
channel to zero mean and unit std (sec. 7.2.3). Anchored at the last observed frame with one std per channel
over a 144-frame window, the root offset's std is 0.48 / 0.64 m (x / y), while its real spread 1 / 10 frames
after the anchor is 1-2 / 7-16 cm (CMU training windows). The network's error floor of ~0.1 standardised units
was then ~5 cm of root at every forecast frame: the first forecast frame 54 mm from the anchor (real 14 mm),
frame-to-frame root steps 3.8x the real ones in standardised units, sample root speed 0.67 / 0.90 / 1.20 m/s
over 0-0.4 / 0.4-1 / 1-4 s against 0.33 / 0.32 / 0.29 real, while the net 1-4 s displacement was below the
real one (0.12 vs 0.18 m/s): jitter from the coding, not a rate or integration bug (both data and model at 25
Hz; offsets decode exactly). Per-lag statistics give every lag its own resolution; frames past the training
window take the last lag's, so one pass still covers any horizon. The shipped one-pass model continued 1600
steps with them (statistics refitted, step 1200 picked on validation NDMS) moved CMU validation (200 windows,
10 samples, ``--split val --ndms``) from 245 to 193 mm MPJPE at 400 ms (best-of-10 161 -> 147, zero velocity
164; root error 201 -> 138 mm, joint speed ratio 0-0.4 / 0.4-1 s 1.21 / 1.90 -> 0.78 / 1.37) with NDMS own
clip left out 2 / 4 s .200 / .214 -> .224 / .226; then on the cmu8 body19 variant at 400 ms 148.0 / 120.3 ->
109.9 / 105.4 (mean / best-of-10; zero 115.2).

Found with it on validation (``--split val --data cmu-all --windows 400 --ndms``, 10 samples): NDMS compares
joint velocities only (eq. 6.11/6.12), and the forecasts that score highest at 2-4 s do not keep a body: the
limb bones of constant velocity are 619 / 1390 mm off their length over 1-2 / 2-4 s, the intention model's 137
/ 299 mm (real motion: 0). Forcing the last observed bone lengths onto every forecast frame (``--keep-bones``)
lowers ndms_loo at 2 / 4 s on the CMU validation windows from .225 / .227 to .156 / .098 (constant velocity)
and from .238 / .239 to .199 / .192 (intention). The intention model is not below constant velocity there
(ndms_loo .224 / .222 against .221 / .220; CMU split .238 / .239 against .225 / .227); its joints move at .66
/ .50 / .58 of the real speed over 0-0.4 / 0.4-1 / 1-2 s. The GRU damps: .54 / .37 / .45 of the real speed,
the mean of the possible futures that a position loss teaches, and its bones drift past its 1-s training
horizon (56 / 110 mm over 1-2 / 2-4 s); trained on 4 s it damps more (validation NDMS 2-4 s .102 -> .074). The
speed term of its training (``w_speed``, ``train.speed_gap``) raises its joint speed at 1-2 s to .93 of the
real one (``w_speed=10``: ndms_loo .165 / .200 -> .217 / .204, MPJPE at 400 ms 164 -> 167 mm, zero velocity
216).

Needs the CMU BVH under $ROOMCAP_SHARED/data/motion. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab import metrics as M
from roomcap.forecast.lab import train as T
from roomcap.forecast.runtime.predict import LHIP, RHIP, forecast_world
from roomcap.keypoints.skeletons import get_skeleton
from roomcap.outputs.skeleton_fit_file import topological_order
from roomcap.synthetic.bvh import BODY19

MS = (40, 80, 160, 400, 1000)
LIMB_ENDS = (
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_knee", "right_knee", "left_ankle",
    "right_ankle",
)  # fmt: skip


def split_clips(split: str, data: str = "cmu") -> list:
    """The clips of one split of ``forecast eval --data cmu`` or ``--data cmu-all`` (split seed 0)."""
    if data == "cmu-all":
        from roomcap.forecast.lab.clips import load_one_person_all

        d = load_one_person_all(0)
        return list({"train": d.train, "val": d.val, "test": d.test}[split])
    tr, va, te = T.split_clips(T.load_sources(["cmu"]), 0)
    return {"train": tr, "val": va, "test": te}[split]


def windows(
    split: str, n_obs: int, n_pred: int, max_windows: int, seed: int, stride: int = 5, data: str = "cmu"
):
    """(obs (B,n_obs,J,3), gt (B,n_pred,J,3), clip names (B,)) as ``evaluate.evaluate_single`` draws them."""
    cs = split_clips(split, data)
    ws = fdata.make_windows(cs, n_obs, n_pred, stride, persons="each")
    sel = np.sort(np.random.default_rng(seed).choice(len(ws), min(max_windows, len(ws)), replace=False))
    x = ws.x[sel, :, 0]
    return x[:, :n_obs], x[:, n_obs:], [cs[c].name for c in ws.clip[sel]], ws.fps


def root(x: np.ndarray) -> np.ndarray:
    return 0.5 * (x[..., LHIP, :] + x[..., RHIP, :])


def diagnose(y: np.ndarray, obs: np.ndarray, gt: np.ndarray, fps: float) -> dict:
    """y (B,S,H,J,3) forecasts -> the measurements of the module docstring (mm, ratios)."""
    err = np.linalg.norm(y - gt[:, None], axis=-1).mean(-1)  # (B,S,H) per-joint mean
    best = M.closest_sequence_error(err)  # (B,H)
    out: dict = {}
    for ms in MS:
        i = int(round(ms / 1000 * fps)) - 1
        out[f"mpjpe_{ms}"] = 1000 * float(err[:, :, i].mean())
        out[f"best_of_k_{ms}"] = 1000 * float(best[:, i].mean())
    i4 = int(round(0.4 * fps)) - 1
    r_err = np.linalg.norm(root(y[:, :, i4]) - root(gt[:, None, i4]), axis=-1)  # (B,S)
    yc = y[:, :, i4] - root(y[:, :, i4])[..., None, :]
    gc = gt[:, None, i4] - root(gt[:, None, i4])[..., None, :]
    out["root_err_400"] = 1000 * float(r_err.mean())
    out["pose_rc_err_400"] = 1000 * float(np.linalg.norm(yc - gc, axis=-1).mean())
    last, prev = obs[:, -1], obs[:, -2]
    d_obs = np.linalg.norm(last - prev, axis=-1).mean(-1)  # (B,)
    d_real = np.linalg.norm(gt[:, 0] - last, axis=-1).mean(-1)
    d_fc = np.linalg.norm(y[:, :, 0] - last[:, None], axis=-1).mean(-1)  # (B,S)
    jump = np.linalg.norm((y[:, :, 0] - last[:, None]) - (last - prev)[:, None], axis=-1).mean(-1)
    jump_real = np.linalg.norm((gt[:, 0] - last) - (last - prev), axis=-1).mean(-1)
    out["first_step_mm"] = 1000 * float(d_fc.mean())
    out["first_step_real_mm"] = 1000 * float(d_real.mean())
    out["last_obs_step_mm"] = 1000 * float(d_obs.mean())
    out["vel_jump_mm"] = 1000 * float(jump.mean())
    out["vel_jump_real_mm"] = 1000 * float(jump_real.mean())

    def speed(a, lo, hi):  # mean joint speed (per frame) over forecast frames lo..hi
        full = np.concatenate([np.broadcast_to(last[:, None, None], (*a.shape[:2], 1, *a.shape[3:])), a], 2)
        return np.linalg.norm(np.diff(full[:, :, lo : hi + 1], axis=2), axis=-1).mean()

    n4, n10 = int(round(0.4 * fps)), int(round(1.0 * fps))
    out["speed_ratio_0_400"] = float(speed(y, 0, n4) / speed(gt[:, None], 0, n4))
    out["speed_ratio_400_1000"] = float(speed(y, n4, n10) / speed(gt[:, None], n4, n10))
    n20 = min(int(round(2.0 * fps)), y.shape[2])
    out["speed_ratio_1_2s"] = float(speed(y, n10, n20) / speed(gt[:, None], n10, n20))
    # limb bones (upper arm, forearm, thigh, shank) against their length in the last observed frame
    limbs = np.array([BODY19.index(n) for n in LIMB_ENDS])
    par = np.array(get_skeleton("body19").parents)[limbs]
    bone = np.linalg.norm(y[..., limbs, :] - y[..., par, :], axis=-1)  # (B,S,H,8)
    b0 = np.linalg.norm(last[:, limbs] - last[:, par], axis=-1)[:, None, None]
    for lo, hi in ((0.0, 1.0), (1.0, 2.0), (2.0, 4.0)):
        a, b = int(round(lo * fps)), min(int(round(hi * fps)), y.shape[2])
        out[f"bone_change_{lo:g}_{hi:g}s_mm"] = 1000 * float(np.abs(bone[:, :, a:b] - b0).mean())
    return out


def keep_bones(y: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Forecasts y (B,S,H,J,3) with every bone set to its length in the last observed frame ``last`` (B,J,3),
    directions kept (root to leaves): ``--keep-bones``."""
    par = np.array(get_skeleton("body19").parents)
    out = y.copy()
    for j in topological_order(par):  # parents before children
        p = par[j]
        if p < 0:
            continue
        length = np.linalg.norm(last[:, j] - last[:, p], axis=-1)[:, None, None, None]
        d = y[..., j, :] - y[..., p, :]
        unit = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
        out[..., j, :] = out[..., p, :] + unit * length
    return out


def _ndms_scorer(split: str, names: list[str], data: str = "cmu"):
    """(obs, y) -> NDMS at 2 / 4 s of the windows: own clip in D, left out, clips weighted equally."""
    from roomcap.forecast.lab import evaluate as E
    from roomcap.forecast.lab.clips import clip_activities

    cs = split_clips(split, data)
    acts = clip_activities(cs)
    wact = [acts.get(n, fdata.UNLABELLED) for n in names]
    groups = np.array([E.clip_group(n) for n in names])
    scorer, _ = E._ndms_scorers(cs, acts, set(wact))

    def score(obs, y) -> dict:
        w = np.stack([scorer.score_forecast(obs[b], y[b], None, wact[b]) for b in range(len(y))])
        lo = np.stack([scorer.score_forecast(obs[b], y[b], int(groups[b]), wact[b]) for b in range(len(y))])
        ok = np.isfinite(lo).all(1)
        out = {}
        for t in (2, 4):
            a = E.ndms_at(w, 25.0, t)
            out[f"ndms_{t}"] = float(a.mean())
            out[f"ndms_loo_{t}"] = float(E.ndms_at(lo[ok], 25.0, t).mean()) if ok.any() else float("nan")
            out[f"ndms_clipw_{t}"] = float(np.mean([a[groups == g].mean() for g in np.unique(groups)]))
        return out

    return score


def table(paths: list[str]) -> None:
    """Print the rows of ``forecast eval`` results (``results.json``) the
    controls-against-models figures are read from: MPJPE, best-of-k and NDMS."""
    print(
        "| run | model | MPJPE 80 / 400 / 1000 ms | best-of-k 80 / 400 / 1000 ms | ndms 2 / 4 s | "
        "ndms_loo 2 / 4 s | ndms ff 2 / 4 s |"
    )
    print("|---|---|---|---|---|---|---|")
    for path in paths:
        res = json.loads(Path(path).read_text())
        fps = res["fps"]
        for name, r in res["models"].items():
            cells = []
            for key in ("mpjpe", "mpjpe_best_of_k"):
                c = r.get(key)
                cells.append(
                    "-"
                    if c is None
                    else " / ".join(
                        f"{1000 * c[int(round(ms / 1000 * fps)) - 1]:.0f}" for ms in (80, 400, 1000)
                    )
                )
            for key in ("ndms_at", "ndms_loo_at", "ndms_word_first_frame_at"):
                at = r.get(key, {})
                cells.append(" / ".join(f"{at[t][0]:.3f}" if t in at else "-" for t in ("2", "4")))
            print(f"| {Path(path).parent.name} | {name} | " + " | ".join(cells) + " |")


def rescore_cmu8(folder: str) -> None:
    """Mean and best-of-k MPJPE of the cmu8 body19 variant from saved samples (the protocol's limb points)."""
    from roomcap.forecast.lab import benchmark_cmu8 as B

    print("| model | k | " + " | ".join(f"{ms} mean / best" for ms in B.HORIZONS_MS) + " |")
    print("|---" * (len(B.HORIZONS_MS) + 2) + "|")
    for f in sorted(Path(folder).glob("samples_*.npz")):
        z = np.load(f)
        names = [str(n) for n in z["joint_names"]]
        if len(names) != 19:
            continue
        limbs = [names.index(n) for n in B.BODY19_LIMBS]
        err = np.linalg.norm(z["pred"] - z["gt"][:, None], axis=-1)[..., limbs].mean(-1)  # (N,S,T)
        err = err * float(z["protocol_mm_per_m"])
        acts = np.array([str(a) for a in z["activity"]])
        mean = [
            np.mean([err[acts == a].mean(1)[:, k].mean() for a in np.unique(acts)]) for k in B.HORIZON_FRAMES
        ]
        closest = M.closest_sequence_error(err)  # (N,T)
        best = [np.mean([closest[acts == a][:, k].mean() for a in np.unique(acts)]) for k in B.HORIZON_FRAMES]
        cells = " | ".join(f"{m:.1f} / {b:.1f}" for m, b in zip(mean, best, strict=True))
        print(f"| {z['model']} | {err.shape[1]} | {cells} |")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--rescore-cmu8", metavar="SAMPLES_DIR", help="rescore the cmu8 body19 samples only")
    p.add_argument("checkpoints", nargs="*")
    p.add_argument("--table", nargs="+", metavar="RESULTS_JSON", help="print the table of eval results only")
    p.add_argument("--split", choices=("val", "test"), default="val")
    p.add_argument("--data", choices=("cmu", "cmu-all"), default="cmu", help="clips of forecast eval --data")
    p.add_argument("--windows", type=int, default=200)
    p.add_argument("--samples", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ndms", action="store_true", help="score NDMS at 2 / 4 s too (slower)")
    p.add_argument("--keep-bones", action="store_true", help="also score each forecast with its bones kept")
    args = p.parse_args()
    if args.table:
        table(args.table)
        return
    if args.rescore_cmu8:
        rescore_cmu8(args.rescore_cmu8)
        return
    torch.set_num_threads(1)
    obs, gt, names, fps = windows(args.split, 50, 100, args.windows, args.seed, data=args.data)
    print(f"{len(obs)} {args.split} windows of {len(set(names))} clips at {fps:g} Hz, {args.samples} samples")
    models = {n: T.baseline(n) for n in ("zero", "const")}
    rates = {"zero": fps, "const": fps}
    for spec in args.checkpoints:
        ck, _, sets = spec.partition(":")
        m, meta = T.load_checkpoint(ck)
        for kv in filter(None, sets.split(",")):
            k, v = kv.split("=")
            cur = getattr(m, k)
            setattr(m, k, v.lower() in ("1", "true") if isinstance(cur, bool) else type(cur)(v))
        name = Path(ck).stem + (f" ({sets})" if sets else "")
        models[name] = m
        rates[name] = float(meta.get("fps", float("nan")))
    nd = _ndms_scorer(args.split, names, args.data) if args.ndms else None
    res: dict = {}
    cols = (
        ["rate"]
        + [f"mpjpe_{ms}" for ms in MS]
        + [f"best_of_k_{ms}" for ms in (80, 400, 1000)]
        + ["root_err_400", "pose_rc_err_400", "first_step_mm", "first_step_real_mm", "last_obs_step_mm"]
        + ["vel_jump_mm", "vel_jump_real_mm", "speed_ratio_0_400", "speed_ratio_400_1000", "speed_ratio_1_2s"]
        + ["bone_change_0_1s_mm", "bone_change_1_2s_mm", "bone_change_2_4s_mm", "s"]
        + (
            ["ndms_2", "ndms_4", "ndms_loo_2", "ndms_loo_4", "ndms_clipw_2", "ndms_clipw_4"]
            if args.ndms
            else []
        )
    )
    print("| model | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for name, m in models.items():
        t0 = time.perf_counter()
        S = args.samples if getattr(m, "stochastic", False) else 1
        torch.manual_seed(args.seed)
        y = forecast_world(m, obs[:, :, None], None, 100, S)[:, :, :, 0]
        for tag, yy in [("", y)] + ([(" +bones", keep_bones(y, obs[:, -1]))] if args.keep_bones else []):
            r = diagnose(yy, obs, gt, fps)
            if nd is not None:
                r.update(nd(obs, yy))
            r["rate"] = rates[name]
            r["s"] = time.perf_counter() - t0
            res[name + tag] = r
            cells = " | ".join(f"{r[c]:.3g}" if c != "rate" else f"{r[c]:g}" for c in cols)
            print(f"| {name + tag} | {cells} |")
    print("BENCH " + json.dumps({"split": args.split, "n_windows": len(obs), "models": res}))


if __name__ == "__main__":
    main()
