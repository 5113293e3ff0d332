"""RoboDesk port: tasks, rewards, inverse kinematics, observations, image pipeline, errors."""

import importlib
import importlib.util
import os
import signal
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs  # noqa: F401  (registers the environments)
from envs import robodesk
from envs.robodesk import CORE_TASKS, EXTRA_TASKS, TASKS, ImageResizer, RoboDeskEnv, make_vector_env

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def env():
    """One attributes-only environment shared by the state-setting tests (reset in each)."""
    e = RoboDeskEnv(render_images=False)
    yield e
    e.close()


def with_objects(env, task, seed=0, **moves):
    """Reset ``env`` on ``task``, then place objects/joints: ``name=value`` sets a slide joint's
    position or a free body's (x, y, z) (``None`` entries keep the current coordinate)."""
    env.task = task
    env.reset(seed=seed)
    qpos, qvel = env.data.qpos.copy(), np.zeros(env.model.nv)
    for name, value in moves.items():
        j = env.model.joint(name)
        if j.type[0] == mujoco.mjtJoint.mjJNT_FREE:
            for k, v in enumerate(value):
                if v is not None:
                    qpos[j.qposadr[0] + k] = v
        else:
            qpos[j.qposadr[0]] = value
    env.set_state(qpos, qvel)
    return env.task_reward("success")


def test_task_list_matches_the_original():
    assert len(CORE_TASKS) == 9 and len(EXTRA_TASKS) == 9 and len(set(TASKS)) == 18


@pytest.mark.parametrize(
    "script", ["gw_dreamer", "gw_dreamer_e2e", "dreamer_baseline", "ppo_variants", "pretrain_vae_gw"]
)
def test_every_script_lists_the_valid_tasks_in_its_help(script, capsys):
    import tyro

    module = importlib.import_module(script)
    with pytest.raises(SystemExit):
        tyro.cli(module.Args, args=["--help"])
    help_text = " ".join(capsys.readouterr().out.replace("│", " ").split())
    for task in TASKS:
        assert task in help_text, task


def test_unknown_task_and_bad_arguments_raise_clear_errors():
    with pytest.raises(ValueError, match="valid tasks: open_slide, open_drawer, push_green"):
        RoboDeskEnv(task="open_door")
    with pytest.raises(ValueError, match="reward mode"):
        RoboDeskEnv(reward="shaped")
    with pytest.raises(ValueError, match="render_quality"):
        RoboDeskEnv(render_quality="ultra")


def test_missing_scene_names_the_install_command(monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(FileNotFoundError, match=r"pip install --no-deps robodesk==1\.0\.0"):
        robodesk.scene_path()


def test_wrong_actions_and_states_raise(env):
    env.reset(seed=0)
    for bad in ([0.0] * 4, [0, 0, np.nan, 0, 0], [0, 0, 2.0, 0, 0], "left"):
        with pytest.raises(ValueError, match="RoboDesk action"):
            env.step(bad)
    with pytest.raises(ValueError, match="qpos of shape"):
        env.set_state(np.zeros(3), np.zeros(env.model.nv))
    with pytest.raises(RuntimeError, match="reset"):
        RoboDeskEnv(render_images=False).step(np.zeros(5))


def test_attribute_space_has_the_joints_soft_bounds_and_refuses_states_outside_them():
    """Joint positions are bounded by their ranges widened by the soft-limit margin, quaternions by
    [-1, 1], free positions and velocities not at all; a random-action episode pressed against the limits
    stays inside; set_state refuses a qpos outside. Fails if the attribute space is left at +-inf or
    set_state skips the bounds."""
    e = RoboDeskEnv(render_images=False, episode_length=400)
    space = e.observation_space["attr"]
    lo, hi = e.model.jnt_range[e.model.joint("panda0_joint4").id]
    assert (space.low[3], space.high[3]) == (np.float32(lo - 0.25), np.float32(hi + 0.25))
    assert space.low[22] == np.float32(-0.02) and space.high[22] == np.float32(0.62)  # the slide, 0-0.6 m
    assert (space.low[32:36] == -1).all() and (
        space.high[43:50][3:] == 1
    ).all()  # ball, flat block quaternions
    assert np.isinf(space.low[29:32]).all() and np.isinf(space.high[9:21]).all()  # positions, velocities
    obs, _ = e.reset(seed=3)
    rng = np.random.default_rng(3)
    for _ in range(100):
        obs = e.step(np.sign(rng.uniform(-1, 1, 5)).astype(np.float32))[0]  # bang-bang, into the limits
        assert space.contains(obs["attr"])
    qpos, qvel = e.data.qpos.copy(), e.data.qvel.copy()
    e.set_state(qpos, qvel)  # inside: accepted
    qpos[0] = 10.0
    with pytest.raises(ValueError, match=r"qpos\[0\] = 10 is outside \[-3.1"):
        e.set_state(qpos, qvel)


def test_check_env_with_and_without_images():
    check_env(RoboDeskEnv(render_images=False, episode_length=40), skip_render_check=True)
    check_env(
        gym.make("RoboDesk-v0", render_quality="fast", episode_length=40).unwrapped, skip_render_check=True
    )


@pytest.mark.parametrize(
    "task, success_moves, failure_moves",
    [
        ("open_slide", {"slide_joint": 0.555}, {"slide_joint": 0.545}),
        ("open_drawer", {"drawer_joint": -0.205}, {"drawer_joint": -0.195}),
        ("push_green", {"green_light": -0.00458}, {"green_light": -0.00448}),
        ("push_blue", {"blue_light": -0.005}, {"green_light": -0.005}),
        ("push_red", {"red_light": -0.005}, {"red_light": -0.004}),
        (
            "lift_upright_block",
            {"upright_block": (None, None, 0.865)},
            {"upright_block": (None, None, 0.855)},
        ),
        ("lift_ball", {"ball": (None, None, 0.815)}, {"ball": (None, None, 0.805)}),
        ("lift_flat_block", {"flat_block": (None, None, 0.785)}, {"flat_block": (None, None, 0.775)}),
        ("flat_block_in_bin", {"flat_block": (0.4, 0.61, 0.2)}, {"flat_block": (0.4, 0.63, 0.2)}),
        ("upright_block_in_bin", {"upright_block": (0.3, 0.4, 0.1)}, {"upright_block": (0.4, 0.5, 0.5)}),
        ("ball_in_bin", {"ball": (0.5, 0.6, 0.3)}, {"ball": (0.6, 0.5, 0.3)}),
        ("flat_block_in_shelf", {"flat_block": (0.21, 1.1, 0.9)}, {"flat_block": (0.19, 1.1, 0.9)}),
        ("upright_block_in_shelf", {"upright_block": (0.3, 1.05, 0.9)}, {"upright_block": (0.3, 0.95, 0.9)}),
        ("ball_in_shelf", {"ball": (0.25, 1.2, 0.9)}, {"ball": (0.15, 1.2, 0.9)}),
        ("upright_block_off_table", {"upright_block": (0.9, 0.5, 0.1)}, {"upright_block": (0.3, 0.7, 0.65)}),
        ("flat_block_off_table", {"flat_block": (0.9, 0.5, 0.1)}, {}),
        ("ball_off_table", {"ball": (-0.9, 0.5, 0.5)}, {"ball": (-0.3, 0.7, 0.61)}),
    ],
)
def test_success_criterion_on_hand_set_states(env, task, success_moves, failure_moves):
    """Each task's success on a hand-set state, bracketing the threshold closely where it is one number
    (slide, drawer, buttons, lifts, the bin's far edge, the shelf's depth): fails when a threshold moves
    by more than half the bracket."""
    assert with_objects(env, task, **success_moves) == 1.0
    assert with_objects(env, task, **failure_moves) == 0.0


def test_stack_success(env):
    env.task = "stack"
    env.reset(seed=3)
    flat = env.data.xpos[env.model.body("flat_block").id].copy()
    assert with_objects(env, "stack", seed=3) == 0.0
    # Put the upright block's frame 0.0378 m above the flat block's.
    assert with_objects(env, "stack", seed=3, upright_block=flat + np.array([0.0, 0.0, 0.0378])) == 1.0


def test_success_is_reported_in_info_every_step():
    e = RoboDeskEnv(task="open_slide", render_images=False, action_repeat=1, reward="sparse")
    e.reset(seed=0)
    qpos = e.data.qpos.copy()
    qpos[e.model.joint("slide_joint").qposadr[0]] = 0.58
    _, info = e.reset(options={"qpos": qpos, "qvel": np.zeros(e.model.nv)})
    assert info["success"]
    _, r, term, trunc, info = e.step(np.zeros(5))
    assert info["success"] and r == 1.0 and not term and not trunc


def test_reward_modes_sum_over_repeats_and_success_pays_once():
    sparse = RoboDeskEnv(task="open_slide", reward="sparse", render_images=False, action_repeat=4)
    once = RoboDeskEnv(task="open_slide", reward="success", render_images=False, action_repeat=4)
    for e in (sparse, once):
        e.reset(seed=0)
        qpos = e.data.qpos.copy()
        qpos[e.model.joint("slide_joint").qposadr[0]] = 0.58
        e.reset(options={"qpos": qpos, "qvel": np.zeros(e.model.nv)})
    assert [sparse.step(np.zeros(5))[1] for _ in range(2)] == [4.0, 4.0]
    assert [once.step(np.zeros(5))[1] for _ in range(2)] == [1.0, 0.0]


def test_reference_position_defect_and_the_corrected_rewards():
    """Lifting the ball 0.2 m: the original's live reference follows it, so the lift term stays 0."""
    rewards = {}
    for frozen in (False, True):
        e = RoboDeskEnv(task="lift_ball", render_images=False, frozen_reference=frozen)
        e.reset(seed=0)
        qpos = e.data.qpos.copy()
        qpos[e.model.joint("ball").qposadr[0] + 2] += 0.2
        e.set_state(qpos, np.zeros(e.model.nv))
        ball = e.data.xpos[e.model.body("ball").id]
        dist = np.clip(1 - np.linalg.norm(e.data.site_xpos[e._ee_site] - ball), 0, 1)
        rewards[frozen] = (e.task_reward("dense"), 0.15 * dist)
    live, frozen = rewards[False], rewards[True]
    assert live[0] == pytest.approx(live[1])  # only the distance term
    assert frozen[0] == pytest.approx(min(1.0, 0.85 + frozen[1]))  # lift term saturated at 1


def test_inverse_kinematics_reaches_the_commanded_delta(env):
    env.reset(seed=1)
    ee = env.data.site_xpos[env._ee_site].copy()
    check = mujoco.MjData(env.model)
    for delta in ([0.01, 0, 0], [0, -0.01, 0], [0, 0, 0.01], [0.007, 0.007, -0.007]):
        env._scratch.qpos[:] = env.data.qpos
        joints = env.inverse_kinematics(ee + np.array(delta))
        np.testing.assert_array_equal(joints[6:], env.data.qpos[6:9])  # only joints 1-6 move
        check.qpos[:] = env.data.qpos
        check.qpos[:9] = joints
        mujoco.mj_kinematics(env.model, check)
        np.testing.assert_allclose(check.site_xpos[env._ee_site], ee + delta, atol=1e-6)


def test_reset_is_reproducible_and_replays_from_a_state():
    a, b = RoboDeskEnv(render_images=False), RoboDeskEnv(render_images=False)
    oa, _ = a.reset(seed=7)
    ob, _ = b.reset(seed=7)
    np.testing.assert_array_equal(oa["attr"], ob["attr"])
    oc, _ = b.reset(seed=8)
    assert not np.allclose(oc["attr"], oa["attr"])
    # Replay: start b from a's full state, apply the same actions, get the same trajectory.
    a.reset(seed=9)
    b.reset(options={"qpos": a.data.qpos.copy(), "qvel": a.data.qvel.copy()})
    actions = np.random.default_rng(0).uniform(-1, 1, (10, 5))
    for act in actions:
        ra, rb = a.step(act), b.step(act)
        np.testing.assert_array_equal(ra[0]["attr"], rb[0]["attr"])
        assert ra[1] == rb[1]


def test_observation_has_76_finite_attributes_and_truncates_without_terminating():
    e = RoboDeskEnv(render_images=False, action_repeat=4, episode_length=16)
    obs, _ = e.reset(seed=0)
    assert obs["attr"].shape == (76,) and np.all(np.isfinite(obs["attr"]))
    n = e.model.nq - 9
    np.testing.assert_array_equal(obs["attr"][21 : 21 + n], e.data.qpos[9:].astype(np.float32))
    flags = [e.step(np.zeros(5))[2:4] for _ in range(4)]
    assert flags == [(False, False)] * 3 + [(False, True)]


def test_image_is_rendered_like_the_original_and_follows_the_arm():
    e = RoboDeskEnv(task="push_green", render_quality="fast", action_repeat=4)
    obs, _ = e.reset(seed=0)
    img = obs["image"]
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8 and img.std() > 20
    for _ in range(10):
        obs, *_ = e.step(np.array([0.0, -1.0, 1.0, 0.0, 1.0]))
    assert np.abs(obs["image"].astype(int) - img).mean() > 1.0
    e.close()


def test_faithful_render_is_non_blank():
    e = RoboDeskEnv(render_quality="faithful")
    obs, _ = e.reset(seed=0)
    assert obs["image"].std() > 20
    e.close()


def test_crop_and_resize_match_pillow_exactly():
    """tests/data/make_pillow_reference.py made the reference with Pillow's crop + LANCZOS resize."""
    ref = np.load(DATA / "pillow_lanczos_reference.npz")
    np.testing.assert_array_equal(ImageResizer(64)(ref["render"]), ref["image"])


def test_vector_env_in_processes_matches_the_one_in_this_process():
    """make_vector_env(processes=True) steps each env in a spawned process (a child forked from a process
    that already rendered inherits a broken GL state): the same observations, rewards, episode ends,
    final observations and success flags as in one process, across an autoreset; its processes ignore
    Ctrl-C, which reaches a terminal's whole process group."""
    kw = dict(task="push_green", render_quality="fast", action_repeat=4, episode_length=24)
    actions = np.random.default_rng(0).uniform(-1, 1, (8, 2, 5)).astype(np.float32)
    runs = {}
    for processes in (False, True):
        vec = make_vector_env(2, processes, **kw)
        if processes:
            for worker in vec.processes:
                os.kill(worker.pid, signal.SIGINT)
        steps = [vec.reset(seed=3)[0]]
        for a in actions:
            steps.append(vec.step(a))
        vec.close()
        runs[processes] = steps
    assert runs[True][0]["image"].shape == (2, 64, 64, 3)
    for one, many in zip(runs[False][1:], runs[True][1:], strict=True):
        for key in ("image", "attr"):
            assert np.array_equal(one[0][key], many[0][key])
        for got, want in zip(many[1:4], one[1:4], strict=True):  # reward, terminated, truncated
            assert np.array_equal(got, want)
        assert np.array_equal(one[4]["success"], many[4]["success"])
    ends = [i for i, step in enumerate(runs[True][1:]) if step[3].all()]
    assert ends == [5], ends  # 24 frames = 6 actions of 4, then the autoreset
    final_one, final_many = runs[False][6][4]["final_obs"], runs[True][6][4]["final_obs"]
    for i in range(2):
        assert np.array_equal(final_one[i]["image"], final_many[i]["image"])
        assert not np.array_equal(final_many[i]["attr"], runs[True][6][0]["attr"][i])  # reset since


def plain_dense_reward(task: str, ee, pos: dict, ref: dict, joints: dict) -> float:
    """The original RoboDesk's dense rewards written out from plain numbers: end-effector position ``ee``,
    object positions ``pos`` now and ``ref`` at reset, and joint positions ``joints``."""

    def near(p):  # 1 at the end effector, 0 from 1 m away
        return min(max(1 - np.linalg.norm(ee - p), 0.0), 1.0)

    def moved(o):
        return np.linalg.norm(pos[o] - ref[o]) / 5.0

    others = {o: [p for p in ("flat_block", "upright_block", "ball") if p != o] for o in pos}
    if task == "open_drawer":
        r = 0.75 * abs(joints["drawer"]) / 0.3 + 0.25 * near(joints["drawer_handle"])
    elif task == "push_green":
        r = 0.25 * (joints["green_light"] < -0.00453) + 0.75 * near(joints["green_button"])
    elif task == "stack":
        diff = np.linalg.norm(np.array([0, 0, 0.0377804]) - (pos["upright_block"] - pos["flat_block"]))
        r = -diff + near(pos["upright_block"])
    elif task == "upright_block_off_table":
        o = "upright_block"
        progress = 0.8 * (1 - pos[o][2] / ref[o][2]) + sum(0.1 * (1 - moved(p)) for p in others[o])
        r = 0.75 * min(max(progress, 0), 1) + 0.25 * near(pos[o])
    elif task == "flat_block_in_bin":
        x, y, z = pos["flat_block"]
        r = 0.5 * near(pos["flat_block"]) + 0.5 * (0.28 < x < 0.52 and 0.38 < y < 0.62 and 0 < z < 0.4)
    elif task == "ball_in_shelf":
        p = pos["ball"]
        success = p[0] > 0.2 and p[1] > 1.0
        in_shelf = 0.33 * near(p) + 0.33 * (1 - np.linalg.norm(np.array([0.4, 1.1]) - p[:2])) + 0.34 * success
        r = 0.5 * in_shelf + sum(0.25 * (1 - moved(o)) for o in others["ball"])
    elif task == "lift_upright_block":
        z = pos["upright_block"][2]
        r = 0.85 * min(max((z - ref["upright_block"][2]) * 10, 0), 1) + 0.15 * near(pos["upright_block"])
    return float(min(max(r, 0.0), 1.0))


@pytest.mark.parametrize(
    "task, moves",
    [
        ("open_drawer", {"drawer_joint": -0.12}),
        ("push_green", {"green_light": -0.005}),
        ("push_green", {}),
        ("stack", {"upright_block": (0.1, 0.75, 0.8)}),
        ("upright_block_off_table", {"upright_block": (0.5, 0.6, 0.6), "ball": (0.0, 0.7, 0.8)}),
        ("flat_block_in_bin", {"flat_block": (0.4, 0.5, 0.2)}),
        ("flat_block_in_bin", {"flat_block": (0.1, 0.7, 0.76)}),
        ("ball_in_shelf", {"ball": (0.3, 1.05, 0.9), "flat_block": (0.0, 0.6, 0.76)}),
        ("lift_upright_block", {"upright_block": (None, None, 0.83)}),
    ],
)
@pytest.mark.parametrize("frozen", [False, True])
def test_dense_reward_of_each_task_family_against_its_formula(task, moves, frozen):
    """Each family of dense rewards (drawer, button, stack, off table, in bin, in shelf, lift) on a
    hand-set state equals the original's formula computed from the positions, with the original's live
    reference positions (the objects' current ones) and with references frozen at reset. Fails if a
    weight, a threshold or a reference position changes (the slide and lift_ball are tested above)."""
    env = RoboDeskEnv(render_images=False, frozen_reference=frozen)
    env.task = task
    env.reset(seed=2)
    m, d = env.model, env.data
    at_reset = {o: d.xpos[m.body(o).id].copy() for o in ("flat_block", "upright_block", "ball")}
    with_objects(env, task, seed=2, **moves)
    pos = {o: d.xpos[m.body(o).id].copy() for o in at_reset}
    ref = at_reset if frozen else pos
    joints = {
        "drawer": d.qpos[m.joint("drawer_joint").qposadr[0]],
        "drawer_handle": d.geom_xpos[m.geom("drawer_handle").id].copy(),
        "green_light": d.qpos[m.joint("green_light").qposadr[0]],
        "green_button": d.xpos[m.body("green_button").id].copy(),
    }
    want = plain_dense_reward(task, d.site_xpos[env._ee_site].copy(), pos, ref, joints)
    assert env.task_reward("dense") == pytest.approx(want, abs=1e-9)
    assert 0.0 < want < 1.0 or task == "flat_block_in_bin"  # the state tests more than a clip


def test_stepping_past_the_end_of_an_episode_is_an_error():
    """After the truncating step the env refuses to step (gymnasium leaves it undefined) until reset.
    Fails if the episode end is not enforced."""
    e = RoboDeskEnv(render_images=False, episode_length=8)
    e.reset(seed=0)
    _, _, _, truncated, _ = e.step(np.zeros(5))
    assert not truncated
    _, _, _, truncated, _ = e.step(np.zeros(5))
    assert truncated
    with pytest.raises(RuntimeError, match="episode has ended"):
        e.step(np.zeros(5))
    e.reset(seed=1)
    e.step(np.zeros(5))
