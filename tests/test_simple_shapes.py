"""Simple Shapes: dynamics, rewards, rendering and the batched environment."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs  # noqa: F401  (registers the environments)
from envs.simple_shapes import (
    OUTLINES,
    ROTATION_STEP,
    SimpleShapesEnv,
    SimpleShapesVectorEnv,
    _colourise,
    draw_from_attr,
    draw_shape,
    greedy_action,
    hls_to_rgb,
    render_shapes,
    sample_dataset,
    shape_polygon,
    state_to_attr,
)

DATA = Path(__file__).parent / "data"


def start(env, **state):
    """Reset ``env`` into a hand-built state (defaults: red triangle of size 10)."""
    full = {"cls": 2, "x": 16, "y": 16, "size": 10, "rotation": 0.0, "rgb": (255, 0, 0)} | state
    return env.reset(options={"state": full})


def polygon_area_centroid(p):
    x, y = p[:, 0], p[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2
    return abs(area), np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6 * area)


def test_check_env_single_and_registered():
    check_env(gym.make("SimpleShapes-v0", render_mode="rgb_array").unwrapped, skip_render_check=False)
    env = gym.make("SimpleShapes-v0", render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    assert obs["image"].shape == (32, 32, 3) and obs["image"].dtype == np.uint8
    assert obs["attr"].shape == (11,) and obs["attr"].dtype == np.float32
    frame = env.render()
    assert frame.shape == (256, 256, 3)
    np.testing.assert_array_equal(frame[::8, ::8], obs["image"])


def test_reward_on_hand_built_states():
    env = SimpleShapesEnv()
    start(env, x=14, y=19, rotation=np.pi / 2)
    _, r, term, trunc, info = env.step(0)  # no-op
    assert r == pytest.approx(-np.sqrt(2**2 + 3**2) - 10 * np.pi / 2)
    assert not term and not trunc
    assert info["distance"] == pytest.approx(np.sqrt(13))
    # The angle to upright is the smaller way round: 3pi/2 is pi/2 away.
    start(env, x=16, y=10, rotation=3 * np.pi / 2)
    _, r, *_ = env.step(2)  # y + 1 (up)
    assert env.state["y"] == 11
    assert r == pytest.approx(-5 - 10 * np.pi / 2)
    # The rotation coefficient is a constructor argument.
    env0 = SimpleShapesEnv(rotation_reward_coef=0.0)
    start(env0, x=19, y=20, rotation=1.0)
    _, r, *_ = env0.step(0)
    assert r == pytest.approx(-5.0)


def test_termination_needs_centre_and_upright():
    env = SimpleShapesEnv()
    start(env, x=15, y=16, rotation=0.05)
    _, r, term, trunc, info = env.step(1)  # x + 1 reaches the centre, 0.05 < pi/32
    assert term and not trunc and info["is_success"]
    assert r == pytest.approx(-10 * 0.05)
    start(env, x=16, y=16, rotation=ROTATION_STEP + 0.01)
    _, _, term, *_ = env.step(0)
    assert not term
    _, r, term, *_ = env.step(6)  # theta - pi/32 leaves 0.01
    assert term and r == pytest.approx(-0.1)
    start(env, x=16, y=17, rotation=0.0)
    _, _, term, *_ = env.step(0)
    assert not term


def test_rotation_kept_modulo_two_pi_and_actions_move_as_documented():
    env = SimpleShapesEnv()
    start(env, x=10, y=10, rotation=0.01)
    env.step(6)
    assert env.state["rotation"] == pytest.approx(2 * np.pi + 0.01 - ROTATION_STEP)
    for action, (dx, dy) in {1: (1, 0), 2: (0, 1), 3: (-1, 0), 4: (0, -1)}.items():
        start(env, x=10, y=10)
        env.step(action)
        assert (env.state["x"], env.state["y"]) == (10 + dx, 10 + dy)


def test_truncation_after_max_episode_steps():
    env = SimpleShapesEnv(max_episode_steps=100)
    start(env, x=8, y=8)
    for t in range(1, 101):
        _, _, term, trunc, _ = env.step(0)
        assert not term
        assert trunc == (t == 100)


def test_invalid_actions_raise_clear_errors():
    env = SimpleShapesEnv()
    env.reset(seed=0)
    for bad in (7, -1, 1.5, "a", [1, 2]):
        with pytest.raises(ValueError, match="actions must be"):
            env.step(bad)
    venv = SimpleShapesVectorEnv(3)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="actions must be"):
        venv.step(np.array([0, 1]))
    with pytest.raises(ValueError, match=r"\[0, 7\)"):
        venv.step(np.array([0, 1, 9]))
    with pytest.raises(RuntimeError, match="reset"):
        SimpleShapesEnv().step(0)
    with pytest.raises(ValueError, match="size"):
        start(env, size=30)
    with pytest.raises(ValueError, match="lacks"):
        env.reset(options={"state": {"cls": 0}})


def test_render_matches_the_dataset_renderer():
    """Images drawn with matplotlib as the public dataset draws them
    (tests/data/make_matplotlib_reference.py made the file)."""
    ref = np.load(DATA / "matplotlib_reference.npz")
    mine = render_shapes(
        ref["cls"], ref["pos"][:, 0], ref["pos"][:, 1], ref["size"], ref["rotation"], ref["rgb"]
    )
    diff = np.abs(mine.astype(int) - ref["image"].astype(int))
    assert diff.mean() < 0.2  # measured 0.05 (of 255)
    assert (diff <= 2).mean() > 0.99


@pytest.mark.parametrize("cls", [0, 1, 2])
def test_rendered_centroid_area_and_colour_follow_the_attributes(cls):
    rng = np.random.default_rng(cls)
    for _ in range(20):
        x, y = rng.integers(9, 23, 2)
        size, rot = int(rng.integers(7, 15)), rng.random() * 2 * np.pi
        rgb = rng.integers(60, 256, 3)
        img = draw_shape(cls, x, y, size, rot, rgb).astype(float)
        area, centroid = polygon_area_centroid(shape_polygon(cls, x, y, size, rot))
        cover = img[..., np.argmax(rgb)] / rgb.max()
        assert cover.sum() == pytest.approx(area, rel=0.01)
        rows, cols = np.mgrid[0:32, 0:32]
        # Pixel (row, col) spans x in [col, col+1], y in [31-row, 32-row]: y points up.
        cx = (cover * (cols + 0.5)).sum() / cover.sum()
        cy = (cover * (31.5 - rows)).sum() / cover.sum()
        assert np.hypot(cx - centroid[0], cy - centroid[1]) < 0.05
        full = cover > 0.999
        assert full.sum() >= 2  # a size-7 triangle is 4.2 pixels wide
        np.testing.assert_array_equal(img[full], np.broadcast_to(rgb, (full.sum(), 3)))


def test_moving_shifts_the_image_by_whole_pixels_and_off_frame_goes_black():
    env = SimpleShapesEnv()
    obs, _ = start(env, cls=1, x=12, y=12, size=14, rotation=0.7)
    before = obs["image"]
    obs, *_ = env.step(1)  # right
    np.testing.assert_array_equal(obs["image"][:, 1:], before[:, :-1])
    obs, *_ = env.step(2)  # up: one row towards the top
    np.testing.assert_array_equal(obs["image"][:-1, 1:], before[1:, :-1])
    for _ in range(40):
        obs, *_ = env.step(3)
    assert obs["image"].max() == 0
    assert obs["attr"][3] == pytest.approx((13 - 40) / 32 * 2 - 1)
    for _ in range(40):
        obs, *_ = env.step(1)
    np.testing.assert_array_equal(obs["image"][:-1, 1:], before[1:, :-1])


def test_attribute_encoding_and_inverse_rendering():
    attr = state_to_attr(2, [[16, 24]], 14, np.pi / 2, [[255, 0, 51]])[0]
    np.testing.assert_allclose(attr, [0, 0, 1, 0, 0.5, 0, 0, 1, 1, -1, -0.6], atol=1e-6)
    img = draw_shape(0, 13, 20, 9, 1.2, (10, 200, 90))
    np.testing.assert_array_equal(
        draw_from_attr(state_to_attr(0, [[13, 20]], 9, 1.2, [[10, 200, 90]])[0]), img
    )


def test_colour_times_coverage_rounds_exactly():
    values = np.arange(256)
    alpha = np.broadcast_to(values, (256, 1, 256)).astype(np.uint8)  # every alpha for every colour
    rgb = np.stack([values, values[::-1], values], 1).astype(np.uint8)
    out = _colourise(alpha, rgb)[:, 0]  # (colour, alpha, channel)
    exact = (2 * values[:, None, None] * rgb[None].astype(int) + 255) // 510  # round half up, integers
    np.testing.assert_array_equal(out, exact.transpose(1, 0, 2))


def test_hls_to_rgb_matches_opencv_convention():
    hls = np.array(
        [[0, 128, 255], [60, 128, 255], [120, 128, 255], [30, 255, 100], [90, 100, 0], [15, 64, 128]]
    )
    # Hand-computed with OpenCV's 8-bit formula (H*2 degrees, L and S over 255, rounded).
    expected = [[255, 1, 1], [1, 255, 1], [1, 1, 255], [255, 255, 255], [100, 100, 100], [96, 64, 32]]
    np.testing.assert_array_equal(hls_to_rgb(hls), expected)


def test_greedy_policy_reaches_the_goal_from_every_start():
    n = 300
    env = SimpleShapesVectorEnv(n)
    env.reset(seed=list(range(1000, 1000 + n)))
    done_at = np.full(n, -1)
    for t in range(1, 101):
        a = greedy_action(env._core.pos, env._core.rotation)
        _, _, term, trunc, _ = env.step(a)
        assert not np.any(trunc & (done_at < 0))
        done_at[(done_at < 0) & term] = t
        if np.all(done_at > 0):
            break
    assert np.all(done_at > 0)
    # Never more than the worst start needs: 2 x 9 moves and 32 turns of pi/32.
    assert done_at.max() <= 50


def test_batched_equals_single_envs_with_the_same_seeds():
    n, seed = 6, 11
    venv = SimpleShapesVectorEnv(n, max_episode_steps=30)
    singles = [SimpleShapesEnv(max_episode_steps=30) for _ in range(n)]
    vobs, _ = venv.reset(seed=seed)
    for i, e in enumerate(singles):
        np.testing.assert_array_equal(e.reset(seed=seed + i)[0]["image"], vobs["image"][i])
    rng = np.random.default_rng(0)
    n_done = 0
    for _ in range(90):
        greedy = greedy_action(venv._core.pos, venv._core.rotation)
        actions = np.where(rng.random(n) < 0.6, greedy, rng.integers(0, 7, n))
        vobs, vr, vterm, vtrunc, vinfo = venv.step(actions)
        for i, e in enumerate(singles):
            o, r, term, trunc, _ = e.step(int(actions[i]))
            assert (r, term, trunc) == (vr[i], vterm[i], vtrunc[i])
            if term or trunc:
                n_done += 1
                np.testing.assert_array_equal(vinfo["final_obs"]["image"][i], o["image"])
                np.testing.assert_array_equal(vinfo["final_obs"]["attr"][i], o["attr"])
                o, _ = e.reset()
            np.testing.assert_array_equal(vobs["image"][i], o["image"])
            np.testing.assert_array_equal(vobs["attr"][i], o["attr"])
    assert n_done >= n  # episodes ended by both termination and truncation were compared


def test_seeding_is_reproducible_and_make_vec_works():
    a = gym.make_vec("SimpleShapes-v0", num_envs=4, vectorization_mode="vector_entry_point")
    b = SimpleShapesVectorEnv(4)
    oa, _ = a.reset(seed=3)
    ob, _ = b.reset(seed=3)
    np.testing.assert_array_equal(oa["image"], ob["image"])
    oc, _ = b.reset(seed=4)
    assert not np.array_equal(oc["attr"], ob["attr"])
    np.testing.assert_array_equal(oc["attr"][:3], ob["attr"][1:])  # env i gets seed + i
    b.reset(seed=3)
    actions = np.array([1, 2, 5, 0])
    np.testing.assert_array_equal(a.step(actions)[0]["image"], b.step(actions)[0]["image"])


def test_dataset_is_reproducible_and_in_range():
    d1, d2 = sample_dataset(2000, seed=5), sample_dataset(2000, seed=5)
    np.testing.assert_array_equal(d1["image"], d2["image"])
    attr = d1["attr"]
    assert np.all(attr[:, :3].sum(1) == 1)
    x = (attr[:, 3] + 1) / 2 * 32
    assert x.min() == 7 and x.max() == 24
    size = (attr[:, 5] + 1) / 2 * 14 + 7
    assert set(np.round(size).astype(int)) == set(range(7, 15))
    assert np.all(d1["image"].reshape(2000, -1).max(1) > 0)
    assert len(OUTLINES) == 3


def test_dataset_wide_share_places_that_share_past_the_border():
    from envs.simple_shapes import WIDE_POSITIONS

    d = sample_dataset(4000, seed=5, wide_share=0.25)
    assert abs(d["wide"].mean() - 0.25) < 0.03
    pos = (d["attr"][:, 3:5] + 1) / 2 * 32
    inside = np.all((pos >= 7) & (pos <= 24), axis=1)
    assert inside[~d["wide"]].all()  # the rest keep the dataset's draw
    wide = pos[d["wide"]]
    assert wide.min() == WIDE_POSITIONS[0] and wide.max() == WIDE_POSITIONS[1] - 1
    # a shape centred 16 px past the border has left the frame: its image is black
    far = np.any((pos < -10) | (pos > 41), axis=1)
    assert far.any() and np.all(d["image"][far].max(axis=(1, 2, 3)) == 0)
    # the other attributes are those of the plain draw from the same seed: only positions move
    plain = sample_dataset(4000, seed=5)
    keep = [0, 1, 2, 5, 6, 7, 8, 9, 10]
    np.testing.assert_array_equal(d["attr"][:, keep], plain["attr"][:, keep])
    np.testing.assert_array_equal(d["attr"][~d["wide"]], plain["attr"][~d["wide"]])
    with pytest.raises(ValueError, match="wide_share"):
        sample_dataset(4, wide_share=1.5)


def test_reference_returns_bracket_the_normalised_return():
    """0 = uniformly random policy, 1 = greedy policy; the greedy policy reaches the goal in every episode
    (it never takes more steps than |dx| + |dy| + the rotation steps), the random one almost never."""
    from envs.simple_shapes import reference_returns

    random_ret, greedy_ret = reference_returns(episodes=200, seed=5)
    assert random_ret < -1_800 and -600 < greedy_ret < -100, (random_ret, greedy_ret)
    # seeded: measured again (not the process's cached figures), the same
    assert reference_returns.__wrapped__(episodes=200, seed=5) == (random_ret, greedy_ret)
    assert reference_returns(episodes=200, seed=5) is reference_returns(episodes=200, seed=5)  # once


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"x": 1000}, "x"),
        ({"y": 6}, "y"),
        ({"x": 16.5}, "x"),
        ({"rotation": float("nan")}, "rotation"),
        ({"cls": 1.7}, "cls"),
        ({"cls": 3}, "cls"),
        ({"size": 10.9}, "size"),
        ({"rgb": (256, 0, 0)}, "rgb"),
        ({"colour": 1}, "unknown keys"),
    ],
)
def test_a_reset_state_outside_the_observation_space_is_refused(bad, match):
    """reset(options={"state": ...}) takes only states the environment could start in (whole pixels in
    [7, 24], a class, a size in [7, 14], a finite rotation, a colour): anything else is a ValueError
    naming the key, never silently rounded or clipped. Fails if a check is dropped."""
    with pytest.raises(ValueError, match=match):
        start(SimpleShapesEnv(), **bad)


def test_every_observation_of_an_episode_lies_in_the_space_and_stepping_past_its_end_is_an_error():
    """From the extreme corner the env allows, 100 steps pushing outwards keep every observation inside
    the observation space; a step after the truncation raises (gymnasium leaves it undefined) until
    reset. Fails if the state bounds are widened or the episode end is not enforced."""
    env = SimpleShapesEnv()
    obs, _ = start(env, x=7, y=7, rotation=1.0)
    for _ in range(100):
        obs, _, terminated, truncated, _ = env.step(3)  # x - 1
        assert env.observation_space.contains(obs)
    assert truncated and not terminated
    with pytest.raises(RuntimeError, match="episode has ended"):
        env.step(0)
    start(env)
    env.step(0)
