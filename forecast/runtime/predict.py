"""World-space forecasting with any model: normalisation (eq. 3.8) in, inverse out, long rollouts.

``forecast_world(model, obs_xyz_m (B,T,P,J,3), person_mask (B,P), n_pred, n_samples)`` returns
``(B,S,n_pred,P,J,3)`` world metres. Single-person models see each person normalised at its own last
observed frame; Social Diffusion sees the scene (features in ``scene_features``) and generates the whole
horizon in one pass where it can (``diffusion_rollout``); chaining windows (observe ``n_obs``, generate
``n_frames - n_obs``, repeat) is the ablation, and the only way for models bound to their window length.
"""

from __future__ import annotations

import numpy as np
import torch

from roomcap.core.errors import InputError
from roomcap.forecast.runtime.normalise import LHIP, RHIP, denormalize, norm_frame, normalize
from roomcap.forecast.runtime.registry import forecasts_the_scene

# ----------------------------------------------------------------------------- scene features (ch. 7.2.3)


def scene_frame(last: np.ndarray, person_mask: np.ndarray, lhip: int = LHIP, rhip: int = RHIP):
    """Scene frame from the last observed frame last (B,P,J,3): heading of the first present person, root =
    mean of present roots on the floor (z = 0). -> R (B,3,3), root (B,3)."""
    B = last.shape[0]
    first = np.argmax(person_mask, 1)
    R, _ = norm_frame(last[np.arange(B), first], lhip, rhip)
    roots = 0.5 * (last[..., lhip, :] + last[..., rhip, :])
    m = person_mask[..., None].astype(np.float32)
    root = (roots * m).sum(1) / np.maximum(m.sum(1), 1)
    root[:, 2] = 0.0
    return R.astype(np.float32), root.astype(np.float32)


def scene_features(x: np.ndarray, anchor: int, lhip: int = LHIP, rhip: int = RHIP) -> np.ndarray:
    """x (...,T,J,3) in the scene frame -> (...,T,3J+10).

    Per frame: the hip-centric pose (3J), the root relative to the person's root at frame ``anchor`` (3) and
    the heading relative to the anchor heading (cos, sin); then, constant over time, the anchor root (3) and
    heading (cos, sin) in the scene frame. Motion is thus coded relative to the last observed frame (fine
    resolution after standardising) while the constant channels keep where people stand and face."""
    d = x[..., rhip, :] - x[..., lhip, :]
    th = np.arctan2(d[..., 1], d[..., 0])
    R, root = norm_frame(x, lhip, rhip)  # per frame
    local = np.einsum("...ij,...kj->...ki", R, x - root[..., None, :])
    r0, th0 = root[..., anchor : anchor + 1, :], th[..., anchor : anchor + 1]
    T = x.shape[-3]
    const = np.concatenate([r0, np.cos(th0)[..., None], np.sin(th0)[..., None]], -1)
    const = np.broadcast_to(const, (*const.shape[:-2], T, 5))
    dth = th - th0
    return np.concatenate(
        [local.reshape(*x.shape[:-2], -1), root - r0, np.cos(dth)[..., None], np.sin(dth)[..., None], const],
        -1,
    ).astype(np.float32)


def features_to_poses(f: np.ndarray, n_joints: int, anchor_const: np.ndarray | None = None) -> np.ndarray:
    """Inverse of scene_features: (...,T,3J+10) -> (...,T,J,3). ``anchor_const`` (...,5) replaces the
    constant channels (use the observed ones when decoding generated frames)."""
    J = n_joints
    local = f[..., : 3 * J].reshape(*f.shape[:-1], J, 3)
    const = f[..., 3 * J + 5 : 3 * J + 10] if anchor_const is None else anchor_const[..., None, :]
    r0, th0 = const[..., :3], np.arctan2(const[..., 4], const[..., 3])
    root = f[..., 3 * J : 3 * J + 3] + r0
    th = np.arctan2(f[..., 3 * J + 4], f[..., 3 * J + 3]) + th0
    c, s = np.cos(th), np.sin(th)
    x = c[..., None] * local[..., 0] - s[..., None] * local[..., 1]
    y = s[..., None] * local[..., 0] + c[..., None] * local[..., 1]
    return np.stack([x, y, local[..., 2]], -1) + root[..., None, :]


# ----------------------------------------------------------------------------- forecasting


def continue_velocity(y: np.ndarray, last: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """Forecasts y (B,S,H,...) shifted (every frame by the same offset, per coordinate) so that the first
    forecast frame continues the last observed velocity: y_1 = x_0 + (x_0 - x_-1). last, prev (B,...): the
    last two observed frames.

    The seed normalises at the last observed frame so that a forecast starts where the observation ends
    (Tanke eq. 3.8, sec. 7.2.3); our trained models still jump there: on CMU validation the first forecast
    frame lies 15-74 mm per joint from the last observed one (real 20 mm) in a direction unrelated to the
    observed motion (|velocity change| 20-81 mm against 11 mm real; ``bench/bench_forecast_trust.py``), and
    every later frame carries that jump. Removing it lowered validation MPJPE at 400 ms for every model
    (intention best-of-10 168 -> 159 mm, Social Diffusion 225 -> 187, GRU 4 s 225 -> 201) with NDMS unchanged
    (its words are root-centred velocities); a shift that fades out over 10-25 frames did less."""
    target = 2.0 * last - prev
    return y - (y[:, :, :1] - target[:, None, None])


def _device(model) -> torch.device:
    p = next(iter(model.parameters()), None)
    if p is None:
        b = next(iter(model.buffers()), None)
        return b.device if b is not None else torch.device("cpu")
    return p.device


@torch.no_grad()
def forecast_world(
    model,
    obs: np.ndarray,
    person_mask: np.ndarray | None,
    n_pred: int,
    n_samples: int = 1,
    hips: tuple[int, int] = (LHIP, RHIP),
    **sample_kw,
) -> np.ndarray:
    """obs (B,T,P,J,3) world metres (no NaN: fill first), person_mask (B,P) -> (B,S,n_pred,P,J,3).
    ``hips``: the skeleton's left/right hip indices (body19 by default) for the normalisation (eq. 3.8)."""
    obs = np.asarray(obs, np.float32)
    if obs.ndim != 5 or obs.shape[-1] != 3:
        raise InputError(f"obs must be (B,T,P,J,3), got {obs.shape}")
    B, T, P, J, _ = obs.shape
    pm = np.ones((B, P), bool) if person_mask is None else np.asarray(person_mask, bool)
    model.eval()
    dev = _device(model)
    if forecasts_the_scene(model):
        return _rollout_diffusion(model, obs, pm, n_pred, n_samples, dev, **sample_kw)
    flat = obs.transpose(0, 2, 1, 3, 4).reshape(B * P, T, J, 3)
    R, root = norm_frame(flat[:, -1], *hips)
    xn = normalize(flat, R, root).reshape(B * P, T, J * 3)
    y = model.sample(torch.from_numpy(xn).to(dev), n_pred, n_samples).cpu().numpy()  # (BP,S,H,D)
    if getattr(model, "continuity", False):
        y = continue_velocity(y, xn[:, -1], xn[:, -2])
    y = y.reshape(B * P, n_samples * n_pred, J, 3)
    yw = denormalize(y, R, root).reshape(B, P, n_samples, n_pred, J, 3)
    return yw.transpose(0, 2, 3, 1, 4, 5)


DIFFUSION_MODES = ("auto", "one_pass", "chained")


def diffusion_rollout(model, n_pred: int, mode: str = "auto") -> str:
    """How Social Diffusion covers ``n_pred`` frames: ``one_pass`` (the whole horizon in one window, as the
    seed's fully convolutional model) or ``chained`` (windows of the training length, each observing the
    last generated frames: the ablation). ``auto``: one pass where the model can (the horizon fits its window,
    or its statistics do not depend on the frame), else chained."""
    if mode not in DIFFUSION_MODES:
        raise InputError(f"diffusion mode must be one of {DIFFUSION_MODES}, got {mode!r}")
    if mode != "auto":
        return mode
    fits = int(model.n_obs) + n_pred <= int(model.n_frames)
    anylen = model.feat_mean.dim() == 1 or getattr(model, "lag_hold", False)
    return "one_pass" if fits or anylen else "chained"


def _rollout_diffusion(model, obs, pm, n_pred, n_samples, dev, steps=None, eta=None, mode="auto"):
    n_obs = int(model.n_obs)
    if obs.shape[1] < n_obs:
        raise InputError(f"Social Diffusion observes {n_obs} frames, got {obs.shape[1]}")
    steps = steps or int(model.sample_steps)
    eta = float(model.sample_eta if eta is None else eta)
    mode = diffusion_rollout(model, n_pred, mode)
    N = max(int(model.n_frames), -(-(n_obs + n_pred) // 16) * 16) if mode == "one_pass" else None
    B, _, P, J, _ = obs.shape
    ctx = np.repeat(obs[:, -n_obs:], n_samples, 0)  # (BS,n_obs,P,J,3)
    pms = np.repeat(pm, n_samples, 0)
    out = []
    done = 0
    while done < n_pred:
        R, root = scene_frame(ctx[:, -1], pms)
        xs = np.einsum("bij,btpkj->btpki", R, ctx - root[:, None, None, None])
        f = scene_features(xs.transpose(0, 2, 1, 3, 4), n_obs - 1)  # (BS,P,n_obs,F)
        gen = model.sample_window(
            torch.from_numpy(f).to(dev), torch.from_numpy(pms).to(dev), 1, steps, eta, n_frames=N
        )
        const = f[:, :, -1, 3 * J + 5 :]  # the observed anchor root and heading
        g = features_to_poses(gen[:, 0, :, n_obs:].cpu().numpy(), J, const)  # (BS,P,G,J,3) scene frame
        gw = np.einsum("bji,bptkj->btpki", R, g) + root[:, None, None, None]
        if getattr(model, "continuity", False):  # (BS,G,P,J,3): one sample per row
            gw = continue_velocity(gw[:, None], ctx[:, -1], ctx[:, -2])[:, 0]
        out.append(gw)
        done += gw.shape[1]
        ctx = np.concatenate([ctx, gw], 1)[:, -n_obs:]
    y = np.concatenate(out, 1)[:, :n_pred]
    return y.reshape(B, n_samples, n_pred, P, J, 3)
