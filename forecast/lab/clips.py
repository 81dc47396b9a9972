"""Clips for training and evaluation: loading CMU and track files, the split by clip, normalised
single-person arrays, the left/right mirror and composed multi-person scenes."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.forecast.lab import cmu_more
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab.cmu_more import CMU_MORE_DIR
from roomcap.forecast.runtime.predict import LHIP, RHIP, scene_features, scene_frame


def clip_key(name: str) -> str:
    """Canonical CMU id (subject_trial) so one trial from two sources is one clip ('01_01' = '001_01')."""
    m = re.fullmatch(r"(?:scaled_)?0*(\d+)_0*(\d+)", name)
    return f"{int(m.group(1))}_{int(m.group(2))}" if m else name


def load_cmu(fps: float = fdata.TARGET_FPS, root: str | os.PathLike | None = None) -> list[fdata.Clip]:
    """All single-person CMU clips at ``fps`` (one copy per trial). The two-person take
    (``data.TWO_PERSON_DIR``, 18_01 + 19_01) is left out: it is the real two-person scene of the
    social evaluation (``data.cmu_two_person_clip``), never trained on, and leaving it out keeps the
    train/val/test split that the shipped checkpoints were trained and selected on. ``cmu-more`` is left out
    too (source ``cmu-all``, :func:`load_one_person_all`)."""
    seen, clips = set(), []
    for f in fdata.cmu_bvh_files(root):
        if f.parent.name == fdata.TWO_PERSON_DIR or CMU_MORE_DIR in f.parts:
            continue
        c = fdata.clip_from_bvh(f, fps)
        k = clip_key(c.name)
        if k in seen:
            continue
        seen.add(k)
        clips.append(c)
    return clips


@dataclass(frozen=True)
class SplitData:
    """Clips split by clip (:func:`load_one_person_all`, :func:`load_two_person_real`), their activities."""

    train: list[fdata.Clip]
    val: list[fdata.Clip]
    test: list[fdata.Clip]
    activities: dict[str, str]

    @property
    def clips(self) -> list[fdata.Clip]:
        return self.train + self.val + self.test


def more_activities() -> dict[str, str]:
    """Activities of ``cmu-more``'s clips from its manifest ({} when the folder is absent)."""
    try:
        return cmu_more.activities()
    except FileNotFoundError:
        return {}


def clip_activities(
    clips: list[fdata.Clip], index: dict[tuple[int, int], str] | None = None
) -> dict[str, str]:
    """Clip name -> activity for the NDMS database: CMU clips by their description in ``index.csv``
    (``activity_of_description``), else by ``cmu-more``'s manifest, the 8-action benchmark's clips
    ('cmu8_test_walking_1') by their action ('cmu8 walking'); clips without an entry (track files, ...) are
    ``data.UNLABELLED``."""
    idx = fdata.cmu_index() if index is None else index
    out = {}
    extra: dict[str, str] | None = None
    for c in clips:
        st = fdata.cmu_subject_trial(c.name)
        if st is not None and st in idx:
            out[c.name] = fdata.activity_of_description(idx[st])
            continue
        if extra is None:  # cmu-more's manifest, read once
            extra = more_activities()
        out[c.name] = extra.get(c.name) or _benchmark_activity(c.name) or fdata.UNLABELLED
    return out


def _benchmark_activity(name: str) -> str | None:
    """'cmu8 walking' for a clip of the 8-action benchmark named 'cmu8_<split>_walking_<n>', else None."""
    parts = name.split("_", 2)
    if len(parts) == 3 and parts[0] == "cmu8" and parts[1] in ("train", "test"):
        return "cmu8 " + parts[2].rsplit("_", 1)[0]
    return None


BENCHMARK_PREFIX = "cmu8"  # clip names of the 8-action benchmark: cmu8_train_walking_1, cmu8_test_walking_1


def load_one_person_all(seed: int = 0, fps: float = fdata.TARGET_FPS) -> SplitData:
    """All one-person CMU motion, split by clip: the CMU BVH of ``load_cmu`` (its split unchanged), the
    one-person ``cmu-more`` BVH (split the same way, on its own, so neither reshuffles the other) and the
    CMU 8-action benchmark's files (``cmu_more.BENCHMARK_ACTIONS``): its train files train, its test files
    are test only, never trained on. The two-person takes are not here (18_01 + 19_01, the salsa pairs).
    Activities: CMU ``index.csv`` for the first, ``cmu-more``'s manifest for the second, and
    "cmu8 <action>" for the benchmark (its NDMS database is the benchmark's own test sequences of the action,
    as the seed scores it, sec. 6.3.2)."""
    old = load_cmu(fps)
    more = cmu_more.load_single(fps)
    tr, va, te = split_clips(old, seed)
    a, v, b = split_clips(more, seed)
    tr, va, te = tr + a, va + v, te + b
    bf = cmu_more.benchmark_files()
    for split, by_action in bf.files.items():
        for files in by_action.values():
            for f in files:
                c = cmu_more.benchmark_clip(f, fps)
                name = f"{BENCHMARK_PREFIX}_{split}_{c.name}"
                (tr if split == "train" else te).append(fdata.Clip(name, c.xyz_m, c.fps, c.skeleton))
    return SplitData(tr, va, te, clip_activities(tr + va + te))


def load_two_person_real(seed: int = 0, fps: float = fdata.TARGET_FPS) -> SplitData:
    """The real two-person CMU takes: the 14 salsa takes of ``cmu-more`` split by take (``split_clips``: with
    seed 0, 9 train / 2 validation / 3 test) and 18_01 + 19_01 (2.5 s, too short for a 10-s evaluation)
    in train."""
    salsa = cmu_more.load_salsa(fps)
    tr, va, te = split_clips(salsa, seed)
    try:
        tr = tr + [fdata.cmu_two_person_clip(fps=fps)]
    except FileNotFoundError:
        pass
    return SplitData(tr, va, te, clip_activities(tr + va + te))


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
    R, root = scene_frame(scenes[:, n_obs - 1], person_mask)
    xs = np.einsum("bij,btpkj->btpki", R, scenes - root[:, None, None, None])
    return scene_features(xs.transpose(0, 2, 1, 3, 4), n_obs - 1)
