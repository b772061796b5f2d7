"""The little rclpy glue both nodes share; the only module that imports rclpy."""

from __future__ import annotations

import contextlib
import importlib
import signal
import sys
import threading

from indoorbev_jax.interrupts import SIGINT_SEEN, check_interrupted
from indoorbev_jax.ros2 import require_rclpy

__all__ = [
    "msg_class", "qos", "require_rclpy", "signals_held", "spin", "start_node", "stop_node"
]  # fmt: skip


def msg_class(msgtype: str):
    """The rclpy message class of a type name such as "sensor_msgs/msg/PointCloud2"."""
    package, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def qos(reliable: bool, depth: int):
    """Keep-last ``depth``, volatile; reliable or best effort."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    policy = ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(depth=depth, reliability=policy)


def start_node(name: str, ros_args: list[str] | None = None):
    """(context, node) in a fresh rclpy context; ``ros_args`` are what followed
    ``--ros-args`` on the command line (remappings, ``-p`` parameters, log levels)."""
    check_interrupted()
    if SIGINT_SEEN.is_set():  # a Ctrl-C during the start-up that Python dropped
        raise KeyboardInterrupt
    rclpy = require_rclpy()
    if threading.current_thread() is threading.main_thread():
        # rclpy handles SIGINT; make SIGTERM (what process managers send) stop as cleanly.
        signal.signal(signal.SIGTERM, _interrupt)
    context = _init_context(ros_args)
    return context, rclpy.create_node(name, context=context)


def check_ros_args(ros_args: list[str] | None) -> None:
    """Raises ``ValueError`` naming the arguments after ``--ros-args`` that rclpy does not
    take; run before a slow start (model load, warm-up) so a typo costs no wait."""
    if ros_args:
        _init_context(ros_args).try_shutdown()


def _init_context(ros_args: list[str] | None):
    rclpy = require_rclpy()
    context = rclpy.Context()
    args = ["indoorbev", "--ros-args", *ros_args] if ros_args else None
    try:
        rclpy.init(args=args, context=context)
    except RuntimeError as e:  # rclpy's UnknownROSArgsError, or rcl's parse error
        what = str(e) if type(e).__name__ == "UnknownROSArgsError" else f"them ({e})"
        raise ValueError(
            f"--ros-args: rclpy does not take {what}; expected remappings (from:=to), "
            f"-p name:=value, --log-level LEVEL or other ROS 2 arguments"
        ) from None
    return context


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def spin(node, context, stop: threading.Event | None = None) -> None:
    """Runs the node's callbacks until Ctrl-C, SIGTERM or ``stop`` is set."""
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        while context.ok() and not (stop is not None and stop.is_set()):
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown(timeout_sec=1.0)


def stop_node(node, context) -> None:
    node.destroy_node()
    if context.ok():
        context.try_shutdown()


@contextlib.contextmanager
def signals_held(message: str):
    """Ctrl-C and SIGTERM print ``message`` instead of interrupting the block.

    For shutdown work that must finish (joining the worker, closing a recording): an
    impatient second Ctrl-C would otherwise abandon the bag, and a sqlite3 bag keeps no
    message until it is closed. A no-op outside the main thread (signals go there).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def hold(signum, frame):
        print(message, file=sys.stderr, flush=True)

    saved = {s: signal.signal(s, hold) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)
