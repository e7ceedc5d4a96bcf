"""``coworld report`` keeps runs that differ apart: runs of one algorithm are one arm only where their presets and
configs agree on everything but the seed, and each arm's label names what sets it apart."""

from __future__ import annotations

import functools
import json
from pathlib import Path

from coworld.config import make_config, to_dict
from coworld.report.results import load_result, load_results
from coworld.report.tables import results_table, seed_table, value_table

SOURCE, TARGET = "toy_reach", "toy_reach_shifted"


def coworld_run(
    root: Path,
    name: str,
    *,
    seed: int = 0,
    preset: str = "cpu",
    overrides: dict | None = None,
    ret: float = 10.0,
    capping: float = 3.0,
    variant: str | None = None,
    algo: str = "coworld",
    drop: tuple[str, ...] = (),
) -> Path:
    """A run folder as `coworld train --preset PRESET --set ...` and `coworld eval` leave it: its whole config saved
    (``drop``: dotted keys left out, as in a config saved before they existed), ``capping`` the cap's critic."""
    run = root / name
    run.mkdir(parents=True)
    info = {"algo": algo, "source": SOURCE if algo == "coworld" else None, "target": TARGET, "preset": preset}
    (run / "run.json").write_text(json.dumps(info))
    config = {**made_config(preset, json.dumps(overrides or {})), "seed": seed}
    for key in drop:
        section, leaf = key.split(".")
        del config[section][leaf]
    (run / "config.json").write_text(json.dumps(config))
    evaluation = {"task": TARGET, "returns": [ret], "std": 0.0, "value_estimate": [5.0], "value_true": [4.0]}
    if algo == "coworld":
        evaluation["value_source"] = [capping]
    (run / "eval.json").write_text(json.dumps(evaluation))
    if variant is not None:
        record = {"algo": algo, "variant": variant, "source": SOURCE, "target": TARGET, "seed": seed}
        (run / "sweep-run.json").write_text(json.dumps(record))
    return run


@functools.cache
def _made_config(preset: str, overrides: str) -> str:
    return json.dumps(to_dict(make_config(preset, json.loads(overrides))))


def made_config(preset: str, overrides: str) -> dict:
    """``coworld config --preset PRESET`` with ``overrides`` (JSON), made once per test session."""
    return json.loads(_made_config(preset, overrides))


def labels(root: Path) -> dict[str, str]:
    return {Path(r.run_dir).name: r.label for r in load_results(root)}


def test_five_runs_without_a_sweep_are_four_arms_each_named_by_what_sets_it_apart(tmp_path):
    coworld_run(tmp_path, "plain", ret=10.0)
    coworld_run(tmp_path, "plain-s1", seed=1, ret=20.0)
    coworld_run(tmp_path, "zeta", overrides={"coworld.zeta": 10}, ret=30.0)
    coworld_run(tmp_path, "policy", overrides={"coworld.cap_critic": "target_policy"}, ret=40.0, capping=9.0)
    coworld_run(tmp_path, "later", preset="cpu+later-dmc", ret=50.0)
    assert labels(tmp_path) == {
        "plain": "coworld",
        "plain-s1": "coworld",  # the seed is no difference: two seeds of one arm
        "zeta": "coworld (coworld.zeta=10)",
        "policy": "coworld (coworld.cap_critic=target_policy)",
        "later": "coworld (+later-dmc)",  # the preset's settings named, not their nine keys
    }
    results = load_results(tmp_path)
    assert results_table(results).splitlines()[2] == f"| {SOURCE} → {TARGET} | 15.0 ± 5.0 |"
    varied = results_table(results, variants=True).splitlines()
    assert varied[0] == ("| pair | coworld | coworld (+later-dmc) | coworld (coworld.cap_critic=target_policy)"
                         " | coworld (coworld.zeta=10) |")  # fmt: skip
    assert varied[2] == f"| {SOURCE} → {TARGET} | 15.0 ± 5.0 | **50.0 (n=1)** | 40.0 (n=1) | 30.0 (n=1) |"
    caps = {line.split(" | ")[1]: line.split(" | ")[4] for line in value_table(results).splitlines()[2:]}
    assert caps["coworld (coworld.cap_critic=target_policy)"] == "9.00" and caps["coworld"] == "3.00"


def test_a_setting_every_run_of_the_algorithm_shares_is_no_difference(tmp_path):
    """A report's runs made with the same ``--set`` (a sweep's shared overrides, say) are not all named by it."""
    shared = {"train.eval_every": 5000, "coworld.target_updates": 1250}
    coworld_run(tmp_path, "plain", overrides=shared)
    coworld_run(tmp_path, "zeta", overrides={**shared, "coworld.zeta": 3.5})
    coworld_run(tmp_path, "dv2", algo="dreamerv2", overrides={"train.eval_every": 2000})  # another algorithm's runs
    assert labels(tmp_path) == {"plain": "coworld", "zeta": "coworld (coworld.zeta=3.5)", "dv2": "dreamerv2"}


def test_runs_at_different_sizes_are_named_by_their_presets(tmp_path):
    coworld_run(tmp_path, "cpu", preset="cpu")
    coworld_run(tmp_path, "tiny", preset="tiny")
    coworld_run(tmp_path, "tiny-later", preset="tiny+later-dmc")
    assert labels(tmp_path) == {
        "cpu": "coworld (cpu)",
        "tiny": "coworld (tiny)",
        "tiny-later": "coworld (tiny+later-dmc)",
    }


def test_a_sweep_variant_keeps_its_name_and_runs_of_one_name_that_differ_stay_apart(tmp_path):
    for seed in (0, 1):
        coworld_run(tmp_path, f"plain{seed}", seed=seed, variant="")
        coworld_run(tmp_path, f"zeta3-{seed}", seed=seed, overrides={"coworld.zeta": 3}, variant="zeta3")
    coworld_run(tmp_path, "zeta3-late", seed=2, overrides={"coworld.zeta": 3, "coworld.k": 0.5}, variant="zeta3")
    assert labels(tmp_path) == {
        "plain0": "coworld",
        "plain1": "coworld",
        "zeta3-0": "coworld (zeta3)",  # the name its sweep gave it, not coworld.zeta=3
        "zeta3-1": "coworld (zeta3)",
        "zeta3-late": "coworld (zeta3, coworld.k=0.5)",  # of the same name, but made otherwise
    }
    rows = seed_table(load_results(tmp_path)).splitlines()[2:]
    assert [row.split(" | ")[1] for row in rows] == ["coworld", "coworld (zeta3)", "coworld (zeta3, coworld.k=0.5)"]


def test_runs_saved_before_a_key_existed_keep_their_labels_and_are_told_from_runs_saved_after(tmp_path):
    """A config saved before ``coworld.cap_form`` existed loads as 'on_mean' (the clamp it ran), today's default is
    'shift': among old runs alone that is no difference; beside a run of today's default, the old runs are named."""
    old = tmp_path / "old"
    coworld_run(old, "plain", overrides={"coworld.cap_form": "on_mean"}, drop=("coworld.cap_form",))
    coworld_run(old, "zeta", overrides={"coworld.cap_form": "on_mean", "coworld.zeta": 10}, drop=("coworld.cap_form",))
    assert labels(old) == {"plain": "coworld", "zeta": "coworld (coworld.zeta=10)"}
    coworld_run(old, "today")
    assert labels(old) == {
        "plain": "coworld (coworld.cap_form=on_mean)",
        "zeta": "coworld (coworld.zeta=10, coworld.cap_form=on_mean)",
        "today": "coworld",
    }


def test_a_coworld_term_switched_off_is_named_as_before_with_what_else_differs(tmp_path):
    coworld_run(tmp_path, "no-align", overrides={"coworld.align": False})
    coworld_run(tmp_path, "no-align-zeta", overrides={"coworld.align": False, "coworld.zeta": 2})
    coworld_run(tmp_path, "plain")
    assert labels(tmp_path) == {
        "no-align": "coworld (no-align)",
        "no-align-zeta": "coworld (no-align, coworld.zeta=2)",
        "plain": "coworld",
    }


def test_a_config_this_version_cannot_read_is_named_and_its_run_labelled_by_its_values_as_saved(tmp_path):
    coworld_run(tmp_path, "plain")
    odd = coworld_run(tmp_path, "odd")
    config = json.loads((odd / "config.json").read_text())
    config["coworld"]["retired_knob"] = 7
    (odd / "config.json").write_text(json.dumps(config))
    assert labels(tmp_path) == {"plain": "coworld", "odd": "coworld (coworld.retired_knob=7)"}
    (line,) = load_result(odd).problems
    assert line.startswith(f"{odd / 'config.json'}: not a config this version reads (unknown config key")
    assert "valid keys" not in line and line.endswith("its values as saved label the run")
