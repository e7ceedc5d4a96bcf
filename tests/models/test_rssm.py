"""The RSSM: state shapes, episode resets, unimix and the straight-through latent."""

from __future__ import annotations

import pytest
import torch

import coworld.models.rssm as rssm_module
from coworld.config import Config
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
    """``observe`` (its work batched across steps, its multiplications by ``keep`` left out where no sequence
    resets) gives what stepping ``obs_step`` gives, from the same random numbers: episodes that start mid-window,
    and a start state that some sequences continue from."""
    rssm = _rssm(tiny)
    batch, length = 3, 7
    embed, action = torch.randn(batch, length, 10), torch.randn(batch, length, 3)
    is_first = torch.zeros(batch, length, dtype=torch.bool)
    is_first[1, 3] = is_first[2, 5] = True
    is_first[0, 0] = not given  # with a start state every sequence continues from it; without, sequence 0 starts
    start = {key: torch.randn_like(value) for key, value in rssm.initial(batch).items()} if given else None
    torch.manual_seed(0)
    post, prior = rssm.observe(embed, action, is_first, start)
    torch.manual_seed(0)
    state = start if start is not None else rssm.initial(batch)
    posts, priors = [], []
    for t in range(length):
        state, step_prior = rssm.obs_step(state, action[:, t], embed[:, t], is_first[:, t])
        posts.append(state)
        priors.append(step_prior)
    for got, want in ((post, stack_states(posts)), (prior, stack_states(priors))):
        for key in want:
            torch.testing.assert_close(got[key], want[key])


def _observe_with_gradients(
    rssm: RSSM, inputs: dict[str, torch.Tensor], is_first: torch.Tensor, used: tuple[str, ...], fused: bool
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor | None]]:
    """``observe``'s states and the gradients of a random weighting of the outputs in ``used`` with respect to
    every input and weight, through the fused loop or step by step."""
    leaves = {name: value.detach().clone().requires_grad_() for name, value in inputs.items()}
    start = {"deter": leaves["deter0"], "stoch": leaves["stoch0"], "logits": torch.zeros_like(leaves["stoch0"])}
    rssm.zero_grad(set_to_none=True)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(rssm_module, "FUSED", fused)
        torch.manual_seed(1)
        post, prior = rssm.observe(leaves["embed"], leaves["action"], is_first, start)
    states = {f"post_{key}": value for key, value in post.items()} | {f"prior_{k}": v for k, v in prior.items()}
    generator = torch.Generator().manual_seed(2)
    loss = sum((torch.randn(states[n].shape, generator=generator) * states[n]).sum() for n in used)
    loss.backward()
    grads = {name: leaf.grad for name, leaf in leaves.items()}
    grads.update({name: param.grad for name, param in rssm.named_parameters()})
    return states, grads


@pytest.mark.parametrize(
    ("used", "batch"),
    [
        (("post_deter", "post_logits", "post_stoch", "prior_deter", "prior_logits", "prior_stoch"), 4),
        (("post_deter", "post_logits", "post_stoch", "prior_deter", "prior_logits", "prior_stoch"), 17),
        (("post_stoch",), 4),
        (("post_logits", "prior_logits"), 4),
        (("post_deter",), 4),
    ],
)
def test_fused_observe_matches_the_step_by_step_loop_with_every_gradient(
    tiny: Config, used: tuple[str, ...], batch: int
) -> None:
    """The fused loop (one autograd function, its backward through time by hand) computes what autograd through
    every step computes: the states (their memory layout too) and the gradients of the inputs, the start state and
    every weight, through episodes that start mid-window, whichever outputs the loss reads; at 17 sequences the
    logits' softmax runs with the classes first (:func:`~coworld.models.distributions.log_softmax`)."""
    rssm = _rssm(tiny)
    with torch.no_grad():  # away from the initial weights' symmetric values, so every term counts
        for param in rssm.parameters():
            param.add_(0.3 * torch.randn_like(param))
    length = 9
    inputs = {
        "embed": torch.randn(batch, length, 10),
        "action": torch.randn(batch, length, 3),
        "deter0": torch.randn(batch, tiny.world_model.deter),
        "stoch0": torch.randn(batch, tiny.world_model.stoch, tiny.world_model.classes).softmax(-1),
    }
    is_first = torch.zeros(batch, length, dtype=torch.bool)
    is_first[1, 0] = is_first[1, 4] = is_first[2, 6] = True
    want_states, want_grads = _observe_with_gradients(rssm, inputs, is_first, used, fused=False)
    got_states, got_grads = _observe_with_gradients(rssm, inputs, is_first, used, fused=True)
    for name, want in want_states.items():
        torch.testing.assert_close(got_states[name], want, msg=name)
        assert got_states[name].stride() == want.stride(), name
    for name, want in want_grads.items():
        got = got_grads[name]
        if want is None:  # not reached by this loss step by step: nothing, or zeros, from the fused loop
            assert got is None or not got.any(), name
            continue
        assert got is not None, name
        # summation orders differ: a rounding's worth of the largest entry, on top of the usual relative tolerance
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6 * float(want.abs().max()), msg=name)


def test_fused_observe_leaves_frozen_weights_without_gradient(tiny: Config) -> None:
    rssm = _rssm(tiny)
    embed = torch.randn(2, 5, 10, requires_grad=True)
    rssm.requires_grad_(False)
    post, _ = rssm.observe(embed, torch.randn(2, 5, 3), torch.zeros(2, 5, dtype=torch.bool))
    (post["stoch"] * torch.randn_like(post["stoch"])).sum().backward()
    assert all(param.grad is None for param in rssm.parameters())
    assert embed.grad is not None and embed.grad.abs().sum() > 0
