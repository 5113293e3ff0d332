"""Training throughput (samples/s) and training FLOPs per sample (forward + backward, counted with
torch.utils.flop_counter) of each pre-training stage of pretrain_vae_gw.py, per environment, at the
paper's widths; multiply FLOPs/sample by batch x steps to compare with the paper's FLOPs table. A timed
update is what the stage runs: loss, backward and the AdamW step, with the script's memory settings
(channels-last visual VAE, glibc allocator thresholds).

    python benchmarks/pretrain_throughput.py
    python benchmarks/pretrain_throughput.py --envs simple_shapes --vae-width 64 --batch-size 128 \
        --gw-batch-size 256        # the --cpu-preset settings: updates/s give the stage times
    python benchmarks/pretrain_throughput.py --batch-size 2056 --device cuda   # paper batch, on a GPU
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
    gw_batch_size: int | None = None
    """samples per timed GW update (default: --batch-size)"""
    device: str = "cpu"
    """torch device"""


def measure(step, batch: int, updates: int, device: str) -> tuple[float, float]:
    with FlopCounterMode(display=False) as counter:
        step()
    step()  # warm-up
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    sync()  # GPU work is asynchronous: time from and to an idle device
    t = time.perf_counter()
    for _ in range(updates):
        step()
    sync()
    return batch * updates / (time.perf_counter() - t), counter.get_total_flops() / batch


def stage_steps(env: str, batch: int, gw_batch: int, vae_width: int, device: str) -> dict:
    """One training update (loss, backward, AdamW step) of each stage on random inputs of the env's
    shapes, as pretrain_vae_gw.py runs it: {stage: (update, batch)}."""
    spec = P.ENV_SPECS[env]
    vae_v, vae_attr = P.make_vaes(env, vae_width)
    vae_v.to(device, memory_format=torch.channels_last)
    vae_attr.to(device)
    gw = P.GlobalWorkspace(spec["latent"], spec["z"], spec["gw_hidden"]).to(device)
    x = P.images_to_tensor(
        torch.randint(0, 256, (batch, spec["image"], spec["image"], 3), dtype=torch.uint8), device
    )
    a = torch.randn(batch, spec["attr"])
    if env == "simple_shapes":
        a[:, :3] = torch.eye(3)[torch.randint(0, 3, (batch,))]
    a = a.to(device)
    u = {k: torch.randn(gw_batch, spec["latent"], device=device) for k in ("v", "attr")}
    alpha = torch.rand(gw_batch, 1, device=device)
    opt_v, opt_a = (torch.optim.AdamW(m.parameters(), lr=1e-4) for m in (vae_v, vae_attr))
    opt_gw = torch.optim.AdamW(gw.parameters(), lr=1e-4, fused=True)

    def update(opt, loss):
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    def gw_step():
        terms = P.gw_losses(gw, u, alpha, 0.07)
        update(opt_gw, sum(P.PRESETS["gw"][k] * terms[k] for k in terms))

    return {
        "visual VAE": (lambda: update(opt_v, vae_v.loss(x, 0.1)[0]), batch),
        "attribute VAE": (lambda: update(opt_a, vae_attr.loss(a, 0.05)[0]), batch),
        "GW": (gw_step, gw_batch),
    }


if __name__ == "__main__":
    args = tyro.cli(Args)
    P.keep_freed_memory()
    gw_batch = args.gw_batch_size or args.batch_size
    for env in args.envs:
        for name, (fn, batch) in stage_steps(
            env, args.batch_size, gw_batch, args.vae_width, args.device
        ).items():
            rate, flops = measure(fn, batch, args.updates if name == "visual VAE" else 100, args.device)
            print(
                f"{env:<14s} {name:<14s} batch {batch:>5d} {rate:>10,.0f} samples/s {rate / batch:>8.1f} "
                f"updates/s {flops:>12.3e} training FLOPs/sample"
            )
