"""Average models' parameters into one file: ``python experiments/average_models.py A B --out F``.

A uniform "model soup" of runs continued from one common model (``train.py --init-from``):
their average usually validates better than each, at no inference cost. Check it on the
validation split (``experiments/eval_sim.py --split val``) before shipping it. The config
(thresholds included) is the first model's unless set here, but for the lidar heights
(``sim.sensor_height``): the span of all the models' heights, and the tilt jitter
(``sim.sensor_tilt_jitter``): the largest of theirs. Models trained for different
lidar tilts (``sim.sensor_rpy``) need ``--sensor-rpy``, the tilt to record for the average
(a level and a tilted model average into one that does fairly at both: docs/RESULTS.md
"Lidar tilt").
"""

from __future__ import annotations

import argparse
import math

import jax

from indoorbev_jax.checks import check_not_an_input
from indoorbev_jax.cli import HelpFormatter, add_views_argument, join_negative_values, rpy_argument
from indoorbev_jax.config import ConfigError
from indoorbev_jax.predict import average_models, export_model, with_thresholds


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("models", nargs="+", help="model files or run directories (2 or more)")
    p.add_argument("--out", required=True, help="model file to write (.msgpack)")
    p.add_argument(
        "--score-threshold",
        type=float,
        default=None,
        help="inference.score_threshold stored in the file (default: the first model's)",
    )
    p.add_argument(
        "--mask-threshold",
        type=float,
        default=None,
        help="inference.mask_threshold stored in the file (default: the first model's)",
    )
    add_views_argument(p, "the first model's")
    p.add_argument(
        "--sensor-rpy",
        type=rpy_argument,
        default=None,
        metavar="ROLL,PITCH,YAW",
        help="sim.sensor_rpy to record, degrees: needed when the models were trained for "
        "different lidar tilts (default: their common one)",
    )
    args = p.parse_args(join_negative_values(argv, flags=("--sensor-rpy",)))
    try:
        check_not_an_input("--out", args.out, args.models)  # an input replaced, exit 0
        config, params = average_models(args.models, args.sensor_rpy)
        config = with_thresholds(config, args.score_threshold, args.mask_threshold, args.views)
    except (ValueError, FileNotFoundError, ConfigError) as e:
        p.error(str(e))
    try:
        path = export_model(params, config, args.out)
    except OSError as e:  # a folder, or a place that cannot be written: named, status 2
        p.exit(2, f"average_models: {e}\n")
    count = sum(math.prod(x.shape) for x in jax.tree.leaves(params))
    lo, hi = config.sim.sensor_height
    print(f"average of {len(args.models)} models ({count:,} parameters, score threshold "
          f"{config.inference.score_threshold}, mask threshold "
          f"{config.inference.mask_threshold}, lidar heights {lo:g}-{hi:g} m) -> {path} "
          f"({path.stat().st_size / 2**20:.1f} MiB)")  # fmt: skip


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "average_models.py")  # Ctrl-C: one line and status 130
