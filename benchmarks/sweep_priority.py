"""CPU a sweep's run gets under ``nice``, beside other work: what ``coworld sweep``'s way of starting a run gives.

A busy child is started by :func:`coworld.sweep.jobs.spawn` (how a sweep starts each command of a run) from a
process at ``nice -n 15``, while ``--others`` busy loops run at nice 0 in this process's session; after ``--seconds``
it prints the CPU seconds the child got and whether it is in the sweep's session. Linux shares the CPU between
sessions first (autogroups, ``/proc/sys/kernel/sched_autogroup_enabled``), so a child in a session of its own runs
at full share whatever its nice; in the sweep's session it yields.

Usage: ``python benchmarks/sweep_priority.py [--seconds 10] [--others 2]``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import psutil

from coworld.sweep.jobs import spawn

BUSY = [sys.executable, "-c", "while True: pass"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--others", type=int, default=os.cpu_count() or 1, help="busy loops at nice 0")
    args = parser.parse_args()
    others = [subprocess.Popen(BUSY) for _ in range(args.others)]
    try:
        os.nice(15)  # this process plays the sweep; the loops above keep nice 0
        with tempfile.TemporaryFile() as log:
            child = spawn(BUSY, log, threads=1)
        try:
            time.sleep(args.seconds)
            cpu = psutil.Process(child.pid).cpu_times()
            same = os.getsid(child.pid) == os.getsid(0)
            print(f"child at nice 15 beside {args.others} busy loop(s) at nice 0: {cpu.user + cpu.system:.1f} CPU s"
                  f" in {args.seconds:g} s; in the sweep's session: {same}")  # fmt: skip
        finally:
            child.kill()
            child.wait()
    finally:
        for other in others:
            other.kill()
            other.wait()


if __name__ == "__main__":
    main()
