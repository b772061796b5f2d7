"""Predict path: model files, PointCloud2 of any layout, KITTI and bag inputs agree."""

import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from indoorbev_jax import predict as P
from indoorbev_jax.cli import main as cli_main
from indoorbev_jax.config import Config, InferenceConfig
from indoorbev_jax.data import kitti
from indoorbev_jax.rosbag import LIVOX_CUSTOM, BagError, pointcloud2_to_points, typestore
from indoorbev_jax.train import init_state

sys.path.insert(0, str(Path(__file__).parent))
from synthetic import write_synthetic_dataset  # noqa: E402

# Thresholds at 0 so that an untrained model still yields segments to write.
CFG = dataclasses.replace(
    Config.tiny(), inference=InferenceConfig(score_threshold=0.0, overlap_threshold=0.0)
)


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    params = init_state(CFG, jax.random.key(0)).params
    return P.export_model(params, CFG, tmp_path_factory.mktemp("model") / "tiny.msgpack")


def test_model_file_round_trip_and_bad_file(model_file, tmp_path):
    config, params = P.load_model(model_file)
    assert config == CFG
    expected = init_state(CFG, jax.random.key(0)).params
    jax.tree.map(np.testing.assert_array_equal, params, expected)
    (tmp_path / "bad.msgpack").write_bytes(b"not a model")
    with pytest.raises(ValueError, match=r"bad\.msgpack: not an indoorbev_jax model file"):
        P.load_model(tmp_path / "bad.msgpack")


def _cloud(fields, dtype, points, bigendian=False):
    """A PointCloud2 with a structured numpy layout."""
    ts = typestore()
    t = ts.types
    pf = t["sensor_msgs/msg/PointField"]
    codes = {"f4": 7, "f8": 8, "u2": 4, "u1": 2}
    arr = np.zeros(len(points["x"]), dtype=dtype)
    for name in fields:
        arr[name] = points[name]
    msg_fields = [
        pf(name=n, offset=dtype.fields[n][1], datatype=codes[dtype.fields[n][0].str[1:]], count=1)
        for n in fields
    ]
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="livox"
    )
    return t["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(arr), fields=msg_fields, is_bigendian=bigendian,
        point_step=dtype.itemsize, row_step=dtype.itemsize * len(arr),
        data=arr.view(np.uint8).reshape(-1), is_dense=True,
    )  # fmt: skip


def test_pointcloud2_any_layout():
    rng = np.random.default_rng(0)
    n = 50
    src = {k: rng.normal(size=n) for k in "xyz"}
    src["intensity"] = rng.integers(0, 255, n)
    # Livox-like: x y z float32, then a uint8 tag, intensity float32 after padding.
    d1 = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": ["<f4", "<f4", "<f4", "<f4"],
                   "offsets": [0, 4, 8, 16], "itemsize": 24})  # fmt: skip
    got = pointcloud2_to_points(_cloud(["x", "y", "z", "intensity"], d1, src))
    expected = np.stack([src["x"], src["y"], src["z"], src["intensity"]], 1).astype(np.float32)
    np.testing.assert_array_equal(got, expected)
    # Big-endian float64 in another order, uint16 intensity.
    d2 = np.dtype([("intensity", ">u2"), ("z", ">f8"), ("x", ">f8"), ("y", ">f8")])
    got = pointcloud2_to_points(_cloud(["intensity", "z", "x", "y"], d2, src, bigendian=True))
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    # No intensity field: zeros.
    d3 = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    got = pointcloud2_to_points(_cloud(["x", "y", "z"], d3, src))
    np.testing.assert_array_equal(got[:, 3], 0)
    with pytest.raises(BagError, match=r"lacks field\(s\) \['z'\]"):
        d4 = np.dtype([("x", "<f4"), ("y", "<f4")])
        pointcloud2_to_points(_cloud(["x", "y"], d4, src))


def test_predict_kitti_then_bag_round_trip(model_file, tmp_path, capsys):
    data = tmp_path / "data"
    write_synthetic_dataset(data, frames=3, val=1)
    out = tmp_path / "pred"
    bag = tmp_path / "pred_bag"
    assert cli_main(["predict", str(model_file), str(data), "--out", str(out),
                     "--bag-out", str(bag)]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "3 frames" in printed and "ms/frame" in printed
    for fid in ("000000", "000001", "000002"):
        lines = (out / "label_2" / f"{fid}.txt").read_text().splitlines()
        assert lines and all(len(line.split()) == 16 for line in lines)
        labels = kitti.read_labels(out / "label_2" / f"{fid}.txt", CFG.data)
        ids = kitti.read_mask(out / "mask_2" / f"{fid}.png", CFG.grid.shape)
        assert set(np.unique(ids)) - {0} == set(range(1, len(labels) + 1))
        assert (out / "pictures" / f"{fid}.png").stat().st_size > 1000
    # The bag written alongside holds the same clouds; predicting from it gives the same.
    out2 = tmp_path / "pred2"
    summary = P.predict(model_file, bag, out2, pictures=False, verbose=False)
    assert summary["frames"] == 3
    for fid in ("000000", "000001", "000002"):
        a = (out / "label_2" / f"{fid}.txt").read_text()
        assert a == (out2 / "label_2" / f"{fid}.txt").read_text()


def test_bad_input_is_named(model_file, tmp_path):
    with pytest.raises(ValueError, match="expected a .bin file, a KITTI-style folder"):
        P.predict(model_file, tmp_path, tmp_path / "o", verbose=False)
    (tmp_path / "x.bin").write_bytes(b"\0" * 10)
    with pytest.raises(kitti.DatasetError, match=r"x\.bin: size 10 bytes"):
        P.predict(model_file, tmp_path / "x.bin", tmp_path / "o", verbose=False)


def test_cli_predict_reports_bad_input_without_a_traceback(model_file, tmp_path, capsys):
    (tmp_path / "x.bin").write_bytes(b"\0" * 10)
    assert cli_main(["predict", str(model_file), str(tmp_path / "x.bin"), "--out",
                     str(tmp_path / "o")]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert err.startswith("indoorbev predict: error:") and "x.bin: size 10 bytes" in err
    assert cli_main(["predict", str(tmp_path / "none.msgpack"), str(tmp_path), "--out",
                     str(tmp_path / "o")]) == 2  # fmt: skip
    assert "none.msgpack" in capsys.readouterr().err


def test_dense_scan_is_thinned_evenly_and_said(model_file, tmp_path, capsys):
    n = CFG.data.max_points
    rng = np.random.default_rng(1)
    pts = rng.uniform(-2.0, 2.0, (3 * n, 4)).astype(np.float32)
    pts[:, 3] = rng.uniform(0.0, 1.0, 3 * n)
    kitti.write_points(tmp_path / "dense.bin", pts)
    summary = P.predict(model_file, tmp_path / "dense.bin", tmp_path / "o", pictures=False)
    assert summary["thinned_frames"] == 1
    printed = capsys.readouterr().out
    assert f"{2 * n} of {3 * n} valid points left out (data.max_points={n}" in printed
    config, params = P.load_model(model_file)
    predictor = P.Predictor(config, params)
    padded, valid, *_ = predictor(pts)
    assert predictor.last_counts["dropped_points"] == 2 * n and valid.all()
    np.testing.assert_array_equal(padded, pts[::3])  # every third: floor(k * 3n / n)


def test_intensity_units_map_onto_the_simulators_range():
    unit = np.array([[1.0, 0.0, 0.0, 0.4], [1.0, 1.0, 0.0, 1.0]], np.float32)
    livox = np.array([[1.0, 0.0, 0.0, 75.0], [1.0, 1.0, 0.0, 255.0]], np.float32)
    assert P.intensity_factor("auto", unit) == 1.0
    assert P.intensity_factor("auto", livox) == pytest.approx(1 / 150)
    assert P.intensity_factor("percent", livox) == pytest.approx(0.01)
    assert P.intensity_factor(0.5, livox) == 0.5
    # Livox: 150 is 100 % Lambertian reflectivity; retro-reflectors (151-255) clip to 1.
    np.testing.assert_allclose(P.normalize_intensity(livox, 1 / 150)[:, 3], [0.5, 1.0])
    np.testing.assert_array_equal(P.normalize_intensity(livox, 1 / 150)[:, :3], livox[:, :3])
    with pytest.raises(ValueError, match=r"'lux'.*'livox', 'percent', 'unit'"):
        P.intensity_factor("lux", unit)
    with pytest.raises(ValueError, match="finite number >= 0"):
        P.intensity_factor(-1.0, unit)


def test_livox_cloud_gives_the_unit_clouds_prediction(model_file, tmp_path, capsys):
    config, params = P.load_model(model_file)
    rng = np.random.default_rng(2)
    unit = rng.uniform(-2.0, 2.0, (500, 4)).astype(np.float32)
    unit[:, 3] = rng.integers(0, 151, 500) / np.float32(150)
    livox = unit.copy()
    livox[:, 3] = np.round(unit[:, 3] * 150)
    want = P.Predictor(config, params, "unit")(unit)
    predictor = P.Predictor(config, params)
    got = predictor(livox)
    assert predictor.last_intensity_factor == pytest.approx(1 / 150)
    np.testing.assert_allclose(got[0], want[0], atol=1e-6)  # the points the model saw
    np.testing.assert_allclose(got[2].logits, want[2].logits, rtol=1e-4, atol=1e-4)
    kitti.write_points(tmp_path / "livox.bin", livox)
    args = ["predict", str(model_file), str(tmp_path / "livox.bin"), "--out", str(tmp_path / "o")]
    assert cli_main([*args, "--no-pictures", "--intensity", "livox"]) == 0
    assert "intensity scaled by 0.00666667" in capsys.readouterr().out
    assert cli_main([*args, "--intensity", "lux"]) == 2
    assert "intensity units 'lux'" in capsys.readouterr().err


def _livox_bag(path, clouds, topic="/livox/lidar"):
    """A rosbag2 folder of livox_ros_driver2/CustomMsg, one message per [N, 4] cloud."""
    from rosbags.rosbag2 import Writer

    from indoorbev_jax.rosbag import header

    ts = typestore()
    t = ts.types
    with Writer(path, version=8) as writer:
        conn = writer.add_connection(topic, LIVOX_CUSTOM, typestore=ts)
        for k, cloud in enumerate(clouds):
            stamp = (k + 1) * 10**8
            points = [
                t["livox_ros_driver2/msg/CustomPoint"](
                    offset_time=i, x=x, y=y, z=z, reflectivity=int(r), tag=0, line=i % 4
                )
                for i, (x, y, z, r) in enumerate(cloud)
            ]
            msg = t[LIVOX_CUSTOM](
                header=header(ts, stamp, "livox_frame"), timebase=stamp, point_num=len(points),
                lidar_id=192, rsvd=np.zeros(3, np.uint8), points=points,
            )  # fmt: skip
            writer.write(conn, stamp, ts.serialize_cdr(msg, LIVOX_CUSTOM))


def test_livox_custom_msg_bag_reads_and_predicts_as_its_points(model_file, tmp_path):
    from indoorbev_jax.rosbag import read_clouds

    rng = np.random.default_rng(3)
    clouds = []
    for n in (300, 450):
        cloud = rng.uniform(-2.0, 2.0, (n, 4)).astype(np.float32)
        cloud[:, 3] = rng.integers(0, 256, n)  # Livox reflectivity
        clouds.append(cloud)
    _livox_bag(tmp_path / "livox_bag", clouds)
    frames = list(read_clouds(tmp_path / "livox_bag"))
    assert [(stamp, frame) for stamp, frame, _ in frames] == [
        (10**8, "livox_frame"),
        (2 * 10**8, "livox_frame"),
    ]
    for (_, _, got), cloud in zip(frames, clouds, strict=True):
        np.testing.assert_array_equal(got, cloud)
    # The bag and the same points as .bin files give the same labels (intensity: auto).
    kitti_root = tmp_path / "kitti"
    for k, cloud in enumerate(clouds):
        kitti.write_points(kitti_root / "velodyne" / f"{k:06d}.bin", cloud)
    P.predict(model_file, tmp_path / "livox_bag", tmp_path / "a", pictures=False, verbose=False)
    P.predict(model_file, kitti_root, tmp_path / "b", pictures=False, verbose=False)
    for fid in ("000000", "000001"):
        a = (tmp_path / "a" / "label_2" / f"{fid}.txt").read_text()
        assert a == (tmp_path / "b" / "label_2" / f"{fid}.txt").read_text()
    # A message whose point count disagrees with its points is named.
    from indoorbev_jax.rosbag import livox_custom_to_points

    msg = typestore().deserialize_cdr(_first_raw(tmp_path / "livox_bag"), LIVOX_CUSTOM)
    msg.point_num = 7
    with pytest.raises(BagError, match=r"bag@1: point_num 7 but 300 points"):
        livox_custom_to_points(msg, "bag@1")


def _first_raw(bag):
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        return next(iter(reader.messages()))[2]


def test_nan_intensity_stays_invalid_after_scaling():
    pts = np.array([[1.0, 0.0, 0.0, np.nan], [1.0, 1.0, 0.0, 200.0]], np.float32)
    scaled = P.normalize_intensity(pts, P.intensity_factor("auto", pts))
    assert np.isnan(scaled[0, 3]) and scaled[1, 3] == 1.0  # 200 > 150: a retro-reflector
    _, valid, counts = P.pad_points(scaled, CFG.grid, CFG.data.max_points)
    assert counts["nonfinite_points"] == 1 and valid.sum() == 1


def test_predictor_with_views_maps_features_and_segments_back(model_file, tmp_path):
    """A mirrored cloud read through the single view ``mirror_y`` is the plain cloud's
    forward: features and panoptic map come back mirrored; ``predict`` writes its labels."""
    config, params = P.load_model(model_file)
    rng = np.random.default_rng(4)
    cloud = rng.uniform(-3.0, 3.0, (800, 4)).astype(np.float32)
    cloud[:, 2:] = rng.uniform(0.0, 1.0, (800, 2))
    mirrored = cloud * np.array([1, -1, 1, 1], np.float32)
    _, _, _, plain, bev = P.Predictor(config, params)(cloud)
    one = P.with_thresholds(config, views=("mirror_y",))
    _, _, final, out, bev_m = P.Predictor(one, params)(mirrored)
    np.testing.assert_allclose(bev_m, bev[::-1], atol=1e-5)
    assert (plain.instance_ids > 0).any()
    np.testing.assert_array_equal(out.instance_ids, plain.instance_ids[::-1])
    assert final.masks.shape[0] == config.head.num_queries
    kitti.write_points(tmp_path / "scan.bin", cloud)
    summary = P.predict(model_file, tmp_path / "scan.bin", tmp_path / "o", pictures=True,
                        verbose=False, views=("identity", "mirror_y"))  # fmt: skip
    assert summary["frames"] == 1
    lines = (tmp_path / "o" / "label_2" / "scan.txt").read_text().splitlines()
    assert len(lines) == summary["objects"] > 0
    with pytest.raises(ValueError, match=r"inference\.views.*'flip'"):
        P.predict(model_file, tmp_path / "scan.bin", tmp_path / "o2", views=("flip",))
