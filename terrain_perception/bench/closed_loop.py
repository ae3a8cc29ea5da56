"""Closed loop: success rate, falls, speed and capture-to-plan latency of the whole graph.

For each course class (``rocks-6cm`` and ``rocks-12cm`` with the LittleDog-like robot,
``stones-15cm`` with the FROG-I-like robot), N seeds and three variants, one ``terrain-demo`` run
(the full node graph as separate processes, headless) per trial:

* ``full``: the system as shipped;
* ``nofill``: terrain fill switched off (``fill.method: none``): occluded cells stay unknown and
  the cost is computed ignoring missing cells (paper 000: the system "will invariably fail"
  without terrain modelling);
* ``blind``: the planner and the controller see a flat map (``/map/blind``, all cells observed
  at height 0, published by the demo on every new ``/map/fine``): flat-ground footsteps with
  the same localisation.

A trial succeeds when the robot crossed without a fall. Latency is the wall time from the
simulator publishing a capture to the plan made on the map of that capture (``FootstepPlan``
stamps are the map's stamp), pooled over trials. The suite only starts processes and reads each
run's ``summary.json``; it imports nothing from ROS.

JSON: ``success`` (course -> variant -> rate), ``falls`` (course -> variant -> total),
``speed_mps`` (course -> variant -> mean over trials that moved), ``latency_ms_median``,
``latency_ms_p95`` (full variant), ``trials`` (every trial's outcome, run directory and code
revision), ``code_revisions``.

A full run (3 courses x 3 variants x 10 seeds) takes about a day of wall time on a 2-core
machine, so it can be run in pieces: ``--resume`` with the same ``--out`` keeps every trial
whose run directory already holds the ``summary.json`` of the same ``terrain-demo`` command,
run from the same commit (``code_revision``, clean tree), and runs the rest. A trial stopped
before its end (interrupted, or without a summary) is run again, and a finished trial the run
does not keep is moved aside to ``seed<S>.replaced-<time>``, never overwritten. ``--resume
any-code`` also keeps trials of other commits; the table then says how many, and
``code_revisions`` lists them. Without ``--resume`` a finished trial in ``--out`` is an error.
``--table-only`` runs nothing: the table of the trials ``--out`` already holds (as ``--resume
any-code`` would keep them, or as ``--resume same-code`` with it), the others listed as not run.

Records: run directories (bags, figures) stay on the machine that ran them, and a table of 90
trials outlives many machines. ``--records DIR`` (the project's table: ``docs/closed-loop-table``,
committed) holds one JSON file per trial the table counts, ``DIR/<course>/<variant>/seed<S>.json``:
that trial's ``summary.json`` as the demo wrote it. Every trial the table counts is written there
(a new one, or one kept from ``--out`` that the records lack or hold another version of), and a
trial whose run directory is not in ``--out`` is kept from its record by the same rules as from a
run directory (same command, ended by itself, the code ``--resume`` asks for). A trial run again
replaces its record (git keeps the earlier one); a record of another command is never replaced
(the suite refuses to start: an experiment given the table's records by mistake).

Stopping: Ctrl-C or SIGTERM (``kill PID``: a run started in the background of a script ignores
SIGINT) stops the trial under way the way Ctrl-C stops ``terrain-demo`` (its nodes stopped, its
report written, marked interrupted), starts no further trial, and prints and writes the table of
the trials finished so far (JSON ``stopped``; exit code 130). A second signal stops the trial at
once. ``--resume`` later runs the interrupted trial again and the ones never started. Each
trial's demo runs in its own process group, so a terminal's Ctrl-C reaches it once, through the
suite, and it gets SIGTERM (and stops the same way) if the suite itself is killed.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

COURSES = {'rocks-6cm': 'littledog', 'rocks-12cm': 'littledog', 'stones-15cm': 'frog'}
VARIANTS = {
    'full': [],
    'nofill': ['--arg', 'fill_method:=none'],
    'blind': ['--blind'],
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument('--courses', nargs='+', default=list(COURSES), choices=list(COURSES),
                   help='course classes (default: all three)')
    p.add_argument('--variants', nargs='+', default=list(VARIANTS), choices=list(VARIANTS),
                   help='system variants (default: all three)')
    p.add_argument('--seeds', type=int, default=10, help='seeds per course (default 10)')
    p.add_argument('--first-seed', type=int, default=100,
                   help='first course seed (default 100: not the demo\'s seed 0)')
    p.add_argument('--max-sim-time', type=float, default=None,
                   help='simulated-time limit per trial [s] (default per course: rocks 200, '
                        'stones 480)')
    p.add_argument('--timeout', type=float, default=None,
                   help='wall-time limit per trial [s] (default per course: rocks 900, stones '
                        '2500)')
    p.add_argument('--image-scale', type=float, default=1.0,
                   help='camera resolution relative to the profile (default 1)')
    p.add_argument('--front-gap', type=float, default=None,
                   help='start each trial with the front feet this far before the rough section '
                        '[m] (default: the launch file\'s start_x, i.e. the whole flat approach; '
                        'a short gap saves the flat walk in a reduced run; widened to the '
                        'ground the robot\'s camera never sees ahead of its front feet plus '
                        '5 cm: FROG-I 0.57 m)')
    p.add_argument('--out', type=Path, default=None,
                   help='folder for the trials\' run directories (default runs/bench-<date>)')
    p.add_argument('--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                   help='set one node parameter in every trial (repeatable; terrain-demo '
                        '--param), e.g. walking_controller:touchdown_verify_s:=0.0 for an A/B '
                        'against the config file')
    p.add_argument('--bag', action='store_true',
                   help='record every trial\'s topics to its run directory (to replay or trace '
                        'a fall afterwards; the recorder shares the cores: capture-to-plan '
                        '~60 ms slower, see the latency suite)')
    p.add_argument('--resume', nargs='?', const='same-code', default=None,
                   choices=('same-code', 'any-code'),
                   help='keep the trials already finished in --out with the same terrain-demo '
                        'command (and, unless "any-code", the same clean commit of the code) '
                        'and run the others: a long run in pieces')
    p.add_argument('--records', type=Path, default=None, metavar='DIR',
                   help='keep every counted trial\'s summary in DIR/<course>/<variant>/'
                        'seed<S>.json, and keep trials from there whose run directory is not '
                        'in --out (the full table: docs/closed-loop-table, committed, so the '
                        'table outlives the machine that ran its trials)')
    p.add_argument('--table-only', action='store_true',
                   help='run no trial: print (and --json) the table of the finished trials '
                        'already in --out for this command (any code revision unless '
                        '--resume same-code); the others are listed as not run')


# Per course: the simulated- and wall-time limits of a trial [s] by default (the limits the
# table's trials have run with). FROG-I crossed the stones in 340-385 s of simulated time,
# LittleDog rocks-6cm in 85-110 s; a trial took about 5.2 s of wall time per simulated second,
# 6.5 s since the world waits while the simulator renders (session 48): the rocks' 900 s still
# hold 135 s simulated (records of earlier trials name 900 s: kept), the stones' limit was
# raised from 2500 s (385 s simulated would now take 2,500 s) before any stones record.
LIMITS = {'rocks-6cm': (200.0, 900.0), 'rocks-12cm': (200.0, 900.0),
          'stones-15cm': (480.0, 3300.0)}


def limits(args, course: str) -> 'tuple[float, float]':
    """A trial's ``(max_sim_time, timeout)``: the options, else the course's defaults."""
    sim, wall = LIMITS[course]
    return (sim if args.max_sim_time is None else args.max_sim_time,
            wall if args.timeout is None else args.timeout)


# Flat ground kept between the camera's first view and the rough section (see effective_gap).
VIEW_MARGIN_M = 0.05


def effective_gap(robot: str, front_gap: float) -> float:
    """The front gap a trial starts with: ``front_gap``, or more where the camera never sees
    that much ground ahead of the front feet (:attr:`RobotModel.nearest_ground_seen_m`; the
    view moves on with the robot, so that band is seen by no capture). FROG-I's band is
    0.52 m: with 0.3 m its trials walked the first 0.22 m of stones on filled guesses, which
    no perception could have shown it (stones seed 146's slides). The gap is then the band
    plus ``VIEW_MARGIN_M``; LittleDog's band (0.13 m) is inside the usual 0.3 m."""
    from terrain_perception.robot_model import load_robot_model
    m = load_robot_model(robot)
    blind = m.nearest_ground_seen_m - float(m.nominal_feet[:, 0].max())
    return max(float(front_gap), round(blind + VIEW_MARGIN_M, 3))


def _start_x(course: str, robot: str, front_gap) -> 'float | None':
    """Base x that puts the front feet :func:`effective_gap` before the rough section (None:
    the launch file's default)."""
    if front_gap is None:
        return None
    from terrain_perception.robot_model import load_robot_model
    from terrain_perception.terrain import COURSE_CLASSES
    front = float(load_robot_model(robot).nominal_feet[:, 0].max())
    return COURSE_CLASSES[course].approach_m - front - effective_gap(robot, front_gap)


def demo_program() -> str:
    """The ``terrain-demo`` the trials run: the one installed next to this Python."""
    return str(Path(sys.executable).parent / 'terrain-demo')


def trial_command(args, course: str, robot: str, variant: str, seed: int,
                  run_dir: Path) -> list:
    """The ``terrain-demo`` command line of one trial."""
    max_sim, timeout = limits(args, course)
    cmd = [demo_program(), '--robot', robot,
           '--course', course, '--seed', str(seed), '--run-dir', str(run_dir),
           *([] if getattr(args, 'bag', False) else ['--no-bag']),
           '--quiet', '--max-sim-time', str(max_sim), '--timeout', str(timeout),
           '--image-scale', str(args.image_scale), *VARIANTS[variant]]
    start_x = _start_x(course, robot, args.front_gap)
    if start_x is not None:
        cmd += ['--arg', f'start_x:={start_x:.3f}']
    for text in getattr(args, 'param', None) or []:
        cmd += ['--param', text]
    return cmd


def _same_command(summary_command: str, cmd: list) -> bool:
    """Whether a run's recorded ``command`` (``terrain-demo ARGS``, as the demo writes it) is
    ``cmd`` but for the demo's path (which may differ between venvs) and the ``--run-dir``
    (the summary is in it, wherever the table's folder was given from or moved to)."""
    args = [str(a) for a in cmd[1:]]
    i = args.index('--run-dir')
    head = ' '.join(args[:i + 1]) + ' '
    tail = ' '.join(args[i + 2:])
    got = summary_command.partition(' ')[2]
    return (got.startswith(head) and len(got) > len(head) + len(tail)
            and (not tail or got.endswith(' ' + tail)))


def record_path(records: Path, course: str, variant: str, seed: int) -> Path:
    """Where ``--records`` keeps one trial's summary."""
    return Path(records) / course / variant / f'seed{seed}.json'


def finished_trial(run_dir: Path, cmd: list, revision: Optional[str],
                   resume: Optional[str]) -> 'tuple[Optional[dict], str]':
    """``(summary, why)``: the summary of the trial already run in ``run_dir`` if ``--resume``
    keeps it (same command, a run that ended by itself and, for ``same-code``, the clean commit
    ``revision``); else None and why not (``''``: nothing there to keep or replace).
    ``run_dir`` may also be a record file (``--records``): the summary itself."""
    f = run_dir if run_dir.suffix == '.json' else run_dir / 'summary.json'
    if not f.is_file():
        return None, ''
    try:
        s = json.loads(f.read_text())
    except (OSError, ValueError) as e:
        return None, f'its {f.name} cannot be read ({e})'
    if not _same_command(str(s.get('command', '')), cmd):
        return None, f'it ran another command ({s.get("command")!r})'
    if str(s.get('end_reason', '')).startswith('interrupted'):
        return None, f'it was {s.get("end_reason")}'
    rev = s.get('code_revision')
    if resume != 'any-code':
        if not rev or rev.endswith('+dirty'):
            return None, f'its code revision is {rev or "unknown"}'
        if rev != revision:
            return None, f'it ran the code of {rev[:10]}, this is {str(revision)[:10]}'
    return s, ''


class Stop:
    """Ctrl-C / SIGTERM while the suite runs: the first stops the trial under way gracefully
    (SIGINT to its demo, which writes its report) and starts no other; a second one is passed
    on too (the demo then stops at once)."""

    def __init__(self) -> None:
        self.reason: Optional[str] = None
        self.proc: Optional[subprocess.Popen] = None

    def on_signal(self, signum, _frame) -> None:
        name = signal.Signals(signum).name
        if self.reason is None:
            self.reason = name
            print(f'\n{name}: stopping the trial under way and writing the table of the '
                  'finished ones (again to stop the trial at once)', flush=True)
        if self.proc is not None and self.proc.poll() is None:
            try:
                self.proc.send_signal(signal.SIGINT)
            except ProcessLookupError:
                pass


_PR_SET_PDEATHSIG = 1


def _demo_child_setup() -> None:
    # In the demo before exec: its own process group (a terminal's Ctrl-C reaches the suite,
    # which passes it on once; the demo's second Ctrl-C means "stop at once"), and SIGTERM,
    # which it handles like Ctrl-C, if the suite dies. Not a new session: that would move it
    # to another scheduling autogroup than a plain terrain-demo run.
    os.setpgid(0, 0)
    try:
        ctypes.CDLL('libc.so.6', use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def run_demo(cmd: list, timeout_s: float, stop: Stop) -> 'tuple[int, str]':
    """Run one trial's demo; return its exit code and output. Past ``timeout_s`` (the demo's
    own wall-time limit did not end it) it gets SIGINT, then SIGKILL a minute later."""
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=dict(os.environ),
                            preexec_fn=_demo_child_setup)
    stop.proc = proc
    try:
        try:
            out, _ = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)
            try:
                out, _ = proc.communicate(timeout=60.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, _ = proc.communicate()
            out = ((out or '')
                   + f'\nterrain-bench: the demo ran past {timeout_s:.0f} s and was stopped')
    finally:
        stop.proc = None
    return proc.returncode, out or ''


def _set_aside(run_dir: Path) -> Path:
    """Move a finished trial's run directory out of the way (never delete results)."""
    dest = run_dir.with_name(run_dir.name + time.strftime('.replaced-%Y%m%d-%H%M%S'))
    run_dir.rename(dest)
    return dest


def _trial(args, course: str, robot: str, variant: str, seed: int, out: Path,
           revision: Optional[str] = None, stop: Optional[Stop] = None) -> dict:
    run_dir = out / course / variant / f'seed{seed}'
    cmd = trial_command(args, course, robot, variant, seed, run_dir)
    start_x = _start_x(course, robot, args.front_gap)
    row = {'course': course, 'robot': robot, 'variant': variant, 'seed': seed,
           'start_x': None if start_x is None else round(start_x, 3),
           'front_gap_m': (None if args.front_gap is None
                           else effective_gap(robot, args.front_gap)),
           'run_dir': str(run_dir)}
    table_only = getattr(args, 'table_only', False)
    resume = getattr(args, 'resume', None) or ('any-code' if table_only else None)
    records = getattr(args, 'records', None)
    record = record_path(records, course, variant, seed) if records is not None else None
    kept, why = finished_trial(run_dir, cmd, revision, resume)
    if kept is None and record is not None and not (run_dir / 'summary.json').is_file():
        kept, why_record = finished_trial(record, cmd, revision, resume)
        if kept is not None:
            row['from_record'] = str(record)
        elif why_record:
            why = f'its record: {why_record}'
            row['record_replaced_because'] = why_record
    if kept is not None:
        s = kept
        row.update(resumed=True, wall_s=s.get('wall_time_s'), exit_code=None)
    elif table_only:
        if not why and run_dir.exists():
            why = 'no summary.json: under way, or stopped before its report'
        row.update(ok=False, not_run=True, error=why or 'not run yet', code_revision=None)
        return row
    else:
        if (run_dir / 'summary.json').is_file():       # only with --resume (run checks)
            row['replaced'] = str(_set_aside(run_dir))
            row['replaced_because'] = why
        t0 = time.monotonic()
        stop = stop or Stop()
        max_sim, timeout = limits(args, course)
        print(f'  {course:12s} {variant:7s} seed {seed:4d}: running ({time.strftime("%H:%M")}; '
              f'at most {max_sim:.0f} s simulated, {timeout:.0f} s wall; {run_dir})', flush=True)
        code, output = run_demo(cmd, timeout + 300, stop)
        row.update(resumed=False, wall_s=round(time.monotonic() - t0, 1), exit_code=code)
        summary_file = run_dir / 'summary.json'
        if not summary_file.is_file():
            tail = output.strip().splitlines()[-3:]
            row.update(ok=False, error='no summary.json: ' + ' | '.join(tail),
                       code_revision=revision, interrupted=stop.reason is not None)
            return row
        s = json.loads(summary_file.read_text())
        if str(s.get('end_reason', '')).startswith('interrupted'):
            row.update(ok=False, interrupted=True, error=f'{s["end_reason"]} at '
                       f'{s.get("sim_time_s")} s sim', code_revision=s.get('code_revision'))
            return row
    if record is not None and 'from_record' not in row:
        row['recorded'] = _write_record(record, s)
    row.update(ok=True, code_revision=s.get('code_revision'),
               crossed=bool(s.get('crossed')), falls=s.get('falls'),
               distance_m=s.get('distance_m'), sim_time_s=s.get('sim_time_s'),
               mean_speed_mps=s.get('mean_speed_mps'), end_reason=s.get('end_reason'),
               complete_graph=s.get('complete_graph'),
               latencies_ms=s.get('capture_to_plan_ms_all') or [],
               fall_analysis=[fa.get('text') for fa in s.get('fall_analysis') or []],
               success=bool(s.get('crossed')) and not s.get('falls'))
    return row


def _write_record(record: Path, summary: dict) -> str:
    """Write one counted trial's summary to its record unless the record already holds it:
    ``'new'``, ``'replaced'`` or ``'same'``."""
    text = json.dumps(summary, indent=1, sort_keys=True) + '\n'
    if record.is_file():
        try:
            if json.loads(record.read_text()) == summary:
                return 'same'
        except (OSError, ValueError):
            pass
        state = 'replaced'
    else:
        state = 'new'
    record.parent.mkdir(parents=True, exist_ok=True)
    tmp = record.with_name(record.name + '.tmp')
    tmp.write_text(text)
    tmp.replace(record)
    return state


def _check_records(args, out: Path) -> None:
    """Refuse to run over the records without ``--resume``, and to run or tabulate against
    records of another command at all: a record is replaced when its trial is run again with
    other code, never by another experiment (an A/B with ``--param``, other limits) given the
    table's ``--records`` by mistake."""
    records = getattr(args, 'records', None)
    if records is None:
        return
    held = [(c, v, seed, record_path(records, c, v, seed)) for c in args.courses
            for v in args.variants for seed in range(args.first_seed, args.first_seed + args.seeds)
            if record_path(records, c, v, seed).is_file()]
    if held and getattr(args, 'resume', None) is None and not getattr(args, 'table_only', False):
        raise ValueError(f'{records} already records {len(held)} trial(s) ({held[0][3]}, ...): '
                         'pass --resume to keep them (trials that do not match are run again and '
                         'their records replaced)')
    other = []
    for c, v, seed, f in held:
        cmd = trial_command(args, c, COURSES[c], v, seed, out / c / v / f'seed{seed}')
        try:
            ran = str(json.loads(f.read_text()).get('command', ''))
        except (OSError, ValueError) as e:
            raise ValueError(f'record {f} cannot be read ({e})') from e
        if not _same_command(ran, cmd):
            other.append((f, ran))
    if other:
        f, ran = other[0]
        raise ValueError(f'{records} holds {len(other)} record(s) of another terrain-demo command '
                         f'({f}: {ran!r}); records are replaced only by the same command: give '
                         'this run its own --records folder, or remove those records')


def run(args) -> dict:
    if args.quick:
        args.courses, args.variants, args.seeds = ['rocks-6cm'], ['full'], 1
        args.max_sim_time, args.image_scale = min(args.max_sim_time or 10.0, 10.0), 0.5
    for text in getattr(args, 'param', None) or []:
        # A malformed override fails here, not after the first trial (terrain-demo checks
        # the node name against the launch file).
        head, sep, _ = text.partition(':=')
        if not sep or head.count(':') != 1 or '' in head.split(':'):
            raise ValueError(f'--param {text!r} is not of the form NODE:NAME:=VALUE '
                             f'(e.g. walking_controller:touchdown_verify_s:=0.0)')
    table_only = getattr(args, 'table_only', False)
    if table_only and getattr(args, 'records', None) is None and (
            args.out is None or not args.out.is_dir()):
        raise ValueError('--table-only tabulates the trials in --out (or --records): '
                         + ('give --out' if args.out is None else f'{args.out} does not exist'))
    out = args.out or Path('runs') / time.strftime('bench-%Y%m%d-%H%M%S')
    if getattr(args, 'resume', None) is None and not getattr(args, 'table_only', False):
        done = [str(out / c / v / f'seed{s}') for c in args.courses for v in args.variants
                for s in range(args.first_seed, args.first_seed + args.seeds)
                if (out / c / v / f'seed{s}' / 'summary.json').is_file()]
        if done:
            raise ValueError(f'{out} already holds {len(done)} finished trial(s) ({done[0]}, '
                             '...): pass --resume to keep them (trials that do not match are '
                             'moved aside and run again) or choose another --out')
    _check_records(args, out)
    if not table_only:
        out.mkdir(parents=True, exist_ok=True)
    from terrain_perception.bench.pipeline import code_revision
    revision = code_revision()
    if args.front_gap is not None:
        for course in args.courses:
            gap = effective_gap(COURSES[course], args.front_gap)
            if gap > args.front_gap:
                print(f'{course}: {COURSES[course]} never sees the ground within '
                      f'{gap - VIEW_MARGIN_M:.2f} m ahead of its front feet; its trials start '
                      f'{gap:.2f} m before the rough section, not {args.front_gap:.2f} m',
                      flush=True)
    stop = Stop()
    handlers = {sig: signal.signal(sig, stop.on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        trials = _run_trials(args, out, revision, stop)
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return _table(args, trials, revision, stop)


def _run_trials(args, out: Path, revision: Optional[str], stop: Stop) -> list:
    trials = []
    for course in args.courses:
        for variant in args.variants:
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                if stop.reason is not None:
                    return trials
                row = _trial(args, course, COURSES[course], variant, seed, out, revision, stop)
                trials.append(row)
                if row.get('not_run') and not Path(row['run_dir']).exists():
                    continue                    # --table-only: listed per cell below the table
                wall = row.get('wall_s')
                wall = '?' if wall is None else f'{wall:.0f}'
                kept = (('; kept from its record' if row.get('from_record') else
                         '; kept from an earlier run')
                        + ('' if row.get('code_revision') == revision else
                           f' of code {str(row.get("code_revision"))[:10]}')
                        if row.get('resumed') else '')
                if row.get('recorded') in ('new', 'replaced'):
                    kept += f'; record {row["recorded"]}'
                print(f'  {course:12s} {variant:7s} seed {seed:4d}: '
                      + (f'{"crossed" if row.get("crossed") else "NOT crossed":11s} '
                         f'falls {row.get("falls")} dist {row.get("distance_m")} m '
                         f'({row.get("end_reason")}; {wall} s wall{kept}'
                         f'{"" if row.get("complete_graph") else "; INCOMPLETE GRAPH"})'
                         if row['ok'] else
                         f'not run ({row["error"]})' if row.get('not_run') else
                         f'INTERRUPTED ({row["error"]}; not counted)' if row.get('interrupted')
                         else f'FAILED TO RUN: {row["error"]}'), flush=True)
                if row.get('recorded') == 'replaced' and row.get('record_replaced_because'):
                    print(f'      its earlier record was replaced: '
                          f'{row["record_replaced_because"]}', flush=True)
                if row.get('replaced'):
                    print(f'      an earlier trial was moved to {row["replaced"]}: '
                          f'{row["replaced_because"]}', flush=True)
                for text in row.get('fall_analysis') or []:
                    print(f'      {text}', flush=True)
    return trials


def _ranges(seeds: list) -> str:
    """``[100, 101, 102, 105]`` -> ``'100-102, 105'``."""
    parts, start = [], None
    for i, s in enumerate(seeds):
        if start is None:
            start = s
        if i + 1 == len(seeds) or seeds[i + 1] != s + 1:
            parts.append(f'{start}' if start == s else f'{start}-{s}')
            start = None
    return ', '.join(parts)


def _table(args, all_trials: list, revision: Optional[str], stop: Stop) -> dict:
    """Print and return the table of the trials that ended by themselves (an interrupted
    trial tells nothing about the system; ``--resume`` runs it again; with ``--table-only``
    the trials not run are left out likewise)."""
    trials = [r for r in all_trials if not r.get('interrupted') and not r.get('not_run')]
    planned = len(args.courses) * len(args.variants) * args.seeds
    success, falls, speed = {}, {}, {}
    for course in args.courses:
        for variant in args.variants:
            rows = [r for r in trials if r['course'] == course and r['variant'] == variant]
            ran = [r for r in rows if r['ok']]
            success.setdefault(course, {})[variant] = (
                round(sum(r['success'] for r in ran) / len(rows), 3) if rows else None)
            falls.setdefault(course, {})[variant] = int(sum(r['falls'] or 0 for r in ran))
            sp = [r['mean_speed_mps'] for r in ran if r.get('mean_speed_mps')]
            speed.setdefault(course, {})[variant] = round(float(np.mean(sp)), 4) if sp else None
    lat = np.asarray([v for r in trials if r['variant'] == 'full' and r['ok']
                      for v in r['latencies_ms']], dtype=float)
    print()
    print(f'{"course":12s} {"variant":8s} {"success":>8s} {"falls":>6s} {"speed m/s":>10s} '
          f'{"trials":>7s}')
    for course in args.courses:
        for variant in args.variants:
            n = sum(1 for r in trials if r['course'] == course and r['variant'] == variant)
            sr = success[course][variant]
            print(f'{course:12s} {variant:8s} {"-" if sr is None else f"{sr:.0%}":>8s} '
                  f'{falls[course][variant]:6d} '
                  f'{"-" if speed[course][variant] is None else speed[course][variant]:>10} '
                  f'{n:7d}')
    med = round(float(np.median(lat)), 1) if lat.size else None
    p95 = round(float(np.percentile(lat, 95)), 1) if lat.size else None
    if lat.size:
        print(f'capture-to-plan latency (full): median {med} ms, p95 {p95} ms over {lat.size} '
              'plans')
    else:
        print('capture-to-plan latency (full): not measured (no trial of the full system)')
    for course in args.courses:
        for variant in args.variants:
            seeds = [r['seed'] for r in all_trials if r['course'] == course
                     and r['variant'] == variant and r.get('not_run')]
            if seeds:
                print(f'{course} {variant}: not run, seeds {_ranges(seeds)}')
    if stop.reason is not None or len(trials) < planned:
        why = (f'stopped ({stop.reason})' if stop.reason is not None else
               'table only' if getattr(args, 'table_only', False) else
               'a trial was interrupted')
        print(f'{why}: {len(trials)} of {planned} trials finished; the same command with '
              '--resume' + (' instead of --table-only' if why == 'table only' else '')
              + ' runs the others')
    revisions = sorted({str(r.get('code_revision')) for r in trials})
    n_kept = sum(1 for r in trials if r.get('resumed'))
    n_records = sum(1 for r in trials if r.get('from_record'))
    if n_kept:
        print(f'{n_kept} of {len(trials)} trials kept from earlier runs (--resume)'
              + (f', {n_records} of them from their records ({args.records})'
                 if n_records else ''))
    if len(revisions) > 1:
        print(f'the trials ran {len(revisions)} code revisions: {", ".join(revisions)}')
    for r in all_trials:
        r.pop('latencies_ms', None)
    return {'stopped': stop.reason, 'trials_planned': planned,
            'trials_finished': len(trials), 'success': success, 'falls': falls, 'speed_mps': speed,
            'latency_ms_median': med, 'latency_ms_p95': p95, 'latency_samples': int(lat.size),
            'code_revision': revision, 'code_revisions': revisions,
            'trials': all_trials, 'settings': {'seeds': args.seeds, 'first_seed': args.first_seed,
                                           'resume': getattr(args, 'resume', None),
                                           'records': (None if getattr(args, 'records', None)
                                                       is None else str(args.records)),
                                           'max_sim_time_s': args.max_sim_time,
                                           'timeout_s': args.timeout,
                                           'limits_s': {c: limits(args, c)
                                                        for c in args.courses},
                                           'image_scale': args.image_scale,
                                           'front_gap_m': args.front_gap,
                                           'params': list(getattr(args, 'param', None) or [])}}
