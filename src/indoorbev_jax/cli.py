"""The ``indoorbev`` command line.

indoorbev dataset check ROOT [--split NAME] [--preset small] [--set FIELD=VALUE]
indoorbev predict MODEL INPUT --out DIR [--lidar-rpy R,P,Y] [--lidar-height H]
indoorbev eval --gt ROOT --pred DIR [--split NAME] [--json FILE]
indoorbev ros2 detect --checkpoint MODEL [--topic /livox/lidar] [--record BAG]
"""

from __future__ import annotations

import argparse
import math
import os
import sys

from indoorbev_jax.checks import check_seed, whole_bound
from indoorbev_jax.interrupts import INTERRUPTED, catch_interrupts


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` with "(default: X)" after each option's help, except where there is no
    default to tell (None, an unset flag's False, an empty list or string) or the help text
    already tells it (it says "default")."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        unset = default is None or default is False or default == [] or default == ""
        if unset or "default" in text:  # not `in (None, False)`: 0 == False
            return text
        return super()._get_help_string(action)


class RawHelpFormatter(HelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``HelpFormatter`` that prints the description and epilog with their line breaks (a
    command to copy, say)."""


def _finite_number(zero_allowed: bool):
    """argparse type: a finite number > 0 (>= 0 with ``zero_allowed``: seconds to wait)."""
    bound = ">= 0" if zero_allowed else "> 0"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number {bound}, got {text!r}") from None
        if not (math.isfinite(value) and (value > 0 or (zero_allowed and value == 0))):
            raise argparse.ArgumentTypeError(f"must be a finite number {bound}, got {text}")
        return value

    return parse


positive_float = _finite_number(zero_allowed=False)
nonnegative_float = _finite_number(zero_allowed=True)


def _whole_number(minimum: int):
    """argparse type: a whole number >= ``minimum`` (0 or 1)."""
    bound = whole_bound(minimum)

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected a whole number {bound}, got {text!r}"
            ) from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be {bound}, got {value}")
        return value

    return parse


positive_int = _whole_number(1)
nonnegative_int = _whole_number(0)


def seed_int(text: str) -> int:
    """argparse type: a random seed, a whole number in [0, 2**32)."""
    try:
        return check_seed("seed", int(text))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a whole number in [0, 2**32), got {text!r}"
        ) from None


def _intensity_units(text: str) -> str | float:
    """argparse type of ``--intensity``: checked here, not once the model has loaded."""
    from indoorbev_jax.predict import check_intensity_units

    try:
        units = float(text)
    except ValueError:
        units = text
    try:
        check_intensity_units(units)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return units


def _add_intensity(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--intensity",
        type=_intensity_units,
        default="auto",
        help="units of the clouds' intensity: auto (values above 1 are Livox reflectivity), "
        "unit ([0, 1], the simulator's), livox (0-255, 150 = 100 %% Lambertian), percent, "
        "or a factor; the model reads it in [0, 1]",
    )


def parse_views(text: str) -> tuple[str, ...]:
    """argparse type: a comma list of ``config.VIEWS`` names, or 'all' for every one."""
    from indoorbev_jax.config import VIEWS

    views = tuple(VIEWS) if text == "all" else tuple(v.strip() for v in text.split(","))
    unknown = [v for v in views if v not in VIEWS]
    if unknown:
        msg = f"unknown view {unknown[0]!r}, expected 'all' or names from {', '.join(VIEWS)}"
        raise argparse.ArgumentTypeError(msg)
    if len(set(views)) != len(views):  # else refused only once the model has loaded
        raise argparse.ArgumentTypeError(f"{text!r} repeats a view")
    return views


def add_views_argument(parser: argparse.ArgumentParser, default_help: str) -> None:
    """``--views``: the test-time views (``inference.views``)."""
    parser.add_argument(
        "--views",
        type=parse_views,
        default=None,
        help="test-time views fused into one prediction: 'all' (8 forwards per frame, the "
        "most accurate), 'identity' (1, the fastest) or a comma list of names "
        f"(default: {default_help})",
    )


def add_boxes_argument(parser: argparse.ArgumentParser) -> None:
    """``--boxes``: where the output boxes come from (``predict.to_labels``)."""
    parser.add_argument(
        "--boxes",
        default="mask",
        choices=("mask", "head"),
        help="'mask': x, y, length, width and yaw of the rectangle around each object's "
        "segment in the panoptic map (default; several times closer to the true box on the "
        "simulated test set), 'head': the regressed box; z and height come from the head "
        "either way",
    )


def add_distributed_arguments(parser: argparse.ArgumentParser) -> None:
    """``--distributed`` and the settings ``jax.distributed.initialize`` takes, for a
    training script run once per host (``start_distributed`` acts on them)."""
    group = parser.add_argument_group("several hosts")
    group.add_argument(
        "--distributed",
        action="store_true",
        help="this is one process of a multi-host run: call jax.distributed.initialize() "
        "first, which finds the coordinator, the process count and this process's id under "
        "SLURM, Open MPI or on Cloud TPU; elsewhere give the three options below. Every "
        "host runs the same command on one shared --workdir",
    )
    group.add_argument("--coordinator-address", metavar="HOST:PORT",
                       help="process 0's address (or env JAX_COORDINATOR_ADDRESS)")  # fmt: skip
    group.add_argument("--num-processes", type=positive_int, help="processes in the run")
    group.add_argument("--process-id", type=nonnegative_int, help="this process's index")


def start_distributed(args: argparse.Namespace, prog: str) -> None:
    """Joins a multi-host run when ``args.distributed``, then checks ``JAX_PLATFORMS`` as
    ``exit_with`` does for other commands (the check starts the backends, after which JAX
    refuses to join: their scripts call ``exit_with(..., check_platforms=False)``). A
    failed join is a ValueError naming the flag, as is a host setting without the flag."""
    given = [f for f in ("coordinator_address", "num_processes", "process_id")
             if getattr(args, f) is not None]  # fmt: skip
    if args.distributed:
        import jax

        try:
            jax.distributed.initialize(
                coordinator_address=args.coordinator_address,
                num_processes=args.num_processes,
                process_id=args.process_id,
            )
        except (ValueError, RuntimeError) as e:
            raise ValueError(
                f"--distributed: jax.distributed.initialize() failed ({e}); outside SLURM, "
                "Open MPI and Cloud TPU, give --coordinator-address, --num-processes and "
                "--process-id"
            ) from e
    elif given:
        flags = ", ".join("--" + f.replace("_", "-") for f in given)
        raise ValueError(f"{flags}: only with --distributed (a multi-host run)")
    _check_jax_platforms(prog)


def join_negative_values(argv: list[str] | None, flags=("--lidar-rpy",)) -> list[str]:
    """``argv`` (None: ``sys.argv[1:]``) with ``FLAG -5,0,0`` written ``FLAG=-5,0,0``:
    argparse takes a negative number for a value only when it is one number, so a
    negative roll read as an unknown option ("expected one argument")."""
    argv = list(sys.argv[1:] if argv is None else argv)
    out: list[str] = []
    for arg in argv:
        if out and out[-1] in flags and arg[:1] == "-" and arg[1:2] in "0123456789.":
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def rpy_argument(text: str) -> tuple[float, float, float]:
    """argparse type of ``--lidar-rpy``: ``ROLL,PITCH,YAW`` in degrees."""
    from indoorbev_jax.mount import parse_rpy

    try:
        return parse_rpy(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _height(text: str) -> float:
    from indoorbev_jax.mount import parse_height

    try:
        return parse_height(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_mount_arguments(parser: argparse.ArgumentParser) -> None:
    """``--lidar-rpy`` and ``--lidar-height``: how the lidar sits (``mount.LidarMount``)."""
    parser.add_argument(
        "--lidar-rpy",
        type=rpy_argument,
        default=(0.0, 0.0, 0.0),
        metavar="ROLL,PITCH,YAW",
        help="the lidar's orientation on the robot in degrees (a URDF's rpy, which is in "
        "radians, fixed axes), for a tilted mount: clouds are levelled first and the outputs "
        "are in that level frame (default 0,0,0)",
    )
    parser.add_argument(
        "--lidar-height",
        type=_height,
        default=None,
        metavar="METRES",
        help="the lidar's height above the floor: outside the model's trained heights "
        "(sim.sensor_height) the cloud is moved to the nearest, output z moved back "
        "(default: z as read)",
    )


def mount_from_args(args: argparse.Namespace):
    """The ``mount.LidarMount`` of ``add_mount_arguments``' options."""
    from indoorbev_jax.mount import LidarMount

    return LidarMount(*args.lidar_rpy, height=args.lidar_height)


def dataset_check(args: argparse.Namespace) -> int:
    """Validates every frame of a dataset folder; prints statistics and the first problems."""
    from indoorbev_jax.config import ConfigError
    from indoorbev_jax.data import kitti
    from indoorbev_jax.data.check import check_dataset
    from indoorbev_jax.data.dataset import dataset_config

    try:
        config, source = dataset_config(args.root, args.preset, args.set)
        progress = sys.stderr.isatty()  # no bar text in a log
        report = check_dataset(args.root, args.split, config, source, progress=progress)
    except (kitti.DatasetError, OSError) as e:
        # stderr: `dataset check ROOT > report.txt` must still show it
        print(f"indoorbev dataset check: error: {e}", file=sys.stderr)
        return 1
    except ConfigError as e:  # a bad --set or --preset: a usage error, as in train.py
        print(f"indoorbev dataset check: error: {e}", file=sys.stderr)
        return 2
    print(report.format(args.max_problems))
    return 0 if report.ok else 1


def build_parser() -> argparse.ArgumentParser:
    from indoorbev_jax.evaluate import add_dataset_config_arguments, add_eval_command

    parser = argparse.ArgumentParser(
        prog="indoorbev",
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],  # the synopsis
        formatter_class=RawHelpFormatter,
    )
    commands = parser.add_subparsers(dest="command", required=True)

    dataset = commands.add_parser(
        "dataset", help="dataset tools", description="dataset tools", formatter_class=HelpFormatter
    ).add_subparsers(dest="dataset_command", required=True)
    check = dataset.add_parser(
        "check",
        help="validate a KITTI-style dataset folder",
        description="Validate every frame of a KITTI-style dataset folder; print statistics "
        "(objects per class, points per frame) and the first warnings and problems. Exit "
        "status 1 when there are problems.",
        formatter_class=HelpFormatter,
    )
    check.add_argument("root", help="dataset folder (velodyne/, label_2/, optional mask_2/)")
    check.add_argument(
        "--split",
        default=None,
        help="check only the frames listed in <root>/<split>.txt (default: every frame)",
    )
    check.add_argument(
        "--max-problems",
        type=positive_int,
        default=10,
        help="list at most this many warnings and this many problems (default 10); their "
        "counts are printed in full",
    )
    add_dataset_config_arguments(check)
    check.set_defaults(func=dataset_check)

    add_eval_command(commands)

    pred = commands.add_parser(
        "predict",
        help="run a trained model on .bin/.pcd/.npy, KITTI or bag input",
        description="Run a trained model on .bin/.pcd/.npy files, a KITTI-style folder or a "
        "ROS 2 bag; write label_2/, mask_2/ and pictures/ per frame into --out. The same "
        "command after a kill resumes.",
        formatter_class=HelpFormatter,
    )
    pred.add_argument("model", help="run directory or exported model file (.msgpack)")
    pred.add_argument(
        "input",
        help=".bin, .pcd or .npy file, a folder of them, KITTI-style folder, ROS 2 bag folder, "
        "or a lone bag storage file (.mcap, .db3)",
    )
    pred.add_argument("--out", required=True, help="output folder (label_2, mask_2, pictures)")
    pred.add_argument(
        "--topic",
        default=None,
        help="cloud topic of a bag (PointCloud2 or Livox CustomMsg; default: the bag's only "
        "cloud topic)",
    )
    pred.add_argument(
        "--bag-out",
        default=None,
        help="also write a ROS 2 bag folder with the input clouds (/points) and the "
        "predictions (/detections)",
    )
    pred.add_argument(
        "--no-pictures",
        action="store_true",
        help="do not write pictures/<id>.png (raw points | feature map | predicted masks | "
        "final BEV); labels and masks only",
    )
    pred.add_argument(
        "--skip-bad-frames",
        action="store_true",
        help="report and skip frames that cannot be read (default: stop, naming the frame)",
    )
    pred.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the label, mask and picture files of another run in --out (the same "
        "command again resumes instead)",
    )
    _add_intensity(pred)
    add_views_argument(pred, "the model file's")
    add_boxes_argument(pred)
    add_mount_arguments(pred)
    pred.add_argument(
        "--level-frame",
        default=None,
        help="with --lidar-rpy and --bag-out: frame id of the bag's levelled clouds and detections",
    )
    pred.set_defaults(func=run_predict)

    ros2 = commands.add_parser(
        "ros2",
        help="live ROS 2 nodes (pip install -e .[ros])",
        description="live ROS 2 nodes (pip install -e .[ros])",
        formatter_class=HelpFormatter,
    )
    ros2_commands = ros2.add_subparsers(dest="ros2_command", required=True)
    det = ros2_commands.add_parser(
        "detect",
        help="inference node: PointCloud2 in; detections, markers, occupancy out",
        description="Live ROS 2 inference node: subscribes to PointCloud2 clouds on --topic "
        "and publishes per cloud, with its stamp and frame id, the detections, markers and "
        "occupancy grid under --out-ns (the newest cloud is processed, stale ones dropped), "
        "until Ctrl-C or --max-frames.",
        formatter_class=HelpFormatter,
    )
    det.add_argument("--checkpoint", required=True, help="run directory or exported model file")
    det.add_argument("--topic", default="/livox/lidar", help="PointCloud2 input topic")
    det.add_argument("--out-ns", default="/indoorbev", help="namespace of the output topics")
    det.add_argument(
        "--reliable", action="store_true", help="reliable input QoS (default best effort)"
    )
    det.add_argument(
        "--record", default=None, help="record inputs and outputs into this bag folder"
    )
    det.add_argument(
        "--storage",
        default="sqlite3",
        choices=("sqlite3", "mcap"),
        help="storage format of the --record bag",
    )
    det.add_argument(
        "--log-every", type=positive_float, default=5.0, help="seconds between summaries"
    )
    det.add_argument(
        "--skip-nonfinite",
        action="store_true",
        help="process the finite points of clouds with NaN/Inf points (default: empty output)",
    )
    det.add_argument(
        "--max-frames",
        type=nonnegative_int,
        default=0,
        help="stop after this many processed frames (0: never)",
    )
    _add_intensity(det)
    add_views_argument(det, "the model file's")
    add_boxes_argument(det)
    add_mount_arguments(det)
    det.add_argument(
        "--level-frame",
        default=None,
        help="frame id of the outputs when --lidar-rpy levels the clouds (required then: "
        "the lidar's origin with z up; publish its transform)",
    )
    det.add_argument("--ros-args", nargs=argparse.REMAINDER, default=[],
                     help="the rest goes to rclpy (remappings, log levels)")  # fmt: skip
    det.set_defaults(func=run_ros2_detect)
    return parser


def run_ros2_detect(args: argparse.Namespace) -> int:
    from indoorbev_jax.ros2 import RosUnavailable

    try:
        from indoorbev_jax.ros2.detect import run_detect_node

        run_detect_node(
            args.checkpoint,
            topic=args.topic,
            out_ns=args.out_ns,
            reliable=args.reliable,
            record=args.record,
            storage=args.storage,
            log_every=args.log_every,
            max_frames=args.max_frames,
            ros_args=args.ros_args,
            skip_nonfinite=args.skip_nonfinite,
            intensity=args.intensity,
            views=args.views,
            boxes=args.boxes,
            mount=mount_from_args(args),
            level_frame=args.level_frame,
        )
    except (RosUnavailable, OSError, ValueError) as e:
        print(f"indoorbev ros2 detect: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # before the node runs (warm-up); afterwards it stops cleanly
        print("indoorbev ros2 detect: interrupted", file=sys.stderr)
        return INTERRUPTED
    return 0


def run_predict(args: argparse.Namespace) -> int:
    from indoorbev_jax.predict import predict

    try:
        predict(
            args.model,
            args.input,
            args.out,
            topic=args.topic,
            bag_out=args.bag_out,
            pictures=not args.no_pictures,
            intensity=args.intensity,
            views=args.views,
            skip_bad_frames=args.skip_bad_frames,
            overwrite=args.overwrite,
            boxes=args.boxes,
            mount=mount_from_args(args),
            level_frame=args.level_frame,
        )
    except (OSError, ValueError) as e:  # bad model file, input or bag (rosbag.BagError)
        print(f"indoorbev predict: error: {e}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(join_negative_values(argv))
    return args.func(args)


def _check_jax_platforms(prog: str) -> None:
    """One line, status 2, when ``JAX_PLATFORMS`` names a backend this machine lacks: JAX
    ends in a traceback (for ``cuda`` without its plugin, a bare AssertionError)."""
    wanted = os.environ.get("JAX_PLATFORMS", "")
    if wanted in ("", "cpu"):
        return
    import jax

    try:
        jax.devices()
    except (RuntimeError, AssertionError) as e:
        why = f" ({str(e).split(' (set JAX_PLATFORMS')[0]})" if str(e) else ""
        print(
            f"{prog}: error: JAX_PLATFORMS={wanted}: no such backend here{why}; unset it or "
            "set JAX_PLATFORMS=cpu (a GPU needs a driver and the jax[cuda12] wheel)",
            file=sys.stderr,
        )
        sys.exit(2)


def exit_with(main_fn, prog: str, check_platforms: bool = True):
    """Runs a console command's ``main`` and exits with its status; ``check_platforms``:
    check ``JAX_PLATFORMS`` first (a command that may join a multi-host run checks it
    after joining, in ``start_distributed``).

    Ctrl-C exits with 130 and one line instead of a traceback, and leaves at once: XLA may
    still be compiling on its own threads, and a normal interpreter shutdown under them
    crashes (a segmentation fault after the warm-up of ``ros2 detect`` was cut short).
    Output files are written atomically, so nothing half-written is left under its name.
    """
    catch_interrupts()
    if check_platforms:
        _check_jax_platforms(prog)
    try:
        status = main_fn()
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        status = INTERRUPTED
    if status == INTERRUPTED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(INTERRUPTED)
    # A main that returns a result for Python callers (a dict, say) succeeded.
    sys.exit(status if isinstance(status, int) else 0)


def entry() -> None:
    """The ``indoorbev`` console script."""
    exit_with(main, "indoorbev")


if __name__ == "__main__":
    entry()
