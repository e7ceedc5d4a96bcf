"""Re-measure recorded random-policy returns through the public API (slow: thousands of rendered steps)."""

from __future__ import annotations

import numpy as np
import pytest

from coworld.envs import make, task_spec


@pytest.mark.slow
@pytest.mark.parametrize("name", ["walker_uphill", "cheetah_run"])
def test_recorded_random_return(name: str) -> None:
    """As recorded in the registry: 10 episodes, reset(seed=i), actions default_rng(i).uniform(-1, 1)."""
    spec = task_spec(name)
    env = make(name, image_size=16)
    returns = []
    for seed in range(10):
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        total, truncated = 0.0, False
        while not truncated:
            _, reward, _, truncated, _ = env.step(rng.uniform(-1, 1, spec.action_size))
            total += reward
        returns.append(total)
    env.close()
    assert np.mean(returns) == pytest.approx(spec.random_return, abs=0.05)


def test_recorded_metaworld_expert_return() -> None:
    """The Meta-World stand-in reference as recorded: the scripted expert, 10 episodes seeded 0-9."""
    from coworld.envs.experts import expert_returns
    from coworld.envs.registry import _METAWORLD_REFERENCE

    returns, successes = expert_returns("mw_button_press", 10)
    assert np.mean(returns) == pytest.approx(_METAWORLD_REFERENCE["mw_button_press"][0], abs=0.05)
    assert all(successes)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["robodesk_push_button", "robodesk_open_slide"])
def test_recorded_robodesk_returns(name: str) -> None:
    """As recorded in the registry by benchmarks/reference_returns.py --robodesk: random 10 episodes, and the
    scripted policy's return that stands in for push_button's reference."""
    from coworld.envs.experts import expert_returns, robodesk_random_returns
    from coworld.envs.registry import _ROBODESK_REFERENCE

    assert np.mean(robodesk_random_returns(name, 10)) == pytest.approx(task_spec(name).random_return, abs=0.05)
    if name == "robodesk_push_button":
        returns, successes = expert_returns(name, 10)
        assert np.mean(returns) == pytest.approx(_ROBODESK_REFERENCE[name][0], abs=0.05) and all(successes)
