"""``forecast characteristic train | eval`` (``python -m roomcap.forecast.characteristic``): the command line
of the characteristic-pose forecaster; the library (labels, model, protocol, training) never prints."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from roomcap.core.cli import Parser, guarded, parse_sets, positive_int
from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import atomic_write_text
from roomcap.core.progress import Bars
from roomcap.forecast.lab.characteristic.labels import segments
from roomcap.forecast.lab.characteristic.model import (
    SHIPPED,
    CharConfig,
    config_from_dict,
    load_checkpoint,
    save_checkpoint,
)
from roomcap.forecast.lab.characteristic.protocol import DATA_SOURCES, evaluate, load_labelled
from roomcap.forecast.lab.characteristic.training import train
from roomcap.forecast.lab.protocol import Table, render, results


def as_results(res: dict) -> dict:
    """An evaluation (:func:`protocol.evaluate`) in the one results schema (:mod:`forecast.lab.protocol`)."""
    source = "CMU" if res.get("data", "cmu") == "cmu" else f"CMU ({res['data']})"
    notes = [
        f"{source} {res.get('split', '')} split: {res['n_labels']} characteristic poses x 5 starts = "
        f"{res['n_windows']} windows, k = {res['k']}"
    ]
    columns = ["method", "MPJPE best-of-k (m)", "diversity (m)"]
    columns.append("MPJPE by start (0 = segment start ... 4 = N frames before)")
    rows = [
        [
            name,
            f"{r['mpjpe']:.3f}",
            "-" if r["diversity"] is None else f"{r['diversity']:.3f}",
            " ".join(f"{v:.3f}" for v in r["mpjpe_by_start"]),
        ]
        for name, r in res["methods"].items()
    ]
    return results(
        "characteristic", "Characteristic 3D poses (Diller ch. 3)", notes, [Table("", columns, rows)], **res
    )


DESCRIPTION = (
    "Characteristic 3D pose forecasting (Diller 2024, ch. 3) on CMU mocap: "
    "labels, data, training, evaluation."
)


DATA_HELP = (
    "clips: 'cmu' (the CMU BVH, default) or 'cmu-all' (every one-person CMU clip: cmu + cmu-more + the "
    "8-action benchmark, split as `forecast train --data cmu-all`; the benchmark's test files are test only)"
)


def _main(argv: list[str] | None = None) -> int:
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    ap = Parser(prog="forecast characteristic", description=DESCRIPTION)
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="annotate CMU, train the heatmap model and the Deterministic ablation")
    t.add_argument("--out", required=True, help="checkpoint path (.pt)")
    t.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help=f"config overrides; keys: {', '.join(f.name for f in dataclasses.fields(CharConfig))}",
    )
    t.add_argument("--data", choices=DATA_SOURCES, default="cmu", help=DATA_HELP)
    t.add_argument("--split-seed", type=int, default=0, help="seed of the split by clip")
    t.add_argument("--no-eval", action="store_true", help="skip the test-split evaluation after training")
    e = sub.add_parser("eval", help="sec. 3.6 evaluation on the CMU test (or val) split")
    e.add_argument("--checkpoint", default=str(SHIPPED), help="checkpoint (default: the shipped one)")
    e.add_argument("--data", choices=DATA_SOURCES, default="cmu", help=DATA_HELP)
    e.add_argument("--split", choices=("test", "val", "train"), default="test", help="split to evaluate")
    e.add_argument("--split-seed", type=int, default=0, help="seed of the split by clip")
    e.add_argument(
        "--k", type=positive_int, default=None, help="hypotheses per window (default: the config's, 10)"
    )
    e.add_argument("--no-refine", action="store_true", help="skip the pose refinement of eq. 3.2")
    e.add_argument(
        "--max-windows", type=positive_int, default=None, help="at most this many windows (default: all)"
    )
    e.add_argument("--seed", type=int, default=0, help="seed of the sampled hypotheses")
    e.add_argument("--json", default=None, help="also write the figures as JSON here (default: no JSON)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    if args.cmd == "train":
        try:
            cfg = config_from_dict(parse_sets(args.set))
        except ValueError as err:
            raise InputError(str(err)) from None
        data = load_labelled(args.data, seed=args.split_seed)
        print(
            "labels: "
            + ", ".join(f"{p} {len(segments(getattr(data, p), cfg.n_obs))}" for p in ("train", "val", "test"))
            + f" (clips {len(data.train)}/{len(data.val)}/{len(data.test)})"
        )
        # the loss terms, as log lines above the bars
        logging.getLogger("roomcap.forecast.lab.characteristic.training").setLevel(logging.INFO)
        t0, c0 = time.perf_counter(), time.process_time()
        with Bars(unit="step") as bars:
            net, det, avg, hist = train(data, cfg, bars)
        hist["train_wall_s"], hist["train_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
        extra = {
            "data": args.data,
            "history": {k: v for k, v in hist.items()},
            "command": "python -m roomcap.forecast.characteristic train "
            + " ".join(sys.argv[2:] if argv is None else argv[1:]),
        }
        for part in ("heatmap", "deterministic"):
            extra["history"][part] = {k: v for k, v in hist[part].items() if k != "loss"}
            extra["history"][part]["loss_last100"] = float(np.mean(hist[part]["loss"][-100:]))
        save_checkpoint(args.out, net, det, cfg, avg, skeleton=data.skeleton, extra=extra)
        print(
            f"wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.2f} MB) after "
            f"{hist['train_wall_s']:.0f} s "
            f"wall, {hist['train_cpu_s']:.0f} s CPU; heatmap {hist['heatmap']['steps_done']} steps, "
            f"val best {hist['heatmap'].get('val_best')}"
        )
        if not args.no_eval:
            args = argparse.Namespace(
                checkpoint=args.out,
                data=args.data,
                split="test",
                split_seed=args.split_seed,
                k=None,
                no_refine=False,
                max_windows=None,
                seed=0,
                json=None,
            )
            return _eval(args)
        return 0
    return _eval(args)


def _eval(args) -> int:
    try:
        net, det, meta = load_checkpoint(args.checkpoint, skeleton="body19")
    except (FormatError, FileNotFoundError) as err:
        raise InputError(str(err)) from None
    cfg = meta["config"]
    data = load_labelled(args.data, meta["fps"], seed=args.split_seed)
    items = getattr(data, args.split)
    c0 = time.process_time()
    with Bars(unit="window") as bars:
        res = evaluate(
            net,
            det,
            meta["avg_pose"],
            items,
            cfg,
            args.k,
            not args.no_refine,
            seed=args.seed,
            max_windows=args.max_windows,
            progress=bars,
            skeleton=meta["skeleton"],
        )
    res["data"], res["split"], res["checkpoint"], res["eval_cpu_s"] = (
        args.data,
        args.split,
        str(args.checkpoint),
        time.process_time() - c0,
    )
    res = as_results(res)
    print(render(res))
    if args.json:
        atomic_write_text(args.json, json.dumps(res, indent=1))
    return 0


main = guarded("forecast characteristic", _main)
