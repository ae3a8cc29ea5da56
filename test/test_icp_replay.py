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


def test_the_final_map_is_scored_against_the_true_terrain():
    """_map_figures: RMSE on observed cells and the cells standing more than 5 cm above
    (phantoms) or below (pits) the terrain the bag recorded."""
    import numpy as np
    from terrain_perception.grid import GridMap
    from terrain_ros.conversions import grid_to_msg
    from terrain_ros.tools.icp_replay import _map_figures
    truth = GridMap(0.01, (0.0, 0.0), (40, 40), {'elevation': np.zeros((40, 40), np.float32)})
    h = np.full((20, 20), 0.002, np.float32)
    h[3, 4], h[5, 6], h[7, 8] = 0.19, 0.12, -0.08          # two phantoms, one pit
    h[10:, :] = np.nan                                      # unobserved
    fine = GridMap(0.01, (0.1, 0.1), (20, 20), {'elevation': h})
    f = _map_figures(fine, grid_to_msg(truth, 0.0))
    assert f['map_cells'] == 200
    assert f['map_cells_above_5cm'] == 2 and f['map_cells_below_5cm'] == 1
    want = np.sqrt((197 * 0.002 ** 2 + 0.19 ** 2 + 0.12 ** 2 + 0.08 ** 2) / 200)
    assert f['map_rmse_m'] == pytest.approx(want, rel=1e-4)
    assert _map_figures(fine, None) == {} and _map_figures(None, grid_to_msg(truth, 0.0)) == {}
