"""The world models of a run folder, and the episodes to show them.

A ``coworld`` run holds two DreamerV2 agents (its checkpoint's ``agent`` is the target agent, ``source`` the
source agent); a ``dreamerv2`` run and its penalised and fine-tuned variants hold one. The model-free baselines
(CURL, CURL+CQL, DrQ+BC) have no world model.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from coworld import envs
from coworld.algorithms import algorithm, names
from coworld.config import Config
from coworld.data.schema import STEP_KEYS
from coworld.data.windows import episode_windows, evenly_spaced
from coworld.errors import CoworldError


@dataclass
class RunModels:
    """What :func:`load_run_models` rebuilt.

    Attributes:
        agents: ``{"target": ..., "source": ...}`` DreamerV2 agents for a CoWorld run, ``{"dreamerv2": ...}`` for
            an offline DreamerV2 run; the first one acts in the target task.
        info: the run description (``run.json``: algo, source, target, dataset).
    """

    run_dir: Path
    config: Config
    info: dict[str, Any]
    agents: dict[str, Any]

    @property
    def algo(self) -> str:
        return str(self.info["algo"])

    @property
    def target_agent(self) -> Any:
        return next(iter(self.agents.values()))

    def world_models(self) -> dict[str, Any]:
        return {name: agent.world_model for name, agent in self.agents.items()}


def load_run_models(path: str | Path, device: str = "auto") -> RunModels:
    """Rebuild the DreamerV2 agents of a run folder (or of its checkpoint file), checked to be what the folder says
    (:mod:`coworld.training.loading`); problems raise one line."""
    from coworld.agents.factory import make_agent
    from coworld.devices import resolve_device
    from coworld.training.checkpoint import load_agent_state
    from coworld.training.loading import load_run_checkpoint, open_run

    run_dir, ckpt, config, info = open_run(path)
    algo, record = info["algo"], algorithm(info["algo"])
    if not record.world_model:
        raise CoworldError(
            f"{run_dir} is a {algo} run: it has no world model to look inside; pass a run of"
            f" {', '.join(names(world_model=True))}"
        )
    parts = {"target": "agent", "source": "source"} if record.collaborative else {algo: "agent"}
    torch_device = resolve_device(device)
    state = load_run_checkpoint(ckpt, config, info, keys=tuple(parts.values()), map_location=torch_device)
    config = replace(config, device=str(torch_device))
    action_size = envs.task_spec(info["target"]).action_size
    agents = {}
    for name, key in parts.items():
        if name == "source":  # a CoWorld source agent: its own actor, a model reading both action spaces
            from coworld.agents.coworld import source_model_action_size
            from coworld.agents.dreamerv2 import DreamerV2

            size = envs.task_spec(str(state.get("source_task", info["source"]))).action_size
            model_size = source_model_action_size(size, action_size)
            agent = DreamerV2(config=config, action_size=size, device=torch_device, model_action_size=model_size)
        else:
            agent = make_agent(algo, config=config, action_size=action_size, device=torch_device)
        load_agent_state(agent, state[key], ckpt, f"a {algo} run of this config")
        agents[name] = agent
    return RunModels(run_dir=run_dir, config=config, info=info, agents=agents)


def run_dataset(info: Mapping[str, Any], override: str | Path | None = None) -> Path:
    """The target dataset a run was trained on (``run.json``), or ``override``; it must exist."""
    path = Path(override) if override is not None else Path(str(info.get("dataset")))
    if not path.exists():
        raise CoworldError(f"no dataset at {path}; pass the run's target dataset with --dataset")
    return path


def target_episodes(
    run: RunModels, count: int, *, dataset: str | Path | None = None, online: bool = False, seed: int = 0
) -> tuple[list[dict[str, np.ndarray]], str]:
    """``count`` episodes of the run's target task and a phrase saying where they come from: evenly spaced
    episodes of its dataset (or ``dataset``), or with ``online`` fresh episodes of its target policy."""
    from coworld.data import open_dataset

    task = run.info["target"]
    if online:
        episodes = rollout_episodes(run.target_agent, task, count, seed=seed)
        return episodes, f"{count} fresh {task} episodes of the run's policy (seed {seed})"
    path = run_dataset(run.info, dataset)
    with open_dataset(path) as data:
        if data.task != task:
            raise CoworldError(f"{path} holds {data.task} episodes, not the run's target task {task}")
        picked = evenly_spaced(data.num_episodes, count)
        episodes = [data.episode(i) for i in picked]
    return episodes, f"episodes {', '.join(map(str, picked))} of {path}"


def prediction_windows(
    episodes: Sequence[Mapping[str, np.ndarray]], *, start: int, length: int, context: int
) -> dict[str, np.ndarray]:
    """Steps ``start .. start + length - 1`` of every episode (fewer if the shortest episode ends first), checked
    to leave at least one step to imagine after ``context`` observed ones."""
    if context >= length:
        raise CoworldError(f"--context {context} must be shorter than --length {length}")
    shortest = min(len(ep["reward"]) for ep in episodes)
    if shortest <= start + context:
        raise CoworldError(
            f"the episodes have {shortest} steps: too few for --start {start} plus --context {context}; lower them"
        )
    return episode_windows(episodes, min(length, shortest - start), [start] * len(episodes))


def rollout_episodes(agent: Any, task: str, episodes: int, seed: int = 0, mode: str = "eval") -> list[dict]:
    """Fresh episodes in ``task`` in the step convention: ``agent``'s policy in ``mode`` ('eval' or 'train'), or
    uniform random actions for ``mode='random'`` (``agent`` may then be None)."""
    spec = envs.task_spec(task)
    rng = np.random.default_rng(seed)
    env = envs.make(task, seed=seed)
    out = []
    try:
        for i in range(episodes):
            obs, _ = env.reset(seed=seed + i)
            steps = [_step(obs, np.zeros(spec.action_size, np.float32), 0.0, first=True)]
            state, done = None, False
            while not done:
                if mode == "random":
                    action = rng.uniform(-1, 1, spec.action_size)
                else:
                    batch_action, state = agent.policy(obs[None], state, mode=mode)
                    action = batch_action[0]
                action = np.asarray(action, np.float32)
                obs, reward, terminated, truncated, _ = env.step(action)
                done = bool(terminated or truncated)
                steps.append(_step(obs, action, float(reward), last=done, terminal=bool(terminated)))
            out.append({key: np.stack([s[key] for s in steps]) for key in STEP_KEYS})
    finally:
        env.close()
    return out


def _step(
    obs: np.ndarray, action: np.ndarray, reward: float, first: bool = False, last: bool = False, terminal: bool = False
) -> dict[str, Any]:
    return {
        "image": obs,
        "action": action,
        "reward": np.float32(reward),
        "is_first": first,
        "is_last": last,
        "is_terminal": terminal,
    }
