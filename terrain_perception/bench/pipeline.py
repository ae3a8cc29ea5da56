"""Pipeline CPU: per-node CPU per capture on a recorded bag, library thread pools vs one thread.

``terrain-bench pipeline --bag DIR [--captures N]`` runs the profile tool
(``python -m terrain_ros.tools.pipeline_profile``: the stereo node, ICP mapper, terrain fill and
footstep planner in one process, the bag's recorded inputs replayed into their callbacks, CPU
per callback from ``time.process_time()``; see that module) twice, in subprocesses, on the same
bag and captures:

* ``default_pools`` (the baseline): ``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``,
  ``MKL_NUM_THREADS`` and ``OPENCV_FOR_THREADS_NUM`` removed from the environment, i.e. every
  library's default pool (one worker per core);
* ``node_env``: the four = 1, what ``terrain-launch`` gives node processes
  (``terrain_ros.env.node_env``);
* ``numpy_ik``: the node env with ``TERRAIN_IK_NUMBA=0``, the numpy leg IK instead of the
  compiled kernel (the baseline of ``_ik_kernel``: the planner's dry run of the controller's
  checks and the controller call it hundreds of times per plan);
* ``against`` (only with ``--against REV``): the node env running the code of git revision
  ``REV`` of this repository (e.g. the commit before a speed-up), checked out into a temporary
  worktree that is removed afterwards: a before/after of a code change on the same bag in the
  same run. Its per-stage medians are printed beside the current tree's with the ratios.

It prints both tables, then the per-stage medians side by side and the ratios baseline / node
env of the ICP mapper's update, the contact patches and all CPU per capture. Without ``--bag``
it first records one with a short ``terrain-demo`` run (default course, ``--max-sim-time``
``--sim-time``, into ``runs/bench/pipeline-demo``; an existing bag there is reused) and says
so. ``--quick``: 15 captures. The suite only starts processes and reads their JSON; it imports
nothing from ROS.

JSON: ``variants`` (name -> ``threads``, ``stage_median_ms`` per stage, ``cpu_ms_per_capture``,
``chain_cpu_ms_median_sum``, ``chain_cpu_ms_per_capture_median``), ``icp_cpu_ratio``,
``patches_cpu_ratio``, ``total_cpu_ratio``, ``chain_cpu_ratio`` (baseline / node env),
``chain_cpu_ms_median`` (node env: the sum of the chain's medians), ``bag``, ``captures``,
``recorded_bag``; with ``--against``: ``against`` (``rev``, ``commit``, the variant's figures)
and ``against_ratio`` (stage -> the revision's median / the current tree's, and ``chain``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict, Iterator, Optional, Tuple

# The pools terrain_ros.env.node_env sets to one thread (NODE_THREAD_DEFAULTS; the core may not
# import terrain_ros, test_pipeline_profile checks that the two lists agree).
THREAD_VARS = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS',
               'OPENCV_FOR_THREADS_NUM')
VARIANTS = ('default_pools', 'node_env', 'numpy_ik')
REPO = Path(__file__).resolve().parents[2]
VARIANT_TITLES = {'default_pools': 'baseline: the libraries\' default thread pools '
                                   '(OMP/OPENBLAS/MKL_NUM_THREADS, OPENCV_FOR_THREADS_NUM '
                                   'unset)',
                  'node_env': 'node env: OMP/OPENBLAS/MKL_NUM_THREADS=1, '
                              'OPENCV_FOR_THREADS_NUM=1 (terrain-launch)',
                  'numpy_ik': 'node env with the numpy leg IK (TERRAIN_IK_NUMBA=0)'}
STAGES = ('stereo', 'icp', 'icp_model', 'fill', 'plan_map', 'patches', 'plan_goal')
DEMO_RUN_DIR = Path('runs') / 'bench' / 'pipeline-demo'
DEFAULT_DOMAIN = '47'
TOOL = 'terrain_ros.tools.pipeline_profile'


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument('--bag', type=Path, default=None,
                   help='rosbag2 directory of a terrain-demo run (default: record one)')
    p.add_argument('--captures', type=int, default=None,
                   help='captures counted per variant (default 60; --quick 15)')
    p.add_argument('--against', metavar='REV', default=None,
                   help='also profile the code of this git revision (a commit before a change) '
                        'in a temporary worktree, with the node env, and print its per-stage '
                        'CPU beside the current tree\'s')
    p.add_argument('--sim-time', type=float, default=25.0,
                   help='without --bag: simulated seconds of the recording run (default 25)')
    p.add_argument('--run-dir', type=Path, default=DEMO_RUN_DIR,
                   help=f'without --bag: run directory of the recording (default {DEMO_RUN_DIR})')


def _env(variant: Optional[str] = None) -> Dict[str, str]:
    env = dict(os.environ)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('ROS_DOMAIN_ID', DEFAULT_DOMAIN)
    if variant == 'default_pools':
        for k in THREAD_VARS:
            env.pop(k, None)
    elif variant in ('node_env', 'numpy_ik'):
        env.update({k: '1' for k in THREAD_VARS})
    if variant == 'numpy_ik':
        env['TERRAIN_IK_NUMBA'] = '0'
    elif variant is not None:
        env.pop('TERRAIN_IK_NUMBA', None)
    return env


def record_bag(run_dir: Path, sim_time: float) -> Path:
    """A bag from a short terrain-demo run (reused when ``run_dir`` already holds one)."""
    bag = run_dir / 'bag'
    if (bag / 'metadata.yaml').is_file():
        print(f'no --bag: reusing the bag of an earlier recording run, {bag}', flush=True)
        return bag
    if run_dir.exists() and any(run_dir.iterdir()):
        raise ValueError(f'{run_dir} exists without a complete bag (an interrupted recording?); '
                         'remove it or pass --bag')
    env = _env()
    cmd = [str(Path(sys.executable).parent / 'terrain-demo'), '--run-dir', str(run_dir),
           '--max-sim-time', str(sim_time), '--timeout', '900', '--quiet']
    print(f'no --bag: recording one first (ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]}): '
          f'{" ".join(["terrain-demo"] + cmd[1:])}', flush=True)
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1200)
    if proc.returncode != 0 or not (bag / 'metadata.yaml').is_file():
        tail = ' | '.join((proc.stdout + proc.stderr).strip().splitlines()[-3:])
        raise ValueError(f'the recording run failed (exit code {proc.returncode}): {tail}')
    print(f'recorded {bag}', flush=True)
    return bag


def profile(bag: Path, captures: int, variant: str, code: Optional[Path] = None,
            title: Optional[str] = None) -> dict:
    """Run the profile tool in a subprocess with ``variant``'s environment (and, with ``code``,
    the package tree there instead of the installed one); its JSON figures."""
    env = _env(variant)
    if code is not None:
        env = code_env(code, env)
    with tempfile.TemporaryDirectory(prefix='bench-pipeline-') as tmp:
        out = Path(tmp) / 'profile.json'
        cmd = [sys.executable, '-m', TOOL, str(Path(bag).resolve()), '--captures',
               str(captures), '--json', str(out)]
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=3600,
                              cwd=str(code) if code is not None else None)
        if proc.returncode != 0 or not out.is_file():
            lines = proc.stderr.strip().splitlines() or proc.stdout.strip().splitlines()
            raise ValueError(f'the profile ({title or variant}) failed with exit code '
                             f'{proc.returncode}: {lines[-1] if lines else "no output"}')
        result = json.loads(out.read_text())
    print(f'\n=== {title or VARIANT_TITLES[variant]}', flush=True)
    print('\n'.join(ln for ln in proc.stdout.rstrip().splitlines()
                    if not ln.startswith('pipeline_profile: figures written')), flush=True)
    return result


def _git(*args: str, repo: Path = REPO) -> str:
    proc = subprocess.run(['git', '-C', str(repo), *args], capture_output=True, text=True,
                          timeout=30)
    if proc.returncode != 0:
        raise ValueError(f'git {" ".join(args)}: {proc.stderr.strip() or proc.stdout.strip()}')
    return proc.stdout.strip()


def code_revision(repo: Path = REPO) -> Optional[str]:
    """The commit the code under ``repo`` is checked out at, with ``+dirty`` when tracked files
    differ from it (their results cannot be traced to a commit); None outside a git checkout
    (an installed package)."""
    try:
        commit = _git('rev-parse', '--verify', 'HEAD', repo=repo)
        dirty = _git('status', '--porcelain', '--untracked-files=no', repo=repo)
    except (ValueError, OSError, subprocess.TimeoutExpired):
        return None
    return commit + ('+dirty' if dirty else '') if commit else None


def code_env(code: Path, env: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    """``env`` (default: this process's) with the package tree ``code`` first on PYTHONPATH."""
    env = dict(os.environ if env is None else env)
    env['PYTHONPATH'] = os.pathsep.join([str(code)] + [p for p in (
        env.get('PYTHONPATH') or '').split(os.pathsep) if p])
    return env


@contextlib.contextmanager
def revision_tree(rev: str) -> Iterator[Tuple[Path, str]]:
    """``(tree, commit)``: git revision ``rev`` of this repository checked out into a temporary
    worktree (its code and its config files), removed on exit."""
    commit = _git('rev-parse', '--verify', f'{rev}^{{commit}}')
    tmp = Path(tempfile.mkdtemp(prefix='bench-rev-'))
    tree = tmp / 'tree'
    try:
        _git('worktree', 'add', '--detach', str(tree), commit)
        yield tree, commit
    finally:
        subprocess.run(['git', '-C', str(REPO), 'worktree', 'remove', '--force', str(tree)],
                       capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)


def profile_revision(bag: Path, captures: int, rev: str) -> dict:
    """:func:`profile` (node env) of the code of git revision ``rev`` (:func:`revision_tree`)."""
    with revision_tree(rev) as (tree, commit):
        r = profile(bag, captures, 'node_env', code=tree,
                    title=f'node env, the code of {rev} ({commit[:10]}), same bag')
    r['commit'] = commit
    return r


def _ratio(a, b) -> Optional[float]:
    return round(a / b, 3) if a is not None and b else None


def run(args) -> dict:
    captures = args.captures if args.captures is not None else (15 if args.quick else 60)
    if captures <= 0:
        raise ValueError('--captures must be positive')
    recorded = args.bag is None and not (args.run_dir / 'bag' / 'metadata.yaml').is_file()
    bag = record_bag(args.run_dir, args.sim_time) if args.bag is None else args.bag
    if not bag.exists():
        raise FileNotFoundError(f'bag {str(bag)!r} does not exist')
    against = getattr(args, 'against', None)
    res = {v: profile(bag, captures, v) for v in VARIANTS}
    if against:
        res['against'] = profile_revision(bag, captures, against)
    variants = {}
    for v, r in res.items():
        variants[v] = {
            'threads': r['threads'], 'compiled_ik': r.get('compiled_ik'),
            # (a stage the code of an --against revision did not have: None)
            'stage_median_ms': {s: r['stages'].get(s, {}).get('median_ms') for s in STAGES},
            'stage_p90_ms': {s: r['stages'].get(s, {}).get('p90_ms') for s in STAGES},
            'cpu_ms_per_capture': r['cpu_ms_per_capture'],
            'chain_cpu_ms_median_sum': r['chain_cpu_ms_median_sum'],
            'chain_cpu_ms_per_capture_median': r['chain_cpu_ms_per_capture_median'],
            'captures': r['captures'], 'wall_s': r['wall_s'], 'loadavg_1min': r['loadavg_1min'],
        }
    b, n = variants['default_pools'], variants['node_env']
    print('\n=== per capture, baseline / node env (CPU ms, medians)')
    print(f'{"stage":22s} {"default pools":>14s} {"node env":>10s} {"ratio":>7s}')
    rows = [(s, b['stage_median_ms'][s], n['stage_median_ms'][s]) for s in STAGES]
    rows += [('CPU per capture (all)', b['cpu_ms_per_capture'], n['cpu_ms_per_capture']),
             ('chain, sum of medians', b['chain_cpu_ms_median_sum'],
              n['chain_cpu_ms_median_sum'])]
    for name, x, y in rows:
        r = _ratio(x, y)
        print(f'{name:22s} {"-" if x is None else f"{x:.1f}":>14s} '
              f'{"-" if y is None else f"{y:.1f}":>10s} {"-" if r is None else f"{r:.2f}":>7s}')
    out = {
        'bag': str(bag), 'recorded_bag': recorded, 'captures': captures,
        'variants': variants,
        'icp_cpu_ratio': _ratio(b['stage_median_ms']['icp'], n['stage_median_ms']['icp']),
        'patches_cpu_ratio': _ratio(b['stage_median_ms']['patches'],
                                    n['stage_median_ms']['patches']),
        'total_cpu_ratio': _ratio(b['cpu_ms_per_capture'], n['cpu_ms_per_capture']),
        'chain_cpu_ratio': _ratio(b['chain_cpu_ms_median_sum'], n['chain_cpu_ms_median_sum']),
        'chain_cpu_ms_median': n['chain_cpu_ms_median_sum'],
        'chain_cpu_ms_median_default_pools': b['chain_cpu_ms_median_sum'],
        'cpu_ms_per_capture': n['cpu_ms_per_capture'],
        'cpu_ms_per_capture_default_pools': b['cpu_ms_per_capture'],
        'icp_cpu_ms_median': n['stage_median_ms']['icp'],
        'icp_cpu_ms_median_default_pools': b['stage_median_ms']['icp'],
    }
    k = variants['numpy_ik']
    out['plan_map_cpu_ms_median'] = n['stage_median_ms']['plan_map']
    out['plan_map_cpu_ms_median_numpy_ik'] = k['stage_median_ms']['plan_map']
    out['plan_map_ik_ratio'] = _ratio(k['stage_median_ms']['plan_map'],
                                      n['stage_median_ms']['plan_map'])
    out['chain_cpu_ms_median_numpy_ik'] = k['chain_cpu_ms_median_sum']
    print(f'planner map callback (replan + dry run): numpy IK {k["stage_median_ms"]["plan_map"]}'
          f' ms, compiled IK {n["stage_median_ms"]["plan_map"]} ms -> {out["plan_map_ik_ratio"]}x;'
          f' chain {k["chain_cpu_ms_median_sum"]} -> {n["chain_cpu_ms_median_sum"]} ms')
    if against:
        a = variants.pop('against')
        ratios = {st: _ratio(a['stage_median_ms'][st], n['stage_median_ms'][st])
                  for st in STAGES}
        ratios['chain'] = _ratio(a['chain_cpu_ms_median_sum'], n['chain_cpu_ms_median_sum'])
        out['against'] = {'rev': against, 'commit': res['against']['commit'], **a}
        out['against_ratio'] = ratios
        print(f'\n=== per capture, {against} / the current tree (node env; CPU ms, medians)')
        print(f'{"stage":22s} {against[:14]:>14s} {"current":>10s} {"ratio":>7s}')
        rows = [(st, a['stage_median_ms'][st], n['stage_median_ms'][st]) for st in STAGES]
        rows += [('chain, sum of medians', a['chain_cpu_ms_median_sum'],
                  n['chain_cpu_ms_median_sum'])]
        for name, x, y in rows:
            r = _ratio(x, y)
            print(f'{name:22s} {"-" if x is None else f"{x:.1f}":>14s} '
                  f'{"-" if y is None else f"{y:.1f}":>10s} '
                  f'{"-" if r is None else f"{r:.2f}":>7s}')
    print(f'ICP update CPU ratio (baseline / node env) {out["icp_cpu_ratio"]}, patches '
          f'{out["patches_cpu_ratio"]}, all CPU per capture {out["total_cpu_ratio"]}'
          + (f'; bag recorded by this run: {bag}' if recorded else f'; bag: {bag}'))
    return out
