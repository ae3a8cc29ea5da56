"""icp_mapper: localise each capture against the terrain (ICP seeded by dead reckoning) and keep
the coarse and fine terrain models (paper 000, section II; core: terrain_perception.mapping).

Subscriptions:
    /stereo/points         sensor_msgs/PointCloud2, organized, camera-optical frame (sensor data)
    /stereo/points_coarse  sensor_msgs/PointCloud2, its sparse subsample (sensor data; used for
                           ICP when ``use_coarse_cloud`` and one with the same stamp arrived)
    /odom/dead_reckoning   nav_msgs/Odometry, ``T_odom_base`` (reliable)
    /imu/data              sensor_msgs/Imu (sensor data; only with ``use_gravity_prior`` or
                           ``use_imu_rotation_prior``): the up vector, the body's attitude
    /joint_states          sensor_msgs/JointState (sensor data): the legs' pose at each cloud's
                           stamp, so points on the robot's own legs are not mapped
                           (``self_filter_margin_m``; no filter while none has arrived)
    /footstep_plan         terrain_msgs/FootstepPlan (reliable, transient local; only with
                           ``model_after_plan``): its stamp tells that a capture's plan is out,
                           so the coarse model's update need not compete with the fill and the
                           planner for the CPU
Publications:
    /icp/pose              geometry_msgs/PoseStamped, ``T_map_base`` of each capture (reliable)
    /icp/odom              nav_msgs/Odometry, the same with dead reckoning's twist (reliable)
    /icp/correction        geometry_msgs/PoseStamped, ``T_map_odom`` to re-anchor dead
                           reckoning (reliable, transient local)
    /map/fine              terrain_msgs/TerrainGrid: elevation, observed, variance, min, max,
                           count, last_seen (reliable, transient local)
    /map/coarse            sensor_msgs/PointCloud2, the ICP model in ``map`` (reliable,
                           transient local; every ``coarse_publish_every``-th capture, once
                           the model holds it)
    /map/capture_poses     geometry_msgs/PoseArray, camera poses kept with the map (reliable,
                           transient local)
    ~/diagnostics          diagnostic_msgs/DiagnosticArray: counters of refused input and
                           rejected alignments

The camera mount ``T_base_camera`` (and the IMU mount) come from the robot profile named by
the ``robot`` parameter. The dead-reckoning pose at a cloud's stamp is interpolated from the
odometry received so far. Every refused input (malformed / empty / all-NaN cloud, cloud older
than the map, odometry that goes back in time or jumps, no odometry for the cloud's stamp) is
counted under its reason key and logged once (then every 100th time); the maps are untouched.
A rejected alignment is counted too; the pose published for it is the dead-reckoning prior.
"""

from __future__ import annotations

from dataclasses import dataclass
from collections import deque
from typing import Deque, Dict, Optional
import time

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState, PointCloud2
from rclpy.clock import Clock, ClockType
from terrain_msgs.msg import FootstepPlan, TerrainGrid

from terrain_perception.config import param
from terrain_perception.kinematics import self_mask
from terrain_perception.mapping import (IcpMapper, MapperConfig, OdometryGate, PoseBuffer,
                                        map_frame_correction)
from terrain_perception.robot_model import load_robot_model
from terrain_perception.transforms import quat_to_R, yaw_of
from terrain_ros.conversions import (ConvertOnce, JointStateError, cloud_to_xyz, grid_to_msg,
                                     joint_state_to_arrays, make_header, matrix_to_pose,
                                     odometry, pose_stamped, pose_to_matrix, stamp_to_sec,
                                     xyz_to_cloud)
from terrain_ros.node import Counters, run_node
from terrain_ros.params import declare_config
from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS


@dataclass(frozen=True)
class IcpMapperNodeConfig:
    """Node-level parameters (the algorithm's own are :class:`MapperConfig`)."""

    robot: str = param('littledog', 'robot profile (config/robots/<name>.yaml) giving the '
                       'camera and IMU mounts')
    map_frame: str = param('map', 'frame of the maps and corrected poses')
    base_frame: str = param('base_link', 'body frame (child frame of /icp/odom)')
    use_coarse_cloud: bool = param(True, 'align /stereo/points_coarse when one with the '
                                   'cloud\'s stamp arrived, else subsample /stereo/points')
    odom_buffer_size: int = param(400, 'dead-reckoning poses kept for interpolation', 2, 100000)
    odom_max_extrapolation_s: float = param(0.25, 'a cloud may be this much newer [s] than the '
                                            'newest odometry', 0.0, 10.0)
    odom_max_speed_m_s: float = param(1.0, 'odometry moving faster than this [m/s] jumped',
                                      0.01, 100.0)
    odom_max_yaw_rate_deg_s: float = param(180.0, 'odometry turning faster than this [deg/s] '
                                           'jumped', 1.0, 10000.0)
    coarse_publish_every: int = param(5, 'publish /map/coarse every n-th fused capture', 1,
                                      1000)
    diagnostics_period_s: float = param(1.0, 'period of the counters message [s]', 0.05,
                                        3600.0)
    self_filter_margin_m: float = param(
        0.015, 'points within the foot radius plus this of a leg (thigh and shank segments, '
        'forward kinematics of /joint_states at the cloud\'s stamp) are dropped: the camera '
        'sees the front legs, which are not terrain [m] (negative = no filter)', -1.0, 0.5)
    self_filter_max_gap_s: float = param(
        0.1, 'the joint state used for a cloud must be stamped within this of it [s]; otherwise '
        'the cloud is mapped unfiltered and counted', 0.0, 10.0)
    imu_max_gap_s: float = param(
        0.05, 'the IMU attitude used for a cloud (use_imu_rotation_prior) must be stamped within '
        'this of it [s]; otherwise the prior is dead reckoning\'s alone', 0.0, 10.0)
    model_after_plan: bool = param(
        False, 'the coarse model\'s part of a capture\'s fusion (voxels, normals, index: 10-20 '
        'ms) and /map/coarse wait until the footstep plan of that capture is out '
        '(/footstep_plan with its stamp or a newer one), at most model_wait_max_s: the fill '
        'and the planner have the CPU meanwhile (the next cloud finishes it first in any '
        'case; false, the default: right after the fine map; session 51\'s A/B with this '
        'and the planner\'s patches after the plan too: the fill stage 4-7 ms shorter, '
        'capture-to-plan 1.02x on the median and its p95 worse, docs/CLOSED_LOOP.md)')
    model_wait_max_s: float = param(0.3, 'longest wait for that plan [s, wall clock]', 0.0,
                                    10.0)


def _odom_key(reason: str) -> str:
    if 'back in time' in reason:
        return 'odom_back_in_time'
    if 'jumped' in reason or 'turned' in reason:
        return 'odom_jump'
    return 'odom_invalid'


def _cloud_key(reason: str) -> str:
    for text, key in (('empty', 'empty_cloud'), ('no finite point', 'all_nan_cloud'),
                      ('older than the map', 'cloud_older_than_map'),
                      ('no field', 'cloud_missing_xyz'), ('not a float', 'cloud_not_float'),
                      ('valid points', 'too_few_points'), ('odometry', 'no_odometry')):
        if text in reason:
            return key
    return 'bad_cloud'


class IcpMapperNode(Node):
    """Dead-reckoning-seeded ICP localisation and terrain mapping; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('icp_mapper', **kwargs)
        self.node_cfg: IcpMapperNodeConfig = declare_config(self, IcpMapperNodeConfig)
        self.mapper_cfg: MapperConfig = declare_config(self, MapperConfig)
        self.robot = load_robot_model(self.node_cfg.robot)
        self.T_base_camera = np.asarray(self.robot.T_base_camera)
        self._T_camera_base = np.linalg.inv(self.T_base_camera)
        # f b of the stereo head sets each point's depth noise (MapperConfig.disparity_sigma_px)
        self.mapper = IcpMapper(self.mapper_cfg, self.T_base_camera,
                                self.robot.camera.fx * self.robot.baseline_m)
        c = self.node_cfg
        self.odom = PoseBuffer(c.odom_buffer_size, c.odom_max_extrapolation_s)
        self.gate = OdometryGate(c.odom_max_speed_m_s, c.odom_max_yaw_rate_deg_s)
        self.counters = Counters(self)
        self._coarse: Dict[tuple, PointCloud2] = {}
        self._twist = None
        self._up_base: Optional[np.ndarray] = None
        self._fine_stamp = None  # stamp of a fused map not yet published
        # a fused capture whose coarse-model part waits (model_after_plan): its stamp [s],
        # header stamp, wall deadline and whether /map/coarse goes out after it
        self._model_wait: Optional[tuple] = None
        self.model_waits_timed_out = 0
        self.captures = 0
        self._joints: Deque[tuple] = deque(maxlen=2000)   # (stamp [s], q (4, 3))
        self._joint_t: Deque[float] = deque(maxlen=2000)  # the same stamps, for np.fromiter
        self._pose_msgs = ConvertOnce(lambda tT: (float(tT[0]), tT[1].tobytes()),
                                      lambda tT: matrix_to_pose(tT[1]))  # -> Pose msg

        self.pub_pose = self.create_publisher(PoseStamped, '/icp/pose', RELIABLE_QOS)
        self.pub_odom = self.create_publisher(Odometry, '/icp/odom', RELIABLE_QOS)
        self.pub_corr = self.create_publisher(PoseStamped, '/icp/correction', LATCHED_QOS)
        self.pub_fine = self.create_publisher(TerrainGrid, '/map/fine', LATCHED_QOS)
        self.pub_coarse = self.create_publisher(PointCloud2, '/map/coarse', LATCHED_QOS)
        self.pub_poses = self.create_publisher(PoseArray, '/map/capture_poses', LATCHED_QOS)

        self.create_subscription(Odometry, '/odom/dead_reckoning', self._on_odom, RELIABLE_QOS)
        self.create_subscription(PointCloud2, '/stereo/points', self._on_cloud, SENSOR_QOS)
        if c.use_coarse_cloud:
            self.create_subscription(PointCloud2, '/stereo/points_coarse', self._on_coarse,
                                     SENSOR_QOS)
        self._attitudes: Deque[tuple] = deque(maxlen=400)   # (stamp [s], R_world_base)
        if self.mapper_cfg.use_gravity_prior or self.mapper_cfg.use_imu_rotation_prior:
            self.create_subscription(Imu, '/imu/data', self._on_imu, SENSOR_QOS)
        if c.self_filter_margin_m >= 0:
            self.create_subscription(JointState, '/joint_states', self._on_joint_state,
                                     SENSOR_QOS)
        self.create_timer(c.diagnostics_period_s, self._publish_diagnostics)
        if c.model_after_plan:
            self.create_subscription(FootstepPlan, '/footstep_plan', self._on_plan,
                                     LATCHED_QOS)
            # wall clock: the wait is for CPU, and simulated time may stand still
            self.create_timer(0.05, self._model_deadline,
                              clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'icp_mapper: robot {self.robot.name}, fine map '
                               f'{self.mapper.fine.shape} cells of '
                               f'{self.mapper_cfg.fine_resolution_m} m')

    # ------------------------------------------------------------------ inputs

    def _on_odom(self, msg: Odometry) -> None:
        try:
            t = stamp_to_sec(msg.header.stamp)
            T = pose_to_matrix(msg.pose.pose)
            self.gate.check(t, T)
            self.odom.add(t, T)
        except ValueError as exc:
            self.counters.bump(_odom_key(str(exc)), str(exc))
            return
        self._twist = msg.twist.twist

    def _on_joint_state(self, msg: JointState) -> None:
        try:
            q = joint_state_to_arrays(msg, self.robot.joint_names)[0]
        except JointStateError as exc:
            self.counters.bump('bad_joint_state', str(exc))
            return
        t = stamp_to_sec(msg.header.stamp)
        if self._joints and t < self._joints[-1][0]:
            self._joints.clear()                    # time went back (a replayed bag restarted)
            self._joint_t.clear()
        self._joints.append((t, q.reshape(4, 3)))
        self._joint_t.append(t)

    def _self_filter(self, cloud: np.ndarray, t: float) -> np.ndarray:
        """``cloud`` (camera frame) with the points on the robot's legs set to NaN."""
        margin = self.node_cfg.self_filter_margin_m
        if margin < 0 or not self._joints:
            return cloud
        stamps = np.fromiter(self._joint_t, float, len(self._joint_t))
        k = int(np.argmin(np.abs(stamps - t)))
        if abs(stamps[k] - t) > self.node_cfg.self_filter_max_gap_s:
            self.counters.bump('self_filter_no_joint_state',
                               f'no joint state within {self.node_cfg.self_filter_max_gap_s} s '
                               f'of the cloud at {t:.3f} s; mapped without the self filter')
            return cloud
        mask = self_mask(self.robot, self._joints[k][1], cloud, self._T_camera_base, margin)
        if not mask.any():
            return cloud
        out = np.array(cloud, dtype=np.float32 if cloud.dtype == np.float32 else np.float64)
        out[mask] = np.nan
        return out

    def _on_coarse(self, msg: PointCloud2) -> None:
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        self._coarse[key] = msg
        while len(self._coarse) > 5:  # bounded: only the latest few wait for their fine cloud
            self._coarse.pop(next(iter(self._coarse)))

    def _on_imu(self, msg: Imu) -> None:
        a = msg.linear_acceleration
        f = np.array([a.x, a.y, a.z], dtype=np.float64)
        n = np.linalg.norm(f)
        if not np.isfinite(n) or n < 1.0:
            self.counters.bump('bad_imu', f'IMU specific force {n:.2f} m/s^2 is not gravity-like')
            if np.isfinite(n):
                # Free fall: a slip or drop the leg odometry does not see; the next ICP
                # correction may be larger than the drift guard allows (note_disturbance).
                self.mapper.note_disturbance(stamp_to_sec(msg.header.stamp))
            return
        # at rest the accelerometer measures +g along "up"
        R_base_imu = np.asarray(self.robot.T_base_imu)[:3, :3]
        self._up_base = R_base_imu @ (f / n)
        o = msg.orientation
        q = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)
        qn = np.linalg.norm(q)
        if not np.isfinite(qn) or abs(qn - 1.0) > 0.1:
            self.counters.bump('bad_imu_orientation', f'IMU orientation quaternion norm {qn:.3f}')
            return
        t = stamp_to_sec(msg.header.stamp)
        if self._attitudes and t < self._attitudes[-1][0]:
            self._attitudes.clear()                 # time went back (a replayed bag restarted)
        self._attitudes.append((t, quat_to_R(q / qn) @ R_base_imu.T))

    def _attitude_at(self, t: float) -> Optional[np.ndarray]:
        """The IMU's ``R_world_base`` nearest to ``t`` within ``imu_max_gap_s``, else None."""
        if not self.mapper_cfg.use_imu_rotation_prior or not self._attitudes:
            return None
        stamp, R = min(self._attitudes, key=lambda a: abs(a[0] - t))
        if abs(stamp - t) > self.node_cfg.imu_max_gap_s:
            self.counters.bump('no_imu_attitude', f'no IMU attitude within '
                               f'{self.node_cfg.imu_max_gap_s} s of the cloud at {t:.3f} s')
            return None
        return R

    def _on_cloud(self, msg: PointCloud2) -> None:
        self._finish_model()               # the last capture's, if its plan never came
        self._align_and_publish(msg)
        # the coarse model's part of the fusion, after the capture's pose and fine map went
        # out: the fill node and the planner work on them meanwhile (IcpMapper.fuse); with
        # model_after_plan only once the plan is out, as they then have the CPU to themselves
        if self._model_wait is None or not self.node_cfg.model_after_plan:
            self._finish_model()

    def _on_plan(self, msg: FootstepPlan) -> None:
        if self._model_wait is not None and \
                stamp_to_sec(msg.header.stamp) >= self._model_wait[0] - 1e-6:
            self._finish_model()

    def _model_deadline(self) -> None:
        if self._model_wait is not None and time.monotonic() >= self._model_wait[2]:
            self.model_waits_timed_out += 1
            self._finish_model()

    def _finish_model(self) -> None:
        """The coarse model's part of the last fusion (``IcpMapper.finish_model``) and, when
        due, ``/map/coarse`` with that capture's stamp."""
        wait, self._model_wait = self._model_wait, None
        try:
            self.mapper.finish_model()
        except (ValueError, RuntimeError, IndexError) as exc:
            # One capture's model update must not take the node down: the pending part is
            # dropped (the model keeps every earlier capture), the next capture fuses anew.
            self.counters.bump('model_update_failed', f'coarse model update of the last '
                               f'capture failed and was skipped: {type(exc).__name__}: {exc}',
                               self.get_logger().error)
            return
        if wait is not None and wait[3]:
            self.pub_coarse.publish(xyz_to_cloud(self.mapper.coarse_points(),
                                                 self.node_cfg.map_frame, wait[1]))

    def _align_and_publish(self, msg: PointCloud2) -> None:
        t = stamp_to_sec(msg.header.stamp)
        try:
            cloud = cloud_to_xyz(msg)
            if cloud.size == 0:
                raise ValueError('empty cloud (no points)')
            coarse = None
            key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
            if key in self._coarse:
                coarse = self._self_filter(cloud_to_xyz(self._coarse.pop(key)), t)
            cloud = self._self_filter(cloud, t)
            if t < self.mapper.stamp_s - self.mapper_cfg.stamp_tolerance_s:
                raise ValueError(f'cloud at {t:.3f} s is older than the map '
                                 f'({self.mapper.stamp_s:.3f} s)')
            prepared = self.mapper.prepare(cloud, coarse)  # content first, then odometry
            T_odom_base = self.odom.at(t)
            up_cam = None
            if self._up_base is not None:
                up_cam = self.T_base_camera[:3, :3].T @ self._up_base
            res = self.mapper.update(cloud, T_odom_base, t, up_camera=up_cam,
                                     prepared=prepared, attitude=self._attitude_at(t),
                                     defer_model=True)
        except ValueError as exc:
            self.counters.bump(_cloud_key(str(exc)), str(exc))
            return
        self.captures += 1
        if res.multi_start > 0:
            # relocalisation (after a refusal, a disturbance or a misfit) left the prior's ICP
            C = map_frame_correction(res.T_map_base_icp, res.T_map_base_prior)
            self.get_logger().info(
                f'relocalisation at {t:.2f} s: start {res.multi_start} fits better than the '
                f'prior\'s ICP, shift ({1e3 * C[0, 3]:.0f}, {1e3 * C[1, 3]:.0f}) mm from the '
                f'prior ({"accepted" if res.accepted else res.reason})')
        if not res.accepted:
            self.counters.bump('rejected_alignment', res.reason)
            if 'drift' in res.reason and res.T_map_base_icp is not None:
                # every one: a run of these is a slip (confirmed or not), worth reading back
                C = map_frame_correction(res.T_map_base_icp, res.T_map_base_prior)
                d = C[:3, 3]
                self.get_logger().info(
                    f'drift guard refused ICP at {t:.2f} s: shift ({1e3 * d[0]:.0f}, '
                    f'{1e3 * d[1]:.0f}, {1e3 * d[2]:.0f}) mm, turn '
                    f'{np.degrees(yaw_of(C)):.2f} deg yaw '
                    f'({res.correction_deg:.2f} deg in all)')
        elif res.confirmed:
            self.get_logger().warn(
                f'accepted a {res.correction_m * 1e3:.0f} mm / {res.correction_deg:.1f} deg '
                f'correction the drift guard had refused: at least '
                f'{self.mapper_cfg.confirm_captures} captures in a row measured it (a slip '
                f'dead reckoning missed)')
        self._publish(res, msg.header.stamp)

    # ------------------------------------------------------------------ outputs

    def _publish(self, res, stamp) -> None:
        c = self.node_cfg
        self.pub_pose.publish(pose_stamped(res.T_map_base, c.map_frame, stamp))
        tw = self._twist
        lin = (tw.linear.x, tw.linear.y, tw.linear.z) if tw is not None else (0, 0, 0)
        ang = (tw.angular.x, tw.angular.y, tw.angular.z) if tw is not None else (0, 0, 0)
        self.pub_odom.publish(odometry(res.T_map_base, c.map_frame, c.base_frame, stamp,
                                       lin, ang))
        self.pub_corr.publish(pose_stamped(self.mapper.T_map_odom, c.map_frame, stamp))
        if not res.fused:
            return
        # The capture poses first: the fill starts once it has both, and the ~130 poses take
        # a few ms of Python to convert and serialise, which it would otherwise wait for
        # after the map arrived.
        stamps, poses = self.mapper.capture_poses()
        arr = PoseArray(header=make_header(c.map_frame, stamp))
        arr.poses = self._capture_pose_msgs(stamps, poses)
        self.pub_poses.publish(arr)
        self._fine_stamp = stamp
        self._publish_fine()
        coarse = (self.mapper.counters['fused'] % c.coarse_publish_every == 1
                  or c.coarse_publish_every == 1)
        self._model_wait = (stamp_to_sec(stamp), stamp,
                            time.monotonic() + c.model_wait_max_s, coarse)

    def _capture_pose_msgs(self, stamps: np.ndarray, poses: np.ndarray) -> list:
        """Pose messages of the kept capture poses, each converted once (keyed by its stamp
        and matrix bytes) instead of all ~200 every capture."""
        return self._pose_msgs(zip(stamps, poses))

    def _publish_fine(self) -> None:
        # the whole window (~2.5 MB at 300 x 300 x 7) is converted only when someone listens;
        # a map fused while nobody did goes out from the timer once a subscriber appears
        # (transient local: a late joiner then gets the current map, not a stale one)
        if self._fine_stamp is None or self.pub_fine.get_subscription_count() == 0:
            return
        grid = self.mapper.fine_grid(self.node_cfg.map_frame)
        grid.metadata.clear()  # capture poses go out on their own topic
        self.pub_fine.publish(grid_to_msg(grid, self._fine_stamp, basic_layers=('elevation',)))
        self._fine_stamp = None
        self.counters.counts['fine_maps_published'] += 1

    def _publish_diagnostics(self) -> None:
        self._publish_fine()
        for k, v in self.mapper.counters.items():
            self.counters.counts[f'mapper_{k}'] = v
        # the IMU's estimated yaw drift [deg/s] (a gyro bias; see imu_yaw_drift_window_s)
        self.counters.counts['mapper_imu_yaw_drift_deg_s'] = round(
            self.mapper.imu_yaw_drift_deg_s, 4)
        # the factor applied to dead reckoning's steps in the prior (odometry_scale_window_m)
        self.counters.counts['mapper_odometry_scale'] = round(self.mapper.odometry_scale, 4)
        self.counters.publish()


def main(args=None) -> int:
    return run_node(IcpMapperNode, args=args)


if __name__ == '__main__':
    main()
