"""One evaluation protocol for every algorithm.

An agent is anything with ``policy(obs, state, mode="eval", is_first=...) -> (action, state)``; agents
with a critic also offer ``value(state) -> (N,)``, the critic's estimate for the states the policy has just
seen. Episodes run in ``workers`` environments side by side (worker processes when more than one); episode
``e`` is seeded by ``(seed, e)`` alone, so the same checkpoint and seed give the same returns whatever the
worker count. The result holds the return of every episode, its normalized score against the task's random and
reference returns, the success rate on tasks that report success, and Figure 4(b)'s value check: the critic's
estimate against the true discounted return of the same episode from the same step (:func:`true_values`), and for
CoWorld also what the critic that caps the target critic (Eq. 6) says of the same states (``source_value(state)``).
World-model agents (``predicted_reward(state)``) add the reward check: the reward head's prediction for the states
the agent reached against the reward of arriving at each, received.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from coworld import envs, interrupt
from coworld.algorithms import algorithm
from coworld.data.values import arrival_rewards, true_values
from coworld.progress import progress_bar


class Agent(Protocol):
    def policy(
        self, obs: np.ndarray, state: Any, mode: str = "eval", is_first: np.ndarray | None = None
    ) -> tuple[np.ndarray, Any]: ...


@dataclass
class EvalResult:
    """What :func:`evaluate` measured; ``to_json`` writes it."""

    task: str
    returns: list[float]
    lengths: list[int]
    successes: list[bool] | None = None
    value_estimate: list[float] | None = None
    """Per episode: the critic's mean estimate over the episode's steps."""
    value_true: list[float] | None = None
    """Per episode: the mean over the same steps of the discounted return actually received from there on."""
    value_source: list[float] | None = None
    """CoWorld: per episode, the mean over the same steps of the estimate of the critic that caps the target critic
    in Eq. 6 (the source critic, or the target-policy critic)."""
    reward_estimate: list[float] | None = None
    """World-model agents: per episode, the reward head's mean prediction for the states the agent reached."""
    reward_true: list[float] | None = None
    """Per episode: the mean over the same states of the reward of arriving at each (0 at the reset), received."""
    discount: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns))

    @property
    def std(self) -> float:
        return float(np.std(self.returns))

    @property
    def success_rate(self) -> float | None:
        return None if self.successes is None else float(np.mean(self.successes))

    @property
    def normalized_score(self) -> float | None:
        """``100 * (mean - random) / (reference - random)`` with the task's returns (``coworld tasks``)."""
        from coworld.data.reader import normalized_score

        spec = envs.task_spec(self.task)
        reference = {"random_return": spec.random_return, "reference_return": spec.reference_return}
        score = normalized_score(self.mean, reference)
        return None if score is None else float(score)

    def summary(self) -> str:
        episodes = len(self.returns)
        text = f"{self.task}: return {self.mean:.1f} ± {self.std:.1f} over {episodes} episode{'s' * (episodes != 1)}"
        if self.normalized_score is not None:
            text += f" (normalized {self.normalized_score:.1f})"
        if self.success_rate is not None:
            text += f", success {100 * self.success_rate:.0f}%"
        if self.value_estimate is not None and self.value_true is not None:
            text += (
                f"; value estimate {np.mean(self.value_estimate):.2f} vs true discounted return"
                f" {np.mean(self.value_true):.2f}"
            )
        if self.value_source is not None:
            text += f" (the cap's critic: {np.mean(self.value_source):.2f})"
        if self.reward_estimate is not None and self.reward_true is not None:
            text += (
                f"; reward a step predicted {np.mean(self.reward_estimate):.3f} vs received"
                f" {np.mean(self.reward_true):.3f}"
            )
        return text

    def metrics(self, prefix: str = "") -> dict[str, float]:
        """The logged scalars: ``eval/return``, ``eval/return_std`` and, when measured, success and value check."""
        out = {f"{prefix}eval/return": self.mean, f"{prefix}eval/return_std": self.std}
        if self.normalized_score is not None:
            out[f"{prefix}eval/normalized_score"] = self.normalized_score
        if self.success_rate is not None:
            out[f"{prefix}eval/success"] = self.success_rate
        if self.value_estimate is not None and self.value_true is not None:
            out[f"{prefix}eval/value_estimate"] = float(np.mean(self.value_estimate))
            out[f"{prefix}eval/value_true"] = float(np.mean(self.value_true))
        if self.value_source is not None:
            out[f"{prefix}eval/value_source"] = float(np.mean(self.value_source))
        if self.reward_estimate is not None and self.reward_true is not None:
            out[f"{prefix}eval/reward_estimate"] = float(np.mean(self.reward_estimate))
            out[f"{prefix}eval/reward_true"] = float(np.mean(self.reward_true))
        return out

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data.update(
            mean=self.mean, std=self.std, normalized_score=self.normalized_score, success_rate=self.success_rate
        )
        return data

    def to_json(self, path: str | Path) -> None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")


def episode_seed(seed: int, episode: int) -> int:
    """The seed of evaluation episode ``episode`` (its environment and its agent-side randomness)."""
    return int(np.random.SeedSequence([seed, episode]).generate_state(1)[0])


class _EpisodeRandomness:
    """Torch random streams of one evaluation episode, swapped into the global generators while its agent acts.

    The agent samples its latents (DreamerV2) from torch's global generators; giving every episode its own
    stream, and stepping the policy one episode at a time, makes an episode's actions depend on its seed alone,
    not on how many episodes run side by side or which worker runs it.
    """

    def __init__(self, seed: int, cuda: bool) -> None:
        self.cpu = torch.Generator().manual_seed(seed).get_state()
        self.cuda = None
        if cuda:
            generator = torch.Generator(device="cuda").manual_seed(seed)
            self.cuda = generator.get_state()

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        torch.set_rng_state(self.cpu)
        if self.cuda is not None:
            torch.cuda.set_rng_state(self.cuda)
        try:
            yield
        finally:
            self.cpu = torch.get_rng_state()
            if self.cuda is not None:
                self.cuda = torch.cuda.get_rng_state()


def evaluate(
    agent: Agent,
    task: str,
    *,
    episodes: int = 10,
    workers: int = 1,
    seed: int = 0,
    discount: float | None = None,
    video_episodes: int = 0,
    progress: bool = False,
) -> tuple[EvalResult, list[np.ndarray]]:
    """Run ``episodes`` evaluation episodes of ``agent`` on ``task``.

    Reproducible: episode ``e`` uses :func:`episode_seed` ``(seed, e)`` for its environment and for the torch
    random stream its agent acts with, and the policy steps one episode at a time, so the returns depend on
    ``seed`` alone, not on ``workers`` (which only sets how many environments step side by side). Torch's
    global random state is left as it was.

    Args:
        discount: when given and the agent has ``value``, also measure the value check with this discount (and,
            where it has ``predicted_reward``, the reward check).
        video_episodes: how many of the first episodes to keep frames of.

    Returns:
        The result, and the frames (T+1, H, W, 3) uint8 of the first ``video_episodes`` episodes.
    """
    workers = max(1, min(workers, episodes))
    spec = envs.task_spec(task)
    want_values = discount is not None and hasattr(agent, "value")
    want_source = want_values and hasattr(agent, "source_value")
    want_rewards = want_values and hasattr(agent, "predicted_reward")
    cuda = torch.cuda.is_available() and getattr(getattr(agent, "device", None), "type", "cpu") == "cuda"
    returns: list[float] = []
    lengths: list[int] = []
    successes: list[bool] = []
    estimates: list[float] = []
    trues: list[float] = []
    sources: list[float] = []
    predicted: list[float] = []
    arrived: list[float] = []
    videos: list[np.ndarray] = []
    venv = envs.make_vector(task, workers, seed=seed)
    bar = progress_bar(total=episodes, desc=f"eval {task}", unit="episodes", enabled=progress, leave=False)
    devices = [torch.cuda.current_device()] if cuda else []
    try:
        with torch.random.fork_rng(devices=devices):
            done_episodes = 0
            while done_episodes < episodes:
                n = min(workers, episodes - done_episodes)
                ids = [done_episodes + i for i in range(workers)]  # rows past n are idle this round
                obs, _ = venv.reset(seed=[episode_seed(seed, e) for e in ids])
                rngs = [_EpisodeRandomness(episode_seed(seed, e), cuda) for e in ids[:n]]
                states: list[Any] = [None] * n
                alive = np.zeros(workers, dtype=bool)
                alive[:n] = True
                ep_rewards: list[list[float]] = [[] for _ in range(n)]
                ep_values: list[list[float]] = [[] for _ in range(n)]
                ep_source: list[list[float]] = [[] for _ in range(n)]
                ep_predicted: list[list[float]] = [[] for _ in range(n)]
                ep_success = np.zeros(n, dtype=bool)
                frames = [[obs[i]] for i in range(n)]
                actions = np.zeros((workers, *venv.single_action_space.shape), np.float32)
                for t in range(spec.episode_length):
                    interrupt.check()
                    for i in np.flatnonzero(alive):
                        with rngs[i].active():
                            first = np.array([t == 0])
                            action, states[i] = agent.policy(obs[i : i + 1], states[i], mode="eval", is_first=first)
                            if want_values:
                                ep_values[i].append(float(np.asarray(agent.value(states[i]))[0]))  # type: ignore[attr-defined]
                            if want_source:
                                ep_source[i].append(float(np.asarray(agent.source_value(states[i]))[0]))  # type: ignore[attr-defined]
                            if want_rewards:
                                ep_predicted[i].append(float(np.asarray(agent.predicted_reward(states[i]))[0]))  # type: ignore[attr-defined]
                        actions[i] = action[0]
                    obs, reward, terminated, truncated, info = venv.step(actions)
                    for i in np.flatnonzero(alive):
                        ep_rewards[i].append(float(reward[i]))
                        if "success" in info:
                            ep_success[i] |= bool(info["success"][i])
                        if done_episodes + i < video_episodes:
                            frames[i].append(obs[i])
                    alive &= ~(terminated | truncated)
                    if not alive.any():
                        break
                for i in range(n):
                    rewards = np.asarray(ep_rewards[i])
                    returns.append(float(rewards.sum()))
                    lengths.append(len(rewards))
                    successes.append(bool(ep_success[i]))
                    if want_values:
                        estimates.append(float(np.mean(ep_values[i])))
                        trues.append(float(np.mean(true_values(rewards, discount))))  # type: ignore[arg-type]
                    if want_source:
                        sources.append(float(np.mean(ep_source[i])))
                    if want_rewards:  # the states the policy acted at, o_0 .. o_T-1
                        predicted.append(float(np.mean(ep_predicted[i])))
                        arrived.append(float(np.mean(arrival_rewards(rewards)[:-1])))
                    if done_episodes + i < video_episodes:
                        videos.append(np.stack(frames[i]))
                done_episodes += n
                bar.update(n)
    finally:
        bar.close()
        venv.close()
    result = EvalResult(
        task=task,
        returns=returns,
        lengths=lengths,
        successes=successes if spec.has_success else None,
        value_estimate=estimates if want_values else None,
        value_true=trues if want_values else None,
        value_source=sources if want_source else None,
        reward_estimate=predicted if want_rewards else None,
        reward_true=arrived if want_rewards else None,
        discount=discount if want_values else None,
    )
    return result, videos


def write_video(path: str | Path, episodes: Sequence[np.ndarray], fps: int = 30, scale: int = 4) -> None:
    """Write episodes of frames (T, H, W, 3) uint8 one after another as an MP4 (or GIF by suffix)."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = np.concatenate(list(episodes))
    if scale > 1:
        frames = frames.repeat(scale, axis=1).repeat(scale, axis=2)
    if path.suffix.lower() == ".gif":
        imageio.mimsave(path, list(frames), duration=1000 / fps, loop=0)
    else:
        imageio.mimsave(path, list(frames), fps=fps, macro_block_size=1)


def load_trained_agent(path: Path, device: str = "auto") -> tuple[Any, dict[str, Any], Any]:
    """Rebuild the agent of a run folder (or its checkpoint file) for evaluation.

    The checkpoint must be what the folder says (its algorithm, tasks and config; :mod:`coworld.training.loading`),
    so a result is never labelled with another run's algorithm. Returns ``(agent, run_info, config)``; problems raise
    one CoworldError line.
    """
    from coworld.agents.factory import make_agent
    from coworld.devices import resolve_device
    from coworld.training.checkpoint import load_agent_state
    from coworld.training.loading import load_run_checkpoint, open_run

    _, ckpt, config, info = open_run(path)
    state = load_run_checkpoint(ckpt, config, info)
    config = replace(config, device=device)
    torch_device = resolve_device(device)
    action_size = envs.task_spec(info["target"]).action_size
    # a CoWorld run: both agents, as the value check reads the cap's critic too
    if algorithm(info["algo"]).collaborative and "source_task" in state:
        from coworld.agents.coworld import CoWorld

        source_size = envs.task_spec(state["source_task"]).action_size
        agent = CoWorld(config=config, action_size=action_size, source_action_size=source_size, device=torch_device)
        load_agent_state(agent.target, state["agent"], ckpt, "a coworld target agent of this config")
        load_agent_state(agent.source, state.get("source"), ckpt, "a coworld source agent of this config")
        if agent.policy_value is not None:
            load_agent_state(agent.policy_value, state.get("policy_value"), ckpt, "a coworld target-policy critic")
        return agent, info, config
    agent = make_agent(info["algo"], config=config, action_size=action_size, device=torch_device)
    load_agent_state(agent, state["agent"], ckpt, f"a {info['algo']} agent of this config")
    return agent, info, config
