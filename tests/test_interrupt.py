"""Ctrl-C and SIGTERM: every long command stops within seconds at a safe point, prints one line (what was kept, how
to resume) and exits 130 / 143; rerunning (with --resume for collect) finishes exactly what was asked.

Signals are sent at seeded random moments, to the process (``kill PID``) or to its whole process group (a Ctrl-C in a
terminal, which also reaches the env worker processes).
"""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path
from types import ModuleType

import numpy as np
import psutil
import pytest

from coworld import interrupt
from coworld.data import open_dataset, verify_dataset
from coworld.errors import DatasetError
from coworld.training.checkpoint import load_checkpoint

STOP_SECONDS = 10.0
"""Signal to exit, on a busy 2-core machine (idle: 0.2-3.5 s, most of it the interpreter's own exit)."""

COLLECT = "collect --task toy_reach --policy random --workers 2 --quiet".split()
TRAIN_DV2 = (
    "train --algo dreamerv2 --target toy_reach_shifted --preset tiny --no-progress --device cpu --threads 1"
    " --set offline.updates=20 --set offline.checkpoint_every=2 --set offline.eval_every=1000"
    " --set offline.eval_episodes=1"
).split()
CURL = (
    "train --algo {algo} --target toy_reach_shifted --preset tiny --no-progress --device cpu --threads 1"
    " --set curl.updates=300 --set curl.eval_every=1000 --set curl.checkpoint_every=20 --set curl.eval_episodes=1"
)
DV2_COLLECT = (
    "collect --task toy_reach --preset tiny --quiet --device cpu --threads 1 --set train.prefill=100"
    " --set train.eval_every=100000 --set train.checkpoint_every=50"
).split()
TRAIN_COWORLD = (
    "train --source toy_reach --target toy_reach_shifted --preset tiny --no-progress --device cpu --threads 1"
    " --set train.prefill=100 --set train.eval_episodes=1 --set coworld.pretrain_steps=300 --set coworld.iterations=2"
    " --set coworld.target_updates=25 --set coworld.source_updates=25"
).split()


def _line(stopped, signum: int) -> str:
    """The one line a stopped command printed, after checking its exit code and how fast it stopped."""
    assert stopped.returncode == 128 + signum, stopped.stderr[-3000:]
    assert stopped.seconds < STOP_SECONDS, stopped.seconds
    return stopped.message()


def _send(signum: int) -> None:
    os.kill(os.getpid(), signum)
    time.sleep(0.05)  # Python runs the handler between two bytecodes of the main thread


# -- the mechanism, in this process --------------------------------------------------------------------------------


def test_inside_safe_points_a_signal_waits_for_the_next_check() -> None:
    previous = signal.getsignal(signal.SIGINT)
    with interrupt.handling_signals(), interrupt.safe_points():
        interrupt.check()  # nothing asked yet
        _send(signal.SIGINT)
        assert interrupt.requested()
        with pytest.raises(interrupt.Interrupted) as stop:
            interrupt.check()
    assert stop.value.exit_code == 130 and str(stop.value) == "stopped by SIGINT"
    assert signal.getsignal(signal.SIGINT) is previous  # handlers restored
    assert not interrupt.requested()


def test_outside_safe_points_a_signal_stops_at_once() -> None:
    with interrupt.handling_signals(), pytest.raises(interrupt.Interrupted) as stop:
        _send(signal.SIGTERM)
    assert stop.value.exit_code == 143


def test_a_stop_that_meets_no_check_interrupts_the_main_thread_after_the_grace_period() -> None:
    with interrupt.handling_signals(), interrupt.safe_points():
        start = time.monotonic()
        with pytest.raises(interrupt.Interrupted):
            _send(signal.SIGINT)
            time.sleep(30)  # a blocking call that never reaches a check
        waited = time.monotonic() - start
    assert interrupt.GRACE_SECONDS <= waited < interrupt.GRACE_SECONDS + 2


def test_no_warning_is_shown_once_a_stop_is_asked_even_after_a_block_restored_the_filters() -> None:
    """torch.compile traces the backward pass in anomaly mode and inside many ``warnings.catch_warnings`` blocks, which
    put the filters back as they found them: a stop asked inside one, delivered in backward later, made PyTorch print
    the forward call's stack ("Error detected in AddmmBackward0") before the stop's line."""
    import warnings

    import torch

    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        with interrupt.handling_signals(), interrupt.safe_points():
            with warnings.catch_warnings():  # the stop is asked inside a block that restores the filters at its end
                _send(signal.SIGINT)
            x = torch.ones(2, 2, requires_grad=True)
            with pytest.raises(interrupt.Interrupted), torch.autograd.detect_anomaly(check_nan=False):
                y = torch.addmm(x, x, x)
                y.register_hook(lambda grad: interrupt.check())  # the stop, delivered inside backward
                y.sum().backward()
            warnings.warn("cleanup noise", stacklevel=1)
        warnings.warn("after the command", stacklevel=1)  # warnings are shown again once signals are not handled
    assert [str(w.message) for w in shown] == ["after the command"]


def test_a_stop_raised_inside_a_weakref_callback_is_delivered_again() -> None:
    """torch.compile runs many weakref callbacks; a stop raised inside one is ignored by Python ("Exception ignored"),
    so it must come again rather than wait for the next check (which compilation may not reach for a minute)."""
    import weakref

    class Graph:
        pass

    def busy(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pass

    def callback(ref: object) -> None:
        busy(0.3)  # the grace period's delivery lands here, where an exception cannot propagate

    with interrupt.handling_signals(), interrupt.safe_points():
        start = time.monotonic()
        with pytest.raises(interrupt.Interrupted):
            _send(signal.SIGINT)
            while time.monotonic() - start < 30:  # "compiling": no check, half the time inside weakref callbacks
                graph = Graph()
                _ref = weakref.ref(graph, callback)
                del graph
                busy(0.3)
        waited = time.monotonic() - start
    assert waited < interrupt.GRACE_SECONDS + 5, waited


@pytest.mark.slow
def test_a_signal_while_torch_compiles_stops_the_run_within_the_bound(
    tmp_path: Path, processes: ModuleType, toy_dataset_writer
) -> None:
    dataset = toy_dataset_writer(tmp_path / "toy.h5", "toy_reach_shifted")
    run = tmp_path / "run"
    proc = processes.start_cli(*TRAIN_DV2, "--dataset", str(dataset), "--logdir", str(run), "--set", "compile=true")
    processes.wait_for((run / "config.json").exists, proc, what="the run folder")
    time.sleep(8)  # inside the first update's compilation (minutes on a CPU)
    line = _line(processes.stop(proc, signal.SIGINT, group=True), signal.SIGINT)
    assert line.startswith("stopped by SIGINT: ")


def test_a_second_signal_stops_at_once_and_a_third_is_not_caught() -> None:
    with interrupt.handling_signals(), interrupt.safe_points():
        _send(signal.SIGINT)
        with pytest.raises(interrupt.Interrupted):
            _send(signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_DFL


def test_a_signal_ignored_at_start_stays_ignored() -> None:
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with interrupt.handling_signals():
            assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
            _send(signal.SIGTERM)
            assert not interrupt.requested()
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_explain_says_what_was_kept_and_errors_after_a_stop_belong_to_it() -> None:
    with interrupt.handling_signals(), interrupt.safe_points():
        with pytest.raises(EOFError), interrupt.explain(lambda: "kept 3"):
            raise EOFError("no stop asked: an error stays an error")
        _send(signal.SIGINT)
        with pytest.raises(interrupt.Interrupted, match="^stopped by SIGINT: kept 3; rerun$"):
            with interrupt.explain(lambda: "kept 3; rerun"):
                raise EOFError("a worker killed by the same signal")
        with pytest.raises(DatasetError), interrupt.explain(lambda: "kept 3"):
            raise DatasetError("a problem a person can act on is reported as itself")


# -- the commands, as real processes -----------------------------------------------------------------------------


@pytest.mark.parametrize(("signum", "group"), [(signal.SIGINT, True), (signal.SIGTERM, False)], ids=["ctrl-c", "term"])
def test_collect_stops_keeps_whole_episodes_and_resumes(
    signum: int, group: bool, tmp_path: Path, processes: ModuleType, helpers: ModuleType
) -> None:
    out = tmp_path / "a.h5"
    proc = processes.start_cli(*COLLECT, "--episodes", "100000", "--out", str(out))
    processes.wait_for(lambda: helpers.committed_episodes(out) >= 1, proc, what="the first episode")
    time.sleep(np.random.default_rng(signum).uniform(0.0, 1.5))
    line = _line(processes.stop(proc, signum, group=group), signum)
    found = re.fullmatch(
        rf"stopped by {signal.Signals(signum).name}: {out} keeps (\d+) whole episodes? \(([\d,]+) steps?\);"
        r" rerun the same command with --resume to continue",
        line,
    )
    assert found, line
    kept = int(found.group(1))
    with open_dataset(out) as data:
        assert data.num_episodes == kept and data.num_steps == int(found.group(2).replace(",", ""))
    helpers.assert_unfinished_but_sound(out)
    before = helpers.episode_digests(out)

    resumed = processes.run_cli(*COLLECT, "--episodes", str(kept + 5), "--out", str(out), "--resume")
    assert resumed.returncode == 0, resumed.stderr
    with open_dataset(out) as data:
        assert data.complete and data.num_episodes == kept + 5
    assert helpers.episode_digests(out)[:kept] == before
    assert verify_dataset(out) == []


def test_offline_training_stops_and_the_same_command_finishes(
    tmp_path: Path, processes: ModuleType, toy_dataset_writer
) -> None:
    dataset = toy_dataset_writer(tmp_path / "toy.h5", "toy_reach_shifted")
    run = tmp_path / "run"
    args = [*TRAIN_DV2, "--dataset", str(dataset), "--logdir", str(run)]
    proc = processes.start_cli(*args)
    processes.wait_for((run / "checkpoint.pt").exists, proc, what="the first checkpoint")
    time.sleep(np.random.default_rng(1).uniform(0.0, 1.0))
    line = _line(processes.stop(proc, signal.SIGINT, group=True), signal.SIGINT)
    found = re.fullmatch(
        rf"stopped by SIGINT: {run} keeps its checkpoint at update (\d+); rerun the same command to resume", line
    )
    assert found, line
    assert load_checkpoint(run / "checkpoint.pt")["updates"] == int(found.group(1)) < 20

    done = processes.run_cli(*args)
    assert done.returncode == 0 and "resuming from" in done.stdout, done.stderr[-3000:]
    assert load_checkpoint(run / "checkpoint.pt")["updates"] == 20  # 10 iterations x 2 target updates


def test_eval_stops_and_writes_nothing(tmp_path: Path, processes: ModuleType, untrained_run: Path) -> None:
    out = tmp_path / "eval.json"
    proc = processes.start_cli(
        "eval", "--ckpt", str(untrained_run), "--episodes", "1000", "--workers", "2", "--out", str(out)
    )
    processes.wait_for(lambda: len(psutil.Process(proc.pid).children()) >= 2, proc, what="the env workers")
    time.sleep(np.random.default_rng(2).uniform(0.0, 2.0))
    line = _line(processes.stop(proc, signal.SIGINT, group=True), signal.SIGINT)
    assert line == "stopped by SIGINT: no results were written (an evaluation does not resume); rerun the same command"
    assert not out.exists()


def test_merge_stops_and_leaves_out_as_it_was(tmp_path: Path, processes: ModuleType, helpers: ModuleType) -> None:
    episodes = helpers.make_episodes([60] * 240)
    a = helpers.write_dataset(tmp_path / "a.h5", episodes[:120], compression="none")
    b = helpers.write_dataset(tmp_path / "b.h5", episodes[120:], compression="none")
    out = helpers.write_dataset(tmp_path / "m.h5", episodes[:3])
    before = helpers.folder_state(tmp_path)
    args = ["dataset", "merge", str(a), str(b), "--out", str(out), "--force"]
    proc = processes.start_cli(*args)
    processes.wait_for(tmp_path.joinpath("m.h5.merging").exists, proc, what="the merge to start")
    time.sleep(np.random.default_rng(3).uniform(0.0, 0.5))
    line = _line(processes.stop(proc, signal.SIGINT), signal.SIGINT)
    assert line == f"stopped by SIGINT: {out} is as it was; run the merge again"
    assert helpers.folder_state(tmp_path) == before  # no half merge, no lock file

    done = processes.run_cli(*args)
    assert done.returncode == 0, done.stderr
    assert helpers.assert_whole_prefix(out, episodes) == 240 and verify_dataset(out) == []


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["curl", "curl-cql"])
def test_model_free_training_stops_and_the_same_command_finishes(
    algo: str, tmp_path: Path, processes: ModuleType, toy_dataset_writer
) -> None:
    dataset = toy_dataset_writer(tmp_path / "toy.h5", "toy_reach_shifted")
    run = tmp_path / "run"
    args = [*CURL.format(algo=algo).split(), "--dataset", str(dataset), "--logdir", str(run)]
    proc = processes.start_cli(*args)
    processes.wait_for((run / "checkpoint.pt").exists, proc, what="the first checkpoint")
    time.sleep(np.random.default_rng(4).uniform(0.0, 1.0))
    line = _line(processes.stop(proc, signal.SIGTERM), signal.SIGTERM)
    kept = rf"stopped by SIGTERM: {run} keeps its checkpoint at update \d+; rerun the same command to resume"
    assert re.fullmatch(kept, line), line
    done = processes.run_cli(*args)
    assert done.returncode == 0, done.stderr[-3000:]
    assert load_checkpoint(run / "checkpoint.pt")["updates"] == 300


@pytest.mark.slow
@pytest.mark.parametrize("phase", ["pretrain", "target", "source"])
def test_coworld_stops_in_each_phase_and_the_same_command_finishes(
    phase: str, tmp_path: Path, processes: ModuleType, toy_dataset_writer
) -> None:
    dataset = toy_dataset_writer(tmp_path / "toy.h5", "toy_reach_shifted")
    run = tmp_path / "run"
    args = [*TRAIN_COWORLD, "--dataset", str(dataset), "--logdir", str(run)]

    def in_phase() -> bool:
        if phase == "pretrain":
            return (run / "source_replay.h5").exists()
        if not (run / "checkpoint.pt").exists():
            return False
        try:
            return load_checkpoint(run / "checkpoint.pt")["progress"]["phase"] == phase
        except Exception:  # being replaced right now
            return False

    proc = processes.start_cli(*args)
    processes.wait_for(in_phase, proc, what=f"the {phase} phase")
    time.sleep(np.random.default_rng(5).uniform(0.0, 0.5))
    line = _line(processes.stop(proc, signal.SIGINT, group=True), signal.SIGINT)
    assert line.startswith(f"stopped by SIGINT: {run} ") and line.endswith("; rerun the same command to resume")
    if phase != "pretrain":
        assert f"keeps its checkpoint from iteration 0, {phase} phase" in line

    done = processes.run_cli(*args)
    assert done.returncode == 0, done.stderr[-3000:]
    final = load_checkpoint(run / "checkpoint.pt")
    assert final["progress"]["iteration"] == 2 and final["agent"]["updates"] == 50  # exactly 2 x K1


@pytest.mark.parametrize(
    "background",
    [pytest.param(False, marks=pytest.mark.slow), True],  # in CI: stopped while an update runs beside acting
    ids=["in-turn", "beside"],
)
def test_the_dreamerv2_collector_stops_and_resumes(
    tmp_path: Path, processes: ModuleType, helpers: ModuleType, background: bool
) -> None:
    out = tmp_path / "d.h5"
    args = [*DV2_COLLECT, "--set", f"train.background_updates={str(background).lower()}"]
    args += ["--max-steps", "600", "--out", str(out)]
    proc = processes.start_cli(*args)
    checkpoint = tmp_path / "d.run" / "checkpoint.pt"
    processes.wait_for(checkpoint.exists, proc, what="the first checkpoint")
    time.sleep(np.random.default_rng(6).uniform(0.0, 1.0))
    line = _line(processes.stop(proc, signal.SIGTERM), signal.SIGTERM)
    assert re.fullmatch(
        rf"stopped by SIGTERM: {out} keeps \d+ whole episodes? \([\d,]+ steps?\); the agent's last checkpoint is in"
        rf" {tmp_path / 'd.run'}; rerun the same command with --resume to continue",
        line,
    ), line
    helpers.assert_unfinished_but_sound(out)
    before = helpers.episode_digests(out)
    done = processes.run_cli(*args, "--resume")
    assert done.returncode == 0, done.stderr[-3000:]
    with open_dataset(out) as data:
        assert data.complete and data.num_steps == 600
    assert helpers.episode_digests(out)[: len(before)] == before
