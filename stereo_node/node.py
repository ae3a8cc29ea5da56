"""stereo_node: rectified stereo pair -> disparity, organized cloud, coarse cloud, ground plane.

Subscriptions (sensor-data QoS unless noted):
    /stereo/left/image_rect, /stereo/right/image_rect  sensor_msgs/Image (mono8, rgb8, bgr8)
    /stereo/left/camera_info, /stereo/right/camera_info  sensor_msgs/CameraInfo
    /capture_request  std_msgs/Header (reliable; only used when ``capture_on_request``)
Publications:
    /stereo/disparity      stereo_msgs/DisparityImage (sensor data)
    /stereo/points         sensor_msgs/PointCloud2, organized, left camera frame (sensor data)
    /stereo/points_coarse  sensor_msgs/PointCloud2, organized coarse subsample (sensor data)
    /stereo/ground_plane   terrain_msgs/GroundPlane (reliable)
    ~/diagnostics          diagnostic_msgs/DiagnosticArray: counters of dropped/refused input

Left and right images are paired by exact header stamp in a small bounded synchroniser
(message_filters is not available). Camera infos are the latest received per side. A complete
pair is processed at once (``process_on_arrival``) unless the previous one was taken less than
``1 / max_rate_hz`` ago; then it waits in a one-slot buffer, a newer pair replaces it (counted
as ``stale_pair``), and a timer processes the slot when the rate allows. The rate is a bound on
the node's CPU, so it runs on the steady (wall) clock even with ``use_sim_time``
(``rate_clock``): on the simulated clock, a simulation at a real-time factor of 0.2 held a pair
five times longer than the bound meant (a requested capture 20-50 ms of simulated time after a
periodic one waited ~0.3-0.5 s of wall; session 53). With capture requests, only the first
pair stamped at or after a request is processed (paper 000: pictures when the body is stable).

The disparity image and the ground plane are computed only while someone subscribes to them
(``always_process`` computes them regardless); the clouds are published first.

Every refused input is counted under its reason key and logged once (then every 100th time);
nothing is published for it.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from stereo_msgs.msg import DisparityImage
from terrain_msgs.msg import GroundPlane as GroundPlaneMsg

from terrain_perception.camera import StereoCamera
from terrain_perception.config import check_value, param
from terrain_perception.ground_plane import GroundPlaneConfig, fit_ground_plane
from terrain_perception.robot_model import available_robots, load_robot_model
from terrain_perception.stereo import (StereoConfig, StereoInputError, StereoPipeline,
                                       floor_disparity_range)
from terrain_ros.conversions import (camera_info_to_stereo, disparity_to_msg, image_to_numpy,
                                     make_header, stamp_key, stamp_to_sec, xyz_to_cloud)
from terrain_ros.node import Counters, run_node
from terrain_ros.params import declare_config
from terrain_ros.qos import RELIABLE_QOS, SENSOR_QOS

ACCEPTED_ENCODINGS = {'mono8': 'rgb', 'rgb8': 'rgb', 'bgr8': 'bgr'}

Stamp = Tuple[int, int]


@dataclass(frozen=True)
class StereoNodeConfig:
    """Node-level parameters (the algorithms' own are StereoConfig and GroundPlaneConfig)."""

    capture_on_request: bool = param(False, 'process only the first pair at or after each '
                                     '/capture_request stamp')
    max_rate_hz: float = param(15.0, 'upper bound on processed pairs per second [Hz]',
                               0.1, 1000.0)
    rate_clock: str = param('steady', 'clock of the max_rate_hz bound and its timer: steady '
                            '(wall time, a bound on the CPU) or node (the node\'s clock, '
                            'simulated with use_sim_time: up to the fifty-second session; '
                            'the latency benchmark\'s baseline)', choices=('steady', 'node'))
    sync_queue_size: int = param(10, 'unpaired images kept per side while waiting for the '
                                 'other side', 1, 1000)
    estimate_ground_plane: bool = param(True, 'fit and publish the RANSAC ground plane')
    diagnostics_period_s: float = param(1.0, 'period of the counters message [s]', 0.05, 3600.0)
    always_process: bool = param(False, 'process pairs even when no one subscribes to an '
                                 'output')
    process_on_arrival: bool = param(True, 'process a pair in its image callback when the rate '
                                     'allows; false: only on the rate timer\'s next tick (up to '
                                     'a period later; the latency baseline of terrain-bench '
                                     'latency)')
    robot: str = param('', 'robot profile (config/robots/) whose camera mount sizes the '
                       'disparity search range: the floor at the bottom image row at standing '
                       'height, x disparity_margin, rounded up to 16 px, with the focal length '
                       'and baseline of camera_info (littledog: 96, frog: 112 at full '
                       'resolution); it replaces num_disparities. Ground nearer than the range '
                       'reaches is matched to the wrong pixel (the loop ran FROG-I with '
                       'LittleDog\'s 96 px). Empty: num_disparities as set')
    disparity_margin: float = param(1.25, 'see robot: the search range covers the floor\'s '
                                    'disparity times this (nearer obstacles, body motion) [-]',
                                    1.0, 10.0)


class StereoSync:
    """Exact-stamp pairing of left and right images with bounded queues.

    ``add(side, msg)`` returns the completed ``(left, right)`` pair or None, and the list of
    stamps that can no longer be paired (older than the pair just completed, or pushed out of a
    full queue), for the caller to count.
    """

    def __init__(self, queue_size: int) -> None:
        self.queue_size = int(queue_size)
        self._q: Dict[str, 'OrderedDict[Stamp, Image]'] = {'left': OrderedDict(),
                                                            'right': OrderedDict()}

    def add(self, side: str, msg: Image):
        other = 'right' if side == 'left' else 'left'
        key = stamp_key(msg.header.stamp)
        dropped = []
        mine, theirs = self._q[side], self._q[other]
        if key in theirs:
            partner = theirs.pop(key)
            # Anything older than a completed pair on either side will never be paired.
            for q in (mine, theirs):
                for k in [k for k in q if k < key]:
                    del q[k]
                    dropped.append(k)
            pair = (msg, partner) if side == 'left' else (partner, msg)
            return pair, dropped
        if key in mine:
            dropped.append(key)              # duplicate stamp: keep the newer image
        mine[key] = msg
        while len(mine) > self.queue_size:
            k, _ = mine.popitem(last=False)
            dropped.append(k)
        return None, dropped


class StereoNode(Node):
    """Stereo pair -> disparity, clouds and ground plane; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('stereo_node', **kwargs)
        self.node_cfg: StereoNodeConfig = declare_config(self, StereoNodeConfig,
                                                         on_change=self._on_node_cfg)
        self.stereo_cfg: StereoConfig = declare_config(self, StereoConfig,
                                                       on_change=self._on_stereo_cfg)
        self.plane_cfg: GroundPlaneConfig = declare_config(
            self, GroundPlaneConfig, prefix='ground_plane', on_change=self._on_plane_cfg)
        # Per-field checks run in declare_config; this one refuses runtime sets that break a
        # rule across fields or of the whole config (e.g. num_disparities % 16).
        self.add_on_set_parameters_callback(self._check_whole_stereo_config)

        self.counters = Counters(self)
        self._robot = None
        self._logged_range: Optional[int] = None
        if self.node_cfg.robot:
            if self.node_cfg.robot not in available_robots():
                raise ValueError(f'unknown robot {self.node_cfg.robot!r} '
                                 f'(known: {available_robots()})')
            self._robot = load_robot_model(self.node_cfg.robot)
        self._sync = StereoSync(self.node_cfg.sync_queue_size)
        self._info: Dict[str, Optional[CameraInfo]] = {'left': None, 'right': None}
        self._stereo: Optional[StereoCamera] = None
        self._stereo_key = None
        self._pipeline: Optional[StereoPipeline] = None
        self._pending: Optional[Tuple[Image, Image]] = None
        self._request_stamp: Optional[float] = None
        # The rate bound's clock (see the module docstring).
        self._rate_clock = self._make_rate_clock(self.node_cfg.rate_clock)
        self._last_taken_ns: Optional[int] = None   # rate clock when a pair was last taken
        self.pairs_taken = 0          # pairs handed to process_pair (published or refused)
        self.frames_processed = 0
        self.planes_fitted = 0        # ground planes fitted (only while someone subscribes)

        self.pub_disparity = self.create_publisher(DisparityImage, '/stereo/disparity', SENSOR_QOS)
        self.pub_points = self.create_publisher(PointCloud2, '/stereo/points', SENSOR_QOS)
        self.pub_coarse = self.create_publisher(PointCloud2, '/stereo/points_coarse', SENSOR_QOS)
        self.pub_plane = self.create_publisher(GroundPlaneMsg, '/stereo/ground_plane',
                                               RELIABLE_QOS)

        for side in ('left', 'right'):
            self.create_subscription(Image, f'/stereo/{side}/image_rect',
                                     lambda m, s=side: self._on_image(s, m), SENSOR_QOS)
            self.create_subscription(CameraInfo, f'/stereo/{side}/camera_info',
                                     lambda m, s=side: self._on_info(s, m), SENSOR_QOS)
        self.create_subscription(Header, '/capture_request', self._on_capture_request,
                                 RELIABLE_QOS)
        self._timer = self.create_timer(1.0 / self.node_cfg.max_rate_hz, self._on_timer,
                                        clock=self._rate_clock)
        self._diag_timer = self.create_timer(self.node_cfg.diagnostics_period_s,
                                             self.counters.publish)

    # ------------------------------------------------------------------ parameters

    def _check_whole_stereo_config(self, params) -> SetParametersResult:
        names = {f.name for f in dataclasses.fields(StereoConfig)}
        try:
            changes = {p.name: check_value(StereoConfig, p.name, p.value)
                       for p in params if p.name in names}
            if changes:
                dataclasses.replace(self.stereo_cfg, **changes)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _on_node_cfg(self, cfg: StereoNodeConfig) -> None:
        old, self.node_cfg = self.node_cfg, cfg
        if (cfg.robot, cfg.disparity_margin) != (old.robot, old.disparity_margin):
            if cfg.robot and cfg.robot not in available_robots():
                self.node_cfg = dataclasses.replace(cfg, robot=old.robot)
                self.counters.bump('bad_parameter', f'unknown robot {cfg.robot!r} (known: '
                                                    f'{available_robots()}); kept {old.robot!r}')
            else:
                self._robot = load_robot_model(cfg.robot) if cfg.robot else None
            self._pipeline = None                # the search range is sized anew
        self._sync.queue_size = cfg.sync_queue_size
        if (cfg.max_rate_hz, cfg.rate_clock) != (old.max_rate_hz, old.rate_clock):
            if cfg.rate_clock != old.rate_clock:
                self._rate_clock = self._make_rate_clock(cfg.rate_clock)
                self._last_taken_ns = None      # another clock's reading means nothing here
            self.destroy_timer(self._timer)
            self._timer = self.create_timer(1.0 / cfg.max_rate_hz, self._on_timer,
                                            clock=self._rate_clock)
        if cfg.diagnostics_period_s != old.diagnostics_period_s:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(cfg.diagnostics_period_s,
                                                 self.counters.publish)

    def _on_stereo_cfg(self, cfg: StereoConfig) -> None:
        self.stereo_cfg = cfg
        self._pipeline = None                    # rebuilt with the new config on the next pair

    def _on_plane_cfg(self, cfg: GroundPlaneConfig) -> None:
        self.plane_cfg = cfg

    # ------------------------------------------------------------------ inputs

    def _on_info(self, side: str, msg: CameraInfo) -> None:
        self._info[side] = msg

    def _on_capture_request(self, msg: Header) -> None:
        self._request_stamp = stamp_to_sec(msg.stamp)
        if self._pending is not None and self.node_cfg.capture_on_request:
            self._try_pending()

    def _on_image(self, side: str, msg: Image) -> None:
        pair, dropped = self._sync.add(side, msg)
        for k in dropped:
            self.counters.bump('unpaired_stamp', f'no {side}/other image with stamp '
                                                 f'{k[0]}.{k[1]:09d} s arrived; image dropped')
        if pair is None:
            return
        if self._pending is not None and not self.node_cfg.capture_on_request:
            # (With capture requests, unrequested pairs are skipped by design, not dropped.)
            self.counters.bump('stale_pair', 'a newer pair arrived before the previous one '
                                             'was processed; the older pair was dropped')
        self._pending = pair
        if self.node_cfg.capture_on_request:
            self._try_pending()
        elif self.node_cfg.process_on_arrival:
            self._on_timer()

    def _make_rate_clock(self, which: str) -> Clock:
        return Clock(clock_type=ClockType.STEADY_TIME) if which == 'steady' else self.get_clock()

    def _rate_allows(self, now_ns: int) -> bool:
        """True when no pair was taken within the last ``1 / max_rate_hz`` of the rate clock
        before ``now_ns`` (or that clock went back, e.g. a restarted simulation)."""
        if self._last_taken_ns is None:
            return True
        elapsed = now_ns - self._last_taken_ns
        return elapsed < 0 or elapsed >= 1e9 / self.node_cfg.max_rate_hz

    def _on_timer(self) -> None:
        if self.node_cfg.capture_on_request or self._pending is None:
            return
        now_ns = self._rate_clock.now().nanoseconds
        if self._rate_allows(now_ns):
            pair, self._pending = self._pending, None
            self._last_taken_ns = now_ns
            self.pairs_taken += 1
            self.process_pair(*pair)

    def _try_pending(self) -> None:
        if self._request_stamp is None or self._pending is None:
            return
        t = stamp_to_sec(self._pending[0].header.stamp)
        if t >= self._request_stamp:
            pair, self._pending = self._pending, None
            self._request_stamp = None
            self.pairs_taken += 1
            self.process_pair(*pair)

    # ------------------------------------------------------------------ processing

    def _wanted(self, pub) -> bool:
        return self.node_cfg.always_process or pub.get_subscription_count() > 0

    def _has_listeners(self) -> bool:
        return any(self._wanted(p) for p in (self.pub_disparity, self.pub_points,
                                             self.pub_coarse, self.pub_plane))

    def _camera(self, left: Image) -> Optional[StereoCamera]:
        li, ri = self._info['left'], self._info['right']
        if li is None or ri is None:
            missing = ' and '.join(s for s in ('left', 'right') if self._info[s] is None)
            self.counters.bump('missing_camera_info', f'no {missing} camera_info received yet; '
                                                      'pair dropped')
            return None
        key = (tuple(li.p), tuple(ri.p), li.width, li.height, ri.width, ri.height)
        if key != self._stereo_key:
            try:
                stereo = camera_info_to_stereo(li, ri)
            except ValueError as exc:
                self.counters.bump('bad_camera_info', f'{exc}; pair dropped')
                return None
            self._stereo, self._stereo_key, self._pipeline = stereo, key, None
        if (left.width, left.height) != (self._stereo.left.width, self._stereo.left.height):
            self.counters.bump('size_mismatch', f'image is {left.width}x{left.height}, '
                                                f'camera_info is {self._stereo.left.width}x'
                                                f'{self._stereo.left.height}; pair dropped')
            return None
        return self._stereo

    def _images(self, left: Image, right: Image):
        for side, m in (('left', left), ('right', right)):
            if m.encoding not in ACCEPTED_ENCODINGS:
                self.counters.bump('bad_encoding', f'{side} image encoding {m.encoding!r} is '
                                                   f'not one of {sorted(ACCEPTED_ENCODINGS)}; '
                                                   'pair dropped')
                return None
        if left.encoding != right.encoding:
            self.counters.bump('encoding_mismatch', f'left is {left.encoding}, right is '
                                                    f'{right.encoding}; pair dropped')
            return None
        if (left.width, left.height) != (right.width, right.height):
            self.counters.bump('size_mismatch', f'left is {left.width}x{left.height}, right is '
                                                f'{right.width}x{right.height}; pair dropped')
            return None
        try:
            return image_to_numpy(left), image_to_numpy(right)
        except ValueError as exc:
            self.counters.bump('bad_image', f'{exc}; pair dropped')
            return None

    def process_pair(self, left: Image, right: Image) -> bool:
        """Process one stamped pair and publish; False (counted) when it was refused."""
        if not self._has_listeners():
            return False
        imgs = self._images(left, right)
        if imgs is None:
            return False
        stereo = self._camera(left)
        if stereo is None:
            return False
        if self._pipeline is None:
            self._pipeline = self._make_pipeline(stereo)
            if self._pipeline is None:
                return False
        try:
            frame = self._pipeline.process(*imgs, ACCEPTED_ENCODINGS[left.encoding])
        except StereoInputError as exc:
            self.counters.bump(exc.key, f'{exc}; pair dropped')
            return False
        stamp, frame_id = left.header.stamp, left.header.frame_id
        c = self._pipeline.config
        # The clouds first: the ICP mapper (and the rest of the capture-to-plan chain) waits
        # on them. An output nobody subscribes to is not computed (the ROS "lazy publisher"
        # idiom): in the closed loop no node reads the ground plane, and its RANSAC fit
        # (~19 ms of CPU per 640x480 frame) ran while the mapper aligned the same capture.
        self.pub_points.publish(xyz_to_cloud(frame.points, frame_id, stamp))
        self.pub_coarse.publish(xyz_to_cloud(frame.coarse, frame_id, stamp))
        if self._wanted(self.pub_disparity):
            self.pub_disparity.publish(disparity_to_msg(
                frame.disparity, stereo, frame_id, stamp, float(c.min_disparity),
                float(c.min_disparity + c.num_disparities - 1)))
        if self.node_cfg.estimate_ground_plane and self._wanted(self.pub_plane):
            self._publish_plane(frame.points, frame_id, stamp)
        self.frames_processed += 1
        return True

    def _make_pipeline(self, stereo: StereoCamera) -> Optional[StereoPipeline]:
        """The pipeline for ``stereo``; with ``robot`` set, its disparity range sized by the
        robot's camera mount (:func:`floor_disparity_range`). None (counted) if that fails."""
        if self._robot is None:
            return StereoPipeline(self.stereo_cfg, stereo)
        T = np.eye(4)
        T[2, 3] = self._robot.standing_height_m
        try:
            nd = floor_disparity_range(stereo, T @ self._robot.T_base_camera,
                                       self.node_cfg.disparity_margin)
            # (the pipeline checks the range against the image width)
            pipeline = StereoPipeline(dataclasses.replace(self.stereo_cfg, num_disparities=nd),
                                      stereo)
        except ValueError as exc:
            self.counters.bump('bad_disparity_range',
                               f'robot {self.node_cfg.robot!r}: {exc}; pair dropped')
            return None
        if nd != self._logged_range:
            self._logged_range = nd
            self.get_logger().info(
                f'disparity search range {nd} px from the {self.node_cfg.robot} camera mount '
                f'(fx {stereo.left.fx:.1f} px, baseline {stereo.baseline_m:.3f} m)')
        return pipeline

    def _publish_plane(self, points: np.ndarray, frame_id: str, stamp) -> None:
        self.planes_fitted += 1
        try:
            plane = fit_ground_plane(points, self.plane_cfg)
        except ValueError as exc:
            self.counters.bump('no_ground_plane', str(exc))
            return
        msg = GroundPlaneMsg()
        msg.header = make_header(frame_id, stamp)
        msg.normal.x, msg.normal.y, msg.normal.z = (float(v) for v in plane.normal)
        msg.d = float(plane.d)
        msg.pitch = float(plane.pitch_rad)
        msg.height = float(plane.height_m)
        msg.inlier_ratio = float(plane.inlier_ratio)
        msg.inliers = int(plane.inliers)
        self.pub_plane.publish(msg)


def main(args=None) -> int:
    return run_node(StereoNode, args=args)


if __name__ == '__main__':
    raise SystemExit(main())
