"""The seed's intention model (Tanke ch. 6, eqs. 6.1-6.8) on the CMU 8-action benchmark's exponential maps,
the representation of Table 6.7: ``forecast cmu8 train --angles --model intention``.

- The model's per-frame vector is the benchmark's used values (:func:`benchmark_cmu8_angle.used_dims`, the
  64 values LTD forecasts); the others are the truth's at scoring, as for every model of the protocol.
- Intention labels (sec. 6.2.3): k-means over the used values of every frame of the train files, then the
  cluster ids merged where the train files cycle through them
  (:func:`roomcap.forecast.lab.intention_labels.fit_intention_labels`). No hip normalisation (eq. 3.5): the
  exponential maps are already rotations of each joint relative to its parent, and the root's six values
  are not among the used ones.
- Training: the body19 loop's pieces (:func:`roomcap.forecast.lab.train.intention_losses`, ``optimise``):
  L_sym (6.4) + L_sym^adv (6.5) + L_rec (6.8, here the Euclidean norm over the frame's values, the shape of
  the protocol's error) + L_adv (6.7); the windows hold the gamma - 1 frames after the 25 forecast ones, so
  the look-ahead labels (6.6) are the data's, not padding. No mirroring (the DCT + MLP's ``--mirror``
  would need the intention clusters mirrored too); ``--reverse`` plays windows backwards (ours; the seed
  names no augmentation). ``--variety K`` (ours): L_rec of each window's closest of K noise draws.
- Scoring a stochastic model (Table 6.7 follows "the same protocol as described in [10]", Mix&Match,
  Aliakbarian et al. 2020): per window ``N_SAMPLES`` samples, the error of the sample closest to the truth
  (chosen as ADE chooses, over the frames up to the horizon: :func:`roomcap.forecast.lab.metrics.
  closest_sequence_error`), the primary figure; the mean error of single samples beside it.
- Selection: the state with the lowest validation angle error (the primary figure, mean of the five
  horizons) on the validation files (the last train file of each action).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.forecast.lab import benchmark_cmu8_angle as A
from roomcap.forecast.lab.benchmark_cmu8 import reverse_windows
from roomcap.forecast.lab.intention_labels import fit_intention_labels
from roomcap.forecast.lab.metrics import closest_sequence_error
from roomcap.forecast.lab.train import intention_losses, intention_sym_loss, optimise
from roomcap.forecast.runtime.checkpoint import read_checkpoint, write_checkpoint
from roomcap.forecast.runtime.config import IntentionConfig
from roomcap.forecast.runtime.models.intention import IntentionModel
from roomcap.forecast.runtime.registry import DISCRIMINATOR_PREFIXES, intention_model

log = logging.getLogger(__name__)

FAMILY = A.INTENTION_FAMILY
N_SAMPLES = 50  # samples per window scored (Mix&Match's and the seed's 50 samples per input sequence)
VAL_SAMPLES = 10  # samples per validation window during training (selection; the checkpoint's card says so)
VAL_STRIDE = 10  # validation windows: every 10th start of the validation files
LABEL_LR = 1e-3  # the first stage's learning rate (train_labels)
SCORING = (
    f"stochastic: {N_SAMPLES} samples per window; angle_error: the sample closest to the truth over the "
    "frames up to each horizon (best of k, as Mix&Match [the seed's ref. 10] scores its table); "
    "angle_error_mean_of_samples: the mean error of single samples"
)
# the benchmark's defaults: 50 frames observed, 25 forecast; no continuity shift (the residual decoder starts
# at the last observed frame); a smaller network than the seed's 512 units (sec. 6.2.4) for a CPU budget
DEFAULTS = {"n_pred": A.N_PRED, "continuity": False, "select": "angle_best_of_k", "steps": 3000}


def config(**kw) -> IntentionConfig:
    """The intention config of the angle benchmark: :data:`DEFAULTS` over IntentionConfig's, then ``kw``."""
    return IntentionConfig(**{**DEFAULTS, **{k: v for k, v in kw.items() if v is not None}})


class IntentionAngleForecaster:
    """The intention model as a forecaster of the protocol: ``samples(obs, k)`` ``(W, k, 25, 117)``;
    ``__call__(obs)`` one sample ``(W, 25, 117)``; the values not used are the last observed frame's (the
    scorer replaces them with the truth's). Sampling is seeded (``seed``): the same input, the same
    samples."""

    scoring = SCORING  # stochastic: how the protocol scores it (benchmark_cmu8_angle.evaluate)

    def __init__(self, model: IntentionModel, dims: np.ndarray, n_obs: int, seed: int = 0):
        self.model, self.dims, self.n_obs, self.seed = model.eval(), np.asarray(dims), n_obs, seed

    @torch.no_grad()
    def samples(self, obs: np.ndarray, k: int = N_SAMPLES, batch: int = 256) -> np.ndarray:
        if obs.ndim != 3 or obs.shape[1] < self.n_obs or obs.shape[2] != 117:
            raise InputError(f"the intention model needs (W, >= {self.n_obs}, 117) frames; got {obs.shape}")
        torch.manual_seed(self.seed)
        x = torch.from_numpy(np.ascontiguousarray(obs[:, -self.n_obs :, self.dims], np.float32))
        # the last observed label from the values themselves (no hip normalisation: obs_local = obs)
        y = torch.cat([self.model.sample(b, A.N_PRED, k, obs_local=b) for b in x.split(batch)]).numpy()
        out = np.repeat(A.zero_velocity(obs)[:, None], k, 1)
        out[..., self.dims] = y
        return out

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.samples(obs, 1)[:, 0]

    def errors(self, obs: np.ndarray, gt: np.ndarray, k: int = N_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
        """Per window and forecast frame ``(W, 25)``: the best of ``k`` samples' error and the mean of the
        single samples' errors."""
        s = self.samples(obs, k)
        W = len(s)
        per = A.score(s.reshape(W * k, *s.shape[2:]), np.repeat(gt, k, 0), self.dims).reshape(W, k, -1)
        return closest_sequence_error(per), per.mean(1)


def validation_errors(f: IntentionAngleForecaster, val: np.ndarray, k: int = VAL_SAMPLES) -> dict:
    """The protocol's errors on validation windows ``(W, >= 75, 117)``, means of the five horizons."""
    best, mean = f.errors(val[:, : A.N_OBS], val[:, A.N_OBS : A.N_OBS + A.N_PRED], k)
    return {
        "val_rad": float(np.mean(A.at_horizons(best))),
        "val_rad_mean": float(np.mean(A.at_horizons(mean))),
    }


def _batch(X: torch.Tensor, labels: torch.Tensor, cfg: IntentionConfig, rng, reverse: bool):
    """A training batch of windows and their labels, drawn with replacement (``reverse``: each played
    backwards with its labels with probability 1/2)."""
    idx = torch.from_numpy(rng.integers(0, len(X), cfg.batch))
    xb, lb = X[idx], labels[idx]
    if reverse:
        flip = torch.from_numpy(rng.random(cfg.batch) < 0.5)
        xb, lb = reverse_windows(xb, flip), reverse_windows(lb, flip)
    return xb, lb


def train_labels(
    model: IntentionModel,
    X: torch.Tensor,
    labels: torch.Tensor,
    cfg: IntentionConfig,
    rng,
    reverse: bool = False,
) -> float:
    """The first stage (``cfg.label_steps`` > 0): the intention forecaster (e_l, d_l and its output layer)
    trained alone on L_sym (eq. 6.4, teacher forced) at lr 1e-3 for ``cfg.label_steps`` batches of windows
    ``X (N, L, D)`` with their labels ``(N, L)``, so the pose forecaster then trains beside intentions that
    are already forecast. Returns the last batch's cross-entropy."""
    params = [p for m in (model.e_l, model.d_l, model.l_out) for p in m.parameters()]
    opt = torch.optim.Adam(params, lr=LABEL_LR)
    for _ in range(cfg.label_steps):
        xb, lb = _batch(X, labels, cfg, rng, reverse)
        ce, _ = intention_sym_loss(model, cfg, xb[:, : cfg.n_obs], lb, cfg.n_pred)
        opt.zero_grad()
        ce.backward()
        opt.step()
    log.info("intention forecaster alone, %d steps: L_sym %.4f", cfg.label_steps, ce.item())
    return ce.item()


def train(
    train_files: list[Path],
    val_files: list[Path],
    cfg: IntentionConfig,
    progress=None,
    on_best=None,
    reverse: bool = False,
) -> tuple[IntentionAngleForecaster, dict]:
    """Train the intention model on every window of ``train_files`` (``reverse``: each played backwards, with
    its labels, with probability 1/2, as the DCT + MLP's ``--reverse``); keep the state with the lowest
    validation angle error (best of :data:`VAL_SAMPLES` samples, every ``cfg.val_every`` steps and at the
    end).
    ``on_best(f, hist)``: called with the forecaster at each new best state (a run stopped early keeps it)."""
    if cfg.n_obs != A.N_OBS or cfg.n_pred < A.N_PRED:
        raise InputError(
            f"the protocol observes {A.N_OBS} frames and scores {A.N_PRED}: n_obs must be {A.N_OBS} and "
            f"n_pred at least {A.N_PRED} (got {cfg.n_obs}, {cfg.n_pred})"
        )
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)  # the adversarial window offsets (train.intention_losses)
    rng = np.random.default_rng(cfg.seed)
    dims = A.used_dims(train_files)
    L = cfg.n_obs + cfg.n_pred + cfg.gamma - 1  # the look-ahead labels of the last forecast frames (6.6)
    win = A.train_windows(train_files, length=L)[..., dims].astype(np.float32)
    val = A.train_windows(val_files, stride=VAL_STRIDE) if val_files else A.train_windows(train_files, 25)
    seqs = [A.sequence(f)[:, dims] for f in train_files]
    # sec. 6.2.3: k-means over all training frames, cycles of cluster ids merged (no hip normalisation: the
    # exponential maps are local already)
    centres, merge = fit_intention_labels(
        np.concatenate(seqs), seqs, cfg.n_clusters, cfg.n_intentions, cfg.seed
    )
    model = intention_model(cfg, len(dims))
    model.centres.copy_(torch.from_numpy(centres))
    model.merge.copy_(torch.from_numpy(merge))
    X = torch.from_numpy(win)
    labels = model.labels(X)  # (N, L)
    if cfg.label_steps:
        train_labels(model, X, labels, cfg, rng, reverse)
    opt = torch.optim.Adam(model.generator_parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps)
    opt_d = torch.optim.Adam(model.discriminator_parameters(), lr=cfg.lr)
    ones = torch.ones(cfg.batch, cfg.n_pred, 1, dtype=torch.bool)  # one error per frame: all values
    f = IntentionAngleForecaster(model, dims, cfg.n_obs, cfg.seed)
    hist: dict = {"loss": [], "val": [], "n_train_windows": len(win), "n_val_windows": len(val)}
    hist.update(
        n_dims=len(dims),
        label_counts=np.bincount(labels.flatten().numpy(), minlength=cfg.n_intentions).tolist(),
    )
    best, best_state, t_val, t0 = None, None, 0.0, time.perf_counter()
    for step in range(cfg.steps):
        model.train()
        xb, lb = _batch(X, labels, cfg, rng, reverse)
        obs, fut = xb[:, : cfg.n_obs], xb[:, cfg.n_obs : cfg.n_obs + cfg.n_pred]
        loss, terms, d_loss, _ = intention_losses(model, cfg, obs, fut, ones, lb)
        optimise(model, loss, opt, sched, opt_d, d_loss)
        hist["loss"].append(loss.item())
        if progress is not None:
            progress(step + 1, cfg.steps)
        if (cfg.val_every and (step + 1) % cfg.val_every == 0) or step + 1 == cfg.steps:
            tv = time.perf_counter()
            v = {"step": step + 1, **validation_errors(f, val)}
            t_val += time.perf_counter() - tv
            hist["val"].append(v)
            loss_text = ", ".join(f"{k} {x:.4f}" for k, x in terms.items())
            log.info(
                "step %d: %s; validation %.4f rad (mean of single samples %.4f)",
                *(step + 1, loss_text, v["val_rad"], v["val_rad_mean"]),
            )
            if best is None or v["val_rad"] < best["val_rad"]:
                best = v
                best_state = {k: t.detach().clone() for k, t in model.state_dict().items()}
                if on_best is not None:
                    model.eval()
                    on_best(f, {**hist, "best": best, "train_s": time.perf_counter() - t0 - t_val})
    model.load_state_dict(best_state)
    model.eval()
    hist.update(best=best, train_s=time.perf_counter() - t0 - t_val, val_s=t_val)
    hist["steps_per_s"] = cfg.steps / max(hist["train_s"], 1e-9)
    return f, hist


def save(path: str | Path, f: IntentionAngleForecaster, cfg: IntentionConfig, extra: dict) -> None:
    """The checkpoint in the one format (family :data:`FAMILY`), without the training-only discriminators,
    with its model card."""
    b = extra.get("best") or {}
    card = {
        "data": "the CMU 8-action benchmark's train files (exponential maps)",
        "split": f"validation: the last train file of each action ({len(extra.get('val_files', []))} files)",
        "selection": f"the lowest validation mean angle error, best of {VAL_SAMPLES} samples "
        f"(step {b.get('step')} of {len(extra.get('loss', []))})",
        "scores": {
            "split": "validation",
            "angle_error_rad": b.get("val_rad"),
            "angle_error_rad_mean_of_samples": b.get("val_rad_mean"),
        },
        "command": extra.get("command", ""),
    }
    state = {k: v for k, v in f.model.state_dict().items() if not k.startswith(DISCRIMINATOR_PREFIXES)}
    write_checkpoint(
        path,
        FAMILY,
        config=cfg,
        weights={"model": state},
        card=card,
        extra=extra,
        dims=[int(d) for d in f.dims],
        fps=A.FPS,
        units="exponential maps (radians), the benchmark's used values of its 117-vectors",
    )


def load(path: str | Path) -> tuple[IntentionAngleForecaster, dict]:
    """An intention checkpoint of the angle benchmark."""
    blob = read_checkpoint(path, FAMILY)
    fields = {f.name for f in dataclasses.fields(IntentionConfig)}
    cfg = IntentionConfig(**{k: v for k, v in blob["config"].items() if k in fields})
    model = intention_model(cfg, len(blob["dims"]))
    try:
        missing, unexpected = model.load_state_dict(blob["weights"]["model"], strict=False)
    except RuntimeError as e:  # a shape mismatch: torch lists every tensor, the last line says enough
        last = str(e).splitlines()[-1].strip()
        raise InputError(
            f"{path}: the weights do not fit its config ({last}); the config or the weights were changed "
            "after training: retrain with `forecast cmu8 train --angles --model intention`"
        ) from None
    missing = [k for k in missing if not k.startswith(DISCRIMINATOR_PREFIXES)]
    if missing or unexpected:
        raise InputError(
            f"{path}: the weights do not fit its config (missing {missing}, unexpected {unexpected})"
        )
    return IntentionAngleForecaster(model, np.asarray(blob["dims"]), cfg.n_obs, cfg.seed), blob
