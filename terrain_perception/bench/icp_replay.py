"""ICP replay: a closed-loop run's mapper inputs replayed, pose errors against ground truth.

``terrain-bench icp-replay --bag RUN/bag [--bag RUN2/bag ...]`` runs the replay tool
(``python -m terrain_ros.tools.icp_replay``: the ICP mapper node's callbacks fed, in bag order,
with a ``terrain-demo`` bag's dead reckoning, joint states, IMU and stereo clouds; see that
module) in subprocesses, twice per bag:

* ``odometry_prior`` (the baseline): ``use_imu_rotation_prior:=false``, the prior's rotation is
  dead reckoning's, as before the eleventh session;
* ``imu_rotation_prior``: the default, the prior turned by the IMU's attitude change since the
  last accepted capture.

Per bag and variant it prints the accepted captures and the yaw and position errors of the
mapper's poses against ``/ground_truth/odom`` (RMS, max, final), then the ratio of the yaw-error
RMS baseline / default. The suite only starts processes and reads their JSON; it imports
nothing from ROS. ``--quick`` is accepted and changes nothing (the bag sets the size).

With ``--param NAME:=VALUE`` (repeatable) the two variants are instead ``default`` (the
baseline: ``config/icp_mapper.yaml``) and ``candidate`` (the same plus those parameters), and
the ratios are baseline / candidate of the yaw and position error RMS: a way to try a mapper
parameter on recorded runs in seconds instead of closed-loop trials in minutes (the replay is
open loop: the recorded dead reckoning does not react to the candidate's poses).

With ``--against REV`` the two variants are instead ``REV`` (the baseline: the tool run from a
temporary worktree of git revision ``REV`` of this repository, its code and its config files)
and ``current`` (this tree), and the ratios are baseline / current of the yaw and position error
RMS: a code change's effect on localisation, rerunnable on the same recorded runs. ``--param``
then applies to both.

Per variant it also prints the final fine map against the bag's true terrain: height RMSE on
observed cells and the cells more than 5 cm above / below it (phantoms / pits).

With ``--slip T:DX,DY`` every replay gets a slip its dead reckoning did not see (the tool's
``--slip``: from bag time T on the odometry is moved by (-DX, -DY) m), and each variant also
prints the position error RMS after the slip and the capture from which it stays under the
tool's ``recovered_m`` (2 cm; ``captures_to_recover``): the mapper's recovery from a slip no
IMU reported, on real recorded clouds.

JSON: ``bags`` (path -> variant -> the tool's figures), ``yaw_rms_ratio`` (path -> baseline /
default or candidate) and, with ``--param``, ``pos_rms_ratio`` and ``params``; with
``--against``, ``pos_rms_ratio``, ``against`` (``rev``, ``commit``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict, Optional

from .pipeline import code_env, revision_tree

TOOL = 'terrain_ros.tools.icp_replay'
VARIANTS = {'odometry_prior': ['use_imu_rotation_prior:=false'], 'imu_rotation_prior': []}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument('--bag', type=Path, action='append', required=True,
                   help='rosbag2 directory of a terrain-demo run (repeatable)')
    p.add_argument('--param', action='append', default=[], metavar='NAME:=VALUE',
                   help='compare the config file (baseline) with it plus these mapper '
                        'parameters (repeatable) instead of the odometry / IMU rotation priors')
    p.add_argument('--against', metavar='REV', default=None,
                   help='compare the code of this git revision (a commit before a change; run '
                        'from a temporary worktree) with the current tree')
    p.add_argument('--slip', default=None, metavar='T:DX,DY',
                   help='inject a slip dead reckoning missed: from bag time T [s] on, move the '
                        'odometry by (-DX, -DY) [m] in every replay')


def _run_tool(bag: Path, params, slip=None, code: Optional[Path] = None) -> dict:
    """The replay tool's figures on ``bag`` (with ``code``: the package tree there)."""
    env = code_env(code) if code is not None else None
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'replay.json'
        cmd = [sys.executable, '-m', TOOL, str(Path(bag).resolve()), '--json', str(out)]
        for p in params:
            cmd += ['--param', p]
        if slip is not None:
            cmd += ['--slip', slip]
        res = subprocess.run(cmd, capture_output=True, text=True, env=env,
                             cwd=str(code) if code is not None else None)
        if res.returncode != 0 or not out.is_file():
            raise ValueError(f'{TOOL} on {bag} failed: {res.stderr.strip()[-500:]}')
        return json.loads(out.read_text())


def run(args) -> Dict:
    params = list(getattr(args, 'param', None) or [])
    for text in params:
        if ':=' not in text or not text.split(':=', 1)[0]:
            raise ValueError(f'--param {text!r} is not of the form NAME:=VALUE')
    against = getattr(args, 'against', None)
    with contextlib.ExitStack() as stack:
        code: Dict[str, Optional[Path]] = {}
        if against:
            tree, commit = stack.enter_context(revision_tree(against))
            variants = {against: params, 'current': params}
            code = {against: tree}
        else:
            variants = {'default': [], 'candidate': params} if params else VARIANTS
        out = _replay(args, variants, code)
        if against:
            out['against'] = {'rev': against, 'commit': commit}
    return out


def _replay(args, variants: Dict[str, list], code: Dict[str, Optional[Path]]) -> Dict:
    params = list(getattr(args, 'param', None) or [])
    base_name, ours_name = list(variants)
    bags, ratios, pos_ratios = {}, {}, {}
    print(f'{"bag / variant":52s} {"accepted":>10s} {"yaw RMS":>8s} {"max":>6s} '
          f'{"final":>6s} {"pos RMS cm":>10s} {"max":>6s} {"final":>6s} {"map mm":>7s} '
          f'{"+5cm":>5s} {"-5cm":>5s}')
    for bag in args.bag:
        if not bag.is_dir():
            raise FileNotFoundError(f'bag directory {bag} does not exist')
        per = {}
        for name, extra in variants.items():
            f = _run_tool(bag, extra, getattr(args, 'slip', None), code.get(name))
            per[name] = f
            print(f'{str(bag)[-30:] + " " + name:52s} {f["accepted"]:>4d}/{f["captures"]:<5d} '
                  f'{f["yaw_err_deg_rms"]:8.2f} {f["yaw_err_deg_max"]:6.2f} '
                  f'{f["yaw_err_deg_final"]:6.2f} {100 * f["pos_err_m_rms"]:10.2f} '
                  f'{100 * f["pos_err_m_max"]:6.2f} {100 * f["pos_err_m_final"]:6.2f} '
                  + (f'{1000 * f["map_rmse_m"]:7.1f} {f["map_cells_above_5cm"]:5d} '
                     f'{f["map_cells_below_5cm"]:5d}' if f.get('map_cells') else
                     f'{"-":>7s} {"-":>5s} {"-":>5s}'), flush=True)
            if 'slip' in f:
                rec, cm = f['captures_to_recover'], f'{100 * f["recovered_m"]:.0f} cm'
                print(f'{"":52s} after the slip: {f["captures_after_slip"]} captures, position '
                      f'error RMS {100 * f["pos_err_m_rms_after_slip"]:.2f} cm, '
                      + (f'under {cm} from capture {rec} on' if rec else f'over {cm} at the end'),
                      flush=True)
        base, ours = per[base_name], per[ours_name]
        ratios[str(bag)] = base['yaw_err_deg_rms'] / max(ours['yaw_err_deg_rms'], 1e-9)
        pos_ratios[str(bag)] = base['pos_err_m_rms'] / max(ours['pos_err_m_rms'], 1e-9)
        print(f'  error RMS, {base_name} / {ours_name}: yaw {ratios[str(bag)]:.2f}x, '
              f'position {pos_ratios[str(bag)]:.2f}x', flush=True)
        bags[str(bag)] = per
    out = {'bags': bags, 'yaw_rms_ratio': ratios}
    if params or code:
        out['pos_rms_ratio'] = pos_ratios
    if params:
        out['params'] = params
    if getattr(args, 'slip', None):
        out['slip'] = args.slip
    return out
