"""The distributions against closed forms, numerical integrals and autograd."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from coworld.distributions import (
    Bernoulli,
    OneHotCategorical,
    TanhNormal,
    TruncatedNormal,
    UnitGaussian,
    categorical_kl,
    exponential_noise,
    log_softmax,
    softmax,
)


def test_straight_through_sample_is_one_hot_with_probability_gradient() -> None:
    logits = torch.randn(4, 3, 5, requires_grad=True)
    weights = torch.randn(4, 3, 5)
    sample = OneHotCategorical(logits).rsample()
    # Forward value is exactly one-hot (``sample + (probs - probs)``, with no rounding of ``(sample + probs) - probs``).
    hard = sample.detach().round()
    assert torch.equal(sample.detach(), hard)
    assert torch.equal(hard.sum(-1), torch.ones(4, 3))
    (grad_sample,) = torch.autograd.grad((weights * sample).sum(), logits)
    (grad_probs,) = torch.autograd.grad((weights * torch.softmax(logits, -1)).sum(), logits)
    torch.testing.assert_close(grad_sample, grad_probs)


def test_exponential_noise_draws_what_exponential_draws() -> None:
    shape = (3, 1000, 7)
    want = torch.empty(shape).exponential_(generator=torch.Generator().manual_seed(5))
    got = exponential_noise(shape, "cpu", torch.Generator().manual_seed(5))
    assert got.dtype == torch.float32 and got.shape == shape
    assert torch.equal(got, want)
    torch.manual_seed(6)
    want = torch.empty(shape).exponential_()
    torch.manual_seed(6)
    assert torch.equal(exponential_noise(shape), want)  # the default generator, on the default device


def test_one_hot_samples_follow_the_probabilities() -> None:
    logits = torch.log(torch.tensor([0.1, 0.2, 0.7])).expand(20000, 1, 3)
    freq = OneHotCategorical(logits).rsample().detach().mean(dim=(0, 1))
    torch.testing.assert_close(freq, torch.tensor([0.1, 0.2, 0.7]), atol=0.02, rtol=0)


def test_categorical_kl_matches_definition_and_is_zero_for_equal() -> None:
    p, q = torch.randn(2, 4, 6), torch.randn(2, 4, 6)
    lp, lq = F.log_softmax(p, -1), F.log_softmax(q, -1)
    expected = (lp.exp() * (lp - lq)).sum(dim=(-2, -1))
    torch.testing.assert_close(categorical_kl(p, q), expected)
    torch.testing.assert_close(categorical_kl(p, p), torch.zeros(2), atol=1e-6, rtol=0)


def test_unit_gaussian_and_bernoulli_log_probs() -> None:
    mean, value = torch.randn(3, 2, 4), torch.randn(3, 2, 4)
    torch.testing.assert_close(
        UnitGaussian(mean, event_dims=2).log_prob(value), -0.5 * ((value - mean) ** 2).sum((1, 2))
    )
    logits, target = torch.randn(5), torch.tensor([0.0, 1.0, 1.0, 0.0, 0.5])
    p = torch.sigmoid(logits)
    torch.testing.assert_close(Bernoulli(logits).log_prob(target), target * p.log() + (1 - target) * (1 - p).log())


def _grid(n: int = 20001) -> tuple[torch.Tensor, float]:
    x = torch.linspace(-1 + 1e-6, 1 - 1e-6, n, dtype=torch.float64)
    return x, float(x[1] - x[0])


def test_truncated_normal_density_entropy_and_mean_match_numerical_integrals() -> None:
    loc, scale = torch.tensor([[0.7]], dtype=torch.float64), torch.tensor([[0.4]], dtype=torch.float64)
    dist = TruncatedNormal(loc, scale)
    x, dx = _grid()
    log_p = torch.stack([dist.log_prob(v.reshape(1, 1)) for v in x[::20]]).squeeze()
    density = log_p.exp()
    step = dx * 20
    assert abs(float(density.sum() * step) - 1.0) < 2e-3
    assert abs(float(-(density * log_p).sum() * step) - float(dist.entropy())) < 5e-3
    assert abs(float((density * x[::20]).sum() * step) - float(dist.mean)) < 5e-3


def test_truncated_normal_samples_stay_in_bounds_and_are_reparameterised() -> None:
    loc = torch.tensor([-0.95, 0.0, 0.95]).repeat(4000, 1).requires_grad_()
    scale = torch.full((4000, 3), 0.5, requires_grad=True)
    dist = TruncatedNormal(loc, scale)
    sample = dist.rsample()
    assert sample.min() > -1 and sample.max() < 1
    torch.testing.assert_close(sample.detach().mean(0), dist.mean[0].detach(), atol=0.03, rtol=0)
    sample.sum().backward()
    assert loc.grad is not None and loc.grad.abs().min() > 0
    assert scale.grad is not None and scale.grad.abs().sum() > 0
    assert torch.equal(dist.mode, loc.detach())


def test_tanh_normal_density_integrates_to_one_and_matches_samples() -> None:
    dist = TanhNormal(torch.tensor([[0.3]], dtype=torch.float64), torch.tensor([[0.6]], dtype=torch.float64))
    x, dx = _grid()
    density = torch.stack([dist.log_prob(v.reshape(1, 1)) for v in x[::20]]).squeeze().exp()
    assert abs(float(density.sum() * dx * 20) - 1.0) < 5e-3
    big = TanhNormal(torch.full((20000, 1), 0.3), torch.full((20000, 1), 0.6))
    samples = big.rsample()
    numeric_mean = float((density * x[::20]).sum() * dx * 20)
    assert abs(float(samples.mean()) - numeric_mean) < 0.02
    assert math.isfinite(float(big.entropy().mean()))


def test_symlog_and_symexp_invert_each_other() -> None:
    from coworld.distributions import symexp, symlog

    x = torch.tensor([-1e6, -3.0, -0.5, 0.0, 0.5, 3.0, 1e6], dtype=torch.float64)
    torch.testing.assert_close(symexp(symlog(x)), x)
    torch.testing.assert_close(symlog(torch.tensor([math.e - 1.0, -(math.e - 1.0)])), torch.tensor([1.0, -1.0]))


def test_twohot_encoding_splits_by_distance_and_its_expected_bin_is_the_symlog() -> None:
    from coworld.distributions import TWOHOT_BINS, TwoHotSymlog, symlog

    dist = TwoHotSymlog(torch.zeros(5, TWOHOT_BINS))
    value = torch.tensor([0.0, 0.3, -7.0, 123.0, 1e12])
    encoding = dist.twohot(value)
    assert encoding.shape == (5, TWOHOT_BINS)
    torch.testing.assert_close(encoding.sum(-1), torch.ones(5))
    assert int((encoding > 0).sum(-1).max()) <= 2  # two neighbouring bins at most
    inside = symlog(value[:4])
    torch.testing.assert_close((encoding[:4] * dist.bins).sum(-1), inside, atol=1e-5, rtol=0)
    assert float(encoding[4, -1]) == 1.0  # beyond the last bin: all on it
    # Bins are 40 / 254 apart: 0 sits on the middle bin exactly.
    assert float(encoding[0, TWOHOT_BINS // 2]) == 1.0


def test_twohot_mean_and_log_prob_known_answers() -> None:
    from coworld.distributions import TWOHOT_BINS, TwoHotSymlog

    uniform = TwoHotSymlog(torch.zeros(3, TWOHOT_BINS))
    torch.testing.assert_close(uniform.mean, torch.zeros(3), atol=1e-5, rtol=0)  # symmetric bins: symexp(0)
    torch.testing.assert_close(
        uniform.log_prob(torch.tensor([0.0, 5.0, -2.0])), torch.full((3,), -math.log(TWOHOT_BINS))
    )
    # Logits that put (almost) all mass on the encoding of a value recover it as the mean.
    value = torch.tensor([4.2, -0.7])
    peaked = TwoHotSymlog(torch.log(TwoHotSymlog(torch.zeros(2, TWOHOT_BINS)).twohot(value) + 1e-12))
    torch.testing.assert_close(peaked.mean, value, atol=1e-3, rtol=1e-4)
    assert float(peaked.log_prob(value).min()) > float(peaked.log_prob(value + 3.0).max())
    # Training the logits by the log-likelihood moves the mean to the target.
    logits = torch.zeros(1, TWOHOT_BINS, requires_grad=True)
    opt = torch.optim.Adam([logits], lr=0.1)
    for _ in range(300):
        opt.zero_grad()
        (-TwoHotSymlog(logits).log_prob(torch.tensor([30.0]))).sum().backward()
        opt.step()
    assert abs(float(TwoHotSymlog(logits.detach()).mean) - 30.0) < 1.0  # from 0


@pytest.mark.parametrize("shape", [(5, 8, 8), (64, 8, 8), (3, 4, 7, 3), (3, 50, 4, 6), (6, 4, 32), (9, 1, 8), (8,)])
def test_softmax_helpers_are_torch_softmax_with_its_gradient(shape: tuple[int, ...]) -> None:
    """The (log-)softmax that short class dimensions take through a copy with the classes first (and every other
    shape straight) has torch's values and gradients."""
    x = torch.randn(*shape, dtype=torch.float64, requires_grad=True)
    grad = torch.randn(*shape, dtype=torch.float64)
    for mine, theirs in ((softmax, torch.softmax), (log_softmax, torch.log_softmax)):
        got, want = mine(x), theirs(x, -1)
        assert got.shape == want.shape
        torch.testing.assert_close(got, want)
        torch.testing.assert_close(torch.autograd.grad(got, x, grad)[0], torch.autograd.grad(want, x, grad)[0])


def test_categorical_kl_of_normalised_logits_has_the_value_and_gradient_of_the_full_one() -> None:
    """Log-probabilities used as they are give the KL and, to the raw outputs they were normalised from, the
    gradient that normalising them again gives."""
    raw = torch.randn(2, 2, 4, 8, dtype=torch.float64, requires_grad=True)
    lhs, rhs = log_softmax(raw[0]), log_softmax(raw[1])
    got, want = categorical_kl(lhs, rhs, normalised=True), categorical_kl(lhs, rhs)
    torch.testing.assert_close(got, want)
    weights = torch.randn(2)
    torch.testing.assert_close(
        torch.autograd.grad((got * weights).sum(), raw, retain_graph=True)[0],
        torch.autograd.grad((want * weights).sum(), raw)[0],
    )
