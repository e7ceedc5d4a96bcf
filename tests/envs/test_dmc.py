"""DMC tasks through the Gymnasium API: each modification is real and shows where physics says it should."""

from __future__ import annotations

import numpy as np
import pytest

from coworld.envs import make


def rollout(name: str, actions: np.ndarray, seed: int = 0, **overrides: object) -> tuple[np.ndarray, np.ndarray]:
    """Frames ``(T + 1, S, S, 3)`` and rewards ``(T,)`` of ``actions`` ``(T, A)`` from ``reset()``."""
    env = make(name, seed=seed, **overrides)
    frames, rewards = [env.reset()[0]], []
    for action in actions:
        frame, reward, terminated, truncated, _ = env.step(action)
        assert not terminated
        frames.append(frame)
        rewards.append(reward)
    env.close()
    return np.stack(frames), np.array(rewards)


def random_actions(steps: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (steps, 6)).astype(np.float32)


@pytest.mark.parametrize(
    "modified, plain, disabled",
    [("walker_nofoot", "walker_walk", [2]), ("cheetah_nopaw", "cheetah_run", [3, 4, 5])],
)
def test_disabled_actuators_have_no_effect(modified: str, plain: str, disabled: list[int]) -> None:
    actions = random_actions(15, seed=1)
    other = actions.copy()
    other[:, disabled] = random_actions(15, seed=2)[:, disabled]
    frames, _ = rollout(modified, actions)
    frames_other, _ = rollout(modified, other)
    np.testing.assert_array_equal(frames, frames_other)
    # the same change of those entries does move the unmodified body
    plain_frames, _ = rollout(plain, actions)
    plain_other, _ = rollout(plain, other)
    assert not np.array_equal(plain_frames[-1], plain_other[-1])
    # and the disabled body still obeys its other actuators
    other[:, 0] = -actions[:, 0]
    frames_moved, _ = rollout(modified, other)
    assert not np.array_equal(frames[-1], frames_moved[-1])


def _rootx_travel(name: str, seed: int, actions: np.ndarray) -> float:
    env = make(name, seed=seed, image_size=16)
    env.reset()
    physics = env.unwrapped.physics
    start = physics.named.data.qpos["rootx"].item()
    for action in actions:
        env.step(action)
    travel = physics.named.data.qpos["rootx"].item() - start
    env.close()
    return travel


@pytest.mark.parametrize("seed", [0, 1])
def test_passive_walker_falls_down_the_slope(seed: int) -> None:
    """Zero torques: the walker collapses; on a slope it ends up further downhill than on the flat."""
    still = np.zeros((50, 6), np.float32)
    flat, up, down = (_rootx_travel(name, seed, still) for name in ("walker_walk", "walker_uphill", "walker_downhill"))
    assert up < flat - 0.1 < flat + 0.1 < down


@pytest.mark.parametrize("seed", [0, 1])
def test_flailing_cheetah_drifts_down_the_slope(seed: int) -> None:
    """A still cheetah stands on 15 degrees (friction 0.4 > tan 15); the same random flailing drifts it downhill."""
    actions = random_actions(100, seed)
    flat, up, down = (
        _rootx_travel(name, seed, actions) for name in ("cheetah_run", "cheetah_uphill", "cheetah_downhill")
    )
    assert up < flat - 0.3 < flat + 0.3 < down


def test_slope_gravity_and_rewards_keep_their_meaning() -> None:
    env = make("walker_uphill", seed=0, image_size=16)
    gravity = env.unwrapped.physics.model.opt.gravity
    np.testing.assert_allclose(gravity, 9.81 * np.array([-np.sin(np.radians(15)), 0, -np.cos(np.radians(15))]))
    env.close()
    # rewards are dm_control's, in [0, 1] per control step, summed over the repeated steps
    _, rewards = rollout("walker_downhill", random_actions(20, 0), image_size=16)
    assert np.all(rewards >= 0) and np.all(rewards <= 2) and rewards.sum() > 0


def horizon_slope(frame: np.ndarray) -> float:
    """Image slope (rows per column; negative rises to the right) of the sky/floor boundary.

    Per column, the sharpest vertical brightness step away from the orange body; then the Theil-Sen median of
    the pairwise slopes, which ignores columns where something else (a reflection, a grid line) won.
    """
    pixels = frame.astype(float)
    body = pixels[..., 0] > pixels[..., 2]  # sky and floor are blue
    jump = np.abs(np.diff(pixels.mean(-1), axis=0))
    jump[body[1:] | body[:-1]] = 0
    rows = jump.argmax(0).astype(float)
    cols = np.arange(frame.shape[1], dtype=float)
    i, j = np.triu_indices(len(cols), 1)
    return float(np.median((rows[j] - rows[i]) / (cols[j] - cols[i])))


@pytest.mark.parametrize("domain, plain", [("walker", "walker_walk"), ("cheetah", "cheetah_run")])
def test_slope_shows_in_the_frames(domain: str, plain: str) -> None:
    slopes = {}
    for name in (plain, f"{domain}_uphill", f"{domain}_downhill"):
        env = make(name, seed=3)
        slopes[name] = horizon_slope(env.reset()[0])
        env.close()
    assert abs(slopes[plain]) < 0.05
    assert slopes[f"{domain}_uphill"] < -0.12  # the floor rises to the right (tan 15 deg = 0.27)
    assert slopes[f"{domain}_downhill"] > 0.12


def test_same_seed_same_frames_and_different_seeds_differ() -> None:
    actions = random_actions(10, seed=5)
    first, rewards = rollout("walker_uphill", actions, seed=7)
    again, rewards_again = rollout("walker_uphill", actions, seed=7)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(rewards, rewards_again)
    other, _ = rollout("walker_uphill", actions, seed=8)
    assert not np.array_equal(first[0], other[0])
    # reset(seed=...) restarts the same sequence on a used env
    env = make("walker_uphill", seed=0)
    env.reset()
    env.step(actions[0])
    assert np.array_equal(env.reset(seed=7)[0], first[0])
    assert np.array_equal(env.step(actions[0])[0], first[1])
    env.close()


def test_action_repeat_and_episode_length() -> None:
    env = make("cheetah_run", seed=0, image_size=32, action_repeat=4)
    settings = env.unwrapped.settings
    assert (settings.action_repeat, settings.episode_length) == (4, 250)  # the 1000 control steps are kept
    assert env.observation_space.shape == (32, 32, 3)
    env.close()
    env = make("cheetah_run", seed=0, episode_length=3)
    env.reset()
    truncated = [env.step(np.zeros(6, np.float32))[3] for _ in range(3)]
    assert truncated == [False, False, True]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(6, np.float32))
    env.close()
    # an agent step's reward is the sum over its repeated control steps
    actions = random_actions(6, seed=0)
    _, single = rollout("walker_walk", np.repeat(actions, 2, axis=0), action_repeat=1, image_size=16)
    _, double = rollout("walker_walk", actions, action_repeat=2, image_size=16)
    np.testing.assert_allclose(double, single.reshape(-1, 2).sum(1))


def test_render_quality_trades_fidelity_for_speed() -> None:
    """'standard' looks almost like the simulator's own settings ('full'); 'fast' visibly less so."""
    frames = {}
    for quality in ("full", "standard", "fast"):
        env = make("walker_walk", seed=0, render_quality=quality)
        frames[quality] = env.reset()[0].astype(int)
        env.close()
    standard_diff = np.abs(frames["standard"] - frames["full"]).mean()
    fast_diff = np.abs(frames["fast"] - frames["full"]).mean()
    assert 0 < standard_diff < 3 < fast_diff


def floor_in_view(name: str, actions: np.ndarray, seed: int = 0) -> tuple[np.ndarray, float]:
    """Per frame, the share of pixels that show the floor (MuJoCo's segmentation render of the task camera), and
    how far the body travelled along the slope (m)."""
    import mujoco

    env = make(name, seed=seed)
    env.reset()
    physics = env.unwrapped.physics
    model, data = physics.model.ptr, physics.data.ptr
    floor = next(i for i in range(model.ngeom) if model.geom_type[i] == mujoco.mjtGeom.mjGEOM_PLANE)
    renderer = mujoco.Renderer(model, 64, 64)
    renderer.enable_segmentation_rendering()
    start = physics.named.data.qpos["rootx"].item()

    def share() -> float:
        renderer.update_scene(data, camera=0)
        ids, types = np.moveaxis(renderer.render(), -1, 0)
        return float(((types == mujoco.mjtObj.mjOBJ_GEOM) & (ids == floor)).mean())

    shares = [share()]
    for action in actions:
        env.step(action)
        shares.append(share())
    travel = physics.named.data.qpos["rootx"].item() - start
    renderer.close()
    env.close()
    return np.array(shares), travel


@pytest.mark.parametrize("name", ["walker_uphill", "cheetah_uphill"])
def test_a_random_episode_on_the_uphill_shows_the_ground_in_every_frame(name: str) -> None:
    shares, travel = floor_in_view(name, random_actions(500, seed=0))
    assert travel < -2.0  # the body slid back past where dm_control's floor ends (x = -2)
    assert shares.min() > 0.05, f"no ground in frame {int(shares.argmin())}"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["walker_uphill", "walker_downhill", "cheetah_uphill", "cheetah_downhill"])
@pytest.mark.parametrize("policy", ["random", "passive"])
def test_slope_tasks_show_the_ground_whichever_way_the_body_goes(name: str, policy: str) -> None:
    # passive: zero actions, the body slides down the slope (backwards uphill, forwards downhill)
    actions = random_actions(500, seed=3) if policy == "random" else np.zeros((500, 6), np.float32)
    shares, _ = floor_in_view(name, actions)
    assert shares.min() > 0.05, f"no ground in frame {int(shares.argmin())}"
