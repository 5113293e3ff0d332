"""How likely a run is to reach the return criterion by chance, at its setting's level and above it.

The criterion is a 10-episode mean of the training returns crossing a line (0.70 on RoboDesk). Seeds that
level off just below it cross it or not by the luck of a window of good episodes. This script draws
runs of `--episodes` training episodes at random from the recorded episodes of one setting after
`--from-frame` (docs/results/<env>_curves.csv; each seed weighs the same), shifted by each of
`--shifts`, and prints the share of those runs whose 10-episode mean reaches the criterion, and that
share to the power `--goal-seeds` (the chance that so many seeds all reach it). Episodes are drawn
independently: the trend within a run is left out, and the runs that stopped at the criterion have no
later episodes to draw, so the level read is a low estimate.

    python benchmarks/criterion_chance.py                       # GW-Dreamer --cpu-preset, push_green
    python benchmarks/criterion_chance.py --setting "critic replay 1.0" --goal-seeds 2
"""

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro


@dataclass
class Args:
    env: str = "robodesk"
    """environment whose records to read (docs/results/<env>_curves.csv)"""
    model: str = "GW-Dreamer"
    """the records' model column"""
    setting: str = "default"
    """the records' setting column"""
    task: str = "push_green"
    """the records' task column"""
    from_frame: int = 80_000
    """first env step of the episodes to draw from (the level a run has settled at)"""
    episodes: int = 60
    """episodes of a drawn run (RoboDesk: 2,000 frames each, so 60 from 80,000 to 200,000 frames)"""
    window: int = 10
    """episodes in the smoothed return (the paper: 10)"""
    criterion: float = 0.70
    """criterion on the smoothed normalised return"""
    shifts: tuple[float, ...] = (0.0, 0.02, 0.04, 0.06, 0.08, 0.1)
    """added to every drawn episode: the level a change of the method would have to add"""
    goal_seeds: int = 3
    """seeds that must all reach the criterion"""
    samples: int = 20_000
    """drawn runs per shift"""
    seed: int = 0
    """random seed of the draws"""
    results: Path = Path("docs/results")
    """folder of the records"""


def late_episodes(a: Args) -> tuple[np.ndarray, np.ndarray]:
    """The normalised returns of the setting's training episodes from --from-frame on, and the chance of
    drawing each: every seed weighs the same, however many of its episodes are recorded."""
    path = a.results / f"{a.env}_curves.csv"
    with open(path, newline="") as f:
        rows = [
            r
            for r in csv.DictReader(f)
            if (r["model"], r["setting"], r.get("task", "")) == (a.model, a.setting, a.task)
            and int(r["env_step"]) >= a.from_frame
        ]
    if not rows:
        raise SystemExit(
            f"{path} holds no episodes of {a.model}, setting {a.setting!r}, task {a.task} "
            f"from frame {a.from_frame:,}"
        )
    returns = np.array([float(r["normalised_return"]) for r in rows])
    seeds = [r["seed"] for r in rows]
    weights = np.array([1.0 / seeds.count(s) for s in seeds])  # every seed weighs the same
    return returns, weights / weights.sum()


def crossing_chance(
    pool: np.ndarray, weights: np.ndarray, a: Args, shift: float, rng: np.random.Generator
) -> float:
    """Share of drawn runs whose mean over some `window` consecutive episodes reaches the criterion."""
    runs = rng.choice(pool, size=(a.samples, a.episodes), p=weights) + shift
    sums = np.cumsum(np.pad(runs, ((0, 0), (1, 0))), axis=1)
    means = (sums[:, a.window :] - sums[:, : -a.window]) / a.window
    return float((means.max(axis=1) >= a.criterion).mean())


def main(a: Args) -> None:
    if a.episodes < a.window:
        raise SystemExit(f"--episodes ({a.episodes}) must hold at least one window of {a.window}")
    pool, weights = late_episodes(a)
    level = float(weights @ pool)
    rng = np.random.default_rng(a.seed)
    print(
        f"{a.model}, setting {a.setting!r}, {a.task}: {len(pool)} episodes from frame {a.from_frame:,}, "
        f"mean {level:.3f} (each seed weighing the same), std {pool.std():.3f}; "
        f"runs of {a.episodes} episodes drawn {a.samples:,} times"
    )
    print(f"| level | P(a seed reaches {a.criterion}) | P({a.goal_seeds} of {a.goal_seeds}) |")
    print("| --- | --- | --- |")
    for shift in a.shifts:
        p = crossing_chance(pool, weights, a, shift, rng)
        print(f"| {level + shift:.3f} (+{shift:.2f}) | {p:.2f} | {p**a.goal_seeds:.2f} |")


if __name__ == "__main__":
    main(tyro.cli(Args))
