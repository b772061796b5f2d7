"""Benchmark the live loop: simulated PointCloud2 -> ``indoorbev ros2 detect`` -> detections.

This process publishes simulator frames (``--preset``, default small: about 17k points,
280 kB a cloud) stamped with the publish time, and receives the detect node's detections,
which carry the cloud's stamp, so ``receive time - stamp`` is the end-to-end latency. The
detect node runs as its own process (Fast DDS over loopback) on an untrained model of the
preset (the weights do not change the work of the jitted model; inference runs with
thresholds at 0 so the panoptic step keeps every query as it would on a busy scene).

Three phases, each with a fresh node:
* latency: ``--latency-frames`` clouds at ``--latency-rate`` Hz (slow enough that no frame
  waits for the previous one);
* sensor rate: ``--seconds`` of clouds at ``--rate`` Hz;
* saturated: ``--seconds`` of clouds at ``--max-rate`` Hz, faster than the node can go, so
  the frames/s it answers is its throughput and the rest are dropped as stale.
Each splits the mean end-to-end latency with the node's own summary: transport in (stamp
-> node callback), the node's other work (mailbox wait, decoding, message building,
publishing), inference (jitted model + panoptic inference) and transport out (node
publish -> received here).

    JAX_PLATFORMS=cpu .venv/bin/python experiments/bench_ros2.py --preset small
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import jax
import numpy as np

from indoorbev_jax.cli import HelpFormatter, positive_float, seed_int
from indoorbev_jax.config import Config, InferenceConfig
from indoorbev_jax.predict import export_model
from indoorbev_jax.ros2 import runtime
from indoorbev_jax.ros2.messages import stamp_ns
from indoorbev_jax.rosbag import POINTCLOUD2, cloud_msg, typestore
from indoorbev_jax.train import init_state

REPO = Path(__file__).resolve().parents[1]
MAX_PHASE_CLOUDS = 1_000_000  # a day at 10 Hz is 864,000
IN_TOPIC, OUT_TOPIC = "/bench/points", "/indoorbev/detections"


def _start_detect(model: Path) -> tuple[subprocess.Popen, list[str]]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "indoorbev_jax.cli", "ros2", "detect", "--checkpoint",
         str(model), "--topic", IN_TOPIC, "--reliable", "--log-every", "1000"],
        stdout=subprocess.PIPE, text=True, cwd=REPO,
    )  # fmt: skip
    lines: list[str] = []
    ready = threading.Event()

    def read():
        for line in proc.stdout:
            lines.append(line)
            if "ready" in line:
                ready.set()

    threading.Thread(target=read, daemon=True).start()
    if not ready.wait(600):
        proc.kill()
        raise RuntimeError(f"detect node not ready after 600 s: {lines}")
    return proc, lines


def _stop_detect(proc: subprocess.Popen, lines: list[str]) -> dict:
    proc.terminate()
    proc.wait(timeout=60)
    for _ in range(50):
        summary = [ln for ln in lines if "summary" in ln]
        if summary:
            return json.loads(summary[-1].split("summary ", 1)[1])
        time.sleep(0.1)
    raise RuntimeError(f"no summary from the detect node: {lines}")


def _run_phase(node, pub, received: dict, clouds: list, rate: float, count: int) -> list[int]:
    """Publishes ``count`` clouds at ``rate`` Hz; returns their stamps."""
    ts = typestore()
    raws = [bytes(ts.serialize_cdr(cloud_msg(ts, c, 0, "lidar"), POINTCLOUD2)) for c in clouds]
    # The node's "ready" precedes DDS discovery: clouds published before it sees our topic
    # are lost, and the first measured ones would pay the set-up the warm-ups are for.
    deadline = time.monotonic() + 60
    while pub.get_subscription_count() == 0 or node.count_publishers(OUT_TOPIC) == 0:
        if time.monotonic() > deadline:
            raise RuntimeError(f"the detect node did not connect to {IN_TOPIC} / {OUT_TOPIC}")
        time.sleep(0.05)
    for raw in raws[:3]:  # first messages pay for buffer set-up; stamp 0 keeps them out of
        pub.publish(raw)  # the node's statistics
        time.sleep(1.0)
    received.clear()
    stamps = []
    start = time.monotonic()
    for k in range(count):
        while (wait := start + k / rate - time.monotonic()) > 0:
            time.sleep(wait)
        stamp = time.time_ns()
        # Stamp the prebuilt bytes (header.stamp: int32 sec, uint32 nanosec after the 4-byte
        # CDR header), so that serializing the cloud stays out of the measured time.
        raw = raws[k % len(raws)]
        pub.publish(raw[:4] + struct.pack("<iI", *divmod(stamp, 10**9)) + raw[12:])
        stamps.append(stamp)
    time.sleep(3.0)  # the last outputs
    return stamps


def _pct(values):
    v = np.asarray(values)
    return (f"mean {v.mean():6.1f} ms  median {statistics.median(v):6.1f} ms  "
            f"p90 {np.percentile(v, 90):6.1f} ms")  # fmt: skip


def _phase(name, model, node, pub, received, clouds, rate, count) -> None:
    proc, lines = _start_detect(model)
    stamps = _run_phase(node, pub, received, clouds, rate, count)
    stats = _stop_detect(proc, lines)
    got = [s for s in stamps if s in received]
    if len(got) < 2:  # no rate, no latency split to give
        print(f"\n{name}: {count} clouds published at {rate:g} Hz; detections for {len(got)}, "
              f"too few to measure (2 needed); node summary: {json.dumps(stats)}")  # fmt: skip
        return
    e2e = [(received[s] - s) / 1e6 for s in got]
    span = (received[got[-1]] - received[got[0]]) / 1e9
    fps = (len(got) - 1) / span
    print(f"\n{name}: {count} clouds published at {rate:g} Hz; detections for {len(got)} "
          f"({fps:.2f} frames/s), {count - len(got)} dropped as stale")  # fmt: skip
    print(f"  end to end (publish -> detections received): {_pct(e2e)}")
    # Means add up (medians do not): split the mean end-to-end latency.
    mean = float(np.mean(e2e))
    t_in, infer = stats["transport_ms"]["mean"], stats["inference_ms"]["mean"]
    node_total = stats["latency_ms"]["mean"]
    parts = {
        "transport in (publish -> node callback)": t_in,
        "wait + decode + build + publish in the node": node_total - t_in - infer,
        "inference (jitted model + panoptic)": infer,
        "transport out (node publish -> received)": mean - node_total,
    }
    for part, ms in parts.items():
        print(f"    {part:<45} {ms:6.1f} ms  {100 * ms / mean:5.1f} %")
    print(f"  node summary: {json.dumps(stats)}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter
    )
    parser.add_argument(
        "--preset",
        default="small",
        choices=("tiny", "small", "paper"),
        help="config preset of the clouds and of the untrained model",
    )
    parser.add_argument(
        "--latency-rate",
        type=positive_float,
        default=1.0,
        help="publish rate (Hz) of the latency phase, slow enough not to queue",
    )
    parser.add_argument(
        "--latency-frames", type=int, default=20, help="clouds published in the latency phase"
    )
    parser.add_argument(
        "--rate",
        type=positive_float,
        default=10.0,
        help="publish rate (Hz) of the sensor-rate phase",
    )
    parser.add_argument(
        "--max-rate",
        type=positive_float,
        default=50.0,
        help="publish rate (Hz) of the saturated phase, above what the node can answer",
    )
    parser.add_argument(
        "--seconds",
        type=positive_float,
        default=20.0,
        help="seconds of publishing per throughput phase (sensor rate, saturated)",
    )
    parser.add_argument("--seed", type=seed_int, default=0, help="seed of the simulated scenes")
    args = parser.parse_args(argv)
    counts = {
        "--latency-frames": args.latency_frames,
        "--seconds x --rate": args.seconds * args.rate,
        "--seconds x --max-rate": args.seconds * args.max_rate,
    }
    for flag, count in counts.items():
        # An inf product ended in round()'s OverflowError.
        if not (math.isfinite(count) and 2 <= round(count) <= MAX_PHASE_CLOUDS):
            parser.error(f"{flag} gives {count:g} clouds; a phase needs 2 to {MAX_PHASE_CLOUDS:,}")

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    config = Config.preset(args.preset)
    config = dataclasses.replace(
        config, inference=InferenceConfig(score_threshold=0.0, overlap_threshold=0.0)
    )
    from indoorbev_sim.ros2 import scene_frames

    frames = scene_frames(config, args.seed)
    clouds = [next(frames)[0] for _ in range(2 * config.sim.frames_per_sequence)]
    npts = [len(c) for c in clouds]
    print(f"preset {args.preset}: {len(clouds)} simulated clouds of {min(npts)}-{max(npts)} "
          f"points ({16 * int(np.mean(npts)) / 1e3:.0f} kB), grid {config.grid.shape}, "
          f"{config.head.num_queries} queries")  # fmt: skip
    tmp = Path(tempfile.mkdtemp(prefix="bench_ros2_"))
    model = export_model(init_state(config, jax.random.key(0)).params, config, tmp / "m.msgpack")

    runtime.require_rclpy()
    import rclpy.executors

    context, node = runtime.start_node("indoorbev_bench")
    pub = node.create_publisher(runtime.msg_class(POINTCLOUD2), IN_TOPIC, runtime.qos(True, 5))
    received: dict[int, int] = {}
    ts = typestore()

    def on_detections(raw: bytes) -> None:
        now = time.time_ns()
        received[stamp_ns(ts.deserialize_cdr(raw, POINTCLOUD2))] = now

    node.create_subscription(
        runtime.msg_class(POINTCLOUD2), OUT_TOPIC, on_detections, runtime.qos(True, 50), raw=True
    )
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    try:
        phase = functools.partial(_phase, model=model, node=node, pub=pub, received=received,
                                  clouds=clouds)  # fmt: skip
        phase("latency", rate=args.latency_rate, count=args.latency_frames)
        phase("sensor rate", rate=args.rate, count=round(args.seconds * args.rate))
        phase("saturated", rate=args.max_rate, count=round(args.seconds * args.max_rate))
    finally:
        executor.shutdown()
        runtime.stop_node(node, context)
        shutil.rmtree(tmp, ignore_errors=True)  # the exported model


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "bench_ros2.py")  # Ctrl-C: one line and status 130
