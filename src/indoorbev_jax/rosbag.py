"""ROS 2 bags without a ROS install, through the pure-Python ``rosbags`` library.

Reads sensor_msgs/PointCloud2 of any field layout holding x, y, z (and optionally
intensity) and Livox's livox_ros_driver2/CustomMsg (what the MID-360's ROS 2 driver
publishes with ``xfer_format`` 1, and what lidar-inertial odometry recipes record), and
builds the PointCloud2 / MarkerArray messages the simulator export and the predict command
write.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from indoorbev_jax.data import kitti
from indoorbev_jax.fileio import check_unheld, hold_folder

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
    """A PointCloud2 of float32 x, y, z, intensity from points [N, 4]; ``is_dense`` says
    whether every point is valid (finite x, y, z), as the message definition has it:
    ``predict --bag-out`` passes on a driver's organised cloud with its NaN points."""
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
        is_dense=bool(np.isfinite(data[..., :3]).all()),
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


_MARKER_DELETEALL = 3  # visualization_msgs/Marker.DELETEALL


def markers_msg(ts, labels: kitti.ObjectLabels, names, stamp_ns: int, frame: str = "lidar"):
    """A MarkerArray: a DELETEALL (so that a replay does not keep the boxes of earlier
    frames), then one CUBE per object: namespace = class name, text = class and occlusion
    (ground truth) or class and score (predictions)."""
    t = ts.types
    hdr = header(ts, stamp_ns, frame)
    kind = t["visualization_msgs/msg/Marker"]
    markers = [marker(ts, hdr, "", 0, kind.CUBE, action=kind.DELETEALL)]
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
    """Inverse of ``markers_msg`` (scores when the texts carry them); DELETEALL markers
    (and bags written before they were) are read alike."""
    m = [x for x in msg.markers if x.action != _MARKER_DELETEALL]
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


_INTENSITY = ("intensity", "reflectivity")  # PointCloud2 field names read as intensity


def pointcloud2_to_points(msg, source: str = "PointCloud2") -> np.ndarray:
    """float32 [N, 4] (x, y, z, intensity) from a PointCloud2 of any field layout.

    x, y and z are required; intensity is taken from a field named ``intensity`` (or
    ``reflectivity``) when present, else 0. Any numeric datatype, either byte order, and
    organized clouds (height > 1) whose rows are padded (``row_step`` > width x point_step).
    """
    fields = {f.name: f for f in msg.fields}
    names = [f.name for f in msg.fields]
    twice = sorted({n for n in names if names.count(n) > 1} & {"x", "y", "z", *_INTENSITY})
    if twice:  # the last one silently won: x read from another field's bytes
        raise BagError(f"{source}: PointCloud2 names field(s) {twice} more than once: {names}")
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        have = sorted(fields)
        raise BagError(f"{source}: PointCloud2 lacks field(s) {missing}; it has {have}")
    order = ">" if msg.is_bigendian else "<"
    width, height, step = int(msg.width), int(msg.height), int(msg.point_step)
    name_i = next((c for c in _INTENSITY if c in fields), None)
    dtypes = {}
    # Every field read must fit in point_step before the sizes below are trusted: with
    # point_step 0 the data check needs no bytes, and width x height went unbounded.
    for name in ("x", "y", "z") + ((name_i,) if name_i else ()):
        f = fields[name]
        if f.datatype not in _FIELD_TYPES:
            raise BagError(f"{source}: field '{name}' has unknown datatype {f.datatype}")
        dtype = np.dtype(order + _FIELD_TYPES[f.datatype])
        if f.offset + dtype.itemsize > step:
            raise BagError(
                f"{source}: field '{name}' ({dtype.itemsize} bytes at offset {f.offset}) runs "
                f"past point_step {step}"
            )
        dtypes[name] = dtype
    row_bytes = width * step
    # One row is read from byte 0 whatever row_step says, as PCL and ROS 2's read_points do:
    # publishers written by hand often leave it 0.
    if height > 1 and int(msg.row_step) < row_bytes:
        raise BagError(
            f"{source}: row_step {msg.row_step} is less than width {width} x point_step {step}"
        )
    n = width * height
    raw = np.asarray(msg.data, np.uint8)
    # The last row needs no padding after its points.
    need = (height - 1) * int(msg.row_step) + row_bytes if n else 0
    if raw.size < need:
        raise BagError(
            f"{source}: data holds {raw.size} bytes, expected {height} rows of {width} points x "
            f"{step} bytes (row_step {msg.row_step}): {need} bytes"
        )
    if n == 0:
        return np.zeros((0, 4), np.float32)
    # Rows viewed in place (row_step apart, padding skipped; the checks above keep the view
    # inside ``raw``), then one point per line: memory for the points only, never
    # height x row_step, which a 1-row cloud may declare as up to 4 GiB.
    raw = np.ascontiguousarray(raw[:need])
    rows = np.lib.stride_tricks.as_strided(
        raw, shape=(height, row_bytes), strides=(int(msg.row_step), 1), writeable=False
    ).reshape(n, step)

    def column(name):
        offset, dtype = fields[name].offset, dtypes[name]
        cols = rows[:, offset : offset + dtype.itemsize]
        return np.ascontiguousarray(cols).view(dtype).reshape(n).astype(np.float32)

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


# One CustomPoint in CDR: 19 bytes, each aligned to 4 (its first member is a uint32).
_LIVOX_POINT_CDR = {"names": ["x", "y", "z", "reflectivity"], "offsets": [4, 8, 12, 16],
                    "itemsize": 19}  # fmt: skip


def _align(pos: int, size: int) -> int:
    return pos + (-pos % size)


def livox_custom_from_cdr(raw, source: str = "CustomMsg") -> tuple[int, str, np.ndarray]:
    """(header stamp ns, frame id, float32 [N, 4] x, y, z, reflectivity) read straight from
    a CustomMsg's CDR bytes: the same as ``deserialize_cdr`` + ``livox_custom_to_points``
    without a Python object per point (``experiments/bench_bag_decode.py``: 0.04 ms
    against 27 ms for a 20,000-point scan on a 2-core CPU)."""
    import struct

    buf = memoryview(bytes(raw) if not isinstance(raw, bytes | bytearray) else raw)
    try:
        if len(buf) < 4 or buf[1] not in (0, 1):
            raise ValueError(f"not a CDR message (header {bytes(buf[:4])!r})")
        order = "<" if buf[1] == 1 else ">"
        body = buf[4:]  # CDR aligns relative to the end of the 4-byte encapsulation header
        sec, nanosec, name_len = struct.unpack_from(order + "iII", body, 0)
        frame = bytes(body[12 : 12 + name_len]).rstrip(b"\0").decode("utf-8")
        pos = _align(12 + name_len, 8) + 8  # past timebase (uint64)
        (point_num,) = struct.unpack_from(order + "I", body, pos)
        pos += 8  # point_num, lidar_id, rsvd[3]
        (count,) = struct.unpack_from(order + "I", body, pos)
        pos += 4
        if count and len(body) < pos + 20 * (count - 1) + 19:
            raise ValueError(f"{len(body) + 4} bytes cannot hold {count} points")
    except (ValueError, struct.error, UnicodeDecodeError) as e:
        raise BagError(f"{source}: cannot read a Livox CustomMsg: {e}") from None
    if point_num != count:
        raise BagError(f"{source}: point_num {point_num} but {count} points")
    fields = dict(_LIVOX_POINT_CDR, formats=[order + "f4"] * 3 + ["u1"])
    points = np.ndarray((count,), np.dtype(fields), buffer=body, offset=pos, strides=(20,))
    out = np.empty((count, 4), np.float32)
    for k, name in enumerate(fields["names"]):
        out[:, k] = points[name]
    return sec * 10**9 + nanosec, frame, out


@dataclasses.dataclass(frozen=True)
class Cloud:
    """One cloud message of a bag: ``points`` float32 [N, 4], or ``error`` (a ``BagError``
    naming the bag, the frame and why) when the message cannot be read."""

    index: int  # position on the topic, from 0: the frame id predict writes
    log_ns: int  # when the bag recorded it
    stamp_ns: int | None  # the message header's stamp
    frame_id: str
    points: np.ndarray | None
    error: BagError | None = None


def _cloud_topics(reader, bag: Path, topic: str | None) -> list:
    """The connections of the chosen cloud topic (``read_clouds``' rules)."""
    kinds = " or ".join(t.rsplit("/", 1)[-1] for t in CLOUD_TYPES)
    every = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
    if topic is not None:
        chosen = [c for c in reader.connections if c.topic == topic]
        if not chosen:
            raise BagError(f"{bag}: no topic '{topic}'; topics: {every}")
        # A topic may carry several connections, of several types: read the clouds only.
        clouds = [c for c in chosen if c.msgtype in CLOUD_TYPES]
        if not clouds:
            types = sorted({c.msgtype for c in chosen})
            raise BagError(f"{bag}: topic '{topic}' is {' and '.join(types)}, not one of "
                           f"{CLOUD_TYPES}")  # fmt: skip
        return clouds
    clouds = [c for c in reader.connections if c.msgtype in CLOUD_TYPES]
    names = sorted({c.topic for c in clouds})
    if not names:
        raise BagError(f"{bag}: no {kinds} topic; topics: {every}")
    if len(names) > 1:
        raise BagError(f"{bag}: {len(names)} {kinds} topics {names}; pick one with --topic")
    return clouds


def _open_reader(bag: Path):
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    try:
        reader = Reader(bag)
        reader.open()
    except ReaderError as e:
        raise BagError(f"{bag}: not a readable ROS 2 bag: {e}") from None
    return reader


def count_clouds(bag: str | os.PathLike, topic: str | None = None) -> int:
    """How many messages ``iter_clouds`` yields (from the bag's index, without reading)."""
    bag = Path(bag)
    reader = _open_reader(bag)
    try:
        return sum(c.msgcount for c in _cloud_topics(reader, bag, topic))
    finally:
        reader.close()


def _decode(ts, conn, raw, source: str) -> tuple[int | None, str, np.ndarray]:
    if conn.msgtype == LIVOX_CUSTOM:
        return livox_custom_from_cdr(raw, source)
    msg = ts.deserialize_cdr(raw, conn.msgtype)
    stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
    return stamp, msg.header.frame_id, pointcloud2_to_points(msg, source)


def iter_clouds(bag: str | os.PathLike, topic: str | None = None) -> Iterator[Cloud]:
    """Yields every cloud message of a bag's cloud topic as a ``Cloud``, in record-time order.

    A message that cannot be decoded is yielded with its ``error`` set (and no points), so
    that a caller may skip it and go on; a bag whose storage cannot be opened or read any
    further raises ``BagError``, naming the bag and the last frame read.

    Args:
      bag: a rosbag2 folder (sqlite3 or MCAP storage), or one such storage file on its own,
        holding sensor_msgs/PointCloud2 or
        livox_ros_driver2/CustomMsg (intensity = Livox reflectivity 0-255).
      topic: topic name; None picks the only such topic (an error when several).
    """
    from rosbags.serde import SerdeError

    bag = Path(bag)
    ts = typestore()
    reader = _open_reader(bag)
    try:
        messages = reader.messages(connections=_cloud_topics(reader, bag, topic))
        index = 0
        while True:
            try:
                item = next(messages, None)
            except Exception as e:  # noqa: BLE001 - rosbags, sqlite and mcap errors differ
                raise BagError(f"{bag}: storage unreadable after {index} frames: {e}") from None
            if item is None:
                return
            conn, log_ns, raw = item
            source = f"{bag} frame {index:06d} (recorded at {log_ns} ns)"
            try:
                stamp, frame, points = _decode(ts, conn, raw, source)
                yield Cloud(index, log_ns, stamp, frame, points)
            except BagError as e:
                yield Cloud(index, log_ns, None, "", None, e)
            except (SerdeError, ValueError, AttributeError, TypeError) as e:
                error = BagError(f"{source}: cannot decode {conn.msgtype}: {e}")
                yield Cloud(index, log_ns, None, "", None, error)
            index += 1
    finally:
        reader.close()


def read_clouds(
    bag: str | os.PathLike, topic: str | None = None
) -> Iterator[tuple[int, str, np.ndarray]]:
    """Yields (timestamp ns, frame id, points [N, 4]) for each cloud message of a bag; the
    first message that cannot be read raises its ``BagError`` (``iter_clouds`` goes on).

    Args:
      bag: a rosbag2 folder (sqlite3 or MCAP storage), or one such storage file on its own,
        holding sensor_msgs/PointCloud2 or
        livox_ros_driver2/CustomMsg (intensity = Livox reflectivity 0-255).
      topic: topic name; None picks the only such topic (an error when several).
    """
    for cloud in iter_clouds(bag, topic):
        if cloud.error is not None:
            raise cloud.error
        yield cloud.log_ns, cloud.frame_id, cloud.points


def _bag_files(bag: Path) -> set[str]:
    """metadata.yaml and the storage files it lists (empty when it cannot be read)."""
    from ruamel.yaml import YAML

    try:
        info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())
        paths = info["rosbag2_bagfile_information"]["relative_file_paths"]
        return {"metadata.yaml"} | {Path(str(p)).name for p in paths}
    except Exception:  # noqa: BLE001 - any unreadable metadata means "not ours"
        return set()


def check_bag_target(bag: str | os.PathLike, topics: Iterable[str]) -> None:
    """Raises ``BagError`` unless ``write_bag`` may write ``bag``: a path that does not exist,
    an empty folder, or a bag with exactly ``topics`` and nothing else in its folder (one
    written before by the same command). Anything else (a file, a folder of other files, a
    bag recorded on other topics) is never replaced."""
    bag = Path(bag)
    if not bag.exists():
        return
    if not bag.is_dir():
        raise BagError(f"{bag}: exists and is a file; choose another bag folder")
    present = {p.name for p in bag.iterdir()}
    if not present:
        return
    why = f"{bag}: exists and is not a bag written on topics {sorted(topics)}"
    if "metadata.yaml" not in present:
        raise BagError(f"{why} (it holds {sorted(present)[:5]}); remove it or choose another")
    listed = _bag_files(bag)
    try:
        reader = _open_reader(bag)
    except BagError as e:
        raise BagError(f"{why}: {e}; remove it or choose another folder") from None
    try:
        have = sorted({c.topic for c in reader.connections})
    finally:
        reader.close()
    extra = sorted(present - listed - {p + s for p in listed for s in ("-wal", "-shm")})
    if have != sorted(topics) or extra:
        detail = f"its topics are {have}" if have != sorted(topics) else f"it also holds {extra}"
        raise BagError(f"{why}: {detail}; remove it or choose another folder")


def partial_path(bag: Path) -> Path:
    """Where a bag is written until it is complete (``<bag>.partial``); rosbags names the
    storage file after the bag folder, so the bag itself is ``<bag>.partial/<name>``."""
    return bag.with_name(bag.name + ".partial")


# (job, place) of the lock a bag's write holds in its temporary folder (fileio.hold_folder).
BAG_LOCK = ("write of this bag", "bag folder")


def check_partial(bag: Path) -> Path:
    """``partial_path(bag)``, refused when it holds files an interrupted write of ``bag``
    does not leave (those are deleted before the write), or while another process writes
    ``bag`` (a ValueError naming it)."""
    partial = partial_path(bag)
    ours = {bag.name, f"{bag.name}.old"}

    def left_by_a_write(p: Path) -> bool:
        return p.name in ours or (p.name == ".lock" and p.is_file() and not p.is_symlink())

    if partial.exists() and not partial.is_dir():
        raise FileExistsError(f"{partial}: a file where the bag's temporary folder goes; move it")
    if partial.is_dir() and not all(left_by_a_write(p) for p in partial.iterdir()):
        raise FileExistsError(
            f"{partial}: holds files that an interrupted write of {bag} does not leave; "
            "move or delete it"
        )
    check_unheld(partial, *BAG_LOCK)
    return partial


def write_bag(
    bag: str | os.PathLike,
    frames: Iterable[tuple],
    class_names,
    points_topic: str,
    objects_topic: str,
) -> int:
    """Writes frames as PointCloud2 on ``points_topic`` and MarkerArray on ``objects_topic``;
    returns how many.

    Each frame is (record time ns, frame id, points [N, 4], labels), optionally followed by
    the header stamp in ns (default: the record time). The bag is written under a temporary
    folder and renamed into place, so an interrupted write never leaves a bag under the
    final name; an existing ``bag`` is replaced only when ``check_bag_target`` allows it.
    """
    bag = Path(bag)
    check_bag_target(bag, (points_topic, objects_topic))
    partial = check_partial(bag)
    # Two writes of one bag (two predict runs given one --bag-out) shared its temporary
    # folder: the second deleted the first's half-written bag. The first now holds it.
    with hold_folder(partial, *BAG_LOCK):
        return _write_bag_into(bag, partial, frames, class_names, points_topic, objects_topic)


def _write_bag_into(bag: Path, partial: Path, frames, class_names, points_topic, objects_topic):
    """``write_bag``'s writing, under the lock on its temporary folder ``partial``."""
    import sqlite3

    from rosbags.rosbag2 import Writer, WriterError

    ts = typestore()
    replaced = partial / f"{bag.name}.old"  # the bag this write replaces, on its way out
    tmp = partial / bag.name
    for stale in (tmp, replaced):  # left by an earlier write of this bag, cut short
        if stale.is_symlink() or stale.is_file():
            stale.unlink()
        else:
            shutil.rmtree(stale, ignore_errors=True)
    count = 0
    try:
        with Writer(tmp, version=8) as writer:
            c_pts = writer.add_connection(points_topic, POINTCLOUD2, typestore=ts)
            c_obj = writer.add_connection(objects_topic, MARKER_ARRAY, typestore=ts)
            for log_ns, frame, points, labels, *header_ns in frames:
                stamp = header_ns[0] if header_ns and header_ns[0] is not None else log_ns
                cloud = cloud_msg(ts, points, stamp, frame)
                writer.write(c_pts, log_ns, ts.serialize_cdr(cloud, POINTCLOUD2))
                markers = markers_msg(ts, labels, class_names, stamp, frame)
                writer.write(c_obj, log_ns, ts.serialize_cdr(markers, MARKER_ARRAY))
                count += 1
    except (sqlite3.Error, WriterError) as e:  # a full disk, say: sqlite3 names no file
        shutil.rmtree(partial, ignore_errors=True)  # its space back (the old bag is intact)
        raise OSError(f"{bag}: cannot write the bag ({type(e).__name__}: {e})") from e
    except Exception:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    check_bag_target(bag, (points_topic, objects_topic))  # nothing else appeared meanwhile
    # Renames only until the new bag is in place: a kill while a large old bag was being
    # deleted left it half gone under the final name, and every rerun refused it.
    if bag.exists():
        os.replace(bag, replaced)
    os.replace(tmp, bag)
    shutil.rmtree(partial)
    return count
