"""Simple Shapes throughput: environment steps per second with images, single and batched, and the time to
generate the paper's 500,000-sample pre-training dataset.

    python benchmarks/env_throughput.py
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from envs.simple_shapes import SimpleShapesEnv, SimpleShapesVectorEnv, sample_dataset  # noqa: E402


@dataclass
class Args:
    steps: int = 200_000
    """environment steps timed per configuration (the single env runs a tenth of them)"""
    batch_sizes: tuple[int, ...] = (1, 64, 1024)
    """numbers of environments stepped together by SimpleShapesVectorEnv"""
    dataset_size: int = 500_000
    """samples generated for the pre-training dataset timing"""
    seed: int = 0


def time_single(steps: int, seed: int) -> float:
    env = SimpleShapesEnv()
    env.reset(seed=seed)
    actions = np.random.default_rng(seed).integers(0, 7, steps)
    t = time.perf_counter()
    for a in actions.tolist():
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    return steps / (time.perf_counter() - t)


def time_batched(n: int, steps: int, seed: int) -> float:
    env = SimpleShapesVectorEnv(n)
    env.reset(seed=seed)
    actions = np.random.default_rng(seed).integers(0, 7, (max(steps // n, 50), n))
    t = time.perf_counter()
    for a in actions:
        env.step(a)
    return actions.size / (time.perf_counter() - t)


if __name__ == "__main__":
    args = tyro.cli(Args)
    rate = time_single(args.steps // 10, args.seed)
    print(f"single env (SimpleShapesEnv):          {rate:>10,.0f} steps/s")
    for n in args.batch_sizes:
        rate = time_batched(n, args.steps, args.seed)
        print(f"batched env, N = {n:<5d}               {rate:>10,.0f} steps/s")
    t = time.perf_counter()
    data = sample_dataset(args.dataset_size, seed=args.seed)
    dt = time.perf_counter() - t
    mb = (data["image"].nbytes + data["attr"].nbytes) / 2**20
    print(f"dataset of {args.dataset_size:,} samples:         {dt:>10.1f} s  ({mb:,.0f} MiB)")
