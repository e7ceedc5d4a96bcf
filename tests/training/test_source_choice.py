"""CoWorld with several candidate sources: the distance and the rule (known answers), the run that chooses (the
closest candidate, recorded, moved into place, resumed and never chosen again), and the command line."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from coworld.agents.coworld import CoWorld
from coworld.agents.dreamerv2 import DreamerV2
from coworld.cli import main
from coworld.config import make_config
from coworld.data import open_dataset
from coworld.errors import CoworldError
from coworld.losses.coworld import closest_source, domain_distance
from coworld.training import multi_source as choice_module
from coworld.training.chosen_source import CHOICE_FILE, candidate_dir, read_choice, trained_source
from coworld.training.multi_source import measure_distance
from coworld.training.run import clear_run_dir, prepare_run_dir
from coworld.training.train import check_job, run_job
from coworld.viz.latents import NAME_THE_SOURCE

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SCHEDULE = [
    "device=cpu",
    "train.prefill=50",
    "train.pretrain_updates=2",
    "train.train_every=5",
    "train.eval_episodes=1",
    "coworld.pretrain_steps=100",
    "coworld.iterations=1",
    "coworld.target_updates=2",
    "coworld.source_updates=5",
    "coworld.select_batches=2",
]
CANDIDATES = "toy_reach,toy_reach_shifted_act3"  # 2-d and 3-d actions; the target toy_reach_shifted has 2


def test_domain_distance_known_answers() -> None:
    # one latent of 2 classes, two steps: source uniform both times; target (1/4, 3/4) then equal to the source
    source = torch.zeros(1, 2, 1, 2)
    target = torch.tensor([[[[math.log(0.25), math.log(0.75)]], [[0.0, 0.0]]]])
    kl = 0.5 * math.log(0.5 / 0.25) + 0.5 * math.log(0.5 / 0.75)  # KL[source || target] at step 0
    assert float(domain_distance(source, target, "latent")) == pytest.approx(kl / 2)  # mean over B, T
    assert float(domain_distance(source, source, "latent")) == 0.0
    reverse = 0.25 * math.log(0.25 / 0.5) + 0.75 * math.log(0.75 / 0.5)
    assert float(domain_distance(target, source, "latent")) == pytest.approx(reverse / 2)  # the direction matters
    # embeddings (B=1, T=2, E=2): softmax of each row, summed over T, averaged over B (the release's batchmean)
    assert float(domain_distance(source[:, :, 0], target[:, :, 0], "embedding")) == pytest.approx(kl)
    with pytest.raises(ValueError, match="align_on"):
        domain_distance(source, target, "pixels")


def test_closest_source_takes_the_smallest_distance_the_first_of_a_tie_and_skips_non_numbers() -> None:
    assert closest_source({"a": 0.3, "b": 0.1, "c": 0.2}) == "b"
    assert closest_source({"a": 0.3, "b": 0.1, "c": 0.1}) == "b"
    assert closest_source({"c": 0.1, "b": 0.1}) == "c"
    assert closest_source({"a": float("nan"), "b": 5.0}) == "b"
    with pytest.raises(ValueError, match="no candidate"):
        closest_source({"a": float("nan"), "b": float("inf")})


def _job(dataset: Path, logdir: Path, source: str = CANDIDATES):
    return check_job(
        algo="coworld",
        source=source,
        target="toy_reach_shifted",
        dataset=dataset,
        preset="tiny",
        logdir=logdir,
        seed=0,
        device="cpu",
        overrides=SCHEDULE,
    )


def test_a_run_chooses_the_closest_candidate_records_it_and_trains_with_it(
    tmp_path: Path, toy_dataset_writer, monkeypatch: pytest.MonkeyPatch
) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    run = tmp_path / "run"
    job = _job(dataset, run)
    assert job.source == CANDIDATES and job.info()["source"] == CANDIDATES
    # a kill inside the second candidate's pretraining: the first one's pretraining and distance are kept
    original = CoWorld.train_source
    calls = {"n": 0}

    def crashing(self, *args):
        calls["n"] += 1
        if calls["n"] > 13 + 5:  # the first candidate's 13 pretraining updates, then 5 of the second's
            raise RuntimeError("simulated crash")
        return original(self, *args)

    monkeypatch.setattr(CoWorld, "train_source", crashing)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_job(job, progress=False)
    measured = json.loads((run / "selection" / "distances.json").read_text())
    assert list(measured) == ["toy_reach"] and not (run / CHOICE_FILE).exists()
    monkeypatch.setattr(CoWorld, "train_source", original)
    pretrained = []
    original_pretrain = choice_module._pretrain
    monkeypatch.setattr(
        choice_module, "_pretrain", lambda job, name, *a: pretrained.append(name) or original_pretrain(job, name, *a)
    )
    summary = run_job(_job(dataset, run), progress=False)
    assert pretrained == ["toy_reach_shifted_act3"]  # the first candidate was not measured again
    assert summary["iterations"] == 1

    choice = read_choice(run, CANDIDATES.split(","))
    assert choice is not None and choice.distances["toy_reach"] == measured["toy_reach"]
    assert choice.chosen == min(choice.distances, key=choice.distances.get)
    assert all(d > 0 for d in choice.distances.values())
    # each distance is the chosen rule on that candidate's own pretrained model and the warmed-up target
    config = make_config("tiny", ["seed=0", *SCHEDULE])
    warm = torch.load(run / "selection" / "target.pt", weights_only=True)
    target = DreamerV2(config=config, action_size=2, device="cpu")
    target.load_state_dict(warm["agent"])
    with open_dataset(dataset) as data:
        batches = choice_module._batches(data, config, config.seed + choice_module.SELECT_SEED, 2)
    for name, size in (("toy_reach", 2), ("toy_reach_shifted_act3", 3)):
        where = run / "source" if name == choice.chosen else candidate_dir(run, name) / "source"
        state = torch.load(where / "checkpoint.pt", weights_only=True)
        assert state["task"] == name
        source = DreamerV2(config=config, action_size=size, device="cpu", model_action_size=max(size, 2))
        source.load_state_dict(state["agent"])
        seed = config.seed + choice_module.SELECT_SEED
        again = measure_distance(source, target, batches, align_on="latent", seed=seed)
        assert again == pytest.approx(choice.distances[name], rel=1e-5)
    # the run went on with the chosen source, its pretraining moved to where a one-source run keeps it
    final = torch.load(run / "checkpoint.pt", weights_only=True)
    assert final["source_task"] == choice.chosen
    with open_dataset(run / "source_replay.h5") as replay:
        assert replay.task == choice.chosen
    logged = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    distances = next(r for r in logged if f"coworld/source_distance/{choice.chosen}" in r)
    assert distances[f"coworld/source_distance/{choice.chosen}"] == pytest.approx(choice.distances[choice.chosen])

    # the choice once made is never made again: a rerun of the finished run measures nothing
    monkeypatch.setattr(choice_module, "measure_distance", lambda *a, **k: pytest.fail("measured again"))
    monkeypatch.setattr(choice_module, "_pretrain", lambda *a: pytest.fail("pretrained again"))
    run_job(_job(dataset, run), progress=False)
    assert read_choice(run, CANDIDATES.split(",")) == choice

    out = CliRunner().invoke(main, ["report", str(run)])
    assert out.exit_code == 0, out.output
    report = (run / "report.md").read_text()
    assert "## Source choice" in report
    for name, value in choice.distances.items():
        assert (f"**{name}** {value:.4g}" if name == choice.chosen else f"{name} {value:.4g}") in report

    clear_run_dir(run)  # --force: the choice and what led to it go with the rest
    assert not [p.name for p in run.iterdir() if p.name in ("sources", "selection", CHOICE_FILE, "source")]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--source", "toy_reach,nope"], "unknown task 'nope'"),
        (["--source", "toy_reach,toy_reach"], "names toy_reach twice"),
        (["--source", "toy_reach,"], "has an empty name"),
        (["--source", "toy_reach,toy_reach_centre", "--algo", "dreamerv2-finetune"], "takes one --source"),
    ],
)
def test_bad_lists_of_sources_get_one_line_and_exit_2(tmp_path: Path, toy_dataset_writer, args, message) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=1)
    run = tmp_path / "run"
    out = CliRunner().invoke(
        main,
        ["train", "--target", "toy_reach_shifted", "--dataset", str(dataset), "--preset", "tiny", "--logdir", str(run)]
        + args,
    )
    assert out.exit_code == 2, out.output
    assert message in out.output and len(out.output.strip().splitlines()) == 1
    assert not run.exists()


@pytest.mark.parametrize(
    ("measured", "why"),
    [
        (b"{", "not JSON"),
        (b"[]", "JSON list, not an object"),
        (b'{"toy_reach": 1.5}\xe9', "not UTF-8 text"),
        (b'{"toy_reach": "far"}', "the distance of toy_reach is 'far', not a number"),
        (b'{"toy_reach": null}', "the distance of toy_reach is None, not a number"),
        (b'{"walker_walk": 1.5}', "walker_walk is not a candidate of this run"),
    ],
)
def test_damaged_distances_are_refused_before_any_candidate_is_pretrained(
    tmp_path: Path, toy_dataset_writer, measured: bytes, why: str
) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=1)
    run = tmp_path / "run"
    job = _job(dataset, run)
    prepare_run_dir(job.logdir, job.config, job.info())
    (run / "selection").mkdir()
    (run / "selection" / "distances.json").write_bytes(measured)
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    args = ["train", "--source", CANDIDATES, "--target", "toy_reach_shifted", "--dataset", str(dataset), "--preset"]
    args += ["tiny", "--logdir", str(run), "--seed", "0", "--no-progress"]
    out = CliRunner().invoke(main, args + [arg for item in SCHEDULE for arg in ("--set", item)])
    lines = out.output.strip().splitlines()
    assert out.exit_code == 2 and len(lines) == 1 and "Traceback" not in out.output, out.output
    assert lines[0].startswith(f"error: {run / 'selection' / 'distances.json'} is damaged ({why}")
    assert "delete it" in lines[0] and "--force" in lines[0]
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before  # nothing warmed up or pretrained


def test_a_damaged_choice_ends_with_what_the_calling_command_offers(tmp_path: Path) -> None:
    (tmp_path / CHOICE_FILE).write_text('{"candidates": []}')
    info = {"algo": "coworld", "source": CANDIDATES, "target": "toy_reach_shifted"}
    with pytest.raises(CoworldError, match=r"is damaged .*; pass a new --logdir, or --force to start this one over$"):
        read_choice(tmp_path)  # train's, by default: it is the command that writes the choice
    with pytest.raises(CoworldError, match=r"is damaged .*; name the run's source with --source TASK$"):
        trained_source(tmp_path, info, NAME_THE_SOURCE)  # viz latents'


def test_a_list_of_sources_for_an_algorithm_without_a_source_is_one_note(tmp_path: Path, toy_dataset_writer) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=1)
    args = ["train", "--target", "toy_reach_shifted", "--dataset", str(dataset), "--algo", "drq-bc"]
    args += ["--source", "toy_reach,toy_reach_centre", "--preset", "tiny", "--logdir", str(tmp_path / "run")]
    args += ["--set", "drqbc.updates=1", "--set", "drqbc.eval_episodes=1", "--device", "cpu", "--no-progress"]
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 0, out.output
    notes = [line for line in out.output.splitlines() if "--source" in line]
    assert notes == ["note: --source is not used by drq-bc: it learns from the target dataset alone"]


CLI = [sys.executable, "-c", "from coworld.cli import run; run()"]


@pytest.mark.long
def test_the_command_killed_inside_the_second_candidate_resumes_and_keeps_the_first_ones_distance(
    tmp_path: Path, toy_dataset_writer
) -> None:
    dataset = toy_dataset_writer(tmp_path / "target.h5", "toy_reach_shifted", episodes=3)
    run = tmp_path / "run"
    args = [*CLI, "train", "--source", CANDIDATES, "--target", "toy_reach_shifted", "--dataset", str(dataset)]
    args += ["--preset", "tiny", "--logdir", str(run), "--seed", "0", "--no-progress", "--threads", "1"]
    # a longer pretraining than SCHEDULE's, so that the kill lands inside the second candidate's on a fast machine too
    schedule = [*SCHEDULE, "coworld.pretrain_steps=400"]
    args += [arg for item in schedule for arg in ("--set", item)]
    second = candidate_dir(run, "toy_reach_shifted_act3") / "source_replay.h5"
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.time() + 300
        while not second.exists():
            assert proc.poll() is None and time.time() < deadline
            time.sleep(0.01)
        time.sleep(0.05)  # inside the second candidate's pretraining, which takes seconds
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    first = json.loads((run / "selection" / "distances.json").read_text())
    assert list(first) == ["toy_reach"] and not (run / CHOICE_FILE).exists()
    out = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    choice = read_choice(run, CANDIDATES.split(","))
    assert choice is not None and choice.distances["toy_reach"] == first["toy_reach"]
    assert f"done: {run}" in out.stdout
    other = next(name for name in choice.candidates if name != choice.chosen)  # the choice is said, not only logged
    said = [line for line in out.stderr.splitlines() if line.startswith("source choice: ")]
    assert said == [
        f"source choice: {choice.chosen}, the closest to the target (distance {choice.distances[choice.chosen]:.4g};"
        f" {other} {choice.distances[other]:.4g}), measured on {choice.batches} target batches; {CHOICE_FILE} holds it"
    ]


@pytest.mark.slow
def test_the_dmc_command_records_its_choice_and_the_distances(tmp_path: Path) -> None:
    """The issue's command: walker_walk or cheetah_run for walker_uphill, tiny preset, a 2-episode random dataset."""
    dataset = tmp_path / "walker_uphill.h5"
    collect = [*CLI, "collect", "--task", "walker_uphill", "--policy", "random", "--episodes", "2"]
    assert subprocess.run([*collect, "--out", str(dataset)], capture_output=True, timeout=600).returncode == 0
    run = tmp_path / "run"
    args = [*CLI, "train", "--source", "walker_walk,cheetah_run", "--target", "walker_uphill", "--preset", "tiny"]
    args += ["--dataset", str(dataset), "--logdir", str(run), "--device", "cpu", "--no-progress"]
    out = subprocess.run(args, capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stderr[-3000:]
    choice = json.loads((run / CHOICE_FILE).read_text())
    assert choice["candidates"] == ["walker_walk", "cheetah_run"]
    assert set(choice["distances"]) == {"walker_walk", "cheetah_run"}
    assert choice["chosen"] == min(choice["distances"], key=choice["distances"].get)
    assert torch.load(run / "checkpoint.pt", weights_only=True)["source_task"] == choice["chosen"]
    evaluated = subprocess.run([*CLI, "eval", "--ckpt", str(run), "--episodes", "1"], capture_output=True, text=True)
    assert evaluated.returncode == 0 and "walker_uphill: return" in evaluated.stdout
    assert subprocess.run([*CLI, "report", str(run)], capture_output=True, timeout=600).returncode == 0
    assert f"**{choice['chosen']}**" in (run / "report.md").read_text()
