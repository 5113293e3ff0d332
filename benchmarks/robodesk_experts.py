"""Success counts of the scripted RoboDesk experts (envs/robodesk_experts.py): for each task, N episodes
on seeds 0..N-1 without images, the number of the 500 agent steps in which the task's success criterion
holds (mean +- s.e.m.), the episodes with any success, and the time taken. The expert table of
docs/environments.md is this script's output.

    MUJOCO_GL=egl python benchmarks/robodesk_experts.py --episodes 20
    MUJOCO_GL=egl python benchmarks/robodesk_experts.py --tasks open_drawer --episodes 20 --per-episode
    MUJOCO_GL=egl python benchmarks/robodesk_experts.py --workers 8     # episodes in 8 processes

Episodes are independent (each its own seed), so any number of worker processes gives the same counts.
"""

import multiprocessing as mp
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from envs.robodesk import RoboDeskEnv  # noqa: E402
from envs.robodesk_experts import EXPERTS  # noqa: E402


@dataclass
class Args:
    tasks: tuple[str, ...] = ()
    """tasks to measure (default: every task with a scripted expert)"""
    episodes: int = 20
    """episodes per task, on seeds 0 .. episodes-1"""
    noise: float = 0.0
    """std of the Gaussian action noise (pretrain_vae_gw.py collects with 0.1)"""
    per_episode: bool = False
    """also print each episode's success count"""
    workers: int = 1
    """processes running episodes side by side (each with its own simulator)"""


def episode_success(job: tuple[str, int, float]) -> int:
    """The success count of one expert episode on ``seed``."""
    task, seed, noise = job
    env = RoboDeskEnv(task=task, render_images=False)
    env.reset(seed=seed)
    policy = EXPERTS[task](env, noise=noise, seed=seed)
    count, done = 0, False
    while not done:
        _, _, term, trunc, info = env.step(policy.act(env))
        count, done = count + int(info["success"]), term or trunc
    env.close()
    return count


def success_counts(task: str, episodes: int, noise: float, workers: int = 1) -> np.ndarray:
    jobs = [(task, seed, noise) for seed in range(episodes)]
    if workers == 1:
        return np.array([episode_success(j) for j in jobs])
    with mp.get_context("spawn").Pool(workers) as pool:
        return np.array(pool.map(episode_success, jobs))


if __name__ == "__main__":
    args = tyro.cli(Args)
    unknown = sorted(set(args.tasks) - set(EXPERTS))
    if unknown:
        raise SystemExit(f"no scripted expert for {unknown}; experts exist for {sorted(EXPERTS)}")
    print("| task | success count, mean ± s.e.m. | episodes with any success | seconds |")
    print("| --- | --- | --- | --- |")
    for task in args.tasks or sorted(EXPERTS):
        t0 = time.perf_counter()
        c = success_counts(task, args.episodes, args.noise, args.workers)
        sem = c.std(ddof=1) / np.sqrt(len(c)) if len(c) > 1 else 0.0
        took = time.perf_counter() - t0
        row = f"| {task} | {c.mean():.0f} ± {sem:.0f} | {(c > 0).sum()} / {len(c)} | {took:.0f} |"
        print(row, flush=True)
        if args.per_episode:
            print("  per episode: " + " ".join(str(int(v)) for v in c))
