"""CURL and CURL+CQL, the paper's model-free baselines, trained offline on the same datasets as CoWorld.

CURL (Laskin, Srinivas & Abbeel, ICML 2020) is SAC from stacked pixel frames whose encoder is trained by the
critic's TD loss and by a contrastive loss between two random crops of each observation (bilinear InfoNCE
against a momentum "key" encoder). CURL+CQL adds the CQL(H) penalty (Kumar et al., NeurIPS 2020) to both
Q-functions so that Q-values of actions the dataset does not contain are pushed down.

One update (:meth:`Curl.train`, CURL's order):

1. critic (and encoder): twin-Q TD loss to the soft Bellman target of the target critic (+ CQL penalty);
2. every ``actor_update_every`` updates: actor on the critic's detached conv features, then temperature;
3. every ``target_update_every`` updates: Polyak averaging of the target Q-heads (``critic_tau``) and of the
   target encoder, which is CURL's key encoder (``encoder_tau``);
4. contrastive update of the encoder and ``W``.

Paper settings (``CurlConfig`` defaults; CURL's DMC table, and what we chose where it leaves a choice):
batch 512 (CURL's table: 512 for cheetah, 128 for the other DMC tasks; its code's default is 32, its README
runs 128; the CoWorld DMC tasks include cheetah and 512 is what a GPU handles easily), learning rate 1e-3 for
actor, critic and encoder (CURL uses 2e-4 for cheetah run: override ``curl.actor_lr``, ``curl.critic_lr``,
``curl.encoder_lr``), Adam betas (0.9, 0.999) and (0.5, 0.999) for the temperature, temperature lr 1e-4,
initial temperature 0.1, target entropy ``-|A|``, critic tau 0.01, encoder tau 0.05, actor and target updates
every 2 critic updates, feature dim 50, 4 conv layers of 32 filters, MLP hidden 1024, frame stack 3,
discount 0.99. CQL: weight 5 (the CQL paper's and the authors' code's ``min_q_weight`` for the Gym-MuJoCo D4RL
tasks, the continuous-control setting closest to DMC locomotion; without Lagrange tuning) and 10 random + 10
+ 10 policy actions per state in the log-sum-exp (CQL's ``num_random = 10``).

Differences from CURL's code, all deliberate: frames are 64 x 64, so augmentation pads 4 pixels then crops 64
(:func:`coworld.models.curl.random_crop`, a random shift) instead of cropping 84 from a 100 render, and evaluation
sees the unshifted frame; one Adam optimiser trains encoder and ``W`` on the contrastive loss (CURL's code steps
the encoder with two optimisers); training is offline, from a fixed dataset, with no exploration steps. From
CQL's code: the log-sum-exp subtracts ``log(number of samples)`` (a constant; see
:func:`coworld.losses.curl.cql_penalty`).

Offline on ``toy_reach`` (30 noisy scripted-expert episodes, return ~46; uniform random ~9.5), the ``tiny``
preset of CURL+CQL reaches ~45 within 400 updates; plain CURL stays between 14 and 30 over 1500 updates
(``tests/agents/test_curl.py``).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from coworld.config import Config
from coworld.data.reader import Dataset
from coworld.data.transitions import TransitionSampler
from coworld.errors import CheckpointError
from coworld.losses.curl import (
    actor_loss,
    cql_penalty,
    info_nce,
    sac_critic_target,
    temperature_loss,
    twin_q_loss,
    uniform_log_prob,
)
from coworld.models.curl import Actor, BilinearSimilarity, Critic, center_crop, random_crop, squashed_gaussian_sample

__all__ = ["Curl", "FrameStackAgent", "load_networks", "make_sampler", "polyak", "stack_frames"]

PolicyState = np.ndarray | None
"""Frame stack of each environment, ``uint8 (N, k*C, H, W)``; None at the start of a run."""


def make_sampler(dataset: Dataset, config: Config, seed: int) -> TransitionSampler:
    """A seeded transition sampler over ``dataset`` (frames loaded into RAM) with ``curl.batch_size`` and
    ``curl.frame_stack``; ``next(sampler)`` is a batch for :meth:`Curl.train`."""
    return TransitionSampler.from_dataset(
        dataset, batch_size=config.curl.batch_size, frame_stack=config.curl.frame_stack, seed=seed
    )


def stack_frames(
    obs: np.ndarray,
    state: np.ndarray | None,
    *,
    frame_stack: int,
    image_shape: tuple[int, ...],
    is_first: np.ndarray | None = None,
) -> np.ndarray:
    """The frame stacks of ``N`` environments after their newest frames (what the pixel baselines act on).

    Args:
        obs: ``uint8 (N, H, W, C)`` the newest frame of each environment.
        state: the stacks returned by the previous call, or None at the start (every row starts).
        frame_stack: ``k``.
        image_shape: ``(H, W, C)`` the agent takes.
        is_first: ``(N,) bool``: rows whose episode starts at this frame; their stack is reset to ``k`` copies of it.

    Returns:
        ``uint8 (N, k*C, H, W)``, oldest frame first (a row starts as ``k`` copies of its first frame).
    """
    obs = np.asarray(obs)
    if obs.ndim != 4 or obs.shape[1:] != tuple(image_shape):
        raise ValueError(f"obs must be uint8 (N, H, W, C) with (H, W, C) = {tuple(image_shape)}, got {obs.shape}")
    N = obs.shape[0]
    frame = obs.transpose(0, 3, 1, 2)  # (N, C, H, W)
    fresh = np.tile(frame, (1, frame_stack, 1, 1))  # (N, k*C, H, W)
    if state is None:
        stack = fresh
    else:
        if state.shape != fresh.shape:
            raise ValueError(f"state must be the stack returned for these {N} envs, {fresh.shape}; got {state.shape}")
        stack = np.concatenate([state[:, frame.shape[1] :], frame], axis=1)
        if is_first is not None:
            restart = np.asarray(is_first, dtype=bool).reshape(N)
            stack[restart] = fresh[restart]
    return np.ascontiguousarray(stack, dtype=np.uint8)


def load_networks(
    state: Mapping[str, Any],
    *,
    kind: str,
    action_size: int,
    networks: Mapping[str, nn.Module],
    optimizers: Mapping[str, torch.optim.Optimizer],
) -> None:
    """Load a pixel baseline's checkpoint ``state`` into its networks and optimisers (by name); a checkpoint of
    another agent, action size or network size is refused with one line (CheckpointError)."""
    if state.get("kind") != kind or state.get("action_size") != action_size:
        raise CheckpointError(
            f"checkpoint is of a {state.get('kind')} agent with {state.get('action_size')} actions, this run is"
            f" {kind} with {action_size}; use the run folder the checkpoint came from"
        )
    try:
        for name, network in networks.items():
            network.load_state_dict(state[name])
    except RuntimeError as err:
        first = str(err).strip().splitlines()[0]
        raise CheckpointError(f"checkpoint does not fit this config's networks ({first[:160]})") from None
    for name, optimizer in optimizers.items():
        optimizer.load_state_dict(state["optimizers"][name])


def polyak(target: nn.Module, source: nn.Module, tau: float) -> None:
    """``target <- tau * source + (1 - tau) * target``, parameter by parameter."""
    with torch.no_grad():
        for t, s in zip(target.parameters(), source.parameters(), strict=True):
            t.lerp_(s, tau)


class FrameStackAgent:
    """What the pixel baselines (:class:`Curl`, :class:`coworld.agents.drq_bc.DrqBc`) share: a :class:`Critic`
    (a pixel encoder of frame stacks and twin Q-functions), its target copy and an actor on the critic's conv
    features; acting on frame stacks; checkpoints of the networks, the optimisers and the update counter.

    Args:
        config: the run's config; the agent reads its section :attr:`config_section`.
        action_size: ``A``; actions live in ``[-1, 1]^A``.
        image_shape: ``(H, W, C)`` of one frame (square).
        device: torch device.

    A subclass names its section, actor class and checkpoint kind, makes its optimisers (:meth:`_add_parts`) and
    says what its actor does (:meth:`eval_action`, :meth:`train_action`) and what its networks read of a frame stack
    (:meth:`frames`, :meth:`input_side`).
    """

    name = "a pixel baseline"
    """The algorithm as an error names it."""
    config_section: str
    """The config section the agent reads (``frame_stack``, ``num_filters``, ``num_layers``, ``feature_dim``,
    ``hidden`` and its own settings)."""
    actor_class: type[nn.Module]
    """The actor, built on the critic's conv features."""
    kind: str
    """The checkpoint's kind."""
    optimizers: dict[str, torch.optim.Optimizer]

    def __init__(
        self,
        *,
        config: Config,
        action_size: int,
        image_shape: tuple[int, int, int] = (64, 64, 3),
        device: str | torch.device = "cpu",
    ) -> None:
        cfg = getattr(config, self.config_section)
        self.cfg = cfg
        self.action_size = action_size
        self.image_shape = tuple(image_shape)
        self.device = torch.device(device)
        H, W, C = self.image_shape
        if H != W:
            raise ValueError(f"{self.name} expects square frames, got {H} x {W}")
        self.channels = C * cfg.frame_stack
        sizes = {key: getattr(cfg, key) for key in ("num_filters", "num_layers", "feature_dim", "hidden")}
        self.critic = Critic(channels=self.channels, size=self.input_side(), action_size=action_size, **sizes)
        self.critic.to(self.device)
        self.critic_target = copy.deepcopy(self.critic)
        self.critic_target.requires_grad_(False)
        trunk, actor = self.critic.encoder.trunk.out_dim, self.actor_class
        self.actor = actor(trunk_dim=trunk, feature_dim=cfg.feature_dim, hidden=cfg.hidden, action_size=action_size)
        self.actor.to(self.device)
        self.updates = 0
        """Gradient updates done so far."""
        self._add_parts()

    def _add_parts(self) -> None:
        """What a subclass adds (its optimisers, its own networks and state), made once the critic and the actor
        are, so their initial weights are drawn after theirs."""
        raise NotImplementedError

    def input_side(self) -> int:
        """Side of the (square) images the encoder reads: the frame's."""
        return self.image_shape[0]

    # -- acting ------------------------------------------------------------------------------------------------------
    def frames(self, stack: np.ndarray) -> Tensor:
        """Frame stacks ``uint8 (N, k*C, H, W)`` as the networks read them when acting (on the device)."""
        return torch.as_tensor(stack, device=self.device)

    def eval_action(self, conv: Tensor) -> Tensor:
        """The actor's evaluation action ``(N, A)`` at conv features ``(N, D)``."""
        raise NotImplementedError

    def train_action(self, conv: Tensor) -> Tensor:
        """The actor's training (exploring) action ``(N, A)`` at conv features ``(N, D)``."""
        raise NotImplementedError

    def policy(
        self, obs: np.ndarray, state: PolicyState, mode: str = "eval", is_first: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Actions for ``N`` environments from their newest frames.

        Args:
            obs: ``uint8 (N, H, W, C)`` the newest frame of each environment.
            state: the frame stacks returned by the previous call, or None at the start (every row starts).
            mode: ``'eval'`` (:meth:`eval_action`) or ``'train'`` (:meth:`train_action`).
            is_first: ``(N,) bool``: rows whose episode starts at this frame; their stack is reset to ``k``
                copies of the frame.

        Returns:
            ``(action float32 (N, A) in [-1, 1], state uint8 (N, k*C, H, W))``.
        """
        if mode not in ("eval", "train"):
            raise ValueError(f"mode must be 'eval' or 'train', got {mode!r}")
        stack = stack_frames(
            obs, state, frame_stack=self.cfg.frame_stack, image_shape=self.image_shape, is_first=is_first
        )
        with torch.no_grad():
            conv = self.critic.encoder.trunk(self.frames(stack))
            action = self.eval_action(conv) if mode == "eval" else self.train_action(conv)
        return action.cpu().numpy().astype(np.float32), stack

    def value(self, state: np.ndarray) -> np.ndarray:
        """The critic's estimate ``min(Q1, Q2)(s, a_eval)`` of the eval action at the stacks ``state``.

        Args:
            state: ``uint8 (N, k*C, H, W)``, the stacks :meth:`policy` just returned.

        Returns:
            ``(N,) float64``, for the evaluator's value check (critic estimate vs the discounted return received).
        """
        with torch.no_grad():
            conv = self.critic.encoder.trunk(self.frames(state))
            q1, q2 = self.critic(self.critic.encoder.head(conv), self.eval_action(conv))
        return torch.minimum(q1, q2).cpu().numpy().astype(np.float64)

    # -- checkpoints -------------------------------------------------------------------------------------------------
    def networks(self) -> dict[str, nn.Module]:
        """The networks a checkpoint holds, by name."""
        return {"critic": self.critic, "critic_target": self.critic_target, "actor": self.actor}

    def state_dict(self) -> dict[str, Any]:
        """Networks, target networks, optimisers and the update counter (tensors and plain data)."""
        return {
            "kind": self.kind,
            "action_size": self.action_size,
            "updates": self.updates,
            **{name: network.state_dict() for name, network in self.networks().items()},
            "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what :meth:`state_dict` saved; another agent's checkpoint, or one of another action size, is
        refused with one line."""
        load_networks(state, kind=self.kind, action_size=self.action_size, networks=self.networks(),
                      optimizers=self.optimizers)  # fmt: skip
        self.updates = int(state["updates"])


class Curl(FrameStackAgent):
    """CURL (``cql=False``) or CURL+CQL (``cql=True``) agent for offline training from pixels.

    Args:
        cql: add the CQL(H) penalty to the critic loss.
        kwargs: :class:`FrameStackAgent`'s (``config``, ``action_size``, ``image_shape``, ``device``); this agent
            reads ``config.curl``.

    API: :meth:`train` (one update from a :class:`~coworld.data.transitions.TransitionSampler` batch),
    :meth:`policy` (actions from single frames; the agent keeps the frame stack in ``state``),
    :meth:`state_dict` / :meth:`load_state_dict` (everything needed to resume, ``weights_only``-loadable).
    """

    name = "CURL"
    config_section = "curl"
    actor_class = Actor

    def __init__(self, *, cql: bool = False, **kwargs: Any) -> None:
        self.cql = cql
        super().__init__(**kwargs)

    def _add_parts(self) -> None:
        """The contrastive ``W``, the temperature and the optimisers."""
        cfg = self.cfg
        self.target_entropy = -float(self.action_size)
        self.similarity = BilinearSimilarity(cfg.feature_dim).to(self.device)
        self.log_alpha = torch.tensor(np.log(cfg.init_temperature), dtype=torch.float32, device=self.device)
        self.log_alpha.requires_grad_(True)
        self.optimizers = {
            "critic": torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr, betas=(0.9, 0.999)),
            "actor": torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr, betas=(0.9, 0.999)),
            "alpha": torch.optim.Adam([self.log_alpha], lr=cfg.alpha_lr, betas=(0.5, 0.999)),
            "curl": torch.optim.Adam(
                [*self.critic.encoder.parameters(), *self.similarity.parameters()], lr=cfg.encoder_lr
            ),
        }
        self._actor_metrics: dict[str, float] = {}

    # ----------------------------------------------------------------------------------------------------------
    # Training
    # ----------------------------------------------------------------------------------------------------------

    @property
    def alpha(self) -> Tensor:
        """SAC temperature ``exp(log_alpha)``, detached."""
        return self.log_alpha.detach().exp()

    def _to_tensors(self, batch: Mapping[str, np.ndarray]) -> dict[str, Tensor]:
        B = len(batch["reward"])
        expected = (B, self.channels, self.image_shape[0], self.image_shape[1])
        for key in ("obs", "next_obs"):
            if tuple(batch[key].shape) != expected:
                raise ValueError(f"batch[{key!r}] must be uint8 (B, k*C, H, W) = {expected}, got {batch[key].shape}")
        if tuple(batch["action"].shape) != (B, self.action_size):
            raise ValueError(f"batch['action'] must be (B, A) = {(B, self.action_size)}, got {batch['action'].shape}")
        out = {key: torch.as_tensor(np.asarray(value), device=self.device) for key, value in batch.items()}
        for key in ("action", "reward", "not_done"):
            out[key] = out[key].float()
        return out

    def train(self, batch: Mapping[str, np.ndarray]) -> dict[str, float]:
        """One update of critic, encoder (CURL), and every ``actor_update_every`` updates actor and temperature.

        Args:
            batch: ``obs (B, k*C, H, W) uint8``, ``action (B, A)``, ``reward (B,)``, ``next_obs``, ``not_done
                (B,)``, as :class:`~coworld.data.transitions.TransitionSampler` returns.

        Returns:
            Scalars: ``critic/loss``, ``critic/q``, ``critic/target``, ``actor/loss``, ``actor/entropy``,
            ``alpha/value``, ``alpha/loss``, ``curl/loss``, ``curl/accuracy`` (share of queries whose own key scores
            highest), and with CQL ``cql/penalty`` (the unweighted penalty, mean of Q1's and Q2's). Actor and
            temperature values are those of the latest actor update.
        """
        cfg = self.cfg
        data = self._to_tensors(batch)
        crop = dict(pad=cfg.pad, crop=cfg.crop)
        obs = random_crop(data["obs"], **crop)
        next_obs = random_crop(data["next_obs"], **crop)
        positive = random_crop(data["obs"], **crop)
        metrics = self._update_critic(obs, data["action"], data["reward"], next_obs, data["not_done"])
        if self.updates % cfg.actor_update_every == 0:
            self._actor_metrics = self._update_actor_and_alpha(obs)
        metrics.update(self._actor_metrics)
        if self.updates % cfg.target_update_every == 0:
            polyak(self.critic_target.q1, self.critic.q1, cfg.critic_tau)
            polyak(self.critic_target.q2, self.critic.q2, cfg.critic_tau)
            polyak(self.critic_target.encoder, self.critic.encoder, cfg.encoder_tau)
        metrics.update(self._update_contrastive(obs, positive))
        self.updates += 1
        return metrics

    def _update_critic(
        self, obs: Tensor, action: Tensor, reward: Tensor, next_obs: Tensor, not_done: Tensor
    ) -> dict[str, float]:
        """TD update of both Q-functions and the encoder (plus the CQL penalty). Images ``(B, k*C, S, S)``."""
        B = reward.shape[0]
        with torch.no_grad():
            next_conv = self.critic.encoder.trunk(next_obs)
            next_action, next_log_prob = self.actor.sample(next_conv)
            next_q1, next_q2 = self.critic_target(self.critic_target.encoder(next_obs), next_action)
            target = sac_critic_target(reward, not_done, next_q1, next_q2, next_log_prob, self.alpha, self.cfg.discount)
        conv = self.critic.encoder.trunk(obs)
        features = self.critic.encoder.head(conv)
        q1, q2 = self.critic(features, action)
        loss = twin_q_loss(q1, q2, target).mean()
        metrics = {"critic/q": q1.mean().item(), "critic/target": target.mean().item()}
        if self.cql:
            penalty = self._cql_penalties(features, conv.detach(), next_conv, q1, q2)
            assert penalty.shape == (B,)
            metrics["cql/penalty"] = 0.5 * penalty.mean().item()
            loss = loss + self.cfg.cql_weight * penalty.mean()
        self.optimizers["critic"].zero_grad(set_to_none=True)
        loss.backward()
        self.optimizers["critic"].step()
        metrics["critic/loss"] = loss.item()
        return metrics

    def _cql_penalties(self, features: Tensor, conv: Tensor, next_conv: Tensor, q1: Tensor, q2: Tensor) -> Tensor:
        """Sum of the CQL(H) penalties of Q1 and Q2, ``(B,)``.

        ``n = cql_samples`` uniform actions, ``n`` policy actions sampled at ``s`` and ``n`` at ``s'``, all scored
        by Q at ``s`` (features ``(B, F)``; conv features ``(B, D)`` of ``s`` and ``s'``, detached).
        """
        B, F_ = features.shape
        n, A = self.cfg.cql_samples, self.action_size
        with torch.no_grad():
            random_action = torch.rand(B, n, A, device=features.device) * 2 - 1
            mean, log_std = self.actor(torch.cat([conv, next_conv]))  # (2B, A): rows of s, then of s'
            mean = mean.view(2, B, 1, A).transpose(0, 1).expand(B, 2, n, A).reshape(B, 2 * n, A)
            log_std = log_std.view(2, B, 1, A).transpose(0, 1).expand(B, 2, n, A).reshape(B, 2 * n, A)
            policy_action, policy_log_prob = squashed_gaussian_sample(mean, log_std)  # (B, 2n, A), (B, 2n)
        actions = torch.cat([random_action, policy_action], dim=1)  # (B, 3n, A)
        q1_all, q2_all = self.critic(features[:, None, :].expand(B, 3 * n, F_), actions)  # (B, 3n)
        log_prob_random = uniform_log_prob(A)
        pen1 = cql_penalty(q1_all[:, :n], log_prob_random, q1_all[:, n:], policy_log_prob, q1)
        pen2 = cql_penalty(q2_all[:, :n], log_prob_random, q2_all[:, n:], policy_log_prob, q2)
        return pen1 + pen2

    def _update_actor_and_alpha(self, obs: Tensor) -> dict[str, float]:
        """SAC actor update on detached conv features, then the temperature. ``obs (B, k*C, S, S)``."""
        with torch.no_grad():
            conv = self.critic.encoder.trunk(obs)
            features = self.critic.encoder.head(conv)
        action, log_prob = self.actor.sample(conv)
        q1, q2 = self.critic(features, action)
        loss = actor_loss(q1, q2, log_prob, self.alpha).mean()
        self.optimizers["actor"].zero_grad(set_to_none=True)
        loss.backward()
        self.optimizers["actor"].step()
        alpha_loss = temperature_loss(self.log_alpha, log_prob, self.target_entropy).mean()
        self.optimizers["alpha"].zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.optimizers["alpha"].step()
        return {
            "actor/loss": loss.item(),
            "actor/entropy": -log_prob.mean().item(),
            "alpha/value": self.alpha.item(),
            "alpha/loss": alpha_loss.item(),
        }

    def _update_contrastive(self, anchor: Tensor, positive: Tensor) -> dict[str, float]:
        """CURL's InfoNCE update of the online encoder and ``W``; keys from the target (momentum) encoder."""
        queries = self.critic.encoder(anchor)
        with torch.no_grad():
            keys = self.critic_target.encoder(positive)
        loss, logits = info_nce(queries, keys, self.similarity.W)
        self.optimizers["curl"].zero_grad(set_to_none=True)
        loss.backward()
        self.optimizers["curl"].step()
        labels = torch.arange(len(logits), device=logits.device)
        accuracy = (logits.argmax(dim=1) == labels).float().mean()
        return {"curl/loss": loss.item(), "curl/accuracy": accuracy.item()}

    # ----------------------------------------------------------------------------------------------------------
    # Acting and checkpoints
    # ----------------------------------------------------------------------------------------------------------

    @property
    def kind(self) -> str:
        return "curl-cql" if self.cql else "curl"

    def input_side(self) -> int:
        """The crop's side."""
        return self.cfg.crop

    def frames(self, stack: np.ndarray) -> Tensor:
        """The centre crop of the stacks (evaluation sees the unshifted frame)."""
        return center_crop(super().frames(stack), pad=self.cfg.pad, crop=self.cfg.crop)

    def eval_action(self, conv: Tensor) -> Tensor:
        """The mean action ``tanh(mu)``."""
        return self.actor.mode(conv)

    def train_action(self, conv: Tensor) -> Tensor:
        """A sample of the policy."""
        return self.actor.sample(conv)[0]

    def networks(self) -> dict[str, nn.Module]:
        return {**super().networks(), "similarity": self.similarity}

    def state_dict(self) -> dict[str, Any]:
        """:meth:`FrameStackAgent.state_dict`, ``log_alpha`` and the latest actor update's metrics."""
        return {
            **super().state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "actor_metrics": dict(self._actor_metrics),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what :meth:`state_dict` saved; a checkpoint of the other variant or action size is refused."""
        super().load_state_dict(state)
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self._actor_metrics = {k: float(v) for k, v in state.get("actor_metrics", {}).items()}
