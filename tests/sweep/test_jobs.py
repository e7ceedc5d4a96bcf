"""A job's commands run in order as child processes that never outlive the sweep."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import psutil
import pytest

from coworld.sweep.jobs import Job, JobProcess, execute, process_record, reap_orphan, write_json


def _job(tmp_path: Path, *steps: tuple[str, ...], finish: tuple[Path, Path] | None = None) -> Job:
    return Job(
        name="job",
        kind="run",
        steps=steps,
        log=tmp_path / "logs" / "job.log",
        pid_file=tmp_path / "logs" / "job.pid",
        finish=finish,
    )


def test_commands_run_in_order_and_the_result_appears_whole(tmp_path):
    written, final = tmp_path / "tasks.txt.partial", tmp_path / "tasks.txt"
    job = _job(tmp_path, ("tasks",), ("--version",), finish=(tmp_path / "missing", final))
    result = execute(job, threads=1)
    assert result.returncode == 1  # the commands succeeded but left no result to rename
    assert not final.exists()
    log = job.log.read_text()
    assert log.index("coworld tasks") < log.index("toy_reach_shifted") < log.index("coworld --version")
    assert "wrote no" in log and not job.pid_file.exists()

    written.write_text("ok")
    result = execute(_job(tmp_path, ("--version",), finish=(written, final)), threads=1)
    assert result.returncode == 0 and final.read_text() == "ok" and not written.exists()
    assert result.cpu_s > 0
    assert job.log.read_text().count(": start on") == 2  # attempts append to the same log


def test_a_failing_command_ends_the_job_and_its_error_stays_in_the_log(tmp_path):
    job = _job(tmp_path, ("train", "--target", "nowhere"), ("tasks",))
    result = execute(job, threads=1)
    assert result.returncode == 2
    log = job.log.read_text()
    assert "error: unknown task 'nowhere'" in log and "coworld tasks" not in log
    assert "FAILED (exit code 2)" in log


def test_a_job_is_not_started_when_the_job_it_needs_failed(tmp_path):
    from coworld.sweep.jobs import JobResult

    job = _job(tmp_path, ("tasks",))
    result = execute(job, threads=1, needed=JobResult("collect-x", 2, 1.0, 1.0))
    assert result.returncode == 2 and "not started: collect-x failed" in job.log.read_text()


def test_stop_ends_the_running_command_and_its_process_group(tmp_path, process_gone):
    # a command that runs for a minute: collecting far more random episodes than the test waits for
    job = _job(tmp_path, ("collect", "--task", "toy_reach", "--policy", "random", "--episodes", "100000", "--out",
                          str(tmp_path / "big.h5"), "--quiet"))  # fmt: skip
    process = JobProcess(job, threads=1)
    record = json.loads(job.pid_file.read_text())
    assert os.getpgid(record["pid"]) == record["pid"]  # the command leads its own process group
    assert os.getsid(record["pid"]) == os.getsid(0)  # in the sweep's session, so the sweep's nice holds for it
    time.sleep(1.0)
    assert process.poll() is None
    process.stop(grace=5.0)
    assert process.result is not None and process.result.returncode != 0
    assert "stopped by the sweep" in job.log.read_text()
    assert process_gone(record["pid"]) and not job.pid_file.exists()


PARENT = textwrap.dedent(
    """
    import sys, time
    from coworld.sweep.jobs import spawn
    with open(sys.argv[1], "ab") as log:
        code = "from coworld.sweep.child import die_with_parent; die_with_parent(); import time; time.sleep(120)"
        child = spawn([sys.executable, "-c", code], log, 1)
    print(child.pid, flush=True)
    time.sleep(120)
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_child_dies_with_a_parent_killed_by_sigkill(tmp_path, process_gone):
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, str(tmp_path / "log")], stdout=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        child = int(parent.stdout.readline())  # type: ignore[union-attr]
        assert psutil.Process(child).is_running()
        os.kill(parent.pid, signal.SIGKILL)  # the parent only: its child is in another process group
        parent.wait()
        assert process_gone(child), "the child outlived its killed parent"
    finally:
        parent.kill()
        parent.wait()


def test_reap_orphan_kills_a_recorded_live_process_and_nothing_else(tmp_path, process_gone):
    orphan = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True)
    try:
        pid_file = tmp_path / "run.pid"
        write_json(pid_file, process_record(orphan.pid))
        record = json.loads(pid_file.read_text())
        stale = tmp_path / "stale.pid"  # the same PID started at another time: a reused PID, not ours to kill
        write_json(stale, {**record, "started": record["started"] - 100})
        assert not reap_orphan(stale) and orphan.poll() is None and not stale.exists()
        assert reap_orphan(pid_file)
        assert process_gone(orphan.pid) and not pid_file.exists()
    finally:
        orphan.kill()
        orphan.wait()
