"""Training throughput (samples/s) and training FLOPs per sample (forward + backward, counted with
torch.utils.flop_counter) of each pre-training stage of pretrain_vae_gw.py, per environment, at the
paper's widths; multiply FLOPs/sample by batch x steps to compare with the paper's FLOPs table.

    python benchmarks/pretrain_throughput.py
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import tyro
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import pretrain_vae_gw as P  # noqa: E402


@dataclass
class Args:
    batch_size: int = 32
    """samples per timed update"""
    updates: int = 3
    """updates timed per stage"""
    envs: tuple[str, ...] = ("simple_shapes", "robodesk")
    """environments to measure"""
    vae_width: int = 1024
    """visual VAE width (1024 as in the paper's tables)"""


def measure(step, batch: int, updates: int) -> tuple[float, float]:
    with FlopCounterMode(display=False) as counter:
        step()
    step()  # warm-up
    t = time.perf_counter()
    for _ in range(updates):
        step()
    return batch * updates / (time.perf_counter() - t), counter.get_total_flops() / batch


def stage_steps(env: str, batch: int, vae_width: int) -> dict:
    """One training update (loss, backward) of each stage on random inputs of the env's shapes."""
    spec = P.ENV_SPECS[env]
    vae_v, vae_attr = P.make_vaes(env, vae_width)
    gw = P.GlobalWorkspace(spec["latent"], spec["z"], spec["gw_hidden"])
    x = torch.rand(batch, 3, spec["image"], spec["image"])
    a = torch.randn(batch, spec["attr"])
    if env == "simple_shapes":
        a[:, :3] = torch.eye(3)[torch.randint(0, 3, (batch,))]
    u = {"v": torch.randn(batch, spec["latent"]), "attr": torch.randn(batch, spec["latent"])}
    alpha = torch.rand(batch, 1)

    def gw_step():
        terms = P.gw_losses(gw, u, alpha, 0.07)
        sum(P.PRESETS["gw"][k] * terms[k] for k in terms).backward()

    return {
        "visual VAE": lambda: vae_v.loss(x, 0.1)[0].backward(),
        "attribute VAE": lambda: vae_attr.loss(a, 0.05)[0].backward(),
        "GW": gw_step,
    }


if __name__ == "__main__":
    args = tyro.cli(Args)
    for env in args.envs:
        for name, fn in stage_steps(env, args.batch_size, args.vae_width).items():
            rate, flops = measure(fn, args.batch_size, args.updates if name == "visual VAE" else 20)
            print(f"{env:<14s} {name:<14s} {rate:>10,.0f} samples/s {flops:>12.3e} training FLOPs/sample")
