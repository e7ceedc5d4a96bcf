"""Shapes and small behaviours of the DreamerV2 building blocks on the tiny preset."""

from __future__ import annotations

import pytest
import torch

from coworld.config import Config
from coworld.errors import CoworldError
from coworld.models import autotune, networks
from coworld.models.networks import (
    ELU,
    MLP,
    ConvDecoder,
    ConvEncoder,
    LayerNormGRUCell,
    Linear,
    check_image_shape,
    conv2d,
    conv2d_stride2,
    conv_transpose_stride2,
    depth_to_space,
    frozen_parameters,
    linear,
    space_to_depth,
    stride2_phases4,
    tanh_,
)
from coworld.models.world_model import preprocess_image, preprocess_phases


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
    assert [type(m) for m in hidden] == [Linear, torch.nn.LayerNorm, torch.nn.SiLU] * 2
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


# Channels and dtypes whose runs move as 2-, 8- and 4-byte words, and as the elements themselves.
@pytest.mark.parametrize(
    ("channels", "dtype"), [(3, torch.uint8), (12, torch.uint8), (1, torch.float32), (3, torch.int64)]
)
def test_space_to_depth_puts_each_2x2_phase_in_channels_and_depth_to_space_undoes_it(
    channels: int, dtype: torch.dtype
) -> None:
    image = torch.randint(0, 256, (2, 3, 6, 4, channels)).to(dtype)
    phases = space_to_depth(image)
    assert phases.shape == (2, 3, 3, 2, 4 * channels) and phases.dtype == dtype
    for p in range(2):
        for s in range(2):
            first = (2 * p + s) * channels
            assert torch.equal(phases[..., first : first + channels], image[..., p::2, s::2, :])
    flat = phases.reshape(6, 3, 2, 4 * channels).permute(0, 3, 1, 2)  # channels first
    assert torch.equal(depth_to_space(flat).permute(0, 2, 3, 1), image.reshape(6, 6, 4, channels))
    # A view that starts off a word boundary is rearranged the same.
    offset = torch.randint(0, 256, (1 + image.numel(),)).to(dtype)[1:].view(image.shape)
    assert offset.storage_offset() == 1
    assert torch.equal(space_to_depth(offset), space_to_depth(offset.clone()))
    if channels != 3 or dtype != torch.uint8:
        return
    # The world model's two preprocessings hold the same numbers.
    expected = space_to_depth(preprocess_image(image).movedim(-3, -1)).movedim(-1, -3)
    assert torch.equal(preprocess_phases(image), expected)


def test_encoder_from_phases_matches_the_image_path(tiny: Config) -> None:
    torch.manual_seed(0)
    depth = tiny.world_model.cnn_depth
    encoder = ConvEncoder(channels=3, depth=depth).double()
    image = torch.randint(0, 256, (2, 3, 64, 64, 3), dtype=torch.uint8)
    phases = preprocess_phases(image).double().requires_grad_()
    plain = preprocess_image(image).double().requires_grad_()
    grad = torch.randn(2, 3, encoder.embed_size, dtype=torch.float64)
    got, want = encoder.from_phases(phases), encoder(plain)
    torch.testing.assert_close(got, want)
    params = list(encoder.parameters())
    got_grads = torch.autograd.grad(got, [phases, *params], grad)
    want_grads = torch.autograd.grad(want, [plain, *params], grad)
    torch.testing.assert_close(got_grads[0], space_to_depth(want_grads[0].movedim(-3, -1)).movedim(-1, -3))
    for a, b in zip(got_grads[1:], want_grads[1:], strict=True):
        torch.testing.assert_close(a, b)
    # The uint8 pixels' phases: the first layer scales them in its weights and bias; same value and weight gradients.
    raw = encoder.from_phases(space_to_depth(image).movedim(-1, -3))
    exact = encoder(image.movedim(-1, -3).double() / 255.0 - 0.5)  # scaled in float64, as the raw path is
    torch.testing.assert_close(raw, exact)
    for a, b in zip(torch.autograd.grad(raw, params, grad), torch.autograd.grad(exact, params, grad), strict=True):
        torch.testing.assert_close(a, b)
    # The pixels' values as float (a prepared batch on a CPU) give the uint8 path's numbers exactly; without
    # `pixels` the same floats would be read as already scaled.
    values = space_to_depth(image).movedim(-1, -3).double()
    assert torch.equal(encoder.from_phases(values, pixels=True), raw)
    assert not torch.allclose(encoder.from_phases(values), raw)


# The tiny preset's depth decodes to 4 x 4 phases, a wider decoder to 2 x 2 phases; on 6 feature vectors the linear
# layer runs apart from the first transposed convolution, on 24 (at depth 8) their weights are multiplied first.
@pytest.mark.parametrize(
    ("depth", "levels", "steps", "folded"), [(8, 2, 3, False), (8, 2, 12, True), (16, 1, 3, False)]
)
def test_decoder_phases_match_the_plain_layers(depth: int, levels: int, steps: int, folded: bool) -> None:
    torch.manual_seed(0)
    decoder = ConvDecoder(feat_size=17, channels=3, depth=depth).double()
    assert decoder.phase_levels == levels
    rows = 2 * steps
    assert decoder.folds_linear(rows) == folded
    feat = torch.randn(2, steps, 17, dtype=torch.float64, requires_grad=True)

    def plain() -> torch.Tensor:  # nn.ConvTranspose2d layers one after another
        return decoder.net(decoder.linear(feat).reshape(rows, 32 * depth, 1, 1)).reshape(2, steps, 3, 64, 64)

    torch.testing.assert_close(decoder(feat), plain())
    out = decoder.phases(feat)
    assert out.shape == (2, steps, 3 * 4**levels, 64 // 2**levels, 64 // 2**levels)
    want = plain().movedim(-3, -1)
    for _ in range(levels):
        want = space_to_depth(want)
    torch.testing.assert_close(out, want.movedim(-1, -3))
    grad = torch.randn_like(out)
    got_grads = torch.autograd.grad(out, [feat, *decoder.parameters()], grad)
    plain_grad = grad.reshape(rows, *out.shape[2:])
    for _ in range(levels):
        plain_grad = depth_to_space(plain_grad)
    want_grads = torch.autograd.grad(plain(), [feat, *decoder.parameters()], plain_grad.reshape(2, steps, 3, 64, 64))
    for a, b in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(a, b)
    # An offset rides on the last layer's bias: the same phases plus the offset, the same gradients.
    shifted = decoder.phases(feat, offset=0.5)
    torch.testing.assert_close(shifted, out + 0.5)
    for a, b in zip(torch.autograd.grad(shifted, [feat, *decoder.parameters()], grad), got_grads, strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize(("rows", "cols", "bias"), [(15, 15, True), (4, 7, False), (1, 2, True)])
def test_stride2_phases4_is_the_transposed_convolution_from_phases_to_phases(rows: int, cols: int, bias: bool) -> None:
    x = torch.randn(2, 3, 2 * rows, 2 * cols, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(3, 5, 6, 6, dtype=torch.float64, requires_grad=True)
    b = torch.randn(5, dtype=torch.float64, requires_grad=True) if bias else None
    inputs = [x, weight] + ([b] if bias else [])
    phases = x.reshape(2, 3, rows, 2, cols, 2).permute(0, 3, 5, 1, 2, 4).reshape(2, 12, rows, cols)  # (p, s, c)
    got = stride2_phases4(phases.contiguous(memory_format=torch.channels_last), weight, b)
    want = torch.nn.functional.conv_transpose2d(x, weight, b, stride=2)
    assert got.shape == (2, 80, rows + 1, cols + 1) and got.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(got, space_to_depth(space_to_depth(want.movedim(1, -1))).movedim(-1, 1))
    grad = torch.randn_like(got)
    want_grad = depth_to_space(depth_to_space(grad))
    for a, c in zip(torch.autograd.grad(got, inputs, grad), torch.autograd.grad(want, inputs, want_grad), strict=True):
        torch.testing.assert_close(a, c)
    with pytest.raises(ValueError, match="kernel-6"):
        stride2_phases4(phases, weight[..., :5, :5], b)


# Output numbers against the bias gradient's rows (a multiple of the channels, at least 128 numbers): whole rows and
# a remainder, whole rows only, and fewer numbers than one row.
@pytest.mark.parametrize(("channels", "size", "padding"), [(8, 5, 0), (12, 7, 1), (48, 3, 2), (96, 2, 0)])
@pytest.mark.parametrize("layout", [torch.channels_last, torch.contiguous_format])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("form", ["rows", "sum"])
def test_conv2d_is_the_convolution_with_its_gradients(
    channels: int,
    size: int,
    padding: int,
    layout: torch.memory_format,
    dtype: torch.dtype,
    form: str,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """:func:`conv2d` takes the bias gradient apart from PyTorch's backward (on a float32 channels-last gradient
    in either form, as a matrix-vector product or a plain sum): PyTorch's values and gradients, without a bias too."""
    monkeypatch.setattr(autotune, "fastest", lambda key, forms, default: form)
    x = torch.randn(3, 5, size, size, dtype=dtype).contiguous(memory_format=layout).requires_grad_()
    weight = torch.randn(channels, 5, 2, 2, dtype=dtype, requires_grad=True)
    b = torch.randn(channels, dtype=dtype, requires_grad=True)
    tolerance = {"rtol": 1e-5, "atol": 1e-4} if dtype == torch.float32 else {}
    for bias in (b, None):
        inputs = [x, weight] + ([b] if bias is not None else [])
        got, want = (
            conv2d(x, weight, bias, padding=padding),
            torch.nn.functional.conv2d(x, weight, bias, padding=padding),
        )
        torch.testing.assert_close(got, want)
        assert got.is_contiguous(memory_format=layout)
        grad = torch.randn_like(want)
        got_grads = torch.autograd.grad(got, inputs, grad)
        for a, c in zip(got_grads, torch.autograd.grad(want, inputs, grad), strict=True):
            torch.testing.assert_close(a, c, **tolerance)


@pytest.mark.parametrize("form", ["matmul", "onednn"])
@pytest.mark.parametrize(("shape", "chooses"), [((6, 16, 7), True), ((96, 7), True), ((67, 7), False)])
def test_linear_is_f_linear_with_its_gradients(
    form: str, shape: tuple[int, ...], chooses: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """:func:`linear` in either form (the matrix product, or oneDNN's 1 x 1 convolution of the rows as pixels) is
    ``F.linear``, gradients included, with a bias and without; rows that no 16 to 64 divide (67) take ``F.linear``
    and time no form."""
    keys: list[object] = []

    def fastest(key: object, forms: object, default: str) -> str:
        keys.append(key)
        return form

    monkeypatch.setattr(autotune, "fastest", fastest)
    monkeypatch.setattr(networks, "_LINEAR_MIN_ROWS", 32)
    x = torch.randn(*shape, requires_grad=True)
    weight = torch.randn(5, 7, requires_grad=True)
    b = torch.randn(5, requires_grad=True)
    for bias in (b, None):
        inputs = [x, weight] + ([b] if bias is not None else [])
        got, want = linear(x, weight, bias), torch.nn.functional.linear(x, weight, bias)
        torch.testing.assert_close(got, want)
        grad = torch.randn_like(want)
        for a, c in zip(torch.autograd.grad(got, inputs, grad), torch.autograd.grad(want, inputs, grad), strict=True):
            torch.testing.assert_close(a, c)
    rows = x.numel() // 7
    assert keys == ([("linear", (rows, 7), 5), ("linear input grad", (rows, 5), 7)] * 2 if chooses else [])


def test_linear_module_is_nn_linear() -> None:
    """:class:`Linear` keeps ``nn.Linear``'s parameters and state-dict keys, so checkpoints load either way."""
    plain = torch.nn.Linear(7, 5)
    ours = Linear(7, 5)
    ours.load_state_dict(plain.state_dict())
    x = torch.randn(3, 7)
    torch.testing.assert_close(ours(x), plain(x))
    assert isinstance(ours, torch.nn.Linear)


@pytest.mark.parametrize(("c_out", "size"), [(16, 5), (12, 3)])
@pytest.mark.parametrize("form", ["rows", "sum"])
def test_conv_transpose_stride2_bias_gradient_in_float32(
    c_out: int, size: int, form: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The transposed convolution's bias gradient, summed apart (as a matrix-vector product or a plain sum) on a
    float32 channels-last gradient, is PyTorch's."""
    monkeypatch.setattr(autotune, "fastest", lambda key, forms, default: form)
    x = torch.randn(4, 6, size, size).contiguous(memory_format=torch.channels_last).requires_grad_()
    weight = torch.randn(6, c_out, 5, 5, requires_grad=True)
    bias = torch.randn(c_out, requires_grad=True)
    got, want = conv_transpose_stride2(x, weight, bias), torch.nn.functional.conv_transpose2d(x, weight, bias, stride=2)
    grad = torch.randn_like(got)
    assert grad.is_contiguous(memory_format=torch.channels_last)
    got_grads = torch.autograd.grad(got, [x, weight, bias], grad)
    want_grads = torch.autograd.grad(want, [x, weight, bias], grad.contiguous())
    for a, c in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize(("size", "bias"), [(31, True), (14, True), (6, False), (9, True), (5, False)])
def test_conv2d_stride2_is_the_strided_convolution_with_its_gradients(size: int, bias: bool) -> None:
    x = torch.randn(2, 3, size, size + 1, dtype=torch.float64).contiguous(memory_format=torch.channels_last)
    x.requires_grad_()
    weight = torch.randn(5, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    b = torch.randn(5, dtype=torch.float64, requires_grad=True) if bias else None
    inputs = [x, weight] + ([b] if bias else [])
    got, want = conv2d_stride2(x, weight, b), torch.nn.functional.conv2d(x, weight, b, stride=2)
    torch.testing.assert_close(got, want)
    grad = torch.randn_like(want)
    for a, c in zip(torch.autograd.grad(got, inputs, grad), torch.autograd.grad(want, inputs, grad), strict=True):
        torch.testing.assert_close(a, c)


@pytest.mark.parametrize("inplace", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(3, 4, 5, 6), (9, 8, 32, 32), (1100, 64), (20, 64), (70000,)])
def test_elu_is_the_elu_with_its_gradient(dtype: torch.dtype, shape: tuple[int, ...], inplace: bool) -> None:
    """Below and above the size where :class:`ELU` leaves ``F.elu`` for its function that keeps the output (and
    on a float32 CPU tensor takes NumPy's forward, over more than one block at 70000 numbers): PyTorch's values and
    gradient, the input's memory order (channels last for a conv's) kept. In place, the gradient reaching the
    layer before is the same."""
    x = torch.randn(*shape, dtype=dtype) * 3
    if x.ndim == 4:
        x = x.contiguous(memory_format=torch.channels_last)
    x.requires_grad_()
    layer_out = x * 1.0  # a fresh output of a layer before, which an in-place ELU may overwrite
    got, want = ELU(inplace=inplace)(layer_out), torch.nn.functional.elu(x)
    torch.testing.assert_close(got, want)
    assert got.stride() == want.stride()
    if x.ndim == 4:
        assert got.is_contiguous(memory_format=torch.channels_last)
    grad = torch.randn_like(want)
    got_grad, want_grad = torch.autograd.grad(got, x, grad)[0], torch.autograd.grad(want, x, grad)[0]
    torch.testing.assert_close(got_grad, want_grad)


def test_elu_in_place_overwrites_only_a_new_float32_cpu_output() -> None:
    """``ELU(inplace=True)`` on a large float32 output writes into it (its forward is NumPy's there, on one torch
    thread); on a view, another dtype, a leaf that requires grad, a small tensor, with a plain ``ELU`` or on two
    threads its input is left as it was."""
    x = torch.randn(1100, 64)
    y = ELU(inplace=True)(x)
    assert y.data_ptr() == x.data_ptr()
    torch.testing.assert_close(x, y)
    for layer, inp in [
        (ELU(inplace=True), torch.randn(2200, 64)[::2]),  # a view, strided
        (ELU(inplace=True), torch.randn(2, 1100, 64).reshape(2200, 64)),  # a contiguous view
        (ELU(inplace=True), torch.randn(1100, 64, dtype=torch.float64)),
        (ELU(inplace=True), torch.randn(1100, 64, requires_grad=True)),  # a leaf that requires grad
        (ELU(inplace=True), torch.randn(100, 64)),  # below the size of the function that keeps the output
        (ELU(), torch.randn(1100, 64)),
    ]:
        before = inp.clone()
        out = layer(inp)
        assert torch.equal(inp, before)
        torch.testing.assert_close(out, torch.nn.functional.elu(before))
    threads = torch.get_num_threads()
    torch.set_num_threads(2)  # PyTorch's ELU, on both threads
    try:
        before = x.clone()
        torch.testing.assert_close(ELU(inplace=True)(x), torch.nn.functional.elu(before))
        assert torch.equal(x, before)
    finally:
        torch.set_num_threads(threads)


def test_elu_numpy_forward_keeps_the_special_values() -> None:
    """The NumPy forward at the edges: infinities, NaN, signed zeros, values past ``expm1``'s float32 range and
    next to zero, and a memory order that is neither contiguous nor channels last (PyTorch's then)."""
    special = torch.tensor([float("inf"), -float("inf"), float("nan"), 0.0, -0.0, 100.0, -100.0, 1e-30, -1e-30])
    x = torch.cat([special, torch.randn(40000) * 4])
    got, want = ELU()(x), torch.nn.functional.elu(x)
    torch.testing.assert_close(got, want, equal_nan=True)
    odd = torch.randn(64, 8, 40, 40).permute(0, 2, 1, 3)  # dense, but neither order
    torch.testing.assert_close(ELU()(odd), torch.nn.functional.elu(odd))


@pytest.mark.parametrize("shape", [(16, 64), (512, 64), (3, 5, 7)])
def test_tanh_in_place_is_torch_tanh(shape: tuple[int, ...]) -> None:
    """``tanh_`` (NumPy's on one thread) overwrites its input with ``torch.tanh``'s values, to a float rounding;
    a strided view takes PyTorch's own, in place too."""
    x = 4.0 * torch.randn(shape)
    want = torch.tanh(x)
    got = x.clone()
    assert tanh_(got) is got
    torch.testing.assert_close(got, want, rtol=0, atol=2e-7)
    wide = 4.0 * torch.randn(*shape[:-1], 2 * shape[-1])
    view = wide[..., ::2]
    want = torch.tanh(view)
    assert tanh_(view) is view
    torch.testing.assert_close(wide[..., ::2], want, rtol=0, atol=2e-7)
