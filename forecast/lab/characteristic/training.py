"""Training of the heatmap model and the Deterministic ablation (sec. 3.4.1) on labelled clips.

Progress goes through the project's protocol (``core.progress``): ``progress("train heatmap", step,
steps)`` and ``progress("train deterministic", ...)``; the loss terms go to the log every ``LOG_EVERY``
steps.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.core.progress import Progress
from roomcap.forecast.lab.characteristic.labels import eval_starts, make_pairs, mirror_pairs, segments
from roomcap.forecast.lab.characteristic.model import CharConfig, build_models
from roomcap.forecast.lab.characteristic.protocol import CharData, best_of_k
from roomcap.keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)

LOG_EVERY = 100  # steps between the log lines with the loss terms


def _batch(items, segs, rng, cfg: CharConfig, names, flip) -> tuple[torch.Tensor, torch.Tensor]:
    r = segs[rng.integers(0, len(segs), cfg.batch)]
    s = rng.integers(
        r[:, 1], r[:, 2] - cfg.n_obs + 1
    )  # random start up to N frames before the label (sec. 3.6)
    obs, tgt = make_pairs(items, np.stack([r[:, 0], s, r[:, 2]], 1), cfg.n_obs, names)
    flipme = rng.random(len(obs)) < 0.5
    if flipme.any():
        obs[flipme], tgt[flipme] = mirror_pairs(obs[flipme], tgt[flipme], flip)
    return torch.from_numpy(obs), torch.from_numpy(tgt)


def _fit(model, steps, items, segs, rng, cfg, names, flip, val, progress, label, time_limit_s=0.0, **loss_kw):
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / max(1, cfg.warmup)))
    hist = {"loss": [], "val": []}
    best, best_state, t0, c0 = np.inf, None, time.perf_counter(), time.process_time()
    step = -1
    for step in range(steps):
        model.train()
        obs, tgt = _batch(items, segs, rng, cfg, names, flip)
        terms = model.loss(obs, tgt, **loss_kw)
        opt.zero_grad()
        terms["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        hist["loss"].append(float(terms["loss"].detach()))
        out_of_time = time_limit_s > 0 and time.process_time() - c0 > time_limit_s
        last = step == steps - 1 or out_of_time
        if val is not None and cfg.val_every and ((step + 1) % cfg.val_every == 0 or last):
            score = val(model)
            hist["val"].append({"step": step + 1, "mpjpe_best_of_k": score})
            if score < best:
                best, best_state = score, {k: v.detach().clone() for k, v in model.state_dict().items()}
        if progress:
            progress(f"train {label}", step + 1, steps)
        if (step + 1) % LOG_EVERY == 0 or last:
            shown = {k: float(v.detach()) for k, v in terms.items()}
            if hist["val"]:
                shown["val"] = hist["val"][-1]["mpjpe_best_of_k"]
            log.info(
                "%s step %d/%d: %s",
                label,
                step + 1,
                steps,
                ", ".join(f"{k} {v:.4f}" for k, v in shown.items()),
            )
        if out_of_time:
            log.warning("%s: time limit reached after %d steps", label, step + 1)
            break
    hist["steps_done"] = step + 1
    hist["wall_s"], hist["cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
    if best_state is not None:
        model.load_state_dict(best_state)
        hist["val_best"] = min(hist["val"], key=lambda r: r["mpjpe_best_of_k"])
    return hist


def train(data: CharData, cfg: CharConfig | None = None, progress: Progress | None = None):
    """-> (heatmap model, deterministic model, average train pose (J,3), history); ``cfg``: the defaults
    when None."""
    cfg = cfg or CharConfig()
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    sk = get_skeleton(data.skeleton)
    names, flip = sk.joint_names, sk.flip_index
    segs = segments(data.train, cfg.n_obs)
    if len(segs) == 0:
        raise InputError(
            f"no training labels: {len(data.train)} clips give no label at least {cfg.n_obs} frames "
            "after the clip start or the previous label"
        )
    _, avg_t = make_pairs(data.train, eval_starts(segs, cfg.n_obs), cfg.n_obs, names)
    avg_pose = avg_t.mean(0)
    net, det = build_models(cfg, data.skeleton)
    val_obs = val_tgt = None
    if data.val and cfg.val_every:
        vrows = eval_starts(segments(data.val, cfg.n_obs), cfg.n_obs)
        if len(vrows) > 60:  # a fixed subset keeps each validation under ~20 s of CPU
            vrows = vrows[np.linspace(0, len(vrows) - 1, 60).round().astype(int)]
        if len(vrows):
            val_obs, val_tgt = make_pairs(data.val, vrows, cfg.n_obs, names)

    def val_net(m):
        g = torch.Generator().manual_seed(cfg.seed)
        m.eval()
        s = np.concatenate(
            [
                m.sample(
                    torch.from_numpy(val_obs[i : i + 32]), cfg.k, cfg.temperature, refine=False, generator=g
                ).numpy()
                for i in range(0, len(val_obs), 32)
            ]
        )
        return float(best_of_k(s, val_tgt)[0].mean())

    def val_det(m):
        m.eval()
        with torch.no_grad():
            return float(np.linalg.norm(m(torch.from_numpy(val_obs)).numpy() - val_tgt, axis=-1).mean())

    have_val = val_obs is not None
    hist = {"n_train_labels": int(len(segs)), "n_train_clips": len(data.train), "skipped": data.skipped}
    gen = torch.Generator().manual_seed(cfg.seed)
    hist["heatmap"] = _fit(
        net,
        cfg.steps,
        data.train,
        segs,
        rng,
        cfg,
        names,
        flip,
        val_net if have_val else None,
        progress,
        "heatmap",
        cfg.time_limit_s,
        n_rest=cfg.n_rest_train,
        w_offset=cfg.w_offset,
        generator=gen,
    )
    hist["deterministic"] = _fit(
        det,
        cfg.det_steps,
        data.train,
        segs,
        rng,
        cfg,
        names,
        flip,
        val_det if have_val else None,
        progress,
        "deterministic",
    )
    net.eval()
    det.eval()
    return net, det, avg_pose, hist
