"""Checkpoints written before the reference model (issue 50) load and evaluate as they did."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from coworld.cli import main

FIXTURE = Path(__file__).parents[1] / "fixtures" / "d01ae27-dreamerv2"


def test_a_d01ae27_checkpoint_evaluates_with_the_returns_and_values_it_had(tmp_path: Path) -> None:
    """Its config has no GRU bias or epsilon keys (read as the older code computed: no bias, 1e-5), its state dict
    the keys of the old modules; the same seed gives the same episodes, returns and value estimates as d01ae27's own
    evaluation, to float rounding."""
    run = shutil.copytree(FIXTURE / "run", tmp_path / "run")
    out = tmp_path / "eval.json"
    args = ["eval", "--ckpt", str(run), "--episodes", "3", "--seed", "0", "--task", "toy_reach"]
    result = CliRunner().invoke(main, [*args, "--out", str(out), "--device", "cpu"])
    assert result.exit_code == 0, result.output
    got, want = json.loads(out.read_text()), json.loads((FIXTURE / "eval-d01ae27.json").read_text())
    assert len(set(np.round(want["returns"], 3))) == 3  # the episodes differ: the comparison can fail
    for key in ("returns", "value_estimate", "value_true"):
        np.testing.assert_allclose(got[key], want[key], rtol=1e-4, atol=1e-5, err_msg=key)
