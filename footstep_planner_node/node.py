"""footstep_planner: contact patches + cost map -> receding-horizon footstep plan with a gait.

Subscriptions:
    /map/filled      terrain_msgs/TerrainGrid (reliable, transient local): the filled map with
                     its ``cost`` layer (or, with ``planner.cost_source`` kolter/shao, any map
                     with ``elevation``). Every new map triggers a replan (receding horizon).
    /stereo/points   sensor_msgs/PointCloud2, organized, camera frame (sensor data)
    /imu/data        sensor_msgs/Imu (sensor data): absolute orientation -> gravity
    /icp/pose        geometry_msgs/PoseStamped (reliable): robot pose ``T_map_base``
    /goal_pose       geometry_msgs/PoseStamped (reliable): goal; without one, straight ahead
                     along the line of the first plan (``planner.straight_lookahead_m``)
    /walking/stance  terrain_msgs/Stance (reliable, transient local): the controller's feet
                     after the step in progress and its next leg; plans start from there
                     (without it: the nominal stance at the pose, first leg free); a step
                     it refused (``last_error``) without stepping is not offered again from
                     that stance for 10 s, even where the dry run of its checks accepts it
Publications:
    /footstep_plan            terrain_msgs/FootstepPlan (reliable, transient local)
    /footstep_plan/markers    visualization_msgs/MarkerArray (reliable)
    /contact_patches          terrain_msgs/ContactPatchArray (reliable), in ``map`` when the
                              robot pose is known, else in the cloud's frame; built only
                              while someone subscribes (the planner uses the patches itself)
    /contact_patches/markers  visualization_msgs/MarkerArray (reliable)
    /map/cost_grid            nav_msgs/OccupancyGrid (reliable, transient local): cost scaled
                              to 0..100 for viewers (-1 unknown)
    /footstep_plan/body_path  nav_msgs/Path (reliable): the body path the plan steered along
                              (``planner.body_path``), at the map's height under it; empty
                              when the plan had none
    ~/diagnostics             diagnostic_msgs/DiagnosticArray: counters of refused input

Bad input never kills the node: a malformed message is counted and logged once; a map or pose
the planner cannot use yields a plan with an explanatory status and no footsteps.
"""

from __future__ import annotations

import array
from dataclasses import dataclass
from typing import Optional

import numpy as np
from geometry_msgs.msg import Point, PoseStamped, Vector3
from nav_msgs.msg import OccupancyGrid, Path
from rclpy.node import Node
from sensor_msgs.msg import Imu, PointCloud2
from terrain_msgs.msg import ContactPatch, ContactPatchArray, Footstep as FootstepMsg
from terrain_msgs.msg import FootstepPlan as FootstepPlanMsg
from terrain_msgs.msg import Stance, TerrainGrid
from visualization_msgs.msg import Marker, MarkerArray

from terrain_perception import footsteps as fs
from terrain_perception.config import load_config, param
from terrain_perception.controller import WalkingConfig, check_footsteps
from terrain_perception.features import CostConfig
from terrain_perception.grid import GridMap
from terrain_perception.patches import PatchConfig, PatchSet, find_patches, gravity_in_camera
from terrain_perception.robot_model import available_robots, load_robot_model
from terrain_ros.conversions import (cloud_to_xyz, make_header, matrix_to_pose, msg_to_grid,
                                     msg_to_stance, pose_to_matrix, stamp_to_sec)
from terrain_ros.node import Counters, now_s, run_node
from terrain_ros.params import declare_config
from terrain_ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS

LEG_COLOURS = {0: (1.0, 0.2, 0.2), 1: (0.2, 0.8, 0.2), 2: (0.2, 0.4, 1.0), 3: (1.0, 0.8, 0.1)}


@dataclass(frozen=True)
class FootstepNodeConfig:
    """Node-level parameters (the algorithms' own are under ``patches.``, ``planner.``,
    ``cost.``)."""

    robot: str = param('littledog', 'robot profile in config/robots/ (geometry, camera mount, '
                       'gait defaults)')
    find_patches: bool = param(True, 'run the contact-patch detector on /stereo/points')
    patches_on_pose: bool = param(
        True, 'place a cloud\'s contact patches at the mapper\'s pose for its stamp '
        '(/icp/pose), not the latest one: the detector (12-19 ms of CPU) runs on the cloud\'s '
        'arrival, beside the ICP (this node is idle then; run when the pose came, it competed '
        'with the terrain fill and the mapper\'s coarse model for the 2 cores), and its '
        'patches wait in the camera frame for that pose. Without a mapper pose yet, they are '
        'published in the camera frame on arrival')
    use_patches: bool = param(True, 'let salient patches lower the foothold cost')
    patch_max_age_s: float = param(2.0, 'patches older than this (vs the map stamp) are not '
                                   'used for planning [s]', 0.0, 3600.0)
    imu_max_age_s: float = param(0.5, 'largest stamp gap between a cloud and the IMU sample '
                                 'used for its gravity [s]', 0.0, 3600.0)
    check_plans: bool = param(True, 'dry-run every walk plan through the walking controller\'s '
                              'own stability and reach checks (walking_config_file) and keep '
                              'the steps it accepts; if it refuses the first, start with '
                              'another leg (the status says so)')
    check_steps: int = param(
        2, 'dry-run only the first this many steps of a plan (0 = every step): plans are '
        'replaced twice a second and the controller starts about one step per plan (rocks-6cm '
        'seed 130: 77 steps in 245 plans); a later step the controller cannot execute it '
        'refuses itself and stands for the next plan. Each checked step costs the plan ~5 ms '
        'of CPU on the capture-to-plan path', 0, 1000)
    walking_config_file: str = param(
        '', 'the walking controller\'s parameter YAML (key walking_controller, e.g. '
        'config/walking_controller.yaml) whose values the dry run uses, so that a parameter '
        'changed there changes both; empty = the WalkingConfig defaults (read at start)')
    use_stance: bool = param(True, 'start plans from the controller\'s /walking/stance (its '
                             'real feet and next leg) instead of the nominal stance')
    stance_max_age_s: float = param(30.0, 'ignore a stance older than this (vs the map '
                                    'stamp) [s]', 0.0, 1e6)
    goal_tolerance_m: float = param(0.01, 'a /goal_pose within this of the current goal does '
                                    'not trigger a replan (re-sent goals) [m]', 0.0, 1e3)
    cost_grid_max: float = param(1.0, 'cost shown as 100 in /map/cost_grid (higher is '
                                 'clipped)', 1e-9, 1e9)
    diagnostics_period_s: float = param(1.0, 'period of the counters message [s]', 0.05, 3600.0)


def plan_to_msg(plan: fs.FootstepPlan, frame_id: str, stamp) -> FootstepPlanMsg:
    """terrain_msgs/FootstepPlan of a core plan."""
    msg = FootstepPlanMsg()
    msg.header = make_header(frame_id, stamp)
    msg.gait_mode = int(plan.gait)
    msg.status = int(plan.status)
    msg.status_text = str(plan.status_text)
    msg.body_move_per_period = float(plan.body_move_per_period_m)
    msg.final_body_pose = matrix_to_pose(plan.final_body_pose)
    for s in plan.footsteps:
        f = FootstepMsg()
        f.leg = int(s.leg)
        f.position = Point(x=float(s.position[0]), y=float(s.position[1]),
                           z=float(s.position[2]))
        f.cost = float(s.cost)
        f.step_index = int(s.step_index)
        f.patch_index = int(s.patch_index)
        msg.footsteps.append(f)
    return msg


def patches_to_msg(p: PatchSet, frame_id: str, stamp) -> ContactPatchArray:
    """terrain_msgs/ContactPatchArray of a core patch set (poses already in ``frame_id``)."""
    from terrain_perception.transforms import make_T
    msg = ContactPatchArray()
    msg.header = make_header(frame_id, stamp)
    msg.gravity = Vector3(x=float(p.gravity[0]), y=float(p.gravity[1]), z=float(p.gravity[2]))
    msg.fixation_point = Point(x=float(p.fixation[0]), y=float(p.fixation[1]),
                               z=float(p.fixation[2]))
    rims = p.boundary(12)
    for i in range(len(p)):
        c = ContactPatch()
        c.pose = matrix_to_pose(make_T(p.R[i], p.vertex[i]))
        c.kx, c.ky = float(p.kx[i]), float(p.ky[i])
        c.radius = float(p.radius[i])
        c.boundary = [Point(x=float(q[0]), y=float(q[1]), z=float(q[2])) for q in rims[i]]
        c.residual = float(p.residual[i])
        c.don, c.dong = float(p.don[i]), float(p.dong[i])
        c.fixation_distance = float(p.fixation_distance[i])
        c.support_points = int(p.support_points[i])
        msg.patches.append(c)
    return msg


def cost_to_occupancy(grid: GridMap, cost: np.ndarray, cost_max: float, stamp) -> OccupancyGrid:
    """nav_msgs/OccupancyGrid (row-major, row = +y) of a cost layer scaled to 0..100."""
    msg = OccupancyGrid()
    msg.header = make_header(grid.frame_id, stamp)
    nx, ny = grid.shape
    msg.info.resolution = float(grid.resolution_m)
    msg.info.width, msg.info.height = nx, ny
    msg.info.origin.position.x, msg.info.origin.position.y = grid.origin_xy
    msg.info.origin.orientation.w = 1.0
    with np.errstate(invalid='ignore'):
        val = np.clip(np.rint(np.asarray(cost, np.float64) / cost_max * 100.0), 0, 100)
    val = np.where(np.isfinite(cost), val, -1).astype(np.int8)
    msg.data = array.array('b', val.T.tobytes())     # int8 as is: no per-element checks
    return msg


class FootstepPlannerNode(Node):
    """Contact patches, cost grid and footstep plans; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('footstep_planner', **kwargs)
        self.node_cfg: FootstepNodeConfig = declare_config(self, FootstepNodeConfig)
        if self.node_cfg.robot not in available_robots():
            raise ValueError(f'unknown robot {self.node_cfg.robot!r} '
                             f'(known: {available_robots()})')
        self.patch_cfg: PatchConfig = declare_config(self, PatchConfig, prefix='patches',
                                                     on_change=self._on_patch_cfg)
        self.plan_cfg: fs.PlannerConfig = declare_config(self, fs.PlannerConfig,
                                                         prefix='planner',
                                                         on_change=self._on_plan_cfg)
        self.cost_cfg: CostConfig = declare_config(self, CostConfig, prefix='cost',
                                                   on_change=self._on_cost_cfg)
        self.robot = load_robot_model(self.node_cfg.robot)
        self.planner = fs.FootstepPlanner(self.robot, self.plan_cfg, self.cost_cfg)
        self.counters = Counters(self)

        self.grid: Optional[GridMap] = None
        self.map_problem: Optional[fs.FootstepPlan] = None
        self.T_map_base: Optional[np.ndarray] = None
        self.stance: Optional[tuple] = None     # (feet (4, 3) map, next leg, stamp [s])
        self.stance_steps_done = 0
        # Steps the controller refused although the dry run accepted them (see RefusedSteps)
        self.refused = fs.RefusedSteps()
        self.walking_cfg = WalkingConfig()
        if self.node_cfg.walking_config_file:
            try:
                self.walking_cfg = load_config(WalkingConfig, self.node_cfg.walking_config_file,
                                               'walking_controller')
            except (OSError, ValueError) as exc:
                raise ValueError(f'walking_config_file: {exc}') from exc
        self.goal_xy: Optional[np.ndarray] = None
        self.imu: Optional[tuple] = None          # (stamp_s, quaternion xyzw)
        self.patches_map: Optional[PatchSet] = None
        # a cloud's patches (camera frame) waiting for its /icp/pose (patches_on_pose):
        # (PatchSet, stamp [s], header stamp, frame id)
        self._patches_pending: Optional[tuple] = None
        self.patches_stamp: float = -np.inf
        self.last_plan: Optional[fs.FootstepPlan] = None
        self.goals_repeated = 0

        self.pub_plan = self.create_publisher(FootstepPlanMsg, '/footstep_plan', LATCHED_QOS)
        self.pub_plan_markers = self.create_publisher(MarkerArray, '/footstep_plan/markers',
                                                      RELIABLE_QOS)
        self.pub_patches = self.create_publisher(ContactPatchArray, '/contact_patches',
                                                 RELIABLE_QOS)
        self.pub_patch_markers = self.create_publisher(MarkerArray, '/contact_patches/markers',
                                                       RELIABLE_QOS)
        self.pub_cost = self.create_publisher(OccupancyGrid, '/map/cost_grid', LATCHED_QOS)
        self.pub_body_path = self.create_publisher(Path, '/footstep_plan/body_path',
                                                   RELIABLE_QOS)

        self.create_subscription(TerrainGrid, '/map/filled', self._on_map, LATCHED_QOS)
        self.create_subscription(PointCloud2, '/stereo/points', self._on_cloud, SENSOR_QOS)
        self.create_subscription(Imu, '/imu/data', self._on_imu, SENSOR_QOS)
        self.create_subscription(PoseStamped, '/icp/pose', self._on_pose, RELIABLE_QOS)
        self.create_subscription(PoseStamped, '/goal_pose', self._on_goal, RELIABLE_QOS)
        self.create_subscription(Stance, '/walking/stance', self._on_stance, LATCHED_QOS)
        self.create_timer(self.node_cfg.diagnostics_period_s, self.counters.publish)

    # ------------------------------------------------------------------ parameters

    def _on_patch_cfg(self, cfg: PatchConfig) -> None:
        self.patch_cfg = cfg

    def _on_plan_cfg(self, cfg: fs.PlannerConfig) -> None:
        self.plan_cfg = cfg
        self._rebuild_planner()

    def _on_cost_cfg(self, cfg: CostConfig) -> None:
        self.cost_cfg = cfg
        self._rebuild_planner()

    def _rebuild_planner(self) -> None:
        line = self.planner.straight_line     # a parameter change keeps the goal-less line
        self.planner = fs.FootstepPlanner(self.robot, self.plan_cfg, self.cost_cfg)
        self.planner.straight_line = line
        if self.grid is not None:
            self.map_problem = self.planner.set_map(self.grid)

    # ------------------------------------------------------------------ inputs

    def _on_map(self, msg: TerrainGrid) -> None:
        self._plan_on_map(msg)

    def _plan_on_map(self, msg: TerrainGrid) -> None:
        stamp = msg.header.stamp
        try:
            grid = msg_to_grid(msg)
        except (ValueError, TypeError) as exc:
            self.counters.bump('bad_map', f'unusable /map/filled: {exc}')
            self.grid = None
            self._publish_plan(fs.failed(fs.STATUS_BAD_MAP, f'map message unusable: {exc}'),
                               msg.header.frame_id or 'map', stamp)
            return
        self.grid = grid
        self.map_problem = self.planner.set_map(grid)
        if self.map_problem is not None:
            self.counters.bump('bad_map', self.map_problem.status_text)
        self.replan(stamp)
        if self.map_problem is None:
            # After the plan, which is what the controller waits for (capture-to-plan latency);
            # latched: late viewers get it, so publish regardless of current subscribers.
            self.pub_cost.publish(cost_to_occupancy(grid, self.planner.cost,
                                                    self.node_cfg.cost_grid_max, stamp))

    def _now(self) -> float:
        return now_s(self)

    def _on_pose(self, msg: PoseStamped) -> None:
        try:
            self.T_map_base = pose_to_matrix(msg.pose)
        except ValueError as exc:
            self.counters.bump('bad_pose', f'/icp/pose refused: {exc}')
            return
        pending = self._patches_pending
        if pending is not None and stamp_to_sec(msg.header.stamp) >= pending[1] - 1e-9:
            self._patches_pending = None
            self._place_patches(*pending, self.T_map_base)

    def _on_stance(self, msg: Stance) -> None:
        try:
            feet, next_leg = msg_to_stance(msg)
        except ValueError as exc:
            self.counters.bump('bad_stance', f'{exc}; ignored')
            return
        self.stance = (feet, next_leg, stamp_to_sec(msg.header.stamp))
        self.stance_steps_done = int(msg.steps_done)
        if self.refused.report(msg.steps_done, msg.last_error, self._now()):
            self.counters.bump('step_refused_by_controller',
                               f'the controller refused a step its dry run accepted '
                               f'({msg.last_error[:200]}); not offered again from this stance')

    def _on_goal(self, msg: PoseStamped) -> None:
        p = msg.pose.position
        xy = np.array([p.x, p.y], dtype=np.float64)
        if not np.all(np.isfinite(xy)):
            self.counters.bump('bad_goal', f'/goal_pose has a non-finite position {xy}')
            return
        # A goal sent again (volatile topics are often re-sent for late joiners) changes no
        # plan: replanning on it cost ~100 ms of the planner's CPU each time and delayed the
        # plan of the next map. The next map plans towards it anyway.
        same = (self.goal_xy is not None and
                float(np.linalg.norm(xy - self.goal_xy)) <= self.node_cfg.goal_tolerance_m)
        self.goal_xy = xy
        if same:
            self.goals_repeated += 1
            return
        if self.grid is not None:
            self.replan()

    def _on_imu(self, msg: Imu) -> None:
        q = msg.orientation
        quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
        if not np.all(np.isfinite(quat)) or np.linalg.norm(quat) < 1e-6 \
                or msg.orientation_covariance[0] == -1.0:
            self.counters.bump('bad_imu', 'IMU message without a usable orientation')
            return
        self.imu = (stamp_to_sec(msg.header.stamp), quat)

    def _on_cloud(self, msg: PointCloud2) -> None:
        if not self.node_cfg.find_patches:
            return
        found = self._detect_patches(msg)
        if found is None:
            return
        if self.node_cfg.patches_on_pose and self.T_map_base is not None:
            if self._patches_pending is not None:
                self.counters.bump('cloud_without_pose', 'no /icp/pose at or after a cloud\'s '
                                   'stamp came before the next cloud: its patches dropped')
            self._patches_pending = found
            return
        self._place_patches(*found, self.T_map_base)

    def _detect_patches(self, msg: PointCloud2) -> Optional[tuple]:
        """Contact patches of the cloud ``msg`` in its own frame: ``(PatchSet, stamp [s],
        header stamp, frame id)``, or None (counted) if the cloud or the IMU is unusable."""
        if self.imu is None:
            self.counters.bump('no_imu', 'cloud dropped: no IMU orientation received yet')
            return None
        t = stamp_to_sec(msg.header.stamp)
        if abs(t - self.imu[0]) > self.node_cfg.imu_max_age_s:
            self.counters.bump('stale_imu', f'cloud dropped: newest IMU sample is '
                                            f'{abs(t - self.imu[0]):.3f} s from the cloud')
            return None
        try:
            xyz = cloud_to_xyz(msg)
            if xyz.ndim != 3:
                raise ValueError('contact patches need an organized cloud (height > 1)')
            R_imu_cam = (self.robot.T_base_imu[:3, :3].T @ self.robot.T_base_camera[:3, :3])
            g = gravity_in_camera(self.imu[1], R_imu_cam)
            cam = self.robot.camera
            sx = xyz.shape[1] / cam.width
            sy = xyz.shape[0] / cam.height
            patches = find_patches(xyz, cam.fx * sx, cam.fy * sy, g, self.patch_cfg)
        except ValueError as exc:
            self.counters.bump('bad_cloud', f'cloud refused: {exc}')
            return None
        return patches, t, msg.header.stamp, msg.header.frame_id

    def _place_patches(self, patches: PatchSet, t: float, stamp, frame: str,
                       T_map_base: Optional[np.ndarray]) -> None:
        """Keep a cloud's patches for planning, placed in the map at ``T_map_base`` (None: no
        mapper pose yet, published in the camera frame only), and publish them to listeners."""
        if T_map_base is not None:
            patches = patches.transformed(T_map_base @ self.robot.T_base_camera)
            frame = self.grid.frame_id if self.grid is not None else 'map'
            self.patches_map, self.patches_stamp = patches, t
        # Built only for a listener (the closed loop has none; a bag recorder or a viewer is
        # one): the message's ~1,500 boundary Points and ~130 Poses cost ~20 ms of Python
        # per capture, on the cores the same capture's ICP and fill need.
        if self.pub_patches.get_subscription_count() > 0:
            self.pub_patches.publish(patches_to_msg(patches, frame, stamp))
        if self.pub_patch_markers.get_subscription_count() > 0:
            self.pub_patch_markers.publish(self._patch_markers(patches, frame, stamp))

    # ------------------------------------------------------------------ planning

    def replan(self, stamp=None) -> fs.FootstepPlan:
        """Plan on the current map, pose, goal and patches; publish and return the plan."""
        frame = self.grid.frame_id if self.grid is not None else 'map'
        if stamp is None:
            stamp = self.grid.stamp_s if self.grid is not None else 0.0
        if self.grid is None:
            plan = fs.failed(fs.STATUS_NO_MAP, 'no usable map received yet')
        elif self.map_problem is not None:
            plan = self.map_problem
        elif self.T_map_base is None:
            plan = fs.failed(fs.STATUS_BAD_INPUT, 'no robot pose received yet on /icp/pose')
        else:
            patches = None
            if (self.node_cfg.use_patches and self.patches_map is not None
                    and len(self.patches_map)
                    and abs(self.grid.stamp_s - self.patches_stamp)
                    <= self.node_cfg.patch_max_age_s):
                patches = (self.patches_map.vertex, self.patches_map.radius)
            feet, first_leg = None, None
            if self.node_cfg.use_stance and self.stance is not None and \
                    abs(self.grid.stamp_s - self.stance[2]) <= self.node_cfg.stance_max_age_s:
                feet, first_leg = self.stance[0], self.stance[1]
            if feet is not None and self.node_cfg.check_plans:
                done, now = self.stance_steps_done, self._now()

                k = self.node_cfg.check_steps

                def check(legs, positions):
                    if len(legs):
                        why = self.refused.refusal(done, legs[0], positions[0], now)
                        if why is not None:
                            return 0, f'the controller refused this step before: {why}'
                    m = len(legs) if k <= 0 else min(k, len(legs))
                    n, why = check_footsteps(self.robot, self.walking_cfg, feet, legs[:m],
                                             positions[:m], 'walk', self.grid,
                                             T_body=self.T_map_base)
                    # the unchecked tail stands as planned
                    return (len(legs), why) if n >= m else (n, why)
                plan = self.planner.plan_checked(self.T_map_base, self.goal_xy, feet, check,
                                                 patches=patches, first_leg=first_leg)
                if plan.check_note:
                    self.counters.bump('plan_changed_by_controller_check', plan.check_note)
                if plan.ok and plan.footsteps:
                    first = plan.footsteps[0]
                    self.refused.offered(done, first.leg, first.position, now)
            else:
                plan = self.planner.plan(self.T_map_base, self.goal_xy, feet=feet,
                                         first_leg=first_leg, patches=patches)
        self._publish_plan(plan, frame, stamp)
        return plan

    def _publish_plan(self, plan: fs.FootstepPlan, frame: str, stamp) -> None:
        self.last_plan = plan
        if plan.status not in (fs.STATUS_OK, fs.STATUS_GOAL_REACHED):
            self.counters.bump(f'plan_status_{plan.status}', plan.status_text)
        self.pub_plan.publish(plan_to_msg(plan, frame, stamp))
        self.pub_body_path.publish(self._body_path_msg(frame, stamp))
        if self.pub_plan_markers.get_subscription_count() > 0:
            self.pub_plan_markers.publish(self._plan_markers(plan, frame, stamp))

    def _body_path_msg(self, frame: str, stamp) -> Path:
        """The planner's last body path as a nav_msgs/Path (z: the map under it)."""
        out = Path()
        out.header = make_header(frame, stamp)
        bp = self.planner.body_path
        if bp is None or self.grid is None:
            return out
        z = self.grid.sample('elevation', bp.points)
        for (x, y), h in zip(bp.points, z):
            p = PoseStamped()
            p.header = out.header
            p.pose.position = Point(x=float(x), y=float(y),
                                    z=float(h) if np.isfinite(h) else 0.0)
            p.pose.orientation.w = 1.0
            out.poses.append(p)
        return out

    # ------------------------------------------------------------------ markers

    def _plan_markers(self, plan: fs.FootstepPlan, frame: str, stamp) -> MarkerArray:
        out = MarkerArray()
        clear = Marker(action=Marker.DELETEALL)
        clear.header = make_header(frame, stamp)
        out.markers.append(clear)
        for i, s in enumerate(plan.footsteps):
            m = Marker()
            m.header = make_header(frame, stamp)
            m.ns, m.id, m.type, m.action = 'footsteps', i, Marker.SPHERE, Marker.ADD
            m.pose.position = Point(x=float(s.position[0]), y=float(s.position[1]),
                                    z=float(s.position[2]))
            m.pose.orientation.w = 1.0
            d = 2.0 * max(self.robot.foot_radius_m, 0.005)
            m.scale = Vector3(x=d, y=d, z=d)
            r, g, b = LEG_COLOURS[int(s.leg)]
            m.color.r, m.color.g, m.color.b = r, g, b
            m.color.a = float(max(0.3, 1.0 - 0.15 * s.step_index))
            out.markers.append(m)
        return out

    def _patch_markers(self, p: PatchSet, frame: str, stamp) -> MarkerArray:
        out = MarkerArray()
        clear = Marker(action=Marker.DELETEALL)
        clear.header = make_header(frame, stamp)
        out.markers.append(clear)
        rims = p.boundary(12)
        for i in range(len(p)):
            m = Marker()
            m.header = make_header(frame, stamp)
            m.ns, m.id, m.type, m.action = 'patches', i, Marker.LINE_STRIP, Marker.ADD
            m.pose.orientation.w = 1.0
            m.scale.x = 0.002
            m.color.g, m.color.b, m.color.a = 0.8, 1.0, 1.0
            m.points = [Point(x=float(q[0]), y=float(q[1]), z=float(q[2]))
                        for q in np.vstack([rims[i], rims[i][:1]])]
            out.markers.append(m)
        return out


def main(args=None) -> int:
    return run_node(FootstepPlannerNode, args=args)


if __name__ == '__main__':
    main()
