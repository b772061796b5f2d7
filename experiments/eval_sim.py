"""Evaluate a model on simulated held-out frames: ``python experiments/eval_sim.py --model M``.

The frames come from the simulator's ``test`` split (layout plans ``sim.test_layouts`` and
object variants ``sim.test_variants``, never drawn for train or val) under a root key that
training never uses: training draws ``fold_in(key(train.seed), 0)`` for its batches and
``fold_in(key(train.seed), 1)`` for validation, this script ``key(--seed)`` with a seed far
from the training seeds. Batch k of the set is ``generate_batch(fold_in(key(seed), k))``,
so the set is the same on every run and machine (up to float rounding of the simulator).

Prints the per-class table and the class confusion at mask IoU 0.5 (which class each object
was detected as, or missed; ``metrics.class_confusion``), then the same counts per object
variant (``Class/variant``, held-out variants marked ``*``), so a held-out shape's errors are
not mistaken for its class's; writes all of it as JSON (``--json``).
The numbers are measured on simulated data: they are not the paper's real-world measurement.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax

from indoorbev_jax.config import ConfigError
from indoorbev_jax.evaluate import report
from indoorbev_jax.metrics import Evaluator
from indoorbev_jax.predict import load_model
from indoorbev_jax.train import make_predict_fn

TEST_SEED = 1_000_003  # root seed of the held-out test set (training uses train.seed, 0)


def evaluate_sim(config, params, split: str, frames: int, batch: int, seed: int, progress=True):
    """An ``Evaluator`` holding ``params``' outputs on ``frames`` simulated frames of ``split``.

    The targets are tagged with their ``indoorbev_sim.objects.ALL_VARIANTS`` index
    (``Evaluator.tag_confusion``).
    """
    from indoorbev_sim.generate import jitted_generate
    from indoorbev_sim.objects import variant_ids
    from tqdm import tqdm

    if frames % batch:
        raise ValueError(f"--frames {frames} must be a multiple of --batch {batch}")
    generate = jitted_generate(config, split, batch)
    predict_fn = make_predict_fn(config)
    evaluator = Evaluator(config.inference, class_names=config.data.class_names)
    root = jax.random.key(seed)
    for k in tqdm(range(frames // batch), disable=not progress, unit="batch"):
        data, info = generate(jax.random.fold_in(root, k))
        tags = variant_ids(data.targets.classes, info.variant)
        evaluator.add_output(
            predict_fn(params, data.points, data.point_valid), data.targets, gt_tags=tags
        )
    return evaluator


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="run directory or exported model file")
    p.add_argument("--split", default="test", choices=("test", "val"))
    p.add_argument("--frames", type=int, default=512)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--seed", type=int, default=TEST_SEED)
    p.add_argument("--json", default=None, help="write the metrics here")
    p.add_argument(
        "--score-threshold",
        type=float,
        default=None,
        help="inference.score_threshold (default: the model's, 0.8 as in the paper)",
    )
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    try:
        config, params = load_model(args.model)
    except (OSError, ValueError) as e:
        p.exit(2, f"eval_sim: {e}\n")
    if args.score_threshold is not None:
        try:  # InferenceConfig checks the range
            inference = dataclasses.replace(config.inference, score_threshold=args.score_threshold)
        except ConfigError as e:
            p.error(str(e))
        config = dataclasses.replace(config, inference=inference)
    start = time.perf_counter()
    evaluator = evaluate_sim(
        config, params, args.split, args.frames, args.batch, args.seed, not args.no_progress
    )
    from indoorbev_sim.objects import ALL_VARIANTS

    held_out = set(config.sim.test_variants)
    names = [f"{v}*" if v in held_out else v for v in ALL_VARIANTS]
    title = "per object variant (* held out of train and val)"
    text, payload = report(evaluator, config.data.class_names, names, title)
    print(
        f"model {args.model} (preset {config.name}), {args.frames} simulated '{args.split}' "
        f"frames, seed {args.seed}, score threshold {config.inference.score_threshold}, "
        f"{time.perf_counter() - start:.0f} s"
    )
    print(text)
    if args.json:
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        payload["setup"] = {"model": str(args.model), "split": args.split,
                            "frames": args.frames, "seed": args.seed,
                            "score_threshold": config.inference.score_threshold}  # fmt: skip
        path.write_text(json.dumps(payload, indent=2) + "\n")
        print(f"metrics written to {path}")


if __name__ == "__main__":
    main()
