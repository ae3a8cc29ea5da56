"""Closed-loop latency: capture-to-plan wall time of the graph in simulation, as shipped against
the earlier settings, one short ``terrain-demo`` run per variant on the same course and seed.

Each variant is the demo's launch file (``config/launch/sim.yaml``) with some node parameters
overridden, written next to the run directories, and sometimes a ``terrain-demo`` option:

* ``before`` (the baseline): the settings up to the fourteenth session. The simulator publishes
  ``/clock`` at 500 Hz of simulated time and the stereo node processes a pair only on the next
  tick of its ``max_rate_hz`` timer, which runs on the simulated clock (``rate_clock: node``;
  shipped: the steady clock since the fifty-third session); with the fifteenth
  session's simulator settings below.
* ``fifteenth``: the fifteenth session's settings. The simulator's physics timer ticks every
  5 ms of wall time (shipped: 20 ms at the real-time factor 0.2), and the simulator and the bag
  recorder run at normal CPU priority.
* ``no_nice``: as shipped, but the simulator and the recorder at normal CPU priority (shipped:
  ``nice: 10`` in the launch file and ``terrain-demo --recorder-nice 10``, applied to the
  processes' autogroups).
* ``timer_only``, ``clock500`` (not run by default; they measured the fifteenth session's two
  changes): as shipped, but the stereo node waits for its timer (``process_on_arrival: false``),
  or ``/clock`` at 500 Hz (``clock_rate_hz: 500``).
* ``shipped``: the defaults.

The runs record their bag as ``make demo`` does (the recorder is part of the main job's load);
the bags are deleted after the run unless ``--keep-bags``. Latency is the demo's capture-to-plan
figure: the wall time from the simulator publishing a capture to the first plan made on its
map. Per-stage figures are the demo's too (first arrival of the capture's stamp on each node's
output minus on its input). CPU per process is read from ``/proc`` once a second while the run
goes (the demo's process tree). The suite only starts processes; it imports nothing from ROS.

JSON: ``latency_ms_median``, ``latency_ms_p95`` (shipped), ``speedup_shipped`` (baseline
median / shipped median), ``variants`` (name -> ``latency_ms_median``, ``latency_ms_p95``,
``plans``, ``stage_ms_median``, ``cpu_s`` per process, ``cpu_share`` (CPU seconds per wall
second, all processes), ``real_time_factor``, ``run_dir``), ``ratio_median`` (name -> baseline
median / variant median), ``baseline``, ``settings``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict

LAUNCH = Path(__file__).resolve().parents[2] / 'config' / 'launch' / 'sim.yaml'
BASELINE = 'before'
#: Changes per variant: node name -> {'parameters': {name: value}, 'nice': n} in the launch
#: file, and '-demo' -> extra ``terrain-demo`` options.
#: The sixteenth session's settings, undone together by ``fifteenth`` (and by ``before``).
_SIXTEENTH_UNDONE = {'parameters': {'tick_period_s': 0.005}, 'nice': 0}
VARIANTS: Dict[str, Dict[str, dict]] = {
    'before': {'sim_bridge': {'parameters': {'clock_rate_hz': 500.0,
                                             **_SIXTEENTH_UNDONE['parameters']}, 'nice': 0},
               'stereo_node': {'parameters': {'process_on_arrival': False,
                                              'rate_clock': 'node'}},
               '-demo': ['--recorder-nice', '0']},
    'fifteenth': {'sim_bridge': _SIXTEENTH_UNDONE, '-demo': ['--recorder-nice', '0']},
    'no_nice': {'sim_bridge': {'nice': 0}, '-demo': ['--recorder-nice', '0']},
    'timer_only': {'stereo_node': {'parameters': {'process_on_arrival': False}}},
    'clock500': {'sim_bridge': {'parameters': {'clock_rate_hz': 500.0}}},
    'shipped': {},
}
VARIANT_TITLES = {
    'before': 'baseline: /clock 500 Hz, stereo on its timer (fourteenth session)',
    'fifteenth': 'the fifteenth session\'s settings: 5 ms simulator ticks, simulator and '
                 'recorder at normal priority',
    'no_nice': 'shipped, but the simulator and the recorder at normal priority',
    'timer_only': 'shipped, but the stereo node on its timer',
    'clock500': 'shipped, but /clock at 500 Hz',
    'shipped': 'as shipped',
}
#: Run by default (timer_only and clock500 measured the fifteenth session's two changes).
DEFAULT_VARIANTS = ['before', 'fifteenth', 'no_nice', 'shipped']


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument('--variants', nargs='+', default=list(DEFAULT_VARIANTS),
                   choices=list(VARIANTS),
                   help=f'variants to run (default: {" ".join(DEFAULT_VARIANTS)}; the baseline '
                        f'is {BASELINE!r})')
    p.add_argument('--course', default='rocks-6cm', help='course class (default rocks-6cm)')
    p.add_argument('--robot', default='littledog', help='robot profile (default littledog)')
    p.add_argument('--seed', type=int, default=0, help='course seed (default 0)')
    p.add_argument('--sim-time', type=float, default=60.0,
                   help='simulated seconds per run (default 60: ~170 captures, ~5.5 min wall)')
    p.add_argument('--image-scale', type=float, default=1.0,
                   help='camera resolution relative to the profile (default 1: 640x480 class)')
    p.add_argument('--keep-bags', action='store_true', help='keep the runs\' bags')
    p.add_argument('--out', type=Path, default=None,
                   help='folder for the run directories (default runs/bench/latency-runs)')


def variant_launch(name: str, src: Path = LAUNCH) -> str:
    """The launch file of variant ``name``: ``src`` with the variant's node parameters set."""
    import yaml
    doc = yaml.safe_load(src.read_text())
    nodes = {n['name']: n for n in doc['nodes']}
    for node, change in VARIANTS[name].items():
        if node == '-demo':
            continue
        if node not in nodes:
            raise ValueError(f'variant {name!r}: no node {node!r} in {src}')
        nodes[node].setdefault('parameters', {}).update(change.get('parameters', {}))
        if 'nice' in change:
            nodes[node]['nice'] = int(change['nice'])
    header = f'# terrain-bench latency, variant {name!r}: {src} with {VARIANTS[name]}\n'
    return header + yaml.safe_dump(doc, sort_keys=False)


def _proc_name(cmd) -> str:
    if len(cmd) > 1 and cmd[1].endswith('terrain-bag') and len(cmd) > 2:
        return f'terrain-bag {cmd[2]}'
    if len(cmd) > 2 and cmd[1] == '-m':
        return cmd[2]
    return os.path.basename(cmd[1] if len(cmd) > 1 and 'python' in cmd[0] else cmd[0])


class TreeCpu(threading.Thread):
    """CPU seconds of a process and its descendants, by name, sampled from /proc every second
    (a process that exits between samples loses at most its last second)."""

    def __init__(self, root_pid: int) -> None:
        super().__init__(daemon=True)
        self.root = root_pid
        self.last: Dict[int, tuple] = {}
        self.done = threading.Event()
        self.tck = os.sysconf('SC_CLK_TCK')

    def _scan(self) -> None:
        parent, info = {}, {}
        for d in os.listdir('/proc'):
            if not d.isdigit():
                continue
            try:
                st = Path(f'/proc/{d}/stat').read_text()
                cmd = Path(f'/proc/{d}/cmdline').read_bytes().decode(errors='replace')
            except OSError:
                continue
            f = st[st.rindex(')') + 2:].split()
            parent[int(d)] = int(f[1])
            info[int(d)] = ((int(f[11]) + int(f[12])) / self.tck, cmd.split('\0'))
        tree = {self.root}
        grew = True
        while grew:
            new = {p for p, pp in parent.items() if pp in tree} - tree
            grew = bool(new)
            tree |= new
        for p in tree:
            if p not in info:
                continue
            cpu, cmd = info[p]
            if not cmd[0] and p in self.last:     # exited, not yet reaped: keep its name
                self.last[p] = (max(cpu, self.last[p][0]), self.last[p][1])
            elif cmd[0]:
                self.last[p] = (cpu, _proc_name(cmd))

    def run(self) -> None:
        while not self.done.wait(1.0):
            self._scan()

    def by_name(self) -> Dict[str, float]:
        out: Dict[str, float] = {}
        for cpu, name in self.last.values():
            out[name] = round(out.get(name, 0.0) + cpu, 1)
        return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def _run_variant(args, name: str, out: Path) -> dict:
    launch = out / f'{name}.launch.yaml'
    launch.write_text(variant_launch(name))
    run_dir = out / name
    if run_dir.exists():
        shutil.rmtree(run_dir)
    cmd = [str(Path(sys.executable).parent / 'terrain-demo'), '--robot', args.robot,
           '--course', args.course, '--seed', str(args.seed), '--run-dir', str(run_dir),
           '--launch', str(launch), '--quiet', '--max-sim-time', str(args.sim_time),
           '--timeout', str(args.sim_time * 8 + 240), '--image-scale', str(args.image_scale),
           *VARIANTS[name].get('-demo', [])]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=dict(os.environ))
    cpu = TreeCpu(proc.pid)
    cpu.start()
    text, _ = proc.communicate()
    cpu.done.set()
    wall = time.monotonic() - t0
    summary = run_dir / 'summary.json'
    if not summary.is_file():
        tail = ' | '.join(text.strip().splitlines()[-3:])
        raise ValueError(f'variant {name}: terrain-demo wrote no summary.json ({tail})')
    s = json.loads(summary.read_text())
    if not args.keep_bags and (run_dir / 'bag').is_dir():
        shutil.rmtree(run_dir / 'bag')
    procs = cpu.by_name()
    return {'latency_ms_median': s.get('capture_to_plan_ms_median'),
            'latency_ms_p95': s.get('capture_to_plan_ms_p95'),
            'plans': len(s.get('capture_to_plan_ms_all') or []),
            'stage_ms_median': {k: v.get('median')
                                for k, v in (s.get('latency_stages_ms') or {}).items()},
            'cpu_s': procs, 'cpu_share': round(sum(procs.values()) / wall, 2),
            'real_time_factor': s.get('real_time_factor'), 'wall_s': round(wall, 1),
            'complete_graph': s.get('complete_graph'), 'run_dir': str(run_dir)}


def run(args) -> dict:
    if args.quick:
        args.variants, args.sim_time, args.image_scale = [BASELINE, 'shipped'], 8.0, 0.5
    variants = list(dict.fromkeys(args.variants))
    out = args.out or Path('runs') / 'bench' / 'latency-runs'
    out.mkdir(parents=True, exist_ok=True)
    print(f'{args.robot} on {args.course} seed {args.seed}, {args.sim_time:g} s of simulated '
          f'time per variant, image scale {args.image_scale:g}; {os.cpu_count()} CPUs; '
          f'run directories in {out}')
    res = {}
    for name in variants:
        load0 = os.getloadavg()[0]
        r = _run_variant(args, name, out)
        res[name] = r
        print(f'\n=== {name}: {VARIANT_TITLES[name]} (load average before {load0:.2f})')
        print(f'capture-to-plan median {r["latency_ms_median"]} ms, p95 {r["latency_ms_p95"]} '
              f'ms over {r["plans"]} plans; stages (median ms) {r["stage_ms_median"]}')
        print(f'simulated RTF {r["real_time_factor"]}, {r["wall_s"]:.0f} s wall; CPU '
              f'{r["cpu_share"]:.2f} cores on average: '
              + ', '.join(f'{k} {v:.0f} s' for k, v in r['cpu_s'].items()))
    ratios = {}
    base = res.get(BASELINE, {}).get('latency_ms_median')
    print()
    print(f'{"variant":11s} {"median ms":>10s} {"p95 ms":>8s} {"cores":>6s} '
          f'{"baseline/variant":>17s}')
    for name, r in res.items():
        ratio = (round(base / r['latency_ms_median'], 2)
                 if base and r['latency_ms_median'] else None)
        ratios[name] = ratio
        print(f'{name:11s} {r["latency_ms_median"]!s:>10s} {r["latency_ms_p95"]!s:>8s} '
              f'{r["cpu_share"]:6.2f} {"-" if ratio is None else f"{ratio:.2f}x":>17s}')
    shipped = res.get('shipped', {})
    return {'variants': res, 'ratio_median': ratios, 'baseline': BASELINE,
            'latency_ms_median': shipped.get('latency_ms_median'),
            'latency_ms_p95': shipped.get('latency_ms_p95'),
            'speedup_shipped': ratios.get('shipped'),
            'settings': {'course': args.course, 'robot': args.robot, 'seed': args.seed,
                         'sim_time_s': args.sim_time, 'image_scale': args.image_scale}}
