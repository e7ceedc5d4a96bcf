"""Several copies of a task stepping in parallel worker processes."""

from __future__ import annotations

import functools
import os
from typing import Any

import gymnasium as gym

from coworld.envs.registry import make, resolve_settings, task_spec
from coworld.envs.render import ensure_gl_backend
from coworld.interrupt import ignored_by_new_processes
from coworld.text import count

MP_CONTEXT = "spawn"
"""Workers start as fresh interpreters: no OpenGL/EGL or MuJoCo state is inherited from the parent (forking
a process that has rendered can leave the child with a broken GL context)."""


def make_vector(name: str, num_envs: int, seed: int = 0, **overrides: Any) -> gym.vector.VectorEnv:
    """``num_envs`` copies of task ``name``, env ``i`` built with ``make(name, seed + i, **overrides)``.

    ``num_envs > 1`` runs each env in its own worker process (:class:`gymnasium.vector.AsyncVectorEnv`,
    'spawn' start method, observations in shared memory); ``num_envs == 1`` steps in this process
    (:class:`gymnasium.vector.SyncVectorEnv`). Scripts that create worker processes need the usual
    ``if __name__ == "__main__":`` guard.

    Autoreset mode: **NEXT_STEP** (Gymnasium's default). When env ``i`` returns ``terminated`` or ``truncated``,
    the following ``step()`` ignores its action, resets it and returns the first observation of the new
    episode with reward 0 and ``terminated = truncated = False``. A collector should treat that step's
    observation as the start of a new episode and drop its action and reward.

    ``reset(seed=s)`` seeds env ``i`` with ``s + i``; ``reset()`` without a seed uses ``seed + i`` the first time.
    Bad names and overrides raise here, in the calling process.

    Worker processes ignore SIGINT and SIGTERM: a Ctrl-C in a terminal reaches the whole process group,
    and a worker that died of it would break the parent's next step. The parent stops (see :mod:`coworld.interrupt`)
    and closes them; a worker whose parent was killed outright ends when its pipe closes.
    """
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        from coworld.errors import ConfigError

        raise ConfigError(f"num_envs takes a positive integer, got {num_envs!r}")
    resolve_settings(task_spec(name), overrides)  # fail here, not in a worker
    env_fns = [functools.partial(make, name, seed + i, **overrides) for i in range(num_envs)]
    mode = gym.vector.AutoresetMode.NEXT_STEP
    if num_envs == 1:
        return gym.vector.SyncVectorEnv(env_fns, autoreset_mode=mode)
    ensure_gl_backend()  # workers inherit the environment variable
    with ignored_by_new_processes():  # the workers ignore SIGINT and SIGTERM
        return gym.vector.AsyncVectorEnv(env_fns, shared_memory=True, context=MP_CONTEXT, autoreset_mode=mode)


def available_cores() -> int:
    """CPU cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def sensible_workers(requested: int, episodes: int | None = None) -> tuple[int, str]:
    """``requested`` worker processes capped at the episodes to run and the cores available; and a note when capped.

    More workers than episodes would idle, more than cores would only take turns (each is a whole interpreter with
    its own simulator).
    """
    workers, why = requested, ""
    if episodes is not None and workers > episodes:
        workers, why = episodes, f"one per episode ({count(episodes, 'episode')} asked for)"
    cores = available_cores()
    if workers > cores:
        workers, why = cores, f"one per CPU core ({count(cores, 'core')} available)"
    return workers, (f"--workers {requested} capped to {workers}: {why}" if workers < requested else "")
