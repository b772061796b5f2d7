"""Overfitting check: how fast a configuration fits one fixed simulated batch.

A quick probe of whether masks can form at all, before paying for a real run::

    python experiments/overfit_check.py --preset small --steps 150 --learning-rate 1e-3
    python experiments/overfit_check.py --steps 150 --set head.mask_prior=false

Trains on one batch (``train.batch_size`` frames of the training layouts, no
augmentation) and prints the loss, final-layer dice and class loss every ``--every``
steps. The numbers compare configurations at equal steps; they say nothing about
generalisation.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax

from indoorbev_jax.cli import HelpFormatter, positive_int, seed_int
from indoorbev_jax.config import Config, ConfigError, with_overrides
from indoorbev_jax.train import Hyper, init_state, jit_train_step, make_train_step


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument(
        "--preset",
        default="small",
        choices=("paper", "small", "tiny"),
        help="config preset (its train.batch_size frames make the batch)",
    )
    p.add_argument("--steps", type=positive_int, default=150, help="training steps")
    p.add_argument(
        "--learning-rate",
        type=float,
        default=1e-3,
        help="peak learning rate, reached after a warm-up of up to 20 steps",
    )
    p.add_argument("--every", type=positive_int, default=25, help="print every N steps")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of the batch (the init uses +1)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="config override, as in experiments/train.py")  # fmt: skip
    args = p.parse_args(argv)
    # These are the check's own: an override of them would print as applied and not be.
    fixed = ("train.augment", "train.learning_rate", "train.warmup_steps", "train.total_steps")
    overridden = [item for item in args.set if item.split("=", 1)[0].strip() in fixed]
    if overridden:
        p.error(f"--set {overridden[0]}: the check sets {', '.join(fixed)} itself "
                "(--learning-rate and --steps set the two that may change)")  # fmt: skip
    config = Config.preset(args.preset)
    try:
        config = with_overrides(config, args.set)
    except ConfigError as e:
        p.error(f"--set: {e}")  # one line, status 2, as its other refusals
    try:  # --learning-rate nan or -1: one line, not ConfigError's traceback
        train = dataclasses.replace(
            config.train,
            augment=False,
            learning_rate=args.learning_rate,
            warmup_steps=min(20, args.steps),
            total_steps=max(args.steps, 10_000),  # ~flat after the warm-up
        )
    except ConfigError as e:
        p.error(f"--learning-rate: {e}")
    config = dataclasses.replace(config, train=train)
    from indoorbev_sim import generate_batch

    batch = jax.jit(lambda k: generate_batch(k, config, "train"))(jax.random.key(args.seed))
    print(f"{config.name}: {int(batch.targets.valid.sum())} objects in "
          f"{config.train.batch_size} frames; overrides {args.set or 'none'}")  # fmt: skip
    state = init_state(config, jax.random.key(args.seed + 1))
    step = jit_train_step(config, make_train_step(config), donate_argnums=0)
    hyper = Hyper.from_config(config)
    key = jax.random.key(args.seed + 2)
    start = time.perf_counter()
    for i in range(args.steps):
        state, m = step(state, batch, key, hyper)
        if i % args.every == 0 or i == args.steps - 1:
            extra = f" seed {float(m['seed']):.3f}" if "seed" in m else ""
            print(f"step {i}: loss {float(m['loss']):.2f} dice_final "
                  f"{float(m['dice_final']):.3f} cls_final {float(m['cls_final']):.3f}"
                  f"{extra} ({time.perf_counter() - start:.0f} s)", flush=True)  # fmt: skip


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "overfit_check.py")  # Ctrl-C: one line and status 130
