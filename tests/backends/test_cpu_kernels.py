"""The CPU fast path's kernels (coworld/backends/cpu_kernels.py) against the PyTorch operations they replace: values
and every gradient, in float64 where the forms differ only by summation order, and the decoder run to its output's
phases (:func:`coworld.backends.cpu.decode_phases`) against :class:`ConvDecoder`'s own forward."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch
import torch.nn.functional as F

from coworld.backends import cpu
from coworld.backends.cpu_kernels import (
    conv_transpose_stride2,
    depth_to_space,
    half_squared_error,
    space_to_depth,
    stride2_phases,
    stride2_phases4,
)
from coworld.models.networks import ConvDecoder


@pytest.fixture(autouse=True)
def _seeded() -> None:
    torch.manual_seed(0)


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


@pytest.mark.parametrize(("kernel", "bias"), [(5, True), (6, True), (4, False), (3, True)])
def test_stride2_phases_are_the_transposed_convolutions_phases(kernel: int, bias: bool) -> None:
    """Interleaved by :func:`depth_to_space` and cropped, the four phases are ``F.conv_transpose2d``'s output (an
    odd kernel pads its taps to an even one, so the phases run one pixel past the output)."""
    x = torch.randn(2, 4, 5, 7, dtype=torch.float64)
    weight = torch.randn(4, 3, kernel, kernel, dtype=torch.float64)
    b = torch.randn(3, dtype=torch.float64) if bias else None
    want = F.conv_transpose2d(x, weight, b, stride=2)
    m = (kernel + 1) // 2
    phases = stride2_phases(x, weight, b)
    assert phases.shape == (2, 12, 5 + m - 1, 7 + m - 1)
    torch.testing.assert_close(depth_to_space(phases)[..., : want.shape[-2], : want.shape[-1]], want)


@pytest.mark.parametrize(
    ("c_in", "c_out", "kernel", "height", "width"), [(5, 4, 5, 1, 1), (4, 3, 5, 5, 7), (3, 2, 6, 4, 3)]
)
@pytest.mark.parametrize("bias", [True, False])
def test_conv_transpose_stride2_is_the_transposed_convolution(
    c_in: int, c_out: int, kernel: int, height: int, width: int, bias: bool
) -> None:
    """Values and the input, weight and bias gradients, from either memory layout (a 1 x 1 input is one matrix
    product)."""
    x = torch.randn(2, c_in, height, width, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(c_in, c_out, kernel, kernel, dtype=torch.float64, requires_grad=True)
    b = torch.randn(c_out, dtype=torch.float64, requires_grad=True) if bias else None
    inputs = [x, weight] + ([b] if bias else [])
    expected = F.conv_transpose2d(x, weight, b, stride=2)
    for layout in (torch.contiguous_format, torch.channels_last):
        out = conv_transpose_stride2(x.contiguous(memory_format=layout), weight, b)
        torch.testing.assert_close(out, expected)
        grad = torch.randn_like(expected)
        got = torch.autograd.grad(out, inputs, grad)
        want = torch.autograd.grad(expected, inputs, grad, retain_graph=True)
        for a, c in zip(got, want, strict=True):
            torch.testing.assert_close(a, c)


@pytest.mark.parametrize(("c_out", "size"), [(16, 5), (12, 3)])
def test_conv_transpose_stride2_gradients_in_float32_channels_last(c_out: int, size: int) -> None:
    """In float32 on a channels-last gradient (as the decoder runs): PyTorch's gradients, the bias's summed apart."""
    x = torch.randn(4, 6, size, size).contiguous(memory_format=torch.channels_last).requires_grad_()
    weight = torch.randn(6, c_out, 5, 5, requires_grad=True)
    bias = torch.randn(c_out, requires_grad=True)
    got, want = conv_transpose_stride2(x, weight, bias), F.conv_transpose2d(x, weight, bias, stride=2)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-4)
    grad = torch.randn_like(got)
    assert grad.is_contiguous(memory_format=torch.channels_last)
    got_grads = torch.autograd.grad(got, [x, weight, bias], grad)
    want_grads = torch.autograd.grad(want, [x, weight, bias], grad.contiguous())
    for a, c in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(a, c, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize(("rows", "cols", "bias"), [(15, 15, True), (4, 7, False), (1, 2, True)])
def test_stride2_phases4_is_the_transposed_convolution_from_phases_to_phases(rows: int, cols: int, bias: bool) -> None:
    x = torch.randn(2, 3, 2 * rows, 2 * cols, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(3, 5, 6, 6, dtype=torch.float64, requires_grad=True)
    b = torch.randn(5, dtype=torch.float64, requires_grad=True) if bias else None
    inputs = [x, weight] + ([b] if bias else [])
    phases = x.reshape(2, 3, rows, 2, cols, 2).permute(0, 3, 5, 1, 2, 4).reshape(2, 12, rows, cols)  # (p, s, c)
    got = stride2_phases4(phases.contiguous(memory_format=torch.channels_last), weight, b)
    want = F.conv_transpose2d(x, weight, b, stride=2)
    assert got.shape == (2, 80, rows + 1, cols + 1) and got.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(got, space_to_depth(space_to_depth(want.movedim(1, -1))).movedim(-1, 1))
    grad = torch.randn_like(got)
    want_grad = depth_to_space(depth_to_space(grad))
    for a, c in zip(torch.autograd.grad(got, inputs, grad), torch.autograd.grad(want, inputs, want_grad), strict=True):
        torch.testing.assert_close(a, c)
    with pytest.raises(ValueError, match="kernel-6"):
        stride2_phases4(phases, weight[..., :5, :5], b)


# The tiny preset's depth decodes to 4 x 4 phases, a wider decoder to 2 x 2 phases; on 6 feature vectors the linear
# layer runs apart from the first transposed convolution, on 24 (at depth 8) their weights are multiplied first.
@pytest.mark.parametrize(
    ("depth", "levels", "steps", "folded"), [(8, 2, 3, False), (8, 2, 12, True), (16, 1, 3, False)]
)
@pytest.mark.parametrize("act", ["elu", "silu"])
def test_decode_phases_is_the_decoders_forward_as_phases(
    depth: int, levels: int, steps: int, folded: bool, act: str, fast_path: Callable[..., object]
) -> None:
    """:func:`~coworld.backends.cpu.decode_phases` equals :meth:`ConvDecoder.forward` taken to its phases by
    :func:`space_to_depth`, with the decoder's own activation; every gradient equals the forward's of the
    interleaved output gradient; an offset rides on the last layer's bias. (A decoder the fast path no longer
    serves is another decoder: skipped.)"""
    fast_path()
    decoder = ConvDecoder(feat_size=17, channels=3, depth=depth, act=act).double()
    with torch.no_grad():  # biases off their zero initialisation, so each one's path counts
        for param in decoder.parameters():
            param.add_(0.1 * torch.randn_like(param))
    rows = 2 * steps
    assert cpu._folds_linear(decoder, rows) == folded
    assert (2 if depth < cpu.PHASES4_BELOW_DEPTH else 1) == levels
    feat = torch.randn(2, steps, 17, dtype=torch.float64, requires_grad=True)
    params = [feat, *decoder.parameters()]
    out = cpu.decode_phases(decoder, feat, levels)
    assert out.shape == (2, steps, 3 * 4**levels, 64 // 2**levels, 64 // 2**levels)
    plain = decoder(feat)
    want = plain.movedim(-3, -1)
    for _ in range(levels):
        want = space_to_depth(want)
    torch.testing.assert_close(out, want.movedim(-1, -3))
    grad = torch.randn_like(out)
    got_grads = torch.autograd.grad(out, params, grad)
    plain_grad = grad.reshape(rows, *out.shape[2:])
    for _ in range(levels):
        plain_grad = depth_to_space(plain_grad)
    want_grads = torch.autograd.grad(plain, params, plain_grad.reshape(2, steps, 3, 64, 64))
    for a, b in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(a, b)
    shifted = cpu.decode_phases(decoder, feat, levels, offset=0.5)
    torch.testing.assert_close(shifted, out + 0.5)
    for a, b in zip(torch.autograd.grad(shifted, params, grad), got_grads, strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize(("scale", "shift"), [(1.0 / 255.0, -0.5), (1.0 / 255.0, 0.0), (2.0, 0.25)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_half_squared_error_against_uint8_targets(scale: float, shift: float, dtype: torch.dtype) -> None:
    """``half_squared_error(pred, t, scale, shift)`` is ``0.5 * sum((pred - (scale t + shift))^2)`` over the last
    three dimensions, with its gradient; its backward reuses the saved difference, so a second backward fails
    rather than run on it."""
    pred = torch.randn(2, 3, 3, 8, 8, dtype=dtype, requires_grad=True)
    target = torch.randint(0, 256, (2, 3, 3, 8, 8), dtype=torch.uint8)
    got = half_squared_error(pred, target, scale, shift)
    want = 0.5 * ((pred - (scale * target.to(dtype) + shift)) ** 2).sum((-3, -2, -1))
    assert got.shape == (2, 3) and got.dtype == dtype
    tolerance = {"rtol": 1e-5, "atol": 1e-3} if dtype == torch.float32 else {}
    torch.testing.assert_close(got, want, **tolerance)
    weight = torch.randn(2, 3, dtype=dtype)
    (got_grad,) = torch.autograd.grad((got * weight).sum(), pred, retain_graph=True)
    (want_grad,) = torch.autograd.grad((want * weight).sum(), pred)
    torch.testing.assert_close(got_grad, want_grad, **tolerance)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        torch.autograd.grad((got * weight).sum(), pred)
