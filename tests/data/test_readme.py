"""The loading snippet of datasets/README.md runs with plain h5py (coworld blocked) on a generated dataset."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

README = Path(__file__).parents[2] / "datasets" / "README.md"


def _loading_snippet() -> str:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    snippets = [block for block in blocks if "import h5py" in block]
    assert len(snippets) == 1, "the README should have exactly one plain-h5py loading snippet"
    return snippets[0]


def test_loading_snippet_runs_without_coworld(
    tmp_path: Path, dataset_path: Path, episodes: list[dict[str, Any]]
) -> None:
    snippet = _loading_snippet()
    assert "coworld" not in snippet
    assert 'path = "datasets/walker_walk-random.h5"' in snippet
    code = snippet.replace("datasets/walker_walk-random.h5", str(dataset_path))
    out = tmp_path / "out.npz"
    script = (
        "import sys\nsys.modules['coworld'] = None  # importing coworld would fail\n"
        + code
        + f"\nnp.savez({str(out)!r}, frames=frames, next_observations=next_observations, actions=actions)\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("fake_task random 102 rows in 7 episodes, action repeat 2"), result.stdout
    got = np.load(out)
    np.testing.assert_array_equal(got["frames"], episodes[0]["observations"])
    np.testing.assert_array_equal(got["actions"], episodes[0]["actions"])
    expected_next = np.concatenate([ep["observations"][1:] for ep in episodes])
    np.testing.assert_array_equal(got["next_observations"], expected_next)
