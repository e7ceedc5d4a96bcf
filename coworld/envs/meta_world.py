"""Meta-World v3 manipulation tasks as pixel envs.

Each task is Meta-World's own environment class (``metaworld.env_dict.ALL_V3_ENVIRONMENTS``) with the object
and goal positions drawn afresh at every reset from the env's seeded RNG (the usual setting of Dreamer-family
pixel agents; Meta-World's benchmarks instead pick one of 50 pre-drawn positions). Frames come from the
``corner2`` camera moved to ``(0.75, 0.075, 0.7)``, the close-up view used by Dreamer-family Meta-World wrappers,
turned 180 degrees so the table is upright. Action: 4-d (end-effector xyz motion, gripper) in [-1, 1].

Episodes last 500 simulator steps (Meta-World's ``max_path_length``), i.e. 500 agent steps at the default action
repeat of 1; rewards are Meta-World's v2 reward (0 to 10 per step, so a return is at most 5000). ``info["success"]``
is True when the task was solved at any simulator step of the agent step. Never terminates on success;
truncates at the episode length.

Rendering uses this env's own OpenGL context (see :mod:`coworld.envs.render`), so several envs can live in one
process and closing one leaves the others rendering.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from coworld.envs.base import PixelEnv
from coworld.envs.render import FrameRenderer, ensure_gl_backend

if TYPE_CHECKING:
    from metaworld.sawyer_xyz_env import SawyerXYZEnv

    from coworld.envs.spec import EnvSettings, TaskSpec

CAMERA = "corner2"
CAMERA_POS = (0.75, 0.075, 0.7)

ENV_NAMES: dict[str, str] = {
    "mw_window_close": "window-close-v3",
    "mw_handle_press": "handle-press-v3",
    "mw_drawer_close": "drawer-close-v3",
    "mw_stick_push": "stick-push-v3",
    "mw_door_close": "door-close-v3",
    "mw_button_press_topdown": "button-press-topdown-v3",
    "mw_button_press": "button-press-v3",
    "mw_assembly": "assembly-v3",
}
"""Our task name -> Meta-World environment name."""


class MetaWorldEnv(PixelEnv):
    """A Meta-World task seen from the ``corner2`` camera.

    Observation: ``(S, S, 3)`` uint8 RGB frame. Action: ``(4,)`` float32 in [-1, 1], held for ``action_repeat``
    simulator steps. Reward: sum over those steps. ``info["success"]``: bool.

    Attributes:
        sim: the underlying Meta-World environment (MuJoCo ``model`` / ``data``, ``_get_pos_objects()``, ...).
        task: the :class:`~coworld.envs.registry.TaskSpec`; ``settings``: the resolved overrides.
    """

    def __init__(self, task: TaskSpec, settings: EnvSettings, *, seed: int) -> None:
        ensure_gl_backend()
        import mujoco
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS

        super().__init__(task, settings, task.action_size, seed)
        sim: SawyerXYZEnv = ALL_V3_ENVIRONMENTS[ENV_NAMES[task.name]]()  # no gymnasium renderer: we draw frames
        # Fresh positions at each reset from sim.np_random (what the goal-observable constructors set up before
        # freezing them); these are Meta-World attributes without a public setter.
        sim._set_task_called = True
        sim._freeze_rand_vec = False
        sim.seeded_rand_vec = True
        sim.max_path_length = settings.episode_length * settings.action_repeat
        sim.seed(seed)
        self.sim = sim
        # Frames per second of simulated time, one frame per agent step (80 at action repeat 1).
        self.metadata = {**self.metadata, "render_fps": 1.0 / (sim.dt * settings.action_repeat)}
        camera = mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA)
        sim.model.cam_pos[camera] = CAMERA_POS
        self._renderer = FrameRenderer(
            sim.model, camera=camera, size=settings.image_size, quality=settings.render_quality, rotate_180=True
        )

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode with object/goal positions drawn from the episode's seed
        (:class:`~coworld.envs.base.PixelEnv`)."""
        import mujoco

        seed = self._episode_seed(seed)
        super().reset(seed=seed)
        self.sim.seed(seed)
        self.sim.reset()
        mujoco.mj_forward(self.sim.model, self.sim.data)  # reset moves goal sites after the last forward pass
        self._start_episode()
        self._frame = self._renderer.render(self.sim.data)
        return self._frame, {"success": False}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        action = self._checked(action, np.float32)
        reward, success = 0.0, False
        for _ in range(self.settings.action_repeat):
            _, step_reward, _, _, info = self.sim.step(action)
            reward += float(step_reward)
            success = success or bool(info["success"])
        truncated = self._count_step()
        self._frame = self._renderer.render(self.sim.data)
        return self._frame, reward, False, truncated, {"success": success}

    def close(self) -> None:
        self._renderer.close()
        self.sim.close()


def make_metaworld(task: TaskSpec, settings: EnvSettings, seed: int) -> MetaWorldEnv:
    """Build the Meta-World task ``task.name``."""
    return MetaWorldEnv(task, settings, seed=seed)
