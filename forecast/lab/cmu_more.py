"""Readers for ``cmu-more`` (``$ROOMCAP_SHARED/data/motion/cmu-more``, see its README) into forecasting clips.

- **one-person cgspeed BVH** (``single/``, 30 fps): through :mod:`roomcap.synthetic.bvh`, which knows the
cgspeed
  "Daz-friendly" skeleton's scale (centimetres, one fixed skeleton for every subject) and always drops its
  T-pose frame 0 -> body19 :class:`roomcap.forecast.lab.data.Clip` (:func:`load_single`).
- **two-person salsa** (``two-person/salsa_NN/60_NN.bvh`` + ``61_NN.bvh``, one world frame, 30 fps, the same
  skeleton written at 1/128): one two-person clip per take, P = 2 (person 0 = subject 60, person 1 = subject
  61) (:func:`salsa_clip`). The two files must have the same frame count (they share the clock).
- **the CMU 8-action forecasting benchmark** (``benchmark-cmu8``, Li et al. 2018; 117 values a line at
  120 Hz: root position + 38 exponential maps on the CMU ASF skeleton): :func:`read_expmap`,
  :func:`expmap_to_xyz` (the forward kinematics of the reference code, LTD's ``utils/forward_kinematics.py``
  ``_some_variables_cmu`` + ``fkl_torch``) and :func:`benchmark_clip` (body19, metres, z up).
"""

from __future__ import annotations

import csv
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError, InputError
from roomcap.forecast.lab import data as fdata
from roomcap.synthetic import bvh

log = logging.getLogger(__name__)

CMU_MORE_DIR = "cmu-more"
BENCHMARK_DIR = "benchmark-cmu8"
# The salsa takes open with a blend out of the T-pose: after frame 0 (dropped by the BVH reader) the next
# three frames still move 14, 3 and 1.5 cm per frame (mean over joints, body frame) against 0.3-1.4 cm from
# the fourth on, in every take; they are left out too (0.1 s).
SALSA_BLEND_FRAMES = 3


def cmu_more_root(root: str | os.PathLike | None = None) -> Path:
    """The ``cmu-more`` folder: ``root`` itself, else under the mocap root (``synthetic.bvh.mocap_root``)."""
    if root is not None:
        p = Path(root)
    else:
        r = bvh.mocap_root(None)
        if r is None:
            raise FileNotFoundError(f"no mocap root for {CMU_MORE_DIR}; set ROOMCAP_MOCAP or ROOMCAP_SHARED")
        p = r / CMU_MORE_DIR
    if not p.is_dir():
        raise FileNotFoundError(f"no folder {p}; set ROOMCAP_MOCAP or ROOMCAP_SHARED")
    return p


# ----------------------------------------------------------------------------- one person, cgspeed BVH


def single_name(path: str | os.PathLike) -> str:
    """Clip name of a one-person file: '08_01' for ``single/08/08_01.bvh``, 'indian_04' for
    ``single/acrnn/indian/04.bvh`` (the redistributing repository gives no CMU trial numbers)."""
    p = Path(path)
    return f"{p.parent.name}_{p.stem}" if p.parent.parent.name == "acrnn" else p.stem


def single_files(root: str | os.PathLike | None = None) -> list[Path]:
    """The one-person BVH files of ``cmu-more/single``, sorted."""
    return sorted((cmu_more_root(root) / "single").rglob("*.bvh"))


def load_single(fps: float = fdata.TARGET_FPS, root: str | os.PathLike | None = None) -> list[fdata.Clip]:
    """Every one-person clip of ``cmu-more`` as body19 at ``fps`` (names: :func:`single_name`)."""
    out = []
    for f in single_files(root):
        c = bvh.load_clip(f, fps=fps)
        out.append(fdata.Clip(single_name(f), np.asarray(c.xyz_m, np.float32), float(c.fps), "body19"))
    return out


def activities(root: str | os.PathLike | None = None) -> dict[str, str]:
    """Clip name -> activity for the clips of ``cmu-more`` from its ``manifest.csv`` description
    (``data.activity_of_description``; the salsa pairs under their two-person name)."""
    out: dict[str, str] = {}
    with open(cmu_more_root(root) / "manifest.csv", newline="", encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            p = row.get("path", "")
            if not p.endswith(".bvh"):
                continue
            act = fdata.activity_of_description(row.get("description", ""))
            if p.startswith("two-person/"):
                nn = Path(p).stem.split("_")[-1]
                out[f"60_{nn}+61_{nn}"] = act
            else:
                out[single_name(p)] = act
    return out


# ----------------------------------------------------------------------------- two persons, salsa


def salsa_folders(root: str | os.PathLike | None = None) -> list[Path]:
    """The salsa take folders (``two-person/salsa_NN``), sorted."""
    return sorted(p for p in (cmu_more_root(root) / "two-person").glob("salsa_*") if p.is_dir())


def salsa_clip(folder: str | os.PathLike, fps: float | None = fdata.TARGET_FPS) -> fdata.Clip:
    """One salsa take ``salsa_NN`` (``60_NN.bvh`` + ``61_NN.bvh``) as one two-person body19 clip at ``fps``
    (None: the files' 30 fps), named ``60_NN+61_NN``.

    Both files are read at their native rate with the same reader (scale known, T-pose dropped), stacked
    frame by frame (they share the world frame and the clock), then the blend frames after the T-pose
    (``SALSA_BLEND_FRAMES``) are dropped and the pair is resampled. Raises ``InputError`` when a file is
    missing or the two frame counts differ (a pair out of step cannot be stacked)."""
    folder = Path(folder)
    nn = folder.name.split("_")[-1]
    files = [folder / f"60_{nn}.bvh", folder / f"61_{nn}.bvh"]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise InputError(f"salsa take {folder}: missing {missing}; a take needs 60_{nn}.bvh and 61_{nn}.bvh")
    a, b = (bvh.load_clip(f) for f in files)
    if a.n_frames != b.n_frames or abs(a.fps - b.fps) > 1e-6:
        raise InputError(
            f"salsa take {folder}: {files[0].name} has {a.n_frames} frames at {a.fps:.3f} fps but "
            f"{files[1].name} has {b.n_frames} at {b.fps:.3f} fps; the two people of a take share one "
            "clock, so the files must have the same frame count and rate. Use the pair as released "
            "(cmu-more README)."
        )
    x = np.stack([a.xyz_m, b.xyz_m], 1)[SALSA_BLEND_FRAMES:].astype(np.float32)
    clip = fdata.Clip(f"60_{nn}+61_{nn}", x, float(a.fps), "body19")
    return clip if fps is None else clip.resampled(fps)


def load_salsa(fps: float = fdata.TARGET_FPS, root: str | os.PathLike | None = None) -> list[fdata.Clip]:
    """All 14 salsa takes as two-person clips at ``fps``."""
    return [salsa_clip(f, fps) for f in salsa_folders(root)]


# ----------------------------------------------------------------------------- the CMU 8-action benchmark

BENCHMARK_FPS = 120.0  # the files' rate (README; a walk's stride is ~118 frames, its speed 1.2 m/s at 120 Hz)
ASF_UNIT_M = 0.0254 / 0.45  # CMU's ASF length unit (``units: length 0.45``: 1/0.45 inch)
# The benchmark's CMU ASF skeleton as the reference code defines it (LTD, utils/forward_kinematics.py,
# _some_variables_cmu): parents (-1 = root) and offsets from the parent in ASF units, y up; the reference
# multiplies the offsets by 70 and calls the result millimetres (``REFERENCE_MM_PER_UNIT``).
CMU38_PARENTS = np.array(
    [-1, 0, 1, 2, 3, 4, 5, 0, 7, 8, 9, 10, 11, 0, 13, 14, 15, 16, 17, 18, 15, 20, 21, 22, 23, 24, 25, 23, 27,
     15, 29, 30, 31, 32, 33, 34, 32, 36]
)  # fmt: skip
CMU38_OFFSETS = np.array(
    [0, 0, 0, 0, 0, 0, 1.65674, -1.80282, 0.62477, 2.5972, -7.13576, 0, 2.49236, -6.8477, 0, 0.19704,
     -0.54136, 2.14581, 0, 0, 1.11249, 0, 0, 0, -1.6107, -1.80282, 0.62476, -2.59502, -7.12977, 0, -2.4678,
     -6.78024, 0, -0.23024, -0.63258, 2.13368, 0, 0, 1.11569, 0, 0, 0, 0.01961, 2.0545, -0.14112, 0.01021,
     2.06436, -0.05921, 0, 0, 0, 0.00713, 1.56711, 0.14968, 0.03429, 1.56041, -0.10006, 0.01305, 1.6256,
     -0.05265, 0, 0, 0, 3.54205, 0.90436, -0.17364, 4.86513, 0, 0, 3.35554, 0, 0, 0, 0, 0, 0.66117, 0, 0,
     0.53306, 0, 0, 0, 0, 0, 0.5412, 0, 0.5412, 0, 0, 0, -3.49802, 0.75994, -0.32616, -5.02649, 0, 0,
     -3.36431, 0, 0, 0, 0, 0, -0.73041, 0, 0, -0.58887, 0, 0, 0, 0, 0, -0.59786, 0, 0.59786]
).reshape(38, 3)  # fmt: skip
REFERENCE_MM_PER_UNIT = 70.0
# Each point is the END of the ASF bone named (the point where the next bone starts); 'root' and the
# zero-length bones sit on their parent.
CMU38_NAMES = (
    "root", "lhipjoint_root", "lhip", "lknee", "lankle", "ltoes", "ltoes_end",
    "rhipjoint_root", "rhip", "rknee", "rankle", "rtoes", "rtoes_end",
    "lowerback_root", "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head_top",
    "lclavicle_root", "lshoulder", "lelbow", "lwrist", "lhand", "lfingers", "lfingers_end", "lthumb",
    "lthumb_end",
    "rclavicle_root", "rshoulder", "relbow", "rwrist", "rhand", "rfingers", "rfingers_end", "rthumb",
    "rthumb_end",
)  # fmt: skip
# body19 joint -> benchmark point (pelvis = mid hips and neck = mid shoulders as everywhere in roomcap; the
# face points are approximated from the head like synthetic.bvh.FACE_OFFSETS_M).
BODY19_FROM_CMU38 = {
    "left_hip": 2, "right_hip": 8, "left_knee": 3, "right_knee": 9, "left_ankle": 4, "right_ankle": 10,
    "left_shoulder": 21, "right_shoulder": 30, "left_elbow": 22, "right_elbow": 31, "left_wrist": 23,
    "right_wrist": 32,
}  # fmt: skip
CMU38_HEAD = 18  # the head bone's start (top of the upper neck), the point the face offsets hang from
BENCHMARK_ACTIONS = (
    "basketball", "basketball_signal", "directing_traffic", "jumping", "running", "soccer", "walking",
    "washwindow",
)  # fmt: skip  # define_actions_cmu of the reference code (walking_extra is not one of them)
BENCHMARK_TRAIN_PER_ACTION = 5  # <action>_1..5.txt in train/, <action>_1.txt in test/ (the released set)


def read_expmap(path: str | os.PathLike) -> np.ndarray:
    """A benchmark file -> ``(F, 117)`` float64 (root position, then 38 exponential maps).

    Raises ``FormatError``."""
    path = Path(path)
    try:
        a = np.loadtxt(path, delimiter=",", ndmin=2)
    except (OSError, ValueError) as e:
        raise FormatError(path, None, f"cannot read comma-separated numbers: {e}", "Check the file.") from e
    if a.shape[1] != 117 or len(a) == 0:
        raise FormatError(
            path,
            None,
            f"{a.shape[1]} values a line ({len(a)} lines), expected 117.",
            "Is this a benchmark file?",
        )
    if not np.isfinite(a).all():
        raise FormatError(path, None, "non-finite values.", "Check the file.")
    return a


def expmap_rotmat(r: np.ndarray) -> np.ndarray:
    """Rodrigues: exponential maps ``(...,3)`` -> rotation matrices ``(...,3,3)`` (the reference's
    ``expmap2rotmat_torch``, with its 1e-7 in the axis normalisation)."""
    th = np.linalg.norm(r, axis=-1, keepdims=True)
    k = r / (th + 1e-7)
    K = np.zeros(r.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    th = th[..., None]
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


def expmap_to_xyz(expmap: np.ndarray) -> np.ndarray:
    """``(F,117)`` -> ``(F,38,3)`` points in ASF units, y up, as the reference computes them (LTD
    ``fkl_torch`` with ``_some_variables_cmu``): row vectors, ``p_i = o_i R_parent + p_parent`` and
    ``R_i = R_i,local R_parent``, composed only below the root's children, so the root's position and rotation
    never enter (the body frame of the benchmark: no global translation or facing)."""
    F = len(expmap)
    R = expmap_rotmat(np.asarray(expmap, np.float64)[:, 3:].reshape(F, 38, 3))
    p = np.broadcast_to(CMU38_OFFSETS, (F, 38, 3)).copy()
    for i in range(1, 38):
        q = int(CMU38_PARENTS[i])
        if q > 0:
            R[:, i] = R[:, i] @ R[:, q]
            p[:, i] = np.einsum("j,fjk->fk", CMU38_OFFSETS[i], R[:, q]) + p[:, q]
    return p


_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # (x, y, z) -> (x, -z, y)


def cmu38_to_body19(xyz_units: np.ndarray) -> np.ndarray:
    """Benchmark points ``(...,38,3)`` ASF units y up -> body19 ``(...,19,3)`` metres z up (body frame, the
    lower ankle per window not moved to the floor: the forecasting models normalise by the hips)."""
    x = (xyz_units * ASF_UNIT_M) @ _Y_UP_TO_Z_UP.T
    J = {n: i for i, n in enumerate(bvh.BODY19)}
    out = np.zeros(x.shape[:-2] + (len(bvh.BODY19), 3))
    for n, k in BODY19_FROM_CMU38.items():
        out[..., J[n], :] = x[..., k, :]
    out[..., J["pelvis"], :] = 0.5 * (out[..., J["left_hip"], :] + out[..., J["right_hip"], :])
    out[..., J["neck"], :] = 0.5 * (out[..., J["left_shoulder"], :] + out[..., J["right_shoulder"], :])
    # face: offsets (forward, left, up) from the head in the frame of the torso's left and the neck->head up
    left = x[..., 21, :] - x[..., 30, :] + x[..., 2, :] - x[..., 8, :]
    left /= np.maximum(np.linalg.norm(left, axis=-1, keepdims=True), 1e-9)
    up = x[..., 19, :] - x[..., 18, :]
    up = up - left * np.sum(up * left, -1, keepdims=True)
    up /= np.maximum(np.linalg.norm(up, axis=-1, keepdims=True), 1e-9)
    fwd = np.cross(left, up)
    for n, (f, lft, u) in bvh.FACE_OFFSETS_M.items():
        out[..., J[n], :] = x[..., CMU38_HEAD, :] + f * fwd + lft * left + u * up
    return out


def benchmark_clip(path: str | os.PathLike, fps: float | None = None) -> fdata.Clip:
    """A benchmark file as a body19 clip (metres, z up, the benchmark's body frame) at ``fps`` (None: 120)."""
    xyz = cmu38_to_body19(expmap_to_xyz(read_expmap(path)))
    c = fdata.Clip(Path(path).stem, xyz.astype(np.float32), BENCHMARK_FPS, "body19")
    return c if fps is None else c.resampled(fps)


@dataclass
class BenchmarkFiles:
    """The benchmark files found, ``files[split][action]`` sorted by number, and the expected ones missing."""

    root: Path
    files: dict[str, dict[str, list[Path]]] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)

    def missing_text(self) -> str:
        return ", ".join(self.missing) if self.missing else "none"


def _file_number(p: Path) -> int:
    try:
        return int(p.stem.rsplit("_", 1)[1])
    except (IndexError, ValueError):
        return 10**9


def benchmark_files(root: str | os.PathLike | None = None) -> BenchmarkFiles:
    """Find the benchmark's files under ``root`` (a ``benchmark-cmu8`` folder; default the shared one) and
    name the missing ones against the released set (``BENCHMARK_TRAIN_PER_ACTION`` train files and one test
    file per action of ``BENCHMARK_ACTIONS``). Raises ``InputError`` when there is no train/test folder."""
    r = Path(root) if root is not None else cmu_more_root() / BENCHMARK_DIR
    if not (r / "train").is_dir() and not (r / "test").is_dir():
        raise InputError(
            f"{r}: no train/ or test/ folder of the CMU 8-action benchmark; give the benchmark-cmu8 folder "
            "(ROOMCAP_SHARED/data/motion/cmu-more/benchmark-cmu8)"
        )
    out = BenchmarkFiles(r)
    for split, n_expected in (("train", BENCHMARK_TRAIN_PER_ACTION), ("test", 1)):
        out.files[split] = {}
        for a in BENCHMARK_ACTIONS:
            d = r / split / a
            fs = sorted(d.glob(f"{a}_*.txt"), key=_file_number) if d.is_dir() else []
            fs = [f for f in fs if _file_number(f) < 10**9]
            out.files[split][a] = fs
            have = {_file_number(f) for f in fs}
            out.missing += [f"{split}/{a}/{a}_{k}.txt" for k in range(1, n_expected + 1) if k not in have]
    return out
