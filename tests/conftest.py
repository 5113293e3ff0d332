"""Test-wide set-up: MuJoCo's headless GL back-end, the repository on sys.path, and the tiny pre-trained
VAE/GW checkpoints that every agent test starts from (made once per session through the real CLI)."""

import atexit
import contextlib
import io
import os
import re
import runpy
import signal
import subprocess
import sys
import traceback
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # before anything imports mujoco
# One thread per test process, for it and the scripts it starts: the suite runs in two processes
# (pytest -n 2) on two cores, and two 2-thread torch processes side by side run slower than with one.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository root (envs/, scripts)

TINY_PRETRAIN = (
    "--n-samples 600 --shard-size 300 --vae-steps 12 --vae-batch-size 16 --vae-width 32 --gw-steps 20"
    " --gw-batch-size 32 --log-every 5 --save-every 5 --eval-size 60"
).split()


def run_cli(script: str, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """Run a top-level script through its command line in ``cwd`` and return what it did (exit code,
    output). The script runs as ``python script args`` runs it (its ``__main__`` block parses ``args``),
    but in this process, where torch is already imported: a new process costs 4-6 s of imports. Tests of
    what only a process shows (signals, kill -9, a second live process, torchrun) start their own."""
    return run_as_main(ROOT / script, cwd, list(args))


def run_as_main(path: Path, cwd: Path, args: list[str]) -> subprocess.CompletedProcess:
    """``path`` executed as ``__main__`` with ``args`` in ``cwd``; its stdout, stderr and exit code
    collected as a process's would be. What the process's end would undo is undone when it returns: the
    working directory, sys.argv and the torch thread count are restored, and the ``atexit`` callbacks it
    registered (its run lock) are called."""
    out, err, at_exit = io.StringIO(), io.StringIO(), []
    before = (os.getcwd(), sys.argv, torch.get_num_threads(), atexit.register)
    os.chdir(cwd)
    sys.argv, atexit.register = [str(path), *args], lambda fn, *a, **k: at_exit.append((fn, a, k)) or fn
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                runpy.run_path(str(path), run_name="__main__")
                code = 0
            except SystemExit as e:
                if isinstance(e.code, str):  # sys.exit(message): Python prints it and exits 1
                    print(e.code, file=sys.stderr)
                code = 1 if isinstance(e.code, str) else e.code or 0
            except Exception:
                traceback.print_exc()
                code = 1
    finally:
        os.chdir(before[0])
        sys.argv, atexit.register = before[1], before[3]
        torch.set_num_threads(before[2])
        for fn, a, k in reversed(at_exit):
            fn(*a, **k)
    return subprocess.CompletedProcess([str(path), *args], code, out.getvalue(), err.getvalue())


def run_script(script: str, cwd: Path, *args: str) -> str:
    """Run a top-level script through its CLI in ``cwd``; fail with its output if it fails."""
    out = run_cli(script, cwd, *args)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def interrupt_cli(script: str, cwd: Path, ready: str, *args: str) -> tuple[int, str]:
    """Run a script through its CLI, press Ctrl-C (SIGINT) once it prints a line containing ``ready``,
    and return (its exit code, its whole output)."""
    command = [sys.executable, str(ROOT / script), *args]
    proc = subprocess.Popen(command, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if ready in line:
            proc.send_signal(signal.SIGINT)
            break
    rest, _ = proc.communicate(timeout=300)
    return proc.returncode, "".join(lines) + rest


def interrupt_run(script: str, cwd: Path, agent: Path, *args: str) -> tuple[dict, int]:
    """Run a Dreamer-family script through its CLI for up to 3,000 env steps with no periodic save or
    evaluation due, press Ctrl-C (SIGINT) once it prints its first training progress line, check that
    it exited 130 naming --resume, and return (the state saved in ``agent``, the step it reports)."""
    never = ["--log-every", "50", "--total-steps", "3000", "--save-every", "100000", "--eval-every", "100000"]
    code, log = interrupt_cli(script, cwd, " updates ", *args, *never)  # training is under way
    found = re.search(r"interrupted at env step ([\d,]+)", log)
    assert found and code == 130 and "--resume continues the run" in log, log
    step = int(found.group(1).replace(",", ""))
    state = torch.load(agent, weights_only=False)["state"]
    assert 100 < step < 3000 and state["env_steps"] == step
    return state, step


# Small dreamer_baseline.py widths for tests (its --size presets are 2M parameters and up).
DREAMER_SMALL = dict(deter=64, hidden=32, units=32, cnn_depth=4, classes=4)

# The smallest agent runs of each script: a few updates, one short final evaluation, no periodic saves.
GW_TINY = (
    "--learning-starts 20 --batch-size 2 --batch-length 4 --imag-horizon 3 --train-ratio 10 --eval-episodes 1"
    " --video-every 0 --log-every 1000 --eval-every 100000 --save-every 100000 --total-steps 40"
).split()
DREAMER_TINY = [a for k, v in DREAMER_SMALL.items() for a in (f"--{k.replace('_', '-')}", str(v))]
AGENT_TINY = {
    "gw_dreamer.py": GW_TINY,
    "gw_dreamer_e2e.py": [*GW_TINY, "--gw-batch-size", "8"],
    "dreamer_baseline.py": [*DREAMER_TINY, *GW_TINY],
    "ppo_variants.py": (
        "--variant gw --num-envs 2 --num-steps 16 --update-epochs 1 --minibatch-size 16 --eval-episodes 1"
        " --total-steps 32"
    ).split(),
}
AGENT_SCRIPTS = tuple(AGENT_TINY)


def tiny_agent_args(module, pretrained, **kw):
    """``module.Args`` (gw_dreamer, gw_dreamer_e2e or dreamer_baseline) with small batches on the
    ``pretrained`` checkpoints."""
    base = dict(checkpoint_dir=str(pretrained[0] / "ck"), learning_starts=50, batch_size=4, batch_length=8)
    return module.Args(**(base | kw)).resolve()


def assert_actions_read_dreamt_states_as_constants(imagine, agent, *starts) -> None:
    """In a differentiable dream (dynamics backpropagation) an action reaches the later states, which the
    rewards and values read, through the dreamt transitions; but no later action depends differentiably
    on it through the state the actor reads (DreamerV3's policy(sg(s))). ``imagine(agent, *starts,
    horizon, grad)`` is a script's dream."""
    taken = []
    sample = type(agent.actor).sample
    agent.actor.sample = lambda *a, **k: taken.append(sample(agent.actor, *a, **k)) or taken[-1]
    try:
        dream = imagine(agent, *starts, 3, grad=True)
    finally:
        del agent.actor.sample
    (to_state,) = torch.autograd.grad(dream.feats[-1].sum(), taken[0], retain_graph=True)
    assert to_state.abs().sum() > 0
    assert torch.autograd.grad(taken[1].sum(), taken[0], allow_unused=True)[0] is None


def logged_totals(tmp: Path, prefix: str) -> list[tuple[int, int]]:
    """(env step, --total-steps) of each part of the one run under tmp/runs named ``prefix``...: every
    start logs the run's length, which --resume may change (benchmarks/paper_figures.py reads the last)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (run,) = (tmp / "runs").glob(prefix + "*")
    acc = EventAccumulator(str(run), size_guidance={"scalars": 0}).Reload()
    return [(e.step, int(e.value)) for e in acc.Scalars("charts/total_steps")]


def assert_episodes_separated(replay: dict) -> None:
    """In a saved GW-Dreamer replay (streams not yet wrapped), every episode start but a stream's first
    entry follows an entry marked last, so no world-model transition crosses from one episode into the
    next, also where a resumed run started new episodes after a save made mid-episode."""
    for i in range(len(replay["count"])):
        n = int(replay["count"][i])
        starts = np.flatnonzero(replay["first"][i, 1:n]) + 1
        assert len(starts) > 0
        assert np.all(replay["last"][i, starts - 1] == 1), starts[replay["last"][i, starts - 1] != 1]


def previous_layout(src: Path, dst: Path) -> None:
    """``src`` rewritten as agent checkpoints were saved before the return scale became a module of the
    agent (a float ``return_scale`` in the loop state, no ``return_scale.*`` buffers) and before
    GW-Dreamer's --done-head flag existed."""
    ck = torch.load(src, weights_only=False)
    ck["state"]["return_scale"] = float(ck["agent"].pop("return_scale.ema"))
    del ck["agent"]["return_scale.count"]
    if ck["kind"] in ("gw_dreamer", "gw_dreamer_e2e"):  # nor the --done-head flag
        del ck["args"]["done_head"]
    torch.save(ck, dst)


def refused_then_converted(run, old: Path) -> None:
    """``run()`` refuses the previous-layout checkpoint ``old`` with the command that converts it; that
    command (benchmarks/experiments/convert_checkpoint.py, through its CLI) converts it in place and
    keeps the original as ``old.pt.old``."""
    command = f"python benchmarks/experiments/convert_checkpoint.py {old}"
    with pytest.raises(ValueError, match=re.escape(f"older version: convert it with `{command}`")):
        run()
    out = run_script("benchmarks/experiments/convert_checkpoint.py", old.parent, str(old))
    assert "converted" in out and old.with_name(old.name + ".old").is_file()
    converted = torch.load(old, weights_only=False)
    assert "return_scale" not in converted["state"]
    assert converted["args"].get("done_head", "on") == "on"  # the flag's value the weights show


def run_pretrain(tmp_path: Path, *extra: str) -> str:
    """pretrain_vae_gw.py with tiny settings, data in tmp_path/data and checkpoints in tmp_path/ck."""
    paths = ["--data-dir", str(tmp_path / "data"), "--checkpoint-dir", str(tmp_path / "ck")]
    return run_script("pretrain_vae_gw.py", tmp_path, *paths, *TINY_PRETRAIN, *extra)


@pytest.fixture(scope="session")
def pretrained(tmp_path_factory):
    """Tiny Simple Shapes run of all three stages, then the CLIP-like preset on the same VAEs:
    (folder, log, clip log) with checkpoints in folder/ck/simple_shapes/{vae,gw,clip}.pt."""
    tmp = tmp_path_factory.mktemp("ss")
    log = run_pretrain(tmp, "--env", "simple_shapes")
    log_clip = run_pretrain(tmp, "--env", "simple_shapes", "--stages", "gw", "--loss-preset", "clip")
    return tmp, log, log_clip


@pytest.fixture(scope="session")
def pretrained_robodesk(tmp_path_factory):
    """Tiny RoboDesk VAEs, GW and CLIP-like model on 40 random-policy samples: (folder, log of the first)."""
    tmp = tmp_path_factory.mktemp("rd")
    small = ["--n-samples", "40", "--shard-size", "20", "--render-quality", "fast", "--eval-size", "8"]
    log = run_pretrain(tmp, "--env", "robodesk", "--vae-batch-size", "8", "--gw-batch-size", "8", *small)
    run_pretrain(
        tmp, "--env", "robodesk", "--stages", "gw", "--loss-preset", "clip", "--gw-batch-size", "8", *small
    )
    return tmp, log


def record_calls(monkeypatch, cls, name: str, pick) -> list:
    """Wrap ``cls.name`` so that every call still runs and ``pick(*args, **kwargs)`` (the arguments after
    self) is appended to the returned list."""
    seen, real = [], getattr(cls, name)

    def spy(self, *args, **kwargs):
        seen.append(pick(*args, **kwargs))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(cls, name, spy)
    return seen


def robodesk_batch(B: int = 3, T: int = 12) -> dict[str, torch.Tensor]:
    """A replayed RoboDesk batch of random z, actions and rewards in which one episode ends."""
    torch.manual_seed(1)
    batch = {
        "z": torch.rand(B, T + 1, 76) * 2 - 1,
        "a": torch.rand(B, T + 1, 5) * 2 - 1,
        "r": torch.rand(B, T + 1) * 4,
    }
    batch |= {k: torch.zeros(B, T + 1) for k in ("d", "first", "last")}
    batch["last"][1, 5], batch["first"][1, 6] = 1.0, 1.0  # an episode ends inside sequence 1
    return batch
