"""GW-Dreamer speed and compute at the paper's network sizes: training updates/s (world model +
actor-critic in imagination; FLOPs per update counted with torch.utils.flop_counter), the RL training
FLOPs to the paper's criteria under both readings of where dreams start, and acting steps/s (frozen VAEs
+ GW + policy + environment). Weights are random: speed does not depend on them.

    python benchmarks/gw_dreamer_throughput.py                      # both envs, both readings
    python benchmarks/gw_dreamer_throughput.py --envs simple_shapes --device cuda
    python benchmarks/gw_dreamer_throughput.py --envs robodesk --cpu-preset --imag-from last \
        --done-head on --wm-open-loop-stride 16 --batch-size 32     # the earlier CPU preset

The paper's FLOPs table gives 5.41e15 RL training FLOPs for GW-Dreamer on RoboDesk push_green until its
criterion at about 200,000 environment steps; the lines "FLOPs to the criterion" set each reading next to
it, counting those steps as simulator frames (the paper's unit: 4 per agent step) and as agent steps.
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import gw_dreamer as G  # noqa: E402


@dataclass
class Args:
    envs: tuple[str, ...] = ("simple_shapes", "robodesk")
    """environments to measure"""
    device: str = "cpu"
    """torch device"""
    updates: int = 3
    """timed updates per setting (after one counted and one warm-up update)"""
    acting_steps: int = 200
    """timed environment steps of acting"""
    vae_widths: tuple[int, ...] = (1024, 64)
    """visual VAE widths for acting (1024: the paper's table; 64: pretrain_vae_gw.py --cpu-preset)"""
    render_quality: str = "fast"
    """RoboDesk image quality while acting"""
    cpu_preset: bool = False
    """measure gw_dreamer.py --cpu-preset (RoboDesk's CPU sizes and batch) instead of the paper's sizes"""
    imag_from: tuple[str, ...] = ("last", "all")
    """readings of where dreams start to measure"""
    batch_size: int | None = None
    """replayed sequences per update (default: the run's)"""
    wm_open_loop_stride: int | None = None
    """replayed entries between two starts of the open-loop term (default: the run's)"""
    done_head: Literal["on", "off"] | None = None
    """with or without the world model's done head (default: the run's)"""


def random_encoder(env: str, width: int) -> G.FrozenEncoder:
    s = G.ENV_SPECS[env]
    depth, hidden = (2, 64) if env == "simple_shapes" else (4, 512)
    vae = {
        "config": {"vae_width": width},
        "vae_v": G.VisualVAE(s["image"], s["latent"], width).state_dict(),
        "vae_attr": G.AttrVAE(s["attr"], s["latent"], hidden, depth).state_dict(),
        "attr_mean": np.zeros(s["attr"], np.float32),
        "attr_std": np.ones(s["attr"], np.float32),
    }
    return G.FrozenEncoder(
        env, vae, {"gw": G.GlobalWorkspace(s["latent"], s["z"], s["gw_hidden"]).state_dict()}
    )


def time_updates(env: str, a: Args, **overrides) -> dict:
    for k in ("batch_size", "wm_open_loop_stride", "done_head"):
        if getattr(a, k) is not None:
            overrides[k] = getattr(a, k)
    args = G.Args(env=env, cpu_preset=a.cpu_preset, **overrides).resolve()
    if args.done_head == "off" and env != "robodesk":
        raise SystemExit("--done-head off is for RoboDesk (no episode ends early there): --envs robodesk")
    z_dim, done_head = G.ENV_SPECS[env]["z"], args.done_head == "on"
    agent = G.Agent(env, z_dim, args.reward_loss, cpu_preset=a.cpu_preset, done_head=done_head).to(a.device)
    counts = {k: sum(p.numel() for p in getattr(agent, k).parameters()) for k in ("wm", "actor", "critic")}
    opts = G.make_optimizers(agent, args)
    n_act = G.SIZES[env]["actions"]
    replay = G.Replay(20_000, 1, G.ENV_SPECS[env]["z"], n_act, 0)
    rng = np.random.default_rng(0)
    for t in range(2_000):
        z = rng.uniform(-1, 1, (1, G.ENV_SPECS[env]["z"]))
        replay.add([0], z, np.eye(n_act)[[t % n_act]], [-1.0], [0], [t % 100 == 0], [0])
    _, flops = G.count_flops(lambda: G.train_update(agent, opts, replay, args))
    parts = flops_by_part(agent, replay, args)
    G.train_update(agent, opts, replay, args)
    if a.device.startswith("cuda"):
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(a.updates):
        G.train_update(agent, opts, replay, args)
    if a.device.startswith("cuda"):
        torch.cuda.synchronize()
    sec = (time.perf_counter() - t) / a.updates
    starts = args.batch_size * (1 if args.imag_from == "last" else args.batch_length)
    # env steps/s that the updates alone allow: train_ratio agent steps per update
    per_env_step = args.train_ratio * G.ACTION_REPEAT[env] / sec
    return {
        "starts": starts,
        "s_per_update": sec,
        "flops": flops,
        "env_steps_per_s": per_env_step,
        "args": args,
        "params": counts,
        "parts": parts,
    }


def flops_by_part(agent: G.Agent, replay: G.Replay, args: G.Args) -> dict[str, float]:
    """Training FLOPs (forward and backward) of each part of one update, on one replayed batch."""
    batch = {k: torch.as_tensor(v) for k, v in replay.sample(args.batch_size, args.batch_length).items()}
    with torch.no_grad():
        h_entry = G.world_model_loss(agent.wm, agent.reward_dec, batch, args)[2]
    h0, z0, start_w = G.dream_starts(h_entry, batch, args.imag_from)
    actor, critic = list(agent.actor.parameters()), list(agent.critic.parameters())

    def world_model():
        G.world_model_loss(agent.wm, agent.reward_dec, batch, args)[0].backward()

    def open_loop():
        G.open_loop_loss(agent.wm, agent.reward_dec, batch, h_entry, args)[0].backward()

    def dreams():
        loss_actor, loss_critic, _ = G.dream_loss(agent, h0, z0, start_w, args)
        loss_actor.backward(inputs=actor, retain_graph=True)
        loss_critic.backward(inputs=critic)

    def replay_critic():
        G.replay_critic_loss(agent, h_entry, batch, args).backward(inputs=critic)

    parts = {"world model (one step, every replayed entry)": world_model}
    if args.wm_open_loop:
        parts["open-loop world-model loss"] = open_loop
    parts["dreams and their actor-critic losses"] = dreams
    if args.critic_replay_coef:
        parts["replay value loss"] = replay_critic
    return {name: G.count_flops(fn)[1] for name, fn in parts.items()}


# The paper's criteria: Simple Shapes about 20,000 env steps (Figure 3), RoboDesk about 200,000 with
# 5.41e15 RL training FLOPs for GW-Dreamer (Table "Training FLOPs", column "RL 1 task").
PAPER_CRITERION = {"simple_shapes": (20_000, None), "robodesk": (200_000, 5.41e15)}


def flops_to_criterion(env: str, r: dict) -> str:
    steps, table = PAPER_CRITERION[env]
    args, repeat = r["args"], G.ACTION_REPEAT[env]
    updates = G.updates_due(steps, args)
    line = f"    FLOPs to the paper's criterion ({steps:,} env steps = {steps // repeat:,} agent steps, "
    line += f"{updates:,} updates): {updates * r['flops']:.2e}"
    if table:
        # the other unit: the same number counted in agent steps (frames = 4x as many)
        updates_agent = G.updates_due(steps * repeat, args)
        line += f" (table: {table:.2e}; {updates_agent * r['flops']:.2e} if the paper counted agent steps)"
    return line


def time_acting(env: str, width: int, a: Args) -> float:
    args = G.Args(env=env, render_quality=a.render_quality, cpu_preset=a.cpu_preset).resolve()
    enc = random_encoder(env, width).to(a.device)
    agent = G.Agent(env, enc.z_dim, args.reward_loss, cpu_preset=a.cpu_preset).to(a.device)
    envs = G.make_envs(args, 1)
    obs, _ = envs.reset(seed=0)
    h = torch.zeros(1, agent.wm.hidden, device=a.device)
    t = time.perf_counter()
    with torch.no_grad():
        for _ in range(a.acting_steps):
            z = enc(obs)
            act = agent.actor.act(h)
            obs, *_ = envs.step(G.action_for_env(act, agent.discrete))
            h = agent.wm.step(h, z, act)
    envs.close()
    return a.acting_steps / (time.perf_counter() - t)


if __name__ == "__main__":
    a = tyro.cli(Args)
    torch.manual_seed(0)
    print(f"device {a.device}, torch threads {torch.get_num_threads()}")
    for env in a.envs:
        unit = (
            "agent steps"
            if G.ACTION_REPEAT[env] == 1
            else f"simulator frames, {G.ACTION_REPEAT[env]} per agent step"
        )
        print(f"{env}: --total-steps and every step count are env steps ({unit})")
        for imag_from in a.imag_from:
            r = time_updates(env, a, imag_from=imag_from)
            print(
                f"{env:13s} --imag-from {imag_from:4s}: {r['starts']:,} dreams per update, "
                f"{1 / r['s_per_update']:.2f} updates/s ({r['s_per_update']:.2f} s), "
                f"{r['flops'] / 1e9:.1f} GFLOP/update ({r['flops'] / 1e9 / r['s_per_update']:.0f} GFLOP/s); "
                f"updates allow {r['env_steps_per_s']:.1f} env steps/s"
            )
            print(flops_to_criterion(env, r))
            for part, f in r["parts"].items():
                print(f"    {part}: {f / 1e9:.1f} GFLOP ({f / r['flops']:.0%})")
            hours = G.updates_due(r["args"].total_steps, r["args"]) * r["s_per_update"] / 3600
            print(
                f"    parameters: world model {r['params']['wm']:,}, actor {r['params']['actor']:,}, critic "
                f"{r['params']['critic']:,}; the updates of --total-steps {r['args'].total_steps:,} take "
                f"{hours:.1f} h"
            )
        for width in a.vae_widths:
            rate = time_acting(env, width, a) * G.ACTION_REPEAT[env]  # agent steps/s -> env steps/s
            print(f"{env:13s} acting, VAE width {width:4d}: {rate:.1f} env steps/s")
