"""Strict, immutable configuration.

One tree of frozen dataclasses holds every default. Named presets (``tiny`` for CPU, ``paper`` for the
paper's Table 3 on a GPU) are dotted overrides layered on top, and ``--set section.key=value`` overrides
from the command line are layered on the preset. An unknown key raises :class:`~coworld.errors.ConfigError`;
a value is cast to the type of its default and checked against the range written next to its field
(``Annotated[float, Range(0, 1)]``), when the config is built and before anything is written; nothing mutates a
config once built. The resolved config is
saved as JSON next to every run and inside every dataset.
"""

from __future__ import annotations

import dataclasses
import decimal
import json
import math
import re
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

from coworld.errors import ConfigError


@dataclass(frozen=True)
class Range:
    """The valid values of a number: finite, ``low <= x <= high`` (strict where ``*_open``); None is unbounded."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def contains(self, value: float) -> bool:
        if isinstance(value, float) and not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return not (self.high is not None and (value >= self.high if self.high_open else value > self.high))

    def __str__(self) -> str:
        low, high = _number(self.low), _number(self.high)
        if self.low is not None and self.high is not None:
            return f"in {'(' if self.low_open else '['}{low}, {high}{')' if self.high_open else ']'}"
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {low}"
        return f"{'<' if self.high_open else '<='} {high}"


@dataclass(frozen=True)
class OneOf:
    """The valid values of a string: one of ``choices``, or a full match of ``pattern``."""

    choices: tuple[str, ...]
    pattern: str | None = None
    pattern_text: str = ""
    """How ``pattern`` reads in an error message, e.g. ``cuda:N``."""

    def contains(self, value: str) -> bool:
        return value in self.choices or (self.pattern is not None and re.fullmatch(self.pattern, value) is not None)

    def __str__(self) -> str:
        return "one of " + ", ".join(self.choices) + (f" or {self.pattern_text}" if self.pattern else "")


@dataclass(frozen=True)
class Each:
    """The valid values of a tuple of numbers: at least one, each within ``range``."""

    range: Range

    def contains(self, value: tuple[float, ...]) -> bool:
        return len(value) > 0 and all(self.range.contains(item) for item in value)

    def __str__(self) -> str:
        return f"one or more numbers, each {self.range}"


def _number(value: float | None) -> str:
    if value is None:
        return ""
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


ACTIVATIONS = ("elu", "silu", "relu", "gelu", "tanh")
"""Hidden activations, by the names every network's config takes them (DreamerV2: elu; DreamerV3: silu)."""
NORMS = ("none", "layer")
"""Normalisations after a hidden layer, by the names every network's config takes them: none (DreamerV2) or
LayerNorm (DreamerV3)."""

POSITIVE = Range(0, low_open=True)
NON_NEGATIVE = Range(0)
AT_LEAST_1 = Range(1)
UNIT = Range(0, 1)
"""Shorthands for the ranges most fields use."""
PENALTY_WEIGHT = Range(0, 1e12)
"""A penalty's weight: the penalised losses are float32, where 1e300 is already infinite and trains to NaN; 1e12
leaves every term in range while reaching far past any weight that keeps the loss's own part visible."""
LEARNING_RATE = Range(0, 0.1, low_open=True)
"""A learning rate, at most 0.1: every optimiser here is Adam, which moves each weight by about the learning rate per
update, and the methods train at 1e-5 to 1e-3. Above it a run blows up and may still end "done": the tiny preset's
offline DreamerV2 ends its 40 updates with a world-model loss of 2e25 at a world-model rate of 1 (2e32 at 3; NaN
within updates at 1e30), of 1.6e3 at 0.1 (35 at its own 6e-4)."""
COWORLD_WEIGHT = Range(0, 1e3)
"""A weight of CoWorld's terms (beta2, alpha): at 1e3 the term already outweighs the loss it is added to by orders of
magnitude (the papers use 0.2 to 2); above it the target agent learns the term alone, and near float32's limit its
losses overflow to inf."""
MLP_LAYERS = Range(0, 100)
"""Hidden layers of a plain MLP (no normalisation, no residual connections): one of 100,000 layers is slow to build,
and none this deep learns."""


@dataclass(frozen=True)
class WorldModelConfig:
    """DreamerV2 world model: encoder, RSSM, decoder, reward and discount heads (paper Sec. 3.2.1)."""

    cnn_depth: Annotated[int, AT_LEAST_1] = 48
    """Channels of the first conv layer; layers double it (48-96-192-384)."""
    encoder_kernels: Annotated[tuple[int, ...], Each(Range(2, 16))] = (4, 4, 4, 4)
    """Kernel of each stride-2 encoder conv layer, one layer each (DreamerV2: 4, 4, 4, 4); e.g. ``3,3,3,3,3``."""
    decoder_kernels: Annotated[tuple[int, ...], Each(Range(2, 16))] = (5, 5, 6, 6)
    """Kernel of each stride-2 transposed decoder conv from 1 x 1, one layer each; they must end at 64 x 64
    (DreamerV2: 5, 5, 6, 6)."""
    act: Annotated[str, OneOf(ACTIVATIONS)] = "elu"
    """Hidden activation of the conv encoder and decoder and of the RSSM's MLPs (DreamerV2: elu; DreamerV3: silu)."""
    norm: Annotated[str, OneOf(NORMS)] = "none"
    """Normalisation after each hidden layer of the conv stacks (over channels) and the RSSM's MLPs: 'none'
    (DreamerV2) or 'layer' (DreamerV3's LayerNorm)."""
    gru_bias: bool = True
    """A bias in the GRU's gate layer before its LayerNorm (DreamerV2's ``GRUCell`` has one)."""
    gru_eps: Annotated[float, POSITIVE] = 1e-3
    """Epsilon of the GRU's LayerNorm (DreamerV2: Keras's 1e-3)."""
    deter: Annotated[int, AT_LEAST_1] = 600
    """Deterministic GRU state size (Table 3: RSSM 600 units)."""
    hidden: Annotated[int, AT_LEAST_1] = 600
    """Hidden units of the RSSM's input and posterior/prior MLPs."""
    stoch: Annotated[int, AT_LEAST_1] = 32
    """Number of categorical latent variables (Table 3: 32 x 32 discrete latents)."""
    classes: Annotated[int, Range(2)] = 32
    """Classes per categorical latent variable."""
    mlp_units: Annotated[int, AT_LEAST_1] = 400
    """Units per layer of the reward and discount heads."""
    mlp_layers: Annotated[int, NON_NEGATIVE] = 4
    """Layers of the reward and discount heads."""
    mlp_norm: Annotated[str, OneOf(NORMS)] = "none"
    """Normalisation after each hidden layer of the reward and discount heads: 'none' (DreamerV2) or 'layer'
    (DreamerV3)."""
    mlp_act: Annotated[str, OneOf(ACTIVATIONS)] = "elu"
    """Hidden activation of the reward and discount heads (DreamerV2: elu; DreamerV3: silu)."""
    kl_scale: Annotated[float, NON_NEGATIVE] = 1.0
    """beta1 in Eq. 3: weight of KL[posterior || prior]."""
    kl_balance: Annotated[float, UNIT] = 0.8
    """Share of the KL gradient that trains the prior (the rest trains the posterior)."""
    free_nats: Annotated[float, NON_NEGATIVE] = 1.0
    """KL below this many nats (averaged over the batch) gives no gradient."""
    image_scale: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of the image log-likelihood."""
    reward_scale: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of the reward log-likelihood."""
    discount_scale: Annotated[float, NON_NEGATIVE] = 1.0
    """Weight of the discount (continuation) log-likelihood."""
    pred_discount: bool = False
    """Learn a discount head from terminal flags (else imagination uses the constant discount). Off, as in
    DreamerV2's DMC config and the authors' release: no task here terminates, and an untrained head starts at
    P(continue) = 0.5, halving imagination's discount until it has learned."""
    reward_dist: Annotated[str, OneOf(("gaussian", "twohot"))] = "gaussian"
    """Reward head: 'gaussian' (DreamerV2: unit-variance Gaussian, a squared error) or 'twohot' (DreamerV3: 255 bins
    evenly spaced in symlog space, trained by cross-entropy against the two-hot encoding of the reward)."""
    zero_init_reward: bool = False
    """Start the reward head at 0 everywhere (DreamerV3): imagined returns give the actor no direction until the
    head has learned one."""
    unimix: Annotated[float, Range(0, 1, high_open=True)] = 0.0
    """Uniform mixture on the categorical latents (0 = DreamerV2; 0.01 = DreamerV3's)."""
    lr: Annotated[float, LEARNING_RATE] = 2e-4
    """World-model learning rate (Table 3); at most 0.1 (:data:`LEARNING_RATE`)."""
    eps: Annotated[float, POSITIVE] = 1e-5
    """Adam epsilon."""
    weight_decay: Annotated[float, Range(0, 1, high_open=True)] = 1e-6
    """DreamerV2's weight decay: each update first multiplies every weight by ``1 - weight_decay``, whatever the
    learning rate (DreamerV2: 1e-6; done as AdamW with ``weight_decay / lr``, which is the same step)."""
    grad_clip: Annotated[float, POSITIVE] = 100.0
    """Global gradient-norm clip."""


@dataclass(frozen=True)
class ActorCriticConfig:
    """Actor and critic trained in imagination with lambda-returns."""

    units: Annotated[int, AT_LEAST_1] = 400
    """Units per MLP layer of actor and critic."""
    layers: Annotated[int, NON_NEGATIVE] = 4
    """MLP layers of actor and critic."""
    mlp_norm: Annotated[str, OneOf(NORMS)] = "none"
    """Normalisation after each hidden layer of actor and critic: 'none' (DreamerV2's DMC config) or 'layer'
    (DreamerV3's LayerNorm). A norm takes out what a hidden layer's output has in common over all states, so the
    output layer learns from what tells states apart rather than only moving its bias."""
    mlp_act: Annotated[str, OneOf(ACTIVATIONS)] = "elu"
    """Hidden activation of actor and critic (DreamerV2: elu; DreamerV3: silu)."""
    horizon: Annotated[int, Range(2)] = 15
    """Imagination horizon H (Table 3)."""
    discount: Annotated[float, Range(0, 1, low_open=True)] = 0.995
    """gamma (Table 3)."""
    lambda_: Annotated[float, UNIT] = 0.95
    """lambda of the lambda-return (Table 3)."""
    actor_lr: Annotated[float, LEARNING_RATE] = 4e-5
    """Actor learning rate (Table 3); at most 0.1 (:data:`LEARNING_RATE`)."""
    critic_lr: Annotated[float, LEARNING_RATE] = 1e-4
    """Critic learning rate (Table 3); at most 0.1 (:data:`LEARNING_RATE`)."""
    actor_entropy: Annotated[float, NON_NEGATIVE] = 1e-4
    """Entropy regularisation weight of the actor."""
    actor_grad: Annotated[str, OneOf(("dynamics", "reinforce"))] = "dynamics"
    """Actor gradient: 'dynamics' (backprop through the model, DMC default) or 'reinforce'."""
    actor_min_std: Annotated[float, NON_NEGATIVE] = 0.1
    """Lower bound of the actor's standard deviation."""
    actor_max_std: Annotated[float, POSITIVE] = 1.0
    """Upper bound of the actor's standard deviation, 'normal' only (DreamerV3: 1.0)."""
    actor_dist: Annotated[str, OneOf(("trunc_normal", "tanh_normal", "normal"))] = "trunc_normal"
    """Actor distribution: 'trunc_normal' (DreamerV2's DMC choice: truncated to [-1, 1]), 'tanh_normal'
    (DreamerV1's: ``tanh(Normal(m, std))``, entropy estimated from one sample, the squash included, so a mean deep in
    tanh's flat tails lowers it), or 'normal' (DreamerV3's: ``Normal(tanh(m), std)`` with std in [actor_min_std,
    actor_max_std], samples not truncated in imagination and clipped to [-1, 1] when acted). With a truncated normal,
    widening the spread moves the mean action away from a bound, so a return that wants a bound also shrinks the
    spread; an untruncated one does not."""
    critic_dist: Annotated[str, OneOf(("gaussian", "twohot"))] = "gaussian"
    """Critic head: 'gaussian' (DreamerV2: a squared error to the lambda-returns) or 'twohot' (DreamerV3: 255 bins
    in symlog space, cross-entropy against the two-hot encoding of the return)."""
    zero_init_critic: bool = False
    """Start the critic (and its slow target) at 0 everywhere (DreamerV3)."""
    return_norm: bool = False
    """Divide the actor's returns by ``max(1, P95 - P5)`` of recent imagined returns (an EMA of the percentiles),
    so the entropy bonus means the same at any return scale (DreamerV3's return normalisation)."""
    return_norm_decay: Annotated[float, Range(0, 1, high_open=True)] = 0.99
    """EMA decay of the return percentiles (DreamerV3: 0.99)."""
    actor_absmax: bool = False
    """Scale each imagined action sample whose magnitude is above 1 back to the bound, keeping its gradient with the
    scale held fixed (DreamerV3's PyTorch port: ``a * sg(1 / max(|a|, 1))``). Without it an untruncated actor's
    samples beyond [-1, 1] reach the world model, which never saw such actions."""
    actor_advantage: bool = False
    """'dynamics' only: the actor maximises ``R_{t+1} - v(s_t)`` instead of ``R_{t+1}``, with ``v`` the critic that
    makes the targets, differentiated through the imagined states (DreamerV3: its advantage is the objective)."""
    critic_target: Annotated[str, OneOf(("slow", "critic"))] = "slow"
    """Which critic's values the lambda-returns bootstrap from: 'slow' (DreamerV2: the slow target) or 'critic'
    (DreamerV3: the critic itself, the slow target then only regularises it, see ``slow_regulariser``)."""
    slow_regulariser: Annotated[float, NON_NEGATIVE] = 0.0
    """Weight of ``0.5 * (v - sg(v_slow))^2`` added to the critic loss on every imagined state (DreamerV3: 1, with
    ``critic_target='critic'``, ``slow_target_every=1``, ``slow_target_fraction=0.02``)."""
    slow_target_every: Annotated[int, AT_LEAST_1] = 100
    """Updates between copies of the critic into its slow target."""
    slow_target_fraction: Annotated[float, Range(0, 1, low_open=True)] = 1.0
    """Fraction of the critic mixed into the slow target at each copy."""
    eps: Annotated[float, POSITIVE] = 1e-5
    """Adam epsilon."""
    weight_decay: Annotated[float, Range(0, 1, high_open=True)] = 1e-6
    """Weight decay of actor and critic, DreamerV2's kind (see ``world_model.weight_decay``)."""
    grad_clip: Annotated[float, POSITIVE] = 100.0
    """Global gradient-norm clip."""


@dataclass(frozen=True)
class TrainConfig:
    """Batches, schedule and bookkeeping of online (and offline) DreamerV2 training."""

    batch_size: Annotated[int, AT_LEAST_1] = 50
    """Sequences per batch (Table 3: 50)."""
    seq_len: Annotated[int, AT_LEAST_1] = 50
    """Steps per sequence (Table 3: 50)."""
    prefill: Annotated[int, NON_NEGATIVE] = 1000
    """Random-policy environment steps before the first update."""
    pretrain_updates: Annotated[int, NON_NEGATIVE] = 100
    """Extra updates made at once right after the prefill (DreamerV2's ``pretrain``: 100 in its DMC config)."""
    train_every: Annotated[int, AT_LEAST_1] = 5
    """Environment steps per gradient update (the train ratio)."""
    steps: Annotated[int, AT_LEAST_1] = 1_000_000
    """Environment steps (after action repeat) of an online run."""
    eval_every: Annotated[int, AT_LEAST_1] = 10_000
    """Environment steps between evaluations."""
    eval_episodes: Annotated[int, AT_LEAST_1] = 5
    """Episodes per evaluation."""
    log_every: Annotated[int, AT_LEAST_1] = 1000
    """Environment steps between metric logs."""
    checkpoint_every: Annotated[int, AT_LEAST_1] = 10_000
    """Environment steps between checkpoints."""
    envs: Annotated[int, Range(1, 256)] = 1
    """Parallel training environments (worker processes when > 1)."""
    background_updates: bool = False
    """Online runs: each update runs on a background thread while the agent takes the next ``train_every``
    environment steps with a copy of the weights from before it, so acting and learning use two cores at the same
    train ratio; the agent then acts one update behind (:mod:`coworld.training.online`)."""
    backend: Annotated[str, OneOf(("auto", "reference", "cpu"))] = "auto"
    """How the world model's loss is computed. 'reference': the plain PyTorch modules of :mod:`coworld.models`.
    'cpu': the CPU fast path (:mod:`coworld.backends.cpu`), which reads the same weights and is first checked to
    compute the configured model (refused with one line where it cannot). 'auto': the CPU fast path where it applies
    and passes that check (float32 on a CPU, eager), else the reference, with one line saying why."""
    prefetch: bool = True
    """Offline batches (offline DreamerV2 and its variants, the model-free baselines, CoWorld's target data): the
    next batch is drawn from the dataset and laid out for the model on a background thread while the current update
    runs (:mod:`coworld.data.prefetch`), in CoWorld's target phases with the source model's pass over it that the
    alignment term reads (:class:`coworld.agents.coworld.TargetBatches`). The same batches in the same order either
    way, and the same weights trained; off, each is made between updates, on the updates' thread."""
    actor_warmup: Annotated[int, NON_NEGATIVE] = 0
    """Updates that train the world model alone before the actor and critic start learning (0: from the first).
    Until then the agent acts with its untrained actor's wide spread, so the data stay varied while the model
    learns the scene."""
    expl_noise: Annotated[float, NON_NEGATIVE] = 0.0
    """Extra Gaussian noise on training actions."""


@dataclass(frozen=True)
class CoWorldConfig:
    """CoWorld's schedule (Alg. 1) and its three domain-collaborative terms (Eqs. 3-6)."""

    pretrain_steps: Annotated[int, NON_NEGATIVE] = 100_000
    """Online pretraining of the source agent, in source environment steps (the paper gives no number)."""
    iterations: Annotated[int, AT_LEAST_1] = 8
    """Iterations of {K1 target updates; K2 source updates}. The paper trains "until converged" and reports
    600K steps in under 4 days; read as updates of both agents, 8 x (5e4 + 2e4) = 560K is the nearest below."""
    target_updates: Annotated[int, AT_LEAST_1] = 50_000
    """K1 of Alg. 1: target-agent updates per iteration, offline on dataset batches. Table 3 gives 2e4 and 5e4
    with its row names swapped against Alg. 1's symbols; we follow the names ("target domain update steps":
    5e4), so the costly online phase is the shorter one (docs/algorithms.md, "The `paper` preset is Table 3")."""
    source_updates: Annotated[int, AT_LEAST_1] = 20_000
    """K2 of Alg. 1: source-agent updates per iteration, with source environment steps at the train ratio
    (Table 3's "source domain update steps": 2e4)."""
    align: bool = True
    """Eq. 3: align the target encoder to the source encoder on target frames."""
    beta2: Annotated[float, COWORLD_WEIGHT] = 1.5
    """Weight of the alignment KL (Table 3); at most 1e3 (:data:`COWORLD_WEIGHT`)."""
    align_on: Annotated[str, OneOf(("latent", "embedding"))] = "latent"
    """What is aligned: 'latent' (the posterior categorical, paper text) or 'embedding' (release's conv
    embedding through softmax)."""
    reward_relabel: bool = True
    """Eqs. 4-5: train the source reward head on target sequences with relabelled rewards."""
    k: Annotated[float, UNIT] = 0.2
    """Eq. 4's mixing weight (Table 3: 0.2), read as ``relabel`` says."""
    relabel: Annotated[str, OneOf(("table3", "later"))] = "table3"
    """How Eq. 4 reads ``k``: 'table3' (the paper text: ``r = k * r_S_pred + (1 - k) * r_T``) or 'later' (the later
    paper and the release: ``r = (1 - k) * r_S_pred + k * r_T``)."""
    reward_mix: Annotated[str, OneOf(("sum", "eta"))] = "sum"
    """How Eq. 5 joins its source-batch and target-batch terms: 'sum' (the paper text: ``L_S + L_T``) or 'eta' (the
    later paper and the release: ``eta * L_S + (1 - eta) * L_T``, both at ``world_model.reward_scale``)."""
    eta_start: Annotated[float, UNIT] = 1.0
    """Eq. 5's ``eta`` at the first source update after pretraining (``reward_mix='eta'``)."""
    eta_end: Annotated[float, UNIT] = 1.0
    """Eq. 5's ``eta`` at the last; it moves linearly from ``eta_start`` over the run's ``iterations x
    source_updates`` source updates (the later paper: from 1 to 0.1; the release: fixed at 0.9875)."""
    value_reg: bool = True
    """Eq. 6: max-min value regularisation of the target critic by the source critic."""
    alpha: Annotated[float, COWORLD_WEIGHT] = 0.2
    """Weight of the value regulariser (Table 3); at most 1e3 (:data:`COWORLD_WEIGHT`)."""
    zeta: Annotated[float, Range(0, 1e3, low_open=True)] = 1.0
    """Rescales target values against source values in Eq. 6 (the papers: 1; the cap studies: up to 10); at most 1e3:
    the 'shift' form moves a binding state's value ``alpha * zeta`` below its return, which far above it is past any
    return and, squared in the critic's float32 loss, overflows to inf (1e30)."""
    cap_form: Annotated[str, OneOf(("shift", "on_mean"))] = "shift"
    """How Eq. 6's max-min term reaches the target critic: 'shift' (a binding state's fixed point ``alpha * zeta``
    below its lambda-return on every critic: the paper's term on a Gaussian critic, the two-hot critic's target
    lowered by ``alpha * zeta`` where the term binds) or 'on_mean' (the term on the critic's mean: the same on a
    Gaussian, on a two-hot critic a hard clamp ``v_T <= v_S / zeta``, kept to compare with; docs/algorithms.md,
    "Eq. 6 on a two-hot critic")."""
    cap_critic: Annotated[str, OneOf(("source", "target_policy"))] = "source"
    """The critic that caps the target critic in Eq. 6: 'source' (both papers and the release: the source agent's
    critic, the value of the source policy) or 'target_policy' (beyond the papers: a critic in the source agent
    that learns the value of the target actor's behaviour imagined in the source world model, scored by the source
    reward head; docs/algorithms.md, "When the cap binds")."""
    eval_every: Annotated[int, AT_LEAST_1] = 1
    """Iterations between evaluations of the target agent in the target environment."""
    select_batches: Annotated[int, Range(1, 10_000)] = 8
    """Several sources (``--source A,B``): target-dataset batches (``train.batch_size`` x ``train.seq_len``) on
    which each candidate's distance to the target is measured (:mod:`coworld.training.multi_source`; the later paper
    gives no number)."""


@dataclass(frozen=True)
class OfflineConfig:
    """How long the offline DreamerV2 family trains on the target dataset (offline DreamerV2, the penalised DreamerV2,
    LOMPO, and the fine-tuned DreamerV2's target phase), and how often it logs, evaluates and checkpoints.

    Every preset gives it CoWorld's target updates (``coworld.iterations`` x ``coworld.target_updates``), evaluated
    and checkpointed once per CoWorld iteration's worth, so the baselines and CoWorld compare at equal cost: change
    both to keep it so."""

    updates: Annotated[int, AT_LEAST_1] = 400_000
    """Updates on dataset batches (CoWorld's 8 x 5e4 target updates)."""
    log_every: Annotated[int, AT_LEAST_1] = 1000
    """Updates between metric logs."""
    eval_every: Annotated[int, AT_LEAST_1] = 50_000
    """Updates between evaluations in the target environment (CoWorld's one per iteration)."""
    eval_episodes: Annotated[int, AT_LEAST_1] = 5
    """Episodes of each evaluation during training."""
    checkpoint_every: Annotated[int, AT_LEAST_1] = 50_000
    """Updates between checkpoints (CoWorld's one per iteration)."""


@dataclass(frozen=True)
class CurlConfig:
    """CURL (contrastive pixel SAC) and CURL+CQL, trained offline (the paper's model-free baselines).

    Defaults are CURL's DMC settings (Laskin et al., 2020, appendix table; see ``coworld/agents/curl.py``) and
    CQL's Gym-MuJoCo weight; the ``tiny`` preset shrinks the networks and batch for CPU tests.
    """

    frame_stack: Annotated[int, AT_LEAST_1] = 3
    """Stacked frames per observation (CURL: 3)."""
    crop: Annotated[int, AT_LEAST_1] = 64
    """Side of the random crop fed to the encoder; 64 on 64 x 64 frames padded by pad = a random shift."""
    pad: Annotated[int, NON_NEGATIVE] = 4
    """Replicate padding before the random crop (CURL crops 84 from a 100 render; our frames are 64)."""
    feature_dim: Annotated[int, AT_LEAST_1] = 50
    """Encoder output size (CURL: 50)."""
    num_filters: Annotated[int, AT_LEAST_1] = 32
    """Conv channels per layer (CURL: 32)."""
    num_layers: Annotated[int, AT_LEAST_1] = 4
    """Conv layers of the encoder (CURL: 4, first with stride 2)."""
    hidden: Annotated[int, AT_LEAST_1] = 1024
    """Units of the actor and critic MLPs (CURL: 1024)."""
    batch_size: Annotated[int, AT_LEAST_1] = 512
    """Transitions per batch (CURL's table: 512 for cheetah, 128 for the other DMC tasks)."""
    updates: Annotated[int, AT_LEAST_1] = 500_000
    """Gradient updates of an offline run."""
    discount: Annotated[float, Range(0, 1, low_open=True)] = 0.99
    """gamma."""
    actor_lr: Annotated[float, LEARNING_RATE] = 1e-3
    """Actor learning rate (CURL: 1e-3; 2e-4 for cheetah run); at most 0.1 (:data:`LEARNING_RATE`)."""
    critic_lr: Annotated[float, LEARNING_RATE] = 1e-3
    """Critic (and encoder) learning rate (CURL: 1e-3; 2e-4 for cheetah run); at most 0.1 (:data:`LEARNING_RATE`)."""
    encoder_lr: Annotated[float, LEARNING_RATE] = 1e-3
    """Contrastive (CURL) learning rate of the encoder and W (CURL: 1e-3; 2e-4 for cheetah run); at most 0.1
    (:data:`LEARNING_RATE`)."""
    alpha_lr: Annotated[float, LEARNING_RATE] = 1e-4
    """Temperature learning rate (CURL: 1e-4, Adam betas 0.5, 0.999); at most 0.1 (:data:`LEARNING_RATE`)."""
    init_temperature: Annotated[float, POSITIVE] = 0.1
    """Initial SAC temperature (CURL: 0.1); the target entropy is -|A|."""
    critic_tau: Annotated[float, Range(0, 1, low_open=True)] = 0.01
    """Polyak rate of the target Q-heads (CURL: 0.01)."""
    encoder_tau: Annotated[float, Range(0, 1, low_open=True)] = 0.05
    """Polyak rate of the target (key) encoder (CURL: 0.05)."""
    actor_update_every: Annotated[int, AT_LEAST_1] = 2
    """Critic updates per actor and temperature update (CURL: 2)."""
    target_update_every: Annotated[int, AT_LEAST_1] = 2
    """Critic updates per target update (CURL: 2)."""
    cql_weight: Annotated[float, NON_NEGATIVE] = 5.0
    """Weight of the CQL(H) penalty, CURL+CQL only (CQL's min_q_weight for Gym-MuJoCo D4RL: 5)."""
    cql_samples: Annotated[int, AT_LEAST_1] = 10
    """Uniform actions, and policy actions at s and again at s', per state in the CQL log-sum-exp (CQL: 10)."""
    eval_every: Annotated[int, AT_LEAST_1] = 10_000
    """Updates between evaluations."""
    eval_episodes: Annotated[int, AT_LEAST_1] = 5
    """Episodes per evaluation."""
    log_every: Annotated[int, AT_LEAST_1] = 1000
    """Updates between metric logs."""
    checkpoint_every: Annotated[int, AT_LEAST_1] = 10_000
    """Updates between checkpoints."""


@dataclass(frozen=True)
class DrqBcConfig:
    """DrQ+BC (V-D4RL's model-free baseline): DrQ-v2's augmented actor-critic plus TD3+BC's behaviour cloning.

    Defaults are V-D4RL's offline DMC settings (``drqbc/cfgs/config.yaml``, ``cfgs/algo/drqv2.yaml`` and
    ``cfgs/task/offline_dmc.yaml`` of github.com/conglu1997/v-d4rl); the ``tiny`` preset shrinks networks and batch.
    """

    frame_stack: Annotated[int, AT_LEAST_1] = 3
    """Stacked frames per observation (V-D4RL ``frame_stack: 3``)."""
    pad: Annotated[int, NON_NEGATIVE] = 4
    """Random shift: pad this many replicated pixels, crop back to 64 (DrQ-v2 ``RandomShiftsAug(pad=4)``)."""
    num_filters: Annotated[int, AT_LEAST_1] = 32
    """Conv channels per layer (DrQ-v2 encoder: 32)."""
    num_layers: Annotated[int, Range(1, 16)] = 4
    """Conv layers, the first with stride 2 (DrQ-v2 encoder: 4; at most 16 leave a pixel of a 64 x 64 frame)."""
    feature_dim: Annotated[int, AT_LEAST_1] = 50
    """Size of the actor's and critic's ``Linear -> LayerNorm -> tanh`` trunk (V-D4RL ``feature_dim: 50``)."""
    hidden: Annotated[int, AT_LEAST_1] = 1024
    """Units of the actor and critic MLPs (``hidden_dim: 1024``)."""
    batch_size: Annotated[int, AT_LEAST_1] = 256
    """Transitions per batch (``batch_size: 256``)."""
    updates: Annotated[int, AT_LEAST_1] = 550_000
    """Gradient updates of a run: V-D4RL trains ``num_train_frames: 1100000`` steps with an update every
    ``update_every_steps: 2``."""
    lr: Annotated[float, LEARNING_RATE] = 3e-4
    """Learning rate of encoder, actor and critic (``offline_dmc.yaml``: ``lr: 3e-4``); at most 0.1
    (:data:`LEARNING_RATE`)."""
    discount: Annotated[float, Range(0, 1, low_open=True)] = 0.99
    """gamma (``discount: 0.99``)."""
    critic_tau: Annotated[float, Range(0, 1, low_open=True)] = 0.01
    """Polyak rate of the target critic (``critic_target_tau: 0.01``)."""
    bc_weight: Annotated[float, NON_NEGATIVE] = 2.5
    """alpha of TD3+BC: the Q term is scaled by ``alpha / mean|Q|`` (``bc_weight: 2.5``; Fujimoto & Gu 2021, Eq. 5)."""
    std_init: Annotated[float, POSITIVE] = 1.0
    """Exploration std of the actor at update 0 (``stddev_schedule: linear(1.0,0.1,250000)``)."""
    std_final: Annotated[float, POSITIVE] = 0.1
    """Exploration std at the end of the schedule (the same schedule)."""
    std_updates: Annotated[int, AT_LEAST_1] = 125_000
    """Updates over which the std falls linearly: the schedule's 250,000 steps at one update every 2 steps."""
    std_clip: Annotated[float, POSITIVE] = 0.3
    """Clip of the actor's noise (``stddev_clip: 0.3``)."""
    eval_every: Annotated[int, AT_LEAST_1] = 5000
    """Updates between evaluations (``eval_every_frames: 10000`` steps = 5,000 updates)."""
    eval_episodes: Annotated[int, AT_LEAST_1] = 10
    """Episodes per evaluation (``num_eval_episodes: 10``)."""
    log_every: Annotated[int, AT_LEAST_1] = 1000
    """Updates between metric logs (``show_train_stats_every_frames: 2000`` steps)."""
    checkpoint_every: Annotated[int, AT_LEAST_1] = 10_000
    """Updates between checkpoints."""


@dataclass(frozen=True)
class PenaltyConfig:
    """V-D4RL's offline DreamerV2: imagined rewards minus ``weight`` times the disagreement of an ensemble of
    dynamics (prior) heads.

    Values from github.com/conglu1997/v-d4rl ``offlinedv2``: its ``configs.yaml`` (``rssm.ensemble: 7``,
    ``offline_model_train_steps: 25001``) and its README's DMC command (``--offline_penalty_type meandis
    --offline_lmbd 10``). The rest of the agent is this project's DreamerV2 (``world_model``, ``actor_critic``) and
    its schedule is offline DreamerV2's (``offline``).
    """

    ensemble: Annotated[int, Range(2)] = 7
    """Dynamics heads ``deter -> prior logits`` whose disagreement is the penalty (``rssm.ensemble: 7``)."""
    weight: Annotated[float, PENALTY_WEIGHT] = 10.0
    """lambda: imagined reward ``r - lambda * disagreement`` (README command: ``--offline_lmbd 10``)."""
    model_updates: Annotated[int, NON_NEGATIVE] = 25_000
    """Updates at the start that train the world model (and heads) alone; after them the world model is frozen and
    only the actor-critic learns (``offline_model_train_steps: 25001``, then ``agent_train``)."""


@dataclass(frozen=True)
class LompoConfig:
    """LOMPO (Rafailov et al., 2021): a latent actor-critic trained on real latent transitions of the dataset and on
    short rollouts of an ensemble of latent dynamics, their reward lowered by the ensemble's disagreement.

    Values from V-D4RL's ``baselines/lompo/run.py`` (github.com/conglu1997/v-d4rl), named after its keys. The world
    model is this project's DreamerV2 (``world_model``) and the run's length offline DreamerV2's (``offline.updates``).
    """

    ensemble: Annotated[int, Range(2)] = 7
    """Latent dynamics heads ``deter -> z`` (``num_models: 7``)."""
    weight: Annotated[float, PENALTY_WEIGHT] = 5.0
    """lambda: imagined reward ``r - lambda * std_k log p_k(z')`` (``lmbd: 5.0``, ``penalty_type: log_prob``)."""
    model_updates: Annotated[int, NON_NEGATIVE] = 25_000
    """Updates at the start that train the world model (and heads) alone; after them the world model is frozen and
    only the actor-critic learns (``model_train_steps: 25000``)."""
    horizon: Annotated[int, Range(1, 1000)] = 5
    """Steps of each latent rollout (``horizon: 5``); at most 1,000: the steps are made one after another, and a
    longer rollout only compounds the model's error."""
    batch_size: Annotated[int, AT_LEAST_1] = 256
    """Real latent transitions per update, and as many imagined ones (``agent_batch_size: 256`` of each)."""
    units: Annotated[int, AT_LEAST_1] = 256
    """Units per hidden layer of the actor and the Q-functions (``num_units: 256``)."""
    actor_layers: Annotated[int, MLP_LAYERS] = 4
    """Hidden layers of the deterministic actor (``ActorNetwork(..., 4, num_units)``)."""
    critic_layers: Annotated[int, MLP_LAYERS] = 3
    """Hidden layers of each of the two Q-functions (``DenseNetwork(1, 3, num_units)``)."""
    actor_lr: Annotated[float, LEARNING_RATE] = 3e-4
    """Actor learning rate (``actor_lr: 3e-4``); at most 0.1 (:data:`LEARNING_RATE`)."""
    critic_lr: Annotated[float, LEARNING_RATE] = 3e-4
    """Q-functions' learning rate (``q_lr: 3e-4``); at most 0.1 (:data:`LEARNING_RATE`)."""
    discount: Annotated[float, Range(0, 1, low_open=True)] = 0.99
    """gamma (``discount: 0.99``)."""
    tau: Annotated[float, Range(0, 1, low_open=True)] = 5e-3
    """Polyak rate of the target Q-functions, every update (``tau: 5e-3``, ``target_update_interval: 1``)."""
    expl_noise: Annotated[float, NON_NEGATIVE] = 0.2
    """Std of the Gaussian noise on the actor's actions in rollouts and when acting to train
    (``expl_amount: 0.2``, ``expl: additive_gaussian``); evaluation acts without it."""
    grad_clip: Annotated[float, POSITIVE] = 100.0
    """Global gradient-norm clip of actor and Q-functions (``grad_clip: 100.0``)."""


@dataclass(frozen=True)
class EwcConfig:
    """DreamerV2 fine-tuned with elastic weight consolidation (Kirkpatrick et al., 2017): after pretraining in the
    source, every network's loss on the target data gains ``weight / 2 * sum_i F_i (theta_i - theta*_i)^2`` toward
    the source weights ``theta*``, ``F`` the diagonal Fisher information estimated on the source's experience.

    The later CoWorld paper names the baseline (DV2 Finetune-EWC) without its settings; the values here are this
    project's choice (docs/algorithms.md)."""

    weight: Annotated[float, PENALTY_WEIGHT] = 1.0
    """lambda of EWC. ``F`` estimates the Fisher of one step's loss, so 1 weighs keeping the source's fit as much as
    one more target step's loss (Kirkpatrick et al.'s scale)."""
    fisher_batches: Annotated[int, Range(1, 10_000)] = 50
    """Source replay batches (``train.batch_size`` x ``train.seq_len``) averaged into the Fisher estimate; at most
    10,000, as each batch's gradients are held until their mean is taken."""


@dataclass(frozen=True)
class Config:
    """Everything a run needs besides its task names and paths."""

    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    actor_critic: ActorCriticConfig = field(default_factory=ActorCriticConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    coworld: CoWorldConfig = field(default_factory=CoWorldConfig)
    offline: OfflineConfig = field(default_factory=OfflineConfig)
    curl: CurlConfig = field(default_factory=CurlConfig)
    seed: Annotated[int, Range(0, 2**32 - 1)] = 0
    """Seed of torch, NumPy and the environments."""
    device: Annotated[str, OneOf(("auto", "cpu", "cuda"), pattern=r"cuda:\d+", pattern_text="cuda:N")] = "auto"
    """'auto' (CUDA when available), 'cpu' or 'cuda'."""
    precision: Annotated[str, OneOf(("auto", "bf16", "fp32"))] = "auto"
    """'auto' (fp32 on every device), 'bf16' (autocast) or 'fp32'. Eager, the paper preset's update on a GPU is
    bound by kernel launches, not arithmetic, so bf16's casts make it slower; with ``compile``, which fuses the small
    operations, bf16 is the fastest setting (benchmarks/RESULTS.md, "GPU"). 'auto' stays fp32, as bf16's learning
    over a run is unmeasured."""
    compile: bool = False
    """torch.compile the reference world model's loss and the imagination rollout, each as one graph
    (``fullgraph``), and the networks acting calls. Shapes are static: a batch of another size compiles anew. The
    compiled run takes the reference path (``train.backend``). On a GPU it pays for its compilation (shorter in a later
    process that finds inductor's cache on disk) within the first few thousand updates of the paper preset, most with
    ``precision=bf16``; its cost and gain per device are in benchmarks/RESULTS.md."""
    compile_mode: Annotated[str, OneOf(("default", "max-autotune-no-cudagraphs"))] = "default"
    """torch.compile's ``mode`` where ``compile`` is on: 'max-autotune-no-cudagraphs' also times kernel choices.
    The modes that replay CUDA graphs ('reduce-overhead', 'max-autotune') are refused: their graphs overwrite the
    world model's posterior states before imagination reads them (benchmarks/RESULTS.md, "GPU")."""
    drqbc: DrqBcConfig = field(default_factory=DrqBcConfig)
    penalty: PenaltyConfig = field(default_factory=PenaltyConfig)
    lompo: LompoConfig = field(default_factory=LompoConfig)
    ewc: EwcConfig = field(default_factory=EwcConfig)


CUDA_GRAPH_MODES = ("reduce-overhead", "max-autotune")
"""torch.compile modes that replay CUDA graphs, which :func:`validate` refuses: their graphs overwrite the world
model's posterior states before imagination reads them (benchmarks/RESULTS.md, "GPU")."""

PRESETS: dict[str, dict[str, Any]] = {
    # The paper's Table 3, for a GPU.
    "paper": {},
    # Real learning on 2 CPU cores: the tiny networks with an update every 2 env steps, on batch 8 x 16 (64 replayed
    # steps per env step). Batch 16 x 32 (a ratio of 256, the one the side-by-side comparison with a reference
    # Dreamer matched) learned no better and held expert level less well on toy_reach, with 4x the replayed steps per
    # update (benchmarks/RESULTS.md, "The `cpu` preset on toy_reach").
    "cpu": {
        "world_model.cnn_depth": 8,
        # The GRU every result of this preset was measured with: no gate bias, LayerNorm epsilon 1e-5 (the paper
        # preset has DreamerV2's bias and 1e-3).
        "world_model.gru_bias": False,
        "world_model.gru_eps": 1e-5,
        "world_model.deter": 64,
        "world_model.hidden": 64,
        "world_model.stoch": 8,
        "world_model.classes": 8,
        "world_model.mlp_units": 64,
        "world_model.mlp_layers": 2,
        "world_model.lr": 6e-4,
        "actor_critic.units": 64,
        "actor_critic.layers": 2,
        "actor_critic.horizon": 10,
        "actor_critic.discount": 0.99,
        "actor_critic.actor_lr": 2e-4,
        "actor_critic.critic_lr": 3e-4,
        # DreamerV3's behaviour learning and heads on DreamerV2's world model (benchmarks/archive/
        # speed-work-notes.md, "The actor collapse"): normalised returns, advantages through the dynamics, a critic
        # that bootstraps from itself with the slow critic as a regulariser, two-hot reward head and critic that start
        # at zero (so the actor keeps its spread until rewards differ), LayerNorm + SiLU heads, 1% unimix latents. The
        # actor is DreamerV1's tanh-squashed normal, whose entropy counts the squash, so a mean pushed into tanh's flat
        # tails costs entropy and can come back (DreamerV3's Normal(tanh(m), std) left one action dimension pinned at
        # +1 on 2 seeds in 4).
        "actor_critic.actor_dist": "tanh_normal",
        "actor_critic.return_norm": True,
        "actor_critic.actor_entropy": 3e-4,
        "actor_critic.actor_advantage": True,
        "actor_critic.critic_target": "critic",
        "actor_critic.slow_regulariser": 1.0,
        "actor_critic.slow_target_every": 1,
        "actor_critic.slow_target_fraction": 0.02,
        "actor_critic.critic_dist": "twohot",
        "actor_critic.zero_init_critic": True,
        "actor_critic.mlp_norm": "layer",
        "actor_critic.mlp_act": "silu",
        "world_model.reward_dist": "twohot",
        "world_model.zero_init_reward": True,
        "world_model.mlp_norm": "layer",
        "world_model.mlp_act": "silu",
        "world_model.unimix": 0.01,
        "train.batch_size": 8,
        "train.seq_len": 16,
        "train.prefill": 500,
        "train.pretrain_updates": 10,
        "train.train_every": 2,
        "train.steps": 100_000,
        "train.eval_every": 1000,
        "train.eval_episodes": 10,
        "train.log_every": 500,
        "train.checkpoint_every": 1000,
        "coworld.pretrain_steps": 4000,
        "coworld.iterations": 4,
        "coworld.target_updates": 500,
        "coworld.source_updates": 250,
        "offline.updates": 2000,
        "offline.log_every": 500,
        "offline.eval_every": 500,
        "offline.eval_episodes": 10,
        "offline.checkpoint_every": 500,
        # LOMPO's latent actor-critic at the actor-critic's widths here; half the run's 2,000 updates for its model
        "lompo.model_updates": 1000,
        "lompo.batch_size": 64,
        "lompo.units": 64,
        "lompo.actor_layers": 2,
        "lompo.critic_layers": 2,
        "ewc.fisher_batches": 20,
    },
    # Small enough that a whole collect -> train -> eval runs on 2 CPU cores in minutes.
    "tiny": {
        "world_model.cnn_depth": 8,
        # The GRU every result of this preset was measured with: no gate bias, LayerNorm epsilon 1e-5 (the paper
        # preset has DreamerV2's bias and 1e-3).
        "world_model.gru_bias": False,
        "world_model.gru_eps": 1e-5,
        "world_model.deter": 64,
        "world_model.hidden": 64,
        "world_model.stoch": 8,
        "world_model.classes": 8,
        "world_model.mlp_units": 64,
        "world_model.mlp_layers": 2,
        "world_model.lr": 6e-4,
        "actor_critic.units": 64,
        "actor_critic.layers": 2,
        "actor_critic.horizon": 10,
        "actor_critic.discount": 0.99,
        "actor_critic.actor_lr": 2e-4,
        "actor_critic.critic_lr": 3e-4,
        "actor_critic.slow_target_every": 20,
        "train.batch_size": 8,
        "train.seq_len": 16,
        "train.prefill": 500,
        "train.pretrain_updates": 10,
        "train.train_every": 10,
        "train.steps": 2000,
        "train.eval_every": 1000,
        "train.eval_episodes": 2,
        "train.log_every": 250,
        "train.checkpoint_every": 500,
        "coworld.pretrain_steps": 1000,
        "coworld.iterations": 2,
        "coworld.target_updates": 20,
        "coworld.source_updates": 20,
        "offline.updates": 40,
        "offline.log_every": 20,
        "offline.eval_every": 20,
        "offline.eval_episodes": 2,
        "offline.checkpoint_every": 20,
        "drqbc.num_filters": 8,
        "drqbc.num_layers": 2,
        "drqbc.feature_dim": 16,
        "drqbc.hidden": 64,
        "drqbc.batch_size": 32,
        "drqbc.updates": 200,
        "drqbc.std_updates": 100,
        "drqbc.eval_every": 100,
        "drqbc.eval_episodes": 2,
        "drqbc.log_every": 50,
        "drqbc.checkpoint_every": 100,
        "penalty.ensemble": 3,
        "penalty.model_updates": 10,
        "lompo.ensemble": 3,
        "lompo.model_updates": 10,
        "lompo.batch_size": 32,
        "lompo.units": 64,
        "lompo.actor_layers": 2,
        "lompo.critic_layers": 2,
        "ewc.fisher_batches": 5,
        "curl.num_filters": 8,
        "curl.num_layers": 2,
        "curl.feature_dim": 16,
        "curl.hidden": 64,
        "curl.batch_size": 32,
        "curl.updates": 200,
        "curl.eval_every": 100,
        "curl.eval_episodes": 2,
        "curl.log_every": 50,
        "curl.checkpoint_every": 100,
    },
}


DREAMERV2_BEHAVIOUR: dict[str, Any] = {
    "actor_critic.critic_dist": "gaussian",
    "actor_critic.critic_target": "slow",
    "actor_critic.slow_target_every": 100,
    "actor_critic.slow_target_fraction": 1.0,
    "actor_critic.slow_regulariser": 0.0,
    "actor_critic.return_norm": False,
    "world_model.reward_dist": "gaussian",
}
"""DreamerV2's behaviour learning where the ``cpu`` preset has DreamerV3's: a unit Gaussian critic whose
lambda-returns bootstrap from a slow critic copied every 100 updates, a Gaussian reward head, returns not normalised.
The critic and heads the paper's Eqs. 4-6 are written for (and the authors' release runs: ``value_head: normal``, a
slow target every 100 updates), at the ``cpu`` preset's sizes: the ``cpu-dv2`` preset."""
PRESETS["cpu-dv2"] = {**PRESETS["cpu"], **DREAMERV2_BEHAVIOUR}

SETTINGS: dict[str, dict[str, Any]] = {
    # The paper text's Table 3: the defaults.
    "table3": {},
    # The later paper (arXiv 2305.15260 v4, NeurIPS 2024), its Table 8 for DMC: beta2 1.5, k 0.9 in its Eq. 4
    # ((1 - k) * pred + k * r_T), alpha 1, no zeta; Eq. 5 weighted by an eta falling from 1 to 0.1; Eq. 3 on
    # softmaxed encoder embeddings.
    "later-dmc": {
        "coworld.beta2": 1.5,
        "coworld.k": 0.9,
        "coworld.relabel": "later",
        "coworld.alpha": 1.0,
        "coworld.zeta": 1.0,
        "coworld.reward_mix": "eta",
        "coworld.eta_start": 1.0,
        "coworld.eta_end": 0.1,
        "coworld.align_on": "embedding",
    },
    # The same paper's Table 8 for Meta-World (and its RoboDesk targets): beta2 1, k 0.3, alpha 2.
    "later-metaworld": {
        "coworld.beta2": 1.0,
        "coworld.k": 0.3,
        "coworld.relabel": "later",
        "coworld.alpha": 2.0,
        "coworld.zeta": 1.0,
        "coworld.reward_mix": "eta",
        "coworld.eta_start": 1.0,
        "coworld.eta_end": 0.1,
        "coworld.align_on": "embedding",
    },
    # The authors' release (qiwang067/CoWorld at 8bc8aaa): co_configs.yaml's beta_2 1, reward_k 0.3, alpha 1.5 in
    # every suite; Eq. 4 as (1 - k) * pred + k * r_T (models.py:108); Eq. 6 without zeta; Eq. 5's eta = max(1 - step
    # / 2e5, 0.2) with a step fixed when the model is built, after the 2,500 prefill steps: 0.9875 throughout.
    "release": {
        "coworld.beta2": 1.0,
        "coworld.k": 0.3,
        "coworld.relabel": "later",
        "coworld.alpha": 1.5,
        "coworld.zeta": 1.0,
        "coworld.reward_mix": "eta",
        "coworld.eta_start": 0.9875,
        "coworld.eta_end": 0.9875,
        "coworld.align_on": "embedding",
    },
}
"""CoWorld's settings as each version of the method gives them, chosen with a preset as ``SIZE+SETTINGS`` (e.g.
``cpu+later-dmc``): the sizes come from the preset, the terms' weights and forms from these."""


def settings_overrides(name: str) -> tuple[str, ...]:
    """A group of :data:`SETTINGS` as ``key=value`` overrides (a sweep variant's ``--set``)."""
    return tuple(f"{key}={value}" for key, value in SETTINGS[name].items())


def split_preset(name: str) -> tuple[str, str]:
    """``'cpu+later-dmc'`` -> ``('cpu', 'later-dmc')``; ``'cpu'`` -> ``('cpu', 'table3')``. One ConfigError line for
    a name that is neither."""
    size, _, settings = name.partition("+")
    settings = settings or "table3"
    if size not in PRESETS or settings not in SETTINGS:
        raise ConfigError(
            f"unknown preset {name!r}; choose one of: {', '.join(PRESETS)}, optionally followed by +SETTINGS, one of"
            f" {', '.join(SETTINGS)} (e.g. cpu+later-dmc)"
        )
    return size, settings


def canonical_preset(name: str) -> str:
    """The one name of a preset: ``'tiny'``, ``'tiny+'`` and ``'tiny+table3'`` are ``'tiny'``; ``'cpu+later-dmc'``
    stays. Raises ConfigError as :func:`split_preset` does."""
    size, settings = split_preset(name)
    return size if settings == "table3" else f"{size}+{settings}"


def make_config(preset: str = "paper", overrides: Iterable[str] | Mapping[str, Any] = ()) -> Config:
    """Build a config from a preset (``SIZE`` or ``SIZE+SETTINGS``: :data:`PRESETS`, :data:`SETTINGS`) plus
    ``key=value`` strings or a ``{dotted.key: value}`` mapping."""
    size, settings = split_preset(preset)
    config = apply_overrides(Config(), {**PRESETS[size], **SETTINGS[settings]})
    if isinstance(overrides, Mapping):
        config = apply_overrides(config, overrides)
    else:
        config = apply_overrides(config, parse_overrides(overrides))
    validate(config)
    return config


def validate(config: Config) -> None:
    """Check every value against the range next to its field, and the few rules that tie fields together.

    Raises :class:`ConfigError` naming the first bad key, its value and what it may be.
    """
    if config.compile_mode in CUDA_GRAPH_MODES:
        raise ConfigError(
            f"config key compile_mode={config.compile_mode} replays CUDA graphs, which overwrite the world model's"
            " posterior states before imagination reads them; use compile_mode=default"
        )
    for dotted, value, constraint in _constrained_values(config):
        if not constraint.contains(value):
            raise ConfigError(f"config key {dotted}={value!r} is out of range: it must be {constraint}")
    _validate_conv_stacks(config.world_model)
    ac = config.actor_critic
    if ac.actor_min_std > ac.actor_max_std:
        raise ConfigError(
            f"config keys actor_critic.actor_min_std={ac.actor_min_std} and actor_critic.actor_max_std="
            f"{ac.actor_max_std}: the least spread is above the most; swap them"
        )
    curl = config.curl
    padded = 64 + 2 * curl.pad  # frames are 64 x 64 (the image size every model here takes)
    if curl.crop > padded:
        raise ConfigError(
            f"config key curl.crop={curl.crop} is larger than the padded frame ({padded} = 64 + 2 * curl.pad)"
        )
    side = (curl.crop - 3) // 2 + 1 - 2 * (curl.num_layers - 1)  # 3x3 convs, the first with stride 2
    if side < 1:
        raise ConfigError(
            f"config keys curl.crop={curl.crop} and curl.num_layers={curl.num_layers} leave no pixels after the"
            " convolutions; use fewer layers or a larger crop"
        )


def _validate_conv_stacks(wm: WorldModelConfig) -> None:
    """The encoder's kernels leave at least one pixel of a 64 x 64 image; the decoder's end at 64 x 64."""
    side = 64
    for kernel in wm.encoder_kernels:
        side = (side - kernel) // 2 + 1
    if side < 1:
        raise ConfigError(
            f"config key world_model.encoder_kernels={wm.encoder_kernels!r} leaves no pixels of a 64 x 64 image;"
            " use fewer or smaller kernels"
        )
    side = 1
    for kernel in wm.decoder_kernels:
        side = (side - 1) * 2 + kernel
    if side != 64:
        raise ConfigError(
            f"config key world_model.decoder_kernels={wm.decoder_kernels!r} decodes {side} x {side} images, not"
            " 64 x 64 (each layer maps side s to 2 (s - 1) + kernel, from 1)"
        )


def _constrained_values(node: Any, prefix: str = "") -> Iterable[tuple[str, Any, Range | OneOf | Each]]:
    hints = typing.get_type_hints(type(node), include_extras=True)
    for f in dataclasses.fields(node):
        value = getattr(node, f.name)
        if dataclasses.is_dataclass(value):
            yield from _constrained_values(value, f"{prefix}{f.name}.")
            continue
        for constraint in getattr(hints[f.name], "__metadata__", ()):
            if isinstance(constraint, (Range, OneOf, Each)):
                yield prefix + f.name, value, constraint


def parse_overrides(items: Iterable[str]) -> dict[str, str]:
    """Turn ``["a.b=1", "c=x"]`` into ``{"a.b": "1", "c": "x"}``."""
    parsed = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"bad override {item!r}: write it as section.key=value, e.g. train.steps=5000")
        parsed[key.strip()] = value.strip()
    return parsed


def apply_overrides(config: Any, overrides: Mapping[str, Any]) -> Any:
    """Return a copy of ``config`` with dotted keys replaced; values are cast to the defaults' types."""
    for dotted, value in overrides.items():
        config = _replace(config, dotted.split("."), value, dotted)
    return config


def _replace(node: Any, path: list[str], value: Any, dotted: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(node)}
    name = path[0]
    if name not in fields:
        raise ConfigError(f"unknown config key {dotted!r}; valid keys: {', '.join(sorted(config_keys(node)))}")
    current = getattr(node, name)
    if dataclasses.is_dataclass(current):
        if len(path) == 1:
            raise ConfigError(f"config key {dotted!r} is a section; set one of its keys, e.g. {dotted}.<key>=...")
        return dataclasses.replace(node, **{name: _replace(current, path[1:], value, dotted)})
    if len(path) > 1:
        raise ConfigError(f"unknown config key {dotted!r}: {'.'.join(dotted.split('.')[: -len(path) + 1])} is a value")
    hint = typing.get_type_hints(type(node))[name]
    return dataclasses.replace(node, **{name: _cast(value, hint, dotted)})


def _cast(value: Any, hint: Any, dotted: str) -> Any:
    if isinstance(hint, types.UnionType):
        hint = next(arg for arg in typing.get_args(hint) if arg is not type(None))
    if typing.get_origin(hint) is tuple:  # tuple[int, ...]: "4,4,4", "[4, 4, 4]" (as `coworld config` prints it)
        items = _list_items(value) if isinstance(value, str) else value  # or a list saved as JSON
        try:
            return tuple(_cast(item, int, dotted) for item in items)
        except (ConfigError, TypeError):
            raise ConfigError(f"config key {dotted!r} takes whole numbers separated by commas, got {value!r}") from None
    try:
        if hint is bool:
            if isinstance(value, bool):
                return value
            text = str(value).lower()
            if text in ("true", "1", "yes", "on"):
                return True
            if text in ("false", "0", "no", "off"):
                return False
            raise ValueError(value)
        if hint is int:
            return _whole_number(value, dotted)
        if hint is float:
            if isinstance(value, bool):
                raise ValueError(value)
            return float(value)
        if hint is str:
            return str(value)
    except (TypeError, ValueError):
        kind = {int: "a whole number", float: "a number", bool: "true or false"}.get(hint, hint.__name__)
        raise ConfigError(f"config key {dotted!r} takes {kind}, got {value!r}") from None
    raise ConfigError(f"config key {dotted!r} has unsupported type {hint}")


def _list_items(text: str) -> list[str]:
    """The items of ``"4,4,4"`` or of a JSON-style list ``"[4, 4, 4]"``."""
    text = text.strip()
    if text.startswith("[") and text.endswith("]"):
        text = text[1:-1]
    return text.split(",")


INT_LIMIT = 2**63 - 1
"""The largest magnitude of an integer config value: what a 64-bit counter (NumPy, torch) holds."""


def _whole_number(value: Any, dotted: str) -> int:
    """``value`` as an exact integer (``"5000"``, ``"5e3"``, ``5000.0``), within :data:`INT_LIMIT`; a fraction, a
    bool or a number beyond the limit raises ConfigError (``int(float("1e30"))`` would be silently inexact)."""
    if isinstance(value, bool):
        raise ValueError(value)
    try:
        exact = decimal.Decimal(str(value).strip())
    except decimal.InvalidOperation:
        raise ValueError(value) from None
    if not exact.is_finite() or exact != exact.to_integral_value():
        raise ValueError(value)
    if abs(exact) > INT_LIMIT:
        raise ConfigError(f"config key {dotted!r} takes a whole number up to {INT_LIMIT:,}, got {value!r}")
    return int(exact)


def config_keys(node: Any, prefix: str = "") -> list[str]:
    """Every dotted leaf key of a config tree."""
    keys = []
    for f in dataclasses.fields(node):
        value = getattr(node, f.name)
        if dataclasses.is_dataclass(value):
            keys += config_keys(value, f"{prefix}{f.name}.")
        else:
            keys.append(prefix + f.name)
    return keys


def to_dict(config: Config) -> dict[str, Any]:
    """The config as a nested plain dict (what is saved as JSON)."""
    return dataclasses.asdict(config)


def to_json(config: Config) -> str:
    return json.dumps(to_dict(config), indent=2, sort_keys=True)


LEGACY_DEFAULTS: dict[str, Any] = {
    "world_model.gru_bias": False,
    "world_model.gru_eps": 1e-5,
    "coworld.cap_form": "on_mean",
}
"""What a saved config without these keys (written before they existed) computed: its GRU had no gate bias and
LayerNorm's epsilon 1e-5, and Eq. 6's term read the critic's mean (on a two-hot critic, the clamp). Keys added
later with a default that computes what the older code did are not listed."""
LEGACY_NORM_KEYS = ("world_model.mlp_norm", "actor_critic.mlp_norm")
"""Norms a config saved before they took norm names held as true / false (LayerNorm or none)."""


def from_dict(data: Mapping[str, Any]) -> Config:
    """Rebuild a config saved with :func:`to_dict`; unknown keys raise ConfigError."""
    flat: dict[str, Any] = {}

    def walk(node: Mapping[str, Any], prefix: str) -> None:
        for key, value in node.items():
            if isinstance(value, Mapping):
                walk(value, f"{prefix}{key}.")
            else:
                flat[prefix + key] = value

    walk(data, "")
    for key, value in LEGACY_DEFAULTS.items():
        flat.setdefault(key, value)
    for key in LEGACY_NORM_KEYS:
        if isinstance(flat.get(key), bool):
            flat[key] = "layer" if flat[key] else "none"
    config = apply_overrides(Config(), flat)
    validate(config)
    return config


def first_difference(saved: Mapping[str, Any], now: Mapping[str, Any], prefix: str = "") -> str:
    """The first key where two nested dicts (saved configs, say) differ, as ``'key: saved X, now Y'``; '' when
    they are equal."""
    for key in sorted(set(saved) | set(now)):
        a, b = saved.get(key), now.get(key)
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            found = first_difference(a, b, f"{prefix}{key}.")
            if found:
                return found
        elif a != b:
            return f"{prefix}{key}: saved {a!r}, now {b!r}"
    return ""
