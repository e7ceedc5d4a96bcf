"""What a task is and how one env of it is built: pure data, imported by the registry and by every task family."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from coworld.envs.render import RenderQuality

Family = Literal["dmc", "metaworld", "robodesk", "toy"]


@dataclass(frozen=True)
class TaskSpec:
    """What a task is; pure data, available without importing any simulator."""

    name: str
    family: Family
    action_size: int
    episode_length: int
    """Agent steps per episode (after action repeat) at the default action repeat."""
    action_repeat: int
    """Simulator (control) steps per agent step by default."""
    modification: str
    """What differs from the plain task, for people; '' when nothing does."""
    base: str
    """What it is built from."""
    reference_return: float | None
    """The best return known to be reachable (see the module docstring)."""
    random_return: float | None
    """Mean return of uniform random actions (see the module docstring)."""
    reference_source: str = ""
    """Where ``reference_return`` comes from, in a few words."""

    @property
    def embodiment(self) -> str:
        """The body the agent controls: ``walker``/``cheetah`` (DMC), ``sawyer`` (Meta-World), ``franka`` (RoboDesk),
        ``dot`` (toy)."""
        if self.family == "dmc":
            return self.name.split("_")[0]
        return {"metaworld": "sawyer", "robodesk": "franka", "toy": "dot"}[self.family]

    @property
    def has_success(self) -> bool:
        """Whether the env reports ``info["success"]`` (Meta-World and RoboDesk tasks)."""
        return self.family in ("metaworld", "robodesk")

    @property
    def medium_return(self) -> float | None:
        """The medium level, where medium-replay collection stops: a third of ``reference_return``.

        Where a third is not above ``random_return`` (the centre toy tasks, whose random policy scores 42% of the
        expert), a third of the way from random to the reference instead, so a medium dataset is better than random.
        """
        if self.reference_return is None:
            return None
        third = self.reference_return / 3.0
        if self.random_return is not None and third <= self.random_return:
            return self.random_return + (self.reference_return - self.random_return) / 3.0
        return third


@dataclass(frozen=True)
class EnvSettings:
    """The resolved overrides of one env (the keyword arguments accepted by :func:`make`)."""

    image_size: int
    """Side of the square RGB frames, in pixels."""
    action_repeat: int
    """Simulator (control) steps per agent step."""
    episode_length: int
    """Agent steps per episode. Default: the task's simulator-step budget divided by ``action_repeat``."""
    render_quality: RenderQuality = "standard"
    """MuJoCo tasks only: 'standard', 'fast' or 'full' (see :mod:`coworld.envs.render`)."""
