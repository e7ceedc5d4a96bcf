"""RoboDesk tasks: frames, seeding, RoboDesk's rewards and success tests, the scripted press, the registry, collect.

Frames are drawn in software at about 4 per second here (three shadow-casting lights), so the tests that step
the env with frames take few steps; the policy tests use ``simulate`` (the step without a frame).
"""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.envs import TASKS, env_id, make, task_spec
from coworld.envs.experts import robodesk_expert_action
from coworld.envs.robodesk import TASK_NAMES, task_reward

ROBODESK = [name for name, task in TASKS.items() if task.family == "robodesk"]


def test_the_four_tasks_of_the_later_paper_are_registered() -> None:
    assert ROBODESK == [
        "robodesk_push_button",
        "robodesk_open_slide",
        "robodesk_drawer_open",
        "robodesk_upright_block_off_table",
    ]
    robodesk_names = ["push_green", "open_slide", "open_drawer", "upright_block_off_table"]
    assert [TASK_NAMES[name] for name in ROBODESK] == robodesk_names
    for name in ROBODESK:
        spec = task_spec(name)
        assert (spec.action_size, spec.episode_length, spec.action_repeat) == (5, 500, 1)
        assert spec.embodiment == "franka" and spec.has_success
        assert TASK_NAMES[name] in spec.base and "dense" in spec.base
        # random below the reference, and both within what RoboDesk's per-step reward allows (at most 1 a step)
        assert 0 < spec.random_return < spec.reference_return <= 500 and spec.reference_source
        assert env_id(name) in gym.registry


def test_steps_shapes_dtypes_and_truncation() -> None:
    env = make("robodesk_push_button", seed=0, episode_length=2)
    assert env.action_space.shape == (5,) and env.observation_space.shape == (64, 64, 3)
    frame, info = env.reset()
    assert frame.shape == (64, 64, 3) and frame.dtype == np.uint8 and info == {"success": False}
    assert frame.std() > 20  # a picture, not a blank
    flags = []
    for _ in range(2):
        frame, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert frame.dtype == np.uint8 and isinstance(reward, float) and 0.0 <= reward <= 1.0
        assert isinstance(info["success"], bool) and not terminated
        flags.append(truncated)
    assert flags == [False, True]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(env.action_space.sample())
    env.reset()
    with pytest.raises(ValueError, match=r"shape \(5,\)"):
        env.step(np.zeros(4, np.float32))  # a Meta-World action
    env.close()


def test_the_gymnasium_id_builds_the_task_at_other_sizes() -> None:
    env = gym.make(env_id("robodesk_open_slide"), seed=1, image_size=32, episode_length=1)
    frame, _ = env.reset()
    assert frame.shape == (32, 32, 3) and frame.std() > 20
    env.close()


def test_a_seed_fixes_the_scene_and_the_frames() -> None:
    actions = np.random.default_rng(0).uniform(-1, 1, (2, 5)).astype(np.float32)

    def frames(seed: int) -> np.ndarray:
        env = make("robodesk_open_slide", seed=seed, image_size=16)  # small frames draw faster
        out = [env.reset()[0]] + [env.step(a)[0] for a in actions]
        env.close()
        return np.stack(out)

    first = frames(0)
    np.testing.assert_array_equal(first, frames(0))
    assert not np.array_equal(first[0], frames(1)[0])  # the slide, the objects and the arm start elsewhere
    env = make("robodesk_open_slide", seed=0, image_size=16)
    env.reset()
    env.unwrapped.reset_state()  # each reset draws a new scene; reset(seed=...) restarts the sequence
    slide = env.unwrapped.physics.named.data.qpos["slide_joint"][0]
    assert np.array_equal(env.reset(seed=0)[0], first[0])
    assert slide != env.unwrapped.physics.named.data.qpos["slide_joint"][0]
    env.close()


@pytest.fixture(scope="module")
def desk():
    """One push_button env without real frames (8 x 8, no shadows): its physics serves every task's reward."""
    env = make("robodesk_push_button", seed=0, image_size=8, render_quality="fast")
    yield env.unwrapped
    env.close()


def _set(desk, **qpos: float):
    """The scene of seed 0 with the joints in ``qpos`` set, and the simulator's derived state recomputed."""
    desk.reset_state(0)
    physics = desk.physics
    for joint, value in qpos.items():
        physics.named.data.qpos[joint] = value
    physics.forward()
    return physics


def _reach(physics, point) -> float:
    return max(0.0, 1.0 - float(np.linalg.norm(physics.named.data.site_xpos["end_effector"] - point)))


def test_the_rewards_are_robodesks_dense_terms(desk) -> None:
    """Known answers from RoboDesk's formulas in set states (coworld/envs/robodesk.py's docstring)."""
    physics = _set(desk, slide_joint=0.3)
    handle = physics.named.data.site_xpos["slide_handle"] - [0.15, 0, 0]
    reward, success = task_reward(physics, "open_slide")
    assert reward == pytest.approx(0.9 * (0.75 * 0.5 + 0.25 * _reach(physics, handle)) + 0.1) and not success
    physics = _set(desk, slide_joint=0.58)
    handle = physics.named.data.site_xpos["slide_handle"] - [0.15, 0, 0]
    reward, success = task_reward(physics, "open_slide")
    assert reward == pytest.approx(0.9 * (0.75 * 0.58 / 0.6 + 0.25 * _reach(physics, handle)) + 0.1) and success

    physics = _set(desk, drawer_joint=-0.15)
    handle = physics.named.data.geom_xpos["drawer_handle"]
    assert task_reward(physics, "open_drawer") == (pytest.approx(0.375 + 0.25 * _reach(physics, handle)), False)
    physics = _set(desk, drawer_joint=-0.25)
    assert task_reward(physics, "open_drawer")[1]

    physics = _set(desk)
    button = physics.named.data.xpos["green_button"]
    assert task_reward(physics, "push_green") == (pytest.approx(0.75 * _reach(physics, button)), False)
    physics = _set(desk, green_light=-0.0048)  # the light follows the pressed button
    assert task_reward(physics, "push_green") == (pytest.approx(0.25 + 0.75 * _reach(physics, button)), True)

    physics = _set(desk)
    block = physics.named.data.xpos["upright_block"]
    expected = 0.15 + 0.25 * _reach(physics, block)
    assert task_reward(physics, "upright_block_off_table") == (pytest.approx(expected), False)
    physics.named.data.qpos["upright_block"][2] = 0.3  # on the floor
    physics.forward()
    assert task_reward(physics, "upright_block_off_table")[1]


def _run(desk, policy: str, steps: int, seed: int) -> tuple[float, bool]:
    desk.reset_state(seed)
    rng = np.random.default_rng(seed)
    total, success, stage = 0.0, False, 0
    for _ in range(steps):
        if policy == "scripted":
            action, stage = robodesk_expert_action(desk, "robodesk_push_button", stage)
        else:
            action = rng.uniform(-1, 1, 5).astype(np.float32)
        reward, _, step_success = desk.simulate(action)
        total += reward
        success = success or step_success
    return total, success


def test_the_scripted_policy_presses_the_button_and_random_arms_do_not(desk) -> None:
    """The arm reaches and presses the green button through the 5-d end-effector actions; random ones do not."""
    for seed in (0, 1):
        scripted, pressed = _run(desk, "scripted", 500, seed)
        random, random_pressed = _run(desk, "random", 500, seed)
        assert pressed and not random_pressed
        assert scripted > random + 20


def test_an_unknown_robodesk_task_gets_one_line_and_exit_2(tmp_path) -> None:
    args = ["collect", "--task", "robodesk_push_green", "--policy", "random", "--episodes", "1"]
    result = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "x.h5")])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: unknown task 'robodesk_push_green'; valid tasks:")
    assert "robodesk_push_button" in lines[0] and not (tmp_path / "x.h5").exists()


def test_collect_random_writes_a_dataset_that_verifies(tmp_path, monkeypatch) -> None:
    """``coworld collect --policy random --episodes 2`` then ``coworld dataset verify`` (episodes cut to 3 steps
    here: a full 500-step episode draws its frames for about two minutes on this machine)."""
    spec = TASKS["robodesk_push_button"]
    monkeypatch.setitem(TASKS, spec.name, replace(spec, episode_length=3))
    out = tmp_path / "rd.h5"
    runner = CliRunner()
    args = ["collect", "--task", spec.name, "--policy", "random", "--episodes", "2", "--out", str(out), "--quiet"]
    result = runner.invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "2 episodes, 6 steps" in result.output
    result = runner.invoke(main, ["dataset", "verify", str(out)])
    assert result.exit_code == 0, result.output
    import h5py

    with h5py.File(out, "r") as f:
        assert f.attrs["task"] == spec.name and int(f.attrs["action_size"]) == 5
        assert f["observations"].shape == (6, 64, 64, 3) and f["actions"].shape == (6, 5)
        assert f["infos/success"].shape == (6,)  # RoboDesk reports success, as Meta-World does
        rewards = f["rewards"][:]
        assert ((rewards >= 0) & (rewards <= 1)).all() and rewards.std() > 0


def test_the_solvers_give_up_warning_is_dropped_and_other_warnings_are_not(desk, caplog) -> None:
    """At the edge of the reach the inverse kinematics stops short every step; its warning would flood the console."""
    import logging

    from dm_control.utils.inverse_kinematics import qpos_from_site_pose

    desk.reset_state(0)
    with caplog.at_level("WARNING"):
        far = np.array([0.0, 3.0, 3.0])  # metres beyond the arm's reach: the solver gives up after its 100 steps
        result = qpos_from_site_pose(desk._ik_physics, "end_effector", far, inplace=True)
        logging.getLogger("absl").warning("another warning")
    assert not result.success
    assert [record.getMessage() for record in caplog.records] == ["another warning"]


def test_a_sweep_grid_takes_robodesk_tasks(tmp_path) -> None:
    folder = tmp_path / "sweep"
    args = ["sweep", "--pairs", "robodesk_open_slide:robodesk_push_button", "--algos", "dreamerv2,drq-bc"]
    result = CliRunner().invoke(main, [*args, "--seeds", "1", "--preset", "tiny", "--dir", str(folder), "--dry-run"])
    assert result.exit_code == 0, result.output
    assert "robodesk_push_button-medium_replay.h5" in result.output
    assert "dreamerv2-robodesk_push_button-s0" in result.output and "drq-bc-robodesk_push_button-s0" in result.output
    assert not folder.exists()  # a dry run writes nothing
