"""Mask AP equal to pycocotools' COCOeval (segm), mask IoU, and the class confusion at an
IoU (docs/METRICS.md)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from indoorbev_jax.config import CLASS_NAMES, NUM_CLASSES

# pycocotools' recall grid, built the same way so the values match bit for bit.
_REC_THRS = np.linspace(0.0, 1.00, int(np.round((1.00 - 0.0) / 0.01)) + 1, endpoint=True)


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


def format_percent(v: float | None) -> str:
    """A metric in % with one decimal; "-" where undefined (AP's -1, NaN, or JSON's null)."""
    return "-" if v is None or math.isnan(v) or v < 0 else f"{100 * v:.1f}"
