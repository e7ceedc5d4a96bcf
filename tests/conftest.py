"""Fixtures shared across the test packages.

The suite runs on one torch (OpenMP) thread, in this process and in every CLI process it starts: tiny networks
gain little from a second thread, and two threads crawl when another job holds a core (benchmarks/RESULTS.md,
"Threads"). Tests about threads set their own count.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"  # before torch starts its thread pool; inherited by subprocesses
os.environ["MKL_NUM_THREADS"] = "1"

import signal  # noqa: E402

# A suite started in the background of a non-interactive shell (`bash .ci/run &`) inherits SIGINT ignored, and
# coworld, like other Unix programs, leaves an ignored signal ignored (test_a_signal_ignored_at_start_stays_ignored).
# The interrupt tests are about a terminal's Ctrl-C, so the suite takes Python's usual handler back: the commands
# it starts then begin with SIGINT at its default, as they do from a terminal.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

import contextlib  # noqa: E402
import dataclasses  # noqa: E402
import importlib.util  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from pathlib import Path  # noqa: E402
from types import ModuleType  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from coworld import envs  # noqa: E402
from coworld.data import DatasetWriter  # noqa: E402


def _load(path: Path, name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


_HELPERS = _load(Path(__file__).parent / "data" / "helpers.py", "coworld_data_test_helpers")
_PROCESSES = _load(Path(__file__).with_name("processes.py"), "coworld_test_processes")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests marked ``long`` run first: a worker that picks one up late would run it alone while the others wait."""
    items.sort(key=lambda item: item.get_closest_marker("long") is None)


@pytest.fixture(scope="session")
def helpers() -> ModuleType:
    """tests/data/helpers.py: episode makers, the step-space oracle, the fake pixel task."""
    return _HELPERS


@pytest.fixture(scope="session")
def processes() -> ModuleType:
    """tests/processes.py: run coworld as a real process, signal it, kill it."""
    return _PROCESSES


def write_toy_dataset(path: Path, task: str = "toy_reach", episodes: int = 4, seed: int = 0) -> Path:
    """Random-policy episodes of a toy task written with the real writer."""
    spec = envs.task_spec(task)
    env = envs.make(task, seed=seed)
    rng = np.random.default_rng(seed)
    with DatasetWriter(
        path,
        task=task,
        env_config=dataclasses.asdict(spec),
        quality="random",
        collector={"algorithm": "random", "seed": seed},
        action_size=spec.action_size,
    ) as writer:
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            frames, actions, rewards = [obs], [], []
            done = False
            while not done:
                action = rng.uniform(-1, 1, spec.action_size).astype(np.float32)
                obs, reward, terminated, truncated, _ = env.step(action)
                frames.append(obs)
                actions.append(action)
                rewards.append(reward)
                done = terminated or truncated
            writer.add_episode(
                observations=np.stack(frames),
                actions=np.stack(actions),
                rewards=np.asarray(rewards, np.float32),
                terminated=bool(terminated),
            )
        writer.close(complete=True)
    env.close()
    return path


@pytest.fixture(scope="session", autouse=True)
def _one_torch_thread_for_the_session() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def toy_dataset_writer():
    """The function writing random-policy toy datasets: ``(path, task, episodes, seed) -> path``."""
    return write_toy_dataset


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """One torch thread for the test, restored after: tiny networks gain little from a second one, and two crawl
    when another job holds a core (benchmarks/RESULTS.md, "Threads")."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# -- locations that refuse writes ---------------------------------------------------------------------------------
# As root (as CI runs) these are real mounts: a small tmpfs that fills up, a tmpfs remounted read-only. Otherwise the
# same refusals come from the kernel another way: a file size limit (RLIMIT_FSIZE: writes past it fail with EFBIG)
# and a folder without write permission (EACCES). Nothing is skipped.

ROOT = os.geteuid() == 0


def _mount(*args: str) -> None:
    subprocess.run(["mount", *args], check=True, capture_output=True, text=True)


def _unmount(path: Path) -> None:
    if subprocess.run(["umount", str(path)], capture_output=True).returncode != 0:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


class SmallDisk:
    """A folder with room for about ``size`` bytes: a tmpfs of that size as root, else a limit of ``file_size`` bytes
    (default ``size``) per file for the processes run with :meth:`popen` and for the code inside :meth:`limited`.
    :meth:`grow` frees space."""

    def __init__(self, path: Path, size: int, file_size: int | None = None) -> None:
        self.path, self.mounted = path, ROOT
        self.size = size if ROOT else file_size or size
        path.mkdir(parents=True)
        if self.mounted:
            _mount("-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path))

    def popen(self) -> dict[str, Any]:
        """Keyword arguments for subprocess that put the child under this disk's limit."""
        if self.mounted:
            return {}
        size = self.size
        return {"preexec_fn": lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (size, resource.RLIM_INFINITY))}

    @contextlib.contextmanager
    def limited(self) -> Iterator[None]:
        """This process under the disk's limit for the block."""
        if self.mounted:
            yield
            return
        old = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (self.size, old[1]))
        try:
            yield
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, old)

    def grow(self, size: int) -> None:
        self.size = size
        if self.mounted:
            _mount("-o", f"remount,size={size}", str(self.path))

    def fill(self) -> None:
        """Use up all the room left."""
        if not self.mounted:
            self.size = 0
            return
        with contextlib.suppress(OSError), open(self.path / "filler", "wb") as f:  # its close fails too
            while True:
                f.write(b"\0" * 65536)
                f.flush()

    def release(self) -> None:
        if self.mounted:
            _unmount(self.path)


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Callable[..., SmallDisk]]:
    """``small_disk(bytes, file_size=None)`` -> a :class:`SmallDisk` under tmp_path, released after the test."""
    disks: list[SmallDisk] = []

    def make(size: int, file_size: int | None = None) -> SmallDisk:
        disks.append(SmallDisk(tmp_path / f"disk{len(disks)}", size, file_size))
        return disks[-1]

    yield make
    for disk in disks:
        disk.release()


class ReadOnlyFolder:
    """A folder to fill, then :meth:`seal`: afterwards nothing in it can be written, created or removed."""

    def __init__(self, path: Path) -> None:
        self.path, self.sealed = path, False
        path.mkdir(parents=True)
        if ROOT:
            _mount("-t", "tmpfs", "-o", "size=64m", "tmpfs", str(path))

    def seal(self) -> None:
        if ROOT:
            _mount("-o", "remount,ro", str(self.path))
        else:
            for folder in [self.path, *(p for p in self.path.rglob("*") if p.is_dir())]:
                folder.chmod(0o555)
        self.sealed = True

    def release(self) -> None:
        if ROOT:
            _unmount(self.path)
        elif self.sealed:
            for folder in [self.path, *(p for p in self.path.rglob("*") if p.is_dir())]:
                folder.chmod(0o755)


@pytest.fixture
def read_only_folder(tmp_path: Path) -> Iterator[ReadOnlyFolder]:
    """A :class:`ReadOnlyFolder` under tmp_path, released after the test."""
    folder = ReadOnlyFolder(tmp_path / "read_only")
    yield folder
    folder.release()


@pytest.fixture(scope="session")
def untrained_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run folder holding an untrained tiny offline DreamerV2 agent for toy_reach_shifted, as `coworld eval` reads
    it (made directly: no training needed to test what eval does with its output)."""
    from coworld.agents.factory import make_agent
    from coworld.config import make_config
    from coworld.training.checkpoint import save_checkpoint
    from coworld.training.run import prepare_run_dir

    run = tmp_path_factory.mktemp("runs") / "dv2"
    config = make_config("tiny", ["device=cpu"])
    info = {"algo": "dreamerv2", "source": None, "target": "toy_reach_shifted", "dataset": "none", "preset": "tiny"}
    prepare_run_dir(run, config, info)
    agent = make_agent("dreamerv2", config=config, action_size=envs.task_spec("toy_reach_shifted").action_size,
                       device=torch.device("cpu"))  # fmt: skip
    save_checkpoint(run / "checkpoint.pt", {"kind": "dreamerv2-offline", "agent": agent.state_dict(), "updates": 0})
    return run
