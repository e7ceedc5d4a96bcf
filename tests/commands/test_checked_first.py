"""Every check that can be made before work is made before work and before anything is written: eval's video,
a dataset shorter than the sequences sampled from it, sizes that cannot be built, the rules between config keys; and
a run folder of other settings can be started over from the command line."""

from __future__ import annotations

import json

import pytest

from coworld.algorithms import ALGOS
from coworld.budget import check_memory, estimate
from coworld.config import make_config
from coworld.errors import ConfigError

TARGET = "toy_reach_shifted"


@pytest.mark.parametrize(
    ("video", "needle"),
    [("v.txt", "cannot write .txt"), ("v", "cannot write a file without suffix"), ("same.mp4", "both name")],
)
def test_eval_checks_its_video_before_it_evaluates(tmp_path, toy_dataset, make_run, processes, video, needle):
    run = make_run(tmp_path / "run", "dreamerv2", toy_dataset)
    out = tmp_path / ("same.mp4" if video == "same.mp4" else "results.json")
    done = processes.run_cli("eval", "--ckpt", str(run), "--device", "cpu", "--episodes", "1",
                             "--video", str(tmp_path / video), "--out", str(out))  # fmt: skip
    assert done.returncode == 2 and needle in processes.last_word(done.stderr, "error: ")
    assert "return" not in done.stdout  # refused before the evaluation
    assert not out.exists() and not (tmp_path / video).exists() and not (run / "eval.json").exists()


def test_a_dataset_shorter_than_a_sequence_is_refused_before_pretraining(tmp_path, toy_dataset, processes):
    logdir = tmp_path / "run"
    done = processes.run_cli("train", "--algo", "dreamerv2-finetune", "--source", "toy_reach", "--target", TARGET,
                             "--dataset", str(toy_dataset), "--logdir", str(logdir), "--preset", "tiny",
                             "--device", "cpu", "--set", "train.seq_len=5000")  # fmt: skip
    assert done.returncode == 2
    line = processes.last_word(done.stderr, "error: ")
    assert "train.seq_len needs sequences of 5000" in line and "steps" in line
    assert not logdir.exists()


@pytest.mark.parametrize(
    ("algo", "override", "key"),
    [
        ("dreamerv2-penalty", "penalty.ensemble=1000000000", "penalty.ensemble"),
        ("lompo", "lompo.ensemble=1000000000", "lompo.ensemble"),
        ("lompo", "lompo.units=10000000", "lompo.units"),
        ("lompo", "lompo.batch_size=1000000000", "lompo.batch_size"),  # its latent transitions and activations
        ("drq-bc", "drqbc.frame_stack=1000000", "drqbc.frame_stack"),
        ("dreamerv2", "world_model.deter=1000000000", "world_model.deter"),
    ],
)
def test_sizes_that_cannot_be_built_are_refused_before_the_run_folder_exists(tmp_path, toy_dataset, algo, override,
                                                                             key, cli, one_line):  # fmt: skip
    logdir = tmp_path / "run"
    code, out = cli("train", "--algo", algo, "--target", TARGET, "--dataset", str(toy_dataset), "--logdir",
                    str(logdir), "--preset", "tiny", "--device", "cpu", "--set", override)  # fmt: skip
    one_line(code, out, f"config key {key}=", "GiB", f"lower {key}")
    assert not logdir.exists()


def test_a_sizes_refusal_as_a_real_process_is_quick(tmp_path, toy_dataset, processes):
    done = processes.run_cli("train", "--algo", "dreamerv2-penalty", "--target", TARGET, "--dataset",
                             str(toy_dataset), "--logdir", str(tmp_path / "run"), "--preset", "tiny", "--device",
                             "cpu", "--set", "penalty.ensemble=1000000000", timeout=60)  # fmt: skip
    assert done.returncode == 2 and "penalty.ensemble" in processes.last_word(done.stderr, "error: ")


def test_the_memory_estimate_passes_every_preset_and_refuses_past_the_machine():
    for preset in ("paper", "cpu", "tiny"):
        for algo in ALGOS:
            check_memory(algo, make_config(preset), available=32 * 2**30)  # what a paper-size GPU host has
    # each Fisher batch's gradients are held until their mean is taken
    ewc = make_config("paper", ["ewc.fisher_batches=10000"])
    assert estimate("dreamerv2-finetune-ewc", ewc)[0].key == "ewc.fisher_batches"
    config = make_config("tiny", ["train.envs=200"])
    assert estimate("dreamerv2", config)[0].key == "train.envs"
    with pytest.raises(ConfigError, match="train.envs=200 makes a dreamerv2 run allocate at least"):
        check_memory("dreamerv2", config, available=2**30)


def test_actor_min_std_above_max_is_refused(tmp_path, toy_dataset, cli, one_line):
    code, out = cli("train", "--algo", "dreamerv2", "--target", TARGET, "--dataset", str(toy_dataset), "--logdir",
                    str(tmp_path / "run"), "--preset", "tiny", "--set", "actor_critic.actor_min_std=2")  # fmt: skip
    one_line(code, out, "actor_critic.actor_min_std=2.0", "actor_critic.actor_max_std=1.0")
    assert not (tmp_path / "run").exists()


def test_drq_bc_on_the_cpu_preset_is_warned_about(tmp_path, toy_dataset):
    from coworld.training.train import check_job

    job = check_job(algo="drq-bc", source=None, target=TARGET, dataset=toy_dataset, preset="cpu",
                    logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    assert any("cpu preset sizes coworld" in w and "--preset tiny" in w for w in job.warnings)
    paper = check_job(algo="dreamerv2", source=None, target=TARGET, dataset=toy_dataset, preset="paper",
                      logdir=tmp_path / "run", seed=0, device="cpu", overrides=())  # fmt: skip
    assert any("--preset cpu" in w for w in paper.warnings)


def test_train_force_starts_a_run_folder_of_other_settings_over(tmp_path, toy_dataset, make_run, cli, one_line):
    run = make_run(tmp_path / "run", "dreamerv2", toy_dataset)
    (run / "notes.txt").write_text("mine")
    args = ["train", "--algo", "dreamerv2", "--target", TARGET, "--dataset", str(toy_dataset), "--logdir", str(run),
            "--preset", "tiny", "--device", "cpu", "--no-progress", "--set", "train.seq_len=8"]  # fmt: skip
    code, out = cli(*args[:-2], "--set", "train.seq_len=4")
    line = one_line(code, out, "other settings", "--force")
    assert "--logdir" in line
    code, out = cli(*args, "--force", "--set", "offline.updates=2", "--set", "offline.eval_episodes=1")
    assert code == 0, out
    assert "--force: starting" in out and (run / "notes.txt").read_text() == "mine"
    assert json.loads((run / "config.json").read_text())["train"]["seq_len"] == 8


def test_collects_hint_names_its_own_options(tmp_path, cli, one_line):
    from coworld.training.description import collector_run_info
    from coworld.training.run import prepare_run_dir

    out = tmp_path / "d.h5"
    prepare_run_dir(
        tmp_path / "d.run", make_config("tiny", ["seed=0", "device=cpu"]), collector_run_info("toy_reach", "tiny")
    )
    code, text = cli("collect", "--task", "toy_reach", "--preset", "cpu", "--device", "cpu", "--max-steps", "100",
                     "--out", str(out), "--resume")  # fmt: skip
    line = one_line(code, text, "other settings", f"pass --force to start {out} and its agent over")
    assert "--logdir" not in line and not out.exists()


@pytest.mark.parametrize("algo", ["dreamerv2-finetune", "dreamerv2-finetune-ewc"])
def test_a_fine_tuned_dreamerv2_without_a_source_is_refused_in_one_line(tmp_path, toy_dataset, algo, cli, one_line):
    logdir = tmp_path / "run"
    code, out = cli("train", "--algo", algo, "--target", TARGET, "--dataset", str(toy_dataset), "--logdir",
                    str(logdir), "--preset", "tiny", "--device", "cpu")  # fmt: skip
    one_line(code, out, f"{algo} needs an online source domain", "--source toy_reach")
    assert not logdir.exists()


@pytest.mark.parametrize(
    ("algo", "override", "needles"),
    [
        ("lompo", "lompo.horizon=0", ("lompo.horizon=0", "in [1, 1000]")),
        ("lompo", "lompo.tau=0", ("lompo.tau=0.0", "in (0, 1]")),
        ("lompo", "lompo.discount=1.5", ("lompo.discount=1.5", "in (0, 1]")),
        ("lompo", "lompo.weight=-1", ("lompo.weight=-1.0", "in [0, 1000000000000]")),
        ("lompo", "lompo.ensemble=1", ("lompo.ensemble=1", ">= 2")),
        ("lompo", "lompo.batch_size=many", ("lompo.batch_size", "a whole number")),
        ("lompo", "lompo.model_updates=40", ("lompo.model_updates=40 leaves none of the run's 40 updates",)),
        ("lompo", "train.seq_len=1", ("train.seq_len must be at least 2",)),
        ("dreamerv2-finetune-ewc", "ewc.weight=-0.5", ("ewc.weight=-0.5", "in [0, 1000000000000]")),
        ("dreamerv2-finetune-ewc", "ewc.fisher_batches=0", ("ewc.fisher_batches=0", "in [1, 10000]")),
        ("dreamerv2-finetune-ewc", "ewc.lambda=1", ("unknown config key 'ewc.lambda'",)),
    ],
)
def test_bad_lompo_and_ewc_values_are_refused_before_the_run_folder_exists(tmp_path, toy_dataset, algo, override,
                                                                           needles, cli, one_line):  # fmt: skip
    logdir = tmp_path / "run"
    code, out = cli("train", "--algo", algo, "--source", "toy_reach", "--target", TARGET, "--dataset",
                    str(toy_dataset), "--logdir", str(logdir), "--preset", "tiny", "--device", "cpu", "--set",
                    override)  # fmt: skip
    one_line(code, out, *needles)
    assert not logdir.exists()
