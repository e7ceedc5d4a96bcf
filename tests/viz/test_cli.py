"""`coworld viz predictions | latents | dataset` through click and as a real process, on run folders of untrained
tiny agents and small random toy datasets."""

from __future__ import annotations

import json
import subprocess
import sys

import imageio.v2 as imageio
import numpy as np
import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.data import open_dataset

from .conftest import SOURCE, TARGET, contains, make_run

COWORLD = [sys.executable, "-c", "from coworld.cli import run; run()"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory, target_dataset, toy_dataset_writer):
    root = tmp_path_factory.mktemp("runs")
    out = {algo: make_run(root, algo, target_dataset) for algo in ("coworld", "dreamerv2", "curl")}
    toy_dataset_writer(out["coworld"] / "source_replay.h5", SOURCE, episodes=2, seed=5)  # what a CoWorld run keeps
    return out


def invoke(*args: object):
    device = [] if args[0] == "dataset" else ["--device", "cpu"]
    return CliRunner().invoke(main, ["viz", *map(str, args), *device])


def test_prediction_strip_shows_the_dataset_frames_and_both_models(runs, tmp_path, target_dataset):
    out = tmp_path / "pred.png"
    result = invoke("predictions", "--ckpt", runs["coworld"], "--out", out, "--length", 8, "--context", 3)
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[2].split() == ["step", "target", "source"]
    assert [line.split()[0] for line in lines[3:11]] == ["0*", "1*", "2*", "3", "4", "5", "6", "7"]
    errors = np.array([[float(v) for v in line.split()[1:]] for line in lines[3:11]])
    assert ((errors > 0) & (errors < 1)).all()  # MSE of pixels in [0, 1]; untrained models are never exact
    strip = imageio.imread(out)[..., :3]
    assert strip.shape[0] > 2 * 5 * 64 and strip.shape[1] > 8 * 64  # 2 episodes x (truth, 2 x (model, error))
    with open_dataset(target_dataset) as data:
        for i in (0, 3):  # --episodes 2: the first and the last episode
            for t in (0, 7):
                assert contains(strip, data.episode(i)["image"][t])  # the truth row holds the real frames


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_prediction_video_has_one_frame_per_step(runs, tmp_path, suffix):
    out = tmp_path / f"pred{suffix}"
    result = invoke("predictions", "--ckpt", runs["dreamerv2"], "--out", out, "--length", 9, "--episodes", 3)
    assert result.exit_code == 0, result.output
    assert "dreamerv2" in result.output.splitlines()[2]
    frames = imageio.mimread(out, memtest=False)
    assert len(frames) == 9
    assert frames[0].shape[0] > 3 * 2 * 64 and frames[0].shape[1] > 3 * 2 * 64  # 3 rows x 3 episodes at scale 2
    assert np.std(frames[-1][..., :3]) > 10


def test_prediction_on_fresh_episodes_of_the_policy(runs, tmp_path):
    out = tmp_path / "online.gif"
    result = invoke("predictions", "--ckpt", runs["coworld"], "--out", out, "--online", "--episodes", 1, "--length", 7)
    assert result.exit_code == 0, result.output
    assert "fresh toy_reach_shifted episodes" in result.output and len(imageio.mimread(out)) == 7


def test_latents_picture_and_numbers_of_a_coworld_run(runs, tmp_path):
    out, numbers = tmp_path / "latents.png", tmp_path / "latents.json"
    result = invoke(
        "latents",
        "--ckpt",
        runs["coworld"],
        "--out",
        out,
        "--frames",
        40,
        "--length",
        10,
        "--perplexity",
        5,
        "--json",
        numbers,
    )
    assert result.exit_code == 0, result.output
    assert "source_replay.h5" in result.output and "domain accuracy" in result.output
    metrics = json.loads(numbers.read_text())
    assert 0.0 <= metrics["domain_accuracy"] <= 1.0 and metrics["matched_distance"] > 0.0
    image = imageio.imread(out)
    assert image.shape[:2] == (500, 550) and np.std(image[..., :3]) > 10


def test_latents_of_a_dreamerv2_run_need_source_frames(runs, tmp_path):
    out = tmp_path / "latents.png"
    result = invoke("latents", "--ckpt", runs["dreamerv2"], "--out", out, "--frames", 20)
    assert result.exit_code == 2 and "--source" in result.output and not out.exists()
    result = invoke(
        "latents",
        "--ckpt",
        runs["dreamerv2"],
        "--out",
        out,
        "--frames",
        30,
        "--length",
        10,
        "--source",
        SOURCE,
        "--perplexity",
        5,
    )
    assert result.exit_code == 0, result.output
    assert f"random-action {SOURCE} episodes" in result.output and "matched distance" not in result.output
    assert out.exists()


def test_dataset_grid_and_histogram(tmp_path, target_dataset):
    out = tmp_path / "grid.png"
    result = invoke("dataset", target_dataset, "--out", out, "--episodes", 2, "--frames", 3)
    assert result.exit_code == 0, result.output
    grid = imageio.imread(out)[..., :3]
    with open_dataset(target_dataset) as data:
        assert contains(grid, data.episode(3)["image"][-1][20:])
    assert imageio.imread(tmp_path / "grid-returns.png").shape[:2] == (320, 500)  # beside --out by default


def test_dataset_video_of_whole_episodes(tmp_path, target_dataset):
    out, hist = tmp_path / "eps.mp4", tmp_path / "h" / "returns.png"
    result = invoke("dataset", target_dataset, "--out", out, "--episodes", 2, "--hist", hist)
    assert result.exit_code == 0, result.output
    with open_dataset(target_dataset) as data:
        expected = int(data.lengths[0] + data.lengths[3]) + 2  # every step of episodes 0 and 3
    assert len(imageio.mimread(out, memtest=False)) == expected and hist.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("predictions", "--ckpt", "{curl}", "--out", "{tmp}/x.png"), "has no world model"),
        (("latents", "--ckpt", "{curl}", "--out", "{tmp}/x.png"), "has no world model"),
        (("predictions", "--ckpt", "{coworld}", "--out", "{tmp}/x.jpg"), "use one of .png, .mp4, .gif"),
        (("latents", "--ckpt", "{coworld}", "--out", "{tmp}/x.mp4"), "use one of .png"),
        (("predictions", "--ckpt", "{coworld}", "--out", "{tmp}/x.png", "--context", "9", "--length", "9"), "shorter"),
        (("predictions", "--ckpt", "{tmp}", "--out", "{tmp}/x.png"), "not a coworld run folder"),
        (("predictions", "--ckpt", "{coworld}", "--out", "{tmp}/x.png", "--dataset", "{tmp}/no.h5"), "no dataset"),
        (("dataset", "{tmp}/missing.h5", "--out", "{tmp}/x.png"), "no such file"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(runs, tmp_path, args, message):
    args = [a.format(tmp=tmp_path, **runs) for a in args]
    result = invoke(*args)
    assert result.exit_code == 2, result.output
    assert message in result.output and "Traceback" not in result.output
    assert list(tmp_path.iterdir()) == []


def test_as_a_real_process_and_dataset_info_points_to_it(tmp_path, target_dataset):
    proc = subprocess.run(
        [*COWORLD, "viz", "dataset", str(target_dataset), "--out", str(tmp_path / "g.png")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "g.png").exists() and (tmp_path / "g-returns.png").exists()
    proc = subprocess.run(
        [*COWORLD, "viz", "dataset", str(tmp_path / "none.h5"), "--out", "x.png"], capture_output=True, text=True
    )
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and proc.stderr.startswith("error: ")
    info = CliRunner().invoke(main, ["dataset", "info", str(target_dataset)])
    assert f"coworld viz dataset {target_dataset}" in info.output
    assert TARGET in info.output
