"""Imagination, actor and critic losses, the value-regulariser hook and the slow target."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from coworld.config import Config, make_config
from coworld.distributions import Normal, TanhNormal, TruncatedNormal
from coworld.errors import ConfigError
from coworld.losses.dreamer import critic_loss, lambda_return
from coworld.models.actor_critic import ActorCritic, flatten_states
from coworld.models.networks import frozen_parameters
from coworld.models.world_model import WorldModel

from .conftest import ACTION_SIZE, random_batch


def _setup(config: Config) -> tuple[WorldModel, ActorCritic, dict[str, torch.Tensor]]:
    wm = WorldModel(config=config.world_model, action_size=ACTION_SIZE)
    ac = ActorCritic(config=config.actor_critic, feat_size=wm.feat_size, action_size=ACTION_SIZE)
    batch = random_batch(batch=2, length=3)
    post, _, _ = wm.observe(batch)
    return wm, ac, flatten_states(post)


def test_flatten_states_merges_batch_and_time(tiny: Config) -> None:
    wm = WorldModel(config=tiny.world_model, action_size=ACTION_SIZE)
    post, _, _ = wm.observe(random_batch(batch=2, length=3))
    start = flatten_states(post)
    assert start["deter"].shape == (6, tiny.world_model.deter)
    assert start["stoch"].shape == (6, tiny.world_model.stoch, tiny.world_model.classes)
    assert not start["deter"].requires_grad
    torch.testing.assert_close(start["deter"][4], post["deter"][1, 1].detach())


def test_imagine_shapes_weights_and_first_continuation(tiny: Config) -> None:
    wm, ac, start = _setup(tiny)
    horizon, n = tiny.actor_critic.horizon, 6
    is_terminal = torch.tensor([True, False, False, False, False, False])
    traj = ac.imagine(wm, start, is_terminal=is_terminal)
    assert traj["feat"].shape == (horizon + 1, n, wm.feat_size)
    assert traj["action"].shape == (horizon + 1, n, ACTION_SIZE)
    state = traj["state"]
    assert state["deter"].shape == (horizon + 1, n, tiny.world_model.deter)
    assert state["stoch"].shape == state["logits"].shape == (horizon + 1, n, wm.rssm.stoch, wm.rssm.classes)
    for key in ("deter", "stoch", "logits"):
        torch.testing.assert_close(state[key][0], start[key])
    torch.testing.assert_close(state["stoch"][1:].detach().sum(-1), torch.ones(horizon, n, wm.rssm.stoch))
    for key in ("reward", "continuation", "weight"):
        assert traj[key].shape == (horizon + 1, n)
    assert torch.equal(traj["action"][0], torch.zeros(n, ACTION_SIZE))
    assert float(traj["action"][1:].detach().abs().max()) < 1.0
    torch.testing.assert_close(traj["feat"][0], wm.features(start))
    gamma = tiny.actor_critic.discount
    cont = traj["continuation"].detach()
    assert float(cont[0, 0]) == 0.0 and float(cont[0, 1]) == pytest.approx(gamma)
    expected_weight = torch.cumprod(torch.cat([torch.ones(1, n), cont[:-1]]), dim=0)
    torch.testing.assert_close(traj["weight"], expected_weight)
    assert torch.all(traj["weight"][1:, 0] == 0.0)  # nothing after a terminal start state counts


def test_losses_use_slow_critic_lambda_returns(tiny: Config) -> None:
    wm, ac, start = _setup(tiny)
    with frozen_parameters(wm):
        traj = ac.imagine(wm, start)
        terms, metrics = ac.losses(wm, traj)
    h, n = tiny.actor_critic.horizon, 6
    assert terms["actor_terms"].shape == (h - 1, n) and terms["critic_terms"].shape == (h, n)
    assert terms["actor"].shape == () and terms["critic"].shape == ()
    slow = ac.slow_critic(traj["feat"]).mean.detach()
    expected = lambda_return(
        traj["reward"][:-1].detach(), slow[:-1], traj["continuation"][:-1].detach(), slow[-1], tiny.actor_critic.lambda_
    )
    torch.testing.assert_close(terms["target"].detach(), expected)
    value = ac.critic_value(traj["feat"][:-1].detach()).detach()
    critic = (traj["weight"][:-1] * 0.5 * (value - expected) ** 2).mean()
    torch.testing.assert_close(terms["critic"].detach(), critic)
    assert {"actor/entropy", "critic/value", "imag/return"} <= set(metrics)


def test_dynamics_gradient_reaches_actor_through_frozen_world_model(tiny: Config) -> None:
    wm, ac, start = _setup(tiny)
    with frozen_parameters(wm):
        traj = ac.imagine(wm, start)
        terms, _ = ac.losses(wm, traj)
    (terms["actor"] + terms["critic"]).backward()
    assert all(p.grad is None for p in wm.parameters())
    assert all(p.grad is None for p in ac.slow_critic.parameters())
    actor_grad = torch.cat([p.grad.flatten() for p in ac.actor.parameters()])
    critic_grad = torch.cat([p.grad.flatten() for p in ac.critic.parameters()])
    assert actor_grad.abs().sum() > 0 and critic_grad.abs().sum() > 0
    # The same with zero entropy scale: gradient then comes only from the imagined returns.
    no_ent = dataclasses.replace(tiny.actor_critic, actor_entropy=0.0)
    ac2 = ActorCritic(config=no_ent, feat_size=wm.feat_size, action_size=ACTION_SIZE)
    with frozen_parameters(wm):
        terms2, _ = ac2.losses(wm, ac2.imagine(wm, start))
    grads = torch.autograd.grad(terms2["actor"], list(ac2.actor.parameters()))
    assert sum(float(g.abs().sum()) for g in grads) > 0


def test_reinforce_actor_loss_has_no_path_through_dynamics(tiny: Config) -> None:
    config = dataclasses.replace(tiny, actor_critic=dataclasses.replace(tiny.actor_critic, actor_grad="reinforce"))
    wm, ac, start = _setup(config)
    traj = ac.imagine(wm, start)
    assert not traj["action"].requires_grad
    terms, _ = ac.losses(wm, traj)
    grads = torch.autograd.grad(terms["actor"], [*ac.actor.parameters(), *wm.rssm.parameters()], allow_unused=True)
    actor_grads = grads[: len(list(ac.actor.parameters()))]
    rssm_grads = grads[len(actor_grads) :]
    assert sum(float(g.abs().sum()) for g in actor_grads if g is not None) > 0
    assert all(g is None or float(g.abs().sum()) == 0.0 for g in rssm_grads)


def test_a_critic_objective_takes_the_critics_loss_with_its_states_value_returns_and_weights(tiny: Config) -> None:
    wm, ac, start = _setup(tiny)
    with frozen_parameters(wm):
        traj = ac.imagine(wm, start)
        seen: dict[str, torch.Tensor] = {}

        def objective(feat: torch.Tensor, value, target: torch.Tensor, weight: torch.Tensor):
            seen.update(feat=feat, value=value.mean, target=target, weight=weight)
            return critic_loss(value, target, weight) + 0.3 * weight * value.mean, {"critic/extra": value.mean.mean()}

        plain, _ = ac.losses(wm, traj)
        extra, metrics = ac.losses(wm, traj, critic_objective=objective)
    h, n = tiny.actor_critic.horizon, 6
    assert seen["feat"].shape == (h, n, wm.feat_size) and not seen["feat"].requires_grad
    assert seen["value"].requires_grad
    torch.testing.assert_close(seen["value"].detach(), ac.critic_value(traj["feat"][:-1]).detach())
    torch.testing.assert_close(seen["target"], plain["target"])
    torch.testing.assert_close(seen["weight"], traj["weight"][:-1])
    added = (traj["weight"][:-1] * 0.3 * seen["value"].detach()).mean()
    torch.testing.assert_close(extra["critic"].detach(), plain["critic"].detach() + added)
    assert "critic/extra" in metrics
    with pytest.raises(ValueError, match="critic_objective"):
        ac.losses(wm, traj, critic_objective=lambda feat, value, target, weight: (value.mean[:-1], {}))


def test_slow_target_copies_every_n_updates(tiny: Config) -> None:
    config = dataclasses.replace(tiny.actor_critic, slow_target_every=3)
    ac = ActorCritic(config=config, feat_size=8, action_size=2)
    feat = torch.randn(5, 8)

    def perturb() -> None:
        with torch.no_grad():
            for p in ac.critic.parameters():
                p.add_(torch.randn_like(p))

    perturb()
    ac.update_slow_target()  # update 0: copy
    torch.testing.assert_close(ac.slow_critic(feat).mean, ac.critic(feat).mean)
    perturb()
    copied = ac.slow_critic(feat).mean.clone()
    ac.update_slow_target()  # 1
    ac.update_slow_target()  # 2
    torch.testing.assert_close(ac.slow_critic(feat).mean, copied)
    assert not torch.allclose(ac.slow_critic(feat).mean, ac.critic(feat).mean)
    ac.update_slow_target()  # 3: copy
    torch.testing.assert_close(ac.slow_critic(feat).mean, ac.critic(feat).mean)
    assert int(ac.updates) == 4


def test_slow_target_fraction_mixes(tiny: Config) -> None:
    config = dataclasses.replace(tiny.actor_critic, slow_target_every=1, slow_target_fraction=0.25)
    ac = ActorCritic(config=config, feat_size=8, action_size=2)
    before = [p.clone() for p in ac.slow_critic.parameters()]
    with torch.no_grad():
        for p in ac.critic.parameters():
            p.add_(1.0)
    ac.update_slow_target()  # the first call copies the critic whole (DreamerV2)
    for new, fast in zip(ac.slow_critic.parameters(), ac.critic.parameters(), strict=True):
        torch.testing.assert_close(new, fast)
    before = [p.clone() for p in ac.slow_critic.parameters()]
    with torch.no_grad():
        for p in ac.critic.parameters():
            p.add_(1.0)
    ac.update_slow_target()  # later calls mix
    for old, new, fast in zip(before, ac.slow_critic.parameters(), ac.critic.parameters(), strict=True):
        torch.testing.assert_close(new, 0.75 * old + 0.25 * fast)


def test_actor_distributions_and_bad_names(tiny: Config) -> None:
    ac = ActorCritic(config=tiny.actor_critic, feat_size=8, action_size=2)
    dist = ac.actor(torch.randn(4, 8))
    assert isinstance(dist, TruncatedNormal)
    assert float(dist.scale.detach().min()) >= tiny.actor_critic.actor_min_std
    tanh = ActorCritic(
        config=dataclasses.replace(tiny.actor_critic, actor_dist="tanh_normal"), feat_size=8, action_size=2
    )
    assert isinstance(tanh.actor(torch.randn(4, 8)), TanhNormal)
    with pytest.raises(ConfigError, match="actor_dist"):
        ActorCritic(config=dataclasses.replace(tiny.actor_critic, actor_dist="gauss"), feat_size=8, action_size=2)
    with pytest.raises(ConfigError, match="actor_grad"):
        ActorCritic(config=dataclasses.replace(tiny.actor_critic, actor_grad="both"), feat_size=8, action_size=2)


def test_normal_actor_distribution_known_answers() -> None:
    loc, scale = torch.tensor([[0.5, -0.2]]), torch.tensor([[0.3, 2.0]])
    dist = Normal(loc, scale)
    reference = torch.distributions.Normal(loc, scale)
    value = torch.tensor([[0.1, 1.7]])
    torch.testing.assert_close(dist.log_prob(value), reference.log_prob(value).sum(-1))
    torch.testing.assert_close(dist.entropy(), reference.entropy().sum(-1))
    torch.manual_seed(0)
    samples = Normal(loc.expand(20000, 2), scale.expand(20000, 2)).rsample()
    torch.testing.assert_close(samples.mean(0), loc[0], atol=0.05, rtol=0)
    torch.testing.assert_close(samples.std(0), scale[0], atol=0.05, rtol=0)
    assert (samples.abs() > 1.0).any()  # not truncated: the agent clips what it executes


class _Fixed(torch.nn.Module):
    """Stands in for the actor's MLP: returns the raw outputs it was given."""

    def __init__(self, raw: torch.Tensor) -> None:
        super().__init__()
        self.raw = raw

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        return self.raw


def test_normal_actor_keeps_its_spread_between_the_bounds(tiny: Config) -> None:
    config = dataclasses.replace(tiny.actor_critic, actor_dist="normal", actor_min_std=0.1, actor_max_std=1.0)
    actor = ActorCritic(config=config, feat_size=8, action_size=2).actor
    raw_std = torch.tensor([-1e4, -3.0, 0.0, 3.0, 1e4])
    actor.mlp = _Fixed(torch.stack([torch.zeros(5), torch.full((5,), 3.0), torch.zeros(5), raw_std], dim=-1))
    dist = actor(torch.zeros(5, 8))
    torch.testing.assert_close(dist.loc, torch.tensor([0.0, math.tanh(3.0)]).expand(5, 2))
    expected = 0.9 * torch.sigmoid(raw_std + 2.0) + 0.1  # DreamerV3: starts near the top, 0.89 at raw 0
    torch.testing.assert_close(dist.scale[:, 1], expected)
    assert float(dist.scale.min()) >= 0.1 and float(dist.scale.max()) <= 1.0
    assert dist.scale[2, 1] == pytest.approx(0.8927, abs=1e-4)


def test_return_scale_is_one_without_return_norm_and_the_percentile_range_with_it(tiny: Config) -> None:
    plain = ActorCritic(config=tiny.actor_critic, feat_size=8, action_size=2)
    target = torch.linspace(0.0, 100.0, 1001)
    assert float(plain.return_scale(target)) == 1.0 and "return_range" not in plain.state_dict()
    config = dataclasses.replace(tiny.actor_critic, return_norm=True, return_norm_decay=0.5)
    ac = ActorCritic(config=config, feat_size=8, action_size=2)
    first = ac.return_scale(target)  # EMA from zero: 0.5 * (P95 - P5) = 0.5 * 90
    torch.testing.assert_close(ac.return_range, torch.tensor([2.5, 47.5]))
    assert float(first) == pytest.approx(45.0)
    second = ac.return_scale(target)  # 0.75 * 90
    assert float(second) == pytest.approx(67.5)
    small = ActorCritic(config=config, feat_size=8, action_size=2)
    assert float(small.return_scale(torch.linspace(0.0, 0.1, 11))) == 1.0  # never divides by less than 1


def test_return_norm_divides_the_actors_returns_by_the_scale(tiny: Config) -> None:
    torch.manual_seed(0)
    config = dataclasses.replace(tiny.actor_critic, return_norm=True, return_norm_decay=0.0, actor_entropy=0.0)
    ac = ActorCritic(config=config, feat_size=8, action_size=2)
    horizon, n = 5, 3
    traj = {
        "feat": torch.randn(horizon + 1, n, 8),
        "action": torch.zeros(horizon + 1, n, 2),
        "reward": 10.0 * torch.arange(horizon + 1.0)[:, None].expand(horizon + 1, n),
        "continuation": torch.full((horizon + 1, n), 0.9),
        "weight": torch.ones(horizon + 1, n),
    }
    terms, metrics = ac.losses(None, traj)
    scale = float(metrics["actor/return_scale"])
    assert scale > 1.0
    torch.testing.assert_close(terms["actor_terms"], -terms["target"][1:] / scale)


def test_zero_initialised_reward_head_and_critic_start_at_zero(tiny: Config) -> None:
    from coworld.models.world_model import WorldModel

    wm_config = dataclasses.replace(tiny.world_model, zero_init_reward=True)
    ac_config = dataclasses.replace(tiny.actor_critic, zero_init_critic=True)
    world_model = WorldModel(config=wm_config, action_size=2)
    ac = ActorCritic(config=ac_config, feat_size=world_model.feat_size, action_size=2)
    feat = torch.randn(7, world_model.feat_size)
    assert torch.equal(world_model.reward_head(feat).mean, torch.zeros(7))
    assert torch.equal(ac.critic(feat).mean, torch.zeros(7)) and torch.equal(ac.slow_critic(feat).mean, torch.zeros(7))
    plain = WorldModel(config=tiny.world_model, action_size=2)
    assert plain.reward_head(feat).mean.abs().sum() > 0  # off by default: DreamerV2's initialisation


def _traj(feat_size: int, horizon: int = 5, n: int = 3) -> dict[str, torch.Tensor]:
    return {
        "feat": torch.randn(horizon + 1, n, feat_size),
        "action": torch.zeros(horizon + 1, n, 2),
        "reward": torch.rand(horizon + 1, n),
        "continuation": torch.full((horizon + 1, n), 0.9),
        "weight": torch.ones(horizon + 1, n),
    }


def test_absmax_scales_imagined_samples_to_the_bound_and_keeps_their_gradient(tiny: Config) -> None:
    torch.manual_seed(0)
    wide = dataclasses.replace(tiny.actor_critic, actor_dist="normal", actor_min_std=3.0, actor_max_std=4.0)
    for absmax in (False, True):
        config = dataclasses.replace(tiny, actor_critic=dataclasses.replace(wide, actor_absmax=absmax))
        wm, ac, start = _setup(config)
        with frozen_parameters(wm):
            traj = ac.imagine(wm, start)
        largest = float(traj["action"].detach().abs().max())
        if absmax:
            assert largest == pytest.approx(1.0)  # at the bound, not beyond
            grads = torch.autograd.grad(traj["reward"].sum(), list(ac.actor.parameters()), allow_unused=True)
            assert sum(float(g.abs().sum()) for g in grads if g is not None) > 0
        else:
            assert largest > 2.0  # a spread of 3+ leaves [-1, 1] without it


def test_critic_target_critic_bootstraps_from_the_critic_without_training_it_through_the_actor(tiny: Config) -> None:
    torch.manual_seed(0)
    config = dataclasses.replace(tiny.actor_critic, critic_target="critic", actor_entropy=0.0)
    ac = ActorCritic(config=config, feat_size=8, action_size=2)
    with torch.no_grad():  # make the critic and its slow target differ
        for p in ac.critic.parameters():
            p.add_(0.3 * torch.randn_like(p))
    traj = _traj(8)
    terms, _ = ac.losses(None, traj)
    value = ac.critic(traj["feat"]).mean.detach()
    expected = lambda_return(traj["reward"][:-1], value[:-1], traj["continuation"][:-1], value[-1], config.lambda_)
    torch.testing.assert_close(terms["target"].detach(), expected)
    slow = ac.slow_critic(traj["feat"]).mean.detach()
    assert not torch.allclose(
        expected, lambda_return(traj["reward"][:-1], slow[:-1], traj["continuation"][:-1], slow[-1], config.lambda_)
    )
    terms["actor"].backward()
    assert all(p.grad is None for p in ac.critic.parameters())  # the actor's loss does not move the critic


def test_actor_advantage_subtracts_the_value_of_the_acting_state(tiny: Config) -> None:
    torch.manual_seed(0)
    base = dataclasses.replace(tiny.actor_critic, actor_entropy=0.0)
    plain = ActorCritic(config=base, feat_size=8, action_size=2)
    adv = ActorCritic(config=dataclasses.replace(base, actor_advantage=True), feat_size=8, action_size=2)
    adv.load_state_dict(plain.state_dict())
    traj = _traj(8)
    terms_plain, _ = plain.losses(None, traj)
    terms_adv, _ = adv.losses(None, traj)
    slow = plain.slow_critic(traj["feat"]).mean.detach()
    torch.testing.assert_close(terms_adv["actor_terms"], terms_plain["actor_terms"] + slow[:-2])


def test_slow_regulariser_adds_the_weighted_distance_to_the_slow_critic(tiny: Config) -> None:
    torch.manual_seed(0)
    base = tiny.actor_critic
    plain = ActorCritic(config=base, feat_size=8, action_size=2)
    reg = ActorCritic(config=dataclasses.replace(base, slow_regulariser=0.5), feat_size=8, action_size=2)
    with torch.no_grad():
        for p in plain.critic.parameters():
            p.add_(0.3 * torch.randn_like(p))
    reg.load_state_dict(plain.state_dict())
    traj = _traj(8)
    traj["weight"] = torch.linspace(1.0, 0.5, 6)[:, None].expand(6, 3).contiguous()
    terms_plain, _ = plain.losses(None, traj)
    terms_reg, _ = reg.losses(None, traj)
    value = plain.critic(traj["feat"][:-1]).mean.detach()
    slow = plain.slow_critic(traj["feat"][:-1]).mean.detach()
    extra = 0.5 * traj["weight"][:-1] * 0.5 * (value - slow) ** 2
    assert float(extra.abs().sum()) > 0
    torch.testing.assert_close(terms_reg["critic_terms"].detach(), terms_plain["critic_terms"].detach() + extra)


def test_twohot_reward_head_and_critic_train_by_cross_entropy(tiny: Config) -> None:
    from coworld.distributions import TWOHOT_BINS, TwoHotSymlog

    torch.manual_seed(0)
    wm_config = dataclasses.replace(tiny.world_model, reward_dist="twohot", zero_init_reward=True)
    ac_config = dataclasses.replace(tiny.actor_critic, critic_dist="twohot", zero_init_critic=True)
    config = dataclasses.replace(tiny, world_model=wm_config, actor_critic=ac_config)
    wm, ac, start = _setup(config)
    feat = torch.randn(4, wm.feat_size)
    head = wm.reward_head(feat)
    assert isinstance(head, TwoHotSymlog) and head.logits.shape == (4, TWOHOT_BINS)
    torch.testing.assert_close(head.mean, torch.zeros(4), atol=1e-5, rtol=0)  # zero init: uniform, mean 0
    terms, _ = wm.loss(random_batch(batch=2, length=3))
    assert float(terms["reward"].detach().mean()) == pytest.approx(math.log(TWOHOT_BINS), rel=1e-4)
    with frozen_parameters(wm):
        traj = ac.imagine(wm, start)
        losses, _ = ac.losses(wm, traj)
    dist = ac.critic(traj["feat"][:-1].detach())
    expected = -(traj["weight"][:-1] * dist.log_prob(losses["target"].detach())).mean()
    torch.testing.assert_close(losses["critic"], expected)


def test_mlp_norm_and_act_reach_actor_critic_and_world_model_heads(tiny: Config) -> None:
    config = make_config(
        "tiny",
        overrides={
            "actor_critic.mlp_norm": "layer",
            "actor_critic.mlp_act": "silu",
            "world_model.mlp_norm": "layer",
            "world_model.mlp_act": "silu",
            "world_model.pred_discount": True,
        },
    )
    wm, ac, start = _setup(config)
    for head in (ac.actor.mlp, ac.critic.mlp, ac.slow_critic.mlp, wm.reward_head.mlp, wm.discount_head.mlp):
        kinds = {type(m) for m in head.modules()}
        assert torch.nn.LayerNorm in kinds and torch.nn.SiLU in kinds and torch.nn.ELU not in kinds
    plain_wm, plain_ac, _ = _setup(tiny)
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in plain_ac.modules())
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in plain_wm.reward_head.modules())
    traj = ac.imagine(wm, start)
    terms, _ = ac.losses(wm, traj)
    assert torch.isfinite(terms["actor"]) and torch.isfinite(terms["critic"])
