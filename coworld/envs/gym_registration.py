"""Every coworld task under a Gymnasium id, so other libraries can use our (modified) environments.

``import coworld.envs`` registers ``coworld/<task>-v0`` for every task of :data:`~coworld.envs.registry.TASKS`
(registration is cheap: no simulator is imported until an env is made). Gymnasium 1.x no longer discovers
plugins by entry points, so code that has not imported coworld names the module in the id instead::

    import gymnasium as gym

    env = gym.make("coworld.envs:coworld/walker_uphill-v0")        # imports coworld.envs, then makes the env
    env = gym.make("coworld/walker_uphill-v0", seed=3, image_size=84)   # after `import coworld.envs`

Keyword arguments are :func:`coworld.envs.make`'s (``seed``, ``image_size``, ``action_repeat``,
``episode_length``, ``render_quality``). The envs truncate their episodes themselves after ``episode_length``
agent steps, so no ``max_episode_steps`` is registered (a TimeLimit at the default length would cut an env made
with a longer one).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from coworld.envs.registry import TASKS, make
from coworld.errors import ConfigError

NAMESPACE = "coworld"
VERSION = 0
RENDER_MODES = ("rgb_array",)


def env_id(task: str) -> str:
    """The Gymnasium id of a task: ``coworld/<task>-v0``."""
    return f"{NAMESPACE}/{task}-v{VERSION}"


def make_env(task: str, render_mode: str | None = None, seed: int = 0, **overrides: Any) -> gym.Env:
    """The Gymnasium entry point of every ``coworld/<task>-v0`` id: :func:`coworld.envs.make` of ``task``.

    ``render_mode``: ``None`` or ``"rgb_array"`` (both give an env whose ``render()`` returns the latest frame;
    Gymnasium turns ``"human"`` and ``"rgb_array_list"`` into wrappers around ``"rgb_array"``).
    """
    if render_mode not in (None, *RENDER_MODES):
        raise ConfigError(f"coworld envs render {', '.join(RENDER_MODES)} only, not render_mode={render_mode!r}")
    return make(task, seed=seed, **overrides)


# Read by gymnasium.make to learn the render modes before it calls the entry point.
make_env.metadata = {"render_modes": list(RENDER_MODES)}  # type: ignore[attr-defined]


def register_tasks() -> None:
    """Register ``coworld/<task>-v0`` for every task (ids already registered are left as they are)."""
    for name in TASKS:
        if env_id(name) not in gym.registry:
            gym.register(id=env_id(name), entry_point=f"{__name__}:make_env", kwargs={"task": name})
