"""Message <-> numpy conversions: the only place that knows both shapes.

Pure functions (no node, no clock). Every reader raises ``ValueError`` with a message naming the
problem when a message cannot be converted, so a node can count and log it and keep running.

* PointCloud2 <-> ``(H, W, 3)`` organized or ``(N, 3)`` float32 arrays, NaN = invalid point,
  optional extra float32 fields.
* Image <-> arrays for mono8, mono16, rgb8, bgr8, rgba8, bgra8, 32FC1, 16UC1.
* TerrainGrid <-> :class:`terrain_perception.grid.GridMap` (grid_map storage order on the wire).
* Pose / Transform / Odometry <-> 4x4 arrays; CameraInfo pair <-> ``StereoCamera``.
"""

from __future__ import annotations

import array
import struct
from typing import Dict, Mapping, Optional, Sequence, Tuple

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Transform, Vector3
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CameraInfo, Image, JointState, PointCloud2, PointField
from std_msgs.msg import Float32MultiArray, Header, MultiArrayDimension
from stereo_msgs.msg import DisparityImage
from terrain_msgs.msg import Stance, TerrainGrid, TerrainGridInfo

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.grid import GridMap
from terrain_perception.transforms import R_to_quat, quat_to_R

# ---------------------------------------------------------------------------------------------
# time and headers


def stamp_to_sec(stamp: Time) -> float:
    """builtin_interfaces/Time -> seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def stamp_key(stamp: Time) -> Tuple[int, int]:
    """``(sec, nanosec)`` of a builtin_interfaces/Time: a hashable, ordered stamp."""
    return (int(stamp.sec), int(stamp.nanosec))


def peek_stamp(raw: bytes) -> Tuple[int, int]:
    """:func:`stamp_key` of a serialised message that starts with a std_msgs/Header, without
    deserialising it (CDR: a 4-byte encapsulation header whose second byte is 1 for little
    endian, then int32 sec, uint32 nanosec). ``struct.error`` if ``raw`` is too short."""
    sec, nsec = struct.unpack_from('<iI' if raw[1] == 1 else '>iI', raw, 4)
    return (int(sec), int(nsec))


def sec_to_stamp(t: float) -> Time:
    """Seconds -> builtin_interfaces/Time (t >= 0)."""
    if not np.isfinite(t) or t < 0:
        raise ValueError(f'cannot make a ROS time from {t} s')
    sec = int(np.floor(t))
    nsec = int(round((t - sec) * 1e9))
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return Time(sec=sec, nanosec=nsec)


def make_header(frame_id: str, stamp) -> Header:
    """Header from a frame and a stamp given as Time or float seconds."""
    if not isinstance(stamp, Time):
        stamp = sec_to_stamp(float(stamp))
    return Header(frame_id=frame_id, stamp=stamp)


# ---------------------------------------------------------------------------------------------
# PointCloud2

_PF_DTYPES = {
    PointField.INT8: np.int8, PointField.UINT8: np.uint8, PointField.INT16: np.int16,
    PointField.UINT16: np.uint16, PointField.INT32: np.int32, PointField.UINT32: np.uint32,
    PointField.FLOAT32: np.float32, PointField.FLOAT64: np.float64,
}


def _cloud_dtype(msg: PointCloud2) -> np.dtype:
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _PF_DTYPES:
            raise ValueError(f'point field {f.name!r} has unknown datatype {f.datatype}')
        base = np.dtype(_PF_DTYPES[f.datatype]).newbyteorder('>' if msg.is_bigendian else '<')
        names.append(f.name)
        formats.append(base if f.count <= 1 else (base, (f.count,)))
        offsets.append(f.offset)
    return np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                     'itemsize': msg.point_step})


def cloud_fields(msg: PointCloud2, names: Sequence[str]) -> np.ndarray:
    """Float32 array ``(H, W, len(names))`` (organized) or ``(N, len(names))`` of named fields."""
    present = {f.name: f for f in msg.fields}
    missing = [n for n in names if n not in present]
    if missing:
        raise ValueError(f'point cloud has no field(s) {missing} (fields: {sorted(present)})')
    n_pts = msg.width * msg.height
    if msg.point_step <= 0 and n_pts > 0:
        raise ValueError('point cloud has point_step 0')
    if msg.row_step < msg.width * msg.point_step:
        raise ValueError(f'point cloud row_step {msg.row_step} < width*point_step '
                         f'{msg.width * msg.point_step}')
    if len(msg.data) < msg.row_step * msg.height:
        raise ValueError(f'point cloud data has {len(msg.data)} bytes, expected '
                         f'{msg.row_step * msg.height} (truncated message)')
    for n in names:
        if present[n].offset + np.dtype(_PF_DTYPES.get(present[n].datatype, np.uint8)).itemsize \
                > msg.point_step:
            raise ValueError(f'point field {n!r} lies outside point_step {msg.point_step}')
    try:        # the message's array('B') as it is: bytes() would copy the 3.7 MB once more
        raw = np.frombuffer(msg.data, np.uint8, count=msg.row_step * msg.height)
    except (TypeError, ValueError):
        raw = np.frombuffer(bytes(msg.data), np.uint8, count=msg.row_step * msg.height)
    k = len(names)
    if (not msg.is_bigendian and msg.point_step == 4 * k
            and msg.row_step == msg.width * msg.point_step
            and all(present[n].datatype == PointField.FLOAT32 and present[n].count <= 1
                    and present[n].offset == 4 * i for i, n in enumerate(names))):
        # The fields asked for are the whole point, little-endian float32 in that order (what
        # the stereo node publishes): the data already is the array. One copy (the result
        # owns its memory, as the general path's does) instead of bytes(), the record view's
        # three strided field copies and their stack.
        out = raw.view('<f4').reshape(msg.height, msg.width, k).astype(np.float32)
        return out if msg.height > 1 else out.reshape(-1, k)
    dtype = _cloud_dtype(msg)
    rows = raw.reshape(msg.height, msg.row_step)[:, :msg.width * msg.point_step]
    pts = np.ascontiguousarray(rows).view(dtype).reshape(msg.height, msg.width)
    out = np.stack([pts[n].astype(np.float32) for n in names], axis=-1)
    return out if msg.height > 1 else out.reshape(-1, len(names))


def cloud_to_xyz(msg: PointCloud2) -> np.ndarray:
    """xyz of a cloud: ``(H, W, 3)`` if organized (height > 1), else ``(N, 3)``, float32 [m]."""
    for n in ('x', 'y', 'z'):
        f = next((f for f in msg.fields if f.name == n), None)
        if f is not None and f.datatype not in (PointField.FLOAT32, PointField.FLOAT64):
            raise ValueError(f'point field {n!r} is not a float (datatype {f.datatype})')
    return cloud_fields(msg, ('x', 'y', 'z'))


def xyz_to_cloud(points: np.ndarray, frame_id: str, stamp,
                 extra: Optional[Mapping[str, np.ndarray]] = None) -> PointCloud2:
    """PointCloud2 with float32 x, y, z (+ ``extra`` float32 fields) from ``(H, W, 3)``/``(N, 3)``.

    An ``(H, W, 3)`` array gives an organized cloud (height H, width W, ``is_dense`` False when
    any point is NaN); ``(N, 3)`` gives height 1.
    """
    pts = np.asarray(points, dtype='<f4')
    if pts.ndim == 2 and pts.shape[1] == 3:
        h, w = 1, pts.shape[0]
    elif pts.ndim == 3 and pts.shape[2] == 3:
        h, w = pts.shape[:2]
    else:
        raise ValueError(f'points must be (N, 3) or (H, W, 3), got {pts.shape}')
    extra = dict(extra or {})
    names = ['x', 'y', 'z'] + list(extra)
    if extra:
        rec = np.empty((h, w), dtype=[(n, '<f4') for n in names])
        flat = pts.reshape(h, w, 3)
        rec['x'], rec['y'], rec['z'] = flat[..., 0], flat[..., 1], flat[..., 2]
        for n, v in extra.items():
            v = np.asarray(v, dtype=np.float32)
            if v.size != h * w:
                raise ValueError(f'extra field {n!r} has {v.size} values for {h * w} points')
            rec[n] = v.reshape(h, w)
    else:
        rec = pts                 # little-endian x, y, z rows: the record layout already
    msg = PointCloud2()
    msg.header = make_header(frame_id, stamp)
    msg.height, msg.width = h, w
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, n in enumerate(names)]
    msg.is_bigendian = False  # written little-endian ('<f4') on every host
    msg.point_step = 4 * len(names)
    msg.row_step = msg.point_step * w
    msg.data = _field_array(rec)
    msg.is_dense = bool(np.isfinite(pts).all())
    return msg


def _field_array(a: np.ndarray, typecode: str = 'B') -> array.array:
    """The bytes of ``a`` (C order) as the ``array`` a uint8[] (``'B'``) or float32[] (``'f'``,
    ``a`` float32) message field holds, taken as it is: one copy (``tobytes()`` and then the
    field's own ``array('B', ...)`` were two of a 3.7 MB cloud, ~1.5 ms per 640x480 frame)."""
    out = array.array(typecode)
    out.frombytes(np.ascontiguousarray(a).reshape(-1).view(np.uint8))
    return out


# ---------------------------------------------------------------------------------------------
# Image

_ENCODINGS: Dict[str, Tuple[type, int]] = {
    'mono8': (np.uint8, 1), '8UC1': (np.uint8, 1),
    'mono16': (np.uint16, 1), '16UC1': (np.uint16, 1),
    'rgb8': (np.uint8, 3), 'bgr8': (np.uint8, 3), '8UC3': (np.uint8, 3),
    'rgba8': (np.uint8, 4), 'bgra8': (np.uint8, 4),
    '32FC1': (np.float32, 1),
}


def image_to_numpy(msg: Image) -> np.ndarray:
    """Array ``(H, W)`` or ``(H, W, C)`` of an Image (a copy; honours ``step`` padding)."""
    if msg.encoding not in _ENCODINGS:
        raise ValueError(f'unsupported image encoding {msg.encoding!r} '
                         f'(supported: {", ".join(sorted(_ENCODINGS))})')
    dt, ch = _ENCODINGS[msg.encoding]
    dtype = np.dtype(dt).newbyteorder('>' if msg.is_bigendian else '<')
    row_bytes = msg.width * ch * dtype.itemsize
    if msg.height == 0 or msg.width == 0:
        raise ValueError(f'image is empty ({msg.width}x{msg.height})')
    if msg.step < row_bytes:
        raise ValueError(f'image step {msg.step} < {row_bytes} bytes per row '
                         f'for {msg.width} px of {msg.encoding}')
    if len(msg.data) < msg.step * msg.height:
        raise ValueError(f'image data has {len(msg.data)} bytes, expected '
                         f'{msg.step * msg.height} (truncated message)')
    raw = np.frombuffer(bytes(msg.data), np.uint8, count=msg.step * msg.height)
    rows = np.ascontiguousarray(raw.reshape(msg.height, msg.step)[:, :row_bytes])
    arr = rows.view(dtype).astype(dtype.newbyteorder('='))
    return arr.reshape(msg.height, msg.width) if ch == 1 else arr.reshape(msg.height, msg.width, ch)


def numpy_to_image(arr: np.ndarray, encoding: str, frame_id: str = '', stamp=0.0) -> Image:
    """Image message of an array; the array's dtype and channels must fit ``encoding``."""
    if encoding not in _ENCODINGS:
        raise ValueError(f'unsupported image encoding {encoding!r}')
    dt, ch = _ENCODINGS[encoding]
    arr = np.asarray(arr)
    shape_ok = arr.ndim == 2 if ch == 1 else (arr.ndim == 3 and arr.shape[2] == ch)
    if ch == 1 and arr.ndim == 3 and arr.shape[2] == 1:
        arr, shape_ok = arr[..., 0], True
    if not shape_ok or arr.dtype != np.dtype(dt):
        raise ValueError(f'array {arr.dtype} {arr.shape} does not fit encoding {encoding} '
                         f'({np.dtype(dt)}, {ch} channel(s))')
    arr = np.ascontiguousarray(arr.astype(np.dtype(dt).newbyteorder('<'), copy=False))
    msg = Image()
    msg.header = make_header(frame_id, stamp)
    msg.height, msg.width = arr.shape[:2]
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = msg.width * ch * arr.dtype.itemsize
    msg.data = _field_array(arr)
    return msg


# ---------------------------------------------------------------------------------------------
# TerrainGrid (grid_map storage order)


def grid_to_msg(grid: GridMap, stamp=None, basic_layers: Sequence[str] = ()) -> TerrainGrid:
    """TerrainGrid of a GridMap. ``stamp`` defaults to ``grid.stamp_s``."""
    msg = TerrainGrid()
    msg.header = make_header(grid.frame_id, grid.stamp_s if stamp is None else stamp)
    nx, ny = grid.shape
    info = TerrainGridInfo()
    info.resolution = grid.resolution_m
    info.length_x, info.length_y = (float(v) for v in grid.length_xy)
    cx, cy = grid.center_xy
    info.pose = Pose(position=Point(x=cx, y=cy, z=0.0), orientation=Quaternion(w=1.0))
    msg.info = info
    msg.layers = list(grid.layers)
    msg.basic_layers = [b for b in basic_layers if b in grid.layers]
    data = []
    for name in msg.layers:
        # grid_map: matrix (rows=nx, cols=ny), index (0,0) at max x / max y, column-major.
        mat = grid.layers[name][::-1, ::-1]
        arr = Float32MultiArray()
        arr.layout.dim = [
            MultiArrayDimension(label='column_index', size=ny, stride=nx * ny),
            MultiArrayDimension(label='row_index', size=nx, stride=nx),
        ]
        arr.layout.data_offset = 0
        # array.array: rclpy range-checks a numpy array's floats one by one in Python
        # (~137 ms for a 300 x 300 x 7 map); an array('f') is taken as it is (~1 ms).
        arr.data = _field_array(np.asarray(mat, dtype=np.float32).ravel(order='F'), 'f')
        data.append(arr)
    msg.data = data
    msg.outer_start_index = 0
    msg.inner_start_index = 0
    return msg


def msg_to_grid(msg: TerrainGrid) -> GridMap:
    """GridMap of a TerrainGrid (honours grid_map's circular-buffer start indices)."""
    res = float(msg.info.resolution)
    if not np.isfinite(res) or res <= 0:
        raise ValueError(f'terrain grid has invalid resolution {res}')
    nx = int(round(msg.info.length_x / res))
    ny = int(round(msg.info.length_y / res))
    if nx <= 0 or ny <= 0:
        raise ValueError(f'terrain grid has no cells (length {msg.info.length_x} x '
                         f'{msg.info.length_y} m at {res} m)')
    if len(msg.layers) != len(msg.data):
        raise ValueError(f'terrain grid names {len(msg.layers)} layers but carries '
                         f'{len(msg.data)} data arrays')
    q = msg.info.pose.orientation
    if abs(abs(q.w) - 1.0) > 1e-6:
        raise ValueError('terrain grid is rotated in its frame; only axis-aligned grids are '
                         'supported')
    layers = {}
    for name, arr in zip(msg.layers, msg.data):
        vals = np.asarray(arr.data, dtype=np.float32)
        if vals.size != nx * ny:
            raise ValueError(f'layer {name!r} has {vals.size} values, the grid has '
                             f'{nx}x{ny} = {nx * ny} cells')
        mat = vals.reshape((nx, ny), order='F')
        if msg.outer_start_index or msg.inner_start_index:
            mat = np.roll(mat, (-int(msg.outer_start_index), -int(msg.inner_start_index)),
                          axis=(0, 1))
        layers[name] = mat[::-1, ::-1].copy()
    cx, cy = msg.info.pose.position.x, msg.info.pose.position.y
    origin = (cx - 0.5 * nx * res, cy - 0.5 * ny * res)
    grid = GridMap(res, origin, (nx, ny), layers, frame_id=msg.header.frame_id,
                   stamp_s=stamp_to_sec(msg.header.stamp))
    return grid


# ---------------------------------------------------------------------------------------------
# poses


def msg_to_stance(msg: Stance) -> Tuple[np.ndarray, Optional[int]]:
    """``(feet (4, 3), next_leg or None)`` of a terrain_msgs/Stance; ValueError naming the
    problem for feet that are not 4 finite points or a next_leg that is not a leg."""
    feet = np.array([[p.x, p.y, p.z] for p in msg.feet], dtype=np.float64).reshape(-1, 3)
    if feet.shape != (4, 3) or not np.all(np.isfinite(feet)):
        raise ValueError('/walking/stance feet are not 4 finite points')
    if msg.next_leg not in (0, 1, 2, 3, Stance.LEG_NONE):
        raise ValueError(f'/walking/stance next_leg {msg.next_leg} is not a leg')
    return feet, None if msg.next_leg == Stance.LEG_NONE else int(msg.next_leg)


class ConvertOnce:
    """Converts each item of a republished list once: the mapper republishes every kept
    capture pose with each capture (~100-200), and a kept pose never changes. ``key(item)``
    identifies an item (exact bytes: -0.0 is not 0.0); the cache keeps only the items of the
    latest call, and an item whose conversion raises is never kept (the error propagates)."""

    def __init__(self, key, convert) -> None:
        self._key, self._convert, self._cache = key, convert, {}

    def __call__(self, items) -> list:
        cache, keep, out = self._cache, {}, []
        for item in items:
            k = self._key(item)
            v = cache.get(k)
            if v is None:
                v = self._convert(item)
            keep[k] = v
            out.append(v)
        self._cache = keep
        return out


def _pose_bytes(p: Pose) -> bytes:
    a, q = p.position, p.orientation
    return struct.pack('7d', a.x, a.y, a.z, q.x, q.y, q.z, q.w)


def pose_matrices_once() -> ConvertOnce:
    """:class:`ConvertOnce` of geometry_msgs/Pose -> 4x4 (``pose_to_matrix``)."""
    return ConvertOnce(_pose_bytes, pose_to_matrix)


class JointStateError(ValueError):
    """A JointState that does not give the robot's joints; ``key`` names the problem for a
    node's counters."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def joint_state_to_arrays(msg: JointState, joint_names: Sequence[str]
                          ) -> Tuple[np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]:
    """``(q, dq, tau)`` in the order of ``joint_names`` (``(12,)`` each). ``dq`` / ``tau`` are
    None when the message has no velocities / efforts for every name (their NaNs are kept: the
    caller decides). Raises :class:`JointStateError` for a missing joint, positions that do not
    match the names, or a NaN/inf position."""
    names = list(msg.name)
    missing = [n for n in joint_names if n not in names]
    if missing:
        raise JointStateError('joint_state_missing_joint', f'joint state lacks {missing}; '
                              'ignored')
    if len(msg.position) != len(names):
        raise JointStateError('joint_state_bad_length', f'{len(msg.position)} positions for '
                              f'{len(names)} names; ignored')
    idx = [names.index(n) for n in joint_names]
    q = np.asarray(msg.position, dtype=float)[idx]
    if not np.all(np.isfinite(q)):
        raise JointStateError('joint_state_nan', 'joint state holds NaN/inf; ignored')
    dq = np.asarray(msg.velocity, dtype=float)[idx] if len(msg.velocity) == len(names) else None
    tau = np.asarray(msg.effort, dtype=float)[idx] if len(msg.effort) == len(names) else None
    return q, dq, tau


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """4x4 transform of a geometry_msgs/Pose."""
    q = pose.orientation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    n = np.linalg.norm(quat)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError('pose has an invalid (zero or non-finite) quaternion')
    p = pose.position
    t = np.array([p.x, p.y, p.z], dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise ValueError('pose has a non-finite position')
    T = np.eye(4)
    T[:3, :3] = quat_to_R(quat)
    T[:3, 3] = t
    return T


def matrix_to_pose(T: np.ndarray) -> Pose:
    """geometry_msgs/Pose of a 4x4 transform."""
    T = np.asarray(T, dtype=np.float64)
    q = R_to_quat(T[:3, :3])
    return Pose(position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                       w=float(q[3])))


def transform_to_matrix(tf: Transform) -> np.ndarray:
    """4x4 of a geometry_msgs/Transform."""
    t, q = tf.translation, tf.rotation
    return pose_to_matrix(Pose(position=Point(x=t.x, y=t.y, z=t.z), orientation=q))


def matrix_to_transform(T: np.ndarray) -> Transform:
    """geometry_msgs/Transform of a 4x4."""
    p = matrix_to_pose(T)
    return Transform(translation=Vector3(x=p.position.x, y=p.position.y, z=p.position.z),
                     rotation=p.orientation)


def pose_stamped(T: np.ndarray, frame_id: str, stamp) -> PoseStamped:
    """PoseStamped of a 4x4."""
    return PoseStamped(header=make_header(frame_id, stamp), pose=matrix_to_pose(T))


def odometry(T: np.ndarray, frame_id: str, child_frame_id: str, stamp,
             linear: Sequence[float] = (0, 0, 0), angular: Sequence[float] = (0, 0, 0)) -> Odometry:
    """nav_msgs/Odometry with pose ``T_frame_child`` and a body-frame twist."""
    msg = Odometry()
    msg.header = make_header(frame_id, stamp)
    msg.child_frame_id = child_frame_id
    msg.pose.pose = matrix_to_pose(T)
    msg.twist.twist.linear = Vector3(x=float(linear[0]), y=float(linear[1]), z=float(linear[2]))
    msg.twist.twist.angular = Vector3(x=float(angular[0]), y=float(angular[1]),
                                      z=float(angular[2]))
    return msg


# ---------------------------------------------------------------------------------------------
# cameras


def camera_info_to_pinhole(info: CameraInfo) -> PinholeCamera:
    """Pinhole model of a rectified CameraInfo (uses the projection matrix P)."""
    P = np.asarray(info.p, dtype=np.float64).reshape(3, 4)
    if info.width == 0 or info.height == 0:
        raise ValueError('camera_info has zero image size')
    if not np.all(np.isfinite(P)) or P[0, 0] <= 0 or P[1, 1] <= 0:
        raise ValueError(f'camera_info projection matrix has no positive focal length '
                         f'(P[0,0]={P[0, 0]}, P[1,1]={P[1, 1]})')
    return PinholeCamera(int(info.width), int(info.height), float(P[0, 0]), float(P[1, 1]),
                         float(P[0, 2]), float(P[1, 2]))


def camera_info_to_stereo(left: CameraInfo, right: CameraInfo) -> StereoCamera:
    """Rectified stereo model of a left/right CameraInfo pair (baseline = -P_r[0,3] / P_r[0,0])."""
    cam = camera_info_to_pinhole(left)
    right_cam = camera_info_to_pinhole(right)
    if (right_cam.width, right_cam.height) != (cam.width, cam.height):
        raise ValueError(f'left camera_info is {cam.width}x{cam.height}, right is '
                         f'{right_cam.width}x{right_cam.height}')
    P = np.asarray(right.p, dtype=np.float64).reshape(3, 4)
    baseline = -P[0, 3] / P[0, 0]
    if not np.isfinite(baseline) or baseline <= 0:
        raise ValueError(f'right camera_info gives a baseline of {baseline} m (P[0,3]={P[0, 3]}); '
                         'a rectified right camera needs P[0,3] = -fx * baseline < 0')
    return StereoCamera(cam, float(baseline))


def stereo_to_camera_info(stereo: StereoCamera, frame_id: str,
                          stamp) -> Tuple[CameraInfo, CameraInfo]:
    """Left/right CameraInfo of a rectified stereo model (no distortion, identity R)."""
    c = stereo.left
    out = []
    for tx in (0.0, -c.fx * stereo.baseline_m):
        info = CameraInfo()
        info.header = make_header(frame_id, stamp)
        info.width, info.height = c.width, c.height
        info.distortion_model = 'plumb_bob'
        info.d = [0.0] * 5
        info.k = [c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [c.fx, 0.0, c.cx, tx, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        out.append(info)
    return out[0], out[1]


def disparity_to_msg(disparity: np.ndarray, stereo: StereoCamera, frame_id: str, stamp,
                     min_disparity: float, max_disparity: float) -> DisparityImage:
    """stereo_msgs/DisparityImage of a float disparity map [px]; invalid pixels become -1."""
    d = np.where(np.isfinite(disparity), disparity, -1.0).astype(np.float32)
    msg = DisparityImage()
    msg.header = make_header(frame_id, stamp)
    msg.image = numpy_to_image(d, '32FC1', frame_id, stamp)
    msg.f = float(stereo.left.fx)
    msg.t = float(stereo.baseline_m)
    msg.min_disparity = float(min_disparity)
    msg.max_disparity = float(max_disparity)
    msg.delta_d = 1.0 / 16.0
    return msg


def msg_to_disparity(msg: DisparityImage) -> np.ndarray:
    """Float disparity [px] of a DisparityImage, NaN where invalid (below min_disparity)."""
    d = image_to_numpy(msg.image).astype(np.float32)
    valid = np.isfinite(d) & (d > 0) & (d >= msg.min_disparity)
    return np.where(valid, d, np.nan).astype(np.float32)
