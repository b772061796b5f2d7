"""KITTI and ROS2-bag export: exact round trips, splits, and resuming after a kill."""

import contextlib
import dataclasses
import fcntl
import filecmp
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import jax
import numpy as np
import pytest
from indoorbev_sim import export as export_mod
from indoorbev_sim import show
from indoorbev_sim.cli import main

from indoorbev_jax.checks import check_seed, check_whole
from indoorbev_jax.config import CLASS_NAMES, Config
from indoorbev_jax.data import kitti
from indoorbev_jax.rosbag import BagError

CFG = Config.tiny()  # the CLI's --preset tiny
FRAMES, SEED = 20, 5  # 10 scenes of 2 frames: train, val and test all present


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A persistent XLA cache shared with the CLI subprocesses, so they skip the compile."""
    from jax.experimental.compilation_cache import compilation_cache

    path = tmp_path_factory.mktemp("xla")
    compilation_cache.reset_cache()
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    yield path
    jax.config.update("jax_compilation_cache_dir", None)
    compilation_cache.reset_cache()


@pytest.fixture(scope="module")
def exported(tmp_path_factory, cache):
    root = tmp_path_factory.mktemp("export")
    bag = root.parent / (root.name + ".bag")
    splits = export_mod.export(root, FRAMES, SEED, CFG, rosbag=bag, progress=False)
    return root, bag, splits


def test_kitti_round_trip_is_exact(exported):
    root, _, splits = exported
    fn = export_mod.scene_fn(CFG)
    # A train, a val and a test scene, regenerated: val draws from the training plans.
    for j in (0, 8, 9):
        batch, info = fn(jax.random.fold_in(jax.random.key(SEED), j), j == 9)
        for t in range(CFG.sim.frames_per_sequence):
            fid = export_mod.frame_id(2 * j + t)
            paths = kitti.frame_paths(root, fid)
            v = np.asarray(batch.targets.valid[0, t])
            got = kitti.read_labels(paths["labels"], CFG.data)
            np.testing.assert_array_equal(got.classes, np.asarray(batch.targets.classes[0, t])[v])
            np.testing.assert_allclose(got.dims, np.asarray(batch.targets.dims[0, t])[v], atol=1e-5)
            np.testing.assert_allclose(got.pos, np.asarray(batch.targets.pos[0, t])[v], atol=1e-5)
            dyaw = got.yaw - np.asarray(batch.targets.yaw[0, t])[v]
            np.testing.assert_allclose(np.sin(dyaw / 2), 0, atol=1e-5)
            np.testing.assert_array_equal(got.occlusion, np.asarray(info.occlusion[0, t])[v])
            pts = np.asarray(batch.points[0, t])[np.asarray(batch.point_valid[0, t])]
            np.testing.assert_array_equal(kitti.read_points(paths["points"]), pts)
            ids = kitti.read_mask(paths["mask"], CFG.grid.shape)
            np.testing.assert_array_equal(ids, np.asarray(batch.targets.instance_ids[0, t]))
    # Splits: scene j % 10 == 9 is test, 8 val; every frame in exactly one split.
    assert splits["test"] == ["000018", "000019"] and splits["val"] == ["000016", "000017"]
    for split, ids in splits.items():
        assert kitti.read_split(root, split) == ids
    assert sorted(sum(splits.values(), [])) == kitti.list_frames(root)


def test_publish_streams_every_frame_of_each_scene_in_turn(cache):
    """``indoorbev-sim ros2 publish`` streams scene after scene, each scene's T consecutive
    frames: stream frame T*j + t is frame t of scene j, the draw an export makes. A mutation
    audit: a stream of each scene's first frame only passed."""
    from indoorbev_sim.ros2 import scene_frames

    fn, stream = export_mod.scene_fn(CFG), scene_frames(CFG, SEED, "test")
    for j in range(2):
        batch, info = fn(jax.random.fold_in(jax.random.key(SEED), j), True)
        for t in range(CFG.sim.frames_per_sequence):
            points, labels = next(stream)
            want_points, want_labels = export_mod.scene_frame(batch, info, t)
            np.testing.assert_array_equal(points, want_points.astype(np.float32))
            np.testing.assert_array_equal(labels.pos, want_labels.pos)


def test_test_split_comes_from_held_out_plans(exported):
    from indoorbev_sim import layouts

    fn = export_mod.scene_fn(CFG)
    held = {layouts.plan_id(n, CFG.sim.plans_per_layout) for n in CFG.sim.test_layouts}
    for j in range(10):
        _, info = fn(
            jax.random.fold_in(jax.random.key(SEED), j), export_mod.scene_split(j) == "test"
        )
        assert (int(info.plan[0, 0]) in held) == (j == 9)


def test_rosbag_round_trip(exported):
    """The bag gives back the KITTI frames, clouds and markers all in frame "lidar" (the
    module docstring, docs/SIMULATOR.md). A mutation audit: another frame id passed."""
    from rosbags.rosbag2 import Reader

    from indoorbev_jax.rosbag import typestore

    root, bag, _ = exported
    ts = typestore()
    with Reader(bag) as reader:
        msgs = [(c.topic, ts.deserialize_cdr(raw, c.msgtype)) for c, _, raw in reader.messages()]
    clouds = [m for t, m in msgs if t == export_mod.POINTS_TOPIC]
    arrays = [m for t, m in msgs if t == export_mod.OBJECTS_TOPIC]
    assert clouds and {m.header.frame_id for m in clouds} == {"lidar"}
    assert {m.header.frame_id for a in arrays for m in a.markers} == {"lidar"}
    frames = export_mod.read_rosbag(bag, CFG)
    ids = kitti.list_frames(root)
    assert len(frames) == len(ids)
    for fid, (points, labels) in zip(ids, frames, strict=True):
        paths = kitti.frame_paths(root, fid)
        np.testing.assert_array_equal(points, kitti.read_points(paths["points"]))
        ref = kitti.read_labels(paths["labels"], CFG.data)
        np.testing.assert_array_equal(labels.classes, ref.classes)
        np.testing.assert_array_equal(labels.occlusion, ref.occlusion)
        np.testing.assert_allclose(labels.dims, ref.dims, atol=1e-6)
        np.testing.assert_allclose(labels.pos, ref.pos, atol=1e-6)
        np.testing.assert_allclose(np.sin((labels.yaw - ref.yaw) / 2), 0, atol=1e-6)


def test_bag_markers_start_with_deleteall(exported):
    """Each frame's MarkerArray clears the previous frame's boxes in a replay (a DELETEALL
    first); reading it back skips that marker (test above)."""
    from rosbags.rosbag2 import Reader

    from indoorbev_jax.rosbag import typestore

    _, bag, _ = exported
    ts = typestore()
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == export_mod.OBJECTS_TOPIC]
        arrays = [ts.deserialize_cdr(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    assert arrays and all(a.markers[0].action == 3 for a in arrays)  # Marker.DELETEALL
    assert all(m.action == 0 for a in arrays for m in a.markers[1:])  # ADD


def test_bag_times_are_one_frame_dt_after_each_frame(exported):
    """The bag's record times (and stamps) of frame i are (i + 1) * frame_dt, as the module
    documents: 100, 200, ... 2000 ms for the tiny preset's 0.1 s frames, no message at time
    0. Guards against stamping frame i at i * frame_dt."""
    from rosbags.rosbag2 import Reader

    _, bag, _ = exported
    with Reader(bag) as reader:
        times = sorted({t for _, t, _ in reader.messages()})
    dt = round(CFG.sim.frame_dt * 1e9)
    assert dt == 100_000_000 and times == [(i + 1) * dt for i in range(FRAMES)]


def test_show_writes_pictures(exported, tmp_path):
    root, _, _ = exported
    written = show.show(root, tmp_path, CFG, ids=["000000", "000001"])
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(ValueError, match="a_file: is a file; out must be a folder"):
        show.show(root, tmp_path / "a_file", CFG)
    # An id with no frame is named before the output folder is made (a raw [Errno 2] after).
    with pytest.raises(FileNotFoundError, match=r"no frame 999999 \(no .*999999\.bin\)"):
        show.show(root, tmp_path / "none", CFG, ids=["999999"])
    assert not (tmp_path / "none").exists()
    from PIL import Image

    for path in written:
        img = np.asarray(Image.open(path))
        assert img.shape[0] >= 600 and img.shape[2] == 3
        assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10  # points, masks, boxes drawn


def test_show_draws_every_frame_with_its_mask(tmp_path, monkeypatch):
    """Without ids, show draws every frame ("all by default"), each with its mask_2 footprints
    where it has one. A mutation audit: the first frame only and masks never drawn passed."""
    drawn = {}
    real = show.render_frame

    def render(points, labels, mask, *args):
        drawn[len(drawn)] = mask
        return real(points, labels, mask, *args)

    monkeypatch.setattr(show, "render_frame", render)
    ids = np.zeros(CFG.grid.shape, np.int32)
    ids[30:60, 30:70] = 1
    empty = kitti.ObjectLabels.empty()
    for k in range(3):  # a mask for frame 000001 only
        mask = ids if k == 1 else None
        kitti.write_frame(
            tmp_path, f"{k:06d}", np.zeros((10, 4), np.float32), empty, CLASS_NAMES, mask
        )
    written = show.show(tmp_path, tmp_path / "pics", CFG)
    assert [p.name for p in written] == ["000000.png", "000001.png", "000002.png"]
    assert drawn[0] is None and drawn[2] is None
    np.testing.assert_array_equal(drawn[1], ids)


def test_show_never_leaves_a_half_written_picture(exported, tmp_path, monkeypatch):
    """Pillow wrote under the picture's name: a full disk on a rerun cut a good picture to
    8 KB, a Ctrl-C left a 33-byte PNG. A Ctrl-C that Python dropped (raised in JAX's
    garbage-collector callback) let show write every picture and exit 0."""
    from PIL import Image

    from indoorbev_jax import interrupts

    root, _, _ = exported
    (good,) = show.show(root, tmp_path, CFG, ids=["000000"])
    before = good.read_bytes()

    def full_disk(self, fp, format=None, **params):
        Path(fp).write_bytes(b"\x89PNG partial")
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(Image.Image, "save", full_disk)
        with pytest.raises(OSError, match=r"cannot write .*000000\.png: No space left"):
            show.show(root, tmp_path, CFG, ids=["000000"])
    assert good.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
        "000000.png"
    ]
    # A dropped Ctrl-C stops the loop after the picture in progress.
    hook_calls, redelivered = [], []
    hook = interrupts._quiet_dropped_interrupts(hook_calls.append, lambda: redelivered.append(1))
    hook(types.SimpleNamespace(exc_value=KeyboardInterrupt()))
    assert hook_calls == [] and redelivered == [1] and interrupts.SIGINT_DROPPED.is_set()
    other = types.SimpleNamespace(exc_value=RuntimeError("x"))
    hook(other)
    assert hook_calls == [other] and redelivered == [1]  # anything else is printed as before
    # Should the delivered-again Ctrl-C be dropped as well, the loop still stops.
    out = tmp_path / "stopped"
    with pytest.raises(KeyboardInterrupt):
        show.show(root, out, CFG, ids=["000000", "000001"])
    assert [p.name for p in out.iterdir()] == [
        "000000.png"
    ] and not interrupts.SIGINT_DROPPED.is_set()


def _cli(out, cache, *extra):
    return [
        sys.executable, "-m", "indoorbev_sim.cli", "export", "--out", str(out),
        "--frames", str(FRAMES), "--seed", str(SEED), "--preset", "tiny", "--no-progress",
        "--cache", str(cache), *extra,
    ]  # fmt: skip


def test_resume_after_kill_equals_uninterrupted_export(exported, cache, tmp_path):
    root, _, _ = exported
    out = tmp_path / "resumed"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.Popen(_cli(out, cache, "--throttle", "0.3"), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.time() + 600
    while time.time() < deadline and len(list((out / "label_2").glob("*.txt"))) < 4:
        assert proc.poll() is None, "export ended before it could be killed"
        time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = kitti.list_frames(out)
    assert 4 <= len(done) < FRAMES
    # A frame torn by the kill: points half written, label missing.
    torn = kitti.frame_paths(out, done[-1])
    torn["points"].write_bytes(torn["points"].read_bytes()[:37])
    torn["labels"].unlink()
    # What a kill inside fileio.atomic_write leaves: the resume deletes it, a minute old at
    # its start, or just made (a kill right before the resume) once the run is done, older
    # than the run; a user's hidden file of another name is kept.
    (out / "mask_2" / f".{done[0]}.png.k1ll3d_a.tmp").write_bytes(b"")
    for tmp in out.rglob(".*.tmp"):
        os.utime(tmp, (time.time() - 120,) * 2)
    fresh = out / "label_2" / f".{done[0]}.txt.fr3sh_ab.tmp"
    keep = out / "velodyne" / ".notes.tmp"
    for path in (fresh, keep):
        path.write_bytes(b"")
    os.utime(keep, (time.time() - 120,) * 2)
    rerun = subprocess.run(_cli(out, cache), env=env, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert not fresh.exists() and keep.exists()  # keep: not atomic_write's name
    keep.unlink()
    for sub in ("velodyne", "label_2", "mask_2"):
        a, b = (
            sorted(p.name for p in (root / sub).iterdir()),
            sorted(p.name for p in (out / sub).iterdir()),
        )
        assert a == b, sub  # no missing, extra or temporary files
        match, mismatch, errors = filecmp.cmpfiles(root / sub, out / sub, a, shallow=False)
        assert not mismatch and not errors, (sub, mismatch, errors)
    for split in export_mod.SPLITS:
        assert filecmp.cmp(root / f"{split}.txt", out / f"{split}.txt", shallow=False)
    # A rerun with other settings is refused, naming the file.
    bad = subprocess.run(_cli(out, cache)[:-2] + ["--seed", "6"] + _cli(out, cache)[-2:],
                         env=env, capture_output=True, text=True)  # fmt: skip
    assert bad.returncode == 2 and "export.json" in bad.stderr


def test_sequence_frames_follow_the_motion(exported):
    """Within a sequence the lidar rides its robot and labelled objects sit where their
    world motion puts them, seen from the moving sensor."""
    fn = export_mod.scene_fn(CFG)
    dt = CFG.sim.frame_dt
    checked = 0
    for j in range(6):
        batch, info = jax.tree.map(
            np.asarray, fn(jax.random.fold_in(jax.random.key(SEED), j), False)
        )
        scene = jax.tree.map(lambda x: x[0, 0], info.scene)  # frame 0's copy of the scene
        np.testing.assert_allclose(
            info.sensor_origin[0, 1, :2] - info.sensor_origin[0, 0, :2],
            scene.ego_velocity * dt, atol=1e-5,
        )  # fmt: skip
        for t in range(CFG.sim.frames_per_sequence):
            origin, yaw = info.sensor_origin[0, t], info.sensor_yaw[0, t]
            for k in np.flatnonzero(batch.targets.valid[0, t]):
                slot = info.slot[0, t, k]
                x, y = batch.targets.pos[0, t, k, :2]
                world = origin[:2] + [np.cos(yaw) * x - np.sin(yaw) * y,
                                      np.sin(yaw) * x + np.cos(yaw) * y]  # fmt: skip
                expect = scene.pose[slot, :2] + scene.velocity[slot] * t * dt
                np.testing.assert_allclose(world, expect, atol=1e-4)
                checked += 1
    assert checked > 0


def _tree(root):
    """{relative path: bytes} of every file under root."""
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def test_export_refuses_dataset_files_without_export_json(exported, tmp_path):
    root, _, _ = exported
    # A copy of an export whose export.json is gone: another seed must not adopt its frames.
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    (copy / "export.json").unlink()
    before = _tree(copy)
    with pytest.raises(export_mod.ExportError, match="copy: holds velodyne/ ") as e:
        export_mod.export(copy, FRAMES, SEED + 1, CFG, progress=False)
    assert f"label_2/ ({FRAMES} files)" in str(e.value) and "train.txt" in str(e.value)
    assert "another --out" in str(e.value) and "remove" not in str(e.value)
    # An `indoorbev predict` output folder: labels and masks, no velodyne, no export.json.
    pred = tmp_path / "pred"
    for sub in ("label_2", "mask_2"):
        shutil.copytree(root / sub, pred / sub)
    (pred / "predict.json").write_text("{}")
    before_pred = _tree(pred)
    with pytest.raises(export_mod.ExportError, match=r"pred: holds label_2/ \(20 files\), mask_2/"):
        export_mod.export(pred, 2, SEED, CFG, progress=False)
    assert _tree(copy) == before and _tree(pred) == before_pred  # nothing written


def test_an_export_checks_the_settings_again_once_it_holds_the_folder(tmp_path, monkeypatch):
    """Two exports of other seeds started together both found no export.json; the one
    refused by the lock could leave its export.json over the other's frames (1 race in 10),
    and a rerun of its seed resumed them. The settings are checked again under the lock."""
    out = tmp_path / "ds"
    hold = export_mod.fileio.hold_folder
    other = {"seed": SEED + 1, "frames": 2, "config": CFG.stable_dict()}

    @contextlib.contextmanager
    def held_after_the_other(folder, *args):
        with hold(folder, *args):
            (out / "export.json").write_text(json.dumps(other))  # written while we waited
            yield

    monkeypatch.setattr(export_mod.fileio, "hold_folder", held_after_the_other)
    with pytest.raises(export_mod.ExportError, match=rf"seed: {SEED + 1} \(saved\) vs {SEED}"):
        export_mod.export(out, 2, SEED, CFG, progress=False)
    assert sorted(p.name for p in out.iterdir()) == [".lock", "export.json"]


def test_an_export_into_a_data_folder_of_a_dataset_is_refused(exported, tmp_path):
    """``--out DS/label_2`` wrote split lists, export.json and frame folders into the
    dataset's label folder, which then no longer read as a dataset."""
    root, _, _ = exported
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    before = _tree(copy)
    for sub in ("label_2", "velodyne", "mask_2"):
        with pytest.raises(export_mod.ExportError) as refused:
            export_mod.export(copy / sub, 2, SEED, CFG, progress=False)
        assert str(refused.value) == (
            f"{copy / sub}: the {sub}/ folder of the dataset {copy.resolve()}, not a dataset "
            "root (an export there broke that dataset); use another --out"
        )
    (copy / "mask_2").rename(copy / "masks_moved")  # a data folder not made yet is one too
    with pytest.raises(export_mod.ExportError, match="the mask_2/ folder of the dataset"):
        export_mod.export(copy / "mask_2", 2, SEED, CFG, progress=False)
    (copy / "masks_moved").rename(copy / "mask_2")
    assert _tree(copy) == before


def test_an_export_running_in_the_folder_refuses_a_second(exported, tmp_path):
    """Two exports into one folder both wrote every frame; the second is now refused,
    naming the first, and writes nothing."""
    root, _, _ = exported
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    with open(copy / ".lock", "w") as other:  # the first export, as its lock shows it
        fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
        other.write("pid 4242\n")
        other.flush()
        before = _tree(copy)
        with pytest.raises(ValueError, match=r"copy: in use by another export \(pid 4242\)"):
            export_mod.export(copy, FRAMES, SEED, CFG, progress=False)
        assert _tree(copy) == before
    export_mod.export(copy, FRAMES, SEED, CFG, progress=False)  # once it has ended
    assert (copy / ".lock").read_text() == f"export, pid {os.getpid()}\n"


def test_bad_options_fail_before_any_frame(cache, tmp_path, monkeypatch):
    not_a_bag = tmp_path / "notes"
    not_a_bag.mkdir()
    (not_a_bag / "readme.txt").write_text("not a bag")
    out = tmp_path / "out"
    with pytest.raises(BagError, match="notes: exists and is not a bag"):
        export_mod.export(out, 4, SEED, CFG, rosbag=not_a_bag, progress=False)
    assert not out.exists()
    assert [p.name for p in not_a_bag.iterdir()] == ["readme.txt"]
    # 1e10 s overflowed time.sleep after the first scene was written.
    for throttle in (-1, "x", float("nan"), 1e10, export_mod.MAX_THROTTLE + 1):
        expected = rf"throttle: must be a number of seconds in \[0, 3600\], got {throttle!r}"
        with pytest.raises(ValueError, match=expected):
            export_mod.export(out, 4, SEED, CFG, progress=False, throttle=throttle)
    for frames in (0, 2.5, True):  # 2.5 used to end in a TypeError from range()
        expected = f"frames: expected a whole number > 0, got {frames!r}"
        with pytest.raises(ValueError, match=expected):
            export_mod.export(out, frames, SEED, CFG, progress=False)
    # 10**20 frames: no message for minutes, then a MemoryError, export.json kept.
    assert export_mod.frame_id(export_mod.MAX_FRAMES - 1) == "999999"
    expected = "frames: at most 1,000,000 (frame ids have six digits), got 1000001"
    with monkeypatch.context() as m, pytest.raises(ValueError, match=re.escape(expected)):
        m.setattr(export_mod, "scene_fn", None)  # without the bound: a TypeError, no hang
        export_mod.export(out, export_mod.MAX_FRAMES + 1, SEED, CFG, progress=False)
    assert not out.exists()
    # jax.random.key folds seeds into 32 bits: 2**32 + 5 gave seed 5's frames.
    for seed in (2**32 + 5, -1, 2**63, True):
        with pytest.raises(ValueError, match=r"seed: expected a whole number in \[0, 2\*\*32\)"):
            export_mod.export(out, 4, seed, CFG, progress=False)
    with pytest.raises(SystemExit):
        main(["export", "--out", str(out), "--frames", "4", "--seed", "-1", "--preset", "tiny"])
    with pytest.raises(ValueError, match="out: an empty path"):
        export_mod.export("", 4, SEED, CFG, progress=False)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    with pytest.raises(export_mod.ExportError, match="a_file: is a file; out must be a folder"):
        export_mod.export(a_file, 4, SEED, CFG, progress=False)
    # The bag is written last: a place it cannot take is refused before the frames.
    for bag in (out, out / "bag", tmp_path):
        with pytest.raises(export_mod.ExportError, match="overlaps the dataset folder"):
            export_mod.export(out, 4, SEED, CFG, rosbag=bag, progress=False)
    # ... and so is one whose temporary <bag>.partial is the dataset, or holds other files
    # (both failed only after every frame).
    with pytest.raises(export_mod.ExportError, match=r"temporary d\.partial\) overlaps"):
        export_mod.export(tmp_path / "d.partial", 4, SEED, CFG, rosbag=tmp_path / "d",
                          progress=False)  # fmt: skip
    (tmp_path / "b.partial").mkdir()
    (tmp_path / "b.partial" / "notes.txt").write_text("")
    with pytest.raises(export_mod.ExportError, match=r"b\.partial: holds files that an inter"):
        export_mod.export(out, 4, SEED, CFG, rosbag=tmp_path / "b", progress=False)
    (tmp_path / "f.partial").write_text("")  # a file there: write_bag failed at the end
    with pytest.raises(export_mod.ExportError, match=r"f\.partial: a file where the bag's"):
        export_mod.export(out, 4, SEED, CFG, rosbag=tmp_path / "f", progress=False)
    # numpy integers are whole numbers (they were refused as "a whole number ... got 2").
    assert check_whole("frames", np.int64(2), 1) == 2 and check_seed("seed", np.uint32(7)) == 7
    for bad in (True, np.bool_(True), 2.0):
        with pytest.raises(ValueError, match="frames: expected a whole number"):
            check_whole("frames", bad, 1)
    with pytest.raises(ValueError, match="rosbag: an empty path"):
        export_mod.export(out, 4, SEED, CFG, rosbag="", progress=False)
    assert not out.exists()
    # Settings no scene can be drawn from are refused before export.json keeps them (it
    # then refused the corrected rerun as "an export with other settings").
    every_plan = {"layouts": ("office",), "plans_per_layout": 1, "test_layouts": ("office/0",)}
    for fields, message in [
        ({"test_variants": ("Misc/foo",)}, r"sim\.test_variants: unknown variant 'Misc/foo'"),
        ({"sensor_height": (0.35, 2.9)}, r"sensor_height"),
        (every_plan, r"sim\.test_layouts holds out every plan"),
    ]:
        bad = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, **fields))
        with pytest.raises(ValueError, match=message):
            export_mod.export(out, 4, SEED, bad, progress=False)
        assert not (out / "export.json").exists()


def test_settings_mismatch_names_each_field(exported, tmp_path):
    root, _, _ = exported
    shutil.copy(root / "export.json", tmp_path / "export.json")
    noisy = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, range_noise=0.5))
    with pytest.raises(export_mod.ExportError) as e:
        export_mod.export(tmp_path, FRAMES, SEED + 1, noisy, progress=False)
    msg = str(e.value)
    assert str(tmp_path / "export.json") in msg
    assert f"config.sim.range_noise: {CFG.sim.range_noise!r} (saved) vs 0.5 (given)" in msg
    assert f"seed: {SEED} (saved) vs {SEED + 1} (given)" in msg
    assert "frames" not in msg.split("other settings:")[1]  # only the fields that differ
    # A field left at its default is not recorded (stable_dict): the default is shown, not
    # "(absent)", which hid that the given value was [0, 0, 0].
    tilted = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, sensor_rpy=(0, 20, 0)))
    (tmp_path / "export.json").write_text(
        json.dumps({"seed": SEED, "frames": FRAMES, "config": tilted.stable_dict()})
    )
    with pytest.raises(export_mod.ExportError) as e:
        export_mod.export(tmp_path, FRAMES, SEED, CFG, progress=False)
    assert str(e.value).endswith(
        "other settings: config.sim.sensor_rpy: [0, 20, 0] (saved) vs [0.0, 0.0, 0.0] (the "
        "default) (given); rerun with the saved settings to resume, or use another --out"
    )
    (tmp_path / "export.json").write_bytes(b"\xff{}")  # not UTF-8: a message naming no file
    with pytest.raises(export_mod.ExportError, match=r"export\.json: unreadable \('utf-8' codec"):
        export_mod.export(tmp_path, FRAMES, SEED, CFG, progress=False)


def test_a_long_settings_mismatch_names_seed_frames_and_preset_before_the_config():
    """With more differing fields than the message lists, seed, frames and the preset name
    still come first (the docstring). A mutation audit: a plain sort, which dropped the seed
    behind twelve config fields, passed."""
    sim = {f"f{i:02d}": i for i in range(12)}
    old = {"seed": 0, "frames": 20, "config": {"name": "tiny", "sim": sim}}
    new = {"seed": 1, "frames": 40, "config": {"name": "small", "sim": {}}}
    rows = export_mod._meta_diff(old, new).split("; ")
    assert set(rows[:3]) == {
        "config.name: 'tiny' (saved) vs 'small' (given)",
        "frames: 20 (saved) vs 40 (given)",
        "seed: 0 (saved) vs 1 (given)",
    }
    assert rows[3] == "config.sim.f00: 0 (saved) vs (absent) (given)"
    assert len(rows) == 11 and rows[-1] == "and 5 more fields"


def test_an_export_json_from_before_a_later_field_still_matches(exported, tmp_path):
    """``sim.sensor_rpy`` came later: a level export leaves it out of export.json, so the
    folders exported before it resume; a tilted one records it, and a level rerun differs."""
    root, _, _ = exported
    saved = json.loads((root / "export.json").read_text())
    assert "sensor_rpy" not in saved["config"]["sim"]
    tilted = dataclasses.replace(CFG, sim=dataclasses.replace(CFG.sim, sensor_rpy=(0, 20, 0)))
    assert tilted.stable_dict()["sim"]["sensor_rpy"] == (0, 20, 0)
    (tmp_path / "export.json").write_text(json.dumps({**saved, "config": tilted.stable_dict()}))
    with pytest.raises(export_mod.ExportError, match=r"config.sim.sensor_rpy: \[0, 20, 0\] "):
        export_mod.export(tmp_path, FRAMES, SEED, CFG, progress=False)


def test_resume_progress_counts_only_new_frames(exported, tmp_path, monkeypatch, capsys):
    import tqdm

    root, _, _ = exported
    out = tmp_path / "resume"
    shutil.copytree(root, out)
    kitti.frame_paths(out, "000019")["labels"].unlink()  # scene 9 (frames 18, 19) is redone
    started = []

    class Bar(tqdm.tqdm):
        def __init__(self, *args, **kwargs):
            started.append(kwargs.get("initial", 0))
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(tqdm, "tqdm", Bar)
    export_mod.export(out, FRAMES, SEED, CFG, progress=True)
    assert started == [FRAMES - 2]
    err = capsys.readouterr().err
    assert err.count("resuming:") == 1 and f"resuming: 18 of {FRAMES} frames already written" in err
    assert _tree(out) == _tree(root)


def test_a_deleted_mask_makes_its_scene_be_written_again(exported, tmp_path, capsys):
    """A frame is complete only with its points, labels and mask: deleting mask_2/000019.png
    makes the resume write scene 9 (frames 18, 19) again, saying 18 of 20 frames were kept,
    and the folder then equals the uninterrupted export. Guards against a completeness test
    that ignores the mask (the frame kept without it, "resuming: 20 of 20")."""
    root, _, _ = exported
    out = tmp_path / "resume"
    shutil.copytree(root, out)
    kitti.frame_paths(out, "000019")["mask"].unlink()
    export_mod.export(out, FRAMES, SEED, CFG, progress=False)
    assert f"resuming: 18 of {FRAMES} frames already written" in capsys.readouterr().err
    assert _tree(out) == _tree(root)


def test_cli_takes_the_preset_of_export_json(exported, tmp_path, capsys):
    root, _, _ = exported
    out = tmp_path / "resume"
    shutil.copytree(root, out)
    kitti.frame_paths(out, "000000")["labels"].unlink()
    args = ["--frames", str(FRAMES), "--seed", str(SEED), "--no-progress", "--cache", ""]
    assert main(["export", "--out", str(out), *args]) == 0, capsys.readouterr().err
    assert _tree(out) == _tree(root)
    assert json.loads((out / "export.json").read_text())["config"]["name"] == "tiny"
    # show: the same pictures as with the tiny config (the paper grid would not fit the masks).
    ids = ["000000", "000019"]
    assert main(["show", str(root), "--out", str(tmp_path / "cli"), "--ids", *ids]) == 0
    ref = show.show(root, tmp_path / "ref", CFG, ids)
    for path in ref:
        assert (tmp_path / "cli" / path.name).read_bytes() == path.read_bytes()


def test_an_export_short_of_a_split_says_how_many_frames_give_every_split(cache, tmp_path, capsys):
    """The note's --frames N is the fewest whole scenes that hold all three splits. A
    mutation audit: the note saying 9 scenes' frames (no test scene among them) passed."""
    import math
    import re

    args = ["--frames", "2", "--seed", str(SEED), "--preset", "tiny", "--no-progress"]
    assert main(["export", "--out", str(tmp_path / "ds"), *args, "--cache", ""]) == 0
    out = capsys.readouterr()
    assert out.out.split() == ["train=2", "val=0", "test=0"]
    n = int(re.search(r"--frames >= (\d+) gives every split", out.err).group(1))
    per_scene = CFG.sim.frames_per_sequence
    splits = {export_mod.scene_split(j) for j in range(math.ceil(n / per_scene))}
    fewer = {export_mod.scene_split(j) for j in range(math.ceil(n / per_scene) - 1)}
    assert splits == {"train", "val", "test"} and fewer != splits


def test_show_draws_with_the_whole_config_of_export_json(exported, tmp_path, capsys):
    """An export with --set grid.x_range=... was drawn with its preset's grid (the preset
    alone was read from export.json): masks 5 m off their boxes, exit 0."""
    root, _, _ = exported
    shifted = tmp_path / "shifted"
    shutil.copytree(root, shifted)
    meta = json.loads((shifted / "export.json").read_text())
    meta["config"]["grid"]["x_range"] = [v + 1.0 for v in meta["config"]["grid"]["x_range"]]
    (shifted / "export.json").write_text(json.dumps(meta))
    config = Config.from_dict(meta["config"])
    assert config.grid.shape == CFG.grid.shape and config.grid != CFG.grid
    fid = kitti.list_frames(shifted)[0]
    assert main(["show", str(shifted), "--out", str(tmp_path / "cli"), "--ids", fid]) == 0
    want = show.show(shifted, tmp_path / "want", config, [fid])[0].read_bytes()
    preset = show.show(shifted, tmp_path / "preset", CFG, [fid])[0].read_bytes()
    assert (tmp_path / "cli" / f"{fid}.png").read_bytes() == want != preset
    # --set still applies over it, and --preset still replaces it.
    argv = ["show", str(shifted), "--out", str(tmp_path / "set"), "--ids", fid]
    assert main([*argv, "--set", f"grid.x_range={list(CFG.grid.x_range)}"]) == 0
    assert (tmp_path / "set" / f"{fid}.png").read_bytes() == preset
    argv = ["show", str(shifted), "--out", str(tmp_path / "tiny"), "--ids", fid]
    assert main([*argv, "--preset", "tiny"]) == 0
    assert (tmp_path / "tiny" / f"{fid}.png").read_bytes() == preset


def test_show_refuses_to_write_into_the_datasets_own_folders(exported, tmp_path, capsys):
    """``show DS --out DS/mask_2`` replaced the dataset's masks with RGB pictures, exit 0."""
    root, _, _ = exported
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    before = _tree(copy)
    fid = kitti.list_frames(copy)[0]
    for sub in ("mask_2", "label_2", "velodyne"):
        out = copy / sub
        assert main(["show", str(copy), "--out", str(out), "--ids", fid, "--preset", "tiny"]) == 2
        err = capsys.readouterr().err
        assert f"--out {out}: a data folder of the dataset {copy}; use another folder" in err
    assert _tree(copy) == before


def test_show_refuses_a_missing_folder(tmp_path, capsys):
    missing = tmp_path / "no_such_export"
    assert main(["show", str(missing), "--out", str(tmp_path / "pics")]) == 2
    assert f"{missing}: no such dataset folder" in capsys.readouterr().err
    tmp_path.joinpath("label_2").mkdir()  # "--ids" and no id wrote 0 pictures, status 0
    assert main(["show", str(tmp_path), "--out", str(tmp_path / "pics"), "--ids"]) == 2
    assert "--ids: name at least one frame id" in capsys.readouterr().err
    assert not (tmp_path / "pics").exists()


def test_show_takes_a_class_map_for_data_of_ones_own(exported, tmp_path, capsys):
    """A folder whose labels name a class otherwise (a user's "Desk") shows with --set
    data.class_map, as dataset check and eval take it; without it the class is named."""
    root, _, _ = exported
    own = tmp_path / "own"
    shutil.copytree(root, own)
    fid = next(
        f
        for f in kitti.list_frames(own)
        if "Table" in kitti.frame_paths(own, f)["labels"].read_text()
    )
    label = kitti.frame_paths(own, fid)["labels"]
    label.write_text(label.read_text().replace("Table", "Desk"))
    argv = ["show", str(own), "--out", str(tmp_path / "pics"), "--ids", fid, "--preset", "tiny"]
    assert main(argv) == 2
    assert "unknown class 'Desk'" in capsys.readouterr().err
    assert main([*argv, "--set", 'data.class_map={"Desk": "Table"}']) == 0
    assert (tmp_path / "pics" / f"{fid}.png").exists()


def test_a_fresh_export_with_a_cut_scene_says_nothing_of_resuming(tmp_path, capsys):
    """A fresh export of 3 frames (scenes of 2, the last cut after one frame) has written
    nothing before, so it prints no "resuming:" line. Guards against counting the frames
    kept as frames - (scenes to do) x (frames a scene), which printed "resuming: -1 of 3"."""
    export_mod.export(tmp_path / "odd", 3, SEED, CFG, progress=False)
    assert "resuming" not in capsys.readouterr().err


def test_an_odd_frame_count_cuts_the_last_scene(exported, tmp_path):
    """--frames 3 with 2 frames a scene: scenes 0 and 1, the second cut after its first
    frame. Exactly frames 000000-000002 are written, equal to those of the 20-frame export
    (frames are a function of seed, scene and time), and the split lists hold those 3 (the
    whole last scene was written and listed, 4 frames; a mutation audit)."""
    root, _, _ = exported
    out = tmp_path / "odd"
    splits = export_mod.export(out, 3, SEED, CFG, progress=False)
    ids = ["000000", "000001", "000002"]
    assert splits == {"train": ids, "val": [], "test": []}
    assert kitti.list_frames(out) == ids and kitti.read_split(out, "train") == ids
    for sub in ("velodyne", "label_2", "mask_2"):
        names = sorted(p.name for p in (out / sub).iterdir())
        assert [n.split(".")[0] for n in names] == ids, sub
        match, mismatch, errors = filecmp.cmpfiles(root / sub, out / sub, names, shallow=False)
        assert not mismatch and not errors, (sub, mismatch, errors)
