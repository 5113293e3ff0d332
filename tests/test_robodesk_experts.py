"""Scripted RoboDesk experts (envs/robodesk_experts.py) and the multi-task data they collect with
pretrain_vae_gw.py: success within an episode, action noise, labelled shards in the asked proportions,
and the tasks a GW saw recorded in its checkpoint."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from conftest import run_pretrain

import pretrain_vae_gw as P
from envs.robodesk import RoboDeskEnv
from envs.robodesk_experts import EXPERTS, LANDMARKS, WANDER_HIGH, WANDER_LOW, Wanderer, landmark_positions


@pytest.mark.parametrize("task", sorted(EXPERTS))
def test_each_expert_succeeds_within_an_episode(task):
    env = RoboDeskEnv(task=task, render_images=False)
    env.reset(seed=0)
    policy = EXPERTS[task](env)
    successes = 0
    for _ in range(500):
        _, _, _, trunc, info = env.step(policy.act(env))
        successes += info["success"]
    assert trunc and successes > 50, successes  # measured on seed 0: 139 (open_slide) to 441 (push_blue)


def test_experts_work_through_gymnasium_wrappers_and_add_seeded_noise():
    env = gym.make("RoboDesk-v0", task="push_blue", render_quality="fast")
    env.reset(seed=3)
    plain = EXPERTS["push_blue"](env)
    a, b = EXPERTS["push_blue"](env, noise=0.2, seed=7), EXPERTS["push_blue"](env, noise=0.2, seed=7)
    act_plain, act_a, act_b = plain.act(env), a.act(env), b.act(env)
    assert np.array_equal(act_a, act_b) and not np.array_equal(act_a, act_plain)
    assert act_a.shape == (5,) and np.all(np.abs(act_a) <= 1)
    env.close()
    with pytest.raises(ValueError, match="push_green expert was given a push_blue environment"):
        EXPERTS["push_green"](env)


def test_collection_plan_follows_the_paper_proportions():
    one = P.robodesk_plan(P.Args(env="robodesk").resolve(), 2_000_000)  # 1M expert + 1M random
    assert one == [("expert", "push_green", 1_000_000), ("random", "push_green", 1_000_000)]
    tasks = ("push_green", "push_red", "push_blue", "open_slide", "upright_block_off_table")
    many = P.robodesk_plan(P.Args(env="robodesk", tasks=tasks).resolve(), 600)  # equal shares, random one
    assert [n for _, _, n in many] == [100] * 6 and many[-1][0] == "random"
    with pytest.raises(ValueError, match="no scripted expert for 'lift_ball'"):
        P.robodesk_plan(P.Args(env="robodesk", tasks=("lift_ball",)), 10)
    with pytest.raises(ValueError, match="unknown RoboDesk task 'fly'"):
        P.robodesk_plan(P.Args(env="robodesk", tasks=("fly",)), 10)


def test_wander_share_comes_before_the_expert_random_split():
    args = P.Args(env="robodesk", tasks=("push_green", "open_slide"), wander_fraction=0.3).resolve()
    assert P.robodesk_plan(args, 1000) == [
        ("expert", "push_green", 233),
        ("expert", "open_slide", 233),
        ("wander", "push_green", 300),
        ("random", "push_green", 234),
    ]
    with pytest.raises(ValueError, match="--wander-fraction must be in"):
        P.robodesk_plan(P.Args(env="robodesk", wander_fraction=1.5).resolve(), 10)


def test_wanderer_goes_to_its_way_points_near_landmarks_and_in_the_box():
    """Without noise the hand heads for each way-point (a few cm above a landmark where it is drawn, or
    anywhere in the box) and reaches those within the arm's reach, then draws the next; the gripper action
    changes between way-points and the wrist turns toward an angle drawn over its whole range; seeded
    runs repeat."""
    env = RoboDeskEnv(task="push_green", render_images=False)
    env.reset(seed=0)
    for near in (1.0, 0.0):
        w = Wanderer(env, noise=0.0, seed=1, near=near)
        targets, grips, start, reached, closer, marks = [], [], None, [], [], []
        wrists, turned, wrist_start = [], [], None
        for _ in range(200):
            ee, wrist = env.data.site_xpos[env._ee_site].copy(), env.data.qpos[6]
            a = w.act(env)
            if not targets or not np.array_equal(w.target, targets[-1]):
                if targets:  # how close the hand came to the way-point it leaves, and the wrist to its angle
                    reached.append(np.linalg.norm(targets[-1] - ee) < 0.03)
                    closer.append(np.linalg.norm(targets[-1] - ee) < np.linalg.norm(targets[-1] - start))
                    turned.append(abs(wrists[-1] - wrist) < abs(wrists[-1] - wrist_start) - 0.05)
                targets.append(w.target.copy())
                wrists.append(w.wrist_target)
                wrist_start = wrist
                grips.append(a[4])
                marks.append(list(landmark_positions(env).values()))  # where the landmarks were then
                start = ee
            env.step(a)
        # Some way-points lie beyond the arm's reach or inside an object; the rest are reached.
        assert len(targets) >= 4 and len(set(grips)) >= 2
        assert any(reached) and np.mean(closer) >= 0.75, (reached, closer)
        lo, hi = env.joint_bounds[6]
        assert np.mean(turned) >= 0.75 and min(wrists) < lo / 2 and max(wrists) > hi / 2, (wrists, turned)
        heights = []  # of near way-points over their landmark: some press on it (below its centre)
        for t, then in zip(targets, marks, strict=True):
            if near:  # at one of the landmarks, within 5 cm across
                mark = min(then, key=lambda m: np.abs(t[:2] - m[:2]).max())
                assert np.abs(t[:2] - mark[:2]).max() <= 0.05 + 1e-6
                heights.append(t[2] - mark[2])
            else:
                assert np.all(t >= WANDER_LOW) and np.all(t <= WANDER_HIGH)
        if near:
            assert min(heights) < 0 < max(heights) and -0.05 <= min(heights) and max(heights) <= 0.15
    assert set(landmark_positions(env)) == set(LANDMARKS) and "red_button" not in LANDMARKS
    ee = env.data.site_xpos[env._ee_site]
    first, second = Wanderer(env, seed=4), Wanderer(env, seed=4)
    assert np.array_equal(first.act(env), second.act(env)) and np.linalg.norm(first.target - ee) > 0


def test_collector_mixes_sources_and_labels_every_sample(tmp_path):
    args = (
        "--env robodesk --stages collect --tasks push_green open_slide --render-quality fast --shard-size 25"
    )
    args = args.split()
    log = run_pretrain(tmp_path, *args, "--n-samples", "60")
    assert "20 expert (push_green), 20 expert (open_slide), 20 random" in log
    assert "[collect] 40/60" in log and "(expert, open_slide)" in log  # a progress line per episode
    folder = tmp_path / "data" / "robodesk"
    assert [len(np.load(p)["attr"]) for p in P.shard_paths(folder)] == [25, 25, 10]
    assert P.label_counts(folder) == {"expert/open_slide": 20, "expert/push_green": 20, "random/": 20}
    run_pretrain(tmp_path, *args, "--n-samples", "90")  # appending keeps the proportions
    assert P.label_counts(folder) == {"expert/open_slide": 30, "expert/push_green": 30, "random/": 30}
    sources, tasks = P.load_labels(folder)
    images, attrs = P.load_data(folder, "robodesk")
    assert len(sources) == len(tasks) == len(images) == len(attrs) == 90
    # Expert samples start from reset states and then follow the expert: they differ from random ones.
    assert set(np.unique(tasks[sources == "expert"])) == {"push_green", "open_slide"}


def test_gw_checkpoint_records_the_tasks_it_saw(pretrained_robodesk):
    ck = torch.load(pretrained_robodesk[0] / "ck" / "robodesk" / "gw.pt", weights_only=False)
    assert ck["data"]["samples_per_source_and_task"] == {"expert/push_green": 20, "random/": 20}


def test_two_collecting_workers_give_the_data_of_one(tmp_path):
    """--workers 2 runs the episodes in two processes (each its own simulator and renderer): the shards
    hold the same images, attributes and labels, in the same order, as one process collecting."""
    flags = (
        "--env robodesk --stages collect --tasks push_green open_slide --render-quality fast --shard-size 25"
    )
    for workers in ("1", "2"):
        (tmp_path / workers).mkdir()
        run_pretrain(tmp_path / workers, *flags.split(), "--n-samples", "60", "--workers", workers)
    one, two = (P.shard_paths(tmp_path / w / "data" / "robodesk") for w in ("1", "2"))
    assert len(one) == len(two) == 3
    for a, b in zip(one, two, strict=True):
        with np.load(a) as x, np.load(b) as y:
            for key in ("image", "attr", "source", "task"):
                np.testing.assert_array_equal(x[key], y[key], err_msg=key)
    assert np.load(one[0])["image"].std() > 0  # real renders, not blank frames
