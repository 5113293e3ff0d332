"""ppo_variants.py: CLI runs of every variant on both envs, learning on Simple Shapes, resume, modality
ablation, GAE, frame stacking, reward normalisation, errors."""

import numpy as np
import pytest
import torch
from conftest import logged_totals, record_calls, run_script

import ppo_variants as PPO

TINY = "--num-envs 2 --num-steps 64 --update-epochs 2 --minibatch-size 64 --eval-episodes 2".split()
VARIANTS = ("raw", "vae", "clip", "gw")


def agent_path(folder, env: str, variant: str, task: str = "") -> str:
    return str(folder / "ck" / env / "agents" / f"ppo_{variant}_{env}{task}_s1.pt")


@pytest.fixture(scope="module")
def ss_runs(pretrained):
    """256 steps of each variant on Simple Shapes through the CLI."""
    tmp = pretrained[0]
    ck = ["--checkpoint-dir", str(tmp / "ck")]
    logs = {
        v: run_script("ppo_variants.py", tmp, "--variant", v, *ck, *TINY, "--total-steps", "256")
        for v in VARIANTS
    }
    return tmp, logs


@pytest.mark.parametrize("variant", VARIANTS)
def test_simple_shapes_cli_run_of_each_variant(ss_runs, variant):
    tmp, logs = ss_runs
    assert f"{variant} PPO on simple_shapes" in logs[variant] and "done:" in logs[variant]
    ck = torch.load(agent_path(tmp, "simple_shapes", variant), weights_only=False)
    assert ck["kind"] == "ppo" and ck["variant"] == variant and ck["state"]["env_steps"] == 256
    # 2 rollouts x 2 epochs x 2 minibatches, each with the FLOPs of the first
    assert ck["state"]["flops"] == 8 * ck["state"]["flops_per_minibatch"] > 0
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tmp / "runs" / f"ppo_{variant}_simple_shapes_s1")).Reload()
    tags = acc.Tags()["scalars"]
    wanted = "charts/episodic_return charts/normalised_return charts/SPS charts/train_flops losses/value_loss"
    for tag in (*wanted.split(), "losses/policy_loss"):
        assert tag in tags, tags


@pytest.mark.parametrize("variant", VARIANTS)
def test_robodesk_cli_run_of_each_variant(pretrained_robodesk, variant):
    tmp = pretrained_robodesk[0]
    env = ["--env", "robodesk", "--variant", variant, "--checkpoint-dir", str(tmp / "ck")]
    more = "--num-steps 32 --total-steps 256 --eval-episodes 1".split()
    fast = "--render-quality fast --episode-length 80".split()
    if variant == "raw":  # one variant steps its envs in their own processes, its evaluation's too
        fast.append("--env-processes")
    log = run_script("ppo_variants.py", tmp, *env, *fast, *TINY, *more)
    assert f"{variant} PPO on robodesk_push_green" in log and "final_success_count" in log
    assert "scripted push_green expert" in log and "final_normalised_return" in log
    ck = torch.load(agent_path(tmp, "robodesk", variant, "_push_green"), weights_only=False)
    # one rollout of 2 x 32 actions, counted in frames (4 per action, the paper's unit)
    assert ck["state"]["env_steps"] == 256 and "actor_logstd" in ck["agent"]  # Gaussian actions


def test_a_short_run_beats_the_random_policy(tmp_path, monkeypatch):
    """10,240 steps of multimodal PPO on Simple Shapes: the greedy policy's normalised return (0 = random,
    1 = scripted greedy) is well above 0 (measured 0.51 and 0.50 on seeds 1 and 2)."""
    monkeypatch.chdir(tmp_path)  # TensorBoard writes runs/ in the working directory
    short = dict(num_steps=512, total_steps=10_240, update_epochs=4, minibatch_size=256, eval_episodes=20)
    out = PPO.main(PPO.Args(variant="raw", checkpoint_dir=str(tmp_path / "ck"), **short))
    assert out["final_normalised_return"] > 0.25, out


def test_stop_at_criterion_ends_the_run_after_that_rollout(pretrained, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # its runs/ folder
    small = dict(num_envs=2, num_steps=64, update_epochs=1, minibatch_size=64, eval_episodes=1, seed=7)
    # every policy meets a criterion of -100 (normalised): it is reached at the first episode's end
    small |= dict(variant="vae", checkpoint_dir=str(pretrained[0] / "ck"), criterion=-100.0, smoothing=1)
    out = PPO.main(PPO.Args(total_steps=128 * 40, stop_at_criterion=True, **small))
    assert out["criterion_step"] is not None and out["env_steps"] < 128 * 40
    assert out["env_steps"] - 128 < out["criterion_step"] <= out["env_steps"]  # the rollout it was met in
    out = PPO.main(PPO.Args(total_steps=128 * 4, overwrite=True, **small))
    assert out["env_steps"] == 128 * 4  # without the flag the run goes on


def test_resume_continues_the_saved_run(ss_runs):
    tmp, _ = ss_runs
    more = ["--checkpoint-dir", str(tmp / "ck"), *TINY, "--total-steps", "512", "--resume"]
    log = run_script("ppo_variants.py", tmp, "--variant", "gw", *more)
    assert "resuming" in log and "at env step 256" in log
    ck = torch.load(agent_path(tmp, "simple_shapes", "gw"), weights_only=False)
    assert ck["state"]["env_steps"] == 512 and ck["state"]["iteration"] == 4
    assert logged_totals(tmp, "ppo_gw_") == [(0, 256), (256, 512)]


def test_a_rollout_saved_before_its_update_resumes_to_the_same_weights(tmp_path, monkeypatch, capsys):
    """Ctrl-C while acting saves the rollout before its update, and --resume runs that update first: the
    weights are those of a run never stopped. A --save-minutes shorter than an update saves every rollout
    before its update as well, and changes nothing. Fails if the saved rollout, the random state saved
    with it or the update on resume differ from the run that was not stopped."""
    monkeypatch.chdir(tmp_path)  # runs/
    small = dict(variant="raw", num_envs=2, num_steps=64, update_epochs=2, minibatch_size=64, eval_episodes=1)

    def run(name: str, steps: int, **more) -> dict:
        path = tmp_path / f"{name}.pt"
        PPO.main(PPO.Args(total_steps=steps, checkpoint=str(path), exp_name=name, **small, **more))
        return torch.load(path, weights_only=False)

    class PressedAtOnce(PPO.StopRequest):  # as if Ctrl-C came during the first rollout
        def __init__(self, tag):
            super().__init__(tag)
            self.requested = True

    whole = run("whole", 128)
    with monkeypatch.context() as m, pytest.raises(SystemExit) as stopped:
        m.setattr(PPO, "StopRequest", PressedAtOnce)
        run("stopped", 128)
    assert stopped.value.code == 130
    saved = torch.load(tmp_path / "stopped.pt", weights_only=False)
    assert saved["state"]["env_steps"] == 128 and saved["pending"]["returns"].shape == (128,)
    assert saved["state"]["flops"] == 0  # no update yet
    capsys.readouterr()
    resumed = run("stopped", 128, resume=True)
    log = capsys.readouterr().out
    assert "the saved rollout's update |" in log and " steps/s |" not in log  # no rate: no new steps
    assert resumed["pending"] is None and resumed["state"]["flops"] == whole["state"]["flops"] > 0
    assert all(torch.equal(resumed["agent"][k], v) for k, v in whole["agent"].items())

    saves, real = [], PPO.atomic_save

    def spy(obj: dict, path):
        saves.append(obj["pending"] is not None)
        real(obj, path)

    with monkeypatch.context() as m:
        m.setattr(PPO, "atomic_save", spy)
        often = run("often", 256, save_minutes=1e-9)
    assert saves == [True, False, True, False, False]  # before and after each update, then the final one
    rare = run("rare", 256)
    assert all(torch.equal(often["agent"][k], v) for k, v in rare["agent"].items())


def test_eval_only_with_each_drop(ss_runs, pretrained):
    tmp, _ = ss_runs
    more = ["--checkpoint-dir", str(tmp / "ck"), *"--eval-only --drop vision --eval-episodes 3".split()]
    log = run_script("ppo_variants.py", tmp, "--variant", "clip", *more)
    assert "drop=vision: return" in log and "3 episodes" in log
    # each drop once, on the two other variants (what each drop feeds the policy: the test below)
    for variant, drop in (("raw", "none"), ("raw", "attr"), ("vae", "vision")):
        args = PPO.Args(variant=variant, checkpoint_dir=str(tmp / "ck"), eval_only=True, drop=drop)
        args.eval_episodes = 2
        out = PPO.main(args)
        assert out["drop"] == drop
        # The same episodes run by hand on the agent loaded from the file give the same return (fails if
        # the evaluation does not load the saved weights or runs other episodes).
        observer, _ = PPO.load_observer(args)
        agent = PPO.Agent(observer, args, 7, True)
        path = tmp / "ck" / "simple_shapes" / "agents" / f"{PPO.run_name(args)}.pt"
        agent.load_state_dict(torch.load(path, weights_only=False)["agent"])
        rets, _ = PPO.run_episodes(agent, observer, args, 2, drop, args.seed + 10**6)
        assert out["return_mean"] == pytest.approx(float(rets.mean()), abs=1e-9)


def test_a_removed_modality_no_longer_reaches_the_policy(pretrained):
    from envs.simple_shapes import sample_dataset

    a, b = sample_dataset(4, seed=0), sample_dataset(4, seed=1)
    other_image = {"image": b["image"], "attr": a["attr"]}
    other_attr = {"image": a["image"], "attr": b["attr"]}
    for variant in VARIANTS:
        obs, _ = PPO.load_observer(PPO.Args(variant=variant, checkpoint_dir=str(pretrained[0] / "ck")))
        for drop, changed in (("vision", other_image), ("attr", other_attr)):
            x, y = obs(a, drop, "cpu"), obs(changed, drop, "cpu")
            assert all(torch.equal(x[k], y[k]) for k in x), (variant, drop)
        x, y = obs(a, "none", "cpu"), obs(other_image, "none", "cpu")
        assert not all(torch.equal(x[k], y[k]) for k in x), variant


# --------------------------------------------------------------------------------------------------
# Pieces
# --------------------------------------------------------------------------------------------------
def test_gae_matches_hand_computed_values():
    args = PPO.Args(gamma=0.5, gae_lambda=0.5)
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    terminated = torch.tensor([[0.0], [1.0], [0.0]])
    next_value = torch.tensor([2.0])
    adv = PPO.gae(rewards, values, next_value, terminated, args)
    d2 = 3 + 0.5 * 2.0 - 1.5  # 2.5
    d1 = 2 + 0 - 1.0  # the episode ends after step 1: no bootstrap, and step 2's advantage is not added
    d0 = 1 + 0.5 * 1.0 - 0.5  # 1.0
    expected = [d0 + 0.25 * d1, d1, d2]
    torch.testing.assert_close(adv[:, 0], torch.tensor(expected))


def test_frame_stack_keeps_the_last_frames_and_refills_new_episodes():
    stack = PPO.FrameStack(3)
    x = stack.reset({"x": torch.tensor([[1.0], [10.0]])})
    assert x["x"].tolist() == [[1, 1, 1], [10, 10, 10]]
    x = stack.push({"x": torch.tensor([[2.0], [11.0]])})
    x = stack.push({"x": torch.tensor([[3.0], [12.0]])})
    assert x["x"].tolist() == [[1, 2, 3], [10, 11, 12]]
    x = stack.push({"x": torch.tensor([[4.0], [20.0]])})
    x = stack.reset({"x": torch.tensor([[4.0], [20.0]])}, np.array([1]))  # env 1 started an episode
    assert x["x"].tolist() == [[2, 3, 4], [20, 20, 20]]


def test_reward_normaliser_scales_by_the_return_std():
    norm = PPO.RewardNormalizer(num_envs=4, gamma=0.9, enabled=True)
    rng = np.random.default_rng(0)
    for t in range(3_000):
        out = norm(rng.normal(-20, 5, 4), np.full(4, t % 100 == 99))
    # discounted returns of ~-20 per step reach about -200: rewards come out around -20 / 200-ish std
    assert np.all(np.abs(out) < 10) and 0.05 < np.abs(out).mean() < 5
    assert np.array_equal(
        PPO.RewardNormalizer(1, 0.9, enabled=False)(np.array([-7.0]), np.array([False])), [-7]
    )


def test_errors_are_explained(pretrained, pretrained_robodesk, tmp_path):
    make = "pretrain_vae_gw.py --env simple_shapes --stages collect vae --cpu-preset"
    make += f" --checkpoint-dir {tmp_path}"
    with pytest.raises(PPO.UsageError, match=f"no vae checkpoint at .*none.pt; make it with `python {make}`"):
        PPO.main(
            PPO.Args(variant="vae", checkpoint_dir=str(tmp_path), vae_checkpoint=str(tmp_path / "none.pt"))
        )
    ck = pretrained[0] / "ck"
    with pytest.raises(ValueError, match="is a 'clip' model but --variant is 'gw'"):
        PPO.main(
            PPO.Args(
                variant="gw", checkpoint_dir=str(ck), gw_checkpoint=str(ck / "simple_shapes" / "clip.pt")
            )
        )
    rd_vae = str(pretrained_robodesk[0] / "ck" / "robodesk" / "vae.pt")
    with pytest.raises(ValueError, match="made for env 'robodesk'"):
        PPO.main(PPO.Args(variant="vae", checkpoint_dir=str(ck), vae_checkpoint=rd_vae))
    with pytest.raises(PPO.UsageError, match="python ppo_variants.py --env simple_shapes --variant raw"):
        PPO.main(PPO.Args(variant="raw", checkpoint_dir=str(tmp_path), eval_only=True))
    with pytest.raises(ValueError, match="unknown RoboDesk task 'fly'"):
        PPO.main(PPO.Args(env="robodesk", task="fly", variant="raw"))
    with pytest.raises(PPO.UsageError, match="must fit in one rollout"):
        PPO.main(PPO.Args(variant="raw", num_steps=8, minibatch_size=512))


def test_ppo_loss_clips_the_surrogate_and_the_value_by_hand():
    """Four samples with ratios 1.5, 0.5, 1.1, 0.9 and advantages +1, -1, -1, +1 (not normalised): the
    surrogate takes min(r A, clip(r) A) per sample (1.2, -0.8, -1.1, 0.9), the value loss
    0.5 max((v - R)^2, (v_clip - R)^2) with v_clip = v_old + clip(v - v_old, +-0.2). Fails if the clip
    range, the min / max or the value clipping is changed."""
    from types import SimpleNamespace

    ratio = torch.tensor([1.5, 0.5, 1.1, 0.9])
    newvalue = torch.tensor([1.0, 0.0, 2.0, -1.0])
    entropy = torch.tensor([0.3, 0.3, 0.3, 0.3])
    agent = SimpleNamespace(get_action_and_value=lambda obs, a: (None, ratio.log(), entropy, newvalue))
    mb = {
        "obs": None,
        "actions": None,
        "logprobs": torch.zeros(4),
        "advantages": torch.tensor([1.0, -1.0, -1.0, 1.0]),
        "values": torch.tensor([0.5, 0.5, 2.1, -1.0]),
        "returns": torch.tensor([1.2, 1.0, 0.0, -1.0]),
    }
    args = SimpleNamespace(clip_coef=0.2, norm_adv=False, clip_vloss=True, ent_coef=0.01, vf_coef=0.5)
    loss, terms = PPO.ppo_loss(agent, mb, args)
    pg = -(1.2 - 0.8 - 1.1 + 0.9) / 4
    # values: v_clip = 0.7, 0.3, 2.0, -1.0; squared errors max((v-R)^2, (vc-R)^2) = 0.25, 1.0, 4.0, 0.0
    v = 0.5 * (0.25 + 1.0 + 4.0 + 0.0) / 4
    assert terms["policy_loss"].item() == pytest.approx(pg)
    assert terms["value_loss"].item() == pytest.approx(v)
    assert loss.item() == pytest.approx(pg - 0.01 * 0.3 + 0.5 * v)
    assert terms["clipfrac"].item() == pytest.approx(0.5)


def test_eval_only_feeds_every_observation_through_the_drop_it_was_given(ss_runs, monkeypatch):
    """Every observation of an --eval-only run reaches the policy through --drop (zeroed input, or the
    GW's fusion weights). Fails if the evaluation ignores --drop."""
    tmp, _ = ss_runs
    seen = record_calls(monkeypatch, PPO.Observer, "forward", lambda obs, drop, dev: drop)
    for drop in ("vision", "attr", "none"):
        seen.clear()
        args = PPO.Args(variant="gw", checkpoint_dir=str(tmp / "ck"), eval_only=True, drop=drop)
        args.eval_episodes = 2
        PPO.main(args)
        assert len(seen) >= 100 and set(seen) == {drop}, drop  # 2 episodes of 100 steps


def test_the_frozen_variants_see_the_images_of_their_vae(pretrained_robodesk):
    """On RoboDesk, vae / clip / gw render the images their VAE was trained on (fast here) and refuse the
    other kind; raw renders faithful ones unless told otherwise."""
    ck = str(pretrained_robodesk[0] / "ck")
    for variant in ("vae", "gw"):
        args = PPO.Args(env="robodesk", variant=variant, checkpoint_dir=ck).resolve()
        assert args.render_quality is None
        PPO.load_observer(args)
        assert args.render_quality == "fast"
        with pytest.raises(PPO.UsageError, match="trained on fast images"):
            PPO.load_observer(
                PPO.Args(env="robodesk", variant=variant, checkpoint_dir=ck, render_quality="faithful")
            )
    assert PPO.Args(env="robodesk", variant="raw").resolve().render_quality == "faithful"
    assert "render_quality" in PPO.EVAL_KEYS
