"""Pictures into PNG / GIF / MP4 files chosen by suffix (the pictures themselves: :mod:`coworld.pictures`).

Every file is written whole to a temporary name in its folder, then renamed, so an interrupted command leaves
either the old file or the new one.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from coworld.errors import CoworldError
from coworld.pictures import pad_even
from coworld.storage import write_text_atomically

IMAGE_SUFFIXES = (".png",)
VIDEO_SUFFIXES = (".mp4", ".gif")


def require_extra(*modules: str) -> None:
    """Raise one CoworldError line with the install hint when a module of the ``viz`` extra is missing."""
    for name in modules:
        if importlib.util.find_spec(name) is None:
            raise CoworldError(f"{name} is needed for this picture; install it with pip install 'coworld[viz]'")


def output_kind(path: str | Path, allowed: Sequence[str] = IMAGE_SUFFIXES + VIDEO_SUFFIXES) -> str:
    """``'image'`` or ``'video'`` by the suffix of ``path``; any other suffix raises one CoworldError line."""
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        raise CoworldError(f"{path}: cannot write {suffix or 'a file without suffix'}; use one of {', '.join(allowed)}")
    return "image" if suffix in IMAGE_SUFFIXES else "video"


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """Write uint8 ``(H, W, 3)`` as a PNG, atomically."""
    import imageio.v2 as imageio

    path = Path(path)
    output_kind(path, IMAGE_SUFFIXES)
    with _atomic(path) as tmp:
        imageio.imwrite(tmp, np.asarray(image, np.uint8))
    return path


def write_video(path: str | Path, frames: np.ndarray, fps: int = 10) -> Path:
    """Write uint8 ``(T, H, W, 3)`` as an MP4 or GIF (by suffix), atomically."""
    from coworld.training.evaluate import write_video as write_episodes

    path = Path(path)
    output_kind(path, VIDEO_SUFFIXES)
    with _atomic(path) as tmp:
        write_episodes(tmp, [pad_even(np.asarray(frames, np.uint8))], fps=fps, scale=1)
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path``, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomically(path, text)
    return path


def write_figure(path: str | Path, figure: Any) -> Path:
    """Save a matplotlib figure as a PNG, atomically."""
    path = Path(path)
    output_kind(path, IMAGE_SUFFIXES)
    with _atomic(path) as tmp:
        figure.savefig(tmp, dpi=100)
    return path


@contextlib.contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    """``with _atomic(path) as tmp``: write ``tmp`` (same folder, same suffix), renamed to ``path`` on success."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
