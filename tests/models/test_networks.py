"""Shapes and small behaviours of the DreamerV2 building blocks on the tiny preset."""

from __future__ import annotations

import pytest
import torch

from coworld.config import Config
from coworld.errors import CoworldError
from coworld.models.networks import (
    MLP,
    ConvDecoder,
    ConvEncoder,
    LayerNormGRUCell,
    check_image_shape,
    frozen_parameters,
)


def test_encoder_maps_64x64_images_to_flat_embedding(tiny: Config) -> None:
    depth = tiny.world_model.cnn_depth
    encoder = ConvEncoder(channels=3, depth=depth)
    out = encoder(torch.rand(2, 5, 3, 64, 64) - 0.5)
    assert encoder.embed_size == 8 * depth * 2 * 2
    assert out.shape == (2, 5, encoder.embed_size)
    assert [layer.out_channels for layer in encoder.net if isinstance(layer, torch.nn.Conv2d)] == [
        depth,
        2 * depth,
        4 * depth,
        8 * depth,
    ]


def test_decoder_maps_features_back_to_64x64(tiny: Config) -> None:
    decoder = ConvDecoder(feat_size=17, channels=3, depth=tiny.world_model.cnn_depth)
    assert decoder(torch.randn(2, 5, 17)).shape == (2, 5, 3, 64, 64)
    grayscale = ConvDecoder(feat_size=17, channels=1, depth=4)
    assert grayscale(torch.randn(4, 17)).shape == (4, 1, 64, 64)


def test_mlp_shape_and_depth() -> None:
    mlp = MLP(in_size=7, out_size=2, units=16, layers=3)
    assert mlp(torch.randn(4, 6, 7)).shape == (4, 6, 2)
    assert sum(isinstance(m, torch.nn.Linear) for m in mlp.modules()) == 4


def test_mlp_norm_centres_and_scales_each_hidden_layer() -> None:
    mlp = MLP(in_size=7, out_size=2, units=16, layers=2, norm=True, act="silu")
    hidden = mlp.net[:-1]
    assert [type(m) for m in hidden] == [torch.nn.Linear, torch.nn.LayerNorm, torch.nn.SiLU] * 2
    # Inputs that share a large common part: after the first Linear + LayerNorm, each row has mean 0, std 1.
    x = torch.randn(32, 7) * 0.01 + 5.0
    normed = hidden[1](hidden[0](x))
    torch.testing.assert_close(normed.mean(-1), torch.zeros(32), atol=1e-5, rtol=0)
    torch.testing.assert_close(normed.std(-1, unbiased=False), torch.ones(32), atol=2e-2, rtol=0)
    plain = MLP(in_size=7, out_size=2, units=16, layers=2)
    assert not any(isinstance(m, torch.nn.LayerNorm | torch.nn.SiLU) for m in plain.modules())
    with pytest.raises(CoworldError, match="unknown MLP activation 'relu'"):
        MLP(in_size=7, out_size=2, units=16, layers=2, act="relu")


def test_gru_cell_shape_and_convex_update() -> None:
    cell = LayerNormGRUCell(in_size=5, size=8)
    h = torch.randn(3, 8)
    out = cell(torch.randn(3, 5), h)
    assert out.shape == (3, 8)
    # h' = u * c + (1 - u) * h with c in (-1, 1): each entry lies between h and a value in (-1, 1).
    assert torch.all(out <= torch.maximum(h, torch.ones_like(h)) + 1e-6)
    assert torch.all(out >= torch.minimum(h, -torch.ones_like(h)) - 1e-6)


def test_only_64x64_images_are_accepted() -> None:
    check_image_shape((64, 64, 3))
    with pytest.raises(CoworldError, match="64 x 64"):
        check_image_shape((84, 84, 3))


def test_frozen_parameters_lets_gradient_through_but_not_into_weights() -> None:
    mlp = MLP(in_size=3, out_size=1, units=4, layers=1)
    x = torch.randn(2, 3, requires_grad=True)
    with frozen_parameters(mlp):
        mlp(x).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert all(p.grad is None for p in mlp.parameters())
    assert all(p.requires_grad for p in mlp.parameters())
