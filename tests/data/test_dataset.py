"""KittiDataset: static shapes, invalid points counted, masks from files or boxes."""

import numpy as np
import pytest

from indoorbev_jax.cli import main as cli_main
from indoorbev_jax.config import CLASS_NAMES, NUM_CLASSES, Config
from indoorbev_jax.data import kitti
from indoorbev_jax.data.dataset import KittiDataset, collate
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


def test_split_id_without_files_is_named(tmp_path):
    make_dataset(tmp_path)
    kitti.write_split(tmp_path, "val", ["000000", "000777"])
    with pytest.raises(kitti.DatasetError, match=r"val\.txt: 1 frame id.*000777"):
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
    assert "invalid points (non-finite or outside the workspace): 10" in out
    (tmp_path / "label_2" / "000002.txt").write_text("Table 1 2\n")
    assert cli_main(["dataset", "check", str(tmp_path), "--preset", "tiny"]) == 1
    out = capsys.readouterr().out
    assert "000002.txt:1: expected 15 fields" in out
