"""Train IndoorBEV: ``python experiments/train.py --preset small --workdir runs/small``.

Rerunning the same command after a kill resumes from the latest checkpoint. Without
``--data`` the batches come from the on-device simulator; with it, from a KITTI-style
folder holding ``train.txt`` and ``val.txt``.
"""

from __future__ import annotations

import argparse
import logging
import sys

from indoorbev_jax.cli import (
    HelpFormatter,
    add_distributed_arguments,
    exit_with,
    start_distributed,
)
from indoorbev_jax.config import add_config_arguments, config_from_args
from indoorbev_jax.train import train_and_evaluate


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("--workdir", required=True, help="run directory (resumed when it exists)")
    p.add_argument("--data", default=None, help="KITTI-style folder (default: simulator)")
    add_config_arguments(p)
    p.add_argument("--skip-bad-frames", action="store_true", help="skip malformed frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--init-from",
        default=None,
        metavar="MODEL",
        help="start from a trained model's parameters (run directory or exported .msgpack); "
        "fresh optimizer state, ignored when the workdir resumes",
    )
    p.add_argument(
        "--init-partial",
        action="store_true",
        help="with --init-from: load the parameters that match by name and shape, keep fresh "
        "ones for the rest (e.g. --set head.upsampler_skips=false from a model with skips)",
    )
    add_distributed_arguments(p)
    return p.parse_args(argv)


def main(argv=None) -> int:
    # Our INFO lines only: an imported library already put a WARNING handler on the root
    # logger (basicConfig would do nothing), and orbax's INFO lines are noise here.
    ours = logging.getLogger("indoorbev_jax")
    if not ours.handlers:  # main() called again in one process adds no second handler
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        ours.addHandler(handler)
    ours.setLevel(logging.INFO)
    ours.propagate = False
    args = parse_args(argv)
    try:
        start_distributed(args, "train.py")  # before anything touches a device
        train_and_evaluate(
            config_from_args(args),
            args.workdir,
            data=args.data,
            skip_bad_frames=args.skip_bad_frames,
            progress=not args.no_progress,
            init_from=args.init_from,
            init_strict=not args.init_partial,
        )
    except (ValueError, OSError) as e:  # refusals and bad data: their message names the cause
        print(f"train.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    # Ctrl-C: one line and status 130, checkpoints closed; JAX_PLATFORMS checked after
    # --distributed joins (start_distributed).
    exit_with(main, "train.py", check_platforms=False)
