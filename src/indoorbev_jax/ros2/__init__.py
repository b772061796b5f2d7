"""Live ROS 2 integration (the optional extra: ``pip install -e .[ros]``).

* ``indoorbev ros2 detect``: the inference node (``indoorbev_jax.ros2.detect``).
* ``indoorbev-sim ros2 publish``: the simulated lidar (``indoorbev_sim.ros2``).

Messages are built and parsed with the pure-Python ``rosbags`` typestore
(``indoorbev_jax.ros2.messages``) and cross rclpy as serialized CDR bytes, so what a node
publishes, what it records into a bag and what the tests check are the same bytes, and
everything but the transport runs without ROS. Only ``runtime`` imports rclpy, lazily.
"""

from __future__ import annotations

INSTALL_HINT = "pip install -e .[ros]"


class RosUnavailable(ImportError):
    """rclpy (the ROS 2 wheels of the ``ros`` extra) cannot be imported."""


def require_rclpy():
    """The ``rclpy`` module, or a ``RosUnavailable`` saying how to install it."""
    try:
        import rclpy
    except ImportError as e:
        raise RosUnavailable(
            f"the ROS 2 nodes need rclpy, which is not installed ({e}); "
            f"install the ROS 2 wheels with `{INSTALL_HINT}`"
        ) from e
    return rclpy
