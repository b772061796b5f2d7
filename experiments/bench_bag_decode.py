"""Benchmark reading lidar bags: Livox CustomMsg decoded from its CDR bytes with numpy
(``rosbag.livox_custom_from_cdr``, what ``indoorbev predict`` uses) against ``rosbags``'
deserializer + one Python object per point (``livox_custom_to_points``, the reference).

One simulated MID-360-sized scan per size is serialized once; the two decoders run on it
interleaved, round by round, and the medians are printed with their ratio. Every round
checks that both give the same array.

Usage::

    .venv/bin/python experiments/bench_bag_decode.py
    .venv/bin/python experiments/bench_bag_decode.py --points 20000 40000 --reps 10
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from indoorbev_jax.cli import HelpFormatter
from indoorbev_jax.rosbag import (
    LIVOX_CUSTOM,
    header,
    livox_custom_from_cdr,
    livox_custom_to_points,
    typestore,
)


def livox_scan(ts, n: int, seed: int) -> bytes:
    """CDR bytes of one CustomMsg with ``n`` random points (reflectivity 0-255)."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-20.0, 20.0, (n, 3)).astype(np.float32)
    refl = rng.integers(0, 256, n)
    point = ts.types["livox_ros_driver2/msg/CustomPoint"]
    points = [
        point(offset_time=i, x=float(x), y=float(y), z=float(z), reflectivity=int(r), tag=0,
              line=i % 4)
        for i, ((x, y, z), r) in enumerate(zip(xyz, refl, strict=True))
    ]  # fmt: skip
    msg = ts.types[LIVOX_CUSTOM](
        header=header(ts, 10**9, "livox_frame"), timebase=10**9, point_num=n, lidar_id=192,
        rsvd=np.zeros(3, np.uint8), points=points,
    )  # fmt: skip
    return bytes(ts.serialize_cdr(msg, LIVOX_CUSTOM))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("--points", type=int, nargs="+", default=[20_000],
                   help="points per scan, one row each (a MID-360 gives about 20,000 at 10 Hz; "
                   "default: 20000)")  # fmt: skip
    p.add_argument("--reps", type=int, default=5, help="timed calls per decoder and round")
    p.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="rounds of the two decoders, interleaved; checked equal each round",
    )
    args = p.parse_args(argv)
    if any(n < 0 for n in args.points) or args.reps < 1 or args.rounds < 1:
        p.error("--points must be >= 0, --reps and --rounds >= 1")
    ts = typestore()

    def reference(raw):
        return livox_custom_to_points(ts.deserialize_cdr(raw, LIVOX_CUSTOM))

    def ours(raw):
        return livox_custom_from_cdr(raw)[2]

    print(f"{'points':>8} {'rosbags ms':>11} {'numpy ms':>9} {'ratio':>7}")
    for n in args.points:
        raw = livox_scan(ts, n, seed=n)
        times = {"reference": [], "ours": []}
        for _ in range(args.rounds):
            for name, fn in (("reference", reference), ("ours", ours)):
                for _ in range(args.reps):
                    start = time.perf_counter()
                    fn(raw)
                    times[name].append(time.perf_counter() - start)
            np.testing.assert_array_equal(ours(raw), reference(raw))
        ref, fast = (1e3 * statistics.median(times[k]) for k in ("reference", "ours"))
        print(f"{n:>8} {ref:>11.2f} {fast:>9.3f} {ref / fast:>6.0f}x", flush=True)


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "bench_bag_decode.py")  # Ctrl-C: one line and status 130
