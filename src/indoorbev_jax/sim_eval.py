"""Scoring a model on the simulator's held-out frames: the frame sets ``eval_sim.py`` uses.

The test set comes from the simulator's ``test`` split (layout plans ``sim.test_layouts``
and object variants ``sim.test_variants``, never drawn for train or val) under a root key
that training never uses: training draws ``fold_in(key(train.seed), 0)`` for its batches
and ``fold_in(key(train.seed), 1)`` for validation, the test set ``key(TEST_SEED)``, a seed
far from the training seeds. Batch k of a set is ``generate_batch(fold_in(key(seed), k))``,
so the set is the same on every run and machine (up to float rounding of the simulator)
for one ``batch`` (frame i of batch k is keyed by ``fold_in(fold_in(key(seed), k), i)``).

The ``val`` split draws the training plans and variants (there are no val-only layouts)
under its own root seed, ``VAL_SEED``, so that choices made on it (thresholds, views, which
model to ship) are not made on frames paired with the test set's.

    config, params = predict.load_model("models/indoorbev_small.msgpack")
    evaluator = sim_eval.evaluate_sim(config, params, "test", frames=64, batch=8,
                                      seed=sim_eval.TEST_SEED)
    print(evaluator.table())

The numbers are measured on simulated data: they are not the paper's real-world measurement.
"""

from __future__ import annotations

import dataclasses
import itertools

import jax
import numpy as np

from indoorbev_jax.checks import check_seed, check_whole
from indoorbev_jax.config import InferenceConfig
from indoorbev_jax.geometry import in_workspace
from indoorbev_jax.metrics import Evaluator

TEST_SEED = 1_000_003  # root seed of the held-out test set (training uses train.seed, 0)
VAL_SEED = 1_000_033  # root seed of the val frames (before 2026-12-05 it was TEST_SEED too)
POINT_EDGES = (10, 30, 100, 300)  # lidar returns on the object
RANGE_EDGES = (2.0, 3.0, 4.0, 5.0)  # metres from the sensor to the box centre, in the BEV plane
AREA_EDGES = (10, 25, 50, 100)  # grid cells of the footprint mask
OCCLUSION_NAMES = ("0 (>=75% seen)", "1 (40-75%)", "2 (<40%)", "3 (no primitive seen)")


def default_seed(split: str) -> int:
    """The root seed of ``split``'s frame set: ``TEST_SEED`` or ``VAL_SEED``."""
    seeds = {"test": TEST_SEED, "val": VAL_SEED}
    if split not in seeds:
        raise ValueError(
            f"split: expected 'test' or 'val' (the sets with a root seed), got {split!r}"
        )
    return seeds[split]


def _interval_names(edges, unit: str) -> tuple[str, ...]:
    """Row names of ``np.digitize(x, edges)``: ``<a``, ``[a, b)``, ..., ``>=z``."""
    inner = [f"[{a:g}, {b:g}){unit}" for a, b in itertools.pairwise(edges)]
    return (f"<{edges[0]:g}{unit}", *inner, f">={edges[-1]:g}{unit}")


# (gt_tags grouping, row names, heading) of the found/missed tables (``evaluate.report``).
BREAKDOWNS = (
    ("points", _interval_names(POINT_EDGES, ""), "by lidar points on the object"),
    ("occlusion", OCCLUSION_NAMES, "by KITTI occlusion level (share of primitives seen)"),
    ("range", _interval_names(RANGE_EDGES, " m"), "by distance from the sensor"),
    ("area", _interval_names(AREA_EDGES, " cells"), "by footprint size on the grid"),
)


def frame_tags(targets, info) -> dict[str, np.ndarray]:
    """``gt_tags`` groupings of B simulated frames: ``"variant"`` and each of ``BREAKDOWNS``."""
    from indoorbev_sim.objects import variant_ids

    pos = np.asarray(targets.pos)
    return {
        "variant": np.asarray(variant_ids(targets.classes, info.variant)),
        "points": np.digitize(np.asarray(info.num_points), POINT_EDGES),
        "occlusion": np.asarray(info.occlusion),
        "range": np.digitize(np.hypot(pos[..., 0], pos[..., 1]), RANGE_EDGES),
        "area": np.digitize(np.asarray(targets.masks).sum((-2, -1)), AREA_EDGES),
    }


def model_input(points, valid, grid, intensity_factor: float = 1.0, z_offset: float = 0.0):
    """Simulated ``points [..., N, 4]`` and ``valid [..., N]`` as the model sees them: the
    intensity times ``intensity_factor``, z moved by ``z_offset`` (what ``predict``'s
    ``--lidar-height`` does) and the points it moves out of the workspace left out."""
    points = points.at[..., 3].multiply(intensity_factor).at[..., 2].add(z_offset)
    return points, valid & in_workspace(points, grid)


def evaluate_sim(
    config, params, split: str, frames: int, batch: int, seed: int | None = None, progress=True
):
    """An ``Evaluator`` holding ``params``' outputs on ``frames`` simulated frames of ``split``
    ("test", "val" or "train"), drawn ``batch`` at a time from root ``seed`` (default:
    ``default_seed(split)``); the frames drawn depend on ``batch`` and ``seed``.

    The targets are tagged with ``frame_tags`` (``Evaluator.tag_confusion(..., grouping=)``):
    ``"variant"`` is the ``indoorbev_sim.objects.ALL_VARIANTS`` index.
    """
    seed = default_seed(split) if seed is None else seed
    return evaluate_sim_sweep(
        config, params, split, frames, batch, seed, [config.inference], progress
    )[0]


def evaluate_sim_sweep(
    config,
    params,
    split: str,
    frames: int,
    batch: int,
    seed: int,
    inferences,
    progress=True,
    intensity_factor: float = 1.0,
    z_offset: float = 0.0,
) -> list[Evaluator]:
    """``evaluate_sim`` for several inference settings on the same frames, in one pass.

    Args:
      inferences: ``InferenceConfig`` per evaluator (``config.inference`` is not used); they
        must share ``views`` and ``view_iou``. The model runs once per batch; with several
        views its outputs are fused once per distinct ``mask_threshold`` (fusion binarises
        the masks at it), so each row sees the views fused as it would alone.
      intensity_factor: the simulated intensity is multiplied by this before the model sees
        it (1: as simulated), to measure what other intensity units do to the model.
      z_offset: metres added to every point's z before the model sees it (0: as simulated),
        to measure a sensor height the model was not trained on and its correction
        (``predict``'s ``--lidar-height``). The targets are footprints, which z leaves alone.

    Returns:
      One ``Evaluator`` per entry of ``inferences``, each equal to ``evaluate_sim`` with
      that ``config.inference``.
    """
    from indoorbev_sim.generate import jitted_generate
    from tqdm import tqdm

    from indoorbev_jax.inference import forward_views, fuse_views, panoptic_inference
    from indoorbev_jax.models import IndoorBEV

    frames, batch = check_whole("frames", frames, 1), check_whole("batch", batch, 1)
    if frames % batch:
        raise ValueError(f"frames {frames} must be a multiple of batch {batch}")
    seed = check_seed("seed", seed)
    inferences = tuple(inferences)
    if len({(i.views, i.view_iou) for i in inferences}) > 1:
        raise ValueError("inferences: every setting of a sweep must share views and view_iou")
    # The simulation does not read the thresholds: one compiled generator for all of them.
    sim_config = dataclasses.replace(config, inference=InferenceConfig())
    generate = jitted_generate(sim_config, split, batch)
    model = IndoorBEV(config)

    @jax.jit
    def predict(params, points, valid):
        points, valid = model_input(points, valid, config.grid, intensity_factor, z_offset)
        views, view_iou = inferences[0].views, inferences[0].view_iou
        out = forward_views(model, params, points, valid, views)
        fused = {}  # mask_threshold -> predictions
        for m in {i.mask_threshold for i in inferences}:
            fused[m] = out if views == ("identity",) else fuse_views(out, m, view_iou)
        return tuple(panoptic_inference(fused[i.mask_threshold], i) for i in inferences)

    names = config.data.class_names
    evaluators = [Evaluator(inference, class_names=names) for inference in inferences]
    root = jax.random.key(seed)
    for k in tqdm(range(frames // batch), disable=not progress, unit="batch"):
        data, info = generate(jax.random.fold_in(root, k))
        tags = frame_tags(data.targets, info)
        outputs = predict(params, data.points, data.point_valid)
        for evaluator, output in zip(evaluators, outputs, strict=True):
            evaluator.add_output(output, data.targets, gt_tags=tags)
    return evaluators
