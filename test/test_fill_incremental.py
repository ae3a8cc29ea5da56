"""TerrainFiller: the filled map the node publishes, its incremental updates and bad input."""

import numpy as np
import pytest
from scipy import ndimage

from terrain_perception.config import make_config
from terrain_perception.features import CostConfig, cost_map
from terrain_perception.fill import FillConfig, TerrainFiller, fill
from terrain_perception.grid import (COST, ELEVATION, FILLED, OBSERVED, UPPER_BOUND, GridMap)

RES = 0.01


def smooth(n, seed, amp=0.04):
    rng = np.random.default_rng(seed)
    h = ndimage.gaussian_filter(rng.normal(size=(n, n)), 3.0)
    return amp * h / np.abs(h).max() + amp


def make_grid(truth, seen, with_observed=True):
    layers = {ELEVATION: np.where(seen, truth, np.nan)}
    if with_observed:
        layers[OBSERVED] = seen.astype(np.float32)
    return GridMap.from_layers(RES, (0.0, 0.0), layers)


@pytest.fixture
def filler():
    lib = [smooth(50, s) for s in (1, 2)]
    return TerrainFiller(lib, RES, make_config(FillConfig, {'samples': 30}))


def two_holes(n=40):
    seen = np.ones((n, n), bool)
    seen[5:10, 5:12] = False        # hole A (low x, low y)
    seen[28:34, 26:33] = False      # hole B (far away)
    return seen


def test_output_layers(filler):
    truth = smooth(40, 0).astype(np.float32).astype(np.float64)
    seen = two_holes()
    cam = np.array([[0.2, 0.2, 0.3], [-0.1, 0.2, 0.3]])
    out = filler.update(make_grid(truth, seen), cam)
    assert set(out.layers) == {ELEVATION, OBSERVED, UPPER_BOUND, FILLED, COST}
    np.testing.assert_array_equal(out[OBSERVED], seen.astype(np.float32))   # fill != observed
    np.testing.assert_array_equal(out[FILLED], (~seen).astype(np.float32))
    np.testing.assert_array_equal(out[ELEVATION][seen], truth[seen].astype(np.float32))
    assert np.isfinite(out[ELEVATION]).all() and np.isfinite(out[COST]).all()
    assert np.isnan(out[UPPER_BOUND][seen]).all()
    np.testing.assert_allclose(out[COST], cost_map(out[ELEVATION], RES, CostConfig()),
                               atol=1e-5)


def test_only_the_changed_region_is_recomputed(filler):
    truth = smooth(40, 0)
    seen = two_holes()
    first = filler.update(make_grid(truth, seen))
    assert filler.last_region == (0, 40, 0, 40)
    # the same map again: nothing to do
    again = filler.update(make_grid(truth, seen))
    assert filler.last_region is None and filler.last_refilled == 0
    np.testing.assert_array_equal(again[ELEVATION], first[ELEVATION])
    # a new observation next to hole A: hole A is refilled, hole B keeps its fill
    seen2 = seen.copy()
    seen2[5, 5:12] = True
    second = filler.update(make_grid(truth, seen2))
    assert filler.last_refilled == int((~seen2[:20, :20]).sum())
    i0, i1, j0, j1 = filler.last_region
    assert i1 <= 25 and j1 <= 25                       # far from hole B
    np.testing.assert_array_equal(second[ELEVATION][25:, 20:], first[ELEVATION][25:, 20:])
    np.testing.assert_array_equal(second[COST][25:, 25:], first[COST][25:, 25:])
    # and the incremental cost equals a full recomputation
    np.testing.assert_allclose(second[COST], cost_map(second[ELEVATION], RES, CostConfig()),
                               atol=1e-5)


def test_grid_moved_by_whole_cells_keeps_the_untouched_fill(filler):
    truth = smooth(60, 0)
    seen = np.ones((60, 60), bool)
    seen[30:36, 30:37] = False
    a = filler.update(make_grid(truth[:40, :40], seen[:40, :40]))
    g = GridMap.from_layers(RES, (10 * RES, 0.0), {
        ELEVATION: np.where(seen, truth, np.nan)[10:50, :40],
        OBSERVED: seen[10:50, :40].astype(np.float32)})
    b = filler.update(g)
    # the hole at [30:36, 30:37] is 10 rows further down in the new grid and unchanged
    np.testing.assert_array_equal(b[ELEVATION][20:26, 30:37], a[ELEVATION][30:36, 30:37])
    assert filler.last_region[0] >= 20                 # only the new rows' neighbourhood


@pytest.mark.parametrize('case, match', [
    ('all_unknown', 'every cell is unknown'),
    ('nan_observed', 'marked observed have a NaN/inf'),
    ('inf_observed', 'marked observed have a NaN/inf'),
    ('inf_no_layer', 'inf'),
    ('bound_below', 'above their line-of-sight upper bound'),
    ('resolution', 'must match'),
    ('bad_observed', 'only 0 and 1'),
])
def test_bad_input_is_refused_and_keeps_the_state(filler, case, match):
    truth = smooth(40, 0)
    seen = two_holes()
    good = filler.update(make_grid(truth, seen))
    grid = make_grid(truth, seen)
    if case == 'all_unknown':
        grid = make_grid(truth, np.zeros_like(seen))
    elif case == 'nan_observed':
        grid[ELEVATION][3, 3] = np.nan
    elif case == 'inf_observed':
        grid[ELEVATION][3, 3] = np.inf
    elif case == 'inf_no_layer':
        grid = make_grid(truth, seen, with_observed=False)
        grid[ELEVATION][3, 3] = np.inf
    elif case == 'bound_below':
        ub = np.full(seen.shape, np.nan)
        ub[20, 20] = truth[20, 20] - 0.01
        grid[UPPER_BOUND] = ub
    elif case == 'resolution':
        grid = GridMap.from_layers(0.02, (0, 0), dict(grid.layers))
    elif case == 'bad_observed':
        grid[OBSERVED][0, 0] = 0.5
    with pytest.raises(ValueError, match=match):
        filler.update(grid)
    # state unchanged: the same good map again needs no work
    again = filler.update(make_grid(truth, seen))
    assert filler.last_region is None
    np.testing.assert_array_equal(again[ELEVATION], good[ELEVATION])


@pytest.mark.parametrize('library, match', [([], 'empty'), ([np.full((20, 20), np.nan)],
                                                            'fully known')])
def test_bad_library_is_refused(library, match):
    with pytest.raises(ValueError, match=match):
        TerrainFiller(library, RES)


@pytest.mark.parametrize('method', ['inpaint', 'shao_rows'])   # deterministic ones
def test_the_configured_method_is_used(method):
    truth = smooth(40, 0)
    seen = two_holes()
    f = TerrainFiller([smooth(50, 1)], RES, make_config(FillConfig, {'method': method,
                                                                     'samples': 10}))
    out = f.update(make_grid(truth, seen))
    ref = fill(np.where(seen, truth, np.nan), None, [smooth(50, 1)],
               make_config(FillConfig, {'method': method, 'samples': 10}))
    np.testing.assert_allclose(out[ELEVATION], ref.heights, atol=1e-6)
