"""The CMU 8-action forecasting benchmark (Li et al. 2018) scored as its reference code scores it, and a
compact DCT + MLP forecaster trained on its train files.

Protocol (read from LTD, Mao et al. 2019: ``utils/data_utils.py`` ``load_data_cmu_3d`` and ``main_cmu_3d.py``
``test``; the data of Tanke Table 6.7, which reports mean angle errors on it):

- every file goes through the reference's forward kinematics
(:func:`roomcap.forecast.lab.cmu_more.expmap_to_xyz`: the
  root's position and rotation never enter) and keeps every 2nd frame (``even_list = range(0, n, 2)``);
- test windows: per test file, ``np.random.RandomState(1234567890)`` (re-seeded for each file) draws 8 starts
  ``idx = rng.randint(0, num_frames - 75)``; the window is frames ``idx .. idx + 74``: 50 observed
  (``source_seq_len``; LTD feeds the last 10), the 25 after them forecast (``target_seq_len``);
- scored: forecast frames 1, 3, 7, 9, 13, 24 (0-based), reported as 80, 160, 320, 400, 560, 1000 ms; MPJPE =
  mean over all 38 points of the Euclidean error, where the 25 used points are the model's, the 7 points that
  coincide with another take that one's forecast and the 6 fixed points are copied from the truth (they do
  not move in the body frame); units: the reference's offsets x 70, which it calls millimetres; mean over
  the 8 windows of an action, then over the actions;
- the files are 120 Hz (a walk's stride is ~118 frames), so after the 2x downsampling a frame is 1/60 s and
  the labels 80 ... 1000 ms are 33 ... 417 ms of real time; the labels are the protocol's and are kept.

Variant ``body19`` (named so everywhere): the project's body19 checkpoints forecast at 25 Hz from 2 s of
history; they get the 2 s before each test window's last observed frame from the same file (body19 of the
benchmark points, :func:`forecast.lab.cmu_more.cmu38_to_body19`), their forecast is interpolated to the
protocol's frame times, and the 12 limb points (hips, knees, ankles, shoulders, elbows, wrists) are scored in
the protocol's units, with zero velocity and the DCT + MLP scored on the same 12 points beside them.

Protocol ``cmu8-all`` (``evaluate(windows="all")``): every window of the test files, as MSR-GCN (Dang et al.
2021, ``datas/cmu/motiondataset.py`` split 2: ``load_data_cmu_3d`` with ``is_test=False`` on the test folder)
and PGBIG (Ma et al. 2022, ``utils/data_utils.py`` ``load_data_cmu_3d_n`` with ``test_sample_num=-1``) score
it: windows of 10 observed + 25 forecast frames at every start (stride 1) of each downsampled test file, the
same 38 points, horizons and per-action then over-actions means (PGBIG ``main_cmu_3d.py`` ``run_model`` /
``eval``). Where a window has fewer than the model's 50 frames of history in its file, the history is padded
with the file's first frame (``n_padded`` counts those windows); the 38-point models only.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from roomcap.core.errors import InputError
from roomcap.forecast.lab import benchmark_cmu8_published as P
from roomcap.forecast.lab import cmu_more as C
from roomcap.forecast.lab.protocol import Table, cells, results
from roomcap.forecast.runtime import samples as fsamples
from roomcap.forecast.runtime.checkpoint import family_of, load_checkpoint, read_checkpoint, write_checkpoint
from roomcap.forecast.runtime.predict import forecast_world
from roomcap.synthetic.bvh import BODY19

log = logging.getLogger(__name__)

PROTOCOL = "cmu8"
TITLE = "CMU 8-action benchmark (protocol {})"
REFERENCE = (
    "LTD (Mao et al. 2019), github.com/wei-mao-2019/LearnTrajDep: utils/data_utils.py load_data_cmu_3d "
    "(windows), utils/forward_kinematics.py _some_variables_cmu + fkl_torch (skeleton), main_cmu_3d.py test "
    "(joints, horizons, averaging)"
)
HORIZONS_MS = (80, 160, 320, 400, 560, 1000)
HORIZON_FRAMES = (1, 3, 7, 9, 13, 24)  # main_cmu_3d.py test(): eval_frame for output_n = 25
DOWNSAMPLE = 2
N_OBS, N_PRED = 50, 25  # source_seq_len, target_seq_len
N_WINDOWS = 8
ALL_OBS = 10  # cmu8-all: MSR-GCN's and PGBIG's input_n; windows of ALL_OBS + N_PRED frames at every start
WINDOWS = {"protocol": "cmu8", "all": "cmu8-all"}  # evaluate(windows=...) -> the protocol's name
SEED = 1234567890
FPS = C.BENCHMARK_FPS / DOWNSAMPLE  # the frames' real rate (60 Hz); the protocol labels them as 25 Hz
MM_PER_UNIT = C.REFERENCE_MM_PER_UNIT
JOINTS_EQUAL = {16: 15, 20: 15, 29: 15, 24: 23, 27: 23, 33: 32, 36: 32}  # point -> the point it sits on
JOINTS_FIXED = (0, 1, 2, 7, 8, 13)
JOINTS_USED = tuple(j for j in range(38) if j not in JOINTS_EQUAL and j not in JOINTS_FIXED)  # 25 points
# each of the 38 points' left/right partner: legs 1-6 <-> 7-12, arms 20-28 <-> 29-37; the spine its own
MIRROR_PARTNER = tuple(
    j + 6 if 1 <= j <= 6 else j - 6 if 7 <= j <= 12 else j + 9 if 20 <= j <= 28 else j - 9 if j >= 29 else j
    for j in range(38)
)
BODY19_LIMBS = (
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)  # fmt: skip
BODY19_LIMB_POINTS = tuple(C.BODY19_FROM_CMU38[n] for n in BODY19_LIMBS)
FAMILY = "cmu8_dct_mlp"  # the registry's family of these checkpoints
MISSING_NOTE = (
    "test/basketball_signal and test/directing_traffic are missing from the shared copy (files over 4 MiB "
    "could not be brought), so 6 of the 8 actions are scored and the average is over those 6; also missing: "
    "train/directing_traffic_2,3,5 and train/washwindow_1..5"
)


# ----------------------------------------------------------------------------- data and windows


def sequence(path: str | os.PathLike) -> np.ndarray:
    """A benchmark file -> ``(F, 38, 3)`` points (ASF units, body frame), every 2nd frame as the reference."""
    return C.expmap_to_xyz(C.read_expmap(path))[::DOWNSAMPLE]


def window_starts(n_frames: int, n: int = N_WINDOWS, seed: int = SEED) -> np.ndarray:
    """The reference's test window starts for a file of ``n_frames`` (downsampled) frames: a fresh
    ``RandomState(seed)``, ``n`` draws of ``randint(0, n_frames - 75)``."""
    if n_frames - (N_OBS + N_PRED) <= 0:
        raise InputError(
            f"a test file needs more than {N_OBS + N_PRED} frames after downsampling, has {n_frames}"
        )
    rng = np.random.RandomState(seed)
    return np.array([rng.randint(0, n_frames - (N_OBS + N_PRED)) for _ in range(n)], np.int64)


@dataclass
class TestSet:
    """Test windows per action: ``windows[action] (W, 75, 38, 3)`` units, ``starts[action]`` (file, start) and
    the files, plus what was missing."""

    windows: dict[str, np.ndarray] = field(default_factory=dict)
    starts: dict[str, list[tuple[int, int]]] = field(default_factory=dict)
    files: dict[str, list[Path]] = field(default_factory=dict)
    missing: list[str] = field(default_factory=list)
    actions_missing: list[str] = field(default_factory=list)
    full_history: dict[str, np.ndarray] = field(default_factory=dict)  # cmu8-all: (W,) history not padded


def all_windows(seq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """cmu8-all: every ``ALL_OBS + N_PRED``-frame window of a downsampled file (start = its first observed
    frame of the reference's 10) -> (starts, windows (W, 75, ...) with the model's ``N_OBS`` frames of
    history, (W,) True where that history lies in the file; elsewhere it is padded with its first frame)."""
    n = len(seq) - (ALL_OBS + N_PRED) + 1
    if n <= 0:
        raise InputError(
            f"a test file needs at least {ALL_OBS + N_PRED} frames after downsampling, has {len(seq)}"
        )
    pad = N_OBS - ALL_OBS
    padded = np.concatenate([np.repeat(seq[:1], pad, 0), seq])
    starts = np.arange(n)
    return starts, np.stack([padded[s : s + N_OBS + N_PRED] for s in starts]), starts >= pad


def test_set(
    bf: C.BenchmarkFiles,
    n_windows: int = N_WINDOWS,
    actions: list[str] | None = None,
    windows: str = "protocol",
) -> TestSet:
    """The test windows of every action with a test file (the others are listed as missing): the protocol's
    8 per file, or with ``windows="all"`` every window (:func:`all_windows`)."""
    if windows not in WINDOWS:
        raise InputError(f"unknown windows '{windows}'; choose one of {', '.join(WINDOWS)}")
    ts = TestSet(missing=list(bf.missing))
    for a in actions or C.BENCHMARK_ACTIONS:
        files = bf.files["test"].get(a, [])
        if not files:
            ts.actions_missing.append(a)
            continue
        ws, st = [], []
        for fi, f in enumerate(files):
            seq = sequence(f)
            if windows == "all":
                starts, w, full = all_windows(seq)
                ws += list(w)
                st += [(fi, int(s)) for s in starts]
                ts.full_history[a] = np.concatenate([ts.full_history.get(a, np.zeros(0, bool)), full])
                continue
            for s in window_starts(len(seq), n_windows):
                ws.append(seq[s : s + N_OBS + N_PRED])
                st.append((fi, int(s)))
        ts.windows[a], ts.starts[a], ts.files[a] = np.stack(ws), st, files
    if not ts.windows:
        raise InputError(
            f"no test file of any action under {bf.root}/test; missing: {bf.missing_text()}. Give the "
            "benchmark-cmu8 folder (ROOMCAP_SHARED/data/motion/cmu-more/benchmark-cmu8)."
        )
    return ts


def train_windows(files: list[Path], stride: int = 1) -> np.ndarray:
    """Every 75-frame window (stride ``stride``) of the downsampled train files -> (N, 75, 38, 3) units, as
    the reference's training windows (all starts)."""
    out = []
    for f in files:
        seq = sequence(f)
        L = N_OBS + N_PRED
        for s in range(0, len(seq) - L + 1, stride):
            out.append(seq[s : s + L])
    if not out:
        raise InputError(f"no train window of {N_OBS + N_PRED} frames in {len(files)} files")
    return np.stack(out).astype(np.float32)


# ----------------------------------------------------------------------------- scoring


def complete(pred_used: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Forecasts of the 25 used points ``(..., T, 25, 3)`` -> all 38 as the reference fills them: the fixed
    points from the truth ``gt (..., T, 38, 3)``, the coinciding ones from their partner's forecast."""
    full = np.broadcast_to(gt, pred_used.shape[:-2] + gt.shape[-2:]).copy()
    full[..., list(JOINTS_USED), :] = pred_used
    for j, k in JOINTS_EQUAL.items():
        full[..., j, :] = full[..., k, :]
    return full


def mpjpe_mm(pred: np.ndarray, gt: np.ndarray, points: tuple[int, ...] | None = None) -> np.ndarray:
    """Per window and frame: mean over ``points`` (default all) of the Euclidean error, in the protocol's mm.
    ``pred (W,S,T,J,3)`` or ``(W,T,J,3)``, ``gt (W,T,J,3)`` units; samples are averaged."""
    if pred.ndim == gt.ndim + 1:
        gt = gt[:, None]
    e = np.linalg.norm(pred - gt, axis=-1)
    if points is not None:
        e = e[..., list(points)]
    e = e.mean(-1) * MM_PER_UNIT
    return e.mean(1) if e.ndim == 3 else e


def at_horizons(per_frame: np.ndarray) -> list[float]:
    """(W, 25) per-frame errors -> the mean over windows at the protocol's horizon frames."""
    return [float(per_frame[:, k].mean()) for k in HORIZON_FRAMES]


# ----------------------------------------------------------------------------- the DCT + MLP forecaster


def dct_matrix(n: int) -> np.ndarray:
    """Orthonormal DCT-II (rows = frequencies), as ``get_dct_matrix`` of the reference code."""
    k, i = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    m = np.sqrt(2.0 / n) * np.cos(np.pi * (i + 0.5) * k / n)
    m[0] /= np.sqrt(2.0)
    return m


@dataclass
class MlpConfig:
    n_obs: int = N_OBS
    n_pred: int = N_PRED  # frames of one pass; fewer than the protocol's 25 are rolled out (:func:`rollout`)
    n_blocks: int = 12
    lr: float = 5e-4
    steps: int = 10000
    batch: int = 64
    weight_decay: float = 1e-4
    val_every: int = 500
    seed: int = 0
    mirror: bool = False  # augment: each training window left/right mirrored with probability 1/2
    reverse: bool = False  # augment: each training window played backwards with probability 1/2 (siMLPe)
    pad_start: float = 0.0  # augment: share of windows whose oldest history is padded as cmu8-all pads it
    width: int = 0  # channels between the spatial layers; 0: the input's values (3 per point), as siMLPe
    frame_loss: bool = False  # the error of a frame is the norm over all its values (LTD's angle loss)
    spatial_mix: bool = False  # each block mixes the points too (MLP-Mixer), not only the input/output layers
    pad_last: bool = False  # the observation padded with its last frame to n_obs + n_pred (LTD's, PGBIG's)


class _Block(nn.Module):
    """A temporal linear layer over the DCT coefficients with LayerNorm and a residual (siMLPe); ``spatial``:
    then a linear layer over the channels, with its own LayerNorm and residual (MLP-Mixer's token/channel
    pair, Tolstikhin et al. 2021)."""

    def __init__(self, T: int, D: int, spatial: bool = False):
        super().__init__()
        self.fc = nn.Linear(T, T)
        self.norm = nn.LayerNorm(D)
        self.fc_s = nn.Linear(D, D) if spatial else None
        self.norm_s = nn.LayerNorm(D) if spatial else None
        for fc in (self.fc, self.fc_s):
            if fc is not None:
                nn.init.xavier_uniform_(fc.weight, gain=1e-4)
                nn.init.zeros_(fc.bias)

    def forward(self, h: torch.Tensor) -> torch.Tensor:  # (B, D, T)
        h = h + self.norm(self.fc(h).transpose(1, 2)).transpose(1, 2)
        if self.fc_s is None or self.norm_s is None:
            return h
        return h + self.norm_s(self.fc_s(h.transpose(1, 2))).transpose(1, 2)


class DctMlp(nn.Module):
    """siMLPe-style forecaster (Guo et al. 2023): the observed points relative to the last observed frame,
    a DCT over time, a spatial linear layer, ``n_blocks`` temporal linear layers with LayerNorm and residuals,
    a spatial linear layer, the inverse DCT; the first ``n_pred`` frames, added to the last observed pose.
    ``pad_last``: the observation is first padded with its last frame to ``n_obs + n_pred`` frames, as LTD and
    PGBIG pad theirs (Mao et al. 2019), and the last ``n_pred`` frames are the forecast."""

    kind = "dct_mlp"

    def __init__(self, n_points: int, config: MlpConfig):
        super().__init__()
        self.n_obs, self.n_pred, self.pad_last = config.n_obs, config.n_pred, config.pad_last
        D, T = 3 * n_points, self.n_obs + (self.n_pred if self.pad_last else 0)
        H = config.width or D
        if self.n_pred > T:
            raise InputError(
                f"n_pred {self.n_pred} > n_obs {T}: the inverse DCT gives n_obs frames (unless --pad-last)"
            )
        d = torch.from_numpy(dct_matrix(T).astype(np.float32))
        self.register_buffer("dct", d)
        self.register_buffer("idct", d.T.contiguous())
        self.fc_in = nn.Linear(D, H)
        self.blocks = nn.Sequential(*[_Block(T, H, config.spatial_mix) for _ in range(config.n_blocks)])
        self.fc_out = nn.Linear(H, D)
        nn.init.xavier_uniform_(self.fc_out.weight, gain=1e-8)
        nn.init.zeros_(self.fc_out.bias)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """obs (B, n_obs, P, 3) -> (B, n_pred, P, 3)."""
        B, T, P, _ = obs.shape
        last = obs[:, -1:]
        x = (obs - last).reshape(B, T, P * 3)
        if self.pad_last:  # the last frame held: zero relative to it
            x = torch.cat([x, x.new_zeros(B, self.n_pred, P * 3)], 1)
        h = self.fc_in(torch.einsum("st,btd->bsd", self.dct, x))
        h = self.blocks(h.transpose(1, 2)).transpose(1, 2)
        y = torch.einsum("ts,bsd->btd", self.idct, self.fc_out(h))
        y = y[:, -self.n_pred :] if self.pad_last else y[:, : self.n_pred]
        return y.reshape(B, self.n_pred, P, 3) + last


def reverse_windows(b: torch.Tensor, flip: torch.Tensor) -> torch.Tensor:
    """Windows ``b (B, T, ...)``: those with ``flip (B,)`` played backwards (the whole window, observed and
    future, so the model observes the last frames and forecasts the first ones); per-frame labels ``(B, T)``
    alike."""
    return torch.where(flip.view(-1, *[1] * (b.dim() - 1)), b.flip(1), b)


def mirror_windows(b: torch.Tensor, flip: torch.Tensor, idx: torch.Tensor, signs) -> torch.Tensor:
    """Windows ``b (B, T, V, 3)``: those with ``flip (B,)`` mirrored left/right: each 3-vector takes its
    partner's (``idx``, from ``MIRROR_PARTNER``) times ``signs`` (a point's (-x, y, z); an exponential map's
    (x, -y, -z))."""
    m = b[:, :, idx] * torch.tensor(signs, dtype=b.dtype)
    return torch.where(flip.view(-1, 1, 1, 1), m, b)


def window_loss(pred: torch.Tensor, fut: torch.Tensor, per_frame: bool = False) -> torch.Tensor:
    """Mean point error plus the mean error of the frame-to-frame changes (siMLPe's two terms); a 'point' is
    the last axis (3D points, or the exponential maps of :mod:`roomcap.forecast.lab.benchmark_cmu8_angle`).
    ``per_frame``: the norm is taken over all values of a frame instead, as LTD's angle loss, ``sen_loss``."""
    if per_frame:
        pred, fut = pred.flatten(2), fut.flatten(2)
    pos = torch.linalg.norm(pred - fut, dim=-1).mean()
    vel = torch.linalg.norm(torch.diff(pred, dim=1) - torch.diff(fut, dim=1), dim=-1).mean()
    return pos + vel


def fit_mlp(
    model: DctMlp, x: torch.Tensor, config: MlpConfig, validate, score: str, augment=None, progress=None
):
    """Train ``model`` on windows ``x (N, T, P, 3)`` as siMLPe does (AdamW, a cosine schedule,
    :func:`window_loss`); ``augment(batch, rng)`` changes a batch (the random draws after the batch's own);
    every ``config.val_every`` steps ``validate(model)`` scores it, and the state with the lowest score is
    loaded at the end. Returns the history: ``best`` {``score``, step}, ``curve``, ``train_s``,
    ``steps_per_s``, ``samples_per_s``, ``n_params``."""
    rng = np.random.default_rng(config.seed)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, config.steps, eta_min=config.lr * 0.05)
    best = {score: float("inf"), "step": 0}
    best_state = {k: v.clone() for k, v in model.state_dict().items()}
    curve, losses = [], []
    t0 = time.perf_counter()
    for step in range(1, config.steps + 1):
        model.train()
        b = x[torch.from_numpy(rng.integers(0, len(x), config.batch))]
        if augment is not None:
            b = augment(b, rng)
        fut = b[:, config.n_obs : config.n_obs + config.n_pred]
        loss = window_loss(model(b[:, : config.n_obs]), fut, config.frame_loss)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if step % config.val_every == 0 or step == config.steps:
            v = validate(model)
            curve.append({"step": step, score: v, "loss": float(np.mean(losses[-config.val_every :]))})
            log.info("step %d loss %.4f %s %.4f", step, curve[-1]["loss"], score, v)
            if v < best[score]:
                best = {score: v, "step": step}
                best_state = {k: t.clone() for k, t in model.state_dict().items()}
        if progress is not None:
            progress(step, config.steps)
    wall = time.perf_counter() - t0
    model.load_state_dict(best_state)
    return {
        "best": best,
        "curve": curve,
        "train_s": wall,
        "steps_per_s": config.steps / wall,
        "samples_per_s": config.steps * config.batch / wall,
        "n_params": sum(p.numel() for p in model.parameters()),
    }


def rollout(model: DctMlp | DctMlpEnsemble, obs: torch.Tensor, n: int) -> torch.Tensor:
    """``n`` frames from a model that forecasts ``model.n_pred`` a pass: each pass's frames appended to the
    observation and the newest ``n_obs`` frames forecast again, as siMLPe forecasts its long-term horizons
    with its 10-frame model (Guo et al. 2023, sec. 4.1). obs (B, n_obs, P, 3) -> (B, n, P, 3)."""
    out: list[torch.Tensor] = []
    while sum(y.shape[1] for y in out) < n:
        out.append(model(obs))
        obs = torch.cat([obs, out[-1]], 1)[:, -model.n_obs :]
    return torch.cat(out, 1)[:, :n]


@torch.no_grad()
def mlp_forecast(
    model: DctMlp | DctMlpEnsemble, obs: np.ndarray, batch: int = 512, n: int = N_PRED
) -> np.ndarray:
    """obs (W, >= n_obs, 38, 3) units -> forecasts of all 38 points (W, n, 38, 3) (used points from the
    model, :func:`rollout` where it forecasts fewer than ``n`` frames a pass; the rest filled by
    :func:`complete` from the last observed frame: they are fixed in the body frame)."""
    model.eval()
    o = obs[:, -model.n_obs :][:, :, list(JOINTS_USED)].astype(np.float32)
    out = []
    for i in range(0, len(o), batch):
        out.append(rollout(model, torch.from_numpy(o[i : i + batch]), n).numpy())
    pred_used = np.concatenate(out)
    fill = np.repeat(obs[:, -1:], n, 1)
    return complete(pred_used, fill)


def save_mlp(path: str | os.PathLike, model: DctMlp, config: MlpConfig, extra: dict) -> None:
    """One DCT + MLP: an ensemble of one member (:func:`save_ensemble`)."""
    save_ensemble(path, [(model, config)], extra)


def is_cmu8_checkpoint(path: str | os.PathLike) -> bool:
    return family_of(path) == FAMILY


class DctMlpEnsemble(nn.Module):
    """The mean forecast of several DCT + MLPs (e.g. trained with different seeds); they share ``n_obs`` and
    ``n_pred``."""

    kind = "dct_mlp_ensemble"

    def __init__(self, members: list[DctMlp]):
        super().__init__()
        if not members:
            raise InputError("an ensemble needs at least one DCT + MLP member")
        if len({(m.n_obs, m.n_pred) for m in members}) != 1:
            raise InputError("the ensemble's members observe or forecast different numbers of frames")
        self.members = nn.ModuleList(members)
        self.n_obs, self.n_pred = members[0].n_obs, members[0].n_pred

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """obs (B, n_obs, P, 3) -> the members' mean forecast (B, n_pred, P, 3)."""
        return torch.stack([m(obs) for m in self.members]).mean(0)


Forecaster = DctMlp | DctMlpEnsemble


def save_ensemble(path: str | os.PathLike, members: list[tuple[DctMlp, MlpConfig]], extra: dict) -> None:
    """One checkpoint holding every member's config and weights (``member<i>``), in the one format."""
    write_checkpoint(
        path,
        FAMILY,
        config={"members": [c for _, c in members]},
        weights={f"member{i}": m.state_dict() for i, (m, _) in enumerate(members)},
        extra=extra,
        points=[C.CMU38_NAMES[j] for j in JOINTS_USED],
        fps=FPS,
        units="CMU ASF units (0.0254/0.45 m), the benchmark's body frame, y up",
    )


def _build(n_points: int, config: dict, state: dict) -> DctMlp:
    m = DctMlp(n_points, MlpConfig(**config))
    m.load_state_dict(state)
    return m.eval()


def load_mlp(path: str | os.PathLike) -> tuple[Forecaster, dict]:
    """A ``forecast cmu8`` checkpoint: one DCT + MLP, or the mean of several."""
    blob = read_checkpoint(Path(path), FAMILY)
    n = len(blob["points"])
    members = [_build(n, c, blob["weights"][f"member{i}"]) for i, c in enumerate(blob["config"]["members"])]
    m: Forecaster = members[0] if len(members) == 1 else DctMlpEnsemble(members)
    m.eval()
    return m, blob


# picked on validation in both layouts: the exact protocol's and cmu8-all's (`cmu8 validate --windows all`)
SHIPPED_MLP = Path(__file__).resolve().parents[1] / "checkpoints" / "cmu8_dct_mlp_ens.pt"


# ----------------------------------------------------------------------------- the body19 variant


def _body19_predictor(model, n_hist: int = 50, fps_model: float = 25.0):
    """A body19 forecast checkpoint as a protocol predictor over the whole file (see the module docstring)."""

    def run(seq120_b19: np.ndarray, t_last_s: np.ndarray, n_samples: int) -> np.ndarray:
        """seq120_b19 (F,19,3) metres at 120 Hz; t_last_s (W,) time of each window's last observed frame ->
        (W, S, 25, 19, 3) metres at the protocol's frame times."""
        T = len(seq120_b19)
        t_hist = t_last_s[:, None] - (n_hist - 1 - np.arange(n_hist))[None] / fps_model
        obs = _interp(seq120_b19, np.clip(t_hist * C.BENCHMARK_FPS, 0, T - 1))
        n_model = int(np.ceil(N_PRED / FPS * fps_model)) + 1
        torch.manual_seed(0)
        y = forecast_world(model, obs[:, :, None], None, n_model, n_samples)[:, :, :, 0]  # (W,S,n_model,19,3)
        full = np.concatenate([np.repeat(obs[:, None, -1:], y.shape[1], 1), y], 2)  # frame 0 = last observed
        t_out = (np.arange(N_PRED) + 1) / FPS * fps_model
        i0 = np.floor(t_out).astype(int)
        w = (t_out - i0)[None, None, :, None, None]
        return (1 - w) * full[:, :, i0] + w * full[:, :, i0 + 1]

    return run


def _interp(seq: np.ndarray, pos: np.ndarray) -> np.ndarray:
    i0 = np.clip(np.floor(pos).astype(int), 0, len(seq) - 1)
    i1 = np.clip(i0 + 1, 0, len(seq) - 1)
    w = (pos - i0)[..., None, None]
    return (1 - w) * seq[i0] + w * seq[i1]


# ----------------------------------------------------------------------------- the evaluation


@dataclass
class _Scores:
    """What an evaluation gathers: per-window errors per model and action, the forecasts for
    ``--save-samples`` (only when ``samples_dir`` is set) and, once scored, the models' result entries."""

    acts: list[str]
    samples_dir: str | os.PathLike | None = None
    per: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # name -> action -> (W, 25)
    meta: dict[str, tuple[str, str, dict]] = field(default_factory=dict)  # name -> (variant, joints, extra)
    samples: dict[str, dict[str, list]] = field(default_factory=dict)
    full_history: dict[str, np.ndarray] = field(default_factory=dict)  # cmu8-all: action -> (W,) mask

    def put(self, name: str, a: str, err: np.ndarray, variant: str, joints: str, extra: dict | None = None):
        self.per.setdefault(name, {})[a] = err
        self.meta.setdefault(name, (variant, joints, extra or {}))

    def keep(self, name: str, a: str, pred_m, obs_m, gt_m, joint_names, fps, clips: list[str]) -> None:
        """Forecasts ``pred_m (W,S,T,J,3)``, ``obs_m``, ``gt_m`` in metres of the windows of the test
        files ``clips (W,)``, for ``samples_<name>.npz``."""
        if self.samples_dir is None:
            return
        s = self.samples.setdefault(name, {"pred": [], "obs": [], "gt": [], "activity": [], "clip": []})
        s["pred"].append(pred_m.astype(np.float32))
        s["obs"].append(obs_m.astype(np.float32))
        s["gt"].append(gt_m.astype(np.float32))
        s["activity"] += [a] * len(gt_m)
        s["clip"] += list(clips)
        s["joint_names"], s["fps"] = list(joint_names), fps

    def models(self) -> dict[str, dict]:
        """The ``models`` entry of ``results.json``: per action the mean over its windows at the horizons,
        and their mean over the actions; exact-protocol models first, as they were scored."""
        out = {}
        order = sorted(self.per, key=lambda n: self.meta[n][0] != "exact")
        for name in order:
            variant, joints, extra = self.meta[name]
            pa = {a: {"mpjpe_mm": at_horizons(self.per[name][a])} for a in self.acts}
            for a, m in self.full_history.items():  # cmu8-all: also over the windows with their own history
                pa[a]["mpjpe_mm_full_history"] = at_horizons(self.per[name][a][m]) if m.any() else None
            out[name] = {"variant": variant, "joints": joints, "per_action": pa, **extra}
            for key in ("mpjpe_mm", "mpjpe_mm_full_history")[: 1 + bool(self.full_history)]:
                v = [pa[a][key] for a in self.acts]
                out[name][key] = None if None in v else [float(x) for x in np.mean(v, 0)]
        return out


_EXACT = ("exact", "38 points (reference)")
_BODY19 = ("body19", "12 body19 limb points (hips, knees, ankles, shoulders, elbows, wrists)")


def _score_exact(
    ts: TestSet, mlps: list[tuple[str, nn.Module, dict]], sc: _Scores, body19: bool = True
) -> None:
    """Zero velocity and the DCT + MLP checkpoints on the exact protocol (all 38 points) and, for the body19
    variant's table (``body19``), on its 12 limb points."""
    u = C.ASF_UNIT_M
    for a in sc.acts:
        w = ts.windows[a]
        obs, gt = w[:, :N_OBS], w[:, N_OBS:]
        preds = [("zero_velocity", np.repeat(obs[:, -1:], N_PRED, 1), {})]
        preds += [(name, mlp_forecast(m, obs), {"train": blob.get("extra", {})}) for name, m, blob in mlps]
        for name, p, extra in preds:
            sc.put(name, a, mpjpe_mm(p, gt), *_EXACT, extra)
            if body19:
                sc.put(f"{name}@body19", a, mpjpe_mm(p, gt, BODY19_LIMB_POINTS), *_BODY19)
            clips = [Path(ts.files[a][fi]).stem for fi, _ in ts.starts[a]]
            sc.keep(name, a, p[:, None] * u, obs * u, gt * u, C.CMU38_NAMES, FPS, clips)


def _score_body19(ts: TestSet, checkpoints: list, n_samples: int, sc: _Scores, progress=None) -> None:
    """The project's body19 checkpoints on the body19 variant (see the module docstring)."""

    limb19 = [BODY19.index(n) for n in BODY19_LIMBS]
    for i, p in enumerate(checkpoints):
        name = f"{Path(p).stem}@body19"
        m, _meta = load_checkpoint(p, skeleton="body19")
        if progress is not None:
            progress(i, len(checkpoints), Path(p).stem)
        S = n_samples if getattr(m, "stochastic", False) else 1
        run = _body19_predictor(m)
        for a in sc.acts:
            errs = []
            for fi, f in enumerate(ts.files[a]):
                sel = [k for k, (fj, _) in enumerate(ts.starts[a]) if fj == fi]
                starts = np.array([ts.starts[a][k][1] for k in sel])
                seq120 = C.cmu38_to_body19(C.expmap_to_xyz(C.read_expmap(f)))
                t_last = (starts + N_OBS - 1) * DOWNSAMPLE / C.BENCHMARK_FPS
                y = run(seq120, t_last, S)  # (W,S,25,19,3) metres
                gt_m = C.cmu38_to_body19(ts.windows[a][sel, N_OBS:])
                obs_m = C.cmu38_to_body19(ts.windows[a][sel, :N_OBS])
                # a rotation keeps distances: metres / ASF unit = the protocol's units
                errs.append(mpjpe_mm(y[..., limb19, :] / C.ASF_UNIT_M, gt_m[..., limb19, :] / C.ASF_UNIT_M))
                sc.keep(name, a, y, obs_m, gt_m, BODY19, FPS, [Path(f).stem] * len(sel))
            sc.put(name, a, np.concatenate(errs), *_BODY19)


def _results(bf: C.BenchmarkFiles, ts: TestSet, models: dict[str, dict], windows: str = "protocol") -> dict:
    """The ``results.json`` dict around the scored models: protocol, units, what was missing, the published
    rows (with their average over the same actions; ``same_windows``: scored on this protocol's windows)."""

    acts = list(ts.windows)
    return {
        "protocol": WINDOWS[windows],
        "windows": "every window of 10 + 25 frames, stride 1 (MSR-GCN's and PGBIG's 'all')"
        if windows == "all"
        else "8 per test file (RandomState(1234567890), LTD's)",
        "n_padded": {a: int((~m).sum()) for a, m in ts.full_history.items()},
        "reference": REFERENCE,
        "horizons_ms": list(HORIZONS_MS),
        "horizon_frames": list(HORIZON_FRAMES),
        "horizons_real_ms": [round(1000 * (k + 1) / FPS, 1) for k in HORIZON_FRAMES],
        "units": "the reference's millimetres: CMU ASF offsets x 70 (CMU's own ASF unit is 56.4 mm, so these "
        "are 1.24x real millimetres)",
        "actions": acts,
        "actions_missing": ts.actions_missing,
        "files_missing": ts.missing,
        "note": MISSING_NOTE,
        "n_windows": {a: len(ts.windows[a]) for a in acts},
        "test_files": {a: [str(Path(f).relative_to(bf.root)) for f in ts.files[a]] for a in acts},
        "models": models,
        "published": {
            k: {
                **v,
                "average_same_actions": P.average_over(v.get("per_action", {}), acts),
                "same_windows": v["all_windows"] == (windows == "all"),
            }
            for k, v in P.PUBLISHED.items()
        },
        "published_other_metric": P.OTHER_METRIC,
        "published_not_found": "siMLPe has no CMU results (Human3.6M, AMASS, 3DPW only); LTD publishes no "
        "560 ms value on CMU",
        "layout": LAYOUT,
    }


def evaluate(
    root: str | os.PathLike | None = None,
    mlp_checkpoints: list[str | os.PathLike] | None = None,
    body19_checkpoints: list[str | os.PathLike] | None = None,
    n_samples: int = 1,
    samples_dir: str | os.PathLike | None = None,
    n_windows: int = N_WINDOWS,
    progress=None,
    windows: str = "protocol",
) -> dict:
    """Score zero velocity and the models on the protocol (``windows="all"``: cmu8-all, the 38-point models
    only) -> the ``results.json`` dict (see ``LAYOUT``)."""
    t0 = time.perf_counter()
    if windows == "all" and body19_checkpoints:
        raise InputError(
            "the all-windows protocol (cmu8-all) scores the 38-point models only; body19 checkpoints: "
            f"{', '.join(Path(p).name for p in body19_checkpoints)} (score them with --protocol cmu8)"
        )
    bf = C.benchmark_files(root)
    ts = test_set(bf, n_windows, windows=windows)
    sc = _Scores(list(ts.windows), samples_dir, full_history=ts.full_history)
    mlps = [(Path(p).stem, *load_mlp(p)) for p in (mlp_checkpoints or [])]
    _score_exact(ts, mlps, sc, body19=windows != "all")
    _score_body19(ts, list(body19_checkpoints or []), n_samples, sc, progress)
    res = _results(bf, ts, sc.models(), windows)
    if samples_dir is not None:
        res["samples"] = write_samples(samples_dir, sc.samples, WINDOWS[windows])
    res["wall_s"] = time.perf_counter() - t0
    report = _report(res)
    name = res.pop("protocol")
    return results(name, TITLE.format(name), *report, **res)


LAYOUT = {
    "horizons_ms": "the protocol's horizon labels; horizons_real_ms: the same frames in real time (60 Hz)",
    "models.<name>.mpjpe_mm": "mean over the scored actions of the per-action values, one per horizon",
    "models.<name>.per_action.<action>.mpjpe_mm": "mean over the action's test windows, one per horizon",
    "n_padded.<action>": "cmu8-all: windows whose 50-frame history is padded with the file's first frame",
    "models.<name>.mpjpe_mm_full_history": "cmu8-all: the same over the windows whose history is not padded",
    "models.<name>.variant": "exact (the reference's 38 points) or body19 (12 limb points, see the module)",
    "published.<paper>.mpjpe_mm": "the paper's average over its 8 actions (all 8 test files), with source",
    "published.<paper>.same_windows": "true where the paper scored this protocol's windows",
}


def write_samples(
    out_dir: str | os.PathLike, samples: dict[str, dict], protocol: str = PROTOCOL
) -> dict[str, str]:
    """``samples_<name>.npz`` per model (:mod:`forecast.runtime.samples`), with the protocol's name and
    its millimetres per metre."""
    return {
        name: str(
            fsamples.write_samples(
                out_dir,
                name,
                np.concatenate(s["pred"]),
                np.concatenate(s["obs"]),
                np.concatenate(s["gt"]),
                s["fps"],
                s["joint_names"],
                s["activity"],
                s["clip"],
                protocol=np.array(protocol),
                protocol_mm_per_m=np.float64(MM_PER_UNIT / C.ASF_UNIT_M),
            )
        )
        for name, s in samples.items()
    }


def _report(res: dict) -> tuple[list[str], list[Table], list[str]]:
    """The report's notes, tables (per variant: the average with the published rows beside ours, then per
    action) and sources."""
    H = res["horizons_ms"]
    notes = [
        f"Reference: {res['reference']}.",
        f"**Missing data**: {res['note']}. Actions scored: {', '.join(res['actions'])}; not scored: "
        f"{', '.join(res['actions_missing']) or 'none'}.",
        f"MPJPE in {res['units']}; horizons as the protocol labels them (real time: "
        f"{', '.join(f'{t:g}' for t in res['horizons_real_ms'])} ms, the files being 120 Hz).",
        f"Windows: {res['windows']}; per action {res['n_windows']}"
        + (f"; history padded with the file's first frame: {res['n_padded']}" if res["n_padded"] else "")
        + ". Published rows on other windows are marked so.",
    ]
    tables = []
    other = {p: "" if r["same_windows"] else ", other windows" for p, r in res["published"].items()}
    exact = "All windows" if res["protocol"] == WINDOWS["all"] else "Exact protocol"
    exact += " (38 points)"
    for variant, title in (("exact", exact), ("body19", "body19 variant (12 limbs)")):
        names = [n for n, r in res["models"].items() if r["variant"] == variant]
        if not names:
            continue
        rows = [[n, *cells(res["models"][n]["mpjpe_mm"])] for n in names]
        rows += [
            [f"{n} (windows with their own history)", *cells(res["models"][n]["mpjpe_mm_full_history"])]
            for n in names
            if res["models"][n].get("mpjpe_mm_full_history")
        ]
        per = []
        for a in res["actions"]:
            per += [[a, n, *cells(res["models"][n]["per_action"][a]["mpjpe_mm"])] for n in names]
            if variant == "exact":
                for p, r in res["published"].items():
                    v = r.get("per_action", {}).get(a)
                    per += [[a, f"{p} (published{other[p]})", *cells(v)]] if v else []
        if variant == "exact":
            for p, r in res["published"].items():
                if r.get("mpjpe_mm"):
                    rows.append([f"{p} (published, 8 actions{other[p]})", *cells(r["mpjpe_mm"])])
                    if r.get("average_same_actions"):
                        n_act = len(res["actions"])
                        label = f"{p} (published, same {n_act} actions{other[p]})"
                        rows.append([label, *cells(r["average_same_actions"])])
        tables.append(
            Table(
                f"{title}: average over {len(res['actions'])} actions",
                ["model", *(f"{h} ms" for h in H)],
                rows,
            )
        )
        tables.append(Table(f"{title}: per action", ["action", "model", *(str(h) for h in H)], per))
    footer = ["## Published rows", ""]
    for p, r in res["published"].items():
        footer.append(f"- {p}: {r.get('source', '')}; windows: {r['windows']}")
    for p, r in res.get("published_other_metric", {}).items():
        avg = ", ".join(f"{h} ms {v}" for h, v in zip(r["horizons_ms"], r["average"], strict=True))
        footer.append(f"- {p}, {r['metric']} (another metric, context only): average {avg}; {r['source']}")
    footer.append(f"- not found: {res.get('published_not_found', '')}")
    return notes, tables, footer
