"""Train K configurations at once by vmapping the train step over learning rate and loss
weights: ``python experiments/sweep.py --preset small --workdir runs/sweep
--learning-rates 1e-4 2e-4 4e-4 --dice-weights 5 5 2``.

All K models see the same batches and augmentation keys; each has its own parameters,
optimizer state, peak learning rate and loss weights (traced arrays, ``train.Hyper``).
Rerunning the same command after a kill resumes from the latest checkpoint.
"""

from __future__ import annotations

import argparse
import sys

from indoorbev_jax.cli import (
    RawHelpFormatter,
    add_distributed_arguments,
    exit_with,
    start_distributed,
)
from indoorbev_jax.config import add_config_arguments, config_from_args
from indoorbev_jax.sweep import run_sweep, stack_hypers

# "seed" only with the seed head (--set head.query_init=select or head.semantic_head=true).
WEIGHTS = ("cls", "dice", "focal", "dims", "pos", "yaw", "background", "seed")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split(": ``")[0] + ".",  # its example command is the epilog
        epilog="example:\n  python experiments/sweep.py --preset small --workdir runs/sweep \\\n"
        "      --learning-rates 1e-4 2e-4 4e-4 --dice-weights 5 5 2\n\n" + __doc__.split("\n\n")[1],
        formatter_class=RawHelpFormatter,
    )
    p.add_argument("--workdir", required=True, help="sweep directory (resumed when it exists)")
    p.add_argument("--data", default=None, help="KITTI-style folder (default: simulator)")
    add_config_arguments(p, skip=("--learning-rate", "--eval-every"))
    p.add_argument("--learning-rates", type=float, nargs="+", required=True,
                   help="one peak learning rate per model (K values)")  # fmt: skip
    for name in WEIGHTS:
        p.add_argument(f"--{name}-weights", type=float, nargs="+", default=None,
                       help=f"K values of loss.{name} weight (default: the config's)")  # fmt: skip
    p.add_argument("--skip-bad-frames", action="store_true", help="skip malformed frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_distributed_arguments(p)
    args = p.parse_args(argv)
    if args.distributed:  # its state is unsharded: orbax refused the first checkpoint, steps lost
        p.error("--distributed: a sweep trains its K models in one process on one device; "
                "run it on one host (train.py runs on several)")  # fmt: skip
    try:
        start_distributed(args, "sweep.py")  # before anything touches a device
    except ValueError as e:
        p.error(str(e))
    config = config_from_args(args)
    overrides = {
        name: getattr(args, f"{name}_weights")
        for name in WEIGHTS
        if getattr(args, f"{name}_weights") is not None
    }
    try:
        hypers = stack_hypers(config, args.learning_rates, overrides)
    except ValueError as e:
        p.error(str(e))
    try:
        run_sweep(config, args.workdir, hypers, args.data, skip_bad_frames=args.skip_bad_frames,
                  progress=not args.no_progress)  # fmt: skip
    except (ValueError, OSError) as e:  # refusals and bad data: their message names the cause
        print(f"sweep.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    # Ctrl-C: one line and status 130; JAX_PLATFORMS checked after --distributed joins.
    exit_with(main, "sweep.py", check_platforms=False)
