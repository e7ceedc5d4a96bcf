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

from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from coworld.models.distributions import OneHotCategorical, exponential_noise, log_softmax, one_hot_race, softmax
from coworld.models.networks import ELU, LayerNormGRUCell, Linear, glorot_init, linear, tanh_

__all__ = ["FUSED", "RSSM", "State", "stack_states"]

State = dict[str, Tensor]
"""An RSSM state: ``deter (..., D)``, ``logits (..., S, K)``, ``stoch (..., S, K)``."""

FUSED = True
"""Whether :meth:`RSSM.observe` may run its posterior loop as one autograd function (:class:`_Observe`) where it
applies (:meth:`RSSM._fuses`); False runs every step through autograd (the tests compare the two)."""


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
        self,
        embed: Tensor,
        action: Tensor,
        is_first: Tensor,
        state: State | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[State, State]:
        """Run the posterior over sequences; returns ``(post, prior)`` with batch shape ``(B, T)``.

        ``embed (B, T, E)``; ``action (B, T, A)`` is the action that led to step ``t``; ``is_first (B, T)``
        resets the recurrent state; ``state`` (batch ``(B,)``) is the state before step 0 (zeros if None);
        ``generator`` draws the categorical samples' noise (torch's default generator if None).

        The same computation as :meth:`obs_step` at every ``t``, with the work that does not depend on the
        recurrent state done once for all steps: the actions' share of the recurrent input layer and the
        embeddings' share of the posterior's first layer; the prior's head and draw, which the next step does not
        read (it continues from the posterior), on every step's ``h`` at once after the loop; and the exponential
        noise of every categorical draw (one :func:`exponential_noise` call that fills the numbers the ``T`` prior
        and ``T`` posterior draws would take one by one, in the same order). On a CPU in float32 the loop itself is
        one autograd function (:class:`_Observe`, :data:`FUSED`): the same values, its gradients by hand.
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
        noise = exponential_noise((length, 2, batch, self.stoch, self.classes), action.device, generator)
        # Which steps reset a sequence (on a CPU, where reading them costs no synchronisation): elsewhere the
        # multiplications by `keep` multiply by 1, and before the first step a zero state needs none either.
        if action.device.type == "cpu":
            resets = is_first.bool().any(0).tolist()
            resets[0] = resets[0] and given
        else:
            resets = [True] * length
        deter, stoch = state["deter"], state["stoch"].reshape(batch, stoch_size)
        if self._fuses(action_share):
            first, _, out = self.obs_out
            cell = self.cell
            deters, logits, stochs = _Observe.apply(
                _ObserveSpec(resets, self.stoch, self.classes, cell.norm.eps, cell.update_bias),
                action_share, embed_share, noise[:, 1], keep, deter, stoch, stoch_weight.t(), cell.linear.weight,
                cell.norm.weight, cell.norm.bias, first.weight[:, : self.deter_size], out.weight, out.bias,
            )  # fmt: skip
            post = {"deter": deters, "logits": logits, "stoch": stochs}  # batch (B, T)
            prior_noise = noise[:, 0].reshape(length * batch, self.stoch, self.classes)
            prior = self._prior(deters.transpose(0, 1).reshape(length * batch, -1), True, prior_noise)
            prior = {k: v.reshape(length, batch, *v.shape[1:]).transpose(0, 1) for k, v in prior.items()}
            return post, prior
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

    def _fuses(self, x: Tensor) -> bool:
        """Whether :meth:`observe` on inputs like ``x`` runs its loop as :class:`_Observe`: float32 on a CPU,
        outside autocast and ``torch.compile``, without unimix (elsewhere through autograd, step by step)."""
        return (
            FUSED
            and x.device.type == "cpu"
            and x.dtype == torch.float32
            and self.unimix == 0.0
            and not torch.is_autocast_enabled("cpu")
            and not torch.compiler.is_compiling()
        )

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


def _ln_bias(ln_b: Tensor, update_bias: float) -> Tensor:
    """The GRU's layer-norm bias with the update gate's bias added to its update part: ``u = sigmoid(norm(z)_u +
    update_bias)`` as one layer norm and one sigmoid."""
    size = ln_b.shape[0] // 3
    bias = ln_b.clone()
    bias[2 * size :] += update_bias
    return bias


def _gru(step: Tensor, w_cell_t: Tensor, ln_w: Tensor, ln_bias: Tensor, eps: float) -> tuple[Tensor, ...]:
    """:class:`~coworld.models.networks.LayerNormGRUCell` of ``step = [x, h] (N, H + D)`` without a graph, and
    what its backward reads: ``(h', z, mean, rstd, gates, cand)``, with ``z = W [x, h]`` and its layer norm's
    statistics, ``gates (N, 2, D)`` the reset and update gates and ``cand`` the candidate ``tanh(r c)``."""
    size = w_cell_t.shape[1] // 3
    z = torch.mm(step, w_cell_t)
    parts, mean, rstd = torch.native_layer_norm(z, [3 * size], ln_w, ln_bias, eps)
    parts = parts.view(-1, 3, size)
    gates = torch.sigmoid(parts[:, 0::2])  # reset r and update u
    cand = tanh_(gates[:, 0] * parts[:, 1])
    deter = torch.lerp(step[:, step.shape[1] - size :], cand, gates[:, 1])  # u c + (1 - u) h
    return deter, z, mean, rstd, gates, cand


def _gru_factors(
    gates: Tensor, cand: Tensor, zhat: Tensor, h: Tensor, ln_w: Tensor, ln_b: Tensor
) -> tuple[Tensor, Tensor]:
    """What :func:`_gru`'s backward multiplies by, for any leading dimensions: ``d parts / d h'`` of the reset,
    candidate and update parts ``(..., 3, D)`` (``h' = u c' + (1 - u) h``, ``c' = tanh(r c)``) and ``1 - u``;
    ``zhat`` is the normalised ``z`` and ``h`` the previous state."""
    size = h.shape[-1]
    r, u = gates[..., 0, :], gates[..., 1, :]
    cand_in = zhat[..., size : 2 * size] * ln_w[size : 2 * size] + ln_b[size : 2 * size]  # norm(z)'s candidate part
    uc = u * (1.0 - cand * cand)
    return torch.stack([uc * cand_in * r * (1.0 - r), uc * r, (cand - h) * u * (1.0 - u)], dim=-2), 1.0 - u


def _elu_backward(grad: Tensor, out: Tensor, *, into: Tensor) -> Tensor:
    """ELU's input gradient from its output ``out``, the op :class:`~coworld.models.networks.ELU`'s backward runs,
    written into ``into``."""
    return torch.ops.aten.elu_backward.grad_input(grad, 1.0, 1, 1, True, out, grad_input=into)


class _ObserveSpec(NamedTuple):
    """What :class:`_Observe` needs besides tensors."""

    resets: list[bool]
    """Per step, whether some sequence starts there (its state and action are zeroed by ``keep``)."""
    stoch: int
    classes: int
    eps: float
    """The GRU's layer norm's epsilon."""
    update_bias: float


class _Observe(torch.autograd.Function):
    """:meth:`RSSM.observe`'s loop over ``T`` steps as one autograd function: the posterior's deterministic states,
    logits and straight-through one-hot samples, batch ``(B, T)``, the same values (and memory layout) as the
    step-by-step loop's.

    The forward runs without recording a graph and keeps each step's intermediate values; the backward runs back
    through time by hand, each step's gradient with respect to the state in a few operations on ``(B, ...)``
    tensors, and every weight's gradient at the end as one matrix product over all ``T B`` rows. At the tiny preset's
    batch of 16 the loop is per-operation overhead rather than arithmetic (16 rows a product), and autograd's graph
    of some 40 operations a step is most of it.

    Inputs: ``action_share (T, B, H)`` (the recurrent input layer's action part and bias), ``embed_share (T, B,
    H)`` (the posterior's first layer's embedding part and bias), ``noise (T, B, S, K)`` (the posterior draws'
    exponential noise), ``keep (T, B, 1)`` (0 where a sequence starts), the state before step 0 ``deter0 (B, D)``,
    ``stoch0 (B, S K)``, and the weights: ``w_stoch (H, S K)`` (the recurrent input layer's stochastic part),
    ``w_cell (3 D, H + D)``, ``ln_w``, ``ln_b (3 D)`` (the GRU's product and layer norm), ``w_deter (H, D)`` (the
    posterior's first layer's deterministic part), ``w_out (S K, H)``, ``b_out (S K)``.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        spec: _ObserveSpec,
        action_share: Tensor,
        embed_share: Tensor,
        noise: Tensor,
        keep: Tensor,
        deter0: Tensor,
        stoch0: Tensor,
        w_stoch: Tensor,
        w_cell: Tensor,
        ln_w: Tensor,
        ln_b: Tensor,
        w_deter: Tensor,
        w_out: Tensor,
        b_out: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        length, batch, hidden = action_share.shape
        size = deter0.shape[-1]
        shape = (batch, spec.stoch, spec.classes)
        ln_bias = _ln_bias(ln_b, spec.update_bias)
        w_stoch_t, w_cell_t, w_deter_t, w_out_t = w_stoch.t(), w_cell.t(), w_deter.t(), w_out.t()
        xh = action_share.new_empty(length, batch, hidden + size)  # each step's GRU input [x, h]
        hids = action_share.new_empty(length, batch, hidden)
        deters, logits, stochs, z_rows, stats, gates, cands = [], [], [], [], [], [], []
        deter, stoch = deter0, stoch0
        for t, (step, hid) in enumerate(zip(xh.unbind(0), hids.unbind(0), strict=True)):
            if spec.resets[t]:
                stoch, deter = stoch * keep[t], deter * keep[t]
            torch.ops.aten.elu.out(torch.addmm(action_share[t], stoch, w_stoch_t), out=step[:, :hidden])
            step[:, hidden:] = deter
            deter, z, mean, rstd, gate, cand = _gru(step, w_cell_t, ln_w, ln_bias, spec.eps)
            torch.ops.aten.elu.out(torch.addmm(embed_share[t], deter, w_deter_t), out=hid)
            logit = log_softmax(torch.addmm(b_out, hid, w_out_t).view(shape))
            sample = one_hot_race(logit.exp(), noise[t])
            stoch = sample.view(batch, -1)
            deters.append(deter)
            logits.append(logit)
            stochs.append(sample)
            z_rows.append(z)
            stats.append((mean, rstd))
            gates.append(gate)
            cands.append(cand)
        ctx.spec = spec
        ctx.save_for_backward(keep, stoch0, w_stoch, w_cell, ln_w, ln_b, w_deter, w_out)
        ctx.saved = (xh, hids, deters, logits, stochs, z_rows, stats, gates, cands)
        # batch (B, T), contiguous as the step-by-step loop stacks its states
        return torch.stack(deters, 1), torch.stack(logits, 1), torch.stack(stochs, 1)

    @staticmethod
    def backward(ctx: Any, g_deters: Tensor | None, g_logits: Tensor | None, g_stochs: Tensor | None) -> tuple:
        spec = ctx.spec
        keep, stoch0, w_stoch, w_cell, ln_w, ln_b, w_deter, w_out = ctx.saved_tensors
        xh, hids, deters, logits, stochs, z_rows, stats, gates, cands = ctx.saved
        length, batch, _ = xh.shape
        size, hidden = deters[0].shape[-1], hids.shape[-1]
        stoch_size = spec.stoch * spec.classes
        shape = (batch, spec.stoch, spec.classes)
        # What each step's backward multiplies by, for all steps at once, (T, B, ...).
        mean, rstd = torch.stack([m for m, _ in stats]), torch.stack([v for _, v in stats])
        zhat = (torch.stack(z_rows) - mean) * rstd
        factors, one_minus_u = _gru_factors(torch.stack(gates), torch.stack(cands), zhat, xh[..., hidden:], ln_w, ln_b)
        log_probs = torch.stack(logits)
        probs = log_probs.exp()
        # the logits' gradient from outside, and the samples' (straight-through: their probabilities', exp(logits))
        outer = torch.zeros_like(probs)
        if g_logits is not None:
            outer += g_logits.transpose(0, 1)
        if g_stochs is not None:
            outer.addcmul_(probs, g_stochs.transpose(0, 1))
        # each step's state gradient from outside, added where the next step's backward gives it (below)
        g_deters = None if g_deters is None else g_deters.transpose(0, 1)
        g_raw = xh.new_empty(length, batch, stoch_size)
        g_preh = xh.new_empty(length, batch, hidden)
        g_parts = xh.new_empty(length, batch, 3 * size)
        g_prex = xh.new_empty(length, batch, hidden)
        g_z: list[Tensor] = []
        gd = xh.new_zeros(batch, size) if g_deters is None else g_deters[-1]
        gs = xh.new_zeros(batch, stoch_size)
        steps = zip(
            *(x.unbind(0) for x in (outer, probs, log_probs, g_raw, g_preh, g_parts, g_prex, hids, xh)),
            factors.unbind(0), one_minus_u.unbind(0), strict=True,
        )  # fmt: skip
        for t, (outer_t, probs_t, log_t, raw_t, preh_t, parts_t, prex_t, hid_t, xh_t, factors_t, omu_t) in reversed(
            list(enumerate(steps))
        ):
            gl = torch.addcmul(outer_t, probs_t, gs.view(shape))
            torch.ops.aten._log_softmax_backward_data.out(gl, log_t, -1, gl.dtype, out=raw_t.view(shape))
            _elu_backward(torch.mm(raw_t, w_out), hid_t, into=preh_t)
            gd = torch.addmm(gd, preh_t, w_deter)
            torch.mul(gd.unsqueeze(1), factors_t, out=parts_t.view(batch, 3, size))
            mean_t, rstd_t = stats[t]
            g_z.append(
                torch.ops.aten.native_layer_norm_backward(
                    parts_t, z_rows[t], [3 * size], mean_t, rstd_t, ln_w, ln_b, [True, False, False]
                )[0]
            )
            g_xh = torch.mm(g_z[-1], w_cell)
            gd = torch.addcmul(g_xh[:, hidden:], gd, omu_t)
            _elu_backward(g_xh[:, :hidden], xh_t[:, :hidden], into=prex_t)
            gs = torch.mm(prex_t, w_stoch)
            if spec.resets[t]:
                gd, gs = gd * keep[t], gs * keep[t]
            if g_deters is not None and t > 0:
                gd = gd + g_deters[t - 1]
        g_z.reverse()
        needs = ctx.needs_input_grad
        rows = length * batch

        def flat(x: Tensor) -> Tensor:
            return x.reshape(rows, -1)

        g_stoch_weight = None
        if needs[7]:  # each step's input sample, zeroed where its sequence starts
            stoch_in = torch.stack([stoch0.view(shape), *stochs[:-1]]).view(length, batch, stoch_size) * keep
            g_stoch_weight = flat(g_prex).t() @ flat(stoch_in)
        return (
            None,
            g_prex if needs[1] else None,
            g_preh if needs[2] else None,
            None,
            None,
            gd if needs[5] else None,
            gs if needs[6] else None,
            g_stoch_weight,
            flat(torch.stack(g_z)).t() @ flat(xh) if needs[8] else None,
            (g_parts * zhat).sum((0, 1)) if needs[9] else None,
            g_parts.sum((0, 1)) if needs[10] else None,
            flat(g_preh).t() @ flat(torch.stack(deters)) if needs[11] else None,
            flat(g_raw).t() @ flat(hids) if needs[12] else None,
            g_raw.sum((0, 1)) if needs[13] else None,
        )
