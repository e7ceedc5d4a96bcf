"""Single-op timings behind the DreamerV2 update's choices (issue 19): each row times our form against the plain
one it replaces, forward and backward where both run, on one CPU thread.

    python benchmarks/update_ops.py [--repeats 30]

Rows:
- ``exponential``: :func:`coworld.models.distributions.exponential_noise` against ``Tensor.exponential_`` for the
  latents of an imagination step at the tiny preset (512 x 8 x 8 numbers; the same numbers, checked);
- ``log_softmax``: the classes-first (log-)softmax of :mod:`coworld.models.distributions` against the plain one
  and against the transposed copy it replaced, at the RSSM posterior's sizes in batches of 8 and 16 sequences and
  of 64 and 512 states, forward and backward;
- ``ELU``: :class:`coworld.models.networks.ELU` (above its threshold NumPy's forward and the backward from the
  output) against ``F.elu``, forward and backward and forward alone, at an imagination step's hidden layer in the
  tiny preset (below the threshold: ``F.elu`` on both sides), the heads' on a whole imagined trajectory and the
  encoder's first layer's output, there also in place (``ELU(inplace=True)``, as the conv stacks run it, against
  PyTorch's ELU on a new tensor);
- ``max indices against argmax``: the categorical sample's class (:class:`OneHotCategorical.rsample`) at an imagination
  step of the tiny preset;
- ``encoder layer 2 input gradient``: its phases interleaved straight into the padded gradient against the
  transposed convolution then ``F.pad``;
- ``adamw``: the world model's AdamW step at the tiny preset, fused against PyTorch's default (``foreach``);
- ``decoder layer 2`` / ``3``: :func:`coworld.models.networks.conv_transpose_stride2` forward and backward, its
  backward PyTorch's own transposed-convolution backward against the phase convolution's autograd, at batch 512;
- ``decoder linear + layer 1 folded``: :meth:`coworld.models.networks.ConvDecoder._first_layer` with the linear
  layer's weights multiplied into the first transposed convolution's, against the two matrix products, forward and
  backward, at the tiny preset's sizes on 512 rows and the authors' (depth 32, 250 features) on 800;
- ``linear``: :func:`coworld.models.networks.linear`'s two forms, each forced, oneDNN's 1 x 1 convolution of the rows
  against the matrix product, forward alone and forward and backward, at the tiny preset's imagined heads and at the
  authors' sizes (the function takes the faster per shape);
- ``observe``: :meth:`coworld.models.rssm.RSSM.observe`'s posterior loop as one autograd function (``_Observe``, its
  backward through time by hand) against every step through autograd (``rssm.FUSED = False``), forward alone and
  forward and backward, at the tiny preset's sizes on batch 16 x 32;
- ``decoder layer 4``: :func:`coworld.models.networks.stride2_phases4` (2 x 2 phases in, 4 x 4 phases out) against
  :func:`~coworld.models.networks.stride2_phases` of the interleaved input, forward and backward, at batch 512, from
  8, 16 and 32 input channels (the decoder takes the faster: ``_PHASES4_BELOW_DEPTH``);
- ``bias gradient apart``: a convolution's backward with the bias gradient summed apart
  (:func:`coworld.models.networks._bias_grad`, the faster form on this machine) against PyTorch's backward computing
  it, at the decoder's transposed layers, its phase convolutions and the encoder's first layer, at the tiny preset's
  widths on batch 512 and the authors' (depth 32) on batch 800;
- ``bias gradient sum``: :func:`~coworld.models.networks._bias_grad_rows`'s matrix-vector product against
  ``grad.sum((0, 2, 3))`` on channels-last gradients of 8 to 48 channels (:func:`~coworld.models.networks._bias_grad`
  takes whichever is faster here, per shape).

Each cell is the median of ``--repeats`` timings (thread CPU time) after 3 warm-up calls.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from collections.abc import Callable

import torch

from coworld.config import make_config
from coworld.models import autotune
from coworld.models import rssm as rssm_module
from coworld.models.distributions import exponential_noise, log_softmax
from coworld.models.networks import (
    ELU,
    ConvDecoder,
    _bias_grad,
    _bias_grad_rows,
    _stride2_backward,
    _transposed_input_grad,
    conv_transpose_stride2,
    depth_to_space,
    linear,
    stride2_phases,
    stride2_phases4,
)
from coworld.models.world_model import WorldModel


def median_us(fn: Callable[[], object], repeats: int) -> float:
    """Median thread CPU time of ``fn()`` in microseconds, after 3 unmeasured calls."""
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        start = time.thread_time()
        fn()
        times.append(time.thread_time() - start)
    return statistics.median(times) * 1e6


def row(name: str, ours: float, plain: float) -> None:
    print(f"{name:<44}{ours:>12.1f}{plain:>12.1f}{plain / ours:>10.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"{'op':<44}{'ours us':>12}{'plain us':>12}{'speed-up':>10}")

    shape = (512, 8, 8)
    generator = torch.Generator()
    assert torch.equal(
        exponential_noise(shape, "cpu", generator.manual_seed(0)),
        torch.empty(shape).exponential_(generator=generator.manual_seed(0)),
    )
    row(
        "exponential, 512 x 8 x 8",
        median_us(lambda: exponential_noise(shape, "cpu", generator), args.repeats),
        median_us(lambda: torch.empty(shape).exponential_(generator=generator), args.repeats),
    )

    for rows in (8, 16, 64, 512):
        x = torch.randn(rows, 8, 8, requires_grad=True)
        grad = torch.randn(rows, 8, 8)

        def ours(x: torch.Tensor = x, grad: torch.Tensor = grad) -> None:
            torch.autograd.grad(log_softmax(x), x, grad)

        def plain(x: torch.Tensor = x, grad: torch.Tensor = grad) -> None:
            torch.autograd.grad(torch.log_softmax(x, -1), x, grad)

        def transposed(x: torch.Tensor = x, grad: torch.Tensor = grad) -> None:  # the form before classes-first
            out = torch.log_softmax(x.transpose(-1, -2).contiguous(), -2).transpose(-1, -2)
            torch.autograd.grad(out, x, grad)

        label = "used" if log_softmax(x.detach()).stride() != torch.log_softmax(x.detach(), -1).stride() else "not used"
        row(
            f"log_softmax classes-first ({label}), {rows} x 8 x 8",
            median_us(ours, args.repeats),
            median_us(plain, args.repeats),
        )
        row(
            f"  against the transposed copy, {rows} x 8 x 8",
            median_us(ours, args.repeats),
            median_us(transposed, args.repeats),
        )

    elu, elu_inplace = ELU(), ELU(inplace=True)
    for shape in ((512, 64), (5632, 64), (512, 8, 31, 31)):
        x = torch.randn(shape, requires_grad=True)
        if x.ndim == 4:
            x = x.detach().contiguous(memory_format=torch.channels_last).requires_grad_()
        grad = torch.randn_like(x)

        def ours(x: torch.Tensor = x, grad: torch.Tensor = grad) -> None:
            torch.autograd.grad(elu(x), x, grad)

        def plain(x: torch.Tensor = x, grad: torch.Tensor = grad) -> None:
            torch.autograd.grad(torch.nn.functional.elu(x), x, grad)

        size = " x ".join(map(str, shape))
        row(f"ELU forward + backward, {size}", median_us(ours, args.repeats), median_us(plain, args.repeats))
        data = x.detach()
        row(
            f"ELU forward, {size}",
            median_us(lambda d=data: elu(d), args.repeats),
            median_us(lambda d=data: torch.nn.functional.elu(d), args.repeats),
        )
        if x.ndim == 4:  # in place on a copy (the copy's time taken out of both)
            copy_us = median_us(data.clone, args.repeats)
            inplace_us = median_us(lambda d=data: elu_inplace(d.clone()), args.repeats) - copy_us
            plain_us = median_us(lambda d=data: torch.nn.functional.elu(d.clone()), args.repeats) - copy_us
            row(f"ELU forward in place, {size}", inplace_us, plain_us)

    race = torch.rand(512, 8, 8)
    assert torch.equal(race.max(-1, keepdim=True).indices, race.argmax(-1, keepdim=True))
    row(
        "max indices against argmax, 512 x 8 x 8",
        median_us(lambda: race.max(-1, keepdim=True).indices, args.repeats),
        median_us(lambda: race.argmax(-1, keepdim=True), args.repeats),
    )

    # The encoder's second layer (8 -> 16 channels, 31 x 31 -> 14 x 14): its input gradient against the
    # transposed convolution then padding it took before.
    weight = torch.randn(16, 8, 4, 4)
    grad = torch.randn(512, 16, 14, 14).contiguous(memory_format=torch.channels_last)
    padded = torch.nn.functional.pad(conv_transpose_stride2(grad, weight, None), (0, 1, 0, 1))
    assert torch.allclose(_transposed_input_grad(grad, weight, padded.shape[-2:]), padded, atol=1e-5)
    row(
        "encoder layer 2 input gradient, batch 512",
        median_us(lambda: _transposed_input_grad(grad, weight, padded.shape[-2:]), args.repeats),
        median_us(
            lambda: torch.nn.functional.pad(conv_transpose_stride2(grad, weight, None), (0, 1, 0, 1)), args.repeats
        ),
    )

    params = list(WorldModel(config=make_config("tiny").world_model, action_size=6).parameters())
    for param in params:
        param.grad = torch.randn_like(param)
    fused = torch.optim.AdamW(params, lr=1e-4, eps=1e-5, weight_decay=0.01, fused=True)
    default = torch.optim.AdamW(params, lr=1e-4, eps=1e-5, weight_decay=0.01)
    row("AdamW step, world model (tiny)", median_us(fused.step, args.repeats), median_us(default.step, args.repeats))

    for layer, (c_in, c_out, size, kernel) in (("2", (32, 16, 5, 5)), ("3", (16, 8, 13, 6))):
        x = torch.randn(512, c_in, size, size).contiguous(memory_format=torch.channels_last).requires_grad_()
        weight = torch.randn(c_in, c_out, kernel, kernel, requires_grad=True)
        bias = torch.randn(c_out, requires_grad=True)
        out_size = 2 * (size - 1) + kernel

        def phases(x: torch.Tensor = x, w: torch.Tensor = weight, b: torch.Tensor = bias, n: int = out_size):
            return depth_to_space(stride2_phases(x, w, b))[..., :n, :n]

        grad = torch.randn_like(phases())
        inputs = [x, weight, bias]

        def ours(inputs: list[torch.Tensor] = inputs, grad: torch.Tensor = grad) -> None:
            torch.autograd.grad(conv_transpose_stride2(*inputs), inputs, grad)

        def theirs(inputs: list[torch.Tensor] = inputs, grad: torch.Tensor = grad) -> None:
            torch.autograd.grad(phases(), inputs, grad)

        row(
            f"decoder layer {layer}, forward + backward", median_us(ours, args.repeats), median_us(theirs, args.repeats)
        )

    # The decoder's linear layer and its first transposed convolution (1 x 1 -> 5 x 5, a matrix product): their
    # weights multiplied first where ConvDecoder.folds_linear says so, against the two products one after the other.
    for rows, feat_size, depth in ((512, 128, 8), (800, 250, 32)):
        folded = ConvDecoder(feat_size=feat_size, channels=3, depth=depth)
        assert folded.folds_linear(rows)
        two = copy.deepcopy(folded)
        two.folds_linear = lambda rows: False  # type: ignore[method-assign]
        x = torch.randn(rows, feat_size, requires_grad=True)
        grad = torch.randn_like(folded._first_layer(x.detach()))

        def first_layer(decoder: ConvDecoder, x: torch.Tensor = x, grad: torch.Tensor = grad) -> None:
            torch.autograd.grad(decoder._first_layer(x), [x, *decoder.parameters()], grad, allow_unused=True)

        row(
            f"decoder linear + layer 1 folded, {rows} x {feat_size}, d {depth}",
            median_us(lambda d=folded: first_layer(d), args.repeats),
            median_us(lambda d=two: first_layer(d), args.repeats),
        )

    # linear's two forms, each forced: oneDNN's 1 x 1 convolution of the rows as pixels against the matrix product,
    # forward alone and forward + backward (the weight gradient a matrix product in both), at an imagined
    # trajectory's heads at the tiny preset (5,632 rows) and at the authors' sizes on batch 16 (12,800) and on batch
    # 150 (7,500 rows per step of the RSSM's loops; their imagined trajectories have 120,000).
    shapes = ((5632, 128, 64), (12800, 250, 400), (12800, 400, 400), (7500, 250, 400), (7500, 1030, 200))
    for rows, n_in, n_out in shapes:
        x = torch.randn(rows, n_in, requires_grad=True)
        weight = torch.randn(n_out, n_in, requires_grad=True)
        bias = torch.randn(n_out, requires_grad=True)
        grad = torch.randn(rows, n_out)

        def forced(form: str, backward: bool, x=x, w=weight, b=bias, g=grad) -> Callable[[], object]:  # noqa: ANN001
            def run() -> None:
                autotune._choices[("linear", tuple(x.shape), w.shape[0])] = form
                autotune._choices[("linear input grad", tuple(g.shape), x.shape[1])] = form
                if backward:
                    torch.autograd.grad(linear(x, w, b), [x, w, b], g)
                else:
                    with torch.no_grad():
                        linear(x, w, b)

            return run

        for backward in (False, True):
            row(
                f"linear {rows} x {n_in} -> {n_out}, {'fwd + bwd' if backward else 'forward'}",
                median_us(forced("onednn", backward), args.repeats),
                median_us(forced("matmul", backward), args.repeats),
            )

    # The RSSM's posterior loop at the tiny preset's sizes, batch 16 x 32: one autograd function (its backward
    # through time by hand) against every step through autograd.
    model = WorldModel(config=make_config("tiny").world_model, action_size=6)
    rssm = model.rssm
    embed = torch.randn(16, 32, model.encoder.embed_size, requires_grad=True)
    action, is_first = torch.randn(16, 32, 6), torch.zeros(16, 32, dtype=torch.bool)
    is_first[:, 0] = True

    def observe(fused: bool, backward: bool) -> Callable[[], object]:
        def run() -> None:
            rssm_module.FUSED = fused
            post, prior = rssm.observe(embed, action, is_first)
            if backward:
                loss = post["deter"].sum() + post["logits"].sum() + post["stoch"].sum() + prior["logits"].sum()
                loss.backward()
            rssm_module.FUSED = True

        return run

    for backward in (False, True):
        row(
            f"observe 16 x 32 fused, {'fwd + bwd' if backward else 'forward'}",
            median_us(observe(True, backward), args.repeats),
            median_us(observe(False, backward), args.repeats),
        )

    # The decoder's last layer (d -> 3 channels, 30 x 30 -> 64 x 64; d = 8 at the tiny preset): from the layer
    # before's 2 x 2 phases to the image's 4 x 4 phases, against the 2 x 2 output phases of the interleaved input.
    for c_in in (8, 16, 32):
        weight = torch.randn(c_in, 3, 6, 6, requires_grad=True)
        bias = torch.randn(3, requires_grad=True)
        x = torch.randn(512, c_in, 30, 30).contiguous(memory_format=torch.channels_last).requires_grad_()
        x_phases = x.detach().reshape(512, c_in, 15, 2, 15, 2).permute(0, 3, 5, 1, 2, 4).reshape(512, -1, 15, 15)
        x_phases = x_phases.contiguous(memory_format=torch.channels_last).requires_grad_()
        grad4 = torch.randn(512, 48, 16, 16).contiguous(memory_format=torch.channels_last)
        grad2 = torch.randn(512, 12, 32, 32).contiguous(memory_format=torch.channels_last)

        def ours(w: torch.Tensor = weight, b: torch.Tensor = bias, x: torch.Tensor = x_phases, g=grad4) -> None:
            torch.autograd.grad(stride2_phases4(x, w, b), [x, w, b], g)

        def plain(w: torch.Tensor = weight, b: torch.Tensor = bias, x: torch.Tensor = x, g=grad2) -> None:
            torch.autograd.grad(stride2_phases(x, w, b), [x, w, b], g)

        row(
            f"decoder layer 4 from {c_in} channels, fwd + bwd",
            median_us(ours, args.repeats),
            median_us(plain, args.repeats),
        )

    bias_rows(args.repeats)


def bias_rows(repeats: int) -> None:
    """The ``bias gradient`` rows: input shape, weight shape, padding (None: a transposed stride-2 layer), and
    whether the layer's input needs its gradient (not the encoder's first, which reads the images)."""
    layers = (
        ("decoder layer 2 (tiny)", (512, 32, 5, 5), (32, 16, 5, 5), None, True),
        ("decoder layer 3 phases (tiny)", (512, 16, 13, 13), (32, 16, 3, 3), 2, True),
        ("decoder layer 4 phases (tiny)", (512, 32, 15, 15), (48, 32, 2, 2), 1, True),
        ("encoder layer 1 (tiny)", (512, 12, 32, 32), (8, 12, 2, 2), 0, False),
        ("decoder layer 2 (authors', 800)", (800, 128, 5, 5), (128, 64, 5, 5), None, True),
        ("decoder layer 3 (authors', 800)", (800, 64, 13, 13), (64, 32, 6, 6), None, True),
        ("encoder layer 1 (authors', 800)", (800, 12, 32, 32), (32, 12, 2, 2), 0, False),
    )
    for name, x_shape, w_shape, padding, input_grad in layers:
        x = torch.randn(x_shape).contiguous(memory_format=torch.channels_last)
        weight = torch.randn(w_shape) * 0.05
        if padding is None:
            out = conv_transpose_stride2(x, weight, None)
        else:
            out = torch.nn.functional.conv2d(x, weight, padding=padding)
        grad = torch.randn_like(out)

        def backward(with_bias: bool, x=x, w=weight, g=grad, p=padding, need_x=input_grad):  # noqa: ANN001, ANN202
            mask = (need_x, True, with_bias)
            if p is None:
                return _stride2_backward(g, x, w, transposed=True, mask=mask)
            sizes = [w.shape[0]] if with_bias else None
            return torch.ops.aten.convolution_backward(
                g, x, w, sizes, [1, 1], [p, p], [1, 1], False, [0, 0], 1, list(mask)
            )

        row(
            f"bias gradient apart, {name}",
            median_us(lambda b=backward, g=grad: (b(False), _bias_grad(g, True)), repeats),
            median_us(lambda b=backward: b(True), repeats),
        )
    for shape in ((512, 8, 31, 31), (512, 12, 32, 32), (512, 16, 13, 13), (512, 32, 15, 15), (512, 48, 16, 16)):
        grad = torch.randn(shape).contiguous(memory_format=torch.channels_last)
        assert torch.allclose(_bias_grad_rows(grad), grad.sum((0, 2, 3)), rtol=1e-4, atol=1e-2)
        row(
            f"bias gradient sum, {' x '.join(map(str, shape))}",
            median_us(lambda g=grad: _bias_grad_rows(g), repeats),
            median_us(lambda g=grad: g.sum((0, 2, 3)), repeats),
        )


if __name__ == "__main__":
    main()
