"""Train-step throughput per preset, and K vmapped models against K sequential runs.

    python experiments/bench_train.py --presets tiny small --steps 10 --sweep-k 4

One simulated batch per preset (``indoorbev_sim.generate_batch``) is reused for every step,
so the figures are the jitted step alone (augment -> forward -> match -> loss -> update).
The sweep rows run the K-way vmapped step and K single-model steps interleaved, median of
``--steps`` rounds each, and print the ratio.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import jax
import numpy as np

from indoorbev_jax.cli import HelpFormatter, nonnegative_int, positive_int
from indoorbev_jax.config import Config
from indoorbev_jax.sweep import init_sweep, make_sweep_step, stack_hypers
from indoorbev_jax.train import Hyper, init_state, jit_train_step, make_train_step


def _time(fn) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - start


def bench_preset(name: str, steps: int, batch_size: int | None, sweep_k: int) -> None:
    from indoorbev_sim.generate import jitted_generate

    config = Config.preset(name)
    if batch_size:
        config = dataclasses.replace(
            config, train=dataclasses.replace(config.train, batch_size=batch_size)
        )
    b = config.train.batch_size
    batch, _ = jitted_generate(config, "train", b)(jax.random.key(0))
    key = jax.random.key(1)
    hyper = Hyper.from_config(config)
    state = init_state(config, jax.random.key(0))
    step = jit_train_step(config, make_train_step(config))
    compile_s = _time(lambda: step.lower(state, batch, key, hyper).compile())
    state, first = jax.block_until_ready(step(state, batch, key, hyper))  # warm-up, waited for
    times = []
    for _ in range(steps):
        t = _time(lambda: step(state, batch, key, hyper))
        times.append(t)
    med = statistics.median(times)
    print(
        f"{name:6s} batch {b}: compile {compile_s:.1f} s, step median {1e3 * med:.0f} ms "
        f"over {steps} -> {1 / med:.2f} steps/s, {b / med:.1f} samples/s",
        flush=True,
    )
    if sweep_k <= 1:
        return
    hypers = stack_hypers(config, [config.train.learning_rate] * sweep_k, {})
    states = init_sweep(config, sweep_k, jax.random.key(0))
    sweep = make_sweep_step(config)
    sweep_compile = _time(lambda: sweep.lower(states, batch, key, hypers).compile())
    states, members = jax.block_until_ready(sweep(states, batch, key, hypers))
    # K copies of the first step: each member's metrics are the single step's (same state,
    # batch, key and Hyper), up to the reduction order of the batched kernels.
    pairs = zip(jax.tree_util.tree_leaves_with_path(first), jax.tree.leaves(members), strict=True)
    for (path, one), many in pairs:
        if not np.allclose(np.asarray(many), np.asarray(one), rtol=1e-3, atol=1e-5):
            raise SystemExit(
                f"{name}: the vmapped step's {jax.tree_util.keystr(path)} {many} differs "
                f"from the single step's {np.asarray(one)}: not timed"
            )
    vmapped, sequential = [], []
    for _ in range(steps):
        vmapped.append(_time(lambda: sweep(states, batch, key, hypers)))
        sequential.append(_time(lambda: [step(state, batch, key, hyper) for _ in range(sweep_k)]))
    print(sweep_row(name, sweep_k, sweep_compile, vmapped, sequential), flush=True)


def sweep_row(name: str, k: int, compile_s: float, vmapped, sequential) -> str:
    """The sweep row: the medians of the rounds' seconds and the speed-up of one vmapped
    round over K sequential steps (> 1: vmap is faster)."""
    v, s = statistics.median(vmapped), statistics.median(sequential)
    return (
        f"{name:6s} sweep K={k}: compile {compile_s:.1f} s, vmapped {1e3 * v:.0f} ms "
        f"vs {k} sequential {1e3 * s:.0f} ms per round -> {s / v:.2f}x"
    )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument(
        "--presets",
        nargs="+",
        default=["tiny", "small"],
        choices=("paper", "small", "tiny"),
        help="config presets to time, in turn (default: tiny small)",
    )
    p.add_argument(
        "--steps",
        type=positive_int,
        default=10,
        help="timed steps per preset (the median), and rounds of the sweep rows",
    )
    p.add_argument(
        "--batch-size",
        type=positive_int,
        default=None,
        help="frames per step (default: each preset's train.batch_size)",
    )
    p.add_argument("--sweep-k", type=nonnegative_int, default=4,
                   help="K vmapped models against K sequential (0 or 1: none)")  # fmt: skip
    args = p.parse_args(argv)
    print(f"devices: {jax.devices()}")
    for name in args.presets:
        bench_preset(name, args.steps, args.batch_size, args.sweep_k)


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "bench_train.py")  # Ctrl-C: one line and status 130
