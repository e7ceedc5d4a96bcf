"""Every command's path and number options, found by walking the command line: each refuses the values that would
exhaust memory or time or land files in the wrong place, while the options are parsed, before any work.

New commands get these checks by default: an integer option without an upper bound, a float option that lets
``nan`` or ``inf`` through, or a path option that is not one of ``coworld.commands.options``' checked paths fails
here until it is one.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import click
import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.commands.options import CheckedPath, Number


def leaf_commands(
    group: click.Group = main, path: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], click.Command]]:
    ctx = click.Context(group)
    for name in group.list_commands(ctx):
        command = group.get_command(ctx, name)
        assert command is not None, name
        if isinstance(command, click.Group):
            yield from leaf_commands(command, (*path, name))
        else:
            yield (*path, name), command


def params_of(kind: str) -> list[tuple[tuple[str, ...], click.Parameter]]:
    found = []
    for path, command in leaf_commands():
        for param in command.params:
            if isinstance(param, click.Option) and (param.is_flag or param.count):
                continue
            base = param.type
            is_int = isinstance(base, click.types.IntParamType)
            is_float = isinstance(base, click.types.FloatParamType)
            is_path = isinstance(base, click.Path)
            if {"int": is_int, "float": is_float, "path": is_path}[kind]:
                found.append((path, param))
    return found


def ids(items: list[tuple[tuple[str, ...], click.Parameter]]) -> list[str]:
    return [" ".join(path) + " " + (max(p.opts, key=len)) for path, p in items]


INTS, FLOATS, PATHS = params_of("int"), params_of("float"), params_of("path")


def given(path: tuple[str, ...], param: click.Parameter, value: str) -> list[str]:
    """The option alone with ``value`` (click checks it before it misses the required others); an argument after
    valid values of the arguments before it."""
    if isinstance(param, click.Option):
        return [max(param.opts, key=len), value]
    command = dict(leaf_commands())[path]
    before = []
    for other in command.params:
        if other is param:
            break
        if isinstance(other, click.Argument):
            before.append(other.type.choices[0] if isinstance(other.type, click.Choice) else "x")
    return [*before, value]


def usage_error(path: tuple[str, ...], param: click.Parameter, value: str) -> str:
    result = CliRunner().invoke(main, [*path, *given(path, param, value)])
    assert result.exit_code == 2, (value, result.output)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result.output


def test_the_walk_finds_the_commands_and_their_options():
    names = {" ".join(path) for path, _ in leaf_commands()}
    assert {"sweep", "report", "viz latents", "viz predictions", "viz dataset", "dataset import", "dataset export",
            "collect", "train", "eval"} <= names  # fmt: skip
    assert len(INTS) > 20 and len(FLOATS) >= 4 and len(PATHS) > 20


@pytest.mark.parametrize("path, param", INTS, ids=ids(INTS))
def test_every_integer_option_has_an_upper_bound_and_refuses_beyond_it(path, param):
    assert isinstance(param.type, click.IntRange) and param.type.max is not None, "bound it (options.count_type)"
    out = usage_error(path, param, str(param.type.max + 1))
    assert "is not in the range" in out
    if param.type.min is not None:
        assert "is not in the range" in usage_error(path, param, str(param.type.min - 1))
    assert "is not a valid integer" in usage_error(path, param, "1e400")


@pytest.mark.parametrize("path, param", FLOATS, ids=ids(FLOATS))
def test_every_float_option_is_finite_and_bounded(path, param):
    assert isinstance(param.type, Number) and param.type.max is not None and math.isfinite(param.type.max)
    for value in ("nan", "inf", "1e400", str(param.type.max * 2 + 1)):
        assert "Invalid value" in usage_error(path, param, value), value


@pytest.mark.parametrize("path, param", PATHS, ids=ids(PATHS))
def test_every_path_option_refuses_an_empty_path(path, param):
    assert isinstance(param.type, CheckedPath), "use options.input_path / output_file / output_folder"
    assert "an empty path" in usage_error(path, param, "")


OUTPUTS = [(path, param) for path, param in PATHS if param.type.output]  # type: ignore[attr-defined]


@pytest.mark.parametrize("path, param", OUTPUTS, ids=ids(OUTPUTS))
def test_every_output_under_a_file_is_one_line_and_the_file_is_untouched(tmp_path, path, param):
    blocker = tmp_path / "a-file"
    blocker.write_bytes(b"keep me")
    target = blocker / "sub" / ("out" if param.type.output == "folder" else "out.png")  # type: ignore[attr-defined]
    result = CliRunner().invoke(main, [*path, *given(path, param, str(target))])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert lines[0].startswith("error: ") and "is a file, not a folder" in lines[0] and str(target) in lines[0]
    assert blocker.read_bytes() == b"keep me" and sorted(tmp_path.iterdir()) == [blocker]
