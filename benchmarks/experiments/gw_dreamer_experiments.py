"""GW-Dreamer with settings that are not the paper's model: the suspects screened for the reliability of
the default (docs/experiments.md; the RoboDesk world-model ones in docs/gw_dreamer.md) and one control.
Each flag changes one thing of gw_dreamer.py, which this script imports and runs; every other flag, the
checkpoints and the logs are gw_dreamer.py's.

    python benchmarks/experiments/gw_dreamer_experiments.py --env simple_shapes --ac-input hz
    python benchmarks/experiments/gw_dreamer_experiments.py --heads-read-sg-z --seed 8
    python benchmarks/experiments/gw_dreamer_experiments.py --z-source attributes   # the control
    python benchmarks/experiments/gw_dreamer_experiments.py --ac-input hz --eval-only --checkpoint PATH
    python benchmarks/experiments/gw_dreamer_experiments.py --env robodesk --cpu-preset --wm-open-loop 10
    python benchmarks/experiments/gw_dreamer_experiments.py --env robodesk --cpu-preset --wm-residual

Runs are named like gw_dreamer.py's with one suffix per experiment (``_hz``, ``_sgz``, ``_zinit``,
``_attrz``, ``_noslope``, ``_ol10``, ``_rec0.5``, ``_res``, ``_nodone``, ``_noise0.3``,
``_noise0.3d150000``), so
they never mix with the paper's runs.
"""

from __future__ import annotations

import copy
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn as nn

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import gw_dreamer as G  # noqa: E402


@dataclass
class Args(G.Args):
    ac_input: Literal["h", "hz"] = "h"
    """what the actor and critic read. h: the GRU state h_t (the paper). hz: [h_t, z_t], the real z_t when
    acting and the world model's z in dreams (DreamerV3's and World Models' controller input)"""
    heads_read_sg_z: bool = False
    """the reward and done heads read sg(z_{t+1}), so their losses do not train the z head"""
    value_slope: bool = True
    """--no-value-slope: the critic reads the dreamt states as constants, so under dynamics backpropagation
    the actor's gradient comes from the dreamt rewards alone (the lambda-return's values carry no derivative
    with respect to the dream); the critic still learns as before"""
    zero_init: bool = False
    """the reward head's and the critic's output layers start at zero (DreamerV3)"""
    recent_fraction: float = 0.0
    """a share of each batch's sequences that start among the newest --recent-window stored steps of their
    stream (the rest uniform, as the paper's replay): the world model sees the policy's newest states more
    often than the older ones it has replayed hundreds of times"""
    recent_window: int = 5000
    """stored steps per stream that count as recent for --recent-fraction"""
    wm_residual: bool = False
    """the z head predicts a change: z_{t+1} = tanh(atanh(z_t) + head(h_{t+1})) instead of the paper's
    tanh(head(h_{t+1})), so a world model that knows nothing of an action predicts that nothing moves
    (same parameters)"""
    explore_noise_decay: int = 0
    """N > 0: gw_dreamer.py's --explore-noise falls linearly from its value at the first frame to 0 at
    frame N (0: constant), so the training episodes that decide the criterion late in a run are the
    policy's own"""
    z_source: Literal["gw", "attributes"] = "gw"
    """gw: the paper's z_t. attributes (Simple Shapes only): z_t is the true attribute vector (its first
    10 entries, clipped to [-1, 1]) instead of the GW's, which tests the world model and actor-critic
    alone"""


def suffix(args: Args) -> str:
    return (
        ("_attrz" if args.z_source == "attributes" else "")
        + ("_hz" if args.ac_input == "hz" else "")
        + ("_sgz" if args.heads_read_sg_z else "")
        + ("_zinit" if args.zero_init else "")
        + ("" if args.value_slope else "_noslope")
        + (f"_ol{args.wm_open_loop}" if args.wm_open_loop else "")
        + (f"_rec{args.recent_fraction:g}" if args.recent_fraction else "")
        + ("_res" if args.wm_residual else "")
        + ("_nodone" if args.done_head == "off" else "")
        + (f"_noise{args.explore_noise:g}" if args.explore_noise else "")
        + (f"d{args.explore_noise_decay}" if args.explore_noise and args.explore_noise_decay else "")
    )


class RecentReplay(G.Replay):
    """gw_dreamer.Replay whose batches draw --recent-fraction of their sequences from the newest
    --recent-window stored steps of their stream."""

    fraction, window = 0.0, 5000

    def sample(self, batch: int, length: int) -> dict[str, np.ndarray]:
        n_recent = int(round(self.fraction * batch))
        out = super().sample(batch, length)
        if n_recent == 0:
            return out
        envs_ = self.rng.integers(0, self.n, n_recent)
        filled = np.minimum(self.count[envs_], self.cap)
        window = np.minimum(filled, max(self.window, length + 1))
        newest = (self.pos[envs_] - 1) % self.cap  # the last written entry
        back = (self.rng.random(n_recent) * (window - length)).astype(
            np.int64
        )  # distance of the window's end
        start = newest - length - back
        idx = (start[:, None] + np.arange(length + 1)[None]) % self.cap
        rows = envs_[:, None]
        for k in out:
            out[k][:n_recent] = getattr(self, k)[rows, idx]
        return out


def experiment_agent(args: Args) -> type[G.Agent]:
    """gw_dreamer.Agent with this run's experiments built in."""

    class SgZWorldModel(G.WorldModel):
        def heads(self, h_next):
            z_next = self.z_head(h_next)
            feat = torch.cat([h_next, z_next.detach()], -1)
            return z_next, self.reward_head(feat), self.done_logit(feat)

    class ResidualWorldModel(G.WorldModel):
        """--wm-residual. Its state is [h, z_t]: step keeps the z_t it read beside the GRU's h_{t+1}, so
        heads(state) adds the change to it; the actor and critic read the GRU's part only."""

        def step(self, state, z, a):
            h = self.gru(self.inp(torch.cat([z, a], -1)), state[..., : self.gru.hidden_size])
            return torch.cat([h, z], -1)

        def heads(self, state):
            h, z_t = state[..., : self.gru.hidden_size], state[..., self.gru.hidden_size :]
            z_next = torch.tanh(self.z_head[:-1](h) + torch.atanh(z_t.clamp(-0.999, 0.999)))
            feat = torch.cat([h, z_next], -1)
            return z_next, self.reward_head(feat), self.done_logit(feat)

    class ConstantInputCritic(G.Critic):
        def forward(self, h):
            return self.net(h.detach())

    class ExperimentAgent(G.Agent):
        def __init__(self, env, z_dim, reward_loss, return_norm_decay=0.99, cpu_preset=False, done_head=True):
            super().__init__(env, z_dim, reward_loss, return_norm_decay, cpu_preset, done_head)
            if args.ac_input == "hz":  # the actor and critic read z_t beside h_t
                s = G.sizes_of(env, cpu_preset)
                ac_in = s["gru_hidden"] + z_dim
                self.actor = G.Actor(ac_in, s["actions"], s["ac_layers"], self.discrete, s["ac_width"])
                self.critic = G.Critic(ac_in, s["ac_layers"], s["ac_width"])
                self.slow_critic = copy.deepcopy(self.critic).requires_grad_(False)
            if args.heads_read_sg_z:
                self.wm.__class__ = SgZWorldModel  # same parameters, other forward
            if args.wm_residual:
                self.wm.__class__ = ResidualWorldModel
                self.wm.hidden = self.wm.gru.hidden_size + z_dim
            if not args.value_slope:
                self.critic.__class__ = ConstantInputCritic
            if args.zero_init:  # DreamerV3: reward and value predictions start at 0
                for last in (self.wm.reward_head[-1], self.critic.net[-1]):
                    nn.init.zeros_(last.weight)
                    nn.init.zeros_(last.bias)
                self.slow_critic.load_state_dict(self.critic.state_dict())

        def features(self, h, z):
            h = h[..., : self.wm.gru.hidden_size]  # --wm-residual's state carries z_t after h
            return torch.cat([h, z], -1) if args.ac_input == "hz" else h

    return ExperimentAgent


def decaying_explore(a: torch.Tensor, args: Args, env_steps: int) -> torch.Tensor:
    """gw_dreamer.explore with --explore-noise-decay: the noise's std falls linearly to 0 at frame N."""
    sigma = args.explore_noise * max(0.0, 1.0 - env_steps / args.explore_noise_decay)
    return (a + sigma * torch.randn_like(a)).clamp(-1, 1)


class AttributeEncoder(G.FrozenEncoder):
    """The control: z_t is the true attribute vector, not the GW's (the images are not read)."""

    @torch.no_grad()
    def forward(self, obs: dict[str, np.ndarray], alpha_v: float = 0.5, alpha_attr: float = 0.5):
        attr = torch.as_tensor(
            obs["attr"][:, : self.z_dim], device=self.attr_mean.device, dtype=torch.float32
        )
        return attr.clamp(-1, 1)


def main(args: Args) -> dict:
    if args.wm_residual and args.heads_read_sg_z:
        raise G.UsageError("--wm-residual and --heads-read-sg-z are separate experiments; give one")
    G.require(
        args.explore_noise_decay >= 0, "explore_noise_decay", args.explore_noise_decay, "must not be negative"
    )
    if args.explore_noise_decay and not args.resolve().explore_noise:
        raise G.UsageError("--explore-noise-decay needs --explore-noise")
    if args.z_source == "attributes" and args.env != "simple_shapes":
        raise G.UsageError(
            "--z-source attributes is a Simple Shapes control (RoboDesk attributes are unbounded)"
        )
    paper_run_name, paper_load_frozen = G.run_name, G.load_frozen

    def load_frozen(a, dev):
        encoder, paths = paper_load_frozen(a, dev)
        if a.z_source == "attributes":
            encoder.__class__ = AttributeEncoder
        return encoder, paths

    RecentReplay.fraction, RecentReplay.window = args.recent_fraction, args.recent_window
    patches = {
        "Replay": RecentReplay if args.recent_fraction else G.Replay,
        "Agent": experiment_agent(args),
        "load_frozen": load_frozen,
        "run_name": lambda a, model: paper_run_name(a, model + suffix(a)),
        "explore": decaying_explore if args.explore_noise_decay else G.explore,
    }
    saved = {name: getattr(G, name) for name in patches}
    for name, value in patches.items():
        setattr(G, name, value)
    try:
        return G.main(args)
    finally:
        for name, value in saved.items():
            setattr(G, name, value)


if __name__ == "__main__":
    G.cli(main, Args)
