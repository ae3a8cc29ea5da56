"""``terrain-bag``: rosbag2 record / play / info through the ``rosbags`` library.

    terrain-bag record -o DIR TOPIC... | -a   [--storage mcap|sqlite3] [--duration S]
    terrain-bag play DIR [--rate R] [--loop] [--topics T...] [--clock [HZ]] [--delay S]
    terrain-bag info DIR

Bags are real rosbag2 directories (metadata.yaml + .mcap or .db3): ``ros2 bag`` reads ours and we
read its. Recording stores the serialized bytes as received (no re-encoding), standard and
project (terrain_msgs) types alike; Ctrl-C closes the bag cleanly with every message received.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Dict, List

from terrain_ros.env import apply_safe_defaults
from terrain_ros.tools.common import (ToolError, fail, message_class, qos_matching_publishers,
                                      typestore_with)

PROG = 'terrain-bag'
# Topics a `record -a` leaves out: per-node service chatter, not data.
_SKIP_ALL = ('/parameter_events',)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0])
    sub = p.add_subparsers(dest='cmd', required=True)
    rec = sub.add_parser('record', help='record topics into a new bag directory')
    rec.add_argument('topics', nargs='*', help='topics to record')
    rec.add_argument('-a', '--all', action='store_true', help='record every topic seen')
    rec.add_argument('-o', '--output', default=None,
                     help='bag directory to create (default rosbag2_<date>)')
    rec.add_argument('-s', '--storage', choices=('mcap', 'sqlite3'), default='mcap',
                     help='storage format (default mcap)')
    rec.add_argument('--duration', type=float, default=None,
                     help='stop after this many seconds (default: until Ctrl-C)')
    rec.add_argument('--max-messages', type=int, default=0,
                     help='stop after this many messages (default: no limit)')
    play = sub.add_parser('play', help='publish the messages of a bag with their timing')
    play.add_argument('bag')
    play.add_argument('-r', '--rate', type=float, default=1.0, help='rate factor (default 1)')
    play.add_argument('-l', '--loop', action='store_true', help='play again and again')
    play.add_argument('--topics', nargs='+', default=None, help='only these topics')
    play.add_argument('--clock', nargs='?', type=float, const=40.0, default=None,
                      metavar='HZ', help='publish /clock with the bag time (default 40 Hz)')
    play.add_argument('-d', '--delay', type=float, default=0.5,
                      help='seconds between creating the publishers and the first message, '
                           'for discovery (default 0.5)')
    play.add_argument('--wait-for-subscribers', type=int, default=0, metavar='N',
                      help='before playing, wait (up to 30 s) until every topic has N '
                           'subscribers (for scripted replays; default 0 = do not wait)')
    info = sub.add_parser('info', help='summary of a bag')
    info.add_argument('bag')
    return p


# ---------------------------------------------------------------------------------------------
# record


def _to_rosbags_qos(q):
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)

    def t(d):
        ns = int(d.nanoseconds) if d is not None else 0
        return QosTime(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)
    return Qos(history=QosHistory(int(q.history)), depth=int(q.depth),
               reliability=QosReliability(int(q.reliability)),
               durability=QosDurability(int(q.durability)),
               deadline=t(q.deadline), lifespan=t(q.lifespan),
               liveliness=QosLiveliness(int(q.liveliness)),
               liveliness_lease_duration=t(q.liveliness_lease_duration),
               avoid_ros_namespace_conventions=False)


def _check_output(path: Path) -> None:
    if path.exists():
        raise ToolError(f'output {str(path)!r} already exists; choose a new bag directory')
    parent = path.resolve().parent
    if not parent.is_dir():
        raise ToolError(f'cannot create bag {str(path)!r}: directory {str(parent)!r} '
                        'does not exist')
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ToolError(f'cannot create bag {str(path)!r}: directory {str(parent)!r} '
                        'is not writable')


def _interrupt(*_args) -> None:
    raise KeyboardInterrupt


def _record(args) -> int:
    from rosbags.rosbag2 import StoragePlugin, Writer
    if not args.all and not args.topics:
        raise ToolError('name topics to record, or -a for all')
    out = Path(args.output or datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S'))
    _check_output(out)
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from rclpy.executors import SingleThreadedExecutor
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)  # Ctrl-C -> KeyboardInterrupt
    node = rclpy.create_node('terrain_bag_record', start_parameter_services=False)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    storage = StoragePlugin.MCAP if args.storage == 'mcap' else StoragePlugin.SQLITE3
    writer = Writer(out, version=9, storage_plugin=storage)
    try:
        writer.open()
    except Exception as exc:  # rosbags raises its own WriterError / OSError
        raise ToolError(f'cannot create bag {str(out)!r}: {exc}') from None
    wanted = {t if t.startswith('/') else '/' + t for t in args.topics}
    connections: Dict[str, object] = {}
    subs = []
    counts: Dict[str, int] = {}
    total = [0]
    write_error: List[BaseException] = []

    def subscribe_new() -> None:
        for topic, types in node.get_topic_names_and_types():
            if topic in connections or node.count_publishers(topic) == 0:
                continue
            if not args.all and topic not in wanted:
                continue
            if args.all and topic in _SKIP_ALL:
                continue
            type_name = types[0]
            try:
                cls = message_class(type_name)
                store = typestore_with([type_name])
            except ToolError as exc:
                print(f'{PROG}: warning: not recording {topic}: {exc}', file=sys.stderr)
                connections[topic] = None
                continue
            offered = [_to_rosbags_qos(i.qos_profile)
                       for i in node.get_publishers_info_by_topic(topic)]
            conn = writer.add_connection(topic, type_name, typestore=store,
                                         offered_qos_profiles=offered)
            connections[topic] = conn
            counts[topic] = 0

            def on_msg(data: bytes, conn=conn, topic=topic) -> None:
                if write_error:
                    return
                try:
                    writer.write(conn, time.time_ns(), data)
                except Exception as exc:  # disk full, removed directory...
                    write_error.append(exc)
                    return
                counts[topic] += 1
                total[0] += 1
            subs.append(node.create_subscription(
                cls, topic, on_msg, qos_matching_publishers(node, topic, depth=1000), raw=True))
            print(f'{PROG}: recording {topic} [{type_name}]', flush=True)

    # SIGTERM closes the bag like Ctrl-C does. SIGINT gets the same handler explicitly: a
    # process started as a background job of a non-interactive shell inherits SIGINT ignored,
    # and Python then installs no KeyboardInterrupt for it (ros2 bag record handles it itself too).
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    end = time.monotonic() + args.duration if args.duration else None
    next_scan = 0.0
    try:
        while end is None or time.monotonic() < end:
            if time.monotonic() >= next_scan:
                subscribe_new()
                next_scan = time.monotonic() + 0.5
            executor.spin_once(timeout_sec=0.05)
            if write_error:
                raise ToolError(f'writing to {str(out)!r} failed: {write_error[0]}')
            if args.max_messages and total[0] >= args.max_messages:
                break
    except KeyboardInterrupt:
        pass
    finally:
        for s in subs:
            node.destroy_subscription(s)
        writer.close()
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'{PROG}: wrote {total[0]} messages on {len(counts)} topics to {out}', flush=True)
    return 0


# ---------------------------------------------------------------------------------------------
# play / info


def open_reader(path):
    """An opened rosbags Reader of the bag directory ``path``; ToolError (one line) if it is
    missing or unreadable."""
    from rosbags.rosbag2 import Reader
    p = Path(path)
    if not p.exists():
        raise ToolError(f'bag {str(path)!r} does not exist')
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:  # ReaderError, yaml errors, missing metadata, truncated files
        text = ' '.join(str(exc).split())
        raise ToolError(f'cannot read bag {str(path)!r}: {text}') from None
    return reader


def _publisher_qos(conn):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    qos = QoSProfile(depth=100)
    offered = list(getattr(conn.ext, 'offered_qos_profiles', []) or [])
    if offered and all(q.durability.value == int(DurabilityPolicy.TRANSIENT_LOCAL)
                       for q in offered):
        qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
    if offered and all(q.reliability.value == int(ReliabilityPolicy.BEST_EFFORT)
                       for q in offered):
        qos.reliability = ReliabilityPolicy.BEST_EFFORT
    return qos


def _play(args) -> int:
    if args.rate <= 0:
        raise ToolError(f'--rate must be positive, got {args.rate}')
    reader = open_reader(args.bag)
    conns = list(reader.connections)
    if args.topics:
        wanted = {t if t.startswith('/') else '/' + t for t in args.topics}
        missing = wanted - {c.topic for c in conns}
        if missing:
            raise ToolError(f'bag {args.bag!r} has no topic(s) {sorted(missing)}')
        conns = [c for c in conns if c.topic in wanted]
    classes = {}
    for c in conns:
        try:
            classes[c.id] = message_class(c.msgtype)
        except ToolError as exc:
            raise ToolError(f'bag topic {c.topic}: {exc}') from None
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from rosgraph_msgs.msg import Clock
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)  # Ctrl-C -> KeyboardInterrupt
    node = rclpy.create_node('terrain_bag_play', start_parameter_services=False)
    pubs = {}
    for c in conns:
        if c.topic not in {p.topic_name for p in pubs.values()}:
            pubs[c.id] = node.create_publisher(classes[c.id], c.topic, _publisher_qos(c))
        else:
            pubs[c.id] = next(p for p in pubs.values() if p.topic_name == c.topic)
    clock_pub = node.create_publisher(Clock, '/clock', 10) if args.clock else None
    if args.wait_for_subscribers > 0:
        deadline = time.monotonic() + 30.0
        while any(p.get_subscription_count() < args.wait_for_subscribers
                  for p in pubs.values()):
            if time.monotonic() > deadline:
                raise ToolError(f'fewer than {args.wait_for_subscribers} subscriber(s) on '
                                f'{sorted({p.topic_name for p in pubs.values() if p.get_subscription_count() < args.wait_for_subscribers})} after 30 s')
            time.sleep(0.05)
    time.sleep(max(0.0, args.delay))
    sent = 0
    try:
        while True:
            wall0, bag0 = time.monotonic(), None
            next_clock = 0.0
            try:
                for conn, t_ns, data in reader.messages(connections=conns):
                    if bag0 is None:
                        bag0 = t_ns
                    due = wall0 + (t_ns - bag0) * 1e-9 / args.rate
                    while True:
                        now = time.monotonic()
                        if clock_pub is not None and now >= next_clock:
                            bag_now = bag0 + int((now - wall0) * args.rate * 1e9)
                            clock_pub.publish(_clock_msg(min(bag_now, t_ns)))
                            next_clock = now + 1.0 / args.clock
                        if now >= due:
                            break
                        wait = due - now
                        if clock_pub is not None:
                            wait = min(wait, next_clock - now)
                        time.sleep(max(wait, 0.0005))
                    if clock_pub is not None:
                        clock_pub.publish(_clock_msg(t_ns))
                    pubs[conn.id].publish(bytes(data))
                    sent += 1
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # corrupt chunk, truncated file
                raise ToolError(f'cannot read bag {args.bag!r} after {sent} messages: '
                                f'{exc}') from None
            if not args.loop:
                break
        # Give reliable subscribers a moment to receive the tail before the publishers go.
        time.sleep(0.3)
    except KeyboardInterrupt:
        pass
    finally:
        reader.close()
        node.destroy_node()
        rclpy.try_shutdown()
    print(f'{PROG}: played {sent} messages from {args.bag}', flush=True)
    return 0


def _clock_msg(t_ns: int):
    from builtin_interfaces.msg import Time
    from rosgraph_msgs.msg import Clock
    return Clock(clock=Time(sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000)))


def _info(args) -> int:
    reader = open_reader(args.bag)
    try:
        files = sorted(p.name for p in Path(args.bag).iterdir() if p.suffix in ('.mcap', '.db3'))
        size = sum(p.stat().st_size for p in Path(args.bag).iterdir() if p.is_file())
        start, end = reader.start_time, reader.end_time
        dur = max(0, end - start) * 1e-9 if reader.message_count else 0.0
        storage = 'mcap' if any(f.endswith('.mcap') for f in files) else 'sqlite3'
        print(f'Files:             {", ".join(files)}')
        print(f'Bag size:          {size / 1e6:.2f} MB')
        print(f'Storage id:        {storage}')
        print(f'Duration:          {dur:.3f}s')
        if reader.message_count:
            print(f'Start:             {datetime.fromtimestamp(start * 1e-9)} ({start * 1e-9:.3f})')
            print(f'End:               {datetime.fromtimestamp(end * 1e-9)} ({end * 1e-9:.3f})')
        print(f'Messages:          {reader.message_count}')
        print('Topic information:')
        for c in reader.connections:
            print(f'  Topic: {c.topic} | Type: {c.msgtype} | Count: {c.msgcount} | '
                  f'Serialization Format: {c.ext.serialization_format}')
    finally:
        reader.close()
    return 0


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    apply_safe_defaults()
    try:
        if args.cmd == 'record':
            return _record(args)
        if args.cmd == 'play':
            return _play(args)
        return _info(args)
    except ToolError as exc:
        return fail(PROG, exc)
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
