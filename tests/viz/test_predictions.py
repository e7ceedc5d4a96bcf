"""Open-loop prediction: the error measure and the strips on known cases, and the real world-model path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from coworld.viz.predictions import (
    copy_context,
    error_table,
    open_loop,
    predict,
    prediction_error,
    prediction_strip,
    prediction_video,
)

from .conftest import contains, tiny_agent

H = W = 64


def scene(values: np.ndarray, batch: int = 2) -> dict[str, np.ndarray]:
    """Sequences whose frame t is the solid grey ``values[t]``; actions and flags in the step convention."""
    length = len(values)
    image = np.broadcast_to(np.asarray(values, np.uint8)[None, :, None, None, None], (batch, length, H, W, 3)).copy()
    is_first = np.zeros((batch, length), bool)
    is_first[:, 0] = True
    action = np.random.default_rng(0).uniform(-1, 1, (batch, length, 2)).astype(np.float32)
    action[:, 0] = 0
    zeros = np.zeros((batch, length), bool)
    return {
        "image": image,
        "action": action,
        "reward": np.zeros((batch, length), np.float32),
        "is_first": is_first,
        "is_last": zeros,
        "is_terminal": zeros,
    }


def test_prediction_error_known_values():
    black = np.zeros((3, 4, 4, 3), np.uint8)
    assert prediction_error(black, black).tolist() == [0.0, 0.0, 0.0]
    assert prediction_error(black, black + 255).tolist() == [1.0, 1.0, 1.0]
    assert prediction_error(black, black + 51) == pytest.approx([0.04] * 3)  # (51 / 255)^2
    half = black.copy()
    half[:, :2] = 255  # half the pixels wrong by the whole range
    assert prediction_error(black, half) == pytest.approx([0.5] * 3)
    with pytest.raises(ValueError, match="shape"):
        prediction_error(black, black[:2])


def test_copying_the_context_predicts_a_static_scene_perfectly():
    pred = predict({"copy": copy_context}, scene(np.full(12, 90)), context=5)
    assert pred.errors["copy"].shape == (2, 12)
    assert (pred.errors["copy"] == 0).all()
    assert pred.imagined_error() == {"copy": 0.0}


def test_copying_the_context_fails_on_a_moving_scene_by_the_known_amount():
    values = 10 * np.arange(12)  # the scene brightens by 10 grey levels a step
    pred = predict({"copy": copy_context}, scene(values), context=5)
    expected = [0.0] * 5 + [((10 * t - 40) / 255) ** 2 for t in range(5, 12)]  # holds frame 4 (value 40)
    np.testing.assert_allclose(pred.step_errors()["copy"], expected, rtol=1e-6)


def test_strip_rows_truth_model_and_error_for_each_model_and_sequence():
    batch = scene(np.zeros(6), batch=2)
    colours = np.array([(90, 20, 200), (170, 60, 10)], np.uint8)  # one colour per sequence, not a grey of the text
    batch["image"][:] = colours[:, None, None, None]
    pred = predict({"copy": copy_context, "white": lambda b, c: np.full_like(b["image"], 255)}, batch, context=2)
    strip = prediction_strip(pred)
    for colour in colours:
        assert (strip == colour).all(-1).sum() == 2 * 6 * H * W  # truth and the copying model's row, 6 steps each
        assert contains(strip, np.broadcast_to(255 - colour, (H, W, 3)).astype(np.uint8))  # the white model's error
    assert (strip == 0).all(-1).sum() == 2 * 6 * H * W  # the copying model's |error| rows are exactly black


def test_video_one_frame_per_step_with_all_rows():
    pred = predict({"copy": copy_context}, scene(10 * np.arange(8), batch=3), context=3)
    video = prediction_video(pred, scale=2)
    assert video.shape[0] == 8 and video.dtype == np.uint8
    for t in (0, 7):
        cell = np.full((2 * H, 2 * W, 3), 10 * t, np.uint8)
        assert (video[t] == 10 * t).all(-1).sum() >= 3 * cell.shape[0] * cell.shape[1]  # truth of 3 sequences
    table = error_table(pred)
    assert len(table.splitlines()) == 2 + 8 + 1 and "copy" in table and "   2* " in table


def test_context_must_leave_steps_to_imagine():
    with pytest.raises(ValueError, match="context"):
        predict({"copy": copy_context}, scene(np.zeros(5)), context=5)


def toy_batch() -> dict[str, np.ndarray]:
    from coworld import envs
    from coworld.data.windows import episode_windows
    from coworld.viz.runs import rollout_episodes

    episodes = rollout_episodes(None, "toy_reach_shifted", 2, seed=3, mode="random")
    assert envs.task_spec("toy_reach_shifted").action_size == episodes[0]["action"].shape[-1]
    return episode_windows(episodes, 10)


def test_world_model_open_loop_shapes_and_only_the_context_is_seen():
    world_model = tiny_agent().world_model
    batch = toy_batch()
    rng = torch.get_rng_state()
    frames = open_loop(world_model, batch, context=4)
    assert torch.equal(rng, torch.get_rng_state())  # modes, not samples: the global generator is untouched
    assert frames.shape == batch["image"].shape and frames.dtype == np.uint8
    assert frames.std() > 1.0  # an untrained decoder still draws something, not a blank frame
    np.testing.assert_array_equal(frames, open_loop(world_model, batch, context=4))  # deterministic
    later = {**batch, "image": batch["image"].copy()}
    later["image"][:, 4:] = 255 - later["image"][:, 4:]  # change every frame after the context
    np.testing.assert_array_equal(open_loop(world_model, later, context=4), frames)
    earlier = {**batch, "image": batch["image"].copy()}
    earlier["image"][:, 3] = 0  # change one context frame: the reconstruction and the future change
    changed = open_loop(world_model, earlier, context=4)
    assert (changed[:, 3] != frames[:, 3]).any() and (changed[:, 4:] != frames[:, 4:]).any()
    actions = {**batch, "action": -batch["action"]}  # the imagined part follows the recorded actions
    assert (open_loop(world_model, actions, context=4)[:, 5:] != frames[:, 5:]).any()


def test_predict_runs_world_models_and_predictors_side_by_side():
    batch = toy_batch()
    pred = predict({"model": tiny_agent().world_model, "copy": copy_context}, batch, context=3)
    assert set(pred.errors) == {"model", "copy"} and pred.errors["model"].shape == (2, 10)
    assert (pred.errors["model"] > 0).all() and np.isfinite(pred.errors["model"]).all()
