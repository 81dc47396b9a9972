"""The data split and the evaluation protocol of sec. 3.6 (five starts per label, best-of-k MPJPE and
Diversity, with the Deterministic ablation, zero velocity and the average train pose beside the model)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.core.progress import Progress
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab.characteristic.labels import (
    Labelled,
    eval_starts,
    label_clips,
    make_pairs,
    segments,
)
from roomcap.forecast.lab.characteristic.model import CharConfig
from roomcap.forecast.lab.clips import load_cmu, load_one_person_all, split_clips
from roomcap.forecast.lab.metrics import mpjpe  # L2 per joint, mean over joints (metres)
from roomcap.keypoints.skeletons import get_skeleton


@dataclass
class CharData:
    train: list[Labelled]
    val: list[Labelled]
    test: list[Labelled]
    skeleton: str
    skipped: dict


DATA_SOURCES = ("cmu", "cmu-all")  # the clip sources of ``load_labelled``, as ``forecast train --data``


def load_labelled(data: str = "cmu", fps: float = fdata.TARGET_FPS, seed: int = 0) -> CharData:
    """The clips of ``data``, split by clip, annotated. ``cmu``: the CMU BVH (``forecast.clips.load_cmu``)
    split by ``forecast.clips.split_clips``; ``cmu-all``: every one-person CMU clip with the split of
    ``forecast train --data cmu-all`` (``forecast.clips.load_one_person_all``: the ``cmu`` split unchanged,
    ``cmu-more`` split on its own, the 8-action benchmark's train files in train and its test files in test
    only, never trained on)."""
    if data == "cmu":
        clips = load_cmu(fps)
        parts = split_clips(clips, seed)
    elif data == "cmu-all":
        d = load_one_person_all(seed, fps)
        clips, parts = d.clips, (d.train, d.val, d.test)
    else:
        raise InputError(f"unknown data source {data!r}; use one of {', '.join(DATA_SOURCES)}")
    out, skipped = [], {}
    for part in parts:
        items, sk = label_clips(part)
        out.append(items)
        for k, v in sk.items():
            skipped[k] = skipped.get(k, 0) + v
    return CharData(*out, skeleton=clips[0].skeleton, skipped=skipped)


def load_cmu_labelled(fps: float = fdata.TARGET_FPS, seed: int = 0) -> CharData:
    """The CMU clips (``forecast.clips.load_cmu``), split by clip (``forecast.clips.split_clips``),
    annotated (``load_labelled("cmu", ...)``)."""
    return load_labelled("cmu", fps, seed)


# ----------------------------------------------------------------------------- evaluation (sec. 3.6)


def best_of_k(samples: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """samples (W,k,J,3), target (W,J,3) -> per window: MPJPE of the best hypothesis, and Diversity (mean
    pairwise MPJPE between hypotheses; 0 for k = 1). MPJPE = mean over joints of the Euclidean error
    (metres)."""
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
    *,
    seed: int = 0,
    batch: int = 16,
    n_starts: int = 5,
    max_windows: int | None = None,
    progress: Progress | None = None,
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
        raise InputError(
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
            progress("eval windows", min(i + batch, W), W)
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
