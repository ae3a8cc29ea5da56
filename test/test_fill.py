"""Fill-Terrain (paper 000, Fig. 6), line-of-sight bounds (Fig. 5) and the Table I baselines."""

import numpy as np
import pytest
from scipy import ndimage

from fill_reference import fill_terrain_reference
from terrain_perception.config import make_config
from terrain_perception.fill import (BoundsConfig, FillConfig, PatchLibrary, _choose, fill,
                                     fill_constant, fill_constraints_as_heights, fill_inpaint,
                                     fill_shao_rows, fill_terrain, gaussian_weights,
                                     line_of_sight_bounds, bounds_from_captures)

RES = 0.01


def smooth_terrain(n, seed, sigma=3.0, amp=0.05):
    rng = np.random.default_rng(seed)
    h = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma)
    return amp * h / np.abs(h).max()


def blob_mask(n, seed, frac, sigma=3.0):
    rng = np.random.default_rng(seed)
    g = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma)
    return g > np.quantile(g, 1.0 - frac)


# ---------------------------------------------------------------- line-of-sight upper bounds
def _profile():
    """1-D profile along x (ny = 1): flat 0, a 5 cm block at cells 15-17, a dip of -3 cm at
    cells 18-24 right behind it, flat 0 after. Camera at x = 0, 0.30 m up."""
    h = np.zeros(40)
    h[15:18] = 0.05
    h[18:25] = -0.03
    cam = np.array([0.0, 0.5 * RES, 0.30])
    return h, cam


def _visible_1d(h, cam):
    """Brute force: the centre point of cell i is visible if the segment from the camera stays
    above the flat top of every cell it crosses before cell i (dense sampling)."""
    vis = np.zeros(len(h), bool)
    for i in range(len(h)):
        x_end = (i + 0.5) * RES
        xs = np.linspace(cam[0], x_end, 4000)[:-1]
        zs = cam[2] + (xs - cam[0]) / (x_end - cam[0]) * (h[i] - cam[2])
        cells = np.floor(xs / RES).astype(int)
        before = cells != i
        vis[i] = np.all(zs[before] >= h[cells[before]] - 1e-12)
    return vis


def test_upper_bounds_on_a_1d_profile_with_an_occluded_dip():
    h, cam = _profile()
    vis = _visible_1d(h, cam)
    shadow = ~vis
    assert shadow[18:25].any() and not shadow[:18].any()       # the dip hides behind the block
    pts = np.c_[(np.flatnonzero(vis) + 0.5) * RES, np.full(vis.sum(), 0.5 * RES), h[vis]]
    cfg = make_config(BoundsConfig, {'step_cells': 0.05})
    ub = line_of_sight_bounds((40, 1), RES, (0.0, 0.0), cam, pts, cfg)[:, 0]
    # analytic bound: lowest height any ray to a visible point has over the cell's footprint
    expected = np.full(40, np.inf)
    for x_p, z_p in zip(pts[:, 0], pts[:, 2]):
        end = int(x_p / RES)
        for c in range(end):
            x_far = (c + 1) * RES                      # the ray descends: lowest at the far edge
            expected[c] = min(expected[c], cam[2] + x_far / x_p * (z_p - cam[2]))
    slope = 0.30 / 0.15
    for c in np.flatnonzero(shadow):
        assert np.isfinite(ub[c])
        assert expected[c] <= ub[c] <= expected[c] + slope * 0.05 * RES + 1e-12
        assert h[c] <= ub[c] < 0.05                   # a true bound, tighter than the block top
    last_vis = np.flatnonzero(vis).max()
    assert np.isnan(ub[last_vis:]).all()               # never crossed by a ray: no bound
    # the dip's bound rises from just behind the block towards the next visible point
    dip = np.flatnonzero(shadow)
    assert np.all(np.diff(ub[dip]) < 0) or np.all(np.diff(ub[dip]) > 0)


def test_viewshed_bounds_on_the_1d_profile_match_a_loop_over_ray_samples():
    h, cam = _profile()
    cam = cam + np.array([0.0013, 0.0, 0.0])       # samples off the cell edges
    vis = _visible_1d(h, cam)
    observed = np.where(vis, h, np.nan)[:, None]
    ub = bounds_from_captures(observed, RES, (0.0, 0.0), cam[None], max_range_m=0.5,
                              tol_m=0.0)[:, 0]
    # oracle: one ray along +x sampled every half cell, flat-topped cells as occluders
    step = 0.5 * RES
    r = step * np.arange(1, int(0.5 / step) + 1)
    cell = np.floor((cam[0] + r) / RES).astype(int)
    r, cell = r[cell < 40], cell[cell < 40]
    hz = np.where(vis[cell], h[cell], np.nan)
    slope = (hz - cam[2]) / r
    seen = np.zeros(len(r), bool)
    steepest = -np.inf
    for m in range(len(r)):
        if np.isfinite(slope[m]):
            seen[m] = slope[m] >= steepest
            steepest = max(steepest, slope[m])
    # the line ends on the seen cell's centre and is evaluated at the hidden cell's centre
    rcen = (cell + 0.5) * RES - cam[0]
    expected = np.full(40, np.inf)
    for m in range(len(r)):
        later = [(hz[q] - cam[2]) / rcen[q] for q in range(m + 1, len(r)) if seen[q]]
        if not vis[cell[m]] and later:
            expected[cell[m]] = min(expected[cell[m]], cam[2] + rcen[m] * min(later))
    expected[np.isinf(expected)] = np.nan
    hidden = ~vis
    assert hidden[18:22].all() and np.isfinite(expected[18:22]).all()
    np.testing.assert_allclose(ub, expected, atol=1e-9, equal_nan=True)
    assert np.all(ub[np.isfinite(ub)] >= h[np.isfinite(ub)])      # true bounds
    assert np.all(ub[19:22] < 0.05)                                 # below the block top


def test_viewshed_bounds_hold_on_a_2d_scene_and_respect_the_view_cone():
    from terrain_perception.grid import GridMap
    from terrain_perception.raycast import visible_cells
    from terrain_perception.transforms import make_T
    n = 60
    truth = smooth_terrain(n, 4, amp=0.01) + 0.01
    truth[25:28, 15:45] = 0.06                          # a wall across the view
    truth[3:7, 48:51] = 0.06                            # a block beside the camera
    grid = GridMap.from_layers(RES, (0, 0), {'elevation': truth.astype(np.float32)})
    truth = grid['elevation'].astype(np.float64)
    cam = np.array([0.02, 0.30, 0.25])
    T = make_T(np.eye(3), cam)
    seen = visible_cells(grid, T, max_range_m=1.0)
    hidden = ~seen
    observed = np.where(seen, truth, np.nan)
    ub = bounds_from_captures(observed, RES, (0, 0), cam[None], max_range_m=1.0)
    shadow = hidden.copy()
    shadow[:28] = False                                 # the wall's shadow (beyond it)
    assert shadow.sum() > 40
    got = shadow & np.isfinite(ub)
    assert got.sum() > 0.5 * shadow.sum()
    # valid bounds up to the bin approximation (ray within half a bin of the cell centre)
    assert np.all(ub[got] >= truth[got] - 0.002)
    assert np.mean(ub[got] < 0.06) > 0.9                 # and below the wall top: informative
    # looking along +x with a 40 deg cone: nothing behind or beside the camera is bounded
    axis = np.array([[1.0, 0.0, -0.5]])
    ub_cone = bounds_from_captures(observed, RES, (0, 0), cam[None], max_range_m=1.0,
                                   camera_axes=axis, fov_half_angle_rad=np.radians(40))
    d = np.stack(np.meshgrid((np.arange(n) + 0.5) * RES - cam[0],
                             (np.arange(n) + 0.5) * RES - cam[1], indexing='ij'), -1)
    side = np.abs(np.degrees(np.arctan2(d[..., 1], d[..., 0]))) > 60
    assert np.isfinite(ub[side & hidden]).sum() > 3     # the block's shadow, seen all round
    assert np.isnan(ub_cone[side]).all()
    assert np.isfinite(ub_cone[got]).mean() > 0.5
    assert np.all(np.isfinite(ub[np.isfinite(ub_cone)]))  # the cone only removes bounds


def test_bounds_reject_unpaired_rays():
    with pytest.raises(ValueError, match='pair'):
        line_of_sight_bounds((5, 5), RES, (0, 0), np.zeros((3, 3)), np.zeros((4, 3)))


# ------------------------------------------------------------------- Fill-Terrain: the rule
def test_choose_prefers_the_most_similar_non_violating_patch():
    w, q = 3, 9
    W = gaussian_weights(w, 1.0).ravel()
    A = np.zeros((1, q))
    B = np.ones((1, q), bool)
    B[0, 4] = False                                    # centre missing
    Abar = np.full((1, q), np.inf)
    Abar[0, 4] = 0.0                                   # the centre must stay below 0
    base = np.zeros(q)
    c0 = base.copy(); c0[4] = 0.02                     # perfect fit elsewhere, violates
    c1 = base + 0.001 * np.arange(q); c1[4] = -0.01    # slightly worse fit, obeys
    c2 = base + 0.004 * np.arange(q); c2[4] = -0.02    # worse fit, obeys
    h, k = _choose(A, B, Abar, np.stack([c0, c1, c2])[None], W)
    assert k[0] == 1
    b1 = -(c1.sum() - c1[4]) / 8
    assert h[0] == pytest.approx(c1[4] + b1)
    # nothing obeys: the least violating patch wins
    Abar[0, 4] = -0.5
    h, k = _choose(A, B, Abar, np.stack([c0, c1, c2])[None], W)
    assert k[0] == 2


def test_fill_never_violates_a_bound_when_a_non_violating_patch_exists():
    n = 36
    truth = smooth_terrain(n, 1)
    mask = blob_mask(n, 2, 0.3)
    h = np.where(mask, np.nan, truth)
    ub = np.where(mask, truth + 0.003, np.nan)         # a tight bound just above the truth
    lib = [smooth_terrain(60, s) for s in (10, 11, 12)]
    cfg = make_config(FillConfig, {'samples': 60, 'seed': 4})
    res = fill_terrain(h, ub, lib, cfg)
    _, _, feasible = fill_terrain_reference(h, ub, lib, 5, 60, cfg.weight_sigma_cells, 4,
                                            return_feasible=True)
    assert feasible[mask].mean() > 0.5                 # the case under test really occurs
    f = feasible & mask
    assert np.all(res.heights[f] <= ub[f] + 1e-12)
    # without the constraints the same draws do break the bounds (the test can fail)
    free = fill_terrain(h, ub, lib, cfg, constrained=False)
    assert np.any(free.heights[mask] > ub[mask] + 1e-4)


# ------------------------------------------------------------- vectorised == reference loop
@pytest.mark.parametrize('constrained, bank', [(True, True), (False, True), (True, False)])
def test_vectorised_fill_equals_the_reference_loop(constrained, bank):
    n = 30
    truth = smooth_terrain(n, 5)
    mask = blob_mask(n, 6, 0.3)
    mask[:4, :6] = True                                # a hole touching the map corner
    h = np.where(mask, np.nan, truth)
    rng = np.random.default_rng(0)
    ub = np.where(rng.random(h.shape) < 0.7, truth + np.abs(rng.normal(0, 0.004, h.shape)),
                  np.nan)
    lib = [smooth_terrain(40, 20), smooth_terrain(33, 21)[:, :29]]   # unequal shapes
    cfg = make_config(FillConfig, {'samples': 25, 'seed': 9, 'batch_cells': 7})
    library = PatchLibrary(lib, 5, bank_max_mb=100.0 if bank else 0.0)
    assert (library.bank is not None) == bank
    res = fill_terrain(h, ub, library, cfg, constrained=constrained)
    ref_h, ref_choice, _ = fill_terrain_reference(h, ub, lib, 5, 25, cfg.weight_sigma_cells, 9,
                                                  constrained=constrained,
                                                  return_feasible=True)
    np.testing.assert_array_equal(res.choice, ref_choice)     # same patch for every cell
    np.testing.assert_allclose(res.heights, ref_h, rtol=0, atol=1e-12)
    assert np.array_equal(res.filled, mask)
    np.testing.assert_array_equal(res.heights[~mask], truth[~mask])


def test_fill_is_seeded():
    truth = smooth_terrain(24, 5)
    h = np.where(blob_mask(24, 1, 0.3), np.nan, truth)
    lib = [smooth_terrain(40, 3)]
    a = fill_terrain(h, None, lib, make_config(FillConfig, {'seed': 1, 'samples': 10}))
    b = fill_terrain(h, None, lib, make_config(FillConfig, {'seed': 1, 'samples': 10}))
    c = fill_terrain(h, None, lib, make_config(FillConfig, {'seed': 2, 'samples': 10}))
    np.testing.assert_array_equal(a.heights, b.heights)
    assert not np.array_equal(a.heights, c.heights)


# ------------------------------------------------------------------------ quality vs baselines
def test_fill_terrain_beats_the_optimal_constant_on_a_masked_region():
    n = 60
    truth = smooth_terrain(n, 7, sigma=4.0)
    mask = np.zeros((n, n), bool)
    mask[20:34, 25:41] = True
    h = np.where(mask, np.nan, truth)
    lib = [smooth_terrain(80, s, sigma=4.0) for s in range(30, 34)]
    res = fill_terrain(h, None, lib, make_config(FillConfig, {'samples': 150, 'seed': 0}))
    rmse = np.sqrt(np.mean((res.heights[mask] - truth[mask]) ** 2))
    best_const = fill_constant(h, float(truth[mask].mean()))
    rmse_c = np.sqrt(np.mean((best_const.heights[mask] - truth[mask]) ** 2))
    assert rmse < 0.85 * rmse_c, (rmse, rmse_c)   # the constant is the oracle mean


@pytest.mark.parametrize('flags', ['telea', 'ns'])
def test_inpaint_keeps_float_precision(flags):
    # 0.0503 m on a map spanning 0..0.1 m: an 8-bit image would store level 128 = 0.0502 m,
    # a 0.1 mm error; the float32 path keeps the flat surround's height to ~1e-8 m
    truth = np.full((40, 40), 0.0503)
    truth[:5, :5] = 0.0
    truth[-5:, -5:] = 0.1
    mask = np.zeros_like(truth, bool)
    mask[18:24, 15:22] = True
    out = fill_inpaint(np.where(mask, np.nan, truth), 3.0, flags)
    # float32 path ~1e-8 m; 16-bit path (telea): a few steps of 0.1 m / 65535 = 1.5 um
    assert np.abs(out.heights[mask] - 0.0503).max() < (1e-7 if flags == 'ns' else 5e-6)
    np.testing.assert_array_equal(out.heights[~mask], truth[~mask])


def test_shao_row_fill_takes_the_nearest_cell_in_the_row():
    h = np.array([[1.0, np.nan, np.nan, np.nan, 5.0],
                  [np.nan, 2.0, np.nan, np.nan, np.nan],
                  [np.nan] * 5])
    out = fill_shao_rows(h, axis=1).heights
    np.testing.assert_array_equal(out[0], [1, 1, 1, 5, 5])    # tie -> lower index
    np.testing.assert_array_equal(out[1], [2, 2, 2, 2, 2])
    assert np.isfinite(out[2]).all()                              # empty row: nearest in 2-D
    out_x = fill_shao_rows(h, axis=0).heights
    assert out_x[2, 0] == 1.0 and out_x[0, 1] == 2.0


def test_constraints_as_heights_and_constant():
    h = np.array([[0.0, np.nan, np.nan], [0.1, 0.2, np.nan]])
    ub = np.array([[np.nan, 0.5, np.nan], [np.nan, np.nan, np.nan]])
    out = fill_constraints_as_heights(h, ub)
    assert out.heights[0, 1] == 0.5
    assert np.isfinite(out.heights).all() and out.filled.sum() == 3
    c = fill_constant(h)
    assert c.heights[0, 2] == pytest.approx(0.1)
    assert fill_constant(h, -1.0).heights[1, 2] == -1.0


@pytest.mark.parametrize('method', ['fill_terrain', 'texture_synthesis',
                                    'constraints_as_heights', 'constant', 'inpaint',
                                    'shao_rows', 'none'])
def test_every_method_keeps_observed_cells_and_fills_the_rest(method):
    truth = smooth_terrain(20, 3)
    mask = blob_mask(20, 4, 0.3)
    h = np.where(mask, np.nan, truth)
    cfg = make_config(FillConfig, {'method': method, 'samples': 10})
    out = fill(h, np.where(mask, truth + 0.01, np.nan), [smooth_terrain(30, 1)], cfg)
    np.testing.assert_array_equal(out.heights[~mask], truth[~mask])
    assert np.isfinite(out.heights).all() == (method != 'none')


# ---------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize('method', ['fill_terrain', 'inpaint', 'shao_rows', 'constant'])
def test_every_cell_unknown_is_refused(method):
    cfg = make_config(FillConfig, {'method': method})
    with pytest.raises(ValueError, match='every cell is unknown'):
        fill(np.full((10, 10), np.nan), None, [smooth_terrain(20, 0)], cfg)


def test_bounds_below_observed_heights_are_refused():
    h = smooth_terrain(20, 0)
    h[5:8, 5:8] = np.nan
    ub = np.full_like(h, np.nan)
    ub[2, 3] = h[2, 3] - 0.01
    with pytest.raises(ValueError, match=r'above their line-of-sight upper bound.*\[2, 3\]'):
        fill_terrain(h, ub, [smooth_terrain(20, 1)])
    with pytest.raises(ValueError, match='shape'):
        fill_terrain(h, ub[:5], [smooth_terrain(20, 1)])


def test_infinite_heights_are_refused():
    h = smooth_terrain(20, 0)
    h[3, 3] = np.inf
    with pytest.raises(ValueError, match='inf'):
        fill_terrain(h, None, [smooth_terrain(20, 1)])


@pytest.mark.parametrize('library, match', [
    ([], 'empty'), (None, 'empty'),
    ([np.full((20, 20), np.nan)], 'fully known'),
    ([np.zeros((3, 30))], 'smaller than'),
    ([np.zeros(30)], '2-D')])
def test_bad_library_is_refused(library, match):
    h = smooth_terrain(20, 0)
    h[5:8, 5:8] = np.nan
    with pytest.raises(ValueError, match=match):
        fill_terrain(h, None, library)


def test_window_must_match_a_prebuilt_library():
    h = smooth_terrain(20, 0)
    h[5:8, 5:8] = np.nan
    lib = PatchLibrary([smooth_terrain(20, 1)], 7)
    with pytest.raises(ValueError, match='w = 7'):
        fill_terrain(h, None, lib, FillConfig())


def _random_rays(seed, n=400):
    rng = np.random.default_rng(seed)
    cams = np.c_[rng.uniform(-0.1, 0.0, n), rng.uniform(0.1, 0.3, n), rng.uniform(0.2, 0.3, n)]
    pts = np.c_[rng.uniform(0.05, 0.4, n), rng.uniform(0.0, 0.4, n), rng.uniform(0, 0.05, n)]
    return cams, pts


def test_target_culling_and_ceiling_keep_the_bounds():
    cams, pts = _random_rays(0)
    cfg = make_config(BoundsConfig, {'step_cells': 0.1})
    full = line_of_sight_bounds((40, 40), RES, (0, 0), cams, pts, cfg)
    target = blob_mask(40, 3, 0.2)
    culled = line_of_sight_bounds((40, 40), RES, (0, 0), cams, pts, cfg, target=target)
    assert np.isnan(culled[~target]).all()
    # The samples sit at other places along the shortened rays, so a cell a ray only clips
    # at a corner may be bounded in one run and not the other; values agree up to the
    # sample spacing times the ray slope (<= 3), except where one run caught a corner clip of
    # another (lower) ray that the other run stepped over.
    ok = np.isfinite(full) & target
    assert ok.sum() > 50
    assert np.isfinite(culled[ok]).mean() > 0.98
    assert np.isfinite(full[np.isfinite(culled)]).all()
    both = ok & np.isfinite(culled)
    assert (np.abs(culled[both] - full[both]) <= 3 * 0.1 * RES).mean() > 0.98
    ceil = line_of_sight_bounds((40, 40), RES, (0, 0), cams, pts, cfg, ceiling_m=0.1)
    low = np.isfinite(full) & (full < 0.1 - 0.01)
    assert np.isfinite(ceil[low]).mean() > 0.98
    both = low & np.isfinite(ceil)
    assert (np.abs(ceil[both] - full[both]) <= 3 * 0.1 * RES).mean() > 0.98
    assert np.nanmax(ceil) <= 0.1 + 1e-12                 # nothing above the ceiling is used
    assert np.isnan(ceil[np.isfinite(full) & (full > 0.1 + 0.01)]).mean() > 0.95


def test_centre_radius_only_uses_samples_near_the_cell_centre():
    # one ray along y = 0.25 cells into row j=0: it passes 0.25 cells from the centres
    cam = np.array([0.0, 0.0025, 0.2])
    pt = np.array([[0.2, 0.0025, 0.0]])
    near = make_config(BoundsConfig, {'center_radius_cells': 0.3, 'step_cells': 0.05})
    far = make_config(BoundsConfig, {'center_radius_cells': 0.2, 'step_cells': 0.05})
    assert np.isfinite(line_of_sight_bounds((20, 2), RES, (0, 0), cam, pt, near)[:, 0]).sum() > 15
    assert np.isnan(line_of_sight_bounds((20, 2), RES, (0, 0), cam, pt, far)).all()
