"""benchmarks/robodesk_diagnose.py: how much of the stored actions the state predicts (part 1), the distance
from the agent's arm poses to a dataset's (part 5), the reward read across agents (part 6) and the GRU
state read over the last steps only (part 7), the critic against the real returns (part 8), and how
near an agent gets to the slide or drawer and how far it moves it (part 9)."""

import sys

import numpy as np
import pytest
import torch
from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
import robodesk_diagnose as D  # noqa: E402


def test_joint_coverage_measures_from_the_agent_and_from_whole_held_out_episodes(tmp_path):
    rng = np.random.default_rng(0)
    # a slow random walk in episodes of 50 steps from two sources in turn; the first two are held out
    walk = np.cumsum(rng.normal(0, 0.05, size=(600, 76)), axis=0).astype(np.float32)
    source = np.repeat(["expert", "wander"] * 6, 50)
    (tmp_path / "robodesk").mkdir()
    np.savez(tmp_path / "robodesk" / "shard_00000.npz", attr=walk, source=source)
    # the agent on poses of the pool's expert episodes: distance 0 to them, > 0 to the other source
    on = D.joint_coverage(walk[200:250], str(tmp_path), held_out=100)
    assert on["expert"][0] == 0 and on["wander"][0] > 0
    # held-out episodes are measured from outside the pool: a sample's own episode neighbours are not in it
    assert on["expert"][1] > 0.05 and on["wander"][1] > 0.05
    # 10 std along each of the 9 joints: about 10 * sqrt(9) = 30 std units from any sample
    far = D.joint_coverage(walk[200:250] + 10 * walk.std(0), str(tmp_path), held_out=100)
    assert 25 < far["expert"][0] < 35 and far["expert"][1] < 10


def test_reward_transfer_leaves_each_agent_out_and_tells_a_reader_that_carries_from_one_that_does_not(
    monkeypatch,
):
    """Three agents in overlapping regions, reward a smooth function of the state: the true attributes
    carry it to the agent left out; a reader of noise fits the training agents and misses the left-out
    one's reward by about its spread."""
    rng = np.random.default_rng(0)

    def episodes(path, n, seed):
        attr = rng.normal(0.3 * int(path), 1.0, size=(501, 76)).astype(np.float32)  # agent k about 0.3 k
        r = np.tanh(0.5 * (attr[1:, 18] + attr[1:, 19]))  # the reward of step t reads the state it leads to
        z = {"fused": torch.randn(501, 76), "attributes": torch.as_tensor(attr)}
        return {"z": z, "attr": attr, "next": list(range(1, 501)), "r": list(r)}

    monkeypatch.setattr(D, "agent_episodes", episodes)
    out = D.reward_transfer(("0", "1", "2"), 1, steps=200)
    assert set(out) == {"fused", "attributes", "true attributes"}
    assert out["true attributes"][1] < 0.2 and out["attributes"][1] < 0.2
    assert out["fused"][0] < 0.2 < 0.4 < out["fused"][1]


def test_held_out_by_source_reads_the_end_effector_of_each_sources_held_out_samples(tmp_path):
    """A stand-in GW whose z is the attributes scaled by alpha_attr, decoded as they are: the attributes
    alone give the end effector back exactly, vision (z = 0) misses it by its norm, fusion by half."""
    rng = np.random.default_rng(0)
    attr = rng.normal(size=(300, 76)).astype(np.float32)
    source = np.repeat(["expert", "wander", "random"], 100)
    (tmp_path / "robodesk").mkdir()
    image = np.zeros((300, 64, 64, 3), np.uint8)
    np.savez(tmp_path / "robodesk" / "shard_00000.npz", image=image, attr=attr, source=source)

    class Stand:
        attr_mean, attr_std = torch.zeros(76), torch.ones(76)
        vae_attr = type("V", (), {"decoder": staticmethod(lambda u: u)})
        gw = type("W", (), {"d": {"attr": lambda z: z}})

        def __call__(self, batch, alpha_v, alpha_attr):
            return alpha_attr * torch.as_tensor(batch["attr"])

    out = D.held_out_by_source({"gw": Stand()}, str(tmp_path), held_out=200)
    assert {src for _, src, _ in out} == {"expert", "wander"}  # the third source lies beyond the front
    norm = 100 * np.linalg.norm(attr[:100, 18:21], axis=1).mean()
    assert out["gw", "expert", "attributes"] == 0 and out["gw", "wander", "attributes"] == 0
    np.testing.assert_allclose(out["gw", "expert", "vision"], norm, rtol=1e-5)
    np.testing.assert_allclose(out["gw", "expert", "fused"], norm / 2, rtol=1e-5)


def test_pose_shares_count_the_steps_in_each_pose_per_source_and_for_the_agent(tmp_path):
    attr = np.zeros((40, 76), np.float32)
    attr[:, 5] = 2.0  # joint 6 straight
    attr[:10, 6] = -2.5  # expert rows 0-9: the wrist at its low end
    attr[20:25, 5] = 0.5  # wanderer rows 20-24: joint 6 bent
    source = np.repeat(["expert", "wander"], 20)
    (tmp_path / "robodesk").mkdir()
    np.savez(tmp_path / "robodesk" / "shard_00000.npz", attr=attr, source=source)
    agent = np.zeros((4, 76), np.float32)
    agent[:, 5], agent[:3, 6] = 2.0, 2.0
    out = D.pose_shares(agent, str(tmp_path))
    assert out["expert"] == {"wrist < -2.4 rad": 0.5, "wrist > 1.5 rad": 0.0, "joint 6 < 1 rad": 0.0}
    assert out["wander"]["joint 6 < 1 rad"] == 0.25 and out["agent"]["wrist > 1.5 rad"] == 0.75


def test_action_predictability_separates_actions_the_state_gives_from_noise():
    """Part 1: actions that are a function of z_t give R^2 near 1 and almost no residual; the same plus
    N(0, 0.3^2) leaves a residual std of 0.3; each 50,000 frames (12,500 stored steps) are one row."""
    rng = np.random.default_rng(0)
    n = 25_000
    z = rng.uniform(-1, 1, size=(1, n, 76)).astype(np.float32)
    policy = np.tanh(z[..., :5] - 0.5 * z[..., 5:10])
    replay = {
        "z": z,
        "first": np.zeros((1, n), np.float32),
        "last": np.zeros((1, n), np.float32),
        "count": np.array([n]),
    }
    for noise, r2, resid in ((0.0, (0.97, 1.0), (0.0, 0.08)), (0.3, (0.6, 0.8), (0.28, 0.34))):
        replay["a"] = (policy + noise * rng.normal(size=policy.shape)).astype(np.float32)
        rows = D.action_predictability(replay)
        assert [frame for frame, *_ in rows] == [0, 50_000]
        for _, got_r2, got_resid in rows:
            assert np.all((r2[0] < got_r2) & (got_r2 <= r2[1])), got_r2
            assert np.all((resid[0] <= got_resid) & (got_resid < resid[1])), got_resid


def test_windowed_state_reads_only_the_last_steps_from_zero_as_a_replayed_h():
    """Part 7: over a window as long as the history, h is the state carried while acting; over a shorter
    one, the state of h = 0 stepped through the window's steps alone, which differs from the carried one."""
    torch.manual_seed(0)
    wm = D.G.WorldModel(D.G.CPU_SIZES["robodesk"], 76, 5, 255)
    zs = [torch.rand(2, 76) * 2 - 1 for _ in range(12)]
    acts = [torch.rand(2, 5) * 2 - 1 for _ in range(12)]
    h = torch.zeros(2, wm.hidden)
    with torch.no_grad():
        for z, a in zip(zs, acts, strict=True):
            h = wm.step(h, z, a)
        tail = torch.zeros(2, wm.hidden)
        for z, a in zip(zs[-4:], acts[-4:], strict=True):
            tail = wm.step(tail, z, a)
    assert torch.equal(D.windowed_state(wm, zs, acts, 64), h)
    assert torch.equal(D.windowed_state(wm, zs, acts, 4), tail)
    assert (tail - h).abs().max() > 1e-3


def test_critic_bias_sets_the_critic_against_the_discounted_returns_of_the_newest_episodes():
    """A stand-in agent whose h counts the steps since the episode's start and whose critic says 10 per
    step: V_t = 10 t. The ring buffer holds an older episode (slots 4-7) and the newest (slots 0-3)."""

    class Stand:
        wm = type("W", (), {"hidden": 1, "step": staticmethod(lambda h, z, a: h + 1)})
        twohot = type("T", (), {"mean": staticmethod(lambda x: x[0, 0])})

        @staticmethod
        def critic(x):
            return 10 * x

        @staticmethod
        def features(h, z):
            return h

    r = np.array([4.0, 2.0, 2.9, 0.0, 3.5, 3.5, 3.5, 0.0], np.float32)[None]
    first = np.array([1, 0, 0, 0, 1, 0, 0, 0], np.float32)[None]
    replay = dict(z=np.zeros((1, 8, 3), np.float32), a=np.zeros((1, 8, 5), np.float32), r=r, first=first)
    replay |= dict(last=np.roll(first, -1), pos=np.array([4]), count=np.array([8]))
    out = D.critic_bias(Stand(), replay, episodes=1, gamma=0.5)
    # newest episode: V = 0, 10, 20, 30; G_3 = V_3 = 30, G_2 = 2.9 + 15 = 17.9, G_1 = 2 + 8.95 = 10.95
    # state 1 follows a reward of 4 (light on), state 2 one of 2 (farther); state 0 follows none
    assert out["light on"] == (1, 10.0, pytest.approx(10.95))
    assert out["farther"] == (1, 20.0, pytest.approx(17.9))
    assert out["near, unpressed"][0] == 0
    # both episodes: the older one's states 1 and 2 follow rewards of 3.5 (G_2 = 3.5 + 15, G_1 = 3.5 + 9.25)
    both = D.critic_bias(Stand(), replay, episodes=2, gamma=0.5)
    assert both["light on"] == (3, 40 / 3, pytest.approx((10.95 + 12.75 + 18.5) / 3))
    # a reward offset (--reward-offset) is taken off the stored rewards, as in training
    off = D.critic_bias(Stand(), replay, episodes=1, gamma=0.5, reward_offset=1.0)
    assert off["light on"] == (1, 10.0, pytest.approx(1 + 0.5 * (1.9 + 15)))  # grouped by the raw reward
    # the groups are the button tasks' rewards: the same for push_red, refused for another task
    assert D.critic_bias(Stand(), replay, episodes=1, gamma=0.5, task="push_red") == out
    with pytest.raises(SystemExit, match="open_slide"):
        D.critic_bias(Stand(), replay, episodes=1, gamma=0.5, task="open_slide")


def test_a_file_that_is_not_an_agent_checkpoint_stops_with_one_line_naming_it(tmp_path):
    garbage, other = tmp_path / "notes.pt", tmp_path / "vae.pt"
    garbage.write_text("not a checkpoint")
    torch.save({"kind": "dreamer_baseline", "env": "robodesk"}, other)
    cases = {garbage: "is not a torch checkpoint", other: "is not a gw_dreamer.py RoboDesk agent checkpoint"}
    cases[tmp_path / "missing.pt"] = "does not exist"
    for path, message in cases.items():
        with pytest.raises(SystemExit, match=f"error: {path} {message}"):
            D.main(D.Args(checkpoints=[str(path)]))


def test_object_reach_tells_the_expert_that_opens_the_slide_from_the_random_policy_that_never_touches_it():
    from envs.robodesk import RoboDeskEnv

    env = RoboDeskEnv(task="open_slide", episode_length=800, render_images=False)  # 200 agent steps
    expert = D.object_reach(env, D.ExpertPolicy(env), episodes=1)
    uniform = D.object_reach(env, D.UniformPolicy(0), episodes=1)
    env.close()
    assert expert["closest"][0] < 2.5 and expert["moved"][0] > 20  # at the handle's edge, then pushing
    assert uniform["closest"][0] > 10 and uniform["moved"][0] < 1
    button = RoboDeskEnv(task="push_green", render_images=False)
    with pytest.raises(SystemExit, match="part 9 reads an object task"):
        D.object_reach(button, D.UniformPolicy(0), 1)
    button.close()
