"""terrain-bench icp-replay and its tool: refused input is one clear error (the replay itself
needs a closed-loop bag, too large for the suite; docs/BENCHMARKS.md has its output)."""

import subprocess
import sys

import pytest

from terrain_perception.bench import icp_replay


def _tool(*args):
    return subprocess.run([sys.executable, '-m', icp_replay.TOOL, *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def test_missing_bag_and_bad_param_are_one_error_line(tmp_path):
    res = _tool(tmp_path / 'nope')
    assert res.returncode == 1 and 'cannot open bag' in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    res = _tool(tmp_path, '--param', 'use_imu_rotation_prior=false')
    assert res.returncode == 1 and "expected NAME:=VALUE" in res.stderr


def test_suite_refuses_a_missing_bag_directory(tmp_path):
    class Args:
        bag = [tmp_path / 'nope']
    with pytest.raises(FileNotFoundError, match='does not exist'):
        icp_replay.run(Args())
