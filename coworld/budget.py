"""What a run will allocate, estimated from its config before anything is built.

Every size in a config is ranged one by one, so ``penalty.ensemble=1000000000`` or ``world_model.deter=1000000000``
pass their ranges and then build for minutes before running out of memory (or overflow). :func:`check_memory`
adds up the largest things a run of an algorithm holds (its weights with their gradients and Adam's two moments,
one batch of inputs and the activations kept for the backward pass, its environment workers) and refuses a config
whose estimate exceeds the machine's memory, in one line naming the key that asks for most. The estimate counts
only the dominant terms, so it stays below what a run really takes: it refuses only what cannot be built, never a
run that fits.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from coworld.algorithms import Algorithm, algorithm
from coworld.config import Config
from coworld.errors import ConfigError

FLOAT = 4
"""Bytes of a float32."""
TRAINED = 4 * FLOAT
"""Bytes a trained weight holds: the weight, its gradient and Adam's two moments."""
IMAGE = 64 * 64 * 3
"""Values of one frame (the size every model here takes)."""
ENV_WORKER = 50 * 2**20
"""Memory of one environment worker process (a simulator and its renderer)."""


@dataclass(frozen=True)
class Term:
    """One part of the estimate: its bytes and the config key that sets its size."""

    bytes: int
    key: str


def estimate(algo: str, config: Config) -> list[Term]:
    """The dominant allocations of a run of ``algo`` (``coworld train --algo``, or ``dreamerv2`` for the collector)
    with ``config``, largest first."""
    record = algorithm(algo)
    terms = _dreamer(config, record) if record.world_model else _model_free(config, record)
    terms.append(Term(config.train.envs * ENV_WORKER, "train.envs"))
    return sorted(terms, key=lambda t: t.bytes, reverse=True)


def _dreamer(config: Config, record: Algorithm) -> list[Term]:
    wm, ac, train = config.world_model, config.actor_critic, config.train
    latent = wm.stoch * wm.classes
    feat = wm.deter + latent
    embed = wm.cnn_depth * 32 * 2 * 2  # the encoder's last feature map, flattened
    agents = 2 if record.collaborative else 1
    batch_key = "train.batch_size" if train.batch_size >= train.seq_len else "train.seq_len"
    terms = [
        Term(agents * TRAINED * 3 * wm.deter * (wm.hidden + wm.deter), "world_model.deter"),  # the GRU cell
        Term(agents * TRAINED * (latent + embed + wm.deter) * wm.hidden, "world_model.hidden"),
        Term(agents * TRAINED * 2 * wm.hidden * latent, "world_model.stoch"),  # prior and posterior logits
        Term(agents * TRAINED * 16 * 42 * wm.cnn_depth**2, "world_model.cnn_depth"),  # encoder and decoder
        Term(agents * TRAINED * 2 * (feat + wm.mlp_layers * wm.mlp_units) * wm.mlp_units, "world_model.mlp_units"),
        Term(agents * TRAINED * 3 * (feat + ac.layers * ac.units) * ac.units, "actor_critic.units"),
        # a batch's frames and the convolutions' activations kept for the backward pass
        Term(FLOAT * train.batch_size * train.seq_len * (IMAGE + 2 * 1529 * wm.cnn_depth), batch_key),
        # imagination: every start state rolled out for the horizon
        Term(FLOAT * train.batch_size * train.seq_len * ac.horizon * (feat + ac.units), "actor_critic.horizon"),
    ]
    own = getattr(config, record.section) if record.section else None
    if hasattr(own, "ensemble"):  # an ensemble of dynamics heads (the penalised DreamerV2, LOMPO)
        per_head = wm.deter * wm.hidden + wm.hidden * latent
        terms.append(Term(TRAINED * own.ensemble * per_head, f"{record.section}.ensemble"))
    if record.section == "lompo":
        terms += _lompo(config, feat)
    if record.section == "ewc":  # the source weights and their Fisher information, beside the networks,
        # and each Fisher batch's gradients, held until their mean is taken
        world_model = 3 * wm.deter * (wm.hidden + wm.deter) + 16 * 42 * wm.cnn_depth**2
        terms.append(Term(FLOAT * 2 * world_model, "world_model.deter"))
        terms.append(Term(FLOAT * config.ewc.fisher_batches * world_model, "ewc.fisher_batches"))
    return terms


def _lompo(config: Config, feat: int) -> list[Term]:
    """LOMPO's latent actor-critic: its weights, and each update's ``lompo.batch_size`` real and as many imagined
    latent transitions (features and next features, kept apart and concatenated) with the activations the actor and
    the twin Q-functions keep of them for the backward pass."""
    lompo = config.lompo
    layers = lompo.actor_layers + 2 * lompo.critic_layers
    activations = lompo.actor_layers + 4 * lompo.critic_layers  # Q-functions on the data and on the actor's actions
    return [
        Term(TRAINED * 3 * (feat + layers * lompo.units) * lompo.units, "lompo.units"),
        Term(FLOAT * 2 * lompo.batch_size * (4 * feat + activations * lompo.units), "lompo.batch_size"),
    ]


def _model_free(config: Config, record: Algorithm) -> list[Term]:
    section = str(record.section)
    c = getattr(config, section)
    side = 64 + 2 * c.pad
    stack = f"{section}.frame_stack"
    channels = 3 * c.frame_stack
    conv = c.num_filters * 9 * (channels + (c.num_layers - 1) * c.num_filters)
    flat = c.num_filters * 35 * 35  # the encoder's output at most (a 3 x 3 stride-2 convolution of 64 + 2 pad)
    return [
        # a batch of observations and next observations, as stored (uint8) and as the encoder takes them (float)
        Term(c.batch_size * 2 * channels * side * side * (1 + FLOAT), stack),
        Term(TRAINED * 3 * (conv + flat * c.feature_dim), f"{section}.num_filters"),  # encoders: actor, critic, target
        Term(TRAINED * 3 * (c.feature_dim + 2 * c.hidden) * c.hidden, f"{section}.hidden"),
        Term(FLOAT * c.batch_size * 2 * c.num_filters * 31 * 31 * c.num_layers, f"{section}.batch_size"),
    ]


def machine_memory() -> int | None:
    """Bytes of physical memory of this machine, or None where the system does not say."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(algo: str, config: Config, available: int | None = None) -> None:
    """Refuse, in one line, a config whose run would allocate more than the machine's memory (``available`` bytes,
    default :func:`machine_memory`)."""
    available = machine_memory() if available is None else available
    if available is None:
        return
    terms = estimate(algo, config)
    total = sum(t.bytes for t in terms)
    if total <= available:
        return
    key = terms[0].key
    value = config
    for part in key.split("."):
        value = getattr(value, part)
    raise ConfigError(
        f"config key {key}={value!r} makes a {algo} run allocate at least {_gib(total)} but this machine has"
        f" {_gib(available)} of memory; lower {key}"
    )


def _gib(n: int) -> str:
    return f"{n / 2**30:,.1f} GiB"
