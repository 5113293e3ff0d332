"""Eager against compiled (--compile) training updates, at the paper's network sizes, for the three
Dreamer-family scripts: updates/s of each, the speed-up, and the time the compilation took. Weights and
replays are random: speed does not depend on them.

    python benchmarks/compile_throughput.py                              # Simple Shapes, the CPU
    python benchmarks/compile_throughput.py --device cuda --envs simple_shapes robodesk

On a GPU --compile uses CUDA graphs (torch.compile mode "reduce-overhead"). One call measures every
script and env asked for; on a GPU the whole default set runs in a few minutes, most of it compiling.
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import dreamer_baseline as D  # noqa: E402
import gw_dreamer as G  # noqa: E402
import gw_dreamer_e2e as E  # noqa: E402


@dataclass
class Args:
    scripts: tuple[str, ...] = ("gw_dreamer", "gw_dreamer_e2e", "dreamer_baseline")
    """scripts whose update is measured"""
    envs: tuple[str, ...] = ("simple_shapes",)
    """environments (RoboDesk's sizes take long to compile and to run on a CPU)"""
    device: str = "cpu"
    """torch device"""
    updates: int = 5
    """timed updates per setting, after the warm-up updates"""
    warmup: int = 3
    """untimed updates first (the compiled ones include the compilation: CUDA graphs record on the
    first calls)"""


def filled_replay(script: str, env: str, args, agent):
    """A replay of 2,000 random entries of the script's own layout."""
    rng = np.random.default_rng(0)
    if script == "dreamer_baseline":
        spaces = D.Observer(env, "raw", None).spaces(env)
        replay = D.Replay(3_000, 1, spaces, agent.n_actions, 0)
        for t in range(2_000):
            entry = {"image": rng.integers(0, 256, (1, *spaces["image"])).astype(np.uint8)}
            entry |= {
                "attr": rng.normal(size=(1, *spaces["attr"])),
                "action": np.eye(agent.n_actions)[[t % 7 % agent.n_actions]],
            }
            entry |= {"reward": [-1.0], "terminal": [0.0], "first": [float(t % 100 == 0)]}
            replay.add(np.array([0]), entry)
        return replay
    mod = G if script == "gw_dreamer" else E
    spec, n_act = mod.ENV_SPECS[env], mod.SIZES[env]["actions"]
    width = spec["z"] if script == "gw_dreamer" else spec["latent"]
    replay = mod.Replay(3_000, 1, width, n_act, 0)
    for t in range(2_000):
        x = [rng.uniform(-1, 1, (1, width)) for _ in range(1 if script == "gw_dreamer" else 2)]
        replay.add([0], *x, np.eye(n_act)[[t % n_act]], [-1.0], [0], [t % 100 == 0], [0])
    return replay


def setup(script: str, env: str, device: str):
    if script == "gw_dreamer":
        args = G.Args(env=env, device=device).resolve()
        return G, args, G.Agent(env, G.ENV_SPECS[env]["z"], args.reward_loss).to(device)
    if script == "gw_dreamer_e2e":
        args = E.Args(env=env, device=device, cpu_preset=env == "simple_shapes" and device == "cpu").resolve()
        return E, args, E.Agent(env, args.reward_loss).to(device)
    args = D.Args(env=env, device=device).resolve()
    return D, args, D.Agent(env, D.Observer(env, "raw", None).spaces(env), args).to(device)


def timed(fn, n: int, device: str) -> float:
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(n):
        fn()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return (time.perf_counter() - t) / n


def measure(script: str, env: str, a: Args) -> dict:
    torch.manual_seed(0)
    mod, args, agent = setup(script, env, a.device)
    replay, opts = filled_replay(script, env, args, agent), mod.make_optimizers(agent, args)
    out = {}
    for name, losses in (("eager", mod.EAGER), ("compiled", mod.compiled_losses(a.device))):
        t0 = time.perf_counter()
        timed(
            lambda losses=losses: mod.train_update(agent, opts, replay, args, losses=losses),
            a.warmup,
            a.device,
        )
        out[f"{name}_warmup_s"] = time.perf_counter() - t0
        out[name] = timed(
            lambda losses=losses: mod.train_update(agent, opts, replay, args, losses=losses),
            a.updates,
            a.device,
        )
    return out


if __name__ == "__main__":
    a = tyro.cli(Args)
    name = torch.cuda.get_device_name() if a.device.startswith("cuda") else "CPU"
    print(f"device {a.device} ({name}), torch {torch.__version__}, {torch.get_num_threads()} threads")
    for env in a.envs:
        for script in a.scripts:
            r = measure(script, env, a)
            print(
                f"{script:16s} {env:13s} eager {1 / r['eager']:6.2f} updates/s ({r['eager'] * 1e3:7.1f} ms), "
                f"compiled {1 / r['compiled']:6.2f} updates/s ({r['compiled'] * 1e3:7.1f} ms): "
                f"x{r['eager'] / r['compiled']:.2f}; compiling and {a.warmup} warm-up updates took "
                f"{r['compiled_warmup_s']:.0f} s",
                flush=True,
            )
