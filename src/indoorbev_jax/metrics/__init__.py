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

from indoorbev_jax.metrics import ap as _ap
from indoorbev_jax.metrics import evaluator as _evaluator
from indoorbev_jax.metrics import panoptic as _panoptic
from indoorbev_jax.metrics.ap import (
    class_confusion,
    confusion_json,
    format_confusion,
    format_found,
    mask_ap,
    mask_intersections,
)
from indoorbev_jax.metrics.evaluator import (
    DEFAULT_GROUPING,
    Evaluator,
    combine_results,
    format_percent,
    format_table,
)
from indoorbev_jax.metrics.panoptic import panoptic_quality, paper_miou, semantic_miou

__all__ = [
    "DEFAULT_GROUPING",
    "Evaluator",
    "class_confusion",
    "combine_results",
    "confusion_json",
    "format_confusion",
    "format_found",
    "format_percent",
    "format_table",
    "mask_ap",
    "mask_intersections",
    "panoptic_quality",
    "paper_miou",
    "semantic_miou",
]


def __getattr__(name: str):
    # metrics was one module until 2026-12-07: code that reached its helpers by that name
    # (metrics._coco_precision, say) still finds them.
    for module in (_ap, _panoptic, _evaluator):
        if name in vars(module):
            return vars(module)[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
