import dataclasses

import pytest

from coworld.config import PRESETS, SETTINGS, Config, config_keys, from_dict, make_config, to_dict
from coworld.errors import ConfigError


def test_presets_layer_on_defaults():
    paper, tiny = make_config("paper"), make_config("tiny")
    assert paper == Config()
    assert paper.world_model.deter == 600 and paper.world_model.stoch == 32 and paper.world_model.classes == 32
    assert (paper.train.batch_size, paper.train.seq_len) == (50, 50)
    assert (paper.coworld.beta2, paper.coworld.k, paper.coworld.alpha) == (1.5, 0.2, 0.2)
    assert tiny.world_model.deter < paper.world_model.deter
    assert tiny.actor_critic.lambda_ == paper.actor_critic.lambda_  # untouched keys keep the defaults


def test_overrides_cast_to_the_default_type():
    config = make_config("tiny", ["world_model.lr=3e-4", "train.steps=1e4", "coworld.align=false", "device=cpu"])
    assert config.world_model.lr == pytest.approx(3e-4)
    assert config.train.steps == 10_000 and isinstance(config.train.steps, int)
    assert config.coworld.align is False
    assert config.device == "cpu"


@pytest.mark.parametrize(
    "item, match",
    [
        ("world_model.nope=1", "unknown config key 'world_model.nope'"),
        ("nope=1", "unknown config key 'nope'"),
        ("train.steps=ten", "takes a whole number"),
        ("train.steps=1.5", "takes a whole number"),
        ("train.steps=1e30", "a whole number up to 9,223,372,036,854,775,807"),
        ("world_model.deter=1e400", "a whole number up to"),
        ("train.steps=true", "takes a whole number"),
        ("coworld.align=maybe", "takes true or false"),
        ("world_model=1", "is a section"),
        ("seed.x=1", "unknown config key"),
        ("novalue", "section.key=value"),
    ],
)
def test_bad_overrides_raise_one_line(item, match):
    with pytest.raises(ConfigError, match=match) as info:
        make_config("tiny", [item])
    assert "\n" not in str(info.value)


def test_a_list_of_kernels_is_taken_as_coworld_config_prints_it_too():
    plain = make_config("tiny", ["world_model.encoder_kernels=3,3,3,3,3"])
    for written in ("[3,3,3,3,3]", "[3, 3, 3, 3, 3]", " [ 3, 3, 3, 3, 3 ] "):
        assert make_config("tiny", [f"world_model.encoder_kernels={written}"]) == plain
    with pytest.raises(ConfigError, match="takes whole numbers separated by commas"):
        make_config("tiny", ["world_model.encoder_kernels=[3,3"])


def test_whole_numbers_written_as_floats_are_exact():
    config = make_config("tiny", ["train.steps=1e18", "train.batch_size=16.0"])
    assert config.train.steps == 10**18 and config.train.batch_size == 16  # not int(float("1e18")) rounding


def test_unknown_preset():
    with pytest.raises(ConfigError, match="unknown preset 'huge'"):
        make_config("huge")


def test_config_is_frozen_and_round_trips():
    config = make_config("tiny", ["seed=3"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.seed = 4  # type: ignore[misc]
    assert from_dict(to_dict(config)) == config
    assert "world_model.kl_balance" in config_keys(config)


def test_every_field_is_documented():
    import ast
    import inspect

    import coworld.config as module

    tree = ast.parse(inspect.getsource(module))
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name.endswith("Config") and node.name != "Config":
            body = node.body
            for i, stmt in enumerate(body):
                if isinstance(stmt, ast.AnnAssign):
                    following = body[i + 1] if i + 1 < len(body) else None
                    documented = isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                    assert documented, f"{node.name}.{stmt.target.id} has no docstring"


@pytest.mark.parametrize(
    "item, message",
    [  # the values a hostile user tried: each is refused when the config is built, with key, value and range
        ("coworld.k=2", "config key coworld.k=2.0 is out of range: it must be in [0, 1]"),
        ("world_model.lr=-1", "config key world_model.lr=-1.0 is out of range: it must be in (0, 0.1]"),
        ("actor_critic.discount=nan", "config key actor_critic.discount=nan is out of range: it must be in (0, 1]"),
        ("curl.batch_size=0", "config key curl.batch_size=0 is out of range: it must be >= 1"),
        ("coworld.iterations=0", "config key coworld.iterations=0 is out of range: it must be >= 1"),
        ("world_model.stoch=0", "config key world_model.stoch=0 is out of range: it must be >= 1"),
        ("precision=fp8", "config key precision='fp8' is out of range: it must be one of auto, bf16, fp32"),
        ("seed=-1", "config key seed=-1 is out of range: it must be in [0, 4294967295]"),
        ("world_model.lr=inf", "config key world_model.lr=inf is out of range: it must be in (0, 0.1]"),
        ("device=tpu", "it must be one of auto, cpu, cuda or cuda:N"),
        ("actor_critic.horizon=1", "it must be >= 2"),
        ("curl.crop=80", "curl.crop=80 is larger than the padded frame"),
        # the compile modes whose CUDA graphs raised on the paper preset's update on a GPU
        ("compile_mode=reduce-overhead", "compile_mode=reduce-overhead replays CUDA graphs"),
        ("compile_mode=max-autotune", "compile_mode=max-autotune replays CUDA graphs"),
        # sizes and weights a run would only trip over late: hours of Fisher batches, a rollout of a billion steps,
        # an MLP of 100,000 layers, a weight that is infinite in float32 (it trains to NaN)
        ("ewc.fisher_batches=1e12", "ewc.fisher_batches=1000000000000 is out of range: it must be in [1, 10000]"),
        ("lompo.horizon=1e9", "lompo.horizon=1000000000 is out of range: it must be in [1, 1000]"),
        ("lompo.actor_layers=1e5", "lompo.actor_layers=100000 is out of range: it must be in [0, 100]"),
        ("lompo.critic_layers=1e5", "lompo.critic_layers=100000 is out of range: it must be in [0, 100]"),
        ("ewc.weight=1e300", "ewc.weight=1e+300 is out of range: it must be in [0, 1000000000000]"),
        ("lompo.weight=1e300", "lompo.weight=1e+300 is out of range: it must be in [0, 1000000000000]"),
        ("penalty.weight=1e300", "penalty.weight=1e+300 is out of range: it must be in [0, 1000000000000]"),
        # learning rates and CoWorld's weights that blow a run up: to NaN within updates (1e30), or to a finite
        # world-model loss of 2e32 (lr 3) or 2e25 (lr 1) that ends "done"
        ("world_model.lr=1", "world_model.lr=1.0 is out of range: it must be in (0, 0.1]"),
        ("world_model.lr=1e30", "world_model.lr=1e+30 is out of range: it must be in (0, 0.1]"),
        ("world_model.lr=3", "world_model.lr=3.0 is out of range: it must be in (0, 0.1]"),
        ("actor_critic.actor_lr=1e30", "actor_critic.actor_lr=1e+30 is out of range: it must be in (0, 0.1]"),
        ("actor_critic.critic_lr=1e30", "actor_critic.critic_lr=1e+30 is out of range: it must be in (0, 0.1]"),
        ("curl.encoder_lr=2", "curl.encoder_lr=2.0 is out of range: it must be in (0, 0.1]"),
        ("drqbc.lr=2", "drqbc.lr=2.0 is out of range: it must be in (0, 0.1]"),
        ("lompo.critic_lr=2", "lompo.critic_lr=2.0 is out of range: it must be in (0, 0.1]"),
        ("coworld.zeta=1e30", "coworld.zeta=1e+30 is out of range: it must be in (0, 1000]"),
        ("coworld.alpha=1e308", "coworld.alpha=1e+308 is out of range: it must be in [0, 1000]"),
        ("coworld.beta2=1e30", "coworld.beta2=1e+30 is out of range: it must be in [0, 1000]"),
    ],
)
def test_values_out_of_range_are_refused_in_one_line(item, message):
    with pytest.raises(ConfigError) as info:
        make_config("tiny", [item])
    assert message in str(info.value) and "\n" not in str(info.value)


def test_every_non_boolean_field_has_a_range_and_the_presets_satisfy_them():
    import typing

    def unchecked(node, prefix=""):
        hints = typing.get_type_hints(type(node), include_extras=True)
        for f in dataclasses.fields(node):
            value = getattr(node, f.name)
            if dataclasses.is_dataclass(value):
                yield from unchecked(value, f"{prefix}{f.name}.")
            elif not isinstance(value, bool) and not getattr(hints[f.name], "__metadata__", ()):
                yield prefix + f.name

    assert list(unchecked(Config())) == []
    for preset in PRESETS:
        for settings in SETTINGS:
            make_config(f"{preset}+{settings}")  # raises if a preset or a settings group breaks a range
    assert make_config("tiny", ["device=cuda:1"]).device == "cuda:1"


def test_a_saved_config_is_checked_when_read_back():
    data = to_dict(make_config("tiny"))
    data["coworld"]["zeta"] = 0.0
    with pytest.raises(ConfigError, match="coworld.zeta=0.0 is out of range"):
        from_dict(data)


def test_a_config_saved_before_the_cap_form_existed_loads_with_the_form_it_ran() -> None:
    """Runs saved before ``coworld.cap_form`` read Eq. 6's term on the critic's mean; loading one must say so, not
    take today's default (its two-hot critic would be reported, resumed and evaluated as another model)."""
    saved = to_dict(make_config("cpu"))
    del saved["coworld"]["cap_form"]
    assert from_dict(saved).coworld.cap_form == "on_mean"
    assert from_dict(to_dict(make_config("cpu"))).coworld.cap_form == "shift"


def test_the_cpu_dv2_preset_is_the_cpu_preset_with_dreamerv2s_behaviour_learning() -> None:
    """A Gaussian critic bootstrapped from a slow critic copied every 100 updates, a Gaussian reward head, returns
    not normalised; every other value the ``cpu`` preset's, with each version's settings on top."""
    cpu, dv2 = to_dict(make_config("cpu")), to_dict(make_config("cpu-dv2"))
    differ = {
        f"{section}.{key}"
        for section, values in cpu.items()
        if isinstance(values, dict)
        for key in values
        if values[key] != dv2[section][key]
    }
    assert differ == {
        "actor_critic.critic_dist",
        "actor_critic.critic_target",
        "actor_critic.slow_target_every",
        "actor_critic.slow_target_fraction",
        "actor_critic.slow_regulariser",
        "actor_critic.return_norm",
        "world_model.reward_dist",
    }
    ac, wm = make_config("cpu-dv2").actor_critic, make_config("cpu-dv2").world_model
    assert (ac.critic_dist, ac.critic_target, ac.slow_target_every, ac.slow_target_fraction) == (
        "gaussian",
        "slow",
        100,
        1.0,
    )
    assert (ac.slow_regulariser, ac.return_norm, wm.reward_dist) == (0.0, False, "gaussian")
    assert make_config("cpu-dv2+later-dmc").coworld == make_config("cpu+later-dmc").coworld
