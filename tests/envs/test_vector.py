"""make_vector: worker processes, per-env seeds, NEXT_STEP autoreset, SIGINT, how many workers make sense."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from coworld.envs import make, make_vector
from coworld.errors import ConfigError, UnknownTaskError


def test_two_toy_workers_seed_and_autoreset() -> None:
    envs = make_vector("toy_reach", 2, seed=3, episode_length=4)
    try:
        obs, _ = envs.reset()
        assert obs.shape == (2, 64, 64, 3) and obs.dtype == np.uint8
        for i in range(2):  # env i is make(name, seed + i)
            np.testing.assert_array_equal(obs[i], make("toy_reach", seed=3 + i, episode_length=4).reset()[0])
        actions = np.zeros((2, 2), np.float32)
        truncated = [envs.step(actions)[3].tolist() for _ in range(4)]
        assert truncated == [[False, False]] * 3 + [[True, True]]
        # NEXT_STEP: the following step resets and returns the new episode's first frame with reward 0
        obs, reward, terminated, truncated, _ = envs.step(np.ones((2, 2), np.float32))
        assert reward.tolist() == [0.0, 0.0] and not terminated.any() and not truncated.any()
        second = make("toy_reach", seed=3, episode_length=4)
        second.reset()
        np.testing.assert_array_equal(obs[0], second.reset()[0])  # the second start of env 0's seed stream
    finally:
        envs.close()


def test_two_walker_workers_render_their_own_episodes() -> None:
    envs = make_vector("walker_walk", 2, seed=0, image_size=32)
    try:
        obs, _ = envs.reset()
        # a worker renders exactly what this process renders for the same seed
        np.testing.assert_array_equal(obs[1], make("walker_walk", seed=1, image_size=32).reset()[0])
        for _ in range(3):
            obs, reward, *_ = envs.step(np.zeros((2, 6), np.float32))
        assert obs.shape == (2, 32, 32, 3) and obs.std() > 10
        assert not np.array_equal(obs[0], obs[1])
        assert reward.shape == (2,)
    finally:
        envs.close()


def test_workers_overrides_where_the_envs_step() -> None:
    one_in_a_worker = make_vector("toy_reach", 1, seed=5, workers=True)
    two_here = make_vector("toy_reach", 2, seed=5, workers=False)
    try:
        assert len(one_in_a_worker.processes) == 1 and one_in_a_worker.processes[0].is_alive()
        assert not hasattr(two_here, "processes")
        np.testing.assert_array_equal(one_in_a_worker.reset()[0][0], two_here.reset()[0][0])  # the same env 0
    finally:
        one_in_a_worker.close()
        two_here.close()


def test_bad_input_raises_in_the_caller() -> None:
    with pytest.raises(UnknownTaskError):
        make_vector("nope", 2)
    with pytest.raises(ConfigError, match="unknown env override"):
        make_vector("toy_reach", 2, colour="red")
    with pytest.raises(ConfigError, match="num_envs"):
        make_vector("toy_reach", 0)
    single = make_vector("toy_reach", 1, seed=5)
    assert single.reset()[0].shape == (1, 64, 64, 3)
    single.close()


def test_workers_ignore_sigint_so_a_terminal_ctrl_c_does_not_break_a_step() -> None:
    venv = make_vector("toy_reach", 2, seed=0)
    try:
        venv.reset(seed=0)
        for process in venv.processes:  # what a Ctrl-C in a terminal does to the whole process group
            os.kill(process.pid, signal.SIGINT)
        time.sleep(0.5)
        obs, *_ = venv.step(np.zeros((2, *venv.single_action_space.shape), np.float32))
        assert obs.shape[0] == 2 and all(process.is_alive() for process in venv.processes)
    finally:
        venv.close()
    assert not any(process.is_alive() for process in venv.processes)


def test_workers_are_capped_by_episodes_and_cores(monkeypatch) -> None:
    import coworld.envs.vector as vector

    monkeypatch.setattr(vector, "available_cores", lambda: 4)
    assert vector.sensible_workers(2, episodes=10) == (2, "")
    assert vector.sensible_workers(1000, episodes=2) == (
        2,
        "--workers 1000 capped to 2: one per episode (2 episodes asked for)",
    )
    assert vector.sensible_workers(1000, episodes=1) == (
        1,
        "--workers 1000 capped to 1: one per episode (1 episode asked for)",
    )
    assert vector.sensible_workers(1000) == (4, "--workers 1000 capped to 4: one per CPU core (4 cores available)")
    assert vector.sensible_workers(8, episodes=100) == (
        4,
        "--workers 8 capped to 4: one per CPU core (4 cores available)",
    )
