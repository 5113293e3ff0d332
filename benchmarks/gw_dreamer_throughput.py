"""GW-Dreamer speed at the paper's network sizes: training updates/s (world model + actor-critic in
imagination, FLOPs per update counted with torch.utils.flop_counter), and acting steps/s (frozen VAEs +
GW + policy + environment), per environment. Weights are random: speed does not depend on them.

    python benchmarks/gw_dreamer_throughput.py                      # both envs, paper and CPU settings
    python benchmarks/gw_dreamer_throughput.py --envs simple_shapes --device cuda
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

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
    args = G.Args(env=env, **overrides).resolve()
    agent = G.Agent(env, G.ENV_SPECS[env]["z"], args.reward_loss).to(a.device)
    opts = G.make_optimizers(agent, args)
    n_act = G.SIZES[env]["actions"]
    replay = G.Replay(20_000, 1, G.ENV_SPECS[env]["z"], n_act, 0)
    rng = np.random.default_rng(0)
    for t in range(2_000):
        z = rng.uniform(-1, 1, (1, G.ENV_SPECS[env]["z"]))
        replay.add([0], z, np.eye(n_act)[[t % n_act]], [-1.0], [0], [t % 100 == 0], [0])
    state = {"env_steps": 0, "updates": 0, "return_scale": 0.0}
    _, flops = G.count_flops(lambda: G.train_update(agent, opts, replay, args, state, a.device))
    G.train_update(agent, opts, replay, args, state, a.device)
    if a.device.startswith("cuda"):
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(a.updates):
        G.train_update(agent, opts, replay, args, state, a.device)
    if a.device.startswith("cuda"):
        torch.cuda.synchronize()
    sec = (time.perf_counter() - t) / a.updates
    starts = args.imag_starts or args.batch_size * args.batch_length
    per_env_step = args.train_ratio / sec  # env steps/s that the updates alone allow (train ratio)
    return {"starts": starts, "s_per_update": sec, "flops": flops, "env_steps_per_s": per_env_step}


def time_acting(env: str, width: int, a: Args) -> float:
    args = G.Args(env=env, render_quality=a.render_quality).resolve()
    enc = random_encoder(env, width).to(a.device)
    agent = G.Agent(env, enc.z_dim, args.reward_loss).to(a.device)
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
        settings = [("paper", {})]
        if env == "simple_shapes":
            settings.append(("cpu-preset", {"cpu_preset": True}))
        for name, overrides in settings:
            r = time_updates(env, a, **overrides)
            print(
                f"{env:13s} {name:10s} update (imagination from {r['starts']:,} states): "
                f"{1 / r['s_per_update']:.2f} updates/s ({r['s_per_update']:.2f} s), "
                f"{r['flops'] / 1e9:.1f} GFLOP/update; updates allow {r['env_steps_per_s']:.1f} env steps/s"
            )
        for width in a.vae_widths:
            print(f"{env:13s} acting, VAE width {width:4d}: {time_acting(env, width, a):.1f} env steps/s")
