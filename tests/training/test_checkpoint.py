import os
import pickle

import numpy as np
import pytest
import torch

from coworld.errors import CheckpointError
from coworld.training.checkpoint import load_checkpoint, rng_state, save_checkpoint, set_rng_state


def test_round_trip_and_rng(tmp_path):
    state = {"kind": "test", "weights": {"w": torch.arange(4.0)}, "step": 7, "rng": rng_state()}
    save_checkpoint(tmp_path / "ckpt.pt", state)
    expected = (np.random.rand(), torch.rand(1).item())
    loaded = load_checkpoint(tmp_path / "ckpt.pt")
    assert loaded["step"] == 7 and torch.equal(loaded["weights"]["w"], torch.arange(4.0))
    set_rng_state(loaded["rng"])
    assert (np.random.rand(), torch.rand(1).item()) == expected
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_save_replaces_atomically(tmp_path):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"kind": "test", "v": 1})
    save_checkpoint(path, {"kind": "test", "v": 2})
    assert load_checkpoint(path)["v"] == 2


def test_missing_and_corrupt(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint at"):
        load_checkpoint(tmp_path / "absent.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(bad)
    good = tmp_path / "good.pt"
    save_checkpoint(good, {"kind": "test", "w": torch.zeros(1000)})
    truncated = tmp_path / "trunc.pt"
    truncated.write_bytes(good.read_bytes()[:500])
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(truncated)


class Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_refuses_pickled_code(tmp_path):
    path = tmp_path / "evil.pt"
    with open(path, "wb") as f:
        pickle.dump({"kind": "x", "payload": Evil()}, f)
    with pytest.raises(CheckpointError):
        load_checkpoint(path)
