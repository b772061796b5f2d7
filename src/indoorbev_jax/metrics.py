"""The paper's metrics on BEV masks: mask AP (COCO), PQ/SQ/RQ, mIoU; and an ``Evaluator``.

Definitions are in docs/METRICS.md (DESIGN section 9). In short:

* ``mask_ap``: COCO mask AP, equal to pycocotools' ``COCOeval`` (iouType "segm", the given
  ``iouThrs``, ``maxDets=[100]``, one area range covering everything, no crowd regions).
* ``panoptic_quality``: Kirillov et al. PQ = SQ x RQ per class, unique matching at IoU > 0.5,
  background is not void; mean over classes with TP + FP + FN > 0.
* ``paper_miou``: the paper's mIoU, the mean IoU of ground-truth objects matched one-to-one to a
  same-class predicted segment (IoU >= 0.25 by default), per class, then over classes.
* ``semantic_miou``: pixel-wise semantic BEV mIoU over foreground classes.

Everything runs on host numpy from small per-frame statistics (mask intersections,
instance-pair pixel counts), which ``Evaluator`` gathers frame by frame during validation.
Undefined values: AP follows pycocotools (-1 where a class has no ground truth, and -1 overall
when no class has any); the other metrics use NaN. ``format_table`` prints both as "-".
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from indoorbev_jax.config import CLASS_NAMES, NUM_CLASSES, InferenceConfig, check_section
from indoorbev_jax.types import Targets, _from_mapping

# pycocotools' recall grid, built the same way so the values match bit for bit.
_REC_THRS = np.linspace(0.0, 1.00, int(np.round((1.00 - 0.0) / 0.01)) + 1, endpoint=True)


# --------------------------------------------------------------------------- mask IoU


def _boxes_and_areas(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half-open bounding boxes int [N, 4] = (y0, y1, x0, x1) (empty: all 0) and areas [N]."""
    h = masks.shape[1]
    rows = masks.any(2)  # [N, H]: the one full pass; the rest looks inside the row band
    boxes = np.zeros((len(masks), 4), np.int64)
    areas = np.zeros(len(masks), np.int64)
    for k in np.flatnonzero(rows.any(1)):
        y0, y1 = rows[k].argmax(), h - rows[k, ::-1].argmax()
        cols = masks[k, y0:y1].any(0)  # [W]
        x0, x1 = cols.argmax(), len(cols) - cols[::-1].argmax()
        boxes[k] = y0, y1, x0, x1
        areas[k] = np.count_nonzero(masks[k, y0:y1, x0:x1])
    return boxes, areas


def mask_intersections(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel counts of pairwise intersections and of each mask.

    Footprints are small next to the grid, so counts are taken inside bounding boxes: one pass
    over each mask stack finds the boxes, then only pairs whose boxes overlap are counted, on
    the overlap window.

    Args:
      a: bool [D, H, W].
      b: bool [G, H, W].

    Returns:
      (inter int64 [D, G], area_a int64 [D], area_b int64 [G]).
    """
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    box_a, area_a = _boxes_and_areas(a)
    box_b, area_b = _boxes_and_areas(b)
    lo = np.maximum(box_a[:, None, [0, 2]], box_b[None, :, [0, 2]])  # [D, G, 2] = (y0, x0)
    hi = np.minimum(box_a[:, None, [1, 3]], box_b[None, :, [1, 3]])  # [D, G, 2] = (y1, x1)
    inter = np.zeros((len(a), len(b)), np.int64)
    for i, j in zip(*np.nonzero((lo < hi).all(-1)), strict=True):
        win = (slice(lo[i, j, 0], hi[i, j, 0]), slice(lo[i, j, 1], hi[i, j, 1]))
        inter[i, j] = np.count_nonzero(a[i][win] & b[j][win])
    return inter, area_a, area_b


def _iou_from_counts(inter: np.ndarray, area_a: np.ndarray, area_b: np.ndarray) -> np.ndarray:
    """IoU in float64 as pycocotools computes it (i / u from integer counts; 0 when u = 0)."""
    union = (area_a[:, None] + area_b[None, :] - inter).astype(np.float64)
    out = np.zeros(union.shape, np.float64)
    np.divide(inter.astype(np.float64), union, out=out, where=union > 0)
    return out


# --------------------------------------------------------------------------- mask AP


@dataclasses.dataclass
class _APFrame:
    """One frame for AP: IoU of every detection with every ground truth, plus labels."""

    iou: np.ndarray  # float64 [D, G]
    det_classes: np.ndarray  # int64 [D]
    det_scores: np.ndarray  # float64 [D]
    gt_classes: np.ndarray  # int64 [G]


def _check_classes(name: str, classes: np.ndarray, num_classes: int) -> None:
    if classes.size and (classes.min() < 0 or classes.max() >= num_classes):
        raise ValueError(f"{name}: class ids must lie in 0..{num_classes - 1}, got {classes}")


def _no_masks_as_3d(masks: np.ndarray, other: np.ndarray) -> np.ndarray:
    """An empty list (or any 0-size array) of masks as [0, H, W], H x W taken from the other
    side of the frame: a frame without objects may be given as ``[]``."""
    if masks.size or masks.ndim == 3:
        return masks
    return masks.reshape((0, *other.shape[1:]) if other.ndim == 3 else (0, 0, 0))


def _check_binary(name: str, masks: np.ndarray) -> None:
    """Float masks must hold 0 and 1 only: read as bool, probabilities or logits (nonzero
    almost everywhere) made every mask the whole grid, and AP 0, without a word."""
    if masks.dtype.kind == "f" and masks.size and not ((masks == 0) | (masks == 1)).all():
        raise ValueError(
            f"{name}: masks must be bool (or 0/1) [N, H, W], got {masks.dtype} with values "
            f"in [{masks.min():g}, {masks.max():g}]; binarise probabilities first (e.g. >= 0.5)"
        )


def _frame_arrays(gt, det, index: int):
    """A frame's ``(gt, det)`` as numpy arrays, empty mask lists as [0, H, W], shapes checked."""
    gt_masks, gt_classes = (np.asarray(x) for x in gt)
    det_masks, det_classes, det_scores = (np.asarray(x) for x in det)
    gt_masks, det_masks = _no_masks_as_3d(gt_masks, det_masks), _no_masks_as_3d(det_masks, gt_masks)
    if gt_masks.ndim != 3 or gt_classes.shape != gt_masks.shape[:1]:
        raise ValueError(
            f"gts[{index}]: expected masks [M, H, W] and classes [M], got shapes "
            f"{gt_masks.shape} and {gt_classes.shape}"
        )
    d = det_masks.shape[0] if det_masks.ndim == 3 else -1
    if d < 0 or det_classes.shape != (d,) or det_scores.shape != (d,):
        raise ValueError(
            f"dets[{index}]: expected masks [D, H, W], classes [D], scores [D], got shapes "
            f"{det_masks.shape}, {det_classes.shape}, {det_scores.shape}"
        )
    if det_masks.shape[1:] != gt_masks.shape[1:]:
        raise ValueError(
            f"frame {index}: detection masks are {det_masks.shape[1:]} but ground truth masks "
            f"are {gt_masks.shape[1:]}"
        )
    _check_binary(f"gts[{index}]", gt_masks)
    _check_binary(f"dets[{index}]", det_masks)
    return (gt_masks, gt_classes), (det_masks, det_classes, det_scores)


def _ap_frame(gt, det, index: int, num_classes: int) -> _APFrame:
    (gt_masks, gt_classes), (det_masks, det_classes, det_scores) = _frame_arrays(gt, det, index)
    if not np.all(np.isfinite(det_scores)):
        raise ValueError(f"dets[{index}]: scores must be finite, got {det_scores}")
    _check_classes(f"gts[{index}]", gt_classes, num_classes)
    _check_classes(f"dets[{index}]", det_classes, num_classes)
    inter, det_area, gt_area = mask_intersections(det_masks, gt_masks)
    return _APFrame(
        iou=_iou_from_counts(inter, det_area, gt_area),
        det_classes=det_classes.astype(np.int64),
        det_scores=det_scores.astype(np.float64),
        gt_classes=gt_classes.astype(np.int64),
    )


def _ap_frames(gts, dets, num_classes: int) -> list[_APFrame]:
    """``_ap_frame`` of every frame of ``mask_ap``-style inputs."""
    if len(gts) != len(dets):
        raise ValueError(f"gts and dets: {len(gts)} vs {len(dets)} frames")
    return [_ap_frame(g, d, i, num_classes) for i, (g, d) in enumerate(zip(gts, dets, strict=True))]


def _greedy_match(iou: np.ndarray, active: np.ndarray, threshold: float) -> np.ndarray:
    """COCO's greedy matching for all frames at once.

    Detections are visited in score order (axis 1); each takes the unmatched ground truth with
    the highest IoU >= threshold, the last one on ties (pycocotools' ``<`` test). ``iou`` is
    -inf wherever a pair may not match (other class, padding), so classes match independently
    as in pycocotools' per-category loop.

    Args:
      iou: float64 [F, D, G], detections sorted by score within each frame.
      active: bool [F, D], detections taking part.
      threshold: IoU threshold.

    Returns:
      int64 [F, D], the ground truth each detection matched, -1 for none.
    """
    f, d, g = iou.shape
    thr = min(threshold, 1 - 1e-10)  # as pycocotools
    taken = np.zeros((f, g), bool)
    match = np.full((f, d), -1, np.int64)
    if g == 0:
        return match
    rows = np.arange(f)
    for j in range(d):
        cand = np.where(taken | ~(iou[:, j] >= thr), -np.inf, iou[:, j])  # [F, G]
        best = cand.max(1)
        hit = active[:, j] & (best > -np.inf)
        # Last index reaching the maximum.
        last = g - 1 - np.argmax(cand[:, ::-1] == best[:, None], axis=1)
        taken[rows[hit], last[hit]] = True
        match[hit, j] = last[hit]
    return match


def _stack_frames(frames: Sequence[_APFrame]):
    """Frames padded to one array each, detections sorted by score within each frame.

    Returns:
      (iou float64 [F, D, G] (-inf padding), det_cls int64 [F, D] (-1 padding),
      scores float64 [F, D], gt_cls int64 [F, G] (-2 padding)).
    """
    nf = len(frames)
    dmax = max((len(fr.det_scores) for fr in frames), default=0)
    gmax = max((len(fr.gt_classes) for fr in frames), default=0)
    iou = np.full((nf, dmax, gmax), -np.inf)
    det_cls = np.full((nf, dmax), -1, np.int64)
    scores = np.zeros((nf, dmax))
    gt_cls = np.full((nf, gmax), -2, np.int64)
    for i, fr in enumerate(frames):
        # Stable sort on -score: pycocotools' order, ties kept in input order.
        order = np.argsort(-fr.det_scores, kind="mergesort")
        nd, ng = len(order), len(fr.gt_classes)
        iou[i, :nd, :ng] = fr.iou[order]
        det_cls[i, :nd] = fr.det_classes[order]
        scores[i, :nd] = fr.det_scores[order]
        gt_cls[i, :ng] = fr.gt_classes
    return iou, det_cls, scores, gt_cls


def _coco_precision(
    frames: Sequence[_APFrame], thresholds: Sequence[float], num_classes: int, max_dets: int
) -> tuple[np.ndarray, np.ndarray]:
    """pycocotools' ``accumulate``: precision [T, R, K] (-1 for classes without ground truth)."""
    iou, det_cls, scores, gt_cls = _stack_frames(frames)
    iou = np.where(det_cls[:, :, None] == gt_cls[:, None, :], iou, -np.inf)
    # maxDets: only the best max_dets detections per frame and class take part.
    onehot = det_cls[:, :, None] == np.arange(num_classes)  # [F, D, K]
    rank = np.take_along_axis(
        np.cumsum(onehot, axis=1) - 1, np.clip(det_cls, 0, None)[:, :, None], axis=2
    )[:, :, 0]  # [F, D]
    active = (det_cls >= 0) & (rank < max_dets)
    matched = np.stack([_greedy_match(iou, active, t) >= 0 for t in thresholds])  # [T, F, D]
    num_gt = np.bincount(gt_cls[gt_cls >= 0], minlength=num_classes)

    precision = -np.ones((len(thresholds), len(_REC_THRS), num_classes))
    for k in range(num_classes):
        if num_gt[k] == 0:
            continue
        sel = active & (det_cls == k)  # frame-major, then score order: pycocotools' concat
        order = np.argsort(-scores[sel], kind="mergesort")
        for t in range(len(thresholds)):
            tps = matched[t][sel][order]
            tp = np.cumsum(tps).astype(float)
            fp = np.cumsum(~tps).astype(float)
            rc = tp / num_gt[k]
            pr = tp / (fp + tp + np.spacing(1))
            pr = np.maximum.accumulate(pr[::-1])[::-1]  # precision envelope
            inds = np.searchsorted(rc, _REC_THRS, side="left")
            q = np.zeros(len(_REC_THRS))
            ok = inds < len(pr)
            q[ok] = pr[inds[ok]]
            precision[t, :, k] = q
    return precision, num_gt


def _check_iou(name: str, value, low_open: bool = False) -> float:
    """``value`` as a float in [0, 1] ((0, 1] with ``low_open``); a string, a bool or NaN is
    refused by name (``float("0.5") < 1`` would pass a string through to a TypeError)."""
    thr = math.nan
    try:
        if np.asarray(value).dtype.kind not in "bUS":  # bools and text are no IoU
            thr = float(value)
    except (TypeError, ValueError):
        pass
    if not (0.0 < thr <= 1.0 if low_open else 0.0 <= thr <= 1.0):
        bounds = "(0, 1]" if low_open else "[0, 1]"
        raise ValueError(f"{name}: expected a number in {bounds}, got {value!r}")
    return thr


def _check_thresholds(iou_thresholds: Sequence[float]) -> tuple[float, ...]:
    try:  # any 1-D iterable: a tuple, a numpy or jax array, a generator
        if isinstance(iou_thresholds, str | bytes):
            raise TypeError
        values = list(iou_thresholds)
    except TypeError:  # a bare number, a 0-d array, text
        raise ValueError(
            f"iou_thresholds: expected a sequence of numbers in [0, 1] (e.g. (0.25, 0.5)), "
            f"got {iou_thresholds!r}"
        ) from None
    if not values:
        raise ValueError("iou_thresholds: expected at least one threshold, got none")
    return tuple(_check_iou("iou_thresholds", t) for t in values)


def _ap_from_frames(
    frames: Sequence[_APFrame],
    iou_thresholds: Sequence[float],
    num_classes: int,
    max_dets: int = 100,
) -> dict:
    thresholds = _check_thresholds(iou_thresholds)
    precision, num_gt = _coco_precision(frames, thresholds, num_classes, max_dets)
    ap = {}
    for t, thr in enumerate(thresholds):
        s = precision[t]  # [R, K], summarised like pycocotools' _summarize
        ap[thr] = float(np.mean(s[s > -1])) if np.any(s > -1) else -1.0
    per_class = {
        k: {thr: float(np.mean(precision[t, :, k])) for t, thr in enumerate(thresholds)}
        for k in range(num_classes)
    }
    return {"ap": ap, "per_class": per_class, "num_gt": {k: int(n) for k, n in enumerate(num_gt)}}


def mask_ap(
    gts: Sequence[tuple[np.ndarray, np.ndarray]],
    dets: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    iou_thresholds: Sequence[float] = (0.25, 0.5),
    *,
    num_classes: int = NUM_CLASSES,
    max_dets: int = 100,
) -> dict:
    """COCO mask AP, equal to pycocotools' ``COCOeval`` (segm) on the same inputs.

    Greedy matching in score order at IoU >= threshold per class, at most ``max_dets``
    detections per frame and class, 101-point interpolated precision, averaged over the classes
    that have ground truth.

    Args:
      gts: per frame ``(masks bool [M, H, W], classes int [M])``.
      dets: per frame ``(masks bool [D, H, W], classes int [D], scores float [D])``.
      iou_thresholds: IoU thresholds, each one AP.
      num_classes: class ids lie in ``0..num_classes - 1``.
      max_dets: pycocotools' ``maxDets``.

    Returns:
      ``{"ap": {threshold: float}, "per_class": {class: {threshold: float}},
      "num_gt": {class: int}}``; -1 where a class (or every class) has no ground truth.

    Example::

        gt = (np.ones((1, 4, 4), bool), np.array([0]))
        det = (np.ones((1, 4, 4), bool), np.array([0]), np.array([0.9]))
        mask_ap([gt], [det])["ap"]  # {0.25: 0.9999999999999999, 0.5: 0.9999999999999999}
    """
    frames = _ap_frames(gts, dets, num_classes)
    return _ap_from_frames(frames, iou_thresholds, num_classes, max_dets)


def _confusion_from_frames(
    frames: Sequence[_APFrame],
    iou_threshold: float,
    num_classes: int,
    max_dets: int = 100,
    rows: tuple[Sequence[np.ndarray], int] | None = None,
) -> np.ndarray:
    """Class-agnostic matches counted by (row, detected class or missed).

    ``rows``: ``(per-frame row ids [G], number of rows)`` to count ground truths by something
    other than their class (e.g. the simulator's object variant); None: by class.
    """
    thr = _check_iou("iou_threshold", iou_threshold)
    iou, det_cls, _, gt_cls = _stack_frames(frames)
    num_rows = num_classes
    if rows is not None:
        row_ids, num_rows = rows
        gt_cls = np.full(gt_cls.shape, -2, np.int64)  # the same padding as _stack_frames
        for i, r in enumerate(row_ids):
            gt_cls[i, : len(r)] = r
    active = (det_cls >= 0) & (np.arange(det_cls.shape[1]) < max_dets)
    match = _greedy_match(iou, active, thr)  # class-agnostic: iou is not masked by class
    confusion = np.zeros((num_rows, num_classes + 1), np.int64)
    f, d = np.nonzero(match >= 0)
    np.add.at(confusion, (gt_cls[f, match[f, d]], det_cls[f, d]), 1)
    found = np.zeros(gt_cls.shape, bool)
    found[f, match[f, d]] = True
    missed = gt_cls[(gt_cls >= 0) & ~found]
    confusion[:, num_classes] = np.bincount(missed, minlength=num_rows)
    return confusion


def class_confusion(
    gts: Sequence[tuple[np.ndarray, np.ndarray]],
    dets: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    iou_threshold: float = 0.5,
    *,
    num_classes: int = NUM_CLASSES,
    max_dets: int = 100,
) -> np.ndarray:
    """Which class each ground-truth object was detected as, by class-agnostic mask matching.

    The matching is ``mask_ap``'s (COCO greedy, score order, IoU >= threshold, at most
    ``max_dets`` detections per frame) with the class test left out, i.e. pycocotools'
    ``dtMatches`` when every object is given one category. So a row shows where a class's
    objects went: found with the right class (the diagonal), found as another class, or not
    found by any mask (last column).

    Args:
      gts, dets: as ``mask_ap``.
      iou_threshold: mask IoU a match needs.
      num_classes: class ids lie in ``0..num_classes - 1``.
      max_dets: detections per frame taking part (highest scores first).

    Returns:
      int64 [num_classes, num_classes + 1]: entry [g, d] counts ground truths of class g
      matched by a detection of class d; column ``num_classes`` counts those left unmatched.
      Row sums are the ground-truth counts per class.

    Example::

        gt = (np.ones((1, 4, 4), bool), np.array([0]))
        det = (np.ones((1, 4, 4), bool), np.array([2]), np.array([0.9]))
        class_confusion([gt], [det], num_classes=3)  # [[0, 0, 1, 0], [0, 0, 0, 0], [0, 0, 0, 0]]
    """
    frames = _ap_frames(gts, dets, num_classes)
    return _confusion_from_frames(frames, iou_threshold, num_classes, max_dets)


def format_confusion(
    confusion: np.ndarray,
    class_names: Sequence[str] = CLASS_NAMES,
    row_names: Sequence[str] | None = None,
) -> str:
    """``class_confusion``'s matrix as a printable table, one row per ground-truth class.

    ``row_names``: names of the rows when they are not the classes (``Evaluator.tag_confusion``).
    """
    confusion = np.asarray(confusion)
    names = [n[:7] for n in class_names] + ["missed"]
    rows = [n[:7] for n in class_names] if row_names is None else list(row_names)
    if confusion.shape != (len(rows), len(class_names) + 1):
        raise ValueError(
            f"confusion: expected shape {(len(rows), len(class_names) + 1)} for "
            f"{len(rows)} rows and {len(class_names)} class names, got {confusion.shape}"
        )
    corner = "gt \\ det"
    width = max(len(n) for n in [*rows, corner])
    lines = [f"{corner:<{width}} " + " ".join(f"{n:>7}" for n in names)]
    for name, row in zip(rows, confusion, strict=True):
        lines.append(f"{name:<{width}} " + " ".join(f"{int(v):>7}" for v in row))
    return "\n".join(lines)


def format_found(confusions: Mapping[float, np.ndarray], row_names: Sequence[str]) -> str:
    """Objects per row and how many no mask found, at each IoU threshold of ``confusions``.

    For groupings that mix classes (e.g. objects by their number of lidar points), where
    only found or missed means something; a miss at 0.5 that is found at 0.25 is a coarse
    mask, one missed at both is not detected.

    Args:
      confusions: ``{iou_threshold: confusion [len(row_names), K + 1]}`` of the same objects
        (``Evaluator.tag_confusion``); the last column counts the missed.
      row_names: one per row.
    """
    items = [(float(t), np.asarray(c)) for t, c in confusions.items()]
    for t, c in items:
        if c.ndim != 2 or len(c) != len(row_names):
            raise ValueError(
                f"confusion at IoU {t:g}: expected {len(row_names)} rows (one per name), got "
                f"shape {c.shape}"
            )
    totals = items[0][1].sum(1)
    if any(not np.array_equal(c.sum(1), totals) for _, c in items):
        raise ValueError("confusions: row totals differ, so they do not count the same objects")
    width = max(len(n) for n in [*row_names, "group"])
    head = ["objects"] + [h for t, _ in items for h in (f"miss@{t:g}", "%")]
    lines = [f"{'group':<{width}} {head[0]:>7}" + "".join(f" {h:>9}" for h in head[1:])]
    for r, name in enumerate(row_names):
        total = int(totals[r])
        cells = []
        for _, c in items:
            missed = int(c[r, -1])
            cells += [str(missed), format_percent(missed / total if total else math.nan)]
        lines.append(f"{name:<{width}} {total:>7}" + "".join(f" {v:>9}" for v in cells))
    return "\n".join(lines)


def confusion_json(
    confusion: np.ndarray,
    class_names: Sequence[str],
    iou_threshold: float,
    row_names: Sequence[str] | None = None,
):
    """``class_confusion``'s matrix as a JSON-ready dict with its row and column names."""
    return {
        "iou_threshold": float(iou_threshold),
        "rows": list(class_names if row_names is None else row_names),
        "columns": [*class_names, "missed"],
        "counts": np.asarray(confusion).tolist(),
    }


# --------------------------------------------------------------------------- panoptic


def _checked_classes(ids: np.ndarray, classes: np.ndarray, name: str) -> np.ndarray:
    """``classes`` (the class of each id, [K + 1]) as int64, once ``ids`` [H, W] and
    ``classes`` have their shapes and every id has a class."""
    if ids.ndim != 2:
        raise ValueError(f"{name}: expected instance_ids [H, W], got shape {ids.shape}")
    if ids.dtype.kind not in "iub" and not (ids.dtype.kind == "f" and (ids == np.round(ids)).all()):
        raise ValueError(f"{name}: instance_ids must be whole numbers, got {ids.dtype}")
    if classes.ndim != 1 or classes.shape[0] < 1:
        raise ValueError(f"{name}: expected instance_classes [K + 1], got shape {classes.shape}")
    if ids.size and (ids.min() < 0 or ids.max() >= classes.shape[0]):
        raise ValueError(
            f"{name}: instance ids must lie in 0..{classes.shape[0] - 1} (len(instance_classes)"
            f" - 1), got {ids.min()}..{ids.max()}"
        )
    return classes.astype(np.int64)


@dataclasses.dataclass
class _PanopticStats:
    """Per-class sums over frames for PQ, the paper's mIoU and the semantic confusion."""

    num_classes: int
    match_iou: float = 0.25

    def __post_init__(self):
        # A threshold of 0 would match same-class segments that share no cell.
        self.match_iou = _check_iou(
            "mIoU match threshold (iou_threshold / miou_match_iou)", self.match_iou, low_open=True
        )
        k = self.num_classes
        self.tp = np.zeros(k, np.int64)
        self.fp = np.zeros(k, np.int64)
        self.fn = np.zeros(k, np.int64)
        self.iou_sum = np.zeros(k)
        self.matched = np.zeros(k, np.int64)  # paper mIoU: matched GT objects
        self.matched_iou_sum = np.zeros(k)
        self.semantic = np.zeros((k + 1, k + 1), np.int64)  # rows GT, columns prediction

    def add(self, gt, pred, index: int) -> None:
        gt_ids, gt_classes = (np.asarray(x) for x in gt)
        pred_ids, pred_classes = (np.asarray(x) for x in pred)
        k = self.num_classes
        gcls = _checked_classes(gt_ids, gt_classes, f"gts[{index}]")
        pcls = _checked_classes(pred_ids, pred_classes, f"preds[{index}]")
        if gt_ids.shape != pred_ids.shape:
            raise ValueError(
                f"frame {index}: instance_ids shapes differ, {gt_ids.shape} vs {pred_ids.shape}"
            )
        ng, np_ = len(gcls), len(pcls)
        pair = gt_ids.ravel().astype(np.int64) * np_ + pred_ids.ravel().astype(np.int64)  # [H*W]
        conf = np.bincount(pair, minlength=ng * np_).reshape(ng, np_)
        g_area, p_area = conf.sum(1), conf.sum(0)
        g_seg = np.arange(ng) > 0
        g_seg &= g_area > 0
        p_seg = (np.arange(np_) > 0) & (p_area > 0)
        for name, cls, seg in (("gts", gcls, g_seg), ("preds", pcls, p_seg)):
            _check_classes(f"{name}[{index}] classes of present ids", cls[seg], k)
        # Semantic confusion: every cell lands in exactly one (GT id, predicted id) pair.
        g_sem = np.where(g_seg, gcls, k)
        p_sem = np.where(p_seg, pcls, k)
        np.add.at(self.semantic, (g_sem[:, None], p_sem[None, :]), conf)

        iou = _iou_from_counts(conf, g_area, p_area)  # [Kg + 1, Kp + 1]
        pairable = g_seg[:, None] & p_seg[None, :] & (gcls[:, None] == pcls[None, :])
        # IoU > 0.5 between disjoint segments is unique on both sides.
        match = pairable & (iou > 0.5)
        g_hit, p_hit = match.any(1), match.any(0)
        self.tp += np.bincount(gcls[g_hit], minlength=k)
        self.iou_sum += np.bincount(gcls[g_hit], weights=iou[match], minlength=k)
        self.fn += np.bincount(gcls[g_seg & ~g_hit], minlength=k)
        self.fp += np.bincount(pcls[p_seg & ~p_hit], minlength=k)

        # Paper mIoU: one-to-one greedy matching by IoU, highest first, at >= match_iou;
        # ties: lower GT id, then lower predicted id (nonzero's order, a stable sort).
        gi, pi = np.nonzero(pairable & (iou >= self.match_iou))
        order = np.argsort(-iou[gi, pi], kind="stable")
        g_used, p_used = set(), set()
        for a, b in zip(gi[order], pi[order], strict=True):
            if a in g_used or b in p_used:
                continue
            g_used.add(a)
            p_used.add(b)
            self.matched[gcls[a]] += 1
            self.matched_iou_sum[gcls[a]] += iou[a, b]

    def panoptic(self) -> dict:
        denom = self.tp + 0.5 * self.fp + 0.5 * self.fn
        present = denom > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            pq = np.where(present, self.iou_sum / denom, np.nan)
            sq = np.where(present, np.where(self.tp > 0, self.iou_sum / self.tp, 0.0), np.nan)
            rq = np.where(present, self.tp / denom, np.nan)
        per_class = {
            c: {
                "pq": float(pq[c]),
                "sq": float(sq[c]),
                "rq": float(rq[c]),
                "tp": int(self.tp[c]),
                "fp": int(self.fp[c]),
                "fn": int(self.fn[c]),
            }
            for c in range(self.num_classes)
        }
        return {
            "pq": _nanmean(pq[present]),
            "sq": _nanmean(sq[present]),
            "rq": _nanmean(rq[present]),
            "per_class": per_class,
        }

    def paper_miou(self) -> dict:
        with np.errstate(invalid="ignore", divide="ignore"):
            per = np.where(self.matched > 0, self.matched_iou_sum / self.matched, np.nan)
        return {
            "miou": _nanmean(per[self.matched > 0]),
            "per_class": {c: float(per[c]) for c in range(self.num_classes)},
            "matched": {c: int(self.matched[c]) for c in range(self.num_classes)},
        }

    def semantic_miou(self) -> dict:
        inter = np.diag(self.semantic).astype(np.float64)
        union = self.semantic.sum(0) + self.semantic.sum(1) - np.diag(self.semantic)
        with np.errstate(invalid="ignore", divide="ignore"):
            iou = np.where(union > 0, inter / union, np.nan)
        fg = iou[: self.num_classes]
        return {
            "semantic_miou": _nanmean(fg[union[: self.num_classes] > 0]),
            "background_iou": float(iou[self.num_classes]),
            "per_class": {c: float(fg[c]) for c in range(self.num_classes)},
        }


def _nanmean(values: np.ndarray) -> float:
    return float(np.mean(values)) if values.size else math.nan


def _panoptic_stats(gts, preds, num_classes: int, match_iou: float = 0.25) -> _PanopticStats:
    if len(gts) != len(preds):
        raise ValueError(f"gts and preds: {len(gts)} vs {len(preds)} frames")
    stats = _PanopticStats(num_classes, match_iou)
    for i, (g, p) in enumerate(zip(gts, preds, strict=True)):
        stats.add(g, p, i)
    return stats


def panoptic_quality(
    gts: Sequence[tuple[np.ndarray, np.ndarray]],
    preds: Sequence[tuple[np.ndarray, np.ndarray]],
    *,
    num_classes: int = NUM_CLASSES,
) -> dict:
    """Panoptic quality (Kirillov et al.) of panoptic BEV maps.

    A segment is an id with at least one cell. Segments of the same class match when their
    IoU > 0.5 (unique); unmatched predictions are false positives and unmatched ground truths
    false negatives (background is not void). Per class PQ = sum(IoU of TP) / (TP + FP/2 + FN/2),
    SQ = sum(IoU of TP) / TP (0 without TP), RQ = TP / (TP + FP/2 + FN/2); each mean is over the
    classes with TP + FP + FN > 0 (NaN when there is none).

    Args:
      gts: per frame ``(instance_ids int [H, W] with 0 = no object, instance_classes int
        [K + 1])``, ``instance_classes[k]`` the class of id k (entry 0 unused).
      preds: per frame, the same for the prediction.
      num_classes: classes of present segments lie in ``0..num_classes - 1``.

    Returns:
      ``{"pq", "sq", "rq", "per_class": {class: {"pq", "sq", "rq", "tp", "fp", "fn"}}}``.
    """
    return _panoptic_stats(gts, preds, num_classes).panoptic()


def paper_miou(gts, preds, *, iou_threshold: float = 0.25, num_classes: int = NUM_CLASSES) -> dict:
    """The paper's mIoU: mean IoU of ground-truth objects matched to a same-class prediction.

    Per frame and class, segments (as in ``panoptic_quality``) are matched one-to-one greedily
    by IoU, highest first (ties: lower ground-truth id, then lower predicted id), among pairs
    with IoU >= ``iou_threshold`` (a correct detection at AP@0.25). Per class: the mean IoU of
    the matched ground-truth objects; ``miou``: the mean over classes with at least one match
    (NaN when none). Unmatched objects do not count: this measures footprint quality of found
    objects; AP and PQ measure finding them.

    Args:
      gts, preds: as in ``panoptic_quality``.
      iou_threshold: minimum IoU of a match, in (0, 1].
      num_classes: number of foreground classes.

    Returns:
      ``{"miou", "per_class": {class: float}, "matched": {class: int}}``.
    """
    return _panoptic_stats(gts, preds, num_classes, iou_threshold).paper_miou()


def semantic_miou(gts, preds, *, num_classes: int = NUM_CLASSES) -> dict:
    """Pixel-wise semantic BEV mIoU: class maps from the panoptic maps, IoU per class over all
    cells of all frames, mean over foreground classes whose union is non-empty.

    Args:
      gts, preds: as in ``panoptic_quality`` (cells with id 0 are background).
      num_classes: number of foreground classes.

    Returns:
      ``{"semantic_miou", "background_iou", "per_class": {class: float}}``.
    """
    return _panoptic_stats(gts, preds, num_classes).semantic_miou()


# --------------------------------------------------------------------------- evaluator

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


def format_percent(v: float | None) -> str:
    """A metric in % with one decimal; "-" where undefined (AP's -1, NaN, or JSON's null)."""
    return "-" if v is None or math.isnan(v) or v < 0 else f"{100 * v:.1f}"


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
