"""Writes the system refuses: a full disk during collect, merge, train and checkpoints; read-only output locations;
a folder passed as a dataset file. Each ends with one line and exit code 2, and damages nothing.

The disks are real (see ``small_disk`` and ``read_only_folder`` in conftest.py): a small tmpfs and a read-only
remount as root, as CI runs, else a file size limit and a folder without write permission.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import ModuleType

import pytest
import torch

from coworld.config import make_config
from coworld.data import open_dataset, verify_dataset
from coworld.errors import StorageError
from coworld.training import pretrained
from coworld.training.checkpoint import load_checkpoint, save_checkpoint

MiB = 2**20
COLLECT = "collect --task toy_reach --policy random --quiet".split()
DV2_COLLECT = (
    "collect --task toy_reach --preset tiny --quiet --device cpu --threads 1 --set train.prefill=100"
    " --set train.eval_every=100000 --set train.checkpoint_every=50"
).split()
EVAL = "eval --episodes 1 --device cpu --ckpt".split()
TRAIN_DV2 = (
    "train --algo dreamerv2 --target toy_reach_shifted --preset tiny --no-progress --device cpu --threads 1"
    " --set offline.updates=6 --set offline.eval_every=3 --set offline.checkpoint_every=3"
    " --set offline.eval_episodes=1"
).split()


def _one_error_line(processes: ModuleType, result) -> str:
    """The single error line of a command that failed with exit code 2 and no traceback."""
    assert result.returncode == 2, result.stderr[-3000:]
    return processes.last_word(result.stderr, "error: ")


def test_a_full_disk_stops_collect_and_resume_continues(small_disk, processes: ModuleType, helpers: ModuleType) -> None:
    disk = small_disk(3 * MiB)
    out = disk.path / "a.h5"
    args = [*COLLECT, "--episodes", "20", "--compression", "none", "--out", str(out)]
    line = _one_error_line(processes, processes.run_cli(*args, **disk.popen()))
    assert line.startswith(f"error: cannot write {out}: ") and "--resume" in line
    kept = int(re.search(r"(\d+) committed episodes? (is|are) intact", line).group(1))
    with open_dataset(out) as data:
        assert not data.complete and data.num_episodes == kept and 0 < kept < 20
    helpers.assert_unfinished_but_sound(out)  # every committed episode passes its checksum
    before = helpers.episode_digests(out)

    disk.grow(64 * MiB)  # space freed
    resumed = processes.run_cli(*args, "--resume", **disk.popen())
    assert resumed.returncode == 0, resumed.stderr
    assert "wrote" in resumed.stdout and "20 episodes" in resumed.stdout
    with open_dataset(out) as data:
        assert data.complete and data.num_episodes == 20
    assert helpers.episode_digests(out)[:kept] == before
    assert verify_dataset(out) == []


def test_a_full_disk_stops_the_dreamerv2_collector_and_resume_continues(
    small_disk, processes: ModuleType, helpers: ModuleType, tmp_path: Path
) -> None:
    disk = small_disk(2 * MiB)
    out = disk.path / "b.h5"
    (tmp_path / "agent").mkdir()
    (disk.path / "b.run").symlink_to(tmp_path / "agent")  # the agent's run folder on a disk with room: the data fails
    args = [*DV2_COLLECT, "--max-steps", "400", "--compression", "none", "--out", str(out)]
    line = _one_error_line(processes, processes.run_cli(*args, **disk.popen()))
    assert line.startswith(f"error: cannot write {out}: ") and "intact" in line and "--resume" in line
    with open_dataset(out) as data:
        assert not data.complete and 0 < data.num_steps < 400
        kept = data.num_episodes
    helpers.assert_unfinished_but_sound(out)
    before = helpers.episode_digests(out)

    disk.grow(64 * MiB)
    resumed = processes.run_cli(*args, "--resume", **disk.popen())
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    with open_dataset(out) as data:
        assert data.complete and data.num_steps == 400  # exactly the rows asked for
    assert helpers.episode_digests(out)[:kept] == before
    assert verify_dataset(out) == []


def test_a_full_disk_stops_merge_and_leaves_out_as_it_was(
    small_disk, processes: ModuleType, helpers: ModuleType, tmp_path: Path
) -> None:
    episodes = helpers.make_episodes([60] * 30)
    a = helpers.write_dataset(tmp_path / "a.h5", episodes[:15], compression="none")
    b = helpers.write_dataset(tmp_path / "b.h5", episodes[15:], compression="none")
    disk = small_disk(3 * MiB)
    out = helpers.write_dataset(disk.path / "m.h5", episodes[:2], compression="none")
    before = helpers.folder_state(disk.path)
    args = ["dataset", "merge", str(a), str(b), "--out", str(out), "--force", "--compression", "none"]
    line = _one_error_line(processes, processes.run_cli(*args, **disk.popen()))
    assert line.startswith(f"error: cannot write the merge next to {out}: ") and f"{out} is as it was" in line
    assert helpers.folder_state(disk.path) == before  # no half-made merge, no lock file left behind

    disk.grow(64 * MiB)
    done = processes.run_cli(*args, **disk.popen())
    assert done.returncode == 0, done.stderr
    assert helpers.assert_whole_prefix(out, episodes) == 30 and verify_dataset(out) == []


def test_a_full_disk_keeps_the_previous_checkpoint(small_disk, tmp_path: Path) -> None:
    disk = small_disk(1 * MiB)
    path = disk.path / "checkpoint.pt"
    with disk.limited():
        with pytest.raises(StorageError, match=r"cannot save checkpoint .*: .*; no earlier checkpoint exists$"):
            save_checkpoint(path, {"kind": "test", "weights": torch.zeros(2 * MiB // 4)})
        assert list(disk.path.iterdir()) == []  # not even the temporary file
        save_checkpoint(path, {"kind": "test", "weights": torch.ones(MiB // 16)})
        with pytest.raises(StorageError, match=r"cannot save checkpoint .*; the previous checkpoint is intact$"):
            save_checkpoint(path, {"kind": "test", "weights": torch.zeros(2 * MiB // 4)})
    assert [p.name for p in disk.path.iterdir()] == ["checkpoint.pt"]
    assert torch.equal(load_checkpoint(path)["weights"], torch.ones(MiB // 16))


def test_a_full_disk_while_keeping_pretraining_leaves_no_copy_marked_whole(small_disk) -> None:
    disk = small_disk(4 * MiB, file_size=3 * MiB // 2)  # room for the copied replay, not for the checkpoint after it
    run, later = disk.path / "run", disk.path / "later"
    run.mkdir()
    later.mkdir()
    (run / "source_replay.h5").write_bytes(bytes(range(256)) * (MiB // 256))
    (run / "metrics.jsonl").write_text('{"step": 0}\n')
    state = {"kind": "test", "weights": torch.ones(2 * MiB // 4)}
    with disk.limited():
        with pytest.raises(StorageError, match=r"^cannot save checkpoint .*pretrained/checkpoint\.pt: "):
            pretrained.keep(run, state)
    assert sorted(p.name for p in (run / pretrained.SNAPSHOT).iterdir()) == ["metrics.jsonl", "source_replay.h5"]
    assert pretrained.start_from(later, [run], make_config("tiny")) is None  # no checkpoint: not a whole copy
    assert list(later.iterdir()) == []

    disk.grow(32 * MiB)
    with disk.limited():
        pretrained.keep(run, state)  # the rerun keeps it whole
        assert pretrained.start_from(later, [run], make_config("tiny")) == run
    assert (later / "source_replay.h5").read_bytes() == (run / "source_replay.h5").read_bytes()
    assert torch.equal(load_checkpoint(later / "checkpoint.pt")["weights"], state["weights"])


def test_a_full_disk_during_training_keeps_the_last_checkpoint_and_the_rerun_finishes(
    small_disk, processes: ModuleType, toy_dataset_writer, tmp_path: Path
) -> None:
    dataset = toy_dataset_writer(tmp_path / "toy.h5", "toy_reach_shifted")
    disk = small_disk(8 * MiB, file_size=4 * MiB)  # room for one tiny DreamerV2 checkpoint (5 MB), not for two
    run = disk.path / "run"
    args = [*TRAIN_DV2, "--dataset", str(dataset), "--logdir", str(run)]
    line = _one_error_line(processes, processes.run_cli(*args, **disk.popen()))
    assert line.startswith(f"error: cannot save checkpoint {run / 'checkpoint.pt'}: ")
    assert not (run / ".checkpoint.pt.tmp").exists()
    if disk.mounted:  # the first iteration's checkpoint fitted, its replacement did not
        assert line.endswith("; the previous checkpoint is intact; free space, then rerun the same command to resume")
        assert load_checkpoint(run / "checkpoint.pt")["updates"] == 3
    else:  # a file size limit: no checkpoint fits
        assert line.endswith("; no earlier checkpoint exists; free space, then rerun the same command to resume")

    disk.grow(64 * MiB)
    done = processes.run_cli(*args, **disk.popen())
    assert done.returncode == 0, done.stderr[-3000:]
    assert load_checkpoint(run / "checkpoint.pt")["updates"] == 6


def test_read_only_outputs_are_refused_in_one_line_and_left_untouched(
    read_only_folder, processes: ModuleType, helpers: ModuleType, toy_dataset_writer, untrained_run: Path
) -> None:
    ro = read_only_folder.path
    partial = helpers.write_dataset(ro / "partial.h5", helpers.make_episodes([5, 6]), complete=False)
    merged = helpers.write_dataset(ro / "merged.h5", helpers.make_episodes([4]))
    (ro / "run").mkdir()
    a = helpers.write_dataset(ro.parent / "a.h5", helpers.make_episodes([5]))
    b = helpers.write_dataset(ro.parent / "b.h5", helpers.make_episodes([7]))
    dataset = toy_dataset_writer(ro.parent / "toy.h5", "toy_reach_shifted", episodes=1)
    read_only_folder.seal()
    before = helpers.folder_state(ro)
    commands = {
        "collect --out": [*COLLECT, "--episodes", "2", "--out", str(ro / "new.h5")],
        "collect --out (a folder to make)": [*COLLECT, "--episodes", "2", "--out", str(ro / "sub" / "new.h5")],
        "collect --resume": [*COLLECT, "--episodes", "4", "--out", str(partial), "--resume"],
        "collect --policy dreamerv2 --out": [*DV2_COLLECT, "--out", str(ro / "dv2.h5")],
        "train --logdir": [*TRAIN_DV2, "--dataset", str(dataset), "--logdir", str(ro / "run")],
        "dataset merge --out": ["dataset", "merge", str(a), str(b), "--out", str(ro / "m.h5")],
        "dataset merge --out --force": ["dataset", "merge", str(a), str(b), "--out", str(merged), "--force"],
        "eval --out": [*EVAL, str(untrained_run), "--out", str(ro / "eval.json")],
        "eval --video": [*EVAL, str(untrained_run), "--video", str(ro / "v.mp4")],
    }
    for name, args in commands.items():
        line = _one_error_line(processes, processes.run_cli(*args))
        assert line.startswith(f"error: cannot write to {ro}") and "choose another --" in line, (name, line)
        assert helpers.folder_state(ro) == before, name


def test_eval_prints_its_results_when_it_cannot_write_them(
    small_disk, processes: ModuleType, untrained_run: Path
) -> None:
    disk = small_disk(1 * MiB)
    disk.fill()
    out = disk.path / "eval.json"
    result = processes.run_cli(
        "eval", "--ckpt", str(untrained_run), "--episodes", "2", "--out", str(out), "--device", "cpu", **disk.popen()
    )
    line = _one_error_line(processes, result)
    assert line.startswith(f"error: cannot write the results to {out}: ") and line.endswith("printed above instead")
    summary, record = result.stdout.splitlines()
    assert summary.startswith("toy_reach_shifted: return ") and "over 2 episodes" in summary
    results = json.loads(record)
    assert len(results["returns"]) == 2 and results["task"] == "toy_reach_shifted"
    assert results["mean"] == pytest.approx(sum(results["returns"]) / 2)
    assert not out.exists() and [p.name for p in disk.path.iterdir()] in ([], ["filler"])  # no half-written file


def test_a_folder_as_dataset_file_is_refused_and_kept(processes: ModuleType, helpers: ModuleType, tmp_path: Path):
    folder = tmp_path / "data"
    helpers.write_dataset(folder / "inside.h5", helpers.make_episodes([5]))
    (tmp_path / "data.run").mkdir()  # what the dreamerv2 collector's --force would delete
    (tmp_path / "data.run" / "keep").write_text("x")
    a = helpers.write_dataset(tmp_path / "a.h5", helpers.make_episodes([5]))
    before = helpers.folder_state(tmp_path)
    for args in (
        [*COLLECT, "--episodes", "2", "--out", str(folder), "--force"],
        [*DV2_COLLECT, "--out", str(folder), "--force"],
        ["dataset", "merge", str(a), str(tmp_path / "data" / "inside.h5"), "--out", str(folder), "--force"],
    ):
        line = _one_error_line(processes, processes.run_cli(*args))
        assert f"{folder} is a folder" in line, line
        assert helpers.folder_state(tmp_path) == before


def test_an_output_in_a_place_that_takes_no_files_is_one_line(tmp_path: Path) -> None:
    """``/proc`` refuses new files with ENOENT, not a write errno: still one line naming the place and the option."""
    from coworld.storage import check_writable

    with pytest.raises(
        StorageError, match=r"^cannot write to /proc \(No such file or directory\); choose another --out$"
    ):
        check_writable("/proc", "--out")


def test_a_collection_resumed_after_a_full_disk_is_the_uninterrupted_one(
    small_disk, processes: ModuleType, helpers: ModuleType, tmp_path: Path
) -> None:
    disk = small_disk(3 * MiB)
    out, whole = disk.path / "a.h5", tmp_path / "whole.h5"
    args = [*COLLECT, "--episodes", "20", "--seed", "5", "--compression", "none"]
    _one_error_line(processes, processes.run_cli(*args, "--out", str(out), **disk.popen()))
    with open_dataset(out) as data:  # the record of the stopped collection counts the rows it holds
        assert 0 < data.num_episodes < 20 and data.metadata["collector"]["steps"] == data.num_steps
    disk.grow(64 * MiB)
    for path, resume in ((out, ["--resume"]), (whole, [])):
        result = processes.run_cli(*args, "--out", str(path), *resume, **disk.popen())
        assert result.returncode == 0, result.stderr[-3000:]
    assert helpers.episode_digests(out) == helpers.episode_digests(whole)  # frames, actions, rewards, ends
    for path in (out, whole):
        with open_dataset(path) as data:
            assert data.num_steps == 1000 and data.metadata["collector"]["steps"] == 1000


def test_the_dreamerv2_collector_resumed_after_a_full_disk_is_the_uninterrupted_one(
    small_disk, processes: ModuleType, helpers: ModuleType, tmp_path: Path
) -> None:
    """With a checkpoint at every episode's end (DV2_COLLECT), the agent's checkpoint saw every episode the stopped
    dataset holds: the resume goes on exactly, and the record's counts are those of the run never stopped."""
    disk = small_disk(3 * MiB)
    out, whole = disk.path / "b.h5", tmp_path / "whole.h5"
    (tmp_path / "agent").mkdir()
    (disk.path / "b.run").symlink_to(tmp_path / "agent")  # the agent's run folder on a disk with room: the data fails
    args = [*DV2_COLLECT, "--max-steps", "300", "--compression", "none"]
    _one_error_line(processes, processes.run_cli(*args, "--out", str(out), **disk.popen()))
    disk.grow(64 * MiB)
    for path, resume in ((out, ["--resume"]), (whole, [])):
        result = processes.run_cli(*args, "--out", str(path), *resume, **disk.popen())
        assert result.returncode == 0, result.stderr[-3000:]
    assert helpers.episode_digests(out) == helpers.episode_digests(whole)
    with open_dataset(out) as data, open_dataset(whole) as reference:
        record, expected = data.metadata["collector"], reference.metadata["collector"]
        assert record["steps"] == data.num_steps == 300 and record.pop("run") != expected.pop("run")
        assert record == expected  # steps, updates, stop reason


def test_a_full_disk_under_the_metrics_log_names_the_file(small_disk) -> None:
    """A write to an open file names no file in its OSError; the log's own says which, so the line does too."""
    from coworld.storage import os_error_text
    from coworld.training.logger import Logger

    disk = small_disk(1 * MiB)
    with pytest.raises(OSError) as err, disk.limited(), Logger(disk.path / "run", outputs=("jsonl",)) as logger:
        logger.log({"wm/loss": 1.0}, 1)
        disk.fill()
        for step in range(2, 10_000):  # past what the file object buffers; its close fails as well
            logger.log({f"wm/term_{i}": float(i) for i in range(100)}, step)
    assert err.value.filename == str(disk.path / "run" / "metrics.jsonl")
    assert os_error_text(err.value).startswith(f"cannot write {disk.path / 'run' / 'metrics.jsonl'}: ")
