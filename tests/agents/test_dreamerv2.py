"""The DreamerV2 agent: training step, policy with per-row resets, checkpoints, hooks, device and precision."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch

from coworld.agents.dreamerv2 import DreamerV2, resolve_precision
from coworld.config import Config, make_config
from coworld.devices import resolve_device
from coworld.errors import ConfigError
from coworld.losses.dreamer import critic_loss

ACTION_SIZE = 2


@pytest.fixture(autouse=True)
def _seeded_single_thread(one_torch_thread: None) -> None:
    torch.manual_seed(0)


@pytest.fixture
def tiny() -> Config:
    return make_config("tiny", {"device": "cpu"})


def numpy_batch(batch: int = 2, length: int = 6, seed: int = 0) -> dict[str, np.ndarray]:
    """A replay-convention batch of NumPy arrays (rewards float64 on purpose: to_batch must cast them)."""
    rng = np.random.default_rng(seed)
    is_first = np.zeros((batch, length), bool)
    is_first[:, 0] = True
    action = rng.uniform(-1, 1, (batch, length, ACTION_SIZE)).astype(np.float32)
    action[is_first] = 0.0
    is_terminal = np.zeros((batch, length), bool)
    is_terminal[-1, -1] = True
    return {
        "image": rng.integers(0, 256, (batch, length, 64, 64, 3), dtype=np.uint8),
        "action": action,
        "reward": rng.normal(size=(batch, length)),
        "is_first": is_first,
        "is_last": is_terminal.copy(),
        "is_terminal": is_terminal,
    }


def _params(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in module.parameters()]).clone()


def test_actor_warmup_trains_the_world_model_alone_first(tiny: Config) -> None:
    config = make_config("tiny", {"device": "cpu", "train.actor_warmup": 2})
    agent = DreamerV2(config=config, action_size=ACTION_SIZE)
    actor, critic, model = (
        _params(m) for m in (agent.actor_critic.actor, agent.actor_critic.critic, agent.world_model)
    )
    for step in range(2):
        metrics = agent.train(numpy_batch(seed=step))
        assert "actor/loss" not in metrics and "wm/loss" in metrics
    assert torch.equal(_params(agent.actor_critic.actor), actor) and torch.equal(
        _params(agent.actor_critic.critic), critic
    )
    assert not torch.equal(_params(agent.world_model), model)
    assert "actor/loss" in agent.train(numpy_batch(seed=2))  # the third update trains the actor too
    assert not torch.equal(_params(agent.actor_critic.actor), actor)
    assert agent.updates == 3 and int(agent.actor_critic.updates) == 1


def test_to_batch_keeps_uint8_images_and_casts_floats(tiny: Config) -> None:
    agent = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    batch = agent.to_batch(numpy_batch())
    assert batch["image"].dtype == torch.uint8 and batch["image"].shape == (2, 6, 64, 64, 3)
    assert batch["reward"].dtype == torch.float32 and batch["action"].dtype == torch.float32
    assert batch["is_first"].dtype == torch.bool


def test_train_updates_all_networks_and_reports_metrics(tiny: Config) -> None:
    agent = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    before = [_params(m) for m in (agent.world_model, agent.actor_critic.actor, agent.actor_critic.critic)]
    metrics = agent.train(numpy_batch())
    after = [_params(m) for m in (agent.world_model, agent.actor_critic.actor, agent.actor_critic.critic)]
    assert all(not torch.equal(b, a) for b, a in zip(before, after, strict=True))
    expected = {
        "wm/image",
        "wm/reward",
        "wm/kl",
        "wm/loss",
        "wm/grad_norm",
        "actor/loss",
        "actor/entropy",
        "critic/loss",
        "critic/value",
        "imag/return",
    }
    assert expected <= set(metrics)
    assert all(isinstance(v, float) and math.isfinite(v) for v in metrics.values())
    assert agent.updates == 1 and int(agent.actor_critic.updates) == 1
    # The first update copied the stepped critic into the slow target (DreamerV2's order).
    assert torch.equal(_params(agent.actor_critic.slow_critic), after[2])


def test_policy_modes_shapes_and_bounds(tiny: Config) -> None:
    agent = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    obs = numpy_batch(batch=3)["image"][:, 0]
    for mode in ("train", "eval", "random"):
        action, state = agent.policy(obs, None, mode)
        assert action.shape == (3, ACTION_SIZE) and action.dtype == np.float32
        assert np.all(np.abs(action) <= 1.0)
        latent, last_action = state  # every mode filters the latent, 'random' too (the prefill)
        np.testing.assert_array_equal(last_action.numpy(), action)
    _, state = agent.policy(obs, None, "eval")
    torch.manual_seed(5)
    first, _ = agent.policy(obs, state, "eval")
    torch.manual_seed(5)
    again, _ = agent.policy(obs, state, "eval")
    np.testing.assert_array_equal(first, again)
    with pytest.raises(ValueError, match="mode"):
        agent.policy(obs, None, "explore")  # type: ignore[arg-type]


def test_policy_is_first_resets_single_rows(tiny: Config) -> None:
    agent = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    frames = numpy_batch(batch=3, length=4)["image"]
    state = None
    for t in range(3):
        _, state = agent.policy(frames[:, t], state, "train")
    obs = frames[:, 3]
    torch.manual_seed(11)
    reset, reset_state = agent.policy(obs, state, "eval", is_first=np.array([True, False, False]))
    torch.manual_seed(11)
    fresh, fresh_state = agent.policy(obs, None, "eval")
    assert reset_state is not None and fresh_state is not None
    np.testing.assert_array_equal(reset[0], fresh[0])
    torch.testing.assert_close(reset_state[0]["deter"][0], fresh_state[0]["deter"][0])
    assert not torch.allclose(reset_state[0]["deter"][1:], fresh_state[0]["deter"][1:])


def _act(actor, obs: np.ndarray, seed: int, mode: str = "train") -> list[np.ndarray]:
    """Three policy steps from a fresh latent, every random number from a generator seeded ``seed``."""
    generator, state, actions = torch.Generator().manual_seed(seed), None, []
    for frame in obs:
        action, state = actor.policy(frame, state, mode, generator=generator)
        actions.append(action)
    return actions


def test_policy_draws_from_the_generator_it_is_given_and_leaves_the_default_alone(tiny: Config) -> None:
    agent = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    obs = numpy_batch(batch=2, length=3)["image"].swapaxes(0, 1)
    for mode in ("train", "random"):
        torch.manual_seed(1)
        first = _act(agent, obs, seed=7, mode=mode)
        default_after = torch.rand(4)
        torch.manual_seed(2)
        again = _act(agent, obs, seed=7, mode=mode)
        np.testing.assert_array_equal(np.stack(first), np.stack(again))  # the default generator played no part
        torch.manual_seed(1)
        torch.testing.assert_close(torch.rand(4), default_after)  # and was not drawn from
        other = _act(agent, obs, seed=8, mode=mode)
        assert not np.array_equal(np.stack(first), np.stack(other))


def test_policy_copy_acts_as_the_agent_did_at_its_last_sync(tiny: Config) -> None:
    agent = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    obs = numpy_batch(batch=2, length=3)["image"].swapaxes(0, 1)
    copy = agent.policy_copy()
    before = _act(agent, obs, seed=3)
    np.testing.assert_array_equal(np.stack(_act(copy, obs, seed=3)), np.stack(before))
    agent.train(numpy_batch())
    after = _act(agent, obs, seed=3)
    assert not np.array_equal(np.stack(after), np.stack(before))  # the update changed the policy ...
    np.testing.assert_array_equal(np.stack(_act(copy, obs, seed=3)), np.stack(before))  # ... not the copy's
    copy.sync()
    np.testing.assert_array_equal(np.stack(_act(copy, obs, seed=3)), np.stack(after))


def test_state_dict_round_trip_through_weights_only_load(tiny: Config) -> None:
    agent = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    for seed in range(2):
        agent.train(numpy_batch(seed=seed))
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=True)
    clone = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    clone.load_state_dict(loaded)
    assert clone.updates == 2 and int(clone.actor_critic.updates) == 2
    obs = numpy_batch(batch=4)["image"][:, 0]
    torch.manual_seed(3)
    a1, _ = agent.policy(obs, None, "eval")
    torch.manual_seed(3)
    a2, _ = clone.policy(obs, None, "eval")
    np.testing.assert_array_equal(a1, a2)
    # Optimiser moments came along too: one more identical update gives identical parameters.
    batch = numpy_batch(seed=7)
    torch.manual_seed(4)
    m1 = agent.train(batch)
    torch.manual_seed(4)
    m2 = clone.train(batch)
    assert m1 == m2
    torch.testing.assert_close(_params(agent.world_model), _params(clone.world_model), rtol=0, atol=0)


def test_extra_world_model_loss_is_added_and_logged(tiny: Config) -> None:
    agent = DreamerV2(config=tiny, action_size=ACTION_SIZE)

    def extra(batch: dict[str, torch.Tensor], aux: dict) -> dict[str, torch.Tensor]:
        assert aux["embed"].shape[:2] == batch["action"].shape[:2]
        return {"align": 10.0 + 0.0 * aux["embed"].sum()}

    metrics, post = agent.train_world_model(numpy_batch(), extra_loss=extra)
    assert metrics["wm/align"] == 10.0
    base = metrics["wm/image"] + metrics["wm/reward"] + metrics["wm/kl_loss"]
    assert metrics["wm/loss"] == pytest.approx(base + 10.0, rel=1e-5)
    assert post["deter"].shape == (2, 6, tiny.world_model.deter) and not post["deter"].requires_grad


def test_a_critic_objective_changes_the_critic_update_alone(tiny: Config) -> None:
    plain, regularised = (DreamerV2(config=tiny, action_size=ACTION_SIZE) for _ in range(2))
    regularised.load_state_dict(plain.state_dict())
    batch = numpy_batch()
    torch.manual_seed(1)
    _, post = plain.train_world_model(batch)
    m_plain = plain.train_actor_critic(post)
    torch.manual_seed(1)
    _, post = regularised.train_world_model(batch)

    def objective(feat, value, target, weight):
        extra = 5.0 * value.mean
        return critic_loss(value, target, weight) + weight * extra, {"critic/regulariser": extra.detach().mean()}

    m_reg = regularised.train_actor_critic(post, objective)
    assert m_reg["critic/regulariser"] == pytest.approx(5.0 * m_reg["critic/value"], rel=1e-5)
    assert m_reg["critic/loss"] != m_plain["critic/loss"]
    torch.testing.assert_close(_params(plain.actor_critic.actor), _params(regularised.actor_critic.actor))
    assert not torch.equal(_params(plain.actor_critic.critic), _params(regularised.actor_critic.critic))


def test_resolve_device_and_precision() -> None:
    cpu = torch.device("cpu")
    assert resolve_device("cpu") == cpu
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ConfigError, match="unknown device"):
        resolve_device("tpu9")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA"):
            resolve_device("cuda")
    assert resolve_precision("auto", cpu) is None
    assert resolve_precision("auto", torch.device("cuda")) is None  # fp32: bf16's learning over a run is unmeasured
    assert resolve_precision("bf16", cpu) is torch.bfloat16
    assert resolve_precision("fp32", torch.device("cuda")) is None
    with pytest.raises(ConfigError, match="precision"):
        resolve_precision("fp8", cpu)


def test_bf16_autocast_step_runs_on_cpu(tiny: Config) -> None:
    agent = DreamerV2(config=make_config("tiny", {"device": "cpu", "precision": "bf16"}), action_size=ACTION_SIZE)
    assert agent.autocast_dtype is torch.bfloat16
    metrics = agent.train(numpy_batch(length=4))
    assert all(math.isfinite(v) for v in metrics.values())
    # Parameters and optimiser state stay float32 under autocast.
    assert all(p.dtype == torch.float32 for p in agent.world_model.parameters())


def _traced_without_codegen(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ``compile=true`` trace as it does (dynamo, ``fullgraph``, static shapes) but run the captured graphs
    through AOT autograd in eager kernels (``backend='aot_eager'``) instead of generating C++ with inductor: the
    project's side of compiling (whole graphs without a break, the same draws, the same state-dict keys), without
    inductor's minutes of C++ compilation."""
    compile_fn, module_compile = torch.compile, torch.nn.Module.compile

    def traced(fn, *, options=None, backend=None, **kwargs):
        del options, backend  # inductor's options; nn.Module.compile passes its own backend through here
        return compile_fn(fn, backend="aot_eager", **kwargs)

    def module_traced(self, *, options=None, **kwargs):
        del options
        return module_compile(self, backend="aot_eager", **kwargs)

    monkeypatch.setattr(torch, "compile", traced)
    monkeypatch.setattr(torch.nn.Module, "compile", module_traced)


def test_compiled_agent_traces_whole_matches_eager_and_shares_checkpoints(
    tiny: Config, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The fast suite's form of the inductor test below: the update's graphs trace whole (a graph break raises),
    and the compiled agent draws and computes what the eager one does, with the same checkpoint layout."""
    torch._dynamo.reset()
    _traced_without_codegen(monkeypatch)
    _check_compiled_against_eager(tiny, lengths=(2, 2, 3))
    torch._dynamo.reset()


@pytest.mark.slow
def test_compiled_agent_matches_eager_and_shares_checkpoints(tiny: Config) -> None:
    """torch.compile (inductor, here on CPU) changes neither the numbers nor the checkpoint layout. Slow: inductor's
    C++ compilation takes minutes, and many more on a loaded machine."""
    _check_compiled_against_eager(tiny, lengths=(4, 4, 5))


def _check_compiled_against_eager(tiny: Config, lengths: tuple[int, ...]) -> None:
    eager = DreamerV2(config=tiny, action_size=ACTION_SIZE)
    compiled = DreamerV2(config=make_config("tiny", {"device": "cpu", "compile": True}), action_size=ACTION_SIZE)
    assert compiled.compiled and not eager.compiled
    compiled.load_state_dict(eager.state_dict())
    assert list(compiled.state_dict()["world_model"]) == list(eager.state_dict()["world_model"])
    # The second step runs the already compiled graphs; the third's batch has another length, which compiles
    # anew (traced with symbolic sizes, the truncated normal's sample raised there).
    for batch in (numpy_batch(length=length) for length in lengths):
        torch.manual_seed(1)
        want = eager.train(batch)
        torch.manual_seed(1)
        got = compiled.train(batch)
        for key in ("wm/image", "wm/reward", "wm/kl", "actor/loss", "critic/loss"):
            assert got[key] == pytest.approx(want[key], rel=1e-4, abs=1e-6), key
    for name, param in eager.world_model.state_dict().items():
        torch.testing.assert_close(compiled.world_model.state_dict()[name], param, rtol=1e-4, atol=1e-5)


def test_value_reads_the_critic_at_the_policy_state():
    import numpy as np
    import torch

    from coworld.agents.dreamerv2 import DreamerV2
    from coworld.config import make_config

    agent = DreamerV2(config=make_config("tiny", ["device=cpu"]), action_size=2)
    obs = np.random.default_rng(0).integers(0, 255, (3, 64, 64, 3), dtype=np.uint8)
    _, state = agent.policy(obs, None, mode="eval")
    value = agent.value(state)
    assert value.shape == (3,)
    with torch.no_grad():
        expected = agent.actor_critic.critic(agent.world_model.features(state[0])).mean
    np.testing.assert_allclose(value, expected.numpy(), rtol=1e-6)
    with torch.no_grad():  # and it follows the critic's weights
        for p in agent.actor_critic.critic.parameters():
            p.add_(0.5)
    assert not np.allclose(agent.value(state), value)


@pytest.mark.parametrize("lr", [1e-4, 1e-2])
def test_weight_decay_is_dreamerv2s_multiplicative_step_whatever_the_learning_rate(lr: float) -> None:
    from coworld.agents.dreamerv2 import make_optimizer

    weight = torch.nn.Parameter(torch.tensor([1.0, -2.0, 4.0]))
    optimizer = make_optimizer([weight], lr=lr, eps=1e-5, decay=0.1)
    weight.grad = torch.zeros_like(weight)  # a zero gradient: Adam's own step is zero, only the decay acts
    optimizer.step()
    assert torch.allclose(weight.detach(), torch.tensor([0.9, -1.8, 3.6]))
