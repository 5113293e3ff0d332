"""pretrain_vae_gw.py at scale: DistributedDataParallel under torchrun (2 CPU processes, gloo) trains
what one process trains on the same global batch, rank 0 alone logs and saves, an interrupted stage
continues under torchrun as in one process, main ends its process group; shards streamed a few at a
time (--stream-shards) give the stages their data with bounded memory."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
import tyro
from conftest import ROOT, TINY_PRETRAIN, run_pretrain, run_script
from torch.utils.tensorboard import SummaryWriter

import pretrain_vae_gw as P

FEW = ["--vae-steps", "1", "--gw-steps", "2"]  # a few updates: float noise has not grown yet
# Worst tensor's relative difference from the one-process weights, measured on this test's run: 1.4e-4
# as it should be (Adam's first steps move a weight whose gradient is all but 0 by a full learning rate,
# with the sign float noise gives it: gw.e.attr.8.weight), 8e-3 without the gathered contrastive term,
# 1.0 without the global batch norm. The bound sits between, a factor of 7 from each.
REL = 1e-3


def torchrun(cwd: Path, *args: str) -> str:
    """pretrain_vae_gw.py under torchrun with 2 CPU processes; fail with its output if it fails."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [*cmd, str(ROOT / "pretrain_vae_gw.py"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def weights(folder: Path) -> dict[str, torch.Tensor]:
    vae = torch.load(folder / "simple_shapes" / "vae.pt", weights_only=False)
    gw = torch.load(folder / "simple_shapes" / "gw.pt", weights_only=False)
    out = {f"vae_v.{k}": v for k, v in vae["vae_v"].items()} | {
        f"vae_attr.{k}": v for k, v in vae["vae_attr"].items()
    }
    return out | {f"gw.{k}": v for k, v in gw["gw"].items()}


def assert_same_weights(a: dict, b: dict, rel: float) -> None:
    """Every tensor within ``rel`` of the other in norm (one Adam step can move a weight whose gradient
    is all but 0 by a full learning rate either way, so single elements may differ by more)."""
    assert a.keys() == b.keys()
    for k in a:
        if a[k].is_floating_point():
            err = float(
                torch.linalg.norm((a[k] - b[k]).double()) / torch.linalg.norm(a[k].double()).clamp(min=1e-12)
            )
            assert err < rel, (k, err)


def test_two_processes_train_what_one_process_trains(tmp_path):
    """Same data, same global batches: the VAEs and the GW of a 2-process torchrun run equal the
    one-process ones to float tolerance (batch norm over the global batch, the contrastive term over all
    pairs of it); rank 0 alone writes logs."""
    run_pretrain(tmp_path, "--env", "simple_shapes", *FEW)  # collect, vae, gw in one process
    runs_before = set((tmp_path / "runs").iterdir())
    data = ["--data-dir", str(tmp_path / "data"), "--checkpoint-dir", str(tmp_path / "ck2")]
    log = torchrun(tmp_path, "--env", "simple_shapes", "--stages", "vae", "gw", *data, *TINY_PRETRAIN, *FEW)
    assert log.count("[vae] wrote") == 1 and log.count("[gw] wrote") == 1  # one process saves
    assert len(set((tmp_path / "runs").iterdir()) - runs_before) == 1  # one TensorBoard folder
    assert_same_weights(weights(tmp_path / "ck"), weights(tmp_path / "ck2"), rel=REL)


def test_an_interrupted_stage_continues_under_torchrun_as_in_one_process(tmp_path, monkeypatch):
    """The partial state of a vae stage stopped at step 4 continues to step 6 under torchrun with the
    result one process gives (every process reads the one partial file rank 0 wrote)."""
    run_pretrain(tmp_path, "--env", "simple_shapes", "--stages", "collect")
    ck = tmp_path / "ck" / "simple_shapes"
    flags = [*TINY_PRETRAIN, *"--env simple_shapes --stages vae --vae-steps 6 --save-every 2".split()]
    flags += ["--data-dir", str(tmp_path / "data")]
    args = tyro.cli(P.Args, args=[*flags, "--checkpoint-dir", str(tmp_path / "ck")]).resolve()
    real_save = P.atomic_save

    def stop_at_step_4(obj, path):  # the run dies right after the partial save of step 4
        real_save(obj, path)
        if obj.get("step") == 4:
            raise KeyboardInterrupt

    monkeypatch.setattr(P, "atomic_save", stop_at_step_4)
    with pytest.raises(KeyboardInterrupt):
        P.train_vae(args, SummaryWriter(str(tmp_path / "runs" / "interrupted")), P.StopRequest("test"))
    monkeypatch.setattr(P, "atomic_save", real_save)
    assert torch.load(ck / "vae.partial.pt", weights_only=False)["step"] == 4
    shutil.copytree(tmp_path / "ck", tmp_path / "ck2")
    one = run_script("pretrain_vae_gw.py", tmp_path, *flags, "--checkpoint-dir", str(tmp_path / "ck"))
    two = torchrun(tmp_path, *flags, "--checkpoint-dir", str(tmp_path / "ck2"))
    assert "continuing the unfinished stage" in one and "continuing the unfinished stage" in two
    a = torch.load(ck / "vae.pt", weights_only=False)["vae_v"]
    b = torch.load(tmp_path / "ck2" / "simple_shapes" / "vae.pt", weights_only=False)["vae_v"]
    assert_same_weights(a, b, rel=REL)


@pytest.mark.parametrize("stage_ends", ["done", "interrupted"])
def test_main_ends_the_process_group_it_ran_in(tmp_path, monkeypatch, stage_ends):
    """A torchrun process that exits with its gloo group alive can abort after its work is done
    ("terminate called without an active exception"): main ends the group, also when a stage stops."""

    def stage(args, stop):
        if stage_ends == "interrupted":
            P.interrupted("test stage")

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(P, "collect", stage)
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'group'}", rank=0, world_size=1)
    try:
        paths = ["--data-dir", str(tmp_path / "data"), "--checkpoint-dir", str(tmp_path / "ck")]
        args = tyro.cli(P.Args, args=["--env", "simple_shapes", "--stages", "collect", *paths])
        if stage_ends == "interrupted":
            with pytest.raises(SystemExit):
                P.main(args)
        else:
            P.main(args)
        assert not dist.is_initialized()
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


def test_collect_and_batches_that_do_not_split_are_refused_under_torchrun(tmp_path):
    env = os.environ | {"WORLD_SIZE": "2"}  # what torchrun sets in each process
    cmd = [sys.executable, str(ROOT / "pretrain_vae_gw.py"), "--env", "simple_shapes"]
    out = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, env=env)
    assert out.returncode == 2 and "the collect stage runs in one process" in out.stderr
    out = subprocess.run(
        [*cmd, "--stages", "vae", "--vae-batch-size", "15"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=env,
    )
    assert out.returncode == 2 and "--vae-batch-size 15: must be a multiple of the 2 processes" in out.stderr


def test_streamed_shards_hold_k_at_a_time_and_cover_the_data(tmp_path):
    """--stream-shards 2 of 5 shards: batches come from the 2 in memory, which change every period steps
    and cover every shard in a pass; held-out samples never appear; the attribute moments equal the
    in-memory ones."""
    folder = tmp_path / "data" / "simple_shapes"
    for i in range(5):  # attributes encode the global sample index in their first entry
        attr = np.zeros((40, 11), np.float32)
        attr[:, 0] = np.arange(40 * i, 40 * (i + 1))
        P.write_shard(folder, np.zeros((40, 32, 32, 3), np.uint8), attr, "random")
    data = P.Streamed(folder, "simple_shapes", n_eval=50, k=2, seed=0, batch=20)
    assert len(data) == 200 and data.period == 2  # 40-sample shards, batches of 20
    rng, seen_shards = np.random.default_rng(0), set()
    for step in range(1, 11):  # one pass over the 5 shards
        data.advance(step)
        assert len(data.slots) == 2
        idx = data.batch(rng, 20)[1][:, 0]
        assert idx.min() >= 50  # the held-out samples are not trained on
        assert set((idx // 40).astype(int)) <= set(data.slots)
        seen_shards |= set(data.slots)
    assert seen_shards == set(range(5))
    images, attrs = data.held_out(50)
    np.testing.assert_array_equal(attrs[:, 0], np.arange(50))
    chunks = list(data.chunks())
    assert [len(c[1]) for c in chunks] == [40] * 5
    whole = P.InMemory(folder, "simple_shapes", 50)
    for a, b in zip(data.train_attr_moments(), whole.train_attr_moments(), strict=True):
        np.testing.assert_allclose(a, b)
