"""The algorithms ``coworld train`` runs: one record each, and every part that treats algorithms differently reads it.

A record names the algorithm's agent, its checkpoint and its config section, and says what it needs (a source task,
the dataset's sequences or single transitions, a world model) and so what the rest can do with its runs: ``eval``
and ``viz`` look inside a world model only where there is one, ``report`` shows CoWorld's cap and ablations only
for the algorithm that has them. Adding an algorithm is its agent, its config section and one record here
(docs/architecture.md, "Adding an algorithm").

This module imports nothing of the package: every layer may read it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal

DREAMER_KNOBS: Mapping[str, tuple[str, ...]] = {
    "wm": ("world_model.lr",),
    "actor": ("actor_critic.actor_lr",),
    "critic": ("actor_critic.critic_lr",),
}
"""The config keys that scale what a DreamerV2 agent's networks learn, by metric group (``wm/loss``,
``actor/loss``): what a line about a diverged loss says to lower."""

_CURL_KNOBS: Mapping[str, tuple[str, ...]] = {
    "curl": ("curl.encoder_lr",),
    "actor": ("curl.actor_lr",),
    "critic": ("curl.critic_lr",),
    "alpha": ("curl.alpha_lr",),
}


@dataclass(frozen=True)
class Algorithm:
    """What one algorithm is, needs and offers."""

    name: str
    """``--algo``: how commands, run folders (``run.json``) and reports name it."""
    agent: str
    """``module:Class`` in :mod:`coworld.agents` of the agent whose policy is evaluated (for CoWorld: the target
    agent); built with :attr:`options` as keyword arguments."""
    checkpoint: str
    """The kind its checkpoints are saved as; a checkpoint of another kind is refused in its run folder."""
    column: int
    """Its place in the report's tables, lowest first: the papers' order, model-free first, then model-based, CoWorld
    last."""
    section: str | None = None
    """The config section of its own settings, beyond DreamerV2's (``world_model``, ``actor_critic``, ``train``)."""
    source: Literal["", "carried", "any"] = ""
    """What it needs of a source task, learned online beside the target's dataset: '' none (the dataset alone);
    'carried' one source of the target's action size, whose networks are carried over to the target; 'any' one
    source or several to choose among, of any action sizes (CoWorld)."""
    world_model: bool = True
    """It trains DreamerV2's world model: it reads ``train.backend``, learns from the dataset's sequences of
    ``train.seq_len``, and ``coworld viz`` can look inside its runs."""
    sampler: str | None = None
    """``module:function`` in :mod:`coworld.agents` making its dataset sampler (``function(dataset, config, seed)``);
    None: sequences of ``train.batch_size`` x ``train.seq_len``."""
    min_seq_len: int = 1
    """The shortest ``train.seq_len`` its updates can learn from."""
    schedule: str = "offline"
    """The config section of its length and its log, evaluation and checkpoint cadence: ``updates``, ``log_every``,
    ``eval_every``, ``eval_episodes`` and ``checkpoint_every`` (``offline``: the offline DreamerV2 family's, which
    every preset sets to CoWorld's target updates; ``coworld``: Alg. 1's iterations)."""
    discount: str = "actor_critic.discount"
    """The config key of the discount its evaluation's value check compares against."""
    collaborative: bool = False
    """CoWorld: two agents, the target's and the source's, and the terms of Eqs. 3-6 with their switches; ``eval``
    reads the capping critic too, ``report`` shows the cap and the ablations."""
    options: Mapping[str, Any] = field(default_factory=dict)
    """Keyword arguments its agent class is built with (CURL+CQL is CURL with ``cql=True``)."""
    knobs: Mapping[str, tuple[str, ...]] = field(default_factory=lambda: DREAMER_KNOBS)
    """The config keys that scale what each of its networks learns, by metric group: what a line about a diverged
    loss says to lower."""

    @property
    def needs_source(self) -> bool:
        return bool(self.source)

    def length(self, config: Any) -> str:
        """How long a run of this config trains, and the settings that say so (for messages)."""
        cw = config.coworld
        if self.schedule == "coworld":
            text = f"{cw.iterations * cw.target_updates:,} target updates (coworld.iterations x coworld.target_updates)"
        else:
            text = f"{getattr(config, self.schedule).updates:,} updates ({self.schedule}.updates)"
        if self.needs_source:  # the same source pretraining as CoWorld's source agent
            text += f" after {cw.pretrain_steps:,} source env steps (coworld.pretrain_steps)"
        return text


_CURL = Algorithm(
    "curl",
    agent="curl:Curl",
    checkpoint="curl",
    column=0,
    section="curl",
    world_model=False,
    sampler="curl:make_sampler",
    schedule="curl",
    discount="curl.discount",
    options={"cql": False},
    knobs=_CURL_KNOBS,
)
"""CURL; CURL+CQL is it with ``cql=True`` and the CQL weight among its critic's knobs."""

REGISTRY: tuple[Algorithm, ...] = (
    Algorithm(
        "coworld",
        agent="dreamerv2:DreamerV2",
        checkpoint="coworld",
        column=99,  # last, whatever is added
        section="coworld",
        schedule="coworld",
        source="any",
        collaborative=True,
        knobs={
            **DREAMER_KNOBS,
            "wm": ("world_model.lr", "coworld.beta2"),
            "critic": ("actor_critic.critic_lr", "coworld.alpha"),
        },
    ),
    Algorithm("dreamerv2", agent="dreamerv2:DreamerV2", checkpoint="dreamerv2-offline", column=3),
    _CURL,
    replace(
        _CURL,
        name="curl-cql",
        checkpoint="curl-cql",
        column=1,
        options={"cql": True},
        knobs={**_CURL_KNOBS, "critic": ("curl.critic_lr", "curl.cql_weight")},
    ),
    Algorithm(
        "drq-bc",
        agent="drq_bc:DrqBc",
        checkpoint="drq-bc",
        column=2,
        section="drqbc",
        world_model=False,
        sampler="drq_bc:make_sampler",
        schedule="drqbc",
        discount="drqbc.discount",
        knobs={"actor": ("drqbc.lr", "drqbc.bc_weight"), "critic": ("drqbc.lr",)},
    ),
    Algorithm(
        "dreamerv2-penalty",
        agent="dreamerv2_penalty:PenaltyDreamerV2",
        checkpoint="dreamerv2-penalty",
        column=4,
        section="penalty",
        knobs={
            **DREAMER_KNOBS,
            "actor": ("actor_critic.actor_lr", "penalty.weight"),
            "critic": ("actor_critic.critic_lr", "penalty.weight"),
        },
    ),
    Algorithm(
        "dreamerv2-finetune",
        agent="dreamerv2:DreamerV2",
        checkpoint="dreamerv2-finetune",
        column=6,
        source="carried",
    ),
    Algorithm(
        "lompo",
        agent="lompo:Lompo",
        checkpoint="lompo",
        column=5,
        section="lompo",
        min_seq_len=2,
        discount="lompo.discount",
        knobs={"wm": ("world_model.lr",), "actor": ("lompo.actor_lr",), "critic": ("lompo.critic_lr", "lompo.weight")},
    ),
    Algorithm(
        "dreamerv2-finetune-ewc",
        agent="dreamerv2_ewc:EwcDreamerV2",
        checkpoint="dreamerv2-finetune-ewc",
        column=7,
        section="ewc",
        source="carried",
        knobs={group: (*keys, "ewc.weight") for group, keys in DREAMER_KNOBS.items()},
    ),
)
"""Every algorithm, in the order ``--algo`` lists them (CoWorld first: the default)."""

ALGOS: tuple[str, ...] = tuple(a.name for a in REGISTRY)
_BY_NAME = {a.name: a for a in REGISTRY}


def algorithm(name: str) -> Algorithm:
    """The record of ``name``; ValueError for a name no record holds (callers check user input first, with
    :data:`ALGOS` in their message)."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r}") from None


def names(**traits: Any) -> tuple[str, ...]:
    """The algorithms whose records have every trait given (``names(world_model=False)``: the model-free ones),
    in :data:`REGISTRY` order; ``needs_source`` is a trait too."""
    return tuple(a.name for a in REGISTRY if all(getattr(a, key) == value for key, value in traits.items()))


def by_column(found: Any) -> list[str]:
    """The names in ``found`` in the report's column order; names no record holds follow, sorted."""
    found = set(found)
    ordered = sorted((a for a in REGISTRY if a.name in found), key=lambda a: a.column)
    return [a.name for a in ordered] + sorted(found - set(_BY_NAME))


def is_collaborative(name: Any) -> bool:
    """Whether ``name`` is a collaborative algorithm's (CoWorld's); False for any other name, known or not."""
    return isinstance(name, str) and name in _BY_NAME and _BY_NAME[name].collaborative
