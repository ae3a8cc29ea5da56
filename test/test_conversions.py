"""Round trips of every conversion in terrain_ros.conversions, NaN cells included."""

import struct

import numpy as np
import pytest
from sensor_msgs.msg import PointField

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.grid import GridMap
from terrain_perception.transforms import make_T, rpy_to_R
from terrain_ros import conversions as cv

RNG = np.random.default_rng(0)


def test_organized_cloud_round_trip_keeps_nan_and_shape():
    pts = RNG.normal(size=(48, 64, 3)).astype(np.float32)
    pts[3, 5] = np.nan
    pts[10:12, :] = np.nan
    msg = cv.xyz_to_cloud(pts, 'camera_optical', 12.5)
    assert (msg.height, msg.width) == (48, 64) and not msg.is_dense
    back = cv.cloud_to_xyz(msg)
    assert back.shape == pts.shape
    np.testing.assert_array_equal(np.isnan(back), np.isnan(pts))
    np.testing.assert_array_equal(back[np.isfinite(back)], pts[np.isfinite(pts)])
    assert msg.header.frame_id == 'camera_optical'
    assert cv.stamp_to_sec(msg.header.stamp) == pytest.approx(12.5)


def test_cloud_bytes_are_little_endian_xyz_records_whatever_the_input_layout():
    """The wire layout (point_step 12, x y z float32 little-endian, row after row) from a
    float32 C array (taken as it is), a float64 one and a transposed view; serialised by
    rclpy the same."""
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2
    pts = RNG.normal(size=(30, 40, 3)).astype(np.float32)
    pts[2, 3] = np.nan
    want = pts.astype('<f4').tobytes()
    for given in (pts, pts.astype(np.float64), np.ascontiguousarray(
            pts.transpose(1, 0, 2)).transpose(1, 0, 2)):
        msg = cv.xyz_to_cloud(given, 'cam', 1.0)
        assert (msg.point_step, msg.row_step) == (12, 12 * 40)
        assert bytes(msg.data) == want
        again = deserialize_message(serialize_message(msg), PointCloud2)
        assert bytes(again.data) == want


def test_unorganized_cloud_with_extra_field_round_trip():
    pts = RNG.normal(size=(100, 3)).astype(np.float32)
    inten = RNG.uniform(size=100).astype(np.float32)
    msg = cv.xyz_to_cloud(pts, 'map', 0.0, extra={'intensity': inten})
    assert msg.height == 1 and msg.is_dense
    np.testing.assert_array_equal(cv.cloud_to_xyz(msg), pts)
    np.testing.assert_array_equal(cv.cloud_fields(msg, ['intensity'])[:, 0], inten)


def test_the_xyz_only_reader_equals_the_general_one_and_owns_its_array():
    """The stereo node's layout (x y z float32, point_step 12) is read straight from the
    data; the same points with an extra field, or big-endian, go the general way: the same
    values, NaN included, and the result is the reader's own (writing it leaves the message
    alone)."""
    pts = RNG.normal(size=(24, 32, 3)).astype(np.float32)
    pts[1, 2] = np.nan
    pts[5, :, 2] = -np.inf
    fast = cv.xyz_to_cloud(pts, 'cam', 1.0)
    wide = cv.xyz_to_cloud(pts, 'cam', 1.0, extra={'w': np.ones((24, 32), np.float32)})
    big = cv.xyz_to_cloud(pts, 'cam', 1.0)
    big.is_bigendian = True
    big.data = pts.astype('>f4').tobytes()
    before = bytes(fast.data)
    out = cv.cloud_to_xyz(fast)
    assert out.dtype == np.float32 and out.shape == pts.shape and out.flags.writeable
    for other in (wide, big):
        np.testing.assert_array_equal(cv.cloud_to_xyz(other), out)
    np.testing.assert_array_equal(out, pts)
    out[:] = 0.0
    assert bytes(fast.data) == before
    # two of three fields, and the same fields in another order, are not the whole point
    np.testing.assert_array_equal(cv.cloud_fields(fast, ('z', 'x')), pts[..., [2, 0]])
    np.testing.assert_array_equal(cv.cloud_fields(fast, ('y',)), pts[..., 1:2])


def test_cloud_reader_handles_padding_float64_and_foreign_layouts():
    # A cloud as another driver might write it: float64 xyz, padding, row_step > width.
    n = 7
    rec = np.zeros(n, dtype=[('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('pad', 'V8')])
    pts = RNG.normal(size=(n, 3))
    rec['x'], rec['y'], rec['z'] = pts.T
    msg = cv.xyz_to_cloud(np.zeros((1, 3), np.float32), 'f', 0.0)
    msg.fields = [PointField(name=c, offset=8 * i, datatype=PointField.FLOAT64, count=1)
                  for i, c in enumerate('xyz')]
    msg.point_step, msg.width, msg.height = 32, n, 1
    msg.row_step = 32 * n + 16
    msg.data = rec.tobytes() + bytes(16)
    np.testing.assert_allclose(cv.cloud_to_xyz(msg), pts.astype(np.float32))


@pytest.mark.parametrize('mutate, match', [
    (lambda m: setattr(m, 'fields', m.fields[:2]), 'no field'),
    (lambda m: setattr(m, 'data', bytes(m.data)[:10]), 'truncated'),
    (lambda m: setattr(m, 'row_step', 3), 'row_step'),
])
def test_bad_clouds_raise_value_error_naming_the_problem(mutate, match):
    msg = cv.xyz_to_cloud(np.ones((4, 3), np.float32), 'f', 0.0)
    mutate(msg)
    with pytest.raises(ValueError, match=match):
        cv.cloud_to_xyz(msg)


@pytest.mark.parametrize('encoding, dtype, shape', [
    ('mono8', np.uint8, (30, 40)), ('rgb8', np.uint8, (30, 40, 3)),
    ('bgr8', np.uint8, (30, 40, 3)), ('32FC1', np.float32, (30, 40)),
    ('16UC1', np.uint16, (30, 40)), ('mono16', np.uint16, (30, 40)),
    ('bgra8', np.uint8, (30, 40, 4)),
])
def test_image_round_trip_every_encoding(encoding, dtype, shape):
    if np.issubdtype(dtype, np.floating):
        arr = RNG.normal(size=shape).astype(dtype)
        arr[0, 0] = np.nan
    else:
        arr = RNG.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True).astype(dtype)
    msg = cv.numpy_to_image(arr, encoding, 'cam', 1.25)
    back = cv.image_to_numpy(msg)
    assert back.dtype == arr.dtype and back.shape == arr.shape
    np.testing.assert_array_equal(back, arr)


def test_image_reader_honours_step_padding_and_big_endian():
    arr = RNG.integers(0, 65535, size=(5, 6), dtype=np.uint16)
    msg = cv.numpy_to_image(arr, '16UC1')
    padded = np.zeros((5, 16), np.uint8)
    padded[:, :12] = arr.astype('>u2').view(np.uint8).reshape(5, 12)
    msg.is_bigendian, msg.step, msg.data = 1, 16, padded.tobytes()
    np.testing.assert_array_equal(cv.image_to_numpy(msg), arr)


def test_image_errors():
    with pytest.raises(ValueError, match='does not fit encoding'):
        cv.numpy_to_image(np.zeros((4, 4), np.float32), 'mono8')
    msg = cv.numpy_to_image(np.zeros((4, 4), np.uint8), 'mono8')
    msg.encoding = 'yuv422'
    with pytest.raises(ValueError, match='unsupported image encoding'):
        cv.image_to_numpy(msg)
    msg.encoding, msg.data = 'mono8', bytes(3)
    with pytest.raises(ValueError, match='truncated'):
        cv.image_to_numpy(msg)


def test_grid_round_trip_and_grid_map_storage_order():
    elev = RNG.normal(size=(5, 3)).astype(np.float32)
    elev[1, 2] = np.nan
    grid = GridMap.from_layers(0.02, (1.0, -0.5), {'elevation': elev,
                                                   'observed': np.isfinite(elev)},
                               frame_id='map', stamp_s=3.5)
    msg = cv.grid_to_msg(grid, basic_layers=['elevation'])
    assert msg.info.length_x == pytest.approx(0.10) and msg.info.length_y == pytest.approx(0.06)
    assert msg.info.pose.position.x == pytest.approx(1.05)
    assert msg.info.pose.position.y == pytest.approx(-0.47)
    assert [d.label for d in msg.data[0].layout.dim] == ['column_index', 'row_index']
    # grid_map: element 0 is the max-x / max-y cell; column-major, so element 1 is one step -x.
    assert msg.data[0].data[0] == elev[4, 2]
    assert msg.data[0].data[1] == elev[3, 2]
    assert msg.data[0].data[5] == elev[4, 1]
    back = cv.msg_to_grid(msg)
    assert back.shape == grid.shape and back.origin_xy == pytest.approx(grid.origin_xy)
    assert back.frame_id == 'map' and back.stamp_s == pytest.approx(3.5)
    for name in grid.layers:
        np.testing.assert_array_equal(back[name], grid[name])


def test_grid_with_circular_start_index_is_unrolled():
    elev = np.arange(12, dtype=np.float32).reshape(4, 3)
    msg = cv.grid_to_msg(GridMap.from_layers(0.1, (0, 0), {'elevation': elev}))
    mat = np.asarray(msg.data[0].data).reshape((4, 3), order='F')
    msg.data[0].data = np.roll(mat, (1, 2), axis=(0, 1)).ravel(order='F')
    msg.outer_start_index, msg.inner_start_index = 1, 2
    np.testing.assert_array_equal(cv.msg_to_grid(msg)['elevation'], elev)


def test_bad_grids():
    msg = cv.grid_to_msg(GridMap.from_layers(0.1, (0, 0), {'elevation': np.zeros((4, 3))}))
    msg.data[0].data = np.zeros(5, np.float32)
    with pytest.raises(ValueError, match="layer 'elevation' has 5 values"):
        cv.msg_to_grid(msg)
    msg.info.resolution = 0.0
    with pytest.raises(ValueError, match='resolution'):
        cv.msg_to_grid(msg)


def test_pose_round_trip():
    T = make_T(rpy_to_R(0.1, -0.4, 2.9), [1.0, -2.0, 0.3])
    np.testing.assert_allclose(cv.pose_to_matrix(cv.matrix_to_pose(T)), T, atol=1e-12)
    np.testing.assert_allclose(cv.transform_to_matrix(cv.matrix_to_transform(T)), T, atol=1e-12)
    odom = cv.odometry(T, 'odom', 'base_link', 2.0, linear=(0.1, 0, 0))
    np.testing.assert_allclose(cv.pose_to_matrix(odom.pose.pose), T, atol=1e-12)
    bad = cv.matrix_to_pose(T)
    bad.orientation.w = bad.orientation.x = bad.orientation.y = bad.orientation.z = 0.0
    with pytest.raises(ValueError, match='quaternion'):
        cv.pose_to_matrix(bad)


def test_stereo_camera_info_round_trip_and_zero_baseline():
    stereo = StereoCamera(PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5), 0.09)
    left, right = cv.stereo_to_camera_info(stereo, 'camera_optical', 1.0)
    assert cv.camera_info_to_stereo(left, right) == stereo
    with pytest.raises(ValueError, match='baseline'):
        cv.camera_info_to_stereo(left, left)


def test_disparity_round_trip():
    stereo = StereoCamera(PinholeCamera(8, 6, 100.0, 100.0, 3.5, 2.5), 0.1)
    d = RNG.uniform(1, 60, size=(6, 8)).astype(np.float32)
    d[2, 3] = np.nan
    msg = cv.disparity_to_msg(d, stereo, 'cam', 0.0, 0.0, 64.0)
    back = cv.msg_to_disparity(msg)
    np.testing.assert_array_equal(np.isnan(back), np.isnan(d))
    np.testing.assert_array_equal(back[np.isfinite(d)], d[np.isfinite(d)])
    assert msg.f == 100.0 and msg.t == pytest.approx(0.1)


def test_stamp_conversion():
    assert cv.stamp_to_sec(cv.sec_to_stamp(12.999999999)) == pytest.approx(12.999999999)
    with pytest.raises(ValueError):
        cv.sec_to_stamp(-1.0)


def test_joint_state_to_arrays_orders_joints_and_names_each_problem():
    from sensor_msgs.msg import JointState
    from terrain_ros.conversions import JointStateError, joint_state_to_arrays
    want = ['a', 'b', 'c']
    msg = JointState(name=['c', 'x', 'a', 'b'], position=[3.0, 9.0, 1.0, 2.0],
                     velocity=[30.0, 90.0, 10.0, 20.0])
    q, dq, tau = joint_state_to_arrays(msg, want)
    np.testing.assert_array_equal(q, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(dq, [10.0, 20.0, 30.0])
    assert tau is None                                     # no efforts in the message
    for bad, key in ((JointState(name=['a', 'b'], position=[1.0, 2.0]), 'missing_joint'),
                     (JointState(name=want, position=[1.0, 2.0]), 'bad_length'),
                     (JointState(name=want, position=[1.0, np.nan, 3.0]), 'nan')):
        with pytest.raises(JointStateError) as err:
            joint_state_to_arrays(bad, want)
        assert err.value.key == f'joint_state_{key}'


def test_peek_stamp_reads_the_header_stamp_of_serialised_messages():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image
    from terrain_msgs.msg import TerrainGrid
    for msg in (Image(), TerrainGrid()):
        msg.header.stamp = cv.sec_to_stamp(1234.000000567)
        raw = serialize_message(msg)
        assert cv.peek_stamp(raw) == cv.stamp_key(msg.header.stamp) == (1234, 567)
    with pytest.raises(struct.error):
        cv.peek_stamp(b'\x00\x01\x00')
