"""The CLI's allocator: tcmalloc preloaded where installed, else glibc's malloc tuned to keep freed memory."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from coworld import allocator

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc and LD_PRELOAD")

PROBE = """
import sys
from coworld import allocator
if sys.argv[1] == "tuned":
    assert allocator.keep_freed_memory()
def resident():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096
block = bytearray(64 << 20)  # 64 MiB, touched
before = resident()
del block
print(before - resident())
"""

AT_EXIT = (
    "import atexit, os; from coworld import allocator; "
    "atexit.register(lambda: print(os.getpid(), allocator.tcmalloc_loaded())); "
    "from coworld.cli import run; run()"
)
"""The ``coworld`` command's entry; at exit it prints its PID and whether tcmalloc is loaded (where the entry starts
over, this code runs again in the new program, so the line comes from there)."""


def _clean_env(**extra: str) -> dict[str, str]:
    """This process's environment without any allocator choice, plus ``extra``."""
    env = {key: value for key, value in os.environ.items() if key != "LD_PRELOAD"}
    return {key: value for key, value in env.items() if not key.startswith("COWORLD_MALLOC")} | extra


def test_keep_freed_memory_keeps_a_freed_block_resident() -> None:
    def released(mode: str) -> int:
        command = [sys.executable, "-c", PROBE, mode]
        out = subprocess.run(command, capture_output=True, text=True, check=True, env=_clean_env())
        return int(out.stdout)

    assert released("default") > 32 << 20  # glibc unmaps a large freed block
    assert released("tuned") < 1 << 20  # with the settings it stays for reuse


def test_tcmalloc_is_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    """scripts/install.sh installs it (Debian's libtcmalloc-minimal4); without it the command runs slower."""
    monkeypatch.delenv(allocator.CHOICE, raising=False)
    preload = allocator.tcmalloc_preload()
    assert preload is not None and "tcmalloc" in preload["LD_PRELOAD"]


def test_the_coworld_command_runs_with_tcmalloc_in_the_same_process() -> None:
    process = subprocess.Popen(
        [sys.executable, "-c", AT_EXIT, "--version"], stdout=subprocess.PIPE, text=True, env=_clean_env()
    )
    out, _ = process.communicate(timeout=120)
    assert process.returncode == 0
    assert "coworld" in out  # the command ran
    pid, loaded = out.splitlines()[-1].split()
    assert int(pid) == process.pid  # started over in place: signals sent to the PID reach it
    assert loaded == "True"


def test_coworld_malloc_glibc_keeps_glibc() -> None:
    out = subprocess.run(
        [sys.executable, "-c", AT_EXIT, "--version"],
        capture_output=True,
        text=True,
        check=True,
        env=_clean_env(COWORLD_MALLOC="glibc"),
    )
    assert out.stdout.splitlines()[-1].split()[1] == "False"


def test_a_bad_coworld_malloc_is_one_line_and_exit_2() -> None:
    out = subprocess.run(
        [sys.executable, "-c", "from coworld.cli import run; run()", "--version"],
        capture_output=True,
        text=True,
        env=_clean_env(COWORLD_MALLOC="jemalloc"),
    )
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == ["error: COWORLD_MALLOC='jemalloc': use tcmalloc or glibc"]


def test_keep_freed_memory_is_a_no_op_under_tcmalloc(monkeypatch: pytest.MonkeyPatch) -> None:
    code = "from coworld import allocator; print(allocator.tcmalloc_loaded(), allocator.keep_freed_memory())"
    monkeypatch.delenv(allocator.CHOICE, raising=False)
    preload = allocator.tcmalloc_preload()
    assert preload is not None
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=_clean_env(**preload)
    )
    assert out.stdout.split() == ["True", "False"]


def test_ctrl_c_while_the_command_starts_again_under_tcmalloc_is_the_one_stop_line() -> None:
    """exec_with_tcmalloc blocks SIGINT and SIGTERM across its exec; a Ctrl-C in that window waits, pending, for the
    command's handlers: "stopped by SIGINT" and exit code 130, not a KeyboardInterrupt traceback from the imports."""
    code = (
        "import os, signal, sys\n"
        "os.execve = lambda *a: print(sorted(signal.pthread_sigmask(signal.SIG_BLOCK, [])))\n"
        "from coworld import allocator\n"
        "allocator.exec_with_tcmalloc()\n"
    )
    env = _clean_env()
    env.pop(allocator.CHOICE, None)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert out.stdout.strip() == str(sorted([signal.SIGINT, signal.SIGTERM])), out.stderr
    # the command started again with SIGINT blocked and already pending, as after a Ctrl-C in the window
    start = (
        "import os, signal, sys\n"
        "signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})\n"
        "os.kill(os.getpid(), signal.SIGINT)\n"
        "os.execve(sys.executable, [sys.executable, '-c', 'from coworld.cli import run; run()', 'tasks'], os.environ)\n"
    )
    out = subprocess.run([sys.executable, "-c", start], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 130 and out.stderr.strip() == "stopped by SIGINT", out.stderr


def test_an_empty_coworld_malloc_is_the_default() -> None:
    out = subprocess.run(
        [sys.executable, "-c", "from coworld.cli import run; run()", "--help"],
        capture_output=True,
        text=True,
        env=_clean_env(COWORLD_MALLOC=""),
    )
    assert out.returncode == 0 and "Usage" in out.stdout, out.stderr
