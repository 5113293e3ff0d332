"""gw_dreamer_e2e.py: CLI runs on both envs, resume, modality ablation, the jointly trained GW (its losses
fall, its weights move, the VAEs' do not), L_GW equal to pre-training's, the GW learning-rate schedule,
errors."""

import math
import random

import numpy as np
import pytest
import torch
from conftest import (
    assert_actions_read_dreamt_states_as_constants,
    assert_episodes_separated,
    interrupt_run,
    logged_totals,
    previous_layout,
    record_calls,
    refused_then_converted,
    run_script,
    tiny_agent_args,
)

import gw_dreamer_e2e as E
import pretrain_vae_gw as P

TINY = (
    "--learning-starts 100 --batch-size 4 --batch-length 8 --imag-horizon 5 --train-ratio 10"
    " --gw-batch-size 64 --eval-episodes 2 --video-every 0 --log-every 100"
).split()
AGENT = "gw_dreamer_e2e_gw_simple_shapes_s1.pt"
SS = ("--env", "simple_shapes", "--checkpoint-dir")  # followed by the folder


def ss_args(pretrained, **kw) -> E.Args:
    return tiny_agent_args(E, pretrained, **kw)


@pytest.fixture(scope="module")
def ss_run(pretrained):
    """250 steps of end-to-end GW-Dreamer on Simple Shapes through the CLI, saving at 150 and at the end
    (mid-episode)."""
    tmp = pretrained[0]
    more = "--total-steps 250 --eval-every 150 --save-every 150".split()
    log = run_script("gw_dreamer_e2e.py", tmp, *SS, str(tmp / "ck"), *TINY, *more)
    return tmp, log, tmp / "ck" / "simple_shapes" / "agents" / AGENT


def test_dream_actions_read_their_states_as_constants():
    """Fails if the actor's reply to a dreamt state carries the gradient of the actions that made it."""
    torch.manual_seed(0)
    agent = E.Agent("robodesk", "twohot", cpu_preset=True)
    h0, z0 = torch.randn(6, agent.wm.hidden), torch.rand(6, E.ENV_SPECS["robodesk"]["z"]) * 2 - 1
    assert_actions_read_dreamt_states_as_constants(E.imagine, agent, h0, z0)


def test_simple_shapes_cli_run_trains_the_gw_saves_and_logs(ss_run):
    tmp, log, agent = ss_run
    assert "GW-Dreamer end to end on simple_shapes: GW 55,336" in log and "done:" in log  # table: 55K
    ck = torch.load(agent, weights_only=False)
    assert ck["kind"] == "gw_dreamer_e2e" and ck["state"]["env_steps"] == 250
    assert ck["state"]["updates"] == (250 - 100) // 10
    assert ck["state"]["gw_updates"] == 2 * ck["state"]["updates"]  # two GW updates per global step
    assert ck["state"]["flops"] == ck["state"]["updates"] * ck["state"]["flops_per_update"] > 0
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tmp / "runs" / "gw_dreamer_e2e_gw_simple_shapes_s1")).Reload()
    tags = acc.Tags()["scalars"]
    for tag in ("charts/episodic_return", "charts/SPS", "charts/gw_lr", "losses/loss_wm", "losses/loss_gw"):
        assert tag in tags, tags
    for term in ("dcy", "cy", "tr", "fusion", "cont"):
        assert f"losses/loss_{term}" in tags
    assert "dreams/real_top_imagined_bottom" in acc.Tags()["images"]


def flops_of_one_update(gw_batch: int) -> int:
    torch.manual_seed(0)
    args = E.Args(batch_size=2, batch_length=4, imag_horizon=2, gw_batch_size=gw_batch).resolve()
    agent = E.Agent("simple_shapes", "twohot")
    opts, replay = E.make_optimizers(agent, args), fill_replay_with_noise(60)
    return E.count_flops(lambda: E.train_update(agent, opts, replay, args))[1]


def test_gw_flops_are_counted():
    """An update's FLOPs grow with the GW batch: the GW's training is part of the count."""
    assert flops_of_one_update(256) > flops_of_one_update(16) > 0


def test_resume_continues_the_saved_run(ss_run):
    tmp, _, agent = ss_run
    more = "--total-steps 400 --resume --eval-every 1000 --save-every 1000".split()
    log = run_script("gw_dreamer_e2e.py", tmp, *SS, str(tmp / "ck"), *TINY, *more)
    assert "resuming" in log and "at env step 250" in log
    ck = torch.load(agent, weights_only=False)
    assert ck["state"]["env_steps"] == 400 and ck["state"]["gw_updates"] == 2 * (400 - 100) // 10
    assert_episodes_separated(ck["replay"])  # the episode cut by the save at 250 is closed
    assert logged_totals(tmp, "gw_dreamer_e2e_gw_") == [(0, 250), (250, 400)]


def test_eval_only_with_each_drop_and_the_vae_check(ss_run, pretrained, tmp_path):
    tmp, _, agent = ss_run
    more = ["--eval-only", "--checkpoint", str(agent), "--drop", "attr", "--eval-episodes", "3"]
    log = run_script("gw_dreamer_e2e.py", tmp, *SS, str(tmp / "ck"), *more)
    assert "drop=attr: return" in log and "3 episodes" in log
    for drop in ("none", "vision"):
        args = ss_args(pretrained, eval_only=True, checkpoint=str(agent), drop=drop, eval_episodes=3)
        out = E.main(args)
        # The same episodes by hand on the agent loaded from the file (same seeds, same draws) give the
        # same return: fails if the evaluation does not load the saved weights or drops another input.
        args = args.resolve()
        vaes, _ = E.load_frozen(args, torch.device("cpu"))
        random.seed(args.seed)
        np.random.seed(args.seed)
        torch.manual_seed(args.seed)
        by_hand = E.Agent(args.env, args.reward_loss, args.return_norm_decay, args.cpu_preset)
        by_hand.load_state_dict(torch.load(agent, weights_only=False)["agent"])
        rets, _ = E.run_episodes(by_hand, vaes, args, 3, drop, seed=args.seed + 10**6)
        assert out["drop"] == drop and out["return_mean"] == pytest.approx(float(rets.mean()), abs=1e-9)
    vae = torch.load(pretrained[0] / "ck" / "simple_shapes" / "vae.pt", weights_only=False)
    vae["vae_attr"] = {k: v + 0.01 for k, v in vae["vae_attr"].items()}
    torch.save(vae, tmp_path / "other_vae.pt")
    other = ss_args(
        pretrained, eval_only=True, checkpoint=str(agent), vae_checkpoint=str(tmp_path / "other_vae.pt")
    )
    with pytest.raises(ValueError, match="trained on other frozen weights"):
        E.main(other)


def test_a_checkpoint_of_the_previous_layout_is_refused_then_converted_and_evaluates(
    ss_run, pretrained, tmp_path
):
    """An agent saved with the return scale in the loop state (the layout before it became part of the
    agent) is refused with the command that converts it; converted, it evaluates to the same returns as
    the current layout."""
    _, _, agent = ss_run
    previous_layout(agent, tmp_path / "old.pt")
    old = ss_args(pretrained, eval_only=True, checkpoint=str(tmp_path / "old.pt"), eval_episodes=2)
    refused_then_converted(lambda: E.main(old), tmp_path / "old.pt")
    runs = [
        E.main(ss_args(pretrained, eval_only=True, checkpoint=str(p), eval_episodes=2))
        for p in (agent, tmp_path / "old.pt")
    ]
    assert runs[0] == runs[1]


def test_dropping_a_modality_removes_it_from_z():
    torch.manual_seed(0)
    agent = E.Agent("simple_shapes", "twohot")
    u_v, u_attr, other = torch.randn(4, 10), torch.randn(4, 10), torch.randn(4, 10)
    assert torch.equal(agent.z(u_v, u_attr, "vision"), agent.z(other, u_attr, "vision"))
    assert torch.equal(agent.z(u_v, u_attr, "attr"), agent.z(u_v, other, "attr"))
    assert not torch.equal(agent.z(u_v, u_attr), agent.z(other, u_attr))


def test_robodesk_cli_run(pretrained_robodesk):
    tmp = pretrained_robodesk[0]
    env = ["--env", "robodesk", "--task", "push_green", "--checkpoint-dir", str(tmp / "ck")]
    more = "--eval-episodes 1 --total-steps 800 --episode-length 240 --batch-size 2 --eval-every 4000".split()
    log = run_script("gw_dreamer_e2e.py", tmp, *env, "--render-quality", "fast", *TINY, *more)
    assert "end to end on robodesk_push_green" in log and "final_success_count" in log
    assert "scripted push_green expert" in log and "final_normalised_return" in log
    ck = torch.load(
        tmp / "ck" / "robodesk" / "agents" / "gw_dreamer_e2e_gw_robodesk_push_green_s1.pt", weights_only=False
    )
    assert ck["state"]["updates"] == 17 and ck["state"]["gw_updates"] == 34  # 200 actions of 4 frames


def test_robodesk_sees_the_images_of_its_vaes(pretrained_robodesk):
    """On RoboDesk the agent renders the images its frozen VAEs were trained on (fast ones here) and
    refuses the other kind; an agent is evaluated on the images it was trained on."""
    ck = str(pretrained_robodesk[0] / "ck")
    args = E.Args(env="robodesk", checkpoint_dir=ck).resolve()
    assert args.render_quality is None
    E.load_frozen(args, torch.device("cpu"))
    assert args.render_quality == "fast"
    with pytest.raises(E.UsageError, match="trained on fast images"):
        E.load_frozen(E.Args(env="robodesk", checkpoint_dir=ck, render_quality="faithful").resolve(), "cpu")
    assert E.Args().resolve().render_quality == "faithful" and "render_quality" in E.EVAL_KEYS


def test_robodesk_cpu_preset_trains_with_gw_dreamers_preset_settings(pretrained_robodesk, monkeypatch):
    """--cpu-preset on RoboDesk takes gw_dreamer.py's replay value loss, open-loop world-model loss,
    exploration noise and world model without a done head (the paper's settings have none of them and a
    done head); every update computes both losses and no done loss, and every collected action after the
    random ones goes through the noise."""
    import gw_dreamer as G

    preset = ("critic_replay_coef", "wm_open_loop", "wm_open_loop_stride", "explore_noise", "done_head")
    cpu, gw_cpu = (m.Args(env="robodesk", cpu_preset=True).resolve() for m in (E, G))
    assert [getattr(cpu, k) for k in preset] == [getattr(gw_cpu, k) for k in preset]
    assert [getattr(cpu, k) for k in preset] == [0.3, 10, 32, 0.3, "off"]
    assert [getattr(E.Args(env="robodesk").resolve(), k) for k in preset] == [0.0, 0, 16, 0.0, "on"]
    taken, real_explore = [], E.explore
    monkeypatch.setattr(E, "explore", lambda a, args, t: taken.append(real_explore(a, args, t)) or taken[-1])
    outs, real_update = [], E.train_update
    monkeypatch.setattr(E, "train_update", lambda *a, **k: outs.append(real_update(*a, **k)) or outs[-1])
    run = dict(env="robodesk", cpu_preset=True, wm_open_loop=4, total_steps=240, learning_starts=200)
    run |= dict(episode_length=240, exp_name="preset", eval_episodes=1, eval_every=10**6, video_every=0)
    monkeypatch.chdir(pretrained_robodesk[0])  # its TensorBoard folder goes under the test's runs/
    E.main(tiny_agent_args(E, pretrained_robodesk, **run))
    assert len(taken) == (240 - 200) // 4 and len(outs) == 5
    assert all({"loss_z_open", "loss_critic_replay"} <= set(out) for out in outs)
    assert all(float(out["loss_d"]) < 1e-12 for out in outs)  # no done head: d = 0 is certain


# --------------------------------------------------------------------------------------------------
# The jointly trained Global Workspace
# --------------------------------------------------------------------------------------------------
def fill_replay_with_noise(n: int) -> E.Replay:
    rng = np.random.default_rng(0)
    replay = E.Replay(1_000, 1, 10, 7, seed=0)
    for t in range(n):
        u = rng.normal(size=(2, 1, 10)).astype(np.float32)
        replay.add([0], u[0], u[1], np.eye(7)[[t % 7]], [-1.0], [0], [t == 0], [0])
    return replay


def random_replay(vaes: E.FrozenVAEs, steps: int, seed: int = 0) -> E.Replay:
    """Random-policy Simple Shapes transitions stored as the training loop stores them."""
    from envs.simple_shapes import SimpleShapesVectorEnv

    env, rng = SimpleShapesVectorEnv(1, max_episode_steps=50), np.random.default_rng(seed)
    replay = E.Replay(10_000, 1, 10, 7, seed)
    obs, _ = env.reset(seed=seed)
    first = 1.0
    for _ in range(steps):
        a = rng.integers(0, 7, 1)
        u_v, u_attr = (u.numpy() for u in vaes(obs))
        obs, r, term, trunc, info = env.step(a)
        replay.add([0], u_v, u_attr, np.eye(7)[a], r, term, [first], [0])
        first = 0.0
        if term[0] or trunc[0]:
            u_v, u_attr = (u.numpy() for u in vaes(info["final_obs"]))
            replay.add([0], u_v, u_attr, np.zeros((1, 7)), [0], [0], [0], [1])
            first = 1.0
    return replay


def test_joint_training_lowers_the_gw_losses_and_keeps_the_vaes_frozen(pretrained):
    vaes = E.load_vaes("simple_shapes", pretrained[0] / "ck" / "simple_shapes" / "vae.pt")
    vae_before = {k: v.clone() for k, v in vaes.state_dict().items()}
    replay = random_replay(vaes, 300)
    torch.manual_seed(0)
    args = E.Args(batch_size=4, batch_length=8, imag_horizon=5, gw_batch_size=128).resolve()
    agent = E.Agent("simple_shapes", "twohot")
    gw_before = {k: v.clone() for k, v in agent.gw.state_dict().items()}
    wm_before = {k: v.clone() for k, v in agent.wm.state_dict().items()}
    opts = E.make_optimizers(agent, args)
    logs = [
        {k: float(v) for k, v in E.train_update(agent, opts, replay, args, 2 * i).items()} for i in range(60)
    ]
    first = np.mean([log["loss_gw"] for log in logs[:5]])
    last = np.mean([log["loss_gw"] for log in logs[-5:]])
    assert last < 0.6 * first, (first, last)
    assert np.mean([log["loss_dcy"] for log in logs[-5:]]) < np.mean([log["loss_dcy"] for log in logs[:5]])
    assert math.isclose(logs[-1]["gw_lr"], E.gw_lr(119, args), rel_tol=1e-6)  # 120 GW updates, numbered
    assert all(not torch.equal(gw_before[k], v) for k, v in agent.gw.state_dict().items() if "weight" in k)
    assert any(not torch.equal(wm_before[k], v) for k, v in agent.wm.state_dict().items())
    assert all(torch.equal(vae_before[k], v) for k, v in vaes.state_dict().items())  # BatchNorm stats too
    assert not any(p.requires_grad for p in vaes.parameters())


def test_world_model_and_actor_critic_send_no_gradient_into_the_gw():
    torch.manual_seed(0)
    args = E.Args(batch_size=2, batch_length=4, imag_horizon=3, gw_updates=0).resolve()
    agent = E.Agent("simple_shapes", "twohot")
    gw_before = {k: v.clone() for k, v in agent.gw.state_dict().items()}
    opts = E.make_optimizers(agent, args)
    E.train_update(agent, opts, fill_replay_with_noise(40), args)
    assert all(torch.equal(gw_before[k], v) for k, v in agent.gw.state_dict().items())
    assert all(p.grad is None for p in agent.gw.parameters())


def test_gw_losses_are_the_pretraining_losses():
    """Same weights, same batch, same fusion weights: the e2e L_GW terms and their gradients equal
    pretrain_vae_gw.py's (whose terms are checked against hand-computed values)."""
    torch.manual_seed(0)
    gw_e2e, gw_pre = E.GlobalWorkspace(10, 10, 64), P.GlobalWorkspace(10, 10, 64)
    gw_pre.load_state_dict(gw_e2e.state_dict())
    u_v, u_attr, alpha = torch.randn(32, 10), torch.randn(32, 10), torch.rand(32, 1)
    ours = E.gw_losses(gw_e2e, u_v, u_attr, alpha, 0.07)
    theirs = P.gw_losses(gw_pre, {"v": u_v, "attr": u_attr}, alpha, 0.07)
    assert ours.keys() == theirs.keys()
    for k in ours:
        torch.testing.assert_close(ours[k], theirs[k])
    for i, k in enumerate(ours):  # each term on its own: weights 1, 2, ... tell a swapped term
        ours[k].mul(i + 1).backward(retain_graph=True)
        theirs[k].mul(i + 1).backward(retain_graph=True)
    for (name, p_ours), p_theirs in zip(gw_e2e.named_parameters(), gw_pre.parameters(), strict=True):
        torch.testing.assert_close(p_ours.grad, p_theirs.grad, msg=name)


def test_gw_learning_rate_follows_the_one_cycle_table():
    args = E.Args().resolve()
    assert (args.gw_lr_start, args.gw_lr_max, args.gw_lr_end, args.gw_cycle) == (3e-3, 1e-2, 1e-3, 25_000)
    assert math.isclose(E.gw_lr(0, args), 3e-3)
    assert math.isclose(E.gw_lr(7_500, args), 1e-2)
    assert math.isclose(E.gw_lr(25_000, args), 1e-3) and math.isclose(E.gw_lr(80_000, args), 1e-3)
    # torch's OneCycleLR with the same table values agrees over the cycle.
    opt = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=1e-2, total_steps=25_000, div_factor=1e-2 / 3e-3, final_div_factor=3e-3 / 1e-3
    )
    for step in range(25_000):
        if step % 2_500 == 0:
            assert math.isclose(E.gw_lr(step, args), sched.get_last_lr()[0], rel_tol=2e-3), step
        opt.step()
        sched.step()
    rd = E.Args(env="robodesk").resolve()
    assert (rd.gw_lr_start, rd.gw_lr_max, rd.gw_lr_end, rd.gw_cycle) == (1e-4, 3e-4, 1e-4, 50_000)
    assert (args.gw_batch_size, rd.gw_batch_size, args.gw_updates) == (64 * 32, 32 * 128, 2)


def test_missing_checkpoints_are_explained(pretrained, pretrained_robodesk, tmp_path):
    make = "pretrain_vae_gw.py --env simple_shapes --stages collect vae --cpu-preset"
    make += f" --checkpoint-dir {tmp_path}"
    with pytest.raises(E.UsageError, match=f"no vae checkpoint at .*none.pt; make it with `python {make}`"):
        E.main(E.Args(checkpoint_dir=str(tmp_path), vae_checkpoint=str(tmp_path / "none.pt")))
    rd_vae = pretrained_robodesk[0] / "ck" / "robodesk" / "vae.pt"
    with pytest.raises(ValueError, match="made for env 'robodesk'.*'simple_shapes'"):
        E.main(ss_args(pretrained, vae_checkpoint=str(rd_vae)))
    with pytest.raises(E.UsageError, match="python gw_dreamer_e2e.py --env simple_shapes"):
        E.main(ss_args(pretrained, eval_only=True, checkpoint=str(tmp_path / "none.pt")))
    with pytest.raises(ValueError, match="unknown RoboDesk task 'fly'"):
        E.main(E.Args(env="robodesk", task="fly", checkpoint_dir=str(pretrained_robodesk[0] / "ck")))


def test_ctrl_c_saves_the_run_where_it_stopped(pretrained):
    tmp = pretrained[0]
    agent = tmp / "ck" / "simple_shapes" / "agents" / "interrupted_e2e_gw_simple_shapes_s1.pt"
    flags = [*SS, str(tmp / "ck"), *TINY, "--exp-name", "interrupted_e2e"]
    state, step = interrupt_run("gw_dreamer_e2e.py", tmp, agent, *flags)
    assert state["updates"] == (step - 100) // 10


def test_eval_only_encodes_every_observation_with_the_drop_it_was_given(ss_run, pretrained, monkeypatch):
    """Every observation of an --eval-only run is fused into z with --drop's weights. Fails if the
    evaluation ignores --drop."""
    _, _, agent = ss_run
    seen = record_calls(monkeypatch, E.Agent, "z", lambda u_v, u_attr, drop="none": drop)
    for drop in ("vision", "attr", "none"):
        seen.clear()
        E.main(ss_args(pretrained, eval_only=True, checkpoint=str(agent), drop=drop, eval_episodes=2))
        assert len(seen) >= 100 and set(seen) == {drop}, drop  # 2 episodes of 100 steps
