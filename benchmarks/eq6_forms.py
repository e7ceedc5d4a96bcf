"""Where a critic head settles under Eq. 6, by critic distribution and ``coworld.cap_form``.

A head with one output per state (4 states) is fitted by Adam (400 steps, learning rate 1 falling linearly to 0) to a
fixed lambda-return ``V`` under :func:`coworld.losses.coworld.regularised_critic_loss`, with a cap ``v_S`` below
``V - alpha * zeta`` so the term binds at the paper's fixed point. The paper's term settles the value ``alpha * zeta``
below ``V``; a form that clamps settles at or under the cap instead.

    .venv/bin/python benchmarks/eq6_forms.py
"""

from __future__ import annotations

import torch
from torch import nn

from coworld.distributions import TWOHOT_BINS, head_distribution
from coworld.losses.coworld import CAP_FORMS, regularised_critic_loss

RETURN = 44.0
"""The cap study's critic level at the end of its uncapped runs."""
CAPS = (10.0, 30.0, 40.0, float("-inf"))
ALPHA, ZETA = 0.2, 1.0
STEPS = 400


def settle(dist: str, form: str, cap: float) -> float:
    """The fitted head's mean value, averaged over its 4 states."""
    torch.manual_seed(0)
    head = nn.Linear(4, TWOHOT_BINS if dist == "twohot" else 1)
    nn.init.zeros_(head.weight)
    nn.init.zeros_(head.bias)
    optimiser = torch.optim.Adam(head.parameters(), lr=1.0)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimiser, lambda step: 1.0 - step / STEPS)
    states, ones = torch.eye(4), torch.ones(1, 4)
    for _ in range(STEPS):
        critic = head_distribution(head(states)[None], dist)
        loss = regularised_critic_loss(critic, RETURN * ones, ones, cap * ones, ALPHA, ZETA, form).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
    with torch.no_grad():
        return float(head_distribution(head(states)[None], dist).mean.mean())


def main() -> None:
    print(f"lambda-return {RETURN}, alpha {ALPHA}, zeta {ZETA}: the paper's fixed point {RETURN - ALPHA * ZETA}")
    print(f"| critic | cap_form | {' | '.join(f'cap {cap:g}' for cap in CAPS)} |")
    print(f"|---|---|{'---:|' * len(CAPS)}")
    for dist in ("gaussian", "twohot"):
        for form in CAP_FORMS:
            cells = " | ".join(f"{settle(dist, form, cap):.4g}" for cap in CAPS)
            print(f"| {dist} | {form} | {cells} |")


if __name__ == "__main__":
    main()
