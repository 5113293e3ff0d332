"""RoboDesk throughput on this machine: physics, inverse kinematics, rendering (each quality) and full
agent steps (faithful images, fast images, attributes only), the fast mode's image difference to the
faithful one, the resident memory of one environment, and fast-image agent steps of --vector-envs
environments stepped in this process and in one process each (``envs.robodesk.make_vector_env``).

    MUJOCO_GL=egl python benchmarks/robodesk_throughput.py
"""

import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from envs.robodesk import RoboDeskEnv, make_vector_env  # noqa: E402


@dataclass
class Args:
    task: str = "push_green"
    """RoboDesk task"""
    physics_steps: int = 20_000
    """physics steps timed"""
    ik_calls: int = 2_000
    """inverse-kinematics solves timed"""
    renders: int = 10
    """renders timed per quality (faithful renders take about 0.3 s each here)"""
    agent_steps: int = 300
    """agent steps timed without images (image runs use fewer: renders and 4 x renders)"""
    vector_envs: int = 2
    """environments of the vector-env timing (ppo_variants.py's --num-envs)"""
    vector_steps: int = 100
    """vector steps timed in each mode (each steps every environment once)"""
    seed: int = 0


def rss_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def rate(fn, n: int) -> float:
    fn()  # warm-up (creates the GL context on the first render)
    t = time.perf_counter()
    for _ in range(n):
        fn()
    return n / (time.perf_counter() - t)


def agent_steps(env: RoboDeskEnv, n: int, seed: int) -> float:
    env.reset(seed=seed)
    actions = np.random.default_rng(seed).uniform(-1, 1, (n + 1, 5))
    it = iter(actions)
    return rate(lambda: env.step(next(it)), n)


def vector_steps(n_envs: int, processes: bool, n: int, task: str, seed: int) -> float:
    """Agent steps per second (all environments together) of a fast-image vector env."""
    vec = make_vector_env(n_envs, processes, task=task, render_quality="fast")
    vec.reset(seed=seed)
    actions = iter(np.random.default_rng(seed).uniform(-1, 1, (n + 1, n_envs, 5)).astype(np.float32))
    steps_per_s = n_envs * rate(lambda: vec.step(next(actions)), n)
    vec.close()
    return steps_per_s


def report(label: str, value: float, unit: str) -> None:
    print(f"{label:<42s}{value:>10,.1f} {unit}")


if __name__ == "__main__":
    args = tyro.cli(Args)
    print(f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}")
    rss0 = rss_mib()
    env = RoboDeskEnv(task=args.task, render_images=False)
    env.reset(seed=args.seed)
    report("resident memory of one env (no renderer)", rss_mib() - rss0, "MiB")
    report("arena per MjData", env.model.narena / 2**20, "MiB")

    import mujoco

    m, d = env.model, env.data
    physics = rate(lambda: (mujoco.mj_step2(m, d), mujoco.mj_step1(m, d)), args.physics_steps)
    report("physics (mj_step2 + mj_step1)", physics, "steps/s")
    target = d.site_xpos[env._ee_site] + 0.005

    def ik():
        env._scratch.qpos[:] = d.qpos
        env.inverse_kinematics(target)

    report("inverse kinematics", rate(ik, args.ik_calls), "solves/s")
    report("agent steps, attributes only", agent_steps(env, args.agent_steps, args.seed), "steps/s")

    faithful = RoboDeskEnv(task=args.task, render_quality="faithful")
    fast = RoboDeskEnv(task=args.task, render_quality="fast")
    faithful.reset(seed=args.seed)
    fast.reset(seed=args.seed)
    report("render, faithful (shadows, 4x MSAA)", rate(faithful.render_image, args.renders), "renders/s")
    report("render, fast", rate(fast.render_image, args.renders * 4), "renders/s")
    report("resident memory, 3 envs, 2 renderers", rss_mib() - rss0, "MiB")
    report("agent steps, faithful images", agent_steps(faithful, args.renders, args.seed), "steps/s")
    report("agent steps, fast images", agent_steps(fast, args.renders * 4, args.seed), "steps/s")

    # Image difference of the fast mode on identical states.
    diffs = []
    for s in range(5):
        faithful.reset(seed=100 + s)
        fast.reset(options={"qpos": faithful.data.qpos.copy(), "qvel": faithful.data.qvel.copy()})
        diffs.append(np.abs(faithful.render_image().astype(int) - fast.render_image().astype(int)).mean())
    report("fast vs faithful image, mean |diff| /255", float(np.mean(diffs)), "(5 states)")

    for processes in (False, True):
        where = f"{args.vector_envs} processes" if processes else "one process"
        steps = vector_steps(args.vector_envs, processes, args.vector_steps, args.task, args.seed)
        report(f"agent steps, fast, {args.vector_envs} envs in {where}", steps, "steps/s")
