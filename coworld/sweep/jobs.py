"""A sweep's jobs and how one job runs: its ``coworld`` commands one after another, each a child process.

A job is a dataset collection or a run (train, then eval). Its commands are plain ``coworld`` command lines, run
with this interpreter in child processes, so a crash of one run never takes the sweep down and each child has its
own torch threads. Every child:

* appends its output to the job's log file (kept, failed or not), after a header naming the command;
* is recorded in the job's pid file (host, PID, start time) while it runs, so a later sweep can recognise it;
* leads its own process group (the sweep stops a job by signalling the whole group), and on Linux is killed by
  the kernel the moment the process that started it dies (``PR_SET_PDEATHSIG``, set by the child itself first
  thing, :mod:`coworld.sweep.child`), so a sweep killed with ``kill -9`` leaves no child behind to race the
  rerun. The signal follows the thread that started the child: the sweep starts children from its main thread,
  a Ray task from the thread that waits for them.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import psutil

from coworld.data.lock import holder_alive, process_record
from coworld.storage import write_text_atomically
from coworld.sweep.child import PARENT_ENV

CLI = ("-c", "from coworld.sweep.child import die_with_parent; die_with_parent(); from coworld.cli import main; main()")
"""How a child runs the ``coworld`` command line with the sweep's interpreter (dying with the sweep)."""


@dataclass(frozen=True)
class Job:
    """Commands run one after another; the job succeeds when all exit with 0."""

    name: str
    kind: str
    """'collect' or 'run'."""
    steps: tuple[tuple[str, ...], ...]
    """``coworld`` arguments of each command, e.g. ``("train", "--algo", "curl", ...)``."""
    log: Path
    pid_file: Path
    finish: tuple[Path, Path] | None = None
    """(written, final): renamed once every command succeeded (the eval result appears whole or not at all)."""
    needs: str | None = None
    """Name of the job that must succeed first (a run's dataset)."""
    run_dir: Path | None = None
    algo: str = ""
    """A run's algorithm (how its metrics are read)."""
    shares: tuple[str, ...] = ()
    """The runs whose source pretraining is this CoWorld run's (see :func:`coworld.sweep.runner.plan`)."""


@dataclass(frozen=True)
class JobResult:
    name: str
    returncode: int
    """0 on success; the failing command's exit code otherwise (negative: killed by that signal)."""
    wall_s: float
    cpu_s: float
    """CPU seconds (user + system) of the job's commands and their own children."""


def spawn(argv: list[str], log: IO[bytes], threads: int) -> subprocess.Popen:
    """Start ``argv``: its own process group, output to ``log``.

    The group stays in this process's session: Linux's scheduler shares the CPU between sessions first
    (autogroups), so a command in a session of its own would run at full share whatever ``nice`` the sweep runs at.

    The child learns this process's PID (:data:`~coworld.sweep.child.PARENT_ENV`); a child that calls
    :func:`~coworld.sweep.child.die_with_parent` first (every ``coworld`` command of a job does) is killed when the
    thread calling this function ends, so call it from a thread that waits for the child.
    """
    env = {**os.environ, PARENT_ENV: str(os.getpid()), "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    return subprocess.Popen(
        argv,
        stdin=subprocess.DEVNULL,
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
        process_group=0,
    )


def write_json(path: Path, data: Any) -> None:
    """Write JSON whole: to a temporary file in the same folder, then renamed."""
    write_text_atomically(path, json.dumps(data, indent=2) + "\n")


class JobProcess:
    """Runs one job without blocking: :meth:`poll` advances it, :meth:`stop` ends it.

    Args:
        job: what to run.
        threads: torch threads of each command (also ``OMP_NUM_THREADS``).
    """

    def __init__(self, job: Job, threads: int) -> None:
        self.job = job
        self.threads = threads
        self._step = -1
        self._proc: subprocess.Popen | None = None
        self._log: IO[bytes] | None = None
        self._start = time.time()
        self._step_start = self._start
        self._cpu = 0.0
        self.result: JobResult | None = None
        self._stopping = False
        self._stop_deadline: float | None = None
        job.log.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(job.log, "ab")
        self._write(f"==== {time.strftime('%Y-%m-%d %H:%M:%S')} {job.name}: start on {socket.gethostname()}\n")
        self._next()

    def _write(self, text: str) -> None:
        assert self._log is not None
        self._log.write(text.encode())
        self._log.flush()

    def _next(self) -> None:
        self._step += 1
        if self._step == len(self.job.steps):
            if self.job.finish is not None:
                written, final = self.job.finish
                if not written.exists():
                    self._write(f"==== the commands succeeded but wrote no {written}\n")
                    self._end(1)
                    return
                os.replace(written, final)
            self._end(0)
            return
        args = self.job.steps[self._step]
        self._write(f"==== {time.strftime('%H:%M:%S')} coworld {' '.join(args)}\n")
        assert self._log is not None
        self._step_start = time.time()
        self._proc = spawn([sys.executable, *CLI, *args], self._log, self.threads)
        write_json(self.job.pid_file, process_record(self._proc.pid))

    def poll(self) -> JobResult | None:
        """Advance the job; its result once it has ended."""
        if self.result is not None or self._proc is None:
            return self.result
        pid, status, usage = os.wait4(self._proc.pid, os.WNOHANG)
        if pid == 0:
            return None
        code = os.waitstatus_to_exitcode(status)
        self._proc.returncode = code  # reaped here (wait4 gives its CPU time); Popen must not wait again
        cpu = usage.ru_utime + usage.ru_stime
        self._cpu += cpu
        self._write(f"==== exit code {code} after {time.time() - self._step_start:.1f} s ({cpu:.1f} CPU s)\n")
        self._proc = None
        if code != 0:
            self._end(code)
        else:
            self._next()
        return self.result

    def wait(self, interval: float = 0.5) -> JobResult:
        """Block until the job ends."""
        while (result := self.poll()) is None:
            time.sleep(interval)
        return result

    def stop(self, grace: float = 5.0, wait: bool = True) -> None:
        """End the job now: SIGTERM to the running command's process group, SIGKILL after ``grace`` seconds.

        ``wait=False`` only sends the SIGTERM (once): stopping several jobs, signal them all, then wait for each.
        """
        if self._proc is None:
            return
        pgid = self._proc.pid
        if self._stop_deadline is None:
            self._stopping = True
            self._stop_deadline = time.time() + grace
            _signal_group(pgid, signal.SIGTERM)
        if not wait:
            return
        deadline = self._stop_deadline
        while time.time() < deadline and self.poll() is None:
            time.sleep(0.1)
        if self.result is None:
            _signal_group(pgid, signal.SIGKILL)
            while self.poll() is None:
                time.sleep(0.05)
        _signal_group(pgid, signal.SIGKILL)  # anything the command left in its group

    def _end(self, code: int) -> None:
        self.job.pid_file.unlink(missing_ok=True)
        wall = time.time() - self._start
        status = "done" if code == 0 else f"FAILED (exit code {code})"
        if self._stopping:
            status = "stopped by the sweep"
        self._write(
            f"==== {time.strftime('%H:%M:%S')} {self.job.name}: {status} in {wall:.1f} s ({self._cpu:.1f} CPU s)\n"
        )
        assert self._log is not None
        self._log.close()
        self.result = JobResult(self.job.name, code, wall, self._cpu)


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def execute(job: Job, threads: int, needed: JobResult | None = None) -> JobResult:
    """Run ``job`` to its end in this process (what a Ray task does); skipped when the job it needs failed."""
    if needed is not None and needed.returncode != 0:
        job.log.parent.mkdir(parents=True, exist_ok=True)
        with open(job.log, "a") as log:
            log.write(f"==== {job.name}: not started: {needed.name} failed (see its log)\n")
        return JobResult(job.name, needed.returncode, 0.0, 0.0)
    return JobProcess(job, threads).wait()


def reap_orphan(pid_file: Path) -> bool:
    """Kill the process group recorded in ``pid_file`` if that process still lives on this host.

    Called only by a sweep that holds the sweep's lock, so a live recorded process is an orphan of an earlier
    sweep. Returns True when one was killed. Records of other hosts (Ray workers) are left to Ray.
    """
    try:
        record = json.loads(pid_file.read_text())
    except (OSError, ValueError):
        pid_file.unlink(missing_ok=True)
        return False
    if record.get("host") != socket.gethostname():
        return False
    killed = False
    if holder_alive(record):  # the recorded process itself, not another that reuses its PID
        try:
            process = psutil.Process(int(record["pid"]))
            _signal_group(process.pid, signal.SIGKILL)
            process.wait(timeout=10)
            killed = True
        except (psutil.NoSuchProcess, psutil.TimeoutExpired):
            pass
    pid_file.unlink(missing_ok=True)
    return killed
