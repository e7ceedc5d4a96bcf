"""Recurrent state-space model with discrete latents (DreamerV2, paper Sec. 3.2.1).

    recurrent:       h_t = GRU(h_{t-1}, MLP([z_{t-1}, a_{t-1}]))
    transition:      z_t ~ p(z_t | h_t)           (the prior, ``img_step``)
    representation:  z_t ~ q(z_t | h_t, e(o_t))   (the posterior, ``obs_step``)

``z`` is ``S`` categorical variables with ``K`` classes each, sampled one-hot with straight-through gradients.
A state is a dict of tensors with a shared batch shape ``(...)``:

* ``deter``: ``(..., D)`` the GRU state ``h``;
* ``logits``: ``(..., S, K)`` log-probabilities of ``z`` (normalised; uniform mixture applied when ``unimix > 0``);
* ``stoch``: ``(..., S, K)`` the one-hot sample ``z``.

Features fed to every head are ``[deter, stoch flattened]``: ``(..., D + S * K)``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from coworld.distributions import OneHotCategorical, exponential_noise
from coworld.models.networks import LayerNormGRUCell, glorot_init, make_act, make_norm

__all__ = ["RSSM", "State", "stack_states"]

State = dict[str, Tensor]
"""An RSSM state: ``deter (..., D)``, ``logits (..., S, K)``, ``stoch (..., S, K)``."""


class RSSM(nn.Module):
    """DreamerV2's RSSM with a layer-normed GRU and ``stoch x classes`` categorical latents.

    Its three MLPs (the GRU's input, the prior's and the posterior's heads) have one hidden layer of ``hidden``
    units with ``norm`` and ``act``; ``gru_bias`` and ``gru_eps`` are the GRU cell's (:class:`LayerNormGRUCell`).
    """

    def __init__(
        self,
        *,
        embed_size: int,
        action_size: int,
        deter: int,
        hidden: int,
        stoch: int,
        classes: int,
        unimix: float = 0.0,
        act: str = "elu",
        norm: str = "none",
        gru_bias: bool = True,
        gru_eps: float = 1e-3,
    ) -> None:
        super().__init__()
        self.deter_size = deter
        self.action_size = action_size
        """Width of the action input; narrower actions are zero-padded to it (:meth:`img_step`)."""
        self.stoch = stoch
        self.classes = classes
        self.unimix = unimix
        self.feat_size = deter + stoch * classes
        """Length of :meth:`features`: ``D + S * K``."""

        def hidden_layer(in_size: int) -> list[nn.Module]:
            return [nn.Linear(in_size, hidden), *make_norm(norm, hidden), make_act(act)]

        self.img_in = nn.Sequential(*hidden_layer(stoch * classes + action_size))
        self.cell = LayerNormGRUCell(in_size=hidden, size=deter, bias=gru_bias, eps=gru_eps)
        self.img_out = nn.Sequential(*hidden_layer(deter), nn.Linear(hidden, stoch * classes))
        self.obs_out = nn.Sequential(*hidden_layer(deter + embed_size), nn.Linear(hidden, stoch * classes))
        glorot_init(self.img_in)
        glorot_init(self.img_out)
        glorot_init(self.obs_out)

    def initial(self, batch_size: int, device: torch.device | str | None = None) -> State:
        """The all-zero state for ``batch_size`` sequences: ``deter (N, D)``, ``logits``/``stoch (N, S, K)``."""
        device = device if device is not None else self.cell.linear.weight.device
        zeros = torch.zeros(batch_size, self.stoch, self.classes, device=device)
        return {"deter": torch.zeros(batch_size, self.deter_size, device=device), "logits": zeros, "stoch": zeros}

    def features(self, state: State) -> Tensor:
        """``[deter, stoch flattened]``: ``(..., D + S * K)``."""
        stoch = state["stoch"]
        return torch.cat([state["deter"], stoch.reshape(*stoch.shape[:-2], -1).to(state["deter"].dtype)], dim=-1)

    def dist(self, state: State) -> OneHotCategorical:
        """The categorical distribution of ``z`` in ``state`` (batch ``(..., S)``, ``K`` classes)."""
        return OneHotCategorical(state["logits"], normalised=True)

    def recurrent(self, prev_state: State, prev_action: Tensor) -> Tensor:
        """The recurrent model: ``(N, ...)`` state and ``(N, A)`` action to the next ``deter (N, D)``.

        An action narrower than :attr:`action_size` is zero-padded at the end: a CoWorld source model is built for
        the wider of the source's and the target's action spaces and reads both (:mod:`coworld.agents.coworld`)."""
        prev_action = pad_action(prev_action, self.action_size)
        stoch = prev_state["stoch"].reshape(prev_action.shape[0], -1)
        x = self.img_in(torch.cat([stoch, prev_action.to(stoch.dtype)], dim=-1))
        return self.cell(x, prev_state["deter"])

    def transition(self, deter: Tensor, sample: bool = True, noise: Tensor | None = None) -> State:
        """The transition model (the prior) at ``deter (N, D)``: the state ``(N, ...)`` it draws ``z`` into.
        ``noise (N, S, K)``: the sample's exponential noise (see :meth:`OneHotCategorical.rsample`), drawn here
        when None."""
        logits = self._logits(self.img_out(deter))
        return {"deter": deter, "logits": logits, "stoch": self._sample(logits, sample, noise)}

    def representation(self, deter: Tensor, embed: Tensor, sample: bool = True, noise: Tensor | None = None) -> State:
        """The representation model (the posterior) at ``deter (N, D)`` with the new observation's embedding
        ``(N, E)``; ``noise`` as :meth:`transition`'s."""
        logits = self._logits(self.obs_out(torch.cat([deter, embed.to(deter.dtype)], dim=-1)))
        return {"deter": deter, "logits": logits, "stoch": self._sample(logits, sample, noise)}

    def img_step(
        self, prev_state: State, prev_action: Tensor, sample: bool = True, noise: Tensor | None = None
    ) -> State:
        """Prior step: ``(N, ...)`` state and ``(N, A)`` action to the prior state at the next step ``(N, ...)``
        (:meth:`recurrent`, then :meth:`transition` with ``noise (N, S, K)``)."""
        return self.transition(self.recurrent(prev_state, prev_action), sample, noise)

    def obs_step(
        self,
        prev_state: State,
        prev_action: Tensor,
        embed: Tensor,
        is_first: Tensor | None = None,
        sample: bool = True,
        noise: Tensor | None = None,
        prior: bool = True,
    ) -> tuple[State, State | None]:
        """Posterior step with the embedding ``(N, E)`` of the new observation; returns ``(post, prior)``.

        Where ``is_first (N,)`` is true the previous state and action are zeroed first (a new episode starts).
        ``noise (2, N, S, K)``: the exponential noise of the prior's and the posterior's draws (see
        :meth:`OneHotCategorical.rsample`), drawn here when None. ``prior=False`` (a caller that reads only the
        posterior) skips the transition model and returns None in its place; the posterior is the same.
        """
        if is_first is not None:
            keep = (~is_first.bool()).to(prev_action.dtype)
            prev_state = {k: v * keep.reshape(-1, *([1] * (v.ndim - 1))) for k, v in prev_state.items()}
            prev_action = prev_action * keep[:, None]
        prior_noise, post_noise = (None, None) if noise is None else noise
        deter = self.recurrent(prev_state, prev_action)
        prior_state = self.transition(deter, sample, prior_noise) if prior else None  # drawn first, as ever
        return self.representation(deter, embed, sample, post_noise), prior_state

    def observe(
        self,
        embed: Tensor,
        action: Tensor,
        is_first: Tensor,
        state: State | None = None,
        generator: torch.Generator | None = None,
        priors: bool = True,
    ) -> tuple[State, State | None]:
        """Run the posterior over sequences; returns ``(post, prior)`` with batch shape ``(B, T)``.

        ``embed (B, T, E)``; ``action (B, T, A)`` is the action that led to step ``t``; ``is_first (B, T)``
        resets the recurrent state; ``state`` (batch ``(B,)``) is the state before step 0 (zeros if None);
        ``generator`` draws the categorical samples' noise (torch's default generator if None): one
        :func:`exponential_noise` call ``(T, 2, B, S, K)`` for the prior's and the posterior's draws of every step.
        ``priors=False`` (a caller that reads only the posterior) skips the transition model (``prior`` is None);
        the same noise is drawn, so the posterior is the one ``priors=True`` gives.
        """
        batch, length = action.shape[:2]
        if state is None:
            state = self.initial(batch, action.device)
        noise = exponential_noise((length, 2, batch, self.stoch, self.classes), action.device, generator)
        posts: list[State] = []
        prior_states: list[State] = []
        for t in range(length):
            state, prior = self.obs_step(state, action[:, t], embed[:, t], is_first[:, t], True, noise[t], priors)
            posts.append(state)
            if prior is not None:
                prior_states.append(prior)
        return stack_states(posts), (stack_states(prior_states) if priors else None)

    def _logits(self, raw: Tensor) -> Tensor:
        """Raw ``(N, S * K)`` outputs to normalised log-probabilities ``(N, S, K)``, float32, with unimix."""
        logits = raw.float().reshape(raw.shape[0], self.stoch, self.classes)
        if self.unimix > 0.0:
            probs = (1.0 - self.unimix) * torch.softmax(logits, -1) + self.unimix / self.classes
            return probs.log()
        return torch.log_softmax(logits, -1)

    def _sample(self, logits: Tensor, sample: bool, noise: Tensor | None = None) -> Tensor:
        """Straight-through one-hot sample (``sample``, with ``noise`` if given) or the one-hot mode, ``(N, S, K)``."""
        dist = OneHotCategorical(logits, normalised=True)
        return dist.rsample(noise) if sample else dist.mode


def pad_action(action: Tensor, size: int) -> Tensor:
    """``(..., A)`` actions zero-padded at the end to ``(..., size)``; ``A > size`` raises ``ValueError`` (an action
    space wider than the model's input is a wiring error, never truncated)."""
    width = action.shape[-1]
    if width == size:
        return action
    if width > size:
        raise ValueError(f"actions of size {width} do not fit a model whose action input has size {size}")
    return torch.nn.functional.pad(action, (0, size - width))


def stack_states(states: list[State], dim: int = 1) -> State:
    """Stack a list of states with batch ``(N,)`` into one with batch ``(N, T)`` (``dim=1``) or ``(T, N)``."""
    return {key: torch.stack([s[key] for s in states], dim=dim) for key in states[0]}
