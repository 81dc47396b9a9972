"""What the ``forecast`` sub-commands do, once :mod:`roomcap.forecast.cli` has parsed the command line and
set the BLAS thread variables: importing this module loads torch.

``train``, ``sample`` and ``eval`` (``run``), and the sub-commands with parsers of their own
(``run_own_parser``: ``characteristic``, ``cmu8``, ``behaviour``).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import torch

from roomcap.core.cli import parse_sets
from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import atomic_path, load_toml
from roomcap.core.progress import Bars
from roomcap.forecast.lab import benchmark_cmu8 as B
from roomcap.forecast.lab import benchmark_cmu8_angle as A
from roomcap.forecast.lab import benchmark_cmu8_train as BT
from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab import hik, protocol
from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.behaviour import cli as behaviour_cli
from roomcap.forecast.lab.characteristic import cli as characteristic_cli
from roomcap.forecast.lab.clips import load_one_person_all, load_two_person_real
from roomcap.forecast.runtime import checkpoint as ckpt
from roomcap.forecast.runtime.preview import DEFAULT_CHECKPOINT, save_forecast, shipped_checkpoints
from roomcap.forecast.runtime.registry import config_from_dict
from roomcap.forecast.runtime.track_forecast import forecast_tracks
from roomcap.track.trackfile import resolve_track_file

log = logging.getLogger(__name__)


def _config(args) -> object:
    d = {}
    if args.config:
        t = load_toml(args.config)
        d.update(t.get(args.model, t))
    d.update(parse_sets(args.set))
    try:
        return config_from_dict(args.model, d)
    except ValueError as e:
        raise InputError(str(e)) from None


def _load_split(args):
    """Clips of every source, split train / val / test by clip per source (adding a source never reshuffles
    another's split)."""
    clips, tr, va, te = [], [], [], []
    if "cmu-all" in args.data:  # every one-person CMU clip (clips.load_one_person_all), its own split rule
        d = load_one_person_all(args.split_seed)
        clips, tr, va, te = d.clips, list(d.train), list(d.val), list(d.test)
    if "two-person" in args.data:  # the real two-person takes (clips.load_two_person_real), split by take
        d = load_two_person_real(args.split_seed)
        clips, tr, va, te = clips + d.clips, tr + d.train, va + d.val, te + d.test
    own = {"cmu", "cmu-all", "two-person"}
    groups = [["cmu"]] if "cmu" in args.data else []
    groups += [[d for d in args.data if d not in own]] if set(args.data) - own else []
    for group in groups:  # CMU and the track files are split separately
        c = T.load_sources(group)
        a, v, b = T.split_clips(c, args.split_seed)
        clips += c
        tr += a
        va += v
        te += b
    return clips, tr, va, te


def _train_command(args) -> str:
    """The ``forecast train`` command line that ``args`` stand for (the model card records it)."""
    parts = ["forecast train", f"--model {args.model}", "--data " + " ".join(args.data)]
    parts += [f"--config {args.config}"] if args.config else []
    parts += [f"--set {s}" for s in args.set or []]
    parts += [f"--init {Path(args.init).name}"] if args.init else []
    return " ".join(parts)


def cmd_train(args) -> int:
    cfg = _config(args)
    clips, tr, va, te = _load_split(args)
    init = None
    if args.init:
        init = ckpt.read_checkpoint(args.init, args.model)["weights"]["model"]
    logging.getLogger("roomcap.forecast.lab.train").setLevel(logging.INFO)  # the loss terms, above the bar
    with Bars(unit="step") as bars:
        model, hist = T.train(args.model, tr, cfg, progress=bars, device=args.device, init=init, val_clips=va)
    T.save_checkpoint(
        args.out,
        model,
        args.model,
        cfg,
        tr[0].skeleton,
        extra={
            "train_clips": [c.name for c in tr],
            "val_clips": [c.name for c in va],
            "test_clips": [c.name for c in te],
            "steps_per_s": float(hist["steps_per_s"]),
            "val": hist.get("val", []),
            "val_best": hist.get("val_best", {}),
            "init": Path(args.init).name if args.init else "",
            "data": ",".join(args.data),
            "command": _train_command(args),  # the model card's
        },
    )
    n = len(hist["loss"])
    first, last = sum(hist["loss"][:20]) / min(20, n), sum(hist["loss"][-20:]) / min(20, n)
    print(
        f"{args.model}: {len(tr)} train clips, {hist['n_windows']} windows, loss {first:.4f} -> {last:.4f}, "
        f"{hist['steps_per_s']:.1f} steps/s; wrote {args.out}"
    )
    if hist.get("val_best"):
        b = hist["val_best"]
        print(
            f"kept step {b['step']} by {b['select']}: validation NDMS 2-4 s {b['ndms_2_4']:.4f}, "
            f"MPJPE 0-1 s {1000 * b['mpjpe_0_1']:.0f} mm ({len(va)} validation clips; step:NDMS/MPJPE "
            + ", ".join(f"{r['step']}:{r['ndms_2_4']:.3f}/{1000 * r['mpjpe_0_1']:.0f}" for r in hist["val"])
            + ")"
        )
    return 0


def cmd_sample(args) -> int:
    path, _ = resolve_track_file(args.tracks)
    fc = forecast_tracks(
        path,
        args.horizon_s,
        args.checkpoint or DEFAULT_CHECKPOINT,
        args.samples,
        args.obs_s,
        start_s=args.start_s,
        strict=True,
    )
    fps, track_fps = float(fc["fps"]), float(fc["track_fps"])
    if abs(track_fps - fps) > 1e-6:
        print(
            f"note: {path} is at {track_fps:g} Hz and the model ({fc['model']}) at {fps:g} Hz: the track was "
            f"resampled to {fps:g} Hz (linear) and the forecast is at {fps:g} Hz."
        )
    if not np.isfinite(fc["xyz_m"]).any():
        raise InputError(
            f"the forecast of {path} is NaN everywhere: none of its {fc['xyz_m'].shape[2]} tracks has "
            "observed joints in the frames the model looks at. Check the track file (forecast the tracks of "
            "a session where people were found) and the checkpoint; nothing was written."
        )
    save_forecast(args.out, fc)
    print(
        f"{fc['model']}: {fc['xyz_m'].shape[2]} tracks, {fc['xyz_m'].shape[1]} frames "
        f"x {fc['xyz_m'].shape[0]} samples -> {args.out}"
    )
    if not args.no_pictures:
        from roomcap.forecast.runtime.sample_plot import plot_forecasts  # lazy: loads matplotlib

        for png in plot_forecasts(fc, args.out, title=f"{path}"):
            print(f"picture: {png}")
    return 0


def _baseline_models(names: list[str], train_clips, lhip: int | None = None, rhip: int | None = None) -> dict:
    models: dict = {}
    for name in names:
        if name == "real":
            models["real"] = E.Real()
        elif name == "fool":
            ws = T.fdata.make_windows(train_clips, 1, 0, 10, persons="each")
            models["fool"] = T.fool_model(ws)
        elif lhip is None:
            models[name] = T.baseline(name)
        else:
            models[name] = T.baseline(name, lhip, rhip)
    return models


PROTOCOLS = ("cmu", "cmu8", "cmu8-all", "hik")


def cmd_eval(args) -> int:
    try:
        names = E.check_baselines(args.baselines + (["fool"] if args.fool else []))
    except ValueError as e:
        raise InputError(str(e)) from None
    if args.protocol not in PROTOCOLS:
        raise InputError(f"unknown protocol '{args.protocol}'; choose one of {', '.join(PROTOCOLS)}")
    if args.protocol == "hik":
        return _eval_hik(args, names)
    if args.protocol == "cmu8":
        return _eval_cmu8_angle(args) if args.metric == "angle" else _eval_cmu8(args)
    if args.metric != "mpjpe":
        raise InputError(f"--metric {args.metric} is a metric of --protocol cmu8 only")
    if args.protocol == "cmu8-all":
        return _eval_cmu8(args, windows="all")
    t0 = time.perf_counter()
    clips, tr, va, te = _load_split(args)
    ck_models: dict = {}
    default = args.checkpoints is None  # no --checkpoints: the shipped ones
    for ck in shipped_checkpoints() if default else args.checkpoints:
        try:
            m, meta = T.load_checkpoint(ck, skeleton=clips[0].skeleton)
        except FormatError as e:
            if not default:
                raise
            print(f"skipping shipped {Path(ck).name}: {e}")
            continue
        used = set(meta["extra"].get("train_clips", [])) | set(meta["extra"].get("val_clips", []))
        leak = sorted(used & {c.name for c in te})
        if leak and default:
            print(
                f"skipping shipped {Path(ck).name}: trained or selected on this split's test clips {leak[:3]}"
            )
            continue
        ck_models[Path(ck).stem] = m
        if leak:  # a checkpoint that trained or was selected on a test clip cannot be evaluated fairly
            raise InputError(
                f"{ck} was trained or selected on test clips {leak[:5]}{'...' if len(leak) > 5 else ''}; "
                "retrain it with this version's split (forecast train) or pass the --split-seed it used"
            )
    models = _baseline_models(names, tr)
    models.update(ck_models)
    print(f"evaluating on {len(te)} test clips: {', '.join(c.name for c in te)}")
    logging.getLogger("roomcap.forecast.lab.evaluate").setLevel(
        logging.INFO
    )  # the model being scored, above the bar
    with Bars(unit="model") as progress:
        res = _eval_cmu(args, models, clips, te, progress)
    res["wall_s_total"] = time.perf_counter() - t0
    path = E.write_report(res, args.out, res.pop("title"))
    print(path.read_text())
    print(f"evaluation wall time {res['wall_s_total']:.1f} s (metrics and sampling {res['wall_s']:.1f} s)")
    return 0


def _eval_cmu(args, models: dict, clips, te, progress) -> dict:
    if args.social:
        real_scenes = []
        if "cmu" in args.data:
            try:
                real_scenes.append(T.fdata.cmu_two_person_clip())
            except FileNotFoundError as e:
                log.warning("no real two-person CMU take: %s", e)
        res = E.evaluate_social(
            models,
            te,
            n_pred=int(round(args.horizon_s * 25)),
            n_scenes=args.scenes,
            progress=progress,
            ndms_database=clips if args.ndms_db == "all" else None,
            real_scenes=real_scenes,
        )
        title = f"Forecast evaluation: two-person scenes ({res['scenes']}, and real ones), held-out clips"
    else:
        res = E.evaluate_single(
            models,
            te,
            ndms_database=clips if args.ndms_db == "all" else None,
            n_pred=int(round(args.horizon_s * 25)),
            n_samples=args.samples,
            max_windows=args.max_windows,
            stride=args.stride,
            progress=progress,
            reference=args.reference,
            samples_dir=args.save_samples,
        )
        title = "Forecast evaluation: held-out clips"
    res["title"] = title
    return res


def _eval_cmu8_angle(args) -> int:
    """The CMU 8-action benchmark in the mean angle error of Tanke Table 6.7
    (``forecast.benchmark_cmu8_angle``): zero velocity and the exponential-map checkpoints (default: the
    shipped one)."""
    if args.checkpoints is None:
        cks = [str(A.SHIPPED)] if A.SHIPPED.is_file() else []
    else:
        cks = list(args.checkpoints)
    for ck in cks:
        if not Path(ck).is_file():
            raise InputError(f"no checkpoint {ck}")
    res = A.evaluate(args.path, cks)
    path = protocol.write(res, args.out)
    print(path.read_text())
    return 0


def _eval_cmu8(args, windows: str = "protocol") -> int:
    """The CMU 8-action benchmark (``forecast.benchmark_cmu8``): zero velocity, the DCT + MLP checkpoints on
    the exact protocol, the body19 checkpoints on its body19 variant; ``windows="all"``: cmu8-all, every test
    window, the DCT + MLP checkpoints only."""
    if args.checkpoints is None:
        cks = [str(B.SHIPPED_MLP)] if B.SHIPPED_MLP.is_file() else []
        cks += shipped_checkpoints() if windows == "protocol" else []
    else:
        cks = list(args.checkpoints)
    for ck in cks:
        if not Path(ck).is_file():
            raise InputError(f"no checkpoint {ck}")
    angle = [c for c in cks if A.is_angle_checkpoint(c)]
    if angle and args.checkpoints is not None:
        raise InputError(
            f"{', '.join(angle)}: forecast exponential maps; score them with `--metric angle`, not in 3D"
        )
    cks = [c for c in cks if c not in angle]
    mlp = [c for c in cks if B.is_cmu8_checkpoint(c)]
    b19 = [c for c in cks if c not in mlp]
    with Bars(unit="model") as progress:
        res = B.evaluate(
            args.path,
            mlp_checkpoints=mlp,
            body19_checkpoints=b19,
            n_samples=args.samples,
            samples_dir=args.save_samples,
            progress=lambda i, n, name=None: progress("body19 models", i, n),
            windows=windows,
        )
    path = protocol.write(res, args.out)
    print(path.read_text())
    print(f"evaluation wall time {res['wall_s']:.1f} s; results in {Path(args.out) / 'results.json'}")
    return 0


def _eval_hik(args, names: list[str]) -> int:
    if not args.path:
        raise InputError(
            "forecast eval --protocol hik DATA: give the folder of HiK person files (data/poses)"
        )
    try:
        res = hik.evaluate_hik(
            args.path, names, args.checkpoints or [], n_samples=args.samples, samples_dir=args.save_samples
        )
    except (FileNotFoundError, FormatError, ValueError) as e:
        raise InputError(str(e)) from None
    path = protocol.write(res, args.out)
    print(path.read_text())
    return 0


def cmd_models(args) -> int:
    from roomcap.forecast.runtime import cards

    if args.convert:
        old, new = args.convert
        print(f"{old} -> {new}: {ckpt.convert(old, new)}")
        return 0
    if args.rescore:
        return _rescore(Path(args.rescore))
    folder = Path(args.folder) if args.folder else cards.CHECKPOINT_DIR
    if not folder.is_dir():
        raise InputError(f"--folder {folder} is not a folder of checkpoints")
    cs = cards.cards(folder)
    if not cs:
        raise InputError(f"no checkpoints (*.pt) in {folder}")
    print(json.dumps(cs, indent=1, default=str) if args.json else cards.render(cs))
    return 0


def _rescore(path: Path) -> int:
    """``forecast models --rescore CK``: the model scored again on its own validation clips by the validator
    that selected it (``lab.selection.Validator``, the config's settings), as it forecasts today; the card's
    scores replaced, the ones before kept under ``scores_before``, the weights unchanged."""
    from argparse import Namespace

    model, meta = T.load_checkpoint(path)
    card, extra, cfg = dict(meta.get("card") or {}), meta.get("extra") or {}, meta["config"]
    names = set(extra.get("val_clips") or [])
    if not names or not card.get("data"):
        raise InputError(f"{path}: its card names no data or validation clips to score it on")
    clips, *_ = _load_split(Namespace(data=card["data"].split(","), split_seed=extra.get("split_seed", 0)))
    val = [c for c in clips if c.name in names]
    if len(val) != len(names):
        raise InputError(
            f"{path}: {len(names) - len(val)} of its validation clips are not in --data {card['data']}"
        )
    scores = T.Validator(
        val,
        n_samples=getattr(cfg, "val_samples", 4),
        max_windows=getattr(cfg, "val_windows", 48),
        stride=getattr(cfg, "val_stride", 10),
        seed=cfg.seed,
    )(model)
    before = card.get("scores", {})
    card["scores_before"] = before
    card["scores"] = {
        "split": "validation",
        "ndms_2_4": scores["ndms_2_4"],
        "mpjpe_0_1_m": scores["mpjpe_0_1"],
    }
    card["rescored"] = f"forecast models --rescore {path.name} ({time.strftime('%Y-%m-%d')})"
    blob = ckpt.read_checkpoint(path)  # the file in the current format, written back with the new card
    blob.pop("upgraded_from", None)
    blob["card"] = card
    with atomic_path(path) as tmp:
        torch.save(blob, tmp)
    print(f"{path.name}: validation {before} -> {card['scores']}")
    return 0


def run(args) -> int:
    """Run the parsed ``train``, ``sample``, ``eval`` or ``models`` command."""
    torch.set_num_threads(args.threads)
    return {"train": cmd_train, "sample": cmd_sample, "eval": cmd_eval, "models": cmd_models}[args.cmd](args)


def run_own_parser(name: str, argv: list[str]) -> int:
    """Run a sub-command that parses its own arguments: ``characteristic``, ``cmu8`` or ``behaviour``."""
    sub_main = {"characteristic": characteristic_cli.main, "cmu8": BT.main, "behaviour": behaviour_cli.main}[
        name
    ]
    return sub_main(argv) or 0
