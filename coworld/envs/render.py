"""Offscreen rendering of MuJoCo scenes into small RGB frames (DMC, Meta-World and RoboDesk tasks).

Each environment owns one :class:`mujoco.Renderer`, i.e. its own OpenGL context, made current before every
frame. That is what lets several Meta-World environments live in one process and survive one of them being
closed: gymnasium's own Meta-World renderer draws into whatever context happens to be current, so closing one
environment (which frees its context) left the others rendering all-zero frames.

Render quality (the ``render_quality`` override). "diff" is the mean absolute pixel difference (0-255 scale)
to the simulator's own settings, over states of a random-policy episode, 64 x 64 frames, llvmpipe (software EGL):

* ``full``: the model's own settings (4x MSAA, 2048/4096 shadow map, shadows, reflections).
* ``standard`` (default): no MSAA, 512 shadow map. Diff 1.35 walker, 0.85 cheetah, 4.0 window-close (MSAA
  smooths thin edges; the shadow map size alone barely matters: 512, 256 and 128 cost and look the same).
* ``fast``: ``standard`` without shadows and reflections. Diff 8.5 walker, 1.5 cheetah, 10.8 window-close:
  without shadows the spot light's dark floor band disappears (mostly floor lighting; the body reads the same).

RoboDesk's scene has three shadow-casting lights: diff 6.2 for ``standard`` and 40 for ``fast`` (one state of a
random episode of push_button; ``full`` there equals RoboDesk's own frames).

``standard`` keeps the look of the paper's frames at a fraction of ``full``'s rendering cost; ``fast`` is cheaper
again but changes the image visibly. Use one quality for a dataset and for every policy evaluated on it.
"""

from __future__ import annotations

import atexit
import os
import weakref
from typing import TYPE_CHECKING, Literal

import numpy as np

from coworld.errors import ConfigError

if TYPE_CHECKING:
    import mujoco

RenderQuality = Literal["standard", "fast", "full"]
RENDER_QUALITIES: tuple[str, ...] = ("standard", "fast", "full")


def ensure_gl_backend() -> None:
    """Choose headless EGL rendering unless the user picked a backend with ``MUJOCO_GL``.

    Must run before ``mujoco`` is first imported (mujoco reads the variable at import time), so every builder
    calls it before its lazy simulator imports. Never called at import time of :mod:`coworld`.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")


def check_render_quality(value: object) -> RenderQuality:
    """Validate the ``render_quality`` override; raise :class:`ConfigError` with the valid values."""
    if value not in RENDER_QUALITIES:
        raise ConfigError(f"render_quality must be one of {', '.join(RENDER_QUALITIES)}; got {value!r}")
    return value  # type: ignore[return-value]


class FrameRenderer:
    """Renders one camera of a MuJoCo model into ``(size, size, 3)`` uint8 RGB frames.

    Args:
        model: the compiled model; its visual quality fields are edited in place for ``quality`` (call before
            anything else renders this model).
        camera: camera name or id, or a free camera (``mujoco.MjvCamera``).
        size: frame side in pixels.
        quality: see the module docstring.
        rotate_180: turn the frame upside down and mirror it (Meta-World's corner cameras render upside down).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        camera: str | int | mujoco.MjvCamera,
        size: int,
        quality: RenderQuality,
        rotate_180: bool = False,
    ) -> None:
        import mujoco

        if quality != "full":
            model.vis.quality.offsamples = 0
            model.vis.quality.shadowsize = 512
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, size)
        model.vis.global_.offheight = max(model.vis.global_.offheight, size)
        self._renderer: mujoco.Renderer | None = mujoco.Renderer(model, size, size)
        if quality == "fast":
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self._camera = camera
        self._rotate_180 = rotate_180
        self._frame = np.empty((size, size, 3), np.uint8)
        _LIVE.add(self)
        global _EXIT_HOOKED
        if not _EXIT_HOOKED:
            # atexit runs last-registered first: this runs before mujoco's EGL display is terminated (registered
            # when the first context was made), so live renderers are freed quietly instead of raising in __del__.
            atexit.register(_close_live)
            _EXIT_HOOKED = True

    def render(self, data: mujoco.MjData) -> np.ndarray:
        """Draw the current state of ``data``; returns a new ``(size, size, 3)`` uint8 array."""
        if self._renderer is None:
            raise RuntimeError("render called after close")
        self._renderer.update_scene(data, camera=self._camera)
        self._renderer.render(out=self._frame)
        if self._rotate_180:
            return self._frame[::-1, ::-1].copy()
        return self._frame.copy()

    def close(self) -> None:
        """Free this renderer's GL context (other renderers in the process are unaffected)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


_LIVE: weakref.WeakSet[FrameRenderer] = weakref.WeakSet()
_EXIT_HOOKED = False


def _close_live() -> None:
    for renderer in list(_LIVE):
        renderer.close()
