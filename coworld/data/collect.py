"""Collect datasets by running a policy in vectorised environments and writing each episode as soon as it ends.

:func:`run_collection` is the policy-agnostic loop (any ``policy(obs, is_first, seeds) -> (actions, log_prob)``);
:func:`collect_random` builds a ``random``-quality dataset with :class:`UniformPolicy`. Both stop at an exact budget
(episodes, or rows with the last episode cut as a timeout) and resume a partial dataset where it stopped.

Episode ``k`` of a collection seeded ``s`` is a function of ``(s, k)`` alone: its environment is reset with
:func:`episode_seed` ``(s, k)`` (an episode is a function of its seed and its actions,
:class:`coworld.envs.base.PixelEnv`) and the random policy draws its actions from that seed too. Episodes are
written in the order of ``k``, whichever worker ends first. So a collection stopped by anything (a kill, a full disk,
Ctrl-C) and resumed holds the episodes of the same collection never stopped, bit for bit, and the worker count
changes how fast a dataset is made, not what it holds. The ``steps`` of a random collection's ``collector`` record
are the rows its episodes hold, committed with each episode.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from coworld import interrupt
from coworld.data.reader import open_dataset
from coworld.data.writer import DatasetWriter
from coworld.errors import ConfigError, DatasetError
from coworld.progress import progress_bar
from coworld.text import count

# policy(obs (W, H, W, C) uint8, is_first (W,) bool, seeds (W,) int64: each env's running episode's seed)
#   -> (actions (W, A) float32, log_prob (W,) float32 or None)
Policy = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray | None]]

ACTION_STREAM = 1
"""Mixed into an episode's seed for the generator of its random actions (its environment draws from the seed
itself, so the two streams stay apart)."""


def episode_seed(seed: int, index: int) -> int:
    """The seed of episode ``index`` (counted from 0 over the whole dataset) of a collection seeded ``seed``: it
    seeds the episode's environment and its random actions, whichever run or worker makes it."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


@dataclass(frozen=True)
class Budget:
    """How much to collect: exactly ``episodes`` episodes, or exactly ``steps`` rows (give one)."""

    episodes: int | None = None
    steps: int | None = None

    def __post_init__(self) -> None:
        if (self.episodes is None) == (self.steps is None):
            raise ConfigError("give exactly one of --episodes and --max-steps")
        amount = self.episodes if self.episodes is not None else self.steps
        if amount is None or amount < 1:
            raise ConfigError(f"the collection budget must be >= 1, got {amount}")

    def reached(self, writer: DatasetWriter) -> bool:
        if self.episodes is not None:
            return writer.num_episodes >= self.episodes
        return writer.num_steps >= (self.steps or 0)

    def describe(self) -> str:
        return count(self.episodes, "episode") if self.episodes is not None else count(self.steps or 0, "step")


@dataclass(frozen=True)
class CollectSummary:
    """What a collection left on disk."""

    path: Path
    episodes: int
    steps: int
    mean_return: float
    env_steps: int
    """Environment steps taken by this run (including episodes in flight when the budget was met)."""
    seconds: float


class UniformPolicy:
    """Actions drawn uniformly from the box ``[low, high]`` (A,), with their (constant) log-probability.

    Each episode's actions come from a generator of its own, seeded by the episode's seed (with
    :data:`ACTION_STREAM`) when it starts: they depend on the episode alone, not on the episodes before it.
    """

    def __init__(self, low: np.ndarray, high: np.ndarray) -> None:
        self.low = np.asarray(low, np.float32)
        self.high = np.asarray(high, np.float32)
        self._rngs: dict[int, np.random.Generator] = {}
        """Env i's running episode's generator."""
        self._log_prob = -float(np.log(self.high.astype(np.float64) - self.low).sum())

    def __call__(self, obs: np.ndarray, is_first: np.ndarray, seeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = len(obs)
        for i in np.flatnonzero(is_first):
            self._rngs[int(i)] = np.random.default_rng([int(seeds[i]), ACTION_STREAM])
        actions = np.stack([self._rngs[i].uniform(self.low, self.high) for i in range(n)]).astype(np.float32)
        return actions, np.full(n, self._log_prob, np.float32)


@dataclass
class _Episode:
    """One environment's episode in flight: frames o_0 .. o_t and the t rows so far."""

    index: int
    """Its place in the dataset (it is written after every episode of a smaller index)."""
    frames: list[np.ndarray]
    actions: list[np.ndarray] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    infos: dict[str, list[Any]] = field(default_factory=dict)

    def add(self, action: np.ndarray, reward: float, frame: np.ndarray, infos: dict[str, Any]) -> None:
        """Row t: ``action`` taken at the last frame earned ``reward`` and led to ``frame``."""
        self.actions.append(np.asarray(action, np.float32))
        self.rewards.append(float(reward))
        self.frames.append(np.asarray(frame))
        for name, value in infos.items():
            self.infos.setdefault(name, []).append(value)

    def __len__(self) -> int:
        return len(self.actions)


def run_collection(
    envs: Any,
    policy: Policy,
    writer: DatasetWriter,
    budget: Budget,
    *,
    seed: int,
    progress: bool = True,
    expected_length: int | None = None,
) -> int:
    """Step a gymnasium VectorEnv with ``policy`` until ``budget`` is met, writing each episode whole as it ends.

    The dataset's episode ``k`` (counting those it holds already) is the one whose environment was reset with
    :func:`episode_seed` ``(seed, k)``; an environment that ends an episode is reset at once with the seed of the next
    one to start (any autoreset mode), and episodes are written in the order of ``k`` (one that ends before an
    earlier one waits for it). Per-step infos recorded: ``success`` when the environment reports it,
    ``behavior_log_prob`` when the policy returns one. With a step budget the episode that crosses it is cut to fit
    and stored as a timeout. Each episode's commit sets the collector record's ``steps`` to the rows the dataset then
    holds. Returns the number of environment steps taken (with the episodes still running when the budget was met).
    """
    from gymnasium.vector import AutoresetMode

    same_step = AutoresetMode(envs.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)) == AutoresetMode.SAME_STEP
    n_envs = int(envs.num_envs)
    first = writer.num_episodes
    seeds = np.array([episode_seed(seed, first + i) for i in range(n_envs)], np.int64)
    obs, _ = envs.reset(seed=[int(s) for s in seeds])
    running = [_Episode(first + i, [np.asarray(obs[i])]) for i in range(n_envs)]
    ended: dict[int, tuple[_Episode, bool]] = {}  # index -> (episode, terminated), until the ones before are written
    next_index = first + n_envs
    is_first = np.ones(n_envs, bool)
    record_success: bool | None = None  # decided by the first step's info
    returns = list(writer.returns())
    total = budget.steps if budget.steps is not None else (budget.episodes or 0) * (expected_length or 0) or None
    env_steps = 0
    with progress_bar(total=total, initial=writer.num_steps, desc="collect", unit="env steps", enabled=progress) as bar:
        while not budget.reached(writer):
            interrupt.check()
            actions, log_prob = policy(obs, is_first, seeds)
            obs, rewards, terminated, truncated, info = envs.step(actions)
            done = np.logical_or(terminated, truncated)
            for i in range(n_envs):
                # SAME_STEP mode returns the next episode's o_0 at once; the final frame and info come apart.
                final = bool(done[i]) and same_step
                step_info = info["final_info"] if final else info
                if record_success is None:
                    record_success = "success" in step_info
                extras: dict[str, Any] = {}
                if record_success:
                    extras["success"] = bool(_info_value(step_info, "success", i, False))
                if log_prob is not None:
                    extras["behavior_log_prob"] = float(log_prob[i])
                running[i].add(actions[i], rewards[i], info["final_obs"][i] if final else obs[i], extras)
                env_steps += 1
                if done[i]:
                    ended[running[i].index] = (running[i], bool(terminated[i]))
            while writer.num_episodes in ended and not budget.reached(writer):  # the next episode of the dataset
                episode, ends_in_terminal = ended.pop(writer.num_episodes)
                _write(writer, episode, ends_in_terminal, budget)
                returns.append(float(writer.returns()[-1]))
                bar.set_postfix(episodes=writer.num_episodes, mean_return=f"{np.mean(returns):.1f}")
            is_first = done
            if done.any() and not budget.reached(writer):
                starting = {int(i): next_index + k for k, i in enumerate(np.flatnonzero(done))}
                next_index += len(starting)
                for i, index in starting.items():
                    seeds[i] = episode_seed(seed, index)
                reset_seeds = [int(seeds[i]) if i in starting else None for i in range(n_envs)]
                obs, _ = envs.reset(seed=reset_seeds, options={"reset_mask": done})
                for i, index in starting.items():
                    running[i] = _Episode(index, [np.asarray(obs[i])])
            in_flight = sum(len(ep) for ep, _ in ended.values()) + sum(len(ep) for ep in running)
            position = writer.num_steps + in_flight
            bar.update(max(0, min(position, total or position) - bar.n))
    return env_steps


def _info_value(info: dict[str, Any], key: str, i: int, default: Any) -> Any:
    """Entry ``i`` of a vector env's info key, or ``default`` where the env did not report it."""
    if key not in info or not info.get(f"_{key}", np.ones(i + 1, bool))[i]:
        return default
    return info[key][i]


def _write(writer: DatasetWriter, ep: _Episode, terminated: bool, budget: Budget) -> None:
    """Store a finished episode, cut to the remaining step budget (as a timeout) if it would cross it."""
    t = len(ep)
    if budget.steps is not None and writer.num_steps + t > budget.steps:
        t, terminated = budget.steps - writer.num_steps, False
    dtypes = {"success": bool, "behavior_log_prob": np.float32}
    infos = {name: np.asarray(values[:t], dtypes.get(name)) for name, values in ep.infos.items()}
    frames, actions, rewards = np.stack(ep.frames[: t + 1]), np.stack(ep.actions[:t]), np.asarray(ep.rewards[:t])
    writer.add_episode(frames, actions, rewards, terminated, infos, collector={"steps": writer.num_steps + t})


def default_dataset_path(task: str, quality: str) -> Path:
    """``datasets/<task>-<quality>.h5``, the quality's dashes as underscores (``walker_uphill-medium_replay.h5``)."""
    return Path("datasets") / f"{task}-{quality.replace('-', '_')}.h5"


def dataset_fields(task: str) -> dict[str, Any]:
    """The writer's ``env_config`` (task spec and resolved env settings) and ``reference`` returns for ``task``."""
    from coworld import envs as coworld_envs
    from coworld.envs.registry import resolve_settings

    spec = coworld_envs.task_spec(task)
    env_config = {**dataclasses.asdict(spec), **dataclasses.asdict(resolve_settings(spec, {}))}
    reference = {"random_return": spec.random_return, "reference_return": spec.reference_return}
    return {"env_config": env_config, "reference": {k: v for k, v in reference.items() if v is not None}}


@contextlib.contextmanager
def new_dataset(
    path: Path,
    task: str,
    *,
    quality: str,
    collector: dict[str, Any],
    action_size: int,
    resume: bool,
    force: bool,
    compression: str,
) -> Iterator[DatasetWriter]:
    """An open ``DatasetWriter`` for ``task`` at ``path``; a file this call made that holds no episode when the block
    fails is removed (a collection or import that stored nothing leaves no file behind)."""
    created = force or not path.exists()
    writer = DatasetWriter(
        path,
        task=task,
        quality=quality,
        collector=collector,
        action_size=action_size,
        resume=resume,
        force=force,
        compression=compression,
        **dataset_fields(task),
    )
    try:
        with writer:
            yield writer
    except BaseException:
        if created and _holds_no_episodes(path):
            path.unlink(missing_ok=True)
        raise


def collect_random(
    task: str,
    out: str | Path | None = None,
    *,
    episodes: int | None = None,
    max_steps: int | None = None,
    seed: int = 0,
    workers: int = 1,
    resume: bool = False,
    force: bool = False,
    compression: str = "gzip",
    progress: bool = True,
) -> CollectSummary:
    """Collect a ``random``-quality dataset of ``task`` with uniformly random actions.

    Writes to ``out`` (default ``datasets/<task>-random.h5``). ``resume`` continues a partial dataset up to the
    budget (a complete one that already meets it is refused); ``force`` replaces an existing file.
    """
    from coworld import envs as coworld_envs

    budget = Budget(episodes=episodes, steps=max_steps)
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    spec = coworld_envs.task_spec(task)
    path = Path(out) if out is not None else default_dataset_path(task, "random")
    collector = {"algorithm": "random", "policy": "uniform", "preset": None, "seed": seed, "workers": workers}
    collector.update(steps=0, last_eval_return=None)
    if resume:
        _check_resumable(path, seed)
    with new_dataset(
        path,
        task,
        quality="random",
        collector=collector,
        action_size=spec.action_size,
        resume=resume,
        force=force,
        compression=compression,
    ) as writer:
        return _collect_random_into(writer, budget, coworld_envs.make_vector, spec, seed, workers, progress)


def _collect_random_into(
    writer: DatasetWriter,
    budget: Budget,
    make_vector: Callable[..., Any],
    spec: Any,
    seed: int,
    workers: int,
    progress: bool,
) -> CollectSummary:
    start = time.perf_counter()
    if writer.metadata["collector"].get("steps") != writer.num_steps:  # a record an older collector left behind
        writer.update_metadata(steps=writer.num_steps)
    if budget.reached(writer):
        if writer.complete:
            raise DatasetError(
                f"{writer.path} is already complete with {count(writer.num_episodes, 'episode')}"
                f" ({count(writer.num_steps, 'step')}), which meets {budget.describe()}; ask for more or pass --force"
                f" to collect it again"
            )
        writer.close(complete=True)  # the collection stopped after its last episode, before marking it done
        return _summary(writer.path, 0, start)
    envs = make_vector(spec.name, workers, seed)  # each episode is reset with its own seed (episode_seed)
    try:
        space = envs.single_action_space
        if tuple(space.shape) != (spec.action_size,):
            raise DatasetError(f"{spec.name}: env action shape {space.shape} != task spec ({spec.action_size},)")
        policy = UniformPolicy(space.low, space.high)
        env_steps = run_collection(
            envs, policy, writer, budget, seed=seed, progress=progress, expected_length=spec.episode_length
        )
    finally:
        envs.close()
    writer.close(complete=True)
    return _summary(writer.path, env_steps, start)


def _check_resumable(path: Path, seed: int) -> None:
    """Refuse to resume a dataset whose next episodes would not be those of the collection that made it: one made by
    another collector, or with another seed (a file that cannot be read is left to the writer to refuse)."""
    try:
        with h5py.File(path, "r") as f:
            theirs = json.loads(f.attrs["collector"])
    except (OSError, KeyError, ValueError):
        return
    if theirs.get("algorithm") != "random":
        raise DatasetError(
            f"cannot resume {path}: it was made by {theirs.get('algorithm')}, not by random actions; choose another"
            f" --out"
        )
    if theirs.get("seed") != seed:
        raise DatasetError(
            f"cannot resume {path}: it was made with --seed {theirs.get('seed')}, not {seed}; resume it with --seed"
            f" {theirs.get('seed')} (its episodes are a function of the seed) or pass --force to start it over"
        )


def _holds_no_episodes(path: Path) -> bool:
    try:
        with h5py.File(path, "r") as f:
            return int(f.attrs.get("num_episodes", 0)) == 0
    except OSError:
        return False


def _summary(path: Path, env_steps: int, start: float) -> CollectSummary:
    with open_dataset(path) as data:
        return CollectSummary(
            path=path,
            episodes=data.num_episodes,
            steps=data.num_steps,
            mean_return=float(data.returns.mean()),
            env_steps=env_steps,
            seconds=time.perf_counter() - start,
        )
