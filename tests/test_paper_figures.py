"""benchmarks/paper_figures.py on synthetic TensorBoard runs whose numbers are known by construction."""

import csv
import importlib
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import tyro
from conftest import ROOT, run_script
from torch.utils.tensorboard import SummaryWriter

sys.path.insert(0, str(ROOT / "benchmarks"))  # the figure script is imported, as a benchmark
import paper_figures as PF  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"


def fake_run(
    folder,
    name,
    returns,
    step_every,
    criterion=None,
    total=None,
    flops_per_step=1e9,
    drops=None,
    pause_at=None,
    resumed_total=None,
    successes=None,
):
    """A run as the agent scripts log it: one normalised return per episode, the criterion step once,
    cumulative FLOPs every 1,000 steps, the settings table, and --eval-only outputs per dropped modality.
    Its clock runs a minute per 1,000 steps, with a 2-hour pause (a resumed run's two parts) at
    ``pause_at`` steps, after which a --resume part with --total-steps ``resumed_total`` logs it; RoboDesk
    runs log ``successes`` (one success count per episode) beside the returns."""
    w = SummaryWriter(folder / name)
    w.add_text("hyperparameters", f"|param|value|\n|-|-|\n|total_steps|{total}|")
    last = step_every * len(returns)

    def clock(k):
        return 1.7e9 + 60 * k / 1000 + (7200 if pause_at is not None and k > pause_at else 0)

    for k in range(0, last + 1, 1000):
        w.add_scalar("charts/train_flops", k * flops_per_step, k, walltime=clock(k))
    for i, r in enumerate(returns, 1):
        w.add_scalar("charts/normalised_return", r, i * step_every, walltime=clock(i * step_every))
        if successes is not None:
            w.add_scalar("charts/success_count", successes[i - 1], i * step_every)
    if criterion is not None:
        w.add_scalar("charts/criterion_step", criterion, criterion)
    if resumed_total is not None:
        w.add_scalar("charts/total_steps", total, 0)
        w.add_scalar("charts/total_steps", resumed_total, pause_at)
    w.close()
    for drop, norm in (drops or {}).items():
        line = f"[eval] drop={drop}: return -1.00 ± 0.50 (s.e.m., 50 episodes), normalised {norm:.3f}\n"
        (folder / name / f"eval_drop_{drop}.txt").write_text(line)


def test_figures_and_table_from_event_files(tmp_path):
    runs = tmp_path / "runs"
    both = {"none": 0.8, "vision": 0.7, "attr": 0.6}
    # GW-Dreamer: criteria at 1,000 and 2,000 steps (FLOPs 1e12 and 2e12); one run that never reaches it
    fake_run(runs, "gw_dreamer_gw_simple_shapes_s1", [0.1] * 9 + [0.8] * 11, 100, 1000, 2000, drops=both)
    fake_run(runs, "gw_dreamer_gw_simple_shapes_s2", [0.2] * 20, 100, 2000, 2000, drops=both | {"none": 0.9})
    fake_run(runs, "gw_dreamer_gw_simple_shapes_s3", [0.0] * 20, 100, None, 2000)
    fake_run(runs, "ppo_gw_simple_shapes_s1", [0.5] * 30, 100, None, 30000)  # cut: 3,000 of 30,000 steps
    # 20,000 steps in 20 minutes of training, in two parts 2 hours apart
    fake_run(runs, "ppo_vae_simple_shapes_s1", [0.5] * 20, 1000, None, 20000, pause_at=10000)
    fake_run(runs, "someone_elses_run_s1", [1.0] * 20, 100, 100, 2000)  # not a known model: ignored
    out, res = tmp_path / "fig", tmp_path / "res"
    cmd = ["--runs", str(runs), "--out", str(out), "--export", str(res), "--caption", "test machine"]
    printed = run_script("benchmarks/paper_figures.py", tmp_path, *cmd)
    for png in ("simple_shapes_curves.png", "simple_shapes_ablation.png", "gw_figure2.png"):
        data = (out / png).read_bytes()
        assert data.startswith(PNG) and len(data) > 5_000, png
    table = (out / "simple_shapes_flops.md").read_text()
    assert "| GW-Dreamer | 2 / 3 | 1,500 ± 500 | 1.50e+12 ± 5.0e+11 | ≈ 20,000 |" in table
    assert (
        "GW-PPO" not in table.split("Cut short")[0] and "GW-PPO seed 1" in table
    )  # cut: listed, not counted
    # the paper's own criterion: 75% of the highest smoothed return (seed 1's 0.8), reached by seed 1
    # when 7 of its last 10 episodes score 0.8 (0.1 + 0.07 x 7 >= 0.6): the 17th episode, 1,700 steps
    assert "(0.80): 0.60" in table and "| GW-Dreamer | 1 / 3 | 1,700 |" in table
    assert "| VAE-PPO | 0 / 1 | – |" in table and "| GW-PPO | 0" not in table  # cut runs left out
    body = table.split("\n", 4)[4]  # the table under its title and source line
    assert "someone" not in table and body.strip() in printed
    with open(res / "simple_shapes_runs.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    status = {(r["model"], r["seed"]): r["status"] for r in rows}
    assert status == {("GW-Dreamer", "1"): "reached", ("GW-Dreamer", "2"): "reached"} | {
        ("GW-Dreamer", "3"): "not reached",
        ("GW-PPO", "1"): "cut",
        ("VAE-PPO", "1"): "not reached",
    }
    minutes = {(r["model"], r["seed"]): r["wall_min"] for r in rows}
    assert minutes[("VAE-PPO", "1")] == "20.0" and minutes[("GW-PPO", "1")] == "3.0"  # the pause left out
    with open(res / "simple_shapes_ablation.csv", newline="") as f:
        ablation = {(r["seed"], r["drop"]): float(r["normalised_return"]) for r in csv.DictReader(f)}
    assert ablation == {(s, d): v for s in "12" for d, v in both.items()} | {("2", "none"): 0.9}
    # The committed records give the same table when read back
    again = [
        "--results",
        str(res),
        "--out",
        str(tmp_path / "b"),
        "--gw-checkpoint",
        "",
        "--caption",
        "test machine",
    ]
    again = run_script("benchmarks/paper_figures.py", tmp_path, *again)
    assert (tmp_path / "b" / "simple_shapes_flops.md").read_text().split("\n", 3)[3] == table.split("\n", 3)[
        3
    ]
    assert "1,500 ± 500" in again


def test_robodesk_figures_carry_the_task_and_the_70_percent_criterion(tmp_path):
    runs = tmp_path / "runs"
    drops = {"none": 0.75, "vision": 0.7, "attr": 0.65}
    # criterion at 30,000 frames (3e13 FLOPs); one seed not reached; a Simple Shapes run is not RoboDesk's
    counts = list(range(0, 300, 10))
    push = "gw_dreamer_gw_robodesk_push_green"
    fake_run(runs, f"{push}_s1", [0.1] * 15 + [0.8] * 15, 2000, 30000, 60000, drops=drops, successes=counts)
    fake_run(runs, "gw_dreamer_gw_robodesk_push_green_s2", [0.3] * 30, 2000, None, 60000)
    fake_run(runs, "gw_dreamer_gw_simple_shapes_s1", [0.9] * 20, 100, 1000, 2000)
    out, res = tmp_path / "fig", tmp_path / "res"
    cmd = ["--env", "robodesk", "--runs", str(runs), "--out", str(out), "--export", str(res)]
    printed = run_script("benchmarks/paper_figures.py", tmp_path, *cmd, "--caption", "test machine")
    for png in ("robodesk_curves.png", "robodesk_ablation.png"):
        assert (out / png).read_bytes().startswith(PNG), png
    assert not (out / "gw_figure2.png").exists()  # Figure 2 is Simple Shapes'
    assert "| GW-Dreamer | 1 / 2 | 30,000 | 3.00e+13 | ≈ 200,000 |" in printed
    # the paper's 70% of the highest smoothed return (0.8): 0.56, at the 22nd episode (0.1 + 0.07 x 7)
    assert "70% of the highest smoothed return" in printed and "| GW-Dreamer | 1 / 2 | 44,000 |" in printed
    with open(res / "robodesk_runs.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["seed"], r["task"], r["status"]) for r in rows] == [
        ("1", "push_green", "reached"),
        ("2", "push_green", "not reached"),
    ]
    with open(res / "robodesk_ablation.csv", newline="") as f:
        assert {r["drop"]: (r["task"], float(r["normalised_return"])) for r in csv.DictReader(f)} == {
            d: ("push_green", v) for d, v in drops.items()
        }
    with open(res / "robodesk_curves.csv", newline="") as f:
        curves = list(csv.DictReader(f))
    assert list(curves[0]) == [
        "model",
        "setting",
        "seed",
        "task",
        "env_step",
        "normalised_return",
        "success_count",
    ]
    # each episode's success count at its step; a run that logged none has an empty column
    assert [int(r["success_count"]) for r in curves if r["seed"] == "1"] == counts
    assert {r["success_count"] for r in curves if r["seed"] == "2"} == {""}
    again = run_script(
        "benchmarks/paper_figures.py", tmp_path, "--env", "robodesk", "--results", str(res), "--out", str(out)
    )
    assert "| GW-Dreamer | 1 / 2 | 30,000 | 3.00e+13 | ≈ 200,000 |" in again


def test_robodesk_tasks_the_gw_saw_and_did_not_and_the_papers_flops_table(tmp_path):
    runs = tmp_path / "runs"
    push = "gw_dreamer_gw_robodesk_push_green"
    n30 = [100] * 30
    fake_run(runs, f"{push}_s1", [0.1] * 15 + [0.8] * 15, 2000, 30000, 60000, successes=n30)  # 3e13 FLOPs
    fake_run(runs, f"{push}_s2", [0.3] * 30, 2000, None, 60000, successes=n30)
    fake_run(runs, "gw_dreamer_gw_robodesk_open_slide_s1", [0.9] * 30, 2000, 40000, 60000, successes=n30)
    fake_run(runs, "gw_dreamer_gw_robodesk_push_red_s1", [0.2] * 30, 2000, None, 60000, successes=n30)
    # a seen task whose run logged no success count gets no panel (Figures 6 and 7 plot success counts)
    fake_run(runs, "gw_dreamer_gw_robodesk_open_drawer_s1", [0.9] * 30, 2000, 40000, 60000)
    fake_run(runs, "dreamer_raw_2m_robodesk_push_green_s1", [0.9] * 60, 2000, 100000, 120000)
    # resumed with its --total-steps lowered from 800,000 to the 60,000 it ran: run in full, not reached;
    # the same run without the resumed part's record stopped far before its 800,000: cut
    dreamer = "dreamer_raw_2m_robodesk_push_green"
    fake_run(runs, f"{dreamer}_s2", [0.1] * 30, 2000, None, 800000, pause_at=30000, resumed_total=60000)
    fake_run(runs, f"{dreamer}_s3", [0.1] * 30, 2000, None, 800000, pause_at=30000)
    out = tmp_path / "fig"
    printed = run_script(
        "benchmarks/paper_figures.py", tmp_path, "--env", "robodesk", "--runs", str(runs), "--out", str(out)
    )
    # Figure 3's table is push_green's alone: the other tasks' runs do not enter it
    assert "| GW-Dreamer | 1 / 2 | 30,000 | 3.00e+13 | ≈ 200,000 |" in printed
    assert "| Dreamer | 1 / 2 | 100,000 | 1.00e+14 | ≈ 800,000 |" in printed
    assert "Cut short, not counted: Dreamer seed 3." in printed
    # the paper's relative criterion over all models: 70% of Dreamer's 0.9, reached by GW-Dreamer at its
    # 23rd episode (0.1 + 0.07 x 8 >= 0.63), by Dreamer at its 10th
    assert "(0.90): 0.63" in printed and "| GW-Dreamer | 1 / 2 | 46,000 |" in printed
    assert "| Dreamer | 1 / 2 | 20,000 |" in printed
    for png in ("robodesk_tasks_seen.png", "robodesk_tasks_unseen.png"):
        assert (out / png).read_bytes().startswith(PNG), png
    assert "task panels of open_slide, push_green, push_red;" in printed
    pre = PF.pretraining_flops(ROOT / "envs/pretrained/robodesk")
    assert PF.gw_tasks(ROOT / "envs/pretrained/robodesk") == [
        "flat_block_in_bin",
        "open_drawer",
        "open_slide",
        "push_green",
        "upright_block_off_table",
    ]
    assert (
        "| RL 1 task (push_green) | RL 5 tasks the GW saw | RL tasks it did not see (push_red) |" in printed
    )
    assert (
        f"| GW-Dreamer | {pre['VAE']:.3e} | {pre['GW']:.3e} | 3.000e+13 (1 / 2 seeds)"
        " | 1.100e+14 (3 of 5 tasks reached: open_drawer, open_slide, push_green)"
        " | not reached (0 of 1 tasks reached: none; not reached: push_red) |"
    ) in printed
    assert (
        "| Dreamer | N/A | N/A | 1.000e+14 (1 / 2 seeds) | 1.000e+14 (1 of 5 tasks reached: push_green) | X |"
        in (printed)
    )


def test_pretraining_flops_follow_the_recipe_of_the_checkpoints(tmp_path):
    bundle = ROOT / "envs/pretrained/robodesk"
    vae, gw = (torch.load(bundle / f, map_location="cpu", weights_only=False) for f in ("vae.pt", "gw.pt"))
    base = PF.pretraining_flops(bundle)

    def with_recipe(vae_args=None, gw_args=None, n_samples=None) -> dict:
        folder = tmp_path / str(len(list(tmp_path.iterdir())))
        folder.mkdir()
        torch.save(vae | {"args": vae["args"] | (vae_args or {})}, folder / "vae.pt")
        data = gw["data"] | ({"n_samples": n_samples} if n_samples else {})
        torch.save(gw | {"args": gw["args"] | (gw_args or {}), "data": data}, folder / "gw.pt")
        return PF.pretraining_flops(folder)

    twice = with_recipe(vae_args={"vae_steps": 2 * vae["args"]["vae_steps"]})
    assert twice["VAE"] == 2 * base["VAE"] and twice["GW"] == base["GW"]
    no_gw_steps = with_recipe(gw_args={"gw_steps": 0})
    encode = no_gw_steps["GW"]  # what is left: encoding the GW's data through the frozen VAEs, once
    assert 0 < encode < base["GW"] and no_gw_steps["VAE"] == base["VAE"]
    assert with_recipe(gw_args={"gw_steps": 0}, n_samples=2 * gw["data"]["n_samples"])["GW"] == 2 * encode
    more_gw = with_recipe(gw_args={"gw_batch_size": 2 * gw["args"]["gw_batch_size"]})["GW"]
    assert more_gw - encode == pytest.approx(2 * (base["GW"] - encode))
    # a wider visual VAE costs more per sample
    assert with_recipe(vae_args={"vae_width": 2 * vae["args"]["vae_width"]})["VAE"] > 2 * base["VAE"]


def test_the_smoothing_is_the_criterions(tmp_path):
    steps = np.arange(1, 21) * 100.0
    rets = np.r_[np.zeros(10), np.ones(10)]
    y = PF.smoothed_on_grid(steps, rets, np.array([50.0, 900.0, 1000.0, 1500.0, 2000.0, 5000.0]))
    assert np.isnan(y[0]) and np.isnan(y[1])  # before the 10th episode
    assert y[2:].tolist() == [0.0, 0.5, 1.0, 1.0]  # mean of the last 10; held after the run's end


def test_a_seed_cut_more_than_once_is_listed_once_with_its_count():
    def run(seed, status, step=""):
        row = dict(model="Dreamer", setting="default", seed=str(seed), status=status, criterion_step=step)
        return row | dict(rl_train_flops="1e14" if step else "")

    runs = [run(2, "cut"), run(3, "cut"), run(2, "cut"), run(2, "reached", "50000")] + [run(4, "cut")] * 3
    table = PF.flops_table(runs, "default", "robodesk")
    cut = "Dreamer seed 2 (twice, then run in full), Dreamer seed 3, Dreamer seed 4 (3 times)."
    assert "Cut short, not counted: " + cut in table
    assert "| Dreamer | 1 / 1 | 50,000 |" in table


def test_the_reproduction_script_runs_valid_commands_only(tmp_path):
    """Its dry run prints every command; each must parse with its script's own flags (tyro), and the dry
    run writes nothing."""
    script = ROOT / "benchmarks" / "reproduce_simple_shapes.sh"
    env = {"DRY_RUN": "1", "PATH": "/usr/bin:/bin"}
    out = subprocess.run(["bash", str(script), "2"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    commands = [shlex.split(line) for line in out.stdout.splitlines()]
    scripts = [Path(c[1]).name for c in commands]
    assert scripts.count("gw_dreamer.py") == 2 * 2 * 4  # two models x two seeds x (train + 3 ablations)
    for s in ("gw_dreamer_e2e.py", "dreamer_baseline.py", "ppo_variants.py", "pretrain_vae_gw.py"):
        assert s in scripts, s
    assert scripts[-1] == "paper_figures.py"
    for c in commands:
        module = importlib.import_module(Path(c[1]).stem)
        tyro.cli(module.Args, args=c[2:])  # exits (SystemExit 2) on a flag the script does not have
    assert list(tmp_path.iterdir()) == []


def test_the_robodesk_reproduction_script_runs_valid_commands_only(tmp_path):
    """Its dry run prints the pre-training (PRETRAIN=1), each seed's training and its three ablations,
    then the figures; every command parses with its script's own flags, and the dry run writes nothing."""
    script = ROOT / "benchmarks" / "reproduce_robodesk.sh"
    env = {"DRY_RUN": "1", "PRETRAIN": "1", "PATH": "/usr/bin:/bin"}
    out = subprocess.run(["bash", str(script), "2"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    commands = [shlex.split(line) for line in out.stdout.splitlines()]
    scripts = [Path(c[1]).name for c in commands]
    assert scripts == ["pretrain_vae_gw.py", *["gw_dreamer.py"] * 8, "paper_figures.py"]
    drops = [c[c.index("--drop") + 1] for c in commands if "--drop" in c]
    assert drops == ["none", "vision", "attr"] * 2
    for c in commands:
        args = tyro.cli(importlib.import_module(Path(c[1]).stem).Args, args=c[2:])
        assert args.env == "robodesk"
        assert getattr(args, "cpu_preset", True)
    assert list(tmp_path.iterdir()) == []
    # MODELS adds the baselines, each at its --cpu-preset (the Dreamers: 2M on fast images)
    env |= {"MODELS": "gw e2e dreamer vae_dreamer", "PRETRAIN": "0"}
    out = subprocess.run(["bash", str(script), "1"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    commands = [shlex.split(line) for line in out.stdout.splitlines()]
    scripts = [Path(c[1]).name for c in commands]
    assert scripts == [
        *["gw_dreamer.py"] * 4,
        *["gw_dreamer_e2e.py"] * 4,
        *["dreamer_baseline.py"] * 8,
        scripts[-1],
    ]
    D = importlib.import_module("dreamer_baseline")
    dreamers = [
        tyro.cli(D.Args, args=c[2:]).resolve() for c in commands if c[1].endswith("dreamer_baseline.py")
    ]
    assert [a.obs for a in dreamers] == ["raw"] * 4 + ["vae"] * 4
    assert {(a.size, a.cpu_preset, a.total_steps) for a in dreamers} == {("2m", True, 800_000)}
    # TASKS runs each model on each task; PPO to its 1,000,000 frames, raw PPO on the GW data's fast images
    env |= {"MODELS": "gw gw_ppo ppo", "TASKS": "push_green push_red"}
    out = subprocess.run(["bash", str(script), "1"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    trains = [shlex.split(line) for line in out.stdout.splitlines() if "--stop-at-criterion" in line]
    parsed = [tyro.cli(importlib.import_module(Path(c[1]).stem).Args, args=c[2:]) for c in trains]
    assert [(Path(c[1]).name, a.task) for c, a in zip(trains, parsed, strict=True)] == [
        (script, task)
        for script in ("gw_dreamer.py", *["ppo_variants.py"] * 2)
        for task in ("push_green", "push_red")
    ]
    ppo = parsed[2:]
    assert [(a.variant, a.render_quality, a.total_steps) for a in ppo] == [("gw", None, 1_000_000)] * 2 + [
        ("raw", "fast", 1_000_000)
    ] * 2
    assert list(tmp_path.iterdir()) == []
    bad = subprocess.run(
        ["bash", str(script), "1"], cwd=tmp_path, capture_output=True, text=True, env=env | {"MODELS": "sac"}
    )
    assert bad.returncode != 0 and "unknown model sac" in bad.stderr


FAKE_PYTHON = r"""#!/bin/bash
# Stands in for python: records its arguments; a seed's training behaves as the test's scenario says.
echo "$*" >> "$CALLS"
case "$*" in
  *--eval-only*) echo "[eval] normalised return 0.5"; exit 0 ;;
  *paper_figures.py*) exit 0 ;;
esac
case "$*" in
  *"--seed 1 "*) exit 0 ;;  # trains to its end in the first call
  *"--seed 2 "*--resume*) echo "error: --resume: there is no checkpoint x.pt to continue" >&2; exit 2 ;;
  *"--seed 2 "*--overwrite*) exit 0 ;;
  *"--seed 3 "*--resume*) exit 0 ;;
esac
exit 137  # seeds 2 and 3 are killed in the first call (seed 2 before its first save)
"""


def test_a_stopped_reproduction_continues_with_resume(tmp_path):
    """RESUME=1 runs no finished step again, continues a cut training from its save (--resume), starts
    again one that had no save (--overwrite), evaluates only finished trainings and redraws the figures;
    without it an existing reproduction is refused."""
    bin_dir, work, calls = tmp_path / "bin", tmp_path / "work", tmp_path / "calls.txt"
    bin_dir.mkdir(), work.mkdir()
    (bin_dir / "python").write_text(FAKE_PYTHON)
    (bin_dir / "python").chmod(0o755)
    script = str(ROOT / "benchmarks" / "reproduce_robodesk.sh")
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "CALLS": str(calls), "JOBS": "1", "OUT": "out"}

    def reproduce(**extra):
        calls.write_text("")
        out = subprocess.run(["bash", script, "3"], cwd=work, capture_output=True, text=True, env=env | extra)
        made = [line.split() for line in calls.read_text().splitlines()]
        return out, [(c[c.index("--seed") + 1] if "--seed" in c else "figures", c[-1]) for c in made]

    out, made = reproduce()
    assert out.returncode == 0, out.stderr
    assert made == [
        ("1", "--stop-at-criterion"),
        *[("1", "10")] * 3,  # its three ablations
        ("2", "--stop-at-criterion"),
        ("3", "--stop-at-criterion"),
        ("figures", "figures"),
    ]
    assert "failed (exit 137)" in out.stdout
    refused, made = reproduce()
    assert refused.returncode == 2 and "RESUME=1" in refused.stderr and made == []
    out, made = reproduce(RESUME="1")
    assert out.returncode == 0, out.stderr
    assert made == [
        ("2", "--resume"),
        ("2", "--overwrite"),
        *[("2", "10")] * 3,
        ("3", "--resume"),
        *[("3", "10")] * 3,
        ("figures", "figures"),
    ]
    out, made = reproduce(RESUME="1")
    assert made == [("figures", "figures")] and "failed" not in out.stdout
    missing = subprocess.run(
        ["bash", script], cwd=work, capture_output=True, text=True, env=env | {"OUT": "x", "RESUME": "1"}
    )
    assert missing.returncode == 2 and "no reproduction to continue" in missing.stderr


def test_robodesk_task_panels_plot_the_smoothed_success_count():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # seed 1: 0 then 500 successes; seed 2: always 100; seed 3 recorded no success counts (older records)
    def rows(seed, counts):
        return [
            dict(
                model="GW-Dreamer",
                setting="default",
                seed=str(seed),
                task="open_slide",
                env_step=str(2000 * i),
            )
            | dict(normalised_return="0.5", success_count=c)
            for i, c in enumerate(counts, 1)
        ]

    curves = rows(1, ["0"] * 10 + ["500"] * 10) + rows(2, ["100"] * 20) + rows(3, [""] * 20)
    runs = [
        dict(model="GW-Dreamer", setting="default", seed=str(s), task="open_slide", status="not reached")
        for s in (1, 2, 3)
    ]
    fig, ax = plt.subplots()
    assert PF.draw_curves(ax, curves, runs, "default", "robodesk", column="success_count") == ["GW-Dreamer"]
    (line,) = ax.get_lines()  # no criterion line: the criterion is a normalised return
    assert line.get_label() == "GW-Dreamer (0/3 reached, 2 drawn)"
    x, y = line.get_data()
    # the mean over seeds 1 and 2 of their 10-episode means: 50 from the 10th episode (20,000 frames) on,
    # 300 at the 20th (40,000), in between as seed 1's window fills with 500s
    assert x[0] >= 20000 and y[x < 22000].tolist() == [50.0] * int((x < 22000).sum())
    assert x[-1] == 40000 and y[-1] == 300.0 and np.all(np.diff(y) >= 0)
    plt.close(fig)
