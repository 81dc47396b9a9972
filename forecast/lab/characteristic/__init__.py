"""Characteristic 3D pose forecasting (Diller 2024, ch. 3) on CMU mocap: labels, data, training, evaluation.

``python -m roomcap.forecast.characteristic train --out PATH`` / ``eval --checkpoint PATH`` (``forecast
characteristic ...``). Modules: ``labels`` (annotation and samples), ``model`` (config, networks,
checkpoint), ``protocol`` (data split and evaluation), ``training`` and ``cli``; the names below are
importable from the package. The shipped
``forecast/checkpoints/characteristic_cmuall.pt`` (1.8 MB, ~8.5 min of CPU on one thread) was trained with::

    OMP_NUM_THREADS=1 python -m roomcap.forecast.characteristic train --data cmu-all
        --out forecast/checkpoints/characteristic_cmuall.pt
        --set steps=1100 det_steps=1000 val_every=100 n_rest_train=3 time_limit_s=560 seed=0 --no-eval

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
  selection on the validation split, figures on the test split. ``--data cmu-all`` (train and eval) reads
  every one-person CMU clip with the split of ``forecast train --data cmu-all``
  (``forecast.clips.load_one_person_all``: the ``cmu`` split unchanged, the 8-action benchmark's test files in
  test only); its labels come from the same annotator. ``characteristic_cmuall.pt`` was trained with the
  recipe above plus ``--data cmu-all`` (seed in ``--set seed=...``; BENCHMARKS.md).
"""

from __future__ import annotations

from roomcap.forecast.lab.characteristic.labels import (
    END_EFFECTORS,
    AnnotatorConfig,
    Labelled,
    annotate,
    articulation,
    eval_starts,
    label_clips,
    make_pairs,
    mirror_pairs,
    segments,
)
from roomcap.forecast.lab.characteristic.model import (
    FAMILY,
    NORMALISATION,
    SHIPPED,
    CharConfig,
    build_models,
    config_from_dict,
    load_checkpoint,
    save_checkpoint,
)
from roomcap.forecast.lab.characteristic.protocol import (
    DATA_SOURCES,
    CharData,
    best_of_k,
    evaluate,
    load_cmu_labelled,
    load_labelled,
)
from roomcap.forecast.lab.characteristic.training import train

__all__ = [
    "FAMILY",
    "DATA_SOURCES",
    "END_EFFECTORS",
    "NORMALISATION",
    "SHIPPED",
    "AnnotatorConfig",
    "CharConfig",
    "CharData",
    "Labelled",
    "annotate",
    "articulation",
    "best_of_k",
    "build_models",
    "config_from_dict",
    "eval_starts",
    "evaluate",
    "label_clips",
    "load_checkpoint",
    "load_cmu_labelled",
    "load_labelled",
    "make_pairs",
    "mirror_pairs",
    "save_checkpoint",
    "segments",
    "train",
]
