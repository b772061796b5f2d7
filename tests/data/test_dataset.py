"""KittiDataset: static shapes, invalid points counted, masks from files or boxes."""

import json

import numpy as np
import pytest

from indoorbev_jax.cli import main as cli_main
from indoorbev_jax.config import CLASS_NAMES, NUM_CLASSES, Config
from indoorbev_jax.data import kitti
from indoorbev_jax.data.dataset import KittiDataset, collate, make_targets, pad_points
from indoorbev_jax.data.rasterize import rasterize_boxes

CFG = Config.tiny()


def labels_two_objects():
    return kitti.ObjectLabels(
        classes=[0, 6],
        dims=[[2.0, 1.0, 0.8], [0.5, 0.5, 1.7]],
        pos=[[1.0, 1.0, 0.4], [-2.0, 0.5, 0.85]],
        yaw=[0.3, 0.0],
        occlusion=[0, 1],
    )


def make_dataset(root):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-2.5, 2.5, (500, 4)).astype(np.float32)
    pts[:, 3] = rng.random(500)  # intensity in [0, 1], as the model takes it
    pts[:5] = np.nan
    pts[5:10, 0] = 50.0  # outside the workspace
    kitti.write_frame(root, "000000", pts, labels_two_objects(), CLASS_NAMES)
    ids = np.zeros(CFG.grid.shape, np.int32)
    ids[10:14, 10:20] = 1
    ids[20, 20] = 2
    kitti.write_frame(
        root, "000001", np.zeros((0, 4), np.float32), labels_two_objects(), CLASS_NAMES, ids
    )
    kitti.write_frame(root, "000002", pts[20:30], kitti.ObjectLabels.empty(), CLASS_NAMES)
    kitti.write_split(root, "train", ["000000", "000001", "000002"])


def test_frames_are_padded_static_shape(tmp_path):
    make_dataset(tmp_path)
    ds = KittiDataset(tmp_path, "train", CFG)
    item, stats = ds.load(0)
    n, m = CFG.data.max_points, CFG.data.max_objects
    assert item.points.shape == (n, 4) and item.point_valid.shape == (n,)
    assert stats.nonfinite_points == 5 and stats.outside_points == 5
    assert item.point_valid.sum() == 490 == stats.valid_points
    assert np.isfinite(item.points).all()
    t = item.targets
    assert t.classes.tolist() == [0, 6] + [NUM_CLASSES] * (m - 2)
    assert t.masks.shape == (m, *CFG.grid.shape)
    # Without mask_2 the footprints are the labelled boxes.
    boxes = np.zeros((m, 5), np.float32)
    boxes[:2] = labels_two_objects().boxes_bev()
    ids, masks = rasterize_boxes(boxes, t.valid, CFG.grid)
    np.testing.assert_array_equal(t.masks, masks)
    np.testing.assert_array_equal(t.instance_ids, ids)


def test_points_in_the_sensors_blind_zone_are_invalid_and_counted(tmp_path):
    cfg = Config.tiny()
    r = cfg.sim.min_range
    pts = np.array(
        [[0.0, 0.0, 0.0, 0.0],  # a driver's "no return" point
         [0.03, 0.04, 0.0, 0.5],  # 5 cm from the sensor
         [r, 0.0, 0.0, 0.5],  # on the blind zone's edge: a return the simulator can give
         [0.0, -1.0, 0.5, 0.5],
         [np.nan, 0.0, 0.0, 0.5],
         [50.0, 0.0, 0.0, 0.5],
         [0.0, 1.0, 0.5, 1e25]], np.float32  # an intensity that overflows the encoder
    )  # fmt: skip
    kitti.write_frame(tmp_path, "a", pts, kitti.ObjectLabels.empty(), CLASS_NAMES)
    item, stats = KittiDataset(tmp_path, None, cfg).load(0)
    assert (stats.nonfinite_points, stats.blind_points, stats.outside_points) == (2, 2, 1)
    assert stats.valid_points == 2 == item.point_valid.sum()
    np.testing.assert_array_equal(item.points[item.point_valid], pts[2:4])
    # min_range 0 (pad_points' default) keeps every finite point inside the workspace.
    _, valid, counts = pad_points(pts, cfg.grid, cfg.data.max_points)
    assert counts["blind_points"] == 0 and valid.sum() == 4


def test_mask_file_gives_true_shape_and_empty_cloud_is_valid(tmp_path):
    make_dataset(tmp_path)
    ds = KittiDataset(tmp_path, "train", CFG)
    item, stats = ds.load(1)
    assert stats.raw_points == 0 and not item.point_valid.any()
    assert item.targets.masks[0].sum() == 40 and item.targets.masks[1].sum() == 1
    assert item.targets.instance_ids[20, 20] == 2
    empty, _ = ds.load(2)
    assert not empty.targets.valid.any() and (empty.targets.instance_ids == 0).all()
    batch = collate([ds.load(k)[0] for k in range(3)])
    assert batch.points.shape == (3, CFG.data.max_points, 4)
    assert batch.targets.masks.shape == (3, CFG.data.max_objects, *CFG.grid.shape)
    # Footprints of another grid: set_loss blamed the predictions' masks for them.
    with pytest.raises(
        ValueError,
        match=r"instance_ids: expected the grid's \[H, W\] = \[40, 40\], got shape \[50, 50\]",
    ):
        make_targets(kitti.ObjectLabels.empty(), CFG.grid, 4, np.zeros((50, 50), np.int32))


def test_more_points_than_max_keeps_an_even_spread(tmp_path):
    cfg = Config.tiny()
    n = cfg.data.max_points
    # A spinning lidar's scan: points in azimuth order, some invalid among them.
    rng = np.random.default_rng(0)
    azimuth = np.sort(rng.uniform(-np.pi, np.pi, 3 * n + 17))
    radius = rng.uniform(0.5, 2.0, azimuth.shape)
    pts = np.stack(
        [radius * np.cos(azimuth), radius * np.sin(azimuth), rng.uniform(-1, 1, azimuth.shape),
         rng.uniform(0, 1, azimuth.shape)], 1
    ).astype(np.float32)  # fmt: skip
    pts[::7, 2] = np.nan
    kitti.write_frame(tmp_path, "a", pts, kitti.ObjectLabels.empty(), CLASS_NAMES)
    item, stats = KittiDataset(tmp_path, None, cfg).load(0)
    valid = np.flatnonzero(np.isfinite(pts).all(1))
    assert stats.nonfinite_points == len(pts) - len(valid)
    assert stats.dropped_points == len(valid) - n and item.point_valid.all()
    # Kept: the valid points at floor(k * count / n), in scan order.
    expected = [valid[k * len(valid) // n] for k in range(n)]
    np.testing.assert_array_equal(item.points, pts[expected])
    # So the kept points cover every azimuth (the first n would leave a gap of about 3.8 rad).
    kept_azimuth = azimuth[expected]
    gaps = np.diff(np.concatenate([kept_azimuth, [kept_azimuth[0] + 2 * np.pi]]))
    assert gaps.max() < 0.05


def test_objects_beyond_max_objects_are_counted_and_reported(tmp_path, capsys):
    """Only the first data.max_objects labels become targets; the rest are counted in
    FrameStats.dropped_objects, and ``dataset check`` reports them as a problem (exit 1)."""
    m = CFG.data.max_objects
    n = m + 2
    labels = kitti.ObjectLabels(
        classes=[k % NUM_CLASSES for k in range(n)],
        dims=[[0.5, 0.5, 0.5]] * n,
        pos=[[0.4 * k - 3.0, 0.5, 0.25] for k in range(n)],
        yaw=[0.0] * n,
        occlusion=[0] * n,
    )
    pts = np.random.default_rng(0).uniform(-2, 2, (200, 4)).astype(np.float32)
    kitti.write_frame(tmp_path, "000000", pts, labels, CLASS_NAMES)
    item, stats = KittiDataset(tmp_path, None, CFG).load(0)
    assert stats.objects == n and stats.dropped_objects == n - m == 2
    assert item.targets.valid.sum() == m
    assert item.targets.classes.tolist() == [k % NUM_CLASSES for k in range(m)]
    assert cli_main(["dataset", "check", str(tmp_path), "--preset", "tiny"]) == 1
    out = capsys.readouterr().out
    assert f"objects beyond data.max_objects: {n - m}" in out
    assert f"000000: {n} objects, only the first {m} fit data.max_objects" in out


def test_a_mask_id_past_the_label_count_is_named(tmp_path):
    """A mask_2 instance id k refers to label line k: an id beyond the label file's objects
    is an unlabelled footprint, refused naming the mask (it was dropped without a word)."""
    make_dataset(tmp_path)
    ids = np.zeros(CFG.grid.shape, np.int32)
    ids[10:14, 10:20] = 1
    ids[20, 20] = 3  # the label file has 2 objects
    kitti.write_frame(
        tmp_path, "000001", np.zeros((0, 4), np.float32), labels_two_objects(), CLASS_NAMES, ids
    )
    ds = KittiDataset(tmp_path, "train", CFG)
    with pytest.raises(
        kitti.DatasetError, match=r"mask_2/000001\.png: instance id 3 but the label file has 2 "
    ):
        ds.load(1)


def test_batches_drop_the_short_last_batch_only_when_asked(tmp_path):
    """``batches`` keeps one static batch shape (jit compiles once) by dropping the remainder
    by default; ``drop_remainder=False`` yields it as a short last batch. Frames come in
    ``order``."""
    for k in range(5):
        pts = np.array([[0.5 + 0.5 * k, 0.0, 0.0, 0.5]], np.float32)
        kitti.write_frame(tmp_path, f"{k:06d}", pts, kitti.ObjectLabels.empty(), CLASS_NAMES)
    ds = KittiDataset(tmp_path, None, CFG)

    def frames(batches):  # the frame index of each batch element, from its one point's x
        return [np.round((b.points[:, 0, 0] - 0.5) / 0.5).astype(int).tolist() for b in batches]

    assert frames(ds.batches(2)) == [[0, 1], [2, 3]]
    assert frames(ds.batches(2, drop_remainder=False)) == [[0, 1], [2, 3], [4]]
    assert frames(ds.batches(2, order=[4, 3, 2, 1, 0])) == [[4, 3], [2, 1]]


def test_split_id_without_files_is_named(tmp_path):
    make_dataset(tmp_path)
    kitti.write_split(tmp_path, "val", ["000000", "000777"])
    with pytest.raises(
        kitti.DatasetError,
        match=r"val\.txt: 2 file\(s\) of its frames are missing.*velodyne/000777\.bin",
    ):
        KittiDataset(tmp_path, "val", CFG)


def test_mask_of_wrong_size_is_named(tmp_path):
    kitti.write_frame(
        tmp_path,
        "a",
        np.zeros((1, 4), np.float32),
        labels_two_objects(),
        CLASS_NAMES,
        np.zeros((7, 7), np.int32),
    )
    with pytest.raises(kitti.DatasetError, match=r"mask_2/a\.png: mask of shape \(7, 7\)"):
        KittiDataset(tmp_path, None, CFG).load(0)


def test_dataset_check_cli(tmp_path, capsys):
    make_dataset(tmp_path)
    assert (
        cli_main(["dataset", "check", str(tmp_path), "--split", "train", "--preset", "tiny"]) == 0
    )
    out = capsys.readouterr().out
    assert "frames: 3 (0 unreadable)" in out
    assert "Table           2" in out and "Person          2" in out
    assert (
        "invalid points (non-finite, within sim.min_range=0.1 m of the sensor, or outside the "
        "workspace): 10" in out
    )
    (tmp_path / "label_2" / "000002.txt").write_text("Table 1 2\n")
    assert cli_main(["dataset", "check", str(tmp_path), "--preset", "tiny"]) == 1
    out = capsys.readouterr().out
    assert "000002.txt:1: expected 15 fields" in out
    # A bad --set is a usage error (2), not "the dataset has problems" (1).
    argv = ["dataset", "check", str(tmp_path), "--preset", "tiny", "--set", "grid.cel=1"]
    assert cli_main(argv) == 2
    assert "indoorbev dataset check: error: " in capsys.readouterr().err


def test_check_dataset_reports_what_the_frames_hold(tmp_path):
    """The Python API of ``dataset check``: counts re-derived from the label files and the
    clouds, and an unreadable frame a problem of the report, not an exception."""
    from indoorbev_jax.data.check import check_dataset

    make_dataset(tmp_path)
    report = check_dataset(tmp_path, "train", CFG)
    ids = kitti.read_split(tmp_path, "train")
    labels = [kitti.read_labels(tmp_path / "label_2" / f"{i}.txt", CFG.data) for i in ids]
    expected = np.bincount(np.concatenate([lab.classes for lab in labels]), minlength=NUM_CLASSES)
    np.testing.assert_array_equal(report.class_counts, expected)
    assert report.ok and report.frames == 3 and report.source == "preset tiny"
    clouds = [np.fromfile(tmp_path / "velodyne" / f"{i}.bin", np.float32) for i in ids]
    assert report.raw_points == [c.size // 4 for c in clouds] == [500, 0, 10]
    assert report.invalid_points == 5 + 5  # NaN rows and x = 50 m, in frame 000000 only
    assert "mask_2: 2 frame(s) have no mask" in report.warnings[0]  # 000001 has one
    assert report.warnings[1:] == ["000001: an empty cloud"]
    (tmp_path / "label_2" / "000002.txt").write_text("Table 1 2\n")
    report = check_dataset(tmp_path, "train", CFG)
    assert not report.ok and len(report.valid_points) == 2
    assert "000002.txt:1: expected 15 fields" in report.problems[0]
    assert "frames: 3 (1 unreadable)" in report.format()
    # Without a config: the folder's export.json (here none: the small preset).
    assert check_dataset(tmp_path, "train").config == Config.small()


def test_check_dataset_statistics_span_every_frame(tmp_path):
    """Over frames of 10, 20 and 300 valid points with intensity up to exactly 1.0: no
    intensity warning (the model takes [0, 1]), the median of the point counts (20, the
    mean is 110), objects beyond data.max_objects summed over the frames (2 + 2), and an
    empty split a problem (the module docstring). A warning at intensity 1, the mean for
    the median, the last frame's dropped objects only and an empty split passed as fine
    each passed every test (a mutation audit)."""
    from indoorbev_jax.data.check import check_dataset

    rng = np.random.default_rng(0)
    n = CFG.data.max_objects + 2
    crowded = kitti.ObjectLabels(
        classes=[k % NUM_CLASSES for k in range(n)], dims=[[0.5, 0.5, 0.5]] * n,
        pos=[[0.4 * k - 3.0, 0.5, 0.25] for k in range(n)], yaw=[0.0] * n, occlusion=[0] * n,
    )  # fmt: skip
    for k, size in enumerate((10, 20, 300)):
        points = np.c_[rng.uniform(-2, 2, (size, 2)), rng.uniform(0, 1, size),
                       np.linspace(0.0, 1.0, size)].astype(np.float32)  # fmt: skip
        labels = crowded if k else kitti.ObjectLabels.empty()
        kitti.write_frame(tmp_path, f"{k:06d}", points, labels, CLASS_NAMES)
    kitti.write_split(tmp_path, "val", [])
    report = check_dataset(tmp_path, None, CFG)
    assert report.valid_points == [10, 20, 300] and report.dropped_objects == 4
    assert not [w for w in report.warnings if "intensity" in w]
    text = report.format()
    assert "min 10  median 20  mean 110.0  max 300" in text
    assert "objects beyond data.max_objects: 4" in text
    empty = check_dataset(tmp_path, "val", CFG)
    assert not empty.ok and empty.problems[0] == f"{tmp_path}: no frames in split val"


def test_dataset_check_names_lost_files(tmp_path, capsys):
    """A cloud whose label file is lost is no frame, and a frame without a mask where
    mask_2/ exists falls back to its boxes: both were passed over in silence. A split
    naming a frame says which of its files is missing."""
    make_dataset(tmp_path)
    kitti.write_frame(tmp_path, "000003", np.zeros((4, 4), np.float32),
                      kitti.ObjectLabels.empty(), CLASS_NAMES)  # fmt: skip
    (tmp_path / "label_2" / "000003.txt").unlink()
    assert cli_main(["dataset", "check", str(tmp_path), "--preset", "tiny"]) == 0
    out = capsys.readouterr().out
    assert "1 cloud(s) have no label_2 file, so are no frame, e.g. ['000003.bin']" in out
    assert (
        "2 frame(s) have no mask, so their footprints are the label boxes, e.g. "
        "['000000.png', '000002.png']" in out
    )
    kitti.write_split(tmp_path, "train", ["000000", "000003"])
    assert (
        cli_main(["dataset", "check", str(tmp_path), "--split", "train", "--preset", "tiny"]) == 1
    )
    assert (
        "dataset check: error: "  # on stderr
        in (err := capsys.readouterr().err)
        and "e.g. ['label_2/000003.txt']" in err
    )


def test_dataset_check_warns_of_off_grid_objects_and_empty_clouds(tmp_path, capsys):
    """Legal but suspicious (units, frames): warned about, exit 0; the evaluator would leave
    the off-grid objects out. Ground truth with a score column is a problem."""
    make_dataset(tmp_path)
    far = labels_two_objects()
    far.pos = far.pos + [30.0, 0.0, 0.0]  # past the tiny grid's 10 m
    kitti.write_frame(tmp_path, "000003", np.full((50, 4), 20.0, np.float32), far, CLASS_NAMES)
    argv = ["dataset", "check", str(tmp_path), "--preset", "tiny"]
    assert cli_main(argv) == 0
    out = capsys.readouterr().out
    assert "warnings: 4; the first 4:" in out  # and three frames without a mask
    assert "000001: an empty cloud" in out
    assert "000003: none of its 50 points is valid" in out
    assert "000003: 2 of 2 objects cover no cell of the grid x [-5.0, 5.0]" in out
    assert out.rstrip().endswith("no problems found (4 warnings above)")
    livox = np.random.default_rng(1).uniform(-2.0, 2.0, (50, 4)).astype(np.float32)
    livox[:, 3] = np.linspace(0.0, 200.0, 50)  # 0-255 units: trained on as they are
    kitti.write_frame(tmp_path, "000001", livox, labels_two_objects(), CLASS_NAMES)
    assert cli_main(argv) == 0
    out = capsys.readouterr().out
    assert "000001: intensity up to 200; the model takes [0, 1]" in out
    assert "000001: an empty cloud" not in out
    scored = labels_two_objects()
    scored.scores = np.ones(2)
    kitti.write_labels(tmp_path / "label_2" / "000002.txt", scored, CLASS_NAMES)
    assert cli_main(argv) == 1
    assert "000002.txt: a score column (16th field); ground truth has 15" in capsys.readouterr().out


def test_dataset_check_lists_max_problems_and_no_false_orphans(tmp_path, capsys):
    """``--max-problems N`` lists N warnings (docs/DATASET.md), and with ``--split`` the
    clouds of frames outside the split are not "clouds without a label_2 file". A mutation
    audit: listing N - 1 and that false warning under --split both passed."""
    cloud = np.random.default_rng(0).uniform(0.0, 1.0, (200, 4)).astype(np.float32)
    for k in range(12):  # 11 empty clouds: 11 warnings; every frame has its labels
        kitti.write_frame(tmp_path, f"{k:06d}", np.zeros((0, 4), np.float32) if k else cloud,
                          kitti.ObjectLabels.empty(), CLASS_NAMES)  # fmt: skip
    argv = ["dataset", "check", str(tmp_path), "--preset", "tiny"]
    assert cli_main([*argv, "--max-problems", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    start = lines.index("warnings: 11; the first 3:")
    listed = [line.startswith("  ") for line in lines[start + 1 : start + 5]]
    assert listed == [True, True, True, False]  # 3 listed, then the next part
    assert cli_main(argv) == 0  # the documented default: 10 of the 11
    lines = capsys.readouterr().out.splitlines()
    start = lines.index("warnings: 11; the first 10:")
    listed = [line.startswith("  ") for line in lines[start + 1 : start + 12]]
    assert listed == [True] * 10 + [False]
    with pytest.raises(SystemExit) as refused:  # listing none would hide every warning
        cli_main([*argv, "--max-problems", "0"])
    assert refused.value.code == 2
    assert "--max-problems: must be > 0, got 0" in capsys.readouterr().err
    kitti.write_split(tmp_path, "train", ["000000"])
    assert cli_main([*argv, "--split", "train"]) == 0
    out = capsys.readouterr().out
    assert "no label_2 file" not in out and out.rstrip().endswith("no problems found")


def test_dataset_commands_take_the_exports_config_and_set(tmp_path, capsys):
    """Without --preset, check and eval read the grid and classes from export.json; --set
    maps a class name; an empty split is a problem; files are world-readable as umask says."""
    import os

    make_dataset(tmp_path)
    (tmp_path / "export.json").write_text(json.dumps({"seed": 0, "config": CFG.to_dict()}))
    # The tiny grid's mask would not fit the default (small) preset's grid.
    assert cli_main(["dataset", "check", str(tmp_path), "--split", "train"]) == 0
    assert f"the config of {tmp_path / 'export.json'} (preset tiny)" in capsys.readouterr().out
    kitti.write_split(tmp_path, "val", [])
    assert cli_main(["dataset", "check", str(tmp_path), "--split", "val"]) == 1
    assert f"{tmp_path}: no frames in split val" in capsys.readouterr().out
    (tmp_path / "label_2" / "000002.txt").write_text(
        (tmp_path / "label_2" / "000000.txt").read_text().replace("Table", "Desk")
    )
    assert cli_main(["dataset", "check", str(tmp_path), "--split", "train"]) == 1
    assert "unknown class 'Desk'" in capsys.readouterr().out
    mapped = ["--set", 'data.class_map={"Desk": "Table"}']
    assert cli_main(["dataset", "check", str(tmp_path), "--split", "train", *mapped]) == 0
    capsys.readouterr()
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "train.txt").stat().st_mode & 0o777 == 0o666 & ~umask


def test_eval_names_missing_ground_truth_duplicates_and_bad_json_paths(tmp_path, capsys):
    make_dataset(tmp_path / "gt")
    pred = tmp_path / "pred"
    for fid in ("000000", "000001", "000002"):
        scored = kitti.read_labels(tmp_path / "gt" / "label_2" / f"{fid}.txt", CFG.data)
        scored.scores = np.ones(len(scored), np.float32)
        kitti.write_labels(pred / "label_2" / f"{fid}.txt", scored, CLASS_NAMES)
    argv = ["eval", "--gt", str(tmp_path / "gt"), "--pred", str(pred), "--preset", "tiny"]
    # A split naming a frame whose ground truth is missing: named, no traceback.
    kitti.write_split(tmp_path / "gt", "odd", ["000000", "777777"])
    assert cli_main([*argv, "--split", "odd"]) == 1
    out = capsys.readouterr().err
    assert "odd.txt: 1 of 2 frames have no ground-truth label file, e.g. " in out
    assert "777777.txt" in out
    # The same id twice would count its frame twice.
    (tmp_path / "gt" / "dup.txt").write_text("000000\n000001\n\n000000\n")
    assert cli_main([*argv, "--split", "dup"]) == 1
    assert "dup.txt:4: frame id '000000' again (first on line 1)" in capsys.readouterr().err
    # An unusable --json path fails before the evaluation, not after it.
    (tmp_path / "file").write_text("")
    assert cli_main([*argv, "--split", "train", "--json", str(tmp_path / "file" / "x")]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith("indoorbev eval: error:") and "frames:" not in captured.out
    assert cli_main([*argv, "--split", "train", "--json", str(tmp_path)]) == 1
    assert f"--json {tmp_path}: is a folder, expected a file name" in capsys.readouterr().err
    # The file's folder is made, parents included.
    nested = tmp_path / "reports" / "2026" / "m.json"
    assert cli_main([*argv, "--split", "train", "--json", str(nested)]) == 0
    assert "ap" in json.loads(nested.read_text())


def test_eval_refuses_scored_ground_truth_and_notes_extra_predictions(tmp_path, capsys):
    make_dataset(tmp_path / "gt")
    pred = tmp_path / "pred"
    for fid in ("000000", "000001", "000002", "000009"):
        labels = kitti.read_labels(tmp_path / "gt" / "label_2" / "000000.txt", CFG.data)
        labels.scores = np.ones(len(labels), np.float32)
        kitti.write_labels(pred / "label_2" / f"{fid}.txt", labels, CLASS_NAMES)
    argv = ["eval", "--preset", "tiny"]
    assert cli_main([*argv, "--gt", str(tmp_path / "gt"), "--pred", str(pred)]) == 0
    assert "note: 1 prediction files have no ground truth" in capsys.readouterr().out
    (pred / "label_2" / "000009.txt").unlink()
    assert cli_main([*argv, "--gt", str(pred), "--pred", str(tmp_path / "gt")]) == 1
    assert "000000.txt: ground truth with a score column" in capsys.readouterr().err


def test_collate_keeps_each_frames_own_point_validity(tmp_path):
    """collate stacks the items along a new axis, every field its own frame's: a frame with
    few valid points next to one with many keeps its own ``point_valid`` (a wrong mask would
    feed padding as points, or drop real ones, silently). A mutation audit (every frame given
    the first frame's ``point_valid``) passed all tests."""
    make_dataset(tmp_path)
    ds = KittiDataset(tmp_path, "train", CFG)
    items = [ds.load(k)[0] for k in (2, 0, 1)]
    counts = [int(b.point_valid.sum()) for b in items]
    assert len(set(counts)) == 3  # three different valid counts, one of them 0
    batch = collate(items)
    for k, item in enumerate(items):
        np.testing.assert_array_equal(batch.point_valid[k], item.point_valid)
        np.testing.assert_array_equal(batch.points[k], item.points)
        np.testing.assert_array_equal(batch.targets.masks[k], item.targets.masks)
    np.testing.assert_array_equal(batch.point_valid.sum(1), counts)
