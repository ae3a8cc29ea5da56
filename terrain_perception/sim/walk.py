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
        fell: base tilted more than 30 deg or touched the ground with a non-foot link.
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


def walk(client, robot: SimRobot, legs: np.ndarray, positions: np.ndarray, gait: str = 'walk',
         config: Optional[WalkingConfig] = None, dt_s: float = 1.0 / 500.0,
         max_time_s: float = 300.0, height: gaitlib.HeightFn = None,
         record_com: bool = False, obstacle_id: Optional[int] = None,
         ground_id: Optional[int] = None,
         on_step: Optional[Callable[[float], None]] = None,
         check_every: int = 5) -> WalkResult:
    """Execute footsteps (world frame contact points) with a fresh controller; see WalkResult.

    The controller's odom frame is initialised at the simulated start pose, so odom = world
    (no drift correction is applied: dead reckoning along the desired trajectory only).
    Falls, non-foot ground contacts and the COG margin are checked every ``check_every``
    physics steps (contacts with ``obstacle_id`` at every step).
    """
    model = robot.model
    cfg = config or WalkingConfig(plan_timeout_s=max_time_s + 1.0)
    ctl = WalkingController(model, cfg, height=height)
    T_start = robot.base_pose()
    q, dq, _ = robot.joint_states()
    ctl.reset(0.0, q, T_start)
    ctl.set_footsteps(legs, positions, gait, 0.0)
    targets = {}
    order = list(zip(np.asarray(legs, int).tolist(), np.asarray(positions, float)))
    foot_err, t, min_margin, max_tilt, fell, hits = [], 0.0, np.inf, 0.0, False, 0
    leg_hits = 0
    prev_seg = None
    step_i = 0
    masses = link_masses(client, robot)
    n_step = 0
    step_simulation = client.stepSimulation
    while t < max_time_s:
        q, dq, _ = robot.joint_states()
        cmd = ctl.update(t, q, dq)
        robot.set_joint_targets(cmd.positions, dq=cmd.velocities)
        step_simulation()
        t += dt_s
        n_step += 1
        check = n_step % check_every == 0
        if on_step is not None:
            on_step(t)
        seg = ctl.phase
        if prev_seg is not None and seg != prev_seg and prev_seg.kind == 'swing':
            feet = robot.foot_positions_world()
            for leg in prev_seg.legs:
                tgt = targets.pop(leg)
                foot_err.append(float(np.linalg.norm(feet[leg, :2] - tgt[:2])))
        if seg is not None and seg != prev_seg and seg.kind == 'swing':
            for leg in seg.legs:
                targets[leg] = order[step_i][1]
                step_i += 1
        prev_seg = seg
        if check:
            tilt = robot.base_tilt_deg()
            max_tilt = max(max_tilt, tilt)
            if tilt > 30.0 or (ground_id is not None and robot.non_foot_contacts(ground_id)):
                fell = True
                break
        if seg is not None and seg.kind == 'swing':
            tau = t - seg.t0
            if record_com and len(seg.legs) == 1 and check:
                stance = [k for k in range(4) if k not in seg.legs]
                feet = robot.foot_positions_world()
                com = com_world(client, robot, masses)
                min_margin = min(min_margin, float(gaitlib.support_margin(
                    com[:2], feet[stance, :2])))
            if obstacle_id is not None and 0.2 * seg.duration < tau < 0.8 * seg.duration:
                for leg in seg.legs:
                    if client.getContactPoints(bodyA=robot.body_id, bodyB=obstacle_id,
                                               linkIndexA=int(robot.foot_links[leg])):
                        hits += 1
        if obstacle_id is not None and robot.non_foot_contacts(obstacle_id):
            leg_hits += 1
        if seg is None and ctl.pending_steps == 0 and t > 0.5:
            break
    return WalkResult(sim_time_s=t, fell=fell, T_start=T_start, T_end=robot.base_pose(),
                      T_end_desired=ctl.odom_pose, foot_errors_m=np.array(foot_err),
                      min_com_margin_m=min_margin if np.isfinite(min_margin) else np.nan,
                      max_tilt_deg=max_tilt, steps_done=ctl.steps_done,
                      controller_error=ctl.last_error, swing_hits=hits,
                      leg_hits=leg_hits)
