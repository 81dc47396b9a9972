"""Social Diffusion (Tanke ch. 7): multi-person motion forecasting with a diffusion model.

- Cosine variance schedule (sec. 7.2.3, Nichol & Dhariwal), T diffusion steps; g predicts the clean
  sequence X_0 (eq. 7.3), trained with the L1 norm ||X_0 - g(X_t, t)|| (eq. 7.4).
- g: per person a causal temporal-convolution encoder e (4 layers, kernel 3, stride 2) and decoder d
  (4 layers, linear x2 upsampling + causal conv), the diffusion step fed to every layer through a
  sinusoidal encoding; an order-invariant mean over the people of the scene at the bottleneck
  (Γ_E, eq. 7.10) concatenated to each person's bottleneck (eq. 7.8). We add U-Net skips from the
  encoder to the decoder (the seed is silent; without them 64 frames through a 4-frame bottleneck lose
  detail on a CPU budget).
- Conditioning by inpainting (eq. 7.6): at every reverse step the observed frames are written back into
  the X_0 estimate before it is re-noised to the next step. Option ``clean_obs`` (default on): the observed
  frames also enter g clean, in training and sampling, and only the forecast frames are scored. Trained
  unconditionally (the seed), our small CPU model ignored the observation's position and heading
  (first-frame jumps of ~0.4 m at 20 or 100 steps, eta 0 or 1); with clean conditioning and features
  relative to the last observed frame (``predict.scene_features``) the jump is ~0.1 m.
  ``eta=1`` re-noises with fresh noise
  (the seed's sampler); ``eta=0`` reuses the predicted noise (DDIM), which allows few steps.
- Band-limited sampling (``sample_dct`` > 0, our addition): at every reverse step the X_0 estimate of the
  window is projected onto its first ``sample_dct`` DCT coefficients over time (in metres, before the
  observation is written back), as methods that diffuse in a truncated DCT space do. On CMU validation the
  samples' root moved ~2x faster frame to frame than real motion (0.83 vs 0.36 m/s; the hip-centric pose
  matched); 10 of 64 coefficients keep real windows to 2 cm RMS and raised validation NDMS 2-4 s by ~0.006.

Per-person features (sec. 7.2.3): the per-frame hip-centric pose (3J) ⊕ root (3) ⊕ (cos θ, sin θ) of the
global heading, in the scene frame, standardised with training mean/std (buffers in the checkpoint).

Continuity with the observation (``anchor``, default on): the seed normalises every sequence at the last
observed frame (sec. 7.2.3, as eq. 3.8) so the forecast starts where the observation ends. We carry that
into the standardisation: the motion channels (everything but the constant anchor channels, the last
``N_CONST``) are coded as offsets from the last observed frame and standardised *per frame* (mean/std of
the offset at that lag, buffers (N,F)). An error of a fixed size in standardised units is then a few
millimetres next to the observation and grows with the lag, as the spread of real motion does; with one
global std per channel the same error was ~8 cm at the first forecast frame (the measured jump). Per-lag
statistics bind the model to its window (longer horizons only by chaining windows); ``lag_stats = false``
keeps the anchored coding with one mean/std per channel shared over time (the seed's standardisation), so
the fully convolutional network generates any length in one pass (trained with a 144-frame
window, it samples 4 s and 10 s in one pass; CMU validation NDMS 2-4 s .247 against .250 for the chained
64-frame model).

``lag_hold`` (shipped CMU one-pass model): per-lag statistics, the last lag's past the window, so one pass
covers any horizon; why (shared statistics made root jitter): bench/bench_forecast_trust.py.

Root as velocity (``root_vel``, default off, our addition): the 3 root channels are coded as per-frame
displacements r[n] - r[n-1] (standardised per lag like the rest) instead of offsets from the anchor, and
decoded by summing from the anchor frame. An offset coding lets per-frame errors of the X_0 estimate
appear as frame-to-frame jitter of the root (samples' root 0.83 vs 0.36 m/s real on CMU validation);
coding displacements scores the root speed directly. Trained from scratch it brought the root speed to
0.42 m/s (real 0.35) but validation NDMS 2-4 s to 0.290 vs 0.309 for the shipped model: not shipped.

What holds NDMS at 2-3 s down (CMU validation, all 125 windows at stride 5, 10 samples, seeds 0/1):
not the root speed. NDMS (eq. 6.9-6.12) rewards coherent whole-body translation: scaling the samples' root
displacement to 0.5x / 0.3x / 0x lowers NDMS at 2 s from 0.320 to 0.275 / 0.253 / 0.215, and the real future
with its root frozen drops from 0.287 to 0.249; the GRU's root moves 2.1 m/s (real 0.28) and it scores above
the real future (0.318 vs 0.287 at 2 s). Not jitter either (smoothing the samples over time: +0.000) nor the
window chaining (with ``sample_dct`` = 0 there is no speed jump at the chunk starts; ``sample_dct`` = 10 makes
a 2 m/s first-frame jump, NDMS within ±0.01 either way). Sampler knobs (steps 10/20/50/100, eta 0/0.5/1,
sample_dct 0/6/10/16, initial-noise temperature 0.6/0.8) all move validation NDMS by ≤ 0.02, within noise,
except 100 steps at eta 1 (-0.05 at 2 s). The validation window mean is dominated by one clip (79 of the
125 windows), where Social Diffusion beats the GRU (0.349 vs 0.305 at 2 s); on the other three it is well
below (0.21-0.31 vs 0.32-0.37), and weighted per clip validation reproduces the test gap (2 s: 0.281 vs
0.334). The trainer's ``select = "ndms_2_3"`` weights clips equally. An EMA of the weights (``ema`` = 0.999,
22k steps from the shipped state) is stable on validation (0.282-0.289 every 2k steps) but below the shipped
state (clip-weighted 2/3 s 0.265/0.245 vs 0.281/0.249): not shipped. Continuing the shipped state 10k steps
(lr 2.5e-4, ``select = "ndms_2_3"``, sample_dct 0) picked step 3000, clip-weighted 2/3 s 0.275/0.287 and
0.275/0.281 (seeds 0/1) vs the shipped state's 0.272/0.274 and 0.280/0.267 with sample_dct 0: gains under
0.01, within the 0.23-0.28 spread of neighbouring states, so not shipped. The GRU: 0.334/0.295.
(The "shipped state" above is the checkpoint shipped before the mirrored-window training below.)

Then (same probe, clip-weighted 2 / 3 s): training on the left/right mirror of every window too (``mirror``,
trainer option, as the GRU and intention trainers do), from scratch, 12k steps, gave 0.297/0.281 and
0.301/0.272 (sampling seeds 0/1), the checkpoint shipped since; the same recipe with training seed 1 gave
0.268/0.269 and 0.274/0.267, and without the mirror 0.277/0.281: training seeds move the figure as much as
any change. Twice the channels fits better (MPJPE 0-1 s 283 vs 410 mm) and scores lower (0.278/0.252): the
better-fitting model moves less. Clips also played 1.25x and 0.8x as fast: 0.272/0.253. The seed's own
sampler (1000 steps, eta 1; Table 7.7), on 36 windows spread over the four clips: 0.268/0.261 against
0.273/0.266 for 20 DDIM steps. Where the GRU's lead comes from: its root speeds up to 2.7 m/s at 3 s and 4.6
m/s at 4 s (real 0.3; test FDE 35 m), coherent translation that NDMS rewards; the same GRU trained on the
4 s horizon it is evaluated at (``n_pred`` = 100, selected on MPJPE 0-1 s) stays put and scores 0.122/0.096,
below every stochastic model.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

N_CONST = 5  # the constant anchor channels at the end of the features (predict.scene_features)


def cosine_alpha_bar(T: int, s: float = 0.008) -> torch.Tensor:
    """ᾱ_t for t = 0..T (ᾱ_0 = 1), Nichol & Dhariwal's cosine schedule (clipped betas ≤ 0.999)."""
    t = torch.arange(T + 1, dtype=torch.float64) / T
    f = torch.cos((t + s) / (1 + s) * math.pi / 2) ** 2
    ab = f / f[0]
    beta = (1 - ab[1:] / ab[:-1]).clamp(max=0.999)
    return torch.cat([torch.ones(1, dtype=torch.float64), torch.cumprod(1 - beta, 0)]).float()


def dct_lowpass_matrix(n: int, keep: int) -> torch.Tensor:
    """(n,n) projection onto the first ``keep`` orthonormal DCT-II basis vectors over time (keep ≥ n: I).

    Real motion at 25 Hz is band-limited; diffusing in a truncated DCT space (Mao et al. 2019, HumanMAC,
    Chen et al. 2023: first 20 of 125 coefficients) keeps samples in that subspace."""
    k = torch.arange(n, dtype=torch.float64)
    basis = torch.cos(math.pi / n * (k[None] + 0.5) * k[:, None])  # (freq, time)
    basis[0] *= 1 / math.sqrt(2)
    basis *= math.sqrt(2 / n)
    b = basis[: min(keep, n)]
    return (b.T @ b).float()


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal encoding (eq. 3.23) of diffusion steps t (B,) -> (B,dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    a = t.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(a), torch.cos(a)], -1)


class _CausalConv(nn.Module):
    def __init__(self, cin: int, cout: int, k: int = 3, stride: int = 1):
        super().__init__()
        self.pad = k - 1
        self.conv = nn.Conv1d(cin, cout, k, stride=stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.pad(x, (self.pad, 0)))


class _Block(nn.Module):
    def __init__(self, cin: int, cout: int, temb: int, stride: int = 1):
        super().__init__()
        self.conv1 = _CausalConv(cin, cout, 3, stride)
        self.conv2 = _CausalConv(cout, cout, 3)
        self.t = nn.Linear(temb, cout)
        self.norm1 = nn.GroupNorm(8, cout)
        self.norm2 = nn.GroupNorm(8, cout)

    def forward(self, x: torch.Tensor, te: torch.Tensor) -> torch.Tensor:
        h = F.silu(self.norm1(self.conv1(x))) + self.t(te)[:, :, None]
        return h + F.silu(self.norm2(self.conv2(h)))


class SocialDiffusion(nn.Module):
    kind = "social_diffusion"
    stochastic = True

    def __init__(
        self,
        feat_dim: int,
        n_frames: int = 64,
        channels: int = 96,
        T: int = 1000,
        temb: int = 64,
        anchored: bool = False,
        lag_stats: bool = True,
    ):
        super().__init__()
        if n_frames % 16:
            raise ValueError(f"n_frames must be a multiple of 16 (4 stride-2 layers), got {n_frames}")
        self.feat_dim, self.n_frames, self.T, self.temb = feat_dim, n_frames, T, temb
        self.n_obs_clean = 0  # set from the config (clean_obs): observed frames fed clean to g
        self.anchor: int | None = None  # set from the config (anchor): index of the last observed frame
        self.sample_dct = 0  # set from the config: low-pass the X_0 estimate to this many DCT coefficients
        self.sample_temp = 1.0  # set from the config: scale of the sampling noise (temperature)
        self.root_vel = False  # set from the config (root_vel): root channels coded as per-frame velocity
        self.lag_hold = False  # set from the config (lag_hold): per-lag statistics held past the window
        self.register_buffer("alpha_bar", cosine_alpha_bar(T))
        # per-lag statistics (anchored, ``lag_stats``) tie the model to its window length; one mean/std per
        # channel shared over time (the seed's standardisation) lets it generate any length in one pass
        shape = (n_frames, feat_dim) if anchored and lag_stats else (feat_dim,)
        self.register_buffer("feat_mean", torch.zeros(shape))
        self.register_buffer("feat_std", torch.ones(shape))
        C = channels
        self.t_mlp = nn.Sequential(nn.Linear(temb, temb), nn.SiLU(), nn.Linear(temb, temb))
        self.inp = nn.Conv1d(feat_dim, C, 1)
        self.enc = nn.ModuleList([_Block(C, C, temb, stride=2) for _ in range(4)])
        self.mix = nn.Conv1d(2 * C, C, 1)  # h^i ⊕ Γ({h^j})
        self.dec = nn.ModuleList([_Block(2 * C, C, temb) for _ in range(4)])
        self.out = nn.Conv1d(C, feat_dim, 1)

    def g(self, x_t: torch.Tensor, t: torch.Tensor, person_mask: torch.Tensor) -> torch.Tensor:
        """Eq. 7.3: x_t (B,P,N,F) standardised, t (B,), person_mask (B,P) -> X̂_0 (B,P,N,F)."""
        B, P, N, Fd = x_t.shape
        te = self.t_mlp(timestep_embedding(t, self.temb)).repeat_interleave(P, 0)
        h = self.inp(x_t.reshape(B * P, N, Fd).transpose(1, 2))
        skips = []
        for blk in self.enc:  # eq. 7.7
            skips.append(h)
            h = blk(h, te)
        m = person_mask.float().reshape(B, P, 1, 1)
        hb = h.view(B, P, *h.shape[1:])
        gamma = (hb * m).sum(1, keepdim=True) / m.sum(1, keepdim=True).clamp(min=1)  # Γ_E (7.10)
        h = self.mix(torch.cat([hb, gamma.expand_as(hb)], 2).flatten(0, 1))
        for blk, skip in zip(self.dec, reversed(skips), strict=True):  # eq. 7.8
            h = F.interpolate(h, scale_factor=2, mode="linear", align_corners=False)
            h = blk(torch.cat([h, skip], 1), te)
        return self.out(h).transpose(1, 2).reshape(B, P, N, Fd)

    def loss(
        self, x0: torch.Tensor, person_mask: torch.Tensor, valid: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Eq. 7.4 (L1) for standardised x0 (B,P,N,F); valid (B,P,N) masks unknown frames.

        With ``n_obs_clean`` > 0 the first frames enter x_t clean (the observation, as at sampling time) and
        only the frames after them are scored."""
        B = x0.shape[0]
        t = torch.randint(1, self.T + 1, (B,), device=x0.device)
        ab = self.alpha_bar[t].view(B, 1, 1, 1)
        x_t = ab.sqrt() * x0 + (1 - ab).sqrt() * torch.randn_like(x0)
        k = self.n_obs_clean
        if k:
            x_t = torch.cat([x0[:, :, :k], x_t[:, :, k:]], 2)
        err = (self.g(x_t, t, person_mask) - x0).abs().mean(-1)
        w = person_mask[:, :, None].float().expand_as(err).clone()
        if k:
            w[:, :, :k] = 0
        if valid is not None:
            w = w * valid.float()
        return (err * w).sum() / w.sum().clamp(min=1)

    def relative(self, f: torch.Tensor, anchor_feat: torch.Tensor, sign: float = -1.0) -> torch.Tensor:
        """Motion channels of f (...,N',F) minus (sign -1) or plus (+1) those of anchor_feat (...,F)."""
        k = self.feat_dim - N_CONST
        return torch.cat([f[..., :k] + sign * anchor_feat[..., None, :k], f[..., k:]], -1)

    def code(self, f: torch.Tensor, anchor_feat: torch.Tensor) -> torch.Tensor:
        """Anchored coding of raw features f (...,N',F): motion channels minus the anchor frame's
        (``relative``); with ``root_vel`` the root channels (3) then become per-frame displacements
        r[n] - r[n-1] (frame 0: 0), lossless because the root offset is 0 at the anchor frame."""
        c = self.relative(f, anchor_feat)
        if not self.root_vel:
            return c
        i = self.feat_dim - 10  # root offset channels (predict.scene_features): 3J .. 3J+3
        r = c[..., i : i + 3]
        v = torch.cat([torch.zeros_like(r[..., :1, :]), r[..., 1:, :] - r[..., :-1, :]], -2)
        return torch.cat([c[..., :i], v, c[..., i + 3 :]], -1)

    def decode(self, c: torch.Tensor, anchor_feat: torch.Tensor) -> torch.Tensor:
        """Inverse of ``code``: with ``root_vel`` the root offsets are summed from the anchor frame (offset 0)
        forwards and backwards, so forecast frames depend only on forecast displacements."""
        if self.root_vel:
            i = self.feat_dim - 10
            v = c[..., i : i + 3]
            a = self.anchor
            cs = torch.cumsum(v, -2)  # cs[n] = sum_{k<=n} v[k];  r[n] = cs[n] - cs[a]
            r = cs - cs[..., a : a + 1, :]
            c = torch.cat([c[..., :i], r, c[..., i + 3 :]], -1)
        return self.relative(c, anchor_feat, +1.0)

    def _stats(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and std for n frames from the window start: per lag (rows :n) or shared over time; with
        ``lag_hold`` frames past the training window take the last lag's (a bound, not a fit)."""
        if self.feat_mean.dim() == 1:
            return self.feat_mean, self.feat_std
        rows = self.feat_mean.shape[0]
        if n <= rows:
            return self.feat_mean[:n], self.feat_std[:n]
        if not self.lag_hold:
            raise ValueError(f"per-lag statistics cover {rows} frames, asked for {n}")
        pad = n - rows
        return (
            torch.cat([self.feat_mean, self.feat_mean[-1:].expand(pad, -1)]),
            torch.cat([self.feat_std, self.feat_std[-1:].expand(pad, -1)]),
        )

    def standardise(self, f: torch.Tensor) -> torch.Tensor:
        """Raw features (...,N',F) from the window start (N' ≤ n_frames for per-lag statistics) ->
        standardised; anchored models code motion relative to the anchor frame first (``code``)."""
        mean, std = self._stats(f.shape[-2])
        if self.anchor is None:
            return (f - mean) / std
        return (self.code(f, f[..., self.anchor, :]) - mean) / std

    def unstandardise(self, f: torch.Tensor, anchor_feat: torch.Tensor | None = None) -> torch.Tensor:
        """Inverse of standardise; anchored models need the raw features of the anchor frame (...,F)."""
        mean, std = self._stats(f.shape[-2])
        if self.anchor is None:
            return f * std + mean
        return self.decode(f * std + mean, anchor_feat)

    @torch.no_grad()
    def sample_window(
        self,
        obs: torch.Tensor,
        person_mask: torch.Tensor,
        n_samples: int = 1,
        steps: int | None = None,
        eta: float = 1.0,
        generator: torch.Generator | None = None,
        n_frames: int | None = None,
    ) -> torch.Tensor:
        """Complete one window. obs (B,P,n_obs,F) raw features (n_obs < n_frames) -> (B,S,P,N,F) raw features
        with the first n_obs frames equal to obs (eq. 7.6). ``steps`` ≤ T reverse steps (strided).

        ``n_frames`` (a multiple of 16) other than the training window: the network is fully convolutional in
        time (sec. 7.2.2, "sequences of arbitrary size"), so a whole horizon is generated in one pass; models
        with per-lag feature statistics (``lag_stats``) only know their training window's length."""
        B, P, n_obs, Fd = obs.shape
        N = self.n_frames if n_frames is None else int(n_frames)
        if N != self.n_frames:
            if N % 16:
                raise ValueError(f"n_frames must be a multiple of 16 (4 stride-2 layers), got {N}")
            if self.feat_mean.dim() != 1 and not (self.lag_hold and N > self.n_frames):
                raise ValueError(
                    f"this Social Diffusion model keeps per-frame statistics for its {self.n_frames}-frame "
                    f"window and cannot generate {N} frames in one pass; train it with n_frames >= the "
                    "horizon "
                    "or use the chained-window ablation"
                )
        steps = steps or self.T
        o = self.standardise(obs).repeat_interleave(n_samples, 0)
        pm = person_mask.repeat_interleave(n_samples, 0)
        BS = B * n_samples
        ts = torch.linspace(self.T, 1, steps, device=obs.device).round().long()
        lowpass = None
        if 0 < self.sample_dct < N:  # band-limit X_0 (dct_lowpass_matrix) in metres, not per-lag units
            lowpass = dct_lowpass_matrix(N, self.sample_dct).to(obs.device)
            mean, std = (a if a.dim() == 2 else a.expand(N, Fd) for a in self._stats(N))
        # temperature (sample_temp): the noise the reverse process starts from (and re-noises with, eta > 0)
        # scaled; > 1 spreads the samples. On CMU validation 0.8 / 1 / 1.2 gave NDMS own-clip-left-out 2 s
        # .150 / .176 / .208 with best-of-10 MPJPE at 400 ms unchanged (187 / 187 / 188 mm)
        temp = float(self.sample_temp)
        x = temp * torch.randn(BS, P, N, Fd, device=obs.device, generator=generator)
        x0 = x
        for i, t in enumerate(ts):
            tt = t.expand(BS)
            if self.n_obs_clean:  # the observation enters clean, as in training
                x = torch.cat([o, x[:, :, n_obs:]], 2)
            x0 = self.g(x, tt, pm)
            x0 = torch.cat([o, x0[:, :, n_obs:]], 2)  # write back the observation
            if lowpass is not None:  # project the whole window onto low frequencies, observation back on top
                xl = torch.einsum("nm,bpmf->bpnf", lowpass, x0 * std + mean)
                x0 = torch.cat([o, ((xl - mean) / std)[:, :, n_obs:]], 2)
            if i == len(ts) - 1:
                break
            ab, ab_next = self.alpha_bar[t], self.alpha_bar[ts[i + 1]]
            eps_hat = (x - ab.sqrt() * x0) / (1 - ab).sqrt().clamp(min=1e-6)
            noise = temp * torch.randn(x.shape, device=x.device, generator=generator)
            e = math.sqrt(1 - eta**2) * eps_hat + eta * noise
            x = ab_next.sqrt() * x0 + (1 - ab_next).sqrt() * e
        anchor = obs[:, :, -1].repeat_interleave(n_samples, 0) if self.anchor is not None else None
        if anchor is not None and self.anchor != n_obs - 1:
            raise ValueError(
                f"this model is anchored at frame {self.anchor}, the observation has {n_obs} frames"
            )
        return self.unstandardise(x0, anchor).view(B, n_samples, P, N, Fd)
