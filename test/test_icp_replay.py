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

    def fake(bag, params, slip=None, code=None):
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


def test_suite_compares_a_git_revision_with_the_current_tree(tmp_path, monkeypatch):
    """--against REV: the baseline runs the tool from a worktree of that revision (its code
    and config; removed afterwards), the current tree from here; a revision git does not
    know is one clear error."""
    import subprocess as sp
    from terrain_perception.bench.pipeline import REPO
    head = sp.run(['git', '-C', str(REPO), 'rev-parse', 'HEAD'], capture_output=True,
                  text=True, check=True).stdout.strip()
    seen = {}

    def fake(bag, params, slip=None, code=None):
        if code is not None:
            got = sp.run(['git', '-C', str(code), 'rev-parse', 'HEAD'], capture_output=True,
                         text=True, check=True).stdout.strip()
            seen['tree'] = (code, got, (code / 'config' / 'icp_mapper.yaml').is_file())
        return {'captures': 10, 'accepted': 10, 'yaw_err_deg_max': 3.0,
                'yaw_err_deg_final': 1.0, 'pos_err_m_max': 0.05, 'pos_err_m_final': 0.01,
                'yaw_err_deg_rms': 1.5 if code is not None else 1.0,
                'pos_err_m_rms': 0.02 if code is not None else 0.01}
    monkeypatch.setattr(icp_replay, '_run_tool', fake)

    class Args:
        bag = [tmp_path]
        against = 'HEAD'
    out = icp_replay.run(Args())
    tree, commit, has_config = seen['tree']
    assert commit == head and has_config
    assert not tree.exists()
    assert out['against'] == {'rev': 'HEAD', 'commit': head}
    assert set(out['bags'][str(tmp_path)]) == {'HEAD', 'current'}
    assert out['yaw_rms_ratio'][str(tmp_path)] == pytest.approx(1.5)
    assert out['pos_rms_ratio'][str(tmp_path)] == pytest.approx(2.0)
    Args.against = 'no-such-revision-here'
    with pytest.raises(ValueError, match='no-such-revision-here'):
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


def test_slip_option_is_checked_and_the_recovery_is_counted_from_the_slip(tmp_path):
    import numpy as np
    from terrain_ros.tools.common import ToolError
    from terrain_ros.tools.icp_replay import _after_slip, parse_slip
    assert parse_slip('40.5:0.05,-0.01') == (40.5, 0.05, -0.01)
    for bad in ('40', '40:0.05', 'a:0.05,0', '40:nan,0'):
        with pytest.raises(ToolError, match='--slip'):
            parse_slip(bad)
    res = _tool(tmp_path, '--slip', '40:0.05')
    assert res.returncode == 1 and 'expected T:DX,DY' in res.stderr
    t = [10.0, 20.0, 30.0, 40.0, 50.0, 60.0]
    err = np.array([0.002, 0.003, 0.05, 0.04, 0.008, 0.004])
    f = _after_slip((25.0, 0.05, 0.0), t, err)
    # captures after the slip: 0.05 0.04 0.008 0.004: under 2 cm from the third on
    assert f['captures_after_slip'] == 4 and f['captures_to_recover'] == 3
    assert _after_slip((5.0, 0.05, 0.0), t, err)['captures_to_recover'] == 5
    assert _after_slip((45.0, 0.05, 0.0), t, err)['captures_to_recover'] == 1
    assert f['pos_err_m_rms_after_slip'] == pytest.approx(
        np.sqrt(np.mean(err[2:] ** 2)))
    assert _after_slip((25.0, 0.05, 0.0), t, np.full(6, 0.05))['captures_to_recover'] is None
    with pytest.raises(ToolError, match='no capture after it'):
        _after_slip((70.0, 0.05, 0.0), t, err)
