"""Live ROS 2 integration (the optional extra: ``pip install -e .[ros]``).

* ``indoorbev ros2 detect``: the inference node (``indoorbev_jax.ros2.detect``).
* ``indoorbev-sim ros2 publish``: the simulated lidar (``indoorbev_sim.ros2``).

Messages are built and parsed with the pure-Python ``rosbags`` typestore
(``indoorbev_jax.ros2.messages``) and cross rclpy as serialized CDR bytes, so what a node
publishes, what it records into a bag and what the tests check are the same bytes, and
everything but the transport runs without ROS. Only ``runtime`` imports rclpy, lazily.
"""

from __future__ import annotations

import re

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


# A token of a ROS 2 name: a letter or underscore, then letters, digits and underscores, or
# a {substitution}; rcl's validator applies these rules after the leading "/" or "~/".
_SUB = r"\{[A-Za-z_][A-Za-z0-9_]*\}"
_TOKEN = re.compile(rf"(?:[A-Za-z_]|{_SUB})(?:[A-Za-z0-9_]|{_SUB})*")
SUBSTITUTIONS = ("{node}", "{ns}", "{namespace}")  # the ones rcl expands
MAX_TOPIC_CHARS = 255 - 8  # rmw's limit on the expanded name (DDS adds a prefix)


def topic_name_problem(name: str) -> str | None:
    """Why ``name`` is not a valid ROS 2 topic name (rcl's rules), or None when it is.

    Checked before a node starts, so that a typo fails at once rather than after the
    model's warm-up (rclpy only checks when the publisher or subscription is made).
    """
    if not name:
        return "is empty"
    if name.endswith("/"):
        return "must not end with '/'"
    if "//" in name:
        return "must not contain '//'"
    body = name
    if body.startswith("~"):
        if body != "~" and not body.startswith("~/"):
            return "must separate '~' from the rest with '/' ('~/name')"
        body = body[2:]
    elif body.startswith("/"):
        body = body[1:]
    if not body:  # "~" alone: the node's private namespace
        return None
    for token in body.split("/"):
        if not _TOKEN.fullmatch(token):
            return (
                f"has the token '{token}': tokens hold letters, digits and '_' (or are a "
                "{substitution}) and must not start with a digit"
            )
    for sub in re.findall(_SUB, name):
        if sub not in SUBSTITUTIONS:
            return f"has the unknown substitution {sub} (rcl expands {', '.join(SUBSTITUTIONS)})"
    if len(name) + (not name.startswith("/")) > MAX_TOPIC_CHARS:
        return f"is longer than the {MAX_TOPIC_CHARS} characters rmw allows"
    return None


def check_topic_name(name: str, what: str) -> str:
    """``name``, or a ``ValueError`` naming ``what`` (e.g. "--topic") and the rule broken."""
    problem = topic_name_problem(name)
    if problem is not None:
        raise ValueError(f"{what}: '{name}' is not a valid ROS 2 topic name: it {problem}")
    return name
