"""``indoorbev-sim``: export simulated datasets, draw BEV pictures, check labels.

    indoorbev-sim export --out DIR --frames N --seed S [--rosbag PATH] [--preset paper]
    indoorbev-sim show DIR --out PICS [--ids 000000 000001] [--preset paper] [--set F=V]
    indoorbev-sim check --frames 200 [--preset paper] [--noise-free]
    indoorbev-sim ros2 publish [--preset small] [--rate 10] [--frames N] [--record BAG]

Compiled generators are kept in a persistent XLA cache (``--cache``, default
``~/.cache/indoorbev_sim/xla``; ``--cache ''`` disables it), so a resumed export does not
compile again. Without ``--preset``, ``export`` (resuming) and ``show`` take the preset that
``DIR/export.json`` records, else paper.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from indoorbev_jax.checks import check_folder
from indoorbev_jax.cli import (
    HelpFormatter,
    RawHelpFormatter,
    exit_with,
    join_negative_values,
    nonnegative_int,
    positive_float,
    positive_int,
    rpy_argument,
    seed_int,
)
from indoorbev_jax.interrupts import INTERRUPTED

if TYPE_CHECKING:  # JAX loads in main, where Ctrl-C is caught (status 130, one line)
    from indoorbev_jax.config import Config


def _config(args) -> Config:
    from indoorbev_jax.config import Config

    preset = args.preset
    if preset is None and args.command == "show" and (Path(args.root) / "export.json").exists():
        from indoorbev_jax.data.dataset import dataset_config

        # The whole config it was exported with: its preset alone drew another grid's
        # masks (an export with --set grid.x_range=...) 5 m off their boxes.
        return dataset_config(args.root, None, args.set)[0]
    if preset is None:  # export: the preset of the folder it resumes; show: no export.json
        from indoorbev_sim.export import saved_preset

        preset = (saved_preset(args.out) if args.command == "export" else None) or "paper"
    cfg = Config.preset(preset)
    if getattr(args, "set", None):
        from indoorbev_jax.config import with_overrides

        cfg = with_overrides(cfg, args.set)
    if getattr(args, "noise_free", False):
        cfg = dataclasses.replace(
            cfg, sim=dataclasses.replace(cfg.sim, range_noise=0.0, dropout=0.0)
        )
    return cfg


def _check_show_root(root: Path, ids: list[str] | None) -> None:
    # A typo in DIR would otherwise "write 0 pictures" and succeed.
    if not root.is_dir():
        raise ValueError(f"{root}: no such dataset folder")
    if ids is None and not any((root / "label_2").glob("*.txt")):
        raise ValueError(f"{root}: holds no frames (no label_2/*.txt files)")
    if ids is not None and not ids:
        raise ValueError("--ids: name at least one frame id (leave --ids out for every frame)")


def _use_cache(path: str) -> None:
    if not path:
        return
    import jax

    try:
        folder = Path(path).expanduser()
    except RuntimeError as e:  # ~nosuchuser/...
        raise ValueError(f"--cache {path}: {e}") from None
    check_folder("--cache", folder)  # a file: JAX warned and compiled every run again
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def _add_set(parser: argparse.ArgumentParser, example: str) -> None:
    """``--set FIELD=VALUE``, repeatable: config overrides (``config.with_overrides``)."""
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help=f"override a config field (repeatable), {example}")  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="indoorbev-sim",
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],  # the synopsis and the cache
        formatter_class=RawHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    default_cache = os.environ.get("INDOORBEV_SIM_CACHE", "~/.cache/indoorbev_sim/xla")
    preset_help = "config preset (paper, small, tiny; default: DIR/export.json's, else paper)"
    cache_help = (
        "persistent XLA cache folder, '' for none (default: %(default)s, from "
        "INDOORBEV_SIM_CACHE when set)"
    )
    seed_help = "root seed of the scenes, in [0, 2**32)"

    ex = sub.add_parser(
        "export",
        help="write a KITTI-layout dataset (resumable)",
        description="Write simulated frames as a KITTI-layout dataset (velodyne/, label_2/, "
        "mask_2/, train/val/test.txt, export.json), scene by scene: scene j goes to val when "
        "j % 10 == 8, to test when j % 10 == 9, else to train. The same command after a "
        "kill resumes.",
        formatter_class=HelpFormatter,
    )
    ex.add_argument("--out", required=True, help="dataset root folder")
    ex.add_argument(
        "--frames",
        type=positive_int,
        required=True,
        help="frames to write, in scenes of sim.frames_per_sequence consecutive frames",
    )
    ex.add_argument("--seed", type=seed_int, default=0, help=seed_help)
    ex.add_argument("--rosbag", default=None, help="also write a ROS2 bag at this path")
    ex.add_argument("--preset", default=None, help=preset_help)
    _add_set(ex, "e.g. 'sim.sensor_rpy=[0,20,0]'; a resumed export needs the same")
    ex.add_argument("--no-progress", action="store_true", help="no progress bar")
    ex.add_argument("--throttle", type=float, default=0.0, help="seconds to pause after each scene")
    ex.add_argument("--cache", default=default_cache, help=cache_help)
    ex.set_defaults(run=_run_export)

    sh = sub.add_parser(
        "show",
        help="write a BEV PNG per frame of a KITTI folder",
        description="Write <out>/<id>.png for frames of a KITTI-layout folder: points coloured "
        "by height, footprint masks, boxes and class names.",
        formatter_class=HelpFormatter,
    )
    sh.add_argument("root", help="dataset root folder")
    sh.add_argument("--out", required=True, help="folder for the PNGs")
    sh.add_argument("--ids", nargs="*", default=None, help="frame ids (default: all)")
    sh.add_argument("--preset", default=None, help=preset_help)
    _add_set(sh, 'e.g. for your own class names --set \'data.class_map={"Desk": "Table"}\'')
    sh.set_defaults(run=_run_show)

    ck = sub.add_parser(
        "check",
        help="label consistency and class statistics over N frames",
        description="Simulate frames and print label statistics: the share of the labelled "
        "objects' points inside their own footprint (dilated by a cell) and those inside "
        "another object's, and the objects per class.",
        formatter_class=HelpFormatter,
    )
    ck.add_argument("--frames", type=positive_int, default=200, help="frames to simulate")
    ck.add_argument(
        "--batch", type=positive_int, default=8, help="frames simulated per jitted call"
    )
    ck.add_argument("--seed", type=seed_int, default=0, help=seed_help)
    ck.add_argument("--preset", default="paper", help="config preset: paper, small or tiny")
    ck.add_argument(
        "--split",
        default="train",
        choices=("train", "val", "test"),
        help="the split's scenes to draw (test: held-out layouts and variants)",
    )
    _add_set(ck, "e.g. 'sim.sensor_rpy=[0,20,0]'")
    ck.add_argument("--noise-free", action="store_true", help="no range noise or dropout")
    ck.add_argument("--cache", default=default_cache, help=cache_help)
    ck.set_defaults(run=_run_check)

    ros2 = sub.add_parser(
        "ros2",
        help="live ROS 2 nodes (pip install -e .[ros])",
        description="live ROS 2 nodes (pip install -e .[ros])",
        formatter_class=HelpFormatter,
    )
    pb = ros2.add_subparsers(dest="ros2_command", required=True).add_parser(
        "publish",
        help="publish simulated PointCloud2 frames and ground-truth markers",
        description="Publish simulated PointCloud2 frames at --rate with their ground truth "
        "as a MarkerArray, until --frames are out or Ctrl-C.",
        formatter_class=HelpFormatter,
    )
    pb.add_argument("--preset", default="small", help="config preset: paper, small or tiny")
    pb.add_argument("--rate", type=positive_float, default=10.0, help="frames per second")
    pb.add_argument("--frames", type=nonnegative_int, default=0,
                    help="frames to publish (0: until Ctrl-C)")  # fmt: skip
    pb.add_argument("--topic", default="/lidar/points", help="PointCloud2 topic")
    pb.add_argument("--objects-topic", default="/lidar/objects", help="ground-truth MarkerArray")
    pb.add_argument(
        "--frame-id",
        default="lidar",
        help="frame id of the clouds (and of the ground truth without --lidar-rpy)",
    )
    pb.add_argument("--lidar-rpy", type=rpy_argument, default=(0.0, 0.0, 0.0),
                    metavar="ROLL,PITCH,YAW",
                    help="simulate the lidar tilted, degrees in the robot's level frame (a "
                    "URDF's rpy: pitch 20 is nose down), and publish its clouds in its own "
                    "frame (--frame-id); the ground truth goes out in --level-frame "
                    "(default: 0,0,0, level)")  # fmt: skip
    pb.add_argument(
        "--level-frame",
        default=None,
        help="frame id of the ground truth with --lidar-rpy (its level frame)",
    )
    pb.add_argument("--seed", type=seed_int, default=0, help=seed_help)
    pb.add_argument(
        "--split",
        default="test",
        choices=("train", "val", "test"),
        help="the split's scenes to draw (test: held-out layouts and variants)",
    )
    pb.add_argument("--record", default=None, help="record what is published into this bag")
    pb.add_argument("--storage", default="sqlite3", choices=("sqlite3", "mcap"),
                    help="storage format of the --record bag")  # fmt: skip
    pb.add_argument("--wait-subscribers", type=nonnegative_int, default=0,
                    help="wait for this many subscribers on --topic before the first "
                    "frame")  # fmt: skip
    pb.add_argument("--wait-timeout", type=positive_float, default=60.0,
                    help="seconds to wait for --wait-subscribers before giving up")  # fmt: skip
    pb.add_argument("--noise-free", action="store_true", help="no range noise or dropout")
    pb.add_argument("--cache", default=default_cache, help=cache_help)
    pb.add_argument("--ros-args", nargs=argparse.REMAINDER, default=[],
                    help="the rest goes to rclpy (remappings, log levels)")  # fmt: skip
    pb.set_defaults(run=_run_publish)
    return parser


def _run_export(args: argparse.Namespace, cfg: Config) -> int:
    from indoorbev_sim.export import export

    _use_cache(args.cache)
    splits = export(args.out, args.frames, args.seed, cfg, args.rosbag,
                    progress=not args.no_progress, throttle=args.throttle)  # fmt: skip
    print(" ".join(f"{k}={len(v)}" for k, v in splits.items()))
    empty = [k for k, v in splits.items() if not v]
    if empty:  # scene j goes to test when j % 10 == 9, to val when j % 10 == 8
        per_scene = cfg.sim.frames_per_sequence
        print(f"note: no {' or '.join(empty)} frames: scene j goes to val when "
              f"j % 10 == 8 and to test when j % 10 == 9 ({per_scene} frames a "
              f"scene), so --frames >= {10 * per_scene} gives every split",
              file=sys.stderr)  # fmt: skip
    return 0


def _run_show(args: argparse.Namespace, cfg: Config) -> int:
    from indoorbev_sim.show import show

    written = show(args.root, args.out, cfg, args.ids)
    print(f"wrote {len(written)} pictures to {args.out}")
    return 0


def _run_check(args: argparse.Namespace, cfg: Config) -> int:
    from indoorbev_sim.labels import check

    _use_cache(args.cache)
    print(check(cfg, args.frames, args.batch, args.seed, args.split))
    return 0


def _run_publish(args: argparse.Namespace, cfg: Config) -> int:
    from indoorbev_sim.ros2 import publish

    from indoorbev_jax.ros2 import RosUnavailable

    _use_cache(args.cache)
    try:
        publish(cfg, args.rate, args.frames, args.topic, args.objects_topic,
                args.frame_id, args.seed, args.split, args.record, args.storage,
                args.wait_subscribers, args.wait_timeout, args.ros_args,
                args.lidar_rpy, args.level_frame)  # fmt: skip
    except RosUnavailable as e:
        print(f"indoorbev-sim: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # before the node runs; afterwards it stops cleanly
        print("indoorbev-sim: interrupted", file=sys.stderr)
        return INTERRUPTED
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(join_negative_values(argv))
    try:
        if args.command == "show":
            _check_show_root(Path(args.root), args.ids)
        return args.run(args, _config(args))
    except (ValueError, RuntimeError, OSError) as e:
        print(f"indoorbev-sim: error: {e}", file=sys.stderr)
        return 2


def entry() -> None:
    """The ``indoorbev-sim`` console script (Ctrl-C: status 130, no traceback)."""
    exit_with(main, "indoorbev-sim")


if __name__ == "__main__":
    entry()
