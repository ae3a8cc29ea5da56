"""docs/BENCHMARKS.md composition: a partial benchmark run replaces its own sections and keeps
the others (``_report --keep``)."""

from __future__ import annotations

import json

import pytest

from terrain_perception.bench import _report


def test_partial_run_replaces_its_sections_and_keeps_the_others(tmp_path, capsys):
    old = ('# Benchmarks\n\nintro\n\n## stereo\n\n```\n$ terrain-bench stereo\nold stereo\n```\n\n'
           '## plan\n\n```\n$ terrain-bench plan\nold plan\n```\n\n| key | value |\n|---|---|\n'
           '| `ratio` | 0.3 |\n\n## sim-rocks\n\n```\n$ terrain-bench sim --rocks-only\nrocks\n```\n')
    doc = tmp_path / 'BENCHMARKS.md'
    doc.write_text(old)
    runs = tmp_path / 'bench'
    runs.mkdir()
    (runs / 'plan.txt').write_text('new plan table\n')
    (runs / 'plan.json').write_text(json.dumps({'ratio': 0.25, 'rows': [1, 2]}))
    (runs / 'plan.cmd').write_text('terrain-bench plan --json runs/bench/plan.json\n')
    assert _report.main(str(runs), keep=doc) == 0
    new = capsys.readouterr().out
    got = _report.sections(new)
    assert list(got) == ['stereo', 'plan', 'sim-rocks']          # ORDER first, then the rest
    assert got['stereo'] == _report.sections(old)['stereo']
    assert got['sim-rocks'] == _report.sections(old)['sim-rocks']
    assert 'new plan table' in got['plan'] and 'old plan' not in got['plan']
    assert '| `ratio` | 0.25 |' in got['plan'] and 'rows' not in got['plan']
    # without --keep only the folder's suites are written
    _report.main(str(runs))
    assert list(_report.sections(capsys.readouterr().out)) == ['plan']


def test_sim_rocks_variant_is_parsed_and_bad_ones_refused_by_name(capsys):
    from terrain_perception.bench import runner
    from terrain_perception.bench.sim import parse_rocks_variant
    assert parse_rocks_variant('') is None
    v = parse_rocks_variant('{"planner": {"stride_centre": "rule"}}')
    assert v == {'planner': {'stride_centre': 'rule'}, 'controller': {}, 'sim': {},
                 'course': {}}
    assert parse_rocks_variant('{"control_rate_hz": 50}') == {
        'planner': {}, 'controller': {}, 'sim': {}, 'course': {}, 'control_rate_hz': 50.0}
    assert parse_rocks_variant('{"sim": {"friction": 2}}')['sim'] == {'friction': 2}
    assert parse_rocks_variant('{"course": {"max_height_m": 0.09}}')['course'] == {
        'max_height_m': 0.09}
    for text, words in (('{"planner": ', 'not JSON'),
                        ('{"walker": {}}', 'must be an object'),
                        ('{"control_rate_hz": -5}', 'positive number'),
                        ('{"controller": {"no_such_gain": 1}}', 'no_such_gain'),
                        ('{"sim": {"gravity": 1}}', 'gravity'),
                        ('{"sim": {"friction": 0}}', 'positive number'),
                        ('{"sim": {"foot_contact_stiffness": 3e4}}', 'go together'),
                        ('{"sim": {"servo_kp_nm_per_rad": 20}}', 'go together'),
                        ('{"course": {"width_m": 1}}', 'width_m'),
                        ('{"course": {"max_height_m": -0.1}}', 'height in (0, 0.5]'),
                        ('{"course": {"max_height_m": "9cm"}}', 'height in (0, 0.5]')):
        rc = runner.main(['sim', '--rocks-only', '--rocks-seeds', '1', '--rocks-variant', text])
        assert rc == 2
        assert words in capsys.readouterr().err


def test_a_sim_variant_sets_the_friction_and_the_feet_contact_of_the_walk():
    """--rocks-variant's "sim" section: the terrain's friction, the feet's compliant
    contact and the joints' PD servos are what the simulator then uses; without it the
    defaults."""
    import numpy as np
    from terrain_perception.bench.sim import _walk_session
    from terrain_perception.sim.world import WorldConfig
    from terrain_perception.terrain import make_course
    course = make_course('rocks-6cm', 0, 0.01)
    for sim, friction, contact in (
            (None, WorldConfig().friction, None),
            ({'friction': 2.0, 'foot_contact_stiffness': 3e4, 'foot_contact_damping': 300.0},
             2.0, (3e4, 300.0))):
        s = _walk_session(course, 'littledog', 0.4, 0, sim)
        try:
            c, robot = s.client, s.robot
            assert c.getDynamicsInfo(s.world.terrain_id, -1)[1] == pytest.approx(friction)
            for link in robot.foot_links:
                info = c.getDynamicsInfo(robot.body_id, int(link))
                if contact is None:
                    assert info[9] < 0 or info[9] > 1e9     # rigid (pybullet: -1 or huge)
                else:
                    assert (info[9], info[8]) == pytest.approx(contact)
        finally:
            s.close()
    # pybullet's position servo gains replace the profile's
    s = _walk_session(course, 'littledog', 0.4, 0, {'velocity_gain': 0.3})
    try:
        assert (s.robot.model.position_gain, s.robot.model.velocity_gain) == (0.3, 0.3)
    finally:
        s.close()
    # the joints' PD servos: the reported torques are the PD law's on the session's targets
    s = _walk_session(course, 'littledog', 0.4, 0, {'servo_kp_nm_per_rad': 20.0,
                                                    'servo_kd_nm_s_per_rad': 0.15})
    try:
        s.step(100)
        q, dq, tau = s.robot.joint_states()
        assert np.abs(tau).max() > 0.1        # they hold the robot up
        np.testing.assert_allclose(tau, 20.0 * (s.q_target - q) - 0.15 * dq, atol=0.05)
    finally:
        s.close()


def test_a_course_variant_walks_the_same_rocks_scaled_to_its_peak(monkeypatch):
    """--rocks-variant's "course" section: the variant row's walk gets the class's terrain
    with the peak height changed (the same seed's layout scaled), the default row the
    class's own."""
    from terrain_perception.bench import sim as B
    import numpy as np
    from terrain_perception.terrain import ELEVATION
    walked = {}

    def fake_walk(course, start_x, goal_x, seed, **kw):
        walked[kw['trace_path'] or 'row'] = course
        return {}
    monkeypatch.setattr(B, '_rocks_walk', fake_walk)
    B._rocks_job(('rocks-12cm', 0.4, 2.4, 3, {'trace_path': 'default'}))
    B._rocks_job(('rocks-12cm', 0.4, 2.4, 3, {'trace_path': 'variant'},
                  {'max_height_m': 0.09}))
    d, v = (walked[k].layers[ELEVATION] for k in ('default', 'variant'))
    assert float(d.max()) == pytest.approx(0.12, abs=1e-4)
    assert float(v.max()) == pytest.approx(0.09, abs=1e-4)
    assert walked['variant'].metadata['max_height_m'] == pytest.approx(0.09)
    # the same rocks, scaled: heights proportional where the default has any
    rock = d > 0.01
    assert np.allclose(v[rock] / d[rock], 0.75, atol=0.02)


def test_closed_loop_trials_record_a_bag_only_when_asked():
    import argparse
    from pathlib import Path
    from terrain_perception.bench import closed_loop
    p = argparse.ArgumentParser()
    closed_loop.add_arguments(p)
    for argv, bag in (([], False), (['--bag'], True)):
        args = p.parse_args(argv + ['--front-gap', '0.3'])
        cmd = closed_loop.trial_command(args, 'rocks-6cm', 'littledog', 'full', 118,
                                        Path('/tmp/x/seed118'))
        assert ('--no-bag' not in cmd) == bag
        assert cmd[cmd.index('--seed') + 1] == '118'
        assert cmd[cmd.index('--run-dir') + 1] == '/tmp/x/seed118'
        start = float(cmd[cmd.index('--arg') + 1].split(':=')[1])
        # front feet 0.3 m before the rough section (rocks-6cm: x = 1.0 m)
        assert 0.55 < start < 0.65


def test_closed_loop_trials_pass_parameter_overrides_to_every_trial(tmp_path, capsys):
    import argparse
    from pathlib import Path
    from terrain_perception.bench import closed_loop, runner
    p = argparse.ArgumentParser()
    closed_loop.add_arguments(p)
    args = p.parse_args(['--param', 'walking_controller:touchdown_verify_s:=0.0',
                         '--param', 'footstep_planner:horizon:=3'])
    cmd = closed_loop.trial_command(args, 'rocks-6cm', 'littledog', 'full', 5, Path('/tmp/x'))
    got = [cmd[i + 1] for i, a in enumerate(cmd) if a == '--param']
    assert got == ['walking_controller:touchdown_verify_s:=0.0', 'footstep_planner:horizon:=3']
    # A malformed override is refused before any trial starts (a wrong node name is refused
    # by terrain-demo against the launch file: test_tools_launch).
    out = tmp_path / 'never'
    rc = runner.main(['closed-loop', '--param', 'touchdown_verify_s:=0.0', '--out', str(out)])
    assert rc == 2 and 'NODE:NAME:=VALUE' in capsys.readouterr().err
    assert not out.exists()
