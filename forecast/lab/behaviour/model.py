"""The joint action and characteristic-3D-pose forecaster of Diller ch. 4 (sec. 4.4), its critic, the
autoregressive rollout (sec. 4.4.3) and the checkpoint.

Generator (sec. 4.4, Fig. 4.7): three encoders in parallel, a joint latent, two decoders.
- pose encoder: the last ``n_obs`` 2D poses (plane features, ``geometry``, with a seen-mask per joint),
  one linear layer and three residual blocks;
- action encoder: the last ``n_obs`` action labels as one-hot vectors (an extra "unknown" class), an MLP;
- context encoder: the seed's initially-observed objects have no counterpart here, so the third encoder
  takes the context a room gives: every action seen so far (multi-hot) and the camera's distance and
  height in the viewer frame (with ``context="room"`` also the person's floor position and the viewer
  frame's direction in the room, ``geometry.room_context``), an MLP;
- an MLP over the concatenation gives the latent z; an MLP decodes the next action's logits, another the
  next characteristic 3D pose (J,3) in the viewer frame, metres from the anchor.

Critic (sec. 4.4.2, 4.7.10): joints through four linear layers and the bone Gram matrix
``Psi = B^T B`` (bone lengths squared on its diagonal, angles off it) through three, in parallel; two linear
layers combine them into the score. Trained as a Wasserstein critic (eq. 4.1's ``L_adv3d``) with a
gradient penalty instead of weight clipping (stabler on small batches; the choice is ours).

Smaller than the seed (one CPU thread, minutes instead of 12 GPU hours): width 128 instead of the seed's
larger layers, batch 128 instead of 4096, learning rate 3e-4 instead of 1e-4 and no weight decay (the
seed: 0.001) over 3,000 steps, the settings chosen on validation.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from roomcap.core.config import config_from_dict as _config_from_dict
from roomcap.core.errors import FormatError
from roomcap.forecast.lab.behaviour.data import ACTIONS, JOINTS, PARENTS, SCRIPTS, UPPER9
from roomcap.forecast.lab.behaviour.geometry import plane_of_3d
from roomcap.forecast.runtime.checkpoint import read_checkpoint, write_checkpoint

SHIPPED = Path(__file__).resolve().parents[2] / "checkpoints" / "behaviour_cmu.pt"
FAMILY = "behaviour"  # the registry's family of these checkpoints
VARIANTS = ("full", "action_only", "pose_only", "action_2d")


@dataclass(frozen=True)
class BehaviourConfig:
    # Table 4.2's loss ablations: full | action_only (no pose losses) | pose_only (no action loss) |
    # action_2d (action and 2D losses, no 3D adversarial loss)
    variant: str = "full"
    joints: str = "body19"  # body19 | upper9 (the seed's 9 upper-body joints, the ablation)
    n_obs: int = 3  # observed steps
    m: int = 5  # forecast steps M (the seed: 5 on IKEA-ASM, 10 on MPII Cooking II)
    hidden: int = 128
    lr: float = 3e-4
    weight_decay: float = 0.0
    batch: int = 128
    steps: int = 3000
    lambda_action: float = 1.0
    lambda_pose2d: float = 1.0  # on pixels / 100 (so the three terms are of one order)
    lambda_adv3d: float = 0.1
    gp: float = 10.0
    n_critic: int = 1  # critic updates per generator update (RepNet's training: 5)
    # plain: our small critic | repnet: RepNet's layout, which the seed's critic follows (sec. 4.7.10, [156]):
    # residual connections in both paths, the KCS path 4x wider (RepNet: 10x; 4x keeps a step short on one
    # thread), the paths' linear outputs concatenated
    critic: str = "plain"
    # free | database: the skeleton layer (``Skeleton``) fixes the database's proportions | learned: the
    # skeleton's proportions start at the database's and are trained (one set for every pose)
    bone_lengths: str = "free"
    short_history: float = 0.25  # fraction of training sequences that hide their first 1..n_obs-1 steps
    n_train: int = 20000  # composite training sequences
    n_eval: int = 1000  # validation / test sequences
    eval_every: int = 500
    seed: int = 0
    script: str = "markov"  # the composite activities (data.SCRIPTS): markov | stations
    context: str = "camera"  # camera | room: the context encoder also takes the person's place in the room
    # free: the pose decoder outputs the joints | prior: it outputs a code of a pose prior learned from the
    # 3D database (``PosePrior``, frozen), a heading, the pelvis and a size
    pose_decoder: str = "free"
    prior_dim: int = 32  # the prior's code size
    prior_beta: float = 1e-4  # the weight of its KL term
    prior_steps: int = 8000  # its training steps (on the database, before the forecaster's)
    prior_proportions: float = 0.0  # the prior also learns bone lengths within 1 +- this of the database's

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.joints not in ("body19", "upper9"):
            raise ValueError(f"joints must be 'body19' or 'upper9', got {self.joints!r}")
        if self.bone_lengths not in ("free", "database", "learned"):
            raise ValueError(
                f"bone_lengths must be 'free', 'database' or 'learned', got {self.bone_lengths!r}"
            )
        if self.script not in SCRIPTS:
            raise ValueError(f"script must be one of {SCRIPTS}, got {self.script!r}")
        if self.context not in ("camera", "room"):
            raise ValueError(f"context must be 'camera' or 'room', got {self.context!r}")
        if self.pose_decoder not in ("free", "prior"):
            raise ValueError(f"pose_decoder must be 'free' or 'prior', got {self.pose_decoder!r}")
        if self.pose_decoder == "prior" and self.bone_lengths != "free":
            raise ValueError(
                "pose_decoder=prior keeps the prior's proportions: use it with bone_lengths=free"
            )
        if self.critic not in ("plain", "repnet"):
            raise ValueError(f"critic must be 'plain' or 'repnet', got {self.critic!r}")
        if self.n_critic < 1:
            raise ValueError(f"n_critic must be >= 1, got {self.n_critic}")

    @property
    def joint_names(self) -> tuple[str, ...]:
        return JOINTS if self.joints == "body19" else UPPER9

    @property
    def use_pose(self) -> bool:
        return self.variant != "action_only"

    @property
    def use_action(self) -> bool:
        return self.variant != "pose_only"

    @property
    def use_adv3d(self) -> bool:
        """Whether eq. 4.1's 3D adversarial term trains the poses (Table 4.2: not in action_2d)."""
        return self.variant in ("full", "pose_only")


def config_from_dict(d: dict) -> BehaviourConfig:
    return _config_from_dict(BehaviourConfig, d, "behaviour config")


def bones(names: tuple[str, ...]) -> np.ndarray:
    """(b,2) child, parent index pairs of the body19 tree restricted to ``names`` (a missing parent is
    skipped up the tree)."""
    idx = {n: i for i, n in enumerate(names)}
    out = []
    for n in names:
        p = PARENTS[JOINTS.index(n)]
        while p >= 0 and JOINTS[p] not in idx:
            p = PARENTS[p]
        if p >= 0:
            out.append((idx[n], idx[JOINTS[p]]))
    return np.asarray(out, np.int64)


def gram(P: torch.Tensor, bone_idx: torch.Tensor) -> torch.Tensor:
    """Psi = B^T B (sec. 4.4.2) of poses P (B,J,3): its upper triangle (B, b(b+1)/2)."""
    Bm = P[:, bone_idx[:, 0]] - P[:, bone_idx[:, 1]]  # (B,b,3): columns b_i = j_k - j_l
    G = Bm @ Bm.transpose(1, 2)
    iu = torch.triu_indices(G.shape[1], G.shape[1])
    return G[:, iu[0], iu[1]]


class _Res(nn.Module):
    def __init__(self, h: int) -> None:
        super().__init__()
        self.f = nn.Sequential(nn.Linear(h, h), nn.LeakyReLU(0.2), nn.Linear(h, h))
        self.act = nn.LeakyReLU(0.2)

    def forward(self, x):
        return self.act(x + self.f(x))


def _mlp(*dims: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:], strict=True):
        layers += [nn.Linear(a, b), nn.LeakyReLU(0.2)]
    return nn.Sequential(*layers[:-1])


def parents_first(bone_idx: np.ndarray) -> np.ndarray:
    """The (b,2) child, parent pairs ordered so that every bone comes after its parent's bone (a pose can be
    rebuilt from the root down in this order)."""
    root = set(bone_idx[:, 1].tolist()) - set(bone_idx[:, 0].tolist())
    order, done = [], set(root)
    while len(order) < len(bone_idx):
        for i, (c, p) in enumerate(bone_idx.tolist()):
            if p in done and c not in done:
                order.append(i)
                done.add(c)
    return bone_idx[order]


class Skeleton(nn.Module):
    """A pose (B,J,3) rebuilt with the 3D database's bone proportions: from the pelvis (kept where the
    decoder put it) down the tree, each bone keeps the direction the decoder gave it and takes the length
    ``scale * bone_len``, one ``scale = 1 + max_scale * tanh(a)`` per pose from the decoder's extra output
    ``a`` (within +-``max_scale`` of the database's mean size, about 3 s.d. of its subjects). Not in the
    seed, whose critic alone holds the bone lengths (sec. 4.4.2): our small critic left them 15 % short and
    scattered (Psi's diagonal), which the quality classifier sees at once.

    With ``learn`` the proportions are trained too: each bone's length is ``bone_len * exp(r)``, one learned
    ``r`` per bone (0 at the start), the same for every pose. The 2D loss can then fit the proportions of the
    training sequences' people, which differ from the database's subjects (shoulders, thighs), while each
    pose keeps one consistent skeleton."""

    def __init__(self, bone_idx: np.ndarray, max_scale: float = 0.15, learn: bool = False) -> None:
        super().__init__()
        self.register_buffer("bone_idx", torch.as_tensor(parents_first(bone_idx)))
        self.register_buffer("bone_len", torch.ones(len(bone_idx)))
        self.log_ratio = nn.Parameter(torch.zeros(len(bone_idx))) if learn else None
        self.max_scale = max_scale

    def lengths(self) -> torch.Tensor:
        """The bone lengths at size 1 (this layer's bone order)."""
        return self.bone_len if self.log_ratio is None else self.bone_len * self.log_ratio.exp()

    def set_lengths(self, db: np.ndarray) -> None:
        """The mean bone lengths of database poses (N,J,3) (this layer's bone order)."""
        b = self.bone_idx.numpy()
        L = np.linalg.norm(db[:, b[:, 0]] - db[:, b[:, 1]], axis=-1).mean(0)
        self.bone_len.copy_(torch.as_tensor(L, dtype=torch.float32))

    def forward(self, raw: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        c, p = self.bone_idx[:, 0], self.bone_idx[:, 1]
        vec = raw[:, c] - raw[:, p]
        u = vec / vec.norm(dim=-1).clamp(min=1e-6)[..., None]
        scale = 1.0 + self.max_scale * torch.tanh(a)
        L = self.lengths()
        out = [raw[:, j] for j in range(raw.shape[1])]
        for i, (ci, pi) in enumerate(zip(c.tolist(), p.tolist(), strict=True)):
            out[ci] = out[pi] + (scale * L[i])[:, None] * u[:, i]
        return torch.stack(out, 1)


class PosePrior(nn.Module):
    """A pose prior learned from the uncorrelated 3D database: a VAE of its canonical poses (pelvis at the
    origin, shoulders along x; ``training._canonical``). Not in the seed, whose critic alone keeps the poses
    valid (sec. 4.4.2): with ``pose_decoder="prior"`` the generator's pose decoder gives a code for this
    frozen decoder, a heading about the vertical, the pelvis and a size within +-``max_scale``, so every
    forecast pose is one the database's poses span (the critic still trains alongside)."""

    def __init__(self, J: int, dim: int, max_scale: float = 0.15, code_bound: float = 2.5) -> None:
        super().__init__()
        self.J, self.dim, self.max_scale, self.code_bound = J, dim, max_scale, code_bound
        self.enc = _mlp(J * 3, 256, 256, 2 * dim)
        self.dec = _mlp(dim, 256, 256, J * 3)

    @property
    def n_inputs(self) -> int:
        """What the generator's pose decoder gives it: code, heading (2), pelvis (3), size (1)."""
        return self.dim + 6

    def forward(self, out: torch.Tensor) -> torch.Tensor:
        """The pose decoder's output (B, n_inputs) -> poses (B,J,3) in the viewer frame."""
        B, d = out.shape[0], self.dim
        X = self.dec(self.code_bound * torch.tanh(out[:, :d] / self.code_bound)).reshape(B, self.J, 3)
        cs = out[:, d : d + 2]  # (cos, sin) of the heading, up to scale; heading 0 when both are 0
        n = cs.norm(dim=1, keepdim=True)
        cs = torch.where(n > 1e-6, cs / n.clamp(min=1e-6), torch.tensor([1.0, 0.0]))
        c, s = cs[:, 0, None], cs[:, 1, None]
        X = torch.stack([c * X[..., 0] - s * X[..., 1], s * X[..., 0] + c * X[..., 1], X[..., 2]], -1)
        size = 1.0 + self.max_scale * torch.tanh(out[:, -1])
        return X * size[:, None, None] + out[:, None, d + 2 : d + 5]


def _with_proportions(
    X: torch.Tensor, names: tuple[str, ...], spread: float, g: torch.Generator
) -> torch.Tensor:
    """Poses X (B,J,3) with each bone's length times a factor drawn uniformly in 1 +- ``spread`` (one per
    pose and bone, the left and right bone alike), rebuilt from the pelvis down the tree."""
    order = parents_first(bones(names)).tolist()
    side = [names[c].replace("left_", "").replace("right_", "") for c, _ in order]
    kinds = sorted(set(side))
    f = 1.0 + spread * (2 * torch.rand(len(X), len(kinds), generator=g) - 1)
    js = [X[:, j] for j in range(X.shape[1])]
    for (c, p), k in zip(order, side, strict=True):
        js[c] = js[p] + f[:, kinds.index(k), None] * (X[:, c] - X[:, p])
    return torch.stack(js, 1)


def fit_pose_prior(canon: np.ndarray, cfg: BehaviourConfig) -> PosePrior:
    """Train the prior's VAE on canonical database poses (N,J,3) of ``cfg``'s joints (its prior settings):
    squared joint error plus ``prior_beta`` times the KL term, Adam, batches of 512; with
    ``prior_proportions`` each batch's bone lengths varied (people are built otherwise than the database's
    subjects); returned frozen."""
    torch.manual_seed(cfg.seed)
    g = torch.Generator().manual_seed(cfg.seed)
    J = canon.shape[1]
    X = torch.as_tensor(canon, dtype=torch.float32)
    vae = PosePrior(J, cfg.prior_dim)
    opt = torch.optim.Adam(vae.parameters(), lr=1e-3)
    for _ in range(cfg.prior_steps):
        x = X[torch.randint(len(X), (512,), generator=g)]
        if cfg.prior_proportions > 0:
            x = _with_proportions(x, cfg.joint_names, cfg.prior_proportions, g)
        x = x.reshape(len(x), -1)
        mu, log_var = vae.enc(x).chunk(2, 1)
        r = vae.dec(mu + torch.randn(mu.shape, generator=g) * (0.5 * log_var).exp())
        kl = (-0.5 * (1 + log_var - mu**2 - log_var.exp())).sum(1).mean()
        loss = ((r - x) ** 2).reshape(-1, J, 3).sum(-1).mean() + cfg.prior_beta * kl
        opt.zero_grad()
        loss.backward()
        opt.step()
    return vae.eval().requires_grad_(False)


class Generator(nn.Module):
    """One step: (pose feats (B,N,J,3) = plane xz + seen, action one-hots (B,N,A+1), context (B,A+2, with
    ``room`` B,A+6)) -> (action logits (B,A), 3D pose (B,J,3) viewer frame). With a ``skeleton`` the pose
    takes its bone lengths; with a ``prior`` it is decoded by the pose prior."""

    def __init__(
        self,
        n_obs: int,
        J: int,
        A: int,
        h: int,
        skeleton: Skeleton | None = None,
        room: bool = False,
        prior: PosePrior | None = None,
    ) -> None:
        super().__init__()
        self.skeleton = skeleton
        self.prior = prior
        self.room = room
        self.J, self.A = J, A
        self.pose_in = nn.Linear(n_obs * J * 3, h)
        self.pose_res = nn.Sequential(_Res(h), _Res(h), _Res(h))
        self.act_enc = _mlp(n_obs * (A + 1), h // 2, h // 2)
        self.ctx_enc = _mlp(A + 2 + 4 * room, h // 4, h // 4)
        self.joint = nn.Sequential(_mlp(h + h // 2 + h // 4, h, h), nn.LeakyReLU(0.2))
        self.dec_action = _mlp(h, h, A)
        n_out = J * 3 + (skeleton is not None) if prior is None else prior.n_inputs  # + the skeleton's size
        self.dec_pose = _mlp(h, h, n_out)

    def forward(self, pose, acts, ctx):
        B = pose.shape[0]
        zp = self.pose_res(self.pose_in(pose.reshape(B, -1)))
        za = self.act_enc(acts.reshape(B, -1))
        zc = self.ctx_enc(ctx)
        z = self.joint(torch.cat([zp, za, zc], 1))
        out = self.dec_pose(z)
        if self.prior is not None:
            return self.dec_action(z), self.prior(out)
        P = out[:, : self.J * 3].reshape(B, self.J, 3)
        return self.dec_action(z), P if self.skeleton is None else self.skeleton(P, out[:, -1])


class Critic(nn.Module):
    """Wasserstein critic over joints (pelvis x, y at 0) and the bone Gram matrix (sec. 4.4.2, 4.7.10): four
    linear layers on the joints and three on Psi in parallel, two combining them."""

    def __init__(self, J: int, bone_idx: np.ndarray, h: int) -> None:
        super().__init__()
        self.register_buffer("bone_idx", torch.as_tensor(bone_idx))
        nb = len(bone_idx)
        self.joints = _mlp(J * 3, h, h, h, h)
        self.kcs = _mlp(nb * (nb + 1) // 2, h, h, h)
        self.head = _mlp(2 * h, h, 1)

    def forward(self, P):
        B = P.shape[0]
        a = self.joints(P.reshape(B, -1))
        b = self.kcs(gram(P, self.bone_idx))
        return self.head(torch.cat([nn.functional.leaky_relu(a, 0.2), nn.functional.leaky_relu(b, 0.2)], 1))[
            :, 0
        ]


class RepNetCritic(nn.Module):
    """The critic laid out as RepNet's (Wandt & Rosenhahn 2019, the seed's [156]; sec. 4.7.10 counts its
    layers): a joint path of four linear layers with a residual connection over the second and third, a KCS
    path of three linear layers over the flattened Psi = B^T B with a residual connection over its last two
    and ``kcs_wide`` times the joint path's width (RepNet: 1000 against 100), the two paths' linear outputs
    concatenated and two linear layers giving the score."""

    def __init__(self, J: int, bone_idx: np.ndarray, h: int, kcs_wide: int = 4) -> None:
        super().__init__()
        self.register_buffer("bone_idx", torch.as_tensor(bone_idx))
        nb, hk = len(bone_idx), h * kcs_wide
        self.j1, self.j2, self.j3, self.j4 = (
            nn.Linear(J * 3, h),
            nn.Linear(h, h),
            nn.Linear(h, h),
            nn.Linear(h, h),
        )
        self.k1, self.k2, self.k3 = nn.Linear(nb * (nb + 1) // 2, hk), nn.Linear(hk, hk), nn.Linear(hk, hk)
        self.head = _mlp(h + hk, h, 1)
        self.act = nn.LeakyReLU(0.2)

    def forward(self, P):
        B, f = P.shape[0], self.act
        d1 = f(self.j1(P.reshape(B, -1)))
        d3 = f(d1 + self.j3(f(self.j2(d1))))
        k1 = f(self.k1(gram(P, self.bone_idx)))
        k3 = k1 + self.k3(f(self.k2(k1)))
        return self.head(torch.cat([self.j4(d3), k3], 1))[:, 0]


def rollout(
    gen: Generator,
    feats: torch.Tensor,
    acts: torch.Tensor,
    seen: torch.Tensor,
    c: torch.Tensor,
    m: int,
    *,
    feed_pose: bool = True,
    feed_action: bool = True,
    room: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sec. 4.4.3: predict m steps autoregressively, each from the n_obs most recent (observed or
    predicted) steps. feats (B,N,J,2) plane features of the observed steps (0 where unseen), seen
    (B,N,J) bool, acts (B,N) observed action indices, c (B,3) camera centre in the viewer frame.
    A predicted step re-enters as the plane features of its 3D pose and its action probabilities
    (``feed_pose``/``feed_action`` False: as unseen / unknown, the ablations without that head).
    ``room`` (B,4) ``geometry.room_context``, the same for every step; read only by a generator built with
    ``context="room"``. -> logits (B,m,A), poses (B,m,J,3)."""
    if gen.room and room is None:
        raise ValueError("rollout: this generator takes the room context; give room=room_context(V, g)")
    B, N, J, _ = feats.shape
    A = gen.A
    pose_hist = torch.cat([feats, seen[..., None].float()], -1)  # (B,N,J,3)
    oh = torch.zeros(B, N, A + 1)
    oh.scatter_(2, acts[..., None], 1.0)
    seen_mh = oh[..., :A].amax(1)
    cam = torch.stack([c[:, 1].abs(), c[:, 2]], 1) / 5.0
    logits_l, poses_l = [], []
    for _ in range(m):
        ctx = torch.cat([seen_mh, cam, room] if gen.room else [seen_mh, cam], 1)
        lg, P = gen(pose_hist[:, -N:], oh[:, -N:], ctx)
        logits_l.append(lg)
        poses_l.append(P)
        if feed_pose:
            nxt = torch.cat([plane_of_3d(P, c), torch.ones(B, J, 1)], -1)
        else:
            nxt = torch.zeros(B, J, 3)
        if feed_action:
            pr = torch.softmax(lg, 1)
            nxt_a = torch.cat([pr, torch.zeros(B, 1)], 1)
            seen_mh = torch.maximum(seen_mh, pr)
        else:
            nxt_a = torch.zeros(B, A + 1)
            nxt_a[:, A] = 1.0
        pose_hist = torch.cat([pose_hist, nxt[:, None]], 1)
        oh = torch.cat([oh, nxt_a[:, None]], 1)
    return torch.stack(logits_l, 1), torch.stack(poses_l, 1)


def build(cfg: BehaviourConfig) -> tuple[Generator, nn.Module]:
    names = cfg.joint_names
    torch.manual_seed(cfg.seed)
    skel = Skeleton(bones(names), learn=cfg.bone_lengths == "learned") if cfg.bone_lengths != "free" else None
    prior = (
        PosePrior(len(names), cfg.prior_dim).requires_grad_(False) if cfg.pose_decoder == "prior" else None
    )
    gen = Generator(cfg.n_obs, len(names), len(ACTIONS), cfg.hidden, skel, cfg.context == "room", prior)
    crit = RepNetCritic if cfg.critic == "repnet" else Critic
    return gen, crit(len(names), bones(names), cfg.hidden)


def save_checkpoint(path, gens: dict[str, Generator], cfgs: dict[str, BehaviourConfig], extra: dict) -> None:
    """One file with every trained variant: {name: (state_dict, config)} plus ``extra`` (the train-average
    pose, the action frequencies, history). Plain tensors and builtins (loads with weights_only=True)."""
    write_checkpoint(
        path,
        FAMILY,
        config={n: cfgs[n] for n in gens},
        weights={n: g.state_dict() for n, g in gens.items()},
        extra=extra,
        actions=list(ACTIONS),
    )


def load_checkpoint(path) -> tuple[dict[str, Generator], dict[str, BehaviourConfig], dict]:
    blob = read_checkpoint(Path(path), FAMILY, missing_as_is=True)
    if list(blob["actions"]) != list(ACTIONS):
        raise FormatError(
            path,
            "actions",
            f"trained on {blob['actions']}, this code knows {list(ACTIONS)}",
            "Train a new checkpoint with `forecast behaviour train`.",
        )
    gens, cfgs = {}, {}
    for n, c in blob["config"].items():
        # older checkpoints: free bones, the markov script, the camera context, the free pose decoder
        old = {
            "bone_lengths": "free",
            "script": "markov",
            "context": "camera",
            "pose_decoder": "free",
            "critic": "plain",
        }
        cfg = BehaviourConfig(**{**old, **c})
        g, _ = build(cfg)
        g.load_state_dict(blob["weights"][n])
        g.eval()
        gens[n], cfgs[n] = g, cfg
    return gens, cfgs, blob["extra"]
