"""Eq. 6 means one thing on every critic the config offers.

On a binding state (``zeta * v_T > v_S``) the paper's term has gradient ``alpha * zeta`` in ``v_T`` on its unit
Gaussian critic, so a critic fitted to a fixed lambda-return settles ``alpha * zeta`` below it: a soft push, never a
clamp at the cap. These tests fit a critic head of each distribution ``actor_critic.critic_dist`` offers to a fixed
return with the term binding throughout, and check where it settles; the form that reads the term on a two-hot
critic's mean (``coworld.cap_form='on_mean'``) fails the same check.
"""

from __future__ import annotations

import typing

import pytest
import torch
from torch import nn

from coworld.config import ActorCriticConfig, CoWorldConfig, make_config
from coworld.distributions import TWOHOT_BINS, TwoHotSymlog, UnitGaussian, head_distribution
from coworld.losses.coworld import CAP_FORMS, regularised_critic_loss, shifted_return


def _choices(section: type, name: str) -> tuple[str, ...]:
    """The values a config field accepts (its ``OneOf``), so a distribution added to the config is tested too."""
    hint = typing.get_type_hints(section, include_extras=True)[name]
    return next(meta.choices for meta in hint.__metadata__ if hasattr(meta, "choices"))


CRITIC_DISTS = _choices(ActorCriticConfig, "critic_dist")

CASES = (
    # (lambda-return, cap v_S, alpha, zeta): the cap below V - alpha * zeta, so the term binds at the fixed point
    (44.0, 10.0, 0.2, 1.0),  # the cap study's critic level under a low cap
    (44.0, 40.0, 0.2, 1.0),  # a cap just under the return
    (44.0, float("-inf"), 0.2, 1.0),  # no cap at all: the term binds everywhere
    (44.0, 5.0, 0.5, 3.0),  # zeta * v_T above the cap
    (-3.0, -50.0, 0.2, 1.0),  # negative values
    (0.5, 0.0, 0.2, 1.0),  # a small return, near symlog's linear part
)


def _settle(dist: str, form: str, value: float, cap: float, alpha: float, zeta: float) -> torch.Tensor:
    """A critic head (one output per state of 4) fitted by Adam to ``value`` under Eq. 6 with the cap ``cap``;
    returns its mean on the 4 states."""
    states = torch.eye(4)
    head = nn.Linear(4, TWOHOT_BINS if dist == "twohot" else 1)
    nn.init.zeros_(head.weight)
    nn.init.zeros_(head.bias)
    steps = 400
    optimiser = torch.optim.Adam(head.parameters(), lr=1.0)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimiser, lambda step: 1.0 - step / steps)
    target, source, weight = torch.full((1, 4), value), torch.full((1, 4), cap), torch.ones(1, 4)
    for _ in range(steps):
        critic = head_distribution(head(states)[None], dist)
        loss = regularised_critic_loss(critic, target, weight, source, alpha, zeta, form).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
    with torch.no_grad():
        return head_distribution(head(states)[None], dist).mean


def _settles_as_the_paper_says(mean: torch.Tensor, value: float, cap: float, alpha: float, zeta: float) -> bool:
    """Within 10% of ``alpha * zeta`` of ``V - alpha * zeta`` on every state, and above the cap."""
    push = alpha * zeta
    return bool(((mean - (value - push)).abs() <= 0.1 * push).all() and (zeta * mean > cap).all())


@pytest.mark.parametrize("dist", CRITIC_DISTS)
@pytest.mark.parametrize(("value", "cap", "alpha", "zeta"), CASES)
def test_a_binding_state_settles_alpha_zeta_below_its_return(
    dist: str, value: float, cap: float, alpha: float, zeta: float
) -> None:
    mean = _settle(dist, "shift", value, cap, alpha, zeta)
    assert _settles_as_the_paper_says(mean, value, cap, alpha, zeta), (dist, mean.tolist(), value - alpha * zeta)


def test_the_term_on_a_twohot_critics_mean_clamps_instead() -> None:
    """The form the cap study ran: on a two-hot critic every case above fails the same check (it sits under the
    cap, or runs to the lowest bins where nothing caps it)."""
    for value, cap, alpha, zeta in CASES:
        mean = _settle("twohot", "on_mean", value, cap, alpha, zeta)
        assert not _settles_as_the_paper_says(mean, value, cap, alpha, zeta), (value, cap, mean.tolist())
    assert float(_settle("twohot", "on_mean", 44.0, float("-inf"), 0.2, 1.0).max()) < -1e6  # runs away


@pytest.mark.parametrize("form", CAP_FORMS)
def test_the_gaussian_critics_gradient_is_the_papers_to_float_precision(form: str) -> None:
    """Either form on the Gaussian critic is the paper's loss: ``d/dv = weight * ((v - V) + alpha * zeta * active)``."""
    gen = torch.Generator().manual_seed(0)
    mean = (10 * torch.randn(15, 32, generator=gen)).requires_grad_()
    returns, source = 10 * torch.randn(15, 32, generator=gen), 10 * torch.randn(15, 32, generator=gen)
    weight = torch.rand(15, 32, generator=gen)
    alpha, zeta = 0.2, 1.5
    regularised_critic_loss(UnitGaussian(mean), returns, weight, source, alpha, zeta, form).sum().backward()
    active = (zeta * mean.detach() > source).float()
    assert 0.1 < float(active.mean()) < 0.9  # both kinds of state
    torch.testing.assert_close(mean.grad, weight * ((mean.detach() - returns) + alpha * zeta * active))


def test_the_shift_on_a_twohot_critic_is_its_cross_entropy_of_the_lowered_return() -> None:
    gen = torch.Generator().manual_seed(0)
    critic = TwoHotSymlog(torch.randn(3, 5, TWOHOT_BINS, generator=gen))
    returns, weight = 20 * torch.rand(3, 5, generator=gen), torch.rand(3, 5, generator=gen)
    source = critic.mean + torch.randn(3, 5, generator=gen)  # binding on about half the states
    lowered = shifted_return(returns, critic.mean, source, 0.3, 2.0)
    active = 2.0 * critic.mean > source
    assert active.any() and not active.all()
    torch.testing.assert_close(lowered, torch.where(active, returns - 0.6, returns))
    loss = regularised_critic_loss(critic, returns, weight, source, 0.3, 2.0)
    torch.testing.assert_close(loss, -weight * critic.log_prob(lowered))


def test_the_config_defaults_to_the_shift_and_names_both_forms() -> None:
    assert CoWorldConfig().cap_form == "shift"
    assert make_config("cpu").coworld.cap_form == "shift" and make_config("cpu").actor_critic.critic_dist == "twohot"
    assert _choices(CoWorldConfig, "cap_form") == CAP_FORMS
    with pytest.raises(ValueError, match="form must be one of shift, on_mean"):
        regularised_critic_loss(torch.zeros(1), torch.zeros(1), torch.ones(1), torch.zeros(1), 0.2, 1.0, "clamp")
