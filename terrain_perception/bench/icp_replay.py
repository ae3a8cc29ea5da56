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

JSON: ``bags`` (path -> variant -> the tool's figures), ``yaw_rms_ratio`` (path -> baseline /
default).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict

TOOL = 'terrain_ros.tools.icp_replay'
VARIANTS = {'odometry_prior': ['use_imu_rotation_prior:=false'], 'imu_rotation_prior': []}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument('--bag', type=Path, action='append', required=True,
                   help='rosbag2 directory of a terrain-demo run (repeatable)')


def _run_tool(bag: Path, params) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'replay.json'
        cmd = [sys.executable, '-m', TOOL, str(bag), '--json', str(out)]
        for p in params:
            cmd += ['--param', p]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0 or not out.is_file():
            raise ValueError(f'{TOOL} on {bag} failed: {res.stderr.strip()[-500:]}')
        return json.loads(out.read_text())


def run(args) -> Dict:
    bags, ratios = {}, {}
    print(f'{"bag / variant":52s} {"accepted":>10s} {"yaw RMS":>8s} {"max":>6s} '
          f'{"final":>6s} {"pos RMS cm":>10s} {"max":>6s} {"final":>6s}')
    for bag in args.bag:
        if not bag.is_dir():
            raise FileNotFoundError(f'bag directory {bag} does not exist')
        per = {}
        for name, params in VARIANTS.items():
            f = _run_tool(bag, params)
            per[name] = f
            print(f'{str(bag)[-30:] + " " + name:52s} {f["accepted"]:>4d}/{f["captures"]:<5d} '
                  f'{f["yaw_err_deg_rms"]:8.2f} {f["yaw_err_deg_max"]:6.2f} '
                  f'{f["yaw_err_deg_final"]:6.2f} {100 * f["pos_err_m_rms"]:10.2f} '
                  f'{100 * f["pos_err_m_max"]:6.2f} {100 * f["pos_err_m_final"]:6.2f}', flush=True)
        base, ours = per['odometry_prior'], per['imu_rotation_prior']
        ratios[str(bag)] = base['yaw_err_deg_rms'] / max(ours['yaw_err_deg_rms'], 1e-9)
        print(f'  yaw error RMS, odometry prior / IMU rotation prior: {ratios[str(bag)]:.1f}x')
        bags[str(bag)] = per
    return {'bags': bags, 'yaw_rms_ratio': ratios}
