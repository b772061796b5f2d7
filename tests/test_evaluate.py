"""``indoorbev eval`` (evaluate.py): KITTI-layout folders to metrics, bad folders named, the
JSON keeping real zeros. The metric functions themselves are checked against pycocotools
and numpy re-derivations in test_metrics.py; here the values follow from the definitions."""

import json
import math
import re

import numpy as np
import pytest

from indoorbev_jax.cli import main
from indoorbev_jax.config import Config
from indoorbev_jax.data import kitti
from indoorbev_jax.evaluate import evaluate_folders, to_json

CFG = Config.tiny()  # grid -5..5 m, 0.25 m cells
NAMES = CFG.data.class_names


def _labels(xy, scores=None):
    """Chairs of 0.5 x 0.5 x 1 m, heading 0, centred on ``xy`` [M, 2] (whole metres: each
    covers its own 2 x 2 cells)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    dims, pos = np.tile([0.5, 0.5, 1.0], (n, 1)), np.c_[xy, np.full(n, 0.5)]
    return kitti.ObjectLabels([1] * n, dims, pos, np.zeros(n), np.zeros(n), scores)


def test_more_than_16_boxes_without_masks(tmp_path):
    """Without mask_2 the boxes are rasterised in batches padded to a multiple of 16: 20
    objects, 19 found and the last (lowest-scored) one placed where there is none. COCO AP:
    precision 1 at the 101 recall points up to recall 19 / 20 (in float64, as pycocotools
    compares them), 0 past it; PQ: 19 exact matches, one false positive and one miss,
    RQ = 19 / (19 + 1 / 2 + 1 / 2)."""
    gt = np.stack(np.meshgrid(np.arange(-3.0, 2.0), np.arange(-3.0, 1.0)), -1).reshape(-1, 2)
    pred = gt.copy()
    pred[-1] = (3.0, 3.0)
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels(gt), NAMES)
    scores = np.linspace(0.9, 0.5, 20)
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", _labels(pred, scores), NAMES)
    res = evaluate_folders(tmp_path / "gt", tmp_path / "pred", CFG)
    ap = np.mean(np.linspace(0.0, 1.0, 101) <= 19 / 20)
    assert res["ap"] == {0.25: pytest.approx(ap), 0.5: pytest.approx(ap)}
    assert res["sq"] == pytest.approx(1.0) and res["rq"] == pytest.approx(0.95)
    assert res["pq"] == pytest.approx(0.95)


def test_a_mask_id_past_the_label_lines_is_named(tmp_path):
    """Mask id k is the object on line k: an id 2 in a mask of a one-object label file is a
    DatasetError naming the PNG, not the metrics' ValueError about ids."""
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels([[0.0, 0.0]]), NAMES)
    ids = np.zeros(CFG.grid.shape, np.int32)
    ids[5:9, 5:9] = 2
    kitti.write_mask(tmp_path / "gt/mask_2/a.png", ids)
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", _labels([[0.0, 0.0]], [0.9]), NAMES)
    mask = tmp_path / "gt/mask_2/a.png"
    message = rf"^{re.escape(str(mask))}: instance id 2 but the label file has only 1 objects"
    with pytest.raises(kitti.DatasetError, match=message):
        evaluate_folders(tmp_path / "gt", tmp_path / "pred", CFG)


def test_json_keeps_real_zeros_and_nulls_undefined_values(tmp_path, capsys):
    """Predictions that miss every object score AP 0 and PQ 0: real values, written as 0.0;
    undefined ones (NaN, AP's -1 for a class without objects) become null."""
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels([[-2.0, -2.0], [-1.0, -2.0]]), NAMES)
    far = _labels([[2.0, 2.0], [3.0, 2.0]], [0.9, 0.8])
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", far, NAMES)
    out = tmp_path / "m.json"
    argv = ["eval", "--gt", str(tmp_path / "gt"), "--pred", str(tmp_path / "pred")]
    assert main([*argv, "--preset", "tiny", "--json", str(out)]) == 0
    capsys.readouterr()
    res = json.loads(out.read_text())
    assert res["ap"] == {"0.25": 0.0, "0.5": 0.0}
    assert res["pq"] == 0.0 and res["rq"] == 0.0
    undefined = {"ap": {0.25: -1.0, 0.5: 0.0}, "pq": 0.0, "sq": math.nan, "frames": 3}
    assert json.loads(to_json(undefined)) == {"ap": {"0.25": None, "0.5": 0.0}, "pq": 0.0,
                                              "sq": None, "frames": 3}  # fmt: skip


def test_json_never_replaces_a_file_of_either_dataset(tmp_path, capsys):
    """``--json GT/export.json`` replaced the record the next eval reads its config from,
    exit 0; ``--json ""`` wrote nothing and said nothing."""
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels([[-2.0, -2.0]]), NAMES)
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", _labels([[-2.0, -2.0]], [0.9]), NAMES)
    (tmp_path / "gt/export.json").write_text("{}")
    argv = ["eval", "--gt", str(tmp_path / "gt"), "--pred", str(tmp_path / "pred"), "--preset",
            "tiny", "--json"]  # fmt: skip
    for out in ("gt/export.json", "gt/train.txt", "pred/label_2/a.txt", "gt/mask_2/a.json"):
        assert main([*argv, str(tmp_path / out)]) == 1
        root = (tmp_path / out.split("/")[0]).resolve()
        assert f"--json {tmp_path / out}: a file of the dataset {root}" in capsys.readouterr().err
    assert (tmp_path / "gt/export.json").read_text() == "{}"
    assert main([*argv, ""]) == 1
    assert "--json: an empty path; expected a file name" in capsys.readouterr().err
    assert main([*argv, str(tmp_path / "gt" / "metrics.json")]) == 0  # beside them is fine


def test_a_json_that_cannot_be_written_is_one_line_after_the_metrics(tmp_path, capsys, full_disk):
    """A disk that filled up during the evaluation gave a traceback; now one line names the
    file and the cause, and the metrics are still printed."""
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels([[-2.0, -2.0]]), NAMES)
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", _labels([[-2.0, -2.0]], [0.9]), NAMES)
    out = tmp_path / "m.json"
    argv = ["eval", "--gt", str(tmp_path / "gt"), "--pred", str(tmp_path / "pred"), "--preset",
            "tiny", "--json", str(out)]  # fmt: skip
    with full_disk():
        assert main(argv) == 1
    printed = capsys.readouterr()
    assert printed.err == (
        f"indoorbev eval: error: [Errno 28] cannot write {out}: No space left on device "
        "(the metrics are printed above)\n"
    )
    assert "ground truth" in printed.out and "Misc" in printed.out and not out.exists()


def test_an_empty_ground_truth_folder_is_named(tmp_path, capsys):
    """Without --split the frames are <gt>/label_2's files: the messages name that folder."""
    (tmp_path / "gt/label_2").mkdir(parents=True)
    (tmp_path / "pred/label_2").mkdir(parents=True)
    argv = ["eval", "--gt", str(tmp_path / "gt"), "--pred", str(tmp_path / "pred"), "--preset",
            "tiny"]  # fmt: skip
    assert main(argv) == 1
    label_2 = tmp_path / "gt" / "label_2"
    assert f"eval: error: {label_2}: no label files (*.txt)" in capsys.readouterr().err
    kitti.write_labels(label_2 / "a.txt", _labels([[0.0, 0.0]]), NAMES)
    assert main(argv) == 1
    assert f"error: {label_2}: 1 of 1 frames have no prediction label file" in (
        capsys.readouterr().err
    )
    assert main([*argv, "--set", "grid.cel=1"]) == 2  # a usage error, not the data's
    assert "indoorbev eval: error: " in capsys.readouterr().err


def test_scores_closer_than_float32_keep_the_files_ranking(tmp_path):
    """Scores are ranked as written (pycocotools keeps them float64): a true chair scored
    0.90000004 after a false one scored 0.90000001 on the line before is the first detection,
    so AP is 1. Read as float32 the two tie, the line order ranked the false one first and AP
    was precision 1/2 at recall 1, 0.5."""
    assert np.float32(0.90000001) == np.float32(0.90000004)  # the case is a float32 tie
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels([[0.0, 0.0]]), NAMES)
    path = tmp_path / "pred/label_2/a.txt"
    kitti.write_labels(path, _labels([[3.0, 3.0], [0.0, 0.0]], [0.25, 0.75]), NAMES)
    text = path.read_text().replace("0.250000", "0.90000001").replace("0.750000", "0.90000004")
    path.write_text(text)
    res = evaluate_folders(tmp_path / "gt", tmp_path / "pred", CFG)
    assert res["ap"] == {0.25: pytest.approx(1.0), 0.5: pytest.approx(1.0)}


def test_swapped_folders_are_named_as_such(tmp_path, capsys):
    """--gt and --pred swapped: the "ground truth" has a score column. The error names that
    file and asks whether the folders are swapped, also when the real ground truth (read as
    predictions) has no objects, which would otherwise pass as a frame with no detections."""
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels([[0.0, 0.0], [2.0, 2.0]]), NAMES)
    kitti.write_labels(tmp_path / "gt/label_2/b.txt", _labels([]), NAMES)
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", _labels([[0.0, 0.0]], [0.9]), NAMES)
    kitti.write_labels(tmp_path / "pred/label_2/b.txt", _labels([[1.0, 1.0]], [0.8]), NAMES)
    argv = ["eval", "--gt", str(tmp_path / "pred"), "--pred", str(tmp_path / "gt"), "--preset",
            "tiny"]  # fmt: skip
    assert main(argv) == 1
    swapped = tmp_path / "pred/label_2/a.txt"
    message = f"error: {swapped}: ground truth with a score column (16th); are the ground truth"
    assert message in capsys.readouterr().err
    # Frame b alone: its true ground truth, read as predictions, holds no object.
    (tmp_path / "pred/only_b.txt").write_text("b\n")
    b_txt = re.escape(f"{tmp_path / 'pred/label_2/b.txt'}: ground truth with a score column")
    with pytest.raises(kitti.DatasetError, match=f"^{b_txt}"):
        evaluate_folders(tmp_path / "pred", tmp_path / "gt", CFG, split="only_b")


def test_prediction_files_without_ground_truth_are_noted(tmp_path, capsys):
    """Without --split the frames are the ground truth's: a prediction file with no ground
    truth is not evaluated, and the command says so (with --split other frames' predictions
    are expected, so it does not)."""
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels([[0.0, 0.0]]), NAMES)
    (tmp_path / "gt/val.txt").write_text("a\n")
    for frame in ("a", "b", "c"):
        path = tmp_path / f"pred/label_2/{frame}.txt"
        kitti.write_labels(path, _labels([[0.0, 0.0]], [0.9]), NAMES)
    argv = ["eval", "--gt", str(tmp_path / "gt"), "--pred", str(tmp_path / "pred"), "--preset",
            "tiny"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "note: 2 prediction files have no ground truth and are not evaluated, e.g. b" in out
    assert "frames: 1" in out
    assert main([*argv, "--split", "val"]) == 0
    assert "prediction files have no ground truth" not in capsys.readouterr().out


def test_rasterised_boxes_on_a_grid_with_a_cell_on_the_origin(tmp_path):
    """Without mask_2 the boxes are padded to 16 with all-zero boxes, which must stay out of
    the raster: on a 41 x 41 grid of 0.25 m cells over -5.125..5.125 m a cell is centred on
    the origin, where a zero box would put a padding id past the one object on the map (refused
    by the metrics). One chair found exactly: PQ and mIoU are 1, AP 1 - 2**-53 (pycocotools'
    precision tp / (tp + fp + 2**-52), as in test_metrics)."""
    import dataclasses

    grid = dataclasses.replace(CFG.grid, x_range=(-5.125, 5.125), y_range=(-5.125, 5.125))
    config = dataclasses.replace(CFG, grid=grid)
    assert grid.shape == (41, 41)
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", _labels([[2.0, 2.0]]), NAMES)
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", _labels([[2.0, 2.0]], [0.9]), NAMES)
    res = evaluate_folders(tmp_path / "gt", tmp_path / "pred", config)
    assert res["ap"] == {0.25: 1 - 2**-53, 0.5: 1 - 2**-53}
    assert (res["pq"], res["miou"], res["semantic_miou"]) == (1.0, 1.0, 1.0)


def test_write_json_keeps_the_old_file_when_a_write_fails(tmp_path, full_disk):
    """--json's write is atomic: a write that fails halfway (a full disk) leaves the last
    metrics file whole, and no temporary file beside it."""
    from indoorbev_jax.checks import write_json

    out = tmp_path / "m.json"
    write_json(out, {"old": 1})
    with full_disk(), pytest.raises(OSError, match=f"cannot write {re.escape(str(out))}: No space"):
        write_json(out, {"new": 2})
    assert json.loads(out.read_text()) == {"old": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["m.json"]
