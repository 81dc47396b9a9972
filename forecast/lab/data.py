"""Motion data for forecasting: windows and adapters (clips and normalisation: ``runtime.normalise``).

A *clip* is ``xyz_m (T,P,J,3)`` world metres, z up, NaN where unknown, at ``fps``, in a
named skeleton (``body19`` by default). Sources: track files (``track.trackfile``), CMU BVH
(via ``synthetic.bvh``), and the Humans-in-Kitchens per-person npz layout (``smpl29``).

Windows for training/evaluation are ``n_obs + n_pred`` frames resampled to a target rate;
missing joints are filled (last known value) and reported in ``mask`` so losses and metrics
can ignore them. Windows whose normalisation frame lacks both hips are skipped, clips
shorter than a window are skipped, and both are counted in ``WindowSet.skipped``.

Normalisation follows the code's version (CONTRACTS.md): root = mid-hips, the hip vector
(left_hip -> right_hip) is rotated onto +x about z (z up).
"""

from __future__ import annotations

import logging
import os
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import load_npz
from roomcap.forecast.runtime import normalise as _normalise
from roomcap.keypoints.skeletons import get_skeleton
from roomcap.synthetic import bvh

log = logging.getLogger(__name__)

# clips and normalisation live in the runtime (forecasting a track needs them); the lab reads them as data.X
TARGET_FPS, LHIP, RHIP = _normalise.TARGET_FPS, _normalise.LHIP, _normalise.RHIP
Clip, clip_from_trackfile, clip_name = _normalise.Clip, _normalise.clip_from_trackfile, _normalise.clip_name
hip_indices, norm_frame, normalize, denormalize = (
    _normalise.hip_indices,
    _normalise.norm_frame,
    _normalise.normalize,
    _normalise.denormalize,
)
fill = _normalise.fill

# ----------------------------------------------------------------------------- clips


def cmu_bvh_files(root: str | os.PathLike | None = None) -> list[Path]:
    """The CMU BVH clips under the mocap root (``synthetic.bvh.list_clips``: ``$ROOMCAP_MOCAP`` or
    ``$ROOMCAP_SHARED/data/motion``); raises with what to set when there are none."""
    files = bvh.list_clips(root)
    if not files:
        raise FileNotFoundError(
            f"no BVH clips under {root or 'the mocap root'}; set ROOMCAP_MOCAP or ROOMCAP_SHARED"
        )
    return files


def clip_from_bvh(path: str | os.PathLike, fps: float = TARGET_FPS) -> Clip:
    """A CMU BVH clip as body19 at ``fps`` through the synthetic-world BVH reader + FK."""
    c = bvh.load_clip(path, fps=fps)
    return Clip(Path(path).stem, np.asarray(c.xyz_m, np.float32), float(c.fps), "body19")


# The evaluation protocol's split (train / validation / test), by clip, never by window: clips are sorted
# by length (ties by a stable hash of the name and ``seed``) and dealt in this cycle (started ``seed``
# places in), so every split gets its share of the long clips (only clips of >= n_obs + n_pred frames give
# evaluation windows; a random split can leave the test set with few of them). 5/8 train, 1/8 validation
# (model selection: checkpoints are picked on it), 2/8 test (reported figures only). With the 64 CMU
# clips: 40 / 8 / 16 clips, of which 18 / 4 / 8 are long enough for 6 s windows (2 s observed, 4 s forecast).
SPLIT_CYCLE = ("train", "train", "train", "test", "train", "val", "train", "test")


def split_train_val_test(
    names: list[str], lengths: list[int], seed: int = 0
) -> tuple[list[int], list[int], list[int]]:
    """Deterministic stratified train/val/test split of clip indices (``SPLIT_CYCLE``) -> (train, val, test).

    Depends only on the clips' names and lengths, not on their order, so adding a clip moves few others."""
    import zlib

    if len(names) != len(lengths):
        raise InputError(f"{len(names)} names but {len(lengths)} lengths")
    if len(names) < 3:
        raise InputError(f"a train/val/test split needs at least 3 clips, got {len(names)}")
    key = [(int(n), zlib.crc32(f"{seed}:{nm}".encode()), nm) for nm, n in zip(names, lengths, strict=True)]
    order = sorted(range(len(names)), key=lambda i: key[i])
    out: dict[str, list[int]] = {"train": [], "val": [], "test": []}
    for r, i in enumerate(order):
        out[SPLIT_CYCLE[(r + seed) % len(SPLIT_CYCLE)]].append(i)
    for part in ("test", "val"):  # few clips: the longest training clips make sure no split is empty
        if not out[part]:
            out[part].append(max(out["train"], key=lambda i: key[i]))
            out["train"].remove(out[part][0])
    return sorted(out["train"]), sorted(out["val"]), sorted(out["test"])


# ----------------------------------------------------------------------------- Humans in Kitchens

KITCHEN_FPS = 25.0
_KITCHEN_KEYS = ("poses3d", "frames")


def load_kitchens_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """One Humans-in-Kitchens person segment (Tanke ch. 8) -> arrays, checked.

    Layout: ``poses3d (n,29,3)`` metres z up (smpl29 order), ``frames (n,)`` global frame numbers at
    25 Hz; optional ``act (n,82)``, ``transforms (n,6)``, ``smpl (n,21,3)``, ``betas (10,)``.
    """
    data = load_npz(path, required=_KITCHEN_KEYS)
    p, f = np.asarray(data["poses3d"], np.float32), np.asarray(data["frames"], np.int64)
    if p.ndim != 3 or p.shape[1:] != (29, 3):
        raise FormatError(path, "poses3d", f"expected (n,29,3) metres, got {p.shape}.")
    if f.shape != (len(p),):
        raise FormatError(path, "frames", f"expected ({len(p)},) frame numbers, got {f.shape}.")
    out = {"poses3d": p, "frames": f}
    for key, tail in (("act", (82,)), ("transforms", (6,)), ("smpl", (21, 3))):
        if key in data:
            if data[key].shape != (len(p), *tail):
                raise FormatError(path, key, f"expected {(len(p), *tail)}, got {data[key].shape}.")
            out[key] = data[key]
    if "betas" in data:
        out["betas"] = data["betas"]
    return out


def kitchens_scene(paths: list[str | os.PathLike], name: str = "kitchen") -> Clip:
    """Person segments of one kitchen recording -> one multi-person ``smpl29`` clip on the global frame axis.

    Frames a person is absent from are NaN (masked downstream).
    """
    segs = [load_kitchens_npz(p) for p in paths]
    if not segs:
        raise InputError("kitchens_scene needs at least one person npz")
    f0 = min(int(s["frames"].min()) for s in segs)
    f1 = max(int(s["frames"].max()) for s in segs)
    x = np.full((f1 - f0 + 1, len(segs), 29, 3), np.nan, np.float32)
    for k, s in enumerate(segs):
        x[s["frames"] - f0, k] = s["poses3d"]
    return Clip(name, x, KITCHEN_FPS, "smpl29")


def smpl29_to_body19(xyz: np.ndarray) -> np.ndarray:
    """Map the SMPL joints shared with body19 (hips, knees, ankles, shoulders, elbows, wrists, pelvis, neck);
    face joints (nose/eyes/ears) are NaN. (...,29,3) -> (...,19,3)."""
    src, dst = get_skeleton("smpl29").joint_names, get_skeleton("body19").joint_names
    out = np.full((*xyz.shape[:-2], len(dst), 3), np.nan, np.float32)
    for j, n in enumerate(dst):
        if n in src:
            out[..., j, :] = xyz[..., src.index(n), :]
    return out


# ----------------------------------------------------------------------------- windows


@dataclass(frozen=True)
class WindowSet:
    """Windows of ``n_obs + n_pred`` frames.

    ``x (N,T,P,J,3)`` world metres with missing values filled (last/next known value),
    ``mask (N,T,P,J)`` True where observed, ``person_mask (N,P)`` True where a person is present at
    the last observed frame, ``clip (N,)`` index into ``clip_names``, ``start (N,)`` first frame.
    """

    x: np.ndarray
    mask: np.ndarray
    person_mask: np.ndarray
    clip: np.ndarray
    start: np.ndarray
    n_obs: int
    n_pred: int
    fps: float
    skeleton: str
    clip_names: tuple[str, ...]
    skipped: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.x)


def make_windows(
    clips: list[Clip],
    n_obs: int,
    n_pred: int,
    stride: int,
    *,
    fps: float = TARGET_FPS,
    persons: str = "each",
    min_persons: int = 1,
    max_persons: int | None = None,
) -> WindowSet:
    """Cut clips into windows at ``fps``.

    persons: ``"each"`` -> one single-person window per present person (P=1); ``"all"`` -> the scene
    (P = the clip's person count, padded to ``max_persons``). A person counts as present when both
    hips are known at the last observed frame (the normalisation frame of eq. 3.8); windows without
    ``min_persons`` present people are skipped and counted.
    """
    if persons not in ("each", "all"):
        raise InputError(f"persons must be 'each' or 'all', got {persons!r}")
    skipped: Counter[str] = Counter()
    xs, ms, pms, cs, ss = [], [], [], [], []
    T = n_obs + n_pred
    sk = clips[0].skeleton if clips else "body19"
    lh, rh = hip_indices(get_skeleton(sk).joint_names)
    for ci, clip in enumerate(clips):
        if clip.skeleton != sk:
            raise InputError(f"clip '{clip.name}' is {clip.skeleton}, others are {sk}; convert first")
        c = clip.resampled(fps)
        if c.n_frames < T:
            skipped["clip_shorter_than_window"] += 1
            continue
        for x, m, pm, s in _clip_windows(
            c, n_obs, T, stride, (lh, rh), persons, min_persons, max_persons, skipped
        ):
            xs.append(x)
            ms.append(m)
            pms.append(pm)
            cs.append(ci)
            ss.append(s)
    if skipped:
        log.info("make_windows skipped %s", dict(skipped))
    J = get_skeleton(sk).n_joints
    P0 = 1 if persons == "each" else (max_persons or (clips[0].xyz_m.shape[1] if clips else 1))
    if not xs:
        return WindowSet(
            np.zeros((0, T, P0, J, 3), np.float32),
            np.zeros((0, T, P0, J), bool),
            np.zeros((0, P0), bool),
            np.zeros(0, int),
            np.zeros(0, int),
            n_obs,
            n_pred,
            fps,
            sk,
            tuple(c.name for c in clips),
            dict(skipped),
        )
    if persons == "all" and len({a.shape for a in xs}) > 1:
        raise InputError("clips have different person counts; pass max_persons")
    return WindowSet(
        np.stack(xs),
        np.stack(ms),
        np.stack(pms),
        np.asarray(cs),
        np.asarray(ss),
        n_obs,
        n_pred,
        fps,
        sk,
        tuple(c.name for c in clips),
        dict(skipped),
    )


def _clip_windows(
    c: Clip,
    n_obs: int,
    T: int,
    stride: int,
    hips: tuple[int, int],
    persons: str,
    min_persons: int,
    max_persons: int | None,
    skipped: Counter[str],
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
    """The windows of one clip (at the windows' rate) as (x (T,P,J,3) gaps filled, mask (T,P,J), person
    mask (P,), start frame): one per present person (``persons="each"``) or the scene (``"all"``); windows
    with too few people present are counted in ``skipped``."""
    lh, rh = hips
    mask_all = np.isfinite(c.xyz_m).all(-1)
    for s in range(0, c.n_frames - T + 1, stride):
        x, m = c.xyz_m[s : s + T], mask_all[s : s + T]
        present = m[n_obs - 1, :, lh] & m[n_obs - 1, :, rh]
        if present.sum() < min_persons:
            skipped["no_person_at_last_observed_frame"] += 1
            continue
        if persons == "each":
            for p in np.flatnonzero(present):
                yield fill(x[:, p : p + 1], m[:, p : p + 1]), m[:, p : p + 1], np.ones(1, bool), s
        else:
            P = max_persons or x.shape[1]
            keep = np.flatnonzero(present)[:P]
            xf = np.zeros((T, P, x.shape[2], 3), np.float32)
            mf = np.zeros((T, P, x.shape[2]), bool)
            xf[:, : len(keep)] = fill(x[:, keep], m[:, keep])
            mf[:, : len(keep)] = m[:, keep]
            pm = np.zeros(P, bool)
            pm[: len(keep)] = True
            yield xf, mf, pm, s


# ------------------------------------------------------------------------- activities (NDMS database groups)

UNLABELLED = "unlabelled"


def cmu_index(root: str | os.PathLike | None = None) -> dict[tuple[int, int], str]:
    """The CMU database listing (``index.csv`` with Subject, Trial #, Motion Description) found under the
    mocap root -> {(subject, trial): description}; {} when there is none."""
    import csv

    r = bvh.mocap_root(root)
    if r is None:
        return {}
    out: dict[tuple[int, int], str] = {}
    for f in sorted(Path(r).rglob("index.csv")):
        with open(f, newline="", encoding="utf-8", errors="replace") as fh:
            for row in csv.DictReader(fh):
                try:
                    out[(int(row["Subject"]), int(row["Trial #"]))] = row["Motion Description"].strip()
                except (KeyError, TypeError, ValueError):
                    continue
    return out


def activity_of_description(desc: str) -> str:
    """The activity of a CMU motion description: the part before ' - ' ("basketball - forward dribble" ->
    "basketball", "dance - ..." -> "dance"); any description that mentions walking is "walk" ("slow walk",
    "walk, shake hands", "Start Walk Stop"); otherwise the description, lower case. Remarks in parentheses
    ("(2 subjects - subject A)") are dropped first."""
    import re

    d = re.sub(r"\([^)]*\)", "", desc).strip().lower()
    if " - " in d:
        return d.split(" - ", 1)[0].strip()
    if "walk" in d:
        return "walk"
    return d or UNLABELLED


def cmu_subject_trial(name: str) -> tuple[int, int] | None:
    """(subject, trial) of a CMU clip name ('001_08', 'scaled_131_02', '18_01', '18_01+19_01': the first)
    or None."""
    parts = name.split("+")[0].split("_")
    try:
        return int(parts[-2]), int(parts[-1])
    except (IndexError, ValueError):
        return None


# ------------------------------------------------------------------------- CMU two-person take 18_01 + 19_01

TWO_PERSON_DIR = "cmu-two-person-18-19"


def cmu_two_person_clip(folder: str | os.PathLike | None = None, fps: float = TARGET_FPS) -> Clip:
    """CMU 18_01 + 19_01 ("walk, shake hands", 2.5 s), recorded together in one capture volume, as one
    two-person body19 clip at ``fps`` (P=2: person 0 is subject 18, person 1 subject 19).

    Each BVH goes through the same reader as every CMU clip (``synthetic.bvh``: ASF units -> metres, z up,
    the synthetic T-pose frame 0 dropped); both share the world frame and the clock, so they are stacked
    frame by frame. The cgspeed conversion lacks the ASF thorax bone (README of the folder): everything above
    Spine1 sits ~0.12 m low, which leaves within-person motion (NDMS) and the hips (SSCP's root and facing)
    intact but makes hand-to-hand distances wrong; nothing here uses them."""
    if folder is None:
        r = bvh.mocap_root(None)
        if r is None:
            raise FileNotFoundError(
                f"no mocap root for {TWO_PERSON_DIR}; set ROOMCAP_MOCAP or ROOMCAP_SHARED"
            )
        folder = Path(r) / TWO_PERSON_DIR
    folder = Path(folder)
    files = [folder / "18_01.bvh", folder / "19_01.bvh"]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise FileNotFoundError(f"two-person CMU take: missing {missing}; expected 18_01.bvh and 19_01.bvh")
    a, b = (clip_from_bvh(f, fps) for f in files)
    n = min(a.n_frames, b.n_frames)
    x = np.concatenate([a.xyz_m[:n], b.xyz_m[:n]], 1)
    return Clip("18_01+19_01", x, fps, "body19")


# ------------------------------------------------------------------------- Humans in Kitchens protocol (8.3)

# activity2index of the HiK API (hik/data/constants.py): the 82 columns of ``act``.
KITCHEN_ACTIVITIES = (
    "carry cake", "carry cup", "carry plate", "carry whiteboard eraser", "carry whiteboard marker",
    "check water in coffee machine", "clean countertop", "clean dish", "close cupboard", "close dishwasher",
    "close drawer", "close fridge", "close window", "cut cake in pieces", "draw on whiteboard", "drink",
    "eat cake", "eat fruit", "empty cup in sink", "empty dishwasher", "empty ground from coffee machine",
    "empty water from coffee machine", "erase on whiteboard", "fill coffee beens", "fill water tank",
    "fill water to coffee machine", "fussball", "kneeling", "kneeling down", "leaning", "leaning down",
    "listening", "make coffee", "mark coffee", "open cupboard", "open dishwasher", "open drawer",
    "open fridge",
    "open window", "peal fruit", "phone call", "place cake on plate", "place cake on table",
    "place cup onto coffee machine", "place in dishwasher", "place sheet onto whiteboard",
    "place water tank in coffee machine", "pour kettle", "pour milk", "press coffee button",
    "put cake in fridge", "put cup in microwave", "put sugar in cup", "put teabag in cup",
    "put water in glass",
    "put water in kettle", "read paper", "remove sheet from whiteboard", "sitting", "sitting down",
    "squatting", "standing", "standing up", "start dishwasher", "start microwave", "steps",
    "take cake out of fridge", "take cup from coffee machine", "take cup out of microwave",
    "take dish out of cupboard", "take kettle", "take milk", "take piece of cake", "take teabag",
    "take water from sink", "take water tank from coffee machine", "talking", "throw in trash", "use laptop",
    "use smartphone", "walking", "washing hands",
)  # fmt: skip


def _kitchen_columns(word: str, exact: bool) -> tuple[int, ...]:
    return tuple(
        i for i, a in enumerate(KITCHEN_ACTIVITIES) if (a == word if exact else word in a.split(" "))
    )


# Tanke ch. 8.3: two motion activities and four human-object interactions; the objects are every activity
# that names them. kind "motion": the last observed frame is 10 frames after the onset; "object": the onset.
HIK_ACTIVITIES: dict[str, tuple[str, tuple[int, ...]]] = {
    "walking": ("motion", _kitchen_columns("walking", True)),
    "sitting down": ("motion", _kitchen_columns("sitting down", True)),
    "whiteboard": ("object", _kitchen_columns("whiteboard", False)),
    "sink": ("object", _kitchen_columns("sink", False)),
    "cupboard": ("object", _kitchen_columns("cupboard", False)),
    "coffee": ("object", _kitchen_columns("coffee", False)),
}
HIK_TRAIN_KITCHENS, HIK_TEST_KITCHEN = ("A", "B", "C"), "D"


@dataclass(frozen=True)
class KitchenPerson:
    """One HiK person file ``{kitchen}_{pid}_{seqid}.npz``: poses on the global frame axis, activity flags."""

    name: str
    kitchen: str
    pid: int
    frames: np.ndarray  # (n,) global frame numbers at 25 Hz
    poses3d: np.ndarray  # (n,29,3) metres, z up
    act: np.ndarray  # (n,82) activity flags (> 0.5 = on)


def load_kitchen_people(folder: str | os.PathLike) -> list[KitchenPerson]:
    """Every ``{kitchen}_{pid}_{seqid}.npz`` under folder (the HiK API's ``data/poses``); each needs the
    activity flags ``act`` (FormatError naming the file otherwise)."""
    folder = Path(folder)
    files = sorted(folder.rglob("*.npz")) if folder.is_dir() else []
    out = []
    for f in files:
        parts = f.stem.split("_")
        if len(parts) != 3 or parts[0] not in "ABCD" or not parts[1].isdigit():
            continue
        d = load_kitchens_npz(f)
        if "act" not in d:
            raise FormatError(
                f,
                "act",
                "this HiK person file has no activity flags 'act' (n,82); the ch. 8.3 protocol picks its "
                "test windows by activity.",
                "Use the HiK release with activity annotations (hik/data/poses/*.npz).",
            )
        out.append(KitchenPerson(f.stem, parts[0], int(parts[1]), d["frames"], d["poses3d"], d["act"]))
    if not out:
        raise FileNotFoundError(
            f"no HiK person files '{{kitchen}}_{{pid}}_{{seqid}}.npz' under {folder} "
            "(the HiK API's data/poses)"
        )
    return out
