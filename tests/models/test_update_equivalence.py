"""The fast DreamerV2 update computes what the straightforward one computed (main at df153e4).

A small reference of the old step is kept here: the RSSM stepped one observation at a time through ``torch.cat``
inputs and ``torch.multinomial`` samples, the decoder through ``nn.ConvTranspose2d``, the GRU's
``u * c + (1 - u) * h``, images preprocessed twice and the image loss as ``UnitGaussian.log_prob``. From the same
weights and the same seed, the losses and every gradient of a fixed batch must match to float tolerance, for the
world model and for the actor-critic on the imagined trajectories.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor

from coworld.config import Config
from coworld.losses.dreamer import kl_balanced_loss, reward_loss
from coworld.models.actor_critic import ActorCritic, flatten_states
from coworld.models.distributions import UnitGaussian
from coworld.models.networks import ELU, conv_transpose_stride2, frozen_parameters
from coworld.models.rssm import RSSM, stack_states
from coworld.models.world_model import WorldModel

from .conftest import ACTION_SIZE, random_batch

TOLERANCE = {"rtol": 1e-4, "atol": 1e-5}


def _reference_sample(logits: Tensor) -> Tensor:
    probs = torch.softmax(logits, -1)
    index = torch.multinomial(probs.reshape(-1, probs.shape[-1]).detach(), 1).squeeze(-1)
    sample = F.one_hot(index, probs.shape[-1]).to(probs.dtype).reshape(probs.shape)
    return sample + probs - probs.detach()


def _reference_img_step(rssm: RSSM, state: dict[str, Tensor], action: Tensor) -> dict[str, Tensor]:
    x = rssm.img_in(torch.cat([state["stoch"].reshape(action.shape[0], -1), action], -1))
    cell = rssm.cell
    parts = cell.norm(cell.linear(torch.cat([x, state["deter"]], -1)))
    reset, cand, update = parts.split(cell.size, -1)
    cand = torch.tanh(torch.sigmoid(reset) * cand)
    update = torch.sigmoid(update + cell.update_bias)
    deter = update * cand + (1.0 - update) * state["deter"]
    logits = torch.log_softmax(rssm.img_out(deter).reshape(-1, rssm.stoch, rssm.classes), -1)
    return {"deter": deter, "logits": logits, "stoch": _reference_sample(logits)}


def _plain(net: torch.nn.Sequential, x: Tensor) -> Tensor:
    """``net(x)`` with PyTorch's own ELU in place of the conv stacks' (:class:`ELU`, NumPy's forward, in place)."""
    for layer in net:
        x = F.elu(x) if isinstance(layer, ELU) else layer(x)
    return x


def _reference_world_model_loss(model: WorldModel, batch: dict[str, Tensor]) -> tuple[dict[str, Tensor], dict]:
    rssm, cfg = model.rssm, model.config

    def preprocess(image: Tensor) -> Tensor:
        return image.movedim(-1, -3).float() / 255.0 - 0.5

    image = preprocess(batch["image"])
    embed = _plain(model.encoder.net, image.reshape(-1, *image.shape[-3:])).reshape(*image.shape[:2], -1)
    batch_size, length = batch["action"].shape[:2]
    state = rssm.initial(batch_size)
    posts, priors = [], []
    for t in range(length):
        keep = (~batch["is_first"][:, t]).float()
        prev = {key: value * keep.reshape(-1, *([1] * (value.ndim - 1))) for key, value in state.items()}
        prior = _reference_img_step(rssm, prev, batch["action"][:, t] * keep[:, None])
        logits = rssm.obs_out(torch.cat([prior["deter"], embed[:, t]], -1)).reshape(-1, rssm.stoch, rssm.classes)
        logits = torch.log_softmax(logits, -1)
        state = {"deter": prior["deter"], "logits": logits, "stoch": _reference_sample(logits)}
        posts.append(state)
        priors.append(prior)
    post, prior = stack_states(posts), stack_states(priors)
    feat = rssm.features(post)
    decoder = model.decoder
    image = _plain(decoder.net, decoder.linear(feat.reshape(-1, feat.shape[-1])).reshape(-1, 32 * decoder.depth, 1, 1))
    image = image.reshape(batch_size, length, *image.shape[1:])
    terms = {
        "image": -UnitGaussian(image, event_dims=3).log_prob(preprocess(batch["image"])),
        "reward": reward_loss(model.reward_head(feat), batch["reward"]),
    }
    kl_loss, terms["kl"] = kl_balanced_loss(post["logits"], prior["logits"], cfg.kl_balance, cfg.free_nats)
    loss = terms["image"].mean() * cfg.image_scale + cfg.reward_scale * terms["reward"].mean()
    return terms, {"post": post, "prior": prior, "loss": loss + cfg.kl_scale * kl_loss}


def _reference_imagine(ac: ActorCritic, model: WorldModel, start: dict[str, Tensor], terminal: Tensor) -> dict:
    """ActorCritic.imagine's rollout with the reference prior step (no discount head)."""
    state = {key: value.detach() for key, value in start.items()}
    feats, actions = [model.features(state)], [torch.zeros(state["deter"].shape[0], ac.action_size)]
    for _ in range(ac.config.horizon):
        action = ac.actor(feats[-1].detach()).rsample()
        state = _reference_img_step(model.rssm, state, action)
        feats.append(model.features(state))
        actions.append(action)
    feat = torch.stack(feats)
    reward = model.reward_head(feat).mean
    gamma = ac.config.discount
    continuation = torch.full_like(reward, gamma)
    continuation[0] = gamma * (1.0 - terminal.float())
    weight = torch.cumprod(torch.cat([torch.ones_like(continuation[:1]), continuation[:-1]]), 0)
    return {
        "feat": feat,
        "action": torch.stack(actions),
        "reward": reward,
        "continuation": continuation,
        "weight": weight.detach(),
    }


def _assert_close_in_norm(got: Tensor, want: Tensor) -> None:
    """Float32 rounding, measured against the tensor's size: a gradient summed over thousands of pixels can
    cancel to a small element whose own relative error is large."""
    assert float((got - want).norm()) <= 1e-4 * float(want.norm()) + 1e-6, (
        float((got - want).norm()),
        float(want.norm()),
    )


def _grads(loss: Tensor, params: list[torch.nn.Parameter]) -> list[Tensor]:
    return list(torch.autograd.grad(loss, params, allow_unused=False))


# The tiny preset's conv depth (its decoder ends in 4 x 4 phases) and a wider one (2 x 2 phases).
@pytest.mark.parametrize(("seed", "cnn_depth"), [(0, None), (1, None), (2, None), (3, None), (0, 16)])
def test_update_matches_the_reference_step(tiny: Config, seed: int, cnn_depth: int | None) -> None:
    depth = tiny.world_model.cnn_depth if cnn_depth is None else cnn_depth
    cfg = dataclasses.replace(tiny, world_model=dataclasses.replace(tiny.world_model, free_nats=0.0, cnn_depth=depth))
    model = WorldModel(config=cfg.world_model, action_size=ACTION_SIZE)
    ac = ActorCritic(config=cfg.actor_critic, feat_size=model.feat_size, action_size=ACTION_SIZE)
    batch = random_batch(batch=3, length=6)
    batch["is_first"][1, 3] = True  # an episode starting mid-window resets the latent there
    wm_params = list(model.parameters())

    torch.manual_seed(seed)
    terms, aux = model.loss(batch)
    wm_grads = _grads(aux["loss"], wm_params)
    torch.manual_seed(seed)
    ref_terms, ref_aux = _reference_world_model_loss(model, batch)
    ref_wm_grads = _grads(ref_aux["loss"], wm_params)

    for name in ("image", "reward", "kl"):
        torch.testing.assert_close(terms[name], ref_terms[name], **TOLERANCE)
    torch.testing.assert_close(aux["post"]["stoch"], ref_aux["post"]["stoch"], **TOLERANCE)
    torch.testing.assert_close(aux["prior"]["stoch"], ref_aux["prior"]["stoch"], **TOLERANCE)
    for grad, ref in zip(wm_grads, ref_wm_grads, strict=True):
        _assert_close_in_norm(grad, ref)

    ac_params = list(ac.actor.parameters()) + list(ac.critic.parameters())
    start = flatten_states(aux["post"])
    terminal = batch["is_terminal"].reshape(-1)
    with frozen_parameters(model):
        torch.manual_seed(seed + 10)
        ac_terms, _ = ac.losses(model, ac.imagine(model, start, is_terminal=terminal))
        ac_grads = _grads(ac_terms["actor"] + ac_terms["critic"], ac_params)
        torch.manual_seed(seed + 10)
        ref_ac_terms, _ = ac.losses(model, _reference_imagine(ac, model, start, terminal))
        ref_ac_grads = _grads(ref_ac_terms["actor"] + ref_ac_terms["critic"], ac_params)
    for name in ("actor", "critic", "target"):
        torch.testing.assert_close(ac_terms[name], ref_ac_terms[name], **TOLERANCE)
    for grad, ref in zip(ac_grads, ref_ac_grads, strict=True):
        _assert_close_in_norm(grad, ref)


@pytest.mark.parametrize(
    ("c_in", "c_out", "kernel", "height", "width"), [(5, 4, 5, 1, 1), (4, 3, 5, 5, 7), (3, 2, 6, 4, 3)]
)
def test_conv_transpose_stride2_is_the_transposed_convolution(
    c_in: int, c_out: int, kernel: int, height: int, width: int
) -> None:
    x = torch.randn(2, c_in, height, width, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(c_in, c_out, kernel, kernel, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(c_out, dtype=torch.float64, requires_grad=True)
    expected = F.conv_transpose2d(x, weight, bias, stride=2)
    for layout in (torch.contiguous_format, torch.channels_last):
        out = conv_transpose_stride2(x.contiguous(memory_format=layout), weight, bias)
        torch.testing.assert_close(out, expected)
        grad = torch.randn_like(expected)
        got = torch.autograd.grad(out, [x, weight, bias], grad)
        want = torch.autograd.grad(expected, [x, weight, bias], grad, retain_graph=True)
        for a, b in zip(got, want, strict=True):
            torch.testing.assert_close(a, b)
