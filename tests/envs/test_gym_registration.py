"""Every task under a Gymnasium id (`coworld/<task>-v0`), made by gymnasium.make and passed by its env checker."""

from __future__ import annotations

import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from coworld.envs import TASKS, env_id
from coworld.errors import ConfigError

# One task of each family runs in the fast suite; every task runs in the slow one (Meta-World renders slowly). RoboDesk
# is slow only: its checker draws for 25-28 s in software (measured on the shared 2-core machine);
# tests/envs/test_robodesk.py builds a RoboDesk task through its Gymnasium id in the fast suite.
FAST = ("toy_reach", "walker_uphill", "mw_button_press")
# Frames per second of simulated time at one frame per agent step: DMC's control timestep x action repeat
# (walker 0.025 s x 2, cheetah 0.01 s x 2), Meta-World's 0.0125 s x 1, RoboDesk's 10 x 0.002 s x 1; the toy has no
# clock.
RENDER_FPS = {"toy": 10, "walker": 20, "cheetah": 50, "mw": 80, "robodesk": 50}


def test_every_task_is_registered_without_building_it() -> None:
    for name in TASKS:
        spec = gym.spec(f"coworld/{name}-v0")
        assert spec.id == env_id(name) and spec.namespace == "coworld" and spec.version == 0
        assert spec.entry_point == "coworld.envs.gym_registration:make_env" and spec.kwargs == {"task": name}
        assert spec.max_episode_steps is None  # the envs truncate themselves after episode_length
    assert sum(1 for key in gym.registry if key.startswith("coworld/")) == len(TASKS)


def _check(name: str) -> None:
    env = gym.make(env_id(name))
    task = TASKS[name]
    assert env.observation_space == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    assert env.action_space == gym.spaces.Box(-1, 1, (task.action_size,), np.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)  # Gymnasium's full check, render and close checks included
    assert not caught, [str(w.message) for w in caught]  # the render fps declared, nothing else to warn about
    assert env.metadata["render_fps"] == pytest.approx(RENDER_FPS[name.split("_")[0]])
    frame, _ = env.reset(seed=0)
    assert frame.std() > 10  # a real picture
    for _ in range(3):
        frame, reward, terminated, truncated, _ = env.step(env.action_space.sample())
    assert isinstance(reward, float) and not terminated and not truncated
    env.close()


@pytest.mark.parametrize("name", FAST)
def test_gymnasium_make_passes_the_env_checker(name: str) -> None:
    _check(name)


@pytest.mark.slow
@pytest.mark.parametrize("name", [name for name in TASKS if name not in FAST])
def test_every_task_passes_the_env_checker(name: str) -> None:
    _check(name)


def test_make_kwargs_reach_coworld_make() -> None:
    env = gym.make("coworld/toy_reach-v0", seed=3, image_size=32, episode_length=4)
    assert env.observation_space.shape == (32, 32, 3) and env.unwrapped.settings.episode_length == 4
    same = gym.make("coworld/toy_reach-v0", seed=3, image_size=32)
    np.testing.assert_array_equal(env.reset()[0], same.reset()[0])  # the seed reaches coworld.envs.make
    for _ in range(4):
        *_, truncated, _ = env.step(env.action_space.sample())
    assert truncated
    with pytest.raises(ConfigError, match="render rgb_array only"), pytest.warns(UserWarning, match="render_modes"):
        gym.make("coworld/toy_reach-v0", render_mode="depth_array")


def test_plain_gymnasium_finds_the_ids_through_the_module_prefix() -> None:
    """Without importing coworld first, `coworld.envs:` in the id imports the module that registers the tasks."""
    code = (
        "import gymnasium as gym\n"
        "assert not any(k.startswith('coworld/') for k in gym.registry)\n"
        "env = gym.make('coworld.envs:coworld/toy_reach_shifted-v0')\n"
        "print(env.unwrapped.task.name, env.reset(seed=0)[0].shape)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "toy_reach_shifted (64, 64, 3)"
