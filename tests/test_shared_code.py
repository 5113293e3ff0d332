"""Code the top-level scripts share on purpose. Each script carries its own copy (one file per algorithm,
readable alone): the four agent scripts end in the same fenced block of run infrastructure, and a few
definitions above it recur in several scripts. These tests fail when a copy drifts, and show the lines."""

import ast
import difflib
import functools

import pytest
from conftest import ROOT

GW, E2E, DREAMER, PPO = "gw_dreamer.py", "gw_dreamer_e2e.py", "dreamer_baseline.py", "ppo_variants.py"
PRETRAIN = "pretrain_vae_gw.py"
AGENTS = (GW, E2E, DREAMER, PPO)
DREAMERS = (GW, E2E, DREAMER)

FENCE = "# ==== run infrastructure: the same in every agent script (tests/test_shared_code.py) ===="

SHARED = {
    # Safe runs (docs/safe_runs.md): pre-training carries the agents' copies (their block holds them)
    **dict.fromkeys(
        "UsageError require atomic_save read_checkpoint ensure_writable setting_changes StopRequest"
        " check_device keep_freed_memory cli".split(),
        (GW, PRETRAIN),
    ),
    # Environments, steps and FLOPs
    **dict.fromkeys("ACTION_REPEAT make_envs step_success count_flops conv_block".split(), AGENTS),
    # The frozen modules read from pretrain_vae_gw.py's checkpoints
    **dict.fromkeys("AttrVAE ENV_SPECS FUSION".split(), (GW, E2E, PPO)),
    "GlobalWorkspace": (GW, PPO),
    "check_gw_vae_pair": (GW, PPO),
    "vae_digest": (GW, PPO, PRETRAIN),
    "VisualVAE": (GW, E2E),
    # DreamerV3's pieces
    **dict.fromkeys("TwoHot symlog symexp lambda_returns action_for_env ReturnScale Dream".split(), DREAMERS),
    # Random actions before learning
    "random_actions": DREAMERS,
    "LoopState": (GW, DREAMER),
    # The GW-Dreamer world model and actor-critic (frozen GW and end-to-end variants)
    **dict.fromkeys(
        "Actor Critic RewardDecoder WorldModel SIZES dream_starts schedule actor_grad world_model_loss"
        " actor_critic_loss dream_loss world_model_loss_open_loop open_loop_loss replay_critic_loss explore"
        " PAPER_OFF PAPER_ON NEVER_ENDS CPU_TABLE"
        " updates_due mlp final_observations imagine run_name finish".split(),
        (GW, E2E),
    ),
}


def fenced_block(text: str) -> str:
    """Everything below the fence line (which must occur once)."""
    if text.count(FENCE) != 1:
        raise ValueError(f"the fence line occurs {text.count(FENCE)} times, not once")
    return text.split(FENCE, 1)[1]


def first_difference(copies: dict[str, str], what: str) -> str:
    """'' when every script's copy is the same text; else the first that differs, as a unified diff."""
    (first, text), *others = copies.items()
    for other, copy in others:
        diff = "\n".join(
            difflib.unified_diff(text.splitlines(), copy.splitlines(), first, other, lineterm="", n=0)
        )
        if diff:
            return f"{what} has drifted between {first} and {other}:\n{diff}"
    return ""


def block_drift(scripts: tuple[str, ...] = AGENTS, root=ROOT) -> str:
    """'' when every script ends in the same fenced block; else the first difference."""
    blocks = {s: fenced_block((root / s).read_text()) for s in scripts}
    return first_difference(blocks, "the run-infrastructure block")


def test_every_agent_script_ends_in_the_same_run_infrastructure_block():
    problem = block_drift()
    assert not problem, problem


def test_the_block_is_the_infrastructure_and_the_method_stays_above_it():
    """The block holds the safe-run and pre-trained-lookup code and the CLI entry, no network or loss;
    main() comes after the update it calls (the method first, as the paper's algorithm box)."""
    for script in AGENTS:
        text = (ROOT / script).read_text()
        block = definitions(fenced_block(text))
        for name in ("atomic_save", "claim_outputs", "load_pretrained", "StopRequest", "cli", "log_episode"):
            assert name in block, (script, name)
        above = definitions(text.split(FENCE)[0])
        assert "main" in above and not set(above) & set(block), script
        names = list(above)
        update = "ppo_update" if script == PPO else "train_update"
        assert names.index("main") > names.index(update), script
        assert fenced_block(text).rstrip().endswith("cli(main, Args)"), script


def test_the_block_check_sees_a_changed_line(tmp_path):
    for s in AGENTS:
        (tmp_path / s).write_text((ROOT / s).read_text())
    assert block_drift(AGENTS, tmp_path) == ""
    text = (tmp_path / PPO).read_text()
    (tmp_path / PPO).write_text(text.replace("def last_good(path", "def last_good(p", 1))
    problem = block_drift(AGENTS, tmp_path)
    assert problem.startswith(
        "the run-infrastructure block has drifted between gw_dreamer.py and ppo_variants"
    )
    assert "-def last_good(path" in problem and "+def last_good(p" in problem
    (tmp_path / PPO).write_text(text.replace(FENCE, "# the fence, edited"))
    with pytest.raises(ValueError, match="occurs 0 times"):
        block_drift(AGENTS, tmp_path)


@functools.cache
def definitions(text: str) -> dict[str, str]:
    """name -> source of every top-level def, class and assignment in ``text``."""
    lines = text.splitlines()
    out = {}
    for node in ast.parse(text).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            name = node.name
        elif isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            name = node.targets[0].id
        else:
            continue
        first = min([node.lineno, *(d.lineno for d in getattr(node, "decorator_list", []))])
        out[name] = "\n".join(lines[first - 1 : node.end_lineno])
    return out


def drift(name: str, scripts: tuple[str, ...], root=ROOT) -> str:
    """'' when every script's copy of ``name`` is the same; else which copy differs, as a unified diff."""
    copies = {s: definitions((root / s).read_text()).get(name) for s in scripts}
    missing = [s for s, src in copies.items() if src is None]
    if missing:
        return f"{name} is missing from {missing}"
    return first_difference(copies, name)


@pytest.mark.parametrize("name", sorted(SHARED))
def test_shared_definition_is_the_same_in_every_script(name):
    problem = drift(name, SHARED[name])
    assert not problem, problem


def test_the_drift_check_sees_a_changed_line(tmp_path):
    """The check compares real source: one changed character in a copy is reported, with the line."""
    for s in (GW, E2E):
        (tmp_path / s).write_text((ROOT / s).read_text())
    assert drift("symlog", (GW, E2E), tmp_path) == ""
    text = (tmp_path / E2E).read_text().replace("def symlog(x", "def symlog(y", 1)
    (tmp_path / E2E).write_text(text)
    problem = drift("symlog", (GW, E2E), tmp_path)
    assert problem.startswith("symlog has drifted between gw_dreamer.py and gw_dreamer_e2e.py")
    assert "-def symlog(x" in problem and "+def symlog(y" in problem
    assert "is missing from" in drift("no_such_definition", (GW, E2E), tmp_path)
