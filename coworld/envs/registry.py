"""The task registry: every source and target task of the paper, the later paper's RoboDesk targets, two toy pairs.

Every task is a Gymnasium env whose observation is the image itself: ``Box(0, 255, (S, S, 3), uint8)`` RGB,
``S = 64`` by default. Actions: ``Box(-1, 1, (A,), float32)``. Episodes never terminate; they truncate after
``episode_length`` agent steps.

Returns in :class:`TaskSpec`:

* ``reference_return`` -- the best return known to be reachable on the task, with its provenance in
  ``reference_source``. It sets the medium level of the medium-replay and medium datasets (the paper: "1/3 of the
  maximum score that the DreamerV2 agent can achieve"; where that is below random, a third of the way from random:
  :attr:`TaskSpec.medium_return`) and the top of the normalized score.

  - ``walker_walk`` 964.9 and ``cheetah_run`` 816.1: DreamerV2's published DMC-vision scores (the scores file
    released with its code, ``scores/dmc-vision-dreamerv2.json``): the maximum over its 2M-frame training curve of
    the mean evaluation return of its 5 seeds.
  - The modified DMC tasks have no published DreamerV2 score; they use the plain task's (walker 964.9, cheetah
    816.1). On a harder variant DreamerV2 may never reach a third of it (the later CoWorld paper reports 225 for
    its best agent on cheetah_uphill): a medium-replay collection there runs to its step limit.
  - Meta-World has no published DreamerV2 return for these tasks; the stand-in is the larger of the mean return
    of Meta-World's scripted expert policy on our setup (10 episodes, ``benchmarks/reference_returns.py``) and
    the best mean return any agent reaches on the task in the CoWorld paper's Table 2.
  - RoboDesk has no published return either: our scripted policy's mean return where it solves the task
    (push_button), else the dense reward's ceiling (see ``_ROBODESK_REFERENCE``).
  - Toy tasks: the scripted :meth:`~coworld.envs.toy.ToyReachEnv.expert_action` policy.
* ``random_return`` -- mean return of uniformly random actions (how measured: comments at ``_DMC`` and ``_TOY``).
  Meta-World's have a large spread (drawer-close 1334 +- 1788: random arms sometimes shut the drawer).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from coworld.envs.render import check_render_quality
from coworld.envs.spec import EnvSettings, Family, TaskSpec
from coworld.errors import ConfigError, UnknownTaskError

if TYPE_CHECKING:
    import gymnasium as gym

# Mean returns of uniform random actions: 10 episodes, episode i drawing its initial state with seed i and its
# actions from numpy.random.default_rng(i).uniform(-1, 1) (tests/envs/test_returns.py re-measures some).
_DMC = [
    # name, modification, base, random_return
    ("walker_walk", "", "dm_control walker-walk", 41.7),
    ("walker_downhill", "15-degree downhill slope", "dm_control walker-walk", 76.4),
    ("walker_uphill", "15-degree uphill slope", "dm_control walker-walk", 27.5),
    ("walker_nofoot", "right foot cannot be controlled (right_ankle motor gear 0)", "dm_control walker-walk", 40.4),
    ("cheetah_run", "", "dm_control cheetah-run", 5.6),
    ("cheetah_downhill", "15-degree downhill slope", "dm_control cheetah-run", 43.2),
    ("cheetah_uphill", "15-degree uphill slope", "dm_control cheetah-run", 0.4),
    (
        "cheetah_nopaw",
        "front paw and two joints cannot be controlled (fthigh, fshin, ffoot motors gear 0)",
        "dm_control cheetah-run",
        11.5,
    ),
]

_METAWORLD = [
    # name, Meta-World name, random_return
    ("mw_window_close", "window-close-v3", 328.9),
    ("mw_handle_press", "handle-press-v3", 286.8),
    ("mw_drawer_close", "drawer-close-v3", 1334.5),
    ("mw_stick_push", "stick-push-v3", 9.8),
    ("mw_door_close", "door-close-v3", 43.8),
    ("mw_button_press_topdown", "button-press-topdown-v3", 178.4),
    ("mw_button_press", "button-press-v3", 177.1),
    ("mw_assembly", "assembly-v3", 211.9),
]

# DreamerV2's published DMC-vision scores (danijar/dreamerv2, scores/dmc-vision-dreamerv2.json): the maximum over
# the training curve (30k to 1.98M frames) of the 5-seed mean evaluation return.
_DREAMERV2_DMC = {"walker": 964.9, "cheetah": 816.1}

# Meta-World stand-ins: (scripted expert mean return, 10 episodes, benchmarks/reference_returns.py;
# best mean return in the CoWorld paper's Table 2 where the task is a target there, else None).
_METAWORLD_REFERENCE = {
    "mw_window_close": (3616.8, None),
    "mw_handle_press": (1338.4, 3903.0),
    "mw_drawer_close": (4256.0, None),
    "mw_stick_push": (1266.0, None),
    "mw_door_close": (2139.1, 3419.0),
    "mw_button_press_topdown": (3791.7, 3794.0),
    "mw_button_press": (564.1, 3623.0),
    "mw_assembly": (1193.5, 1397.0),
}

# RoboDesk tasks (coworld/envs/robodesk.py): our name, RoboDesk's task name (with RoboDesk's dense reward, as the
# later CoWorld paper used them), random_return (measured as _DMC's, without drawing frames:
# `benchmarks/reference_returns.py --robodesk --episodes 10`).
_ROBODESK = [
    ("robodesk_push_button", "push_green", 227.5),
    ("robodesk_open_slide", "open_slide", 172.3),
    ("robodesk_drawer_open", "open_drawer", 152.3),
    ("robodesk_upright_block_off_table", "upright_block_off_table", 139.4),
]

# RoboDesk has no published DreamerV2 return. Our scripted policies (coworld.envs.experts.ROBODESK_WAYPOINTS, 10
# episodes, same command) reach: push_button 394.1 (pressed 10/10), open_slide 224.4 (0/10 opened), drawer_open
# 157.8 (0/10), upright_block_off_table 175.8 (1/10). Where one solves the task its return is the stand-in; where
# none does, the dense reward's ceiling (500 steps at the reward's per-step maximum: 1, or 0.4 for the block, whose
# reward as RoboDesk 1.0.0 computes it is 0.15 + 0.25 * reach).
_ROBODESK_CEILING = "no published return and no scripted policy of ours solves it; stand-in: the dense reward's ceiling"
_ROBODESK_REFERENCE: dict[str, tuple[float, str]] = {
    "robodesk_push_button": (
        394.1,
        "no published return; stand-in: our scripted policy (presses the button 10/10), mean of 10 episodes",
    ),
    "robodesk_open_slide": (500.0, f"{_ROBODESK_CEILING} (500 steps x 1)"),
    "robodesk_drawer_open": (500.0, f"{_ROBODESK_CEILING} (500 steps x 1)"),
    "robodesk_upright_block_off_table": (200.0, f"{_ROBODESK_CEILING} (500 steps x 0.4)"),
}

# Toy returns: 200 episodes, seeds 0-199, the env's own seeded action sampler (tests/envs/test_toy.py).
_TOY = [
    # name, modification, reference_return (scripted expert), random_return, action size
    ("toy_reach", "", 46.5, 9.6, 2),
    ("toy_reach_shifted", "other colours; constant drift towards -x", 45.6, 2.3, 2),
    ("toy_reach_centre", "goal at the centre", 48.5, 20.3, 2),
    ("toy_reach_centre_shifted", "goal at the centre; other colours; constant drift towards -x", 48.4, 18.3, 2),
    ("toy_reach_shifted_act3", "as toy_reach_shifted; a 3rd action component, ignored (for tests)", 45.6, 2.2, 3),
]


def _metaworld_reference(name: str) -> tuple[float, str]:
    expert, paper = _METAWORLD_REFERENCE[name]
    if paper is not None and paper > expert:
        return paper, "no published DreamerV2 return; stand-in: best mean return in the CoWorld paper's Table 2"
    return expert, "no published DreamerV2 return; stand-in: Meta-World's scripted expert, mean of 10 episodes"


def _build_tasks() -> dict[str, TaskSpec]:
    tasks: list[TaskSpec] = []
    for name, modification, base, random_return in _DMC:
        domain = name.split("_")[0]
        plain = {"walker": "walker_walk", "cheetah": "cheetah_run"}[domain]
        source = "DreamerV2's published DMC-vision score (max of the 5-seed mean curve)"
        if name != plain:
            source = f"no published DreamerV2 score; stand-in: {plain}'s DreamerV2 score"
        reference = _DREAMERV2_DMC[domain]
        tasks.append(TaskSpec(name, "dmc", 6, 500, 2, modification, base, reference, random_return, source))
    for name, mw_name, random_return in _METAWORLD:
        reference, source = _metaworld_reference(name)
        base = f"Meta-World {mw_name}"
        tasks.append(TaskSpec(name, "metaworld", 4, 500, 1, "", base, reference, random_return, source))
    for name, robodesk_name, random_return in _ROBODESK:
        reference, source = _ROBODESK_REFERENCE[name]
        base = f"RoboDesk {robodesk_name} (dense reward)"
        tasks.append(TaskSpec(name, "robodesk", 5, 500, 1, "", base, reference, random_return, source))
    for name, modification, reference_return, random_return, action_size in _TOY:
        base = "NumPy dot-to-goal reaching"
        source = "scripted expert policy, mean of 200 episodes"
        tasks.append(
            TaskSpec(name, "toy", action_size, 50, 1, modification, base, reference_return, random_return, source)
        )
    return {task.name: task for task in tasks}


TASKS: dict[str, TaskSpec] = _build_tasks()
"""Every task by name."""

PAIRS: tuple[tuple[str, str], ...] = (
    ("walker_walk", "walker_downhill"),
    ("walker_walk", "walker_uphill"),
    ("walker_walk", "walker_nofoot"),
    ("cheetah_run", "cheetah_downhill"),
    ("cheetah_run", "cheetah_uphill"),
    ("cheetah_run", "cheetah_nopaw"),
    ("mw_window_close", "mw_door_close"),
    ("mw_handle_press", "mw_button_press_topdown"),
    ("mw_drawer_close", "mw_handle_press"),
    ("mw_drawer_close", "mw_button_press"),
    ("mw_stick_push", "mw_assembly"),
    ("mw_button_press", "robodesk_push_button"),
    ("mw_window_close", "robodesk_open_slide"),
    ("mw_drawer_close", "robodesk_drawer_open"),
    ("mw_handle_press", "robodesk_upright_block_off_table"),
    ("toy_reach", "toy_reach_shifted"),
    ("toy_reach_centre", "toy_reach_centre_shifted"),
)
"""(source, target) pairs: the paper's DMC and Meta-World transfer settings, the later paper's Meta-World -> RoboDesk
pairs (another robot with another action size), and the two toy pairs."""


def paired_source(target: str) -> str | None:
    """The source task the paper pairs with ``target`` (:data:`PAIRS`), or None where it pairs none."""
    return next((source for source, paired in PAIRS if paired == target), None)


def task_spec(name: str) -> TaskSpec:
    """The :class:`TaskSpec` of ``name``; raises :class:`UnknownTaskError` listing the valid names."""
    try:
        return TASKS[name]
    except (KeyError, TypeError):
        raise UnknownTaskError(f"unknown task {name!r}; valid tasks: {', '.join(TASKS)}") from None


_COMMON_OVERRIDES = ("image_size", "action_repeat", "episode_length")
_OVERRIDES: dict[str, tuple[str, ...]] = {
    "dmc": (*_COMMON_OVERRIDES, "render_quality"),
    "metaworld": (*_COMMON_OVERRIDES, "render_quality"),
    "robodesk": (*_COMMON_OVERRIDES, "render_quality"),
    "toy": _COMMON_OVERRIDES,
}


def resolve_settings(task: TaskSpec, overrides: Mapping[str, Any]) -> EnvSettings:
    """Validate ``overrides`` for ``task`` and fill in the defaults; raises :class:`ConfigError` on bad input."""
    valid = _OVERRIDES[task.family]
    for key in overrides:
        if key not in valid:
            raise ConfigError(f"unknown env override {key!r} for {task.name}; valid overrides: {', '.join(valid)}")
    image_size = _positive_int(overrides.get("image_size", 64), "image_size")
    action_repeat = _positive_int(overrides.get("action_repeat", task.action_repeat), "action_repeat")
    budget = task.episode_length * task.action_repeat
    default_length = budget // action_repeat
    if default_length < 1:
        raise ConfigError(f"action_repeat {action_repeat} exceeds {task.name}'s {budget} simulator steps per episode")
    episode_length = _positive_int(overrides.get("episode_length", default_length), "episode_length")
    settings = EnvSettings(image_size, action_repeat, episode_length)
    if "render_quality" in overrides:
        settings = replace(settings, render_quality=check_render_quality(overrides["render_quality"]))
    return settings


def _positive_int(value: Any, key: str) -> int:
    if isinstance(value, bool):
        raise ConfigError(f"env override {key} takes a positive integer, got {value!r}")
    try:
        number = int(value)
    except (TypeError, ValueError):
        raise ConfigError(f"env override {key} takes a positive integer, got {value!r}") from None
    if number < 1 or number != float(value):
        raise ConfigError(f"env override {key} takes a positive integer, got {value!r}")
    return number


def _builder(family: Family) -> Callable[[TaskSpec, EnvSettings, int], gym.Env]:
    # Simulators are imported only when a task of their family is built.
    if family == "dmc":
        from coworld.envs.dmc import make_dmc

        return make_dmc
    if family == "metaworld":
        from coworld.envs.meta_world import make_metaworld

        return make_metaworld
    if family == "robodesk":
        from coworld.envs.robodesk import make_robodesk

        return make_robodesk
    from coworld.envs.toy import make_toy

    return make_toy


def make(name: str, seed: int = 0, **overrides: Any) -> gym.Env:
    """Build task ``name`` as a pixel Gymnasium env.

    Args:
        name: a key of :data:`TASKS`.
        seed: the first episode's seed (the first ``reset()`` without a seed uses it; each later one the next of
            a chain from it, :class:`~coworld.envs.base.PixelEnv`) and the action space sampler's. An episode's
            seed and actions give identical frames; ``reset(seed=s)`` restarts the chain at ``s``.
        **overrides: ``image_size`` (64), ``action_repeat`` (task's), ``episode_length`` (agent steps; default
            keeps the task's simulator-step budget), and for MuJoCo tasks ``render_quality`` ('standard').

    Returns:
        The env; ``env.unwrapped.task`` is its :class:`TaskSpec`, ``env.unwrapped.settings`` its
        :class:`EnvSettings`. Unknown names raise :class:`UnknownTaskError`, bad overrides :class:`ConfigError`.
    """
    task = task_spec(name)
    settings = resolve_settings(task, overrides)
    env = _builder(task.family)(task, settings, int(seed))
    env.action_space.seed(int(seed))
    return env
