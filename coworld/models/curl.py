"""Networks of the CURL baseline: conv encoder, squashed-Gaussian actor, twin Q critic, bilinear similarity.

The architecture follows CURL's DMC encoder (Laskin et al., 2020): ``num_layers`` 3x3 convolutions with
``num_filters`` channels (the first with stride 2, the rest stride 1, ReLU after each) on ``frame_stack`` stacked
RGB frames scaled to ``[0, 1]``, then a projection ``Linear -> LayerNorm -> tanh`` to ``feature_dim``. The
critic owns the encoder; its gradients train it. The actor has its own projection on the critic's conv output,
detached, as CURL ties only the conv layers of actor and critic.

Augmentation: CURL renders 100 x 100 frames and crops 84 x 84. Our datasets store 64 x 64 frames, so the
encoder sees a random ``crop`` x ``crop`` window of the frame padded by ``pad`` pixels (edge pixels
replicated); with ``crop = 64`` and ``pad = 4`` this is a random shift of up to 4 pixels (DrQ's augmentation).
Evaluation takes the centre window, which for ``crop = H`` is the unpadded frame itself.

Images: ``uint8 (B, C, H, W)`` with ``C = 3 * frame_stack`` channels, oldest frame first.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "Actor",
    "BilinearSimilarity",
    "ConvTrunk",
    "Critic",
    "Encoder",
    "Projection",
    "center_crop",
    "random_crop",
    "squashed_gaussian_log_prob",
    "squashed_gaussian_sample",
]

LOG_STD_MIN = -10.0
LOG_STD_MAX = 2.0


# --------------------------------------------------------------------------------------------------------------
# Augmentation
# --------------------------------------------------------------------------------------------------------------


def _window(images: Tensor, top: Tensor, left: Tensor, pad: int, crop: int) -> Tensor:
    """Crop ``crop x crop`` windows at ``(top, left)`` of the replicate-padded images, without padding them.

    Row ``r`` of the padded image is row ``clamp(r - pad, 0, H - 1)`` of the original, so the window can be
    gathered from the original with clamped indices.

    Args:
        images: ``(B, C, H, W)`` any dtype.
        top: ``(B,)`` int64 first padded row of each window, in ``[0, H + 2 pad - crop]``.
        left: ``(B,)`` int64 first padded column.

    Returns:
        ``(B, C, crop, crop)``, same dtype.
    """
    B, _, H, W = images.shape
    offsets = torch.arange(crop, device=images.device)
    rows = (top[:, None] + offsets - pad).clamp(0, H - 1)  # (B, crop)
    cols = (left[:, None] + offsets - pad).clamp(0, W - 1)  # (B, crop)
    batch = torch.arange(B, device=images.device)[:, None, None]
    window = images[batch, :, rows[:, :, None], cols[:, None, :]]  # (B, crop, crop, C)
    return window.permute(0, 3, 1, 2).contiguous()


def random_crop(images: Tensor, *, pad: int, crop: int, generator: torch.Generator | None = None) -> Tensor:
    """A random ``crop x crop`` window of each image padded by ``pad`` replicated edge pixels.

    Args:
        images: ``(B, C, H, W)``; all channels (stacked frames) of one image share the window.
        pad: pixels of replicate padding on each side.
        crop: side of the window; at most ``min(H, W) + 2 * pad``.
        generator: torch generator for the offsets (the global one when None).

    Returns:
        ``(B, C, crop, crop)``, same dtype.
    """
    B, _, H, W = images.shape
    if crop > min(H, W) + 2 * pad:
        raise ValueError(f"crop {crop} is larger than the padded image ({H + 2 * pad} x {W + 2 * pad})")
    top = torch.randint(0, H + 2 * pad - crop + 1, (B,), generator=generator, device="cpu").to(images.device)
    left = torch.randint(0, W + 2 * pad - crop + 1, (B,), generator=generator, device="cpu").to(images.device)
    return _window(images, top, left, pad, crop)


def center_crop(images: Tensor, *, pad: int, crop: int) -> Tensor:
    """The centre ``crop x crop`` window of the padded images (the unpadded image when ``crop`` = H = W).

    Args:
        images: ``(B, C, H, W)``.

    Returns:
        ``(B, C, crop, crop)``, same dtype.
    """
    B, _, H, W = images.shape
    if crop == H == W:
        return images
    if crop > min(H, W) + 2 * pad:
        raise ValueError(f"crop {crop} is larger than the padded image ({H + 2 * pad} x {W + 2 * pad})")
    top = torch.full((B,), (H + 2 * pad - crop) // 2, dtype=torch.long, device=images.device)
    left = torch.full((B,), (W + 2 * pad - crop) // 2, dtype=torch.long, device=images.device)
    return _window(images, top, left, pad, crop)


# --------------------------------------------------------------------------------------------------------------
# Networks
# --------------------------------------------------------------------------------------------------------------


def _init_weights(module: nn.Module) -> None:
    """Orthogonal weights and zero biases, as SAC-AE and CURL initialise their layers (ReLU gain for convs)."""
    if isinstance(module, nn.Linear):
        nn.init.orthogonal_(module.weight)
        nn.init.zeros_(module.bias)
    elif isinstance(module, nn.Conv2d):
        nn.init.orthogonal_(module.weight, gain=nn.init.calculate_gain("relu"))
        nn.init.zeros_(module.bias)


class ConvTrunk(nn.Module):
    """``num_layers`` 3x3 convolutions with ReLU; the first has stride 2. ``uint8`` frames in, flat features out.

    Args:
        channels: input channels ``C = 3 * frame_stack``.
        size: input side (the crop).
        num_filters: channels of every conv layer.
        num_layers: conv layers.
    """

    def __init__(self, *, channels: int, size: int, num_filters: int, num_layers: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        for i in range(num_layers):
            layers += [nn.Conv2d(channels if i == 0 else num_filters, num_filters, 3, stride=2 if i == 0 else 1)]
            layers += [nn.ReLU()]
        self.convs = nn.Sequential(*layers)
        side = (size - 3) // 2 + 1 - 2 * (num_layers - 1)
        if side < 1:
            raise ValueError(f"{num_layers} conv layers leave nothing of a {size} x {size} input")
        self.out_dim = num_filters * side * side
        """Size of the flat output."""
        self.apply(_init_weights)

    def forward(self, images: Tensor) -> Tensor:
        """``(B, C, H, W)`` uint8 (or float in [0, 255]) -> ``(B, out_dim)`` float."""
        x = images.float() / 255.0
        return self.convs(x).flatten(1)


class Projection(nn.Module):
    """``Linear -> LayerNorm -> tanh``: conv features to the ``feature_dim`` representation."""

    def __init__(self, in_dim: int, feature_dim: int) -> None:
        super().__init__()
        self.linear = nn.Linear(in_dim, feature_dim)
        self.norm = nn.LayerNorm(feature_dim)
        self.apply(_init_weights)

    def forward(self, x: Tensor) -> Tensor:
        """``(B, in_dim)`` -> ``(B, feature_dim)`` in ``(-1, 1)``."""
        return torch.tanh(self.norm(self.linear(x)))


class Encoder(nn.Module):
    """CURL's pixel encoder: :class:`ConvTrunk` then :class:`Projection`."""

    def __init__(self, *, channels: int, size: int, num_filters: int, num_layers: int, feature_dim: int) -> None:
        super().__init__()
        self.trunk = ConvTrunk(channels=channels, size=size, num_filters=num_filters, num_layers=num_layers)
        self.head = Projection(self.trunk.out_dim, feature_dim)

    def forward(self, images: Tensor) -> Tensor:
        """``(B, C, H, W)`` uint8 -> ``(B, feature_dim)``."""
        return self.head(self.trunk(images))


def _mlp(in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    """Two hidden ReLU layers of ``hidden`` units (CURL's actor and critic MLPs)."""
    net = nn.Sequential(
        nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, out_dim)
    )
    net.apply(_init_weights)
    return net


def squashed_gaussian_log_prob(pre_tanh: Tensor, mean: Tensor, log_std: Tensor) -> Tensor:
    """``log pi(tanh(u))`` for ``u ~ N(mean, exp(log_std))``, with the tanh change of variables.

    ``log pi(a) = sum_i [ log N(u_i; mean_i, std_i) - log(1 - tanh(u_i)^2) ]``, where
    ``log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u))`` (stable for large ``|u|``).

    Args:
        pre_tanh: ``(B, A)`` the Gaussian sample ``u``.
        mean: ``(B, A)``.
        log_std: ``(B, A)``.

    Returns:
        ``(B,)``.
    """
    noise = (pre_tanh - mean) / log_std.exp()
    gaussian = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
    jacobian = (2 * (math.log(2.0) - pre_tanh - F.softplus(-2 * pre_tanh))).sum(-1)
    return gaussian - jacobian


def squashed_gaussian_sample(
    mean: Tensor, log_std: Tensor, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Reparameterised sample ``a = tanh(mean + std * eps)`` and its log-probability.

    Args:
        mean: ``(B, A)``.
        log_std: ``(B, A)``.

    Returns:
        ``(action (B, A) in (-1, 1), log_prob (B,))``.
    """
    eps = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
    pre_tanh = mean + log_std.exp() * eps
    return torch.tanh(pre_tanh), squashed_gaussian_log_prob(pre_tanh, mean, log_std)


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy on the critic's (detached) conv features.

    Args:
        trunk_dim: size of the conv features (:attr:`ConvTrunk.out_dim`).
        feature_dim: size of the actor's own projection.
        hidden: MLP units.
        action_size: ``A``.
    """

    def __init__(self, *, trunk_dim: int, feature_dim: int, hidden: int, action_size: int) -> None:
        super().__init__()
        self.head = Projection(trunk_dim, feature_dim)
        self.mlp = _mlp(feature_dim, hidden, 2 * action_size)

    def forward(self, conv_features: Tensor) -> tuple[Tensor, Tensor]:
        """``(B, trunk_dim)`` -> ``(mean (B, A), log_std (B, A))`` of the pre-tanh Gaussian.

        ``log_std`` is squashed into ``[LOG_STD_MIN, LOG_STD_MAX]`` with a tanh, as CURL does.
        """
        mean, raw = self.mlp(self.head(conv_features)).chunk(2, dim=-1)
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(raw) + 1)
        return mean, log_std

    def sample(self, conv_features: Tensor, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """``(B, trunk_dim)`` -> reparameterised ``(action (B, A), log_prob (B,))``."""
        mean, log_std = self(conv_features)
        return squashed_gaussian_sample(mean, log_std, generator)

    def mode(self, conv_features: Tensor) -> Tensor:
        """``(B, trunk_dim)`` -> the deterministic action ``tanh(mean)``, ``(B, A)``."""
        mean, _ = self(conv_features)
        return torch.tanh(mean)


class Critic(nn.Module):
    """Twin Q-functions on a shared pixel :class:`Encoder` (which the critic loss trains)."""

    def __init__(
        self,
        *,
        channels: int,
        size: int,
        num_filters: int,
        num_layers: int,
        feature_dim: int,
        hidden: int,
        action_size: int,
    ) -> None:
        super().__init__()
        self.encoder = Encoder(
            channels=channels, size=size, num_filters=num_filters, num_layers=num_layers, feature_dim=feature_dim
        )
        self.q1 = _mlp(feature_dim + action_size, hidden, 1)
        self.q2 = _mlp(feature_dim + action_size, hidden, 1)

    def forward(self, features: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        """``features (..., F)``, ``action (..., A)`` -> ``(q1, q2)`` each ``(...)``."""
        x = torch.cat([features, action], dim=-1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


class BilinearSimilarity(nn.Module):
    """CURL's learned ``W (F, F)`` of the similarity ``q^T W k`` (initialised uniform in [0, 1), as CURL does)."""

    def __init__(self, feature_dim: int) -> None:
        super().__init__()
        self.W = nn.Parameter(torch.rand(feature_dim, feature_dim))
