"""GW-Dreamer end to end: the Global Workspace is trained with the world model and the actor-critic.

Paper: section "Results" (GW-Dreamer-end-to-end), appendix "GW-Dreamer details / Training", Table
"Hyperparameters used for the training of the Global Workspace in GW-Dreamer End-to-End" and Algorithm 2.
Only the VAEs are pre-trained; the GW starts from random weights.

    python pretrain_vae_gw.py --env simple_shapes --cpu-preset --stages collect vae   # frozen VAEs only
    python gw_dreamer_e2e.py --env simple_shapes                       # paper settings
    python gw_dreamer_e2e.py --env simple_shapes --cpu-preset          # settings for a 2-core CPU
    python gw_dreamer_e2e.py --env robodesk --task push_green
    python gw_dreamer_e2e.py --env simple_shapes --eval-only --checkpoint PATH --drop vision   # ablation

Each global training step (Algorithm 2): two GW updates with the full L_GW of eq. 1-3 on replayed
observations (their frozen VAE means u_v, u_attr), then the world model on z_t = GW(u_v, u_attr) at
alpha_v = alpha_attr = 0.5 from the updated GW, then the actor-critic on dreams, as in gw_dreamer.py.

Reading map, top to bottom:
    Args, TABLE, SIZES, CPU_*     the paper's settings (appendix tables) and the --cpu-preset
    gw_losses, gw_lr              L_GW of eq. 1-3 with random fusion weights, the GW's OneCycle schedule
    TwoHot ... Agent              the world model and actor-critic of gw_dreamer.py, and the trained GW
    Replay                        the frozen VAE means (u_v, u_attr), re-fused by the current GW
    world_model_loss ... dream_loss   L_WM, dreams from replayed states, the actor-critic's losses
    gw_update, train_update       one global training step (Algorithm 2)
    main                          Algorithm 2: act, store, train, then log / evaluate / film / save when due
    run_episodes, dream_filmstrip evaluation episodes and real frames beside a dream
    VisualVAE ... FrozenVAEs      the frozen VAEs of pretrain_vae_gw.py
    SCRIPT ... start_run          this script's part of the run; below the ==== fence, the shared block
"""

from __future__ import annotations

import atexit
import copy
import ctypes
import errno
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
@dataclass
class Args:
    env: Literal["simple_shapes", "robodesk"] = "simple_shapes"
    """environment"""
    task: str = "push_green"
    """RoboDesk task (ignored for Simple Shapes): one of open_slide, open_drawer, push_green, stack,
    upright_block_off_table, flat_block_in_bin, flat_block_in_shelf, lift_upright_block, lift_ball
    (RoboDesk's core tasks), push_blue, push_red, flat_block_off_table, ball_off_table,
    upright_block_in_bin, ball_in_bin, upright_block_in_shelf, ball_in_shelf, lift_flat_block"""
    seed: int = 1
    """seed of the environments, the networks and the replay sampling"""
    exp_name: str = "gw_dreamer_e2e"
    """run name prefix: runs/<exp_name>_<env>[_<task>]_s<seed>"""
    device: str = "cuda" if torch.cuda.is_available() else "cpu"
    """torch device"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default)"""
    compile: bool = False
    """run the update's losses (GW, world model, actor-critic) through torch.compile (on a GPU with CUDA
    graphs, mode "reduce-overhead"); compiling takes minutes at start, and a non-finite loss is then caught
    at the next log line or save rather than at once (docs/gw_dreamer_e2e.md)"""
    cpu_preset: bool = False
    """a 2-core CPU: GW updates on 256 replayed observations instead of 2,048 (see CPU_PRESET); on
    RoboDesk also gw_dreamer.py's CPU sizes and batch (CPU_SIZES, CPU_TABLE); flags given explicitly win"""

    # frozen VAEs (pretrain_vae_gw.py --stages collect vae)
    checkpoint_dir: str = "checkpoints"
    """where pretrain_vae_gw.py wrote <env>/vae.pt; agent checkpoints go to <env>/agents/"""
    vae_checkpoint: str | None = None
    """VAE checkpoint (default <checkpoint_dir>/<env>/vae.pt)"""

    # Global Workspace trained end to end (appendix Table "GW training in GW-Dreamer End-to-End")
    gw_updates: int = 2
    """GW updates per global training step (appendix "Training": two)"""
    gw_batch_size: int | None = None
    """replayed observations per GW update (default: batch_size x batch_length, the observations of one
    world-model batch; 2,048 for Simple Shapes, close to the 2,056 of GW pre-training)"""
    gw_lr_start: float | None = None
    """GW OneCycle start learning rate (default 3e-3 Simple Shapes, 1e-4 RoboDesk)"""
    gw_lr_max: float | None = None
    """GW OneCycle max learning rate (default 1e-2 Simple Shapes, 3e-4 RoboDesk)"""
    gw_lr_end: float | None = None
    """GW OneCycle end learning rate, kept after the cycle (default 1e-3 Simple Shapes, 1e-4 RoboDesk)"""
    gw_cycle: int | None = None
    """GW updates in one OneCycle schedule (default 25,000 Simple Shapes, 50,000 RoboDesk)"""
    gw_weight_decay: float | None = None
    """GW AdamW weight decay (default: the GW pre-training table's 1e-5 Simple Shapes, 1e-6 RoboDesk)"""
    loss_preset: Literal["gw", "clip"] = "gw"
    """L_GW weights: gw (beta_dcy = beta_cy = beta_tr = beta_fusion = 1, beta_cont = 0.1) or clip
    (contrastive only; an end-to-end CLIP-Dreamer)"""
    fusion_temperature: float = 0.2
    """fusion weights of L_fusion are softmax(U / T), U uniform per modality (as in pre-training)"""
    contrastive_temperature: float = 0.07
    """fixed temperature of the contrastive loss (as in pre-training)"""

    # training (appendix Table "GW-Dreamer training"; None: the table's value for --env, see TABLE)
    total_steps: int | None = None
    """environment steps, in the paper's unit: agent steps on Simple Shapes, simulator frames on RoboDesk
    (4 per agent step: its action repeat); default 100,000 Simple Shapes, 1,000,000 RoboDesk"""
    num_envs: int = 1
    """environments stepped together"""
    learning_starts: int = 1_000
    """random-policy environment steps that fill the replay buffer before the first update"""
    buffer_size: int = 100_000
    """replay capacity in transitions"""
    batch_size: int | None = None
    """replayed sequences per update (default 64 Simple Shapes, 32 RoboDesk)"""
    batch_length: int | None = None
    """transitions per replayed sequence (default 32 Simple Shapes, 128 RoboDesk)"""
    train_ratio: float | None = None
    """the table's train ratio (default 4 Simple Shapes, 2 RoboDesk), read as agent steps per training
    update (see `updates_due`)"""
    imag_horizon: int = 20
    """imagined steps per rollout"""
    imag_from: Literal["last", "all"] = "last"
    """where dreams start. last: one dream per replayed sequence, from its newest state (the real z_t
    there and the h_t of a world model that has read the whole sequence), batch_size dreams per update:
    the paper's "first observation" reading, which its FLOPs table supports (docs/paper_readings.md).
    all: from every replayed state, batch_size x batch_length dreams (DreamerV3's)"""
    wm_lr: float | None = None
    """world-model Adam learning rate (default 1e-3 Simple Shapes, 3e-4 RoboDesk)"""
    ac_lr: float = 3e-4
    """actor and critic Adam learning rate"""
    wm_z_coef: float = 10.0
    """weight of the z_{t+1} MSE in L_WM. The paper gives L_WM as a weighted sum without its weights; at 1
    the reward term is 20-50x the z term and the world model's one-step z error stays as large as one
    action's effect on z (the reading and its runs: docs/paper_readings.md)"""
    wm_reward_coef: float = 1.0
    """weight of the reward term in L_WM"""
    wm_done_coef: float = 1.0
    """weight of the done BCE in L_WM"""
    reward_offset: float = 0.0
    """constant subtracted from every reward the world model learns, hence from every dreamt reward and
    value (0: the paper). RoboDesk has no termination, so the best policy is the same; the two-hot heads
    then work on smaller values (docs/paper_readings.md)"""
    reward_loss: Literal["twohot", "mse"] = "twohot"
    """reward head: 255-bin two-hot over symlog rewards (the table's FC_256 output,
    docs/paper_readings.md) or one output trained with MSE on symlog(r) (the text's 'MSE')"""
    gamma: float = 1 - 1 / 333
    """discount (DreamerV3)"""
    lam: float = 0.95
    """lambda of the lambda-returns"""
    entropy_coef: float | None = None
    """actor entropy regulariser, which the paper does not give (default 3e-3 Simple Shapes, 3e-4
    RoboDesk: DreamerV3's value, for its continuous actor; why they differ: docs/paper_readings.md)"""
    critic_replay_coef: float | None = None
    """weight of a second critic loss on the replayed states themselves, toward lambda-returns of their real
    rewards (DreamerV3's later replay value loss, 0.3 there); 0 (default): the critic learns from dreams
    alone, as the paper's actor-critic; 0.3 with RoboDesk's --cpu-preset (docs/paper_readings.md)"""
    wm_open_loop: int | None = None
    """K > 0: L_WM adds a K-step open-loop term: from every --wm-open-loop-stride-th replayed h_t, K steps
    that feed the world model's own z back along the actions taken, with the same z, reward and done losses
    against the real z_{t+k}, r and d. 0 (default): the paper's one-step loss from the real z; 10 with
    RoboDesk's --cpu-preset, whose dreams otherwise drift off the real track (docs/paper_readings.md)"""
    wm_open_loop_stride: int | None = None
    """replayed entries between two starts of the open-loop term (default 16; 32 with RoboDesk's
    --cpu-preset)"""
    done_head: Literal["on", "off"] | None = None
    """off: the world model has no done head and its dreams continue (c = 1), for RoboDesk, whose episodes
    never end early (only the step limit truncates them), so the head can only learn that nothing ends.
    Default on, the paper's world model; off with RoboDesk's --cpu-preset (13% fewer FLOPs per update)"""
    explore_noise: float | None = None
    """sigma > 0: Gaussian noise N(0, sigma^2) added to each continuous action taken while collecting
    training data (clipped to the action box; the replay stores the action taken), as DreamerV1. 0
    (default): the paper's actor alone; 0.3 with RoboDesk's --cpu-preset, whose actor at its std floor
    gives the world model too little action variety to learn the actions' effect (docs/paper_readings.md).
    Evaluations and dreams use the actor as it is"""
    slow_critic_decay: float = 0.98
    """EMA decay of the slow critic that regularises the critic (DreamerV3)"""
    return_norm_decay: float = 0.99
    """EMA decay of the return scale max(1, P95 - P5) (DreamerV3)"""
    actor_mean_reg: float | None = None
    """weight of 0.5 mean(m^2) on the continuous actor's mean m before its tanh, in the actor's loss: it
    keeps the tanh out of saturation, where dynamics backpropagation can no longer move the policy (the
    original SAC's policy regulariser; default 0 Simple Shapes, 1e-3 RoboDesk; docs/paper_readings.md)"""
    actor_grad: Literal["auto", "reinforce", "dynamics"] = "auto"
    """actor gradient: REINFORCE, or backpropagation of the lambda-returns through the dreamt transitions
    into the actions (the world model's weights get no gradient from it); auto: REINFORCE for discrete
    actions (Simple Shapes), dynamics for continuous ones (RoboDesk), as DreamerV3 (docs/paper_readings.md)"""

    # environments
    render_quality: Literal["faithful", "fast"] | None = None
    """RoboDesk image quality (fast: CPU experiments only, docs/environments.md); default: the images the
    VAEs were trained on (another kind is refused)"""
    episode_length: int = 2000
    """RoboDesk episode length in physics-control repeats (paper: 2000, i.e. 500 agent steps)"""

    # evaluation, logging, checkpoints
    eval_every: int | None = None
    """environment steps between evaluations (default 5,000 Simple Shapes, 50,000 RoboDesk)"""
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
    video_every: int = 20_000
    """environment steps between dream videos (0: only at the end)"""
    log_every: int = 1_000
    """environment steps between TensorBoard scalars and progress lines"""
    save_every: int = 10_000
    """environment steps between resumable checkpoints"""
    save_minutes: float = 15.0
    """wall-clock minutes after which a resumable checkpoint is written even if --save-every steps have
    not passed (a run stopped without warning loses at most this much)"""
    resume: bool = False
    """continue the run stored at --checkpoint (default: this run's agent checkpoint)"""
    overwrite: bool = False
    """replace an earlier run of the same name (its agent checkpoint and runs/ folder); without it a run
    whose files exist stops at start"""
    checkpoint: str | None = None
    """agent checkpoint (default <checkpoint_dir>/<env>/agents/<run name>.pt)"""
    eval_only: bool = False
    """only evaluate --checkpoint (the modality ablation with --drop) and exit"""
    drop: Literal["none", "vision", "attr"] = "none"
    """modality removed at evaluation: vision -> alpha = (0, 1), attr -> alpha = (1, 0)"""

    def resolve(self) -> Args:
        """The CPU preset (if asked) for every flag left at its default, then the tables' values for --env."""
        if self.cpu_preset:
            plain = Args(env=self.env)
            for name, value in CPU_PRESET.items():
                if getattr(self, name) == getattr(plain, name):  # flags given explicitly win
                    setattr(self, name, value)
        table = TABLE[self.env] | (CPU_TABLE.get(self.env, {}) if self.cpu_preset else {})
        for name, value in table.items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.gw_batch_size is None:
            self.gw_batch_size = self.batch_size * self.batch_length
        if self.env == "simple_shapes" and self.render_quality is None:
            self.render_quality = "faithful"  # not used: Simple Shapes has one renderer
        return self


# Settings the paper does not have, which RoboDesk's --cpu-preset turns on (CPU_TABLE): off by default;
# and the paper's done head, which it turns off.
PAPER_OFF = dict(critic_replay_coef=0.0, wm_open_loop=0, wm_open_loop_stride=16, explore_noise=0.0)
PAPER_ON = dict(done_head="on")


# The flags whose defaults differ between the environments (appendix Tables "GW-Dreamer training" and
# "GW training in GW-Dreamer End-to-End"; the step counts and evaluation intervals are the scale of the
# paper's Figure 3; the weight decay is the GW pre-training table's).
TABLE = {
    "simple_shapes": dict(
        criterion=0.75,
        total_steps=100_000,
        batch_size=64,
        batch_length=32,
        train_ratio=4.0,
        wm_lr=1e-3,
        entropy_coef=3e-3,
        actor_mean_reg=0.0,
        eval_every=5_000,
        gw_lr_start=3e-3,
        gw_lr_max=1e-2,
        gw_lr_end=1e-3,
        gw_cycle=25_000,
        gw_weight_decay=1e-5,
        **PAPER_OFF,
        **PAPER_ON,
    ),
    "robodesk": dict(
        criterion=0.70,
        total_steps=1_000_000,
        batch_size=32,
        batch_length=128,
        train_ratio=2.0,
        wm_lr=3e-4,
        entropy_coef=3e-4,
        actor_mean_reg=1e-3,
        eval_every=50_000,
        gw_lr_start=1e-4,
        gw_lr_max=3e-4,
        gw_lr_end=1e-4,
        gw_cycle=50_000,
        gw_weight_decay=1e-6,
        **PAPER_OFF,
        **PAPER_ON,
    ),
}


# A smaller GW batch for a 2-core CPU: the contrastive loss compares every pair of a batch, so a GW
# update costs ~15x more at 2,048 than at 256 (the paper gives no batch for the end-to-end GW).
CPU_PRESET = {"gw_batch_size": 256}


# RoboDesk under --cpu-preset: gw_dreamer.py's preset (its CPU_SIZES networks, batch, replay critic loss,
# open-loop world-model loss, exploration noise and no done head), so that the two variants differ only in
# how the GW is trained. An evaluation's 10 episodes are 20,000 frames of acting, so the preset evaluates
# every 100,000.
CPU_TABLE = {
    "robodesk": dict(
        total_steps=200_000,
        batch_size=28,
        batch_length=64,
        eval_every=100_000,
        critic_replay_coef=0.3,
        wm_open_loop=10,
        wm_open_loop_stride=32,
        explore_noise=0.3,
        done_head="off",
    )
}
TAG = "gw_dreamer_e2e"  # the prefix of every line this script prints
SIZES = {
    "simple_shapes": {
        "gru_in": 32,
        "gru_hidden": 64,
        "z_head": (),
        "ac_layers": 3,
        "ac_width": 512,
        "actions": 7,
    },
    # The RoboDesk actor-critic table gives x in R^512 while the GRU table gives h in R^1024; the AC
    # reads h_t (text), so its input is 1024 and its 4 hidden layers are 512 wide as listed.
    "robodesk": {
        "gru_in": 1024,
        "gru_hidden": 1024,
        "z_head": (512, 512),
        "ac_layers": 4,
        "ac_width": 512,
        "actions": 5,
    },
}


# --cpu-preset: the same networks, a quarter as wide (the GRU state h_t of 256 instead of 1024).
CPU_SIZES = {
    "robodesk": {
        "gru_in": 256,
        "gru_hidden": 256,
        "z_head": (256,),
        "ac_layers": 3,
        "ac_width": 256,
        "actions": 5,
    }
}


def sizes_of(env: str, cpu_preset: bool = False) -> dict:
    """The network sizes of a run: the appendix tables', or the CPU preset's."""
    return CPU_SIZES[env] if cpu_preset and env in CPU_SIZES else SIZES[env]


ENV_SPECS = {  # must agree with pretrain_vae_gw.py (checked against the checkpoints)
    "simple_shapes": {"image": 32, "attr": 11, "latent": 10, "z": 10, "gw_hidden": 64},
    "robodesk": {"image": 64, "attr": 76, "latent": 40, "z": 76, "gw_hidden": 512},
}


def mlp(cin: int, hidden: int, cout: int, depth: int) -> nn.Sequential:
    layers = []
    for _ in range(depth):
        layers += [nn.Linear(cin, hidden), nn.ReLU()]
        cin = hidden
    return nn.Sequential(*layers, nn.Linear(hidden, cout))


LOSS_PRESETS = {  # appendix Table "GW losses weights"
    "gw": {"dcy": 1.0, "cy": 1.0, "tr": 1.0, "fusion": 1.0, "cont": 0.1},
    "clip": {"dcy": 0.0, "cy": 0.0, "tr": 0.0, "fusion": 0.0, "cont": 1.0},
}


def gw_losses(gw: GlobalWorkspace, u_v, u_attr, alpha_fusion: torch.Tensor, temperature: float) -> dict:
    """The terms of L_GW (eq. 1-3), each a mean over both modalities: demi-cycle (alpha_x = 1, decode x),
    translation (alpha_x = 1, decode the other), cycle (translate and back), fusion (random alpha_v per
    sample, decode both) and the CLIP-like contrastive loss on the pre-fusion encodings.

    Each decoder runs once, on its demi-cycle, translation and fusion inputs stacked along the batch, and
    the cycle re-encodes those translations: the same terms as separate calls, with two decoder passes
    fewer (this update runs twice per global step)."""
    u = {"v": u_v, "attr": u_attr}
    other = {"v": "attr", "attr": "v"}
    batch = len(u_v)
    z_pre = {x: gw.e[x](u[x]) for x in u}
    z_uni = {x: torch.tanh(z_pre[x]) for x in u}  # alpha_x = 1, the other 0
    z_fused = torch.tanh(alpha_fusion * z_pre["v"] + (1 - alpha_fusion) * z_pre["attr"])
    # decoded[x]: d_x of z_uni[x] (demi-cycle), of z_uni[other] (x translated from the other), of z_fused
    decoded = {x: gw.d[x](torch.cat([z_uni[x], z_uni[other[x]], z_fused])).split(batch) for x in u}
    u_tr = {x: decoded[x][1] for x in u}
    # cycle x -> other -> x: encode the other modality translated from x, decode it back to x
    u_cy = {x: gw.d[x](torch.tanh(gw.e[other[x]](u_tr[other[x]]))) for x in u}
    loss_dcy = sum(F.mse_loss(decoded[x][0], u[x]) for x in u) / 2
    loss_tr = sum(F.mse_loss(u_tr[x], u[x]) for x in u) / 2
    loss_cy = sum(F.mse_loss(u_cy[x], u[x]) for x in u) / 2
    loss_fusion = sum(F.mse_loss(decoded[x][2], u[x]) for x in u) / 2
    zv, za = F.normalize(z_pre["v"], dim=-1), F.normalize(z_pre["attr"], dim=-1)
    logits = zv @ za.T / temperature
    target = torch.arange(len(zv), device=zv.device)
    loss_cont = (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target)) / 2
    return {"dcy": loss_dcy, "cy": loss_cy, "tr": loss_tr, "fusion": loss_fusion, "cont": loss_cont}


def fusion_weights(batch: int, temperature: float, device) -> torch.Tensor:
    """alpha_v per sample for L_fusion: softmax(U / T) over the two modalities, U uniform in [0, 1)."""
    return torch.softmax(torch.rand(batch, 2, device=device) / temperature, dim=1)[:, :1]


def gw_lr(update: int, args: Args) -> float:
    """OneCycle learning rate of the GW (cosine up from start to max over the first 30% of the cycle,
    down to end over the rest, as torch's OneCycleLR) held at the end rate once the cycle is over."""
    warm = 0.3 * args.gw_cycle
    if update >= args.gw_cycle:
        return args.gw_lr_end
    if update < warm:
        lo, hi, frac = args.gw_lr_start, args.gw_lr_max, update / warm
    else:
        lo, hi, frac = args.gw_lr_max, args.gw_lr_end, (update - warm) / (args.gw_cycle - warm)
    return hi + (lo - hi) * (1 + math.cos(math.pi * frac)) / 2


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
# World model (appendix Tables GRU_archi, WM_heads_SS / WM_heads_Rob)
# --------------------------------------------------------------------------------------------------
class WorldModel(nn.Module):
    """h_{t+1} = GRU(h_t, in([z_t, a_t])); z_{t+1} = tanh-head(h_{t+1}); reward and done heads read
    [h_{t+1}, z_{t+1}] (the tables' inputs 74 = 64 + 10 and 1100 = 1024 + 76)."""

    def __init__(self, sizes: dict, z_dim: int, action_dim: int, reward_out: int, done_head: bool = True):
        super().__init__()
        s = sizes
        # A linear input layer brings [z, a] to the table's GRU input size (docs/paper_readings.md).
        self.inp = nn.Sequential(nn.Linear(z_dim + action_dim, s["gru_in"]), nn.ReLU())
        self.gru = nn.GRUCell(s["gru_in"], s["gru_hidden"])
        layers, cin = [], s["gru_hidden"]
        for width in s["z_head"]:
            layers += [nn.Linear(cin, width), nn.ReLU()]
            cin = width
        self.z_head = nn.Sequential(*layers, nn.Linear(cin, z_dim), nn.Tanh())
        # Two hidden layers of 256: the tables draw three, but all four of their parameter counts (reward
        # 150,000 / 413,000, done 85,000 / 348,000) are those of two (docs/paper_readings.md).
        self.reward_head = mlp(s["gru_hidden"] + z_dim, 256, reward_out, 2)
        self.done_head = mlp(s["gru_hidden"] + z_dim, 256, 1, 2) if done_head else None
        self.hidden = s["gru_hidden"]

    def step(self, h: torch.Tensor, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.gru(self.inp(torch.cat([z, a], -1)), h)

    def heads(self, h_next: torch.Tensor):
        z_next = self.z_head(h_next)
        feat = torch.cat([h_next, z_next], -1)
        return z_next, self.reward_head(feat), self.done_logit(feat)

    def done_logit(self, feat: torch.Tensor) -> torch.Tensor:
        """The done head's logit; --done-head off: NEVER_ENDS everywhere (a dream continues with c = 1 -
        1e-13 and the done loss against d = 0 is 1e-13, with no parameters and no gradient)."""
        if self.done_head is None:
            return torch.full_like(feat[..., 0], NEVER_ENDS)
        return self.done_head(feat).squeeze(-1)


NEVER_ENDS = -30.0  # the done logit of a world model without done head: sigmoid(-30) = 9e-14


class RewardDecoder:
    """Reward head outputs -> reward, and the reward loss (two-hot or MSE on symlog)."""

    def __init__(self, kind: str, twohot: TwoHot):
        self.kind, self.twohot = kind, twohot

    def value(self, out: torch.Tensor) -> torch.Tensor:
        return self.twohot.mean(out) if self.kind == "twohot" else symexp(out.squeeze(-1))

    def loss(self, out: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        if self.kind == "twohot":
            return self.twohot.loss(out, r)
        return (out.squeeze(-1) - symlog(r)) ** 2


# --------------------------------------------------------------------------------------------------
# Actor-critic (appendix Tables AC_SS / AC_Rob) and DreamerV3's return normaliser
# --------------------------------------------------------------------------------------------------
class Actor(nn.Module):
    """Discrete: categorical with 1% uniform mix (DreamerV3). Continuous: Gaussian with tanh mean and
    std in [0.1, 1], the table's FC_{2x5}; samples are clipped to the action box."""

    def __init__(
        self, hidden: int, n_actions: int, depth: int, discrete: bool, width: int = 512, unimix: float = 0.01
    ):
        super().__init__()
        self.discrete, self.n, self.unimix = discrete, n_actions, unimix
        self.net = mlp(hidden, width, n_actions if discrete else 2 * n_actions, depth)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """The network's output: logits, or the mean and std before their squashing."""
        return self.net(h)

    def dist(self, h: torch.Tensor) -> torch.distributions.Distribution:
        return self.dist_of(self(h))

    def dist_of(self, out: torch.Tensor) -> torch.distributions.Distribution:
        if self.discrete:
            probs = (1 - self.unimix) * out.softmax(-1) + self.unimix / self.n
            return torch.distributions.Categorical(probs=probs)
        mean, std = out.chunk(2, -1)
        std = 0.9 * torch.sigmoid(std + 2.0) + 0.1
        return torch.distributions.Independent(torch.distributions.Normal(torch.tanh(mean), std), 1)

    def act(self, h: torch.Tensor, mode: bool = False) -> torch.Tensor:
        """Action as the world model reads it: one-hot (discrete) or a vector in [-1, 1]."""
        return self.sample(self(h), mode)

    def sample(self, out: torch.Tensor, mode: bool = False) -> torch.Tensor:
        """``act`` from the network's output ``out``."""
        d = self.dist_of(out)
        if self.discrete:
            idx = d.probs.argmax(-1) if mode else d.sample()
            return F.one_hot(idx, self.n).float()
        return (d.mean if mode else d.rsample()).clamp(-1, 1)  # rsample: differentiable in dreams

    def log_prob(self, out: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Log-probability of ``a`` and the entropy, from the network's output ``out``."""
        d = self.dist_of(out)
        return d.log_prob(a.argmax(-1) if self.discrete else a), d.entropy()


class Critic(nn.Module):
    def __init__(self, hidden: int, depth: int, width: int = 512, n_bins: int = 255):
        super().__init__()
        self.net = mlp(hidden, width, n_bins, depth)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.net(h)


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
    """The trainable part of GW-Dreamer end to end: Global Workspace, world model, actor, critic, the slow
    critic and the return scale."""

    def __init__(
        self,
        env: str,
        reward_loss: str,
        return_norm_decay: float = 0.99,
        cpu_preset: bool = False,
        done_head: bool = True,
    ):
        super().__init__()
        s, spec = sizes_of(env, cpu_preset), ENV_SPECS[env]
        z_dim = spec["z"]
        self.discrete = env == "simple_shapes"
        self.gw = GlobalWorkspace(spec["latent"], z_dim, spec["gw_hidden"])
        self.twohot = TwoHot()
        self.wm = WorldModel(s, z_dim, s["actions"], 255 if reward_loss == "twohot" else 1, done_head)
        self.actor = Actor(s["gru_hidden"], s["actions"], s["ac_layers"], self.discrete, s["ac_width"])
        self.critic = Critic(s["gru_hidden"], s["ac_layers"], s["ac_width"])
        self.slow_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.reward_dec = RewardDecoder(reward_loss, self.twohot)
        self.return_scale = ReturnScale(return_norm_decay)

    @torch.no_grad()
    def z(self, u_v: torch.Tensor, u_attr: torch.Tensor, drop: str = "none") -> torch.Tensor:
        """z_t of the current GW: alpha = 0.5/0.5, or (1, 0)/(0, 1) with the dropped modality zeroed. The
        world model and actor-critic never send gradients into the GW; it learns from L_GW alone."""
        alpha_v, alpha_attr = FUSION[drop]
        if alpha_v == 0:
            u_v = torch.zeros_like(u_v)
        if alpha_attr == 0:
            u_attr = torch.zeros_like(u_attr)
        return self.gw.fuse(u_v, u_attr, alpha_v, alpha_attr)

    def features(self, h: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """What the actor and critic read: the GRU state h_t, as in gw_dreamer.py."""
        return h


# --------------------------------------------------------------------------------------------------
# Replay buffer: one stream per environment of entries (u_v, u_attr, a_t, r_{t+1}, d_{t+1}, first, last)
# --------------------------------------------------------------------------------------------------
class Replay:
    """The VAEs are frozen and the GW reads only their means, so each observation is stored as (u_v,
    u_attr), computed once when it is collected: the same as re-encoding the stored images and
    attributes at every update (Algorithm 2), and a 100,000-step buffer takes megabytes, not gigabytes.
    The GW changes during the run, so z_t is computed from (u_v, u_attr) at every update.

    An episode that ends adds one more entry holding its final observation (``last``); sequences are
    read across episode boundaries and the world model restarts its state at ``first`` entries."""

    def __init__(self, capacity: int, num_envs: int, latent: int, action_dim: int, seed: int):
        self.cap = max(capacity // num_envs, 2)
        self.n = num_envs
        self.u_v = np.zeros((num_envs, self.cap, latent), np.float32)
        self.u_attr = np.zeros((num_envs, self.cap, latent), np.float32)
        self.a = np.zeros((num_envs, self.cap, action_dim), np.float32)
        self.r = np.zeros((num_envs, self.cap), np.float32)
        self.d = np.zeros((num_envs, self.cap), np.float32)
        self.first = np.zeros((num_envs, self.cap), np.float32)
        self.last = np.zeros((num_envs, self.cap), np.float32)
        self.pos = np.zeros(num_envs, np.int64)  # next write index per stream
        self.count = np.zeros(num_envs, np.int64)  # entries written per stream (not capped)
        self.rng = np.random.default_rng(seed)

    def add(self, env_idx, u_v, u_attr, a, r, d, first, last) -> None:
        for j, i in enumerate(np.atleast_1d(env_idx)):
            p = self.pos[i]
            self.u_v[i, p], self.u_attr[i, p] = u_v[j], u_attr[j]
            self.a[i, p], self.r[i, p], self.d[i, p] = a[j], r[j], d[j]
            self.first[i, p], self.last[i, p] = first[j], last[j]
            self.pos[i] = (p + 1) % self.cap
            self.count[i] += 1

    def __len__(self) -> int:
        return int(np.minimum(self.count, self.cap).sum())

    def ready(self, length: int) -> bool:
        return bool(np.all(np.minimum(self.count, self.cap) >= length + 1))

    def sample(self, batch: int, length: int) -> dict[str, np.ndarray]:
        """``batch`` windows of ``length + 1`` consecutive entries (``length`` transitions)."""
        envs_ = self.rng.integers(0, self.n, batch)
        filled = np.minimum(self.count[envs_], self.cap)
        oldest = np.where(self.count[envs_] > self.cap, self.pos[envs_], 0)
        start = oldest + (self.rng.random(batch) * (filled - length)).astype(np.int64)
        idx = (start[:, None] + np.arange(length + 1)[None]) % self.cap
        rows = envs_[:, None]
        return {k: getattr(self, k)[rows, idx] for k in ("u_v", "u_attr", "a", "r", "d", "first", "last")}

    def sample_observations(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """``n`` stored observations (u_v, u_attr) drawn uniformly: the GW's training batch."""
        envs_ = self.rng.integers(0, self.n, n)
        idx = (self.rng.random(n) * np.minimum(self.count[envs_], self.cap)).astype(np.int64)
        return self.u_v[envs_, idx], self.u_attr[envs_, idx]

    _KEYS = ("u_v", "u_attr", "a", "r", "d", "first", "last", "pos", "count")

    def state_dict(self) -> dict:
        return {k: getattr(self, k) for k in self._KEYS} | {"rng": self.rng.bit_generator.state}

    def load_state_dict(self, s: dict) -> None:
        for k in self._KEYS:
            setattr(self, k, s[k])
        self.rng.bit_generator.state = s["rng"]

    def close_episodes(self) -> None:
        """Mark each stream's newest entry as an episode's last. Called on resume: the saved run stopped
        mid-episode, and the next entry will start a new episode, so the world model must not learn a
        transition from the old episode's last stored state into the new one's first (the newest entry's
        own transition is dropped with it: its next observation was never stored)."""
        for i in range(self.n):
            if self.count[i]:
                self.last[i, (self.pos[i] - 1) % self.cap] = 1.0


# --------------------------------------------------------------------------------------------------
# Losses and imagination
# --------------------------------------------------------------------------------------------------
def world_model_loss(wm, reward_dec, batch: dict[str, torch.Tensor], args: Args):
    """L_WM = coef_z MSE(z_{t+1}) + coef_r L_r + coef_d BCE(d_{t+1}) on replayed sequences (Algorithm 1,
    lines 8-10; Algorithm 2, lines 13-17). Returns the loss, its terms, the GRU state h_t at every entry
    of the sequences (B, T + 1, hidden: the states dreams can start from) and the mask of valid
    transitions. MSE is summed over the z dimensions, averaged over transitions."""
    z, a, r, d = batch["z"], batch["a"], batch["r"] - args.reward_offset, batch["d"]
    first, last = batch["first"], batch["last"]
    B, T1, _ = z.shape
    h = torch.zeros(B, wm.hidden, device=z.device)
    hs, hs_after = [], []
    for t in range(T1):
        h = h * (1 - first[:, t, None])  # a new episode starts from h = 0
        hs.append(h)
        if t < T1 - 1:
            h = wm.step(h, z[:, t], a[:, t])
            hs_after.append(h)
    h_entry, h_next = torch.stack(hs, 1), torch.stack(hs_after, 1)  # (B, T + 1, hidden), (B, T, hidden)
    z_hat, r_out, d_logit = wm.heads(h_next)
    valid = 1 - last[:, :-1]  # no transition out of an episode's final observation
    n = valid.sum().clamp(min=1)
    loss_z = (((z_hat - z[:, 1:]) ** 2).sum(-1) * valid).sum() / n
    loss_r = (reward_dec.loss(r_out, r[:, :-1]) * valid).sum() / n
    loss_d = (F.binary_cross_entropy_with_logits(d_logit, d[:, :-1], reduction="none") * valid).sum() / n
    loss = args.wm_z_coef * loss_z + args.wm_reward_coef * loss_r + args.wm_done_coef * loss_d
    return loss, {"loss_z": loss_z, "loss_r": loss_r, "loss_d": loss_d}, h_entry, valid


def world_model_loss_open_loop(wm, reward_dec, batch: dict[str, torch.Tensor], args: Args):
    """L_WM as the update computes it: world_model_loss, plus open_loop_loss under --wm-open-loop."""
    loss, terms, h_entry, valid = world_model_loss(wm, reward_dec, batch, args)
    if args.wm_open_loop:
        loss_open, terms_open = open_loop_loss(wm, reward_dec, batch, h_entry, args)
        loss, terms = loss + loss_open, terms | terms_open
    return loss, terms, h_entry, valid


def open_loop_loss(wm, reward_dec, batch: dict[str, torch.Tensor], h_entry: torch.Tensor, args: Args):
    """--wm-open-loop K: L_WM's terms after k = 1..K steps dreamt along the replayed actions from the
    teacher-forced h_t of every stride-th entry t, the world model's own z fed back (gradients through
    it): a dream runs open loop for 20 steps, while the one-step loss trains from the real z only. A
    start's step k counts while no episode ended in between."""
    K, z, a, last = args.wm_open_loop, batch["z"], batch["a"], batch["last"]
    r, d = batch["r"] - args.reward_offset, batch["d"]
    starts = torch.arange(0, z.shape[1] - K, args.wm_open_loop_stride, device=z.device)
    h, z_k = h_entry[:, starts].flatten(0, 1), z[:, starts].flatten(0, 1)
    alive = torch.ones(h.shape[0], device=z.device)
    loss_z = loss_r = loss_d = n = 0.0
    for k in range(K):
        t = starts + k
        alive = alive * (1 - last[:, t].flatten())
        h = wm.step(h, z_k, a[:, t].flatten(0, 1))
        z_k, r_out, d_logit = wm.heads(h)
        loss_z = loss_z + (((z_k - z[:, t + 1].flatten(0, 1)) ** 2).sum(-1) * alive).sum()
        loss_r = loss_r + (reward_dec.loss(r_out, r[:, t].flatten()) * alive).sum()
        bce = F.binary_cross_entropy_with_logits(d_logit, d[:, t].flatten(), reduction="none")
        loss_d = loss_d + (bce * alive).sum()
        n = n + alive.sum()
    n = n.clamp(min=1)
    loss_z, loss_r, loss_d = loss_z / n, loss_r / n, loss_d / n
    loss = args.wm_z_coef * loss_z + args.wm_reward_coef * loss_r + args.wm_done_coef * loss_d
    return loss, {"loss_z_open": loss_z, "loss_r_open": loss_r}


def dream_starts(h_entry: torch.Tensor, batch: dict[str, torch.Tensor], imag_from: str):
    """The states (h, z) that dreams start from, and their weights (0 for an episode's final observation,
    which has no next step to dream).

    last (the default): one per replayed sequence, its newest entry. Algorithms 1 and 2 encode "the
    first observation" of a dream and the text gives observations "only at the first step": one dream per
    sequence, whose FLOPs match the paper's table (docs/paper_readings.md). The newest entry is the one
    whose h_t has read the whole sequence, like h_t when acting; earlier entries of a sequence sampled
    mid-episode have an h_t that started from 0 at the sequence's start, which acting never sees.
    all: every entry that has a next one (DreamerV3's starts)."""
    if imag_from == "last":
        return h_entry[:, -1], batch["z"][:, -1], 1 - batch["last"][:, -1]
    n = h_entry.shape[0] * (h_entry.shape[1] - 1)
    h0 = h_entry[:, :-1].reshape(n, -1)
    return h0, batch["z"][:, :-1].reshape(n, -1), (1 - batch["last"][:, :-1]).reshape(n)


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


def imagine(agent, h0: torch.Tensor, z0: torch.Tensor, horizon: int, grad: bool = False) -> Dream:
    """Dream ``horizon`` steps from replayed states (h_t, z_t): the real z_t is given only at the first
    step, then the world model's own predictions (paper Figure 3 (2)). With ``grad`` the rollout is
    differentiable in the actions (dynamics backpropagation); without, no gradient flows through it."""
    wm = agent.wm
    with torch.set_grad_enabled(grad):
        feats, actions, rewards, conts, outs = [agent.features(h0, z0)], [], [], [], []
        h, z = h0, z0
        for _ in range(horizon):
            # The actor reads the dreamt state with its gradient stopped, as DreamerV3's policy(sg(s)):
            # an action's gradient is that of the returns after it, never through the actor's reply to
            # states its own earlier actions made (that path trains period-2 alternation on RoboDesk).
            outs.append(agent.actor(feats[-1].detach()))
            a = agent.actor.sample(outs[-1])
            h = wm.step(h, z, a)
            z, r_out, d_logit = wm.heads(h)
            feats.append(agent.features(h, z))
            actions.append(a)
            rewards.append(agent.reward_dec.value(r_out))
            conts.append(1 - torch.sigmoid(d_logit))
    return Dream(*map(torch.stack, (feats, actions, rewards, conts)), torch.stack(outs) if grad else None)


def lambda_returns(rewards, conts, values, gamma: float, lam: float) -> torch.Tensor:
    """R_k = r_{k+1} + gamma c_{k+1} ((1 - lam) v_{k+1} + lam R_{k+1}), R_H = v_H (DreamerV3)."""
    out, last = [], values[-1]
    for k in reversed(range(len(rewards))):
        last = rewards[k] + gamma * conts[k] * ((1 - lam) * values[k + 1] + lam * last)
        out.append(last)
    return torch.stack(out[::-1])


def actor_critic_loss(
    agent,
    dream: Dream,
    start_w,
    *,
    dynamics=False,
    gamma=1 - 1 / 333,
    lam=0.95,
    entropy_coef=3e-3,
    mean_reg=0.0,
):
    """DreamerV3 actor-critic on an imagined rollout, advantages normalised by the return scale, with an
    entropy bonus. The actor's gradient is REINFORCE, or (``dynamics``) that of the normalised
    lambda-return through the differentiable dream into the actions (DreamerV3 for continuous actions);
    the world model is trained by L_WM alone either way (``train_update``). A two-hot critic on
    lambda-returns regularised toward its slow copy. ``start_w`` masks starts that are an episode's final
    observation."""
    twohot, feats, conts = agent.twohot, dream.feats, dream.conts
    # One critic pass serves the bootstrap values and the critic's loss. Under dynamics backpropagation the
    # values stay differentiable through the dream for the actor; each loss is back-propagated into its
    # own network only (train_update), so the critic's loss still trains the critic alone.
    all_logits = agent.critic(feats)
    values, logits = twohot.mean(all_logits if dynamics else all_logits.detach()), all_logits[:-1]
    returns = lambda_returns(dream.rewards, conts, values, gamma, lam)  # (H, N)
    with torch.no_grad():
        # Weight of dreamt state k: the predicted probability that the episode is still running.
        w = torch.cumprod(torch.cat([torch.ones_like(conts[:1]), conts[:-1]]), 0) * start_w
        scale = agent.return_scale.update(returns)
        norm = scale.clamp(min=1.0).to(returns.dtype)  # float64 state, float32 math
        slow_target = twohot.mean(agent.slow_critic(feats[:-1].detach()))
    policy = agent.actor(feats[:-1].detach()) if dream.policy is None else dream.policy
    logp, entropy = agent.actor.log_prob(policy, dream.actions.detach())
    if dynamics:
        objective = (returns - values[:-1].detach()) / norm
    else:
        objective = logp * ((returns - values[:-1]) / norm).detach()
    loss_actor = -(w * (objective + entropy_coef * entropy)).mean()
    if mean_reg:  # the continuous actor's mean before its tanh, kept out of saturation
        m = policy.chunk(2, -1)[0]
        loss_actor = loss_actor + mean_reg * 0.5 * (m**2).sum(-1).mean()
    target = returns.detach()
    loss_critic = (w * (twohot.loss(logits, target) + twohot.loss(logits, slow_target))).mean()
    stats = {"return_scale": scale, "imag_return": target.mean(), "entropy": entropy.detach().mean()}
    return loss_actor, loss_critic, stats


def gw_loss(gw: GlobalWorkspace, u_v: torch.Tensor, u_attr: torch.Tensor, args: Args):
    """L_GW = sum_k beta_k L_k (eq. 1-3) on one batch of observations, and its terms."""
    alpha = fusion_weights(len(u_v), args.fusion_temperature, u_v.device)
    terms = gw_losses(gw, u_v, u_attr, alpha, args.contrastive_temperature)
    betas = LOSS_PRESETS[args.loss_preset]
    return sum(betas[k] * terms[k] for k in terms), terms


def replay_critic_loss(agent: Agent, h_entry: torch.Tensor, batch: dict[str, torch.Tensor], args: Args):
    """The critic on every replayed state (B, T + 1), toward lambda-returns of the replayed rewards that
    bootstrap from its own values and stop at an episode's final observation, regularised toward its slow
    copy like the dream loss (DreamerV3's replay value loss). A dream gives the critic one start per
    sequence; this gives it every state the agent visited, with rewards nobody dreamt."""
    r, d, last = batch["r"] - args.reward_offset, batch["d"], batch["last"]
    feats = agent.features(h_entry, batch["z"])
    logits = agent.critic(feats)
    values = agent.twohot.mean(logits.detach())
    ret, out = values[:, -1], []
    for t in reversed(range(feats.shape[1] - 1)):
        ret = r[:, t] + args.gamma * (1 - d[:, t]) * ((1 - args.lam) * values[:, t + 1] + args.lam * ret)
        ret = torch.where(last[:, t] > 0, values[:, t], ret)  # no transition out of a final observation
        out.append(ret)
    returns, valid = torch.stack(out[::-1], 1), 1 - last[:, :-1]
    with torch.no_grad():
        slow_target = agent.twohot.mean(agent.slow_critic(feats[:, :-1]))
    twohot = agent.twohot
    loss = twohot.loss(logits[:, :-1], returns) + twohot.loss(logits[:, :-1], slow_target)
    return (loss * valid).sum() / valid.sum().clamp(min=1)


def dream_loss(agent: Agent, h0: torch.Tensor, z0: torch.Tensor, start_w: torch.Tensor, args: Args):
    """The actor-critic's part of an update: dreams from (h0, z0), then their loss (Algorithm 1, lines
    12-14)."""
    dynamics = actor_grad(args) == "dynamics"
    dream = imagine(agent, h0, z0, args.imag_horizon, grad=dynamics)
    return actor_critic_loss(
        agent,
        dream,
        start_w,
        dynamics=dynamics,
        gamma=args.gamma,
        lam=args.lam,
        entropy_coef=args.entropy_coef,
        mean_reg=args.actor_mean_reg,
    )


EAGER = {
    "gw": gw_loss,
    "wm": world_model_loss_open_loop,
    "ac": dream_loss,
}  # the loss computations of an update


def compiled_losses(device, backend: str = "inductor") -> dict:
    """--compile: both loss computations through torch.compile, with CUDA graphs on a GPU. The optimizer
    steps stay eager; nothing in the compiled parts reads a value back to the host. (``backend``: the
    tests also use "aot_eager", the same graphs without generated kernels.)"""
    mode = "reduce-overhead" if str(device).startswith("cuda") else None
    # The actor's and the critic's losses come out of one compiled graph whose backward runs once per
    # loss (each reaches only its own network), so that graph keeps its buffers between the two calls.
    torch._functorch.config.donated_buffer = False
    return {k: torch.compile(fn, mode=mode, backend=backend) for k, fn in EAGER.items()}


def gw_update(
    agent: Agent, opt, replay: Replay, args: Args, gw_step: int, env_step: int = 0, losses: dict = EAGER
) -> dict:
    """GW update number ``gw_step`` on replayed observations: L_GW, AdamW at the OneCycle rate of this
    update (Algorithm 2, lines 7-11)."""
    dev = agent.twohot.bins.device
    u_v, u_attr = (torch.as_tensor(u, device=dev) for u in replay.sample_observations(args.gw_batch_size))
    loss_gw, terms = losses["gw"](agent.gw, u_v, u_attr, args)
    if losses is EAGER and not torch.isfinite(loss_gw):
        raise FloatingPointError(f"non-finite GW loss at env step {env_step:,}")
    for group in opt.param_groups:
        group["lr"] = gw_lr(gw_step, args)
    opt.zero_grad(set_to_none=True)
    loss_gw.backward()
    opt.step()
    return {"loss_gw": loss_gw} | {f"loss_{k}": v for k, v in terms.items()}


def train_update(
    agent: Agent,
    opts: dict,
    replay: Replay,
    args: Args,
    gw_steps: int = 0,
    env_step: int = 0,
    losses: dict = EAGER,
) -> dict:
    """One global training step: ``args.gw_updates`` GW updates (numbered from ``gw_steps``), the world
    model on replayed sequences encoded by the updated GW, then the actor-critic on rollouts dreamt from
    the replayed states (Algorithm 2). Returns detached tensors, read once per log interval. Eager losses
    are checked at once (the bad update is not applied); compiled ones at the next log line or save."""
    dev, check = agent.twohot.bins.device, losses is EAGER
    gw_terms = {}  # --gw-updates 0 freezes the random GW (a check, not a paper variant)
    for i in range(args.gw_updates):
        gw_terms = gw_update(agent, opts["gw"], replay, args, gw_steps + i, env_step, losses)
    batch = {
        k: torch.as_tensor(v, device=dev)
        for k, v in replay.sample(args.batch_size, args.batch_length).items()
    }
    batch["z"] = agent.z(batch.pop("u_v"), batch.pop("u_attr"))  # current GW, alpha 0.5/0.5, no gradient
    loss_wm, terms, h_entry, _ = losses["wm"](agent.wm, agent.reward_dec, batch, args)
    if check and not torch.isfinite(loss_wm):
        raise FloatingPointError(f"non-finite world-model loss at env step {env_step:,}")
    opts["wm"].zero_grad(set_to_none=True)
    loss_wm.backward()
    nn.utils.clip_grad_norm_(agent.wm.parameters(), 1000.0)
    opts["wm"].step()
    h0, z0, start_w = dream_starts(h_entry.detach(), batch, args.imag_from)
    loss_actor, loss_critic, stats = losses["ac"](agent, h0, z0, start_w, args)
    if args.critic_replay_coef:
        stats["loss_critic_replay"] = replay_critic_loss(agent, h_entry.detach(), batch, args)
        loss_critic = loss_critic + args.critic_replay_coef * stats["loss_critic_replay"]
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
    with torch.no_grad():  # slow critic: EMA of the critic (DreamerV3)
        for p_slow, p in zip(agent.slow_critic.parameters(), agent.critic.parameters(), strict=True):
            p_slow.lerp_(p, 1 - args.slow_critic_decay)
    out = {
        "loss_wm": loss_wm,
        **terms,
        "loss_actor": loss_actor,
        "loss_critic": loss_critic,
        **stats,
        **gw_terms,
    }
    out = {k: v.detach().clone() for k, v in out.items()}  # a copy: CUDA graphs reuse their outputs
    return out | {"gw_lr": torch.tensor(opts["gw"].param_groups[0]["lr"])}


def make_optimizers(agent: Agent, args: Args) -> dict:
    """AdamW for the GW (its learning rate is set by ``gw_lr`` before each update), Adam for the others
    (appendix Tables "GW-Dreamer training" and "GW training in GW-Dreamer End-to-End"; eps as DreamerV3)."""
    return {
        "gw": torch.optim.AdamW(
            agent.gw.parameters(), lr=args.gw_lr_start, weight_decay=args.gw_weight_decay
        ),
        "wm": torch.optim.Adam(agent.wm.parameters(), lr=args.wm_lr, eps=1e-8),
        "actor": torch.optim.Adam(agent.actor.parameters(), lr=args.ac_lr, eps=1e-5),
        "critic": torch.optim.Adam(agent.critic.parameters(), lr=args.ac_lr, eps=1e-5),
    }


def updates_due(env_steps: int, args: Args) -> int:
    """Training updates owed after ``env_steps`` environment steps (the paper's unit).

    The paper's "train ratio" (4 Simple Shapes, 2 RoboDesk) is read as agent steps per update: Algorithm
    1 collects n transitions then makes m updates, here m = 1 update per n = train_ratio agent steps,
    i.e. 4,750 updates by the paper's 20,000-step Simple Shapes criterion (after 1,000 random steps), and
    one update per 8 simulator frames on RoboDesk. DreamerV3's meaning (replayed steps per env step)
    would give one update of 64 x 32 replayed steps per 512 env steps, 39 updates by 20,000 steps: too
    few to train a world model and an actor-critic from scratch, so it cannot be the paper's."""
    agent_steps = max(env_steps - args.learning_starts, 0) / ACTION_REPEAT[args.env]
    return int(agent_steps / args.train_ratio)


def explore(a: torch.Tensor, args: Args, env_steps: int) -> torch.Tensor:
    """The action taken while collecting: the actor's a_t plus --explore-noise's N(0, sigma^2), clipped to
    the action box (the replay stores it). Evaluations and dreams use the actor's a_t as it is."""
    if not args.explore_noise:
        return a
    return (a + args.explore_noise * torch.randn_like(a)).clamp(-1, 1)


def count_flops(fn):
    """``fn()`` and the forward + backward FLOPs it took (torch.utils.flop_counter)."""
    with FlopCounterMode(display=False) as counter:
        out = fn()
    return out, counter.get_total_flops()


# --------------------------------------------------------------------------------------------------
# Algorithm 2
# --------------------------------------------------------------------------------------------------
def main(args: Args) -> dict:
    args = args.resolve()
    check_settings(args)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    dev = torch.device(args.device)
    vaes, paths = load_frozen(args, dev)  # Require: the pre-trained unimodal models (VAEs)
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    agent = Agent(
        args.env, args.reward_loss, args.return_norm_decay, args.cpu_preset, done_head=args.done_head == "on"
    ).to(dev)
    model = "gw" if args.loss_preset == "gw" else "clip"
    default = Path(args.checkpoint_dir) / args.env / "agents" / f"{run_name(args, model)}.pt"
    agent_path = Path(args.checkpoint) if args.checkpoint else default
    if args.eval_only:
        return evaluate_checkpoint(agent, vaes, args, agent_path, vae_fingerprint(vaes))
    # Initialize the GW, the world model, the actor-critic and the replay buffer (or continue a run).
    run = start_run(args, vaes, agent, paths, agent_path)
    state, replay, n_envs, repeat = run.state, run.replay, args.num_envs, ACTION_REPEAT[args.env]
    losses = compiled_losses(dev) if args.compile else EAGER
    action_dim = SIZES[args.env]["actions"]

    envs_ = make_envs(args, n_envs)
    obs, _ = envs_.reset(seed=args.seed + state.env_steps)
    h = torch.zeros(n_envs, agent.wm.hidden, device=dev)
    first = np.ones(n_envs, np.float32)
    ep_ret, ep_succ = np.zeros(n_envs), np.zeros(n_envs)
    rng = np.random.default_rng(args.seed + state.env_steps)
    logs = {}
    stop = StopRequest(TAG)
    while state.env_steps < args.total_steps:
        if args.stop_at_criterion and state.criterion_step is not None:
            break
        # Collect transitions (o_t, a_t, o_{t+1}, r_{t+1}, d_{t+1}) with the current policy into the
        # replay buffer as frozen VAE means (u_v, u_attr) (uniformly random actions before learning
        # starts); the policy reads z_t of the GW as it is now.
        with torch.no_grad():
            u_v, u_attr = vaes(obs)
            z = agent.z(u_v, u_attr)
            if state.env_steps < args.learning_starts:
                a = random_actions(rng, n_envs, action_dim, agent.discrete, dev)
            else:
                a = explore(agent.actor.act(agent.features(h, z)), args, state.env_steps)
            h = agent.wm.step(h, z, a)
        obs, r, term, trunc, info = envs_.step(action_for_env(a, agent.discrete))
        u = (u_v.cpu().numpy(), u_attr.cpu().numpy())
        replay.add(np.arange(n_envs), *u, a.cpu().numpy(), r, term, first, np.zeros(n_envs))
        first = np.zeros(n_envs, np.float32)
        ep_ret += r
        ep_succ += step_success(info, n_envs)
        state.env_steps += n_envs * repeat  # the paper's unit: simulator frames on RoboDesk
        done = term | trunc
        if done.any():  # the episode's final observation closes its stream (an entry marked last)
            ends = np.flatnonzero(done)
            u_final = (u.cpu().numpy() for u in vaes(final_observations(info, ends)))
            zeros, no_action = np.zeros(len(ends)), np.zeros((len(ends), action_dim))
            replay.add(ends, *u_final, no_action, zeros, zeros, zeros, np.ones(len(ends)))
            for i in ends:
                log_episode(run, float(ep_ret[i]), float(ep_succ[i]))
            ep_ret[ends], ep_succ[ends], first[ends] = 0.0, 0.0, 1.0
            h[torch.as_tensor(ends, device=dev)] = 0.0

        # Training steps: the updates owed by the train ratio, each two GW updates, the world model
        # and the actor-critic in dreams (train_update), once the buffer holds a full batch sequence.
        while state.updates < updates_due(state.env_steps, args) and replay.ready(args.batch_length):
            try:
                if state.flops_per_update == 0:  # same shapes every update: count the first one
                    logs, state.flops_per_update = count_flops(
                        lambda: train_update(agent, run.opts, replay, args, state.gw_updates, state.env_steps)
                    )
                else:
                    logs = train_update(
                        agent, run.opts, replay, args, state.gw_updates, state.env_steps, losses
                    )
            except FloatingPointError as err:
                raise FloatingPointError(f"{err}; {last_good(run.agent_path)}") from err
            state.updates += 1
            state.gw_updates += args.gw_updates
            state.flops += state.flops_per_update

        # What is due at this step: the last update's losses and a progress line (--log-every), an
        # evaluation on fresh episodes (--eval-every), real frames beside a dream (--video-every), a save.
        if state.env_steps % args.log_every < n_envs * ACTION_REPEAT[args.env] and logs:
            log_progress(run, logs)
        if state.env_steps >= state.next_eval:
            state.next_eval += args.eval_every
            evaluate(run)
        if state.env_steps >= state.next_video:
            state.next_video += args.video_every or args.total_steps
            strip = dream_filmstrip(agent, vaes, args, 16, seed=10**6)
            run.writer.add_image("dreams/real_top_imagined_bottom", strip, state.env_steps, dataformats="HWC")
        if save_due(run):
            save(run)
        if stop.requested:
            envs_.close()
            stop.restore()
            interrupted(run)
    stop.restore()
    envs_.close()
    return finish(run)


ACTION_REPEAT = {"simple_shapes": 1, "robodesk": 4}


# --------------------------------------------------------------------------------------------------
# Environments and evaluation
# --------------------------------------------------------------------------------------------------
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
    """Last observations of the episodes that ended (same-step autoreset): the batched Simple Shapes env
    gives a dict of arrays, gymnasium's SyncVectorEnv an array of per-env dicts."""
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


@torch.no_grad()
def run_episodes(agent: Agent, vaes: FrozenVAEs, args: Args, n: int, drop: str, seed: int):
    """n full episodes with fresh environments (seeds seed..seed+n-1); returns per-episode returns and
    success counts (RoboDesk: steps in which the task's success criterion holds)."""
    dev = vaes.attr_mean.device
    envs_ = make_envs(args, n)
    obs, _ = envs_.reset(seed=seed)
    h = torch.zeros(n, agent.wm.hidden, device=dev)
    returns, successes = np.zeros(n), np.zeros(n)
    alive = np.ones(n, bool)
    while alive.any():
        z = agent.z(*vaes(obs), drop)
        a = agent.actor.act(agent.features(h, z))
        obs, r, term, trunc, info = envs_.step(action_for_env(a, agent.discrete))
        returns += r * alive
        successes += step_success(info, n) * alive
        alive &= ~(term | trunc)
        h = agent.wm.step(h, z, a)
    envs_.close()
    return returns, successes


@torch.no_grad()
def dream_filmstrip(agent: Agent, vaes: FrozenVAEs, args: Args, steps: int, seed: int) -> np.ndarray:
    """Real frames (top row) beside the world model's dream (bottom row) from the same start state and
    actions: the dream sees the real z_0 only, then its own predictions, decoded through d_v and the
    visual VAE decoder. Returns a uint8 (2 H, steps W, 3) image."""
    dev = vaes.attr_mean.device
    env = make_envs(args, 1)
    obs, _ = env.reset(seed=seed)
    h = torch.zeros(1, agent.wm.hidden, device=dev)
    z_dream = agent.z(*vaes(obs))
    h_dream = h.clone()
    real, dream = [obs["image"][0]], [vaes.decode_image(agent.gw.d["v"](z_dream))]
    for _ in range(steps - 1):
        z = agent.z(*vaes(obs))
        a = agent.actor.act(agent.features(h, z), mode=True)
        obs, _, term, trunc, info = env.step(action_for_env(a, agent.discrete))
        h = agent.wm.step(h, z, a)
        h_dream = agent.wm.step(h_dream, z_dream, a)
        z_dream = agent.wm.heads(h_dream)[0]
        ended = (term | trunc).any()
        real.append(final_observations(info, np.array([0]))["image"][0] if ended else obs["image"][0])
        dream.append(vaes.decode_image(agent.gw.d["v"](z_dream)))
        if ended:
            break
    env.close()
    dream_img = [(d[0].permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8) for d in dream]
    return np.concatenate([np.concatenate(real, 1), np.concatenate(dream_img, 1)], 0)


def random_actions(rng: np.random.Generator, n: int, action_dim: int, discrete: bool, dev) -> torch.Tensor:
    """The uniformly random policy that fills the replay buffer before learning starts."""
    if discrete:
        a = F.one_hot(torch.as_tensor(rng.integers(0, action_dim, n)), action_dim)
    else:
        a = torch.as_tensor(rng.uniform(-1, 1, (n, action_dim)))
    return a.float().to(dev)


# --------------------------------------------------------------------------------------------------
# Frozen VAEs of pretrain_vae_gw.py (same layers, so the same weights load) and the trainable GW
# --------------------------------------------------------------------------------------------------
def conv_block(cin: int, cout: int, transpose: bool = False, stride: int = 2) -> nn.Sequential:
    conv = (nn.ConvTranspose2d if transpose else nn.Conv2d)(
        cin, cout, 4 if stride == 2 else 3, stride, 1, bias=False
    )
    return nn.Sequential(conv, nn.BatchNorm2d(cout), nn.ReLU())


class VisualVAE(nn.Module):
    """Appendix Tables VAE_v: conv encoder to the mean/log-variance of u_v, decoder back to an image."""

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
        self.width = width
        self.fc = nn.Linear(latent, 8 * 8 * width)
        dec, cin = [], width
        for i, c in enumerate(up):
            dec.append(conv_block(cin, c, transpose=True, stride=2 if i < n_up else 1))
            cin = c
        self.decoder = nn.Sequential(*dec, nn.Conv2d(cin, 3, 3, 1, 1), nn.Sigmoid())

    def encode_mean(self, x: torch.Tensor) -> torch.Tensor:
        return self.q(self.encoder(x)).chunk(2, dim=-1)[0]

    def decode(self, u: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.fc(u).view(-1, self.width, 8, 8))


class AttrVAE(nn.Module):
    """Appendix Tables VAE_attr (only the encoder's mean is used here)."""

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


class GlobalWorkspace(nn.Module):
    """Encoders e_v, e_attr and decoders d_v, d_attr (appendix Tables GW_SS / GW_Rob), here from random
    weights and trained during the run (Algorithm 2)."""

    def __init__(self, latent: int, z: int, hidden: int):
        super().__init__()
        self.e = nn.ModuleDict({"v": mlp(latent, hidden, z, 4), "attr": mlp(latent, hidden, z, 4)})
        self.d = nn.ModuleDict({"v": mlp(z, hidden, latent, 4), "attr": mlp(z, hidden, latent, 4)})

    def fuse(self, u_v, u_attr, alpha_v, alpha_attr) -> torch.Tensor:
        """z = tanh(alpha_v e_v(u_v) + alpha_attr e_attr(u_attr)) (eq. of Figure 1); alphas are scalars or
        per-sample (B, 1)."""
        return torch.tanh(alpha_v * self.e["v"](u_v) + alpha_attr * self.e["attr"](u_attr))


class FrozenVAEs(nn.Module):
    """Observation -> frozen VAE means (u_v, u_attr) (Algorithm 2, "Encode the different observations
    using the pre-trained VAEs"), and u_v -> image for the dream frames."""

    def __init__(self, env: str, vae: dict):
        """``vae``: the checkpoint of pretrain_vae_gw.py's vae stage (see ``load_vaes``)."""
        super().__init__()
        s = ENV_SPECS[env]
        self.vae_v = VisualVAE(s["image"], s["latent"], vae["config"]["vae_width"])
        depth, hidden = (2, 64) if env == "simple_shapes" else (4, 512)
        self.vae_attr = AttrVAE(s["attr"], s["latent"], hidden, depth)
        self.vae_v.load_state_dict(vae["vae_v"])
        self.vae_attr.load_state_dict(vae["vae_attr"])
        self.register_buffer("attr_mean", torch.as_tensor(vae["attr_mean"], dtype=torch.float32))
        self.register_buffer("attr_std", torch.as_tensor(vae["attr_std"], dtype=torch.float32))
        self.latent = s["latent"]
        # RoboDesk: the image quality of the VAEs' training data (the agent must see the same images).
        self.render_quality = vae.get("args", {}).get("render_quality", "faithful")
        self.eval().requires_grad_(False)

    @torch.no_grad()
    def forward(self, obs: dict[str, np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        dev = self.attr_mean.device
        image = torch.as_tensor(obs["image"], device=dev).permute(0, 3, 1, 2).float() / 255.0
        attr = torch.as_tensor(obs["attr"], device=dev, dtype=torch.float32)
        return self.vae_v.encode_mean(image), self.vae_attr.encode_mean(
            (attr - self.attr_mean) / self.attr_std
        )

    @torch.no_grad()
    def decode_image(self, u_v: torch.Tensor) -> torch.Tensor:
        return self.vae_v.decode(u_v)


def load_vaes(env: str, vae_path: Path, checkpoint_dir: str = "checkpoints") -> FrozenVAEs:
    """The frozen VAEs from pretrain_vae_gw.py's checkpoint, checked against ``env``."""
    vae = load_pretrained(vae_path, "vae", env, "collect vae", checkpoint_dir)
    try:
        return FrozenVAEs(env, vae)
    except RuntimeError as err:  # a state dict of other sizes
        raise UsageError(f"{vae_path} does not fit the {env} networks: {err}") from err


FUSION = {"none": (0.5, 0.5), "vision": (0.0, 1.0), "attr": (1.0, 0.0)}  # (alpha_v, alpha_attr)


# --------------------------------------------------------------------------------------------------
# Checkpoints and settings
# --------------------------------------------------------------------------------------------------
def vae_fingerprint(vaes: FrozenVAEs) -> float:
    """A number that changes with the frozen weights: a resumed or evaluated agent must use the VAEs it
    was trained on (its GW is part of the agent checkpoint)."""
    return float(sum(p.double().sum() for p in vaes.parameters()))


# Settings that may differ between the parts of one run (how long it runs, how it reports, where its files
# are); every other setting defines the run, and --resume refuses a change to any of them.
MAY_CHANGE = set(
    "total_steps stop_at_criterion eval_every eval_episodes log_every save_every video_every device"
    " save_minutes torch_threads resume overwrite checkpoint checkpoint_dir vae_checkpoint exp_name"
    " eval_only drop compile".split()
)


# Settings an evaluation must share with the agent it loads (they shape its networks or inputs).
EVAL_KEYS = ("task", "reward_loss", "loss_preset", "render_quality", "done_head")


# What the run infrastructure below the fence reads of this script.
SCRIPT = {
    "kind": "gw_dreamer_e2e",  # the kind recorded in its agent checkpoints
    "train": "python gw_dreamer_e2e.py --env {env}",  # the command that trains one
    "fingerprint": "vae_fingerprint",  # the checkpoint entry that identifies the frozen weights
    # checkpoints saved before --done-head existed record no "on" / "off" (convert_checkpoint.py adds it)
    "older_layout": lambda ckpt: not isinstance(ckpt["args"].get("done_head"), str),
    # On RoboDesk --cpu-preset sets the network sizes; on Simple Shapes only the GW's batch.
    "eval_keys": lambda args: EVAL_KEYS + (("cpu_preset",) if args.env == "robodesk" else ()),
    "video": lambda run: dream_filmstrip(run.agent, run.frozen, run.args, 16, seed=10**6),
    "progress": lambda logs: (
        f"wm {logs['loss_wm']:.3f} (z {logs['loss_z']:.3f} r {logs['loss_r']:.3f} d {logs['loss_d']:.3f}) "
        f"gw {logs.get('loss_gw', math.nan):.3f}"
    ),
    "charts": ("gw_lr",),  # scalars of the progress logs that are no losses
}


def checkpoint_entries(run: Run) -> dict:
    """What an agent checkpoint of this script holds besides its kind, env, task, settings, counters and
    random states (never weights a non-finite --compile update has reached)."""
    if run.args.compile and not all(torch.isfinite(p).all() for p in run.agent.parameters()):
        step = run.state.env_steps
        raise FloatingPointError(f"non-finite weights at env step {step:,}; {last_good(run.agent_path)}")
    return {
        "model": run.model,
        "vae_checkpoint": str(run.pretrained["vae.pt"]),
        "vae_fingerprint": vae_fingerprint(run.frozen),
        "agent": run.agent.state_dict(),
        "opts": {name: opt.state_dict() for name, opt in run.opts.items()},
        "replay": run.replay.state_dict(),
    }


# Ranges of this script's flags (check_settings, below the fence, adds the flags every agent has).
RANGES = {
    ">= 1": "batch_size batch_length imag_horizon eval_every log_every wm_open_loop_stride",
    ">= 2": "gw_batch_size",  # it pairs samples
    ">= 0": "learning_starts video_every entropy_coef wm_z_coef wm_reward_coef wm_done_coef actor_mean_reg"
    " gw_updates gw_weight_decay critic_replay_coef wm_open_loop explore_noise",
    "> 0": "save_minutes train_ratio wm_lr ac_lr gw_cycle gw_lr_start gw_lr_max gw_lr_end fusion_temperature"
    " contrastive_temperature",
    "[0, 1]": "lam slow_critic_decay return_norm_decay",
}


def script_checks(args: Args) -> None:
    """The replay holds a whole sequence per environment, the run makes at least one update, and rewards
    are offset and the done head left out only where episodes never end."""
    need = (args.batch_length + 1) * args.num_envs
    rule = f"must hold a replayed sequence (--batch-length + 1 entries) per environment: at least {need}"
    require(args.buffer_size >= need, "buffer_size", args.buffer_size, rule)
    rule = f"must be below --total-steps {args.total_steps:,}, or the run would make no update"
    ok = args.eval_only or args.learning_starts < args.total_steps
    require(ok, "learning_starts", args.learning_starts, rule)
    rule = "is for RoboDesk, whose episodes never end: where they end it changes the best policy"
    require(args.env == "robodesk" or args.reward_offset == 0, "reward_offset", args.reward_offset, rule)
    rule = "is for RoboDesk, whose episodes never end early: Simple Shapes episodes end at the goal"
    require(args.env == "robodesk" or args.done_head == "on", "done_head", args.done_head, rule)
    rule = f"must be below --batch-length {args.batch_length}: each start needs K replayed steps after it"
    require(args.wm_open_loop < args.batch_length, "wm_open_loop", args.wm_open_loop, rule)
    rule = "is for continuous actions (RoboDesk)"
    require(args.env == "robodesk" or not args.explore_noise, "explore_noise", args.explore_noise, rule)


def schedule(args: Args) -> str:
    """One line that says how this run reads the paper's training schedule (printed at start)."""
    repeat = ACTION_REPEAT[args.env]
    starts = args.batch_size * (1 if args.imag_from == "last" else args.batch_length)
    unit = "agent steps" if repeat == 1 else f"simulator frames ({repeat} per agent step)"
    last = args.imag_from == "last"
    where = "the newest state of each replayed sequence" if last else "every replayed state"
    return (
        f"schedule: one update per {args.train_ratio:g} agent steps (train ratio) after "
        f"{args.learning_starts:,} random steps; world model on {args.batch_size} x {args.batch_length} "
        f"replayed steps; {starts:,} dreams of {args.imag_horizon} steps from {where} (--imag-from "
        f"{args.imag_from}); actor gradient {actor_grad(args)}; {args.total_steps:,} env steps, counted "
        f"in {unit}"
    )


def actor_grad(args: Args) -> str:
    """The actor's gradient estimator: --actor-grad, or by the action space (auto, as DreamerV3)."""
    if args.actor_grad != "auto":
        return args.actor_grad
    return "reinforce" if args.env == "simple_shapes" else "dynamics"


# --------------------------------------------------------------------------------------------------
# The run: what the training loop carries, and the bookkeeping around Algorithm 2
# --------------------------------------------------------------------------------------------------
@dataclass
class LoopState:
    """Counters of the training loop (saved in the agent checkpoint, restored by --resume)."""

    env_steps: int = 0  # in the paper's unit (RoboDesk: simulator frames)
    updates: int = 0
    gw_updates: int = 0  # the GW's own updates (its OneCycle schedule counts them)
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
    frozen: FrozenVAEs  # the frozen VAEs
    agent: Agent
    opts: dict
    replay: Replay
    state: LoopState
    writer: SummaryWriter
    agent_path: Path
    pretrained: dict  # {"vae.pt": path}
    model: str  # "gw" (GW-Dreamer end to end) or "clip" (its CLIP-like variant)
    ref: tuple | None  # Simple Shapes returns of the random and the greedy policy (normalisation)
    t0: float = field(default_factory=time.time)
    last_save: float = field(default_factory=time.time)
    steps0: int = 0

    def normalise(self, ret: float) -> float:
        return (ret - self.ref[0]) / (self.ref[1] - self.ref[0]) if self.ref else float("nan")


def load_frozen(args: Args, dev) -> tuple[FrozenVAEs, dict]:
    """The frozen VAEs this run reads (yours under --checkpoint-dir, else the bundled ones)."""
    paths = pretrained_paths(args.checkpoint_dir, args.env, {"vae.pt": args.vae_checkpoint})
    vaes = load_vaes(args.env, paths["vae.pt"], args.checkpoint_dir)
    if args.env == "robodesk":  # the images the VAEs were trained on, or a clear refusal
        if args.render_quality is None:
            args.render_quality = vaes.render_quality
        elif args.render_quality != vaes.render_quality:
            raise UsageError(
                f"--render-quality {args.render_quality}: the VAEs in {paths['vae.pt']} were trained on "
                f"{vaes.render_quality} images, and their encoders have never seen the other kind; leave "
                f"the flag out, or pre-train VAEs on {args.render_quality} images"
            )
    return vaes.to(dev), paths


def run_name(args: Args, model: str) -> str:
    task = "" if args.env == "simple_shapes" else f"_{args.task}"
    return f"{args.exp_name}_{model}_{args.env}{task}_s{args.seed}"


def start_run(args: Args, vaes: FrozenVAEs, agent: Agent, paths: dict, agent_path: Path) -> Run:
    """Claim the outputs, build optimizers and replay, resume when asked, and print what runs."""
    model = "gw" if args.loss_preset == "gw" else "clip"
    runs_dir = Path("runs") / run_name(args, model)
    # Nothing of an earlier run is overwritten by accident, and the output folders take files now.
    claim_outputs([agent_path, runs_dir], args.resume, args.overwrite, "gw_dreamer_e2e")
    ensure_writable(agent_path.parent)
    ensure_writable(runs_dir)
    opts = make_optimizers(agent, args)
    replay = Replay(args.buffer_size, args.num_envs, vaes.latent, SIZES[args.env]["actions"], args.seed)
    state = LoopState(
        next_eval=args.eval_every, next_save=args.save_every, next_video=args.video_every or args.total_steps
    )
    if args.resume:
        ck = load_agent_checkpoint(agent_path, args, vae_fingerprint(vaes))
        agent.load_state_dict(ck["agent"])
        for name, opt in opts.items():
            opt.load_state_dict(ck["opts"][name])
        replay.load_state_dict(ck["replay"])
        replay.close_episodes()  # the saved run stopped mid-episode
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
    run = Run(args, vaes, agent, opts, replay, state, writer, agent_path, paths, model, ref)
    run.steps0 = state.env_steps
    n = {k: sum(p.numel() for p in getattr(agent, k).parameters()) for k in ("gw", "wm", "actor", "critic")}
    frozen = sum(p.numel() for p in vaes.parameters())
    task = "" if args.env == "simple_shapes" else f"_{args.task}"
    print(
        f"[{TAG}] {model.upper()}-Dreamer end to end on {args.env}{task}: GW {n['gw']:,}, "
        f"world model {n['wm']:,}, actor {n['actor']:,}, critic {n['critic']:,} parameters "
        f"(+ {frozen:,} frozen VAE)"
    )
    print(f"[{TAG}] {schedule(args)}")
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
