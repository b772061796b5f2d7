"""The ``indoorbev`` command line.

indoorbev dataset check ROOT [--split NAME] [--preset small]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from indoorbev_jax.config import Config


def _add_preset(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--preset",
        default="small",
        choices=("paper", "small", "tiny"),
        help="config preset giving the grid, padding and classes (default: small)",
    )


def dataset_check(args: argparse.Namespace) -> int:
    """Validates every frame of a dataset folder; prints statistics and the first problems."""
    from indoorbev_jax.data import kitti
    from indoorbev_jax.data.dataset import KittiDataset

    config = Config.preset(args.preset)
    root = Path(args.root)
    problems: list[str] = []
    try:
        ds = KittiDataset(root, args.split, config)
    except kitti.DatasetError as e:
        print(f"error: {e}")
        return 1
    class_counts = np.zeros(config.num_classes, np.int64)
    valid_points, raw_points = [], []
    invalid = dropped_points = dropped_objects = 0
    for k in range(len(ds)):
        try:
            item, stats = ds.load(k)
        except (kitti.DatasetError, OSError) as e:
            problems.append(str(e))
            continue
        t = item.targets
        class_counts += np.bincount(t.classes[t.valid], minlength=config.num_classes)
        raw_points.append(stats.raw_points)
        valid_points.append(stats.valid_points)
        invalid += stats.nonfinite_points + stats.outside_points
        dropped_points += stats.dropped_points
        if stats.dropped_objects:
            dropped_objects += stats.dropped_objects
            problems.append(
                f"{ds.ids[k]}: {stats.objects} objects, only the first "
                f"{config.data.max_objects} fit data.max_objects"
            )
    print(f"dataset {root} (split: {args.split or 'all'}, preset {config.name})")
    print(f"frames: {len(ds)} ({len(ds) - len(valid_points)} unreadable)")
    print("objects per class:")
    for name, n in zip(config.data.class_names, class_counts, strict=True):
        print(f"  {name:<8} {n:>8}")
    print(f"  {'total':<8} {class_counts.sum():>8}")
    if valid_points:
        v = np.asarray(valid_points)
        print(
            f"points per frame (valid): min {v.min()}  median {int(np.median(v))}  "
            f"mean {v.mean():.1f}  max {v.max()}  (raw total {sum(raw_points)})"
        )
    print(f"invalid points (non-finite or outside the workspace): {invalid}")
    print(f"points beyond data.max_points={config.data.max_points}: {dropped_points}")
    if dropped_objects:
        print(f"objects beyond data.max_objects: {dropped_objects}")
    if problems:
        print(f"problems: {len(problems)}; the first {min(len(problems), args.max_problems)}:")
        for p in problems[: args.max_problems]:
            print(f"  {p}")
        return 1
    print("no problems found")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="indoorbev", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    dataset = commands.add_parser("dataset", help="dataset tools").add_subparsers(
        dest="dataset_command", required=True
    )
    check = dataset.add_parser("check", help="validate a KITTI-style dataset folder")
    check.add_argument("root", help="dataset folder (velodyne/, label_2/, optional mask_2/)")
    check.add_argument("--split", default=None, help="split name (<root>/<split>.txt)")
    check.add_argument("--max-problems", type=int, default=10)
    _add_preset(check)
    check.set_defaults(func=dataset_check)

    from indoorbev_jax.evaluate import add_eval_command  # owns `indoorbev eval`

    add_eval_command(commands)

    pred = commands.add_parser("predict", help="run a trained model on .bin, KITTI or bag input")
    pred.add_argument("model", help="run directory or exported model file (.msgpack)")
    pred.add_argument("input", help=".bin file, KITTI-style folder or ROS 2 bag folder")
    pred.add_argument("--out", required=True, help="output folder (label_2, mask_2, pictures)")
    pred.add_argument("--topic", default=None, help="PointCloud2 topic of a bag")
    pred.add_argument("--bag-out", default=None, help="also write a bag with the predictions")
    pred.add_argument("--no-pictures", action="store_true")
    pred.set_defaults(func=run_predict)
    return parser


def run_predict(args: argparse.Namespace) -> int:
    from indoorbev_jax.predict import predict

    predict(
        args.model,
        args.input,
        args.out,
        topic=args.topic,
        bag_out=args.bag_out,
        pictures=not args.no_pictures,
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
