"""Scripted expert policies, and the returns they reach on our tasks (the reference returns' stand-ins).

Meta-World ships a scripted policy per task (``metaworld.policies``) that reads the simulator state; the toy
tasks have :meth:`~coworld.envs.toy.ToyReachEnv.expert_action`; RoboDesk ships none, so :data:`ROBODESK_WAYPOINTS`
are ours: the end effector visits a few points set by the objects' current positions, one after the other, and
holds the last (it presses the button; on the slide, drawer and block tasks it reaches what the dense reward
measures and pushes or pulls, without solving them reliably). :func:`expert_returns` runs one of them on our task
setup (Meta-World: positions drawn afresh at each reset from the seeded RNG, 500 steps, action repeat 1) without
drawing frames, episode ``i`` seeded ``i``. ``benchmarks/reference_returns.py`` prints the table that
:mod:`coworld.envs.registry` records.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from coworld.envs.registry import make, task_spec
from coworld.errors import ConfigError

if TYPE_CHECKING:
    from coworld.envs.robodesk import RoboDeskEnv

METAWORLD_POLICIES = {
    "mw_window_close": "SawyerWindowCloseV3Policy",
    "mw_handle_press": "SawyerHandlePressV3Policy",
    "mw_drawer_close": "SawyerDrawerCloseV3Policy",
    "mw_stick_push": "SawyerStickPushV3Policy",
    "mw_door_close": "SawyerDoorCloseV3Policy",
    "mw_button_press_topdown": "SawyerButtonPressTopdownV3Policy",
    "mw_button_press": "SawyerButtonPressV3Policy",
    "mw_assembly": "SawyerAssemblyV3Policy",
}
"""Our Meta-World task -> its scripted policy class in ``metaworld.policies``."""


Waypoint = tuple[str, str, tuple[float, float, float], float]
"""(data field, name, offset in m, gripper action): the point ``physics.named.data.<field>[name] + offset``, and
``a[4]`` on the way there (-1 closes the fingers, 1 opens them)."""

ROBODESK_WAYPOINTS: dict[str, tuple[Waypoint, ...]] = {
    "robodesk_push_button": (
        ("xpos", "green_button", (0.0, 0.0, 0.12), -1.0),
        ("xpos", "green_button", (0.0, 0.0, -0.05), -1.0),
    ),
    "robodesk_open_slide": (
        ("site_xpos", "slide_handle", (-0.05, -0.08, -0.04), -1.0),
        ("site_xpos", "slide_handle", (-0.05, 0.0, -0.04), -1.0),
        ("site_xpos", "slide_handle", (0.10, 0.0, -0.04), -1.0),
    ),
    "robodesk_drawer_open": (  # the drawer's handle bar is 0.36 m in front of and 0.01 m above the drawer's origin
        ("xpos", "drawer", (0.0, -0.39, 0.11), 1.0),
        ("xpos", "drawer", (0.0, -0.39, 0.01), 1.0),
        ("xpos", "drawer", (0.0, -0.51, 0.01), -1.0),
    ),
    "robodesk_upright_block_off_table": (
        ("xpos", "upright_block", (-0.08, 0.0, 0.10), -1.0),
        ("xpos", "upright_block", (-0.08, 0.0, -0.03), -1.0),
        ("xpos", "upright_block", (0.15, 0.0, -0.03), -1.0),
    ),
}
"""Our scripted RoboDesk policies: waypoints of the end effector (RoboDesk's frame: x right, y away from the
robot, z up)."""

WAYPOINT_REACHED = 0.015
"""Distance (m) at which the end effector moves on to the next waypoint."""


def expert_returns(task: str, episodes: int) -> tuple[list[float], list[bool] | None]:
    """Returns (and, where the task reports it, successes) of the task's scripted expert over seeded episodes."""
    family = task_spec(task).family
    if family == "metaworld":
        return _metaworld(task, episodes)
    if family == "robodesk":
        return _robodesk(task, episodes)
    if family == "toy":
        return _toy(task, episodes), None
    raise ConfigError(f"{task} has no scripted expert (DMC tasks have none); see `coworld tasks` for its reference")


def _metaworld(task: str, episodes: int) -> tuple[list[float], list[bool]]:
    import warnings

    import metaworld.policies
    import mujoco

    env = make(task, seed=0)
    sim = env.unwrapped.sim
    with warnings.catch_warnings():  # the policies warn that their gains exceed the action bounds (clipped below)
        warnings.simplefilter("ignore", UserWarning)
        policy = getattr(metaworld.policies, METAWORLD_POLICIES[task])()
    returns, successes = [], []
    try:
        for episode in range(episodes):
            sim.seed(episode)  # what env.reset(seed=episode) does, without drawing a frame
            obs, _ = sim.reset()
            mujoco.mj_forward(sim.model, sim.data)
            total, success = 0.0, False
            for _ in range(env.unwrapped.settings.episode_length):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)
                    action = np.clip(policy.get_action(obs), -1.0, 1.0)
                obs, reward, _, _, info = sim.step(action)
                total += float(reward)
                success = success or bool(info["success"])
            returns.append(total)
            successes.append(success)
    finally:
        env.close()
    return returns, successes


def robodesk_expert_action(env: RoboDeskEnv, task: str, stage: int) -> tuple[np.ndarray, int]:
    """The waypoint policy's action in the current state of a RoboDesk env, and the waypoint it now heads for.

    Moves the end effector straight at waypoint ``stage`` (at most 1 cm, the action's reach, per step) and
    advances ``stage`` once within :data:`WAYPOINT_REACHED` of it (the last waypoint is held).
    """
    from coworld.envs.robodesk import END_EFFECTOR_SCALE

    waypoints = ROBODESK_WAYPOINTS[task]
    data = env.physics.named.data
    effector = data.site_xpos["end_effector"]

    def point(index: int) -> np.ndarray:
        field, name, offset, _ = waypoints[index]
        return getattr(data, field)[name] + np.asarray(offset)

    if stage < len(waypoints) - 1 and np.linalg.norm(point(stage) - effector) < WAYPOINT_REACHED:
        stage += 1
    action = np.zeros(5, np.float32)
    action[:3] = np.clip((point(stage) - effector) / END_EFFECTOR_SCALE, -1.0, 1.0)
    action[4] = waypoints[stage][3]
    return action, stage


def _robodesk(task: str, episodes: int) -> tuple[list[float], list[bool]]:
    env = make(task, seed=0, image_size=8, render_quality="fast")
    sim = env.unwrapped
    returns, successes = [], []
    try:
        for episode in range(episodes):
            sim.reset_state(episode)  # what env.reset(seed=episode) does, without drawing a frame
            total, success, stage, truncated = 0.0, False, 0, False
            while not truncated:
                action, stage = robodesk_expert_action(sim, task, stage)
                reward, truncated, step_success = sim.simulate(action)
                total += reward
                success = success or step_success
            returns.append(total)
            successes.append(success)
    finally:
        env.close()
    return returns, successes


def robodesk_random_returns(task: str, episodes: int) -> list[float]:
    """Returns of uniform random actions on a RoboDesk task without drawing frames, as every task's random return is
    measured: episode ``i`` is ``reset(seed=i)`` with actions ``numpy.random.default_rng(i).uniform(-1, 1)``."""
    env = make(task, seed=0, image_size=8, render_quality="fast")
    sim = env.unwrapped
    returns = []
    try:
        for episode in range(episodes):
            sim.reset_state(episode)
            rng = np.random.default_rng(episode)
            total, truncated = 0.0, False
            while not truncated:
                reward, truncated, _ = sim.simulate(rng.uniform(-1, 1, sim.action_space.shape).astype(np.float32))
                total += reward
            returns.append(total)
    finally:
        env.close()
    return returns


def _toy(task: str, episodes: int) -> list[float]:
    env = make(task, seed=0)
    returns = []
    try:
        for episode in range(episodes):
            env.reset(seed=episode)
            total, done = 0.0, False
            while not done:
                _, reward, terminated, truncated, _ = env.step(env.unwrapped.expert_action())
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
    finally:
        env.close()
    return returns
