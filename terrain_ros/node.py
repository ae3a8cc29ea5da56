"""Helpers every node shares: the Jazzy ``main()`` idiom (and its executor) and counted,
rate-limited bad-input logs."""

from __future__ import annotations

import os
import sys
import time
from collections import Counter
from typing import Callable, Dict, Optional, Type

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from terrain_ros import timing
from terrain_ros.env import apply_safe_defaults
from terrain_ros.qos import RELIABLE_QOS


def now_s(node: Node) -> float:
    """The node's clock (simulated time with ``use_sim_time``) in seconds."""
    return node.get_clock().now().nanoseconds * 1e-9


EXECUTOR_ENV_VAR = 'TERRAIN_EXECUTOR'


def make_executor(context=None, kind: Optional[str] = None):
    """The executor a node process spins: ``kind`` (default ``$TERRAIN_EXECUTOR``, else
    ``events``) ``events`` is rclpy's EventsExecutor (Jazzy: ``rclpy.experimental``; falls back
    to the single-threaded one where missing), ``single`` the classic SingleThreadedExecutor.

    Why events: the classic executor rebuilds its wait set in Python before every callback.
    Under simulated time a node handles ~20 ``/clock``, joint-state, IMU and odometry messages
    per wall second besides its real work (the ICP mapper: ~13k wait-set rebuilds in a 125 s
    loop), CPU taken from the two cores the capture-to-plan chain runs on. The EventsExecutor
    queues the middleware's events in C++ and runs simulated-time timers from clock jumps; in
    50 s loop trials the nodes' CPU fell from 236-258 to 173-212 s (docs/CLOSED_LOOP.md,
    session 50). Both run every callback on the spinning thread."""
    kind = (kind or os.environ.get(EXECUTOR_ENV_VAR) or 'events').strip().lower()
    if kind not in ('events', 'single'):
        raise ValueError(f'{EXECUTOR_ENV_VAR}={kind!r}: use events or single')
    if kind == 'events':
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor(context=context)
        except (ImportError, TypeError):
            pass
    from rclpy.executors import SingleThreadedExecutor
    return SingleThreadedExecutor(context=context)


def run_node(node_cls: Type[Node], args=None, **kwargs) -> int:
    """Create ``node_cls`` and spin it until Ctrl-C / shutdown; the Jazzy idiom, with the
    executor of :func:`make_executor` (the timing trace, ``TERRAIN_TIMING_DIR``, hooks the
    classic executor's takes: with it the node spins the single-threaded one).

    A configuration error at start-up (``ValueError``, e.g. a refused parameter) is printed as
    one line and gives exit code 2 instead of a traceback.
    """
    apply_safe_defaults()
    rclpy.init(args=args)
    node = None
    executor = None
    try:
        node = node_cls(**kwargs)
        traced = timing.install(node) is not None
        executor = make_executor(kind='single' if traced else None)
        executor.add_node(node)
        with timing.profiled(node):
            # spin_once with a timeout, not spin(): the EventsExecutor's spin() stays in C++
            # through SIGINT/SIGTERM; this returns to Python (and its signal handling) at
            # least every 0.1 s and ends when a signal has shut the context down
            while rclpy.ok(context=node.context):
                executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:
        print(f'{node_cls.__name__}: {exc}', file=sys.stderr)
        return 2
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


class Counters:
    """Named counters of dropped / rejected input, logged once per reason and published.

    ``bump(key, reason)`` counts an event; the first occurrence of each key is logged as a
    warning with its reason, later ones every ``log_every`` occurrences. ``publish()`` sends a
    ``diagnostic_msgs/DiagnosticArray`` on ``~/diagnostics``: the counters and, as the value
    ``process_cpu_ms`` (not a counter: it does not raise the level), the CPU this process has
    used so far (all its threads), which the closed-loop report gives per node.
    """

    def __init__(self, node: Node, log_every: int = 100,
                 publish_topic: Optional[str] = '~/diagnostics') -> None:
        self._node = node
        self._log_every = max(1, int(log_every))
        self.counts: Counter = Counter()
        self.last_reason: Dict[str, str] = {}
        self._pub = (node.create_publisher(DiagnosticArray, publish_topic, RELIABLE_QOS)
                     if publish_topic else None)

    def bump(self, key: str, reason: str = '', level: Callable | None = None) -> None:
        self.counts[key] += 1
        self.last_reason[key] = reason
        n = self.counts[key]
        if n == 1 or n % self._log_every == 0:
            suffix = '' if n == 1 else f' ({n} times so far)'
            self._log(level, f'{key}: {reason}{suffix}')

    def _log(self, level: Callable | None, text: str) -> None:
        # One call site per severity: rclpy fixes the severity of each call site at its first
        # call and raises on another ('Logger severity cannot be changed between calls'), so
        # a node whose counters logged an error once died at its next warning.
        name = getattr(level, '__name__', 'warning') if level is not None else 'warning'
        logger = self._node.get_logger()
        if name == 'error':
            logger.error(text)
        elif name == 'fatal':
            logger.fatal(text)
        elif name == 'info':
            logger.info(text)
        elif name == 'debug':
            logger.debug(text)
        else:
            logger.warning(text)

    def __getitem__(self, key: str) -> int:
        return self.counts[key]

    def publish(self) -> None:
        if self._pub is None:
            return
        status = DiagnosticStatus(name=self._node.get_fully_qualified_name(),
                                  level=DiagnosticStatus.OK if not self.counts
                                  else DiagnosticStatus.WARN,
                                  message=', '.join(f'{k}={v}' for k, v in
                                                    sorted(self.counts.items())) or 'ok')
        status.values = [KeyValue(key=k, value=str(v)) for k, v in sorted(self.counts.items())]
        status.values.append(KeyValue(key=timing.CPU_KEY,
                                      value=str(int(1000 * time.process_time()))))
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)
