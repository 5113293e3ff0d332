"""DreamerV3 baseline and VAE-Dreamer: the paper's Dreamer comparison agents in one file.

Paper: section "Dreamer details" (tables "Architecture details used in Dreamer baseline" and
"Hyperparameters used during Dreamer training"); the method is DreamerV3 (Hafner et al. 2023), written
here from that paper's description in PyTorch.

    python dreamer_baseline.py --env simple_shapes                      # Dreamer 2M, raw observations
    python dreamer_baseline.py --env simple_shapes --obs vae            # VAE-Dreamer
    python dreamer_baseline.py --env robodesk --task push_green         # Dreamer 12M
    python dreamer_baseline.py --env robodesk --task push_green --size 40m
    python dreamer_baseline.py --env simple_shapes --eval-only --checkpoint PATH --drop vision  # ablation

World model: an RSSM with a deterministic GRU state h_t (``deter``) and a stochastic state of 32
categorical variables with 32 classes each (1% uniform mix), encoders of the image (CNN) and attribute
vector (MLP on symlog inputs), decoders of both, a 255-bin two-hot reward head and a continue head, trained
with KL balancing and free bits. The actor-critic learns in imagination (horizon 15, lambda-returns,
percentile return normalisation, slow critic). ``--obs vae`` replaces the raw observation by the
concatenated frozen VAE means [u_v, u_attr] of pretrain_vae_gw.py, encoded and decoded as one vector.

The saved policy doubles as a RoboDesk data-collection expert: every checkpoint is accompanied by
``<checkpoint>.policy.pt2``, a self-contained ``torch.export`` program (observation -> action, with its
recurrent state) that ``pretrain_vae_gw.py --expert-checkpoint`` runs without importing this file.

Reading map, top to bottom:
    Args, MODEL_SIZES             the tables' settings and the 2M / 12M / 40M sizes
    TwoHot ... Decoder            symlog two-hot values, the observation encoder and decoders
    BlockLinear, RSSM             the recurrent state-space model (block GRU, 32 x 32 categoricals)
    Actor, ReturnScale, Agent     the actor-critic and the whole agent
    Replay, world_model_loss      replayed sequences, the RSSM's losses (KL balancing, free bits)
    rollout ... dream_loss        dreams from every replayed state and the actor-critic's losses
    train_update                  one training step: the world model, then the actor-critic
    main                          act, store, train, then log / evaluate / film / save when due
    run_episodes ... Observer     evaluation, the exported policy, raw or frozen-VAE observations
    SCRIPT ... start_run          this script's part of the run; below the ==== fence, the shared block
"""

from __future__ import annotations

import atexit
import copy
import ctypes
import errno
import json
import math
import os
import random
import shutil
import signal
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, NamedTuple

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from torch.utils.flop_counter import FlopCounterMode
from torch.utils.tensorboard import SummaryWriter

import envs  # noqa: F401  (registers the environments)
from envs.simple_shapes import reference_returns as ss_reference_returns


@dataclass
class Args:
    env: Literal["simple_shapes", "robodesk"] = "simple_shapes"
    """environment"""
    task: str = "push_green"
    """RoboDesk task (ignored for Simple Shapes): one of open_slide, open_drawer, push_green, stack,
    upright_block_off_table, flat_block_in_bin, flat_block_in_shelf, lift_upright_block, lift_ball
    (RoboDesk's core tasks), push_blue, push_red, flat_block_off_table, ball_off_table,
    upright_block_in_bin, ball_in_bin, upright_block_in_shelf, ball_in_shelf, lift_flat_block"""
    obs: Literal["raw", "vae"] = "raw"
    """raw: image + attributes (Dreamer); vae: the frozen VAE means [u_v, u_attr] as one vector
    (the paper's VAE-Dreamer)"""
    size: Literal["2m", "12m", "40m"] | None = None
    """model size of the paper's table (default 2m Simple Shapes, 12m RoboDesk)"""
    seed: int = 1
    """seed of the environments, the networks and the replay sampling"""
    exp_name: str = "dreamer"
    """run name prefix: runs/<exp_name>_<obs>_<size>_<env>[_<task>]_s<seed>"""
    device: str = "cuda" if torch.cuda.is_available() else "cpu"
    """torch device"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default)"""
    compile: bool = False
    """run the update's losses through torch.compile (on a GPU with CUDA graphs, mode "reduce-overhead");
    compiling takes minutes at start, and a non-finite loss is then caught at the next log line or save
    rather than at once (docs/dreamer_baseline.md)"""
    cpu_preset: bool = False
    """RoboDesk at the scale of gw_dreamer.py's --cpu-preset on a 2-core CPU (CPU_TABLE): the table's 2M
    model instead of 12M, fast-rendered images, 800,000 frames, an evaluation every 100,000; flags given
    explicitly win. Simple Shapes runs at the paper's sizes already: there it changes nothing"""

    # network sizes beyond the table's (tests and quick CPU runs; None: the size's value)
    deter: int | None = None
    """GRU recurrent units (deterministic state h_t)"""
    hidden: int | None = None
    """RSSM hidden dimension (the layers around the GRU and the prior/posterior)"""
    units: int | None = None
    """dense hidden units of the encoders, decoders, heads, actor and critic"""
    cnn_depth: int | None = None
    """channels of the first image-encoder convolution (doubled per stage)"""
    layers: int | None = None
    """hidden layers of every MLP"""
    classes: int | None = None
    """classes of each of the 32 categorical latents"""

    # frozen VAEs (--obs vae)
    checkpoint_dir: str = "checkpoints"
    """where pretrain_vae_gw.py wrote <env>/vae.pt; agent checkpoints go to <env>/agents/"""
    vae_checkpoint: str | None = None
    """VAE checkpoint for --obs vae (default <checkpoint_dir>/<env>/vae.pt)"""

    # training (appendix Table "Hyperparameters used during Dreamer training")
    total_steps: int | None = None
    """environment steps (default 400,000 Simple Shapes, 1,000,000 RoboDesk)"""
    num_envs: int = 1
    """environments stepped together"""
    learning_starts: int = 1_000
    """random-policy steps that fill the replay buffer before the first update"""
    buffer_size: int = 1_000_000
    """replay capacity in transitions (memory is only touched as it fills)"""
    batch_size: int = 16
    """replayed sequences per update"""
    batch_length: int = 65
    """entries per replayed sequence"""
    train_ratio: float = 32.0
    """replayed steps per environment step (DreamerV3's meaning): one update of batch_size x
    batch_length replayed steps every batch_size x batch_length / train_ratio environment steps"""
    imag_horizon: int = 15
    """imagined steps per rollout"""
    wm_lr: float | None = None
    """world-model Adam learning rate (default 1e-3 Simple Shapes, 3e-4 RoboDesk)"""
    ac_lr: float = 3e-4
    """actor and critic Adam learning rate"""
    kl_free: float = 1.0
    """free nats of each KL term (DreamerV3)"""
    kl_dyn: float = 0.5
    """weight of the dynamics KL, KL(sg(posterior) || prior)"""
    kl_rep: float = 0.1
    """weight of the representation KL, KL(posterior || sg(prior))"""
    unimix: float = 0.01
    """uniform mix of the latent and discrete-action categoricals"""
    gamma: float = 1 - 1 / 333
    """discount (DreamerV3)"""
    lam: float = 0.95
    """lambda of the lambda-returns"""
    entropy_coef: float = 3e-4
    """actor entropy regulariser (DreamerV3)"""
    slow_critic_decay: float = 0.98
    """EMA decay of the slow critic that regularises the critic (DreamerV3)"""
    return_norm_decay: float = 0.99
    """EMA decay of the return scale max(1, P95 - P5) (DreamerV3)"""
    actor_grad: Literal["auto", "reinforce", "dynamics"] = "auto"
    """actor gradient: REINFORCE (discrete actions) or backpropagation through the imagined dynamics
    (continuous actions), as DreamerV3; auto picks by the action space"""

    # environments
    render_quality: Literal["faithful", "fast"] | None = None
    """RoboDesk image quality; default: --obs vae that of the images its VAE was trained on (another one is
    refused), --obs raw faithful (fast with --cpu-preset, as GW-Dreamer's CPU runs) (docs/environments.md)"""
    episode_length: int = 2000
    """RoboDesk episode length in physics-control repeats (paper: 2000, i.e. 500 agent steps)"""

    # evaluation, logging, checkpoints
    eval_every: int | None = None
    """environment steps between evaluations (default 10,000; 100,000 with RoboDesk's --cpu-preset)"""
    eval_episodes: int = 10
    """episodes per evaluation (and for --eval-only)"""
    criterion: float | None = None
    """normalised return that defines the return criterion (default 0.75 Simple Shapes, 0.70 RoboDesk:
    the paper's 70%)"""
    smoothing: int = 10
    """training episodes in the sliding window of the smoothed return (paper: 10)"""
    stop_at_criterion: bool = False
    """end the run (final evaluation, checkpoint) once the return criterion is reached: measures the
    steps and wall time to the criterion without training on"""
    video_every: int = 50_000
    """environment steps between dream filmstrips (raw observations; 0: only at the end)"""
    log_every: int = 1_000
    """environment steps between TensorBoard scalars and progress lines"""
    save_every: int = 20_000
    """environment steps between resumable checkpoints"""
    save_minutes: float = 15.0
    """wall-clock minutes after which a resumable checkpoint is written even if --save-every steps have
    not passed (a run stopped without warning loses at most this much)"""
    resume: bool = False
    """continue the run stored at --checkpoint (default: this run's agent checkpoint)"""
    overwrite: bool = False
    """replace an earlier run of the same name (its agent checkpoint, exported policy and runs/ folder);
    without it a run whose files exist stops at start"""
    checkpoint: str | None = None
    """agent checkpoint (default <checkpoint_dir>/<env>/agents/<run name>.pt)"""
    eval_only: bool = False
    """only evaluate --checkpoint (the modality ablation with --drop) and exit"""
    drop: Literal["none", "vision", "attr"] = "none"
    """modality removed at evaluation: its input is zeroed (the image, or u_v for --obs vae)"""

    def resolve(self) -> Args:
        """Per-environment defaults of the tables (TABLE, and CPU_TABLE under --cpu-preset), then the
        size's network widths. --obs vae reads its render quality from the VAE (load_frozen)."""
        table = TABLE[self.env] | (CPU_TABLE.get(self.env, {}) if self.cpu_preset else {})
        for name, value in table.items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.render_quality is None and (self.obs == "raw" or self.env == "simple_shapes"):
            self.render_quality = "fast" if self.cpu_preset and self.env == "robodesk" else "faithful"
        for name, value in MODEL_SIZES[self.size].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.deter % BLOCKS:
            raise UsageError(f"--deter {self.deter}: must be a multiple of the GRU's {BLOCKS} blocks")
        return self


# The flags whose defaults differ between the environments (appendix Table "Hyperparameters used during
# Dreamer training"; the step counts are the scale of the paper's Figure 3).
TABLE = {
    "simple_shapes": dict(criterion=0.75, total_steps=400_000, wm_lr=1e-3, size="2m", eval_every=10_000),
    "robodesk": dict(criterion=0.70, total_steps=1_000_000, wm_lr=3e-4, size="12m", eval_every=10_000),
}


# RoboDesk under --cpu-preset: the 2M model on the images of GW-Dreamer's CPU runs, to 800,000 frames (the
# paper's Dreamer criterion, about 4x GW-Dreamer's); an evaluation's 10 episodes are 20,000 frames of acting.
CPU_TABLE = {"robodesk": dict(size="2m", total_steps=800_000, eval_every=100_000)}


# Appendix table "Architecture details used in Dreamer baseline": GRU recurrent units (deter), dense hidden
# units (units), RSSM hidden dimension (hidden) and the total size. The table does not give the CNN depth,
# the MLP depth or the latent classes; they are chosen so that the printed total matches the table's
# within 10% (tested). The totals also fix two readings:
# - the recurrent core is DreamerV3's block-diagonal GRU (8 blocks): a dense GRU of 4,096 units alone has
#   over 55M weights, more than the 40M model;
# - 32 latents of 32 classes (2023 DreamerV3) fit 40M, but at 12M the heads reading [h, z] would alone
#   push the total past 13.2M, so the smaller models use 16 classes, as DreamerV3's own 12M preset does.
MODEL_SIZES = {
    "2m": {"deter": 512, "hidden": 128, "units": 128, "cnn_depth": 8, "layers": 1, "classes": 16},
    "12m": {"deter": 2048, "hidden": 384, "units": 256, "cnn_depth": 4, "layers": 1, "classes": 16},
    "40m": {"deter": 4096, "hidden": 384, "units": 512, "cnn_depth": 8, "layers": 2, "classes": 32},
}
TABLE_TOTALS = {"2m": 2e6, "12m": 12e6, "40m": 40e6}
TAG = "dreamer"  # the prefix of every line this script prints
BLOCKS = 8  # blocks of the block-diagonal GRU
STOCH = 32  # categorical latents (DreamerV3); their class count is a size setting
ENV_SPECS = {  # must agree with envs/ and pretrain_vae_gw.py
    "simple_shapes": {"image": 32, "attr": 11, "latent": 10, "actions": 7},
    "robodesk": {"image": 64, "attr": 76, "latent": 40, "actions": 5},
}


# --------------------------------------------------------------------------------------------------
# Symlog and two-hot (DreamerV3): rewards and values as 255-bin distributions over symlog(y)
# --------------------------------------------------------------------------------------------------
def symlog(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.expm1(x.abs())


class TwoHot(nn.Module):
    """Bins evenly spaced on symlog values in [-20, 20]."""

    def __init__(self, n_bins: int = 255, low: float = -20.0, high: float = 20.0):
        super().__init__()
        self.register_buffer("bins", torch.linspace(low, high, n_bins))

    def encode(self, y: torch.Tensor) -> torch.Tensor:
        """Targets y (...,) -> two-hot weights (..., n_bins) on the bins around symlog(y)."""
        x = symlog(y).clamp(self.bins[0], self.bins[-1])
        hi = torch.searchsorted(self.bins, x.contiguous(), right=True).clamp(1, len(self.bins) - 1)
        lo = hi - 1
        w_hi = (x - self.bins[lo]) / (self.bins[hi] - self.bins[lo])
        out = torch.zeros(*x.shape, len(self.bins), device=x.device)
        out.scatter_(-1, lo.unsqueeze(-1), (1 - w_hi).unsqueeze(-1))
        out.scatter_add_(-1, hi.unsqueeze(-1), w_hi.unsqueeze(-1))
        return out

    def mean(self, logits: torch.Tensor) -> torch.Tensor:
        """Expected value: symexp of the softmax-weighted bin."""
        return symexp((logits.softmax(-1) * self.bins).sum(-1))

    def loss(self, logits: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Cross-entropy to the two-hot target of y, per element."""
        return -(self.encode(y) * logits.log_softmax(-1)).sum(-1)


# --------------------------------------------------------------------------------------------------
# Networks (DreamerV3: LayerNorm + SiLU everywhere)
# --------------------------------------------------------------------------------------------------
def dense(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(cin, cout, bias=False), nn.LayerNorm(cout), nn.SiLU())


def mlp(cin: int, units: int, cout: int, layers: int, zero_out: bool = False) -> nn.Sequential:
    hidden = [dense(cin if i == 0 else units, units) for i in range(layers)]
    out = nn.Linear(units if layers else cin, cout)
    if zero_out:  # reward and critic start predicting 0 (DreamerV3)
        nn.init.zeros_(out.weight)
        nn.init.zeros_(out.bias)
    return nn.Sequential(*hidden, out)


class ChannelNorm(nn.Module):
    """LayerNorm over the channels of an image tensor (N, C, H, W)."""

    def __init__(self, c: int):
        super().__init__()
        self.norm = nn.LayerNorm(c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


def cnn_channels(image: int, depth: int) -> list[int]:
    """Stride-2 stages down to 4x4 pixels, channels doubling from ``depth``."""
    return [depth * 2**i for i in range(int(np.log2(image // 4)))]


class Encoder(nn.Module):
    """Image -> CNN (kernel 4, stride 2) features; vector (attributes or [u_v, u_attr]) -> MLP on its
    symlog; the embedding is their concatenation."""

    def __init__(self, spaces: dict[str, tuple[int, ...]], depth: int, units: int, layers: int):
        super().__init__()
        self.image_key = "image" if "image" in spaces else None
        self.vec_keys = [k for k in spaces if k != "image"]
        self.out_dim = 0
        if self.image_key:
            size = spaces["image"][0]
            convs, cin = [], 3
            for c in cnn_channels(size, depth):
                convs += [nn.Conv2d(cin, c, 4, 2, 1, bias=False), ChannelNorm(c), nn.SiLU()]
                cin = c
            self.cnn = nn.Sequential(*convs, nn.Flatten())
            self.out_dim += cin * 16
        vec = sum(spaces[k][0] for k in self.vec_keys)
        self.mlp = nn.Sequential(*[dense(vec if i == 0 else units, units) for i in range(layers)])
        self.out_dim += units

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        lead = obs[self.vec_keys[0]].shape[:-1]
        parts = []
        if self.image_key:
            img = obs["image"].reshape(-1, *obs["image"].shape[-3:]).permute(0, 3, 1, 2).float() / 255.0 - 0.5
            parts.append(self.cnn(img).reshape(*lead, -1))
        vec = torch.cat([obs[k].float() for k in self.vec_keys], -1)
        parts.append(self.mlp(symlog(vec)))
        return torch.cat(parts, -1)


class Decoder(nn.Module):
    """Features -> image (transposed CNN, mean of a unit Gaussian on pixels - 0.5) and vector (MLP,
    symlog targets)."""

    def __init__(self, spaces: dict[str, tuple[int, ...]], feat: int, depth: int, units: int, layers: int):
        super().__init__()
        self.spaces = spaces
        self.image_key = "image" if "image" in spaces else None
        self.vec_keys = [k for k in spaces if k != "image"]
        if self.image_key:
            chans = cnn_channels(spaces["image"][0], depth)[::-1]
            self.c0 = chans[0]
            self.fc = nn.Linear(feat, chans[0] * 16)
            ups = []
            for cin, cout in zip(chans, chans[1:], strict=False):
                ups += [nn.ConvTranspose2d(cin, cout, 4, 2, 1, bias=False), ChannelNorm(cout), nn.SiLU()]
            self.up = nn.Sequential(*ups, nn.ConvTranspose2d(chans[-1], 3, 4, 2, 1))
        vec = sum(spaces[k][0] for k in self.vec_keys)
        self.mlp = mlp(feat, units, vec, layers)

    def loss(self, feat: torch.Tensor, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Negative log-likelihoods (summed squared errors) per entry, one per modality."""
        out = {}
        if self.image_key:
            target = obs["image"].permute(0, 1, 4, 2, 3).float() / 255.0 - 0.5  # (B, T, 3, H, W)
            pred = self.image(feat)
            out["image"] = ((pred - target) ** 2).sum((-3, -2, -1))
        vec = torch.cat([obs[k].float() for k in self.vec_keys], -1)
        out["vector"] = ((self.mlp(feat) - symlog(vec)) ** 2).sum(-1)
        return out

    def image(self, feat: torch.Tensor) -> torch.Tensor:
        """Decoded image in [-0.5, 0.5] units, (..., 3, H, W)."""
        x = self.fc(feat.reshape(-1, feat.shape[-1])).view(-1, self.c0, 4, 4)
        x = self.up(x)
        return x.reshape(*feat.shape[:-1], *x.shape[1:])


class BlockLinear(nn.Module):
    """``blocks`` independent linear maps, (..., blocks, cin) -> (..., blocks, cout)."""

    def __init__(self, blocks: int, cin: int, cout: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(blocks, cin, cout))
        self.bias = nn.Parameter(torch.zeros(blocks, cout))
        nn.init.uniform_(self.weight, -1 / math.sqrt(cin), 1 / math.sqrt(cin))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.einsum("...gi,gio->...go", x, self.weight) + self.bias

    def mixed(self, own: torch.Tensor, shared: torch.Tensor) -> torch.Tensor:
        """``forward`` of each block's own input (n, blocks, k) concatenated with an input all blocks share
        (n, s), without copying the shared input per block: its part of every block's map is one (s,
        blocks x cout) product."""
        n, g, k = own.shape
        w_shared = self.weight[:, k:].permute(1, 0, 2).reshape(shared.shape[-1], -1)
        out = torch.einsum("ngi,gio->ngo", own, self.weight[:, :k]) + (shared @ w_shared).view(n, g, -1)
        return out + self.bias


class RSSM(nn.Module):
    """Recurrent state-space model: h_t = GRU(h_{t-1}, z_{t-1}, a_{t-1}); prior p(z_t | h_t); posterior
    q(z_t | h_t, embed(o_t)); z_t is 32 one-hot categoricals of 32 classes."""

    def __init__(self, embed: int, actions: int, deter: int, hidden: int, classes: int, unimix: float):
        super().__init__()
        self.deter, self.classes, self.unimix, self.g = deter, classes, unimix, BLOCKS
        self.stoch = STOCH * classes
        self.dynin = nn.ModuleList([dense(deter, hidden), dense(self.stoch, hidden), dense(actions, hidden)])
        self.dynhid = BlockLinear(BLOCKS, deter // BLOCKS + 3 * hidden, deter // BLOCKS)
        self.dynnorm = nn.LayerNorm(deter)
        self.dyngru = BlockLinear(BLOCKS, deter // BLOCKS, 3 * deter // BLOCKS)
        self.prior = nn.Sequential(dense(deter, hidden), nn.Linear(hidden, self.stoch))
        self.post = nn.Sequential(dense(deter + embed, hidden), nn.Linear(hidden, self.stoch))

    def initial(self, n: int, dev) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.zeros(n, self.deter, device=dev), torch.zeros(n, self.stoch, device=dev)

    def core(self, deter: torch.Tensor, stoch: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Block-diagonal GRU step (DreamerV3): each of the 8 blocks of h sees its own slice of h and all of
        the mixed inputs; update gate biased toward keeping h (sigmoid(u - 1))."""
        n, g = deter.shape[0], self.g
        action = action / action.abs().clamp(min=1).detach()
        x = torch.cat([self.dynin[0](deter), self.dynin[1](stoch), self.dynin[2](action)], -1)
        x = F.silu(self.dynnorm(self.dynhid.mixed(deter.view(n, g, -1), x).reshape(n, -1))).view(n, g, -1)
        # The gates stay (n, blocks, units): the block views are read in place, not copied out.
        reset, cand, update = self.dyngru(x).chunk(3, -1)
        cand = torch.tanh(torch.sigmoid(reset) * cand)
        update = torch.sigmoid(update - 1)
        return (update * cand + (1 - update) * deter.view(n, g, -1)).reshape(n, -1)

    def probs(self, logits: torch.Tensor) -> torch.Tensor:
        """Class probabilities with the 1% uniform mix, (..., 32, 32)."""
        p = logits.unflatten(-1, (STOCH, self.classes)).softmax(-1)
        return (1 - self.unimix) * p + self.unimix / self.classes

    def sample(self, logits: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """One-hot samples with straight-through gradients, flattened to (..., 1024). ``noise``: uniform
        numbers for Gumbel-max sampling (the exported policy gets its randomness as an input)."""
        p = self.probs(logits)
        if noise is None:
            noise = torch.rand_like(p)
        gumbel = -torch.log(-torch.log(noise.clamp(1e-9, 1 - 1e-7)))
        one_hot = F.one_hot((p.log() + gumbel).argmax(-1), self.classes).to(p.dtype)
        return (one_hot + p - p.detach()).flatten(-2)

    def img_step(self, deter, stoch, action):
        deter = self.core(deter, stoch, action)
        return deter, self.sample(self.prior(deter))

    def obs_step(self, deter, stoch, action, embed, first, noise=None):
        """One filtering step; ``first`` (n,) restarts the state and previous action at an episode start."""
        keep = (1 - first).unsqueeze(-1)
        deter = self.core(deter * keep, stoch * keep, action * keep)
        prior_logits = self.prior(deter)
        post_logits = self.post(torch.cat([deter, embed], -1))
        return deter, self.sample(post_logits, noise), post_logits, prior_logits

    def kl(self, post_logits: torch.Tensor, prior_logits: torch.Tensor) -> torch.Tensor:
        """KL(post || prior) summed over the 32 latents."""
        p, q = self.probs(post_logits), self.probs(prior_logits)
        return (p * (p.log() - q.log())).sum((-2, -1))


class Actor(nn.Module):
    """Discrete: categorical with 1% uniform mix. Continuous: Gaussian with tanh mean and std in [0.1, 1],
    samples clipped to the action box (DreamerV3)."""

    def __init__(self, feat: int, units: int, layers: int, n_actions: int, discrete: bool, unimix: float):
        super().__init__()
        self.discrete, self.n, self.unimix = discrete, n_actions, unimix
        self.net = mlp(feat, units, n_actions if discrete else 2 * n_actions, layers)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        """The network's output: logits, or the mean and std before their squashing."""
        return self.net(feat)

    def params(self, out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Class probabilities (discrete) or Gaussian mean and std (continuous) of the output ``out``."""
        if self.discrete:
            return (1 - self.unimix) * out.softmax(-1) + self.unimix / self.n, None
        mean, std = out.chunk(2, -1)
        return torch.tanh(mean), 0.9 * torch.sigmoid(std + 2.0) + 0.1

    def dist(self, out: torch.Tensor) -> torch.distributions.Distribution:
        a, b = self.params(out)
        if self.discrete:
            return torch.distributions.Categorical(probs=a)
        return torch.distributions.Independent(torch.distributions.Normal(a, b), 1)

    def act(self, feat: torch.Tensor, mode: bool = False, noise: torch.Tensor | None = None) -> torch.Tensor:
        """One-hot (discrete) or a vector in [-1, 1]. ``noise``: uniform (discrete, Gumbel-max) or
        standard normal (continuous) numbers given from outside (the exported policy); without it the
        sample is drawn here (reparameterised for continuous actions)."""
        return self.sample(self(feat), mode, noise)

    def sample(self, out: torch.Tensor, mode: bool = False, noise: torch.Tensor | None = None):
        """``act`` from the network's output ``out``."""
        probs, std = self.params(out)
        if self.discrete:
            if mode:
                return F.one_hot(probs.argmax(-1), self.n).float()
            if noise is None:
                noise = torch.rand_like(probs)
            gumbel = -torch.log(-torch.log(noise.clamp(1e-9, 1 - 1e-7)))
            return F.one_hot((probs.log() + gumbel).argmax(-1), self.n).float()
        mean = probs
        if mode:
            return mean.clamp(-1, 1)
        if noise is None:
            noise = torch.randn_like(mean)
        return (mean + std * noise).clamp(-1, 1)

    def log_prob(self, out: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Log-probability of ``a`` and the entropy, from the network's output ``out``."""
        d = self.dist(out)
        return d.log_prob(a.argmax(-1) if self.discrete else a), d.entropy()


class ReturnScale(nn.Module):
    """DreamerV3's return scale S = EMA of P95 - P5 of the lambda-returns; advantages are divided by
    max(1, S). Bias-corrected like Adam's moments: the EMA starts at 0, and dividing by its raw value over
    the first updates would blow the advantages up by up to 100x. Its state is part of the agent."""

    def __init__(self, decay: float = 0.99):
        super().__init__()
        self.decay = decay
        # One element rather than a 0-d tensor: torch.compile (2.13, CPU) drops writes to 0-d float64 buffers.
        self.register_buffer("ema", torch.zeros(1, dtype=torch.float64))
        self.register_buffer("count", torch.zeros(1, dtype=torch.float64))

    def update(self, returns: torch.Tensor) -> torch.Tensor:
        """Fold in one batch of returns; the debiased scale S (a tensor, no host sync)."""
        lo, hi = torch.quantile(returns.detach(), torch.tensor([0.05, 0.95], device=returns.device))
        ema = self.decay * self.ema + (1 - self.decay) * (hi - lo).double()
        count = self.count + 1
        self.ema.copy_(ema)
        self.count.copy_(count)
        return ema / (1 - self.decay**count)


class Agent(nn.Module):
    """World model (encoder, RSSM, decoder, reward and continue heads), actor, critic, slow critic and
    the return scale."""

    def __init__(self, env: str, spaces: dict[str, tuple[int, ...]], args: Args):
        super().__init__()
        s = ENV_SPECS[env]
        self.discrete = env == "simple_shapes"
        self.n_actions = s["actions"]
        self.twohot = TwoHot()
        self.encoder = Encoder(spaces, args.cnn_depth, args.units, args.layers)
        self.rssm = RSSM(
            self.encoder.out_dim, s["actions"], args.deter, args.hidden, args.classes, args.unimix
        )
        self.feat_dim = args.deter + self.rssm.stoch
        self.decoder = Decoder(spaces, self.feat_dim, args.cnn_depth, args.units, args.layers)
        self.reward_head = mlp(self.feat_dim, args.units, 255, args.layers, zero_out=True)
        self.cont_head = mlp(self.feat_dim, args.units, 1, args.layers)
        self.actor = Actor(self.feat_dim, args.units, args.layers, s["actions"], self.discrete, args.unimix)
        self.critic = mlp(self.feat_dim, args.units, 255, args.layers, zero_out=True)
        self.slow_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.return_scale = ReturnScale(args.return_norm_decay)

    def world_model_parameters(self) -> list[nn.Parameter]:
        parts = (self.encoder, self.rssm, self.decoder, self.reward_head, self.cont_head)
        return [p for m in parts for p in m.parameters()]

    def n_trainable(self) -> dict[str, int]:
        wm = sum(p.numel() for p in self.world_model_parameters())
        actor = sum(p.numel() for p in self.actor.parameters())
        critic = sum(p.numel() for p in self.critic.parameters())
        return {"world_model": wm, "actor": actor, "critic": critic, "total": wm + actor + critic}


def feat_of(deter: torch.Tensor, stoch: torch.Tensor) -> torch.Tensor:
    return torch.cat([deter, stoch], -1)


def heads(x: torch.Tensor, *nets: nn.Sequential) -> list[torch.Tensor]:
    """Several ``mlp`` heads on the same input, their first linear maps as one product: a dream's features
    (H + 1, N, F) are read once, and backward gives one gradient for them rather than one per head."""
    if not all(isinstance(n[0], nn.Sequential) for n in nets):  # heads without hidden layers
        return [n(x) for n in nets]
    first = [n[0][0] for n in nets]
    hidden = F.linear(x, torch.cat([f.weight for f in first])).split([f.out_features for f in first], -1)
    return [n[1:](n[0][1:](y)) for n, y in zip(nets, hidden, strict=True)]


# --------------------------------------------------------------------------------------------------
# Replay buffer: one stream per environment of DreamerV3 entries
# (o_t, a_{t-1}, r_t, terminal_t, first_t): the observation, the action that led to it, the reward
# received with it, whether it ends the episode, whether it starts one.
# --------------------------------------------------------------------------------------------------
class Replay:
    def __init__(self, capacity: int, num_envs: int, spaces: dict, action_dim: int, seed: int):
        self.cap = max(capacity // num_envs, 2)
        self.n = num_envs
        self.data = {
            k: np.zeros((num_envs, self.cap, *shape), np.uint8 if k == "image" else np.float32)
            for k, shape in spaces.items()
        }
        self.data |= {
            "action": np.zeros((num_envs, self.cap, action_dim), np.float32),
            "reward": np.zeros((num_envs, self.cap), np.float32),
            "terminal": np.zeros((num_envs, self.cap), np.float32),
            "first": np.zeros((num_envs, self.cap), np.float32),
        }
        self.pos = np.zeros(num_envs, np.int64)  # next write index per stream
        self.count = np.zeros(num_envs, np.int64)  # entries written per stream (not capped)
        self.rng = np.random.default_rng(seed)

    def add(self, env_idx: np.ndarray, entry: dict[str, np.ndarray]) -> None:
        for j, i in enumerate(env_idx):
            p = self.pos[i]
            for k, v in entry.items():
                self.data[k][i, p] = v[j]
            self.pos[i] = (p + 1) % self.cap
            self.count[i] += 1

    def __len__(self) -> int:
        return int(np.minimum(self.count, self.cap).sum())

    def ready(self, length: int) -> bool:
        return bool(np.all(np.minimum(self.count, self.cap) >= length))

    def sample(self, batch: int, length: int) -> dict[str, np.ndarray]:
        """``batch`` windows of ``length`` consecutive entries; each window's first entry is treated as
        an episode start (the state restarts there, as DreamerV3 without replayed latents)."""
        envs_ = self.rng.integers(0, self.n, batch)
        filled = np.minimum(self.count[envs_], self.cap)
        oldest = np.where(self.count[envs_] > self.cap, self.pos[envs_], 0)
        start = oldest + (self.rng.random(batch) * (filled - length + 1)).astype(np.int64)
        idx = (start[:, None] + np.arange(length)[None]) % self.cap
        out = {k: v[envs_[:, None], idx] for k, v in self.data.items()}
        out["first"][:, 0] = 1.0
        return out

    def state_dict(self) -> dict:
        """Only the filled part of each stream is saved (a full-size buffer of images is gigabytes)."""
        used = int(np.minimum(self.count, self.cap).max())
        data = {k: v[:, :used].copy() for k, v in self.data.items()}
        return {"data": data, "pos": self.pos, "count": self.count, "rng": self.rng.bit_generator.state}

    def load_state_dict(self, s: dict) -> None:
        for k, v in s["data"].items():
            if v.shape[0] != self.n or v.shape[2:] != self.data[k].shape[2:]:
                raise ValueError(f"replay entry {k!r} of shape {v.shape} does not fit this run")
            self.data[k][:, : v.shape[1]] = v
        self.pos, self.count = s["pos"], s["count"]
        self.rng.bit_generator.state = s["rng"]


# --------------------------------------------------------------------------------------------------
# Losses
# --------------------------------------------------------------------------------------------------
def observe(agent: Agent, batch: dict[str, torch.Tensor]):
    """Posterior states along replayed sequences: deter, stoch, post_logits, prior_logits, each (B, T, .)."""
    embed = agent.encoder({k: batch[k] for k in agent.encoder.vec_keys + ["image"] if k in batch})
    B, T = batch["first"].shape
    deter, stoch = agent.rssm.initial(B, embed.device)
    outs = []
    for t in range(T):
        deter, stoch, post, prior = agent.rssm.obs_step(
            deter, stoch, batch["action"][:, t], embed[:, t], batch["first"][:, t]
        )
        outs.append((deter, stoch, post, prior))
    return [torch.stack(x, 1) for x in zip(*outs, strict=True)]


def world_model_loss(agent: Agent, batch: dict[str, torch.Tensor], args: Args):
    """DreamerV3: prediction (decoders, two-hot reward, continue) + kl_dyn max(free, KL(sg(q) || p)) +
    kl_rep max(free, KL(q || sg(p))), averaged over the replayed entries. Returns the loss, its terms and
    the posterior states (imagination starts)."""
    deter, stoch, post, prior = observe(agent, batch)
    feat = feat_of(deter, stoch)
    rec = agent.decoder.loss(feat, batch)
    loss_rew = agent.twohot.loss(agent.reward_head(feat), batch["reward"])
    cont_logit = agent.cont_head(feat).squeeze(-1)
    loss_cont = F.binary_cross_entropy_with_logits(cont_logit, 1 - batch["terminal"], reduction="none")
    kl_dyn = agent.rssm.kl(post.detach(), prior)
    kl_rep = agent.rssm.kl(post, prior.detach())
    loss_dyn, loss_rep = kl_dyn.clamp(min=args.kl_free), kl_rep.clamp(min=args.kl_free)
    total = sum(rec.values()) + loss_rew + loss_cont + args.kl_dyn * loss_dyn + args.kl_rep * loss_rep
    terms = {f"loss_{k}": v.mean() for k, v in rec.items()}
    terms |= {"loss_reward": loss_rew.mean(), "loss_cont": loss_cont.mean(), "kl": kl_dyn.mean()}
    return total.mean(), terms, (deter, stoch)


class Dream(NamedTuple):
    """An imagined rollout of H steps from N starts: the actor-critic's inputs (H + 1, N, ...), the
    actions taken (H, N, A), the predicted rewards and continuation probabilities (H, N), and the actor's
    outputs that drew the actions (H, N, ...) when the rollout is differentiable, with their graph (the
    actor-critic loss reads them rather than running the actor again; None otherwise)."""

    feats: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    conts: torch.Tensor
    policy: torch.Tensor | None = None


def rollout(agent: Agent, deter: torch.Tensor, stoch: torch.Tensor, horizon: int, grad: bool):
    """Dream ``horizon`` steps with the actor from the given states: features (H + 1, N, F), actions
    (H, N, A) and, with ``grad`` (the rollout differentiable: dynamics backpropagation for continuous
    actions), the actor's outputs that drew them (else None)."""
    with torch.set_grad_enabled(grad):
        feats, actions, outs = [feat_of(deter, stoch)], [], []
        for _ in range(horizon):
            # The actor reads the dreamt state with its gradient stopped, as DreamerV3's policy(sg(s)):
            # an action's gradient is that of the returns after it, never through the actor's reply to
            # states its own earlier actions made (that path trains period-2 alternation on RoboDesk).
            outs.append(agent.actor(feats[-1].detach()))
            a = agent.actor.sample(outs[-1])
            deter, stoch = agent.rssm.img_step(deter, stoch, a)
            feats.append(feat_of(deter, stoch))
            actions.append(a)
        return torch.stack(feats), torch.stack(actions), torch.stack(outs) if grad else None


def dream_of(agent: Agent, feats, actions, policy, reward_logits, cont_logits) -> Dream:
    """The Dream of a rollout from its heads' outputs on every dreamt state, the start included: the
    rewards and continue probabilities of states 1..H are a slice of those small outputs rather than of
    the large features, whose gradient is then one product (``heads``)."""
    rewards = agent.twohot.mean(reward_logits[1:])
    return Dream(feats, actions, rewards, torch.sigmoid(cont_logits[1:].squeeze(-1)), policy)


def lambda_returns(rewards, conts, values, gamma: float, lam: float) -> torch.Tensor:
    """R_k = r_{k+1} + gamma c_{k+1} ((1 - lam) v_{k+1} + lam R_{k+1}), R_H = v_H (DreamerV3)."""
    out, last = [], values[-1]
    for k in reversed(range(len(rewards))):
        last = rewards[k] + gamma * conts[k] * ((1 - lam) * values[k + 1] + lam * last)
        out.append(last)
    return torch.stack(out[::-1])


def actor_critic_loss(
    agent: Agent,
    dream: Dream,
    start_w,
    *,
    dynamics=False,
    gamma=1 - 1 / 333,
    lam=0.95,
    entropy_coef=3e-4,
    value_logits=None,
):
    """DreamerV3 actor-critic on an imagined rollout. Advantages are normalised by the return scale
    max(1, S) (``ReturnScale``). The actor uses REINFORCE, or (``dynamics``) the gradient of the
    normalised lambda-return through the differentiable rollout; both with an entropy bonus. The two-hot
    critic fits the lambda-returns and is regularised toward its slow copy. ``value_logits``: the critic on
    ``dream.feats``, computed by the caller in the reward and continue heads' product (``heads``)."""
    feats, conts = dream.feats, dream.conts
    # With dynamics the values stay differentiable through the rollout for the actor; each loss is
    # back-propagated into its own network only (train_update), so the critic's loss trains the critic
    # alone. Without given logits one critic pass serves both; given ones are left to the actor's
    # gradient, and the critic's loss gets a pass of its own: its backward then computes the weight
    # gradient of the critic only, not of the shared product.
    if value_logits is None:
        value_logits = agent.critic(feats)
        logits = value_logits[:-1]
    else:
        logits = agent.critic(feats[:-1].detach())
    values = agent.twohot.mean(value_logits if dynamics else value_logits.detach())
    returns = lambda_returns(dream.rewards, conts, values, gamma, lam)  # (H, N)
    with torch.no_grad():
        w = torch.cumprod(torch.cat([torch.ones_like(conts[:1]), conts[:-1]]), 0) * start_w
        scale = agent.return_scale.update(returns)
        norm = scale.clamp(min=1.0).to(returns.dtype)  # float64 state, float32 math
        slow_target = agent.twohot.mean(agent.slow_critic(feats[:-1].detach()))
    policy = agent.actor(feats[:-1].detach()) if dream.policy is None else dream.policy
    logp, entropy = agent.actor.log_prob(policy, dream.actions.detach())
    if dynamics:
        objective = (returns - values[:-1].detach()) / norm
    else:
        objective = logp * ((returns - values[:-1]) / norm).detach()
    loss_actor = -(w * (objective + entropy_coef * entropy)).mean()
    target = returns.detach()
    loss_critic = (w * (agent.twohot.loss(logits, target) + agent.twohot.loss(logits, slow_target))).mean()
    stats = {
        "return_scale": scale,
        "imag_return": returns.detach().mean(),
        "entropy": entropy.detach().mean(),
    }
    return loss_actor, loss_critic, stats


def count_flops(fn):
    """``fn()`` and the forward + backward FLOPs it took (torch.utils.flop_counter)."""
    with FlopCounterMode(display=False) as counter:
        out = fn()
    return out, counter.get_total_flops()


def updates_due(env_steps: int, args: Args) -> int:
    """Training updates owed after ``env_steps`` environment steps (the paper's unit: frames on
    RoboDesk). The table's train ratio 32 is DreamerV3's (replayed steps per agent step): a batch of
    16 x 65 = 1,040 replayed steps per update gives one update per 32.5 agent steps."""
    agent_steps = max(env_steps - args.learning_starts, 0) / ACTION_REPEAT[args.env]
    return int(agent_steps * args.train_ratio / (args.batch_size * args.batch_length))


def dream_loss(agent: Agent, deter0: torch.Tensor, stoch0: torch.Tensor, start_w, dynamics: bool, args: Args):
    """The actor-critic's part of an update: dreams from the replayed posterior states, then their loss.
    With dynamics backpropagation the critic joins the reward and continue heads' product (``heads``):
    the actor's backward then makes one gradient of the large dreamt features, not two and their sum."""
    feats, actions, policy = rollout(agent, deter0, stoch0, args.imag_horizon, grad=dynamics)
    with torch.set_grad_enabled(dynamics):
        nets = (agent.reward_head, agent.cont_head) + ((agent.critic,) if dynamics else ())
        reward_logits, cont_logits, *value_logits = heads(feats, *nets)
    return actor_critic_loss(
        agent,
        dream_of(agent, feats, actions, policy, reward_logits, cont_logits),
        start_w,
        value_logits=value_logits[0] if value_logits else None,
        dynamics=dynamics,
        gamma=args.gamma,
        lam=args.lam,
        entropy_coef=args.entropy_coef,
    )


EAGER = {"wm": world_model_loss, "ac": dream_loss}  # the two loss computations of an update


def compiled_losses(device, backend: str = "inductor") -> dict:
    """--compile: both loss computations through torch.compile, with CUDA graphs on a GPU. The optimizer
    steps stay eager; nothing in the compiled parts reads a value back to the host. (``backend``: the
    tests also use "aot_eager", the same graphs without generated kernels.)"""
    mode = "reduce-overhead" if str(device).startswith("cuda") else None
    # The actor's and the critic's losses come out of one compiled graph whose backward runs once per
    # loss (each reaches only its own network), so that graph keeps its buffers between the two calls.
    torch._functorch.config.donated_buffer = False
    return {k: torch.compile(fn, mode=mode, backend=backend) for k, fn in EAGER.items()}


def train_update(
    agent: Agent, opts: dict, replay: Replay, args: Args, env_step: int = 0, losses: dict = EAGER
) -> dict:
    """One training step: the world model on replayed sequences, then the actor-critic on rollouts
    dreamt from every replayed posterior state. Returns detached tensors, read once per log interval.
    Eager losses are checked at once (the bad update is not applied); compiled ones at the next log line
    or save (no host sync in the update)."""
    dev, check = agent.twohot.bins.device, losses is EAGER
    batch = {
        k: torch.as_tensor(v, device=dev)
        for k, v in replay.sample(args.batch_size, args.batch_length).items()
    }
    loss_wm, terms, (deter, stoch) = losses["wm"](agent, batch, args)
    if check and not torch.isfinite(loss_wm):
        raise FloatingPointError(f"non-finite world-model loss at env step {env_step:,}")
    opts["wm"].zero_grad(set_to_none=True)
    loss_wm.backward()
    nn.utils.clip_grad_norm_(agent.world_model_parameters(), 1000.0)
    opts["wm"].step()

    dynamics = args.actor_grad == "dynamics" or (args.actor_grad == "auto" and not agent.discrete)
    deter0, stoch0 = deter.detach().flatten(0, 1), stoch.detach().flatten(0, 1)
    start_w = (1 - batch["terminal"]).flatten()  # no dream from an episode's final observation
    loss_actor, loss_critic, stats = losses["ac"](agent, deter0, stoch0, start_w, dynamics, args)
    if check and not (torch.isfinite(loss_actor) and torch.isfinite(loss_critic)):
        raise FloatingPointError(f"non-finite actor-critic loss at env step {env_step:,}")
    opts["actor"].zero_grad(set_to_none=True)
    opts["critic"].zero_grad(set_to_none=True)
    # Each loss reaches only its own network (the world model is trained by L_WM alone); the first call
    # keeps the graph's buffers for the second (one graph when compiled).
    loss_actor.backward(inputs=list(agent.actor.parameters()), retain_graph=True)
    loss_critic.backward(inputs=list(agent.critic.parameters()))
    nn.utils.clip_grad_norm_(agent.actor.parameters(), 100.0)
    nn.utils.clip_grad_norm_(agent.critic.parameters(), 100.0)
    opts["actor"].step()
    opts["critic"].step()
    with torch.no_grad():  # slow critic: EMA of the critic
        for p_slow, p in zip(agent.slow_critic.parameters(), agent.critic.parameters(), strict=True):
            p_slow.lerp_(p, 1 - args.slow_critic_decay)
    out = {"loss_wm": loss_wm, **terms, "loss_actor": loss_actor, "loss_critic": loss_critic, **stats}
    return {k: v.detach().clone() for k, v in out.items()}  # a copy: CUDA graphs reuse their outputs


def make_optimizers(agent: Agent, args: Args) -> dict:
    """Adam per part with the table's rates (eps as DreamerV3)."""
    return {
        "wm": torch.optim.Adam(agent.world_model_parameters(), lr=args.wm_lr, eps=1e-8),
        "actor": torch.optim.Adam(agent.actor.parameters(), lr=args.ac_lr, eps=1e-5),
        "critic": torch.optim.Adam(agent.critic.parameters(), lr=args.ac_lr, eps=1e-5),
    }


# --------------------------------------------------------------------------------------------------
# DreamerV3's training loop
# --------------------------------------------------------------------------------------------------
def main(args: Args) -> dict:
    args = args.resolve()
    check_settings(args)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    dev = torch.device(args.device)
    observer, paths = load_frozen(args, dev)
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    agent = Agent(args.env, observer.spaces(args.env), args).to(dev)
    default = Path(args.checkpoint_dir) / args.env / "agents" / f"{run_name(args, args.obs)}.pt"
    agent_path = Path(args.checkpoint) if args.checkpoint else default
    if args.eval_only:
        return evaluate_checkpoint(agent, observer, args, agent_path, observer_fingerprint(observer))
    run = start_run(args, observer, agent, paths, agent_path)
    state, replay, ne, n_actions = run.state, run.replay, args.num_envs, agent.n_actions
    losses = compiled_losses(dev) if args.compile else EAGER

    envs_ = make_envs(args, ne)
    obs, _ = envs_.reset(seed=args.seed + state.env_steps)
    idx = np.arange(ne)
    deter, stoch = agent.rssm.initial(ne, dev)
    prev_a = torch.zeros(ne, n_actions, device=dev)
    reward, terminal, first = np.zeros(ne), np.zeros(ne), np.ones(ne)
    ep_ret, ep_succ = np.zeros(ne), np.zeros(ne)
    rng = np.random.default_rng(args.seed + state.env_steps)
    logs = {}
    stop = StopRequest(TAG)
    while state.env_steps < args.total_steps:
        if args.stop_at_criterion and state.criterion_step is not None:
            break
        # Store the entry (o_t, a_{t-1}, r_t, terminal_t, first_t), then act on the filtered state.
        o = observer(*as_tensors(obs, dev))
        entry = {k: v.cpu().numpy() for k, v in o.items()}
        replay.add(
            idx,
            entry | {"action": prev_a.cpu().numpy(), "reward": reward, "terminal": terminal, "first": first},
        )
        with torch.no_grad():
            embed = agent.encoder(o)
            first_t = torch.as_tensor(first, device=dev, dtype=torch.float32)
            deter, stoch, _, _ = agent.rssm.obs_step(deter, stoch, prev_a, embed, first_t)
            if state.env_steps < args.learning_starts:
                a = random_actions(rng, ne, n_actions, agent.discrete, dev)
            else:
                a = agent.actor.act(feat_of(deter, stoch))
        obs, r, term, trunc, info = envs_.step(action_for_env(a, agent.discrete))
        done = term | trunc
        ep_ret += r
        ep_succ += step_success(info, ne)
        state.env_steps += ne * ACTION_REPEAT[args.env]  # the paper's unit: simulator frames on RoboDesk
        prev_a, reward, terminal, first = a, r.astype(np.float64), term.astype(np.float64), np.zeros(ne)
        if done.any():
            # The final observation is its own entry; the reset observation starts the next episode.
            ends = np.flatnonzero(done)
            o_final = {
                k: v.cpu().numpy()
                for k, v in observer(*as_tensors(final_observations(info, ends), dev)).items()
            }
            last = {"action": a[ends].cpu().numpy(), "reward": r[ends], "terminal": term[ends].astype(float)}
            replay.add(ends, o_final | last | {"first": np.zeros(len(ends))})
            for i in ends:
                log_episode(run, float(ep_ret[i]), float(ep_succ[i]))
            ep_ret[ends], ep_succ[ends] = 0.0, 0.0
            reward[ends], terminal[ends], first[ends] = 0.0, 0.0, 1.0
            prev_a[torch.as_tensor(ends, device=dev)] = 0.0  # a new episode has no previous action

        # Train: the updates owed by the train ratio, once the buffer holds a full sequence.
        while state.updates < updates_due(state.env_steps, args) and replay.ready(args.batch_length):
            try:
                if state.flops_per_update == 0:  # same shapes every update: count the first one
                    logs, state.flops_per_update = count_flops(
                        lambda: train_update(agent, run.opts, replay, args, state.env_steps)
                    )
                else:
                    logs = train_update(agent, run.opts, replay, args, state.env_steps, losses)
            except FloatingPointError as err:
                raise FloatingPointError(f"{err}; {last_good(run.agent_path)}") from err
            state.updates += 1
            state.flops += state.flops_per_update

        # What is due at this step: the last update's losses and a progress line (--log-every), an
        # evaluation on fresh episodes (--eval-every), real frames beside a dream (--video-every), a save.
        if state.env_steps % args.log_every < ne * ACTION_REPEAT[args.env] and logs:
            log_progress(run, logs)
        if state.env_steps >= state.next_eval:
            state.next_eval += args.eval_every
            evaluate(run)
        if state.env_steps >= state.next_video:
            state.next_video += args.video_every or args.total_steps
            strip = dream_filmstrip(agent, observer, args, 16, seed=10**6)
            if strip is not None:  # raw observations: no decoder to draw a dream with
                run.writer.add_image(
                    "dreams/real_top_imagined_bottom", strip, state.env_steps, dataformats="HWC"
                )
        if save_due(run):
            save(run)
        if stop.requested:
            envs_.close()
            stop.restore()
            interrupted(run)
    stop.restore()
    envs_.close()
    return finish(run)


# --------------------------------------------------------------------------------------------------
# Environments and evaluation
# --------------------------------------------------------------------------------------------------
# Simulator frames per agent step. The paper counts RoboDesk "environment steps" in frames ("2,000
# environment steps but with an action repetition of 4 steps, leading to 500 chosen actions"), so step
# counts (--total-steps, criteria, logs) are frames there; Simple Shapes has no action repeat.
ACTION_REPEAT = {"simple_shapes": 1, "robodesk": 4}


def make_envs(args: Args, num_envs: int):
    """Vector env with same-step autoreset (info["final_obs"] holds the last observation)."""
    if args.env == "simple_shapes":
        from envs.simple_shapes import SimpleShapesVectorEnv

        return SimpleShapesVectorEnv(num_envs)
    from envs.robodesk import TASKS

    if args.task not in TASKS:
        raise UsageError(f"unknown RoboDesk task {args.task!r}; valid tasks: {', '.join(TASKS)}")
    fns = [
        lambda: gym.make(
            "RoboDesk-v0",
            task=args.task,
            render_quality=args.render_quality,
            action_repeat=ACTION_REPEAT["robodesk"],
            episode_length=args.episode_length,
        )
        for _ in range(num_envs)
    ]
    return gym.vector.SyncVectorEnv(fns, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


def final_observations(info: dict, ends: np.ndarray) -> dict[str, np.ndarray]:
    """Last observations of the episodes that ended (same-step autoreset)."""
    fo = info["final_obs"]
    if isinstance(fo, dict):
        return {k: v[ends] for k, v in fo.items()}
    return {k: np.stack([fo[i][k] for i in ends]) for k in fo[ends[0]]}


def step_success(info: dict, n: int) -> np.ndarray:
    """RoboDesk's per-step success flag; for an env that just reset, the flag of its final step."""
    if "success" not in info:
        return np.zeros(n)
    success = np.asarray(info["success"], float).copy()
    for i in np.flatnonzero(info.get("_final_info", np.zeros(n, bool))):
        success[i] = float(info["final_info"]["success"][i])
    return success


def action_for_env(a: torch.Tensor, discrete: bool) -> np.ndarray:
    return a.argmax(-1).cpu().numpy() if discrete else a.cpu().numpy().astype(np.float32)


def as_tensors(obs: dict[str, np.ndarray], dev) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.as_tensor(obs["image"], device=dev), torch.as_tensor(obs["attr"], device=dev).float()


class PolicyStep(nn.Module):
    """One acting step from a raw environment observation: observer -> encoder -> posterior -> actor.
    The whole recurrent state is explicit, and randomness enters as inputs, so the module exports with
    ``torch.export`` and runs anywhere without this file (the expert of pretrain_vae_gw.py)."""

    def __init__(self, agent: Agent, observer: Observer):
        super().__init__()
        self.agent, self.observer = agent, observer

    def forward(self, image, attr, deter, stoch, prev_action, first, noise_z, noise_a):
        o = self.observer(image, attr)
        embed = self.agent.encoder(o)
        deter, stoch, _, _ = self.agent.rssm.obs_step(deter, stoch, prev_action, embed, first, noise_z)
        action = self.agent.actor.act(feat_of(deter, stoch), noise=noise_a)
        return action, deter, stoch


@torch.no_grad()
def run_episodes(agent: Agent, observer: Observer, args: Args, n: int, drop: str, seed: int):
    """n full episodes with fresh environments (seeds seed..seed+n-1), the policy sampling its actions;
    returns per-episode returns and success counts (RoboDesk)."""
    dev = next(agent.parameters()).device
    envs_ = make_envs(args, n)
    obs, _ = envs_.reset(seed=seed)
    deter, stoch = agent.rssm.initial(n, dev)
    action = torch.zeros(n, agent.n_actions, device=dev)
    first = torch.ones(n, device=dev)
    returns, successes = np.zeros(n), np.zeros(n)
    alive = np.ones(n, bool)
    while alive.any():
        embed = agent.encoder(observer(*as_tensors(obs, dev), drop))
        deter, stoch, _, _ = agent.rssm.obs_step(deter, stoch, action, embed, first)
        action = agent.actor.act(feat_of(deter, stoch))
        first = torch.zeros(n, device=dev)
        obs, r, term, trunc, info = envs_.step(action_for_env(action, agent.discrete))
        returns += r * alive
        successes += step_success(info, n) * alive
        alive &= ~(term | trunc)
    envs_.close()
    return returns, successes


@torch.no_grad()
def dream_filmstrip(agent: Agent, observer: Observer, args: Args, steps: int, seed: int) -> np.ndarray | None:
    """Real frames (top row) beside the decoded dream (bottom row) from the same start and actions
    (raw observations only: VAE-Dreamer decodes vectors, not images). uint8 (2 H, steps W, 3)."""
    if "image" not in agent.decoder.spaces:
        return None
    dev = next(agent.parameters()).device
    env = make_envs(args, 1)
    obs, _ = env.reset(seed=seed)
    deter, stoch = agent.rssm.initial(1, dev)
    embed = agent.encoder(observer(*as_tensors(obs, dev)))
    no_action, first = torch.zeros(1, agent.n_actions, device=dev), torch.ones(1, device=dev)
    deter, stoch, _, _ = agent.rssm.obs_step(deter, stoch, no_action, embed, first)
    real, dream = [obs["image"][0]], [agent.decoder.image(feat_of(deter, stoch))]
    for _ in range(steps - 1):
        a = agent.actor.act(feat_of(deter, stoch), mode=True)
        obs, _, term, trunc, info = env.step(action_for_env(a, agent.discrete))
        deter, stoch = agent.rssm.img_step(deter, stoch, a)
        ended = (term | trunc).any()
        real.append(final_observations(info, np.array([0]))["image"][0] if ended else obs["image"][0])
        dream.append(agent.decoder.image(feat_of(deter, stoch)))
        if ended:
            break
    env.close()
    imgs = [
        ((d[0] + 0.5).clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
        for d in dream
    ]
    return np.concatenate([np.concatenate(real, 1), np.concatenate(imgs, 1)], 0)


def random_actions(rng: np.random.Generator, n: int, action_dim: int, discrete: bool, dev) -> torch.Tensor:
    """The uniformly random policy that fills the replay buffer before learning starts."""
    if discrete:
        a = F.one_hot(torch.as_tensor(rng.integers(0, action_dim, n)), action_dim)
    else:
        a = torch.as_tensor(rng.uniform(-1, 1, (n, action_dim)))
    return a.float().to(dev)


# --------------------------------------------------------------------------------------------------
# Frozen VAEs of pretrain_vae_gw.py (--obs vae): same layers, so the same weights load
# --------------------------------------------------------------------------------------------------
def conv_block(cin: int, cout: int, transpose: bool = False, stride: int = 2) -> nn.Sequential:
    conv = (nn.ConvTranspose2d if transpose else nn.Conv2d)(
        cin, cout, 4 if stride == 2 else 3, stride, 1, bias=False
    )
    return nn.Sequential(conv, nn.BatchNorm2d(cout), nn.ReLU())


class VisualVAE(nn.Module):
    """Appendix Tables VAE_v (the encoder's mean u_v is the observation of VAE-Dreamer)."""

    def __init__(self, image: int, latent: int, width: int = 1024):
        super().__init__()
        n_down = int(np.log2(image)) - 1
        chans = [width // 2 ** (n_down - 1 - i) for i in range(n_down)]
        layers, cin = [], 3
        for c in chans:
            layers.append(conv_block(cin, c))
            cin = c
        self.encoder = nn.Sequential(*layers, nn.Flatten())
        self.q = nn.Linear(width * 4, 2 * latent)
        n_up = int(np.log2(image // 8))
        up = [width // 2 ** (i + 1) for i in range(n_up)] + [width // 2**n_up]
        self.fc = nn.Linear(latent, 8 * 8 * width)
        dec, cin = [], width
        for i, c in enumerate(up):
            dec.append(conv_block(cin, c, transpose=True, stride=2 if i < n_up else 1))
            cin = c
        self.decoder = nn.Sequential(*dec, nn.Conv2d(cin, 3, 3, 1, 1), nn.Sigmoid())

    def encode_mean(self, x: torch.Tensor) -> torch.Tensor:
        return self.q(self.encoder(x)).chunk(2, dim=-1)[0]


class AttrVAE(nn.Module):
    """Appendix Tables VAE_attr (only the encoder's mean u_attr is used here)."""

    def __init__(self, attr: int, latent: int, hidden: int, depth: int):
        super().__init__()
        enc, cin = [], attr
        for _ in range(depth):
            enc += [nn.Linear(cin, hidden), nn.ReLU()]
            cin = hidden
        self.encoder = nn.Sequential(
            *enc, nn.Linear(hidden, latent), nn.ReLU(), nn.Linear(latent, 2 * latent)
        )
        dec, cin = [], latent
        for _ in range(depth):
            dec += [nn.Linear(cin, hidden), nn.ReLU()]
            cin = hidden
        self.decoder = nn.Sequential(*dec, nn.Linear(hidden, attr))

    def encode_mean(self, a: torch.Tensor) -> torch.Tensor:
        return self.encoder(a).chunk(2, dim=-1)[0]


class Observer(nn.Module):
    """Environment observation -> the agent's observation dict, with a modality optionally zeroed.

    raw: {"image": uint8 (n, H, W, 3), "attr": (n, A)}; vae: {"x": [u_v, u_attr]} from the frozen VAEs.
    It is part of the exported policy, so a VAE-Dreamer expert also reads raw observations."""

    def __init__(self, env: str, kind: str, vae: dict | None):
        super().__init__()
        self.kind = kind
        s = ENV_SPECS[env]
        if kind == "vae":
            self.vae_v = VisualVAE(s["image"], s["latent"], vae["config"]["vae_width"])
            depth, hidden = (2, 64) if env == "simple_shapes" else (4, 512)
            self.vae_attr = AttrVAE(s["attr"], s["latent"], hidden, depth)
            try:
                self.vae_v.load_state_dict(vae["vae_v"])
                self.vae_attr.load_state_dict(vae["vae_attr"])
            except RuntimeError as err:
                raise UsageError(f"the VAE checkpoint does not fit the {env} networks: {err}") from err
            self.register_buffer("attr_mean", torch.as_tensor(vae["attr_mean"], dtype=torch.float32))
            self.register_buffer("attr_std", torch.as_tensor(vae["attr_std"], dtype=torch.float32))
        self.eval().requires_grad_(False)

    def spaces(self, env: str) -> dict[str, tuple[int, ...]]:
        s = ENV_SPECS[env]
        if self.kind == "raw":
            return {"image": (s["image"], s["image"], 3), "attr": (s["attr"],)}
        return {"x": (2 * s["latent"],)}

    @torch.no_grad()
    def forward(self, image: torch.Tensor, attr: torch.Tensor, drop: str = "none") -> dict[str, torch.Tensor]:
        if self.kind == "raw":
            return {"image": image * (drop != "vision"), "attr": attr * (drop != "attr")}
        u_v = self.vae_v.encode_mean(image.permute(0, 3, 1, 2).float() / 255.0)
        u_attr = self.vae_attr.encode_mean((attr - self.attr_mean) / self.attr_std)
        return {"x": torch.cat([u_v * (drop != "vision"), u_attr * (drop != "attr")], -1)}


# --------------------------------------------------------------------------------------------------
# Checkpoints and the exported expert policy
# --------------------------------------------------------------------------------------------------
def export_policy(agent: Agent, observer: Observer, args: Args, path: Path) -> None:
    """``path``: a torch.export program of ``PolicyStep`` with a batch dimension of any size, and its
    description (env, task, input and state shapes) as the extra file meta.json."""
    s = ENV_SPECS[args.env]
    policy = PolicyStep(copy.deepcopy(agent).cpu().eval(), copy.deepcopy(observer).cpu().eval())
    n = 2
    image, attr = torch.zeros(n, s["image"], s["image"], 3, dtype=torch.uint8), torch.zeros(n, s["attr"])
    state = (torch.zeros(n, args.deter), torch.zeros(n, agent.rssm.stoch), torch.zeros(n, s["actions"]))
    noise_z = torch.rand(n, STOCH, args.classes)
    noise_a = torch.rand(n, s["actions"]) if agent.discrete else torch.randn(n, s["actions"])
    example = (image, attr, *state, torch.ones(n), noise_z, noise_a)
    batch = torch.export.Dim("batch", min=1, max=4096)
    with torch.no_grad():
        program = torch.export.export(policy, example, dynamic_shapes=tuple({0: batch} for _ in example))
    meta = {
        "kind": "dreamer_policy",
        "env": args.env,
        "task": args.task if args.env == "robodesk" else None,
        "obs": args.obs,
        "size": args.size,
        "deter": args.deter,
        "stoch": agent.rssm.stoch,
        "latents": [STOCH, args.classes],
        "actions": s["actions"],
        "discrete": agent.discrete,
        "inputs": "image uint8 (n,H,W,3), attr (n,A), deter, stoch, prev_action, first (n,), "
        "noise_z uniform (n,32,classes), noise_a uniform (discrete) / standard normal (continuous)",
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.pt2")  # torch.export wants the .pt2 suffix
    try:
        torch.export.save(program, tmp, extra_files={"meta.json": json.dumps(meta)})
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def observer_fingerprint(observer: Observer) -> float:
    """A number that changes with the frozen VAE weights (0 for raw observations)."""
    return float(sum(p.double().sum() for p in observer.parameters()))


# Settings that may differ between the parts of one run (how long it runs, how it reports, where its files
# are); every other setting defines the run, and --resume refuses a change to any of them.
MAY_CHANGE = set(
    "total_steps stop_at_criterion eval_every eval_episodes log_every save_every video_every device"
    " save_minutes torch_threads resume overwrite checkpoint checkpoint_dir vae_checkpoint exp_name eval_only"
    " drop compile".split()
)


# Settings an evaluation must share with the agent it loads (they shape its networks or inputs).
EVAL_KEYS = ("task", "obs", "deter", "hidden", "units", "cnn_depth", "layers", "classes", "render_quality")


# What the run infrastructure below the fence reads of this script.
SCRIPT = {
    "kind": "dreamer",  # the kind recorded in its agent checkpoints
    "train": "python dreamer_baseline.py --env {env} --obs {obs} --size {size}",  # trains one
    "fingerprint": "observer_fingerprint",  # the checkpoint entry that identifies the frozen weights
    "eval_keys": lambda args: EVAL_KEYS,
    "video": lambda run: dream_filmstrip(run.agent, run.frozen, run.args, 16, seed=10**6),
    "after_save": lambda run: export_beside(run),
    "exports": {".policy.pt2": "expert policy"},
    "progress": lambda logs: (
        f"wm {logs['loss_wm']:.2f} (kl {logs['kl']:.2f} reward {logs['loss_reward']:.3f})"
    ),
}


def checkpoint_entries(run: Run) -> dict:
    """What an agent checkpoint of this script holds besides its kind, env, task, settings, counters and
    random states (never weights a non-finite --compile update has reached)."""
    if run.args.compile and not all(torch.isfinite(p).all() for p in run.agent.parameters()):
        step = run.state.env_steps
        raise FloatingPointError(f"non-finite weights at env step {step:,}; {last_good(run.agent_path)}")
    return {
        "vae_checkpoint": str(run.pretrained["vae.pt"]) if run.pretrained else None,
        "observer_fingerprint": observer_fingerprint(run.frozen),
        "agent": run.agent.state_dict(),
        "opts": {k: opt.state_dict() for k, opt in run.opts.items()},
        "replay": run.replay.state_dict(),
    }


def export_beside(run: Run) -> None:
    """The expert policy exported beside each saved agent checkpoint (pretrain_vae_gw.py reads it)."""
    policy = run.agent_path.with_suffix(".policy.pt2")
    try:
        export_policy(run.agent, run.frozen, run.args, policy)
    except KeyboardInterrupt:  # Ctrl-C while exporting: the agent is saved, its policy not
        raise KeyboardInterrupt(
            f"while exporting {policy}; the agent is saved at {run.agent_path}, and the same command "
            "with --resume exports it"
        ) from None


# Ranges of this script's flags (check_settings, below the fence, adds the flags every agent has).
RANGES = {
    ">= 1": "batch_size imag_horizon eval_every log_every deter hidden units cnn_depth layers classes",
    ">= 2": "batch_length",
    ">= 0": "learning_starts video_every entropy_coef kl_free kl_dyn kl_rep",
    "> 0": "save_minutes train_ratio wm_lr ac_lr",
    "[0, 1]": "lam unimix slow_critic_decay return_norm_decay",
}


def script_checks(args: Args) -> None:
    """The replay holds a whole sequence per environment, and the run makes at least one update."""
    need = args.batch_length * args.num_envs
    rule = f"must hold a replayed sequence (--batch-length entries) per environment: at least {need}"
    require(args.buffer_size >= need, "buffer_size", args.buffer_size, rule)
    rule = f"must be below --total-steps {args.total_steps:,}, or the run would make no update"
    ok = args.eval_only or args.learning_starts < args.total_steps
    require(ok, "learning_starts", args.learning_starts, rule)


# --------------------------------------------------------------------------------------------------
# The run: what the training loop carries, and the bookkeeping around DreamerV3's loop
# --------------------------------------------------------------------------------------------------
@dataclass
class LoopState:
    """Counters of the training loop (saved in the agent checkpoint, restored by --resume)."""

    env_steps: int = 0  # in the paper's unit (RoboDesk: simulator frames)
    updates: int = 0
    flops: int = 0  # forward + backward FLOPs of every update so far (the paper's "RL training FLOPs")
    flops_per_update: int = 0  # counted on the first update; every update has the same shapes
    episodes: int = 0
    criterion_step: int | None = None
    recent: list = field(default_factory=list)  # the last --smoothing normalised training returns
    next_eval: int = 0
    next_save: int = 0
    next_video: int = 0


@dataclass
class Run:
    """One training run: its settings, networks, data, counters and outputs."""

    args: Args
    frozen: Observer  # raw observations, or the frozen VAE means (--obs vae)
    agent: Agent
    opts: dict
    replay: Replay
    state: LoopState
    writer: SummaryWriter
    agent_path: Path
    pretrained: dict  # {"vae.pt": path} with --obs vae
    model: str  # "raw" (Dreamer) or "vae" (VAE-Dreamer)
    ref: tuple | None  # Simple Shapes returns of the random and the greedy policy (normalisation)
    t0: float = field(default_factory=time.time)
    last_save: float = field(default_factory=time.time)
    steps0: int = 0

    def normalise(self, ret: float) -> float:
        return (ret - self.ref[0]) / (self.ref[1] - self.ref[0]) if self.ref else float("nan")


def load_frozen(args: Args, dev) -> tuple[Observer, dict]:
    """What the agent observes: raw observations, or the frozen VAE means (yours under
    --checkpoint-dir, else the bundled ones)."""
    if args.obs == "raw":
        return Observer(args.env, "raw", None).to(dev), {}
    paths = pretrained_paths(args.checkpoint_dir, args.env, {"vae.pt": args.vae_checkpoint})
    vae = load_pretrained(paths["vae.pt"], "vae", args.env, "collect vae", args.checkpoint_dir)
    made_on = vae.get("args", {}).get("render_quality", "faithful")  # the images the VAE was trained on
    if args.render_quality is None:
        args.render_quality = made_on
    elif args.env == "robodesk" and args.render_quality != made_on:
        raise UsageError(
            f"--render-quality {args.render_quality}: the VAE in {paths['vae.pt']} was trained on {made_on} "
            "images, and its encoders have never seen the other kind; leave the flag out, or pre-train a "
            f"VAE on {args.render_quality} images"
        )
    return Observer(args.env, "vae", vae).to(dev), paths


def run_name(args: Args, model: str) -> str:
    task = "" if args.env == "simple_shapes" else f"_{args.task}"
    return f"{args.exp_name}_{model}_{args.size}_{args.env}{task}_s{args.seed}"


def start_run(args: Args, observer: Observer, agent: Agent, paths: dict, agent_path: Path) -> Run:
    """Claim the outputs, build optimizers and replay, resume when asked, and print what runs."""
    runs_dir = Path("runs") / run_name(args, args.obs)
    # Nothing of an earlier run is overwritten by accident, and the output folders take files now.
    claim_outputs(
        [agent_path, agent_path.with_suffix(".policy.pt2"), runs_dir], args.resume, args.overwrite, "dreamer"
    )
    ensure_writable(agent_path.parent)
    ensure_writable(runs_dir)
    opts = make_optimizers(agent, args)
    replay = Replay(args.buffer_size, args.num_envs, observer.spaces(args.env), agent.n_actions, args.seed)
    state = LoopState(
        next_eval=args.eval_every, next_save=args.save_every, next_video=args.video_every or args.total_steps
    )
    if args.resume:
        ck = load_agent_checkpoint(agent_path, args, observer_fingerprint(observer))
        agent.load_state_dict(ck["agent"])
        for name, opt in opts.items():
            opt.load_state_dict(ck["opts"][name])
        replay.load_state_dict(ck["replay"])
        state = LoopState(**ck["state"])
        torch.set_rng_state(ck["torch_rng"])
        np.random.set_state(ck["np_rng"])
        print(f"[{TAG}] resuming {agent_path} at env step {state.env_steps:,}")
    writer = SummaryWriter(str(runs_dir))
    if not args.resume:
        table = "\n".join(f"|{k}|{v}|" for k, v in vars(args).items())
        writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + table)
    # each part of a run logs its length, which --resume may change (benchmarks/paper_figures.py reads it)
    writer.add_scalar("charts/total_steps", args.total_steps, state.env_steps)
    ref = reference_returns(args)
    run = Run(args, observer, agent, opts, replay, state, writer, agent_path, paths, args.obs, ref)
    run.steps0 = state.env_steps
    n, total = agent.n_trainable(), TABLE_TOTALS[args.size]
    name = "VAE-Dreamer" if args.obs == "vae" else "Dreamer"
    custom = any(getattr(args, k) != v for k, v in MODEL_SIZES[args.size].items())
    task = "" if args.env == "simple_shapes" else f"_{args.task}"
    print(
        f"[{TAG}] {name} {args.size}{' with custom widths' if custom else ''} on {args.env}{task}: "
        f"{n['total']:,} trainable parameters (world model {n['world_model']:,}, actor {n['actor']:,}, "
        f"critic {n['critic']:,})"
        + ("" if custom else f"; the table's total {total / 1e6:.0f}M ({n['total'] / total - 1:+.1%})")
    )
    print(f"[{TAG}] {describe_reference(ref, args)}")
    return run


# ==== run infrastructure: the same in every agent script (tests/test_shared_code.py) ====
# --------------------------------------------------------------------------------------------------
# Pre-trained VAEs and GW (the same block in every agent script): where they are read from, and what to
# run when they are missing. A Simple Shapes VAE + GW made by `pretrain_vae_gw.py --env simple_shapes
# --cpu-preset` ships in envs/pretrained/ so the main job runs on a fresh clone; checkpoints of your own
# under --checkpoint-dir always win.
BUNDLED = Path(__file__).resolve().parent / "envs" / "pretrained"


# What to run when the RoboDesk VAEs + GW are missing (the paper's scale and its hours:
# docs/pretrain_vae_gw.md).
ROBODESK_PIPELINE = (
    "the RoboDesk agents read the frozen VAEs and GW of pretrain_vae_gw.py; make them with `python "
    "pretrain_vae_gw.py --env robodesk --cpu-preset{cd}` (about 70 min on 2 cores), then train with "
    "--cpu-preset; the paper's scale: docs/pretrain_vae_gw.md"
)


def pretrained_paths(checkpoint_dir: str, env: str, wanted: dict[str, str | None]) -> dict[str, Path]:
    """{file name: path} for the pre-trained checkpoints a run needs: the flag's path when given, else
    <checkpoint_dir>/<env>/<name>, else, when that folder holds none of them, the bundled copies."""
    folder = Path(checkpoint_dir) / env
    paths = {name: Path(given) if given else folder / name for name, given in wanted.items()}
    defaults = [name for name, given in wanted.items() if not given]
    if (
        defaults
        and not any((folder / name).is_file() for name in defaults)
        and all((BUNDLED / env / name).is_file() for name in defaults)
    ):
        paths |= {name: BUNDLED / env / name for name in defaults}
        print(
            f"[pretrained] {folder} holds no {' / '.join(defaults)}: using the bundled copies in "
            f"envs/pretrained/{env}/ (made by `python pretrain_vae_gw.py --env {env} --cpu-preset`)"
        )
    return paths


def pretrain_command(env: str, checkpoint_dir: str, stages: str, extra: str = "") -> str:
    """The pretrain_vae_gw.py command that makes a missing checkpoint, with the user's --checkpoint-dir."""
    preset = " --cpu-preset" if env == "simple_shapes" else ""  # the scale that runs on a CPU
    cd = "" if checkpoint_dir == "checkpoints" else f" --checkpoint-dir {checkpoint_dir}"
    return f"python pretrain_vae_gw.py --env {env} --stages {stages}{preset}{extra}{cd}"


def load_pretrained(
    path: Path,
    kind: str,
    env: str,
    stages: str,
    checkpoint_dir: str = "checkpoints",
    extra: str = "",
) -> dict:
    """A checkpoint of pretrain_vae_gw.py, checked against ``kind`` and ``env``; when it is missing, the
    error gives the command that makes it (on RoboDesk, the whole pipeline)."""
    make = pretrain_command(env, checkpoint_dir, stages, extra)
    if not path.is_file():
        if env == "robodesk":
            cd = "" if checkpoint_dir == "checkpoints" else f" --checkpoint-dir {checkpoint_dir}"
            raise UsageError(f"no {kind} checkpoint at {path}: " + ROBODESK_PIPELINE.format(cd=cd))
        raise UsageError(f"no {kind} checkpoint at {path}; make it with `{make}`")
    ckpt = read_checkpoint(path, make)
    if ckpt.get("kind") != kind:
        raise UsageError(f"{path} holds a {ckpt.get('kind')!r} checkpoint, expected {kind!r}")
    if ckpt.get("env") != env:
        raise UsageError(
            f"{path} was made for env {ckpt.get('env')!r}, but this run is for env {env!r}; "
            f"make a matching one with `{make}`"
        )
    return ckpt


# --------------------------------------------------------------------------------------------------
# Safe runs: a new run never overwrites an earlier one, a resumed run is the same run, checkpoints are
# written atomically, and bad settings or unreadable files stop the run at once with one line
# --------------------------------------------------------------------------------------------------
class UsageError(ValueError):
    """A mistake in the command line or in the files it names: the CLI prints the message and exits 2."""


def require(ok: bool, flag: str, value, rule: str) -> None:
    if not ok:
        raise UsageError(f"--{flag.replace('_', '-')} {value}: {rule}")


def atomic_save(obj: dict, path: Path) -> None:
    """Write to a temporary file of this process, then rename it over ``path``: an interruption (even
    kill -9) leaves the previous file whole, and two processes never share a temporary file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    kept = f"the previous {path.name} is kept" if path.exists() else f"no {path.name} was written"
    try:
        with open(tmp, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except KeyboardInterrupt:  # a second Ctrl-C: stop at once
        raise KeyboardInterrupt(f"while saving {path}; {kept}") from None
    except (OSError, RuntimeError) as err:  # torch reports a full disk as "unexpected pos"
        full = getattr(err, "errno", None) == errno.ENOSPC or "unexpected pos" in str(err)
        cause = "no space left on the device" if full else " ".join(str(err).split())[:200]
        raise UsageError(f"cannot save {path} ({cause}); {kept}") from err
    finally:
        tmp.unlink(missing_ok=True)


def read_checkpoint(path: Path, remake: str) -> dict:
    """``torch.load``, or a message that names the file and the command that makes it again."""
    if path.suffix == ".pt2":
        raise UsageError(
            f"{path} is a policy exported by dreamer_baseline.py (torch.export), not a checkpoint: give the "
            f"agent checkpoint beside it, {path.with_name(path.name.removesuffix('.policy.pt2') + '.pt')}"
        )
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # a truncated zip, a text file, a pickle of something else: many types
        brief = " ".join(str(err).split())[:200]  # one line
        raise UsageError(
            f"cannot read {path} ({type(err).__name__}: {brief}); the file is damaged or is no checkpoint: "
            f"make it again with `{remake}`"
        ) from err
    if not isinstance(ckpt, dict) or "kind" not in ckpt and "identity" not in ckpt:
        raise UsageError(
            f"{path} holds a {type(ckpt).__name__} of torch.save, not a checkpoint of these scripts: "
            f"make one with `{remake}`"
        )
    return ckpt


def ensure_writable(folder: Path) -> None:
    """Create ``folder`` and write a file in it now, rather than fail at the first save."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write_test.{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise UsageError(f"cannot write to {folder}: {err.strerror or err}") from err


def claim_outputs(paths: list[Path], resume: bool, overwrite: bool, kind: str) -> None:
    """A new run stops before it would overwrite an earlier run's checkpoint or mix its TensorBoard
    events with that run's; --overwrite removes them on purpose, --resume continues the run they hold.
    A run that is still training holds a lock (``take_lock``), so no second process writes the same run."""
    take_lock(paths[0].with_name(f".{paths[0].name}.lock"))
    existing = [p for p in paths if p.exists()]
    if existing and not paths[0].exists() and not overwrite:  # the run stopped before its first save
        raise UsageError(
            f"{' and '.join(map(str, existing))} exist, but no checkpoint {paths[0]}: that run stopped "
            "before its first save and cannot be continued; add --overwrite (without --resume) to start again"
        )
    if resume and not paths[0].exists():
        raise UsageError(f"--resume: there is no checkpoint {paths[0]} to continue; start the run without it")
    if paths[0].is_file() and not overwrite:  # the same --exp-name given to another script
        try:
            other = read_checkpoint(paths[0], "").get("kind")
        except UsageError:  # a damaged file: --resume names it
            other = kind
        if other != kind:
            raise UsageError(
                f"{paths[0]} holds a {other!r} run, not a {kind!r} one (the same run name in another "
                "script?): choose another --exp-name or --checkpoint"
            )
    if resume or not existing:
        return
    if not overwrite:
        raise UsageError(
            f"{' and '.join(map(str, existing))} already exist from an earlier run: add --resume to continue "
            "it, change --exp-name or --seed to start a separate one, or add --overwrite to replace it"
        )
    for p in existing:
        shutil.rmtree(p) if p.is_dir() else p.unlink()


def take_lock(lock: Path) -> None:
    """Hold ``lock`` (a file with this process's id) until the process exits. A lock whose process is
    alive stops this run; one left by a process that died without cleaning up (kill -9) is taken over."""
    ensure_writable(lock.parent)
    while True:
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            break
        except FileExistsError:
            text = lock.read_text().strip() if lock.is_file() else ""
            pid = int(text) if text.isdigit() else 0
            if pid == os.getpid():
                return
            try:
                os.kill(pid, 0) if pid > 0 else None
                alive = pid > 0
            except ProcessLookupError:
                alive = False
            except PermissionError:  # another user's live process
                alive = True
            if alive:
                raise UsageError(
                    f"process {pid} is training this run now (lock {lock}): wait for it to end, or stop it "
                    "(Ctrl-C saves) and continue with --resume"
                ) from None
            lock.unlink(missing_ok=True)  # stale: its process is gone
    os.write(fd, str(os.getpid()).encode())
    os.close(fd)
    atexit.register(lambda: lock.unlink(missing_ok=True))


def check_unrecorded(path: Path, saved: dict, args, may_change) -> None:
    """A checkpoint made before a flag existed does not record it, and what that run did in its place is
    unknown; it continues only at the flag's default (the tables' value for the run's recorded settings)."""
    now = vars(args)
    made = type(args)(**{k: v for k, v in saved.items() if k in now})  # the run, new flags at default
    default = vars(made.resolve() if hasattr(made, "resolve") else made)
    odd = [k for k in now if k not in saved and k not in may_change and now[k] != default[k]]
    if odd:
        flags = " ".join(f"--{k.replace('_', '-')} {now[k]}" for k in odd)
        raise UsageError(
            f"{path} was made by an older version that does not record {flags}, so that run continues only "
            "at their defaults: leave them out"
        )


def check_device(device: str) -> None:
    """--device names a device this torch has (a CPU-only build has no cuda)."""
    try:
        torch.empty(1, device=device)
    except (RuntimeError, AssertionError) as err:
        brief = " ".join(str(err).split())[:120]
        raise UsageError(f"--device {device}: this torch cannot use it ({brief}); use --device cpu") from err


def non_finite(tree, where: str = "") -> str:
    """The key path of the first floating-point tensor or array in ``tree`` that holds a NaN or an
    infinity ('' if none): a checkpoint written from such a state is no good to continue."""
    if isinstance(tree, dict):
        return next((bad for k, v in tree.items() if (bad := non_finite(v, f"{where}/{k}".strip("/")))), "")
    if isinstance(tree, torch.Tensor) and tree.is_floating_point() and not torch.isfinite(tree).all():
        return where
    if isinstance(tree, np.ndarray) and tree.dtype.kind == "f" and not np.isfinite(tree).all():
        return where
    return ""


def setting_changes(saved: dict, now: dict, keys) -> list[str]:
    """The saved ``--flag value`` (a switch: ``--flag`` or ``--no-flag``, as the CLI takes it) of each
    setting in ``keys`` whose saved value differs from this command's."""
    out = []
    for k in (k for k in keys if k in saved and saved[k] != now[k]):
        flag, value = k.replace("_", "-"), saved[k]
        if isinstance(value, bool):
            out.append(f"--{flag}" if value else f"--no-{flag}")
        else:
            out.append(f"--{flag} {' '.join(map(str, value)) if isinstance(value, (list, tuple)) else value}")
    return out


# What each range rule of RANGES (above the fence) demands of a flag's value.
RULES = {
    ">= 1": (lambda v: v >= 1, "must be at least 1"),
    ">= 2": (lambda v: v >= 2, "must be at least 2"),
    ">= 0": (lambda v: v >= 0, "must not be negative"),
    "> 0": (lambda v: v > 0, "must be positive"),
    "(0, 1]": (lambda v: 0 < v <= 1, "must be in (0, 1]"),
    "[0, 1]": (lambda v: 0 <= v <= 1, "must be in [0, 1]"),
}


def check_settings(args) -> None:
    """Every flag in range and flags that only make sense together, before anything runs: the flags every
    agent has, this script's RANGES and its own rules (script_checks)."""
    for flag, value in vars(args).items():  # inf and nan would pass every range check below
        if isinstance(value, float):
            require(math.isfinite(value), flag, value, "must be a finite number")
    check_device(args.device)
    ranges = {">= 1": "total_steps num_envs eval_episodes save_every smoothing", ">= 0": "seed torch_threads"}
    ranges["(0, 1]"] = "gamma"
    for rule, flags in [*ranges.items(), *RANGES.items()]:
        ok, message = RULES[rule]
        for flag in flags.split():
            require(ok(getattr(args, flag)), flag, getattr(args, flag), message)
    rule = f"must be at least one agent step ({ACTION_REPEAT['robodesk']} frames)"
    require(args.episode_length >= ACTION_REPEAT["robodesk"], "episode_length", args.episode_length, rule)
    require(args.drop == "none" or args.eval_only, "drop", args.drop, "is for evaluation: add --eval-only")
    for other in ("overwrite", "eval_only"):
        if args.resume and getattr(args, other):
            raise UsageError(f"--resume continues a run; it cannot go with --{other.replace('_', '-')}")
    if args.env == "robodesk":
        from envs.robodesk import TASKS
        from envs.robodesk_experts import EXPERTS

        if args.task not in TASKS:
            raise UsageError(f"unknown RoboDesk task {args.task!r}; valid tasks: {', '.join(TASKS)}")
        if args.stop_at_criterion and args.task not in EXPERTS:
            raise UsageError(
                f"--stop-at-criterion: {args.task} has no scripted expert, so its returns are not "
                "normalised and the run has no criterion to stop at"
            )
    script_checks(args)


def last_good(path: Path) -> str:
    """Where a run stopped by a non-finite value stands: its last save (written only from finite
    weights), or none yet."""
    if path.is_file():
        return f"the last good checkpoint is {path}"
    return f"no checkpoint was saved before it ({path} does not exist yet)"


class StopRequest:
    """Ctrl-C (SIGINT) or SIGTERM asks the run to finish what it is doing, save and exit with code 130,
    so an interrupted run loses nothing and ``--resume`` continues it (a save made in the middle of an
    update would pair half-stepped optimisers). A second signal stops at once."""

    def __init__(self, tag: str):
        self.tag, self.requested, self.previous = tag, False, {}
        if threading.current_thread() is threading.main_thread():  # signal handlers live there only
            self.previous = {s: signal.signal(s, self.handle) for s in (signal.SIGINT, signal.SIGTERM)}

    def handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        name = signal.Signals(signum).name
        print(f"[{self.tag}] {name}: saving after this step (send it again to stop at once)", flush=True)

    def restore(self) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler)
        self.previous = {}


# --------------------------------------------------------------------------------------------------
# The agent checkpoint: written atomically with all a run needs to continue (the script's own entries:
# checkpoint_entries), read back checked against the command (what differs per script: SCRIPT)
# --------------------------------------------------------------------------------------------------
def load_agent_checkpoint(path: Path, args, fingerprint: float) -> dict:
    """The agent checkpoint at ``path``, checked against this command: made by this script for the same
    env and task on the same frozen weights (``fingerprint``), with the settings an evaluation must
    repeat, and (``--resume``) every setting that defines the run."""
    kind, train = SCRIPT["kind"], SCRIPT["train"].format(**vars(args))
    if not path.is_file():
        raise UsageError(f"no agent checkpoint at {path}; train one with `{train}`")
    ckpt = read_checkpoint(path, train)
    if ckpt.get("kind") != kind:
        raise UsageError(f"{path} holds a {ckpt.get('kind')!r} checkpoint, expected a {kind} agent")
    # an older version's layout: the loop state held the return scale, or the script's own test says so
    if "return_scale" in ckpt.get("state", {}) or SCRIPT.get("older_layout", lambda ckpt: False)(ckpt):
        raise UsageError(
            f"{path} has the layout of an older version: convert it with `python "
            f"benchmarks/experiments/convert_checkpoint.py {path}`"
        )
    bad = non_finite({k: ckpt[k] for k in ("agent", "replay") if k in ckpt})
    if bad:
        raise UsageError(
            f"{path} holds non-finite values ({bad}): it is no state to continue or evaluate; go back to a "
            "copy saved earlier or train again"
        )
    if ckpt.get("env") != args.env:
        raise UsageError(f"{path} is an agent for env {ckpt.get('env')!r}, but --env is {args.env!r}")
    experiments = SCRIPT.get("experiments", {})  # settings of benchmarks/experiments/, at their off value
    saved, now = experiments | ckpt["args"], experiments | asdict(args)
    if args.env == "simple_shapes":
        now["task"] = saved.get("task", now["task"])  # Simple Shapes has no task
    changed = setting_changes(saved, now, experiments)
    if changed:
        raise UsageError(
            f"{path} was trained with {' '.join(changed)}, an experiment: use "
            f"`python benchmarks/experiments/{kind}_experiments.py {' '.join(changed)} ...`"
        )
    changed = setting_changes(saved, now, SCRIPT["eval_keys"](args))
    if changed:
        raise UsageError(f"{path} was trained with {' '.join(changed)}; pass {' '.join(changed)}")
    if abs(ckpt[SCRIPT["fingerprint"]] - fingerprint) > 1e-6 * max(1.0, abs(fingerprint)):
        frozen = ckpt.get("frozen_paths") or [
            ckpt[k] for k in ("vae_checkpoint", "gw_checkpoint") if ckpt.get(k)
        ]
        raise UsageError(f"{path} was trained on other frozen weights ({', '.join(map(str, frozen))})")
    changed = setting_changes(saved, now, [k for k in now if k not in MAY_CHANGE]) if args.resume else []
    if changed:
        raise UsageError(
            f"{path} was made with {' '.join(changed)}, which differ from this command: give the same "
            "settings to continue that run, or start a separate one (another --exp-name or --seed)"
        )
    if args.resume:
        check_unrecorded(path, saved, args, MAY_CHANGE)
    return ckpt


def log_progress(run, logs: dict) -> None:
    """Every --log-every steps: the last update's losses and the loop's counters to TensorBoard, and a
    progress line that shows the losses SCRIPT["progress"] names (the one host sync of the interval)."""
    a, s, w, step = run.args, run.state, run.writer, run.state.env_steps
    logs = {k: float(v) for k, v in logs.items()}
    if not all(map(math.isfinite, logs.values())):  # --compile checks here, not in the update
        raise FloatingPointError(f"non-finite losses by env step {step:,}; {last_good(run.agent_path)}")
    sps = (step - run.steps0) / max(time.time() - run.t0, 1e-9)
    for k, v in logs.items():
        w.add_scalar(f"charts/{k}" if k in SCRIPT.get("charts", ()) else f"losses/{k}", v, step)
    w.add_scalar("charts/SPS", sps, step)
    w.add_scalar("charts/updates", s.updates, step)
    w.add_scalar("charts/agent_steps", step // ACTION_REPEAT[a.env], step)
    w.add_scalar("charts/train_flops", s.flops, step)
    smooth = np.mean(s.recent) if s.recent else float("nan")
    eta = (a.total_steps - step) / max(sps, 1e-9) / 60
    print(
        f"[{TAG}] step {step:,}/{a.total_steps:,} updates {s.updates:,} {sps:.1f} steps/s ETA {eta:.1f} min"
        f" | {SCRIPT['progress'](logs)} smoothed normalised return {smooth:.3f}",
        flush=True,
    )


def evaluate(run) -> None:
    """An evaluation while training: --eval-episodes fresh episodes of the current policy."""
    a, w, step = run.args, run.writer, run.state.env_steps
    rets, succ = run_episodes(run.agent, run.frozen, a, a.eval_episodes, "none", seed=10**6 + step)
    w.add_scalar("eval/episodic_return", rets.mean(), step)
    if run.ref:
        w.add_scalar("eval/normalised_return", run.normalise(float(rets.mean())), step)
    if a.env == "robodesk":
        w.add_scalar("eval/success_count", succ.mean(), step)


def save_due(run) -> bool:
    """A resumable save is due every --save-every steps, and after --save-minutes of wall time since the
    last save (which leaves the step schedule as it is)."""
    s, a = run.state, run.args
    if s.env_steps >= s.next_save:
        s.next_save += a.save_every
        return True
    return time.time() - run.last_save >= 60 * a.save_minutes


def save(run) -> None:
    """The resumable agent checkpoint: this script's networks, optimizers and data (checkpoint_entries),
    the loop counters and both random states; then what the script exports beside it."""
    a, entries = run.args, checkpoint_entries(run)
    run.last_save = time.time()
    head = {"kind": SCRIPT["kind"], "env": a.env, "task": a.task, "args": asdict(a)}
    rngs = {"torch_rng": torch.get_rng_state(), "np_rng": np.random.get_state()}
    atomic_save(head | entries | {"state": asdict(run.state)} | rngs, run.agent_path)
    if SCRIPT.get("after_save"):
        SCRIPT["after_save"](run)


def finish(run) -> dict:
    """Save the trained agent, then a final evaluation (and dream video); the run's figures."""
    a, s = run.args, run.state
    save(run)  # before the final evaluation, so Ctrl-C there loses nothing
    try:
        rets, succ = run_episodes(run.agent, run.frozen, a, a.eval_episodes, "none", seed=10**6 + 1)
        strip = SCRIPT["video"](run) if SCRIPT.get("video") else None
    except KeyboardInterrupt:
        run.writer.close()
        print(f"[{TAG}] interrupted in the final evaluation; the agent is saved at {run.agent_path}")
        raise SystemExit(130) from None
    if strip is not None:
        run.writer.add_image("dreams/real_top_imagined_bottom", strip, s.env_steps, dataformats="HWC")
    run.writer.add_scalar("eval/episodic_return", rets.mean(), s.env_steps)
    run.writer.close()
    result = {"env_steps": s.env_steps, "agent_steps": s.env_steps // ACTION_REPEAT[a.env]}
    result |= {"updates": s.updates} if hasattr(s, "updates") else {}
    result |= {"train_flops": s.flops, "criterion_step": s.criterion_step, "final_return": float(rets.mean())}
    result["wall_s"] = time.time() - run.t0
    if run.ref:
        result["final_normalised_return"] = run.normalise(float(rets.mean()))
    if a.env == "robodesk":
        result["final_success_count"] = float(succ.mean())
    exports = "".join(
        f", {what} {run.agent_path.with_suffix(x)}" for x, what in SCRIPT.get("exports", {}).items()
    )
    print(f"[{TAG}] done: {result}; agent checkpoint {run.agent_path}{exports}")
    return result


def evaluate_checkpoint(agent, frozen, args, path: Path, fingerprint: float) -> dict:
    """--eval-only: the modality ablation of a trained agent (paper section "Modality Ablation
    Robustness"): --eval-episodes fresh episodes with --drop removed."""
    agent.load_state_dict(load_agent_checkpoint(path, args, fingerprint)["agent"])
    rets, succ = run_episodes(agent, frozen, args, args.eval_episodes, args.drop, seed=args.seed + 10**6)
    sem = rets.std(ddof=1) / math.sqrt(len(rets)) if len(rets) > 1 else 0.0
    out = {"drop": args.drop, "return_mean": float(rets.mean()), "return_sem": float(sem)}
    line = f"[eval] drop={args.drop}: return {rets.mean():.2f} ± {sem:.2f} (s.e.m., {len(rets)} episodes)"
    ref = reference_returns(args)
    if ref:
        out["normalised_return"] = (out["return_mean"] - ref[0]) / (ref[1] - ref[0])
        line += f", normalised {out['normalised_return']:.3f}"
    if args.env == "robodesk":
        out["success_count"] = float(succ.mean())
        succ_sem = succ.std(ddof=1) / math.sqrt(len(succ)) if len(succ) > 1 else 0.0
        line += f", success count {succ.mean():.1f} ± {succ_sem:.1f}"
    print(line)
    return out


def reference_returns(args) -> tuple[float, float] | None:
    """The returns that normalise this run's: 0 for a uniformly random policy, 1 for the scripted policy
    (Simple Shapes: greedy; RoboDesk: the task's expert, measured once and cached beside the
    checkpoints). None for a RoboDesk task without a scripted expert."""
    if args.env == "simple_shapes":
        return ss_reference_returns()
    from envs.robodesk_experts import EXPERTS
    from envs.robodesk_experts import reference_returns as rd_reference_returns

    if args.task not in EXPERTS:
        return None
    cache = Path(args.checkpoint_dir) / "robodesk" / "reference_returns.json"
    return rd_reference_returns(args.task, args.episode_length, cache=cache)


def describe_reference(ref: tuple | None, args) -> str:
    """The start line that says what the normalised return measures."""
    if not ref:
        return f"{args.task} has no scripted expert: returns are not normalised, no criterion"
    scripted = "greedy policy" if args.env == "simple_shapes" else f"scripted {args.task} expert"
    return f"normalised return: random policy {ref[0]:.1f} -> 0, {scripted} {ref[1]:.1f} -> 1"


def log_episode(run: Run, ret: float, success: float) -> None:
    """A finished training episode: its return, the smoothed normalised return and the criterion."""
    s, a, step = run.state, run.args, run.state.env_steps
    s.episodes += 1
    run.writer.add_scalar("charts/episodic_return", ret, step)
    if a.env == "robodesk":
        run.writer.add_scalar("charts/success_count", success, step)
    if not run.ref:
        return
    s.recent = (s.recent + [run.normalise(ret)])[-a.smoothing :]
    smooth = float(np.mean(s.recent))
    run.writer.add_scalar("charts/normalised_return", run.normalise(ret), step)
    run.writer.add_scalar("charts/smoothed_normalised_return", smooth, step)
    if s.criterion_step is None and len(s.recent) == a.smoothing and smooth >= a.criterion:
        s.criterion_step = step
        run.writer.add_scalar("charts/criterion_step", step, step)
        minutes = (time.time() - run.t0) / 60
        print(
            f"[{TAG}] return criterion ({a.criterion}) reached at env step {step:,}, "
            f"{minutes:.1f} min into this run"
        )


def interrupted(run: Run) -> None:
    """Ctrl-C or SIGTERM: the step and its updates are done; save and exit 130."""
    save(run)
    run.writer.close()
    print(
        f"[{TAG}] interrupted at env step {run.state.env_steps:,}: saved {run.agent_path}; "
        "the same command with --resume continues the run",
        flush=True,
    )
    raise SystemExit(130)  # the shell's code for a run ended by Ctrl-C


def keep_freed_memory() -> None:
    """Keep freed memory in the process (Linux, glibc). By default glibc maps blocks over 128 kB afresh
    (over 32 MB at most, as its threshold adapts) and hands them back when they are freed, so every CPU
    update page-faults its large tensors in again: a third of the CPU time of a 12M Dreamer update
    (docs/dreamer_baseline.md, "Against a peer"), 1.3x on the visual VAE's (PyTorch's CPU tuning guide
    gets the same through jemalloc / tcmalloc). Elsewhere nothing changes."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL("libc.so.6")
            libc.mallopt(-4, 0)  # M_MMAP_MAX: every block comes from the heap, which keeps it once freed
            libc.mallopt(-1, -1)  # M_TRIM_THRESHOLD at SIZE_MAX: nor is the heap's free top handed back
        except (OSError, AttributeError):  # not glibc (musl): the allocator stays as it is
            pass


def cli(main, args_type) -> None:
    """Run ``main`` on the parsed command line; a UsageError is printed as one line (exit code 2), and
    Ctrl-C outside the places that save prints one line too (exit code 130)."""
    keep_freed_memory()
    try:
        main(tyro.cli(args_type))
    except UsageError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    except KeyboardInterrupt as err:
        print(f"interrupted {err}".strip(), flush=True)
        raise SystemExit(130) from None


if __name__ == "__main__":
    cli(main, Args)
