"""Where the encoders put the source and the target domain (the paper's Figure 6).

A latent is the posterior over ``z`` at one step: the class probabilities of its ``S`` categorical variables,
flattened to ``S * K`` numbers (what CoWorld's Eq. 3 aligns), computed with the latents' modes along each
sequence so the numbers are deterministic. A picture projects them to 2-D with scikit-learn's t-SNE; two
numbers say the same without the picture:

* **domain accuracy**: cross-validated accuracy of a logistic-regression classifier telling source-domain latents
  from target-domain latents (classes balanced: 0.5 is chance, the domains overlap; 1.0 means fully separated);
* **matched distance**: the mean Euclidean distance between the source encoder's and the target encoder's latents
  of the *same* target frames (0 = the encoders agree), next to the same mean over randomly re-paired frames,
  the scale of "no agreement at all".
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from coworld import envs
from coworld.data.windows import EpisodeSource, EpisodeStore, count_episodes, episode_windows, get_episodes
from coworld.errors import CoworldError
from coworld.training.chosen_source import trained_source
from coworld.training.openloop import batch_tensors
from coworld.viz.media import require_extra

__all__ = [
    "LatentGroup",
    "LatentReport",
    "domain_accuracy",
    "latent_figure",
    "latent_report",
    "latents_of_run",
    "matched_distance",
    "posterior_latents",
    "run_latents",
    "sample_windows",
    "shuffled_distance",
    "tsne",
]

NAME_THE_SOURCE = "name the run's source with --source TASK"
"""What ``viz latents`` offers where a run's record of its source choice is damaged."""
DOMAIN_COLOURS = {"source": "tab:blue", "target": "tab:orange"}
ENCODER_MARKERS = {"source": "o", "target": "^", "model": "o"}


@torch.no_grad()
def posterior_latents(world_model: Any, batch: Mapping[str, np.ndarray], chunk: int = 16) -> np.ndarray:
    """Posterior class probabilities of every step of ``batch`` (B sequences of T steps), ``(B * T, S * K)``.

    Each sequence is observed from the zero state, ``chunk`` sequences at a time.
    """
    image, action, is_first = batch_tensors(world_model, batch)
    rssm = world_model.rssm
    out = []
    for lo in range(0, action.shape[0], chunk):
        embed = world_model.encode(image[lo : lo + chunk])
        state = rssm.initial(embed.shape[0], action.device)
        probs = []
        for t in range(action.shape[1]):
            state, _ = rssm.obs_step(
                state, action[lo : lo + chunk, t], embed[:, t], is_first[lo : lo + chunk, t], False
            )
            probs.append(state["logits"].float().exp().flatten(-2))
        out.append(torch.stack(probs, dim=1).flatten(0, 1))
    return torch.cat(out).cpu().numpy()


def sample_windows(source: EpisodeSource, frames: int, length: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Windows of ``length`` steps holding at least ``frames`` steps in all, from evenly spaced episodes.

    ``source``: an open :class:`~coworld.data.reader.Dataset` or a list of episodes (step convention). Window
    starts are drawn with ``seed``; ``length`` is cut to the shortest episode used.
    """
    total = count_episodes(source)
    count = -(-frames // length)
    which = np.round(np.linspace(0, total - 1, count)).astype(int).tolist() if total else []
    episodes = get_episodes(source, which)
    if not episodes:
        raise CoworldError("no episodes to take frames from")
    rng = np.random.default_rng(seed)
    starts = [int(rng.integers(0, max(1, len(ep["reward"]) - length + 1))) for ep in episodes]
    return episode_windows(episodes, length, starts)


def domain_accuracy(first: np.ndarray, second: np.ndarray, folds: int = 5, seed: int = 0) -> float:
    """Cross-validated accuracy of a logistic-regression classifier telling ``first`` (N1, D) from ``second``
    (N2, D); the larger set is subsampled to the smaller, so 0.5 is chance."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import StratifiedKFold, cross_val_score

    rng = np.random.default_rng(seed)
    n = min(len(first), len(second))
    if n < folds:
        raise CoworldError(f"need at least {folds} latents of each domain for the classifier, got {n}")
    first = first[rng.permutation(len(first))[:n]]
    second = second[rng.permutation(len(second))[:n]]
    x = np.concatenate([first, second])
    y = np.repeat([0, 1], n)
    split = StratifiedKFold(n_splits=folds, shuffle=True, random_state=seed)
    return float(cross_val_score(LogisticRegression(max_iter=2000), x, y, cv=split).mean())


def matched_distance(first: np.ndarray, second: np.ndarray) -> float:
    """Mean Euclidean distance between row ``i`` of ``first`` and row ``i`` of ``second`` (both (N, D))."""
    if first.shape != second.shape:
        raise ValueError(f"matched latents must have one shape, got {first.shape} and {second.shape}")
    return float(np.linalg.norm(first - second, axis=-1).mean())


def shuffled_distance(first: np.ndarray, second: np.ndarray, seed: int = 0) -> float:
    """:func:`matched_distance` after randomly re-pairing the rows of ``second`` (the scale of no agreement)."""
    return matched_distance(first, second[np.random.default_rng(seed).permutation(len(second))])


@dataclass
class LatentGroup:
    """Latents of the frames of one ``domain`` through one ``encoder`` (``source``/``target``/``model``)."""

    domain: str
    encoder: str
    latents: np.ndarray

    @property
    def label(self) -> str:
        encoder = "the model's encoder" if self.encoder == "model" else f"{self.encoder} encoder"
        return f"{self.domain} frames, {encoder}"


@dataclass
class LatentReport:
    """The groups, their t-SNE coordinates and the numbers (see the module docstring)."""

    groups: list[LatentGroup]
    domain_accuracy: float
    matched_distance: float | None = None
    shuffled_distance: float | None = None
    embedding: list[np.ndarray] = field(default_factory=list)
    """Per group, its t-SNE coordinates (N, 2), when computed."""

    def summary(self) -> str:
        first, second = self._compared()
        lines = [
            f"domain accuracy {self.domain_accuracy:.3f} (chance 0.5, fully separated 1.0): a classifier telling"
            f" [{first.label}] from [{second.label}], 5-fold cross-validated"
        ]
        if self.matched_distance is not None:
            lines.append(
                f"matched distance {self.matched_distance:.3f} between the source and the target encoder's latents"
                f" of the same target frames (re-paired at random: {self.shuffled_distance:.3f})"
            )
        return "\n".join(lines)

    def metrics(self) -> dict[str, float | None]:
        return {
            "domain_accuracy": self.domain_accuracy,
            "matched_distance": self.matched_distance,
            "shuffled_distance": self.shuffled_distance,
        }

    def _compared(self) -> tuple[LatentGroup, LatentGroup]:
        source = next(g for g in self.groups if g.domain == "source")
        target = next(g for g in self.groups if g.domain == "target" and g.encoder != "source")
        return source, target


def latent_report(
    world_models: Mapping[str, Any],
    source_batch: Mapping[str, np.ndarray],
    target_batch: Mapping[str, np.ndarray],
    seed: int = 0,
    limit: int | None = None,
) -> LatentReport:
    """Encode source and target sequences and measure how far apart the domains are.

    ``world_models``: ``{"source": ..., "target": ...}`` (a CoWorld run: each domain through its own encoder,
    plus the target frames through the source encoder) or one model under any name (both domains through it).
    ``limit`` keeps the first ``limit`` latents of each group.
    """

    def encode(model: Any, batch: Mapping[str, np.ndarray]) -> np.ndarray:
        return posterior_latents(model, batch)[:limit]

    if "source" in world_models and "target" in world_models:
        source, target = world_models["source"], world_models["target"]
        groups = [
            LatentGroup("source", "source", encode(source, source_batch)),
            LatentGroup("target", "target", encode(target, target_batch)),
            LatentGroup("target", "source", encode(source, target_batch)),
        ]
        accuracy = domain_accuracy(groups[0].latents, groups[1].latents, seed=seed)
        matched = matched_distance(groups[2].latents, groups[1].latents)
        shuffled = shuffled_distance(groups[2].latents, groups[1].latents, seed=seed)
        return LatentReport(groups, accuracy, matched, shuffled)
    if len(world_models) != 1:
        raise ValueError(f"pass a source and a target model, or one model; got {sorted(world_models)}")
    model = next(iter(world_models.values()))
    groups = [
        LatentGroup("source", "model", encode(model, source_batch)),
        LatentGroup("target", "model", encode(model, target_batch)),
    ]
    return LatentReport(groups, domain_accuracy(groups[0].latents, groups[1].latents, seed=seed))


def tsne(groups: Sequence[LatentGroup], seed: int = 0, perplexity: float = 30.0) -> list[np.ndarray]:
    """scikit-learn t-SNE of all groups' latents together; per group its (N, 2) coordinates."""
    from sklearn.manifold import TSNE

    x = np.concatenate([g.latents for g in groups]).astype(np.float32)
    perplexity = min(perplexity, (len(x) - 1) / 3)
    points = TSNE(n_components=2, perplexity=perplexity, init="pca", random_state=seed).fit_transform(x)
    bounds = np.cumsum([0] + [len(g.latents) for g in groups])
    return [points[lo:hi] for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]


def latent_figure(report: LatentReport, title: str) -> Any:
    """Scatter of the t-SNE coordinates: colour = domain of the frames, marker = encoder. Returns the figure."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 5.0))
    ax = fig.subplots()
    for group, points in zip(report.groups, report.embedding, strict=True):
        hollow = group.encoder == "source" and group.domain == "target"
        ax.scatter(
            points[:, 0],
            points[:, 1],
            s=10,
            marker=ENCODER_MARKERS[group.encoder],
            facecolors="none" if hollow else DOMAIN_COLOURS[group.domain],
            edgecolors=DOMAIN_COLOURS[group.domain],
            linewidths=0.6,
            alpha=0.7,
            label=group.label,
        )
    ax.set_xticks([])
    ax.set_yticks([])
    numbers = f"domain accuracy {report.domain_accuracy:.2f} (chance 0.5)"
    if report.matched_distance is not None:
        numbers += f"; matched distance {report.matched_distance:.2f} (random pairs {report.shuffled_distance:.2f})"
    ax.set_title(f"{title}\n{numbers}", fontsize=8)
    ax.legend(fontsize=7, loc="best", markerscale=1.5)
    fig.tight_layout()
    return fig


def run_latents(
    world_models: Mapping[str, Any],
    source: Any,
    target: Any,
    *,
    frames: int,
    length: int,
    seed: int = 0,
    perplexity: float = 30.0,
) -> LatentReport:
    """Sample ``frames`` steps of each domain (``source`` / ``target``: a Dataset or a list of episodes), encode,
    measure, and fit the t-SNE."""
    require_extra("sklearn", "matplotlib")
    source_batch = sample_windows(source, frames, length, seed)
    target_batch = sample_windows(target, frames, length, seed + 1)
    report = latent_report(world_models, source_batch, target_batch, seed=seed, limit=frames)
    report.embedding = tsne(report.groups, seed=seed, perplexity=perplexity)
    return report


def latents_of_run(
    run: Any,
    *,
    frames: int,
    length: int,
    dataset: str | Path | None = None,
    source_dataset: str | Path | None = None,
    source: str | None = None,
    seed: int = 0,
    perplexity: float = 30.0,
) -> tuple[LatentReport, str]:
    """:func:`run_latents` for a :class:`~coworld.viz.runs.RunModels`, and a line saying where the frames came from.

    Target frames: the run's dataset (or ``dataset``). Source frames: ``source_dataset``; else a CoWorld run's
    ``source_replay.h5``; else uniform-random-action episodes of ``source`` (default: the run's source task).
    """
    from coworld.data import open_dataset
    from coworld.viz.runs import rollout_episodes, run_dataset

    target_path = run_dataset(run.info, dataset)
    replay = run.run_dir / "source_replay.h5"
    source_task = source or trained_source(run.run_dir, run.info, NAME_THE_SOURCE)
    with contextlib.ExitStack() as stack:
        target = stack.enter_context(open_dataset(target_path))
        if target.task != run.info["target"]:
            raise CoworldError(f"{target_path} holds {target.task} episodes, not the run's target {run.info['target']}")
        if source_dataset is not None or (source is None and replay.exists()):
            source_path = Path(source_dataset) if source_dataset is not None else replay
            source_frames: Any = stack.enter_context(open_dataset(source_path))
            expected = source_task
            if expected is not None and source_frames.task != expected:
                raise CoworldError(
                    f"{source_path} holds {source_frames.task} episodes, not the source task {expected}; pass a"
                    f" {expected} dataset as --source-dataset"
                )
            if source_frames.task == run.info["target"]:
                raise CoworldError(f"{source_path} holds target episodes ({source_frames.task}); pass source ones")
            where = f"source frames from {source_path}"
        elif source_task is not None:
            count = max(2, -(-frames // envs.task_spec(source_task).episode_length))
            source_frames = rollout_episodes(None, source_task, count, seed=seed, mode="random")
            where = f"source frames from {count} random-action {source_task} episodes"
        else:
            raise CoworldError("no source frames: pass --source-dataset PATH or --source TASK (random actions)")
        held = min(d.num_steps for d in (target, source_frames) if isinstance(d, EpisodeStore))
        if frames > held:  # more would show the same frames again
            where = f"{where} (--frames {frames} capped to {held:,}: the data hold no more)"
            frames = held
        report = run_latents(
            run.world_models(), source_frames, target, frames=frames, length=length, seed=seed, perplexity=perplexity
        )
    return report, f"{where}; target frames from {target_path}"
