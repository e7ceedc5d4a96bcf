"""``coworld config``: print the resolved config of a preset and overrides, as a run would save it."""

from __future__ import annotations

import click

from coworld.config import PRESETS, SETTINGS, make_config, to_json


@click.command("config")
@click.option(
    "--preset",
    default="paper",
    show_default=True,
    help=f"A size ({', '.join(PRESETS)}), optionally +SETTINGS: a version of the method's settings"
    f" ({', '.join(SETTINGS)}), e.g. cpu+later-dmc.",
)
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="Config override (repeatable).")
def config(preset: str, overrides: tuple[str, ...]) -> None:
    """Print the resolved config as JSON.

    Exactly the config.json a run with these settings saves. Docs: docs/algorithms.md (the paper preset is
    Table 3; "Three versions of the method" for +SETTINGS), docs/usage.md (presets and overrides).
    """
    click.echo(to_json(make_config(preset, overrides)))
