"""Atomic checkpoints that load without unpickling arbitrary objects.

A checkpoint is a dict of tensors, numbers, strings, lists, tuples and dicts written with ``torch.save`` to a
temporary file in the same folder, flushed to disk and renamed over the old one, so a kill at any moment
leaves either the previous checkpoint or the new one, never half of one. A write the system refuses (a full disk)
raises :class:`~coworld.errors.StorageError` with one line, removes the temporary file and leaves the previous
checkpoint as it was. A state holding a NaN or infinite float tensor is refused before anything is written
(:class:`~coworld.errors.NonFiniteCheckpoint`): a diverged run never replaces its last good checkpoint. Loading uses
``torch.load(weights_only=True)``: a checkpoint from an untrusted source cannot run code.
"""

from __future__ import annotations

import math
import os
import random
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from coworld.config import to_dict
from coworld.errors import CheckpointError, NonFiniteCheckpoint, StorageError
from coworld.storage import WRITE_ERRNOS, failure_errno, failure_reason
from coworld.training.description import EARLIER_RELEASE

CHECKPOINT_NAME = "checkpoint.pt"


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> None:
    """Write ``state`` to ``path`` atomically (write to a temporary file, fsync, rename); a state with a non-finite
    float tensor is refused first (:class:`~coworld.errors.NonFiniteCheckpoint`), leaving ``path`` as it was."""
    path = Path(path)
    damaged = first_non_finite(state)
    if damaged is not None:
        entry, value = damaged
        kept = f"the previous checkpoint {path} is kept as it was" if path.exists() else "no earlier checkpoint exists"
        raise NonFiniteCheckpoint(
            f"refusing to write checkpoint {path}: {entry} holds {value} values; {kept}",
            path=str(path),
            entry=entry,
            value=value,
        )
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            out = _Recording(f)
            try:
                torch.save(state, out)
            except RuntimeError as err:  # torch reports a failed write as "unexpected pos ..."; the OSError says why
                raise (out.error or err) from None
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except (OSError, RuntimeError) as err:
        tmp.unlink(missing_ok=True)
        if failure_errno(err) not in WRITE_ERRNOS:
            raise
        kept = "the previous checkpoint is intact" if path.exists() else "no earlier checkpoint exists"
        reason = failure_reason(err)
        raise StorageError(f"cannot save checkpoint {path}: {reason}; {kept}", reason) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def first_non_finite(state: Any, prefix: str = "") -> tuple[str, str] | None:
    """The first float tensor of ``state`` (dicts, lists and tuples walked in order) holding a NaN or an infinity, as
    ``(entry, value)``: its path (``agent/world_model/encoder.net.0.weight``) and ``nan``, ``inf`` or ``-inf``; None
    where every one is finite. It reads the tensors and changes nothing."""
    if isinstance(state, torch.Tensor):
        if not (state.is_floating_point() or state.is_complex()) or bool(torch.isfinite(state).all()):
            return None
        value = "nan" if bool(torch.isnan(state).any()) else "inf" if bool((state == math.inf).any()) else "-inf"
        return prefix, value
    if isinstance(state, dict):
        items: Any = state.items()
    elif isinstance(state, list | tuple):
        items = enumerate(state)
    else:
        return None
    for key, value in items:
        found = first_non_finite(value, f"{prefix}/{key}" if prefix else str(key))
        if found is not None:
            return found
    return None


class _Recording:
    """A file that remembers the OSError of a failed write (torch replaces it by a RuntimeError without errno)."""

    def __init__(self, f: IO[bytes]) -> None:
        self._f = f
        self.error: OSError | None = None

    def write(self, data: Any) -> int:
        try:
            return self._f.write(data)
        except OSError as err:
            self.error = err
            raise

    def flush(self) -> None:
        self._f.flush()


def load_checkpoint(
    path: str | os.PathLike[str],
    map_location: str | torch.device = "cpu",
    *,
    keys: Sequence[str] = (),
    mmap: bool = False,
) -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint`; any problem raises CheckpointError in one line: a
    missing, truncated or foreign file, objects the weights-only loader refuses, or a dict lacking ``kind`` or one
    of ``keys`` (the entries the caller reads). ``mmap``: map the tensors rather than read them (a check that
    only looks at the entries)."""
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}; pass the run folder or its {CHECKPOINT_NAME}")
    try:
        with warnings.catch_warnings():  # torch warns about what it is about to refuse; the refusal says it
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except Exception as err:  # torch raises many types for truncated or foreign files
        raise CheckpointError(
            f"checkpoint {path} is corrupt or not a coworld checkpoint ({refusal_reason(err)}); nothing was run"
        ) from None
    if not isinstance(state, dict) or "kind" not in state:
        raise CheckpointError(f"{path} is not a coworld checkpoint (no 'kind' entry)")
    missing = [key for key in keys if key not in state]
    if missing:
        raise CheckpointError(
            f"{path} is a damaged {state['kind']} checkpoint (no {', '.join(map(repr, missing))} entry); restore it"
            " from a copy, or start the run over"
        )
    return state


_TORCH_ADVICE = ("Weights only load failed", "Please file an issue", "Check the documentation", "In PyTorch")


def refusal_reason(err: BaseException, limit: int = 200) -> str:
    """Why torch could not load a file, in whole words: the loader's own reason without torch's advice (which
    suggests unpickling, never done here); at most ``limit`` characters, cut between words."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    reasons = [line.split("WeightsUnpickler error:")[-1].strip() for line in lines]
    reasons = [line for line in reasons if line and not line.startswith(_TORCH_ADVICE)]
    reason = reasons[0] if reasons else (lines[0] if lines else type(err).__name__)
    if len(reason) > limit:
        reason = reason[:limit].rsplit(" ", 1)[0] + " ..."
    return reason


def load_agent_state(agent: Any, state: Any, path: Path, what: str) -> None:
    """``agent.load_state_dict(state)``, with any mismatch (a missing or extra entry, a tensor of another shape)
    raised as one CheckpointError line saying that ``path`` does not fit ``what`` (e.g. 'a drq-bc agent of this
    config')."""
    try:
        agent.load_state_dict(state)
    except (KeyError, RuntimeError, ValueError, TypeError, AttributeError, IndexError) as err:
        reason = refusal_reason(err, 160) if str(err).strip() else type(err).__name__
        if isinstance(err, KeyError):
            reason = f"no {err} entry"
        raise CheckpointError(f"{path} does not fit {what} ({reason}); use the run folder it came from") from None


def rng_state() -> dict[str, Any]:
    """The state of Python's, NumPy's global and torch's random generators."""
    state: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": _numpy_state(),
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` captured (from a checkpoint loaded onto any device: torch's generators take their
    states from the CPU)."""
    random.setstate(state["python"])
    name, key, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(key, dtype=np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([cuda.cpu() for cuda in state["cuda"]])


def _numpy_state() -> tuple[str, list[int], int, int, float]:
    # NumPy's legacy state holds an array, which the weights-only loader refuses: keep it as a list.
    name, key, pos, has_gauss, cached = np.random.get_state(legacy=True)  # type: ignore[misc]
    return str(name), [int(k) for k in key], int(pos), int(has_gauss), float(cached)


def read_run_checkpoint(path: Path, agent: Any, kind: str, keys: tuple[str, ...]) -> dict[str, Any]:
    """The checkpoint at ``path`` of a run of ``kind`` (an offline or an online one), its tensors on ``agent``'s
    device, holding ``keys``; one of another kind is refused (CheckpointError)."""
    state = load_checkpoint(path, map_location=getattr(agent, "device", "cpu"), keys=keys)
    if state.get("kind") != kind:
        raise CheckpointError(f"{path} is a {state.get('kind')!r} checkpoint, not {kind!r}")
    return state


def refuse_earlier_format(path: Path, state: Mapping[str, Any], entries: Sequence[str]) -> None:
    """Refuse, in one CheckpointError line that says what to do, a checkpoint at ``path`` written before the format
    this release writes: one without all of ``entries``."""
    missing = [key for key in entries if key not in state]
    if missing:
        raise CheckpointError(
            f"{path} was written by an earlier coworld (no {', '.join(map(repr, missing))} entry), which this one does"
            f" not resume: train the run again (--force), or resume it with {EARLIER_RELEASE}"
        )


def restore_agent(agent: Any, state: dict[str, Any], path: Path, what: str) -> None:
    """Load a run checkpoint's ``state`` (from ``path``) into ``agent`` (described as ``what`` where it does not
    fit), and the random state the run had when it was saved."""
    load_agent_state(agent, state["agent"], path, what)
    set_rng_state(state["rng"])


def run_state(kind: str, task: str, config: Any, agent: Any) -> dict[str, Any]:
    """What every run checkpoint holds beyond its counters: its kind, task, config, agent and random state."""
    return {"kind": kind, "task": task, "config": to_dict(config), "agent": agent.state_dict(), "rng": rng_state()}
