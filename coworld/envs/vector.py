"""Several copies of a task stepping in parallel worker processes."""

from __future__ import annotations

import functools
import multiprocessing
import multiprocessing.context
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import gymnasium as gym

from coworld import interrupt
from coworld.envs.registry import make, resolve_settings, task_spec
from coworld.envs.render import ensure_gl_backend
from coworld.interrupt import ignored_by_new_processes
from coworld.text import count

MP_CONTEXT = "spawn"
"""Workers start as fresh interpreters: no OpenGL/EGL or MuJoCo state is inherited from the parent (forking
a process that has rendered can leave the child with a broken GL context)."""


def make_vector(
    name: str, num_envs: int, seed: int = 0, *, workers: bool | None = None, **overrides: Any
) -> gym.vector.VectorEnv:
    """``num_envs`` copies of task ``name``, env ``i`` built with ``make(name, seed + i, **overrides)``.

    ``num_envs > 1`` runs each env in its own worker process (:class:`gymnasium.vector.AsyncVectorEnv`,
    'spawn' start method, observations in shared memory); ``num_envs == 1`` steps in this process
    (:class:`gymnasium.vector.SyncVectorEnv`) unless ``workers`` is true (``workers`` false: in this process
    whatever ``num_envs``). Scripts that create worker processes need the usual ``if __name__ == "__main__":``
    guard.

    Autoreset mode: **NEXT_STEP** (Gymnasium's default). When env ``i`` returns ``terminated`` or ``truncated``,
    the following ``step()`` ignores its action, resets it and returns the first observation of the new
    episode with reward 0 and ``terminated = truncated = False``. A collector should treat that step's
    observation as the start of a new episode and drop its action and reward.

    ``reset(seed=s)`` seeds env ``i`` with ``s + i``; ``reset()`` without a seed uses ``seed + i`` the first time.
    Bad names and overrides raise here, in the calling process.

    Worker processes ignore SIGINT: a Ctrl-C in a terminal reaches the whole process group, and a worker that died
    of it would break the parent's next step. The parent stops (see :mod:`coworld.interrupt`) and closes them; a
    worker whose parent was killed outright ends when its pipe closes.
    """
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        from coworld.errors import ConfigError

        raise ConfigError(f"num_envs takes a positive integer, got {num_envs!r}")
    resolve_settings(task_spec(name), overrides)  # fail here, not in a worker
    env_fns = [functools.partial(make, name, seed + i, **overrides) for i in range(num_envs)]
    mode = gym.vector.AutoresetMode.NEXT_STEP
    if not (num_envs > 1 if workers is None else workers):
        return gym.vector.SyncVectorEnv(env_fns, autoreset_mode=mode)
    ensure_gl_backend()  # workers inherit the environment variable
    with _workers_ignoring_signals():
        return _WorkerEnvs(env_fns, shared_memory=True, context=MP_CONTEXT, autoreset_mode=mode)


class _WorkerEnvs(gym.vector.AsyncVectorEnv):
    """Gymnasium's AsyncVectorEnv whose ``close`` also copes with workers already gone.

    While the job is stopping (:mod:`coworld.interrupt`) the workers are ended rather than asked to close: a SIGTERM
    sent to the whole process group may have killed them, and a dead worker's pipe raises EOFError.
    """

    def close_extras(self, timeout: float | None = None, terminate: bool = False) -> None:
        try:
            super().close_extras(timeout=timeout, terminate=terminate or interrupt.requested())
        except (EOFError, OSError):
            for process in self.processes:
                if process.is_alive():
                    process.kill()
                process.join()


_started: list[multiprocessing.context.SpawnProcess] = []


class _SigintIgnoringProcess(multiprocessing.context.SpawnProcess):
    """A spawned process that ignores SIGINT from its first instruction on."""

    def start(self) -> None:
        with ignored_by_new_processes():  # only for the fork and exec: the workers' start-up is waited for outside
            super().start()
        _started.append(self)


@contextmanager
def _workers_ignoring_signals() -> Iterator[None]:
    """Make the processes that Gymnasium starts through the 'spawn' context ignore SIGINT.

    Gymnasium asks ``multiprocessing.get_context(MP_CONTEXT)`` (one shared object) for its ``Process`` class; for
    the block, that object hands out :class:`_SigintIgnoringProcess`. Stopped while it waits for them to start
    (:mod:`coworld.interrupt`), the workers started so far are killed: nothing else holds them.
    """
    context = multiprocessing.get_context(MP_CONTEXT)
    context.Process = _SigintIgnoringProcess  # type: ignore[attr-defined]
    _started.clear()
    try:
        yield
    except BaseException:
        for process in _started:
            process.kill()
            process.join()
        raise
    finally:
        _started.clear()
        del context.Process  # type: ignore[attr-defined]  # back to the class's own


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
