"""Evaluate a model on simulated held-out frames: ``python experiments/eval_sim.py --model M``.

The frames come from the simulator's ``test`` split (layout plans ``sim.test_layouts`` and
object variants ``sim.test_variants``, never drawn for train or val) under a root key that
training never uses: training draws ``fold_in(key(train.seed), 0)`` for its batches and
``fold_in(key(train.seed), 1)`` for validation, this script ``key(--seed)`` with a seed far
from the training seeds. Batch k of the set is ``generate_batch(fold_in(key(seed), k))``,
so the set is the same on every run and machine (up to float rounding of the simulator) for
one ``--batch`` (frame i of batch k is keyed by ``fold_in(fold_in(key(seed), k), i)``).

``--split val`` draws the training plans and variants (there are no val-only layouts) under
its own root seed, ``VAL_SEED``, so that choices made on it (thresholds, views, which model
to ship) are not made on frames paired with the test set's: with one root, val frame i and
test frame i shared the layout kind, the sensor noise and most object draws.

Prints the per-class table and the class confusion at mask IoU 0.5 (which class each object
was detected as, or missed; ``metrics.class_confusion``), then the same counts per object
variant (``Class/variant``, held-out variants marked ``*``), so a held-out shape's errors are
not mistaken for its class's, and the objects found and missed by their number of lidar
points, their KITTI occlusion level, their distance from the sensor and their footprint size
(``BREAKDOWNS``), so a miss rate can be put down to the data or to the model; writes all of
it as JSON (``--json``).

Threshold sweeps: ``--score-threshold`` and ``--mask-threshold`` take comma lists; every
combination is scored on the same frames in one pass (one simulation and one network
forward per batch), and a line of means per combination is printed instead of the tables
(``--tables``: and each combination's tables; the JSON holds each combination's full report
under ``"sweep"``). Pick thresholds on
``--split val``, then store them with ``export_model.py``.

Test-time views: ``--views all`` (or a comma list of ``config.VIEWS`` names) runs the model on the
mirrored and rotated clouds and fuses the outputs (``inference.apply_views``); the default
is the model file's ``inference.views``.
A mount other than the trained one: ``--sensor-height`` simulates the lidar at other heights
(``--z-offset`` then moves the cloud as predict's ``--lidar-height`` does) and ``--lidar-rpy``
simulates it tilted (``sim.sensor_rpy``, one tilt for every frame): the model sees the tilted
lidar's returns levelled, as predict's ``--lidar-rpy`` feeds them. ``--tilt-jitter`` tilts each
scene's lidar by up to that many degrees more (``sim.sensor_tilt_jitter``).

The numbers are measured on simulated data: they are not the paper's real-world measurement.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import sys
import time

import jax
import numpy as np

from indoorbev_jax.checks import check_out_file, write_json
from indoorbev_jax.cli import (
    HelpFormatter,
    add_views_argument,
    join_negative_values,
    positive_int,
    rpy_argument,
    seed_int,
)
from indoorbev_jax.config import ConfigError, InferenceConfig
from indoorbev_jax.evaluate import report
from indoorbev_jax.geometry import in_workspace
from indoorbev_jax.metrics import Evaluator, format_percent
from indoorbev_jax.mount import LidarMount
from indoorbev_jax.predict import load_model

TEST_SEED = 1_000_003  # root seed of the held-out test set (training uses train.seed, 0)
VAL_SEED = 1_000_033  # root seed of --split val (before 2026-12-05 it was TEST_SEED too)
POINT_EDGES = (10, 30, 100, 300)  # lidar returns on the object
RANGE_EDGES = (2.0, 3.0, 4.0, 5.0)  # metres from the sensor to the box centre, in the BEV plane
AREA_EDGES = (10, 25, 50, 100)  # grid cells of the footprint mask
OCCLUSION_NAMES = ("0 (>=75% seen)", "1 (40-75%)", "2 (<40%)", "3 (no primitive seen)")


def default_seed(split: str) -> int:
    """The root seed ``--split`` uses when ``--seed`` is not given."""
    return {"test": TEST_SEED, "val": VAL_SEED}[split]


def _interval_names(edges, unit: str) -> tuple[str, ...]:
    """Row names of ``np.digitize(x, edges)``: ``<a``, ``[a, b)``, ..., ``>=z``."""
    inner = [f"[{a:g}, {b:g}){unit}" for a, b in itertools.pairwise(edges)]
    return (f"<{edges[0]:g}{unit}", *inner, f">={edges[-1]:g}{unit}")


# (gt_tags grouping, row names, heading) of the found/missed tables eval_sim prints.
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


def evaluate_sim(config, params, split: str, frames: int, batch: int, seed: int, progress=True):
    """An ``Evaluator`` holding ``params``' outputs on ``frames`` simulated frames of ``split``.

    The targets are tagged with ``frame_tags`` (``Evaluator.tag_confusion(..., grouping=)``):
    ``"variant"`` is the ``indoorbev_sim.objects.ALL_VARIANTS`` index.
    """
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

    if frames % batch:
        raise ValueError(f"--frames {frames} must be a multiple of --batch {batch}")
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


def _thresholds(text: str) -> tuple[float, ...]:
    """argparse type: one threshold or a comma list."""
    try:
        return tuple(float(t) for t in text.split(","))
    except ValueError:
        msg = f"expected numbers separated by commas, got {text!r}"
        raise argparse.ArgumentTypeError(msg) from None


def sweep_table(rows: list[tuple[InferenceConfig, dict]]) -> str:
    """One line of means (in %) per inference setting of a sweep, from ``report``'s JSON dicts."""
    head = ["score", "mask", "AP@0.25", "AP@0.50", "PQ", "SQ", "RQ", "mIoU", "semIoU"]
    lines = [" ".join(f"{h:>8}" for h in head)]
    for inference, r in rows:
        values = [r["ap"]["0.25"], r["ap"]["0.5"], r["pq"], r["sq"], r["rq"], r["miou"],
                  r["semantic_miou"]]  # fmt: skip
        lines.append(
            f"{inference.score_threshold:>8g} {inference.mask_threshold:>8g} "
            + " ".join(f"{format_percent(v):>8}" for v in values)
        )
    return "\n".join(lines)


def add_frame_set_arguments(p: argparse.ArgumentParser) -> None:
    """``--model`` and the simulated frames to score it on: ``--split``, ``--frames``,
    ``--batch``, ``--seed`` (shared with ``pose_errors.py``, so both see the same frames)."""
    p.add_argument("--model", required=True, help="run directory or exported model file")
    p.add_argument(
        "--split",
        default="test",
        choices=("test", "val"),
        help="test: the held-out layouts and variants; val: the training ones under another "
        "root seed (pick thresholds and views on it)",
    )
    p.add_argument(
        "--frames", type=positive_int, default=512, help="frames to score, a multiple of --batch"
    )
    p.add_argument(
        "--batch",
        type=positive_int,
        default=8,
        help="frames simulated and run per call; the frames drawn depend on it",
    )
    seeds = f"{TEST_SEED} for test, {VAL_SEED} for val"
    p.add_argument("--seed", type=seed_int, default=None, help=f"root seed (default: {seeds})")


def check_frame_set(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuses (one line, status 2) ``--frames`` that ``--batch`` does not divide, and a
    ``--json`` path that cannot be written (found now, not after the evaluation)."""
    if args.frames % args.batch:
        p.error(f"--frames {args.frames} must be a multiple of --batch {args.batch}")
    if args.json is not None:
        try:
            check_out_file("--json", args.json)
        except (OSError, ValueError) as e:
            p.error(str(e))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    add_frame_set_arguments(p)
    p.add_argument("--json", default=None, help="write the metrics here")
    p.add_argument(
        "--score-threshold",
        type=_thresholds,
        default=None,
        help="inference.score_threshold, or a comma list to sweep (default: the model's)",
    )
    p.add_argument(
        "--mask-threshold",
        type=_thresholds,
        default=None,
        help="inference.mask_threshold, or a comma list to sweep (default: the model's)",
    )
    p.add_argument(
        "--tables",
        action="store_true",
        help="with a sweep, also print every setting's tables (default: the means only)",
    )
    p.add_argument(
        "--intensity-factor",
        type=float,
        default=1.0,
        help="multiply the simulated intensity by this (150: a Livox driver's units fed raw; "
        "0: a sensor without intensity)",
    )
    p.add_argument(
        "--sensor-height",
        type=_thresholds,
        default=None,
        help="simulate the lidar this high above the floor, metres: one value or MIN,MAX "
        "(default: the model's sim.sensor_height)",
    )
    p.add_argument(
        "--z-offset",
        type=float,
        default=0.0,
        help="add this to every point's z before the model sees it, metres (what predict's "
        "--lidar-height does for a sensor outside the trained heights)",
    )
    p.add_argument(
        "--lidar-rpy",
        type=rpy_argument,
        default=None,
        metavar="ROLL,PITCH,YAW",
        help="simulate the lidar tilted, degrees in the level frame (URDF rpy: pitch 20 is "
        "nose down); the model gets the cloud levelled, as predict's --lidar-rpy gives it "
        "(default: the model's sim.sensor_rpy)",
    )
    p.add_argument(
        "--tilt-jitter",
        type=float,
        default=None,
        metavar="DEGREES",
        help="tilt each scene's lidar by up to this much more, degrees (sim.sensor_tilt_jitter; "
        "default: 0 with --lidar-rpy, else the model's)",
    )
    add_views_argument(p, "the model's")
    p.add_argument(
        "--view-iou", type=float, default=None, help="inference.view_iou (default: the model's)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = p.parse_args(join_negative_values(argv))
    check_frame_set(p, args)
    if not 0 <= args.intensity_factor < math.inf:  # as predict's intensity_factor
        p.error(f"--intensity-factor: expected a finite number >= 0, got {args.intensity_factor}")
    if args.seed is None:
        args.seed = default_seed(args.split)
    try:
        config, params = load_model(args.model)
    except (OSError, ValueError) as e:
        p.exit(2, f"eval_sim: {e}\n")
    if args.sensor_height is not None:
        heights = args.sensor_height * 2 if len(args.sensor_height) == 1 else args.sensor_height
        if len(heights) != 2:
            p.error(f"--sensor-height: expected HEIGHT or MIN,MAX, got {len(heights)} values")
        try:
            sim = dataclasses.replace(config.sim, sensor_height=heights)
            from indoorbev_sim.scenes import check_sensor_height

            check_sensor_height(sim)  # a ceiling too low: said here, not as a traceback
        except (ConfigError, ValueError) as e:
            p.error(f"--sensor-height: {e}")
        config = dataclasses.replace(config, sim=sim)
    if args.lidar_rpy is not None or args.tilt_jitter is not None:
        tilt = {"sensor_tilt_jitter": 0.0 if args.tilt_jitter is None else args.tilt_jitter}
        if args.lidar_rpy is not None:
            tilt["sensor_rpy"] = args.lidar_rpy
        try:
            sim = dataclasses.replace(config.sim, **tilt)
        except ConfigError as e:
            p.error(f"--tilt-jitter: {e}")
        config = dataclasses.replace(config, sim=sim)
    if args.lidar_rpy is not None:
        if hint := LidarMount(*args.lidar_rpy).radians_hint():
            print(f"note: {hint}", file=sys.stderr)
    scores = args.score_threshold or (config.inference.score_threshold,)
    masks = args.mask_threshold or (config.inference.mask_threshold,)
    views = {"views": args.views, "view_iou": args.view_iou}
    views = {k: v for k, v in views.items() if v is not None}
    inferences = []
    for score, mask in itertools.product(scores, masks):
        try:  # InferenceConfig checks the range, Config the views against the grid
            inference = dataclasses.replace(
                config.inference, score_threshold=score, mask_threshold=mask, **views
            )
            inferences.append(dataclasses.replace(config, inference=inference).inference)
        except ConfigError as e:
            p.error(str(e))
    from indoorbev_sim.scenes import held_out_note

    if args.split == "test" and (note := held_out_note(config.sim)):
        print(note, file=sys.stderr)
    start = time.perf_counter()
    evaluators = evaluate_sim_sweep(
        config, params, args.split, args.frames, args.batch, args.seed, inferences,
        not args.no_progress, args.intensity_factor, args.z_offset,
    )  # fmt: skip
    from indoorbev_sim.objects import ALL_VARIANTS

    held_out = set(config.sim.test_variants)
    names = [f"{v}*" if v in held_out else v for v in ALL_VARIANTS]
    title = "per object variant (* held out of train and val)"
    setup = {"model": str(args.model), "split": args.split, "frames": args.frames,
             "batch": args.batch, "seed": args.seed, "intensity_factor": args.intensity_factor,
             "sensor_height": list(config.sim.sensor_height), "z_offset": args.z_offset,
             "sensor_rpy": list(config.sim.sensor_rpy),
             "sensor_tilt_jitter": config.sim.sensor_tilt_jitter,
             "views": list(inferences[0].views), "view_iou": inferences[0].view_iou}  # fmt: skip
    sweep = []
    for inference, evaluator in zip(inferences, evaluators, strict=True):
        text, payload = report(
            evaluator, config.data.class_names, names, title, tag_grouping="variant",
            breakdowns=BREAKDOWNS,
        )  # fmt: skip
        setting = {"score_threshold": inference.score_threshold,
                   "mask_threshold": inference.mask_threshold}  # fmt: skip
        sweep.append((inference, text, {**setting, **payload}))
    # The batch is part of the frame set (B scenes of frames / B frames each), as the seed is.
    head = f"model {args.model} (preset {config.name}), {args.frames} simulated '{args.split}' " \
        f"frames, batch {args.batch}, seed {args.seed}"  # fmt: skip
    if args.intensity_factor != 1.0:
        head += f", intensity x {args.intensity_factor:g}"
    if args.sensor_height is not None:
        head += ", sensor height {:g}-{:g} m".format(*config.sim.sensor_height)
    if args.z_offset:
        head += f", z {args.z_offset:+g} m"
    if any(config.sim.sensor_rpy):
        head += ", lidar tilted roll {:g}, pitch {:g}, yaw {:g} deg".format(*config.sim.sensor_rpy)
    if config.sim.sensor_tilt_jitter:
        head += f", lidar tilt jittered by up to {config.sim.sensor_tilt_jitter:g} deg"
    if inferences[0].views != ("identity",):
        head += f", {len(inferences[0].views)} views fused at IoU {inferences[0].view_iou:g}"
    seconds = f"{time.perf_counter() - start:.0f} s"
    if len(sweep) == 1:
        inference, text, payload = sweep[0]
        print(f"{head}, score threshold {inference.score_threshold}, mask threshold "
              f"{inference.mask_threshold}, {seconds}")  # fmt: skip
        print(text)
        payload = {**payload, "setup": {**setup, "score_threshold": inference.score_threshold,
                                        "mask_threshold": inference.mask_threshold}}  # fmt: skip
    else:
        print(f"{head}, {len(sweep)} threshold settings, {seconds}")
        print(sweep_table([(inference, entry) for inference, _, entry in sweep]))
        for inference, text, _ in sweep if args.tables else ():
            print(f"\nscore threshold {inference.score_threshold}, mask threshold "
                  f"{inference.mask_threshold}:\n{text}")  # fmt: skip
        payload = {"setup": setup, "sweep": [entry for _, _, entry in sweep]}
    if args.json:
        write_json(args.json, payload)
        print(f"metrics written to {args.json}")


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "eval_sim.py")  # Ctrl-C: one line and status 130
