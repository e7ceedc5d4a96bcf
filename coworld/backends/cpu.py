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
    DreamerV2's (a linear layer, then transposed convolutions of kernels 5, 5, 6, 6 and stride 2 from 1 x 1, one
    elementwise activation between each two, no norm). The reason names the part that differs."""
    decoder = world_model.decoder
    for module, cls in ((decoder, ConvDecoder), (world_model, WorldModel)):
        if type(module) is not cls:
            return f"{type(module).__name__} is not {cls.__name__}"
    if type(decoder.linear) is not nn.Linear:
        return f"the decoder's first layer (decoder.linear) is a {type(decoder.linear).__name__}, not a Linear"
    layers = list(decoder.net)
    convs = [i for i, layer in enumerate(layers) if isinstance(layer, nn.modules.conv._ConvNd)]
    for number, i in enumerate(convs, 1):
        if not _is_stride2_transposed(layers[i]):
            return f"decoder layer {number} (decoder.net[{i}]) is {_describe_conv(layers[i])}, not {_SERVED_CONV}"
    kernels = tuple(_kernel(layers[i]) for i in convs)
    if kernels != DECODER_KERNELS:
        return f"the decoder's kernels are {kernels}, not DreamerV2's {', '.join(map(str, DECODER_KERNELS))}"
    return _between_convolutions(layers, convs, world_model.config.norm)


_SERVED_CONV = "a ConvTranspose2d of stride 2 (no padding, dilation or groups)"

_ACTIVATION_NAMES = [cls.__name__ for cls in ACTIVATIONS.values()]
_SERVED_ACTIVATION = f"{', '.join(_ACTIVATION_NAMES[:-1])} or {_ACTIVATION_NAMES[-1]}"
"""The elementwise activations the phase forms apply as they are: 'ELU, SiLU, ReLU, GELU or Tanh'."""


def _is_stride2_transposed(conv: nn.Module) -> bool:
    """Whether ``conv`` is a plain transposed convolution of stride 2, the form the phase kernels take."""
    return (
        type(conv) is nn.ConvTranspose2d
        and conv.stride == (2, 2)
        and conv.padding == (0, 0)
        and conv.output_padding == (0, 0)
        and conv.dilation == (1, 1)
        and conv.groups == 1
    )


def _describe_conv(conv: nn.Module) -> str:
    """``conv`` as a reason reads it: its class and, for a transposed convolution, the settings the fast path does
    not serve (stride 1, padding 2, say)."""
    if type(conv) is not nn.ConvTranspose2d:
        return _article(type(conv).__name__)
    served = {"stride": (2, 2), "padding": (0, 0), "output_padding": (0, 0), "dilation": (1, 1), "groups": 1}
    settings = [f"{key} {_plain(getattr(conv, key))}" for key, want in served.items() if getattr(conv, key) != want]
    return f"a ConvTranspose2d of {', '.join(settings)}"


def _plain(value: Any) -> Any:
    """A square setting ``(k, k)`` as ``k``; anything else as it is."""
    return value[0] if isinstance(value, tuple) and len(set(value)) == 1 else value


def _kernel(conv: nn.Module) -> int | tuple[int, ...]:
    return _plain(conv.kernel_size)


def _between_convolutions(layers: list[nn.Module], convs: list[int], norm: str) -> str:
    """'' where exactly one elementwise activation stands between each two transposed convolutions (at ``convs`` in
    ``layers``) and nothing before the first or after the last, else what stands there instead (``norm``: the
    config's, named where it put the layers)."""
    gaps = [layers[a + 1 : b] for a, b in zip(convs, convs[1:], strict=False)]
    others = [[layer for layer in gap if type(layer) not in ACTIVATIONS.values()] for gap in gaps]
    if any(others):
        return _other_layers(others, norm)
    for number, gap in enumerate(gaps, 1):
        if len(gap) != 1:
            return (
                f"the decoder has {_names(gap) or 'nothing'} between its transposed convolutions {number} and"
                f" {number + 1} (the fast path serves one {_SERVED_ACTIVATION} there)"
            )
    outside = {"after its last": layers[convs[-1] + 1 :], "before its first": layers[: convs[0]]}
    for where, extra in outside.items():
        if extra:
            return f"the decoder has {_names(extra)} {where} transposed convolution (the fast path serves none there)"
    return ""


def _other_layers(others: list[list[nn.Module]], norm: str) -> str:
    """The reason for layers other than an activation between the decoder's transposed convolutions (``others``:
    those of each gap)."""
    found = sorted({type(layer).__name__ for gap in others for layer in gap})
    setting = ""
    if all(others):
        where = "after each transposed convolution but the last"
        if norm != "none" and found == ["ChannelNorm"]:
            setting = f"world_model.norm={norm}; "
    else:
        pairs = [f"{number} and {number + 1}" for number, gap in enumerate(others, 1) if gap]
        where = f"between its transposed convolutions {', '.join(pairs)}"
    names = " and ".join(_article(name) for name in found)
    return f"the decoder has {names} {where} ({setting}the fast path serves an {_SERVED_ACTIVATION} alone there)"


def _names(layers: list[nn.Module]) -> str:
    """``layers`` by class, in order: 'an ELU and a Tanh'."""
    names = [_article(type(layer).__name__) for layer in layers]
    return " and ".join([", ".join(names[:-1]), names[-1]]) if len(names) > 1 else "".join(names)


def _article(name: str) -> str:
    return f"{'an' if name[0] in 'AEIOU' else 'a'} {name}"


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
