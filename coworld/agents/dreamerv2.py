"""The DreamerV2 agent: world model + actor-critic, their optimisers, the policy and one training update.

Used online (the source agent, and the online DreamerV2 baseline) and offline (the target agent, trained on
dataset batches). CoWorld's agent calls :meth:`DreamerV2.train_world_model` and
:meth:`DreamerV2.train_actor_critic` separately to add its own loss terms through their hooks.

Batches are dicts of NumPy arrays (or torch tensors) in the replay convention, see
:mod:`coworld.models.world_model`.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor
from torch._inductor import list_mode_options

from coworld import backends
from coworld.config import Config
from coworld.devices import resolve_device
from coworld.distributions import exponential_noise
from coworld.errors import ConfigError
from coworld.models.actor_critic import ActorCritic, CriticObjective, flatten_states
from coworld.models.networks import frozen_parameters
from coworld.models.rssm import State
from coworld.models.world_model import WorldModel

__all__ = [
    "DreamerV2",
    "ExtraWorldModelLoss",
    "ImaginedReward",
    "PolicyCopy",
    "PolicyState",
    "resolve_precision",
]

PolicyState = tuple[State, Tensor]
"""What :meth:`DreamerV2.policy` carries between steps: the posterior (batch ``(N,)``) and the last action
``(N, A)``."""

ExtraWorldModelLoss = Callable[[dict[str, Tensor], dict[str, Any]], dict[str, Tensor]]
"""``(batch, aux) -> {name: weighted scalar loss}``: extra world-model terms (e.g. CoWorld's Eq. 3 alignment).
``aux`` is :meth:`WorldModel.loss`'s aux dict; each returned term is added to the loss and logged as
``wm/<name>``."""

ImaginedReward = Callable[[dict[str, Any]], Tensor]
"""``traj -> (H+1, N)``: the reward the actor-critic learns from on an imagined trajectory (see
:meth:`ActorCritic.imagine`), in place of the reward head's ``traj['reward']`` (V-D4RL's offline DreamerV2 passes
its penalised reward this way)."""

_OPTIM_KEYS = ("wm_opt", "actor_opt", "critic_opt")


def resolve_precision(precision: str, device: torch.device) -> torch.dtype | None:
    """The autocast dtype: 'auto' -> None (fp32) on every device; 'bf16' -> bf16; 'fp32' -> None (why: the
    ``precision`` docstring in coworld/config.py)."""
    if precision == "auto":
        return None
    if precision == "bf16":
        return torch.bfloat16
    if precision == "fp32":
        return None
    raise ConfigError(f"unknown precision {precision!r}; choose one of: auto, bf16, fp32")


class DreamerV2:
    """DreamerV2 (paper Sec. 3.2.1): world-model learning plus actor-critic learning in imagination.

    ``device`` None uses ``config.device``; ``config.precision`` picks autocast; ``config.compile`` compiles the
    world model's loss and the imagination rollout whole, and the networks acting calls, with ``torch.compile``
    (the first updates then wait for compilation, shorter in a later process that finds inductor's on-disk cache
    holding the graphs; its cost per device: docs/performance.md).
    """

    def __init__(
        self,
        *,
        config: Config,
        action_size: int,
        image_shape: tuple[int, int, int] = (64, 64, 3),
        device: torch.device | str | None = None,
        model_action_size: int | None = None,
    ) -> None:
        self.config = config
        self.action_size = action_size
        """The actor's actions (the agent's own task's action space)."""
        model_action_size = action_size if model_action_size is None else model_action_size
        if model_action_size < action_size:
            raise ValueError(f"model_action_size {model_action_size} is below the actor's {action_size}")
        self.image_shape = tuple(image_shape)
        self.device = resolve_device(config.device if device is None else device)
        self.autocast_dtype = resolve_precision(config.precision, self.device)
        # the world model's action input: the actor's size, or wider for a CoWorld source model that also reads
        # target sequences (narrower actions are zero-padded by the RSSM)
        self.world_model = WorldModel(config=config.world_model, action_size=model_action_size, image_shape=image_shape)
        self.actor_critic = ActorCritic(
            config=config.actor_critic, feat_size=self.world_model.feat_size, action_size=action_size
        )
        self.world_model.to(self.device)
        self.actor_critic.to(self.device)
        wm, ac = config.world_model, config.actor_critic
        self.wm_opt = make_optimizer(self.world_model.parameters(), lr=wm.lr, eps=wm.eps, decay=wm.weight_decay)
        self.actor_opt = make_optimizer(
            self.actor_critic.actor.parameters(), lr=ac.actor_lr, eps=ac.eps, decay=ac.weight_decay
        )
        self.critic_opt = make_optimizer(
            self.actor_critic.critic.parameters(), lr=ac.critic_lr, eps=ac.eps, decay=ac.weight_decay
        )
        self.updates = 0
        """Completed calls of :meth:`train`."""
        self.model_path = backends.select(self.world_model, config, self.device, self.autocast_dtype is not None)
        """How the world model's loss is computed (``train.backend``): the reference or a checked fast path."""
        self.compiled = config.compile
        if self.compiled:
            self._compile()
        self._add_parts()

    def _add_parts(self) -> None:
        """What a subclass adds to the agent (its networks, optimisers, state), made once DreamerV2's own are, so
        their initial weights are drawn after DreamerV2's; DreamerV2 adds nothing."""

    # ------------------------------------------------------------------------------------------------ acting

    @torch.no_grad()
    def policy(
        self,
        obs: np.ndarray,
        state: PolicyState | None = None,
        mode: Literal["train", "eval", "random"] = "train",
        *,
        is_first: np.ndarray | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[np.ndarray, PolicyState | None]:
        """Actions for a batch of observations.

        ``obs``: uint8 images ``(N, H, W, C)``. ``state``: None at the start of every episode, else what the
        previous call returned. ``is_first (N,)`` resets the latent and previous action of single rows (for
        vectorised envs). ``mode``: 'train' samples the actor (plus ``train.expl_noise``), 'eval' takes its
        mode, 'random' draws uniform actions in ``[-1, 1]`` (the prefill) while still filtering the latent, so a
        run that switches from 'random' to 'train' mid-episode continues the episode's state. The returned
        state holds the action actually returned, noise included: the next step conditions on what was executed.
        ``generator`` (on the agent's device): where every random number of the call comes from, torch's default
        generator when None. Returns float32 actions ``(N, A)`` and the new state.
        """
        n = obs.shape[0]
        if mode not in ("train", "eval", "random"):
            raise ValueError(f"unknown policy mode {mode!r}; use 'train', 'eval' or 'random'")
        if state is None:
            latent, action = self.world_model.rssm.initial(n, self.device), self._zero_action(n)
            first = torch.ones(n, dtype=torch.bool, device=self.device)
        else:
            latent, action = state
            first = torch.zeros(n, dtype=torch.bool, device=self.device)
        if is_first is not None:
            first = first | torch.as_tensor(np.asarray(is_first, dtype=bool), device=self.device)
        image = torch.as_tensor(obs, device=self.device)
        rssm = self.world_model.rssm
        race = None  # the latent draws' noise, drawn inside obs_step from the default generator
        if generator is not None:
            race = exponential_noise((2, n, rssm.stoch, rssm.classes), self.device, generator)
        with self._autocast():
            embed = self.world_model.encode(image)
            latent, _ = rssm.obs_step(latent, action, embed, first, noise=race)
            if mode == "random":
                action = torch.rand(n, self.action_size, generator=generator, device=self.device) * 2.0 - 1.0
            else:
                dist = self.actor_critic.actor(self.world_model.features(latent))
                action = dist.mode if mode == "eval" else dist.sample(generator)
        action = action.float().clamp(-1.0, 1.0)  # an untruncated actor's samples are clipped when executed
        noise = self.config.train.expl_noise
        if mode == "train" and noise > 0.0:
            normal = torch.randn(action.shape, generator=generator, device=self.device)
            action = (action + noise * normal).clamp(-1.0, 1.0)
        return action.cpu().numpy(), (latent, action)

    def policy_copy(self) -> PolicyCopy:
        """A copy of the networks acting needs, which acts with this agent's weights as they were at its last
        :meth:`PolicyCopy.sync` while this agent trains (online runs' background updates)."""
        return PolicyCopy(self)

    @torch.no_grad()
    def value(self, state: PolicyState) -> np.ndarray:
        """The critic's estimate ``(N,)`` for the latent states the policy has just reached (``state`` from
        :meth:`policy`): the discounted return it expects from there on (Figure 4(b)'s value check)."""
        latent, _ = state
        with self._autocast():
            value = self.actor_critic.critic_value(self.world_model.features(latent))
        return value.float().cpu().numpy()

    @torch.no_grad()
    def predicted_reward(self, state: PolicyState) -> np.ndarray:
        """The reward head's prediction ``(N,)`` for the latent states the policy has just reached (``state`` from
        :meth:`policy`): the reward of arriving there, set beside the rewards received (the reward check), which
        tells whether the world model scores the agent's own states as the environment does."""
        latent, _ = state
        with self._autocast():
            reward = self.world_model.reward_head(self.world_model.features(latent)).mean
        return reward.float().cpu().numpy()

    # ---------------------------------------------------------------------------------------------- training

    def to_batch(self, batch: Mapping[str, np.ndarray | Tensor]) -> dict[str, Tensor]:
        """NumPy batch -> torch tensors on the device; images stay uint8, actions and rewards become float32."""
        out = {}
        for key, value in batch.items():
            tensor = torch.as_tensor(value)
            if tensor.is_floating_point():
                tensor = tensor.float()
            out[key] = tensor.to(self.device, non_blocking=True)
        return out

    def prepare(self, batch: Mapping[str, np.ndarray | Tensor]) -> dict[str, Tensor]:
        """:meth:`to_batch` and the model path's ``prepare`` (:mod:`coworld.backends`): the batch as the update
        reads it, made with no weight (so :class:`~coworld.data.prefetch.Prefetcher` can make the next one during an
        update). :meth:`train` takes batches either way."""
        return self.model_path.prepare(self.to_batch(batch))

    def train(self, batch: Mapping[str, np.ndarray | Tensor]) -> dict[str, float]:
        """One world-model update and one actor-critic update in imagination (the latter only once
        ``train.actor_warmup`` updates are done); returns namespaced metrics."""
        tensors = self.to_batch(batch)
        metrics, post = self.train_world_model(tensors)
        if self.updates >= self.config.train.actor_warmup:
            metrics.update(self.train_actor_critic(post, is_terminal=tensors["is_terminal"]))
        self.updates += 1
        return metrics

    def train_world_model(
        self, batch: Mapping[str, np.ndarray | Tensor], extra_loss: ExtraWorldModelLoss | None = None
    ) -> tuple[dict[str, float], State]:
        """One world-model gradient step. Returns ``(metrics, post)`` with the detached posterior (batch
        ``(B, T)``) to start imagination from. ``extra_loss`` adds weighted terms (see
        :data:`ExtraWorldModelLoss`)."""
        tensors = self.to_batch(batch)
        with self._autocast():
            terms, aux = self.model_path.loss(tensors)
            loss = aux["loss"]
            extras = extra_loss(tensors, aux) if extra_loss is not None else {}
            for term in extras.values():
                loss = loss + term
        self.wm_opt.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.world_model.parameters(), self.config.world_model.grad_clip)
        self.wm_opt.step()
        post, prior = aux["post"], aux["prior"]
        metrics = {f"wm/{name}": term.detach().mean() for name, term in terms.items()}
        metrics.update({f"wm/{name}": term.detach() for name, term in extras.items()})
        metrics["wm/kl_loss"] = aux["kl_loss"].detach()
        metrics["wm/loss"] = loss.detach()
        metrics["wm/grad_norm"] = grad_norm
        with torch.no_grad():
            metrics["wm/post_entropy"] = self.world_model.rssm.dist(post).entropy().mean()
            metrics["wm/prior_entropy"] = self.world_model.rssm.dist(prior).entropy().mean()
            metrics["wm/reward_pred"] = aux["reward_head"].mean.mean()  # the prediction the loss was taken of
        return _to_floats(metrics), {key: value.detach() for key, value in post.items()}

    def train_actor_critic(
        self,
        post: State,
        critic_objective: CriticObjective | None = None,
        *,
        is_terminal: Tensor | np.ndarray | None = None,
        imagined_reward: ImaginedReward | None = None,
        extra_loss: Callable[[], dict[str, Tensor]] | None = None,
    ) -> dict[str, float]:
        """One actor and one critic step on trajectories imagined from every posterior state in ``post``.

        ``post``: states with batch ``(B, T)`` (from :meth:`train_world_model`). ``critic_objective``: the critic's
        loss in place of DreamerV2's, see :meth:`ActorCritic.losses`; give it parameters that need no gradient (or
        wrap its network in :func:`coworld.models.networks.frozen_parameters`). ``is_terminal (B, T)``: true
        continuation of the start states. ``imagined_reward``: replaces the reward head's reward of the imagined
        states (see :data:`ImaginedReward`). ``extra_loss() -> {name: weighted scalar loss}``: terms added to the
        actor's and critic's loss and logged under their names (EWC's pull toward the source weights). The slow
        critic is refreshed after the optimiser steps, per ``slow_target_every`` (DreamerV2's order: the first update
        copies the stepped critic whole).
        """
        ac = self.actor_critic
        start = flatten_states(post)
        terminal = None if is_terminal is None else torch.as_tensor(is_terminal, device=self.device).reshape(-1)
        with frozen_parameters(self.world_model), self._autocast():
            traj = ac.imagine(self.world_model, start, is_terminal=terminal)
            if imagined_reward is not None:
                traj["reward"] = imagined_reward(traj)
            terms, metrics = ac.losses(self.world_model, traj, critic_objective)
            extras = extra_loss() if extra_loss is not None else {}
        loss = terms["actor"] + terms["critic"]
        for term in extras.values():
            loss = loss + term
        self.actor_opt.zero_grad(set_to_none=True)
        self.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        clip = self.config.actor_critic.grad_clip
        metrics["actor/grad_norm"] = torch.nn.utils.clip_grad_norm_(ac.actor.parameters(), clip)
        metrics["critic/grad_norm"] = torch.nn.utils.clip_grad_norm_(ac.critic.parameters(), clip)
        self.actor_opt.step()
        self.critic_opt.step()
        ac.update_slow_target()
        metrics["actor/loss"] = terms["actor"].detach()
        metrics["critic/loss"] = terms["critic"].detach()
        metrics.update({name: term.detach() for name, term in extras.items()})
        return _to_floats(metrics)

    # ---------------------------------------------------------------------------------------- checkpointing

    def state_dict(self) -> dict[str, Any]:
        """Networks, optimisers and the update counter: tensors, numbers, strings, lists and dicts only."""
        return {
            "world_model": self.world_model.state_dict(),
            "actor_critic": self.actor_critic.state_dict(),
            **{key: getattr(self, key).state_dict() for key in _OPTIM_KEYS},
            "updates": self.updates,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned (strict: every network key must match)."""
        self.world_model.load_state_dict(state["world_model"])
        self.actor_critic.load_state_dict(state["actor_critic"])
        for key in _OPTIM_KEYS:
            getattr(self, key).load_state_dict(state[key])
        self.updates = int(state["updates"])

    # -------------------------------------------------------------------------------------------- internals

    def _zero_action(self, n: int) -> Tensor:
        return torch.zeros(n, self.action_size, device=self.device)

    def _autocast(self) -> contextlib.AbstractContextManager[Any]:
        if self.autocast_dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(device_type=self.device.type, dtype=self.autocast_dtype)

    def _compile(self) -> None:
        """Compile the update's two loops whole, and the per-step networks that acting calls, in place
        (state-dict keys unchanged).

        The reference world model's loss (encoder, the RSSM's observe loop, decoder, heads) and the imagination
        rollout are each one graph (``fullgraph``: a graph break raises rather than splitting the update), so the
        small ops of every step fuse and CUDA graphs can take each whole. Random numbers come from the eager
        generator (inductor's ``fallback_random``), so a compiled agent draws what an eager one draws.

        Shapes are static (``dynamic=False``): a batch of another size compiles anew. Automatic dynamic shapes
        traced the truncated normal's ``torch.rand`` over a symbolic shape, which failed.
        """
        wm, ac = self.world_model, self.actor_critic
        # torch.compile takes a mode or options, not both: the mode's options, with the eager generator's draws
        mode_options = {} if self.config.compile_mode == "default" else list_mode_options(self.config.compile_mode)
        options = {**mode_options, "fallback_random": True}
        whole = {"options": options, "dynamic": False, "fullgraph": True}
        wm.loss = torch.compile(wm.loss, **whole)  # type: ignore[method-assign]
        ac.imagine = torch.compile(ac.imagine, **whole)  # type: ignore[method-assign]
        for module in (
            wm.encoder,
            wm.decoder,
            wm.reward_head,
            wm.discount_head,
            wm.rssm.img_in,
            wm.rssm.cell,
            wm.rssm.img_out,
            wm.rssm.obs_out,
            ac.actor,
            ac.critic,
            ac.slow_critic,
        ):
            if module is not None:
                module.compile(dynamic=False, options=options)


class PolicyCopy:
    """The encoder, RSSM and actor of ``agent``, copied: :meth:`policy` acts exactly as ``agent.policy`` did at the
    last :meth:`sync`, so it can act while ``agent`` trains on another thread. The copy is never compiled."""

    def __init__(self, agent: DreamerV2) -> None:
        with torch.random.fork_rng(devices=[]):  # its initial weights are overwritten: draw them off the record
            self.copy = DreamerV2(
                config=dataclasses.replace(agent.config, compile=False),
                action_size=agent.action_size,
                image_shape=agent.image_shape,
                device=agent.device,
                model_action_size=agent.world_model.action_size,
            )
        sources = (agent.world_model.encoder, agent.world_model.rssm, agent.actor_critic.actor)
        copies = (self.copy.world_model.encoder, self.copy.world_model.rssm, self.copy.actor_critic.actor)
        self._pairs = [
            (source, copy)
            for source_module, copy_module in zip(sources, copies, strict=True)
            for source, copy in zip(
                [*source_module.parameters(), *source_module.buffers()],
                [*copy_module.parameters(), *copy_module.buffers()],
                strict=True,
            )
        ]
        self.sync()

    @torch.no_grad()
    def sync(self) -> None:
        """Take the agent's current weights (call it while the agent is not training)."""
        for source, copy in self._pairs:
            copy.copy_(source)

    def policy(self, *args: Any, **kwargs: Any) -> tuple[np.ndarray, PolicyState | None]:
        """:meth:`DreamerV2.policy` with the weights of the last :meth:`sync`."""
        return self.copy.policy(*args, **kwargs)


def make_optimizer(params: Any, *, lr: float, eps: float, decay: float) -> torch.optim.AdamW:
    """Adam with DreamerV2's weight decay: every step first scales each weight by ``1 - decay``, independent of
    the learning rate. AdamW scales by ``1 - lr * weight_decay`` before its Adam step, so ``weight_decay =
    decay / lr`` is exactly that step. PyTorch's fused kernel (CPU and CUDA) takes the same step in one pass over
    each tensor."""
    return torch.optim.AdamW(params, lr=lr, eps=eps, weight_decay=decay / lr, fused=True)


def _to_floats(metrics: Mapping[str, Tensor]) -> dict[str, float]:
    """Scalar tensors -> Python floats with a single device-to-host copy."""
    if not metrics:
        return {}
    values = torch.stack([value.detach().float().reshape(()) for value in metrics.values()]).cpu().tolist()
    return dict(zip(metrics.keys(), values, strict=True))
