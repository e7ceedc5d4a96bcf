"""Helpers of the dataset tests: episodes with recognisable frames, and a fake pixel task for collection.

Loaded by path (``tests/conftest.py`` and the subprocess scripts of ``tests/processes.py`` and ``test_crash.py``),
since tests are no package.
Frames carry their own identity: pixel (0, 0, 0) is the step j within the episode, pixels (0, 0, 1) and (0, 0, 2)
are the episode id (low and high byte), so a test can tell which step of which episode any frame is.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from coworld.data import DatasetWriter
from coworld.envs import TaskSpec

IMAGE = (64, 64, 3)
ACTION_SIZE = 3
WRITER_ARGS: dict[str, Any] = {
    "task": "fake_task",
    "env_config": {"action_repeat": 2, "image_size": 64, "camera": "tracking"},
    "collector": {"algorithm": "random", "seed": 0},
    "action_size": ACTION_SIZE,
    "reference": {"random_return": 0.0, "reference_return": 10.0},
}


def make_episode(rng: np.random.Generator, length: int, episode_id: int, terminated: bool = False) -> dict[str, Any]:
    """One episode of ``length`` rows: frames (length+1, 64, 64, 3) tagged with (step, episode id), random rest."""
    frames = np.zeros((length + 1, *IMAGE), np.uint8)
    frames[:, 8:16, 8:16] = rng.integers(0, 256, (length + 1, 8, 8, 3), dtype=np.uint8)
    frames[:, 0, 0, 0] = np.arange(length + 1) % 256
    frames[:, 0, 0, 1] = episode_id % 256
    frames[:, 0, 0, 2] = episode_id // 256
    return {
        "observations": frames,
        "actions": rng.uniform(-1, 1, (length, ACTION_SIZE)).astype(np.float32),
        "rewards": rng.normal(size=length).astype(np.float32),
        "terminated": terminated,
        "infos": {
            "success": rng.random(length) < 0.3,
            "behavior_log_prob": rng.normal(size=length).astype(np.float32),
        },
    }


def make_episodes(lengths: list[int], seed: int = 0, first_id: int = 0) -> list[dict[str, Any]]:
    """Episodes of the given lengths; every other one terminates, the rest time out."""
    rng = np.random.default_rng(seed)
    return [make_episode(rng, t, first_id + i, terminated=bool(i % 2)) for i, t in enumerate(lengths)]


def write_dataset(path: Path, episodes: list[dict[str, Any]], *, complete: bool = True, **overrides: Any) -> Path:
    """Write ``episodes`` to a new dataset at ``path`` with :data:`WRITER_ARGS` (plus overrides)."""
    args = {"quality": "random", **WRITER_ARGS, **overrides}
    with DatasetWriter(path, **args) as writer:
        for ep in episodes:
            writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], ep["terminated"], ep["infos"])
        writer.close(complete=complete)
    return path


def step_space(episodes: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """The episodes in the DreamerV2 step convention, back to back: the oracle for sampled windows."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("image", "action", "reward", "is_first", "is_last")}
    parts["is_terminal"] = []
    for ep in episodes:
        t = len(ep["rewards"])
        parts["image"].append(ep["observations"])
        parts["action"].append(np.concatenate([np.zeros((1, ACTION_SIZE), np.float32), ep["actions"]]))
        parts["reward"].append(np.concatenate([np.zeros(1, np.float32), ep["rewards"]]))
        parts["is_first"].append(np.arange(t + 1) == 0)
        parts["is_last"].append(np.arange(t + 1) == t)
        parts["is_terminal"].append((np.arange(t + 1) == t) & ep["terminated"])
    return {k: np.concatenate(v) for k, v in parts.items()}


def assert_whole_prefix(path: Path, expected: list[dict[str, Any]]) -> int:
    """The dataset opens and holds exactly the first episodes of ``expected``, each whole; returns how many."""
    from coworld.data import open_dataset

    with open_dataset(path) as data:
        n = data.num_episodes
        assert n <= len(expected)
        for i in range(n):
            ep = data.episode(i)
            np.testing.assert_array_equal(ep["image"], expected[i]["observations"])
            np.testing.assert_array_equal(ep["reward"][1:], expected[i]["rewards"])
    return n


def assert_unfinished_but_sound(path: Path) -> None:
    """``verify`` finds the dataset only unfinished: not complete, maybe rows past the last commit (which a resume
    drops), and nothing else (no checksum, shape or boundary problem in the committed episodes)."""
    from coworld.data import verify_dataset

    problems = verify_dataset(path)
    assert any(p.startswith("not complete") for p in problems), problems
    for problem in problems:
        assert problem.startswith("not complete") or "rows past the last committed episode" in problem, problems


def episode_digests(path: Path) -> list[str]:
    """One digest per committed episode of frames, actions, rewards and end: to show they were left as they were."""
    import hashlib

    from coworld.data import open_dataset

    digests = []
    with open_dataset(path) as data:
        for i in range(data.num_episodes):
            ep = data.episode(i)
            digest = hashlib.sha256()
            for key in ("image", "action", "reward", "is_terminal"):
                digest.update(np.ascontiguousarray(ep[key]).tobytes())
            digests.append(digest.hexdigest())
    return digests


def committed_episodes(path: Path) -> int:
    """The committed episode count of a dataset another process may be writing (0 while unreadable)."""
    import h5py

    try:
        with h5py.File(path, "r", locking=False) as f:
            return int(f.attrs.get("num_episodes", 0))
    except (OSError, KeyError, RuntimeError):
        return 0


def folder_state(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative name -> bytes), to show a command left the folder as it was."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def file_state(path: Path) -> tuple[bytes, int]:
    """Bytes and modification time of a file, to show a command left it untouched."""
    return path.read_bytes(), path.stat().st_mtime_ns


# -- a fake pixel task ----------------------------------------------------------------------------------------

FAKE_TASK = "fake_task"
FAKE_SPEC = TaskSpec(FAKE_TASK, "toy", 2, 12, 1, "", "test fake", 10.0, 0.0)


class FakePixelEnv(gym.Env):
    """Frames tag (step, a byte drawn at reset); reward = action[0]; may terminate at random, else truncates at 12
    steps. As :class:`coworld.envs.base.PixelEnv` promises, an episode is a function of its reset seed and actions.

    Reports ``success`` (step >= 3) in its info. ``delay`` seconds of sleep per step slow it down for crash tests.
    """

    metadata: dict[str, Any] = {"render_modes": []}
    observation_space = gym.spaces.Box(0, 255, IMAGE, np.uint8)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def __init__(self, delay: float = 0.0, max_length: int = 12, terminate_prob: float = 0.15) -> None:
        self.delay, self.max_length, self.terminate_prob = delay, max_length, terminate_prob
        self.t, self.tag = 0, 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t, self.tag = 0, int(self.np_random.integers(256))
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        time.sleep(self.delay)
        self.t += 1
        terminated = bool(self.np_random.random() < self.terminate_prob)
        truncated = self.t >= self.max_length and not terminated
        return self._obs(), float(action[0]), terminated, truncated, {"success": self.t >= 3}

    def _obs(self) -> np.ndarray:
        obs = np.zeros(IMAGE, np.uint8)
        obs[0, 0, 0], obs[0, 0, 1] = self.t, self.tag
        return obs


def fake_vector(num_envs: int, seed: int = 0, *, same_step: bool = False, delay: float = 0.0) -> gym.vector.VectorEnv:
    mode = gym.vector.AutoresetMode.SAME_STEP if same_step else gym.vector.AutoresetMode.NEXT_STEP
    envs = gym.vector.SyncVectorEnv([lambda: FakePixelEnv(delay) for _ in range(num_envs)], autoreset_mode=mode)
    envs.reset(seed=seed)
    return envs


def patch_envs(setattr_: Callable[[Any, str, Any], None], *, same_step: bool = False, delay: float = 0.0) -> None:
    """Make ``coworld.envs`` serve :data:`FAKE_TASK` (other names still reach the real registry)."""
    import coworld.envs as envs

    real_spec, real_make = envs.task_spec, envs.make_vector

    def task_spec(name: str) -> TaskSpec:
        return FAKE_SPEC if name == FAKE_TASK else real_spec(name)

    def make_vector(name: str, num_envs: int, seed: int = 0, **overrides: Any) -> gym.vector.VectorEnv:
        if name != FAKE_TASK:
            return real_make(name, num_envs, seed, **overrides)
        return fake_vector(num_envs, seed, same_step=same_step, delay=delay)

    setattr_(envs, "task_spec", task_spec)
    setattr_(envs, "make_vector", make_vector)


def states_differ(a: object, b: object) -> bool:
    """Whether two nested checkpoint states differ in structure or in any value, tensors element for element."""
    import torch

    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() != b.keys() or any(states_differ(a[key], b[key]) for key in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) != len(b) or any(states_differ(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return a.shape != b.shape or not torch.equal(a, b)
    return a != b
