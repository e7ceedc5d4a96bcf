"""The world model: loss terms, their combination, and learning on a small structured dataset."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import nn

from coworld.config import Config, make_config
from coworld.distributions import UnitGaussian
from coworld.models.networks import ChannelNorm
from coworld.models.world_model import WorldModel, preprocess_image

from .conftest import ACTION_SIZE, random_batch


def test_preprocess_image_layout_and_range() -> None:
    image = torch.zeros(2, 3, 64, 64, 3, dtype=torch.uint8)
    image[..., 1] = 255
    out = preprocess_image(image)
    assert out.shape == (2, 3, 3, 64, 64) and out.dtype == torch.float32
    assert float(out[:, :, 0].max()) == -0.5 and float(out[:, :, 1].min()) == 0.5


def test_loss_terms_shapes_and_total(tiny: Config) -> None:
    tiny = dataclasses.replace(tiny, world_model=dataclasses.replace(tiny.world_model, pred_discount=True))
    model = WorldModel(config=tiny.world_model, action_size=ACTION_SIZE)
    batch = random_batch(batch=2, length=5)
    terms, aux = model.loss(batch)
    assert set(terms) == {"image", "reward", "discount", "kl"}
    assert all(term.shape == (2, 5) for term in terms.values())
    assert aux["embed"].shape == (2, 5, model.encoder.embed_size)
    assert aux["feat"].shape == (2, 5, model.feat_size)
    assert aux["post"]["logits"].shape == (2, 5, tiny.world_model.stoch, tiny.world_model.classes)
    cfg = tiny.world_model
    kl_loss = torch.clamp(terms["kl"].mean(), min=cfg.free_nats)
    expected = terms["image"].mean() + terms["reward"].mean() + terms["discount"].mean() + kl_loss
    torch.testing.assert_close(aux["loss"], expected)
    # The reward head's mean, fed to reward-loss, reproduces the term (how CoWorld relabels source rewards).
    pred = model.reward_head(aux["feat"]).mean
    torch.testing.assert_close(0.5 * (pred - batch["reward"]) ** 2, terms["reward"])


def test_image_term_is_the_decoders_gaussian_nll_of_the_preprocessed_image(tiny: Config) -> None:
    """The image term is ``-ln N(preprocess_image(o); decoder(feat), 1)`` summed over pixels (its constant dropped),
    and the loss repeats bit for bit from the same generator seed."""
    model = WorldModel(config=tiny.world_model, action_size=ACTION_SIZE)
    batch = random_batch(batch=2, length=5)
    terms, aux = model.loss(batch, torch.Generator().manual_seed(5))
    mean = model.decoder(aux["feat"])
    assert mean.shape == (2, 5, 3, 64, 64)
    want = 0.5 * ((mean - preprocess_image(batch["image"])) ** 2).sum((-3, -2, -1))
    torch.testing.assert_close(terms["image"], want)
    target = preprocess_image(batch["image"])
    torch.testing.assert_close(terms["image"], -UnitGaussian(mean, event_dims=3).log_prob(target))
    normal = torch.distributions.Normal(mean.double(), 1.0).log_prob(target.double()).sum((-3, -2, -1))
    constant = 0.5 * math.log(2 * math.pi) * mean[0, 0].numel()
    torch.testing.assert_close(terms["image"].double(), -normal - constant, rtol=1e-5, atol=1e-3)
    again, again_aux = model.loss(batch, torch.Generator().manual_seed(5))
    assert all(torch.equal(again[name], terms[name]) for name in terms)
    assert torch.equal(again_aux["loss"], aux["loss"])
    # The same generator seed gives observe's posterior too; the loss reads it.
    post, _, embed = model.observe(batch, generator=torch.Generator().manual_seed(5))
    assert torch.equal(post["stoch"], aux["post"]["stoch"]) and torch.equal(embed, aux["embed"])
    torch.testing.assert_close(embed, model.encoder(preprocess_image(batch["image"])), rtol=0, atol=0)


def test_config_reaches_every_module(tiny: Config) -> None:
    """``act``, ``norm``, the conv kernels and the GRU's bias and epsilon build the modules they name."""
    overrides = {"act": "silu", "norm": "layer", "encoder_kernels": (3, 3, 3, 3, 3), "gru_bias": True, "gru_eps": 1e-3}
    cfg = dataclasses.replace(tiny.world_model, **overrides)
    model = WorldModel(config=cfg, action_size=ACTION_SIZE)
    kinds = {type(m) for m in (*model.encoder.modules(), *model.decoder.modules(), *model.rssm.modules())}
    assert nn.SiLU in kinds and nn.ELU not in kinds and ChannelNorm in kinds and nn.LayerNorm in kinds
    assert [m.kernel_size for m in model.encoder.net if isinstance(m, nn.Conv2d)] == [(3, 3)] * 5
    assert model.encoder.embed_size == 16 * cfg.cnn_depth
    assert model.rssm.cell.linear.bias is not None and model.rssm.cell.norm.eps == 1e-3
    terms, aux = model.loss(random_batch(batch=2, length=3))
    assert torch.isfinite(aux["loss"]) and terms["image"].shape == (2, 3)
    plain = WorldModel(config=tiny.world_model, action_size=ACTION_SIZE)
    assert not any(isinstance(m, ChannelNorm | nn.SiLU) for m in plain.modules())
    assert [type(m) for m in plain.rssm.img_in] == [nn.Linear, nn.ELU]  # the GRU cell's own LayerNorm stays
    assert plain.rssm.cell.linear.bias is None and plain.rssm.cell.norm.eps == 1e-5  # the tiny preset's
    paper = WorldModel(config=make_config("paper").world_model, action_size=ACTION_SIZE)
    assert paper.rssm.cell.linear.bias is not None and paper.rssm.cell.norm.eps == 1e-3  # DreamerV2's


def test_no_discount_head_without_pred_discount(tiny: Config) -> None:
    config = dataclasses.replace(tiny.world_model, pred_discount=False)
    model = WorldModel(config=config, action_size=ACTION_SIZE)
    assert model.discount_head is None
    terms, _ = model.loss(random_batch())
    assert "discount" not in terms


def test_scales_weight_the_terms(tiny: Config) -> None:
    tiny = dataclasses.replace(tiny, world_model=dataclasses.replace(tiny.world_model, pred_discount=True))
    batch = random_batch()
    model = WorldModel(config=tiny.world_model, action_size=ACTION_SIZE)
    scaled = WorldModel(config=dataclasses.replace(tiny.world_model, image_scale=0.0, free_nats=0.0), action_size=3)
    scaled.load_state_dict(model.state_dict())
    torch.manual_seed(1)
    terms, aux = scaled.loss(batch)
    expected = terms["reward"].mean() + terms["discount"].mean() + terms["kl"].mean()
    torch.testing.assert_close(aux["loss"], expected)


def moving_square_batch(episodes: int = 4, length: int = 16, seed: int = 0) -> dict[str, torch.Tensor]:
    """Episodes of a white 12 x 12 square on grey, moved by 2-D actions; reward = horizontal position in [-1, 1]."""
    rng = np.random.default_rng(seed)
    image = np.full((episodes, length, 64, 64, 3), 40, dtype=np.uint8)
    action = rng.uniform(-1, 1, (episodes, length, 2)).astype(np.float32)
    action[:, 0] = 0.0
    reward = np.zeros((episodes, length), np.float32)
    for e in range(episodes):
        pos = rng.uniform(0, 52, 2)
        for t in range(length):
            pos = np.clip(pos + 8.0 * action[e, t], 0, 52)
            x, y = pos.astype(int)
            image[e, t, y : y + 12, x : x + 12] = 230
            reward[e, t] = pos[0] / 26.0 - 1.0
    is_first = np.zeros((episodes, length), bool)
    is_first[:, 0] = True
    flags = np.zeros((episodes, length), bool)
    arrays = {"image": image, "action": action, "reward": reward, "is_first": is_first}
    arrays |= {"is_last": flags, "is_terminal": flags}
    return {key: torch.as_tensor(value) for key, value in arrays.items()}


def test_image_and_reward_losses_fall_on_moving_square(tiny: Config) -> None:
    batch = moving_square_batch()
    model = WorldModel(config=tiny.world_model, action_size=2)
    opt = torch.optim.AdamW(model.parameters(), lr=tiny.world_model.lr, eps=tiny.world_model.eps)
    history: list[tuple[float, float]] = []
    for _ in range(120):
        terms, aux = model.loss(batch)
        opt.zero_grad()
        aux["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), tiny.world_model.grad_clip)
        opt.step()
        history.append((terms["image"].mean().item(), terms["reward"].mean().item()))
    first = np.mean(history[:5], axis=0)
    last = np.mean(history[-5:], axis=0)
    assert last[0] < 0.3 * first[0], f"image loss {first[0]:.1f} -> {last[0]:.1f}"
    assert last[1] < 0.4 * first[1], f"reward loss {first[1]:.3f} -> {last[1]:.3f}"
