"""benchmarks/criterion_chance.py on records whose crossing chances are known by hand."""

import csv
import sys

import numpy as np
import pytest
from conftest import ROOT, run_script

sys.path.insert(0, str(ROOT / "benchmarks"))  # the script is imported, as a benchmark
import criterion_chance as CC  # noqa: E402

FIELDS = ["model", "setting", "seed", "task", "env_step", "normalised_return", "success_count"]


def write_curves(folder, episodes):
    """robodesk_curves.csv holding ``episodes``: (seed, env_step, normalised return) of GW-Dreamer."""
    with open(folder / "robodesk_curves.csv", "w", newline="") as f:
        w = csv.writer(f, lineterminator="\r\n")
        w.writerow(FIELDS)
        for seed, step, ret in episodes:
            w.writerow(["GW-Dreamer", "default", seed, "push_green", step, ret, 0])


def chance(folder, **kw):
    a = CC.Args(results=folder, samples=40_000, **kw)
    pool, weights = CC.late_episodes(a)
    return CC.crossing_chance(pool, weights, a, 0.0, np.random.default_rng(0))


def test_every_seed_weighs_the_same_and_early_episodes_are_left_out(tmp_path):
    # Seed 1: one late episode at 0.9; seed 2: three at 0.5; an early 0.9 of seed 2 is before --from-frame.
    # A one-episode run reaches 0.7 with chance 1/2 (each seed's episodes drawn half the time), not 1/4.
    write_curves(
        tmp_path, [(1, 90_000, 0.9), (2, 2_000, 0.9), (2, 90_000, 0.5), (2, 92_000, 0.5), (2, 94_000, 0.5)]
    )
    assert chance(tmp_path, episodes=1, window=1) == pytest.approx(0.5, abs=0.01)


def test_the_smoothed_return_is_a_sliding_window(tmp_path):
    # Episodes 0.5 or 1.0, equally likely. Window 2 over 2 episodes: a mean >= 0.7 unless both are 0.5,
    # 3/4. Over 3 episodes the two windows both fail only if all three are 0.5: 7/8.
    write_curves(tmp_path, [(1, 90_000, 0.5), (1, 92_000, 1.0)])
    assert chance(tmp_path, episodes=2, window=2) == pytest.approx(0.75, abs=0.01)
    assert chance(tmp_path, episodes=3, window=2) == pytest.approx(0.875, abs=0.01)


def test_the_cli_prints_the_chance_per_level_and_for_all_seeds(tmp_path):
    # One recorded episode at 0.65: below 0.70 unshifted, above it shifted by 0.1; 2 seeds square it.
    write_curves(tmp_path, [(1, 90_000, 0.65)])
    out = run_script(
        "benchmarks/criterion_chance.py",
        tmp_path,
        "--results",
        str(tmp_path),
        "--shifts",
        "0",
        "0.1",
        "--goal-seeds",
        "2",
        "--samples",
        "100",
    )
    assert "| 0.650 (+0.00) | 0.00 | 0.00 |" in out
    assert "| 0.750 (+0.10) | 1.00 | 1.00 |" in out
    missing = CC.Args(results=tmp_path, setting="another")
    with pytest.raises(SystemExit, match="holds no episodes"):
        CC.late_episodes(missing)
