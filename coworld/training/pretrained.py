"""Shared source pretraining: CoWorld runs that differ only in their target phases' settings start from one run's
pretraining instead of each pretraining a source agent of its own.

Algorithm 1's line 3 trains the source agent alone, online (:meth:`~coworld.training.coworld.Algorithm1.
pretrain_source`): the target agent is built and left as built, and no term of Eqs. 3-6 runs, so none of
:data:`SHARED_KEYS` is read. Runs whose configs differ only there pretrain to the same bits
(tests/agents/test_coworld_pretrained.py changes every one of them). A run started with ``--keep-pretrained`` keeps
a copy of its folder as pretraining left it, ``pretrained/``; a new run started with ``--pretrained-from DIR`` copies
DIR's in and resumes from it as from a stop, so it ends with the weights it would have had after pretraining itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coworld.algorithms import algorithm
from coworld.config import Config, first_difference, to_dict
from coworld.errors import CoworldError
from coworld.storage import copy_file_atomically
from coworld.training.checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint

SNAPSHOT = "pretrained"
"""The folder, inside a run folder, of its pretraining's end."""
COPIED = ("source_replay.h5", "metrics.jsonl")
"""What a snapshot holds besides its checkpoint, which is written last: a snapshot with a checkpoint is whole."""
SHARED_KEYS = frozenset(
    {f"offline.{key}" for key in ("updates", "log_every", "eval_every", "eval_episodes", "checkpoint_every")}
) | frozenset(
    f"coworld.{key}"
    for key in (
        # Algorithm 1's loop after pretraining
        "iterations",
        "target_updates",
        "source_updates",
        "eval_every",
        # Eq. 3's alignment, Eqs. 4-5's relabelled reward, Eq. 6's value cap: target phases and source phases only
        "align",
        "beta2",
        "align_on",
        "reward_relabel",
        "k",
        "relabel",
        "reward_mix",
        "eta_start",
        "eta_end",
        "value_reg",
        "alpha",
        "zeta",
        "cap_form",
    )
)
"""The settings that source pretraining never reads: the offline baselines' schedule and what CoWorld does after
pretraining (``coworld.cap_critic`` is not one: the target-policy critic
learns from the source agent's first update on)."""


def pretraining_difference(saved: Config, now: Config) -> str:
    """The first setting outside :data:`SHARED_KEYS` where two runs' configs differ (``'key: saved X, now Y'``),
    '' where they pretrain alike."""

    def pretraining(config: Config) -> dict[str, Any]:
        settings = to_dict(config)
        for key in SHARED_KEYS:
            section, name = key.split(".")
            settings[section].pop(name)
        return settings

    return first_difference(pretraining(saved), pretraining(now))


def keep(logdir: Path, state: dict[str, Any]) -> None:
    """Copy the run's source experience and metrics as they stand into ``logdir/pretrained``, then save ``state``
    (the checkpoint the run writes at the end of its pretraining) there."""
    folder = logdir / SNAPSHOT
    folder.mkdir(exist_ok=True)
    (folder / CHECKPOINT_NAME).unlink(missing_ok=True)  # rewritten (a rerun after a stop): not whole until saved
    for name in COPIED:
        copy_file_atomically(logdir / name, folder / name)
    save_checkpoint(folder / CHECKPOINT_NAME, state)


def check_donors(donors: Sequence[Path], *, config: Config, info: dict[str, Any]) -> None:
    """The run is a CoWorld run of one source, and each ``--pretrained-from`` folder a CoWorld run of its tasks and
    dataset whose pretraining is this run's (one CoworldError line otherwise); a folder that holds no run yet (a
    sweep's run still to start) passes."""
    from coworld.training.run import load_run

    if not algorithm(info["algo"]).collaborative:
        raise CoworldError(
            f"--keep-pretrained and --pretrained-from share CoWorld's source pretraining; {info['algo']} has none"
        )
    if "," in str(info["source"]):
        raise CoworldError(
            "--keep-pretrained and --pretrained-from take one --source; CoWorld's choice among several pretrains each"
        )
    for donor in donors:
        if not donor.is_dir():
            raise CoworldError(f"--pretrained-from {donor}: no such run folder")
        if not (donor / "config.json").exists():
            continue
        saved, described = load_run(donor)
        for key in ("algo", "source", "target"):
            if described.get(key) != info[key]:
                raise CoworldError(
                    f"--pretrained-from {donor} is a run of {key} {described.get(key)}, not {info[key]}; pass a run"
                    " of this run's algorithm and tasks"
                )
        if Path(described["dataset"]).resolve() != Path(info["dataset"]).resolve():
            raise CoworldError(f"--pretrained-from {donor} learned from {described['dataset']}, not {info['dataset']}")
        if diff := pretraining_difference(saved, config):
            raise CoworldError(
                f"--pretrained-from {donor} pretrains with other settings ({diff}); runs may differ only in"
                f" {', '.join(sorted(SHARED_KEYS))}"
            )


def start_from(logdir: Path, donors: Sequence[Path], config: Config) -> Path | None:
    """Copy the first of ``donors`` with a whole snapshot into ``logdir``, a run folder that has not started yet,
    its checkpoint last and rewritten with this run's ``config``; the donor, or None where none has one yet."""
    if (logdir / CHECKPOINT_NAME).exists() or (logdir / "source" / CHECKPOINT_NAME).exists():
        return None  # the run has started: it resumes its own
    donor = next((d for d in donors if (d / SNAPSHOT / CHECKPOINT_NAME).exists()), None)
    if donor is None:
        return None
    for name in COPIED:
        copy_file_atomically(donor / SNAPSHOT / name, logdir / name)
    state = load_checkpoint(donor / SNAPSHOT / CHECKPOINT_NAME)
    save_checkpoint(logdir / CHECKPOINT_NAME, {**state, "config": to_dict(config)})
    return donor
