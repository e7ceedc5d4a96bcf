"""Run a sweep: plan its jobs from the files on disk, then execute them on local worker processes or a Ray cluster.

Layout of a sweep folder ``DIR``::

    DIR/sweep.json           the grid (SweepSpec), extended by reruns asking for more runs
    DIR/sweep.lock           held while a sweep process works on DIR (a second one is refused)
    DIR/datasets/<target>-<quality>.h5  one dataset per target task (``--data-dir`` moves them)
    DIR/runs/<run name>/     each run's folder, as ``coworld train`` makes it, plus eval.json and sweep-run.json
    DIR/logs/<job name>.log  the output of every command of a job, all attempts, kept

Resuming is planning: a dataset marked complete is not collected again (a partial one is continued with
``--resume``); a run whose ``eval.json`` holds its evaluation is finished and skipped; any other run is started
again, and ``coworld train`` resumes its run folder from the last checkpoint. Collection and training never
race: a run starts only after its dataset's job succeeded (or when the dataset was complete at planning).
A failed job is reported with its log and does not stop the others; the runs needing a failed dataset fail too.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from coworld import interrupt
from coworld.config import first_difference
from coworld.errors import CoworldError, DatasetError
from coworld.sweep.grid import Run, SweepSpec
from coworld.sweep.jobs import Job, JobProcess, JobResult, execute, reap_orphan, write_json
from coworld.sweep.progress import ProgressView, latest_eval

SPEC_FILE = "sweep.json"
AXES = ("pairs", "algos", "seeds", "variants")
"""The fields of a grid that a rerun in the same folder may change (it extends the grid)."""
RUN_RECORD = "sweep-run.json"
"""Written into each run folder: the run's place in the grid (its variant name, its pair)."""


@dataclass(frozen=True)
class SweepDirs:
    """Where a sweep keeps its files."""

    root: Path
    data: Path

    @classmethod
    def at(cls, root: str | Path, data: str | Path | None = None) -> SweepDirs:
        root = Path(root)
        return cls(root, Path(data) if data is not None else root / "datasets")

    @property
    def runs(self) -> Path:
        return self.root / "runs"

    @property
    def logs(self) -> Path:
        return self.root / "logs"

    def run_dir(self, run: Run) -> Path:
        return self.runs / run.name

    def dataset(self, target: str, spec: SweepSpec) -> Path:
        """``<data>/<target>-<quality>.h5``, named as ``coworld collect`` names it by default."""
        from coworld.data.collect import default_dataset_path

        return self.data / default_dataset_path(target, spec.data.label).name


@dataclass(frozen=True)
class Execution:
    """How the jobs run (not part of the grid: a rerun may change these)."""

    jobs: int = 1
    """Jobs at once on local worker processes."""
    threads: int = 1
    """Torch threads per command (and CPUs requested per Ray task)."""
    device: str | None = None
    """--device of every command (None: each command's default, auto)."""
    ray: str | None = None
    """Ray address ('auto', 'local' or host:port); None runs local worker processes."""
    gpus_per_run: float = 0.0
    """GPUs requested per Ray task (0.5: two runs share a GPU)."""
    progress: bool | None = None
    """Show the progress view (None: when stderr is a terminal, else a plain line each ``interval`` seconds)."""
    interval: float = 60.0
    poll: float = 1.0
    """Seconds between checks of running jobs."""


@dataclass
class Plan:
    """The jobs still to do and the runs already finished."""

    jobs: list[Job]
    runs: list[Run]
    finished: list[str] = field(default_factory=list)
    """Names of runs skipped because their eval.json is there."""


@dataclass(frozen=True)
class Outcome:
    """What a sweep process did; ``ok`` when every run of the grid is finished."""

    runs: int
    finished_before: int
    results: tuple[JobResult, ...]
    failed: tuple[tuple[str, Path], ...]
    """(job name, log file) of each failed job."""

    @property
    def ok(self) -> bool:
        return not self.failed


# -- planning -------------------------------------------------------------------------------------------------------


def run_finished(run_dir: Path, episodes: int) -> bool:
    """A run is finished when its eval.json holds a final evaluation of ``episodes`` episodes."""
    try:
        result = json.loads((run_dir / "eval.json").read_text())
        return len(result["returns"]) == episodes
    except (OSError, ValueError, KeyError, TypeError):
        return False


def dataset_state(path: Path) -> str:
    """'complete', 'partial' or 'missing'."""
    if not path.exists():
        return "missing"
    from coworld.data import open_dataset

    try:
        with open_dataset(path) as data:
            return "complete" if data.complete else "partial"
    except DatasetError:
        return "partial"


def collect_args(spec: SweepSpec, target: str, out: Path, execution: Execution, resume: bool) -> tuple[str, ...]:
    d = spec.data
    args = ["collect", "--task", target, "--policy", d.policy, "--out", str(out), "--seed", str(d.seed), "--quiet"]
    if d.policy == "dreamerv2":
        args += ["--quality", d.quality, "--preset", spec.preset]
        for item in d.overrides:
            args += ["--set", item]
        if execution.device is not None:
            args += ["--device", execution.device]
    if d.episodes is not None:
        args += ["--episodes", str(d.episodes)]
    if d.max_steps is not None:
        args += ["--max-steps", str(d.max_steps)]
    if resume:
        args.append("--resume")
    return (*args, "--threads", str(execution.threads))


def run_steps(
    spec: SweepSpec, run: Run, run_dir: Path, dataset: Path, execution: Execution, shares: tuple[Path, ...] = ()
) -> tuple[tuple[str, ...], ...]:
    """The train and eval command lines of one run; ``shares``: the run folders whose source pretraining is this
    CoWorld run's (each keeps its own, and a new run starts from the first kept)."""
    device = ("--device", execution.device) if execution.device is not None else ()
    threads = ("--threads", str(execution.threads))
    train = ["train", "--algo", run.algo, "--target", run.target, "--dataset", str(dataset)]
    if run.source is not None:
        train += ["--source", run.source]
    train += ["--preset", spec.preset, "--logdir", str(run_dir), "--seed", str(run.seed), "--no-progress"]
    for item in spec.run_overrides(run):
        train += ["--set", item]
    if shares:
        train.append("--keep-pretrained")
        for folder in shares:
            train += ["--pretrained-from", str(folder)]
    evaluate = ["eval", "--ckpt", str(run_dir), "--episodes", str(spec.eval_episodes), "--seed", "0", "--force"]
    evaluate += ["--out", str(run_dir / "eval.json.partial")]
    return (*train, *device, *threads), (*evaluate, *device, *threads)


def plan(spec: SweepSpec, dirs: SweepDirs, execution: Execution) -> Plan:
    """The jobs left to do, judged from the files in ``dirs``."""
    runs = spec.runs()
    jobs: list[Job] = []
    collect_job: dict[str, str | None] = {}
    for target in spec.targets():
        path = dirs.dataset(target, spec)
        state = dataset_state(path)
        if state == "complete":
            collect_job[target] = None
            continue
        name = f"collect-{path.stem}"
        jobs.append(
            Job(
                name=name,
                kind="collect",
                steps=(collect_args(spec, target, path, execution, resume=state == "partial"),),
                log=dirs.logs / f"{name}.log",
                pid_file=dirs.logs / f"{name}.pid",
            )
        )
        collect_job[target] = name
    finished = []
    siblings = spec.shared_pretraining()
    for run in runs:
        run_dir = dirs.run_dir(run)
        if run_finished(run_dir, spec.eval_episodes):
            finished.append(run.name)
            continue
        shares = siblings.get(run.name, ())
        folders = tuple(dirs.run_dir(other) for other in shares)
        jobs.append(
            Job(
                name=run.name,
                kind="run",
                steps=run_steps(spec, run, run_dir, dirs.dataset(run.target, spec), execution, folders),
                log=dirs.logs / f"{run.name}.log",
                pid_file=dirs.logs / f"{run.name}.pid",
                finish=(run_dir / "eval.json.partial", run_dir / "eval.json"),
                needs=collect_job[run.target],
                run_dir=run_dir,
                algo=run.algo,
                shares=tuple(other.name for other in shares),
            )
        )
    return Plan(jobs, runs, finished)


def write_run_records(spec: SweepSpec, plan: Plan, dirs: SweepDirs) -> None:
    """Give each run folder its place in the grid (read by ``coworld report``)."""
    pairs = {target: source for source, target in spec.pairs}
    for run in plan.runs:
        run_dir = dirs.run_dir(run)
        path = run_dir / RUN_RECORD
        if path.exists():
            continue
        run_dir.mkdir(parents=True, exist_ok=True)
        record = {
            "algo": run.algo,
            "variant": run.variant,
            "source": run.source or pairs[run.target],
            "target": run.target,
            "seed": run.seed,
        }
        write_json(path, record)


# -- the sweep folder -----------------------------------------------------------------------------------------------


class SweepLock:
    """One sweep process per folder: ``DIR/sweep.lock`` (a lock left by a killed sweep is taken over)."""

    def __init__(self, root: Path) -> None:
        from coworld.data.lock import WriterLock, read_lock

        try:
            self._lock = WriterLock(root / "sweep")
        except DatasetError:
            holder = read_lock(root / "sweep") or {}
            who = f"process {holder.get('pid')} on {holder.get('host')}" if holder else "another process"
            raise CoworldError(
                f"{root} is in use by another sweep ({who}); wait for it to end, or delete {root / 'sweep.lock'}"
                " if it no longer runs"
            ) from None

    def release(self) -> None:
        self._lock.release()


def check_spec(spec: SweepSpec, root: Path) -> None:
    """Save the grid of a new sweep folder; in an existing one, extend its grid or refuse other settings.

    A rerun may ask for other pairs, algorithms, seeds or CoWorld variants: ``sweep.json`` then holds the union
    of every grid run in the folder. What changes the runs or datasets themselves (preset, ``--set``, data,
    evaluation episodes, the overrides of a variant already there) is refused: such runs would not compare.
    """
    path = root / SPEC_FILE
    if not path.exists():
        write_json(path, spec.to_dict())
        return
    saved = load_spec(root)
    write_json(path, merge_specs(saved, spec, root).to_dict())


def merge_specs(saved: SweepSpec, now: SweepSpec, root: Path) -> SweepSpec:
    """The union of two grids of one folder; CoworldError if their shared settings differ."""
    settings = [{k: v for k, v in spec.to_dict().items() if k not in AXES} for spec in (saved, now)]
    diff = first_difference(*settings)
    if diff:
        raise CoworldError(
            f"{root} holds a sweep with other run settings ({diff}); rerun with the same --preset, --set, data"
            " and --eval-episodes, or use a new --dir"
        )
    variants = {entry[0]: entry for entry in saved.variants}
    for entry in now.variants:
        held = variants.setdefault(entry[0], entry)
        if held != entry:
            raise CoworldError(
                f"{root} holds the variant {entry[0] or 'coworld'!r} with overrides {list(held[1])}"
                f"{'' if len(held) < 3 else ' of ' + ', '.join(held[2])}, not {list(entry[1])}; give the new variant"
                " another name, or use a new --dir"
            )

    def union(a: tuple, b: tuple) -> tuple:
        return tuple(dict.fromkeys((*a, *b)))

    return dataclasses.replace(
        saved,
        pairs=union(saved.pairs, now.pairs),
        algos=union(saved.algos, now.algos),
        seeds=union(saved.seeds, now.seeds),
        variants=tuple(variants.values()),
    )


def load_spec(root: str | Path) -> SweepSpec:
    path = Path(root) / SPEC_FILE
    try:
        return SweepSpec.from_dict(json.loads(path.read_text()))
    except FileNotFoundError:
        raise CoworldError(f"{root} is not a sweep folder (no {SPEC_FILE})") from None
    except (ValueError, KeyError, TypeError) as err:
        raise CoworldError(f"{path} is unreadable ({err})") from None


# -- running --------------------------------------------------------------------------------------------------------


def run_sweep(
    spec: SweepSpec,
    root: str | Path,
    execution: Execution = Execution(),
    *,
    data_dir: str | Path | None = None,
    on_plan: Callable[[Plan], None] | None = None,
) -> Outcome:
    """Run every unfinished run of ``spec`` in the sweep folder ``root`` (see the module docstring).

    Raises CoworldError (one line) if the folder holds another grid or another sweep works on it.
    """
    dirs = SweepDirs.at(root, data_dir)
    check_execution(execution)
    ray = connect_ray(execution.ray) if execution.ray is not None else None
    dirs.root.mkdir(parents=True, exist_ok=True)
    lock = SweepLock(dirs.root)
    try:
        check_spec(spec, dirs.root)
        dirs.logs.mkdir(exist_ok=True)
        dirs.data.mkdir(parents=True, exist_ok=True)
        for pid_file in sorted(dirs.logs.glob("*.pid")):
            reap_orphan(pid_file)  # children of a killed sweep (none on Linux, where they die with it)
        the_plan = plan(spec, dirs, execution)
        write_run_records(spec, the_plan, dirs)
        if on_plan is not None:
            on_plan(the_plan)
        view = ProgressView(
            len(the_plan.runs),
            enabled=execution.progress is not False,
            interval=execution.interval,
        )
        tracker = _Tracker(the_plan, view)
        try:
            if ray is None:
                _run_local(the_plan, execution, tracker)
            else:
                _run_ray(ray, the_plan, execution, tracker)
        finally:
            view.close()
        failed = tuple((r.name, _log_of(the_plan, r.name)) for r in tracker.results if r.returncode != 0)
        return Outcome(len(the_plan.runs), len(the_plan.finished), tuple(tracker.results), failed)
    finally:
        lock.release()


def check_execution(execution: Execution) -> None:
    """What every run of the sweep would find wrong with how it runs, checked once before anything is made."""
    if execution.gpus_per_run and execution.ray is None:
        raise CoworldError("--gpus-per-run is a Ray resource request; pass --ray ADDRESS (locally, runs share the GPU)")
    if execution.jobs < 1 or execution.threads < 1:
        raise CoworldError("--jobs and --threads must be at least 1")
    if execution.ray is None and execution.device is not None:  # on Ray, the workers' devices count, not this one's
        from coworld.devices import resolve_device

        resolve_device(execution.device)


def _log_of(plan: Plan, name: str) -> Path:
    return next(job.log for job in plan.jobs if job.name == name)


class _Tracker:
    """Bookkeeping shared by the backends: job states, results, the progress view."""

    def __init__(self, plan: Plan, view: ProgressView) -> None:
        self.plan = plan
        self.view = view
        self.jobs = {job.name: job for job in plan.jobs}
        self.run_states = {run.name: "pending" for run in plan.runs}
        for name in plan.finished:
            self.run_states[name] = "done"
        self.results: list[JobResult] = []
        self.collecting: set[str] = set()

    def started(self, name: str) -> None:
        if name in self.run_states:
            self.run_states[name] = "running"
        elif self.jobs[name].kind == "collect":
            self.collecting.add(name)

    def ended(self, result: JobResult) -> None:
        self.results.append(result)
        self.collecting.discard(result.name)
        job = self.jobs[result.name]
        took = f"{result.wall_s:.0f} s, {result.cpu_s:.0f} CPU s"
        if job.kind == "run":
            self.run_states[job.name] = "done" if result.returncode == 0 else "failed"
        if result.returncode != 0:
            self.view.event(f"FAILED {job.name} (exit code {result.returncode}); log: {job.log}")
            return
        try:
            mean = json.loads((job.run_dir / "eval.json").read_text())["mean"]  # type: ignore[operator]
            self.view.event(f"done {job.name}: return {mean:.1f} ({took})")
        except (TypeError, OSError, ValueError, KeyError):  # a dataset, or a run without its result
            self.view.event(f"done {job.name} ({took})")

    def refresh(self) -> None:
        running = {
            name: latest_eval(self.jobs[name].run_dir, self.jobs[name].algo)
            for name, state in self.run_states.items()
            if state == "running"
        }
        self.view.update(self.run_states, running, len(self.collecting))


def _run_local(plan: Plan, execution: Execution, tracker: _Tracker) -> None:
    """Local worker processes, at most ``execution.jobs`` jobs at once, started from this (the main) thread."""
    pending = list(plan.jobs)
    outcome: dict[str, int] = {}
    active: list[JobProcess] = []
    restore = _stop_on_sigterm()
    try:
        while pending or active:
            for job in sorted(pending, key=lambda job: _waits_for_pretraining(job, active)):  # stable: grid order
                if len(active) >= execution.jobs:
                    break
                if job.needs is not None and job.needs not in outcome:
                    continue  # its dataset is still being collected
                pending.remove(job)
                if job.needs is not None and outcome[job.needs] != 0:
                    result = execute(job, execution.threads, JobResult(job.needs, outcome[job.needs], 0, 0))
                    outcome[job.name] = result.returncode
                    tracker.ended(result)
                    continue
                active.append(JobProcess(job, execution.threads))
                tracker.started(job.name)
            tracker.refresh()
            time.sleep(execution.poll)
            for process in list(active):
                result = process.poll()
                if result is not None:
                    active.remove(process)
                    outcome[result.name] = result.returncode
                    tracker.ended(result)
        tracker.refresh()
    finally:
        for process in active:
            process.stop(wait=False)  # all at once: each gets its grace period at the same time
        for process in active:
            process.stop()
        restore()


def _waits_for_pretraining(job: Job, active: list[JobProcess]) -> bool:
    """Whether a run shares the source pretraining that a running run is doing now (it has no checkpoint of its own
    yet, which it writes once it kept its pretraining): it had better start after the jobs that wait for nothing,
    and then copy that pretraining rather than do its own."""
    from coworld.training.checkpoint import CHECKPOINT_NAME

    return any(p.job.name in job.shares and not (p.job.run_dir / CHECKPOINT_NAME).exists() for p in active)


def _stop_on_sigterm() -> Callable[[], None]:
    """Stop on SIGTERM (raising :class:`~coworld.interrupt.Interrupted`, exit code 143 in the CLI) so the children
    are stopped, where nobody handles SIGTERM yet (the CLI does already); returns the undo."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    if signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, None):
        return lambda: None

    def handler(signum: int, frame: Any) -> None:
        raise interrupt.Interrupted(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    return lambda: signal.signal(signal.SIGTERM, previous)


# -- Ray ------------------------------------------------------------------------------------------------------------


RAY_CONNECT_SECONDS = 5.0
"""How long the sweep waits for a Ray cluster's head to answer before it gives up (Ray itself retries for minutes)."""
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
"""What a gRPC client sends first: HTTP/2's connection preface and an empty SETTINGS frame."""


def connect_ray(address: str) -> Any:
    """Ray, connected to the cluster at ``address`` ('local' starts one here); one CoworldError line within about
    :data:`RAY_CONNECT_SECONDS` when nothing there answers as a Ray head does, before Ray is asked to connect."""
    import logging

    ray = import_ray()
    if ray.is_initialized():
        return ray
    quiet = {"log_to_driver": False, "logging_level": logging.ERROR}
    if address == "local":
        ray.init(include_dashboard=False, **quiet)
        return ray
    target = os.environ.get("RAY_ADDRESS", "") if address == "auto" else address
    if target and target != "auto":
        check_ray_head(target, given="RAY_ADDRESS" if address == "auto" else "--ray")
    try:
        ray.init(address=address, **quiet)
    except (ConnectionError, ValueError, RuntimeError) as err:
        raise CoworldError(f"cannot connect to Ray at {address} ({_first_line(err)}); {_RAY_HINT}") from None
    return ray


_RAY_HINT = "start a cluster with `ray start --head`, or pass --ray local to start one here"


def check_ray_head(address: str, given: str = "--ray") -> None:
    """Refuse, in one line, an address that is not ``HOST:PORT`` (or ``ray://HOST:PORT``) or where no gRPC server
    answers (a Ray head's GCS speaks gRPC: it answers HTTP/2's preface with a SETTINGS frame)."""
    import socket

    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise CoworldError(
            f"{given} {address!r} is not an address: use HOST:PORT of a Ray cluster's head (e.g. 10.0.0.5:6379),"
            " 'auto' for the one started on this machine, or 'local'"
        )
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=RAY_CONNECT_SECONDS) as conn:
            conn.settimeout(RAY_CONNECT_SECONDS)
            conn.sendall(_HTTP2_PREFACE)
            reply = conn.recv(9)
    except OSError as err:
        reason = "no answer" if isinstance(err, TimeoutError) else err.strerror or type(err).__name__
        raise CoworldError(f"no Ray cluster answers at {address} ({reason}); {_RAY_HINT}") from None
    if len(reply) < 4 or reply[3] != 4:  # a SETTINGS frame's type byte
        raise CoworldError(f"{address} answers, but not as a Ray cluster's head does; check the port ({_RAY_HINT})")


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0][:200] if text else type(err).__name__


def import_ray() -> Any:
    try:
        import ray
    except ModuleNotFoundError:
        raise CoworldError("--ray needs Ray: pip install 'coworld[ray]'") from None
    return ray


def _ray_task(job: Job, threads: int, needed: JobResult | None = None) -> JobResult:
    """What a Ray task runs: the job's commands on the worker (the same child processes as locally)."""
    return execute(job, threads, needed)


def _run_ray(ray: Any, plan: Plan, execution: Execution, tracker: _Tracker) -> None:
    """Each job a Ray task requesting ``threads`` CPUs and ``gpus_per_run`` GPUs; runs wait for their dataset."""
    if not ray.is_initialized():
        connect_ray(execution.ray or "local")
    task = ray.remote(_ray_task).options(
        num_cpus=execution.threads, num_gpus=execution.gpus_per_run, max_retries=0, name="coworld-sweep-job"
    )
    refs: dict[str, Any] = {}
    for job in plan.jobs:  # collection jobs come first in the plan
        needed = refs.get(job.needs) if job.needs is not None else None
        refs[job.name] = task.remote(job, execution.threads, needed)
    waiting = {ref: name for name, ref in refs.items()}
    try:
        while waiting:
            ready, _ = ray.wait(list(waiting), num_returns=len(waiting), timeout=execution.poll)
            for ref in ready:
                name = waiting.pop(ref)
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayError as err:  # the worker died, or the task could not run
                    tracker.view.event(f"Ray could not run {name}: {str(err).splitlines()[0]}")
                    result = JobResult(name, -1, 0.0, 0.0)
                tracker.ended(result)
            for name in waiting.values():
                job = tracker.jobs[name]
                if job.pid_file.exists():  # written by the worker when a command starts (shared folder)
                    tracker.started(name)
            tracker.refresh()
    except BaseException:
        for ref in waiting:
            ray.cancel(ref, force=True)
        raise


def preview(spec: SweepSpec, root: str | Path, execution: Execution, *, data_dir: str | Path | None = None) -> str:
    """What a sweep would do, one line per dataset to collect and per run, writing nothing (``--dry-run``), and
    what the runs still to do will cost (:func:`cost_lines`)."""
    dirs = SweepDirs.at(root, data_dir)
    if (dirs.root / SPEC_FILE).exists():
        merge_specs(load_spec(dirs.root), spec, dirs.root)
    the_plan = plan(spec, dirs, execution)
    lines = [
        f"collect   {job.steps[0][job.steps[0].index('--out') + 1]}" for job in the_plan.jobs if job.kind == "collect"
    ]
    hours = arm_hours(the_plan.runs, the_plan.finished, dirs)
    for run in the_plan.runs:
        if run.name in the_plan.finished:
            state = "finished"
        elif (dirs.run_dir(run) / "checkpoint.pt").exists():
            state = "resume"
        else:
            state = "new"
        cost = hours.get(_arm(run))
        lines.append(f"{state:9} {run.name}" + (f"  (about {cost:.1f} h)" if cost and state != "finished" else ""))
    return "\n".join([*lines, *cost_lines(the_plan, hours, execution)])


def _arm(run: Run) -> tuple[str, str]:
    return run.algo, run.variant


def arm_hours(runs: list[Run], finished: list[str], dirs: SweepDirs) -> dict[tuple[str, str], float]:
    """Training hours a run of each arm (algorithm, variant) took, the mean over the arm's finished runs in the
    folder (``coworld report``'s ``wall_time_s``); an arm with none takes its algorithm's mean over other arms."""
    from coworld.report.results import load_result

    walls: dict[tuple[str, str], list[float]] = {}
    for run in runs:
        if run.name in finished:
            wall = load_result(dirs.run_dir(run)).wall_time_s
            if wall is not None:
                walls.setdefault(_arm(run), []).append(wall / 3600)
    hours = {arm: sum(w) / len(w) for arm, w in walls.items()}
    for run in runs:
        if _arm(run) not in hours:
            same = [h for (algo, _), h in hours.items() if algo == run.algo]
            if same:
                hours[_arm(run)] = sum(same) / len(same)
    return hours


def cost_lines(the_plan: Plan, hours: dict[tuple[str, str], float], execution: Execution) -> list[str]:
    """The estimate's closing lines: the runs to go, their training hours where an estimate exists, and the wall
    clock at ``--jobs`` runs at once. The datasets to collect and the evaluations are not counted."""
    todo = [run for run in the_plan.runs if run.name not in the_plan.finished]
    if not todo:
        return [f"all {len(the_plan.runs)} runs are finished"]
    known = [hours[_arm(run)] for run in todo if _arm(run) in hours]
    if not known:
        return [
            f"{len(todo)} runs to go; no finished run in this folder to estimate their cost from (docs/reproducing.md,"
            " 'Cost', gives measured ones)"
        ]
    total = sum(known)
    jobs = max(1, min(execution.jobs, len(todo)))
    unknown = len(todo) - len(known)
    rest = f"; {unknown} runs of algorithms with no finished run are not counted" if unknown else ""
    return [
        f"{len(todo)} runs to go: about {total:.1f} training hours, {total / jobs:.1f} h of wall clock at --jobs {jobs}"
        f" (each arm's finished runs here; dataset collection and evaluations not counted{rest})"
    ]
