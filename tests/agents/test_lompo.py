"""LOMPO's agent: its two phases, real transitions within episodes, the penalised imagined reward, acting and
checkpoints."""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch

from coworld.agents.lompo import Lompo
from coworld.config import make_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _agent(*sets: str) -> Lompo:
    torch.manual_seed(0)
    return Lompo(config=make_config("tiny", ["device=cpu", *sets]), action_size=2)


def test_world_model_phase_then_latent_actor_critic_phase_on_the_penalised_reward(
    numpy_batch: Callable[..., Any], flat_params: Callable[..., Any]
) -> None:
    agent = _agent("lompo.model_updates=2", "lompo.weight=3.0", "lompo.tau=0.5")
    ac = agent.actor_critic
    rng = np.random.default_rng(0)
    wm, heads, actor, critic = (
        flat_params(agent.world_model),
        flat_params(agent.ensemble),
        flat_params(ac.actor),
        flat_params(ac.critic),
    )
    for _ in range(2):
        metrics = agent.train(numpy_batch(rng))
        assert "penalty/head_kl" in metrics and not any(key.startswith(("actor/", "lompo/")) for key in metrics)
    assert not torch.equal(flat_params(agent.world_model), wm) and not torch.equal(flat_params(agent.ensemble), heads)
    assert torch.equal(flat_params(ac.actor), actor) and torch.equal(
        flat_params(ac.critic), critic
    )  # phase 1 leaves them
    wm, heads, target = flat_params(agent.world_model), flat_params(agent.ensemble), flat_params(ac.target_critic)
    metrics = agent.train(numpy_batch(rng))
    assert torch.equal(flat_params(agent.world_model), wm) and torch.equal(flat_params(agent.ensemble), heads)  # frozen
    assert not torch.equal(flat_params(ac.actor), actor) and not torch.equal(flat_params(ac.critic), critic)
    # The target Q-functions moved halfway (tau 0.5) toward the stepped ones.
    torch.testing.assert_close(flat_params(ac.target_critic), 0.5 * target + 0.5 * flat_params(ac.critic))
    # The imagined transitions learnt from r - 3 * std_k log p_k(z').
    assert metrics["lompo/spread"] > 0.0
    expected = metrics["lompo/imag_reward"] - 3.0 * metrics["lompo/spread"]
    assert metrics["lompo/penalised_reward"] == pytest.approx(expected, rel=1e-4, abs=1e-5)


def test_real_transitions_stay_inside_episodes_and_pair_each_step_with_the_next_action_and_reward(
    numpy_batch: Callable[..., Any],
) -> None:
    agent = _agent("lompo.batch_size=400")
    batch = agent.to_batch(numpy_batch(np.random.default_rng(0), B=2, T=6))
    batch["is_first"][:, 3] = True  # each row holds two episodes: steps 0-2 and 3-5
    batch["reward"] = torch.tensor([[100.0 * b + t for t in range(6)] for b in range(2)])
    batch["action"] = batch["reward"][..., None].expand(2, 6, 2).clone()
    with torch.no_grad():
        post, _, _ = agent.model_path.observe(batch)
    real = agent.real_transitions(post, batch)
    feat = agent.world_model.features(post)
    reward = real["reward"]
    # Allowed (b, t + 1): t + 1 in {1, 2, 4, 5}; never onto a first step.
    assert set(reward.tolist()) == {100.0 * b + t for b in range(2) for t in (1, 2, 4, 5)}
    torch.testing.assert_close(real["action"][:, 0], reward)  # a_{t+1} with r_{t+1}
    for i in range(0, 400, 37):
        b, t = int(reward[i]) // 100, int(reward[i]) % 100
        torch.testing.assert_close(real["feat"][i], feat[b, t - 1])
        torch.testing.assert_close(real["next_feat"][i], feat[b, t])
    assert torch.equal(real["not_done"], torch.ones(400))


def test_imagined_transitions_chain_from_state_to_state(numpy_batch: Callable[..., Any]) -> None:
    agent = _agent("lompo.batch_size=12", "lompo.horizon=3")
    batch = agent.to_batch(numpy_batch(np.random.default_rng(1)))
    with torch.no_grad():
        post, _, _ = agent.model_path.observe(batch)
    imagined, seen = agent.imagined_transitions(post)
    assert imagined["feat"].shape == (12, agent.world_model.feat_size) and imagined["action"].shape == (12, 2)
    # 4 rollouts of 3 steps, step-major: step s + 1 starts where step s ended.
    torch.testing.assert_close(imagined["feat"][4:], imagined["next_feat"][:8])
    assert imagined["action"].abs().max() <= 1.0
    torch.testing.assert_close(imagined["reward"], seen["raw"] - agent.config.lompo.weight * seen["spread"])


def test_policy_acts_with_the_actor_and_values_with_the_smaller_q() -> None:
    agent = _agent("lompo.expl_noise=0.5")
    obs = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    action, state = agent.policy(obs, mode="eval")
    latent, _ = state
    feat = agent.world_model.features(latent)
    with torch.no_grad():
        expected = agent.actor_critic.actor.action(feat)
        q1, q2 = agent.actor_critic.q(feat, expected)
    np.testing.assert_allclose(action, expected.numpy(), atol=1e-6)
    np.testing.assert_allclose(agent.value(state), torch.minimum(q1, q2).numpy(), atol=1e-6)
    noisy, _ = agent.policy(obs, mode="train")  # the same latent filter, plus noise of std 0.5, clipped
    assert np.abs(noisy).max() <= 1.0 and not np.allclose(noisy, action)


def test_state_dict_round_trip_through_weights_only_load(
    numpy_batch: Callable[..., Any], flat_params: Callable[..., Any]
) -> None:
    agent = _agent("lompo.model_updates=1")
    rng = np.random.default_rng(0)
    for _ in range(2):
        agent.train(numpy_batch(rng))
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)
    clone = _agent("lompo.model_updates=1")
    clone.load_state_dict(torch.load(buffer, weights_only=True))
    assert clone.updates == 2 and torch.equal(flat_params(clone.actor_critic), flat_params(agent.actor_critic))
    batch = numpy_batch(np.random.default_rng(1))
    torch.manual_seed(3)
    expected = agent.train(batch)
    torch.manual_seed(3)
    assert clone.train(batch) == pytest.approx(expected)


def test_the_latent_actor_critic_learns_the_best_action_of_a_one_step_task(monkeypatch) -> None:
    """The update alone, on transitions that end at once with reward ``-||a - (1, -1)||^2``: Q learns the reward and
    the actor climbs it to the best action, a corner of the action box, from around the centre where it starts. (An
    optimum inside the box is overshot: the tanh actor runs to the bound while Q is still about linear, and its
    gradient vanishes there, as a DDPG actor's does.)"""
    agent = _agent("lompo.batch_size=64")
    feat_size, best = agent.world_model.feat_size, torch.tensor([1.0, -1.0])
    gen = torch.Generator().manual_seed(0)

    def transitions() -> dict[str, torch.Tensor]:
        feat = torch.randn(64, feat_size, generator=gen)
        action = torch.rand(64, 2, generator=gen) * 2 - 1
        reward = -(action - best).square().sum(-1)
        return {"feat": feat, "action": action, "next_feat": feat, "reward": reward, "not_done": torch.zeros(64)}

    monkeypatch.setattr(agent, "real_transitions", lambda post, batch: transitions())
    seen = {"raw": torch.zeros(64), "spread": torch.zeros(64)}
    monkeypatch.setattr(agent, "imagined_transitions", lambda post: (transitions(), seen))
    probe = torch.randn(256, feat_size, generator=gen)

    def distance() -> float:
        with torch.no_grad():
            return float((agent.actor_critic.actor.action(probe) - best).norm(dim=-1).mean())

    before = distance()
    for _ in range(300):
        agent.train_latent_actor_critic({}, {})
    after = distance()
    assert after < 0.15 and after < before / 3, (before, after)
