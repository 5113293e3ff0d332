"""dreamer_baseline.py: parameter counts per size, CLI runs on both envs for both --obs, resume, modality
ablation, world-model learning, symlog/two-hot, imagination gradients, replay entries, the exported
expert policy feeding pretrain_vae_gw.py, errors."""

import copy
import dataclasses
import math
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F
from conftest import (
    DREAMER_SMALL,
    ROOT,
    assert_actions_read_dreamt_states_as_constants,
    interrupt_run,
    logged_totals,
    previous_layout,
    record_calls,
    refused_then_converted,
    run_pretrain,
    run_script,
    tiny_agent_args,
)

import dreamer_baseline as D
import pretrain_vae_gw as P

SMALL = [arg for k, v in DREAMER_SMALL.items() for arg in (f"--{k.replace('_', '-')}", str(v))]
TINY = [
    *SMALL,
    *"--learning-starts 100 --batch-size 4 --batch-length 8 --train-ratio 16 --imag-horizon 5".split(),
    *"--eval-episodes 2 --video-every 0 --log-every 100".split(),
]
SS = ("--env", "simple_shapes", "--checkpoint-dir")  # followed by the folder
RD = ["--env", "robodesk", "--task", "push_green", "--render-quality", "fast", "--episode-length", "40"]


def small_args(pretrained, **kw) -> D.Args:
    """``tiny_agent_args`` with the small network widths of DREAMER_SMALL."""
    return tiny_agent_args(D, pretrained, **(DREAMER_SMALL | kw))


def agent_path(ck: Path, name: str) -> Path:
    return ck / "agents" / f"{name}.pt"


@pytest.mark.parametrize("env,size", [("simple_shapes", "2m"), ("robodesk", "12m"), ("robodesk", "40m")])
def test_parameter_count_matches_the_table_within_10_percent(env, size):
    args = D.Args(env=env, size=size).resolve()
    agent = D.Agent(env, D.Observer(env, "raw", None).spaces(env), args)
    total = agent.n_trainable()["total"]
    assert abs(total / D.TABLE_TOTALS[size] - 1) < 0.10, total


@pytest.fixture(scope="module")
def ss_run(tmp_path_factory):
    """300 steps of Dreamer (raw observations) on Simple Shapes through the CLI, saving at 150 and the end."""
    tmp = tmp_path_factory.mktemp("dreamer_ss")
    more = "--total-steps 300 --eval-every 150 --save-every 150 --video-every 300".split()
    log = run_script("dreamer_baseline.py", tmp, *SS, str(tmp / "ck"), *TINY, *more)
    return tmp, log, agent_path(tmp / "ck" / "simple_shapes", "dreamer_raw_2m_simple_shapes_s1")


def test_simple_shapes_cli_run_trains_saves_and_logs(ss_run):
    tmp, log, agent = ss_run
    assert "Dreamer 2m with custom widths on simple_shapes" in log and "done:" in log
    ck = torch.load(agent, weights_only=False)
    assert ck["kind"] == "dreamer" and ck["state"]["env_steps"] == 300
    assert ck["state"]["updates"] == (300 - 100) * 16 // (4 * 8)  # DreamerV3's train ratio
    assert ck["state"]["flops"] == ck["state"]["updates"] * ck["state"]["flops_per_update"] > 0
    assert agent.with_suffix(".policy.pt2").is_file()
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tmp / "runs" / "dreamer_raw_2m_simple_shapes_s1")).Reload()
    tags = "charts/episodic_return charts/normalised_return charts/SPS losses/loss_wm losses/kl"
    for tag in (*tags.split(), "losses/loss_image", "eval/episodic_return"):
        assert tag in acc.Tags()["scalars"], tag
    assert "dreams/real_top_imagined_bottom" in acc.Tags()["images"]


def test_replay_holds_dreamerv3_entries(ss_run):
    """Entries (o_t, a_{t-1}, r_t, terminal_t, first_t): an episode's final observation is its own entry
    and the next entry starts a new episode with no previous action."""
    replay = torch.load(ss_run[2], weights_only=False)["replay"]["data"]
    first, reward, action = replay["first"][0], replay["reward"][0], replay["action"][0]
    starts = np.flatnonzero(first)
    assert starts[0] == 0 and len(starts) >= 2  # 100-step episodes: several in 300 steps
    assert np.all(reward[starts] == 0) and np.all(action[starts] == 0)
    assert np.all(action[1:].sum(-1)[first[1:] == 0] == 1)  # one-hot previous actions inside episodes
    assert np.all(np.diff(starts) == 101)  # 100 steps + the final observation's entry


def test_resume_continues_the_saved_run(ss_run):
    tmp, _, agent = ss_run
    more = "--total-steps 400 --resume --eval-every 1000 --save-every 1000".split()
    log = run_script("dreamer_baseline.py", tmp, *SS, str(tmp / "ck"), *TINY, *more)
    assert "resuming" in log and "at env step 300" in log
    ck = torch.load(agent, weights_only=False)
    assert ck["state"]["env_steps"] == 400 and ck["state"]["updates"] == (400 - 100) * 16 // 32
    assert logged_totals(tmp, "dreamer_raw_") == [(0, 300), (300, 400)]


def test_eval_only_with_each_drop_and_size_mismatch(ss_run, pretrained):
    tmp, _, agent = ss_run
    more = ["--eval-only", "--checkpoint", str(agent), "--drop", "vision", "--eval-episodes", "3"]
    log = run_script("dreamer_baseline.py", tmp, "--env", "simple_shapes", *SMALL, *more)
    assert "drop=vision: return" in log and "3 episodes" in log
    for drop in ("none", "attr"):
        args = small_args(pretrained, eval_only=True, checkpoint=str(agent), drop=drop, eval_episodes=2)
        out = D.main(args)
        # The same episodes by hand on the agent loaded from the file (same seeds, same draws) give the
        # same return: fails if the evaluation does not load the saved weights or drops another input.
        args = args.resolve()
        observer, _ = D.load_frozen(args, torch.device("cpu"))
        random.seed(args.seed)
        np.random.seed(args.seed)
        torch.manual_seed(args.seed)
        by_hand = D.Agent(args.env, observer.spaces(args.env), args)
        by_hand.load_state_dict(torch.load(agent, weights_only=False)["agent"])
        rets, _ = D.run_episodes(by_hand, observer, args, 2, drop, seed=args.seed + 10**6)
        assert out["drop"] == drop and out["return_mean"] == pytest.approx(float(rets.mean()), abs=1e-9)
    with pytest.raises(D.UsageError, match="was trained with --deter 64 .*; pass --deter 64"):
        D.main(D.Args(eval_only=True, checkpoint=str(agent)))


def test_a_checkpoint_of_the_previous_layout_is_refused_then_converted_and_evaluates(
    ss_run, pretrained, tmp_path
):
    """An agent saved with the return scale in the loop state (the layout before it became part of the
    agent) is refused with the command that converts it; converted, it evaluates to the same returns as
    the current layout."""
    _, _, agent = ss_run
    previous_layout(agent, tmp_path / "old.pt")
    old = small_args(pretrained, eval_only=True, checkpoint=str(tmp_path / "old.pt"), eval_episodes=2)
    refused_then_converted(lambda: D.main(old), tmp_path / "old.pt")
    paths = (agent, tmp_path / "old.pt")
    runs = [D.main(small_args(pretrained, eval_only=True, checkpoint=str(p), eval_episodes=2)) for p in paths]
    assert runs[0] == runs[1]


def test_dropping_a_modality_zeroes_its_input(pretrained):
    from envs.simple_shapes import sample_dataset

    obs = sample_dataset(3, seed=0)
    image, attr = torch.as_tensor(obs["image"]), torch.as_tensor(obs["attr"])
    raw = D.Observer("simple_shapes", "raw", None)
    assert raw(image, attr, "vision")["image"].abs().sum() == 0
    assert torch.equal(raw(image, attr, "vision")["attr"], attr)
    assert raw(image, attr, "attr")["attr"].abs().sum() == 0
    vae = D.Observer(
        "simple_shapes",
        "vae",
        D.load_pretrained(
            pretrained[0] / "ck" / "simple_shapes" / "vae.pt", "vae", "simple_shapes", "collect vae"
        ),
    )
    full, no_attr, no_vision = (
        vae(image, attr)["x"],
        vae(image, attr, "attr")["x"],
        vae(image, attr, "vision")["x"],
    )
    assert (
        full.shape == (3, 20)
        and torch.all(no_attr[:, 10:] == 0)
        and torch.equal(no_attr[:, :10], full[:, :10])
    )
    assert torch.all(no_vision[:, :10] == 0) and torch.equal(no_vision[:, 10:], full[:, 10:])


def test_vae_dreamer_cli_run(pretrained):
    tmp = pretrained[0]
    more = "--obs vae --total-steps 200 --eval-every 1000".split()
    log = run_script("dreamer_baseline.py", tmp, *SS, str(tmp / "ck"), *TINY, *more)
    assert "VAE-Dreamer 2m with custom widths" in log and "done:" in log
    ck = torch.load(
        agent_path(tmp / "ck" / "simple_shapes", "dreamer_vae_2m_simple_shapes_s1"), weights_only=False
    )
    assert ck["replay"]["data"]["x"].shape[-1] == 20 and "image" not in ck["replay"]["data"]


@pytest.fixture(scope="module")
def rd_run(pretrained_robodesk):
    """Dreamer (raw) on RoboDesk push_green, 60 actions (240 frames, the step unit) of 10-action episodes;
    its policy is an expert."""
    tmp = pretrained_robodesk[0]
    more = "--total-steps 240 --learning-starts 80 --batch-size 2 --eval-episodes 1 --eval-every 1000".split()
    log = run_script("dreamer_baseline.py", tmp, *RD, "--checkpoint-dir", str(tmp / "ck"), *TINY, *more)
    return tmp, log, agent_path(tmp / "ck" / "robodesk", "dreamer_raw_12m_robodesk_push_green_s1")


def test_robodesk_cli_runs_for_both_observations(rd_run):
    tmp, log, agent = rd_run
    assert "Dreamer 12m with custom widths on robodesk_push_green" in log and "final_success_count" in log
    # normalised as GW-Dreamer's: 0 the random policy, 1 the task's scripted expert
    assert "scripted push_green expert" in log and "final_normalised_return" in log
    ck = torch.load(agent, weights_only=False)
    # one update per batch_size x batch_length / train_ratio = 2 x 8 / 16 = 1 action (4 frames)
    assert ck["state"]["updates"] == (240 - 80) // 4 and ck["task"] == "push_green"
    more = (
        "--obs vae --total-steps 120 --learning-starts 40 --batch-size 2 --eval-episodes 1 --eval-every 1000"
    )
    log = run_script(
        "dreamer_baseline.py",
        tmp,
        *RD,
        "--checkpoint-dir",
        str(tmp / "ck"),
        *TINY,
        *more.split(),
    )
    assert "VAE-Dreamer 12m" in log and "final_success_count" in log


def test_exported_policy_matches_the_agent_and_feeds_the_collector(rd_run, pretrained, tmp_path):
    tmp, _, agent = rd_run
    policy = agent.with_suffix(".policy.pt2")
    program = P.ExpertProgram(policy)
    assert program.meta["task"] == "push_green" and program.meta["env"] == "robodesk"
    # Same weights, same noise: the exported program acts exactly like the agent's own networks.
    args = small_args(pretrained, env="robodesk", task="push_green")
    net = D.Agent("robodesk", D.Observer("robodesk", "raw", None).spaces("robodesk"), args)
    net.load_state_dict(torch.load(agent, weights_only=False)["agent"])
    step = D.PolicyStep(net.eval(), D.Observer("robodesk", "raw", None))
    g = torch.Generator().manual_seed(0)
    image, attr = (
        torch.randint(0, 255, (3, 64, 64, 3), dtype=torch.uint8, generator=g),
        torch.randn(3, 76, generator=g),
    )
    state = (
        torch.zeros(3, 64),
        torch.zeros(3, 128),
        torch.zeros(3, 5),
        torch.ones(3),
    )  # deter, stoch, a, first
    inputs = (image, attr, *state, torch.rand(3, 32, 4, generator=g), torch.randn(3, 5, generator=g))
    with torch.no_grad():
        for a, b in zip(step(*inputs), program.program(*inputs), strict=True):
            assert torch.allclose(a, b, atol=1e-5)
    # The collector takes the agent checkpoint (or its .policy.pt2) as the push_green expert.
    collect = "--env robodesk --stages collect --n-samples 30 --render-quality fast".split()
    log = run_pretrain(tmp_path, *collect, "--expert-checkpoint", str(agent))
    assert f"expert data of push_green: the dreamer_baseline.py policy {policy}" in log
    assert P.label_counts(tmp_path / "data" / "robodesk") == {"expert/push_green": 15, "random/": 15}
    with pytest.raises(ValueError, match="expert for 'push_green', which is not among the tasks collected"):
        P.load_expert_policies((str(policy),), ["open_slide"])
    # A policy for a task without a scripted expert makes that task collectable.
    assert (
        P.robodesk_plan(P.Args(env="robodesk", task="open_drawer"), 10, ("open_drawer",))[0][1]
        == "open_drawer"
    )


def test_expert_checkpoint_errors(ss_run, tmp_path):
    ss_policy = ss_run[2].with_suffix(".policy.pt2")
    with pytest.raises(ValueError, match="policy for env 'simple_shapes'"):
        P.load_expert_policies((str(ss_policy),), ["push_green"])
    with pytest.raises(P.UsageError, match="python dreamer_baseline.py --env robodesk"):
        P.load_expert_policies((str(tmp_path / "none.pt"),), ["push_green"])
    bad = tmp_path / "bad.policy.pt2"
    bad.write_bytes(b"not an archive")
    with pytest.raises(ValueError, match="not a policy exported by dreamer_baseline.py"):
        P.load_expert_policies((str(bad),), ["push_green"])


# --------------------------------------------------------------------------------------------------
def fixed_batch(seed: int = 0) -> dict[str, torch.Tensor]:
    """Sequences of a moving bright square with its position as the attribute: learnable structure."""
    rng = np.random.default_rng(seed)
    B, T = 4, 8
    pos = rng.integers(0, 24, (B, 1, 2)) + np.arange(T)[None, :, None]
    image = np.zeros((B, T, 32, 32, 3), np.uint8)
    for b in range(B):
        for t in range(T):
            y, x = pos[b, t]
            image[b, t, y : y + 6, x : x + 6] = 255
    attr = np.zeros((B, T, 11), np.float32)
    attr[..., :2] = pos / 32.0
    first = torch.zeros(B, T).index_fill_(1, torch.tensor([0]), 1.0)
    action = torch.nn.functional.one_hot(torch.ones(B, T, dtype=torch.long), 7).float()
    reward = torch.as_tensor(-pos.sum(-1) / 32.0, dtype=torch.float32)
    batch = {
        "image": torch.as_tensor(image),
        "attr": torch.as_tensor(attr),
        "action": action,
        "reward": reward,
    }
    return batch | {"terminal": torch.zeros(B, T), "first": first}


def test_world_model_loss_falls_on_a_fixed_batch(pretrained):
    torch.manual_seed(0)
    args = small_args(pretrained)
    spaces = D.Observer("simple_shapes", "raw", None).spaces("simple_shapes")
    agent = D.Agent("simple_shapes", spaces, args)
    opt = D.make_optimizers(agent, args)["wm"]
    batch = fixed_batch()
    losses = []
    for _ in range(60):
        loss, terms, _ = D.world_model_loss(agent, batch, args)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses[::10]
    assert math.isfinite(terms["kl"].item())


def test_symlog_and_two_hot_round_trips():
    x = torch.tensor([-1e4, -20.0, -1.0, -0.3, 0.0, 0.7, 3.0, 512.0])
    assert torch.allclose(D.symexp(D.symlog(x)), x, rtol=1e-5)
    th = D.TwoHot()
    w = th.encode(x)
    assert torch.allclose(w.sum(-1), torch.ones(len(x))) and ((w > 0).sum(-1) <= 2).all()
    assert torch.allclose(th.mean(torch.log(w + 1e-30)), x, rtol=1e-4, atol=1e-4)


def imagine(agent, deter, stoch, horizon: int, grad: bool, critic: bool = False):
    """A Dream as dream_loss makes it: the rollout, then its heads in one product; with ``critic`` also
    the critic's logits from that product."""
    feats, actions, policy = D.rollout(agent, deter, stoch, horizon, grad)
    with torch.set_grad_enabled(grad):
        nets = (agent.reward_head, agent.cont_head) + ((agent.critic,) if critic else ())
        reward, cont, *value = D.heads(feats, *nets)
    dream = D.dream_of(agent, feats, actions, policy, reward, cont)
    return (dream, value[0]) if critic else dream


def test_imagination_gradients_follow_the_actor_gradient_mode(pretrained):
    torch.manual_seed(0)
    args = small_args(pretrained, env="robodesk")
    agent = D.Agent("robodesk", D.Observer("robodesk", "raw", None).spaces("robodesk"), args)
    deter, stoch = torch.randn(6, 64), torch.zeros(6, 128)
    feats, actions, rewards, conts, policy = imagine(agent, deter, stoch, 4, grad=False)
    assert feats.shape == (5, 6, 64 + 128) and actions.shape == (4, 6, 5) and not feats.requires_grad
    assert policy is None  # without a graph the loss runs the actor on the dreamt states itself
    dream = imagine(agent, deter, stoch, 4, grad=True)
    # The loss reads the actor outputs that drew the actions (the actor on each dreamt state), not a
    # second pass of the actor: the same losses either way.
    assert torch.allclose(dream.policy, agent.actor(dream.feats[:-1].detach()))
    again = D.actor_critic_loss(agent, dream._replace(policy=None), torch.ones(6), dynamics=True)
    agent.return_scale.ema.zero_(), agent.return_scale.count.zero_()
    loss_actor, loss_critic, _ = D.actor_critic_loss(agent, dream, torch.ones(6), dynamics=True)
    assert loss_actor.item() == pytest.approx(again[0].item(), rel=1e-5)
    assert loss_actor.dtype == loss_critic.dtype == torch.float32  # the float64 return scale stays apart
    # Dynamics backpropagation: the actor's loss reaches its weights through the imagined transitions.
    first_layer = agent.actor.net[0][0].weight
    (g_actor,) = torch.autograd.grad(loss_actor, [first_layer], retain_graph=True)
    assert g_actor.abs().sum() > 0
    # One critic pass serves both losses: the critic's loss trains the critic exactly as it would on
    # detached features (train_update keeps it from the world model and the actor).
    crit = list(agent.critic.parameters())
    g_crit = torch.autograd.grad(loss_critic, crit, retain_graph=True)
    detached = D.Dream(*(x.detach() for x in dream[:4]))
    _, loss_critic_detached, _ = D.actor_critic_loss(agent, detached, torch.ones(6), dynamics=True)
    assert loss_critic_detached.item() == pytest.approx(loss_critic.item(), rel=1e-6)
    for g, g_detached in zip(g_crit, torch.autograd.grad(loss_critic_detached, crit), strict=True):
        assert torch.allclose(g, g_detached, rtol=1e-5, atol=1e-7)
    # The actor reads each dreamt state as a constant (DreamerV3's policy(sg(s))).
    assert_actions_read_dreamt_states_as_constants(imagine, agent, deter, stoch)


def random_replay(agent, spaces, length: int = 24) -> D.Replay:
    """One stream of random entries (one episode) for updates on random data."""
    replay, rng = D.Replay(length, 1, spaces, agent.n_actions, 0), np.random.default_rng(0)
    for t in range(length):
        entry = {k: rng.normal(size=(1, *shape)).astype(np.float32) for k, shape in spaces.items()}
        if "image" in spaces:
            entry["image"] = rng.integers(0, 256, (1, *spaces["image"])).astype(np.uint8)
        entry |= {"action": rng.uniform(-1, 1, (1, agent.n_actions)), "reward": [float(t % 3)]}
        replay.add(np.array([0]), entry | {"terminal": [0.0], "first": [float(t == 0)]})
    return replay


def test_train_update_leaves_the_world_model_to_its_own_loss_under_dynamics_backprop(pretrained):
    """The dream and the critic's values are differentiable, but only L_WM trains the world model and the
    critic's loss is the critic's alone: after an update the world model holds the gradients of L_WM on
    the same batch. Fails if the actor-critic losses are back-propagated into every network."""
    torch.manual_seed(0)
    args = dataclasses.replace(small_args(pretrained, env="robodesk"), batch_size=3, batch_length=5)
    spaces = D.Observer("robodesk", "raw", None).spaces("robodesk")
    agent = D.Agent("robodesk", spaces, args)
    replay = random_replay(agent, spaces)
    twin, replay_twin, rng = copy.deepcopy(agent), copy.deepcopy(replay), torch.get_rng_state()
    D.train_update(agent, D.make_optimizers(agent, args), replay, args)
    batch = {k: torch.as_tensor(v) for k, v in replay_twin.sample(3, 5).items()}
    torch.set_rng_state(rng)  # the same posterior samples
    D.world_model_loss(twin, batch, args)[0].backward()
    nn.utils.clip_grad_norm_(twin.world_model_parameters(), 1000.0)  # as train_update clips them
    for p, q in zip(agent.world_model_parameters(), twin.world_model_parameters(), strict=True):
        assert (p.grad is None) == (q.grad is None)
        if p.grad is not None:
            assert torch.allclose(p.grad, q.grad, atol=1e-6)


def test_the_block_gru_mixes_a_shared_input_as_if_copied_to_every_block():
    """``BlockLinear.mixed(own, shared)`` is ``forward`` on [own_g, shared] per block (the GRU core's
    input), values and gradients. Fails if the shared part of the weights is sliced or laid out wrongly."""
    torch.manual_seed(0)
    block = D.BlockLinear(4, 3 + 5, 6)
    nn.init.normal_(block.bias)
    own, shared = torch.randn(7, 4, 3, requires_grad=True), torch.randn(7, 5, requires_grad=True)
    copied = block(torch.cat([own, shared.unsqueeze(1).expand(7, 4, 5)], -1))
    mixed = block.mixed(own, shared)
    assert torch.allclose(mixed, copied, atol=1e-6)
    grads = [
        torch.autograd.grad(y.square().sum(), [own, shared, block.weight, block.bias])
        for y in (mixed, copied)
    ]
    for g, h in zip(*grads, strict=True):
        assert torch.allclose(g, h, atol=1e-5)


def test_the_gru_core_is_the_block_diagonal_gru_written_out_per_block():
    """``RSSM.core`` against DreamerV3's block-diagonal GRU written out block by block, values and
    gradients: block g reads its own slice of h and all of the mixed inputs, and its reset, candidate and
    update gates are its own output's thirds. Fails if the gates are taken from the wrong block or
    third."""
    torch.manual_seed(0)
    rssm = D.RSSM(embed=8, actions=3, deter=32, hidden=6, classes=4, unimix=0.01)
    for p in rssm.parameters():
        nn.init.normal_(p, std=0.3)
    deter = torch.randn(5, 32, requires_grad=True)
    stoch, action = torch.randn(5, rssm.stoch), torch.randn(5, 3)
    x = torch.cat(
        [rssm.dynin[0](deter), rssm.dynin[1](stoch), rssm.dynin[2](action / action.abs().clamp(min=1))], -1
    )
    own, w = 32 // D.BLOCKS, rssm.dynhid.weight
    hid = [
        torch.cat([deter[:, g * own : (g + 1) * own], x], -1) @ w[g] + rssm.dynhid.bias[g]
        for g in range(D.BLOCKS)
    ]
    hid = F.silu(rssm.dynnorm(torch.cat(hid, -1)))
    out = []
    for g in range(D.BLOCKS):
        y = hid[:, g * own : (g + 1) * own] @ rssm.dyngru.weight[g] + rssm.dyngru.bias[g]
        reset, cand, update = y[:, :own], y[:, own : 2 * own], y[:, 2 * own :]
        cand, update = torch.tanh(torch.sigmoid(reset) * cand), torch.sigmoid(update - 1)
        out.append(update * cand + (1 - update) * deter[:, g * own : (g + 1) * own])
    reference, core = torch.cat(out, -1), rssm.core(deter, stoch, action)
    assert torch.allclose(core, reference, atol=1e-5)
    wrt = [deter, rssm.dyngru.weight, rssm.dynhid.weight]
    for g, h in zip(*(torch.autograd.grad(y.square().sum(), wrt) for y in (core, reference)), strict=True):
        assert torch.allclose(g, h, atol=1e-4)


def test_heads_share_their_first_product_and_compute_each_head():
    """``heads(x, *nets)`` gives each head's own output and the same gradient for x as separate calls.
    Fails if the shared product's output is split in the wrong order or width."""
    torch.manual_seed(0)
    nets = [D.mlp(12, 5, 7, 1), D.mlp(12, 5, 1, 1), D.mlp(12, 5, 3, 2)]
    for net in nets:
        for p in net.parameters():
            nn.init.normal_(p, std=0.5)
    x = torch.randn(4, 6, 12, requires_grad=True)
    together, apart = D.heads(x, *nets), [net(x) for net in nets]
    for y, z in zip(together, apart, strict=True):
        assert y.shape == z.shape and torch.allclose(y, z, atol=1e-6)
    (g,) = torch.autograd.grad(sum(y.square().sum() for y in together), x)
    (h,) = torch.autograd.grad(sum(z.square().sum() for z in apart), x)
    assert torch.allclose(g, h, atol=1e-5)


def test_values_from_the_shared_heads_product_train_as_the_critic_alone(pretrained):
    """The critic in the heads' shared product (dream_loss under dynamics backpropagation): the same
    losses, actor gradients and critic gradients as one critic pass of its own. Fails if the critic's own
    pass reads other states or the shared product's values lose their gradient for the actor."""
    torch.manual_seed(0)
    args = small_args(pretrained, env="robodesk")
    agent = D.Agent("robodesk", D.Observer("robodesk", "raw", None).spaces("robodesk"), args)
    for p in agent.critic.parameters():
        nn.init.normal_(p, std=0.1)
    deter, stoch = torch.randn(6, 64), torch.zeros(6, 128)
    nets = [list(agent.actor.parameters()), list(agent.critic.parameters())]
    grads = []
    for shared in (False, True):
        agent.return_scale.ema.zero_(), agent.return_scale.count.zero_()
        torch.manual_seed(1)
        dream, value = imagine(agent, deter, stoch, 4, grad=True, critic=True)
        given = value if shared else None
        losses = D.actor_critic_loss(agent, dream, torch.ones(6), dynamics=True, value_logits=given)
        grads.append(
            [torch.autograd.grad(x, n, retain_graph=True) for x, n in zip(losses[:2], nets, strict=True)]
        )
    for plain, shared in zip(*grads, strict=True):
        for g, h in zip(plain, shared, strict=True):
            assert g.abs().sum() > 0 and torch.allclose(g, h, rtol=1e-4, atol=1e-6)


def test_freed_large_blocks_stay_in_the_process():
    """After ``keep_freed_memory()`` a freed 256 MB tensor's memory is reused by the next ones, so
    touching them costs no page faults, where glibc's default maps every one afresh (65,536 faults each).
    Where the heap places a block varies, so the test takes the fewest faults of four allocations. Fails
    if large blocks are still mapped per allocation."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the allocator setting is glibc's")
    code = (
        "import resource, sys, torch; sys.path.insert(0, '.'); import dreamer_baseline as D\n"
        "def faults():\n"
        "    x = torch.empty(64 * 2**20); f = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "    x.fill_(1.0); return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f\n"
        "before = min(faults() for _ in range(3)); D.keep_freed_memory()\n"
        "print(before, min(faults() for _ in range(4)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    before, after = map(int, out.stdout.split())
    assert before > 30_000 and after < 1_000, (before, after)


def test_bad_input_is_explained(tmp_path, pretrained):
    missing = dict(checkpoint_dir=str(tmp_path), vae_checkpoint=str(tmp_path / "none.pt"))
    make = "pretrain_vae_gw.py --env simple_shapes --stages collect vae --cpu-preset"
    make += f" --checkpoint-dir {tmp_path}`"
    with pytest.raises(D.UsageError, match=f"no vae checkpoint at .*none.pt; make it with `python {make}"):
        D.main(small_args(pretrained, obs="vae", **missing))
    rd_vae = str(pretrained[0] / "ck" / "simple_shapes" / "vae.pt")
    with pytest.raises(ValueError, match="made for env 'simple_shapes'.*'robodesk'"):
        D.main(small_args(pretrained, env="robodesk", obs="vae", vae_checkpoint=rd_vae))
    with pytest.raises(ValueError, match="unknown RoboDesk task 'fly'"):
        D.main(small_args(pretrained, env="robodesk", task="fly"))
    with pytest.raises(D.UsageError, match="python dreamer_baseline.py --env simple_shapes --obs raw"):
        D.main(small_args(pretrained, eval_only=True, checkpoint=str(tmp_path / "none.pt")))
    with pytest.raises(ValueError, match="multiple of the GRU's 8 blocks"):
        D.Args(deter=100).resolve()
    assert D.updates_due(1_000 + 65 * 16, D.Args().resolve()) == 32  # 16 x 65 replayed steps, ratio 32


def test_ctrl_c_saves_the_run_where_it_stopped(tmp_path):
    agent = agent_path(tmp_path / "ck" / "simple_shapes", "dreamer_raw_2m_simple_shapes_s1")
    state, step = interrupt_run("dreamer_baseline.py", tmp_path, agent, *SS, str(tmp_path / "ck"), *TINY)
    assert state["updates"] == (step - 100) * 16 // (4 * 8)


def test_kl_balancing_and_free_bits_against_autograd_of_the_plain_terms(monkeypatch):
    """DreamerV3's KL: kl_dyn max(free, KL(sg(q) || p)) trains the prior only, kl_rep max(free, KL(q ||
    sg(p))) the posterior only, and an entry under the free nats gives no gradient. Two entries, one far
    above 1 nat and one under it, with every other loss term stubbed to zero. Fails if the stop-gradients
    or the two scales are swapped, or the free bits are dropped."""
    from types import SimpleNamespace

    rssm = SimpleNamespace(classes=32, unimix=0.01)
    rssm.probs = lambda logits: D.RSSM.probs(rssm, logits)
    rssm.kl = lambda q, p: D.RSSM.kl(rssm, q, p)
    g = torch.Generator().manual_seed(0)
    prior0 = torch.randn(1, 2, 1024, generator=g)
    post0 = prior0.clone()
    post0[0, 0] += 3 * torch.randn(1024, generator=g)  # far from the prior: KL >> 1 nat
    post0[0, 1] += 0.01 * torch.randn(1024, generator=g)  # close: KL << 1 nat
    post, prior = post0.clone().requires_grad_(), prior0.clone().requires_grad_()
    monkeypatch.setattr(D, "observe", lambda agent, batch: (None, None, post, prior))
    monkeypatch.setattr(D, "feat_of", lambda deter, stoch: torch.zeros(1, 2, 3))
    agent = SimpleNamespace(
        rssm=rssm,
        decoder=SimpleNamespace(loss=lambda feat, batch: {}),
        twohot=SimpleNamespace(loss=lambda out, r: torch.zeros(1, 2)),
        reward_head=lambda feat: torch.zeros(1, 2, 1),
        cont_head=lambda feat: torch.full((1, 2, 1), 30.0),  # continue predicted surely: BCE ~ 0
    )
    batch = {"reward": torch.zeros(1, 2), "terminal": torch.zeros(1, 2)}
    args = SimpleNamespace(kl_free=1.0, kl_dyn=0.5, kl_rep=0.1)
    total, terms, _ = D.world_model_loss(agent, batch, args)
    total.backward()
    kl = rssm.kl(post0, prior0)
    assert kl[0, 0] > 5 and kl[0, 1] < 0.1
    assert total.item() == pytest.approx(((0.5 + 0.1) * kl.clamp(min=1.0)).mean().item(), rel=1e-4)
    p_leaf, q_leaf = prior0.clone().requires_grad_(), post0.clone().requires_grad_()
    (0.5 * rssm.kl(post0, p_leaf)[0, 0] / 2).backward()
    (0.1 * rssm.kl(q_leaf, prior0)[0, 0] / 2).backward()
    assert torch.allclose(prior.grad, p_leaf.grad, atol=1e-6) and torch.allclose(
        post.grad, q_leaf.grad, atol=1e-6
    )
    assert (prior.grad[0, 1] == 0).all() and (post.grad[0, 1] == 0).all()  # under the free nats


def test_eval_only_feeds_every_observation_through_the_drop_it_was_given(ss_run, pretrained, monkeypatch):
    """Every observation of an --eval-only run reaches the agent with --drop's modality zeroed. Fails if
    the evaluation ignores --drop."""
    _, _, agent = ss_run
    seen = record_calls(monkeypatch, D.Observer, "forward", lambda image, attr, drop="none": drop)
    for drop in ("vision", "attr", "none"):
        seen.clear()
        D.main(small_args(pretrained, eval_only=True, checkpoint=str(agent), drop=drop, eval_episodes=2))
        assert len(seen) >= 100 and set(seen) == {drop}, drop  # 2 episodes of 100 steps


def test_robodesk_cpu_preset_and_the_images_of_the_vae(pretrained_robodesk):
    """--cpu-preset on RoboDesk: the table's 2M model on fast images to 800,000 frames, the paper's 12M on
    faithful ones by default; --obs vae sees the images its VAE was trained on and refuses the other kind."""
    paper, cpu = D.Args(env="robodesk").resolve(), D.Args(env="robodesk", cpu_preset=True).resolve()
    assert (paper.size, paper.deter, paper.total_steps, paper.eval_every) == ("12m", 2048, 1_000_000, 10_000)
    assert (cpu.size, cpu.deter, cpu.total_steps, cpu.eval_every) == ("2m", 512, 800_000, 100_000)
    assert (paper.render_quality, cpu.render_quality) == ("faithful", "fast")
    assert D.Args(env="robodesk", cpu_preset=True, size="12m").resolve().deter == 2048  # explicit flags win
    ss = D.Args(cpu_preset=True).resolve()
    assert (ss.size, ss.total_steps, ss.eval_every) == ("2m", 400_000, 10_000)
    ck = str(pretrained_robodesk[0] / "ck")  # its VAE was trained on fast images
    args = D.Args(env="robodesk", obs="vae", checkpoint_dir=ck).resolve()
    assert args.render_quality is None
    D.load_frozen(args, torch.device("cpu"))
    assert args.render_quality == "fast"
    with pytest.raises(D.UsageError, match="trained on fast images"):
        D.load_frozen(D.Args(env="robodesk", obs="vae", checkpoint_dir=ck, render_quality="faithful"), "cpu")
    assert "render_quality" in D.EVAL_KEYS  # an agent is evaluated on the images it was trained on
