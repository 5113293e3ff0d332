"""The data path of pretrain_vae_gw.py's vae stage, in memory against streamed (--stream-shards K):
samples/s of drawing batches and turning them into the VAE's input tensors, the time to get ready, and
the process's peak memory, on a dataset of RoboDesk-sized shards (64 x 64 images, 76 attributes) made
for the purpose. Each path runs in a process of its own, so that its peak memory is its own.

    python benchmarks/pretrain_data_throughput.py                       # 40,000 samples in 8 shards
    python benchmarks/pretrain_data_throughput.py --samples 200000 --shard-size 25000 --stream 2 4
"""

import json
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import pretrain_vae_gw as P  # noqa: E402


@dataclass
class Args:
    samples: int = 40_000
    """samples in the made dataset"""
    shard_size: int = 5_000
    """samples per shard"""
    stream: tuple[int, ...] = (2,)
    """--stream-shards values to measure (the in-memory path is always measured)"""
    batch: int = 256
    """samples per batch"""
    steps: int = 400
    """batches drawn per measurement"""
    data: str = ""
    """an existing folder of shards to read instead of making one"""
    one: str = ""
    """(internal) measure one path on --data and print its figures as JSON"""


def make_data(folder: Path, n: int, shard: int) -> None:
    """RoboDesk-sized shards: a dark frame with a bright block at a random place (it compresses like
    renders do, unlike noise)."""
    rng = np.random.default_rng(0)
    for start in range(0, n, shard):
        k = min(shard, n - start)
        images = np.full((k, 64, 64, 3), 20, np.uint8)
        xy = rng.integers(0, 56, (k, 2))
        for i, (x, y) in enumerate(xy):
            images[i, y : y + 8, x : x + 8] = 230
        P.write_shard(folder, images, rng.normal(size=(k, 76)).astype(np.float32), "random")


def measure(folder: Path, mode: str, a: Args) -> dict:
    t0 = time.perf_counter()
    if mode == "memory":
        data = P.InMemory(folder, "robodesk", n_eval=1_000)
    else:
        data = P.Streamed(folder, "robodesk", n_eval=1_000, k=int(mode), seed=0, batch=a.batch)
    mean, std = data.train_attr_moments()
    data.advance(1)
    ready = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for step in range(1, a.steps + 1):
        data.advance(step)
        images, attrs = data.batch(rng, a.batch)
        P.images_to_tensor(images, "cpu"), (attrs - mean) / std
    rate = a.steps * a.batch / (time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kB -> GiB
    return {"ready_s": ready, "samples_per_s": rate, "peak_gib": peak}


if __name__ == "__main__":
    a = tyro.cli(Args)
    if a.one:
        print(json.dumps(measure(Path(a.data), a.one, a)))
        raise SystemExit
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(a.data) if a.data else Path(tmp) / "robodesk"
        if not a.data:
            make_data(folder, a.samples, a.shard_size)
        gib = a.samples * (64 * 64 * 3 + 76 * 4) / 2**30
        size = f"{a.samples:,} samples in shards of {a.shard_size:,} ({gib:.2f} GiB as arrays)"
        print(f"{size}, batches of {a.batch}")
        for mode in ("memory", *map(str, a.stream)):
            flags = [f"--{k.replace('_', '-')}={v}" for k, v in vars(a).items() if k in ("batch", "steps")]
            cmd = [sys.executable, __file__, "--data", str(folder), "--one", mode, *flags]
            r = json.loads(
                subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.splitlines()[-1]
            )
            name = "in memory" if mode == "memory" else f"streamed, {mode} shards"
            print(
                f"{name:22s}: ready in {r['ready_s']:5.1f} s, {r['samples_per_s']:8,.0f} samples/s, "
                f"peak memory {r['peak_gib']:.2f} GiB",
                flush=True,
            )
