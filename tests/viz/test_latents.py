"""Latent numbers on cases with known answers, the posterior latents of a real model, and the picture."""

from __future__ import annotations

import numpy as np
import pytest

from coworld.data import open_dataset
from coworld.viz.latents import (
    domain_accuracy,
    latent_figure,
    latent_report,
    matched_distance,
    posterior_latents,
    run_latents,
    sample_windows,
    shuffled_distance,
)
from coworld.viz.media import write_figure

from .conftest import tiny_agent


def test_one_domain_split_at_random_gives_chance_accuracy():
    rng = np.random.default_rng(0)
    latents = rng.normal(size=(400, 16))
    half = rng.permutation(400)
    for seed in range(3):
        assert 0.4 <= domain_accuracy(latents[half[:200]], latents[half[200:]], seed=seed) <= 0.6


def test_well_separated_domains_are_told_apart():
    rng = np.random.default_rng(1)
    first = rng.normal(size=(150, 16))
    second = rng.normal(size=(250, 16)) + 6.0  # unbalanced on purpose: the classifier sees 150 of each
    assert domain_accuracy(first, second) >= 0.99


def test_matched_distance_known_values():
    x = np.random.default_rng(2).normal(size=(50, 4))
    assert matched_distance(x, x) == 0.0
    assert matched_distance(x, x + np.array([3.0, 0.0, 0.0, 4.0])) == pytest.approx(5.0)
    assert shuffled_distance(x, x) > 1.0  # re-pairing distinct points separates them
    same = np.ones((20, 4))
    assert shuffled_distance(same, same) == 0.0
    with pytest.raises(ValueError):
        matched_distance(x, x[:10])


def test_posterior_latents_are_class_probabilities(target_dataset):
    agent = tiny_agent()
    config = agent.config.world_model
    with open_dataset(target_dataset) as data:
        batch = sample_windows(data, frames=30, length=8)
    assert batch["image"].shape[:2] == (4, 8)  # ceil(30 / 8) windows of 8 steps
    latents = posterior_latents(agent.world_model, batch, chunk=3)
    assert latents.shape == (32, config.stoch * config.classes)
    sums = latents.reshape(32, config.stoch, config.classes).sum(-1)
    np.testing.assert_allclose(sums, 1.0, rtol=1e-5)  # each categorical variable's probabilities sum to 1
    np.testing.assert_allclose(latents, posterior_latents(agent.world_model, batch), atol=1e-6)  # chunks: the same


def test_same_encoder_on_both_sides_gives_zero_matched_distance(target_dataset, source_dataset):
    model = tiny_agent().world_model
    with open_dataset(target_dataset) as target, open_dataset(source_dataset) as source:
        report = latent_report(
            {"source": model, "target": model}, sample_windows(source, 40, 10), sample_windows(target, 40, 10)
        )
    assert [(g.domain, g.encoder) for g in report.groups] == [
        ("source", "source"),
        ("target", "target"),
        ("target", "source"),
    ]
    assert report.matched_distance == 0.0 and report.shuffled_distance > 0.0
    assert 0.0 <= report.domain_accuracy <= 1.0


def test_latent_picture_of_a_two_model_run(tmp_path, target_dataset, source_dataset):
    models = {"source": tiny_agent(0).world_model, "target": tiny_agent(1).world_model}
    with open_dataset(target_dataset) as target, open_dataset(source_dataset) as source:
        report = run_latents(models, source, target, frames=60, length=10, perplexity=10)
    assert [len(g.latents) for g in report.groups] == [60, 60, 60]
    assert [p.shape for p in report.embedding] == [(60, 2)] * 3
    assert report.matched_distance > 0.0
    assert "domain accuracy" in report.summary() and "matched distance" in report.summary()
    import imageio.v2 as imageio

    path = write_figure(tmp_path / "latents.png", latent_figure(report, "test"))
    image = imageio.imread(path)[..., :3].astype(int)
    assert image.shape[:2] == (500, 550)  # 5.5 x 5 inches at 100 dpi
    assert ((image[..., 2] - image[..., 0]) > 40).sum() > 300  # blue source-domain points
    assert ((image[..., 0] - image[..., 2]) > 40).sum() > 300  # orange target-domain points
