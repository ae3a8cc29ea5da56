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


def test_suite_compares_the_config_with_candidate_parameters(tmp_path, monkeypatch):
    # --param: the variants are the config file and the config plus the parameters, and the
    # ratios are baseline / candidate (the tool itself is stubbed: a bag is too large here).
    calls = []

    def fake(bag, params):
        calls.append(list(params))
        worse = not params
        return {'captures': 10, 'accepted': 10, 'yaw_err_deg_rms': 2.0 if worse else 1.0,
                'yaw_err_deg_max': 3.0, 'yaw_err_deg_final': 1.0,
                'pos_err_m_rms': 0.04 if worse else 0.01, 'pos_err_m_max': 0.05,
                'pos_err_m_final': 0.01}
    monkeypatch.setattr(icp_replay, '_run_tool', fake)

    class Args:
        bag = [tmp_path]
        param = ['degeneracy_noise_gain:=3.0']
    out = icp_replay.run(Args())
    assert calls == [[], ['degeneracy_noise_gain:=3.0']]
    assert out['pos_rms_ratio'][str(tmp_path)] == pytest.approx(4.0)
    assert out['yaw_rms_ratio'][str(tmp_path)] == pytest.approx(2.0)
    assert set(out['bags'][str(tmp_path)]) == {'default', 'candidate'}
    Args.param = ['degeneracy_noise_gain=3']
    with pytest.raises(ValueError, match='NAME:=VALUE'):
        icp_replay.run(Args())
