"""End to end through the real CLI: collect -> train CoWorld -> eval, and kill -9 during training then resume.

The toy pair (toy_reach -> toy_reach_shifted) runs in CI; the walker pair on the tiny preset is marked slow.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from coworld.data import open_dataset
from coworld.training.logger import read_metrics

CLI = [sys.executable, "-c", "from coworld.cli import run; run()"]
FAST = ["--set", "train.prefill=100", "--set", "train.eval_episodes=2", "--device", "cpu"]
SCHEDULE = [
    "--set",
    "coworld.pretrain_steps=200",
    "--set",
    "coworld.iterations=2",
    "--set",
    "coworld.target_updates=4",
    "--set",
    "coworld.source_updates=4",
    "--set",
    "offline.updates=8",  # the baselines at CoWorld's target updates (2 x 4), a checkpoint every 4
    "--set",
    "offline.checkpoint_every=4",
]


def cli(*args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return proc


def collect_args(out: Path, task: str, *extra: str) -> list[str]:
    """``coworld collect`` of ``task`` by the tiny preset's DreamerV2 into ``out``, quietly, then ``extra``."""
    return ["collect", "--task", task, "--preset", "tiny", "--out", str(out), "--quiet", *extra]


def train_args(
    run: Path,
    dataset: Path,
    *extra: str,
    algo: str | None = None,
    source: str | None = "toy_reach",
    target: str = "toy_reach_shifted",
) -> list[str]:
    """``coworld train`` of ``algo`` (CoWorld's default when None) from ``source`` (none when None) to ``target``
    on ``dataset`` with the tiny preset, into ``run`` without a progress bar, then ``extra``."""
    args = ["train", *(["--algo", algo] if algo else []), *(["--source", source] if source else [])]
    args += ["--target", target, "--dataset", str(dataset), "--preset", "tiny", "--logdir", str(run), "--no-progress"]
    return [*args, *extra]


@pytest.fixture(scope="module")
def toy_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("e2e") / "toy_reach_shifted-medium_replay.h5"
    cli(*collect_args(out, "toy_reach_shifted", "--max-steps", "300", *FAST))
    return out


def test_collect_train_eval(toy_dataset, tmp_path):
    with open_dataset(toy_dataset) as data:
        assert data.num_steps == 300 and data.complete
        assert data.metadata["collector"]["algorithm"] == "dreamerv2"
    run = tmp_path / "run"
    cli(*train_args(run, toy_dataset, *FAST, *SCHEDULE))
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["kind"] == "coworld" and state["progress"]["iteration"] == 2
    assert state["agent"]["updates"] == 8  # K1 = 4 target updates in each of 2 iterations
    keys = set().union(*(record.keys() for record in read_metrics(run)))
    for key in (
        "target/coworld/align_kl",
        "target/coworld/maxmin_active",
        "target/coworld/source_value",
        "target/coworld/target_value",
        "source/coworld/relabel_reward_loss",
        "eval/return",
        "eval/value_estimate",
        "eval/value_true",
        "eval/reward_estimate",
        "eval/reward_true",
    ):
        assert key in keys, key
    assert list((run / "tb").glob("events.out.tfevents.*"))

    video = tmp_path / "eval.mp4"
    proc = cli("eval", "--ckpt", str(run), "--episodes", "3", "--video", str(video), "--device", "cpu")
    assert "return" in proc.stdout and video.stat().st_size > 1000
    result = json.loads((run / "eval.json").read_text())
    assert len(result["returns"]) == 3 and result["task"] == "toy_reach_shifted"
    assert len(result["value_estimate"]) == 3 and len(result["value_true"]) == 3
    assert len(result["reward_estimate"]) == 3 and len(result["reward_true"]) == 3
    assert result["mean"] == pytest.approx(sum(result["returns"]) / 3)
    # a second evaluation keeps the first unless told to replace it, and says so in one line
    before = (run / "eval.json").read_bytes()
    again = subprocess.run([*CLI, "eval", "--ckpt", str(run), "--episodes", "2"], capture_output=True, text=True)
    assert again.returncode == 2 and again.stderr.count("\n") == 1, again.stderr
    assert "holds an earlier evaluation (3 episodes); kept. Pass --force" in again.stderr
    assert (run / "eval.json").read_bytes() == before
    cli("eval", "--ckpt", str(run), "--episodes", "2", "--device", "cpu", "--force")
    assert len(json.loads((run / "eval.json").read_text())["returns"]) == 2


def test_offline_dreamerv2_baseline(toy_dataset, tmp_path):
    run = tmp_path / "dv2"
    cli(*train_args(run, toy_dataset, *FAST, *SCHEDULE, algo="dreamerv2", source=None))
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["kind"] == "dreamerv2-offline" and state["updates"] == 8  # same target budget as CoWorld
    assert not (run / "source_replay.h5").exists()  # no environment interaction while training

    # Evaluation is reproducible across processes, thread counts and worker counts.
    results = []
    for threads, workers in (("1", "1"), ("2", "2")):
        out = tmp_path / f"eval-{threads}-{workers}.json"
        args = ("--episodes", "3", "--threads", threads, "--workers", workers, "--out", str(out))
        cli("eval", "--ckpt", str(run), *args)
        results.append(json.loads(out.read_text()))
    assert results[0]["returns"] == results[1]["returns"]
    assert results[0]["value_estimate"] == results[1]["value_estimate"]


@pytest.mark.slow  # tests/test_kill.py kills training in CI
def test_kill_during_training_resumes(toy_dataset, tmp_path):
    run = tmp_path / "run"
    args = [*CLI, *train_args(run, toy_dataset, *FAST, *SCHEDULE, "--set", "coworld.target_updates=30")]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 600
    while not (run / "checkpoint.pt").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    assert proc.poll() is None, "training ended before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)  # right after the pretraining checkpoint, inside the first target phase
    proc.wait()
    first = torch.load(run / "checkpoint.pt", weights_only=True)
    assert first["progress"] == {"iteration": 0, "phase": "target", "last_eval": None}
    with open_dataset(run / "source_replay.h5") as replay:
        rows_at_kill = replay.num_steps
    assert rows_at_kill >= 200

    out = cli(*args[len(CLI) :])
    assert "resuming from" in out.stdout
    final = torch.load(run / "checkpoint.pt", weights_only=True)
    assert final["progress"]["iteration"] == 2
    assert final["agent"]["updates"] == 60  # exactly 2 x K1: the killed phase was redone, not double counted
    with open_dataset(run / "source_replay.h5") as replay:
        assert replay.num_steps > rows_at_kill  # continued the source experience, not restarted
        assert replay.num_steps == int(sum(replay.lengths))


@pytest.mark.slow
def test_walker_quickstart_pipeline(tmp_path):
    out = tmp_path / "walker_uphill-medium_replay.h5"
    cli(*collect_args(out, "walker_uphill", "--max-steps", "2000"), timeout=1800)
    run = tmp_path / "run"
    cli(*train_args(run, out, source="walker_walk", target="walker_uphill"), timeout=1800)
    proc = cli("eval", "--ckpt", str(run), "--episodes", "2", "--workers", "2", timeout=1800)
    assert "walker_uphill: return" in proc.stdout


@pytest.mark.parametrize("algo", [pytest.param("curl", marks=pytest.mark.slow), "curl-cql"])
def test_model_free_baselines_train_and_eval(toy_dataset, tmp_path, algo):
    run = tmp_path / algo
    sets = ["--set", "curl.updates=20", "--set", "curl.eval_every=20", "--set", "curl.checkpoint_every=10"]
    proc = cli(*train_args(run, toy_dataset, "--device", "cpu", *sets, algo=algo))
    assert f"--source is not used by {algo}" in proc.stderr
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["kind"] == algo and state["updates"] == 20
    keys = set().union(*(record.keys() for record in read_metrics(run)))
    assert "curl/loss" in keys and "eval/return" in keys
    assert ("cql/penalty" in keys) == (algo == "curl-cql")
    proc = cli("eval", "--ckpt", str(run), "--episodes", "2", "--device", "cpu")
    assert "toy_reach_shifted: return" in proc.stdout


@pytest.mark.slow  # tests/test_interrupt.py and tests/test_storage.py stop collectors in CI
def test_kill_during_collect_then_resume(tmp_path):
    out = tmp_path / "toy.h5"
    args = [*CLI, *collect_args(out, "toy_reach", "--max-steps", "600", *FAST, "--set", "train.checkpoint_every=50")]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    checkpoint = tmp_path / "toy.run" / "checkpoint.pt"
    deadline = time.time() + 600
    while proc.poll() is None and time.time() < deadline:
        if checkpoint.exists() and torch.load(checkpoint, weights_only=True)["updates"] > 0:
            break  # past the prefill: the agent is learning
        time.sleep(0.2)
    assert proc.poll() is None, "collection ended before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    with open_dataset(out) as data:
        rows_at_kill, episodes_at_kill = data.num_steps, data.num_episodes
        first_frames = [data.episode(i)["image"][0].copy() for i in range(episodes_at_kill)]
        assert not data.complete and 0 < rows_at_kill < 600
    updates_at_kill = torch.load(checkpoint, weights_only=True)["updates"]

    proc = subprocess.run([*args, "--resume"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with open_dataset(out) as data:
        assert data.complete and data.num_steps == 600  # exactly the requested rows
        assert int(sum(data.lengths)) == 600 and data.num_episodes > episodes_at_kill
        for i, frame in enumerate(first_frames):  # the episodes written before the kill are kept as they were
            assert (data.episode(i)["image"][0] == frame).all()
        starts = [data.episode(i)["image"][0].tobytes() for i in range(data.num_episodes)]
        assert len(set(starts)) == len(starts)  # no episode written twice
        assert data.metadata["collector"]["algorithm"] == "dreamerv2"
    assert torch.load(checkpoint, weights_only=True)["updates"] > updates_at_kill  # the agent continued


@pytest.mark.parametrize("algo", ["lompo", "dreamerv2-finetune-ewc"])
def test_lompo_and_the_ewc_fine_tuned_dreamerv2_train_on_a_random_dataset_and_eval(tmp_path, algo):
    """The issue's commands: a random dataset of 5 episodes, `train --preset tiny`, `eval --ckpt`."""
    data = tmp_path / "D.h5"
    cli("collect", "--task", "toy_reach_shifted", "--policy", "random", "--episodes", "5", "--out", str(data))
    run = tmp_path / algo
    extra = ["--source", "toy_reach", *FAST, "--set", "coworld.pretrain_steps=200"] if algo != "lompo" else FAST
    cli(*train_args(run, data, *extra, algo=algo, source=None))
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["kind"] == algo and state["updates"] == 40  # the tiny preset's 2 x 20 target updates
    keys = set().union(*(record.keys() for record in read_metrics(run)))
    if algo == "lompo":  # 10 model updates, then its latent actor-critic on penalised imagined transitions
        assert {"lompo/spread", "lompo/penalised_reward", "critic/q"} <= keys
    else:  # the source weights and their Fisher taken, then each network held toward them
        assert {"ewc/fisher_world_model", "wm/ewc", "actor/ewc", "critic/ewc"} <= keys
        assert set(state["agent"]["ewc"]["fisher"]) == {"world_model", "actor", "critic"}
    proc = cli("eval", "--ckpt", str(run), "--episodes", "2", "--device", "cpu")
    assert "toy_reach_shifted: return" in proc.stdout and (run / "eval.json").exists()
