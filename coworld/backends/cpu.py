"""The CPU fast path of the world model (``train.backend=cpu``): the same loss and gradients as
:meth:`WorldModel.loss <coworld.models.world_model.WorldModel.loss>`, to float rounding, computed faster on a CPU.

It reads the reference modules' weights and changes the form of one thing, where PyTorch's CPU transposed
convolutions are slow at DreamerV2's sizes (benchmarks/RESULTS.md, "CPU backend"; ``benchmarks/backend_parts.py``
measures it): the decoder runs to its output's phases (:func:`decode_phases`), its transposed convolutions as
ordinary ones, and the image term compares them with the target's phases
(:func:`~coworld.backends.cpu_kernels.half_squared_error`, the pixel scaling of
:func:`~coworld.models.world_model.preprocess_image` applied to the target there), so the largest tensors of the
update are never interleaved. Everything else (the encoder, the RSSM, the heads, the KL) is the reference's own
code. The path applies only to the conv
stacks it implements (:func:`unsupported`), and :func:`coworld.backends.select` checks it against the reference
before it trains.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from coworld.backends.cpu_kernels import (
    conv_transpose_stride2,
    half_squared_error,
    space_to_depth,
    stride2_phases,
    stride2_phases4,
)
from coworld.backends.reference import ReferencePath
from coworld.models import world_model as world_model_module
from coworld.models.networks import ACTIVATIONS, ConvDecoder
from coworld.models.world_model import WorldModel

__all__ = ["CpuPath", "decode_phases", "pixel_affine", "unsupported"]

DECODER_KERNELS = (5, 5, 6, 6)
"""The decoder's kernels the phase forms are written for (DreamerV2's)."""

PHASES4_BELOW_DEPTH = 16
"""The decoder's last layer maps its input's 2 x 2 phases to its output's 4 x 4 phases (:func:`stride2_phases4`,
1.8x the multiply-adds) below this many channels, where the narrow layer is slow as an ordinary convolution."""


def unsupported(world_model: WorldModel) -> str:
    """Why the fast path cannot compute ``world_model``, or '' where its decoder is the one it implements:
    DreamerV2's (transposed convolutions of kernels 5, 5, 6, 6 and stride 2 from 1 x 1, an elementwise activation
    between them, no norm)."""
    decoder = world_model.decoder
    for module, cls in ((decoder, ConvDecoder), (world_model, WorldModel)):
        if type(module) is not cls:
            return f"{type(module).__name__} is not {cls.__name__}"
    layers = list(decoder.net)
    convs, acts = layers[::2], layers[1::2]
    if (
        len(layers) != 2 * len(DECODER_KERNELS) - 1
        or any(type(conv) is not nn.ConvTranspose2d for conv in convs)
        or tuple(conv.kernel_size for conv in convs) != tuple((k, k) for k in DECODER_KERNELS)
        or any(conv.stride != (2, 2) or conv.padding != (0, 0) or conv.output_padding != (0, 0) for conv in convs)
        or any(conv.dilation != (1, 1) or conv.groups != 1 for conv in convs)
    ):
        return "the decoder is not DreamerV2's transposed convolutions (kernels 5, 5, 6, 6, stride 2)"
    if any(type(act) not in ACTIVATIONS.values() for act in acts):
        return "the decoder has a layer between its convolutions that is not an elementwise activation"
    return ""


def pixel_affine() -> tuple[float, float] | None:
    """``(scale, shift)`` with ``preprocess_image(x) == scale * x + shift`` for every uint8 value, read off the
    reference's one pixel scaling; None where that is not affine in the pixel values."""
    pixels = torch.arange(256, dtype=torch.uint8).reshape(256, 1, 1, 1)
    values = world_model_module.preprocess_image(pixels, torch.float64).reshape(256)  # as the model calls it
    shift = float(values[0])
    scale = float(values[255] - values[0]) / 255.0
    expected = scale * torch.arange(256, dtype=torch.float64) + shift
    if not torch.allclose(values, expected, rtol=1e-6, atol=1e-9):
        return None
    return scale, shift


class CpuPath(ReferencePath):
    """The world model's loss with its image term in the CPU fast path's form, and the :meth:`prepare` it reads,
    with ``world_model``'s weights and the pixel scaling ``scale * x + shift``
    (:func:`pixel_affine`); ``embed`` and ``observe`` are the reference's."""

    name = "cpu"

    def __init__(self, world_model: WorldModel, scale: float, shift: float) -> None:
        self.world_model = world_model
        self.scale = scale
        self.shift = shift
        self.phase_levels = 2 if world_model.config.cnn_depth < PHASES4_BELOW_DEPTH else 1
        """How many times the decoder's output and the target are taken to :func:`space_to_depth`: 2 (4 x 4 phases)
        where :func:`stride2_phases4` is the faster last layer, else 1."""

    def prepare(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The batch with ``target``, its uint8 pixels as the decoder ends (their 2 x 2 phases, or theirs, 4 x 4),
        work that depends on no weight (so the prefetch thread can make it during an update). ``image`` is kept."""
        if "target" in batch:
            return batch
        phases = space_to_depth(batch["image"])
        return {**batch, "target": space_to_depth(phases) if self.phase_levels == 2 else phases}

    def loss(
        self, batch: dict[str, Tensor], generator: torch.Generator | None = None
    ) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """:meth:`WorldModel.loss <coworld.models.world_model.WorldModel.loss>` itself, its image term
        (:meth:`image_term`) in the phase form."""
        return self.world_model.loss(self.prepare(batch), generator, image_term=self.image_term)

    def image_term(self, feat: Tensor, batch: dict[str, Tensor]) -> Tensor:
        """:meth:`WorldModel.image_nll <coworld.models.world_model.WorldModel.image_nll>` as half the squared error
        between the decoder's phases and the target's (the same sum over pixels), ``(B, T)``."""
        # pred - (scale t + shift) = (pred - shift) - scale t: the shift goes into the last layer's bias
        mean = decode_phases(self.world_model.decoder, feat, self.phase_levels, offset=-self.shift)
        return half_squared_error(mean.float(), batch["target"].movedim(-1, -3), self.scale, 0.0)


def _folds_linear(decoder: ConvDecoder, rows: int) -> bool:
    """Whether :func:`decode_phases` on ``rows`` feature vectors multiplies the linear layer's weights into the
    first transposed convolution's: where that counts fewer multiply-adds."""
    feat_size, hidden = decoder.linear.in_features, decoder.linear.out_features
    first = decoder.net[0]
    out_size = first.out_channels * first.kernel_size[0] * first.kernel_size[1]
    return rows * feat_size * out_size + feat_size * hidden * out_size < rows * hidden * (feat_size + out_size)


def _first_layer(decoder: ConvDecoder, feat: Tensor) -> Tensor:
    """The decoder's linear layer and first transposed convolution (of a 1 x 1 input: one matrix product, no
    activation between): ``(N, feat_size)`` -> ``(N, C, K, K)``, channels last in memory.

    Two linear maps in a row are one: ``(x W1^T + b1) T + b2 = x (W1^T T) + (b1 T + b2)``, with ``T`` the
    convolution's taps ``(hidden, K K C)``; where :func:`_folds_linear` says so the features are multiplied once
    by the folded weight."""
    first = decoder.net[0]
    if not _folds_linear(decoder, feat.shape[0]):
        hidden = decoder.linear(feat)
        return conv_transpose_stride2(hidden.reshape(*hidden.shape, 1, 1), first.weight, first.bias)
    c_in, c_out, kernel, _ = first.weight.shape
    taps = first.weight.permute(0, 2, 3, 1).reshape(c_in, kernel * kernel * c_out)
    bias = torch.addmm(first.bias.repeat(kernel * kernel), decoder.linear.bias[None], taps)
    out = F.linear(feat, (decoder.linear.weight.t() @ taps).t(), bias[0])
    return out.reshape(-1, kernel, kernel, c_out).permute(0, 3, 1, 2)


def decode_phases(decoder: ConvDecoder, feat: Tensor, levels: int, offset: float = 0.0) -> Tensor:
    """The decoder's mean image as its phases, :func:`space_to_depth` applied ``levels`` times (channels first):
    ``(..., feat_size)`` -> ``(..., 4 C, 32, 32)`` or ``(..., 16 C, 16, 16)``; plus ``offset``, which the last
    layer adds with its bias.

    The activations are the decoder's own (elementwise, so they apply to phases as to pixels). With 4 x 4 phases
    the third layer stops at its output's 2 x 2 phases (:func:`stride2_phases`) and the last maps them straight to
    its own 4 x 4 phases (:func:`stride2_phases4`); with 2 x 2 phases the last layer stops at its output's.
    """
    batch = feat.shape[:-1]
    layers = list(decoder.net)
    convs, acts = layers[::2], layers[1::2]
    out = acts[0](_first_layer(decoder, feat.reshape(-1, feat.shape[-1])))
    last = len(convs) - 1
    for i in range(1, last + 1):
        conv = convs[i]
        out = out.contiguous(memory_format=torch.channels_last)
        if i == last:
            to_phases = stride2_phases4 if levels == 2 else stride2_phases
            out = to_phases(out, conv.weight, conv.bias + offset if offset else conv.bias)
        elif i == last - 1 and levels == 2:  # its phases feed the last layer
            out = acts[i](stride2_phases(out, conv.weight, conv.bias))
        else:
            out = acts[i](conv_transpose_stride2(out, conv.weight, conv.bias))
    return out.reshape(*batch, *out.shape[1:])
