"""Samples/s of pretrain_vae_gw.py's collect stage with 1 and N worker processes: RoboDesk episodes
(scripted experts and the random policy, fast and faithful rendering) and Simple Shapes shards, into a
temporary folder. The data are the same for any number of workers (tests/test_robodesk_experts.py).

    MUJOCO_GL=egl python benchmarks/collect_throughput.py                  # 1 and 2 workers
    MUJOCO_GL=egl python benchmarks/collect_throughput.py --workers 1 8 16 --samples 8000
"""

import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
import tyro  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import pretrain_vae_gw as P  # noqa: E402


@dataclass
class Args:
    workers: tuple[int, ...] = (1, 2)
    """worker counts to measure"""
    samples: int = 3_000
    """RoboDesk samples per measurement with fast rendering (a third per source: push_green expert,
    open_slide expert, random; whole episodes are 500 samples)"""
    faithful_samples: int = 1_000
    """the same with faithful rendering (about 14 frames/s a core: an episode takes minutes)"""
    qualities: tuple[str, ...] = ("fast", "faithful")
    """RoboDesk render qualities"""
    shapes_samples: int = 60_000
    """Simple Shapes samples per measurement (the --cpu-preset dataset), in shards of 5,000"""


def timed_collect(**kw) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        args = P.Args(stages=("collect",), data_dir=tmp, checkpoint_dir=tmp, **kw).resolve()
        t = time.perf_counter()
        P.collect(args, P.StopRequest("bench"))
        return time.perf_counter() - t


if __name__ == "__main__":
    a = tyro.cli(Args)
    print(f"{os.cpu_count()} CPUs")
    for w in a.workers:
        sec = timed_collect(env="simple_shapes", n_samples=a.shapes_samples, shard_size=5_000, workers=w)
        print(f"simple_shapes            {w:3d} workers: {a.shapes_samples / sec:8.0f} samples/s", flush=True)
    for q in a.qualities:
        for w in a.workers:
            kw = dict(env="robodesk", tasks=("push_green", "open_slide"), render_quality=q, workers=w)
            n = a.samples if q == "fast" else a.faithful_samples
            sec = timed_collect(n_samples=n, shard_size=n, **kw)
            print(f"robodesk {q:8s} {n:6,d}  {w:3d} workers: {n / sec:8.1f} samples/s", flush=True)
