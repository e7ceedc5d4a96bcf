"""Offline datasets: the HDF5 format (v1), a crash-safe writer, a validated reader with a sequence sampler,
dataset checks, merging and random-policy collection, a D4RL-style API (:func:`load`, :func:`episodes`), V-D4RL
import and Minari / npz-episode export. ``datasets/README.md`` documents the format field by field.

    from coworld.data import open_dataset

    with open_dataset("datasets/walker_walk-random.h5") as data:
        batch = next(data.sampler(batch_size=50, seq_len=50, seed=0))  # batch["image"]: (50, 50, 64, 64, 3) uint8

    import coworld.data

    d4rl = coworld.data.load("walker_walk-random")  # observations, actions, rewards, terminals, timeouts
"""

from coworld.data.api import Episode, episodes, load, qlearning_dataset, resolve_dataset
from coworld.data.collect import Budget, CollectSummary, UniformPolicy, collect_random, run_collection
from coworld.data.export import export_minari, export_npz_episodes
from coworld.data.merge import merge_datasets
from coworld.data.reader import Dataset, StepArrays, normalized_score, open_dataset
from coworld.data.sampler import SAMPLER_MODES, SequenceSampler
from coworld.data.schema import CODECS, FORMAT_VERSION, IMAGE_SHAPE, QUALITIES
from coworld.data.vd4rl import import_vd4rl
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
    "Episode",
    "SequenceSampler",
    "StepArrays",
    "UniformPolicy",
    "collect_random",
    "episodes",
    "export_minari",
    "export_npz_episodes",
    "import_vd4rl",
    "load",
    "qlearning_dataset",
    "merge_datasets",
    "normalized_score",
    "open_dataset",
    "resolve_dataset",
    "run_collection",
    "verify_dataset",
]
