"""DreamerV2's world model: encoder, RSSM, decoder, reward head and discount head.

Batches follow the replay / dataset-sampler convention, as torch tensors on the model's device:

* ``image`` uint8 ``(B, T, H, W, C)``: converted to float ``(B, T, C, H, W)`` in ``[-0.5, 0.5]`` here;
* ``action`` float ``(B, T, A)``: the action that led to step ``t`` (zeros where ``is_first``);
* ``reward`` float ``(B, T)``: the reward received on arriving at step ``t``;
* ``is_first``, ``is_last``, ``is_terminal`` bool ``(B, T)``.

The reward and discount heads predict ``reward[t]`` and ``1 - is_terminal[t]`` from the posterior at ``t``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn

from coworld.config import WorldModelConfig
from coworld.distributions import TWOHOT_BINS, Bernoulli, TwoHotSymlog, UnitGaussian, head_distribution
from coworld.losses.dreamer import discount_loss, image_loss, kl_balanced_loss, reward_loss
from coworld.models.networks import MLP, ConvDecoder, ConvEncoder, check_image_shape
from coworld.models.rssm import RSSM, State

__all__ = ["DiscountHead", "ImageTerm", "ScalarHead", "WorldModel", "preprocess_image"]

ImageTerm = Callable[[Tensor, dict[str, Tensor]], Tensor]
"""``(feat (B, T, F), batch) -> (B, T)``: the image term of :meth:`WorldModel.loss`, computed another way."""


def preprocess_image(image: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
    """uint8 pixels ``(..., H, W, C)`` to the float images ``(..., C, H, W)`` in ``[-0.5, 0.5]`` that the encoder
    reads and the decoder predicts (DreamerV2's scaling). The one place pixels are scaled."""
    return image.movedim(-1, -3).to(dtype) / 255.0 - 0.5


class ScalarHead(nn.Module):
    """MLP from features ``(..., F)`` to a distribution over one number per state: a :class:`UnitGaussian` or, with
    ``dist='twohot'``, a :class:`TwoHotSymlog`. The world model's reward head and the critic are both one.

    ``head(feat).mean`` is the prediction ``(...)`` (float32); pass the distribution and a target to
    :func:`coworld.losses.dreamer.reward_loss` or :func:`~coworld.losses.dreamer.critic_loss`.
    """

    def __init__(
        self, *, feat_size: int, units: int, layers: int, dist: str = "gaussian", norm: str = "none", act: str = "elu"
    ) -> None:
        super().__init__()
        self.dist = dist
        out_size = TWOHOT_BINS if dist == "twohot" else 1
        self.mlp = MLP(in_size=feat_size, out_size=out_size, units=units, layers=layers, norm=norm, act=act)

    def forward(self, feat: Tensor) -> UnitGaussian | TwoHotSymlog:
        """``(..., F)`` -> distribution with mean ``(...)``."""
        return head_distribution(self.mlp(feat), self.dist)


class DiscountHead(nn.Module):
    """MLP from features ``(..., F)`` to a :class:`Bernoulli` over continuation (``1 - is_terminal``).

    ``discount_head(feat).mean`` is the predicted probability that the episode continues, ``(...)``.
    """

    def __init__(self, *, feat_size: int, units: int, layers: int, norm: str = "none", act: str = "elu") -> None:
        super().__init__()
        self.mlp = MLP(in_size=feat_size, out_size=1, units=units, layers=layers, norm=norm, act=act)

    def forward(self, feat: Tensor) -> Bernoulli:
        """``(..., F)`` -> continuation distribution, batch ``(...)``."""
        return Bernoulli(self.mlp(feat).squeeze(-1).float())


class WorldModel(nn.Module):
    """Encoder ``e(o)``, RSSM, decoder ``p(o | h, z)``, reward head and (optional) discount head."""

    def __init__(
        self, *, config: WorldModelConfig, action_size: int, image_shape: tuple[int, int, int] = (64, 64, 3)
    ) -> None:
        super().__init__()
        check_image_shape(image_shape)
        self.config = config
        self.action_size = action_size
        self.image_shape = tuple(image_shape)
        channels = image_shape[2]
        conv = {"channels": channels, "depth": config.cnn_depth, "act": config.act, "norm": config.norm}
        self.encoder = ConvEncoder(kernels=config.encoder_kernels, **conv)
        self.rssm = RSSM(
            embed_size=self.encoder.embed_size,
            action_size=action_size,
            deter=config.deter,
            hidden=config.hidden,
            stoch=config.stoch,
            classes=config.classes,
            unimix=config.unimix,
            act=config.act,
            norm=config.norm,
            gru_bias=config.gru_bias,
            gru_eps=config.gru_eps,
        )
        self.feat_size = self.rssm.feat_size
        """Length of the features ``D + S * K``."""
        self.decoder = ConvDecoder(feat_size=self.feat_size, kernels=config.decoder_kernels, **conv)
        head = {"units": config.mlp_units, "layers": config.mlp_layers, "norm": config.mlp_norm, "act": config.mlp_act}
        self.reward_head = ScalarHead(feat_size=self.feat_size, dist=config.reward_dist, **head)
        if config.zero_init_reward:
            self.reward_head.mlp.zero_output()
        self.discount_head: DiscountHead | None = (
            DiscountHead(feat_size=self.feat_size, **head) if config.pred_discount else None
        )

    def encode(self, image: Tensor) -> Tensor:
        """uint8 images ``(..., H, W, C)`` -> embeddings ``(..., E)``."""
        return self.encoder(preprocess_image(image, self.dtype))

    @property
    def dtype(self) -> torch.dtype:
        """The weights' dtype (float32; float64 where a test or :mod:`coworld.backends`' check makes it so)."""
        return self.decoder.linear.weight.dtype

    def features(self, state: State) -> Tensor:
        """RSSM state -> features ``(..., D + S * K)``."""
        return self.rssm.features(state)

    def observe(
        self,
        batch: dict[str, Tensor],
        state: State | None = None,
        generator: torch.Generator | None = None,
        priors: bool = True,
    ) -> tuple[State, State | None, Tensor]:
        """Encode a batch's images and run the posterior over it.

        Returns ``(post, prior, embed)``: states with batch ``(B, T)`` (``deter (B, T, D)``,
        ``logits``/``stoch (B, T, S, K)``) and the embeddings ``(B, T, E)``. The recurrent state and the previous
        action are zeroed where ``is_first``; ``state`` (batch ``(B,)``) continues from an earlier chunk; ``generator``
        draws the latent samples' noise (torch's default generator if None). ``priors=False``: ``prior`` is None
        (not computed; the posterior is the same, :meth:`RSSM.observe`).
        """
        embed = self.encode(batch["image"])
        post, prior = self.rssm.observe(embed, batch["action"], batch["is_first"], state, generator, priors)
        return post, prior, embed

    def loss(
        self, batch: dict[str, Tensor], generator: torch.Generator | None = None, image_term: ImageTerm | None = None
    ) -> tuple[dict[str, Tensor], dict[str, Any]]:
        """DreamerV2's world-model loss on a batch.

        Returns ``(terms, aux)``. ``terms`` holds unreduced ``(B, T)`` tensors: ``'image'``, ``'reward'``,
        ``'discount'`` (only with ``pred_discount``) negative log-likelihoods and ``'kl'``, the balanced KL before
        free nats. ``aux`` holds ``'post'``, ``'prior'`` (states, batch ``(B, T)``), ``'embed' (B, T, E)``,
        ``'feat' (B, T, F)``, ``'reward_head'`` (the reward head's distribution over ``(B, T)``), ``'kl_loss'`` (the
        scalar KL loss after balancing and free nats) and ``'loss'``::

            loss = image_scale * mean(image) + reward_scale * mean(reward)
                   + discount_scale * mean(discount) + kl_scale * kl_loss

        ``image_term(feat, batch) -> (B, T)`` computes the image term in place of :meth:`image_nll` (a fast path
        computes the same number in another form, :mod:`coworld.backends`); every other term is this method's.
        """
        cfg = self.config
        post, prior, embed = self.observe(batch, generator=generator)
        feat = self.features(post)
        batch_size, length = feat.shape[:2]
        reward = self.reward_head(feat)
        terms: dict[str, Tensor] = {
            "image": (self.image_nll if image_term is None else image_term)(feat, batch),
            "reward": reward_loss(reward, batch["reward"].float()),
        }
        if self.discount_head is not None:
            continuation = 1.0 - batch["is_terminal"].float()
            terms["discount"] = discount_loss(self.discount_head(feat), continuation)
        kl_loss, terms["kl"] = kl_balanced_loss(
            post["logits"], prior["logits"], cfg.kl_balance, cfg.free_nats, normalised=True
        )
        for name, term in terms.items():
            assert term.shape == (batch_size, length), f"{name} term has shape {tuple(term.shape)}"
        loss = cfg.image_scale * terms["image"].mean() + cfg.reward_scale * terms["reward"].mean()
        if "discount" in terms:
            loss = loss + cfg.discount_scale * terms["discount"].mean()
        loss = loss + cfg.kl_scale * kl_loss
        aux = {"post": post, "prior": prior, "embed": embed, "feat": feat, "kl_loss": kl_loss, "loss": loss}
        aux["reward_head"] = reward
        return terms, aux

    def image_nll(self, feat: Tensor, batch: dict[str, Tensor]) -> Tensor:
        """The image term of :meth:`loss`: the decoder's unit Gaussian over the frames of ``batch`` at features
        ``feat (B, T, F)``, its negative log-likelihood ``(B, T)``."""
        image = UnitGaussian(self.decoder(feat).float(), event_dims=3)
        return image_loss(image, preprocess_image(batch["image"], self.dtype))
