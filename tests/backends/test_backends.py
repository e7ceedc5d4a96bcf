"""The boundary between the reference model and the CPU fast path (issue 50).

* Every edit a researcher makes trains the *edited* model: the path the run takes computes the edited model's loss
  and gradients exactly as the reference does (and not the unedited model's), or steps aside to the reference.
* A fast path that computes another model is caught: ``auto`` steps aside with one line, ``cpu`` is refused.
* The CPU path equals the reference on trained-looking weights at the tiny, cpu and paper widths: the world-model
  loss terms, every gradient, the actor-critic's losses after it, and the acting embedding against the training one.
* Where it steps aside, its one line says what happened: the layer or the loss term that differs from what the fast
  path serves, or that the model draws random numbers the check cannot hold equal; the check runs both sides from
  the same random state and leaves the caller's as it was.

A research edit that makes the default model leave the fast path fails one test,
:func:`test_the_default_model_takes_the_fast_path`; the tests that need a model the path serves take the
``fast_path`` fixture (conftest.py) and are skipped then, naming it.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from torch import nn

from coworld import backends
from coworld.agents.dreamerv2 import DreamerV2
from coworld.backends import ReferencePath, cpu
from coworld.cli import main
from coworld.config import Config, make_config
from coworld.errors import ConfigError
from coworld.models import world_model as world_model_module
from coworld.models.networks import ConvDecoder, LayerNormGRUCell
from coworld.models.world_model import WorldModel

CPU = torch.device("cpu")


@pytest.fixture(autouse=True)
def _fresh_verdicts(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test checks its models anew (the verdicts are cached per process)."""
    monkeypatch.setattr(backends, "_CHECKED", {})


def random_batch(batch: int, length: int, action_size: int, seed: int = 0) -> dict[str, torch.Tensor]:
    rng = np.random.default_rng(seed)
    is_first = np.zeros((batch, length), bool)
    is_first[:, 0] = True
    is_first[0, length // 2] = True
    return {
        "image": torch.as_tensor(rng.integers(0, 256, (batch, length, 64, 64, 3), dtype=np.uint8)),
        "action": torch.as_tensor(rng.uniform(-1, 1, (batch, length, action_size)), dtype=torch.float32),
        "reward": torch.as_tensor(rng.normal(size=(batch, length)), dtype=torch.float32),
        "is_first": torch.as_tensor(is_first),
        "is_last": torch.zeros(batch, length, dtype=torch.bool),
        "is_terminal": torch.as_tensor(rng.uniform(size=(batch, length)) < 0.1),
    }


def perturb(module: nn.Module, seed: int = 1, scale: float = 0.05) -> None:
    """Weights that look trained: every parameter moved off its initial value (zero-initialised heads included)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for param in module.parameters():
            param.add_(scale * torch.randn(param.shape, generator=generator))


def loss_and_grads(model: WorldModel, path: backends.ModelPath, batch: dict, seed: int = 7) -> dict[str, torch.Tensor]:
    """The loss, its terms and every parameter's gradient through ``path``, the latents drawn from ``seed``."""
    model.zero_grad(set_to_none=True)
    terms, aux = path.loss(path.prepare(dict(batch)), torch.Generator().manual_seed(seed))
    aux["loss"].backward()
    out = {"loss": aux["loss"].detach()} | {f"term/{k}": v.detach().mean() for k, v in terms.items()}
    for name, param in model.named_parameters():
        out[name] = param.grad.detach().clone()
    model.zero_grad(set_to_none=True)
    return out


def assert_same(got: dict[str, torch.Tensor], want: dict[str, torch.Tensor], rtol: float = 1e-4) -> None:
    assert got.keys() == want.keys()
    for name, value in want.items():
        scale = float(value.abs().max())
        error = float((got[name] - value).abs().max())
        assert error <= rtol * scale + 1e-6, f"{name}: differs by {error:.3g} (largest {scale:.3g})"


def differs(got: dict[str, torch.Tensor], want: dict[str, torch.Tensor]) -> bool:
    return abs(float(got["loss"]) - float(want["loss"])) > 1e-3 * abs(float(want["loss"]))


def build(config: Config, edit: Callable[[WorldModel], None] | None = None, seed: int = 0) -> WorldModel:
    torch.manual_seed(seed)
    model = WorldModel(config=config.world_model, action_size=3)
    if edit is not None:
        edit(model)
    perturb(model)
    return model


# -- the edits ----------------------------------------------------------------------------------------------------


def gru_candidate_sigmoid(self: LayerNormGRUCell, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """The GRU cell with its candidate's tanh replaced by a sigmoid (an edit of the cell's code)."""
    parts = self.norm(self.linear(torch.cat([x, h], dim=-1)))
    reset, cand, update = parts.split(self.size, dim=-1)
    cand = torch.sigmoid(torch.sigmoid(reset) * cand)
    update = torch.sigmoid(update + self.update_bias)
    return update * cand + (1.0 - update) * h


def pixels_0_to_1(image: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return image.movedim(-1, -3).to(dtype) / 255.0


def group_norm_in_decoder(model: WorldModel) -> None:
    layers = list(model.decoder.net)
    channels = layers[0].out_channels
    model.decoder.net = nn.Sequential(layers[0], nn.GroupNorm(4, channels), *layers[1:])


def extra_stride1_encoder_layer(model: WorldModel) -> None:
    layers = list(model.encoder.net)
    channels = layers[0].out_channels
    model.encoder.net = nn.Sequential(
        layers[0], layers[1], nn.Conv2d(channels, channels, 3, padding=1), nn.ELU(), *layers[2:]
    )


def second_posterior_hidden_layer(model: WorldModel) -> None:
    first, act, out = model.rssm.obs_out
    hidden = first.out_features
    model.rssm.obs_out = nn.Sequential(first, act, nn.Linear(hidden, hidden), nn.ELU(), out)


EDITS = {
    # name: (config overrides, edit of the built model, patches (object, attribute, value)), expected path
    "act=silu (conv stacks and RSSM)": (["world_model.act=silu"], None, (), "cpu"),
    "act=silu, norm=layer": (["world_model.act=silu", "world_model.norm=layer"], None, (), "reference"),
    "GRU candidate edited": ([], None, ((LayerNormGRUCell, "forward", gru_candidate_sigmoid),), "cpu"),
    "pixels scaled to [0, 1]": ([], None, ((world_model_module, "preprocess_image", pixels_0_to_1),), "cpu"),
    "GroupNorm in the decoder": ([], group_norm_in_decoder, (), "reference"),
    "extra stride-1 encoder layer": ([], extra_stride1_encoder_layer, (), "cpu"),
    "second posterior hidden layer": ([], second_posterior_hidden_layer, (), "cpu"),
    "other latent and deter sizes": (
        ["world_model.stoch=4", "world_model.classes=5", "world_model.deter=48"],
        None,
        (),
        "cpu",
    ),
    "GRU bias and eps 1e-3": (["world_model.gru_bias=true", "world_model.gru_eps=1e-3"], None, (), "cpu"),
    "encoder kernels 3,3,3,3,3": (["world_model.encoder_kernels=3,3,3,3,3"], None, (), "cpu"),
}


def test_the_default_model_takes_the_fast_path(preset_verdicts: dict[str, str]) -> None:
    """The models the presets build take the CPU fast path. Where this fails, a change to the model (a research
    edit, say) made it leave the path: legitimate, and the tests that need a model the path serves are skipped."""
    leaving = [f"\n  {name}: {reason}" for name, reason in preset_verdicts.items() if reason]
    if leaving:
        pytest.fail("the default model no longer takes the fast path:" + "".join(leaving), pytrace=False)


@pytest.mark.parametrize("name", list(EDITS))
def test_an_edited_model_trains_as_edited_never_as_before(
    name: str, monkeypatch: pytest.MonkeyPatch, fast_path: Callable[..., Config]
) -> None:
    overrides, edit, patches, expected = EDITS[name]
    if expected == "cpu":
        fast_path()
    batch = random_batch(2, 6, 3)
    unedited = build(make_config("tiny"))
    before = loss_and_grads(unedited, ReferencePath(unedited), batch)
    for owner, attribute, value in patches:
        monkeypatch.setattr(owner, attribute, value)
    config = make_config("tiny", [*overrides, "train.backend=auto"])
    model = build(config, edit)
    path = backends.select(model, config, CPU, autocast=False)
    assert path.name == expected
    got = loss_and_grads(model, path, batch)
    assert_same(got, loss_and_grads(model, ReferencePath(model), batch))
    assert differs(got, before), "the edit left the loss as it was: the test would not see the old model"


def test_a_fast_path_that_computes_another_model_steps_aside_or_is_refused(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], fast_path: Callable[..., Config]
) -> None:
    """A decoder form that is off by a little (its last layer's bias shifted by 0.01) fails the check."""
    config = fast_path()
    plain = cpu.decode_phases

    def wrong(decoder, feat, levels, offset=0.0):
        return plain(decoder, feat, levels, offset + 0.01)

    monkeypatch.setattr(cpu, "decode_phases", wrong)
    model = build(config)
    assert "differs by" in backends.check_against_reference(model, lambda m: cpu.CpuPath(m, *cpu.pixel_affine()))
    assert backends.select(model, config, CPU, autocast=False).name == "reference"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("backend: the CPU fast path steps aside") and "reference model" in err[0]
    with pytest.raises(ConfigError, match="train.backend=cpu cannot compute this model"):
        backends.select(model, make_config("tiny", ["train.backend=cpu"]), CPU, autocast=False)


def test_a_patched_reference_decoder_is_seen_by_the_numbers(
    monkeypatch: pytest.MonkeyPatch, fast_path: Callable[..., Config]
) -> None:
    """An edit of the decoder's code that its structure does not show (its output halved) makes the path step
    aside: the fast path does not know it, and the check on a batch does."""
    config = fast_path()
    plain = ConvDecoder.forward
    monkeypatch.setattr(ConvDecoder, "forward", lambda self, feat: 0.5 * plain(self, feat))
    assert backends.select(build(config), config, CPU, autocast=False).name == "reference"


# -- what a step aside says ---------------------------------------------------------------------------------------


def decoder_layer_replaced(index: int, make: Callable[[nn.ConvTranspose2d], nn.Module]) -> Callable[[WorldModel], None]:
    """An edit that puts ``make(layer)`` in place of the decoder's layer ``net[index]``."""

    def edit(model: WorldModel) -> None:
        layers = list(model.decoder.net)
        layers[index] = make(layers[index])
        model.decoder.net = nn.Sequential(*layers)

    return edit


def second_activation_in_the_decoder(model: WorldModel) -> None:
    layers = list(model.decoder.net)
    model.decoder.net = nn.Sequential(*layers[:4], nn.Tanh(), *layers[4:])


def tanh_after_the_decoder(model: WorldModel) -> None:
    model.decoder.net = nn.Sequential(*model.decoder.net, nn.Tanh())


STRUCTURE_REASONS = {
    # name: (config overrides, edit of the built model, the reason)
    "GroupNorm in the decoder": (
        [],
        group_norm_in_decoder,
        "the decoder has a GroupNorm between its transposed convolutions 1 and 2 (the fast path serves an ELU,"
        " SiLU, ReLU, GELU or Tanh alone there)",
    ),
    "act=silu, norm=layer": (
        ["world_model.act=silu", "world_model.norm=layer"],
        None,
        "the decoder has a ChannelNorm after each transposed convolution but the last (world_model.norm=layer;"
        " the fast path serves an ELU, SiLU, ReLU, GELU or Tanh alone there)",
    ),
    "other decoder kernels": (
        ["world_model.decoder_kernels=2,2,2,2,2,2"],
        None,
        "the decoder's kernels are (2, 2, 2, 2, 2, 2), not DreamerV2's 5, 5, 6, 6",
    ),
    "a Conv2d for the second transposed convolution": (
        [],
        decoder_layer_replaced(2, lambda t: nn.Conv2d(t.in_channels, t.out_channels, 3, padding=1)),
        "decoder layer 2 (decoder.net[2]) is a Conv2d, not a ConvTranspose2d of stride 2 (no padding, dilation or"
        " groups)",
    ),
    "a stride-1 transposed convolution": (
        [],
        decoder_layer_replaced(4, lambda t: nn.ConvTranspose2d(t.in_channels, t.out_channels, 6, padding=2)),
        "decoder layer 3 (decoder.net[4]) is a ConvTranspose2d of stride 1, padding 2, not a ConvTranspose2d of"
        " stride 2 (no padding, dilation or groups)",
    ),
    "a LeakyReLU for the first activation": (
        [],
        decoder_layer_replaced(1, lambda _: nn.LeakyReLU()),
        "the decoder has a LeakyReLU between its transposed convolutions 1 and 2 (the fast path serves an ELU,"
        " SiLU, ReLU, GELU or Tanh alone there)",
    ),
    "a second activation": (
        [],
        second_activation_in_the_decoder,
        "the decoder has an ELU and a Tanh between its transposed convolutions 2 and 3 (the fast path serves one ELU,"
        " SiLU, ReLU, GELU or Tanh there)",
    ),
    "a Tanh after the last transposed convolution": (
        [],
        tanh_after_the_decoder,
        "the decoder has a Tanh after its last transposed convolution (the fast path serves none there)",
    ),
}


@pytest.mark.parametrize("name", list(STRUCTURE_REASONS))
def test_a_step_aside_names_the_decoder_layer_that_differs(
    name: str, capsys: pytest.CaptureFixture[str], fast_path: Callable[..., Config]
) -> None:
    """The one line and the refusal name the layer (or the setting) that differs from what the fast path serves,
    not the kernels it was written for."""
    fast_path()
    overrides, edit, reason = STRUCTURE_REASONS[name]
    config = make_config("tiny", overrides)
    model = build(config, edit)
    assert cpu.unsupported(model) == reason
    assert backends.select(model, config, CPU, autocast=False).name == "reference"
    assert capsys.readouterr().err.splitlines() == [
        f"backend: the CPU fast path steps aside ({reason}); training with the reference model"
    ]
    with pytest.raises(ConfigError, match=re.escape(reason)):
        backends.select(model, make_config("tiny", [*overrides, "train.backend=cpu"]), CPU, autocast=False)


def test_an_elementwise_activation_alone_stays_on_the_fast_path(fast_path: Callable[..., Config]) -> None:
    """``world_model.act=silu`` is an elementwise activation the path serves; the norm is what leaves it."""
    fast_path()
    assert cpu.unsupported(build(make_config("tiny", ["world_model.act=silu"]))) == ""
    assert "ChannelNorm" in cpu.unsupported(build(make_config("tiny", ["world_model.norm=layer"])))


def dropout_in_the_heads(model: WorldModel) -> None:
    """A dropout after the first hidden layer of the reward and discount heads (one before the image term is
    computed, one after)."""
    for head in (model.reward_head, model.discount_head):
        assert head is not None
        layers = list(head.mlp.net)
        head.mlp.net = nn.Sequential(*layers[:2], nn.Dropout(0.3), *layers[2:])


def test_a_head_with_dropout_passes_the_check_and_the_callers_random_state_is_kept(
    fast_path: Callable[..., Config],
) -> None:
    """Every pass of the check starts from the same global random state, so a dropout draws the same masks on both
    sides: the fast path, which computes the heads as the reference does, passes and trains; the random state the
    caller had is the one it has after."""
    fast_path()
    config = make_config("tiny", ["world_model.pred_discount=true"])
    model = build(config, dropout_in_the_heads)
    batch = random_batch(2, 6, 3)
    torch.manual_seed(11)
    unseeded = [float(loss_and_grads(model, ReferencePath(model), batch)["loss"]) for _ in range(2)]
    assert unseeded[0] != unseeded[1], "the dropout draws nothing: the test would not see the random state"
    torch.manual_seed(12)
    before = torch.random.get_rng_state()
    assert backends.check_against_reference(model, lambda m: cpu.CpuPath(m, *cpu.pixel_affine())) == ""
    assert torch.equal(torch.random.get_rng_state(), before)
    path = backends.select(model, config, CPU, autocast=False)
    assert path.name == "cpu"
    torch.manual_seed(13)
    got = loss_and_grads(model, path, batch)
    torch.manual_seed(13)
    assert_same(got, loss_and_grads(model, ReferencePath(model), batch))


class OwnNoise(nn.Module):
    """Noise from a generator of the module's own, which no seed of the check reaches."""

    def __init__(self) -> None:
        super().__init__()
        self.generator = torch.Generator().manual_seed(5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + 0.1 * torch.randn(x.shape, generator=self.generator, dtype=x.dtype)


def test_a_model_drawing_random_numbers_the_check_cannot_hold_equal_is_named(
    capsys: pytest.CaptureFixture[str], fast_path: Callable[..., Config]
) -> None:
    config = fast_path()
    model = build(
        config, lambda m: setattr(m.reward_head.mlp, "net", nn.Sequential(OwnNoise(), *m.reward_head.mlp.net))
    )
    assert backends.select(model, config, CPU, autocast=False).name == "reference"
    assert capsys.readouterr().err.splitlines() == [
        "backend: the CPU fast path steps aside (the model draws random numbers beyond its latent noise that the"
        " check cannot hold equal (from a generator other than torch's global one, say)); training with the"
        " reference model"
    ]


def test_an_edited_image_term_is_named_with_the_gradient_it_changes(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], fast_path: Callable[..., Config]
) -> None:
    """The fast path runs :meth:`WorldModel.loss` with only its image term replaced, so where the reference's image
    term is edited (its features detached from the encoder and the RSSM), the line says it is that term, and which
    gradient shows it."""
    config = fast_path()
    plain = WorldModel.image_nll
    monkeypatch.setattr(WorldModel, "image_nll", lambda self, feat, batch: plain(self, feat.detach(), batch))
    assert backends.select(build(config), config, CPU, autocast=False).name == "reference"
    (line,) = capsys.readouterr().err.splitlines()
    prefix = (
        "backend: the CPU fast path steps aside (the reference's image term (WorldModel.image_nll) is not the one the"
        " fast path computes: "
    )
    assert line.startswith(prefix), line
    assert re.search(
        r"^encoder\.[\w.]+'s gradient differs by [\d.e+-]+ \(relative [\d.e+-]+\)\); training", line[len(prefix) :]
    )


def test_where_only_the_reference_runs() -> None:
    config = make_config("tiny")
    model = build(config)
    assert backends.select(model, make_config("tiny", ["train.backend=reference"]), CPU, False).name == "reference"
    assert backends.select(model, config, CPU, autocast=True).name == "reference"
    assert backends.select(model, make_config("tiny", ["compile=true"]), CPU, False).name == "reference"
    assert backends.select(model, config, torch.device("meta"), False).name == "reference"
    for overrides, message in ((["compile=true"], "compile"), ([], "precision")):
        cfg = make_config("tiny", ["train.backend=cpu", *overrides])
        with pytest.raises(ConfigError, match=message):
            backends.select(model, cfg, CPU, autocast=not overrides)


@pytest.mark.parametrize(
    ("preset", "overrides", "batch_size", "length"),
    [
        ("tiny", [], 4, 8),
        ("cpu", [], 4, 8),  # unimix, two-hot heads, LayerNorm + SiLU heads
        ("tiny", ["world_model.cnn_depth=16"], 2, 4),  # the decoder ends at 2 x 2 phases
        ("paper", [], 2, 3),  # the paper's widths (GRU bias, eps 1e-3)
    ],
)
def test_the_cpu_path_equals_the_reference_update(
    preset: str, overrides: list[str], batch_size: int, length: int, fast_path: Callable[..., Config]
) -> None:
    """World-model loss terms and every gradient, the actor-critic's losses after it, and the acting embedding
    against the training one, on trained-looking weights."""
    fast_path(preset, overrides)
    agents = {}
    for backend in ("reference", "cpu"):
        torch.manual_seed(0)
        cfg = make_config(preset, [*overrides, f"train.backend={backend}", "device=cpu"])
        agent = DreamerV2(config=cfg, action_size=3, device="cpu")
        perturb(agent.world_model)
        perturb(agent.actor_critic)
        agents[backend] = agent
    assert agents["cpu"].model_path.name == "cpu" and agents["reference"].model_path.name == "reference"
    batch = random_batch(batch_size, length, 3)
    grads = {name: loss_and_grads(a.world_model, a.model_path, batch) for name, a in agents.items()}
    assert_same(grads["cpu"], grads["reference"])
    metrics = {}
    for name, agent in agents.items():
        torch.manual_seed(3)
        _, aux = agent.model_path.loss(agent.model_path.prepare(dict(batch)), torch.Generator().manual_seed(7))
        post = {key: value.detach() for key, value in aux["post"].items()}
        torch.manual_seed(5)
        metrics[name] = agent.train_actor_critic(post, is_terminal=batch["is_terminal"])
    for key in ("actor/loss", "critic/loss"):
        assert metrics["cpu"][key] == pytest.approx(metrics["reference"][key], rel=1e-4, abs=1e-6), key
    agent = agents["cpu"]
    with torch.no_grad():
        acting = agent.world_model.encode(batch["image"][:, 0])
        training = agent.model_path.embed(agent.model_path.prepare(dict(batch)))[:, 0]
    torch.testing.assert_close(acting, training)


def test_backend_and_architecture_keys_are_range_checked() -> None:
    with pytest.raises(ConfigError, match="train.backend"):
        make_config("tiny", ["train.backend=gpu"])
    with pytest.raises(ConfigError, match="world_model.act"):
        make_config("tiny", ["world_model.act=swish"])
    with pytest.raises(ConfigError, match="world_model.norm"):
        make_config("tiny", ["world_model.norm=batch"])
    with pytest.raises(ConfigError, match="decodes 30 x 30"):
        make_config("tiny", ["world_model.decoder_kernels=5,5,6"])
    with pytest.raises(ConfigError, match="leaves no pixels"):
        make_config("tiny", ["world_model.encoder_kernels=4,4,4,4,4,4"])
    with pytest.raises(ConfigError, match="whole numbers separated by commas"):
        make_config("tiny", ["world_model.encoder_kernels=4,x"])
    assert make_config("tiny", ["world_model.encoder_kernels=3,3,3,3,3"]).world_model.encoder_kernels == (3,) * 5


def test_the_paper_preset_has_dreamerv2s_gru_and_older_configs_keep_theirs() -> None:
    from coworld.config import from_dict, to_dict

    paper = make_config("paper").world_model
    assert paper.gru_bias is True and paper.gru_eps == 1e-3
    saved = to_dict(make_config("paper"))
    del saved["world_model"]["gru_bias"], saved["world_model"]["gru_eps"]  # a config saved before these keys
    old = from_dict(saved).world_model
    assert old.gru_bias is False and old.gru_eps == 1e-5


# -- through the command ------------------------------------------------------------------------------------------


def train(dataset: Path, logdir: Path, *overrides: str, processes: ModuleType | None = None) -> list[dict]:
    """A short offline DreamerV2 run through ``coworld train`` (in this process, or as a real one with
    ``processes``); its logged metrics."""
    args = ["train", "--algo", "dreamerv2", "--target", "toy_reach", "--dataset", str(dataset), "--preset", "tiny"]
    args += ["--logdir", str(logdir), "--no-progress", "--device", "cpu"]
    for item in ("offline.updates=2", "offline.log_every=1", "offline.eval_episodes=1", "train.batch_size=4",
                 "train.seq_len=8", *overrides):  # fmt: skip
        args += ["--set", item]
    if processes is not None:
        done = processes.run_cli(*args)
        assert done.returncode == 0, done.stderr[-2000:]
    else:
        result = CliRunner().invoke(main, args)
        assert result.exit_code == 0, result.output
    return [json.loads(line) for line in (logdir / "metrics.jsonl").read_text().splitlines()]


def first_wm_loss(rows: list[dict]) -> float:
    return next(row["wm/loss"] for row in rows if "wm/loss" in row)


def test_the_command_trains_the_configured_activation_and_repeats_itself(
    tmp_path: Path, toy_dataset_writer, processes: ModuleType
) -> None:
    """Issue 50's done-when: ``--set world_model.act=silu`` trains a model whose first world-model loss equals the
    reference backend's and differs from the elu run's; two identical commands (the second a process of its own)
    log identical losses."""
    dataset = toy_dataset_writer(tmp_path / "toy.h5", episodes=2)
    silu = first_wm_loss(train(dataset, tmp_path / "silu", "world_model.act=silu"))
    silu_reference = first_wm_loss(
        train(dataset, tmp_path / "silu-ref", "world_model.act=silu", "train.backend=reference")
    )
    elu_rows = train(dataset, tmp_path / "elu", "world_model.act=elu")
    elu_reference = first_wm_loss(train(dataset, tmp_path / "elu-ref", "train.backend=reference"))
    assert silu == pytest.approx(silu_reference, rel=1e-5)
    assert first_wm_loss(elu_rows) == pytest.approx(elu_reference, rel=1e-5)
    assert abs(silu - first_wm_loss(elu_rows)) > 1e-4 * abs(silu)  # ten times the equalities' tolerance
    again = train(dataset, tmp_path / "elu-again", "world_model.act=elu", processes=processes)
    losses = [{k: v for k, v in row.items() if k.endswith("loss")} for row in elu_rows]
    assert losses == [{k: v for k, v in row.items() if k.endswith("loss")} for row in again]


def test_an_explicit_cpu_backend_it_cannot_serve_is_refused_before_anything_is_written(
    tmp_path: Path, toy_dataset_writer
) -> None:
    dataset = toy_dataset_writer(tmp_path / "toy.h5", episodes=2)
    logdir = tmp_path / "run"
    args = ["train", "--algo", "dreamerv2", "--target", "toy_reach", "--dataset", str(dataset), "--preset", "tiny"]
    args += ["--logdir", str(logdir), "--set", "train.backend=cpu", "--set", "world_model.norm=layer"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 2
    lines = [line for line in result.output.strip().splitlines() if line]
    assert len(lines) == 1 and "train.backend=cpu cannot compute this model" in lines[0], result.output
    assert not logdir.exists()


def test_a_verdict_is_not_reused_for_a_module_patched_on_its_own(fast_path: Callable[..., Config]) -> None:
    """The verdicts are cached per structure and code: a model like a checked one but with one module's own
    ``forward`` replaced is checked anew, and the CPU path steps aside for it."""
    config = fast_path()
    assert backends.select(build(config), config, CPU, autocast=False).name == "cpu"
    model = build(config)
    decoder = model.decoder
    decoder.forward = lambda feat: 0.5 * ConvDecoder.forward(decoder, feat)  # type: ignore[method-assign]
    assert backends.select(model, config, CPU, autocast=False).name == "reference"
