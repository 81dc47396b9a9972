"""Characteristic 3D pose forecaster (Diller 2024, ch. 3): attention, volumetric heatmaps, autoregressive
sampling.

A compact, CPU-trainable version of sec. 3.3-3.5 and the appendix (Fig. 3.10):

* Encoder (sec. 3.4): a single-layer GRU over the N observed poses (each frame flattened, J x 3); its N hidden
  states are the attention nodes, and every already predicted joint adds one node (its 3D location and
  identity), so the attention map is J' x (N + n_p) as in the text.
* Attention (eq. 3.1): scaled dot-product attention with Q, K, V projections shared by all joints; the query
  of an output joint is a learned joint embedding. Result: one feature per joint to predict.
* Decoder (sec. 3.4): per output joint, a small 3D-conv decoder (4^3 -> 8^3 -> grid^3, five 3D convolutions
  instead of the seed's nine, for the CPU) predicting the heatmap H_j as ``n_discr`` bin logits per voxel
  (values discretised in [0, 1], cross-entropy) and a per-voxel offset field O_j clamped to one voxel length.
  A volume made from the last input skeleton (relative position of every voxel to the joint's last observed
  location) is concatenated before the last convolutions (the appendix's "offsets volume generated from the
  last input skeleton"). The grid is centred at the hips and spans ``span`` metres (seed: 16^3 voxels over 2
  m).
* Autoregression (sec. 3.5, Fig. 3.4): right wrist first, then the left wrist conditioned on it, then the
  rest of the body conditioned on both; heatmaps are sharpened by a softmax with temperature 0.025 and
  sampled. Teacher forcing in training.
* Pose refinement (eq. 3.2) with the seed's weights w_e = 0.2, w_b = 1.0, w_a = 0.4, w_h = 0.1, w_c = 0.1.

``DeterministicCharacteristic`` is the seed's "Deterministic" ablation (Tab. 3.3): the same backbone with an
MLP head regressing each joint's offset from its last observed position.

Poses are hip-centred and normalised as in ``forecast.characteristic`` (eq. 3.8 at the last observed frame).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

REFINE_WEIGHTS = {"w_e": 0.2, "w_b": 1.0, "w_a": 0.4, "w_h": 0.1, "w_c": 0.1}  # eq. 3.2, sec. 3.5


# ----------------------------------------------------------------------------- the heatmap grid (sec. 3.4)


def voxel_centres(grid: int, span: float) -> torch.Tensor:
    """(grid,) coordinates of voxel centres along one axis (metres, grid centred at the hips)."""
    vs = span / grid
    return -span / 2 + (torch.arange(grid, dtype=torch.float32) + 0.5) * vs


def target_heatmap(y: torch.Tensor, grid: int, span: float, sigma_vox: float = 2.0, radius: int = 2):
    """Gaussian target heatmaps (sec. 3.4.1: kernel size 5 = radius 2 voxels, sigma = 2 voxels) for points y
    (M,3) -> (M,grid,grid,grid) values in [0, 1] (1 at the point), zero outside the kernel around the nearest
    voxel. Points outside the grid are clamped to it."""
    vs = span / grid
    c = voxel_centres(grid, span).to(y)
    half = span / 2 - 1e-4
    y = y.clamp(-half, half)
    idx = torch.floor((y + span / 2) / vs).long().clamp(0, grid - 1)  # nearest voxel (M,3)
    ar = torch.arange(grid, device=y.device)
    d = (c[None, None] - y[:, :, None]) / vs  # (M,3,grid) distance in voxels per axis
    inside = (ar[None, None] - idx[:, :, None]).abs() <= radius
    g = torch.exp(-(d**2) / (2 * sigma_vox**2)) * inside
    return g[:, 0, :, None, None] * g[:, 1, None, :, None] * g[:, 2, None, None, :]


def discretise(h: torch.Tensor, n_discr: int) -> torch.Tensor:
    """Heatmap values in [0,1] -> bin indices 0..n_discr-1 (sec. 3.4: n_discr bins in [0, 1])."""
    return torch.clamp((h * n_discr).long(), 0, n_discr - 1)


def bin_values(n_discr: int) -> torch.Tensor:
    """Heatmap value of each bin for expectations: bin centres, the no-probability bin 0 counts as 0."""
    v = (torch.arange(n_discr, dtype=torch.float32) + 0.5) / n_discr
    v[0] = 0.0
    return v


def class_weights(grid: int, span: float, n_discr: int, n: int = 256, seed: int = 0) -> torch.Tensor:
    """Sec. 3.10.5: classes weighted by the inverse of their log-scaled occurrence (here 1/log(2 + mean count
    per volume) over random target positions), 0.1 for the no-probability bin 0."""
    g = torch.Generator().manual_seed(seed)
    y = (torch.rand(n, 3, generator=g) - 0.5) * span * 0.5
    b = discretise(target_heatmap(y, grid, span), n_discr)
    counts = torch.bincount(b.flatten(), minlength=n_discr).float() / n
    w = 1.0 / torch.log(2.0 + counts)
    w[0] = 0.1
    return w


# ----------------------------------------------------------------------------- backbone (sec. 3.4, eq. 3.1)


class Backbone(nn.Module):
    """Single-layer GRU over the observed frames + scaled dot-product attention (eq. 3.1) with the prior
    joints as extra nodes. ``features(obs, prior_xyz, prior_ids, query_ids) -> (B,J',dim)``."""

    def __init__(self, n_joints: int, n_obs: int, hidden: int = 128, dim: int = 64, heads: int = 4):
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} must be a multiple of heads {heads}")
        self.n_joints, self.n_obs, self.dim, self.heads = n_joints, n_obs, dim, heads
        self.gru = nn.GRU(3 * n_joints, hidden, num_layers=1, batch_first=True)
        self.node = nn.Linear(hidden, dim)
        self.time_emb = nn.Parameter(torch.zeros(n_obs, dim))
        self.joint_emb = nn.Embedding(n_joints, dim)
        self.prior = nn.Sequential(nn.Linear(3, dim), nn.ReLU(), nn.Linear(dim, dim))
        self.q = nn.Linear(dim, dim)  # Q, K, V shared between all joints (sec. 3.4)
        self.k = nn.Linear(dim, dim)
        self.v = nn.Linear(dim, dim)
        self.glob = nn.Linear(hidden, dim)
        self.norm = nn.LayerNorm(dim)
        self.ffn = nn.Sequential(nn.Linear(2 * dim, 2 * dim), nn.ReLU(), nn.Linear(2 * dim, dim))

    def encode(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """obs (B,N,J,3) -> nodes (B,N,dim), last hidden state (B,hidden)."""
        B, N = obs.shape[:2]
        if N != self.n_obs or obs.shape[2:] != (self.n_joints, 3):
            raise ValueError(f"expected obs (B,{self.n_obs},{self.n_joints},3), got {tuple(obs.shape)}")
        h, last = self.gru(obs.reshape(B, N, -1))
        return self.node(h) + self.time_emb, last[0]

    def features(self, enc, prior_xyz=None, prior_ids=None, query_ids=None, return_attn: bool = False):
        """enc from ``encode``; prior_xyz (B,n_p,3) with prior_ids (n_p,) (may be None); query_ids (J',) ->
        per-joint features (B,J',dim) (and the attention map (B,heads,J',N+n_p))."""
        nodes, last = enc
        B = nodes.shape[0]
        if prior_xyz is not None and prior_xyz.shape[1] > 0:
            pn = self.prior(prior_xyz) + self.joint_emb(prior_ids)[None]
            nodes = torch.cat([nodes, pn], 1)
        qe = self.joint_emb(query_ids)[None].expand(B, -1, -1)
        H, dh = self.heads, self.dim // self.heads
        Q = self.q(qe).view(B, -1, H, dh).transpose(1, 2)
        K = self.k(nodes).view(B, -1, H, dh).transpose(1, 2)
        V = self.v(nodes).view(B, -1, H, dh).transpose(1, 2)
        A = torch.softmax(Q @ K.transpose(-1, -2) / math.sqrt(dh), -1)  # eq. 3.1
        out = (A @ V).transpose(1, 2).reshape(B, -1, self.dim)
        x = self.norm(qe + out)
        g = self.glob(last)[:, None].expand_as(x)
        x = x + self.ffn(torch.cat([x, g], -1))
        return (x, A) if return_attn else x


# ----------------------------------------------------------------------------- heatmap model


class Up2(nn.Module):
    """A 2x2x2 stride-2 transposed convolution written as a 1x1x1 convolution + 3D pixel shuffle (same
    function; PyTorch's CPU ConvTranspose3d is many times slower)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.cout = cout
        self.conv = nn.Conv3d(cin, 8 * cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        M, _, a, b, c = x.shape
        y = self.conv(x).view(M, self.cout, 2, 2, 2, a, b, c)
        return y.permute(0, 1, 5, 2, 6, 3, 7, 4).reshape(M, self.cout, 2 * a, 2 * b, 2 * c)


class CharacteristicPoseNet(nn.Module):
    """Volumetric-heatmap forecaster of the next characteristic pose (sec. 3.3-3.5).

    ``order``: (right wrist, left wrist) joint indices, sampled first and second; all other joints follow.
    ``bones`` (L,2) parent/child pairs for the refinement (eq. 3.2)."""

    kind = "characteristic"

    def __init__(
        self,
        n_joints: int,
        order: tuple[int, int],
        bones: list[tuple[int, int]],
        n_obs: int = 10,
        hidden: int = 128,
        dim: int = 64,
        heads: int = 4,
        grid: int = 16,
        span: float = 2.0,
        n_discr: int = 10,
        channels: int = 16,
    ):
        super().__init__()
        if grid % 4:
            raise ValueError(f"grid must be a multiple of 4, got {grid}")
        self.n_joints, self.grid, self.span, self.n_discr = n_joints, grid, float(span), n_discr
        self.order = (int(order[0]), int(order[1]))
        rest = [j for j in range(n_joints) if j not in self.order]
        self.stages = [[self.order[0]], [self.order[1]], rest]  # Fig. 3.4: right hand, left hand, rest
        self.register_buffer("bones", torch.as_tensor(np.asarray(bones, np.int64).reshape(-1, 2)))
        self.backbone = Backbone(n_joints, n_obs, hidden, dim, heads)
        c, g0 = channels, grid // 4
        self.g0 = g0
        self.fc = nn.Linear(dim, 2 * c * g0**3)
        self.conv0 = nn.Conv3d(2 * c, 2 * c, 3, padding=1)
        self.up0 = Up2(2 * c, c)
        self.conv1 = nn.Conv3d(c + 4, c, 3, padding=1)  # + the last-input-skeleton volume (4 channels)
        self.conv2 = nn.Conv3d(c, c, 3, padding=1)
        self.up1 = Up2(c, n_discr + 4)  # heatmap bin logits + offsets + the gate of the last-skeleton offsets
        self.register_buffer("centres", voxel_centres(grid, span))
        self.register_buffer("centres_half", voxel_centres(grid // 2, span))
        self.register_buffer("values", bin_values(n_discr))
        self.register_buffer("ce_weight", class_weights(grid, span, n_discr))

    # -- decoding

    def _last_volume(self, last_xyz: torch.Tensor) -> torch.Tensor:
        """(M,3) last observed joint locations -> (M,4,g,g,g) at half resolution: voxel - joint (scaled) and a
        Gaussian bump at the joint."""
        c = self.centres_half
        g = len(c)
        rel = torch.stack(
            [
                (c[None, :, None, None] - last_xyz[:, 0, None, None, None]).expand(-1, g, g, g),
                (c[None, None, :, None] - last_xyz[:, 1, None, None, None]).expand(-1, g, g, g),
                (c[None, None, None, :] - last_xyz[:, 2, None, None, None]).expand(-1, g, g, g),
            ],
            1,
        )
        bump = torch.exp(-(rel**2).sum(1, keepdim=True) / (2 * (self.span / g) ** 2))
        return torch.cat([rel / (self.span / 2), bump], 1)

    def decode(self, feat: torch.Tensor, last_xyz: torch.Tensor):
        """feat (B,J',dim), last_xyz (B,J',3) -> bin logits (B,J',n_discr,G,G,G), offsets (B,J',3,G,G,G)
        metres (each at most one voxel length, sec. 3.4)."""
        B, Jp = feat.shape[:2]
        g0 = self.g0
        x = self.fc(feat.reshape(B * Jp, -1)).view(B * Jp, -1, g0, g0, g0)
        x = F.relu(self.conv0(F.relu(x)))
        x = F.relu(self.up0(x))
        x = torch.cat([x, self._last_volume(last_xyz.reshape(-1, 3))], 1)
        x = F.relu(self.conv1(x))
        x = F.relu(self.conv2(x))
        x = self.up1(x)
        G, nd, vs = self.grid, self.n_discr, self.span / self.grid
        logits = x[:, :nd].reshape(B, Jp, nd, G, G, G)
        # offsets: a learned field mixed (per-voxel gate) with the offsets volume of the last input skeleton
        # at full resolution (appendix, Fig. 3.10); both lie within one voxel length (sec. 3.4)
        c = self.centres
        last = last_xyz.reshape(-1, 3)
        last_off = torch.stack(
            [
                (last[:, 0, None, None, None] - c[None, :, None, None]).expand(-1, G, G, G),
                (last[:, 1, None, None, None] - c[None, None, :, None]).expand(-1, G, G, G),
                (last[:, 2, None, None, None] - c[None, None, None, :]).expand(-1, G, G, G),
            ],
            1,
        ).clamp(-vs, vs)
        gate = torch.sigmoid(x[:, nd + 3 : nd + 4])
        off = gate * last_off + (1 - gate) * torch.tanh(x[:, nd : nd + 3]) * vs
        return logits, off.reshape(B, Jp, 3, G, G, G)

    def stage(self, enc, obs_last: torch.Tensor, query: list[int], prior_xyz=None, prior_ids=None):
        q = torch.as_tensor(query, device=obs_last.device)
        pid = None if prior_ids is None else torch.as_tensor(prior_ids, device=obs_last.device)
        feat = self.backbone.features(enc, prior_xyz, pid, q)
        return self.decode(feat, obs_last[:, q])

    def heat(self, logits: torch.Tensor) -> torch.Tensor:
        """Bin logits (...,n_discr,G,G,G) -> expected heatmap value in [0,1] (...,G,G,G)."""
        return torch.einsum("...bxyz,b->...xyz", torch.softmax(logits, -4), self.values)

    # -- training (sec. 3.4.1: teacher forcing)

    def loss(
        self,
        obs: torch.Tensor,
        target: torch.Tensor,
        n_rest: int | None = None,
        w_offset: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> dict:
        """obs (B,N,J,3), target (B,J,3) (hip-centred, normalised). Weighted cross-entropy on the discretised
        heatmaps plus an l1 loss on the offsets around the target; teacher forcing for the prior joints.
        ``n_rest``: train this many random 'rest' joints per step (all when None) to fit the CPU budget."""
        enc = self.backbone.encode(obs)
        last = obs[:, -1]
        rw, lw = self.order
        rest = self.stages[2]
        if n_rest is not None and n_rest < len(rest):
            pick = torch.randperm(len(rest), generator=generator)[:n_rest].tolist()
            rest = [rest[i] for i in pick]
        plan = [([rw], None, None), ([lw], target[:, [rw]], [rw]), (rest, target[:, [rw, lw]], [rw, lw])]
        ce_sum, off_sum, n_vol = 0.0, 0.0, 0
        for query, pxyz, pids in plan:
            logits, off = self.stage(enc, last, query, pxyz, pids)
            y = target[:, query].reshape(-1, 3)
            h = target_heatmap(y, self.grid, self.span)  # (M,G,G,G)
            bins = discretise(h, self.n_discr)
            lg = logits.reshape(-1, self.n_discr, *h.shape[1:])
            ce_sum = ce_sum + F.cross_entropy(lg, bins, weight=self.ce_weight, reduction="mean") * len(query)
            # offsets: l1 on the voxels inside the target kernel, target clamped to one voxel length
            vs = self.span / self.grid
            c = self.centres
            G = self.grid
            cv = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), 0)  # (3,G,G,G)
            t_off = (y[:, :, None, None, None] - cv[None]).clamp(-vs, vs)
            m = (h > 0).unsqueeze(1).float()
            o = off.reshape(-1, 3, G, G, G)
            off_sum = off_sum + ((o - t_off).abs() * m).sum() / (3 * m.sum()).clamp_min(1) * len(query) / vs
            n_vol += len(query)
        ce, l1 = ce_sum / n_vol, off_sum / n_vol
        return {"loss": ce + w_offset * l1, "ce": ce, "offset_l1_vox": l1}

    # -- sampling (sec. 3.5)

    def _sample_voxels(self, feat, last_xyz, n: int, temperature: float, generator=None, chunk: int = 256):
        """feat (M,dim), last_xyz (M,3) -> n samples per heatmap (M,n,3) and the heat (M,G,G,G), decoded in
        chunks of ``chunk`` volumes (memory)."""
        G = self.grid
        c = self.centres
        pos_l, heat_l = [], []
        for a in range(0, feat.shape[0], chunk):
            logits, off = self.decode(feat[None, a : a + chunk], last_xyz[None, a : a + chunk])
            logits, off = logits[0], off[0]
            M = logits.shape[0]
            h = self.heat(logits)
            p = torch.softmax(h.reshape(M, -1) / temperature, -1)  # temperature scaling, then random sampling
            idx = torch.multinomial(p, n, replacement=True, generator=generator)  # (M,n)
            ix, iy, iz = idx // (G * G), (idx // G) % G, idx % G
            pos = torch.stack([c[ix], c[iy], c[iz]], -1)
            o = off.reshape(M, 3, -1).gather(2, idx[:, None].expand(-1, 3, -1)).transpose(1, 2)
            pos_l.append(pos + o)
            heat_l.append(h)
        return torch.cat(pos_l), torch.cat(heat_l)

    def _features(self, enc, query: list[int], prior_xyz=None, prior_ids=None):
        dev = enc[0].device
        pid = None if prior_ids is None else torch.as_tensor(prior_ids, device=dev)
        return self.backbone.features(enc, prior_xyz, pid, torch.as_tensor(query, device=dev))

    @torch.no_grad()
    def sample(
        self,
        obs: torch.Tensor,
        k: int = 10,
        temperature: float = 0.025,
        *,
        refine: bool = True,
        refine_iters: int = 60,
        generator: torch.Generator | None = None,
        return_raw: bool = False,
        angles_from: str = "last",
    ):
        """obs (B,N,J,3) normalised -> k pose hypotheses (B,k,J,3): right wrist, then left wrist given it,
        then the rest given both (Fig. 3.4); refined with eq. 3.2 unless ``refine=False``."""
        B, J, G = obs.shape[0], self.n_joints, self.grid
        enc = self.backbone.encode(obs)
        last = obs[:, -1]
        rw, lw = self.order
        f = self._features(enc, [rw])
        p_rw, h_rw = self._sample_voxels(f[:, 0], last[:, rw], k, temperature, generator)  # (B,k,3)
        encb = (enc[0].repeat_interleave(k, 0), enc[1].repeat_interleave(k, 0))
        lastb = last.repeat_interleave(k, 0)
        p_rw = p_rw.reshape(B * k, 1, 3)
        f = self._features(encb, [lw], p_rw, [rw])
        p_lw, h_lw = self._sample_voxels(f[:, 0], lastb[:, lw], 1, temperature, generator)
        p_lw = p_lw.reshape(B * k, 1, 3)
        rest = self.stages[2]
        f = self._features(encb, rest, torch.cat([p_rw, p_lw], 1), [rw, lw])
        p_rest, h_rest = self._sample_voxels(
            f.reshape(-1, f.shape[-1]), lastb[:, rest].reshape(-1, 3), 1, temperature, generator
        )
        pose = torch.zeros(B * k, J, 3, device=obs.device)
        pose[:, rw] = p_rw[:, 0]
        pose[:, lw] = p_lw[:, 0]
        pose[:, rest] = p_rest.reshape(B * k, len(rest), 3)
        raw = pose.reshape(B, k, J, 3)
        if not refine:
            return (raw, raw) if return_raw else raw
        heat = torch.zeros(B * k, J, G, G, G, device=obs.device)
        heat[:, rw] = h_rw.repeat_interleave(k, 0)
        heat[:, lw] = h_lw
        heat[:, rest] = h_rest.reshape(B * k, len(rest), G, G, G)
        ref = refine_pose(
            pose,
            heat,
            obs[:, 0].repeat_interleave(k, 0),
            lastb,
            self.order,
            self.bones,
            self.span,
            iters=refine_iters,
            angles_from=angles_from,
        ).reshape(B, k, J, 3)
        return (ref, raw) if return_raw else ref


# ----------------------------------------------------------------------------- pose refinement (eq. 3.2)


def joint_angle_triples(bones: torch.Tensor) -> torch.Tensor:
    """(A,3) (grandparent, parent, child) triples from parent/child bones: the angle at the parent joint."""
    bones = bones.tolist()
    out = []
    for a, b in bones:
        for c, d in bones:
            if c == b:
                out.append((a, b, d))
    return torch.as_tensor(out, dtype=torch.long).reshape(-1, 3)


def _lengths(x, bones):
    return (x[:, bones[:, 1]] - x[:, bones[:, 0]]).norm(dim=-1)


def _angles(x, tri):
    u = x[:, tri[:, 0]] - x[:, tri[:, 1]]
    v = x[:, tri[:, 2]] - x[:, tri[:, 1]]
    cos = (u * v).sum(-1) / (u.norm(dim=-1) * v.norm(dim=-1)).clamp_min(1e-6)
    return torch.acos(cos.clamp(-0.999, 0.999))


def refine_pose(
    x,
    heat,
    first_obs,
    last_obs,
    order,
    bones,
    span,
    *,
    iters: int = 60,
    lr: float = 0.005,
    weights: dict | None = None,
    reduce: str = "sum",
    angles_from: str = "first",
):
    """Eq. 3.2: min_x w_e||x_e - e||_2 + w_b||bonelengths(x) - b||_1 + w_a||angles(x) - theta||_1
    + w_c||x - x_0||_1 + w_h sum_i (1 - H_i(x_i)).

    x (M,J,3) raw sampled poses; heat (M,J,G,G,G) heatmaps (values in [0,1]); first_obs (M,J,3) the initially
    observed skeleton (bone lengths b and angles theta; ``angles_from="last"`` takes theta from x_0 instead);
    last_obs (M,J,3) x_0, the last input skeleton; e the sampled end effectors (``order``). ``reduce``: the
    norms sum over joints / bones / angles as written ("sum") or average ("mean"). Adam, ``iters`` steps with
    the learning rate decaying linearly to 0 (l1 terms would otherwise leave the pose jittering by ``lr``)."""
    if angles_from not in ("first", "last") or reduce not in ("sum", "mean"):
        raise ValueError(
            f"angles_from must be 'first'/'last' and reduce 'sum'/'mean', got {angles_from!r}, {reduce!r}"
        )
    w = dict(REFINE_WEIGHTS, **(weights or {}))
    red = (lambda t: t.sum(-1)) if reduce == "sum" else (lambda t: t.mean(-1))
    bones = bones.to(x.device)
    tri = joint_angle_triples(bones).to(x.device)
    b = _lengths(first_obs, bones)
    theta = None
    if len(tri):
        theta = _angles(first_obs if angles_from == "first" else last_obs, tri)
    e_idx = list(order)
    e = x[:, e_idx].clone()
    M, J = x.shape[:2]
    vol = heat.reshape(M * J, 1, *heat.shape[2:])  # one volume per joint for grid_sample
    with torch.enable_grad():
        y = x.clone().requires_grad_(True)
        opt = torch.optim.Adam([y], lr=lr)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 1 - i / max(1, iters))
        for _ in range(iters):
            opt.zero_grad()
            E = w["w_e"] * red((y[:, e_idx] - e).norm(dim=-1))
            E = E + w["w_b"] * red((_lengths(y, bones) - b).abs())
            if theta is not None:
                E = E + w["w_a"] * red((_angles(y, tri) - theta).abs())
            E = E + w["w_c"] * red((y - last_obs).abs().sum(-1))
            # heatmap likelihood by trilinear lookup; grid_sample takes (x,y,z) -> (W,H,D), coords in [-1,1]
            g = (y / (span / 2)).reshape(M * J, 1, 1, 1, 3).flip(-1)
            h = F.grid_sample(vol, g, align_corners=False, padding_mode="border").reshape(M, J)
            E = E + w["w_h"] * red(1 - h)
            E.sum().backward()
            opt.step()
            sched.step()
    return y.detach()


# ----------------------------------------------------------------------------- the "Deterministic" ablation


class DeterministicCharacteristic(nn.Module):
    """Tab. 3.3 "Deterministic": the same backbone, an MLP head regressing each joint's offset from its last
    observed position."""

    kind = "characteristic_deterministic"

    def __init__(self, n_joints: int, n_obs: int = 10, hidden: int = 128, dim: int = 64, heads: int = 4):
        super().__init__()
        self.n_joints = n_joints
        self.backbone = Backbone(n_joints, n_obs, hidden, dim, heads)
        self.head = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, 3))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        q = torch.arange(self.n_joints, device=obs.device)
        f = self.backbone.features(self.backbone.encode(obs), query_ids=q)
        return obs[:, -1] + self.head(f)

    def loss(self, obs, target, **_) -> dict:
        err = (self(obs) - target).norm(dim=-1).mean()
        return {"loss": err, "mpjpe": err}

    @torch.no_grad()
    def sample(self, obs, k: int = 10, **_) -> torch.Tensor:
        return self(obs)[:, None].expand(-1, k, -1, -1).clone()
