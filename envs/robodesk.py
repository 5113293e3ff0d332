"""RoboDesk (Kannan et al. 2021) on the ``mujoco`` bindings and gymnasium, without dm_control or gym.

Paper, section "Environments / RoboDesk": a Franka Panda arm at a desk with a sliding door, a drawer,
three buttons with lights, two blocks, a ball, a bin and a shelf. Behaviour follows the original
(google-research/robodesk) unless stated; the scene (desk.xml, the Franka XML, meshes and textures) is
the one shipped in the ``robodesk==1.0.0`` package, installed with ``pip install --no-deps
robodesk==1.0.0`` and found without importing it (its ``__init__`` imports dm_control).

Action (5 values in [-1, 1]): end-effector position delta (x 0.01 m) reached by inverse kinematics on
joints 1-6, wrist rotation, gripper opening. Each agent action is applied ``action_repeat`` times, each
time as one joint-position control held for 10 physics steps with gravity compensation. The episode
lasts ``episode_length`` physics-control repeats (paper: 2000 with action_repeat 4, i.e. 500 agent steps)
and never terminates early: it is truncated at the limit.

Observation ``{"image": uint8 (64, 64, 3), "attr": float32 (76,)}``; attr = robot qpos (9), robot qvel
(9), end-effector position (3), object qpos (29), object qvel (26). The original returns the object qvel
in place of the object qpos (a bug); the true qpos gives the paper's 76 dimensions.

Reference-position defect of the original (reproduced by default, ``frozen_reference=False``): it keeps
the objects' reset positions as live views of the simulator state, so they follow the objects. Then
"did not move" always holds and the lift and off-table progress terms of the dense rewards stay 0. The
paper's numbers were obtained with that behaviour. ``frozen_reference=True`` freezes the reference
positions at reset, which gives the rewards the original meant.
"""

from __future__ import annotations

import importlib.util
import os
import signal
from functools import partial
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; must be set before mujoco is imported

import gymnasium as gym  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

INSTALL_HINT = "pip install --no-deps robodesk==1.0.0"
CORE_TASKS = (
    "open_slide",
    "open_drawer",
    "push_green",
    "stack",
    "upright_block_off_table",
    "flat_block_in_bin",
    "flat_block_in_shelf",
    "lift_upright_block",
    "lift_ball",
)
EXTRA_TASKS = (
    "push_blue",
    "push_red",
    "flat_block_off_table",
    "ball_off_table",
    "upright_block_in_bin",
    "ball_in_bin",
    "upright_block_in_shelf",
    "ball_in_shelf",
    "lift_flat_block",
)
TASKS = CORE_TASKS + EXTRA_TASKS
REWARD_MODES = ("dense", "sparse", "success")
RENDER_QUALITIES = ("faithful", "fast")
OBJECTS = ("flat_block", "upright_block", "ball")
ATTR_DIM = 76
N_ROBOT_JOINTS = 9
IK_JOINTS = tuple(f"panda0_joint{i}" for i in range(1, 7))
END_EFFECTOR_SCALE = 0.01  # metres per unit of action
WRIST_SCALE = 0.02
INIT_ROBOT_QPOS = np.array([-0.30, -0.4, 0.28, -2.5, 0.13, 1.87, 0.91, 0.01, 0.01])
# Camera of the original: free camera, 120x120 render, crop box, antialiased resize.
CAMERA = {"distance": 1.8, "azimuth": 90.0, "elevation": -60.0, "lookat": (0.0, 0.535, 1.1)}
RENDER_SIZE = 120
CROP_BOX = (16.75, 25.0, 105.0, 88.75)  # (left, upper, right, lower), rounded to whole pixels like PIL


def scene_path() -> Path:
    """Path of desk.xml in the installed robodesk package (located without importing the package)."""
    spec = importlib.util.find_spec("robodesk")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(f"RoboDesk scene not found: install it with `{INSTALL_HINT}`")
    path = Path(list(spec.submodule_search_locations)[0]) / "assets" / "desk.xml"
    if not path.is_file():
        raise FileNotFoundError(f"RoboDesk scene missing at {path}: reinstall it with `{INSTALL_HINT}`")
    return path


def load_model(arena_mib: int = 16) -> mujoco.MjModel:
    """The desk scene with its arena sized to what it uses. The XML's njmax/nconmax of 2000 would give
    every MjData a ~208 MiB arena under mujoco >= 3; ``arena_mib`` MiB covered 5,000 steps with room."""
    spec = mujoco.MjSpec.from_file(str(scene_path()))
    spec.njmax, spec.nconmax, spec.memory = -1, -1, arena_mib * 2**20
    return spec.compile()


# --------------------------------------------------------------------------------------------------
# Image pipeline: crop and antialiased (Lanczos) resize with Pillow's arithmetic, in numpy.
# --------------------------------------------------------------------------------------------------
def _lanczos(x: np.ndarray) -> np.ndarray:
    return np.where(np.abs(x) < 3.0, np.sinc(x) * np.sinc(x / 3.0), 0.0)


# MuJoCo's joint limits are soft: under load a joint passes its range (in 150,000 samples of the CPU
# pre-training data by up to 0.083 rad for a hinge and 6.6 mm for a slide). The bounds add three times that.
SOFT_LIMIT_MARGIN = {int(mujoco.mjtJoint.mjJNT_HINGE): 0.25, int(mujoco.mjtJoint.mjJNT_SLIDE): 0.02}


def qpos_bounds(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of every qpos entry: a limited joint's range widened by SOFT_LIMIT_MARGIN, a free body's
    quaternion [-1, 1], anything else (a free body's position) unbounded."""
    low, high = np.full(model.nq, -np.inf, np.float32), np.full(model.nq, np.inf, np.float32)
    for j in range(model.njnt):
        adr, kind = model.jnt_qposadr[j], int(model.jnt_type[j])
        if kind == int(mujoco.mjtJoint.mjJNT_FREE):
            low[adr + 3 : adr + 7], high[adr + 3 : adr + 7] = -1.0, 1.0
        elif model.jnt_limited[j] and kind in SOFT_LIMIT_MARGIN:
            low[adr], high[adr] = model.jnt_range[j] + np.array([-1, 1]) * SOFT_LIMIT_MARGIN[kind]
    return low, high


def lanczos_matrix(in_size: int, out_size: int) -> np.ndarray:
    """Integer resampling weights (out_size, in_size) of Pillow's Lanczos filter, 22-bit fixed point
    (Pillow's 8-bit path): support 3 pixels widened by the scale, weights normalised then rounded."""
    bits = 22
    scale = in_size / out_size
    filterscale = max(scale, 1.0)
    support = 3.0 * filterscale
    weights = np.zeros((out_size, in_size), dtype=np.int64)
    for xx in range(out_size):
        center = (xx + 0.5) * scale
        xmin = max(int(center - support + 0.5), 0)
        xmax = min(int(center + support + 0.5), in_size)
        k = _lanczos((np.arange(xmin, xmax) - center + 0.5) / filterscale)
        k = k / k.sum() if k.sum() != 0 else k
        # C's (int) cast after adding +-0.5 rounds half away from zero.
        weights[xx, xmin:xmax] = np.trunc(k * (1 << bits) + np.where(k < 0, -0.5, 0.5)).astype(np.int64)
    return weights


def _resample(image: np.ndarray, weights: np.ndarray, axis: int) -> np.ndarray:
    bits = 22
    acc = np.tensordot(image.astype(np.int64), weights, axes=([axis], [1]))
    acc = np.moveaxis(acc, -1, axis) + (1 << (bits - 1))
    return np.clip(acc >> bits, 0, 255).astype(np.uint8)


class ImageResizer:
    """Crop the 120x120 render to the original's box and resize it to ``size`` like Pillow's
    ``Image.crop(box).resize((size, size), LANCZOS)`` (horizontal pass first, 8-bit in between)."""

    def __init__(self, size: int):
        self.left, self.top, self.right, self.bottom = (int(round(v)) for v in CROP_BOX)
        w, h = self.right - self.left, self.bottom - self.top
        self.size = size
        self.wx = lanczos_matrix(w, size) if w != size else None
        self.wy = lanczos_matrix(h, size) if h != size else None

    def __call__(self, render: np.ndarray) -> np.ndarray:
        image = render[self.top : self.bottom, self.left : self.right]
        if self.wx is not None:
            image = _resample(image, self.wx, axis=1)
        if self.wy is not None:
            image = _resample(image, self.wy, axis=0)
        return np.ascontiguousarray(image)


class RoboDeskEnv(gym.Env):
    """RoboDesk as a gymnasium environment (see the module docstring).

    Args:
        task: one of ``TASKS`` (paper: push_green).
        reward: ``dense`` (task reward clipped to [0, 1], summed over repeats), ``sparse`` (success
            summed over repeats) or ``success`` (1 the first time the task succeeds).
        action_repeat: controls per agent step (paper: 4).
        episode_length: episode length in physics-control repeats (paper: 2000 = 500 agent steps).
        image_size: side of the square image observation.
        render_images: False drops the image from the observation (attributes only, much faster).
        render_quality: ``faithful`` reproduces the original's image; ``fast`` turns off shadows,
            reflections and multisampling (documented difference, several times faster on a CPU).
        frozen_reference: False reproduces the original's live reference positions (the paper's
            rewards); True freezes them at reset (the corrected rewards).
        arena_mib: MuJoCo arena per MjData, in MiB.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        task: str = "push_green",
        reward: str = "dense",
        action_repeat: int = 4,
        episode_length: int = 2000,
        image_size: int = 64,
        render_images: bool = True,
        render_quality: str = "faithful",
        frozen_reference: bool = False,
        render_mode: str | None = None,
        arena_mib: int = 16,
    ):
        if task not in TASKS:
            raise ValueError(f"unknown RoboDesk task {task!r}; valid tasks: {', '.join(TASKS)}")
        if reward not in REWARD_MODES:
            raise ValueError(f"unknown reward mode {reward!r}; valid modes: {', '.join(REWARD_MODES)}")
        if render_quality not in RENDER_QUALITIES:
            raise ValueError(f"render_quality must be one of {RENDER_QUALITIES}, got {render_quality!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if action_repeat < 1 or episode_length < action_repeat:
            raise ValueError("need action_repeat >= 1 and episode_length >= action_repeat")
        self.task, self.reward_mode = task, reward
        self.action_repeat, self.episode_length = int(action_repeat), int(episode_length)
        self.image_size, self.render_images = int(image_size), bool(render_images)
        self.render_quality, self.frozen_reference = render_quality, bool(frozen_reference)
        self.render_mode = render_mode

        self.model = load_model(arena_mib)
        self.data = mujoco.MjData(self.model)
        self._scratch = mujoco.MjData(self.model)  # IK runs here, never on the simulated state
        self.joint_bounds = self.model.actuator_ctrlrange.copy()
        self._ik_dofs = np.array([self.model.joint(j).dofadr[0] for j in IK_JOINTS])
        self._ee_site = self.model.site("end_effector").id

        self.action_space = spaces.Box(-1.0, 1.0, (5,), dtype=np.float32)
        self.qpos_low, self.qpos_high = qpos_bounds(self.model)
        attr_low, attr_high = np.full(ATTR_DIM, -np.inf, np.float32), np.full(ATTR_DIM, np.inf, np.float32)
        qpos_attrs = np.r_[0:N_ROBOT_JOINTS, 21:50]  # where attr holds qpos (robot, then objects)
        attr_low[qpos_attrs], attr_high[qpos_attrs] = self.qpos_low, self.qpos_high
        obs = {"attr": spaces.Box(attr_low, attr_high, (ATTR_DIM,), dtype=np.float32)}
        if self.render_images:
            obs = {"image": spaces.Box(0, 255, (image_size, image_size, 3), dtype=np.uint8)} | obs
        self.observation_space = spaces.Dict(obs)

        self._renderer: mujoco.Renderer | None = None
        self._camera = mujoco.MjvCamera()
        mujoco.mjv_defaultFreeCamera(self.model, self._camera)
        self._camera.distance = CAMERA["distance"]
        self._camera.azimuth = CAMERA["azimuth"]
        self._camera.elevation = CAMERA["elevation"]
        self._camera.lookat[:] = CAMERA["lookat"]
        self._resize = ImageResizer(self.image_size)

        self._reward_fns = {
            "open_slide": self._slide_reward,
            "open_drawer": self._drawer_reward,
            "push_green": lambda kind: self._button_reward("green", kind),
            "push_blue": lambda kind: self._button_reward("blue", kind),
            "push_red": lambda kind: self._button_reward("red", kind),
            "stack": self._stack_reward,
        }
        for obj in OBJECTS:
            self._reward_fns[f"{obj}_off_table"] = lambda kind, o=obj: self._push_off_table(o, kind)
            self._reward_fns[f"{obj}_in_bin"] = lambda kind, o=obj: self._put_in_bin(o, kind)
            self._reward_fns[f"{obj}_in_shelf"] = lambda kind, o=obj: self._put_in_shelf(o, kind)
            self._reward_fns[f"lift_{obj}"] = lambda kind, o=obj: self._lift_block(o, kind)
        self._reference: dict[str, np.ndarray] = {}
        self._num_steps = 0
        self._succeeded = False
        self._started = False

    # ---------------------------------------------------------------------------------------------
    # Gymnasium API
    # ---------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        if options and ("qpos" in options or "qvel" in options):
            qpos = np.asarray(options.get("qpos", m.qpos0), dtype=np.float64)
            qvel = np.asarray(options.get("qvel", np.zeros(m.nv)), dtype=np.float64)
            self._check_state(qpos, qvel)
            d.qpos[:], d.qvel[:] = qpos, qvel
        else:
            # Random initial state of the original, drawn from the env's seeded generator.
            rng = self.np_random
            self._qpos("drawer_joint")[0] -= 0.10 * rng.random()
            self._qpos("slide_joint")[0] += 0.20 * rng.random()
            self._qpos("flat_block")[0] += 0.3 * rng.random()
            self._qpos("flat_block")[1] += 0.07 * rng.random()
            self._qpos("ball")[0] += 0.48 * rng.random()
            self._qpos("ball")[1] += 0.08 * rng.random()
            self._qpos("upright_block")[0] += 0.3 * rng.random() + 0.05
            self._qpos("upright_block")[1] += 0.05 * rng.random()
            bounds = m.actuator_ctrlrange[:N_ROBOT_JOINTS]
            d.qpos[:N_ROBOT_JOINTS] = INIT_ROBOT_QPOS + 0.15 * rng.uniform(bounds[:, 0], bounds[:, 1])
            d.qvel[:N_ROBOT_JOINTS] = 0.0
        mujoco.mj_forward(m, d)
        self._scratch.qpos[:] = d.qpos
        # The original stores live views (the defect); frozen copies give the intended rewards.
        for obj in OBJECTS:
            view = d.xpos[m.body(obj).id]
            self._reference[obj] = view.copy() if self.frozen_reference else view
        self._num_steps, self._succeeded, self._started = 0, False, True
        return self._obs(), self._info()

    def step(self, action):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        if self._num_steps >= self.episode_length:  # gymnasium leaves stepping past the end undefined
            raise RuntimeError("the episode has ended (truncated): call reset() before step()")
        action = self._check_action(action)
        m, d = self.model, self.data
        total = 0.0
        for _ in range(self.action_repeat):
            target = self._convert_action(action)
            for _ in range(10):
                d.ctrl[:N_ROBOT_JOINTS] = target
                d.qfrc_applied[:N_ROBOT_JOINTS] = d.qfrc_bias[:N_ROBOT_JOINTS]  # gravity compensation
                # dm_control's Physics.step: mj_step2 then mj_step1, leaving derived quantities
                # (site positions, bias forces) up to date with the new state.
                mujoco.mj_step2(m, d)
                mujoco.mj_step1(m, d)
            self._scratch.qpos[:] = d.qpos
            if self.reward_mode == "dense":
                total += self.task_reward("dense")
            elif self.reward_mode == "sparse":
                total += self.task_reward("success")
            elif not self._succeeded:  # "success": reward once per episode
                self._succeeded = bool(self.task_reward("success"))
                total += float(self._succeeded)
        self._num_steps += self.action_repeat
        truncated = self._num_steps >= self.episode_length
        return self._obs(), float(total), False, truncated, self._info()

    def render(self):
        if self.render_mode == "rgb_array":
            return self.render_image()
        return None

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def set_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Set the full simulator state (as gymnasium's MuJoCo envs do); episode counters are kept. A qpos
        outside ``qpos_bounds`` is refused."""
        qpos, qvel = np.asarray(qpos, dtype=np.float64), np.asarray(qvel, dtype=np.float64)
        self._check_state(qpos, qvel)
        self.data.qpos[:], self.data.qvel[:] = qpos, qvel
        mujoco.mj_forward(self.model, self.data)
        self._scratch.qpos[:] = self.data.qpos

    # ---------------------------------------------------------------------------------------------
    # Control: inverse kinematics and action conversion
    # ---------------------------------------------------------------------------------------------
    def inverse_kinematics(self, target: np.ndarray) -> np.ndarray:
        """Joint positions that put the end-effector site at ``target``, moving joints 1-6 only.

        Gauss-Newton on the site Jacobian from the current scratch state, as dm_control's
        ``qpos_from_site_pose`` (our own code, same constants): damped least squares (strength 3e-2)
        while the error exceeds 0.1 m, the minimum-norm least-squares step below; updates capped at norm 2;
        stop at error 1e-14, after 100 iterations, or when error / update exceeds 20 (no progress).
        Only the kinematics are recomputed between iterations (no collision detection is needed).
        """
        m, d = self.model, self._scratch
        jacp = np.zeros((3, m.nv))
        update = np.zeros(m.nv)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        for _ in range(100):
            err = target - d.site_xpos[self._ee_site]
            err_norm = np.linalg.norm(err)
            if err_norm < 1e-14:
                break
            mujoco.mj_jacSite(m, d, jacp, None, self._ee_site)
            jac = jacp[:, self._ik_dofs]
            if err_norm > 0.1:
                dq = np.linalg.solve(jac.T @ jac + 3e-2 * np.eye(len(self._ik_dofs)), jac.T @ err)
            else:  # minimum-norm solution J^T (J J^T)^-1 err (J has full row rank away from singularities)
                dq = jac.T @ np.linalg.solve(jac @ jac.T, err)
            dq_norm = np.linalg.norm(dq)
            if err_norm / dq_norm > 20.0:
                break
            if dq_norm > 2.0:
                dq *= 2.0 / dq_norm
            update[self._ik_dofs] = dq
            mujoco.mj_integratePos(m, d.qpos, update, 1.0)
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
        return d.qpos[:N_ROBOT_JOINTS].copy()

    def _to_range(self, value: float, joint: int) -> float:
        lo, hi = self.joint_bounds[joint]
        return (value + 1.0) * (hi - lo) / 2.0 + lo

    def _convert_action(self, action: np.ndarray) -> np.ndarray:
        """Action in [-1, 1]^5 -> joint position targets of the 9 actuators (original's mapping)."""
        target = self.data.site_xpos[self._ee_site] + action[:3] * END_EFFECTOR_SCALE
        joints = self.inverse_kinematics(target)
        # Wrist: a step of 0.02 x (action mapped onto the joint's range) from the current angle.
        wrist = WRIST_SCALE * self._to_range(action[3], 6) + self.data.qpos[6]
        joints[6] = np.clip(wrist, *self.joint_bounds[6])
        joints[7] = joints[8] = self._to_range(action[4], 7)  # gripper fingers, absolute
        return joints

    # ---------------------------------------------------------------------------------------------
    # Observations
    # ---------------------------------------------------------------------------------------------
    def render_image(self) -> np.ndarray:
        """The image observation: 120x120 render from the original's camera, cropped and resized."""
        if self._renderer is None:
            if self.render_quality == "fast":
                self.model.vis.quality.offsamples = 0  # read when the GL context is created
            self._renderer = mujoco.Renderer(self.model, RENDER_SIZE, RENDER_SIZE)
            if self.render_quality == "fast":
                self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
                self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._renderer.update_scene(self.data, self._camera)
        return self._resize(self._renderer.render())

    def attributes(self) -> np.ndarray:
        d, n = self.data, N_ROBOT_JOINTS
        ee = d.site_xpos[self._ee_site]
        return np.concatenate([d.qpos[:n], d.qvel[:n], ee, d.qpos[n:], d.qvel[n:]]).astype(np.float32)

    def _obs(self) -> dict[str, np.ndarray]:
        obs = {"attr": self.attributes()}
        if self.render_images:
            obs = {"image": self.render_image()} | obs
        return obs

    def _info(self) -> dict:
        return {"success": bool(self.task_reward("success")), "num_steps": self._num_steps}

    # ---------------------------------------------------------------------------------------------
    # Rewards (original's definitions; every value is clipped to [0, 1])
    # ---------------------------------------------------------------------------------------------
    def task_reward(self, kind: str = "dense") -> float:
        """Dense reward (``kind="dense"``) or success (``kind="success"``) of the task now."""
        return float(np.clip(self._reward_fns[self.task](kind), 0.0, 1.0))

    def _qpos(self, joint: str) -> np.ndarray:
        j = self.model.joint(joint)
        size = {0: 7, 1: 4, 2: 1, 3: 1}[int(j.type[0])]
        return self.data.qpos[j.qposadr[0] : j.qposadr[0] + size]

    def _xpos(self, body: str) -> np.ndarray:
        return self.data.xpos[self.model.body(body).id]

    def _did_not_move(self, obj: str) -> bool:
        return bool(np.linalg.norm(self._xpos(obj) - self._reference[obj]) < 0.01)

    def _total_movement(self, obj: str, max_dist: float = 5.0) -> float:
        return float(np.linalg.norm(self._xpos(obj) - self._reference[obj]) / max_dist)

    def _dist_reward(self, pos: np.ndarray, max_dist: float = 1.0) -> float:
        dist = np.linalg.norm(self.data.site_xpos[self._ee_site] - pos)
        return float(np.clip(1 - dist / max_dist, 0.0, 1.0))

    def _slide_reward(self, kind):
        if kind == "success":
            return float(self._qpos("slide_joint")[0] > 0.55)
        door = self._qpos("slide_joint")[0] / 0.6
        handle = self.data.site_xpos[self.model.site("slide_handle").id] - np.array([0.15, 0.0, 0.0])
        still = sum(w * self._did_not_move(o) for w, o in zip((0.33, 0.33, 0.34), OBJECTS, strict=True))
        return 0.9 * (0.75 * door + 0.25 * self._dist_reward(handle)) + 0.1 * still

    def _drawer_reward(self, kind):
        if kind == "success":
            return float(self._qpos("drawer_joint")[0] < -0.2)
        handle = self.data.geom_xpos[self.model.geom("drawer_handle").id]
        return 0.75 * abs(self._qpos("drawer_joint")[0]) / 0.3 + 0.25 * self._dist_reward(handle)

    def _button_reward(self, colour, kind):
        pressed = float(self._qpos(f"{colour}_light")[0] < -0.00453)
        if kind == "success":
            return pressed
        return 0.25 * pressed + 0.75 * self._dist_reward(self._xpos(f"{colour}_button"))

    def _stack_reward(self, kind):
        offset = self._xpos("upright_block") - self._xpos("flat_block")
        diff = np.linalg.norm(np.array([0.0, 0.0, 0.0377804]) - offset)
        if kind == "success":
            return float(diff < 0.04)
        return -diff + self._dist_reward(self._xpos("upright_block"))

    def _push_off_table(self, obj, kind):
        others = [o for o in OBJECTS if o != obj]
        if kind == "success":
            return float(
                self._qpos(obj)[2] < 0.6 and self._did_not_move(others[0]) and self._did_not_move(others[1])
            )
        pushed = 1 - self._xpos(obj)[2] / self._reference[obj][2]
        stay = [1 - self._total_movement(o) for o in others]
        progress = np.clip(0.8 * pushed + 0.1 * stay[0] + 0.1 * stay[1], 0.0, 1.0)
        return 0.75 * progress + 0.25 * self._dist_reward(self._xpos(obj))

    def _put_in_bin(self, obj, kind):
        x, y, z = self._xpos(obj)
        success = float(0.28 < x < 0.52 and 0.38 < y < 0.62 and 0 < z < 0.4)
        if kind == "success":
            return success
        return 0.5 * self._dist_reward(self._xpos(obj)) + 0.5 * success

    def _put_in_shelf(self, obj, kind):
        pos = self._xpos(obj)
        success = float(pos[0] > 0.2 and pos[1] > 1.0)
        if kind == "success":
            return success
        others = [o for o in OBJECTS if o != obj]
        block_dist = 1 - np.linalg.norm(np.array([0.4, 1.1]) - pos[:2])
        in_shelf = 0.33 * self._dist_reward(pos) + 0.33 * block_dist + 0.34 * success
        stay = [1 - self._total_movement(o) for o in others]
        return 0.5 * in_shelf + 0.25 * stay[0] + 0.25 * stay[1]

    def _lift_block(self, obj, kind):
        z = self._xpos(obj)[2]
        if kind == "success":
            return float(z > {"upright_block": 0.86, "ball": 0.81, "flat_block": 0.78}[obj])
        lifted = np.clip((z - self._reference[obj][2]) * 10, 0.0, 1.0)
        return 0.85 * lifted + 0.15 * self._dist_reward(self._xpos(obj))

    # ---------------------------------------------------------------------------------------------
    # Input checks
    # ---------------------------------------------------------------------------------------------
    def _check_action(self, action) -> np.ndarray:
        try:
            a = np.asarray(action, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(f"RoboDesk actions are 5 floats in [-1, 1], got {action!r}") from None
        if a.shape != (5,) or not np.all(np.isfinite(a)):
            raise ValueError(f"RoboDesk actions are 5 finite floats in [-1, 1], got {action!r}")
        if np.any(np.abs(a) > 1.0 + 1e-6):
            raise ValueError(f"RoboDesk action out of [-1, 1]: {a}; clip it or squash it with tanh")
        return np.clip(a, -1.0, 1.0)

    def _check_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        if qpos.shape != (self.model.nq,) or qvel.shape != (self.model.nv,):
            raise ValueError(
                f"RoboDesk state needs qpos of shape ({self.model.nq},) and qvel of shape "
                f"({self.model.nv},), got {qpos.shape} and {qvel.shape}"
            )
        if not (np.all(np.isfinite(qpos)) and np.all(np.isfinite(qvel))):
            raise ValueError("RoboDesk state contains non-finite values")
        out = np.flatnonzero((qpos < self.qpos_low) | (qpos > self.qpos_high))
        if len(out):
            i = out[0]
            raise ValueError(
                f"RoboDesk qpos[{i}] = {qpos[i]:g} is outside [{self.qpos_low[i]:g}, {self.qpos_high[i]:g}] "
                "(its joint's range with the soft-limit margin, or a quaternion's [-1, 1])"
            )


# -------------------------------------------------------------------------------------------------
# Vector environments
# -------------------------------------------------------------------------------------------------
def make_vector_env(num_envs: int, processes: bool = False, **kwargs) -> gym.vector.VectorEnv:
    """``num_envs`` RoboDesk environments (``kwargs`` of ``RoboDeskEnv``, made by ``gym.make``) stepped
    together with same-step autoreset (``info["final_obs"]`` holds an ended episode's last observation).

    ``processes=True`` steps each in its own spawned process (gymnasium's ``AsyncVectorEnv``), so that the
    simulators and renderers, most of an agent step's time, run side by side on several cores; the
    observations, rewards and infos are those of the in-process ``SyncVectorEnv``. The processes ignore
    Ctrl-C, which only the training loop's process answers (its run is saved, then the envs closed)."""
    fns = [partial(_make_env, processes, kwargs) for _ in range(num_envs)]
    mode = gym.vector.AutoresetMode.SAME_STEP
    if processes:
        return gym.vector.AsyncVectorEnv(fns, context="spawn", autoreset_mode=mode)
    return gym.vector.SyncVectorEnv(fns, autoreset_mode=mode)


def _make_env(in_worker: bool, kwargs: dict) -> gym.Env:
    if in_worker:  # a spawned process (which imported envs, registering RoboDesk-v0, to unpickle this)
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C in a terminal reaches the process group
    return gym.make("RoboDesk-v0", **kwargs)
