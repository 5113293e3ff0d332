"""GW-Dreamer end-to-end speed at the paper's network sizes and at --cpu-preset's: one global training
step (two GW updates + world model + actor-critic in imagination) in updates/s, its FLOPs
(torch.utils.flop_counter), and the share of the two GW updates alone.
Weights are random: speed does not depend on them.

    python benchmarks/gw_dreamer_e2e_throughput.py                   # both envs, paper and CPU settings
    python benchmarks/gw_dreamer_e2e_throughput.py --envs robodesk --settings cpu-preset
    python benchmarks/gw_dreamer_e2e_throughput.py --envs simple_shapes --device cuda
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import gw_dreamer_e2e as E  # noqa: E402


@dataclass
class Args:
    envs: tuple[str, ...] = ("simple_shapes", "robodesk")
    """environments to measure"""
    settings: tuple[str, ...] = ("paper", "cpu-preset")
    """network sizes to measure: the paper's, --cpu-preset's"""
    device: str = "cpu"
    """torch device"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default); 1 measures a run beside another (--torch-threads 1)"""
    updates: int = 3
    """timed updates per setting (after one counted and one warm-up update)"""


def timed(fn, a: Args) -> float:
    """Seconds per call of fn, averaged over a.updates calls."""
    if a.device.startswith("cuda"):
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(a.updates):
        fn()
    if a.device.startswith("cuda"):
        torch.cuda.synchronize()
    return (time.perf_counter() - t) / a.updates


def measure(env: str, a: Args, **overrides) -> dict:
    args = E.Args(env=env, **overrides).resolve()
    agent = E.Agent(env, args.reward_loss, args.return_norm_decay, args.cpu_preset, args.done_head == "on")
    agent = agent.to(a.device)
    opts = E.make_optimizers(agent, args)
    spec, n_act = E.ENV_SPECS[env], E.SIZES[env]["actions"]
    replay = E.Replay(20_000, 1, spec["latent"], n_act, 0)
    rng = np.random.default_rng(0)
    for t in range(2_000):
        u = rng.normal(size=(2, 1, spec["latent"]))
        replay.add([0], u[0], u[1], np.eye(n_act)[[t % n_act]], [-1.0], [0], [t % 100 == 0], [0])

    def step():
        E.train_update(agent, opts, replay, args)

    def gw_only():
        for i in range(args.gw_updates):
            E.gw_update(agent, opts["gw"], replay, args, i)

    _, flops = E.count_flops(step)
    _, gw_flops = E.count_flops(gw_only)
    step()
    sec, gw_sec = timed(step, a), timed(gw_only, a)
    starts = args.batch_size * (1 if args.imag_from == "last" else args.batch_length)
    out = {"starts": starts, "gw_batch": args.gw_batch_size, "s": sec, "gw_s": gw_sec, "flops": flops}
    # train_ratio counts agent steps per update; RoboDesk counts env steps in frames (4 per agent step)
    return out | {"gw_flops": gw_flops, "env_steps_per_s": args.train_ratio * E.ACTION_REPEAT[env] / sec}


if __name__ == "__main__":
    a = tyro.cli(Args)
    if a.torch_threads:
        torch.set_num_threads(a.torch_threads)
    torch.manual_seed(0)
    print(f"device {a.device}, torch threads {torch.get_num_threads()}")
    for env in a.envs:
        for name in a.settings:
            overrides = {"cpu_preset": True} if name == "cpu-preset" else {}
            r = measure(env, a, **overrides)
            print(
                f"{env:13s} {name:10s} global step (2 GW updates of {r['gw_batch']:,}, imagination from "
                f"{r['starts']:,} states): {1 / r['s']:.2f} updates/s "
                f"({r['s']:.2f} s, GW {r['gw_s']:.2f} s), "
                f"{r['flops'] / 1e9:.1f} GFLOP (GW {r['gw_flops'] / 1e9:.2f}); "
                f"updates allow {r['env_steps_per_s']:.1f} env steps/s"
            )
