"""Forecasting models (PyTorch): baselines, seq2seq GRU, the ch. 6 intention model, Social Diffusion (ch. 7).

Every model maps observed motion to ``n_samples`` futures through ``sample(obs, n_pred, n_samples, ...)``.
Single-person models take ``obs (B,T,D)`` normalised at the last observed frame (eq. 3.8) with
D = 3J; Social Diffusion takes scenes (see ``diffusion.py``).
"""

from roomcap.forecast.runtime.models.baselines import (
    ConstantVelocity,
    FoolClusters,
    SlideLastPose,
    ZeroVelocity,
)
from roomcap.forecast.runtime.models.diffusion import SocialDiffusion
from roomcap.forecast.runtime.models.gru import Seq2SeqGRU
from roomcap.forecast.runtime.models.intention import IntentionModel

__all__ = [
    "ConstantVelocity",
    "FoolClusters",
    "IntentionModel",
    "Seq2SeqGRU",
    "SlideLastPose",
    "SocialDiffusion",
    "ZeroVelocity",
]
