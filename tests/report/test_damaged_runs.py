"""``coworld report`` of damaged run folders, as a real process: what cannot be read is skipped with one line per
file, everything else is written; an output it cannot write is named as given, with what to do."""

from __future__ import annotations

import csv
import errno
import io
import json
import os
from pathlib import Path

import pytest


def run_folder(root: Path, name: str, *, returns: list[float] | None = None, seed: int = 0) -> Path:
    run = root / name
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"algo": "dreamerv2", "target": "toy_reach_shifted"}))
    (run / "config.json").write_text(json.dumps({"seed": seed}))
    (run / "metrics.jsonl").write_text(json.dumps({"step": 10, "eval/return": 5.0, "time": 1.0}) + "\n")
    if returns is not None:
        (run / "eval.json").write_text(json.dumps({"returns": returns, "std": 0.0}))
    return run


DAMAGE = {  # case: (file, content, what the line says)
    "metrics.jsonl": ("metrics.jsonl", b'{"step": 1}\n\xff\xfe not utf-8\n', "not UTF-8 text"),
    "config.json": ("config.json", b'["valid JSON", "of the wrong shape"]', "holds a JSON list, not an object"),
    "config.json without a seed": ("config.json", b"{}", "its seed is None, not a whole number"),
    "eval.json": ("eval.json", b'{"returns": "many"', "not JSON"),
    "sweep-run.json": ("sweep-run.json", b"\xff\xff", "not JSON"),
}


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_a_damaged_file_is_skipped_with_one_line_and_the_rest_is_reported(tmp_path, processes, case):
    pytest.importorskip("matplotlib")
    pytest.importorskip("scipy")
    good = run_folder(tmp_path, "good", returns=[10.0, 20.0])
    bad = run_folder(tmp_path, "bad", returns=[1.0], seed=1)
    name, content, reason = DAMAGE[case]
    (bad / name).write_bytes(content)
    done = processes.run_cli("report", str(tmp_path), timeout=120)
    assert done.returncode == 0, done.stderr
    warnings = [line for line in done.stderr.splitlines() if line.strip()]
    assert warnings == [f"warning: skipped {bad / name}: " + warnings[0].split(": ", 2)[2]], done.stderr
    assert reason in warnings[0] and "Traceback" not in done.stderr
    rows = {row["run_dir"]: row for row in csv.DictReader(io.StringIO((tmp_path / "results.csv").read_text()))}
    assert rows[good.name]["final_return"] == "15.0"  # the good run is whole
    if name == "config.json":  # which seed the run is, is unknown: it is left out, and the line says so
        assert set(rows) == {good.name} and "the run is left out" in warnings[0]
    else:
        assert set(rows) == {good.name, bad.name}
    assert f"- bad/{name}:" in (tmp_path / "report.md").read_text()


CHOICES = {
    "not JSON": b"{",
    "no candidates": json.dumps(
        {"candidates": [], "distances": {}, "chosen": "toy_reach", "align_on": "latent", "batches": 8}
    ).encode(),  # fmt: skip
}


@pytest.mark.parametrize("damage", sorted(CHOICES))
def test_a_damaged_source_choice_is_skipped_with_a_line_that_names_no_option_of_another_command(tmp_path, processes,
                                                                                                damage):  # fmt: skip
    pytest.importorskip("matplotlib")
    pytest.importorskip("scipy")
    run = run_folder(tmp_path, "run", returns=[1.0])
    (run / "run.json").write_text(json.dumps({"algo": "coworld", "source": "toy_reach,toy_reach_centre",
                                              "target": "toy_reach_shifted"}))  # fmt: skip
    (run / "source_choice.json").write_bytes(CHOICES[damage])
    done = processes.run_cli("report", str(tmp_path), timeout=120)
    assert done.returncode == 0, done.stderr
    line = processes.last_word(done.stderr, "warning: ")
    assert line.startswith(f"warning: skipped {run / 'source_choice.json'} is damaged"), line
    assert "--" not in line and "source choice out" in line  # report has no --force, no --logdir


def test_an_unreadable_eval_json_is_named_not_called_never_evaluated(tmp_path, processes):
    pytest.importorskip("matplotlib")
    pytest.importorskip("scipy")
    bad = run_folder(tmp_path, "bad")
    (bad / "eval.json").write_text('{"returns": []}')
    done = processes.run_cli("report", str(tmp_path), timeout=120)
    assert done.returncode == 0 and f"warning: skipped {bad / 'eval.json'}: not an evaluation record" in done.stderr


def test_a_read_only_sweep_folder_is_refused_before_any_work_naming_the_users_path(processes, helpers,
                                                                                   read_only_folder):  # fmt: skip
    pytest.importorskip("matplotlib")
    pytest.importorskip("scipy")
    ro = read_only_folder.path
    run_folder(ro, "good", returns=[1.0])
    read_only_folder.seal()
    before = helpers.folder_state(ro)
    done = processes.run_cli("report", str(ro), timeout=120)  # the report goes into the folder itself by default
    line = processes.last_word(done.stderr, "error: ")
    assert done.returncode == 2 and line.startswith(f"error: cannot write to {ro}") and "choose another --out" in line
    assert ".tmp" not in line and helpers.folder_state(ro) == before


def test_a_refused_atomic_write_names_the_file_asked_for_and_what_to_do(tmp_path, monkeypatch):
    from coworld import storage

    real = Path.write_text

    def refuse(self, *args, **kwargs):
        if self.name.endswith(".tmp"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", refuse)
    with pytest.raises(OSError) as info:
        storage.write_text_atomically(tmp_path / "results.csv", "x")
    text = storage.os_error_text(info.value)
    assert text == f"cannot write {tmp_path / 'results.csv'}: Read-only file system; make it writable or choose" \
        " another location, then rerun"  # fmt: skip
    assert list(tmp_path.iterdir()) == []
