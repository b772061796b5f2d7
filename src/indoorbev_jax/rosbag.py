"""ROS 2 bags without a ROS install, through the pure-Python ``rosbags`` library.

Reads sensor_msgs/PointCloud2 of any field layout holding x, y, z (and optionally
intensity) and Livox's livox_ros_driver2/CustomMsg (what the MID-360's ROS 2 driver
publishes with ``xfer_format`` 1, and what lidar-inertial odometry recipes record), and
builds the PointCloud2 / MarkerArray messages the simulator export and the predict command
write.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from indoorbev_jax.data import kitti

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
LIVOX_CUSTOM = "livox_ros_driver2/msg/CustomMsg"

# livox_ros_driver2's msg/CustomPoint.msg and msg/CustomMsg.msg, so that its bags read
# without the package; reflectivity is Livox's 0-255 (150 = 100 % Lambertian).
_LIVOX_POINT = """uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""
_LIVOX_CLOUD = """std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
livox_ros_driver2/CustomPoint[] points
"""
# The message types read as lidar frames.
CLOUD_TYPES = (POINTCLOUD2, LIVOX_CUSTOM)

# sensor_msgs/PointField datatypes -> numpy scalar types.
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


class BagError(ValueError):
    """A bag or message cannot be read as lidar frames; the message names what and why."""


def typestore():
    """ROS 2 Humble's message types, plus Livox's CustomMsg."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    types = get_types_from_msg(_LIVOX_POINT, "livox_ros_driver2/msg/CustomPoint")
    types |= get_types_from_msg(_LIVOX_CLOUD, LIVOX_CUSTOM)
    ts.register(types)
    return ts


def header(ts, stamp_ns: int, frame: str = "lidar"):
    t = ts.types
    stamp = t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def cloud_msg(ts, points: np.ndarray, stamp_ns: int, frame: str = "lidar"):
    """A PointCloud2 of float32 x, y, z, intensity from points [N, 4]."""
    t = ts.types
    field = t["sensor_msgs/msg/PointField"]
    fields = [
        field(name=n, offset=4 * i, datatype=field.FLOAT32, count=1)
        for i, n in enumerate(("x", "y", "z", "intensity"))
    ]
    data = np.ascontiguousarray(points, dtype="<f4")
    return t[POINTCLOUD2](
        header=header(ts, stamp_ns, frame),
        height=1,
        width=len(data),
        fields=fields,
        is_bigendian=False,
        point_step=16,
        row_step=16 * len(data),
        data=data.view(np.uint8).reshape(-1),
        is_dense=True,
    )


def marker(ts, hdr, ns: str, ident: int, kind: int, **fields):
    """A visualization_msgs/Marker (action ADD, identity pose, white, no lifetime) with every
    field set, as rosbags needs; ``fields`` override any of them."""
    t = ts.types
    empty = np.zeros(0, np.uint8)
    cls = t["visualization_msgs/msg/Marker"]
    values = {
        "header": hdr,
        "ns": ns,
        "id": ident,
        "type": kind,
        "action": cls.ADD,
        "pose": t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](0.0, 0.0, 0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
        ),
        "scale": t["geometry_msgs/msg/Vector3"](1.0, 1.0, 1.0),
        "color": t["std_msgs/msg/ColorRGBA"](1.0, 1.0, 1.0, 1.0),
        "lifetime": t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        "frame_locked": False,
        "points": [],
        "colors": [],
        "texture_resource": "",
        "texture": t["sensor_msgs/msg/CompressedImage"](header=hdr, format="", data=empty),
        "uv_coordinates": [],
        "text": "",
        "mesh_resource": "",
        "mesh_file": t["visualization_msgs/msg/MeshFile"](filename="", data=empty),
        "mesh_use_embedded_materials": False,
    }
    values.update(fields)
    return cls(**values)


def markers_msg(ts, labels: kitti.ObjectLabels, names, stamp_ns: int, frame: str = "lidar"):
    """A MarkerArray with one CUBE per object: namespace = class name, text = class and
    occlusion (ground truth) or class and score (predictions)."""
    t = ts.types
    hdr = header(ts, stamp_ns, frame)
    markers = []
    for k in range(len(labels)):
        yaw = float(labels.yaw[k])
        name = names[int(labels.classes[k])]
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](*(float(v) for v in labels.pos[k])),
            orientation=t["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        )
        hue = int(labels.classes[k]) / max(len(names), 1)
        extra = (
            f"{float(labels.scores[k]):.3f}"
            if labels.scores is not None
            else str(int(labels.occlusion[k]))
        )
        markers.append(
            marker(
                ts,
                hdr,
                name,
                k,
                t["visualization_msgs/msg/Marker"].CUBE,
                pose=pose,
                scale=t["geometry_msgs/msg/Vector3"](*(float(v) for v in labels.dims[k])),
                color=t["std_msgs/msg/ColorRGBA"](r=hue, g=1.0 - hue, b=0.5, a=0.6),
                text=f"{name} {extra}",
            )  # fmt: skip
        )
    return t[MARKER_ARRAY](markers=markers)


def markers_to_labels(msg, data_config) -> kitti.ObjectLabels:
    """Inverse of ``markers_msg`` (scores when the texts carry them)."""
    m = msg.markers
    extras = [x.text.split()[-1] for x in m]
    has_scores = any("." in e for e in extras)
    return kitti.ObjectLabels(
        classes=[data_config.class_index(x.ns) for x in m],
        dims=[[x.scale.x, x.scale.y, x.scale.z] for x in m],
        pos=[[x.pose.position.x, x.pose.position.y, x.pose.position.z] for x in m],
        yaw=[2 * math.atan2(x.pose.orientation.z, x.pose.orientation.w) for x in m],
        occlusion=[0 if has_scores else int(e) for e in extras],
        scores=[float(e) for e in extras] if has_scores else None,
    )


def pointcloud2_to_points(msg, source: str = "PointCloud2") -> np.ndarray:
    """float32 [N, 4] (x, y, z, intensity) from a PointCloud2 of any field layout.

    x, y and z are required; intensity is taken from a field named ``intensity`` (or
    ``reflectivity``) when present, else 0. Any numeric datatype and either byte order.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        have = sorted(fields)
        raise BagError(f"{source}: PointCloud2 lacks field(s) {missing}; it has {have}")
    order = ">" if msg.is_bigendian else "<"
    n = int(msg.width) * int(msg.height)
    raw = np.asarray(msg.data, np.uint8)
    if raw.size < n * msg.point_step:
        raise BagError(
            f"{source}: data holds {raw.size} bytes, expected {n} points x {msg.point_step}"
        )
    rows = raw[: n * msg.point_step].reshape(n, msg.point_step)

    def column(name):
        f = fields[name]
        if f.datatype not in _FIELD_TYPES:
            raise BagError(f"{source}: field '{name}' has unknown datatype {f.datatype}")
        dtype = np.dtype(order + _FIELD_TYPES[f.datatype])
        cols = rows[:, f.offset : f.offset + dtype.itemsize]
        return np.ascontiguousarray(cols).view(dtype).reshape(n).astype(np.float32)

    name_i = next((c for c in ("intensity", "reflectivity") if c in fields), None)
    intensity = column(name_i) if name_i else np.zeros(n, np.float32)
    return np.stack([column("x"), column("y"), column("z"), intensity], axis=1)


def livox_custom_to_points(msg, source: str = "CustomMsg") -> np.ndarray:
    """float32 [N, 4] (x, y, z, reflectivity 0-255) from a livox_ros_driver2/CustomMsg."""
    points = msg.points
    if int(msg.point_num) != len(points):
        raise BagError(f"{source}: point_num {msg.point_num} but {len(points)} points")
    out = np.empty((len(points), 4), np.float32)
    for k, field in enumerate(("x", "y", "z", "reflectivity")):
        out[:, k] = [getattr(p, field) for p in points]
    return out


def read_clouds(
    bag: str | os.PathLike, topic: str | None = None
) -> Iterator[tuple[int, str, np.ndarray]]:
    """Yields (timestamp ns, frame id, points [N, 4]) for each cloud message of a bag.

    Args:
      bag: a rosbag2 folder (sqlite3 or MCAP storage) holding sensor_msgs/PointCloud2 or
        livox_ros_driver2/CustomMsg (intensity = Livox reflectivity 0-255).
      topic: topic name; None picks the only such topic (an error when several).
    """
    from rosbags.rosbag2 import Reader

    bag = Path(bag)
    ts = typestore()
    kinds = " or ".join(t.rsplit("/", 1)[-1] for t in CLOUD_TYPES)
    with Reader(bag) as reader:
        clouds = [c for c in reader.connections if c.msgtype in CLOUD_TYPES]
        if topic is not None:
            chosen = [c for c in reader.connections if c.topic == topic]
            if not chosen:
                have = sorted({c.topic for c in reader.connections})
                raise BagError(f"{bag}: no topic '{topic}'; topics: {have}")
            if chosen[0].msgtype not in CLOUD_TYPES:
                raise BagError(
                    f"{bag}: topic '{topic}' is {chosen[0].msgtype}, not one of {CLOUD_TYPES}"
                )
        elif len({c.topic for c in clouds}) != 1:
            names = sorted({c.topic for c in clouds})
            raise BagError(f"{bag}: {len(names)} {kinds} topics {names}; pick one with --topic")
        else:
            chosen = clouds
        for conn, stamp, raw in reader.messages(connections=chosen):
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            source = f"{bag}@{stamp}"
            if conn.msgtype == LIVOX_CUSTOM:
                points = livox_custom_to_points(msg, source)
            else:
                points = pointcloud2_to_points(msg, source)
            yield stamp, msg.header.frame_id, points


def write_bag(
    bag: str | os.PathLike,
    frames: Iterable[tuple[int, str, np.ndarray, kitti.ObjectLabels]],
    class_names,
    points_topic: str,
    objects_topic: str,
) -> None:
    """Writes (stamp ns, frame id, points [N, 4], labels) frames as PointCloud2 on
    ``points_topic`` and MarkerArray on ``objects_topic``.

    The bag is written under a temporary folder and renamed into place, so an interrupted
    write never leaves a bag under the final name.
    """
    from rosbags.rosbag2 import Writer

    ts = typestore()
    bag = Path(bag)
    # rosbags names the storage file after the bag folder: write <bag>.partial/<name>.
    partial = bag.with_name(bag.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    tmp = partial / bag.name
    with Writer(tmp, version=8) as writer:
        c_pts = writer.add_connection(points_topic, POINTCLOUD2, typestore=ts)
        c_obj = writer.add_connection(objects_topic, MARKER_ARRAY, typestore=ts)
        for stamp, frame, points, labels in frames:
            cloud = cloud_msg(ts, points, stamp, frame)
            writer.write(c_pts, stamp, ts.serialize_cdr(cloud, POINTCLOUD2))
            markers = markers_msg(ts, labels, class_names, stamp, frame)
            writer.write(c_obj, stamp, ts.serialize_cdr(markers, MARKER_ARRAY))
    if bag.exists():
        shutil.rmtree(bag)
    os.replace(tmp, bag)
    partial.rmdir()
