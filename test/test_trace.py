"""The walk trace (terrain_perception.sim.trace): what it records is the simulator's truth,
and its fall report names the cause of a fall planted in the scene."""

import numpy as np
import pytest

from terrain_perception import gait as G
from terrain_perception import kinematics as K
from terrain_perception.controller import WalkingConfig
from terrain_perception.robot_model import load_robot_model
from terrain_perception.sim.trace import (PHASES, WalkTrace, fall_report, hanging_runs,
                                          landing_summary, landings, load_trace)
from terrain_perception.sim.walk import WalkRunner, link_masses, make_flat_world, spawn_standing

DT = 1.0 / 500.0
LF = 0


def _traced_walk(lf_in_the_air_m: float = 0.0, sensing: bool = True):
    """LittleDog crawls 0.3 m on flat ground, traced; the sixth footstep (LF) is planned
    ``lf_in_the_air_m`` above the ground. Returns ``(trace, result, total mass, legs,
    robot model)``."""
    m = load_robot_model('littledog')
    client, plane = make_flat_world(DT)
    robot = spawn_standing(client, m, dt_s=DT)
    legs, pos = G.straight_footsteps(m, robot.base_pose(), 0.3)
    assert legs[5] == LF
    pos[5, 2] += lf_in_the_air_m
    cfg = WalkingConfig(plan_timeout_s=1e6) if sensing else \
        WalkingConfig(plan_timeout_s=1e6, contact_force_n=0.0, attitude_gain=0.0)
    tr = WalkTrace()
    runner = WalkRunner(client, robot, cfg, DT, ground_id=plane, trace=tr)
    runner.run(legs, pos, 'walk', max_time_s=40.0)
    res = runner.result()
    mass = float(link_masses(client, robot).sum())
    client.disconnect()
    return tr, res, mass, legs, m


@pytest.mark.timeout(120)
def test_the_trace_records_the_truth_of_a_flat_walk(tmp_path):
    tr, res, mass, legs, m = _traced_walk()
    assert not res.fell and res.steps_done == len(legs)
    a = tr.arrays()
    n = len(tr)
    assert n > 100 and all(a[k].shape[0] == n for k in a)
    np.testing.assert_allclose(np.diff(a['t']), 5 * DT, rtol=1e-6)
    # With four feet down (body shifts) the feet carry the robot's weight.
    shift = a['phase'] == PHASES.index('shift')
    assert shift.sum() > 20
    np.testing.assert_allclose(np.median(a['force'][shift].sum(axis=1)), mass * 9.81, rtol=0.1)
    # A swinging foot more than 1 cm above the ground carries nothing.
    bottom = a['feet'][..., 2] - m.foot_radius_m
    airborne = a['swing_legs'] & (bottom > 0.01)
    assert airborne.sum() > 50
    assert np.all(a['force'][airborne] == 0.0)
    # Nothing but the feet touches flat ground.
    assert a['other_force'].shape == (n, 5) and np.all(a['other_force'] == 0.0)
    # The measured joint angles and motor torques: the feet's forces computed from them
    # (kinematics.foot_forces, what the controller does at its own ticks) are the true ones.
    assert a['q'].shape == (n, 12) and a['tau'].shape == (n, 12)
    est = K.foot_forces(m, a['q'].reshape(n, 4, 3), a['tau'].reshape(n, 4, 3))[..., 2]
    assert np.median(np.abs(est - a['force'])[shift]) < 1.5
    # On flat ground the controller's stance feet are where the feet really stand.
    stance = ~a['swing_legs']
    off = np.linalg.norm(a['feet'][..., :2] - a['believed_feet'][..., :2], axis=2)[stance]
    assert np.percentile(off, 95) < 0.015
    assert np.percentile(np.abs(bottom - a['believed_feet'][..., 2])[stance], 95) < 0.005
    # Every swing lands once, each leg on its own swings, and is loaded when it does.
    ld = landings(a)
    assert sorted(ld['leg'].tolist()) == sorted(int(k) for k in legs)
    assert np.all(ld['peak_n'] > 1.0) and np.all(ld['swing_fraction'] > 0.4)
    assert fall_report(a, tilt_deg=10.0) is None
    saved = load_trace(tr.save(tmp_path / 'walk.npz', seed=3, status='ok'))
    for k, v in a.items():
        np.testing.assert_array_equal(saved[k], v)
    assert int(saved['meta_seed']) == 3 and str(saved['meta_status']) == 'ok'


@pytest.mark.timeout(120)
def test_the_fall_report_names_a_foot_that_ended_its_swing_in_the_air():
    # Blind (no touchdown sensing), LF's foothold planned 2 cm above the ground: LF ends its
    # swing in the air, the next shifts move the COM off the feet that carry weight and the
    # robot tips. The report must name LF as the hanging stance foot, from the end of its
    # swing on.
    tr, res, _, legs, _ = _traced_walk(0.02, sensing=False)
    a = tr.arrays()
    assert res.fell
    text = fall_report(a, tilt_deg=10.0)
    assert text is not None and 'LF' in text.split('longest run:')[1].split('\n')[0]
    assert 'legs (hip, thigh, shank) and body on the terrain' in text
    lf_swing = np.flatnonzero(a['swing_legs'][:, LF] & (a['steps_done'] == 5))
    end_of_swing = a['t'][lf_swing[-1]]
    fell = a['t'][np.flatnonzero(np.degrees(np.arccos(
        np.cos(a['base_rpy'][:, 0]) * np.cos(a['base_rpy'][:, 1]))) > 10.0)[0]]
    hang = hanging_runs(a, np.flatnonzero(a['t'] <= fell))
    assert LF in hang
    duration, start, _ = hang[LF]
    assert duration >= 0.3 and 0.0 <= start - end_of_swing <= 0.05
    # The counterfactual: with touchdown sensing (the defaults) the same walk does not tip.
    tr2, res2, _, _, _ = _traced_walk(0.02, sensing=True)
    assert not res2.fell and fall_report(tr2.arrays(), tilt_deg=10.0) is None


def test_bad_trace_input_is_named():
    with pytest.raises(ValueError, match='every'):
        WalkTrace(every=0)
    with pytest.raises(ValueError, match='empty'):
        fall_report(WalkTrace().arrays())


@pytest.mark.timeout(180)
def test_a_localised_rocks_walk_lands_the_feet_where_planned(tmp_path):
    # The ground-truth rocks walk without localisation plans on the true terrain from the
    # controller's dead reckoning, which drifts as the feet slip; localised, it is re-anchored
    # before each plan with the correction a perfect ICP would give (as the closed loop does
    # with its ICP), and the feet land where the plan put them. Measured (0.5 m of rocks-6cm,
    # seed 13): mean landing error 2.7 mm unlocalised, 1.1 mm localised; p95 5.1, 2.8 mm
    # (unlocalised 4.8 and 9.4 mm without the planner's heading cost of the twenty-eighth
    # session, which keeps the stance from turning). The walks use the foothold filter they
    # were measured with (the heights over 2 foot radii): with the foot-surface filter, the
    # default since the rocks12 branch, they step on other footholds and land 2.3 mm
    # unlocalised, 1.4 mm localised (0.59x); this test is about the localisation.
    from terrain_perception.bench.sim import _rocks_walk
    from terrain_perception.terrain import make_course
    course = make_course('rocks-6cm', 13, 0.005)
    old_filter = {'safety_surface': 'heights', 'safety_window_m': 0.0}
    # The natural drift of this short walk is chaotic: on an AMD EPYC (session 38) the
    # unlocalised walk drifted as little as the localised one (stance p90 4.1 against 4.0 mm).
    # The unlocalised walk gets 2 mm more of dead-reckoning error per plan, as slips the
    # contacts do not show, so the counterfactual does not rest on that drift (there: landing
    # 5.9 mm off in the mean, stance p90 10.0 mm; localised 1.5 and 4.0 mm).
    drift, fixed = (_rocks_walk(course, 0.8, 1.3, 13, localise=loc, planner_kw=old_filter,
                                trace_path=tmp_path / f'{loc}.npz',
                                odom_error_m_per_plan=0.0 if loc else 0.002)
                    for loc in (False, True))
    for r in (drift, fixed):
        assert not r['fell'] and r['reached'] and r['steps'] >= 20, r['status']
    assert fixed['foot_err_mean_m'] < 0.5 * drift['foot_err_mean_m']
    assert fixed['foot_err_p95_m'] < 0.005
    # The trace puts the controller's belief in the map (its T_map_odom), so localised its
    # stance feet are where the true ones are; unlocalised the drift shows (measured: p90
    # of the loaded stance feet's x-y offset 3.1 mm localised, 4.7 mm unlocalised; 9.0 mm
    # without the heading cost).
    off = {}
    for loc in (False, True):
        a = load_trace(tmp_path / f'{loc}.npz')
        stance = ~a['swing_legs'] & (a['force'] > 1.0)
        off[loc] = np.linalg.norm(a['feet'][..., :2] - a['believed_feet'][..., :2],
                                  axis=-1)[stance]
    p90 = {loc: float(np.percentile(o, 90)) for loc, o in off.items()}
    assert p90[True] < 0.005 and p90[False] > 1.3 * p90[True], p90


@pytest.mark.timeout(180)
def test_frog_walks_in_among_the_stones_on_ground_truth_footsteps():
    # terrain-bench sim --rocks-course stones-15cm: the closed-loop benchmark's FROG-I course
    # (stones from x = 1.5 m), walked on footsteps planned on the true terrain from 0.3 m before
    # the stones to 0.5 m into them.
    from terrain_perception.bench import runner
    from terrain_perception.bench.sim import _rocks_walk
    from terrain_perception.terrain import make_course
    course = make_course('stones-15cm', 0, 0.005)
    xs, ys = course.cell_centers()
    near = course['elevation'][(xs > 1.5) & (xs < 2.2)][:, np.abs(ys) < 0.2]
    assert near.max() > 0.08                         # stones to walk among, not a flat strip
    r = _rocks_walk(course, 1.2, 2.0, 0, robot_name='frog')
    assert (r['robot'], r['course']) == ('frog', 'stones-15cm')
    assert r['reached'] and not r['fell'] and r['steps'] >= 12, r['status']
    assert r['foot_err_p95_m'] < 0.02
    # the full sim run walks rocks-6cm only: another course is refused, by name
    assert runner.main(['sim', '--rocks-course', 'stones-15cm', '--rocks-seeds', '1']) == 2


def _one_swing_trace(descent_m_s: float, peak_n: float) -> dict:
    """A 1 s trace at 10 ms rows: LF swings over rows 20-59 and lowers at ``descent_m_s``
    until it touches the ground between rows 49 and 50, where its force jumps to ``peak_n``
    and then settles at 7 N; the other feet stand."""
    n = 100
    t = np.arange(n) * 0.01
    feet = np.zeros((n, 4, 3))
    z = np.zeros(n)
    z[20:50] = 0.04
    z[40:50] = descent_m_s * 0.01 * np.arange(10, 0, -1)      # row 49: one row above ground
    feet[:, LF, 2] = z
    force = np.full((n, 4), 9.0)
    force[20:50, LF] = 0.0
    force[50, LF] = peak_n
    force[51:, LF] = 7.0
    swing = np.zeros((n, 4), bool)
    swing[20:60, LF] = True
    return {'t': t, 'feet': feet, 'force': force, 'swing_legs': swing}


def test_landings_measure_the_touchdown_speed_place_in_the_swing_and_force():
    ld = landings(_one_swing_trace(0.5, 60.0))
    assert ld['leg'].tolist() == [LF] and ld['t'][0] == pytest.approx(0.50)
    assert ld['descent_m_s'][0] == pytest.approx(0.5)
    assert ld['swing_fraction'][0] == pytest.approx(30 / 40)
    assert ld['peak_n'][0] == pytest.approx(60.0)
    soft = _one_swing_trace(0.05, 12.0)
    s = landing_summary([_one_swing_trace(0.5, 60.0), soft], weight_n=27.0)
    assert s['count'] == 2 and s['share_over_weight'] == pytest.approx(0.5)
    assert s['descent_m_s_median'] == pytest.approx(0.275)
    # a swing that never meets the ground is no touchdown
    soft['force'][:, LF] = 0.0
    assert landings(soft)['leg'].size == 0 and landing_summary([soft], 27.0) == {'count': 0}


def test_the_fall_report_names_the_body_resting_on_the_terrain():
    """The walk runner's other fall, the body touching the terrain with the base still level:
    reported from the row the body force shows, with the legs' links that touched before; a
    trace whose bench meta says it fell without a row showing it (the runner checks every
    physics step, the trace samples fewer) is reported at its last row."""
    tr = _one_swing_trace(0.5, 20.0)
    n = len(tr['t'])
    tr['feet'][:, :, :2] = [[0.1, 0.06], [0.1, -0.06], [-0.1, 0.06], [-0.1, -0.06]]
    tr.update(base_rpy=np.zeros((n, 3)), base_xyz=np.zeros((n, 3)), com=np.zeros((n, 3)),
              phase=np.full(n, PHASES.index('shift')), steps_done=np.zeros(n, int),
              force_estimate=tr['force'].copy(), believed_feet=tr['feet'].copy(),
              other_force=np.zeros((n, 5)))
    assert fall_report(tr) is None
    tr['other_force'][60:, 3] = 5.0
    tr['other_force'][70:, 4] = 12.0
    text = fall_report(tr)
    assert text.startswith('fell at t = 0.70 s') and 'the body on the terrain with 12.0 N' in text
    assert 'RH leg 15 % of the time (peak 5 N), body 1 % of the time (peak 12 N)' in text
    tr['other_force'][:] = 0.0
    tr['meta_fell'] = np.asarray(True)
    text = fall_report(tr)
    assert text.startswith('fell at t = 0.99 s') and 'just after this row' in text


def test_the_fall_report_dates_a_fall_from_the_tilt_it_ended_in():
    """A walk that tilts beyond the report's 20 deg on steep rocks, comes back and falls
    later (the runner's fall is 30 deg) is reported from the start of its last excursion,
    or from its last row if it fell after it without one, with the earlier one named;
    without the bench's fell flag, from the first."""
    tr = _one_swing_trace(0.5, 20.0)
    n = len(tr['t'])
    tr['feet'][:, :, :2] = [[0.1, 0.06], [0.1, -0.06], [-0.1, 0.06], [-0.1, -0.06]]
    roll = np.zeros(n)
    roll[10:30] = np.radians(22.0)           # 0.20 s beyond 20 deg, then back
    roll[80:] = np.radians(25.0)             # the tilt it fell in
    tr.update(base_rpy=np.stack([roll, np.zeros(n), np.zeros(n)], axis=1),
              base_xyz=np.zeros((n, 3)), com=np.zeros((n, 3)),
              phase=np.full(n, PHASES.index('shift')), steps_done=np.zeros(n, int),
              force_estimate=tr['force'].copy(), believed_feet=tr['feet'].copy(),
              other_force=np.zeros((n, 5)))
    assert fall_report(tr).startswith('fell at t = 0.10 s')
    tr['meta_fell'] = np.asarray(True)
    text = fall_report(tr)
    assert text.startswith('fell at t = 0.80 s')
    assert 'beyond 20 deg before, first at t = 0.10 s, 0.2 s in all' in text
    # fallen after the last row (the runner's body test) with the tilt back under 20 deg
    tr['base_rpy'][80:, 0] = 0.0
    text = fall_report(tr)
    assert text.startswith('fell at t = 0.99 s') and 'just after this row' in text
    assert 'first at t = 0.10 s, 0.2 s in all' in text


@pytest.mark.timeout(240)
def test_rocks_walks_in_worker_processes_end_as_in_one(tmp_path):
    """terrain-bench sim --workers: the same walks, traces and fall reports as one process
    (every walk has its own simulator), rows and seeds in order."""
    from terrain_perception.bench.sim import _rocks_seeds
    kw = dict(course_class='rocks-6cm', baseline=False, control_rate_hz=50.0,
              variant={'planner': {}, 'controller': {'touchdown_depth_m': 0.0}})
    one = _rocks_seeds(2, 0.8, 1.05, 13, trace_dir=str(tmp_path / 'one'), **kw)
    two = _rocks_seeds(2, 0.8, 1.05, 13, trace_dir=str(tmp_path / 'two'), workers=2, **kw)
    keys = ('seed', 'advanced_m', 'steps', 'fell', 'status', 'sim_s', 'foot_err_mean_m')
    for row in ('default', 'variant'):
        a, b = one['rocks6_seed_rows'][row], two['rocks6_seed_rows'][row]
        assert [r['seed'] for r in b] == [13, 14]
        assert [tuple(r[k] for k in keys) for r in a] == [tuple(r[k] for k in keys) for r in b]
        assert all(r['steps'] >= 4 for r in b)
        for r, s in zip(a, b):
            np.testing.assert_array_equal(load_trace(r['trace'])['feet'],
                                          load_trace(s['trace'])['feet'])
    assert one['rocks6_seeds'] == two['rocks6_seeds']
