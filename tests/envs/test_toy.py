"""The NumPy toy pair: pixels show the state, the recorded returns hold, the shift is real."""

from __future__ import annotations

import numpy as np
import pytest

from coworld.envs import make, task_spec
from coworld.envs.toy import CENTRE_GOAL, GOAL, SPEED


def episode_return(env, policy) -> float:
    total, done = 0.0, False
    while not done:
        _, reward, terminated, truncated, _ = env.step(policy())
        assert 0.0 <= reward <= 1.0
        total += reward
        done = terminated or truncated
    return total


@pytest.mark.parametrize(
    "name", ["toy_reach", "toy_reach_shifted", "toy_reach_centre", "toy_reach_centre_shifted", "toy_reach_shifted_act3"]
)
def test_recorded_returns_and_a_clear_gap(name: str) -> None:
    """Re-measure the TaskSpec's returns exactly as recorded (200 episodes, seeds 0-199, env seed 0)."""
    env = make(name, seed=0)
    random, expert = [], []
    for seed in range(200):
        env.reset(seed=seed)
        random.append(episode_return(env, env.action_space.sample))
    for seed in range(200):
        env.reset(seed=seed)
        expert.append(episode_return(env, env.unwrapped.expert_action))
    spec = task_spec(name)
    assert np.mean(random) == pytest.approx(spec.random_return, abs=0.05)
    assert np.mean(expert) == pytest.approx(spec.reference_return, abs=0.05)
    assert spec.reference_return > 2 * spec.random_return
    assert max(expert) < 50  # starts are outside the goal


@pytest.mark.parametrize("name", ["toy_reach_centre", "toy_reach_centre_shifted"])
def test_no_constant_action_scores_on_the_centre_tasks(name: str) -> None:
    """With the goal at the centre every constant direction ends at a wall: the best of 16 stays below random."""
    env = make(name, seed=0)
    best = 0.0
    for angle in np.linspace(0, 2 * np.pi, 16, endpoint=False):
        direction = np.array([np.cos(angle), np.sin(angle)], np.float32)
        totals = []
        for seed in range(20):
            env.reset(seed=seed)
            totals.append(episode_return(env, lambda d=direction: d))
        best = max(best, float(np.mean(totals)))
    assert best < 0.6 * task_spec(name).random_return


def test_the_dot_is_read_from_the_frame() -> None:
    env = make("toy_reach", seed=0)
    frame, _ = env.reset()
    dot = np.array([230, 60, 50])
    near = np.abs(frame.astype(int) - dot).sum(-1) < 30
    rows, cols = np.nonzero(near)
    x = (cols.mean() + 0.5) / 64 * 2 - 1
    y = 1 - (rows.mean() + 0.5) / 64 * 2
    np.testing.assert_allclose([x, y], env.unwrapped.position, atol=0.05)
    # moving right by one step moves the drawn dot right by SPEED * 32 = 3.2 pixels
    moved = env.step(np.array([1.0, 0.0], np.float32))[0]
    cols_after = np.nonzero(np.abs(moved.astype(int) - dot).sum(-1) < 30)[1]
    assert cols_after.mean() - cols.mean() == pytest.approx(SPEED * 32, abs=0.5)


def test_seeds_and_starts() -> None:
    a, b, c = make("toy_reach", seed=1), make("toy_reach", seed=1), make("toy_reach", seed=2)
    np.testing.assert_array_equal(a.reset()[0], b.reset()[0])
    assert not np.array_equal(a.reset(seed=1)[0], c.reset()[0])
    starts = []
    for _ in range(50):
        a.reset()
        starts.append(a.unwrapped.position)
    distances = np.linalg.norm(np.array(starts) - GOAL, axis=1)
    assert np.all(distances >= 0.6)
    assert np.array(starts).std(0).min() > 0.3  # spread over the box
    centre = make("toy_reach_centre", seed=1)
    for _ in range(50):
        centre.reset()
        assert np.linalg.norm(centre.unwrapped.position - CENTRE_GOAL) >= 0.6


def test_the_centre_pair_draws_and_rewards_its_goal_at_the_centre() -> None:
    corner, centre = make("toy_reach", seed=0), make("toy_reach_centre", seed=0)
    goal_colour = np.array([40, 160, 70])
    for env, inside, outside in ((corner, GOAL, CENTRE_GOAL), (centre, CENTRE_GOAL, GOAL)):
        frame = env.reset()[0]
        is_goal = np.abs(frame.astype(int) - goal_colour).sum(-1) < 30
        for point, expected in ((inside, True), (outside, False)):
            col, row = int((point[0] + 1) / 2 * 64), int((1 - point[1]) / 2 * 64)
            assert is_goal[row, col] == expected
        assert env.unwrapped.reward(np.asarray(inside)) == 1.0
        assert env.unwrapped.reward(np.asarray(outside)) < 0.6


def test_shift_changes_colours_and_dynamics() -> None:
    plain, shifted = make("toy_reach", seed=0), make("toy_reach_shifted", seed=0)
    frame_plain, frame_shifted = plain.reset()[0], shifted.reset()[0]
    np.testing.assert_array_equal(plain.unwrapped.position, shifted.unwrapped.position)  # same start
    assert np.abs(frame_plain.astype(int) - frame_shifted).mean() > 50
    still = np.zeros(2, np.float32)
    for _ in range(5):
        plain.step(still)
        shifted.step(still)
    start = plain.unwrapped.position
    assert shifted.unwrapped.position[0] < start[0] - 0.1  # drifted left
    assert shifted.unwrapped.position[1] == start[1]
