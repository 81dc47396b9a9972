"""``forecast train | sample | eval``.

Examples::

    forecast train --model gru --data cmu --out runs/gru.pt
    forecast train --model social_diffusion --data cmu tracks.npz --set steps=2000 --out runs/sd.pt
    forecast sample --checkpoint runs/gru.pt --tracks session/track/tracks.npz --horizon-s 2 --out fc.npz
    forecast eval --checkpoints runs/gru.pt runs/intention.pt --data cmu --out runs/eval
    forecast eval --social --checkpoints runs/gru.pt runs/sd.pt --data cmu --out runs/eval_social
    forecast characteristic eval --checkpoint forecast/checkpoints/characteristic_cmu.pt   # Diller ch. 3

Data: ``cmu`` = the CMU BVH under ``$ROOMCAP_MOCAP`` / ``$ROOMCAP_SHARED/data/motion``; otherwise track files
or folders containing ``tracks.npz``. Train / validation / test split by clip (``data.split_train_val_test``,
``--split-seed``): ``train`` fits on the train split and keeps the state with the best validation NDMS;
``eval`` reports on the test split only.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from core.cli import Parser, guarded, parse_sets, positive_float, positive_int
from core.errors import FormatError, InputError
from core.fileio import load_toml
from core.progress import Bars
from forecast.config import config_from_dict

__all__ = ["main", "parse_sets"]  # parse_sets: core.cli's, importable from here as before

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
    from forecast import train as T  # lazy: loads torch (after --threads set the BLAS threads)

    clips, tr, va, te = [], [], [], []
    if "cmu-all" in args.data:  # every one-person CMU clip (clips.load_one_person_all), its own split rule
        from forecast.clips import load_one_person_all

        d = load_one_person_all(args.split_seed)
        clips, tr, va, te = d.clips, list(d.train), list(d.val), list(d.test)
    if "two-person" in args.data:  # the real two-person takes (clips.load_two_person_real), split by take
        from forecast.clips import load_two_person_real

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


def cmd_train(args) -> int:
    import torch  # lazy: loads torch

    from forecast import train as T  # lazy: loads torch

    cfg = _config(args)
    clips, tr, va, te = _load_split(args)
    init = None
    if args.init:
        blob = torch.load(args.init, map_location="cpu", weights_only=True)
        if blob.get("kind") != args.model:
            raise InputError(f"--init {args.init} is a '{blob.get('kind')}' checkpoint, not '{args.model}'")
        init = blob["state_dict"]
    logging.getLogger("forecast.train").setLevel(logging.INFO)  # the loss terms, above the bar
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
    from forecast.preview import no_forecast_reason, preview, save_forecast  # lazy: loads torch

    fc = preview(args.tracks, args.horizon_s, args.checkpoint, args.samples)
    if not np.isfinite(fc["xyz_m"]).any():
        why = no_forecast_reason(args.tracks, args.checkpoint)
        if why:
            raise InputError(f"{why} Nothing was written.")
        raise InputError(
            f"the forecast of {args.tracks} is NaN everywhere: none of its {fc['xyz_m'].shape[2]} tracks has "
            "observed joints in the frames the model looks at. Check the track file (forecast the tracks of "
            "a session where people were found) and the checkpoint; nothing was written."
        )
    save_forecast(args.out, fc)
    print(
        f"{fc['model']}: {fc['xyz_m'].shape[2]} tracks, {fc['xyz_m'].shape[1]} frames "
        f"x {fc['xyz_m'].shape[0]} samples -> {args.out}"
    )
    return 0


def _baseline_models(names: list[str], train_clips, lhip: int | None = None, rhip: int | None = None) -> dict:
    from forecast import evaluate as E  # lazy: loads torch
    from forecast import train as T  # lazy: loads torch

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


PROTOCOLS = ("cmu", "cmu8", "hik")


def shipped_checkpoints() -> list[str]:
    """The body19 forecast checkpoints shipped in forecast/checkpoints (not the characteristic-pose one, not
    the behaviour model, not the CMU 8-action benchmark's own models)."""
    d = Path(__file__).resolve().parent / "checkpoints"
    skip = ("characteristic", "behaviour", "cmu8_")
    return [str(p) for p in sorted(d.glob("*.pt")) if not p.name.startswith(skip)]


def cmd_eval(args) -> int:
    from forecast import evaluate as E  # lazy: loads torch
    from forecast import train as T  # lazy: loads torch

    try:
        names = E.check_baselines(args.baselines + (["fool"] if args.fool else []))
    except ValueError as e:
        raise InputError(str(e)) from None
    if args.protocol not in PROTOCOLS:
        raise InputError(f"unknown protocol '{args.protocol}'; choose one of {', '.join(PROTOCOLS)}")
    if args.protocol == "hik":
        return _eval_hik(args, names)
    if args.protocol == "cmu8":
        return _eval_cmu8(args)
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
    logging.getLogger("forecast.evaluate").setLevel(logging.INFO)  # the model being scored, above the bar
    with Bars(unit="model") as progress:
        res = _eval_cmu(args, E, T, models, clips, te, progress)
    res["wall_s_total"] = time.perf_counter() - t0
    path = E.write_report(res, args.out, res.pop("title"))
    print(path.read_text())
    print(f"evaluation wall time {res['wall_s_total']:.1f} s (metrics and sampling {res['wall_s']:.1f} s)")
    return 0


def _eval_cmu(args, E, T, models: dict, clips, te, progress) -> dict:
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


def _eval_cmu8(args) -> int:
    """The CMU 8-action benchmark (``forecast.benchmark_cmu8``): zero velocity, the DCT + MLP checkpoints on
    the exact protocol, the body19 checkpoints on its body19 variant."""
    from forecast import benchmark_cmu8 as B  # lazy: loads torch

    if args.checkpoints is None:
        cks = ([str(B.SHIPPED_MLP)] if B.SHIPPED_MLP.is_file() else []) + shipped_checkpoints()
    else:
        cks = list(args.checkpoints)
    for ck in cks:
        if not Path(ck).is_file():
            raise InputError(f"no checkpoint {ck}")
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
        )
    path = B.write_report(res, args.out)
    print(path.read_text())
    print(f"evaluation wall time {res['wall_s']:.1f} s; results in {Path(args.out) / 'results.json'}")
    return 0


def _eval_hik(args, names: list[str]) -> int:
    from forecast import hik  # lazy: loads torch

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
    path = hik.write_hik_report(res, args.out)
    print(path.read_text())
    return 0


# sub-commands with parsers of their own, dispatched before parsing (each loads torch when it runs)
OWN_PARSERS = {
    "characteristic": "the characteristic-3D-pose forecaster (Diller ch. 3): train|eval",
    "cmu8": "the CMU 8-action benchmark's DCT + MLP forecaster: train",
    "behaviour": "next actions and their characteristic 3D poses (Diller ch. 4): train|eval|sample",
}


def _run_own_parser(name: str, argv: list[str]) -> int:
    if name == "characteristic":
        from forecast.characteristic.cli import main as sub_main
    elif name == "cmu8":
        from forecast.benchmark_cmu8_train import main as sub_main
    else:
        from forecast.behaviour.cli import main as sub_main
    return sub_main(argv) or 0


def _data_args(sp: argparse.ArgumentParser) -> None:
    """The data a command trains or evaluates on."""
    sp.add_argument(
        "--data",
        nargs="+",
        default=["cmu"],
        help="'cmu' (the CMU BVH), 'cmu-all' (every one-person CMU clip: cmu + cmu-more + the 8-action "
        "benchmark, whose test files are test only), 'two-person' (the salsa takes + 18_01/19_01, split "
        "by take) and/or track files / folders",
    )
    sp.add_argument("--split-seed", type=int, default=0, help="seed of the train/val/test split by clip")


def _add_train(sub: Any) -> None:
    """``forecast train``."""
    t = sub.add_parser("train", help="train a model")
    t.add_argument(
        "--model", required=True, choices=["gru", "intention", "social_diffusion"], help="model to train"
    )
    t.add_argument("--config", help="TOML with the config (a [model] table or top-level keys)")
    t.add_argument(
        "--set", action="append", help="override one config key: key=value (repeatable; default: none)"
    )
    t.add_argument("--out", required=True, help="checkpoint to write (.pt)")
    t.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:1)")
    t.add_argument(
        "--init",
        help="continue training from this checkpoint (same model and architecture; default: from scratch)",
    )
    _data_args(t)


def _add_sample(sub: Any) -> None:
    """``forecast sample``."""
    s = sub.add_parser("sample", help="forecast every track of a track file")
    s.add_argument(
        "--checkpoint", help="model checkpoint (default: the shipped GRU, forecast/checkpoints/gru_cmuall.pt)"
    )
    s.add_argument("--tracks", required=True, help="track file (track/tracks.npz) or session folder")
    s.add_argument("--horizon-s", type=positive_float, default=1.0, help="seconds to forecast")
    s.add_argument("--samples", type=positive_int, default=1, help="samples per track (stochastic models)")
    s.add_argument("--out", required=True, help="forecast file to write (.npz)")


def _add_eval(sub: Any) -> None:
    """``forecast eval``."""
    e = sub.add_parser("eval", help="evaluate checkpoints and baselines on held-out clips")
    e.add_argument(
        "--checkpoints",
        nargs="*",
        default=None,
        help="checkpoints to score (default: the shipped ones in forecast/checkpoints that fit the protocol)",
    )
    e.add_argument(
        "--baselines",
        nargs="*",
        default=["real", "zero", "const", "slide", "fool"],
        help="any of real (the ground-truth future), zero, const, slide (last pose carried along the last "
        "root velocity), fool (clustered static poses, sec. 6.4.4); zero_velocity / constant_velocity "
        "also work",
    )
    e.add_argument("--fool", action="store_true", help="add the 'fool' (sec. 6.4.4) to --baselines")
    e.add_argument(
        "--protocol",
        default="cmu",
        help="cmu (held-out CMU clips, --data), cmu8 (the CMU 8-action benchmark of Li et al. 2018 as LTD "
        "scores it; PATH: its benchmark-cmu8 folder, default the shared one) or hik (Tanke ch. 8.3 on the "
        "HiK person files in PATH)",
    )
    e.add_argument(
        "path", nargs="?", help="--protocol hik: the folder of HiK person files; cmu8: the benchmark folder"
    )
    e.add_argument(
        "--save-samples",
        metavar="DIR",
        help="write samples_<model>.npz per model and baseline (pred, obs, gt in metres, fps, joint_names, "
        "activity, model) for rescoring (protocols cmu, cmu8 and hik; not --social)",
    )
    e.add_argument("--social", action="store_true", help="composed two-person scenes, long horizon, SSCP")
    e.add_argument("--horizon-s", type=positive_float, default=4.0, help="seconds forecast per window")
    e.add_argument(
        "--samples", type=positive_int, default=50, help="samples per stochastic model (DLow, Tanke: 50)"
    )
    e.add_argument("--scenes", type=positive_int, default=24, help="--social: composed two-person scenes")
    e.add_argument("--max-windows", type=positive_int, default=400, help="at most this many test windows")
    e.add_argument("--stride", type=positive_int, default=5, help="frames between test windows")
    e.add_argument(
        "--reference",
        default="gru_cmu",
        help="model whose NDMS the others are compared with (paired differences with bootstrap CIs)",
    )
    e.add_argument(
        "--ndms-db",
        choices=["test", "all"],
        default="test",
        help="NDMS database: held-out clips (seed) or all clips, always grouped by activity; ndms keeps the "
        "query's own clip in it (seed), ndms_loo leaves it out",
    )
    e.add_argument("--out", required=True, help="report to write (Markdown; a .json beside it)")
    _data_args(e)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="forecast", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--threads", type=positive_int, default=1, help="torch CPU threads (1 is fastest on a busy machine)"
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log progress messages")
    sub = p.add_subparsers(dest="cmd", required=True)
    for name, text in OWN_PARSERS.items():  # listed so that `forecast --help` shows them
        sub.add_parser(name, help=text)
    _add_train(sub)
    _add_sample(sub)
    _add_eval(sub)
    return p


def _main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in OWN_PARSERS:
        return _run_own_parser(argv[0], argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # numpy's BLAS, if not loaded
        os.environ.setdefault(var, str(args.threads))
    import torch  # lazy: loads torch (after the BLAS thread variables above)

    torch.set_num_threads(args.threads)
    return {"train": cmd_train, "sample": cmd_sample, "eval": cmd_eval}[args.cmd](args)


main = guarded("forecast", _main)


if __name__ == "__main__":
    sys.exit(main())
