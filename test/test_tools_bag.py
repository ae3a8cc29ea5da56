"""terrain-bag and terrain-topic as a user runs them: separate processes, real bags."""

from __future__ import annotations

import math
import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rclpy.serialization import deserialize_message

from terrain_ros.tools.common import message_class, msg_to_plain

import tools_fixture

pytestmark = pytest.mark.graph
HERE = Path(__file__).parent
BIN = Path(sys.executable).parent
N = 10


def _run(*cmd, timeout=60, **kw):
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True,
                          timeout=timeout, **kw)


def _popen(*cmd, **kw):
    return subprocess.Popen([str(c) for c in cmd], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def _same(a, b) -> bool:
    """Equality of plain message trees where NaN equals NaN (NaN marks unknown grid cells)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def _record(bag: Path, storage: str, **popen_kw) -> None:
    rec = _popen(BIN / 'terrain-bag', 'record', '-o', bag, '--storage', storage,
                 *tools_fixture.TOPICS, **popen_kw)
    pub = _popen(sys.executable, HERE / 'tools_fixture.py', 'pub', N)
    assert pub.wait(timeout=60) == 0, pub.stderr.read()
    rec.send_signal(signal.SIGINT)
    try:
        out, err = rec.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        rec.kill()          # leave no recorder behind
        out, err = rec.communicate()
        pytest.fail(f'terrain-bag record did not stop within 30 s of SIGINT: {err[-500:]}')
    assert rec.returncode == 0, err
    assert f'wrote {N * len(tools_fixture.TOPICS)} messages' in out, out + err


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_record_then_play_delivers_the_same_content(tmp_path, storage):
    bag = tmp_path / 'bag'
    _record(bag, storage)
    info = _run(BIN / 'terrain-bag', 'info', bag)
    assert info.returncode == 0 and f'Messages:          {N * 5}' in info.stdout
    assert ('.mcap' if storage == 'mcap' else '.db3') in info.stdout

    out = tmp_path / 'got.pkl'
    recv = _popen(sys.executable, HERE / 'tools_fixture.py', 'recv', out, N)
    assert recv.stdout.readline().strip() == 'ready'
    play = _run(BIN / 'terrain-bag', 'play', bag, '--rate', '2.0', '--delay', '0.5',
                '--wait-for-subscribers', '1')
    assert play.returncode == 0, play.stderr
    recv.wait(timeout=60)
    got = pickle.loads(out.read_bytes())
    for topic, type_name in tools_fixture.TOPICS.items():
        cls = message_class(type_name)
        # Compare messages, not bytes: CDR padding bytes are not defined.
        received = [deserialize_message(raw, cls) for raw in got[topic]]
        expected = [tools_fixture.make_messages(i)[topic] for i in range(N)]
        assert len(received) == N, f'{topic}: {len(received)} of {N} messages arrived'
        for r, e in zip(received, expected):
            assert _same(msg_to_plain(r, 0), msg_to_plain(e, 0)), f'{topic}: content differs'


def test_record_stops_on_sigint_when_started_with_it_ignored(tmp_path):
    # A background job of a non-interactive shell (`cmd &` in a script) starts with SIGINT
    # ignored; Ctrl-C / kill -INT must still close the bag.
    bag = tmp_path / 'bag'
    _record(bag, 'mcap', preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    info = _run(BIN / 'terrain-bag', 'info', bag)
    assert info.returncode == 0 and f'Messages:          {N * 5}' in info.stdout, info.stdout


def test_play_topic_filter_and_timing(tmp_path):
    bag = tmp_path / 'bag'
    _record(bag, 'mcap')
    out = tmp_path / 'got.pkl'
    recv = _popen(sys.executable, HERE / 'tools_fixture.py', 'recv', out, N)
    recv.stdout.readline()
    t0 = time.monotonic()
    play = _run(BIN / 'terrain-bag', 'play', bag, '--topics', '/imu/data', '--delay', '0.5',
                '--rate', '0.5', '--wait-for-subscribers', '1')
    wall = time.monotonic() - t0
    assert play.returncode == 0, play.stderr
    recv.terminate()
    recv.wait(timeout=30)
    # 10 messages recorded ~0.05 s apart (plus publishing time), played at half speed.
    assert wall > 0.5 + 2 * 9 * 0.05 * 0.9


def _hz_pub(rate: float):
    code = ('import rclpy\nfrom std_msgs.msg import String\nrclpy.init()\n'
            'n = rclpy.create_node("hz_pub")\np = n.create_publisher(String, "/hz_test", 10)\n'
            f'n.create_timer({1.0 / rate}, lambda: p.publish(String(data="x")))\n'
            'rclpy.spin(n)\n')
    return _popen(sys.executable, '-c', code)


def test_topic_hz_reports_20hz_within_5_percent():
    pub = _hz_pub(20.0)
    try:
        res = _run(BIN / 'terrain-topic', '--spin-time', '10', 'hz', '/hz_test',
                   '--duration', '5')
        assert res.returncode == 0, res.stderr
        rates = [float(line.split(':')[1]) for line in res.stdout.splitlines()
                 if line.startswith('average rate')]
        assert rates and abs(rates[-1] - 20.0) <= 1.0, res.stdout
        listing = _run(BIN / 'terrain-topic', '--spin-time', '5', 'list', '-t')
        assert '/hz_test [std_msgs/msg/String]' in listing.stdout
        info = _run(BIN / 'terrain-topic', '--spin-time', '5', 'info', '/hz_test')
        assert 'Type: std_msgs/msg/String' in info.stdout and 'Publisher count: 1' in info.stdout
        echo = _run(BIN / 'terrain-topic', 'echo', '/hz_test', '--once', '--timeout', '10')
        assert echo.returncode == 0 and 'data: x' in echo.stdout
    finally:
        pub.kill()
        pub.wait()


def _one_error_line(res, *needles):
    assert res.returncode != 0
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def test_echo_missing_topic_is_one_clear_error():
    res = _run(BIN / 'terrain-topic', 'echo', '/does_not_exist', '--once')
    _one_error_line(res, '/does_not_exist', 'does not exist')


def test_record_into_unwritable_directory(tmp_path):
    locked = tmp_path / 'locked'
    locked.mkdir()
    locked.chmod(0o500)
    if os.access(locked, os.W_OK):  # root ignores permission bits: use a path under a file
        target = tmp_path / 'a_file' / 'bag'
        (tmp_path / 'a_file').write_text('x')
    else:
        target = locked / 'bag'
    res = _run(BIN / 'terrain-bag', 'record', '-o', target, '/imu/data', timeout=30)
    _one_error_line(res, 'cannot create bag', str(target))


def test_record_refuses_existing_output_and_keeps_it(tmp_path):
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'keep.txt').write_text('precious')
    res = _run(BIN / 'terrain-bag', 'record', '-o', bag, '/imu/data', timeout=30)
    _one_error_line(res, 'already exists')
    assert (bag / 'keep.txt').read_text() == 'precious'


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_play_truncated_or_corrupt_bag(tmp_path, storage):
    bag = tmp_path / 'bag'
    _record(bag, storage)
    data = next(p for p in bag.iterdir() if p.suffix in ('.mcap', '.db3'))
    raw = data.read_bytes()
    data.write_bytes(raw[: len(raw) // 2])
    res = _run(BIN / 'terrain-bag', 'play', bag, '--delay', '0')
    _one_error_line(res, 'cannot read bag', str(bag))
    garbage = tmp_path / 'garbage'
    garbage.mkdir()
    (garbage / 'metadata.yaml').write_text(': not yaml : [')
    _one_error_line(_run(BIN / 'terrain-bag', 'play', garbage), 'cannot read bag')


def test_play_unknown_message_type(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg('float64 value', 'mystery_msgs/msg/Thing'))
    bag = tmp_path / 'bag'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/thing', 'mystery_msgs/msg/Thing', typestore=store)
        msg = store.types['mystery_msgs/msg/Thing'](value=1.0)
        w.write(conn, 1, store.serialize_cdr(msg, 'mystery_msgs/msg/Thing'))
    res = _run(BIN / 'terrain-bag', 'play', bag, '--delay', '0')
    _one_error_line(res, 'mystery_msgs/msg/Thing', '/thing')
