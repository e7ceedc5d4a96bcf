import numpy as np

from coworld.training.replay import Replay


def _episode(length, offset, action_size=2):
    steps = length + 1
    return {
        "image": np.full((steps, 4, 4, 3), 0, np.uint8)
        + (np.arange(steps) + offset)[:, None, None, None].astype(np.uint8),
        "action": np.zeros((steps, action_size), np.float32),
        "reward": (np.arange(steps) + offset).astype(np.float32),
        "is_first": np.arange(steps) == 0,
        "is_last": np.arange(steps) == steps - 1,
        "is_terminal": np.zeros(steps, bool),
    }


def test_windows_are_contiguous_inside_episodes():
    replay = Replay(seed=0)
    replay.add_episode(_episode(20, 0))
    replay.add_episode(_episode(30, 100))
    batch = replay.sample(64, 8)
    assert batch["image"].shape == (64, 8, 4, 4, 3)
    diffs = np.diff(batch["reward"], axis=1)
    assert np.all(diffs == 1)  # consecutive steps, never across an episode seam
    assert not batch["is_first"][:, 1:].any()


def test_short_episodes_continue_with_is_first_at_the_seam():
    replay = Replay(seed=0)
    for i in range(3):
        replay.add_episode(_episode(3, 10 * i))
    batch = replay.sample(16, 10)
    for row in range(16):
        rewards, first = batch["reward"][row], batch["is_first"][row]
        for t in range(1, 10):
            assert first[t] or rewards[t] == rewards[t - 1] + 1


def test_add_step_assembles_episodes_per_env():
    replay = Replay()
    episode = _episode(4, 0)
    finished = None
    for t in range(5):
        for env in (0, 1):
            step = {k: v[t] for k, v in episode.items()}
            out = replay.add_step(env, step)
            finished = out if out is not None else finished
    assert len(replay.episodes) == 2 and replay.num_steps == 10
    np.testing.assert_array_equal(finished["reward"], episode["reward"])


def test_capacity_drops_oldest():
    replay = Replay(capacity=25)
    for i in range(4):
        replay.add_episode(_episode(9, 10 * i))
    assert replay.num_steps <= 25 and replay.episodes[-1]["reward"][0] == 30
