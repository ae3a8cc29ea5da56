"""TerrainFiller: the filled map the node publishes, its incremental updates and bad input."""

import numpy as np
import pytest
from scipy import ndimage

from terrain_perception.config import make_config
from terrain_perception.features import CostConfig, cost_map
from terrain_perception.fill import CONTACT, FillConfig, FillerConfig, TerrainFiller, fill
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


# these tests are about the update mechanics: every hole is filled, bounded or not
TEXTURE = make_config(FillerConfig, {'blind_area': 'texture'})


@pytest.fixture
def filler():
    lib = [smooth(50, s) for s in (1, 2)]
    return TerrainFiller(lib, RES, make_config(FillConfig, {'samples': 30}),
                         filler_config=TEXTURE)


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
    assert set(out.layers) == {ELEVATION, OBSERVED, UPPER_BOUND, FILLED, COST, CONTACT}
    assert not out[CONTACT].any()                      # no stance given
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
                                                                     'samples': 10}),
                      filler_config=TEXTURE)
    out = f.update(make_grid(truth, seen))
    ref = fill(np.where(seen, truth, np.nan), None, [smooth(50, 1)],
               make_config(FillConfig, {'method': method, 'samples': 10}))
    np.testing.assert_allclose(out[ELEVATION], ref.heights, atol=1e-6)


# --------------------------------------------------------------------------------------------
# incremental bounds, local refill, blind area
# --------------------------------------------------------------------------------------------
def rock_scene(n=60):
    """Flat floor with a 4 cm block across x = 0.30-0.33 m; cameras walk +x at y = 0.3 m,
    0.25 m up, looking down the +x axis. Returns truth, seen mask, camera positions (K, 3)."""
    truth = np.zeros((n, n))
    truth[30:33, 15:45] = 0.04
    cams = np.array([[0.05 + 0.02 * k, 0.3, 0.25] for k in range(5)])
    seen = np.zeros((n, n), bool)
    for c in cams:                          # true line of sight to each cell centre, x ahead
        for i in range(n):
            x = (i + 0.5) * RES
            if x <= c[0] + 0.1:             # the camera sees from 10 cm ahead of itself
                continue
            xs = (np.arange(i) + 0.5) * RES
            for j in range(n):
                ray = c[2] + (xs - c[0]) / (x - c[0]) * (truth[i, j] - c[2])
                between = xs > c[0]
                seen[i, j] |= np.all(truth[:i, j][between] <= ray[between] + 1e-9)
    return truth, seen, cams


def test_incremental_bounds_equal_bounds_from_every_capture():
    truth, seen, cams = rock_scene()
    lib = [smooth(50, 1)]
    inc = TerrainFiller(lib, RES, make_config(FillConfig, {'samples': 10}))
    grid = make_grid(truth, seen)
    for k in range(1, len(cams) + 1):
        out = inc.update(grid, cams[:k])
        assert inc.last_new_captures == 1
    scratch = TerrainFiller(lib, RES).bounds(grid, np.where(seen, truth, np.nan), cams)
    assert np.isfinite(scratch).sum() > 50
    np.testing.assert_array_equal(out[UPPER_BOUND], scratch.astype(np.float32))
    # the same poses again add no rays and change nothing
    again = inc.update(grid, cams)
    assert inc.last_new_captures == 0 and inc.last_refilled == 0 and inc.last_region is None
    np.testing.assert_array_equal(again[ELEVATION], out[ELEVATION])


def test_bound_layer_moves_with_the_grid_origin():
    truth, seen, cams = rock_scene()
    f = TerrainFiller([smooth(50, 1)], RES, make_config(FillConfig, {'samples': 10}))
    a = f.update(make_grid(truth, seen), cams)
    # the window moves 7 cells along +x and 3 along +y; no new capture: bounds only move
    g = GridMap.from_layers(RES, (7 * RES, 3 * RES), {
        ELEVATION: np.where(seen, truth, np.nan)[7:, 3:],
        OBSERVED: seen[7:, 3:].astype(np.float32)})
    b = f.update(g, cams)
    assert f.last_new_captures == 0
    np.testing.assert_array_equal(b[UPPER_BOUND], a[UPPER_BOUND][7:, 3:])


def test_blind_area_is_left_unknown_not_textured():
    """Behind the cameras and beside their view nothing was seen and no line of sight passed:
    the default leaves those cells unknown; 'texture' invents heights there (the truth is a
    flat floor at 0)."""
    truth, seen, cams = rock_scene()
    lib = [smooth(50, s) for s in (1, 2)]            # rough library: 0..8 cm
    grid = make_grid(truth, seen)
    out = TerrainFiller(lib, RES, make_config(FillConfig, {'samples': 30})).update(grid, cams)
    tex = TerrainFiller(lib, RES, make_config(FillConfig, {'samples': 30}),
                        filler_config=TEXTURE).update(grid, cams)
    ub = out[UPPER_BOUND]
    blind = ~seen & np.isnan(ub)
    bounded = ~seen & np.isfinite(ub)
    assert blind.sum() > 500 and bounded.sum() > 50
    # default: blind cells unknown and not marked filled; their cost is unknown too
    assert np.isnan(out[ELEVATION][blind]).all() and np.isnan(out[COST][blind]).all()
    np.testing.assert_array_equal(out[FILLED], bounded.astype(np.float32))
    np.testing.assert_array_equal(out[OBSERVED], seen.astype(np.float32))
    # ... while the bounded shadow behind the block is still filled, under its bounds
    assert np.isfinite(out[ELEVATION][bounded]).all()
    assert np.mean(out[ELEVATION][bounded] <= ub[bounded] + 1e-6) > 0.9
    # texture: heights invented on the flat floor, many of them cm-high phantoms
    err = np.abs(tex[ELEVATION][blind] - truth[blind])
    assert np.isfinite(err).all() and np.mean(err > 0.01) > 0.2
    # the cost of the observed cells next to the blind area (features ignoring the unknown
    # cells) is about as good as with the invented texture there
    true_cost = cost_map(truth, RES, CostConfig())
    edge = seen & ndimage.binary_dilation(blind, np.ones((9, 9), bool))
    rmse = {k: np.sqrt(np.mean((o[COST][edge] - true_cost[edge]) ** 2))
            for k, o in (('unknown', out), ('texture', tex))}
    assert rmse['unknown'] < 1.2 * rmse['texture']


def test_refill_stays_local_in_a_large_hole():
    """A 1-cell change at one end of a large textured hole refills only its neighbourhood."""
    truth = smooth(80, 0)
    seen = np.zeros((80, 80), bool)
    seen[:, :10] = True                               # one observed strip, a huge hole
    f = TerrainFiller([smooth(50, 1)], RES, make_config(FillConfig, {'samples': 10}),
                      filler_config=TEXTURE)
    a = f.update(make_grid(truth, seen))
    seen2 = seen.copy()
    seen2[0, 10] = True
    b = f.update(make_grid(truth, seen2))
    m = FillerConfig().refill_margin_cells
    assert 0 < f.last_refilled <= (2 * m + 1) ** 2
    np.testing.assert_array_equal(b[ELEVATION][10:, 20:], a[ELEVATION][10:, 20:])


def test_fill_mask_leaves_other_missing_cells_unknown():
    from terrain_perception.fill import fill_terrain
    truth = smooth(30, 0)
    h = truth.copy()
    h[10:20, 10:20] = np.nan
    lib = [smooth(50, 1)]
    cfg = make_config(FillConfig, {'samples': 10})
    full = fill_terrain(h, None, lib, cfg)
    same = fill_terrain(h, None, lib, cfg, fill_mask=np.ones(h.shape, bool))
    np.testing.assert_array_equal(same.heights, full.heights)
    np.testing.assert_array_equal(same.choice, full.choice)
    mask = np.zeros(h.shape, bool)
    mask[10:20, 10:13] = True
    part = fill_terrain(h, None, lib, cfg, fill_mask=mask)
    assert np.isfinite(part.heights[10:20, 10:13]).all()
    assert np.isnan(part.heights[10:20, 13:20]).all()
    np.testing.assert_array_equal(part.filled, mask & np.isnan(h))


def test_blind_cells_under_the_feet_take_the_stance_plane():
    # Nothing seen in the left half and no capture: blind. The robot stands on a 2 deg
    # slope there; cells within the support radius of its feet get that plane, marked
    # `contact`, not observed and not filled; the rest of the blind area stays unknown; a
    # later observation replaces them.
    lib = [smooth(50, s) for s in (1, 2)]
    filler = TerrainFiller(lib, RES, make_config(FillConfig, {'samples': 30}))  # unknown
    n = 40
    truth = np.zeros((n, n))
    seen = np.zeros((n, n), bool)
    seen[:, 25:] = True
    slope = np.tan(np.radians(2.0))
    feet = np.array([[0.05, 0.05, 0.0], [0.05, 0.15, 0.0], [0.15, 0.05, 0.0],
                     [0.15, 0.15, 0.0]])
    feet[:, 2] = 0.01 + slope * feet[:, 0]
    out = filler.update(make_grid(truth, seen), np.zeros((0, 3)), feet)
    r = filler.filler_config.contact_support_radius_m
    x = (np.arange(n) + 0.5) * RES
    X, Y = np.meshgrid(x, x, indexing='ij')
    near = np.min(np.hypot(X[..., None] - feet[:, 0], Y[..., None] - feet[:, 1]), -1) <= r
    want = near & ~seen
    np.testing.assert_array_equal(out[CONTACT] > 0.5, want)
    np.testing.assert_allclose(out[ELEVATION][want], (0.01 + slope * X)[want], atol=1e-9)
    assert not out[OBSERVED][want].any() and not out[FILLED][want].any()
    assert np.isnan(out[ELEVATION][~seen & ~want]).all()
    # the feet move on: the supported cells are remembered; seeing them replaces the plane
    seen2 = seen.copy()
    seen2[:10] = True
    out2 = filler.update(make_grid(truth, seen2), np.zeros((0, 3)))
    np.testing.assert_array_equal(out2[CONTACT] > 0.5, want & ~seen2)
    np.testing.assert_array_equal(out2[ELEVATION][seen2], 0.0)
