"""Pixel environments: every source and target task of the paper, plus a toy pair.

Importing this package loads no simulator; :func:`make` imports dm_control or Meta-World when it first builds
one of their tasks, choosing headless EGL rendering if ``MUJOCO_GL`` is unset.

>>> from coworld.envs import make, TASKS, PAIRS
>>> env = make("walker_downhill", seed=0)          # obs (64, 64, 3) uint8, action (6,) in [-1, 1]
"""

from coworld.envs.registry import PAIRS, TASKS, EnvSettings, TaskSpec, make, paired_source, task_spec
from coworld.envs.vector import make_vector

__all__ = ["PAIRS", "TASKS", "EnvSettings", "TaskSpec", "make", "make_vector", "paired_source", "task_spec"]
