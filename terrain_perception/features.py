"""Foothold cost maps from local features of a height map.

Two cost functions behind one entry point, :func:`cost_map`:

* ``'kolter'`` (paper 000, section IV, after Kolter, Rodgers & Ng 2008): a weighted sum of local
  features that describe the terrain in foot-scale patches around each cell:

  - **slope**: tangent of the inclination of the least-squares plane fitted to the heights in a
    ``foot_window_m`` square around the cell [-];
  - **roughness**: standard deviation of the heights in the same window [m] (the feature the
    paper names as its example);
  - **height differential**: highest height in a larger ``leg_window_m`` square minus the cell's
    own height [m]; large where the foot would sit in a gap or against a wall (paper 000,
    section II: "small gaps which can trap the robot").

  ``cost = slope_weight * slope + roughness_weight_per_m * roughness
  + height_diff_weight_per_m * height_differential`` (dimensionless, higher = worse).

* ``'shao'`` (paper 002, eq. 2-3): ``cost = h + Dev(h)`` with
  ``Dev(h) = sum over the 8 neighbours of |h - h_n| / sqrt(2)`` (diagonal) or ``/ 2`` (axial).
  Heights are in metres, so this cost is in metres too; it depends on the absolute height, as in
  the paper.

Missing heights (NaN) are *ignored*: every feature is computed from the known cells of its window
(cells outside the grid count as missing). This is the "ignore missing heights" baseline of paper
000, Table I; on a complete map it is simply the cost. A cell whose own height is missing gets
cost NaN. With ``nan_policy='propagate'`` a cell whose window holds any missing height gets NaN
instead.

Everything is vectorised with separable box / ramp filters (``scipy.ndimage``); no loops over
cells. Grids follow the project convention: ``heights[i, j]`` with ``i`` along +x, ``j`` along +y,
``resolution_m`` [m/cell].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict

import numpy as np
from scipy import ndimage

from terrain_perception.config import param

METHODS = ('kolter', 'shao')


@dataclass(frozen=True)
class CostConfig:
    """Parameters of :func:`cost_map`. Window sizes are in metres and turned into odd cell counts
    by :func:`window_cells` so that the cost means the same thing at any grid resolution."""

    method: str = param('kolter', 'cost function: kolter (paper 000 sec IV local features) or '
                        'shao (paper 002 eq. 2-3, h + Dev(h))', choices=METHODS)
    foot_window_m: float = param(
        0.03, 'edge of the square over which slope and roughness are computed [m]; LittleDog\'s '
        'foot is a ~2 cm ball, so 3 cm covers the contact area plus placement error', 0.0, 1.0)
    leg_window_m: float = param(
        0.09, 'edge of the square for the height differential [m]; about the clearance the '
        'lower leg needs around a foothold', 0.0, 2.0)
    slope_weight: float = param(
        1.0, 'cost per unit slope (tan of inclination) [-]; a 45 deg face costs 1', 0.0, 1e3)
    roughness_weight_per_m: float = param(
        20.0, 'cost per metre of height standard deviation in the foot window [1/m]; 5 mm of '
        'roughness costs 0.1', 0.0, 1e4)
    height_diff_weight_per_m: float = param(
        5.0, 'cost per metre by which the leg window rises above the cell [1/m]; a 2 cm gap '
        'costs 0.1', 0.0, 1e4)
    shao_height_weight: float = param(
        1.0, 'shao: weight of the absolute height h in h + Dev(h) [-] (paper: 1)', 0.0, 1e3)
    shao_dev_weight: float = param(
        1.0, 'shao: weight of Dev(h) [-] (paper: 1)', 0.0, 1e3)
    nan_policy: str = param(
        'ignore', 'missing heights: ignore (features from the known cells of each window) or '
        'propagate (any missing height in a window makes the cost NaN)',
        choices=('ignore', 'propagate'))


def window_cells(size_m: float, resolution_m: float) -> int:
    """Odd number of cells (>= 1) closest to a window of ``size_m`` [m] at ``resolution_m``."""
    if not np.isfinite(resolution_m) or resolution_m <= 0.0:
        raise ValueError(f'resolution_m must be a positive number, got {resolution_m}')
    k = int(round(size_m / resolution_m))
    return max(1, k if k % 2 == 1 else k + 1)


def _check_heights(heights: np.ndarray) -> np.ndarray:
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2 or h.size == 0:
        raise ValueError(f'heights must be a non-empty 2-D (nx, ny) array, got shape {h.shape}')
    if np.isinf(h).any():
        raise ValueError('heights contain +-inf; use NaN for unknown cells')
    return h


def _sep(a: np.ndarray, k0: np.ndarray, k1: np.ndarray) -> np.ndarray:
    """Separable correlation with zero padding: sum_{u,v} k0[u] k1[v] a[i+u, j+v]."""
    out = ndimage.correlate1d(a, k0, axis=0, mode='constant', cval=0.0)
    return ndimage.correlate1d(out, k1, axis=1, mode='constant', cval=0.0)


def _window_kernels(k: int):
    u = np.arange(k, dtype=np.float64) - (k - 1) / 2.0
    return np.ones(k), u, u * u


def max_filter(a: np.ndarray, size: int, mode: str = 'nearest') -> np.ndarray:
    """``scipy.ndimage.maximum_filter(a, size, mode=mode, cval=-inf)`` for a float64 map
    without NaN, by OpenCV's dilation with a square kernel (~9x faster on 300 x 300; a
    maximum has no rounding, so the result is bitwise the same). ``mode``: 'nearest' (edges
    replicated) or 'constant' (-inf outside)."""
    import cv2
    a = np.ascontiguousarray(a, dtype=np.float64)
    kernel = np.ones((int(size), int(size)), np.uint8)
    if mode == 'nearest':
        return cv2.dilate(a, kernel, borderType=cv2.BORDER_REPLICATE)
    if mode == 'constant':
        return cv2.dilate(a, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    raise ValueError(f"max_filter mode must be 'nearest' or 'constant', got {mode!r}")


def kolter_features(heights: np.ndarray, resolution_m: float,
                    config: CostConfig = CostConfig()) -> Dict[str, np.ndarray]:
    """The local features of paper 000 section IV (see module docstring).

    Args:
        heights: (nx, ny) heights [m], NaN = unknown.
        resolution_m: cell edge [m/cell].
        config: window sizes and NaN policy.

    Returns:
        dict of float64 (nx, ny) arrays: ``slope`` [-], ``roughness`` [m],
        ``height_differential`` [m], ``known_fraction`` [-] (share of the foot window that is
        known). Features are NaN where the cell itself is unknown.
    """
    h = _check_heights(heights)
    kf = window_cells(config.foot_window_m, resolution_m)
    kl = window_cells(config.leg_window_m, resolution_m)
    known = np.isfinite(h)
    m = known.astype(np.float64)
    hz = np.where(known, h, 0.0)
    # Heights relative to the map's mean keep the moment sums well conditioned.
    ref = float(hz.sum() / max(m.sum(), 1.0))
    hz = np.where(known, h - ref, 0.0)

    one, ramp, quad = _window_kernels(kf)
    s0 = _sep(m, one, one)
    su = _sep(m, ramp, one)
    sv = _sep(m, one, ramp)
    suu = _sep(m, quad, one)
    svv = _sep(m, one, quad)
    suv = _sep(m, ramp, ramp)
    sh = _sep(hz, one, one)
    shu = _sep(hz, ramp, one)
    shv = _sep(hz, one, ramp)
    shh = _sep(hz * hz, one, one)

    # Weighted least-squares plane a + b*u + c*v over the known cells of each window, only
    # where the features are kept (a cell of unknown height gets NaN ones): the normal
    # equations are solved cell by cell, so these cells' values are those of the whole grid's,
    # at a fraction of the cost on a map that is mostly unknown (the moving fill map is ~80 %
    # unknown). The symmetric 3 x 3 systems are solved in closed form (cofactors, Cramer's
    # rule): as array expressions ~10x faster than LAPACK's per-matrix det and solve, equal to
    # them within rounding.
    fit = known & (s0 >= 3)
    f0, fu, fv, fuu, fvv, fuv = (a[fit] for a in (s0, su, sv, suu, svv, suv))
    r0, r1, r2 = sh[fit], shu[fit], shv[fit]
    c11 = fuu * fvv - fuv * fuv
    c12 = fv * fuv - fu * fvv
    c13 = fu * fuv - fuu * fv
    det = f0 * c11 + fu * c12 + fv * c13
    ok = np.abs(det) > 1e-9 * np.maximum(f0, 1.0) ** 3
    grad = np.zeros(h.shape + (2,))
    if ok.any():
        solvable = np.zeros(h.shape, bool)
        solvable[fit] = ok
        f0, fu, fv, fuu, fvv, fuv, r0, r1, r2, c12, c13, det = (
            a[ok] for a in (f0, fu, fv, fuu, fvv, fuv, r0, r1, r2, c12, c13, det))
        c22 = f0 * fvv - fv * fv
        c23 = fu * fv - f0 * fuv
        c33 = f0 * fuu - fu * fu
        grad[solvable] = np.stack([(c12 * r0 + c22 * r1 + c23 * r2) / det,
                                   (c13 * r0 + c23 * r1 + c33 * r2) / det], -1)
    # A window with too few known cells to fix a plane has no measurable slope: 0, not NaN, so
    # the other features still rank the cell.
    slope = np.hypot(grad[..., 0], grad[..., 1]) / resolution_m

    n = np.maximum(s0, 1.0)
    mean = sh / n
    roughness = np.sqrt(np.maximum(shh / n - mean * mean, 0.0))

    hmax = max_filter(np.where(known, h, -np.inf), kl, 'constant')
    height_diff = np.maximum(hmax - h, 0.0)

    known_fraction = s0 / float(kf * kf)
    feats = {'slope': slope, 'roughness': roughness, 'height_differential': height_diff,
             'known_fraction': known_fraction}
    invalid = ~known
    if config.nan_policy == 'propagate':
        full_f = _sep(m, one, one) >= kf * kf - 0.5
        onel = np.ones(kl)
        full_l = _sep(m, onel, onel) >= kl * kl - 0.5
        invalid = invalid | ~full_f | ~full_l
    for name in ('slope', 'roughness', 'height_differential'):
        feats[name] = np.where(invalid, np.nan, feats[name])
    return feats


_SHAO_OFFSETS = ((-1, -1, 1 / np.sqrt(2)), (-1, 1, 1 / np.sqrt(2)), (1, -1, 1 / np.sqrt(2)),
                 (1, 1, 1 / np.sqrt(2)), (-1, 0, 0.5), (1, 0, 0.5), (0, -1, 0.5), (0, 1, 0.5))


def shao_dev(heights: np.ndarray, nan_policy: str = 'ignore') -> np.ndarray:
    """Dev(h) of paper 002 eq. 3 [m]: weighted absolute differences to the 8 neighbours.

    Missing neighbours (NaN or off the grid) are ignored and the sum is rescaled by
    (total weight / weight of the known neighbours), so a border cell is not made to look
    smoother than it is. With ``nan_policy='propagate'`` any missing neighbour gives NaN.
    """
    h = _check_heights(heights)
    padded = np.pad(h, 1, constant_values=np.nan)
    nx, ny = h.shape
    total = np.zeros_like(h)
    wsum = np.zeros_like(h)
    wall = 0.0
    for di, dj, w in _SHAO_OFFSETS:  # 8 whole-array shifts, not a loop over cells
        nb = padded[1 + di:1 + di + nx, 1 + dj:1 + dj + ny]
        ok = np.isfinite(nb)
        total += np.where(ok, w * np.abs(h - np.where(ok, nb, 0.0)), 0.0)
        wsum += np.where(ok, w, 0.0)
        wall += w
    with np.errstate(invalid='ignore', divide='ignore'):
        dev = np.where(wsum > 0, total * (wall / wsum), 0.0)
    dev = np.where(np.isfinite(h), dev, np.nan)
    if nan_policy == 'propagate':
        dev = np.where(wsum < wall - 1e-9, np.nan, dev)
    return dev


def cost_map(heights: np.ndarray, resolution_m: float,
             config: CostConfig = CostConfig()) -> np.ndarray:
    """Foothold cost of every cell of a height map (higher = worse).

    Args:
        heights: (nx, ny) heights [m] in the grid frame, NaN = unknown.
        resolution_m: cell edge [m/cell].
        config: which cost (``config.method``) and its weights.

    Returns:
        float32 (nx, ny) cost; NaN where the cell's height is unknown (and, with
        ``nan_policy='propagate'``, where its neighbourhood is incomplete).

    Raises:
        ValueError: heights not 2-D / empty / containing inf, bad resolution, unknown method.
    """
    if config.method == 'kolter':
        f = kolter_features(heights, resolution_m, config)
        cost = (config.slope_weight * f['slope']
                + config.roughness_weight_per_m * f['roughness']
                + config.height_diff_weight_per_m * f['height_differential'])
    elif config.method == 'shao':
        h = _check_heights(heights)
        if not np.isfinite(resolution_m) or resolution_m <= 0.0:
            raise ValueError(f'resolution_m must be a positive number, got {resolution_m}')
        cost = (config.shao_height_weight * h
                + config.shao_dev_weight * shao_dev(h, config.nan_policy))
    else:
        raise ValueError(f'unknown cost method {config.method!r}; use one of {METHODS}')
    return cost.astype(np.float32)
