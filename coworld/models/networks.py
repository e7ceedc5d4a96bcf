"""Neural-network building blocks of DreamerV2 (no RL logic here): plain PyTorch modules.

* :class:`ConvEncoder`: conv layers of stride 2 (DreamerV2: 4 of kernel 4, channels ``d, 2d, 4d, 8d``) from a 64 x 64
  image to a flat embedding.
* :class:`ConvDecoder`: a linear layer to ``32d`` channels at 1 x 1, then transposed convs of stride 2 (DreamerV2:
  kernels 5, 5, 6, 6; channels ``4d, 2d, d, C``) back to 64 x 64: the mean of a unit-variance Gaussian over pixels.
* :class:`MLP`: the heads, the actor and the critic.
* :class:`LayerNormGRUCell`: DreamerV2's GRU cell with layer normalisation and update bias -1.

Architecture choices are names from the config: the hidden activation (:data:`ACTIVATIONS`) and the
normalisation after each hidden layer (:data:`NORMS`). Weights are initialised Glorot-uniform with zero biases (the
Keras defaults DreamerV2 was tuned with).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import torch
from torch import Tensor, nn

from coworld import config
from coworld.errors import ConfigError, CoworldError

__all__ = [
    "ACTIVATIONS",
    "NORMS",
    "ChannelNorm",
    "ConvDecoder",
    "ConvEncoder",
    "LayerNormGRUCell",
    "MLP",
    "check_image_shape",
    "conv_out_size",
    "conv_transpose_out_size",
    "frozen_parameters",
    "glorot_init",
    "make_act",
    "make_norm",
]

SUPPORTED_IMAGE_SIZE = 64
"""DreamerV2's conv stacks take 64 x 64 images and decode back to 64 x 64."""

ACTIVATIONS: dict[str, type[nn.Module]] = dict(
    zip(config.ACTIVATIONS, (nn.ELU, nn.SiLU, nn.ReLU, nn.GELU, nn.Tanh), strict=True)
)
"""Hidden activations by their config names (:data:`coworld.config.ACTIVATIONS`)."""

NORMS = config.NORMS
"""Normalisations after a hidden layer, by their config names (:data:`coworld.config.NORMS`)."""


def make_act(name: str) -> nn.Module:
    """The activation module named ``name`` (:data:`ACTIVATIONS`)."""
    if name not in ACTIVATIONS:
        raise ConfigError(f"unknown activation {name!r}; choose one of: {', '.join(ACTIVATIONS)}")
    return ACTIVATIONS[name]()


def make_norm(name: str, size: int, *, channels: bool = False) -> list[nn.Module]:
    """The normalisation layers ``name`` puts after a hidden layer of ``size`` units (or, with ``channels``, conv
    channels): none, or a LayerNorm with DreamerV3's epsilon 1e-3."""
    if name not in NORMS:
        raise ConfigError(f"unknown norm {name!r}; choose one of: {', '.join(NORMS)}")
    if name == "none":
        return []
    return [ChannelNorm(size, eps=1e-3) if channels else nn.LayerNorm(size, eps=1e-3)]


class ChannelNorm(nn.LayerNorm):
    """LayerNorm over the channels of each pixel of ``(N, C, H, W)`` feature maps."""

    def forward(self, x: Tensor) -> Tensor:
        return super().forward(x.movedim(1, -1)).movedim(-1, 1)


def check_image_shape(image_shape: tuple[int, int, int]) -> None:
    """Raise :class:`CoworldError` unless ``image_shape`` is ``(64, 64, C)``."""
    if len(image_shape) != 3 or image_shape[0] != SUPPORTED_IMAGE_SIZE or image_shape[1] != SUPPORTED_IMAGE_SIZE:
        raise CoworldError(
            f"DreamerV2's conv encoder/decoder take 64 x 64 x C images, got image_shape={tuple(image_shape)}; "
            "render or resize observations to 64 x 64"
        )


def conv_out_size(size: int, kernels: Sequence[int], stride: int = 2) -> int:
    """Side of the feature map after unpadded convolutions of ``kernels`` and ``stride`` on a ``size``-pixel side."""
    for kernel in kernels:
        size = (size - kernel) // stride + 1
    return size


def conv_transpose_out_size(size: int, kernels: Sequence[int], stride: int = 2) -> int:
    """Side of the image after unpadded transposed convolutions of ``kernels`` and ``stride``."""
    for kernel in kernels:
        size = (size - 1) * stride + kernel
    return size


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


class ConvEncoder(nn.Module):
    """Image encoder: ``(..., C, 64, 64)`` float (as :func:`~coworld.models.world_model.preprocess_image` makes it)
    to ``(..., embed_size)``. Layer ``i`` has ``depth * 2**i`` channels, ``kernels[i]`` and stride 2, then ``norm``
    and ``act``."""

    def __init__(
        self,
        *,
        channels: int,
        depth: int,
        kernels: Sequence[int] = (4, 4, 4, 4),
        act: str = "elu",
        norm: str = "none",
    ) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        in_channels = channels
        for i, kernel in enumerate(kernels):
            out_channels = depth * 2**i
            layers += [nn.Conv2d(in_channels, out_channels, kernel, stride=2)]
            layers += [*make_norm(norm, out_channels, channels=True), make_act(act)]
            in_channels = out_channels
        self.net = nn.Sequential(*layers)
        glorot_init(self)
        with torch.no_grad():
            probe = torch.zeros(1, channels, SUPPORTED_IMAGE_SIZE, SUPPORTED_IMAGE_SIZE)
            self.embed_size = self.net(probe).numel()
            """Length of the flat embedding (DreamerV2: ``8 depth * 2 * 2``)."""

    def forward(self, image: Tensor) -> Tensor:
        """``(..., C, 64, 64)`` -> ``(..., embed_size)``."""
        batch = image.shape[:-3]
        out = self.net(image.reshape(-1, *image.shape[-3:]))
        return out.reshape(*batch, self.embed_size)


class ConvDecoder(nn.Module):
    """Image decoder: features ``(..., feat_size)`` to the mean image ``(..., C, 64, 64)``. A linear layer to
    ``32 depth`` channels at 1 x 1, then transposed convs of stride 2 with ``kernels``; every one but the last has
    ``depth * 2**(n - i - 2)`` channels, then ``norm`` and ``act``; the last has the image's ``C``."""

    def __init__(
        self,
        *,
        feat_size: int,
        channels: int,
        depth: int,
        kernels: Sequence[int] = (5, 5, 6, 6),
        act: str = "elu",
        norm: str = "none",
    ) -> None:
        super().__init__()
        size = conv_transpose_out_size(1, kernels)
        if size != SUPPORTED_IMAGE_SIZE:
            raise ConfigError(f"decoder kernels {tuple(kernels)} make {size} x {size} images, not 64 x 64")
        self.linear = nn.Linear(feat_size, 32 * depth)
        layers: list[nn.Module] = []
        in_channels = 32 * depth
        for i, kernel in enumerate(kernels):
            last = i == len(kernels) - 1
            out_channels = channels if last else depth * 2 ** (len(kernels) - i - 2)
            layers.append(nn.ConvTranspose2d(in_channels, out_channels, kernel, stride=2))
            if not last:
                layers += [*make_norm(norm, out_channels, channels=True), make_act(act)]
            in_channels = out_channels
        self.net = nn.Sequential(*layers)
        glorot_init(self)

    def forward(self, feat: Tensor) -> Tensor:
        """``(..., feat_size)`` -> ``(..., C, 64, 64)``."""
        batch = feat.shape[:-1]
        hidden = self.linear(feat.reshape(-1, feat.shape[-1]))
        image = self.net(hidden[:, :, None, None])
        return image.reshape(*batch, *image.shape[1:])


class MLP(nn.Module):
    """``layers`` hidden layers of ``units``, then a linear layer: ``(..., in_size)`` -> ``(..., out_size)``.

    Each hidden layer is ``Linear -> norm -> act`` (DreamerV2: no norm, ELU; DreamerV3: LayerNorm, SiLU); the
    norm removes the part of a hidden layer's output common to all inputs, so the layer after it learns from what
    tells inputs apart.
    """

    def __init__(
        self, *, in_size: int, out_size: int, units: int, layers: int, norm: str = "none", act: str = "elu"
    ) -> None:
        super().__init__()
        modules: list[nn.Module] = []
        size = in_size
        for _ in range(layers):
            modules += [nn.Linear(size, units), *make_norm(norm, units), make_act(act)]
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

    ``parts = LayerNorm(W [x, h] + b)`` split into reset ``r``, candidate ``c`` and update ``u``;
    ``r = sigmoid(r)``, ``c = tanh(r * c)``, ``u = sigmoid(u - 1)``, ``h' = u * c + (1 - u) * h``.
    DreamerV2's cell has the bias ``b`` and Keras's LayerNorm epsilon 1e-3 (``bias``, ``eps``).
    Shapes: ``x (N, in_size)``, ``h (N, size)`` -> ``(N, size)``.
    """

    def __init__(
        self, *, in_size: int, size: int, bias: bool = True, eps: float = 1e-3, update_bias: float = -1.0
    ) -> None:
        super().__init__()
        self.size = size
        self.update_bias = update_bias
        self.linear = nn.Linear(in_size + size, 3 * size, bias=bias)
        self.norm = nn.LayerNorm(3 * size, eps=eps)
        glorot_init(self)

    def forward(self, x: Tensor, h: Tensor) -> Tensor:
        """One step: ``(N, in_size), (N, size)`` -> ``(N, size)``."""
        parts = self.norm(self.linear(torch.cat([x, h], dim=-1)))
        reset, cand, update = parts.split(self.size, dim=-1)
        reset = torch.sigmoid(reset)
        cand = torch.tanh(reset * cand)
        update = torch.sigmoid(update + self.update_bias)
        return update * cand + (1.0 - update) * h
