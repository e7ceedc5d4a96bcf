"""Toy reaching tasks in pure NumPy: a small CPU-only source -> target pair for testing CoWorld end to end.

``toy_reach``: a dot moves in the square [-1, 1]^2 (x right, y up); the action is its velocity (2-d, in [-1, 1],
times ``SPEED`` per step). A fixed goal disc is drawn on the frame; the dot starts at a random place at least
``MIN_START_DISTANCE`` from the goal, so a policy has to read the dot's position from the pixels. Reward per step,
dense in [0, 1]: 1 inside the goal disc, falling linearly to 0 at ``REWARD_MARGIN`` beyond its edge.

``toy_reach_shifted``: the same task seen and felt differently -- other colours, and a constant drift of
``DRIFT`` per step towards -x (a "slope"), so a policy has to push right to stay on the goal.

``toy_reach_centre`` and ``toy_reach_centre_shifted``: the same two with the goal at the centre of the square
(``CENTRE_GOAL``). With the goal in a corner the best of 16 constant directions scores 30.7 on both corner tasks, two
thirds of the expert's return; with it at the centre every constant direction drives the dot into a wall, and the
best of 16 scores 10.6 / 10.4, below the random policy, so any return above random needs the dot's position read
from the frame (20 episodes each: ``benchmarks/toy_baselines.py`` and ``--pair centre``).

``toy_reach_shifted_act3``: ``toy_reach_shifted`` with a 3-d action whose third component the dot ignores: a target
of another action size than ``toy_reach`` (2), for fast tests of CoWorld across action sizes.

All: 50 steps per episode, action repeat 1, never terminate. Returns (mean over 200 episodes, seeds 0-199,
re-measured by ``tests/envs/test_toy.py``): uniform random actions 9.6 on toy_reach and 2.3 on toy_reach_shifted
(the drift carries an aimless dot away from the goal); :meth:`ToyReachEnv.expert_action` (full speed at the goal)
46.5 and 45.6. The centre pair: random 20.3 and 18.3, expert 48.5 and 48.4. No policy can reach
50: the dot starts at least 0.4 outside the goal disc.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from coworld.envs.base import PixelEnv

if TYPE_CHECKING:
    from coworld.envs.spec import EnvSettings, TaskSpec

SPEED = 0.1
"""Distance moved per step per unit of action."""
GOAL = (0.45, 0.45)
"""Goal centre of toy_reach and toy_reach_shifted."""
CENTRE_GOAL = (0.0, 0.0)
"""Goal centre of toy_reach_centre and toy_reach_centre_shifted."""
GOAL_RADIUS = 0.2
DOT_RADIUS = 0.12
REWARD_MARGIN = 1.0
"""Distance beyond the goal's edge where the reward reaches 0."""
MIN_START_DISTANCE = 0.6
"""Smallest distance between the dot's start and the goal centre."""
DRIFT = 0.03
"""Per-step drift towards -x in the shifted task."""
LIMIT = 1.0 - DOT_RADIUS
"""The dot's centre stays in [-LIMIT, LIMIT]^2, so it is always fully in view."""


@dataclass(frozen=True)
class ToyVariant:
    """Colours (RGB, 0-255) and dynamics of a toy task."""

    background: tuple[int, int, int]
    goal_colour: tuple[int, int, int]
    dot_colour: tuple[int, int, int]
    drift: tuple[float, float] = (0.0, 0.0)
    goal: tuple[float, float] = GOAL
    action_size: int = 2
    """Action components; the first two are the dot's velocity, any further ones are taken and ignored."""


_PLAIN = ToyVariant(background=(30, 30, 40), goal_colour=(40, 160, 70), dot_colour=(230, 60, 50))
_SHIFTED = ToyVariant(
    background=(200, 190, 150), goal_colour=(60, 90, 200), dot_colour=(250, 240, 40), drift=(-DRIFT, 0.0)
)
VARIANTS: dict[str, ToyVariant] = {
    "toy_reach": _PLAIN,
    "toy_reach_shifted": _SHIFTED,
    "toy_reach_centre": replace(_PLAIN, goal=CENTRE_GOAL),
    "toy_reach_centre_shifted": replace(_SHIFTED, goal=CENTRE_GOAL),
    "toy_reach_shifted_act3": replace(_SHIFTED, action_size=3),
}
"""Each toy task's look and dynamics; the centre pair differs from the corner pair by its goal only."""


class ToyReachEnv(PixelEnv):
    """Move a dot to a fixed goal, from pixels.

    Observation: ``(S, S, 3)`` uint8 RGB frame (dot drawn with anti-aliased edges, so sub-pixel motion shows).
    Action: ``(A,)`` float32 in [-1, 1], ``A`` the variant's ``action_size``; the first two are the velocity.
    Reward in [0, 1] per step (summed over ``action_repeat``).

    Attributes:
        position: the dot's centre, ``(2,)`` float64 in [-LIMIT, LIMIT]; ``goal``: the goal's centre, ``(2,)``.
        task: the :class:`~coworld.envs.registry.TaskSpec`; ``settings``: the resolved overrides.
    """

    metadata = {**PixelEnv.metadata, "render_fps": 10}  # no simulated time: 5 s per 50-step episode

    def __init__(self, task: TaskSpec, settings: EnvSettings, *, seed: int, variant: ToyVariant) -> None:
        super().__init__(task, settings, variant.action_size, seed)
        self._variant = variant
        size = settings.image_size
        self._start_rng = np.random.default_rng(seed)
        self._drift = np.array(variant.drift)
        self.goal = np.array(variant.goal)
        # World coordinates of pixel centres: column -> x, row -> y (row 0 is the top, y = +1).
        centres = (np.arange(size) + 0.5) / size * 2.0 - 1.0
        self._xs, self._ys = centres, -centres
        self._pixel = 2.0 / size
        self._background = np.empty((size, size, 3), np.float32)
        self._background[:] = variant.background
        self._blend(self._background, self.goal, GOAL_RADIUS, variant.goal_colour)
        self.position = np.zeros(2)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Put the dot at a random start drawn from the episode's seed (:class:`~coworld.envs.base.PixelEnv`)."""
        seed = self._episode_seed(seed)
        super().reset(seed=seed)
        self._start_rng = np.random.default_rng(seed)
        while True:
            start = self._start_rng.uniform(-LIMIT, LIMIT, 2)
            if np.linalg.norm(start - self.goal) >= MIN_START_DISTANCE:
                break
        self.position = start
        self._start_episode()
        self._frame = self._draw()
        return self._frame, {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        action = self._checked(action)
        velocity = np.clip(action[:2], -1.0, 1.0) * SPEED + self._drift
        reward = 0.0
        for _ in range(self.settings.action_repeat):
            self.position = np.clip(self.position + velocity, -LIMIT, LIMIT)
            reward += self.reward(self.position)
        truncated = self._count_step()
        self._frame = self._draw()
        return self._frame, reward, False, truncated, {}

    def reward(self, position: np.ndarray) -> float:
        """The reward at ``position``: :func:`reach_reward` towards this task's goal."""
        return reach_reward(position, self.goal)

    def expert_action(self) -> np.ndarray:
        """A scripted near-optimal action from the true state: full speed at the goal, cancelling the drift.

        Returns ``(A,)`` float32 in [-1, 1] (components past the second 0); used to measure the reference return
        and to script good data.
        """
        wanted = (self.goal - self.position - self._drift) / SPEED
        largest = np.abs(wanted).max()
        if largest > 1.0:
            wanted = wanted / largest
        action = np.zeros(self.action_space.shape, np.float32)
        action[:2] = wanted
        return action

    def _draw(self) -> np.ndarray:
        frame = self._background.copy()
        self._blend(frame, self.position, DOT_RADIUS, self._variant.dot_colour)
        return frame.astype(np.uint8)

    def _blend(self, image: np.ndarray, centre: np.ndarray, radius: float, colour: tuple[int, int, int]) -> None:
        """Paint an anti-aliased disc into ``image`` (``(S, S, 3)`` float32) in place, touching only its box."""
        size = image.shape[0]
        reach = radius + self._pixel
        cols = np.nonzero(np.abs(self._xs - centre[0]) <= reach)[0]
        rows = np.nonzero(np.abs(self._ys - centre[1]) <= reach)[0]
        if cols.size == 0 or rows.size == 0:
            return
        r0, r1, c0, c1 = rows[0], min(rows[-1] + 1, size), cols[0], min(cols[-1] + 1, size)
        dx = self._xs[c0:c1][None, :] - centre[0]
        dy = self._ys[r0:r1][:, None] - centre[1]
        coverage = np.clip((radius - np.sqrt(dx * dx + dy * dy)) / self._pixel + 0.5, 0.0, 1.0)[..., None]
        patch = image[r0:r1, c0:c1]
        patch += coverage * (np.asarray(colour, np.float32) - patch)


def reach_reward(position: np.ndarray, goal: np.ndarray | tuple[float, float] = GOAL) -> float:
    """1 inside the goal disc around ``goal``, linear down to 0 at ``REWARD_MARGIN`` beyond its edge."""
    outside = max(float(np.linalg.norm(np.asarray(position) - goal)) - GOAL_RADIUS, 0.0)
    return max(1.0 - outside / REWARD_MARGIN, 0.0)


def make_toy(task: TaskSpec, settings: EnvSettings, seed: int) -> ToyReachEnv:
    """Build the toy task ``task.name``."""
    return ToyReachEnv(task, settings, seed=seed, variant=VARIANTS[task.name])
