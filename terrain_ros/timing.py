"""Opt-in message timing trace: where a node's wall time per message goes.

With ``TERRAIN_TIMING_DIR=DIR`` in a node's environment, :func:`terrain_ros.node.run_node`
calls :func:`install` and every message the node takes, and every message it publishes, is
recorded (wall clock ``time.time()``, this process's CPU ``time.process_time()``) and written as
JSON lines to ``DIR/<node name>.<pid>.jsonl`` (one file per process, named after its first
node) when the node stops (and every
``FLUSH_EVERY`` records). A ``take`` record holds:

``topic``, ``stamp`` (the message header's stamp in s, or null), ``src`` / ``recv`` (the
middleware's source and reception timestamps, s since the epoch, 0 when the RMW gives none),
``t0`` / ``t1`` (wall around ``take_message``, i.e. deserialisation), ``t2`` / ``t3`` (wall
around the callback), ``take_cpu`` / ``cb_cpu`` (CPU s of the two), ``cb_runq`` (s the
node's thread waited on a CPU run queue during the callback, from ``/proc/thread-self/schedstat``:
runnable but another process had the core).

A ``pub`` record holds ``topic``, ``stamp``, ``t0`` / ``t1`` (wall around ``publish``, i.e.
serialisation and hand-over to the middleware) and ``cpu``.

``python -m terrain_ros.tools.timing_report DIR`` joins the files on (topic, stamp) and prints
per stage of the capture-to-plan chain: the queue wait before the take, deserialisation, the
callback's wall and CPU, and the publish. The trace costs a few microseconds per message; it
is for diagnosis, off by default.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

ENV_VAR = 'TERRAIN_TIMING_DIR'
#: the ~/diagnostics value of a node process's CPU time so far [ms] (terrain_ros.node.Counters)
CPU_KEY = 'process_cpu_ms'
PROFILE_ENV_VAR = 'TERRAIN_CPROFILE_DIR'
FLUSH_EVERY = 2000


def _run_delay() -> float:
    """Seconds this thread has waited on a run queue so far (/proc schedstat; 0 without)."""
    try:
        with open('/proc/thread-self/schedstat') as f:
            return int(f.read().split()[1]) * 1e-9
    except (OSError, ValueError, IndexError):
        return 0.0


def _stamp(msg: Any) -> Optional[float]:
    """The message's header stamp (or its own, for a std_msgs/Header) in s, else None."""
    stamp = getattr(getattr(msg, 'header', msg), 'stamp', None)
    if not hasattr(stamp, 'nanosec'):
        return None
    return round(stamp.sec + stamp.nanosec * 1e-9, 9)


class TimingTrace:
    """Buffered JSON-lines writer of take / publish records for one process."""

    def __init__(self, directory: Path, name: str) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.path = directory / f'{name}.{os.getpid()}.jsonl'
        self.records: List[Dict[str, Any]] = []
        self.closed = False
        atexit.register(self.flush)

    def add(self, rec: Dict[str, Any]) -> None:
        if self.closed:
            return
        self.records.append(rec)
        if len(self.records) >= FLUSH_EVERY:
            self.flush()

    def flush(self) -> None:
        if not self.records:
            return
        with open(self.path, 'a') as f:
            for r in self.records:
                f.write(json.dumps(r) + '\n')
        self.records = []


_TRACE: Optional[TimingTrace] = None
_ORIGINAL_TAKE = None


def install(node, directory: Optional[str] = None) -> Optional[TimingTrace]:
    """Trace ``node``'s takes and publishes if ``directory`` (default: $TERRAIN_TIMING_DIR)."""
    global _TRACE, _ORIGINAL_TAKE
    directory = directory or os.environ.get(ENV_VAR)
    if not directory:
        return None
    from rclpy.executors import Executor, await_or_execute
    from rclpy.subscription import Subscription
    from rclpy.exceptions import InvalidHandle

    if _TRACE is not None:   # one trace (one file) per process, named after its first node
        trace = _TRACE
    else:
        try:
            trace = _TRACE = TimingTrace(Path(directory), node.get_name())
        except OSError as exc:   # a diagnostic must not stop the node: run untraced
            node.get_logger().error(f'{ENV_VAR}={directory!r} unusable ({exc}); no timing '
                                    'trace')
            return None

    def _take_subscription(self, sub):  # mirrors rclpy's Executor._take_subscription (Jazzy)
        try:
            t0, c0 = time.time(), time.process_time()
            with sub.handle:
                msg_info = sub.handle.take_message(sub.msg_type, sub.raw)
            if msg_info is None:
                return None
            t1, c1 = time.time(), time.process_time()
            msg, info = msg_info[0], msg_info[1]
            args = (msg,) if sub._callback_type is Subscription.CallbackType.MessageOnly \
                else msg_info

            async def _execute():
                t2, c2, q2 = time.time(), time.process_time(), _run_delay()
                await await_or_execute(sub.callback, *args)
                t3, c3, q3 = time.time(), time.process_time(), _run_delay()
                trace.add({'k': 'take', 'topic': sub.topic_name,
                           'stamp': None if sub.raw else _stamp(msg),
                           'src': info.get('source_timestamp', 0) * 1e-9,
                           'recv': info.get('received_timestamp', 0) * 1e-9,
                           't0': t0, 't1': t1, 't2': t2, 't3': t3,
                           'take_cpu': c1 - c0, 'cb_cpu': c3 - c2, 'cb_runq': q3 - q2})
            return _execute
        except InvalidHandle:
            return None

    if _ORIGINAL_TAKE is None:
        _ORIGINAL_TAKE = Executor._take_subscription
    Executor._take_subscription = _take_subscription

    for pub in list(node.publishers):
        _wrap_publisher(pub, trace)
    original_create = node.create_publisher

    def create_publisher(*a, **kw):
        pub = original_create(*a, **kw)
        _wrap_publisher(pub, trace)
        return pub
    node.create_publisher = create_publisher
    return trace


def uninstall() -> None:
    """Flush the trace and give rclpy's executors their own take back (tests)."""
    global _TRACE, _ORIGINAL_TAKE
    if _TRACE is not None:
        _TRACE.flush()
        _TRACE.closed = True
        _TRACE = None
    if _ORIGINAL_TAKE is not None:
        from rclpy.executors import Executor
        Executor._take_subscription = _ORIGINAL_TAKE
        _ORIGINAL_TAKE = None


def _wrap_publisher(pub, trace: TimingTrace) -> None:
    publish = pub.publish
    topic = pub.topic_name

    def timed_publish(msg):
        t0, c0 = time.time(), time.process_time()
        publish(msg)
        trace.add({'k': 'pub', 'topic': topic, 'stamp': _stamp(msg), 't0': t0,
                   't1': time.time(), 'cpu': time.process_time() - c0})
    pub.publish = timed_publish


@contextlib.contextmanager
def profiled(node, directory: Optional[str] = None):
    """cProfile the body (a node's spin) if ``directory`` (default: $TERRAIN_CPROFILE_DIR);
    the stats go to ``DIR/<node name>.<pid>.prof`` (``python -m pstats`` reads them)."""
    directory = directory or os.environ.get(PROFILE_ENV_VAR)
    if not directory:
        yield
        return
    import cProfile
    Path(directory).mkdir(parents=True, exist_ok=True)
    prof = cProfile.Profile()
    prof.enable()
    try:
        yield
    finally:
        prof.disable()
        prof.dump_stats(str(Path(directory) / f'{node.get_name()}.{os.getpid()}.prof'))
