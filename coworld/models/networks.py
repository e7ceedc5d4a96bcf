"""Neural-network building blocks of DreamerV2 (no RL logic here).

* :class:`ConvEncoder`: 4 conv layers, kernel 4, stride 2, channels ``d, 2d, 4d, 8d``, ELU; 64 x 64 image to a
  flat embedding of ``8d * 2 * 2`` numbers.
* :class:`ConvDecoder`: dense layer to ``32d`` channels at 1 x 1, then 4 transposed convs (kernels 5, 5, 6, 6,
  stride 2; channels ``4d, 2d, d, C``) back to 64 x 64: the mean of a unit-variance Gaussian over pixels. They
  run as :func:`conv_transpose_stride2` (the same function as ``nn.ConvTranspose2d``, 2-3x faster on a CPU); the
  last ones can stop at the image's phases (:meth:`ConvDecoder.phases`, :func:`stride2_phases4`).
* :class:`MLP`: ELU multilayer perceptron used by the heads, the actor and the critic (optionally DreamerV3's
  LayerNorm + SiLU).
* :class:`LayerNormGRUCell`: DreamerV2's GRU cell with layer normalisation and update bias -1.

Weights are initialised Glorot-uniform with zero biases (the Keras defaults DreamerV2 was tuned with).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from coworld.errors import ConfigError, CoworldError
from coworld.models import autotune

__all__ = [
    "ConvDecoder",
    "ELU",
    "ConvEncoder",
    "LayerNormGRUCell",
    "Linear",
    "MLP",
    "check_image_shape",
    "conv2d",
    "conv2d_stride2",
    "conv_transpose_stride2",
    "depth_to_space",
    "frozen_parameters",
    "glorot_init",
    "linear",
    "space_to_depth",
    "stride2_phases",
    "stride2_phases4",
    "tanh_",
]

SUPPORTED_IMAGE_SIZE = 64
"""DreamerV2's conv stacks map exactly 64 x 64 images to 2 x 2 features and back."""


def check_image_shape(image_shape: tuple[int, int, int]) -> None:
    """Raise :class:`CoworldError` unless ``image_shape`` is ``(64, 64, C)``."""
    if len(image_shape) != 3 or image_shape[0] != SUPPORTED_IMAGE_SIZE or image_shape[1] != SUPPORTED_IMAGE_SIZE:
        raise CoworldError(
            f"DreamerV2's conv encoder/decoder take 64 x 64 x C images, got image_shape={tuple(image_shape)}; "
            "render or resize observations to 64 x 64"
        )


def glorot_init(module: nn.Module) -> None:
    """Glorot-uniform weights and zero biases for every linear and (transposed) conv layer in ``module``."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear | nn.Conv2d | nn.ConvTranspose2d):
            nn.init.xavier_uniform_(layer.weight)
            if layer.bias is not None:
                nn.init.zeros_(layer.bias)


@contextmanager
def frozen_parameters(module: nn.Module) -> Iterator[None]:
    """Temporarily set ``requires_grad=False`` on the parameters of ``module``.

    Gradients still flow *through* the module to its inputs (e.g. from imagined returns back to the actor's
    actions through the world model's dynamics), but no gradient is computed for its own weights.
    """
    params = [p for p in module.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


class _EluKeepingOutput(torch.autograd.Function):
    """``F.elu(x)`` whose backward reads its output (``grad * (y + 1)`` where ``x <= 0``) rather than its input
    (which PyTorch's keeps, to take ``exp(x)`` again): no second exponential, and the input, a layer's output that
    nothing else keeps, is freed as soon as the activation has run (the next layer keeps the output anyway).

    On a float32 CPU tensor the forward is :func:`_elu_numpy`'s; with ``inplace`` it overwrites ``x`` where
    it may (not a view, nor a leaf that requires grad)."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, inplace: bool) -> Tensor:
        out = _elu_numpy(x, inplace=inplace and x._base is None and not (x.is_leaf and x.requires_grad))
        if out is None:
            out = F.elu(x)
        elif out is x:
            ctx.mark_dirty(x)
        ctx.save_for_backward(out)
        return out

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:
        (out,) = ctx.saved_tensors
        return torch.ops.aten.elu_backward(grad, 1.0, 1, 1, True, out), None


def _memory_order(t: Tensor) -> np.ndarray | None:
    """The numbers of a contiguous or (4-D) channels-last CPU tensor as a 1-D NumPy view in memory order; None for
    any other tensor."""
    if t.is_contiguous():
        flat = t.view(-1)
    elif t.ndim == 4 and t.is_contiguous(memory_format=torch.channels_last):
        flat = t.permute(0, 2, 3, 1).reshape(-1)  # the same memory, read in its order
    else:
        return None
    return flat.detach().numpy()


_ELU_BLOCK = 65536
"""Numbers per block of :func:`_elu_numpy` (256 KiB of float32): its three passes over a block find it in cache."""


def _elu_numpy(x: Tensor, inplace: bool = False) -> Tensor | None:
    """``F.elu(x)`` of a float32 CPU tensor, computed by NumPy (into ``x`` itself with ``inplace``), or None
    where this does not apply: another dtype or device, another memory order, more than one torch thread (PyTorch's
    ELU then runs on all of them, NumPy's on one), or while ``torch.compile`` traces.

    It takes ``max(x, expm1(min(x, 0)))``: ``x`` where ``x > 0``, and ``expm1(x)`` elsewhere, since
    ``expm1(x) >= x``. The same function to float rounding, 1.6x faster on a 512 x 8 x 31 x 31 activation, 1.8x
    in place (benchmarks/update_ops.py): PyTorch's CPU ELU spends its time in its vectorised ``expm1``, NumPy's is
    about 4x faster, and the three passes run block by block in cache.
    """
    if x.device.type != "cpu" or x.dtype != torch.float32 or torch.get_num_threads() > 1:
        return None
    src = None if torch.compiler.is_compiling() else _memory_order(x)
    if src is None:
        return None
    out = x if inplace else torch.empty_like(x)  # the input's strides: read in the same memory order
    dst = src if inplace else _memory_order(out)
    scratch = np.empty(min(_ELU_BLOCK, src.size), np.float32)
    for start in range(0, src.size, _ELU_BLOCK):
        a, y = src[start : start + _ELU_BLOCK], dst[start : start + _ELU_BLOCK]
        low = scratch[: a.size]
        np.minimum(a, _ELU_ZEROS[: a.size], out=low)  # against an array: NumPy's minimum with a scalar is 3x slower
        np.expm1(low, out=low)
        np.maximum(a, low, out=y)
    return out


_ELU_ZEROS = np.zeros(_ELU_BLOCK, np.float32)
"""The zeros :func:`_elu_numpy` takes the minimum with (0.16 ns a number against 0.50 for the scalar 0 on one AMD
EPYC core: the whole in-place ELU of a 512 x 8 x 31 x 31 activation in 3.6 ms against 4.1)."""


def tanh_(x: Tensor) -> Tensor:
    """``x.tanh_()``, for a tensor without a graph; a contiguous float32 CPU tensor with one torch thread is
    computed by NumPy's ``tanh`` instead, 4-8x faster from 4,096 numbers up on one AMD EPYC core (PyTorch's CPU
    ``tanh`` there: 112 us for 32,768 numbers against NumPy's 15) and within one float rounding of it."""
    if (
        x.device.type == "cpu"
        and x.dtype == torch.float32
        and x.is_contiguous()
        and torch.get_num_threads() == 1
        and not torch.compiler.is_compiling()
    ):
        flat = x.detach().view(-1).numpy()
        np.tanh(flat, out=flat)
        return x
    return x.tanh_()


_ELU_KEEPING_OUTPUT_MIN = 65536
"""From this many numbers up :class:`ELU` runs as :class:`_EluKeepingOutput`; below, a plain ``F.elu`` call costs
about as much as the custom function's own overhead (its forward and backward against ``F.elu``'s: 0.95x at 512 x
64, timed with the threshold at 32k, and 1.19x at 5632 x 64; benchmarks/update_ops.py), and the memory it saves is
small."""


class ELU(nn.Module):
    """``nn.ELU()`` for the conv stacks, the MLPs and the RSSM: from :data:`_ELU_KEEPING_OUTPUT_MIN` numbers up (a
    training batch's conv activations, the heads over a whole imagined trajectory; at the paper's sizes every
    imagination step too), :class:`_EluKeepingOutput`, which leaves one tensor per layer for the backward where
    ``nn.ELU`` and the next layer keep two; a plain ``F.elu`` below that.

    ``inplace``: overwrite the input where it can (as ``nn.ELU(inplace=True)``), for a layer whose input is a
    fresh output that nothing else reads, e.g. a convolution's."""

    def __init__(self, inplace: bool = False) -> None:
        super().__init__()
        self.inplace = inplace

    def forward(self, x: Tensor) -> Tensor:
        if x.numel() >= _ELU_KEEPING_OUTPUT_MIN:
            return _EluKeepingOutput.apply(x, self.inplace)
        return F.elu(x)


MLP_ACTS: dict[str, type[nn.Module]] = {"elu": ELU, "silu": nn.SiLU}
"""Hidden-layer activations of :class:`MLP` by name."""


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
    return conv2d(x, phases, phase_bias, padding=m - 1)


def stride2_phases4(phases: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """A kernel-6, stride-2 transposed convolution from its input's 2 x 2 phases to its output's 4 x 4 phases,
    one ordinary convolution: the decoder's last layer, without interleaving the layer before it or its own output.

    Output pixel ``4a + r`` (``r < 4``) of the transposed convolution sees input pixel ``2b + q`` (``q < 2``) through
    kernel tap ``4 (a - b) + r - 2q``, a tap only for ``b = a - 1`` and ``b = a``: a 2 x 2 convolution (padding 1) of
    the phases, whose weight holds each tap where an ``(r, q)`` pair uses it and zeros elsewhere (9 of 16 entries:
    1.8x the multiply-adds, which pay only where oneDNN runs the narrow layer slowly; see
    :data:`_PHASES4_BELOW_DEPTH`).

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
    return conv2d(phases, w, None if bias is None else bias.repeat(16), padding=1)


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


_BIAS_ROW = 128
"""Numbers per row of :func:`_bias_grad_rows`'s matrix-vector product (rounded up to a multiple of the channels)."""


def _bias_grad(grad: Tensor, needed: bool) -> Tensor | None:
    """A convolution's bias gradient from its output gradient ``(N, C, H, W)``: the sum over all but the channels
    (None where it is not needed).

    Summed apart from PyTorch's convolution backward, whose own bias gradient costs far more than the sum where the
    output is channels last: the decoder's transposed second layer's backward takes 5.1 ms with it summed apart
    against 7.9 at the tiny preset's batch of 512 frames, and at the authors' widths on 800 frames the second and
    third layers' take 114 and 254 ms against 173 and 365 (benchmarks/update_ops.py, "bias gradient apart"). A
    float32 channels-last gradient on a CPU is summed by whichever of two forms is faster on this machine for its
    shape (:func:`coworld.models.autotune.fastest`): :func:`_bias_grad_rows`, or ``grad.sum((0, 2, 3))``. One
    Intel Xeon ran the first 1.6-4.8x faster at 12, 16 and 48 channels, where PyTorch's reduction ran below the
    memory's speed; one AMD EPYC ran it 1.3-10x slower at 8, 16, 32 and 48 (benchmarks/RESULTS.md, "Eighth pass" and
    "Eleventh pass").
    """
    if not needed:
        return None
    if (
        grad.device.type != "cpu"
        or grad.dtype != torch.float32
        or not grad.is_contiguous(memory_format=torch.channels_last)
    ):
        return grad.sum((0, 2, 3))
    forms = {"rows": lambda: _bias_grad_rows(grad), "sum": lambda: grad.sum((0, 2, 3))}
    return forms[autotune.fastest(("bias_grad", tuple(grad.shape)), forms, default="rows")]()


def _bias_grad_rows(grad: Tensor) -> Tensor:
    """``grad.sum((0, 2, 3))`` of a channels-last gradient ``(N, C, H, W)`` as a ones-vector times its numbers in
    rows of a multiple of ``C`` (at least :data:`_BIAS_ROW` numbers), then the rows' channels folded."""
    channels = grad.shape[1]
    flat = grad.permute(0, 2, 3, 1).reshape(-1)  # the same memory, in its order
    width = math.lcm(channels, _BIAS_ROW)
    whole = flat.numel() // width * width
    out = (flat.new_ones(whole // width) @ flat[:whole].view(-1, width)).view(-1, channels).sum(0)
    if whole < flat.numel():
        out += flat[whole:].view(-1, channels).sum(0)
    return out


class _Conv2d(torch.autograd.Function):
    """``F.conv2d(x, weight, bias, padding=padding)`` (stride 1) whose backward takes the bias gradient apart
    (:func:`_bias_grad`): 0.5 and 0.7 ms less at the decoder's phase convolutions and 0.3 ms at the encoder's first
    layer at the tiny preset, 3.7 ms at the encoder's first at the authors' widths (benchmarks/update_ops.py)."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, weight: Tensor, bias: Tensor, padding: int) -> Tensor:
        ctx.padding = padding
        return _keep_for_backward(ctx, x, weight, bias, F.conv2d(x, weight, bias, padding=padding))

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None, None]:
        x, weight = ctx.saved_tensors
        needs = ctx.needs_input_grad
        grad_x, grad_weight, _ = torch.ops.aten.convolution_backward(
            grad, x, weight, None, [1, 1], [ctx.padding] * 2, [1, 1], False, [0, 0], 1, [needs[0], needs[1], False]
        )
        return grad_x, grad_weight, _bias_grad(grad, needs[2]), None


def conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, padding: int = 0) -> Tensor:
    """``F.conv2d(x, weight, bias, padding=padding)``, stride 1, its bias gradient summed apart from PyTorch's
    backward (:class:`_Conv2d`); equal to it up to float rounding, gradients included."""
    if bias is None:
        return F.conv2d(x, weight, None, padding=padding)
    return _Conv2d.apply(x, weight, bias, padding)


def _stride2_backward(
    grad: Tensor, x: Tensor, weight: Tensor, *, transposed: bool, mask: tuple[bool, bool, bool]
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """PyTorch's backward of the unpadded stride-2 (transposed) convolution of ``x`` by ``weight`` with output
    gradient ``grad``: the input, weight and bias gradients that ``mask`` asks for (None for the others)."""
    bias_sizes = [weight.shape[1 if transposed else 0]] if mask[2] else None
    return torch.ops.aten.convolution_backward(
        grad, x, weight, bias_sizes, [2, 2], [0, 0], [1, 1], transposed, [0, 0], 1, list(mask)
    )


class _Conv2dStride2(torch.autograd.Function):
    """``F.conv2d(x, weight, bias, stride=2)`` whose input gradient, a stride-2 transposed convolution, runs as
    :func:`conv_transpose_stride2` (about 1.4x faster than oneDNN's backward-data at the encoder's second layer);
    the weight and bias gradients are PyTorch's own."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        return _keep_for_backward(ctx, x, weight, bias, F.conv2d(x, weight, bias, stride=2))

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        x, weight = ctx.saved_tensors
        grad_x = _transposed_input_grad(grad, weight, x.shape[-2:]) if ctx.needs_input_grad[0] else None
        grad_weight = grad_bias = None
        if ctx.needs_input_grad[1] or ctx.needs_input_grad[2]:
            mask = (False, True, ctx.has_bias)
            _, grad_weight, grad_bias = _stride2_backward(grad, x, weight, transposed=False, mask=mask)
        return grad_x, grad_weight, grad_bias


def _transposed_input_grad(grad: Tensor, weight: Tensor, size: torch.Size) -> Tensor:
    """The input gradient ``(N, C_in, *size)`` of an unpadded stride-2 convolution by ``weight`` from its output
    gradient ``grad``: :func:`conv_transpose_stride2` of ``grad``, zero in the input rows and columns no output
    reads (an odd input size; the encoder's second layer reads 30 of its 31).

    With an even kernel the transposed convolution's size is even and its phases interleave straight into the
    result, padding included: one copy, where interleaving and then padding take two and a zero-fill (about 2 ms of
    an update at the tiny preset's sizes). Called from a backward, so it records no graph.
    """
    kernel = weight.shape[-1]
    if kernel % 2 or min(grad.shape[-2:]) < 2:  # odd sizes, or a 1 x 1 input (a matrix product): pad afterwards
        full = conv_transpose_stride2(grad, weight, None)
        return F.pad(full, (0, size[1] - full.shape[-1], 0, size[0] - full.shape[-2]))
    grid = _pixel_grid(stride2_phases(grad, weight, None))  # an even kernel: the whole grid is the result
    n, rows, _, cols, _, channels = grid.shape
    out = grid.new_empty(n, size[0], size[1], channels)  # channels last
    out[:, : 2 * rows, : 2 * cols].view(grid.shape).copy_(grid)
    out[:, 2 * rows :].zero_()
    out[:, : 2 * rows, 2 * cols :].zero_()
    return out.permute(0, 3, 1, 2)


def conv2d_stride2(x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """``F.conv2d(x, weight, bias, stride=2)`` (no padding), the input's gradient computed by
    :func:`conv_transpose_stride2`; equal to it up to float rounding, gradients included."""
    return _Conv2dStride2.apply(x, weight, bias)


_LINEAR_MIN_ROWS = 2048
"""From this many rows up :func:`linear` chooses between its two forms; below, ``F.linear`` (a custom autograd
function's overhead is then a visible part of the product, and those shapes gain nothing)."""


def linear(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``F.linear(x, weight, bias)``, its forward and its input gradient each computed by whichever of two forms is
    faster on this machine for the shape (:func:`coworld.models.autotune.fastest`): the BLAS matrix product, or
    oneDNN's 1 x 1 convolution of the rows laid out as pixels.

    The rows ``(N, in)`` are already a channels-last image of ``N`` pixels: viewed as ``B`` images of ``N / B``
    pixels (``B`` at least 16, so that PyTorch hands the convolution to oneDNN), the product is a 1 x 1 convolution
    and its output, channels last, is the ``(N, out)`` result, with no copy either way. On one AMD EPYC, where
    PyTorch's BLAS (MKL) runs generic kernels, oneDNN's form was 1.11-1.28x faster forward and 1.13-1.43x forward
    and backward at 7,500 and 12,800 rows of 250 to 1,030 numbers (the authors' sizes; benchmarks/update_ops.py,
    "linear"), 7.7% of a whole update on batch 150 x 50 (benchmarks/linear_ab.py), and slower at the tiny preset's
    512-row layers. The weight gradient, about as fast either way, stays a matrix product. The forms differ in
    summation order only.

    Falls back to ``F.linear`` off the CPU, for other dtypes, under autocast or ``torch.compile``, below
    :data:`_LINEAR_MIN_ROWS` rows and where no ``B`` from 16 to 64 divides the rows."""
    rows = x.numel() // x.shape[-1] if x.shape[-1] else 0
    images = None
    if (
        rows >= _LINEAR_MIN_ROWS
        and x.device.type == "cpu"
        and x.dtype == weight.dtype == torch.float32
        and not torch.is_autocast_enabled("cpu")
        and not torch.compiler.is_compiling()
    ):
        images = next((b for b in range(16, 65) if rows % b == 0), None)
    if images is None:
        return F.linear(x, weight, bias)
    out = _Linear.apply(x.reshape(rows, x.shape[-1]), weight, bias, images)
    return out.reshape(*x.shape[:-1], weight.shape[0])


def _as_pixels(rows: Tensor, images: int) -> Tensor:
    """Rows ``(N, C)`` (contiguous) as ``images`` channels-last images ``(images, C, N / images, 1)``: a view."""
    n, channels = rows.shape
    return rows.view(images, n // images, 1, channels).permute(0, 3, 1, 2)


def _from_pixels(pixels: Tensor) -> Tensor:
    """:func:`_as_pixels`'s images back as rows ``(N, C)`` (a view where they are channels last)."""
    return pixels.permute(0, 2, 3, 1).reshape(-1, pixels.shape[1])


class _Linear(torch.autograd.Function):
    """:func:`linear` on rows ``(N, in)``: forward and input gradient in the faster of their two forms."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, weight: Tensor, bias: Tensor | None, images: int) -> Tensor:
        x = x.contiguous()
        ctx.save_for_backward(x, weight)
        ctx.images, ctx.has_bias = images, bias is not None
        kernel = weight[:, :, None, None]
        forms = {
            "matmul": lambda: F.linear(x, weight, bias),
            "onednn": lambda: _from_pixels(F.conv2d(_as_pixels(x, images), kernel, bias)),
        }
        return forms[autotune.fastest(("linear", tuple(x.shape), weight.shape[0]), forms, default="matmul")]()

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None, None]:
        x, weight = ctx.saved_tensors
        needs = ctx.needs_input_grad
        grad = grad.contiguous()
        grad_x = grad_weight = grad_bias = None
        if needs[0]:
            images, kernel = ctx.images, weight[:, :, None, None]

            def onednn() -> Tensor:
                pixels = torch.ops.aten.convolution_backward(
                    _as_pixels(grad, images), _as_pixels(x, images), kernel, None,
                    [1, 1], [0, 0], [1, 1], False, [0, 0], 1, [True, False, False],
                )[0]  # fmt: skip
                return _from_pixels(pixels)

            forms = {"matmul": lambda: grad @ weight, "onednn": onednn}
            key = ("linear input grad", tuple(grad.shape), x.shape[1])
            grad_x = forms[autotune.fastest(key, forms, default="matmul")]()
        if needs[1]:
            grad_weight = grad.t() @ x
        if ctx.has_bias and needs[2]:
            grad_bias = grad.sum(0)
        return grad_x, grad_weight, grad_bias, None


class Linear(nn.Linear):
    """``nn.Linear`` (the same parameters and state-dict keys) computed by :func:`linear`."""

    def forward(self, x: Tensor) -> Tensor:
        return linear(x, self.weight, self.bias)


class ConvEncoder(nn.Module):
    """Image encoder: ``(..., C, 64, 64)`` float in ``[-0.5, 0.5]`` to ``(..., embed_size)``."""

    def __init__(self, *, channels: int, depth: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        in_channels = channels
        for i in range(4):
            out_channels = depth * 2**i
            layers += [nn.Conv2d(in_channels, out_channels, kernel_size=4, stride=2), ELU(inplace=True)]
            in_channels = out_channels
        self.net = nn.Sequential(*layers)
        self.embed_size = in_channels * 2 * 2
        """Length of the flat embedding: ``8 * depth * 2 * 2``."""
        glorot_init(self)

    def forward(self, image: Tensor) -> Tensor:
        """``(..., C, 64, 64)`` -> ``(..., embed_size)``."""
        batch = image.shape[:-3]
        out = self.net(image.reshape(-1, *image.shape[-3:]))
        return out.reshape(*batch, self.embed_size)

    def from_phases(self, phases: Tensor, pixels: bool = False) -> Tensor:
        """The same embedding from the image's 2 x 2 phases, :func:`space_to_depth` as channels first:
        ``(..., 4 C, 32, 32)`` -> ``(..., embed_size)``.

        The first layer (kernel 4, stride 2) is then a kernel-2, stride-1 convolution of the phases with the same
        weights rearranged (about as fast on a CPU as the 3-channel strided one); the world model's loss
        rearranges its images into phases once, for this and for the decoder's target.

        ``phases`` is float in ``[-0.5, 0.5]`` (:func:`~coworld.models.world_model.preprocess_phases`), or, with
        ``pixels`` (always so for uint8), the pixels' values 0 to 255: the first layer then takes the scaling
        ``x / 255 - 0.5`` into its weights and bias (it pads nothing, so every output sees every tap), and uint8
        input needs one float copy, not three passes. (Leaving out of that copy the phases' last row and column,
        which feed only the first layer's 31st output row and column, which the second layer never reads, saved 6%
        of the first layer's work but raised the peak memory with tcmalloc: at the authors' widths on batch
        40 x 50, 3.0 against 2.5 GiB.)
        """
        batch = phases.shape[:-3]
        first = self.net[0]
        out_channels, channels = first.weight.shape[:2]
        # Tap (2a + p, 2b + s) of channel c is tap (a, b) of phase channel (p, s, c).
        weight = first.weight.reshape(out_channels, channels, 2, 2, 2, 2).permute(0, 3, 5, 1, 2, 4)
        weight = weight.reshape(out_channels, 4 * channels, 2, 2)
        bias = first.bias
        x = phases.reshape(-1, *phases.shape[-3:])
        if pixels or x.dtype == torch.uint8:  # conv(w, x / 255 - 0.5) = conv(w / 255, x) - 0.5 * sum(w)
            bias = bias - 0.5 * weight.sum(dim=(1, 2, 3))
            weight = weight / 255.0
            x = x.to(weight.dtype)
        out = conv2d(x, weight, bias)
        for layer in self.net[1:]:
            out = conv2d_stride2(out, layer.weight, layer.bias) if isinstance(layer, nn.Conv2d) else layer(out)
        return out.reshape(*batch, self.embed_size)


_PHASES4_BELOW_DEPTH = 16
"""The decoder's last layer runs as :func:`stride2_phases4` below this many input channels (its 1.8x multiply-adds
pay where oneDNN runs the narrow layer slowly): forward and backward against :func:`stride2_phases` of the
interleaved input at batch 512, 1.24x at 8 channels (the tiny preset), 1.08x at 16 (0.99x at batch 800) and 0.90x at
32 (benchmarks/update_ops.py)."""


class ConvDecoder(nn.Module):
    """Image decoder: ``(..., feat_size)`` to the mean image ``(..., C, 64, 64)``."""

    def __init__(self, *, feat_size: int, channels: int, depth: int) -> None:
        super().__init__()
        self.depth = depth
        self.linear = Linear(feat_size, 32 * depth)
        kernels = (5, 5, 6, 6)
        layers: list[nn.Module] = []
        in_channels = 32 * depth
        for i, kernel in enumerate(kernels):
            last = i == len(kernels) - 1
            out_channels = channels if last else depth * 2 ** (len(kernels) - i - 2)
            layers.append(nn.ConvTranspose2d(in_channels, out_channels, kernel_size=kernel, stride=2))
            if not last:
                layers.append(ELU(inplace=True))
            in_channels = out_channels
        self.net = nn.Sequential(*layers)
        glorot_init(self)
        self.phase_levels = 2 if depth < _PHASES4_BELOW_DEPTH else 1
        """How many times :meth:`phases` applies :func:`space_to_depth`: 2 (4 x 4 phases) where
        :func:`stride2_phases4` is the faster last layer, else 1."""

    def forward(self, feat: Tensor) -> Tensor:
        """``(..., feat_size)`` -> ``(..., C, 64, 64)``."""
        phases = self.phases(feat)
        image = phases.reshape(-1, *phases.shape[-3:])
        for _ in range(self.phase_levels):
            image = depth_to_space(image)
        return image.reshape(*phases.shape[:-3], *image.shape[1:])

    def folds_linear(self, rows: int) -> bool:
        """Whether :meth:`phases` on ``rows`` feature vectors multiplies the linear layer's weights into the first
        transposed convolution's (:meth:`_first_layer`): where that counts fewer multiply-adds."""
        feat_size, hidden = self.linear.in_features, self.linear.out_features
        first = self.net[0]
        out_size = first.out_channels * first.kernel_size[0] * first.kernel_size[1]
        return rows * feat_size * out_size + feat_size * hidden * out_size < rows * hidden * (feat_size + out_size)

    def _first_layer(self, feat: Tensor) -> Tensor:
        """The linear layer and the first transposed convolution (of a 1 x 1 input: one matrix product, no
        activation between): ``(N, feat_size)`` -> ``(N, C, K, K)``, channels last in memory.

        Two linear maps in a row are one: ``(x W1^T + b1) T + b2 = x (W1^T T) + (b1 T + b2)``, with ``T`` the
        convolution's taps ``(hidden, K K C)``. Where :meth:`folds_linear` says so the update multiplies the
        weights once and the features once, and autograd's backward then takes the features' gradient through the
        folded weight and the two weights' through the ``feat_size x K K C`` gradient of the folded one: at the
        tiny preset's sizes on 512 rows (128 features, 256 hidden, 800 outputs) 0.65x the multiply-adds of the
        two layers, forward and backward; at the paper's widths on 800 rows it would be 1.97x, so they run as two.
        """
        first = self.net[0]
        if not self.folds_linear(feat.shape[0]):
            hidden = self.linear(feat)
            return conv_transpose_stride2(hidden.reshape(*hidden.shape, 1, 1), first.weight, first.bias)
        taps = _taps_1x1(first.weight)
        bias = torch.addmm(first.bias.repeat(first.kernel_size[0] * first.kernel_size[1]), self.linear.bias[None], taps)
        return _pixels_1x1(linear(feat, (self.linear.weight.t() @ taps).t(), bias[0]), first.weight)

    def phases(self, feat: Tensor, offset: float = 0.0) -> Tensor:
        """The mean image's phases, :func:`space_to_depth` applied :attr:`phase_levels` times (channels first):
        ``(..., feat_size)`` -> ``(..., 4 C, 32, 32)`` or ``(..., 16 C, 16, 16)``; plus ``offset``, which the last
        layer adds with its bias (the image loss takes the mean plus 0.5, on the pixels' scale, without a pass of
        its own over the image).

        A loss summed over pixels compares these with the target's phases, so the largest tensors of the update are
        never interleaved (forward and backward). With 4 x 4 phases the third layer stops at its output's 2 x 2
        phases (:func:`stride2_phases`) and the last maps them straight to its own 4 x 4 phases
        (:func:`stride2_phases4`); with 2 x 2 phases the last layer stops at its output's (:func:`stride2_phases`).
        """
        batch = feat.shape[:-1]
        out = self._first_layer(feat.reshape(-1, feat.shape[-1]))
        last = len(self.net) - 1
        for i, layer in enumerate(self.net):
            if i == 0:  # done by _first_layer
                continue
            if isinstance(layer, nn.ConvTranspose2d):
                out = out.contiguous(memory_format=torch.channels_last)
                if i == last:
                    to_phases = stride2_phases4 if self.phase_levels == 2 else stride2_phases
                    out = to_phases(out, layer.weight, layer.bias + offset if offset else layer.bias)
                elif i == last - 2 and self.phase_levels == 2:  # its phases feed the last layer
                    out = stride2_phases(out, layer.weight, layer.bias)
                else:
                    out = conv_transpose_stride2(out, layer.weight, layer.bias)
            else:
                out = layer(out)
        return out.reshape(*batch, *out.shape[1:])


class MLP(nn.Module):
    """``layers`` hidden layers of ``units``, then a linear layer: ``(..., in_size)`` -> ``(..., out_size)``.

    Each hidden layer is ``Linear -> act`` (DreamerV2: ELU), or with ``norm`` ``Linear -> LayerNorm -> act``
    (DreamerV3, with ``act='silu'``); ``norm`` removes the part of a hidden layer's output common to all inputs,
    so the layer after it learns from what tells inputs apart.
    """

    def __init__(
        self, *, in_size: int, out_size: int, units: int, layers: int, norm: bool = False, act: str = "elu"
    ) -> None:
        super().__init__()
        if act not in MLP_ACTS:
            raise ConfigError(f"unknown MLP activation {act!r}; choose one of: {', '.join(MLP_ACTS)}")
        modules: list[nn.Module] = []
        size = in_size
        for _ in range(layers):
            modules.append(Linear(size, units))
            if norm:
                modules.append(nn.LayerNorm(units, eps=1e-3))
            modules.append(MLP_ACTS[act]())
            size = units
        modules.append(Linear(size, out_size))
        self.net = nn.Sequential(*modules)
        glorot_init(self)

    def forward(self, x: Tensor) -> Tensor:
        """``(..., in_size)`` -> ``(..., out_size)``."""
        return self.net(x)

    @torch.no_grad()
    def zero_output(self) -> None:
        """Zero the output layer's weights and bias, so the MLP starts at 0 everywhere (DreamerV3's ``outscale``
        0 for its reward head and critic)."""
        output = self.net[len(self.net) - 1]
        output.weight.zero_()
        output.bias.zero_()


class LayerNormGRUCell(nn.Module):
    """GRU cell with layer normalisation of the gate pre-activations (DreamerV2's ``GRUCell(norm=True)``).

    ``parts = LayerNorm(W [x, h])`` split into reset ``r``, candidate ``c`` and update ``u``;
    ``r = sigmoid(r)``, ``c = tanh(r * c)``, ``u = sigmoid(u - 1)``, ``h' = u * c + (1 - u) * h``.
    Shapes: ``x (N, in_size)``, ``h (N, size)`` -> ``(N, size)``.
    """

    def __init__(self, *, in_size: int, size: int, update_bias: float = -1.0) -> None:
        super().__init__()
        self.size = size
        self.update_bias = update_bias
        self.linear = Linear(in_size + size, 3 * size, bias=False)
        self.norm = nn.LayerNorm(3 * size)
        glorot_init(self)

    def forward(self, x: Tensor, h: Tensor) -> Tensor:
        """One step: ``(N, in_size), (N, size)`` -> ``(N, size)``."""
        parts = self.norm(self.linear(torch.cat([x, h], dim=-1)))
        reset, cand, update = parts.split(self.size, dim=-1)
        reset = torch.sigmoid(reset)
        cand = torch.tanh(reset * cand)
        update = torch.sigmoid(update + self.update_bias)
        dtype = torch.promote_types(h.dtype, cand.dtype)  # as u * c + (1 - u) * h would (bf16 autocast)
        return torch.lerp(h.to(dtype), cand.to(dtype), update.to(dtype))  # u * c + (1 - u) * h in one op
