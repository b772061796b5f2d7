"""``Evaluator``: every metric accumulated frame by frame during validation, and the tables
it prints."""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from indoorbev_jax.config import CLASS_NAMES, InferenceConfig, check_section
from indoorbev_jax.metrics.ap import (
    _ap_frame,
    _ap_from_frames,
    _APFrame,
    _check_iou,
    _check_thresholds,
    _confusion_from_frames,
    _frame_arrays,
    format_percent,
)
from indoorbev_jax.metrics.panoptic import _PanopticStats
from indoorbev_jax.types import Targets, _from_mapping

DEFAULT_GROUPING = "tag"  # the name of ``gt_tags`` given as one array


def _tag_groupings(gt_tags) -> dict[str, np.ndarray] | None:
    """``gt_tags`` (None, one array or a dict of arrays) as a dict of arrays by grouping."""
    if gt_tags is None:
        return None
    if isinstance(gt_tags, Mapping):
        return {str(k): np.asarray(v) for k, v in gt_tags.items()}
    return {DEFAULT_GROUPING: np.asarray(gt_tags)}


def _tags_name(grouping: str) -> str:
    """How errors name a grouping's tags."""
    return "gt_tags" if grouping == DEFAULT_GROUPING else f"gt_tags[{grouping!r}]"


class Evaluator:
    """Accumulates frames of model outputs and targets; ``compute`` returns every metric.

    Per frame only small statistics are kept (detection-GT IoUs, instance-pair pixel counts),
    so memory does not grow with the grid. The numbers equal ``mask_ap``, ``panoptic_quality``,
    ``paper_miou`` and ``semantic_miou`` on the same masks, with one rule of its own: valid
    targets whose mask is empty on the grid are left out of AP (no BEV mask can find them).

    Example::

        ev = Evaluator(config.inference)
        for batch in val_data:
            ev.add(model.apply(params, batch.points, batch.point_valid), batch.targets)
        print(ev.table())
    """

    def __init__(
        self,
        inference: InferenceConfig | None = None,
        *,
        class_names: Sequence[str] = CLASS_NAMES,
        iou_thresholds: Sequence[float] = (0.25, 0.5),
        miou_match_iou: float = 0.25,
    ):
        if inference is not None:
            check_section("inference", inference, InferenceConfig, "inference")
        if isinstance(class_names, str):  # "Chair" was 5 classes, one a letter
            raise TypeError(f"class_names: expected a sequence of names, got {class_names!r}")
        self.inference = inference or InferenceConfig()
        self.class_names = tuple(class_names)
        self.num_classes = len(self.class_names)
        self.iou_thresholds = _check_thresholds(iou_thresholds)
        self.miou_match_iou = _check_iou("miou_match_iou", miou_match_iou, low_open=True)
        self.reset()

    def reset(self) -> None:
        self._ap_frames: list[_APFrame] = []
        self._gt_tags: list[dict[str, np.ndarray] | None] = []
        self._panoptic = _PanopticStats(self.num_classes, self.miou_match_iou)

    @property
    def num_frames(self) -> int:
        return len(self._ap_frames)

    def add(self, predictions, targets) -> None:
        """Runs panoptic inference on the last decoder layer and adds the B frames.

        Args:
          predictions: ``types.Predictions`` (logits [L, B, Q, K], masks [L, B, Q, H, W]).
          targets: ``types.Targets`` of the same B frames, or a dict of its fields
            (``instance_ids`` included).
        """
        from indoorbev_jax.inference import panoptic_inference

        self.add_output(panoptic_inference(predictions, self.inference), targets)

    def add_output(self, output, targets, gt_tags=None) -> None:
        """Adds B frames whose inference already ran (e.g. inside a jitted eval step).

        Args:
          output: ``inference.PanopticOutput`` of B frames.
          targets: ``types.Targets`` of the same B frames, or a dict of its fields
            (``instance_ids`` included).
          gt_tags: optional int [B, M], a group id >= 0 per valid target (e.g. the simulator's
            object variant) for ``tag_confusion``; or a dict of such arrays, one per named
            grouping (``tag_confusion(..., grouping=name)``).
        """
        # A dict of the Targets fields, as set_loss takes; the maps are needed here.
        targets = _from_mapping(Targets, targets, "targets")
        out = {f.name: np.asarray(getattr(output, f.name)) for f in dataclasses.fields(output)}
        classes = np.asarray(targets.classes)
        valid = np.asarray(targets.valid).astype(bool)
        masks = np.asarray(targets.masks).astype(bool)
        ids = np.asarray(targets.instance_ids)
        if out["instance_ids"].shape != ids.shape:
            raise ValueError(
                f"targets.instance_ids {ids.shape} and predicted maps "
                f"{out['instance_ids'].shape} differ in shape"
            )
        tags = _tag_groupings(gt_tags)
        for name, t in (tags or {}).items():
            if t.shape != classes.shape:
                raise ValueError(
                    f"{_tags_name(name)}: expected shape {classes.shape} (targets), got {t.shape}"
                )
        # All B frames or none: a refused frame i must not leave frames 0..i-1 behind.
        start, panoptic = self.num_frames, copy.deepcopy(self._panoptic)
        try:
            for i in range(classes.shape[0]):
                self._add_batch_frame(i, out, masks, classes, valid, ids, tags)
        except Exception:
            del self._ap_frames[start:], self._gt_tags[start:]  # appended in step
            self._panoptic = panoptic
            raise

    def _add_batch_frame(self, i, out, masks, classes, valid, ids, tags) -> None:
        """``add_frame`` of frame i of ``add_output``'s arrays."""
        dv = out["det_valid"][i]
        self.add_frame(
            gt=(masks[i][valid[i]], classes[i][valid[i]]),
            det=(out["det_masks"][i][dv], out["det_classes"][i][dv], out["det_scores"][i][dv]),
            gt_panoptic=(
                ids[i],
                np.concatenate(
                    [[self.num_classes], np.where(valid[i], classes[i], self.num_classes)]
                ),
            ),
            pred_panoptic=(out["instance_ids"][i], out["instance_classes"][i]),
            gt_tags=None if tags is None else {k: t[i][valid[i]] for k, t in tags.items()},
        )

    def add_frame(self, gt, det, gt_panoptic, pred_panoptic, gt_tags=None) -> None:
        """Adds one frame given as numpy masks (the formats of ``mask_ap``/``panoptic_quality``).

        Empty masks are not objects: ground truths and detections whose mask has no cell are
        left out of AP (no BEV mask can find them; ``panoptic_quality`` ignores ids without
        cells in the same way).

        Args:
          gt: ``(masks bool [M, H, W], classes [M])``.
          det: ``(masks bool [D, H, W], classes [D], scores [D])``.
          gt_panoptic: ``(instance_ids [H, W], instance_classes [K + 1])``.
          pred_panoptic: the same for the prediction.
          gt_tags: optional int [M], a group id >= 0 per ground truth for ``tag_confusion``,
            or a dict of them by grouping name.
        """
        index = self.num_frames
        (gm, gc), (dm, dc, ds) = _frame_arrays(gt, det, index)
        g_keep = gm.reshape(len(gm), math.prod(gm.shape[1:])).any(1)  # [M]
        d_keep = dm.reshape(len(dm), math.prod(dm.shape[1:])).any(1)  # [D]
        gt_tags = _tag_groupings(gt_tags)
        for name, tags in (gt_tags or {}).items():
            tags = tags.astype(np.int64)
            if tags.shape != gc.shape or (tags.size and tags.min() < 0):
                raise ValueError(
                    f"frame {index}: {_tags_name(name)} must be {gc.shape[0]} ids >= 0, got {tags}"
                )
            gt_tags[name] = tags[g_keep]
        # Every check runs before any state changes (the panoptic add checks, then adds), so
        # a refused frame leaves no part behind.
        ap_frame = _ap_frame(
            (gm[g_keep], gc[g_keep]), (dm[d_keep], dc[d_keep], ds[d_keep]), index, self.num_classes
        )
        self._panoptic.add(gt_panoptic, pred_panoptic, index)
        self._ap_frames.append(ap_frame)
        self._gt_tags.append(gt_tags)

    def compute(self) -> dict:
        """All metrics over the frames added so far.

        Returns:
          ``{"num_frames", "ap": {thr: float}, "pq", "sq", "rq", "miou", "semantic_miou",
          "background_iou", "per_class": {name: {...}}}``; per class: ``num_gt``,
          ``ap@<thr>``, ``pq``, ``sq``, ``rq``, ``miou``, ``semantic_iou``.
        """
        ap = _ap_from_frames(self._ap_frames, self.iou_thresholds, self.num_classes)
        return combine_results(
            ap,
            self._panoptic.panoptic(),
            self._panoptic.paper_miou(),
            self._panoptic.semantic_miou(),
            self.class_names,
            self.num_frames,
        )

    def confusion(self, iou_threshold: float = 0.5) -> np.ndarray:
        """``class_confusion`` over the frames added so far (int64 [K, K + 1])."""
        return _confusion_from_frames(self._ap_frames, iou_threshold, self.num_classes)

    def tag_confusion(
        self, num_tags: int, iou_threshold: float = 0.5, *, grouping: str = DEFAULT_GROUPING
    ) -> np.ndarray:
        """``confusion`` with ground truths counted by their ``gt_tags`` instead of their class.

        The matches are ``confusion``'s, so summing the rows of the tags of one class gives that
        class's row there, and every grouping's rows sum to the same column totals.

        Args:
          num_tags: tags lie in ``0..num_tags - 1``.
          iou_threshold: mask IoU a match needs.
          grouping: which of the named groupings ``gt_tags`` was given as a dict (an array
            given alone is ``DEFAULT_GROUPING``).

        Returns:
          int64 [num_tags, K + 1]: entry [t, d] counts objects tagged t found as class d; the
          last column those found by no mask.

        Raises:
          ValueError: a frame was added without tags, or a tag is not below ``num_tags``.
        """
        missing = [i for i, t in enumerate(self._gt_tags) if t is None or grouping not in t]
        if missing:
            raise ValueError(
                f"tag_confusion: frames {missing[:5]} were added without {_tags_name(grouping)}"
            )
        rows = [t[grouping] for t in self._gt_tags]
        top = max((int(t.max()) for t in rows if t.size), default=-1)
        if top >= num_tags:
            raise ValueError(f"tag_confusion: tag {top} but num_tags is {num_tags}")
        return _confusion_from_frames(
            self._ap_frames, iou_threshold, self.num_classes, rows=(rows, num_tags)
        )

    def table(self, results: dict | None = None) -> str:
        """The per-class table of ``compute()`` (or of ``results``) as printable text."""
        return format_table(results if results is not None else self.compute())


def combine_results(ap, pan, miou, sem, class_names: Sequence[str], num_frames: int) -> dict:
    """Merges the outputs of the four metric functions into ``Evaluator.compute``'s layout."""
    per_class = {}
    for c, name in enumerate(class_names):
        row = {"num_gt": ap["num_gt"][c]}
        row.update({f"ap@{t:g}": v for t, v in ap["per_class"][c].items()})
        row.update({k: pan["per_class"][c][k] for k in ("pq", "sq", "rq")})
        row["miou"] = miou["per_class"][c]
        row["semantic_iou"] = sem["per_class"][c]
        per_class[name] = row
    return {
        "num_frames": num_frames,
        "ap": dict(ap["ap"]),
        "pq": pan["pq"],
        "sq": pan["sq"],
        "rq": pan["rq"],
        "miou": miou["miou"],
        "semantic_miou": sem["semantic_miou"],
        "background_iou": sem["background_iou"],
        "per_class": per_class,
    }


def format_table(results: dict) -> str:
    """A per-class table (values in %) with a final row of the means.

    Args:
      results: ``Evaluator.compute()`` output.
    """
    per_class = results["per_class"]
    cols = [k for k in next(iter(per_class.values())) if k != "num_gt"] if per_class else []
    heads = [c.upper().replace("MIOU", "mIoU").replace("SEMANTIC_IOU", "semIoU") for c in cols]
    width = max([len(n) for n in per_class] + [5])
    lines = [f"{'class':<{width}} {'#gt':>6} " + " ".join(f"{h:>8}" for h in heads)]
    for name, row in per_class.items():
        vals = " ".join(f"{format_percent(row[c]):>8}" for c in cols)
        lines.append(f"{name:<{width}} {row['num_gt']:>6} {vals}")
    means = {f"ap@{t:g}": v for t, v in results["ap"].items()}
    means.update({k: results[k] for k in ("pq", "sq", "rq", "miou")})
    means["semantic_iou"] = results["semantic_miou"]
    total = sum(row["num_gt"] for row in per_class.values())
    vals = " ".join(f"{format_percent(means.get(c, math.nan)):>8}" for c in cols)
    lines.append(f"{'mean':<{width}} {total:>6} {vals}")
    lines.append(f"frames: {results['num_frames']}")
    return "\n".join(lines)
