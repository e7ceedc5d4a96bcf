"""RoboDesk tasks (a Franka Panda arm at a desk) as pixel envs, on this project's MuJoCo and dm_control.

The scene is RoboDesk's (google-research/robodesk 1.0.0, Apache-2.0): its ``desk.xml``, Franka XMLs, meshes and
textures, unchanged, under ``coworld/envs/assets/robodesk``. The env around it is ours; what it does follows
RoboDesk's definitions, as the later CoWorld paper used them (``reward='dense'``, action repeat 1, 500 steps,
64 x 64 frames):

* **Action**: 5-d in [-1, 1] (clipped): end-effector motion ``a[0:3] * 0.01`` m, turned into arm joint targets by
  dm_control's inverse kinematics on joints 1-6; wrist joint 7 moves by ``0.02 * a[3] * 2.9671`` rad; ``a[4]``
  sets both finger targets in [0, 0.04] m. Each agent step holds the joint targets for 10 physics steps of 2 ms
  with gravity compensation (``qfrc_applied = qfrc_bias`` on the arm joints).
* **Reset**: the drawer starts up to 0.10 m open, the slide up to 0.20 m open, the three objects shifted
  within their ranges, the arm at RoboDesk's pose plus 15% of each actuator's range of uniform noise; all drawn
  from this env's seeded generator (RoboDesk draws from NumPy's global one).
* **Frames**: RoboDesk's view (free camera 1.8 m from ``(0, 0.535, 1.1)``, azimuth 90, elevation -60) rendered
  at 120 x 120, cropped to its 88 x 64 box and resized to ``S x S`` with Pillow's Lanczos filter, as RoboDesk
  does; at other sizes the render and the box scale with ``S``. At ``render_quality='full'`` a 64 x 64 frame is
  RoboDesk 1.0.0's frame of the same state, pixel for pixel. The scene has three shadow-casting lights, so
  shadows weigh more than in the other tasks (see :mod:`coworld.envs.render`).
* **Reward**: RoboDesk's dense reward of the task, in [0, 1] per simulator step, as RoboDesk 1.0.0 computes it
  (the package the later paper's code runs). That package records the objects' start positions as views
  of the live positions, so its "other objects did not move" terms always count as met and the "block pushed
  down" term of ``upright_block_off_table`` is always 0; the rewards below are those values. ``reach(p)`` is
  ``clip(1 - |end effector - p|, 0, 1)``.

  - push_green: ``0.25 * pressed + 0.75 * reach(green button)``; pressed: the green light's joint below -0.00453.
  - open_slide: ``0.9 * (0.75 * slide / 0.6 + 0.25 * reach(slide handle - 0.15 x)) + 0.1``.
  - open_drawer: ``0.75 * |drawer| / 0.3 + 0.25 * reach(drawer handle)``.
  - upright_block_off_table: ``0.15 + 0.25 * reach(upright block)``.

  ``info["success"]`` is RoboDesk's success test (pressed; slide > 0.55; drawer < -0.2; the block's height below
  0.6 m), true when met at any simulator step of the agent step. Never terminates; truncates at the episode
  length.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from coworld.envs.base import PixelEnv
from coworld.envs.render import FrameRenderer, ensure_gl_backend

if TYPE_CHECKING:
    from dm_control.mujoco import Physics

    from coworld.envs.spec import EnvSettings, TaskSpec

ASSETS = Path(__file__).parent / "assets" / "robodesk"
"""RoboDesk's scene: ``desk.xml`` and the files it includes."""

TASK_NAMES: dict[str, str] = {
    "robodesk_push_button": "push_green",
    "robodesk_open_slide": "open_slide",
    "robodesk_drawer_open": "open_drawer",
    "robodesk_upright_block_off_table": "upright_block_off_table",
}
"""Our task name -> RoboDesk's task name (its ``task=`` argument; the later paper's ``robodesk_<name>``)."""

ARM_JOINTS = tuple(f"panda0_joint{i}" for i in range(1, 7))
"""The joints the inverse kinematics moves (RoboDesk's)."""

HOME_POSE = np.array([-0.30, -0.4, 0.28, -2.5, 0.13, 1.87, 0.91, 0.01, 0.01])
"""RoboDesk's arm and finger joint positions at reset, before noise."""

END_EFFECTOR_SCALE = 0.01
"""Metres of end-effector motion per unit of action."""
WRIST_SCALE = 0.02
"""Per unit of action the wrist turns this fraction of its control range's half-width (2.9671 rad)."""
PHYSICS_STEPS = 10
"""Physics steps (2 ms each) per simulator step."""

CAMERA_DISTANCE, CAMERA_AZIMUTH, CAMERA_ELEVATION = 1.8, 90.0, -60.0
CAMERA_LOOKAT = (0.0, 0.535, 1.1)
RENDER_SIDE = 120
"""RoboDesk renders 120 x 120 and crops ``CROP`` out of it for a 64 x 64 frame."""
CROP = (25, 89, 17, 105)
"""Rows [25, 89) and columns [17, 105) of the 120 x 120 render: Pillow's rounding of RoboDesk's crop box
``(16.75, 25.0, 105.0, 88.75)``."""

PRESS_DEPTH = -0.00453
"""A button counts as pressed when its light's joint is below this (m)."""


class _IKConvergenceFilter(logging.Filter):
    """Drops dm_control's "Failed to converge" warning of the inverse kinematics.

    Where the target is out of the arm's reach, the solver stops short of it; RoboDesk uses the joint positions it
    reached anyway, and so do we, so the warning says nothing a user can act on. A trained agent's evaluation
    printed it hundreds of times.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.module == "inverse_kinematics" and record.getMessage().startswith("Failed to converge"))


def _quiet_ik_warnings() -> None:
    logger = logging.getLogger("absl")  # where dm_control's absl.logging calls end up
    if not any(isinstance(f, _IKConvergenceFilter) for f in logger.filters):
        logger.addFilter(_IKConvergenceFilter())


class RoboDeskEnv(PixelEnv):
    """One RoboDesk task seen from RoboDesk's camera.

    Observation: ``(S, S, 3)`` uint8 RGB frame. Action: ``(5,)`` float32 in [-1, 1], held for ``action_repeat``
    simulator steps. Reward: sum over those steps of the task's dense reward (each in [0, 1]).
    ``info["success"]``: bool.

    Attributes:
        physics: the dm_control ``Physics`` of the desk (``physics.named.data.qpos['slide_joint']``, ...).
        task: the :class:`~coworld.envs.registry.TaskSpec`; ``settings``: the resolved overrides.
    """

    def __init__(self, task: TaskSpec, settings: EnvSettings, *, seed: int) -> None:
        ensure_gl_backend()
        import mujoco
        from dm_control.mujoco import Physics

        _quiet_ik_warnings()
        super().__init__(task, settings, task.action_size, seed)
        self.robodesk_task = TASK_NAMES[task.name]
        self.physics: Physics = Physics.from_xml_path(str(ASSETS / "desk.xml"))
        # The inverse kinematics moves a second state of the same model, so it never disturbs the simulation.
        self._ik_physics: Physics = self.physics.copy(share_model=True)
        self._ctrl_range = self.physics.model.actuator_ctrlrange.copy()
        self._rng = np.random.default_rng(seed)
        self.metadata = {
            **self.metadata,
            "render_fps": 1.0 / (self.physics.timestep() * PHYSICS_STEPS * settings.action_repeat),
        }
        size = settings.image_size
        scale = size / 64
        side = round(RENDER_SIDE * scale)
        self._crop = tuple(round(edge * scale) for edge in CROP)
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        camera.distance, camera.azimuth, camera.elevation = CAMERA_DISTANCE, CAMERA_AZIMUTH, CAMERA_ELEVATION
        camera.lookat[:] = CAMERA_LOOKAT
        self._renderer = FrameRenderer(
            self.physics.model.ptr, camera=camera, size=side, quality=settings.render_quality
        )

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode with object and arm positions drawn from the episode's seed
        (:class:`~coworld.envs.base.PixelEnv`)."""
        seed = self._episode_seed(seed)
        super().reset(seed=seed)
        self.reset_state(seed)
        self._frame = self._render()
        return self._frame, {"success": False}

    def reset_state(self, seed: int | None = None) -> None:
        """:meth:`reset` without drawing a frame (for policies that read the state, and return measurements)."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        rng, physics = self._rng, self.physics
        physics.reset()
        qpos = physics.named.data.qpos
        # RoboDesk's ranges, drawn in its order.
        qpos["drawer_joint"] -= 0.10 * rng.random()
        qpos["slide_joint"] += 0.20 * rng.random()
        qpos["flat_block"][0] += 0.3 * rng.random()
        qpos["flat_block"][1] += 0.07 * rng.random()
        qpos["ball"][0] += 0.48 * rng.random()
        qpos["ball"][1] += 0.08 * rng.random()
        qpos["upright_block"][0] += 0.3 * rng.random() + 0.05
        qpos["upright_block"][1] += 0.05 * rng.random()
        arm = len(HOME_POSE)
        noise = rng.uniform(self._ctrl_range[:arm, 0], self._ctrl_range[:arm, 1])
        physics.data.qpos[:arm] = HOME_POSE + 0.15 * noise
        physics.data.qvel[:arm] = 0.0
        physics.forward()
        self._ik_physics.data.qpos[:] = physics.data.qpos
        self._start_episode()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        reward, truncated, success = self.simulate(action)
        self._frame = self._render()
        return self._frame, reward, False, truncated, {"success": success}

    def simulate(self, action: np.ndarray) -> tuple[float, bool, bool]:
        """:meth:`step` without drawing a frame: ``(reward, truncated, success)``."""
        action = self._checked(action, np.float32)
        action = np.clip(action, -1.0, 1.0).astype(np.float64)
        physics = self.physics
        reward, success = 0.0, False
        for _ in range(self.settings.action_repeat):
            target = self._joint_targets(action)
            for _ in range(PHYSICS_STEPS):
                physics.data.ctrl[:] = target
                physics.data.qfrc_applied[: len(target)] = physics.data.qfrc_bias[: len(target)]
                physics.step()
            self._ik_physics.data.qpos[:] = physics.data.qpos
            step_reward, step_success = task_reward(physics, self.robodesk_task)
            reward += step_reward
            success = success or step_success
        truncated = self._count_step()
        return reward, truncated, success

    def _joint_targets(self, action: np.ndarray) -> np.ndarray:
        """Position targets of the 9 actuators (7 arm joints, 2 fingers) for one simulator step."""
        from dm_control.utils.inverse_kinematics import qpos_from_site_pose

        position = self.physics.named.data.site_xpos["end_effector"] + action[:3] * END_EFFECTOR_SCALE
        solved = qpos_from_site_pose(self._ik_physics, "end_effector", position, joint_names=ARM_JOINTS, inplace=True)
        target = np.array(solved.qpos[: len(HOME_POSE)])
        low, high = self._ctrl_range[6]
        wrist = self.physics.data.qpos[6] + WRIST_SCALE * _to_range(action[3], low, high)
        target[6] = np.clip(wrist, low, high)
        target[7] = target[8] = _to_range(action[4], *self._ctrl_range[7])
        return target

    def _render(self) -> np.ndarray:
        from PIL import Image

        top, bottom, left, right = self._crop
        view = self._renderer.render(self.physics.data.ptr)[top:bottom, left:right]
        size = self.settings.image_size
        return np.asarray(Image.fromarray(view).resize((size, size), resample=Image.Resampling.LANCZOS))

    def close(self) -> None:
        self._renderer.close()


def _to_range(value: float, low: float, high: float) -> float:
    """Map ``value`` in [-1, 1] linearly onto [low, high]."""
    return (value + 1.0) * (high - low) / 2.0 + low


def _reach(physics: Physics, point: np.ndarray) -> float:
    """1 at the end effector, falling linearly to 0 at 1 m from it."""
    distance = np.linalg.norm(physics.named.data.site_xpos["end_effector"] - point)
    return float(np.clip(1.0 - distance, 0.0, 1.0))


def task_reward(physics: Physics, task: str) -> tuple[float, bool]:
    """RoboDesk's dense reward in [0, 1] and its success test for RoboDesk task ``task`` in the current state."""
    data = physics.named.data
    if task == "push_green":
        pressed = bool(data.qpos["green_light"][0] < PRESS_DEPTH)
        reward = 0.25 * pressed + 0.75 * _reach(physics, data.xpos["green_button"])
        success = pressed
    elif task == "open_slide":
        slide = float(data.qpos["slide_joint"][0])
        handle = data.site_xpos["slide_handle"] - np.array([0.15, 0.0, 0.0])
        reward = 0.9 * (0.75 * slide / 0.6 + 0.25 * _reach(physics, handle)) + 0.1
        success = slide > 0.55
    elif task == "open_drawer":
        drawer = float(data.qpos["drawer_joint"][0])
        reward = 0.75 * abs(drawer) / 0.3 + 0.25 * _reach(physics, data.geom_xpos["drawer_handle"])
        success = drawer < -0.2
    elif task == "upright_block_off_table":
        reward = 0.15 + 0.25 * _reach(physics, data.xpos["upright_block"])
        success = bool(data.qpos["upright_block"][2] < 0.6)
    else:
        raise ValueError(f"no RoboDesk task {task!r}; known: {', '.join(TASK_NAMES.values())}")
    return float(np.clip(reward, 0.0, 1.0)), bool(success)


def make_robodesk(task: TaskSpec, settings: EnvSettings, seed: int) -> RoboDeskEnv:
    """Build the RoboDesk task ``task.name``."""
    return RoboDeskEnv(task, settings, seed=seed)
