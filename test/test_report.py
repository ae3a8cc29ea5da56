"""The demo report: latency figures (per-capture stamps in, per-node wall times out) and the
localisation errors against ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from terrain_ros.report import CourseInfo, RunData, compute_summary, format_summary
from terrain_ros.tools.demo import STAGE_NAMES, STAGE_TOPICS, stage_latencies


def _walls():
    # captures 1..3; capture 3 never reached the planner, capture 2 skipped by the mapper
    image = {(1, 0): 10.0, (2, 0): 20.0, (3, 0): 30.0}
    stages = {'/stereo/points': {(1, 0): 10.1, (2, 0): 20.2, (3, 0): 30.1},
              '/map/fine': {(1, 0): 10.4, (3, 0): 30.5},
              '/map/filled': {(1, 0): 10.5, (3, 0): 30.6},
              '/footstep_plan': {(1, 0): 10.8}}
    return image, stages


def test_stage_latencies_follow_each_stamp_from_node_to_node():
    assert STAGE_TOPICS[-1] == '/footstep_plan' and len(STAGE_NAMES) == len(STAGE_TOPICS)
    lat = stage_latencies(*_walls())
    assert list(lat) == list(STAGE_NAMES)
    assert lat['stereo'] == pytest.approx([100.0, 200.0, 100.0])
    assert lat['icp_mapper'] == pytest.approx([300.0, 400.0])     # capture 2 never fused
    assert lat['terrain_fill'] == pytest.approx([100.0, 100.0])
    assert lat['footstep_planner'] == pytest.approx([300.0])


def test_summary_reports_the_per_node_latency_with_the_total():
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    d.latencies_ms = [800.0]
    d.latency_stages_ms = stage_latencies(*_walls())
    s = compute_summary(d)
    assert s['capture_to_plan_ms_median'] == 800.0
    st = s['latency_stages_ms']
    assert st['icp_mapper'] == {'median': 350.0, 'p95': pytest.approx(395.0), 'captures': 2}
    assert st['footstep_planner']['captures'] == 1
    assert 'icp_mapper 350' in format_summary(s)


def test_summary_carries_the_node_counters_and_prints_the_mappers_decisions():
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    d.node_counters = {'icp_mapper': {'mapper_accepted': 290, 'mapper_rejected_correction': 7,
                                      'mapper_rejected_rotation': 1, 'mapper_rejected_rmse': 4,
                                      'mapper_accepted_confirmed': 2, 'odom_jump': 1},
                       'stereo_node': {'bad_image': 3, 'process_cpu_ms': 35250},
                       'sim_bridge': {'process_cpu_ms': 117468}}
    s = compute_summary(d)
    assert s['node_counters']['stereo_node'] == {'bad_image': 3}
    assert s['node_counters']['sim_bridge'] == {}
    # the process CPU comes out of the counters into its own entry [s]
    assert s['node_cpu_s'] == {'sim_bridge': 117.5, 'stereo_node': 35.2}
    s['wall_time_s'] = 235.0
    assert 'node CPU       sim_bridge 50%, stereo_node 15% of a core' in format_summary(s)
    assert ('ICP decisions  290 accepted, refused: 8 by the drift guard, 4 as misfits; 2 '
            'confirmed by repeated captures, 0 after a free fall, 0 model restarts'
            in format_summary(s))
    d.node_counters = {}
    assert 'ICP decisions' not in format_summary(compute_summary(d))


def test_machine_cpu_shares_between_two_proc_stat_readings():
    from terrain_ros.report import cpu_ticks, machine_cpu_pct
    # user nice system idle iowait irq softirq steal guest guest_nice
    a = [100, 50, 10, 800, 20, 0, 5, 15, 0, 0]
    b = [500, 200, 40, 1100, 40, 0, 60, 60, 0, 0]
    # 1000 ticks: 300 idle + 20 iowait + 45 steal -> 63.5% busy, 4.5% stolen
    assert machine_cpu_pct(a, b) == {'busy': 63.5, 'steal': 4.5}
    assert machine_cpu_pct(None, b) == {} and machine_cpu_pct(a, a) == {}
    now = cpu_ticks()
    assert now is None or len(now) >= 8
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    d.machine_cpu_pct = machine_cpu_pct(a, b)
    s = compute_summary(d)
    assert s['machine_cpu_pct'] == {'busy': 63.5, 'steal': 4.5}
    assert 'machine        64% busy, 4.5% stolen by the host' in format_summary(s)


def test_the_monitor_keeps_each_nodes_latest_integer_counters():
    from types import SimpleNamespace as NS
    from terrain_ros.tools.demo import Monitor
    import threading
    m = Monitor.__new__(Monitor)           # the callback alone: no ROS context needed
    m.lock, m.node_counters = threading.Lock(), {}
    kv = [NS(key='mapper_accepted', value='12'), NS(key='note', value='not a number')]
    m._on_diagnostics(NS(status=[NS(name='/icp_mapper', values=kv)]))
    m._on_diagnostics(NS(status=[NS(name='/icp_mapper',
                                    values=[NS(key='mapper_accepted', value='13')])]))
    assert m.node_counters == {'icp_mapper': {'mapper_accepted': 13}}


def _pose(x, y, yaw_deg):
    c, s_ = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:2, :2] = [[c, -s_], [s_, c]]
    T[:2, 3] = x, y
    return T


def test_summary_reports_the_heading_error_a_slip_leaves():
    # The robot pivots 11 deg in place at t = 2 s (a slip); the estimate keeps the old
    # heading and ends 3 mm off in position: the position error alone would hide it.
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    t = np.arange(0.0, 4.0, 0.5)
    d.gt_t = t
    d.gt_T = np.stack([_pose(0.4 + 0.01 * k, 0.0, 0.0 if k < 4 else 11.0)
                       for k in range(len(t))])
    d.dr_t = t
    d.dr_T = np.stack([_pose(0.4 + 0.01 * k + (0.003 if k == len(t) - 1 else 0.0), 0.0, 179.0
                             if k == 0 else 0.0) for k in range(len(t))])
    s = compute_summary(d)
    assert s['final_localisation_error_m'] == pytest.approx(0.003, abs=1e-6)
    assert s['final_heading_error_deg'] == pytest.approx(11.0, abs=1e-6)
    # wrapped: 179 deg against 0 is 179 deg off, not 181
    assert s['max_heading_error_deg'] == pytest.approx(179.0, abs=1e-6)
    assert 'heading 11.0 deg (max 179.0 deg)' in format_summary(s)


def test_summary_reports_where_the_estimate_put_the_feet_at_touchdown():
    # The body stands 0.5 s, moves 5 cm, stands ... with the legs fixed: each stand is a
    # foothold of every leg. The estimate is 2 cm off in y until an ICP correction at t = 4 s
    # fixes it; a heading error of 2 deg then moves the feet by their lever arm.
    from terrain_perception.kinematics import forward, standing_joint_angles
    from terrain_perception.robot_model import load_robot_model
    model = load_robot_model('littledog')
    q = standing_joint_angles(model)
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    t = np.arange(0.0, 8.0, 0.01)
    x = 0.4 + 0.05 * np.clip(np.floor(t) + 2.0 * (t % 1.0) - 1.0, np.floor(t), None)
    d.gt_t, d.gt_T = t, np.stack([_pose(xi, 0.0, 0.0) for xi in x])
    d.joint_t, d.joint_q = t, np.repeat(q[None], len(t), axis=0)
    d.dr_t = t
    d.dr_T = np.stack([_pose(xi, 0.02, 0.0) for xi in x])
    d.corr_t, d.corr_T = np.array([4.0]), _pose(0.0, -0.02, 0.0)[None]
    s = compute_summary(d, model)
    assert s['executed_footholds'] == 4 * 7          # stands 1..7 after the initial one
    # 12 footholds before the correction (2 cm off), 16 after (exact)
    assert s['foothold_belief_error_m_mean'] == pytest.approx(0.02 * 12 / 28, abs=1e-5)
    assert s['foothold_belief_error_m_p95'] == pytest.approx(0.02, abs=1e-5)
    assert 'believed vs true at touchdown 0.0086 m mean' in format_summary(s)
    # After the correction the estimate's heading is 2 deg off (the position exact): each foot
    # is off by its lever arm from the base centre, 2 sin(1 deg) |p_xy|.
    d.dr_T[t >= 4.0] = [_pose(xi, 0.02, 2.0) for xi in x[t >= 4.0]]
    arm = 2.0 * np.sin(np.radians(1.0)) * np.linalg.norm(forward(model, q)[:, :2], axis=1)
    s = compute_summary(d, model)
    assert s['foothold_belief_error_m_mean'] == pytest.approx(
        (0.02 * 12 + 4 * arm.sum()) / 28, abs=1e-5)
    assert s['foothold_belief_error_footholds'] == 28
    # The robot tips over at 7.3 s: footholds from 0.5 s before are not counted (the 7th stand).
    d.gt_T[t >= 7.3] = [_pitched(xi, 90.0) for xi in x[t >= 7.3]]
    s = compute_summary(d, model)
    assert s['falls'] == 1 and s['foothold_belief_error_footholds'] == 24
    d.dr_t = np.zeros(0)
    d.dr_T = np.zeros((0, 4, 4))
    s = compute_summary(d, model)
    assert s['foothold_belief_error_m_mean'] is None
    assert 'no pose estimate' in s['missing']['foothold_belief_error_m_mean']


def test_the_summary_of_a_run_that_crossed_is_written_as_json():
    """Run AB lost its report: a numpy bool in the summary (crossed, computed from the first
    crossing and the first fall) was not JSON-serialisable. Any flag numpy computes must be
    written as a JSON boolean."""
    import json
    from terrain_ros.report import _jsonable
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    t = np.arange(0.0, 20.0, 0.5)
    d.gt_t = t
    d.gt_T = np.stack([_pose(0.4 + 0.1 * k, 0.0, 0.0) for k in range(len(t))])
    d.dr_t, d.dr_T = t, d.gt_T.copy()
    s = compute_summary(d)
    out = json.loads(json.dumps(s, default=_jsonable))
    assert out['crossed'] is True and out['falls'] == 0
    assert json.loads(json.dumps({'flag': np.bool_(False)}, default=_jsonable)) == {'flag': False}


def _pitched(x, tilt_deg):
    """Base at (x, 0, 0.15), pitched forward by ``tilt_deg``."""
    c, s_ = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    T = np.eye(4)
    T[:3, :3] = [[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]]
    T[:3, 3] = x, 0.0, 0.15
    return T


# The last 0.7 s of closed-loop run AB (true base x [m] and tilt [deg], from its bag): the
# robot stood 5 cm short of the 2.15 m finish, toppled, and the fall carried the base past
# the line. Then it lies there (tilt 140 deg).
AB_TAIL = [(155.13, 2.044, 7.8), (155.33, 2.060, 20.8), (155.53, 2.078, 38.3),
           (155.58, 2.088, 45.7), (155.63, 2.101, 55.8), (155.68, 2.117, 69.6),
           (155.73, 2.135, 88.7), (155.78, 2.144, 113.5), (155.83, 2.160, 139.5)]


def _walk(samples):
    from terrain_ros.report import fall_mask
    t = np.array([s[0] for s in samples])
    T = np.stack([_pitched(x, a) for _, x, a in samples])
    return t, T, fall_mask(T, None, np.array([0.24, 0.10, 0.06]))


def _live_end(t, T, fallen, finish_x=2.15):
    from terrain_ros.tools.demo import WalkEnd
    rule = WalkEnd(finish_x, stall_s=60.0)
    for tk, Tk, fk in zip(t, T, fallen):
        reason = rule.update(float(tk), float(Tk[0, 3]), bool(fk))
        if reason:
            return reason, float(tk)
    return None, None


def _summary(t, T):
    """The report's summary of a run whose true poses are ``T`` at times ``t``."""
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    d.gt_t, d.gt_T = t, T
    return compute_summary(d)


def test_a_robot_that_topples_over_the_finish_has_not_crossed():
    """Run AB: the live monitor ended it as 'crossed' because it looked at x before the fall.
    Both the live rule and the report must call it a fall."""
    lying = [(155.83 + 0.05 * k, 2.16, 139.5) for k in range(1, 61)]
    t, T, fallen = _walk(AB_TAIL + lying)
    reason, t_end = _live_end(t, T, fallen)
    assert reason == 'fell' and t_end == pytest.approx(155.63 + 2.0, abs=0.051)
    s = _summary(t, T)
    assert s['crossed'] is False and s['falls'] == 1 and s['time_to_cross_s'] is None


def test_a_robot_that_falls_just_after_the_finish_has_not_crossed():
    """Past the line upright, then tipped over 0.5 s later: the first sample past the finish
    comes before the first fallen one, which the report used to count as a crossing."""
    walk = [(0.1 * k, 2.10 + 0.01 * k, 2.0) for k in range(10)]            # past 2.15 at 0.5 s
    fall = [(1.0 + 0.1 * k, 2.20, 60.0 + 10.0 * k) for k in range(30)]
    t, T, fallen = _walk(walk + fall)
    assert _live_end(t, T, fallen)[0] == 'fell'
    assert _summary(t, T)['crossed'] is False


def test_a_robot_upright_past_the_finish_crossed_when_it_reached_the_line():
    walk = [(0.1 * k, 2.10 + 0.01 * k, 2.0) for k in range(30)]            # 2.15 at t = 0.5 s
    t, T, fallen = _walk(walk)
    reason, t_end = _live_end(t, T, fallen)
    assert reason == 'crossed' and t_end == pytest.approx(1.5)
    s = _summary(t, T)
    assert s['crossed'] is True and s['time_to_cross_s'] == pytest.approx(0.5)


def test_the_live_rule_ends_a_walk_that_makes_no_progress():
    stuck = [(0.5 * k, 1.20 + (0.004 if k % 2 else 0.0), 3.0) for k in range(200)]
    reason, t_end = _live_end(*_walk(stuck))
    assert reason.startswith('stalled') and t_end == pytest.approx(60.0)


def test_a_fall_is_explained_from_the_true_poses_joints_and_terrain():
    # Feet fixed on flat ground except LH, which stands still over a 2 cm pit (hanging); the
    # body leans towards RF. At t = 4 s RF lifts: the model COM is left over the LF-RH
    # diagonal only, and the robot pitches over from t = 4.5 s (past 20 deg at 4.57 s). The
    # pose estimate is 1 cm off in x. The analysis must name all of it.
    from terrain_perception.grid import GridMap
    from terrain_perception.kinematics import feet_in_base, inverse
    from terrain_perception.robot_model import load_robot_model
    model = load_robot_model('littledog')
    base0 = _pose(1.2, 0.0, 0.0)
    base0[2, 3] = model.standing_height_m
    feet = model.nominal_feet @ base0[:3, :3].T + base0[:3, 3]
    feet[:, 2] = 0.0
    elev = np.zeros((200, 100), np.float32)           # 5 mm cells from (0.7, -0.25)
    terrain = GridMap.from_layers(0.005, (0.7, -0.25), {'elevation': elev})
    i, j = terrain.world_to_index(feet[2, :2])
    elev[i - 4:i + 5, j - 4:j + 5] = -0.02                # the pit under LH
    terrain['elevation'] = elev
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    d.true_terrain = terrain
    t = np.round(np.arange(0.0, 6.0, 0.01), 2)
    T, Q = [], []
    for tk in t:
        B = base0.copy()
        B[:2, 3] += [0.015, -0.015]                       # the body leans towards RF
        f = feet.copy()
        f[:, 2] += model.foot_radius_m                    # sphere centres
        if tk >= 4.0:                                     # RF lifts 25 mm, comes down
            f[1, 2] += max(min(tk - 4.0, 0.25) * 0.1 - max(tk - 4.25, 0.0) * 0.05, 0.0)
        q = inverse(model, feet_in_base(B, f))
        if tk >= 4.5:
            B = B @ _pitched(0.0, min((tk - 4.5) * 300.0, 90.0))
            B[:3, 3] = base0[:3, 3]
        T.append(B)
        Q.append(q)
    d.gt_t, d.gt_T = t, np.stack(T)
    d.joint_t, d.joint_q = t, np.stack(Q)
    d.joint_tau = np.zeros_like(d.joint_q)
    # LH's motors hold 80 N of ground force at t = 4.3 s (the body falling onto it), RF's
    # 60 N at 4.4 s as it comes down at 5 cm/s (a landing)
    from terrain_perception.kinematics import jacobian
    for tk, leg, force in ((4.3, 2, 80.0), (4.4, 1, 60.0)):
        k = int(np.flatnonzero(t == tk)[0])
        d.joint_tau[k, leg] = -jacobian(model, d.joint_q[k])[leg].T @ np.array([0, 0, force])
    d.dr_t, d.dr_T = t, d.gt_T.copy()
    d.dr_T[:, 0, 3] += 0.01
    s = compute_summary(d, model)
    assert s['falls'] == 1 and len(s['fall_analysis']) == 1
    fa = s['fall_analysis'][0]
    assert fa['t_s'] == pytest.approx(4.57, abs=0.011)           # 300 deg/s past 20 deg
    assert fa['swinging'] == 'RF'
    # RF is off the ground once 5 mm up (CONTACT_GAP_M): 0.05 s into its lift
    assert fa['com_left_support_t_s'] == pytest.approx(4.05, abs=0.011)
    assert fa['support'] == 'LF+RF+RH' and fa['support_after'] == 'LF+RH'
    assert fa['margin_mm'] > 0.0
    assert set(fa['hanging']) == {'LH'}
    assert fa['hanging']['LH']['gap_mm'] == pytest.approx(20.0, abs=1.0)
    assert fa['hanging']['LH']['estimated_load_n'] == pytest.approx(0.0, abs=1e-6)   # before
    assert all(v[0] == pytest.approx(10.0, abs=0.5) and abs(v[1]) < 0.5
               for v in fa['belief_offset_mm'].values())
    assert fa['localisation_error_mm'] == pytest.approx(10.0, abs=0.5)
    assert fa['belief_t_s'] == pytest.approx(4.05, abs=0.011)
    assert fa['hard_contacts'] == {
        'LH': {'n': pytest.approx(80.0, abs=0.1), 't_s': 4.3, 'descent_mps': 0.0},
        'RF': {'n': pytest.approx(60.0, abs=0.1), 't_s': 4.4,
               'descent_mps': pytest.approx(0.05, abs=0.002)}}
    assert 'fall           fell at t = 4.57 s' in format_summary(s)
    # An upright walk has nothing to explain.
    d.gt_T, d.joint_q = d.gt_T[:350], d.joint_q[:350]
    d.gt_t = d.joint_t = d.dr_t = t[:350]
    d.joint_tau, d.dr_T = d.joint_tau[:350], d.dr_T[:350]
    assert compute_summary(d, model)['fall_analysis'] == []


def _blocks_terrain():
    """True terrain for the registration tests: 3 cm blocks in a 4 cm checkerboard, 1 mm
    cells."""
    from terrain_perception.grid import GridMap
    truth = GridMap.empty(0.001, (0.3, -0.3), (600, 600))
    xs, ys = truth.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    truth['elevation'] = (0.03 * ((np.floor(X / 0.04) + np.floor(Y / 0.04)) % 2)).astype(
        np.float32)
    return truth


def test_the_map_and_footholds_are_read_where_the_estimate_error_puts_them():
    # The estimate is 12 mm behind the truth in x and 3 deg off in yaw. A map built through
    # that estimate shows each rock where the estimate puts it: registered by the estimate
    # error it matches the terrain exactly, read at the same coordinates it does not.
    from terrain_perception.grid import GridMap
    from terrain_ros.report import (estimate_offsets, landing_positions, map_rmse,
                                    sample_cell_mean)
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    d.gt_t = d.dr_t = np.array([0.0, 1.0, 2.0])
    d.gt_T = np.stack([_pose(0.5 + 0.01 * k, 0.02, 3.0) for k in range(3)])
    d.dr_T = np.stack([_pose(0.488 + 0.01 * k, 0.02, 0.0) for k in range(3)])
    C = estimate_offsets(d, np.array([2.0]))[0]
    np.testing.assert_allclose(C @ d.dr_T[2], d.gt_T[2], atol=1e-12)
    p = landing_positions(d, np.array([2.0, 2.0]), np.array([[0.508, 0.02, 0.0],
                                                              [0.7, 0.1, 0.01]]))
    np.testing.assert_allclose(p[0, :2], d.gt_T[2][:2, 3], atol=1e-12)  # under the base
    q = np.linalg.inv(d.dr_T[2]) @ [0.7, 0.1, 0.01, 1.0]       # base frame, estimated
    np.testing.assert_allclose(p[1], (d.gt_T[2] @ q)[:3], atol=1e-12)
    # True terrain: 4 cm blocks on a 1 mm grid; the map (1 cm) shows it through C^-1.
    truth = _blocks_terrain()
    grid = GridMap.empty(0.01, (0.4, -0.2), (40, 40))
    grid['elevation'] = sample_cell_mean(truth, grid, T_world_grid=C)
    mask = np.ones(grid.shape, bool)
    registered, n = map_rmse(grid, truth, mask, C)
    same_xy, _ = map_rmse(grid, truth, mask)
    assert n == grid.shape[0] * grid.shape[1]
    assert registered < 1e-6 < 0.005 < same_xy


def test_each_map_cell_is_registered_by_the_estimate_error_of_when_it_was_seen():
    # The estimate drifts: 10 mm behind and level at t = 1 s, then 25 mm behind and pitched
    # 0.5 deg at t = 2 s. Cells x < 0.6 m were last seen at 1 s, the rest at 2 s, each through
    # the estimate of its time. Per-cell registration matches the terrain exactly; the last
    # pose's error alone misplaces the early cells (and tilts them by the late pitch).
    from terrain_perception.grid import GridMap
    from terrain_ros.report import cell_offsets, estimate_offsets, map_rmse, sample_cell_mean
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    d.gt_t = d.dr_t = np.array([0.0, 1.0, 2.0])
    d.gt_T = np.stack([_pose(0.5 + 0.05 * k, 0.0, 0.0) for k in range(3)])
    est = [_pose(0.5, 0.0, 0.0), _pose(0.54, 0.0, 0.0), _pose(0.575, 0.0, 0.0)]
    p = np.radians(0.5)
    est[2][:3, :3] = [[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]]
    d.dr_T = np.stack(est)
    truth = _blocks_terrain()
    grid = GridMap.empty(0.01, (0.4, -0.2), (40, 40))
    gx, _ = grid.cell_centers()
    grid['last_seen'] = np.where(gx[:, None] < 0.6, 1.0, 2.0) + np.zeros(grid.shape, np.float32)
    mask = np.ones(grid.shape, bool)
    C_cells = cell_offsets(d, grid, mask)
    for t in (1.0, 2.0):                         # what the map shows: the terrain through C^-1
        C = estimate_offsets(d, np.array([t]))[0]
        sel = grid['last_seen'] == t
        Xg, Yg = np.meshgrid(*grid.cell_centers(), indexing='ij')
        h_world = sample_cell_mean(truth, grid, T_world_grid=C)
        # the map height whose world height (C applied) is the truth there
        r = C[2]
        grid['elevation'][sel] = ((h_world - r[0] * Xg - r[1] * Yg - r[3]) / r[2])[sel]
        np.testing.assert_allclose(C_cells[sel], np.broadcast_to(C, (int(sel.sum()), 4, 4)))
    per_cell, n = map_rmse(grid, truth, mask, C_cells)
    last_only, _ = map_rmse(grid, truth, mask, estimate_offsets(d, np.array([2.0]))[0])
    assert n == grid.shape[0] * grid.shape[1]
    assert per_cell < 1e-6 and last_only > 0.003, (per_cell, last_only)
    np.testing.assert_array_equal(cell_offsets(d, grid, ~mask), np.broadcast_to(
        np.eye(4), grid.shape + (4, 4)))
    with pytest.raises(ValueError, match='last_seen'):
        cell_offsets(d, GridMap.empty(0.01, (0.4, -0.2), (4, 4)), mask[:4, :4])


def test_counters_log_at_several_severities_from_one_node(ros_context):
    """A counter logged as an error and others as warnings (the fill node's bad_library, then
    a bad grid) in one process: rclpy fixes each logging call site's severity, so one shared
    call site raised 'Logger severity cannot be changed between calls' and killed the node."""
    from rclpy.node import Node
    from terrain_ros.node import Counters
    node = Node('counters_severity_test', context=ros_context)
    try:
        c = Counters(node, publish_topic=None)
        for _ in range(2):
            c.bump('bad_library', 'no library', node.get_logger().error)
            c.bump('bad_grid', 'a NaN cell')
            c.bump('served', 'fine', node.get_logger().info)
        assert c['bad_library'] == c['bad_grid'] == c['served'] == 2
    finally:
        node.destroy_node()


def _drift_run():
    """A walk along y (heading +90 deg) at 1 cm/s for 20 s; dead reckoning overstates every
    step by 4 %; one ICP correction at t = 15 s takes 3 mm off the estimate along the heading."""
    d = RunData(CourseInfo('rocks-6cm', 0, 0.4, 1.0, 1.75, 2.15), 'littledog')
    t = np.arange(0.0, 20.0 + 1e-9, 0.1)
    d.gt_t = t
    d.gt_T = np.stack([_pose(0.0, 0.01 * s, 90.0) for s in t])
    d.dr_t = t
    d.dr_T = np.stack([_pose(0.0, 0.0104 * s, 90.0) for s in t])
    shift = np.eye(4)
    shift[1, 3] = -0.003
    d.corr_t, d.corr_T = np.array([15.0]), shift[None]
    return d


def test_drift_windows_split_the_estimate_error_into_odometry_and_icp():
    from terrain_ros.report import drift_windows
    rows = drift_windows(_drift_run(), 10.0)
    assert [(r['t0'], r['t1']) for r in rows] == [(0.0, 10.0), (10.0, 20.0)]
    a, b = rows
    # the heading is +y: "along" is y, "across" is -x
    assert a['err_along'] == pytest.approx(0.004, abs=1e-9)
    assert a['dr_along'] == pytest.approx(0.004, abs=1e-9)
    assert a['icp_along'] == pytest.approx(0.0, abs=1e-9)
    assert a['dr_scale'] == pytest.approx(1.04, abs=1e-9)
    assert a['corrections'] == 0 and a['x'] == pytest.approx(0.0)
    assert b['err_along'] == pytest.approx(0.008 - 0.003, abs=1e-9)
    assert b['dr_along'] == pytest.approx(0.004, abs=1e-9)
    assert b['icp_along'] == pytest.approx(-0.003, abs=1e-9)
    assert b['corrections'] == 1
    for r in rows:
        assert r['err_across'] == pytest.approx(0.0, abs=1e-9)
        assert r['yaw_err_deg'] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match='window_s'):
        drift_windows(_drift_run(), 0.0)
    assert drift_windows(RunData(CourseInfo('x', 0, 0, 0, 0, 0), 'littledog'), 10.0) == []


def test_the_drift_tool_reads_the_windows_from_a_bag(tmp_path):
    """The same run written as a bag (ground truth, odometry, one correction received at
    15 s on the recorded /clock): the tool prints and writes the same windows."""
    import json
    import subprocess
    import sys

    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    from scipy.spatial.transform import Rotation
    store = get_typestore(Stores.ROS2_JAZZY)
    T = store.types
    d = _drift_run()
    wall0 = 1_000_000_000_000

    def stamp(s):
        return T['builtin_interfaces/msg/Time'](sec=int(s), nanosec=int(round((s % 1) * 1e9)))

    def pose(M):
        q = Rotation.from_matrix(M[:3, :3]).as_quat()
        return T['geometry_msgs/msg/Pose'](
            position=T['geometry_msgs/msg/Point'](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
            orientation=T['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3]))

    def odom(s, M, frame):
        cov = np.zeros(36)
        return T['nav_msgs/msg/Odometry'](
            header=T['std_msgs/msg/Header'](stamp=stamp(s), frame_id=frame),
            child_frame_id='base_link',
            pose=T['geometry_msgs/msg/PoseWithCovariance'](pose=pose(M), covariance=cov),
            twist=T['geometry_msgs/msg/TwistWithCovariance'](
                twist=T['geometry_msgs/msg/Twist'](linear=T['geometry_msgs/msg/Vector3'](
                    x=0.0, y=0.0, z=0.0), angular=T['geometry_msgs/msg/Vector3'](
                    x=0.0, y=0.0, z=0.0)), covariance=cov))
    bag = tmp_path / 'bag'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_gt = w.add_connection('/ground_truth/odom', 'nav_msgs/msg/Odometry', typestore=store)
        c_dr = w.add_connection('/odom/dead_reckoning', 'nav_msgs/msg/Odometry',
                                typestore=store)
        c_clk = w.add_connection('/clock', 'rosgraph_msgs/msg/Clock', typestore=store)
        c_cor = w.add_connection('/icp/correction', 'geometry_msgs/msg/PoseStamped',
                                 typestore=store)
        for k, s in enumerate(d.gt_t):
            wall = wall0 + int(s * 1e9) * 3          # the recorder's clock: 3x slower
            w.write(c_clk, wall, store.serialize_cdr(
                T['rosgraph_msgs/msg/Clock'](clock=stamp(s)), 'rosgraph_msgs/msg/Clock'))
            w.write(c_gt, wall + 1, store.serialize_cdr(odom(s, d.gt_T[k], 'map'),
                                                        'nav_msgs/msg/Odometry'))
            w.write(c_dr, wall + 2, store.serialize_cdr(odom(s, d.dr_T[k], 'odom'),
                                                        'nav_msgs/msg/Odometry'))
            if abs(s - 15.0) < 1e-9:
                # stamped with a capture of the first window; received (logged) in the second
                w.write(c_cor, wall + 3, store.serialize_cdr(T['geometry_msgs/msg/PoseStamped'](
                    header=T['std_msgs/msg/Header'](stamp=stamp(9.0), frame_id='map'),
                    pose=pose(d.corr_T[0])), 'geometry_msgs/msg/PoseStamped'))
    out = tmp_path / 'drift.json'
    res = subprocess.run([sys.executable, '-m', 'terrain_ros.tools.drift', str(bag), '--json',
                          str(out)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    rows = json.loads(out.read_text())
    assert len(rows) == 2
    assert rows[1]['icp_along'] == pytest.approx(-0.003, abs=1e-6)
    assert rows[1]['err_along'] == pytest.approx(0.005, abs=1e-6)
    assert rows[0]['dr_scale'] == pytest.approx(1.04, abs=1e-6)
    assert '10.0-  20.0' in res.stdout
    res = subprocess.run([sys.executable, '-m', 'terrain_ros.tools.drift', str(tmp_path / 'no')],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 1 and 'does not exist' in res.stderr
