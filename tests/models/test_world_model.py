"""The world model: loss terms, their combination, and learning on a small structured dataset."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from coworld.config import Config
from coworld.models.networks import space_to_depth
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


# The tiny preset's conv depth (its decoder ends in 4 x 4 phases, so the loss's target is laid out again) and 16.
@pytest.mark.parametrize("depth", [None, 16])
def test_a_prepared_batch_gives_the_same_loss_gradients_and_posterior(tiny: Config, depth: int | None) -> None:
    cfg = tiny.world_model if depth is None else dataclasses.replace(tiny.world_model, cnn_depth=depth)
    model = WorldModel(config=cfg, action_size=ACTION_SIZE)
    batch = random_batch(batch=2, length=5)
    prepared = model.prepare(batch)
    assert "image" not in prepared and model.prepare(prepared) is prepared
    phases = space_to_depth(batch["image"])
    # On a CPU the encoder's phases come as the pixels' values in float32; the loss's target stays uint8.
    torch.testing.assert_close(prepared["phases"], phases.float(), rtol=0, atol=0)
    target = space_to_depth(phases) if model.decoder.phase_levels == 2 else phases
    torch.testing.assert_close(prepared["target"], target, rtol=0, atol=0)
    results = []
    for given in (batch, prepared):
        torch.manual_seed(0)
        terms, aux = model.loss(given)
        grads = torch.autograd.grad(aux["loss"], list(model.parameters()))
        torch.manual_seed(1)
        post, _, embed = model.observe(given)
        results.append([*terms.values(), *grads, post["stoch"], embed])
    for a, b in zip(*results, strict=True):
        assert torch.equal(a, b)


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
