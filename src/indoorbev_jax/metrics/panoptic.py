"""Panoptic quality (PQ = SQ x RQ), the paper's mIoU and the semantic BEV mIoU from
instance-id maps (docs/METRICS.md)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from indoorbev_jax.config import NUM_CLASSES
from indoorbev_jax.metrics.ap import _check_classes, _check_iou, _iou_from_counts


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
