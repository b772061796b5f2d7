"""Predict path: model files, PointCloud2 of any layout, KITTI and bag inputs agree."""

import copy
import dataclasses
import fcntl
import json
import os
import re
import shutil
import sys
import time
import types
from pathlib import Path

import jax
import numpy as np
import pytest

from indoorbev_jax import predict as P
from indoorbev_jax.cli import main as cli_main
from indoorbev_jax.config import LATER_FIELDS, Config, InferenceConfig
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
    # A folder that is no run directory is said so (not a bare "No such file").
    with pytest.raises(FileNotFoundError, match="not a training run directory"):
        P.load_model(tmp_path)
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"config\.json: not valid JSON"):
        P.load_model(tmp_path)


def test_a_pipe_given_as_the_model_is_named_not_read(tmp_path, errors_without_blocking):
    os.mkfifo(tmp_path / "m.msgpack")
    errors = errors_without_blocking({"model": lambda: P.load_model(tmp_path / "m.msgpack")})
    assert (
        str(errors["model"])
        == f"{tmp_path / 'm.msgpack'}: a pipe, socket or device, not a model file"
    )


def test_a_model_file_must_hold_its_configs_network(model_file, tmp_path):
    """A config field left out took its default (the shipped model without head.mask_prior
    detected nothing, exit 0); parameters of another shape or tree than the config's
    network were read, failing later with flax's traceback or, extra ones, silently dropped;
    a file without its config or parameters raised a KeyError. Each is refused, named."""
    from flax import serialization

    good = serialization.msgpack_restore(model_file.read_bytes())
    del good["sha256"]  # as files written before it: their contents are checked alone
    settings = json.loads(good["config"])

    def load(name, **changes):
        path = tmp_path / f"{name}.msgpack"
        path.write_bytes(serialization.msgpack_serialize({**good, **changes}))
        with pytest.raises(ValueError) as refused:
            P.load_model(path)
        assert str(refused.value).startswith(f"{path}: ")
        return str(refused.value)[len(str(path)) + 2 :]

    no_prior = copy.deepcopy(settings)
    del no_prior["head"]["mask_prior"], no_prior["head"]["mask_pooled_class"]
    text = json.dumps(no_prior)
    expected = "missing config field(s) ['head.mask_pooled_class', 'head.mask_prior']"
    assert load("no_prior", config=text) == expected
    no_grid = json.dumps({k: v for k, v in settings.items() if k != "grid"})
    assert load("no_grid", config=no_grid) == "missing config field(s) ['grid']"
    assert load("not_json", config="{grid") == (
        "its config is not valid JSON (Expecting property name enclosed in double quotes: "
        "line 1 column 2 (char 1))"
    )
    assert load("no_config", config=None) == (
        "not an indoorbev_jax model file (expected a config text and a tree of parameters, "
        "got NoneType and dict)"
    )
    assert load("int_params", params=3).endswith("got str and int)")
    params = good["params"]
    flat = jax.tree_util.tree_flatten_with_path(params)[0]
    name, kernel = next((jax.tree_util.keystr(p), x) for p, x in flat if x.ndim == 2)
    assert kernel.shape[0] != kernel.shape[1]
    swapped = jax.tree_util.tree_map_with_path(
        lambda p, x: x.T if jax.tree_util.keystr(p) == name else x, params
    )
    assert load("swapped", params=swapped) == (
        f"parameter {name} has shape {kernel.T.shape}, its config's model expects {kernel.shape}"
    )
    halved = jax.tree_util.tree_map_with_path(
        lambda p, x: x.astype(np.float16) if jax.tree_util.keystr(p) == name else x, params
    )
    assert load("halved", params=halved) == (
        f"parameter {name} has dtype float16, its config's model expects float32"
    )
    fewer = copy.deepcopy(params)
    del fewer["params"]["head"]
    assert re.fullmatch(
        r"parameter \['params'\]\['head'\]\[.*\] is missing", load("no_head", params=fewer)
    )
    extra = copy.deepcopy(params)
    extra["params"]["lateral"] = {"kernel": np.ones((2, 2), np.float32)}
    assert load("extra", params=extra) == (
        "parameter ['params']['lateral']['kernel'] is not in its config's model"
    )
    small = json.dumps(Config.small().to_dict())  # another preset's config over these params
    assert "its config's model expects" in load("small_config", config=small)
    # The fields added later may be left out (files written before them), and only they.
    for path in LATER_FIELDS:
        section, field = path.split(".")
        del settings[section][field]
    older = tmp_path / "older.msgpack"
    older.write_bytes(serialization.msgpack_serialize({**good, "config": json.dumps(settings)}))
    assert P.load_model(older)[0] == CFG


def test_a_model_file_is_checked_against_the_sha256_written_with_it(model_file, tmp_path):
    """A byte flipped in a model file's parameters or config loaded as other weights or
    settings, silently; the file now holds the sha256 of both, and a copy that does not
    match it is refused, named."""
    from flax import serialization

    data = model_file.read_bytes()
    stored = serialization.msgpack_restore(data)
    assert re.fullmatch(r"[0-9a-f]{64}", stored["sha256"])
    kernel = next(x for x in jax.tree.leaves(stored["params"]) if x.ndim == 2 and x.size >= 64)
    at = data.find(kernel.tobytes())
    assert at > 0 and data.find(kernel.tobytes(), at + 1) < 0
    steps = b'"total_steps": '
    assert data.count(steps) == 1
    edits = {
        "weight": (at + 4 * 10 + 1, 1),  # the second byte of the kernel's 11th float32
        "config": (data.find(steps) + len(steps), 1),  # its first digit: 20 -> 30
    }
    for what, (offset, n) in edits.items():
        damaged = bytearray(data)
        damaged[offset : offset + n] = bytes(b ^ 0x01 for b in damaged[offset : offset + n])
        path = tmp_path / f"{what}.msgpack"
        path.write_bytes(bytes(damaged))
        with pytest.raises(ValueError) as refused:
            P.load_model(path)
        assert str(refused.value) == (
            f"{path}: its config and parameters do not match the sha256 written with them "
            "(a damaged copy): copy or export the model again"
        )
        # Without the sha256 (an older file) the damage goes unseen: the flip is real.
        unchecked = serialization.msgpack_restore(bytes(damaged))
        del unchecked["sha256"]
        path.write_bytes(serialization.msgpack_serialize(unchecked))
        config, params = P.load_model(path)
        differs = config != CFG or any(
            not np.array_equal(a, b)
            for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(stored["params"]), strict=True)
        )
        assert differs, what
    # A flip in the key's own name must not read as an older file without a checksum.
    assert data.count(b"sha256") == 1
    path = tmp_path / "key.msgpack"
    path.write_bytes(data.replace(b"sha256", b"sha2T6"))
    with pytest.raises(ValueError) as refused:
        P.load_model(path)
    assert str(refused.value) == (
        f"{path}: unexpected field(s) 'sha2T6', expected only format, config, params, sha256 "
        "(a damaged copy, or a newer indoorbev_jax's file)"
    )


def test_write_bag_clears_only_its_own_leftovers(tmp_path):
    from indoorbev_jax.rosbag import write_bag

    frame = (10**9, "lidar", np.zeros((3, 4), np.float32), kitti.ObjectLabels.empty())
    bag = tmp_path / "out_bag"
    (tmp_path / "out_bag.partial" / "out_bag").mkdir(parents=True)  # a write cut short
    assert write_bag(bag, [frame], CFG.data.class_names, "/points", "/objects") == 1
    assert bag.is_dir() and not (tmp_path / "out_bag.partial").exists()
    other = tmp_path / "b.partial" / "notes.txt"
    other.parent.mkdir()
    other.write_text("mine")
    with pytest.raises(FileExistsError, match=r"b\.partial: holds files"):
        write_bag(tmp_path / "b", [frame], CFG.data.class_names, "/points", "/objects")
    assert other.read_text() == "mine"
    # Killed while replacing a finished bag: the old one moved aside, the new one not yet in
    # place. The rerun completes (it used to find a half-deleted bag and refuse it).
    (tmp_path / "out_bag.partial").mkdir()
    bag.rename(tmp_path / "out_bag.partial" / "out_bag.old")
    assert write_bag(bag, [frame], CFG.data.class_names, "/points", "/objects") == 1
    assert bag.is_dir() and not (tmp_path / "out_bag.partial").exists()
    assert write_bag(bag, [frame, frame], CFG.data.class_names, "/points", "/objects") == 2


def test_a_second_write_of_one_bag_is_refused_while_the_first_runs(tmp_path):
    """Two predict runs given one --bag-out (from different --out folders) shared the bag's
    temporary folder: the second deleted the first's half-written bag, which then failed."""
    from indoorbev_sim.export import ExportError, _check_bag_place

    from indoorbev_jax.rosbag import check_partial, count_clouds, write_bag

    frame = (10**9, "lidar", np.zeros((3, 4), np.float32), kitti.ObjectLabels.empty())
    bag = tmp_path / "out_bag"
    names = CFG.data.class_names

    said = (r"out_bag\.partial: in use by another write of this bag \(pid \d+\); wait for it "
            "to end, or use another bag folder")  # fmt: skip

    def frames():
        yield frame
        with pytest.raises(ValueError, match=said):
            write_bag(bag, [frame], names, "/points", "/objects")
        # An export or predict that would write it at its end is told at its start.
        with pytest.raises(ValueError, match=said):
            check_partial(bag)
        with pytest.raises(ExportError, match=said):
            _check_bag_place(bag, tmp_path / "dataset")
        with pytest.raises(ValueError, match=said):  # predict's checks before its first frame
            P._check_out_paths(tmp_path / "clouds", tmp_path / "out", bag)
        yield frame

    assert write_bag(bag, frames(), names, "/points", "/objects") == 2
    assert count_clouds(bag, "/points") == 2 and not (tmp_path / "out_bag.partial").exists()
    # A write killed (-9) leaves its lock file: the next one is not refused.
    (tmp_path / "out_bag.partial").mkdir()
    (tmp_path / "out_bag.partial" / ".lock").write_text("write of this bag, pid 1\n")
    assert write_bag(bag, [frame], names, "/points", "/objects") == 1
    # Only a plain .lock file is the lock's: a symlink or a folder of that name is a user's.
    for make in (lambda p: p.symlink_to(tmp_path / "notes.txt"), lambda p: p.mkdir()):
        (tmp_path / "out_bag.partial").mkdir()
        make(tmp_path / "out_bag.partial" / ".lock")
        with pytest.raises(FileExistsError, match=r"out_bag\.partial: holds files"):
            write_bag(bag, [frame], names, "/points", "/objects")
        shutil.rmtree(tmp_path / "out_bag.partial")
    # A file where the killed write's bag folder was (put there by hand) is cleared too.
    (tmp_path / "out_bag.partial").mkdir()
    (tmp_path / "out_bag.partial" / "out_bag").write_text("")
    assert write_bag(bag, [frame], names, "/points", "/objects") == 1


def test_a_bag_folder_holding_another_file_is_never_replaced(tmp_path):
    """``check_bag_target`` replaces only a bag on the same topics with nothing else in its
    folder: a user's file put into a bag written before must stop the rewrite, not be deleted."""
    from indoorbev_jax.rosbag import write_bag

    frame = (10**9, "lidar", np.zeros((3, 4), np.float32), kitti.ObjectLabels.empty())
    bag = tmp_path / "out_bag"
    assert write_bag(bag, [frame], CFG.data.class_names, "/points", "/objects") == 1
    (bag / "notes.txt").write_text("mine")
    with pytest.raises(BagError, match=r"out_bag: exists .* it also holds \['notes\.txt'\]"):
        write_bag(bag, [frame, frame], CFG.data.class_names, "/points", "/objects")
    assert (bag / "notes.txt").read_text() == "mine"


def test_a_failed_bag_write_names_the_bag(tmp_path, monkeypatch):
    """sqlite3's "database or disk is full" named no file and was no OSError: a traceback."""
    import sqlite3

    from rosbags.rosbag2 import Writer

    from indoorbev_jax.rosbag import write_bag

    def full(*args, **kwargs):
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(Writer, "write", full)
    frame = (10**9, "lidar", np.zeros((3, 4), np.float32), kitti.ObjectLabels.empty())
    with pytest.raises(OSError, match=r"full_bag: cannot write the bag \(OperationalError"):
        write_bag(tmp_path / "full_bag", [frame], CFG.data.class_names, "/points", "/objects")
    assert not (tmp_path / "full_bag").exists()
    # Its temporary folder goes too: it kept the full disk's space until a rerun.
    assert not (tmp_path / "full_bag.partial").exists()


def _cloud(fields, dtype, points, bigendian=False):
    """A PointCloud2 with a structured numpy layout."""
    ts = typestore()
    t = ts.types
    pf = t["sensor_msgs/msg/PointField"]
    # The datatypes as sensor_msgs/PointField defines them (not our reader's table).
    codes = {"f4": pf.FLOAT32, "f8": pf.FLOAT64, "u2": pf.UINT16, "u1": pf.UINT8, "i1": pf.INT8}
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
    # Ouster/Livox drivers name intensity "reflectivity"; with both fields, "intensity" wins.
    src["reflectivity"] = rng.integers(0, 255, n)
    d5 = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("reflectivity", "<u2")])
    got = pointcloud2_to_points(_cloud(["x", "y", "z", "reflectivity"], d5, src))
    np.testing.assert_array_equal(got[:, :3], expected[:, :3])
    np.testing.assert_array_equal(got[:, 3], src["reflectivity"])
    d6 = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("reflectivity", "<u2"),
                   ("intensity", "<f4")])  # fmt: skip
    got = pointcloud2_to_points(_cloud(["x", "y", "z", "reflectivity", "intensity"], d6, src))
    np.testing.assert_array_equal(got, expected)
    # One-byte fields: a uint8 intensity of 0-254 and int8 coordinates of either sign. A
    # mutation audit: INT8 and UINT8 swapped (intensity 150 read as -106) passed.
    small = {"x": rng.integers(-128, 128, n), "y": rng.integers(-128, 128, n),
             "z": rng.integers(-128, 128, n), "intensity": np.arange(n) * 5}  # fmt: skip
    d7 = np.dtype([("x", "i1"), ("y", "i1"), ("z", "i1"), ("intensity", "u1")])
    got = pointcloud2_to_points(_cloud(["x", "y", "z", "intensity"], d7, small))
    want = np.stack([small[k] for k in ("x", "y", "z", "intensity")], 1).astype(np.float32)
    assert (want[:, :3] < 0).any() and want[:, 3].max() > 127
    np.testing.assert_array_equal(got, want)
    with pytest.raises(BagError, match=r"lacks field\(s\) \['z'\]"):
        d4 = np.dtype([("x", "<f4"), ("y", "<f4")])
        pointcloud2_to_points(_cloud(["x", "y"], d4, src))
    # A field named twice (x at 0 and again at 12): the last one silently won, x read from
    # the other field's bytes. Refused, as the PCD reader refuses FIELDS x y z x.
    d8 = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    twice = _cloud(["x", "y", "z", "intensity"], d8, src)
    twice.fields[3].name = "x"
    with pytest.raises(
        BagError, match=r"names field\(s\) \['x'\] more than once: \['x', 'y', 'z', 'x'\]"
    ):
        pointcloud2_to_points(twice, "scan")


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
    with pytest.raises(ValueError, match=r"expected a \.bin, \.pcd or \.npy file, a folder"):
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


def test_clouds_of_three_or_five_columns_are_read_by_column(model_file):
    """Predictor reshaped its input to [-1, 4]: an open3d [N, 3] cloud was read as groups
    of four numbers (other points, other objects) without an error."""
    config, params = P.load_model(model_file)
    predictor = P.Predictor(config, params, "unit")
    cloud = _scans(1, seed=9, points=400)[0]
    with_zero = cloud.copy()
    with_zero[:, 3] = 0.0
    ring = np.concatenate([cloud, np.full((400, 1), 7.0, np.float32)], axis=1)
    for given, same_as in ((cloud[:, :3], with_zero), (ring, cloud)):
        got, want = predictor(given), predictor(same_as)
        np.testing.assert_array_equal(got[0], want[0])  # the points the model saw
        np.testing.assert_array_equal(got[2].logits, want[2].logits)
    for bad in (cloud.ravel(), cloud[:, :2], cloud.astype(str)):
        with pytest.raises(ValueError, match=r"points: expected a numeric array \[N, 3\] or"):
            predictor(bad)
    # Channels-first, as nuScenes and torch keep clouds: read as 3-5 points, it found nothing.
    for channels in (3, 4, 5):
        first = np.c_[cloud, np.zeros(400, np.float32)][:, :channels].T
        with pytest.raises(ValueError, match=rf"shape \[{channels}, 400\] looks channels-first"):
            predictor(first)


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


def test_an_absurd_intensity_neither_switches_units_nor_passes_as_valid(model_file):
    """One point at intensity 1e25 picked Livox units for the frame and, under "auto", every
    later one; clipped to 1, it then passed pad_points' intensity rule as a valid point."""
    config, params = P.load_model(model_file)
    predictor = P.Predictor(config, params)
    cloud = _scans(1, seed=4, points=300)[0]  # intensities in [0, 1]
    loud = cloud.copy()
    loud[0, 3] = 1e25
    _, valid, counts = predictor.prepare(loud)
    assert predictor.last_intensity_factor == 1.0
    assert counts["nonfinite_points"] == 1 and np.isfinite(cloud).all()
    assert valid.sum() == predictor.prepare(cloud)[1].sum() - 1
    predictor.prepare(cloud)
    assert predictor.last_intensity_factor == 1.0  # the next clean frame keeps [0, 1] units


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
    # Refused by argparse, naming the flag (it was refused only once the model had loaded).
    for units, message in [("lux", "intensity units 'lux'"), ("-1", "intensity factor -1.0")]:
        with pytest.raises(SystemExit) as refused:
            cli_main([*args, "--intensity", units])
        assert refused.value.code == 2
        assert f"argument --intensity: {message}" in capsys.readouterr().err


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


def test_head_boxes_have_their_yaw_wrapped():
    """to_labels documents "Yaw is wrapped to [-pi, pi) either way": the head's yaw is an
    unbounded Dense output, and a raw 4.0 rad must come out as 4 - 2 pi = -2.2831853 (ROS
    detections publish labels.yaw as it is). Guards against passing the head's yaw through
    unwrapped. Pure function: no model."""
    final = types.SimpleNamespace(
        dims=np.array([[1.0, 0.5, 0.8]]), pos=np.array([[1.0, 2.0, 0.4]]), yaw=np.array([[4.0]])
    )
    output = types.SimpleNamespace(
        segment_valid=np.array([True]),
        det_classes=np.array([1]),
        det_scores=np.array([0.9]),
        instance_ids=np.array([[0, 1], [1, 1]]),
    )
    labels, _ = P.to_labels(final, output, "head")
    np.testing.assert_allclose(labels.yaw, [4.0 - 2 * np.pi], atol=1e-6)


def test_a_resumed_frame_needs_every_label_lines_mask_id(tmp_path):
    """_damaged_outputs keeps an earlier run's frame only when its mask ids are exactly
    1..(label lines): with 2 label lines and only id 1 in the mask (object 2's cells lost)
    the frame is damaged and predicted again; with ids 1 and 2 it is kept. Guards against a
    subset check (ids within 1..n) that keeps the frame with an object missing."""
    labels = kitti.ObjectLabels(
        [1, 2], [[1, 1, 1], [1, 1, 1]], [[1, 1, 0.5], [2, 2, 0.5]], [0, 0], [0, 0], [0.9, 0.8]
    )
    kitti.write_labels(tmp_path / "l.txt", labels, CFG.data.class_names)
    ids = np.zeros(CFG.grid.shape, np.int32)
    ids[0, 0] = 1
    kitti.write_mask(tmp_path / "m.png", ids)
    assert P._damaged_outputs(tmp_path / "l.txt", tmp_path / "m.png", None, CFG) is not None
    ids[0, 1] = 2
    kitti.write_mask(tmp_path / "m.png", ids)
    assert P._damaged_outputs(tmp_path / "l.txt", tmp_path / "m.png", None, CFG) is None


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
    assert P.with_thresholds(config, views="mirror_y") == one  # not its letters
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


def test_predict_boxes_come_from_the_masks_or_the_head(model_file, tmp_path, capsys):
    """``--boxes mask`` (the default) writes the rectangles fitted to the output segments,
    ``--boxes head`` the regressed boxes; z and height are the head's in both, and the
    choice is part of the run (no resuming into another's outputs)."""
    from indoorbev_jax.boxes import segment_boxes

    config, params = P.load_model(model_file)
    cloud = _scans(1, seed=9, points=800)[0]
    _, _, final, output, _ = P.Predictor(config, params)(cloud)
    queries = np.flatnonzero(output.segment_valid)
    assert len(queries) > 0
    kitti.write_points(tmp_path / "scan.bin", cloud)
    written = {}
    for boxes in ("mask", "head"):
        out = tmp_path / boxes
        argv = ["predict", str(model_file), str(tmp_path / "scan.bin"), "--out", str(out),
                "--no-pictures"] + (["--boxes", "head"] if boxes == "head" else [])  # fmt: skip
        assert cli_main(argv) == 0
        written[boxes] = kitti.read_labels(out / "label_2" / "scan.txt", config.data)
        assert json.loads((out / "predict.json").read_text())["boxes"] == boxes
    fits = segment_boxes(output.instance_ids, queries + 1, config.grid)
    head = np.concatenate([final.pos[queries, :2], np.abs(final.dims[queries, :2]),
                           final.yaw[queries]], 1)  # fmt: skip
    for boxes, expected in (("mask", fits), ("head", head)):
        got = written[boxes].boxes_bev()
        np.testing.assert_allclose(got[:, :4], expected[:, :4], atol=2e-3)
        turn = (got[:, 4] - expected[:, 4] + np.pi) % (2 * np.pi) - np.pi  # labels wrap yaw
        np.testing.assert_allclose(turn, 0.0, atol=2e-3)
        np.testing.assert_allclose(written[boxes].pos[:, 2], final.pos[queries, 2], atol=2e-3)
        np.testing.assert_allclose(written[boxes].dims[:, 2], np.abs(final.dims[queries, 2]),
                                   atol=2e-3)  # fmt: skip
    capsys.readouterr()
    with pytest.raises(ValueError, match=r"another run \(boxes: 'head' -> 'mask'"):
        P.predict(model_file, tmp_path / "scan.bin", tmp_path / "head", verbose=False)
    # A run from before predict.json recorded "boxes" wrote the head's: it resumes as such.
    manifest = tmp_path / "head" / "predict.json"
    record = json.loads(manifest.read_text())
    manifest.write_text(json.dumps({k: v for k, v in record.items() if k != "boxes"}))
    with pytest.raises(ValueError, match=r"another run \(boxes: 'head' -> 'mask'"):
        P.predict(model_file, tmp_path / "scan.bin", tmp_path / "head", verbose=False)
    summary = P.predict(model_file, tmp_path / "scan.bin", tmp_path / "head", verbose=False,
                        boxes="head", pictures=False)  # fmt: skip
    assert summary["resumed_frames"] == 1
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["predict", str(model_file), str(tmp_path / "scan.bin"), "--out",
                  str(tmp_path / "x"), "--boxes", "fit"])  # fmt: skip
    assert exit_info.value.code == 2 and "invalid choice: 'fit'" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"boxes: expected one of \('head', 'mask'\)"):
        P.predict(model_file, tmp_path / "scan.bin", tmp_path / "y", boxes="fit")


# Bags, resuming and bad input -------------------------------------------------------------


def _cloud_bag(path, clouds, log_ns, stamp_ns, topic="/cloud"):
    """A rosbag2 folder of float32 x, y, z, intensity PointCloud2, one message per cloud,
    recorded at ``log_ns`` with header stamps ``stamp_ns``."""
    from rosbags.rosbag2 import Writer

    from indoorbev_jax.rosbag import POINTCLOUD2, cloud_msg

    ts = typestore()
    with Writer(path, version=8) as writer:
        conn = writer.add_connection(topic, POINTCLOUD2, typestore=ts)
        for cloud, log, stamp in zip(clouds, log_ns, stamp_ns, strict=True):
            msg = cloud_msg(ts, cloud, stamp, "os")
            writer.write(conn, log, ts.serialize_cdr(msg, POINTCLOUD2))


def _scans(n, seed=5, points=400):
    rng = np.random.default_rng(seed)
    scans = rng.uniform(-3.0, 3.0, (n, points, 4)).astype(np.float32)
    scans[..., 2:] = rng.uniform(0.0, 1.0, (n, points, 2))
    return list(scans)


def _bag_messages(bag, topic):
    """[(record ns, header stamp ns, message)] of one topic."""
    from rosbags.rosbag2 import Reader

    ts = typestore()
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        out = []
        for conn, log, raw in reader.messages(connections=conns):
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            # A MarkerArray's stamp is its markers' (all the same); None when it has none.
            hdr = msg.markers[0].header if hasattr(msg, "markers") and msg.markers else None
            hdr = getattr(msg, "header", hdr)
            stamp = None if hdr is None else hdr.stamp.sec * 10**9 + hdr.stamp.nanosec
            out.append((log, stamp, msg))
        return out


def test_timeless_clouds_are_logged_at_10_hz_and_sparse_ones_not_thinned(
    model_file, tmp_path, capsys
):
    """Clouds without times (.bin files) go into --bag-out at 10 Hz, the k-th (from 1) at
    k x 0.1 s: 100 and 200 ms for two files. Two 400-point clouds are far below
    data.max_points, so no frame counts as thinned and the closing "more valid points than
    data.max_points" line is not printed. Guards against logging the first frame at 0 and
    against counting every frame as thinned (dropped points >= 0 always)."""
    assert CFG.data.max_points > 400
    for k, scan in enumerate(_scans(2)):
        kitti.write_points(tmp_path / "in" / f"{k:06d}.bin", scan)
    summary = P.predict(
        model_file, tmp_path / "in", tmp_path / "o", bag_out=tmp_path / "bag", pictures=False
    )
    assert summary["frames"] == 2 and summary["thinned_frames"] == 0
    assert "more valid points than" not in capsys.readouterr().out
    from rosbags.rosbag2 import Reader

    with Reader(tmp_path / "bag") as reader:
        times = sorted({t for _, t, _ in reader.messages()})
    assert times == [100_000_000, 200_000_000]


def test_organized_cloud_with_padded_rows_reads_each_point_once():
    rng = np.random.default_rng(6)
    height, width, pad = 3, 5, 12
    pts = rng.normal(size=(height, width, 4)).astype("<f4")
    rows = np.full((height, width * 16 + pad), 0xEE, np.uint8)  # padding holds garbage
    rows[:, : width * 16] = pts.view(np.uint8).reshape(height, -1)
    ts = typestore()
    msg = ts.types["sensor_msgs/msg/PointCloud2"](
        header=ts.types["std_msgs/msg/Header"](
            stamp=ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="l"),
        height=height, width=width,
        fields=[ts.types["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
                for i, n in enumerate("xyz")],
        is_bigendian=False, point_step=16, row_step=width * 16 + pad,
        data=rows.reshape(-1)[:-pad],  # the last row may end without its padding
        is_dense=True,
    )  # fmt: skip
    got = pointcloud2_to_points(msg)
    np.testing.assert_array_equal(got[:, :3], pts[..., :3].reshape(-1, 3))
    msg.row_step = width * 16 - 1
    with pytest.raises(BagError, match="row_step 79 is less than width 5 x point_step 16"):
        pointcloud2_to_points(msg, "scan")
    # A single row is read from byte 0 whatever row_step says (it was refused when 0).
    one_row = copy.copy(msg)
    one_row.height, one_row.row_step = 1, 0
    np.testing.assert_array_equal(pointcloud2_to_points(one_row)[:, :3], pts[0, :, :3])
    msg.row_step, msg.fields[2].offset = width * 16 + pad, 14
    with pytest.raises(BagError, match=r"scan: field 'z' \(4 bytes at offset 14\) runs past"):
        pointcloud2_to_points(msg, "scan")
    # point_step 0 asks for no bytes at all: the field check must come before any size.
    msg.fields[2].offset, msg.point_step, msg.row_step = 8, 0, 0
    msg.width = msg.height = 2**32 - 1
    with pytest.raises(
        BagError, match=r"scan: field 'x' \(4 bytes at offset 0\) runs past point_step 0"
    ):
        pointcloud2_to_points(msg, "scan")


def test_livox_cdr_decoder_equals_rosbags(tmp_path):
    from indoorbev_jax.rosbag import livox_custom_from_cdr, livox_custom_to_points

    rng = np.random.default_rng(7)
    for n in (0, 1, 257):
        cloud = rng.uniform(-5, 5, (n, 4)).astype(np.float32)
        cloud[:, 3] = rng.integers(0, 256, n)
        _livox_bag(tmp_path / f"b{n}", [cloud])
        raw = _first_raw(tmp_path / f"b{n}")
        ts = typestore()
        msg = ts.deserialize_cdr(raw, LIVOX_CUSTOM)
        for data in (raw, ts.serialize_cdr(msg, LIVOX_CUSTOM, little_endian=False)):
            stamp, frame, got = livox_custom_from_cdr(data)
            assert (stamp, frame) == (10**8, "livox_frame")
            np.testing.assert_array_equal(got, livox_custom_to_points(msg))
            np.testing.assert_array_equal(got, cloud)
    with pytest.raises(BagError, match=r"m@3: cannot read a Livox CustomMsg: .* 257 points"):
        livox_custom_from_cdr(raw[:-30], "m@3")


def test_corrupt_bag_names_the_frame_and_skips_it_when_asked(model_file, tmp_path, capsys):
    import sqlite3

    scans = _scans(3)
    bag = tmp_path / "in"
    _cloud_bag(bag, scans, [10**9, 2 * 10**9, 3 * 10**9], [5, 6, 7])
    with sqlite3.connect(bag / "in.db3") as db:  # cut the second message short
        where = ("where timestamp = ?", (2 * 10**9,))
        (data,) = db.execute(f"select data from messages {where[0]}", where[1]).fetchone()
        db.execute(f"update messages set data = ? {where[0]}", (data[:40], *where[1]))
    with pytest.raises(BagError, match=r"in frame 000001 \(recorded at 2000000000 ns\): cannot "
                       r"decode .*--skip-bad-frames skips it"):  # fmt: skip
        P.predict(model_file, bag, tmp_path / "o", pictures=False, verbose=False)
    args = ["predict", str(model_file), str(bag), "--out", str(tmp_path / "o"), "--no-pictures"]
    assert cli_main([*args, "--skip-bad-frames"]) == 0
    captured = capsys.readouterr()
    assert "[2/3] 000001: skipped:" in captured.err
    assert "1 unreadable frames skipped: 000001" in captured.out
    assert sorted(p.name for p in (tmp_path / "o" / "label_2").iterdir()) == [
        "000000.txt", "000002.txt"]  # fmt: skip
    # A storage file that cannot be opened is named, without a traceback.
    db3 = (bag / "in.db3").read_bytes()
    (bag / "in.db3").write_bytes(db3[: len(db3) // 2])
    assert cli_main(args) == 2
    assert f"{bag}: not a readable ROS 2 bag" in capsys.readouterr().err


def test_bag_out_keeps_stamps_and_never_replaces_other_folders(model_file, tmp_path):
    scans = _scans(2)
    bag = tmp_path / "in"
    _cloud_bag(bag, scans, [10**9, 2 * 10**9], [123, 10**9 + 456])
    # iter_frames' stamp is the header's (it gave the record time).
    assert [f[2] for f in P.iter_frames(bag)] == [123, 10**9 + 456]
    out, pred_bag = tmp_path / "o", tmp_path / "pred"
    run = dict(pictures=False, verbose=False)
    P.predict(model_file, bag, out, bag_out=pred_bag, **run)
    clouds = _bag_messages(pred_bag, "/points")
    assert [(log, stamp) for log, stamp, _ in clouds] == [(10**9, 123), (2 * 10**9, 10**9 + 456)]
    assert {m.header.frame_id for *_, m in clouds} == {"os"}
    for (*_, m), scan in zip(clouds, scans, strict=True):
        np.testing.assert_array_equal(pointcloud2_to_points(m), scan)
    markers = _bag_messages(pred_bag, "/detections")
    assert all(m.markers for *_, m in markers)  # thresholds at 0: each frame has detections
    assert [(log, stamp) for log, stamp, _ in markers] == [(10**9, 123), (2 * 10**9, 10**9 + 456)]
    # The bag's detections are the label files' (the same run again resumes, and rewrites it).
    from indoorbev_jax.rosbag import markers_to_labels

    P.predict(model_file, bag, out, bag_out=pred_bag, **run)
    for k, (*_, m) in enumerate(_bag_messages(pred_bag, "/detections")):
        want = kitti.read_labels(out / "label_2" / f"{k:06d}.txt", CFG.data)
        got = markers_to_labels(m, CFG.data)
        np.testing.assert_allclose(got.pos, want.pos, atol=1e-6)
        np.testing.assert_allclose(got.scores, want.scores, atol=5e-4 + 1e-6)  # text: 3 decimals
    # Folders that are not such a bag are left alone.
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    other = tmp_path / "other"
    _cloud_bag(other, scans[:1], [1], [1])
    for target, match in ((mine, "mine: exists and is not a bag written on topics"),
                          (other, "other: exists and is not a bag .* topics are \\['/cloud'\\]"),
                          (out, "would replace --out"), (bag, "would replace INPUT"),
                          (bag / "sub", "lies inside the INPUT bag"),
                          (tmp_path, "would replace INPUT")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            P.predict(model_file, bag, out, bag_out=target, **run)
    assert (mine / "notes.txt").read_text() == "keep me"
    assert len(_bag_messages(bag, "/cloud")) == 2 and len(_bag_messages(other, "/cloud")) == 1


def test_predict_resumes_and_refuses_another_runs_outputs(model_file, tmp_path, capsys):
    data = tmp_path / "data"
    for k, scan in enumerate(_scans(3)):
        kitti.write_points(data / "velodyne" / f"{k:06d}.bin", scan)
    out = tmp_path / "o"
    first = P.predict(model_file, data, out)
    printed = capsys.readouterr().out
    assert "[1/3] 000000:" in printed and "[3/3] 000002:" in printed and "ETA 0:" in printed
    files = {p.relative_to(out): p.read_bytes() for p in out.rglob("*.*")}
    # A kill between frames: frame 1 lost its label, frame 2 its picture.
    (out / "label_2" / "000001.txt").unlink()
    (out / "pictures" / "000002.png").unlink()
    # ... and a kill -9 inside atomic_write left its hidden temporary file: removed, a
    # minute old at the start; one killed 30 s before this run (kept then: it could be a
    # write in flight) once the run is done, as export does. A user's hidden file stays.
    stale = out / "mask_2" / ".000001.png.x8k2j3_a.tmp"
    fresh = out / "label_2" / ".000001.txt.k3j4k5l6.tmp"
    keep = out / "label_2" / ".notes.tmp"
    for path in (stale, fresh, keep):
        path.write_bytes(b"\x89PNG")
    os.utime(stale, (time.time() - 120,) * 2)
    os.utime(fresh, (time.time() - 30,) * 2)
    os.utime(keep, (time.time() - 120,) * 2)
    again = P.predict(model_file, data, out, verbose=False)
    assert not stale.exists() and not fresh.exists() and keep.exists()
    keep.unlink()
    assert again["resumed_frames"] == 1 and again["objects"] == first["objects"]
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*.*")} == files
    assert not list(out.rglob("*.tmp"))
    # A second run into this --out while one runs is refused, naming it: both wrote every
    # frame, and with --overwrite the second deleted the first's outputs as it wrote them.
    with open(out / ".lock", "w") as other:  # the first run, as its lock shows it
        fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
        other.write("pid 4242\n")
        other.flush()
        with pytest.raises(ValueError, match=r"o: in use by another predict run \(pid 4242\)"):
            P.predict(model_file, data, out, verbose=False, overwrite=True)
    files[Path(".lock")] = b"pid 4242\n"
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*.*")} == files
    # Another run's settings, or label files of unknown origin, are not mixed in.
    with pytest.raises(ValueError, match=r"another run \(views: \['identity'\] -> \['mirror_x'\]"):
        P.predict(model_file, data, out, views=("mirror_x",), verbose=False)
    # A run stopped before its first frame left only predict.json: a run with other
    # settings takes the folder (it was refused, asking for --overwrite).
    early = tmp_path / "early"
    early.mkdir()
    (early / "predict.json").write_text((out / "predict.json").read_text())
    P.predict(model_file, data, early, views=("mirror_x",), pictures=False, verbose=False)
    assert json.loads((early / "predict.json").read_text())["views"] == ["mirror_x"]
    # ... but another tool's predict.json, or an unreadable one, is not replaced unasked.
    for text in ('{"detector": "other"}', "not json", '[{"image_id": 0}]'):  # a list: COCO
        (early / "predict.json").write_text(text)
        for d in ("label_2", "mask_2"):
            shutil.rmtree(early / d, ignore_errors=True)
        with pytest.raises(ValueError, match="holds the predictions of another run"):
            P.predict(model_file, data, early, pictures=False, verbose=False)
        assert (early / "predict.json").read_text() == text
    stale = tmp_path / "stale"
    kitti.write_labels(stale / "label_2" / "009999.txt", kitti.read_labels(
        out / "label_2" / "000000.txt", CFG.data), CFG.data.class_names)  # fmt: skip
    with pytest.raises(ValueError, match=r"stale already holds 1 label, mask or picture files"):
        P.predict(model_file, data, stale, verbose=False)
    assert not (stale / ".lock").exists()  # refused before the lock: nothing left in it
    with pytest.raises(ValueError, match=r"--out .*data is INPUT"):
        P.predict(model_file, data, data, verbose=False, overwrite=True)
    P.predict(model_file, data, stale, pictures=False, verbose=False, overwrite=True)
    assert sorted(p.stem for p in (stale / "label_2").iterdir()) == ["000000", "000001", "000002"]


def test_a_resumed_run_predicts_damaged_frames_again(model_file, tmp_path, capsys):
    """A frame counted as done when its files existed: an emptied label file was kept as a
    frame without objects, and a cut mask failed only later, in `indoorbev eval`."""
    data = tmp_path / "data"
    for k, scan in enumerate(_scans(3)):
        kitti.write_points(data / "velodyne" / f"{k:06d}.bin", scan)
    out = tmp_path / "o"
    first = P.predict(model_file, data, out, verbose=False)
    files = {p.relative_to(out): p.read_bytes() for p in out.rglob("*.*")}
    labels = [kitti.read_labels(out / "label_2" / f"{k:06d}.txt", CFG.data) for k in range(3)]
    emptied = next(k for k in range(3) if len(labels[k]))
    (out / "label_2" / f"{emptied:06d}.txt").write_text("")
    cut = (emptied + 1) % 3
    mask = out / "mask_2" / f"{cut:06d}.png"
    mask.write_bytes(mask.read_bytes()[:40])
    (out / "pictures" / f"{(emptied + 2) % 3:06d}.png").write_bytes(b"")
    capsys.readouterr()
    again = P.predict(model_file, data, out, verbose=False)
    said = capsys.readouterr().err
    assert again["resumed_frames"] == 0 and again["objects"] == first["objects"]
    assert "holds ids [1" in said and f"{emptied:06d}.txt has 0 lines; predicting it again" in said
    assert f"{mask}: not a readable PNG" in said
    assert f"{(emptied + 2) % 3:06d}.png: not a readable PNG" in said
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*.*")} == files


def test_a_kitti_folder_reads_every_cloud_kind_in_velodyne(model_file, tmp_path):
    """velodyne/ was globbed for lowercase *.bin only: a .BIN, .pcd or .npy gave "no frames
    found", while the same files in a plain folder were read."""
    scans = _scans(3)
    velodyne = tmp_path / "k" / "velodyne"
    kitti.write_points(velodyne / "000000.BIN", scans[0])
    np.save(velodyne / "000001.npy", scans[1])
    kitti.write_points(tmp_path / "plain" / "000000.bin", scans[0])
    np.save(tmp_path / "plain" / "000001.npy", scans[1])
    got = P.predict(model_file, tmp_path / "k", tmp_path / "o1", pictures=False, verbose=False)
    want = P.predict(model_file, tmp_path / "plain", tmp_path / "o2", pictures=False, verbose=False)
    assert got["frames"] == want["frames"] == 2
    for k in ("000000", "000001"):
        a, b = tmp_path / "o1" / "label_2" / f"{k}.txt", tmp_path / "o2" / "label_2" / f"{k}.txt"
        assert a.read_bytes() == b.read_bytes()
    empty = tmp_path / "e" / "velodyne"
    empty.mkdir(parents=True)
    with pytest.raises(ValueError, match=r"e/velodyne: no \.bin, \.pcd, \.npy cloud files"):
        P.predict(model_file, tmp_path / "e", tmp_path / "o3", verbose=False)


def test_input_errors_name_the_path_and_empty_clouds_are_said(model_file, tmp_path, capsys):
    with pytest.raises(FileNotFoundError, match=r"nowhere: no such file or folder"):
        P.predict(model_file, tmp_path / "nowhere", tmp_path / "o", verbose=False)
    kitti.write_points(tmp_path / "scan.bin", _scans(1)[0])
    with pytest.raises(ValueError, match=r"scan\.bin: --topic /x applies to ROS 2 bag input"):
        P.predict(model_file, tmp_path / "scan.bin", tmp_path / "o", topic="/x", verbose=False)
    bag = tmp_path / "bag"
    _cloud_bag(bag, _scans(1), [1], [1])
    for topic in (None, "/cloud"):  # the advice, not "--topic applies to bags only"
        with pytest.raises(ValueError, match=r"bag\.db3: a storage file of the bag .*bag; pass"):
            P.predict(model_file, bag / "bag.db3", tmp_path / "o", topic=topic, verbose=False)
    with pytest.raises(BagError, match=r"no topic '/x'; topics: \['/cloud \(sensor_msgs/msg/Po"):
        P.predict(model_file, bag, tmp_path / "o", topic="/x", verbose=False)
    far = np.full((50, 4), 1e3, np.float32)
    far[:10] = np.nan
    far[10:15] = 0.0  # a driver's "no return" points
    kitti.write_points(tmp_path / "far.bin", far)
    summary = P.predict(model_file, tmp_path / "far.bin", tmp_path / "o", pictures=False)
    assert summary["empty_frames"] == ["far"]
    printed = capsys.readouterr().out
    # One frame, the one that compiles: no latency to give (it would be the compile time).
    assert "latency_ms" not in summary and "ms/frame" not in printed
    assert (
        "none of its 50 points is valid (10 non-finite, 5 within sim.min_range=0.1 m of the "
        "sensor, 35 outside the workspace x [" in printed
    )


def test_driver_no_return_points_leave_the_prediction_unchanged(model_file):
    """Livox drivers write a pulse with no return as (0, 0, 0), inside the workspace; the
    simulator never returns a point that close (sim.min_range), so such points are invalid
    and the cloud is read as if they were not there."""
    config, params = P.load_model(model_file)
    predictor = P.Predictor(config, params)
    scan = _scans(1)[0]
    scan = scan[np.linalg.norm(scan[:, :3], axis=1) > 0.2]
    with_zeros = np.insert(scan, np.arange(0, len(scan), 3), 0.0, axis=0)
    with_zeros[0, :3] = (0.03, 0.04, 0.0)  # 5 cm: inside the 0.1 m blind zone too
    padded, valid, counts = predictor.prepare(with_zeros)
    assert counts["blind_points"] == len(with_zeros) - len(scan)
    np.testing.assert_array_equal(padded[valid], scan)
    final, output, _ = predictor.infer(padded, valid)
    clean_final, clean_output, _ = predictor.infer(*predictor.prepare(scan)[:2])
    jax.tree.map(np.testing.assert_array_equal, (final, output), (clean_final, clean_output))


def test_auto_intensity_stays_livox_once_seen(model_file):
    config, params = P.load_model(model_file)
    predictor = P.Predictor(config, params)
    livox, dark = _scans(2)
    livox[:, 3] = 200.0
    dark[:, 3] = 0.5  # a Livox scan of dark surfaces: 0.5 of 255, not 50 % reflectivity
    predictor.prepare(livox)
    padded, valid, _ = predictor.prepare(dark)
    assert predictor.last_intensity_factor == pytest.approx(1 / 150)
    np.testing.assert_allclose(padded[valid, 3], 0.5 / 150, rtol=1e-6)
    fresh = P.Predictor(config, params)
    fresh.prepare(dark)
    assert fresh.last_intensity_factor == 1.0


def test_auto_intensity_ignores_points_outside_the_workspace(model_file):
    """A garbage cloud (1e30 m, NaN) with high intensities must not switch "auto" to
    Livox units for the real frames after it: only the workspace's points count."""
    config, params = P.load_model(model_file)
    predictor = P.Predictor(config, params)
    (unit,) = _scans(1)
    garbage = np.full((50, 4), 1e30, np.float32)
    garbage[:10, :3] = np.nan
    garbage[:, 3] = 200.0
    predictor.prepare(garbage)
    padded, valid, _ = predictor.prepare(unit)
    assert predictor.last_intensity_factor == 1.0
    np.testing.assert_allclose(padded[valid, 3], unit[valid[: len(unit)], 3][: valid.sum()])
    far = unit.copy()
    far[:5, :3] = (40.0, 0.0, 0.0)  # outside the workspace, beside the valid points
    far[:5, 3] = 200.0
    predictor.prepare(far)
    assert predictor.last_intensity_factor == 1.0


def test_input_listing_skips_hidden_files_and_reads_upper_case_bin(tmp_path):
    """macOS ``._<id>.bin`` metadata next to a scan is not a frame (its bytes once read as a
    cloud with intensity > 1 switched "auto" intensity for the real frames); SCAN.BIN is a
    scan."""
    scans = _scans(2)
    for name, scan in zip(("000000", "000001"), scans, strict=True):
        kitti.write_points(tmp_path / "kitti" / "velodyne" / f"{name}.bin", scan)
    (tmp_path / "kitti" / "velodyne" / "._000000.bin").write_bytes(b"\0\5\26\7" * 1024)
    count, frames = P.open_input(tmp_path / "kitti")
    assert count == 2 and [f.frame_id for f in frames] == ["000000", "000001"]
    # Entries named like clouds that are no file are bad frames, named: a dangling symlink
    # (a scan on an unmounted disk) or a folder was left out without a word.
    (tmp_path / "kitti" / "velodyne" / "000002.bin").symlink_to(tmp_path / "unmounted.bin")
    (tmp_path / "kitti" / "velodyne" / "000003.pcd").mkdir()
    os.mkfifo(tmp_path / "kitti" / "velodyne" / "000004.npy")  # read, it would block
    count, frames = P.open_input(tmp_path / "kitti")
    frames = list(frames)
    assert count == 5 and [f.frame_id for f in frames] == [f"{k:06d}" for k in range(5)]
    assert [f.error is None for f in frames] == [True, True, False, False, False]
    assert str(frames[4].error).endswith("000004.npy: a pipe, socket or device, not a cloud file")
    assert re.fullmatch(r".*000002\.bin: a broken or looping symlink, not a cloud file",
                        str(frames[2].error))  # fmt: skip
    assert re.fullmatch(r".*000003\.pcd: a folder, not a cloud file", str(frames[3].error))
    kitti.write_points(tmp_path / "SCAN.BIN", scans[0])
    count, frames = P.open_input(tmp_path / "SCAN.BIN")
    (frame,) = list(frames)
    assert count == 1 and frame.frame_id == "SCAN"
    np.testing.assert_array_equal(frame.points, scans[0])


def test_lone_storage_file_reads_as_its_bag(model_file, tmp_path):
    """A .db3 / .mcap without metadata.yaml beside it (a Foxglove recording, a killed
    recording recovered) is read as the bag it holds, frame for frame."""
    scans = _scans(2)
    bag = tmp_path / "bag"
    _cloud_bag(bag, scans, [1, 2], [1, 2])
    lone = tmp_path / "lone.db3"
    lone.write_bytes((bag / "bag.db3").read_bytes())
    count, frames = P.open_input(lone)
    got = list(frames)
    assert count == 2 and [f.frame_id for f in got] == ["000000", "000001"]
    for frame, scan in zip(got, scans, strict=True):
        np.testing.assert_array_equal(frame.points, scan)
    run = dict(pictures=False, verbose=False)
    P.predict(model_file, bag, tmp_path / "a", **run)
    P.predict(model_file, lone, tmp_path / "b", topic="/cloud", **run)
    for k in range(2):
        name = f"label_2/{k:06d}.txt"
        assert (tmp_path / "a" / name).read_text() == (tmp_path / "b" / name).read_text()
    # A lone file that is no bag is named, before any frame.
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file")
    with pytest.raises(BagError, match=r"junk\.mcap: not a readable ROS 2 bag"):
        P.predict(model_file, junk, tmp_path / "c", **run)
    assert not (tmp_path / "c" / "label_2").exists()


def test_topic_with_a_second_message_type_reads_its_clouds_only(tmp_path):
    """A topic that also carries another type (two connections) yields its clouds; before,
    the first non-cloud message ended the run with an AttributeError."""
    from rosbags.rosbag2 import Writer

    from indoorbev_jax.rosbag import POINTCLOUD2, cloud_msg, iter_clouds

    ts = typestore()
    scans = _scans(2)
    bag = tmp_path / "mixed"
    with Writer(bag, version=8) as writer:
        clouds = writer.add_connection("/livox/lidar", POINTCLOUD2, typestore=ts)
        string = ts.types["std_msgs/msg/String"]
        other = writer.add_connection("/livox/lidar", "std_msgs/msg/String", typestore=ts)
        writer.write(clouds, 1, ts.serialize_cdr(cloud_msg(ts, scans[0], 1, "os"), POINTCLOUD2))
        writer.write(other, 2, ts.serialize_cdr(string(data="hi"), "std_msgs/msg/String"))
        writer.write(clouds, 3, ts.serialize_cdr(cloud_msg(ts, scans[1], 3, "os"), POINTCLOUD2))
    got = list(iter_clouds(bag, "/livox/lidar"))
    assert [c.error for c in got] == [None, None] and [c.log_ns for c in got] == [1, 3]
    for cloud, scan in zip(got, scans, strict=True):
        np.testing.assert_array_equal(cloud.points, scan)
    with pytest.raises(BagError, match=r"topic '/s' is std_msgs/msg/String, not one of"):
        only = tmp_path / "only"
        with Writer(only, version=8) as writer:
            conn = writer.add_connection("/s", "std_msgs/msg/String", typestore=ts)
            writer.write(conn, 1, ts.serialize_cdr(string(data="x"), "std_msgs/msg/String"))
        list(iter_clouds(only, "/s"))


def test_model_fingerprint_is_the_one_older_versions_gave():
    """predict.json holds the model's hash; a config field added later at its default
    (``config.LATER_FIELDS``) leaves it as it was, so runs of older versions resume. The
    value is what the version before ``sim.sensor_rpy`` (e02316c~1) printed."""
    params = {"params": {"a": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    tiny = Config.tiny()
    old = "34d8b7e6117624d2caa77e3a88186d305a786b74210643b369215e923ecb010d"
    assert P.model_fingerprint(tiny, params) == old
    tilted = dataclasses.replace(tiny, sim=dataclasses.replace(tiny.sim, sensor_rpy=(0, 5, 0)))
    assert P.model_fingerprint(tilted, params) != old
    # Each later field leaves the record at its default and only then (a mutation audit
    # found sensor_tilt_jitter checked by the hash above alone).
    for path, default in LATER_FIELDS.items():
        section, name = path.split(".")
        assert name not in tiny.stable_dict()[section] and name in tiny.to_dict()[section]
        assert getattr(getattr(tiny, section), name) == default
    jittered = dataclasses.replace(tiny, sim=dataclasses.replace(tiny.sim, sensor_tilt_jitter=3.0))
    assert jittered.stable_dict()["sim"]["sensor_tilt_jitter"] == 3.0
    assert P.model_fingerprint(jittered, params) != old


def test_a_resumed_run_reads_its_finished_frames_as_the_first_run_did(
    model_file, tmp_path, monkeypatch
):
    """A scan in Livox units, an empty one, then a dark one (every intensity <= 1, which
    "auto" reads in the units seen so far). Rerun after a kill that left the last frame
    undone, the model sees the dark scan as the uninterrupted run did (it saw it in unit
    intensities, 150x brighter), and the summary still names the empty frame done before."""
    rng = np.random.default_rng(6)
    livox, dark = rng.uniform(-3.0, 3.0, (2, 600, 4)).astype(np.float32)
    livox[:, 3] = rng.integers(0, 256, 600)
    dark[:, 3] = rng.uniform(0.0, 1.0, 600)
    for frame_id, cloud in (("000000", livox), ("000001", np.zeros((0, 4))), ("000002", dark)):
        kitti.write_points(tmp_path / "scans" / "velodyne" / f"{frame_id}.bin", cloud)
    seen = []
    infer = P.Predictor.infer
    monkeypatch.setattr(
        P.Predictor, "infer", lambda self, p, v: (seen.append(p), infer(self, p, v))[1]
    )

    def run():
        seen.clear()
        return P.predict(model_file, tmp_path / "scans", tmp_path / "o", verbose=False,
                         pictures=False)  # fmt: skip

    first = run()
    assert first["empty_frames"] == ["000001"] and len(seen) == 3
    want = seen[-1].copy()
    for folder, suffix in (("label_2", "txt"), ("mask_2", "png")):
        (tmp_path / "o" / folder / f"000002.{suffix}").unlink()
    again = run()
    assert again["resumed_frames"] == 2 and len(seen) == 1
    np.testing.assert_array_equal(seen[0], want)
    assert again["empty_frames"] == ["000001"]


def test_a_negative_roll_is_a_value_not_an_option(model_file, tmp_path, capsys):
    """argparse reads "-5,10,0" as an unknown option ("expected one argument"): the mount
    of a lidar leaning right could not be given without "=". Each command joins it."""
    from indoorbev_jax.cli import join_negative_values

    assert join_negative_values(["--lidar-rpy", "-5,10,0", "-x", "-1"]) == [
        "--lidar-rpy=-5,10,0", "-x", "-1"]  # fmt: skip
    # A fraction without its leading zero is a number too (float("-.5") == -0.5).
    assert join_negative_values(["--lidar-rpy", "-.5,0,0"]) == ["--lidar-rpy=-.5,0,0"]
    kitti.write_points(tmp_path / "scan.bin", _scans(1, seed=3, points=200)[0])
    argv = ["predict", str(model_file), str(tmp_path / "scan.bin"), "--out", str(tmp_path / "o"),
            "--no-pictures", "--lidar-rpy", "-5,10,0"]  # fmt: skip
    assert cli_main(argv) == 0
    assert "roll -5" in capsys.readouterr().out


def test_pointcloud2_intensity_field_wins_over_reflectivity():
    """An input cloud may carry ``intensity`` (or ``reflectivity``) (docs/ROBOT.md, Topics):
    an Ouster-style cloud with both, float32 intensity and uint16 reflectivity, must read
    the ``intensity`` field. A mutation audit: preferring ``reflectivity`` passed."""
    from indoorbev_jax.rosbag import POINTCLOUD2, header

    ts = typestore()
    field = ts.types["sensor_msgs/msg/PointField"]
    names, offsets = ["x", "y", "z", "intensity", "reflectivity"], [0, 4, 8, 16, 20]
    rows = np.zeros(2, {"names": names, "formats": ["<f4"] * 4 + ["<u2"], "offsets": offsets,
                        "itemsize": 24})  # fmt: skip
    rows["x"], rows["y"], rows["z"] = [1.0, 2.0], [-1.0, 0.5], [0.25, 0.75]
    rows["intensity"], rows["reflectivity"] = [0.25, 0.75], [200, 40]
    # sensor_msgs/PointField datatype constants: UINT16 = 4, FLOAT32 = 7.
    fields = [
        field(name=n, offset=o, datatype=4 if n == "reflectivity" else 7, count=1)
        for n, o in zip(names, offsets, strict=True)
    ]
    msg = ts.types[POINTCLOUD2](
        header=header(ts, 1, "os_sensor"), height=1, width=2, fields=fields,
        is_bigendian=False, point_step=24, row_step=48, data=rows.view(np.uint8).reshape(-1),
        is_dense=True,
    )  # fmt: skip
    msg = ts.deserialize_cdr(ts.serialize_cdr(msg, POINTCLOUD2), POINTCLOUD2)
    want = np.stack([rows[n] for n in ("x", "y", "z", "intensity")], 1)
    np.testing.assert_array_equal(pointcloud2_to_points(msg), want)


def test_livox_cdr_decoder_equals_rosbags_for_every_frame_id_length():
    """``livox_custom_from_cdr`` must decode what rosbags' deserializer does whatever the
    frame id: the CDR alignment of ``timebase`` (uint64, 8 bytes) after the frame id string
    depends on its length, and ``livox_frame`` (12 bytes with its NUL) aligns alike to 4
    and 8. A mutation audit: aligning ``timebase`` to 4 passed with only ``livox_frame``."""
    from indoorbev_jax.rosbag import header, livox_custom_from_cdr, livox_custom_to_points

    ts = typestore()
    t = ts.types
    cloud = np.array([[1.5, -2.0, 0.25, 100], [3.0, 1.0, -0.5, 7]], np.float32)
    points = [
        t["livox_ros_driver2/msg/CustomPoint"](
            offset_time=i, x=x, y=y, z=z, reflectivity=int(r), tag=0, line=i
        )
        for i, (x, y, z, r) in enumerate(cloud)
    ]
    stamp = 1_700_000_000_123_456_789
    for n in range(1, 13):
        frame = "livox_frame1"[:n]
        msg = t[LIVOX_CUSTOM](
            header=header(ts, stamp, frame), timebase=5, point_num=2, lidar_id=0,
            rsvd=np.zeros(3, np.uint8), points=points,
        )  # fmt: skip
        for little in (True, False):
            raw = ts.serialize_cdr(msg, LIVOX_CUSTOM, little_endian=little)
            ref = livox_custom_to_points(ts.deserialize_cdr(raw, LIVOX_CUSTOM))
            got_stamp, got_frame, got = livox_custom_from_cdr(raw)
            assert (got_stamp, got_frame) == (stamp, frame)
            np.testing.assert_array_equal(got, ref)
            np.testing.assert_array_equal(got, cloud)


def test_read_clouds_yields_the_record_time(tmp_path):
    """``read_clouds`` yields each cloud's record time, the bag's log time (``Cloud.log_ns``,
    the first item of a ``write_bag`` frame), not its header stamp: a bag written with record
    time 1 s and stamp 5 ns reads back 1 s, as ``iter_clouds`` says. A mutation audit:
    yielding the header stamp passed."""
    from indoorbev_jax.rosbag import iter_clouds, read_clouds, write_bag

    points = np.array([[1, 0, 0, 0.5]], np.float32)
    empty = kitti.ObjectLabels.empty(with_scores=True)
    frames = [(10**9, "lidar", points, empty, 5), (2 * 10**9, "lidar", points, empty, 9)]
    write_bag(tmp_path / "b", frames, CFG.data.class_names, "/points", "/objects")
    assert [(c.log_ns, c.stamp_ns) for c in iter_clouds(tmp_path / "b")] == [
        (10**9, 5), (2 * 10**9, 9)
    ]  # fmt: skip
    got = list(read_clouds(tmp_path / "b"))
    assert [(log_ns, frame) for log_ns, frame, _ in got] == [(10**9, "lidar"), (2 * 10**9, "lidar")]
    np.testing.assert_array_equal(got[0][2], points)


def test_the_summary_latencies_are_the_median_p90_and_max_of_the_timed_frames(
    model_file, tmp_path, monkeypatch
):
    """``latency_ms`` holds the median, 90th percentile and maximum of each frame's model
    time, the first (compiling) frame left out. A clock that moves only while the model
    runs gives frames of 50 (first), 1, 2, 3 and 4 ms. A mutation audit: p90 computed as
    the median passed."""
    clock, durations = [0.0], iter([50.0, 1.0, 2.0, 3.0, 4.0])
    infer = P.Predictor.infer

    def timed_infer(self, padded, valid):
        out = infer(self, padded, valid)
        clock[0] += next(durations) / 1e3
        return out

    monkeypatch.setattr(P.Predictor, "infer", timed_infer)
    monkeypatch.setattr(
        P, "time", types.SimpleNamespace(time=time.time, perf_counter=lambda: clock[0])
    )
    for k, scan in enumerate(_scans(5)):
        kitti.write_points(tmp_path / "in" / f"{k:06d}.bin", scan)
    summary = P.predict(model_file, tmp_path / "in", tmp_path / "o", pictures=False, verbose=False)
    assert summary["frames"] == 5
    lat = summary["latency_ms"]
    assert lat["median"] == pytest.approx(2.5) and lat["max"] == pytest.approx(4.0)
    assert 3.0 < lat["p90"] <= 4.0  # numpy's 3.7; a nearest-rank p90 gives 4
