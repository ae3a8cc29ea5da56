"""Cost features (paper 000 sec IV) and Shao's h + Dev(h) (paper 002 eq. 2-3) vs brute force."""

import numpy as np
import pytest

from terrain_perception.config import make_config
from terrain_perception.features import (CostConfig, cost_map, kolter_features, shao_dev,
                                         window_cells)

RES = 0.01


def _brute_features(h, kf, kl):
    """Per-cell loops over the same definitions (the oracle)."""
    nx, ny = h.shape
    rf, rl = kf // 2, kl // 2
    out = {k: np.full(h.shape, np.nan) for k in ('slope', 'roughness', 'height_differential')}
    for i in range(nx):
        for j in range(ny):
            if not np.isfinite(h[i, j]):
                continue
            us, vs, zs = [], [], []
            for u in range(-rf, rf + 1):
                for v in range(-rf, rf + 1):
                    a, b = i + u, j + v
                    if 0 <= a < nx and 0 <= b < ny and np.isfinite(h[a, b]):
                        us.append(u), vs.append(v), zs.append(h[a, b])
            zs = np.array(zs)
            A = np.c_[np.ones(len(us)), us, vs]
            if len(us) >= 3 and np.linalg.matrix_rank(A) == 3:
                coef = np.linalg.lstsq(A, zs, rcond=None)[0]
                out['slope'][i, j] = np.hypot(coef[1], coef[2]) / RES
            else:
                out['slope'][i, j] = 0.0
            out['roughness'][i, j] = zs.std()
            win = h[max(i - rl, 0):i + rl + 1, max(j - rl, 0):j + rl + 1]
            out['height_differential'][i, j] = max(np.nanmax(win) - h[i, j], 0.0)
    return out


def test_window_cells_is_odd_and_scaled():
    assert window_cells(0.03, 0.01) == 3
    assert window_cells(0.04, 0.01) == 5
    assert window_cells(0.001, 0.01) == 1
    with pytest.raises(ValueError, match='resolution'):
        window_cells(0.03, 0.0)


def test_plane_has_exact_slope_and_zero_roughness():
    i, j = np.meshgrid(np.arange(30), np.arange(25), indexing='ij')
    h = 0.3 * i * RES - 0.4 * j * RES + 0.05       # slope sqrt(0.09 + 0.16) = 0.5
    f = kolter_features(h, RES, CostConfig())
    np.testing.assert_allclose(f['slope'], 0.5, atol=1e-9)
    inner = (slice(4, -4), slice(4, -4))
    # std of a plane over a 3x3 window: only the linear spread, no noise
    expected_std = np.std(0.3 * np.array([-1, 0, 1] * 3) * RES
                          - 0.4 * np.repeat([-1, 0, 1], 3) * RES)
    np.testing.assert_allclose(f['roughness'][inner], expected_std, atol=1e-9)


@pytest.mark.parametrize('missing', [0.0, 0.3])
def test_features_match_brute_force_with_missing_cells(missing):
    rng = np.random.default_rng(3)
    h = rng.normal(0, 0.02, (23, 19)).cumsum(0) * 0.3
    h[rng.random(h.shape) < missing] = np.nan
    cfg = make_config(CostConfig, {'foot_window_m': 0.05, 'leg_window_m': 0.07})
    got = kolter_features(h, RES, cfg)
    ref = _brute_features(h, window_cells(0.05, RES), window_cells(0.07, RES))
    for name in ref:
        np.testing.assert_allclose(got[name], ref[name], atol=1e-9, equal_nan=True,
                                   err_msg=name)
    c = cost_map(h, RES, cfg)
    expected = (ref['slope'] + 20.0 * ref['roughness'] + 5.0 * ref['height_differential'])
    np.testing.assert_allclose(c, expected, rtol=1e-5, atol=1e-6, equal_nan=True)
    assert np.isnan(c[~np.isfinite(h)]).all()


def test_propagate_policy_marks_incomplete_windows():
    h = np.zeros((20, 20))
    h[10, 10] = np.nan
    cfg = make_config(CostConfig, {'nan_policy': 'propagate', 'foot_window_m': 0.03,
                                   'leg_window_m': 0.05})
    c = cost_map(h, RES, cfg)
    assert np.isnan(c[8:13, 8:13]).all()                 # leg window (5x5) reaches the hole
    assert np.isfinite(c[5:15, 3]).all()
    ignore = cost_map(h, RES, CostConfig())
    assert np.isfinite(ignore[9, 9]) and np.isnan(ignore[10, 10])


def test_step_edge_costs_more_than_flat():
    h = np.zeros((40, 40))
    h[20:, :] = 0.05
    c = cost_map(h, RES, CostConfig())
    assert c[5, 20] == pytest.approx(0.0, abs=1e-9)
    assert c[19, 20] > 0.2                               # foot of a 5 cm step
    assert c[19, 20] > c[20, 20] > c[35, 20] == pytest.approx(0.0, abs=1e-9)


def test_shao_dev_matches_equation_3():
    rng = np.random.default_rng(0)
    h = rng.normal(0, 0.01, (12, 9))
    dev = shao_dev(h)
    i, j = 5, 4
    expected = sum(abs(h[i, j] - h[i + a, j + b]) / (np.sqrt(2) if a and b else 2)
                   for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b)
    assert dev[i, j] == pytest.approx(expected, rel=1e-12)
    cfg = make_config(CostConfig, {'method': 'shao'})
    c = cost_map(h, RES, cfg)
    assert c[i, j] == pytest.approx(h[i, j] + expected, rel=1e-5)
    # a missing neighbour is ignored and the known ones rescaled to the full weight
    h2 = h.copy()
    h2[i - 1, j] = np.nan
    wall = 4 / np.sqrt(2) + 4 * 0.5
    partial = expected - abs(h[i, j] - h[i - 1, j]) / 2
    assert shao_dev(h2)[i, j] == pytest.approx(partial * wall / (wall - 0.5), rel=1e-12)
    assert np.isnan(shao_dev(h2, 'propagate')[i, j])


@pytest.mark.parametrize('bad, match', [
    (np.zeros(5), '2-D'), (np.zeros((0, 3)), '2-D'),
    (np.array([[0.0, np.inf], [0, 0]]), 'inf')])
def test_bad_heights_are_rejected(bad, match):
    with pytest.raises(ValueError, match=match):
        cost_map(bad, RES, CostConfig())


def test_bad_config_is_rejected():
    with pytest.raises(ValueError, match='method'):
        make_config(CostConfig, {'method': 'nope'})
    with pytest.raises(ValueError, match='resolution'):
        cost_map(np.zeros((4, 4)), -1.0, CostConfig())
