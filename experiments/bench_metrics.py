"""Benchmark: mask AP, PQ and the Evaluator on paper-sized frames, next to pycocotools.

The same inputs go to ``metrics.mask_ap`` and to pycocotools' ``COCOeval`` (segm; RLE
encoding included in its time, since a pycocotools user has to encode), interleaved, median of
``--repeats`` runs; the two AP values are checked to agree to 1e-6. Frames are ``--distinct``
random scenes cycled to ``--frames`` (the list holds references, so memory stays bounded);
neither side caches anything across frames.

Also timed: ``panoptic_quality`` on the same frames' panoptic maps, and ``Evaluator.add`` from
raw logits (panoptic inference under jit + statistics) for ``--eval-frames`` frames.

    .venv/bin/python experiments/bench_metrics.py [--frames 1000] [--repeats 3]

pycocotools is a test dependency (``pip install -e .[dev]``).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import statistics
import time

import numpy as np

from indoorbev_jax.cli import HelpFormatter
from indoorbev_jax.config import NUM_CLASSES, InferenceConfig
from indoorbev_jax.metrics import Evaluator, mask_ap, panoptic_quality
from indoorbev_jax.types import Predictions, Targets


def make_frame(rng, h, w, num_gt, num_det):
    """Random footprints (rectangles and discs), detections near them plus false positives."""
    yy, xx = np.mgrid[:h, :w]

    def shape():
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        r = rng.uniform(8, 50)  # 0.16 m .. 1 m half-size at 0.02 m cells
        if rng.random() < 0.5:
            return (np.abs(yy - cy) < r) & (np.abs(xx - cx) < rng.uniform(8, 50))
        return (yy - cy) ** 2 + (xx - cx) ** 2 < r**2

    gm = np.stack([shape() for _ in range(num_gt)])
    gc = rng.integers(0, NUM_CLASSES, num_gt)
    dm, dc = [], []
    for k in range(num_det):
        if k < num_gt and rng.random() < 0.8:
            dm.append(np.roll(gm[k], rng.integers(-6, 7, 2), axis=(0, 1)))
            dc.append(gc[k] if rng.random() < 0.85 else rng.integers(0, NUM_CLASSES))
        else:
            dm.append(shape())
            dc.append(rng.integers(0, NUM_CLASSES))
    ids = np.zeros((h, w), np.int32)
    for k in np.argsort(-gm.sum((1, 2))):  # smaller objects on top, like the rasteriser
        ids[gm[k]] = k + 1
    pid = np.zeros((h, w), np.int32)
    for k in range(num_det):
        pid[dm[k] & (pid == 0)] = k + 1
    gt = (gm, gc)
    det = (np.stack(dm), np.asarray(dc), rng.random(num_det))
    pan_gt = (ids, np.concatenate([[NUM_CLASSES], gc]))
    pan_pred = (pid, np.concatenate([[NUM_CLASSES], dc]))
    return gt, det, pan_gt, pan_pred


def pycocotools_ap(gts, dets, thresholds):
    from pycocotools import mask as mask_utils
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    images, anns, results = [], [], []
    for i, ((gm, gc), (dm, dc, ds)) in enumerate(zip(gts, dets, strict=True)):
        images.append({"id": i + 1, "height": gm.shape[1], "width": gm.shape[2]})
        rles = mask_utils.encode(np.asfortranarray(gm.transpose(1, 2, 0).astype(np.uint8)))
        areas = mask_utils.area(rles)
        for r, a, c in zip(rles, areas, gc, strict=True):
            anns.append({"id": len(anns) + 1, "image_id": i + 1, "category_id": int(c) + 1,
                         "segmentation": r, "area": float(a), "iscrowd": 0})  # fmt: skip
        rles = mask_utils.encode(np.asfortranarray(dm.transpose(1, 2, 0).astype(np.uint8)))
        for r, c, s in zip(rles, dc, ds, strict=True):
            results.append({"image_id": i + 1, "category_id": int(c) + 1,
                            "segmentation": r, "score": float(s)})  # fmt: skip
    categories = [{"id": k + 1, "name": str(k)} for k in range(NUM_CLASSES)]
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = {"images": images, "annotations": anns, "categories": categories}
        gt.createIndex()
        ev = COCOeval(gt, gt.loadRes(results), "segm")
        ev.params.iouThrs = np.array(thresholds)
        ev.params.maxDets = [100]
        ev.params.areaRng = [[0, 1e10]]
        ev.params.areaRngLbl = ["all"]
        ev.evaluate()
        ev.accumulate()
    out = {}
    for t, thr in enumerate(thresholds):
        s = ev.eval["precision"][t, :, :, 0, 0]
        out[thr] = float(np.mean(s[s > -1]))
    return out


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def bench_evaluator(rng, frames, h, w, q, m, batch):
    """Evaluator.add from raw logits: jitted panoptic inference + per-frame statistics."""
    logits = rng.normal(0, 3, (1, batch, q, NUM_CLASSES + 1)).astype(np.float32)
    # Confident background (as a trained model gives) with one 50 x 40 cell blob per query.
    masks = rng.normal(-8, 1.5, (1, batch, q, h, w)).astype(np.float32)
    gmask = np.zeros((batch, m, h, w), bool)
    for b in range(batch):
        for k in range(q):
            y, x = rng.integers(0, h - 60), rng.integers(0, w - 60)
            masks[0, b, k, y : y + 50, x : x + 40] += 12.0
            if k < m:
                gmask[b, k, y + 3 : y + 53, x : x + 40] = True
    ids = np.zeros((batch, h, w), np.int32)
    for b, k in np.ndindex(batch, m):
        ids[b][gmask[b, k]] = k + 1
    z = np.zeros((batch, m, 3), np.float32)
    targets = Targets(
        classes=rng.integers(0, NUM_CLASSES, (batch, m)), dims=z, pos=z, yaw=z[..., 0],
        valid=np.ones((batch, m), bool), masks=gmask, instance_ids=ids,
    )  # fmt: skip
    zq = np.zeros((1, batch, q, 3), np.float32)
    preds = Predictions(logits=logits, dims=zq, pos=zq, yaw=zq[..., :1], masks=masks)
    ev = Evaluator(InferenceConfig(score_threshold=0.5))
    ev.add(preds, targets)  # compile
    ev.reset()
    per_batch = [timed(lambda: ev.add(preds, targets))[0] for _ in range(frames // batch)]
    t_compute, res = timed(ev.compute)
    return statistics.median(per_batch) / batch, t_compute / ev.num_frames, res


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter
    )
    parser.add_argument(
        "--frames",
        type=int,
        default=1000,
        help="frames scored by mask_ap, pycocotools and panoptic_quality",
    )
    parser.add_argument(
        "--distinct", type=int, default=20, help="random frames made, cycled to --frames"
    )
    parser.add_argument("--size", type=int, default=500, help="grid cells a side (H = W)")
    parser.add_argument("--queries", type=int, default=30, help="detections per frame")
    parser.add_argument("--objects", type=int, default=15, help="ground-truth objects per frame")
    parser.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="interleaved timed runs of the AP and PQ rows (their median)",
    )
    parser.add_argument(
        "--eval-frames",
        type=int,
        default=200,
        help="frames for the Evaluator row (at least --eval-batch)",
    )
    parser.add_argument("--eval-batch", type=int, default=4, help="frames per Evaluator.add call")
    parser.add_argument(
        "--skip-pycocotools",
        action="store_true",
        help="time ours only (pycocotools not installed, say)",
    )
    args = parser.parse_args(argv)
    if args.size < 64:  # footprints and blobs reach 60 cells
        parser.error(f"--size must be at least 64 cells, got {args.size}")
    for flag in ("frames", "distinct", "queries", "objects", "repeats", "eval_frames",
                 "eval_batch"):  # fmt: skip
        if getattr(args, flag) < 1:
            parser.error(f"--{flag.replace('_', '-')} must be at least 1")
    if args.eval_frames < args.eval_batch:
        parser.error(f"--eval-frames {args.eval_frames}: at least --eval-batch {args.eval_batch}")
    if not args.skip_pycocotools and importlib.util.find_spec("pycocotools") is None:
        parser.error(
            "pycocotools is not installed (pip install -e .[dev]); or add --skip-pycocotools"
        )

    rng = np.random.default_rng(0)
    h = w = args.size
    distinct = [make_frame(rng, h, w, args.objects, args.queries) for _ in range(args.distinct)]
    frames = [distinct[i % args.distinct] for i in range(args.frames)]
    gts, dets, pan_gts, pan_preds = (list(x) for x in zip(*frames, strict=True))
    thresholds = (0.25, 0.5)
    print(
        f"{args.frames} frames ({args.distinct} distinct), {h} x {w}, {args.objects} GT objects, "
        f"{args.queries} detections per frame"
    )

    ours_t, ref_t, pq_t = [], [], []
    for r in range(args.repeats):
        t, ours = timed(lambda: mask_ap(gts, dets, thresholds))
        ours_t.append(t)
        t, pan = timed(lambda: panoptic_quality(pan_gts, pan_preds))
        pq_t.append(t)
        if not args.skip_pycocotools:
            t, ref = timed(lambda: pycocotools_ap(gts, dets, thresholds))
            ref_t.append(t)
            for thr in thresholds:
                assert abs(ours["ap"][thr] - ref[thr]) < 1e-6, (thr, ours["ap"][thr], ref[thr])
        print(f"  run {r}: mask_ap {ours_t[-1]:.2f} s" + (f", pycocotools {ref_t[-1]:.2f} s"
              if ref_t else "") + f", panoptic_quality {pq_t[-1]:.2f} s")  # fmt: skip
    ap = ", ".join(f"AP@{t:g} = {ours['ap'][t]:.4f}" for t in thresholds)
    print(f"mask_ap: {ap}; PQ = {pan['pq']:.4f}")
    med = statistics.median(ours_t)
    print(f"mask_ap          median {med:.2f} s  ({1e3 * med / args.frames:.2f} ms/frame)")
    if ref_t:
        ref_med = statistics.median(ref_t)
        print(
            f"pycocotools      median {ref_med:.2f} s  ({1e3 * ref_med / args.frames:.2f} ms/frame)"
        )
        print(f"speed-up over pycocotools: {ref_med / med:.1f}x (AP equal to 1e-6)")
    pq_med = statistics.median(pq_t)
    print(f"panoptic_quality median {pq_med:.2f} s  ({1e3 * pq_med / args.frames:.2f} ms/frame)")

    t_add, t_compute, _ = bench_evaluator(
        rng, args.eval_frames, h, w, args.queries, args.objects, args.eval_batch
    )
    per = 1e3 * (t_add + t_compute)
    print(
        f"Evaluator from logits ({args.eval_frames} frames, batch {args.eval_batch}): add "
        f"{1e3 * t_add:.1f} ms/frame (median over batches) + compute {1e3 * t_compute:.2f} "
        f"ms/frame = {per:.1f} ms/frame -> {per:.0f} s per 1000 frames"
    )


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "bench_metrics.py")  # Ctrl-C: one line and status 130
