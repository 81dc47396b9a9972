"""Train the GRU motion prior of eq. 5.1 on the CMU mocap in ``../shared/data/motion``.

    python -m roomcap.track.train_motion --out track/checkpoints/motion_gru.pt

Clips are read with :mod:`roomcap.synthetic.bvh` (body19, metres, z up) and resampled to the
tracking frame rate (``--fps``, default 25 as in the seed). Each step normalises the
pose at t-1 (eq. 5.2–5.5), feeds it and its last displacement to the GRU and regresses
the displacement to t (Huber loss, Adam, weight decay 1e-8 as in sec. 5.2.1). Inputs
are perturbed with Gaussian noise so the prior also pulls noisy particles back toward
plausible motion. Clips whose name ends with a digit in ``--val-suffix`` are held out; the
held-out one-step error of the GRU, a constant-velocity and a zero-velocity forecast is
printed and stored in the checkpoint.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch

from roomcap.core.cli import guarded
from roomcap.core.progress import Bars, Progress
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.synthetic.bvh import load_clips
from roomcap.track.motion import PoseGRU, save_checkpoint, step_inputs
from roomcap.track.normalize import rotate_vectors

log = logging.getLogger(__name__)


def load_motion(fps: float, root: str | None = None) -> tuple[list[np.ndarray], list[str]]:

    clips = [c for c in load_clips(fps, root, min_frames=8) if np.isfinite(c.xyz_m).all()]
    if not clips:
        raise FileNotFoundError(
            "no BVH clips found; set ROOMCAP_SHARED to the shared/ folder "
            "(mocap under shared/data/motion) or pass --mocap."
        )
    return [c.xyz_m.astype(np.float32) for c in clips], [c.name for c in clips]


def windows(clips: list[np.ndarray], length: int, stride: int) -> np.ndarray:
    """(B, length+2, J, 3) windows: two frames of history plus ``length`` targets."""
    w = [c[s : s + length + 2] for c in clips for s in range(0, len(c) - length - 2, stride)]
    return np.stack(w).astype(np.float32)


def mirror(x: np.ndarray) -> np.ndarray:
    """Left/right mirror (y -> -y, swap sides): doubles the data."""
    y = x[..., CANONICAL.flip_index, :].copy()
    y[..., 1] *= -1
    return y


def make_batch(w: np.ndarray, noise_m: float, rng: np.random.Generator) -> tuple[torch.Tensor, ...]:
    """Inputs (B,T,J*3) x 2 and targets (B,T,J*3) per model frame for windows w (B,T+2,J,3)."""
    prev = w[:, 1:-1] + rng.normal(0, noise_m, w[:, 1:-1].shape).astype(np.float32)
    prev2 = w[:, :-2] + rng.normal(0, noise_m, w[:, :-2].shape).astype(np.float32)
    x_hat, v_hat, _, theta = step_inputs(prev, prev2, 1.0, 1.0)
    target = rotate_vectors(w[:, 2:] - prev, theta).reshape(*w.shape[:1], w.shape[1] - 2, -1)
    return (
        torch.from_numpy(np.ascontiguousarray(x_hat)),
        torch.from_numpy(np.ascontiguousarray(v_hat)),
        torch.from_numpy(np.ascontiguousarray(target)),
    )


def evaluate(model: PoseGRU, w: np.ndarray, noise_m: float = 0.0) -> dict[str, float]:
    """Held-out one-step MPJPE (m, averaged over joints, last half of each window) for GRU, CV, ZV, with
    inputs perturbed by ``noise_m`` (particles are noisy poses)."""
    model.eval()
    x_hat, v_hat, target = make_batch(w, noise_m, np.random.default_rng(0))
    with torch.no_grad():
        pred = model.forward_sequence(x_hat, v_hat)
    T = pred.shape[1]
    half = slice(T // 2, T)

    def err(p):
        return float(torch.linalg.norm((p - target)[:, half].reshape(-1, 3), dim=-1).mean())

    out = {
        "gru_m": err(pred),
        "constant_velocity_m": err(v_hat),
        "zero_velocity_m": err(torch.zeros_like(pred)),
    }
    model.train()
    return out


def split_clips(
    clips: list[np.ndarray], names: list[str], val_suffix: str
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(train, validation) clips: a clip is held out when its name ends with a digit in ``val_suffix``
    (the last clip when none does)."""
    is_val = [n[-1] in val_suffix and len(clips) > 1 for n in names]
    train = [c for c, v in zip(clips, is_val, strict=True) if not v]
    val = [c for c, v in zip(clips, is_val, strict=True) if v] or clips[-1:]
    return train, val


def fit(
    model: torch.nn.Module,
    batch_loss,
    steps: int,
    lr: float,
    desc: str,
    progress: Progress | None,
    log_every: int,
) -> None:
    """Adam (weight decay 1e-8, sec. 5.2.1) with a cosine learning-rate schedule; ``batch_loss()`` draws a
    batch and returns its loss."""
    opt = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=1e-8)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    model.train()
    for step in range(steps):
        loss = batch_loss()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if progress is not None:
            progress(desc, step + 1, steps)
        if step % log_every == 0:
            log.info("step %d loss %.6f", step, loss.item())


def common_arguments(description: str, out: str) -> argparse.ArgumentParser:
    """The command-line options both trainers share (``--out --fps --seed --mocap --threads``)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--out", default=out)
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mocap", default=None, help="mocap folder (default: $ROOMCAP_SHARED/data/motion)")
    ap.add_argument("--threads", type=int, default=1)
    return ap


def report_written(out: str, info: dict) -> None:
    print(
        f"wrote {out}: "
        + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in info.items())
    )


def train(
    *,
    fps: float = 25.0,
    hidden: int = 64,
    dropout: float = 0.5,
    steps: int = 3000,
    batch: int = 64,
    length: int = 32,
    lr: float = 1e-3,
    noise_m: float = 0.005,
    seed: int = 0,
    val_suffix: str = "1",
    mocap: str | None = None,
    progress: Progress | None = None,
) -> tuple[PoseGRU, dict]:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    clips, names = load_motion(fps, mocap)
    tr, va = split_clips(clips, names, val_suffix)
    w_tr = windows(tr, length, 4)
    w_tr = np.concatenate([w_tr, mirror(w_tr)])
    w_va = windows(va, length, length)
    model = PoseGRU(CANONICAL.n_joints, hidden, dropout)
    loss_fn = torch.nn.HuberLoss(delta=0.01)

    def batch_loss() -> torch.Tensor:
        x_hat, v_hat, target = make_batch(w_tr[rng.integers(0, len(w_tr), batch)], noise_m, rng)
        pred = model.forward_sequence(x_hat, v_hat)
        return loss_fn(pred[:, 2:], target[:, 2:])  # the first steps have no useful hidden state yet

    t0 = time.perf_counter()
    fit(model, batch_loss, steps, lr, "train motion GRU", progress, log_every=500)
    metrics = evaluate(model, w_va)
    metrics.update({f"noisy_{k}": v for k, v in evaluate(model, w_va, 0.01).items()})
    info = {
        "fps": fps,
        "hidden": hidden,
        "dropout": dropout,
        "steps": steps,
        "batch": batch,
        "length": length,
        "lr": lr,
        "noise_m": noise_m,
        "seed": seed,
        "n_train_windows": int(len(w_tr)),
        "n_val_windows": int(len(w_va)),
        "train_s": time.perf_counter() - t0,
        "clips": int(len(clips)),
        **{f"val_{k}": v for k, v in metrics.items()},
    }
    return model.eval(), info


def _main(argv: list[str] | None = None) -> None:
    ap = common_arguments(__doc__.split("\n\n")[0], "track/checkpoints/motion_gru.pt")
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--dropout", type=float, default=0.5)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=64)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    torch.set_num_threads(a.threads)
    with Bars(unit="step") as bars:
        model, info = train(
            fps=a.fps,
            hidden=a.hidden,
            dropout=a.dropout,
            steps=a.steps,
            batch=a.batch,
            seed=a.seed,
            mocap=a.mocap,
            progress=bars,
        )
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(a.out, model, a.fps, CANONICAL, info)
    report_written(a.out, info)


main = guarded("python -m roomcap.track.train_motion", _main)


if __name__ == "__main__":
    sys.exit(main())
