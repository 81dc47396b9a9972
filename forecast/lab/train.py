"""Training loops for every forecasting model (the GRU, the intention model and Social Diffusion).

The configs live in :mod:`roomcap.forecast.runtime.config`, checkpoints and baselines in
:mod:`roomcap.forecast.runtime.checkpoint`, the
clip loading and scene composition in :mod:`roomcap.forecast.lab.clips`, model selection in
:mod:`roomcap.forecast.lab.selection`; their public names stay importable from here
(``forecast.train.load_checkpoint``
and so on). A training loop reports through the project's progress protocol (``core.progress``):
``progress("train <kind>", step, steps)``; the loss terms go to the log every ``LOG_EVERY`` steps.
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np
import torch
import torch.nn.functional as F
from scipy.cluster.vq import kmeans2

from roomcap.core.errors import InputError
from roomcap.core.progress import Progress
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab.clips import (
    clip_key,
    composed_batch,
    diffusion_batch_features,
    load_cmu,
    load_sources,
    mirror,
    single_person_arrays,
    split_clips,
)
from roomcap.forecast.lab.intention_labels import fit_intention_labels
from roomcap.forecast.lab.selection import SELECT, VAL_FROM, VAL_N_OBS, VAL_N_PRED, Selector, Validator
from roomcap.forecast.runtime.checkpoint import (
    NORMALISATION,
    SCHEMA,
    baseline,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
    write_checkpoint,
)
from roomcap.forecast.runtime.config import BASELINES, DiffusionConfig, GRUConfig, IntentionConfig
from roomcap.forecast.runtime.models import FoolClusters
from roomcap.forecast.runtime.models.diffusion import N_CONST
from roomcap.forecast.runtime.models.intention import ADV_WINDOW, local_poses
from roomcap.forecast.runtime.normalise import LHIP, RHIP
from roomcap.forecast.runtime.predict import continue_velocity
from roomcap.forecast.runtime.registry import DISCRIMINATOR_PREFIXES, build_model, config_from_dict, spec
from roomcap.keypoints.skeletons import get_skeleton

__all__ = [
    "BASELINES",
    "DISCRIMINATOR_PREFIXES",
    "NORMALISATION",
    "SCHEMA",
    "SELECT",
    "VAL_FROM",
    "VAL_N_OBS",
    "VAL_N_PRED",
    "DiffusionConfig",
    "GRUConfig",
    "IntentionConfig",
    "Selector",
    "Validator",
    "baseline",
    "build_model",
    "clip_key",
    "composed_batch",
    "config_from_dict",
    "diffusion_batch_features",
    "fdata",
    "fool_model",
    "load_checkpoint",
    "load_cmu",
    "load_sources",
    "mirror",
    "read_checkpoint",
    "save_checkpoint",
    "single_person_arrays",
    "split_clips",
    "train",
    "write_checkpoint",
]

log = logging.getLogger(__name__)

LOG_EVERY = 100  # steps between the log lines with the loss terms


def _report(progress: Progress | None, task: str, step: int, steps: int, terms: dict) -> None:
    """Step ``step`` (0-based) of ``steps`` done: the progress callback, and the loss terms in the log."""
    if progress is not None:
        progress(task, step + 1, steps)
    if (step + 1) % LOG_EVERY == 0 or step + 1 == steps:
        log.info(
            "%s step %d/%d: %s", task, step + 1, steps, ", ".join(f"{k} {v:.4f}" for k, v in terms.items())
        )


def fool_model(train_windows: fdata.WindowSet, k: int = 48, seed: int = 0) -> FoolClusters:
    """Sec. 6.4.4's fool: 48 cluster means of the training poses (hip-centric, per-frame normalised)."""
    x = train_windows.x[:, :, 0].reshape(-1, train_windows.x.shape[3], 3)
    R, root = fdata.norm_frame(x, LHIP, RHIP)
    loc = np.einsum("nij,nkj->nki", R, x - root[:, None]).reshape(len(x), -1)
    rng = np.random.default_rng(seed)
    sub = loc[rng.choice(len(loc), min(len(loc), 20000), replace=False)].astype(np.float64)
    with warnings.catch_warnings():  # tiny data sets leave clusters empty; the centres are still poses
        warnings.simplefilter("ignore")
        centres, _ = kmeans2(sub, k, minit="++", seed=seed)
    centres = centres[np.isfinite(centres).all(1)]
    return FoolClusters(torch.from_numpy(centres.astype(np.float32)))


def _masked_joint_l2(pred, fut, mask):
    J = mask.shape[-1]
    err = (pred - fut).view(*pred.shape[:2], J, 3).norm(dim=-1)
    m = mask.float()
    return (err * m).sum() / m.sum().clamp(min=1)


def speed_gap(pred, fut, last, mask):
    """Mean gap between the forecast's and the truth's joint speeds (frame-to-frame displacement norms, the
    first from the last observed pose ``last`` (B,D)): a deterministic model trained on the position error
    alone forecasts the mean of the possible futures, which barely moves (joint speed 20 % of the real one
    at 1-2 s); the speed's magnitude does not average out, so this term keeps the forecast moving."""
    J = mask.shape[-1]
    sp = [
        torch.diff(torch.cat([last[:, None], x], 1), dim=1).view(*x.shape[:2], J, 3).norm(dim=-1)
        for x in (pred, fut)
    ]
    m = mask.float()
    return ((sp[0] - sp[1]).abs() * m).sum() / m.sum().clamp(min=1)


def intention_sym_loss(model, config, obs, lab, H: int) -> tuple[torch.Tensor, torch.Tensor]:
    """L_sym (Tanke eq. 6.4, teacher forced) of a batch forecasting ``H`` frames: ``lab`` (B,L) the window's
    intention labels. Returns L_sym and the labels from the last observed frame on (B, H + gamma): the
    forecast frames' and the gamma - 1 look-ahead frames' after them, the last label repeated where the
    window ends sooner."""
    need = H + config.gamma  # the last observed frame's label, the forecast's, the look-ahead's
    c_all = lab[:, config.n_obs - 1 : config.n_obs - 1 + need]
    c_all = torch.cat([c_all, c_all[:, -1:].expand(-1, need - c_all.shape[1])], 1)
    # teacher-forced CE on labels t+1..t+H+γ-1
    logits = model.label_logits_teacher(obs, c_all[:, : need - 1])
    return F.cross_entropy(logits.reshape(-1, model.C), c_all[:, 1:need].reshape(-1)), c_all


def intention_losses(model, config, obs, fut, mfut, lab):
    """The intention model's training losses (Tanke eqs. 6.4-6.8) of a batch: obs (B,T,D), fut (B,H,D), mfut
    (B,H,J) the forecast frames' joint masks, ``lab`` (B,L) the intention labels of the window's frames; the
    labels of the forecast frames and the gamma - 1 look-ahead frames after them are those from frame
    n_obs - 1 on, the last label repeated where the window ends sooner. Returns the generator loss, its terms,
    a closure for the discriminators' step and the poses forecast from the reference intentions (B,H,D).
    ``config.variety`` K > 1 (ours, Social GAN's variety loss, Gupta et al. 2018): each window decodes K
    noise draws z and L_rec scores the closest one, so the noise learns the futures a best-of-k score needs;
    the adversarial terms see the first draw. ``config.continuity``: score (and show the pose discriminator)
    the forecast shifted to continue the last observed velocity, as it is forecast
    (``predict.continue_velocity``). Shared by the body19 loop (:func:`train`) and the exponential-map one
    (:mod:`roomcap.forecast.lab.benchmark_cmu8_angle_intention`)."""
    H, g, B, K = fut.shape[1], config.gamma, obs.shape[0], config.variety
    l_sym, c_all = intention_sym_loss(model, config, obs, lab, H)
    c_free = model.label_rollout(obs, c_all[:, 0], H + g - 1)
    # poses conditioned on the reference intentions (teacher) with noise z, K draws per window
    c_ref = F.one_hot(c_all[:, 1 : H + g], model.C).float()
    obs_k = obs.repeat_interleave(K, 0)
    z = torch.randn(B * K, model.z_dim, device=obs.device)
    pred = model.decode(obs_k, c_ref.repeat_interleave(K, 0), H, z)
    if config.continuity:
        pred = pred - (pred[:, :1] - (2 * obs_k[:, -1:] - obs_k[:, -2:-1]))
    J = mfut.shape[-1]
    m = mfut.float()
    lam = torch.clamp(1.0 - torch.arange(H, device=obs.device, dtype=obs.dtype) / config.tau_rec, min=0.0)
    err = (pred.view(B, K, H, J, -1) - fut.view(B, 1, H, J, -1)).norm(dim=-1)  # 3 values a joint, or D/J
    w = m * lam[None, :, None]  # L_rec's weights (6.8), fading to 0 over tau_rec frames
    if K == 1:  # summed in this order, the seed's recipe trains bit for bit as before the variety loss
        l_rec = (err[:, 0] * m * lam[None, :, None]).sum() / w.sum().clamp(min=1)
    else:  # the closest draw per window
        l_rec = (err * w[:, None]).sum((2, 3)).min(1).values.sum() / w.sum().clamp(min=1)
    pred = pred.view(B, K, H, -1)[:, 0]
    # adversarial (6.5, 6.7), non-saturating generator losses on random 25-frame windows
    s = np.random.randint(0, max(H - ADV_WINDOW, 0) + 1)
    fake_p, real_p = pred[:, s : s + ADV_WINDOW], fut[:, s : s + ADV_WINDOW]
    fake_c, real_c = c_free[:, s : s + ADV_WINDOW], c_ref[:, s : s + ADV_WINDOW]
    ones = torch.ones(B, device=obs.device)
    bce = F.binary_cross_entropy_with_logits
    l_adv = bce(model.D_pose(fake_p), ones)
    l_sym_adv = bce(model.D_label(fake_c), ones)
    total = l_rec + l_sym + config.w_adv * (l_adv + l_sym_adv)
    terms = {"rec": l_rec.item(), "sym": l_sym.item(), "adv": l_adv.item(), "sym_adv": l_sym_adv.item()}

    def d_loss():
        zeros = torch.zeros_like(ones)
        return (
            bce(model.D_pose(real_p), ones)
            + bce(model.D_pose(fake_p.detach()), zeros)
            + bce(model.D_label(real_c), ones)
            + bce(model.D_label(fake_c.detach()), zeros)
        )

    return total, terms, d_loss, pred


def optimise(model, loss, opt, sched, opt_d=None, d_loss=None) -> None:
    """One generator step (gradient norm clipped to 1) and, for a model trained against discriminators, one
    discriminator step on ``d_loss()``."""
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
    opt.step()
    sched.step()
    if opt_d is not None:
        opt_d.zero_grad()
        d_loss().backward()
        opt_d.step()


def train(
    kind: str,
    clips: list[fdata.Clip],
    config=None,
    *,
    progress: Progress | None = None,
    device: str = "cpu",
    init: dict | None = None,
    val_clips: list[fdata.Clip] | None = None,
) -> tuple[torch.nn.Module, dict]:
    """Train ``kind`` on clips (body19). Returns the model and a history dict (loss per step, timing).
    ``init``: a state dict to continue from (same architecture; the intention model keeps its labels,
    discriminators start fresh when the state has none). ``val_clips``: the validation split; with
    ``config.val_every`` > 0 the returned model is the state with the best validation NDMS at 2-4 s
    (``Validator``), else the last state."""
    config = config or config_from_dict(kind)
    if getattr(config, "label_steps", 0):
        raise InputError(
            "label_steps (a first stage of the intention forecaster alone) is an option of the angle "
            "benchmark's intention model: `forecast cmu8 train --angles --model intention --label-steps N`"
        )
    torch.manual_seed(config.seed)
    np.random.seed(config.seed)  # the intention model's adversarial window offsets
    rng = np.random.default_rng(config.seed)
    sk = clips[0].skeleton if clips else "body19"
    J = get_skeleton(sk).n_joints
    ms = spec(kind)
    if ms.scene:
        return _train_diffusion(clips, config, J, rng, progress, device, init, val_clips)
    ws = fdata.make_windows(clips, config.n_obs, config.n_pred, stride=5, persons="each")
    if len(ws) == 0:
        raise InputError(
            f"no training windows of {config.n_obs + config.n_pred} frames (skipped: {ws.skipped})"
        )
    xn, mk = single_person_arrays(ws)
    xm, mm = mirror(xn, mk, get_skeleton(sk).flip_index)
    xn, mk = np.concatenate([xn, xm]), np.concatenate([mk, mm])
    model, labels_all = _single_person_model(kind, config, J, init, xn, device)
    X, M = torch.from_numpy(xn), torch.from_numpy(mk)
    opt = torch.optim.Adam(
        model.generator_parameters() if ms.intentions else model.parameters(), lr=config.lr
    )
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, config.steps)
    if ms.intentions:
        opt_d = torch.optim.Adam(model.discriminator_parameters(), lr=config.lr)
    hist: dict = {"loss": [], "n_windows": len(xn), "skipped": ws.skipped}
    sel = Selector(model, config, val_clips)
    t0 = time.perf_counter()
    t_val = 0.0
    model.train()
    n_obs, H = config.n_obs, config.n_pred
    for step in range(config.steps):
        idx = torch.from_numpy(rng.integers(0, len(X), config.batch))
        xb, mb = X[idx].to(device), M[idx].to(device)
        obs, fut, mfut = xb[:, :n_obs], xb[:, n_obs:], mb[:, n_obs:]
        if ms.intentions:
            lab = torch.from_numpy(labels_all)[idx].to(device)
            loss, terms, d_loss, pred = intention_losses(model, config, obs, fut, mfut, lab)
        else:
            pred = model(obs, H)
            if config.continuity:  # train on what is forecast (predict.continue_velocity)
                pred = continue_velocity(pred[:, None], obs[:, -1], obs[:, -2])[:, 0]
            loss, terms = _masked_joint_l2(pred, fut, mfut), {}
        if getattr(config, "w_speed", 0.0):  # intention: pred = poses of the reference intentions, one z
            gap = speed_gap(pred, fut, obs[:, -1], mfut)
            loss, terms["speed"] = loss + config.w_speed * gap, gap.item()
        terms["loss"] = loss.item()
        optimise(model, loss, opt, sched, opt_d if ms.intentions else None, d_loss if ms.intentions else None)
        hist["loss"].append(terms["loss"])
        tv = time.perf_counter()
        sel.step(step, step == config.steps - 1)
        t_val += time.perf_counter() - tv
        _report(progress, f"train {kind}", step, config.steps, terms)
    hist["seconds"] = time.perf_counter() - t0 - t_val
    hist["steps_per_s"] = config.steps / hist["seconds"]
    sel.finish(hist)
    model.eval()
    return model, hist


def _single_person_model(kind: str, config, J: int, init: dict | None, xn: np.ndarray, device: str):
    """The single-person model to train, and for a model that learns intentions each window's intention
    labels (N,T) (its clusters fitted on the windows ``xn`` unless ``init`` brings them); else labels None."""
    if not spec(kind).intentions:
        return build_model(kind, config, J, init).to(device), None
    loc = local_poses(torch.from_numpy(xn)).numpy()
    model = build_model(kind, config, J, init).to(device)
    if init is None:
        centres, merge = fit_intention_labels(
            loc[::3].reshape(-1, 3 * J),
            [s for s in loc[:, ::1]][:2000],
            config.n_clusters,
            config.n_intentions,
            config.seed,
        )
        model.centres.copy_(torch.from_numpy(centres))
        model.merge.copy_(torch.from_numpy(merge))
    return model, model.labels(torch.from_numpy(loc)).numpy()  # (N,T)


def _feature_stats(model, f: np.ndarray, stat) -> np.ndarray:
    """Mean or std of raw features f (B,P,N,F) in the model's coding (anchored models: offsets from the anchor
    frame): per channel pooled over frames, or (``lag_stats``) per frame and channel, constant channels
    pooled over frames."""
    rel = f
    if model.anchor is not None:
        rel = model.code(torch.from_numpy(f), torch.from_numpy(f[:, :, model.anchor])).numpy()
    if model.feat_mean.dim() == 1:
        return stat(rel.reshape(-1, rel.shape[-1]), 0).astype(np.float32)
    out = stat(rel.reshape(-1, *rel.shape[-2:]), 0)  # (N,F)
    out[:, -N_CONST:] = stat(rel[..., -N_CONST:].reshape(-1, N_CONST), 0)
    return out.astype(np.float32)


def _stats_shape(config: DiffusionConfig, nf: tuple[int, int]) -> tuple[int, ...]:
    """Shape of Social Diffusion's feature statistics for ``config`` and features of (frames, channels) nf."""
    return tuple(nf) if config.anchor and config.lag_stats else (nf[1],)


def _train_diffusion(clips, config: DiffusionConfig, J, rng, progress, device, init=None, val_clips=None):
    N, P = config.n_frames, config.persons
    single = fdata.make_windows(clips, config.n_obs, N - config.n_obs, stride=4, persons="each")
    multi_clips = [c for c in clips if c.xyz_m.shape[1] > 1]
    scenes = (
        fdata.make_windows(
            multi_clips, config.n_obs, N - config.n_obs, stride=4, persons="all", min_persons=1, max_persons=P
        )
        if multi_clips
        else None
    )
    xs = single.x[:, :, 0]
    if len(xs) == 0:
        raise InputError(f"no training windows of {N} frames")
    if config.mirror:  # x -> -x with the sides swapped is a real pose too; composed_batch re-frames it
        flip = get_skeleton(clips[0].skeleton).flip_index
        xm, _ = mirror(xs.reshape(*xs.shape[:2], -1), single.mask[:, :, 0], flip)
        xs = np.concatenate([xs, xm.reshape(xs.shape)])
    # feature statistics from a large composed sample
    sample = composed_batch(xs, P, 2048, rng)
    f = diffusion_batch_features(sample, np.ones((len(sample), P), bool), config.n_obs)
    # a continued model keeps its feature statistics, unless the config codes them differently (per lag
    # ``lag_stats`` against per channel): then the weights continue and the statistics are fitted anew
    restat = init is None or tuple(init["feat_mean"].shape) != _stats_shape(config, f.shape[-2:])
    model = build_model("social_diffusion", config, J, None if restat else init).to(device)
    if init is not None and restat:
        model.load_state_dict({k: v for k, v in init.items() if not k.startswith("feat_")}, strict=False)
    if restat:
        model.feat_mean.copy_(torch.from_numpy(_feature_stats(model, f, np.mean)))
        model.feat_std.copy_(torch.from_numpy(_feature_stats(model, f, np.std) + 1e-3))
    # EMA of the weights (Ho et al. 2020, Nichol & Dhariwal 2021 sample from one): validated, kept, returned
    ema = None
    if config.ema > 0:
        ema = build_model("social_diffusion", config, J, model.state_dict()).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, config.steps)
    hist: dict = {
        "loss": [],
        "n_windows": len(xs),
        "n_scene_windows": 0 if scenes is None else len(scenes),
        "skipped": single.skipped,
    }
    sel = Selector(model if ema is None else ema, config, val_clips)
    t0 = time.perf_counter()
    t_val = 0.0
    model.train()
    for step in range(config.steps):
        use_real = scenes is not None and len(scenes) and rng.random() < config.p_real
        if use_real:
            idx = rng.integers(0, len(scenes), config.batch)
            sc, pm = scenes.x[idx], scenes.person_mask[idx]
            valid = scenes.mask[idx].all(-1).transpose(0, 2, 1)  # (B,P,T)
        else:
            sc = composed_batch(xs, P, config.batch, rng)
            pm = np.ones((config.batch, P), bool)
            # scenes of one person too: the mean over people (eq. 7.10) then holds only the person itself, as
            # when a single track is forecast; trained on pairs only, that case was never seen
            if config.p_single > 0:
                pm[rng.random(config.batch) < config.p_single, 1:] = False
            valid = np.ones((config.batch, P, N), bool)
        feats = torch.from_numpy(diffusion_batch_features(sc, pm, config.n_obs)).to(device)
        loss = model.loss(
            model.standardise(feats), torch.from_numpy(pm).to(device), torch.from_numpy(valid).to(device)
        )
        optimise(model, loss, opt, sched)
        if ema is not None:
            with torch.no_grad():
                for pe, pm_ in zip(ema.parameters(), model.parameters(), strict=True):
                    pe.lerp_(pm_, 1 - config.ema)
        hist["loss"].append(loss.item())
        tv = time.perf_counter()
        sel.step(step, step == config.steps - 1)
        t_val += time.perf_counter() - tv
        _report(progress, "train social_diffusion", step, config.steps, {"loss": loss.item()})
    hist["seconds"] = time.perf_counter() - t0 - t_val
    hist["steps_per_s"] = config.steps / hist["seconds"]
    sel.finish(hist)
    model = model if ema is None else ema
    model.eval()
    return model, hist
