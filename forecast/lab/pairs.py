"""Two people together over a long horizon, on real two-person takes (the CMU salsa pairs).

Per model, from windows of held-out takes (observe ``n_obs`` frames of both partners, forecast ``n_pred``):

- NDMS(t) per person (eq. 6.9-6.12, the seed's root-centred words): D = the held-out takes' motion of the
  partner's activity, the window's own take included (as ``evaluate.evaluate_single``'s ``ndms``), and with
  it left out (``ndms_loo``, the seed's form);
- MPJPE(t) in world coordinates over both partners, mean over samples and best-of-k (Tanke Table 6.8: per
  window the scene sample closest to the truth up to t, ``metrics.closest_sequence_error``);
- the partners' distance (mid-hip to mid-hip, floor plane) and facing angle (the angle between one partner's
  forward direction and the direction to the other, averaged over the two; 0° = both face each other) against
  the real takes' distribution: its 5-95 % range over every frame of the held-out takes, and the share of the
  forecast frames whose median over windows lies inside it (``*_in_range``), beside the share of all
  (window, frame) values inside it (``*_in_range_all``);
- the SSCP distance (sec. 7.3, eq. 7.14, ``metrics.default_social_state``) between the state transitions of
  the real windows (observed + real future) and the forecast ones (observed + forecast).

``real`` (the real future) is the reference row. Shapes: B windows, H forecast frames, P = 2, J joints.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab import metrics as M
from roomcap.forecast.lab.clips import clip_activities
from roomcap.forecast.lab.evaluate import Real, clip_group, ndms_scorer_for
from roomcap.forecast.lab.protocol import Table, results
from roomcap.forecast.runtime.predict import forecast_world
from roomcap.keypoints.skeletons import get_skeleton

PAIR_TIMES_S = (2.0, 4.0, 6.0, 8.0, 10.0)


def partner_distance(X: np.ndarray, lhip: int, rhip: int) -> np.ndarray:
    """Floor-plane distance of the two partners' roots: X (...,2,J,3) -> (...,) metres."""
    root = M.root_trajectory(X, lhip, rhip)[..., 0, :2]  # (...,2,2)
    return np.linalg.norm(root[..., 1, :] - root[..., 0, :], axis=-1)


def facing_angle(X: np.ndarray, lhip: int, rhip: int) -> np.ndarray:
    """Mean over the two partners of the angle (degrees) between one's forward direction
    (``metrics.facing_direction``) and the floor-plane direction to the other: X (...,2,J,3) -> (...,)."""
    root = M.root_trajectory(X, lhip, rhip)[..., 0, :2]
    fwd = M.facing_direction(X, lhip, rhip)  # (...,2,2)
    d = root[..., 1, :] - root[..., 0, :]
    d = d / (np.linalg.norm(d, axis=-1, keepdims=True) + 1e-9)
    c0 = np.clip((fwd[..., 0, :] * d).sum(-1), -1, 1)
    c1 = np.clip((fwd[..., 1, :] * -d).sum(-1), -1, 1)
    return 0.5 * (np.degrees(np.arccos(c0)) + np.degrees(np.arccos(c1)))


def _range_share(values: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    """values (B,H): share of frames whose median over windows lies in [lo, hi]; share of all values in it."""
    med = np.median(values, 0)
    return float(((med >= lo) & (med <= hi)).mean()), float(((values >= lo) & (values <= hi)).mean())


def evaluate_pairs(
    models: dict[str, object],
    takes: list[fdata.Clip],
    *,
    n_obs: int = 32,
    n_pred: int = 250,
    stride: int = 50,
    seed: int = 0,
    activities: dict[str, str] | None = None,
    n_samples: int = 1,
) -> dict:
    """Models on windows of the held-out two-person ``takes`` (P = 2 each, complete). ``n_samples`` per window
    of a stochastic model (NDMS and MPJPE over all of them; distance, facing and SSCP of the first, as
    ``evaluate.evaluate_social``). -> {"fps", "n_windows", "takes", "real_range": {...}, "models": {name:
    {"ndms": [H], "ndms_p0": [H], "ndms_p1": [H], "ndms_at": {t: v}, "distance": [H] (median over windows),
    "facing_deg": [H], "distance_in_range", "distance_in_range_all", "facing_in_range",
    "facing_in_range_all", "sscp_jsd", "wall_s"}}}."""
    t0 = time.perf_counter()
    takes = [c for c in takes if c.xyz_m.shape[1] == 2 and np.isfinite(c.xyz_m).all()]
    if not takes:
        raise InputError("no complete two-person takes to evaluate on")
    ws = fdata.make_windows(takes, n_obs, n_pred, stride, persons="all", min_persons=2, max_persons=2)
    if len(ws) == 0:
        raise InputError(f"no two-person windows of {n_obs + n_pred} frames in {len(takes)} takes")
    acts = clip_activities(takes) if activities is None else activities
    names = get_skeleton(takes[0].skeleton).joint_names
    lh, rh = fdata.hip_indices(names)
    scorer = ndms_scorer_for(takes, activities=acts)
    sscp = M.SSCP(lambda X: M.default_social_state(X, names), M.N_DEFAULT_STATES)
    x = ws.x  # (B,T,2,J,3)
    obs, gt = x[:, :n_obs], x[:, n_obs:]
    wact = [acts.get(takes[c].name, fdata.UNLABELLED) for c in ws.clip]
    rng_d, rng_f = _real_ranges(takes, lh, rh)
    real_scenes = list(x)
    groups = [clip_group(takes[c].name) for c in ws.clip]
    fps = ws.fps
    out: dict = {
        "fps": fps,
        "n_obs": n_obs,
        "n_pred": n_pred,
        "n_windows": len(x),
        "n_samples": n_samples,
        "takes": [c.name for c in takes],
        "real_range": {"distance_m_5_95": list(rng_d), "facing_deg_5_95": list(rng_f)},
        "models": {},
    }
    for name, model in models.items():
        tm = time.perf_counter()
        S = n_samples if getattr(model, "stochastic", False) else 1
        ys = gt[:, None] if isinstance(model, Real) else _forecast_pairs(model, obs, n_pred, seed, S)
        y = ys[:, 0]
        per = _ndms_per_person(scorer, obs, ys, wact)  # (2,B,H)
        nd = per.mean((0, 1))
        loo = _ndms_per_person(scorer, obs, ys, wact, groups)
        ok = np.isfinite(loo).all((0, 2))  # windows whose activity has another held-out take
        nd_loo = loo[:, ok].mean((0, 1)) if ok.any() else np.full(n_pred, np.nan)
        yp, gp = ys.transpose(0, 3, 1, 2, 4, 5), gt.transpose(0, 2, 1, 3, 4)  # (B,P,S,H,J,3), (B,P,H,J,3)
        mp = M.mpjpe(yp, np.broadcast_to(gp[:, :, None], yp.shape))
        per = np.linalg.norm(yp - gp[:, :, None], axis=-1).mean(
            (1, 4)
        )  # (B,S,H): a sample is the whole scene
        mp_best = np.nanmean(M.closest_sequence_error(per), 0)
        d, f = partner_distance(y, lh, rh), facing_angle(y, lh, rh)  # (B,H)
        d_in, d_all = _range_share(d, *rng_d)
        f_in, f_all = _range_share(f, *rng_f)
        gen = [np.concatenate([obs[b], y[b]], 0) for b in range(len(y))]
        out["models"][name] = {
            "mpjpe": mp.tolist(),
            "mpjpe_best_of_k": mp_best.tolist(),
            "ndms_loo": nd_loo.tolist(),
            "ndms_loo_at": _at_times(nd_loo, fps, n_pred),
            "n_windows_loo": int(ok.sum()),
            "ndms": nd.tolist(),
            "ndms_p0": per[0].mean(0).tolist(),
            "ndms_p1": per[1].mean(0).tolist(),
            "ndms_at": _at_times(nd, fps, n_pred),
            "distance": np.median(d, 0).tolist(),
            "facing_deg": np.median(f, 0).tolist(),
            "distance_in_range": d_in,
            "distance_in_range_all": d_all,
            "facing_in_range": f_in,
            "facing_in_range_all": f_all,
            "sscp_jsd": sscp.distance(real_scenes, gen),
            "wall_s": time.perf_counter() - tm,
        }
    out["wall_s"] = time.perf_counter() - t0
    return results("pairs", "Two people over a long horizon: the held-out salsa pairs", *_report(out), **out)


def _at_times(curve: np.ndarray, fps: float, n_pred: int) -> dict[str, float]:
    """{t: the curve's mean over the 0.2 s before t} at ``PAIR_TIMES_S`` within the horizon."""
    win = max(1, int(0.2 * fps))
    return {
        f"{t:g}": float(curve[max(0, int(round(t * fps)) - win) : int(round(t * fps))].mean())
        for t in PAIR_TIMES_S
        if t * fps <= n_pred
    }


def _real_ranges(
    takes: list[fdata.Clip], lh: int, rh: int
) -> tuple[tuple[float, float], tuple[float, float]]:
    """The 5th-95th percentile range of the partners' distance (m) and facing angle (deg) over every real
    frame of the takes."""
    every = np.concatenate([c.xyz_m for c in takes], 0)  # every real frame of the held-out takes
    dist_real, face_real = partner_distance(every, lh, rh), facing_angle(every, lh, rh)
    rng_d = (float(np.percentile(dist_real, 5)), float(np.percentile(dist_real, 95)))
    rng_f = (float(np.percentile(face_real, 5)), float(np.percentile(face_real, 95)))
    return rng_d, rng_f


def _forecast_pairs(model, obs: np.ndarray, n_pred: int, seed: int, n_samples: int = 1) -> np.ndarray:
    """``n_samples`` forecasts (B,S,H,2,J,3) of each two-person window, the same sampling noise every run."""
    torch.manual_seed(seed)
    return forecast_world(model, obs, None, n_pred, n_samples)  # (B,S,H,2,J,3)


def _ndms_per_person(scorer, obs: np.ndarray, y: np.ndarray, wact: list[str], groups=None) -> np.ndarray:
    """NDMS (2,B,H) of each person's forecasts y (B,S,H,2,J,3) in each window (mean over samples), against
    the windows' activities; ``groups`` (B,): leave each window's own take out of D (NaN where nothing of
    its activity is left)."""
    return np.stack(
        [
            np.stack(
                [
                    scorer.score_forecast(
                        obs[b, :, p], y[b, :, :, p], None if groups is None else groups[b], wact[b]
                    )
                    for b in range(len(y))
                ]
            )
            for p in range(2)
        ]
    )


def _report(res: dict) -> tuple[list[str], list[Table]]:
    """The report's note and its table: NDMS at 2-10 s per model, the range shares and SSCP."""
    rr = res["real_range"]
    ts = list(next(iter(res["models"].values()))["ndms_at"])
    notes = [
        f"{res['n_windows']} windows of held-out takes ({', '.join(res['takes'])}), observe {res['n_obs']} / "
        f"forecast {res['n_pred']} frames at {res['fps']:g} Hz, {res.get('n_samples', 1)} sample(s) per "
        f"stochastic model (distance, facing, SSCP: the first); real 5-95 %: distance "
        f"{rr['distance_m_5_95'][0]:.2f}-{rr['distance_m_5_95'][1]:.2f} m, facing "
        f"{rr['facing_deg_5_95'][0]:.0f}-{rr['facing_deg_5_95'][1]:.0f}°"
    ]
    columns = [
        "model",
        *(f"NDMS {t} s" for t in ts),
        "NDMS loo 2 / 4 s",
        "MPJPE 400 ms, mean / best-of-k (mm)",
    ]
    columns += [
        "NDMS p0 / p1 (mean)",
        "distance in range (median / all)",
        "facing in range (median / all)",
        "SSCP",
    ]
    i400 = int(round(0.4 * res["fps"])) - 1
    rows = [
        [
            name,
            *(f"{r['ndms_at'][t]:.3f}" for t in ts),
            " / ".join(f"{r['ndms_loo_at'].get(t, float('nan')):.3f}" for t in ("2", "4")),
            " / ".join(f"{1000 * r[k][i400]:.0f}" for k in ("mpjpe", "mpjpe_best_of_k")),
            f"{np.mean(r['ndms_p0']):.3f} / {np.mean(r['ndms_p1']):.3f}",
            f"{r['distance_in_range']:.2f} / {r['distance_in_range_all']:.2f}",
            f"{r['facing_in_range']:.2f} / {r['facing_in_range_all']:.2f}",
            f"{r['sscp_jsd']:.3f}",
        ]
        for name, r in res["models"].items()
    ]
    return notes, [Table("", columns, rows)]
