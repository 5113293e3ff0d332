"""PPO variants' speed: acting (frozen encoders + policy + environment, env steps/s), one minibatch update
(minibatches/s and FLOPs with torch.utils.flop_counter), and the resulting env steps/s of a whole run at
the paper's settings (2 envs x 8,192 steps per rollout, 15 epochs of 512-sample minibatches). Weights are
random: speed does not depend on them.

    python benchmarks/ppo_throughput.py                           # Simple Shapes, all variants
    python benchmarks/ppo_throughput.py --envs robodesk --variants raw gw
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import ppo_variants as PPO  # noqa: E402


@dataclass
class Args:
    envs: tuple[str, ...] = ("simple_shapes",)
    """environments to measure"""
    variants: tuple[str, ...] = ("raw", "vae", "clip", "gw")
    """variants to measure"""
    vae_width: int = 1024
    """visual VAE width (1024: the paper's table; 64: pretrain_vae_gw.py --cpu-preset)"""
    device: str = "cpu"
    """torch device"""
    acting_steps: int = 200
    """timed acting steps (per environment)"""
    minibatches: int = 10
    """timed minibatch updates"""
    render_quality: str = "fast"
    """RoboDesk image quality while acting"""


def random_observer(env: str, variant: str, width: int) -> PPO.Observer:
    s = PPO.ENV_SPECS[env]
    depth, hidden = (2, 64) if env == "simple_shapes" else (4, 512)
    vae = {
        "config": {"vae_width": width},
        "vae_v": PPO.VisualVAE(s["image"], s["latent"], width).state_dict(),
        "vae_attr": PPO.AttrVAE(s["attr"], s["latent"], hidden, depth).state_dict(),
        "attr_mean": np.zeros(s["attr"], np.float32),
        "attr_std": np.ones(s["attr"], np.float32),
    }
    gw = {"gw": PPO.GlobalWorkspace(s["latent"], s["z"], s["gw_hidden"]).state_dict()}
    return PPO.Observer(env, variant, None if variant == "raw" else vae, gw)


def measure(env: str, variant: str, a: Args) -> dict:
    args = PPO.Args(env=env, variant=variant, render_quality=a.render_quality)
    obs_model = random_observer(env, variant, a.vae_width).to(a.device)
    discrete = env == "simple_shapes"
    agent = PPO.Agent(obs_model, args, 7 if discrete else 5, discrete).to(a.device)
    envs = PPO.make_envs(args, args.num_envs)
    obs, _ = envs.reset(seed=0)
    stack = PPO.FrameStack(args.frame_stack)
    x = stack.reset(obs_model(obs, "none", a.device))
    xs = []
    t = time.perf_counter()
    for _ in range(a.acting_steps):
        with torch.no_grad():
            action, *_ = agent.get_action_and_value(x)
        obs, *_ = envs.step(PPO.env_action(action, discrete))
        x = stack.push(obs_model(obs, "none", a.device))
        xs.append(x)
    acting = a.acting_steps * args.num_envs / (time.perf_counter() - t)
    envs.close()
    n = args.minibatch_size
    batch = {k: torch.cat([x[k] for x in xs])[:n] for k in xs[0]}
    reps = -(-n // len(batch[next(iter(batch))]))
    batch = {k: v.repeat(reps, *[1] * (v.dim() - 1))[:n] for k, v in batch.items()}
    with torch.no_grad():
        actions, logp, _, values = agent.get_action_and_value(batch)
    mb = {"obs": batch, "actions": actions, "logprobs": logp, "values": values}
    mb |= {"advantages": torch.randn(n, device=a.device), "returns": torch.randn(n, device=a.device)}
    opt = torch.optim.Adam(agent.parameters(), lr=3e-4)

    def update():
        loss, _ = PPO.ppo_loss(agent, mb, args)
        opt.zero_grad()
        loss.backward()
        opt.step()

    _, flops = PPO.count_flops(update)
    sync = torch.cuda.synchronize if a.device.startswith("cuda") else (lambda: None)
    sync()  # GPU work is asynchronous: time from and to an idle device
    t = time.perf_counter()
    for _ in range(a.minibatches):
        update()
    sync()
    per_mb = (time.perf_counter() - t) / a.minibatches
    rollout = args.num_envs * args.num_steps
    n_mb = args.update_epochs * (rollout // n)
    run_sps = rollout / (rollout / acting + n_mb * per_mb)
    return {"acting": acting, "mb_s": per_mb, "flops": flops, "run_sps": run_sps}


if __name__ == "__main__":
    a = tyro.cli(Args)
    torch.manual_seed(0)
    print(f"device {a.device}, torch threads {torch.get_num_threads()}, VAE width {a.vae_width}")
    for env in a.envs:
        for variant in a.variants:
            r = measure(env, variant, a)
            print(
                f"{env:13s} {variant:4s}: acting {r['acting']:.0f} env steps/s; minibatch of 512 "
                f"{1 / r['mb_s']:.1f}/s ({r['flops'] / 1e9:.2f} GFLOP); whole run at paper settings "
                f"{r['run_sps']:.0f} env steps/s"
            )
