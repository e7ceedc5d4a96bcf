"""What issue 61 added to CoWorld's terms, through the agents' real update methods: where Eq. 6's cap binds at other
``zeta`` (measured, without effect), Eq. 4 and Eq. 5 as the later paper and the release write them, and the
target-policy critic as the cap."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor

from coworld.agents.coworld import PROBE_ZETAS, CoWorld
from coworld.config import make_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _agent(*overrides: str, preset: str = "tiny") -> CoWorld:
    torch.manual_seed(0)
    return CoWorld(config=make_config(preset, ["device=cpu", *overrides]), action_size=2, device="cpu")


def _capture_objective(agent: CoWorld) -> list[dict[str, Tensor]]:
    """Record what the target critic step's objective is given and what it reads from the cap's critic."""
    calls: list[dict[str, Tensor]] = []
    original = agent.target.train_actor_critic

    def spy(post: Any, objective: Any = None, **kwargs: Any) -> Any:
        def recording(feat: Tensor, value: Any, target: Tensor, weight: Tensor) -> Any:
            calls.append({"feat": feat.detach(), "value": value.mean.detach()})
            return objective(feat, value, target, weight)

        return original(post, recording, **kwargs)

    agent.target.train_actor_critic = spy
    return calls


def test_each_target_update_measures_where_the_cap_would_bind_at_other_zetas(target_batch) -> None:
    agent = _agent("coworld.align=false", "coworld.zeta=1")
    with torch.no_grad():  # a source critic of 0: the share where zeta * v_T > 0 differs from zeta to zeta only by ties
        for param in agent.source.actor_critic.critic.parameters():
            param.zero_()
        agent.target.actor_critic.critic.mlp.net[-1].bias.fill_(0.01)  # values around 0, on both sides of it
    calls = _capture_objective(agent)
    batch = target_batch(b=2, t=4)
    metrics = agent.train_target(batch)
    value = calls[0]["value"]
    for zeta in PROBE_ZETAS:
        assert metrics[f"target/coworld/binds_zeta_{zeta:g}"] == pytest.approx(float((zeta * value > 0).float().mean()))
    assert metrics["target/coworld/maxmin_active"] == pytest.approx(float((value > 0).float().mean()))


def test_the_target_policy_critic_is_the_cap_and_learns_the_target_actors_value_in_the_source_model(
    target_batch,
) -> None:
    agent = _agent("coworld.align=false", "coworld.cap_critic=target_policy", "train.actor_warmup=0")
    assert agent.policy_value is not None and agent.cap_critic is agent.policy_value.critic
    before = [p.detach().clone() for p in agent.policy_value.critic.parameters()]
    metrics = agent.train_source(target_batch(b=2, t=4), agent.target.prepare(target_batch(b=2, t=4)))
    assert "policy_value/loss" in metrics
    assert any(not torch.equal(b, p) for b, p in zip(before, agent.policy_value.critic.parameters(), strict=True))
    calls = _capture_objective(agent)
    metrics = agent.train_target(target_batch(b=2, t=4))
    with torch.no_grad():
        capped = agent.policy_value.critic(calls[0]["feat"]).mean
        own = agent.source.actor_critic.critic(calls[0]["feat"]).mean
    assert not torch.allclose(capped, own)
    assert metrics["target/coworld/source_value"] == pytest.approx(float(capped.mean()), rel=1e-5)


def test_the_source_agent_trains_exactly_as_without_the_target_policy_critic(target_batch) -> None:
    """The option adds a critic; the source agent's own world model, actor and critic, and the target agent, are
    trained bit for bit as before (the new critic's imagination draws its numbers off the record)."""
    plain = _agent("coworld.align=false")
    capped = _agent("coworld.align=false", "coworld.cap_critic=target_policy")
    for step in range(3):
        batches = [target_batch(b=2, t=4) for _ in range(2)]
        for agent in (plain, capped):
            torch.manual_seed(step)
            agent.train_source(batches[0], agent.target.prepare(batches[1]))
    for name in ("world_model", "actor_critic"):
        for a, b in zip(
            getattr(plain.source, name).state_dict().values(),
            getattr(capped.source, name).state_dict().values(),
            strict=True,
        ):
            assert torch.equal(a, b), name
    assert capped.policy_value is not None and plain.policy_value is None
    state = capped.state_dict()
    twin = _agent("coworld.align=false", "coworld.cap_critic=target_policy")
    twin.load_state_dict(state)
    for a, b in zip(twin.policy_value.critic.parameters(), capped.policy_value.critic.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize(("form", "on_pred"), [("table3", 0.3), ("later", 0.7)])
def test_eq5_with_eta_weighs_the_source_and_target_reward_terms_at_the_reward_scale(
    form: str, on_pred: float, target_batch
) -> None:
    """``eta * s * L_S + (1 - eta) * s * L_T``, eta moving linearly from eta_start to eta_end over the run's source
    updates, and Eq. 4's label ``k * pred + (1 - k) * r_T`` or ``(1 - k) * pred + k * r_T`` by ``coworld.relabel``."""
    overrides = [
        "coworld.align=false",
        "coworld.value_reg=false",
        "coworld.k=0.3",
        f"coworld.relabel={form}",
        "coworld.reward_mix=eta",
        "coworld.eta_start=1.0",
        "coworld.eta_end=0.2",
        "coworld.iterations=2",
        "coworld.source_updates=4",
        "world_model.reward_scale=2.0",
    ]
    agent = _agent(*overrides)
    agent.relabelled = 3  # 3 of the run's 8 source updates done: eta = 1 + (0.2 - 1) * 3 / 8 = 0.7
    source_batch, relabel_batch = target_batch(b=2, t=4), target_batch(b=2, t=4)
    prepared = agent.target.prepare(relabel_batch)
    seen: dict[str, Any] = {}
    original = agent.source.train_world_model

    def spy(batch: Any, extra_loss: Any = None) -> Any:
        def recording(batch_t: dict[str, Tensor], aux: dict[str, Any]) -> dict[str, Tensor]:
            state = torch.get_rng_state()
            terms = extra_loss(batch_t, aux)
            torch.set_rng_state(state)  # the hook's own pass of the target batch, drawn again
            wm = agent.source.world_model
            post, _, _ = wm.observe(prepared)
            pred = wm.reward_head(wm.features(post)).mean.detach()
            label = on_pred * pred + (1.0 - on_pred) * prepared["reward"]
            target_term = (0.5 * (pred - label).square()).mean()
            source_term = (0.5 * (aux["reward_head"].mean - batch_t["reward"]).square()).mean()
            seen.update(
                terms={k: v.detach() for k, v in terms.items()}, target=target_term, source=source_term.detach()
            )
            return terms

        return original(batch, recording)

    agent.source.train_world_model = spy
    metrics = agent.train_source(source_batch, prepared)
    eta, scale = 0.7, 2.0
    assert metrics["coworld/eta"] == pytest.approx(eta)
    assert float(seen["terms"]["relabel"]) == pytest.approx((1 - eta) * scale * float(seen["target"]), rel=1e-4)
    assert float(seen["terms"]["eta_mix"]) == pytest.approx((eta - 1) * scale * float(seen["source"]), rel=1e-4)
    # with the world model's own scale * L_S, the loss holds eta * s * L_S + (1 - eta) * s * L_T
    assert metrics["coworld/relabel_reward_loss"] == pytest.approx(float(seen["target"]), rel=1e-4)
    assert agent.relabelled == 4


def test_eq5_eta_runs_from_start_to_end_over_the_runs_source_updates() -> None:
    from coworld.losses.coworld import reward_mix_eta

    steps = [reward_mix_eta(done, 10, 1.0, 0.1) for done in (0, 5, 10, 20)]
    np.testing.assert_allclose(steps, [1.0, 0.55, 0.1, 0.1])
    assert reward_mix_eta(7, 10, 0.9875, 0.9875) == 0.9875


@pytest.mark.parametrize("form", ["shift", "on_mean"])
def test_a_twohot_target_critic_is_trained_with_the_configured_form_of_eq6(target_batch, form: str) -> None:
    """The ``cpu`` preset's two-hot critic, through the real target update: 'shift' (the default) fits the
    lambda-return lowered by alpha * zeta where the cap binds, 'on_mean' adds the term on the critic's mean."""
    agent = _agent("coworld.align=false", "train.actor_warmup=0", f"coworld.cap_form={form}", preset="cpu")
    cfg = agent.config.coworld
    assert agent.config.actor_critic.critic_dist == "twohot"
    with torch.no_grad():  # a source critic far below the target critic's 0: the cap binds on every state
        agent.source.actor_critic.critic.mlp.net[-1].bias[100] = 30.0
    calls: list[dict[str, Any]] = []
    original = agent.target.train_actor_critic

    def spy(post: Any, objective: Any = None, **kwargs: Any) -> Any:
        def recording(feat: Tensor, value: Any, target: Tensor, weight: Tensor) -> Any:
            out, metrics = objective(feat, value, target, weight)
            calls.append({"value": value, "target": target, "weight": weight, "out": out, "metrics": metrics})
            return out, metrics

        return original(post, recording, **kwargs)

    agent.target.train_actor_critic = spy
    agent.train_target(target_batch(b=2, t=4))
    call = calls[0]
    value, target, weight = call["value"], call["target"].detach(), call["weight"]
    assert float(call["metrics"]["coworld/maxmin_active"]) == 1.0
    with torch.no_grad():
        if form == "shift":
            expected = -weight * value.log_prob(target - cfg.alpha * cfg.zeta)
        else:
            expected = weight * (-value.log_prob(target) + cfg.alpha * cfg.zeta * value.mean)
    torch.testing.assert_close(call["out"].detach(), expected)
