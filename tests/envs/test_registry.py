"""The task table, pairs, names and overrides (no simulator needed except where a test builds an env)."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from coworld.envs import PAIRS, TASKS, make, task_spec
from coworld.errors import ConfigError, UnknownTaskError

PAPER_PAIRS = {
    ("walker_walk", "walker_downhill"),
    ("walker_walk", "walker_uphill"),
    ("walker_walk", "walker_nofoot"),
    ("cheetah_run", "cheetah_downhill"),
    ("cheetah_run", "cheetah_uphill"),
    ("cheetah_run", "cheetah_nopaw"),
    ("mw_window_close", "mw_door_close"),
    ("mw_handle_press", "mw_button_press_topdown"),
    ("mw_drawer_close", "mw_handle_press"),
    ("mw_drawer_close", "mw_button_press"),
    ("mw_stick_push", "mw_assembly"),
}


LATER_PAPER_PAIRS = {
    ("mw_button_press", "robodesk_push_button"),
    ("mw_window_close", "robodesk_open_slide"),
    ("mw_drawer_close", "robodesk_drawer_open"),
    ("mw_handle_press", "robodesk_upright_block_off_table"),
}


def test_pairs_are_the_papers_plus_two_toy_pairs() -> None:
    assert PAPER_PAIRS | LATER_PAPER_PAIRS < set(PAIRS)
    toys = set(PAIRS) - PAPER_PAIRS - LATER_PAPER_PAIRS
    assert toys == {("toy_reach", "toy_reach_shifted"), ("toy_reach_centre", "toy_reach_centre_shifted")}
    for source, target in set(PAIRS) - LATER_PAPER_PAIRS:
        a, b = TASKS[source], TASKS[target]
        assert (a.family, a.action_size, a.action_repeat) == (b.family, b.action_size, b.action_repeat)
    for source, target in LATER_PAPER_PAIRS:  # across environments: Meta-World's 4-d sources, RoboDesk's 5-d targets
        a, b = TASKS[source], TASKS[target]
        assert (a.family, a.action_size, b.family, b.action_size) == ("metaworld", 4, "robodesk", 5)


def test_spec_fields_are_consistent() -> None:
    for name, task in TASKS.items():
        assert task.name == name
        assert (task.modification == "") == (
            task.name in {"walker_walk", "cheetah_run", "toy_reach"} or task.family in ("metaworld", "robodesk")
        )
        if task.family == "dmc":
            assert task.episode_length * task.action_repeat == 1000
        assert task.reference_return is not None and task.reference_source
        if task.random_return is not None:
            assert 0 <= task.random_return < task.medium_return  # a medium dataset is better than random


def test_the_medium_level_is_a_third_of_the_reference_unless_random_scores_more() -> None:
    for task in TASKS.values():
        third = task.reference_return / 3
        if task.random_return is None or task.random_return < third:
            assert task.medium_return == pytest.approx(third)
    centre = TASKS["toy_reach_centre_shifted"]  # random 18.3 is above a third of 48.4
    assert centre.medium_return == pytest.approx(18.3 + (48.4 - 18.3) / 3)


def test_reference_returns_name_their_provenance() -> None:
    # published DreamerV2 scores for the plain DMC tasks; the modified ones say they borrow them
    assert (TASKS["walker_walk"].reference_return, TASKS["cheetah_run"].reference_return) == (964.9, 816.1)
    for name in ("walker_downhill", "walker_uphill", "walker_nofoot"):
        assert TASKS[name].reference_return == 964.9 and "walker_walk" in TASKS[name].reference_source
    for name in ("cheetah_downhill", "cheetah_uphill", "cheetah_nopaw"):
        assert TASKS[name].reference_return == 816.1 and "cheetah_run" in TASKS[name].reference_source
    for task in TASKS.values():
        if task.family == "metaworld":
            assert "no published DreamerV2" in task.reference_source


def test_unknown_task_lists_the_valid_ones() -> None:
    with pytest.raises(UnknownTaskError) as info:
        task_spec("walker_run")
    message = str(info.value)
    assert "\n" not in message and message.startswith("unknown task 'walker_run'; valid tasks: walker_walk,")
    assert all(name in message for name in TASKS)
    with pytest.raises(UnknownTaskError):
        make("walker_run")


@pytest.mark.parametrize(
    "name, overrides, match",
    [
        ("toy_reach", {"camera": 1}, "unknown env override 'camera' for toy_reach; valid overrides: image_size"),
        ("toy_reach", {"render_quality": "fast"}, "unknown env override 'render_quality'"),
        ("toy_reach", {"image_size": 0}, "image_size takes a positive integer"),
        ("toy_reach", {"action_repeat": 2.5}, "action_repeat takes a positive integer"),
        ("toy_reach", {"episode_length": "ten"}, "episode_length takes a positive integer"),
        ("toy_reach", {"action_repeat": 51}, "exceeds toy_reach's 50 simulator steps"),
        ("walker_walk", {"render_quality": "ultra"}, "render_quality must be one of standard, fast, full"),
    ],
)
def test_bad_overrides_raise_one_line(name: str, overrides: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        make(name, **overrides)
    assert "\n" not in str(info.value)


def test_overrides_from_strings_and_defaults() -> None:
    env = make("toy_reach", seed=0, image_size="32", action_repeat=2)
    assert env.observation_space.shape == (32, 32, 3)
    assert env.unwrapped.settings.episode_length == 25
    assert make("toy_reach", episode_length=7, action_repeat=2).unwrapped.settings.episode_length == 7


def test_importing_envs_loads_no_simulator() -> None:
    code = (
        "import sys, coworld.envs, coworld.commands.tasks\n"
        "print(sorted(m for m in ('mujoco', 'dm_control', 'metaworld', 'torch') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("name", ["toy_reach", "cheetah_nopaw", "mw_button_press"])
def test_gymnasium_env_checker(name: str) -> None:
    env = make(name, seed=0)
    check_env(env, skip_render_check=True)
    assert env.observation_space == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    assert env.action_space == gym.spaces.Box(-1, 1, (TASKS[name].action_size,), np.float32)
    env.close()


@pytest.mark.parametrize("name", [name for name, task in TASKS.items() if task.family != "metaworld"])
def test_every_dmc_and_toy_task_renders(name: str) -> None:
    env = make(name, seed=0)
    frame, _ = env.reset()
    assert frame.shape == (64, 64, 3) and frame.dtype == np.uint8
    assert frame.std() > 10 and len(np.unique(frame.reshape(-1, 3), axis=0)) > 20
    env.close()


@pytest.mark.parametrize("name", ["toy_reach", "walker_walk", "mw_button_press", "robodesk_push_button"])
def test_every_family_refuses_a_step_outside_an_episode_and_an_action_of_another_shape(name: str) -> None:
    """Each family's env: no step before reset() nor after the time limit, actions of the action space's shape
    only, an episode of exactly ``episode_length`` steps truncated (never terminated), and ``render()`` a copy of
    the latest frame."""
    env = make(name, seed=0, episode_length=3).unwrapped
    action = np.zeros(env.action_space.shape, np.float32)
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(action)
    env.reset()
    with pytest.raises(ValueError, match=rf"{name} takes actions of shape \({TASKS[name].action_size},\)"):
        env.step(np.zeros(TASKS[name].action_size + 1, np.float32))
    ends = [env.step(action)[2:4] for _ in range(3)]
    assert ends == [(False, False), (False, False), (False, True)]
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(action)
    frame = env.render()
    frame[:] = 0
    assert env.render().any()  # the env's own frame is untouched
    env.reset()
    assert env.step(action)[3] is False  # a new episode runs
    env.close()


@pytest.mark.parametrize(
    "name",
    ["toy_reach", "cheetah_run", "mw_button_press", pytest.param("robodesk_push_button", marks=pytest.mark.slow)],
)
def test_every_familys_episode_is_a_function_of_its_seed_and_actions(name: str) -> None:
    """The third episode of a chain of ``reset()`` calls is made again by an env whose history differs, reset with that
    episode's seed and given the same actions (what an online run's exact resume relies on); the chain's episodes
    differ from each other."""
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (4, TASKS[name].action_size)).astype(np.float32)

    def episode(env: gym.Env, seed: int | None) -> list[np.ndarray]:
        frames = [env.reset(seed=seed)[0]]
        return frames + [env.step(action)[0] for action in actions]

    first = make(name, seed=3, episode_length=4)
    chain = [episode(first, None) for _ in range(3)]
    seed = first.unwrapped.episode_seed
    other = make(name, seed=11, episode_length=4)
    episode(other, None)  # another history before it
    again = episode(other, seed)
    assert other.unwrapped.episode_seed == seed
    assert all(np.array_equal(a, b) for a, b in zip(chain[2], again, strict=True))
    assert not np.array_equal(chain[0][0], chain[1][0]) or not np.array_equal(chain[1][0], chain[2][0])
    first.close()
    other.close()
