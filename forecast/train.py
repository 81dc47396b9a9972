"""Training configurations, loops and checkpoints for every forecasting model.

Configs are frozen dataclasses holding the only copy of each default (``config_from_dict`` rejects
unknown keys, listing the valid ones). The small defaults train on 2 CPU cores in minutes.

Checkpoints (``torch.save`` of plain containers, loaded with ``weights_only=True``) carry
``schema = "forecast-checkpoint/1"``, the model kind, its config, the skeleton id and joint names, the
frame rate and the normalisation convention, plus the state dict (k-means centres, feature statistics
and the diffusion schedule are buffers inside it).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from capture.fileio import FormatError, atomic_path
from forecast import data as fdata
from forecast.models import (
    ConstantVelocity,
    FoolClusters,
    IntentionModel,
    Seq2SeqGRU,
    SlideLastPose,
    SocialDiffusion,
    ZeroVelocity,
)
from forecast.models.intention import fit_intention_labels
from forecast.predict import LHIP, N_GLOBAL, RHIP, scene_features
from keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)

CKPT_SCHEMA = "forecast-checkpoint/1"
DISCRIMINATOR_PREFIXES = ("D_pose.", "D_label.")
NORMALISATION = "eq. 3.8 at the last observed frame: root = mid-hips, hip vector (left->right) on +x, z up"


@dataclass(frozen=True)
class GRUConfig:
    hidden: int = 128
    dropout: float = 0.0
    n_obs: int = 50
    n_pred: int = 25
    steps: int = 1200
    batch: int = 32
    lr: float = 1e-3
    seed: int = 0
    val_every: int = 50  # steps between validation scores (model selection); 0 = keep the last
    select: str = "mpjpe"  # the deterministic model is selected by its own objective (validation MPJPE, 1 s)


@dataclass(frozen=True)
class IntentionConfig:
    hidden: int = 128
    layers: int = 2
    z_dim: int = 16
    n_clusters: int = 32
    n_intentions: int = 8
    gamma: int = 10
    f_dim: int = 16
    tau_rec: int = 15
    w_adv: float = 0.05
    n_obs: int = 50
    n_pred: int = 50
    steps: int = 800
    batch: int = 32
    lr: float = 1e-3
    seed: int = 0
    val_every: int = 200  # steps between validation scores (model selection); 0 = keep the last
    select: str = "ndms"  # validation NDMS at 2-4 s


@dataclass(frozen=True)
class DiffusionConfig:
    channels: int = 64
    T: int = 1000
    n_frames: int = 64
    n_obs: int = 32
    persons: int = 2
    sample_steps: int = 20
    sample_eta: float = 0.0
    sample_dct: int = 0  # >0: the sampler keeps X_0 to this many DCT coefficients over the window (0 = off)
    clean_obs: bool = True
    anchor: bool = True  # motion coded relative to the last observed frame, per-lag statistics (continuity)
    root_vel: bool = False  # (anchored) root coded as per-frame displacements, not offsets from the anchor
    p_single: float = 0.0  # share of composed training scenes with one person (0.25: val NDMS .268 vs .281)
    mirror: bool = True  # also train on the left/right mirror of every single-person window (as the others)
    steps: int = 2500
    batch: int = 32
    lr: float = 5e-4
    seed: int = 0
    val_every: int = 250  # steps between validation scores (model selection); 0 = keep the last
    select: str = "ndms"  # validation NDMS at 2-4 s ("ndms_2_3": NDMS at 2 s and 3 s, clips weighted equally)
    val_windows: int = 48  # validation windows scored (at most; every val_stride frames of the val clips)
    val_stride: int = 10
    val_samples: int = 4
    ema: float = 0.0  # >0: validate and keep an exponential moving average of the weights (decay per step)


CONFIGS = {"gru": GRUConfig, "intention": IntentionConfig, "social_diffusion": DiffusionConfig}
BASELINES = ("zero_velocity", "constant_velocity", "slide")  # the evaluation's names: evaluate.BASELINES


def config_from_dict(kind: str, d: dict | None = None):
    """Typed config for ``kind`` from a dict (e.g. a TOML table); unknown keys are an error."""
    if kind not in CONFIGS:
        raise ValueError(f"unknown model '{kind}'; trainable models: {sorted(CONFIGS)}")
    cls = CONFIGS[kind]
    d = dict(d or {})
    names = {f.name: f.type for f in dataclasses.fields(cls)}
    bad = sorted(set(d) - set(names))
    if bad:
        raise ValueError(f"unknown {kind} config keys {bad}; valid keys: {sorted(names)}")
    defaults = cls()
    out = {}
    for k, v in d.items():
        kind_t = type(getattr(defaults, k))
        out[k] = (str(v).lower() in ("1", "true", "yes")) if kind_t is bool else kind_t(v)
    return cls(**out)


# ----------------------------------------------------------------------------- data


def clip_key(name: str) -> str:
    """Canonical CMU id (subject_trial) so one trial from two sources is one clip ('01_01' = '001_01')."""
    m = re.fullmatch(r"(?:scaled_)?0*(\d+)_0*(\d+)", name)
    return f"{int(m.group(1))}_{int(m.group(2))}" if m else name


def load_cmu(fps: float = fdata.TARGET_FPS, root: str | os.PathLike | None = None) -> list[fdata.Clip]:
    """All single-person CMU clips at ``fps`` (one copy per trial). The two-person take
    (``data.TWO_PERSON_DIR``, 18_01 + 19_01) is left out: it is the real two-person scene of the
    social evaluation (``data.cmu_two_person_clip``), never trained on, and leaving it out keeps the
    train/val/test split that the shipped checkpoints were trained and selected on."""
    seen, clips = set(), []
    for f in fdata.cmu_bvh_files(root):
        if f.parent.name == fdata.TWO_PERSON_DIR:
            continue
        c = fdata.clip_from_bvh(f, fps)
        k = clip_key(c.name)
        if k in seen:
            continue
        seen.add(k)
        clips.append(c)
    return clips


def load_sources(sources: list[str], fps: float = fdata.TARGET_FPS) -> list[fdata.Clip]:
    """'cmu' (the mocap root), track files (``tracks.npz``) or folders searched for ``tracks.npz``."""
    clips: list[fdata.Clip] = []
    for s in sources:
        if s == "cmu":
            clips += load_cmu(fps)
            continue
        p = Path(s)
        files = sorted(p.rglob("tracks.npz")) if p.is_dir() else [p]
        if not files:
            raise FileNotFoundError(f"no tracks.npz under {p}")
        clips += [fdata.clip_from_trackfile(f).resampled(fps) for f in files]
    return clips


def split_clips(clips: list[fdata.Clip], seed: int = 0):
    """The protocol's train / validation / test split by clip (``data.split_train_val_test``)."""
    tr, va, te = fdata.split_train_val_test([c.name for c in clips], [c.n_frames for c in clips], seed)
    return [clips[i] for i in tr], [clips[i] for i in va], [clips[i] for i in te]


def single_person_arrays(ws: fdata.WindowSet) -> tuple[np.ndarray, np.ndarray]:
    """Windows (N,T,1,J,3) -> normalised at the last observed frame (N,T,3J) and joint mask (N,T,J)."""
    x = ws.x[:, :, 0]
    R, root = fdata.norm_frame(x[:, ws.n_obs - 1], LHIP, RHIP)
    xn = fdata.normalize(x, R, root)
    return xn.reshape(len(x), x.shape[1], -1).astype(np.float32), ws.mask[:, :, 0]


def mirror(xn: np.ndarray, mask: np.ndarray, flip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left/right mirror of normalised poses (x -> -x, swap sides): doubles the data, keeps eq. 3.8."""
    N, T, D = xn.shape
    p = xn.reshape(N, T, D // 3, 3)[:, :, flip].copy()
    p[..., 0] *= -1
    return p.reshape(N, T, D), mask[:, :, flip]


# ----------------------------------------------------------------------------- checkpoints


def write_checkpoint(
    path: str | os.PathLike,
    schema: str,
    kind: str,
    config,
    skeleton: str,
    fps: float,
    normalisation: str,
    extra: dict | None,
    **payload,
) -> None:
    """Write a forecast checkpoint atomically: its config, skeleton, joints, fps and normalisation, then the
    caller's ``payload`` (weights and whatever else the model needs)."""
    blob = {
        "schema": schema,
        "kind": kind,
        "config": dataclasses.asdict(config),
        "skeleton": skeleton,
        "joint_names": list(get_skeleton(skeleton).joint_names),
        "fps": float(fps),
        "normalisation": normalisation,
        **payload,
        "extra": extra or {},
    }
    with atomic_path(path) as tmp:
        torch.save(blob, tmp)


def read_checkpoint(
    path: Path, schema: str, skeleton: str | None, what: str, train_cmd: str, map_location: str = "cpu"
) -> dict:
    """Load a checkpoint written by :func:`write_checkpoint` (weights_only=True) and check that it is one
    (``schema``) and fits the caller's data ``skeleton`` (None: any); errors say how to get a good one."""
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001 - re-raised with what to do
        raise FormatError(
            path, None, f"not a readable {what} ({type(e).__name__}: {e}).", f"Train one with `{train_cmd}`."
        ) from e
    if not isinstance(blob, dict) or blob.get("schema") != schema:
        got = blob.get("schema") if isinstance(blob, dict) else type(blob).__name__
        raise FormatError(
            path,
            "schema",
            f"expected '{schema}', got {got!r}.",
            f"This is not a {what} of this version; train one with `{train_cmd}`.",
        )
    if skeleton is not None and blob["skeleton"] != skeleton:
        raise FormatError(
            path,
            "skeleton",
            f"the checkpoint was trained on skeleton '{blob['skeleton']}' "
            f"({len(blob['joint_names'])} joints) but the data is '{skeleton}'.",
            f"Convert the data to '{blob['skeleton']}' or train a model on '{skeleton}'.",
        )
    return blob


def save_checkpoint(
    path: str | os.PathLike,
    model: torch.nn.Module,
    kind: str,
    config,
    skeleton: str = "body19",
    fps: float = fdata.TARGET_FPS,
    extra: dict | None = None,
) -> None:
    state = {
        k: v.detach().cpu()
        for k, v in model.state_dict().items()
        if not k.startswith(DISCRIMINATOR_PREFIXES)  # only needed for training; keeps files < 2 MB
    }
    write_checkpoint(path, CKPT_SCHEMA, kind, config, skeleton, fps, NORMALISATION, extra, state_dict=state)


def build_model(kind: str, config, n_joints: int, state: dict | None = None) -> torch.nn.Module:
    D = 3 * n_joints
    if kind == "gru":
        m = Seq2SeqGRU(D, config.hidden, config.dropout)
    elif kind == "intention":
        centres = np.zeros((config.n_clusters, D), np.float32) if state is None else state["centres"].numpy()
        merge = np.zeros(config.n_clusters, np.int64) if state is None else state["merge"].numpy()
        m = IntentionModel(
            D,
            centres,
            merge,
            config.n_intentions,
            config.hidden,
            config.layers,
            config.z_dim,
            gamma=config.gamma,
            f_dim=config.f_dim,
        )
    elif kind == "social_diffusion":
        m = SocialDiffusion(D + N_GLOBAL, config.n_frames, config.channels, config.T, anchored=config.anchor)
        m.n_obs, m.sample_steps, m.sample_eta = config.n_obs, config.sample_steps, config.sample_eta
        m.sample_dct = config.sample_dct
        m.n_obs_clean = config.n_obs if config.clean_obs else 0
        m.anchor = config.n_obs - 1 if config.anchor else None
        if config.root_vel and not config.anchor:
            raise ValueError(
                "root_vel = true needs anchor = true (displacements are summed from the anchor frame)"
            )
        m.root_vel = config.root_vel
    else:
        raise ValueError(f"unknown model '{kind}'")
    if state is not None:
        try:
            missing, unexpected = m.load_state_dict(state, strict=False)
        except RuntimeError as e:  # shape mismatches: torch lists every tensor, the first says enough
            lines = [ln.strip() for ln in str(e).splitlines() if "mismatch" in ln]
            first = lines[0] if lines else str(e).splitlines()[0]
            raise ValueError(
                f"the {kind} state does not fit the checkpoint's config ({len(lines)} tensors differ; first: "
                f"{first}). The config or the weights were changed after training: retrain with "
                "`forecast train`, or use the original file."
            ) from None
        missing = [k for k in missing if not k.startswith(DISCRIMINATOR_PREFIXES)]
        if missing or unexpected:
            raise ValueError(
                f"{kind} state does not fit the config: missing {missing}, unexpected {unexpected}"
            )
    m.n_obs = config.n_obs
    return m


def load_checkpoint(path: str | os.PathLike, skeleton: str | None = None, map_location: str = "cpu"):
    """-> (model, meta). ``skeleton``: the skeleton the caller's data uses; a mismatch is a clear error."""
    blob = read_checkpoint(
        Path(path), CKPT_SCHEMA, skeleton, "forecast checkpoint", "forecast train", map_location
    )
    config = config_from_dict(blob["kind"], blob["config"])
    model = build_model(blob["kind"], config, len(blob["joint_names"]), blob["state_dict"])
    meta = {k: v for k, v in blob.items() if k != "state_dict"}
    meta["config"] = config
    return model.to(map_location), meta


def baseline(kind: str, lhip: int = LHIP, rhip: int = RHIP) -> torch.nn.Module:
    if kind in ("zero_velocity", "zero"):
        return ZeroVelocity()
    if kind in ("constant_velocity", "const"):
        return ConstantVelocity()
    if kind == "slide":
        return SlideLastPose(lhip, rhip)
    raise ValueError(f"unknown baseline '{kind}'; baselines: {BASELINES}")


def fool_model(train_windows: fdata.WindowSet, k: int = 48, seed: int = 0) -> FoolClusters:
    """Sec. 6.4.4's fool: 48 cluster means of the training poses (hip-centric, per-frame normalised)."""
    from scipy.cluster.vq import kmeans2

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


# ----------------------------------------------------------------------------- model selection

# The evaluation protocol's model selection (validation split only, never the test split): every
# ``val_every`` steps the model forecasts validation windows (observe 2 s, forecast 4 s at 25 Hz, the rate
# make_windows resamples every clip to, as for training; fixed windows and seed) and is scored by NDMS
# (eq. 6.9-6.12, mean over samples; D = the validation clips of the window's activity, its own clip
# included, as the evaluation's `ndms`) over the 2-4 s horizon, the horizon the issue compares models at; the
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
        from forecast import evaluate as E

        ws = fdata.make_windows(clips, VAL_N_OBS, VAL_N_PRED, stride, persons="each")
        if len(ws) == 0:
            raise ValueError(
                f"no validation windows of {VAL_N_OBS + VAL_N_PRED} frames in {len(clips)} clips "
                f"(skipped {ws.skipped}); add longer validation clips or set val_every=0"
            )
        sel = np.sort(np.random.default_rng(seed).choice(len(ws), min(max_windows, len(ws)), replace=False))
        self.x = ws.x[sel, :, 0]
        acts = fdata.clip_activities(clips)
        self.activities = [acts[clips[c].name] for c in ws.clip[sel]]
        self.groups = [E.clip_group(clips[c].name) for c in ws.clip[sel]]
        self.scorer = E.ndms_scorer_for(clips, activities=acts)
        self.n_samples, self.seed, self.fps = n_samples, seed, ws.fps

    def __call__(self, model: torch.nn.Module) -> dict:
        from forecast.evaluate import ndms_at
        from forecast.predict import forecast_world

        was_training = model.training
        obs, gt = self.x[:, :VAL_N_OBS], self.x[:, VAL_N_OBS:]
        S = self.n_samples if getattr(model, "stochastic", False) else 1
        with torch.random.fork_rng(devices=[]):  # fixed sampling noise, training RNG untouched
            torch.manual_seed(self.seed)
            y = forecast_world(model, obs[:, :, None], None, VAL_N_PRED, S)[:, :, :, 0]  # (B,S,H,J,3)
        model.train(was_training)
        # the seed's NDMS (issue 19): D = validation clips of the window's activity, its own clip included
        nd_w = np.stack(
            [self.scorer.score_forecast(obs[b], y[b], None, self.activities[b]) for b in range(len(y))]
        )
        nd = nd_w.mean(0)
        err = np.linalg.norm(y[:, :, :25] - gt[:, None, :25], axis=-1).mean()
        # NDMS at 2 and 3 s (as the report), every validation clip weighted equally: on CMU one long clip
        # holds 79 of the 125 windows at stride 5 and decided the window mean
        at = 0.5 * (ndms_at(nd_w, self.fps, 2.0) + ndms_at(nd_w, self.fps, 3.0))  # (B,)
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


class _Selector:
    """Keeps the state with the best validation score (``config.select``, ``val_every`` steps apart)."""

    def __init__(self, model, config, val_clips):
        self.every = int(getattr(config, "val_every", 0)) if val_clips else 0
        if config.select not in SELECT:
            raise ValueError(f"select must be one of {sorted(SELECT)}, got {config.select!r}")
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


# ----------------------------------------------------------------------------- training loops

Progress = Callable[[int, dict], None]


def _masked_joint_l2(pred, fut, mask):
    J = mask.shape[-1]
    err = (pred - fut).view(*pred.shape[:2], J, 3).norm(dim=-1)
    m = mask.float()
    return (err * m).sum() / m.sum().clamp(min=1)


def train(
    kind: str,
    clips: list[fdata.Clip],
    config=None,
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
    torch.manual_seed(config.seed)
    np.random.seed(config.seed)  # the intention model's adversarial window offsets
    rng = np.random.default_rng(config.seed)
    sk = clips[0].skeleton if clips else "body19"
    J = get_skeleton(sk).n_joints
    if kind == "social_diffusion":
        return _train_diffusion(clips, config, J, rng, progress, device, init, val_clips)
    ws = fdata.make_windows(clips, config.n_obs, config.n_pred, stride=5, persons="each")
    if len(ws) == 0:
        raise ValueError(
            f"no training windows of {config.n_obs + config.n_pred} frames (skipped: {ws.skipped})"
        )
    xn, mk = single_person_arrays(ws)
    flip = get_skeleton(sk).flip_index
    xm, mm = mirror(xn, mk, flip)
    xn, mk = np.concatenate([xn, xm]), np.concatenate([mk, mm])
    model = None
    if kind == "gru":
        model = build_model(kind, config, J, init).to(device)
    elif kind == "intention":
        from forecast.models.intention import local_poses

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
        labels_all = model.labels(torch.from_numpy(loc)).numpy()  # (N,T)
    X, M = torch.from_numpy(xn), torch.from_numpy(mk)
    opt = torch.optim.Adam(
        model.parameters() if kind == "gru" else model.generator_parameters(), lr=config.lr
    )
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, config.steps)
    if kind == "intention":
        opt_d = torch.optim.Adam(model.discriminator_parameters(), lr=config.lr)
    hist: dict = {"loss": [], "n_windows": len(xn), "skipped": ws.skipped}
    sel = _Selector(model, config, val_clips)
    t0 = time.perf_counter()
    t_val = 0.0
    model.train()
    n_obs, H = config.n_obs, config.n_pred
    for step in range(config.steps):
        idx = torch.from_numpy(rng.integers(0, len(X), config.batch))
        xb, mb = X[idx].to(device), M[idx].to(device)
        obs, fut, mfut = xb[:, :n_obs], xb[:, n_obs:], mb[:, n_obs:]
        if kind == "gru":
            loss = _masked_joint_l2(model(obs, H), fut, mfut)
            terms = {"loss": loss.item()}
        else:
            g = config.gamma
            lab = torch.from_numpy(labels_all)[idx].to(device)
            c_all = torch.cat([lab[:, n_obs - 1 :], lab[:, -1:].expand(-1, g - 1)], 1)  # pad the look-ahead
            loss, terms, d_loss, _ = model.losses(obs, fut, c_all, mfut, config.tau_rec, config.w_adv)
            terms["loss"] = loss.item()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        if kind == "intention":
            opt_d.zero_grad()
            dl = d_loss()
            dl.backward()
            opt_d.step()
        hist["loss"].append(terms["loss"])
        tv = time.perf_counter()
        sel.step(step, step == config.steps - 1)
        t_val += time.perf_counter() - tv
        if progress:
            progress(step, terms)
    hist["seconds"] = time.perf_counter() - t0 - t_val
    hist["steps_per_s"] = config.steps / hist["seconds"]
    sel.finish(hist)
    model.eval()
    return model, hist


def composed_batch(
    x_single: np.ndarray,
    P: int,
    batch: int,
    rng: np.random.Generator,
    dist_m: tuple[float, float] = (1.0, 3.0),
    return_index: bool = False,
):
    """Compose ``batch`` scenes of P people from single-person windows x_single (N,T,J,3) world metres (as the
    seed's composed CMU-Mocap scenes [200]): each person is rotated about z at random and placed at a random
    distance around the first. -> (batch,T,P,J,3) (and the windows used, (batch,P), with return_index)."""
    N, T, J, _ = x_single.shape
    idx = rng.integers(0, N, (batch, P))
    x = x_single[idx]  # (B,P,T,J,3)
    R, root = fdata.norm_frame(x[:, :, 0], LHIP, RHIP)
    root[..., 2] = 0
    x = np.einsum("bpij,bptkj->bptki", R, x - root[:, :, None, None])
    a = rng.uniform(-np.pi, np.pi, (batch, P))
    c, s = np.cos(a), np.sin(a)
    Rz = np.stack(
        [np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1), np.stack([0 * c, 0 * c, 1 + 0 * c], -1)],
        -2,
    )
    x = np.einsum("bpij,bptkj->bptki", Rz, x)
    r, b = rng.uniform(*dist_m, (batch, P)), rng.uniform(-np.pi, np.pi, (batch, P))
    off = np.stack([r * np.cos(b), r * np.sin(b), 0 * r], -1)
    off[:, 0] = 0
    x = x + off[:, :, None, None]
    x = x.transpose(0, 2, 1, 3, 4).astype(np.float32)
    return (x, idx) if return_index else x


def diffusion_batch_features(scenes: np.ndarray, person_mask: np.ndarray, n_obs: int) -> np.ndarray:
    """Scenes (B,T,P,J,3) world -> features (B,P,T,F) in the scene frame of the last observed frame."""
    from forecast.predict import scene_frame

    R, root = scene_frame(scenes[:, n_obs - 1], person_mask)
    xs = np.einsum("bij,btpkj->btpki", R, scenes - root[:, None, None, None])
    return scene_features(xs.transpose(0, 2, 1, 3, 4), n_obs - 1)


def _feature_stats(model, f: np.ndarray, stat) -> np.ndarray:
    """Mean or std of raw features f (B,P,N,F) in the model's coding: per channel, or (anchored models) per
    frame and channel of the offsets from the anchor frame, constant channels pooled over frames."""
    from forecast.models.diffusion import N_CONST

    if model.feat_mean.dim() == 1:
        return stat(f.reshape(-1, f.shape[-1]), 0).astype(np.float32)
    rel = model.code(torch.from_numpy(f), torch.from_numpy(f[:, :, model.anchor])).numpy()
    out = stat(rel.reshape(-1, *rel.shape[-2:]), 0)  # (N,F)
    out[:, -N_CONST:] = stat(rel[..., -N_CONST:].reshape(-1, N_CONST), 0)
    return out.astype(np.float32)


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
        raise ValueError(f"no training windows of {N} frames")
    if config.mirror:  # x -> -x with the sides swapped is a real pose too; composed_batch re-frames it
        flip = get_skeleton(clips[0].skeleton).flip_index
        xm, _ = mirror(xs.reshape(*xs.shape[:2], -1), single.mask[:, :, 0], flip)
        xs = np.concatenate([xs, xm.reshape(xs.shape)])
    # feature statistics from a large composed sample
    sample = composed_batch(xs, P, 2048, rng)
    f = diffusion_batch_features(sample, np.ones((len(sample), P), bool), config.n_obs)
    model = build_model("social_diffusion", config, J, init).to(device)
    if init is None:  # a continued model keeps its feature statistics
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
    sel = _Selector(model if ema is None else ema, config, val_clips)
    t0 = time.perf_counter()
    t_val = 0.0
    model.train()
    for step in range(config.steps):
        use_real = scenes is not None and len(scenes) and rng.random() < 0.5
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
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        if ema is not None:
            with torch.no_grad():
                for pe, pm_ in zip(ema.parameters(), model.parameters(), strict=True):
                    pe.lerp_(pm_, 1 - config.ema)
        hist["loss"].append(loss.item())
        tv = time.perf_counter()
        sel.step(step, step == config.steps - 1)
        t_val += time.perf_counter() - tv
        if progress:
            progress(step, {"loss": loss.item()})
    hist["seconds"] = time.perf_counter() - t0 - t_val
    hist["steps_per_s"] = config.steps / hist["seconds"]
    sel.finish(hist)
    model = model if ema is None else ema
    model.eval()
    return model, hist
