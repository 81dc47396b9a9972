"""``forecast behaviour train | eval | sample`` (``python -m roomcap.forecast.behaviour``): the command line
of the action and characteristic-3D-pose forecaster (Diller ch. 4); the library never prints."""

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

from roomcap.core.cli import guarded, parse_sets
from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import atomic_write_text
from roomcap.core.progress import Bars
from roomcap.forecast.lab.behaviour import quality as Q
from roomcap.forecast.lab.behaviour.model import (
    SHIPPED,
    VARIANTS,
    BehaviourConfig,
    config_from_dict,
    load_checkpoint,
    save_checkpoint,
)
from roomcap.forecast.lab.behaviour.refine import RefineConfig, refine_config_from_dict
from roomcap.forecast.lab.behaviour.sample import run_sample, session_windows
from roomcap.forecast.lab.behaviour.training import (
    action_frequencies,
    as_results,
    concat,
    evaluate_all,
    load_splits,
    share_real,
    train,
    train_average,
)
from roomcap.forecast.lab.protocol import render

# the shipped 3D quality classifier of each script's data (built by `forecast behaviour quality`)
QUALITY_OF_SCRIPT = {
    "markov": Q.QUALITY_SHIPPED,
    "stations": Q.QUALITY_SHIPPED.with_name("behaviour_quality_stations_cmu.pt"),
}

DESCRIPTION = (
    "Long-horizon behaviour forecasting (Diller 2024, ch. 4, FutureHuman3D): the next M actions and their "
    "characteristic 3D poses from observed 2D poses and action labels."
)


def _cfg(sets: list[str]) -> BehaviourConfig:
    try:
        return config_from_dict(parse_sets(sets))
    except ValueError as err:
        raise InputError(str(err)) from None


def _main(argv: list[str] | None = None) -> int:
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    ap = argparse.ArgumentParser(prog="forecast behaviour", description=DESCRIPTION)
    sub = ap.add_subparsers(dest="cmd", required=True)
    keys = ", ".join(f.name for f in dataclasses.fields(BehaviourConfig) if f.name != "variant")
    t = sub.add_parser("train", help="build composite CMU activities, train the model and its ablations")
    t.add_argument("--out", required=True, help="checkpoint path (.pt)")
    t.add_argument(
        "--set", nargs="*", default=[], metavar="KEY=VALUE", help=f"config overrides; keys: {keys}"
    )
    t.add_argument("--variants", default=",".join(VARIANTS), help=f"comma list of {VARIANTS}")
    t.add_argument("--split-seed", type=int, default=0)
    t.add_argument(
        "--eval-split",
        choices=("val", "test", "none"),
        default="val",
        help="evaluate on this split after training (model choice on val; test once)",
    )
    t.add_argument("--json", default=None, help="write the evaluation as JSON here")
    t.add_argument(
        "--sessions",
        nargs="*",
        default=[],
        metavar="SESSION=LABELS",
        help="your own sessions with their label files, added to the training sequences",
    )
    e = sub.add_parser("eval", help="Table 4.1 / 4.2 and Fig. 4.3 on composite activities")
    e.add_argument("--checkpoint", default=str(SHIPPED))
    e.add_argument("--split", choices=("test", "val"), default="test")
    e.add_argument("--split-seed", type=int, default=0)
    e.add_argument("--out", default="results.json", help="results JSON (default results.json)")
    e.add_argument(
        "--quality-classifier",
        default=None,
        help="the 3D quality classifier (`forecast behaviour quality`; default the shipped one of the "
        "checkpoint's data, its `script`)",
    )
    e.add_argument(
        "--sessions",
        nargs="*",
        default=[],
        metavar="SESSION=LABELS",
        help="evaluate on these sessions and label files instead of the composite test split",
    )
    rkeys = ", ".join(f.name for f in dataclasses.fields(RefineConfig))
    e.add_argument(
        "--refine",
        action="store_true",
        help="also score every pose model after ch. 3's pose refinement (eq. 3.2; beyond ch. 4): the "
        "*_refined keys beside the raw figures",
    )
    e.add_argument(
        "--refine-set", nargs="*", default=[], metavar="KEY=VALUE", help=f"refinement settings; keys: {rkeys}"
    )
    s = sub.add_parser("sample", help="forecast the next M actions and 3D poses of every person of a session")
    s.add_argument("session", help="session folder with keypoints/, track/tracks.npz and calib/rig.toml")
    s.add_argument(
        "--labels", required=True, help="CSV track_id,start_s,end_s,label (s from the first frame)"
    )
    s.add_argument("--out", default=None, help="output .npz (default SESSION/forecast/behaviour.npz)")
    s.add_argument("--checkpoint", default=str(SHIPPED))
    s.add_argument(
        "--camera", default=None, help="observing camera (default: the one seeing each person best)"
    )
    s.add_argument("--model", default="full", help="variant of the checkpoint to use (default full)")
    q = sub.add_parser(
        "quality",
        help="train the 3D quality classifier once (sec. 4.7.7): database vs training-time poses",
    )
    q.add_argument("--out", required=True, help="classifier path (.pt)")
    q.add_argument(
        "--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides of the snapshot runs"
    )
    q.add_argument(
        "--variants",
        default=",".join(Q.POOL_VARIANTS),
        help=f"pose-predicting variants whose training snapshots join the fake pool ({Q.POOL_VARIANTS})",
    )
    q.add_argument(
        "--baselines",
        default=",".join(Q.POOL_BASELINES),
        help=f"baselines whose poses join the fake pool ({Q.POOL_BASELINES}; '' for none)",
    )
    q.add_argument("--every", type=int, default=200, help="collect a snapshot every this many steps")
    q.add_argument("--per-snapshot", type=int, default=625, help="training sequences predicted per snapshot")
    q.add_argument("--clf-steps", type=int, default=4000, help="classifier training steps (batches 2x256)")
    q.add_argument("--split-seed", type=int, default=0)
    argv = sys.argv[1:] if argv is None else list(argv)
    mg = sub.add_parser("merge", help="join checkpoints of variants trained apart (in parallel) into one")
    mg.add_argument("checkpoints", nargs="+")
    mg.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    args.argv = argv
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.cmd == "train":
        return _train(args)
    if args.cmd == "eval":
        return _eval(args)
    if args.cmd == "merge":
        return _merge(args)
    if args.cmd == "quality":
        return _quality(args)
    out = run_sample(
        args.session, args.labels, args.out, checkpoint=args.checkpoint, camera=args.camera, model=args.model
    )
    print(out)
    return 0


def _train(args) -> int:
    base = _cfg(args.set)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in variants if v not in VARIANTS]
    if bad or not variants:
        raise InputError(f"--variants: {bad or variants} - give a comma list of {VARIANTS}")
    t0 = time.perf_counter()
    sp = load_splits(base, args.split_seed, base.joint_names)
    print(
        f"composite sequences: train {len(sp.train)}, val {len(sp.val)}, test {len(sp.test)}; "
        f"3D database {len(sp.db)} poses; data {time.perf_counter() - t0:.0f} s"
    )
    if args.sessions:
        own = _session_windows(args.sessions, base)
        sp.train = concat([sp.train, own])
        print(f"added {len(own)} windows of {len(args.sessions)} sessions to the training sequences")
    logging.getLogger("roomcap.forecast.lab.behaviour.training").setLevel(logging.INFO)
    gens, cfgs, hists = {}, {}, {}
    with Bars(unit="step") as bars:
        for v in variants:
            cfg = dataclasses.replace(base, variant=v)
            c0 = time.process_time()
            gens[v], h = train(cfg, sp.train, sp.val, sp.db, bars)
            h["train_cpu_s"] = time.process_time() - c0
            h.pop("loss")
            cfgs[v], hists[v] = cfg, h
    extra = {
        "action_freq": action_frequencies(sp.train, base.n_obs).tolist(),
        "avg_pose": train_average(sp.train).tolist(),
        "history": hists,
        "command": "forecast behaviour " + " ".join(args.argv),
    }
    save_checkpoint(args.out, gens, cfgs, extra)
    print(
        f"wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.2f} MB); training "
        + ", ".join(
            f"{v} {h['train_wall_s']:.0f} s wall (best step {h.get('best_step')})" for v, h in hists.items()
        )
    )
    if args.eval_split == "none":
        return 0
    qm = _quality_model(str(QUALITY_OF_SCRIPT[base.script]), missing_ok=True)
    qc = (qm.clf, qm.joints) if qm is not None else None
    res = evaluate_all(gens, cfgs, extra, sp.val, getattr(sp, args.eval_split), sp.db, quality_clf=qc)
    res["split"] = args.eval_split
    res = as_results(res)
    print(render(res))
    if args.json:
        atomic_write_text(args.json, json.dumps(res, indent=1))
    return 0


def _merge(args) -> int:
    gens, cfgs, extra = {}, {}, {}
    for path in args.checkpoints:
        try:
            g, c, e = load_checkpoint(path)
        except (FormatError, FileNotFoundError) as err:
            raise InputError(str(err)) from None
        clash = sorted(set(g) & set(gens))
        if clash:
            raise InputError(f"{path}: holds {clash} again; give each variant once")
        if extra and e["avg_pose"] != extra["avg_pose"]:
            raise InputError(
                f"{path}: trained on other data than {args.checkpoints[0]} (another train average)"
            )
        hist = {**extra.get("history", {}), **e.get("history", {})}
        cmds = [c for c in (extra.get("command"), e.get("command")) if c]
        extra = {**e, "history": hist, "command": " ; ".join(cmds)}
        gens.update(g)
        cfgs.update(c)
    save_checkpoint(args.out, gens, cfgs, extra)
    print(f"wrote {args.out} ({Path(args.out).stat().st_size / 1e6:.2f} MB): {sorted(gens)}")
    return 0


def _quality_model(path: str, missing_ok: bool = False) -> Q.QualityModel | None:
    if missing_ok and not Path(path).exists():
        return None
    try:
        return Q.load(path)
    except FileNotFoundError:
        raise InputError(
            f"{path}: no 3D quality classifier; build one with `forecast behaviour quality --out FILE`"
        ) from None
    except FormatError as err:
        raise InputError(str(err)) from None


def _quality(args) -> int:
    base = _cfg(args.set)
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in variants if v not in Q.POOL_VARIANTS]
    if bad or not variants:
        raise InputError(f"--variants: {bad or variants} - give a comma list of {', '.join(Q.POOL_VARIANTS)}")
    baselines = [v.strip() for v in args.baselines.split(",") if v.strip()]
    bad = [v for v in baselines if v not in Q.POOL_BASELINES]
    if bad:
        raise InputError(f"--baselines: {bad} - give a comma list of {', '.join(Q.POOL_BASELINES)} or ''")
    if args.every < 1 or args.per_snapshot < 1 or args.clf_steps < 1:
        raise InputError("--every, --per-snapshot and --clf-steps must be positive")
    t0 = time.perf_counter()
    sp = load_splits(base, args.split_seed, base.joint_names)
    print(f"training sequences {len(sp.train)}; 3D database {len(sp.db)} poses")
    with Bars(unit="step") as bars:
        snaps, secs = Q.build_pool(base, variants, sp.train, sp.db, args.every, args.per_snapshot, bars)
    names = base.joint_names
    sources = dict(snaps)
    if "train_average" in baselines:
        sources["train_average"] = Q.train_average_snapshots(base, sp.train, args.every)
    fake, pooled = Q.pool_fakes(sources, seed=base.seed)
    real, held = Q.real_split(sp.db, names)
    q = Q.fit(real, fake, names, seed=base.seed, steps=args.clf_steps)
    avg = np.broadcast_to(np.asarray(train_average(sp.train), np.float32), (1, len(names), 3))
    checks = {
        "database_held_out": share_real(q.clf, held, names),
        "train_average_pose": share_real(q.clf, avg, names),
        **{
            f"{v}_step{st}": share_real(q.clf, p, names)
            for v, s in snaps.items()
            for st, p in (s[0], s[len(s) // 2], s[-1])
        },
    }
    q.meta.update(
        variants=variants,
        baselines=baselines,
        sources=pooled,
        snapshot_steps={v: [st for st, _ in s] for v, s in snaps.items()},
        poses_per_snapshot={v: len(s[0][1]) for v, s in snaps.items()},
        n_database_held_out=len(held),
        config=dataclasses.asdict(base),
        snapshot_cpu_s=secs,
        share_judged_real=checks,
        command="forecast behaviour " + " ".join(args.argv),
    )
    Q.save(args.out, q)
    print(
        f"fake pool {len(fake)} poses ("
        + ", ".join(f"{v} {len(s)} snapshots, {pooled[v]['n_poses']} poses" for v, s in sources.items())
        + f"; each source weighs {len(fake) // len(sources)} poses), "
        f"real pool {len(real)} (database even frames; class-balanced batches); "
        f"{time.perf_counter() - t0:.0f} s"
    )
    for k, v in checks.items():
        print(f"share judged real: {k:<28} {v:.3f}")
    print(f"wrote {args.out}")
    return 0


def _session_windows(pairs: list[str], cfg: BehaviourConfig):
    out = []
    for pair in pairs:
        sess, sep, lab = pair.partition("=")
        if not sep:
            raise InputError(
                f"--sessions {pair!r}: write SESSION=LABELS (a session folder and its label CSV)"
            )
        out.append(session_windows(sess, lab, cfg.n_obs, cfg.m, cfg.joint_names))
    return concat(out)


def _eval(args) -> int:
    try:
        gens, cfgs, extra = load_checkpoint(args.checkpoint)
    except (FormatError, FileNotFoundError) as err:
        raise InputError(str(err)) from None
    if not gens:
        raise InputError(f"{args.checkpoint}: holds no model; train one with `forecast behaviour train`")
    cfg = cfgs["full"] if "full" in gens else next(iter(cfgs.values()))
    other = sorted(n for n, c in cfgs.items() if (c.script, c.n_obs, c.m) != (cfg.script, cfg.n_obs, cfg.m))
    if other:
        raise InputError(
            f"{args.checkpoint}: {other} were trained on another script or n_obs / M than the rest; "
            "evaluate them apart"
        )
    if args.refine_set and not args.refine:
        raise InputError("--refine-set: give --refine too")
    try:
        refine = refine_config_from_dict(parse_sets(args.refine_set)) if args.refine else None
    except ValueError as err:
        raise InputError(f"--refine-set: {err}") from None
    sp = load_splits(cfg, args.split_seed, cfg.joint_names, with_train=False)
    c0 = time.process_time()
    test = _session_windows(args.sessions, cfg) if args.sessions else getattr(sp, args.split)
    if args.quality_classifier is None:
        args.quality_classifier = str(QUALITY_OF_SCRIPT[cfg.script])
    qm = _quality_model(args.quality_classifier)
    assert qm is not None
    res = evaluate_all(gens, cfgs, extra, sp.val, test, sp.db, quality_clf=(qm.clf, qm.joints), refine=refine)
    res["quality3d_classifier"] = {
        "path": str(args.quality_classifier),
        **{k: qm.meta.get(k) for k in ("n_real", "n_fake", "variants", "baselines", "sources", "seed")},
        # the compared pose models whose training did not feed the classifier's fake pool (sec. 4.7.7 pools
        # every compared model's)
        "not_in_pool": sorted(
            n
            for n, r in res["models"].items()
            if n != "true_3d"
            and r.get("symmetry_mm") is not None
            and n not in (qm.meta.get("sources") or qm.meta.get("variants") or ())
        ),
    }
    res.update(
        split="sessions" if args.sessions else args.split,
        checkpoint=str(args.checkpoint),
        eval_cpu_s=time.process_time() - c0,
    )
    res["train_wall_s"] = {n: h.get("train_wall_s") for n, h in extra.get("history", {}).items()}
    print(
        (
            f"{len(args.sessions)} sessions: {res['n_sequences']} windows"
            if args.sessions
            else f"{args.split} split: {res['n_sequences']} composite sequences"
        )
        + f", {res['n_obs']} observed + "
        f"M = {res['m']} forecast steps, {len(res['joints'])} joints"
    )
    res = as_results(res)
    print(render(res))
    atomic_write_text(args.out, json.dumps(res, indent=1))
    return 0


main = guarded("forecast behaviour", _main)
