"""More bad input, refused before anything is written: run folders that are not ours, values a run would only
trip over late, images of the wrong size, evaluation on another body; and the warnings a long run starts with."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from coworld.config import make_config
from coworld.data import DatasetWriter
from coworld.training.checkpoint import save_checkpoint
from coworld.training.run import prepare_run_dir
from coworld.training.train import check_job


def digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def fake_dataset(path: Path, task: str, action_size: int, image_shape=(64, 64, 3)) -> Path:
    with DatasetWriter(
        path, task=task, env_config={}, quality="random", collector={}, action_size=action_size, image_shape=image_shape
    ) as writer:
        writer.add_episode(  # 17 frames: the tiny preset's sequences of 16 steps fit
            np.zeros((17, *image_shape), np.uint8), np.zeros((16, action_size)), np.zeros(16), terminated=False
        )
        writer.close(complete=True)
    return path


def train_args(dataset: Path, logdir: Path, *extra: str) -> list[str]:
    return ["train", "--source", "toy_reach", "--target", "toy_reach_shifted", "--dataset", str(dataset),
            "--logdir", str(logdir), "--preset", "tiny", *extra]  # fmt: skip


def test_a_folder_with_a_checkpoint_but_no_config_is_refused_and_left_untouched(tmp_path, toy_dataset, cli, one_line):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "checkpoint.pt").write_bytes(b"a CURL checkpoint copied here")
    (folder / "metrics.jsonl").write_text("{}\n")
    before = digest(folder)
    code, out = cli(*train_args(toy_dataset, folder, "--algo", "dreamerv2"))
    one_line(code, out, "checkpoint.pt, metrics.jsonl but no config.json", "nothing was changed")
    assert "resuming" not in out and digest(folder) == before


@pytest.mark.parametrize("bad", ["precision=fp8", "coworld.align_on=encoder", "actor_critic.actor_dist=beta"])
def test_a_value_a_run_would_trip_over_late_is_refused_before_the_run_folder_exists(
    tmp_path, toy_dataset, bad, cli, one_line
):
    code, out = cli(*train_args(toy_dataset, tmp_path / "run", "--set", bad))
    one_line(code, out, bad.split("=")[0], "out of range")
    assert not (tmp_path / "run").exists()  # so the corrected command starts afresh


def test_a_refused_resume_says_why_without_first_claiming_to_resume(tmp_path, toy_dataset, cli, one_line):
    job = check_job(algo="coworld", source="toy_reach", target="toy_reach_shifted", dataset=toy_dataset,
                    preset="tiny", logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    prepare_run_dir(job.logdir, job.config, job.info())
    save_checkpoint(job.logdir / "checkpoint.pt", {"kind": "coworld"})
    code, out = cli(*train_args(toy_dataset, tmp_path / "run", "--device", "cpu", "--set", "coworld.k=0.5"))
    one_line(code, out, "other settings", "coworld.k")
    assert "resuming" not in out


@pytest.mark.parametrize("source", ["toy_reach_shifted", "toy_reach,toy_reach_shifted", "toy_reach+toy_reach_shifted"])
def test_a_source_that_is_the_target_is_refused(tmp_path, toy_dataset, source, cli, one_line):
    args = ["train", "--source", source, "--target", "toy_reach_shifted", "--dataset", str(toy_dataset), "--logdir",
            str(tmp_path / "run"), "--preset", "tiny"]  # fmt: skip
    one_line(*cli(*args), "source toy_reach_shifted is the target itself", "--source toy_reach")
    assert not (tmp_path / "run").exists()


def test_an_unknown_preset_is_named_before_a_missing_source(cli, one_line):
    one_line(*cli("train", "--target", "toy_reach_shifted", "--preset", "foo"), "unknown preset 'foo'")


def test_train_help_says_how_to_write_several_sources(cli):
    code, out = cli("train", "--help")
    assert code == 0 and "A,B,... or A+B+..." in " ".join(out.split())


def test_the_missing_source_hint_names_the_targets_own_pair(cli, one_line):
    code, out = cli("train", "--target", "cheetah_nopaw")
    one_line(code, out, "--source cheetah_run")


def test_different_bodies_with_one_action_size_are_warned_about(tmp_path):
    dataset = fake_dataset(tmp_path / "cheetah.h5", "cheetah_uphill", 6)
    job = check_job(algo="coworld", source="walker_walk", target="cheetah_uphill", dataset=dataset, preset="tiny",
                    logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    assert any("different bodies" in w and "cheetah_run -> cheetah_uphill" in w for w in job.warnings)
    paired = check_job(algo="coworld", source="cheetah_run", target="cheetah_uphill", dataset=dataset,
                       preset="tiny", logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    assert paired.warnings == ()


def test_the_paper_preset_on_a_cpu_starts_with_a_warning(tmp_path, toy_dataset):
    common = dict(algo="dreamerv2", source=None, target="toy_reach_shifted", dataset=toy_dataset,
                  logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    assert any("sized for a GPU" in w and "--preset tiny" in w for w in check_job(preset="paper", **common).warnings)
    assert check_job(preset="tiny", **common).warnings == ()


def test_frames_of_another_size_are_refused_with_the_size_the_models_take(tmp_path, cli, one_line):
    dataset = fake_dataset(tmp_path / "big.h5", "toy_reach_shifted", 2, image_shape=(84, 84, 3))
    code, out = cli(*train_args(dataset, tmp_path / "run"))
    one_line(code, out, "84 x 84 x 3 frames", "64 x 64 x 3")
    assert not (tmp_path / "run").exists()


def test_eval_on_a_task_of_another_action_size_is_refused(tmp_path, cli, one_line):
    from coworld.agents.dreamerv2 import DreamerV2

    config = make_config("tiny", ["device=cpu"])
    folder = tmp_path / "run"
    info = {"algo": "dreamerv2", "source": None, "target": "toy_reach_shifted", "dataset": "x", "preset": "tiny"}
    prepare_run_dir(folder, config, info)
    agent = DreamerV2(config=config, action_size=2)
    save_checkpoint(folder / "checkpoint.pt", {"kind": "dreamerv2-offline", "agent": agent.state_dict()})
    code, out = cli("eval", "--ckpt", str(folder), "--task", "walker_walk", "--device", "cpu")
    one_line(code, out, "walker_walk takes 6-d actions", "toy_reach_shifted (2-d)")


@pytest.mark.parametrize(
    "args",
    [
        ["eval", "--ckpt", "x", "--video-episodes", "-3"],
        ["collect", "--task", "toy_reach", "--policy", "random", "--episodes", "1", "--seed", "-1"],
        ["train", "--target", "toy_reach_shifted", "--source", "toy_reach", "--seed", "-1"],
    ],
)
def test_negative_counts_and_seeds_are_usage_errors(args, cli):
    code, out = cli(*args)
    assert code == 2 and "Invalid value" in out and "Traceback" not in out


def test_an_unfinished_dataset_is_warned_about(tmp_path):
    path = tmp_path / "partial.h5"
    with DatasetWriter(
        path, task="toy_reach_shifted", env_config={}, quality="random", collector={}, action_size=2
    ) as w:
        w.add_episode(np.zeros((17, 64, 64, 3), np.uint8), np.zeros((16, 2)), np.zeros(16), terminated=False)
    job = check_job(algo="dreamerv2", source=None, target="toy_reach_shifted", dataset=path, preset="tiny",
                    logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    assert any("is not complete" in warning for warning in job.warnings)
