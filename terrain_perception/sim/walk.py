"""Closed-loop walking in pybullet: a WalkingController driving a SimRobot, with ground truth.

Shared by the tests and ``terrain-bench sim``: runs the controller at every physics step (the
PD targets are the controller's cubic splines sampled at the physics rate; holding targets
for several steps makes the stiff stance legs jerk and the feet slip) and records what the
simulator says really happened.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from terrain_perception import gait as gaitlib
from terrain_perception.controller import WalkingConfig, WalkingController
from terrain_perception.robot_model import RobotModel
from terrain_perception.sim.robots import SimRobot


def make_flat_world(dt_s: float = 1.0 / 500.0, friction: float = 1.0):
    """A DIRECT ``BulletClient`` with gravity, fixed step ``dt_s`` and a ground plane at z=0.

    Returns ``(client, plane_id)``.
    """
    import pybullet
    from pybullet_utils.bullet_client import BulletClient
    client = BulletClient(connection_mode=pybullet.DIRECT)
    client.setGravity(0.0, 0.0, -9.81)
    client.setTimeStep(dt_s)
    plane = client.createMultiBody(0, client.createCollisionShape(pybullet.GEOM_PLANE))
    client.changeDynamics(plane, -1, lateralFriction=friction)
    return client, plane


def spawn_standing(client, model: RobotModel, xy=(0.0, 0.0), yaw: float = 0.0,
                   ground_z: float = 0.0, settle_s: float = 0.2,
                   dt_s: float = 1.0 / 500.0) -> SimRobot:
    """Load ``model`` standing at ``xy`` on ground at ``ground_z`` and let it settle."""
    robot = SimRobot.load(client, model, (xy[0], xy[1], ground_z + model.standing_height_m
                                          + 0.002), (0.0, 0.0, yaw))
    for _ in range(int(round(settle_s / dt_s))):
        client.stepSimulation()
    return robot


def link_masses(client, robot: SimRobot) -> np.ndarray:
    """Masses [kg] of the base and every link, in pybullet link order (base first)."""
    n = client.getNumJoints(robot.body_id)
    return np.array([client.getDynamicsInfo(robot.body_id, i)[0] for i in range(-1, n)])


def com_world(client, robot: SimRobot, masses: Optional[np.ndarray] = None) -> np.ndarray:
    """Whole-robot centre of mass in the world [m] from the simulator's link states."""
    bid = robot.body_id
    masses = link_masses(client, robot) if masses is None else masses
    pos = [client.getBasePositionAndOrientation(bid)[0]]
    pos += [s[0] for s in client.getLinkStates(bid, list(range(len(masses) - 1)))]
    return (masses[:, None] * np.array(pos)).sum(axis=0) / masses.sum()


@dataclass
class WalkResult:
    """Ground truth of one walk.

    Attributes:
        sim_time_s: simulated time until the plan was done and the robot stood still.
        fell: base tilted more than 30 deg or the body link touched the ground.
        extra: ``leg_ground_steps``: checks in which a thigh or shank touched the ground.
        T_start, T_end: simulated base poses (world) at the start and end.
        T_end_desired: controller's dead-reckoning pose at the end (odom = world here).
        foot_errors_m: horizontal distance between each landed foot's contact point and its
            footstep target [m], one per executed footstep.
        min_com_margin_m: smallest signed distance of the simulated COM inside the support
            triangle during crawl swings (NaN if not recorded).
        max_tilt_deg: largest base tilt seen.
        steps_done: footsteps executed; controller_error: controller's last_error.
        swing_hits: number of physics steps in which a swinging foot (between 20 % and 80 % of
            its swing, i.e. off its lift-off and landing spots) touched ``obstacle_id``.
        leg_hits: number of physics steps in which a non-foot link (shank, thigh, body)
            touched ``obstacle_id``.
    """

    sim_time_s: float
    fell: bool
    T_start: np.ndarray
    T_end: np.ndarray
    T_end_desired: np.ndarray
    foot_errors_m: np.ndarray
    min_com_margin_m: float
    max_tilt_deg: float
    steps_done: int
    controller_error: str
    swing_hits: int = 0
    leg_hits: int = 0
    extra: dict = field(default_factory=dict)


class WalkRunner:
    """A controller driving a robot in an existing world, footstep chunk after chunk.

    ``run(legs, positions, gait)`` executes one chunk (the controller keeps its state between
    chunks, like a receding-horizon plan being replaced); ``result()`` summarises everything
    run so far. The controller's odom frame starts at the simulated base pose, so odom = world
    (no drift correction: dead reckoning along the desired trajectory only). Falls (tilt over
    30 deg or the body touching ``ground_id``, one body id or several), non-foot ground
    contacts and the COG margin are checked every ``check_every`` physics steps; contacts
    with ``obstacle_id`` at every step. A :class:`terrain_perception.sim.trace.WalkTrace`
    given as ``trace`` records the truth and the controller's belief as the walk runs.

    ``control_rate_hz``: None (default) updates the controller at every physics step; a rate
    updates it that often, as the walking controller node does (``control_rate_hz`` 50, joint
    states sensed at the tick), and between ticks the joints follow the controller's preview of
    its trajectory, as the simulator bridge follows the node's ``/joint_commands``. Touchdown
    sensing then reacts as late as in the closed loop: at 50 Hz the 3-tick debounce is 60 ms of
    descent past first contact instead of 6 ms.
    """

    def __init__(self, client, robot: SimRobot, config: Optional[WalkingConfig] = None,
                 dt_s: float = 1.0 / 500.0, height: gaitlib.HeightFn = None,
                 record_com: bool = False, obstacle_id: Optional[int] = None,
                 ground_id=None, check_every: int = 5, trace=None,
                 control_rate_hz: Optional[float] = None) -> None:
        self.client, self.robot, self.dt_s = client, robot, dt_s
        if control_rate_hz is not None and not (np.isfinite(control_rate_hz)
                                                and control_rate_hz > 0):
            raise ValueError(f'control_rate_hz must be positive, got {control_rate_hz}')
        # physics steps per controller update (1: every step)
        self.steps_per_tick = (1 if control_rate_hz is None else
                               max(int(round(1.0 / (control_rate_hz * dt_s))), 1))
        self.trace = trace      # a terrain_perception.sim.trace.WalkTrace, or None
        cfg = config or WalkingConfig(plan_timeout_s=1e6)
        self.controller = WalkingController(robot.model, cfg, height=height)
        self.T_start = robot.base_pose()
        q, dq, _ = robot.joint_states()
        self.controller.reset(0.0, q, self.T_start)
        self.record_com, self.obstacle_id = record_com, obstacle_id
        self.ground_ids = () if ground_id is None else tuple(
            int(g) for g in np.atleast_1d(ground_id))
        self.check_every = check_every
        self.t = 0.0
        self.foot_err: list = []
        self.min_margin, self.max_tilt, self.fell = np.inf, 0.0, False
        self.swing_hits = self.leg_hits = self.leg_ground_steps = 0
        self._queue: list = []
        self._targets: dict = {}
        self._prev = None
        self._masses = link_masses(client, robot)
        self._n = 0

    def run(self, legs: np.ndarray, positions: np.ndarray, gait: str = 'walk',
            max_time_s: float = 300.0, on_step: Optional[Callable[[float], None]] = None,
            frame: str = 'odom') -> bool:
        """Execute footsteps (world contact points) until done, a fall or ``max_time_s`` of
        simulated time for this chunk; True when every footstep was executed. ``frame``
        'map' converts them with the controller's ``T_map_odom`` (after
        :meth:`WalkingController.apply_correction`; map = world, odom = the controller's
        dead reckoning)."""
        ctl, robot, client = self.controller, self.robot, self.client
        legs = np.asarray(legs, int).reshape(-1)
        positions = np.asarray(positions, float).reshape(-1, 3)
        ctl.set_footsteps(legs, positions, gait, self.t, frame=frame)
        self._queue = list(zip(legs.tolist(), positions))
        done_before = ctl.steps_done
        t_end = self.t + max_time_s
        step_simulation = client.stepSimulation
        t_chunk = self.t
        n_tick = self.steps_per_tick
        k = n_tick
        while self.t < t_end and not self.fell:
            if n_tick == 1:
                q, dq, tau = robot.joint_states()
                cmd = ctl.update(self.t, q, dq, tau, robot.base_pose()[:3, :3])
                robot.set_joint_targets(cmd.positions, dq=cmd.velocities)
            else:
                if k >= n_tick:
                    q, dq, tau = robot.joint_states()
                    ctl.update(self.t, q, dq, tau, robot.base_pose()[:3, :3])
                    tick = ctl.preview(self.t + np.arange(n_tick) * self.dt_s)
                    k = 0
                robot.set_joint_targets(tick.positions[k], dq=tick.velocities[k])
                k += 1
            step_simulation()
            self.t += self.dt_s
            self._n += 1
            check = self._n % self.check_every == 0
            if on_step is not None:
                on_step(self.t)
            if self.trace is not None:
                self.trace.sample(self.t, client, robot, ctl, self._masses)
            self._track(ctl.phase, check)
            if ctl.phase is None and ctl.pending_steps == 0 and self.t > t_chunk + 0.05:
                break
        return ctl.steps_done - done_before == len(legs)

    def _track(self, seg, check: bool) -> None:
        robot, client, prev = self.robot, self.client, self._prev
        if prev is not None and seg != prev and prev.kind == 'swing':
            feet = robot.foot_positions_world()
            for leg in prev.legs:
                tgt = self._targets.pop(leg, None)
                if tgt is not None:
                    self.foot_err.append(float(np.linalg.norm(feet[leg, :2] - tgt[:2])))
        if seg is not None and seg != prev and seg.kind == 'swing':
            for leg in seg.legs:
                # the controller may reorder a pair (a split trot step): match by leg
                k = next((k for k, (lg, _) in enumerate(self._queue) if lg == leg), None)
                if k is not None:
                    self._targets[leg] = self._queue.pop(k)[1]
        self._prev = seg
        if check:
            tilt = robot.base_tilt_deg()
            self.max_tilt = max(self.max_tilt, tilt)
            for gid in self.ground_ids:
                # Bullet also reports points of a near miss (its contact margin, e.g. a rock
                # 2.5 mm under the belly, no force): only touching points count.
                pts = [p for p in client.getContactPoints(bodyA=robot.body_id, bodyB=gid)
                       if p[8] <= 0.0]
                feet = set(int(i) for i in robot.foot_links)
                if any(p[3] == -1 for p in pts):
                    self.fell = True
                if any(p[3] not in feet and p[3] != -1 for p in pts):
                    self.leg_ground_steps += 1
            if tilt > 30.0:
                self.fell = True
        if seg is not None and seg.kind == 'swing':
            tau = self.t - seg.t0
            if self.record_com and len(seg.legs) == 1 and check:
                stance = [k for k in range(4) if k not in seg.legs]
                feet = robot.foot_positions_world()
                com = com_world(client, robot, self._masses)
                self.min_margin = min(self.min_margin, float(gaitlib.support_margin(
                    com[:2], feet[stance, :2])))
            if self.obstacle_id is not None and 0.2 * seg.duration < tau < 0.8 * seg.duration:
                for leg in seg.legs:
                    if client.getContactPoints(bodyA=robot.body_id, bodyB=self.obstacle_id,
                                               linkIndexA=int(robot.foot_links[leg])):
                        self.swing_hits += 1
        if self.obstacle_id is not None and robot.non_foot_contacts(self.obstacle_id):
            self.leg_hits += 1

    def result(self) -> WalkResult:
        ctl = self.controller
        return WalkResult(sim_time_s=self.t, fell=self.fell, T_start=self.T_start,
                          T_end=self.robot.base_pose(), T_end_desired=ctl.odom_pose,
                          foot_errors_m=np.array(self.foot_err),
                          min_com_margin_m=(self.min_margin if np.isfinite(self.min_margin)
                                            else np.nan),
                          max_tilt_deg=self.max_tilt, steps_done=ctl.steps_done,
                          controller_error=ctl.last_error, swing_hits=self.swing_hits,
                          leg_hits=self.leg_hits,
                          extra={'leg_ground_steps': self.leg_ground_steps})


def walk(client, robot: SimRobot, legs: np.ndarray, positions: np.ndarray, gait: str = 'walk',
         config: Optional[WalkingConfig] = None, dt_s: float = 1.0 / 500.0,
         max_time_s: float = 300.0, height: gaitlib.HeightFn = None,
         record_com: bool = False, obstacle_id: Optional[int] = None,
         ground_id: Optional[int] = None,
         on_step: Optional[Callable[[float], None]] = None,
         check_every: int = 5) -> WalkResult:
    """Execute footsteps (world contact points) with a fresh controller; see WalkRunner."""
    runner = WalkRunner(client, robot, config or WalkingConfig(plan_timeout_s=max_time_s + 1),
                        dt_s, height, record_com, obstacle_id, ground_id, check_every)
    runner.run(legs, positions, gait, max_time_s, on_step)
    return runner.result()
