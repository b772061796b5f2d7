"""Export a run's checkpoint as one model file: ``python experiments/export_model.py RUN --out F``.

The file (msgpack: config + parameters, written atomically) is what ``indoorbev predict``,
``indoorbev ros2 detect`` and ``make demo`` load; ``models/indoorbev_small.msgpack`` is the
shipped one. RUN may also be a model file, to store other inference settings in a copy:
``export_model.py models/indoorbev_small.msgpack --views identity --out fast.msgpack``, or a
sweep's workdir with ``--member K``, to take out one of its K models.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import jax

from indoorbev_jax.checks import check_not_an_input
from indoorbev_jax.cli import HelpFormatter, add_views_argument
from indoorbev_jax.config import ConfigError
from indoorbev_jax.predict import export_model, load_model, with_thresholds
from indoorbev_jax.sweep import load_member
from indoorbev_jax.train import load_run


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("run", help="run directory (config.json + checkpoints) or model file")
    p.add_argument("--out", required=True, help="model file to write (.msgpack)")
    p.add_argument(
        "--which",
        default=None,
        choices=("best", "latest"),
        help="with a run directory: its best checkpoint (validation PQ; the latest where "
        "there is none) or its latest (default: best; a sweep's --member: always its latest)",
    )
    p.add_argument(
        "--score-threshold",
        type=float,
        default=None,
        help="inference.score_threshold stored in the file (default: the run's); pick it on "
        "the validation split (experiments/eval_sim.py --split val)",
    )
    p.add_argument(
        "--mask-threshold",
        type=float,
        default=None,
        help="inference.mask_threshold stored in the file (default: the run's)",
    )
    p.add_argument(
        "--member",
        type=int,
        default=None,
        help="with a sweep's workdir: export its model K (0-based, in the order of "
        "--learning-rates) from the latest checkpoint",
    )
    add_views_argument(p, "the run's")
    args = p.parse_args(argv)
    from_run = Path(args.run).is_dir()
    if not Path(args.run).exists():
        p.exit(2, f"export_model: {args.run}: no such model file or run directory\n")
    if args.member is not None and not from_run:
        p.error("--member takes a sweep's workdir, not a model file")
    if args.member is not None and args.which is not None:
        p.error("--which applies to a training run; a sweep member comes from its latest")
    args.which = args.which or "best"
    try:
        # A run's config.json as --out was replaced by the model; the model file itself may
        # be rewritten in place (new thresholds).
        check_not_an_input("--out", args.out, [args.run], files=False)
        if args.member is not None:
            config, params = load_member(args.run, args.member)
        elif from_run:
            config, params, source = load_run(args.run, args.which)
        else:
            config, params = load_model(args.run)
    except (OSError, ValueError) as e:
        p.exit(2, f"export_model: {e}\n")
    try:
        config = with_thresholds(config, args.score_threshold, args.mask_threshold, args.views)
    except ConfigError as e:
        p.error(str(e))
    try:
        path = export_model(params, config, args.out)
    except OSError as e:  # a folder, or a place that cannot be written: named, status 2
        p.exit(2, f"export_model: {e}\n")
    count = sum(math.prod(x.shape) for x in jax.tree.leaves(params))
    _, back = load_model(path)  # the file must read back to the same parameters
    same = jax.tree.all(jax.tree.map(lambda a, b: bool((a == b).all()), params, back))
    if not same:
        raise SystemExit(f"{path}: parameters did not read back unchanged")
    if args.member is not None:
        source = f"sweep member {args.member}, latest"
    elif not from_run:
        source = "model file"
    print(f"{args.run} ({source}, preset {config.name}, {count:,} parameters, score "
          f"threshold {config.inference.score_threshold}, mask threshold "
          f"{config.inference.mask_threshold}, views {','.join(config.inference.views)}) -> "
          f"{path} "
          f"({path.stat().st_size / 2**20:.1f} MiB)")  # fmt: skip


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "export_model.py")  # Ctrl-C: one line and status 130
