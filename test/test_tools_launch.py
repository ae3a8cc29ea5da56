"""terrain-launch: starts processes with params and remaps, forwards Ctrl-C, leaves no orphan."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.graph
BIN = Path(sys.executable).parent

TALKER = '''
import sys, rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import String
rclpy.init(args=sys.argv)
node = rclpy.create_node('talker')
node.declare_parameter('word', 'none')
pub = node.create_publisher(String, 'chatter', 10)
node.create_timer(0.1, lambda: pub.publish(String(data=node.get_parameter('word').value)))
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
'''


def _nice(pid) -> int:
    """The process's nice value (field 19 of /proc/PID/stat)."""
    return int(Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[16])


def _autogroups_enabled() -> bool:
    flag = Path('/proc/sys/kernel/sched_autogroup_enabled')
    return flag.exists() and flag.read_text().strip() == '1'


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie still answers kill(0); read its state.
    try:
        return Path(f'/proc/{pid}/stat').read_text().split()[2] != 'Z'
    except FileNotFoundError:
        return False


def _write_launch(tmp_path: Path, respawn: bool = False) -> Path:
    (tmp_path / 'talker.py').write_text(TALKER)
    (tmp_path / 'params.yaml').write_text('talker_a:\n  ros__parameters:\n    word: from_file\n')
    launch = tmp_path / 'two.yaml'
    launch.write_text(f'''
arguments:
  word: hello
nodes:
  - name: talker_a
    command: [{sys.executable}, {tmp_path / 'talker.py'}]
    params: [params.yaml]
    remappings: {{chatter: /a/chatter}}
  - name: talker_b
    command: [{sys.executable}, {tmp_path / 'talker.py'}]
    parameters: {{word: "${{word}}"}}
    remappings: {{chatter: /b/chatter}}
    respawn: {str(respawn).lower()}
    respawn_delay: 0.2
    nice: 7
''')
    return launch


def _started_pids(proc, n: int, timeout: float = 20.0) -> dict:
    pids = {}
    deadline = time.monotonic() + timeout
    while len(pids) < n and time.monotonic() < deadline:
        line = proc.stdout.readline()
        m = re.search(r'started (\S+) pid (\d+)', line)
        if m:
            pids[m.group(1)] = int(m.group(2))
    return pids


def test_two_processes_with_params_and_remaps_stop_cleanly_on_sigint(tmp_path):
    launch = _write_launch(tmp_path)
    proc = subprocess.Popen([BIN / 'terrain-launch', launch, 'word:=bonjour'],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    pids = _started_pids(proc, 2)
    assert set(pids) == {'talker_a', 'talker_b'}
    try:
        # Parameters and remaps reached the processes: the file value on /a, the argument on /b.
        for topic, word in (('/a/chatter', 'from_file'), ('/b/chatter', 'bonjour')):
            echo = subprocess.run([BIN / 'terrain-topic', 'echo', topic, '--once',
                                   '--timeout', '20'], capture_output=True, text=True,
                                  timeout=60)
            assert f'data: {word}' in echo.stdout, echo.stdout + echo.stderr
        # talker_b's launch entry lowers its priority by 7 (field 19 of /proc/PID/stat);
        # talker_a keeps the launcher's.
        nice = {n: _nice(p) for n, p in pids.items()}
        assert nice['talker_b'] == nice['talker_a'] + 7 or nice['talker_b'] == 19, nice
        # Each launched process leads its own session, so with autogroup scheduling the
        # priority must be its autogroup's too: a nice value alone only orders threads within
        # one session, and talker_b would get as much CPU as talker_a.
        if _autogroups_enabled():
            group = {n: Path(f'/proc/{p}/autogroup').read_text().split() for n, p in
                     pids.items()}
            assert group['talker_b'][0] != group['talker_a'][0], group
            assert group['talker_b'][-1] == '7' and group['talker_a'][-1] == '0', group
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    time.sleep(0.2)
    assert not [n for n, p in pids.items() if _alive(p)], 'a launched process survived SIGINT'


def test_respawn_restarts_a_dead_node_and_sigkill_of_launcher_leaves_no_orphan(tmp_path):
    launch = _write_launch(tmp_path, respawn=True)
    proc = subprocess.Popen([BIN / 'terrain-launch', launch], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    pids = _started_pids(proc, 2)
    os.kill(pids['talker_b'], signal.SIGKILL)
    again = _started_pids(proc, 1)
    assert 'talker_b' in again and again['talker_b'] != pids['talker_b']
    proc.kill()  # the launcher dies without cleaning up: children must follow it
    proc.wait(timeout=10)
    deadline = time.monotonic() + 10
    survivors = [pids['talker_a'], again['talker_b']]
    while time.monotonic() < deadline and any(map(_alive, survivors)):
        time.sleep(0.1)
    assert not any(map(_alive, survivors)), 'orphans left after the launcher was killed'


def test_bad_launch_files_give_one_error_line(tmp_path):
    cases = {
        'missing.yaml': None,
        'bad.yaml': 'nodes: [',
        'noexe.yaml': 'nodes:\n  - name: x\n    executable: no_such_program\n',
        'undeclared.yaml': 'nodes:\n  - name: x\n    command: [true]\n    args: ["${nope}"]\n',
        'badnice.yaml': 'nodes:\n  - name: x\n    command: [true]\n    nice: -5\n',
    }
    for name, text in cases.items():
        path = tmp_path / name
        if text is not None:
            path.write_text(text)
        res = subprocess.run([BIN / 'terrain-launch', path], capture_output=True, text=True,
                             timeout=30)
        assert res.returncode != 0
        assert len(res.stderr.strip().splitlines()) == 1, res.stderr


def test_launched_nodes_get_one_thread_per_pool_unless_the_user_set_it(tmp_path, monkeypatch):
    from terrain_ros.tools.launch import load_launch_file
    launch = _write_launch(tmp_path)
    for k in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS',
              'OPENCV_FOR_THREADS_NUM'):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv('OPENBLAS_NUM_THREADS', '4')
    specs = load_launch_file(launch, {})
    assert len(specs) == 2
    for s in specs:
        # OpenMP (Open3D's ICP), MKL and OpenCV pools: one worker; the user's BLAS choice is
        # kept.
        assert s.env['OMP_NUM_THREADS'] == '1' and s.env['MKL_NUM_THREADS'] == '1'
        assert s.env['OPENCV_FOR_THREADS_NUM'] == '1'
        assert s.env['OPENBLAS_NUM_THREADS'] == '4'
        assert s.env['ROS_AUTOMATIC_DISCOVERY_RANGE'] in ('LOCALHOST', os.environ.get(
            'ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST'))


def test_demo_recorder_runs_at_its_priority(tmp_path):
    # terrain-demo's bag recorder yields the CPU to the nodes (--recorder-nice): the value is
    # the process's nice and, where autogroups are enabled, its autogroup's.
    from terrain_ros.tools.demo import start_recorder, stop_process
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID='93')
    own = _nice('self')
    proc = start_recorder(tmp_path / 'bag', tmp_path, env, nice=6)
    try:
        nice = _nice(proc.pid)
        assert nice == min(own + 6, 19), nice
        if _autogroups_enabled():
            assert Path(f'/proc/{proc.pid}/autogroup').read_text().split()[-1] == '6'
    finally:
        stop_process(proc, signal.SIGINT, 20.0)


def test_parameter_overrides_win_over_files_and_name_a_started_node(tmp_path):
    # --param NODE:NAME:=VALUE is the last -p of that node's command (the last value of a
    # parameter wins in ROS 2), only that node gets it, and a node the file does not start
    # or a malformed override is a one-line error.
    launch = _write_launch(tmp_path)
    res = subprocess.run([BIN / 'terrain-launch', '--print', launch,
                          '--param', 'talker_b:word:=override', '--param', 'talker_a:rate:=2.5'],
                         capture_output=True, text=True, timeout=30)
    assert res.returncode == 0, res.stderr
    lines = {ln.split(':', 1)[0]: ln for ln in res.stdout.splitlines()}
    b = lines['talker_b'].split()
    ps = [b[i + 1] for i, a in enumerate(b) if a == '-p']
    assert ps[-1] == 'word:=override' and 'word:=hello' in ps
    assert 'word:=override' not in lines['talker_a']
    assert 'rate:=2.5' in lines['talker_a']
    for bad, words in ((['--param', 'talker_c:word:=x'], "talker_c"),
                       (['--param', 'word:=x'], 'NODE:NAME:=VALUE')):
        res = subprocess.run([BIN / 'terrain-launch', '--print', launch, *bad],
                             capture_output=True, text=True, timeout=30)
        assert res.returncode != 0 and words in res.stderr, res.stderr
        assert len(res.stderr.strip().splitlines()) == 1, res.stderr


def test_an_optional_parameter_file_is_layered_when_present(tmp_path):
    # 'NAME.yaml?' in params: loaded after the files before it when it exists (a robot's
    # overlay), skipped when it does not; a missing file without '?' is still an error.
    from terrain_ros.tools.launch import load_launch_file
    from terrain_ros.tools.common import ToolError
    (tmp_path / 'base.yaml').write_text('n:\n  ros__parameters:\n    word: base\n')
    (tmp_path / 'base.big.yaml').write_text('n:\n  ros__parameters:\n    word: big\n')
    launch = tmp_path / 'l.yaml'
    launch.write_text('arguments:\n  size: big\nnodes:\n  - name: n\n    command: [true]\n'
                      '    params: [base.yaml, "base.${size}.yaml?"]\n')

    def files(**args):
        cmd = load_launch_file(launch, args)[0].command
        return [Path(cmd[i + 1]).name for i, a in enumerate(cmd) if a == '--params-file']
    assert files() == ['base.yaml', 'base.big.yaml']
    assert files(size='small') == ['base.yaml']
    launch.write_text('nodes:\n  - name: n\n    command: [true]\n    params: [base.small.yaml]\n')
    with pytest.raises(ToolError, match='base.small.yaml'):
        load_launch_file(launch, {})


def test_the_frog_planner_gets_its_overlay_over_the_shared_file(tmp_path):
    # The sim profile with robot:=frog, as terrain-demo runs it (its preflight copy), gives
    # the planner config/footstep_planner.frog.yaml after footstep_planner.yaml: the
    # overlay's keys win, every other key is the shared file's; LittleDog's planner gets the
    # shared file alone.
    import yaml
    from rclpy.parameter import Parameter
    from footstep_planner_node.node import FootstepPlannerNode
    from terrain_ros.env import CONFIG_DIR
    from terrain_ros.tools.demo import preflight
    from terrain_ros.tools.launch import load_launch_file
    preflight(CONFIG_DIR / 'launch' / 'sim.yaml', tmp_path / 'launch.yaml')
    overlay = yaml.safe_load((CONFIG_DIR / 'footstep_planner.frog.yaml').read_text())
    overlay = overlay['footstep_planner']['ros__parameters']['planner']
    assert overlay, 'the FROG-I overlay sets no planner value'
    got = {}
    for robot in ('littledog', 'frog'):
        spec = [s for s in load_launch_file(tmp_path / 'launch.yaml', {'robot': robot})
                if s.name == 'footstep_planner'][0]
        cmd = spec.command
        files = [cmd[i + 1] for i, a in enumerate(cmd) if a == '--params-file']
        args = ['--ros-args', '-r', '__node:=footstep_planner']
        for f in files:
            args += ['--params-file', f]
        import rclpy
        from rclpy.context import Context
        ctx = Context()
        rclpy.init(args=args, context=ctx, domain_id=int(os.environ['ROS_DOMAIN_ID']))
        try:
            node = FootstepPlannerNode(context=ctx, parameter_overrides=[
                Parameter('robot', value=robot)])
            got[robot] = node.plan_cfg
            node.destroy_node()
        finally:
            rclpy.shutdown(context=ctx)
    for key, value in overlay.items():
        assert getattr(got['frog'], key) == pytest.approx(value), key
        assert getattr(got['littledog'], key) != pytest.approx(value), key
    import dataclasses
    same = {f.name for f in dataclasses.fields(got['frog'])} - set(overlay)
    assert all(getattr(got['frog'], k) == getattr(got['littledog'], k) for k in same)
    # the ground-truth walks of terrain-bench sim build their planner with the same overlay
    from terrain_perception.bench.plan import robot_planner_overrides
    assert robot_planner_overrides('frog') == overlay
    assert robot_planner_overrides('littledog') == {}
