"""Scripted expert policies, and the returns they reach on our tasks (the reference returns' stand-ins).

Meta-World ships a scripted policy per task (``metaworld.policies``) that reads the simulator state; the toy
tasks have :meth:`~coworld.envs.toy.ToyReachEnv.expert_action`. :func:`expert_returns` runs one of them on our
task setup (Meta-World: positions drawn afresh at each reset from the seeded RNG, 500 steps, action repeat 1)
without drawing frames, episode ``i`` seeded ``i``. ``benchmarks/reference_returns.py`` prints the table that
:mod:`coworld.envs.registry` records.
"""

from __future__ import annotations

import numpy as np

from coworld.envs.registry import make, task_spec
from coworld.errors import ConfigError

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


def expert_returns(task: str, episodes: int) -> tuple[list[float], list[bool] | None]:
    """Returns (and, on Meta-World, successes) of the task's scripted expert over ``episodes`` seeded episodes."""
    family = task_spec(task).family
    if family == "metaworld":
        return _metaworld(task, episodes)
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
