"""Train IndoorBEV: ``python experiments/train.py --preset small --workdir runs/small``.

Rerunning the same command after a kill resumes from the latest checkpoint. Without
``--data`` the batches come from the on-device simulator; with it, from a KITTI-style
folder holding ``train.txt`` and ``val.txt``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging

from indoorbev_jax.config import Config, ConfigError, with_overrides
from indoorbev_jax.train import train_and_evaluate


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="small", choices=("paper", "small", "tiny"))
    p.add_argument("--workdir", required=True, help="run directory (resumed when it exists)")
    p.add_argument("--data", default=None, help="KITTI-style folder (default: simulator)")
    p.add_argument("--steps", type=int, help="train.total_steps")
    p.add_argument("--batch-size", type=int, help="train.batch_size")
    p.add_argument("--learning-rate", type=float, help="train.learning_rate (peak)")
    p.add_argument("--warmup-steps", type=int, help="train.warmup_steps")
    p.add_argument("--eval-every", type=int, help="train.eval_every")
    p.add_argument("--checkpoint-every", type=int, help="train.checkpoint_every")
    p.add_argument("--seed", type=int, help="train.seed")
    p.add_argument("--no-augment", action="store_true", help="train.augment = False")
    p.add_argument("--bfloat16", action="store_true", help="bfloat16 compute (GPUs)")
    p.add_argument("--skip-bad-frames", action="store_true", help="skip malformed frames")
    p.add_argument("--no-progress", action="store_true")
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
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override any config field, VALUE checked against its type (repeatable), e.g. "
        "--set head.upsampler_skips=false --set augment.gt_sampling=4",
    )
    return p.parse_args(argv)


def config_from_args(args: argparse.Namespace) -> Config:
    config = Config.preset(args.preset)
    overrides = {
        "total_steps": args.steps,
        "batch_size": args.batch_size,
        "learning_rate": args.learning_rate,
        "warmup_steps": args.warmup_steps,
        "eval_every": args.eval_every,
        "checkpoint_every": args.checkpoint_every,
        "seed": args.seed,
    }
    train = {k: v for k, v in overrides.items() if v is not None}
    if args.no_augment:
        train["augment"] = False
    if args.bfloat16:
        train["bfloat16"] = True
    if "total_steps" in train and "warmup_steps" not in train:
        train["warmup_steps"] = min(config.train.warmup_steps, train["total_steps"])
    config = dataclasses.replace(config, train=dataclasses.replace(config.train, **train))
    try:
        return with_overrides(config, args.set)
    except ConfigError as e:
        raise SystemExit(f"--set: {e}") from None


def main(argv=None) -> None:
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
    train_and_evaluate(
        config_from_args(args),
        args.workdir,
        data=args.data,
        skip_bad_frames=args.skip_bad_frames,
        progress=not args.no_progress,
        init_from=args.init_from,
        init_strict=not args.init_partial,
    )


if __name__ == "__main__":
    main()
