"""`coworld viz` refusals before any work, as a real process: outputs naming one file, a missing run folder, a
source dataset of the wrong task."""

from __future__ import annotations

from .conftest import make_run


def test_two_outputs_naming_one_file_are_refused(tmp_path, target_dataset, processes):
    run = make_run(tmp_path, "coworld", target_dataset)
    out = tmp_path / "x.png"
    done = processes.run_cli("viz", "latents", "--ckpt", str(run), "--out", str(out), "--json", str(out))
    line = processes.last_word(done.stderr, "error: ")
    assert done.returncode == 2 and "--out and --json both name" in line and not out.exists()


def test_a_missing_run_folder_is_named_itself(tmp_path, processes):
    missing = tmp_path / "runs" / "nothing-here"
    done = processes.run_cli("viz", "predictions", "--ckpt", str(missing), "--out", str(tmp_path / "p.png"))
    line = processes.last_word(done.stderr, "error: ")
    assert done.returncode == 2 and f"no run folder or checkpoint at {missing};" in line


def test_a_source_dataset_of_the_wrong_task_is_refused(tmp_path, target_dataset, processes):
    run = make_run(tmp_path, "coworld", target_dataset)
    done = processes.run_cli("viz", "latents", "--ckpt", str(run), "--out", str(tmp_path / "l.png"),
                             "--source-dataset", str(target_dataset), "--device", "cpu")  # fmt: skip
    line = processes.last_word(done.stderr, "error: ")
    assert done.returncode == 2 and "not the source task toy_reach" in line
    assert not (tmp_path / "l.png").exists()
