"""DreamerV2's actor and critic, trained on trajectories imagined by the world model.

Imagination starts from ``N`` posterior states (the flattened ``B * T`` states of a world-model batch) and rolls
the prior forward ``H`` steps with actions from the actor. A trajectory ``traj`` is a dict of tensors with
leading ``(H + 1, N)``; index 0 is the start state (its ``action`` entry is zeros)::

    Actions:        0   [a1]  [a2]   a3          a_{t+1} is taken in state t and leads to state t+1
    States:     [z0] -> [z1] -> z2 -> z3
    Targets:     R0    [R1]  [R2]                lambda-returns, bootstrapped from the slow critic (or the critic)
    Weights:    [ 1]   [w1]   w2    w3           cumulative predicted discount of reaching the state

The critic regresses ``v(z_t)`` to ``sg(R_t)`` for ``t < H``; the actor maximises ``R_{t+1}`` for ``t < H-1``
(backpropagating through the dynamics; with ``actor_advantage`` minus ``v(z_t)``) or uses REINFORCE with the value
as baseline, plus an entropy bonus. ``critic_target='critic'`` bootstraps from the critic itself and
``slow_regulariser`` pulls it towards its slow target instead (DreamerV3).
With ``return_norm`` the actor's returns are first divided by ``max(1, P95 - P5)`` of recent returns (DreamerV3).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from coworld.config import ActorCriticConfig
from coworld.distributions import (
    Normal,
    TanhNormal,
    TruncatedNormal,
    TwoHotSymlog,
    UnitGaussian,
)
from coworld.errors import ConfigError
from coworld.losses.dreamer import actor_loss, critic_loss, lambda_return
from coworld.models.networks import MLP, frozen_parameters
from coworld.models.rssm import State
from coworld.models.world_model import ScalarHead, WorldModel

__all__ = ["Actor", "ActorCritic", "CriticObjective", "flatten_states"]

CriticObjective = Callable[[Tensor, UnitGaussian | TwoHotSymlog, Tensor, Tensor], tuple[Tensor, dict[str, Tensor]]]
"""``(feat (H, N, F), value, lambda-returns (H, N), weight (H, N)) -> (loss (H, N), metrics)``: the critic's loss in
place of DreamerV2's :func:`~coworld.losses.dreamer.critic_loss` (CoWorld's Eq. 6,
:func:`~coworld.losses.coworld.regularised_critic_loss`); ``feat`` are the detached features of the states the
critic is fitted on, ``value`` its distribution there (with gradient)."""

ACTOR_DISTS = ("trunc_normal", "tanh_normal", "normal")
ACTOR_GRADS = ("dynamics", "reinforce")


def flatten_states(state: State) -> State:
    """Posterior states with batch ``(B, T)`` -> detached start states with batch ``(N,) = (B * T,)``."""
    deter = state["deter"]
    n = deter.shape[:-1].numel()
    return {key: value.detach().reshape(n, *value.shape[deter.ndim - 1 :]) for key, value in state.items()}


def _stack_imagined(states: list[State], feat: Tensor, world_model: WorldModel) -> State:
    """The imagined states with batch ``(H + 1, N)``: ``deter`` and (where its dtype is the features') ``stoch`` as
    views of the stacked features ``feat (H + 1, N, D + S K)``, which hold them already, rather than two more
    stacked copies."""
    rssm = world_model.rssm
    state = {"deter": feat[..., : rssm.deter_size], "logits": torch.stack([s["logits"] for s in states])}
    stoch = feat[..., rssm.deter_size :].unflatten(-1, (rssm.stoch, rssm.classes))
    state["stoch"] = stoch if stoch.dtype == states[0]["stoch"].dtype else torch.stack([s["stoch"] for s in states])
    return state


class Actor(nn.Module):
    """MLP policy over continuous actions in ``[-1, 1]``: features ``(..., F)`` -> distribution over ``(..., A)``.

    ``trunc_normal`` (DreamerV2's DMC choice): ``loc = tanh(m)``, ``scale = 2 * sigmoid(s / 2) + min_std``,
    truncated to ``[-1, 1]``. ``tanh_normal``: ``Normal(m, softplus(s + softplus^-1(1)) + min_std)`` squashed
    by ``tanh``. ``normal`` (DreamerV3's): ``Normal(tanh(m), (max_std - min_std) * sigmoid(s + 2) + min_std)``,
    not truncated (the agent clips what it executes).
    """

    def __init__(
        self,
        *,
        feat_size: int,
        action_size: int,
        units: int,
        layers: int,
        dist: str,
        min_std: float,
        max_std: float = 1.0,
        norm: str = "none",
        act: str = "elu",
    ) -> None:
        super().__init__()
        if dist not in ACTOR_DISTS:
            raise ConfigError(f"unknown actor_critic.actor_dist {dist!r}; choose one of: {', '.join(ACTOR_DISTS)}")
        self.dist = dist
        self.min_std = min_std
        self.max_std = max_std
        self.mlp = MLP(in_size=feat_size, out_size=2 * action_size, units=units, layers=layers, norm=norm, act=act)

    def forward(self, feat: Tensor) -> TruncatedNormal | TanhNormal | Normal:
        """``(..., F)`` -> action distribution, event ``(A,)``."""
        return self.distribution(self.mlp(feat))

    def distribution(self, out: Tensor) -> TruncatedNormal | TanhNormal | Normal:
        """The action distribution of the MLP's output ``(..., 2 A)``."""
        mean, std = out.float().chunk(2, dim=-1)
        if self.dist == "trunc_normal":
            return TruncatedNormal(torch.tanh(mean), 2.0 * torch.sigmoid(std / 2.0) + self.min_std, -1.0, 1.0)
        if self.dist == "normal":
            spread = (self.max_std - self.min_std) * torch.sigmoid(std + 2.0) + self.min_std
            return Normal(torch.tanh(mean), spread)
        return TanhNormal(mean, F.softplus(std + math.log(math.e - 1.0)) + self.min_std)


class ActorCritic(nn.Module):
    """Actor, critic and the critic's slow target, with DreamerV2's imagination losses."""

    updates: Tensor
    return_range: Tensor

    def __init__(self, *, config: ActorCriticConfig, feat_size: int, action_size: int) -> None:
        super().__init__()
        if config.actor_grad not in ACTOR_GRADS:
            raise ConfigError(
                f"unknown actor_critic.actor_grad {config.actor_grad!r}; choose one of: {', '.join(ACTOR_GRADS)}"
            )
        self.config = config
        self.action_size = action_size
        mlp = {"units": config.units, "layers": config.layers, "norm": config.mlp_norm, "act": config.mlp_act}
        self.actor = Actor(
            feat_size=feat_size,
            action_size=action_size,
            dist=config.actor_dist,
            min_std=config.actor_min_std,
            max_std=config.actor_max_std,
            **mlp,
        )
        self.critic = ScalarHead(feat_size=feat_size, dist=config.critic_dist, **mlp)
        if config.zero_init_critic:
            self.critic.mlp.zero_output()
        self.slow_critic = copy.deepcopy(self.critic)
        self.slow_critic.requires_grad_(False)
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))
        if config.return_norm:  # only then, so checkpoints of runs without it load as they are
            self.register_buffer("return_range", torch.zeros(2))
            """EMA of the 5th and 95th percentiles of imagined returns."""

    def return_scale(self, target: Tensor) -> Tensor:
        """With ``return_norm``: update the percentile EMA with ``target`` and return ``max(1, P95 - P5)``
        (DreamerV3); else 1. ``target`` is any shape; returns a detached scalar."""
        if not self.config.return_norm:
            return torch.ones((), device=target.device)
        with torch.no_grad():
            flat = target.detach().float().reshape(-1)
            quantiles = torch.quantile(flat, torch.tensor([0.05, 0.95], device=flat.device))
            decay = self.config.return_norm_decay
            self.return_range.mul_(decay).add_(quantiles, alpha=1.0 - decay)
            return (self.return_range[1] - self.return_range[0]).clamp_min(1.0)

    def critic_value(self, feat: Tensor) -> Tensor:
        """The critic's mean value ``(...)`` of features ``(..., F)`` (no sampling; gradient kept)."""
        return self.critic(feat).mean

    @torch.no_grad()
    def update_slow_target(self) -> None:
        """Every ``slow_target_every`` calls (starting with the first), mix the critic into its slow target:
        ``slow <- fraction * critic + (1 - fraction) * slow``; the first call copies it whole (DreamerV2). Called
        after the critic's optimiser step."""
        if int(self.updates) % self.config.slow_target_every == 0:
            mix = 1.0 if int(self.updates) == 0 else self.config.slow_target_fraction
            for slow, fast in zip(self.slow_critic.parameters(), self.critic.parameters(), strict=True):
                slow.mul_(1.0 - mix).add_(fast, alpha=mix)
        self.updates += 1

    def imagine(
        self,
        world_model: WorldModel,
        start: State,
        horizon: int | None = None,
        is_terminal: Tensor | None = None,
        actor: Actor | None = None,
    ) -> dict[str, Tensor | State]:
        """Roll the world model's prior forward ``horizon`` steps (default ``config.horizon``) from ``start``.

        ``start``: RSSM states with batch ``(N,)`` (see :func:`flatten_states`); they are detached here.
        ``is_terminal (N,)``, if given, replaces the predicted continuation of the start states by the true one.
        ``actor``: the policy that acts in imagination, this one's own when None (another agent's: CoWorld's
        target-policy critic, :class:`coworld.agents.policy_value.PolicyValue`).
        Returns ``traj`` with ``'feat' (H+1, N, F)``, ``'action' (H+1, N, A)`` (zeros at 0), ``'state'``
        (states with batch ``(H+1, N)``), ``'reward' (H+1, N)`` (the reward head's mean),
        ``'continuation' (H+1, N)`` (``gamma * P(continue)``), ``'weight' (H+1, N)`` (detached
        ``prod_{i<t} continuation_i``) and ``'actor_out' (H, N, 2 A)``, the actor's outputs in the states
        ``0..H-1`` (:meth:`losses` reuses them rather than running the actor on those states again). With
        ``actor_grad='dynamics'`` actions are reparameterised samples and everything downstream carries their
        gradient.
        """
        horizon = self.config.horizon if horizon is None else horizon
        actor = self.actor if actor is None else actor
        state = {key: value.detach() for key, value in start.items()}
        n = state["deter"].shape[0]
        reparam = self.config.actor_grad == "dynamics"
        states = [state]
        feats = [world_model.features(state)]
        actions = [torch.zeros(n, self.action_size, device=feats[0].device, dtype=feats[0].dtype)]
        actor_outs: list[Tensor] = []
        for _ in range(horizon):
            actor_outs.append(actor.mlp(feats[-1].detach()))
            policy = actor.distribution(actor_outs[-1])
            action = policy.rsample() if reparam else policy.sample()
            if self.config.actor_absmax:
                action = action * action.detach().abs().clamp_min(1.0).reciprocal()
            state = world_model.rssm.img_step(state, action)
            states.append(state)
            feats.append(world_model.features(state))
            actions.append(action.to(feats[-1].dtype))
        feat = torch.stack(feats, dim=0)
        reward = world_model.reward_head(feat).mean
        gamma = self.config.discount
        if world_model.discount_head is not None:
            continuation = gamma * world_model.discount_head(feat).mean
        else:
            continuation = torch.full_like(reward, gamma)
        if is_terminal is not None:
            first = gamma * (1.0 - is_terminal.reshape(n).to(continuation.dtype))
            continuation = torch.cat([first[None], continuation[1:]], dim=0)
        weight = torch.cumprod(torch.cat([torch.ones_like(continuation[:1]), continuation[:-1]], dim=0), dim=0)
        return {
            "feat": feat,
            "action": torch.stack(actions, dim=0),
            "state": _stack_imagined(states, feat, world_model),
            "reward": reward,
            "continuation": continuation,
            "weight": weight.detach(),
            "actor_out": torch.stack(actor_outs, dim=0),
        }

    def losses(
        self,
        world_model: WorldModel,
        traj: dict[str, Tensor | State],
        critic_objective: CriticObjective | None = None,
    ) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """Actor and critic losses on an imagined trajectory (see the module docstring).

        ``critic_objective`` (:data:`CriticObjective`) computes the critic's loss on the states ``0..H-1`` in place
        of DreamerV2's regression (CoWorld's Eq. 6); its metrics join the returned ones.

        Returns ``(terms, metrics)``: ``terms['actor']`` and ``terms['critic']`` are the scalar losses,
        ``terms['actor_terms'] (H-1, N)`` and ``terms['critic_terms'] (H, N)`` the unreduced ones, and
        ``terms['target'] (H, N)`` the lambda-returns; ``metrics`` are detached scalars.
        ``world_model`` is accepted for symmetry with :meth:`imagine` (subclasses may re-evaluate heads).
        """
        del world_model
        cfg = self.config
        feat, action, reward = traj["feat"], traj["action"], traj["reward"]
        continuation, weight = traj["continuation"], traj["weight"]
        assert isinstance(feat, Tensor) and isinstance(action, Tensor) and isinstance(reward, Tensor)
        assert isinstance(continuation, Tensor) and isinstance(weight, Tensor)
        horizon = feat.shape[0] - 1
        slow_value = self.slow_critic(feat).mean
        if cfg.critic_target == "slow":
            bootstrap_value = slow_value
        else:  # the critic's own values: a gradient to the actor through ``feat``, none to the critic's weights
            with frozen_parameters(self.critic):
                bootstrap_value = self.critic(feat).mean
        target = lambda_return(reward[:-1], bootstrap_value[:-1], continuation[:-1], bootstrap_value[-1], cfg.lambda_)

        actor_out = traj.get("actor_out")  # the actor in states 0..H-1, if imagine ran it there
        if isinstance(actor_out, Tensor):
            policy = self.actor.distribution(actor_out[:-1])
        else:
            policy = self.actor(feat[:-2].detach())
        entropy = policy.entropy()
        scale = self.return_scale(target)
        if cfg.actor_grad == "dynamics":
            objective = target[1:] - bootstrap_value[:-2] if cfg.actor_advantage else target[1:]
            actor_terms = actor_loss(
                target=objective / scale, weight=weight[:-2], entropy=entropy, entropy_scale=cfg.actor_entropy
            )
        else:
            actor_terms = actor_loss(
                target=target[1:] / scale,
                weight=weight[:-2],
                entropy=entropy,
                entropy_scale=cfg.actor_entropy,
                log_prob=policy.log_prob(action[1:-1].detach()),
                baseline=bootstrap_value[:-2].detach() / scale,
            )

        critic_feat = feat[:-1].detach()
        value_dist = self.critic(critic_feat)
        value = value_dist.mean
        metrics: dict[str, Tensor] = {}
        if critic_objective is None:
            critic_terms = critic_loss(value_dist, target, weight[:-1])
        else:
            critic_terms, extra = critic_objective(critic_feat, value_dist, target, weight[:-1])
            if critic_terms.shape != value.shape:
                raise ValueError(f"critic_objective returned {tuple(critic_terms.shape)}, expected {value.shape}")
            metrics.update(extra)
        if cfg.slow_regulariser > 0.0:
            critic_terms = critic_terms + cfg.slow_regulariser * critic_loss(value_dist, slow_value[:-1], weight[:-1])
        assert actor_terms.shape == (horizon - 1, feat.shape[1]) and critic_terms.shape == value.shape
        terms = {
            "actor": actor_terms.mean(),
            "critic": critic_terms.mean(),
            "actor_terms": actor_terms,
            "critic_terms": critic_terms,
            "target": target,
        }
        metrics.update(
            {
                "actor/entropy": entropy.detach().mean(),
                "actor/return_scale": scale,
                "critic/value": value.detach().mean(),
                "imag/return": target.detach().mean(),
                "imag/reward": reward.detach().mean(),
                "imag/continuation": continuation.detach().mean(),
                "imag/action_abs": action[1:].detach().abs().mean(),
            }
        )
        return terms, metrics
