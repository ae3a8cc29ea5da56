"""The pipeline CPU profile (terrain_ros.tools.pipeline_profile) and its benchmark suite
(terrain-bench pipeline): one-line errors with exit code 2, and on a small synthetic bag
(4 rendered captures with odometry, IMU, joint states and the downstream maps) every stage runs
once per counted capture, the JSON has its keys and the thread variables are reported as given."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from terrain_ros.tools import pipeline_profile as pp

N_CAPTURES = 4          # in the synthetic bag; the first is the tool's warm-up
T0 = 10.0               # stamp of the first capture [s]
DT = 0.5                # between captures [s]


def _type_name(msg) -> str:
    return f'{type(msg).__module__.split(".")[0]}/msg/{type(msg).__name__}'


def write_bag(path: Path, messages) -> None:
    """A rosbag2 (mcap) directory of ``[(log time [s], topic, message)]`` via rosbags' writer."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer

    from terrain_ros.tools.common import typestore_with
    types = {}
    for _, topic, msg in messages:
        types.setdefault(topic, _type_name(msg))
    store = typestore_with(sorted(set(types.values())))
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conns = {t: writer.add_connection(t, ty, typestore=store) for t, ty in types.items()}
    for t, topic, msg in sorted(messages, key=lambda m: m[0]):
        writer.write(conns[topic], int(round(t * 1e9)), serialize_message(msg))
    writer.close()


def synthetic_messages():
    """Four captures of a littledog walking 2 cm per capture over a rocky course: rendered
    stereo pairs and camera infos (the littledog baseline, half resolution), raycast
    organized clouds, odometry at 20 Hz, IMU and joint states at every capture, and per capture
    the mapper's /icp/pose, /map/fine and /map/capture_poses and the fill's /map/filled (the
    true heights, observed ahead of the robot), plus one /goal_pose."""
    from geometry_msgs.msg import PoseArray, PoseStamped
    from sensor_msgs.msg import Imu, JointState

    from terrain_perception import features
    from terrain_perception.bench.stereo import render_pair_raycast, synthetic_course
    from terrain_perception.camera import PinholeCamera, StereoCamera
    from terrain_perception.grid import ELEVATION, OBSERVED, GridMap
    from terrain_perception.raycast import HeightFieldScene, raycast_points
    from terrain_perception.robot_model import load_robot_model
    from terrain_perception.transforms import R_to_quat, make_T
    from terrain_ros.conversions import (grid_to_msg, make_header, matrix_to_pose,
                                         numpy_to_image, odometry, pose_stamped,
                                         stereo_to_camera_info, xyz_to_cloud)

    robot = load_robot_model('littledog')
    c = robot.camera
    half = PinholeCamera(c.width // 2, c.height // 2, c.fx / 2, c.fy / 2,
                         (c.width // 2 - 1) / 2.0, (c.height // 2 - 1) / 2.0)
    stereo = StereoCamera(half, robot.baseline_m)
    course = synthetic_course('rocks', seed=1, size_xy=(2.0, 1.5))
    scene = HeightFieldScene(course)
    h = np.asarray(course[ELEVATION], np.float32)
    xs, _ = course.cell_centers()

    def T_base(t):
        return make_T(np.eye(3), [0.04 * (t - T0), 0.0, robot.standing_height_m])

    out = []
    for t in np.arange(T0 - 0.5, T0 + N_CAPTURES * DT + 0.5, 0.05):
        out.append((t, '/odom/dead_reckoning', odometry(T_base(t), 'odom', 'base_link', t)))
    goal = PoseStamped(header=make_header('map', T0 - 0.2))
    goal.pose.position.x = 2.0
    goal.pose.orientation.w = 1.0
    out.append((T0 - 0.2, '/goal_pose', goal))
    cams = []
    for k in range(N_CAPTURES):
        t = T0 + k * DT
        T_mb = T_base(t)
        T_mc = T_mb @ robot.T_base_camera
        cams.append(T_mc)
        imu = Imu(header=make_header('imu', t))
        q = R_to_quat(T_mb[:3, :3] @ robot.T_base_imu[:3, :3])
        imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w = q
        imu.linear_acceleration.z = 9.81
        out.append((t, '/imu/data', imu))
        js = JointState(header=make_header('', t), name=list(robot.joint_names),
                        position=[0.0] * 12)
        out.append((t, '/joint_states', js))
        left, right, _ = render_pair_raycast(course, stereo, T_mc, seed=k, scene=scene)
        li, ri = stereo_to_camera_info(stereo, 'camera_optical', t)
        out += [(t, '/stereo/left/camera_info', li), (t, '/stereo/right/camera_info', ri),
                (t + 0.001, '/stereo/left/image_rect',
                 numpy_to_image(left, 'mono8', 'camera_optical', t)),
                (t + 0.002, '/stereo/right/image_rect',
                 numpy_to_image(right, 'mono8', 'camera_optical', t))]
        pts = raycast_points(course, half, T_mc)
        out.append((t + 0.1, '/stereo/points', xyz_to_cloud(pts, 'camera_optical', t)))
        out.append((t + 0.2, '/icp/pose', pose_stamped(T_mb, 'map', t)))
        seen = ((xs > T_mb[0, 3] + 0.1) & (xs < T_mb[0, 3] + 0.7))[:, None] \
            & np.ones(h.shape[1], bool)[None, :]
        fine = GridMap.from_layers(course.resolution_m, course.origin_xy,
                                   {ELEVATION: np.where(seen, h, np.nan).astype(np.float32),
                                    OBSERVED: seen.astype(np.float32)},
                                   stamp_s=t, frame_id='map')
        out.append((t + 0.2, '/map/fine', grid_to_msg(fine, t)))
        poses = PoseArray(header=make_header('map', t))
        poses.poses = [matrix_to_pose(T) for T in cams]
        out.append((t + 0.2, '/map/capture_poses', poses))
        filled = GridMap.from_layers(course.resolution_m, course.origin_xy,
                                     {ELEVATION: h, 'cost': features.cost_map(h, 0.01)},
                                     stamp_s=t, frame_id='map')
        out.append((t + 0.4, '/map/filled', grid_to_msg(filled, t)))
    return out


@pytest.fixture(scope='module')
def synthetic_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('pipeline') / 'bag'
    write_bag(path, synthetic_messages())
    return path


def _tool(*args, env=None, timeout=180):
    return subprocess.run([sys.executable, '-m', 'terrain_ros.tools.pipeline_profile',
                           *map(str, args)], capture_output=True, text=True, timeout=timeout,
                          env=env or dict(os.environ))


def _one_error_line(stderr: str) -> str:
    lines = [ln for ln in stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    assert lines[0].startswith('pipeline_profile: error: '), lines[0]
    return lines[0]


# ------------------------------------------------------------------------------- errors


def test_bag_without_the_needed_topics_is_one_line_naming_them(tmp_path):
    from sensor_msgs.msg import Imu

    from terrain_ros.conversions import make_header, numpy_to_image
    bag = tmp_path / 'small'
    write_bag(bag, [(1.0, '/imu/data', Imu(header=make_header('imu', 1.0))),
                    (1.1, '/stereo/left/image_rect',
                     numpy_to_image(np.zeros((8, 8), np.uint8), 'mono8', 'cam', 1.1))])
    res = _tool(bag, timeout=60)
    assert res.returncode == 2, res.stdout + res.stderr
    line = _one_error_line(res.stderr)
    missing = [t for t in pp.REQUIRED_TOPICS if t not in ('/imu/data', '/stereo/left/image_rect')]
    for t in missing:
        assert t in line, (t, line)
    assert '/imu/data' not in line and '/stereo/left/image_rect' not in line
    assert res.stdout == ''


def test_missing_bag_unknown_robot_and_non_bag_directory(tmp_path, capsys):
    assert pp.main([str(tmp_path / 'nope')]) == 2
    assert 'does not exist' in _one_error_line(capsys.readouterr().err)
    assert pp.main([str(tmp_path), '--robot', 'spot']) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "unknown robot 'spot'" in line and 'littledog' in line and 'frog' in line
    assert pp.main([str(tmp_path)]) == 2
    assert 'not a rosbag2 directory' in _one_error_line(capsys.readouterr().err)
    assert pp.main([str(tmp_path), '--profile', 'everything']) == 2
    assert 'unknown stage' in _one_error_line(capsys.readouterr().err)
    assert pp.main([str(tmp_path), '--profile-out', str(tmp_path / 'x.prof')]) == 2
    assert '--profile-out needs --profile' in _one_error_line(capsys.readouterr().err)


def test_mistyped_topic_is_named():
    class C:
        def __init__(self, topic, msgtype):
            self.topic, self.msgtype = topic, msgtype
    conns = [C(t, ty) for t, ty in pp.REQUIRED_TOPICS.items() if t != '/map/filled']
    conns.append(C('/map/filled', 'nav_msgs/msg/OccupancyGrid'))
    with pytest.raises(pp.ProfileError, match='/map/filled is nav_msgs/msg/OccupancyGrid'):
        pp.check_topics(conns)
    assert pp.check_topics([C(t, ty) for t, ty in pp.REQUIRED_TOPICS.items()])


# ------------------------------------------------------------------------------- end to end


@pytest.mark.graph
def test_every_stage_runs_once_per_capture_on_a_synthetic_bag(synthetic_bag, tmp_path):
    out = tmp_path / 'profile.json'
    env = dict(os.environ, OMP_NUM_THREADS='1', MKL_NUM_THREADS='3')
    env.pop('OPENBLAS_NUM_THREADS', None)
    env['OPENCV_FOR_THREADS_NUM'] = '2'
    stats = tmp_path / 'icp.prof'
    res = _tool(synthetic_bag, '--json', out, '--profile', 'icp', '--profile-out', stats,
                env=env)
    assert res.returncode == 0, res.stdout + res.stderr[-3000:]
    r = json.loads(out.read_text())
    counted = N_CAPTURES - 1
    assert r['captures'] == counted and r['warmup'] == 1
    assert r['robot'] == 'littledog' and 'baseline' in r['robot_source']
    # the nodes did the work, not only got called: every pair, cloud and map went through
    c = r['node_counters']
    assert c['stereo']['frames_processed'] == N_CAPTURES
    assert c['icp_mapper']['captures'] == N_CAPTURES
    assert c['terrain_fill']['updates_published'] == N_CAPTURES
    for stage in ('stereo', 'icp', 'fill', 'plan_map', 'patches'):
        s = r['stages'][stage]
        assert s['calls'] == counted, (stage, s)
        assert s['median_ms'] > 0 and s['p90_ms'] >= s['median_ms'] and s['kind'] == 'stage'
    assert r['stages']['plan_goal']['calls'] == 0          # the goal came before capture 1
    assert r['stages']['icp_odom']['calls'] > 0 and r['stages']['icp_odom']['kind'] == 'small'
    assert [p['capture'] for p in r['per_capture']] == [1, 2, 3]
    assert r['chain_captures_complete'] == counted
    meds = sum(r['stages'][s]['median_ms'] for s in pp.CHAIN)
    assert r['chain_cpu_ms_median_sum'] == pytest.approx(meds, abs=0.1)
    assert sum(s['share'] for s in r['stages'].values()) == pytest.approx(1.0, abs=0.01)
    assert r['cpu_ms_per_capture'] == pytest.approx(r['total_cpu_ms'] / counted, abs=0.1)
    assert r['sink_matched'] is True
    # thread variables: reported as given, not changed
    assert r['threads'] == {'OMP_NUM_THREADS': '1', 'OPENBLAS_NUM_THREADS': None,
                            'MKL_NUM_THREADS': '3', 'OPENCV_FOR_THREADS_NUM': '2'}
    assert ('OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=unset MKL_NUM_THREADS=3 '
            'OPENCV_FOR_THREADS_NUM=2') in res.stdout
    # the table and the profile of the asked stage
    for stage in pp.STAGES:
        assert f'\n{stage} ' in res.stdout
    assert 'critical chain stereo -> icp -> fill -> plan_map' in res.stdout
    assert 'cProfile of icp' in res.stdout and 'icp_mapper_node/node.py' in res.stdout
    assert '_align_and_publish' in res.stdout and 'stereo_node/node.py' not in res.stdout
    # the stage's stats, for pstats / snakeviz: the counted captures' calls of icp only
    import pstats
    st = pstats.Stats(str(stats)).stats
    calls = {f[2]: v[1] for f, v in st.items() if f[0].endswith('icp_mapper_node/node.py')}
    assert calls['_align_and_publish'] == counted
    assert not any(f[0].endswith('stereo_node/node.py') for f in st)


@pytest.mark.graph
def test_bench_runs_each_variant_and_gives_the_ratios(synthetic_bag, capsys):
    from terrain_perception.bench import pipeline as bench
    args = argparse.Namespace(bag=synthetic_bag, captures=2, quick=False, sim_time=25.0,
                              run_dir=Path('unused'))
    r = bench.run(args)
    printed = capsys.readouterr().out
    v = r['variants']
    assert v['default_pools']['threads'] == {k: None for k in bench.THREAD_VARS}
    assert v['node_env']['threads'] == {k: '1' for k in bench.THREAD_VARS}
    for name in bench.VARIANTS:
        assert v[name]['captures'] == 2
        assert all(v[name]['stage_median_ms'][s] > 0 for s in pp.CHAIN + ('patches',))
    b, n = v['default_pools'], v['node_env']
    assert r['icp_cpu_ratio'] == pytest.approx(
        b['stage_median_ms']['icp'] / n['stage_median_ms']['icp'], rel=1e-2)
    assert r['total_cpu_ratio'] == pytest.approx(
        b['cpu_ms_per_capture'] / n['cpu_ms_per_capture'], rel=1e-2)
    assert r['patches_cpu_ratio'] > 0 and r['chain_cpu_ms_median'] == n['chain_cpu_ms_median_sum']
    assert r['recorded_bag'] is False
    assert printed.count('median ms') == 3                      # every variant's table
    assert v['node_env']['compiled_ik'] is True and v['numpy_ik']['compiled_ik'] is False
    assert v['numpy_ik']['threads'] == v['node_env']['threads']
    assert r['plan_map_ik_ratio'] == pytest.approx(
        v['numpy_ik']['stage_median_ms']['plan_map'] / n['stage_median_ms']['plan_map'],
        rel=1e-2)
    assert 'baseline / node env' in printed


def test_bench_thread_variables_are_the_launchers():
    from terrain_perception.bench import pipeline as bench
    from terrain_ros.env import NODE_THREAD_DEFAULTS
    assert bench.THREAD_VARS == tuple(NODE_THREAD_DEFAULTS)
    assert set(NODE_THREAD_DEFAULTS.values()) == {'1'}
    old = {k: os.environ.get(k) for k in bench.THREAD_VARS}
    try:
        os.environ['OMP_NUM_THREADS'] = '4'
        base, node = bench._env('default_pools'), bench._env('node_env')
        assert not any(k in base for k in bench.THREAD_VARS)
        assert all(node[k] == '1' for k in bench.THREAD_VARS)
        assert os.environ['OMP_NUM_THREADS'] == '4'           # the caller's env is untouched
    finally:
        for k, val in old.items():
            if val is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = val


def test_bench_against_profiles_an_earlier_commit_in_a_temporary_worktree(monkeypatch, capsys,
                                                                          tmp_path):
    # --against REV: the revision's code is checked out into a temporary git worktree, the
    # profile runs there (cwd and PYTHONPATH), its medians are set beside the current tree's,
    # and the worktree is gone afterwards. The profiles themselves are stubbed here (the test
    # above runs the real ones): each returns its stage medians, twice as slow in the worktree.
    from terrain_perception.bench import pipeline as bench
    repo = bench.REPO
    if subprocess.run(['git', '-C', str(repo), 'rev-parse', 'HEAD'],
                      capture_output=True).returncode != 0:
        pytest.fail(f'{repo} is not a git checkout: the --against benchmark needs one')
    head = subprocess.run(['git', '-C', str(repo), 'rev-parse', 'HEAD'], capture_output=True,
                          text=True).stdout.strip()
    seen = []

    def fake_profile(bag, captures, variant, code=None, title=None):
        seen.append((variant, code))
        if code is not None:
            # the revision's tree is really there while its profile runs
            assert (Path(code) / 'terrain_perception' / 'bench' / 'pipeline.py').is_file()
            assert subprocess.run(['git', '-C', str(code), 'rev-parse', 'HEAD'],
                                  capture_output=True, text=True).stdout.strip() == head
        k = 2.0 if code is not None else 1.0
        stages = {s: {'median_ms': k * (i + 1), 'p90_ms': k * (i + 2)}
                  for i, s in enumerate(bench.STAGES)}
        if code is not None:
            del stages['icp_model']      # a revision from before that stage existed
        return {'threads': {}, 'compiled_ik': True, 'stages': stages,
                'cpu_ms_per_capture': 10.0 * k, 'chain_cpu_ms_median_sum': 20.0 * k,
                'chain_cpu_ms_per_capture_median': 20.0 * k, 'captures': captures,
                'wall_s': 1.0, 'loadavg_1min': [0.0, 0.0]}

    monkeypatch.setattr(bench, 'profile', fake_profile)
    bag = tmp_path / 'bag'
    bag.mkdir()
    args = argparse.Namespace(bag=bag, captures=2, quick=False, sim_time=25.0,
                              run_dir=Path('unused'), against='HEAD')
    r = bench.run(args)
    printed = capsys.readouterr().out
    code = [c for v, c in seen if c is not None]
    assert len(code) == 1 and not Path(code[0]).exists()          # removed afterwards
    listed = subprocess.run(['git', '-C', str(repo), 'worktree', 'list'], capture_output=True,
                            text=True).stdout
    assert str(code[0]) not in listed
    assert r['against']['rev'] == 'HEAD' and r['against']['commit'] == head
    assert r['against_ratio']['chain'] == pytest.approx(2.0)
    assert all(r['against_ratio'][s] == pytest.approx(2.0) for s in bench.STAGES
               if s != 'icp_model')
    assert r['against_ratio']['icp_model'] is None
    assert r['against']['stage_median_ms']['icp_model'] is None
    assert 'HEAD / the current tree' in printed
    with pytest.raises(ValueError, match='rev-parse'):
        bench.profile_revision(bag, 2, 'no-such-revision-xyz')
