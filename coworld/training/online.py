"""Online DreamerV2 training: the loop behind ``coworld collect`` and CoWorld's source agent.

The loop steps ``config.train.envs`` environments, stores every finished episode both in the in-RAM replay
the agent trains from and in an HDF5 dataset (the collected dataset itself, or ``<logdir>/replay.h5``), trains
once every ``train_every`` environment steps after a random prefill, evaluates every ``eval_every`` steps,
and checkpoints at episode boundaries. The dataset is the record of what was experienced: when a killed run is
started again on the same folder, the agent comes back from its checkpoint and the replay is reloaded from the
dataset.

Resumes: a checkpoint holds, beside the agent and the random states, the trainer's counters, the replay sampler's
state and the running episodes, as each environment's episode seed and its actions so far (an episode is a function
of the two, :class:`coworld.envs.base.PixelEnv`). Where the dataset holds exactly the episodes the checkpoint had
seen, the next :meth:`OnlineTrainer.acting` makes the running episodes again by replaying those actions and goes on as
the uninterrupted run did: the same steps, batches and weights. Collection and a two-phase run's source agent cut
their dataset back to the checkpoint (``restore(rollback=True)``) to resume this way, and their log with it (emptied
where no checkpoint was written). Without the cut, where the dataset recorded episodes after its checkpoint, the step
count continues from the dataset's row count and new episodes start (the ones running at the kill are lost, as
promised by the dataset writer).

Vector environments follow Gymnasium's default NEXT_STEP autoreset: after a step that ends an episode, the
next ``step`` of that environment ignores its action and returns the first observation of a new episode. The
acting side agrees with training on where episodes start: the policy is told ``is_first`` with the first frame
of every episode (and only with it), the frame the replay stores as ``is_first``.

Train ratio: after ``train.prefill`` random steps the agent makes ``train.pretrain_updates`` updates at once
(DreamerV2's ``pretrain``), then one update every ``train.train_every`` environment steps
(:meth:`OnlineTrainer.updates_due`). A run resumed from a dataset that went on past its checkpoint keeps
that ratio from its restored state on rather than catching up the updates lost with the killed process.

Two loops drive the same pieces inside :meth:`OnlineTrainer.acting`. :meth:`OnlineTrainer.run` (collection, a source
agent's pretraining) counts environment steps: :meth:`~OnlineTrainer.step`, the updates due by then
(:meth:`~OnlineTrainer.sample` and :meth:`~OnlineTrainer.update`), :meth:`~OnlineTrainer.settle` (log, evaluation,
checkpoint). CoWorld's source phases count updates (:mod:`coworld.training.coworld`): :meth:`~OnlineTrainer.act`
takes the steps until the next update falls due, settling each, then the phase samples and updates. Both give each
step, update and checkpoint the same place in the run.

By default each update is made as soon as it falls due, before the next step, and acting draws its random numbers
from torch's default generator, as the updates do. ``train.background_updates=true`` acts beside learning
instead: an update that falls due after step ``s`` samples its batch from the replay as it is at ``s`` (as the
default does) and runs on a background thread while the agent takes the next ``train_every`` steps with a copy of
the weights from before that update (:meth:`DreamerV2.policy_copy`); the next update waits for it, and the copy
then takes its weights. Acting (policy and environment, rendering included) and learning use two cores, at the
same train ratio, and the agent acts one update behind the default schedule. Acting then draws from a generator
of its own (``act_rng``, saved in the checkpoint), so the two threads never share one, and the thread changes
nothing: run in turn (:class:`Updates` without ``in_thread``), the same schedule records the same data and trains
the same weights (a test holds them equal). Evaluation, checkpoints and the end of a call wait for the running
update.
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from coworld import envs, interrupt
from coworld.config import Config
from coworld.data import DatasetWriter, open_dataset
from coworld.progress import progress_bar
from coworld.training.checkpoint import (
    CHECKPOINT_NAME,
    read_run_checkpoint,
    refuse_earlier_format,
    restore_agent,
    run_state,
    save_checkpoint,
)
from coworld.training.divergence import Phase
from coworld.training.evaluate import evaluate
from coworld.training.logger import EMPTY_MARK, METRICS_MARK, Logger, Rate
from coworld.training.openloop import log_open_loop
from coworld.training.replay import Replay

CHECKPOINT_KIND = "dreamerv2-online"
CHECKPOINT_KEYS = ("agent", "updates", "last_eval", "last_eval_step", "rng")
"""What an online run's checkpoint holds beyond its kind, at least (:meth:`OnlineTrainer.save`)."""
ONLINE_STATE_KEYS = ("steps", "episodes", "skipped_updates", "last_checkpoint_step", "act_rng", "replay_rng")
"""The trainer's own entries of a checkpoint (:meth:`OnlineTrainer.online_state`) that :meth:`OnlineTrainer.resume`
reads beside ``CHECKPOINT_KEYS``' counters; one without them was written before this release's format."""
ACT_SEED_OFFSET = 30_000
"""Acting's generator is seeded with ``seed + ACT_SEED_OFFSET`` (evaluation uses ``seed + 10_000``)."""
STOP_WAIT_SECONDS = 5.0
"""How long a call stopped by an error or a signal waits for the update running in the background to end."""


@dataclass
class Window:
    """What one :meth:`OnlineTrainer.acting` call keeps from step to step: its progress bar, the rates and metrics
    of the log window, and whether the last step is still to be settled (:meth:`OnlineTrainer.settle`) and ended an
    episode."""

    bar: Any
    update_rate: Rate
    step_rate: Rate
    last_log: int
    metrics: dict[str, float] = field(default_factory=dict)
    unsettled: bool = False
    ended: bool = False


@dataclass
class OnlineResult:
    steps: int
    updates: int
    episodes: int
    last_eval_return: float | None
    stop_reason: str


class Updates:
    """The online trainer's updates, one at a time: :meth:`start` hands over an update and its arguments,
    :meth:`wait` returns its metrics. ``in_thread``: the update runs on a thread of its own from :meth:`start` on;
    else :meth:`wait` runs it in the caller's thread. Either way an update starts and ends between the same two calls,
    so both run the same schedule."""

    def __init__(self, in_thread: bool) -> None:
        self.in_thread = in_thread
        self._update: tuple[Callable[..., dict[str, float]], tuple[Any, ...]] | None = None
        self._thread: threading.Thread | None = None
        self._result: dict[str, float] | None = None
        self._error: BaseException | None = None

    @property
    def pending(self) -> bool:
        """An update was started and not yet waited for."""
        return self._update is not None or self._thread is not None

    def start(self, train: Callable[..., dict[str, float]], *args: Any) -> None:
        """Start ``train(*args)``."""
        if self.pending:
            raise RuntimeError("an update is still pending: wait() for it before starting the next")
        if self.in_thread:
            self._thread = threading.Thread(target=self._run, args=(train, args), name="coworld-update", daemon=True)
            self._thread.start()
        else:
            self._update = (train, args)

    def wait(self, timeout: float | None = None) -> dict[str, float] | None:
        """The pending update's metrics, once it has ended (None if none was pending); raises what it raised.
        ``timeout`` (``in_thread`` only): give up after that many seconds and return None, leaving it pending."""
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                return None
            self._thread = None
        elif self._update is not None:
            (train, args), self._update = self._update, None
            self._run(train, args)
        result, error = self._result, self._error
        self._result = self._error = None
        if error is not None:
            raise error
        return result

    def abandon(self, timeout: float) -> None:
        """Drop the pending update (the job is stopping): a background one gets ``timeout`` seconds to end."""
        if self._thread is not None:
            self._thread.join(timeout)
        self._thread = self._update = self._result = self._error = None

    def _run(self, train: Callable[..., dict[str, float]], args: tuple[Any, ...]) -> None:
        try:
            self._result = train(*args)
        except BaseException as error:  # handed to the thread that waits
            self._error = error


def host(value: Any) -> np.ndarray:
    """A checkpoint's array as NumPy: its tensors are loaded onto the agent's device, a GPU's among them."""
    return value.cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)


def replay_step(
    image: np.ndarray, action: np.ndarray, reward: float, is_first: bool, is_last: bool, is_terminal: bool
) -> dict[str, Any]:
    """One step as the replay stores it (:mod:`coworld.training.replay`)."""
    return {
        "image": image,
        "action": action,
        "reward": np.float32(reward),
        "is_first": is_first,
        "is_last": is_last,
        "is_terminal": is_terminal,
    }


def dataset_episodes(path: str | Path) -> list[dict[str, np.ndarray]]:
    """Every episode of a dataset in the step convention (for reloading a replay)."""
    with open_dataset(path) as dataset:
        return [dataset.episode(i) for i in range(dataset.num_episodes)]


class OnlineTrainer:
    """Trains a DreamerV2 agent online in ``task`` while recording all it experiences into ``writer``.

    Args:
        agent: a DreamerV2 agent (``policy``, ``train``, ``state_dict``, ``load_state_dict``).
        train: the update, ``train(batch) -> metrics`` (named without this trainer's ``metric_prefix``); None: the
            agent's ``train`` (CoWorld's source agent: :meth:`coworld.agents.coworld.CoWorld.train_source`).
        task: registry name of the environment.
        config: resolved config (``train`` section drives the schedule).
        logdir: run folder for the checkpoint and logs.
        writer: open dataset writer receiving every finished episode; its rows are the step count.
        logger: where metrics go.
        checkpoint_extra: callable returning more entries to save in the checkpoint (CoWorld's target-policy critic,
            which learns beside the source agent while it pretrains).
        phase: what the trainer's updates, actions and checkpoints are checked as (:mod:`coworld.training.divergence`;
            a two-phase run names each of its phases by setting :attr:`phase`); None: collection.
    """

    def __init__(
        self,
        *,
        agent: Any,
        task: str,
        config: Config,
        logdir: str | Path,
        writer: DatasetWriter,
        logger: Logger,
        train: Callable[..., dict[str, float]] | None = None,
        checkpoint_extra: Callable[[], dict[str, Any]] | None = None,
        metric_prefix: str = "",
        step_unit_prefix: str = "",
        phase: Phase | None = None,
    ) -> None:
        self.agent, self.task, self.config = agent, task, config
        self.train = agent.train if train is None else train
        self.logdir = Path(logdir)
        self.writer, self.logger = writer, logger
        self.checkpoint_extra = checkpoint_extra
        self.prefix = metric_prefix
        self.step_unit = f"{step_unit_prefix}env_step"
        """What the step of this trainer's log records counts (``env_step``, ``source_env_step``)."""
        self.phase = phase or Phase(
            name="collection",
            agent="the agent",
            unit="update",
            kind=CHECKPOINT_KIND,
            config=config,
            resume_from=self.logdir / CHECKPOINT_NAME,
        )
        """The phase the trainer runs in, for :mod:`coworld.training.divergence`'s checks."""
        self.spec = envs.task_spec(task)
        self.replay = Replay(seed=config.seed)
        self.steps = writer.num_steps
        self.updates = 0
        self._skipped_updates = 0
        """Updates a resumed run skips rather than catching up (see :meth:`_skip_missed_updates`)."""
        self.last_eval: float | None = None
        self._updates_per_s: float | None = None
        self.last_eval_step = -1
        self._venv: Any = None
        self._obs: np.ndarray | None = None
        self._is_last = np.zeros(config.train.envs, dtype=bool)
        self._episode_actions: list[list[np.ndarray]] = [[] for _ in range(config.train.envs)]
        """Each environment's actions since its running (or just ended) episode began: with the episode's seed,
        what makes it again (:meth:`_replay_episodes`)."""
        self._running_success: list[list[float]] = [[] for _ in range(config.train.envs)]
        """Each environment's success flags in its running episode (Meta-World, RoboDesk)."""
        self._cut = False
        """The running episodes were cut at ``max_steps`` (a collection's last step): they cannot go on."""
        self._acting: dict[str, Any] | None = None
        """A checkpoint's running episodes, which the next :meth:`acting` makes again (see the module docstring)."""
        self._last_checkpoint_step = self.steps
        self.background = config.train.background_updates
        """Acting beside learning (see the module docstring)."""
        self._updates = Updates(in_thread=self.background)
        self._unlogged: dict[str, float] = {}
        """Metrics of the last update that ended (whoever waited for it), for the run loop's next log."""
        self._actor: Any = None
        """What acts: the agent itself, or its policy copy when updates run beside acting."""
        self._window: Window | None = None
        """The open :meth:`acting` call's progress bar, rates and log window, and its last step."""
        self.act_rng = torch.Generator(device=getattr(agent, "device", "cpu")).manual_seed(
            config.seed + ACT_SEED_OFFSET
        )
        """Where acting draws its random numbers beside learning (torch's default generator otherwise)."""

    # -- persistence -----------------------------------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path:
        return self.logdir / CHECKPOINT_NAME

    def restore(self, *, rollback: bool = False) -> dict[str, Any] | None:
        """Reload agent, counters and RNG from the checkpoint and the replay from the dataset, if any.

        ``rollback`` (collection, a source agent's pretraining): the dataset is first cut back to the episodes the
        checkpoint had seen (to none without a checkpoint, the log emptied too), so the agent, its counters and its
        replay are again those of one moment of the run, and the rerun ends with the counts an uninterrupted run ends
        with. Without it every recorded episode is kept.
        """
        state = None
        if self.checkpoint_path.exists():
            state = read_run_checkpoint(self.checkpoint_path, self.agent, CHECKPOINT_KIND, CHECKPOINT_KEYS)
            refuse_earlier_format(self.checkpoint_path, state, ONLINE_STATE_KEYS)
            restore_agent(self.agent, state, self.checkpoint_path, "an online dreamerv2 agent of this config")
        self.resume(state, rollback=rollback)
        return state

    def resume(self, state: Mapping[str, Any] | None, *, rollback: bool) -> None:
        """Continue from ``state`` (a checkpoint's :meth:`online_state` entries; None: from the data alone), the
        agent's weights and the random state being restored by the caller: the replay reloaded from the dataset, cut
        back first to the episodes ``state`` had seen where ``rollback``; its counters and random states; and, where
        the dataset then holds exactly those episodes, its running episodes, which the next :meth:`acting` makes again.
        """
        if rollback:
            seen = 0 if state is None else state["episodes"]
            self.writer.keep_episodes(min(int(seen), self.writer.num_episodes))
        for episode in dataset_episodes(self.writer.path) if self.writer.num_episodes else []:
            self.replay.add_episode(episode)
        self.steps = self.writer.num_steps
        if state is None:
            if rollback:  # nothing of the run was kept: it starts over, its log too
                self.logger.rewind(EMPTY_MARK)
            return
        self.updates = int(state["updates"])
        self.last_eval = state["last_eval"]
        self.last_eval_step = int(state["last_eval_step"])
        if state["episodes"] == self.writer.num_episodes:  # the steps after the checkpoint are taken (and logged)
            self.logger.rewind(state.get(METRICS_MARK))  # again; a collection that recorded more goes on after them
        self.act_rng.set_state(state["act_rng"].cpu())  # loaded onto the agent's device; generators take CPU states
        if "acting" in state and state["episodes"] == self.writer.num_episodes:
            self.steps = int(state["steps"])
            self._skipped_updates = int(state["skipped_updates"])
            self._last_checkpoint_step = int(state["last_checkpoint_step"])
            self.replay.sampler_state = state["replay_rng"]
            self._acting = dict(state["acting"])

    def online_state(self) -> dict[str, Any]:
        """The trainer's entries of a checkpoint: counters, acting's and the replay sampler's random states, and the
        running episodes (each environment's episode seed and actions so far, its latent state and last frame)
        unless none runs or they were cut. With the agent's weights and the global random state, what
        :meth:`resume` continues from exactly."""
        self._finish_update()
        state: dict[str, Any] = {
            "steps": self.steps,
            "episodes": self.writer.num_episodes,
            "updates": self.updates,
            "skipped_updates": self._skipped_updates,
            "last_eval": self.last_eval,
            "last_eval_step": self.last_eval_step,
            "last_checkpoint_step": self._last_checkpoint_step,
            "act_rng": self.act_rng.get_state(),
            "replay_rng": self.replay.sampler_state,
            METRICS_MARK: self.logger.mark(),
        }
        if self._venv is not None and self._obs is not None and not self._cut:
            size = self.spec.action_size
            state["acting"] = {
                "seeds": [int(seed) for seed in self._venv.get_attr("episode_seed")],
                "actions": [
                    torch.as_tensor(np.asarray(a, np.float32).reshape(len(a), size)) for a in self._episode_actions
                ],
                "obs": torch.as_tensor(self._obs),
                "is_first": torch.as_tensor(self._is_first),
                "is_last": torch.as_tensor(self._is_last),
                "latent": self._state,
            }
        elif self._acting is not None:  # restored and not yet made again: still the checkpoint's
            state["acting"] = self._acting
        return state

    def save(self) -> None:
        online = self.online_state()
        state = {**run_state(CHECKPOINT_KIND, self.task, self.config, self.agent), **online}
        if self.checkpoint_extra is not None:
            state.update(self.checkpoint_extra())
        with self.phase.saving(self.updates):
            save_checkpoint(self.checkpoint_path, state)

    # -- the loop --------------------------------------------------------------------------------------------------
    def run(
        self, *, max_steps: int, stop_return: float | None = None, progress: bool = True, cut_episodes: bool = True
    ) -> OnlineResult:
        """Step, record and train until ``max_steps`` steps are taken or evaluation reaches ``stop_return``: after
        each step the updates due by then (:meth:`updates_due`), then its log, evaluation and checkpoint.

        ``cut_episodes`` (collection): stop at exactly ``max_steps`` rows, ending the running episodes there as
        time limits. Without it (CoWorld's source pretraining) the call stops once ``max_steps`` is reached (at
        most ``envs - 1`` steps later) and the running episodes continue in the next call, so the phase boundary
        leaves no mark in the data.
        """
        reason = "max steps"
        with self.acting(total=max_steps, progress=progress):
            if stop_return is not None and self.last_eval is not None and self.last_eval >= stop_return:
                max_steps = self.steps  # a resumed run that had already reached its goal does not go on
                reason = f"evaluation return {self.last_eval:.1f} reached {stop_return:.1f}"
            while self.steps < max_steps:
                self.step(max_steps if cut_episodes else None)
                self._train_due()
                if self.settle(stop_return):
                    reason = f"evaluation return {self.last_eval:.1f} reached {stop_return:.1f}"
                    break
        self.save()
        return OnlineResult(self.steps, self.updates, self.writer.num_episodes, self.last_eval, reason)

    @contextmanager
    def acting(self, *, total: int = 0, progress: bool = False) -> Iterator[None]:
        """Where :meth:`step`, :meth:`act`, :meth:`sample` and :meth:`update` are called: the environments made (or
        the running episodes a checkpoint held made again) on entry; on exit the last step settled, the running
        update waited for and the log window's metrics written (a stop by an error or a signal gives the running
        update a few seconds to end). The environments stay open, so the next call continues the running
        episodes (CoWorld's source phases). ``total``: the progress bar's length in environment steps."""
        self._start_acting()
        bar = progress_bar(
            total=total, initial=min(self.steps, total), desc=self.task, unit="env steps", enabled=progress
        )
        self._window = window = Window(bar, Rate(self.updates), Rate(self.steps), last_log=self.steps)
        try:
            yield
            self.settle()
            self._finish_update()
            window.metrics.update(self._take_unlogged())
        finally:
            bar.close()
            self._window = None
            if self._updates.pending:  # stopped by an error or a signal: let the running update end, briefly
                self._updates.abandon(STOP_WAIT_SECONDS)
        if window.metrics:  # what the last log_every window had not written yet
            self.logger.log(window.metrics, self.steps, unit=self.step_unit)

    def act(self) -> None:
        """Step the environments until an update falls due (no step where one is due already): the source agent's
        interaction between two of CoWorld's source updates, at the train ratio (:meth:`updates_due`). Each step
        is settled (:meth:`settle`) once the updates due after it are made."""
        while not self.update_due():
            self.settle()
            self.step()

    def update_due(self) -> bool:
        """An update is due: fewer have been made than :meth:`updates_due` says by now (the missed ones skipped),
        and the replay holds a finished episode to sample from."""
        if self.steps < self.config.train.prefill or not self.replay.episodes:
            return False
        return self.updates < self.updates_due(self.steps) - self._skipped_updates

    def sample(self) -> Mapping[str, np.ndarray]:
        """A batch ``(B, T, ...)`` of the replay as it is now, once the update before has ended."""
        self._finish_update()
        cfg = self.config.train
        return self.replay.sample(cfg.batch_size, cfg.seq_len)

    def update(self, train: Callable[..., dict[str, float]], *args: Any) -> None:
        """Make one update, ``train(*args)``; beside learning it is left running while the agent acts, and the next
        :meth:`sample` (or evaluation, checkpoint, end of :meth:`acting`) waits for it."""
        self._updates.start(train, *args)
        self.updates += 1
        if not self.background:
            self._finish_update()

    def step(self, max_steps: int | None = None) -> None:
        """One step of every environment with the acting policy, each recorded in the replay and, once its episode
        ends, in the dataset. ``max_steps``: the run ends at exactly that many rows, the running episodes ending
        there (stored as time limits); None: every environment's step is kept and the episodes run on."""
        cfg, n = self.config.train, self.config.train.envs
        window = self._open_window()
        interrupt.check()
        mode = "random" if self.steps < cfg.prefill else "train"
        # The agent adds its own exploration noise (train.expl_noise), so the action the latent conditions on is
        # the one executed; during the prefill it still filters the latent, so the first trained action continues
        # the running episode's state rather than restarting it mid-episode.
        action, self._state = self._actor.policy(
            self._obs,
            self._state,
            mode=mode,
            is_first=self._is_first,
            generator=self.act_rng if self.background else None,
        )
        action = action.astype(np.float32)
        self.phase.check_actions(action, self.steps + 1, self.step_unit.replace("_", " "))
        obs, reward, terminated, truncated, info = self._venv.step(action)
        keep = n if max_steps is None else min(n, max_steps - self.steps)
        final = max_steps is not None and self.steps + keep >= max_steps
        self._cut |= final
        ended = False
        for i in range(n):
            if self._is_last[i]:  # NEXT_STEP autoreset: this step only reset env i; obs[i] is o_0
                self._record(i, obs[i], np.zeros_like(action[i]), 0.0, True, False, False)
                self._is_first[i] = True  # the next action starts a new latent from o_0, and only there
                continue
            self._is_first[i] = False
            if i >= keep:
                continue
            success = float(info["success"][i]) if "success" in info else None
            last = bool(terminated[i] or truncated[i]) or final
            ended |= self._record(i, obs[i], action[i], float(reward[i]), False, last, bool(terminated[i]), success)
            self.steps += 1
            window.bar.update(1)
        self._obs = obs
        window.unsettled, window.ended = True, ended

    def settle(self, stop_return: float | None = None) -> bool:
        """What follows the last step once the updates due after it are made (nothing if it is settled): the log
        window's record when ``train.log_every`` steps have passed, and, where the step ended an episode, an
        evaluation when ``train.eval_every`` steps have passed and a checkpoint when ``train.checkpoint_every``
        have. Returns True when that evaluation reached ``stop_return`` (the checkpoint then left to the caller)."""
        cfg, window = self.config.train, self._open_window()
        if not window.unsettled:
            return False
        window.unsettled = False
        window.metrics.update(self._take_unlogged())
        if self.steps - window.last_log >= cfg.log_every and window.metrics:
            # Rates over this log window, evaluation and checkpoint time included.
            window.metrics[f"{self.prefix}perf/updates_per_s"] = window.update_rate(self.updates)
            window.metrics[f"{self.prefix}perf/steps_per_s"] = window.step_rate(self.steps)
            window.bar.set_postfix(self._bar_info(window.metrics[f"{self.prefix}perf/updates_per_s"]))
            self.logger.log(window.metrics, self.steps, unit=self.step_unit)
            window.metrics, window.last_log = {}, self.steps
        if not window.ended:
            return False
        if self.steps >= cfg.prefill and self.steps - self.last_eval_step >= cfg.eval_every:
            self._evaluate()
            window.bar.set_postfix(self._bar_info())
            if stop_return is not None and self.last_eval >= stop_return:
                return True
        if self.steps - self._last_checkpoint_step >= cfg.checkpoint_every:
            self._last_checkpoint_step = self.steps
            self.save()
        return False

    def close(self) -> None:
        if self._venv is not None:
            self._venv.close()
            self._venv = None

    # -- pieces ----------------------------------------------------------------------------------------------------
    def _start_acting(self) -> None:
        """The environments and the acting policy as :meth:`acting` needs them: made on the first call (with a
        checkpoint's running episodes made again, or new ones started), the missed updates of a resume skipped, the
        policy copy given the agent's weights (which may have been loaded since the last call)."""
        n = self.config.train.envs
        if self._venv is None:
            # beside learning, the environments step in worker processes: this process's other thread is learning
            workers = True if self.background else None
            self._venv = envs.make_vector(self.task, n, seed=self.config.seed + self.steps, workers=workers)
            self._obs = None
            if self._acting is not None:
                self._replay_episodes(self._acting)
            self._acting = None
        if self._obs is None:
            self._obs, _ = self._venv.reset(seed=[self.config.seed + self.steps + i for i in range(n)])
            self._state = None
            self._is_first = np.ones(n, dtype=bool)
            self._running_success = [[] for _ in range(n)]
            for i in range(n):
                self._record(i, self._obs[i], np.zeros(self.spec.action_size, np.float32), 0.0, True, False, False)
        self._skip_missed_updates()
        if self._actor is None:
            self._actor = self.agent.policy_copy() if self.background else self.agent
        elif self._actor is not self.agent:
            self._actor.sync()

    def _open_window(self) -> Window:
        if self._window is None:
            raise RuntimeError("step, act and settle run inside `with trainer.acting():`")
        return self._window

    def _record(
        self,
        i: int,
        image: np.ndarray,
        action: np.ndarray,
        reward: float,
        is_first: bool,
        is_last: bool,
        is_terminal: bool,
        success: float | None = None,
    ) -> bool:
        """Add one step of env ``i``; write the episode when it ends. Returns True when it ended one."""
        self._is_last[i] = is_last
        self._note_step(i, action, is_first, success)
        episode = self.replay.add_step(i, replay_step(image, action, reward, is_first, is_last, is_terminal))
        if episode is None:
            return False
        infos = {"success": np.asarray(self._running_success[i], np.float32)} if self._running_success[i] else None
        self.writer.add_episode(
            observations=episode["image"],
            actions=episode["action"][1:],
            rewards=episode["reward"][1:],
            terminated=bool(episode["is_terminal"][-1]),
            infos=infos,
        )
        return True

    def _note_step(self, i: int, action: np.ndarray, is_first: bool, success: float | None) -> None:
        """What env ``i``'s running episode keeps beside the replay: its actions and successes so far."""
        if is_first:
            self._episode_actions[i], self._running_success[i] = [], []
            return
        self._episode_actions[i].append(action)
        if success is not None:
            self._running_success[i].append(success)

    def _replay_episodes(self, acting: Mapping[str, Any]) -> None:
        """Make a checkpoint's running episodes again (``acting``, :meth:`online_state`): each environment reset
        with its episode's seed and stepped with its actions, the steps of the episodes still running added to the
        replay as they were first; then the latent state, flags and frames the checkpoint held. The environments
        step together, so their episodes, of one length and started together, have run as many steps."""
        actions = [host(a).astype(np.float32) for a in acting["actions"]]
        n, is_last = len(actions), host(acting["is_last"]).astype(bool)
        if n != self.config.train.envs or len({len(a) for a in actions}) != 1:
            warnings.warn(
                f"{self.task}: the checkpoint's running episodes do not fit {self.config.train.envs} "
                "environments stepping together; new episodes start",
                stacklevel=2,
            )
            return
        obs, _ = self._venv.reset(seed=[int(seed) for seed in acting["seeds"]])
        zero = np.zeros(self.spec.action_size, np.float32)
        for i in range(n):
            self._note_step(i, zero, True, None)
            if not is_last[i]:
                self.replay.add_step(i, replay_step(obs[i], zero, 0.0, True, False, False))
        for t in range(len(actions[0])):
            step = np.stack([a[t] for a in actions])
            obs, reward, _, _, info = self._venv.step(step)
            for i in range(n):
                success = float(info["success"][i]) if "success" in info else None
                self._note_step(i, step[i], False, success)
                if not is_last[i]:
                    self.replay.add_step(i, replay_step(obs[i], step[i], float(reward[i]), False, False, False))
        if not np.array_equal(obs, host(acting["obs"])):
            warnings.warn(
                f"{self.task}: replayed from their seeds and actions, the running episodes reach other "
                "frames than the checkpoint's (another simulator build?); they go on from the replayed "
                "ones",
                stacklevel=2,
            )
        self._obs, self._state = obs, acting["latent"]
        self._is_first = host(acting["is_first"]).astype(bool)
        self._is_last = is_last.copy()

    def _bar_info(self, updates_per_s: float | None = None) -> dict[str, str]:
        """The progress bar's postfix: updates, updates/s over the last log window, last evaluation return."""
        if updates_per_s is not None:
            self._updates_per_s = updates_per_s
        info = {"updates": f"{self.updates:,}"}
        if self._updates_per_s is not None:
            info["updates/s"] = f"{self._updates_per_s:.1f}"
        if self.last_eval is not None:
            info["eval_return"] = f"{self.last_eval:.1f}"
        return info

    def updates_due(self, steps: int) -> int:
        """Updates an uninterrupted run has made after ``steps`` environment steps: none during the random
        prefill; at the end of it ``train.pretrain_updates`` extra ones (DreamerV2's ``pretrain``) plus the
        first regular one; then one every ``train.train_every`` steps."""
        cfg = self.config.train
        if steps < cfg.prefill:
            return 0
        return cfg.pretrain_updates + (steps - cfg.prefill) // cfg.train_every + 1

    def _skip_missed_updates(self) -> None:
        """Keep the train ratio from here on instead of catching up.

        After a resume the agent comes from its last checkpoint, while the steps recorded after that checkpoint
        stay in the replay; the updates made in between were lost with the process. Catching them up would be a
        burst of updates with no environment step between them, which an uninterrupted run never makes. So the
        missed updates are skipped: updates and steps interleave at ``train_every`` from the restored state on.
        In an uninterrupted run (and between CoWorld's phases) nothing is missed and this changes nothing.
        """
        missed = self.updates_due(self.steps) - self._skipped_updates - self.updates
        if missed > 0:
            self._skipped_updates += missed

    def _train_due(self) -> None:
        """Make the updates due by now, each on a batch of the replay as it is now, after the one before ends.
        Beside learning the last one is left running."""
        while self.update_due():
            self.update(self.train, self.sample())

    def _finish_update(self) -> None:
        """Wait for the running update, if any; the policy copy then takes its weights, and its metrics wait in
        :attr:`_unlogged` for the run loop's log."""
        result = self._updates.wait()
        if result is None:
            return
        if self._actor is not None and self._actor is not self.agent:
            self._actor.sync()
        self._unlogged = {f"{self.prefix}{k}": v for k, v in result.items()}
        self.phase.check(self._unlogged, self.updates)

    def _take_unlogged(self) -> dict[str, float]:
        """The metrics :attr:`_unlogged` holds, which it then forgets."""
        unlogged, self._unlogged = self._unlogged, {}
        return unlogged

    def _evaluate(self) -> None:
        self._finish_update()
        cfg = self.config.train
        result, _ = evaluate(
            self.agent,
            self.task,
            episodes=cfg.eval_episodes,
            workers=min(cfg.envs, cfg.eval_episodes),
            seed=self.config.seed + 10_000,
        )
        self.last_eval, self.last_eval_step = result.mean, self.steps
        self.writer.update_metadata(last_eval_return=result.mean, last_eval_step=self.steps)
        metrics = result.metrics(self.prefix)
        self.logger.log(metrics, self.steps, unit=self.step_unit)
        log_open_loop(
            self.logger,
            self.agent,
            self.replay.episodes,
            self.steps,
            tag=f"{self.prefix}openl/{self.task}",
            unit=self.step_unit,
        )


def source_replay_writer(logdir: str | Path, source: str, *, algorithm: str, seed: int) -> DatasetWriter:
    """The dataset that records a two-phase run's online source experience (``<logdir>/source_replay.h5``),
    resumed when it exists; ``algorithm`` names the run's algorithm in its collector metadata."""
    return DatasetWriter(
        Path(logdir) / "source_replay.h5",
        task=source,
        env_config={"task": source},
        quality="medium-replay",
        collector={"algorithm": f"{algorithm}-source", "seed": seed},
        action_size=envs.task_spec(source).action_size,
        resume=True,
    )


def make_source_trainer(
    agent: Any,
    source: str,
    *,
    config: Config,
    logdir: str | Path,
    writer: DatasetWriter,
    logger: Logger,
    phase: Phase,
    train: Callable[..., dict[str, float]] | None = None,
    checkpoint_extra: Callable[[], dict[str, Any]] | None = None,
) -> OnlineTrainer:
    """The online trainer of a two-phase run's source agent (CoWorld's, a fine-tuned DreamerV2's), updated by
    ``train`` (None: the agent's own): its checkpoint in ``<logdir>/source`` (with ``checkpoint_extra()``'s
    entries), its metrics and step unit marked ``source``, checked as ``phase`` (:func:`source_phase`)."""
    return OnlineTrainer(
        agent=agent,
        task=source,
        config=config,
        logdir=Path(logdir) / "source",
        writer=writer,
        logger=logger,
        train=train,
        checkpoint_extra=checkpoint_extra,
        metric_prefix="source/",
        step_unit_prefix="source_",
        phase=phase,
    )


def source_phase(name: str, *, agent: str, kind: str, config: Config, logdir: str | Path) -> Phase:
    """The phase of a two-phase run's source agent learning online (``name``: ``source pretraining``, ...), its
    updates counted as source updates, a rerun starting from the source trainer's checkpoint in ``<logdir>/source``
    (:mod:`coworld.training.divergence`)."""
    resume_from = Path(logdir) / "source" / CHECKPOINT_NAME
    return Phase(name=name, agent=agent, unit="source update", kind=kind, config=config, resume_from=resume_from)


def pretrain_source(
    agent: Any,
    source: str,
    *,
    config: Config,
    logdir: str | Path,
    logger: Logger,
    algorithm: str,
    phase: Phase,
    train: Callable[..., dict[str, float]] | None = None,
    progress: bool = True,
    cut_episodes: bool = True,
) -> int:
    """A two-phase run's source agent (a fine-tuned DreamerV2, a candidate source of CoWorld's choice) trained online
    in ``source`` until ``coworld.pretrain_steps`` steps, recorded in ``<logdir>/source_replay.h5``; a stopped
    pretraining resumes from its last checkpoint with its replay cut back to it (:meth:`OnlineTrainer.restore`).
    ``phase``: what its checks call it (:func:`source_phase`); ``train``: its update (None: the agent's own). Returns
    the source environment steps taken."""
    writer = source_replay_writer(logdir, source, algorithm=algorithm, seed=config.seed)
    with writer:
        trainer = make_source_trainer(
            agent, source, config=config, logdir=logdir, writer=writer, logger=logger, phase=phase, train=train
        )
        try:
            trainer.restore(rollback=True)
            if trainer.steps < config.coworld.pretrain_steps or not trainer.checkpoint_path.exists():
                trainer.run(max_steps=config.coworld.pretrain_steps, progress=progress, cut_episodes=cut_episodes)
        finally:
            trainer.close()
    return trainer.steps
