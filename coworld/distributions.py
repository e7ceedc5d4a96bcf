"""Small distribution objects used by DreamerV2's heads, latents and actor.

They are plain classes rather than ``torch.distributions`` subclasses: no argument validation on the hot path,
and each one exposes exactly what the agent uses (``mean``, ``mode``, ``sample``/``rsample``, ``log_prob``,
``entropy``). Batch shapes are written ``(...)``; event dimensions are summed where stated.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "Bernoulli",
    "Normal",
    "OneHotCategorical",
    "TanhNormal",
    "TruncatedNormal",
    "TWOHOT_BINS",
    "TwoHotSymlog",
    "UnitGaussian",
    "symexp",
    "symlog",
    "categorical_kl",
    "exponential_noise",
    "head_distribution",
    "log_softmax",
    "one_hot_race",
    "softmax",
]

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def exponential_noise(
    shape: tuple[int, ...], device: torch.device | str | None = None, generator: torch.Generator | None = None
) -> Tensor:
    """Standard exponential draws ``(shape)``, float32: the numbers ``torch.empty(shape).exponential_()`` draws.

    On a CPU, PyTorch's ``exponential_`` takes ``-log1p(-u)`` of one float64 uniform ``u`` per number, one number
    at a time; the same formula over a vectorised float64 ``uniform_`` of the same generator gives the same numbers
    bit for bit (a test checks it), faster. Elsewhere, ``exponential_``.
    """
    if torch.device("cpu" if device is None else device).type != "cpu":
        return torch.empty(shape, device=device).exponential_(generator=generator)
    uniform = torch.empty(shape, dtype=torch.float64).uniform_(generator=generator)
    return uniform.neg_().log1p_().neg_().to(torch.float32)


def softmax(x: Tensor) -> Tensor:
    """Class probabilities ``torch.softmax(x, -1)``."""
    return torch.softmax(x, -1)


def log_softmax(x: Tensor) -> Tensor:
    """Normalised log-probabilities ``torch.log_softmax(x, -1)``."""
    return torch.log_softmax(x, -1)


class UnitGaussian:
    """Normal distribution with unit variance over the last ``event_dims`` dimensions.

    Used for the image decoder, the reward head and the critic: its negative log-likelihood is half the squared
    error. ``log_prob`` drops the additive constant ``-0.5 * log(2 pi)`` per element (it carries no gradient
    and would only shift the logged numbers by ``0.92 * 12288`` for a 64 x 64 x 3 image).
    """

    def __init__(self, mean: Tensor, event_dims: int = 0) -> None:
        self.mean = mean
        """Predicted mean, shape ``(..., *event)``."""
        self.event_dims = event_dims

    @property
    def mode(self) -> Tensor:
        """The mean, shape ``(..., *event)``."""
        return self.mean

    def log_prob(self, value: Tensor) -> Tensor:
        """``-0.5 * sum_event (value - mean)^2``, shape ``(...)`` (constant dropped)."""
        squared = (value - self.mean).square()
        if self.event_dims:
            squared = squared.sum(dim=tuple(range(-self.event_dims, 0)))
        return -0.5 * squared


def symlog(x: Tensor) -> Tensor:
    """``sign(x) * log(1 + |x|)`` (DreamerV3)."""
    return torch.sign(x) * torch.log1p(x.abs())


def symexp(x: Tensor) -> Tensor:
    """The inverse of :func:`symlog`: ``sign(x) * (exp(|x|) - 1)``."""
    return torch.sign(x) * torch.expm1(x.abs())


class TwoHotSymlog:
    """A categorical over ``K`` bins evenly spaced in symlog space (DreamerV3's reward head and critic).

    ``logits (..., K)``; the bins span ``[-20, 20]`` in symlog space (DreamerV3: 255 of them). ``mean`` is the
    symexp of the expected bin, ``(...)``. ``log_prob(x)`` is the cross-entropy against the two-hot encoding of
    ``symlog(x)``: the two neighbouring bins share the weight by distance, so the expected bin of the target
    encoding is exactly ``symlog(x)`` (values beyond the bins go wholly to the outer bin).
    """

    LOW, HIGH = -20.0, 20.0

    def __init__(self, logits: Tensor) -> None:
        self.logits = logits.float()
        self.bins = torch.linspace(self.LOW, self.HIGH, logits.shape[-1], device=logits.device)

    @property
    def mean(self) -> Tensor:
        """``symexp(sum_k p_k b_k)``, shape ``(...)`` (differentiable in the logits)."""
        return symexp((self.logits.softmax(-1) * self.bins).sum(-1))

    @property
    def mode(self) -> Tensor:
        """The mean (DreamerV3 uses it for both)."""
        return self.mean

    def log_prob(self, value: Tensor) -> Tensor:
        """``sum_k twohot(symlog(value))_k * log p_k``, shape ``(...)`` like ``value``."""
        target = self.twohot(value)
        return (target * self.logits.log_softmax(-1)).sum(-1)

    def twohot(self, value: Tensor) -> Tensor:
        """Two-hot encoding ``(..., K)`` of ``symlog(value)`` over the bins (no gradient)."""
        x = symlog(value.detach().float()).clamp(self.LOW, self.HIGH)
        k = self.bins.shape[0]
        step = (self.HIGH - self.LOW) / (k - 1)
        position = (x - self.LOW) / step
        below = position.floor().clamp(0, k - 2)
        upper_weight = (position - below).clamp(0.0, 1.0)
        below_index = below.long()[..., None]
        encoding = torch.zeros(*x.shape, k, device=x.device)
        encoding.scatter_(-1, below_index, (1.0 - upper_weight)[..., None])
        encoding.scatter_add_(-1, below_index + 1, upper_weight[..., None])
        return encoding


TWOHOT_BINS = 255
"""Bins of a :class:`TwoHotSymlog` head (DreamerV3)."""


def head_distribution(out: Tensor, dist: str) -> UnitGaussian | TwoHotSymlog:
    """A scalar head's output ``(..., 1)`` or ``(..., TWOHOT_BINS)`` -> its distribution over ``(...)``."""
    if dist == "twohot":
        return TwoHotSymlog(out)
    return UnitGaussian(out.squeeze(-1).float())


class Bernoulli:
    """Bernoulli distribution parameterised by logits, shape ``(...)``; used for the continuation head."""

    def __init__(self, logits: Tensor) -> None:
        self.logits = logits

    @property
    def mean(self) -> Tensor:
        """Probability of 1, shape ``(...)``."""
        return torch.sigmoid(self.logits)

    @property
    def mode(self) -> Tensor:
        """1.0 where the probability exceeds 0.5, else 0.0, shape ``(...)``."""
        return (self.logits > 0).to(self.logits.dtype)

    def log_prob(self, value: Tensor) -> Tensor:
        """``value * log p + (1 - value) * log(1 - p)``, shape ``(...)``; ``value`` may be soft (in [0, 1])."""
        return -F.binary_cross_entropy_with_logits(self.logits, value.to(self.logits.dtype), reduction="none")


def one_hot_race(probs: Tensor, noise: Tensor) -> Tensor:
    """The one-hot class ``argmax(probs / noise)`` over the last dimension, contiguous, in ``probs``' dtype (no
    gradient): :meth:`OneHotCategorical.rsample`'s draw from exponential ``noise`` of the same shape."""
    race = torch.empty(probs.shape, device=probs.device)  # contiguous: argmax along a strided dim is slow
    # max's indices are argmax's (the first of equal values), and faster
    index = torch.div(probs.float(), noise, out=race).max(dim=-1, keepdim=True).indices
    # F.one_hot's values, without its checks of the indices' range (two more reductions)
    return torch.zeros(probs.shape, dtype=probs.dtype, device=probs.device).scatter_(-1, index, 1.0)


class OneHotCategorical:
    """Independent categoricals over the last dimension with straight-through one-hot samples.

    ``logits`` has shape ``(..., S, K)``: ``S`` latent variables with ``K`` classes each. ``rsample`` returns a
    one-hot sample whose gradient flows to the logits as if through the probabilities
    (``sample + (probs - probs.detach())``: exactly one-hot forward), as in DreamerV2.

    ``normalised``: the logits are already log-probabilities (each row's exponentials sum to 1, as the RSSM's
    are), so the probabilities are their exponentials: the same values as the softmax, and the same gradient to
    whatever normalised them (the softmax's Jacobian differs only along the constant direction, which a
    normalisation removes), in one elementwise pass.
    """

    def __init__(self, logits: Tensor, normalised: bool = False) -> None:
        self.logits = logits
        self.normalised = normalised

    @property
    def probs(self) -> Tensor:
        """Class probabilities, shape ``(..., S, K)``."""
        return self.logits.exp() if self.normalised else softmax(self.logits)

    @property
    def mode(self) -> Tensor:
        """One-hot of the most likely class, shape ``(..., S, K)`` (no gradient)."""
        index = self.logits.argmax(dim=-1)
        return F.one_hot(index, self.logits.shape[-1]).to(self.logits.dtype)

    def rsample(self, noise: Tensor | None = None) -> Tensor:
        """Straight-through one-hot sample, shape ``(..., S, K)``.

        The class is ``argmax(probs / q)`` with ``q ~ Exp(1)`` of shape ``(..., S, K)`` (``noise``, drawn here when
        None): the exponential race ``torch.multinomial`` runs for one sample, so the same random numbers give
        the same classes, without its input checks (each a host synchronisation).
        """
        probs = self.probs
        if noise is None:
            noise = exponential_noise(probs.shape, probs.device)  # contiguous, as multinomial's
        sample = one_hot_race(probs.detach(), noise)
        return sample + (probs - probs.detach())  # exactly one-hot forward, as DreamerV2's; the gradient of probs

    def entropy(self) -> Tensor:
        """Entropy summed over the ``S`` variables, shape ``(...)``."""
        log_probs = self.logits if self.normalised else log_softmax(self.logits)
        return -(log_probs.exp() * log_probs).sum(dim=(-2, -1))


def categorical_kl(lhs_logits: Tensor, rhs_logits: Tensor, normalised: bool = False) -> Tensor:
    """``KL[lhs || rhs]`` of independent categoricals, summed over ``S`` and ``K``.

    Shapes: ``(..., S, K)`` each, returns ``(...)``. ``normalised``: both are log-probabilities already (as the
    RSSM's are), used as they are; the same value and, to whatever normalised them, the same gradient (see
    :class:`OneHotCategorical`), without two more (log-)softmax passes each way.
    """
    if normalised:
        lhs_log, rhs_log = lhs_logits.float(), rhs_logits.float()
    else:
        lhs_log, rhs_log = log_softmax(lhs_logits.float()), log_softmax(rhs_logits.float())
    return (lhs_log.exp() * (lhs_log - rhs_log)).sum(dim=(-2, -1))


class TruncatedNormal:
    """Normal distribution truncated to ``[low, high]``, independent over the last (action) dimension.

    DreamerV2's actor distribution for continuous control. ``loc`` and ``scale`` have shape ``(..., A)``;
    ``log_prob`` and ``entropy`` sum over ``A`` and return ``(...)``. ``rsample`` is reparameterised by the
    inverse CDF: ``x = loc + scale * Phi^-1(Phi(alpha) + u * (Phi(beta) - Phi(alpha)))`` with ``u ~ U(0, 1)``,
    so gradients reach ``loc`` and ``scale``; samples are then clipped ``clip`` inside the bounds with a
    straight-through gradient (as DreamerV2 does).
    """

    def __init__(self, loc: Tensor, scale: Tensor, low: float = -1.0, high: float = 1.0, clip: float = 1e-6) -> None:
        self.loc = loc
        self.scale = scale
        self.low = low
        self.high = high
        self.clip = clip
        self._alpha = (low - loc) / scale
        self._beta = (high - loc) / scale
        self._cdf_alpha = torch.special.ndtr(self._alpha)
        self._mass = (torch.special.ndtr(self._beta) - self._cdf_alpha).clamp_min(1e-8)

    @property
    def mode(self) -> Tensor:
        """The most likely action: ``loc`` clamped to the bounds, shape ``(..., A)``."""
        return self.loc.clamp(self.low, self.high)

    @property
    def mean(self) -> Tensor:
        """``loc + scale * (phi(alpha) - phi(beta)) / Z``, shape ``(..., A)``."""
        return self.loc + self.scale * (_std_normal_pdf(self._alpha) - _std_normal_pdf(self._beta)) / self._mass

    def rsample(self, generator: torch.Generator | None = None) -> Tensor:
        """Reparameterised sample in ``[low + clip, high - clip]``, shape ``(..., A)`` (``generator``: where the
        random numbers come from, torch's default when None)."""
        uniform = torch.rand(self.loc.shape, generator=generator, dtype=self.loc.dtype, device=self.loc.device)
        tiny = torch.finfo(self.loc.dtype).eps
        quantile = (self._cdf_alpha + uniform * self._mass).clamp(tiny, 1.0 - tiny)
        sample = self.loc + self.scale * torch.special.ndtri(quantile)
        clipped = sample.clamp(self.low + self.clip, self.high - self.clip)
        return sample + (clipped - sample).detach()

    def sample(self, generator: torch.Generator | None = None) -> Tensor:
        """Sample without gradient, shape ``(..., A)``."""
        with torch.no_grad():
            return self.rsample(generator)

    def log_prob(self, value: Tensor) -> Tensor:
        """Log-density summed over actions, shape ``(...)`` (``value`` must lie inside the bounds)."""
        z = (value - self.loc) / self.scale
        log_density = -0.5 * z.square() - _LOG_SQRT_2PI - self.scale.log() - self._mass.log()
        return log_density.sum(-1)

    def entropy(self) -> Tensor:
        """``log(sqrt(2 pi e) scale Z) + (alpha phi(alpha) - beta phi(beta)) / (2 Z)`` summed over actions."""
        pdf_alpha = _std_normal_pdf(self._alpha)
        pdf_beta = _std_normal_pdf(self._beta)
        entropy = (
            _LOG_SQRT_2PI
            + 0.5
            + self.scale.log()
            + self._mass.log()
            + (self._alpha * pdf_alpha - self._beta * pdf_beta) / (2.0 * self._mass)
        )
        return entropy.sum(-1)


class TanhNormal:
    """Normal distribution squashed by ``tanh`` into ``(-1, 1)``, independent over the last dimension.

    ``loc`` and ``scale`` have shape ``(..., A)``. The entropy has no closed form: :meth:`entropy` returns the
    one-sample estimate ``-log_prob(rsample())`` (as DreamerV1/V2 do), shape ``(...)``.
    """

    def __init__(self, loc: Tensor, scale: Tensor) -> None:
        self.loc = loc
        self.scale = scale

    @property
    def mode(self) -> Tensor:
        """``tanh(loc)``, shape ``(..., A)`` (the squashed Gaussian mode, a standard approximation)."""
        return torch.tanh(self.loc)

    @property
    def mean(self) -> Tensor:
        """``tanh(loc)`` (approximation of the mean), shape ``(..., A)``."""
        return torch.tanh(self.loc)

    def rsample(self, generator: torch.Generator | None = None) -> Tensor:
        """Reparameterised sample, shape ``(..., A)`` (random numbers from ``generator``, torch's default when None)."""
        return torch.tanh(self.loc + self.scale * _standard_normal(self.loc, generator))

    def sample(self, generator: torch.Generator | None = None) -> Tensor:
        """Sample without gradient, shape ``(..., A)``."""
        with torch.no_grad():
            return self.rsample(generator)

    def log_prob(self, value: Tensor) -> Tensor:
        """Log-density of the squashed sample summed over actions, shape ``(...)``."""
        value = value.clamp(-1.0 + 1e-6, 1.0 - 1e-6)
        pre = torch.atanh(value)
        z = (pre - self.loc) / self.scale
        log_normal = -0.5 * z.square() - _LOG_SQRT_2PI - self.scale.log()
        # log |d tanh(x)/dx| = log(1 - tanh(x)^2) = 2 * (log 2 - x - softplus(-2x)), stable for large |x|.
        log_det = 2.0 * (math.log(2.0) - pre - F.softplus(-2.0 * pre))
        return (log_normal - log_det).sum(-1)

    def entropy(self) -> Tensor:
        """One-sample entropy estimate ``-log_prob(x)``, ``x ~ rsample()``, shape ``(...)``."""
        pre = self.loc + self.scale * torch.randn_like(self.loc)
        z = (pre - self.loc) / self.scale
        log_normal = -0.5 * z.square() - _LOG_SQRT_2PI - self.scale.log()
        log_det = 2.0 * (math.log(2.0) - pre - F.softplus(-2.0 * pre))
        return -(log_normal - log_det).sum(-1)


class Normal:
    """Normal distribution, independent over the last (action) dimension: DreamerV3's continuous actor.

    ``loc`` and ``scale`` have shape ``(..., A)``; ``log_prob`` and ``entropy`` sum over ``A`` and return ``(...)``.
    Samples are not bounded: the agent clips the actions it executes, imagination uses them as drawn.
    """

    def __init__(self, loc: Tensor, scale: Tensor) -> None:
        self.loc = loc
        self.scale = scale

    @property
    def mode(self) -> Tensor:
        """``loc``, shape ``(..., A)``."""
        return self.loc

    @property
    def mean(self) -> Tensor:
        """``loc``, shape ``(..., A)``."""
        return self.loc

    def rsample(self, generator: torch.Generator | None = None) -> Tensor:
        """Reparameterised sample ``loc + scale * eps``, shape ``(..., A)`` (``eps`` from ``generator``, torch's
        default when None)."""
        return self.loc + self.scale * _standard_normal(self.loc, generator)

    def sample(self, generator: torch.Generator | None = None) -> Tensor:
        """Sample without gradient, shape ``(..., A)``."""
        with torch.no_grad():
            return self.rsample(generator)

    def log_prob(self, value: Tensor) -> Tensor:
        """Log-density summed over actions, shape ``(...)``."""
        z = (value - self.loc) / self.scale
        return (-0.5 * z.square() - _LOG_SQRT_2PI - self.scale.log()).sum(-1)

    def entropy(self) -> Tensor:
        """``log(sqrt(2 pi e) scale)`` summed over actions, shape ``(...)``."""
        return (_LOG_SQRT_2PI + 0.5 + self.scale.log()).sum(-1)


def _standard_normal(like: Tensor, generator: torch.Generator | None) -> Tensor:
    """Standard normal numbers shaped like ``like`` (``torch.randn_like``'s draw, from ``generator`` if given)."""
    return torch.randn(like.shape, generator=generator, dtype=like.dtype, device=like.device)


def _std_normal_pdf(x: Tensor) -> Tensor:
    """Standard normal density, elementwise."""
    return torch.exp(-0.5 * x.square() - _LOG_SQRT_2PI)
