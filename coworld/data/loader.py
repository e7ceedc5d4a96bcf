"""PyTorch DataLoader over a :class:`~coworld.data.sampler.SequenceSampler` (imports torch; the rest of
``coworld.data`` does not).

Each worker process gets its own copy of the sampler: it reopens the HDF5 file itself and seeds its windows from
``(seed, worker id)``, so workers never share an h5py handle and never draw the same windows.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset

from coworld.data.reader import Dataset
from coworld.data.sampler import SequenceSampler


class SamplerDataset(IterableDataset):
    """An endless stream of ready-made batches (dicts of NumPy arrays) from one sampler."""

    def __init__(self, sampler: SequenceSampler) -> None:
        super().__init__()
        self.sampler = sampler

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        return iter(self.sampler)


def make_loader(
    dataset: Dataset,
    batch_size: int,
    seq_len: int,
    *,
    seed: int = 0,
    mode: str = "auto",
    num_workers: int = 0,
    pin_memory: bool = False,
    **loader_kwargs: Any,
) -> DataLoader:
    """A DataLoader yielding batches of torch tensors with the sampler's keys and shapes (B, L, ...).

    Batches are made whole by the sampler (``batch_size=None`` for the DataLoader), in ``num_workers`` processes.
    In "ram" mode the frames are loaded before the workers start, so forked workers share them.
    """
    sampler = dataset.sampler(batch_size, seq_len, seed=seed, mode=mode)
    return DataLoader(
        SamplerDataset(sampler),
        batch_size=None,
        num_workers=num_workers,
        pin_memory=pin_memory and torch.cuda.is_available(),
        persistent_workers=num_workers > 0,
        **loader_kwargs,
    )
