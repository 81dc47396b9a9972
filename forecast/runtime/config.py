"""Training configurations of the forecasting models: frozen dataclasses holding the only copy of each
default, built by :func:`forecast.runtime.registry.config_from_dict` (``core.config``: unknown keys are an
error listing the valid ones, values are coerced, a wrong kind names the key), which maps each model's name
to its class. The small defaults train on 2 CPU cores in minutes.
"""

from __future__ import annotations

from dataclasses import dataclass

# scene features beyond the 3J pose (forecast.predict.scene_features): root offset (3), relative heading (2),
# anchor root (3), heading (2)
N_GLOBAL = 10


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
    continuity: bool = True  # forecasts continue the last observed velocity (predict.continue_velocity)
    w_speed: float = 0.0  # weight of the joint-speed term (lab.train.speed_gap) beside the position error


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
    continuity: bool = True  # forecasts continue the last observed velocity (predict.continue_velocity)
    w_speed: float = 0.0  # weight of the joint-speed term (lab.train.speed_gap) beside L_rec and L_adv
    label_temp: float = 1.0  # sampling: temperature of the intention labels (models.intention.sample)
    z_scale: float = 1.0  # sampling: scale of the pose decoder's noise z (models.intention.sample)
    variety: int = 1  # training: noise draws per window, L_rec of the closest (lab.train.intention_losses)
    label_steps: int = 0  # training (angle benchmark): steps of the intention forecaster alone on L_sym first


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
    sample_temp: float = 1.0  # scale of the sampler's noise (models.diffusion.SocialDiffusion.sample_window)
    clean_obs: bool = True
    anchor: bool = True  # motion coded relative to the last observed frame, per-lag statistics (continuity)
    lag_stats: bool = True  # (anchored) mean/std per lag: bound to n_frames; false: per channel, any length
    root_vel: bool = False  # (anchored) root coded as per-frame displacements, not offsets from the anchor
    lag_hold: bool = False  # (lag_stats) past the window the last lag's statistics hold: one pass, any length
    p_single: float = 0.0  # share of composed training scenes with one person
    p_real: float = 0.5  # share of batches of real multi-person scenes (if the clips hold any), else composed
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
    continuity: bool = True  # forecasts continue the last observed velocity (predict.continue_velocity)


BASELINES = ("zero_velocity", "constant_velocity", "slide")  # the evaluation's names: evaluate.BASELINES
