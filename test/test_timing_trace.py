"""The opt-in message timing trace (terrain_ros.timing) and its report (tools.timing_report)."""

import json

import pytest
from conftest import spin_until

from terrain_ros import timing
from terrain_ros.tools import timing_report


def _take(topic, stamp, t0, t2, t3, cpu=0.01):
    return {'k': 'take', 'topic': topic, 'stamp': stamp, 'src': 0.0, 'recv': 0.0,
            't0': t0, 't1': t0 + 0.001, 't2': t2, 't3': t3, 'take_cpu': 0.001,
            'cb_cpu': cpu, 'cb_runq': 0.0}


def _pub(topic, stamp, t0, t1):
    return {'k': 'pub', 'topic': topic, 'stamp': stamp, 't0': t0, 't1': t1, 'cpu': 0.0}


def test_report_splits_each_stage_into_wait_take_callback_and_publish(tmp_path):
    # One capture (stamp 5.0) through the chain with known times [s].
    recs = {
        'sim_bridge': [_pub('/stereo/left/image_rect', 5.0, 10.000, 10.001)],
        # stereo: the pair completes on the right image; the cloud is published 40 ms in
        'stereo_node': [_take('/stereo/left/image_rect', 5.0, 10.003, 10.004, 10.0041),
                        _take('/stereo/right/image_rect', 5.0, 10.005, 10.006, 10.080, 0.05),
                        _pub('/stereo/points', 5.0, 10.046, 10.050)],
        'icp_mapper': [_take('/stereo/points', 5.0, 10.060, 10.062, 10.150),
                       _pub('/map/fine', 5.0, 10.120, 10.121)],
        'terrain_fill': [_take('/map/fine', 5.0, 10.125, 10.126, 10.1261),
                         _take('/map/capture_poses', 5.0, 10.127, 10.128, 10.200),
                         _pub('/map/filled', 5.0, 10.190, 10.192)],
        'footstep_planner': [_take('/map/filled', 5.0, 10.193, 10.195, 10.260),
                             _pub('/footstep_plan', 5.0, 10.250, 10.251),
                             # another stamp's publish must not join this capture
                             _pub('/footstep_plan', 6.0, 10.255, 10.256)],
    }
    for node, rs in recs.items():
        (tmp_path / f'{node}.1.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in rs))
    parts = timing_report.stage_parts(timing_report.load(tmp_path))
    st = {k: {p: v[0] for p, v in d.items()} for k, d in parts.items()}
    assert st['stereo']['wait'] == pytest.approx(4.0)      # 10.001 -> right take at 10.005
    assert st['stereo']['cb'] == pytest.approx(40.0)       # 10.006 -> publish at 10.046
    assert st['stereo']['cb_cpu'] == pytest.approx(50.0)
    assert st['stereo']['stage'] == pytest.approx(49.0)    # 10.001 -> 10.050
    assert st['icp_mapper']['wait'] == pytest.approx(10.0)
    assert st['icp_mapper']['pub'] == pytest.approx(1.0)
    assert st['terrain_fill']['cb'] == pytest.approx(62.0)  # the capture_poses callback
    assert st['footstep_planner']['stage'] == pytest.approx(59.0)
    assert all(len(v) == 1 for d in parts.values() for v in d.values())
    out = tmp_path / 'r.json'
    assert timing_report.main([str(tmp_path), '--json', str(out)]) == 0
    assert json.loads(out.read_text())['icp_mapper']['n'] == 1


def test_report_of_an_empty_directory_is_a_clear_error(tmp_path, capsys):
    assert timing_report.main([str(tmp_path)]) == 2
    assert 'no *.jsonl timing trace' in capsys.readouterr().err


def test_trace_records_takes_and_publishes_of_a_live_node(ros_context, executor, tmp_path):
    from rclpy.node import Node
    from std_msgs.msg import Header
    from terrain_ros.conversions import sec_to_stamp
    from terrain_ros.qos import RELIABLE_QOS

    sink = Node('timing_sink', context=ros_context)
    got = []
    sink.create_subscription(Header, '/timing_test', got.append, RELIABLE_QOS)
    src = Node('timing_source', context=ros_context)
    try:
        assert timing.install(sink, str(tmp_path)) is not None
        assert timing.install(src, str(tmp_path)) is not None
        pub = src.create_publisher(Header, '/timing_test', RELIABLE_QOS)  # wrapped later too
        executor.add_node(sink)
        executor.add_node(src)
        assert spin_until(executor, lambda: pub.get_subscription_count() > 0, 5.0)
        for t in (1.5, 2.5):
            pub.publish(Header(stamp=sec_to_stamp(t), frame_id='x'))
        assert spin_until(executor, lambda: len(got) == 2, 5.0)
    finally:
        timing.uninstall()
    recs = [json.loads(line) for f in tmp_path.glob('*.jsonl') for line in f.open()]
    takes = sorted(r['stamp'] for r in recs if r['k'] == 'take' and r['topic'] == '/timing_test')
    pubs = sorted(r['stamp'] for r in recs if r['k'] == 'pub' and r['topic'] == '/timing_test')
    assert takes == [1.5, 2.5] and pubs == [1.5, 2.5]
    for r in recs:
        if r['k'] == 'take':
            assert r['t0'] <= r['t1'] <= r['t2'] <= r['t3'] and r['cb_cpu'] >= 0.0
    # uninstalled: rclpy's own take is back, nothing more is recorded
    n = len(recs)
    pub.publish(Header(stamp=sec_to_stamp(3.5)))
    assert spin_until(executor, lambda: len(got) == 3, 5.0)
    assert sum(1 for f in tmp_path.glob('*.jsonl') for _ in f.open()) == n


def test_an_unusable_directory_leaves_the_node_untraced(ros_context, tmp_path):
    from rclpy.executors import Executor
    from rclpy.node import Node
    blocker = tmp_path / 'a_file'
    blocker.write_text('x')
    node = Node('timing_bad_dir', context=ros_context)
    take = Executor._take_subscription
    try:
        assert timing.install(node, str(blocker / 'trace')) is None
        assert Executor._take_subscription is take
    finally:
        timing.uninstall()
        node.destroy_node()


def test_without_the_variable_nothing_is_installed(ros_context, monkeypatch):
    from rclpy.executors import Executor
    from rclpy.node import Node
    monkeypatch.delenv(timing.ENV_VAR, raising=False)
    node = Node('timing_off', context=ros_context)
    take = Executor._take_subscription
    try:
        assert timing.install(node) is None
        assert Executor._take_subscription is take
        with timing.profiled(node):
            pass
    finally:
        node.destroy_node()
