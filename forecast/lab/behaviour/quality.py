"""The 3D pose quality metric of sec. 4.5.1 / appendix 4.7.7, as the seed defines it.

One binary classifier (a 3-layer MLP) is trained ONCE on real 3D poses (the uncorrelated 3D database) and fake
poses "collected during the training process of our method and all baselines": the poses the pose-predicting
models output at several training steps, from the random initial network (random joint placements) to
nearly converged ones (minor bone-length inconsistencies). The classifier is saved and then used to score
every method alike: quality = 1 - a, with a the share of the method's poses the classifier calls fake
(``training.share_real``), so 1 means indistinguishable from real poses.

Here the snapshots come from separate training runs (their own model seed) on the training sequences only;
their predictions on training sequences (never validation or test) form the fake pool. The real pool is the
3D database's even frames (subjects disjoint from every sequence); its odd frames stay out as a check.

Every compared model that outputs 3D poses is a source of the pool (``pool_fakes``): the pose-predicting
variants (``POOL_VARIANTS``: full, pose_only, action_2d; action_only has no pose) by their snapshot runs, and
the train-average baseline by its own "training", the running mean of the training targets over the batches
a network would see, on the same schedule (``train_average_snapshots``); zero velocity has no 3D. Each
source weighs the same in the fake class (``pool_fakes``), so the classifier learns no one model's flaws
more than another's.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
from torch import nn

from roomcap.core.progress import Progress
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.behaviour.data import JOINTS
from roomcap.forecast.lab.behaviour.model import BehaviourConfig
from roomcap.forecast.runtime.checkpoint import read_checkpoint, write_checkpoint

QUALITY_SHIPPED = Path(__file__).resolve().parents[2] / "checkpoints" / "behaviour_quality_cmu.pt"
FAMILY = "behaviour_quality"  # the registry's family of these checkpoints
POOL_VARIANTS = ("full", "pose_only", "action_2d")  # the variants that output 3D poses (Table 4.2)
POOL_BASELINES = ("train_average",)  # the baselines that output 3D poses (Table 4.1)


def snapshot_poses(
    cfg: BehaviourConfig,
    tr: T.Prepared,
    db: np.ndarray,
    every: int,
    per_snapshot: int,
    progress: Progress | None = None,
) -> list[tuple[int, np.ndarray]]:
    """Train ``cfg`` (eq. 4.1, no model selection) for ``cfg.steps`` steps and collect its predicted poses on
    ``per_snapshot`` random training sequences at step 0 (the untrained network) and every ``every`` steps
    -> [(step, poses (n,J,3) viewer frame)]."""
    f = T._fit_state(cfg, db)
    rng = np.random.default_rng(cfg.seed)
    J = len(cfg.joint_names)

    def snap(step: int) -> tuple[int, np.ndarray]:
        f.gen.eval()
        idx = rng.choice(len(tr), min(per_snapshot, len(tr)), replace=False)
        return step, T.predict(f.gen, cfg, tr.take(idx))[1].reshape(-1, J, 3)

    out = [snap(0)]
    for step in range(1, cfg.steps + 1):
        T._generator_step(f, tr)
        if step % every == 0:
            out.append(snap(step))
        if progress:
            progress(f"snapshots {cfg.variant}", step, cfg.steps)
    return out


@dataclasses.dataclass
class QualityModel:
    """The trained classifier, its joints and how it was made (pool sizes, sources, seed)."""

    clf: nn.Module
    joints: tuple[str, ...]
    meta: dict


def fit(real: np.ndarray, fake: np.ndarray, names, seed: int = 0, steps: int = 4000) -> QualityModel:
    """The classifier on every pose of both pools, class-balanced: each batch draws as many real as fake
    poses (the two classes weigh the same whatever the pools' sizes); fixed seed."""
    clf = T.quality_classifier(real, fake, names, seed, steps)
    return QualityModel(
        clf, tuple(names), {"n_real": len(real), "n_fake": len(fake), "seed": seed, "clf_steps": steps}
    )


def save(path, q: QualityModel) -> None:
    write_checkpoint(
        path, FAMILY, config={}, weights={"model": q.clf.state_dict()}, extra=q.meta, joints=list(q.joints)
    )


def load(path) -> QualityModel:
    blob = read_checkpoint(Path(path), FAMILY, missing_as_is=True)
    names = tuple(blob["joints"])
    clf = T.quality_mlp(len(names))
    clf.load_state_dict(blob["weights"]["model"])
    clf.eval()
    return QualityModel(clf, names, dict(blob["extra"]))


def build_pool(
    base: BehaviourConfig,
    variants: list[str],
    tr: T.Prepared,
    db: np.ndarray,
    every: int,
    per_snapshot: int,
    progress: Progress | None = None,
) -> tuple[dict[str, list[tuple[int, np.ndarray]]], dict]:
    """The fake pool: the snapshots of each pose-predicting variant -> ({variant: snapshots}, timings)."""
    snaps, secs = {}, {}
    for v in variants:
        cfg = dataclasses.replace(base, variant=v)
        t0 = time.process_time()
        snaps[v] = snapshot_poses(cfg, tr, db, every, per_snapshot, progress)
        secs[v] = time.process_time() - t0
    return snaps, secs


def real_split(db: np.ndarray, names) -> tuple[np.ndarray, np.ndarray]:
    """The 3D database's even frames (the classifier's real pool) and odd frames (held out)."""
    jidx = [JOINTS.index(n) for n in names]
    return db[0::2][:, jidx], db[1::2][:, jidx]


def train_average_snapshots(cfg: BehaviourConfig, tr: T.Prepared, every: int) -> list[tuple[int, np.ndarray]]:
    """The train-average baseline's snapshots on a network's schedule: at every ``every``-th of
    ``cfg.steps`` steps, the average target pose (``training.train_average``) of the ``step * cfg.batch``
    training sequences drawn so far (one random stream, ``cfg.seed``) -> [(step, pose (1,J,3))]."""
    rng = np.random.default_rng(cfg.seed)
    drawn = rng.integers(len(tr), size=cfg.steps * cfg.batch)
    S, m, J = tr.tgt_3d.shape[:3]
    X = tr.tgt_3d.astype(np.float64)  # as train_average: the pelvis at x = y = 0
    p = tr.names.index("pelvis")
    X[..., :2] -= X[..., p : p + 1, :2]
    per_seq = X.sum(1).reshape(S, -1)  # (S, J*3) each sequence's m target poses summed
    out = []
    for step in range(every, cfg.steps + 1, every):
        n = np.bincount(drawn[: step * cfg.batch], minlength=S)  # how often each sequence was drawn
        out.append((step, (n @ per_seq / (n.sum() * m)).reshape(1, J, 3).astype(np.float32)))
    return out


def pool_fakes(
    sources: dict[str, list[tuple[int, np.ndarray]]], seed: int = 0
) -> tuple[np.ndarray, dict[str, dict]]:
    """Sec. 4.7.7's fake class pooled over every compared model: ``sources`` {model: [(step, poses (n,J,3))]}
    -> (fake poses (S*n_max,J,3), {model: {n_poses, n_pooled, snapshot_steps}}). Each source enters with as
    many poses as the largest (``n_max``): its own, then repeats of them drawn at random (``seed``) where it
    has fewer (the train average has one pose per snapshot), so each compared model weighs the same."""
    if not sources or any(not s for s in sources.values()):
        raise ValueError("pool_fakes: every source needs at least one snapshot")
    rng = np.random.default_rng(seed)
    own = {n: np.concatenate([p for _, p in s]).astype(np.float32) for n, s in sources.items()}
    n_max = max(len(p) for p in own.values())
    out, info = [], {}
    for n, p in own.items():
        extra = rng.integers(len(p), size=n_max - len(p))
        out.append(np.concatenate([p, p[extra]]))
        info[n] = {"n_poses": len(p), "n_pooled": n_max, "snapshot_steps": [st for st, _ in sources[n]]}
    return np.concatenate(out), info
