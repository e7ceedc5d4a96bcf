"""CoWorld's settings as each version of the method gives them (``--preset SIZE+SETTINGS``), switch by switch.

The values are read off the sources: the paper text's Table 3 (the default, ``+table3``), the later paper's Table 8
(arXiv 2305.15260 v4) for DMC and for Meta-World, and the authors' release (qiwang067/CoWorld at 8bc8aaa,
``co_configs.yaml`` lines 37-39 and ``models.py`` lines 18, 108, 115-116 and 309-313). A settings group changes the
method's terms alone: each preset's sizes stay.
"""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.config import PRESETS, SETTINGS, make_config, to_dict
from coworld.errors import ConfigError

VERSIONS = {
    "table3": {
        "coworld.beta2": 1.5,
        "coworld.k": 0.2,
        "coworld.relabel": "table3",  # k * pred + (1 - k) * r_T
        "coworld.alpha": 0.2,
        "coworld.zeta": 1.0,
        "coworld.reward_mix": "sum",  # Eq. 5's two expectations added
        "coworld.align_on": "latent",
        "coworld.cap_critic": "source",
    },
    "later-dmc": {
        "coworld.beta2": 1.5,
        "coworld.k": 0.9,
        "coworld.relabel": "later",  # (1 - k) * pred + k * r_T
        "coworld.alpha": 1.0,
        "coworld.zeta": 1.0,  # no zeta
        "coworld.reward_mix": "eta",
        "coworld.eta_start": 1.0,
        "coworld.eta_end": 0.1,
        "coworld.align_on": "embedding",
        "coworld.cap_critic": "source",
    },
    "later-metaworld": {
        "coworld.beta2": 1.0,
        "coworld.k": 0.3,
        "coworld.relabel": "later",
        "coworld.alpha": 2.0,
        "coworld.zeta": 1.0,
        "coworld.reward_mix": "eta",
        "coworld.eta_start": 1.0,
        "coworld.eta_end": 0.1,
        "coworld.align_on": "embedding",
        "coworld.cap_critic": "source",
    },
    "release": {
        "coworld.beta2": 1.0,  # beta_2
        "coworld.k": 0.3,  # reward_k
        "coworld.relabel": "later",
        "coworld.alpha": 1.5,
        "coworld.zeta": 1.0,
        "coworld.reward_mix": "eta",
        "coworld.eta_start": 0.9875,  # max(1 - 2500 / 2e5, 0.2), a step fixed after the 2,500-step prefill
        "coworld.eta_end": 0.9875,
        "coworld.align_on": "embedding",
        "coworld.cap_critic": "source",
    },
}


def _value(config: dict, key: str) -> object:
    section, name = key.split(".")
    return config[section][name]


def test_every_version_is_a_settings_group_and_pins_its_values() -> None:
    assert set(SETTINGS) == set(VERSIONS)
    for name, pins in VERSIONS.items():
        for size in PRESETS:
            config = to_dict(make_config(f"{size}+{name}"))
            for key, value in pins.items():
                assert _value(config, key) == value, (size, name, key)


@pytest.mark.parametrize("name", sorted(VERSIONS))
def test_a_settings_group_changes_the_methods_terms_alone(name: str) -> None:
    for size in PRESETS:
        plain, versioned = to_dict(make_config(size)), to_dict(make_config(f"{size}+{name}"))
        changed = {
            f"{section}.{key}"
            for section, values in plain.items()
            if isinstance(values, dict)
            for key, value in values.items()
            if versioned[section][key] != value
        }
        assert changed <= set(VERSIONS[name]), changed


def test_the_default_is_table3_and_coworld_config_shows_a_version() -> None:
    assert to_dict(make_config("cpu")) == to_dict(make_config("cpu+table3"))
    result = CliRunner().invoke(main, ["config", "--preset", "tiny+release"])
    assert result.exit_code == 0, result.output
    shown = json.loads(result.output)
    assert shown["coworld"]["alpha"] == 1.5 and shown["world_model"]["cnn_depth"] == 8  # release terms, tiny sizes


@pytest.mark.parametrize("preset", ["cpu+later", "later-dmc", "cpu+later-dmc+release", "gpu"])
def test_an_unknown_preset_or_version_is_one_line_naming_both_lists(preset: str) -> None:
    listed = "choose one of: paper, cpu, tiny, cpu-dv2, optionally followed by \\+SETTINGS"
    with pytest.raises(ConfigError, match=listed):
        make_config(preset)
    result = CliRunner().invoke(main, ["config", "--preset", preset])
    assert result.exit_code == 2 and len(result.output.strip().splitlines()) == 1, result.output
