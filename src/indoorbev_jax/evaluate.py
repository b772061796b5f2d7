"""``indoorbev eval``: the paper's metrics between two KITTI-layout folders.

    indoorbev eval --gt DATA --pred PRED [--split val] [--preset paper] [--json OUT]

Ground truth: ``<gt>/label_2/<id>.txt`` and, where present, ``<gt>/mask_2/<id>.png`` (true
footprints; otherwise the label boxes are rasterised). Predictions: ``<pred>/label_2/<id>.txt``
with the score column, and ``<pred>/mask_2/<id>.png`` whose id k + 1 is the object on line k
(the panoptic map; without it the predicted boxes are rasterised). Each prediction line is one
AP detection with its mask from the map; the map itself is the panoptic prediction.
Frames: the ids of ``<gt>/<split>.txt``, or every ground-truth label file. Under the table it
prints the class confusion at mask IoU 0.5 (``metrics.class_confusion``), also in the JSON.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
from pathlib import Path

import jax
import numpy as np

from indoorbev_jax.checks import check_out_file, write_json
from indoorbev_jax.config import Config, GridConfig
from indoorbev_jax.metrics import (
    DEFAULT_GROUPING,
    Evaluator,
    confusion_json,
    format_confusion,
    format_found,
    format_table,
)

CONFUSION_IOU = 0.5  # mask IoU of the printed class confusion (AP@0.50's matches)


@functools.partial(jax.jit, static_argnames="grid")
def _rasterize(boxes, valid, grid: GridConfig):
    from indoorbev_jax.data.rasterize import rasterize_boxes

    return rasterize_boxes(boxes, valid, grid)


def _masks_of(labels, mask_path: Path, grid: GridConfig):
    """Panoptic ids [H, W] and per-object masks [M, H, W] of one label file."""
    from indoorbev_jax.data import kitti

    m = len(labels)
    if mask_path.exists():
        ids = kitti.read_mask(mask_path, grid.shape)
        if ids.max(initial=0) > m:
            raise kitti.DatasetError(
                f"{mask_path}: instance id {ids.max()} but the label file has only {m} "
                f"objects (DontCare lines not counted)"
            )
        masks = ids[None] == np.arange(1, m + 1)[:, None, None]  # [M, H, W]
        return ids, masks
    # Pad to a multiple of 16 boxes so the jitted rasteriser compiles only a few shapes.
    n = max(16, -(-m // 16) * 16)
    boxes = np.zeros((n, 5), np.float32)
    boxes[:m] = labels.boxes_bev()
    ids, masks = _rasterize(boxes, np.arange(n) < m, grid)
    return np.asarray(ids), np.asarray(masks)[:m]


def evaluate_folders(
    gt_root: str | Path, pred_root: str | Path, config: Config, split: str | None = None
) -> dict:
    """All metrics between a ground-truth and a prediction folder.

    ``folder_evaluator(...).compute()``; see there for the arguments.

    Returns:
      ``Evaluator.compute()``'s dict.
    """
    return folder_evaluator(gt_root, pred_root, config, split).compute()


def folder_evaluator(
    gt_root: str | Path,
    pred_root: str | Path,
    config: Config,
    split: str | None = None,
    notes: list[str] | None = None,
) -> Evaluator:
    """An ``Evaluator`` holding every frame of a ground-truth and a prediction folder.

    Args:
      gt_root: KITTI-layout ground truth.
      pred_root: KITTI-layout predictions (label_2 with scores, optional mask_2).
      config: gives the grid, the classes and the inference thresholds.
      split: frame list ``<gt_root>/<split>.txt``; None: every ground-truth label file.
      notes: if given, receives a line per side whose objects have no cell in their mask
        (the ``Evaluator`` leaves those out of AP, where pycocotools would count such a
        prediction as a false positive and such a ground truth as a miss).

    Returns:
      The filled ``Evaluator`` (``compute()``, ``confusion()``).

    Raises:
      kitti.DatasetError: a missing or malformed file (the message names it).
    """
    from indoorbev_jax.data import kitti

    gt_root, pred_root = Path(gt_root), Path(pred_root)
    ids = kitti.read_split(gt_root, split) if split else kitti.list_frames(gt_root)
    where = gt_root / f"{split}.txt" if split else gt_root / "label_2"
    if not ids:
        raise kitti.DatasetError(f"{where}: no frames (expected frame ids, one per line)"
                                 if split else f"{where}: no label files (*.txt)")  # fmt: skip
    for side, root in (("ground-truth", gt_root), ("prediction", pred_root)):
        missing = [i for i in ids if not kitti.frame_paths(root, i)["labels"].is_file()]
        if missing:
            first = kitti.frame_paths(root, missing[0])["labels"]
            hint = " (write an empty file for a frame with no detections)" * (root == pred_root)
            if first.exists():  # a folder (or a pipe) where the file should be
                hint = " (a folder or other non-file there)"
            raise kitti.DatasetError(
                f"{where}: {len(missing)} of {len(ids)} frames have no {side} label file, "
                f"e.g. {first}{hint}"
            )
    k = config.num_classes
    evaluator = Evaluator(config.inference, class_names=config.data.class_names)
    empty = {"ground-truth": [0, None], "prediction": [0, None]}  # [count, first example]
    for frame_id in ids:
        gp, pp = kitti.frame_paths(gt_root, frame_id), kitti.frame_paths(pred_root, frame_id)
        gt = kitti.read_labels(gp["labels"], config.data)
        if gt.scores is not None:
            raise kitti.DatasetError(
                f"{gp['labels']}: ground truth with a score column (16th); are the ground "
                f"truth and the predictions swapped?"
            )
        pred = kitti.read_labels(pp["labels"], config.data)
        if len(pred) and pred.scores is None:
            raise kitti.DatasetError(f"{pp['labels']}: predictions need the score column (16th)")
        scores = pred.scores if pred.scores is not None else np.zeros(0, np.float32)
        gt_ids, gt_masks = _masks_of(gt, gp["mask"], config.grid)
        pred_ids, pred_masks = _masks_of(pred, pp["mask"], config.grid)
        for side, path, masks in (("ground-truth", gp, gt_masks), ("prediction", pp, pred_masks)):
            no_cell = np.flatnonzero(~masks.any(axis=(-2, -1)))
            empty[side][0] += len(no_cell)
            if len(no_cell) and empty[side][1] is None:
                empty[side][1] = f"{path['labels']}, the object of mask id {no_cell[0] + 1}"
        evaluator.add_frame(
            gt=(gt_masks, gt.classes),
            det=(pred_masks, pred.classes, scores),
            gt_panoptic=(gt_ids, np.concatenate([[k], gt.classes])),
            pred_panoptic=(pred_ids, np.concatenate([[k], pred.classes])),
        )
    for side, (count, example) in empty.items():
        if count and notes is not None:
            notes.append(f"note: {count} {side} objects have no cell in their mask and are left "
                         f"out of AP, e.g. {example}")  # fmt: skip
    return evaluator


def to_json(results: dict) -> str:
    """JSON text of a results dict; undefined values (NaN, AP's -1) become null."""

    def clean(v):
        if isinstance(v, dict):
            return {str(key): clean(x) for key, x in v.items()}
        if isinstance(v, float) and (math.isnan(v) or v < 0):
            return None
        return v

    return json.dumps(clean(results), indent=2)


def report(
    evaluator: Evaluator,
    class_names,
    tag_names=None,
    tag_title="",
    *,
    tag_grouping: str = DEFAULT_GROUPING,
    breakdowns=(),
) -> tuple[str, dict]:
    """What both evaluation commands print and write for the frames an ``Evaluator`` holds.

    Args:
      evaluator: the filled ``Evaluator``.
      class_names: its classes.
      tag_names: names of the ``gt_tags`` the frames were added with (e.g. object variants);
        None: no tags. With names, a second confusion counts objects per tag.
      tag_title: what the tags are, for that table's heading.
      tag_grouping: which named grouping of ``gt_tags`` those tags are.
      breakdowns: ``(grouping, row names, title)`` per further grouping of ``gt_tags``
        printed as objects and misses per group at each of the evaluator's IoU thresholds
        (``metrics.format_found``), e.g. by the number of lidar points on the object.

    Returns:
      (the per-class table and the class confusion at ``CONFUSION_IOU`` as printable text,
      the same as a JSON-ready dict: ``compute()``'s metrics plus ``"confusion@0.5"``,
      ``"tag_confusion@0.5"`` with tags and ``"breakdowns@<iou>"`` (by grouping) with
      breakdowns).
    """
    iou = CONFUSION_IOU
    results, confusion = evaluator.compute(), evaluator.confusion(iou)
    head = f"confusion at mask IoU {iou:g} (rows: ground truth, columns: found as)"
    text = [format_table(results), "", head, format_confusion(confusion, class_names)]
    payload = json.loads(to_json(results))
    payload[f"confusion@{iou:g}"] = confusion_json(confusion, class_names, iou)
    if tag_names is not None:
        by_tag = evaluator.tag_confusion(len(tag_names), iou, grouping=tag_grouping)
        text += ["", f"{head}, {tag_title}", format_confusion(by_tag, class_names, tag_names)]
        payload[f"tag_confusion@{iou:g}"] = {
            "tags": tag_title,
            **confusion_json(by_tag, class_names, iou, tag_names),
        }
    for grouping, names, title in breakdowns:
        by_iou = {t: evaluator.tag_confusion(len(names), t, grouping=grouping)
                  for t in evaluator.iou_thresholds}  # fmt: skip
        text += ["", f"objects no mask found, {title}", format_found(by_iou, names)]
        for t, counts in by_iou.items():
            payload.setdefault(f"breakdowns@{t:g}", {})[grouping] = {
                "title": title,
                **confusion_json(counts, class_names, t, names),
            }
    return "\n".join(text), payload


def check_dataset_file(flag: str, out, roots) -> None:
    """Raises ``ValueError`` when the output ``out`` would replace a file of one of the
    dataset folders ``roots``: its export.json or predict.json, a split list, or a frame
    file (a --json GT/export.json replaced the record the next eval reads its config from)."""
    from indoorbev_jax.data import kitti

    target = Path(out).resolve()
    for root in (Path(r).resolve() for r in roots):
        records = target.parent == root and (
            target.name in ("export.json", "predict.json") or target.suffix == ".txt"
        )
        if records or target.parent in kitti.frame_folders(root):
            raise ValueError(f"{flag} {out}: a file of the dataset {root}; expected a new file")


def eval_command(args: argparse.Namespace) -> int:
    """Entry point of ``indoorbev eval``: prints ``report``'s text, optionally writes its JSON."""
    from indoorbev_jax.config import ConfigError
    from indoorbev_jax.data import kitti
    from indoorbev_jax.data.dataset import dataset_config

    try:
        config, source = dataset_config(args.gt, args.preset, args.set)
        if args.json is not None:  # a bad path fails now, not after the whole evaluation
            check_out_file("--json", args.json)  # "" too: it wrote nothing, silently
            check_dataset_file("--json", args.json, [args.gt, args.pred])
        notes: list[str] = []
        evaluator = folder_evaluator(args.gt, args.pred, config, args.split, notes)
    except ConfigError as e:  # a bad --set or --preset: a usage error, as in train.py
        print(f"indoorbev eval: error: {e}", file=sys.stderr)
        return 2
    except (kitti.DatasetError, OSError, ValueError) as e:  # ValueError: a bad --json
        # stderr: `indoorbev eval GT PRED > metrics.txt` must still show it
        print(f"indoorbev eval: error: {e}", file=sys.stderr)
        return 1
    text, payload = report(evaluator, config.data.class_names)
    print(f"ground truth {args.gt}, predictions {args.pred} ({source})")
    if args.split is None:  # with a split, the other splits' predictions are expected
        extra = sorted(set(kitti.list_frames(args.pred)) - set(kitti.list_frames(args.gt)))
        if extra:
            print(f"note: {len(extra)} prediction files have no ground truth and are not "
                  f"evaluated, e.g. {extra[0]}")  # fmt: skip
    for note in notes:
        print(note)
    print(text)
    if args.json is not None:
        try:  # a disk that filled up during the evaluation: the metrics are printed above
            write_json(args.json, payload)
        except OSError as e:
            print(f"indoorbev eval: error: {e} (the metrics are printed above)", file=sys.stderr)
            return 1
        print(f"metrics written to {args.json}")
    return 0


def add_eval_command(commands) -> None:
    """Registers ``eval`` on the ``indoorbev`` subcommand parsers."""
    from indoorbev_jax.cli import HelpFormatter

    parser = commands.add_parser(
        "eval",
        help="AP@0.25/0.50, PQ/SQ/RQ and mIoU between two KITTI-layout folders",
        description="Score the predictions of one KITTI-layout folder against the ground "
        "truth of another: prints the per-class table of AP@0.25/0.50, PQ/SQ/RQ and mIoU and "
        "the class confusion at mask IoU 0.5.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--gt", required=True, help="ground-truth folder (label_2/, mask_2/)")
    parser.add_argument("--pred", required=True, help="prediction folder (label_2/ + scores)")
    parser.add_argument(
        "--split",
        default=None,
        help="score only the frames listed in <gt>/<split>.txt (default: every frame of --gt)",
    )
    parser.add_argument("--json", default=None, help="also write the metrics to this file")
    add_dataset_config_arguments(parser)
    parser.set_defaults(func=eval_command)


def add_dataset_config_arguments(parser) -> None:
    """``--preset`` and ``--set`` of the commands that read a dataset folder
    (``dataset.dataset_config``)."""
    parser.add_argument(
        "--preset",
        default=None,
        choices=("paper", "small", "tiny"),
        help="config preset giving the grid and classes (default: the config in the "
        "dataset's export.json, else small)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help='override a config field (repeatable), e.g. --set \'data.class_map={"Desk": '
        '"Table"}\'',
    )
