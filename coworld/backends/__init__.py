"""How the world model's loss is computed: the reference modules, or a fast path that proves it computes them.

The model a researcher reads and edits is :mod:`coworld.models` (plain PyTorch). A fast path reads the same
weights and computes the same loss in other forms; it trains only where it applies and where it has been checked
against the reference for the model as built: its structure (:func:`coworld.backends.cpu.unsupported`), then on a
batch of random frames, in float64 and with perturbed weights, the loss and every gradient, each pass from the same
random state (:func:`check_against_reference`). Where it cannot serve a model, the reason names the layer or the
loss term that differs, or says the model draws random numbers the check cannot hold equal. ``train.backend``:

* ``reference``: :class:`ReferencePath`, always;
* ``cpu``: :class:`~coworld.backends.cpu.CpuPath`, or :class:`~coworld.errors.ConfigError` saying why not;
* ``auto``: the CPU path on a CPU in float32, eager (``compile`` off), where it passes; else the reference, with a
  line saying why where the CPU path was a candidate. On a GPU, under autocast or ``torch.compile`` the reference
  runs: no fast path was measured to win there.

The reference never imports this package; the agents do.
"""

from __future__ import annotations

import copy
import sys
from typing import Any

import torch
from torch import Tensor

from coworld.backends.reference import ModelPath, ReferencePath
from coworld.config import Config
from coworld.errors import ConfigError
from coworld.models.world_model import WorldModel

__all__ = ["ModelPath", "ReferencePath", "check_against_reference", "cpu_reason", "select"]

TOLERANCE = 1e-6
"""The check's bound on ``max |fast - reference|`` over each gradient (and the loss), relative to the reference's
largest magnitude there. In float64 the two forms differ by summation order, and where the model rounds to float32
(its logits, the decoder's mean) by a float32 rounding; a different model differs by far more."""


def select(world_model: WorldModel, config: Config, device: torch.device, autocast: bool) -> ModelPath:
    """The path ``config.train.backend`` asks for, for ``world_model`` on ``device`` (``autocast``: under a reduced
    precision). ``cpu`` where the CPU path cannot serve raises :class:`ConfigError`; ``auto`` then prints one line
    (once per model) and takes the reference."""
    wanted = config.train.backend
    if wanted == "reference":
        return ReferencePath(world_model)
    if device.type != "cpu" or autocast or config.compile:
        if wanted == "cpu":
            why = "the run is on " + device.type if device.type != "cpu" else "precision is not fp32"
            why = "compile=true traces the reference" if config.compile else why
            raise ConfigError(f"train.backend=cpu cannot serve this run: {why}; use train.backend=auto or reference")
        return ReferencePath(world_model)
    key = _model_key(world_model)
    if key not in _CHECKED:
        _CHECKED[key] = cpu_reason(world_model)
        if _CHECKED[key] and wanted == "auto":
            print(
                f"backend: the CPU fast path steps aside ({_CHECKED[key]}); training with the reference model",
                file=sys.stderr,
            )
    reason = _CHECKED[key]
    if reason and wanted == "cpu":
        raise ConfigError(f"train.backend=cpu cannot compute this model: {reason}; use train.backend=auto or reference")
    if reason:
        return ReferencePath(world_model)
    from coworld.backends import cpu

    return cpu.CpuPath(world_model, *cpu.pixel_affine())


def check_config(
    config: Config, action_size: int, image_shape: tuple[int, int, int], device: torch.device, autocast: bool
) -> None:
    """What :func:`select` will decide for a run of ``config``, decided now, before the run writes anything: a
    refusal raises :class:`ConfigError`, a step aside prints its line here (once per process)."""
    if config.train.backend != "reference":
        model = WorldModel(config=config.world_model, action_size=action_size, image_shape=image_shape)
        select(model, config, device, autocast)


_CHECKED: dict[tuple, str] = {}
"""The CPU path's verdict per model structure and code (:func:`_model_key`): checked once per process."""


def _model_key(world_model: WorldModel) -> tuple:
    """What the CPU path's verdict on ``world_model`` depends on: its module tree as printed (layers, sizes,
    activations, epsilons), the config, and the code its modules and the pixel scaling run (a patched method, of a
    class or of one module, is another key)."""
    from coworld.models import world_model as world_model_module

    code = tuple(
        (type(module), getattr(type(module), "forward", None), vars(module).get("forward"))  # an instance's own too
        for module in world_model.modules()
    )
    methods = tuple(
        getattr(type(module), name, None)
        for module in (world_model, world_model.rssm)
        for name in (
            "loss",
            "image_nll",
            "observe",
            "obs_step",
            "img_step",
            "recurrent",
            "transition",
            "representation",
            "encode",
            "features",
            "_logits",
        )
    )
    return repr(world_model), world_model.config, code, methods, world_model_module.preprocess_image


def cpu_reason(world_model: WorldModel) -> str:
    """Why the CPU path cannot serve ``world_model``, or '' where it computes it (structure, then numbers)."""
    from coworld.backends import cpu

    reason = cpu.unsupported(world_model)
    if reason:
        return reason
    affine = cpu.pixel_affine()
    if affine is None:
        return "preprocess_image is not an affine map of the pixel values"
    return check_against_reference(world_model, lambda model: cpu.CpuPath(model, *affine))


SEED = 0
"""The global random state every pass of the check starts from (``torch.manual_seed``), inside
:func:`torch.random.fork_rng`: a model that draws from torch's global generator (a dropout) draws the same numbers
on both sides, and the caller's random state is left as it was."""


UNSEEDED = (
    "the model draws random numbers beyond its latent noise that the check cannot hold equal (from a generator other"
    " than torch's global one, say)"
)
"""The reason where two passes of the reference from the same seeds differ."""


def check_against_reference(world_model: WorldModel, make_path: Any) -> str:
    """'' where the path ``make_path(model)`` computes ``model``'s loss and every gradient as
    :meth:`WorldModel.loss` does, else what differs.

    Checked on a float64 copy of ``world_model`` with its weights perturbed (so no head starts at zero and hides a
    gradient) and a batch of random frames with a sequence starting mid-way. Every pass draws the same latent noise
    (a generator of its own) and starts from the same global random state (:data:`SEED`); in float64 the categorical
    draws of the two sides agree. Where two passes of the reference differ, the model draws random numbers the check
    cannot hold equal, and it says so. The fast path computes :meth:`WorldModel.loss` itself with only its image
    term replaced, so a difference after that is the image term's.
    """
    generator = torch.Generator().manual_seed(0)
    model = copy.deepcopy(world_model).to(device="cpu", dtype=torch.float64)
    with torch.no_grad():
        for param in model.parameters():
            param.add_(0.1 * torch.randn(param.shape, generator=generator, dtype=torch.float64))
    batch = _random_batch(model, generator)
    with torch.random.fork_rng(devices=[]):
        try:
            reference = _loss_and_grads(model, ReferencePath(model), batch)
            again = _loss_and_grads(model, ReferencePath(model), batch, grads=False)
        except Exception as error:  # a model the check cannot copy to float64 is not checked, so not taken
            return f"the check could not run the reference on a float64 copy: {type(error).__name__}"
        if _difference(again, {"loss": reference["loss"]}):
            return UNSEEDED
        try:
            fast = _loss_and_grads(model, make_path(model), batch)
        except Exception as error:  # the path cannot run this model: it steps aside, and says so
            return f"it failed on this model: {type(error).__name__}: {str(error).splitlines()[0][:200]}"
    difference = _difference(fast, reference)
    if difference:
        return f"the reference's image term (WorldModel.image_nll) is not the one the fast path computes: {difference}"
    return ""


def _difference(got: dict[str, Tensor], want: dict[str, Tensor]) -> str:
    """The first of ``want``'s entries (the loss, then each parameter's gradient) that ``got`` does not hold to
    :data:`TOLERANCE`, as a reason; '' where none."""
    for name, value in want.items():
        what = "the loss" if name == "loss" else f"{name}'s gradient"
        other = got.get(name)
        if other is None or other.shape != value.shape:
            return f"{what} has no counterpart"
        scale = float(value.abs().max())
        error = float((other - value).abs().max())
        if not error <= TOLERANCE * scale + 1e-12:
            return f"{what} differs by {error:.3g} (relative {error / max(scale, 1e-300):.2g})"
    return ""


def _random_batch(model: WorldModel, generator: torch.Generator, batch: int = 3, length: int = 6) -> dict[str, Tensor]:
    """Random uint8 frames ``(B, T, 64, 64, C)``, actions, rewards and flags, one sequence starting at step 3."""
    height, width, channels = model.image_shape
    is_first = torch.zeros(batch, length, dtype=torch.bool)
    is_first[:, 0] = True
    is_first[0, 3] = True
    return {
        "image": torch.randint(0, 256, (batch, length, height, width, channels), generator=generator).to(torch.uint8),
        "action": torch.rand(batch, length, model.action_size, generator=generator, dtype=torch.float64) * 2 - 1,
        "reward": torch.rand(batch, length, generator=generator, dtype=torch.float64),
        "is_first": is_first,
        "is_last": torch.zeros(batch, length, dtype=torch.bool),
        "is_terminal": torch.rand(batch, length, generator=generator) < 0.2,
    }


def _loss_and_grads(
    model: WorldModel, path: ModelPath, batch: dict[str, Tensor], grads: bool = True
) -> dict[str, Tensor]:
    """The loss and (with ``grads``) the gradient of every parameter of ``model`` through ``path``, the latent noise
    and the global random state from fixed seeds."""
    model.zero_grad(set_to_none=True)
    torch.manual_seed(SEED)
    with torch.set_grad_enabled(grads):
        _, aux = path.loss(path.prepare(dict(batch)), torch.Generator().manual_seed(1))
    out = {"loss": aux["loss"].detach().reshape(1)}
    if not grads:
        return out
    aux["loss"].backward()
    for name, param in model.named_parameters():
        out[name] = param.grad.detach().clone() if param.grad is not None else torch.zeros_like(param)
    model.zero_grad(set_to_none=True)
    return out
