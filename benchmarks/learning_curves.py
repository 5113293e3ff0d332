"""Learning curves from TensorBoard runs: the smoothed normalised return (sliding window of 10 training
episodes, as the paper's figures) against env steps, mean ± s.e.m. over seeds, and each seed's criterion
step (first env step where the smoothed normalised return reaches the criterion).

    python benchmarks/learning_curves.py "runs/gw_dreamer_gw_simple_shapes_s*" --every 2500
"""

import glob
from dataclasses import dataclass

import numpy as np
import tyro
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator


@dataclass
class Args:
    pattern: tyro.conf.Positional[str]
    """glob of run folders (one per seed)"""
    tag: str = "charts/normalised_return"
    """per-episode scalar to smooth"""
    window: int = 10
    """episodes in the sliding window (paper: 10)"""
    criterion: float = 0.75
    """criterion on the smoothed value"""
    every: int = 2_500
    """env steps between rows of the table"""


def smoothed(run: str, a: Args) -> tuple[np.ndarray, np.ndarray]:
    events = EventAccumulator(run, size_guidance={"scalars": 0}).Reload().Scalars(a.tag)
    steps = np.array([e.step for e in events])
    values = np.array([e.value for e in events])
    kernel = np.ones(a.window) / a.window
    return steps[a.window - 1 :], np.convolve(values, kernel, mode="valid")


if __name__ == "__main__":
    a = tyro.cli(Args)
    runs = sorted(glob.glob(a.pattern))
    if not runs:
        raise SystemExit(f"no run folder matches {a.pattern!r}")
    curves = {}
    for run in runs:
        steps, values = smoothed(run, a)
        hit = np.flatnonzero(values >= a.criterion)
        crit = f"{steps[hit[0]]:,}" if hit.size else f"not reached (max {values.max():.2f})"
        print(f"{run}: criterion {a.criterion} at env step {crit}")
        curves[run] = (steps, values)
    last = min(s[-1] for s, _ in curves.values())
    print(f"\n| env steps | smoothed {a.tag.split('/')[-1]} (mean ± s.e.m. over {len(runs)} runs) |")
    print("| --- | --- |")
    for step in range(a.every, last + 1, a.every):
        at = np.array([v[np.searchsorted(s, step, side="right") - 1] for s, v in curves.values()])
        sem = at.std(ddof=1) / np.sqrt(len(at)) if len(at) > 1 else 0.0
        print(f"| {step:,} | {at.mean():.2f} ± {sem:.2f} |")
