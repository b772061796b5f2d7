"""Benchmark test-time views: what each added view costs per frame, and where the time goes.

For 1, 2, 4 and 8 views (``config.VIEWS`` in order), one jitted function per count runs
``inference.apply_views`` + panoptic inference on one simulated held-out frame at batch 1,
as ``Predictor`` does; the counts are interleaved round by round and the medians printed
with their ratio to one view. Then the largest count split into its parts, each jitted
alone: the forward of the V clouds (the last layer's outputs, as the views function uses
them), the fusion (``fuse_views``) and panoptic inference on the V * Q fused queries
against the plain Q.

Usage::

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_views.py
    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_views.py --model runs/small --reps 20
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import jax
import jax.numpy as jnp

from indoorbev_jax.cli import HelpFormatter, positive_int, seed_int
from indoorbev_jax.config import VIEWS, InferenceConfig
from indoorbev_jax.inference import (
    apply_views,
    fuse_views,
    panoptic_inference,
    unview_batch,
    view_batch,
)
from indoorbev_jax.models import IndoorBEV
from indoorbev_jax.predict import load_model

SHIPPED = "models/indoorbev_small.msgpack"


def _median_ms(fn, *args, reps: int) -> float:
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("--model", default=SHIPPED, help="model file or run directory")
    p.add_argument("--reps", type=positive_int, default=10, help="timed calls per count and round")
    p.add_argument(
        "--rounds",
        type=positive_int,
        default=3,
        help="rounds, each timing every view count in turn (their median)",
    )
    p.add_argument("--seed", type=seed_int, default=0, help="seed of the simulated held-out frame")
    args = p.parse_args(argv)
    try:
        config, params = load_model(args.model)
    except (OSError, ValueError) as e:
        p.exit(2, f"bench_views: {e}\n")
    from indoorbev_sim.generate import jitted_generate

    base = dataclasses.replace(config, inference=InferenceConfig())
    data, _ = jitted_generate(base, "test", 1)(jax.random.key(args.seed))
    points, valid = data.points, data.point_valid
    params = jax.tree.map(jnp.asarray, params)
    model = IndoorBEV(config)
    names = list(VIEWS)
    counts = [c for c in (1, 2, 4, 8) if c <= len(names)]
    settings = {c: dataclasses.replace(config.inference, views=tuple(names[:c])) for c in counts}

    def end_to_end(inference):
        return jax.jit(
            lambda params, points, valid: panoptic_inference(
                apply_views(model, params, points, valid, inference), inference
            )
        )

    fns = {c: end_to_end(settings[c]) for c in counts}
    print(f"model {args.model} (preset {config.name}), grid {config.grid.shape}, "
          f"{config.head.num_queries} queries, {int(valid.sum())} points, "
          f"{jax.devices()[0].device_kind}")  # fmt: skip
    times = {c: [] for c in counts}
    for _ in range(args.rounds):
        for c in counts:
            times[c].append(_median_ms(fns[c], params, points, valid, reps=args.reps))
    one = statistics.median(times[1])
    print("views  median ms/frame (per round)            x one view")
    for c in counts:
        rounds = " ".join(f"{t:7.1f}" for t in times[c])
        print(f"{c:5d}  {statistics.median(times[c]):8.1f}  ({rounds})  "
              f"{statistics.median(times[c]) / one:6.2f}")  # fmt: skip

    big = counts[-1]
    inference = settings[big]
    clouds, valids = view_batch(points, valid, inference.views)
    forward = jax.jit(model.apply)  # every layer: the fusion's input below
    stacked = unview_batch(forward(params, clouds, valids), inference.views)
    # Timed as the views function runs it: only the last layer's outputs are used there, so
    # XLA drops the other layers' heads (their L x Q x H x W masks).
    last_layer = jax.jit(lambda p, x, v: jax.tree.map(lambda a: a[-1], model.apply(p, x, v)))
    fuse = jax.jit(fuse_views, static_argnums=(1, 2))
    fused = fuse(stacked, inference.mask_threshold, inference.view_iou)
    panoptic = jax.jit(panoptic_inference, static_argnums=1)
    plain = jax.tree.map(lambda x: x[0], stacked)  # the identity view's outputs
    parts = {
        "forward, 1 cloud": (last_layer, params, points, valid),
        f"forward, {big} clouds": (last_layer, params, clouds, valids),
        f"fusion of {big} x {config.head.num_queries} queries": (
            fuse, stacked, inference.mask_threshold, inference.view_iou,
        ),
        f"panoptic inference, {big * config.head.num_queries} fused queries": (
            panoptic, fused, inference,
        ),
        f"panoptic inference, {config.head.num_queries} queries": (panoptic, plain, inference),
    }  # fmt: skip
    print(f"\nparts of {big} views (median ms over {args.reps} calls)")
    for name, (fn, *fn_args) in parts.items():
        print(f"  {name:<40} {_median_ms(fn, *fn_args, reps=args.reps):8.1f}")


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "bench_views.py")  # Ctrl-C: one line and status 130
