"""The RSSM: state shapes, episode resets, unimix and the straight-through latent."""

from __future__ import annotations

import pytest
import torch

from coworld.config import Config
from coworld.distributions import exponential_noise
from coworld.models.rssm import RSSM, stack_states


def _rssm(tiny: Config, unimix: float = 0.0) -> RSSM:
    wm = tiny.world_model
    return RSSM(
        embed_size=10,
        action_size=3,
        deter=wm.deter,
        hidden=wm.hidden,
        stoch=wm.stoch,
        classes=wm.classes,
        unimix=unimix,
    )


def test_observe_shapes(tiny: Config) -> None:
    rssm = _rssm(tiny)
    wm = tiny.world_model
    is_first = torch.zeros(2, 6, dtype=torch.bool)
    is_first[:, 0] = True
    post, prior = rssm.observe(torch.randn(2, 6, 10), torch.randn(2, 6, 3), is_first)
    for state in (post, prior):
        assert state["deter"].shape == (2, 6, wm.deter)
        assert state["logits"].shape == (2, 6, wm.stoch, wm.classes)
        assert state["stoch"].shape == (2, 6, wm.stoch, wm.classes)
    assert rssm.features(post).shape == (2, 6, wm.deter + wm.stoch * wm.classes) == (2, 6, rssm.feat_size)
    # Posterior and prior share the deterministic state; logits are normalised log-probabilities.
    assert torch.equal(post["deter"], prior["deter"])
    torch.testing.assert_close(post["logits"].exp().sum(-1), torch.ones(2, 6, wm.stoch))


def test_is_first_resets_state_and_action(tiny: Config) -> None:
    rssm = _rssm(tiny)
    embed = torch.randn(3, 10)
    garbage = {key: torch.randn_like(value) for key, value in rssm.initial(3).items()}
    action = torch.randn(3, 3)
    is_first = torch.tensor([True, False, True])
    post, _ = rssm.obs_step(garbage, action, embed, is_first, sample=False)
    fresh, _ = rssm.obs_step(rssm.initial(3), torch.zeros(3, 3), embed, sample=False)
    for key in post:
        torch.testing.assert_close(post[key][is_first], fresh[key][is_first])
        assert not torch.allclose(post[key][1], fresh[key][1])


def test_unimix_puts_a_floor_under_class_probabilities(tiny: Config) -> None:
    rssm = _rssm(tiny, unimix=0.1)
    rssm.img_out[-1].weight.data.mul_(100.0)  # very peaked raw logits
    prior = rssm.img_step(rssm.initial(4), torch.randn(4, 3))
    probs = prior["logits"].detach().exp()
    assert float(probs.min()) >= 0.1 / tiny.world_model.classes - 1e-6
    torch.testing.assert_close(probs.sum(-1), torch.ones(4, tiny.world_model.stoch))


def test_latent_sample_passes_gradient_to_the_representation(tiny: Config) -> None:
    rssm = _rssm(tiny)
    embed = torch.randn(2, 10, requires_grad=True)
    post, _ = rssm.obs_step(rssm.initial(2), torch.zeros(2, 3), embed)
    (post["stoch"] * torch.randn_like(post["stoch"])).sum().backward()
    assert embed.grad is not None and embed.grad.abs().sum() > 0


@pytest.mark.parametrize("given", [False, True])
def test_observe_is_obs_step_at_every_step_through_resets(tiny: Config, given: bool) -> None:
    """``observe`` gives what stepping ``obs_step`` gives, from the same random numbers (one
    :func:`exponential_noise` draw ``(T, 2, B, S, K)`` from the generator, step ``t`` taking ``noise[t]``): episodes
    that start mid-window, and a start state that some sequences continue from; the same generator seed gives the
    same states."""
    rssm = _rssm(tiny)
    wm = tiny.world_model
    batch, length = 3, 7
    embed, action = torch.randn(batch, length, 10), torch.randn(batch, length, 3)
    is_first = torch.zeros(batch, length, dtype=torch.bool)
    is_first[1, 3] = is_first[2, 5] = True
    is_first[0, 0] = not given  # with a start state every sequence continues from it; without, sequence 0 starts
    start = {key: torch.randn_like(value) for key, value in rssm.initial(batch).items()} if given else None
    post, prior = rssm.observe(embed, action, is_first, start, torch.Generator().manual_seed(3))
    noise = exponential_noise((length, 2, batch, wm.stoch, wm.classes), generator=torch.Generator().manual_seed(3))
    state = start if start is not None else rssm.initial(batch)
    posts, priors = [], []
    for t in range(length):
        state, step_prior = rssm.obs_step(state, action[:, t], embed[:, t], is_first[:, t], noise=noise[t])
        posts.append(state)
        priors.append(step_prior)
    for got, want in ((post, stack_states(posts)), (prior, stack_states(priors))):
        for key in want:
            torch.testing.assert_close(got[key], want[key], rtol=0, atol=0)
    again, _ = rssm.observe(embed, action, is_first, start, torch.Generator().manual_seed(3))
    assert all(torch.equal(again[key], post[key]) for key in post)
    other, _ = rssm.observe(embed, action, is_first, start, torch.Generator().manual_seed(4))
    assert not torch.equal(other["stoch"], post["stoch"])


def test_observe_without_priors_gives_the_same_posterior_and_gradients(tiny: Config) -> None:
    """``priors=False`` (the callers that read only the posterior: Eq. 3's source latents, Eq. 5's relabel pass, the
    source choice, the penalised policy phase) returns the posterior ``priors=True`` gives, bit for bit, with the same
    gradients to the embedding, draws the same noise (the generator ends in the same state), and never runs the
    transition model."""
    rssm = _rssm(tiny)
    batch, length = 3, 6
    embed, action = torch.randn(batch, length, 10), torch.randn(batch, length, 3)
    is_first = torch.zeros(batch, length, dtype=torch.bool)
    is_first[:, 0] = is_first[1, 3] = True
    weights = torch.randn(batch, length, tiny.world_model.stoch, tiny.world_model.classes)
    results = {}
    for priors in (True, False):
        leaf = embed.clone().requires_grad_(True)
        generator = torch.Generator().manual_seed(5)
        post, prior = rssm.observe(leaf, action, is_first, generator=generator, priors=priors)
        (post["stoch"] * weights).sum().backward()
        results[priors] = post, prior, leaf.grad, generator.get_state()
    (post, prior, grad, after), (post_only, none, grad_only, after_only) = results[True], results[False]
    assert prior is not None and none is None
    assert all(torch.equal(post[key], post_only[key]) for key in post)
    assert torch.equal(grad, grad_only) and grad.abs().sum() > 0
    assert torch.equal(after, after_only)
    calls = []
    rssm.transition = lambda *args: calls.append(args)  # an instance attribute shadows the method
    rssm.observe(embed, action, is_first, priors=False)
    assert calls == []


def test_observe_with_frozen_weights_passes_gradient_to_the_embedding(tiny: Config) -> None:
    rssm = _rssm(tiny)
    embed = torch.randn(2, 5, 10, requires_grad=True)
    rssm.requires_grad_(False)
    post, _ = rssm.observe(embed, torch.randn(2, 5, 3), torch.zeros(2, 5, dtype=torch.bool))
    (post["stoch"] * torch.randn_like(post["stoch"])).sum().backward()
    assert all(param.grad is None for param in rssm.parameters())
    assert embed.grad is not None and embed.grad.abs().sum() > 0


def test_act_norm_and_gru_options_reach_every_layer(tiny: Config) -> None:
    wm = tiny.world_model
    rssm = RSSM(
        embed_size=10,
        action_size=3,
        deter=wm.deter,
        hidden=wm.hidden,
        stoch=wm.stoch,
        classes=wm.classes,
        act="silu",
        norm="layer",
        gru_bias=False,
        gru_eps=1e-5,
    )
    hidden = [torch.nn.Linear, torch.nn.LayerNorm, torch.nn.SiLU]
    assert [type(m) for m in rssm.img_in] == hidden
    assert [type(m) for m in rssm.img_out] == [*hidden, torch.nn.Linear]
    assert [type(m) for m in rssm.obs_out] == [*hidden, torch.nn.Linear]
    assert rssm.cell.linear.bias is None and rssm.cell.norm.eps == 1e-5
    plain = _rssm(tiny)
    assert [type(m) for m in plain.img_in] == [torch.nn.Linear, torch.nn.ELU]
    assert plain.cell.linear.bias is not None and plain.cell.norm.eps == 1e-3
