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

from coworld.models.distributions import OneHotCategorical, exponential_noise, log_softmax, softmax
from coworld.models.networks import ELU, LayerNormGRUCell, Linear, glorot_init, linear

__all__ = ["RSSM", "State", "stack_states"]

State = dict[str, Tensor]
"""An RSSM state: ``deter (..., D)``, ``logits (..., S, K)``, ``stoch (..., S, K)``."""


class RSSM(nn.Module):
    """DreamerV2's RSSM with a layer-normed GRU and ``stoch x classes`` categorical latents."""

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
    ) -> None:
        super().__init__()
        self.deter_size = deter
        self.stoch = stoch
        self.classes = classes
        self.unimix = unimix
        self.feat_size = deter + stoch * classes
        """Length of :meth:`features`: ``D + S * K``."""
        self.img_in = nn.Sequential(Linear(stoch * classes + action_size, hidden), ELU())
        self.cell = LayerNormGRUCell(in_size=hidden, size=deter)
        self.img_out = nn.Sequential(Linear(deter, hidden), ELU(), Linear(hidden, stoch * classes))
        self.obs_out = nn.Sequential(Linear(deter + embed_size, hidden), ELU(), Linear(hidden, stoch * classes))
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
        return OneHotCategorical(state["logits"])

    def img_step(
        self, prev_state: State, prev_action: Tensor, sample: bool = True, noise: Tensor | None = None
    ) -> State:
        """Prior step: ``(N, ...)`` state and ``(N, A)`` action to the prior state at the next step ``(N, ...)``.

        ``noise (N, S, K)``: the sample's exponential noise (see :meth:`OneHotCategorical.rsample`), drawn here
        when None."""
        stoch = prev_state["stoch"].reshape(prev_action.shape[0], -1)
        x = self.img_in(torch.cat([stoch, prev_action.to(stoch.dtype)], dim=-1))
        return self._prior(self.cell(x, prev_state["deter"]), sample, noise)

    def obs_step(
        self,
        prev_state: State,
        prev_action: Tensor,
        embed: Tensor,
        is_first: Tensor | None = None,
        sample: bool = True,
        noise: Tensor | None = None,
    ) -> tuple[State, State]:
        """Posterior step with the embedding ``(N, E)`` of the new observation; returns ``(post, prior)``.

        Where ``is_first (N,)`` is true the previous state and action are zeroed first (a new episode starts).
        ``noise (2, N, S, K)``: the exponential noise of the prior's and the posterior's draws (see
        :meth:`OneHotCategorical.rsample`), drawn here when None (one call of :func:`exponential_noise` draws the same).
        """
        if is_first is not None:
            keep = (~is_first.bool()).to(prev_action.dtype)
            prev_state = {k: v * keep.reshape(-1, *([1] * (v.ndim - 1))) for k, v in prev_state.items()}
            prev_action = prev_action * keep[:, None]
        prior_noise, post_noise = (None, None) if noise is None else noise
        prior = self.img_step(prev_state, prev_action, sample, prior_noise)
        return self._posterior(prior, self._embed_share(embed), sample, post_noise), prior

    def observe(
        self, embed: Tensor, action: Tensor, is_first: Tensor, state: State | None = None
    ) -> tuple[State, State]:
        """Run the posterior over sequences; returns ``(post, prior)`` with batch shape ``(B, T)``.

        ``embed (B, T, E)``; ``action (B, T, A)`` is the action that led to step ``t``; ``is_first (B, T)``
        resets the recurrent state; ``state`` (batch ``(B,)``) is the state before step 0 (zeros if None).

        The same computation as :meth:`obs_step` at every ``t``, with the work that does not depend on the
        recurrent state done once for all steps: the actions' share of the recurrent input layer and the
        embeddings' share of the posterior's first layer; the prior's head and draw, which the next step does not
        read (it continues from the posterior), on every step's ``h`` at once after the loop; and the exponential
        noise of every categorical draw (one :func:`exponential_noise` call that fills the numbers the ``T`` prior
        and ``T`` posterior draws would take one by one, in the same order).
        """
        batch, length = action.shape[:2]
        given = state is not None
        if state is None:
            state = self.initial(batch, action.device)
        keep = (~is_first.bool()).to(action.dtype).transpose(0, 1)[..., None]  # (T, B, 1)
        embed_share = self._embed_share(embed).transpose(0, 1).contiguous()  # (T, B, H)
        img_in, act = self.img_in
        stoch_size = self.stoch * self.classes
        # W [z, a] + b = W_z z + (W_a a + b); a zeroed where the episode starts, as obs_step zeroes it.
        action_share = linear(action.transpose(0, 1) * keep, img_in.weight[:, stoch_size:], img_in.bias)
        stoch_weight = img_in.weight[:, :stoch_size].t()
        noise = exponential_noise((length, 2, batch, self.stoch, self.classes), action.device)
        # Which steps reset a sequence (on a CPU, where reading them costs no synchronisation): elsewhere the
        # multiplications by `keep` multiply by 1, and before the first step a zero state needs none either.
        if action.device.type == "cpu":
            resets = is_first.bool().any(0).tolist()
            resets[0] = resets[0] and given
        else:
            resets = [True] * length
        deter, stoch = state["deter"], state["stoch"].reshape(batch, stoch_size)
        deters: list[Tensor] = []
        posts: list[State] = []
        for t in range(length):
            if resets[t]:
                stoch, deter = stoch * keep[t], deter * keep[t]
            x = act(torch.addmm(action_share[t], stoch.to(action_share.dtype), stoch_weight))
            deter = self.cell(x, deter)
            post = self._posterior({"deter": deter}, embed_share[t], True, noise[t, 1])
            stoch = post["stoch"].reshape(batch, stoch_size)
            deters.append(deter)
            posts.append(post)
        prior_noise = noise[:, 0].reshape(length * batch, self.stoch, self.classes)
        prior = self._prior(torch.stack(deters).reshape(length * batch, -1), True, prior_noise)  # batch (T B,)
        prior = {key: value.reshape(length, batch, *value.shape[1:]).transpose(0, 1) for key, value in prior.items()}
        return stack_states(posts), prior

    def _embed_share(self, embed: Tensor) -> Tensor:
        """The embedding's part ``W_e e + b`` of the posterior's first layer ``W [h, e] + b``:
        ``(..., E) -> (..., H)``."""
        first, *_ = self.obs_out
        return linear(embed, first.weight[:, self.deter_size :], first.bias)

    def _prior(self, deter: Tensor, sample: bool, noise: Tensor | None = None) -> State:
        """The prior state of the recurrent state ``deter (N, D)``: its head's logits and their draw."""
        logits = self._logits(self.img_out(deter))
        return {"deter": deter, "logits": logits, "stoch": self._sample(logits, sample, noise)}

    def _posterior(self, prior: State, embed_share: Tensor, sample: bool, noise: Tensor | None = None) -> State:
        """The posterior next to ``prior`` ``(N, ...)``, given :meth:`_embed_share` ``(N, H)`` of the observation's
        embedding."""
        first, *rest = self.obs_out  # Linear([h, e] -> hidden), ELU, Linear(hidden -> S * K)
        hidden = torch.addmm(embed_share, prior["deter"], first.weight[:, : self.deter_size].t())
        for layer in rest:
            hidden = layer(hidden)
        logits = self._logits(hidden)
        return {"deter": prior["deter"], "logits": logits, "stoch": self._sample(logits, sample, noise)}

    def _logits(self, raw: Tensor) -> Tensor:
        """Raw ``(N, S * K)`` outputs to normalised log-probabilities ``(N, S, K)``, float32, with unimix."""
        logits = raw.float().reshape(raw.shape[0], self.stoch, self.classes)
        if self.unimix > 0.0:
            probs = (1.0 - self.unimix) * softmax(logits) + self.unimix / self.classes
            return probs.log()
        return log_softmax(logits)

    def _sample(self, logits: Tensor, sample: bool, noise: Tensor | None = None) -> Tensor:
        """Straight-through one-hot sample (``sample``, with ``noise`` if given) or the one-hot mode, ``(N, S, K)``."""
        dist = OneHotCategorical(logits, normalised=True)
        return dist.rsample(noise) if sample else dist.mode


def stack_states(states: list[State], dim: int = 1) -> State:
    """Stack a list of states with batch ``(N,)`` into one with batch ``(N, T)`` (``dim=1``) or ``(T, N)``."""
    return {key: torch.stack([s[key] for s in states], dim=dim) for key in states[0]}
