"""Shapes and small behaviours of the DreamerV2 building blocks (plain PyTorch modules) on the tiny preset."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from coworld.config import Config
from coworld.errors import ConfigError, CoworldError
from coworld.models.networks import (
    MLP,
    ChannelNorm,
    ConvDecoder,
    ConvEncoder,
    LayerNormGRUCell,
    check_image_shape,
    frozen_parameters,
    make_act,
    make_norm,
)


def test_encoder_maps_64x64_images_to_flat_embedding(tiny: Config) -> None:
    depth = tiny.world_model.cnn_depth
    encoder = ConvEncoder(channels=3, depth=depth)
    out = encoder(torch.rand(2, 5, 3, 64, 64) - 0.5)
    assert encoder.embed_size == 8 * depth * 2 * 2
    assert out.shape == (2, 5, encoder.embed_size)
    convs = [layer for layer in encoder.net if isinstance(layer, nn.Conv2d)]
    assert [conv.out_channels for conv in convs] == [depth, 2 * depth, 4 * depth, 8 * depth]
    assert all(conv.kernel_size == (4, 4) and conv.stride == (2, 2) for conv in convs)


def test_decoder_maps_features_back_to_64x64(tiny: Config) -> None:
    depth = tiny.world_model.cnn_depth
    decoder = ConvDecoder(feat_size=17, channels=3, depth=depth)
    assert decoder(torch.randn(2, 5, 17)).shape == (2, 5, 3, 64, 64)
    convs = [layer for layer in decoder.net if isinstance(layer, nn.ConvTranspose2d)]
    assert [conv.out_channels for conv in convs] == [4 * depth, 2 * depth, depth, 3]
    assert [conv.kernel_size[0] for conv in convs] == [5, 5, 6, 6]
    assert decoder.linear.out_features == 32 * depth
    grayscale = ConvDecoder(feat_size=17, channels=1, depth=4)
    assert grayscale(torch.randn(4, 17)).shape == (4, 1, 64, 64)


def test_decoder_is_its_linear_layer_then_the_transposed_convolutions(tiny: Config) -> None:
    """The decoder is nothing but ``nn.Linear`` to ``32 depth`` channels at 1 x 1 and its ``nn.Sequential``."""
    depth = tiny.world_model.cnn_depth
    decoder = ConvDecoder(feat_size=17, channels=3, depth=depth)
    feat = torch.randn(2, 3, 17)
    plain = decoder.net(decoder.linear(feat.reshape(6, 17)).reshape(6, 32 * depth, 1, 1)).reshape(2, 3, 3, 64, 64)
    torch.testing.assert_close(decoder(feat), plain)


def test_conv_stacks_honour_act_norm_and_kernels() -> None:
    """``act`` is the activation after every hidden conv, ``norm='layer'`` puts a :class:`ChannelNorm` between each
    hidden conv and its activation (never after the decoder's output layer), and ``kernels`` sets the layers."""
    encoder = ConvEncoder(channels=3, depth=4, act="silu", norm="layer")
    assert [type(m) for m in encoder.net] == [nn.Conv2d, ChannelNorm, nn.SiLU] * 4
    assert [m.normalized_shape for m in encoder.net if isinstance(m, ChannelNorm)] == [(4,), (8,), (16,), (32,)]
    assert encoder(torch.rand(2, 3, 64, 64)).shape == (2, encoder.embed_size)
    decoder = ConvDecoder(feat_size=9, channels=3, depth=4, act="silu", norm="layer")
    assert [type(m) for m in decoder.net] == [nn.ConvTranspose2d, ChannelNorm, nn.SiLU] * 3 + [nn.ConvTranspose2d]
    assert [m.normalized_shape for m in decoder.net if isinstance(m, ChannelNorm)] == [(16,), (8,), (4,)]
    assert decoder(torch.randn(2, 9)).shape == (2, 3, 64, 64)
    plain_enc, plain_dec = ConvEncoder(channels=3, depth=4), ConvDecoder(feat_size=9, channels=3, depth=4)
    assert [type(m) for m in plain_enc.net] == [nn.Conv2d, nn.ELU] * 4
    assert [type(m) for m in plain_dec.net] == [nn.ConvTranspose2d, nn.ELU] * 3 + [nn.ConvTranspose2d]
    # Five kernel-3 convs of stride 2: 64 -> 31 -> 15 -> 7 -> 3 -> 1 pixels, 16 depth channels.
    deeper = ConvEncoder(channels=3, depth=4, kernels=(3, 3, 3, 3, 3))
    assert deeper.embed_size == 16 * 4 * 1 * 1
    assert deeper(torch.rand(2, 3, 64, 64)).shape == (2, 64)
    assert [m.kernel_size for m in deeper.net if isinstance(m, nn.Conv2d)] == [(3, 3)] * 5
    # Decoder kernels set its layers: six of kernel 2 double 1 x 1 six times to 64 x 64 (channels halving to depth).
    six = ConvDecoder(feat_size=9, channels=3, depth=4, kernels=(2,) * 6)
    convs = [m for m in six.net if isinstance(m, nn.ConvTranspose2d)]
    assert [conv.kernel_size for conv in convs] == [(2, 2)] * 6
    assert [conv.out_channels for conv in convs] == [64, 32, 16, 8, 4, 3]
    assert six(torch.randn(2, 9)).shape == (2, 3, 64, 64)
    # Kernels that do not end at 64 x 64 are refused: 1 -> 4 -> 10 -> 22 -> 46, and 1 -> 6 -> 16 -> 36 -> 76.
    for kernels, side in (((4, 4, 4, 4), 46), ((6, 6, 6, 6), 76)):
        with pytest.raises(ConfigError, match=f"make {side} x {side} images, not 64 x 64"):
            ConvDecoder(feat_size=9, channels=3, depth=4, kernels=kernels)


def test_make_act_and_make_norm_name_their_layers() -> None:
    assert isinstance(make_act("elu"), nn.ELU) and isinstance(make_act("silu"), nn.SiLU)
    with pytest.raises(ConfigError, match="unknown activation 'swish'"):
        make_act("swish")
    assert make_norm("none", 8) == []
    (norm,) = make_norm("layer", 8)
    assert type(norm) is nn.LayerNorm and norm.eps == 1e-3
    (channel_norm,) = make_norm("layer", 8, channels=True)
    assert type(channel_norm) is ChannelNorm
    with pytest.raises(ConfigError, match="unknown norm 'batch'"):
        make_norm("batch", 8)


def test_channel_norm_normalises_each_pixel_over_its_channels() -> None:
    x = torch.randn(2, 6, 5, 7) * 3 + 1
    norm = ChannelNorm(6, eps=1e-3)
    with torch.no_grad():
        norm.weight.copy_(torch.randn(6))
        norm.bias.copy_(torch.randn(6))
    want = nn.functional.layer_norm(x.permute(0, 2, 3, 1), (6,), norm.weight, norm.bias, 1e-3).permute(0, 3, 1, 2)
    torch.testing.assert_close(norm(x), want)


def test_mlp_shape_and_depth() -> None:
    mlp = MLP(in_size=7, out_size=2, units=16, layers=3)
    assert mlp(torch.randn(4, 6, 7)).shape == (4, 6, 2)
    assert sum(isinstance(m, nn.Linear) for m in mlp.modules()) == 4


def test_mlp_norm_centres_and_scales_each_hidden_layer() -> None:
    mlp = MLP(in_size=7, out_size=2, units=16, layers=2, norm="layer", act="silu")
    hidden = mlp.net[:-1]
    assert [type(m) for m in hidden] == [nn.Linear, nn.LayerNorm, nn.SiLU] * 2
    # Inputs that share a large common part: after the first Linear + LayerNorm, each row has mean 0, std 1.
    x = torch.randn(32, 7) * 0.01 + 5.0
    normed = hidden[1](hidden[0](x))
    torch.testing.assert_close(normed.mean(-1), torch.zeros(32), atol=1e-5, rtol=0)
    torch.testing.assert_close(normed.std(-1, unbiased=False), torch.ones(32), atol=2e-2, rtol=0)
    plain = MLP(in_size=7, out_size=2, units=16, layers=2)
    assert not any(isinstance(m, nn.LayerNorm | nn.SiLU) for m in plain.modules())
    assert any(isinstance(m, nn.ELU) for m in plain.modules())
    with pytest.raises(ConfigError, match="unknown activation 'swish'"):
        MLP(in_size=7, out_size=2, units=16, layers=2, act="swish")


def test_mlp_zero_output_starts_at_zero() -> None:
    mlp = MLP(in_size=7, out_size=3, units=16, layers=2)
    mlp.zero_output()
    assert torch.equal(mlp(torch.randn(5, 7)), torch.zeros(5, 3))


def test_gru_cell_shape_and_convex_update() -> None:
    cell = LayerNormGRUCell(in_size=5, size=8)
    h = torch.randn(3, 8)
    out = cell(torch.randn(3, 5), h)
    assert out.shape == (3, 8)
    # h' = u * c + (1 - u) * h with c in (-1, 1): each entry lies between h and a value in (-1, 1).
    assert torch.all(out <= torch.maximum(h, torch.ones_like(h)) + 1e-6)
    assert torch.all(out >= torch.minimum(h, -torch.ones_like(h)) - 1e-6)


def test_gru_cell_bias_and_epsilon() -> None:
    """DreamerV2's cell (the default) has an input bias and LayerNorm epsilon 1e-3; both are arguments, and the
    cell computes its docstring's formula with them."""
    cell = LayerNormGRUCell(in_size=5, size=8, bias=True, eps=1e-3)
    assert cell.linear.bias is not None and cell.linear.bias.shape == (24,)
    assert "linear.bias" in dict(cell.named_parameters())
    assert cell.norm.eps == 1e-3
    default = LayerNormGRUCell(in_size=5, size=8)
    assert default.linear.bias is not None and default.norm.eps == 1e-3
    plain = LayerNormGRUCell(in_size=5, size=8, bias=False, eps=1e-5)
    assert plain.linear.bias is None and plain.norm.eps == 1e-5
    assert "linear.bias" not in dict(plain.named_parameters())
    with torch.no_grad():
        cell.linear.bias.copy_(torch.randn(24))
    x, h = torch.randn(3, 5), torch.randn(3, 8)
    pre = torch.cat([x, h], -1) @ cell.linear.weight.t() + cell.linear.bias
    parts = nn.functional.layer_norm(pre, (24,), cell.norm.weight, cell.norm.bias, 1e-3)
    reset, cand, update = parts.split(8, -1)
    cand = torch.tanh(torch.sigmoid(reset) * cand)
    update = torch.sigmoid(update - 1.0)
    torch.testing.assert_close(cell(x, h), update * cand + (1 - update) * h)


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
