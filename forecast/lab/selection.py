"""Model selection on the validation split (never the test split): :class:`Validator` scores a model on
fixed validation windows, :class:`Selector` keeps the best state during training."""

from __future__ import annotations

import logging

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab.clips import clip_activities
from roomcap.forecast.runtime.predict import forecast_world

log = logging.getLogger(__name__)


# The evaluation protocol's model selection (validation split only, never the test split): every
# ``val_every`` steps the model forecasts validation windows (observe 2 s, forecast 4 s at 25 Hz, the rate
# make_windows resamples every clip to, as for training; fixed windows and seed) and is scored by NDMS
# (eq. 6.9-6.12, mean over samples; D = the validation clips of the window's activity, its own clip
# included, as the evaluation's `ndms`) over the 2-4 s horizon, where the evaluation compares models; the
# best state is kept. Every model is selected the same way.
VAL_N_OBS, VAL_N_PRED, VAL_FROM = 50, 100, 50


class Validator:
    """Scores a model on fixed validation windows: ``__call__(model) -> {"ndms_2_4", "ndms_2_3",
    "mpjpe_0_1"}`` (NDMS over 2-4 s; NDMS at 2 and 3 s with clips weighted equally; MPJPE in metres averaged
    over the first second and the samples)."""

    def __init__(
        self,
        clips: list[fdata.Clip],
        n_samples: int = 4,
        max_windows: int = 48,
        stride: int = 10,
        seed: int = 0,
    ):
        ws = fdata.make_windows(clips, VAL_N_OBS, VAL_N_PRED, stride, persons="each")
        if len(ws) == 0:
            raise InputError(
                f"no validation windows of {VAL_N_OBS + VAL_N_PRED} frames in {len(clips)} clips "
                f"(skipped {ws.skipped}); add longer validation clips or set val_every=0"
            )
        sel = np.sort(np.random.default_rng(seed).choice(len(ws), min(max_windows, len(ws)), replace=False))
        self.x = ws.x[sel, :, 0]
        acts = clip_activities(clips)
        self.activities = [acts[clips[c].name] for c in ws.clip[sel]]
        self.groups = [E.clip_group(clips[c].name) for c in ws.clip[sel]]
        queried = set(self.activities)  # D holds the activities queried, as in the evaluation
        self.scorer = E.ndms_scorer_for([c for c in clips if acts[c.name] in queried], activities=acts)
        self.n_samples, self.seed, self.fps = n_samples, seed, ws.fps

    def __call__(self, model: torch.nn.Module) -> dict:
        was_training = model.training
        obs, gt = self.x[:, :VAL_N_OBS], self.x[:, VAL_N_OBS:]
        S = self.n_samples if getattr(model, "stochastic", False) else 1
        with torch.random.fork_rng(devices=[]):  # fixed sampling noise, training RNG untouched
            torch.manual_seed(self.seed)
            y = forecast_world(model, obs[:, :, None], None, VAL_N_PRED, S)[:, :, :, 0]  # (B,S,H,J,3)
        model.train(was_training)
        # the seed's NDMS: D = validation clips of the window's activity, its own clip included
        nd_w = np.stack(
            [self.scorer.score_forecast(obs[b], y[b], None, self.activities[b]) for b in range(len(y))]
        )
        nd = nd_w.mean(0)
        err = np.linalg.norm(y[:, :, :25] - gt[:, None, :25], axis=-1).mean()
        # NDMS at 2 and 3 s (as the report), every validation clip weighted equally: on CMU one long clip
        # holds 79 of the 125 windows at stride 5 and decided the window mean
        at = 0.5 * (E.ndms_at(nd_w, self.fps, 2.0) + E.ndms_at(nd_w, self.fps, 3.0))  # (B,)
        g = np.asarray(self.groups)
        return {
            "ndms_2_4": float(nd[VAL_FROM - 1 :].mean()),
            "ndms_2_3": float(np.mean([at[g == c].mean() for c in np.unique(g)])),
            "mpjpe_0_1": float(err),
        }


SELECT = {  # criterion -> (score key, sign)
    "ndms": ("ndms_2_4", 1.0),
    "ndms_2_3": ("ndms_2_3", 1.0),
    "mpjpe": ("mpjpe_0_1", -1.0),
}


class Selector:
    """Keeps the state with the best validation score (``config.select``, ``val_every`` steps apart)."""

    def __init__(self, model, config, val_clips):
        self.every = int(getattr(config, "val_every", 0)) if val_clips else 0
        if config.select not in SELECT:
            raise InputError(f"select must be one of {sorted(SELECT)}, got {config.select!r}")
        self.key, self.sign = SELECT[config.select]
        self.validator = None
        if self.every:
            try:
                self.validator = Validator(
                    val_clips,
                    n_samples=getattr(config, "val_samples", 4),
                    max_windows=getattr(config, "val_windows", 48),
                    stride=getattr(config, "val_stride", 10),
                    seed=config.seed,
                )
            except ValueError as e:  # e.g. short track files: train without selection, say so
                log.warning("no model selection, the last state is kept: %s", e)
        self.model, self.best, self.best_state, self.history = model, -np.inf, None, []

    def step(self, step: int, last: bool) -> None:
        if self.validator is None or not ((step + 1) % self.every == 0 or last):
            return
        r = self.validator(self.model)
        self.history.append({"step": step + 1, **r})
        log.info("validation at step %d: %s", step + 1, r)
        if self.sign * r[self.key] > self.best:
            self.best = self.sign * r[self.key]
            self.best_state = {k: v.detach().clone() for k, v in self.model.state_dict().items()}

    def finish(self, hist: dict) -> None:
        hist["val"] = self.history
        if self.best_state is not None:
            self.model.load_state_dict(self.best_state)
            best = max(self.history, key=lambda r: self.sign * r[self.key])
            hist["val_best"] = {**best, "select": self.key}
            log.info("kept the state of step %d (validation %s)", best["step"], best)
