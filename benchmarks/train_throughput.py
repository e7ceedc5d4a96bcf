"""Training throughput: DreamerV2 updates per second, split into world model, imagination and actor-critic;
CoWorld's target and source updates; CURL and CURL+CQL updates.

Examples::

    python benchmarks/train_throughput.py --algo all                   # every algorithm, tiny preset, CPU
    python benchmarks/train_throughput.py                              # tiny preset on CPU (2 threads)
    python benchmarks/train_throughput.py --preset paper --device cpu --updates 1 --warmup 0
    python benchmarks/train_throughput.py --preset paper --device cuda --compare   # fp32 / bf16, eager / compiled
    # on a GPU, benchmarks/paper_gpu.py adds peak GPU memory, acting and the ETA of a paper CoWorld run
    python benchmarks/train_throughput.py --profile --threads 1 --updates 3 --set train.batch_size=16 \
        --set train.seq_len=32    # where an update's time goes, op by op
    python benchmarks/train_throughput.py --roofline --threads 1 --updates 5 --set train.batch_size=16 \
        --set train.seq_len=32    # and how close the counted work runs to this machine's matrix-product rate
    python benchmarks/train_throughput.py --threads 1 --set train.batch_size=16 --set train.seq_len=32 \
        --interleave /tmp/base --blocks 4 --updates 6    # this tree against another checkout, side by side
    python benchmarks/train_throughput.py --threads 1 --interleave /tmp/base --dreamerv3 /path/to/dreamerv3-torch \
        --peer-python /path/to/python --set train.batch_size=16 --set train.seq_len=32   # and a peer

Batches are random uint8 frames (throughput does not depend on content). Timings are medians over
``--updates`` measured steps after ``--warmup`` steps; CUDA work is synchronised before each clock read.

* ``wm``: one world-model update (encode, RSSM over B x T, decode, heads, backward, AdamW);
* ``imagine``: the imagination rollout alone (H steps from B * T start states, forward only with graph);
* ``actor_critic``: one full actor-critic update (imagination, losses, backward, two AdamW steps);
* ``train``: one complete :meth:`DreamerV2.train` call (both updates plus the batch transfer).

``--interleave PATH`` times whole updates (DreamerV2, CoWorld's target and source) of this tree and of the
checkout at ``PATH`` in alternating fresh processes, ``--blocks`` rounds, each process timing ``--updates`` calls
after ``--warmup``; it prints the min and median seconds per update of each side and block with the 1-minute load
average read before the block, and the seconds the warm-up updates took (with ``--set compile=true``, the
compilation; set ``TORCHINDUCTOR_CACHE_DIR`` to an empty folder to time it without inductor's on-disk cache).
This tree runs up to three times per block: with glibc's malloc as it comes (``new``), tuned
(:func:`coworld.allocator.keep_freed_memory`, ``new+malloc``: how the ``coworld`` command runs where tcmalloc is not
installed) and with tcmalloc preloaded (``new+tcmalloc``: how it runs where it is). With
``--dreamerv3 PATH`` each block also times NM512/dreamerv3-torch's update from its checkout at ``PATH`` (its
``Dreamer._train``: world model, then behaviour in imagination), at the tiny preset's sizes in its config names
(those benchmarks/learning_side_by_side.py matched) and the same batch; ``--authors PATH`` the CoWorld authors'
release's (its ``WorldModel._train`` in source pre-training mode, a plain DreamerV2 step, then
``ImagBehavior._train``) at its own DMC config (cnn 32, deter 200, continuous latents of 50, horizon 15) with our
batch; ``--r2dreamer PATH`` NM512/r2dreamer's (its ``Dreamer.update``, twice: its DreamerV3 with the image decoder,
and decoder-free R2-Dreamer) at the tiny preset's widths (:func:`r2dreamer_settings`), eager and in float32 (its
update autocasts to float16 on any device, which on a CPU is ten times slower). Their code is run from their
checkouts, not copied; ``--peer-python`` names an interpreter with torch and ruamel.yaml (and, for r2dreamer,
hydra-core and tensordict). ``--flops`` has every side count the floating-point operations of one more update, untimed
(PyTorch's ``FlopCounterMode``: matrix products and convolutions, forward and backward): on our sides after the
warm-up (with ``--warmup 0`` the counted update is the first); on the peers' before it. ``--ops`` has our sides
count the ATen operations of one more update, untimed (:class:`OpCounter`): in eager mode on a GPU each one not a
view is a kernel launch or more, which is what bounds an update there.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from learning_side_by_side import REFERENCE_NESTED, REFERENCE_SETTINGS
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import PRESETS, Config, make_config
from coworld.devices import resolve_device
from coworld.models.actor_critic import flatten_states
from coworld.models.networks import frozen_parameters


class OpCounter(TorchDispatchMode):
    """Counts the ATen operations dispatched inside it: ``total`` and ``views`` (those that only view memory)."""

    def __init__(self) -> None:
        super().__init__()
        self.total = self.views = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        self.total += 1
        self.views += bool(func.is_view)
        return func(*args, **(kwargs or {}))


@dataclass(frozen=True)
class Timing:
    """Median seconds per call of each part, and the resulting full updates per second."""

    label: str
    wm_s: float
    imagine_s: float
    actor_critic_s: float
    train_s: float

    @property
    def updates_per_s(self) -> float:
        return 1.0 / self.train_s


def random_batch(batch: int, length: int, action_size: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A replay-convention batch of random frames and actions."""
    rng = np.random.default_rng(seed)
    is_first = np.zeros((batch, length), bool)
    is_first[:, 0] = True
    flags = np.zeros((batch, length), bool)
    return {
        "image": rng.integers(0, 256, (batch, length, 64, 64, 3), dtype=np.uint8),
        "action": rng.uniform(-1, 1, (batch, length, action_size)).astype(np.float32),
        "reward": rng.normal(size=(batch, length)).astype(np.float32),
        "is_first": is_first,
        "is_last": flags,
        "is_terminal": flags,
    }


def _median_time(fn: Callable[[], object], device: torch.device, warmup: int, repeats: int) -> float:
    """Median wall-clock seconds of ``fn`` over ``repeats`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(
    preset: str, device: str, overrides: dict[str, object], label: str, warmup: int, repeats: int, action_size: int
) -> Timing:
    """Time each part of a DreamerV2 update for one configuration."""
    config = make_config(preset, {"device": device, **overrides})
    agent = DreamerV2(config=config, action_size=action_size)
    batch_np = random_batch(config.train.batch_size, config.train.seq_len, action_size)
    batch = agent.to_batch(batch_np)
    _, post = agent.train_world_model(batch)
    start = flatten_states(post)

    def imagine() -> None:
        with frozen_parameters(agent.world_model), agent._autocast():
            agent.actor_critic.imagine(agent.world_model, start)

    return Timing(
        label=label,
        wm_s=_median_time(lambda: agent.train_world_model(batch), agent.device, warmup, repeats),
        imagine_s=_median_time(imagine, agent.device, warmup, repeats),
        actor_critic_s=_median_time(lambda: agent.train_actor_critic(post), agent.device, warmup, repeats),
        train_s=_median_time(lambda: agent.train(batch_np), agent.device, warmup, repeats),
    )


def measure_others(preset: str, device: str, warmup: int, repeats: int, action_size: int) -> list[tuple[str, float]]:
    """Median seconds of one update of CoWorld's target and source agents, CURL and CURL+CQL."""
    from coworld.agents.coworld import CoWorld
    from coworld.agents.curl import Curl

    config = make_config(preset, {"device": device})
    dev = resolve_device(device)
    coworld = CoWorld(config=config, action_size=action_size, device=dev)
    batch = random_batch(config.train.batch_size, config.train.seq_len, action_size)
    out = [
        ("coworld target update", _median_time(lambda: coworld.train_target(batch), dev, warmup, repeats)),
        ("coworld source update", _median_time(lambda: coworld.train_source(batch, batch), dev, warmup, repeats)),
    ]
    c = config.curl
    rng = np.random.default_rng(0)
    frames = (c.batch_size, 3 * c.frame_stack, 64, 64)
    curl_batch = {
        "obs": rng.integers(0, 256, frames, dtype=np.uint8),
        "next_obs": rng.integers(0, 256, frames, dtype=np.uint8),
        "action": rng.uniform(-1, 1, (c.batch_size, action_size)).astype(np.float32),
        "reward": rng.normal(size=c.batch_size).astype(np.float32),
        "not_done": np.ones(c.batch_size, np.float32),
    }
    for cql in (False, True):
        agent = Curl(config=config, action_size=action_size, device=dev, cql=cql)
        seconds = _median_time(lambda agent=agent: agent.train(curl_batch), dev, warmup, repeats)
        out.append(("curl-cql update" if cql else "curl update", seconds))
    return out


def args_config(args: argparse.Namespace) -> Config:
    """The config of ``--preset``, ``--device`` and the ``--set`` overrides."""
    return make_config(args.preset, {"device": args.device, **dict(item.split("=", 1) for item in args.set)})


def worker(args: argparse.Namespace) -> None:
    """One side of ``--interleave``: time whole updates of the ``coworld`` on ``sys.path``, print JSON."""
    import coworld

    if args.allocator:
        from coworld import allocator

        allocator.keep_freed_memory()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    config = args_config(args)
    batch = random_batch(config.train.batch_size, config.train.seq_len, args.action_size)
    agent = DreamerV2(config=config, action_size=args.action_size)
    updates: dict[str, Callable[[], object]] = {"dreamerv2": lambda: agent.train(batch)}
    if args.algo in ("others", "all"):
        from coworld.agents.coworld import CoWorld

        pair = CoWorld(config=config, action_size=args.action_size, device=resolve_device(args.device))
        updates["coworld target"] = lambda: pair.train_target(batch)
        updates["coworld source"] = lambda: pair.train_source(batch, batch)
    out: dict[str, object] = {"coworld": str(Path(coworld.__file__).parent.parent)}
    warmup_s, flops, ops = {}, {}, {}
    for name, update in updates.items():
        start = time.perf_counter()
        for _ in range(args.warmup):
            update()
        warmup_s[name] = time.perf_counter() - start  # with compile=true, compilation happens here
        if args.flops:  # one more update after the warm-up, counted, not timed (see the module's docstring)
            with FlopCounterMode(display=False) as counter:
                update()
            flops[name] = counter.get_total_flops()
        if args.ops:  # and one more, its operations counted, not timed
            with OpCounter() as counter:
                update()
            ops[name] = [counter.total, counter.views]
        times = []
        for _ in range(args.updates):
            start = time.perf_counter()
            update()
            times.append(time.perf_counter() - start)
        out[name] = times
    print(json.dumps({**out, "warmup_s": warmup_s, "flops": flops, "ops": ops}))


_PEER_LOOP = textwrap.dedent(
    """
    flops = {}
    if run["flops"]:
        from torch.utils.flop_counter import FlopCounterMode
        with FlopCounterMode(display=False) as counter:
            update()
        flops["dreamerv2"] = counter.get_total_flops()
    for _ in range(run["warmup"]):
        update()
    times = []
    for _ in range(run["updates"]):
        start = time.perf_counter()
        update()
        times.append(time.perf_counter() - start)
    print(json.dumps({"coworld": reference, "dreamerv2": times, "flops": flops}))
    """
)
"""The end of each peer driver: ``update``, ``run`` and ``reference`` set by its start."""

_PEER_TIMING = (
    textwrap.dedent(
        """
    def update():  # as the peer's Dreamer._train: world model, then behaviour from its posterior
        post, _, _ = wm._train(data)
        reward = lambda f, s, a: wm.heads["reward"](wm.dynamics.get_feat(s)).mode()
        behavior._train(post, reward)
    """
    )
    + _PEER_LOOP
)
"""The end of the drivers of dreamerv3-torch and the authors' release: ``wm``, ``behavior``, ``data``, ``run`` and
``reference`` set by its start."""

_PEER_HEAD = textwrap.dedent(
    """
    import json, pathlib, sys, time, types
    reference, settings = sys.argv[1], json.loads(sys.argv[2])  # the peer's checkout, what to time and how
    sys.path.insert(0, reference)
    """
)
"""The start of the drivers of dreamerv3-torch and r2dreamer."""

DREAMERV3_DRIVER = (
    _PEER_HEAD
    + textwrap.dedent(
        """
    # Written by coworld's benchmarks/train_throughput.py: times NM512/dreamerv3-torch's update (world model, then
    # behaviour in imagination, as its Dreamer._train) on a random batch; prints JSON like our --worker.
    import argparse
    import numpy as np, ruamel.yaml, torch
    import models, tools
    run = settings.pop("run")
    torch.set_num_threads(run["threads"])
    config = ruamel.yaml.YAML(typ="safe").load((pathlib.Path(reference) / "configs.yaml").read_text())["defaults"]
    for key, value in settings.items():
        if isinstance(value, dict):
            config[key].update(value)
        else:
            config[key] = value
    parser = argparse.ArgumentParser()
    for key, value in sorted(config.items()):
        kind = tools.args_type(value)
        parser.add_argument(f"--{key}", type=kind, default=kind(value))
    config = parser.parse_args([])
    config.num_actions = run["action_size"]
    tools.set_seed_everywhere(0)
    space = types.SimpleNamespace(spaces={"image": types.SimpleNamespace(shape=(64, 64, 3))})
    wm = models.WorldModel(space, None, 0, config).to(config.device)
    behavior = models.ImagBehavior(config, wm).to(config.device)
    wm.requires_grad_(False)  # as its main() does; _train enables what it trains
    behavior.requires_grad_(False)
    rng = np.random.default_rng(0)
    batch, length, actions = config.batch_size, config.batch_length, config.num_actions
    first = np.zeros((batch, length), np.float32)
    first[:, 0] = 1.0
    data = {
        "image": rng.integers(0, 256, (batch, length, 64, 64, 3), dtype=np.uint8),
        "action": rng.uniform(-1, 1, (batch, length, actions)).astype(np.float32),
        "reward": rng.normal(size=(batch, length)).astype(np.float32),
        "discount": np.ones((batch, length), np.float32),
        "is_first": first,
        "is_terminal": np.zeros((batch, length), np.float32),
    }
    """
    )
    + _PEER_TIMING
)


AUTHORS_DRIVER = (
    textwrap.dedent(
        """
    # Written by coworld's benchmarks/train_throughput.py: times the CoWorld authors' release's DreamerV2 update (its
    # WorldModel._train in the source-domain pre-training mode, a plain DreamerV2 step, then ImagBehavior._train, as
    # its Dreamer._train) on a random batch at its DMC config; prints JSON like our --worker.
    import argparse, json, pathlib, sys, time, types
    reference, run = sys.argv[1], json.loads(sys.argv[2])
    sys.path.insert(0, reference)
    sys.modules.setdefault("wandb", types.ModuleType("wandb"))  # imported by its tools.py, unused here
    import numpy as np, ruamel.yaml, torch
    import models, tools
    torch.set_num_threads(run["threads"])
    configs = ruamel.yaml.YAML(typ="safe").load((pathlib.Path(reference) / "co_configs.yaml").read_text())
    defaults = {**configs["defaults"], **configs["dmc"]}
    defaults.update(device="cpu", precision=32, sc_domain=True, pre_train=True)
    defaults.update(batch_size=run["batch_size"], batch_length=run["batch_length"])
    parser = argparse.ArgumentParser()
    for key, value in sorted(defaults.items()):
        kind = tools.args_type(value)
        parser.add_argument(f"--{key}", type=kind, default=kind(value))
    config = parser.parse_args([])
    config.act = getattr(torch.nn, config.act)
    config.num_actions = run["action_size"]
    for key in ("actor_entropy", "actor_state_entropy", "imag_gradient_mix"):  # as its Dreamer.__init__ does
        config.__dict__[key] = lambda x=getattr(config, key): tools.schedule(x, 0)
    torch.manual_seed(0)
    wm = models.WorldModel(0, config).to("cpu")
    behavior = models.ImagBehavior(config, wm).to("cpu")
    wm.requires_grad_(False)
    behavior.requires_grad_(False)
    rng = np.random.default_rng(0)
    batch, length, actions = config.batch_size, config.batch_length, config.num_actions
    data = {
        "image": rng.integers(0, 256, (batch, length, 64, 64, 3), dtype=np.uint8),
        "action": rng.uniform(-1, 1, (batch, length, actions)).astype(np.float32),
        "reward": rng.normal(size=(batch, length)).astype(np.float32),
        "discount": np.ones((batch, length), np.float32),
    }
    """
    )
    + _PEER_TIMING
)


R2DREAMER_DRIVER = (
    _PEER_HEAD
    + textwrap.dedent(
        """
    # Written by coworld's benchmarks/train_throughput.py: times NM512/r2dreamer's update (its Dreamer.update: one
    # backward through world model, imagination losses and replay value, then its optimiser step) on a random batch
    # at the sizes given; prints JSON like our --worker.
    import numpy as np, torch
    from hydra import compose, initialize_config_dir
    from tensordict import TensorDict
    import dreamer, tools
    run = settings.pop("run")
    torch.set_num_threads(run["threads"])
    with initialize_config_dir(config_dir=str(pathlib.Path(reference) / "configs"), version_base=None):
        config = compose(config_name="configs", overrides=[f"{key}={value}" for key, value in settings.items()])
    # Its update autocasts to float16 whatever the device; on a CPU that is 10x slower than float32, so float32.
    dreamer.autocast = lambda device_type, dtype: torch.autocast(device_type, enabled=False)
    tools.set_seed_everywhere(0)
    space = types.SimpleNamespace(spaces={"image": types.SimpleNamespace(shape=(64, 64, 3))})
    agent = dreamer.Dreamer(config.model, space, types.SimpleNamespace(shape=(run["action_size"],))).to("cpu")
    rng = np.random.default_rng(0)
    batch, length, actions = config.batch_size, config.batch_length, run["action_size"]
    first = np.zeros((batch, length, 1), bool)  # its environments give scalars a trailing axis of 1
    first[:, 0] = True
    arrays = {
        "image": rng.integers(0, 256, (batch, length, 64, 64, 3), dtype=np.uint8),
        "action": rng.uniform(-1, 1, (batch, length, actions)).astype(np.float32),
        "reward": rng.normal(size=(batch, length, 1)).astype(np.float32),
        "is_first": first,
        "is_terminal": np.zeros((batch, length, 1), bool),
        "is_last": np.zeros((batch, length, 1), bool),
    }

    class Replay:  # its Buffer's interface: a fresh batch (its update scales the images in place), start latents
        def sample(self):
            data = TensorDict({k: torch.as_tensor(v.copy()) for k, v in arrays.items()}, batch_size=(batch, length))
            return data, None, agent.rssm.initial(batch)

        def update(self, index, stoch, deter):
            pass

    replay = Replay()
    update = lambda: agent.update(replay)
    """
    )
    + _PEER_LOOP
)


def r2dreamer_settings(config: Config, rep_loss: str) -> dict[str, str]:
    """r2dreamer's Hydra overrides at our widths and batch (at the tiny preset's sizes only, as
    :func:`dreamerv3_settings`): the same encoder and decoder channels (``cnn_depth`` x 1, 2, 4, 8), deterministic
    and hidden sizes, latents, units and horizon; its own layers otherwise (5 x 5 stride-1 convolutions with
    max-pooling, upsampling in the decoder, block-diagonal GRU of 8 blocks), eager."""
    dreamerv3_settings(config)  # the same size check
    wm, ac = config.world_model, config.actor_critic
    return {
        "device": "cpu",
        "batch_size": str(config.train.batch_size),
        "batch_length": str(config.train.seq_len),
        "model.compile": "False",
        "model.rep_loss": rep_loss,
        "model.depth": str(wm.cnn_depth),
        "model.encoder.cnn.mults": "[1,2,4,8]",
        "model.decoder.cnn.mults": "[1,2,4,8]",
        "model.deter": str(wm.deter),
        "model.hidden": str(wm.hidden),
        "model.rssm.stoch": str(wm.stoch),
        "model.discrete": str(wm.classes),
        "model.units": str(ac.units),
        "model.imag_horizon": str(ac.horizon),
    }


def dreamerv3_settings(config: Config) -> dict[str, object]:
    """dreamerv3-torch's config at our network sizes and batch (the tiny and cpu presets' sizes, which
    benchmarks/learning_side_by_side.py matched in its names); raises if ``config`` has other sizes."""
    wm, ac = config.world_model, config.actor_critic
    ours = (wm.cnn_depth, wm.deter, wm.hidden, wm.stoch, wm.classes, wm.mlp_units, ac.units, ac.horizon)
    matched = (8, 64, 64, 8, 8, 64, 64, 10)
    if ours != matched:
        print(f"--dreamerv3 compares at the tiny preset's sizes {matched}, not {ours}", file=sys.stderr)
        raise SystemExit(2)
    keys = ("dyn_deter", "dyn_hidden", "dyn_stoch", "dyn_discrete", "units", "model_lr", "imag_horizon", "compile")
    settings: dict[str, object] = {key: REFERENCE_SETTINGS[key] for key in keys}
    settings.update(REFERENCE_NESTED)
    settings.update(batch_size=config.train.batch_size, batch_length=config.train.seq_len, precision=32, device="cpu")
    return settings


def interleave(args: argparse.Namespace) -> None:
    """Alternate worker processes of this tree and of ``args.interleave``; print min / median per block."""
    here = Path(__file__).resolve().parent.parent
    from coworld import allocator  # this tree's (a worker imports the coworld of its side's checkout)

    # (label, checkout, allocator): "" glibc's defaults, "malloc" glibc tuned, "tcmalloc" preloaded.
    sides = [("base", Path(args.interleave).resolve(), ""), ("new", here, ""), ("new+malloc", here, "malloc")]
    tcmalloc = allocator.tcmalloc_preload()
    if tcmalloc is not None:
        sides.append(("new+tcmalloc", here, "tcmalloc"))
    else:
        print("tcmalloc is not installed (or COWORLD_MALLOC=glibc): no new+tcmalloc side", file=sys.stderr)
    # The peers: side label -> the driver's command (their checkout's path and a JSON of what to time).
    config = args_config(args)
    run = {"threads": args.threads, "updates": args.updates, "warmup": args.warmup, "action_size": args.action_size}
    run["flops"] = args.flops
    peers: dict[str, list[str]] = {}
    if args.dreamerv3:
        sides.append(("dreamerv3-torch", Path(args.dreamerv3).resolve(), ""))
        settings = {**dreamerv3_settings(config), "run": run}
        peers["dreamerv3-torch"] = [args.peer_python, "-c", DREAMERV3_DRIVER, str(sides[-1][1]), json.dumps(settings)]
    if args.r2dreamer:
        for label, rep_loss in (("r2dreamer, decoder", "dreamer"), ("r2dreamer, R2", "r2dreamer")):
            sides.append((label, Path(args.r2dreamer).resolve(), ""))
            settings = {**r2dreamer_settings(config, rep_loss), "run": run}
            peers[label] = [args.peer_python, "-W", "ignore", "-c", R2DREAMER_DRIVER, str(sides[-1][1])]
            peers[label].append(json.dumps(settings))
    if args.authors:
        sides.append(("authors' release", Path(args.authors).resolve(), ""))
        batch = {"batch_size": config.train.batch_size, "batch_length": config.train.seq_len}
        peers["authors' release"] = [args.peer_python, "-c", AUTHORS_DRIVER, str(sides[-1][1]), json.dumps(run | batch)]
    common = ["--threads", str(args.threads), "--updates", str(args.updates), "--warmup", str(args.warmup)]
    common += ["--preset", args.preset, "--device", args.device, "--algo", args.algo]
    common += ["--action-size", str(args.action_size)] + [f"--set={item}" for item in args.set]
    common += ["--flops"] if args.flops else []
    common += ["--ops"] if args.ops else []
    rows = []
    for block in range(args.blocks):
        for label, tree, malloc in sides:
            with open("/proc/loadavg") as f:
                load = float(f.read().split()[0])
            if label in peers:
                env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
                command = peers[label]
            else:
                env = {**os.environ, "PYTHONPATH": str(tree), **(tcmalloc if malloc == "tcmalloc" else {})}
                tuned = ["--allocator"] if malloc == "malloc" else []  # glibc tuned in the worker
                command = [sys.executable, __file__, "--worker", *common, *tuned]
            stdout = subprocess.run(command, env=env, cwd=tree, capture_output=True, check=True, text=True).stdout
            result = json.loads(stdout.strip().splitlines()[-1])  # the peer prints its model's shapes first
            assert Path(result.pop("coworld")) == tree, "the worker imported another checkout"
            warmup_s, flops, ops = result.pop("warmup_s", {}), result.pop("flops", {}), result.pop("ops", {})
            for name, times in result.items():
                rows.append((block, label, name, load, min(times), statistics.median(times)))
                print(
                    f"block {block} {label:<20}{name:<16} load {load:5.2f}  min {min(times):.3f} s  median "
                    f"{statistics.median(times):.3f} s"
                    + (f"  (warm-up {warmup_s[name]:.1f} s)" if name in warmup_s else "")
                    + (f"  {flops[name] / 1e9:.1f} GFLOP" if name in flops else "")
                    + (f"  {ops[name][0]:,} ATen ops ({ops[name][1]:,} views)" if name in ops else ""),
                    flush=True,
                )
    print(f"\n{'update':<16}{'side':<20}{'min s (best block)':>20}{'median of block medians':>25}{'x base':>8}")
    for name in dict.fromkeys(row[2] for row in rows):
        base = statistics.median(r[5] for r in rows if r[2] == name and r[1] == "base")
        for label, _, _ in sides:
            mine = [r for r in rows if r[2] == name and r[1] == label]
            if not mine:  # the peer times the DreamerV2 update only
                continue
            median = statistics.median(r[5] for r in mine)
            print(f"{name:<16}{label:<20}{min(r[4] for r in mine):>20.3f}{median:>25.3f}{base / median:>8.2f}")
    if args.json:
        keys = ("block", "side", "update", "load", "min_s", "median_s")
        Path(args.json).write_text(json.dumps([dict(zip(keys, row, strict=True)) for row in rows], indent=2))


def profile(args: argparse.Namespace) -> None:
    """torch.profiler's table of ``--updates`` whole DreamerV2 updates (after ``--warmup``), ops by self CPU time,
    with the CLI's malloc settings."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    from coworld import allocator

    allocator.keep_freed_memory()
    config = args_config(args)
    agent = DreamerV2(config=config, action_size=args.action_size)
    batch = random_batch(config.train.batch_size, config.train.seq_len, args.action_size)
    for _ in range(args.warmup):
        agent.train(batch)
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(args.updates):
            agent.train(batch)
    print(f"{args.updates} updates; divide the times by {args.updates} for one")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    if args.roofline:
        with FlopCounterMode(display=False) as counter:
            agent.train(batch)
        print(roofline(prof, counter.get_flop_counts()["Global"], args.updates, args.threads))


ROOFLINE_CLASSES = {
    "convolution forward": ("aten.convolution", "aten::convolution"),
    "convolution backward": ("aten.convolution_backward", "aten::convolution_backward"),
    "matrix products": ("aten.mm aten.addmm aten.bmm aten.baddbmm", "aten::mm aten::addmm aten::bmm aten::baddbmm"),
}
"""What ``--roofline`` counts: class -> (``FlopCounterMode``'s op names, the profiler's event names), space-separated.
The profiler's time of an event is its total, children included (``aten::convolution`` runs its kernel in a child)."""


def roofline(prof: Any, flops: dict[Any, int], updates: int, threads: int) -> str:
    """The counted work of one update (``flops``: ``FlopCounterMode``'s global counts) beside the profiled time of
    the same ops over ``updates`` updates (``prof``), the rate each class ran at, this machine's single-precision
    matrix-product rate on ``threads`` threads, and the time the counted work would take at that rate."""
    events = {event.key: event for event in prof.key_averages()}
    total_ms = sum(event.self_cpu_time_total for event in events.values()) / 1e3 / updates
    lines = [f"{'class':<24}{'GMAC':>8}{'ms/update':>11}{'GMAC/s':>8}"]
    macs_all = ms_all = 0.0
    for label, (counted, profiled) in ROOFLINE_CLASSES.items():
        macs = sum(n for op, n in flops.items() if str(op) in counted.split()) / 2e9
        ms = sum(events[name].cpu_time_total for name in profiled.split() if name in events) / 1e3 / updates
        macs_all, ms_all = macs_all + macs, ms_all + ms
        lines.append(f"{label:<24}{macs:>8.3f}{ms:>11.1f}{macs / ms * 1e3 if ms else 0.0:>8.1f}")
    lines.append(f"{'all counted':<24}{macs_all:>8.3f}{ms_all:>11.1f}{macs_all / ms_all * 1e3:>8.1f}")
    lines.append(f"{'the rest (not counted)':<24}{'':>8}{total_ms - ms_all:>11.1f}")
    lines.append(f"{'the update (profiled)':<24}{'':>8}{total_ms:>11.1f}")
    peak = matmul_rate(2048)
    lines.append(
        f"float32 2048^3 matrix product on {threads} thread(s): {peak:.1f} GMAC/s; the counted work at that rate: "
        f"{macs_all / peak * 1e3:.1f} ms an update"
    )
    return "\n".join(lines)


def matmul_rate(n: int, repeats: int = 5) -> float:
    """GMAC/s of the best of ``repeats`` float32 ``n x n`` matrix products on torch's current threads."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return n**3 / best / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", choices=sorted(PRESETS))
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--updates", type=int, default=20, help="measured calls per part")
    parser.add_argument("--warmup", type=int, default=3, help="unmeasured calls per part first")
    parser.add_argument("--action-size", type=int, default=6)
    parser.add_argument(
        "--compare", action="store_true", help="fp32 / bf16 autocast, each eager and torch.compiled (meant for CUDA)"
    )
    parser.add_argument(
        "--algo",
        default="dreamerv2",
        choices=["dreamerv2", "others", "all"],
        help="dreamerv2 (with its breakdown), others (CoWorld, CURL, CURL+CQL) or all",
    )
    parser.add_argument("--json", default=None, help="also write the timings to this JSON file")
    parser.add_argument("--set", action="append", default=[], help="config override KEY=VALUE (repeatable)")
    parser.add_argument("--interleave", metavar="PATH", help="time against the coworld checkout at PATH")
    parser.add_argument("--blocks", type=int, default=4, help="alternating rounds of --interleave")
    parser.add_argument(
        "--dreamerv3",
        metavar="PATH",
        help="with --interleave, also time NM512/dreamerv3-torch's update at matched sizes from its checkout at PATH",
    )
    parser.add_argument(
        "--r2dreamer",
        metavar="PATH",
        help="with --interleave, also time NM512/r2dreamer's update (its DreamerV3 with a decoder, and R2-Dreamer) at "
        "matched widths from its checkout at PATH (its peer interpreter needs hydra-core and tensordict)",
    )
    parser.add_argument(
        "--authors",
        metavar="PATH",
        help="with --interleave, also time the CoWorld authors' release's DreamerV2 update from its checkout at PATH, "
        "at its own DMC config and our batch (give this tree its sizes with --set)",
    )
    parser.add_argument(
        "--peer-python", default=sys.executable, help="interpreter for the peers (needs torch, ruamel.yaml)"
    )
    parser.add_argument(
        "--flops",
        action="store_true",
        help="with --interleave, each side also counts the floating-point operations of one update "
        "(torch.utils.flop_counter: matrix products and convolutions, forward and backward)",
    )
    parser.add_argument(
        "--ops",
        action="store_true",
        help="with --interleave, our sides also count the ATen operations of one update (views among them)",
    )
    parser.add_argument("--profile", action="store_true", help="torch.profiler table of whole DreamerV2 updates")
    parser.add_argument(
        "--roofline",
        action="store_true",
        help="--profile, then the counted work of an update by class beside its profiled time, and the time that work "
        "would take at this machine's float32 matrix-product rate",
    )
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--allocator", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        return worker(args)
    if args.interleave:
        return interleave(args)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.profile or args.roofline:
        return profile(args)
    if args.algo in ("others", "all"):
        print(f"preset={args.preset} device={args.device} threads={args.threads}")
        print(f"{'update':<24}{'s':>10}{'updates/s':>11}")
        for label, seconds in measure_others(args.preset, args.device, args.warmup, args.updates, args.action_size):
            print(f"{label:<24}{seconds:>10.4f}{1.0 / seconds:>11.2f}")
        if args.algo == "others":
            return

    sets = dict(item.split("=", 1) for item in args.set)
    runs = [("default", sets)]
    if args.compare:
        runs = [
            (f"{precision}-{mode}", {**sets, "precision": precision, "compile": mode == "compile"})
            for mode in ("eager", "compile")
            for precision in ("fp32", "bf16")
        ]
    results = [
        measure(args.preset, args.device, overrides, label, args.warmup, args.updates, args.action_size)
        for label, overrides in runs
    ]
    config = args_config(args)
    print(
        f"preset={args.preset} device={args.device} threads={args.threads} "
        f"batch={config.train.batch_size}x{config.train.seq_len} horizon={config.actor_critic.horizon}"
    )
    print(f"{'run':<14}{'wm s':>10}{'imagine s':>12}{'ac s':>10}{'train s':>10}{'updates/s':>11}")
    for r in results:
        print(
            f"{r.label:<14}{r.wm_s:>10.4f}{r.imagine_s:>12.4f}{r.actor_critic_s:>10.4f}"
            f"{r.train_s:>10.4f}{r.updates_per_s:>11.2f}"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {
                    "preset": args.preset,
                    "device": args.device,
                    "threads": args.threads,
                    "runs": [asdict(r) for r in results],
                },
                f,
                indent=2,
            )


if __name__ == "__main__":
    main()
