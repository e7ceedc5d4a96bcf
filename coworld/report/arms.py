"""Which runs of a report are one arm, and the label that tells each arm from the others.

Runs are seeds of one arm where they are of one algorithm, carry one name (their sweep's variant, or without a
sweep the CoWorld terms they switch off: ``no-align``) and agree on their preset (run.json's ``preset``) and on every
value of their config (config.json, loaded with :func:`coworld.config.from_dict`) but the seed. Runs that differ in
anything else are never one arm, however they were made.

An arm's label is its name, then what sets it apart from the other runs of that name and algorithm in the report:

* the preset's parts that differ among them: the size where sizes differ (``tiny``), the settings group where
  groups differ (``+later-dmc``, not its nine keys; the defaults, ``table3``, unnamed);
* each config key whose value differs among them, where the arm's value is not its preset's default
  (``coworld.zeta=10``; a CoWorld term switched off by its ablation name, ``no-align``).

So ``coworld (coworld.zeta=10)`` beside ``coworld``, and ``coworld (zeta3, coworld.k=0.5)`` for runs a sweep named
zeta3 that were made otherwise than the other zeta3 runs. Differences are taken between the runs being reported,
not against today's defaults alone: a setting every run of the name shares (a sweep's shared overrides, or
``coworld.cap_form`` 'on_mean', which a config saved before that key existed loads with) names none of them, and
is named only beside runs that differ in it. Two arms never share a label: they differ in a key or a preset part
the label names for at least one of them (where both hold their preset's default, they agree).
"""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coworld.config import LEGACY_DEFAULTS, Config, from_dict, make_config, split_preset, to_dict
from coworld.errors import ConfigError

ABLATION_SWITCHES = (("align", "no-align"), ("reward_relabel", "no-relabel"), ("value_reg", "no-value-reg"))
"""CoWorld config switch -> the variant name of the run with that term off."""
NOT_A_DIFFERENCE = ("seed",)
"""Config keys in which the seeds of one arm differ."""


@dataclass(frozen=True)
class Settings:
    """What made a run, to tell it from others: its preset and its config's values (dotted key -> value as JSON
    holds it), without :data:`NOT_A_DIFFERENCE`."""

    preset: str | None
    values: Mapping[str, Any]

    @property
    def size(self) -> str | None:
        """The preset's size (``cpu``); the preset as written where it is not one this version knows."""
        return self._parts[0]

    @property
    def group(self) -> str | None:
        """The preset's settings group (``later-dmc``, ``table3`` where it names none)."""
        return self._parts[1]

    @property
    def _parts(self) -> tuple[str | None, str | None]:
        if self.preset is None:
            return None, None
        try:
            return split_preset(self.preset)
        except ConfigError:
            return self.preset, None

    @property
    def defaults(self) -> Mapping[str, Any]:
        """The values of the preset's config; the paper preset's where the preset is unknown."""
        known = self.preset if self.preset is not None and self.group is not None else None
        return _defaults(known)


def run_settings(config: Mapping[str, Any], preset: Any, where: Path, problems: list[str]) -> Settings:
    """The :class:`Settings` of a run: ``config`` (config.json, ``where``) loaded as this version loads it; a config
    it cannot load (a key since removed) is taken as saved over its preset's defaults, with a line in ``problems``."""
    preset = preset if isinstance(preset, str) and preset else None
    saved = {key: value for key, value in config.items() if key not in NOT_A_DIFFERENCE}
    try:
        values = dict(_loaded(json.dumps(saved, sort_keys=True)))
    except ConfigError as err:
        problems.append(
            f"{where}: not a config this version reads ({str(err).split('; ')[0]}); its values as saved label the run"
        )
        values = {**Settings(preset, {}).defaults, **_flat(saved)}
    return Settings(preset, {key: value for key, value in values.items() if key not in NOT_A_DIFFERENCE})


def arm_variants(runs: Sequence[tuple[str, str, Settings]]) -> list[str]:
    """Each run's variant, for runs given as (algorithm, name, settings): its name, then what tells its arm from the
    other arms of that algorithm and name (the module's rule), joined by ``, ``; '' for the algorithm as
    configured."""
    names: dict[tuple[str, str], list[int]] = {}
    for i, (algo, name, _) in enumerate(runs):
        names.setdefault((algo, name), []).append(i)
    variants = [name for _, name, _ in runs]
    for members in names.values():
        settings = [runs[i][2] for i in members]
        for i in members:
            parts = [runs[i][1], _preset_part(runs[i][2], settings), *_differences(runs[i][2], settings)]
            variants[i] = ", ".join(part for part in parts if part)
    return variants


def _preset_part(mine: Settings, among: Sequence[Settings]) -> str:
    """``tiny``, ``+later-dmc``, ``tiny+later-dmc`` or '': the parts of the preset that differ ``among`` the runs."""
    size = mine.size if len({s.size for s in among}) > 1 and mine.size else ""
    named = len({s.group for s in among}) > 1 and mine.group not in (None, "table3")
    return size + (f"+{mine.group}" if named else "")


def _differences(mine: Settings, among: Sequence[Settings]) -> list[str]:
    """Each key whose value differs ``among`` the runs and where ``mine`` is not its preset's default, in config
    order, as ``key=value`` (a CoWorld term switched off: its ablation name)."""
    keys = dict.fromkeys(key for s in among for key in s.values)
    varying = [key for key in keys if any(s.values.get(key) != among[0].values.get(key) for s in among)]
    defaults = mine.defaults
    return [_shown(key, mine.values.get(key)) for key in varying if mine.values.get(key) != defaults.get(key)]


def _shown(key: str, value: Any) -> str:
    """``coworld.zeta=10``, ``coworld.cap_critic=target_policy``; ``no-align`` for ``coworld.align`` false."""
    for switch, name in ABLATION_SWITCHES:
        if key == f"coworld.{switch}" and value is False:
            return name
    if isinstance(value, bool) or value is None:
        text = "null" if value is None else str(value).lower()
    elif isinstance(value, float):
        text = repr(value).removesuffix(".0")
    elif isinstance(value, list):
        text = ",".join(str(item) for item in value)
    else:
        text = str(value)
    return f"{key}={text}"


@functools.lru_cache(maxsize=256)
def _loaded(text: str) -> Mapping[str, Any]:
    """The values of a saved config (its JSON text) as :func:`coworld.config.from_dict` loads it. ``from_dict`` casts
    each key it is given (a millisecond or two a key): the keys saved at today's default are left for it to fill
    (those of :data:`~coworld.config.LEGACY_DEFAULTS` given, as it fills them otherwise), and each config, seeds
    aside, is loaded once."""
    return _flat(to_dict(from_dict(_without(json.loads(text), _defaults(None)))))


def _without(tree: Mapping[str, Any], defaults: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``tree`` less its values equal to ``defaults`` (flat), but for the keys of ``LEGACY_DEFAULTS``."""
    kept: dict[str, Any] = {}
    for key, value in tree.items():
        dotted = prefix + key
        if isinstance(value, Mapping):
            kept[key] = _without(value, defaults, f"{dotted}.")
        elif dotted in LEGACY_DEFAULTS or dotted not in defaults or defaults[dotted] != value:
            kept[key] = value
    return kept


@functools.cache
def _defaults(preset: str | None) -> Mapping[str, Any]:
    return _flat(to_dict(make_config(preset) if preset is not None else Config()))


def _flat(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested config dict as dotted key -> value, tuples as the lists JSON holds."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[prefix + key] = list(value) if isinstance(value, tuple) else value
    return flat
