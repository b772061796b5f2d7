"""Live ROS 2 nodes: message builders, bad input, and the sim -> detect loop over loopback."""

import argparse
import contextlib
import dataclasses
import importlib.util
import math
import os
import queue
import re
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
import types

import jax
import numpy as np
import pytest

from indoorbev_jax import predict as P
from indoorbev_jax.config import VIEWS, Config, GridConfig, InferenceConfig
from indoorbev_jax.data import kitti
from indoorbev_jax.ros2 import RosUnavailable, require_rclpy
from indoorbev_jax.ros2 import messages as M
from indoorbev_jax.ros2.detect import OUTPUTS, Detector, speed_hint
from indoorbev_jax.ros2.record import BagRecorder, ensure_new, read_bag
from indoorbev_jax.rosbag import (
    MARKER_ARRAY,
    POINTCLOUD2,
    cloud_msg,
    header,
    pointcloud2_to_points,
    typestore,
)
from indoorbev_jax.train import init_state

# Thresholds at 0 so that an untrained model still yields objects to publish.
CFG = dataclasses.replace(
    Config.tiny(), inference=InferenceConfig(score_threshold=0.0, overlap_threshold=0.0)
)
TS = typestore()


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    params = init_state(CFG, jax.random.key(0)).params
    path = P.export_model(params, CFG, tmp_path_factory.mktemp("model") / "tiny.msgpack")
    return path, params


@pytest.fixture(scope="module")
def detector(model):
    return Detector(CFG, model[1], TS)


def _scan(n=300, seed=0):
    """n uniform points inside the tiny grid, with intensity."""
    rng = np.random.default_rng(seed)
    return rng.uniform([-4, -4, -0.5, 0], [4, 4, 1.5, 1], (n, 4)).astype(np.float32)


def _raw_cloud(points, stamp=5 * 10**9 + 7, frame="test_lidar"):
    return bytes(TS.serialize_cdr(cloud_msg(TS, points, stamp, frame), POINTCLOUD2))


def _canonical(raw, msgtype):
    """CDR bytes as rosbags writes them, without the padding a middleware may append."""
    return bytes(TS.serialize_cdr(TS.deserialize_cdr(raw, msgtype), msgtype))


def _decode(result):
    return {k: TS.deserialize_cdr(result.outputs[k], OUTPUTS[k]) for k in OUTPUTS}


def _two_detections():
    """(labels, the detections message of them, as a subscriber receives it); scores a
    float32 field holds exactly."""
    labels = kitti.ObjectLabels(
        classes=[1, 6], dims=[[2.0, 1.0, 0.8], [0.5, 0.5, 1.7]], pos=[[1.0, 2.0, 0.4],
        [-1.0, 0.5, 0.85]], yaw=[math.pi / 2, 0.3], occlusion=[0, 0], scores=[0.5, 0.25],
    )  # fmt: skip
    raw = TS.serialize_cdr(M.detections_msg(TS, labels, 123, "base"), POINTCLOUD2)
    return labels, TS.deserialize_cdr(raw, POINTCLOUD2)


def test_detection_messages_round_trip():
    labels, msg = _two_detections()
    assert (msg.header.frame_id, M.stamp_ns(msg), msg.width) == ("base", 123, 2)
    back = M.detections_to_labels(msg)
    for name in ("classes", "dims", "pos", "yaw", "scores"):
        np.testing.assert_array_equal(getattr(back, name), getattr(labels, name))
    # A 2 x 1 box turned by 90 degrees at (1, 2): corners at (1 -+ 0.5, 2 +- 1).
    corners = M.footprint_corners(labels)[0]
    np.testing.assert_allclose(corners, [[0.5, 3], [0.5, 1], [1.5, 1], [1.5, 3]], atol=1e-6)
    markers = M.footprint_markers_msg(TS, labels, CFG.data.class_names, 123, "base").markers
    marker = TS.types["visualization_msgs/msg/Marker"]
    assert markers[0].action == marker.DELETEALL and len(markers) == 1 + 2 * 2
    strip = markers[1]
    assert (strip.ns, strip.type, len(strip.points)) == ("footprints", marker.LINE_STRIP, 5)
    assert (strip.points[0].x, strip.points[0].y) == (strip.points[4].x, strip.points[4].y)
    assert strip.points[0].z == pytest.approx(0.0)  # the floor under the box
    assert markers[2].text == "Chair 0.50" and markers[4].text == "Person 0.25"
    # RViz keys markers by (ns, id): id = object index (else each replaces the last); each
    # label floats 0.2 m over its box's top. A mutation audit: ids all 0 passed.
    assert [(m.ns, m.id) for m in markers[1:]] == [
        ("footprints", 0), ("labels", 0), ("footprints", 1), ("labels", 1)
    ]  # fmt: skip
    tops = labels.pos[:, 2] + labels.dims[:, 2] / 2 + 0.2
    np.testing.assert_allclose([markers[2].pose.position.z, markers[4].pose.position.z], tops)


def test_detections_read_with_their_declared_fields():
    """A ROS client (``sensor_msgs_py.point_cloud2.read_points``, docs/ROBOT.md) reads each
    field at its declared offset with its declared datatype, not with our own dtype as
    ``detections_to_labels`` does: decoding with a numpy dtype built from ``msg.fields``
    alone must give back the labels, and the row must be ``point_step * width`` long."""
    labels, msg = _two_detections()
    # sensor_msgs/PointField datatype constants: INT32 = 5, FLOAT32 = 7.
    formats = {5: "<i4", 7: "<f4"}
    assert not msg.is_bigendian and msg.height == 1
    assert msg.row_step == msg.point_step * msg.width == len(msg.data)
    dt = np.dtype({
        "names": [f.name for f in msg.fields],
        "formats": [formats[f.datatype] for f in msg.fields],
        "offsets": [f.offset for f in msg.fields],
        "itemsize": msg.point_step,
    })  # fmt: skip
    assert all(f.count == 1 for f in msg.fields)
    assert dt.fields["class_id"][0] == np.dtype("<i4")
    rows = np.frombuffer(bytes(msg.data), dt, count=msg.width)
    np.testing.assert_array_equal(rows["class_id"], [1, 6])
    np.testing.assert_array_equal(np.stack([rows[n] for n in "xyz"], 1), np.float32(labels.pos))
    dims = np.stack([rows[n] for n in ("length", "width", "height")], 1)
    np.testing.assert_array_equal(dims, np.float32(labels.dims))
    np.testing.assert_array_equal(rows["yaw"], np.float32(labels.yaw))
    np.testing.assert_array_equal(rows["score"], np.float32(labels.scores))


def test_occupancy_grid_on_a_rectangular_off_centre_grid():
    """On a non-square grid that starts at the sensor (a forward-looking grid, allowed by
    DESIGN 2), width must count the x cells, height the y cells and the origin must be the
    (x_range[0], y_range[0]) corner: a ROS client then finds an occupied cell at the
    grid's own cell centre (GridConfig docstring). A square grid centred on the sensor
    cannot tell x from y."""
    grid = GridConfig(x_range=(0.0, 4.0), y_range=(-1.0, 1.0), cell_size=0.5)
    assert grid.shape == (4, 8)
    occupied = np.zeros(grid.shape, bool)
    occupied[1, 6] = True  # centre (0 + 6.5 * 0.5, -1 + 1.5 * 0.5) = (3.25, -0.25)
    msg = M.occupancy_msg(TS, occupied, grid, 42, "base")
    info = msg.info
    assert (info.width, info.height, info.resolution) == (8, 4, 0.5)
    assert (info.origin.position.x, info.origin.position.y) == (0.0, -1.0)
    (k,) = np.flatnonzero(msg.data)
    r, c = divmod(int(k), info.width)
    centre = (
        info.origin.position.x + (c + 0.5) * info.resolution,
        info.origin.position.y + (r + 0.5) * info.resolution,
    )
    assert centre == (3.25, -0.25)


def test_cloud_is_dense_only_without_invalid_points():
    """PointCloud2's is_dense: "True if there are no invalid points". predict --bag-out
    passes an organised cloud's NaN returns on, and every cloud was marked dense, so a
    consumer trusting the flag (PCL) skipped its NaN check (a mutation audit)."""
    points = _scan(20)
    assert cloud_msg(TS, points, 1, "lidar").is_dense is True
    holes = points.copy()
    holes[3, 1] = np.nan
    msg = TS.deserialize_cdr(bytes(TS.serialize_cdr(cloud_msg(TS, holes, 1), POINTCLOUD2)),
                             POINTCLOUD2)  # fmt: skip
    assert msg.is_dense is False
    np.testing.assert_array_equal(pointcloud2_to_points(msg), holes)
    for empty in (np.zeros((0, 4), np.float32), np.zeros(0, np.float32)):  # no point invalid
        msg = cloud_msg(TS, empty, 1)
        assert msg.is_dense is True and msg.width == 0


def test_cloud_msg_layout_is_float32_xyzi_as_sensor_msgs_defines_it():
    """The bytes a ROS client reads: fields x, y, z, intensity at offsets 0, 4, 8, 12 as
    PointField.FLOAT32 (7), little-endian, 16 bytes a point, one row of the points as given
    (checked against the message definition's constant, not our reader)."""
    points = _scan(20)
    msg = cloud_msg(TS, points, 1, "lidar")
    float32 = TS.types["sensor_msgs/msg/PointField"].FLOAT32
    assert float32 == 7
    fields = [(f.name, f.offset, f.datatype, f.count) for f in msg.fields]
    assert fields == [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 7, 1)]
    assert (msg.is_bigendian, msg.point_step, msg.height, msg.width) == (False, 16, 1, 20)
    assert msg.row_step == 16 * 20 and bytes(msg.data) == points.astype("<f4").tobytes()


def test_occupancy_grid_layout():
    grid = CFG.grid
    h, w = grid.shape
    occupied = np.zeros((h, w), bool)
    occupied[3, 7] = True  # row 3 along +y, column 7 along +x
    msg = M.occupancy_msg(TS, occupied, grid, 42, "base")
    assert (msg.info.width, msg.info.height, msg.info.resolution) == (w, h, grid.cell_size)
    o = msg.info.origin.position
    assert (o.x, o.y) == (grid.x_range[0], grid.y_range[0])
    # OccupancyGrid cell (row r, column c) is data[r * width + c], centred at
    # origin + ((c + 0.5), (r + 0.5)) * resolution: the grid's cell centre.
    assert np.flatnonzero(msg.data).tolist() == [3 * w + 7] and msg.data[3 * w + 7] == 100
    np.testing.assert_array_equal(M.occupancy_to_array(msg), np.where(occupied, 100, 0))
    unknown = M.occupancy_msg(TS, None, grid, 42, "base")
    assert set(np.unique(unknown.data)) == {-1}
    with pytest.raises(ValueError, match=r"occupied: expected shape \(40, 40\)"):
        M.occupancy_msg(TS, occupied[:3], grid, 42, "base")


def test_detector_matches_predictor(detector):
    points = _scan()
    result = detector.process(_raw_cloud(points))
    assert result.warning is None and result.infer_ms > 0
    _, _, final, output, _ = detector.predictor(points)
    labels, ids = P.to_labels(final, output, "mask", detector.config.grid)  # the default
    assert len(labels) > 0
    msgs = _decode(result)
    for m in (msgs["detections"], msgs["occupancy"], *msgs["markers"].markers):
        assert (m.header.frame_id, M.stamp_ns(m)) == ("test_lidar", 5 * 10**9 + 7)
    got = M.detections_to_labels(msgs["detections"])
    np.testing.assert_array_equal(got.classes, labels.classes)
    np.testing.assert_array_equal(got.pos, labels.pos)
    np.testing.assert_array_equal(got.dims, labels.dims)
    np.testing.assert_array_equal(got.yaw, labels.yaw)
    np.testing.assert_array_equal(M.occupancy_to_array(msgs["occupancy"]) == 100, ids > 0)
    assert len(msgs["markers"].markers) == 1 + 2 * len(labels)


def _assert_empty(result, frame="test_lidar"):
    msgs = _decode(result)
    assert msgs["detections"].width == 0 and msgs["detections"].header.frame_id == frame
    assert [m.action for m in msgs["markers"].markers] == [3]  # DELETEALL only
    assert set(np.unique(msgs["occupancy"].data)) == {-1}
    assert result.infer_ms == 0.0 and len(result.labels) == 0


def test_detector_bad_input(detector):
    # No z field.
    pf = TS.types["sensor_msgs/msg/PointField"]
    xy = np.zeros((4, 2), "<f4")
    no_z = TS.types[POINTCLOUD2](
        header=header(TS, 10**9, "test_lidar"), height=1, width=4,
        fields=[pf(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xy")],
        is_bigendian=False, point_step=8, row_step=32, data=xy.view(np.uint8).reshape(-1),
        is_dense=True,
    )  # fmt: skip
    result = detector.process(bytes(TS.serialize_cdr(no_z, POINTCLOUD2)))
    assert "lacks field(s) ['z']" in result.warning and "test_lidar" in result.warning
    _assert_empty(result)
    # point_step 0 and a 2^64-point header in 113 bytes: a warning, not a failed worker.
    zero = TS.types[POINTCLOUD2](
        header=header(TS, 10**9, "test_lidar"), height=2**32 - 1, width=2**32 - 1,
        fields=[pf(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")],
        is_bigendian=False, point_step=0, row_step=0, data=np.zeros(0, np.uint8),
        is_dense=True,
    )  # fmt: skip
    result = detector.process(bytes(TS.serialize_cdr(zero, POINTCLOUD2)))
    assert "field 'x' (4 bytes at offset 0) runs past point_step 0" in result.warning
    _assert_empty(result)
    # Empty cloud, all-NaN cloud, bytes that are no PointCloud2.
    result = detector.process(_raw_cloud(np.zeros((0, 4), np.float32)))
    assert "empty; 0 points" in result.warning
    _assert_empty(result)
    result = detector.process(_raw_cloud(np.full((50, 4), np.nan, np.float32)))
    assert "50 of 50 points are not finite; cloud skipped" in result.warning
    _assert_empty(result)
    result = detector.process(b"\x00\x01\x00\x00garbage")
    assert result.warning.startswith("cannot decode the PointCloud2")
    assert "nothing published" in result.warning and result.outputs == {}
    # A cloud cut short: its header still places the empty outputs.
    raw = _raw_cloud(_scan(20), stamp=3 * 10**9 + 11, frame="cut_lidar")
    assert M.header_from_cdr(raw) == (3 * 10**9 + 11, "cut_lidar")
    result = detector.process(raw[:-100])
    assert result.warning.startswith("cloud 'cut_lidar' @ 3.000s: cannot decode the PointCloud2")
    _assert_empty(result, frame="cut_lidar")
    msgs = _decode(result)
    headers = [
        msgs["detections"].header,
        msgs["occupancy"].header,
        msgs["markers"].markers[0].header,
    ]
    assert {M.stamp_ns(argparse.Namespace(header=h)) for h in headers} == {3 * 10**9 + 11}
    # Some NaN rows: by default the cloud gets a warning and empty outputs; with
    # skip_nonfinite (organized clouds mark missing returns so) those points are skipped and
    # the outputs equal those of the clean cloud.
    clean = _scan()
    dirty = np.concatenate([clean[:100], np.full((3, 4), np.nan, np.float32), clean[100:]])
    result = detector.process(_raw_cloud(dirty))
    assert "3 of 303 points are not finite; cloud skipped" in result.warning
    _assert_empty(result)
    detector.skip_nonfinite = True
    try:
        result = detector.process(_raw_cloud(dirty))
    finally:
        detector.skip_nonfinite = False
    assert "3 of 303 points are not finite (those points are skipped)" in result.warning
    assert result.outputs == detector.process(_raw_cloud(clean)).outputs


def test_detector_reads_a_huge_row_step_without_allocating_it(detector):
    # A 1-row cloud may declare any row_step (the last row needs no padding): a 300-byte
    # message with row_step 2**32 - 1 must not make the reader allocate 4 GiB (a MemoryError
    # on a robot computer with little memory, which would stop the node's worker).
    import tracemalloc

    points = _scan(10)
    msg = TS.deserialize_cdr(_raw_cloud(points), POINTCLOUD2)
    msg.row_step = 2**32 - 1
    raw = bytes(TS.serialize_cdr(msg, POINTCLOUD2))
    tracemalloc.start()
    try:
        result = detector.process(raw)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20, f"reading the cloud allocated {peak / 2**20:.0f} MiB"
    assert result.outputs == detector.process(_raw_cloud(points)).outputs
    # Padded rows of an organized cloud are still skipped as laid out.
    rows = np.zeros((2, 5 * 16 + 8), np.uint8)
    rows[:, : 5 * 16] = points.astype("<f4").view(np.uint8).reshape(2, 5 * 16)
    msg.height, msg.width, msg.row_step = 2, 5, 5 * 16 + 8
    msg.data = rows.reshape(-1)[:-8]  # the last row's padding may be left out
    np.testing.assert_array_equal(pointcloud2_to_points(msg), points)


def test_recorder_round_trip_and_missing_rclpy(tmp_path, monkeypatch):
    raw = _raw_cloud(_scan(20))
    for storage in ("sqlite3", "mcap"):
        bag = tmp_path / storage
        rec = BagRecorder(bag, {"/a": POINTCLOUD2}, TS, storage)
        assert (tmp_path / f"{storage}.partial").is_dir() and not bag.exists()
        rec.write("/a", 2, raw)
        rec.write("/a", 3, raw[:-4] + b"abcd")
        assert rec.close() == bag and rec.counts == {"/a": 2}
        assert read_bag(bag) == {"/a": [(2, raw), (3, raw[:-4] + b"abcd")]}
    with pytest.raises(FileExistsError, match="already exists"):
        BagRecorder(tmp_path / "mcap", {"/a": POINTCLOUD2}, TS)
    # What an interrupted recording left is the user's: never silently deleted.
    left = tmp_path / "cut.partial" / "cut" / "cut_0.mcap"
    left.parent.mkdir(parents=True)
    left.write_bytes(b"recorded")
    with pytest.raises(FileExistsError, match=r"cut\.partial: left by an interrupted recording"):
        BagRecorder(tmp_path / "cut", {"/a": POINTCLOUD2}, TS, "mcap")
    assert left.read_bytes() == b"recorded" and not (tmp_path / "cut").exists()
    # A folder that cannot be made is found before anything (a node's warm-up) starts.
    (tmp_path / "afile").write_text("")
    with pytest.raises(OSError, match=r"afile/bag: cannot record here"):
        ensure_new(tmp_path / "afile" / "bag")
    # A writer failure (mcap refuses a negative time) is close's error, not a thread's
    # traceback from the writer's own close.
    hook_calls = []
    monkeypatch.setattr(threading, "excepthook", hook_calls.append)
    rec = BagRecorder(tmp_path / "neg", {"/a": POINTCLOUD2}, TS, "mcap")
    rec.write("/a", -5, raw)
    with pytest.raises(RuntimeError, match="neg: recording failed"):
        rec.close()
    assert hook_calls == []
    # A recorder that cannot open leaves nothing behind either.
    with pytest.raises(RuntimeError, match="recording failed"):
        BagRecorder(tmp_path / "bad", {"/a": "no_pkg/msg/NoSuchType"}, TS)
    assert not (tmp_path / "bad.partial").exists()
    monkeypatch.setitem(sys.modules, "rclpy", None)  # as if the ros extra were missing
    with pytest.raises(RosUnavailable, match=r"pip install -e \.\[ros\]"):
        require_rclpy()


# ---------------------------------------------------------------- the live loop (rclpy)

FRAMES = 5


class _Lines:
    """Collects a subprocess's stdout lines on a thread."""

    def __init__(self, proc):
        self.lines: queue.Queue = queue.Queue()
        self.all: list[str] = []
        threading.Thread(target=self._read, args=(proc,), daemon=True).start()

    def _read(self, proc):
        for line in proc.stdout:
            self.all.append(line)
            self.lines.put(line)

    def wait_for(self, text, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.5)
            except queue.Empty:
                continue
            if text in line:
                return line
        raise AssertionError(f"no line with '{text}' within {timeout} s; got {self.all}")


def test_a_closed_recording_leaves_no_partial_folder(tmp_path):
    """close() moves the bag out of <bag>.partial/ and removes that folder: a finished
    recording leaves only the bag, and after the bag is removed the same path can be
    recorded again. Guards against leaving the emptied .partial folder, which the next
    recording to that path refuses as "left by an interrupted recording"."""
    raw = _raw_cloud(_scan(20))
    for _ in range(2):
        rec = BagRecorder(tmp_path / "bag", {"/a": POINTCLOUD2}, TS, "mcap")
        rec.write("/a", 2, raw)
        assert rec.close() == tmp_path / "bag"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]
        shutil.rmtree(tmp_path / "bag")


def test_a_writer_that_fails_to_close_is_reported_and_the_bag_left_partial(tmp_path, monkeypatch):
    """The writer's close flushes the mcap footer or commits sqlite: a full disk there must
    reach the caller, not move a truncated bag into place as if it were whole."""
    from rosbags.rosbag2 import Writer

    close = Writer.close

    def full_disk(self):
        close(self)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Writer, "close", full_disk)
    for storage in ("sqlite3", "mcap"):
        rec = BagRecorder(tmp_path / storage, {"/a": POINTCLOUD2}, TS, storage)
        rec.write("/a", 2, _raw_cloud(_scan(20)))
        said = (
            rf"{storage}: recording failed: .*No space left.* into {re.escape(str(rec.partial))}$"
        )
        with pytest.raises(RuntimeError, match=said):  # names where the bag is kept
            rec.close()
        assert rec.partial.is_dir() and not (tmp_path / storage).exists()


def test_sim_to_detect_loop(model, tmp_path, monkeypatch):
    pytest.importorskip("rclpy", reason="the ros extra is not installed (pip install -e .[ros])")
    from rclpy.serialization import deserialize_message
    from rclpy.signals import SignalHandlerOptions

    from indoorbev_jax.ros2 import runtime

    # Loopback discovery, Fast DDS, and a domain of our own against crosstalk.
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    # 1..100: domains above 101 reach into Linux ephemeral ports.
    monkeypatch.setenv("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    model_path = model[0]
    sim_bag, det_bag = tmp_path / "sim_bag", tmp_path / "det_bag"
    outs = {k: f"/indoorbev/{k}" for k in OUTPUTS}
    topics = {"/lidar/points": POINTCLOUD2, "/lidar/objects": MARKER_ARRAY}
    topics |= {outs[k]: OUTPUTS[k] for k in OUTPUTS}

    import rclpy
    import rclpy.executors

    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("indoorbev_test", context=context)
    received: dict[str, list[bytes]] = {t: [] for t in topics}
    for t, msgtype in topics.items():
        node.create_subscription(runtime.msg_class(msgtype), t,
                                 lambda raw, t=t: received[t].append(raw),
                                 runtime.qos(True, 50), raw=True)  # fmt: skip
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    procs = []
    try:
        cmd = [sys.executable, "-m"]
        det = subprocess.Popen(
            [*cmd, "indoorbev_jax.cli", "ros2", "detect", "--checkpoint", str(model_path),
             "--topic", "/lidar/points", "--reliable", "--record", str(det_bag)],
            stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        procs.append(det)
        det_out = _Lines(det)
        det_out.wait_for("ready", timeout=240)  # the model compiles first
        # The sim waits for both subscribers of its points: the detect node and this test.
        sim = subprocess.Popen(
            [*cmd, "indoorbev_sim.cli", "ros2", "publish", "--preset", "tiny", "--rate", "2",
             "--frames", str(FRAMES), "--frame-id", "test_lidar", "--record", str(sim_bag),
             "--wait-subscribers", "2", "--wait-timeout", "120", "--cache", ""],
            stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        procs.append(sim)
        sim_out = _Lines(sim)
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and len(received[outs["occupancy"]]) < FRAMES:
            executor.spin_once(timeout_sec=0.1)
            if sim.poll() is not None:  # all published: outputs follow within seconds
                deadline = min(deadline, time.monotonic() + 10)
        assert sim.wait(timeout=30) == 0, sim_out.all
        for _ in range(10):  # anything still in flight
            executor.spin_once(timeout_sec=0.05)
        det.send_signal(signal.SIGTERM)
        assert det.wait(timeout=60) == 0, det_out.all
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()

    # Every published frame got its detections, markers and grid, with its stamp and frame.
    clouds = [deserialize_message(r, runtime.msg_class(POINTCLOUD2)) for r in
              received["/lidar/points"]]  # fmt: skip
    assert len(clouds) == FRAMES, sim_out.all
    stamps = [M.stamp_ns(c) for c in clouds]
    for k in OUTPUTS:
        msgs = [deserialize_message(r, runtime.msg_class(OUTPUTS[k])) for r in received[outs[k]]]
        assert len(msgs) == FRAMES, (k, det_out.all)
        heads = [m.markers[0].header if k == "markers" else m.header for m in msgs]
        assert [h.frame_id for h in heads] == ["test_lidar"] * FRAMES
        assert [h.stamp.sec * 10**9 + h.stamp.nanosec for h in heads] == stamps
    grids = [deserialize_message(r, runtime.msg_class(M.OCCUPANCY_GRID))
             for r in received[outs["occupancy"]]]  # fmt: skip
    assert all((g.info.height, g.info.width) == CFG.grid.shape for g in grids)
    dets = [TS.deserialize_cdr(r, POINTCLOUD2) for r in received[outs["detections"]]]
    assert tuple(f.name for f in dets[0].fields) == M.DETECTION_FIELDS
    assert f'"processed": {FRAMES}' in det_out.wait_for("summary", timeout=5)

    # The bags hold exactly the messages that went over the wire, up to the alignment
    # padding that the middleware may append to CDR bytes (and the detect node records its
    # input as it received it).
    sim_rec, det_rec = read_bag(sim_bag), read_bag(det_bag)
    assert set(sim_rec) == {"/lidar/points", "/lidar/objects"}
    assert set(det_rec) == {"/lidar/points", *outs.values()}
    for rec in (sim_rec, det_rec):
        for t in rec:
            wire = [_canonical(raw, topics[t]) for raw in received[t]]
            assert [_canonical(raw, topics[t]) for _, raw in rec[t]] == wire, t
            assert [s for s, _ in rec[t]] == stamps, t

    # `indoorbev predict` reads the recorded bag and finds what the live node published.
    summary = P.predict(model_path, sim_bag, tmp_path / "pred", pictures=False, verbose=False)
    assert summary["frames"] == FRAMES
    for k, det_msg in enumerate(dets):
        live = M.detections_to_labels(det_msg)
        offline = kitti.read_labels(tmp_path / "pred" / "label_2" / f"{k:06d}.txt", CFG.data)
        np.testing.assert_array_equal(live.classes, offline.classes)
        np.testing.assert_allclose(live.pos, offline.pos, atol=1e-4)  # label text: 6 decimals
        np.testing.assert_allclose(live.scores, offline.scores, atol=1e-5)


def test_speed_hint_only_when_views_outpace_the_sensor(detector):
    assert detector.inference_ms() > 0  # the model ran on the dummy cloud
    assert speed_hint(250.0, ("identity",)) is None  # one view: nothing to trade
    assert speed_hint(90.0, ("identity", "mirror_y")) is None  # within 100 ms at 10 Hz
    assert speed_hint(100.0, ("identity", "mirror_y")) is None  # exactly keeps up
    assert speed_hint(100.5, ("identity", "mirror_y")).startswith("inference takes 100 ms")
    hint = speed_hint(216.6, tuple(VIEWS))
    assert hint.startswith("inference takes 217 ms per cloud with 8 test-time views")
    assert "--views identity" in hint
    assert speed_hint(216.6, tuple(VIEWS), sensor_hz=4.0) is None


# Names from the ROS 2 design article "Topic and Service name mapping to DDS", as rcl and
# rmw decide them once expanded (they allow "__", which the article once banned).
VALID_TOPICS = ["foo", "abc123", "_foo", "Foo", "BAR", "~", "foo/bar", "~/foo", "foo/_bar",
                "foo_/bar", "foo_", "/livox/lidar", "foo__bar", "{node}/x", "~/{node}_raw",
                "a" * 246]  # fmt: skip
INVALID_TOPICS = ["123abc", "123", "foo bar", "", "foo//bar", "/~", "~foo", "foo~", "foo~/bar",
                  "foo/~bar", "foo/~/bar", "foo/", "/", "foo/{bar", "foo}", "/a/2b", "/a-b",
                  "/{1}/x", "{foo}_bar", "foo/{ping}/bar", "a" * 247]  # fmt: skip


def test_topic_names_follow_the_ros2_rules():
    from indoorbev_jax.ros2 import check_topic_name, topic_name_problem

    assert [n for n in VALID_TOPICS if topic_name_problem(n) is not None] == []
    assert [n for n in INVALID_TOPICS if topic_name_problem(n) is None] == []
    with pytest.raises(ValueError, match="topic: '/a b' is not a valid ROS 2 topic name"):
        check_topic_name("/a b", "topic")
    try:  # where the ros extra is installed, rclpy's own checks agree
        from rclpy.exceptions import NameValidationException
        from rclpy.expand_topic_name import expand_topic_name
        from rclpy.validate_full_topic_name import validate_full_topic_name
        from rclpy.validate_topic_name import validate_topic_name
    except ImportError:
        return
    for name in VALID_TOPICS + INVALID_TOPICS:
        try:  # what create_publisher does with a name
            validate_topic_name(name)
            validate_full_topic_name(expand_topic_name(name, "indoorbev_detect", "/"))
            valid = True
        except (NameValidationException, ValueError):  # ValueError: unknown substitution
            valid = False
        assert valid == (name in VALID_TOPICS), name


def test_node_settings_fail_before_the_node_starts(monkeypatch, capsys):
    """Settings that rclpy would refuse only after the model's warm-up (or that would run
    silently wrong) are refused first, naming the setting; without rclpy even."""
    from indoorbev_sim.ros2 import publish

    from indoorbev_jax import cli
    from indoorbev_jax.ros2 import detect

    monkeypatch.setitem(sys.modules, "rclpy", None)
    for bad, match in [
        ({"topic": "/livox lidar"}, "topic: '/livox lidar' is not a valid"),
        ({"out_ns": "/1bev"}, "out_ns: '/1bev/detections' is not a valid"),
        ({"max_frames": -1}, "max_frames: expected a whole number >= 0"),
        ({"log_every": 0.0}, "log_every: expected seconds > 0"),
        ({"log_every": float("nan")}, "log_every: expected seconds > 0"),
        # The node fed on its own detections (a PointCloud2), ~800 messages/s.
        ({"topic": "/indoorbev/detections"}, "topic: '/indoorbev/detections' is one of the"),
        ({"topic": "/r/markers", "out_ns": "/r/"}, "topic: '/r/markers' is one of the node"),
    ]:
        with pytest.raises(ValueError, match=match):
            detect.run_detect_node("no-such-model", **bad)
    with pytest.raises(RosUnavailable):  # good settings get as far as rclpy
        detect.run_detect_node("no-such-model", topic="~/points", out_ns="bev")
    # --record "" (an unset shell variable) detected and recorded nothing, exit 0.
    with pytest.raises(ValueError, match="record: an empty path; expected a new folder"):
        ensure_new("")
    monkeypatch.delitem(sys.modules, "rclpy")  # the None set above
    if importlib.util.find_spec("rclpy") is not None:  # refused after require_rclpy
        with pytest.raises(ValueError, match="record: an empty path"):
            detect.run_detect_node("no-such-model", record="")
    # A trailing slash is no second one (a mutation audit: "/indoorbev/" refused passed).
    for ns, root in (("/indoorbev/", "/indoorbev"), ("/", ""), ("bev", "bev")):
        topics = detect.check_settings("/livox/lidar", ns, 5.0, 0)
        assert topics == {k: f"{root}/{k}" for k in OUTPUTS}
    for bad, match in [
        ({"frames": -1}, "frames: expected a whole number >= 0"),
        ({"topic": "points/"}, "topic: 'points/' is not a valid"),
        ({"objects_topic": "/2d"}, "objects_topic: '/2d' is not a valid"),
        ({"wait_subscribers": -2}, "wait_subscribers: expected a whole number >= 0"),
        ({"wait_timeout": float("inf")}, "wait_timeout: expected seconds > 0"),
        ({"wait_timeout": 0.0}, "wait_timeout: expected seconds > 0"),
        ({"rate": 0.0}, "rate: expected frames per second > 0"),  # a ZeroDivisionError
        ({"topic": "/same", "objects_topic": "/same"}, "objects_topic: '/same' is the clouds'"),
    ]:
        with pytest.raises(ValueError, match=match):
            publish(CFG, **bad)
    # The command lines refuse the same before anything loads.
    for argv, flag in [
        (["ros2", "detect", "--checkpoint", "m", "--max-frames", "-1"], "--max-frames"),
        (["ros2", "detect", "--checkpoint", "m", "--log-every", "0"], "--log-every"),
    ]:
        with pytest.raises(SystemExit):
            cli.main(argv)
        assert f"argument {flag}: must be" in capsys.readouterr().err

    # Ctrl-C before the node runs (the warm-up takes seconds) exits quietly with 130.
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(detect, "run_detect_node", interrupted)
    assert cli.main(["ros2", "detect", "--checkpoint", "m"]) == 130
    assert capsys.readouterr().err == "indoorbev ros2 detect: interrupted\n"
    # Every flag reaches the node as given (a mutation audit: --max-frames dropped passed).
    seen = {}
    monkeypatch.setattr(detect, "run_detect_node", lambda checkpoint, **kw: seen.update(kw))
    argv = ["ros2", "detect", "--checkpoint", "m", "--topic", "/in", "--out-ns", "/o",
            "--reliable", "--record", "bag", "--storage", "mcap", "--log-every", "2.5",
            "--skip-nonfinite", "--max-frames", "3", "--intensity", "unit", "--views",
            "identity,mirror_x", "--boxes", "head", "--lidar-rpy", "0,20,0", "--lidar-height",
            "0.5", "--level-frame", "lvl", "--ros-args", "-r", "a:=b"]  # fmt: skip
    assert cli.main(argv) == 0
    mount = seen.pop("mount")
    assert (mount.roll, mount.pitch, mount.yaw, mount.height) == (0.0, 20.0, 0.0, 0.5)
    assert seen == {"topic": "/in", "out_ns": "/o", "reliable": True, "record": "bag",
                    "storage": "mcap", "log_every": 2.5, "max_frames": 3,
                    "ros_args": ["-r", "a:=b"], "skip_nonfinite": True, "intensity": "unit",
                    "views": ("identity", "mirror_x"), "boxes": "head",
                    "level_frame": "lvl"}  # fmt: skip


def test_shutdown_work_holds_a_second_ctrl_c(capsys):
    """Closing a recording must not be cut short by an impatient Ctrl-C: rosbags commits
    a sqlite3 bag only when it is closed."""
    from indoorbev_jax.ros2 import runtime
    from indoorbev_jax.ros2.runtime import signals_held

    before = signal.getsignal(signal.SIGINT)
    # As the node runs: SIGTERM interrupts as Ctrl-C does (a service manager's stop).
    term = signal.signal(signal.SIGTERM, runtime._interrupt)
    try:
        steps = []
        try:
            with signals_held("finishing the recording"):
                for signum in (signal.SIGINT, signal.SIGTERM):
                    os.kill(os.getpid(), signum)
                    time.sleep(0.2)  # the handler runs in the main thread between bytecodes
                steps.append("closed")
        except KeyboardInterrupt as e:  # as pytest would take it: the user's
            pytest.fail(f"the held block was interrupted: {e!r}")
        assert steps == ["closed"]
        assert capsys.readouterr().err == "finishing the recording\n" * 2
        assert signal.getsignal(signal.SIGINT) is before
        assert signal.getsignal(signal.SIGTERM) is runtime._interrupt
    finally:
        signal.signal(signal.SIGTERM, term)


def test_silence_hint_names_the_likely_qos_cause():
    from indoorbev_jax.ros2.detect import silence_hint

    assert silence_hint(3, 1, "/livox/lidar", False) is None  # clouds arrive
    assert silence_hint(0, 0, "/livox/lidar", False) is None  # nobody publishes yet
    hint = silence_hint(0, 2, "/livox/lidar", False)
    assert hint.startswith("/livox/lidar: 2 publisher(s) but no cloud arrived in 5 s")
    assert "best-effort" in hint and "--reliable" in hint
    assert "needs a reliable publisher" in silence_hint(0, 1, "/livox/lidar", True)
    assert "needs a reliable publisher" in silence_hint(0, 1, "/livox/lidar", True, 0)
    # A reliable publisher that is idle (a driver still starting): QoS is not the cause.
    idle = silence_hint(0, 2, "/livox/lidar", True, 1)
    assert idle.endswith("1 of them reliable, so QoS is not the cause: they have sent nothing yet")
    # A publisher of another type (a Livox driver on xfer_format 1) is named, not QoS blamed.
    for reliable in (False, True):
        other = silence_hint(0, 0, "/livox/lidar", reliable, 0, ["livox_ros_driver2/msg/CustomMsg"])
        assert other == (
            "/livox/lidar: published as livox_ros_driver2/msg/CustomMsg, not "
            "sensor_msgs/msg/PointCloud2, which is what the node reads (the Livox driver "
            "publishes PointCloud2 with xfer_format 0)"
        )
    assert silence_hint(3, 0, "/livox/lidar", False, 0, ["sensor_msgs/msg/LaserScan"]) is None
    mixed = silence_hint(0, 1, "/livox/lidar", False, 0, ["sensor_msgs/msg/LaserScan"])
    assert "best-effort" in mixed  # a PointCloud2 publisher too: QoS is still the likely cause


def test_silence_is_explained_until_the_first_cloud_each_reason_once():
    """The node checked once, 5 s after it was ready: a publisher of another type or a
    driver that came up later was never named. Now every 5 s until a cloud arrives, each
    new reason once."""
    from indoorbev_jax.ros2.detect import SILENCE_S, SilenceWatch

    asked = []

    def hint(text):
        return lambda: asked.append(text) or text

    watch = SilenceWatch(100.0)
    assert watch.due(100.0 + SILENCE_S - 0.1, 0, hint("early")) is None and asked == []
    assert watch.due(100.0 + SILENCE_S, 0, hint(None)) is None  # nobody publishes yet
    assert watch.due(100.0 + SILENCE_S + 1, 0, hint("x")) is None and asked == [None]
    assert watch.due(100.0 + 2 * SILENCE_S, 0, hint("other type")) == "other type"
    assert watch.due(100.0 + 3 * SILENCE_S, 0, hint("other type")) is None  # said already
    assert watch.due(100.0 + 4 * SILENCE_S, 0, hint("best effort")) == "best effort"
    assert watch.due(100.0 + 5 * SILENCE_S, 0, hint("other type")) == "other type"
    assert watch.due(100.0 + 6 * SILENCE_S, 3, hint("late")) is None  # clouds arrive
    assert asked == [None, "other type", "other type", "best effort", "other type"]


def test_silence_hint_reads_the_graph_and_never_raises():
    """The node's hint reads the topic's publishers off the graph: their types and the QoS
    they offer; a graph query that fails gives no hint rather than stopping the node."""
    import types

    from indoorbev_jax.ros2.detect import _silence_hint, silence_hint

    def info(kind, reliability):
        qos = types.SimpleNamespace(reliability=types.SimpleNamespace(name=reliability))
        return types.SimpleNamespace(topic_type=kind, qos_profile=qos)

    graph = [info("sensor_msgs/msg/PointCloud2", "RELIABLE"),
             info("sensor_msgs/msg/PointCloud2", "BEST_EFFORT"),
             info("livox_ros_driver2/msg/CustomMsg", "RELIABLE")]  # fmt: skip
    asked = []
    node = types.SimpleNamespace(get_publishers_info_by_topic=lambda t: asked.append(t) or graph)
    got = _silence_hint(node, "/ns/livox/lidar", 0, "/livox/lidar", True)
    assert asked == ["/ns/livox/lidar"]
    assert got == silence_hint(0, 2, "/livox/lidar", True, 1, ["livox_ros_driver2/msg/CustomMsg"])
    assert "1 of them reliable, so QoS is not the cause" in got

    def broken(topic):
        raise RuntimeError("graph unavailable")

    gone = types.SimpleNamespace(get_publishers_info_by_topic=broken)
    assert _silence_hint(gone, "/livox/lidar", 0, "/livox/lidar", False) is None


def test_bag_log_time_is_never_negative():
    """mcap refuses a negative log time: a pre-1970 stamp ended the recording."""
    from indoorbev_jax.ros2.detect import bag_log_ns

    assert bag_log_ns(1_700_000_000_000_000_000, 5) == 1_700_000_000_000_000_000
    assert bag_log_ns(0, 5) == 5 and bag_log_ns(-5_000_000_000, 5) == 5


def test_console_scripts_exit_130_on_ctrl_c(monkeypatch, capsys):
    """Ctrl-C gives one line and status 130, leaving at once (os._exit): a normal shutdown
    while XLA still compiles on its threads crashed the interpreter."""
    from indoorbev_jax import cli

    exits = []

    def fake_exit(status):
        exits.append(status)
        raise SystemExit(status)

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.os, "_exit", fake_exit)
    with pytest.raises(SystemExit):
        cli.exit_with(interrupted, "indoorbev")
    assert exits == [130] and capsys.readouterr().err == "indoorbev: interrupted\n"
    with pytest.raises(SystemExit) as done:  # other statuses exit normally
        cli.exit_with(lambda: 2, "indoorbev")
    assert done.value.code == 2 and exits == [130]


def test_a_ctrl_c_python_dropped_still_stops_the_command():
    """A KeyboardInterrupt raised inside a garbage-collector callback (JAX has one) is
    printed as "Exception ignored" and dropped: `dataset check` then ran to its end, status
    0. exit_with's unraisable hook delivers it again, quietly, and the command stops."""
    code = (
        "import signal, sys, time, types\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "from indoorbev_jax.cli import exit_with\n"
        "def main():\n"
        "    dropped = types.SimpleNamespace(exc_type=KeyboardInterrupt, exc_traceback=None,\n"
        "        exc_value=KeyboardInterrupt(), err_msg=None, object=None)\n"
        "    sys.unraisablehook(dropped)  # what Python does with it in a GC callback\n"
        "    for _ in range(300):\n"
        "        time.sleep(0.01)\n"
        "    print('ran to the end')\n"
        "    return 0\n"
        "exit_with(main, 'probe')\n"
    )
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, env=env)  # fmt: skip
    assert (done.returncode, done.stdout, done.stderr) == (130, "", "probe: interrupted\n")


def test_catch_interrupts_leaves_an_ignored_sigint_and_raises_a_ctrl_c_once(monkeypatch):
    """A job started in the background by a non-interactive shell ignores SIGINT: the
    terminal's Ctrl-C is not for it, and catch_interrupts keeps it so. A dropped Ctrl-C that
    was delivered again and raised is not raised a second time by check_interrupted."""
    import types

    from indoorbev_jax import interrupts

    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # restored after
    saved = signal.getsignal(signal.SIGINT)
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        hook = sys.unraisablehook
        interrupts.catch_interrupts()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN and sys.unraisablehook is hook
        signal.signal(signal.SIGINT, signal.default_int_handler)
        interrupts.catch_interrupts()
        assert signal.getsignal(signal.SIGINT) is interrupts._remember_sigint
    finally:
        signal.signal(signal.SIGINT, saved)
    dropped = interrupts._quiet_dropped_interrupts(lambda unraisable: None, lambda: None)
    dropped(types.SimpleNamespace(exc_value=KeyboardInterrupt()))
    assert interrupts.SIGINT_DROPPED.is_set()
    with pytest.raises(KeyboardInterrupt):  # delivered again: the handler raises it
        interrupts._remember_sigint(signal.SIGINT, None)
    try:
        interrupts.check_interrupted()  # nothing is left to raise
    except KeyboardInterrupt:
        pytest.fail("check_interrupted raised the Ctrl-C that was raised already")
    finally:
        interrupts.SIGINT_SEEN.clear()


def test_unknown_ros_args_fail_first_in_one_line(capsys):
    """An argument after --ros-args that rclpy does not take is named before the model
    loads (it used to end in rclpy's traceback after the warm-up, status 1)."""
    pytest.importorskip("rclpy")
    from indoorbev_jax import cli

    argv = ["ros2", "detect", "--checkpoint", "no-such-model", "--ros-args", "--bogus"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "error: --ros-args: rclpy does not take ['--bogus']" in err and "model" not in err
    from indoorbev_jax.ros2 import runtime

    runtime.check_ros_args(["-r", "points:=/livox/lidar"])  # a remapping is taken
    # A remapping rcl cannot parse: "rclpy does not take failed to initialize rcl: ...".
    with pytest.raises(ValueError, match=r"^--ros-args: rclpy does not take them \(failed to"):
        runtime.check_ros_args(["-r", "bad"])


def test_levelled_clouds_publish_in_the_level_frame(model, capsys):
    """With --lidar-rpy the outputs are in the level frame, which needs its own frame id."""
    from indoorbev_jax import cli
    from indoorbev_jax.mount import LidarMount
    from indoorbev_jax.ros2 import detect

    mount = LidarMount(pitch=20.0, height=1.2)
    with pytest.raises(ValueError, match="name their frame with --level-frame"):
        Detector(CFG, model[1], TS, mount=mount)
    with pytest.raises(ValueError, match="outputs stay in the cloud's frame"):
        Detector(CFG, model[1], TS, mount=LidarMount(height=1.2), level_frame="lvl")
    with pytest.raises(ValueError, match="name their frame with --level-frame"):
        detect.run_detect_node("no-such-model", mount=mount)  # before the model loads
    assert cli.main(["ros2", "detect", "--checkpoint", "m", "--lidar-rpy", "0,20,0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("indoorbev ros2 detect: error: --lidar-rpy levels the clouds")
    assert err.count("\n") == 1
    levelled = Detector(CFG, model[1], TS, mount=mount, level_frame="lidar_level")
    # The warm-up cloud is placed in the level frame: pointing up from 2 m, it still counts.
    upward = LidarMount(pitch=-90.0, height=2.0)
    assert Detector(CFG, model[1], TS, mount=upward, level_frame="up").inference_ms() > 0
    tilted = _scan()
    tilted[:, :3] = (tilted[:, :3].astype(np.float64) @ mount.rotation()).astype(np.float32)
    msgs = _decode(levelled.process(_raw_cloud(tilted)))
    for m in (msgs["detections"], msgs["occupancy"], *msgs["markers"].markers):
        assert m.header.frame_id == "lidar_level"
    predictor = P.Predictor(CFG, model[1], mount=mount)
    labels, _ = predictor.labels(*predictor.infer(*predictor.prepare(tilted)[:2])[:2])
    got = M.detections_to_labels(msgs["detections"])
    assert len(labels) > 0
    np.testing.assert_array_equal(got.pos, labels.pos)  # z moved back by the height offset
    np.testing.assert_array_equal(got.classes, labels.classes)


@contextlib.contextmanager
def _publishing(topic: str, monkeypatch):
    """A live publisher of a scan on ``topic`` every 0.3 s (reliable), for run_detect_node."""
    pytest.importorskip("rclpy", reason="the ros extra is not installed (pip install -e .[ros])")
    from rclpy.signals import SignalHandlerOptions

    from indoorbev_jax.ros2 import runtime

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    domain = os.environ.get("ROS_DOMAIN_ID") or str(1 + os.getpid() % 100)
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("indoorbev_test_pub", context=context)
    pub = node.create_publisher(runtime.msg_class(POINTCLOUD2), topic, runtime.qos(True, 5))
    stop = threading.Event()

    def publish():
        k = 0
        while not stop.wait(0.3):
            pub.publish(_raw_cloud(_scan(), stamp=(k + 1) * 10**9))
            k += 1

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    sigterm = signal.getsignal(signal.SIGTERM)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, sigterm)
        stop.set()
        thread.join()
        node.destroy_node()
        context.try_shutdown()


def test_recording_names_the_topics_as_resolved(model, tmp_path, monkeypatch):
    # A namespaced node (multi-robot setups) with relative topic names: the bag must name
    # the topics the clouds really came from (/robot1/points), as `ros2 bag record` does,
    # not the unresolved "points", so that `indoorbev predict --topic /robot1/points` and
    # `ros2 bag play` find them.
    from indoorbev_jax.ros2.detect import run_detect_node

    bag = tmp_path / "bag"
    with _publishing("/robot1/points", monkeypatch):
        summary = run_detect_node(str(model[0]), topic="points", out_ns="indoorbev",
                                  reliable=True, record=str(bag), max_frames=2,
                                  ros_args=["-r", "__ns:=/robot1"])  # fmt: skip
    assert summary["processed"] == 2
    assert set(read_bag(bag)) == {"/robot1/points"} | {f"/robot1/indoorbev/{k}" for k in OUTPUTS}


def test_a_topic_that_resolves_to_an_output_is_refused(model, monkeypatch):
    """A relative ``--topic indoorbev/detections`` passed the check of the names as given
    and fed the node its own detections; the resolved names are compared too."""
    pytest.importorskip("rclpy", reason="the ros extra is not installed (pip install -e .[ros])")
    from indoorbev_jax.ros2 import runtime
    from indoorbev_jax.ros2.detect import run_detect_node

    def spin(*args):  # reached only when the topic was taken: fail, do not wait for clouds
        raise AssertionError("the node started on its own output")

    monkeypatch.setattr(runtime, "spin", spin)
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    expected = (r"topic: 'indoorbev/detections' resolves to /indoorbev/detections, one of "
                r"the node's own outputs")  # fmt: skip
    with pytest.raises(ValueError, match=expected):
        run_detect_node(str(model[0]), topic="indoorbev/detections", max_frames=1)


def _failing_writer(monkeypatch, after: int):
    """rosbags' Writer.write raises ENOSPC (a full disk) after ``after`` messages."""
    from rosbags.rosbag2 import Writer

    write, calls = Writer.write, []

    def full(self, *args, **kwargs):
        calls.append(1)
        if len(calls) > after:
            raise OSError(28, "No space left on device")
        return write(self, *args, **kwargs)

    monkeypatch.setattr(Writer, "write", full)


def test_a_failed_recorder_drops_later_messages(tmp_path, monkeypatch):
    """It queued every later message in memory (55 MiB in 20 s of a 20k-point lidar) and
    said nothing until close."""
    _failing_writer(monkeypatch, after=2)
    raw = _raw_cloud(_scan(20))
    rec = BagRecorder(tmp_path / "full", {"/a": POINTCLOUD2}, TS)
    deadline = time.monotonic() + 30
    while rec.write("/a", 1, raw) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert "No space left on device" in rec.error and rec.counts == {"/a": 2}
    assert not rec.write("/a", 2, raw) and rec._queue.qsize() == 0  # nothing held
    with pytest.raises(RuntimeError, match=r"full: recording failed: .*No space left"):
        rec.close()
    assert rec.partial.is_dir() and not (tmp_path / "full").exists()


def test_detect_goes_on_and_reports_when_its_recording_fails(model, tmp_path, monkeypatch, capsys):
    from indoorbev_jax.ros2.detect import run_detect_node

    _failing_writer(monkeypatch, after=5)  # fails within the first two clouds
    with _publishing("/points", monkeypatch), pytest.raises(OSError) as failed:
        run_detect_node(str(model[0]), topic="/points", reliable=True,
                        record=str(tmp_path / "bag"), max_frames=3)  # fmt: skip
    assert "recording failed" in str(failed.value) and "into " in str(failed.value)
    out = capsys.readouterr().out
    assert '"processed": 3' in out  # the summary came, after every frame asked for
    assert (tmp_path / "bag.partial").is_dir() and not (tmp_path / "bag").exists()


def test_sim_ctrl_c_while_a_scene_is_generated_exits_cleanly(tmp_path, monkeypatch):
    # Ctrl-C while the generator thread is inside jitted code (here: compiling the first
    # scene, no XLA cache): the bag is finished and the process exits 0, not with an abort
    # (status 134, "FATAL: exception not rethrown") at interpreter shutdown.
    pytest.importorskip("rclpy", reason="the ros extra is not installed (pip install -e .[ros])")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    domain = os.environ.get("ROS_DOMAIN_ID") or str(1 + os.getpid() % 100)
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    bag = tmp_path / "sim_bag"
    sim = subprocess.Popen(
        [sys.executable, "-c", "import signal, sys; "
         "signal.signal(signal.SIGINT, signal.default_int_handler); "  # even if inherited ignored
         "sys.argv[0] = 'indoorbev-sim'; from indoorbev_sim.cli import entry; entry()",
         "ros2", "publish", "--preset", "small", "--frames", "0", "--topic", "/sigint_test",
         "--record", str(bag), "--cache", ""],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        out = _Lines(sim)
        out.wait_for(" at 10.0 Hz", timeout=120)  # printed as the generator starts compiling
        time.sleep(2.5)  # well into the compile (it ends during shutdown: the abort)
        sim.send_signal(signal.SIGINT)
        assert sim.wait(timeout=120) == 0, out.all
    finally:
        if sim.poll() is None:
            sim.kill()
            sim.wait()
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:  # a finished bag (maybe without a frame yet)
        assert {c.topic for c in reader.connections} == {"/sigint_test", "/lidar/objects"}


DROPPED_CTRL_C = """
import os, signal, time
from indoorbev_jax.cli import exit_with
from indoorbev_jax.ros2 import runtime

signal.signal(signal.SIGINT, signal.default_int_handler)  # even if inherited ignored

def main():
    try:  # as Python does with a KeyboardInterrupt raised in a garbage-collector callback
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    runtime.start_node("dropped")
    print("node started")
    return 0

exit_with(main, "probe")
"""


def test_a_ctrl_c_dropped_during_the_start_up_stops_the_node_from_starting():
    """Python drops a KeyboardInterrupt raised inside a gc callback (JAX has one): a Ctrl-C
    during ``ros2 publish``'s start-up was lost and the node published until the next one.
    The console scripts remember SIGINT, and ``start_node`` refuses to start after one."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    run = subprocess.run([sys.executable, "-c", DROPPED_CTRL_C], capture_output=True,
                         text=True, timeout=120, env=env)  # fmt: skip
    assert run.returncode == 130, run.stderr
    assert "node started" not in run.stdout and "probe: interrupted" in run.stderr


def test_sim_publish_goes_on_and_reports_when_its_recording_fails(tmp_path, monkeypatch, capsys):
    pytest.importorskip("rclpy", reason="the ros extra is not installed (pip install -e .[ros])")
    from indoorbev_sim.ros2 import publish

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    domain = os.environ.get("ROS_DOMAIN_ID") or str(1 + os.getpid() % 100)
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    _failing_writer(monkeypatch, after=3)  # fails on the second frame's cloud
    sigterm = signal.getsignal(signal.SIGTERM)
    try:
        with pytest.raises(OSError) as failed:
            publish(CFG, rate=20.0, frames=4, record=str(tmp_path / "bag"))
    finally:
        signal.signal(signal.SIGTERM, sigterm)
    assert "recording failed" in str(failed.value) and "No space left" in str(failed.value)
    assert "'frames': 4" in capsys.readouterr().out  # every frame went out, then the summary
    assert (tmp_path / "bag.partial").is_dir() and not (tmp_path / "bag").exists()


def test_sim_publish_simulates_the_tilt_it_publishes_and_records_resolved_names(
    monkeypatch, tmp_path
):
    """``--lidar-rpy`` publishes clouds as scanned at exactly that tilt: the config's
    ``sim.sensor_tilt_jitter`` is turned off for them (else each scene would carry up to 8
    degrees more than the frame says). ``--record`` under a namespace records the topics as
    they resolve. A mutation audit: keeping the jitter passed, and recording under the
    unresolved names raised KeyError, untested."""
    import indoorbev_sim.ros2 as sim_ros2

    labels, _ = _two_detections()
    simulated = []

    def frames(config, seed, split):
        simulated.append((config.sim.sensor_rpy, config.sim.sensor_tilt_jitter))
        while True:
            yield _scan(5), labels

    _fake_sim_node(monkeypatch, frames, namespace="/robot1")
    jittered = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, sensor_tilt_jitter=8.0))
    sim_ros2.publish(jittered, rate=50.0, frames=1, lidar_rpy=(0.0, 20.0, 0.0),
                     level_frame="lidar_level")  # fmt: skip
    assert simulated == [((0.0, 20.0, 0.0), 0.0)]
    assert sim_ros2.publish(CFG, rate=50.0, frames=2, record=str(tmp_path / "bag"))["frames"] == 2
    recorded = read_bag(tmp_path / "bag")
    assert {topic: len(messages) for topic, messages in recorded.items()} == {
        "/robot1/lidar/points": 2,
        "/robot1/lidar/objects": 2,
    }


def test_header_from_cdr_reads_either_byte_order_and_refuses_nanosec_of_a_second():
    """builtin_interfaces/Time keeps ``nanosec < 10**9``: ``header_from_cdr`` reads a broken
    cloud's header only when it is a valid one, else None (its docstring), so a header of
    nanosec 10**9 gives no outputs rather than a stamp one second off. A mutation audit:
    accepting nanosec == 10**9 passed."""
    frame = b"lidar\0"
    for nanosec, want in ((10**9 - 1, (5 * 10**9 + 10**9 - 1, "lidar")), (10**9, None)):
        raw = b"\x00\x01\x00\x00" + struct.pack("<iII", 5, nanosec, len(frame)) + frame
        assert M.header_from_cdr(raw + b"\x00\x00") == want
    # Big-endian CDR (encapsulation 0x0000) is read in its own byte order. A mutation audit:
    # reading every header little-endian (a big-endian cloud lost its stamp) passed.
    msg = cloud_msg(TS, np.zeros((3, 4), np.float32), 5 * 10**9 + 7, "test_lidar")
    for little_endian in (True, False):
        raw = bytes(TS.serialize_cdr(msg, POINTCLOUD2, little_endian=little_endian))
        assert raw[1] == little_endian
        assert M.header_from_cdr(raw) == (5 * 10**9 + 7, "test_lidar")


def test_occupancy_map_load_time_is_the_cloud_stamp():
    """Every output carries the input cloud's stamp (docs/ROBOT.md, Topics); the grid's
    ``info.map_load_time`` is that stamp too, not 0 (a map loaded in 1970). A mutation
    audit: a zero map_load_time passed."""
    stamp = 1_700_000_000_500_000_000
    msg = M.occupancy_msg(TS, None, CFG.grid, stamp, "lidar")
    msg = TS.deserialize_cdr(TS.serialize_cdr(msg, M.OCCUPANCY_GRID), M.OCCUPANCY_GRID)
    assert M.stamp_ns(msg) == stamp
    load = msg.info.map_load_time
    assert load.sec * 10**9 + load.nanosec == stamp


def test_node_qos_reliability_follows_the_flag():
    """Input subscribed best effort unless --reliable; outputs published reliable
    (docs/ROBOT.md, Topics): ``runtime.qos(reliable, depth)`` must map True to RELIABLE and
    False to BEST_EFFORT. The live loop test uses ``runtime.qos`` on both ends, so it cannot
    see an inversion. A mutation audit: inverted reliability passed."""
    pytest.importorskip("rclpy", reason="the ros extra is not installed (pip install -e .[ros])")
    from rclpy.qos import ReliabilityPolicy

    from indoorbev_jax.ros2 import runtime

    assert runtime.qos(True, 5).reliability == ReliabilityPolicy.RELIABLE
    assert runtime.qos(True, 5).depth == 5
    assert runtime.qos(False, 1).reliability == ReliabilityPolicy.BEST_EFFORT
    assert runtime.qos(False, 1).depth == 1


def test_node_drops_stale_clouds_and_times_only_stamped_ones(monkeypatch):
    """run_detect_node's own callback and worker under a fake rclpy node (no DDS), with a
    fake detector whose first cloud blocks while more arrive (docs/ROBOT.md, Behaviour):

    - the subscription keeps one message (keep last 1, best effort by default) and the
      outputs are reliable, keep last 5;
    - the callback parks only the newest cloud: a burst of 19 while the worker is busy
      gives one processed (the newest) and 18 dropped as stale, and a later cloud that
      finds the mailbox empty is not counted as dropped (a mailbox that kept the stale
      ones would count it, and grow without bound);
    - ``latency_ms`` runs from the stamp until the detections are published, so it holds
      a detections publish that takes 0.1 s (markers and grid follow);
    - unstamped clouds (stamp 0) stay out of every latency (else ~1.8e12 ms).

    A mutation audit: keeping stale clouds in the mailbox, a subscription depth of 10,
    latency ending before the detections are published, unstamped clouds in the latency
    statistics, transport timed to the publish and bad inputs not counted all passed."""
    from indoorbev_jax.ros2 import detect, runtime

    entered, gate, processed, published = threading.Event(), threading.Event(), [], []
    last = list(OUTPUTS)[-1].encode()
    slow_ms = 100

    class FakeDetector:
        def __init__(self, *a, **k):
            self.ts = TS

        def warmup(self):
            return 0.0

        def inference_ms(self):
            return 1.0

        def process(self, raw):
            stamp, frame = M.header_from_cdr(raw)
            processed.append(frame)
            entered.set()
            assert gate.wait(10)
            outputs = {k: k.encode() for k in OUTPUTS}
            empty = kitti.ObjectLabels.empty(with_scores=True)
            infer_ms = 0.0 if frame == "c0" else 5.0  # c0 a bad input: the model not run
            return detect.Result(stamp, frame, outputs, empty, None, infer_ms)

    class Pub:
        def __init__(self, topic):
            self.topic_name = topic

        def publish(self, message):
            if message == b"detections":
                time.sleep(slow_ms / 1000)
            published.append(message)

    qos_of = {}

    class Node:
        def get_logger(self):
            return type("Log", (), {"__getattr__": lambda s, n: lambda *a, **k: None})()

        def create_publisher(self, cls, topic, qos):
            qos_of[topic] = qos
            return Pub(topic)

        def create_subscription(self, cls, topic, cb, qos, raw):
            qos_of["input"], self.cb = qos, cb
            return Pub(topic)

    def wait_for(n):  # the n-th cloud's outputs all published
        deadline = time.monotonic() + 10
        while published.count(last) < n:
            assert time.monotonic() < deadline
            time.sleep(0.01)

    def spin(node, context, stop):
        node.cb(_raw_cloud(_scan(5), stamp=0, frame="c0"))  # unstamped
        assert entered.wait(10)
        for k in range(1, 20):  # a burst while c0 is in the model
            node.cb(_raw_cloud(_scan(5), stamp=time.time_ns(), frame=f"c{k}"))
        gate.set()
        wait_for(2)  # c19 done: the mailbox is empty, nothing in the model
        node.cb(_raw_cloud(_scan(5), stamp=time.time_ns(), frame="c20"))
        wait_for(3)
        stop.set()

    node = Node()
    monkeypatch.setattr(detect, "load_model", lambda checkpoint: (CFG, None))
    monkeypatch.setattr(detect, "with_thresholds", lambda config, views=None: config)
    monkeypatch.setattr(detect, "Detector", FakeDetector)
    monkeypatch.setattr(runtime, "require_rclpy", lambda: None)
    monkeypatch.setattr(runtime, "start_node", lambda name, args: (None, node))
    monkeypatch.setattr(runtime, "stop_node", lambda node, context: None)
    monkeypatch.setattr(runtime, "msg_class", lambda msgtype: None)
    monkeypatch.setattr(runtime, "qos", lambda reliable, depth: (reliable, depth))
    monkeypatch.setattr(runtime, "spin", spin)
    summary = detect.run_detect_node("no-model", log_every=1e9)
    assert qos_of.pop("input") == (False, 1)
    assert set(qos_of.values()) == {(True, 5)}
    assert processed == ["c0", "c19", "c20"]
    assert (summary["received"], summary["processed"], summary["dropped_stale"]) == (21, 3, 18)
    assert summary["bad_input"] == 1
    # Two stamped clouds timed: c19 waits out c0's detections publish and its own (at
    # least 0.2 s), c20 its own (at least 0.1 s); the callback took each at once, and
    # transport ends there (unstamped c0 left out: it read 1.8e12).
    assert summary["transport_ms"]["max"] < 1.5 * slow_ms
    assert summary["latency_ms"]["mean"] >= 1.5 * slow_ms
    assert summary["latency_ms"]["max"] < 10_000


def _fake_sim_node(monkeypatch, frames, namespace: str = "") -> list:
    """``indoorbev_sim.ros2.publish`` under a fake rclpy node whose topics resolve under
    ``namespace``, with ``frames(config, seed, split)`` in place of the scene generator (no
    DDS, no scene generation). Returns the list of (resolved topic, message) it publishes."""
    import indoorbev_sim.ros2 as sim_ros2

    from indoorbev_jax.ros2 import runtime

    sent = []

    class Pub:
        def __init__(self, topic):
            self.topic_name = namespace + topic

        def publish(self, message):
            sent.append((self.topic_name, message))

    class Node:
        def create_publisher(self, cls, topic, qos):
            return Pub(topic)

        def get_clock(self):
            return type("Clock", (), {"now": lambda s: types.SimpleNamespace(nanoseconds=7)})()

        def get_logger(self):
            return types.SimpleNamespace(error=print)

    context = types.SimpleNamespace(ok=lambda: True)
    monkeypatch.setattr(sim_ros2, "scene_frames", frames)
    monkeypatch.setattr(runtime, "require_rclpy", lambda: None)
    monkeypatch.setattr(runtime, "start_node", lambda name, args: (context, Node()))
    monkeypatch.setattr(runtime, "stop_node", lambda node, context: None)
    monkeypatch.setattr(runtime, "msg_class", lambda msgtype: None)
    monkeypatch.setattr(runtime, "qos", lambda reliable, depth: None)
    return sent


def test_sim_publish_markers_live_two_frame_periods(monkeypatch):
    """The simulator's ground-truth markers live two frame periods (docs/ROBOT.md, Topics):
    at 20 Hz every marker of every published MarkerArray has lifetime 0.1 s, so a box
    stays until the next frame replaces it and vanishes if the stream stops. Driven under a
    fake rclpy node with fixed frames. A mutation audit: a lifetime 1000 times too short
    passed."""
    import indoorbev_sim.ros2 as sim_ros2

    labels, _ = _two_detections()

    def frames(config, seed, split):
        while True:
            yield _scan(5), labels

    sent = _fake_sim_node(monkeypatch, frames)
    rate = 20.0
    assert sim_ros2.publish(CFG, rate=rate, frames=2)["frames"] == 2
    arrays = [TS.deserialize_cdr(m, MARKER_ARRAY) for t, m in sent if t.endswith("objects")]
    assert len(arrays) == 2 and all(len(a.markers) == 1 + len(labels) for a in arrays)
    lifetime = divmod(round(2 / rate * 1e9), 10**9)
    assert {(m.lifetime.sec, m.lifetime.nanosec) for a in arrays for m in a.markers} == {lifetime}
    # rate_hz is frames per second between the first and the last publish: 3 frames 0.05 s
    # apart on a clock that moves only while publish waits. A mutation audit: frames over
    # that time (30 Hz here) passed.
    now = [1000.0]
    clock = types.SimpleNamespace(
        monotonic=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s)
    )
    monkeypatch.setattr(sim_ros2, "time", clock)
    assert sim_ros2.publish(CFG, rate=rate, frames=3) == {"frames": 3, "rate_hz": 20.0, "late": 0}
