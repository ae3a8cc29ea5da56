"""``terrain-launch FILE.yaml [name:=value ...]``: start a set of nodes as separate processes.

The launch file (see ``config/launch/*.yaml``)::

    arguments:                 # defaults of name:=value command-line arguments
      robot: littledog
    env:                       # extra environment for every process
      SOME_VAR: value
    nodes:
      - name: stereo_node      # node name (also the prefix of its output lines)
        executable: stereo_node        # console script in this environment ...
        # module: stereo_node.node     # ... or a Python module run with `python -m`
        params: [stereo_node.yaml]     # parameter files, relative to the launch file's folder
                                       # or to config/; later files override earlier ones,
                                       # and a name ending in '?' may be absent (e.g. a
                                       # robot's overlay: footstep_planner.${robot}.yaml?)
        parameters: {use_sim_time: true, robot: ${robot}}   # inline overrides
        remappings: {/stereo/points: /cam/points}
        args: []               # extra command-line arguments (before --ros-args)
        respawn: false         # restart when it exits
        respawn_delay: 1.0     # [s]
        required: false        # when it exits (and is not respawned), stop everything
        nice: 0                # CPU priority 0-19 (higher yields the CPU to the others)

``${name}`` is replaced by the argument's value; ``${config}`` by the project's config folder.
``--param NODE:NAME:=VALUE`` (repeatable) sets one node parameter over its files and inline
values, e.g. ``--param walking_controller:touchdown_verify_s:=0.0`` to try a value without
editing ``config/``.
Ctrl-C (or SIGTERM) is forwarded to every process; a process still running after
``--grace`` seconds gets SIGTERM, then SIGKILL. Children die with the launcher even if it is
killed (PR_SET_PDEATHSIG), so no process is left behind.
"""

from __future__ import annotations

import argparse
import ctypes
import functools
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import yaml

from terrain_ros.env import CONFIG_DIR, node_env
from terrain_ros.tools.common import ToolError, fail

PROG = 'terrain-launch'
_PR_SET_PDEATHSIG = 1


@dataclass
class NodeSpec:
    name: str
    command: List[str]
    env: Dict[str, str]
    respawn: bool = False
    respawn_delay: float = 1.0
    required: bool = False
    nice: int = 0


@dataclass
class Running:
    spec: NodeSpec
    proc: Optional[subprocess.Popen] = None
    restarts: int = 0
    next_start: float = 0.0
    done: bool = False
    threads: List[threading.Thread] = field(default_factory=list)


def _substitute(value, args: Dict[str, str]):
    if isinstance(value, str):
        def repl(m):
            key = m.group(1)
            if key == 'config':
                return str(CONFIG_DIR)
            if key not in args:
                raise ToolError(f'launch file uses ${{{key}}} but no argument {key!r} is '
                                f'declared (declared: {sorted(args)})')
            return str(args[key])
        return re.sub(r'\$\{([A-Za-z_][A-Za-z0-9_]*)\}', repl, value)
    if isinstance(value, list):
        return [_substitute(v, args) for v in value]
    if isinstance(value, dict):
        return {k: _substitute(v, args) for k, v in value.items()}
    return value


def _param_value(v) -> str:
    if isinstance(v, bool):
        return 'true' if v else 'false'
    if isinstance(v, (list, dict)):
        return yaml.safe_dump(v, default_flow_style=True).strip()
    return str(v)


def _find_file(name: str, base: Path, optional: bool = False) -> Optional[Path]:
    for cand in (Path(name), base / name, CONFIG_DIR / name):
        if cand.is_file():
            return cand.resolve()
    if optional:
        return None
    raise ToolError(f'parameter file {name!r} not found (looked in {base} and {CONFIG_DIR})')


def parse_param_override(text: str) -> 'tuple[str, str, str]':
    """``NODE:NAME:=VALUE`` -> (node, name, value)."""
    head, sep, value = text.partition(':=')
    node, colon, name = head.partition(':')
    if not sep or not colon or not node or not name:
        raise ToolError(f'parameter override {text!r} is not of the form NODE:NAME:=VALUE '
                        f'(e.g. walking_controller:touchdown_verify_s:=0.0)')
    return node, name, value


def load_launch_file(path: Path, cli_args: Dict[str, str],
                     param_overrides: 'List[str] | None' = None) -> List[NodeSpec]:
    """Parse a launch file into node specs (commands, environments).

    ``param_overrides``: ``NODE:NAME:=VALUE`` strings, applied last (they win over the node's
    parameter files and inline parameters)."""
    overrides: Dict[str, Dict[str, str]] = {}
    for text in param_overrides or []:
        node, name, value = parse_param_override(text)
        overrides.setdefault(node, {})[name] = value
    if not path.is_file():
        raise ToolError(f'launch file {str(path)!r} does not exist')
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ToolError(f'launch file {str(path)!r} is not valid YAML: {exc}') from None
    declared = {k: str(v) for k, v in (data.get('arguments') or {}).items()}
    unknown = set(cli_args) - set(declared)
    if unknown:
        raise ToolError(f'unknown launch argument(s) {sorted(unknown)}; '
                        f'{path.name} declares {sorted(declared)}')
    args = {**declared, **cli_args}
    base_env = node_env(dict(os.environ))
    base_env.update({k: str(v) for k, v in _substitute(data.get('env') or {}, args).items()})
    nodes = data.get('nodes') or []
    if not nodes:
        raise ToolError(f'launch file {str(path)!r} has no nodes')
    bindir = Path(sys.executable).parent
    specs = []
    for i, raw in enumerate(nodes):
        n = _substitute(raw, args)
        name = n.get('name') or f'node{i}'
        if 'executable' in n:
            exe = bindir / n['executable']
            if not exe.exists():
                raise ToolError(f'node {name!r}: executable {n["executable"]!r} is not installed '
                                f'in {bindir}')
            cmd = [str(exe)]
        elif 'module' in n:
            cmd = [sys.executable, '-m', n['module']]
        elif 'command' in n:
            cmd = shlex.split(n['command']) if isinstance(n['command'], str) else n['command']
        else:
            raise ToolError(f'node {name!r} needs an executable, module or command')
        cmd += [str(a) for a in n.get('args') or []]
        ros = ['--ros-args', '-r', f'__node:={name}']
        for f in n.get('params') or []:
            f = str(f)
            optional = f.endswith('?')
            found = _find_file(f[:-1] if optional else f, path.parent, optional)
            if found is not None:
                ros += ['--params-file', str(found)]
        for k, v in (n.get('parameters') or {}).items():
            ros += ['-p', f'{k}:={_param_value(v)}']
        mine = overrides.pop(name, {})
        for k, v in mine.items():
            ros += ['-p', f'{k}:={v}']
        if mine and not n.get('ros_args', True):
            raise ToolError(f'node {name!r} takes no ROS arguments (ros_args: false): '
                            f'cannot set {sorted(mine)}')
        for a, b in (n.get('remappings') or {}).items():
            ros += ['-r', f'{a}:={b}']
        if n.get('ros_args', True):
            cmd += ros
        env = dict(base_env)
        env.update({k: str(v) for k, v in (n.get('env') or {}).items()})
        nice = n.get('nice', 0)
        if isinstance(nice, bool) or not isinstance(nice, int) or not 0 <= nice <= 19:
            raise ToolError(f'node {name!r}: nice must be an integer 0-19 (a lower priority; '
                            f'raising one needs root), not {nice!r}')
        specs.append(NodeSpec(name, cmd, env, bool(n.get('respawn', False)),
                              float(n.get('respawn_delay', 1.0)), bool(n.get('required', False)),
                              nice))
    if overrides:
        raise ToolError(f'parameter override(s) for node(s) {sorted(overrides)} that '
                        f'{path.name} does not start (it starts {[s.name for s in specs]})')
    return specs


def _die_with_parent(nice: int = 0) -> None:
    # Runs in the child before exec: own process group, SIGTERM when the launcher dies, and
    # the node's CPU priority.
    os.setsid()
    try:
        ctypes.CDLL('libc.so.6', use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass
    if nice:
        os.nice(nice)
        # With the kernel's autogroup scheduling (sched_autogroup_enabled, the default on
        # desktop and many server kernels) the CPU is shared fairly between sessions first,
        # and a nice value only orders the threads inside one: the setsid above made a new
        # session, so the priority must be given to its autogroup too, or it does nothing.
        try:
            with open('/proc/self/autogroup', 'w') as f:
                f.write(str(nice))
        except OSError:
            pass    # no autogroups (a kernel without them): os.nice alone is the priority


def child_setup(spec: NodeSpec):
    """The ``preexec_fn`` that starts ``spec``'s process: see :func:`_die_with_parent`."""
    return functools.partial(_die_with_parent, spec.nice)


def _pump(name: str, stream, out) -> None:
    for line in iter(stream.readline, ''):
        out.write(f'[{name}] {line}')
        out.flush()
    stream.close()


class Launcher:
    def __init__(self, specs: List[NodeSpec], grace_s: float = 5.0) -> None:
        self.items = [Running(s) for s in specs]
        self.grace_s = grace_s
        self.stopping = False

    def _start(self, item: Running) -> None:
        proc = subprocess.Popen(item.spec.command, env=item.spec.env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, bufsize=1,
                                preexec_fn=child_setup(item.spec))
        item.proc = proc
        t = threading.Thread(target=_pump, args=(item.spec.name, proc.stdout, sys.stdout),
                             daemon=True)
        t.start()
        item.threads.append(t)
        print(f'[{PROG}] started {item.spec.name} pid {proc.pid}', flush=True)

    def run(self) -> int:
        for item in self.items:
            self._start(item)
        exit_code = 0
        while not self.stopping:
            now = time.monotonic()
            for item in self.items:
                if item.done:
                    continue
                if item.proc is None:
                    if now >= item.next_start:
                        self._start(item)
                    continue
                rc = item.proc.poll()
                if rc is None:
                    continue
                print(f'[{PROG}] {item.spec.name} exited with code {rc}', flush=True)
                item.proc = None
                if item.spec.respawn:
                    item.restarts += 1
                    item.next_start = now + item.spec.respawn_delay
                    print(f'[{PROG}] respawning {item.spec.name} in '
                          f'{item.spec.respawn_delay:.1f} s', flush=True)
                else:
                    item.done = True
                    if item.spec.required:
                        print(f'[{PROG}] {item.spec.name} is required: shutting down',
                              flush=True)
                        exit_code = rc or 1
                        self.stopping = True
            if all(i.done for i in self.items):
                break
            time.sleep(0.1)
        self.shutdown()
        return exit_code

    def shutdown(self) -> None:
        self.stopping = True
        live = [i for i in self.items if i.proc is not None and i.proc.poll() is None]
        for sig, wait in ((signal.SIGINT, self.grace_s), (signal.SIGTERM, 2.0),
                          (signal.SIGKILL, 2.0)):
            for item in live:
                try:
                    os.killpg(item.proc.pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait
            while time.monotonic() < deadline and any(i.proc.poll() is None for i in live):
                time.sleep(0.05)
            live = [i for i in live if i.proc.poll() is None]
            if not live:
                break
            names = ', '.join(i.spec.name for i in live)
            print(f'[{PROG}] still running after {sig.name}: {names}', flush=True)
        # Also reap whatever the children left in their process groups.
        for item in self.items:
            if item.proc is not None:
                try:
                    os.killpg(item.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        for item in self.items:
            for t in item.threads:
                t.join(timeout=1.0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n')[0])
    p.add_argument('launch_file', type=Path)
    p.add_argument('arguments', nargs='*', metavar='name:=value', help='launch arguments')
    p.add_argument('--grace', type=float, default=5.0,
                   help='seconds a node gets to stop after Ctrl-C before SIGTERM (default 5)')
    p.add_argument('--print', action='store_true', dest='print_only',
                   help='print the commands and exit')
    p.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                   help='set one node parameter over its files (repeatable), e.g. '
                        'walking_controller:touchdown_verify_s:=0.0')
    args = p.parse_args(argv)
    try:
        cli = {}
        for a in args.arguments:
            if ':=' not in a:
                raise ToolError(f'launch argument {a!r} is not of the form name:=value')
            k, v = a.split(':=', 1)
            cli[k] = v
        specs = load_launch_file(args.launch_file, cli, args.param)
    except ToolError as exc:
        return fail(PROG, exc)
    if args.print_only:
        for s in specs:
            print(f'{s.name}: {shlex.join(s.command)}')
        return 0
    launcher = Launcher(specs, args.grace)

    def on_signal(signum, _frame):
        if not launcher.stopping:
            print(f'[{PROG}] {signal.Signals(signum).name}: stopping all nodes', flush=True)
        launcher.stopping = True
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    return launcher.run()


if __name__ == '__main__':
    sys.exit(main())
