"""Characteristic 3D pose forecasting (Diller 2024, ch. 3) on CMU mocap: labels, data, training, evaluation.

``python -m forecast.characteristic train --out PATH`` / ``eval --checkpoint PATH``. The shipped
``forecast/checkpoints/characteristic_cmu.pt`` (1.8 MB, ~8.5 min of CPU on one thread) was trained with::

    OMP_NUM_THREADS=1 python -m forecast.characteristic train
        --out forecast/checkpoints/characteristic_cmu.pt
        --set steps=1100 det_steps=1000 val_every=100 n_rest_train=3 time_limit_s=560 --no-eval

(one command line).

* Labels (sec. 3.6). CMU has no characteristic-pose annotations, so ``annotate`` finds them automatically
  with the seed's definition: "the point in time when the action is most articulated, right before the actor
  starts returning back to another pose", i.e. the cusps of the end effectors' motion curves (Fig. 3.2). The
  rule: end effectors (wrists, ankles) in the per-frame hip-centred body frame (eq. 3.8 applied to every
  frame), smoothed; articulation ``A(t)`` = sum over effectors of the distance from the clip's median
  (resting) position; a characteristic frame is a peak of ``A`` that (1) rises at least ``prominence_m``
  above the valleys on both sides (the actor returns towards another pose afterwards), (2) is a cusp: the
  effectors' speed there is at most ``cusp_speed_ratio`` of the peak speed in the +-``window_s`` around it,
  and (3) lies at least ``min_sep_s`` from a stronger label (greedy, by prominence).
* Samples (sec. 3.6): N = 10 observed frames starting at a random frame between the previous label (or the
  clip start) and N frames before the label; the target is that next characteristic pose. Poses are
  hip-centred: the observation is normalised at its last frame (eq. 3.8, ``forecast.data``), the target is
  rotated by the same rotation and centred at its own hips (so the hip-centred heatmap grid of sec. 3.4 holds
  it).
* Evaluation (sec. 3.6): five starts per label spread evenly from the segment start to N frames before the
  label; k = 10 hypotheses; MPJPE of the best hypothesis (plain Euclidean per-joint error in metres, averaged
  over joints, as ``forecast.metrics.mpjpe``; eq. 3.3 prints a squared norm, but the seed's figures (0.054 m)
  are metres, which a squared norm would not give); Diversity = mean pairwise MPJPE between the k hypotheses.
  Baselines: average train target pose, zero velocity (last observed pose), and the "Deterministic" ablation
  of Tab. 3.3 (same backbone, an MLP head). The Inception Score is not computed: it needs an action
  classifier trained on action labels that the CMU clips here do not have.
* Split: the repository's train / val / test split by clip (``forecast.train.split_clips``); checkpoint
  selection on the validation split, figures on the test split.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from core.cli import guarded, positive_int
from core.errors import InputError
from forecast import data as fdata
from keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)

CKPT_SCHEMA = "forecast-characteristic/1"
END_EFFECTORS = ("left_wrist", "right_wrist", "left_ankle", "right_ankle")
SHIPPED = Path(__file__).resolve().parent / "checkpoints" / "characteristic_cmu.pt"


# ----------------------------------------------------------------------------- labels (sec. 3.6, Fig. 3.2)


@dataclass(frozen=True)
class AnnotatorConfig:
    smooth_s: float = 0.08  # Gaussian smoothing of effector tracks (sigma, seconds)
    prominence_m: float = 0.15  # articulation must rise this much above the valleys on both sides
    window_s: float = 1.0  # how far to look for those valleys and for the approach speed
    cusp_speed_ratio: float = 0.5  # speed at the label <= ratio * peak speed within +-window (a cusp)
    min_sep_s: float = 0.8  # labels at least this far apart


def _smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return x
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(x, sigma, axis=0, mode="nearest")


def articulation(xyz: np.ndarray, joint_names, fps: float, cfg: AnnotatorConfig = AnnotatorConfig()):
    """Articulation A(t) (m) and effector speed v(t) (m/s) of one person's clip xyz (T,J,3), world metres."""
    names = list(joint_names)
    lh, rh = fdata.hip_indices(names)
    eff = [names.index(n) for n in END_EFFECTORS]
    x = np.asarray(xyz, np.float64)
    if x.ndim != 3 or x.shape[1:] != (len(names), 3):
        raise ValueError(f"annotate: expected xyz (T,{len(names)},3), got {x.shape}")
    R, root = fdata.norm_frame(x, lh, rh)  # eq. 3.8 at every frame: the hip-centred body frame
    q = np.einsum("tij,tkj->tki", R, x[:, eff] - root[:, None])
    q = _smooth(q, cfg.smooth_s * fps)
    rest = np.median(q, axis=0)
    A = np.linalg.norm(q - rest, axis=-1).sum(-1)
    v = np.linalg.norm(np.gradient(q, axis=0), axis=-1).sum(-1) * fps
    return A, v


def annotate(
    xyz: np.ndarray, joint_names, fps: float, cfg: AnnotatorConfig = AnnotatorConfig()
) -> np.ndarray:
    """Characteristic frames (sorted int array) of one person's clip xyz (T,J,3) (rule in the module
    docstring)."""
    from scipy.signal import find_peaks

    x = np.asarray(xyz, np.float64)
    if not np.isfinite(x).all():
        raise ValueError("annotate: xyz has NaN/inf; fill or cut the gaps first")
    A, v = articulation(x, joint_names, fps, cfg)
    T = len(A)
    w = max(1, int(round(cfg.window_s * fps)))
    # prominence within +-window on both sides: find_peaks' prominence uses the higher of the two valleys
    peaks, props = find_peaks(A, prominence=cfg.prominence_m, wlen=2 * w + 1)
    keep = []
    for p, prom in zip(peaks, props["prominences"], strict=True):
        lo, hi = max(0, p - w), min(T, p + w + 1)
        if v[p] <= cfg.cusp_speed_ratio * v[lo:hi].max():
            keep.append((prom, int(p)))
    sep = cfg.min_sep_s * fps
    chosen: list[int] = []
    for _, p in sorted(keep, reverse=True):
        if all(abs(p - c) >= sep for c in chosen):
            chosen.append(p)
    return np.asarray(sorted(chosen), dtype=np.int64)


# ----------------------------------------------------------------------------- samples (sec. 3.6)


@dataclass(frozen=True)
class Labelled:
    """One person's clip ``x (T,J,3)`` world metres with its characteristic frames ``labels``."""

    name: str
    x: np.ndarray
    labels: np.ndarray


def label_clips(
    clips: list[fdata.Clip], cfg: AnnotatorConfig = AnnotatorConfig()
) -> tuple[list[Labelled], dict]:
    """Annotate every person of every clip; people with unknown joints (NaN) are skipped and counted."""
    out, skipped = [], {"person_with_missing_joints": 0}
    for c in clips:
        names = get_skeleton(c.skeleton).joint_names
        for p in range(c.xyz_m.shape[1]):
            x = c.xyz_m[:, p]
            if not np.isfinite(x).all():
                skipped["person_with_missing_joints"] += 1
                continue
            out.append(
                Labelled(
                    c.name if c.xyz_m.shape[1] == 1 else f"{c.name}/{p}", x, annotate(x, names, c.fps, cfg)
                )
            )
    return out, skipped


def segments(items: list[Labelled], n_obs: int) -> np.ndarray:
    """(S,3) rows (item, segment start, characteristic frame): the observation may start anywhere from the
    previous label (or the clip start) to ``n_obs`` frames before the label (sec. 3.6)."""
    rows = []
    for i, it in enumerate(items):
        prev = 0
        for c in it.labels.tolist():
            if c - n_obs >= prev:
                rows.append((i, prev, c))
            prev = c
    return np.asarray(rows, np.int64).reshape(-1, 3)


def eval_starts(segs: np.ndarray, n_obs: int, n_starts: int = 5) -> np.ndarray:
    """(W,4) rows (item, start, characteristic frame, start index 0..n_starts-1): ``n_starts`` observation
    starts evenly spread from the segment start to ``n_obs`` frames before the label (sec. 3.6, Fig. 3.9)."""
    rows = []
    for i, s0, c in segs.tolist():
        for k, s in enumerate(np.linspace(s0, c - n_obs, n_starts).round().astype(int).tolist()):
            rows.append((i, s, c, k))
    return np.asarray(rows, np.int64).reshape(-1, 4)


def make_pairs(
    items: list[Labelled], rows: np.ndarray, n_obs: int, joint_names
) -> tuple[np.ndarray, np.ndarray]:
    """rows (item, start, characteristic frame, ...) -> observations (B,N,J,3) normalised at their last frame
    (eq. 3.8) and targets (B,J,3): the characteristic pose rotated by the same rotation and centred at its
    own hips (hip-centred poses, sec. 3.6)."""
    lh, rh = fdata.hip_indices(joint_names)
    obs = np.stack([items[i].x[s : s + n_obs] for i, s in rows[:, :2].tolist()]).astype(np.float64)
    tgt = np.stack([items[i].x[c] for i, c in rows[:, [0, 2]].tolist()]).astype(np.float64)
    R, root = fdata.norm_frame(obs[:, -1], lh, rh)
    obs_n = fdata.normalize(obs, R, root)
    troot = 0.5 * (tgt[:, lh] + tgt[:, rh])
    tgt_n = fdata.normalize(tgt[:, None], R, troot)[:, 0]
    return obs_n.astype(np.float32), tgt_n.astype(np.float32)


def mirror_pairs(obs: np.ndarray, tgt: np.ndarray, flip) -> tuple[np.ndarray, np.ndarray]:
    """Left/right mirror of normalised pairs (``forecast.train.mirror``): doubles the data, keeps eq. 3.8."""
    from forecast.train import mirror

    B, N, J, _ = obs.shape
    seq = np.concatenate([obs, tgt[:, None]], 1).reshape(B, N + 1, 3 * J)
    m, _ = mirror(seq, np.ones((B, N + 1, J), bool), np.asarray(flip))
    m = m.reshape(B, N + 1, J, 3)
    return m[:, :N], m[:, N]


# ----------------------------------------------------------------------------- config, models, checkpoints


@dataclass(frozen=True)
class CharConfig:
    n_obs: int = 10  # N (sec. 3.6)
    hidden: int = 128  # GRU hidden size
    dim: int = 64  # attention / joint feature size
    heads: int = 4
    grid: int = 16  # voxels per axis (seed: 16)
    span: float = 2.0  # metres covered by the grid (seed: 2 m)
    n_discr: int = 10  # heatmap bins (seed: 10)
    channels: int = 16
    n_rest_train: int = 4  # 'rest' joints trained per step (random subset; all are used at sampling)
    w_offset: float = 1.0
    batch: int = 32
    steps: int = 1500
    det_steps: int = 1500  # the Deterministic ablation (trained in the same run)
    lr: float = 1e-3  # sec. 3.4.1: Adam, lr 1e-3, weight decay 1e-3, linear warm-up
    weight_decay: float = 1e-3
    warmup: int = 100
    temperature: float = 0.025  # sec. 3.4.1
    k: int = 10  # hypotheses (sec. 3.6)
    refine_iters: int = 60
    refine_angles_from: str = "last"  # eq. 3.2's theta: joint angles of the "first" or "last" observed pose
    val_every: int = 250  # model selection on the validation split (best-of-k MPJPE); 0 = keep the last
    time_limit_s: float = 0.0  # stop the heatmap model's training after this much process CPU time (0 = none)
    seed: int = 0


def config_from_dict(d: dict | None = None) -> CharConfig:
    """Typed config from a dict; unknown keys are an error (listing the valid ones)."""
    d = dict(d or {})
    fields = {f.name for f in dataclasses.fields(CharConfig)}
    bad = sorted(set(d) - fields)
    if bad:
        raise ValueError(f"unknown characteristic config keys {bad}; valid keys: {sorted(fields)}")
    base = CharConfig()
    return CharConfig(**{k: type(getattr(base, k))(v) for k, v in d.items()})


def _order(joint_names) -> tuple[int, int]:
    names = list(joint_names)
    try:
        return names.index("right_wrist"), names.index("left_wrist")
    except ValueError:
        raise ValueError(
            f"the characteristic model needs 'right_wrist' and 'left_wrist'; joints are {names}"
        ) from None


def build_models(cfg: CharConfig, skeleton: str = "body19"):
    from forecast.models.characteristic import CharacteristicPoseNet, DeterministicCharacteristic

    sk = get_skeleton(skeleton)
    bones = [(p, j) for j, p in enumerate(sk.parents) if p >= 0]
    net = CharacteristicPoseNet(
        sk.n_joints,
        _order(sk.joint_names),
        bones,
        cfg.n_obs,
        cfg.hidden,
        cfg.dim,
        cfg.heads,
        cfg.grid,
        cfg.span,
        cfg.n_discr,
        cfg.channels,
    )
    det = DeterministicCharacteristic(sk.n_joints, cfg.n_obs, cfg.hidden, cfg.dim, cfg.heads)
    return net, det


NORMALISATION = (
    "observation: eq. 3.8 at the last observed frame (root = mid-hips, hip vector left->right on +x, z up); "
    "target: the same rotation, centred at its own mid-hips"
)


def save_checkpoint(
    path,
    net,
    det,
    cfg: CharConfig,
    avg_pose: np.ndarray,
    skeleton: str = "body19",
    fps: float = fdata.TARGET_FPS,
    extra: dict | None = None,
) -> None:
    from forecast.train import write_checkpoint

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_checkpoint(
        path,
        CKPT_SCHEMA,
        "characteristic",
        cfg,
        skeleton,
        fps,
        NORMALISATION,
        extra,
        annotator=dataclasses.asdict(AnnotatorConfig()),
        state_dict={k: v.detach().cpu() for k, v in net.state_dict().items()},
        det_state_dict={k: v.detach().cpu() for k, v in det.state_dict().items()},
        avg_pose=torch.as_tensor(np.asarray(avg_pose, np.float32)),
    )


def load_checkpoint(path, skeleton: str | None = None):
    """-> (heatmap model, deterministic model, meta). ``skeleton``: the caller's data skeleton; a mismatch is
    a clear error (``FormatError``)."""
    from capture.fileio import FormatError
    from forecast.train import read_checkpoint

    path = Path(path)
    train_cmd = "forecast characteristic train --out PATH"
    blob = read_checkpoint(path, CKPT_SCHEMA, skeleton, "characteristic-pose checkpoint", train_cmd)
    if list(get_skeleton(blob["skeleton"]).joint_names) != list(blob["joint_names"]):
        raise FormatError(
            path,
            "joint_names",
            f"the joints differ from skeleton '{blob['skeleton']}' of this version.",
            "Retrain the model.",
        )
    cfg = config_from_dict(blob["config"])
    net, det = build_models(cfg, blob["skeleton"])
    try:
        net.load_state_dict(blob["state_dict"])
        det.load_state_dict(blob["det_state_dict"])
    except RuntimeError as e:
        raise FormatError(
            path, "state_dict", f"the weights do not fit the stored config: {e}", "Retrain."
        ) from None
    net.eval()
    det.eval()
    meta = {k: v for k, v in blob.items() if k not in ("state_dict", "det_state_dict")}
    meta["config"] = cfg
    meta["avg_pose"] = blob["avg_pose"].numpy()
    return net, det, meta


# ----------------------------------------------------------------------------- data split


@dataclass
class CharData:
    train: list[Labelled]
    val: list[Labelled]
    test: list[Labelled]
    skeleton: str
    skipped: dict


def load_cmu_labelled(fps: float = fdata.TARGET_FPS, seed: int = 0) -> CharData:
    """The CMU clips (``forecast.train.load_cmu``), split by clip (``forecast.train.split_clips``),
    annotated."""
    from forecast import train as T

    clips = T.load_cmu(fps)
    tr, va, te = T.split_clips(clips, seed)
    out, skipped = [], {}
    for part in (tr, va, te):
        items, sk = label_clips(part)
        out.append(items)
        for k, v in sk.items():
            skipped[k] = skipped.get(k, 0) + v
    return CharData(*out, skeleton=clips[0].skeleton, skipped=skipped)


# ----------------------------------------------------------------------------- evaluation (sec. 3.6)


def best_of_k(samples: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """samples (W,k,J,3), target (W,J,3) -> per window: MPJPE of the best hypothesis, and Diversity (mean
    pairwise MPJPE between hypotheses; 0 for k = 1). MPJPE = mean over joints of the Euclidean error
    (metres)."""
    from forecast.metrics import mpjpe  # L2 per joint, mean over joints (metres)

    W, k, J = samples.shape[:3]
    err = mpjpe(samples.reshape(W * k, J, 3), np.repeat(target, k, 0)).reshape(W, k)
    if k < 2:
        return err.min(1), np.zeros(W)
    a, b = np.triu_indices(k, 1)
    pair = mpjpe(samples[:, a].reshape(-1, J, 3), samples[:, b].reshape(-1, J, 3)).reshape(W, len(a))
    return err.min(1), pair.mean(1)


def _batched(fn, obs: np.ndarray, batch: int) -> np.ndarray:
    return np.concatenate([fn(torch.from_numpy(obs[i : i + batch])) for i in range(0, len(obs), batch)])


def evaluate(
    net,
    det,
    avg_pose: np.ndarray,
    items: list[Labelled],
    cfg: CharConfig,
    k: int | None = None,
    refine: bool = True,
    seed: int = 0,
    batch: int = 16,
    n_starts: int = 5,
    max_windows: int | None = None,
    progress=None,
    skeleton: str = "body19",
    per_window: bool = False,
) -> dict:
    """Sec. 3.6 protocol on ``items``: ``n_starts`` starts per label, k hypotheses, best-of-k MPJPE and
    Diversity for the heatmap model (refined and not refined), the Deterministic ablation, zero velocity and
    the average train pose. -> {"n_windows", "n_labels", "methods": {name: {"mpjpe", "diversity",
    "mpjpe_by_start"}}}."""
    k = k or cfg.k
    names = get_skeleton(skeleton).joint_names
    segs = segments(items, cfg.n_obs)
    rows = eval_starts(segs, cfg.n_obs, n_starts)
    if max_windows is not None and len(rows) > max_windows:
        rows = rows[np.linspace(0, len(rows) - 1, max_windows).round().astype(int)]
    if len(rows) == 0:
        raise ValueError(
            f"no evaluation windows: {len(items)} clips give no label at least {cfg.n_obs} frames "
            "after the clip start or the previous label"
        )
    obs, tgt = make_pairs(items, rows, cfg.n_obs, names)
    W, J = len(obs), obs.shape[2]
    g = torch.Generator().manual_seed(seed)
    ref_l, raw_l = [], []
    net.eval()
    for i in range(0, W, batch):
        ref, raw = net.sample(
            torch.from_numpy(obs[i : i + batch]),
            k,
            cfg.temperature,
            refine=refine,
            refine_iters=cfg.refine_iters,
            generator=g,
            return_raw=True,
            angles_from=cfg.refine_angles_from,
        )
        ref_l.append(ref.numpy())
        raw_l.append(raw.numpy())
        if progress:
            progress(min(batch, W - i))
    det.eval()
    with torch.no_grad():
        det_pred = _batched(lambda o: det(o).numpy(), obs, 256)
    preds = {
        "ours": np.concatenate(ref_l) if refine else np.concatenate(raw_l),
        "ours_not_refined": np.concatenate(raw_l),
        "deterministic": det_pred[:, None],
        "zero_velocity": obs[:, -1][:, None],
        "average_train_pose": np.broadcast_to(np.asarray(avg_pose, np.float32), (W, 1, J, 3)),
    }
    if not refine:
        del preds["ours_not_refined"]
    out = {"n_windows": int(W), "n_labels": int(len(segs)), "k": int(k), "methods": {}}
    for name, p in preds.items():
        best, div = best_of_k(p, tgt)
        out["methods"][name] = {
            "mpjpe": float(best.mean()),
            "diversity": float(div.mean()) if p.shape[1] > 1 else None,
            "mpjpe_by_start": [float(best[rows[:, 3] == s].mean()) for s in range(n_starts)],
        }
        if per_window:
            out["methods"][name]["per_window"] = best.tolist()
    if per_window:
        out["rows"] = rows.tolist()  # (item, start, characteristic frame, start index)
    return out


# ----------------------------------------------------------------------------- training (sec. 3.4.1)


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
            shown = {k: float(v.detach()) for k, v in terms.items()}
            if hist["val"]:
                shown["val"] = hist["val"][-1]["mpjpe_best_of_k"]
            progress(label, step, shown)
        if out_of_time:
            log.warning("%s: time limit reached after %d steps", label, step + 1)
            break
    hist["steps_done"] = step + 1
    hist["wall_s"], hist["cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
    if best_state is not None:
        model.load_state_dict(best_state)
        hist["val_best"] = min(hist["val"], key=lambda r: r["mpjpe_best_of_k"])
    return hist


def train(data: CharData, cfg: CharConfig = CharConfig(), progress=None):
    """-> (heatmap model, deterministic model, average train pose (J,3), history)."""
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    sk = get_skeleton(data.skeleton)
    names, flip = sk.joint_names, sk.flip_index
    segs = segments(data.train, cfg.n_obs)
    if len(segs) == 0:
        raise ValueError(
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


# ----------------------------------------------------------------------------- CLI


def _table(res: dict) -> str:
    lines = [
        f"{'method':<20} {'MPJPE best-of-k (m)':>20} {'Diversity (m)':>14}   "
        "MPJPE by start (0 = segment start ... 4 = N frames before)"
    ]
    for name, r in res["methods"].items():
        div = "-" if r["diversity"] is None else f"{r['diversity']:.3f}"
        by = " ".join(f"{v:.3f}" for v in r["mpjpe_by_start"])
        lines.append(f"{name:<20} {r['mpjpe']:>20.3f} {div:>14}   {by}")
    return "\n".join(lines)


def _main(argv: list[str] | None = None) -> int:
    from tqdm import tqdm

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    ap = argparse.ArgumentParser(prog="forecast characteristic", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="annotate CMU, train the heatmap model and the Deterministic ablation")
    t.add_argument("--out", required=True, help="checkpoint path (.pt)")
    t.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help=f"config overrides; keys: {', '.join(f.name for f in dataclasses.fields(CharConfig))}",
    )
    t.add_argument("--split-seed", type=int, default=0)
    t.add_argument("--no-eval", action="store_true", help="skip the test-split evaluation after training")
    e = sub.add_parser("eval", help="sec. 3.6 evaluation on the CMU test (or val) split")
    e.add_argument("--checkpoint", default=str(SHIPPED))
    e.add_argument("--split", choices=("test", "val", "train"), default="test")
    e.add_argument("--split-seed", type=int, default=0)
    e.add_argument(
        "--k", type=positive_int, default=None, help="hypotheses per window (default: the config's, 10)"
    )
    e.add_argument("--no-refine", action="store_true", help="skip the pose refinement of eq. 3.2")
    e.add_argument("--max-windows", type=positive_int, default=None)
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--json", default=None, help="also write the figures as JSON here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    if args.cmd == "train":
        from forecast.cli import parse_sets

        try:
            cfg = config_from_dict(parse_sets(args.set))
        except ValueError as err:
            raise InputError(str(err)) from None
        data = load_cmu_labelled(seed=args.split_seed)
        print(
            "labels: "
            + ", ".join(f"{p} {len(segments(getattr(data, p), cfg.n_obs))}" for p in ("train", "val", "test"))
            + f" (clips {len(data.train)}/{len(data.val)}/{len(data.test)})"
        )
        bars: dict = {}

        def progress(label, step, terms):
            if label not in bars:
                for b in bars.values():
                    b.close()
                bars[label] = tqdm(
                    total=cfg.steps if label == "heatmap" else cfg.det_steps,
                    desc=f"train {label}",
                    unit="step",
                )
            bars[label].update(1)
            if step % 20 == 0:
                bars[label].set_postfix({k: f"{v:.3f}" for k, v in terms.items()})

        t0, c0 = time.perf_counter(), time.process_time()
        net, det, avg, hist = train(data, cfg, progress)
        for b in bars.values():
            b.close()
        hist["train_wall_s"], hist["train_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
        extra = {
            "history": {k: v for k, v in hist.items()},
            "command": "python -m forecast.characteristic train "
            + " ".join(sys.argv[2:] if argv is None else argv[1:]),
        }
        for part in ("heatmap", "deterministic"):
            extra["history"][part] = {k: v for k, v in hist[part].items() if k != "loss"}
            extra["history"][part]["loss_last100"] = float(np.mean(hist[part]["loss"][-100:]))
        save_checkpoint(args.out, net, det, cfg, avg, data.skeleton, extra=extra)
        print(
            f"wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.2f} MB) after "
            f"{hist['train_wall_s']:.0f} s "
            f"wall, {hist['train_cpu_s']:.0f} s CPU; heatmap {hist['heatmap']['steps_done']} steps, "
            f"val best {hist['heatmap'].get('val_best')}"
        )
        if not args.no_eval:
            args = argparse.Namespace(
                checkpoint=args.out,
                split="test",
                split_seed=args.split_seed,
                k=None,
                no_refine=False,
                max_windows=None,
                seed=0,
                json=None,
            )
            return _eval(args, tqdm)
        return 0
    return _eval(args, tqdm)


def _eval(args, tqdm) -> int:
    from capture.fileio import FormatError

    try:
        net, det, meta = load_checkpoint(args.checkpoint, skeleton="body19")
    except (FormatError, FileNotFoundError) as err:
        raise InputError(str(err)) from None
    cfg = meta["config"]
    data = load_cmu_labelled(meta["fps"], seed=args.split_seed)
    items = getattr(data, args.split)
    n = len(eval_starts(segments(items, cfg.n_obs), cfg.n_obs))
    if args.max_windows:
        n = min(n, args.max_windows)
    bar = tqdm(total=n, desc=f"eval {args.split}", unit="window")
    c0 = time.process_time()
    res = evaluate(
        net,
        det,
        meta["avg_pose"],
        items,
        cfg,
        args.k,
        not args.no_refine,
        args.seed,
        max_windows=args.max_windows,
        progress=bar.update,
        skeleton=meta["skeleton"],
    )
    bar.close()
    res["split"], res["checkpoint"], res["eval_cpu_s"] = (
        args.split,
        str(args.checkpoint),
        time.process_time() - c0,
    )
    print(
        f"CMU {args.split} split: {res['n_labels']} characteristic poses x 5 starts = "
        f"{res['n_windows']} windows, "
        f"k = {res['k']}"
    )
    print(_table(res))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))
    return 0


main = guarded("forecast characteristic", _main)


if __name__ == "__main__":
    raise SystemExit(main())
