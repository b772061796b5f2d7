"""Train K configurations at once by vmapping the train step over learning rate and loss
weights: ``python experiments/sweep.py --preset small --workdir runs/sweep
--learning-rates 1e-4 2e-4 4e-4 --dice-weights 5 5 2``.

All K models see the same batches and augmentation keys; each has its own parameters,
optimizer state, peak learning rate and loss weights (traced arrays, ``train.Hyper``).
"""

from __future__ import annotations

import argparse
import dataclasses

from indoorbev_jax.config import Config
from indoorbev_jax.sweep import run_sweep, stack_hypers


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="small", choices=("paper", "small", "tiny"))
    p.add_argument("--workdir", required=True)
    p.add_argument("--data", default=None, help="KITTI-style folder (default: simulator)")
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--learning-rates", type=float, nargs="+", required=True)
    for name in ("cls", "dice", "focal", "dims", "pos", "yaw", "background"):
        p.add_argument(f"--{name}-weights", type=float, nargs="+", default=None)
    args = p.parse_args(argv)
    config = Config.preset(args.preset)
    if args.steps:
        train = dataclasses.replace(
            config.train,
            total_steps=args.steps,
            warmup_steps=min(config.train.warmup_steps, args.steps),
        )
        config = dataclasses.replace(config, train=train)
    overrides = {
        name: getattr(args, f"{name}_weights")
        for name in ("cls", "dice", "focal", "dims", "pos", "yaw", "background")
        if getattr(args, f"{name}_weights") is not None
    }
    hypers = stack_hypers(config, args.learning_rates, overrides)
    run_sweep(config, args.workdir, hypers, args.data)


if __name__ == "__main__":
    main()
