"""stereo_node in process: a published rendered pair becomes a cloud on the true surface; every
bad input is counted, logged and never published."""

import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from stereo_msgs.msg import DisparityImage
from terrain_msgs.msg import GroundPlane

from conftest import spin_until
from stereo_node.node import StereoNode, StereoSync
from terrain_perception.bench.stereo import render_pair_raycast, synthetic_course
from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.ground_plane import camera_pitch_from_pose
from terrain_perception.stereo import StereoConfig
from terrain_perception.raycast import interpolate_height
from terrain_perception.transforms import make_T, rot_y, transform_points
from terrain_ros.conversions import (cloud_to_xyz, msg_to_disparity, numpy_to_image,
                                     sec_to_stamp, stereo_to_camera_info)
from terrain_ros.qos import RELIABLE_QOS, SENSOR_QOS

FRAME = 'camera_optical'
STEREO = StereoCamera(PinholeCamera.from_fov(320, 240, 45.0), 0.08)
# Optical frame 0.5 m above the ground, pitched 35 deg down (columns: x right, y down, z fwd).
_R_BODY_OPTICAL = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
T_WORLD_CAM = make_T(rot_y(np.radians(35.0)) @ _R_BODY_OPTICAL, [0.0, 0.0, 0.5])


@pytest.fixture(scope='module')
def scene():
    grid = synthetic_course('boxes', seed=3, size_xy=(4.0, 3.0))
    left, right, depth = render_pair_raycast(grid, STEREO, T_WORLD_CAM, seed=3)
    return grid, left, right, depth


def _edge_distance(grid, xy):
    """Distance [m] (in cells, rounded down) from x-y to the nearest height step > 1 cm."""
    import cv2
    h = grid['elevation']
    step = np.zeros(h.shape, bool)
    step[1:, :] |= np.abs(np.diff(h, axis=0)) > 0.01
    step[:, 1:] |= np.abs(np.diff(h, axis=1)) > 0.01
    dist = cv2.distanceTransform((~step).astype(np.uint8), cv2.DIST_L2, 3) * grid.resolution_m
    ij = np.clip(grid.world_to_index(xy), 0, np.array(h.shape) - 1)
    return dist[ij[:, 0], ij[:, 1]]


class Harness:
    """Publishers of the node's inputs and recorders of its outputs."""

    def __init__(self, ctx, executor, outputs=('points', 'coarse', 'disparity', 'plane'),
                 **params):
        # A 9 px window for the 320x240 test camera (15 px is the default at 640x480).
        overrides = [Parameter('num_disparities', value=64), Parameter('block_size_px', value=9)]
        overrides += [Parameter(k, value=v) for k, v in params.items()]
        self.node = StereoNode(context=ctx, parameter_overrides=overrides)
        self.io = Node('stereo_test_io', context=ctx)
        self.ex = executor
        executor.add_node(self.node)
        executor.add_node(self.io)
        self.pub = {s: self.io.create_publisher(Image, f'/stereo/{s}/image_rect', SENSOR_QOS)
                    for s in ('left', 'right')}
        self.info = {s: self.io.create_publisher(CameraInfo, f'/stereo/{s}/camera_info',
                                                 SENSOR_QOS) for s in ('left', 'right')}
        self.req = self.io.create_publisher(Header, '/capture_request', RELIABLE_QOS)
        self.got = {'points': [], 'coarse': [], 'disparity': [], 'plane': []}
        for key, typ, topic, qos in (('points', PointCloud2, '/stereo/points', SENSOR_QOS),
                                     ('coarse', PointCloud2, '/stereo/points_coarse',
                                      SENSOR_QOS),
                                     ('disparity', DisparityImage, '/stereo/disparity',
                                      SENSOR_QOS),
                                     ('plane', GroundPlane, '/stereo/ground_plane',
                                      RELIABLE_QOS)):
            if key in outputs:
                self.subscribe(key, typ, topic, qos)
        assert spin_until(executor, lambda: all(
            p.get_subscription_count() > 0 for p in (*self.pub.values(), *self.info.values())),
            5.0)
        assert spin_until(executor, lambda: self.node.pub_points.get_subscription_count() > 0,
                          5.0)

    def subscribe(self, key, typ, topic, qos):
        self.io.create_subscription(typ, topic, lambda m, k=key: self.got[k].append(m), qos)

    def send_info(self, stereo=STEREO, t=1.0):
        li, ri = stereo_to_camera_info(stereo, FRAME, t)
        self.info['left'].publish(li)
        self.info['right'].publish(ri)

    def send_pair(self, left, right, t, enc='mono8', enc_right=None):
        for side, img, e in (('left', left, enc), ('right', right, enc_right or enc)):
            self.pub[side].publish(numpy_to_image(img, e, FRAME, t))

    def spin(self, pred, timeout=10.0):
        return spin_until(self.ex, pred, timeout)

    def counter(self, key):
        return self.node.counters[key]


def test_published_pair_gives_a_cloud_on_the_true_surface(ros_context, executor, scene):
    grid, left, right, depth = scene
    h = Harness(ros_context, executor)
    h.send_info()
    assert h.spin(lambda: h.node._info['right'] is not None, 5.0)
    h.send_pair(left, right, 12.5)
    assert h.spin(lambda: h.got['points'] and h.got['plane'] and h.got['coarse']
                  and h.got['disparity'])
    cloud = h.got['points'][0]
    assert cloud.header.frame_id == FRAME and cloud.header.stamp == sec_to_stamp(12.5)
    pts = cloud_to_xyz(cloud)
    assert pts.shape == (240, 320, 3)
    valid = np.isfinite(pts).all(axis=2)
    truth = np.isfinite(depth)
    assert valid[truth].mean() > 0.85
    world = transform_points(T_WORLD_CAM, pts[valid].astype(np.float64))
    err = world[:, 2] - interpolate_height(grid, world[:, :2])
    ok = np.isfinite(err)
    assert ok.mean() > 0.8
    assert np.median(np.abs(err[ok])) < 0.005
    # Away from the boxes' edges (where a small x-y error jumps between top and floor) the
    # points are on the surface.
    smooth = ok & (_edge_distance(grid, world[:, :2]) > 0.03)
    assert smooth.mean() > 0.8
    assert np.mean(np.abs(err[smooth]) < 0.02) > 0.98
    # Disparity message against the exact disparity of the depth buffer.
    d = msg_to_disparity(h.got['disparity'][0])
    gt = STEREO.depth_to_disparity(depth)
    both = np.isfinite(d) & np.isfinite(gt)
    assert np.mean(np.abs(d[both] - gt[both]) <= 1.0) > 0.95
    assert cloud_to_xyz(h.got['coarse'][0]).shape == (30, 40, 3)
    plane = h.got['plane'][0]
    assert abs(plane.pitch - camera_pitch_from_pose(T_WORLD_CAM)) < np.radians(1.0)
    assert abs(plane.height - 0.5) < 0.01
    assert not h.node.counters.counts


def test_ground_plane_and_disparity_are_computed_only_while_someone_listens(
        ros_context, executor, scene):
    grid, left, right, depth = scene
    h = Harness(ros_context, executor, outputs=('points', 'coarse'))
    h.send_info()
    assert h.spin(lambda: h.node._info['right'] is not None, 5.0)
    h.send_pair(left, right, 3.0)
    assert h.spin(lambda: h.got['points'] and h.got['coarse'])
    assert h.node.frames_processed == 1
    assert h.node.planes_fitted == 0
    assert h.node.pub_disparity.get_subscription_count() == 0
    # A late subscriber gets the plane (and the disparity) from the next pair on.
    h.subscribe('plane', GroundPlane, '/stereo/ground_plane', RELIABLE_QOS)
    h.subscribe('disparity', DisparityImage, '/stereo/disparity', SENSOR_QOS)
    assert h.spin(lambda: h.node.pub_plane.get_subscription_count() > 0
                  and h.node.pub_disparity.get_subscription_count() > 0, 5.0)
    h.send_pair(left, right, 4.0)
    assert h.spin(lambda: h.got['plane'] and h.got['disparity'])
    assert h.node.planes_fitted == 1
    assert h.got['plane'][0].header.stamp == sec_to_stamp(4.0)
    assert h.got['plane'][0].inlier_ratio > 0.3


def test_capture_request_mode_processes_only_requested_pairs(ros_context, executor, scene):
    _, left, right, _ = scene
    h = Harness(ros_context, executor, capture_on_request=True)
    h.send_info()
    assert h.spin(lambda: h.node._info['right'] is not None, 5.0)
    h.send_pair(left, right, 2.0)
    assert h.spin(lambda: h.node._pending is not None, 5.0)
    h.spin(lambda: False, 0.3)
    assert not h.got['points']                    # no request yet
    h.req.publish(Header(stamp=sec_to_stamp(3.0)))
    h.spin(lambda: h.node._request_stamp is not None, 5.0)
    h.spin(lambda: False, 0.3)
    assert not h.got['points']                    # the waiting pair is older than the request
    h.send_pair(left, right, 3.5)
    assert h.spin(lambda: len(h.got['points']) == 1)
    assert h.got['points'][0].header.stamp == sec_to_stamp(3.5)
    h.send_pair(left, right, 4.0)                 # request consumed: not processed
    h.spin(lambda: False, 0.5)
    assert len(h.got['points']) == 1
    assert not h.node.counters.counts              # skipping unrequested pairs is no error


def _bad_cases(left, right):
    black = np.zeros_like(left)
    white = np.full_like(left, 255)
    rgb = np.repeat(left[..., None], 3, axis=2)
    return [
        ('size_mismatch', dict(left=left, right=right[:, :300])),
        ('encoding_mismatch', dict(left=left, right=rgb, enc_right='rgb8')),
        ('bad_encoding', dict(left=left.astype(np.uint16) * 256, right=right.astype(np.uint16),
                              enc='mono16')),
        ('bad_encoding', dict(left=left.astype(np.float32), right=right.astype(np.float32),
                              enc='32FC1')),
        ('black_image', dict(left=black, right=right)),
        ('saturated_image', dict(left=left, right=white)),
    ]


def test_every_bad_input_is_counted_and_nothing_is_published(ros_context, executor, scene):
    _, left, right, _ = scene
    h = Harness(ros_context, executor)
    # No camera info yet.
    h.send_pair(left, right, 1.0)
    assert h.spin(lambda: h.counter('missing_camera_info') == 1)
    # Zero baseline.
    li, ri = stereo_to_camera_info(STEREO, FRAME, 1.0)
    ri.p[3] = 0.0
    h.info['left'].publish(li)
    h.info['right'].publish(ri)
    assert h.spin(lambda: h.node._info['right'] is not None)
    h.send_pair(left, right, 1.5)
    assert h.spin(lambda: h.counter('bad_camera_info') == 1)
    h.send_info()
    assert h.spin(lambda: h.node._info['right'] is not None
                  and h.node._info['right'].p[3] != 0.0)
    t = 2.0
    expected = {}
    for key, kw in _bad_cases(left, right):
        expected[key] = expected.get(key, 0) + 1
        h.send_pair(t=t, **kw)
        t += 0.5
        assert h.spin(lambda: h.counter(key) == expected[key]), key
    # Unpaired stamps: a left image that never gets its right one is dropped once a later
    # pair completes.
    h.pub['left'].publish(numpy_to_image(left, 'mono8', FRAME, t))
    h.pub['right'].publish(numpy_to_image(right, 'mono8', FRAME, t + 0.01))
    h.spin(lambda: False, 0.3)
    assert not h.got['points']
    h.send_pair(left, right, t + 1.0)
    assert h.spin(lambda: h.counter('unpaired_stamp') == 2 and h.got['points'])
    # The node kept running and published only the one good pair.
    assert len(h.got['points']) == 1
    assert h.got['points'][0].header.stamp == sec_to_stamp(t + 1.0)
    want = {'missing_camera_info': 1, 'bad_camera_info': 1, 'size_mismatch': 1,
            'encoding_mismatch': 1, 'bad_encoding': 2, 'black_image': 1, 'saturated_image': 1,
            'unpaired_stamp': 2}
    assert dict(h.node.counters.counts) == want
    # The same counts go out on ~/diagnostics.
    diags = []
    h.io.create_subscription(DiagnosticArray, '/stereo_node/diagnostics', diags.append,
                             RELIABLE_QOS)
    assert h.spin(lambda: diags, 5.0)
    got = {kv.key: int(kv.value) for kv in diags[-1].status[0].values}
    # with this process's CPU so far [ms] (the report's node_cpu_s), not a counter
    cpu_ms = got.pop('process_cpu_ms')
    assert got == want
    assert 0 < cpu_ms <= 1000 * time.process_time()
    assert diags[-1].status[0].message == ', '.join(f'{k}={v}' for k, v in sorted(want.items()))


def _img(t):
    return numpy_to_image(np.zeros((4, 4), np.uint8), 'mono8', FRAME, t)


def test_sync_pairs_by_exact_stamp_and_bounds_its_queue():
    s = StereoSync(queue_size=2)
    assert s.add('left', _img(1.0)) == (None, [])
    pair, dropped = s.add('right', _img(1.0))
    assert pair is not None and dropped == []
    assert pair[0].header.stamp == sec_to_stamp(1.0)
    s.add('left', _img(2.0))
    s.add('left', _img(3.0))
    _, dropped = s.add('left', _img(4.0))           # queue of 2: the oldest goes
    assert dropped == [(2, 0)]
    pair, dropped = s.add('right', _img(4.0))
    assert pair is not None and dropped == [(3, 0)]


def test_rate_mode_processes_at_once_then_keeps_only_the_newest_pair(ros_context, scene):
    # At most 0.5 pairs/s: the first pair is processed in its image callback (no wait for the
    # timer), the next two within the period wait in the one-slot buffer, the newer replacing
    # the older, until the rate allows the timer to process it.
    node = StereoNode(context=ros_context, parameter_overrides=[
        Parameter('max_rate_hz', value=0.5), Parameter('always_process', value=True),
        Parameter('num_disparities', value=64), Parameter('block_size_px', value=9)])
    _, left, right, _ = scene
    for side, info in zip(('left', 'right'), stereo_to_camera_info(STEREO, FRAME, 1.0)):
        node._on_info(side, info)
    for t in (1.0, 1.1, 1.2):
        node._on_image('left', numpy_to_image(left, 'mono8', FRAME, t))
        node._on_image('right', numpy_to_image(right, 'mono8', FRAME, t))
        if t == 1.0:
            assert node.frames_processed == 1 and node._pending is None
    assert node.frames_processed == 1
    assert node.counters['stale_pair'] == 1
    assert node._pending[0].header.stamp == sec_to_stamp(1.2)
    node._on_timer()                                     # within the period: still waiting
    assert node.frames_processed == 1 and node._pending is not None
    assert node.set_parameters([Parameter('max_rate_hz', value=1000.0)])[0].successful
    time.sleep(0.01)                                     # > 1 ms: the rate allows it
    node._on_timer()
    assert node.frames_processed == 2 and node._pending is None and node.pairs_taken == 2
    node.destroy_node()


def test_the_rate_bound_is_on_the_steady_clock_with_simulated_time(ros_context, scene):
    # With use_sim_time and no /clock yet the node's clock stands still (as it nearly does
    # while the simulator renders a capture): on that clock a second pair would wait for
    # simulated time to pass 1 / max_rate_hz; the bound is on the CPU, so wall time counts.
    node = StereoNode(context=ros_context, parameter_overrides=[
        Parameter('use_sim_time', value=True), Parameter('max_rate_hz', value=20.0),
        Parameter('always_process', value=True),
        Parameter('num_disparities', value=64), Parameter('block_size_px', value=9)])
    _, left, right, _ = scene
    for side, info in zip(('left', 'right'), stereo_to_camera_info(STEREO, FRAME, 1.0)):
        node._on_info(side, info)

    def pair(t):
        node._on_image('left', numpy_to_image(left, 'mono8', FRAME, t))
        node._on_image('right', numpy_to_image(right, 'mono8', FRAME, t))

    pair(1.0)
    pair(1.02)                    # within 1/20 s of wall time: waits in the slot
    assert node.frames_processed == 1 and node._pending is not None
    time.sleep(0.06)
    pair(1.04)                    # 1/20 s of wall time later: taken on arrival
    assert node.frames_processed == 2 and node._pending is None
    assert node.get_clock().now().nanoseconds == 0      # simulated time never moved
    # The node's clock, as before (the latency benchmark's baseline): simulated time stands
    # still, so the pair waits however long the wall clock runs.
    assert node.set_parameters([Parameter('rate_clock', value='node')])[0].successful
    pair(1.06)
    assert node.frames_processed == 3                    # no earlier pair on this clock
    time.sleep(0.06)
    pair(1.08)
    assert node.frames_processed == 3 and node._pending is not None
    assert not node.set_parameters([Parameter('rate_clock', value='wall')])[0].successful
    node.destroy_node()


def test_runtime_parameters_are_checked_and_applied(ros_context):
    node = StereoNode(context=ros_context)
    res = node.set_parameters([Parameter('num_disparities', value=40)])[0]
    assert not res.successful and 'multiple of 16' in res.reason
    assert node.stereo_cfg.num_disparities == StereoConfig().num_disparities
    res = node.set_parameters([Parameter('block_size_px', value=99)])[0]
    assert not res.successful and 'block_size_px' in res.reason
    assert node.set_parameters([Parameter('num_disparities', value=112)])[0].successful
    assert node.stereo_cfg.num_disparities == 112
    assert node.set_parameters([Parameter('ground_plane.inlier_threshold_m',
                                          value=0.01)])[0].successful
    assert node.plane_cfg.inlier_threshold_m == 0.01
    assert node.set_parameters([Parameter('max_rate_hz', value=5.0)])[0].successful
    assert node._timer.timer_period_ns == 200_000_000
    node.destroy_node()


def _frog_view():
    """FROG-I's stereo camera at half resolution (as the graph tests run it), standing on flat
    ground among 3-20 cm blocks: the pair, the camera pose and the terrain."""
    from terrain_perception.robot_model import load_robot_model
    m = load_robot_model('frog')
    cam = m.camera
    half = PinholeCamera(cam.width // 2, cam.height // 2, cam.fx / 2, cam.fy / 2,
                         (cam.width // 2 - 1) / 2.0, (cam.height // 2 - 1) / 2.0)
    stereo = StereoCamera(half, m.baseline_m)
    T_base = make_T(np.eye(3), [0.0, 0.0, m.standing_height_m])
    T_world_cam = T_base @ m.T_base_camera
    grid = synthetic_course('boxes', seed=5, size_xy=(5.0, 4.0))
    left, right, _ = render_pair_raycast(grid, stereo, T_world_cam, seed=5)
    return stereo, T_world_cam, grid, left, right


def _disparity_of_pair(h, stereo, left, right):
    h.send_info(stereo)
    assert h.spin(lambda: h.node._info['right'] is not None, 5.0)
    h.send_pair(left, right, 3.0)
    assert h.spin(lambda: bool(h.got['disparity']))
    return msg_to_disparity(h.got['disparity'][0])


def test_the_robot_profile_sizes_the_disparity_range_to_the_nearest_ground(ros_context,
                                                                         executor):
    # FROG-I's camera is 0.65 m up with a 12 cm baseline: at half resolution the floor at the
    # bottom image row is 47 px away, 59 with the 1.25 margin -> 64 px from camera_info and
    # the mount (112 at full resolution, LittleDog's 96). A range that stops short of the
    # nearest ground (32 px here) matches the wrong pixel there instead of leaving it empty.
    stereo, T, grid, left, right = _frog_view()
    _, _, depth = render_pair_raycast(grid, stereo, T, seed=5)
    gt = stereo.depth_to_disparity(depth)

    def bad2(d):
        both = np.isfinite(d) & np.isfinite(gt)
        return float(np.mean(np.abs(d[both] - gt[both]) > 2.0))

    sized = Harness(ros_context, executor, robot='frog')
    d = _disparity_of_pair(sized, stereo, left, right)
    assert sized.node._pipeline.config.num_disparities == 64
    assert np.nanmax(gt) < 64 and bad2(d) < 0.01
    executor.remove_node(sized.node)
    executor.remove_node(sized.io)
    sized.node.destroy_node()
    sized.io.destroy_node()
    short = Harness(ros_context, executor, num_disparities=32)
    d_short = _disparity_of_pair(short, stereo, left, right)
    assert short.node._pipeline.config.num_disparities == 32
    beyond = np.isfinite(gt) & (gt >= 32)
    assert beyond.sum() > 10000 and np.sum(beyond & np.isfinite(d_short)) > 1000
    assert bad2(d_short) > 5 * bad2(d)


def test_an_unknown_robot_is_refused_with_its_name(ros_context):
    with pytest.raises(ValueError, match="unknown robot 'dog'"):
        StereoNode(context=ros_context, parameter_overrides=[Parameter('robot', value='dog')])
