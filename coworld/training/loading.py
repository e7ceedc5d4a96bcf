"""What a run folder holds, checked against what the folder says before anything uses it.

``eval``, ``viz`` and a resumed ``train`` read a run folder's description (``run.json``: algorithm, tasks), its
config (``config.json``) and its checkpoint. A checkpoint copied in from another run would otherwise be scored,
pictured or trained on under the folder's name (a penalised DreamerV2's weights load into an offline DreamerV2,
whose ``load_state_dict`` reads only its own entries). So the checkpoint must be of the folder's algorithm
(its ``kind``), of its target (and source) task and of its config, which fixes every network's shape; a mismatch is
one CheckpointError line, before any work.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from coworld.algorithms import ALGOS, algorithm
from coworld.config import Config, first_difference, from_dict, to_dict
from coworld.envs import task_spec
from coworld.errors import CheckpointError, CoworldError
from coworld.training.checkpoint import CHECKPOINT_NAME, load_checkpoint
from coworld.training.job import parse_sources
from coworld.training.run import load_run

ONLINE_KIND = "dreamerv2-online"
"""The checkpoint of an agent that learned online (the dreamerv2 collector, a source agent's pretraining)."""


def checkpoint_kind(info: Mapping[str, Any]) -> str:
    """The ``kind`` of the checkpoint a run of this description writes."""
    return ONLINE_KIND if info.get("online") else algorithm(str(info["algo"])).checkpoint


def open_run(path: str | Path) -> tuple[Path, Path, Config, dict[str, Any]]:
    """The run folder of ``path`` (a run folder or its checkpoint file), the checkpoint file, the config and the run
    description, all checked to exist and read; problems raise one CoworldError line naming what was given."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"no run folder or checkpoint at {path}; pass a run folder made by `coworld train`")
    if path.is_dir():
        run_dir, ckpt = path, path / CHECKPOINT_NAME
    else:
        run_dir, ckpt = path.parent, path
        if not (run_dir / "run.json").is_file():
            raise CheckpointError(
                f"{path} is not inside a run folder ({run_dir} has no run.json), so nothing says what it holds;"
                f" pass a run folder made by `coworld train` or the {CHECKPOINT_NAME} inside one"
            )
    config, info = load_run(run_dir)
    described = run_dir / "run.json"
    if info["algo"] not in ALGOS:
        raise CoworldError(
            f"{described} is damaged (an unknown algorithm {info['algo']!r}; coworld trains {', '.join(ALGOS)})"
        )
    if not isinstance(info.get("target"), str):
        raise CoworldError(f"{described} is damaged (no target: it does not say which task the run learned)")
    task_spec(info["target"])  # a task this version knows
    if not ckpt.is_file():
        raise CheckpointError(
            f"{run_dir} holds no {CHECKPOINT_NAME} yet (its training stopped before its first checkpoint); rerun"
            " the command that made it to continue, and use the folder once a checkpoint is written"
        )
    return run_dir, ckpt, config, info


def load_run_checkpoint(
    ckpt: Path, config: Config, info: Mapping[str, Any], *, keys: Sequence[str] = ("agent",), **load: Any
) -> dict[str, Any]:
    """The checkpoint ``ckpt`` of the run described by ``config`` and ``info``, checked by :func:`check_matches`;
    one without an entry of ``keys`` is damaged, unless it is another run's (then that is what is said)."""
    try:
        state = load_checkpoint(ckpt, keys=keys, **load)
    except CheckpointError:
        check_matches(load_checkpoint(ckpt, mmap=True), ckpt, config, info)  # another run's is called that
        raise
    check_matches(state, ckpt, config, info)
    return state


def sources(info: Mapping[str, Any]) -> list[str]:
    """The source tasks a run description names: one, or the candidates of CoWorld's automatic choice (the chosen
    one is what its checkpoint records)."""
    return list(parse_sources(str(info["source"])))


def check_matches(state: Mapping[str, Any], ckpt: Path, config: Config, info: Mapping[str, Any]) -> None:
    """Refuse a checkpoint that is not what its run folder says: another algorithm, target or source task, or
    config (the config fixes every network's shape)."""
    expected = checkpoint_kind(info)
    label = f"{ckpt.parent} is a {info['algo']} run of {info['target']}"
    fix = "it was copied from another run: put it back in the folder it came from, or use that folder"
    if state.get("kind") != expected:
        raise CheckpointError(f"{ckpt} is a {state.get('kind')!r} checkpoint but {label}; {fix}")
    if "task" in state and state["task"] != info["target"]:
        raise CheckpointError(f"{ckpt} was trained on {state['task']} but {label}; {fix}")
    if "source_task" in state and info.get("source") is not None and state["source_task"] not in sources(info):
        raise CheckpointError(f"{ckpt} learned from source {state['source_task']}, not {info['source']}; {fix}")
    saved = state.get("config")
    if isinstance(saved, Mapping):
        try:  # read as config.json was: keys added since it was saved take the values the older code computed with
            saved = to_dict(from_dict(saved))
        except CoworldError:
            pass  # a config this version cannot read: compared as it is, so its first odd key is named
        diff = first_difference(dict(saved), to_dict(config))
        if diff:
            raise CheckpointError(f"{ckpt} was made with other settings than {ckpt.parent}/config.json ({diff}); {fix}")
