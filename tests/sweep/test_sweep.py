"""Whole sweeps through the real CLI: kill -9 in the middle then the same command, a failing run, Ray.

The runs are the cheapest the pipeline allows: the toy pair, the tiny preset, CURL with 20 updates (DreamerV2 with
4 updates per iteration where it matters), 2 evaluation episodes, a 4-episode random dataset.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from coworld.errors import CoworldError
from coworld.sweep.grid import build_spec, read_grid_file
from coworld.sweep.jobs import Job
from coworld.sweep.progress import ProgressView
from coworld.sweep.runner import Execution, Plan, _run_ray, _Tracker, run_sweep

CLI = [sys.executable, "-c", "from coworld.cli import run; run()"]
GRID = """
pairs = ["toy_reach:toy_reach_shifted"]
algos = {algos}
seeds = {seeds}
preset = "tiny"
eval_episodes = 2
set = ["train.eval_episodes=2", "train.prefill=100", "coworld.pretrain_steps=200", "coworld.iterations=2",
       "coworld.target_updates=4", "coworld.source_updates=4",
       "offline.updates=8", "offline.eval_every=4", "offline.checkpoint_every=4",
       "curl.updates=20", "curl.eval_every=10", "curl.checkpoint_every=10", "curl.eval_episodes=1"]
[data]
policy = "random"
episodes = 4
"""


def grid(tmp_path: Path, algos: list[str], seeds: int) -> Path:
    path = tmp_path / "grid.toml"
    path.write_text(GRID.format(algos=json.dumps(algos), seeds=seeds))
    return path


def sweep_args(grid_file: Path, root: Path, *extra: str) -> list[str]:
    return [*CLI, "sweep", "--grid", str(grid_file), "--dir", str(root), "--device", "cpu", "--no-progress", *extra]


def wait_for(condition, proc: subprocess.Popen, timeout: float = 600) -> None:
    deadline = time.time() + timeout
    while not condition():
        assert proc.poll() is None, "the sweep ended before the moment the test waits for"
        assert time.time() < deadline, "timed out"
        time.sleep(0.1)


@pytest.mark.long
def test_kill9_in_the_middle_then_the_same_command_finishes_without_redoing(tmp_path, process_gone):
    root = tmp_path / "sweep"
    args = sweep_args(grid(tmp_path, ["curl"], 3), root, "--jobs", "1")
    runs = root / "runs"
    names = [f"curl-toy_reach_shifted-s{seed}" for seed in range(3)]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        # the moment: the first run finished, the second trained to its first checkpoint, its command still running
        second = runs / names[1]
        wait_for(lambda: (runs / names[0] / "eval.json").exists() and (second / "checkpoint.pt").exists(), proc)
        pid_file = root / "logs" / f"{names[1]}.pid"
        child = json.loads(pid_file.read_text())["pid"]
        os.kill(proc.pid, signal.SIGKILL)  # the sweep process alone; its children are in their own groups
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert process_gone(child), "a child of the killed sweep is still running"
    assert not (runs / names[1] / "eval.json").exists()
    finished = runs / names[0]
    stamps = {p.name: p.stat().st_mtime_ns for p in finished.iterdir() if p.is_file()}

    out = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "3 runs, 1 finished, 2 to run, 0 datasets to collect" in out.stderr
    for name in names:
        result = json.loads((runs / name / "eval.json").read_text())
        assert len(result["returns"]) == 2
    assert {p.name: p.stat().st_mtime_ns for p in finished.iterdir() if p.is_file()} == stamps  # not redone
    logs = {name: (root / "logs" / f"{name}.log").read_text() for name in names}
    assert logs[names[0]].count(": start on") == 1
    assert logs[names[1]].count(": start on") == 2
    assert "resuming from" in logs[names[1]].split(": start on")[-1]  # the second attempt resumed the checkpoint
    assert not list((root / "logs").glob("*.pid"))

    again = subprocess.run(args, capture_output=True, text=True, timeout=600)  # all finished: nothing to do
    assert again.returncode == 0 and "3 runs, 3 finished, 0 to run" in again.stderr


def test_coworld_variants_apart_in_zeta_pretrain_once(tmp_path):
    """The second run starts from the source pretraining the first kept, and both finish."""
    grid_file = grid(tmp_path, ["coworld"], 1)
    variants = '[variants]\n"" = []\nzeta3 = ["coworld.zeta=3"]\n\n[data]'
    grid_file.write_text(grid_file.read_text().replace("[data]", variants))
    root = tmp_path / "sweep"
    out = subprocess.run(sweep_args(grid_file, root, "--jobs", "1"), capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    first, second = (f"coworld-{v}toy_reach-toy_reach_shifted-s0" for v in ("", "zeta3-"))
    kept = root / "runs" / first / "pretrained"
    assert (kept / "checkpoint.pt").exists() and not (root / "runs" / second / "pretrained").exists()
    assert f"source pretraining copied from {kept}" in (root / "logs" / f"{second}.log").read_text()
    assert all((root / "runs" / name / "eval.json").exists() for name in (first, second))


def test_a_failed_run_is_reported_and_the_others_finish(tmp_path):
    root = tmp_path / "sweep"
    broken = root / "runs" / "curl-toy_reach_shifted-s1"
    broken.mkdir(parents=True)
    (broken / "config.json").write_text("{not json")  # `coworld train` refuses this folder
    out = subprocess.run(sweep_args(grid(tmp_path, ["curl"], 2), root), capture_output=True, text=True, timeout=600)
    assert out.returncode == 1, out.stdout + out.stderr[-3000:]
    log = root / "logs" / "curl-toy_reach_shifted-s1.log"
    assert f"failed: curl-toy_reach_shifted-s1 (log: {log})" in out.stdout
    assert "1/2 runs finished" in out.stdout
    assert "is not a coworld run folder" in log.read_text() and "FAILED (exit code 2)" in log.read_text()
    assert (root / "runs" / "curl-toy_reach_shifted-s0" / "eval.json").exists()


def test_a_second_sweep_on_the_same_folder_is_refused(tmp_path):
    from coworld.data.lock import WriterLock

    root = tmp_path / "sweep"
    root.mkdir()
    lock = WriterLock(root / "sweep")  # held by this (live) test process
    try:
        out = subprocess.run(sweep_args(grid(tmp_path, ["curl"], 1), root), capture_output=True, text=True, timeout=60)
    finally:
        lock.release()
    assert out.returncode == 2 and "is in use by another sweep" in out.stderr
    assert not (root / "sweep.json").exists()


def test_missing_ray_gives_the_install_hint(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` does without the extra
    spec = build_spec(**read_grid_file(grid(tmp_path, ["curl"], 1)))
    with pytest.raises(CoworldError) as info:
        run_sweep(spec, tmp_path / "sweep", Execution(ray="auto"))
    assert "pip install 'coworld[ray]'" in str(info.value) and not (tmp_path / "sweep").exists()


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray instance with 2 CPUs, shared by this module's Ray tests."""
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_ray_runs_jobs_as_tasks_and_skips_those_whose_dataset_failed(tmp_path, local_ray):
    def job(name: str, kind: str, steps, needs=None) -> Job:
        return Job(name, kind, steps, tmp_path / f"{name}.log", tmp_path / f"{name}.pid", needs=needs)

    jobs = [
        job("collect-bad", "collect", (("collect", "--task", "nowhere"),)),
        job("collect-good", "collect", (("--version",),)),
        job("run-a", "run", (("tasks",),), needs="collect-bad"),
        job("run-b", "run", (("tasks",), ("--version",)), needs="collect-good"),
    ]
    plan = Plan(jobs=jobs, runs=[])
    tracker = _Tracker(plan, ProgressView(0, enabled=False))
    _run_ray(local_ray, plan, Execution(ray="local", poll=0.2), tracker)
    codes = {result.name: result.returncode for result in tracker.results}
    assert codes == {"collect-bad": 2, "collect-good": 0, "run-a": 2, "run-b": 0}
    assert "not started: collect-bad failed" in (tmp_path / "run-a.log").read_text()
    log_b = (tmp_path / "run-b.log").read_text()
    assert log_b.index("coworld tasks") < log_b.index("coworld --version") and "done in" in log_b


@pytest.mark.slow  # test_ray_runs_jobs_as_tasks_... runs the Ray path in CI
def test_the_same_sweep_through_ray_gives_the_local_results(tmp_path, local_ray):
    spec = build_spec(**read_grid_file(grid(tmp_path, ["curl", "dreamerv2"], 1)))
    local = run_sweep(spec, tmp_path / "local", Execution(jobs=2, device="cpu", progress=False))
    on_ray = run_sweep(spec, tmp_path / "ray", Execution(ray="local", device="cpu", progress=False))
    assert local.ok and on_ray.ok and len(on_ray.results) == 1 + 2  # the dataset and two runs, as Ray tasks
    for run in spec.runs():
        a = json.loads((tmp_path / "local" / "runs" / run.name / "eval.json").read_text())
        b = json.loads((tmp_path / "ray" / "runs" / run.name / "eval.json").read_text())
        assert a["returns"] == b["returns"], run.name


def test_dry_run_lists_the_work_and_writes_nothing(tmp_path):
    from click.testing import CliRunner

    from coworld.cli import main

    root = tmp_path / "sweep"
    out = CliRunner().invoke(main, ["sweep", "--table", "toy", "--algos", "curl", "--seeds", "2", "--dir", str(root),
                                    "--dry-run"])  # fmt: skip
    assert out.exit_code == 0, out.output
    assert out.output.splitlines() == [
        f"collect   {root / 'datasets' / 'toy_reach_shifted-random.h5'}",
        "new       curl-toy_reach_shifted-s0",
        "new       curl-toy_reach_shifted-s1",
        "2 runs to go; no finished run in this folder to estimate their cost from (docs/reproducing.md, 'Cost', gives"
        " measured ones)",
    ]
    assert not root.exists()
    out = CliRunner().invoke(main, ["sweep", "--table", "toy", "--dir", str(root), "--gpus-per-run", "0.5"])
    assert out.exit_code == 2 and "--gpus-per-run is a Ray resource request" in out.output and not root.exists()


def test_dry_run_estimates_the_runs_to_go_from_the_finished_runs_of_their_arm(tmp_path):
    """The committed cap study with two runs unfinished: each is estimated at its arm's mean training time over the
    arm's finished runs (``wall_time_s``), and the total at --jobs runs at once."""
    import shutil

    from click.testing import CliRunner

    from coworld.cli import main
    from coworld.report.results import load_result
    from coworld.sweep.grid import named_table

    study = Path(__file__).parents[2] / "benchmarks" / "results" / "cap-study"
    root = tmp_path / "study"
    shutil.copytree(study, root)
    # the grid as this version writes it (the committed study's record predates the offline baselines' own schedule
    # settings, which the table now sets: a sweep folder of other settings is refused)
    (root / "sweep.json").write_text(json.dumps(named_table("cap-study").to_dict()))
    for name in ("coworld-4x-cheetah_run-cheetah_uphill-s2", "dreamerv2-cheetah_uphill-s0"):
        (root / "runs" / name / "eval.json").unlink()
    hours = {
        arm: sum(load_result(study / "runs" / f"{arm}-s{seed}").wall_time_s for seed in seeds) / len(seeds) / 3600
        for arm, seeds in (("coworld-4x-cheetah_run-cheetah_uphill", (0, 1)), ("dreamerv2-cheetah_uphill", (1, 2)))
    }
    args = ["sweep", "--table", "cap-study", "--dir", str(root), "--data-dir", str(tmp_path / "d"), "--jobs", "2"]
    out = CliRunner().invoke(main, [*args, "--dry-run"])
    assert out.exit_code == 0, out.output
    lines = out.output.splitlines()
    coworld = hours["coworld-4x-cheetah_run-cheetah_uphill"]
    assert f"new       coworld-4x-cheetah_run-cheetah_uphill-s2  (about {coworld:.1f} h)" in lines
    assert f"new       dreamerv2-cheetah_uphill-s0  (about {hours['dreamerv2-cheetah_uphill']:.1f} h)" in lines
    total = sum(hours.values())
    assert lines[-1].startswith(
        f"2 runs to go: about {total:.1f} training hours, {total / 2:.1f} h of wall clock at --jobs 2"
    )
    assert sum(line.startswith("finished ") for line in lines) == 31


@pytest.mark.slow
def test_lompo_and_the_ewc_fine_tuned_dreamerv2_run_in_a_sweep_and_get_report_rows(tmp_path):
    from click.testing import CliRunner

    from coworld.cli import main

    grid_file = tmp_path / "grid.toml"
    grid_file.write_text(
        GRID.format(algos=json.dumps(["lompo", "dreamerv2-finetune-ewc"]), seeds=1).replace(
            '"curl.updates=20"', '"lompo.model_updates=4", "ewc.fisher_batches=2", "curl.updates=20"'
        )
    )
    root = tmp_path / "sweep"
    done = subprocess.run(sweep_args(grid_file, root), capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout + done.stderr
    runs = sorted(p.name for p in (root / "runs").iterdir())
    assert runs == ["dreamerv2-finetune-ewc-toy_reach-toy_reach_shifted-s0", "lompo-toy_reach_shifted-s0"]
    assert all((root / "runs" / run / "eval.json").exists() for run in runs)
    out = CliRunner().invoke(main, ["report", str(root)])
    assert out.exit_code == 0, out.output
    report = (root / "report.md").read_text()
    assert "| pair | lompo | dreamerv2-finetune-ewc |" in report  # the columns: LOMPO, then fine-tuned
    assert "| toy_reach → toy_reach_shifted | lompo |" in report  # its value-check row
    assert "| toy_reach → toy_reach_shifted | dreamerv2-finetune-ewc |" in report
