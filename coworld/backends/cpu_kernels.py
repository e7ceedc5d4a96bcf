"""The CPU fast path's kernels: the same functions as PyTorch's own operations (to float rounding, gradients
included), in forms that run faster on a CPU at DreamerV2's sizes. Nothing here knows the model; each function is
tested against the PyTorch operation it replaces (tests/backends/test_cpu_kernels.py).

* images as their 2 x 2 phases (:func:`space_to_depth`): a stride-2 transposed convolution is one ordinary
  convolution to its output's phases (:func:`stride2_phases`, :func:`stride2_phases4`) and an interleave
  (:func:`depth_to_space`, :func:`conv_transpose_stride2`), where PyTorch's CPU transposed convolution scatters
  columns;
* half the squared error over an image's pixels against uint8 targets (:func:`half_squared_error`).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "conv_transpose_stride2",
    "depth_to_space",
    "half_squared_error",
    "space_to_depth",
    "stride2_phases",
    "stride2_phases4",
]


def space_to_depth(x: Tensor) -> Tensor:
    """The 2 x 2 phases of a channels-last image as channels: ``(..., H, W, C)`` -> ``(..., H / 2, W / 2, 4 C)``.

    Output channel ``(p, s, c)`` (``p, s`` in ``{0, 1}``, ``c`` fastest) at ``(q, r)`` is channel ``c`` of pixel
    ``(2q + p, 2r + s)``; any dtype; ``H`` and ``W`` even. A stride-2 convolution with an even kernel ``K`` of the
    image is a stride-1 convolution with kernel ``K / 2`` of its phases, and :func:`conv_transpose_stride2`'s
    phases come out in this order. Two strided copies, each of whole ``2 C``-element runs.
    """
    *batch, height, width, channels = x.shape
    rows = x.reshape(-1, height // 2, 2, width // 2, 2 * channels)  # (M, q, p, r, [s, c])
    for word, dtype in ((8, torch.int64), (4, torch.int32), (2, torch.int16)):
        # Each run [s, c] moves as the widest words that tile it (a uint8 image's 6 bytes as three 2-byte words, its
        # phases' 24 as three 8-byte ones), where every row starts on a word.
        ratio = word // x.element_size()
        tiled = (*rows.stride()[:-1], rows.shape[-1], rows.storage_offset())
        if ratio > 1 and rows.stride(-1) == 1 and all(n % ratio == 0 for n in tiled):
            rows = rows.view(dtype)
            break
    out = rows.new_empty(rows.shape[0], height // 2, width // 2, 2, rows.shape[-1])  # (M, q, r, p, [s, c])
    for p in range(2):
        out[:, :, :, p] = rows[:, :, p]
    return out.view(x.dtype).reshape(*batch, height // 2, width // 2, 4 * channels)


def stride2_phases(x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """The four output phases of ``F.conv_transpose2d(x, weight, bias, stride=2)`` as channels, before
    :func:`conv_transpose_stride2` interleaves them.

    With ``M = ceil(K / 2)``, the output pixel ``(2q + p, 2r + s)`` of a stride-2 transposed convolution only
    sees the kernel taps ``(p + 2m, s + 2n)``, ``m, n < M``, applied to the input pixels ``(q - m, r - n)``:
    an ordinary ``M x M`` convolution of the input padded by ``M - 1``, one output channel per phase ``(p, s)``.
    The four phases are stacked as ``4 C_out`` channels of one convolution, in :func:`space_to_depth`'s order
    ``(p, s, c)``. Shapes: ``x (N, C_in, H, W)``, ``weight (C_in, C_out, K, K)`` (``nn.ConvTranspose2d``'s layout),
    ``bias (C_out,)``; returns ``(N, 4 C_out, H + M - 1, W + M - 1)``, channels last when ``x`` is.
    """
    c_in, c_out, kernel, _ = weight.shape
    m = (kernel + 1) // 2
    taps = F.pad(weight, (0, 2 * m - kernel, 0, 2 * m - kernel)).reshape(c_in, c_out, m, 2, m, 2)
    phases = taps.flip(2, 4).permute(3, 5, 1, 0, 2, 4).reshape(4 * c_out, c_in, m, m)
    phase_bias = None if bias is None else bias.repeat(4)
    return F.conv2d(x, phases, phase_bias, padding=m - 1)


def stride2_phases4(phases: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """A kernel-6, stride-2 transposed convolution from its input's 2 x 2 phases to its output's 4 x 4 phases,
    one ordinary convolution: the decoder's last layer, without interleaving the layer before it or its own output.

    Output pixel ``4a + r`` (``r < 4``) of the transposed convolution sees input pixel ``2b + q`` (``q < 2``) through
    kernel tap ``4 (a - b) + r - 2q``, a tap only for ``b = a - 1`` and ``b = a``: a 2 x 2 convolution (padding 1) of
    the phases, whose weight holds each tap where an ``(r, q)`` pair uses it and zeros elsewhere (9 of 16 entries:
    1.8x the multiply-adds, which pay only where the narrow layer is slow as an ordinary convolution; see
    :data:`coworld.backends.cpu.PHASES4_BELOW_DEPTH`).

    Shapes: ``phases (N, 4 C_in, H, W)`` in :func:`space_to_depth`'s channel order, as :func:`stride2_phases` makes
    them, ``weight (C_in, C_out, 6, 6)`` (``nn.ConvTranspose2d``'s layout), ``bias (C_out,)``; returns
    ``(N, 16 C_out, H + 1, W + 1)``: the output's :func:`space_to_depth` applied twice, channels ``(p2, s2, p1, s1,
    c)`` for pixel ``(4a + 2 p2 + p1, 4b + 2 s2 + s1)``, channels last when ``phases`` is.
    """
    c_in, c_out, kernel, _ = weight.shape
    if kernel != 6 or phases.shape[-3] != 4 * c_in:
        raise ValueError(
            f"stride2_phases4 takes a kernel-6 weight and 4 x {c_in} phase channels, got {kernel} and "
            f"{phases.shape[-3]}"
        )
    taps = _phase4_taps(weight.device)  # (p2, p1, q, t): index 6 is the zero appended below
    padded = F.pad(weight, (0, 1, 0, 1))
    w = padded[:, :, taps.view(2, 1, 2, 1, 2, 1, 2, 1), taps.view(1, 2, 1, 2, 1, 2, 1, 2)]
    # (c_in, c_out, p2, s2, p1, s1, q_row, q_col, t_row, t_col) -> (out (p2, s2, p1, s1, c_out), in (q, q, c_in), t, t)
    w = w.permute(2, 3, 4, 5, 1, 6, 7, 0, 8, 9).reshape(16 * c_out, 4 * c_in, 2, 2)
    return F.conv2d(phases, w, None if bias is None else bias.repeat(16), padding=1)


_PHASE4_TAPS: dict[torch.device, Tensor] = {}


def _phase4_taps(device: torch.device) -> Tensor:
    """Kernel tap (or 6, none) linking output phase ``r = 2 p2 + p1`` to input phase ``q`` at offset ``t`` (input
    position ``a - 1 + t``) in :func:`stride2_phases4`, ``(2, 2, 2, 2)`` indexed ``(p2, p1, q, t)``."""
    if device not in _PHASE4_TAPS:
        taps = torch.full((4, 2, 2), 6, dtype=torch.long)
        for r in range(4):
            for q in range(2):
                for t in range(2):
                    tap = 4 * (1 - t) + r - 2 * q
                    if 0 <= tap < 6:
                        taps[r, q, t] = tap
        _PHASE4_TAPS[device] = taps.view(2, 2, 2, 2).to(device)
    return _PHASE4_TAPS[device]


def depth_to_space(phases: Tensor) -> Tensor:
    """Inverse of :func:`space_to_depth` on a channels-first view: ``(N, 4 C, H, W)`` -> ``(N, C, 2 H, 2 W)``.

    The result is channels last in memory (a plain strided copy, faster than ``pixel_shuffle`` here, when
    ``phases`` is channels last too).
    """
    grid = _pixel_grid(phases)
    n, rows, _, cols, _, channels = grid.shape
    return grid.reshape(n, 2 * rows, 2 * cols, channels).permute(0, 3, 1, 2)


def _pixel_grid(phases: Tensor) -> Tensor:
    """The phases ``(N, 4 C, rows, cols)`` (:func:`space_to_depth`'s order) as a view ``(N, rows, 2, cols, 2, C)``
    indexed ``(q, p, r, s, c)``: pixel ``(2q + p, 2r + s)`` of the interleaved image, to copy into one."""
    n, channels, rows, cols = phases.shape
    return phases.permute(0, 2, 3, 1).reshape(n, rows, cols, 2, 2, channels // 4).transpose(2, 3)


def conv_transpose_stride2(x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """``F.conv_transpose2d(x, weight, bias, stride=2)`` computed as one ordinary convolution and a pixel shuffle.

    :func:`stride2_phases` computes the four output phases in one convolution and :func:`depth_to_space`
    interleaves them (PyTorch's CPU transposed convolution scatters columns instead, several times slower at
    DreamerV2's sizes). A 1 x 1 input (the decoder's first layer) is one matrix product, whose result is channels
    last in memory. The result equals the transposed convolution up to float rounding (summation order), gradients
    included.

    Shapes: ``x (N, C_in, H, W)``, ``weight (C_in, C_out, K, K)`` (``nn.ConvTranspose2d``'s layout),
    ``bias (C_out,)``; returns ``(N, C_out, 2 (H - 1) + K, 2 (W - 1) + K)``.
    """
    c_in, c_out, kernel, _ = weight.shape
    n, _, height, width = x.shape
    if height == 1 and width == 1:  # one matrix product, its output channels last (as the next layer reads it)
        taps = _taps_1x1(weight)
        flat = x.reshape(n, c_in)
        out = flat @ taps if bias is None else torch.addmm(bias.repeat(kernel * kernel), flat, taps)
        return _pixels_1x1(out, weight)
    return _ConvTransposeStride2.apply(x, weight, bias)


def _taps_1x1(weight: Tensor) -> Tensor:
    """A transposed convolution's weight ``(C_in, C_out, K, K)`` as the matrix ``(C_in, K K C_out)`` that maps a 1 x 1
    input to its output's pixels, channels last."""
    c_in, c_out, kernel, _ = weight.shape
    return weight.permute(0, 2, 3, 1).reshape(c_in, kernel * kernel * c_out)


def _pixels_1x1(out: Tensor, weight: Tensor) -> Tensor:
    """The rows ``(N, K K C_out)`` of a 1 x 1 input times :func:`_taps_1x1` as the image ``(N, C_out, K, K)``
    (channels last in memory)."""
    _, c_out, kernel, _ = weight.shape
    return out.reshape(-1, kernel, kernel, c_out).permute(0, 3, 1, 2)


def _phases_interleaved(x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """:func:`conv_transpose_stride2`'s value for inputs larger than 1 x 1: its phases, interleaved and cropped."""
    kernel = weight.shape[-1]
    out = depth_to_space(stride2_phases(x, weight, bias))
    return out[..., : 2 * (x.shape[-2] - 1) + kernel, : 2 * (x.shape[-1] - 1) + kernel]


class _ConvTransposeStride2(torch.autograd.Function):
    """:func:`conv_transpose_stride2` forward by its phases; backward by PyTorch's own transposed-convolution
    backward, whose input gradient is a strided convolution and whose weight gradient correlates the input with
    the interleaved output gradient: they take only the kernel's real taps, where the phases' backward also runs
    over the taps a kernel of odd size pads with and over the padded border (at the decoder's second layer, 5 x 5
    to 13 x 13 with kernel 5, 2.8x the multiply-adds), and it needs no de-interleaved copy of the gradient. The bias
    gradient is summed apart (:func:`_bias_grad`), not by that backward."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        return _keep_for_backward(ctx, x, weight, bias, _phases_interleaved(x, weight, bias))

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        x, weight = ctx.saved_tensors
        needs = ctx.needs_input_grad
        grad_x, grad_weight, _ = _stride2_backward(grad, x, weight, transposed=True, mask=(needs[0], needs[1], False))
        return grad_x, grad_weight, _bias_grad(grad, ctx.has_bias and needs[2])


def _keep_for_backward(ctx: Any, x: Tensor, weight: Tensor, bias: Tensor | None, out: Tensor) -> Tensor:
    """Save ``x`` and ``weight`` for a stride-2 convolution's backward, in ``out``'s dtype (under autocast the
    convolution ran in it, and its backward does too), and whether it has a bias; returns ``out``."""
    ctx.save_for_backward(x.to(out.dtype), weight.to(out.dtype))
    ctx.has_bias = bias is not None
    return out


def _bias_grad(grad: Tensor, needed: bool) -> Tensor | None:
    """A convolution's bias gradient from its output gradient ``(N, C, H, W)`` (None where it is not needed)."""
    return grad.sum((0, 2, 3)) if needed else None


def _stride2_backward(
    grad: Tensor, x: Tensor, weight: Tensor, *, transposed: bool, mask: tuple[bool, bool, bool]
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """PyTorch's backward of the unpadded stride-2 (transposed) convolution of ``x`` by ``weight`` with output
    gradient ``grad``: the input, weight and bias gradients that ``mask`` asks for (None for the others)."""
    bias_sizes = [weight.shape[1 if transposed else 0]] if mask[2] else None
    return torch.ops.aten.convolution_backward(
        grad, x, weight, bias_sizes, [2, 2], [0, 0], [1, 1], transposed, [0, 0], 1, list(mask)
    )


class _HalfSquaredError(torch.autograd.Function):
    """``0.5 * sum((pred - (scale * target + shift))^2)`` over the last three dimensions, with the gradient kept from
    the forward pass: one reading pass over the pixels each way, the uint8 target scaled in the subtraction."""

    @staticmethod
    def forward(ctx: Any, pred: Tensor, target: Tensor, scale: float, shift: float) -> Tensor:
        diff = target.to(pred.dtype)  # the one new image-sized tensor; the rest runs in place on it
        torch.sub(pred, diff, alpha=scale, out=diff)
        if shift != 0.0:
            diff.sub_(shift)
        ctx.save_for_backward(diff)
        return 0.5 * torch.linalg.vector_norm(diff, dim=(-3, -2, -1)).square()

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, None, None, None]:
        (diff,) = ctx.saved_tensors
        return diff.mul_(grad[..., None, None, None]), None, None, None  # nothing reads the difference again


def half_squared_error(pred: Tensor, target: Tensor, scale: float, shift: float) -> Tensor:
    """``0.5 * sum_{C,H,W} (pred - (scale * target + shift))^2``: ``pred (..., C, H, W)`` float, ``target`` the same
    shape, uint8 pixels (or any layout of them both, their phases say: the sum is the same). Returns ``(...)``; no
    gradient to ``target``."""
    return _HalfSquaredError.apply(pred, target, scale, shift)
