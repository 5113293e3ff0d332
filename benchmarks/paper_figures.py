"""The paper's figures and FLOPs table of one environment, drawn from recorded runs.

    python benchmarks/paper_figures.py                       # from the records in docs/results/
    python benchmarks/paper_figures.py --runs runs --export docs/results   # from TensorBoard runs
    python benchmarks/paper_figures.py --env robodesk        # RoboDesk (Figures 3 and 5, right)

Writes to --out (docs/figures/), <env> being simple_shapes or robodesk:
- <env>_curves.png: normalised return of every model, smoothed over 10 episodes, mean ± s.e.m.
  over seeds, on log-scaled env steps, with the criterion line (the paper's Figure 3);
- <env>_ablation.png: normalised return with both modalities, without vision, without
  attributes, mean ± s.e.m. over agents (Figure 5);
- <env>_flops.md: env steps and RL training FLOPs to the criterion per model, env steps to the paper's
  own criterion (a share of the highest smoothed return any run reached); on RoboDesk also the
  paper's FLOPs table (VAE, GW, RL on push_green, on the tasks the GW saw, on the tasks it did not);
- robodesk_tasks_seen.png, robodesk_tasks_unseen.png: one panel per task, the success count (steps of
  the 500 in which the task's success criterion held) smoothed over 10 episodes (Figures 6 and 7), drawn
  when the records hold runs on those tasks with success counts;
- gw_figure2.png (Simple Shapes): the GW grid of Figure 2 (image, image of the attributes, translation,
  demi-cycle, fusion) from a Simple Shapes GW checkpoint (the bundled one by default).

Runs are recognised by the default run names of the agent scripts (runs/<name>_s<seed>, e.g.
gw_dreamer_gw_simple_shapes_s3, gw_dreamer_gw_robodesk_push_green_s1); a run's modality ablation is read
from runs/<run>/eval_drop_<drop>.txt, the `[eval]` line of `--eval-only --drop <drop>`
(benchmarks/reproduce_simple_shapes.sh writes them). RoboDesk records carry the task of each run:
Figures 3 and 5 are push_green's, and the tasks the GW saw are those of its data record.
"""

import csv
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# smoothed normalised return at the criterion: Simple Shapes 0.75, RoboDesk the paper's 70%
CRITERION = {"simple_shapes": 0.75, "robodesk": 0.70}
# RoboDesk's single task of Figures 3 and 5 and of the FLOPs table's "RL 1 task" column
MAIN_TASK = {"simple_shapes": "", "robodesk": "push_green"}
TITLE = {"simple_shapes": "Simple Shapes", "robodesk": "RoboDesk"}
SMOOTH = 10  # episodes
# label, the run name's model part (before _<env>), the paper's steps to the criterion (Figure 3, read off
# the plot; RoboDesk in frames: GW-Dreamer about 200,000, "4x faster than other Dreamer variants",
# the end-to-end model 150,000, from the text)
MODEL_TABLE = (
    ("GW-Dreamer", "gw_dreamer_gw", "≈ 20,000", "≈ 200,000"),
    ("GW-Dreamer end-to-end", "gw_dreamer_e2e_gw", "≈ 50,000", "≈ 150,000"),
    ("CLIP-Dreamer", "gw_dreamer_clip", "fails", "–"),
    ("Dreamer", "dreamer_raw_2m", "≈ 200,000", "≈ 800,000"),
    ("VAE-Dreamer", "dreamer_vae_2m", "≈ 200,000", "≈ 800,000"),
    ("GW-PPO", "ppo_gw", "≈ 200,000", "–"),
    ("VAE-PPO", "ppo_vae", "≈ 400,000", "–"),
    ("CLIP-PPO", "ppo_clip", "fails", "–"),
    ("PPO", "ppo_raw", "≈ 300,000", "–"),
)


def models(env: str) -> list[tuple[str, str, str]]:
    """(label, default run name without seed and task, paper's steps to the criterion) for ``env``."""
    col = 2 if env == "simple_shapes" else 3
    return [(m[0], f"{m[1]}_{env}", m[col]) for m in MODEL_TABLE]


DROPS = {"none": "both", "vision": "without vision", "attr": "without attributes"}
RUN_FIELDS = (
    "model setting seed status criterion_step env_steps_run rl_train_flops wall_min command note".split()
)
CURVE_FIELDS = "model setting seed env_step normalised_return".split()
ABLATION_FIELDS = "model setting seed drop episodes return_mean return_sem normalised_return command".split()


def fields(kind: str, env: str) -> list[str]:
    """Columns of a record file: RoboDesk's add the task after the seed, and its curves each episode's
    success count (steps of the 500 in which the task's success criterion held; Figures 6 and 7)."""
    cols = {"runs": RUN_FIELDS, "curves": CURVE_FIELDS, "ablation": ABLATION_FIELDS}[kind]
    if env == "simple_shapes":
        return cols
    return [*cols[:3], "task", *cols[3:]] + (["success_count"] if kind == "curves" else [])


EVAL_LINE = re.compile(
    r"\[eval\] drop=(\w+): return (-?[\d.]+) ± ([\d.]+) \(s\.e\.m\., (\d+) episodes\), normalised (-?[\d.]+)"
)


@dataclass
class Args:
    env: str = "simple_shapes"
    """environment of the figures: simple_shapes or robodesk"""
    results: str = "docs/results"
    """folder of the committed records (<env>_{runs,curves,ablation}.csv), read unless --runs"""
    runs: str | None = None
    """read TensorBoard runs from this folder instead of --results"""
    export: str | None = None
    """also write the records the figures are drawn from (CSV) to this folder"""
    out: str = "docs/figures"
    """where the figures and the table go"""
    setting: str = "default"
    """which setting of the records to draw (the default command's runs)"""
    gw_checkpoint: str = "envs/pretrained/simple_shapes/gw.pt"
    """Simple Shapes GW of Figure 2 ('' skips it)"""
    vae_checkpoint: str = "envs/pretrained/simple_shapes/vae.pt"
    """VAEs of that GW"""
    caption: str = ""
    """hardware, torch version and date printed under every figure (default: torch version only)"""
    pretrained: str = "envs/pretrained/robodesk"
    """RoboDesk VAEs and GW of the agents: the FLOPs table's VAE and GW columns and the tasks they saw"""


# --------------------------------------------------------------------------------------------------
# Records: from the CSVs, or from TensorBoard event files
# --------------------------------------------------------------------------------------------------
def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def write_csv(path: Path, rows: list[dict], fields: list[str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fields)
        w.writeheader()
        w.writerows({k: r.get(k, "") for k in fields} for r in rows)
    tmp.replace(path)


def model_of(run_name: str, env: str = "simple_shapes") -> tuple[str, int, str] | None:
    """(model, seed, task) of a default run name; the task is "" on Simple Shapes."""
    task = "" if env == "simple_shapes" else r"_(?P<task>[a-z_]+?)"
    for label, name, _ in models(env):
        m = re.fullmatch(re.escape(name) + task + r"_s(?P<seed>\d+)", run_name)
        if m:
            return label, int(m.group("seed")), m.groupdict().get("task") or ""
    return None


def running_minutes(walls: list[float]) -> float:
    """Minutes a run trained, from the wall times of its events: a gap over 3 times the median spacing is
    a pause between two parts of a resumed run and counts as one median spacing."""
    gaps = np.diff(np.sort(walls))
    if gaps.size == 0:
        return 0.0
    typical = float(np.median(gaps))
    return float(np.where(gaps > 3 * typical, typical, gaps).sum()) / 60


def read_runs(folder: Path, env: str = "simple_shapes") -> tuple[list[dict], list[dict], list[dict]]:
    """(runs, curves, ablation) records of every recognised run of ``env`` under ``folder``."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    runs, curves, ablation = [], [], []
    for run in sorted(p for p in folder.iterdir() if p.is_dir()):
        known = model_of(run.name, env)
        if known is None:
            continue
        model, seed, task = known
        tag = {"task": task} if env != "simple_shapes" else {}
        acc = EventAccumulator(str(run), size_guidance={"scalars": 0, "tensors": 0}).Reload()
        tags = acc.Tags()["scalars"]
        if "charts/normalised_return" not in tags:
            continue
        episodes = acc.Scalars("charts/normalised_return")
        success = {}  # RoboDesk: logged with every training episode, at its step
        if "charts/success_count" in tags:
            success = {e.step: f"{e.value:g}" for e in acc.Scalars("charts/success_count")}
        curves += [
            dict(model=model, setting="default", seed=seed, env_step=e.step)
            | tag
            | dict(normalised_return=f"{e.value:.4f}")
            | ({"success_count": success.get(e.step, "")} if success else {})
            for e in episodes
        ]
        crit = acc.Scalars("charts/criterion_step")[0].step if "charts/criterion_step" in tags else None
        flops = ""
        if "charts/train_flops" in tags:
            f = acc.Scalars("charts/train_flops")
            at = crit if crit is not None else f[-1].step  # FLOPs are logged per interval: interpolate
            flops = f"{np.interp(at, [e.step for e in f], [e.value for e in f]):.4g}"
        hyper = ""
        if "hyperparameters/text_summary" in acc.Tags()["tensors"]:
            hyper = acc.Tensors("hyperparameters/text_summary")[0].tensor_proto.string_val[0].decode()
        total = re.search(r"\|total_steps\|(\d+)\|", hyper)
        total = int(total.group(1)) if total else None
        if "charts/total_steps" in tags:  # logged by every part of a run: the last part's --total-steps
            total = int(acc.Scalars("charts/total_steps")[-1].value)
        last = max(e.step for e in episodes)
        status = "reached" if crit is not None else "not reached"
        if crit is None and total and last < total * 0.95:
            status = "cut"  # stopped well before its --total-steps (PPO ends at whole rollouts)
        clock = acc.Scalars(
            "charts/train_flops" if "charts/train_flops" in tags else "charts/normalised_return"
        )
        wall_min = f"{running_minutes([e.wall_time for e in clock]):.1f}"
        runs.append(
            dict(model=model, setting="default", seed=seed, status=status, criterion_step=crit or "")
            | tag
            | dict(env_steps_run=last, rl_train_flops=flops, wall_min=wall_min, command=f"runs/{run.name}")
        )
        for txt in sorted(run.glob("eval_drop_*.txt")):
            m = EVAL_LINE.search(txt.read_text())
            if m:
                drop, mean, sem, n, norm = m.groups()
                ablation.append(
                    dict(model=model, setting="default", seed=seed, drop=drop, episodes=n)
                    | tag
                    | dict(return_mean=mean, return_sem=sem, normalised_return=norm)
                    | dict(command=f"runs/{run.name}/{txt.name}")
                )
    return runs, curves, ablation


# --------------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------------
def mean_sem(values) -> tuple[float, float]:
    v = np.asarray(list(values), dtype=float)
    sem = v.std(ddof=1) / math.sqrt(len(v)) if len(v) > 1 else float("nan")
    return float(v.mean()), float(sem)


def smoothed(steps: np.ndarray, returns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The episodes' end steps in order and the 10-episode moving average (the criterion's smoothing) at
    each of them, nan before the 10th episode."""
    order = np.argsort(steps)
    steps, returns = steps[order], returns[order]
    csum = np.cumsum(np.insert(returns, 0, 0.0))
    n = np.arange(1, len(returns) + 1)
    k = np.minimum(n, SMOOTH)
    smooth = (csum[n] - csum[n - k]) / k
    smooth[: SMOOTH - 1] = np.nan
    return steps, smooth


def smoothed_on_grid(steps: np.ndarray, returns: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """The smoothed return at each grid step: the value of the last episode that ended at or before it
    (nan before the 10th episode); a run that stopped (at its criterion or its --total-steps) keeps its
    last value."""
    steps, smooth = smoothed(steps, returns)
    idx = np.searchsorted(steps, grid, side="right") - 1
    return np.where(idx >= 0, smooth[np.clip(idx, 0, None)], np.nan)


def flops_table(runs: list[dict], setting: str, env: str = "simple_shapes") -> str:
    lines = [
        "| model | reached / run | env steps to the criterion (mean ± s.e.m.)"
        " | RL training FLOPs to the criterion (mean ± s.e.m.) | paper (steps) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for label, _, paper in models(env):
        rows = [r for r in runs if r["model"] == label and r["setting"] == setting and r["status"] != "cut"]
        if not rows:
            continue
        hit = [r for r in rows if r["status"] == "reached"]
        steps = flops = "–"
        if hit:
            m, s = mean_sem(int(float(r["criterion_step"])) for r in hit)
            steps = f"{m:,.0f}" + (f" ± {s:,.0f}" if len(hit) > 1 else "")
            f_hit = [float(r["rl_train_flops"]) for r in hit if r["rl_train_flops"]]
            if f_hit:
                fm, fs = mean_sem(f_hit)
                flops = f"{fm:.2e}" + (f" ± {fs:.1e}" if len(f_hit) > 1 else "")
                flops += f" (n = {len(f_hit)})" if len(f_hit) < len(hit) else ""
        lines.append(f"| {label} | {len(hit)} / {len(rows)} | {steps} | {flops} | {paper} |")
    mine = [r for r in runs if r["setting"] == setting]
    finished = {(r["model"], r["seed"]) for r in mine if r["status"] != "cut"}
    cuts: dict[tuple[str, str], int] = {}  # each cut seed once, in the records' order, with its count
    for r in mine:
        if r["status"] == "cut":
            cuts[r["model"], r["seed"]] = cuts.get((r["model"], r["seed"]), 0) + 1
    cut = []
    for (model, seed), n in cuts.items():
        notes = ([{2: "twice"}.get(n, f"{n} times")] if n > 1 else []) + (
            ["then run in full"] if (model, seed) in finished else []
        )
        cut.append(f"{model} seed {seed}" + (f" ({', '.join(notes)})" if notes else ""))
    if cut:
        lines += ["", "Cut short, not counted: " + ", ".join(cut) + "."]
    return "\n".join(lines) + "\n"


def relative_criterion_table(curves: list[dict], runs: list[dict], setting: str, env: str) -> str:
    """Steps to the paper's own criterion (Figure 3's caption): 75% (Simple Shapes) / 70% (RoboDesk) of
    the highest smoothed return that any model of the figure reached, the random policy at 0, where the
    fixed criterion above is that fraction of the scripted expert's return."""
    done = {(r["model"], r["seed"]) for r in runs if r["setting"] == setting and r["status"] != "cut"}
    series: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for r in curves:
        if r["setting"] == setting and (r["model"], r["seed"]) in done:
            series.setdefault((r["model"], r["seed"]), []).append(
                (float(r["env_step"]), float(r["normalised_return"]))
            )
    smooth = {key: smoothed(*np.array(v).T) for key, v in series.items()}
    tops = [float(np.nanmax(sm)) for _, sm in smooth.values() if np.isfinite(sm).any()]
    if not tops:
        return ""
    best = max(tops)
    level = CRITERION[env] * best
    lines = [
        f"The paper's own criterion, {CRITERION[env]:.0%} of the highest smoothed return any of these runs"
        f" reached ({best:.2f}): {level:.2f} (runs that stop at the criterion above may understate that"
        " highest return).",
        "",
        "| model | reached / run | env steps to it (mean ± s.e.m.) |",
        "| --- | --- | --- |",
    ]
    for label, _, _ in models(env):
        mine = [(steps, sm) for (m, _), (steps, sm) in sorted(smooth.items()) if m == label]
        if not mine:
            continue
        hit = [float(steps[np.argmax(sm >= level)]) for steps, sm in mine if (sm >= level).any()]
        cell = "–"
        if hit:
            m, s = mean_sem(hit)
            cell = f"{m:,.0f}" + (f" ± {s:,.0f}" if len(hit) > 1 else "")
        lines.append(f"| {label} | {len(hit)} / {len(mine)} | {cell} |")
    return "\n".join(lines) + "\n"


# What each model pre-trains before RL (the FLOPs table's VAE and GW columns): the bundled VAEs, the
# bundled GW, or a GW of its own (CLIP-like, not bundled); models absent here have neither (N/A).
PRETRAINS = {
    "GW-Dreamer": ("VAE", "GW"),
    "GW-Dreamer end-to-end": ("VAE",),  # its GW trains during RL: counted in the RL column
    "CLIP-Dreamer": ("VAE", "CLIP"),
    "VAE-Dreamer": ("VAE",),
    "GW-PPO": ("VAE", "GW"),
    "VAE-PPO": ("VAE",),
    "CLIP-PPO": ("VAE", "CLIP"),
}


def gw_tasks(folder: Path) -> list[str]:
    """The tasks of the expert data the GW in ``folder`` was trained on (its data record)."""
    ck = torch.load(folder / "gw.pt", map_location="cpu", weights_only=False)
    sources = ck["data"]["samples_per_source_and_task"]
    return sorted(k.split("/", 1)[1] for k in sources if k.startswith("expert/"))


def pretraining_flops(folder: Path) -> dict[str, float]:
    """Training FLOPs (forward and backward) of the VAEs and the GW in ``folder`` until those checkpoints:
    each stage's update FLOPs per sample, counted at the checkpoints' widths, times the samples of their
    recipe (steps x batch; the attribute VAE's extra updates per step), the GW's plus the one pass that
    encodes its data through the frozen VAEs."""
    from pretrain_throughput import stage_steps
    from torch.utils.flop_counter import FlopCounterMode

    import pretrain_vae_gw as P

    vae_ck, gw_ck = (
        torch.load(folder / f, map_location="cpu", weights_only=False) for f in ("vae.pt", "gw.pt")
    )
    va, ga = vae_ck["args"], gw_ck["args"]
    per_sample = {}
    for name, (update, batch) in stage_steps("robodesk", 2, 2, va["vae_width"], "cpu").items():
        with FlopCounterMode(display=False) as counter:
            update()
        per_sample[name] = counter.get_total_flops() / batch
    vae_v, vae_attr = P.make_vaes("robodesk", va["vae_width"])
    spec = P.ENV_SPECS["robodesk"]
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        vae_v.encode(torch.zeros(1, 3, spec["image"], spec["image"]))
        vae_attr.encode(torch.zeros(1, spec["attr"]))
    vae = (per_sample["visual VAE"] + va["attr_updates_per_step"] * per_sample["attribute VAE"]) * (
        va["vae_batch_size"] * va["vae_steps"]
    )
    gw = per_sample["GW"] * ga["gw_batch_size"] * ga["gw_steps"]
    return {"VAE": vae, "GW": gw + counter.get_total_flops() * gw_ck["data"]["n_samples"]}


def rl_flops_cell(runs: list[dict], label: str, setting: str, tasks: list[str], single: bool) -> str:
    """RL training FLOPs to the criterion of ``label`` on ``tasks``: per task the mean over its reached
    seeds, summed over the tasks (the paper's sum until each task's convergence); X if never run."""
    mine = [r for r in runs if r["model"] == label and r["setting"] == setting and r["status"] != "cut"]
    ran = [t for t in tasks if any(r["task"] == t for r in mine)]
    if not ran:
        return "X"
    total, reached = 0.0, []
    for t in ran:
        hit = [r["rl_train_flops"] for r in mine if r["task"] == t and r["status"] == "reached"]
        if hit := [float(f) for f in hit if f]:  # a reached run without a FLOPs record is left out
            total, reached = total + float(np.mean(hit)), [*reached, t]
    if single:
        n_hit = sum(1 for r in mine if r["task"] == ran[0] and r["status"] == "reached")
        n_run = sum(1 for r in mine if r["task"] == ran[0])
        return f"{total:.3e} ({n_hit} / {n_run} seeds)" if reached else f"not reached (0 / {n_run} seeds)"
    missed = [t for t in ran if t not in reached]
    head = f"{total:.3e}" if reached else "not reached"
    return (
        f"{head} ({len(reached)} of {len(tasks)} tasks reached: {', '.join(reached) or 'none'}"
        + (f"; not reached: {', '.join(missed)}" if missed else "")
        + ")"
    )


def robodesk_flops_table(runs: list[dict], setting: str, pre: dict[str, float], seen: list[str]) -> str:
    """The paper's FLOPs table: VAE and GW pre-training, RL to the criterion on push_green, summed over
    the tasks the GW saw and over those it did not (every task of the records not in its data)."""
    unseen = sorted({r["task"] for r in runs} - set(seen))
    lines = [
        f"| model | VAE | GW | RL 1 task ({MAIN_TASK['robodesk']}) | RL {len(seen)} tasks the GW saw"
        f" | RL tasks it did not see ({', '.join(unseen) or 'none run'}) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for label, _, _ in models("robodesk"):
        if not any(r["model"] == label and r["setting"] == setting for r in runs):
            continue
        uses = PRETRAINS.get(label, ())
        vae = f"{pre['VAE']:.3e}" if "VAE" in uses else "N/A"
        gw = f"{pre['GW']:.3e}" if "GW" in uses else "own, not counted" if "CLIP" in uses else "N/A"
        cells = [rl_flops_cell(runs, label, setting, [MAIN_TASK["robodesk"]], True)]
        cells += [rl_flops_cell(runs, label, setting, ts, False) for ts in (seen, unseen)]
        lines.append(f"| {label} | {vae} | {gw} | {' | '.join(cells)} |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------------
def draw_curves(
    ax, curves: list[dict], runs: list[dict], setting: str, env: str, column: str = "normalised_return"
) -> list[str]:
    """Each model's ``column`` (the normalised return, or RoboDesk's success count) smoothed over 10
    episodes on ``ax``, mean ± s.e.m. over its finished seeds that recorded it."""
    drawn = []
    for label, _, _ in models(env):
        mine = [r for r in runs if r["model"] == label and r["setting"] == setting]
        done = {int(r["seed"]) for r in mine if r["status"] != "cut"}  # a cut run's curve is partial
        rows = [
            r
            for r in curves
            if r["model"] == label and r["setting"] == setting and int(r["seed"]) in done and r.get(column)
        ]
        seeds = sorted({int(r["seed"]) for r in rows})
        if not seeds:
            continue
        top = max(int(float(r["env_step"])) for r in rows)
        grid = np.unique(np.geomspace(100, top, 200).astype(int))
        per_seed = []
        for s in seeds:
            mine = [r for r in rows if int(r["seed"]) == s]
            steps = np.array([float(r["env_step"]) for r in mine])
            rets = np.array([float(r[column]) for r in mine])
            per_seed.append(smoothed_on_grid(steps, rets, grid))
        y = np.array(per_seed)
        ok = np.isfinite(y).all(axis=0)  # where every seed has its first 10 episodes
        mean = y[:, ok].mean(axis=0)
        sem = y[:, ok].std(axis=0, ddof=1) / math.sqrt(len(seeds)) if len(seeds) > 1 else np.zeros_like(mean)
        reached = sum(
            1 for r in runs if r["model"] == label and r["setting"] == setting and r["status"] == "reached"
        )
        drawn_of = f", {len(seeds)} drawn" if len(seeds) < len(done) else ""  # older records lack the column
        line = ax.plot(grid[ok], mean, label=f"{label} ({reached}/{len(done)} reached{drawn_of})")[0]
        ax.fill_between(grid[ok], mean - sem, mean + sem, color=line.get_color(), alpha=0.2)
        drawn.append(label)
    if column == "normalised_return":
        ax.axhline(CRITERION[env], color="k", ls="--", lw=1, label=f"criterion ({CRITERION[env]})")
    ax.set_xscale("log")
    ax.set_xlabel("env steps" if env == "simple_shapes" else "env steps (simulator frames)")
    return drawn


def plot_curves(
    curves: list[dict], runs: list[dict], setting: str, path: Path, caption: str, env: str = "simple_shapes"
) -> list[str]:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    drawn = draw_curves(ax, curves, runs, setting, env)
    ax.set_ylabel("normalised return (smoothed over 10 episodes)")
    tasks = sorted({r.get("task", "") for r in runs if r["setting"] == setting} - {""})
    ax.set_title(f"{TITLE[env]}{' ' + ', '.join(tasks) if tasks else ''}: mean ± s.e.m. over seeds")
    ax.legend(fontsize=8, loc="lower right")
    fig.text(0.01, 0.01, caption, fontsize=7)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return drawn


def plot_tasks(
    curves: list[dict], runs: list[dict], setting: str, tasks: list[str], title: str, path: Path, caption: str
) -> list[str]:
    """RoboDesk, one panel per task of ``tasks`` whose runs recorded success counts (Figures 6 and 7: the
    paper's y-axis, smoothed here over 10 episodes, a tenth of a 200,000-frame run, where the paper's
    runs of millions of frames take 100); the tasks drawn."""
    import matplotlib.pyplot as plt

    counted = {r["task"] for r in curves if r["setting"] == setting and r.get("success_count")}
    tasks = [
        t for t in tasks if t in counted and any(r["task"] == t and r["setting"] == setting for r in runs)
    ]
    if not tasks:
        return []
    cols = min(3, len(tasks))
    rows = math.ceil(len(tasks) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax, task in zip(axes.flat, tasks, strict=False):
        of_task = [r for r in runs if r["task"] == task]
        of_curves = [r for r in curves if r["task"] == task]
        draw_curves(ax, of_curves, of_task, setting, "robodesk", column="success_count")
        ax.set_title(task, fontsize=9)
        ax.xaxis.set_minor_formatter(plt.NullFormatter())  # narrow panels: label the decades only
        ax.set_ylim(0, 500)
        ax.set_ylabel("success count (steps of 500)")
        ax.legend(fontsize=6, loc="upper left")
    for ax in list(axes.flat)[len(tasks) :]:
        ax.axis("off")
    fig.suptitle(
        f"RoboDesk, {title}: success count\nsmoothed over 10 episodes, mean ± s.e.m. over seeds", fontsize=9
    )
    fig.text(0.01, 0.01, caption, fontsize=7)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return tasks


def plot_ablation(
    ablation: list[dict], setting: str, path: Path, caption: str, env: str = "simple_shapes"
) -> list[str]:
    import matplotlib.pyplot as plt

    labels = [
        m for m, _, _ in models(env) if any(r["model"] == m and r["setting"] == setting for r in ablation)
    ]
    fig, ax = plt.subplots(figsize=(max(5.0, 2.2 * len(labels) + 1.5), 4.0))
    width = 0.8 / len(DROPS)
    for j, (drop, name) in enumerate(DROPS.items()):
        means, sems = [], []
        for m in labels:
            mine = [r for r in ablation if r["model"] == m and r["setting"] == setting]
            v = [float(r["normalised_return"]) for r in mine if r["drop"] == drop]
            mu, se = mean_sem(v) if v else (float("nan"), float("nan"))
            means.append(mu), sems.append(0.0 if math.isnan(se) else se)
        x = np.arange(len(labels)) + (j - 1) * width
        ax.bar(x, means, width, yerr=sems, capsize=3, label=name)
    ax.axhline(CRITERION[env], color="k", ls="--", lw=1, label=f"criterion ({CRITERION[env]})")
    ax.set_xticks(np.arange(len(labels)))
    n_agents = [
        len({r["seed"] for r in ablation if r["model"] == m and r["setting"] == setting}) for m in labels
    ]
    ax.set_xticklabels([f"{m}\n({n} agents)" for m, n in zip(labels, n_agents, strict=True)])
    ax.set_ylabel("normalised return")
    ax.set_title(f"{TITLE[env]}: modality ablation (mean ± s.e.m.)")
    ax.legend(fontsize=8)
    fig.text(0.01, 0.01, caption, fontsize=7)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return labels


def figure2(gw_path: Path, vae_path: Path, path: Path, caption: str, n: int = 8, seed: int = 123) -> None:
    """Rows: images, the images whose attributes are paired with them (incongruent pairs), then the image
    decoded from z for alpha_v = 0 (translation from the attributes), 1 (demi-cycle) and 0.5 (fusion)."""
    import matplotlib.pyplot as plt

    import pretrain_vae_gw as P
    from envs.simple_shapes import sample_dataset

    vae_v, vae_attr, vae_ck = P.load_vaes(vae_path, "simple_shapes")
    ck = torch.load(gw_path, map_location="cpu", weights_only=False)
    spec = P.ENV_SPECS["simple_shapes"]
    gw = P.GlobalWorkspace(spec["latent"], spec["z"], spec["gw_hidden"])
    gw.load_state_dict(ck["gw"])
    gw.eval()
    data = sample_dataset(n, seed=seed)
    attrs_n = ((data["attr"] - vae_ck["attr_mean"]) / vae_ck["attr_std"]).astype(np.float32)
    u_v, u_a = P.encode_unimodal(vae_v, vae_attr, data["image"], attrs_n, "cpu")
    perm = torch.arange(n).roll(1)  # each image with the attributes of another sample
    rows = [P.images_to_tensor(data["image"], "cpu"), P.images_to_tensor(data["image"][perm.numpy()], "cpu")]
    with torch.no_grad():
        for alpha_v in (0.0, 1.0, 0.5):
            rows.append(vae_v.decode(gw.d["v"](gw.fuse(u_v, u_a[perm], alpha_v, 1 - alpha_v))))
    names = [
        "image (vision)",
        "attributes (as image)",
        "translation attr→v",
        "demi-cycle v→v",
        "fusion 0.5/0.5",
    ]
    fig, axes = plt.subplots(len(rows), n, figsize=(n * 0.9 + 1.6, len(rows) * 0.95))
    for i, row in enumerate(rows):
        for j in range(n):
            axes[i, j].imshow(row[j].permute(1, 2, 0).clamp(0, 1).numpy())
            axes[i, j].set_xticks([]), axes[i, j].set_yticks([])
        axes[i, 0].set_ylabel(names[i], rotation=0, ha="right", va="center", fontsize=7)
    fig.suptitle("Simple Shapes GW (Figure 2): incongruent image / attribute pairs", fontsize=9)
    fig.text(0.01, 0.005, f"{gw_path.name} ({gw_path.parent}); {caption}", fontsize=6)
    fig.tight_layout(rect=(0.08, 0.03, 1, 0.95))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def shown(path: str) -> str:
    """A path as the user would type it: relative to the repository when inside it."""
    p = Path(path).resolve()
    return str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else path


def main(args: Args) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("results", "gw_checkpoint", "vae_checkpoint", "pretrained"):  # defaults: repository files
        p = Path(getattr(args, name))
        if getattr(args, name) and not p.is_absolute() and not p.exists() and (ROOT / p).exists():
            setattr(args, name, str(ROOT / p))
    env = args.env
    if env not in CRITERION:
        raise SystemExit(f"error: --env {env}: choose one of {', '.join(CRITERION)}")
    if args.runs:
        runs, curves, ablation = read_runs(Path(args.runs), env)
        if not runs:
            raise SystemExit(
                f"error: no {env} run of a known model under {args.runs} (names: <model>_{env}_s<seed>"
                + (")" if env == "simple_shapes" else " with the task before _s)")
            )
    else:
        res = Path(args.results)
        runs, curves, ablation = (read_csv(res / f"{env}_{k}.csv") for k in ("runs", "curves", "ablation"))
    if args.export:
        for k, rows in {"runs": runs, "curves": curves, "ablation": ablation}.items():
            write_csv(Path(args.export) / f"{env}_{k}.csv", rows, fields(k, env))
    caption = args.caption or f"torch {torch.__version__}"
    task = MAIN_TASK[env]  # Figures 3 and 5 and the first table are one task's (RoboDesk: push_green)
    one = [[r for r in rows if r.get("task", "") == task] for rows in (runs, curves, ablation)]
    drawn = plot_curves(one[1], one[0], args.setting, out / f"{env}_curves.png", caption, env)
    bars = plot_ablation(one[2], args.setting, out / f"{env}_ablation.png", caption, env)
    table = flops_table(one[0], args.setting, env)
    relative = relative_criterion_table(one[1], one[0], args.setting, env)
    table += f"\n{relative}" if relative else ""
    tasks_drawn = []
    if env == "robodesk":
        pretrained = Path(args.pretrained)
        seen = gw_tasks(pretrained)
        unseen = sorted({r["task"] for r in runs} - set(seen))
        for name, tasks, title in (
            ("seen", seen, "tasks the GW saw"),
            ("unseen", unseen, "tasks it did not"),
        ):
            png = out / f"robodesk_tasks_{name}.png"
            tasks_drawn += plot_tasks(curves, runs, args.setting, tasks, title, png, caption)
        paper = robodesk_flops_table(runs, args.setting, pretraining_flops(pretrained), seen)
        table += (
            f"\nThe paper's layout: training FLOPs of the VAEs and the GW ({shown(str(pretrained))}, until"
            " their checkpoints) and RL training FLOPs to the criterion, the mean over reached seeds summed"
            " over tasks.\n\n" + paper
        )
    (out / f"{env}_flops.md").write_text(
        f"# {TITLE[env]}: env steps and RL training FLOPs to the return criterion\n\n"
        f"Drawn by `benchmarks/paper_figures.py` from {shown(args.runs or args.results)} ({caption}).\n\n"
        + table
    )
    if args.gw_checkpoint and env == "simple_shapes":
        figure2(Path(args.gw_checkpoint), Path(args.vae_checkpoint), out / "gw_figure2.png", caption)
    print(table)
    print(
        f"[figures] curves of {', '.join(drawn)}; ablation of {', '.join(bars) or 'none'}"
        + (f"; task panels of {', '.join(tasks_drawn)}" if env == "robodesk" else "")
        + f"; written to {out}/"
    )
    return {"curves": drawn, "ablation": bars, "table": table, "tasks": tasks_drawn}


if __name__ == "__main__":
    main(tyro.cli(Args))
