"""The simulated lidar node: ``indoorbev-sim ros2 publish``.

Publishes simulated scenes frame by frame at sensor rate: sensor_msgs/PointCloud2 (float32
x, y, z, intensity) on ``--topic`` and the ground truth as visualization_msgs/MarkerArray
(a DELETEALL, then one CUBE per object, as in the exported bags: ``ns`` = class, ``text`` =
"class occlusion"; each marker lives two frame periods so RViz drops objects that left) on
``--objects-topic``, stamped with the publish time. Scenes are the consecutive-frame
sequences of ``generate.generate_sequences`` (people and robots move, the lidar rides its
robot); scene j uses ``fold_in(key(seed), j)``. A thread generates frames ahead of the
publishing loop, so the rate holds whenever generation keeps up (it says when it does not).

``--lidar-rpy ROLL,PITCH,YAW`` simulates a tilted lidar (``sim.sensor_rpy``) and publishes
its clouds as the sensor delivers them, in its own tilted frame (``--frame-id``); the
ground truth stays in the level frame, named by ``--level-frame``: what ``indoorbev ros2
detect --lidar-rpy ... --level-frame ...`` takes in and gives out.
"""

from __future__ import annotations

import dataclasses
import queue
import sys
import threading
import time
from collections.abc import Iterator

import jax
import numpy as np

from indoorbev_jax.checks import check_positive, check_seed, check_whole
from indoorbev_jax.config import Config
from indoorbev_jax.mount import LEVEL, LidarMount
from indoorbev_jax.rosbag import MARKER_ARRAY, POINTCLOUD2, cloud_msg, markers_msg, typestore

POINTS_TOPIC, OBJECTS_TOPIC = "/lidar/points", "/lidar/objects"


def scene_frames(config: Config, seed: int, split: str = "test") -> Iterator:
    """Endless (points float32 [N, 4], ground-truth labels) frames, scene after scene."""
    from indoorbev_sim.export import scene_fn, scene_frame
    from indoorbev_sim.scenes import split_flag

    fn, test = scene_fn(config), split_flag(split)
    key = jax.random.key(seed)
    for j in range(2**31):
        batch, info = jax.device_get(fn(jax.random.fold_in(key, j), test))
        for t in range(config.sim.frames_per_sequence):
            points, labels = scene_frame(batch, info, t)
            yield points.astype(np.float32), labels


def frame_messages(ts, points, labels, names, stamp: int, frame_id: str, mount=LEVEL,
                   level_frame: str | None = None):  # fmt: skip
    """(PointCloud2, MarkerArray) of one simulated frame: the cloud turned from the level
    frame into the tilted lidar's (``mount``; the points R^T p) under ``frame_id``, the
    ground truth under ``level_frame`` when tilted, else ``frame_id``."""
    cloud = cloud_msg(ts, mount.unlevelled(points), stamp, frame_id)
    return cloud, markers_msg(ts, labels, names, stamp, level_frame or frame_id)


def check_settings(rate, frames, topic, objects_topic, wait_subscribers, wait_timeout,
                   mount=LEVEL, level_frame=None, frame_id="lidar") -> None:  # fmt: skip
    """A ``ValueError`` naming the first setting of ``publish`` that cannot work, before
    the node starts."""
    from indoorbev_jax.ros2 import check_topic_name

    check_positive("rate", rate, "frames per second")
    check_whole("frames", frames, 0, " (0: unbounded)")
    check_topic_name(topic, "topic")
    check_topic_name(objects_topic, "objects_topic")
    if topic == objects_topic:  # else rcl's "incompatible type" error, naming no flag
        raise ValueError(f"objects_topic: {objects_topic!r} is the clouds' topic; give another")
    check_whole("wait_subscribers", wait_subscribers, 0)
    check_positive("wait_timeout", wait_timeout)
    if not frame_id:  # RViz and tf cannot place a message of frame ""
        raise ValueError("frame_id: an empty frame id; expected a tf frame name such as 'lidar'")
    if mount.rotated and not level_frame:
        raise ValueError(
            "--lidar-rpy publishes the clouds in the tilted lidar's frame and the ground "
            "truth in the level one: name it with --level-frame (the lidar's origin with the "
            "robot's level axes)"
        )
    if level_frame and level_frame == frame_id:
        raise ValueError(
            f"--level-frame {level_frame!r} is --frame-id's: the tilted cloud and the level "
            "ground truth are in different frames and need different ids"
        )
    if level_frame and not mount.rotated:
        raise ValueError(
            f"--level-frame {level_frame!r} without a --lidar-rpy rotation: the ground truth "
            "is in --frame-id's frame; drop --level-frame"
        )


def publish(
    config: Config,
    rate: float = 10.0,
    frames: int = 0,
    topic: str = POINTS_TOPIC,
    objects_topic: str = OBJECTS_TOPIC,
    frame_id: str = "lidar",
    seed: int = 0,
    split: str = "test",
    record: str | None = None,
    storage: str = "sqlite3",
    wait_subscribers: int = 0,
    wait_timeout: float = 60.0,
    ros_args: list[str] | None = None,
    lidar_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0),
    level_frame: str | None = None,
) -> dict:
    """Publishes simulated frames until ``frames`` are out (0: until Ctrl-C / SIGTERM).

    Args:
      config: run configuration (grid, sim: rays, pattern, scene contents).
      rate: frames per second.
      frames: frames to publish (0: unbounded).
      topic, objects_topic: the PointCloud2 and the ground-truth MarkerArray topics.
      frame_id: the header frame id.
      seed: base seed of the scenes.
      split: "train", "val" or "test" (held-out floor plans).
      record: optional rosbag2 folder receiving every published message.
      storage: bag storage, "sqlite3" or "mcap".
      wait_subscribers: wait for this many subscribers on ``topic`` before the first frame
        (then half a second more, for the subscriber's side of the discovery).
      wait_timeout: give up waiting after this many seconds (a ``RuntimeError``).
      ros_args: arguments after ``--ros-args``, passed to rclpy.
      lidar_rpy: the lidar's roll, pitch, yaw in the level frame, degrees (URDF rpy): the
        scans are simulated tilted (it replaces ``config.sim.sensor_rpy``) and published
        in the lidar's frame.
      level_frame: the ground truth's frame id when ``lidar_rpy`` tilts (required then).

    Returns:
      {"frames": published, "rate_hz": achieved rate, "late": frames sent over a period late}.
    """
    from indoorbev_jax.ros2 import runtime

    mount = LidarMount(*lidar_rpy)
    check_settings(rate, frames, topic, objects_topic, wait_subscribers, wait_timeout, mount,
                   level_frame, frame_id)  # fmt: skip
    check_seed("seed", seed)
    if hint := mount.radians_hint():
        print(f"indoorbev-sim ros2 publish: note: {hint}", file=sys.stderr, flush=True)
    # The scans are simulated with the one tilt the clouds are published with, whatever
    # config.sim.sensor_rpy and sensor_tilt_jitter said.
    sim = dataclasses.replace(
        config.sim, sensor_rpy=tuple(map(float, lidar_rpy)), sensor_tilt_jitter=0.0
    )
    config = dataclasses.replace(config, sim=sim)
    runtime.require_rclpy()
    if record is not None:  # "" is refused, not taken for no recording
        from indoorbev_jax.ros2.record import ensure_new

        ensure_new(record)
    ts = typestore()
    names = config.data.class_names
    stop = threading.Event()
    ahead: queue.Queue = queue.Queue(maxsize=2 * config.sim.frames_per_sequence)

    def produce() -> None:
        for frame in scene_frames(config, seed, split):
            while not stop.is_set():
                try:
                    ahead.put(frame, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if stop.is_set():
                return

    period = 1.0 / rate
    lifetime_ns = round(2e9 * period)
    sent = late = 0
    first = last = 0.0  # monotonic times of the first and last frame
    recorder = producer = None
    recording_stopped = False  # the writer failed: publishing goes on unrecorded
    context, node = runtime.start_node("indoorbev_sim", ros_args)
    try:  # from here on, Ctrl-C still finishes the recording and stops the node
        reliable = runtime.qos(True, 5)
        pub_points = node.create_publisher(runtime.msg_class(POINTCLOUD2), topic, reliable)
        pub_objects = node.create_publisher(runtime.msg_class(MARKER_ARRAY), objects_topic,
                                            reliable)  # fmt: skip
        # Fully qualified names, after the node's namespace and remappings: the bag's.
        points_name, objects_name = pub_points.topic_name, pub_objects.topic_name
        if record is not None:
            from indoorbev_jax.ros2.record import BagRecorder

            recorder = BagRecorder(record, {points_name: POINTCLOUD2, objects_name: MARKER_ARRAY},
                                   ts, storage)  # fmt: skip
        producer = threading.Thread(target=produce, name="indoorbev-sim", daemon=True)
        producer.start()
        if wait_subscribers:
            deadline = time.monotonic() + wait_timeout
            while pub_points.get_subscription_count() < wait_subscribers:
                if time.monotonic() > deadline or not context.ok():
                    raise RuntimeError(
                        f"{topic}: {pub_points.get_subscription_count()} subscriber(s) after "
                        f"{wait_timeout} s, waited for {wait_subscribers}"
                    )
                time.sleep(0.05)
            time.sleep(0.5)
        print(f"indoorbev-sim ros2 publish: {points_name}, {objects_name} at {rate} Hz",
              flush=True)  # fmt: skip
        next_time = 0.0
        while context.ok() and (frames == 0 or sent < frames):
            try:
                points, labels = ahead.get(timeout=0.1)
            except queue.Empty:
                continue
            if sent == 0 or time.monotonic() - next_time > period:
                late += sent > 0  # generation fell a period behind: re-anchor the schedule
                next_time = time.monotonic()
            while context.ok() and (wait := next_time - time.monotonic()) > 0:
                time.sleep(min(wait, 0.1))
            if not context.ok():
                break
            last = time.monotonic()
            first = first or last
            stamp = node.get_clock().now().nanoseconds
            cloud, truth = frame_messages(ts, points, labels, names, stamp, frame_id, mount,
                                          level_frame)  # fmt: skip
            cloud = ts.serialize_cdr(cloud, POINTCLOUD2)
            for m in truth.markers:
                m.lifetime.sec, m.lifetime.nanosec = divmod(lifetime_ns, 10**9)
            truth = ts.serialize_cdr(truth, MARKER_ARRAY)
            pub_points.publish(bytes(cloud))
            pub_objects.publish(bytes(truth))
            if recorder is not None and not recording_stopped:
                ok = recorder.write(points_name, stamp, bytes(cloud))
                if not (ok and recorder.write(objects_name, stamp, bytes(truth))):
                    recording_stopped = True
                    node.get_logger().error(f"{recorder.error}; publishing goes on unrecorded")
            sent += 1
            next_time += period
        time.sleep(0.5)  # let reliable deliveries of the last frames complete
    except KeyboardInterrupt:
        pass
    finally:
        held = "indoorbev-sim ros2 publish: stopping" + (
            f"; finishing the recording {record} (kill -9 abandons it)" if recorder else ""
        )
        with runtime.signals_held(held):
            stop.set()
            if producer is not None:
                # Let the scene in progress finish: an interpreter that exits while this
                # thread is inside jitted code aborts (SIGABRT, "FATAL: exception not
                # rethrown"), so a Ctrl-C that came mid-scene would end in status 134.
                producer.join()
            recording_failed = None
            if recorder is not None:
                try:
                    print(f"indoorbev-sim ros2 publish: recorded into {recorder.close()}",
                          flush=True)  # fmt: skip
                except RuntimeError as e:  # the node still stops and reports
                    recording_failed = str(e)
            runtime.stop_node(node, context)
    achieved = (sent - 1) / (last - first) if sent > 1 and last > first else 0.0
    summary = {"frames": sent, "rate_hz": round(achieved, 2), "late": late}
    print(f"indoorbev-sim ros2 publish: {summary}", flush=True)
    if recording_failed:
        raise OSError(recording_failed)
    return summary
