"""Metrics against pycocotools (mask AP) and direct numpy re-derivations (PQ, mIoU)."""

import contextlib
import io
import math

import jax
import numpy as np
import pytest

from indoorbev_jax.config import CLASS_NAMES, NUM_CLASSES, Config, InferenceConfig
from indoorbev_jax.inference import panoptic_inference
from indoorbev_jax.metrics import (
    Evaluator,
    class_confusion,
    format_confusion,
    format_found,
    mask_ap,
    mask_intersections,
    panoptic_quality,
    paper_miou,
    semantic_miou,
)
from indoorbev_jax.types import Predictions, Targets

THRESHOLDS = (0.25, 0.5)


# --------------------------------------------------------------------------- references


def _coco_eval(gts, dets, thresholds, num_classes, agnostic=False):
    """pycocotools' COCOeval (segm) after ``evaluate``; ``agnostic``: every object category 1."""
    from pycocotools import mask as mask_utils
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    def rle(m):
        return mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))

    def category(c):
        return 1 if agnostic else int(c) + 1

    images, anns, results = [], [], []
    for i, ((gm, gc), (dm, dc, ds)) in enumerate(zip(gts, dets, strict=True)):
        images.append({"id": i + 1, "height": gm.shape[1], "width": gm.shape[2]})
        for m, c in zip(gm, gc, strict=True):
            r = rle(m)
            anns.append({
                "id": len(anns) + 1, "image_id": i + 1, "category_id": category(c),
                "segmentation": r, "area": float(mask_utils.area(r)),
                "bbox": mask_utils.toBbox(r).tolist(), "iscrowd": 0,
            })  # fmt: skip
        for m, c, s in zip(dm, dc, ds, strict=True):
            results.append({
                "image_id": i + 1, "category_id": category(c), "segmentation": rle(m),
                "score": float(s),
            })  # fmt: skip
    categories = [{"id": k + 1, "name": str(k)} for k in range(1 if agnostic else num_classes)]
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = {"images": images, "annotations": anns, "categories": categories}
        gt.createIndex()
        if results:
            dt = gt.loadRes(results)
        else:  # loadRes cannot take an empty list
            dt = COCO()
            dt.dataset = {"images": images, "annotations": [], "categories": categories}
            dt.createIndex()
        ev = COCOeval(gt, dt, "segm")
        ev.params.iouThrs = np.array(thresholds, dtype=np.float64)
        ev.params.maxDets = [100]
        ev.params.areaRng = [[0, 1e10]]
        ev.params.areaRngLbl = ["all"]
        ev.evaluate()
    return ev


def coco_reference(gts, dets, thresholds=THRESHOLDS, num_classes=NUM_CLASSES):
    """AP per threshold and per class from pycocotools' COCOeval (segm)."""
    ev = _coco_eval(gts, dets, thresholds, num_classes)
    with contextlib.redirect_stdout(io.StringIO()):
        ev.accumulate()
    precision = ev.eval["precision"][:, :, :, 0, 0]  # [T, R, K]
    ap = {}
    for t, thr in enumerate(thresholds):
        s = precision[t]
        ap[thr] = float(np.mean(s[s > -1])) if np.any(s > -1) else -1.0
    per_class = {k: {thr: float(np.mean(precision[t, :, k])) for t, thr in enumerate(thresholds)}
                 for k in range(num_classes)}  # fmt: skip
    return ap, per_class


def coco_confusion_reference(gts, dets, threshold, num_classes=NUM_CLASSES):
    """Confusion from pycocotools' ``dtMatches`` with every object in one category."""
    ev = _coco_eval(gts, dets, (threshold,), num_classes, agnostic=True)
    gt_class = np.concatenate([np.asarray(gc, np.int64) for _, gc in gts])  # by annotation id - 1
    det_class = np.concatenate([np.asarray(dc, np.int64) for _, dc, _ in dets])  # by result id - 1
    confusion = np.zeros((num_classes, num_classes + 1), np.int64)
    for e in ev.evalImgs:
        if e is None:
            continue
        for did, gid in zip(e["dtIds"], e["dtMatches"][0], strict=True):
            if gid > 0:
                confusion[gt_class[int(gid) - 1], det_class[did - 1]] += 1
        for gid, hit in zip(e["gtIds"], e["gtMatches"][0], strict=True):
            if hit == 0:
                confusion[gt_class[gid - 1], num_classes] += 1
    return confusion


def random_mask(rng, h, w):
    m = np.zeros((h, w), bool)
    y, x = rng.integers(0, h - 2), rng.integers(0, w - 2)
    m[y : y + rng.integers(1, 7), x : x + rng.integers(1, 7)] = True
    if rng.random() < 0.3:  # an L or a blob: not every mask is a rectangle
        m[rng.integers(0, h), rng.integers(0, w)] = True
    return m


def random_frames(seed, num_frames=60, h=16, w=20, num_classes=NUM_CLASSES):
    """GTs and detections with overlaps, duplicates, score ties, wrong classes, empty frames."""
    rng = np.random.default_rng(seed)
    gts, dets = [], []
    for f in range(num_frames):
        ng = 0 if f % 11 == 3 else rng.integers(0, 6)
        gm = np.stack([random_mask(rng, h, w) for _ in range(ng)] or [np.zeros((h, w), bool)])
        gm = gm[:ng]
        # Class 8 never has ground truth; detections of it still occur.
        gc = rng.integers(0, num_classes - 1, ng)
        if ng >= 2 and rng.random() < 0.2:  # two identical GTs: IoU ties between GTs
            gm[1], gc[1] = gm[0], gc[0]
        dm, dc = [], []
        for m, c in zip(gm, gc, strict=True):
            for _ in range(rng.integers(0, 3)):  # misses, hits and duplicates
                d = np.roll(m, (rng.integers(-1, 2), rng.integers(-1, 2)), axis=(0, 1))
                if rng.random() < 0.3:
                    d = d | random_mask(rng, h, w)
                dm.append(d)
                dc.append(c if rng.random() < 0.8 else rng.integers(0, num_classes))
        for _ in range(rng.integers(0, 4)):  # false positives
            dm.append(random_mask(rng, h, w))
            dc.append(rng.integers(0, num_classes))
        if f % 7 == 2:  # frames with no predictions
            dm, dc = [], []
        nd = len(dm)
        scores = rng.integers(1, 8, nd) / 8.0  # coarse: many ties within and across frames
        dm = np.stack(dm) if nd else np.zeros((0, h, w), bool)
        gts.append((gm, gc))
        dets.append((dm, np.asarray(dc, np.int64), scores))
    return gts, dets


def assert_ap_equal(ours, ref_ap, ref_per_class):
    for thr in THRESHOLDS:
        assert ours["ap"][thr] == pytest.approx(ref_ap[thr], abs=1e-6)
        for k in range(NUM_CLASSES):
            assert ours["per_class"][k][thr] == pytest.approx(ref_per_class[k][thr], abs=1e-6)


def frame(gm, gc):
    return (np.asarray(gm, bool), np.asarray(gc))


# --------------------------------------------------------------------------- mask AP


def test_mask_intersections_match_direct_counts():
    rng = np.random.default_rng(0)
    a = rng.random((5, 9, 11)) < 0.3
    b = rng.random((4, 9, 11)) < 0.3
    a[1] = False  # an empty mask
    b[2] = False
    b[2, 8, 10] = True  # a single cell in the last row and column
    a[3, :, 10] = True
    inter, area_a, area_b = mask_intersections(a, b)
    np.testing.assert_array_equal(inter, (a[:, None] & b[None]).sum((2, 3)))
    np.testing.assert_array_equal(area_a, a.sum((1, 2)))
    np.testing.assert_array_equal(area_b, b.sum((1, 2)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mask_ap_equals_pycocotools_random(seed):
    gts, dets = random_frames(seed)
    ours = mask_ap(gts, dets, THRESHOLDS)
    assert_ap_equal(ours, *coco_reference(gts, dets))
    assert ours["per_class"][NUM_CLASSES - 1][0.5] == -1.0  # class without GT
    assert 0.0 < ours["ap"][0.25] < 1.0


def test_mask_ap_max_dets_truncation_equals_pycocotools():
    # 110 detections of one class per frame: only the best 100 count (per frame and class),
    # and the only hit on GT 3 has the lowest score, so truncation changes the result.
    rng = np.random.default_rng(3)
    h = w = 12
    gm = np.zeros((4, h, w), bool)
    for k in range(4):
        gm[k, 3 * k : 3 * k + 2, 1:5] = True
    fp = np.zeros((106, h, w), bool)
    fp[:, :, 8:] = rng.random((106, h, 4)) < 0.5  # never overlaps a GT
    dm = np.concatenate([gm, fp])
    scores = np.concatenate([[0.9, 0.8, 0.7, 0.001], rng.uniform(0.01, 1.0, 106)])
    gts = [(gm, np.zeros(4, np.int64))] * 3
    dets = [(dm, np.zeros(110, np.int64), scores)] * 3
    ours = mask_ap(gts, dets)
    assert_ap_equal(ours, *coco_reference(gts, dets))
    assert mask_ap(gts, dets, max_dets=110)["ap"][0.5] > ours["ap"][0.5]


def test_mask_ap_equals_pycocotools_bit_for_bit():
    """mask_ap is pycocotools' number exactly, not only to 1e-6: pycocotools divides by
    tp + fp + np.spacing(1), so a class whose first detection is a hit has precision
    1 / (1 + 2**-52) = 1 - 2**-53 there, and one exact detection scores 0.9999999999999999 (the
    mask_ap docstring's example), a difference the abs=1e-6 comparisons elsewhere cannot see."""
    gts, dets = random_frames(3, num_frames=30)
    ref_ap, ref_per_class = coco_reference(gts, dets)
    ours = mask_ap(gts, dets)
    assert ours["ap"] == ref_ap
    assert ours["per_class"] == ref_per_class
    one = (np.ones((1, 4, 4), bool), np.array([0]))
    exact = (np.ones((1, 4, 4), bool), np.array([0]), np.array([0.9]))
    assert mask_ap([one], [exact])["ap"] == coco_reference([one], [exact])[0]
    assert mask_ap([one], [exact])["ap"] == {0.25: 1 - 2**-53, 0.5: 1 - 2**-53}


def test_max_dets_boundary_is_per_frame_and_class_for_ap_per_frame_for_confusion():
    """pycocotools keeps the max_dets = 100 best detections per frame AND class for AP, and
    per frame for the class-agnostic confusion (every object in one category). (a) 100 false
    positives outscore the only hit, the 101st: AP 0 and the object missed, exactly at the
    boundary (a `<=` let it in). (b) 60 higher-scored class-1 false positives, then 50 class-0
    detections whose last one hits: the 110th of the frame but the 50th of its class, so AP
    counts it (recall 1 at precision 1/50) and the agnostic confusion does not."""
    h = w = 12
    gm = np.zeros((1, h, w), bool)
    gm[0, 0:2, 0:4] = True
    fp = np.zeros((100, h, w), bool)
    fp[:, 6:, 6:] = True  # never overlaps the ground truth
    gts = [(gm, np.zeros(1, np.int64))]
    last_hit = (np.concatenate([fp, gm]), np.zeros(101, np.int64),
                np.concatenate([np.linspace(0.9, 0.5, 100), [0.1]]))  # fmt: skip
    by_class = (np.concatenate([fp[:60], fp[:49], gm]), np.repeat([1, 0], [60, 50]),
                np.concatenate([np.full(60, 0.95), np.linspace(0.9, 0.5, 49), [0.1]]))  # fmt: skip
    for dets, ap50 in (([last_hit], 0.0), ([by_class], 1 / 50)):
        ours = mask_ap(gts, dets)
        assert ours["ap"] == coco_reference(gts, dets)[0]
        assert ours["ap"][0.5] == pytest.approx(ap50)
        confusion = class_confusion(gts, dets, 0.5)
        np.testing.assert_array_equal(confusion, coco_confusion_reference(gts, dets, 0.5))
        assert confusion[0, NUM_CLASSES] == 1  # missed in both: past the 100th of the frame


def test_mask_ap_iou_tie_goes_to_the_last_ground_truth():
    # Detection A has IoU 1/3 with both GTs; pycocotools gives it the later GT (its "<" test),
    # so the lower-scored exact hit B on that GT becomes a false positive.
    gm = np.zeros((2, 1, 5), bool)
    gm[0, 0, 0:2] = True
    gm[1, 0, 3:5] = True
    dm = np.zeros((2, 1, 5), bool)
    dm[0, 0, [1, 3]] = True  # A
    dm[1] = gm[1]  # B
    gts = [(gm, np.array([0, 0]))]
    dets = [(dm, np.array([0, 0]), np.array([0.9, 0.8]))]
    ours = mask_ap(gts, dets)
    assert_ap_equal(ours, *coco_reference(gts, dets))
    assert ours["ap"][0.25] == pytest.approx(51 / 101)  # recall stops at 1/2


def test_mask_ap_perfect_is_one():
    rng = np.random.default_rng(4)
    gts = [frame([random_mask(rng, 10, 10) for _ in range(3)], [0, 1, 2]) for _ in range(4)]
    dets = [(m, c, np.linspace(0.9, 0.5, len(c))) for m, c in gts]
    ours = mask_ap(gts, dets)
    assert ours["ap"] == {0.25: 1.0, 0.5: 1.0}
    assert_ap_equal(ours, *coco_reference(gts, dets))


def test_mask_ap_one_of_two_found_is_51_over_101():
    gm = np.zeros((2, 8, 8), bool)
    gm[0, :3, :3] = True
    gm[1, 5:, 5:] = True
    gts = [(gm, np.array([4, 4]))]
    dets = [(gm[:1], np.array([4]), np.array([0.7]))]
    ours = mask_ap(gts, dets)
    assert ours["ap"][0.5] == pytest.approx(51 / 101, abs=1e-12)
    assert_ap_equal(ours, *coco_reference(gts, dets))


def test_mask_ap_iou_exactly_at_threshold_and_single_pixel():
    gm = np.zeros((2, 6, 6), bool)
    gm[0, 2, 2] = True  # single-pixel object
    gm[1, 4, 0:2] = True
    dm = np.zeros((3, 6, 6), bool)
    dm[0, 2, 2] = True  # exact hit on the pixel
    dm[1, 4, 1:3] = True  # IoU 1/3 with gm[1]: found at 0.25, not at 0.5
    dm[2, 4, 0:4] = True  # IoU exactly 0.5 with gm[1] (2 / 4)
    gts = [(gm, np.array([0, 0]))]
    dets = [(dm, np.array([0, 0, 0]), np.array([0.9, 0.8, 0.1]))]
    ours = mask_ap(gts, dets)
    assert_ap_equal(ours, *coco_reference(gts, dets))
    assert ours["ap"][0.25] == 1.0


def test_mask_ap_no_ground_truth_and_no_predictions():
    empty = np.zeros((0, 5, 5), bool)
    no_gt = [(empty, np.zeros(0, int))] * 2
    dets = [(np.ones((1, 5, 5), bool), np.array([0]), np.array([0.5]))] * 2
    ours = mask_ap(no_gt, dets)
    assert ours["ap"] == {0.25: -1.0, 0.5: -1.0}  # pycocotools' "undefined"
    assert_ap_equal(ours, *coco_reference(no_gt, dets))
    gts = [(np.ones((1, 5, 5), bool), np.array([2]))] * 2
    no_det = [(empty, np.zeros(0, int), np.zeros(0))] * 2
    ours = mask_ap(gts, no_det)
    assert ours["ap"] == {0.25: 0.0, 0.5: 0.0}
    assert_ap_equal(ours, *coco_reference(gts, no_det))
    # An empty frame may be given as plain lists; the result is the same.
    assert mask_ap(gts, [([], [], [])] * 2) == ours
    assert mask_ap([([], [])] * 2, dets) == mask_ap(no_gt, dets)
    mixed = mask_ap([gts[0], ([], [])], [dets[0], ([], [], [])])
    assert mixed == mask_ap([gts[0], no_gt[0]], [dets[0], no_det[0]])


def test_mask_ap_rejects_bad_input():
    m = np.ones((1, 4, 4), bool)
    with pytest.raises(ValueError, match="gts and dets"):
        mask_ap([(m, np.array([0]))], [])
    with pytest.raises(ValueError, match=r"dets\[0\]: class ids"):
        mask_ap([(m, np.array([0]))], [(m, np.array([9]), np.array([0.5]))])
    with pytest.raises(ValueError, match="frame 0"):
        mask_ap([(m, np.array([0]))], [(np.ones((1, 3, 4), bool), np.array([0]), np.ones(1))])
    # Probabilities or logits read as bool are the whole grid: refused, not scored AP 0.
    prob = np.full((1, 4, 4), 0.1)
    prob[0, :2] = 0.9
    with pytest.raises(ValueError, match=r"dets\[0\]: masks must be bool .* in \[0\.1, 0\.9\]"):
        mask_ap([(m, np.array([0]))], [(prob, np.array([0]), np.ones(1))])
    with pytest.raises(ValueError, match=r"gts\[0\]: masks must be bool"):
        mask_ap([(prob - 0.5, np.array([0]))], [(m, np.array([0]), np.ones(1))])
    as_float = mask_ap([(m.astype(float), np.array([0]))], [(prob >= 0.5, [0], np.ones(1))])
    assert as_float == mask_ap([(m, np.array([0]))], [(prob >= 0.5, [0], np.ones(1))])


def test_iou_thresholds_above_1_are_refused():
    """An IoU threshold lies in [0, 1]: above 1 no pair can match, and percentages (25, 50)
    given by mistake were accepted by mask_ap and the Evaluator (mask_ap scored 1.5 as AP
    0.9999999999999999, pycocotools' cap at 1 - 1e-10 turning it into an exact-match test)."""
    g = (np.ones((1, 4, 4), bool), np.array([0]))
    d = (np.ones((1, 4, 4), bool), np.array([0]), np.array([0.9]))
    # Strings, bools, None and a bare number are named too (a string was a TypeError).
    refused = r"iou_thresholds: expected (a number in \[0, 1\]|at least one|a sequence of)"
    for bad in ((1.5,), (25, 50), (0.5, 1.0 + 1e-9), (-0.25,), (math.nan,), (),
                ("0.5",), (True,), (None,), 0.5, "0.25, 0.5"):  # fmt: skip
        with pytest.raises(ValueError, match=refused):
            mask_ap([g], [d], bad)
        with pytest.raises(ValueError, match=refused):
            Evaluator(iou_thresholds=bad)
    assert Evaluator(iou_thresholds=np.array([0.25, 0.5])).iou_thresholds == (0.25, 0.5)
    with pytest.raises(
        TypeError, match=r"inference: expected InferenceConfig, got Config; pass config\.inference"
    ):
        Evaluator(Config.tiny())
    with pytest.raises(TypeError, match=r"class_names: expected a sequence of names, got 'Chair'"):
        Evaluator(class_names="Chair")  # was 5 classes, one a letter
    # Any 1-D iterable of numbers still serves (a jax array, a generator); a 0-d array or a
    # bool array is named like a bare number or a bool.
    assert Evaluator(iou_thresholds=jax.numpy.array([0.25, 0.5])).iou_thresholds == (0.25, 0.5)
    assert Evaluator(iou_thresholds=(t for t in (0.25, 0.5))).iou_thresholds == (0.25, 0.5)
    for bad in (np.array(0.5), np.array([True])):
        with pytest.raises(ValueError, match=refused):
            Evaluator(iou_thresholds=bad)
    assert mask_ap([g], [d], (0.0, 1.0))["ap"] == coco_reference([g], [d], (0.0, 1.0))[0]


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("threshold", [0.25, 0.5])
def test_class_confusion_equals_pycocotools_agnostic_matches(seed, threshold):
    gts, dets = random_frames(seed)
    ours = class_confusion(gts, dets, threshold)
    np.testing.assert_array_equal(ours, coco_confusion_reference(gts, dets, threshold))
    num_gt = np.bincount(np.concatenate([gc for _, gc in gts]), minlength=NUM_CLASSES)
    np.testing.assert_array_equal(ours.sum(1), num_gt)  # every object counted once
    # random_frames relabels about 20 % of detections: some off the diagonal, most on it.
    assert 0 < ours[:, :NUM_CLASSES].sum() - np.trace(ours) < np.trace(ours)
    assert ours[:, NUM_CLASSES].sum() > 0


def test_class_confusion_hand_example():
    a = np.zeros((1, 6, 6), bool)
    a[0, :3, :3] = True
    b = np.zeros((1, 6, 6), bool)
    b[0, 3:, 3:] = True
    gts = [(np.concatenate([a, b]), np.array([0, 1]))]
    # The higher-scored class-2 detection takes object 0 first; the class-0 duplicate finds
    # nothing left, and object 1 has no detection: one confusion, one miss.
    dets = [(np.concatenate([a, a]), np.array([0, 2]), np.array([0.5, 0.9]))]
    expected = np.zeros((3, 4), np.int64)
    expected[0, 2] = 1
    expected[1, 3] = 1
    np.testing.assert_array_equal(class_confusion(gts, dets, num_classes=3), expected)
    text = format_confusion(expected, ["Table", "Chair", "Sofa"])
    assert text.splitlines()[1].split() == ["Table", "0", "0", "1", "0"]
    with pytest.raises(ValueError, match="expected shape \\(2, 3\\)"):
        format_confusion(expected, ["Table", "Chair"])
    for bad in (1.5, "0.5", None):
        with pytest.raises(ValueError, match=r"iou_threshold: expected a number in \[0, 1\]"):
            class_confusion(gts, dets, bad, num_classes=3)
    with pytest.raises(ValueError, match="gts and dets: 1 vs 0 frames"):
        class_confusion(gts, [], num_classes=3)
    with pytest.raises(ValueError, match=r"dets\[0\]: class ids must lie in 0..2"):
        class_confusion(gts, [(dets[0][0], np.array([0, 3]), dets[0][2])], num_classes=3)


# --------------------------------------------------------------------------- panoptic


def panoptic_reference(gts, preds, num_classes=NUM_CLASSES, match_iou=0.25):
    """Direct per-segment loops: PQ/SQ/RQ, the paper's mIoU and semantic mIoU."""
    tp, fp, fn = (np.zeros(num_classes) for _ in range(3))
    iou_sum, m_sum, m_cnt = np.zeros(num_classes), np.zeros(num_classes), np.zeros(num_classes)
    inter_c, union_c = np.zeros(num_classes), np.zeros(num_classes)
    for (gid, gcl), (pid, pcl) in zip(gts, preds, strict=True):
        gsegs = [k for k in range(1, len(gcl)) if (gid == k).any()]
        psegs = [k for k in range(1, len(pcl)) if (pid == k).any()]
        matched_p, pairs = set(), []
        for g in gsegs:
            hit = False
            for p in psegs:
                if gcl[g] != pcl[p]:
                    continue
                a, b = gid == g, pid == p
                iou = (a & b).sum() / (a | b).sum()
                if iou >= match_iou:
                    pairs.append((-iou, g, p))
                if iou > 0.5:
                    tp[gcl[g]] += 1
                    iou_sum[gcl[g]] += iou
                    matched_p.add(p)
                    hit = True
            if not hit:
                fn[gcl[g]] += 1
        for p in psegs:
            if p not in matched_p:
                fp[pcl[p]] += 1
        used_g, used_p = set(), set()
        for negiou, g, p in sorted(pairs):
            if g not in used_g and p not in used_p:
                used_g.add(g), used_p.add(p)
                m_sum[gcl[g]] += -negiou
                m_cnt[gcl[g]] += 1
        gsem = np.where(gid > 0, np.asarray(gcl)[gid], -1)
        psem = np.where(pid > 0, np.asarray(pcl)[pid], -1)
        for c in range(num_classes):
            inter_c[c] += ((gsem == c) & (psem == c)).sum()
            union_c[c] += ((gsem == c) | (psem == c)).sum()
    present = tp + fp + fn > 0
    pq = [iou_sum[c] / (tp[c] + fp[c] / 2 + fn[c] / 2) for c in range(num_classes) if present[c]]
    sq = [iou_sum[c] / tp[c] if tp[c] else 0.0 for c in range(num_classes) if present[c]]
    rq = [tp[c] / (tp[c] + fp[c] / 2 + fn[c] / 2) for c in range(num_classes) if present[c]]
    miou = [m_sum[c] / m_cnt[c] for c in range(num_classes) if m_cnt[c]]
    sem = [inter_c[c] / union_c[c] for c in range(num_classes) if union_c[c]]

    def mean(v):
        return float(np.mean(v)) if v else math.nan

    return {"pq": mean(pq), "sq": mean(sq), "rq": mean(rq), "miou": mean(miou),
            "semantic_miou": mean(sem), "tp": tp, "fp": fp, "fn": fn}  # fmt: skip


def random_panoptic(seed, num_frames=25, h=14, w=14):
    rng = np.random.default_rng(seed)
    gts, preds = [], []
    for _ in range(num_frames):
        k = rng.integers(0, 6)
        gid = np.zeros((h, w), np.int32)
        for i in range(k):
            gid[random_mask(rng, h, w)] = i + 1  # later ones overwrite: some ids vanish
        gcl = np.concatenate([[NUM_CLASSES], rng.integers(0, 4, k)])
        # Predictions: GT map shifted, some ids relabelled, plus random extra segments.
        pid = np.roll(gid, (rng.integers(-1, 2), rng.integers(-1, 2)), axis=(0, 1))
        pcl = gcl.copy()
        pcl[1:] = np.where(rng.random(k) < 0.2, rng.integers(0, 4, k), pcl[1:])
        extra = rng.integers(0, 3)
        for i in range(extra):
            pid[random_mask(rng, h, w)] = k + i + 1
        pcl = np.concatenate([pcl, rng.integers(0, 4, extra)])
        gts.append((gid, gcl))
        preds.append((pid, pcl))
    return gts, preds


@pytest.mark.parametrize("seed", [0, 1])
def test_panoptic_metrics_match_numpy_rederivation(seed):
    gts, preds = random_panoptic(seed)
    ref = panoptic_reference(gts, preds)
    ours = panoptic_quality(gts, preds)
    for key in ("pq", "sq", "rq"):
        assert ours[key] == pytest.approx(ref[key], abs=1e-12)
    for c in range(NUM_CLASSES):
        row = ours["per_class"][c]
        assert (row["tp"], row["fp"], row["fn"]) == (ref["tp"][c], ref["fp"][c], ref["fn"][c])
    assert paper_miou(gts, preds)["miou"] == pytest.approx(ref["miou"], abs=1e-12)
    assert semantic_miou(gts, preds)["semantic_miou"] == pytest.approx(
        ref["semantic_miou"], abs=1e-12
    )


def test_panoptic_quality_hand_example():
    gid = np.zeros((4, 6), np.int32)
    gid[0, 0:4] = 1  # class 0, 4 cells
    gid[3, 0:2] = 2  # class 2, missed: FN
    pid = np.zeros((4, 6), np.int32)
    pid[0, 0:4] = 1
    pid[1, 0:2] = 1  # 6 cells, IoU 4 / 6 with GT 1: TP
    pid[3, 4:6] = 2  # class 1 where nothing is: FP
    gts = [(gid, np.array([9, 0, 2]))]
    preds = [(pid, np.array([9, 0, 1]))]
    out = panoptic_quality(gts, preds)
    c0 = out["per_class"][0]
    assert c0["pq"] == pytest.approx(2 / 3) and c0["sq"] == pytest.approx(2 / 3)
    assert c0["rq"] == 1.0
    assert out["per_class"][1] == {"pq": 0.0, "sq": 0.0, "rq": 0.0, "tp": 0, "fp": 1, "fn": 0}
    assert out["per_class"][2]["fn"] == 1 and out["per_class"][2]["pq"] == 0.0
    assert math.isnan(out["per_class"][5]["pq"])  # absent class: not averaged
    assert out["pq"] == pytest.approx((2 / 3) / 3)
    assert out["sq"] == pytest.approx((2 / 3) / 3)
    assert out["rq"] == pytest.approx(1 / 3)
    # A half-overlapping prediction (IoU exactly 0.5) is not a match: IoU must exceed 0.5.
    pid2 = np.zeros((4, 6), np.int32)
    pid2[0, 0:2] = 1  # IoU 2 / 4
    out2 = panoptic_quality([(gid[:1], np.array([9, 0, 2]))], [(pid2[:1], np.array([9, 0]))])
    assert out2["per_class"][0]["tp"] == 0 and out2["pq"] == 0.0
    assert paper_miou([(gid[:1], np.array([9, 0, 2]))], [(pid2[:1], np.array([9, 0]))])[
        "miou"
    ] == pytest.approx(0.5)


def test_paper_miou_ties_go_to_the_lower_ids_and_its_threshold_is_above_0():
    """METRICS.md: pairs tied on IoU are taken lower ground-truth id first, then lower
    predicted id. One row of 12 cells, all class 0: GT A = cells 0-3, GT B = 4-7; P = 2-5
    (IoU 1/3 with A and with B), Q = {0, 1, 8, 9} (IoU 1/3 with A only). P numbered before Q
    takes A and leaves B alone (1 match); Q before P takes A and P then takes B (2)."""
    gt = np.zeros((1, 12), np.int32)
    gt[0, 0:4], gt[0, 4:8] = 1, 2
    p_cells, q_cells = [2, 3, 4, 5], [0, 1, 8, 9]
    for first, second, matched in ((p_cells, q_cells, 1), (q_cells, p_cells, 2)):
        pred = np.zeros((1, 12), np.int32)
        pred[0, first], pred[0, second] = 1, 2
        out = paper_miou([(gt, np.array([9, 0, 0]))], [(pred, np.array([9, 0, 0]))])
        assert out["matched"][0] == matched
        assert out["miou"] == pytest.approx(1 / 3)
    # At threshold 0 segments sharing no cell would be a match: refused, as a negative one.
    disjoint = np.zeros((1, 12), np.int32)
    disjoint[0, 10:12] = 1
    for bad in (0.0, -1.0, 1.5, math.nan, "0.5", True):
        with pytest.raises(ValueError, match=r"expected a number in \(0, 1\]"):
            paper_miou([(gt, np.array([9, 0, 0]))], [(disjoint, np.array([9, 0]))],
                       iou_threshold=bad)  # fmt: skip
        with pytest.raises(ValueError, match="miou_match_iou"):
            Evaluator(miou_match_iou=bad)
    tiny = paper_miou([(gt, np.array([9, 0, 0]))], [(disjoint, np.array([9, 0]))],
                      iou_threshold=1e-9)  # fmt: skip
    assert tiny["matched"][0] == 0 and math.isnan(tiny["miou"])


def test_paper_miou_takes_the_highest_iou_first_and_the_evaluator_shares_its_threshold():
    """One row of 10 cells, one class-0 GT; predicted segment 1 covers 4 of its cells (IoU
    0.4), segment 2 another 3 (IoU 0.3). Highest IoU first (METRICS.md) matches segment 1: mIoU
    0.4 (lowest first gave 0.3). The Evaluator's default match IoU is paper_miou's 0.25, so it
    reports the same 0.4 (at 0.5 nothing matched: NaN)."""
    gid = np.ones((1, 10), np.int32)
    pid = np.zeros((1, 10), np.int32)
    pid[0, 0:4], pid[0, 4:7] = 1, 2
    gt, pred = (gid, np.array([NUM_CLASSES, 0])), (pid, np.array([NUM_CLASSES, 0, 0]))
    out = paper_miou([gt], [pred])
    assert out["miou"] == pytest.approx(0.4) and out["matched"][0] == 1
    assert out["miou"] == pytest.approx(panoptic_reference([gt], [pred])["miou"])
    ev = Evaluator()
    masks = pid[None] == np.arange(1, 3)[:, None, None]
    ev.add_frame((gid[None] == 1, np.array([0])), (masks, np.array([0, 0]), np.array([0.9, 0.8])),
                 gt, pred)  # fmt: skip
    assert ev.compute()["miou"] == out["miou"]
    assert ev.compute()["per_class"][CLASS_NAMES[0]]["miou"] == pytest.approx(0.4)


def test_panoptic_edge_cases():
    empty = np.zeros((5, 5), np.int32)
    one = empty.copy()
    one[2, 3] = 1  # a single-pixel object
    bg = np.array([NUM_CLASSES, 4])
    # Perfect single pixel.
    out = panoptic_quality([(one, bg)], [(one, bg)])
    assert (out["pq"], out["sq"], out["rq"]) == (1.0, 1.0, 1.0)
    assert semantic_miou([(one, bg)], [(one, bg)])["semantic_miou"] == 1.0
    # No ground truth at all: the prediction is a false positive.
    out = panoptic_quality([(empty, bg)], [(one, bg)])
    assert out["pq"] == 0.0 and out["per_class"][4]["fp"] == 1
    # No predictions at all: a false negative.
    out = panoptic_quality([(one, bg)], [(empty, np.array([NUM_CLASSES]))])
    assert out["pq"] == 0.0 and out["per_class"][4]["fn"] == 1
    assert math.isnan(paper_miou([(one, bg)], [(empty, bg)])["miou"])
    # Neither: every mean is undefined.
    out = panoptic_quality([(empty, bg)], [(empty, bg)])
    assert math.isnan(out["pq"]) and math.isnan(out["rq"])


def test_panoptic_rejects_bad_input():
    ids = np.zeros((3, 3), np.int32)
    ids[0, 0] = 2
    with pytest.raises(ValueError, match=r"preds\[0\]: instance ids"):
        panoptic_quality([(ids * 0, np.array([9]))], [(ids, np.array([9, 0]))])
    with pytest.raises(ValueError, match=r"gts\[0\] classes"):
        panoptic_quality([(ids, np.array([9, 0, 12]))], [(ids * 0, np.array([9]))])
    # Float ids: whole ones are read as ids on both sides (predicted ones were a numpy
    # casting TypeError), others are refused by name.
    ok = np.zeros((4, 4), int)
    ok[:2] = 1
    want = panoptic_quality([(ok, np.array([9, 0]))], [(ok, np.array([9, 0]))])
    got = panoptic_quality([(ok * 1.0, np.array([9, 0]))], [(ok * 1.0, np.array([9, 0]))])
    assert got["pq"] == want["pq"] == 1.0
    with pytest.raises(ValueError, match=r"preds\[0\]: instance_ids must be whole numbers"):
        panoptic_quality([(ok, np.array([9, 0]))], [(ok * 0.5, np.array([9, 0]))])


# --------------------------------------------------------------------------- Evaluator


H, W, Q, M, B = 12, 14, 6, 4, 3


def random_targets(rng):
    masks = np.zeros((B, M, H, W), bool)
    for b in range(B):
        for m in range(M):
            masks[b, m] = random_mask(rng, H, W)
    valid = rng.random((B, M)) < 0.75
    valid[0, -1] = True
    masks[0, -1] = False  # a valid object with an empty mask: left out of AP
    classes = np.where(valid, rng.integers(0, NUM_CLASSES, (B, M)), NUM_CLASSES)
    ids = np.zeros((B, H, W), np.int32)
    for b in range(B):
        for m in range(M):
            ids[b][masks[b, m] & valid[b, m]] = m + 1
    z = np.zeros((B, M, 3), np.float32)
    return Targets(classes=classes, dims=z, pos=z, yaw=z[..., 0], valid=valid, masks=masks,
                   instance_ids=ids)  # fmt: skip


@pytest.mark.parametrize("threshold", [0.25, 0.5])
def test_tag_confusion_counts_matches_by_tag(threshold):
    gts, dets = random_frames(2)
    gts = list(gts)
    # An object with an empty mask leads a frame: its tag must leave with it (the tags of
    # the others shifted onto the wrong objects when it stayed).
    i = next(i for i, (_, gc) in enumerate(gts) if len(gc))
    gm, gc = gts[i]
    gts[i] = (np.concatenate([np.zeros_like(gm[:1]), gm]), np.concatenate([gc[:1], gc]))
    rng = np.random.default_rng(7)
    num_tags = 2 * NUM_CLASSES  # tag t belongs to class t // 2, as variants to their class
    ev = Evaluator()
    h, w = gts[0][0].shape[1:]
    empty = (np.zeros((h, w), np.int32), np.array([NUM_CLASSES]))
    tagged = []
    for gt, det in zip(gts, dets, strict=True):
        tags = 2 * gt[1] + rng.integers(0, 2, len(gt[1]))
        ev.add_frame(gt, det, empty, empty, gt_tags=tags)
        keep = gt[0].any((1, 2))  # the Evaluator leaves empty masks out
        tagged.append((gt[0][keep], tags[keep]))
    ours = ev.tag_confusion(num_tags, threshold)
    # pycocotools' class-agnostic matches with the tags as the ground-truth categories.
    ref = coco_confusion_reference(tagged, dets, threshold, num_classes=num_tags)
    np.testing.assert_array_equal(ours[:, :NUM_CLASSES], ref[:, :NUM_CLASSES])
    np.testing.assert_array_equal(ours[:, NUM_CLASSES], ref[:, num_tags])
    # Same matches as the class confusion: a class's tag rows sum to its row.
    by_class = ours.reshape(NUM_CLASSES, 2, NUM_CLASSES + 1).sum(1)
    np.testing.assert_array_equal(by_class, ev.confusion(threshold))
    assert ours[1::2].sum() > 0 and ours[::2].sum() > 0
    top = max(int(t.max()) for _, t in tagged if t.size)
    with pytest.raises(ValueError, match=f"tag {top} but num_tags is {top}"):
        ev.tag_confusion(top)
    ev.add_frame(gts[0], dets[0], empty, empty)
    with pytest.raises(ValueError, match=r"frames \[60\] were added without gt_tags"):
        ev.tag_confusion(num_tags)
    i = next(i for i, (_, gc) in enumerate(gts) if len(gc))
    with pytest.raises(ValueError, match="gt_tags must be"):
        ev.add_frame(gts[i], dets[i], empty, empty, gt_tags=-np.ones(len(gts[i][1]), int))


def test_named_tag_groupings_share_the_matches():
    gts, dets = random_frames(2)
    rng = np.random.default_rng(8)
    h, w = gts[0][0].shape[1:]
    empty = (np.zeros((h, w), np.int32), np.array([NUM_CLASSES]))
    alone, named = Evaluator(), Evaluator()
    for gt, det in zip(gts, dets, strict=True):
        variant = 2 * gt[1] + rng.integers(0, 2, len(gt[1]))
        alone.add_frame(gt, det, empty, empty, gt_tags=variant)
        size = rng.integers(0, 3, len(gt[1]))
        named.add_frame(gt, det, empty, empty, gt_tags={"variant": variant, "size": size})
    by_variant = named.tag_confusion(2 * NUM_CLASSES, 0.5, grouping="variant")
    np.testing.assert_array_equal(by_variant, alone.tag_confusion(2 * NUM_CLASSES, 0.5))
    by_size = named.tag_confusion(3, 0.5, grouping="size")
    np.testing.assert_array_equal(by_size.sum(0), named.confusion(0.5).sum(0))
    assert by_size.sum() == sum(int(g[0].any((1, 2)).sum()) for g in gts)
    with pytest.raises(ValueError, match=r"without gt_tags\['weight'\]"):
        named.tag_confusion(3, grouping="weight")
    with pytest.raises(ValueError, match="without gt_tags$"):
        named.tag_confusion(3)
    i = next(i for i, (_, gc) in enumerate(gts) if len(gc))
    bad = {"variant": np.zeros(len(gts[i][1]), int), "size": -np.ones(len(gts[i][1]), int)}
    with pytest.raises(ValueError, match=r"gt_tags\['size'\] must be"):
        named.add_frame(gts[i], dets[i], empty, empty, gt_tags=bad)


def test_format_found_counts_each_row():
    loose = np.array([[5, 1, 2], [0, 0, 0], [0, 2, 0]])  # 2 classes + missed column
    tight = np.array([[3, 1, 4], [0, 0, 0], [0, 2, 0]])
    lines = format_found({0.25: loose, 0.5: tight}, ["near", "mid", "far"]).splitlines()
    assert lines[0].split() == ["group", "objects", "miss@0.25", "%", "miss@0.5", "%"]
    assert lines[1].split() == ["near", "8", "2", "25.0", "4", "50.0"]
    assert lines[2].split() == ["mid", "0", "0", "-", "0", "-"]
    assert lines[3].split() == ["far", "2", "0", "0.0", "0", "0.0"]
    with pytest.raises(ValueError, match="at IoU 0.5: expected 2 rows"):
        format_found({0.5: tight}, ["near", "mid"])
    with pytest.raises(ValueError, match="row totals differ"):
        format_found({0.25: loose, 0.5: tight[[0, 2, 1]]}, ["near", "mid", "far"])


def predictions_from(logits, masks):
    z = np.zeros(logits.shape[:-1] + (3,), np.float32)
    return Predictions(logits=logits, dims=z, pos=z, yaw=z[..., :1], masks=masks)


def test_evaluator_equals_metric_functions_on_inference_output():
    rng = np.random.default_rng(5)
    ev = Evaluator(InferenceConfig(score_threshold=0.3))
    gts_ap, dets_ap, gts_pan, preds_pan = [], [], [], []
    for _ in range(2):
        targets = random_targets(rng)
        logits = 3 * rng.standard_normal((2, B, Q, NUM_CLASSES + 1), np.float32)
        masks = 4 * rng.standard_normal((2, B, Q, H, W), np.float32) - 1
        preds = predictions_from(logits, masks)
        ev.add(preds, targets)
        out = jax.tree.map(np.asarray, panoptic_inference(preds, ev.inference))
        t = jax.tree.map(np.asarray, targets)
        for b in range(B):
            keep = t.valid[b] & t.masks[b].any((1, 2))
            gts_ap.append((t.masks[b][keep], t.classes[b][keep]))
            dv = out.det_valid[b]
            dets_ap.append((out.det_masks[b][dv], out.det_classes[b][dv], out.det_scores[b][dv]))
            gts_pan.append((t.instance_ids[b], np.concatenate([[NUM_CLASSES], t.classes[b]])))
            preds_pan.append((out.instance_ids[b], out.instance_classes[b]))
    res = ev.compute()
    assert res["num_frames"] == 2 * B
    ap = mask_ap(gts_ap, dets_ap)
    assert res["ap"] == ap["ap"]
    assert_ap_equal(ap, *coco_reference(gts_ap, dets_ap))
    pan = panoptic_quality(gts_pan, preds_pan)
    assert (res["pq"], res["sq"], res["rq"]) == (pan["pq"], pan["sq"], pan["rq"])
    ref = panoptic_reference(gts_pan, preds_pan)
    assert res["miou"] == pytest.approx(ref["miou"], nan_ok=True)
    assert res["semantic_miou"] == pytest.approx(ref["semantic_miou"], nan_ok=True)
    np.testing.assert_array_equal(ev.confusion(0.5), class_confusion(gts_ap, dets_ap, 0.5))
    with pytest.raises(ValueError, match="gt_tags: expected shape"):
        ev.add_output(out, targets, gt_tags=np.zeros((B, 1), int))
    table = ev.table(res)
    assert all(name in table for name in CLASS_NAMES) and "AP@0.25" in table
    assert len(table.splitlines()) == NUM_CLASSES + 3


def test_evaluator_perfect_predictions():
    rng = np.random.default_rng(6)
    targets = random_targets(rng)
    targets = targets.replace(masks=targets.masks & (targets.instance_ids[:, None] > 0))
    onehot = np.eye(NUM_CLASSES + 1, dtype=np.float32)[targets.classes]  # padding: background
    logits = 20.0 * onehot[None]  # [1, B, M, K]
    # Each query draws exactly its object's cells of the panoptic map.
    own = targets.instance_ids[:, None] == np.arange(1, M + 1)[None, :, None, None]
    masks = np.where(own, 10.0, -10.0).astype(np.float32)[None]  # [1, B, M, H, W]
    ev = Evaluator()
    ev.add(predictions_from(logits, masks), targets)
    res = ev.compute()
    assert res["ap"] == {0.25: 1.0, 0.5: 1.0}
    assert (res["pq"], res["sq"], res["rq"], res["miou"]) == (1.0, 1.0, 1.0, 1.0)
    assert res["semantic_miou"] == 1.0 and res["background_iou"] == 1.0


# --------------------------------------------------------------------------- indoorbev eval


def test_eval_cli_matches_metric_functions(tmp_path, capsys):
    import json

    from indoorbev_jax.cli import main
    from indoorbev_jax.config import Config
    from indoorbev_jax.data import kitti
    from indoorbev_jax.data.rasterize import rasterize_boxes

    config = Config.tiny()
    grid, names = config.grid, config.data.class_names
    h, w = grid.shape

    def labels(classes, boxes, scores=None):
        boxes = np.asarray(boxes, np.float32).reshape(-1, 5)  # (x, y, length, width, yaw)
        n = len(boxes)
        pos = np.concatenate([boxes[:, :2], np.full((n, 1), 0.5)], axis=1)
        dims = np.concatenate([boxes[:, 2:4], np.ones((n, 1))], axis=1)
        return kitti.ObjectLabels(classes, dims, pos, boxes[:, 4], np.zeros(n), scores)

    def raster(boxes):
        boxes = np.asarray(boxes, np.float32).reshape(-1, 5)
        ids, masks = rasterize_boxes(boxes, np.ones(len(boxes), bool), grid)
        return np.asarray(ids), np.asarray(masks)

    gts_ap, dets_ap, gts_pan, preds_pan = [], [], [], []
    # Frame a: true-shape masks (an L and a disc-ish blob) in mask_2, predictions too.
    gid = np.zeros((h, w), np.int32)
    gid[5:15, 5:8] = 1
    gid[12:15, 8:14] = 1
    gid[25:31, 20:26] = 2
    pid = np.zeros((h, w), np.int32)
    pid[5:15, 5:8] = 1  # the L without its foot: IoU 30 / 48
    pid[25:31, 21:27] = 2  # the blob shifted by one column: IoU 30 / 42
    pid[0:2, 30:33] = 3  # a false positive
    dummy = [[0.0, 0.0, 1.0, 1.0, 0.0]] * 3
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", labels([0, 3], dummy[:2]), names)
    kitti.write_mask(tmp_path / "gt/mask_2/a.png", gid)
    scores = np.array([0.9, 0.6, 0.7], np.float32)
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", labels([0, 3, 1], dummy, scores), names)
    kitti.write_mask(tmp_path / "pred/mask_2/a.png", pid)
    gts_ap.append((gid[None] == np.arange(1, 3)[:, None, None], np.array([0, 3])))
    dets_ap.append((pid[None] == np.arange(1, 4)[:, None, None], np.array([0, 3, 1]), scores))
    gts_pan.append((gid, np.array([9, 0, 3])))
    preds_pan.append((pid, np.array([9, 0, 3, 1])))
    # Frame b: boxes only, rasterised on both sides; a wrong-class and a good detection.
    gboxes = [[0.0, 0.0, 2.0, 1.0, 0.0], [-3.0, 2.0, 1.0, 1.0, 0.0]]
    pboxes = [[0.25, 0.0, 2.0, 1.0, 0.0], [-3.0, 2.0, 1.0, 1.0, 0.0]]
    kitti.write_labels(tmp_path / "gt/label_2/b.txt", labels([2, 6], gboxes), names)
    scores_b = np.array([0.8, 0.5], np.float32)
    kitti.write_labels(tmp_path / "pred/label_2/b.txt", labels([2, 7], pboxes, scores_b), names)
    (gi, gm), (pi, pm) = raster(gboxes), raster(pboxes)
    gts_ap.append((gm, np.array([2, 6])))
    dets_ap.append((pm, np.array([2, 7]), scores_b))
    gts_pan.append((gi, np.array([9, 2, 6])))
    preds_pan.append((pi, np.array([9, 2, 7])))
    # Frame c: nothing at all.
    kitti.write_labels(tmp_path / "gt/label_2/c.txt", labels([], []), names)
    kitti.write_labels(tmp_path / "pred/label_2/c.txt", labels([], [], []), names)
    gts_ap.append((np.zeros((0, h, w), bool), np.zeros(0, int)))
    dets_ap.append((np.zeros((0, h, w), bool), np.zeros(0, int), np.zeros(0)))
    gts_pan.append((np.zeros((h, w), np.int32), np.array([9])))
    preds_pan.append((np.zeros((h, w), np.int32), np.array([9])))

    out = tmp_path / "metrics.json"
    argv = ["eval", "--gt", str(tmp_path / "gt"), "--pred", str(tmp_path / "pred")]
    assert main([*argv, "--preset", "tiny", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert all(name in printed for name in names) and "frames: 3" in printed
    res = json.loads(out.read_text())
    ap = mask_ap(gts_ap, dets_ap)
    assert_ap_equal(ap, *coco_reference(gts_ap, dets_ap))
    for thr in THRESHOLDS:
        assert res["ap"][str(thr)] == pytest.approx(ap["ap"][thr], abs=1e-12)
    pan = panoptic_quality(gts_pan, preds_pan)
    for key in ("pq", "sq", "rq"):
        assert res[key] == pytest.approx(pan[key], abs=1e-12)
    ref = panoptic_reference(gts_pan, preds_pan)
    assert res["miou"] == pytest.approx(ref["miou"]) and res["per_class"]["Misc"]["pq"] is None
    assert res["semantic_miou"] == pytest.approx(ref["semantic_miou"])
    confusion = res["confusion@0.5"]
    assert confusion["columns"] == [*names, "missed"]
    np.testing.assert_array_equal(confusion["counts"], class_confusion(gts_ap, dets_ap, 0.5))
    # Frame b's Person (class 6) was found as a Robot (class 7): the one confusion.
    assert confusion["counts"][6][7] == 1 and "confusion at mask IoU 0.5" in printed
    # A missing prediction file is an error naming it.
    (tmp_path / "pred/label_2/c.txt").unlink()
    assert main([*argv, "--preset", "tiny"]) == 1
    printed = capsys.readouterr().err  # errors go to stderr, past `> metrics.txt`
    assert "1 of 3 frames have no prediction label file, e.g. " in printed
    assert "pred/label_2/c.txt (write an empty file" in printed
    # A folder in its place is said to be one (it read as a file simply missing).
    (tmp_path / "pred/label_2/c.txt").mkdir()
    assert main([*argv, "--preset", "tiny"]) == 1
    assert "pred/label_2/c.txt (a folder or other non-file there)" in capsys.readouterr().err


def test_eval_cli_says_which_objects_have_no_cell(tmp_path, capsys):
    """Objects whose mask has no cell are left out of AP (METRICS); the command says how
    many on each side and names one, since pycocotools would count them."""
    from indoorbev_jax.cli import main
    from indoorbev_jax.config import Config
    from indoorbev_jax.data import kitti

    config = Config.tiny()
    names, (h, w) = config.data.class_names, config.grid.shape

    def labels(n, scores=None):
        one = np.ones((n, 3))
        return kitti.ObjectLabels([1] * n, one, one * 0.5, np.zeros(n), np.zeros(n), scores)

    gid = np.zeros((h, w), np.int32)
    gid[5:9, 5:9] = 1  # object 2 of the ground truth has no cell
    pid = np.zeros((h, w), np.int32)
    pid[5:9, 5:9] = 2  # the high-score line 1 has no cell, line 2 is exact
    kitti.write_labels(tmp_path / "gt/label_2/a.txt", labels(2), names)
    kitti.write_mask(tmp_path / "gt/mask_2/a.png", gid)
    kitti.write_labels(tmp_path / "pred/label_2/a.txt", labels(2, np.array([0.9, 0.1])), names)
    kitti.write_mask(tmp_path / "pred/mask_2/a.png", pid)
    argv = ["eval", "--gt", str(tmp_path / "gt"), "--pred", str(tmp_path / "pred")]
    assert main([*argv, "--preset", "tiny"]) == 0
    printed = capsys.readouterr().out
    assert "note: 1 ground-truth objects have no cell in their mask and are left out of AP, " \
        f"e.g. {tmp_path / 'gt/label_2/a.txt'}, the object of mask id 2" in printed  # fmt: skip
    assert "note: 1 prediction objects have no cell" in printed
    assert "the object of mask id 1" in printed
    # The counts cover every frame, not the last one read.
    for side in ("gt", "pred"):
        for kind, ext in (("label_2", "txt"), ("mask_2", "png")):
            copy = tmp_path / side / kind / f"b.{ext}"
            copy.write_bytes((tmp_path / side / kind / f"a.{ext}").read_bytes())
    assert main([*argv, "--preset", "tiny"]) == 0
    printed = capsys.readouterr().out
    assert "note: 2 ground-truth objects have no cell" in printed
    assert "note: 2 prediction objects have no cell" in printed
    # An empty split file names itself.
    (tmp_path / "gt/val.txt").write_text("\n")
    assert main([*argv, "--preset", "tiny", "--split", "val"]) == 1
    assert f"{tmp_path / 'gt/val.txt'}: no frames" in capsys.readouterr().err


def test_evaluator_takes_targets_as_a_dict_like_set_loss():
    """types.py lets the containers read like the PyTorch code's dicts; the Evaluator read
    targets.classes and raised a bare AttributeError for one."""
    import dataclasses as dc

    import jax.numpy as jnp

    from indoorbev_jax.types import Targets

    rng = np.random.default_rng(0)
    b, q, m, h, w = 1, 4, 2, 8, 8
    preds = {"logits": jnp.asarray(rng.normal(size=(1, b, q, 10)), jnp.float32),
             "dims": jnp.zeros((1, b, q, 3)), "pos": jnp.zeros((1, b, q, 3)),
             "yaw": jnp.zeros((1, b, q, 1)),
             "masks": jnp.asarray(rng.normal(size=(1, b, q, h, w)), jnp.float32)}  # fmt: skip
    masks = np.zeros((b, m, h, w), bool)
    masks[0, 0, :3, :3] = True
    targets = Targets(classes=jnp.array([[1, 9]]), dims=jnp.ones((b, m, 3)),
                      pos=jnp.zeros((b, m, 3)), yaw=jnp.zeros((b, m)),
                      valid=jnp.array([[True, False]]), masks=jnp.asarray(masks),
                      instance_ids=jnp.asarray(masks[:, 0].astype(np.int32)))  # fmt: skip
    as_dataclass, as_dict = Evaluator(), Evaluator()
    as_dataclass.add(preds, targets)
    as_dict.add(preds, {f.name: getattr(targets, f.name) for f in dc.fields(targets)})
    np.testing.assert_equal(as_dict.compute(), as_dataclass.compute())  # NaN mIoU: no match
    with pytest.raises(TypeError, match=r"targets: missing \['instance_ids'\]"):
        Evaluator().add(preds, {f.name: getattr(targets, f.name) for f in dc.fields(targets)
                                if f.name != "instance_ids"})  # fmt: skip


def test_a_refused_frame_or_batch_leaves_the_evaluator_as_it_was():
    """add_frame kept a frame's AP half when the panoptic check refused it, and add_output
    kept the frames before a refused one, so AP and PQ covered different frame sets."""
    rng = np.random.default_rng(8)
    ev = Evaluator(InferenceConfig(score_threshold=0.3))
    targets = random_targets(rng)
    logits = 3 * rng.standard_normal((2, B, Q, NUM_CLASSES + 1), np.float32)
    preds = predictions_from(logits, 4 * rng.standard_normal((2, B, Q, H, W), np.float32) - 1)
    out = jax.tree.map(np.asarray, panoptic_inference(preds, ev.inference))
    tags = np.asarray(targets.classes) % 3  # the refused batch's tags must go with it too
    ev.add_output(out, targets, gt_tags=tags)
    before, tagged = ev.compute(), ev.tag_confusion(3)
    bad_ids = out.instance_ids.copy()
    bad_ids[B - 1, 0, 0] = out.instance_classes.shape[1]  # an id with no class entry
    with pytest.raises(ValueError, match=rf"preds\[{2 * B - 1}\]"):
        ev.add_output(out.replace(instance_ids=bad_ids), targets, gt_tags=tags)
    np.testing.assert_array_equal(ev.tag_confusion(3), tagged)
    m = np.zeros((1, H, W), bool)
    m[0, :2, :2] = True
    ids = m[0].astype(np.int32)
    frame = dict(gt=(m, np.array([0])), det=(m, np.array([0]), np.array([0.9])),
                 gt_panoptic=(ids, np.array([NUM_CLASSES, 0])),
                 pred_panoptic=(ids, np.array([NUM_CLASSES])))  # fmt: skip
    with pytest.raises(ValueError, match=rf"preds\[{B}\]"):
        ev.add_frame(**frame)
    np.testing.assert_equal(ev.compute(), before)
    # Counts that disagree are named as mask_ap names them, not a bare IndexError.
    with pytest.raises(ValueError, match=rf"gts\[{B}\]: expected masks \[M, H, W\] and classes"):
        ev.add_frame(**dict(frame, gt=(m, np.array([0, 1]))))
    with pytest.raises(ValueError, match=rf"dets\[{B}\]: expected masks \[D, H, W\]"):
        ev.add_frame(**dict(frame, det=(m, np.array([0]), np.array([0.9, 0.8]))))
    np.testing.assert_equal(ev.compute(), before)
    np.testing.assert_array_equal(ev.tag_confusion(3), tagged)


def test_table_rows_and_mean_row_are_the_computed_values():
    """Every cell of the printed table is its ``compute()`` value in %: the mean row's
    semIoU column showing mIoU instead passed every test."""
    from indoorbev_jax.metrics import format_percent

    rng = np.random.default_rng(9)
    ev = Evaluator(InferenceConfig(score_threshold=0.3))
    targets = random_targets(rng)
    logits = 3 * rng.standard_normal((2, B, Q, NUM_CLASSES + 1), np.float32)
    ev.add(predictions_from(logits, 4 * rng.standard_normal((2, B, Q, H, W), np.float32) - 1),
           targets)  # fmt: skip
    r = ev.compute()
    assert r["miou"] != r["semantic_miou"]  # the columns can be told apart
    lines = ev.table(r).splitlines()
    keys = ["ap@0.25", "ap@0.5", "pq", "sq", "rq", "miou", "semantic_iou"]
    means = [r["ap"][0.25], r["ap"][0.5], r["pq"], r["sq"], r["rq"], r["miou"], r["semantic_miou"]]
    rows = {line.split()[0]: line.split()[1:] for line in lines[1:-1]}
    total = sum(row["num_gt"] for row in r["per_class"].values())
    assert rows["mean"] == [str(total), *map(format_percent, means)]
    for name, row in r["per_class"].items():
        assert rows[name] == [str(row["num_gt"]), *(format_percent(row[k]) for k in keys)]


def test_metrics_keeps_the_names_of_the_one_module_it_was():
    """metrics.py became a package (ap, panoptic, evaluator); every name it had, its helpers
    included, is still read from ``indoorbev_jax.metrics``."""
    from indoorbev_jax import metrics
    from indoorbev_jax.metrics import ap, evaluator, panoptic

    assert metrics.mask_ap is ap.mask_ap and metrics.Evaluator is evaluator.Evaluator
    assert metrics._coco_precision is ap._coco_precision
    assert metrics._PanopticStats is panoptic._PanopticStats
    assert metrics._tag_groupings is evaluator._tag_groupings
    with pytest.raises(AttributeError, match="has no attribute 'nothing_here'"):
        metrics.nothing_here  # noqa: B018
