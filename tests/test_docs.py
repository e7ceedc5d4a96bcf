"""The docs cannot rot silently: README.md, docs/*.md and benchmarks/RESULTS.md.

Every relative link resolves (a file or folder of the repository, and a heading where it names an anchor); every
``coworld ...`` line in a fenced code block names a real command with real options (parsed by the click command
line, run never); every config key the docs name (``section.key`` in backticks or after ``--set``) exists. The
checkers return the problems they find, so the tests below also show each one failing on a broken input.
"""

from __future__ import annotations

import contextlib
import dataclasses
import re
import shlex
from collections.abc import Iterator
from pathlib import Path

import click
import pytest

from coworld import cli
from coworld.commands import options
from coworld.config import PRESETS, config_keys, make_config

ROOT = Path(__file__).parents[1]
RESULTS = ROOT / "benchmarks" / "RESULTS.md"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PAGES = [*DOCS, RESULTS]

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


def command_problem(line: str) -> str | None:
    """Why ``line`` (``coworld ...``) is not a valid command line, or None. Nothing runs: each level's context is
    made with ``resilient_parsing=False`` (options, choices, types and counts checked), then dropped."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True  # punctuation_chars: `; done`, `&& ...` and `| ...` end the command
    tokens = list(lexer)
    ends = [i for i, token in enumerate(tokens) if token in SHELL_OPERATORS]
    tokens = tokens[: ends[0]] if ends else tokens
    args = [token for token in tokens if token not in PLACEHOLDERS][1:]
    command: click.Command = cli.main
    ctx = click.Context(cli.main, info_name="coworld")
    with _parsing_only():
        try:
            while isinstance(command, click.Group):
                if not args or args[0].startswith("-"):
                    return f"{line!r}: no command after {ctx.command_path!r}"
                name, args = args[0], args[1:]
                sub = command.get_command(ctx, name)
                if sub is None:
                    return f"{line!r}: {ctx.command_path} has no command {name!r}"
                command = sub
                if isinstance(command, click.Group):
                    ctx = click.Context(command, info_name=name, parent=ctx)
            command.make_context(command.name, list(args), parent=ctx, resilient_parsing=False)  # click eats its list
        except click.ClickException as err:
            return f"{line!r}: {err.format_message()}"
    for key_value in _option_values(args, "--set"):
        problem = key_problem(key_value.partition("=")[0])
        if problem:
            return f"{line!r}: {problem}"
    for preset in _option_values(args, "--preset"):  # checked by the command's body, not its parser
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


# -- the docs ----------------------------------------------------------------------------------------------------


def _name(page: Path) -> str:
    return str(page.relative_to(ROOT))


@pytest.mark.parametrize("page", PAGES, ids=_name)
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


DOC_PATH = re.compile(r"\b((?:docs/[\w-]+|datasets/README)\.md)\b")


@pytest.mark.parametrize("name", sorted(cli.COMMANDS))
def test_each_command_says_what_it_is_for_and_points_to_its_docs(name: str) -> None:
    command = cli.main.get_command(click.Context(cli.main), name)
    assert command is not None and command.help
    assert not command.get_short_help_str(limit=70).endswith("..."), "one line, whole in `coworld --help`'s list"
    pointed = DOC_PATH.findall(command.help)
    assert pointed, f"`coworld {name} --help` names no docs page"
    assert all((ROOT / path).exists() for path in pointed), pointed
