"""PPO, VAE-PPO, CLIP-PPO and GW-PPO: the model-free baselines of the paper, in one CleanRL-style file.

Paper: section "Results / Comparison with baselines" (the paper trained them with stable-baselines3; this
is our own PPO, with the settings of the group's GW-PPO on Simple Shapes, docs/paper_readings.md).

    python pretrain_vae_gw.py --env simple_shapes --cpu-preset      # VAEs + GW (for vae / gw)
    python pretrain_vae_gw.py --env simple_shapes --stages gw --loss-preset clip --cpu-preset   # clip
    python ppo_variants.py --env simple_shapes --variant gw         # GW-PPO
    python ppo_variants.py --env simple_shapes --variant raw        # multimodal PPO on raw observations
    python ppo_variants.py --env simple_shapes --variant gw --eval-only --drop vision \\
        --checkpoint checkpoints/simple_shapes/agents/ppo_gw_simple_shapes_s1.pt

Inputs per variant (4 stacked frames each):
- raw: the image (CNN) and the attribute vector together;
- vae: the concatenated frozen VAE means [u_v, u_attr];
- clip / gw: the single fused representation z = tanh(0.5 e_v(u_v) + 0.5 e_attr(u_attr)) of the frozen
  CLIP-like / GW model.

Reading map, top to bottom:
    Args, ENV_SPECS               the settings, and the shapes of each environment's inputs
    RawExtractor, Agent           the image + attribute CNN for raw inputs, the policy and value heads
    ppo_loss, gae, ppo_update     the clipped PPO loss, advantages, one minibatch update
    main, update                  rollouts, GAE, update epochs, the log line and the saves
    FrameStack ... run_episodes   4-frame stacks, the environments, evaluation episodes
    VisualVAE ... Observer        the frozen VAEs, GW or CLIP-like model of pretrain_vae_gw.py
    SCRIPT ... log_iteration      this script's part of the run; below the ==== fence, the shared block
"""

from __future__ import annotations

import atexit
import ctypes
import errno
import hashlib
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
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
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
    variant: Literal["raw", "vae", "clip", "gw"] = "gw"
    """raw: PPO on image + attributes; vae: VAE-PPO; clip: CLIP-PPO; gw: GW-PPO"""
    seed: int = 1
    """seed of the environments, the networks and the minibatches"""
    exp_name: str = "ppo"
    """run name prefix: runs/<exp_name>_<variant>_<env>[_<task>]_s<seed>"""
    device: str = "cuda" if torch.cuda.is_available() else "cpu"
    """torch device"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default)"""

    # frozen representations (pretrain_vae_gw.py), for vae / clip / gw
    checkpoint_dir: str = "checkpoints"
    """where pretrain_vae_gw.py wrote <env>/{vae,gw,clip}.pt; agent checkpoints go to <env>/agents/"""
    vae_checkpoint: str | None = None
    """VAE checkpoint (default <checkpoint_dir>/<env>/vae.pt)"""
    gw_checkpoint: str | None = None
    """GW or CLIP-like checkpoint (default <checkpoint_dir>/<env>/gw.pt for gw, clip.pt for clip)"""

    # PPO (the group's GW-PPO settings on Simple Shapes, docs/paper_readings.md; CleanRL's algorithm)
    total_steps: int = 1_000_000
    """environment steps"""
    num_envs: int = 2
    """parallel environments"""
    env_processes: bool = False
    """RoboDesk: step each of the --num-envs environments in its own process (gymnasium's AsyncVectorEnv),
    so that their simulators and renderers run on several cores; the same observations and rewards as in
    one process"""
    num_steps: int = 8_192
    """steps per environment per rollout (2 x 8,192 = 16,384 per rollout)"""
    update_epochs: int = 15
    """passes over each rollout"""
    minibatch_size: int = 512
    """transitions per gradient step"""
    learning_rate: float = 3e-4
    """Adam learning rate (annealed linearly to 0 with --anneal-lr)"""
    anneal_lr: bool = True
    """anneal the learning rate linearly to 0 over the run (CleanRL)"""
    gamma: float = 0.9
    """discount"""
    gae_lambda: float = 0.95
    """lambda of generalised advantage estimation"""
    clip_coef: float = 0.2
    """surrogate clipping coefficient"""
    clip_vloss: bool = True
    """clip the value loss around the rollout's values (CleanRL)"""
    norm_adv: bool = True
    """normalise advantages per minibatch"""
    ent_coef: float = 0.0
    """entropy coefficient"""
    vf_coef: float = 0.5
    """value-loss coefficient"""
    max_grad_norm: float = 0.5
    """global gradient-norm clip"""
    target_kl: float | None = None
    """stop an update's epochs early when the approximate KL exceeds this (None: never)"""
    norm_reward: bool = True
    """divide rewards by a running std of the discounted return (stable-baselines3's VecNormalize,
    CleanRL's NormalizeReward): Simple Shapes rewards of -5 to -40 per step give values near -250 that a
    64-unit critic fits slowly (its effect: docs/ppo_variants.md)"""
    frame_stack: int = 4
    """observations stacked as the policy input"""
    hidden: int = 64
    """width of the two hidden layers of the actor and the critic (stable-baselines3's default)"""

    # environments
    render_quality: Literal["faithful", "fast"] | None = None
    """RoboDesk image quality; default: for vae / clip / gw that of the images their VAE was trained on
    (another one is refused), for raw faithful (fast: CPU experiments, docs/environments.md)"""
    episode_length: int = 2000
    """RoboDesk episode length in physics-control repeats (paper: 2000, i.e. 500 agent steps)"""

    # evaluation, logging, checkpoints
    criterion: float | None = None
    """normalised return that defines the return criterion (default 0.75 Simple Shapes, 0.70 RoboDesk:
    the paper's 70%)"""
    smoothing: int = 10
    """training episodes in the sliding window of the smoothed return (paper: 10)"""
    stop_at_criterion: bool = False
    """end the run (final evaluation, checkpoint) after the rollout in which the return criterion is
    reached: measures the steps and wall time to the criterion without training on"""
    eval_episodes: int = 10
    """episodes for --eval-only and the final evaluation"""
    save_every: int = 1
    """rollouts between resumable checkpoints"""
    save_minutes: float = 15.0
    """wall-clock minutes a run may go without a resumable checkpoint: when the update about to start
    would end later than that after the last save (judged by the last update's length), the rollout is
    saved before it, and --resume runs that update first"""
    overwrite: bool = False
    """replace an earlier run of the same name (its agent checkpoint and runs/ folder); without it a run
    whose files exist stops at start"""
    resume: bool = False
    """continue the run stored at --checkpoint (default: this run's agent checkpoint)"""
    checkpoint: str | None = None
    """agent checkpoint (default <checkpoint_dir>/<env>/agents/<run name>.pt)"""
    eval_only: bool = False
    """only evaluate --checkpoint (the modality ablation with --drop) and exit"""
    drop: Literal["none", "vision", "attr"] = "none"
    """modality removed at evaluation: clip/gw set alpha to (0, 1) / (1, 0), raw/vae zero the input"""

    def resolve(self) -> Args:
        """The per-environment default of --criterion (and of the images, where no VAE decides them)."""
        if self.criterion is None:
            self.criterion = 0.75 if self.env == "simple_shapes" else 0.70
        if self.render_quality is None and (self.variant == "raw" or self.env == "simple_shapes"):
            self.render_quality = "faithful"
        return self


ENV_SPECS = {  # must agree with pretrain_vae_gw.py (checked against the checkpoints)
    "simple_shapes": {"image": 32, "attr": 11, "latent": 10, "z": 10, "gw_hidden": 64},
    "robodesk": {"image": 64, "attr": 76, "latent": 40, "z": 76, "gw_hidden": 512},
}
TAG = "ppo"  # the prefix of every line this script prints


def mlp(cin: int, hidden: int, cout: int, depth: int, act=nn.ReLU) -> nn.Sequential:
    layers = []
    for _ in range(depth):
        layers += [nn.Linear(cin, hidden), act()]
        cin = hidden
    return nn.Sequential(*layers, nn.Linear(hidden, cout))


# --------------------------------------------------------------------------------------------------
# Agent (CleanRL's PPO agent; stable-baselines3's layout: a feature extractor, then separate 64-64 tanh
# MLPs for the policy and the value)
# --------------------------------------------------------------------------------------------------
def layer_init(layer: nn.Linear | nn.Conv2d, std: float = math.sqrt(2), bias: float = 0.0):
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


class RawExtractor(nn.Module):
    """Stacked images through a small CNN (SB3's NatureCNN needs 36 px or more; Simple Shapes has 32),
    concatenated with the stacked attribute vectors (SB3's CombinedExtractor flattens vectors)."""

    def __init__(self, channels: int, side: int, attr_dim: int):
        super().__init__()
        convs, cin, size = [], channels, side
        for cout in (32, 64, 64, 64)[: int(np.log2(side)) - 2]:  # down to 4x4
            convs += [layer_init(nn.Conv2d(cin, cout, 3, 2, 1)), nn.ReLU()]
            cin, size = cout, size // 2
        self.cnn = nn.Sequential(
            *convs, nn.Flatten(), layer_init(nn.Linear(cin * size * size, 256)), nn.ReLU()
        )
        self.out_dim = 256 + attr_dim

    def forward(self, x: dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.cat([self.cnn(x["image"].float() / 255.0), x["attr"]], -1)


def tanh_mlp(cin: int, h: int) -> list[nn.Module]:
    """Two tanh layers of h units, orthogonally initialised (the hidden part of each PPO head)."""
    return [layer_init(nn.Linear(cin, h)), nn.Tanh(), layer_init(nn.Linear(h, h)), nn.Tanh()]


class Agent(nn.Module):
    def __init__(self, observer: Observer, args: Args, n_actions: int, discrete: bool):
        super().__init__()
        k = args.frame_stack
        if observer.variant == "raw":
            self.extract = RawExtractor(3 * k, observer.image_shape[1], observer.attr_dim * k)
            feat = self.extract.out_dim
        else:
            self.extract = nn.Identity()
            feat = observer.feat_dim * k
        h = args.hidden
        self.actor = nn.Sequential(*tanh_mlp(feat, h), layer_init(nn.Linear(h, n_actions), std=0.01))
        self.critic = nn.Sequential(*tanh_mlp(feat, h), layer_init(nn.Linear(h, 1), std=1.0))
        self.discrete = discrete
        if not discrete:  # state-independent log std (CleanRL's continuous PPO)
            self.actor_logstd = nn.Parameter(torch.zeros(1, n_actions))

    def features(self, x: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.extract(x) if isinstance(self.extract, RawExtractor) else x["x"]

    def get_value(self, x: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.critic(self.features(x)).squeeze(-1)

    def get_action_and_value(self, x: dict[str, torch.Tensor], action: torch.Tensor | None = None):
        f = self.features(x)
        out = self.actor(f)
        if self.discrete:
            dist = torch.distributions.Categorical(logits=out)
        else:
            dist = torch.distributions.Normal(out, self.actor_logstd.expand_as(out).exp())
        if action is None:
            action = dist.sample()
        logp, ent = dist.log_prob(action), dist.entropy()
        if not self.discrete:
            logp, ent = logp.sum(-1), ent.sum(-1)
        return action, logp, ent, self.critic(f).squeeze(-1)

    def act_greedy(self, x: dict[str, torch.Tensor]) -> torch.Tensor:
        out = self.actor(self.features(x))
        return out.argmax(-1) if self.discrete else out


def count_flops(fn):
    """``fn()`` and the forward + backward FLOPs it took (torch.utils.flop_counter)."""
    with FlopCounterMode(display=False) as counter:
        out = fn()
    return out, counter.get_total_flops()


def ppo_loss(agent: Agent, mb: dict, args: Args):
    """CleanRL's PPO loss on one minibatch: clipped surrogate, clipped value loss, entropy bonus."""
    _, newlogp, entropy, newvalue = agent.get_action_and_value(mb["obs"], mb["actions"])
    logratio = newlogp - mb["logprobs"]
    ratio = logratio.exp()
    with torch.no_grad():
        approx_kl = ((ratio - 1) - logratio).mean()
        clipfrac = ((ratio - 1.0).abs() > args.clip_coef).float().mean()
    adv = mb["advantages"]
    if args.norm_adv:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
    if args.clip_vloss:
        v_clipped = mb["values"] + (newvalue - mb["values"]).clamp(-args.clip_coef, args.clip_coef)
        v_loss = 0.5 * torch.max((newvalue - mb["returns"]) ** 2, (v_clipped - mb["returns"]) ** 2).mean()
    else:
        v_loss = 0.5 * ((newvalue - mb["returns"]) ** 2).mean()
    ent = entropy.mean()
    loss = pg_loss - args.ent_coef * ent + args.vf_coef * v_loss
    terms = {"policy_loss": pg_loss, "value_loss": v_loss, "entropy": ent}
    return loss, terms | {"approx_kl": approx_kl, "clipfrac": clipfrac}


class RewardNormalizer:
    """r / sqrt(Var[G] + eps), G the running discounted return of each environment, Var a running
    variance over all of them (no mean subtraction, clipped to +-10, as VecNormalize)."""

    def __init__(self, num_envs: int, gamma: float, enabled: bool):
        self.gamma, self.enabled = gamma, enabled
        self.ret = np.zeros(num_envs)
        self.count, self.mean, self.var = 1e-4, 0.0, 1.0

    def __call__(self, r: np.ndarray, done: np.ndarray) -> np.ndarray:
        if not self.enabled:
            return r
        self.ret = self.ret * self.gamma + r
        b_mean, b_var, b_n = self.ret.mean(), self.ret.var(), len(self.ret)
        delta, total = b_mean - self.mean, self.count + b_n  # parallel mean/variance update (Chan et al.)
        self.var = (self.var * self.count + b_var * b_n + delta**2 * self.count * b_n / total) / total
        self.mean, self.count = self.mean + delta * b_n / total, total
        self.ret[done] = 0.0
        return np.clip(r / np.sqrt(self.var + 1e-8), -10.0, 10.0)

    def state_dict(self) -> dict:
        return {"ret": self.ret, "count": self.count, "mean": self.mean, "var": self.var}

    def load_state_dict(self, s: dict) -> None:
        self.ret, self.count, self.mean, self.var = s["ret"], s["count"], s["mean"], s["var"]


def gae(rewards, values, next_value, terminated, args: Args) -> torch.Tensor:
    """Generalised advantage estimation over a rollout (T, N). ``terminated[t]`` cuts the bootstrap
    after step t; time-limit truncations were already folded into the rewards (see the rollout)."""
    adv = torch.zeros_like(rewards)
    last = torch.zeros_like(next_value)
    for t in reversed(range(len(rewards))):
        nxt = next_value if t == len(rewards) - 1 else values[t + 1]
        nonterminal = 1.0 - terminated[t]
        delta = rewards[t] + args.gamma * nxt * nonterminal - values[t]
        last = delta + args.gamma * args.gae_lambda * nonterminal * last
        adv[t] = last
    return adv


def ppo_update(agent: Agent, optimizer, mb: dict, args: Args, env_step: int) -> dict:
    """One Adam step on the PPO loss of a minibatch (gradient norm clipped)."""
    loss, terms = ppo_loss(agent, mb, args)
    if not torch.isfinite(loss):
        raise FloatingPointError(f"non-finite PPO loss at env step {env_step:,}")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
    optimizer.step()
    return terms


# --------------------------------------------------------------------------------------------------
# CleanRL's PPO loop
# --------------------------------------------------------------------------------------------------
def main(args: Args) -> dict:
    args = args.resolve()
    check_settings(args)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    dev = torch.device(args.device)
    observer, frozen = load_observer(args)
    observer = observer.to(dev)
    discrete = args.env == "simple_shapes"
    n_actions = 7 if discrete else 5
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    agent = Agent(observer, args, n_actions, discrete).to(dev)
    default = Path(args.checkpoint_dir) / args.env / "agents" / f"{run_name(args)}.pt"
    agent_path = Path(args.checkpoint) if args.checkpoint else default
    if args.eval_only:
        return evaluate_checkpoint(agent, observer, args, agent_path, frozen["fingerprint"])
    batch_size = args.num_envs * args.num_steps  # agent steps per rollout
    repeat = ACTION_REPEAT[args.env]  # env steps (the paper's unit, frames on RoboDesk) per agent step
    num_iterations = -(-args.total_steps // (batch_size * repeat))  # whole rollouts, at least total_steps
    if (steps := num_iterations * batch_size * repeat) != args.total_steps:
        print(
            f"--total-steps {args.total_steps:,} is no whole number of rollouts ({batch_size * repeat:,} env "
            f"steps each): training {num_iterations:,} rollouts, {steps:,} steps"
        )
    run = start_run(args, observer, agent, frozen, agent_path, num_iterations)
    state, optimizer = run.state, run.optimizer

    # Rollout storage (T, N, ...); observations keep the stacked frames the policy saw.
    envs_ = vector_envs(args, args.num_envs)
    obs, _ = envs_.reset(seed=args.seed + state.env_steps)
    stack = FrameStack(args.frame_stack)
    x = stack.reset(observer(obs, "none", dev))
    store = {k: torch.zeros((args.num_steps, *v.shape), dtype=v.dtype, device=dev) for k, v in x.items()}
    act_shape = () if discrete else (n_actions,)
    act_dtype = torch.long if discrete else torch.float32
    actions = torch.zeros((args.num_steps, args.num_envs, *act_shape), dtype=act_dtype, device=dev)
    logprobs, rewards, values, terms = (
        torch.zeros((args.num_steps, args.num_envs), device=dev) for _ in range(4)
    )
    ep_ret, ep_succ = np.zeros(args.num_envs), np.zeros(args.num_envs)
    stop = StopRequest(TAG)  # Ctrl-C: the rollout finishes, then the run saves (before its update) and exits
    while state.iteration < num_iterations or run.pending:
        if run.pending:  # --resume of a run saved between a rollout and its update: that update first
            flat, run.pending = to_device(run.pending, dev), None
            update(run, flat, stop, num_iterations * batch_size * repeat)
            continue
        if args.stop_at_criterion and state.criterion_step is not None:
            break
        state.iteration += 1
        if args.anneal_lr:
            frac = 1.0 - (state.iteration - 1.0) / num_iterations
            optimizer.param_groups[0]["lr"] = frac * args.learning_rate
        # Rollout: num_steps steps of every environment with the current policy.
        for t in range(args.num_steps):
            for k in store:
                store[k][t] = x[k]
            with torch.no_grad():
                action, logp, _, value = agent.get_action_and_value(x)
            actions[t], logprobs[t], values[t] = action, logp, value
            obs, r, term, trunc, info = envs_.step(env_action(action, discrete))
            state.env_steps += args.num_envs * repeat
            ep_ret += r
            ep_succ += step_success(info, args.num_envs)
            r = torch.as_tensor(run.reward_norm(r, term | trunc), dtype=torch.float32, device=dev)
            frame = observer(obs, "none", dev)
            x = stack.push(frame)
            ends = np.flatnonzero(term | trunc)
            if len(ends):
                bootstrap_truncations(run, r, info, term, trunc, {k: v[t] for k, v in store.items()})
                x = stack.reset(frame, ends)
                for i in ends:
                    log_episode(run, float(ep_ret[i]), float(ep_succ[i]))
                ep_ret[ends], ep_succ[ends] = 0.0, 0.0
            rewards[t] = r
            terms[t] = torch.as_tensor(term | trunc, dtype=torch.float32, device=dev)

        # Advantages (GAE); the rollout is saved when the update would end too late after the last save
        # (update_ends_late) or when Ctrl-C asks to stop; then update_epochs passes over it (update).
        with torch.no_grad():
            advantages = gae(rewards, values, agent.get_value(x), terms, args)
            returns = advantages + values
        flat = {
            "obs": {k: v.reshape(batch_size, *v.shape[2:]) for k, v in store.items()},
            "actions": actions.reshape(batch_size, *act_shape),
            "logprobs": logprobs.reshape(-1),
            "advantages": advantages.reshape(-1),
            "returns": returns.reshape(-1),
            "values": values.reshape(-1),
        }
        if stop.requested or update_ends_late(run):  # the rollout is kept, so the update can be redone
            run.pending = flat
            if not stop.requested:
                save(run)
                run.pending = None
        if run.pending is None:
            update(run, flat, stop, num_iterations * batch_size * repeat)
        if stop.requested:  # saved below with the update done, or with the rollout pending
            envs_.close()
            stop.restore()
            interrupted(run)
    stop.restore()
    envs_.close()
    return finish(run)


def update(run: Run, flat: dict, stop: StopRequest, total: int) -> None:
    """update_epochs passes of minibatch updates over one rollout (``flat``), its log line and its save
    (``total``: the run's env steps, for the log line)."""
    args, agent, optimizer, state = run.args, run.agent, run.optimizer, run.state
    t0, batch_size = time.time(), len(flat["returns"])
    for _ in range(args.update_epochs):
        perm = torch.randperm(batch_size, device=flat["returns"].device)
        for start in range(0, batch_size - args.minibatch_size + 1, args.minibatch_size):
            idx = perm[start : start + args.minibatch_size]
            mb = {
                k: ({kk: vv[idx] for kk, vv in v.items()} if k == "obs" else v[idx]) for k, v in flat.items()
            }
            try:
                if state.flops_per_minibatch == 0:  # same shapes every minibatch: count the first one
                    stats, state.flops_per_minibatch = count_flops(
                        lambda mb=mb: ppo_update(agent, optimizer, mb, args, state.env_steps)
                    )
                else:
                    stats = ppo_update(agent, optimizer, mb, args, state.env_steps)
            except FloatingPointError as err:
                raise FloatingPointError(f"{err}; {last_good(run.agent_path)}") from err
            state.flops += state.flops_per_minibatch
        if args.target_kl is not None and stats["approx_kl"] > args.target_kl:
            break
    state.update_seconds = time.time() - t0
    log_iteration(run, stats, flat, total)
    if state.iteration % args.save_every == 0 and not stop.requested:
        save(run)


def update_ends_late(run: Run) -> bool:
    """Whether the update about to start, as long as the last one, would end more than --save-minutes
    after the last save: then the rollout is saved before it. A run stopped without warning then loses at
    most one rollout's acting or one update, not both."""
    due = 60 * run.args.save_minutes
    return time.time() - run.last_save + run.state.update_seconds > due


def to_device(tree, dev):
    """The tensors of a nested dict on ``dev``."""
    if isinstance(tree, dict):
        return {k: to_device(v, dev) for k, v in tree.items()}
    return tree.to(dev)


# Simulator frames per agent step. The paper counts RoboDesk "environment steps" in frames ("2,000
# environment steps but with an action repetition of 4 steps, leading to 500 chosen actions"), so step
# counts (--total-steps, criteria, logs) are frames there; Simple Shapes has no action repeat.
ACTION_REPEAT = {"simple_shapes": 1, "robodesk": 4}


class FrameStack:
    """The last ``k`` frames of each environment, concatenated along the feature/channel axis; an
    environment that starts an episode is refilled with k copies of its first frame."""

    def __init__(self, k: int):
        self.k, self.frames = k, None

    def reset(self, frame: dict[str, torch.Tensor], idx: np.ndarray | None = None) -> dict[str, torch.Tensor]:
        if self.frames is None or idx is None:
            self.frames = {key: torch.cat([v] * self.k, 1) for key, v in frame.items()}
        else:
            for key, v in frame.items():
                self.frames[key][idx] = torch.cat([v[idx]] * self.k, 1)
        return {key: v.clone() for key, v in self.frames.items()}

    def push(self, frame: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        self.frames = {key: self.shifted(key, v) for key, v in frame.items()}
        return {key: v.clone() for key, v in self.frames.items()}

    def shifted(self, key: str, v: torch.Tensor) -> torch.Tensor:
        """The stack of ``key`` with ``v`` appended as the newest frame (oldest dropped)."""
        width = v.shape[1]
        return torch.cat([self.frames[key][:, width:], v], 1)


# --------------------------------------------------------------------------------------------------
# Environments, evaluation, checkpoints
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


def vector_envs(args: Args, num_envs: int):
    """The envs of the rollouts and evaluations: make_envs's, or with --env-processes (RoboDesk) each in a
    spawned process of its own (envs.robodesk.make_vector_env), which steps the same episodes."""
    if args.env != "robodesk" or not args.env_processes:
        return make_envs(args, num_envs)
    from envs.robodesk import TASKS, make_vector_env

    if args.task not in TASKS:
        raise UsageError(f"unknown RoboDesk task {args.task!r}; valid tasks: {', '.join(TASKS)}")
    return make_vector_env(
        num_envs,
        True,
        task=args.task,
        render_quality=args.render_quality,
        action_repeat=ACTION_REPEAT["robodesk"],
        episode_length=args.episode_length,
    )


def final_observations(info: dict, ends: np.ndarray) -> dict[str, np.ndarray]:
    """Last observations of the episodes that ended: a dict of arrays (batched Simple Shapes env) or an
    array of per-env dicts (gymnasium's vector envs, in this process or in one process each)."""
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


def env_action(action: torch.Tensor, discrete: bool) -> np.ndarray:
    a = action.cpu().numpy()
    return a if discrete else np.clip(a, -1.0, 1.0).astype(np.float32)


@torch.no_grad()
def run_episodes(agent: Agent, observer: Observer, args: Args, n: int, drop: str, seed: int):
    """n episodes with the greedy action (arg-max / Gaussian mean) and ``drop`` applied: per-episode
    returns and success counts."""
    dev = next(agent.parameters()).device
    envs_ = vector_envs(args, n)
    obs, _ = envs_.reset(seed=seed)
    stack = FrameStack(args.frame_stack)
    x = stack.reset(observer(obs, drop, dev))
    returns, successes, alive = np.zeros(n), np.zeros(n), np.ones(n, bool)
    while alive.any():
        obs, r, term, trunc, info = envs_.step(env_action(agent.act_greedy(x), agent.discrete))
        returns += r * alive
        successes += step_success(info, n) * alive
        alive &= ~(term | trunc)
        x = stack.push(observer(obs, drop, dev))
    envs_.close()
    return returns, successes


FUSION = {"none": (0.5, 0.5), "vision": (0.0, 1.0), "attr": (1.0, 0.0)}  # (alpha_v, alpha_attr)


# --------------------------------------------------------------------------------------------------
# Frozen representations: the VAEs and the GW of pretrain_vae_gw.py (same layers, so the same weights load)
# --------------------------------------------------------------------------------------------------
def conv_block(cin: int, cout: int, transpose: bool = False, stride: int = 2) -> nn.Sequential:
    conv = (nn.ConvTranspose2d if transpose else nn.Conv2d)(
        cin, cout, 4 if stride == 2 else 3, stride, 1, bias=False
    )
    return nn.Sequential(conv, nn.BatchNorm2d(cout), nn.ReLU())


class VisualVAE(nn.Module):
    """Appendix Tables VAE_v: conv encoder to the mean/log-variance of u_v (the decoder is kept so the
    checkpoint loads; PPO only encodes)."""

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
    """Encoders e_v, e_attr and decoders d_v, d_attr (appendix Tables GW_SS / GW_Rob)."""

    def __init__(self, latent: int, z: int, hidden: int):
        super().__init__()
        self.e = nn.ModuleDict({"v": mlp(latent, hidden, z, 4), "attr": mlp(latent, hidden, z, 4)})
        self.d = nn.ModuleDict({"v": mlp(z, hidden, latent, 4), "attr": mlp(z, hidden, latent, 4)})

    def fuse(self, u_v, u_attr, alpha_v: float, alpha_attr: float) -> torch.Tensor:
        """z = tanh(alpha_v e_v(u_v) + alpha_attr e_attr(u_attr)) (eq. of Figure 1)."""
        return torch.tanh(alpha_v * self.e["v"](u_v) + alpha_attr * self.e["attr"](u_attr))


class Observer(nn.Module):
    """Observation dict -> the variant's policy input for one frame, with a modality optionally removed.

    raw: {"image": uint8 (n, 3, H, W), "attr": (n, A)}; vae: {"x": [u_v, u_attr]};
    clip / gw: {"x": z} with (alpha_v, alpha_attr) = (0.5, 0.5), or (1, 0) / (0, 1) without a modality."""

    def __init__(self, env: str, variant: str, vae: dict | None, gw: dict | None):
        super().__init__()
        s = ENV_SPECS[env]
        self.variant = variant
        self.image_shape = (3, s["image"], s["image"])
        self.attr_dim = s["attr"]
        self.feat_dim = {"raw": 0, "vae": 2 * s["latent"], "clip": s["z"], "gw": s["z"]}[variant]
        if variant == "raw":
            return
        self.vae_v = VisualVAE(s["image"], s["latent"], vae["config"]["vae_width"])
        depth, hidden = (2, 64) if env == "simple_shapes" else (4, 512)
        self.vae_attr = AttrVAE(s["attr"], s["latent"], hidden, depth)
        self.vae_v.load_state_dict(vae["vae_v"])
        self.vae_attr.load_state_dict(vae["vae_attr"])
        self.register_buffer("attr_mean", torch.as_tensor(vae["attr_mean"], dtype=torch.float32))
        self.register_buffer("attr_std", torch.as_tensor(vae["attr_std"], dtype=torch.float32))
        if variant in ("clip", "gw"):
            self.gw = GlobalWorkspace(s["latent"], s["z"], s["gw_hidden"])
            self.gw.load_state_dict(gw["gw"])
        self.eval().requires_grad_(False)

    @torch.no_grad()
    def forward(self, obs: dict[str, np.ndarray], drop: str, dev) -> dict[str, torch.Tensor]:
        image = torch.as_tensor(obs["image"], device=dev).permute(0, 3, 1, 2)
        attr = torch.as_tensor(obs["attr"], device=dev, dtype=torch.float32)
        if self.variant == "raw":  # uint8 images keep the rollout small; zeros for a removed modality
            return {
                "image": image * 0 if drop == "vision" else image,
                "attr": attr * 0 if drop == "attr" else attr,
            }
        u_v = self.vae_v.encode_mean(image.float() / 255.0)
        u_attr = self.vae_attr.encode_mean((attr - self.attr_mean) / self.attr_std)
        if self.variant == "vae":
            u_v = u_v * 0 if drop == "vision" else u_v
            u_attr = u_attr * 0 if drop == "attr" else u_attr
            return {"x": torch.cat([u_v, u_attr], -1)}
        alpha_v, alpha_attr = FUSION[drop]
        return {"x": self.gw.fuse(u_v * (alpha_v > 0), u_attr * (alpha_attr > 0), alpha_v, alpha_attr)}


def load_observer(args: Args) -> tuple[Observer, dict]:
    """The frozen part of the variant, and the paths/fingerprint that tie an agent checkpoint to it."""
    if args.variant == "raw":
        return Observer(args.env, "raw", None, None), {"fingerprint": 0.0, "paths": []}
    wanted = {"vae.pt": args.vae_checkpoint}
    if args.variant in ("clip", "gw"):
        wanted[f"{args.variant}.pt"] = args.gw_checkpoint
    pre = pretrained_paths(args.checkpoint_dir, args.env, wanted)
    vae_path = pre["vae.pt"]
    stages = "collect vae" if args.variant == "vae" else "collect vae gw"
    extra = " --loss-preset clip" if args.variant == "clip" else ""
    vae = load_pretrained(vae_path, "vae", args.env, stages, args.checkpoint_dir, extra)
    made_on = vae.get("args", {}).get("render_quality", "faithful")  # the images the VAE was trained on
    if args.render_quality is None:
        args.render_quality = made_on
    elif args.env == "robodesk" and args.render_quality != made_on:
        raise UsageError(
            f"--render-quality {args.render_quality}: the VAE in {vae_path} was trained on {made_on} images, "
            "and its encoders have never seen the other kind; leave the flag out, or pre-train a VAE on "
            f"{args.render_quality} images"
        )
    gw, paths = None, [str(vae_path)]
    if args.variant in ("clip", "gw"):
        gw_path = pre[f"{args.variant}.pt"]
        gw = load_pretrained(gw_path, "gw", args.env, "gw", args.checkpoint_dir, extra)
        if gw.get("preset") != args.variant:
            raise UsageError(
                f"{gw_path} is a {gw.get('preset')!r} model but --variant is {args.variant!r}; make one with "
                f"`{pretrain_command(args.env, args.checkpoint_dir, 'gw', f' --loss-preset {args.variant}')}`"
            )
        check_gw_vae_pair(vae, gw, vae_path, gw_path, args.checkpoint_dir)
        paths.append(str(gw_path))
    try:
        obs = Observer(args.env, args.variant, vae, gw)
    except RuntimeError as err:  # a state dict of other sizes
        raise UsageError(f"{', '.join(paths)} do not fit the {args.env} networks: {err}") from err
    return obs, {"fingerprint": float(sum(p.double().sum() for p in obs.parameters())), "paths": paths}


def vae_digest(vae: dict) -> str:
    """Identity of a VAE checkpoint's weights: SHA-256 of its tensors with floating ones rounded to
    float16, the precision of the bundled copies, so that a bundled VAE keeps the digest of its source."""
    h = hashlib.sha256()
    for part in ("vae_v", "vae_attr"):
        for key, t in sorted(vae[part].items()):
            t = t.detach().cpu()
            h.update(key.encode() + (t.half() if torch.is_floating_point(t) else t).numpy().tobytes())
    return h.hexdigest()[:16]


def check_gw_vae_pair(vae: dict, gw: dict, vae_path: Path, gw_path: Path, checkpoint_dir: str) -> None:
    """A GW reads the latents of the VAE it was trained on (pretrain_vae_gw.py records that VAE's digest);
    with any other VAE its z means nothing, so a mismatch stops the run."""
    if gw.get("vae_digest", vae_digest(vae)) != vae_digest(vae):
        made = gw.get("args", {})  # the GW's own flags: its scale and the data it read
        extra = " --cpu-preset" if made.get("cpu_preset") else ""
        extra += f" --data-dir {made['data_dir']}" if made.get("data_dir", "data") != "data" else ""
        extra += f" --loss-preset {gw.get('preset', 'gw')} --overwrite"
        extra += "" if checkpoint_dir == "checkpoints" else f" --checkpoint-dir {checkpoint_dir}"
        remake = f"python pretrain_vae_gw.py --env {gw['env']} --stages gw{extra}"
        raise UsageError(
            f"{gw_path} was trained on the latents of another VAE than {vae_path} (the VAE was remade "
            f"after it): retrain the GW on this VAE with `{remake}`"
        )


# Settings that may differ between the parts of one run (how long it runs, how it reports, where its files
# are); every other setting defines the run, and --resume refuses a change to any of them.
MAY_CHANGE = set(
    "total_steps stop_at_criterion eval_episodes save_every save_minutes device torch_threads env_processes"
    " resume overwrite checkpoint checkpoint_dir vae_checkpoint gw_checkpoint exp_name eval_only drop".split()
)


# Settings an evaluation must share with the agent it loads (they shape its networks or inputs).
EVAL_KEYS = ("task", "variant", "frame_stack", "hidden", "render_quality")


# What the run infrastructure below the fence reads of this script.
SCRIPT = {
    "kind": "ppo",  # the kind recorded in its agent checkpoints
    "train": "python ppo_variants.py --env {env} --variant {variant}",  # the command that trains one
    "fingerprint": "fingerprint",  # the checkpoint entry that identifies the frozen weights
    "eval_keys": lambda args: EVAL_KEYS,
}


def checkpoint_entries(run: Run) -> dict:
    """What an agent checkpoint of this script holds besides its kind, env, task, settings, counters and
    random states."""
    return {
        "variant": run.args.variant,
        "fingerprint": run.pretrained["fingerprint"],
        "frozen_paths": run.pretrained["paths"],
        "agent": run.agent.state_dict(),
        "optimizer": run.optimizer.state_dict(),
        "reward_norm": run.reward_norm.state_dict(),
        "pending": run.pending,  # a rollout saved before its update (update_ends_late), else None
    }


# Ranges of this script's flags (check_settings, below the fence, adds the flags every agent has).
RANGES = {
    ">= 1": "num_steps update_epochs minibatch_size frame_stack hidden",
    ">= 0": "ent_coef vf_coef",
    "> 0": "learning_rate clip_coef max_grad_norm save_minutes",
    "[0, 1]": "gae_lambda",
}


def script_checks(args: Args) -> None:
    """A minibatch fits in one rollout."""
    rollout = args.num_envs * args.num_steps
    rule = f"must fit in one rollout of --num-envs x --num-steps = {rollout:,} steps"
    require(args.minibatch_size <= rollout, "minibatch_size", args.minibatch_size, rule)


# --------------------------------------------------------------------------------------------------
# The run: what the training loop carries, and the bookkeeping around CleanRL's PPO loop
# --------------------------------------------------------------------------------------------------
@dataclass
class LoopState:
    """Counters of the training loop (saved in the agent checkpoint, restored by --resume)."""

    iteration: int = 0  # rollouts collected (and trained on) so far
    env_steps: int = 0  # in the paper's unit (RoboDesk: simulator frames)
    flops: int = 0  # forward + backward FLOPs of every minibatch update so far
    flops_per_minibatch: int = 0  # counted on the first minibatch; every one has the same shapes
    episodes: int = 0
    criterion_step: int | None = None
    recent: list = field(default_factory=list)  # the last --smoothing normalised training returns
    update_seconds: float = 0.0  # wall time of the last update (update_ends_late)


@dataclass
class Run:
    """One training run: its settings, networks, counters and outputs."""

    args: Args
    frozen: Observer  # the variant's frozen VAEs / GW (nothing for raw observations)
    agent: Agent
    optimizer: torch.optim.Optimizer
    reward_norm: RewardNormalizer
    state: LoopState
    writer: SummaryWriter
    agent_path: Path
    pretrained: dict  # {"fingerprint": float, "paths": [...]} of the frozen weights
    ref: tuple | None  # Simple Shapes returns of the random and the greedy policy (normalisation)
    pending: dict | None = None  # a rollout saved before its update, which --resume runs first
    t0: float = field(default_factory=time.time)
    last_save: float = field(default_factory=time.time)
    steps0: int = 0

    def normalise(self, ret: float) -> float:
        return (ret - self.ref[0]) / (self.ref[1] - self.ref[0]) if self.ref else float("nan")


def run_name(args: Args) -> str:
    task = "" if args.env == "simple_shapes" else f"_{args.task}"
    return f"{args.exp_name}_{args.variant}_{args.env}{task}_s{args.seed}"


def start_run(
    args: Args, observer: Observer, agent: Agent, frozen: dict, agent_path: Path, iterations: int
) -> Run:
    """Claim the outputs, build the optimizer, resume when asked, and print what runs."""
    runs_dir = Path("runs") / run_name(args)
    # Nothing of an earlier run is overwritten by accident, and the output folders take files now.
    claim_outputs([agent_path, runs_dir], args.resume, args.overwrite, "ppo")
    ensure_writable(agent_path.parent)
    ensure_writable(runs_dir)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)
    state, reward_norm = LoopState(), RewardNormalizer(args.num_envs, args.gamma, args.norm_reward)
    pending = None
    if args.resume:
        ck = load_agent_checkpoint(agent_path, args, frozen["fingerprint"])
        agent.load_state_dict(ck["agent"])
        optimizer.load_state_dict(ck["optimizer"])
        state = LoopState(**ck["state"])
        reward_norm.load_state_dict(ck["reward_norm"])
        torch.set_rng_state(ck["torch_rng"])
        np.random.set_state(ck["np_rng"])
        pending = ck.get("pending")
        first = "; first the update of the rollout saved before it" if pending else ""
        print(f"[{TAG}] resuming {agent_path} at env step {state.env_steps:,}{first}")
    writer = SummaryWriter(str(runs_dir))
    if not args.resume:
        table = "\n".join(f"|{k}|{v}|" for k, v in vars(args).items())
        writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + table)
    # each part of a run logs its length, which --resume may change (benchmarks/paper_figures.py reads it)
    writer.add_scalar("charts/total_steps", args.total_steps, state.env_steps)
    ref = reference_returns(args)
    run = Run(args, observer, agent, optimizer, reward_norm, state, writer, agent_path, frozen, ref, pending)
    run.steps0 = state.env_steps
    n_params = sum(p.numel() for p in agent.parameters())
    task = "" if args.env == "simple_shapes" else f"_{args.task}"
    rollout = args.num_envs * args.num_steps
    print(
        f"[{TAG}] {args.variant} PPO on {args.env}{task}: {n_params:,} trainable parameters, "
        f"{iterations} rollouts of {rollout:,} steps"
    )
    print(f"[{TAG}] {describe_reference(ref, args)}")
    return run


def bootstrap_truncations(run: Run, r, info, term, trunc, before: dict) -> None:
    """A time-limit truncation is not an end of the task: add to its reward the discounted value of its
    final observation (stable-baselines3 does the same). ``before``: the stacks this step acted on."""
    cut = np.flatnonzero(trunc & ~term)
    if not len(cut):
        return
    dev = r.device
    final = run.frozen(final_observations(info, cut), "none", dev)
    x_final = {}
    for k, v in final.items():  # the stack before this step's push, plus the final frame
        x_final[k] = torch.cat([before[k][cut][:, v.shape[1] :], v], 1)
    with torch.no_grad():
        r[cut] += run.args.gamma * run.agent.get_value(x_final)


def log_iteration(run: Run, stats: dict, flat: dict, total: int) -> None:
    """The scalars and the progress line of one rollout and its update."""
    s, w, step = run.state, run.writer, run.state.env_steps
    var_y = flat["returns"].var()
    explained = float("nan") if var_y == 0 else (1 - (flat["returns"] - flat["values"]).var() / var_y).item()
    sps = (step - run.steps0) / max(time.time() - run.t0, 1e-9)
    for k, v in stats.items():
        w.add_scalar(f"losses/{k}", v.item(), step)
    w.add_scalar("losses/explained_variance", explained, step)
    w.add_scalar("charts/learning_rate", run.optimizer.param_groups[0]["lr"], step)
    if step > run.steps0:  # not after the update of a rollout saved before it (--resume): no steps yet
        w.add_scalar("charts/SPS", sps, step)
    w.add_scalar("charts/train_flops", s.flops, step)
    smooth = np.mean(s.recent) if s.recent else float("nan")
    rate = f"{sps:.0f} steps/s" if step > run.steps0 else "the saved rollout's update"
    print(
        f"[{TAG}] step {step:,}/{total:,} {rate} | value loss {stats['value_loss'].item():.3f} "
        f"entropy {stats['entropy'].item():.3f} smoothed normalised return {smooth:.3f}",
        flush=True,
    )


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
