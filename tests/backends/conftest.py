"""What the backend tests share: whether the CPU fast path serves the models the presets build.

A research edit may make the default model leave the fast path (an edited image term, a norm in the decoder): that
is a legitimate change, and one test says so, :data:`DEFAULT_TEST`. The tests that need a model the fast path
serves take the :func:`fast_path` fixture, which skips them (``pytest -ra`` lists the skips) naming that test,
rather than failing each for the same reason.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import pytest
import torch

from coworld import backends
from coworld.config import Config, make_config
from coworld.models.world_model import WorldModel

DEFAULT_TEST = "tests/backends/test_backends.py::test_the_default_model_takes_the_fast_path"
"""The one test that fails where a preset's model no longer takes the fast path."""

SERVED_PRESETS: dict[str, tuple[str, tuple[str, ...]]] = {
    "tiny": ("tiny", ()),
    "cpu": ("cpu", ()),  # unimix, two-hot heads, LayerNorm + SiLU heads
    "tiny at cnn_depth 16": ("tiny", ("world_model.cnn_depth=16",)),  # the decoder ends at 2 x 2 phases
    "paper": ("paper", ()),  # the paper's widths (GRU bias, eps 1e-3)
}
"""The models the fast path serves as the code stands (preset, overrides), by name."""

_VERDICTS: dict[tuple[str, tuple[str, ...]], str] = {}


def fast_path_reason(preset: str = "tiny", overrides: Sequence[str] = ()) -> str:
    """Why the CPU fast path does not serve the model ``preset`` with ``overrides`` builds (3 actions), '' where it
    does; checked once per session (the verdict is the model code's, which a test's own patches come after)."""
    key = (preset, tuple(overrides))
    if key not in _VERDICTS:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            model = WorldModel(config=make_config(preset, list(overrides)).world_model, action_size=3)
        _VERDICTS[key] = backends.cpu_reason(model)
    return _VERDICTS[key]


@pytest.fixture
def fast_path() -> Callable[..., Config]:
    """``fast_path(preset='tiny', overrides=())``: the config of a model the CPU fast path serves; the test is
    skipped where that model no longer takes the path (:data:`DEFAULT_TEST` fails then, saying why)."""

    def served(preset: str = "tiny", overrides: Sequence[str] = ()) -> Config:
        reason = fast_path_reason(preset, overrides)
        if reason:
            model = f"{preset} ({', '.join(overrides)})" if overrides else preset
            pytest.skip(
                f"needs a model the CPU fast path serves; the {model} model no longer takes it ({DEFAULT_TEST})"
            )
        return make_config(preset, list(overrides))

    return served


@pytest.fixture
def preset_verdicts() -> dict[str, str]:
    """:data:`SERVED_PRESETS`' models by name: why the fast path does not serve each, '' where it does."""
    return {name: fast_path_reason(preset, overrides) for name, (preset, overrides) in SERVED_PRESETS.items()}
