"""Fault injection: SIGKILL `collect`, `train` and `dataset merge` at seeded random moments, again and again.

After every kill, what was committed before it is intact (the dataset verifies apart from being unfinished, every
episode kept by an earlier round is unchanged, the checkpoint loads, the file a merge replaces is byte for byte the
same), and the last rerun finishes with exactly the amount asked for; a training run killed again and again ends
with the weights of the same command never killed. A few kills run in the fast suite; the longer
sweeps are marked slow.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from coworld.data import open_dataset, verify_dataset
from coworld.training.checkpoint import load_checkpoint


@pytest.mark.parametrize(
    "kills", [pytest.param(3, id="3-kills"), pytest.param(12, id="12-kills", marks=pytest.mark.slow)]
)
def test_collect_killed_at_random_moments(kills: int, tmp_path: Path, processes: ModuleType, helpers: ModuleType):
    path, wanted = tmp_path / "collect.h5", 20 + 6 * kills
    args = [*f"collect --policy random --task {helpers.FAKE_TASK} --workers 2 --quiet".split(), "--out", str(path)]
    args += ["--episodes", str(wanted)]
    rng = np.random.default_rng(kills)
    kept: list[str] = []
    for round_ in range(kills):
        proc = processes.start_script(processes.COLLECT_SCRIPT, *args, *(["--resume"] if round_ else []))
        reported = processes.wait_for_episodes(proc, len(kept) + int(rng.integers(1, 6)))
        time.sleep(float(rng.uniform(0.0, 0.1)))  # between episodes or in the middle of writing one
        processes.kill(proc)
        helpers.assert_unfinished_but_sound(path)
        digests = helpers.episode_digests(path)
        assert reported <= len(digests) < wanted and digests[: len(kept)] == kept
        kept = digests
    proc = processes.start_script(processes.COLLECT_SCRIPT, *args, "--resume")
    assert proc.wait(timeout=300) == 0, proc.stderr.read() if proc.stderr else ""
    with open_dataset(path) as data:
        assert data.complete and data.num_episodes == wanted
    assert helpers.episode_digests(path)[: len(kept)] == kept
    assert verify_dataset(path) == []


@pytest.mark.parametrize(
    "kills", [pytest.param(3, id="3-kills"), pytest.param(10, id="10-kills", marks=pytest.mark.slow)]
)
def test_merge_killed_at_random_moments(kills: int, tmp_path: Path, processes: ModuleType, helpers: ModuleType):
    episodes = helpers.make_episodes([60] * 160)
    a = helpers.write_dataset(tmp_path / "a.h5", episodes[:80], compression="none")
    b = helpers.write_dataset(tmp_path / "b.h5", episodes[80:], compression="none")
    out = helpers.write_dataset(tmp_path / "m.h5", episodes[:2])  # replaced with --force once the merge is whole
    before = helpers.file_state(out)
    merge = ["dataset", "merge", str(a), str(b)]
    args = [*merge, "--out", str(out), "--force"]
    # how long a whole merge writes here, so that every kill lands while it is writing, on a fast machine or a busy one
    trial = processes.start_cli(*merge, "--out", str(tmp_path / "trial.h5"))
    processes.wait_for(tmp_path.joinpath("trial.h5.merging").exists, trial, what="the trial merge to start")
    start = time.monotonic()
    _, err = trial.communicate(timeout=300)  # drains the pipes, which a long output could fill
    writing = time.monotonic() - start
    assert trial.returncode == 0, err
    tmp_path.joinpath("trial.h5").unlink()
    rng = np.random.default_rng(kills)
    for _ in range(kills):
        proc = processes.start_cli(*args)
        processes.wait_for(tmp_path.joinpath("m.h5.merging").exists, proc, what="the merge to start")
        time.sleep(float(rng.uniform(0.0, 0.8 * writing)))
        processes.kill(proc)
        assert helpers.file_state(out) == before
    done = processes.run_cli(*args)
    assert done.returncode == 0, done.stderr
    assert helpers.assert_whole_prefix(out, episodes) == 160 and verify_dataset(out) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5", "b.h5", "m.h5"]  # what the kills left is gone


TRAIN = (
    "train --target toy_reach_shifted --preset tiny --no-progress --device cpu --threads 1 --set train.eval_episodes=1"
).split()
CURL = "--algo curl --set curl.updates=150 --set curl.checkpoint_every=10 --set curl.eval_every=1000".split()
DRQ_BC = "--algo drq-bc --set drqbc.updates=150 --set drqbc.checkpoint_every=10 --set drqbc.eval_every=1000".split()
DREAMER_SCHEDULE = "--set offline.updates=100 --set offline.checkpoint_every=10".split()
PENALTY = ["--algo", "dreamerv2-penalty", *DREAMER_SCHEDULE, "--set", "penalty.model_updates=15"]
FINETUNE = ["--algo", "dreamerv2-finetune", "--source", "toy_reach", "--set", "train.prefill=100"]
FINETUNE += ["--set", "coworld.pretrain_steps=200", *DREAMER_SCHEDULE]
LOMPO = ["--algo", "lompo", *DREAMER_SCHEDULE, "--set", "lompo.model_updates=15"]
DREAMERV2 = ["--algo", "dreamerv2", *DREAMER_SCHEDULE]
EWC = ["--algo", "dreamerv2-finetune-ewc", *FINETUNE[2:]]
OFFLINE = {
    "dreamerv2": DREAMERV2,
    "curl": CURL,
    "drq-bc": DRQ_BC,
    "dreamerv2-penalty": PENALTY,
    "dreamerv2-finetune": FINETUNE,
    "lompo": LOMPO,
    "dreamerv2-finetune-ewc": EWC,
}
"""Algorithms whose checkpoint counts its updates at the top level (the offline loop's)."""
COWORLD = (
    "--algo coworld --source toy_reach --set train.prefill=100 --set coworld.pretrain_steps=200"
    " --set coworld.iterations=3 --set coworld.target_updates=10 --set coworld.source_updates=10"
).split()


@pytest.mark.parametrize(
    ("algo", "kills"),
    [
        pytest.param("dreamerv2", 3, id="dreamerv2-3-kills", marks=pytest.mark.slow),
        pytest.param("curl", 2, id="curl-2-kills", marks=pytest.mark.slow),
        pytest.param("drq-bc", 2, id="drq-bc-2-kills"),
        pytest.param("dreamerv2-penalty", 3, id="dreamerv2-penalty-3-kills", marks=pytest.mark.slow),
        pytest.param("dreamerv2-finetune", 3, id="dreamerv2-finetune-3-kills", marks=pytest.mark.slow),
        pytest.param("lompo", 3, id="lompo-3-kills", marks=pytest.mark.slow),
        pytest.param("dreamerv2-finetune-ewc", 3, id="dreamerv2-finetune-ewc-3-kills", marks=pytest.mark.slow),
        pytest.param("coworld", 5, id="coworld-5-kills", marks=pytest.mark.slow),
    ],
)
def test_train_killed_at_random_moments(
    algo: str, kills: int, tmp_path: Path, processes: ModuleType, helpers: ModuleType, toy_dataset_writer
) -> None:
    dataset = toy_dataset_writer(tmp_path / "toy.h5", "toy_reach_shifted")
    run = tmp_path / "run"
    checkpoint, replay = run / "checkpoint.pt", run / "source_replay.h5"
    args = [*TRAIN, *OFFLINE.get(algo, COWORLD), "--dataset", str(dataset), "--logdir", str(run)]
    rng = np.random.default_rng(kills)
    progress, experience = -1, []
    for _ in range(kills):
        mtime = checkpoint.stat().st_mtime_ns if checkpoint.exists() else None
        proc = processes.start_cli(*args)
        if not processes.wait_for(_replaced(checkpoint, mtime), proc, what="a checkpoint", or_end=True):
            break  # it finished before this kill
        time.sleep(float(rng.uniform(0.0, 2.0)))
        processes.kill(proc)
        state = load_checkpoint(checkpoint)  # whole: it loads
        done = state["updates"] if algo in OFFLINE else state["agent"]["updates"]
        assert done >= progress and done % 10 == 0  # checkpoint boundaries only, never going back
        progress = done
        if algo == "coworld":  # the source agent's experience, a dataset too
            helpers.assert_unfinished_but_sound(replay)
            digests = helpers.episode_digests(replay)
            assert digests[: len(experience)] == experience
            experience = digests
    assert progress >= 0
    done = processes.run_cli(*args)
    assert done.returncode == 0, done.stderr[-3000:]
    state = load_checkpoint(checkpoint)
    if algo in OFFLINE:
        assert state["updates"] == (150 if algo in ("curl", "drq-bc") else 100)
        # the agent resumed with the loop, not from zero (the fine-tuned one also counts its source updates)
        fine_tuned = algo in ("dreamerv2-finetune", "dreamerv2-finetune-ewc")
        source = load_checkpoint(run / "source" / "checkpoint.pt")["updates"] if fine_tuned else 0
        assert state["agent"]["updates"] == state["updates"] + source
    else:
        assert state["progress"]["iteration"] == 3 and state["agent"]["updates"] == 30
        assert helpers.episode_digests(replay)[: len(experience)] == experience
    whole = tmp_path / "whole"
    done = processes.run_cli(*args[:-2], "--logdir", str(whole))  # the same command, in a folder of its own
    assert done.returncode == 0, done.stderr[-3000:]
    never_killed = load_checkpoint(whole / "checkpoint.pt")
    differ = helpers.states_differ
    changed = [key for key in ("agent", "source") if key in state and differ(state[key], never_killed[key])]
    assert not changed, changed


def _replaced(path: Path, mtime: int | None):
    """Whether ``path`` exists and is not the file of modification time ``mtime``."""
    return lambda: path.exists() and path.stat().st_mtime_ns != mtime


DV2_COLLECT = (
    "collect --task toy_reach --preset tiny --quiet --device cpu --threads 1 --max-steps 400 --set train.prefill=100"
    " --set train.checkpoint_every=200 --set train.log_every=10"
).split()
"""400 steps of 50-step episodes, an update every 10 steps after the prefill, checkpoints at steps 200 and 400."""


def test_the_dreamerv2_collector_killed_past_its_checkpoint_resumes_to_the_uninterrupted_run(
    tmp_path: Path, processes: ModuleType, helpers: ModuleType
) -> None:
    """Killed after an episode its agent's checkpoint (step 200) had not seen, the collector resumes from that
    checkpoint with the dataset cut back to it: the rerun ends with the episodes, the record, the log and the agent
    of the run never stopped."""
    out, whole = tmp_path / "stopped" / "d.h5", tmp_path / "whole" / "d.h5"
    done = processes.run_cli(*DV2_COLLECT, "--out", str(whole))
    assert done.returncode == 0, done.stderr[-3000:]
    run = out.with_name("d.run")
    proc = processes.start_cli(*DV2_COLLECT, "--out", str(out))
    processes.wait_for((run / "checkpoint.pt").exists, proc, what="the first checkpoint")
    processes.wait_for(lambda: max(_logged_steps(run), default=0) >= 260, proc, what="the step 260 record")
    processes.kill(proc)
    with open_dataset(out) as data:  # it holds an episode the checkpoint had not seen
        assert data.num_episodes > load_checkpoint(run / "checkpoint.pt")["episodes"]
    done = processes.run_cli(*DV2_COLLECT, "--out", str(out), "--resume")
    assert done.returncode == 0, done.stderr[-3000:]
    assert re.search(
        rf"warning: {out} held \d+ episodes and the agent's last checkpoint had seen 4: the \d+ episodes?"
        " after it are collected again",
        done.stderr,
    ), done.stderr[-3000:]
    assert helpers.episode_digests(out) == helpers.episode_digests(whole)
    with open_dataset(out) as data, open_dataset(whole) as reference:
        record, expected = data.metadata["collector"], reference.metadata["collector"]
        assert data.complete and record["steps"] == data.num_steps == 400
        assert record.pop("run") != expected.pop("run") and record == expected  # steps, updates, stop reason
    states = [load_checkpoint(path.with_name("d.run") / "checkpoint.pt") for path in (out, whole)]
    for state in states:
        state.pop("config")
        state.pop("metrics_mark")
    assert not helpers.states_differ(*states)  # the agent, its counters and random states
    assert _logged_steps(run) == _logged_steps(whole.with_name("d.run"))  # each record once


def _logged_steps(run: Path) -> list[int]:
    """The steps of a run's metrics records, in order."""
    from coworld.training.logger import read_metrics

    return [record["step"] for record in read_metrics(run)]
