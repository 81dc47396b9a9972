"""Training of the CMU 8-action benchmark's DCT + MLP forecaster: ``forecast cmu8 train | ensemble``.

The train files of the benchmark (:mod:`forecast.lab.benchmark_cmu8`) less the last file of each action,
which
is the validation split (model selection only); the test files are never read. siMLPe's recipe (Guo et al.
2023): AdamW with a cosine schedule, the point error plus the velocity error, and the augmentations
``--mirror`` (left/right) and ``--reverse`` (windows played backwards); the state with the lowest validation
MPJPE is kept. ``forecast cmu8 ensemble`` writes one checkpoint averaging several trained models.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch

from roomcap.core.cli import positive_float, positive_int
from roomcap.core.errors import InputError
from roomcap.core.progress import Bars
from roomcap.forecast.lab import benchmark_cmu8_angle as A
from roomcap.forecast.lab import benchmark_cmu8_angle_intention as AI
from roomcap.forecast.lab import cmu_more as C
from roomcap.forecast.lab.benchmark_cmu8 import (
    ALL_OBS,
    JOINTS_USED,
    MIRROR_PARTNER,
    N_OBS,
    DctMlp,
    DctMlpEnsemble,
    Forecaster,
    MlpConfig,
    all_windows,
    at_horizons,
    fit_mlp,
    is_cmu8_checkpoint,
    load_mlp,
    mirror_windows,
    mlp_forecast,
    mpjpe_mm,
    reverse_windows,
    save_ensemble,
    save_mlp,
    sequence,
    train_windows,
)

log = logging.getLogger(__name__)


def mirror_index() -> np.ndarray:
    """For the 25 used points: the index of each one's left/right partner (``MIRROR_PARTNER``)."""
    used = list(JOINTS_USED)
    return np.array([used.index(MIRROR_PARTNER[j]) for j in used])


def _mirror(b: torch.Tensor, flip: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Windows ``b (B,T,25,3)``: those with ``flip`` mirrored (x -> -x in the body frame, left <-> right)."""
    return mirror_windows(b, flip, idx, (-1.0, 1.0, 1.0))


def _pad_start(b: torch.Tensor, pad: torch.Tensor) -> torch.Tensor:
    """Windows ``b (B,T,25,3)``: those with ``pad`` (B,) > 0 have their first ``pad`` frames replaced by frame
    ``pad``, as cmu8-all pads the history of a window that starts near its file's first frame."""
    src = torch.maximum(torch.arange(b.shape[1])[None], pad[:, None])  # (B,T): the frame each one copies
    return torch.gather(b, 1, src[:, :, None, None].expand_as(b))


def split_train_val(bf: C.BenchmarkFiles) -> tuple[list[Path], list[Path]]:
    """Train / validation split of the train files: the highest-numbered file of each action with at least
    two files is validation (model selection only); the test files are never touched."""
    tr, va = [], []
    for a in C.BENCHMARK_ACTIONS:
        fs = bf.files["train"].get(a, [])
        if len(fs) >= 2:
            tr += fs[:-1]
            va.append(fs[-1])
        else:
            tr += fs
    return tr, va


def train_mlp(
    train_files: list[Path], val_files: list[Path], config: MlpConfig, progress=None
) -> tuple[DctMlp, dict]:
    """Train the DCT + MLP on all windows of ``train_files``; keep the state with the lowest validation MPJPE
    (protocol units, mean over the six horizons, windows every 5 frames of ``val_files``)."""
    torch.manual_seed(config.seed)
    t_load = time.perf_counter()
    win = train_windows(train_files)
    val = train_windows(val_files, stride=5) if val_files else win[:: max(1, len(win) // 256)]
    t_load = time.perf_counter() - t_load
    used = list(JOINTS_USED)
    model = DctMlp(len(used), config)
    midx = torch.from_numpy(mirror_index())

    def augment(b: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        if config.mirror:
            b = _mirror(b, torch.from_numpy(rng.random(len(b)) < 0.5), midx)
        if config.reverse:
            b = reverse_windows(b, torch.from_numpy(rng.random(len(b)) < 0.5))
        if config.pad_start:  # after reversing, so the padded frames are the history's oldest; the newest
            # ALL_OBS observed frames stay real, as in every cmu8-all window
            k = rng.integers(1, config.n_obs - ALL_OBS + 1, len(b)) * (rng.random(len(b)) < config.pad_start)
            b = _pad_start(b, torch.from_numpy(k))
        return b

    hist = fit_mlp(
        model,
        torch.from_numpy(win[:, :, used]),
        config,
        lambda m: validation_mm(m, val),
        "val_mm",
        augment,
        progress,
    )
    hist.update(n_train_windows=len(win), n_val_windows=len(val), load_s=t_load)
    return model, hist


def validation_mm(model: Forecaster, val: np.ndarray) -> float:
    """Validation MPJPE: protocol units, mean over the six horizons of windows ``val (W, 75, 38, 3)``."""
    pred = mlp_forecast(model, val[:, :N_OBS])  # the newest n_obs frames; 25 frames, rolled out if need be
    return float(np.mean(at_horizons(mpjpe_mm(pred, val[:, N_OBS:]))))


# ----------------------------------------------------------------------------- `forecast cmu8 train`


def main(argv: list[str] | None = None) -> int:
    """``forecast cmu8 train --out PATH``: train the DCT + MLP on the benchmark's train files (validation =
    the last train file of each action), keep the best validation state, write the checkpoint."""
    p = argparse.ArgumentParser(prog="forecast cmu8", description=main.__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train the DCT + MLP on the benchmark's train files")
    t.add_argument("path", nargs="?", help="the benchmark-cmu8 folder (default: the shared one)")
    t.add_argument("--out", required=True)
    d, di = MlpConfig(), AI.config()  # the DCT + MLP's defaults and those of --model intention
    t.add_argument("--steps", type=positive_int, help=f"default {d.steps} (intention: {di.steps})")
    t.add_argument("--batch", type=positive_int, help=f"default {d.batch} (intention: {di.batch})")
    t.add_argument("--blocks", type=positive_int, default=d.n_blocks)
    t.add_argument(
        "--width",
        type=positive_int,
        help="channels between the DCT + MLP's spatial layers (default: the input's values, siMLPe's)",
    )
    t.add_argument(
        "--frame-loss",
        action="store_true",
        help="the DCT + MLP's error of a frame is the norm over all its values (LTD's angle loss) instead of "
        "the mean of per-point norms",
    )
    t.add_argument(
        "--spatial-mix",
        action="store_true",
        help="each of the DCT + MLP's blocks mixes the points too (MLP-Mixer), not only its input and output "
        "layers",
    )
    t.add_argument(
        "--pad-last",
        action="store_true",
        help="the DCT + MLP pads its observation with the last observed frame to n_obs + n_pred frames and "
        "forecasts them in one pass (LTD's and PGBIG's input; lets --n-pred exceed --n-obs)",
    )
    t.add_argument(
        "--n-pred",
        type=positive_int,
        help=f"frames forecast in one pass (default {d.n_pred}; siMLPe: 10, rolled out to 25; intention: "
        "frames forecast in training, at least 25)",
    )
    t.add_argument(
        "--n-obs",
        type=positive_int,
        help=f"frames observed (default {d.n_obs}, the protocol's; MSR-GCN and PGBIG: 10, the all-windows "
        "protocol's history)",
    )
    t.add_argument("--lr", type=positive_float, help=f"default {d.lr} (intention: {di.lr})")
    t.add_argument("--seed", type=int, default=d.seed)
    t.add_argument("--mirror", action="store_true", help="augment with left/right mirrored windows")
    t.add_argument("--reverse", action="store_true", help="augment with windows played backwards")
    t.add_argument(
        "--pad-start",
        type=float,
        default=d.pad_start,
        help="share of training windows whose oldest history frames (all but the newest 10) are padded with "
        "their first real frame, as cmu8-all pads windows near a file's start (default 0)",
    )
    t.add_argument(
        "--angles",
        action="store_true",
        help="forecast the exponential maps (scored by `forecast eval --protocol cmu8 --metric angle`) "
        "instead of the 3D points",
    )
    t.add_argument(
        "--all-files",
        action="store_true",
        help="train on every train file, the validation files too, and keep the last step (a recipe already "
        "chosen on validation, refit on all the training data)",
    )
    t.add_argument(
        "--model",
        choices=("dct_mlp", "intention"),
        default="dct_mlp",
        help="with --angles: the DCT + MLP (default) or the seed's intention model (Tanke ch. 6, stochastic)",
    )
    t.add_argument("--hidden", type=positive_int, help="intention: the pose GRUs' units (default 128)")
    t.add_argument(
        "--tau-rec",
        type=positive_int,
        help="intention: frames over which L_rec's weight fades to 0 (eq. 6.8; default 15, the seed's)",
    )
    t.add_argument(
        "--variety",
        type=positive_int,
        help="intention: noise draws per training window, L_rec scoring the closest (ours, Social GAN's "
        "variety loss; default 1, the seed's)",
    )
    t.add_argument(
        "--label-steps",
        type=positive_int,
        help="intention: steps of a first stage training the intention forecaster alone on L_sym (eq. 6.4)",
    )
    t.add_argument("--val-every", type=positive_int, help="steps between validation scores (model selection)")
    t.add_argument("--threads", type=positive_int, default=1)
    e = sub.add_parser("ensemble", help="one checkpoint averaging trained DCT + MLPs, scored on validation")
    e.add_argument("members", nargs="+", help="checkpoints written by `forecast cmu8 train`")
    e.add_argument("--data", help="the benchmark-cmu8 folder (default: the shared one)")
    e.add_argument("--out", required=True)
    e.add_argument("--threads", type=positive_int, default=1)
    v = sub.add_parser(
        "validate", help="score 3D checkpoints on the validation files, as a protocol lays out windows"
    )
    v.add_argument("checkpoints", nargs="+", help="checkpoints written by `forecast cmu8 train | ensemble`")
    v.add_argument("--data", help="the benchmark-cmu8 folder (default: the shared one)")
    v.add_argument(
        "--windows",
        choices=("train", "all"),
        default="train",
        help="train: every 5th window with its full history, as training validates; all: every window, as "
        "cmu8-all lays out the test files (history padded with the file's first frame)",
    )
    v.add_argument("--threads", type=positive_int, default=1)
    args = p.parse_args(argv)
    args.command = "forecast cmu8 " + " ".join(sys.argv[1:] if argv is None else argv)  # the model card's
    torch.set_num_threads(args.threads)
    if args.cmd == "ensemble":
        return _main_ensemble(args)
    if args.cmd == "validate":
        return _main_validate(args)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger(fit_mlp.__module__).setLevel(logging.INFO)  # the validation curve, one line per check
    given = {"n_obs": args.n_obs, "n_pred": args.n_pred, "lr": args.lr, "steps": args.steps}
    given.update(batch=args.batch, seed=args.seed, val_every=args.val_every)
    if args.model == "intention":
        return _main_intention(args, given)
    if any(v is not None for v in (args.hidden, args.tau_rec, args.variety, args.label_steps)):
        raise InputError("--hidden, --tau-rec, --variety and --label-steps are options of --model intention")
    if args.all_files:  # no validation files left: only the last step is scored, and kept
        given["val_every"] = args.steps
    kw = {k: v for k, v in given.items() if v is not None}
    cfg = MlpConfig(
        n_blocks=args.blocks,
        mirror=args.mirror,
        reverse=args.reverse,
        pad_start=args.pad_start,
        width=args.width or 0,
        frame_loss=args.frame_loss,
        spatial_mix=args.spatial_mix,
        pad_last=args.pad_last,
        **kw,
    )
    bf, tr, va = _train_files(args.path, args.all_files)
    if args.angles:
        with Bars(unit="step") as bars:
            f, hist = A.train(tr, va, cfg, progress=lambda i, n: bars("train", i, n))
        A.save(
            args.out,
            f,
            [cfg],
            {
                "train_files": [p.name for p in tr],
                "val_files": [p.name for p in va],
                **hist,
                "command": args.command,
            },
        )
        b = hist["best"]
        print(
            f"kept step {b['step']} (validation angle error {b['val_rad']:.3f} rad, mean of the 5 horizons); "
            f"{hist['n_train_windows']} train windows, {hist['train_s']:.0f} s; wrote {args.out}"
        )
        return 0
    with Bars(unit="step") as bars:
        model, hist = train_mlp(tr, va, cfg, progress=lambda i, n: bars("train", i, n))
    extra = {
        "train_files": [f.name for f in tr],
        "val_files": [f.name for f in va],
        "files_missing": bf.missing,
        **{k: v for k, v in hist.items()},
        "command": args.command,
    }
    save_mlp(args.out, model, cfg, extra)
    b = hist["best"]
    print(
        f"kept step {b['step']} (validation MPJPE {b['val_mm']:.1f} mm, mean of the six horizons); "
        f"{hist['n_train_windows']} train windows, {hist['train_s']:.0f} s, "
        f"{hist['steps_per_s']:.2f} steps/s, {hist['samples_per_s']:.0f} samples/s; wrote {args.out}"
    )
    return 0


def _train_files(
    path: str | None, all_files: bool = False
) -> tuple[C.BenchmarkFiles, list[Path], list[Path]]:
    """The benchmark's files, its train and validation files (``all_files``: every train file trains, none
    validates), said on the terminal; a clear error without train files."""
    bf = C.benchmark_files(path)
    tr, va = split_train_val(bf)
    if all_files:
        tr, va = sorted(tr + va), []
    if not tr:
        raise InputError(f"no train files under {bf.root}/train; missing: {bf.missing_text()}")
    print(f"train files {len(tr)}, validation files {len(va)} ({', '.join(f.name for f in va)}); "
          f"missing: {bf.missing_text()}")  # fmt: skip
    return bf, tr, va


def _validation_files(data: str | None) -> tuple[C.BenchmarkFiles, list[Path]]:
    """The benchmark's files and its validation files (each action's last train file), or a clear error."""
    bf = C.benchmark_files(data)
    _, va = split_train_val(bf)
    if not va:
        raise InputError(f"no validation file under {bf.root}/train (each action's last train file)")
    return bf, va


def _main_intention(args, given: dict) -> int:
    """``forecast cmu8 train --angles --model intention``: the seed's intention model on the exponential maps
    (:mod:`roomcap.forecast.lab.benchmark_cmu8_angle_intention`), the best validation state written."""
    dct_mlp_only = {
        "--width": args.width,
        "--frame-loss": args.frame_loss,
        "--spatial-mix": args.spatial_mix,
        "--pad-last": args.pad_last,
        "--mirror": args.mirror,
        "--pad-start": args.pad_start,
        "--all-files": args.all_files,
    }
    if misplaced := [flag for flag, value in dct_mlp_only.items() if value]:
        raise InputError(
            f"{', '.join(misplaced)}: options of the DCT + MLP (--model dct_mlp), not of --model intention"
        )
    if not args.angles:
        raise InputError("--model intention forecasts the exponential maps: add --angles")
    logging.getLogger(AI.__name__).setLevel(logging.INFO)  # the validation curve, one line per check
    cfg = AI.config(
        hidden=args.hidden, tau_rec=args.tau_rec, variety=args.variety, label_steps=args.label_steps, **given
    )
    bf, tr, va = _train_files(args.path)
    files = {
        "train_files": [p.name for p in tr],
        "val_files": [p.name for p in va],
        "files_missing": bf.missing,
    }

    def write(f, hist: dict) -> None:  # at each new best too: a run stopped early leaves its best state
        AI.save(args.out, f, cfg, {**files, **hist, "command": args.command})

    with Bars(unit="step") as bars:
        f, hist = AI.train(
            tr, va, cfg, progress=lambda i, n: bars("train", i, n), on_best=write, reverse=args.reverse
        )
    write(f, hist)
    b = hist["best"]
    print(
        f"kept step {b['step']} (validation angle error {b['val_rad']:.3f} rad, best of {AI.VAL_SAMPLES} "
        f"samples, mean of the 5 horizons; single samples {b['val_rad_mean']:.3f}); "
        f"{hist['n_train_windows']} train windows, {hist['train_s']:.0f} s, "
        f"{hist['steps_per_s']:.2f} steps/s; wrote {args.out}"
    )
    return 0


def _warn_trained_on_validation(names: list[str], extras: list[dict]) -> None:
    """Say so when a member was trained with ``--all-files``: its validation score above is not held out."""
    refit = [n for n, e in zip(names, extras, strict=True) if e.get("val_files") == []]
    if refit:
        print(f"note: {', '.join(refit)} trained on the validation files too (--all-files): these scores are "
              "not held out")  # fmt: skip


def _main_ensemble(args) -> int:
    """``forecast cmu8 ensemble --out PATH A.pt B.pt ...``: every member and their mean scored on the
    validation windows (as in training), the ensemble written."""
    if all(A.is_angle_checkpoint(p) for p in args.members):
        return _main_angle_ensemble(args)
    members, names, extras = [], [], []
    for p in args.members:
        m, blob = load_mlp(p)
        if not isinstance(m, DctMlp):
            raise InputError(f"{p} is already an ensemble; give the single models it was made of")
        members.append((m, MlpConfig(**blob["config"]["members"][0])))
        names.append(Path(p).name)
        extras.append(blob.get("extra", {}))
    bf, va = _validation_files(args.data)
    val = train_windows(va, stride=5)
    scores = {n: validation_mm(m, val) for n, (m, _) in zip(names, members, strict=True)}
    ens = DctMlpEnsemble([m for m, _ in members])
    v = validation_mm(ens, val)
    for n, s in scores.items():
        print(f"{n}: validation MPJPE {s:.2f} mm")
    print(f"ensemble of {len(members)}: validation MPJPE {v:.2f} mm (mean of the six horizons)")
    _warn_trained_on_validation(names, extras)
    extra = {
        "members": names,
        "member_val_mm": scores,
        "best": {"val_mm": v},
        "val_files": [f.name for f in va],
        "files_missing": bf.missing,
        "member_train": extras,
        "command": args.command,
    }
    save_ensemble(args.out, members, extra)
    print(f"wrote {args.out}")
    return 0


def validation_windows(files: list[Path], windows: str = "train") -> np.ndarray:
    """The validation windows (W, 75, 38, 3): ``train``, every 5th start with its full history (as training
    validates); ``all``, every start with the history padded as cmu8-all pads the test files'
    (:func:`roomcap.forecast.lab.benchmark_cmu8.all_windows`)."""
    if windows == "train":
        return train_windows(files, stride=5)
    return np.concatenate([all_windows(sequence(f))[1] for f in files]).astype(np.float32)


def _main_validate(args) -> int:
    """``forecast cmu8 validate CK...``: each checkpoint's validation MPJPE (mean of the six horizons)."""
    _, va = _validation_files(args.data)
    val = validation_windows(va, args.windows)
    for p in args.checkpoints:
        if not is_cmu8_checkpoint(p):
            raise InputError(f"{p} is not a `forecast cmu8 train | ensemble` checkpoint of 3D points")
        m, _ = load_mlp(p)
        score = validation_mm(m, val)
        print(f"{Path(p).name}: validation MPJPE {score:.2f} ({len(val)} windows, {args.windows})")
    return 0


def _main_angle_ensemble(args) -> int:
    """The same for exponential-map models (``--angles``): the members and their mean scored by the angle
    error on the validation windows, the ensemble written."""
    fs, names, extras = [], [], []
    for p in args.members:
        f, blob = A.load(p)
        if isinstance(f.model, DctMlpEnsemble):
            raise InputError(f"{p} is already an ensemble; give the single models it was made of")
        fs.append((f, MlpConfig(**A.member_configs_and_weights(blob)[0][0])))
        names.append(Path(p).name)
        extras.append(blob.get("extra", {}))
    if len({(tuple(f.joints), tuple(f.dims)) for f, _ in fs}) != 1:
        raise InputError("the members forecast different values (trained on different files?)")
    _, va = _validation_files(args.data)
    val = A.train_windows(va, stride=5)
    scores = {n: A.validation_error(f, val) for n, (f, _) in zip(names, fs, strict=True)}
    f0 = fs[0][0]
    ens = A.AngleForecaster(DctMlpEnsemble([f.model for f, _ in fs]), f0.joints, f0.dims)
    v = A.validation_error(ens, val)
    for n, s in scores.items():
        print(f"{n}: validation angle error {s:.4f} rad")
    print(f"ensemble of {len(fs)}: validation angle error {v:.4f} rad (mean of the five horizons)")
    _warn_trained_on_validation(names, extras)
    extra = {
        "members": names,
        "member_val_rad": scores,
        "best": {"val_rad": v},
        "val_files": [f.name for f in va],
        "member_train": extras,
        "command": args.command,
    }
    A.save(args.out, ens, [c for _, c in fs], extra)
    print(f"wrote {args.out}")
    return 0
