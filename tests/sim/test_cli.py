"""``indoorbev-sim`` argument checks that need no simulated frames."""

import pytest
from indoorbev_sim.cli import main


@pytest.mark.parametrize(
    "flag, value", [("--batch", "0"), ("--batch", "-1"), ("--frames", "0"), ("--frames", "-3")]
)
def test_check_needs_positive_frames_and_batch(flag, value, capsys):
    with pytest.raises(SystemExit) as e:
        main(["check", "--preset", "tiny", "--cache", "", flag, value])
    assert e.value.code == 2
    assert f"argument {flag}: must be > 0, got {value}" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["0", "-2", "nan", "inf"])
def test_publish_needs_a_positive_rate(value, capsys):
    with pytest.raises(SystemExit) as e:
        main(["ros2", "publish", "--rate", value])
    assert e.value.code == 2
    assert f"argument --rate: must be a finite number > 0, got {value}" in capsys.readouterr().err


@pytest.mark.parametrize("frames, batch", [(0, 4), (8, 0), (-1, 4), (8, 2.0)])
def test_check_library_needs_positive_frames_and_batch(frames, batch):
    from indoorbev_sim.labels import check

    from indoorbev_jax.config import Config

    with pytest.raises(ValueError, match="(frames|batch_size): expected a whole number > 0"):
        check(Config.tiny(), frames, batch, seed=0)


@pytest.mark.parametrize("seed", [-1, 2**32, 1.5])
def test_check_library_and_cli_need_a_32_bit_seed(seed, capsys):
    """jax.random.key folds a seed into 32 bits: others would repeat seeds in [0, 2**32)."""
    from indoorbev_sim.labels import check

    from indoorbev_jax.config import Config

    with pytest.raises(ValueError, match=r"seed: expected a whole number in \[0, 2\*\*32\)"):
        check(Config.tiny(), 8, 4, seed=seed)
    with pytest.raises(SystemExit) as e:
        main(["check", "--preset", "tiny", "--seed", str(seed)])
    assert e.value.code == 2
    assert "argument --seed: expected a whole number in [0, 2**32)" in capsys.readouterr().err


def test_publish_a_tilted_lidar_needs_a_level_frame_and_only_then(capsys):
    assert main(["ros2", "publish", "--lidar-rpy", "0,20,0"]) == 2
    assert "name it with --level-frame" in capsys.readouterr().err
    assert main(["ros2", "publish", "--level-frame", "lvl"]) == 2
    assert "--level-frame 'lvl' without a --lidar-rpy rotation" in capsys.readouterr().err
    assert main(["ros2", "publish", "--lidar-rpy", "0,20,0", "--level-frame", "lidar"]) == 2
    assert "--level-frame 'lidar' is --frame-id's" in capsys.readouterr().err


def test_export_and_check_take_config_overrides_and_name_a_bad_one(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["export", "--out", str(out), "--frames", "1", "--set", "sim.nope=1"]) == 2
    assert "sim has no field 'nope'" in capsys.readouterr().err and not out.exists()
    assert main(["check", "--preset", "tiny", "--set", "sim.sensor_rpy=[0, 20]"]) == 2
    assert "config field 'sim.sensor_rpy': got '[0, 20]'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:  # was "split: expected ...", no option named
        main(["check", "--preset", "tiny", "--split", "bogus"])
    assert refused.value.code == 2
    assert "argument --split: invalid choice: 'bogus'" in capsys.readouterr().err


def test_a_tilted_lidar_publishes_in_its_own_frame_and_the_truth_in_the_level_one():
    """The published cloud is what a tilted MID-360 delivers: every return within the
    pattern's elevations in the lidar's frame; levelled, it is the simulated cloud."""
    import dataclasses

    import numpy as np
    from indoorbev_sim import generate, reference
    from indoorbev_sim.ros2 import frame_messages, scene_frames

    from indoorbev_jax.config import Config
    from indoorbev_jax.mount import LidarMount
    from indoorbev_jax.rosbag import markers_to_labels, pointcloud2_to_points, typestore

    tiny = Config.tiny()
    mount = LidarMount(roll=5.0, pitch=25.0)
    config = dataclasses.replace(tiny, sim=dataclasses.replace(tiny.sim, sensor_rpy=(5, 25, 0)))
    points, labels = next(scene_frames(config, seed=0))
    ts, names = typestore(), config.data.class_names
    cloud, truth = frame_messages(ts, points, labels, names, 7, "lidar", mount, "lidar_level")
    assert cloud.header.frame_id == "lidar"
    assert {m.header.frame_id for m in truth.markers} == {"lidar_level"}
    got = markers_to_labels(truth, config.data)
    np.testing.assert_allclose(got.pos, labels.pos, atol=1e-5)  # the truth is not turned
    raw = pointcloud2_to_points(cloud)
    np.testing.assert_allclose(mount.levelled(raw), points, atol=1e-5)
    hit = np.abs(raw[:, :3]).sum(1) > 0
    lo, hi = np.degrees(reference.elevation_limits(generate.make_pattern(config.sim)))
    el = np.degrees(np.arctan2(raw[hit, 2], np.linalg.norm(raw[hit, :2], axis=1)))
    assert hit.sum() > 100 and el.min() >= lo - 0.5 and el.max() <= hi + 0.5
    level = np.degrees(np.arctan2(points[hit, 2], np.linalg.norm(points[hit, :2], axis=1)))
    assert level.min() < lo - 15  # levelled, the tilt reaches below the pattern's floor


def test_the_console_module_loads_no_jax_before_main():
    """JAX loads inside ``main``, where Ctrl-C is caught (status 130, one line): imported at
    module level, a Ctrl-C in the first second gave a traceback and status -2."""
    import subprocess
    import sys

    probe = "import sys, indoorbev_sim.cli; print('jax' in sys.modules)"
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert run.stdout.strip() == "False", run.stderr


def test_check_and_publish_defaults_and_noise_free(monkeypatch):
    """The defaults the docs give (docs/SIMULATOR.md: check's preset paper; docs/ROBOT.md:
    publish's preset small, rate 10, seed 0, split test) and ``--noise-free``: no range noise
    and no dropout. A mutation audit: check on small, publish drawing train scenes and
    --noise-free keeping the dropout all passed."""
    import indoorbev_sim.labels
    import indoorbev_sim.ros2

    seen = {}

    def check(cfg, frames, batch, seed, split):
        seen["check"] = cfg
        return "ok"

    def publish(cfg, rate, frames, topic, objects_topic, frame_id, seed, split, *args):
        seen["publish"] = cfg, rate, seed, split

    monkeypatch.setattr(indoorbev_sim.labels, "check", check)
    monkeypatch.setattr(indoorbev_sim.ros2, "publish", publish)
    assert main(["check", "--cache", ""]) == 0
    assert seen["check"].name == "paper" and seen["check"].sim.dropout > 0
    assert main(["ros2", "publish", "--cache", ""]) == 0
    cfg, rate, seed, split = seen["publish"]
    assert (cfg.name, rate, seed, split) == ("small", 10.0, 0, "test")
    for argv in (["check"], ["ros2", "publish"]):
        assert main([*argv, "--cache", "", "--noise-free"]) == 0
        cfg = seen[argv[-1]] if argv == ["check"] else seen["publish"][0]
        assert (cfg.sim.range_noise, cfg.sim.dropout) == (0.0, 0.0), argv


def test_a_ctrl_c_before_the_node_runs_exits_130(monkeypatch, capsys):
    """docs/ROBOT.md: Ctrl-C during the warm-up exits with status 130 (the node's own stop,
    later, is tested in test_ros2)."""
    import indoorbev_sim.ros2

    def warming_up(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(indoorbev_sim.ros2, "publish", warming_up)
    assert main(["ros2", "publish", "--cache", ""]) == 130
    assert capsys.readouterr().err == "indoorbev-sim: interrupted\n"


def test_show_names_a_missing_frame_in_one_line(tmp_path, capsys):
    """A frame id that is not in the dataset is an error line and status 2, no traceback."""
    (tmp_path / "label_2").mkdir()
    (tmp_path / "label_2" / "000000.txt").write_text("")
    argv = ["show", str(tmp_path), "--out", str(tmp_path / "pics"), "--ids", "999999"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("indoorbev-sim: error: ") and "no frame 999999" in err
    assert len(err.splitlines()) == 1


def test_the_preset_read_from_an_export_is_a_preset_or_none(tmp_path):
    """``saved_preset`` gives the preset export.json's config names, or None for a name of
    no preset (a config built by hand), so that export and show fall back to paper and the
    settings check names each field that differs, not "unknown preset 'mine'" (a mutation
    audit: passing any name on passed every test)."""
    import json

    from indoorbev_sim.export import saved_preset

    assert saved_preset(tmp_path) is None  # no export.json
    for name, want in (("small", "small"), ("mine", None)):
        (tmp_path / "export.json").write_text(json.dumps({"config": {"name": name}}))
        assert saved_preset(tmp_path) == want


def test_publish_refuses_an_empty_record_path_and_frame_id(tmp_path, capsys, monkeypatch):
    """``--record ""`` (an unset shell variable) published and recorded nothing, exit 0;
    ``--frame-id ""`` published messages RViz and tf cannot place."""
    monkeypatch.chdir(tmp_path)
    assert main(["ros2", "publish", "--frames", "1", "--record", "", "--cache", ""]) == 2
    err = capsys.readouterr().err
    assert err == "indoorbev-sim: error: record: an empty path; expected a new folder for the bag\n"
    assert main(["ros2", "publish", "--frames", "1", "--frame-id", "", "--cache", ""]) == 2
    err = capsys.readouterr().err
    assert "frame_id: an empty frame id; expected a tf frame name such as 'lidar'" in err
    assert list(tmp_path.iterdir()) == []


def test_a_cache_that_cannot_be_a_folder_is_named(tmp_path, capsys):
    """A file as --cache: JAX warned and compiled every run again; ~nosuchuser said only
    "Could not determine home directory."."""
    a_file = tmp_path / "afile"
    a_file.write_text("x")
    argv = ["check", "--preset", "tiny", "--frames", "1", "--cache"]
    assert main([*argv, str(a_file)]) == 2
    assert f"indoorbev-sim: error: {a_file}: is a file; --cache must be a folder" in (
        capsys.readouterr().err
    )
    assert main([*argv, "~no_such_user_here/cache"]) == 2
    assert "--cache ~no_such_user_here/cache: " in capsys.readouterr().err
