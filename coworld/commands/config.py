"""``coworld config``: print the resolved config of a preset and overrides, as a run would save it."""

from __future__ import annotations

import click

from coworld.config import PRESETS, make_config, to_json


@click.command("config")
@click.option("--preset", type=click.Choice(sorted(PRESETS)), default="paper", show_default=True)
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="Config override (repeatable).")
def config(preset: str, overrides: tuple[str, ...]) -> None:
    """Print the resolved config as JSON.

    Exactly the config.json a run with these settings saves. Docs: docs/algorithms.md (the paper preset is
    Table 3), docs/usage.md (presets and overrides).
    """
    click.echo(to_json(make_config(preset, overrides)))
