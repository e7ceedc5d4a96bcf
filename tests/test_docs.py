"""The docs cannot rot silently: README.md, docs/*.md and benchmarks/RESULTS.md.

Every relative link resolves (a file or folder of the repository, and a heading where it names an anchor; the
archive's pages too); every ``coworld ...`` line in a fenced code block names a real command with real options
(parsed by the click command line, run never); every config key the docs name (``section.key`` in backticks or after
``--set``) exists; every training example in README and docs/ names its preset. The README's command blocks run top
to bottom after the set-up, on a CPU: each line reads only what an earlier line wrote, and what they write in the
checkout is ignored by git. The checkers return the problems they find, so the tests below also show each one
failing on a broken input.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click
import pytest

from coworld import cli
from coworld.commands import options
from coworld.config import PRESETS, config_keys, make_config
from coworld.data.collect import default_dataset_path
from coworld.training.train import default_logdir

ROOT = Path(__file__).parents[1]
RESULTS = ROOT / "benchmarks" / "RESULTS.md"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PAGES = [*DOCS, RESULTS]
ARCHIVE = sorted((ROOT / "benchmarks" / "archive").glob("*.md"))  # history: its links resolve, its commands may not

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", flags=re.S | re.M)
PLACEHOLDERS = {"..."}  # a token that stands for "more of the same" in a shown command
SHELL_OPERATORS = {";", "&&", "||", "|", "&", ">", ">>", "<"}  # what ends a command on a shell line
FILE_SUFFIXES = {"py", "md", "h5", "json", "jsonl", "toml", "png", "mp4", "gif", "pt", "csv", "log", "yaml", "sh"}


# -- links -------------------------------------------------------------------------------------------------------


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped (``-`` and ``_`` kept), spaces as ``-``."""
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """The anchors of a Markdown page's headings (repeated headings get ``-1``, ``-2``... as on GitHub)."""
    seen: dict[str, int] = {}
    found = set()
    for line in FENCE.sub("", text).splitlines():
        match = re.match(r"#{1,6} (.+)", line)
        if not match:
            continue
        base = slug(match.group(1))
        count = seen.get(base, 0)
        found.add(base if count == 0 else f"{base}-{count}")
        seen[base] = count + 1
    return found


def link_problems(page: Path) -> list[str]:
    """Each relative link of ``page`` (outside code blocks) that names no existing path, or no heading of it."""
    text = page.read_text()
    problems = []
    for target in LINK.findall(FENCE.sub("", text)):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:: not checked here
            continue
        path_part, _, anchor = target.partition("#")
        path = (page.parent / path_part).resolve() if path_part else page
        if not path.exists():
            problems.append(f"{page.name}: link {target!r}: {path_part} does not exist")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path.read_text()):
            problems.append(f"{page.name}: link {target!r}: no heading #{anchor} in {path.name}")
    return problems


# -- coworld command lines ---------------------------------------------------------------------------------------


def command_lines(text: str) -> list[str]:
    """The ``coworld ...`` lines of a page's fenced code blocks, continuation lines joined, comments dropped."""
    lines = []
    for block in FENCE.findall(text):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip().removeprefix("$ ")
            if line.startswith("coworld "):
                lines.append(line)
    return lines


@contextlib.contextmanager
def _parsing_only() -> Iterator[None]:
    """Parse as the CLI does but touch nothing: output paths are not probed, torch's thread count is restored."""
    check_output = options.check_output
    options.check_output = lambda *args, **kwargs: None
    try:
        import torch

        threads = torch.get_num_threads()
    except ImportError:  # pragma: no cover - torch is a core dependency
        threads = None
    try:
        yield
    finally:
        options.check_output = check_output
        if threads is not None:
            torch.set_num_threads(threads)


@dataclasses.dataclass(frozen=True)
class Parsed:
    """A ``coworld ...`` line as the command line parses it: the command's names (``("dataset", "info")``), the
    click command, its parameters' values (defaults filled in) and the arguments as written."""

    names: tuple[str, ...]
    command: click.Command
    params: dict[str, Any]
    args: list[str]


def parse_command(line: str) -> Parsed | str:
    """``line`` (``coworld ...``) parsed by the real command line, or why it is not a valid one. Nothing runs: each
    level's context is made with ``resilient_parsing=False`` (options, choices, types and counts checked)."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True  # punctuation_chars: `; done`, `&& ...` and `| ...` end the command
    tokens = list(lexer)
    ends = [i for i, token in enumerate(tokens) if token in SHELL_OPERATORS]
    tokens = tokens[: ends[0]] if ends else tokens
    args = [token for token in tokens if token not in PLACEHOLDERS][1:]
    given = list(args)
    command: click.Command = cli.main
    ctx = click.Context(cli.main, info_name="coworld")
    names: list[str] = []
    with _parsing_only():
        try:
            while isinstance(command, click.Group):
                if not args or args[0].startswith("-"):
                    return f"{line!r}: no command after {ctx.command_path!r}"
                name, args = args[0], args[1:]
                sub = command.get_command(ctx, name)
                if sub is None:
                    return f"{line!r}: {ctx.command_path} has no command {name!r}"
                names.append(name)
                command = sub
                if isinstance(command, click.Group):
                    ctx = click.Context(command, info_name=name, parent=ctx)
            made = command.make_context(command.name, list(args), parent=ctx, resilient_parsing=False)
        except click.ClickException as err:
            return f"{line!r}: {err.format_message()}"
    return Parsed(tuple(names), command, dict(made.params), given)


def command_problem(line: str) -> str | None:
    """Why ``line`` (``coworld ...``) is not a valid command line, or None."""
    parsed = parse_command(line)
    if isinstance(parsed, str):
        return parsed
    for key_value in _option_values(parsed.args, "--set"):
        problem = key_problem(key_value.partition("=")[0])
        if problem:
            return f"{line!r}: {problem}"
    for preset in _option_values(parsed.args, "--preset"):  # checked by the command's body, not its parser
        if preset not in PRESETS:
            return f"{line!r}: no preset {preset!r} (presets: {', '.join(sorted(PRESETS))})"
    return None


def _option_values(args: list[str], option: str) -> list[str]:
    """The values given to ``option`` in a command's arguments (``--set`` gives ``KEY=VALUE``)."""
    return [value for name, value in zip(args, args[1:], strict=False) if name == option]


# -- config keys -------------------------------------------------------------------------------------------------

_CONFIG = make_config("paper")
KEYS = set(config_keys(_CONFIG))
SECTIONS = sorted(f.name for f in dataclasses.fields(_CONFIG) if dataclasses.is_dataclass(getattr(_CONFIG, f.name)))
PACKAGE_MODULES = {path.stem for path in (ROOT / "coworld").iterdir() if not path.name.startswith("_")}
DOTTED = re.compile(rf"(?<![\w./-])({'|'.join(SECTIONS)})\.([A-Za-z_]\w*)(?![\w/(]|\.\w)")


def key_problem(key: str) -> str | None:
    """Why ``key`` (``section.field``) is not a key of the config, or None."""
    return None if key in KEYS else f"no config key {key!r}"


def config_key_problems(text: str) -> list[str]:
    """Each ``section.field`` named in backticks (outside code blocks) that the config lacks. ``coworld.<module>``
    (the package's own modules) and file names (``train.py``) are not keys."""
    problems = []
    for span in re.findall(r"`([^`\n]+)`", FENCE.sub("", text)):
        for section, field in DOTTED.findall(span):
            if field in FILE_SUFFIXES or (section == "coworld" and field in PACKAGE_MODULES):
                continue
            problem = key_problem(f"{section}.{field}")
            if problem:
                problems.append(f"{problem} (in `{span}`)")
    return problems


# -- the README, top to bottom -----------------------------------------------------------------------------------

README = ROOT / "README.md"
QUICKSTART = ROOT / "scripts" / "quickstart.sh"
BASH_BLOCK = re.compile(r"^```bash\n(.*?)^```", flags=re.S | re.M)
GPU_SCALE = "# GPU-scale"  # the comment that marks a README line as a GPU's job, not the CPU walk's
SET_UP = "bash scripts/quickstart.sh"
PLAIN_SHELL = {"source .venv/bin/activate", "bash scripts/test.sh", SET_UP}  # the README's lines that are not coworld


def readme_lines(text: str) -> list[str]:
    """The lines of a page's ```bash blocks in order, continuation lines joined, blank and comment lines dropped."""
    lines = []
    for block in BASH_BLOCK.findall(text):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                lines.append(line)
    return lines


def quickstart_lines(text: str) -> list[str]:
    """The ``$coworld ...`` lines of scripts/quickstart.sh as ``coworld ...``, its variables (``out=${OUT_DIR:-out/
    quickstart}``, ``dataset="$out/..."``) put in with their default values; a ``$coworld`` inside a condition
    (``if ... $coworld dataset verify ...``) is left out."""
    values: dict[str, str] = {}

    def expand(text: str) -> str:
        return re.sub(r"\$\{?(\w+)\}?", lambda m: values.get(m.group(1), m.group(0)), text)

    lines = []
    for line in text.replace("\\\n", " ").splitlines():
        line = line.strip()
        assignment = re.fullmatch(r"(\w+)=(\S+)", line)
        if assignment:
            value = re.sub(r"\$\{\w+:-([^}]*)\}", r"\1", assignment.group(2).strip('"'))
            values[assignment.group(1)] = expand(value)
        elif line.startswith("$coworld "):
            lines.append("coworld " + expand(line.removeprefix("$coworld ")))
    return lines


def _dataset_argument(path: Path) -> Path:
    """A dataset command's PATH as the command reads it: a name (``walker_uphill-medium-replay``) stands for
    ``datasets/<task>-<quality>.h5`` (coworld.data.api.resolve_dataset)."""
    if path.suffix or len(path.parts) > 1:
        return path
    task, _, quality = str(path).partition("-")
    return default_dataset_path(task, quality.replace("_", "-"))


def reads_and_writes(parsed: Parsed) -> tuple[list[Path], list[Path]]:
    """The files and folders a command line reads and writes, from its path options (an input or an output by the
    option's type, ``coworld.commands.options.CheckedPath``) and the defaults the commands give them."""
    reads: list[Path] = []
    writes: list[Path] = []
    for param in parsed.command.params:
        value = parsed.params.get(param.name)
        if value is None or not isinstance(param.type, options.CheckedPath):
            continue
        for path in value if isinstance(value, tuple) else (value,):
            (writes if param.type.output else reads).append(Path(path))
    names, params = parsed.names, parsed.params
    if names[0] == "dataset" or names == ("viz", "dataset"):
        reads = [_dataset_argument(path) for path in reads]
    if names == ("collect",):
        quality = "random" if params["policy"] == "random" else params["quality"] or "medium-replay"
        out = Path(params["out"] or default_dataset_path(params["task"], quality))
        writes = [out]
        if params["policy"] == "dreamerv2":  # and the run of the DreamerV2 that learned: <out>.run
            writes.append(out.with_name(out.name.removesuffix(".h5") + ".run"))
    elif names == ("dataset", "import") and params["out"] is None and params["quality"]:
        writes.append(default_dataset_path(params["task"], params["quality"]))
    elif names == ("train",):
        if params["dataset"] is None:
            reads.append(default_dataset_path(params["target"], "medium-replay"))
        if params["logdir"] is None:
            writes.append(default_logdir(params["algo"], params["source"], params["target"], params["seed"] or 0))
    return reads, writes


def trains(parsed: Parsed) -> bool:
    """Whether the line trains an agent: ``train``, ``collect`` with DreamerV2 learning online, a ``sweep``."""
    if parsed.names == ("collect",):
        return parsed.params["policy"] != "random"
    if parsed.names == ("sweep",):
        return not parsed.params["dry_run"]
    return parsed.names == ("train",)


def _made(path: Path, made: set[Path]) -> bool:
    path = Path(os.path.normpath(path))
    return path in made or any(parent in made for parent in path.parents)


def walk_problems(lines: list[str], made: set[Path], gpu_made: set[Path] | None = None) -> list[str]:
    """Each problem of running ``lines`` top to bottom on a CPU, from the files in ``made``; adds what they write
    to ``made``. A line must parse with the real command line; every file or folder it reads must be one an earlier
    line wrote; a line that trains must name its ``--preset``. A line marked ``# GPU-scale`` may read what any
    earlier line wrote, and what it writes is made for GPU-scale lines only; an unmarked line may not train at the
    ``paper`` preset (a GPU's)."""
    gpu_made = set() if gpu_made is None else gpu_made
    problems = []
    for line in lines:
        command = line.partition(" #")[0].strip()
        if command in PLAIN_SHELL:
            if command == SET_UP:
                problems += walk_problems(quickstart_lines(QUICKSTART.read_text()), made, gpu_made)
            continue
        if not command.startswith("coworld "):
            known = ", ".join(sorted(PLAIN_SHELL))
            problems.append(f"{line!r}: not a coworld command, nor a line this test knows ({known})")
            continue
        parsed = parse_command(command)
        if isinstance(parsed, str):
            problems.append(parsed)
            continue
        gpu = GPU_SCALE in line
        reads, writes = reads_and_writes(parsed)
        for path in reads:
            if not (_made(path, made) or (gpu and _made(path, gpu_made))):
                problems.append(f"{command!r} reads {path}, which no earlier line writes")
        if trains(parsed):
            if "--preset" not in parsed.args:
                problems.append(f"{command!r} trains without naming its --preset")
            elif parsed.params["preset"] == "paper" and not gpu:
                problems.append(f"{command!r} trains at the paper preset on a CPU; mark it {GPU_SCALE!r}")
        (gpu_made if gpu else made).update(Path(os.path.normpath(path)) for path in writes)
    return problems


def readme_outputs(lines: list[str]) -> list[Path]:
    """Every file and folder the README's lines (and the set-up's) write, in order."""
    outputs = []
    for line in lines:
        command = line.partition(" #")[0].strip()
        commands = quickstart_lines(QUICKSTART.read_text()) if command == SET_UP else [command]
        for each in commands:
            parsed = parse_command(each) if each.startswith("coworld ") else None
            if isinstance(parsed, Parsed):
                outputs += reads_and_writes(parsed)[1]
    return outputs


# -- the docs ----------------------------------------------------------------------------------------------------


def _name(page: Path) -> str:
    return str(page.relative_to(ROOT))


@pytest.mark.parametrize("page", [*PAGES, *ARCHIVE], ids=_name)
def test_every_relative_link_resolves(page: Path) -> None:
    assert link_problems(page) == []


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_every_coworld_line_is_a_real_command(page: Path) -> None:
    lines = command_lines(page.read_text())
    problems = [problem for problem in map(command_problem, lines) if problem]
    assert problems == []


def test_the_readme_shows_commands() -> None:
    assert len(command_lines((ROOT / "README.md").read_text())) >= 10


@pytest.mark.parametrize("page", PAGES, ids=_name)
def test_every_config_key_named_exists(page: Path) -> None:
    assert config_key_problems(page.read_text()) == []


def test_every_docs_page_is_linked_from_the_readme() -> None:
    readme = (ROOT / "README.md").read_text()
    for page in DOCS[1:]:
        assert f"({_name(page)}" in readme, f"README.md does not link {_name(page)}"


def test_the_readme_runs_top_to_bottom_after_the_set_up() -> None:
    """Every command block of the README runs in order on a fresh clone after `bash scripts/quickstart.sh`, on a
    CPU, as written: each line parses, reads only what an earlier line (or the quickstart) wrote, and names the
    preset it trains at; the paper preset only on lines marked # GPU-scale."""
    lines = readme_lines(README.read_text())
    assert lines[0].partition(" #")[0].strip() == SET_UP, "the README's first command is the set-up"
    assert walk_problems(lines, set()) == []


def test_the_readme_trains_at_sizes_that_build() -> None:
    """Each README line's preset and --set make a config (the values in range), as its run would."""
    for line in readme_lines(README.read_text()):
        parsed = parse_command(line) if line.startswith("coworld ") else None
        if isinstance(parsed, Parsed) and parsed.params.get("preset"):
            make_config(parsed.params["preset"], list(parsed.params.get("overrides", ())))


README_SWEEPS = [line for line in readme_lines(README.read_text()) if line.startswith("coworld sweep ")]


@pytest.mark.parametrize(
    "line",
    # a GPU-scale table builds and checks every run's config, tens of seconds on a CPU
    [pytest.param(line, marks=pytest.mark.slow) if GPU_SCALE in line else line for line in README_SWEEPS],
    ids=lambda line: line.partition(" --dir")[0],
)
def test_the_readme_sweeps_pass_their_dry_run(tmp_path: Path, line: str) -> None:
    """A sweep checks every run's config before its folder exists; --dry-run does that and runs nothing."""
    from click.testing import CliRunner

    parsed = parse_command(line.partition(" #")[0])
    assert isinstance(parsed, Parsed), parsed
    args = list(parsed.args)
    args[args.index("--dir") + 1] = str(tmp_path / "sweep")
    with _parsing_only():  # the sweep sets torch's threads; they are put back
        result = CliRunner().invoke(cli.main, [*args, "--dry-run"])
    assert result.exit_code == 0, f"{line}: {result.output}"
    assert not (tmp_path / "sweep").exists()


def test_what_the_readme_writes_in_the_checkout_is_ignored_by_git() -> None:
    """After the README's commands `git status` is clean: every file and folder they write inside the checkout
    (datasets, runs, sweeps, videos, pictures) matches .gitignore."""
    if subprocess.run(["git", "-C", str(ROOT), "rev-parse"], capture_output=True).returncode != 0:
        pytest.skip("not a git checkout")
    outputs = readme_outputs(readme_lines(README.read_text()))
    assert outputs

    def ignored(path: Path) -> bool:  # a folder's pattern (`/runs/`) matches a file in it
        return any(
            subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", "--no-index", str(each)]).returncode == 0
            for each in (path, path / "a-file")
        )

    inside = [path for path in outputs if not path.is_absolute() and ".." not in path.parts]
    assert [str(path) for path in inside if not ignored(path)] == []


COMMITTED_REPORTS = sorted(
    path for name in ("report.md", "results.csv") for path in ROOT.glob(f"benchmarks/results/*/{name}")
)
ABSOLUTE_PATH = re.compile(r"(?<![\w.])/(?:work|home|tmp|root|mnt|Users)/")


def test_committed_reports_name_no_folder_of_the_machine_that_made_them() -> None:
    """A report under benchmarks/results names its runs relative to its sweep (`coworld report SWEEP` writes them
    so), never by a path of the machine the sweep ran on."""
    assert {path.name for path in COMMITTED_REPORTS} == {"report.md", "results.csv"}
    named = [f"{path.relative_to(ROOT)}: {line}" for path in COMMITTED_REPORTS for line in path.read_text().split("\n")]
    assert [line for line in named if ABSOLUTE_PATH.search(line)] == []


@pytest.mark.parametrize("page", DOCS, ids=_name)
def test_every_training_example_names_its_preset(page: Path) -> None:
    """The default preset is paper, a GPU's: every example that trains (train, collect with DreamerV2, sweep) says
    which preset it means. benchmarks/RESULTS.md keeps its commands as they were run."""
    problems = []
    for line in command_lines(page.read_text()):
        parsed = parse_command(line)
        if isinstance(parsed, Parsed) and trains(parsed) and "--preset" not in parsed.args:
            problems.append(line)
    assert problems == []


# -- the checkers fail where they should -------------------------------------------------------------------------


def test_a_broken_link_is_found(tmp_path: Path) -> None:
    (tmp_path / "there.md").write_text("# A heading\n")
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](there.md) [ok](there.md#a-heading) [web](https://example.org/x) ![pic](there.md)\n"
        "[gone](missing.md) [no anchor](there.md#another-heading)\n```\n[in code](ignored.md)\n```\n"
    )
    problems = link_problems(page)
    assert len(problems) == 2
    assert "missing.md does not exist" in problems[0]
    assert "no heading #another-heading" in problems[1]


def test_an_unknown_command_or_option_is_found() -> None:
    assert command_problem("coworld train --target toy_reach_shifted --preset cpu  # a comment") is None
    assert command_problem("coworld dataset info datasets/x.h5") is None
    assert command_problem('coworld eval --ckpt "$run" --episodes 20; done  # a loop') is None
    assert command_problem("coworld eval --ckpt RUN --episodes 20 | tee out --bogus") is None  # the pipe ends it
    assert "no such option" in command_problem("coworld train --target walker_uphill --no-such-option 1").lower()
    assert "has no command 'trian'" in command_problem("coworld trian --target walker_uphill")
    assert "has no command 'inspect'" in command_problem("coworld dataset inspect datasets/x.h5")
    assert "no preset 'cheap'" in command_problem("coworld train --target walker_uphill --preset cheap")  # not a choice
    assert "--target" in command_problem("coworld train --preset cpu")  # a required option left out
    assert command_problem("coworld collect --task toy_reach --episodes 0") is not None  # out of range


def test_continuation_lines_are_joined() -> None:
    block = "```bash\ncoworld sweep --pairs walker_walk:walker_uphill \\\n  --no-such-flag --dir d\n```\n"
    (line,) = command_lines(block)
    assert "--no-such-flag" in line
    assert "no such option" in command_problem(line).lower()


def test_an_unknown_config_key_is_found() -> None:
    assert config_key_problems("`train.batch_size`, `--set coworld.k=0.5`, `coworld.data.load(...)`, `train.py`") == []
    assert config_key_problems("`train.no_such_key`") == ["no config key 'train.no_such_key' (in `train.no_such_key`)"]
    assert config_key_problems("`--set world_model.lrr=3e-4`") != []
    assert "train.bach_size" in command_problem("coworld train --target walker_uphill --set train.bach_size=8")


def test_the_list_of_commands_is_shown_without_importing_them() -> None:
    """`coworld --help` answers at once: no command module is imported for it, nor torch."""
    code = (
        "import sys; from click.testing import CliRunner; from coworld.cli import main;"
        "out = CliRunner().invoke(main, ['--help']); assert out.exit_code == 0, out.output; print(out.output);"
        "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('coworld.commands')))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    help_text, imported = done.stdout.rstrip().rsplit("\n", 1)
    assert imported == "[]"
    assert all(f"  {name} " in help_text for name in cli.COMMANDS)


DOC_PATH = re.compile(r"\b((?:docs/[\w-]+|datasets/README)\.md)\b")


@pytest.mark.parametrize("name", sorted(cli.COMMANDS))
def test_each_command_says_what_it_is_for_and_points_to_its_docs(name: str) -> None:
    command = cli.main.get_command(click.Context(cli.main), name)
    assert command is not None and command.help
    assert not command.get_short_help_str(limit=70).endswith("..."), "one line, whole in `coworld --help`'s list"
    assert cli.SUMMARIES[name] == command.get_short_help_str(limit=70), "the list shows the command's own line"
    pointed = DOC_PATH.findall(command.help)
    assert pointed, f"`coworld {name} --help` names no docs page"
    assert all((ROOT / path).exists() for path in pointed), pointed


def test_the_walk_finds_a_missing_input_a_missing_preset_and_an_unmarked_gpu_line() -> None:
    collect = "coworld collect --task walker_uphill --policy random --episodes 4 --workers 2"
    assert walk_problems([collect, "coworld dataset info datasets/walker_uphill-random.h5"], set()) == []
    assert walk_problems([collect, "coworld dataset info walker_uphill-random"], set()) == []  # a dataset's name
    (problem,) = walk_problems([collect, "coworld train --target walker_uphill --algo curl-cql --preset tiny"], set())
    assert "reads datasets/walker_uphill-medium_replay.h5, which no earlier line writes" in problem
    train = "coworld train --target walker_uphill --dataset datasets/walker_uphill-random.h5 --algo curl-cql"
    (problem,) = walk_problems([collect, train], set())
    assert "without naming its --preset" in problem
    (problem,) = walk_problems([collect, train + " --preset paper"], set())
    assert "paper preset on a CPU" in problem
    assert walk_problems([collect, train + " --preset paper  # GPU-scale"], set()) == []
    eval_ = "coworld eval --ckpt runs/curl-cql-walker_uphill-s0 --episodes 2"
    assert walk_problems([collect, train + " --preset tiny", eval_], set()) == []
    gpu_run = walk_problems([collect, train + " --preset paper  # GPU-scale", eval_], set())
    assert gpu_run == [f"{eval_!r} reads runs/curl-cql-walker_uphill-s0, which no earlier line writes"]
    assert walk_problems([collect, train + " --preset paper  # GPU-scale", eval_ + "  # GPU-scale"], set()) == []
    assert "not a coworld command" in walk_problems(["rm -rf runs"], set())[0]
    assert walk_problems(["coworld sweep --table toy --dir sweeps/toy"], set()) != []  # a sweep trains
    assert walk_problems(["coworld sweep --table toy --dir sweeps/toy --dry-run"], set()) == []


def test_the_walk_knows_what_the_quickstart_makes() -> None:
    made: set[Path] = set()
    assert walk_problems([SET_UP], made) == []
    lines = quickstart_lines(QUICKSTART.read_text())
    assert any(line.startswith("coworld train ") for line in lines)
    assert Path("out/quickstart/walker_uphill-medium_replay.h5") in made
    assert any(path.parts[:3] == ("out", "quickstart", "runs") for path in made)
    script = 'out=${OUT_DIR:-out/x}\nrun="$out/runs/r"\nif ! $coworld dataset verify d; then\n'
    script += '  $coworld eval --ckpt "$run"\nfi\n'
    assert quickstart_lines(script) == ['coworld eval --ckpt "out/x/runs/r"']
