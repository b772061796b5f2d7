"""Evaluate a model on simulated held-out frames: ``python experiments/eval_sim.py --model M``.

The frames are the held-out sets of ``indoorbev_jax.sim_eval`` (the Python API this script
wraps): ``--split test`` the held-out layouts and object variants under root seed
``TEST_SEED``, ``--split val`` the training ones under ``VAL_SEED``, so that choices made on
val (thresholds, views, which model to ship) are not made on frames paired with the test
set's. The frames drawn depend on ``--seed`` and ``--batch`` too.

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

from indoorbev_jax.checks import check_not_an_input, check_out_file, write_json
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
from indoorbev_jax.metrics import format_percent
from indoorbev_jax.mount import LidarMount
from indoorbev_jax.predict import load_model

# The library names pose_errors.py, split_pairing.py and the tests read from this script.
from indoorbev_jax.sim_eval import (  # noqa: F401
    BREAKDOWNS,
    TEST_SEED,
    VAL_SEED,
    default_seed,
    evaluate_sim,
    evaluate_sim_sweep,
    frame_tags,
    model_input,
)


def _thresholds(text: str) -> tuple[float, ...]:
    """argparse type: one threshold or a comma list."""
    try:
        return tuple(float(t) for t in text.split(","))
    except ValueError:
        msg = f"expected numbers separated by commas, got {text!r}"
        raise argparse.ArgumentTypeError(msg) from None


def _sweep(text: str) -> tuple[float, ...]:
    """argparse type of the threshold sweeps: ``_thresholds``, none repeated (a repeat was
    evaluated twice, a second identical row)."""
    values = _thresholds(text)
    if len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"{text!r} repeats a value")
    return values


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
            check_not_an_input("--json", args.json, [args.model])
        except (OSError, ValueError) as e:
            p.error(str(e))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    add_frame_set_arguments(p)
    p.add_argument("--json", default=None, help="write the metrics here")
    p.add_argument(
        "--score-threshold",
        type=_sweep,
        default=None,
        help="inference.score_threshold, or a comma list to sweep (default: the model's)",
    )
    p.add_argument(
        "--mask-threshold",
        type=_sweep,
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
    # A negative first value read as an option ("expected one argument"), not as the value
    # the range checks name.
    negative = ("--lidar-rpy", "--score-threshold", "--mask-threshold", "--sensor-height",
                "--z-offset")  # fmt: skip
    args = p.parse_args(join_negative_values(argv, flags=negative))
    check_frame_set(p, args)
    if not 0 <= args.intensity_factor < math.inf:  # as predict's intensity_factor
        p.error(f"--intensity-factor: expected a finite number >= 0, got {args.intensity_factor}")
    if not math.isfinite(args.z_offset):  # NaN: every object missed, exit 0
        p.error(f"--z-offset: expected a finite number of metres, got {args.z_offset}")
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
        try:  # a disk that filled up during the evaluation: the metrics are printed above
            write_json(args.json, payload)
        except OSError as e:
            sys.exit(f"eval_sim.py: error: {e} (the metrics are printed above)")
        print(f"metrics written to {args.json}")


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "eval_sim.py")  # Ctrl-C: one line and status 130
