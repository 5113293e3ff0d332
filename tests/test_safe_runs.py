"""Safe runs, through the real CLIs: nothing made earlier is overwritten, mixed or mis-read by accident,
bad input stops at start with one line (exit code 2), Ctrl-C exits 130 with the work saved, and a save
killed half-way leaves the previous checkpoint whole. docs/safe_runs.md lists what each case shows."""

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from types import SimpleNamespace

import pytest
import torch
from conftest import (
    AGENT_SCRIPTS,
    AGENT_TINY,
    GW_TINY,
    ROOT,
    TINY_PRETRAIN,
    interrupt_cli,
    run_cli,
    run_script,
)

import gw_dreamer as G
import pretrain_vae_gw as P


def agent_cli(script: str, pretrained, cwd, *extra: str, checkpoint=None) -> subprocess.CompletedProcess:
    """``script`` on Simple Shapes with its tiny settings, the session's pre-trained VAE/GW, its runs/
    in ``cwd`` and its agent checkpoint at ``checkpoint`` (default cwd/agent.pt)."""
    ck = ["--checkpoint-dir", str(pretrained[0] / "ck"), "--checkpoint", str(checkpoint or cwd / "agent.pt")]
    return run_cli(script, cwd, "--env", "simple_shapes", *ck, *AGENT_TINY[script], *extra)


def assert_refused(out: subprocess.CompletedProcess, *phrases: str) -> None:
    """Exit code 2 and one line on stderr (no traceback) that contains each phrase."""
    err = out.stderr.strip()
    assert out.returncode == 2 and err.startswith("error: ") and "\n" not in err, out.stdout + out.stderr
    for phrase in phrases:
        assert phrase in err, err


@pytest.fixture(scope="module")
def gw_run(pretrained, tmp_path_factory):
    """One finished tiny gw_dreamer.py run: (its folder, agent checkpoint, the checkpoint's bytes)."""
    cwd = tmp_path_factory.mktemp("safe")
    out = agent_cli("gw_dreamer.py", pretrained, cwd)
    assert out.returncode == 0, out.stdout + out.stderr
    return cwd, cwd / "agent.pt", (cwd / "agent.pt").read_bytes()


# 1. A second run under the same name ----------
def test_a_second_run_is_refused_and_overwrite_replaces_it(gw_run, pretrained):
    cwd, agent, saved = gw_run
    again = agent_cli("gw_dreamer.py", pretrained, cwd)
    assert_refused(again, str(agent), "already exist", "add --resume to continue", "--overwrite")
    assert agent.read_bytes() == saved  # the earlier run's agent is untouched
    events = cwd / "runs" / "gw_dreamer_gw_simple_shapes_s1"
    assert len(list(events.glob("events.*"))) == 1
    # On purpose: --overwrite replaces the agent and the TensorBoard folder (no mixed events).
    other = cwd / "other"
    shutil.copytree(cwd / "runs", other / "runs")
    shutil.copy(agent, other / "agent.pt")
    out = agent_cli("gw_dreamer.py", pretrained, other, "--overwrite", "--seed", "1")
    assert out.returncode == 0, out.stdout + out.stderr
    assert len(list((other / "runs" / events.name).glob("events.*"))) == 1
    assert (other / "agent.pt").read_bytes() != saved


@pytest.mark.parametrize("script", AGENT_SCRIPTS[1:])
def test_every_agent_script_refuses_to_replace_an_earlier_agent(script, pretrained, tmp_path):
    earlier = tmp_path / "agent.pt"
    earlier.write_bytes(b"an earlier run's agent")
    assert_refused(agent_cli(script, pretrained, tmp_path), "already exist", "--resume", "--overwrite")
    assert earlier.read_bytes() == b"an earlier run's agent"
    assert not (tmp_path / "runs").exists()  # nothing was started


def test_pretraining_never_replaces_a_checkpoint_made_otherwise(pretrained, tmp_path):
    ck = tmp_path / "ck" / "simple_shapes"
    shutil.copytree(pretrained[0] / "ck" / "simple_shapes", ck, ignore=shutil.ignore_patterns("agents"))
    data = ["--data-dir", str(pretrained[0] / "data"), "--env", "simple_shapes", "--stages", "gw"]
    paths = ["--checkpoint-dir", str(tmp_path / "ck"), *TINY_PRETRAIN]
    gw = (ck / "gw.pt").read_bytes()
    same = run_script("pretrain_vae_gw.py", tmp_path, *data, *paths)
    assert "was made with these settings: stage skipped" in same and (ck / "gw.pt").read_bytes() == gw
    # later flags win in tyro: --gw-steps 21 replaces the tiny 20
    out = run_cli("pretrain_vae_gw.py", tmp_path, *data, *paths, "--gw-steps", "21")
    assert_refused(out, str(ck / "gw.pt"), "made with --gw-steps 20", "--overwrite")
    assert (ck / "gw.pt").read_bytes() == gw
    assert not list((tmp_path / "runs").iterdir())  # the skipped and the refused call logged nothing
    run_script("pretrain_vae_gw.py", tmp_path, *data, *paths, "--gw-steps", "21", "--overwrite")
    assert torch.load(ck / "gw.pt", weights_only=False)["identity"]["gw_steps"] == 21


def test_a_run_that_died_before_its_first_save_is_started_again_as_the_hint_says(pretrained, tmp_path):
    """runs/<name> without a checkpoint (killed before its first save): the plain command and --resume
    both say that nothing can be continued and to add --overwrite, which then trains; --resume with
    nothing at all says to start without it, which then trains. Fails if the two hints point at each other."""
    (tmp_path / "runs" / "gw_dreamer_gw_simple_shapes_s1").mkdir(parents=True)
    for extra in ([], ["--resume"]):
        out = agent_cli("gw_dreamer.py", pretrained, tmp_path, *extra)
        assert_refused(
            out, "but no checkpoint", "stopped before its first save", "add --overwrite (without --resume)"
        )
    assert agent_cli("gw_dreamer.py", pretrained, tmp_path, "--overwrite").returncode == 0
    other = tmp_path / "other"
    other.mkdir()
    out = agent_cli("gw_dreamer.py", pretrained, other, "--resume")
    assert_refused(
        out, f"--resume: there is no checkpoint {other / 'agent.pt'} to continue; start the run without it"
    )  # without it, it is a plain first run


# 2. Pre-training partials of other settings ----------
def test_pretraining_refuses_a_partial_stage_of_other_settings(pretrained, tmp_path):
    """Ctrl-C during the vae stage saves a partial (exit 130); other flags refuse to continue it, naming
    the file and the differing flag; a damaged partial is named too; --overwrite starts the stage over."""
    vae = ["--data-dir", str(pretrained[0] / "data"), "--env", "simple_shapes", "--stages", "vae"]
    vae += ["--checkpoint-dir", str(tmp_path / "ck"), *TINY_PRETRAIN]  # --vae-steps 12
    long = ["--vae-steps", "5000", "--save-every", "100000"]  # later flags win in tyro
    code, log = interrupt_cli("pretrain_vae_gw.py", tmp_path, "[vae] ", *vae, *long)
    partial = tmp_path / "ck" / "simple_shapes" / "vae.partial.pt"
    assert code == 130 and "[pretrain] interrupted in the vae stage at step" in log, log
    assert "Traceback" not in log and partial.is_file()
    saved = partial.read_bytes()
    assert_refused(run_cli("pretrain_vae_gw.py", tmp_path, *vae), str(partial), "made with --vae-steps 5000")
    assert partial.read_bytes() == saved  # kept for the command that made it
    partial.write_bytes(saved[:1000])  # a partial cut short (a full disk): named, not a pickle dump
    out = run_cli("pretrain_vae_gw.py", tmp_path, *vae, *long)
    assert_refused(out, f"cannot read {partial}", "add --overwrite to start the unfinished vae stage over")
    run_script("pretrain_vae_gw.py", tmp_path, *vae, "--overwrite")
    made = torch.load(tmp_path / "ck" / "simple_shapes" / "vae.pt", weights_only=False)
    assert made["identity"]["vae_steps"] == 12 and not partial.exists()


# 3. --resume with changed settings ----------
def test_resume_refuses_changed_settings_and_accepts_a_longer_run(gw_run, pretrained):
    cwd, agent, saved = gw_run
    out = agent_cli("gw_dreamer.py", pretrained, cwd, "--resume", "--wm-lr", "0.002", "--buffer-size", "500")
    assert_refused(out, "made with --buffer-size 100000 --wm-lr 0.001", "give the same settings")
    assert agent.read_bytes() == saved
    cont = cwd / "cont"
    cont.mkdir()
    shutil.copy(agent, cont / "agent.pt")
    out = agent_cli("gw_dreamer.py", pretrained, cont, "--resume", "--total-steps", "60", "--log-every", "7")
    assert out.returncode == 0 and "resuming" in out.stdout, out.stdout + out.stderr
    assert torch.load(cont / "agent.pt", weights_only=False)["state"]["env_steps"] == 60


def test_a_checkpoint_without_a_newer_flag_resumes_only_at_its_default(gw_run, pretrained):
    """An agent saved before --actor-mean-reg existed (the key taken out of its args) continues at the
    flag's default and refuses another value. Fails if flags the checkpoint lacks accept any value."""
    cwd, agent, _ = gw_run
    old = cwd / "older"
    old.mkdir()
    ck = torch.load(agent, weights_only=False)
    del ck["args"]["actor_mean_reg"]
    torch.save(ck, old / "agent.pt")
    out = agent_cli("gw_dreamer.py", pretrained, old, "--resume", "--actor-mean-reg", "0.5")
    assert_refused(out, "older version that does not record --actor-mean-reg 0.5", "leave them out")
    out = agent_cli("gw_dreamer.py", pretrained, old, "--resume", "--total-steps", "60", "--log-every", "7")
    assert out.returncode == 0 and "resuming" in out.stdout, out.stdout + out.stderr


def test_a_checkpoint_holding_a_nan_is_refused_naming_where(gw_run, pretrained):
    """A NaN in the saved replay (or weights) stops --resume and --eval-only with one line naming the
    entry. Fails if a checkpoint is read back without the finite-value check."""
    cwd, agent, _ = gw_run
    bad = cwd / "nan"
    bad.mkdir()
    ck = torch.load(agent, weights_only=False)
    ck["replay"]["r"][0, 1] = float("nan")
    torch.save(ck, bad / "agent.pt")
    for extra in (["--resume"], ["--eval-only"]):
        out = agent_cli("gw_dreamer.py", pretrained, bad, *extra)
        assert_refused(out, f"{bad / 'agent.pt'} holds non-finite values (replay/r)", "no state to continue")


# 4. Data and agents of another task ----------
def test_collect_refuses_data_of_other_settings(pretrained, pretrained_robodesk, tmp_path):
    folder = pretrained[0] / "data" / "simple_shapes"
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest == {"env": "simple_shapes", "seed": 1, "wide_share": 0.0}
    shutil.copytree(folder, tmp_path / "data" / "simple_shapes")
    common = ["--data-dir", str(tmp_path / "data"), "--checkpoint-dir", str(tmp_path / "ck"), *TINY_PRETRAIN]
    out = run_cli("pretrain_vae_gw.py", tmp_path, "--env", "simple_shapes", *common, "--seed", "2")
    assert_refused(out, str(tmp_path / "data" / "simple_shapes"), "collected with --seed 1", "--data-dir")
    (tmp_path / "data" / "simple_shapes" / "manifest.json").unlink()
    out = run_cli("pretrain_vae_gw.py", tmp_path, "--env", "simple_shapes", *common)
    assert_refused(out, "without a manifest.json")
    assert not list(tmp_path.rglob("*.pt"))  # no stage ran
    # RoboDesk: data of the push_green expert is not reused for another task
    rd = ["--data-dir", str(pretrained_robodesk[0] / "data"), "--checkpoint-dir", str(tmp_path / "ck")]
    out = run_cli("pretrain_vae_gw.py", tmp_path, "--env", "robodesk", *rd, "--task", "open_drawer")
    assert_refused(out, "collected with --tasks push_green", "another --data-dir")


def test_an_agent_of_one_task_refuses_another(pretrained_robodesk, tmp_path):
    ck = ["--checkpoint-dir", str(pretrained_robodesk[0] / "ck"), "--checkpoint", str(tmp_path / "a.pt")]
    rd = ["--env", "robodesk", "--render-quality", "fast", "--episode-length", "8", *ck, *GW_TINY]
    run_script("gw_dreamer.py", tmp_path, *rd, "--task", "push_green", "--learning-starts", "8")
    out = run_cli("gw_dreamer.py", tmp_path, *rd, "--task", "open_drawer", "--eval-only")
    assert_refused(out, "trained with --task push_green; pass --task push_green")


# 5. Bad output paths, damaged checkpoints, Ctrl-C in the final evaluation ----------
def test_unwritable_outputs_stop_the_run_before_it_trains(pretrained, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    out = agent_cli("gw_dreamer.py", pretrained, tmp_path, checkpoint=blocker / "agent.pt")
    assert_refused(out, f"cannot write to {blocker}")
    assert "step" not in out.stdout and not (tmp_path / "runs").exists()
    data = ["--data-dir", str(pretrained[0] / "data"), *TINY_PRETRAIN, "--stages", "vae"]
    out = run_cli("pretrain_vae_gw.py", tmp_path, *data, "--checkpoint-dir", str(blocker))
    assert_refused(out, f"cannot write to {blocker}")
    (tmp_path / "runs").write_text("not a folder")  # TensorBoard's folder cannot be made here
    out = run_cli("pretrain_vae_gw.py", tmp_path, *data, "--checkpoint-dir", str(tmp_path / "ck"))
    assert_refused(out, "cannot write to runs")
    assert not (tmp_path / "ck" / "simple_shapes" / "vae.pt").exists()  # nothing trained


def test_a_damaged_checkpoint_names_its_path_and_the_command_that_remakes_it(gw_run, pretrained, tmp_path):
    broken = tmp_path / "broken.pt"
    broken.write_bytes(gw_run[2][: len(gw_run[2]) // 2])
    out = agent_cli("gw_dreamer.py", pretrained, tmp_path, "--eval-only", checkpoint=broken)
    assert_refused(out, f"cannot read {broken}", "python gw_dreamer.py --env simple_shapes")
    shutil.copytree(pretrained[0] / "ck" / "simple_shapes", tmp_path / "ck" / "simple_shapes")
    gw = tmp_path / "ck" / "simple_shapes" / "gw.pt"
    gw.write_text("a text file")
    out = run_cli(
        "gw_dreamer.py", tmp_path, "--env", "simple_shapes", "--checkpoint-dir", str(tmp_path / "ck")
    )
    assert_refused(out, f"cannot read {gw}", "python pretrain_vae_gw.py --env simple_shapes")
    torch.save(torch.zeros(3), gw)  # a torch file, but no checkpoint of these scripts
    out = run_cli(
        "gw_dreamer.py", tmp_path, "--env", "simple_shapes", "--checkpoint-dir", str(tmp_path / "ck")
    )
    assert_refused(out, f"{gw} holds a Tensor of torch.save, not a checkpoint of these scripts")


SIGINT_IN = textwrap.dedent(
    """
    import os, signal, sys
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (a background job ignores it)
    sys.path.insert(0, {root!r})
    import {module} as m
    real = m.{func}
    def final_evaluation(*a, **k):  # Ctrl-C arrives as the final evaluation starts
        os.kill(os.getpid(), signal.SIGINT)
        return real(*a, **k)
    m.{func} = final_evaluation
    sys.argv = {argv!r}
    m.cli(m.main, m.Args)
    """
)
FINAL_EVAL = {
    "gw_dreamer.py": "run_episodes",
    "gw_dreamer_e2e.py": "run_episodes",
    "dreamer_baseline.py": "run_episodes",
    "ppo_variants.py": "run_episodes",
}


@pytest.mark.parametrize("script", AGENT_SCRIPTS)
def test_ctrl_c_in_the_final_evaluation_keeps_the_trained_agent(script, pretrained, tmp_path):
    ck = ["--checkpoint-dir", str(pretrained[0] / "ck"), "--checkpoint", str(tmp_path / "agent.pt")]
    argv = [script, "--env", "simple_shapes", *ck, *AGENT_TINY[script]]
    code = SIGINT_IN.format(root=str(ROOT), module=script[:-3], func=FINAL_EVAL[script], argv=argv)
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    log = out.stdout + out.stderr
    assert out.returncode == 130 and "interrupted in the final evaluation; the agent is saved" in log, log
    assert "Traceback" not in log
    state = torch.load(tmp_path / "agent.pt", weights_only=False)["state"]
    assert state["env_steps"] == int(AGENT_TINY[script][AGENT_TINY[script].index("--total-steps") + 1])


def test_ctrl_c_during_ppo_training_saves_and_exits_130(pretrained, tmp_path):
    ppo = [a if a != "32" else "100000" for a in AGENT_TINY["ppo_variants.py"]]  # a long run
    ck = ["--checkpoint-dir", str(pretrained[0] / "ck"), "--checkpoint", str(tmp_path / "agent.pt")]
    code, log = interrupt_cli("ppo_variants.py", tmp_path, "[ppo] step ", "--env", "simple_shapes", *ck, *ppo)
    assert code == 130 and "the same command with --resume continues the run" in log, log
    assert "Traceback" not in log
    step = torch.load(tmp_path / "agent.pt", weights_only=False)["state"]["env_steps"]
    assert 0 < step < 100000 and f"interrupted at env step {step:,}" in log


def test_a_damaged_data_shard_or_manifest_is_one_line_naming_it(pretrained, tmp_path):
    """A shard cut short (BadZipFile) and a manifest that is no JSON stop pre-training with one line that
    names the file. Fails if np.load or json.loads errors reach the user raw."""
    shutil.copytree(pretrained[0] / "data", tmp_path / "data")
    folder = tmp_path / "data" / "simple_shapes"
    flags = [
        "--env",
        "simple_shapes",
        "--data-dir",
        str(tmp_path / "data"),
        "--checkpoint-dir",
        str(tmp_path),
    ]
    shard = sorted(folder.glob("shard_*.npz"))[-1]
    shard.write_bytes(shard.read_bytes()[:500])
    out = run_cli("pretrain_vae_gw.py", tmp_path, *flags, *TINY_PRETRAIN, "--stages", "vae")
    assert_refused(out, f"cannot read the data shard {shard} (BadZipFile", "run the collect stage again")
    (folder / "manifest.json").write_text('{"env": "simple_')
    out = run_cli("pretrain_vae_gw.py", tmp_path, *flags, *TINY_PRETRAIN, "--stages", "collect")
    assert_refused(out, f"cannot read {folder / 'manifest.json'} (JSONDecodeError)")


def test_hints_keep_the_users_folders_stages_and_loss_preset(tmp_path):
    """The commands that missing files name carry --data-dir, --checkpoint-dir and --loss-preset clip.
    Fails if a hint is built without the user's flags (it would make the files somewhere else)."""
    data, ck = tmp_path / "mydata", tmp_path / "myck"
    base = ["--env", "simple_shapes", "--data-dir", str(data), "--checkpoint-dir", str(ck)]
    out = run_cli("pretrain_vae_gw.py", tmp_path, *base, "--stages", "vae")
    assert_refused(out, f"`python pretrain_vae_gw.py --env simple_shapes --stages collect --data-dir {data}`")
    (ck / "simple_shapes").mkdir(parents=True, exist_ok=True)
    out = run_cli("pretrain_vae_gw.py", tmp_path, *base, "--stages", "gw", "--loss-preset", "clip")
    want = f"--stages collect vae gw --loss-preset clip --data-dir {data} --checkpoint-dir {ck}`"
    assert_refused(out, f"no vae checkpoint at {ck / 'simple_shapes' / 'vae.pt'}", want)
    clip = ["--gw-checkpoint", str(ck / "clip.pt"), "--vae-checkpoint", str(tmp_path / "vae.pt")]
    torch.save({"kind": "vae", "env": "simple_shapes"}, tmp_path / "vae.pt")
    out = run_cli("gw_dreamer.py", tmp_path, "--env", "simple_shapes", *clip)
    assert_refused(
        out, f"no gw checkpoint at {ck / 'clip.pt'}", "--stages gw --cpu-preset --loss-preset clip"
    )


def test_another_scripts_run_under_the_same_name_and_an_exported_policy_are_named_as_such(gw_run, pretrained):
    """A gw_dreamer.py checkpoint met by gw_dreamer_e2e.py (the same --exp-name / --checkpoint), with or
    without --resume, is named as another script's run; a .policy.pt2 given as a checkpoint is named as
    the exported policy, not as a damaged file. Fails if the kind is not read before "add --resume"."""
    cwd, agent, saved = gw_run
    for extra in ([], ["--resume"]):
        out = agent_cli("gw_dreamer_e2e.py", pretrained, cwd, *extra, checkpoint=agent)
        assert_refused(out, f"{agent} holds a 'gw_dreamer' run, not a 'gw_dreamer_e2e' one", "--exp-name")
    assert agent.read_bytes() == saved
    policy = cwd / "dreamer.policy.pt2"
    policy.write_bytes(b"an exported program")
    out = agent_cli("dreamer_baseline.py", pretrained, cwd, "--eval-only", checkpoint=policy)
    assert_refused(
        out, f"{policy} is a policy exported by dreamer_baseline.py", str(cwd / "dreamer.policy.pt")
    )


# 6. Numbers that make no sense ----------
BAD_FLAGS = [
    ("gw_dreamer.py", ["--total-steps", "-5"], "--total-steps -5: must be at least 1"),
    ("gw_dreamer.py", ["--critic-replay-coef", "-0.3"], "--critic-replay-coef -0.3: must not be negative"),
    ("gw_dreamer.py", ["--buffer-size", "5"], "--buffer-size 5: must hold a replayed sequence"),
    ("gw_dreamer.py", ["--num-envs", "0"], "--num-envs 0: must be at least 1"),
    ("gw_dreamer.py", ["--train-ratio", "0"], "--train-ratio 0.0: must be positive"),
    ("gw_dreamer.py", ["--batch-size", "0"], "--batch-size 0: must be at least 1"),
    ("gw_dreamer.py", ["--save-every", "0"], "--save-every 0: must be at least 1"),
    ("gw_dreamer.py", ["--drop", "vision"], "--drop vision: is for evaluation: add --eval-only"),
    ("gw_dreamer.py", ["--resume", "--overwrite"], "cannot go with --overwrite"),
    ("gw_dreamer_e2e.py", ["--gw-batch-size", "1"], "--gw-batch-size 1"),
    ("gw_dreamer.py", ["--reward-offset", "0.5"], "--reward-offset 0.5: is for RoboDesk"),
    ("gw_dreamer_e2e.py", ["--reward-offset", "1"], "--reward-offset 1.0: is for RoboDesk"),
    ("dreamer_baseline.py", ["--train-ratio", "0"], "--train-ratio 0.0: must be positive"),
    ("ppo_variants.py", ["--num-envs", "0"], "--num-envs 0: must be at least 1"),
    ("ppo_variants.py", ["--drop", "attr"], "--drop attr: is for evaluation: add --eval-only"),
    ("pretrain_vae_gw.py", ["--vae-batch-size", "1"], "--vae-batch-size 1: must be at least 2"),
    ("pretrain_vae_gw.py", ["--n-samples", "0"], "--n-samples 0: must be at least 1"),
    ("gw_dreamer.py", ["--ac-lr", "inf"], "--ac-lr inf: must be a finite number"),
    ("gw_dreamer_e2e.py", ["--gw-lr-max", "nan"], "--gw-lr-max nan: must be a finite number"),
    ("dreamer_baseline.py", ["--wm-lr", "inf"], "--wm-lr inf: must be a finite number"),
    ("ppo_variants.py", ["--learning-rate", "inf"], "--learning-rate inf: must be a finite number"),
    ("pretrain_vae_gw.py", ["--beta-v", "inf"], "--beta-v inf: must be a finite number"),
    ("gw_dreamer_e2e.py", ["--fusion-temperature", "0"], "--fusion-temperature 0.0: must be positive"),
    ("gw_dreamer_e2e.py", ["--contrastive-temperature", "-1"], "--contrastive-temperature -1.0: must be"),
    ("gw_dreamer_e2e.py", ["--gw-weight-decay", "-1"], "--gw-weight-decay -1.0: must not be negative"),
    ("dreamer_baseline.py", ["--seed", "-1"], "--seed -1: must not be negative"),
    ("ppo_variants.py", ["--torch-threads", "-2"], "--torch-threads -2: must not be negative"),
    ("gw_dreamer_e2e.py", ["--smoothing", "0"], "--smoothing 0: must be at least 1"),
    ("ppo_variants.py", ["--gae-lambda", "1.5"], "--gae-lambda 1.5: must be in [0, 1]"),
    ("gw_dreamer.py", ["--criterion", "nan"], "--criterion nan: must be a finite number"),
    (
        "gw_dreamer.py",
        ["--env", "robodesk", "--task", "stack", "--stop-at-criterion"],
        "--stop-at-criterion: stack has no scripted expert",
    ),
    *(
        (s, ["--device", "cuda:99"], "--device cuda:99: this torch cannot use it")
        for s in (*AGENT_SCRIPTS, "pretrain_vae_gw.py")
    ),
    *(
        (script, ["--learning-starts", "50", "--total-steps", "50"], "--learning-starts 50: must be below")
        for script in ("gw_dreamer.py", "gw_dreamer_e2e.py", "dreamer_baseline.py")
    ),
]


def test_flags_out_of_range_stop_at_start_with_one_line(tmp_path):
    """Exit 2, one line, and nothing written, for each bad value of BAD_FLAGS."""
    for script, flags, message in BAD_FLAGS:
        assert_refused(run_cli(script, tmp_path, *flags, "--checkpoint-dir", str(tmp_path / "ck")), message)
    assert not (tmp_path / "ck").exists() and not (tmp_path / "runs").exists()


def test_ctrl_c_during_the_policy_export_says_so_and_resume_exports_it(pretrained, tmp_path):
    """Dreamer's final save, then Ctrl-C while its policy is exported: one line saying the agent is saved
    and how to export it; the hint, run as printed, writes the policy. Fails if the interruption is silent."""
    script = "dreamer_baseline.py"
    ck = ["--checkpoint-dir", str(pretrained[0] / "ck"), "--checkpoint", str(tmp_path / "agent.pt")]
    argv = [script, "--env", "simple_shapes", *ck, *AGENT_TINY[script]]
    code = SIGINT_IN.format(root=str(ROOT), module=script[:-3], func="export_policy", argv=argv)
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    policy = tmp_path / "agent.policy.pt2"
    hint = (
        f"interrupted while exporting {policy}; the agent is saved at {tmp_path / 'agent.pt'}, and the same"
    )
    assert out.returncode == 130 and hint in out.stdout and "Traceback" not in out.stderr, (
        out.stdout + out.stderr
    )
    assert (tmp_path / "agent.pt").is_file() and not policy.exists()
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]
    again = run_cli(script, tmp_path, *argv[1:], "--resume")
    assert again.returncode == 0 and policy.is_file(), again.stdout + again.stderr


# Saves killed half-way ----------
KILLED_SAVE = textwrap.dedent(
    """
    import os, sys, time
    sys.path.insert(0, {root!r})
    import gw_dreamer as G
    def stall(fd):  # the new file is written but not yet in place: the process dies here
        print("writing", flush=True)
        time.sleep(120)
    os.fsync = stall
    G.atomic_save({{"version": 2, "payload": list(range(100000))}}, G.Path({path!r}))
    """
)


def test_kill_9_during_a_save_leaves_the_previous_checkpoint_loadable(tmp_path):
    import gw_dreamer as G

    path = tmp_path / "agent.pt"
    G.atomic_save({"version": 1}, path)
    code = KILLED_SAVE.format(root=str(ROOT), path=str(path))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "writing"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    assert torch.load(path, weights_only=False) == {"version": 1}
    # its temporary file is its own (named by its process id), so another process's save is unaffected
    assert [p.name for p in tmp_path.iterdir() if p.suffix == ".tmp"] == [f".agent.pt.{proc.pid}.tmp"]
    G.atomic_save({"version": 3}, path)
    assert torch.load(path, weights_only=False) == {"version": 3}


@pytest.mark.parametrize("fault", ["full disk", "torch's full disk", "second Ctrl-C"])
def test_a_failed_save_says_why_keeps_the_previous_checkpoint_and_leaves_no_partial(
    fault, tmp_path, monkeypatch, capsys
):
    """A full disk (OSError ENOSPC, or torch's "unexpected pos") is one line naming the file and the cause;
    a second Ctrl-C stops at once, saying which save it cut; the previous checkpoint loads and no .tmp is
    left. Fails if atomic_save lets the raw error through or forgets its temporary file."""
    import gw_dreamer as G

    path = tmp_path / "agent.pt"
    G.atomic_save({"version": 1}, path)

    def broken_save(obj, f):
        f.write(b"the first bytes")
        if fault == "full disk":
            raise OSError(errno.ENOSPC, "No space left on device")
        if fault == "torch's full disk":
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64 vs 0")
        raise KeyboardInterrupt

    monkeypatch.setattr(G.torch, "save", broken_save)
    monkeypatch.setattr(sys, "argv", ["gw_dreamer.py"])
    with pytest.raises(SystemExit) as stop:
        G.cli(lambda _: G.atomic_save({"version": 2}, path), G.Args)  # parse the Args, then the save
    monkeypatch.undo()
    out = capsys.readouterr()
    if fault == "second Ctrl-C":
        assert stop.value.code == 130
        assert out.out == f"interrupted while saving {path}; the previous agent.pt is kept\n"
    else:
        assert stop.value.code == 2
        assert (
            out.err
            == f"error: cannot save {path} (no space left on the device); the previous agent.pt is kept\n"
        )
    assert torch.load(path, weights_only=False) == {"version": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["agent.pt"]


def test_stage_identity_covers_the_data_and_the_vaes():
    """The gw stage's identity changes with its own flags, the data's and the VAE weights it encodes with."""
    base = P.Args(env="simple_shapes").resolve()
    vae = {"vae_v": {"w": torch.zeros(3)}, "vae_attr": {"w": torch.ones(3)}}
    ident = P.stage_identity(base, "gw", vae)
    assert ident != P.stage_identity(base, "gw", vae | {"vae_attr": {"w": torch.full((3,), 1.01)}})
    assert ident != P.stage_identity(P.Args(env="simple_shapes", wide_share=0.5).resolve(), "gw", vae)
    assert ident != P.stage_identity(P.Args(env="simple_shapes", gw_lr=1e-3).resolve(), "gw", vae)
    assert ident == P.stage_identity(P.Args(env="simple_shapes", log_every=7).resolve(), "gw", vae)


# 7. Silent mix-ups of pre-trained files ----------
def test_a_gw_of_another_vae_is_refused_by_pretraining_and_by_the_agents(pretrained, tmp_path):
    """After `--stages vae --overwrite` remakes the VAE, the GW trained on the old one's latents is refused
    by `--stages gw` (named as another VAE, not as a flag) and by GW-Dreamer and GW-PPO, whose hint
    retrains the GW on the same data. Fails if a reader skips check_gw_vae_pair or the gw stage stops
    recording the VAE's digest."""
    ck = tmp_path / "ck" / "simple_shapes"
    shutil.copytree(pretrained[0] / "ck" / "simple_shapes", ck, ignore=shutil.ignore_patterns("agents"))
    flags = [
        "--data-dir",
        str(pretrained[0] / "data"),
        "--checkpoint-dir",
        str(tmp_path / "ck"),
        *TINY_PRETRAIN,
    ]
    gw = (ck / "gw.pt").read_bytes()
    run_script("pretrain_vae_gw.py", tmp_path, "--env", "simple_shapes", "--stages", "vae", *flags,
               "--vae-steps", "13", "--overwrite")  # fmt: skip
    out = run_cli("pretrain_vae_gw.py", tmp_path, "--env", "simple_shapes", "--stages", "gw", *flags)
    assert_refused(out, str(ck / "gw.pt"), "another VAE (vae.pt was remade since)", "--overwrite")
    assert "--vae-" not in out.stderr and (ck / "gw.pt").read_bytes() == gw
    hint = f"--stages gw --data-dir {pretrained[0] / 'data'} --loss-preset gw --overwrite --checkpoint-dir"
    for script in ("gw_dreamer.py", "ppo_variants.py"):
        ours = ["--checkpoint-dir", str(tmp_path / "ck"), "--checkpoint", str(tmp_path / "agent.pt")]
        out = run_cli(script, tmp_path, "--env", "simple_shapes", *ours, *AGENT_TINY[script])
        assert_refused(out, f"{ck / 'gw.pt'} was trained on the latents of another VAE than", hint)
        assert not (tmp_path / "agent.pt").exists()


def test_a_vae_records_the_data_it_read_and_refuses_to_stand_for_grown_data(pretrained, tmp_path):
    """The vae stage's record holds the samples it read; after the data folder grows, the old vae.pt is
    no longer "made with these settings". Fails if the identity records only the --n-samples flag."""
    shutil.copytree(pretrained[0] / "data", tmp_path / "data")
    shutil.copytree(pretrained[0] / "ck" / "simple_shapes", tmp_path / "ck" / "simple_shapes")
    flags = [
        "--env",
        "simple_shapes",
        "--data-dir",
        str(tmp_path / "data"),
        "--checkpoint-dir",
        str(tmp_path / "ck"),
    ]
    vae = torch.load(tmp_path / "ck" / "simple_shapes" / "vae.pt", weights_only=False)
    assert vae["identity"]["data_read"].startswith("600 samples, shards ")
    same = run_script("pretrain_vae_gw.py", tmp_path, *flags, *TINY_PRETRAIN, "--stages", "vae")
    assert "stage skipped" in same
    run_script(
        "pretrain_vae_gw.py", tmp_path, *flags, *TINY_PRETRAIN, "--stages", "collect", "--n-samples", "700"
    )
    out = run_cli("pretrain_vae_gw.py", tmp_path, *flags, *TINY_PRETRAIN, "--stages", "vae")
    assert_refused(out, "other data (600 samples, shards", "the data folder now holds 700 samples")


def test_a_run_still_training_holds_a_lock_that_a_second_process_cannot_take(pretrained, tmp_path):
    """While a run trains, a second command on it (--resume) stops at start naming the process; Ctrl-C
    releases the lock; a lock left by a process that is gone (kill -9) is taken over. Fails if
    claim_outputs takes no lock, or cannot tell a dead holder from a live one."""
    ck = ["--checkpoint-dir", str(pretrained[0] / "ck"), "--checkpoint", str(tmp_path / "agent.pt")]
    long = ["--log-every", "50", "--total-steps", "3000"]
    command = [sys.executable, str(ROOT / "gw_dreamer.py"), "--env", "simple_shapes", *ck, *GW_TINY, *long]
    proc = subprocess.Popen(
        command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    for line in proc.stdout:
        if " updates " in line:  # training is under way
            break
    lock = tmp_path / ".agent.pt.lock"
    assert lock.read_text() == str(proc.pid)
    second = agent_cli("gw_dreamer.py", pretrained, tmp_path, "--resume")
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=300)
    assert_refused(second, f"process {proc.pid} is training this run now (lock {lock})", "--resume")
    assert proc.returncode == 130 and not lock.exists()
    import gw_dreamer as G

    gone = subprocess.Popen(["true"])
    gone.wait()
    (tmp_path / ".stale.lock").write_text(str(gone.pid))
    G.take_lock(tmp_path / ".stale.lock")  # its process is gone: taken over
    assert (tmp_path / ".stale.lock").read_text() == str(os.getpid())


def test_ppo_trains_at_least_the_steps_asked_in_whole_rollouts(pretrained, tmp_path):
    """--total-steps 40 with rollouts of 32 steps: two rollouts (64 steps), said at start. Fails if the
    total is rounded down (one rollout, 32 steps) or changed silently."""
    out = agent_cli("ppo_variants.py", pretrained, tmp_path, "--total-steps", "40")
    assert out.returncode == 0, out.stdout + out.stderr
    assert (
        "--total-steps 40 is no whole number of rollouts (32 env steps each): training 2 rollouts, 64"
        in out.stdout
    )
    assert torch.load(tmp_path / "agent.pt", weights_only=False)["state"]["env_steps"] == 64


def test_a_run_saves_after_save_minutes_of_wall_time_between_step_saves():
    """A save is due when --save-minutes of wall time have passed since the last one, even before
    --save-every steps; the step schedule stays as it was (save_due, in the block every agent script
    ends in). Fails if the wall-clock save is missing or if it shifts the next step save."""
    args = SimpleNamespace(save_every=1000, save_minutes=15.0)
    state = G.LoopState(env_steps=500, next_save=1000)
    run = SimpleNamespace(args=args, state=state, last_save=time.time() - 14 * 60)
    assert not G.save_due(run)
    run.last_save = time.time() - 16 * 60
    assert G.save_due(run) and state.next_save == 1000
    run.last_save, state.env_steps = time.time(), 1000
    assert G.save_due(run) and state.next_save == 2000
    run.last_save, state.env_steps = time.time(), 1500
    assert not G.save_due(run)
