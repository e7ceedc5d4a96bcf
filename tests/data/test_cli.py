"""`coworld dataset info | verify | merge`, through click and as a real process."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.data import open_dataset

COWORLD = [sys.executable, "-c", "from coworld.cli import run; run()"]


def test_info_reports_counts_returns_scores_and_size(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    result = CliRunner().invoke(main, ["dataset", "info", str(dataset_path)])
    assert result.exit_code == 0, result.output
    lines = dict(line.split(None, 1) for line in result.stdout.splitlines())
    returns = np.array([ep["rewards"].astype(np.float64).sum() for ep in episodes])
    assert lines["episodes"].startswith("7 (3 terminated")
    assert lines["steps"].startswith(f"{sum(len(ep['rewards']) for ep in episodes)} rows")
    assert lines["return"].split()[:2] == ["mean", f"{returns.mean():.1f}"]
    rewards = np.concatenate([ep["rewards"] for ep in episodes]).astype(np.float64)
    assert lines["reward"].split() == [
        *("mean", f"{rewards.mean():.3f}", "std", f"{rewards.std():.3f}"),
        *("min", f"{rewards.min():.3f}", "max", f"{rewards.max():.3f}", "(a", "step)"),
    ]
    assert lines["normalized"].split()[:2] == ["mean", f"{10 * returns.mean():.1f}"]
    assert "on disk" in lines["size"] and "gzip, ratio" in lines["size"]
    assert json.loads(lines["env_config"])["action_repeat"] == 2
    assert lines["complete"] == "yes" and lines["quality"] == "random"


def test_info_values_are_each_steps_discounted_return_to_its_episodes_end(
    dataset_path: Path, episodes: list[dict[str, Any]]
) -> None:
    """The value line: over every row, the sum of gamma^k times the rewards received on arriving at the following
    steps (the first step's value is 0 + gamma r_0 + ...), counted here by brute force."""
    gamma = 0.9
    values = []
    for ep in episodes:
        arrival = np.concatenate([[0.0], ep["rewards"].astype(np.float64)])
        values += [sum(gamma**k * r for k, r in enumerate(arrival[t:])) for t in range(len(ep["rewards"]))]
    result = CliRunner().invoke(main, ["dataset", "info", "--discount", str(gamma), str(dataset_path)])
    assert result.exit_code == 0, result.output
    line = dict(line.split(None, 1) for line in result.stdout.splitlines())["value"]
    assert line.split()[:4] == ["mean", f"{np.mean(values):.2f}", "std", f"{np.std(values):.2f}"]
    assert line.split()[6:8] == ["max", f"{np.max(values):.2f}"] and "gamma 0.9)" in line


def test_info_discount_help_names_each_presets_critic_discount() -> None:
    """The help's figures are written out (the command does not import the config); they follow the presets."""
    from coworld.config import PRESETS, make_config

    info = main.get_command(None, "dataset").get_command(None, "info")
    option = next(p for p in info.params if p.name == "discount")
    discount = {preset: make_config(preset).actor_critic.discount for preset in PRESETS}
    assert set(discount) == {"tiny", "cpu", "cpu-dv2", "paper"}
    assert discount["tiny"] == discount["cpu"] == discount["cpu-dv2"] == option.default
    assert f"tiny, cpu and cpu-dv2 presets {discount['cpu']}, paper {discount['paper']}" in option.help


def test_info_json_is_the_summary(dataset_path: Path) -> None:
    result = CliRunner().invoke(main, ["dataset", "info", "--json", str(dataset_path)])
    assert result.exit_code == 0, result.output
    with open_dataset(dataset_path) as data:
        assert json.loads(result.stdout) == json.loads(json.dumps(data.summary()))


def test_verify_ok(dataset_path: Path) -> None:
    result = CliRunner().invoke(main, ["dataset", "verify", str(dataset_path)])
    assert result.exit_code == 0 and result.stdout.strip() == f"{dataset_path}: ok"


def _flip_a_pixel(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        frame = f["observations"][20]
        frame[30, 30, 0] ^= 0xFF
        f["observations"][20] = frame


def _nan_and_incomplete(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        f["rewards"][0] = np.nan
        f.attrs["complete"] = False


@pytest.mark.parametrize(
    ("damage", "findings"),
    [
        (_flip_a_pixel, ["1 episodes: checksum mismatch (data damaged): 2"]),
        (_nan_and_incomplete, ["1 rewards are NaN or inf", "not complete"]),
        (lambda p: p.write_bytes(p.read_bytes()[:5000]), ["not a readable HDF5 file"]),
    ],
)
def test_verify_lists_findings_and_exits_1(
    tmp_path: Path, dataset_path: Path, helpers: ModuleType, damage: Any, findings: list[str]
) -> None:
    path = tmp_path / "damaged.h5"
    shutil.copy(dataset_path, path)
    damage(path)
    before = helpers.file_state(path)
    result = CliRunner().invoke(main, ["dataset", "verify", str(path)])
    assert result.exit_code == 1
    for finding in findings:
        assert any(finding in line for line in result.stdout.splitlines()), result.stdout
    assert result.stdout.splitlines()[-1].endswith("problem" + ("s" if len(findings) > 1 else ""))
    assert helpers.file_state(path) == before


@pytest.mark.parametrize("damage", ["not hdf5", "missing key", "nan rewards", "truncated"])
def test_info_on_a_bad_file_is_one_line_exit_2_and_touches_nothing(
    tmp_path: Path, dataset_path: Path, helpers: ModuleType, damage: str
) -> None:
    path = tmp_path / "bad.h5"
    shutil.copy(dataset_path, path)
    if damage == "not hdf5":
        path.write_text("hello")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:-4096])
    else:
        with h5py.File(path, "r+") as f:
            if damage == "missing key":
                del f["rewards"]
            else:
                f["rewards"][1] = np.nan
    before = helpers.file_state(path)
    result = CliRunner().invoke(main, ["dataset", "info", str(path)])
    assert result.exit_code == 2
    assert result.stdout == "" and len(result.stderr.splitlines()) == 1
    assert result.stderr.startswith(f"error: {path}: ") and "Traceback" not in result.stderr
    assert helpers.file_state(path) == before


def test_merge_concatenates_episodes_and_names_the_quality(tmp_path: Path, helpers: ModuleType) -> None:
    a_eps, b_eps = helpers.make_episodes([6, 9], seed=1), helpers.make_episodes([4, 7, 5], seed=2, first_id=2)
    a = helpers.write_dataset(tmp_path / "a.h5", a_eps, quality="medium-replay")
    b = helpers.write_dataset(tmp_path / "b.h5", b_eps, quality="expert")
    out = tmp_path / "me.h5"
    result = CliRunner().invoke(main, ["dataset", "merge", str(a), str(b), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "medium-expert, 5 episodes, 31 steps" in result.stdout
    with open_dataset(out) as data:
        assert data.quality == "medium-expert" and data.complete
        for i, ep in enumerate(a_eps + b_eps):
            got = data.episode(i)
            np.testing.assert_array_equal(got["image"], ep["observations"])
            np.testing.assert_array_equal(got["action"][1:], ep["actions"])
            assert got["is_terminal"][-1] == ep["terminated"]
            np.testing.assert_array_equal(got["success"][1:], ep["infos"]["success"])
        sources = data.metadata["collector"]["sources"]
        assert [s["quality"] for s in sources] == ["medium-replay", "expert"]
        assert [(s["episodes"], s["steps"]) for s in sources] == [(2, 15), (3, 16)]  # what it is made of, in order
    assert CliRunner().invoke(main, ["dataset", "verify", str(out)]).exit_code == 0


def test_merge_refusals(tmp_path: Path, helpers: ModuleType) -> None:
    eps = helpers.make_episodes([5, 6])
    a = helpers.write_dataset(tmp_path / "a.h5", eps, quality="random")
    b = helpers.write_dataset(tmp_path / "b.h5", eps, quality="expert")
    other = helpers.write_dataset(tmp_path / "o.h5", eps, quality="random", task="other_task")
    runner = CliRunner()
    cases = [
        ([a, other], "task and env config must match"),
        ([a, b], "say which quality the merge has with --quality"),
        ([a, a], "the output"),
    ]
    for inputs, message in cases:
        out = inputs[0] if message == "the output" else tmp_path / "m.h5"
        result = runner.invoke(main, ["dataset", "merge", *map(str, inputs), "--out", str(out)])
        assert result.exit_code == 2 and message in result.stderr, result.stderr
    assert not (tmp_path / "m.h5").exists()
    result = runner.invoke(main, ["dataset", "merge", str(a), str(b), "--out", str(tmp_path / "m.h5"), "--quality",
                                  "medium-expert"])  # fmt: skip
    assert result.exit_code == 0, result.output


def test_real_process_exit_codes(dataset_path: Path, tmp_path: Path) -> None:
    ok = subprocess.run([*COWORLD, "dataset", "verify", str(dataset_path)], capture_output=True, text=True)
    assert ok.returncode == 0 and ok.stdout.strip().endswith(": ok")
    info = subprocess.run([*COWORLD, "dataset", "info", "--json", str(dataset_path)], capture_output=True, text=True)
    assert info.returncode == 0 and json.loads(info.stdout)["episodes"] == 7
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    result = subprocess.run([*COWORLD, "dataset", "info", str(bad)], capture_output=True, text=True)
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    result = subprocess.run([*COWORLD, "dataset", "verify", str(bad)], capture_output=True, text=True)
    assert result.returncode == 1 and "not a readable HDF5 file" in result.stdout


def test_merge_refuses_an_input_given_twice(tmp_path: Path, helpers: ModuleType, monkeypatch: pytest.MonkeyPatch):
    a = helpers.write_dataset(tmp_path / "a.h5", helpers.make_episodes([5, 6]))
    (tmp_path / "link.h5").symlink_to(a)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "m.h5"
    for twice in (["a.h5", "a.h5"], ["a.h5", f"../{tmp_path.name}/a.h5"], [str(a), "link.h5"]):
        result = CliRunner().invoke(main, ["dataset", "merge", *twice, "--out", str(out)])
        assert result.exit_code == 2 and len(result.stderr.splitlines()) == 1, result.output
        assert f"{twice[1]} is given twice" in result.stderr and "list each input once" in result.stderr
        assert not out.exists()


def test_merge_onto_an_existing_file_needs_force_and_offers_no_resume(tmp_path: Path, helpers: ModuleType) -> None:
    a = helpers.write_dataset(tmp_path / "a.h5", helpers.make_episodes([5]))
    b = helpers.write_dataset(tmp_path / "b.h5", helpers.make_episodes([6], first_id=1))
    out = helpers.write_dataset(tmp_path / "m.h5", helpers.make_episodes([4]))
    before = helpers.file_state(out)
    result = CliRunner().invoke(main, ["dataset", "merge", str(a), str(b), "--out", str(out)])
    assert result.exit_code == 2 and len(result.stderr.splitlines()) == 1
    assert "already exists" in result.stderr and "--force" in result.stderr and "--resume" not in result.stderr
    assert helpers.file_state(out) == before
    result = CliRunner().invoke(main, ["dataset", "merge", str(a), str(b), "--out", str(out), "--force"])
    assert result.exit_code == 0 and f"wrote {out}: random, 2 episodes, 11 steps" in result.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5", "b.h5", "m.h5"]  # nothing left beside it


def test_counts_agree_with_their_nouns(tmp_path: Path, helpers: ModuleType, monkeypatch: pytest.MonkeyPatch) -> None:
    from coworld.text import count

    assert [count(n, "episode") for n in (0, 1, 2, 1000)] == ["0 episodes", "1 episode", "2 episodes", "1,000 episodes"]
    helpers.patch_envs(monkeypatch.setattr)
    out = tmp_path / "one.h5"
    args = ["collect", "--policy", "random", "--task", helpers.FAKE_TASK, "--episodes", "1", "--out", str(out)]
    result = CliRunner().invoke(main, [*args, "--quiet"])
    assert result.exit_code == 0 and f"wrote {out}: 1 episode, " in result.stdout, result.output
    result = CliRunner().invoke(main, [*args, "--resume"])
    assert result.exit_code == 2 and "is already complete with 1 episode (" in result.stderr
    assert "which meets 1 episode;" in result.stderr
