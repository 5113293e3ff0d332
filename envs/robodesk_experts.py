"""Scripted RoboDesk experts: way-point controllers that read the simulator state.

The paper collected its RoboDesk pre-training data partly with expert policies (100M-parameter DreamerV3
agents, section "Unique Global Workspace for all tasks") and notes that demonstrations would serve as well.
These experts stand in for them: each reads object positions from ``env.unwrapped`` and moves the end
effector through way-points with a proportional controller on the action's position delta (the env's
inverse kinematics does the rest), wrist held still.

    from envs.robodesk_experts import EXPERTS
    env = gymnasium.make("RoboDesk-v0", task="push_green")
    policy = EXPERTS["push_green"](env, noise=0.1, seed=0)
    obs, info = env.reset(seed=0)
    policy.reset()
    obs, r, term, trunc, info = env.step(policy.act(env))

``noise`` adds Gaussian noise (std in action units) to every action, for more varied data.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np

from envs.robodesk import WRIST_SCALE

STEP = 0.04  # metres the end effector may move per agent step (0.01 per unit action x 4 repeats)
CLOSED = -1.0  # gripper action (+1 opens the fingers)
BIN_X = 0.40  # x of the bin's centre (its walls stand at 0.28 and 0.52)
DESK_Z = 0.76  # height of the desk top (the upright block's base at reset)


class WaypointExpert:
    """Follows a list of way-points (position, gripper, tolerance); the list is recomputed from the
    simulator state at every step, so targets track moving objects. A way-point is passed once the end
    effector is within its tolerance. The last way-point is held."""

    def __init__(self, env: gym.Env, plan: Callable, noise: float = 0.0, seed: int | None = None):
        robodesk = env.unwrapped
        lo, hi = robodesk.joint_bounds[6]
        self.wrist_hold = -(lo + hi) / (hi - lo)  # the action whose wrist step is 0
        self.plan, self.noise = plan, float(noise)
        self.rng = np.random.default_rng(seed)
        self.stage = 0

    def reset(self) -> None:
        self.stage = 0

    def act(self, env: gym.Env) -> np.ndarray:
        robodesk = env.unwrapped
        ee = robodesk.data.site_xpos[robodesk._ee_site]
        waypoints = self.plan(robodesk)
        target, grip, tol = waypoints[min(self.stage, len(waypoints) - 1)]
        while self.stage < len(waypoints) - 1 and np.linalg.norm(target - ee) < tol:
            self.stage += 1
            target, grip, tol = waypoints[self.stage]
        action = np.zeros(5)
        action[:3] = np.clip((target - ee) / STEP, -1.0, 1.0)
        action[3], action[4] = self.wrist_hold, grip
        if self.noise:
            action += self.rng.normal(0.0, self.noise, 5)
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def _button(colour: str):
    """Above the button, then press it with the closed gripper and hold (the light is on while held).
    The fingertips are about 5 cm below the end-effector site; a target 3.5 cm above the button presses
    it without driving the arm into the desk (deeper targets made the arm drift off the red button)."""

    def plan(env):
        b = env._xpos(f"{colour}_button")
        return [(b + [0.0, 0.0, 0.12], CLOSED, 0.02), (b + [0.0, 0.0, 0.035], CLOSED, 0.0)]

    return plan


def _slide(env):
    """Behind the left edge of the handle, then push the sliding door to the right (+x)."""
    h = env.data.site_xpos[env.model.site("slide_handle").id]
    return [
        (h + [-0.10, -0.10, 0.0], CLOSED, 0.02),
        (h + [-0.10, 0.0, 0.0], CLOSED, 0.02),
        (h + [0.60, 0.0, 0.0], CLOSED, 0.0),
    ]


def _push_off_right(obj: str):
    """Behind the object's left end (-x), low over the desk, then push it right (+x) past the desk's edge.
    The push point is 4.5 cm above the desk for the end-effector site, as low as the hand gets (it
    stalls about 7 cm up when the fingers meet the desk, hence the loose tolerance there). The tall
    upright block tips over under the push (friction beats its 2.3 cm half-width); the left end is read
    from the box's current orientation, so the push goes on against the lying block. Pushing at the
    block's mid-height instead lost the tipped block in 11 of 20 episodes (docs/environments.md)."""

    def plan(env):
        p = env._xpos(obj)
        geom = env.model.body_geomadr[env.model.body(obj).id]
        half = np.abs(env.data.geom_xmat[geom].reshape(3, 3)) @ env.model.geom_size[geom]  # world extents
        behind = np.array([p[0] - half[0] - 0.05, p[1], DESK_Z + 0.045])
        return [
            (behind + [0.0, 0.0, 0.10], CLOSED, 0.02),
            (behind, CLOSED, 0.04),
            (np.array([p[0] + 0.30, p[1], behind[2]]), CLOSED, 0.0),
        ]

    return plan


def _drawer(env):
    """Hook the handle: come down with closed fingers into the slot between the handle bar and the drawer
    front (5.5 cm behind the bar, passed within 4 cm), then pull toward the robot and to its left (-x).
    The bar is the handle mesh's front capsule, 3.9 cm in front of the mesh's centre. Both choices keep
    the hand as far from the shoulder as the task allows: the bar sits about 40 cm from it, and nearer
    targets drive the elbow into its -3.07 rad limit, where the local inverse kinematics stalls.
    Straddling the bar with open fingers and gripping it (5 of 20 episodes) failed that way, as does
    pulling straight back. docs/environments.md: 17 of 20 episodes succeed."""
    bar = env.data.geom_xpos[env.model.geom("drawer_handle").id] + [0.0, -0.039, 0.0]
    slot = bar + [0.0, 0.055, 0.0]
    return [
        (slot + [0.0, 0.0, 0.12], CLOSED, 0.02),
        (slot, CLOSED, 0.04),
        (np.array([-0.25, 0.10, slot[2]]), CLOSED, 0.0),
    ]


def _flat_block_to_bin(env):
    """The bin stands under the desk's front right corner (walls x 0.28-0.52, y 0.43-0.67; the desk top
    ends at y 0.575). Push the flat block (16 x 7 x 3 cm, long along x) from its end to the bin's x
    (0.40), then go over it, come down behind it (+y) and push it toward the robot (-y) off the front
    edge, where it drops into the bin. When the upright block stands close behind, the push point
    moves along the flat block, away from it. The hand cannot always come down behind the block (wrist
    pitch at its limit): docs/environments.md, 16 of 20 episodes succeed."""
    p, upright = env._xpos("flat_block"), env._xpos("upright_block")
    z = p[2] + 0.03  # fingertips about 5 cm below the end-effector site: just above the desk
    side = np.sign(BIN_X - p[0]) or 1.0  # push toward the bin's x from this end
    end = 0.08 + 0.05  # half the block's length plus the fingers' clearance
    dx = 0.0
    if abs(upright[0] - p[0]) < 0.12 and upright[1] - p[1] < 0.2:
        dx = 0.05 if upright[0] < p[0] else -0.05
    return [
        (np.array([p[0] - side * end, p[1], z + 0.10]), CLOSED, 0.03),
        (np.array([p[0] - side * end, p[1], z]), CLOSED, 0.02),
        (np.array([BIN_X - side * end, p[1], z]), CLOSED, 0.03),
        (np.array([p[0] - side * end, p[1], z + 0.12]), CLOSED, 0.03),
        (np.array([p[0] + dx, p[1] + 0.10, z + 0.12]), CLOSED, 0.03),
        (np.array([p[0] + dx, p[1] + 0.085, z]), CLOSED, 0.025),
        (np.array([p[0] + dx, 0.45, z]), CLOSED, 0.0),
    ]


PLANS = {
    "push_green": _button("green"),
    "push_red": _button("red"),
    "push_blue": _button("blue"),
    "open_slide": _slide,
    "open_drawer": _drawer,
    "upright_block_off_table": _push_off_right("upright_block"),
    "flat_block_in_bin": _flat_block_to_bin,
}


# The box the end-effector site wanders in (m): the desk's width, from the robot's side to the shelf, from
# 8 cm below the desk top (the hand pressed onto it, the arm's joints winding up as an agent's do when
# it pushes down) to 60 cm above it; the agents' own episodes spend their steps there.
WANDER_LOW, WANDER_HIGH = np.array([-0.6, 0.3, DESK_Z - 0.08]), np.array([0.6, 0.9, DESK_Z + 0.6])
# Way-points near a landmark: within 5 cm across, from 5 cm below it (pressing on it) to 15 cm above.
NEAR_LOW, NEAR_HIGH = np.array([-0.05, -0.05, -0.05]), np.array([0.05, 0.05, 0.15])
LANDMARKS = ("green_button", "drawer_handle", "slide_handle", "upright_block", "flat_block", "ball")


def landmark_positions(env) -> dict[str, np.ndarray]:
    """Where each of ``LANDMARKS`` is now (m; copies, not views of the simulator's state)."""
    robodesk = env.unwrapped
    out = {name: robodesk._xpos(name) for name in ("green_button", "upright_block", "flat_block", "ball")}
    out["drawer_handle"] = robodesk.data.geom_xpos[robodesk.model.geom("drawer_handle").id]
    out["slide_handle"] = robodesk.data.site_xpos[robodesk.model.site("slide_handle").id]
    return {name: np.array(where) for name, where in out.items()}


class Wanderer:
    """Exploration data for the GW (pretrain_vae_gw.py --wander-fraction): the hand goes to random
    way-points, each with a random gripper action, and moves on when it is there (2 cm) or after 40
    steps. A share ``near`` of the way-points lies at a random landmark of the desk (the green button,
    the handles, the objects; not the red and blue buttons, whose tasks stay zero-shot), from 5 cm below
    its centre (pressing on it) to 15 cm above, so the data hold the hand near and on things in every
    pose, not only along the experts' paths. The
    wrist turns toward an angle drawn at each way-point, uniformly over its range with a sixth of the
    draws at either end: a learning agent turns it to either end, which neither the experts' paths nor a
    random policy reach
    (docs/pretrain_vae_gw.md). ``noise`` as for the experts."""

    def __init__(self, env: gym.Env, noise: float = 0.3, seed: int | None = None, near: float = 0.4):
        self.wrist_range = env.unwrapped.joint_bounds[6]
        lo, hi = self.wrist_range
        # the wrist action is a change of angle at each of the agent step's frames (envs/robodesk.py):
        # this one holds it still, and each unit away from it turns it by wrist_rate radians per step
        self.wrist_hold = -(lo + hi) / (hi - lo)
        self.wrist_rate = WRIST_SCALE * (hi - lo) / 2 * env.unwrapped.action_repeat
        self.noise, self.near = float(noise), near
        self.rng = np.random.default_rng(seed)
        self.target, self.steps_left, self.grip, self.wrist_target = None, 0, 0.0, None

    def reset(self) -> None:
        self.target = None

    def _landmark(self, env) -> np.ndarray:
        # the green button a third of the time: the paper's RoboDesk task, pressed from every side
        name = "green_button" if self.rng.random() < 1 / 3 else LANDMARKS[1 + self.rng.integers(5)]
        return landmark_positions(env)[name]

    def act(self, env: gym.Env) -> np.ndarray:
        robodesk = env.unwrapped
        ee = robodesk.data.site_xpos[robodesk._ee_site]
        if self.target is None or self.steps_left == 0 or np.linalg.norm(self.target - ee) < 0.02:
            if self.rng.random() < self.near:
                self.target = self._landmark(robodesk) + self.rng.uniform(NEAR_LOW, NEAR_HIGH)
            else:
                self.target = self.rng.uniform(WANDER_LOW, WANDER_HIGH)
            self.grip = float(self.rng.choice([-1.0, 1.0, self.rng.uniform(-1, 1)]))
            lo, hi = self.wrist_range  # uniform, with a sixth of the draws at either end
            self.wrist_target = float(
                np.clip(self.rng.uniform(lo - (hi - lo) / 4, hi + (hi - lo) / 4), lo, hi)
            )
            self.steps_left = 40
        self.steps_left -= 1
        action = np.zeros(5)
        action[:3] = np.clip((self.target - ee) / STEP, -1.0, 1.0)
        turn = 0.5 * (self.wrist_target - robodesk.data.qpos[6]) / self.wrist_rate  # half the way
        action[3], action[4] = np.clip(self.wrist_hold + turn, -1.0, 1.0), self.grip
        action += self.rng.normal(0.0, self.noise, 5)
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def _factory(task: str) -> Callable[..., WaypointExpert]:
    def make(env: gym.Env, noise: float = 0.0, seed: int | None = None) -> WaypointExpert:
        if env.unwrapped.task != task:
            raise ValueError(f"the {task} expert was given a {env.unwrapped.task} environment")
        return WaypointExpert(env, PLANS[task], noise, seed)

    return make


EXPERTS: dict[str, Callable[..., WaypointExpert]] = {task: _factory(task) for task in PLANS}


def reference_returns(
    task: str, episode_length: int = 2000, episodes: int = 10, seed: int = 10_000, cache: Path | None = None
) -> tuple[float, float]:
    """Mean dense returns of a uniformly random policy and of the task's scripted expert (no action noise)
    over ``episodes`` episodes on seeds seed, seed + 1, ...: the 0 and the 1 of the normalised return
    the agent scripts log on RoboDesk (docs/paper_readings.md). Rewards do not depend on images, so the
    episodes run without rendering (about 20 s for both policies on one core). With ``cache`` (a JSON
    file) the figures are read from it when it holds this task and these settings, else measured and
    added to it."""
    from envs.robodesk import RoboDeskEnv

    if task not in EXPERTS:
        raise ValueError(f"no scripted expert for {task!r}; experts exist for {', '.join(EXPERTS)}")
    key = f"{task} episode_length={episode_length} episodes={episodes} seed={seed}"
    table = json.loads(cache.read_text()) if cache is not None and cache.is_file() else {}
    if key in table:
        return tuple(table[key])
    env = RoboDeskEnv(task=task, episode_length=episode_length, render_images=False)
    out = []
    for policy in ("random", "expert"):
        total = 0.0
        for e in range(episodes):
            env.reset(seed=seed + e)
            rng = np.random.default_rng(seed + e)
            expert = EXPERTS[task](env) if policy == "expert" else None
            done = False
            while not done:
                action = rng.uniform(-1, 1, 5) if policy == "random" else expert.act(env)
                _, r, term, trunc, _ = env.step(action)
                total, done = total + r, term or trunc
        out.append(total / episodes)
    env.close()
    if cache is not None:  # written whole, then renamed: a reader never sees half a file
        table[key] = out
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(f".{cache.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(table, indent=1))
        os.replace(tmp, cache)
    return out[0], out[1]
