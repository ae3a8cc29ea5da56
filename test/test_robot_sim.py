"""Both robots in pybullet (DIRECT, fixed 500 Hz step): stand still, walk 2 m on flat ground
with the crawl, keep the simulated COG inside the support triangle, step over a box.

Ground truth comes from the simulator (base pose, link COMs, contacts)."""

import numpy as np
import pytest

from terrain_perception import gait as G
from terrain_perception.robot_model import load_robot_model
from terrain_perception.sim.walk import WalkRunner, make_flat_world, spawn_standing, walk
from terrain_perception.transforms import yaw_of

DT = 1.0 / 500.0


@pytest.mark.parametrize('name', ['littledog', 'frog'])
def test_stands_ten_seconds_without_drift(name):
    m = load_robot_model(name)
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, dt_s=DT)
    T0 = robot.base_pose()
    q0 = robot.joint_states()[0]
    for _ in range(int(10.0 / DT)):
        client.stepSimulation()
    T1 = robot.base_pose()
    assert np.linalg.norm(T1[:3, 3] - T0[:3, 3]) < 0.01
    assert abs(T1[2, 3] - m.standing_height_m) < 0.01
    assert robot.foot_contacts(plane).all()
    assert robot.non_foot_contacts(plane) == 0
    feet_f, legs_f, body_f = robot.contact_forces_by_part()
    weight = m.total_mass_kg * 9.81
    assert feet_f.sum() == pytest.approx(weight, rel=0.05) and np.all(feet_f > 0.1 * weight)
    assert np.all(legs_f == 0.0) and body_f == 0.0
    np.testing.assert_array_equal(robot.foot_contact_forces(), feet_f)
    np.testing.assert_allclose(robot.joint_states()[0], q0, atol=0.01)
    # Camera pose is the base pose composed with the profile's mount.
    np.testing.assert_allclose(robot.camera_pose(), T1 @ m.T_base_camera, atol=1e-12)
    client.disconnect()


def test_contact_forces_by_part_name_the_body_and_a_shank_resting_on_the_ground():
    """A robot whose motors go limp collapses onto its legs' links and body: the forces say
    so, and still add up to its weight."""
    m = load_robot_model('littledog')
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, dt_s=DT)
    robot.set_joint_targets(robot.joint_states()[0], max_force=0.0)
    for _ in range(int(2.0 / DT)):
        client.stepSimulation()
    feet_f, legs_f, body_f = robot.contact_forces_by_part()
    weight = m.total_mass_kg * 9.81
    assert feet_f.sum() + legs_f.sum() + body_f == pytest.approx(weight, rel=0.1)
    assert legs_f.sum() + body_f > 0.5 * weight        # the feet no longer carry it
    client.disconnect()


@pytest.mark.timeout(120)
@pytest.mark.parametrize('name', ['littledog', 'frog'])
def test_walks_two_metres_and_ends_on_the_commanded_pose(name):
    m = load_robot_model(name)
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, xy=(0.3, -0.2), yaw=0.1, dt_s=DT)
    T0 = robot.base_pose()
    legs, pos = G.straight_footsteps(m, T0, 2.0)
    res = walk(client, robot, legs, pos, 'walk', dt_s=DT, max_time_s=120.0, record_com=True,
               ground_id=plane)
    assert not res.fell and res.controller_error == ''
    assert res.steps_done == len(legs)
    assert res.extra['leg_ground_steps'] == 0          # only the feet touch the ground
    yaw0 = yaw_of(T0)
    end_xy = T0[:2, 3] + 2.0 * np.array([np.cos(yaw0), np.sin(yaw0)])
    # The walk has no heading feedback, and its drift depends on the last bits of numpy's
    # trigonometric functions and the CPU: LittleDog ends 1.4 cm / 1.4 deg off with the C
    # library's, 7.0 cm / 5.2 deg off with numpy's AVX-512 ones (same code,
    # NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL" selects the former; FROG-I 2 cm / 0.5 deg
    # either way). On an AMD EPYC (session 38) LittleDog ends 8.9 cm / 3.3 deg off, its feet
    # 27 mm from the planned footholds in the median as the body drifts (5.6 cm, 5.0 deg,
    # 9 mm with the C library's functions); FROG-I 4.5 cm / 3.0 deg, 10 mm. The bounds take
    # all of them; a walk that goes astray or misplaces its feet by a step still fails.
    assert np.linalg.norm(res.T_end[:2, 3] - end_xy) < 0.11
    assert abs(yaw_of(res.T_end) - yaw0) < np.radians(6.0)
    assert res.max_tilt_deg < 5.0
    assert np.median(res.foot_errors_m) < 0.035
    # Statically stable: the simulated whole-robot COG stays inside the three stance feet
    # with a good part of the planned margin during every swing.
    assert res.min_com_margin_m > 0.4 * m.stability_margin_m
    client.disconnect()


def _box_walk(use_height_map):
    m = load_robot_model('littledog')
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, dt_s=DT)
    # A 5 cm high (above the 4 cm nominal swing lift), 2 cm deep box across the path, between
    # the footholds: every foot has to swing over it.
    import pybullet
    half = [0.01, 0.25, 0.025]
    x_box = 0.25
    box = client.createMultiBody(0, client.createCollisionShape(pybullet.GEOM_BOX,
                                                                halfExtents=half),
                                 basePosition=[x_box, 0.0, half[2]])
    client.changeDynamics(box, -1, lateralFriction=1.0)

    def height(xy):
        xy = np.asarray(xy)
        on = (np.abs(xy[..., 0] - x_box) <= half[0]) & (np.abs(xy[..., 1]) <= half[1])
        return np.where(on, 2 * half[2], 0.0)

    legs, pos = G.straight_footsteps(m, robot.base_pose(), 0.4, 0.1, height=height)
    assert np.all(np.abs(pos[:, 0] - x_box) > half[0] + 0.03)    # no foothold near it
    res = walk(client, robot, legs, pos, 'walk', dt_s=DT, max_time_s=60.0,
               height=height if use_height_map else None, obstacle_id=box, ground_id=plane)
    feet = robot.foot_positions_world()
    client.disconnect()
    return res, feet, x_box, half


def test_swing_clears_a_box_in_the_path():
    res, feet, x_box, half = _box_walk(use_height_map=True)
    assert not res.fell and res.steps_done == 16 and res.controller_error == ''
    # The swinging feet never touch it. (The shanks may: LittleDog's slanted shanks reach
    # past the foot, so a foothold 4 cm from an edge is close - that is the planner's cost.)
    assert res.swing_hits == 0
    # Every foot crossed the box.
    assert np.all(feet[:, 0] > x_box + half[0])
    # Blind to the box (no height map) the same swings hit it: the check can fail.
    res_blind, _, _, _ = _box_walk(use_height_map=False)
    assert res_blind.swing_hits > 0


def test_littledog_trots_on_flat_ground():
    # Shao's discontinuous trot: body moves with four feet down, diagonal pairs swing.
    m = load_robot_model('littledog')
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, dt_s=DT)
    T0 = robot.base_pose()
    legs, pos = G.straight_footsteps(m, T0, 0.6, gait='trot')
    res = walk(client, robot, legs, pos, 'trot', dt_s=DT, max_time_s=60.0, ground_id=plane)
    client.disconnect()
    assert not res.fell and res.steps_done == len(legs) and res.controller_error == ''
    assert np.linalg.norm(res.T_end[:2, 3] - (T0[:2, 3] + [0.6, 0.0])) < 0.05
    assert res.max_tilt_deg < 10.0


def _surprise_walk(dz: float, sensing: bool):
    """LittleDog crawls 0.3 m; the ground under one foothold is ``dz`` higher than the plan
    says (a hidden 3 cm wide slab when dz > 0; the foothold planned in mid-air when dz < 0)."""
    import pybullet
    from terrain_perception.controller import WalkingConfig
    m = load_robot_model('littledog')
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, dt_s=DT)
    legs, pos = G.straight_footsteps(m, robot.base_pose(), 0.3)
    k = 5                                   # the sixth footstep (LF, 0.3 m ahead)
    if dz > 0:
        half = [0.015, 0.015, 0.5 * dz]
        client.changeDynamics(client.createMultiBody(
            0, client.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half),
            basePosition=[pos[k, 0], pos[k, 1], half[2]]), -1, lateralFriction=1.0)
    else:
        pos[k, 2] -= dz                     # planned above the real ground
    cfg = WalkingConfig(plan_timeout_s=1e6) if sensing else \
        WalkingConfig(plan_timeout_s=1e6, contact_force_n=0.0, attitude_gain=0.0)
    seen = {}

    def on_step(t):
        if res_ctl.steps_done == k + 1 and 'belief' not in seen:
            seen['belief'] = res_ctl.feet[legs[k], 2]
    runner = WalkRunner(client, robot, cfg, DT, ground_id=plane)
    res_ctl = runner.controller
    runner.run(legs, pos, 'walk', max_time_s=60.0, on_step=on_step)
    res = runner.result()
    client.disconnect()
    return res, res_ctl.touchdowns, seen.get('belief', np.nan)


def test_touchdown_sensing_stops_a_foot_on_higher_ground():
    # The joint torques tell the controller the foot met the slab early: the swing ends
    # there, the controller knows the foot stands 2 cm up, and the body stays level.
    res, touch, belief = _surprise_walk(0.02, sensing=True)
    assert not res.fell and res.steps_done == 12
    assert touch['early'] >= 1
    assert belief > 0.008                       # it knows the foot stands on something
    blind, _, belief_blind = _surprise_walk(0.02, sensing=False)
    assert abs(belief_blind) < 0.006            # blind: it believes the plan's height
    # measured: 2.6 vs 14.6 deg
    assert res.max_tilt_deg < 0.5 * blind.max_tilt_deg


def _slab_landing(approach_m: float, control_rate_hz=None, slab_m: float = 0.02) -> tuple:
    """LittleDog crawls 0.3 m; a hidden 3 cm wide slab ``slab_m`` high under one foothold, the
    controller updated at every physics step or at ``control_rate_hz`` (the node's rate).
    Returns the largest 20 ms mean of the slab's normal force, the walk's result and the
    body's largest rise [m] in the 0.5 s after the foot meets the slab."""
    import pybullet
    from terrain_perception.controller import WalkingConfig
    m = load_robot_model('littledog')
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, dt_s=DT)
    legs, pos = G.straight_footsteps(m, robot.base_pose(), 0.3)
    half = [0.015, 0.015, 0.5 * slab_m]
    slab = client.createMultiBody(0, client.createCollisionShape(
        pybullet.GEOM_BOX, halfExtents=half), basePosition=[pos[5, 0], pos[5, 1], half[2]])
    force, z = [], []

    def on_step(t):
        force.append(sum(c[9] for c in client.getContactPoints(bodyA=slab)))
        z.append(robot.base_pose()[2, 3])
    runner = WalkRunner(client, robot, WalkingConfig(plan_timeout_s=1e6,
                                                     swing_approach_m=approach_m), DT,
                        ground_id=plane, control_rate_hz=control_rate_hz)
    runner.run(legs, pos, 'walk', max_time_s=60.0, on_step=on_step)
    res = runner.result()
    client.disconnect()
    force, z = np.array(force), np.array(z)
    k = int(np.argmax(force > 0.5))
    assert force[k] > 0.5, 'the foot never met the slab'
    rise = float(z[k:k + int(0.5 / DT)].max() - z[max(k - 50, 0):k].mean())
    return float(np.convolve(force, np.ones(10) / 10, 'valid').max()), res, rise


def test_a_slow_final_approach_lands_softly_on_ground_higher_than_believed():
    # The foot meets the slab 2 cm above its believed foothold. Without the approach it hits
    # it at the minimum-jerk lowering's speed: measured 28.8 N over 20 ms, a kick larger than
    # the 27 N robot's weight; with a 2 cm approach at 0.15 m/s 15.2 N, the foot's share.
    soft, res, _ = _slab_landing(0.02)
    hard, res_hard, _ = _slab_landing(0.0)
    assert not res.fell and res.steps_done == 12
    assert not res_hard.fell
    assert soft < 0.7 * hard
    assert soft < 20.0


def test_at_the_nodes_control_rate_the_approach_halves_the_landing_kick():
    # The walking controller node updates at 50 Hz: touchdown is confirmed 3 ticks (60 ms) after
    # the foot meets the 2 cm slab, and the lowering goes on meanwhile. Without the approach
    # that landing measured 46.8 N and lifted the body 14.7 mm (every physics step: 28.8 N,
    # 4.6 mm), with it 19.8 N and 4.8 mm (the loop's falls at the rocks' end: a hind foot
    # landing at 0.8-1.3 m/s on ground 1.5 cm above the map).
    soft, res, soft_rise = _slab_landing(0.02, control_rate_hz=50.0)
    hard, res_hard, hard_rise = _slab_landing(0.0, control_rate_hz=50.0)
    assert not res.fell and res.steps_done == 12
    assert hard > 35.0 and hard_rise > 0.010
    assert soft < 0.6 * hard and soft_rise < 0.5 * hard_rise


def test_touchdown_sensing_lowers_a_hanging_foot_before_the_next_swing():
    # The foothold was planned 2 cm above the real ground: the foot ends its swing in the
    # air; before the next leg lifts, the controller lowers it until it carries weight.
    res, touch, _ = _surprise_walk(-0.02, sensing=True)
    assert not res.fell and res.steps_done == 12
    assert touch['probed'] >= 1
    blind, _, _ = _surprise_walk(-0.02, sensing=False)
    # measured: 7.5 vs 21.4 deg
    assert res.max_tilt_deg < 0.5 * blind.max_tilt_deg


def test_a_pd_servo_deflects_under_load_by_its_stiffness_and_reports_its_torques():
    """SimRobot.use_pd_servo: the joints obey tau = kp (q* - q) + kd (dq* - dq), so a standing
    robot sinks more on softer servos, the reported torques are the applied ones (the foot
    forces computed from them carry the robot's weight), and pybullet's position servo,
    which does not deflect, stays the default."""
    from terrain_perception import kinematics
    m = load_robot_model('littledog')
    weight = m.total_mass_kg * 9.81
    sink = {}
    for kp in (None, 40.0, 10.0):
        client, plane = make_flat_world(DT)
        robot = spawn_standing(client, m, dt_s=DT)
        q0 = robot.joint_states()[0]
        if kp is not None:
            robot.use_pd_servo(kp, 0.1)
        for _ in range(int(1.0 / DT)):
            robot.set_joint_targets(q0)
            client.stepSimulation()
        q, dq, tau = robot.joint_states()
        sink[kp] = m.standing_height_m - robot.base_pose()[2, 3]
        if kp is not None:
            np.testing.assert_allclose(tau, np.clip(kp * (q0 - q) - 0.1 * dq, -m.max_torque_nm,
                                                    m.max_torque_nm), atol=0.02)
            J = kinematics.jacobian(m, q.reshape(4, 3))
            fz = kinematics.foot_forces(m, q.reshape(4, 3), tau.reshape(4, 3), J)[:, 2]
            # each foot's force from the torques is the simulator's contact force, but for
            # the leg's own weight the estimate neglects (~0.9 N a leg)
            np.testing.assert_allclose(fz, robot.foot_contact_forces(), atol=1.5)
            assert robot.foot_contact_forces().sum() == pytest.approx(weight, rel=0.02)
        assert robot.foot_contacts(plane).all() and robot.base_tilt_deg() < 1.0
        client.disconnect()
    assert abs(sink[None]) < 5e-4
    assert 0.0 < sink[40.0] < sink[10.0] < 0.01
    with pytest.raises(ValueError, match='kp > 0'):
        robot.use_pd_servo(0.0, 0.1)
    # explicit gains switch back to pybullet's servo: its torques are reported again
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, dt_s=DT)
    q0 = robot.joint_states()[0]
    robot.use_pd_servo(40.0, 0.1)
    robot.set_joint_targets(q0, max_force=m.max_torque_nm)
    client.stepSimulation()
    q, _, tau = robot.joint_states()
    assert not np.allclose(tau, np.clip(40.0 * (q0 - q), -m.max_torque_nm, m.max_torque_nm),
                           atol=0.02)
    client.disconnect()
