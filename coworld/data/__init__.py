"""Offline datasets: the HDF5 format (v1), a crash-safe writer, a validated reader with a sequence sampler,
dataset checks, merging and random-policy collection. ``datasets/README.md`` documents the format field by field.

    from coworld.data import open_dataset

    with open_dataset("datasets/walker_walk-random.h5") as data:
        batch = next(data.sampler(batch_size=50, seq_len=50, seed=0))  # batch["image"]: (50, 50, 64, 64, 3) uint8
"""

from coworld.data.collect import Budget, CollectSummary, UniformPolicy, collect_random, run_collection
from coworld.data.merge import merge_datasets
from coworld.data.reader import Dataset, StepArrays, normalized_score, open_dataset
from coworld.data.sampler import SAMPLER_MODES, SequenceSampler
from coworld.data.schema import CODECS, FORMAT_VERSION, IMAGE_SHAPE, QUALITIES
from coworld.data.verify import verify_dataset
from coworld.data.writer import DatasetWriter

__all__ = [
    "CODECS",
    "FORMAT_VERSION",
    "IMAGE_SHAPE",
    "QUALITIES",
    "SAMPLER_MODES",
    "Budget",
    "CollectSummary",
    "Dataset",
    "DatasetWriter",
    "SequenceSampler",
    "StepArrays",
    "UniformPolicy",
    "collect_random",
    "merge_datasets",
    "normalized_score",
    "open_dataset",
    "run_collection",
    "verify_dataset",
]
