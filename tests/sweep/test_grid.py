"""Grids: the named tables, the runs a grid makes, grids from flags and TOML, and what a rerun may change."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import pytest

from coworld.config import make_config
from coworld.errors import ConfigError, CoworldError, UnknownTaskError
from coworld.sweep.grid import (
    ABLATION,
    DataSpec,
    Run,
    SweepSpec,
    build_spec,
    cap_study_table,
    named_table,
    parse_pairs,
    read_grid_file,
    seeds_from,
)
from coworld.sweep.runner import (
    SPEC_FILE,
    Execution,
    SweepDirs,
    _waits_for_pretraining,
    check_spec,
    collect_args,
    plan,
    run_steps,
)

TOY = (("toy_reach", "toy_reach_shifted"),)


def test_table1_is_the_papers_five_dmc_pairs():
    spec = named_table("dmc")
    assert spec.pairs == (
        ("walker_walk", "walker_downhill"),
        ("walker_walk", "walker_uphill"),
        ("walker_walk", "walker_nofoot"),
        ("cheetah_run", "cheetah_downhill"),
        ("cheetah_run", "cheetah_nopaw"),
    )
    assert spec.preset == "paper" and spec.data.quality == "medium-replay" and spec.eval_episodes == 10
    assert len(spec.runs()) == 5 * 9 * 3  # every algorithm: DrQ+BC, LOMPO and the three DreamerV2 variants included


def test_table2_is_the_papers_five_metaworld_pairs():
    spec = named_table("metaworld")
    assert [target for _, target in spec.pairs] == [
        "mw_door_close",
        "mw_button_press_topdown",
        "mw_handle_press",
        "mw_button_press",
        "mw_assembly",
    ]
    assert {source for source, _ in spec.pairs} == {
        "mw_window_close",
        "mw_handle_press",
        "mw_drawer_close",
        "mw_stick_push",
    }


def test_toy_table_has_every_algorithm_three_seeds_and_a_random_target_dataset():
    spec = named_table("toy").check()
    assert spec.pairs == TOY and spec.preset == "tiny"
    runs = spec.runs()
    for algo in ("coworld", "dreamerv2", "curl", "curl-cql", "lompo", "dreamerv2-finetune-ewc"):
        assert sorted(r.seed for r in runs if r.algo == algo) == [0, 1, 2]
    assert spec.data.policy == "random" and spec.data.episodes is not None


def test_toy_cpu_table_uses_the_cpu_preset_and_a_dreamerv2_medium_replay_target():
    spec = named_table("toy-cpu").check()
    assert spec.pairs == TOY and spec.preset == "cpu"
    assert spec.data.policy == "dreamerv2" and spec.data.quality == "medium-replay" and spec.data.max_steps == 4000
    runs = spec.runs()
    for algo in ("coworld", "dreamerv2", "curl", "curl-cql"):
        assert sorted(r.seed for r in runs if r.algo == algo) == [0, 1, 2]
    # Every override names a real config key with a value in range on the cpu preset.
    config = make_config("cpu", list(spec.overrides))
    assert config.curl.updates == 3000 and config.curl.hidden == 64 and config.penalty.ensemble == 3
    assert config.lompo.model_updates == 1000 < config.offline.updates
    assert config.offline.updates == config.coworld.iterations * config.coworld.target_updates  # at equal cost
    # The model-free baselines take the toy table's networks and batch, not the cpu preset's (the paper's).
    tiny = make_config("tiny")
    assert config.curl.batch_size == tiny.curl.batch_size < make_config("cpu").curl.batch_size
    assert config.drqbc.batch_size == tiny.drqbc.batch_size < make_config("cpu").drqbc.batch_size


def test_toy_centre_table_is_the_toy_cpu_schedule_on_the_centre_pair():
    spec, cpu = named_table("toy-centre").check(), named_table("toy-cpu")
    assert spec.pairs == (("toy_reach_centre", "toy_reach_centre_shifted"),)
    assert (spec.preset, spec.overrides, spec.data, spec.eval_episodes) == (
        cpu.preset, cpu.overrides, cpu.data, cpu.eval_episodes
    )  # fmt: skip
    assert sorted({r.algo for r in spec.runs()}) == ["coworld", "curl", "curl-cql", "dreamerv2"]
    assert len(spec.runs()) == 4 * 3


def test_dmc_cpu_table_gives_every_agent_the_same_target_budget():
    spec = named_table("dmc-cpu").check()
    assert spec.pairs == (("walker_walk", "walker_uphill"), ("cheetah_run", "cheetah_uphill"))
    assert spec.preset == "cpu" and spec.eval_episodes == 10
    assert spec.data.policy == "dreamerv2" and spec.data.quality == "medium-replay"
    runs = spec.runs()
    for target in ("walker_uphill", "cheetah_uphill"):
        for algo in ("coworld", "dreamerv2", "dreamerv2-finetune", "drq-bc"):
            assert sorted(r.seed for r in runs if r.algo == algo and r.target == target) == [0, 1, 2]
    config = make_config("cpu", list(spec.overrides))
    cw, train = config.coworld, config.train
    target_updates = cw.iterations * cw.target_updates  # CoWorld's, offline and fine-tuned DreamerV2's
    assert target_updates == 10_000
    assert cw.target_updates * 2 == cw.source_updates * 5  # Table 3's K1:K2
    # DrQ+BC samples as many frames as the world-model agents' batches hold
    assert config.drqbc.updates * config.drqbc.batch_size == target_updates * train.batch_size * train.seq_len
    # online evaluations are a fraction of the source pretraining's steps, not a multiple of them
    assert train.eval_every * 4 == cw.pretrain_steps and train.eval_episodes == 5


def test_ablation_switches_each_term_off_in_turn():
    spec = build_spec(ablation=True)
    variants = dict(spec.variants)
    assert variants == {
        "": (),
        "no-align": ("coworld.align=false",),
        "no-relabel": ("coworld.reward_relabel=false",),
        "no-value-reg": ("coworld.value_reg=false",),
    }
    run = Run("coworld", "mw_drawer_close", "mw_button_press", 0, "no-relabel")
    assert spec.run_overrides(run)[-1] == "coworld.reward_relabel=false"
    # on a table: the table's grid with the variants added, only CoWorld runs multiplied
    toy = build_spec(table="toy", ablation=True)
    assert toy.pairs == TOY and toy.variants == ABLATION
    assert len(toy.runs()) == 3 * (9 + 3)


def test_algorithms_with_a_source_keep_it_and_the_others_share_the_target():
    spec = SweepSpec(
        pairs=(("walker_walk", "walker_uphill"), ("cheetah_run", "walker_uphill")),
        algos=("dreamerv2-finetune", "drq-bc", "dreamerv2-penalty"),
        seeds=(0,),
    ).check()
    assert [run.name for run in spec.runs()] == [
        "dreamerv2-finetune-walker_walk-walker_uphill-s0",
        "drq-bc-walker_uphill-s0",
        "dreamerv2-penalty-walker_uphill-s0",
        "dreamerv2-finetune-cheetah_run-walker_uphill-s0",
    ]


def test_baselines_are_shared_by_pairs_with_the_same_target():
    spec = SweepSpec(
        pairs=(("walker_walk", "walker_uphill"), ("walker_downhill", "walker_uphill")),
        algos=("coworld", "dreamerv2"),
        seeds=(0, 1),
        variants=(("", ()), ("no-align", ("coworld.align=false",))),
    )
    names = [run.name for run in spec.runs()]
    assert len(names) == len(set(names)) == 2 * 2 * 2 + 2  # CoWorld per source and variant; one DreamerV2 per seed
    assert "coworld-no-align-walker_downhill-walker_uphill-s1" in names
    assert "dreamerv2-walker_uphill-s0" in names
    assert spec.targets() == ["walker_uphill"]


def test_flags_replace_the_tables_values():
    spec = build_spec(
        table="dmc",
        pairs=parse_pairs("walker_walk:walker_uphill"),
        algos=("coworld", "dreamerv2"),
        seeds=seeds_from(2),
        preset="tiny",
        overrides=["train.batch_size=4"],
    )
    assert spec.pairs == (("walker_walk", "walker_uphill"),) and spec.seeds == (0, 1) and spec.preset == "tiny"
    assert len(spec.runs()) == 4
    toy = build_spec(table="toy", overrides=["train.batch_size=4"])
    assert toy.overrides[-1] == "train.batch_size=4" and len(toy.overrides) > 1  # added after the table's own


@pytest.mark.parametrize(
    ("kwargs", "error", "words"),
    [
        ({}, CoworldError, "say what to run"),
        ({"table": "atari"}, CoworldError, "unknown table"),
        ({"pairs": (("toy_reach", "walker_uphill"),)}, CoworldError, "action dimensions"),
        ({"table": "toy", "algos": ("dqn",)}, CoworldError, "unknown algorithm"),
        ({"table": "toy", "seeds": (1, 1)}, CoworldError, "distinct"),
        ({"table": "toy", "overrides": ["coworld.nope=1"]}, ConfigError, "unknown config key"),
        ({"table": "toy", "overrides": ["coworld.iterations=many"]}, ConfigError, "takes a whole number"),
        ({"table": "toy", "preset": "huge"}, ConfigError, "unknown preset"),
        ({"table": "toy", "data": {"episodes": None}}, ConfigError, "random dataset needs"),
        ({"table": "toy", "data": {"colour": "red"}}, CoworldError, "bad data setting"),
        ({"table": "toy", "variants": (("a b", ()),)}, CoworldError, "variant name"),
    ],
)
def test_bad_grids_are_refused_with_one_line(kwargs, error, words):
    with pytest.raises(error) as info:
        build_spec(**kwargs)
    assert words in str(info.value) and "\n" not in str(info.value)


def test_parse_pairs_and_seeds():
    assert parse_pairs("toy_reach:toy_reach_shifted, walker_walk:walker_uphill") == (
        ("toy_reach", "toy_reach_shifted"),
        ("walker_walk", "walker_uphill"),
    )
    with pytest.raises(CoworldError, match="SOURCE:TARGET"):
        parse_pairs("toy_reach")
    with pytest.raises(UnknownTaskError):
        parse_pairs("toy_reach:nowhere")
    assert seeds_from(3) == (0, 1, 2) and seeds_from([4, 7]) == (4, 7)
    with pytest.raises(CoworldError):
        seeds_from(0)


def test_toml_grid_file(tmp_path):
    path = tmp_path / "grid.toml"
    path.write_text(
        'pairs = ["toy_reach:toy_reach_shifted"]\nalgos = ["coworld", "curl"]\nseeds = [3, 5]\npreset = "tiny"\n'
        'set = ["curl.updates=7"]\neval_episodes = 4\n'
        '[variants]\nfull = []\nno-align = ["coworld.align=false"]\n'
        '[data]\npolicy = "random"\nmax_steps = 300\n'
    )
    spec = build_spec(**read_grid_file(path))
    assert spec.algos == ("coworld", "curl") and spec.seeds == (3, 5) and spec.eval_episodes == 4
    assert spec.data == DataSpec(policy="random", max_steps=300) and spec.overrides == ("curl.updates=7",)
    assert [r.name for r in spec.runs()] == [
        "coworld-full-toy_reach-toy_reach_shifted-s3",
        "coworld-full-toy_reach-toy_reach_shifted-s5",
        "coworld-no-align-toy_reach-toy_reach_shifted-s3",
        "coworld-no-align-toy_reach-toy_reach_shifted-s5",
        "curl-toy_reach_shifted-s3",
        "curl-toy_reach_shifted-s5",
    ]
    path.write_text('pairs = ["toy_reach:toy_reach_shifted"]\nseed = 3\n')
    with pytest.raises(CoworldError, match="unknown keys \\['seed'\\]"):
        read_grid_file(path)
    path.write_text("pairs = [\n")
    with pytest.raises(CoworldError, match="not valid TOML"):
        read_grid_file(path)
    with pytest.raises(CoworldError, match="no grid file"):
        read_grid_file(tmp_path / "missing.toml")


def test_spec_round_trips_through_json():
    spec = build_spec(table="toy", ablation=True)
    again = SweepSpec.from_dict(json.loads(json.dumps(spec.to_dict())))
    assert again == spec


def test_rerun_may_extend_the_grid_but_not_change_its_runs(tmp_path):
    first = build_spec(table="toy", seeds=(0, 1), algos=("curl",))
    check_spec(first, tmp_path)
    check_spec(first, tmp_path)  # the same grid again
    check_spec(build_spec(table="toy", seeds=(2,), algos=("curl-cql",)), tmp_path)
    saved = json.loads((tmp_path / SPEC_FILE).read_text())
    assert saved["seeds"] == [0, 1, 2] and saved["algos"] == ["curl", "curl-cql"]  # the union of both grids
    for changed, words in (
        ({"preset": "paper"}, "preset: saved 'tiny', now 'paper'"),
        ({"overrides": ["curl.updates=5"]}, "overrides"),
        ({"eval_episodes": 3}, "eval_episodes: saved 10, now 3"),
        ({"data": {"episodes": 99}}, "data.episodes: saved 20, now 99"),
        ({"variants": (("", ()), ("no-align", ("coworld.align=true",)))}, None),
    ):
        before = (tmp_path / SPEC_FILE).read_text()
        if words is None:
            check_spec(build_spec(table="toy", variants=(("no-align", ("coworld.align=false",)),)), tmp_path)
            with pytest.raises(CoworldError, match="holds the variant 'no-align'"):
                check_spec(build_spec(table="toy", **changed), tmp_path)
            continue
        with pytest.raises(CoworldError) as info:
            check_spec(build_spec(table="toy", **changed), tmp_path)
        assert words in str(info.value) and "use a new --dir" in str(info.value)
        assert (tmp_path / SPEC_FILE).read_text() == before  # nothing written


def test_commands_of_a_run_and_a_dataset(tmp_path):
    spec = build_spec(table="toy", ablation=True)
    dirs = SweepDirs.at(tmp_path)
    run = Run("coworld", "toy_reach", "toy_reach_shifted", 2, "no-align")
    execution = Execution(threads=3, device="cpu")
    dataset = dirs.dataset("toy_reach_shifted", spec)
    assert dataset == tmp_path / "datasets" / "toy_reach_shifted-random.h5"
    train, evaluate = run_steps(spec, run, dirs.run_dir(run), dataset, execution)
    assert train[:2] == ("train", "--algo") and "--source" in train and train[train.index("--seed") + 1] == "2"
    assert train[-4:] == ("--device", "cpu", "--threads", "3")
    sets = [train[i + 1] for i, arg in enumerate(train) if arg == "--set"]
    assert sets == [*spec.overrides, "coworld.align=false"]  # the variant's override comes last and wins
    assert evaluate[evaluate.index("--episodes") + 1] == "10"
    assert evaluate[evaluate.index("--out") + 1].endswith("eval.json.partial")
    baseline = run_steps(spec, Run("curl", None, "toy_reach_shifted", 0), dirs.run_dir(run), dataset, execution)[0]
    assert "--source" not in baseline
    collect = collect_args(spec, "toy_reach_shifted", dataset, execution, resume=True)
    assert collect[collect.index("--policy") + 1] == "random" and "--resume" in collect and "--preset" not in collect
    assert collect[collect.index("--episodes") + 1] == str(spec.data.episodes)


def test_coworld_runs_that_pretrain_alike_share_their_pretraining_and_wait_for_it(tmp_path):
    spec = cap_study_table()
    dirs = SweepDirs.at(tmp_path)
    jobs = {job.name: job for job in plan(spec, dirs, Execution()).jobs}
    name = "coworld-{}cheetah_run-cheetah_uphill-s{}".format
    zeta3 = jobs[name("zeta3-", 1)]
    train = zeta3.steps[0]
    shared = [train[i + 1] for i, arg in enumerate(train) if arg == "--pretrained-from"]
    others = ("", "zeta10-", "later-dmc-", "no-align-", "no-align-no-cap-", "4x-")
    siblings = [name(variant, 1) for variant in others]  # seed 1's others
    assert shared == [str(dirs.runs / sibling) for sibling in siblings] and "--keep-pretrained" in train
    assert zeta3.shares == tuple(siblings)
    policy_critic = jobs[name("target-policy-", 1)]  # its critic learns while pretraining: none shares it
    assert policy_critic.shares == () and "--keep-pretrained" not in policy_critic.steps[0]
    assert all(job.shares == () for job in jobs.values() if job.algo != "coworld")

    first = jobs[name("", 1)]
    running = [SimpleNamespace(job=first)]
    assert _waits_for_pretraining(zeta3, running)  # its pretraining is being done
    assert not _waits_for_pretraining(policy_critic, running) and not _waits_for_pretraining(zeta3, [])
    first.run_dir.mkdir(parents=True)
    (first.run_dir / "checkpoint.pt").touch()  # written once the pretraining is kept
    assert not _waits_for_pretraining(zeta3, running)


def test_plan_skips_finished_runs_and_complete_datasets(tmp_path, toy_dataset_writer):
    spec = build_spec(table="toy", algos=("curl", "dreamerv2"), seeds=(0, 1), eval_episodes=2)
    dirs = SweepDirs.at(tmp_path)
    first = plan(spec, dirs, Execution())
    assert [job.kind for job in first.jobs] == ["collect"] + ["run"] * 4
    assert all(job.needs == first.jobs[0].name for job in first.jobs[1:])
    dirs.data.mkdir(parents=True)
    toy_dataset_writer(dirs.dataset("toy_reach_shifted", spec), "toy_reach_shifted", episodes=1)
    finished = dirs.runs / "curl-toy_reach_shifted-s1"
    finished.mkdir(parents=True)
    (finished / "eval.json").write_text(json.dumps({"returns": [1.0, 2.0]}))
    wrong = dirs.runs / "curl-toy_reach_shifted-s0"
    wrong.mkdir(parents=True)
    (wrong / "eval.json").write_text(json.dumps({"returns": [1.0]}))  # evaluated with other settings: not finished
    second = plan(spec, dirs, Execution())
    assert second.finished == ["curl-toy_reach_shifted-s1"]
    assert [job.name for job in second.jobs] == [
        "curl-toy_reach_shifted-s0",
        "dreamerv2-toy_reach_shifted-s0",
        "dreamerv2-toy_reach_shifted-s1",
    ]
    assert all(job.needs is None for job in second.jobs)  # the dataset is complete


def test_the_later_papers_dmc_tables_are_its_six_pairs_on_two_dataset_qualities():
    from coworld.report import paper

    for name, quality, columns in (
        ("dmc-mr", "medium-replay", ["dreamerv2-penalty", "drq-bc", "curl", "lompo", "dreamerv2-finetune", "coworld"]),
        ("dmc-me", "medium-expert", ["dreamerv2-penalty", "drq-bc", "lompo", "dreamerv2-finetune", "coworld"]),
    ):
        spec = named_table(name).check()
        assert spec.pairs == paper.TABLES[name].pairs
        assert [target for _, target in spec.pairs] == [
            "walker_downhill", "walker_uphill", "walker_nofoot", "cheetah_downhill", "cheetah_uphill", "cheetah_nopaw"
        ]  # fmt: skip
        # the paper's columns we have, then offline DreamerV2 and the EWC fine-tuning
        assert list(spec.algos) == [*columns, "dreamerv2", "dreamerv2-finetune-ewc"]
        assert (spec.seeds, spec.eval_episodes, spec.preset) == ((0, 1, 2), 10, "paper")
        assert (spec.data.policy, spec.data.quality) == ("dreamerv2", quality)
        cw = make_config(spec.preset, list(spec.overrides)).coworld
        # Table 8's DMC column (+later-dmc: its k 0.9 in its form of Eq. 4, eta from 1 to 0.1), 2e4 updates each
        assert (cw.beta2, cw.k, cw.relabel, cw.alpha, cw.zeta) == (1.5, 0.9, "later", 1.0, 1.0)
        assert (cw.reward_mix, cw.eta_start, cw.eta_end, cw.align_on) == ("eta", 1.0, 0.1, "embedding")
        assert (cw.target_updates, cw.source_updates) == (20_000, 20_000)


def test_the_robodesk_table_is_figure_4s_pairs_across_action_sizes():
    from coworld import envs
    from coworld.report import paper
    from coworld.sweep.grid import TABLES, robodesk_table

    spec = robodesk_table()
    assert spec.pairs == (
        ("mw_button_press", "robodesk_push_button"),
        ("mw_window_close", "robodesk_open_slide"),
        ("mw_drawer_close", "robodesk_drawer_open"),
        ("mw_handle_press", "robodesk_upright_block_off_table"),
    )
    assert list(spec.algos) == ["coworld", "dreamerv2-penalty", "dreamerv2"]  # the fine-tunings need one size
    spec.check()
    cw = make_config(spec.preset, list(spec.overrides)).coworld
    # Table 8's Meta-World / RoboDesk column (+later-metaworld)
    assert (cw.beta2, cw.k, cw.relabel, cw.alpha, cw.reward_mix) == (1.0, 0.3, "later", 2.0, "eta")
    assert {target for target, _ in paper.META_WORLD_TO_ROBODESK.cells} <= {t for _, t in spec.pairs}
    assert all(target in envs.TASKS for _, target in spec.pairs) and "robodesk" in TABLES


def test_an_unknown_table_is_one_line_naming_the_tables(tmp_path):
    with pytest.raises(CoworldError, match="unknown table 'nope'; choose from .*dmc-mr, dmc-me"):
        named_table("nope")
    grid = tmp_path / "grid.toml"
    grid.write_text('table = "nope"\n')
    with pytest.raises(CoworldError, match="unknown table 'nope'"):
        build_spec(**read_grid_file(grid))


def test_the_cap_study_runs_each_arm_on_dmc_cpus_cheetah_pair() -> None:
    """Issue 61's study: ``dmc-cpu``'s cheetah pair, its schedule and dataset, with CoWorld at zeta 1, 3, 10, with the
    later paper's DMC settings, with the target-policy cap, without alignment and without alignment and cap, CoWorld
    and offline DreamerV2 at 4x the target updates, and V-D4RL's penalised DreamerV2; 3 seeds each."""
    spec = named_table("cap-study").check()
    dmc = named_table("dmc-cpu")
    assert spec.pairs == (("cheetah_run", "cheetah_uphill"),)
    assert (spec.preset, spec.data, spec.eval_episodes, spec.seeds) == ("cpu", dmc.data, 10, (0, 1, 2))
    assert set(dmc.overrides) <= set(spec.overrides)
    arms = {(run.algo, run.variant) for run in spec.runs()}
    coworld = {"", "zeta3", "zeta10", "later-dmc", "target-policy", "no-align", "no-align-no-cap", "4x"}
    assert arms == {("coworld", v) for v in coworld} | {
        ("dreamerv2", ""),
        ("dreamerv2", "4x"),
        ("dreamerv2-penalty", ""),
    }
    assert len(spec.runs()) == 3 * len(arms)

    def config(algo: str, variant: str):
        run = next(r for r in spec.runs() if (r.algo, r.variant) == (algo, variant))
        return make_config(spec.preset, spec.run_overrides(run))

    assert config("coworld", "").coworld.zeta == 1.0 and config("coworld", "zeta10").coworld.zeta == 10.0
    later = make_config("cpu+later-dmc", [*dmc.overrides, "coworld.cap_form=on_mean"]).coworld
    assert config("coworld", "later-dmc").coworld == later
    assert config("coworld", "target-policy").coworld.cap_critic == "target_policy"
    assert config("coworld", "no-align").coworld == dataclasses.replace(config("coworld", "").coworld, align=False)
    control = dataclasses.replace(config("coworld", "").coworld, align=False, value_reg=False)
    assert config("coworld", "no-align-no-cap").coworld == control
    for algo in ("coworld", "dreamerv2"):  # 4x the target updates, the rest as dmc-cpu
        assert config(algo, "4x").coworld.target_updates == 4 * config(algo, "").coworld.target_updates
        assert config(algo, "4x").offline.updates == 4 * config(algo, "").offline.updates
    assert config("dreamerv2-penalty", "").penalty.model_updates == 2_500  # a quarter of its 10,000 updates
    assert config("coworld", "").coworld.cap_form == "on_mean"  # the form the committed study ran


def test_the_cap_shift_table_asks_the_cap_study_again_with_the_papers_push() -> None:
    """Issue 79's table: the cap study's pair, dataset, schedule, seeds and evaluation; CoWorld without alignment under
    the shift, its control, CoWorld whole, at the later paper's DMC settings, without alignment under the clamp, and
    offline DreamerV2 as the preset gives it and at the cpu-dv2 behaviour; every CoWorld run of a seed shares one
    source pretraining, so each arm pairs with its seed's control."""
    spec = named_table("cap-shift").check()
    study = named_table("cap-study")
    assert (spec.pairs, spec.data, spec.seeds, spec.eval_episodes) == (study.pairs, study.data, (0, 1, 2), 10)
    assert set(spec.overrides) <= set(study.overrides) and spec.preset == "cpu"
    order = list(dict.fromkeys((run.algo, run.variant) for run in spec.runs()))
    assert order == [
        ("coworld", "no-align"),
        ("coworld", "no-align-no-cap"),
        ("coworld", ""),
        ("coworld", "later-dmc"),
        ("coworld", "no-align-clamp"),
        ("dreamerv2", ""),
        ("dreamerv2", "dv2"),
    ]

    def config(algo: str, variant: str):
        run = next(r for r in spec.runs() if (r.algo, r.variant) == (algo, variant))
        return make_config(spec.preset, spec.run_overrides(run))

    whole = config("coworld", "").coworld
    assert whole.cap_form == "shift" and whole.value_reg and whole.align
    assert config("coworld", "no-align").coworld == dataclasses.replace(whole, align=False)
    assert config("coworld", "no-align-no-cap").coworld == dataclasses.replace(whole, align=False, value_reg=False)
    clamp = config("coworld", "no-align-clamp").coworld
    assert clamp == dataclasses.replace(whole, align=False, cap_form="on_mean")
    assert config("coworld", "later-dmc").coworld == make_config("cpu+later-dmc", spec.overrides).coworld
    assert config("dreamerv2", "dv2") == make_config("cpu-dv2", spec.overrides)
    assert config("dreamerv2", "").actor_critic.critic_dist == "twohot"
    shared = spec.shared_pretraining()
    for seed in spec.seeds:
        names = {run.name for run in spec.runs() if run.algo == "coworld" and run.seed == seed}
        for name in names:
            assert {other.name for other in shared[name]} == names - {name}
