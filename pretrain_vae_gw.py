"""Pre-training of the frozen representations: paired data, one beta-VAE per modality, and the Global
Workspace (or its CLIP-like variant).

Paper: "Model / Global Workspace" (eq. 1-3), appendix "VAE details" and "GW details".

    python pretrain_vae_gw.py --env simple_shapes                       # collect, vae, gw (paper scale)
    python pretrain_vae_gw.py --env simple_shapes --loss-preset clip --stages gw   # CLIP-like model
    python pretrain_vae_gw.py --env simple_shapes --cpu-preset          # ~10 min on a 2-core CPU

Stages run in the order collect -> vae -> gw; each can run alone (``--stages vae``). Outputs go to
``checkpoints/<env>/{vae,gw,clip}.pt`` (data to ``data/<env>/``), where the agents find them.

    torchrun --nproc_per_node 4 pretrain_vae_gw.py --env robodesk --stages vae gw --stream-shards 4

Under torchrun the vae and gw stages train with DistributedDataParallel (gloo on a CPU, NCCL on GPUs):
each process computes its slice of every global batch, and rank 0 alone logs and saves; the result is
the one-process result for the same global batch (``--vae-batch-size``, ``--gw-batch-size``).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import hashlib
import inspect
import json
import math
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.distributed as dist
import torch.distributed.nn.functional as dist_nn
import torch.nn as nn
import torch.nn.functional as F
import tyro
from torch.nn.parallel import DistributedDataParallel as DDP
from torch.utils.tensorboard import SummaryWriter

import envs  # noqa: F401  (registers the environments)


@dataclass
class Args:
    env: Literal["simple_shapes", "robodesk"] = "simple_shapes"
    """environment whose observations are encoded"""
    stages: tuple[Literal["collect", "vae", "gw"], ...] = ("collect", "vae", "gw")
    """stages to run; they run in the pipeline's order (collect, vae, gw) whatever the order given"""
    task: str = "push_green"
    """RoboDesk task whose expert collects the expert data, unless --tasks is given (ignored for Simple
    Shapes): one of open_slide, open_drawer, push_green, stack, upright_block_off_table,
    flat_block_in_bin, flat_block_in_shelf, lift_upright_block, lift_ball (RoboDesk's core tasks), push_blue,
    push_red, flat_block_off_table, ball_off_table, upright_block_in_bin, ball_in_bin, upright_block_in_shelf,
    ball_in_shelf, lift_flat_block"""
    tasks: tuple[str, ...] = ()
    """RoboDesk tasks for a multi-task dataset (one GW for all of them, paper section "Unique Global
    Workspace for all tasks"): each task's scripted expert (envs/robodesk_experts.py) collects an equal
    share; default: just --task"""
    expert_fraction: float | None = None
    """share of expert samples in the RoboDesk data (default k/(k+1) for k tasks: the paper's 1M random +
    1M expert for one task, and 500k per task + 500k random for six)"""
    wander_fraction: float = 0.0
    """share of RoboDesk samples from the wanderer (envs/robodesk_experts.py Wanderer: random way-points,
    many at the desk's handles, objects and green button, random gripper and wrist), taken before the
    expert / random split; the experts' paths and a random policy near the start pose leave most of the
    states an agent visits unseen (docs/pretrain_vae_gw.md)"""
    expert_noise: float = 0.1
    """std of the Gaussian noise added to the scripted experts' actions (more varied data)"""
    seed: int = 1
    """seed of data collection, initialisation and batches"""
    data_dir: str = "data"
    """paired observations are stored in <data_dir>/<env>/"""
    checkpoint_dir: str = "checkpoints"
    """checkpoints are written to <checkpoint_dir>/<env>/"""
    overwrite: bool = False
    """replace the checkpoints of the requested stages (vae.pt, gw.pt / clip.pt) and a stage left
    unfinished with other settings; without it the run stops before it would overwrite them"""
    exp_name: str = "pretrain_vae_gw"
    """TensorBoard run name prefix (runs/<exp_name>_<env>_<stage>_<seed>_<time>)"""
    device: str = "cuda" if torch.cuda.is_available() else "cpu"
    """torch device"""
    cpu_preset: bool = False
    """settings sized for a 2-core CPU (docs/pretrain_vae_gw.md, "Results at a CPU scale"): Simple Shapes
    in about 10 minutes; RoboDesk one shared GW for the five scripted tasks (push_red and push_blue left
    out, zero-shot) from fast images, in about 70 minutes; flags left at their default take the preset's
    value"""

    # collect
    n_samples: int | None = None
    """samples to collect (default: 500,000 Simple Shapes; RoboDesk 2,000,000, the paper's 1M random + 1M
    expert; use 3,500,000 for its six-task dataset)"""
    expert_checkpoint: tuple[str, ...] = ()
    """RoboDesk expert policies from dreamer_baseline.py (its <agent>.policy.pt2 files, or the agent .pt
    beside them), one per task: each collects its own task's expert share instead of the scripted expert"""
    shard_size: int = 50_000
    """samples per compressed shard"""
    workers: int = 1
    """collect stage: processes side by side, each with its own simulator and renderer (RoboDesk: one
    episode at a time; Simple Shapes: one shard at a time); the data are the same for any number"""
    stream_shards: int = 0
    """vae and gw stages: 0 loads every shard into memory; K > 0 streams them, K shards in memory at a
    time (the next one read ahead), so memory stays at about K + 1 shards whatever the data's size; the
    visual VAE then samples its batches from those K shards (docs/pretrain_vae_gw.md)"""
    render_quality: Literal["faithful", "fast"] = "faithful"
    """RoboDesk image quality of the collected data (fast: CPU experiments only, docs/environments.md)"""

    # vae (appendix Table "VAE training")
    vae_steps: int = 500_000
    """VAE training steps"""
    vae_batch_size: int = 2056
    """VAE batch size (the table's 2.056)"""
    vae_lr_v: float | None = None
    """visual VAE max learning rate (default: 5e-3 Simple Shapes, 3e-4 RoboDesk)"""
    vae_lr_attr: float | None = None
    """attribute VAE max learning rate (default: 5e-3 Simple Shapes, 5e-4 RoboDesk)"""
    vae_lr_start_end: float | None = None
    """OneCycle start and end learning rate (default: 5e-3 Simple Shapes, 1e-4 RoboDesk)"""
    vae_weight_decay: float = 1e-5
    """AdamW weight decay"""
    beta_v: float = 0.1
    """beta of the visual VAE (shimmer-ssd's value; the paper does not give it)"""
    beta_attr: float = 0.05
    """beta of the attribute VAE (shimmer-ssd's value)"""
    attr_updates_per_step: int = 1
    """attribute-VAE updates per visual-VAE update (each on a fresh batch after the first)"""
    attr_noise: float = 0.0
    """std of Gaussian noise added to the normalised attributes of each attribute-VAE batch (0: none)"""
    vae_width: int = 1024
    """channels of the last encoder convolution (halved layer by layer before it), as in the table"""

    # gw (appendix Tables "GW losses weights" and "GW training")
    loss_preset: Literal["gw", "clip"] = "gw"
    """gw: beta_dcy = beta_cy = beta_tr = beta_fusion = 1, beta_cont = 0.1; clip: contrastive only"""
    gw_steps: int = 500_000
    """GW training steps"""
    gw_batch_size: int = 2056
    """GW batch size"""
    gw_lr: float | None = None
    """GW max learning rate (default: 5e-3 Simple Shapes, 3e-4 RoboDesk)"""
    gw_lr_start_end: float | None = None
    """GW OneCycle start and end learning rate (default: 5e-4 Simple Shapes, 1e-4 RoboDesk)"""
    gw_weight_decay: float | None = None
    """GW AdamW weight decay (default: 1e-5 Simple Shapes, 1e-6 RoboDesk)"""
    fusion_temperature: float = 0.2
    """fusion weights of L_fusion are softmax(U / T), U uniform per modality (shimmer)"""
    contrastive_temperature: float = 0.07
    """fixed temperature of the contrastive loss (logit scale 1/T, shimmer)"""

    # logging and checkpoints
    log_every: int = 100
    """steps between TensorBoard scalars and progress lines"""
    save_every: int = 2_000
    """steps between resumable checkpoints"""
    eval_size: int = 2_000
    """held-out samples for the final evaluation figures"""
    torch_threads: int = 0
    """torch CPU threads (0: torch's default)"""

    # -- an experiment, not the paper's data (docs/experiments.md, "Why runs stalled: off frame") ------
    wide_share: float = 0.0
    """Simple Shapes: share of samples whose position is drawn from 16 px before to 16 px past the frame
    (envs.simple_shapes.WIDE_POSITIONS) instead of the dataset's [7, 25), so that the frozen GW also
    represents the states an agent reaches by pushing the shape out (0: the paper's dataset draw)"""

    def resolve_tables(self) -> Args:
        """Fill the per-environment defaults of the appendix tables."""
        ss = self.env == "simple_shapes"
        for name, ss_value, rd_value in [
            ("n_samples", 500_000, 2_000_000),
            ("vae_lr_v", 5e-3, 3e-4),
            ("vae_lr_attr", 5e-3, 5e-4),
            ("vae_lr_start_end", 5e-3, 1e-4),
            ("gw_lr", 5e-3, 3e-4),
            ("gw_lr_start_end", 5e-4, 1e-4),
            ("gw_weight_decay", 1e-5, 1e-6),
        ]:
            if getattr(self, name) is None:
                setattr(self, name, ss_value if ss else rd_value)
        return self

    def resolve(self) -> Args:
        """The tables' defaults, then the CPU preset (if asked) for every flag left at its default."""
        if not 0.0 <= self.wide_share <= 1.0 or (self.wide_share and self.env != "simple_shapes"):
            raise UsageError(
                f"--wide-share is a share in [0, 1] for --env simple_shapes, got {self.wide_share}"
            )
        self.resolve_tables()
        if self.cpu_preset:
            defaults = Args(env=self.env).resolve_tables()
            for name, value in CPU_PRESET[self.env].items():
                if getattr(self, name) == getattr(defaults, name):  # flags given explicitly win
                    setattr(self, name, value)
        return self


# At beta_attr 0.05 and a few thousand updates the attribute VAE kept 5 of its 10 latent dimensions and
# lost the position (6.7 px error); beta_attr 0.005 with 4 updates per step keeps all of them.
# 20,000 GW steps (3 min here) rather than 60,000 (10 min): GW-Dreamer at --entropy-coef 3e-3 reached its
# return criterion in 4 of 6 seeds on the shorter GW (4 of 5 on the longer), and the 7 minutes saved
# bring pre-training and a seed's run within 30 minutes on 2 cores (docs/pretrain_vae_gw.md).
CPU_PRESET = {}
CPU_PRESET["simple_shapes"] = {
    "n_samples": 60_000,
    "vae_width": 64,
    "vae_steps": 5_000,
    "vae_batch_size": 128,
    "vae_lr_v": 1e-3,
    "vae_lr_attr": 3e-3,
    "vae_lr_start_end": 1e-3,
    "beta_attr": 0.005,
    "attr_updates_per_step": 4,
    "gw_steps": 20_000,
    "gw_batch_size": 256,
}
# RoboDesk: the tasks with a scripted expert except push_red and push_blue (kept zero-shot), fast images
# (a faithful one costs 0.35 s to render here), collected by 2 processes; the recipe's evidence is in
# docs/pretrain_vae_gw.md ("RoboDesk at a CPU scale").
CPU_PRESET["robodesk"] = {
    "tasks": ("push_green", "open_slide", "open_drawer", "upright_block_off_table", "flat_block_in_bin"),
    "n_samples": 150_000,
    "render_quality": "fast",
    "workers": 2,
    "eval_size": 6_000,
    "vae_width": 64,
    "vae_steps": 6_000,
    "vae_batch_size": 128,
    "vae_lr_v": 1e-3,
    "vae_lr_attr": 3e-3,
    "vae_lr_start_end": 1e-4,
    "beta_attr": 0.005,
    "attr_updates_per_step": 2,
    "attr_noise": 0.1,
    "gw_steps": 10_000,
    "gw_batch_size": 256,
    "gw_lr": 1e-3,
}


# --------------------------------------------------------------------------------------------------
# Per-environment shapes (appendix tables)
# --------------------------------------------------------------------------------------------------
ENV_SPECS = {
    # image side, attribute size, VAE latent size (u_v, u_attr), GW latent size z, GW hidden width
    "simple_shapes": {"image": 32, "attr": 11, "latent": 10, "z": 10, "gw_hidden": 64},
    # z: 76 per the GW and world-model tables (the text's 60 contradicts them; docs/paper_readings.md)
    "robodesk": {"image": 64, "attr": 76, "latent": 40, "z": 76, "gw_hidden": 512},
}


def env_dir(root: str, args: Args) -> Path:
    return Path(root) / args.env


# --------------------------------------------------------------------------------------------------
# Safe runs: nothing made earlier is overwritten or reused by accident, an interrupted stage continues
# only with the settings it started with, checkpoints are written atomically, and bad settings or
# unreadable files stop the run at once with one line
# --------------------------------------------------------------------------------------------------
class UsageError(ValueError):
    """A mistake in the command line or in the files it names: the CLI prints the message and exits 2."""


def require(ok: bool, flag: str, value, rule: str) -> None:
    if not ok:
        raise UsageError(f"--{flag.replace('_', '-')} {value}: {rule}")


def atomic_save(obj: dict, path: Path) -> None:
    """Write to a temporary file of this process, then rename it over ``path``: an interruption (even
    kill -9) leaves the previous file whole, and two processes never share a temporary file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    kept = f"the previous {path.name} is kept" if path.exists() else f"no {path.name} was written"
    try:
        with open(tmp, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except KeyboardInterrupt:  # a second Ctrl-C: stop at once
        raise KeyboardInterrupt(f"while saving {path}; {kept}") from None
    except (OSError, RuntimeError) as err:  # torch reports a full disk as "unexpected pos"
        full = getattr(err, "errno", None) == errno.ENOSPC or "unexpected pos" in str(err)
        cause = "no space left on the device" if full else " ".join(str(err).split())[:200]
        raise UsageError(f"cannot save {path} ({cause}); {kept}") from err
    finally:
        tmp.unlink(missing_ok=True)


def read_checkpoint(path: Path, remake: str) -> dict:
    """``torch.load``, or a message that names the file and the command that makes it again."""
    if path.suffix == ".pt2":
        raise UsageError(
            f"{path} is a policy exported by dreamer_baseline.py (torch.export), not a checkpoint: give the "
            f"agent checkpoint beside it, {path.with_name(path.name.removesuffix('.policy.pt2') + '.pt')}"
        )
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # a truncated zip, a text file, a pickle of something else: many types
        brief = " ".join(str(err).split())[:200]  # one line
        raise UsageError(
            f"cannot read {path} ({type(err).__name__}: {brief}); the file is damaged or is no checkpoint: "
            f"make it again with `{remake}`"
        ) from err
    if not isinstance(ckpt, dict) or "kind" not in ckpt and "identity" not in ckpt:
        raise UsageError(
            f"{path} holds a {type(ckpt).__name__} of torch.save, not a checkpoint of these scripts: "
            f"make one with `{remake}`"
        )
    return ckpt


def ensure_writable(folder: Path) -> None:
    """Create ``folder`` and write a file in it now, rather than fail at the first save."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write_test.{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise UsageError(f"cannot write to {folder}: {err.strerror or err}") from err


def check_device(device: str) -> None:
    """--device names a device this torch has (a CPU-only build has no cuda)."""
    try:
        torch.empty(1, device=device)
    except (RuntimeError, AssertionError) as err:
        brief = " ".join(str(err).split())[:120]
        raise UsageError(f"--device {device}: this torch cannot use it ({brief}); use --device cpu") from err


def setting_changes(saved: dict, now: dict, keys) -> list[str]:
    """The saved ``--flag value`` (a switch: ``--flag`` or ``--no-flag``, as the CLI takes it) of each
    setting in ``keys`` whose saved value differs from this command's."""
    out = []
    for k in (k for k in keys if k in saved and saved[k] != now[k]):
        flag, value = k.replace("_", "-"), saved[k]
        if isinstance(value, bool):
            out.append(f"--{flag}" if value else f"--no-{flag}")
        else:
            out.append(f"--{flag} {' '.join(map(str, value)) if isinstance(value, (list, tuple)) else value}")
    return out


class StopRequest:
    """Ctrl-C (SIGINT) or SIGTERM asks the run to finish what it is doing, save and exit with code 130,
    so an interrupted run loses nothing and ``--resume`` continues it (a save made in the middle of an
    update would pair half-stepped optimisers). A second signal stops at once."""

    def __init__(self, tag: str):
        self.tag, self.requested, self.previous = tag, False, {}
        if threading.current_thread() is threading.main_thread():  # signal handlers live there only
            self.previous = {s: signal.signal(s, self.handle) for s in (signal.SIGINT, signal.SIGTERM)}

    def handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        name = signal.Signals(signum).name
        print(f"[{self.tag}] {name}: saving after this step (send it again to stop at once)", flush=True)

    def restore(self) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler)
        self.previous = {}


def keep_freed_memory() -> None:
    """Keep freed memory in the process (Linux, glibc). By default glibc maps blocks over 128 kB afresh
    (over 32 MB at most, as its threshold adapts) and hands them back when they are freed, so every CPU
    update page-faults its large tensors in again: a third of the CPU time of a 12M Dreamer update
    (docs/dreamer_baseline.md, "Against a peer"), 1.3x on the visual VAE's (PyTorch's CPU tuning guide
    gets the same through jemalloc / tcmalloc). Elsewhere nothing changes."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL("libc.so.6")
            libc.mallopt(-4, 0)  # M_MMAP_MAX: every block comes from the heap, which keeps it once freed
            libc.mallopt(-1, -1)  # M_TRIM_THRESHOLD at SIZE_MAX: nor is the heap's free top handed back
        except (OSError, AttributeError):  # not glibc (musl): the allocator stays as it is
            pass


def cli(main, args_type) -> None:
    """Run ``main`` on the parsed command line; a UsageError is printed as one line (exit code 2), and
    Ctrl-C outside the places that save prints one line too (exit code 130)."""
    keep_freed_memory()
    try:
        main(tyro.cli(args_type))
    except UsageError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    except KeyboardInterrupt as err:
        print(f"interrupted {err}".strip(), flush=True)
        raise SystemExit(130) from None


def own_command(args: Args, stages: str, extra: str = "") -> str:
    """This script's command for ``stages`` with the user's folders, scale and loss preset (for hints)."""
    cmd = f"python pretrain_vae_gw.py --env {args.env} --stages {stages}"
    cmd += " --cpu-preset" if args.cpu_preset else ""
    cmd += f" --loss-preset {args.loss_preset}" if args.loss_preset != "gw" else ""
    cmd += f" --data-dir {args.data_dir}" if args.data_dir != "data" else ""
    cmd += f" --checkpoint-dir {args.checkpoint_dir}" if args.checkpoint_dir != "checkpoints" else ""
    return cmd + extra


def load_checkpoint(path: Path, kind: str, env: str, make: str) -> dict:
    """Load a checkpoint and check that it is a ``kind`` checkpoint of ``env``; ``make`` is the command
    that produces it (named in the error)."""
    if not path.is_file():
        raise UsageError(f"no {kind} checkpoint at {path}; make it with `{make}`")
    ckpt = read_checkpoint(path, make)
    if ckpt.get("kind") != kind:
        raise UsageError(f"{path} holds a {ckpt.get('kind')!r} checkpoint, expected {kind!r}")
    if ckpt.get("env") != env:
        raise UsageError(
            f"{path} was made for env {ckpt.get('env')!r}, but this run is for env {env!r}; "
            f"make a matching one with `{make}`"
        )
    return ckpt


# --------------------------------------------------------------------------------------------------
# What defines the data and each stage, compared before anything made earlier is reused
# --------------------------------------------------------------------------------------------------
VAE_KEYS = tuple(
    "n_samples seed vae_steps vae_batch_size vae_lr_v vae_lr_attr vae_lr_start_end vae_weight_decay beta_v"
    " beta_attr attr_updates_per_step attr_noise vae_width eval_size".split()
)
GW_KEYS = tuple(
    "seed loss_preset gw_steps gw_batch_size gw_lr gw_lr_start_end gw_weight_decay fusion_temperature"
    " contrastive_temperature".split()
)


def data_identity(args: Args) -> dict:
    """The settings that decide which samples the collect stage draws (not how many: asking for more
    appends shards). Written to <data_dir>/<env>/manifest.json."""
    if args.env == "simple_shapes":
        return {"env": args.env, "seed": args.seed, "wide_share": args.wide_share}
    tasks = list(args.tasks) or [args.task]
    frac = len(tasks) / (len(tasks) + 1) if args.expert_fraction is None else args.expert_fraction
    out = {"env": args.env, "seed": args.seed, "tasks": tasks, "expert_fraction": frac}
    out |= {"expert_noise": args.expert_noise, "render_quality": args.render_quality}
    return out | {"expert_checkpoint": [str(p) for p in args.expert_checkpoint]}


def stage_identity(args: Args, stage: str, vae: dict | None = None) -> dict:
    """What defines the vae or gw stage's result: its own flags, the data's collection settings, the data
    it reads (``data_read``: samples and a digest of the shards' names and sizes) and (gw) the VAE whose
    latents it learns from (``vae_digest``)."""
    keys = VAE_KEYS if stage == "vae" else GW_KEYS
    out = {k: getattr(args, k) for k in keys} | data_identity(args) | {"data_read": data_read(args)}
    if stage == "vae" and args.stream_shards:  # streamed batches are other batches (the gw stage's are not)
        out["stream_shards"] = args.stream_shards
    return out | ({"vae_digest": vae_digest(vae)} if stage == "gw" else {})


def data_read(args: Args) -> str:
    """The data a stage reads: "<samples> samples, shards <digest of their names and sizes>"."""
    h = hashlib.sha256()
    for p in shard_paths(env_dir(args.data_dir, args)):
        h.update(f"{p.name}:{p.stat().st_size};".encode())
    return f"{data_size(args)} samples, shards {h.hexdigest()[:12]}"


def vae_digest(vae: dict) -> str:
    """Identity of a VAE checkpoint's weights: SHA-256 of its tensors with floating ones rounded to
    float16, the precision of the bundled copies, so that a bundled VAE keeps the digest of its source."""
    h = hashlib.sha256()
    for part in ("vae_v", "vae_attr"):
        for key, t in sorted(vae[part].items()):
            t = t.detach().cpu()
            h.update(key.encode() + (t.half() if torch.is_floating_point(t) else t).numpy().tobytes())
    return h.hexdigest()[:16]


def identity_changes(saved: dict, now: dict) -> list[str]:
    """How a saved stage identity differs from this command's: ``--flag value`` for flags, words for the
    data read and the VAE."""
    flags = [k for k in now if k not in ("data_read", "vae_digest")]
    out = setting_changes(saved, now, flags)
    if "data_read" in saved and saved["data_read"] != now["data_read"]:
        out.append(f"other data ({saved['data_read']}; the data folder now holds {now['data_read']})")
    if "vae_digest" in saved and saved["vae_digest"] != now["vae_digest"]:
        out.append("another VAE (vae.pt was remade since)")
    return out


def check_data(folder: Path, args: Args) -> None:
    """Data in ``folder`` must have been collected with this command's settings (its manifest)."""
    if not shard_paths(folder):
        return
    manifest = folder / "manifest.json"
    if not manifest.is_file():
        raise UsageError(
            f"{folder} holds data without a manifest.json, so the settings it was collected with are "
            "unknown: collect into another --data-dir (or delete that folder)"
        )
    try:
        recorded = json.loads(manifest.read_text())
    except (OSError, ValueError) as err:  # JSONDecodeError is a ValueError
        raise UsageError(
            f"cannot read {manifest} ({type(err).__name__}): it is damaged; write back the settings the data "
            "were collected with, or collect into another --data-dir"
        ) from err
    changed = setting_changes(recorded, data_identity(args), data_identity(args))
    if changed:
        raise UsageError(
            f"{folder} holds data collected with {' '.join(changed)}: give the same settings to use it, "
            "or collect into another --data-dir"
        )


def stage_is_done(path: Path, identity: dict, args: Args) -> bool:
    """True if ``path`` was made by this stage with these settings (the stage is skipped); False if it is
    absent (or --overwrite replaces it); an error if it was made otherwise, since agents trained on it
    would no longer load once it changed."""
    if not path.is_file() or args.overwrite:
        return False
    saved = read_checkpoint(path, own_command(args, " ".join(args.stages), " --overwrite")).get("identity")
    if saved == identity:
        print(f"[{path.stem}] {path} was made with these settings: stage skipped")
        return True
    changed = (
        (identity_changes(saved, identity) or ["(an older record)"]) if saved else ["(settings not recorded)"]
    )
    raise UsageError(
        f"{path} already exists, made with {' '.join(changed)}: use it as it is (leave its stage out of "
        "--stages), write to another --checkpoint-dir, or add --overwrite to replace it"
    )


def resume_partial(partial: Path, identity: dict, args: Args, stage: str) -> dict | None:
    """The saved state of an unfinished stage made with these settings, or None to start the stage
    (--overwrite discards an unfinished stage made with other settings)."""
    if not partial.is_file():
        return None
    try:
        ck = read_checkpoint(partial, "")
    except UsageError as err:  # e.g. cut short by a full disk
        if not args.overwrite:
            reason = str(err).split("; ")[0]
            raise UsageError(f"{reason}: add --overwrite to start the unfinished {stage} stage over") from err
        ck = {}
    changed = identity_changes(ck.get("identity", {}), identity)
    changed += [] if "identity" in ck else ["(settings not recorded)"]
    changed += ["(an older record)"] if ck.get("identity", identity) != identity and not changed else []
    if not changed:
        print(f"[{stage}] continuing the unfinished stage in {partial} from step {ck['step']:,}")
        return ck
    if not args.overwrite:
        raise UsageError(
            f"{partial} is an unfinished {stage} stage made with {' '.join(changed)}: give the same "
            "settings to continue it, or add --overwrite to start the stage over"
        )
    partial.unlink()
    return None


def check_settings(args: Args) -> None:
    """Every numeric flag in range before anything runs."""
    for flag, value in vars(args).items():  # inf and nan would pass every range check below
        if isinstance(value, float):
            require(math.isfinite(value), flag, value, "must be a finite number")
    check_device(args.device)
    at_least_1 = "n_samples shard_size vae_steps attr_updates_per_step gw_steps log_every save_every"
    for flag in (at_least_1 + " eval_size").split():
        require(getattr(args, flag) >= 1, flag, getattr(args, flag), "must be at least 1")
    world = int(os.environ.get("WORLD_SIZE", 1))  # torchrun's processes share each global batch
    for flag in ("vae_batch_size", "gw_batch_size"):  # batch norm and the contrastive loss pair samples
        require(getattr(args, flag) >= 2, flag, getattr(args, flag), "must be at least 2")
        rule = f"must be a multiple of the {world} processes of torchrun"
        require(getattr(args, flag) % world == 0, flag, getattr(args, flag), rule)
    require(args.workers >= 1, "workers", args.workers, "must be at least 1")
    if world > 1 and "collect" in args.stages:
        raise UsageError(
            "the collect stage runs in one process (its --workers run episodes side by side): collect "
            "first without torchrun, then run the vae and gw stages under it (--stages vae gw)"
        )
    require(args.stream_shards >= 0, "stream_shards", args.stream_shards, "must not be negative")
    positive = "vae_lr_v vae_lr_attr vae_lr_start_end gw_lr gw_lr_start_end fusion_temperature"
    for flag in (positive + " contrastive_temperature").split():
        require(getattr(args, flag) > 0, flag, getattr(args, flag), "must be positive")
    for flag in "vae_weight_decay gw_weight_decay beta_v beta_attr attr_noise expert_noise".split():
        require(getattr(args, flag) >= 0, flag, getattr(args, flag), "must not be negative")
    n_down = int(np.log2(ENV_SPECS[args.env]["image"])) - 1  # conv layers that halve the image
    rule = f"must be a multiple of {2 ** (n_down - 1)} (the encoder halves it {n_down - 1} times)"
    ok = args.vae_width > 0 and args.vae_width % 2 ** (n_down - 1) == 0
    require(ok, "vae_width", args.vae_width, rule)
    if args.env == "robodesk":
        for t in tuple(args.tasks) or (args.task,):
            from envs.robodesk import TASKS

            if t not in TASKS:
                raise UsageError(f"unknown RoboDesk task {t!r}; valid tasks: {', '.join(TASKS)}")


def check_outputs(args: Args) -> None:
    """Before any stage runs: the folders take files and the data on disk is the data asked for."""
    if "collect" in args.stages:
        ensure_writable(env_dir(args.data_dir, args))
    if "vae" in args.stages or "gw" in args.stages:
        ensure_writable(env_dir(args.checkpoint_dir, args))
    ensure_writable(Path("runs"))  # TensorBoard
    check_data(env_dir(args.data_dir, args), args)


class Progress:
    """One progress line with rate and ETA per stage."""

    def __init__(self, name: str, total: int, start: int = 0):
        self.name, self.total, self.start, self.t0 = name, total, start, time.time()

    def show(self, step: int, extra: str = "") -> None:
        done = step - self.start
        rate = done / max(time.time() - self.t0, 1e-9)
        eta = (self.total - step) / max(rate, 1e-9)
        print(
            f"[{self.name}] {step:,}/{self.total:,} {rate:,.1f} it/s ETA {eta / 60:.1f} min {extra}",
            flush=True,
        )


# --------------------------------------------------------------------------------------------------
# Stage 1: paired data in compressed uint8 shards
# --------------------------------------------------------------------------------------------------
def shard_paths(folder: Path) -> list[Path]:
    return sorted(folder.glob("shard_*.npz"))


def write_shard(folder: Path, image: np.ndarray, attr: np.ndarray, source, task="") -> Path:
    """One compressed shard; ``source`` ("random" / "expert") and ``task`` label every sample (a single
    string labels them all)."""
    folder.mkdir(parents=True, exist_ok=True)
    existing = shard_paths(folder)
    index = int(existing[-1].stem.split("_")[1]) + 1 if existing else 0
    path = folder / f"shard_{index:05d}.npz"
    tmp = folder / f".tmp_shard_{index:05d}.npz"
    n = len(attr)
    source, task = np.broadcast_to(np.asarray(source), (n,)), np.broadcast_to(np.asarray(task), (n,))
    np.savez_compressed(tmp, image=image, attr=attr.astype(np.float32), source=source, task=task)
    os.replace(tmp, path)
    return path


@contextlib.contextmanager
def read_shard(path: Path):
    """``np.load`` of one data shard; a damaged one (cut short, not a zip, a member missing) stops the run
    with one line that names it."""
    try:
        with np.load(path) as d:
            yield d
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        brief = " ".join(str(err).split())[:120]
        raise UsageError(
            f"cannot read the data shard {path} ({type(err).__name__}: {brief}): it is damaged; delete it "
            "and run the collect stage again, which collects the samples that are missing"
        ) from err


def load_labels(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample (source, task) of every shard of ``folder``, in the order of ``load_data``."""
    sources, tasks = [], []
    for p in shard_paths(folder):
        with read_shard(p) as d:
            n = len(d["attr"])
            sources.append(np.broadcast_to(d["source"], (n,)))
            tasks.append(np.broadcast_to(d["task"], (n,)) if "task" in d else np.full(n, ""))
    return np.concatenate(sources), np.concatenate(tasks)


def label_counts(folder: Path) -> dict[str, int]:
    """Samples per "source/task" label, e.g. {"expert/push_green": 500, "random/": 500}."""
    sources, tasks = load_labels(folder)
    labels, counts = np.unique(
        np.char.add(np.char.add(sources.astype(str), "/"), tasks.astype(str)), return_counts=True
    )
    return {str(k): int(v) for k, v in zip(labels, counts, strict=True)}


def load_data(folder: Path, env: str) -> tuple[np.ndarray, np.ndarray]:
    """All shards of ``folder``, checked against the environment's shapes and dtypes."""
    paths = shard_paths(folder)
    if not paths:
        data = "" if folder.parent == Path("data") else f" --data-dir {folder.parent}"
        raise UsageError(
            f"no data shards in {folder}; collect them with "
            f"`python pretrain_vae_gw.py --env {env} --stages collect{data}` (and the flags of your run)"
        )
    spec = ENV_SPECS[env]
    images, attrs = [], []
    for p in paths:
        with read_shard(p) as d:
            img, attr = d["image"], d["attr"]
        if img.dtype != np.uint8 or img.shape[1:] != (spec["image"], spec["image"], 3):
            raise UsageError(f"{p}: images {img.dtype} {img.shape[1:]} do not match env {env}")
        if attr.shape != (len(img), spec["attr"]) or not np.all(np.isfinite(attr)):
            raise UsageError(f"{p}: attributes {attr.shape} (or non-finite values) do not match env {env}")
        images.append(img)
        attrs.append(attr)
    return np.concatenate(images), np.concatenate(attrs)


def collect(args: Args, stop: StopRequest) -> None:
    folder = env_dir(args.data_dir, args)
    check_data(folder, args)
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".manifest.{os.getpid()}.json"  # written before the first shard, atomically
    tmp.write_text(json.dumps(data_identity(args), indent=1))
    os.replace(tmp, folder / "manifest.json")
    have = 0
    for p in shard_paths(folder):
        with read_shard(p) as d:  # reads only the attribute array, and closes the file
            have += len(d["attr"])
    need = args.n_samples - have
    if need <= 0:
        print(f"[collect] {folder} already holds {have:,} samples >= {args.n_samples:,}")
        return
    progress = Progress("collect", args.n_samples, have)
    rng_seed = args.seed * 1_000_003 + have  # appending draws fresh states
    if args.env == "simple_shapes":  # one job per shard, seeded rng_seed, rng_seed + 1, ...
        sizes = [min(args.shard_size, need - k) for k in range(0, need, args.shard_size)]
        jobs = [(n, rng_seed + i, args.wide_share) for i, n in enumerate(sizes)]
        with Workers(args.workers, shapes_shard, {}) as results:
            for d in results(jobs):
                write_shard(folder, d["image"], d["attr"], np.where(d["wide"], "random_wide", "random"), "")
                need, have = need - len(d["attr"]), have + len(d["attr"])
                progress.show(have)
                if stop.requested and need > 0:
                    interrupted(f"collect stage with {have:,} samples in {folder}")
        return

    collect_robodesk(args, folder, need, have, rng_seed, progress, stop)


class Workers:
    """``workers`` processes (spawned: each starts its own simulator and renderer) that run ``fn`` over
    jobs and hand the results back in the jobs' order, so the data do not depend on their number; one
    worker runs the jobs in this process. ``context`` is what every worker sets up once (WORKER)."""

    def __init__(self, workers: int, fn, context: dict):
        self.workers, self.fn, self.context, self.pool = workers, fn, context, None

    def __enter__(self):
        if self.workers > 1:
            spawn = mp.get_context("spawn")
            self.pool = spawn.Pool(self.workers, init_worker, (self.context, True))
        else:
            init_worker(self.context, False)
        return self.results

    def results(self, jobs):
        return self.pool.imap(self.fn, jobs) if self.pool else map(self.fn, jobs)

    def __exit__(self, *exc) -> None:
        if self.pool:
            self.pool.terminate()  # nothing is left to do (or Ctrl-C stopped the stage): no waiting
            self.pool.join()
        for env in WORKER.pop("envs", {}).values():
            env.close()


WORKER: dict = {}  # what one collecting process keeps between jobs: its settings, envs and expert programs


def init_worker(context: dict, subprocess: bool) -> None:
    if subprocess:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle
        torch.set_num_threads(1)
    WORKER.clear()
    WORKER.update(context, envs={})
    paths = context.get("learned", {})
    WORKER["learned"] = {task: ExpertProgram(Path(p)) for task, p in paths.items()}


def shapes_shard(job: tuple[int, int, float]) -> dict[str, np.ndarray]:
    """One Simple Shapes shard: ``n`` random states drawn with ``seed`` and rendered."""
    from envs.simple_shapes import sample_dataset

    n, seed, wide_share = job
    return sample_dataset(n, seed=seed, wide_share=wide_share)


def robodesk_plan(args: Args, need: int, learned: tuple[str, ...] = ()) -> list[tuple[str, str, int]]:
    """(source, task, samples) blocks: an equal expert share per task, the rest random (random episodes
    run in the first task's env; the task only changes the reward, which is not stored). A task needs a
    scripted expert unless ``learned`` (tasks with a dreamer_baseline.py policy) holds it."""
    from envs.robodesk import TASKS
    from envs.robodesk_experts import EXPERTS

    tasks = tuple(args.tasks) or (args.task,)
    frac = len(tasks) / (len(tasks) + 1) if args.expert_fraction is None else args.expert_fraction
    if not 0.0 <= frac <= 1.0:
        raise UsageError(f"--expert-fraction must be in [0, 1], got {frac}")
    for t in tasks:
        if t not in TASKS:
            raise UsageError(f"unknown RoboDesk task {t!r}; valid tasks: {', '.join(TASKS)}")
        if frac > 0 and t not in EXPERTS and t not in learned:
            raise UsageError(
                f"no scripted expert for {t!r}; experts exist for {', '.join(EXPERTS)} (or give its "
                f"dreamer_baseline.py policy with --expert-checkpoint, or --expert-fraction 0 for random "
                f"data only)"
            )
    if not 0.0 <= args.wander_fraction <= 1.0:
        raise UsageError(f"--wander-fraction must be in [0, 1], got {args.wander_fraction}")
    wander = int(round(need * args.wander_fraction))
    per_task = int(round((need - wander) * frac)) // len(tasks)
    experts = [("expert", t, per_task) for t in tasks if per_task > 0]
    wanderer = [("wander", tasks[0], wander)] if wander else []
    return experts + wanderer + [("random", tasks[0], need - wander - per_task * len(experts))]


class ExpertProgram:
    """A policy exported by dreamer_baseline.py (torch.export program + meta.json): runs without that
    file's code. Inputs: image, attributes, recurrent state (deter, stoch), previous action, episode-start
    flag and the noise it samples with; outputs: action and the next state."""

    def __init__(self, path: Path):
        self.path = path
        extra = {"meta.json": ""}
        try:
            self.program = torch.export.load(path, extra_files=extra).module()
            self.meta = json.loads(extra["meta.json"])
        except Exception as err:  # not a torch.export archive, or one without the description
            raise UsageError(
                f"{path} is not a policy exported by dreamer_baseline.py ({type(err).__name__}: {err}); "
                f"train one with `python dreamer_baseline.py --env robodesk --task TASK`"
            ) from err
        if self.meta.get("kind") != "dreamer_policy":
            raise UsageError(f"{path} describes a {self.meta.get('kind')!r}, not a dreamer_policy")

    def start(self, noise: float, seed: int) -> LearnedExpert:
        return LearnedExpert(self, noise, seed)


class LearnedExpert:
    """One episode stream of an ``ExpertProgram``: keeps its recurrent state; ``noise`` adds Gaussian
    noise to the actions like the scripted experts' option."""

    def __init__(self, program: ExpertProgram, noise: float, seed: int):
        self.program, self.noise = program, noise
        self.gen = torch.Generator().manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self.reset()

    def reset(self) -> None:
        m = self.program.meta
        self.deter, self.stoch = torch.zeros(1, m["deter"]), torch.zeros(1, m["stoch"])
        self.prev, self.first = torch.zeros(1, m["actions"]), torch.ones(1)

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        m = self.program.meta
        noise_z = torch.rand(1, *m["latents"], generator=self.gen)
        noise_a = torch.randn(1, m["actions"], generator=self.gen)
        image, attr = (
            torch.as_tensor(obs["image"])[None],
            torch.as_tensor(obs["attr"], dtype=torch.float32)[None],
        )
        state = (self.deter, self.stoch, self.prev, self.first)
        action, self.deter, self.stoch = self.program.program(image, attr, *state, noise_z, noise_a)
        self.prev, self.first = action, torch.zeros(1)
        a = action[0].numpy().astype(np.float64)
        return np.clip(a + self.rng.normal(0, self.noise, a.shape), -1, 1) if self.noise else a


def load_expert_policies(paths: tuple[str, ...], expert_tasks: list[str]) -> dict[str, ExpertProgram]:
    """Task -> exported dreamer_baseline.py policy, checked to be a RoboDesk policy for a task whose
    expert data is being collected (one per task)."""
    out = {}
    for given in paths:
        path = Path(given)
        if path.suffix == ".pt":  # the agent checkpoint: its exported policy sits beside it
            path = path.with_suffix(".policy.pt2")
        if not path.is_file():
            raise UsageError(
                f"no exported policy at {path}; `python dreamer_baseline.py --env robodesk --task TASK` "
                f"writes <agent checkpoint>.policy.pt2 with every checkpoint"
            )
        program = ExpertProgram(path)
        env, task = program.meta.get("env"), program.meta.get("task")
        if env != "robodesk":
            raise UsageError(f"{path} is a policy for env {env!r}; RoboDesk data needs a robodesk policy")
        if task not in expert_tasks:
            raise UsageError(
                f"{path} is an expert for {task!r}, which is not among the tasks collected "
                f"({', '.join(expert_tasks) or 'none'}); add it with --tasks"
            )
        if task in out:
            raise UsageError(f"two expert policies for {task!r}: {out[task].path} and {path}")
        out[task] = program
    return out


def robodesk_jobs(
    blocks: list[tuple[str, str, int]], seed: int, steps: int
) -> list[tuple[str, str, int, int]]:
    """(source, task, samples, seed) of every episode of ``blocks``, ``steps`` samples per episode. The
    blocks take turns (an episode of each task's expert, one random, then again), so that every shard,
    and the held-out samples at the front of the data, hold every source."""
    per_block = [
        [(src, t, min(steps, n - e * steps), episode_seed(seed, b, e)) for e in range(math.ceil(n / steps))]
        for b, (src, t, n) in enumerate(blocks)
    ]
    return [block[e] for e in range(max(map(len, per_block))) for block in per_block if e < len(block)]


def episode_seed(seed: int, block: int, episode: int) -> int:
    """The seed of one collected episode (its reset, random actions and expert noise): episodes do not
    share a random stream, so any process can run any of them."""
    return int(np.random.SeedSequence([seed, block, episode]).generate_state(1)[0])


def robodesk_episode(job: tuple[str, str, int, int]) -> dict:
    """One episode of the scripted expert, the exported policy, the wanderer or the random policy of
    ``task``, cut at ``n`` samples: the observations (image, attributes) seen before each action."""
    from envs.robodesk import RoboDeskEnv
    from envs.robodesk_experts import EXPERTS, Wanderer

    source, task, n, seed = job
    if task not in WORKER["envs"]:
        WORKER["envs"][task] = RoboDeskEnv(task=task, render_quality=WORKER["render_quality"])
    env, noise = WORKER["envs"][task], WORKER["noise"]
    obs, _ = env.reset(seed=seed)
    rng, policy = np.random.default_rng(seed), None
    if source == "expert":
        learned = WORKER["learned"].get(task)
        policy = (
            learned.start(noise=noise, seed=seed) if learned else EXPERTS[task](env, noise=noise, seed=seed)
        )
    elif source == "wander":
        policy = Wanderer(env, seed=seed)
    images, attrs, done = [], [], False
    while len(attrs) < n and not done:
        images.append(obs["image"])
        attrs.append(obs["attr"])
        if isinstance(policy, LearnedExpert):
            action = policy.act(obs)
        else:
            action = policy.act(env) if policy is not None else rng.uniform(-1, 1, 5)
        obs, _, term, trunc, _ = env.step(action)
        done = term or trunc
    label = task if source == "expert" else ""  # random data are no task's (the task only sets the reward)
    return {"image": np.stack(images), "attr": np.stack(attrs), "source": source, "task": label, "env": task}


def collect_robodesk(
    args: Args, folder: Path, need: int, have: int, seed: int, progress: Progress, stop: StopRequest
) -> None:
    """Full episodes of the scripted experts (with action noise) and of a uniformly random policy, in the
    proportions of ``robodesk_plan``, written as labelled shards; ``--workers`` processes run them."""
    from envs.robodesk import RoboDeskEnv

    learned = load_expert_policies(args.expert_checkpoint, list(args.tasks or (args.task,)))
    blocks = robodesk_plan(args, need, tuple(learned))
    print("[collect] RoboDesk data: " + ", ".join(f"{n:,} {src} ({t})" for src, t, n in blocks if n))
    for src, t, n in blocks:
        if src == "expert" and n:
            who = (
                f"the dreamer_baseline.py policy {learned[t].path}" if t in learned else "its scripted expert"
            )
            print(f"[collect] expert data of {t}: {who}")
    defaults = inspect.signature(RoboDeskEnv).parameters  # the env the episodes run in: the paper's
    steps = defaults["episode_length"].default // defaults["action_repeat"].default  # 500, no early end
    jobs = robodesk_jobs(blocks, seed, steps)
    buf, pending = {"image": [], "attr": [], "source": [], "task": []}, 0  # episodes not yet in a shard

    def flush(force: bool) -> None:
        nonlocal have, pending
        if pending < args.shard_size and not (force and pending):
            return
        data = {key: np.concatenate(v) for key, v in buf.items()}
        k = 0
        while pending - k >= args.shard_size or (force and k < pending):
            m = min(args.shard_size, pending - k)
            write_shard(folder, *(data[key][k : k + m] for key in ("image", "attr", "source", "task")))
            k += m
        buf.update({key: [v[k:]] if k < pending else [] for key, v in data.items()})
        have, pending = have + k, pending - k

    context = {"render_quality": args.render_quality, "noise": args.expert_noise}
    context["learned"] = {t: str(program.path) for t, program in learned.items()}
    with Workers(args.workers, robodesk_episode, context) as results:
        for ep in results(jobs):
            n = len(ep["attr"])
            for key in ("image", "attr"):
                buf[key].append(ep[key])
            buf["source"].append(np.full(n, ep["source"]))
            buf["task"].append(np.full(n, ep["task"]))
            pending += n
            flush(stop.requested)  # Ctrl-C: the samples so far go to a shard of their own
            # one line per episode (a 50k-sample shard is a quarter of an hour of RoboDesk on a CPU)
            progress.show(have + pending, f"({ep['source']}, {ep['env']})")
            if stop.requested:
                interrupted(f"collect stage with {have:,} samples in {folder}")
    flush(True)


# --------------------------------------------------------------------------------------------------
# Training data, in memory or streamed from the shards; one process or many (torchrun)
# --------------------------------------------------------------------------------------------------
class InMemory:
    """Every shard loaded at once (--stream-shards 0): sampling from the whole data, memory that grows
    with it (12.3 kB per RoboDesk sample). The first ``n_eval`` samples are held out."""

    def __init__(self, folder: Path, env: str, n_eval: int):
        self.images, self.attrs = load_data(folder, env)
        self.env, self.train_idx = env, np.arange(n_eval, len(self.attrs))

    def __len__(self) -> int:
        return len(self.attrs)

    def held_out(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        return self.images[:n], self.attrs[:n]

    def train_attr_moments(self) -> tuple[np.ndarray, np.ndarray]:
        return normaliser(self.attrs[self.train_idx], self.env)

    def advance(self, step: int) -> None:  # the whole data is always there
        pass

    def batch(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        idx = rng.choice(self.train_idx, n)
        return self.images[idx], self.attrs[idx]

    def attr_batch(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return self.attrs[rng.choice(self.train_idx, n)]

    def chunks(self):
        """(images, attributes) of every sample, in order (the GW stage encodes them)."""
        yield self.images, self.attrs


class Streamed:
    """--stream-shards K: K shards in memory, from which batches are drawn as from the whole data; every
    ``period`` steps the oldest gives way to the next shard of a shuffled order (a new one per pass), read
    ahead in a thread and copied into the slot it frees. Memory: about K + 1 shards, whatever the number
    of shards. The shard order and the batches depend only on the seed and the step, so every process of
    a torchrun draws the same ones."""

    def __init__(self, folder: Path, env: str, n_eval: int, k: int, seed: int, batch: int):
        self.paths, self.env, self.n_eval, self.seed = shard_paths(folder), env, n_eval, seed
        if not self.paths:
            load_data(folder, env)  # its message: no shards, and the command that collects them
        self.sizes = []
        for p in self.paths:
            with read_shard(p) as d:  # the attribute member only
                self.sizes.append(len(d["attr"]))
        self.starts = np.cumsum([0, *self.sizes[:-1]])  # global index of each shard's first sample
        self.k = min(k, len(self.paths))
        self.period = max(1, round(np.mean(self.sizes) / batch))  # about one pass over the data per pass
        self.window, self.slots, self.lengths, self.perms = None, {}, {}, {}  # slots: shard -> buffer place
        self.reader, self.ahead = ThreadPoolExecutor(1), None
        room, spec = max(self.sizes), ENV_SPECS[env]
        self.room = room
        self.images = np.empty((self.k * room, spec["image"], spec["image"], 3), np.uint8)
        self.attrs = np.empty((self.k * room, spec["attr"]), np.float32)

    def __len__(self) -> int:
        return int(sum(self.sizes))

    def shard(self, i: int, train: bool) -> tuple[np.ndarray, np.ndarray]:
        """Shard i, checked; with ``train`` its held-out samples are removed."""
        spec = ENV_SPECS[self.env]
        with read_shard(self.paths[i]) as d:
            img, attr = d["image"], d["attr"]
        if img.dtype != np.uint8 or img.shape[1:] != (spec["image"], spec["image"], 3):
            raise UsageError(
                f"{self.paths[i]}: images {img.dtype} {img.shape[1:]} do not match env {self.env}"
            )
        keep = max(0, self.n_eval - self.starts[i]) if train else 0
        return img[keep:], attr[keep:]

    def order(self, j: int) -> int:
        """The j-th shard of the endless sequence of shuffled passes."""
        p, r = divmod(j, len(self.paths))
        if p not in self.perms:
            self.perms = {p: np.random.default_rng([self.seed, p]).permutation(len(self.paths))}
        return int(self.perms[p][r])

    def advance(self, step: int) -> None:
        """Before training step ``step`` (1-based): the K shards of that step in memory."""
        c = (step - 1) // self.period
        if c == self.window:
            return
        want, j = [], c
        while len(want) < self.k:  # K different shards (a pass's end and the next pass's start may share one)
            if self.order(j) not in want:
                want.append(self.order(j))
            j += 1
        free = [slot for i, slot in self.slots.items() if i not in want]
        free += [slot for slot in range(self.k) if slot not in self.slots.values()]
        self.slots = {i: slot for i, slot in self.slots.items() if i in want}
        rows = []
        for i in want:
            if i not in self.slots:  # read ahead (or now), then copied into a freed slot
                ready = self.ahead is not None and self.ahead[0] == i
                img, attr = self.ahead[1].result() if ready else self.shard(i, True)
                self.slots[i] = slot = free.pop()
                self.images[slot * self.room : slot * self.room + len(img)] = img
                self.attrs[slot * self.room : slot * self.room + len(attr)] = attr
                self.lengths[i] = len(attr)
            rows.append(self.slots[i] * self.room + np.arange(self.lengths[i]))
        self.rows = np.concatenate(rows)  # buffer rows of the K shards, in the order of ``want``
        nxt = self.order(j)
        self.ahead = (nxt, self.reader.submit(self.shard, nxt, True)) if nxt not in want else None
        self.window = c

    def batch(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        idx = self.rows[rng.integers(0, len(self.rows), n)]
        return self.images[idx], self.attrs[idx]

    def attr_batch(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return self.attrs[self.rows[rng.integers(0, len(self.rows), n)]]

    def held_out(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        parts, have = [], 0
        for i in range(len(self.paths)):
            if have >= n:
                break
            parts.append(self.shard(i, False))
            have += len(parts[-1][1])
        return np.concatenate([p[0] for p in parts])[:n], np.concatenate([p[1] for p in parts])[:n]

    def train_attr_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """The normaliser of the training attributes, read from the shards' attribute members."""
        if self.env == "simple_shapes":  # fixed scale: nothing to read
            return normaliser(np.zeros((1, ENV_SPECS[self.env]["attr"]), np.float32), self.env)
        parts = []
        for i in range(len(self.paths)):  # the attribute members only (0.3 kB per RoboDesk sample)
            keep = max(0, self.n_eval - self.starts[i])
            with read_shard(self.paths[i]) as d:
                parts.append(d["attr"][keep:])
        return normaliser(np.concatenate(parts), self.env)

    def chunks(self):
        for i in range(len(self.paths)):
            yield self.shard(i, False)


def training_data(args: Args, n_eval: int, batch: int):
    folder = env_dir(args.data_dir, args)
    if args.stream_shards:
        return Streamed(folder, args.env, n_eval, args.stream_shards, args.seed, batch)
    return InMemory(folder, args.env, n_eval)


def data_size(args: Args) -> int:
    """Samples in the data folder, read from the shards' attribute members only."""
    total = 0
    for p in shard_paths(env_dir(args.data_dir, args)):
        with read_shard(p) as d:
            total += len(d["attr"])
    return total


def start_processes(args: Args) -> tuple[int, int]:
    """(rank, number of processes): under torchrun the process group (gloo on a CPU, NCCL on GPUs, one
    GPU per process), else (0, 1)."""
    world = int(os.environ.get("WORLD_SIZE", 1))
    if world == 1:
        return 0, 1
    if not dist.is_initialized():
        cuda = args.device.startswith("cuda")
        if cuda:
            args.device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}"
            torch.cuda.set_device(args.device)
        dist.init_process_group("nccl" if cuda else "gloo")
    return dist.get_rank(), world


def my_slice(x, rank: int, world: int):
    """This process's rows of a global batch (contiguous slices, in rank order)."""
    n = len(x) // world
    return x[rank * n : (rank + 1) * n]


def gather_rows(x: torch.Tensor) -> torch.Tensor:
    """Every process's rows, in rank order, with gradients flowing back to each process's own."""
    if not (dist.is_initialized() and dist.get_world_size() > 1):
        return x
    return torch.cat(dist_nn.all_gather(x))


def barrier() -> None:
    """Under torchrun: wait until every process is here."""
    if dist.is_initialized() and dist.get_world_size() > 1:
        dist.barrier()


def any_process(flag: bool) -> bool:
    """True if any process has ``flag`` set (a Ctrl-C reaches them at different steps)."""
    if not (dist.is_initialized() and dist.get_world_size() > 1):
        return flag
    t = torch.tensor([float(flag)], device="cuda" if dist.get_backend() == "nccl" else "cpu")
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item())


class GlobalBatchNorm2d(nn.BatchNorm2d):
    """BatchNorm over the global batch of all processes (what SyncBatchNorm does, but on any backend:
    torch's own needs a GPU), so that many processes train what one process does on the whole batch.
    One process: plain BatchNorm2d."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        c = x.shape[1]
        count = torch.full((1,), x.numel() / c, device=x.device, dtype=x.dtype)
        stats = dist_nn.all_reduce(torch.cat([x.sum((0, 2, 3)), (x * x).sum((0, 2, 3)), count]))
        n = stats[-1]
        mean = stats[:c] / n
        var = stats[c : 2 * c] / n - mean * mean
        with torch.no_grad():
            self.running_mean.lerp_(mean, self.momentum)
            self.running_var.lerp_(var * n / (n - 1), self.momentum)
            self.num_batches_tracked += 1
        scale = self.weight / torch.sqrt(var + self.eps)
        return x * scale[None, :, None, None] + (self.bias - mean * scale)[None, :, None, None]


def global_batch_norm(module: nn.Module) -> nn.Module:
    """``module`` with its BatchNorm2d layers computing global-batch statistics (same state dict)."""
    for m in module.modules():
        if type(m) is nn.BatchNorm2d:
            m.__class__ = GlobalBatchNorm2d
    return module


class Loss(nn.Module):
    """``fn(module, *inputs)`` as a module, so that DistributedDataParallel wraps the loss computation
    (its gradient averaging starts in forward)."""

    def __init__(self, module: nn.Module, fn):
        super().__init__()
        self.module, self.fn = module, fn

    def forward(self, *inputs):
        return self.fn(self.module, *inputs)


def parallel(module: nn.Module, fn, world: int) -> nn.Module:
    """The loss of ``module`` as DistributedDataParallel across the processes (or as it is for one)."""
    loss = Loss(module, fn)
    return DDP(loss, broadcast_buffers=False) if world > 1 else loss


# --------------------------------------------------------------------------------------------------
# Stage 2: beta-VAEs (appendix Tables VAE_v and VAE_attr)
# --------------------------------------------------------------------------------------------------
def conv_block(cin: int, cout: int, transpose: bool = False, stride: int = 2) -> nn.Sequential:
    conv = (nn.ConvTranspose2d if transpose else nn.Conv2d)(
        cin, cout, 4 if stride == 2 else 3, stride, 1, bias=False
    )
    return nn.Sequential(conv, nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class VisualVAE(nn.Module):
    """Conv encoder (kernel 4, stride 2, BatchNorm, ReLU) to FC_{2 x latent}; decoder FC_{8x8xwidth},
    transposed convolutions up to the image size, then Conv_3 - Sigmoid (an RGB image;
    docs/paper_readings.md). Simple Shapes: channels 128-256-512-1024 (32 -> 2 pixels); RoboDesk:
    64-128-256-512-1024 (64 -> 2). The decoder's last transposed convolution keeps the resolution
    (stride 1) so the listed layers end at the image size."""

    def __init__(self, image: int, latent: int, width: int = 1024):
        super().__init__()
        n_down = int(np.log2(image)) - 1  # down to 2x2
        chans = [width // 2 ** (n_down - 1 - i) for i in range(n_down)]
        layers, cin = [], 3
        for c in chans:
            layers.append(conv_block(cin, c))
            cin = c
        self.encoder = nn.Sequential(*layers, nn.Flatten())
        self.q = nn.Linear(width * 4, 2 * latent)  # mean and log-variance
        n_up = int(np.log2(image // 8))
        up = [width // 2 ** (i + 1) for i in range(n_up)] + [width // 2**n_up]
        self.width = width
        self.fc = nn.Linear(latent, 8 * 8 * width)
        dec, cin = [], width
        for i, c in enumerate(up):
            dec.append(conv_block(cin, c, transpose=True, stride=2 if i < n_up else 1))
            cin = c
        self.decoder = nn.Sequential(*dec, nn.Conv2d(cin, 3, 3, 1, 1), nn.Sigmoid())

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, logvar = self.q(self.encoder(x)).chunk(2, dim=-1)
        return mean, logvar

    def decode(self, u: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.fc(u).view(-1, self.width, 8, 8))

    def loss(self, x: torch.Tensor, beta: float, eps: torch.Tensor | None = None):
        """beta-VAE loss; ``eps``: the reparameterisation noise (default: drawn here)."""
        mean, logvar = self.encode(x)
        eps = torch.randn_like(mean) if eps is None else eps
        u = mean + eps * (0.5 * logvar).exp()
        recon = ((self.decode(u) - x) ** 2).flatten(1).sum(1).mean()  # unit-variance Gaussian
        kl = (-0.5 * (1 + logvar - mean**2 - logvar.exp()).sum(1)).mean()
        return recon + beta * kl, recon, kl


class AttrVAE(nn.Module):
    """MLP VAE. Simple Shapes: 11 -> 64 -> 64 -> 10 -> FC_{2x10}; decoder 64 -> 64 -> (FC_3 class
    logits, FC_8 - Tanh). RoboDesk: 76 -> 4 x 512 -> 40 -> FC_{2x40}; decoder 4 x 512 -> FC_76
    (standardised attributes)."""

    def __init__(self, attr: int, latent: int, hidden: int, depth: int, n_classes: int = 0):
        super().__init__()
        enc, cin = [], attr
        for _ in range(depth):
            enc += [nn.Linear(cin, hidden), nn.ReLU()]
            cin = hidden
        self.encoder = nn.Sequential(
            *enc, nn.Linear(hidden, latent), nn.ReLU(), nn.Linear(latent, 2 * latent)
        )
        dec, cin = [], latent
        for _ in range(depth):
            dec += [nn.Linear(cin, hidden), nn.ReLU()]
            cin = hidden
        self.decoder = nn.Sequential(*dec, nn.Linear(hidden, attr))
        self.n_classes = n_classes

    def encode(self, a: torch.Tensor):
        return self.encoder(a).chunk(2, dim=-1)

    def decode_raw(self, u: torch.Tensor) -> torch.Tensor:
        out = self.decoder(u)
        if self.n_classes:  # class logits | tanh attributes
            return torch.cat([out[:, : self.n_classes], torch.tanh(out[:, self.n_classes :])], 1)
        return out

    def decode(self, u: torch.Tensor) -> torch.Tensor:
        """Attribute vector (class one-hot from the arg-max logits)."""
        out = self.decode_raw(u)
        if self.n_classes:
            one_hot = F.one_hot(out[:, : self.n_classes].argmax(1), self.n_classes).float()
            return torch.cat([one_hot, out[:, self.n_classes :]], 1)
        return out

    def loss(self, a: torch.Tensor, beta: float, eps: torch.Tensor | None = None):
        mean, logvar = self.encode(a)
        eps = torch.randn_like(mean) if eps is None else eps
        u = mean + eps * (0.5 * logvar).exp()
        out = self.decode_raw(u)
        if self.n_classes:
            recon = (
                F.cross_entropy(out[:, : self.n_classes], a[:, : self.n_classes].argmax(1))
                + ((out[:, self.n_classes :] - a[:, self.n_classes :]) ** 2).sum(1).mean()
            )
        else:
            recon = ((out - a) ** 2).sum(1).mean()
        kl = (-0.5 * (1 + logvar - mean**2 - logvar.exp()).sum(1)).mean()
        return recon + beta * kl, recon, kl


def make_vaes(env: str, width: int) -> tuple[VisualVAE, AttrVAE]:
    s = ENV_SPECS[env]
    vae_v = VisualVAE(s["image"], s["latent"], width)
    if env == "simple_shapes":
        vae_attr = AttrVAE(s["attr"], s["latent"], 64, 2, n_classes=3)
    else:
        vae_attr = AttrVAE(s["attr"], s["latent"], 512, 4)
    return vae_v, vae_attr


def load_vaes(path: Path, env: str, make: str = "") -> tuple[VisualVAE, AttrVAE, dict]:
    """Frozen VAEs from a ``vae`` checkpoint (eval mode, no gradients); ``make``: the command making it."""
    ckpt = load_checkpoint(
        path, "vae", env, make or f"python pretrain_vae_gw.py --env {env} --stages collect vae"
    )
    vae_v, vae_attr = make_vaes(env, ckpt["config"]["vae_width"])
    vae_v.load_state_dict(ckpt["vae_v"])
    vae_attr.load_state_dict(ckpt["vae_attr"])
    for m in (vae_v, vae_attr):
        m.eval().requires_grad_(False)
    return vae_v, vae_attr, ckpt


def images_to_tensor(images: np.ndarray, device) -> torch.Tensor:
    """uint8 (B, H, W, 3) -> float (B, 3, H, W) in [0, 1], kept in channels-last memory order: the
    stored order, and the one the CPU convolutions of the visual VAE run fastest in (together with
    channels-last weights, see train_vae)."""
    x = torch.as_tensor(images, device=device).permute(0, 3, 1, 2).float() / 255.0
    return x.contiguous(memory_format=torch.channels_last)


def one_cycle(opt, max_lr, start_end, steps):
    """OneCycleLR from start_end up to max_lr and back down to start_end (appendix tables)."""
    return torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=max_lr, total_steps=max(steps, 2), div_factor=max_lr / start_end, final_div_factor=1.0
    )


def optimise(opt, sched, loss: torch.Tensor, where: str) -> None:
    """One update; a non-finite loss stops training with a message saying where."""
    if not torch.isfinite(loss):
        raise FloatingPointError(f"non-finite {where}")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    sched.step()


# RoboDesk attributes that barely move in the data (a button never pressed, the ball's height: stds of
# 1e-6 to 1e-4) would become unit-variance noise if divided by their own std, and the attribute VAE would
# spend latent dimensions on it; their scale is floored at 1 mm (or mrad, mm/s) instead.
ATTR_STD_FLOOR = 1e-3
# Object velocities and quaternions are still most of the time and spike on contact (over 90% of their
# variance lies in samples beyond 5 std); divided by their std they put values of 10 to 100 into the
# attribute VAE's squared error, which then fits the spikes of its training episodes and reconstructs the
# held-out ones worse (docs/pretrain_vae_gw.md). Such a dimension's scale is widened until
# ATTR_TAIL[0] % of the samples lie within +-ATTR_TAIL[1].
ATTR_TAIL = (99.9, 3.0)
# The end effector's position (attr 18-20) in units of 2 cm rather than of its std (17-32 cm): an agent
# action moves it by 1-4 cm, and every dense reward is linear in its distance to a target. Scaled by its
# std it weighs 3/76 of the attribute VAE's squared error, which then reconstructs it within 5.6 cm (10 cm
# on 44,000 samples); in 2 cm units within 2.1 cm on those samples (docs/pretrain_vae_gw.md).
END_EFFECTOR_ATTRS, END_EFFECTOR_UNIT = slice(18, 21), 0.02


def normaliser(attr: np.ndarray, env: str) -> tuple[np.ndarray, np.ndarray]:
    """Simple Shapes attributes are already in [-1, 1]; RoboDesk's are centred and scaled by their std,
    floored at ATTR_STD_FLOOR and widened for heavy tails (ATTR_TAIL), except the end effector's
    position, in END_EFFECTOR_UNIT metres."""
    if env == "simple_shapes":
        return np.zeros(attr.shape[1], np.float32), np.ones(attr.shape[1], np.float32)
    mean = attr.mean(0, dtype=np.float64)
    tail = np.percentile(np.abs(attr - mean), ATTR_TAIL[0], axis=0) / ATTR_TAIL[1]
    scale = np.maximum(np.maximum(attr.std(0, dtype=np.float64), ATTR_STD_FLOOR), tail)
    scale[END_EFFECTOR_ATTRS] = END_EFFECTOR_UNIT
    return mean.astype(np.float32), scale.astype(np.float32)


def train_vae(args: Args, writer: SummaryWriter, stop: StopRequest) -> None:
    path = env_dir(args.checkpoint_dir, args) / "vae.pt"
    identity = stage_identity(args, "vae")
    if stage_is_done(path, identity, args):
        return
    rank, world = start_processes(args)
    n_eval = min(args.eval_size, data_size(args) // 10)
    data = training_data(args, n_eval, args.vae_batch_size)
    mean, std = data.train_attr_moments()
    dev = torch.device(args.device)
    torch.manual_seed(args.seed)  # every process draws the same noise for the global batch
    vae_v, vae_attr = make_vaes(args.env, args.vae_width)
    # channels-last weights: with 16-channel 32x32 maps, oneDNN's CPU kernels ran ~1.4x faster here
    vae_v.to(dev, memory_format=torch.channels_last), vae_attr.to(dev)
    opts = [
        torch.optim.AdamW(vae_v.parameters(), lr=args.vae_lr_v, weight_decay=args.vae_weight_decay),
        torch.optim.AdamW(vae_attr.parameters(), lr=args.vae_lr_attr, weight_decay=args.vae_weight_decay),
    ]
    scheds = [
        one_cycle(opts[0], args.vae_lr_v, args.vae_lr_start_end, args.vae_steps),
        one_cycle(
            opts[1], args.vae_lr_attr, args.vae_lr_start_end, args.vae_steps * args.attr_updates_per_step
        ),
    ]
    partial = path.with_suffix(".partial.pt")
    start = 0
    ck = resume_partial(partial, identity, args, "vae")  # continue after an interruption
    if ck:
        vae_v.load_state_dict(ck["vae_v"]), vae_attr.load_state_dict(ck["vae_attr"])
        for o, s, so, ss in zip(opts, scheds, ck["opts"], ck["scheds"], strict=True):
            o.load_state_dict(so), s.load_state_dict(ss)
        start = ck["step"]
    # Many processes: each computes its slice of the global batch, gradients averaged (DDP), batch norm
    # over the global batch, so the updates are the one-process updates.
    loss_v_of = parallel(global_batch_norm(vae_v), VisualVAE.loss, world)
    loss_a_of = parallel(vae_attr, AttrVAE.loss, world)
    latent = ENV_SPECS[args.env]["latent"]

    def save_partial(step: int) -> None:
        state = {"opts": [o.state_dict() for o in opts], "scheds": [s.state_dict() for s in scheds]}
        weights = {"vae_v": vae_v.state_dict(), "vae_attr": vae_attr.state_dict()}
        if rank == 0:
            atomic_save(weights | state | {"step": step, "identity": identity}, partial)

    rng = np.random.default_rng(args.seed + start)
    progress = Progress("vae", args.vae_steps, start)
    vae_v.train(), vae_attr.train()
    b = args.vae_batch_size
    for step in range(start + 1, args.vae_steps + 1):
        data.advance(step)
        images, attrs = data.batch(rng, b)  # the global batch, the same in every process
        eps = my_slice(torch.randn(b, latent, device=dev), rank, world)
        x = images_to_tensor(my_slice(images, rank, world), dev)
        loss_v, recon_v, kl_v = loss_v_of(x, args.beta_v, eps)
        optimise(opts[0], scheds[0], loss_v, f"[vae] visual loss at step {step}; last good state: {partial}")
        for k in range(args.attr_updates_per_step):  # the attribute VAE is tiny: extra updates are cheap
            a_raw = attrs if k == 0 else data.attr_batch(rng, b)
            a = torch.as_tensor((my_slice(a_raw, rank, world) - mean) / std, device=dev)
            if args.attr_noise:  # drawn for the global batch, as eps, so every process adds its slice
                a = a + args.attr_noise * my_slice(torch.randn(b, a.shape[1], device=dev), rank, world)
            loss_a, recon_a, kl_a = loss_a_of(
                a, args.beta_attr, my_slice(torch.randn(b, latent, device=dev), rank, world)
            )
            optimise(opts[1], scheds[1], loss_a, f"[vae] attribute loss at step {step}; last good: {partial}")
        if rank == 0 and (step % args.log_every == 0 or step == args.vae_steps):
            for k, v in dict(
                loss_v=loss_v, recon_v=recon_v, kl_v=kl_v, loss_attr=loss_a, recon_attr=recon_a, kl_attr=kl_a
            ).items():
                writer.add_scalar(f"losses/vae_{k}", v.item(), step)
            writer.add_scalar("charts/vae_lr_v", scheds[0].get_last_lr()[0], step)
            progress.show(step, f"recon_v {recon_v.item():.2f} recon_attr {recon_a.item():.3f}")
        stopping = any_process(stop.requested)
        if (step % args.save_every == 0 or stopping) and step < args.vae_steps:
            save_partial(step)
        if stopping and step < args.vae_steps:
            interrupted(f"vae stage at step {step:,}: saved {partial}")
    vae_v.eval(), vae_attr.eval()
    if rank > 0:
        return barrier()  # rank 0 evaluates and writes the checkpoint the next stage reads
    images, attrs = data.held_out(n_eval)
    with torch.no_grad():
        x = images_to_tensor(images, dev)
        rec = vae_v.decode(vae_v.encode(x)[0])
        mse_v = F.mse_loss(rec, x).item()
        a = torch.as_tensor((attrs - mean) / std, device=dev)
        mse_attr = F.mse_loss(vae_attr.decode(vae_attr.encode(a)[0]), a).item()
        writer.add_images("vae/reconstructions", torch.cat([x[:8], rec[:8]]), args.vae_steps)
    print(
        f"[vae] held-out reconstruction MSE: image {mse_v:.5f} (pixels in [0, 1]), attributes {mse_attr:.5f}"
    )
    atomic_save(
        {
            "kind": "vae",
            "env": args.env,
            "identity": identity,
            "config": {"vae_width": args.vae_width, **ENV_SPECS[args.env]},
            "args": asdict(args),
            "vae_v": vae_v.state_dict(),
            "vae_attr": vae_attr.state_dict(),
            "attr_mean": mean,
            "attr_std": std,
            "data": {
                "folder": str(env_dir(args.data_dir, args)),
                "n_samples": len(data),
                "eval_samples": n_eval,
                "samples_per_source_and_task": label_counts(env_dir(args.data_dir, args)),
            },
            "eval": {"recon_mse_v": mse_v, "recon_mse_attr": mse_attr},
        },
        path,
    )
    partial.unlink(missing_ok=True)
    print(f"[vae] wrote {path}")
    barrier()


# --------------------------------------------------------------------------------------------------
# Stage 3: Global Workspace (eq. 1-3) and the CLIP-like variant
# --------------------------------------------------------------------------------------------------
def mlp(cin: int, hidden: int, cout: int, depth: int = 4) -> nn.Sequential:
    layers = []
    for _ in range(depth):
        layers += [nn.Linear(cin, hidden), nn.ReLU()]
        cin = hidden
    return nn.Sequential(*layers, nn.Linear(hidden, cout))


class GlobalWorkspace(nn.Module):
    """Encoders e_v, e_attr (u -> pre-fusion z^x) and decoders d_v, d_attr (z -> u), 4 hidden layers
    each (appendix Tables GW_SS / GW_Rob). z = tanh(alpha_v e_v(u_v) + alpha_attr e_attr(u_attr))."""

    def __init__(self, latent: int, z: int, hidden: int):
        super().__init__()
        self.e = nn.ModuleDict({"v": mlp(latent, hidden, z), "attr": mlp(latent, hidden, z)})
        self.d = nn.ModuleDict({"v": mlp(z, hidden, latent), "attr": mlp(z, hidden, latent)})

    def fuse(self, u_v, u_attr, alpha_v, alpha_attr) -> torch.Tensor:
        """GW state z from both unimodal latents with fusion weights (scalars or per-sample (B, 1))."""
        return torch.tanh(alpha_v * self.e["v"](u_v) + alpha_attr * self.e["attr"](u_attr))


PRESETS = {  # appendix Table "GW losses weights"
    "gw": {"dcy": 1.0, "cy": 1.0, "tr": 1.0, "fusion": 1.0, "cont": 0.1},
    "clip": {"dcy": 0.0, "cy": 0.0, "tr": 0.0, "fusion": 0.0, "cont": 1.0},
}


def gw_losses(
    gw: GlobalWorkspace, u: dict[str, torch.Tensor], alpha_fusion: torch.Tensor, temperature: float
):
    """The GW loss terms of eq. 1 and the contrastive loss, each family a mean over its terms.

    ``alpha_fusion`` (B, 1) holds alpha_v per sample for L_fusion (alpha_attr = 1 - alpha_v). Each decoder
    runs once on its demi-cycle, translation and fusion inputs stacked along the batch (one call of
    3B rows is cheaper on a CPU than three of B), and the cycle re-encodes the translations."""
    other = {"v": "attr", "attr": "v"}
    batch = len(u["v"])
    z_pre = {x: gw.e[x](u[x]) for x in u}  # pre-fusion z^v, z^attr
    z_uni = {x: torch.tanh(z_pre[x]) for x in u}  # alpha_x = 1, alpha_y = 0
    z_fused = torch.tanh(alpha_fusion * z_pre["v"] + (1 - alpha_fusion) * z_pre["attr"])
    decoded = {x: gw.d[x](torch.cat([z_uni[x], z_uni[other[x]], z_fused])).split(batch) for x in u}
    u_dcy = {x: decoded[x][0] for x in u}  # d_x(tanh(e_x(u_x)))
    u_tr = {x: decoded[x][1] for x in u}  # d_x(tanh(e_y(u_y))): x translated from the other modality
    u_fusion = {x: decoded[x][2] for x in u}
    # cycle x -> y -> x: encode the translation u_tr[y] (made from u_x) and decode back to x
    u_cy = {x: gw.d[x](torch.tanh(gw.e[other[x]](u_tr[other[x]]))) for x in u}
    loss_dcy = sum(F.mse_loss(u_dcy[x], u[x]) for x in u) / 2
    loss_tr = sum(F.mse_loss(u_tr[x], u[x]) for x in u) / 2
    loss_cy = sum(F.mse_loss(u_cy[x], u[x]) for x in u) / 2
    loss_fusion = sum(F.mse_loss(u_fusion[x], u[x]) for x in u) / 2
    # CLIP-style symmetric cross-entropy on L2-normalised pre-fusion encodings, fixed temperature.
    zv, za = F.normalize(z_pre["v"], dim=-1), F.normalize(z_pre["attr"], dim=-1)
    zv, za = gather_rows(zv), gather_rows(za)  # every pair of the global batch (torchrun: all processes)
    logits = zv @ za.T / temperature
    target = torch.arange(len(zv), device=zv.device)
    loss_cont = (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target)) / 2
    return {"dcy": loss_dcy, "cy": loss_cy, "tr": loss_tr, "fusion": loss_fusion, "cont": loss_cont}


def gw_terms(
    gw: GlobalWorkspace, u_v: torch.Tensor, u_a: torch.Tensor, alpha: torch.Tensor, temperature: float
):
    return gw_losses(gw, {"v": u_v, "attr": u_a}, alpha, temperature)


def fusion_weights(batch: int, temperature: float, generator: torch.Generator, device) -> torch.Tensor:
    """alpha_v per sample: softmax(U / T) over the two modalities, U uniform in [0, 1) (shimmer)."""
    uni = torch.rand(batch, 2, generator=generator).to(device)
    return torch.softmax(uni / temperature, dim=1)[:, :1]


def encode_unimodal(vae_v, vae_attr, images, attrs_n, device, batch: int = 1024):
    """VAE means u_v, u_attr of a whole dataset (the GW sees means, not samples)."""
    u_v, u_a = [], []
    with torch.no_grad():
        for i in range(0, len(images), batch):
            u_v.append(vae_v.encode(images_to_tensor(images[i : i + batch], device))[0])
            u_a.append(vae_attr.encode(torch.as_tensor(attrs_n[i : i + batch], device=device))[0])
    return torch.cat(u_v), torch.cat(u_a)


def train_gw(args: Args, writer: SummaryWriter, stop: StopRequest) -> None:
    vae_path = env_dir(args.checkpoint_dir, args) / "vae.pt"
    vae_v, vae_attr, vae_ckpt = load_vaes(vae_path, args.env, own_command(args, "collect vae gw"))
    path = env_dir(args.checkpoint_dir, args) / f"{args.loss_preset}.pt"
    identity = stage_identity(args, "gw", vae_ckpt)
    if stage_is_done(path, identity, args):
        return
    rank, world = start_processes(args)
    dev = torch.device(args.device)
    vae_v.to(dev), vae_attr.to(dev)
    n_eval = vae_ckpt["data"]["eval_samples"]
    data = training_data(args, n_eval, args.gw_batch_size)
    encoded = [  # the frozen VAE means of every sample, one chunk (streamed: one shard) at a time
        encode_unimodal(vae_v, vae_attr, images, (attrs - vae_ckpt["attr_mean"]) / vae_ckpt["attr_std"], dev)
        for images, attrs in data.chunks()
    ]
    u_v, u_a = (torch.cat(u) for u in zip(*encoded, strict=True))
    del encoded
    spec = ENV_SPECS[args.env]
    torch.manual_seed(args.seed)
    gw = GlobalWorkspace(spec["latent"], spec["z"], spec["gw_hidden"]).to(dev)
    betas = PRESETS[args.loss_preset]
    # fused: one kernel for all parameters (the GW's layers are small, per-tensor updates cost more)
    opt = torch.optim.AdamW(gw.parameters(), lr=args.gw_lr, weight_decay=args.gw_weight_decay, fused=True)
    sched = one_cycle(opt, args.gw_lr, args.gw_lr_start_end, args.gw_steps)
    partial = path.with_suffix(".partial.pt")
    start = 0
    ck = resume_partial(partial, identity, args, "gw")  # continue after an interruption
    if ck:
        gw.load_state_dict(ck["gw"]), opt.load_state_dict(ck["opt"]), sched.load_state_dict(ck["sched"])
        start = ck["step"]
    gen = torch.Generator().manual_seed(args.seed + start)
    progress = Progress(args.loss_preset, args.gw_steps, start)
    n = len(u_v)
    # Many processes: each its slice of the global batch, gradients averaged (DDP); the contrastive term
    # compares every pair of the global batch (gathered), so the updates are the one-process updates.
    terms_of = parallel(gw, gw_terms, world)
    for step in range(start + 1, args.gw_steps + 1):
        idx = torch.randint(n_eval, n, (args.gw_batch_size,), generator=gen).to(dev)  # the global batch
        alpha = fusion_weights(args.gw_batch_size, args.fusion_temperature, gen, dev)
        idx, alpha = my_slice(idx, rank, world), my_slice(alpha, rank, world)
        terms = terms_of(u_v[idx], u_a[idx], alpha, args.contrastive_temperature)
        loss_gw = sum(betas[k] * terms[k] for k in terms)  # eq. 2-3
        if not torch.isfinite(loss_gw):
            raise FloatingPointError(f"[gw] non-finite loss at step {step}; last good state: {partial}")
        opt.zero_grad(set_to_none=True)
        loss_gw.backward()
        opt.step()
        sched.step()
        if rank == 0 and (step % args.log_every == 0 or step == args.gw_steps):
            writer.add_scalar("losses/loss_gw", loss_gw.item(), step)
            for k, v in terms.items():
                writer.add_scalar(f"losses/loss_{k}", v.item(), step)
            writer.add_scalar("charts/gw_lr", sched.get_last_lr()[0], step)
            progress.show(step, " ".join(f"{k} {v.item():.4f}" for k, v in terms.items()))
        stopping = any_process(stop.requested)
        if rank == 0 and (step % args.save_every == 0 or stopping) and step < args.gw_steps:
            state = {"gw": gw.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict()}
            atomic_save(state | {"step": step, "identity": identity}, partial)
        if stopping and step < args.gw_steps:
            interrupted(f"{args.loss_preset} stage at step {step:,}: saved {partial}")
    gw.eval()
    if rank > 0:
        return barrier()  # rank 0 evaluates and writes the checkpoint the next stage reads
    images, attrs = data.held_out(n_eval)
    figures = evaluate_gw(args, gw, vae_v, vae_attr, vae_ckpt, images, attrs, u_v, u_a, n_eval, writer)
    atomic_save(
        {
            "kind": "gw",
            "identity": identity,
            "preset": args.loss_preset,
            "env": args.env,
            "config": {"betas": betas, **spec},
            "args": asdict(args),
            "gw": gw.state_dict(),
            "vae_checkpoint": str(env_dir(args.checkpoint_dir, args) / "vae.pt"),
            "vae_digest": identity["vae_digest"],  # the VAE it was trained on, checked by every reader
            "data": vae_ckpt["data"],
            "eval": figures,
        },
        path,
    )
    partial.unlink(missing_ok=True)
    print(f"[gw] wrote {path}")
    barrier()


def evaluate_gw(args, gw, vae_v, vae_attr, vae_ckpt, images, attrs, u_v, u_a, n_eval, writer) -> dict:
    """Held-out figures: translations image -> attributes and attributes -> image, and the Figure 2
    grid (translation, demi-cycle, fusion) on incongruent image / attribute pairs."""
    dev = u_v.device
    held_out = np.arange(n_eval)
    wide = held_out[:0]
    if args.env == "simple_shapes":
        from envs.simple_shapes import IMAGE_SIZE, MARGIN

        # The figures describe the dataset's draw (positions in [7, 25)); samples of --wide-share that
        # fall outside it get a figure of their own below.
        pos = (attrs[:n_eval, 3:5] + 1) / 2 * IMAGE_SIZE
        inside = np.all((pos > MARGIN - 0.5) & (pos < IMAGE_SIZE - MARGIN - 0.5), axis=1)
        held_out, wide = held_out[inside], held_out[~inside][:1000]
    ev = torch.as_tensor(held_out[:1000], device=dev)
    figures = {}
    with torch.no_grad():
        z_from_v = gw.fuse(u_v[ev], u_a[ev], 1.0, 0.0)  # alpha_v = 1: vision only
        z_from_attr = gw.fuse(u_v[ev], u_a[ev], 0.0, 1.0)
        attr_hat = vae_attr.decode(gw.d["attr"](z_from_v)).cpu().numpy()
        attr_hat = attr_hat * vae_ckpt["attr_std"] + vae_ckpt["attr_mean"]
        img_hat = vae_v.decode(gw.d["v"](z_from_attr))
        true_img = images_to_tensor(images[ev.cpu().numpy()], dev)
        figures["tr_attr_to_image_mae"] = (img_hat - true_img).abs().mean().item() * 255
        true_attr = attrs[ev.cpu().numpy()]
        if args.env == "simple_shapes":
            from envs.simple_shapes import attr_to_state

            s_hat, s_true = attr_to_state(attr_hat), attr_to_state(true_attr)
            figures["tr_image_to_class_accuracy"] = float((s_hat["cls"] == s_true["cls"]).mean())
            figures["tr_image_to_position_error_px"] = float(
                np.linalg.norm(s_hat["pos"] - s_true["pos"], axis=1).mean()
            )
            d_rot = np.abs((s_hat["rotation"] - s_true["rotation"] + np.pi) % (2 * np.pi) - np.pi)
            figures["tr_image_to_rotation_error_rad"] = float(d_rot.mean())
            figures["tr_image_to_colour_error"] = float(
                np.abs(s_hat["rgb"].astype(int) - s_true["rgb"]).mean()
            )
            # What GW-Dreamer sees: z fused at alpha 0.5/0.5, decoded back to attributes.
            z_fused = gw.fuse(u_v[ev], u_a[ev], 0.5, 0.5)
            fused_hat = vae_attr.decode(gw.d["attr"](z_fused)).cpu().numpy()
            s_fused = attr_to_state(fused_hat * vae_ckpt["attr_std"] + vae_ckpt["attr_mean"])
            figures["fusion_to_position_error_px"] = float(
                np.linalg.norm(s_fused["pos"] - s_true["pos"], axis=1).mean()
            )
            d_rot = np.abs((s_fused["rotation"] - s_true["rotation"] + np.pi) % (2 * np.pi) - np.pi)
            figures["fusion_to_rotation_error_rad"] = float(d_rot.mean())
            if len(wide):  # positions past the dataset's range: is z still telling them apart?
                w = torch.as_tensor(wide, device=dev)
                wide_hat = vae_attr.decode(gw.d["attr"](gw.fuse(u_v[w], u_a[w], 0.5, 0.5))).cpu().numpy()
                wide_hat = wide_hat * vae_ckpt["attr_std"] + vae_ckpt["attr_mean"]
                # positions read without attr_to_state's clipping to the frame
                err = (wide_hat[:, 3:5] - attrs[wide, 3:5]) / 2 * IMAGE_SIZE
                figures["fusion_to_position_error_px_outside"] = float(np.linalg.norm(err, axis=1).mean())
        else:
            figures["tr_image_to_attr_mse_standardised"] = float(
                (((attr_hat - true_attr) / vae_ckpt["attr_std"]) ** 2).mean()
            )
            every = torch.as_tensor(held_out, device=dev)
            for mode, alpha_v in (("fused", 0.5), ("vision", 1.0), ("attr", 0.0)):
                z = gw.fuse(u_v[every], u_a[every], alpha_v, 1 - alpha_v)
                read = vae_attr.decode(gw.d["attr"](z)).cpu().numpy()
                read = read * vae_ckpt["attr_std"] + vae_ckpt["attr_mean"]
                figures |= robodesk_readout(read, attrs[held_out], mode)
        # Figure 2: incongruent pairs (attributes of another sample); decode z as an image per mode.
        k = ev[:8]
        perm = k.roll(1)
        rows = [true_img[:8], images_to_tensor(images[perm.cpu().numpy()], dev)]
        for alpha_v in (0.0, 1.0, 0.5):  # translation, demi-cycle, fusion
            z = gw.fuse(u_v[k], u_a[perm], alpha_v, 1 - alpha_v)
            rows.append(vae_v.decode(gw.d["v"](z)))
        writer.add_images("gw/figure2_image_attrimage_tr_dcy_fusion", torch.cat(rows), 0)
    for key, v in figures.items():
        writer.add_scalar(f"eval/{key}", v, 0)
    print("[gw] held-out evaluation: " + json.dumps({k: round(v, 4) for k, v in figures.items()}))
    if args.env == "robodesk":
        print(
            f"[gw] what z holds, {len(held_out):,} held-out samples: R^2 (error in cm) of the decoded state"
        )
        print(f"[gw]   {'group':14s} {'fused':>16s} {'vision only':>16s} {'attributes only':>16s}")
        for group in READOUT_GROUPS:
            cells = []
            for mode in ("fused", "vision", "attr"):
                cm = figures.get(f"{mode}_{group}_error_cm")
                cells.append(f"{figures[f'{mode}_{group}_r2']:.3f}" + (f" ({cm:.1f} cm)" if cm else ""))
            print(f"[gw]   {group:14s} " + " ".join(f"{c:>16s}" for c in cells))
    return figures


# The groups of RoboDesk's state that single images hold (attr indices, envs/robodesk.py: robot qpos 0-8,
# qvel 9-17, end effector 18-20, object qpos 21-49: drawer, slide, the buttons red / green / blue, their
# lights, then ball, upright block and flat block as position + quaternion; object qvel 50-75).
READOUT_GROUPS = {
    "end_effector": [18, 19, 20],
    "gripper": [7, 8],
    "button_red": [23, 26],
    "button_green": [24, 27],
    "button_blue": [25, 28],
    "drawer": [21],
    "slide": [22],
    "ball": [29, 30, 31],
    "upright_block": [36, 37, 38],
    "flat_block": [43, 44, 45],
}
POSITIONS = ("end_effector", "ball", "upright_block", "flat_block")  # groups in metres: also an error in cm


def robodesk_readout(read: np.ndarray, true: np.ndarray, mode: str) -> dict[str, float]:
    """What z holds of each group of the state, from attributes decoded out of z (d_attr, then the
    attribute VAE's decoder): R^2 per group (mean over its dimensions of 1 - SSE / SST on the held-out
    samples; NaN for a group constant over them) and, for positions, the mean distance in cm. ``mode``
    names the z (fused, vision, attr)."""
    out = {}
    for group, idx in READOUT_GROUPS.items():
        y, y_hat = true[:, idx].astype(np.float64), read[:, idx].astype(np.float64)
        sst = ((y - y.mean(0)) ** 2).sum(0)
        varies = y.std(0) > 1e-3  # a dimension constant over the samples (< 1 mm or mrad) has no R^2
        r2 = 1 - ((y - y_hat) ** 2).sum(0)[varies] / sst[varies]
        out[f"{mode}_{group}_r2"] = float(r2.mean()) if varies.any() else float("nan")
        if group in POSITIONS:
            out[f"{mode}_{group}_error_cm"] = float(100 * np.linalg.norm(y - y_hat, axis=1).mean())
    return out


# --------------------------------------------------------------------------------------------------
def interrupted(where: str) -> None:
    """End the run after Ctrl-C once the work so far is on disk."""
    print(f"[pretrain] interrupted in the {where}; the same command continues it", flush=True)
    raise SystemExit(130)  # the shell's code for a run ended by Ctrl-C


def main(args: Args) -> None:
    args.resolve()
    check_settings(args)
    check_outputs(args)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    rank = int(os.environ.get("RANK", 0))  # torchrun: rank 0 alone logs and saves
    writer = None
    if rank == 0:
        run_name = f"{args.exp_name}_{args.env}_{args.loss_preset}_{args.seed}_{int(time.time())}"
        table = "\n".join(f"|{k}|{v}|" for k, v in vars(args).items())
        writer = LazyWriter(f"runs/{run_name}", "|param|value|\n|-|-|\n" + table)
    t0 = time.time()
    stop = StopRequest("pretrain")  # Ctrl-C: the stage saves what it has and the run exits 130
    try:
        if "collect" in args.stages:
            collect(args, stop)
        if "vae" in args.stages:
            train_vae(args, writer, stop)
        if "gw" in args.stages:
            train_gw(args, writer, stop)
    finally:
        stop.restore()
        if dist.is_initialized():  # torchrun: a process that exits with its group alive can abort
            dist.destroy_process_group()
    if writer is not None:
        writer.close()
        print(f"done in {(time.time() - t0) / 60:.1f} min")


class LazyWriter:
    """TensorBoard's SummaryWriter, made at the first thing a stage logs: a call that trains nothing (a
    refused one, or one whose stages are all up to date) leaves no runs/ folder behind."""

    def __init__(self, logdir: str, hyperparameters: str):
        self.logdir, self.hyperparameters, self.writer = logdir, hyperparameters, None

    def __getattr__(self, name: str):
        if self.writer is None:
            self.writer = SummaryWriter(self.logdir)
            self.writer.add_text("hyperparameters", self.hyperparameters)
        return getattr(self.writer, name)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


if __name__ == "__main__":
    cli(main, Args)
