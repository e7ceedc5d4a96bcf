"""What a sweep runs: a grid of runs (pairs x algorithms x seeds x variants), the named grids of the paper,
and the CPU-sized toy table.

A :class:`SweepSpec` is pure data. :meth:`SweepSpec.runs` lists its :class:`Run` s; the baselines (offline
DreamerV2, CURL, CURL+CQL) learn from the target dataset alone, so pairs that share a target share their baseline
runs. Every target task gets one dataset, made as :class:`DataSpec` says and shared by all runs on that target.

Named grids (:data:`TABLES`):

* ``dmc`` -- the paper's Table 1: the five DMC pairs it reports (walker walk -> downhill, uphill, nofoot; cheetah
  run -> downhill, nopaw), the four algorithms, 3 seeds, the ``paper`` preset, DreamerV2 medium-replay datasets.
* ``metaworld`` -- Table 2: its five Meta-World pairs, otherwise as ``dmc``.
* ``ablation`` -- Figure 4(a): CoWorld as configured and with each of its three terms switched off in turn
  (:data:`ABLATION`), offline DreamerV2 as the reference, on drawer close -> button press (the one ablation task
  the paper text names, its Figure 9(b)).
* ``toy`` -- the CPU-sized table: see :func:`toy_table`.
* ``toy-cpu`` -- the toy pair with a learned source and a medium-replay target: see :func:`toy_cpu_table`.
* ``toy-centre`` -- the same with the goal at the centre, where no constant action scores: :func:`toy_centre_table`.
* ``dmc-cpu`` -- walker_walk -> walker_uphill and cheetah_run -> cheetah_uphill with medium-replay targets, at the
  scale 2 CPU cores allow: :func:`dmc_cpu_table`.
* ``cap-study`` -- when Eq. 6's cap binds: ``dmc-cpu``'s cheetah pair with zeta 3 and 10, the later paper's
  settings, the target-policy cap, no alignment and 4x the target updates: :func:`cap_study_table`. Its two-hot
  critic met Eq. 6's term as a clamp, not the paper's push.
* ``cap-shift`` -- the cap study asked again with Eq. 6 as the paper means it: :func:`cap_shift_table`.
* ``dmc-mr`` and ``dmc-me`` -- the later CoWorld paper's (NeurIPS 2024) Tables 3 and 9: its six DMC pairs on
  medium-replay and medium-expert target datasets, with its Table 8 hyperparameters (:func:`later_table`);
  ``coworld report`` puts its published numbers (:mod:`coworld.report.paper`) beside ours.
* ``robodesk`` -- its Meta-World -> RoboDesk pairs, across action sizes: :func:`robodesk_table`.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from coworld import envs
from coworld.algorithms import ALGOS, algorithm, names
from coworld.budget import check_memory
from coworld.config import DREAMERV2_BEHAVIOUR, PRESETS, make_config, settings_overrides
from coworld.errors import ConfigError, CoworldError
from coworld.report import paper
from coworld.report.paper import PaperTable
from coworld.training.collect import TRAINED_QUALITIES as QUALITIES
from coworld.training.train import check_config, check_source, parse_sources

COLLECT_POLICIES = ("dreamerv2", "random")
SEED_MAX = 2**32 - 1
"""The largest seed, as every command takes it (``--seed``)."""
MAX_SEEDS = 1_000
"""The most seeds of one grid."""
MAX_COUNT = 10**9
"""The largest count of episodes or steps, the command line's bound (``coworld.commands.options.MAX_COUNT``)."""


def check_count(name: str, value: int, low: int = 1, high: int = MAX_COUNT) -> None:
    """Raise one ConfigError line unless ``value`` is a whole number in ``[low, high]``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{name} must be a whole number, got {value!r}")
    if not low <= value <= high:
        raise ConfigError(f"{name} must be in [{low}, {high:,}], got {value:,}")


@dataclass(frozen=True)
class DataSpec:
    """How the dataset of each target task is made: the options of one ``coworld collect``."""

    policy: str = "dreamerv2"
    """'dreamerv2' (DreamerV2 learns online and is recorded) or 'random' (uniform actions)."""
    quality: str = "medium-replay"
    """dreamerv2 only: medium-replay (the paper's), medium-expert (the later paper's Table 9), medium or expert."""
    episodes: int | None = None
    """Collect exactly this many episodes (random: required unless ``max_steps``)."""
    max_steps: int | None = None
    """Collect exactly this many steps (dreamerv2: at most, it also stops at its return goal)."""
    overrides: tuple[str, ...] = ()
    """dreamerv2 only: ``--set`` of the collector (the sweep's preset is its preset)."""
    seed: int = 0
    """Seed of the collection."""

    @property
    def label(self) -> str:
        """The dataset's name after the task: its quality."""
        return "random" if self.policy == "random" else self.quality

    def check(self) -> None:
        if self.policy not in COLLECT_POLICIES:
            raise ConfigError(f"data policy must be one of {', '.join(COLLECT_POLICIES)}, not {self.policy!r}")
        if self.policy == "dreamerv2" and self.quality not in QUALITIES:
            raise ConfigError(f"data quality must be one of {', '.join(QUALITIES)}, not {self.quality!r}")
        if self.policy == "random":
            if (self.episodes is None) == (self.max_steps is None):
                raise ConfigError("a random dataset needs exactly one of data episodes and data max_steps")
            if self.overrides:
                raise ConfigError("data set= overrides are for the dreamerv2 collector, not random collection")
        for name in ("episodes", "max_steps"):
            value = getattr(self, name)
            if value is not None:
                check_count(f"data {name}", value)
        check_count("data seed", self.seed, 0, SEED_MAX)
        for name in ("policy", "quality"):
            if not isinstance(getattr(self, name), str):
                raise ConfigError(f"data {name} must be a string, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class Run:
    """One training run of a sweep: an algorithm on a target (CoWorld also with its source), one seed."""

    algo: str
    source: str | None
    """The online source task of CoWorld and the fine-tuned DreamerV2; None for the other baselines."""
    target: str
    seed: int
    variant: str = ""
    """Name of the CoWorld variant ('' = as configured)."""

    @property
    def name(self) -> str:
        """Run folder name, e.g. ``coworld-no-align-toy_reach-toy_reach_shifted-s0`` or ``curl-walker_uphill-s1``."""
        algo = f"{self.algo}-{self.variant}" if self.variant else self.algo
        pair = f"{self.source}-{self.target}" if self.source else self.target
        return f"{algo}-{pair}-s{self.seed}"


@dataclass(frozen=True)
class SweepSpec:
    """A grid of runs and the settings every run shares. Saved as ``sweep.json`` in the sweep's folder."""

    pairs: tuple[tuple[str, str], ...]
    """(source, target) task pairs."""
    algos: tuple[str, ...] = ALGOS
    seeds: tuple[int, ...] = (0, 1, 2)
    variants: tuple[tuple[Any, ...], ...] = (("", ()),)
    """Variants: ``(name, config overrides)`` of CoWorld, or ``(name, overrides, algorithms)`` of the algorithms
    named; '' is CoWorld as configured. Every baseline also runs as configured."""
    preset: str = "paper"
    overrides: tuple[str, ...] = ()
    """``--set`` given to every training run."""
    data: DataSpec = field(default_factory=DataSpec)
    eval_episodes: int = 10
    """Episodes of the final evaluation of each run (the paper: 10)."""

    def check(self) -> SweepSpec:
        """Raise CoworldError with one line if anything in the grid is invalid; returns self."""
        if not self.pairs:
            raise CoworldError("the sweep has no pairs; pass --pairs SOURCE:TARGET[,...] or --table")
        if not self.algos:
            raise CoworldError(f"the sweep has no algorithms; choose from {', '.join(ALGOS)}")
        for algo in self.algos:
            if algo not in ALGOS:
                raise CoworldError(f"unknown algorithm {algo!r}; choose from {', '.join(ALGOS)}")
        for source, target in self.pairs:
            check_pair(source, target, self.algos)
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise CoworldError(f"seeds must be distinct and at least one, got {list(self.seeds)}")
        if len(self.seeds) > MAX_SEEDS:
            raise CoworldError(f"at most {MAX_SEEDS:,} seeds, got {len(self.seeds):,}")
        for seed in self.seeds:
            check_count("a seed", seed, 0, SEED_MAX)
        names = [name for name, *_ in self.variants]
        if not names or len(set(names)) != len(names):
            raise CoworldError(f"variant names must be distinct and at least one, got {names}")
        for name in names:
            if name and not name.replace("-", "").replace("_", "").isalnum():
                raise CoworldError(f"variant name {name!r}: use letters, digits, '-' and '_' only")
        for name, _, *algos in self.variants:
            unknown = [algo for algo in (algos[0] if algos else ()) if algo not in ALGOS]
            if unknown:
                raise CoworldError(
                    f"variant {name!r} names unknown algorithms {unknown}; choose from {', '.join(ALGOS)}"
                )
        check_count("eval episodes", self.eval_episodes)
        self.data.check()
        for _, extra, *_ in self.variants:  # every run's config must build (unknown keys, bad values)
            make_config(self.preset, [*self.overrides, *extra])
        for algo in self.algos:  # and pass what `train` requires of it (rules between keys, memory)
            for name in self.variants_of(algo):
                extra = self.variant_overrides(name)
                try:
                    config = make_config(self.preset, [*self.overrides, *extra])
                    for target in self.targets():
                        check_config(algo, config, envs.task_spec(target).action_size)
                except CoworldError as err:
                    raise ConfigError(f"the {algo}{f' ({name})' if name else ''} runs: {err}") from None
        if self.data.policy == "dreamerv2":  # and the collector's: the same preset with the data's own --set
            try:
                check_memory("dreamerv2", make_config(self.preset, self.data.overrides))
            except ConfigError as err:
                raise ConfigError(f"data set: {err}") from None
        return self

    def runs(self) -> list[Run]:
        """Every run, in a stable order: pair, algorithm, variant, seed; a baseline once per target."""
        runs: list[Run] = []
        seen: set[Run] = set()
        for source, target in self.pairs:
            for algo in self.algos:
                for variant in self.variants_of(algo):
                    for seed in self.seeds:
                        run = Run(algo, source if algorithm(algo).needs_source else None, target, seed, variant)
                        if run not in seen:
                            seen.add(run)
                            runs.append(run)
        return runs

    def targets(self) -> list[str]:
        """Target tasks, each once, in pair order (one dataset each)."""
        return list(dict.fromkeys(target for _, target in self.pairs))

    def variants_of(self, algo: str) -> list[str]:
        """The variant names ``algo`` runs in: CoWorld's those of two entries; every algorithm those naming it, and a
        baseline also ''."""
        default = names(collaborative=True)  # a variant naming no algorithm is CoWorld's
        named = [name for name, _, *algos in self.variants if algo in (algos[0] if algos else default)]
        return named if algorithm(algo).collaborative else list(dict.fromkeys(["", *named]))

    def variant_overrides(self, name: str) -> tuple[str, ...]:
        """The ``--set`` of variant ``name`` ('' as configured)."""
        return next((tuple(extra) for entry_name, extra, *_ in self.variants if entry_name == name), ())

    def run_overrides(self, run: Run) -> list[str]:
        """The ``--set`` of one run: the sweep's, then its variant's."""
        return [*self.overrides, *self.variant_overrides(run.variant)]

    def shared_pretraining(self) -> dict[str, tuple[Run, ...]]:
        """For each CoWorld run of one source, the other runs of the grid whose source pretraining is its own: its
        tasks and seed, a config apart only in the target phases' settings (:mod:`coworld.training.pretrained`)."""
        from coworld.training.pretrained import pretraining_difference

        runs = [
            run for run in self.runs() if algorithm(run.algo).collaborative and run.source and "+" not in run.source
        ]
        configs = {run: make_config(self.preset, [*self.run_overrides(run), f"seed={run.seed}"]) for run in runs}

        def shares(a: Run, b: Run) -> bool:
            same_place = (a.source, a.target, a.seed) == (b.source, b.target, b.seed)
            return a != b and same_place and not pretraining_difference(configs[a], configs[b])

        return {run.name: tuple(other for other in runs if shares(run, other)) for run in runs}

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SweepSpec:
        return cls(
            pairs=tuple((s, t) for s, t in data["pairs"]),
            algos=tuple(data["algos"]),
            seeds=tuple(int(s) for s in data["seeds"]),
            variants=tuple((entry[0], tuple(entry[1]), *(tuple(a) for a in entry[2:])) for entry in data["variants"]),
            preset=data["preset"],
            overrides=tuple(data["overrides"]),
            data=DataSpec(**{**data["data"], "overrides": tuple(data["data"]["overrides"])}),
            eval_episodes=int(data["eval_episodes"]),
        )


# -- the named grids ------------------------------------------------------------------------------------------------

TABLE1_PAIRS = (
    ("walker_walk", "walker_downhill"),
    ("walker_walk", "walker_uphill"),
    ("walker_walk", "walker_nofoot"),
    ("cheetah_run", "cheetah_downhill"),
    ("cheetah_run", "cheetah_nopaw"),
)
"""The five DMC pairs of the paper's Table 1 (cheetah run -> uphill is registered but not in the table)."""

TABLE2_PAIRS = (
    ("mw_window_close", "mw_door_close"),
    ("mw_handle_press", "mw_button_press_topdown"),
    ("mw_drawer_close", "mw_handle_press"),
    ("mw_drawer_close", "mw_button_press"),
    ("mw_stick_push", "mw_assembly"),
)
"""The five Meta-World pairs of the paper's Table 2."""

ABLATION: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("", ()),
    ("no-align", ("coworld.align=false",)),
    ("no-relabel", ("coworld.reward_relabel=false",)),
    ("no-value-reg", ("coworld.value_reg=false",)),
)
"""Figure 4(a): CoWorld as configured, then with each domain-collaborative term off in turn."""


def at_equal_cost(iterations: int, target_updates: int) -> tuple[str, ...]:
    """The ``offline`` schedule that gives the offline DreamerV2 family CoWorld's target updates (``iterations`` x
    ``target_updates``), evaluated and checkpointed once per iteration's worth: what every table sets beside CoWorld's
    schedule, so that they compare at equal cost."""
    every = f"{target_updates}"
    return (f"offline.updates={iterations * target_updates}", f"offline.eval_every={every}",
            f"offline.checkpoint_every={every}")  # fmt: skip


TOY_DATA = DataSpec(policy="random", episodes=20)
"""The toy target dataset: 20 episodes (1,000 steps) of uniform random actions in toy_reach_shifted."""

TOY_OVERRIDES = (
    "coworld.pretrain_steps=2000",
    "coworld.iterations=5",
    "coworld.target_updates=300",
    "coworld.source_updates=100",
    *at_equal_cost(5, 300),
    "offline.log_every=250",
    "train.eval_episodes=5",
    "offline.eval_episodes=5",
    "curl.updates=3000",
    "curl.eval_every=600",
    "curl.checkpoint_every=600",
    "curl.eval_episodes=5",
    "drqbc.updates=3000",
    "drqbc.std_updates=1500",
    "drqbc.eval_every=600",
    "drqbc.checkpoint_every=600",
    "drqbc.eval_episodes=5",
    "penalty.model_updates=750",
    "lompo.model_updates=750",
)
"""The toy schedule on the ``tiny`` preset (see :func:`toy_table`)."""


def toy_table() -> SweepSpec:
    """The CPU-sized table: toy_reach -> toy_reach_shifted, every algorithm, 3 seeds, ``tiny`` preset.

    Design. The target dataset is deliberately too poor to learn from alone: 20 episodes (1,000 steps) of uniform
    random actions in toy_reach_shifted, where the constant drift towards -x carries an aimless dot away from the
    goal (random return 2.3 against the scripted expert's 45.6), so the dataset barely shows the goal region or
    what reaching it is worth. The online source, toy_reach, has the same goal, reward and action meaning under
    other colours and without the drift; its agent, interacting, sees the goal region as often as it likes. So
    what an offline agent lacks is exactly what the source knows: CoWorld's alignment (Eq. 3) maps target frames
    into the source's latent space, its relabelled reward (Eqs. 4-5) and the source critic's cap on the target
    critic (Eq. 6) carry the source's values over.

    Size. Every algorithm gets the same target budget: 5 iterations of 300 target updates (1,500 updates), the
    offline DreamerV2, its variants and LOMPO the same 1,500 updates (V-D4RL's penalised one and LOMPO spend the
    first 750 on their world model, the fine-tuned ones first pretrain in the source as CoWorld's source does),
    CURL, CURL+CQL and DrQ+BC 3,000 of their cheaper updates. CoWorld's source pretrains for 2,000 environment
    steps and makes 100 updates per iteration. Each run ends with a 10-episode evaluation (the table's runs and their
    cost: benchmarks/archive/toy-tables.md).
    """
    return SweepSpec(
        pairs=(("toy_reach", "toy_reach_shifted"),),
        algos=ALGOS,
        seeds=(0, 1, 2),
        preset="tiny",
        overrides=TOY_OVERRIDES,
        data=TOY_DATA,
        eval_episodes=10,
    )


TOY_CPU_DATA = DataSpec(policy="dreamerv2", quality="medium-replay", max_steps=4000)
"""The ``toy-cpu`` target dataset: DreamerV2 (``cpu`` preset) learning online in toy_reach_shifted, everything it
experienced until its evaluation return reaches a third of the scripted expert's (or 4,000 steps)."""

TOY_CPU_OVERRIDES = tuple(
    f"{key}={PRESETS['tiny'][key]}"
    for section in ("curl", "drqbc")
    for key in (
        f"{section}.num_filters",
        f"{section}.num_layers",
        f"{section}.feature_dim",
        f"{section}.hidden",
        f"{section}.batch_size",
    )
) + (
    "curl.updates=3000",
    "curl.eval_every=1000",
    "curl.checkpoint_every=1000",
    "drqbc.updates=3000",
    "drqbc.std_updates=1500",
    "drqbc.eval_every=1000",
    "drqbc.checkpoint_every=1000",
    "penalty.model_updates=1000",
    "penalty.ensemble=3",
    "lompo.model_updates=1000",
    "lompo.ensemble=3",
)
"""The ``toy-cpu`` schedule on the ``cpu`` preset: its world-model agents as the preset has them (source pretrain
4,000 env steps, 4 iterations of 500 target updates); the model-free baselines at the ``toy`` table's sizes, networks
and batch (32 transitions: the ``cpu`` preset's 512, the paper's, made a CURL run on these small networks many
times longer; benchmarks/archive/toy-tables.md)."""


def toy_cpu_table() -> SweepSpec:
    """The toy pair with agents that learn: ``cpu`` preset, a source that reads the dot online (45.4-46.1 on
    seeds 0-3 at 3,500 steps), and a medium-replay target dataset collected the way the paper makes its datasets
    (:data:`TOY_CPU_DATA`).

    Where :func:`toy_table` tests the pipeline with agents that learn little, this table is the transfer result: on
    the ``cpu`` preset DreamerV2 reads the dot in toy_reach (benchmarks/RESULTS.md, "The `cpu` preset on
    toy_reach"), so CoWorld's source knows what the goal is worth.
    """
    return dataclasses.replace(
        toy_table(), preset="cpu", overrides=TOY_CPU_OVERRIDES, data=TOY_CPU_DATA, eval_episodes=20
    )


TOY_CENTRE = ("toy_reach_centre", "toy_reach_centre_shifted")


def toy_centre_table() -> SweepSpec:
    """The centre pair on the ``toy-cpu`` schedule: CoWorld, offline DreamerV2, CURL and CURL+CQL, 3 seeds.

    On the corner pair a constant push towards the goal scores two thirds of the expert's return, above the medium
    level, so a dataset collected by an agent that stopped there shows little beyond that constant (its best
    episodes score about the constant's mean), and every method can score by direction alone. With the goal at the
    centre no constant direction scores (the best of 16: 10.4 in toy_reach_centre_shifted, random 18.3, expert
    48.4): the target dataset's medium level is a third of the way from random to the expert (28.3), and returns
    above random need the dot read from the frame.
    """
    return dataclasses.replace(toy_cpu_table(), pairs=(TOY_CENTRE,), algos=("coworld", "dreamerv2", "curl", "curl-cql"))


DMC_CPU_DATA = DataSpec(
    policy="dreamerv2",
    quality="medium-replay",
    max_steps=60_000,
    overrides=("train.eval_every=2000", "train.eval_episodes=5"),
)
"""The ``dmc-cpu`` target dataset: the ``cpu`` preset's DreamerV2 learning online in the target, everything it
experienced until it reached the paper's medium level or 60,000 env steps (on 2 CPU cores the cut comes first on
walker_uphill and cheetah_uphill: the dataset's ``collector.stop_reason`` says "max steps")."""

DMC_CPU_OVERRIDES = (
    # the source: pretrained as long as the pilot's walker_walk needed to pass a sixth of DreamerV2's score
    "coworld.pretrain_steps=20000",
    # Alg. 1 with Table 3's K1:K2 = 5:2, 8 alternations: 10,000 target and 4,000 source updates in all
    "coworld.iterations=8",
    "coworld.target_updates=1250",
    "coworld.source_updates=500",
    "coworld.eval_every=1",
    *at_equal_cost(8, 1250),
    # online evaluation every 5,000 env steps (the preset's 1,000 x 10 episodes would out-step the training)
    "train.eval_every=5000",
    "train.eval_episodes=5",
    "offline.eval_episodes=5",
    # DrQ+BC: V-D4RL's networks; batches of 64 transitions, so its 20,000 updates sample the 1.28M frames the
    # world-model agents' 10,000 batches of 8 x 16 do; its exploration std falls over the first quarter, as
    # V-D4RL's 125,000 of 550,000 updates
    "drqbc.batch_size=64",
    "drqbc.updates=20000",
    "drqbc.std_updates=5000",
    "drqbc.eval_every=2500",
    "drqbc.eval_episodes=5",
    "drqbc.checkpoint_every=2500",
    "drqbc.log_every=500",
)
"""The ``dmc-cpu`` schedule on the ``cpu`` preset (see :func:`dmc_cpu_table`)."""


def dmc_cpu_table() -> SweepSpec:
    """The paper's kind of pair at the scale 2 CPU cores allow: walker_walk -> walker_uphill and cheetah_run ->
    cheetah_uphill (the later paper's largest gap over offline DreamerV2: 225 against 3), ``cpu`` preset.

    The four algorithms of the later paper's DMC table that fit: CoWorld, offline DreamerV2, DreamerV2 fine-tuned
    from the source, DrQ+BC; 3 seeds; the final evaluation over the paper's 10 episodes. Table 3's schedule
    scaled down (:data:`DMC_CPU_OVERRIDES`): every agent gets 10,000 target updates (the paper 8 x 50,000), CoWorld
    and the fine-tuned DreamerV2 first pretrain their own source agent for 20,000 env steps with the run's seed,
    CoWorld then alternates 1,250 target with 500 source updates 8 times, DrQ+BC makes 20,000 updates of 64
    transitions. The source pretraining is not shared between the runs of a seed: each two-phase run makes its
    own, with the same budget. The dataset: :data:`DMC_CPU_DATA`.
    """
    return SweepSpec(
        pairs=(("walker_walk", "walker_uphill"), ("cheetah_run", "cheetah_uphill")),
        algos=("coworld", "dreamerv2", "dreamerv2-finetune", "drq-bc"),
        seeds=(0, 1, 2),
        preset="cpu",
        overrides=DMC_CPU_OVERRIDES,
        data=DMC_CPU_DATA,
        eval_episodes=10,
    )


CAP_STUDY_VARIANTS: tuple[tuple[Any, ...], ...] = (
    ("", ()),
    ("zeta3", ("coworld.zeta=3",)),
    ("zeta10", ("coworld.zeta=10",)),
    ("later-dmc", settings_overrides("later-dmc")),
    ("target-policy", ("coworld.cap_critic=target_policy",)),
    ("no-align", ("coworld.align=false",)),
    ("no-align-no-cap", ("coworld.align=false", "coworld.value_reg=false")),
    ("4x", ("coworld.target_updates=5000", *at_equal_cost(8, 5000)), ("coworld", "dreamerv2")),
)
"""The arms of :func:`cap_study_table`: CoWorld as Table 3 gives it (zeta 1), with zeta 3 and 10, with the later
paper's DMC settings, with the target-policy critic as its cap, without Eq. 3's alignment (where the cap does not
bind, the alignment is the only way the source agent reaches the target agent's training: this arm tells what of a
difference from offline DreamerV2 is the alignment's), without the alignment and the cap (the control: its target
agent's updates are offline DreamerV2's, so what separates it from offline DreamerV2 is CoWorld's loop alone, and
what separates the other arms from it is their terms); CoWorld and offline DreamerV2 with 4x the target updates
(5,000 per iteration, 40,000 in all)."""


def cap_study_table() -> SweepSpec:
    """When does CoWorld's value cap bind? ``dmc-cpu``'s cheetah_run -> cheetah_uphill (its schedule, its
    dataset, the ``cpu`` preset, 3 seeds, 10 evaluation episodes) with the arms of :data:`CAP_STUDY_VARIANTS`, beside
    offline DreamerV2 and V-D4RL's penalised DreamerV2 (the later paper's "Offline DV2"; its ensemble learns alone
    for the first quarter of the updates, as the ``tiny`` preset's does).

    Eq. 6's term is read on the two-hot critic's mean (``coworld.cap_form=on_mean``), the form the committed study
    ran: there it clamps the critic at the cap rather than pushing it ``alpha * zeta`` down (:func:`cap_shift_table`
    asks again with the paper's push).
    """
    return SweepSpec(
        pairs=(("cheetah_run", "cheetah_uphill"),),
        algos=("coworld", "dreamerv2", "dreamerv2-penalty"),
        seeds=(0, 1, 2),
        variants=CAP_STUDY_VARIANTS,
        preset="cpu",
        overrides=(*DMC_CPU_OVERRIDES, "penalty.model_updates=2500", "coworld.cap_form=on_mean"),
        data=DMC_CPU_DATA,
        eval_episodes=10,
    )


CAP_SHIFT_VARIANTS: tuple[tuple[Any, ...], ...] = (
    ("no-align", ("coworld.align=false",)),
    ("no-align-no-cap", ("coworld.align=false", "coworld.value_reg=false")),
    ("", ()),
    ("later-dmc", settings_overrides("later-dmc")),
    ("no-align-clamp", ("coworld.align=false", "coworld.cap_form=on_mean")),
    ("dv2", tuple(f"{key}={value}" for key, value in DREAMERV2_BEHAVIOUR.items()), ("dreamerv2",)),
)
"""The arms of :func:`cap_shift_table`, in the order they run: CoWorld without the alignment under Eq. 6 as the
paper means it (``coworld.cap_form='shift'``, the default), its control without the cap, CoWorld whole, CoWorld at the
later paper's DMC settings, the no-alignment arm under the clamp the cap study ran (``cap_form='on_mean'``), and
offline DreamerV2 at the ``cpu-dv2`` preset's behaviour (a Gaussian critic with a slow target, a Gaussian reward
head, no return normalisation), which tells whether CoWorld's arms at that behaviour are worth running."""


def cap_shift_table() -> SweepSpec:
    """The cap study asked again with Eq. 6 as the paper means it on the ``cpu`` preset's two-hot critic: the cap
    study's pair, dataset, schedule, seeds and evaluation (:func:`cap_study_table`), the arms of
    :data:`CAP_SHIFT_VARIANTS` beside offline DreamerV2.

    Each arm pairs with the control of its seed: the CoWorld runs of a seed share one source pretraining and draw
    the same target batches and random numbers, so they differ only in their terms. The control and the clamp run
    again here rather than being taken from the cap study, because runs pair only on one kind of machine: the same
    command's floats differ between processors from the first logged update (docs/reproducing.md).
    """
    return SweepSpec(
        pairs=(("cheetah_run", "cheetah_uphill"),),
        algos=("coworld", "dreamerv2"),
        seeds=(0, 1, 2),
        variants=CAP_SHIFT_VARIANTS,
        preset="cpu",
        overrides=DMC_CPU_OVERRIDES,
        data=DMC_CPU_DATA,
        eval_episodes=10,
    )


LATER_EXTRA_ALGOS = ("dreamerv2", "dreamerv2-finetune-ewc")
"""Run beside the later paper's columns in its tables, with no published number of its own there: offline DreamerV2
without V-D4RL's penalty (the seed paper's baseline and every other table's reference) and the EWC fine-tuning (the
later paper reports it on Meta-World only)."""

LATER_DMC_OVERRIDES = (
    *settings_overrides("later-dmc"),
    "coworld.target_updates=20000",
    "coworld.source_updates=20000",
    *at_equal_cost(8, 20000),
)
"""The later paper's Table 8, DMC column, on the ``paper`` preset: its settings (``+later-dmc``: beta2 1.5, k 0.9 in
its Eq. 4, alpha 1, Eq. 5's eta from 1 to 0.1) and 2e4 target and 2e4 source updates per iteration."""

LATER_ROBODESK_OVERRIDES = settings_overrides("later-metaworld")
"""Table 8, Meta-World / RoboDesk column (``+later-metaworld``: beta2 1, k 0.3 in its Eq. 4, alpha 2), with 5e4 target
and 2e4 source updates per iteration (the ``paper`` preset's)."""


def later_table(table: PaperTable, overrides: tuple[str, ...]) -> SweepSpec:
    """One of the later CoWorld paper's tables (:mod:`coworld.report.paper`) as a grid: its pairs, our algorithms
    its columns map to plus :data:`LATER_EXTRA_ALGOS`, 3 seeds, 10 evaluation episodes, the ``paper`` preset with its
    Table 8 hyperparameters, target datasets collected by DreamerV2 at the table's quality.

    An algorithm joins a table where :attr:`~coworld.report.paper.PaperTable.columns` maps a column to it.
    """
    return SweepSpec(
        pairs=table.pairs,
        algos=(*table.algos(), *LATER_EXTRA_ALGOS),
        seeds=(0, 1, 2),
        preset="paper",
        overrides=overrides,
        data=DataSpec(policy="dreamerv2", quality=table.quality),
        eval_episodes=10,
    )


def dmc_medium_replay_table() -> SweepSpec:
    """The later paper's Table 3: the six DMC pairs (Table 1's five and cheetah run -> uphill), medium-replay."""
    return later_table(paper.DMC_MEDIUM_REPLAY, LATER_DMC_OVERRIDES)


def dmc_medium_expert_table() -> SweepSpec:
    """Its Table 9: the same pairs with medium-expert target datasets (``coworld collect --quality medium-expert``)."""
    return later_table(paper.DMC_MEDIUM_EXPERT, LATER_DMC_OVERRIDES)


def robodesk_table() -> SweepSpec:
    """Its Figure 4: Meta-World sources, RoboDesk targets (4-D against 5-D actions), medium-replay.

    Without the two DreamerV2 fine-tunings: they carry the source agent's networks over to the target, which needs
    one action size (:func:`coworld.training.train.check_source`).
    """
    spec = later_table(paper.META_WORLD_TO_ROBODESK, LATER_ROBODESK_OVERRIDES)
    one_size = ("dreamerv2-finetune", "dreamerv2-finetune-ewc")
    return dataclasses.replace(spec, algos=tuple(a for a in spec.algos if a not in one_size))


TABLES: dict[str, Any] = {
    "toy": toy_table,
    "toy-cpu": toy_cpu_table,
    "toy-centre": toy_centre_table,
    "dmc-cpu": dmc_cpu_table,
    "cap-study": cap_study_table,
    "cap-shift": cap_shift_table,
    "dmc": lambda: SweepSpec(pairs=TABLE1_PAIRS),
    "metaworld": lambda: SweepSpec(pairs=TABLE2_PAIRS),
    "dmc-mr": dmc_medium_replay_table,
    "dmc-me": dmc_medium_expert_table,
    "robodesk": robodesk_table,
    "ablation": lambda: SweepSpec(
        pairs=(("mw_drawer_close", "mw_button_press"),), algos=("coworld", "dreamerv2"), variants=ABLATION
    ),
}
"""Named grids: name -> function returning its :class:`SweepSpec`."""


def named_table(name: str) -> SweepSpec:
    if name not in TABLES:
        raise CoworldError(f"unknown table {name!r}; choose from {', '.join(TABLES)}")
    return TABLES[name]()


# -- grids from the command line and TOML files ---------------------------------------------------------------------


def check_pair(source: str, target: str, algos: Sequence[str]) -> None:
    """A pair the grid's algorithms can serve (one CoworldError line otherwise): its source is one task or several
    joined by ``+`` (CoWorld's automatic source choice), each known, none twice and none the target itself; CoWorld
    takes any action sizes, a fine-tuned DreamerV2 one source of the target's
    (:func:`coworld.training.train.check_source`)."""
    try:
        sources = parse_sources(source)
        envs.task_spec(target)
        if target in sources:
            raise CoworldError(f"source {target} is the target itself; pair the target with another domain")
        for algo in (a for a in algos if algorithm(a).needs_source):
            if len(sources) > 1 and algorithm(algo).source != "any":
                raise CoworldError(
                    f"{algo} takes one source; several ({source}) are CoWorld's automatic source choice: drop {algo}"
                    " from --algos or give this pair one source"
                )
            for name in sources:
                check_source(algo, name, target)
    except CoworldError as err:
        raise CoworldError(f"pair {source}:{target}: {err}") from None


def parse_pairs(text: str) -> tuple[tuple[str, str], ...]:
    """``"a:b,c:d"`` -> ``(("a", "b"), ("c", "d"))``; ``"a+b:c"``: CoWorld choosing between sources a and b for
    target c (:mod:`coworld.training.multi_source`). Task names are checked; an empty pair (``"a:b,"``) is refused, as
    ``train --source`` refuses an empty name."""
    if not text.strip():
        raise CoworldError("--pairs is empty; write SOURCE:TARGET[,SOURCE:TARGET...]")
    pairs = []
    for item in (part.strip() for part in text.split(",")):
        if not item:
            raise CoworldError(f"--pairs {text!r} has an empty pair; write SOURCE:TARGET[,SOURCE:TARGET...]")
        source, sep, target = item.partition(":")
        if not sep or not source or not target:
            raise CoworldError(
                f"bad pair {item!r}: write SOURCE:TARGET (or SOURCE+SOURCE:TARGET), e.g. walker_walk:walker_uphill"
            )
        source = "+".join(parse_sources(source))
        envs.task_spec(target)
        pairs.append((source, target))
    return tuple(pairs)


def parse_list(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def seeds_from(value: int | Sequence[int]) -> tuple[int, ...]:
    """A count N -> seeds 0..N-1; a list -> those seeds."""
    if isinstance(value, bool):
        raise CoworldError(f"seeds must be a count or a list of integers, got {value!r}")
    if isinstance(value, int):
        check_count("seeds", value, 1, MAX_SEEDS)
        return tuple(range(value))
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise CoworldError(f"seeds must be a count or a list of integers, got {value!r}")
    for seed in value:
        check_count("a seed", seed, 0, SEED_MAX)
    return tuple(value)


_FILE_KEYS = {"table", "pairs", "algos", "seeds", "variants", "preset", "set", "eval_episodes", "data", "ablation"}
_DATA_KEYS = {f.name for f in dataclasses.fields(DataSpec)} - {"overrides"} | {"set"}


def read_grid_file(path: str | Path) -> dict[str, Any]:
    """Read a TOML grid file into keyword arguments of :func:`build_spec` (see docs/reproducing.md for its keys)."""
    path = Path(path)
    import tomllib

    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise CoworldError(f"no grid file at {path}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise CoworldError(f"{path} is not valid TOML ({err})") from None
    unknown = set(data) - _FILE_KEYS
    if unknown:
        raise CoworldError(f"{path}: unknown keys {sorted(unknown)}; valid keys: {', '.join(sorted(_FILE_KEYS))}")
    out: dict[str, Any] = {}
    where = str(path)
    if "table" in data:
        out["table"] = _typed(where, "table", data["table"], str)
    if "pairs" in data:
        out["pairs"] = parse_pairs(",".join(_strings(where, "pairs", data["pairs"])))
    if "algos" in data:
        out["algos"] = _strings(where, "algos", data["algos"])
    if "seeds" in data:
        try:
            out["seeds"] = seeds_from(data["seeds"])
        except CoworldError as err:
            raise CoworldError(f"{path}: {err}") from None
    if "variants" in data:
        variants = _typed(where, "variants", data["variants"], dict)
        out["variants"] = tuple((name, _strings(where, f"variants.{name}", extra)) for name, extra in variants.items())
    if "ablation" in data:
        out["ablation"] = _typed(where, "ablation", data["ablation"], bool)
    if "preset" in data:
        out["preset"] = _typed(where, "preset", data["preset"], str)
    if "set" in data:
        out["overrides"] = _strings(where, "set", data["set"])
    if "eval_episodes" in data:
        out["eval_episodes"] = _typed(where, "eval_episodes", data["eval_episodes"], int)
    if "data" in data:
        fields = dict(_typed(where, "data", data["data"], dict))
        bad = set(fields) - _DATA_KEYS
        if bad:
            raise CoworldError(f"{path}: unknown [data] keys {sorted(bad)}; valid: {', '.join(sorted(_DATA_KEYS))}")
        kinds = {"policy": str, "quality": str, "episodes": int, "max_steps": int, "seed": int}
        for key, kind in kinds.items():
            if key in fields:
                fields[key] = _typed(where, f"data.{key}", fields[key], kind)
        if "set" in fields:
            fields["overrides"] = _strings(where, "data.set", fields.pop("set"))
        out["data"] = fields
    return out


_KIND_NAMES = {str: "a string", bool: "true or false", int: "a whole number", dict: "a table", list: "a list"}


def _typed(path: str, key: str, value: Any, kind: type) -> Any:
    """``value`` if TOML gave it the type ``kind`` (a bool is not a whole number here), else one ConfigError line."""
    if isinstance(value, kind) and not (kind is int and isinstance(value, bool)):
        return value
    raise ConfigError(f"{path}: {key} must be {_KIND_NAMES[kind]}, got {value!r}")


def _strings(path: str, key: str, value: Any) -> tuple[str, ...]:
    """A TOML list of strings as a tuple, else one ConfigError line (a lone string is not a list)."""
    items = _typed(path, key, value, list)
    for item in items:
        if not isinstance(item, str):
            raise ConfigError(f"{path}: {key} must be a list of strings, got {value!r}")
    return tuple(items)


def build_spec(
    *,
    table: str | None = None,
    ablation: bool = False,
    pairs: tuple[tuple[str, str], ...] | None = None,
    algos: tuple[str, ...] | None = None,
    seeds: tuple[int, ...] | None = None,
    variants: tuple[tuple[str, tuple[str, ...]], ...] | None = None,
    preset: str | None = None,
    overrides: Iterable[str] = (),
    eval_episodes: int | None = None,
    data: Mapping[str, Any] | None = None,
) -> SweepSpec:
    """A checked grid: a named table (or ``ablation``'s) as the base, then every given value replacing its field.

    ``overrides`` are added after the table's own. ``ablation`` with a table adds Figure 4(a)'s variants to it;
    alone it is the ``ablation`` table. Without a table, ``pairs`` is required and the defaults of
    :class:`SweepSpec` fill the rest.
    """
    if table is not None:
        spec = named_table(table)
    elif ablation:
        spec = named_table("ablation")
    else:
        if pairs is None:
            raise CoworldError("say what to run: --table toy|dmc|metaworld, --ablation, --pairs or --grid FILE")
        spec = SweepSpec(pairs=pairs)
    if ablation:
        spec = dataclasses.replace(spec, variants=ABLATION)
    changes: dict[str, Any] = {}
    for name, value in (
        ("pairs", pairs),
        ("algos", algos),
        ("seeds", seeds),
        ("variants", variants),
        ("preset", preset),
        ("eval_episodes", eval_episodes),
    ):
        if value is not None:
            changes[name] = value
    extra = tuple(overrides)
    if extra:
        changes["overrides"] = (*spec.overrides, *extra)
    if data:
        try:
            changes["data"] = dataclasses.replace(spec.data, **data)
        except TypeError as err:
            raise CoworldError(f"bad data setting ({err})") from None
    return dataclasses.replace(spec, **changes).check()
