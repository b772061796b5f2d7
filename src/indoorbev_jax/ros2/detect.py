"""The inference node: ``indoorbev ros2 detect --checkpoint MODEL [--topic /livox/lidar]``.

Subscribes to sensor_msgs/PointCloud2 (any field layout with x, y, z and optional
intensity) and publishes per cloud, with the cloud's stamp and frame id, the detections,
markers and occupancy grid of ``indoorbev_jax.ros2.messages`` under ``--out-ns``.

Stale frames are dropped rather than queued: the subscription keeps one message, its
callback only parks the newest cloud in a one-slot mailbox (replacing an unprocessed one,
counted as dropped), and a worker thread runs the model on whatever is newest. So
callbacks never queue and the published frame is always the freshest the node could see.

``Detector`` is the ROS-free core (serialized cloud in, serialized messages out), which
the tests drive directly; ``run_detect_node`` wraps it in rclpy.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import threading
import time
from collections import deque
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from indoorbev_jax.boxes import check_box_source
from indoorbev_jax.checks import check_positive, check_whole
from indoorbev_jax.data import kitti
from indoorbev_jax.mount import LEVEL, LidarMount, check_level_frame
from indoorbev_jax.predict import Predictor, load_model, with_thresholds
from indoorbev_jax.ros2 import messages as M
from indoorbev_jax.rosbag import (
    MARKER_ARRAY,
    POINTCLOUD2,
    BagError,
    cloud_msg,
    pointcloud2_to_points,
)
from indoorbev_jax.rosbag import typestore as default_typestore

OUTPUTS = {  # output name -> message type
    "detections": POINTCLOUD2,
    "markers": MARKER_ARRAY,
    "occupancy": M.OCCUPANCY_GRID,
}


@dataclasses.dataclass
class Result:
    """What the node publishes for one cloud.

    Attributes:
      stamp: the cloud's header stamp (ns), carried to every output.
      frame: the cloud's frame id, carried to every output.
      outputs: {output name: serialized message} for every name of ``OUTPUTS``; empty
        when not even the cloud's header is readable (nothing to publish).
      labels: the predicted objects (empty for unusable input).
      warning: why the cloud was (partly) unusable, or None.
      infer_ms: model + panoptic inference time; 0 when the model did not run.
    """

    stamp: int
    frame: str
    outputs: dict[str, bytes]
    labels: kitti.ObjectLabels
    warning: str | None
    infer_ms: float


def speed_hint(infer_ms: float, views: tuple[str, ...], sensor_hz: float = 10.0) -> str | None:
    """A hint when test-time views make inference slower than the sensor (None otherwise)."""
    if len(views) == 1 or infer_ms * sensor_hz <= 1e3:
        return None
    return (
        f"inference takes {infer_ms:.0f} ms per cloud with {len(views)} test-time views, "
        f"slower than a {sensor_hz:g} Hz sensor, so stale clouds will be dropped; "
        "--views identity runs one forward per cloud"
    )


class Detector:
    """Serialized PointCloud2 in, serialized detections / markers / occupancy out.

    Bad input never raises: a cloud without x, y or z, with truncated data, or without a
    single finite point inside the grid gives a warning and empty outputs (no object, no
    marker, an all-unknown grid). So does a cloud holding non-finite points, unless
    ``skip_nonfinite`` (organized clouds that mark missing returns with NaN): then those
    points are dropped with a warning and the rest is processed. ``intensity``: the units of
    the clouds' intensity (``predict.intensity_factor``). ``mount`` (``mount.LidarMount``)
    levels the clouds of a tilted lidar; the outputs then carry ``level_frame`` as their
    frame id (required with a rotation), else the cloud's.
    """

    def __init__(
        self, config, params, ts=None, skip_nonfinite: bool = False, intensity="auto",
        boxes: str = "mask", mount: LidarMount = LEVEL, level_frame: str | None = None,
    ):  # fmt: skip
        check_box_source(boxes)
        check_level_frame(mount, level_frame)
        self.mount = mount
        self.level_frame = level_frame or None
        self.config = config
        self.boxes = boxes
        self.skip_nonfinite = skip_nonfinite
        self.ts = ts if ts is not None else default_typestore()
        self.names = config.data.class_names
        params = jax.tree.map(jnp.asarray, params)
        self.predictor = Predictor(config, params, intensity, self.mount)

    def warmup(self) -> float:
        """Runs one dummy cloud through every step (the model compiles, ``rosbags`` builds
        its (de)serializers) so that the first real frame is not late; returns seconds."""
        start = time.perf_counter()
        self.process(self._dummy())
        return time.perf_counter() - start

    def inference_ms(self) -> float:
        """Model + panoptic inference time of one dummy cloud, after ``warmup``."""
        return self.process(self._dummy()).infer_ms

    def _dummy(self) -> bytes:
        # One valid point, so the model runs: three quarters along x, clear of the sensor's
        # blind zone (sim.min_range), where (0, 0, 0) would be skipped; placed there in the
        # level frame, so sent in the lidar's (the mount's inverse).
        g = self.config.grid
        level = np.array([g.x_range[0] + 0.75 * (g.x_range[1] - g.x_range[0]),
                          sum(g.y_range) / 2, sum(g.z_range) / 2])  # fmt: skip
        level[2] -= self.predictor.z_offset
        point = self.mount.unlevelled(np.array([[*level, 0.5]]))
        cloud = cloud_msg(self.ts, point, 0, "warmup")
        return bytes(self.ts.serialize_cdr(cloud, POINTCLOUD2))

    def process(self, raw: bytes) -> Result:
        try:
            msg = self.ts.deserialize_cdr(bytes(raw), POINTCLOUD2)
        except Exception as e:  # noqa: BLE001 - any decoding failure is bad input
            why = f"cannot decode the PointCloud2 ({type(e).__name__}: {e})"
            known = M.header_from_cdr(raw)
            if known is None:  # no stamp, no frame: outputs would be placed nowhere
                labels = kitti.ObjectLabels.empty(with_scores=True)
                return Result(0, "", {}, labels, f"{why}; not even its header is readable, "
                              "nothing published", 0.0)  # fmt: skip
            stamp, frame = known
            return self._empty(stamp, frame, f"cloud '{frame}' @ {stamp / 1e9:.3f}s: {why}")
        stamp, frame = M.stamp_ns(msg), msg.header.frame_id
        source = f"cloud '{frame}' @ {stamp / 1e9:.3f}s"
        try:
            points = pointcloud2_to_points(msg, source)
        except BagError as e:
            return self._empty(stamp, frame, str(e))
        except Exception as e:  # noqa: BLE001 - a layout the checks missed is still bad input
            # MemoryError included, on purpose: a cloud whose header claims billions of
            # points is one bad message, and the node goes on with the next.
            return self._empty(stamp, frame, f"{source}: cannot read ({type(e).__name__}: {e})")
        padded, valid, counts = self.predictor.prepare(points)
        notes = []
        if counts["nonfinite_points"]:
            notes.append(f"{counts['nonfinite_points']} of {len(points)} points are not finite")
        if counts["dropped_points"]:
            notes.append(
                f"{counts['dropped_points']} valid points beyond data.max_points="
                f"{self.config.data.max_points} left out, the rest spread over the cloud"
            )
        if counts["nonfinite_points"] and not self.skip_nonfinite:
            return self._empty(stamp, frame, f"{source}: {notes[0]}; cloud skipped "
                               "(--skip-nonfinite processes the finite points)")  # fmt: skip
        if not valid.any():
            why = (
                "empty" if len(points) == 0
                else "no valid point (finite, inside the grid, beyond sim.min_range)"
            )  # fmt: skip
            return self._empty(stamp, frame, f"{source}: {why}; {len(points)} points")
        start = time.perf_counter()
        final, output, _ = self.predictor.infer(padded, valid)
        infer_ms = 1e3 * (time.perf_counter() - start)
        labels, ids = self.predictor.labels(final, output, self.boxes)
        warning = f"{source}: {'; '.join(notes)} (those points are skipped)" if notes else None
        return Result(stamp, frame, self._serialize(labels, ids > 0, stamp, frame),
                      labels, warning, infer_ms)  # fmt: skip

    def _empty(self, stamp: int, frame: str, warning: str) -> Result:
        labels = kitti.ObjectLabels.empty(with_scores=True)
        outputs = self._serialize(labels, None, stamp, frame)
        return Result(stamp, frame, outputs, labels, warning, 0.0)

    def _serialize(self, labels, occupied, stamp: int, frame: str) -> dict[str, bytes]:
        ts, frame = self.ts, self.level_frame or frame
        msgs = {
            "detections": M.detections_msg(ts, labels, stamp, frame),
            "markers": M.footprint_markers_msg(ts, labels, self.names, stamp, frame),
            "occupancy": M.occupancy_msg(ts, occupied, self.config.grid, stamp, frame),
        }
        return {k: bytes(ts.serialize_cdr(m, OUTPUTS[k])) for k, m in msgs.items()}


def _percentiles(values) -> dict[str, float] | None:
    if not values:
        return None
    v = np.asarray(values)
    return {
        "mean": round(float(v.mean()), 2),
        "median": round(float(statistics.median(v)), 2),
        "p90": round(float(np.percentile(v, 90)), 2),
        "max": round(float(v.max()), 2),
    }


class _Stats:
    """Frame counts, and latencies (ms) of the last ``window`` frames; shared by the
    callback and the worker."""

    def __init__(self, window: int = 10_000):
        self.received = self.processed = self.dropped = self.bad = 0
        self.transport, self.infer, self.total = (deque(maxlen=window) for _ in range(3))

    def summary(self) -> dict:
        return {
            "received": self.received,
            "processed": self.processed,
            "dropped_stale": self.dropped,
            "bad_input": self.bad,
            # stamp -> callback: sensor driver + transport + deserialization by rclpy
            "transport_ms": _percentiles(self.transport),
            "inference_ms": _percentiles(self.infer),
            # stamp -> detections published (markers and grid follow)
            "latency_ms": _percentiles(self.total),
        }


SILENCE_S = 5.0  # seconds without a cloud before the node says why none may be arriving


def check_settings(topic: str, out_ns: str, log_every: float, max_frames: int) -> dict:
    """{output name: topic} of the node, after checking the settings that would otherwise
    fail only once the model has warmed up (or never, silently); a ``ValueError`` names
    the setting."""
    from indoorbev_jax.ros2 import check_topic_name

    check_topic_name(topic, "topic")
    out_topics = {k: f"{out_ns.rstrip('/')}/{k}" for k in OUTPUTS}
    for t in out_topics.values():
        check_topic_name(t, "out_ns")
    if topic in out_topics.values():  # the node fed on its own output, ~800 messages/s
        raise ValueError(
            f"topic: {topic!r} is one of the node's own outputs (out_ns {out_ns!r}); "
            "subscribe to the lidar's cloud topic"
        )
    check_positive("log_every", log_every)
    check_whole("max_frames", max_frames, 0, " (0: never)")
    return out_topics


def bag_log_ns(stamp: int, received: int) -> int:
    """The log time of a cloud and its outputs in a recording: the cloud's header stamp, or,
    for an unstamped or pre-1970 one, when it arrived (a bag's time is unsigned: mcap
    refuses < 0, which ended the recording)."""
    return stamp if stamp > 0 else received


def silence_hint(
    received: int,
    publishers: int,
    topic: str,
    reliable: bool,
    reliable_publishers=None,
    other_types: list[str] | tuple[str, ...] = (),
) -> str | None:
    """Why no cloud arrived although ``publishers`` publish PointCloud2 on ``topic`` (None
    when some did arrive, or nobody publishes: then there is nothing to explain).
    ``reliable_publishers``: how many of them offer reliable QoS (None: unknown);
    ``other_types``: the message types of publishers on ``topic`` that are not PointCloud2."""
    if received:
        return None
    if other_types and not publishers:
        hint = (
            f"{topic}: published as {', '.join(other_types)}, not {POINTCLOUD2}, which is what "
            "the node reads"
        )
        if any("livox" in t.lower() for t in other_types):
            hint += " (the Livox driver publishes PointCloud2 with xfer_format 0)"
        return hint
    if not publishers:
        return None
    hint = f"{topic}: {publishers} publisher(s) but no cloud arrived in {SILENCE_S:g} s; "
    if reliable and reliable_publishers:
        # QoS matches: the publisher is idle (a driver starting, a lidar not spinning yet).
        return (
            hint + f"{reliable_publishers} of them reliable, so QoS is not the cause: "
            "they have sent nothing yet"
        )
    if reliable:
        return hint + "--reliable needs a reliable publisher (ros2 topic info -v shows its QoS)"
    return hint + (
        "large clouds (megabytes) are often lost whole over best-effort QoS, as one lost "
        "fragment drops the message: with a reliable publisher, --reliable subscribes reliably"
    )


class SilenceWatch:
    """Says, every ``SILENCE_S`` seconds until the first cloud arrives, why none arrives:
    each reason once in a row (checked once, a driver that came up later, or a publisher
    of another type, was never named)."""

    def __init__(self, started: float):
        self.next_check, self.last = started + SILENCE_S, None

    def due(self, now: float, received: int, hint: Callable[[], str | None]) -> str | None:
        """The hint to log now, if any; ``hint`` is called only when a check is due."""
        if received or now < self.next_check:
            return None
        self.next_check = now + SILENCE_S
        text = hint()
        new = text if text != self.last else None
        self.last = text
        return new


def _silence_hint(node, input_name: str, received: int, topic: str, reliable: bool):
    """``silence_hint`` for the input topic as the graph shows it now (its publishers, the
    QoS they offer, other message types on it); never raises: it is only a hint."""
    try:
        infos = node.get_publishers_info_by_topic(input_name)
        other_types = sorted({i.topic_type for i in infos} - {POINTCLOUD2})
        infos = [i for i in infos if i.topic_type == POINTCLOUD2]
        publishing = len(infos)
        offered = [getattr(i.qos_profile.reliability, "name", "") for i in infos]
        reliable_publishers = offered.count("RELIABLE")
    except Exception:  # noqa: BLE001 - only a hint; never stop the node
        publishing, reliable_publishers, other_types = 0, None, []
    return silence_hint(received, publishing, topic, reliable, reliable_publishers, other_types)


def run_detect_node(
    checkpoint: str,
    topic: str = "/livox/lidar",
    out_ns: str = "/indoorbev",
    reliable: bool = False,
    record: str | None = None,
    storage: str = "sqlite3",
    log_every: float = 5.0,
    max_frames: int = 0,
    ros_args: list[str] | None = None,
    skip_nonfinite: bool = False,
    intensity: str | float = "auto",
    views: tuple[str, ...] | None = None,
    boxes: str = "mask",
    mount: LidarMount = LEVEL,
    level_frame: str | None = None,
) -> dict:
    """Runs the detect node until Ctrl-C / SIGTERM (or ``max_frames`` processed frames).

    Args:
      checkpoint: run directory or exported model file.
      topic: the PointCloud2 input topic.
      out_ns: namespace of the outputs ``<out_ns>/detections|markers|occupancy``.
      reliable: subscribe with reliable QoS (default best effort, which matches both best
        effort and reliable publishers).
      record: optional rosbag2 folder receiving the input clouds and every output.
      storage: bag storage, "sqlite3" or "mcap".
      log_every: seconds between summary log lines.
      max_frames: stop after this many processed frames (0: run until stopped).
      ros_args: arguments after ``--ros-args`` (remappings, log levels), passed to rclpy.
      skip_nonfinite: process the finite points of clouds holding NaN/Inf points
        (default: warn and publish empty outputs for such a cloud).
      intensity: units of the clouds' intensity (``predict.intensity_factor``).
      views: test-time views (``config.VIEWS``; None: the model file's ``inference.views``).
      boxes: ``"mask"`` (boxes fitted to the masks) or ``"head"`` (regressed), as for
        ``predict.to_labels``.
      mount: how the lidar sits (``mount.LidarMount``; default level, read as it is).
      level_frame: frame id of the outputs, required when ``mount`` rotates the clouds.

    Returns:
      the statistics of ``_Stats.summary`` (counts and latency percentiles).
    """
    from indoorbev_jax.ros2 import runtime

    out_topics = check_settings(topic, out_ns, log_every, max_frames)
    check_level_frame(mount, level_frame)
    runtime.require_rclpy()
    runtime.check_ros_args(ros_args)
    if record is not None:  # before the slow warm-up ('' refused, not taken for none)
        from indoorbev_jax.ros2.record import ensure_new

        ensure_new(record)
    config, params = load_model(checkpoint)
    config = with_thresholds(config, views=views)
    detector = Detector(
        config, params, skip_nonfinite=skip_nonfinite, intensity=intensity, boxes=boxes,
        mount=mount, level_frame=level_frame,
    )  # fmt: skip
    if mount != LEVEL:
        print(f"indoorbev ros2 detect: lidar mount: "
              f"{mount.describe(config.sim.sensor_height)}", flush=True)  # fmt: skip
    for hint in mount.notes(config):
        print(f"indoorbev ros2 detect: note: {hint}", file=sys.stderr, flush=True)
    compile_s = detector.warmup()
    hint = speed_hint(detector.inference_ms(), config.inference.views)
    if hint:
        print(f"indoorbev ros2 detect: {hint}", flush=True)

    stats, lock, wake, stop = _Stats(), threading.Lock(), threading.Event(), threading.Event()
    mailbox: list = []  # at most one (raw cloud, receive time ns)
    failure: list[BaseException] = []
    started = time.monotonic()

    def on_cloud(raw: bytes) -> None:
        now = time.time_ns()
        with lock:
            stats.received += 1
            if mailbox:
                stats.dropped += 1
                mailbox.clear()
            mailbox.append((raw, now))
        wake.set()

    def work() -> None:
        try:
            process_forever()
        except BaseException as e:  # noqa: BLE001 - re-raised by the main thread
            failure.append(e)
            stop.set()

    # Runs on the worker thread, started below once node, log, publishers, bag_names and
    # recorder exist (the names are bound by then).
    def process_forever() -> None:
        last_log = time.monotonic()
        silence = SilenceWatch(started)
        recording_stopped = False  # the writer failed: detection goes on unrecorded
        while not stop.is_set():
            if not wake.wait(0.1):
                with lock:
                    received = stats.received
                hint = silence.due(
                    time.monotonic(),
                    received,
                    lambda: _silence_hint(node, bag_names["input"], 0, topic, reliable),
                )
                if hint:
                    log.warning(hint)
                continue
            with lock:
                wake.clear()
                if not mailbox:
                    continue
                raw, received = mailbox.pop()
            result = detector.process(raw)
            published = time.time_ns()
            for k, message in result.outputs.items():  # detections first: latency counts it
                publishers[k].publish(message)
                if k == "detections":
                    published = time.time_ns()
            if recorder is not None and not recording_stopped:
                log_ns = bag_log_ns(result.stamp, received)
                ok = recorder.write(bag_names["input"], log_ns, bytes(raw))
                for k, message in result.outputs.items():
                    ok = ok and recorder.write(bag_names[k], log_ns, message)
                if not ok:
                    recording_stopped = True
                    log.error(f"{recorder.error}; detection goes on unrecorded")
            with lock:
                stats.processed += 1
                if result.warning is not None:
                    # At most one a second: a sensor that sends bad clouds sends them at rate.
                    log.warning(result.warning, throttle_duration_sec=1.0)
                if not result.infer_ms:
                    stats.bad += 1
                if result.stamp:  # unstamped clouds (warm-ups) leave every latency alone
                    if result.infer_ms:
                        stats.infer.append(result.infer_ms)
                    stats.transport.append((received - result.stamp) / 1e6)
                    stats.total.append((published - result.stamp) / 1e6)
                done = max_frames and stats.processed >= max_frames
            log.debug(f"{result.frame} @ {result.stamp}: {len(result.labels)} objects, "
                      f"{result.infer_ms:.1f} ms inference")  # fmt: skip
            if time.monotonic() - last_log > log_every:
                last_log = time.monotonic()
                with lock:
                    log.info(json.dumps(stats.summary()))
            if done:
                stop.set()

    recorder = worker = None
    context, node = runtime.start_node("indoorbev_detect", ros_args)
    # Everything after the node exists runs under try, so that Ctrl-C at any point still
    # finishes the recording and stops the node.
    try:
        log = node.get_logger()
        publishers = {
            k: node.create_publisher(runtime.msg_class(OUTPUTS[k]), t, runtime.qos(True, 5))
            for k, t in out_topics.items()
        }
        subscription = node.create_subscription(
            runtime.msg_class(POINTCLOUD2), topic, on_cloud, runtime.qos(reliable, 1), raw=True
        )
        # The bag names the topics as they are on the wire: fully qualified, after the
        # node's namespace and any remapping (what `ros2 bag record` would write).
        bag_names = {"input": subscription.topic_name}
        bag_names |= {k: publishers[k].topic_name for k in OUTPUTS}
        if bag_names["input"] in {bag_names[k] for k in OUTPUTS}:  # relative, or remapped
            raise ValueError(
                f"topic: {topic!r} resolves to {bag_names['input']}, one of the node's own "
                "outputs; subscribe to the lidar's cloud topic"
            )
        if record is not None:
            from indoorbev_jax.ros2.record import BagRecorder

            bag_topics = {bag_names["input"]: POINTCLOUD2}
            bag_topics |= {bag_names[k]: OUTPUTS[k] for k in OUTPUTS}
            recorder = BagRecorder(record, bag_topics, detector.ts, storage)
        worker = threading.Thread(target=work, name="indoorbev-detect", daemon=True)
        worker.start()
        print(
            f"indoorbev ros2 detect: ready (warm-up {compile_s:.1f} s); "
            f"{bag_names['input']} -> {', '.join(bag_names[k] for k in OUTPUTS)}",
            flush=True,
        )
        runtime.spin(node, context, stop)
    finally:
        held = "indoorbev ros2 detect: finishing the current frame" + (
            f" and the recording {record} (kill -9 abandons it)" if recorder else ""
        )
        with runtime.signals_held(held):
            stop.set()
            if worker is not None:
                worker.join()
            recording_failed = None
            if recorder is not None:
                try:
                    path = recorder.close()
                    print(f"indoorbev ros2 detect: recorded {recorder.counts} into {path}",
                          flush=True)  # fmt: skip
                except RuntimeError as e:  # the node still stops and reports
                    recording_failed = str(e)
            runtime.stop_node(node, context)
    if failure:
        raise RuntimeError("the inference worker failed") from failure[0]
    summary = stats.summary()
    print("indoorbev ros2 detect: summary " + json.dumps(summary), flush=True)
    if recording_failed:
        raise OSError(recording_failed)
    return summary
