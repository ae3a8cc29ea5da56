"""``terrain-topic``: what ``ros2 topic`` does for the common cases (the ros2 CLI has no wheel).

    terrain-topic list [-t]
    terrain-topic info TOPIC [-v]
    terrain-topic hz TOPIC [--window N] [--duration S]
    terrain-topic echo TOPIC [--once] [--count N] [--field a.b] [--full-arrays]

Discovery stays on this host unless ROS_AUTOMATIC_DISCOVERY_RANGE says otherwise.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import deque

from terrain_ros.env import apply_safe_defaults
from terrain_ros.tools.common import (ToolError, fail, message_class, msg_to_plain,
                                      qos_matching_publishers, to_yaml, wait_for_topic)

PROG = 'terrain-topic'


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0])
    p.add_argument('--spin-time', type=float, default=2.5,
                   help='seconds to wait for discovery before answering (default 2.5; '
                        'localhost discovery can take ~2 s)')
    sub = p.add_subparsers(dest='cmd', required=True)
    ls = sub.add_parser('list', help='list the topics in the graph')
    ls.add_argument('-t', '--show-types', action='store_true', help='also print each type')
    info = sub.add_parser('info', help='type and endpoints of a topic')
    info.add_argument('topic')
    info.add_argument('-v', '--verbose', action='store_true', help='node names and QoS too')
    hz = sub.add_parser('hz', help='publishing rate of a topic')
    hz.add_argument('topic')
    hz.add_argument('-w', '--window', type=int, default=10000,
                    help='rolling window of intervals (default 10000)')
    hz.add_argument('--duration', type=float, default=None,
                    help='stop after this many seconds (default: until Ctrl-C)')
    echo = sub.add_parser('echo', help='print the messages of a topic')
    echo.add_argument('topic')
    echo.add_argument('--once', action='store_true', help='print one message and exit')
    echo.add_argument('--count', type=int, default=0, help='exit after this many messages')
    echo.add_argument('--field', default=None, help='print only this field (a.b.c)')
    echo.add_argument('--full-arrays', action='store_true',
                      help='print arrays in full (default: first 16 items)')
    echo.add_argument('--timeout', type=float, default=None,
                      help='exit with an error if nothing arrives in this many seconds')
    return p


def _fmt_qos(q) -> str:
    return (f'reliability={q.reliability.name} durability={q.durability.name} '
            f'history={q.history.name} depth={q.depth}')


def _list(node, args) -> int:
    for name, types in sorted(node.get_topic_names_and_types()):
        print(f'{name} [{", ".join(types)}]' if args.show_types else name)
    return 0


def _info(node, args) -> int:
    type_name = wait_for_topic(node, args.topic, args.spin_time, need_publisher=False)
    pubs = node.get_publishers_info_by_topic(args.topic)
    subs = node.get_subscriptions_info_by_topic(args.topic)
    print(f'Type: {type_name}')
    print(f'Publisher count: {len(pubs)}')
    print(f'Subscription count: {len(subs)}')
    if args.verbose:
        for kind, infos in (('Publisher', pubs), ('Subscription', subs)):
            for i in infos:
                print(f'  {kind}: node {i.node_namespace.rstrip("/")}/{i.node_name} '
                      f'{_fmt_qos(i.qos_profile)}')
    return 0


def _spin_until(executor, done, end_time=None) -> None:
    while not done():
        if end_time is not None and time.monotonic() >= end_time:
            return
        executor.spin_once(timeout_sec=0.05)


def _hz(node, executor, args) -> int:
    type_name = wait_for_topic(node, args.topic, args.spin_time)
    cls = message_class(type_name)
    stamps: deque = deque(maxlen=max(2, args.window + 1))
    node.create_subscription(cls, args.topic, lambda _m: stamps.append(time.monotonic()),
                             qos_matching_publishers(node, args.topic), raw=True)
    start = time.monotonic()
    end = start + args.duration if args.duration else None
    next_report = start + 1.0
    reported = False
    while end is None or time.monotonic() < end:
        executor.spin_once(timeout_sec=0.02)
        now = time.monotonic()
        if now >= next_report:
            next_report = now + 1.0
            reported |= _report_rate(stamps)
    if not _report_rate(stamps) and not reported:
        raise ToolError(f'no messages received on {args.topic!r} in {args.duration:.1f} s')
    return 0


def _report_rate(stamps) -> bool:
    if len(stamps) < 2:
        return False
    ts = list(stamps)
    dts = [b - a for a, b in zip(ts, ts[1:])]
    mean = sum(dts) / len(dts)
    std = math.sqrt(sum((d - mean) ** 2 for d in dts) / len(dts))
    print(f'average rate: {1.0 / mean:.3f}\n'
          f'\tmin: {min(dts):.3f}s max: {max(dts):.3f}s std dev: {std:.5f}s '
          f'window: {len(dts)}', flush=True)
    return True


def _echo(node, executor, args) -> int:
    # With --timeout the topic may also take that long to appear (slow discovery, late start).
    type_name = wait_for_topic(node, args.topic, max(args.spin_time, args.timeout or 0.0))
    cls = message_class(type_name)
    want = 1 if args.once else args.count
    got = []

    def on_msg(msg) -> None:
        value = msg
        if args.field:
            for part in args.field.split('.'):
                if not hasattr(value, part):
                    raise ToolError(f'{type_name} has no field {args.field!r}')
                value = getattr(value, part)
        plain = msg_to_plain(value, 0 if args.full_arrays else 16)
        print(to_yaml(plain) if isinstance(plain, (dict, list)) else plain)
        print('---', flush=True)
        got.append(1)

    node.create_subscription(cls, args.topic, on_msg, qos_matching_publishers(node, args.topic))
    end = time.monotonic() + args.timeout if args.timeout else None
    _spin_until(executor, lambda: want and len(got) >= want, end)
    if not got and args.timeout:
        raise ToolError(f'no message received on {args.topic!r} in {args.timeout:.1f} s')
    return 0


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    apply_safe_defaults()
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from rclpy.executors import SingleThreadedExecutor
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)  # Ctrl-C -> KeyboardInterrupt
    node = rclpy.create_node('terrain_topic', start_parameter_services=False)
    executor = SingleThreadedExecutor()
    try:
        if args.cmd == 'list':
            time.sleep(args.spin_time)  # the graph cache fills in the background
            return _list(node, args)
        if args.cmd == 'info':
            return _info(node, args)
        executor.add_node(node)
        if args.cmd == 'hz':
            return _hz(node, executor, args)
        return _echo(node, executor, args)
    except ToolError as exc:
        return fail(PROG, exc)
    except KeyboardInterrupt:
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
