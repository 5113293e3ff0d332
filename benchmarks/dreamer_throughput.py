"""Dreamer baseline speed at the paper's sizes: trainable parameters, training updates/s (world model +
actor-critic in imagination on a 16 x 65 batch, FLOPs per update from torch.utils.flop_counter), the env
steps/s that the train ratio 32 then allows, and peak memory. Weights and replay are random: speed does
not depend on them.

    python benchmarks/dreamer_throughput.py                                  # 2m (Simple Shapes), 12m, 40m
    python benchmarks/dreamer_throughput.py --settings simple_shapes:2m:raw simple_shapes:2m:vae --device cuda
"""

import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import dreamer_baseline as D  # noqa: E402


@dataclass
class Args:
    settings: tuple[str, ...] = ("simple_shapes:2m:raw", "robodesk:12m:raw", "robodesk:40m:raw")
    """env:size:obs triples to measure"""
    device: str = "cpu"
    """torch device"""
    updates: int = 2
    """timed updates per setting (after one counted, warm-up update)"""
    batch_size: int = 16
    """replayed sequences per update (paper: 16)"""
    batch_length: int = 65
    """entries per sequence (paper: 65)"""


def random_observer(env: str, obs: str) -> D.Observer:
    if obs == "raw":
        return D.Observer(env, "raw", None)
    s = D.ENV_SPECS[env]
    depth, hidden = (2, 64) if env == "simple_shapes" else (4, 512)
    vae = {
        "config": {"vae_width": 64},
        "vae_v": D.VisualVAE(s["image"], s["latent"], 64).state_dict(),
        "vae_attr": D.AttrVAE(s["attr"], s["latent"], hidden, depth).state_dict(),
        "attr_mean": np.zeros(s["attr"], np.float32),
        "attr_std": np.ones(s["attr"], np.float32),
    }
    return D.Observer(env, "vae", vae)


def measure(setting: str, a: Args) -> dict:
    env, size, obs = setting.split(":")
    args = D.Args(env=env, size=size, obs=obs, batch_size=a.batch_size, batch_length=a.batch_length).resolve()
    spaces = random_observer(env, obs).spaces(env)
    agent = D.Agent(env, spaces, args).to(a.device)
    opts = D.make_optimizers(agent, args)
    replay = D.Replay(2_000, 1, spaces, agent.n_actions, 0)
    rng = np.random.default_rng(0)
    for t in range(300):
        entry = {
            k: (
                rng.integers(0, 256, (1, *shp)).astype(np.uint8)
                if k == "image"
                else rng.normal(size=(1, *shp))
            )
            for k, shp in spaces.items()
        }
        entry |= {"action": np.eye(agent.n_actions)[[t % agent.n_actions]], "reward": [-1.0]}
        entry |= {"terminal": [0.0], "first": [float(t % 100 == 0)]}
        replay.add(np.array([0]), entry)
    if a.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    _, flops = D.count_flops(lambda: D.train_update(agent, opts, replay, args))
    if a.device.startswith("cuda"):
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(a.updates):
        D.train_update(agent, opts, replay, args)
    if a.device.startswith("cuda"):
        torch.cuda.synchronize()
    sec = (time.perf_counter() - t) / a.updates
    if a.device.startswith("cuda"):
        peak = torch.cuda.max_memory_allocated() / 2**30
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # process high-water mark
    replayed = args.batch_size * args.batch_length
    return {
        "setting": setting,
        "params": agent.n_trainable()["total"],
        "s_per_update": sec,
        "updates_per_s": 1 / sec,
        "gflop_per_update": flops / 1e9,
        "env_steps_per_s": replayed / args.train_ratio / sec,  # what the updates alone allow
        "peak_gib": peak,
    }


if __name__ == "__main__":
    a = tyro.cli(Args)
    print(
        f"device {a.device}, torch threads {torch.get_num_threads()}, batch {a.batch_size} x {a.batch_length}"
    )
    print(
        "| env:size:obs | parameters | s/update | updates/s | GFLOP/update | env steps/s (ratio 32) "
        "| peak GiB |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for setting in a.settings:
        r = measure(setting, a)
        print(
            f"| {r['setting']} | {r['params'] / 1e6:.2f}M | {r['s_per_update']:.2f} | "
            f"{r['updates_per_s']:.3f} | "
            f"{r['gflop_per_update']:.1f} | {r['env_steps_per_s']:.1f} | {r['peak_gib']:.2f} |",
            flush=True,
        )
