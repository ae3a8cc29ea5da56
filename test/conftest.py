"""Shared pytest fixtures. Every ROS process a test starts stays on this host.

* ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` always (never the default multicast range).
* A ``ROS_DOMAIN_ID`` of this test session's own (set before anything creates a context), so
  parallel test runs and other ROS traffic on the machine do not mix. Subprocesses inherit both.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_DOMAIN_ID', str(20 + os.getpid() % 70))
import terrain_ros  # noqa: E402,F401  (applies the Fast DDS profile default)

DATA_DIR = Path(__file__).parent / 'data'


@pytest.fixture
def ros_context():
    """An initialised private rclpy Context on this session's domain; shut down afterwards."""
    import rclpy
    from rclpy.context import Context
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(os.environ['ROS_DOMAIN_ID']))
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def executor(ros_context):
    """A single-threaded executor on the private context (nodes are removed at teardown)."""
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=ros_context)
    yield ex
    for node in list(ex.get_nodes()):
        ex.remove_node(node)
        node.destroy_node()
    ex.shutdown()


def spin_until(executor, predicate, timeout_s: float = 5.0, step_s: float = 0.02) -> bool:
    """Spin ``executor`` until ``predicate()`` is true or ``timeout_s`` passes; return the result."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=step_s)
    return bool(predicate())
