"""Open-loop video prediction (the paper's Figure 5; dreamerv3's ``openl`` reports), and the strip every training
evaluation logs to TensorBoard.

The world model observes the first ``context`` frames of each sequence through the posterior, then rolls its
prior forward with the recorded actions alone and decodes every state. Shown side by side over time: the true
frames, each model's frames (reconstructions during the context, predictions after it) and their absolute
difference. The error of a frame is the mean squared difference of its pixels in ``[0, 1]`` units. Latents are
taken at their mode (``sample=False``), so a prediction is deterministic and draws no random numbers.

The strip is one image (``Logger.log_image``, TensorBoard's ``add_image``), not a video: an image needs nothing
beyond TensorBoard itself (``add_video`` needs moviepy), and it shows every step of every sequence at once, which
is what one compares from one evaluation to the next. The same sequences are shown each time (evenly spaced
episodes, windows drawn with a fixed seed), so the strips of one run can be compared directly. Beside the image,
the mean error over the imagined steps is logged as a scalar ``<tag>/mse`` (``<tag>/mse_<model>`` for CoWorld).
Nothing here draws from the global random generators, so a run's batches are the same with or without it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from coworld.data.windows import EpisodeSource, count_episodes, episode_windows, evenly_spaced, get_episodes
from coworld.models.rssm import stack_states
from coworld.pictures import labelled_grid

CONTEXT = 5
"""Frames observed before imagining (DreamerV2's and dreamerv3's open-loop reports)."""

Predictor = Callable[[Mapping[str, np.ndarray], int], np.ndarray]
"""``(batch, context) -> frames``: a batch of B sequences of T steps (step convention, uint8 images
``(B, T, H, W, C)``) and the number of observed frames, to the predicted uint8 frames ``(B, T, H, W, C)``."""


def prediction_error(truth: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Mean squared error per frame, pixels scaled to ``[0, 1]``: uint8 ``(..., H, W, C)`` pair -> ``(...)``."""
    if truth.shape != predicted.shape:
        raise ValueError(f"truth {truth.shape} and prediction {predicted.shape} differ in shape")
    diff = truth.astype(np.float32) / 255.0 - predicted.astype(np.float32) / 255.0
    return np.square(diff).mean(axis=(-3, -2, -1))


def copy_context(batch: Mapping[str, np.ndarray], context: int) -> np.ndarray:
    """A predictor that knows no dynamics: it shows the observed frames, then holds the last one."""
    image = np.asarray(batch["image"])
    index = np.minimum(np.arange(image.shape[1]), context - 1)
    return image[:, index]


def batch_tensors(world_model: Any, batch: Mapping[str, np.ndarray]) -> tuple[torch.Tensor, ...]:
    """``image`` uint8, ``action`` float32 and ``is_first`` bool of a batch as tensors on the model's device."""
    device = next(world_model.parameters()).device
    return (
        torch.as_tensor(np.asarray(batch["image"]), device=device),
        torch.as_tensor(np.asarray(batch["action"]), device=device).float(),
        torch.as_tensor(np.asarray(batch["is_first"]), device=device),
    )


@torch.no_grad()
def open_loop(world_model: Any, batch: Mapping[str, np.ndarray], context: int = CONTEXT) -> np.ndarray:
    """Open-loop frames of a :class:`~coworld.models.world_model.WorldModel`.

    Args:
        batch: B sequences of T steps, step convention (``image``, ``action``, ``is_first``).
        context: frames observed through the posterior; the other ``T - context`` come from the prior.

    Returns:
        uint8 ``(B, T, H, W, C)``: decoded reconstructions for ``t < context``, predictions after.
    """
    image, action, is_first = batch_tensors(world_model, batch)
    device = action.device
    size, length = action.shape[:2]
    rssm = world_model.rssm
    embed = world_model.encode(image[:, :context])
    state = rssm.initial(size, device)
    states = []
    for t in range(length):
        if t < context:
            state, _ = rssm.obs_step(state, action[:, t], embed[:, t], is_first[:, t], sample=False)
        else:
            state = rssm.img_step(state, action[:, t], sample=False)
        states.append(state)
    mean = world_model.decoder(world_model.features(stack_states(states))).float()  # (B, T, C, H, W) in [-.5, .5]
    frames = ((mean + 0.5) * 255.0).clamp(0, 255).round().to(torch.uint8)
    return frames.movedim(-3, -1).cpu().numpy()


@dataclass(frozen=True)
class Predictions:
    """True frames and each model's open-loop frames of the same sequences.

    Attributes:
        truth: uint8 ``(B, T, H, W, C)``.
        frames: model name -> uint8 ``(B, T, H, W, C)``.
        context: observed frames at the start of each sequence.
    """

    truth: np.ndarray
    frames: dict[str, np.ndarray]
    context: int

    @property
    def errors(self) -> dict[str, np.ndarray]:
        """Model name -> per-frame MSE ``(B, T)`` (pixels in ``[0, 1]``)."""
        return {name: prediction_error(self.truth, frames) for name, frames in self.frames.items()}

    def step_errors(self) -> dict[str, np.ndarray]:
        """Model name -> per-step MSE ``(T,)``, the mean over the B sequences."""
        return {name: error.mean(axis=0) for name, error in self.errors.items()}

    def imagined_error(self) -> dict[str, float]:
        """Model name -> mean MSE over the imagined steps (``t >= context``) of every sequence."""
        return {name: float(error[:, self.context :].mean()) for name, error in self.errors.items()}


def predict(models: Mapping[str, Any], batch: Mapping[str, np.ndarray], context: int = CONTEXT) -> Predictions:
    """Open-loop frames of each model on ``batch``. A model is a world model or any :data:`Predictor`."""
    length = np.asarray(batch["image"]).shape[1]
    if not 1 <= context < length:
        raise ValueError(f"context {context} must be at least 1 and shorter than the sequences ({length} steps)")
    frames = {
        name: model(batch, context) if not isinstance(model, torch.nn.Module) else open_loop(model, batch, context)
        for name, model in models.items()
    }
    return Predictions(truth=np.asarray(batch["image"]), frames=frames, context=context)


def abs_difference(truth: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """``|truth - frames|`` per pixel and channel, uint8 (black where the prediction is exact)."""
    return np.abs(truth.astype(np.int16) - frames.astype(np.int16)).astype(np.uint8)


def prediction_rows(pred: Predictions) -> tuple[list[str], list[np.ndarray]]:
    """Row names and ``(B, T, H, W, C)`` rows: truth, then each model and its difference."""
    names, rows = ["truth"], [pred.truth]
    for name, frames in pred.frames.items():
        names += [name, "|error|"]
        rows += [frames, abs_difference(pred.truth, frames)]
    return names, rows


def prediction_strip(pred: Predictions, *, scale: int = 1, title: str | None = None) -> np.ndarray:
    """One picture, time along x: for each sequence the rows truth / model / |error| (per model).

    Column labels are step numbers, context steps marked with ``*``. Returns uint8 ``(H, W, 3)``.
    """
    names, rows = prediction_rows(pred)
    length = pred.truth.shape[1]
    cells, labels = [], []
    for b in range(pred.truth.shape[0]):
        for name, row in zip(names, rows, strict=True):
            cells.append(list(row[b]))
            labels.append(f"{b}: {name}" if pred.truth.shape[0] > 1 and name == "truth" else name)
    col_labels = [f"{t}*" if t < pred.context else str(t) for t in range(length)]
    if title is None:
        title = f"open loop: * = {pred.context} observed frames, then imagined from the recorded actions"
    return labelled_grid(cells, row_labels=labels, col_labels=col_labels, title=title, scale=scale)


SEQUENCES = 4
"""Sequences in a training strip."""
LENGTH = CONTEXT + 15
"""Steps per sequence in a training strip: the observed context, then 15 imagined (the imagination horizon)."""

SamplerFactory = Callable[[int], Iterator[Mapping[str, np.ndarray]]]
"""``seed -> iterator of batches (B, L, ...)``: the offline trainers' ``make_sampler``."""


def world_models_of(agent: Any) -> dict[str, Any]:
    """The world models an agent trains, by name: a DreamerV2 (CoWorld's source agent among them) -> ``{"model"}``,
    a CoWorld -> ``{"target", "source"}``; others -> ``{}``."""
    if hasattr(agent, "world_model"):
        return {"model": agent.world_model}
    if hasattr(agent, "target") and hasattr(agent, "source"):
        return {"target": agent.target.world_model, "source": agent.source.world_model}
    return {}


def strip_sequences(source: SamplerFactory | EpisodeSource, seed: int = 0) -> dict[str, np.ndarray] | None:
    """``SEQUENCES`` windows of up to ``LENGTH`` steps from ``source``; None when too short to imagine anything."""
    if callable(source):
        batch = {key: np.asarray(value)[:SEQUENCES, :LENGTH] for key, value in next(iter(source(seed))).items()}
    else:
        pick = get_episodes(source, evenly_spaced(count_episodes(source), SEQUENCES))
        if not pick:
            return None
        rng = np.random.default_rng(seed)
        starts = [int(rng.integers(0, max(1, len(ep["reward"]) - LENGTH + 1))) for ep in pick]
        batch = episode_windows(pick, LENGTH, starts)
    return batch if batch["image"].shape[1] > CONTEXT else None


def log_open_loop(
    logger: Any, agent: Any, source: SamplerFactory | EpisodeSource, step: int, *, tag: str, unit: str = "step"
) -> dict[str, float]:
    """Log the open-loop strip of ``agent``'s world models on sequences of ``source`` at ``step`` (counting
    ``unit``, see :meth:`~coworld.training.logger.Logger.log`).

    Does nothing (returns ``{}``) for agents without a world model and for sequences too short to imagine.
    Returns the logged scalars.
    """
    models = world_models_of(agent)
    if not models:
        return {}
    batch = strip_sequences(source)
    if batch is None:
        return {}
    pred = predict(models, batch, CONTEXT)
    logger.log_image(tag, prediction_strip(pred, title=f"{tag} at step {step}"), step)
    imagined = pred.imagined_error()
    metrics = {f"{tag}/mse" if len(imagined) == 1 else f"{tag}/mse_{name}": value for name, value in imagined.items()}
    logger.log(metrics, step, unit=unit)
    return metrics
