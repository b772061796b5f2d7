"""Pose errors of the boxes a model outputs: ``python experiments/pose_errors.py --model M``.

The metrics of ``eval_sim.py`` (DESIGN 9) score footprint masks only; the boxes a robot
reads from ``label_2`` (centre, size, yaw) are scored nowhere else. This script simulates
the same frames as ``eval_sim.py`` (same split, seed, ``--batch`` and views), pairs each
output object (a segment of the panoptic map) with the ground truth of its class whose
footprint mask overlaps its binarised mask at IoU > ``--match-iou`` (unique, like PQ's
matching), and prints per class the medians of:

  * ``centre``: BEV distance from the regressed box centre to the true one (m), and
    ``fit c.`` from the centre of the rectangle around the largest piece of the output's
    segment (``boxes.segment_boxes``, what ``--boxes mask`` outputs); ``gt c.`` is the
    true footprint's
    centroid's distance from the true centre, not zero where a shape is not its box (an
    L-shaped sofa) or the grid edge cuts it;
  * ``IoU``, ``fit IoU``: rotated-box IoU in the ground plane (shapely) of the regressed
    and of the fitted box with the true box;
  * ``yaw``, ``fit yaw``: the angle between the box's sides and the true box's, in degrees
    (modulo 90: a fitted rectangle has no front, and a table's front and side are alike to
    a mask); uniform guessing would give a median of 22.5;
  * ``size``, ``fit size``: mean absolute error of length and width (m) of the regressed
    and of the fitted box (the longer side against the true box's longer side), ``h``: of
    the regressed height, ``z``: of the regressed centre height; the fitted box keeps h and
    z from the head.

A last row, ``all p90``, gives the 90th percentiles over every matched object.

The numbers are measured on simulated data, like every figure of ``eval_sim.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_sim import add_frame_set_arguments, check_frame_set, default_seed  # noqa: E402

from indoorbev_jax.boxes import fit_box, segment_boxes  # noqa: E402
from indoorbev_jax.checks import write_json  # noqa: E402
from indoorbev_jax.cli import HelpFormatter, add_views_argument  # noqa: E402
from indoorbev_jax.config import ConfigError  # noqa: E402
from indoorbev_jax.geometry import box_corners, cell_centers, wrap_angle  # noqa: E402
from indoorbev_jax.metrics import mask_intersections  # noqa: E402
from indoorbev_jax.predict import load_model, with_thresholds  # noqa: E402

COLUMNS = (
    "centre",
    "fit c.",
    "gt c.",
    "IoU",
    "fit IoU",
    "yaw",
    "fit yaw",
    "size",
    "fit size",
    "h",
    "z",
)


def box_polygon(x: float, y: float, length: float, width: float, yaw: float):
    """The BEV rectangle of a box (length along its heading) as a shapely polygon."""
    from shapely.geometry import Polygon

    return Polygon(box_corners(np.array([[x, y]]), np.array([[length, width]]), np.array([yaw]))[0])


def box_iou(a, b) -> float:
    """BEV IoU of two boxes given as (x, y, length, width, yaw)."""
    pa, pb = box_polygon(*a), box_polygon(*b)
    inter = pa.intersection(pb).area
    union = pa.area + pb.area - inter
    return float(inter / union) if union > 0 else 0.0


def mask_centroids(masks: np.ndarray, grid) -> np.ndarray:
    """float64 [K, 2]: (x, y) mean of the cell centres of each non-empty mask [K, H, W]."""
    xs, ys = (np.asarray(c, np.float64) for c in cell_centers(grid))
    area = masks.sum((1, 2)).astype(np.float64)
    cx = (masks.sum(1) * xs).sum(1) / area
    cy = (masks.sum(2) * ys).sum(1) / area
    return np.stack([cx, cy], 1)


def match_frame(det_masks, det_classes, gt_masks, gt_classes, match_iou: float):
    """Unique pairs (d, g) of the same class with mask IoU > ``match_iou`` (>= 0.5 makes
    each pair unique, as in PQ); returns int arrays (d, g)."""
    inter, area_d, area_g = mask_intersections(det_masks, gt_masks)
    union = area_d[:, None] + area_g[None] - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
    iou = np.where(det_classes[:, None] == gt_classes[None], iou, 0.0)
    pairs, used_d, used_g = [], set(), set()
    for k in np.argsort(-iou, axis=None, kind="stable"):
        i, j = np.unravel_index(k, iou.shape)
        if iou[i, j] <= match_iou:
            break
        if i not in used_d and j not in used_g:
            pairs.append((i, j))
            used_d.add(i)
            used_g.add(j)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    return pairs[:, 0], pairs[:, 1]


def frame_errors(
    final, output, targets, grid, match_iou: float, fit_to: str = "segment"
) -> dict[str, np.ndarray]:
    """Per matched object of one frame (numpy, batch axis removed): its class and errors."""
    keep = np.flatnonzero(output.segment_valid)
    valid = np.flatnonzero(targets.valid)
    det_masks = output.det_masks[keep]
    d, g = match_frame(
        det_masks, output.det_classes[keep], targets.masks[valid], targets.classes[valid],
        match_iou,
    )  # fmt: skip
    q, t = keep[d], valid[g]
    pos, dims, yaw = final.pos[q], np.abs(final.dims[q]), final.yaw[q, 0]
    gpos, gdims, gyaw = targets.pos[t], targets.dims[t], targets.yaw[t]
    if fit_to == "segment":  # what --boxes mask writes
        fits = segment_boxes(output.instance_ids, q + 1, grid)
    else:  # the whole binarised mask, specks and all
        fits = np.array([fit_box(m, grid) for m in output.det_masks[q]]).reshape(-1, 5)
    gc = mask_centroids(targets.masks[t], grid)
    boxes = np.concatenate([pos[:, :2], dims[:, :2], yaw[:, None]], 1)
    gboxes = np.concatenate([gpos[:, :2], gdims[:, :2], gyaw[:, None]], 1)

    def heading_error(a, b):  # degrees between two rectangles' sides: modulo 90
        return np.degrees(np.abs(np.asarray(wrap_angle(4 * (a - b))) / 4))

    return {
        "class": targets.classes[t],
        "centre": np.hypot(*(pos[:, :2] - gpos[:, :2]).T),
        "fit c.": np.hypot(*(fits[:, :2] - gpos[:, :2]).T),
        "gt c.": np.hypot(*(gc - gpos[:, :2]).T),
        "IoU": np.array([box_iou(a, b) for a, b in zip(boxes, gboxes, strict=True)]),
        "fit IoU": np.array([box_iou(a, b) for a, b in zip(fits, gboxes, strict=True)]),
        "yaw": heading_error(yaw, gyaw),
        "fit yaw": heading_error(fits[:, 4], gyaw),
        "size": np.abs(np.sort(dims[:, :2], 1) - np.sort(gdims[:, :2], 1)).mean(1),
        "fit size": np.abs(np.sort(fits[:, 2:4], 1) - np.sort(gdims[:, :2], 1)).mean(1),
        "h": np.abs(dims[:, 2] - gdims[:, 2]),
        "z": np.abs(pos[:, 2] - gpos[:, 2]),
    }


def pose_errors(
    config, params, split, frames, batch, seed, match_iou=0.5, progress=True, fit_to="segment"
):
    """Errors of every matched object over ``frames`` simulated frames (``eval_sim``'s)."""
    from indoorbev_sim.generate import jitted_generate
    from tqdm import tqdm

    from indoorbev_jax.config import InferenceConfig
    from indoorbev_jax.inference import apply_views, panoptic_inference
    from indoorbev_jax.models import IndoorBEV

    if frames % batch:
        raise ValueError(f"--frames {frames} must be a multiple of --batch {batch}")
    generate = jitted_generate(dataclasses.replace(config, inference=InferenceConfig()), split,
                               batch)  # fmt: skip
    model = IndoorBEV(config)

    @jax.jit
    def predict(params, points, valid):
        predictions = apply_views(model, params, points, valid, config.inference)
        output = panoptic_inference(predictions, config.inference)
        return jax.tree.map(lambda x: x[-1], predictions), output

    rows: list[dict[str, np.ndarray]] = []
    root = jax.random.key(seed)
    for k in tqdm(range(frames // batch), disable=not progress, unit="batch"):
        data, _ = generate(jax.random.fold_in(root, k))
        final, output = jax.device_get(predict(params, data.points, data.point_valid))
        targets = jax.device_get(data.targets)
        for i in range(batch):
            one = lambda tree, i=i: jax.tree.map(lambda x: np.asarray(x[i]), tree)  # noqa: E731
            rows.append(frame_errors(one(final), one(output), one(targets), config.grid,
                                     match_iou, fit_to))  # fmt: skip
    return {key: np.concatenate([r[key] for r in rows]) for key in rows[0]}


def summary(errors: dict[str, np.ndarray], class_names) -> dict:
    """Medians of every column per class (and ``all``), with the matched counts."""
    out = {}
    for c, name in [*enumerate(class_names), (None, "all")]:
        sel = np.ones(len(errors["class"]), bool) if c is None else errors["class"] == c
        if sel.any():
            out[name] = {"matched": int(sel.sum())}
            out[name].update({k: float(np.median(errors[k][sel])) for k in COLUMNS})
    if len(errors["class"]):
        out["all p90"] = {"matched": len(errors["class"])}
        out["all p90"].update({k: float(np.percentile(errors[k], 90)) for k in COLUMNS})
    return out


def format_summary(table: dict) -> str:
    head = f"{'class':<10}{'matched':>8}" + "".join(f"{c:>10}" for c in COLUMNS)
    lines = [head]
    for name, row in table.items():
        lines.append(
            f"{name:<10}{row['matched']:>8}"
            + "".join(
                f"{row[c]:>10.1f}" if "yaw" in c else f"{row[c]:>10.3f}" for c in COLUMNS
            )  # fmt: skip
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    add_frame_set_arguments(p)
    p.add_argument("--match-iou", type=float, default=0.5, help="mask IoU a pair exceeds")
    p.add_argument("--json", default=None, help="write the medians here")
    p.add_argument(
        "--fit-to",
        default="segment",
        choices=("segment", "mask"),
        help="fit the boxes to the largest piece of each object's segment (what --boxes mask "
        "writes) or to its whole binarised mask",
    )
    add_views_argument(p, "the model's")
    args = p.parse_args(argv)
    if not 0.5 <= args.match_iou < 1.0:
        p.error(f"--match-iou must lie in [0.5, 1) for unique pairs, got {args.match_iou}")
    check_frame_set(p, args)
    try:
        config, params = load_model(args.model)
        config = with_thresholds(config, views=args.views)
    except (OSError, ValueError, ConfigError) as e:
        p.error(str(e))
    seed = default_seed(args.split) if args.seed is None else args.seed
    errors = pose_errors(config, params, args.split, args.frames, args.batch, seed,
                         args.match_iou, fit_to=args.fit_to)  # fmt: skip
    table = summary(errors, config.data.class_names)
    print(f"{args.frames} {args.split} frames (seed {seed}, batch {args.batch}, views "
          f"{len(config.inference.views)}); medians of the objects matched at mask IoU > "
          f"{args.match_iou:g}; distances and sizes in m, angles in degrees (mod 90)")  # fmt: skip
    print(format_summary(table))
    if args.json:
        write_json(args.json, table, indent=1)


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "pose_errors.py")  # Ctrl-C: one line and status 130
