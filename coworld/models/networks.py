"""Neural-network building blocks of DreamerV2 (no RL logic here).

* :class:`ConvEncoder`: 4 conv layers, kernel 4, stride 2, channels ``d, 2d, 4d, 8d``, ELU; 64 x 64 image to a
  flat embedding of ``8d * 2 * 2`` numbers.
* :class:`ConvDecoder`: dense layer to ``32d`` channels at 1 x 1, then 4 transposed convs (kernels 5, 5, 6, 6,
  stride 2; channels ``4d, 2d, d, C``) back to 64 x 64: the mean of a unit-variance Gaussian over pixels. They
  run as :func:`conv_transpose_stride2` (the same function as ``nn.ConvTranspose2d``, 2-3x faster on a CPU).
* :class:`MLP`: ELU multilayer perceptron used by the heads, the actor and the critic (optionally DreamerV3's
  LayerNorm + SiLU).
* :class:`LayerNormGRUCell`: DreamerV2's GRU cell with layer normalisation and update bias -1.

Weights are initialised Glorot-uniform with zero biases (the Keras defaults DreamerV2 was tuned with).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from coworld.errors import ConfigError, CoworldError

MLP_ACTS: dict[str, type[nn.Module]] = {"elu": nn.ELU, "silu": nn.SiLU}
"""Hidden-layer activations of :class:`MLP` by name."""

__all__ = [
    "ConvDecoder",
    "ConvEncoder",
    "LayerNormGRUCell",
    "MLP",
    "check_image_shape",
    "conv_transpose_stride2",
    "frozen_parameters",
    "glorot_init",
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


def conv_transpose_stride2(x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """``F.conv_transpose2d(x, weight, bias, stride=2)`` computed as one ordinary convolution and a pixel shuffle.

    With ``M = ceil(K / 2)``, the output pixel ``(2q + p, 2r + s)`` of a stride-2 transposed convolution only
    sees the kernel taps ``(p + 2m, s + 2n)``, ``m, n < M``, applied to the input pixels ``(q - m, r - n)``:
    an ordinary ``M x M`` convolution of the input padded by ``M - 1``, one output channel per phase ``(p, s)``.
    The four phases are stacked as ``4 C_out`` channels of one convolution and then interleaved
    (PyTorch's CPU transposed convolution scatters columns instead, several times slower at DreamerV2's sizes).
    A 1 x 1 input (the decoder's first layer) is one matrix product. The result equals the transposed
    convolution up to float rounding (summation order), gradients included.

    Shapes: ``x (N, C_in, H, W)``, ``weight (C_in, C_out, K, K)`` (``nn.ConvTranspose2d``'s layout),
    ``bias (C_out,)``; returns ``(N, C_out, 2 (H - 1) + K, 2 (W - 1) + K)``.
    """
    c_in, c_out, kernel, _ = weight.shape
    n, _, height, width = x.shape
    if height == 1 and width == 1:
        out = (x.reshape(n, c_in) @ weight.reshape(c_in, -1)).reshape(n, c_out, kernel, kernel)
        return out if bias is None else out + bias[:, None, None]
    m = (kernel + 1) // 2
    taps = F.pad(weight, (0, 2 * m - kernel, 0, 2 * m - kernel)).reshape(c_in, c_out, m, 2, m, 2)
    phases = taps.flip(2, 4).permute(3, 5, 1, 0, 2, 4).reshape(4 * c_out, c_in, m, m)
    phase_bias = None if bias is None else bias.repeat(4)
    y = F.conv2d(x, phases, phase_bias, padding=m - 1)  # (N, [p, s, C_out], H + M - 1, W + M - 1)
    rows, cols = y.shape[-2:]
    # Interleave the phases into a channels-last image (a plain strided copy, faster than pixel_shuffle here).
    out = y.permute(0, 2, 3, 1).reshape(n, rows, cols, 2, 2, c_out).transpose(2, 3)
    out = out.reshape(n, 2 * rows, 2 * cols, c_out).permute(0, 3, 1, 2)
    return out[..., : 2 * (height - 1) + kernel, : 2 * (width - 1) + kernel]


class ConvEncoder(nn.Module):
    """Image encoder: ``(..., C, 64, 64)`` float in ``[-0.5, 0.5]`` to ``(..., embed_size)``."""

    def __init__(self, *, channels: int, depth: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        in_channels = channels
        for i in range(4):
            out_channels = depth * 2**i
            layers += [nn.Conv2d(in_channels, out_channels, kernel_size=4, stride=2), nn.ELU()]
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


class ConvDecoder(nn.Module):
    """Image decoder: ``(..., feat_size)`` to the mean image ``(..., C, 64, 64)``."""

    def __init__(self, *, feat_size: int, channels: int, depth: int) -> None:
        super().__init__()
        self.depth = depth
        self.linear = nn.Linear(feat_size, 32 * depth)
        kernels = (5, 5, 6, 6)
        layers: list[nn.Module] = []
        in_channels = 32 * depth
        for i, kernel in enumerate(kernels):
            last = i == len(kernels) - 1
            out_channels = channels if last else depth * 2 ** (len(kernels) - i - 2)
            layers.append(nn.ConvTranspose2d(in_channels, out_channels, kernel_size=kernel, stride=2))
            if not last:
                layers.append(nn.ELU())
            in_channels = out_channels
        self.net = nn.Sequential(*layers)
        glorot_init(self)

    def forward(self, feat: Tensor) -> Tensor:
        """``(..., feat_size)`` -> ``(..., C, 64, 64)``."""
        batch = feat.shape[:-1]
        out = self.linear(feat.reshape(-1, feat.shape[-1])).reshape(-1, 32 * self.depth, 1, 1)
        for layer in self.net:
            if isinstance(layer, nn.ConvTranspose2d):
                out = conv_transpose_stride2(
                    out.contiguous(memory_format=torch.channels_last), layer.weight, layer.bias
                )
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
            modules.append(nn.Linear(size, units))
            if norm:
                modules.append(nn.LayerNorm(units, eps=1e-3))
            modules.append(MLP_ACTS[act]())
            size = units
        modules.append(nn.Linear(size, out_size))
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
        self.linear = nn.Linear(in_size + size, 3 * size, bias=False)
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
