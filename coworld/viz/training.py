"""What the training loops call at every evaluation: an open-loop prediction strip into TensorBoard.

The strip is one image (``Logger.log_image``, TensorBoard's ``add_image``), not a video: an image needs nothing
beyond TensorBoard itself (``add_video`` needs moviepy), and it shows every step of every sequence at once, which
is what one compares from one evaluation to the next. The same sequences are shown each time (evenly spaced
episodes, windows drawn with a fixed seed), so the strips of one run can be compared directly. Beside the image,
the mean error over the imagined steps is logged as a scalar ``<tag>/mse`` (``<tag>/mse_<model>`` for CoWorld).
Nothing here draws from the global random generators, so a run's batches are the same with or without it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np

from coworld.viz.predictions import CONTEXT, predict, prediction_strip
from coworld.viz.runs import EpisodeSource, count_episodes, episode_windows, evenly_spaced, get_episodes

SEQUENCES = 4
"""Sequences in a training strip."""
LENGTH = CONTEXT + 15
"""Steps per sequence in a training strip: the observed context, then 15 imagined (the imagination horizon)."""

SamplerFactory = Callable[[int], Iterator[Mapping[str, np.ndarray]]]
"""``seed -> iterator of batches (B, L, ...)``: the offline trainers' ``make_sampler``."""


def world_models_of(agent: Any) -> dict[str, Any]:
    """The world models an agent trains, by name: a DreamerV2 -> ``{"model"}``, a CoWorld -> ``{"target",
    "source"}``, CoWorld's source learner (what its online trainer drives) -> ``{"source"}``; others -> ``{}``."""
    if hasattr(agent, "world_model"):
        return {"model": agent.world_model}
    if hasattr(agent, "target") and hasattr(agent, "source"):
        return {"target": agent.target.world_model, "source": agent.source.world_model}
    if hasattr(agent, "coworld"):
        return {"source": agent.coworld.source.world_model}
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
