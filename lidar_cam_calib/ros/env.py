"""Process environment for DDS on loopback (no rclpy import here).

Every script, test and CI step that starts rclpy goes through
:func:`loopback_env`: discovery stays on localhost and a domain id can be
chosen per test. Replay does not rely on transport tuning: it is lossless
because it uses RELIABLE QoS and waits for the node's ack of each message
(measured here: 1.8 MB BEST_EFFORT images were dropped by Fast DDS whatever
the shared-memory profile, RELIABLE ones never).
"""
from __future__ import annotations

import os


def loopback_env(domain_id: int | None = None, base: dict | None = None) -> dict:
    """A copy of ``base`` (default: os.environ) set up for loopback-only DDS."""
    env = dict(os.environ if base is None else base)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)  # deprecated in Jazzy; the range above wins
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(int(domain_id))
    return env


def apply_loopback_env(domain_id: int | None = None) -> None:
    """Set :func:`loopback_env` in this process (call before rclpy.init)."""
    os.environ.update(loopback_env(domain_id))
