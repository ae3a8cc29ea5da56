"""terrain_fill_node in process: a published fine grid with a hole comes back filled, bounded
and costed; every bad input is counted and the last good output stays published."""

import numpy as np
import pytest
from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from rclpy.parameter import Parameter
from scipy import ndimage
from terrain_msgs.msg import TerrainGrid

from conftest import spin_until
from terrain_fill_node.node import TerrainFillNode
from terrain_perception.features import CostConfig, cost_map
from terrain_perception.grid import (COST, ELEVATION, FILLED, OBSERVED, UPPER_BOUND, GridMap)
from terrain_perception.transforms import make_T
from terrain_ros.conversions import grid_to_msg, matrix_to_pose, msg_to_grid
from terrain_ros.qos import LATCHED_QOS

RES = 0.01


def smooth(n, seed, amp=0.03):
    rng = np.random.default_rng(seed)
    h = ndimage.gaussian_filter(rng.normal(size=(n, n)), 3.0)
    return (amp * h / np.abs(h).max() + amp).astype(np.float32)


def scene():
    """A 40 x 40 map with a 4 cm block at x = 0.15 m and the shadow behind it, seen by a
    camera at x = 0, 0.25 m up (the shadow computed by the true line of sight)."""
    truth = smooth(40, 0, 0.005)
    truth[15:18, 10:30] = 0.04
    seen = np.ones(truth.shape, bool)
    cam = np.array([-0.05, 0.2, 0.25])
    for i in range(18, 40):     # behind the block: hidden while under the block's ray
        x = (i + 0.5) * RES
        z_ray = cam[2] + (x - cam[0]) / (0.18 - cam[0]) * (0.04 - cam[2])
        seen[i, 10:30] &= truth[i, 10:30] > z_ray
    assert (~seen).sum() > 20
    return truth, seen, cam


def grid_msg(truth, seen, stamp=1.0, extra=None):
    layers = {ELEVATION: np.where(seen, truth, np.nan).astype(np.float32),
              OBSERVED: seen.astype(np.float32)}
    layers.update(extra or {})
    return grid_to_msg(GridMap.from_layers(RES, (0.0, 0.0), layers, stamp_s=stamp))


def poses_msg(cams, frame='map', pitch_down_deg=35.0):
    """Optical-frame poses looking along +x, pitched down (z forward, x right, y down)."""
    a = np.radians(pitch_down_deg)
    z = np.array([np.cos(a), 0.0, -np.sin(a)])
    x = np.array([0.0, -1.0, 0.0])
    R = np.c_[x, np.cross(z, x), z]
    msg = PoseArray()
    msg.header.frame_id = frame
    for c in cams:
        msg.poses.append(matrix_to_pose(make_T(R, c)))
    return msg


@pytest.fixture
def library_dir(tmp_path):
    for s in range(2):
        GridMap.from_layers(RES, (0, 0), {ELEVATION: smooth(50, 10 + s, 0.02)}).save(
            tmp_path / f'lib{s}.npz')
    return tmp_path


class Harness:
    def __init__(self, ctx, executor, library, **params):
        overrides = [Parameter('library_dir', value=str(library)),
                     Parameter('fill.samples', value=30),
                     Parameter('process_period_s', value=0.02)]
        overrides += [Parameter(k, value=v) for k, v in params.items()]
        self.node = TerrainFillNode(context=ctx, parameter_overrides=overrides)
        self.io = Node('fill_test_io', context=ctx)
        self.ex = executor
        executor.add_node(self.node)
        executor.add_node(self.io)
        self.pub_grid = self.io.create_publisher(TerrainGrid, '/map/fine', LATCHED_QOS)
        self.pub_poses = self.io.create_publisher(PoseArray, '/map/capture_poses', LATCHED_QOS)
        self.got = []
        self.io.create_subscription(TerrainGrid, '/map/filled', self.got.append, LATCHED_QOS)
        assert self.spin(lambda: self.pub_grid.get_subscription_count() > 0
                         and self.node.pub.get_subscription_count() > 0, 5.0)

    def spin(self, pred, timeout=10.0):
        return spin_until(self.ex, pred, timeout)

    def settle(self, seconds=0.4):
        self.spin(lambda: False, seconds)


def test_hole_behind_a_block_is_filled_below_the_line_of_sight(ros_context, executor,
                                                               library_dir):
    truth, seen, cam = scene()
    h = Harness(ros_context, executor, library_dir)
    h.pub_poses.publish(poses_msg([cam]))
    h.pub_grid.publish(grid_msg(truth, seen))
    assert h.spin(lambda: len(h.got) >= 1)
    h.settle()
    out = msg_to_grid(h.got[-1])
    assert out.frame_id == 'map'
    np.testing.assert_array_equal(out[OBSERVED], seen.astype(np.float32))  # never by filling
    np.testing.assert_array_equal(out[FILLED], (~seen).astype(np.float32))
    np.testing.assert_array_equal(out[ELEVATION][seen], truth[seen])
    assert np.isfinite(out[ELEVATION]).all()
    ub = out[UPPER_BOUND]
    hidden = ~seen
    assert np.isnan(ub[seen]).all()
    bounded = hidden & np.isfinite(ub)
    assert bounded.mean() > 0.5 * hidden.mean()                  # the shadow got bounds
    assert np.all(ub[bounded] >= truth[bounded] - 0.002)         # ... that hold (ray tol)
    assert np.all(ub[bounded] < 0.04)                             # ... below the block top
    # Fill-Terrain keeps to the bounds where one of its 30 draws fits (least violation else)
    over = out[ELEVATION][bounded] - ub[bounded]
    assert (over <= 0).mean() > 0.85 and over.max() < 0.005
    assert np.median(out[ELEVATION][hidden]) < 0.02    # the shadow drops off, unlike the block
    np.testing.assert_allclose(out[COST], cost_map(out[ELEVATION], RES, CostConfig()),
                               atol=1e-5)


def _bad_grids(truth, seen):
    nan_obs = np.where(seen, truth, np.nan).astype(np.float32)
    nan_obs[2, 2] = np.nan
    inf_obs = np.where(seen, truth, np.nan).astype(np.float32)
    inf_obs[2, 3] = np.inf
    low = np.full(truth.shape, np.nan, np.float32)
    low[5, 5] = truth[5, 5] - 0.01
    return {
        'all unknown': grid_msg(truth, np.zeros_like(seen), 2.0),
        'NaN in observed': grid_msg(truth, seen, 3.0, {ELEVATION: nan_obs}),
        'inf in observed': grid_msg(truth, seen, 4.0, {ELEVATION: inf_obs}),
        'bound below observed': grid_msg(truth, seen, 5.0, {UPPER_BOUND: low}),
    }


def test_bad_grids_are_counted_and_the_last_output_stays(ros_context, executor, library_dir):
    truth, seen, cam = scene()
    h = Harness(ros_context, executor, library_dir)
    h.pub_poses.publish(poses_msg([cam]))
    h.pub_grid.publish(grid_msg(truth, seen, 1.0))
    assert h.spin(lambda: len(h.got) >= 1)
    h.settle()
    good = h.got[-1]
    n_good = len(h.got)
    for k, (name, msg) in enumerate(_bad_grids(truth, seen).items(), start=1):
        h.pub_grid.publish(msg)
        assert h.spin(lambda: h.node.counters['bad_grid'] >= k), name
    h.settle()
    assert len(h.got) == n_good and h.node.published == 1
    reasons = h.node.counters.last_reason['bad_grid']
    assert 'above their line-of-sight upper bound' in reasons
    # a late joiner still receives the last good map (transient local)
    late = []
    h.io.create_subscription(TerrainGrid, '/map/filled', late.append, LATCHED_QOS)
    assert h.spin(lambda: len(late) >= 1)
    assert late[0].header.stamp == good.header.stamp
    # and the node recovers on the next good grid
    h.pub_grid.publish(grid_msg(truth, seen, 6.0))
    assert h.spin(lambda: h.node.published == 2)


@pytest.mark.parametrize('which', ['missing', 'empty'])
def test_missing_or_empty_library_publishes_nothing(ros_context, executor, tmp_path, which):
    folder = tmp_path / 'nope' if which == 'missing' else tmp_path
    truth, seen, _ = scene()
    h = Harness(ros_context, executor, folder)
    assert h.node.counters['bad_library'] == 1
    assert ('does not exist' if which == 'missing' else 'empty') in \
        h.node.counters.last_reason['bad_library']
    h.pub_grid.publish(grid_msg(truth, seen))
    assert h.spin(lambda: h.node.counters['no_library'] >= 1)
    h.settle(0.2)
    assert h.got == [] and h.node.published == 0


def test_poses_in_another_frame_are_not_used(ros_context, executor, library_dir):
    truth, seen, cam = scene()
    h = Harness(ros_context, executor, library_dir)
    h.pub_poses.publish(poses_msg([cam], frame='odom'))
    h.pub_grid.publish(grid_msg(truth, seen))
    assert h.spin(lambda: len(h.got) >= 1)
    assert h.node.counters['frame_mismatch'] >= 1
    assert np.isnan(msg_to_grid(h.got[-1])[UPPER_BOUND]).all()


def test_grid_and_poses_of_one_capture_are_processed_at_once(ros_context, executor,
                                                             library_dir):
    """No waiting for the timer: a grid and poses with one stamp trigger the update."""
    truth, seen, cam = scene()
    h = Harness(ros_context, executor, library_dir, process_period_s=60.0)
    poses = poses_msg([cam])
    grid = grid_msg(truth, seen, 7.0)
    poses.header.stamp = grid.header.stamp
    h.pub_grid.publish(grid)
    h.pub_poses.publish(poses)
    assert h.spin(lambda: len(h.got) >= 1, 5.0)
    assert h.node.published == 1 and len(h.node.update_cpu_s) == 1
    out = msg_to_grid(h.got[-1])
    assert np.isfinite(out[UPPER_BOUND]).any()          # the poses were used


def test_queued_grids_are_coalesced_to_the_newest(ros_context, executor, library_dir):
    truth, seen, cam = scene()
    h = Harness(ros_context, executor, library_dir, process_period_s=60.0)
    node = h.node
    node._on_poses(poses_msg([cam]))
    for k in range(5):                  # as if five grids had queued during a long update
        seen_k = seen.copy()
        seen_k[:, :k] = False
        node._on_grid(grid_msg(truth, seen_k, 10.0 + k))
    node._process()
    assert node.published == 1 and node.skipped == 4 and len(node.update_cpu_s) == 1
    assert node.last_output.stamp_s == pytest.approx(14.0)
    node._process()                     # nothing pending: nothing done
    assert node.published == 1


def test_poses_ahead_of_their_grid_wait_one_period_for_it(ros_context, executor,
                                                        library_dir):
    """The mapper publishes a capture's poses before its grid: a timer tick between the two
    keeps the poses for the grid (no fill of the previous grid with them), the grid then pairs
    at once; poses whose grid never comes are processed at the next tick."""
    truth, seen, cam = scene()
    h = Harness(ros_context, executor, library_dir, process_period_s=60.0)
    node = h.node

    def poses(stamp):
        msg = poses_msg([cam])
        msg.header.stamp = grid_msg(truth, seen, stamp).header.stamp
        return msg
    node._on_grid(grid_msg(truth, seen, 10.0))
    node._on_poses(poses(10.0))                       # paired: at once
    assert node.published == 1
    node._on_poses(poses(11.0))                       # the next capture's poses come first
    node._on_timer()
    assert node.published == 1 and node._poses_msg is not None    # kept for their grid
    seen_11 = seen.copy()
    seen_11[:, :3] = False
    node._on_grid(grid_msg(truth, seen_11, 11.0))     # pairs at once
    assert node.published == 2 and node.last_output.stamp_s == pytest.approx(11.0)
    node._on_poses(poses(12.0))                       # a grid that never comes
    node._on_timer()
    assert node.published == 2
    node._on_timer()                                  # one period later: processed anyway
    assert node.published == 3 and node._poses_msg is None
    assert node.last_output.stamp_s == pytest.approx(11.0)
    node._on_poses(poses(11.0))                       # not newer than the grid held: at once
    node._on_timer()
    assert node.published == 4


def test_blind_area_is_published_unknown(ros_context, executor, library_dir):
    """Cells no capture looked at (here: without poses, all unobserved ones) stay NaN and are
    not marked filled; with filler.blind_area texture they are filled."""
    truth, seen, _ = scene()
    h = Harness(ros_context, executor, library_dir)
    h.pub_grid.publish(grid_msg(truth, seen))
    assert h.spin(lambda: len(h.got) >= 1)
    out = msg_to_grid(h.got[-1])
    assert np.isnan(out[ELEVATION][~seen]).all() and not out[FILLED].any()
    np.testing.assert_array_equal(out[ELEVATION][seen], truth[seen])
    h.node.set_parameters([Parameter('filler.blind_area', value='texture')])
    assert h.spin(lambda: len(h.got) >= 2)
    assert np.isfinite(msg_to_grid(h.got[-1])[ELEVATION]).all()
