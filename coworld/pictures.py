"""Frames into pictures: labelled grids of equal-sized cells, text drawn with OpenCV's Hershey font
(``cv2.putText``). Training logs its open-loop strips with these; :mod:`coworld.viz` writes them to files."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

__all__ = ["labelled_grid", "pad_even", "put_text", "stack_frames", "text_size", "upscale"]

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_FONT_SCALE = 0.4
_TEXT_COLOUR = (20, 20, 20)
_BACKGROUND = 255
_PAD = 4


def upscale(image: np.ndarray, scale: int) -> np.ndarray:
    """Nearest-neighbour enlargement of ``(..., H, W, C)`` by an integer ``scale``."""
    if scale == 1:
        return image
    return image.repeat(scale, axis=-3).repeat(scale, axis=-2)


def text_size(text: str) -> tuple[int, int]:
    """(width, height) in pixels of ``text`` drawn by :func:`put_text`, the baseline's descent included."""
    (width, height), baseline = cv2.getTextSize(text, _FONT, _FONT_SCALE, 1)
    return width, height + baseline


def put_text(
    image: np.ndarray, text: str, x: int, y: int, colour: tuple[int, int, int] = _TEXT_COLOUR, box: bool = False
) -> None:
    """Draw ``text`` into the uint8 ``(H, W, 3)`` ``image`` in place, its top-left corner at ``(x, y)``;
    ``box`` draws it on a black box (readable on any picture)."""
    (width, height), baseline = cv2.getTextSize(text, _FONT, _FONT_SCALE, 1)
    if box:
        image[max(0, y - 1) : y + height + baseline, max(0, x - 1) : x + width + 1] = 0
    cv2.putText(image, text, (x, y + height), _FONT, _FONT_SCALE, colour, 1, cv2.LINE_AA)


def labelled_grid(
    cells: Sequence[Sequence[np.ndarray]],
    *,
    row_labels: Sequence[str] | None = None,
    col_labels: Sequence[str] | None = None,
    title: str | None = None,
    scale: int = 1,
    gap: int = 2,
) -> np.ndarray:
    """Rows of equal-sized uint8 cells ``(h, w, 3)`` laid out on a white canvas with text around them.

    Row labels go to the left of each row, column labels above the first row, the title above everything.
    Each cell is enlarged ``scale`` times (nearest neighbour) and cells are ``gap`` pixels apart.

    Returns:
        uint8 ``(H, W, 3)``.
    """
    if not cells or not cells[0]:
        raise ValueError("labelled_grid needs at least one row with one cell")
    h, w = cells[0][0].shape[:2]
    h, w = h * scale, w * scale
    rows, cols = len(cells), max(len(row) for row in cells)
    line = text_size("Ag")[1] + _PAD
    left = max((text_size(label)[0] for label in row_labels or ()), default=-_PAD) + 2 * _PAD
    top = (line if title else 0) + (line if col_labels else 0) + _PAD
    width = left + cols * (w + gap) - gap + _PAD
    if title:
        width = max(width, text_size(title)[0] + 2 * _PAD)
    canvas = np.full((top + rows * (h + gap) - gap + _PAD, width, 3), _BACKGROUND, np.uint8)
    if title:
        put_text(canvas, title, _PAD, _PAD)
    for j, label in enumerate(col_labels or ()):
        put_text(canvas, label, left + j * (w + gap), top - line)
    for i, row in enumerate(cells):
        y = top + i * (h + gap)
        if row_labels:
            put_text(canvas, row_labels[i], _PAD, y + (h - text_size(row_labels[i])[1]) // 2)
        for j, cell in enumerate(row):
            if cell.shape[:2] != cells[0][0].shape[:2]:
                raise ValueError(f"cell ({i}, {j}) has shape {cell.shape}, not {cells[0][0].shape}")
            x = left + j * (w + gap)
            canvas[y : y + h, x : x + w] = upscale(np.asarray(cell, np.uint8), scale)
    return canvas


def stack_frames(frames: Sequence[np.ndarray]) -> np.ndarray:
    """Stack uint8 ``(H_i, W_i, 3)`` pictures into ``(T, H, W, 3)``, padding each with white to the largest size."""
    h = max(frame.shape[0] for frame in frames)
    w = max(frame.shape[1] for frame in frames)
    out = np.full((len(frames), h, w, 3), _BACKGROUND, np.uint8)
    for i, frame in enumerate(frames):
        out[i, : frame.shape[0], : frame.shape[1]] = frame
    return out


def pad_even(frames: np.ndarray) -> np.ndarray:
    """Pad ``(..., H, W, 3)`` with white on the bottom and right to even H and W (what H.264 needs)."""
    h, w = frames.shape[-3:-1]
    pad = [(0, 0)] * (frames.ndim - 3) + [(0, h % 2), (0, w % 2), (0, 0)]
    return np.pad(frames, pad, constant_values=_BACKGROUND) if h % 2 or w % 2 else frames
