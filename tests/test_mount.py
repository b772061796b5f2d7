"""LidarMount: levelling a tilted lidar's clouds and moving a sensor outside the trained heights."""

import dataclasses
import json
import math

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from indoorbev_jax import predict as P
from indoorbev_jax.cli import main as cli_main
from indoorbev_jax.config import Config, InferenceConfig
from indoorbev_jax.data.dataset import pad_points
from indoorbev_jax.mount import LidarMount, parse_height, parse_rpy
from indoorbev_jax.train import init_state

# Thresholds at 0 so that an untrained model still yields objects.
CFG = dataclasses.replace(
    Config.tiny(), inference=InferenceConfig(score_threshold=0.0, overlap_threshold=0.0)
)
TRAINED = CFG.sim.sensor_height


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    params = init_state(CFG, jax.random.key(0)).params
    return P.export_model(params, CFG, tmp_path_factory.mktemp("model") / "tiny.msgpack")


def _scan(n=600, seed=3):
    """A level scan inside the tiny grid, clear of the sensor's blind zone."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([-4, -4, -0.4, 0], [4, 4, 1.2, 1], (n, 4)).astype(np.float32)
    return points[np.linalg.norm(points[:, :3], axis=1) > 0.5]


def test_rotation_is_urdf_rpy():
    rng = np.random.default_rng(0)
    for roll, pitch, yaw in rng.uniform(-180, 180, (20, 3)):
        expected = Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix()
        got = LidarMount(roll, pitch, yaw).rotation()
        np.testing.assert_allclose(got, expected, atol=1e-12)
    # Positive pitch tips the lidar's nose down: what it sees 1 m ahead lies below it.
    ahead = LidarMount(pitch=20.0).apply(np.array([[1.0, 0.0, 0.0, 0.5]]), TRAINED)[0]
    np.testing.assert_allclose(ahead, [np.cos(np.radians(20)), 0, -np.sin(np.radians(20)), 0.5],
                               atol=1e-6)  # fmt: skip
    # Upside down (roll 180): its +z is the world's -z, its y the world's -y.
    flipped = LidarMount(roll=180.0).apply(np.array([[1.0, 2.0, 3.0, 0.1]]), TRAINED)[0]
    np.testing.assert_allclose(flipped, [1.0, -2.0, -3.0, 0.1], atol=1e-6)
    # unlevelled is levelled's inverse: the level frame's point as the tilted lidar sends it.
    tilted = LidarMount(10.0, 20.0, -30.0)
    point = np.array([[0.3, -1.2, 2.5, 0.7]], np.float32)
    want = np.concatenate([point[:, :3] @ Rotation.from_euler("xyz", [10, 20, -30], True)
                           .as_matrix(), point[:, 3:]], 1)  # fmt: skip
    np.testing.assert_allclose(tilted.unlevelled(point), want, atol=1e-6)
    np.testing.assert_allclose(tilted.levelled(tilted.unlevelled(point)), point, atol=1e-6)


def test_height_offset_moves_the_floor_to_the_nearest_trained_height():
    lo, hi = TRAINED
    assert LidarMount().z_offset(TRAINED) == 0.0
    assert LidarMount(height=(lo + hi) / 2).z_offset(TRAINED) == 0.0
    assert LidarMount(height=hi + 0.4).z_offset(TRAINED) == pytest.approx(0.4)
    assert LidarMount(height=lo / 2).z_offset(TRAINED) == pytest.approx(-lo / 2)
    # The floor, -height in the lidar frame, lands at -hi after the move.
    floor = LidarMount(height=1.5).apply(np.array([[2.0, 0.0, -1.5, 0.0]]), TRAINED)[0, 2]
    assert floor == pytest.approx(-hi)
    nan = LidarMount(pitch=10.0, height=1.5).apply(np.array([[np.nan, 0, 0, 0.3]]), TRAINED)
    assert np.isnan(nan[0, :3]).all() and nan[0, 3] == pytest.approx(0.3)


def test_full_turns_and_inf_points_are_no_rotation_and_no_warning():
    assert not LidarMount(yaw=360.0).rotated and not LidarMount(roll=-0.0).rotated
    assert LidarMount(yaw=1e-3).rotated
    with np.errstate(all="raise"):  # an Inf coordinate is invalid, not a warning
        out = LidarMount(pitch=10.0).levelled(np.array([[np.inf, 0, 0, 0.2]], np.float32))
    assert not np.isfinite(out[0, :3]).all()
    assert LidarMount(pitch=20.0).radians_hint() is None
    assert LidarMount(pitch=0.349).radians_hint().endswith("pass 0,20,0")
    # One fractional angle is enough to look like radians (1 rad = 57.30 deg, 0.5 rad =
    # 28.65 deg); whole degrees alone do not.
    assert LidarMount(roll=1.0, pitch=0.5).radians_hint().endswith("pass 57.3,28.65,0")
    assert LidarMount(roll=1.0, pitch=2.0).radians_hint() is None
    # Radians only if every angle could be one: a pitch of 20 (> pi) says degrees.
    assert LidarMount(roll=0.5, pitch=20.0).radians_hint() is None


def test_a_mount_away_from_the_trained_tilt_is_pointed_out():
    # Level-trained: a tilt beyond LEVEL_TOLERANCE (2 degrees) is pointed out, a yaw is not.
    for quiet in (LidarMount(pitch=1.9), LidarMount(roll=1.0, pitch=1.5), LidarMount(yaw=90.0)):
        assert quiet.tilt_hint((0.0, 0.0, 0.0)) is None, quiet
    hint = LidarMount(roll=3.0, pitch=4.0, yaw=45.0).tilt_hint((0.0, 0.0, 0.0))
    tilt = np.degrees(np.arccos(np.cos(np.radians(3.0)) * np.cos(np.radians(4.0))))
    assert (
        f"trained on a level lidar and this mount's --lidar-rpy 3,4,45 tilts it {tilt:.1f} deg"
        in hint
    )
    assert "tilts it 180.0 deg" in LidarMount(roll=180.0).tilt_hint((0.0, 0.0, 0.0))
    assert LidarMount(pitch=20.5).tilt_hint((0.0, 20.0, 0.0)) is None  # within a degree
    assert LidarMount(yaw=360.0, pitch=20.0).tilt_hint((0.0, 20.0, 0.0)) is None
    # The angle between the two orientations, against scipy's rotation magnitude.
    hint = LidarMount().tilt_hint((0.0, 20.0, 0.0))
    assert "pitch 20, yaw 0 deg (sim.sensor_rpy), 20.0 deg from this mount's --lidar-rpy" in hint
    assert hint.split("--lidar-rpy ")[1].startswith("0,0,0;")
    a, b = (5.0, 20.0, 0.0), (0.0, 12.0, 30.0)
    angle = Rotation.from_euler("xyz", a, True).inv() * Rotation.from_euler("xyz", b, True)
    assert f"{np.degrees(angle.magnitude()):.1f} deg from" in LidarMount(*b).tilt_hint(a)
    # Trained within a jitter of the tilt: no note inside it, level-trained included.
    assert LidarMount(pitch=7.0).tilt_hint((0.0, 0.0, 0.0), 8.0) is None
    assert LidarMount(roll=-5.0, pitch=15.0).tilt_hint((0.0, 10.0, 0.0), 8.0) is None
    hint = LidarMount(pitch=20.0).tilt_hint((0.0, 10.0, 0.0), 8.0)
    assert "lidar within 8 deg of roll 0, pitch 10, yaw 0 deg (sim.sensor_rpy, " in hint
    assert "sensor_tilt_jitter), 10.0 deg from this mount's" in hint
    # The jitter tilts a level lidar in every direction: a mount's yaw is no tilt (a lidar
    # turned 90 deg about z was told it was 90 deg from the trained one).
    assert LidarMount(yaw=90.0).tilt_hint((0.0, 0.0, 0.0), 8.0) is None
    # A lidar trained level but turned about z, without jitter, is a level one: 2 degrees
    # of tolerance, and no jitter named (it was given a 1 degree band "as the jitter does").
    assert LidarMount(pitch=1.5).tilt_hint((0.0, 0.0, 30.0)) is None
    assert "trained on a level lidar" in LidarMount(pitch=5.0).tilt_hint((0.0, 0.0, 30.0))
    assert LidarMount(pitch=3.0, yaw=90.0).tilt_hint((0.0, 0.0, 0.0), 8.0) is None
    hint = LidarMount(pitch=20.0, yaw=90.0).tilt_hint((0.0, 0.0, 0.0), 8.0)
    assert "lidars tilted 0.0 to 8.0 deg (sim.sensor_rpy 0,0,0, sensor_tilt_jitter 8;" in hint
    assert "as the jitter does) and this mount's --lidar-rpy 0,20,90 tilts it 20.0 deg" in hint


def test_bad_mounts_are_named():
    with pytest.raises(ValueError, match="lidar height: expected metres >= 0"):
        LidarMount(height=-1.0)
    # 0 m (a lidar at floor level) is a height: below the trained ones, the cloud moves down.
    assert parse_height("0") == 0.0
    assert LidarMount(height=0.0).z_offset(TRAINED) == pytest.approx(-TRAINED[0])
    for bad in ("-0.01", "nan", "inf", "x"):
        with pytest.raises(ValueError, match=f"expected metres >= 0, got '{bad}'"):
            parse_height(bad)
    with pytest.raises(ValueError, match="lidar mount pitch"):
        LidarMount(pitch=float("nan"))
    assert parse_rpy("0,-20.5,90") == (0.0, -20.5, 90.0)
    # Exactly three: a fourth value (a height typed into --lidar-rpy) would reach
    # LidarMount(*rpy, height=...) as a height given twice, or LidarMount(*rpy) as the height.
    for bad in ("1,2", "a,b,c", "1,2,inf", "0,20,0,1.2"):
        with pytest.raises(ValueError, match="expected ROLL,PITCH,YAW"):
            parse_rpy(bad)


def test_empty_and_all_nan_clouds_leave_nothing_valid(model_file):
    config, params = P.load_model(model_file)
    predictor = P.Predictor(config, params, mount=LidarMount(pitch=30.0, height=1.4))
    for cloud in (np.zeros((0, 4), np.float32), np.full((5, 4), np.nan, np.float32)):
        padded, valid, counts = predictor.prepare(cloud)
        assert padded.shape == (config.data.max_points, 4) and not valid.any()
        assert counts["nonfinite_points"] == len(cloud)


def test_blind_zone_follows_the_moved_sensor(model_file):
    """A driver's (0, 0, 0) no-return point stays blind after the height move, in
    ``pad_points`` and through ``Predictor.prepare`` for a lidar above and below the trained
    heights. A mutation audit: the predictor's blind zone centred at -z_offset (the
    no-return point of a high lidar kept as a return at the sensor) passed."""
    grid = CFG.grid
    cloud = np.array([[0.0, 0.0, 0.4, 0.0], [2.0, 0.0, 0.4, 0.0]], np.float32)
    _, valid, counts = pad_points(cloud, grid, 4, 0.1, origin=(0.0, 0.0, 0.4))
    assert counts["blind_points"] == 1 and valid.sum() == 1
    config, params = P.load_model(model_file)
    lo, hi = TRAINED
    raw = np.array([[0.0, 0.0, 0.0, 0.0], [2.0, 0.5, 0.0, 0.0]], np.float32)
    for height in (hi + 0.3, lo - 0.2):
        predictor = P.Predictor(config, params, mount=LidarMount(height=height))
        assert abs(predictor.z_offset) > 0.15
        padded, valid, counts = predictor.prepare(raw)
        assert counts["blind_points"] == 1 and valid.sum() == 1, height
        np.testing.assert_allclose(padded[valid], [[2.0, 0.5, predictor.z_offset, 0.0]], atol=1e-6)


def test_tilted_scan_levelled_gives_the_level_scans_prediction(model_file):
    config, params = P.load_model(model_file)
    scan = _scan()
    mount = LidarMount(roll=-3.0, pitch=25.0, yaw=30.0)
    # The same scene seen by the tilted lidar: its points in the lidar's own frame.
    tilted = scan.copy()
    tilted[:, :3] = (scan[:, :3].astype(np.float64) @ mount.rotation()).astype(np.float32)
    level = P.Predictor(config, params)
    levelled = P.Predictor(config, params, mount=mount)
    padded, valid, _ = levelled.prepare(tilted)
    np.testing.assert_allclose(padded[valid], scan, atol=2e-6)
    got = levelled.labels(*levelled.infer(padded, valid)[:2])
    want = level.labels(*level.infer(*level.prepare(scan)[:2])[:2])
    np.testing.assert_array_equal(got[1], want[1])  # segments
    np.testing.assert_array_equal(got[0].classes, want[0].classes)
    np.testing.assert_allclose(got[0].pos, want[0].pos, atol=1e-4)
    # Not levelled, the tilted scan gives another answer: the mount matters.
    raw = level.labels(*level.infer(*level.prepare(tilted)[:2])[:2])
    assert not np.array_equal(raw[1], want[1])


def test_high_lidar_is_moved_and_its_boxes_moved_back(model_file):
    config, params = P.load_model(model_file)
    scan = _scan()
    offset = 0.5
    high = P.Predictor(config, params, mount=LidarMount(height=TRAINED[1] + offset))
    assert high.z_offset == pytest.approx(offset)
    lifted = scan.copy()
    lifted[:, 2] += np.float32(offset)
    plain = P.Predictor(config, params)
    got = high.labels(*high.infer(*high.prepare(scan)[:2])[:2])
    want = plain.labels(*plain.infer(*plain.prepare(lifted)[:2])[:2])
    assert len(want[0]) > 0
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_allclose(got[0].pos[:, :2], want[0].pos[:, :2], atol=1e-5)
    np.testing.assert_allclose(got[0].pos[:, 2], want[0].pos[:, 2] - offset, atol=1e-5)


def test_predict_records_the_mount_and_refuses_to_mix(model_file, tmp_path, capsys):
    scan = tmp_path / "scan.bin"
    _scan().tofile(scan)
    out = tmp_path / "pred"
    argv = ["predict", str(model_file), str(scan), "--out", str(out), "--no-pictures"]
    assert cli_main([*argv, "--lidar-rpy", "0,15,0", "--lidar-height", "1.3"]) == 0
    said = capsys.readouterr().out
    assert "lidar mount: levelled (lidar at roll 0, pitch 15, yaw 0 deg)" in said
    assert "z +0.5 m (lidar 1.3 m above the floor" in said
    run = json.loads((out / "predict.json").read_text())
    assert run["mount"] == {"roll": 0.0, "pitch": 15.0, "yaw": 0.0, "z_offset": pytest.approx(0.5)}
    mounted = [*argv, "--lidar-rpy", "0,15,0", "--lidar-height", "1.3"]
    assert cli_main(mounted) == 0  # the same command after a kill resumes
    assert "1 frames were done by an earlier run" in capsys.readouterr().out
    assert cli_main(argv) == 2  # the level run would mix its files with the tilted one's
    assert "mount: {'roll': 0.0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main([*argv, "--lidar-rpy", "0,15"])
    assert "--lidar-rpy: expected ROLL,PITCH,YAW in degrees" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main([*argv, "--lidar-height", "-2"])
    assert "--lidar-height: expected metres >= 0" in capsys.readouterr().err
    # A mount that changes nothing is no other run: a level lidar within the trained heights.
    level = ["predict", str(model_file), str(scan), "--out", str(tmp_path / "lvl"), "--no-pictures"]
    assert cli_main([*level, "--lidar-height", "0.5", "--lidar-rpy", "0,0,360"]) == 0
    assert "mount" not in json.loads((tmp_path / "lvl" / "predict.json").read_text())
    assert cli_main(level) == 0
    assert "1 frames were done by an earlier run" in capsys.readouterr().out
    assert cli_main([*level, "--level-frame", "lvl"]) == 2
    assert "--level-frame 'lvl' without a --lidar-rpy rotation" in capsys.readouterr().err
    # A URDF's radians given as degrees are pointed out.
    assert cli_main([*argv, "--lidar-rpy", "0,0.349,0", "--overwrite"]) == 0
    assert "if these are a URDF's radians, pass 0,20,0" in capsys.readouterr().err
    # A model trained on a tilted lidar: a run with another tilt is pointed out.
    params = P.load_model(model_file)[1]
    tilted = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, sensor_rpy=(0, 20, 0)))
    tilted_file = P.export_model(params, tilted, tmp_path / "tilted.msgpack")
    run = ["predict", str(tilted_file), str(scan), "--no-pictures"]
    assert cli_main([*run, "--out", str(tmp_path / "t1")]) == 0
    assert "trained on lidars tilted 19.0 to 21.0 deg (sim.sensor_rpy 0,20,0;" in (
        capsys.readouterr().err
    )
    assert cli_main([*run, "--out", str(tmp_path / "t2"), "--lidar-rpy", "0,20,0"]) == 0
    assert "trained on lidars" not in capsys.readouterr().err
    # A level frame with nothing to name (no --bag-out) is pointed out, not silently dropped.
    assert cli_main([*argv, "--lidar-rpy", "0,0.349,0", "--level-frame", "lvl"]) == 0
    assert "--level-frame 'lvl' names the frame of --bag-out's messages" in capsys.readouterr().err


def test_bag_out_of_a_levelled_run_shares_the_level_frame(model_file, tmp_path):
    from rosbags.rosbag2 import Reader

    from indoorbev_jax.rosbag import markers_to_labels, pointcloud2_to_points, typestore

    scan = tmp_path / "scan.bin"
    tilted = _scan()
    tilted.tofile(scan)
    mount = LidarMount(roll=5.0, pitch=-30.0, height=1.0)
    run = dict(pictures=False, verbose=False, mount=mount)
    with pytest.raises(ValueError, match="name their frame with --level-frame"):
        P.predict(model_file, scan, tmp_path / "o", bag_out=tmp_path / "bag", **run)
    P.predict(model_file, scan, tmp_path / "o", bag_out=tmp_path / "bag", level_frame="lvl", **run)
    ts, msgs = typestore(), {}
    with Reader(tmp_path / "bag") as reader:
        for conn, _, raw in reader.messages():
            msgs[conn.topic] = ts.deserialize_cdr(raw, conn.msgtype)
    cloud, markers = msgs["/points"], msgs["/detections"]
    assert cloud.header.frame_id == "lvl"
    assert {m.header.frame_id for m in markers.markers} == {"lvl"}
    # The cloud levelled but not moved in height; the boxes are the label file's.
    want = tilted.copy()
    want[:, :3] = tilted[:, :3].astype(np.float64) @ mount.rotation().T
    np.testing.assert_allclose(pointcloud2_to_points(cloud), want, atol=1e-6)
    labels = P.kitti.read_labels(tmp_path / "o" / "label_2" / "scan.txt", CFG.data)
    np.testing.assert_allclose(markers_to_labels(markers, CFG.data).pos, labels.pos, atol=1e-6)


def test_rpy_matrix_is_scipys_extrinsic_xyz_in_numpy_and_jax():
    """``rpy_matrix`` (the simulator's per-scene tilt, jittable) is ``LidarMount.rotation``."""
    import jax.numpy as jnp

    from indoorbev_jax.mount import rpy_matrix

    angles = np.random.default_rng(3).uniform(-180, 180, (2, 5, 3))
    want = Rotation.from_euler("xyz", angles.reshape(-1, 3), degrees=True).as_matrix()
    np.testing.assert_allclose(rpy_matrix(angles).reshape(-1, 3, 3), want, atol=1e-12)
    got = np.asarray(rpy_matrix(jnp.asarray(angles, jnp.float32), jnp)).reshape(-1, 3, 3)
    np.testing.assert_allclose(got, want, atol=2e-6)
    np.testing.assert_allclose(LidarMount(*angles[0, 0]).rotation(), want[0], atol=1e-12)


def test_the_shipped_tilted_model_is_the_level_ones_architecture_for_pitch_0_to_20():
    """models/indoorbev_small_tilted.msgpack (docs/ROBOT.md "Mount"): the level model's
    architecture, trained on pitch 10 +- 10; no tilt note from 0 to 20 degrees down."""
    from pathlib import Path

    from indoorbev_jax.predict import ARCHITECTURE_SECTIONS, load_model

    models = Path(__file__).resolve().parents[1] / "models"
    level, _ = load_model(models / "indoorbev_small.msgpack")
    tilted, _ = load_model(models / "indoorbev_small_tilted.msgpack")
    for section in ARCHITECTURE_SECTIONS:
        assert getattr(tilted, section) == getattr(level, section), section
    assert (tilted.sim.sensor_rpy, tilted.sim.sensor_tilt_jitter) == ((0.0, 10.0, 0.0), 10.0)
    assert (level.sim.sensor_rpy, level.sim.sensor_tilt_jitter) == ((0.0, 0.0, 0.0), 0.0)
    for pitch in (0.0, 5.0, 15.0, 20.0):
        assert LidarMount(pitch=pitch).notes(tilted) == [], pitch
    # Trained with every scene turned about z (augment.rotation pi): a tilt facing any way is
    # one the model saw, so a roll, a nose-up pitch and a yawed mount get no note.
    assert tilted.train.augment and tilted.augment.rotation == math.pi
    for rpy in [(10, 0, 0), (5, 0, 0), (0, -10, 0), (0, 15, 180), (-14, 14, 30)]:
        assert LidarMount(*rpy).notes(tilted) == [], rpy
    (hint,) = LidarMount(roll=25.0).notes(tilted)
    assert "trained on lidars tilted 0.0 to 20.0 deg (sim.sensor_rpy 0,10,0, sensor_tilt_" in hint
    assert "--lidar-rpy 25,0,0 tilts it 25.0 deg" in hint
    # Without the full turn (or without augmentation) the direction counts, as before.
    for config in (
        dataclasses.replace(tilted, augment=dataclasses.replace(tilted.augment, rotation=1.0)),
        dataclasses.replace(tilted, train=dataclasses.replace(tilted.train, augment=False)),
    ):
        assert "within 10 deg of" in LidarMount(pitch=-10.0).notes(config)[0]
    # The level model points a lidar tilted 5 degrees to models trained on tilts.
    assert "(sim.sensor_tilt_jitter, docs/ROBOT.md 'Mount')" in LidarMount(pitch=5).notes(level)[0]
