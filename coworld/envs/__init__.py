"""Pixel environments: every source and target task of the paper, plus a toy pair.

Importing this package loads no simulator; :func:`make` imports dm_control or Meta-World when it first builds
one of their tasks, choosing headless EGL rendering if ``MUJOCO_GL`` is unset.

>>> from coworld.envs import make, TASKS, PAIRS
>>> env = make("walker_downhill", seed=0)          # obs (64, 64, 3) uint8, action (6,) in [-1, 1]

Importing it also registers every task with Gymnasium as ``coworld/<task>-v0`` (see
:mod:`coworld.envs.gym_registration`): ``gymnasium.make("coworld/walker_downhill-v0")``.
"""

from coworld.envs.gym_registration import env_id, register_tasks
from coworld.envs.registry import PAIRS, TASKS, EnvSettings, TaskSpec, make, paired_source, task_spec
from coworld.envs.vector import make_vector

register_tasks()

__all__ = [
    "PAIRS",
    "TASKS",
    "EnvSettings",
    "TaskSpec",
    "env_id",
    "make",
    "make_vector",
    "paired_source",
    "task_spec",
]
