"""Benchmark matching and the set loss.

1. Matching latency: ``jit(matching.match)`` (optax's pure-JAX Hungarian solver, vmapped
   over the batch, on the padded [B, Q, M] costs) against a host loop of
   ``scipy.optimize.linear_sum_assignment`` on each frame's valid columns (what a PyTorch
   DETR matcher does), and against a naive wrapper (optax on [Q, M] with padded columns
   set to 0, no dummy columns). All run in the same process, interleaved; medians of
   ``--match-reps`` runs and the ratios are printed.
2. Memory of the cost matrix and of the loss + gradient w.r.t. the predictions at the
   paper's grid (500 x 500, L = 4 layers, Q = M = 30) with every mask cell vs.
   ``num_mask_points`` sampled cells: XLA's buffer assignment of the compiled function
   (arguments, outputs, temporaries; exact and load-independent), plus the median run time.

Usage::

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_matching.py
    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_matching.py --grid 500 --batch 2 \
        --points 12544 --reps 3
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from scipy.optimize import linear_sum_assignment

from indoorbev_jax.cli import HelpFormatter
from indoorbev_jax.config import NUM_CLASSES, LossConfig
from indoorbev_jax.losses import cost_matrix, set_loss
from indoorbev_jax.matching import match
from indoorbev_jax.types import Predictions, Targets

MiB = 2**20


def _naive_match(cost: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array]:
    """optax on the [Q, M] cost with padded columns set to 0 (no dummy columns)."""
    return optax.assignment.hungarian_algorithm(jnp.where(valid, cost, 0.0))


def _scipy_totals(cost: np.ndarray, valid: np.ndarray) -> list[tuple[int, float]]:
    """Per frame, (pairs, total cost) of scipy's ``linear_sum_assignment`` on the valid
    targets: what ``_check_totals`` holds each matcher to."""
    out = []
    for c, v in zip(cost, valid, strict=True):
        rows, cols = linear_sum_assignment(c[:, v])
        out.append((len(rows), c[:, v][rows, cols].sum(dtype=np.float64)))
    return out


def _check_totals(name: str, rows, cols, cost: np.ndarray, valid: np.ndarray, scipy=None):
    """Largest |total - scipy's total| over the frames, for the (query, target) pairs
    ``rows[b], cols[b]`` (pairs on padded targets, and targets left without a query (-1)
    where they outnumber the queries, left out); a wrong matcher ends the run before it is
    timed: a fast wrong answer is no result. ``scipy``: ``_scipy_totals`` of the frames,
    computed here if not given."""
    scipy = _scipy_totals(cost, valid) if scipy is None else scipy
    worst = 0.0
    for b, (pairs, ref) in enumerate(scipy):
        keep = valid[b][cols[b]] & (rows[b] >= 0)
        total = cost[b][rows[b][keep], cols[b][keep]].sum(dtype=np.float64)
        worst = max(worst, abs(total - ref))
        if keep.sum() != pairs or not abs(total - ref) <= 1e-4:
            raise SystemExit(
                f"{name}: frame {b} matched {keep.sum()} targets at total {total:.6f}, scipy's "
                f"linear_sum_assignment {pairs} at {ref:.6f}: not timed"
            )
    return worst


def bench_matching(batch: int, q: int, m: int, reps: int, all_valid: bool = False) -> None:
    rng = np.random.default_rng(0)
    cost = rng.random((batch, q, m)).astype(np.float32)
    valid = np.ones((batch, m), bool)
    if not all_valid:
        for b in range(batch):  # 5-15 objects per frame, padded to m
            valid[b, rng.integers(5, 16) :] = False
    ours_fn = jax.jit(match)
    naive_fn = jax.jit(jax.vmap(_naive_match))
    fns = {
        "jit(match)": lambda: jax.block_until_ready(ours_fn(cost, valid)),
        "naive optax": lambda: jax.block_until_ready(naive_fn(cost, valid)),
        "scipy loop": lambda: [
            linear_sum_assignment(c[:, v]) for c, v in zip(cost, valid, strict=True)
        ],
    }
    ours_rows = np.asarray(ours_fn(cost, valid)[0])  # also compiles both
    naive_rows, naive_cols = map(np.asarray, naive_fn(cost, valid))
    targets = np.broadcast_to(np.arange(m), (batch, m))
    scipy = _scipy_totals(cost, valid)
    worst = max(
        _check_totals("jit(match)", ours_rows, targets, cost, valid, scipy),
        _check_totals("naive optax", naive_rows, naive_cols, cost, valid, scipy),
    )
    times = {name: [] for name in fns}
    for _ in range(reps):  # interleaved so load changes hit all
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    what = "all valid" if all_valid else "5-15 valid"
    print(
        f"matching B={batch} Q={q} M={m} ({what}), median of {reps} (totals equal scipy's "
        f"on all {batch} frames, largest difference {worst:.2g}):"
    )
    for k, v in med.items():
        print(f"  {k:12s} {v:8.3f} ms")
    print(
        f"  ratio jit(match) / scipy loop = {med['jit(match)'] / med['scipy loop']:.2f}, "
        f"naive optax / jit(match) = {med['naive optax'] / med['jit(match)']:.2f} "
        "(time / time: above 1, the first is slower)"
    )


def make_batch(layers: int, batch: int, q: int, m: int, grid: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    k = NUM_CLASSES + 1
    preds = Predictions(
        logits=rng.normal(size=(layers, batch, q, k)).astype(np.float32),
        dims=rng.random((layers, batch, q, 3)).astype(np.float32),
        pos=rng.normal(size=(layers, batch, q, 3)).astype(np.float32),
        yaw=rng.normal(size=(layers, batch, q, 1)).astype(np.float32),
        masks=rng.normal(size=(layers, batch, q, grid, grid)).astype(np.float32),
    )
    valid = np.zeros((batch, m), bool)
    valid[:, :10] = True
    masks = np.zeros((batch, m, grid, grid), bool)
    for b in range(batch):
        for j in range(10):  # axis-aligned footprints of 10-60 cells a side
            y, x = rng.integers(0, grid - 60, 2)
            hy, hx = rng.integers(10, 60, 2)
            masks[b, j, y : y + hy, x : x + hx] = True
    targets = Targets(
        classes=np.where(valid, rng.integers(0, NUM_CLASSES, (batch, m)), NUM_CLASSES).astype(
            np.int32
        ),
        dims=rng.random((batch, m, 3)).astype(np.float32),
        pos=rng.normal(size=(batch, m, 3)).astype(np.float32),
        yaw=rng.normal(size=(batch, m)).astype(np.float32),
        valid=valid,
        masks=masks,
        instance_ids=np.zeros((batch, grid, grid), np.int32),
    )
    return preds, targets


def _memory(compiled) -> dict[str, float]:
    stats = compiled.memory_analysis()
    out = {
        "args": stats.argument_size_in_bytes / MiB,
        "out": stats.output_size_in_bytes / MiB,
        "temp": stats.temp_size_in_bytes / MiB,
    }
    out["total"] = out["args"] + out["out"] + out["temp"] - stats.alias_size_in_bytes / MiB
    return out


def bench_memory(layers: int, batch: int, q: int, m: int, grid: int, points: int, reps: int):
    # On the device up front: the timings measure compute, not a host-to-device copy.
    preds, targets = jax.device_put(make_batch(layers, batch, q, m, grid))
    weights = LossConfig().weights()
    key = jax.random.key(0)
    rows = []
    for k in (0, points):
        cfg = dataclasses.replace(LossConfig(), num_mask_points=k)
        sample_key = key if k else None  # the dense path takes no key
        cost_fn = jax.jit(lambda p, t, _, cfg=cfg, k=sample_key: cost_matrix(p, t, cfg, k))
        loss_fn = jax.jit(
            jax.value_and_grad(
                lambda p, t, _, cfg=cfg, k=sample_key: set_loss(p, t, weights, cfg, key=k)[0]
            )
        )
        for name, fn in (("cost", cost_fn), ("loss+grad", loss_fn)):
            compiled = fn.lower(preds, targets, key).compile()
            rows.append(((name, k), _memory(compiled), compiled))
    # Run times, interleaved over the four compiled functions.
    times = {row[0]: [] for row in rows}
    for _, _, compiled in rows:  # untimed first calls: page faults, one-time allocations
        jax.block_until_ready(compiled(preds, targets, key))
    for _ in range(reps):
        for label, _, compiled in rows:
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(preds, targets, key))
            times[label].append(time.perf_counter() - t0)
    print(
        f"memory at {grid} x {grid}, L={layers} B={batch} Q={q} M={m} (10 valid), "
        f"XLA buffer assignment in MiB, run time median of {reps}:"
    )
    print(f"  {'function':10s} {'points':>8s} {'args':>8s} {'out':>8s} {'temp':>8s} {'total':>8s}")
    for (name, k), mem, _ in rows:
        pts = "all" if k == 0 else str(k)
        t = statistics.median(times[(name, k)])
        print(
            f"  {name:10s} {pts:>8s} {mem['args']:8.1f} {mem['out']:8.1f} {mem['temp']:8.1f} "
            f"{mem['total']:8.1f}   {t * 1e3:8.1f} ms"
        )
    for name in ("cost", "loss+grad"):
        dense = next(r[1]["temp"] for r in rows if r[0] == (name, 0))
        sampled = next(r[1]["temp"] for r in rows if r[0] == (name, points))
        print(f"  {name}: temporaries dense / sampled = {dense / max(sampled, 1e-9):.1f}x")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter
    )
    parser.add_argument("--batch", type=int, default=1, help="frames for the memory bench")
    parser.add_argument("--grid", type=int, default=500, help="H = W of the memory bench")
    parser.add_argument("--points", type=int, default=112 * 112, help="sampled mask cells")
    parser.add_argument("--reps", type=int, default=3, help="timed runs of the memory bench")
    parser.add_argument(
        "--match-reps",
        type=int,
        default=50,
        help="timed runs of each matcher, interleaved (their median)",
    )
    parser.add_argument(
        "--skip-memory", action="store_true", help="time the matching only, not the memory bench"
    )
    args = parser.parse_args(argv)
    if args.grid < 64:  # footprints reach 60 cells
        parser.error(f"--grid must be at least 64 cells, got {args.grid}")
    for flag in ("batch", "points", "reps", "match_reps"):
        if getattr(args, flag) < 1:
            parser.error(f"--{flag.replace('_', '-')} must be at least 1")
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}")
    bench_matching(16, 30, 30, args.match_reps)
    bench_matching(16, 30, 30, args.match_reps, all_valid=True)
    bench_matching(16, 30, 12, args.match_reps)
    if not args.skip_memory:
        bench_memory(4, args.batch, 30, 30, args.grid, args.points, args.reps)


if __name__ == "__main__":
    jnp.zeros(())  # initialise the backend before timing anything
    from indoorbev_jax.cli import exit_with

    exit_with(main, "bench_matching.py")  # Ctrl-C: one line and status 130
