"""Benchmark: labelled frames/s, batched on-device generation vs the sequential pipeline.

Ours: ``indoorbev_sim.generate_batch_with_info`` jitted, B scenes per call (scene sampling,
Warp ray casting, noise, labels, masks, padded targets in one XLA program).
Reference: the plain sequential pipeline, frame by frame: the same scene sampler (jitted,
one scene), MuJoCo ``mj_multiRay`` for the scan and the visibility rays, numpy footprints,
counts and filtering (``generate.reference_frame``).

Runs are interleaved (ours, reference, ours, ...) and the median per-frame time is reported.
A third row times the same generator traced with every Warp launch kept on one CPU thread
(``_lidar_kernels.MIN_ITEMS_PER_THREAD`` raised while it is traced: the choice between one
launch and launches shared over threads is made when the program is traced).

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_datagen.py --preset small --batch 8
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import numpy as np
from indoorbev_sim import _lidar_kernels, generate

from indoorbev_jax.config import Config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="small")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--ref-frames", type=int, default=4, help="reference frames per repeat")
    args = parser.parse_args()
    cfg = Config.preset(args.preset)
    b = args.batch
    ours = generate.jitted_generate(cfg, "train", b)
    # A second program (jitted_generate is cached), traced on one thread below.
    ours_1t = jax.jit(lambda key: generate.generate_batch_with_info(key, cfg, "train", b))
    one = generate.jitted_draw(cfg, "train", 1)
    pattern = generate.make_pattern(cfg.sim)
    rng = np.random.default_rng(0)

    split_at = _lidar_kernels.MIN_ITEMS_PER_THREAD
    t0 = time.perf_counter()
    jax.block_until_ready(ours(jax.random.key(0)))
    compile_ours = time.perf_counter() - t0
    _lidar_kernels.MIN_ITEMS_PER_THREAD = 1 << 62
    jax.block_until_ready(ours_1t(jax.random.key(0)))
    _lidar_kernels.MIN_ITEMS_PER_THREAD = split_at
    t0 = time.perf_counter()
    scene, t, k, _ = one(jax.random.key(0))
    generate.reference_frame(cfg, generate.scene_numpy(scene, 0), float(t[0]),
                             np.asarray(pattern.frame(k).directions, np.float64), rng)  # fmt: skip
    compile_ref = time.perf_counter() - t0

    ours_s, ours1_s, ref_s = [], [], []
    for r in range(args.repeats):
        # The two "ours" rows swap places each repeat: the first after the single-threaded
        # reference finds the second core asleep.
        for one_thread in (False, True) if r % 2 == 0 else (True, False):
            t0 = time.perf_counter()
            jax.block_until_ready((ours_1t if one_thread else ours)(jax.random.key(100 + r)))
            (ours1_s if one_thread else ours_s).append((time.perf_counter() - t0) / b)
        t0 = time.perf_counter()
        for f in range(args.ref_frames):
            scene, t, k, _ = one(jax.random.key(1000 * r + f))
            dirs = np.asarray(pattern.frame(k).directions, np.float64)
            generate.reference_frame(cfg, generate.scene_numpy(scene, 0), float(t[0]), dirs, rng)
        ref_s.append((time.perf_counter() - t0) / args.ref_frames)

    o, s = statistics.median(ours_s), statistics.median(ref_s)
    o1 = statistics.median(ours1_s)
    geoms = generate.scenes_mod.template_for(cfg).num_geoms
    print(
        f"device: {jax.devices()[0].platform}, preset {cfg.name}: grid {cfg.grid.shape}, "
        f"{cfg.sim.num_rays} rays/frame ({cfg.sim.pattern}), {geoms} geoms"
    )
    print(f"compile/warm-up: ours {compile_ours:.1f} s, reference {compile_ref:.1f} s")
    print(f"ours (batched, B={b}):        {1 / o:8.2f} frames/s  (median {o * 1e3:.1f} ms/frame)")
    print(f"ours, launches on 1 thread: {1 / o1:8.2f} frames/s  (median {o1 * 1e3:.1f} ms/frame)")
    print(f"reference (sequential):     {1 / s:8.2f} frames/s  (median {s * 1e3:.1f} ms/frame)")
    print(
        f"speed-up: {s / o:.2f}x  (runs: ours {[f'{x * 1e3:.0f}' for x in ours_s]} ms, "
        f"reference {[f'{x * 1e3:.0f}' for x in ref_s]} ms per frame)"
    )


if __name__ == "__main__":
    main()
