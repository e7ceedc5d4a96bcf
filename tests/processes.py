"""Helpers of the tests that run coworld as a real process: start it, wait for it, signal or kill it.

Loaded by path (``conftest.py`` exposes it as the ``processes`` fixture), since tests are no package.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

CLI = [sys.executable, "-c", "from coworld.cli import run; run()"]
PROGRESS_LINE = re.compile(r"\[(\d+:)?\d+:\d+<")
"""What a plain progress line holds (``[elapsed<remaining``; see coworld/training/progress.py)."""
DATA_HELPERS = str(Path(__file__).parent / "data" / "helpers.py")

# argv: data/helpers.py, then the `coworld` arguments. The fake pixel task (slowed down) serves collect, and the
# count of committed episodes is printed after each one.
COLLECT_SCRIPT = """
import importlib.util, sys
spec = importlib.util.spec_from_file_location("helpers", sys.argv[1])
helpers = importlib.util.module_from_spec(spec)
spec.loader.exec_module(helpers)
helpers.patch_envs(setattr, delay=0.01)
from coworld.data import DatasetWriter
add_episode = DatasetWriter.add_episode
def add_and_report(self, *args, **kwargs):
    add_episode(self, *args, **kwargs)
    print(self.num_episodes, flush=True)
DatasetWriter.add_episode = add_and_report
from coworld.cli import main
main(sys.argv[2:])
"""


def last_word(stderr: str, prefix: str) -> str:
    """The one line of ``stderr`` that starts with ``prefix`` (``error: ``, ``stopped by ``), checked to be the last
    line there, with nothing amiss before it (no traceback, no ignored exception, no warning); progress and metric
    lines before it are fine."""
    lines = [line for line in stderr.splitlines() if line.strip() and not PROGRESS_LINE.search(line)]
    found = [line for line in lines if line.startswith(prefix)]
    assert len(found) == 1 and lines[-1] == found[0], stderr[-3000:]
    for amiss in ("Traceback", "Exception ignored", "Error", "WARN", "warn("):
        assert amiss not in stderr, stderr[-3000:]
    return found[0]


def start_cli(*args: str, **popen: Any) -> subprocess.Popen[str]:
    """``coworld ARGS`` in its own session (so a signal can go to its whole process group, as a terminal's does)."""
    return subprocess.Popen(
        [*CLI, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True, **popen
    )


def start_script(script: str, *args: str) -> subprocess.Popen[str]:
    """``python -c SCRIPT data/helpers.py ARGS`` (the scripts load the data helpers from their first argument)."""
    return subprocess.Popen(
        [sys.executable, "-c", script, DATA_HELPERS, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def run_cli(*args: str, timeout: float = 600, **popen: Any) -> subprocess.CompletedProcess[str]:
    """Run ``coworld ARGS`` to the end and return what it printed (whatever its exit code)."""
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout, **popen)


def wait_for_episodes(proc: subprocess.Popen[str], count: int, timeout: float = 60.0) -> int:
    """Read the episode counts a child prints, one a line, until it reports ``count``; return the last one."""
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"child exited early: {proc.stderr.read() if proc.stderr else ''}")
        if int(line) >= count:
            return int(line)
    raise AssertionError("child too slow")


def wait_for(
    condition: Any, proc: subprocess.Popen[str], timeout: float = 300.0, what: str = "", or_end: bool = False
) -> bool:
    """Poll ``condition()`` until it holds (True). A process that ends first fails the test, or with ``or_end`` returns
    False once it ended with exit code 0."""
    deadline = time.monotonic() + timeout
    while not condition():
        if proc.poll() is not None:
            out, err = proc.communicate()
            if or_end and proc.returncode == 0:
                return False
            raise AssertionError(f"the process ended (exit {proc.returncode}) before {what}: {err[-2000:]}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)
    return True


def kill(proc: subprocess.Popen[str]) -> None:
    """SIGKILL the process and everything in its process group (its env workers), and reap it."""
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL


@dataclass
class Stopped:
    """How a process ended after a signal."""

    returncode: int
    seconds: float
    """From the signal to the end of the process."""
    stdout: str
    stderr: str

    def message(self) -> str:
        """The one-line stop message (see :func:`last_word`)."""
        return last_word(self.stderr, "stopped by ")


def stop(proc: subprocess.Popen[str], sig: int, *, group: bool = False, timeout: float = 120.0) -> Stopped:
    """Send ``sig`` to the process (or its whole process group, like a Ctrl-C in a terminal) and wait for the end.

    A process still running after ``timeout`` seconds is killed, and the test fails.
    """
    start = time.monotonic()
    if group:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        kill(proc)
        raise AssertionError(f"still running {timeout:.0f} s after {signal.Signals(sig).name}") from None
    return Stopped(proc.returncode, time.monotonic() - start, out, err)
