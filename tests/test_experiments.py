"""benchmarks/experiments/gw_dreamer_experiments.py: each experiment changes the one thing it names, its
runs stay apart from the paper's, and gw_dreamer.py refuses (with the command to use) an agent trained
with one."""

import sys

import numpy as np
import pytest
import torch
import tyro
from conftest import ROOT, robodesk_batch, run_script, tiny_agent_args

import gw_dreamer as G

sys.path.insert(0, str(ROOT / "benchmarks" / "experiments"))
import gw_dreamer_experiments as X  # noqa: E402

AGENTS = ("ck", "simple_shapes", "agents")


def x_args(pretrained, **kw) -> X.Args:
    return tiny_agent_args(X, pretrained, **kw)


def test_actor_critic_input_hz_reads_z_in_dreams_and_when_acting(pretrained, monkeypatch):
    torch.manual_seed(0)
    agent = X.experiment_agent(X.Args(ac_input="hz"))("simple_shapes", 10, "twohot")
    h0, z0 = torch.randn(6, 64), torch.rand(6, 10) * 2 - 1
    feats = G.imagine(agent, h0, z0, 3).feats
    assert feats.shape == (4, 6, 74) and torch.equal(feats[0], torch.cat([h0, z0], -1))
    # later steps: the dreamt h_k beside the world model's own z_k = z_head(h_k)
    torch.testing.assert_close(feats[1, :, 64:], agent.wm.z_head(feats[1, :, :64]))
    # when acting the actor reads the real z_t: the run records each input it was given
    seen, act = [], G.Actor.act
    monkeypatch.setattr(
        G.Actor, "act", lambda self, x, mode=False: seen.append(x.shape[-1]) or act(self, x, mode)
    )
    monkeypatch.chdir(pretrained[0])  # its TensorBoard folder goes under the test's runs/
    X.main(x_args(pretrained, ac_input="hz", total_steps=120, eval_every=10**6, video_every=0))
    assert seen and set(seen) == {74}
    path = pretrained[0].joinpath(*AGENTS, "gw_dreamer_gw_hz_simple_shapes_s1.pt")
    # the patches are undone after the run: gw_dreamer.py builds the paper's agent and run names again
    assert G.Agent.__qualname__ == "Agent" and G.run_name(G.Args(), "gw") == "gw_dreamer_gw_simple_shapes_s1"
    with pytest.raises(
        G.UsageError, match="trained with --ac-input hz, an experiment: use .*gw_dreamer_experiments"
    ):
        G.main(tiny_agent_args(G, pretrained, eval_only=True, checkpoint=str(path)))
    out = X.main(x_args(pretrained, ac_input="hz", eval_only=True, checkpoint=str(path), eval_episodes=2))
    assert out["drop"] == "none"


def test_heads_read_sg_z_keeps_the_reward_loss_out_of_the_z_head():
    torch.manual_seed(0)
    plain = G.Agent("simple_shapes", 10, "twohot")
    sgz = X.experiment_agent(X.Args(heads_read_sg_z=True))("simple_shapes", 10, "twohot")
    sgz.load_state_dict(plain.state_dict())
    h = torch.randn(5, 64)
    for agent, reaches in ((plain, True), (sgz, False)):
        z_next, r_out, _ = agent.wm.heads(h)
        r_out.sum().backward()
        assert (agent.wm.z_head[0].weight.grad is not None) == reaches
        assert agent.wm.reward_head[0].weight.grad is not None
    torch.testing.assert_close(sgz.wm.heads(h)[1], plain.wm.heads(h)[1])  # same forward values


def test_no_value_slope_keeps_the_values_derivative_out_of_the_dream():
    """--no-value-slope: the values give the dreamt states no gradient (the actor's dynamics gradient is the
    rewards' alone), while the critic's own weights still get theirs. Fails if the critic reads the states
    with their gradient."""
    torch.manual_seed(0)
    for slope in (True, False):
        agent = X.experiment_agent(X.Args(value_slope=slope))("robodesk", 76, "twohot", cpu_preset=True)
        h = torch.randn(4, 256, requires_grad=True)
        agent.twohot.mean(agent.critic(h)).sum().backward()
        assert (h.grad is not None and h.grad.abs().sum() > 0) == slope
        assert agent.critic.net[0].weight.grad.abs().sum() > 0


def test_zero_init_starts_reward_and_value_at_zero():
    agent = X.experiment_agent(X.Args(zero_init=True))("simple_shapes", 10, "twohot")
    h = torch.randn(4, 64)
    zero = torch.zeros(4)  # uniform logits over the symmetric bins: the mean is 0 up to rounding
    torch.testing.assert_close(agent.twohot.mean(agent.critic(h)), zero, atol=1e-5, rtol=0)
    torch.testing.assert_close(agent.twohot.mean(agent.slow_critic(h)), zero, atol=1e-5, rtol=0)
    value = agent.reward_dec.value(agent.wm.reward_head(torch.cat([h, torch.rand(4, 10)], -1)))
    torch.testing.assert_close(value, zero, atol=1e-5, rtol=0)
    plain = G.Agent("simple_shapes", 10, "twohot")
    assert plain.twohot.mean(plain.critic(h)).abs().max() > 1e-3  # which the paper's initialisation is not


def test_attribute_control_feeds_the_true_attributes(pretrained, pretrained_robodesk, tmp_path):
    ck = pretrained[0] / "ck" / "simple_shapes"
    enc = G.load_encoder("simple_shapes", ck / "vae.pt", ck / "gw.pt")
    enc.__class__ = X.AttributeEncoder
    from envs.simple_shapes import sample_dataset

    obs = sample_dataset(3, seed=0)
    torch.testing.assert_close(enc(obs), torch.as_tensor(obs["attr"][:, :10]).clamp(-1, 1))
    rd = str(pretrained_robodesk[0] / "ck")
    with pytest.raises(G.UsageError, match="Simple Shapes control"):
        X.main(X.Args(env="robodesk", checkpoint_dir=rd, z_source="attributes"))
    # through the CLI: the run is named apart from the paper's and logs its flag
    script = "benchmarks/experiments/gw_dreamer_experiments.py"
    flags = "--z-source attributes --learning-starts 20 --batch-size 2 --batch-length 4 --total-steps 40"
    flags += " --eval-episodes 1 --video-every 0 --eval-every 1000 --train-ratio 10 --imag-horizon 3"
    log = run_script(script, tmp_path, "--checkpoint-dir", str(pretrained[0] / "ck"), *flags.split())
    assert "done:" in log and (tmp_path / "runs" / "gw_dreamer_gw_attrz_simple_shapes_s1").is_dir()


def test_recent_fraction_draws_that_share_of_sequences_from_the_newest_steps():
    """--recent-fraction 0.5 --recent-window 30: half of each batch ends among the 30 newest stored steps of
    its stream (the stored z counts the steps), the other half is the paper's uniform replay; at 0 the
    batches are exactly the paper's."""
    replay, plain = (cls(400, 2, 1, 5, seed=3) for cls in (X.RecentReplay, G.Replay))
    for r in (replay, plain):
        for t in range(300):  # stream 0 holds 0..299, stream 1 holds 1000..1299
            r.add(
                [0, 1],
                np.array([[t], [1000 + t]], np.float32),
                np.zeros((2, 5)),
                [0, 0],
                [0, 0],
                [0, 0],
                [0, 0],
            )
    X.RecentReplay.fraction, X.RecentReplay.window = 0.0, 30
    for key, v in replay.sample(8, 6).items():
        np.testing.assert_array_equal(v, plain.sample(8, 6)[key])
    X.RecentReplay.fraction = 0.5
    z = replay.sample(64, 6)["z"][..., 0] % 1000
    assert (z[:32] >= 270).all() and (np.diff(z, axis=1) == 1).all()
    assert (z[32:, 0] < 270).mean() > 0.5  # the rest spread over the whole stream
    X.RecentReplay.fraction, X.RecentReplay.window = 0.0, 5000


def test_residual_world_model_predicts_a_change_of_z_and_acts_on_the_gru_state():
    """--wm-residual: with the z head's last layer at zero the world model predicts z_{t+1} = z_t, whatever
    h; its loss and dreams run through gw_dreamer.py's own functions, and the actor reads the GRU's part of
    the state only."""
    torch.manual_seed(0)
    agent = X.experiment_agent(X.Args(env="robodesk", cpu_preset=True, wm_residual=True))(
        "robodesk", 76, "twohot", cpu_preset=True
    )
    hidden = agent.wm.gru.hidden_size
    assert agent.wm.hidden == hidden + 76
    batch = robodesk_batch()
    torch.nn.init.zeros_(agent.wm.z_head[-2].weight)
    torch.nn.init.zeros_(agent.wm.z_head[-2].bias)
    state = agent.wm.step(torch.randn(3, agent.wm.hidden), batch["z"][:, 0], batch["a"][:, 0])
    torch.testing.assert_close(agent.wm.heads(state)[0], batch["z"][:, 0].clamp(-0.999, 0.999))
    args = X.Args(env="robodesk", cpu_preset=True)
    loss, terms, h_entry, _ = G.world_model_loss(agent.wm, agent.reward_dec, batch, args)
    valid = 1 - batch["last"][:, :-1]
    expected = (((batch["z"][:, :-1].clamp(-0.999, 0.999) - batch["z"][:, 1:]) ** 2).sum(-1) * valid).sum()
    torch.testing.assert_close(terms["loss_z"], expected / valid.sum())
    assert h_entry.shape == (3, 13, hidden + 76)
    dream = G.imagine(agent, h_entry[:, -1], batch["z"][:, -1], 4)
    assert dream.feats.shape == (5, 3, hidden)  # the actor and critic read h, not z_t
    torch.testing.assert_close(dream.feats[0], h_entry[:, -1, :hidden])


def test_explore_noise_decay_falls_to_zero_at_its_frame():
    """--explore-noise 0.3 --explore-noise-decay 1000: the collected actions' extra noise is 0.3 at frame 0,
    0.15 at frame 500 and none from frame 1,000; the run uses it in place of gw_dreamer.explore."""
    torch.manual_seed(0)
    args = X.Args(env="robodesk", cpu_preset=True, explore_noise=0.3, explore_noise_decay=1000).resolve()
    a = torch.zeros(20_000, 5)
    for frame, extra in [(0, 0.3), (500, 0.15), (1000, 0.0), (5000, 0.0)]:
        got = X.decaying_explore(a, args, frame).std(0)
        torch.testing.assert_close(got, torch.full((5,), extra), rtol=0.03, atol=1e-6)
    assert X.suffix(args) == "_ol10_nodone_noise0.3d1000"
    with pytest.raises(G.UsageError, match="needs --explore-noise"):
        X.main(X.Args(env="robodesk", explore_noise_decay=1000))


def test_refusal_names_experiment_flags_as_the_cli_takes_them():
    """A checkpoint trained with experiments is refused by gw_dreamer.py with the flags that run it: a
    switch as ``--flag`` / ``--no-flag`` (tyro takes no value after it), and --wm-residual among the
    settings that change the agent's forward pass."""
    saved = {"wm_residual": True, "value_slope": False, "ac_input": "hz", "seed": 1}
    now = {"wm_residual": False, "value_slope": True, "ac_input": "h", "seed": 1}
    words = G.setting_changes(saved, now, ["wm_residual", "value_slope", "ac_input", "seed"])
    assert words == ["--wm-residual", "--no-value-slope", "--ac-input hz"]
    parsed = tyro.cli(X.Args, args=" ".join(words).split())
    assert (parsed.wm_residual, parsed.value_slope, parsed.ac_input) == (True, False, "hz")
    assert G.SCRIPT["experiments"]["wm_residual"] is False


def test_the_robodesk_cpu_preset_is_the_experiments_command_that_reached_the_criterion():
    """gw_dreamer.py --env robodesk --cpu-preset runs the setting recorded as the candidate in
    docs/results/robodesk_runs.csv (the experiments script's --cpu-preset with --no-done-head
    --wm-open-loop-stride 32 --batch-size 28): the same settings and run name, and the first three updates
    from the same weights and replay give the losses and weights that the experiments script, with its
    own world model without a done head, gave at commit d54724b."""
    preset = G.Args(env="robodesk", cpu_preset=True).resolve()
    recorded = dict(
        total_steps=200_000,
        batch_size=28,
        batch_length=64,
        critic_replay_coef=0.3,
        wm_open_loop=10,
        wm_open_loop_stride=32,
        explore_noise=0.3,
        done_head="off",
    )
    assert {k: getattr(preset, k) for k in recorded} == recorded
    # the experiments script names the preset's runs as the candidate's, so --resume finds them
    assert X.suffix(X.Args(env="robodesk", cpu_preset=True).resolve()) == "_ol10_nodone_noise0.3"
    torch.manual_seed(0)
    with_done_head = G.Agent("robodesk", 76, "twohot", cpu_preset=True)
    agent = G.Agent("robodesk", 76, "twohot", cpu_preset=True, done_head=False)
    agent.load_state_dict({k: v for k, v in with_done_head.state_dict().items() if "done_head" not in k})
    replay, rng = G.Replay(400, 1, 76, 5, seed=0), np.random.default_rng(0)
    for t in range(200):
        z, a = rng.uniform(-1, 1, (1, 76)), rng.uniform(-1, 1, (1, 5))
        replay.add(np.arange(1), z, a, rng.uniform(0, 3, 1), np.zeros(1), np.zeros(1) + (t == 0), np.zeros(1))
    replay.rng, opts = np.random.default_rng(1), G.make_optimizers(agent, preset)
    torch.manual_seed(5)
    keys = ("loss_wm", "loss_z_open", "loss_r_open", "loss_actor", "loss_critic", "loss_critic_replay")
    got = [
        [float(logs[k]) for k in keys]
        for logs in (G.train_update(agent, opts, replay, preset) for _ in range(3))
    ]
    at_d54724b = [
        [520.862671, 25.517746, 5.538613, -0.054303, 14.442257, 11.106598],
        [518.286499, 25.396383, 5.532137, -0.062974, 14.411154, 11.085616],
        [514.317261, 25.093977, 5.525144, -0.068864, 14.381881, 11.066423],
    ]
    np.testing.assert_allclose(got, at_d54724b, rtol=1e-5, atol=2e-6)
    weight_sum = sum(float(p.detach().abs().sum()) for p in agent.parameters())
    assert weight_sum == pytest.approx(45290.234887, rel=1e-6)
