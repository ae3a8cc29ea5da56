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


def _fake_demo(calls, revision):
    """A stand-in for the trials' terrain-demo: writes the summary.json the demo would, with
    the command it was given, and the outcome 'crossed' for even seeds."""
    import json as _json
    from pathlib import Path

    def run(cmd, _timeout_s, _stop):
        calls.append(cmd)
        run_dir = Path(cmd[cmd.index('--run-dir') + 1])
        run_dir.mkdir(parents=True, exist_ok=True)
        seed = int(cmd[cmd.index('--seed') + 1])
        crossed = seed % 2 == 0
        (run_dir / 'summary.json').write_text(_json.dumps({
            'command': ' '.join(['terrain-demo'] + [str(a) for a in cmd[1:]]),
            'code_revision': revision, 'crossed': crossed, 'falls': 0 if crossed else 1,
            'distance_m': 1.5, 'sim_time_s': 100.0, 'wall_time_s': 500.0,
            'mean_speed_mps': 0.015, 'end_reason': 'crossed' if crossed else 'fell',
            'complete_graph': True, 'capture_to_plan_ms_all': [150.0 + seed]}))
        return 0, ''
    return run


# A stand-in terrain-demo as a real process: it writes the summary at once, except that odd
# seeds wait (up to a minute) while the file $FAKE_DEMO_HOLD exists; SIGINT or SIGTERM ends it
# with the interrupted summary the demo writes. It notes its pid and process group, and the
# signal it got.
_DEMO_SCRIPT = """
import json, os, signal, sys, time
from pathlib import Path
argv = sys.argv
run_dir = Path(argv[argv.index('--run-dir') + 1])
seed = int(argv[argv.index('--seed') + 1])
run_dir.mkdir(parents=True, exist_ok=True)
got = []
for sig in (signal.SIGINT, signal.SIGTERM):
    signal.signal(sig, lambda n, _f: got.append(signal.Signals(n).name))
(run_dir / 'started').write_text(json.dumps([os.getpid(), os.getpgid(0)]))
hold = Path(os.environ.get('FAKE_DEMO_HOLD', '/nonexistent'))
t0 = time.monotonic()
while not got and seed % 2 and hold.exists() and time.monotonic() - t0 < 60.0:
    time.sleep(0.02)
end = 'interrupted (%s)' % got[0] if got else 'crossed'
(run_dir / 'summary.json').write_text(json.dumps({
    'command': ' '.join(['terrain-demo'] + argv[1:]), 'code_revision': 'a' * 40,
    'crossed': not got, 'falls': 0, 'distance_m': 1.5, 'sim_time_s': 12.0,
    'wall_time_s': 1.0, 'mean_speed_mps': 0.1, 'end_reason': end, 'complete_graph': True,
    'capture_to_plan_ms_all': [150.0 + seed], 'signals': got}))
"""


def _demo_program(tmp_path):
    import stat
    import sys
    prog = tmp_path / 'terrain-demo'
    prog.write_text(f'#!{sys.executable}\n{_DEMO_SCRIPT}')
    prog.chmod(prog.stat().st_mode | stat.S_IXUSR)
    return str(prog)


def _wait_for(path, timeout_s=20.0):
    import time
    t0 = time.monotonic()
    while not path.exists():
        assert time.monotonic() - t0 < timeout_s, f'{path} never appeared'
        time.sleep(0.02)


def test_closed_loop_stopped_by_sigterm_keeps_the_finished_trials(tmp_path, monkeypatch,
                                                                   capsys):
    import json as _json
    import os
    import signal
    import threading
    from terrain_perception.bench import closed_loop, pipeline, runner
    monkeypatch.setattr(pipeline, 'code_revision', lambda *a: 'a' * 40)
    monkeypatch.setattr(closed_loop, 'demo_program', lambda: _demo_program(tmp_path))
    (tmp_path / 'hold').touch()
    monkeypatch.setenv('FAKE_DEMO_HOLD', str(tmp_path / 'hold'))
    out = tmp_path / 'table'
    cell = out / 'rocks-6cm' / 'full'
    base = ['closed-loop', '--courses', 'rocks-6cm', '--variants', 'full', '--seeds', '3',
            '--first-seed', '10', '--front-gap', '0.3', '--out', str(out)]

    def stop_seed11():
        _wait_for(cell / 'seed11' / 'started')
        os.kill(os.getpid(), signal.SIGTERM)
    killer = threading.Thread(target=stop_seed11, daemon=True)
    killer.start()
    before = signal.getsignal(signal.SIGTERM)
    assert runner.main(base + ['--json', str(tmp_path / 'a.json')]) == 130
    killer.join(timeout=5)
    assert signal.getsignal(signal.SIGTERM) is before          # the suite's handler is gone
    a = _json.loads((tmp_path / 'a.json').read_text())
    assert a['stopped'] == 'SIGTERM'
    assert (a['trials_planned'], a['trials_finished']) == (3, 1)
    # The table is the finished trial's: the interrupted one is not counted a failure.
    assert a['success']['rocks-6cm']['full'] == 1.0 and a['latency_ms_median'] == 160.0
    assert [(t['seed'], bool(t.get('interrupted'))) for t in a['trials']] == [(10, False),
                                                                             (11, True)]
    # The demo got one SIGINT, forwarded by the suite, in its own process group.
    s11 = _json.loads((cell / 'seed11' / 'summary.json').read_text())
    assert s11['signals'] == ['SIGINT'] and s11['end_reason'] == 'interrupted (SIGINT)'
    pid, pgid = _json.loads((cell / 'seed11' / 'started').read_text())
    assert pgid == pid != os.getpgid(0)
    assert not (cell / 'seed12').exists()                      # no trial after the stop
    printed = capsys.readouterr().out
    assert 'INTERRUPTED (interrupted (SIGINT)' in printed and '1 of 3 trials finished' in printed
    # --resume keeps seed 10 and runs 11 (its interrupted run moved aside) and 12.
    (tmp_path / 'hold').unlink()
    assert runner.main(base + ['--resume', '--json', str(tmp_path / 'b.json')]) == 0
    b = _json.loads((tmp_path / 'b.json').read_text())
    assert b['stopped'] is None and b['trials_finished'] == 3
    assert [t['resumed'] for t in b['trials']] == [True, False, False]
    assert 'interrupted (SIGINT)' in b['trials'][1]['replaced_because']
    assert len(list(cell.glob('seed11.replaced-*/summary.json'))) == 1
    # --table-only runs nothing: the three finished trials, and a fourth seed not run yet.
    capsys.readouterr()
    wider = [a if a != '3' else '4' for a in base]
    assert runner.main(wider + ['--table-only', '--json', str(tmp_path / 'c.json')]) == 0
    c = _json.loads((tmp_path / 'c.json').read_text())
    assert (c['trials_planned'], c['trials_finished']) == (4, 3) and c['stopped'] is None
    assert [bool(t.get('not_run')) for t in c['trials']] == [False, False, False, True]
    assert c['success']['rocks-6cm']['full'] == 1.0 and c['latency_ms_median'] == 161.0
    assert not (cell / 'seed13').exists()
    assert 'rocks-6cm full: not run, seeds 13\n' in capsys.readouterr().out
    assert runner.main(base + ['--table-only', '--out', str(tmp_path / 'none')]) == 2


def test_closed_loop_trial_stops_gracefully_when_the_suite_is_killed(tmp_path):
    import json as _json
    import os
    import signal
    import subprocess
    import sys
    out = tmp_path / 'table'
    (tmp_path / 'hold').touch()
    code = ('import sys; from terrain_perception.bench import closed_loop, runner; '
            f'closed_loop.demo_program = lambda: {_demo_program(tmp_path)!r}; '
            f'sys.exit(runner.main(["closed-loop", "--courses", "rocks-6cm", "--variants", '
            f'"full", "--seeds", "1", "--first-seed", "11", "--out", {str(out)!r}]))')
    suite = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL,
                             env={**os.environ, 'FAKE_DEMO_HOLD': str(tmp_path / 'hold')})
    seed = out / 'rocks-6cm' / 'full' / 'seed11'
    try:
        _wait_for(seed / 'started', timeout_s=60.0)
    finally:
        suite.kill()                                            # no chance to pass anything on
        suite.wait()
    _wait_for(seed / 'summary.json')
    s = _json.loads((seed / 'summary.json').read_text())
    assert s['signals'] == ['SIGTERM'] and s['end_reason'] == 'interrupted (SIGTERM)'
    pid, _ = _json.loads((seed / 'started').read_text())
    for _ in range(250):                                        # the demo exits after it
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        import time
        time.sleep(0.02)
    else:
        os.kill(pid, signal.SIGKILL)
        raise AssertionError('the demo outlived the killed suite')


def test_closed_loop_resume_keeps_finished_trials_of_the_same_code(tmp_path, monkeypatch,
                                                                    capsys):
    import json as _json
    from terrain_perception.bench import closed_loop, pipeline, runner
    calls = []
    monkeypatch.setattr(pipeline, 'code_revision', lambda *a: 'a' * 40)
    monkeypatch.setattr(closed_loop, 'run_demo', _fake_demo(calls, 'a' * 40))
    out = tmp_path / 'full table'          # a space in the path, as a user's may have
    base = ['closed-loop', '--courses', 'rocks-6cm', '--variants', 'full', '--seeds', '2',
            '--first-seed', '10', '--front-gap', '0.3', '--out', str(out)]
    assert runner.main(base + ['--json', str(tmp_path / 'a.json')]) == 0
    assert len(calls) == 2
    first = _json.loads((tmp_path / 'a.json').read_text())
    assert first['success']['rocks-6cm']['full'] == 0.5
    # Without --resume the finished trials are not run over.
    capsys.readouterr()
    assert runner.main(base) == 2
    assert '--resume' in capsys.readouterr().err and len(calls) == 2
    # --resume keeps both: nothing runs, the same table and latencies.
    assert runner.main(base + ['--resume', '--json', str(tmp_path / 'b.json')]) == 0
    assert len(calls) == 2
    again = _json.loads((tmp_path / 'b.json').read_text())
    assert again['success'] == first['success']
    assert again['latency_ms_median'] == first['latency_ms_median'] == 160.5
    assert [t['resumed'] for t in again['trials']] == [True, True]
    # A trial of another commit is run again, the old one moved aside, not lost.
    seed11 = out / 'rocks-6cm' / 'full' / 'seed11' / 'summary.json'
    s = _json.loads(seed11.read_text())
    seed11.write_text(_json.dumps({**s, 'code_revision': 'b' * 40}))
    assert runner.main(base + ['--resume', '--json', str(tmp_path / 'c.json')]) == 0
    assert len(calls) == 3 and '--seed' in calls[-1] and calls[-1][calls[-1].index('--seed')
                                                                   + 1] == '11'
    moved = list((out / 'rocks-6cm' / 'full').glob('seed11.replaced-*/summary.json'))
    assert len(moved) == 1 and _json.loads(moved[0].read_text())['code_revision'] == 'b' * 40
    c = _json.loads((tmp_path / 'c.json').read_text())
    assert 'another' not in c['trials'][1]['replaced_because']
    assert 'bbbbbbbbbb' in c['trials'][1]['replaced_because']
    # any-code keeps a trial of another commit and says so; an interrupted trial is rerun.
    s = _json.loads(seed11.read_text())
    seed11.write_text(_json.dumps({**s, 'code_revision': 'c' * 40}))
    seed10 = out / 'rocks-6cm' / 'full' / 'seed10' / 'summary.json'
    s = _json.loads(seed10.read_text())
    seed10.write_text(_json.dumps({**s, 'end_reason': 'interrupted (SIGINT)'}))
    capsys.readouterr()
    assert runner.main(base + ['--resume', 'any-code', '--json', str(tmp_path / 'd.json')]) == 0
    assert len(calls) == 4 and calls[-1][calls[-1].index('--seed') + 1] == '10'
    d = _json.loads((tmp_path / 'd.json').read_text())
    assert d['code_revisions'] == ['a' * 40, 'c' * 40]
    assert [t['resumed'] for t in d['trials']] == [False, True]
    assert 'kept from an earlier run of code cccccccccc' in capsys.readouterr().out


def test_closed_loop_records_outlive_the_run_directories(tmp_path, monkeypatch, capsys):
    """--records: every counted trial's summary is kept in the records; on a machine without
    the run directories (a fresh clone) the table is rebuilt from them, and a record the
    resume does not keep is run again and replaced."""
    import json as _json
    import shutil
    from terrain_perception.bench import closed_loop, pipeline, runner
    calls = []
    monkeypatch.setattr(pipeline, 'code_revision', lambda *a: 'a' * 40)
    monkeypatch.setattr(closed_loop, 'run_demo', _fake_demo(calls, 'a' * 40))
    out, records = tmp_path / 'out', tmp_path / 'records'
    base = ['closed-loop', '--courses', 'rocks-6cm', '--variants', 'full', '--seeds', '2',
            '--first-seed', '10', '--front-gap', '0.3', '--out', str(out),
            '--records', str(records)]
    assert runner.main(base + ['--json', str(tmp_path / 'a.json')]) == 0
    first = _json.loads((tmp_path / 'a.json').read_text())
    rec10 = records / 'rocks-6cm' / 'full' / 'seed10.json'
    assert _json.loads(rec10.read_text()) == _json.loads(
        (out / 'rocks-6cm' / 'full' / 'seed10' / 'summary.json').read_text())
    assert [t['recorded'] for t in first['trials']] == ['new', 'new']
    # A new machine: no run directories. Without --resume the records are not run over.
    shutil.rmtree(out)
    capsys.readouterr()
    assert runner.main(base) == 2 and 'already records 2' in capsys.readouterr().err
    assert len(calls) == 2
    # --table-only reads them (no --out folder needed); so does --resume, running nothing.
    assert runner.main(base + ['--table-only', '--json', str(tmp_path / 'b.json')]) == 0
    b = _json.loads((tmp_path / 'b.json').read_text())
    assert not out.exists() and len(calls) == 2
    assert b['success'] == first['success'] == {'rocks-6cm': {'full': 0.5}}
    assert b['latency_ms_median'] == first['latency_ms_median']
    assert [t.get('from_record') for t in b['trials']] == [str(rec10), str(
        records / 'rocks-6cm' / 'full' / 'seed11.json')]
    # A record of other code: --resume (same code) runs that trial again and replaces it.
    rec11 = records / 'rocks-6cm' / 'full' / 'seed11.json'
    rec11.write_text(_json.dumps({**_json.loads(rec11.read_text()), 'code_revision': 'b' * 40}))
    capsys.readouterr()
    assert runner.main(base + ['--resume', '--json', str(tmp_path / 'c.json')]) == 0
    assert len(calls) == 3 and calls[-1][calls[-1].index('--seed') + 1] == '11'
    printed = capsys.readouterr().out
    assert 'kept from its record' in printed and 'earlier record was replaced' in printed
    assert _json.loads(rec11.read_text())['code_revision'] == 'a' * 40
    c = _json.loads((tmp_path / 'c.json').read_text())
    assert [t.get('recorded') for t in c['trials']] == [None, 'replaced']
    # Another command (an A/B experiment given the table's records by mistake) replaces no
    # record: the suite refuses to start.
    capsys.readouterr()
    assert runner.main(base + ['--resume', '--max-sim-time', '50']) == 2
    assert 'another terrain-demo command' in capsys.readouterr().err and len(calls) == 3
    # A trial finished in --out but missing from the records (run without --records) is
    # written there when the table is next made.
    rec11.unlink()
    assert runner.main(base + ['--table-only']) == 0
    assert _json.loads(rec11.read_text()) == _json.loads(
        (out / 'rocks-6cm' / 'full' / 'seed11' / 'summary.json').read_text())


def test_closed_loop_keeps_a_trial_whose_table_was_moved_but_not_another_command():
    from terrain_perception.bench.closed_loop import _same_command
    cmd = ['/venv/bin/terrain-demo', '--robot', 'frog', '--seed', '100', '--run-dir',
           '/new place/t/seed100', '--no-bag', '--max-sim-time', '480.0']
    ran = ('terrain-demo --robot frog --seed 100 --run-dir /old place/t/seed100 --no-bag '
           '--max-sim-time 480.0')
    assert _same_command(ran, cmd)                       # the folder given another way / moved
    assert not _same_command(ran.replace('480.0', '200.0'), cmd)
    assert not _same_command(ran.replace('--seed 100', '--seed 101'), cmd)
    assert not _same_command(ran + ' --blind', cmd)
    assert not _same_command(ran.replace(' --no-bag', ''), cmd)


def test_code_revision_names_the_commit_and_a_changed_tree(tmp_path):
    import subprocess
    from terrain_perception.bench.pipeline import code_revision
    assert code_revision(tmp_path) is None                     # not a git checkout
    git = ['git', '-C', str(tmp_path), '-c', 'user.name=t', '-c', 'user.email=t@t']
    subprocess.run(git + ['init', '-q'], check=True)
    (tmp_path / 'a.py').write_text('x = 1\n')
    subprocess.run(git + ['add', 'a.py'], check=True)
    subprocess.run(git + ['commit', '-q', '-m', 'a'], check=True)
    head = subprocess.run(git + ['rev-parse', 'HEAD'], capture_output=True, text=True,
                          check=True).stdout.strip()
    assert code_revision(tmp_path) == head
    (tmp_path / 'b.py').write_text('untracked files do not count\n')
    assert code_revision(tmp_path) == head
    (tmp_path / 'a.py').write_text('x = 2\n')
    assert code_revision(tmp_path) == head + '+dirty'
