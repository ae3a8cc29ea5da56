"""walking_controller: footstep plan -> joint trajectories, dead reckoning, capture requests.

Wraps ``terrain_perception.controller.WalkingController`` (paper 000 sec. IV, paper 002 sec.
III): a statically stable crawl (or Shao's discontinuous trot when the plan asks for it).

Subscriptions:
    /footstep_plan     terrain_msgs/FootstepPlan (reliable, transient local): replaces the
                       pending footsteps (the step in progress finishes); a plan with a non-OK
                       status or GAIT_STAND clears them and the robot stands
    /joint_states      sensor_msgs/JointState (sensor data): initial stance, stillness and,
                       when it carries efforts, touchdown sensing (foot forces from torques)
    /imu/data          sensor_msgs/Imu (sensor data): body tilt, levelled at each body shift
    /icp/correction    geometry_msgs/PoseStamped ``T_map_odom`` (reliable, transient local)
    /map/filled        terrain_msgs/TerrainGrid (reliable, transient local; with
                       ``use_terrain_map``): swing paths clear its elevation layer
Publications:
    /joint_commands        trajectory_msgs/JointTrajectory (reliable): points every
                           ``point_dt_s`` over ``horizon_s`` from header.stamp (the bridge
                           interpolates them at its physics rate)
    /odom/dead_reckoning   nav_msgs/Odometry odom -> base_link along the desired trajectory
                           (reliable); the ICP prior
    /capture_request       std_msgs/Header (reliable): the body is still, take a picture
    /walking/stance        terrain_msgs/Stance (reliable, transient local): feet after the
                           step in progress and the next leg, in ``map``, on every change
    ~/diagnostics          diagnostic_msgs/DiagnosticArray: counters of refused input

Time is the node clock (``use_sim_time`` with the simulator). The odom frame starts equal to
``map`` at the configured initial pose; ``/icp/correction`` re-anchors it afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Header
from terrain_msgs.msg import FootstepPlan, Stance, TerrainGrid
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from terrain_perception import kinematics
from terrain_perception.config import param
from terrain_perception.controller import WalkingConfig, WalkingController
from terrain_perception.robot_model import load_robot_model
from terrain_perception.transforms import make_T, quat_to_R, rot_z, transform_points
from terrain_ros.conversions import (JointStateError, joint_state_to_arrays, make_header,
                                     msg_to_grid, odometry, pose_to_matrix, sec_to_stamp)
from terrain_ros.node import Counters, now_s, run_node
from terrain_ros.params import declare_config
from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS

GAITS = {FootstepPlan.GAIT_STAND: 'stand', FootstepPlan.GAIT_WALK: 'walk',
         FootstepPlan.GAIT_TROT: 'trot'}


@dataclass(frozen=True)
class WalkingNodeConfig:
    """Node-level parameters (the controller's own are WalkingConfig)."""

    robot: str = param('littledog', 'robot profile: config/robots/<name>.yaml or a path')
    control_rate_hz: float = param(50.0, 'joint trajectories published per second [Hz]',
                                   1.0, 1000.0)
    horizon_s: float = param(0.5, 'time covered by each published trajectory [s]; longer than '
                             'the worst gap between ticks, so a late tick does not stall the '
                             'bridge mid-motion', 0.0, 5.0)
    point_dt_s: float = param(0.01, 'spacing of the trajectory points [s]', 0.001, 1.0)
    initial_x_m: float = param(0.0, 'base x in map at start-up (odom = map until ICP) [m]')
    initial_y_m: float = param(0.0, 'base y in map at start-up [m]')
    initial_yaw_rad: float = param(0.0, 'base heading in map at start-up [rad]', -3.1416,
                                   3.1416)
    ground_z_m: float = param(0.0, 'ground height under the feet at start-up, map [m]')
    use_terrain_map: bool = param(True, 'clear the terrain of /map/filled with the swings')
    request_captures: bool = param(True, 'publish /capture_request when the body is still')
    diagnostics_period_s: float = param(1.0, 'period of ~/diagnostics [s]', 0.05, 3600.0)


class WalkingControllerNode(Node):
    """Footstep plans in, joint trajectories / odometry / capture requests out."""

    def __init__(self, **kwargs) -> None:
        super().__init__('walking_controller', **kwargs)
        self.node_cfg: WalkingNodeConfig = declare_config(self, WalkingNodeConfig)
        self.ctl_cfg: WalkingConfig = declare_config(self, WalkingConfig,
                                                     on_change=self._on_ctl_cfg)
        self.model = load_robot_model(self.node_cfg.robot)
        self.controller = WalkingController(self.model, self.ctl_cfg)
        self.counters = Counters(self)
        self._q: Optional[np.ndarray] = None
        self._dq: Optional[np.ndarray] = None
        self._tau: Optional[np.ndarray] = None
        self._R_base: Optional[np.ndarray] = None
        self._started = False
        self._durations: list = []
        self.plans_received = 0

        self.pub_cmd = self.create_publisher(JointTrajectory, '/joint_commands', RELIABLE_QOS)
        self.pub_odom = self.create_publisher(Odometry, '/odom/dead_reckoning', RELIABLE_QOS)
        self.pub_capture = self.create_publisher(Header, '/capture_request', RELIABLE_QOS)
        self.pub_stance = self.create_publisher(Stance, '/walking/stance', LATCHED_QOS)
        self._stance_key = None
        self.create_subscription(FootstepPlan, '/footstep_plan', self._on_plan, LATCHED_QOS)
        self.create_subscription(JointState, '/joint_states', self._on_joint_state, SENSOR_QOS)
        self.create_subscription(Imu, '/imu/data', self._on_imu, SENSOR_QOS)
        self.create_subscription(PoseStamped, '/icp/correction', self._on_correction,
                                 LATCHED_QOS)
        if self.node_cfg.use_terrain_map:
            self.create_subscription(TerrainGrid, '/map/filled', self._on_terrain, LATCHED_QOS)
        self.create_timer(1.0 / self.node_cfg.control_rate_hz, self._on_timer)
        self.create_timer(self.node_cfg.diagnostics_period_s, self.counters.publish)

    # ------------------------------------------------------------------ parameters
    def _on_ctl_cfg(self, cfg: WalkingConfig) -> None:
        # Takes effect for segments planned from now on.
        self.ctl_cfg = cfg
        self.controller.config = cfg

    def _now(self) -> float:
        return now_s(self)

    # ------------------------------------------------------------------ inputs
    def _on_joint_state(self, msg: JointState) -> None:
        try:
            q, dq, tau = joint_state_to_arrays(msg, self.model.joint_names)
        except JointStateError as exc:
            self.counters.bump(exc.key, str(exc))
            return
        self._q = q
        if dq is not None:
            self._dq = dq if np.all(np.isfinite(dq)) else None
        self._tau = tau if tau is not None and np.all(np.isfinite(tau)) else None

    def _on_imu(self, msg: Imu) -> None:
        o = msg.orientation
        quat = np.array([o.x, o.y, o.z, o.w], dtype=float)
        n = float(np.linalg.norm(quat))
        if not np.all(np.isfinite(quat)) or abs(n - 1.0) > 0.05:
            self.counters.bump('imu_bad_orientation',
                               f'IMU orientation {quat.tolist()} is not a unit quaternion; '
                               f'ignored')
            return
        # R_world_base = R_world_imu R_imu_base
        self._R_base = quat_to_R(quat / n) @ self.model.T_base_imu[:3, :3].T

    def _on_correction(self, msg: PoseStamped) -> None:
        try:
            self.controller.apply_correction(pose_to_matrix(msg.pose))
        except ValueError as exc:
            self.counters.bump('bad_correction', f'/icp/correction refused: {exc}')

    def _on_terrain(self, msg: TerrainGrid) -> None:
        try:
            grid = msg_to_grid(msg)
        except ValueError as exc:
            self.counters.bump('bad_terrain', f'/map/filled refused: {exc}')
            return
        if grid.frame_id not in ('', 'map'):
            self.counters.bump('terrain_frame', f'/map/filled in frame {grid.frame_id!r}, '
                                                'expected map; ignored')
            return
        from terrain_perception.grid import ELEVATION
        if ELEVATION not in grid:
            self.counters.bump('terrain_no_elevation', f'/map/filled has no {ELEVATION!r} '
                                                       'layer; ignored')
            return
        self.controller.set_height_map(grid)

    def _on_plan(self, msg: FootstepPlan) -> None:
        self.plans_received += 1
        now = self._now()
        if msg.status != FootstepPlan.STATUS_OK or msg.gait_mode == FootstepPlan.GAIT_STAND:
            self.controller.clear_plan()
            if msg.status != FootstepPlan.STATUS_OK:
                self.counters.bump(f'plan_status_{msg.status}',
                                   f'plan not OK ({msg.status_text!r}); standing')
            return
        gait = GAITS.get(msg.gait_mode)
        frame = msg.header.frame_id or 'map'
        try:
            if gait is None:
                raise ValueError(f'unknown gait_mode {msg.gait_mode}')
            if frame not in ('map', 'odom'):
                raise ValueError(f"footsteps in frame {frame!r}, expected 'map' or 'odom'")
            steps = sorted(msg.footsteps, key=lambda f: f.step_index)
            legs = np.array([f.leg for f in steps], dtype=int)
            pos = np.array([[f.position.x, f.position.y, f.position.z] for f in steps],
                           dtype=float).reshape(-1, 3)
            if not self._started:
                raise ValueError('no joint state received yet')
            self.controller.set_footsteps(legs, pos, gait, now, frame=frame)
        except ValueError as exc:
            self.counters.bump('bad_plan', f'footstep plan refused: {exc}')

    # ------------------------------------------------------------------ control tick
    def _start(self, t: float) -> None:
        c = self.node_cfg
        q = self._q.reshape(4, 3)
        contact_z = kinematics.forward(self.model, q)[:, 2] - self.model.foot_radius_m
        z0 = c.ground_z_m - float(np.mean(contact_z))
        T0 = make_T(rot_z(c.initial_yaw_rad), [c.initial_x_m, c.initial_y_m, z0])
        self.controller.reset(t, q, T0)
        self._started = True

    def _on_timer(self) -> None:
        if self._q is None:
            return
        t = self._now()
        if not self._started:
            self._start(t)
        err_before = self.controller.last_error
        try:
            self.controller.update(t, self._q, self._dq, self._tau, self._R_base)
        except ValueError as exc:
            self.counters.bump('controller_error', f'controller refused the tick: {exc}')
            return
        if self.controller.last_error and self.controller.last_error != err_before:
            self.counters.bump('step_refused', self.controller.last_error)
        c = self.node_cfg
        n = int(round(c.horizon_s / c.point_dt_s)) + 1
        offsets = np.arange(n) * c.point_dt_s
        if len(self._durations) != n:
            self._durations = [Duration(sec=int(o), nanosec=int(round((o - int(o)) * 1e9)))
                               for o in offsets]
        cmd = self.controller.preview(t + offsets)
        traj = JointTrajectory()
        traj.header = make_header('base_link', t)
        traj.joint_names = list(self.model.joint_names)
        pos, vel = cmd.positions.tolist(), cmd.velocities.tolist()
        traj.points = [JointTrajectoryPoint(positions=pos[k], velocities=vel[k],
                                            time_from_start=self._durations[k])
                       for k in range(n)]
        self.pub_cmd.publish(traj)

        T = self.controller.odom_pose
        v, w = self.controller.odom_velocity()
        R = T[:3, :3]
        self.pub_odom.publish(odometry(T, 'odom', 'base_link', t, R.T @ v, R.T @ w))
        if c.request_captures and self.controller.capture_due(t):
            self.pub_capture.publish(Header(stamp=sec_to_stamp(t), frame_id='base_link'))
        self._publish_stance(t)

    def _publish_stance(self, t: float) -> None:
        ctl = self.controller
        feet, next_leg = ctl.upcoming_stance()
        if feet is None:
            return
        feet = transform_points(ctl.T_map_odom, feet)
        key = (np.round(feet, 4).tobytes(), next_leg, ctl.steps_done, ctl.pending_steps,
               ctl.last_error)
        if key == self._stance_key:
            return
        self._stance_key = key
        msg = Stance()
        msg.header = make_header('map', t)
        msg.feet = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in feet]
        msg.next_leg = Stance.LEG_NONE if next_leg is None else int(next_leg)
        msg.steps_done = int(ctl.steps_done)
        msg.pending_steps = int(ctl.pending_steps)
        msg.last_error = ctl.last_error
        self.pub_stance.publish(msg)


def main(args=None) -> int:
    return run_node(WalkingControllerNode, args=args)


__all__ = ['WalkingControllerNode', 'WalkingNodeConfig', 'main']
