"""What a run folder holds is what it says: a checkpoint copied in from another run, a damaged run.json or
config.json and a checkpoint missing an entry are refused in one line (exit code 2) by every command that loads them,
before anything is written; the model-based variants' world models can be looked inside."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from coworld.algorithms import algorithm
from coworld.report import write_report
from coworld.training.checkpoint import save_checkpoint
from coworld.training.run import prepare_run_dir
from coworld.training.train import check_job

TARGET = "toy_reach_shifted"


def digest(folder: Path) -> dict[str, str]:
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize(
    ("folder_algo", "checkpoint_algo"),
    [
        ("dreamerv2-finetune", "dreamerv2-penalty"),
        ("dreamerv2", "dreamerv2-finetune"),
        ("dreamerv2-finetune", "dreamerv2"),
        ("lompo", "dreamerv2-penalty"),
        ("dreamerv2-finetune-ewc", "dreamerv2-finetune"),
    ],
)
def test_eval_refuses_a_checkpoint_of_another_algorithm(
    tmp_path, toy_dataset, make_run, folder_algo, checkpoint_algo, cli, one_line
):
    run = make_run(tmp_path / "run", folder_algo, toy_dataset, checkpoint_of=checkpoint_algo)
    before = digest(run)
    code, out = cli("eval", "--ckpt", str(run), "--episodes", "1", "--device", "cpu")
    one_line(code, out, f"'{algorithm(checkpoint_algo).checkpoint}' checkpoint", f"is a {folder_algo} run", "copied")
    assert digest(run) == before  # no eval.json labelled with the folder's algorithm


def test_eval_refuses_a_checkpoint_of_another_task_as_a_real_process(tmp_path, toy_dataset, make_run, processes):
    run = make_run(tmp_path / "run", "dreamerv2-penalty", toy_dataset, task="toy_reach_centre")
    done = processes.run_cli("eval", "--ckpt", str(run), "--episodes", "1", "--device", "cpu")
    assert done.returncode == 2
    line = processes.last_word(done.stderr, "error: ")
    assert "was trained on toy_reach_centre" in line and f"run of {TARGET}" in line
    assert not (run / "eval.json").exists()


def test_eval_refuses_a_checkpoint_of_other_settings(tmp_path, toy_dataset, make_run, cli, one_line):
    run = make_run(tmp_path / "run", "dreamerv2", toy_dataset)
    state = json.loads((run / "config.json").read_text())
    state["world_model"]["deter"] = 32
    (run / "config.json").write_text(json.dumps(state))
    code, out = cli("eval", "--ckpt", str(run), "--episodes", "1", "--device", "cpu")
    one_line(code, out, "other settings", "world_model.deter: saved 64, now 32")


def test_report_does_not_count_an_evaluation_of_another_algorithm(tmp_path, toy_dataset, make_run):
    run = make_run(tmp_path / "runs" / "a", "dreamerv2-finetune", toy_dataset)
    record = {"task": TARGET, "returns": [26.3], "lengths": [50], "extra": {"algo": "dreamerv2-penalty"}}
    (run / "eval.json").write_text(json.dumps(record))
    report = write_report(tmp_path / "runs", tmp_path / "report")
    assert report.finished == 0
    assert "an evaluation of a dreamerv2-penalty agent" in (tmp_path / "report" / "report.md").read_text()


def test_viz_refuses_a_checkpoint_of_another_algorithm_as_copied_not_damaged(tmp_path, toy_dataset, make_run, cli,
                                                                             one_line):  # fmt: skip
    run = make_run(tmp_path / "run", "coworld", toy_dataset, checkpoint_of="dreamerv2-finetune-ewc")  # intact
    out = tmp_path / "p.png"
    code, text = cli("viz", "predictions", "--ckpt", str(run), "--out", str(out), "--device", "cpu", "--length", "8")
    line = one_line(code, text, "'dreamerv2-finetune-ewc' checkpoint", "is a coworld run", "copied from another run")
    assert "damaged" not in line and not out.exists()


def test_train_refuses_a_source_replay_of_another_task_with_its_own_options(tmp_path, toy_dataset, cli, one_line):
    job = check_job(algo="coworld", source="toy_reach", target=TARGET, dataset=toy_dataset, preset="tiny",
                    logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    prepare_run_dir(job.logdir, job.config, job.info())
    shutil.copy(toy_dataset, job.logdir / "source_replay.h5")  # a toy_reach_shifted dataset, not toy_reach's
    before = digest(job.logdir)
    code, out = cli(*train(job.logdir, toy_dataset, "--source", "toy_reach"))
    line = one_line(code, out, "source_replay.h5 holds toy_reach_shifted experience", "--logdir", "--force")
    assert "--out" not in line and digest(job.logdir) == before


def test_train_refuses_a_source_choice_edited_to_another_candidate(tmp_path, toy_dataset, toy_dataset_writer, cli,
                                                                   one_line):  # fmt: skip
    candidates = "toy_reach,toy_reach_centre"
    job = check_job(algo="coworld", source=candidates, target=TARGET, dataset=toy_dataset, preset="tiny",
                    logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    prepare_run_dir(job.logdir, job.config, job.info())
    toy_dataset_writer(job.logdir / "source_replay.h5", "toy_reach", episodes=1)  # the chosen candidate's experience
    choice = {
        "candidates": candidates.split(","),
        "distances": {"toy_reach": 1.0, "toy_reach_centre": 2.0},
        "chosen": "toy_reach_centre",
        "align_on": "latent",
        "batches": 8,
    }  # edited: it chose toy_reach
    (job.logdir / "source_choice.json").write_text(json.dumps(choice))
    before = digest(job.logdir)
    code, out = cli(*train(job.logdir, toy_dataset, "--source", candidates))
    line = one_line(code, out, "source_replay.h5 holds toy_reach experience", "toy_reach_centre", "--force")
    assert "--out" not in line and digest(job.logdir) == before


def train(logdir: Path, dataset: Path, *extra: str) -> list[str]:
    return ["train", "--target", TARGET, "--dataset", str(dataset), "--logdir", str(logdir), "--preset", "tiny",
            "--device", "cpu", "--seed", "0", "--no-progress", *extra]  # fmt: skip


DAMAGED = {
    "a number": b"5",
    "a list": b"[]",
    "null": b"null",
    "an empty object": b"{}",
    "not UTF-8": b"\xff\xfe\x00garbage",
    "no algo": b'{"target": "toy_reach_shifted"}',
    "an unknown algo": b'{"algo": "ppo", "target": "toy_reach_shifted"}',
}


TINY_DREAMER = ["--algo", "dreamerv2", "--preset", "tiny", "--device", "cpu"]


def commands(run: Path, dataset: Path, tmp_path: Path) -> dict[str, list[str]]:
    return {
        "eval": ["eval", "--ckpt", str(run), "--episodes", "1", "--device", "cpu"],
        "viz": ["viz", "predictions", "--ckpt", str(run), "--out", str(tmp_path / "p.png"), "--device", "cpu"],
        "train": ["train", "--target", TARGET, "--dataset", str(dataset), "--logdir", str(run), *TINY_DREAMER],
    }


RUN_JSON_ONLY = ("no algo", "an unknown algo")
"""Damages that only a run.json can have (a config.json has no algo)."""


@pytest.mark.parametrize(
    ("file", "damage"),
    [("run.json", damage) for damage in sorted(DAMAGED)]
    + [("config.json", damage) for damage in sorted(DAMAGED) if damage not in RUN_JSON_ONLY],
)
def test_a_damaged_run_description_is_one_line_in_every_command(
    tmp_path, toy_dataset, make_run, file, damage, cli, one_line
):
    run = make_run(tmp_path / "run", "dreamerv2", toy_dataset)
    (run / file).write_bytes(DAMAGED[damage])
    before = digest(run)
    for name, args in commands(run, toy_dataset, tmp_path).items():
        code, out = cli(*args)
        line = one_line(code, out)
        named = "damaged" in line and file in line
        assert named or (name == "train" and "holds a run with algo='ppo'" in line), (name, line)
        assert digest(run) == before and not (tmp_path / "p.png").exists(), name


def test_a_damaged_run_json_as_a_real_process(tmp_path, toy_dataset, make_run, processes):
    run = make_run(tmp_path / "run", "dreamerv2", toy_dataset)
    (run / "run.json").write_bytes(b"\xff\xfe")
    done = processes.run_cli("eval", "--ckpt", str(run), "--device", "cpu")
    assert done.returncode == 2 and "not UTF-8" in processes.last_word(done.stderr, "error: ")


def test_a_checkpoint_missing_an_entry_is_refused_before_a_resume_writes_anything(tmp_path, toy_dataset, processes):
    job = check_job(algo="drq-bc", source=None, target=TARGET, dataset=toy_dataset, preset="tiny",
                    logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    prepare_run_dir(job.logdir, job.config, job.info())
    save_checkpoint(job.logdir / "checkpoint.pt", {"kind": "drq-bc"})
    before = digest(job.logdir)
    args = ["--target", TARGET, "--dataset", str(toy_dataset), "--logdir", str(job.logdir), "--preset", "tiny"]
    done = processes.run_cli("train", "--algo", "drq-bc", *args, "--device", "cpu", "--seed", "0")
    assert done.returncode == 2
    line = processes.last_word(done.stderr, "error: ")
    assert "damaged drq-bc checkpoint" in line and "'agent'" in line
    assert digest(job.logdir) == before


def test_eval_of_a_run_folder_without_a_checkpoint_says_so(tmp_path, toy_dataset, make_run, cli, one_line):
    run = make_run(tmp_path / "run", "dreamerv2", toy_dataset)
    (run / "checkpoint.pt").unlink()
    code, out = cli("eval", "--ckpt", str(run), "--device", "cpu")
    one_line(code, out, "holds no checkpoint.pt yet", "rerun the command that made it")


def test_eval_of_a_file_outside_a_run_folder_names_the_file(tmp_path, toy_dataset, cli, one_line):
    code, out = cli("eval", "--ckpt", str(toy_dataset), "--device", "cpu")
    one_line(code, out, f"{toy_dataset} is not inside a run folder")


@pytest.mark.parametrize("algo", ["dreamerv2-penalty", "dreamerv2-finetune", "lompo", "dreamerv2-finetune-ewc"])
def test_viz_predictions_looks_inside_the_model_based_variants(tmp_path, toy_dataset, make_run, algo, cli):
    run = make_run(tmp_path / "run", algo, toy_dataset)
    out = tmp_path / "p.png"
    code, text = cli("viz", "predictions", "--ckpt", str(run), "--out", str(out), "--device", "cpu", "--length", "8")
    assert code == 0, text
    assert f"({algo} run)" in text and out.exists()


class _RunsCode:
    def __reduce__(self):
        import os

        return (os.system, ("echo ran",))


def test_a_refused_pickle_is_one_line_with_the_whole_reason(tmp_path, toy_dataset, make_run, processes):
    import torch

    run = make_run(tmp_path / "run", "dreamerv2", toy_dataset)
    torch.save({"kind": "dreamerv2-offline", "agent": _RunsCode()}, run / "checkpoint.pt")
    done = processes.run_cli("eval", "--ckpt", str(run), "--device", "cpu")
    line = processes.last_word(done.stderr, "error: ")  # also: no torch warning before it
    assert done.returncode == 2 and "ran" not in done.stdout
    assert "unsupported GLOBAL posix.system whose module posix is blocked." in line, line
    assert "Weights only load failed" not in line


def test_a_preset_named_two_ways_resumes_and_a_missing_preset_is_named(tmp_path) -> None:
    """'tiny+' is 'tiny+table3' is 'tiny': one preset, so the folder resumes under any of its names; a run made with
    another preset is refused with both presets named, not only the first setting that differs."""
    from coworld.config import canonical_preset, make_config
    from coworld.errors import CoworldError
    from coworld.training.run import check_run_dir, prepare_run_dir

    assert canonical_preset("tiny+") == canonical_preset("tiny+table3") == "tiny"
    assert canonical_preset("cpu+later-dmc") == "cpu+later-dmc"
    info = {"algo": "dreamerv2", "source": None, "target": TARGET, "dataset": "d.h5", "preset": "tiny+"}
    prepare_run_dir(tmp_path / "run", make_config("tiny+"), info)
    for name in ("tiny", "tiny+", "tiny+table3"):
        assert check_run_dir(tmp_path / "run", make_config(name), {**info, "preset": name})
    with pytest.raises(CoworldError, match=r"made with --preset tiny \(this command's: paper\)"):
        check_run_dir(tmp_path / "run", make_config("paper"), {**info, "preset": "paper"})


def test_sequences_longer_than_every_episode_are_warned_of(toy_dataset) -> None:
    from coworld.data import open_dataset
    from coworld.training.train import longer_than_episodes

    with open_dataset(toy_dataset) as data:
        longest = int(data.lengths.max()) + 1
    assert longer_than_episodes(toy_dataset, (longest, "train.seq_len")) == []
    assert longer_than_episodes(toy_dataset, None) == []
    [warning] = longer_than_episodes(toy_dataset, (longest + 1, "train.seq_len"))
    assert f"train.seq_len={longest + 1} is longer than every episode" in warning and f"to {longest} or less" in warning


@pytest.mark.parametrize(
    ("algo", "length"),
    [
        ("dreamerv2", "dreamerv2 makes 40 updates (offline.updates)"),
        ("coworld", "coworld makes 40 target updates (coworld.iterations x coworld.target_updates) after 1,000 source"),
        ("drq-bc", "drq-bc makes 200 updates (drqbc.updates)"),
    ],
)
def test_train_steps_set_for_training_is_said_to_be_unread(algo: str, length: str) -> None:
    """``--set train.steps=300`` on ``coworld train`` changes nothing: the run says so and names its length."""
    from coworld.config import make_config
    from coworld.training.train import unread_length

    preset = make_config("tiny")
    assert unread_length(algo, preset, preset) == []
    [warning] = unread_length(algo, make_config("tiny", ["train.steps=300"]), preset)
    assert (
        warning.startswith("train.steps is the length of `coworld collect`'s online run, not of training")
        and length in warning
    )
