"""Training (eq. 4.1) and the evaluation of sec. 4.5.1 on composite activities.

``prepare`` turns a :class:`~roomcap.forecast.lab.behaviour.data.Composite` into the model's arrays (plane
features of the observed steps, the targets' undistorted 2D, the viewer frames, and the 3D truth that only the
evaluation reads). ``train`` fits one variant; ``evaluate`` scores the baselines of Table 4.1 (zero velocity,
train average) and the trained variants of Table 4.2 by 2D MPJPE (px), 3D quality (the share of a method's
poses that a once-trained real-vs-predicted pose classifier judges real, sec. 4.7.7), action top-1/top-3 per
step and overall (Fig. 4.3), and the 3D MPJPE (mm, pelvis-centred) that the sequences' known 3D allows.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from roomcap.core.progress import Progress
from roomcap.forecast.lab.behaviour import data as bdata
from roomcap.forecast.lab.behaviour.data import ACTIONS, JOINTS, Composite
from roomcap.forecast.lab.behaviour.geometry import (
    View,
    anchor_from_2d,
    make_view,
    plane_features,
    project,
    rays,
    room_context,
    to_world,
)
from roomcap.forecast.lab.behaviour.model import BehaviourConfig, Generator, build, fit_pose_prior, rollout
from roomcap.forecast.lab.behaviour.refine import RefineConfig
from roomcap.forecast.lab.behaviour.refine import refine as refine_poses
from roomcap.forecast.lab.protocol import Table, results

log = logging.getLogger(__name__)

NECK_FALLBACK_M = 1.45  # neck height used to place a person whose ankles are never seen
PX = 100.0  # the 2D loss is on pixels / PX


@dataclass
class Prepared:
    """Arrays of S sequences (n_obs observed steps, m forecast steps) for the joints ``names``."""

    names: tuple[str, ...]
    view: View
    feats: np.ndarray  # (S,N,J,2) plane features, 0 where unseen
    seen: np.ndarray  # (S,N,J) bool
    obs_px: np.ndarray  # (S,N,J,2) undistorted px of the observed steps, NaN unseen
    acts: np.ndarray  # (S,N+m) action indices
    tgt_px: np.ndarray  # (S,m,J,2) undistorted px of the forecast steps, NaN unseen
    tgt_3d: np.ndarray  # (S,m,J,3) viewer frame, metres from the anchor (evaluation only)
    # (S,N+m) the script's hidden states (``data.script_chain``; evaluation only: the top-1 ceiling), None
    # where unknown (a user's sessions)
    states: np.ndarray | None = None

    def take(self, idx) -> Prepared:
        return Prepared(
            self.names,
            self.view.take(idx),
            *(getattr(self, f)[idx] for f in ("feats", "seen", "obs_px", "acts", "tgt_px", "tgt_3d")),
            None if self.states is None else self.states[idx],
        )

    def __len__(self) -> int:
        return len(self.acts)


def concat(parts: list[Prepared]) -> Prepared:
    """One set of the sequences of several (same joints)."""
    v = View(*(np.concatenate([getattr(p.view, f) for p in parts]) for f in ("K", "R", "t", "g", "V", "c")))
    return Prepared(
        parts[0].names,
        v,
        *(
            np.concatenate([getattr(p, f) for p in parts])
            for f in ("feats", "seen", "obs_px", "acts", "tgt_px", "tgt_3d")
        ),
        None if any(p.states is None for p in parts) else np.concatenate([p.states for p in parts]),
    )


def anchors(K, R, t, und_px: np.ndarray) -> np.ndarray:
    """Floor anchor (S,3) from the observed undistorted 2D (S,N,19,2): the ankles of the latest step that
    shows one, else the neck's ray at ``NECK_FALLBACK_M``, else 3 m in front of the camera."""
    S, N = und_px.shape[:2]
    la, ra, nk = JOINTS.index("left_ankle"), JOINTS.index("right_ankle"), JOINTS.index("neck")
    g = np.full((S, 3), np.nan)
    for k in range(N - 1, -1, -1):
        miss = ~np.isfinite(g[:, 0])
        if not miss.any():
            break
        g[miss] = anchor_from_2d(K[miss], R[miss], t[miss], und_px[miss, k], (la, ra))
    for k in range(N - 1, -1, -1):
        miss = ~np.isfinite(g[:, 0]) & np.isfinite(und_px[:, k, nk, 0])
        if miss.any():
            C, d = rays(K[miss], R[miss], t[miss], und_px[miss, k, nk][:, None])
            s = (NECK_FALLBACK_M - C[:, 2]) / d[:, 0, 2]
            P = C + np.abs(s)[:, None] * d[:, 0]
            g[miss] = np.c_[P[:, :2], np.zeros(len(P))]
    miss = ~np.isfinite(g[:, 0])
    if miss.any():
        C = -np.einsum("sji,sj->si", R[miss], t[miss])
        fwd = R[miss][:, 2]
        fwd[:, 2] = 0
        fwd /= np.maximum(np.linalg.norm(fwd, axis=1, keepdims=True), 1e-9)
        g[miss] = np.c_[(C + 3.0 * fwd)[:, :2], np.zeros(miss.sum())]
    return g


def prepare(comp: Composite, n_obs: int, m: int, names: tuple[str, ...] = JOINTS) -> Prepared:
    S, L = comp.actions.shape
    if L < n_obs + m:
        raise ValueError(f"prepare: sequences of {L} steps, need n_obs + m = {n_obs + m}")
    rig = comp.rig
    und = np.stack([rig[int(c)].undistort_px(comp.xy_px[s]) for s, c in enumerate(comp.cam)])
    K = np.stack([rig[int(c)].K for c in comp.cam])
    R = np.stack([rig[int(c)].R for c in comp.cam])
    t = np.stack([rig[int(c)].t for c in comp.cam])
    g = anchors(K, R, t, und[:, :n_obs])
    view = make_view(K, R, t, g)
    jidx = [JOINTS.index(n) for n in names]
    feats = plane_features(view, und[:, :n_obs])[:, :, jidx]
    seen = np.isfinite(feats).all(-1)
    X = comp.xyz_m[:, n_obs : n_obs + m][:, :, jidx].astype(np.float64) - g[:, None, None]
    tgt3 = np.einsum("sij,smnj->smni", view.V, X)
    return Prepared(
        tuple(names),
        view,
        np.nan_to_num(feats).astype(np.float32),
        seen,
        und[:, :n_obs][:, :, jidx].astype(np.float32),
        comp.actions[:, : n_obs + m],
        und[:, n_obs : n_obs + m][:, :, jidx].astype(np.float32),
        tgt3.astype(np.float32),
        None if comp.states is None else comp.states[:, : n_obs + m],
    )


def neck_centred(px: torch.Tensor, neck: int) -> torch.Tensor:
    """The seed's translation removal: 2D poses (...,J,2) relative to their neck."""
    return px - px[..., neck : neck + 1, :]


def pose2d_error(
    P: torch.Tensor, view: dict, tgt_px: torch.Tensor, neck: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 4.2-4.3 terms: predicted viewer-frame poses P (B,m,J,3) projected into the observing camera,
    against target px (B,m,J,2) (NaN unseen), both neck-centred -> (per-joint error px (B,m,J), valid
    mask)."""
    px = project(to_world(P, view["V"], view["g"]), view["K"], view["R"], view["t"])
    ok = torch.isfinite(tgt_px).all(-1) & torch.isfinite(tgt_px[..., neck : neck + 1, :]).all(-1)
    tgt = torch.nan_to_num(tgt_px)
    d = neck_centred(px, neck) - neck_centred(tgt, neck)
    return d.norm(dim=-1), ok


def critic_input(P: torch.Tensor, pelvis: int) -> torch.Tensor:
    """Poses (B,J,3) with the pelvis moved to x = y = 0 (the height above the floor kept)."""
    off = P[:, pelvis : pelvis + 1].clone()
    off[..., 2] = 0
    return P - off


def _random_yaw(X: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    a = torch.rand(X.shape[0], generator=g) * 2 * np.pi
    c, s = torch.cos(a), torch.sin(a)
    Rz = torch.zeros(X.shape[0], 3, 3)
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1
    return torch.einsum("bij,bnj->bni", Rz, X)


def _losses(gen, cfg, tb, neck):
    feed = {"feed_pose": cfg.use_pose, "feed_action": cfg.use_action}
    logits, P = rollout(
        gen, tb["feats"], tb["obs_acts"], tb["seen"], tb["view"]["c"], cfg.m, room=tb["room"], **feed
    )
    l_act = nn.functional.cross_entropy(logits.reshape(-1, logits.shape[-1]), tb["tgt_acts"].reshape(-1))
    err, ok = pose2d_error(P, tb["view"], tb["tgt_px"], neck)
    l_2d = ((err / PX) ** 2 * ok).sum() / ok.sum().clamp(min=1)  # eq. 4.3 on the seen joints
    return logits, P, l_act, l_2d


def to_torch(d: Prepared, idx, n_obs: int) -> dict:
    v = d.view.take(idx).torch()
    return {
        "feats": torch.from_numpy(d.feats[idx]),
        "seen": torch.from_numpy(d.seen[idx]),
        "obs_acts": torch.from_numpy(d.acts[idx, :n_obs]),
        "tgt_acts": torch.from_numpy(d.acts[idx, n_obs:]),
        "tgt_px": torch.from_numpy(d.tgt_px[idx]),
        "view": v,
        "room": room_context(v["V"], v["g"]),
    }


def hide_history(tb: dict, cfg: BehaviourConfig, g: torch.Generator) -> None:
    """A person labelled fewer than n_obs times shows only the last steps: hide the first 1..n_obs-1
    observed steps (unseen pose, unknown action) of a ``short_history`` fraction of the batch, in place."""
    B, N = tb["obs_acts"].shape
    if N < 2 or cfg.short_history <= 0:
        return
    hide = torch.rand(B, generator=g) < cfg.short_history
    n = torch.randint(1, N, (B,), generator=g)
    drop = hide[:, None] & (torch.arange(N)[None] < n[:, None])
    tb["seen"] = tb["seen"] & ~drop[..., None]
    tb["feats"] = tb["feats"] * (~drop)[..., None, None]
    tb["obs_acts"] = torch.where(drop, torch.full_like(tb["obs_acts"], len(ACTIONS)), tb["obs_acts"])


@dataclass
class _Fit:
    """One variant's training state: the two networks, their optimisers, the random stream, the real 3D
    poses of the critic and the eq. 4.1 weights of the variant (0 for the heads it lacks)."""

    cfg: BehaviourConfig
    gen: Generator
    critic: nn.Module
    og: torch.optim.Optimizer
    oc: torch.optim.Optimizer
    g: torch.Generator
    real: torch.Tensor  # (N,J,3) the 3D database, the variant's joints
    neck: int
    pelvis: int
    la: float
    l2: float
    lv: float


def _fit_state(cfg: BehaviourConfig, db: np.ndarray) -> _Fit:
    gen, critic = build(cfg)
    names = cfg.joint_names
    jidx = [JOINTS.index(n) for n in names]
    if gen.skeleton is not None:
        gen.skeleton.set_lengths(db[:, jidx])
    if gen.prior is not None and cfg.use_pose:  # action_only never decodes a pose
        vae = fit_pose_prior(_canonical(db[:, jidx], names), cfg)
        gen.prior.load_state_dict(vae.state_dict())
    return _Fit(
        cfg,
        gen,
        critic,
        torch.optim.Adam(gen.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay),
        torch.optim.Adam(critic.parameters(), lr=cfg.lr, betas=(0.5, 0.9)),
        torch.Generator().manual_seed(cfg.seed),
        torch.from_numpy(np.ascontiguousarray(db[:, jidx])),
        names.index("neck"),
        names.index("pelvis"),
        cfg.lambda_action if cfg.use_action else 0.0,
        cfg.lambda_pose2d if cfg.use_pose else 0.0,
        cfg.lambda_adv3d if cfg.use_adv3d else 0.0,
    )


def _critic_step(f: _Fit, fake: torch.Tensor) -> None:
    """One critic update: Wasserstein loss with gradient penalty, real database poses at a random heading
    against the generator's poses ``fake`` (B,J,3) (detached here)."""
    g = f.g
    r = _random_yaw(f.real[torch.randint(len(f.real), (len(fake),), generator=g)], g)
    fk = fake.detach()
    eps = torch.rand(len(fk), 1, 1, generator=g)
    mix = (eps * r + (1 - eps) * fk).requires_grad_(True)
    grad = torch.autograd.grad(f.critic(mix).sum(), mix, create_graph=True)[0]
    gp = ((grad.reshape(len(fk), -1).norm(dim=1) - 1) ** 2).mean()
    l_c = f.critic(fk).mean() - f.critic(r).mean() + f.cfg.gp * gp
    f.oc.zero_grad()
    l_c.backward()
    f.oc.step()


def _generator_step(f: _Fit, tr: Prepared) -> list[float]:
    """One eq. 4.1 step on a random batch (after the critic's step when the variant has the 3D term)
    -> [action CE, 2D term, adversarial term]."""
    cfg, g = f.cfg, f.g
    idx = torch.randint(len(tr), (cfg.batch,), generator=g).numpy()
    tb = to_torch(tr, idx, cfg.n_obs)
    hide_history(tb, cfg, g)
    f.gen.train()
    _, P, l_act, l_2d = _losses(f.gen, cfg, tb, f.neck)
    fake = critic_input(P.reshape(-1, len(cfg.joint_names), 3), f.pelvis)
    fake = fake[torch.randperm(len(fake), generator=g)[: cfg.batch]]  # one batch of the B*m poses
    l_adv = torch.zeros(())
    if f.lv > 0:
        for _ in range(cfg.n_critic):
            _critic_step(f, fake)
        l_adv = -f.critic(fake).mean()
    loss = f.la * l_act + f.l2 * l_2d + f.lv * l_adv
    f.og.zero_grad()
    loss.backward()
    f.og.step()
    return [l_act.item(), l_2d.item(), l_adv.item()]


def _validate(f: _Fit, vb: dict, step: int, wall_s: float) -> dict:
    """The validation objective of the variant (its weighted action and 2D terms) at ``step``."""
    f.gen.eval()
    with torch.no_grad():
        _, _, va_act, va_2d = _losses(f.gen, f.cfg, vb, f.neck)
    return {
        "step": step,
        "action_ce": float(va_act),
        "pose2d": float(va_2d),
        "objective": f.la * float(va_act) + f.l2 * float(va_2d),
        "wall_s": wall_s,
    }


def train(
    cfg: BehaviourConfig,
    tr: Prepared,
    va: Prepared,
    db: np.ndarray,
    progress: Progress | None = None,
) -> tuple[Generator, dict]:
    """Fit one variant (eq. 4.1) with Adam, the critic alternating with the generator; keeps the state
    with the lowest validation objective (the variant's weighted action and 2D terms)."""
    f = _fit_state(cfg, db)
    vb = to_torch(va, np.arange(len(va)), cfg.n_obs)
    hist: dict = {"val": [], "loss": []}
    best, best_state = np.inf, copy.deepcopy(f.gen.state_dict())
    t0 = time.perf_counter()
    for step in range(1, cfg.steps + 1):
        hist["loss"].append(_generator_step(f, tr))
        if step % cfg.eval_every == 0 or step == cfg.steps:
            v = _validate(f, vb, step, time.perf_counter() - t0)
            hist["val"].append(v)
            log.info(
                "%s step %d: train ce %.3f 2d %.3f adv %.3f | val ce %.3f 2d %.3f",
                cfg.variant,
                step,
                *hist["loss"][-1],
                v["action_ce"],
                v["pose2d"],
            )
            if v["objective"] < best:
                best, best_state = v["objective"], copy.deepcopy(f.gen.state_dict())
                hist["best_step"] = step
        if progress:
            progress(f"train {cfg.variant}", step, cfg.steps)
    f.gen.load_state_dict(best_state)
    f.gen.eval()
    hist["train_wall_s"] = time.perf_counter() - t0
    return f.gen, hist


# ----------------------------------------------------------------------------- evaluation (sec. 4.5.1)


def train_average(tr: Prepared) -> np.ndarray:
    """The average training target 3D pose (J,3) in the viewer frame, pelvis at x = y = 0."""
    X = tr.tgt_3d.reshape(-1, len(tr.names), 3).copy()
    p = tr.names.index("pelvis")
    X[..., :2] -= X[:, p : p + 1, :2]
    return X.mean(0)


def predict(
    gen: Generator, cfg: BehaviourConfig, d: Prepared, batch: int = 1024
) -> tuple[np.ndarray, np.ndarray]:
    """-> action probabilities (S,m,A), viewer-frame poses (S,m,J,3)."""
    pr, ps = [], []
    with torch.no_grad():
        for i in range(0, len(d), batch):
            tb = to_torch(d, np.arange(i, min(i + batch, len(d))), cfg.n_obs)
            lg, P = rollout(
                gen,
                tb["feats"],
                tb["obs_acts"],
                tb["seen"],
                tb["view"]["c"],
                cfg.m,
                feed_pose=cfg.use_pose,
                feed_action=cfg.use_action,
                room=tb["room"],
            )
            pr.append(torch.softmax(lg, -1).numpy())
            ps.append(P.numpy())
    return np.concatenate(pr), np.concatenate(ps)


def _canonical(P: np.ndarray, names) -> np.ndarray:
    """Poses (N,J,3) pelvis-centred and turned so the shoulders (or hips) lie along +x: what the quality
    classifier sees (position and heading are no evidence of realism)."""
    a, b = names.index("left_shoulder"), names.index("right_shoulder")
    X = P - P[:, names.index("pelvis"), None]
    v = X[:, b] - X[:, a]
    ang = np.arctan2(v[:, 1], v[:, 0])
    c, s = np.cos(-ang), np.sin(-ang)
    R = np.zeros((len(X), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1
    return np.einsum("nij,nkj->nki", R, X).astype(np.float32)


def quality_mlp(J: int) -> nn.Module:
    """Sec. 4.7.7's 3-layer MLP over a canonical pose's J*3 coordinates -> one logit (> 0: real)."""
    return nn.Sequential(
        nn.Linear(J * 3, 128), nn.LeakyReLU(0.2), nn.Linear(128, 128), nn.LeakyReLU(0.2), nn.Linear(128, 1)
    )


def share_real(clf: nn.Module, pred: np.ndarray, names, batch: int = 65536) -> float:
    """Sec. 4.5.1 as the seed defines it: 1 - a, a the accuracy of the once-trained classifier ``clf`` on the
    method's poses (N,J,3) alone, i.e. the share it judges real (1: indistinguishable from real poses)."""
    n = 0
    with torch.no_grad():
        for i in range(0, len(pred), batch):
            x = torch.from_numpy(_canonical(pred[i : i + batch], names)).reshape(-1, len(names) * 3)
            n += int((clf(x)[:, 0] > 0).sum())
    return n / max(len(pred), 1)


def quality_classifier(
    real: np.ndarray, fakes: np.ndarray, names, seed: int = 0, steps: int = 1500
) -> nn.Module:
    """Sec. 4.7.7: a 3-layer MLP that tells real poses (N,J,3) from predicted ones (canonical frame)."""
    torch.manual_seed(seed)
    clf = quality_mlp(len(names))
    Xr = torch.from_numpy(_canonical(real, names)).reshape(len(real), -1)
    Xf = torch.from_numpy(_canonical(fakes, names)).reshape(len(fakes), -1)
    opt = torch.optim.Adam(clf.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        r = Xr[torch.randint(len(Xr), (256,), generator=g)]
        f = Xf[torch.randint(len(Xf), (256,), generator=g)]
        x = torch.cat([r, f])
        y = torch.cat([torch.ones(256), torch.zeros(256)])
        loss = nn.functional.binary_cross_entropy_with_logits(clf(x)[:, 0], y)
        opt.zero_grad()
        loss.backward()
        opt.step()
    clf.eval()
    return clf


def quality(clf: nn.Module, real: np.ndarray, pred: np.ndarray, names, seed: int = 0) -> float:
    """1 - balanced accuracy of ``clf`` on as many predicted as real poses: the per-method variant
    (``quality3d_per_method``, at most 0.5), its classifier with the method's own val predictions as fakes."""
    rng = np.random.default_rng(seed)
    n = min(len(real), len(pred))
    r = real[rng.choice(len(real), n, replace=False)]
    p = pred[rng.choice(len(pred), n, replace=False)]
    with torch.no_grad():
        sr = clf(torch.from_numpy(_canonical(r, names)).reshape(n, -1))[:, 0].numpy()
        sp = clf(torch.from_numpy(_canonical(p, names)).reshape(n, -1))[:, 0].numpy()
    acc = ((sr > 0).sum() + (sp <= 0).sum()) / (2 * n)
    return float(1.0 - acc)


def perturbed(real: np.ndarray, names, seed: int = 0) -> np.ndarray:
    """Unrealistic poses for the quality classifier's fake class besides the models' predictions: real poses
    with joint noise (1-20 cm) and bone-length changes, the range of deformations sec. 4.7.7 describes."""
    rng = np.random.default_rng(seed)
    n = len(real)
    X = real + rng.normal(0, 1, real.shape) * rng.choice([0.01, 0.03, 0.08, 0.2], n)[:, None, None]
    s = rng.uniform(0.7, 1.3, (n, 1, 1))
    p = names.index("pelvis")
    return (X[:, p : p + 1] + (X - X[:, p : p + 1]) * s).astype(np.float32)


# Table 4.10's limbs: (name, joint, joint) of the left side; the right side swaps left_ for right_
SYMMETRY_BONES = (
    ("upper_arm", "left_shoulder", "left_elbow"),
    ("forearm", "left_elbow", "left_wrist"),
    ("thigh", "left_hip", "left_knee"),
    ("shin", "left_knee", "left_ankle"),
)


def symmetry(poses: np.ndarray | None, names) -> dict | None:
    """Table 4.10's classifier-free check (sec. 4.7.7): the left/right difference of the upper-arm, forearm,
    thigh and shin lengths of poses (...,J,3) in metres -> ``symmetry_mm``, the median over poses of each
    pose's mean absolute difference over the limbs its joints hold (mm), and ``symmetry_mm_by_bone``, the
    median per limb. The seed prints a mean over poses; the median is ours (a few broken poses do not rule
    it). None without poses or without a left/right limb pair among ``names``."""
    if poses is None:
        return None
    names = list(names)
    X = np.asarray(poses, np.float64).reshape(-1, len(names), 3)
    diffs, by_bone = [], {}
    for bone, a, b in SYMMETRY_BONES:
        ra, rb = a.replace("left_", "right_"), b.replace("left_", "right_")
        if not {a, b, ra, rb} <= set(names):
            continue
        ln = np.linalg.norm(X[:, names.index(a)] - X[:, names.index(b)], axis=-1)
        rn = np.linalg.norm(X[:, names.index(ra)] - X[:, names.index(rb)], axis=-1)
        d = np.abs(ln - rn) * 1000.0
        diffs.append(d)
        by_bone[bone] = float(np.median(d)) if len(d) else None
    if not diffs or len(X) == 0:
        return None
    return {"symmetry_mm": float(np.median(np.mean(diffs, 0))), "symmetry_mm_by_bone": by_bone}


def metrics(
    probs: np.ndarray | None,
    poses: np.ndarray | None,
    d: Prepared,
    n_obs: int,
    px2d: np.ndarray | None = None,
) -> dict:
    """mpjpe2d_px (neck-centred, mean over seen joints, steps and sequences), top1/top3 overall and per step,
    mpjpe3d_mm (pelvis-centred). None where the method has no such output."""
    out: dict = {}
    names = d.names
    neck, pelvis = names.index("neck"), names.index("pelvis")
    if poses is not None or px2d is not None:
        tgt = torch.from_numpy(d.tgt_px)
        if px2d is None:
            P = torch.from_numpy(np.asarray(poses, np.float32))
            err, ok = pose2d_error(P, d.view.torch(), tgt, neck)
        else:
            ok = torch.isfinite(tgt).all(-1) & torch.isfinite(tgt[..., neck : neck + 1, :]).all(-1)
            pz = torch.from_numpy(px2d.astype(np.float32))
            ok &= torch.isfinite(pz).all(-1) & torch.isfinite(pz[..., neck : neck + 1, :]).all(-1)
            err = (neck_centred(torch.nan_to_num(pz), neck) - neck_centred(torch.nan_to_num(tgt), neck)).norm(
                dim=-1
            )
        e, o = err.numpy(), ok.numpy()
        out["mpjpe2d_px"] = float((e * o).sum() / max(o.sum(), 1))
        out["mpjpe2d_px_by_step"] = [
            float((e[:, k] * o[:, k]).sum() / max(o[:, k].sum(), 1)) for k in range(e.shape[1])
        ]
    else:
        out["mpjpe2d_px"] = None
    if poses is not None:
        P = poses - poses[:, :, pelvis : pelvis + 1]
        T = d.tgt_3d - d.tgt_3d[:, :, pelvis : pelvis + 1]
        e3 = np.linalg.norm(P - T, axis=-1).mean(-1) * 1000
        out["mpjpe3d_mm"] = float(e3.mean())
        out["mpjpe3d_mm_by_step"] = e3.mean(0).tolist()
    else:
        out["mpjpe3d_mm"] = None
    if probs is not None:
        gt = d.acts[:, n_obs:]
        order = np.argsort(-probs, -1)
        top1 = order[..., 0] == gt
        top3 = (order[..., :3] == gt[..., None]).any(-1)
        out["top1"], out["top3"] = float(top1.mean()), float(top3.mean())
        out["top1_by_step"], out["top3_by_step"] = top1.mean(0).tolist(), top3.mean(0).tolist()
    else:
        out["top1"] = out["top3"] = None
    return out


def zero_velocity_2d(d: Prepared, m: int) -> np.ndarray:
    """The last observed 2D pose (the latest step whose neck is seen), repeated m times (S,m,J,2)."""
    neck = d.names.index("neck")
    S, N = d.obs_px.shape[:2]
    last = np.full(d.obs_px.shape[:1] + d.obs_px.shape[2:], np.nan, np.float32)
    for k in range(N):
        ok = np.isfinite(d.obs_px[:, k, neck, 0])
        last[ok] = d.obs_px[ok, k]
    return np.repeat(last[:, None], m, 1)


def one_hot_probs(idx: np.ndarray, m: int) -> np.ndarray:
    """A constant prediction idx (S,) as probabilities (S,m,A) (ties broken by a tiny ramp so top-3 is
    defined: the order of ``ACTIONS``)."""
    A = len(ACTIONS)
    p = np.tile(np.linspace(1e-3, 0, A), (len(idx), m, 1))
    p[np.arange(len(idx)), :, idx] = 1.0
    return p


# ----------------------------------------------------------------------------- the whole protocol


@dataclass
class Splits:
    train: Prepared
    val: Prepared
    test: Prepared
    db: np.ndarray  # (N,19,3) the uncorrelated 3D database


def load_splits(
    cfg: BehaviourConfig, seed: int = 0, names: tuple[str, ...] = JOINTS, with_train: bool = True
) -> Splits:
    """The composite train / val / test sequences of ``cfg.script`` (``n_train`` / ``n_eval`` / ``n_eval``,
    each its own seed) and the 3D database; without ``with_train``, the train split holds its first 100
    sequences only (the evaluation needs none)."""
    pool = bdata.split_pool(bdata.load_pool())
    L = cfg.n_obs + cfg.m
    sizes = (("train", cfg.n_train if with_train else 100), ("val", cfg.n_eval), ("test", cfg.n_eval))
    parts = [
        prepare(
            bdata.make_composite(pool[p], n, L, seed * 10 + i, script=cfg.script), cfg.n_obs, cfg.m, names
        )
        for i, (p, n) in enumerate(sizes)
    ]
    return Splits(*parts, db=bdata.load_db_poses())


def action_frequencies(tr: Prepared, n_obs: int) -> np.ndarray:
    f = np.bincount(tr.acts[:, n_obs:].ravel(), minlength=len(ACTIONS)).astype(np.float64)
    return f / f.sum()


def ceiling_top1(d: Prepared, script: str, n_obs: int, m: int) -> dict | None:
    """The best top-1 any forecaster can reach on ``d`` (Fig. 4.3's ceiling): the script's chain forecast
    from the hidden state of the last observed step (labels and place; for ``markov`` the label is the
    state), ``data.chain_forecast``. None where the states are unknown (a user's sessions)."""
    if d.states is None:
        return None
    ch = bdata.script_chain(script)
    r = metrics(
        bdata.chain_forecast(ch, d.acts[:, :n_obs], m, last_state=d.states[:, n_obs - 1]), None, d, n_obs
    )
    return {"ceiling_top1": r["top1"], "ceiling_top1_by_step": r["top1_by_step"], "ceiling_top3": r["top3"]}


def evaluate_all(
    gens: dict[str, Generator],
    cfgs: dict[str, BehaviourConfig],
    extra: dict,
    val: Prepared,
    test: Prepared,
    db: np.ndarray,
    seed: int = 0,
    quality_clf: tuple[nn.Module, tuple[str, ...]] | None = None,
    refine: RefineConfig | None = None,
) -> dict:
    """Table 4.1/4.2/4.10 on ``test``: zero velocity and train average (poses and, as in sec. 4.7.4, actions:
    repeat the last one / the most common), then every trained variant of ``gens`` (a variant the
    checkpoint lacks is absent from ``models``), then ``true_3d``: the test sequences' true 3D poses.

    Each model: ``mpjpe2d_px``, ``top1``/``top3`` (None where it has no such output), ``quality3d``,
    ``symmetry_mm`` (Table 4.10, ``symmetry``) and the diagnostics ``mpjpe3d_mm``, ``quality3d_per_method``.
    ``quality3d`` is the seed's metric (sec. 4.5.1, 4.7.7): the share of the method's test poses that the
    once-trained classifier ``quality_clf`` (module, its joints; see ``forecast.behaviour.quality``) judges
    real; None without a classifier for these joints. ``quality3d_per_method`` is the earlier variant: a
    classifier trained here, real = half of the 3D database ``db`` (N,19,3), fake = every method's
    predictions on ``val`` plus perturbed real poses, scored as 1 - balanced accuracy against the other
    half. ``ceiling_top1``: ``ceiling_top1`` of the split (None on a user's sessions).

    With ``refine`` every trained pose model (``REFINED_MODELS``) is also scored after ch. 3's pose
    refinement (``forecast.lab.behaviour.refine``, a variant beyond ch. 4): ``mpjpe2d_px_refined``,
    ``quality3d_refined``, ``symmetry_mm_refined``, ``mpjpe3d_mm_refined`` and ``refine_cost_px`` (refined
    minus raw 2D) beside the raw figures, which stay under their own keys; ``refine``: its settings."""
    if not gens:
        raise ValueError("evaluate_all: no trained model")
    c0 = next(iter(cfgs.values()))
    n_obs, m = c0.n_obs, c0.m
    freq = np.asarray(extra["action_freq"])
    avg = np.asarray(extra["avg_pose"], np.float32)
    names = val.names
    preds: dict[str, dict[str, tuple]] = {"val": {}, "test": {}}
    for split, d in (("val", val), ("test", test)):
        S = len(d)
        last = d.acts[:, n_obs - 1]
        zv = np.tile(freq * 0.1, (S, m, 1))
        zv[np.arange(S), :, last] = 1.0
        preds[split]["zero_velocity"] = (zv, None, zero_velocity_2d(d, m))
        preds[split]["train_average"] = (
            np.tile(freq, (S, m, 1)),
            np.broadcast_to(avg, (S, m) + avg.shape).copy(),
            None,
        )
        for n, g in gens.items():
            if cfgs[n].joint_names != names:
                continue
            pr, ps = predict(g, cfgs[n], d)
            preds[split][n] = (pr if cfgs[n].use_action else None, ps if cfgs[n].use_pose else None, None)
    # real poses: the 3D database (sec. 4.5.1), even frames train the classifier, odd frames test it, so
    # the real poses of both halves come from one distribution whatever the test sequences' subjects
    jidx = [JOINTS.index(n) for n in names]
    real_v, real_t = db[0::2][:, jidx], db[1::2][:, jidx]
    fakes = [perturbed(real_v, names, seed)] + [
        p[1].reshape(-1, len(names), 3) for p in preds["val"].values() if p[1] is not None
    ]
    clf = quality_classifier(real_v, np.concatenate(fakes), names, seed)
    out = {
        "n_sequences": len(test),
        "n_obs": n_obs,
        "m": m,
        "script": c0.script,
        "actions": list(ACTIONS),
        "joints": list(names),
        "models": {},
    }
    seed_clf = quality_clf[0] if quality_clf is not None and tuple(quality_clf[1]) == names else None
    for n, (pr, ps, px) in preds["test"].items():
        r = metrics(pr, ps, test, n_obs, px2d=px)
        P = ps.reshape(-1, len(names), 3) if ps is not None else None
        r["quality3d"] = share_real(seed_clf, P, names) if P is not None and seed_clf is not None else None
        r["quality3d_per_method"] = quality(clf, real_t, P, names, seed) if P is not None else None
        r.update(symmetry(P, names) or {"symmetry_mm": None})
        if refine is not None and n in REFINED_MODELS and ps is not None:
            r.update(_refined_scores(ps, test, n_obs, names, seed_clf, refine, db))
        out["models"][n] = r
    true3 = test.tgt_3d.reshape(-1, len(names), 3)
    out["models"]["true_3d"] = {
        "quality3d": share_real(seed_clf, true3, names) if seed_clf is not None else None,
        **(symmetry(true3, names) or {"symmetry_mm": None}),
    }
    out.update(ceiling_top1(test, c0.script, n_obs, m) or {"ceiling_top1": None})
    if refine is not None:
        out["refine"] = {**dataclasses.asdict(refine), "models": [n for n in REFINED_MODELS if n in gens]}
    return out


REFINED_MODELS = ("full", "pose_only", "action_2d")  # the trained models that output 3D poses


def _refined_scores(ps, d: Prepared, n_obs: int, names, clf, cfg: RefineConfig, db) -> dict:
    """The ``*_refined`` figures of poses ps (S,m,J,3) after ``refine.refine`` (``evaluate_all``)."""
    R = refine_poses(ps, names, cfg, db)
    r = metrics(None, R, d, n_obs)
    P = R.reshape(-1, len(names), 3)
    raw2d = metrics(None, ps, d, n_obs)["mpjpe2d_px"]
    sym = symmetry(P, names) or {"symmetry_mm": None, "symmetry_mm_by_bone": None}
    return {
        "mpjpe2d_px_refined": r["mpjpe2d_px"],
        "mpjpe3d_mm_refined": r["mpjpe3d_mm"],
        "quality3d_refined": share_real(clf, P, names) if clf is not None else None,
        "symmetry_mm_refined": sym["symmetry_mm"],
        "symmetry_mm_by_bone_refined": sym["symmetry_mm_by_bone"],
        "refine_cost_px": r["mpjpe2d_px"] - raw2d,
    }


def as_results(res: dict, title: str = "Behaviour forecasting (Diller ch. 4)") -> dict:
    """An evaluation (:func:`evaluate_all`) in the one results schema (:mod:`forecast.lab.protocol`): one row
    per model, the action top-1 by step (Fig. 4.3) and the best top-1 any forecaster reaches below."""

    def f(v, fmt):
        return "-" if v is None else format(v, fmt)

    columns = [
        "method",
        "2D MPJPE px",
        "3D quality",
        "per-method",
        "symm. mm",
        "top-1",
        "top-3",
        "3D MPJPE mm",
    ]
    rows = [
        [
            n,
            f(r.get("mpjpe2d_px"), ".1f"),
            f(r.get("quality3d"), ".2f"),
            f(r.get("quality3d_per_method"), ".2f"),
            f(r.get("symmetry_mm"), ".1f"),
            f(r.get("top1"), ".1%"),
            f(r.get("top3"), ".1%"),
            f(r.get("mpjpe3d_mm"), ".0f"),
        ]
        for n, r in res["models"].items()
    ]
    footer = [
        "action top-1 by step (Fig. 4.3): "
        + "; ".join(
            f"{n} " + " ".join(f"{v:.0%}" for v in r["top1_by_step"])
            for n, r in res["models"].items()
            if r.get("top1_by_step")
        )
    ]
    if res.get("ceiling_top1") is not None:
        footer.append(
            f"best top-1 any forecaster can reach on this split (labels and place): {res['ceiling_top1']:.1%}"
        )
    notes = [f"split: {res['split']}"] if res.get("split") else []
    tables = [Table("", columns, rows)]
    if res.get("refine"):
        rc = res["refine"]
        tables.append(
            Table(
                "after ch. 3's pose refinement (eq. 3.2; beyond ch. 4: bones "
                f"{rc['bones']}, angles {rc['angles']}, w_b {rc['w_b']}, w_a {rc['w_a']}, w_c {rc['w_c']})",
                ["method", "2D MPJPE px", "2D cost px", "3D quality", "symm. mm", "3D MPJPE mm"],
                [
                    [
                        n,
                        f(r.get("mpjpe2d_px_refined"), ".1f"),
                        f(r.get("refine_cost_px"), "+.1f"),
                        f(r.get("quality3d_refined"), ".2f"),
                        f(r.get("symmetry_mm_refined"), ".1f"),
                        f(r.get("mpjpe3d_mm_refined"), ".0f"),
                    ]
                    for n, r in res["models"].items()
                    if "mpjpe2d_px_refined" in r
                ],
            )
        )
    return results("behaviour", title, notes, tables, footer, **res)
