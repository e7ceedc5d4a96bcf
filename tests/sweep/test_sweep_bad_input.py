"""Bad sweeps refused before the sweep folder exists (values in grid files checked as strictly as flags, devices,
Ray addresses), the --jobs note, and SIGTERM's exit code, through the CLI as a real process."""

from __future__ import annotations

import json
import signal
import socket
import time
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from coworld.cli import main

TOY = 'pairs = ["toy_reach:toy_reach_shifted"]\npreset = "tiny"\n'


def refused(args: list[str], *needles: str) -> str:
    """Run ``coworld ARGS`` in this process; it must print one error line and exit 2."""
    result = CliRunner().invoke(main, args)
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), result.output
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize(
    "toml, needles",
    [
        ("seeds = [0, 1.5]", ["grid.toml: a seed must be a whole number", "1.5"]),
        ("seeds = [0, true]", ["grid.toml: a seed must be a whole number"]),
        ("seeds = [0, 4294967296]", ["a seed must be in [0, 4,294,967,295]"]),
        ("seeds = 0", ["seeds must be in [1, 1,000]"]),
        ('seeds = "3"', ["seeds must be a count or a list"]),
        ('ablation = "yes"', ["grid.toml: ablation must be true or false", "'yes'"]),
        ("eval_episodes = 2.0", ["grid.toml: eval_episodes must be a whole number"]),
        ('algos = "curl"', ["grid.toml: algos must be a list"]),
        ('set = "train.steps=5"', ["grid.toml: set must be a list"]),
        ("set = [5]", ["grid.toml: set must be a list of strings"]),
        ('set = ["train.steps=1e30"]', ["train.steps", "up to 9,223,372,036,854,775,807"]),
        ('[data]\npolicy = "random"\nepisodes = "4"', ["grid.toml: data.episodes must be a whole number"]),
        ('[data]\npolicy = "random"\nepisodes = 4\nseed = -1', ["data seed must be in [0, 4,294,967,295]"]),
        ('[data]\nset = ["world_model.nope=1"]', ["data set: unknown config key 'world_model.nope'"]),
        ("data = 3", ["grid.toml: data must be a table"]),
    ],
)
def test_grid_file_values_are_checked_like_flags_before_the_folder_exists(tmp_path, toml, needles):
    grid = tmp_path / "grid.toml"
    grid.write_text(TOY + toml + "\n")
    refused(["sweep", "--grid", str(grid), "--dir", str(tmp_path / "sweep")], *needles)
    assert not (tmp_path / "sweep").exists()


def test_a_string_where_the_pairs_list_belongs_is_named(tmp_path):
    grid = tmp_path / "grid.toml"
    grid.write_text('pairs = "toy_reach:toy_reach_shifted"\n')
    refused(["sweep", "--grid", str(grid), "--dir", str(tmp_path / "s")], "pairs must be a list")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_on_a_machine_without_it_is_refused_before_any_dataset(tmp_path):
    refused(["sweep", "--table", "toy", "--dir", str(tmp_path / "s"), "--device", "cuda"], "no CUDA GPU")
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize(
    "folder, said",
    [
        ("", "Invalid value for '--dir': an empty path"),
        ("{file}/sweep", "is a file, not a folder; choose another --dir"),
    ],
)
def test_a_sweep_folder_that_cannot_be_made_is_refused(tmp_path, folder, said):
    (tmp_path / "file").write_text("a file")
    result = CliRunner().invoke(main, ["sweep", "--table", "toy", "--dir", folder.format(file=tmp_path / "file")])
    assert result.exit_code == 2 and said in result.output and "Traceback" not in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_jobs_beyond_the_cores_are_capped_with_a_note(tmp_path):
    result = CliRunner().invoke(main, ["sweep", "--table", "toy", "--dir", str(tmp_path / "s"), "--jobs", "100000",
                                       "--dry-run"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "note: --jobs 100000 capped to" in result.output and "per CPU core" in result.output


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_ray_address_where_no_cluster_answers_is_one_line_within_seconds(tmp_path, processes):
    """Only loopback is contacted (nothing listens on a port just freed; the listener below speaks no gRPC).

    An address the sweep need not contact is refused first; each contacted address may take 20 s beyond that (the
    command's start-up and plan, slower on a busy machine), far less than Ray's own retries (minutes)."""
    with socket.socket() as listener:  # something that answers, but not as a Ray head does
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        addresses = ["not-an-address", f"127.0.0.1:{listener.getsockname()[1]}", "127.0.0.1:0"]
        addresses += [f"ray://127.0.0.1:{free_port()}"]
        allowed = None
        for address in addresses:
            folder = tmp_path / address.replace(":", "-").replace("/", "")
            start = time.monotonic()
            done = processes.run_cli("sweep", "--table", "toy", "--dir", str(folder), "--ray", address, timeout=120)
            seconds = time.monotonic() - start
            allowed = allowed or seconds + 20
            assert seconds < allowed, address
            assert done.returncode == 2, done.stderr
            line = processes.last_word(done.stderr, "error: ")
            assert address in line and ("ray start --head" in line or "is not an address" in line)
            assert done.stderr.count("\n") == 1  # none of Ray's own log lines
            assert not folder.exists()


GRID = (
    TOY
    + """algos = ["curl"]
seeds = 1
eval_episodes = 1
set = ["curl.updates=2000", "curl.eval_every=1000", "curl.checkpoint_every=1000"]
[data]
policy = "random"
episodes = 4
"""
)


def test_sigterm_stops_the_sweep_and_its_child_with_exit_code_143(tmp_path, processes, process_gone):
    grid = tmp_path / "grid.toml"
    grid.write_text(GRID)
    root = tmp_path / "sweep"
    proc = processes.start_cli("sweep", "--grid", str(grid), "--dir", str(root), "--device", "cpu", "--no-progress")
    pid_files = lambda: list((root / "logs").glob("*.pid")) if (root / "logs").exists() else []  # noqa: E731
    processes.wait_for(lambda: bool(pid_files()), proc, timeout=120, what="the first job's command")
    child = json.loads(pid_files()[0].read_text())["pid"]
    stopped = processes.stop(proc, signal.SIGTERM, timeout=60)
    assert stopped.returncode == 143, stopped.stderr[-2000:]
    assert stopped.seconds < 15
    assert "stopped by SIGTERM: finished runs are kept; rerun the same command" in stopped.stderr
    assert process_gone(child)
    assert Path(root / "sweep.json").exists()  # the rerun resumes this folder


@pytest.mark.parametrize(
    "args, needles",
    [
        (["--pairs", "toy_reach:toy_reach_shifted", "--preset", "tiny", "--set", "penalty.model_updates=40"],
         ["the dreamerv2-penalty runs", "penalty.model_updates=40 leaves none"]),
        (["--pairs", "toy_reach:toy_reach_shifted", "--algos", "lompo", "--preset", "tiny", "--set",
          "lompo.model_updates=40"], ["the lompo runs", "lompo.model_updates=40 leaves none"]),
        (["--table", "toy-cpu", "--set", "penalty.model_updates=100000"], ["penalty.model_updates=100000"]),
        (["--table", "toy-cpu", "--set", "penalty.model_updates=100000", "--dry-run"], ["penalty.model_updates"]),
        (["--pairs", "toy_reach:toy_reach_shifted", "--preset", "tiny", "--set", "penalty.ensemble=1000000000"],
         ["penalty.ensemble", "GiB"]),
        (["--pairs", "toy_reach:toy_reach_shifted", "--algos", "lompo", "--preset", "tiny", "--set",
          "lompo.batch_size=1000000000", "--dry-run"], ["the lompo runs", "lompo.batch_size", "GiB"]),
    ],
)  # fmt: skip
def test_the_rules_train_applies_are_checked_for_every_run_before_the_folder_exists(tmp_path, args, needles):
    refused(["sweep", *args, "--dir", str(tmp_path / "s")], *needles)
    assert not (tmp_path / "s").exists()


def test_a_rule_train_applies_refuses_a_real_sweep_process_before_collecting(tmp_path, processes):
    done = processes.run_cli("sweep", "--pairs", "toy_reach:toy_reach_shifted", "--preset", "tiny", "--set",
                             "penalty.model_updates=40", "--dir", str(tmp_path / "s"))  # fmt: skip
    assert done.returncode == 2 and "penalty.model_updates=40" in processes.last_word(done.stderr, "error: ")
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["--pairs", "toy_reach:toy_reach_shifted,"], ["--pairs", "empty pair", "SOURCE:TARGET"]),
        (["--pairs", "toy_reach_shifted:toy_reach_shifted"], ["pair toy_reach_shifted:toy_reach_shifted", "target"]),
        (["--pairs", "toy_reach+toy_reach_shifted:toy_reach_shifted"], ["source toy_reach_shifted is the target"]),
    ],
)
def test_pairs_train_would_refuse_are_refused(tmp_path, args, needles):
    refused(["sweep", *args, "--preset", "tiny", "--dir", str(tmp_path / "s"), "--dry-run"], *needles)
    assert not (tmp_path / "s").exists()


def test_a_grid_file_and_a_table_are_not_combined(tmp_path):
    grid = tmp_path / "grid.toml"
    grid.write_text(TOY)
    refused(["sweep", "--grid", str(grid), "--table", "toy", "--dir", str(tmp_path / "s"), "--dry-run"], "--grid",
            "--table")  # fmt: skip
    assert not (tmp_path / "s").exists()


def test_an_unknown_table_exits_2_naming_the_tables_and_writes_nothing(tmp_path):
    result = CliRunner().invoke(main, ["sweep", "--table", "nope", "--dir", str(tmp_path / "s")])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert "Invalid value for '--table': 'nope' is not one of" in result.output
    assert "'dmc-me', 'dmc-mr'" in result.output
    assert not (tmp_path / "s").exists()


def test_an_unknown_table_in_a_grid_file_is_one_line(tmp_path):
    grid = tmp_path / "grid.toml"
    grid.write_text('table = "nope"\n')
    refused(["sweep", "--grid", str(grid), "--dir", str(tmp_path / "s")], "unknown table 'nope'; choose from", "dmc-mr")
    assert not (tmp_path / "s").exists()
