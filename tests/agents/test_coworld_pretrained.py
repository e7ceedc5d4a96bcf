"""Shared source pretraining (coworld.training.pretrained): runs that differ only in the target phases' settings
pretrain to the same bits, and a run started from another's kept pretraining ends with the weights it would have
had after pretraining itself."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from coworld.config import to_dict
from coworld.data import open_dataset
from coworld.errors import CoworldError
from coworld.training.pretrained import SHARED_KEYS, SNAPSHOT
from coworld.training.run import prepare_run_dir
from coworld.training.train import check_job, run_job

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ON = [
    "coworld.iterations=3",
    "coworld.target_updates=3",
    "coworld.eval_every=2",
    "coworld.beta2=1.0",
    "coworld.align_on=embedding",
    "coworld.k=0.9",
    "coworld.relabel=later",
    "coworld.reward_mix=eta",
    "coworld.eta_start=0.9",
    "coworld.eta_end=0.1",
    "coworld.alpha=1.0",
    "coworld.zeta=3",
    "coworld.cap_form=on_mean",
    "offline.updates=9",
    "offline.log_every=3",
    "offline.eval_every=3",
    "offline.eval_episodes=1",
    "offline.checkpoint_every=3",
]
"""Every shared setting that a value changes, Eqs. 3-6 on (and the offline baselines' schedule)."""
OFF = [
    "coworld.iterations=1",
    "coworld.target_updates=1",
    "coworld.source_updates=1",
    "coworld.align=false",
    "coworld.reward_relabel=false",
    "coworld.value_reg=false",
]
"""And the switches that turn Eqs. 3-6 off (the shortest run that pretrains)."""


def test_the_settings_shared_leave_pretraining_alone_and_a_run_from_shared_pretraining_ends_as_its_own(
    tmp_path: Path, toy_dataset_writer, coworld_toy_job, toy_schedule
) -> None:
    job, schedule = coworld_toy_job, toy_schedule
    assert {o.split("=")[0] for o in ON + OFF} == SHARED_KEYS  # the test changes every key the module names
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    runs = {name: tmp_path / name for name in ("a", "on", "off", "on-shared")}
    run_job(job(dataset, runs["a"], schedule, keep_pretrained=True), progress=False)
    run_job(job(dataset, runs["on"], schedule + ON, keep_pretrained=True), progress=False)
    run_job(job(dataset, runs["off"], schedule + OFF, keep_pretrained=True), progress=False)
    kept = {name: _load(runs[name] / SNAPSHOT / "checkpoint.pt") for name in ("a", "on", "off")}
    assert kept["a"]["progress"] == {"iteration": 0, "phase": "target", "last_eval": None}
    for name in ("on", "off"):
        assert _differences(_but_config(kept["a"]), _but_config(kept[name])) == []
        assert _episodes(runs[name] / SNAPSHOT / "source_replay.h5") == _episodes(
            runs["a"] / SNAPSHOT / "source_replay.h5"
        )

    not_started = tmp_path / "not-started"  # a sweep's run folder before its run: passed over
    not_started.mkdir()
    shared = job(dataset, runs["on-shared"], schedule + ON, pretrained_from=[not_started, runs["a"]])
    summary = run_job(shared, progress=False)
    assert summary["iterations"] == 3
    own, from_shared = _load(runs["on"] / "checkpoint.pt"), _load(runs["on-shared"] / "checkpoint.pt")
    # every weight, optimiser state, counter and random state (configs apart: compared next)
    assert _differences(_but_config(own), _but_config(from_shared)) == []
    assert from_shared["config"] == own["config"] == to_dict(shared.config)
    assert _episodes(runs["on-shared"] / "source_replay.h5") == _episodes(runs["on"] / "source_replay.h5")
    pretraining = (runs["a"] / SNAPSHOT / "metrics.jsonl").read_text()
    assert (runs["on-shared"] / "metrics.jsonl").read_text().startswith(pretraining)
    assert not (runs["on-shared"] / SNAPSHOT).exists()  # kept only where asked


@pytest.mark.parametrize(
    ("overrides", "algo", "message"),
    [
        (["coworld.pretrain_steps=200"], "coworld", "pretrains with other settings (coworld.pretrain_steps: saved 100"),
        (["coworld.cap_critic=target_policy"], "coworld", "(coworld.cap_critic: saved 'source'"),
        ([], "dreamerv2", "dreamerv2 has none"),
    ],
)
def test_a_run_whose_pretraining_differs_is_refused_before_anything_is_written(
    overrides: list[str], algo: str, message: str, tmp_path: Path, toy_dataset_writer, coworld_toy_job, toy_schedule
) -> None:
    schedule = toy_schedule
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    donor = tmp_path / "donor"
    described = coworld_toy_job(dataset, donor, schedule + OFF)
    prepare_run_dir(donor, described.config, described.info())  # a run folder, described by its config
    with pytest.raises(CoworldError, match=message.replace("(", r"\(").replace(")", r"\)")):
        check_job(
            algo=algo,
            source="toy_reach",
            target="toy_reach_shifted",
            dataset=dataset,
            preset="tiny",
            logdir=tmp_path / "new",
            seed=0,
            device="cpu",
            overrides=schedule + OFF + overrides,
            pretrained_from=[donor],
        )
    assert not (tmp_path / "new").exists()


def _load(path: Path) -> dict[str, Any]:
    return torch.load(path, weights_only=True)


def _but_config(state: dict[str, Any]) -> dict[str, Any]:
    """The state without its config and without where its metrics log stood (``metrics_mark``: the log holds wall
    times, so two runs' logs differ in their bytes however alike their training)."""
    kept = {key: value for key, value in state.items() if key != "config"}
    if isinstance(kept.get("source_online"), dict):
        kept["source_online"] = {k: v for k, v in kept["source_online"].items() if k != "metrics_mark"}
    return kept


def _differences(a: Any, b: Any, path: str = "") -> list[str]:
    """The paths where two nested states differ in structure or value, tensors element for element."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{path}: keys {sorted(a.keys() ^ b.keys())}"]
        return [d for key in a for d in _differences(a[key], b[key], f"{path}/{key}")]
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        if len(a) != len(b):
            return [f"{path}: length"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in _differences(x, y, f"{path}/{i}")]
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return [] if a.shape == b.shape and torch.equal(a, b) else [path]
    if isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
        return [] if np.array_equal(a, b) else [path]
    return [] if a == b else [path]


def _episodes(path: Path) -> list[bytes]:
    """Each stored episode's arrays, as bytes."""
    with open_dataset(path) as data:
        return [
            b"".join(np.ascontiguousarray(v).tobytes() for v in data.episode(i).values())
            for i in range(data.num_episodes)
        ]
