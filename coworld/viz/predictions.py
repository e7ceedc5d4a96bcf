"""Open-loop video prediction (the paper's Figure 5; dreamerv3's ``openl`` reports).

The world model observes the first ``context`` frames of each sequence through the posterior, then rolls its
prior forward with the recorded actions alone and decodes every state. Shown side by side over time: the true
frames, each model's frames (reconstructions during the context, predictions after it) and their absolute
difference. The error of a frame is the mean squared difference of its pixels in ``[0, 1]`` units.

Latents are taken at their mode (``sample=False``), so a prediction is deterministic and draws no random numbers:
logging one during training leaves the run's random state untouched.
"""

from __future__ import annotations

import numpy as np

from coworld.pictures import labelled_grid, stack_frames
from coworld.training.openloop import (
    CONTEXT,
    Predictions,
    Predictor,
    copy_context,
    open_loop,
    predict,
    prediction_error,
    prediction_rows,
    prediction_strip,
)

__all__ = [
    "CONTEXT",
    "Predictions",
    "Predictor",
    "copy_context",
    "error_table",
    "open_loop",
    "predict",
    "prediction_error",
    "prediction_strip",
    "prediction_video",
]


def prediction_video(pred: Predictions, *, scale: int = 2) -> np.ndarray:
    """One video frame per step: the rows truth / model / |error| (per model), one column per sequence.

    Returns uint8 ``(T, H, W, 3)``.
    """
    names, rows = prediction_rows(pred)
    errors = pred.errors
    frames = []
    for t in range(pred.truth.shape[1]):
        phase = "observed" if t < pred.context else "imagined"
        text = ", ".join(f"{name} {errors[name][:, t].mean():.4f}" for name in errors)
        cells = [list(row[:, t]) for row in rows]
        frames.append(labelled_grid(cells, row_labels=names, title=f"step {t} ({phase})  MSE {text}", scale=scale))
    return stack_frames(frames)


def error_table(pred: Predictions) -> str:
    """Per-step MSE of each model as text: one line per step, context steps marked, then the imagined mean."""
    steps = pred.step_errors()
    names = list(steps)
    width = max(10, *(len(name) + 2 for name in names))
    lines = [
        f"open-loop prediction error (MSE per frame, pixels in [0, 1]), mean over {pred.truth.shape[0]} sequences;"
        f" steps marked * are observed context",
        "step  " + "".join(f"{name:>{width}}" for name in names),
    ]
    for t in range(pred.truth.shape[1]):
        mark = "*" if t < pred.context else " "
        lines.append(f"{t:>4}{mark} " + "".join(f"{steps[name][t]:>{width}.5f}" for name in names))
    imagined = pred.imagined_error()
    lines.append("imagined steps, mean: " + ", ".join(f"{name} {value:.5f}" for name, value in imagined.items()))
    return "\n".join(lines)
