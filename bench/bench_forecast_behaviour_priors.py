"""Behaviour forecaster (Diller ch. 4): what two priors built from the uncorrelated 3D database do to the
two 3D targets (3D MPJPE below the train average, 3D quality), on the VALIDATION split only.

1. **Lifted depth** (post hoc): an MLP trained on the database alone (random heading, the training views'
   cameras) maps a pose's plane features (``geometry.plane_of_3d``) to each joint's depth behind the pelvis.
   Applied to a checkpoint's forecasts, every joint moves along its camera ray to the lifted depth, so the
   projected 2D (and the 2D MPJPE) stays exactly as it was. Also: the truth itself lifted (the lifter's own
   error) and the forecasts scaled along the rays to the person's true size (an oracle).
2. **Pose prior decoder** (``pose_decoder=prior``, ``model.PosePrior``): the pose decoder outputs a code for a
   frozen VAE decoder trained on the database's canonical poses, a heading, the pelvis and a size. Trained as
   ``full`` with the checkpoint's other settings (``--set`` changes them); with ``--own-classifier`` the
   quality classifier is rebuilt from the prior model's own snapshot runs (sec. 4.7.7, as ``forecast
   behaviour quality`` does), since a classifier that never saw a setting's snapshots overrates it.
3. With ``--supervised-3d``, a diagnostic the method may not use: the same generator trained on the
   sequences' true 3D, i.e. what the architecture reaches in 3D when it sees 3D.

The 3D error is split by axis of the viewer frame (x right, y away from the camera, z up).

    .venv/bin/python bench/bench_forecast_behaviour_priors.py [--checkpoint FILE] [--prior-steps 3000]
        [--set KEY=VALUE ...] [--own-classifier] [--skip-prior] [--supervised-3d]

Needs the CMU mocap (ROOMCAP_SHARED). Torch on one thread. Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import torch
from torch import nn

from roomcap.core.cli import parse_sets
from roomcap.forecast.lab.behaviour import model as M
from roomcap.forecast.lab.behaviour import quality as Q
from roomcap.forecast.lab.behaviour import training as T
from roomcap.forecast.lab.behaviour.data import JOINTS
from roomcap.forecast.lab.behaviour.geometry import plane_of_3d

J = len(JOINTS)
PELVIS = JOINTS.index("pelvis")


def _plane_input(P: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """The lifter's input: pelvis-relative plane features (n,J*2) and the camera's distance and height."""
    q = plane_of_3d(P, c)
    q = q - q[:, PELVIS : PELVIS + 1]
    return torch.cat([q.reshape(len(P), -1), torch.stack([c[:, 1].abs(), c[:, 2]], 1) / 5.0], 1)


def train_lifter(db: np.ndarray, cams: np.ndarray, steps: int = 4000, seed: int = 0) -> nn.Module:
    """Depth behind the pelvis of each joint from the plane features, trained on database poses only."""
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    X, C = torch.from_numpy(db), torch.from_numpy(cams.astype(np.float32))
    net = M._mlp(J * 2 + 2, 256, 256, 256, J)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(steps):
        P = T._random_yaw(X[torch.randint(len(X), (512,), generator=g)], g)
        c = C[torch.randint(len(C), (512,), generator=g)]
        loss = ((net(_plane_input(P, c)) - (P[..., 1] - P[:, PELVIS : PELVIS + 1, 1])) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net.eval()


def along_rays(P: torch.Tensor, c: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """Poses P (n,J,3) with each joint moved along its ray from the camera c (n,3) to ``depth`` (n,J): the
    same projection, another depth."""
    q = plane_of_3d(P, c)
    on_plane = torch.stack([q[..., 0], torch.zeros_like(q[..., 0]), q[..., 1]], -1)
    cc = c[:, None]
    s = (depth - cc[..., 1]) / (on_plane[..., 1] - cc[..., 1])
    return cc + s[..., None] * (on_plane - cc)


def lifted(lifter: nn.Module, P: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return along_rays(P, c, P[:, PELVIS : PELVIS + 1, 1] + lifter(_plane_input(P, c)))


def _bone_sum(P: torch.Tensor) -> torch.Tensor:
    b = torch.as_tensor(M.bones(JOINTS))
    return (P[:, b[:, 0]] - P[:, b[:, 1]]).norm(dim=-1).sum(-1)


def errors(P: np.ndarray, d: T.Prepared) -> dict:
    """3D MPJPE (mm, pelvis-centred), by step, mean absolute error by viewer axis, and where the poses put
    the pelvis in depth (mean, s.d., metres behind the anchor)."""
    e = P - P[:, :, PELVIS : PELVIS + 1] - (d.tgt_3d - d.tgt_3d[:, :, PELVIS : PELVIS + 1])
    return {
        "mpjpe3d_mm": float(np.linalg.norm(e, axis=-1).mean() * 1000),
        "by_step": (np.linalg.norm(e, axis=-1).mean((0, 2)) * 1000).round(1).tolist(),
        "abs_by_axis_mm": (np.abs(e).mean((0, 1, 2)) * 1000).round(1).tolist(),
        "pelvis_depth_m": [float(P[..., PELVIS, 1].mean()), float(P[..., PELVIS, 1].std())],
    }


def train_3d_supervised(
    cfg: M.BehaviourConfig, tr: T.Prepared, va: T.Prepared, db: np.ndarray
) -> M.Generator:
    """A diagnostic the method may not use: the same generator trained on the sequences' true 3D (MSE of
    the pelvis-centred poses) and the action loss, the state with the lowest val 3D error kept. It shows
    what this architecture reaches in 3D when it sees 3D."""
    f = T._fit_state(cfg, db)
    best, state = np.inf, None
    for step in range(1, cfg.steps + 1):
        idx = torch.randint(len(tr), (cfg.batch,), generator=f.g).numpy()
        tb = T.to_torch(tr, idx, cfg.n_obs)
        f.gen.train()
        lg, P = M.rollout(
            f.gen, tb["feats"], tb["obs_acts"], tb["seen"], tb["view"]["c"], cfg.m, room=tb["room"]
        )
        tgt = torch.from_numpy(tr.tgt_3d[idx])
        e = (P - P[..., PELVIS : PELVIS + 1, :]) - (tgt - tgt[..., PELVIS : PELVIS + 1, :])
        loss = (
            nn.functional.cross_entropy(lg.reshape(-1, lg.shape[-1]), tb["tgt_acts"].reshape(-1))
            + (e**2).sum(-1).mean() / 0.01
        )
        f.og.zero_grad()
        loss.backward()
        f.og.step()
        if step % cfg.eval_every == 0:
            f.gen.eval()
            e3 = errors(T.predict(f.gen, cfg, va)[1], va)["mpjpe3d_mm"]
            if e3 < best:
                best, state = e3, {k: v.clone() for k, v in f.gen.state_dict().items()}
    f.gen.load_state_dict(state)
    return f.gen.eval()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default=str(M.SHIPPED))
    ap.add_argument("--prior-steps", type=int, default=3000)
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="the prior model's other settings (prior_dim=48)",
    )
    ap.add_argument("--own-classifier", action="store_true")
    ap.add_argument("--skip-prior", action="store_true")
    ap.add_argument("--supervised-3d", action="store_true", help="also the 3D-supervised diagnostic")
    a = ap.parse_args()
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    gens, cfgs, extra = M.load_checkpoint(a.checkpoint)
    base = cfgs["full"]
    sp = T.load_splits(base, 0, JOINTS)
    va = sp.val
    S, m = va.tgt_3d.shape[:2]
    shipped = Q.load(str(Q.QUALITY_SHIPPED)).clf
    avg = np.broadcast_to(np.asarray(extra["avg_pose"], np.float32), (S, m, J, 3)).copy()
    out: dict = {"split": "val", "checkpoint": a.checkpoint, "train_average": errors(avg, va)}
    out["train_average"]["mpjpe2d_px"] = T.metrics(None, avg, va, base.n_obs)["mpjpe2d_px"]
    print(f"train average: 3D {out['train_average']['mpjpe3d_mm']:.0f} mm, by axis {out['train_average']}")

    lifter = train_lifter(sp.db, sp.train.view.c)
    c = torch.from_numpy(va.view.c.astype(np.float32))[:, None].expand(S, m, 3).reshape(-1, 3)
    truth = torch.from_numpy(va.tgt_3d).reshape(-1, J, 3)
    out["truth_lifted"] = errors(lifted(lifter, truth, c).reshape(S, m, J, 3).numpy(), va)
    out["truth_quality_shipped"] = T.share_real(shipped, truth.numpy(), JOINTS)
    out["truth_pelvis_depth_m"] = [
        float(va.tgt_3d[..., PELVIS, 1].mean()),
        float(va.tgt_3d[..., PELVIS, 1].std()),
    ]
    print(f"the truth's depth lifted (the lifter's own error): {out['truth_lifted']}")
    for n in ("full", "pose_only"):
        _, ps = T.predict(gens[n], cfgs[n], va)
        P = torch.from_numpy(ps).reshape(-1, J, 3)
        L = lifted(lifter, P, c)
        sized = lifted(
            lifter, c[:, None] + (_bone_sum(truth) / _bone_sum(L))[:, None, None] * (L - c[:, None]), c
        )
        r = {}
        for k, X in (("as_trained", P), ("lifted_depth", L), ("lifted_true_size_oracle", sized)):
            Xn = X.reshape(S, m, J, 3).numpy()
            r[k] = errors(Xn, va) | {
                "mpjpe2d_px": T.metrics(None, Xn, va, base.n_obs)["mpjpe2d_px"],
                "quality_shipped_classifier": T.share_real(shipped, Xn.reshape(-1, J, 3), JOINTS),
            }
            print(f"{n} {k}: {r[k]}")
        out[n] = r

    if a.supervised_3d:
        w0 = time.perf_counter()
        gen = train_3d_supervised(base, sp.train, va, sp.db)
        pr, ps = T.predict(gen, base, va)
        r = errors(ps, va) | {
            "mpjpe2d_px": T.metrics(pr, ps, va, base.n_obs)["mpjpe2d_px"],
            "top1": T.metrics(pr, ps, va, base.n_obs)["top1"],
            "quality_shipped_classifier": T.share_real(shipped, ps.reshape(-1, J, 3), JOINTS),
            "train_wall_s": time.perf_counter() - w0,
        }
        print(f"3D-supervised diagnostic (sees the true 3D): {r}")
        out["supervised_3d"] = r

    if not a.skip_prior:
        cfg = M.config_from_dict(
            {**dataclasses.asdict(base), "pose_decoder": "prior", "steps": a.prior_steps, **parse_sets(a.set)}
        )
        w0 = time.perf_counter()
        gen, hist = T.train(cfg, sp.train, va, sp.db)
        pr, ps = T.predict(gen, cfg, va)
        r = errors(ps, va) | {
            "mpjpe2d_px": T.metrics(pr, ps, va, cfg.n_obs)["mpjpe2d_px"],
            "top1": T.metrics(pr, ps, va, cfg.n_obs)["top1"],
            "quality_shipped_classifier": T.share_real(shipped, ps.reshape(-1, J, 3), JOINTS),
            "best_step": hist.get("best_step"),
            "train_wall_s": time.perf_counter() - w0,
            "settings": parse_sets(a.set),
        }
        if a.own_classifier:
            w0 = time.perf_counter()
            snaps, _ = Q.build_pool(
                dataclasses.replace(cfg, seed=1), ["full", "pose_only"], sp.train, sp.db, 200, 625
            )
            fake = np.concatenate([p for s in snaps.values() for _, p in s]).astype(np.float32)
            real, held = Q.real_split(sp.db, JOINTS)
            own = Q.fit(real, fake, JOINTS, seed=1, steps=4000).clf
            r["quality_own_classifier"] = T.share_real(own, ps.reshape(-1, J, 3), JOINTS)
            r["quality_own_classifier_by_step"] = [T.share_real(own, ps[:, k], JOINTS) for k in range(m)]
            r["own_classifier_truth"] = T.share_real(own, truth.numpy(), JOINTS)
            r["own_classifier_database_held_out"] = T.share_real(own, held, JOINTS)
            r["own_classifier_wall_s"] = time.perf_counter() - w0
        print(f"pose prior decoder: {r}")
        out["pose_prior"] = r
    out["wall_s"] = time.perf_counter() - t0
    print("BENCH " + json.dumps(out))


if __name__ == "__main__":
    main()
