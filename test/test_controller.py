"""WalkingController core without a simulator: perfect joint tracking (q_measured = command).

Checks the desired motion against the footsteps: feet land on the targets, the dead-reckoning
pose ends on the commanded pose, the model COG stays inside the support triangle with the
margin during every crawl swing, and bad plans / stale plans / corrections behave.
"""

import numpy as np
import pytest

from terrain_perception import gait as G
from terrain_perception import kinematics as K
from terrain_perception.controller import (WalkingConfig, WalkingController, _shank_angles,
                                           check_footsteps)
from terrain_perception.robot_model import load_robot_model
from terrain_perception.transforms import make_T, rot_z, transform_points

DT = 0.01


def _run(ctl, t0, t_max, on_tick=None):
    t = t0
    q = None
    while t < t_max:
        cmd = ctl.update(t, q)
        q = cmd.positions
        if on_tick:
            on_tick(t, cmd)
        if ctl.phase is None and ctl.pending_steps == 0 and t > t0 + 0.1:
            break
        t += DT
    return t


def _feet_from_command(ctl, cmd):
    m = ctl.model
    centres = K.forward(m, cmd.positions.reshape(4, 3))
    T = ctl.odom_pose
    world = centres @ T[:3, :3].T + T[:3, 3]
    world[:, 2] -= m.foot_radius_m
    return world


@pytest.mark.parametrize('name', ['littledog', 'frog'])
def test_crawl_lands_feet_keeps_cog_margin_and_ends_on_pose(name):
    m = load_robot_model(name)
    cfg = WalkingConfig(plan_timeout_s=1e3, touchdown_depth_m=0.0)
    ctl = WalkingController(m, cfg)
    T0 = make_T(rot_z(0.2), [0.5, -0.3, m.standing_height_m])
    ctl.reset(0.0, None, T0)
    legs, pos = G.straight_footsteps(m, T0, 0.5)
    ctl.set_footsteps(legs, pos, 'walk', 0.0)
    margins, landed, prev = [], [], [None]
    targets = iter(zip(legs, pos))

    def tick(t, cmd):
        ph = ctl.phase
        if prev[0] is not None and ph != prev[0] and prev[0].kind == 'swing':
            leg, tgt = next(targets)
            assert leg == prev[0].legs[0]
            landed.append(np.linalg.norm(_feet_from_command(ctl, cmd)[leg] - tgt))
        if ph is not None and ph.kind == 'swing':
            feet = _feet_from_command(ctl, cmd)
            T = ctl.odom_pose
            com = K.com_base(m, cmd.positions.reshape(4, 3)) @ T[:3, :3].T + T[:3, 3]
            stance = [k for k in range(4) if k not in ph.legs]
            margins.append(G.support_margin(com[:2], feet[stance, :2]))
        prev[0] = ph

    _run(ctl, 0.0, 200.0, tick)
    assert ctl.last_error == ''
    assert ctl.steps_done == len(legs) == len(landed)
    # Feet land on the footsteps (the IK is exact; spline knots every knot_dt_s).
    assert max(landed) < 1e-6
    # The model COG is never closer than the margin to a support-triangle edge.
    assert min(margins) >= m.stability_margin_m - 2e-3
    end = make_T(rot_z(0.2), T0[:3, 3] + 0.5 * np.array([np.cos(0.2), np.sin(0.2), 0.0]))
    # Rolling feet shift the stance by a few foot-radius-scale millimetres.
    np.testing.assert_allclose(ctl.odom_pose[:3, 3], end[:3, 3], atol=0.3 * m.foot_radius_m)
    assert abs(np.arctan2(ctl.odom_pose[1, 0], ctl.odom_pose[0, 0]) - 0.2) < 0.02


def test_unreachable_step_is_refused_and_robot_keeps_standing():
    m = load_robot_model('littledog')
    ctl = WalkingController(m, WalkingConfig())
    ctl.reset(0.0)
    q0 = ctl.update(0.0).positions
    feet = G.nominal_feet_world(m, np.eye(4))
    ctl.set_footsteps([0], [feet[0] + [0.6, 0.0, 0.0]], 'walk', 0.0)
    cmd = ctl.update(0.01)
    assert 'LF' in ctl.last_error and ctl.status == 'standing'
    np.testing.assert_allclose(cmd.positions, q0, atol=1e-9)
    assert np.all(cmd.velocities == 0)


def test_bad_footsteps_raise_and_keep_the_plan():
    m = load_robot_model('littledog')
    ctl = WalkingController(m, WalkingConfig(plan_timeout_s=100))
    ctl.reset(0.0)
    legs, pos = G.straight_footsteps(m, ctl.odom_pose, 0.2)
    ctl.set_footsteps(legs, pos, 'walk', 0.0)
    bad = pos.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match='NaN'):
        ctl.set_footsteps(legs, bad, 'walk', 0.0)
    with pytest.raises(ValueError, match='leg indices'):
        ctl.set_footsteps(legs + 4, pos, 'walk', 0.0)
    with pytest.raises(ValueError, match='diagonal'):
        ctl.set_footsteps([0, 1], pos[:2], 'trot', 0.0)
    with pytest.raises(ValueError, match='gait'):
        ctl.set_footsteps(legs, pos, 'gallop', 0.0)
    assert ctl.pending_steps == len(legs)


def test_stale_plan_starts_no_step():
    m = load_robot_model('littledog')
    ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1.0))
    ctl.reset(0.0)
    legs, pos = G.straight_footsteps(m, ctl.odom_pose, 0.3)
    ctl.set_footsteps(legs, pos, 'walk', 0.0)
    t = _run(ctl, 5.0, 20.0)       # first update long after the plan was made
    assert ctl.steps_done == 0 and 'older' in ctl.last_error
    np.testing.assert_allclose(ctl.odom_pose, np.eye(4) @ make_T(t=[0, 0, 0]), atol=1e-9)
    assert t < 5.2
    # A fresh plan walks; the plan then goes stale mid-way and the robot stops and stands.
    ctl.set_footsteps(legs, pos, 'walk', 20.0)
    _run(ctl, 20.0, 60.0)
    assert 0 < ctl.steps_done < len(legs)
    assert ctl.phase is None and ctl.status == 'standing'


def test_swing_apex_clears_the_map_terrain_at_both_ends_when_the_correction_is_pitched():
    # The traverse is level in odom; with a pitched T_map_odom its map height changes along
    # the swing, and the apex must still clear the terrain (+ clearance) at both ends.
    m = load_robot_model('littledog')
    ctl = WalkingController(m, WalkingConfig(touchdown_depth_m=0.0))
    ctl.reset(0.0)
    ctl.set_height_map(lambda xy: np.where(np.asarray(xy)[..., 0] > 0.1, 0.05, 0.0))
    T = make_T(rot_z(0.3), [0.4, -0.2, 0.01])
    pitch = np.deg2rad(4.0)
    T[:3, :3] = T[:3, :3] @ np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0],
                                       [-np.sin(pitch), 0, np.cos(pitch)]])
    ctl.apply_correction(T)
    Ti = np.linalg.inv(T)
    a, b = np.array([-0.1, 0.05, 0.0]), np.array([0.25, 0.1, 0.05])      # map frame
    p0, p1 = transform_points(Ti, a[None])[0], transform_points(Ti, b[None])[0]
    apex_map = G.swing_apex(a, b, ctl.height, ctl.clearance_m, 1.5 * m.foot_radius_m,
                            m.swing_height_m)
    apex = ctl._apex(p0, p1)
    ends = transform_points(T, np.array([[*p0[:2], apex], [*p1[:2], apex]]))
    assert ends[:, 2].min() >= apex_map - 1e-3, (ends[:, 2], apex_map)   # 2nd order: 0.2 mm
    # ... and not much higher than needed (the slope over the swing, 0.35 m at 4 degrees).
    assert ends[:, 2].max() <= apex_map + 0.36 * np.sin(pitch) + 1e-3


def test_map_frame_footsteps_use_the_correction_and_odometry_reanchors():
    m = load_robot_model('littledog')
    ctl = WalkingController(m, WalkingConfig(plan_timeout_s=100, touchdown_depth_m=0.0))
    ctl.reset(0.0)
    T_map_odom = make_T(rot_z(0.5), [2.0, 1.0, 0.0])
    ctl.apply_correction(T_map_odom)
    np.testing.assert_allclose(ctl.map_pose, T_map_odom, atol=1e-12)
    legs, pos_odom = G.straight_footsteps(m, ctl.odom_pose, 0.2)
    pos_map = pos_odom @ T_map_odom[:3, :3].T + T_map_odom[:3, 3]
    ctl.set_footsteps(legs, pos_map, 'walk', 0.0, frame='map')
    _run(ctl, 0.0, 60.0)
    assert ctl.steps_done == len(legs)
    np.testing.assert_allclose(ctl.odom_pose[:2, 3], [0.2, 0.0], atol=0.005)
    with pytest.raises(ValueError, match='orthonormal'):
        ctl.apply_correction(np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError):
        ctl.apply_correction(np.full((4, 4), np.nan))


def test_pending_map_footsteps_stay_in_the_map_when_a_correction_arrives():
    # ICP moves T_map_odom mid-plan: the footsteps not yet started keep their map positions
    # (so they land where the planner chose them), the one in progress keeps its target.
    m = load_robot_model('littledog')
    cfg = WalkingConfig(plan_timeout_s=100, touchdown_depth_m=0.0)
    T_corr = make_T(rot_z(0.02), [0.01, 0.03, 0.0])

    def walk(replan):
        ctl = WalkingController(m, cfg)
        ctl.reset(0.0)
        legs, pos_map = G.straight_footsteps(m, ctl.odom_pose, 0.3)
        ctl.set_footsteps(legs, pos_map, 'walk', 0.0, frame='map')
        t = 0.0
        while ctl.steps_done < 2:
            ctl.update(t)
            t += DT
        pending = ctl.pending_steps          # not started yet
        replan(ctl, legs, pos_map, pending, t)
        _run(ctl, t, 60.0)
        assert ctl.steps_done == len(legs)
        return ctl, legs, pos_map, pending

    # The reference: the pending footsteps re-sent in odom, converted by hand.
    ref, legs, pos_map, pending = walk(lambda ctl, legs, pos, n, t: ctl.set_footsteps(
        legs[-n:], (pos[-n:] - T_corr[:3, 3]) @ T_corr[:3, :3], 'walk', t))
    ctl, *_ = walk(lambda ctl, legs, pos, n, t: ctl.apply_correction(T_corr))
    assert pending >= 4
    np.testing.assert_allclose(ctl.feet, ref.feet, atol=1e-9)
    # ... so the last footstep of each leg lands at its map position (to the controller's
    # own placement accuracy, well under the correction's 3 cm).
    feet_map = ctl.feet @ T_corr[:3, :3].T + T_corr[:3, 3]
    last = [np.flatnonzero(legs == leg)[-1] for leg in range(4)]
    assert np.linalg.norm(feet_map - pos_map[last], axis=1).max() < 0.01
    # Footsteps given in odom do not move with the correction.
    ctl2, *_ = walk(lambda ctl, legs, pos, n, t: (
        ctl.set_footsteps(legs[-n:], pos[-n:], 'walk', t), ctl.apply_correction(T_corr)))
    assert np.linalg.norm(ctl2.feet - pos_map[last], axis=1).max() < 0.01


def test_capture_requests_only_when_body_is_still():
    m = load_robot_model('littledog')
    cfg = WalkingConfig(plan_timeout_s=100, still_settle_s=0.1, capture_min_interval_s=0.5)
    ctl = WalkingController(m, cfg)
    ctl.reset(0.0)
    legs, pos = G.straight_footsteps(m, ctl.odom_pose, 0.3)
    ctl.set_footsteps(legs, pos, 'walk', 0.0)
    captures = []

    def tick(t, cmd):
        v, w = ctl.odom_velocity()
        if ctl.capture_due(t):
            captures.append(t)
            assert np.linalg.norm(v) < 1e-9 and np.linalg.norm(w) < 1e-9
            assert ctl.phase is None or ctl.phase.kind == 'swing'
            assert t - ctl.phase.t0 >= 0.1 - 1e-9 if ctl.phase else True

    t_end = _run(ctl, 0.0, 60.0, tick)
    assert len(captures) >= 3
    assert np.min(np.diff(captures)) >= 0.5 - 1e-9
    # Standing still: requests keep coming at the minimum interval.
    for k in range(1, 4):
        ctl.update(t_end + k * 0.5)
        assert ctl.capture_due(t_end + k * 0.5)


def test_preview_matches_the_commands_at_those_times():
    m = load_robot_model('littledog')
    a, b = (WalkingController(m, WalkingConfig(plan_timeout_s=100)) for _ in range(2))
    legs, pos = G.straight_footsteps(m, np.eye(4) @ make_T(t=[0, 0, m.standing_height_m]),
                                     0.1)
    for c in (a, b):
        c.reset(0.0, None, make_T(t=[0, 0, m.standing_height_m]))
        c.set_footsteps(legs, pos, 'walk', 0.0)
    a.update(0.2)
    times = 0.2 + np.arange(11) * 0.01         # within the first body shift
    prev = a.preview(times)
    for k, t in enumerate(times):
        cmd = b.update(t)
        np.testing.assert_allclose(prev.positions[k], cmd.positions, atol=1e-12)
        np.testing.assert_allclose(prev.velocities[k], cmd.velocities, atol=1e-12)
    assert np.abs(prev.positions[-1] - prev.positions[0]).max() > 1e-4   # it does move


def test_long_trot_steps_are_refused():
    m = load_robot_model('littledog')
    ctl = WalkingController(m, WalkingConfig(plan_timeout_s=100))
    ctl.reset(0.0)
    legs, pos = G.straight_footsteps(m, ctl.odom_pose, 0.4, 0.1, gait='trot')
    pos[legs == 0] += [0.04, 0.0, 0.0]         # LF's first trot step becomes 0.14 m > 0.12 m
    ctl.set_footsteps(legs, pos, 'trot', 0.0)
    ctl.update(0.0)
    assert 'trot step of LF' in ctl.last_error and ctl.steps_done == 0
    assert ctl.status == 'standing'


def test_upcoming_stance_is_where_a_new_plan_starts():
    # During a step, the stance after it (swing target included) and the next crawl leg.
    m = load_robot_model('littledog')
    ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3, touchdown_depth_m=0.0))
    ctl.reset(0.0, None, make_T(np.eye(3), [0.0, 0.0, m.standing_height_m]))
    feet0, nxt = ctl.upcoming_stance()
    assert nxt is None                                   # no step yet: any leg may start
    legs, pos = G.straight_footsteps(m, ctl.odom_pose, 0.3)
    ctl.set_footsteps(legs, pos, 'walk', 0.0)
    seen = []

    def tick(t, cmd):
        ph = ctl.phase
        if ph is not None and (not seen or seen[-1][0] != (ph.kind, ph.t0)):
            feet, nxt = ctl.upcoming_stance()
            seen.append(((ph.kind, ph.t0), ctl.steps_done, feet, nxt))
        if ctl.steps_done >= 2:
            ctl.clear_plan()
    _run(ctl, 0.0, 30.0, tick)
    # In the first shift and swing: leg legs[0] is (or will be) at its target, legs[1] next.
    for _, done, feet, nxt in seen[:2]:
        assert done == 0
        np.testing.assert_allclose(feet[legs[0]], pos[0], atol=1e-9)
        assert nxt == legs[1] == list(G.CRAWL_ORDER)[(list(G.CRAWL_ORDER).index(legs[0]) + 1) % 4]
    # At rest after the plan was cleared (the step under way when it was finished too):
    # every executed target reached, the following leg next.
    done = ctl.steps_done
    assert ctl.phase is None and 2 <= done < len(legs)
    feet, nxt = ctl.upcoming_stance()
    np.testing.assert_allclose(feet[legs[:done]], pos[:done], atol=0.5 * m.foot_radius_m)
    assert nxt == legs[done]


def _recentrings_with_a_rocking_imu(ctl, t_max=8.0):
    """Body shifts the controller starts after its two steps are done, over ``t_max`` of
    simulated time, the IMU reading a roll of +-3 deg that changes sign every 0.3 s whatever
    the body does (a body rocking from side to side)."""
    t, q, last, shifts = 0.0, None, None, 0
    while t < t_max:
        a = np.radians(3.0) * (1 if int(t / 0.3) % 2 else -1)
        R = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)],
                      [0.0, np.sin(a), np.cos(a)]])
        q = ctl.update(t, q, attitude=R).positions
        ph = ctl.phase
        if ctl.steps_done == 2 and ph is not None and ph != last and ph.kind == 'shift':
            shifts += 1
        last = ph
        t += DT
    return shifts


def test_the_body_is_recentred_once_per_stance(monkeypatch):
    # Every recentring levels the body on the measured tilt, which changes the feet's believed
    # heights and so the next goal: recentring again on the same feet goes on while the body
    # rocks (here an IMU reading +-3 deg alternately; in the rocks walks up to 11 recentrings
    # in a row), each levelling on the rocking of the last. Once per stance: one shift after
    # the plan; recentring on every call (the counterfactual): many (measured: 1 vs 16).
    m = load_robot_model('littledog')
    T = make_T(np.eye(3), [0.0, 0.0, m.standing_height_m])
    legs, pos = G.straight_footsteps(m, T, 0.2)

    def fresh():
        ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3))
        ctl.reset(0.0, None, T)
        ctl.set_footsteps(legs[:2], pos[:2], 'walk', 0.0)
        return ctl
    once = _recentrings_with_a_rocking_imu(fresh())
    assert once <= 1
    recenter = WalkingController._recenter

    def every_time(self, t0):
        self._recentred_at = -1
        return recenter(self, t0)
    monkeypatch.setattr(WalkingController, '_recenter', every_time)
    many = _recentrings_with_a_rocking_imu(fresh())
    assert many >= 5


def test_upcoming_body_is_where_the_step_under_way_leaves_the_body():
    # At rest: the current pose. During the body shift before a swing: the pose the shift
    # ends at (the swing keeps it), which is where the body is once the shift is done.
    m = load_robot_model('littledog')
    T = make_T(np.eye(3), [0.0, 0.0, m.standing_height_m])
    legs, pos = G.straight_footsteps(m, T, 0.2)
    ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3))
    ctl.reset(0.0, None, T)
    np.testing.assert_allclose(ctl.upcoming_body(), T, atol=1e-12)
    ctl.set_footsteps(legs[:1], pos[:1], 'walk', 0.0)
    q = ctl.update(0.0).positions
    assert ctl.phase.kind == 'shift'
    expected = ctl.upcoming_body()
    assert np.linalg.norm(expected[:2, 3] - T[:2, 3]) > 0.005      # the COG shift
    t = 0.0
    while ctl.phase is not None and ctl.phase.kind == 'shift':
        t += DT
        q = ctl.update(t, q).positions
    np.testing.assert_allclose(ctl.odom_pose, expected, atol=1e-9)


def test_the_dry_run_without_joint_splines_decides_as_with_them(monkeypatch):
    """check_footsteps skips the joint splines (the checks and the end state need only the IK
    knots). On 30 jittered plans, accepted and refused alike, it returns exactly what the
    same dry run with the splines built returns."""
    m = load_robot_model('littledog')
    T = make_T(np.eye(3), [0.0, 0.0, m.standing_height_m])
    feet = G.nominal_feet_world(m, T)
    legs, pos = G.straight_footsteps(m, T, 0.3)
    rng = np.random.default_rng(3)
    plans = [pos[:4] + rng.normal(0.0, [0.035, 0.035, 0.02], (4, 3)) for _ in range(30)]
    fast = [check_footsteps(m, WalkingConfig(), feet, legs[:4], p) for p in plans]
    build = WalkingController._build

    def with_splines(self, *args, **kw):
        self._dry = False
        return build(self, *args, **kw)
    monkeypatch.setattr(WalkingController, '_build', with_splines)
    slow = [check_footsteps(m, WalkingConfig(), feet, legs[:4], p) for p in plans]
    assert fast == slow
    n = [k for k, _ in fast]
    assert min(n) < 4 and n.count(4) >= 3          # refusals and acceptances both tested


def test_check_footsteps_dry_runs_the_controllers_own_refusals():
    m = load_robot_model('littledog')
    T = make_T(np.eye(3), [0.0, 0.0, m.standing_height_m])
    feet = G.nominal_feet_world(m, T)
    legs, pos = G.straight_footsteps(m, T, 0.3)
    assert check_footsteps(m, WalkingConfig(), feet, legs[:4], pos[:4]) == (4, '')
    wide = pos[:4].copy()
    wide[0, 1] += 0.08                           # the first foot far out sideways
    n, why = check_footsteps(m, WalkingConfig(), feet, legs[:4], wide)
    assert n == 0 and 'reach' in why
    long = pos[:4].copy()
    long[1, 0] += 0.3                            # the second step far too long
    n, why = check_footsteps(m, WalkingConfig(), feet, legs[:4], long)
    assert n == 1 and 'longer than' in why
    # the same footsteps executed by a controller: it refuses exactly there
    ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3))
    ctl.reset(0.0, None, T)
    ctl.set_footsteps(legs[:4], long, 'walk', 0.0)
    _run(ctl, 0.0, 30.0)
    assert ctl.steps_done == 1 and 'longer than' in ctl.last_error


def test_body_tilts_with_the_feet_plane_and_keeps_legs_mid_range():
    """Front feet step onto a 4 cm ledge. With body_tilt_gain 1 the body ends pitched nose-up
    by the feet plane's slope, the commanded feet are where they were planned, and the most
    stretched leg is less stretched than with the level body (gain 0)."""
    m = load_robot_model('littledog')
    T = make_T(np.eye(3), [0.0, 0.0, m.standing_height_m])
    legs, pos = G.straight_footsteps(m, T, 0.05)
    legs, pos = legs[:4], pos[:4].copy()
    pos[legs < 2, 2] += 0.04                      # LF, RF onto the ledge
    stretch = {}
    for gain in (1.0, 0.0):
        ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3, body_tilt_gain=gain))
        ctl.reset(0.0, None, T)
        ctl.set_footsteps(legs, pos, 'walk', 0.0)
        last = []
        _run(ctl, 0.0, 30.0, lambda t, cmd: last.__setitem__(slice(None), [cmd]))
        assert ctl.steps_done == 4, ctl.last_error
        feet = _feet_from_command(ctl, last[0])
        # contacts roll with the shank angle during later shifts (up to ~half a foot radius)
        np.testing.assert_allclose(feet[legs, :2], pos[:, :2], atol=0.5 * m.foot_radius_m)
        np.testing.assert_allclose(feet[legs, 2], pos[:, 2], atol=0.003)
        R = ctl.odom_pose[:3, :3]
        pitch = float(np.arcsin(-R[2, 0]))
        spacing = np.mean(pos[legs < 2, 0]) - np.mean(pos[legs >= 2, 0])
        expect = -gain * np.arctan2(0.04, spacing)
        assert pitch == pytest.approx(expect, abs=2e-3)
        centres = K.forward(m, last[0].positions.reshape(4, 3))
        stretch[gain] = float(np.max(np.linalg.norm(
            centres - np.array(m.leg_plane_offsets), axis=1)))
    assert stretch[1.0] < stretch[0.0] - 0.003


def test_body_tilt_follows_a_foot_only_as_far_as_the_map_under_it_allows():
    """The same 4 cm ledge, with a height map: where the map shows the ledge the body pitches
    with the feet; where the map says the ground under the front feet is flat (the feet held
    up by something the map does not know, as by a shank resting on an obstacle) the pitch
    is capped by ``tilt_map_tolerance_m`` above the map."""
    m = load_robot_model('littledog')
    T = make_T(np.eye(3), [0.0, 0.0, m.standing_height_m])
    legs, pos = G.straight_footsteps(m, T, 0.05)
    legs, pos = legs[:4], pos[:4].copy()
    pos[legs < 2, 2] += 0.04
    edge = 0.5 * (pos[legs < 2, 0].min() + pos[legs >= 2, 0].max())
    spacing = np.mean(pos[legs < 2, 0]) - np.mean(pos[legs >= 2, 0])
    tol = 0.01
    pitches = {}
    for name, height in (('ledge', lambda xy: np.where(np.asarray(xy)[..., 0] > edge, 0.04, 0.0)),
                         ('flat', lambda xy: np.zeros(np.shape(xy)[:-1]))):
        ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3, body_tilt_gain=1.0,
                                                 tilt_map_tolerance_m=tol), height=height)
        ctl.reset(0.0, None, T)
        ctl.set_footsteps(legs, pos, 'walk', 0.0)
        _run(ctl, 0.0, 30.0)
        assert ctl.steps_done == 4, ctl.last_error
        R = ctl.odom_pose[:3, :3]
        pitches[name] = float(np.arcsin(-R[2, 0]))
    assert pitches['ledge'] == pytest.approx(-np.arctan2(0.04, spacing), abs=2e-3)
    # the front feet count at most tol above the flat map (the hind feet stand
    # touchdown_depth_m below it): the pitch of a ledge that much high
    dz = tol + WalkingConfig().touchdown_depth_m
    assert pitches['flat'] == pytest.approx(-np.arctan2(dz, spacing), abs=2e-3)


def _shift_zmp_offsets(cfg):
    """Largest ZMP excursion (cart-table: h |a| / g) of the desired body over each crawl body
    shift of a straight 0.4 m walk, and the walk's duration."""
    m = load_robot_model('littledog')
    ctl = WalkingController(m, cfg)
    T0 = make_T(np.eye(3), [0.0, 0.0, m.standing_height_m])
    ctl.reset(0.0, None, T0)
    legs, pos = G.straight_footsteps(m, T0, 0.4)
    ctl.set_footsteps(legs, pos, 'walk', 0.0)
    rows = []
    _run(ctl, 0.0, 300.0, lambda t, cmd: rows.append(
        (t, ctl.phase.kind if ctl.phase else '', *ctl.odom_pose[:3, 3])))
    t = np.array([r[0] for r in rows])
    kind = np.array([r[1] for r in rows])
    p = np.array([r[2:] for r in rows])
    acc = np.gradient(np.gradient(p[:, :2], t, axis=0), t, axis=0)
    h = p[:, 2] - 0.0                                  # flat ground at z = 0
    zmp = h * np.linalg.norm(acc, axis=1) / 9.81
    inner = (kind == 'shift') & np.r_[False, kind[:-1] == 'shift'] & np.r_[kind[1:] == 'shift',
                                                                            False]
    assert ctl.steps_done == len(legs) and ctl.last_error == ''
    return float(zmp[inner].max()), float(t[-1])


def test_body_shifts_keep_the_zmp_within_the_bound():
    fast, t_fast = _shift_zmp_offsets(WalkingConfig(plan_timeout_s=1e3,
                                                    shift_zmp_offset_m=0.0))
    slow, t_slow = _shift_zmp_offsets(WalkingConfig(plan_timeout_s=1e3))   # default 5 mm
    # The profile's fixed 0.35 s shifts swing the ZMP centimetres off the COM (the stability
    # margin is 1.5 cm); the bounded ones stay within 5 mm (+3 % for the numeric derivative).
    assert fast > 0.012
    assert slow <= 0.005 * 1.03
    assert t_slow > t_fast


def _straight_rh(side_m=0.0):
    """A standing LittleDog controller whose RH foot (moved ``side_m`` sideways) is lowered into
    a hole until the leg is straight: ``(ctl, reach, lo, hi)`` with ``reach(dz) -> (IK angles
    or None, feet)`` and the straight leg between the depths ``lo`` (in reach) and ``hi``."""
    m = load_robot_model('littledog')
    ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3, touchdown_depth_m=0.0))
    ctl.reset(0.0, None, make_T(np.eye(3), [0.0, 0.0, m.standing_height_m]))
    T = G.pose_to_T(ctl._body)
    base = ctl._feet.copy()
    base[3, 1] += side_m

    def reach(dz):
        feet = base.copy()
        feet[3, 2] -= dz
        return ctl._ik(T, feet), feet

    lo, hi = 0.0, 0.2
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if reach(mid)[0] is not None else (lo, mid)
    return ctl, reach, lo, hi


def _step_once(ctl, leg, target):
    """Plan one step of ``leg`` to ``target`` and run with perfect tracking until it is done
    (6 s at most): ``(errors seen, t, last command)``."""
    ctl.set_footsteps([leg], target[None], 'walk', 0.0)
    errors, t, q = [], 0.0, None
    while t < 6.0 and ctl.steps_done == 0:
        q = ctl.update(t, q).positions
        if ctl.last_error:
            errors.append(ctl.last_error)
        t += DT
    return errors, t, q


def test_a_stance_a_hair_past_full_stretch_is_reanchored_not_refused_forever():
    # Closed-loop run L: the believed RH foot ended a segment 0.2 mm past the fully stretched
    # leg; every later segment failed at its first knot ("pose 0 leg RH: target beyond the leg
    # length") and the robot refused the same step 200+ times. The last commanded angles are a
    # valid configuration: the controller re-anchors the belief on them and walks on.
    rh = 3
    ctl, reach, lo, hi = _straight_rh()
    q_ok, _ = reach(lo - 1e-5)
    _, past = reach(hi + 3e-4)
    assert q_ok is not None and reach(hi + 3e-4)[0] is None
    ctl._feet, ctl._q_last = past, q_ok.reshape(12)
    ctl._phi_ref = _shank_angles(q_ok.reshape(4, 3))
    target = np.array([past[rh, 0] + 0.02, past[rh, 1] + 0.02, 0.0])   # out of the hole
    errors, t, q = _step_once(ctl, rh, target)
    assert not errors, errors[:1]
    assert ctl.steps_done == 1
    assert ctl.touchdowns['reanchored'] >= 1
    assert np.linalg.norm(_feet_from_command(ctl, ctl.update(t, q))[rh] - target) < 2e-3


def test_a_stale_rolling_reference_does_not_push_a_stretched_leg_out_of_reach():
    # A ground-truth rocks walk (seed 7) ended refusing the same step at every replan: 'pose 0
    # leg LH: target beyond the leg length' with the stance itself in reach. The feet roll from
    # the shank angles kept since the previous segment; 0.007 rad off the angles the stance
    # was re-solved at, that roll moved the stretched leg's first target out of reach.
    rh = 3
    # out to the side: the leg slants, rolling changes reach
    ctl, reach, lo, _ = _straight_rh(side_m=-0.05)
    T = G.pose_to_T(ctl._body)
    q, feet = reach(lo - 2e-6)
    assert q is not None
    ctl._feet, ctl._q_last = feet, q.reshape(12)
    stale = _shank_angles(q)
    stale[rh, 1] -= 0.02                # the foot rolls 0.2 mm outwards from here
    ctl._phi_ref = stale
    roll = ctl._rolling(q[None], np.ones(1), np.zeros(1))[0]
    assert ctl._ik(T, feet + roll) is None          # the first knot would be out of reach
    target = np.array([feet[rh, 0] + 0.02, feet[rh, 1] + 0.03, 0.0])
    errors, _, _ = _step_once(ctl, rh, target)
    assert not errors, errors[:1]
    assert ctl.steps_done == 1 and ctl.touchdowns['reanchored'] >= 1


def _torques_for(m, q, fz):
    """Joint torques (12,) with which each foot feels the vertical ground force ``fz`` (4,)
    [N] (base frame), the inverse of kinematics.foot_forces."""
    J = K.jacobian(m, np.asarray(q).reshape(4, 3))
    f = np.zeros((4, 3))
    f[:, 2] = fz
    return -np.einsum('kji,kj->ki', J, f).reshape(12)


def test_a_hanging_stance_foot_is_lowered_until_it_touches():
    # RH reads its own weight (-0.8 N): it hangs a little above the ground. Standing and
    # walking, the controller lowers it at stance_extend_m_s until it reads a load, up to
    # max_stance_extend_m between two of its swings; the lowered foot becomes the stance the
    # next segment starts from (no jump in the joint commands), and the other feet stay.
    m = load_robot_model('littledog')

    def run(rate, hang_until, walk=True, t_stand=0.6):
        # (no recentring: it would move the body towards the lowered foot's new height)
        cfg = WalkingConfig(plan_timeout_s=1e3, stance_extend_m_s=rate, recenter=False)
        ctl = WalkingController(m, cfg)
        ctl.reset(0.0, None, make_T(np.eye(3), [0.0, 0.0, m.standing_height_m]))
        fz = np.array([7.0, 7.0, 7.0, -0.8])
        q, t, z, jumps = K.standing_joint_angles(m).reshape(12), 0.0, [], []

        def tick(t, q):
            before = ctl.phase.legs if ctl.phase is not None else ()
            cmd = ctl.update(t, q, np.zeros(12), _torques_for(m, q, fz))
            moving = set(before) | set(ctl.phase.legs if ctl.phase is not None else ())
            stance = [k for k in range(4) if k not in moving]
            jumps.append(np.abs(cmd.positions - q).reshape(4, 3)[stance].max())
            return cmd.positions
        while t < t_stand:
            fz[3] = -0.8 if t < hang_until else 3.0        # it touches from hang_until on
            q = tick(t, q)
            z.append(K.forward(m, q.reshape(4, 3))[:, 2])
            t += DT
        if walk:
            legs, pos = G.straight_footsteps(m, ctl.odom_pose, 0.1)
            ctl.set_footsteps(legs, pos, 'walk', t)
            t_walk = t
            while t < t_walk + 6.0 and (ctl.phase is not None or ctl.pending_steps):
                # RH hangs again for 0.2 s while the body starts its first shift
                fz[3] = -0.8 if t < t_walk + 0.2 else 3.0
                q = tick(t, q)
                t += DT
            assert ctl.steps_done == len(legs), ctl.last_error
        return ctl, np.array(z), max(jumps)

    ctl, z, jump = run(0.01, 0.3)
    drop = z[0] - z                            # how far each foot was lowered (base frame)
    assert np.abs(drop[:, :3]).max() < 1e-6    # the loaded feet stay
    # 3 debounce ticks, then 1 cm/s: ~2.7 mm by 0.3 s; then it touches and stays
    assert 0.0022 < drop[30, 3] < 0.0031
    assert abs(drop[-1, 3] - drop[31, 3]) < 1e-6
    assert ctl.touchdowns['extended'] >= 1
    assert jump < 0.02       # stance joints: each segment starts from the lowered foot
    # capped: never more than max_stance_extend_m between two swings of the foot
    ctl, z, _ = run(0.01, 10.0, walk=False, t_stand=1.5)
    assert abs((z[0] - z)[-1, 3] - 0.01) < 2e-4
    # off: nothing moves
    ctl, z, _ = run(0.0, 10.0, walk=False)
    assert np.abs(z[0] - z).max() < 1e-9 and ctl.touchdowns['extended'] == 0


def test_a_swing_cut_in_the_air_is_checked_and_the_foot_probed_down():
    # Near the end of LF's swing its motors read a load for a few ticks (a swing foot that
    # decelerates loads them like a contact; seen on rocks, 3.2 N at 37 mm above the
    # foothold): the swing ends there. Then the foot reads its own weight, hanging. With
    # touchdown_verify_s the body holds still, sees it hang and probes the foot down until
    # it touches the ground; without, the controller believes the foot stands in mid-air.
    m = load_robot_model('littledog')

    def step(verify_s):
        cfg = WalkingConfig(plan_timeout_s=1e3, touchdown_verify_s=verify_s,
                            stance_extend_m_s=0.0, touchdown_depth_m=0.0)
        ctl = WalkingController(m, cfg)
        ctl.reset(0.0, None, make_T(np.eye(3), [0.0, 0.0, m.standing_height_m]))
        q, t = K.standing_joint_angles(m).reshape(12), 0.0
        f0 = ctl.feet[0]
        ctl.set_footsteps([0], [[f0[0] + 0.06, f0[1], 0.0]], 'walk', 0.0)
        cut_above, probed, kinds = None, False, []
        while t < 3.0:
            ph = ctl.phase
            if ph is not None and (not kinds or kinds[-1] != ph.kind):
                kinds.append(ph.kind)
            foot = transform_points(ctl.odom_pose, K.forward(m, q.reshape(4, 3)))[0]
            lf_z = foot[2] - m.foot_radius_m
            fz = np.array([-0.8, 7.0, 7.0, 7.0])
            if ph is not None and ph.kind == 'swing' and 0 in ph.legs:
                frac = (t - ph.t0) / ph.duration
                if 0.8 <= frac <= 0.9:
                    fz[0] = 3.0                 # the spurious load
            elif lf_z <= 0.0005:
                fz[0] = 3.0                     # on the ground
            probed |= ph is not None and ph.kind == 'probe'
            was_swing = ph is not None and ph.kind == 'swing'
            q = ctl.update(t, q, np.zeros(12), _torques_for(m, q, fz)).positions
            if was_swing and (ctl.phase is None or ctl.phase.kind != 'swing'):
                cut_above = ctl.feet[0, 2]
            t += DT
        return ctl, cut_above, probed, kinds

    ctl, cut_above, probed, kinds = step(0.05)
    assert ctl.touchdowns['early'] == 1 and cut_above > 0.01       # cut in the air
    assert probed and ctl.touchdowns['hanging_after_swing'] == 1
    # The wait is a phase of its own (a runner that waits for phase None waits for it too).
    assert kinds[kinds.index('swing'):][:3] == ['swing', 'verify', 'probe'], kinds
    assert abs(ctl.feet[0, 2]) < 0.002 and ctl.steps_done == 1     # found the ground
    blind, cut_above, probed, kinds = step(0.0)
    assert blind.touchdowns['early'] == 1 and not probed and 'verify' not in kinds
    assert blind.feet[0, 2] > 0.01                                  # believed in mid-air


def test_inward_swing_lifts_sideways_only_towards_the_centre_line():
    """swing_inward_lift: a foot standing out to the side and stepping inwards makes its
    sideways part while lifting (in the body's frame, here turned 30 deg); stepping outwards,
    or with the option off, it lifts straight up."""
    m = load_robot_model('littledog')
    yaw = np.radians(30.0)
    T = make_T(rot_z(yaw), [1.0, 0.5, m.standing_height_m])
    ctl = WalkingController(m, WalkingConfig())
    ctl.reset(0.0)
    ctl._body = np.array([1.0, 0.5, m.standing_height_m, yaw, 0.0, 0.0])
    out_rh = transform_points(T, np.array([[-0.16, -0.11, -m.standing_height_m]]))[0]
    in_rh = transform_points(T, np.array([[-0.10, -0.07, -m.standing_height_m + 0.05]]))[0]
    far_rh = transform_points(T, np.array([[-0.10, -0.15, -m.standing_height_m]]))[0]
    sw = ctl._swing_trajectory(out_rh, in_rh, in_rh[2] + 0.03, 0.4)
    side = np.array([-np.sin(yaw), np.cos(yaw)])
    np.testing.assert_allclose(sw.lift_xy, 0.04 * side, atol=1e-9)    # 4 cm in, body's y
    top = sw.position(0.1)                                               # end of the lift
    lateral = float((top[:2] - out_rh[:2]) @ side)
    assert lateral == pytest.approx(0.04, abs=0.002)
    assert ctl._swing_trajectory(in_rh, far_rh, in_rh[2] + 0.03, 0.4).lift_xy is None
    off = WalkingController(m, WalkingConfig(swing_inward_lift=False))
    off.reset(0.0)
    off._body = ctl._body.copy()
    assert off._swing_trajectory(out_rh, in_rh, in_rh[2] + 0.03, 0.4).lift_xy is None


def test_fore_aft_lift_only_for_a_foot_far_from_its_nominal_place():
    """swing_lift_fore_aft_m (a swing the shift asks to lift along the step): a hind foot 10
    cm behind its nominal place stepping 8 cm forward makes the 5 cm beyond the threshold
    while lifting; 3 cm behind, or stepping further back, it lifts straight up."""
    m = load_robot_model('littledog')
    yaw = np.radians(-20.0)
    T = make_T(rot_z(yaw), [0.8, -0.1, m.standing_height_m])
    ctl = WalkingController(m, WalkingConfig(swing_inward_lift=False,
                                             swing_lift_fore_aft_m=0.05))
    ctl.reset(0.0)
    ctl._body = np.array([0.8, -0.1, m.standing_height_m, yaw, 0.0, 0.0])
    nom = np.array(m.nominal_feet[2])                       # LH

    def at(dx):
        return transform_points(T, (nom + [dx, 0.0, 0.0])[None])[0]
    ahead = np.array([np.cos(yaw), np.sin(yaw)])

    def lift(a, b, **kw):
        return ctl._swing_trajectory(at(a), at(b), 0.05, 0.4, fore_aft=True, **kw).lift_xy
    np.testing.assert_allclose(lift(-0.10, -0.02, leg=2), 0.05 * ahead, atol=1e-9)
    assert lift(-0.03, 0.05, leg=2) is None
    assert lift(-0.10, -0.12, leg=2) is None
    assert lift(-0.10, -0.02) is None                                  # no leg
    assert ctl._swing_trajectory(at(-0.10), at(-0.02), 0.05, 0.4, leg=2).lift_xy is None


def test_fore_aft_lift_is_used_only_when_the_straight_lift_is_out_of_reach(monkeypatch):
    """The shift plans the straight lift first and the lift along the step only when no body
    pose reaches the straight one; the swing then flies the path the shift checked. A hind
    foot 10 cm behind its nominal place on flat ground (rocks-6cm ground-truth seed 0 stalled
    on LH 10 cm behind its hip, refused at lift-off): the straight lift reaches, so the stride
    keeps it (lifting along every such step dragged the feet of flat strides). With the
    straight lift made unreachable (a mock joint limit: LH may not rise more than 1 cm within
    1 cm of where it stands), the option is what lets the step through."""
    m = load_robot_model('littledog')
    nom = np.array(m.nominal_feet, float)
    nom[:, 2] = 0.0
    feet = nom.copy()
    feet[2, 0] -= 0.10
    target = nom[2] + [-0.01, 0.0, 0.0]
    cfg = WalkingConfig(swing_lift_fore_aft_m=0.05)
    asked = []
    plain = WalkingController._swing_trajectory

    def spy(self, *a, fore_aft=False, **kw):
        asked.append(fore_aft)
        return plain(self, *a, fore_aft=fore_aft, **kw)
    monkeypatch.setattr(WalkingController, '_swing_trajectory', spy)
    assert check_footsteps(m, cfg, feet, [2], [target]) == (1, '')
    assert asked and not any(asked)                                    # straight lift only

    reachable = WalkingController._reachable

    def no_straight_lift(self, body, poses):
        lh = np.asarray(poses)[:, 2]
        if np.any((lh[:, 2] > feet[2, 2] + 0.01) & (lh[:, 0] < feet[2, 0] + 0.01)):
            self.last_ik_reasons = ['leg LH: mock joint limit']
            return False
        return reachable(self, body, poses)
    monkeypatch.setattr(WalkingController, '_reachable', no_straight_lift)
    n, why = check_footsteps(m, WalkingConfig(swing_lift_fore_aft_m=0.0), feet, [2], [target])
    assert n == 0 and 'no body pose keeps every foot in reach' in why
    asked.clear()
    assert check_footsteps(m, cfg, feet, [2], [target]) == (1, '')
    assert True in asked and asked[-1] is True                         # the swing flew it


def test_a_body_shift_that_turns_a_shank_into_a_rock_is_refused():
    """shank_max_penetration_m: LittleDog's hind knees point forwards, so moving the body
    forward turns a hind shank down towards the ground ahead of its foot. With a 6 cm rock
    3.5 cm ahead of RH, two front steps of 8 cm would push RH's shank 15 mm into it (the
    robot would rest on the shank with the foot in the air); the controller (and so its dry
    run) refuses the second and names the leg. Shorter steps, or no rock, or the check off
    (negative): both steps go."""
    m = load_robot_model('littledog')
    nom = np.array(m.nominal_feet, float)
    nom[:, 2] = 0.0
    x_rock = nom[3, 0] + 0.035

    def rock(xy):
        x, y = np.asarray(xy)[..., 0], np.asarray(xy)[..., 1]
        return np.where((x > x_rock) & (x < x_rock + 0.1) & (y < -0.03) & (y > -0.15), 0.06, 0.0)

    def steps(adv):
        return [1, 0], [nom[1] + [adv, 0.0, 0.0], nom[0] + [adv, 0.0, 0.0]]
    n, why = check_footsteps(m, WalkingConfig(), nom, *steps(0.08), height=rock)
    assert n == 1 and 'leg RH: shank' in why and 'into the terrain' in why
    assert check_footsteps(m, WalkingConfig(), nom, *steps(0.03), height=rock) == (2, '')
    assert check_footsteps(m, WalkingConfig(), nom, *steps(0.08),
                           height=lambda xy: np.zeros(np.shape(xy)[:-1])) == (2, '')
    assert check_footsteps(m, WalkingConfig(shank_max_penetration_m=-1.0), nom, *steps(0.08),
                           height=rock) == (2, '')


def test_the_body_rises_over_a_rock_under_its_belly_as_far_as_the_legs_reach():
    """belly_clearance_m: rocks-12cm ground-truth walks stopped with LittleDog's belly
    (11.5 cm up at the standing height) on 10-11 cm rocks between its feet. At 0.01 a rock
    under the body makes the controller lift the body to keep the underside 1 cm above it
    while the legs reach: 12 cm under a nominal stance -> 0.16 m; flat ground or the check off
    leave it at the standing height; a rock already under the body and too tall for the legs
    is not made worse (capped at their reach; the robot was standing on it already)."""
    m = load_robot_model('littledog')

    def rock(h):
        def f(xy):
            x, y = np.asarray(xy)[..., 0], np.asarray(xy)[..., 1]
            return np.where((np.abs(x) < 0.04) & (np.abs(y) < 0.03), h, 0.0)
        return f

    def top_of_body(height, **kw):
        kw = {'belly_clearance_m': 0.01, **kw}
        ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3, **kw), height=height)
        ctl.reset(0.0, None, make_T(np.eye(3), [0.0, 0.0, m.standing_height_m]))
        target = ctl._feet[2] + [0.03, 0.0, 0.0]                      # LH 3 cm forward
        ctl.set_footsteps([2], target[None], 'walk', 0.0)
        t, q, z = 0.0, None, []
        while t < 6.0 and ctl.steps_done == 0:
            q = ctl.update(t, q).positions
            z.append(ctl._body[2])
            t += DT
        assert ctl.steps_done == 1 and not ctl.last_error
        return max(z)

    half = 0.5 * float(m.body_size_m[2])
    assert top_of_body(rock(0.12)) == pytest.approx(0.12 + half + 0.01, abs=0.002)
    assert top_of_body(rock(0.0)) == pytest.approx(m.standing_height_m, abs=0.002)
    assert top_of_body(rock(0.12), belly_clearance_m=-1.0) == pytest.approx(
        m.standing_height_m, abs=0.002)
    tall = top_of_body(rock(0.25))                                   # beyond any reach
    assert m.standing_height_m + 0.01 < tall < 0.25


def test_a_body_shift_that_lowers_the_belly_onto_a_rock_is_refused():
    """A 14 cm block just ahead of the body: two 8 cm front steps move the body forward over
    its edge, where the legs cannot lift the belly 1.2 cm clear of it (it would need 0.182 m,
    beyond their reach from the floor). The controller (and its dry run) refuses the step
    that gets there and says why; a 10 cm block it rises over; with the check off the
    steps go (and the belly comes down on the block)."""
    m = load_robot_model('littledog')
    nom = np.array(m.nominal_feet, float)
    nom[:, 2] = 0.0
    front = 0.5 * float(m.body_size_m[0])

    def block(h):
        def f(xy):
            x, y = np.asarray(xy)[..., 0], np.asarray(xy)[..., 1]
            return np.where((x > front + 0.005) & (x < front + 0.06) & (np.abs(y) < 0.04),
                            h, 0.0)
        return f

    steps = [3, 1, 2, 0], [nom[3] + [0.04, 0, 0], nom[1] + [0.08, 0, 0], nom[2] + [0.04, 0, 0],
                           nom[0] + [0.08, 0, 0]]
    n, why = check_footsteps(m, WalkingConfig(), nom, *steps, height=block(0.14))
    assert n < 4 and 'belly' in why and 'above the terrain' in why, (n, why)
    assert check_footsteps(m, WalkingConfig(), nom, *steps, height=block(0.10)) == (4, '')
    assert check_footsteps(m, WalkingConfig(belly_clearance_m=-1.0), nom, *steps,
                           height=block(0.14)) == (4, '')


def test_swing_max_speed_stretches_the_swings_not_the_landings():
    """swing_max_speed_m_s: the swing foot's commanded speed stays under the cap (a fast
    profile swing exceeds it), the swings last longer, and the feet still land on the
    footsteps (within the millimetres the stance feet roll)."""
    m = load_robot_model('littledog')
    T0 = make_T(rot_z(0.0), [0.0, 0.0, m.standing_height_m])
    legs, pos = G.straight_footsteps(m, T0, 0.3)
    out = {}
    for cap in (0.0, 0.4):
        ctl = WalkingController(m, WalkingConfig(plan_timeout_s=1e3, touchdown_depth_m=0.0,
                                                 swing_max_speed_m_s=cap))
        ctl.reset(0.0, None, T0)
        ctl.set_footsteps(legs, pos, 'walk', 0.0)
        speeds, swing_t, prev = [], [0.0], {}

        def tick(t, cmd, ctl=ctl, speeds=speeds, swing_t=swing_t, prev=prev):
            ph = ctl.phase
            feet = _feet_from_command(ctl, cmd)
            if ph is not None and ph.kind == 'swing':
                swing_t[0] += DT
                leg = ph.legs[0]
                if prev.get('leg') == leg:
                    speeds.append(np.linalg.norm(feet[leg] - prev['p']) / DT)
                prev.update(leg=leg, p=feet[leg])
            else:
                prev.clear()

        _run(ctl, 0.0, 200.0, tick)
        assert ctl.last_error == '' and ctl.steps_done == len(legs)
        # rolling feet shift the stance by millimetres (as in the crawl test)
        np.testing.assert_allclose(ctl.feet[legs[-1]], pos[-1], atol=0.3 * m.foot_radius_m)
        out[cap] = (max(speeds), swing_t[0])
    assert out[0.0][0] > 0.6                      # the profile's 0.35 s swings
    assert out[0.4][0] < 0.4 * 1.1                # finite differences of the splines
    assert out[0.4][1] > 1.5 * out[0.0][1]
