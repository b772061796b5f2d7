"""How much ``eval_sim.py --split val`` frame i shares with ``--split test`` frame i:
``python experiments/split_pairing.py [--val-seed 1000033]``.

Draws the scenes of both sets (no ray casting; ``generate.jitted_draw``, ``--batch`` as
eval_sim's) and counts the frames whose layout kind is the same and the test objects with an
identical twin in the paired val frame (same slot, variant and primitive sizes). Under one
root seed (``--val-seed 1000003``, eval_sim's default before 2026-12-05) val frame i was
test frame i with another room; ``VAL_SEED`` separates them (docs/RESULTS.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import numpy as np
from indoorbev_sim import generate

from indoorbev_jax.cli import RawHelpFormatter, positive_int, seed_int
from indoorbev_jax.config import Config

# eval_sim.py beside it, also when this file is loaded by path (the tests) from elsewhere.
sys.path.insert(0, str(Path(__file__).resolve().parent))
import eval_sim  # noqa: E402


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=RawHelpFormatter
    )
    p.add_argument("--preset", default="small", choices=("paper", "small", "tiny"),
                   help="config preset")  # fmt: skip
    p.add_argument(
        "--frames", type=positive_int, default=256, help="frames per set, a multiple of --batch"
    )
    p.add_argument(
        "--batch",
        type=positive_int,
        default=8,
        help="frames drawn per call, as eval_sim.py's --batch (the frames drawn depend on it)",
    )
    p.add_argument(
        "--val-seed",
        type=seed_int,
        default=eval_sim.VAL_SEED,
        help="root seed of the val frames (the test frames keep eval_sim's TEST_SEED)",
    )
    args = p.parse_args(argv)
    if args.frames % args.batch:
        p.error(f"--frames {args.frames} must be a multiple of --batch {args.batch}")
    config = Config.preset(args.preset)
    test_root = jax.random.key(eval_sim.TEST_SEED)
    val_root = jax.random.key(args.val_seed)
    draw_test = generate.jitted_draw(config, "test", args.batch)
    draw_val = generate.jitted_draw(config, "val", args.batch)
    counts = {"frames": 0, "same layout kind": 0, "test objects": 0, "twins in val": 0}
    for k in range(args.frames // args.batch):
        test = jax.tree.map(np.asarray, draw_test(jax.random.fold_in(test_root, k))[0])
        val = jax.tree.map(np.asarray, draw_val(jax.random.fold_in(val_root, k))[0])
        twin = test.on & val.on & (test.variant == val.variant)
        twin &= np.all(test.prims.dims == val.prims.dims, -1)
        counts["frames"] += args.batch
        counts["same layout kind"] += int((test.room.kind == val.room.kind).sum())
        counts["test objects"] += int(test.on.sum())
        counts["twins in val"] += int(twin.sum())
    print(counts)
    return counts


if __name__ == "__main__":
    from indoorbev_jax.cli import exit_with

    exit_with(main, "split_pairing.py")  # Ctrl-C: one line and status 130
