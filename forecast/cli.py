"""``forecast train | sample | eval``.

Examples::

    forecast train --model gru --data cmu --out runs/gru.pt
    forecast train --model social_diffusion --data cmu tracks.npz --set steps=2000 --out runs/sd.pt
    forecast sample --checkpoint runs/gru.pt --tracks session/track/tracks.npz --horizon-s 2 --out fc.npz
    forecast eval --checkpoints runs/gru.pt runs/intention.pt --data cmu --out runs/eval
    forecast eval --social --checkpoints runs/gru.pt runs/sd.pt --data cmu --out runs/eval_social
    forecast characteristic eval --checkpoint forecast/checkpoints/characteristic_cmuall.pt   # Diller ch. 3
    forecast models        # the shipped checkpoints with their model cards
    forecast models --convert OLD.pt NEW.pt   # an older checkpoint in the current format

Data: ``cmu`` = the CMU BVH under ``$ROOMCAP_MOCAP`` / ``$ROOMCAP_SHARED/data/motion``; otherwise track files
or folders containing ``tracks.npz``. Train / validation / test split by clip (``data.split_train_val_test``,
``--split-seed``): ``train`` fits on the train split and keeps the state with the best validation NDMS;
``eval`` reports on the test split only.
"""

# The module docstring is `forecast --help`'s text. This module parses the command line and stays light;
# forecast.commands runs the commands (importing it loads torch).

from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import Any

from roomcap.core.cli import Parser, guarded, positive_float, positive_int
from roomcap.forecast.runtime.registry import NAMES

# sub-commands with parsers of their own, dispatched before parsing (each loads torch when it runs)
OWN_PARSERS = {
    "characteristic": "the characteristic-3D-pose forecaster (Diller ch. 3): train|eval",
    "cmu8": "the CMU 8-action benchmark's DCT + MLP forecaster: train",
    "behaviour": "next actions and their characteristic 3D poses (Diller ch. 4): train|eval|sample",
}


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
    t.add_argument("--model", required=True, choices=NAMES, help="model to train")
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
    s.add_argument(
        "--tracks",
        required=True,
        help="session folder (its track/tracks.npz, else the live track/live.npz) or track file",
    )
    s.add_argument("--horizon-s", type=positive_float, default=1.0, help="seconds to forecast")
    s.add_argument("--samples", type=positive_int, default=1, help="samples per track (stochastic models)")
    s.add_argument(
        "--obs-s",
        type=positive_float,
        help="seconds the model observes before the forecast (default: what it was trained on; shorter lets "
        "a shorter track be forecast, outside what the model was trained for)",
    )
    s.add_argument(
        "--start-s",
        type=float,
        help="forecast from this time (seconds after the track's first frame; default: its last frame); "
        "the track after it is the truth the pictures show",
    )
    s.add_argument(
        "--out",
        required=True,
        help="forecast file to write (.npz); beside it one picture per person, <out stem>_track<ID>.png",
    )
    s.add_argument("--no-pictures", action="store_true", help="write the arrays only")


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
        "scores it; PATH: its benchmark-cmu8 folder, default the shared one), cmu8-all (the same on every "
        "test window, as MSR-GCN and PGBIG score it) or hik (Tanke ch. 8.3 on the "
        "HiK person files in PATH)",
    )
    e.add_argument(
        "path", nargs="?", help="--protocol hik: the folder of HiK person files; cmu8: the benchmark folder"
    )
    e.add_argument(
        "--metric",
        choices=["mpjpe", "angle"],
        default="mpjpe",
        help="--protocol cmu8: mpjpe (3D, as LTD's main_cmu_3d.py) or angle (the mean angle error of Tanke "
        "Table 6.7, as LTD's main_cmu.py; scores zero velocity and the checkpoints of `forecast cmu8 train "
        "--angles`)",
    )
    e.add_argument(
        "--save-samples",
        metavar="DIR",
        help="write samples_<model>.npz per model and baseline (pred, obs, gt in metres, fps, joint_names, "
        "activity, clip: the window's clip, model) for rescoring (protocols cmu, cmu8 and hik; not --social)",
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
        default="gru_cmuall",
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


def _add_models(sub: Any) -> None:
    """``forecast models``."""
    m = sub.add_parser("models", help="list the shipped checkpoints with their model cards")
    m.add_argument("--folder", help="list the checkpoints of this folder instead (default: the shipped ones)")
    m.add_argument("--json", action="store_true", help="print the cards as JSON")
    m.add_argument(
        "--convert",
        nargs=2,
        metavar=("OLD", "NEW"),
        help="rewrite the checkpoint OLD (an older schema) in the current format at NEW, the same weights",
    )
    m.add_argument(
        "--rescore",
        metavar="CK",
        help="score CK again on its own validation clips as it forecasts today and write the scores into its "
        "card (the ones before kept; weights unchanged)",
    )


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
    _add_models(sub)
    return p


def _main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in OWN_PARSERS:
        return _commands().run_own_parser(argv[0], argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING)
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # numpy's BLAS, if not loaded
        os.environ.setdefault(var, str(args.threads))
    return _commands().run(args)


def _commands():
    """:mod:`roomcap.forecast.commands`, imported when a command runs (after the BLAS thread variables are
    set)."""
    from roomcap.forecast import commands  # lazy: loads torch

    return commands


main = guarded("forecast", _main)


if __name__ == "__main__":
    sys.exit(main())
