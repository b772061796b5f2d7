"""The messages the live nodes publish, built with the ``rosbags`` typestore (no ROS needed).

Per input cloud the detect node publishes, all stamped and framed like the cloud:

* detections, sensor_msgs/PointCloud2 with one "point" per object and the fields
  ``x y z`` (box centre), ``length width height yaw``, ``score`` (float32) and
  ``class_id`` (int32, an index into ``config.data.class_names``). There is no detection
  message among the standard ROS 2 interfaces shipped as PyPI wheels (vision_msgs is not),
  and PointCloud2 is stamped, framed, self-describing (named, typed fields) and read by
  every ROS client library (``sensor_msgs_py.point_cloud2.read_points``) and RViz.
* markers, visualization_msgs/MarkerArray: a DELETEALL (so that objects of the previous
  frame vanish), then per object a closed LINE_STRIP footprint (``ns`` "footprints") and a
  TEXT_VIEW_FACING "class score" label (``ns`` "labels"), ``id`` = object index.
* occupancy, nav_msgs/OccupancyGrid on the model's BEV grid (``config.grid``): 100 where
  the predicted panoptic map has an object, 0 elsewhere, -1 everywhere when the cloud was
  unusable.
"""

from __future__ import annotations

import struct

import numpy as np

from indoorbev_jax.config import GridConfig
from indoorbev_jax.data import kitti
from indoorbev_jax.geometry import box_corners
from indoorbev_jax.rosbag import MARKER_ARRAY, POINTCLOUD2, header, marker

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
DETECTION_FIELDS = ("x", "y", "z", "length", "width", "height", "yaw", "score", "class_id")
_FLOAT32, _INT32 = 7, 5
_DETECTION_DTYPE = np.dtype([(n, "<i4" if n == "class_id" else "<f4") for n in DETECTION_FIELDS])


def stamp_ns(msg) -> int:
    """The header stamp of a message, in nanoseconds."""
    return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)


def header_from_cdr(raw: bytes) -> tuple[int, str] | None:
    """(stamp ns, frame id) of a serialized message that starts with a std_msgs/Header,
    read without decoding the rest, or None when even that is unreadable. So that outputs
    for a cloud whose body is broken still carry its stamp and frame."""
    raw = bytes(raw)
    if len(raw) < 16 or raw[0] != 0 or raw[1] not in (0, 1):
        return None
    order = "<" if raw[1] == 1 else ">"  # encapsulation 0x0001: little-endian CDR
    sec, nanosec, size = struct.unpack_from(order + "iII", raw, 4)
    text = raw[16 : 16 + size]
    if size == 0 or len(text) != size or text[-1] != 0 or nanosec >= 10**9:
        return None
    try:
        frame = text[:-1].decode()
    except UnicodeDecodeError:
        return None
    return sec * 10**9 + nanosec, frame


def detections_msg(ts, labels: kitti.ObjectLabels, stamp: int, frame: str):
    """Predicted objects (labels with scores) as a PointCloud2 of ``DETECTION_FIELDS``."""
    rows = np.zeros(len(labels), _DETECTION_DTYPE)
    for axis, name in enumerate(("x", "y", "z")):
        rows[name] = labels.pos[:, axis]
    for axis, name in enumerate(("length", "width", "height")):
        rows[name] = labels.dims[:, axis]
    rows["yaw"] = labels.yaw
    rows["score"] = labels.scores if labels.scores is not None else 1.0
    rows["class_id"] = labels.classes
    field = ts.types["sensor_msgs/msg/PointField"]
    fields = [
        field(name=n, offset=4 * k, datatype=_INT32 if n == "class_id" else _FLOAT32, count=1)
        for k, n in enumerate(DETECTION_FIELDS)
    ]
    step = _DETECTION_DTYPE.itemsize
    return ts.types[POINTCLOUD2](
        header=header(ts, stamp, frame),
        height=1,
        width=len(rows),
        fields=fields,
        is_bigendian=False,
        point_step=step,
        row_step=step * len(rows),
        data=rows.view(np.uint8).reshape(-1),
        is_dense=True,
    )


def detections_to_labels(msg) -> kitti.ObjectLabels:
    """Inverse of ``detections_msg``."""
    names = tuple(f.name for f in msg.fields)
    if names != DETECTION_FIELDS or msg.point_step != _DETECTION_DTYPE.itemsize:
        raise ValueError(
            f"not a detections PointCloud2: fields {names}, expected {DETECTION_FIELDS}"
        )
    rows = np.frombuffer(bytes(msg.data), _DETECTION_DTYPE, count=int(msg.width))
    return kitti.ObjectLabels(
        classes=rows["class_id"],
        dims=np.stack([rows["length"], rows["width"], rows["height"]], 1),
        pos=np.stack([rows["x"], rows["y"], rows["z"]], 1),
        yaw=rows["yaw"],
        occlusion=np.zeros(len(rows)),
        scores=rows["score"],
    )


def footprint_corners(labels: kitti.ObjectLabels) -> np.ndarray:
    """float32 [M, 4, 2]: the xy corners of each box footprint, counter-clockwise."""
    return box_corners(labels.pos[:, :2], labels.dims[:, :2], labels.yaw)


def footprint_markers_msg(ts, labels: kitti.ObjectLabels, names, stamp: int, frame: str):
    """RViz markers: DELETEALL, then per object a footprint LINE_STRIP and a TEXT label."""
    t = ts.types
    mk = t["visualization_msgs/msg/Marker"]
    point = t["geometry_msgs/msg/Point"]
    hdr = header(ts, stamp, frame)
    markers = [marker(ts, hdr, "", 0, mk.CUBE, action=mk.DELETEALL)]
    corners = footprint_corners(labels)
    for k in range(len(labels)):
        cls = int(labels.classes[k])
        hue = cls / max(len(names), 1)
        colour = t["std_msgs/msg/ColorRGBA"](r=hue, g=1.0 - hue, b=0.5, a=1.0)
        z = float(labels.pos[k, 2] - labels.dims[k, 2] / 2)  # the outline lies on the floor
        ring = [point(float(x), float(y), z) for x, y in corners[k]]
        markers.append(
            marker(ts, hdr, "footprints", k, mk.LINE_STRIP, points=ring + ring[:1],
                    scale=t["geometry_msgs/msg/Vector3"](0.03, 0.0, 0.0), color=colour)
        )  # fmt: skip
        score = f" {float(labels.scores[k]):.2f}" if labels.scores is not None else ""
        top = point(float(labels.pos[k, 0]), float(labels.pos[k, 1]),
                    float(labels.pos[k, 2] + labels.dims[k, 2] / 2 + 0.2))  # fmt: skip
        markers.append(
            marker(ts, hdr, "labels", k, mk.TEXT_VIEW_FACING, text=f"{names[cls]}{score}",
                    pose=t["geometry_msgs/msg/Pose"](
                        position=top, orientation=t["geometry_msgs/msg/Quaternion"](0, 0, 0, 1.0)
                    ),
                    scale=t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.25), color=colour)
        )  # fmt: skip
    return t[MARKER_ARRAY](markers=markers)


def occupancy_msg(ts, occupied: np.ndarray | None, grid: GridConfig, stamp: int, frame: str):
    """An OccupancyGrid on the BEV grid: ``occupied`` bool [H, W] (row i along +y, column j
    along +x, as the grid and OccupancyGrid both lay them out) -> 100 / 0; None -> all -1."""
    t = ts.types
    h, w = grid.shape
    if occupied is None:
        data = np.full(h * w, -1, np.int8)
    else:
        if occupied.shape != (h, w):
            raise ValueError(f"occupied: expected shape {(h, w)}, got {occupied.shape}")
        data = np.where(occupied, 100, 0).astype(np.int8).reshape(-1)
    hdr = header(ts, stamp, frame)
    origin = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](float(grid.x_range[0]), float(grid.y_range[0]), 0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.0, 1.0),
    )
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=hdr.stamp,
        resolution=float(grid.cell_size),
        width=w,
        height=h,
        origin=origin,
    )
    return t[OCCUPANCY_GRID](header=hdr, info=info, data=data)


def occupancy_to_array(msg) -> np.ndarray:
    """int8 [H, W] cells of an OccupancyGrid."""
    return np.asarray(msg.data, np.int8).reshape(msg.info.height, msg.info.width)
