"""Filling occluded parts of a height map: Fill-Terrain under line-of-sight constraints (paper
000, section III, Fig. 6) and the baselines of its Table I plus two more.

Grids follow the project convention: ``heights[i, j]`` [m] with ``i`` along +x, ``j`` along +y,
NaN = unknown, cell ``[i, j]`` centred at ``origin_xy + (i + 0.5, j + 0.5) * resolution_m``.

Line-of-sight upper bounds (:func:`line_of_sight_bounds`)
    A camera at ``c`` that observed a surface point ``p`` saw nothing between them, so every cell
    the segment ``c -> p`` passes over has its height below the segment there. Each ray's x-y
    footprint is rasterised through the grid (samples every ``step_cells`` cells) and the bound
    of a cell is the running minimum of the ray heights over all rays that crossed it. The cell
    that holds ``p`` itself is skipped (the ray ends on its surface). Cells never crossed have
    no bound (NaN). Used when the true (camera, point) pairs are known (the benchmark).

Bounds from capture poses only (:func:`bounds_from_captures`)
    A fused map does not say which camera saw which cell; a viewshed (horizon test along a fan
    of rays from each capture, observed cells as occluders) recovers the plausible lines of
    sight. This is what :class:`TerrainFiller` (the node) uses.

Fill-Terrain (:func:`fill_terrain`), Fig. 6, for a missing cell with window ``A`` (w x w around
it), known mask ``B``, bound window ``A_bar``, weighting matrix ``W`` and ``n`` random library
patches ``C_k``::

    m   = sum B
    b_k = sum B (A - C_k) / m
    h_k = C_k[centre] + b_k
    s_k = sum W B (C_k - A + b_k)^2
    v_k = sum max(C_k + b_k - A_bar, 0)^2        (over window cells that have a bound)
    H[x, y] = h_k*,  k* = argmin_{k: v_k = 0} s_k  if any v_k = 0, else argmin_k v_k

The printed Fig. 6 writes the violation as ``max{B (C - A_bar + b)^2, 0}``, which is never
negative, so the ``max`` could never act and a perfect fit would count as a violation; we read it
as the squared amount by which the shifted patch rises above the bound, which is what the text
("how much the library patch violates the height constraints") describes.

Fill order. The issue asks for the cells with the most known neighbours first, with filled cells
counting as known afterwards. To fill many cells at once and still get the same map as a
one-cell-at-a-time loop, cells are filled in *rounds*: in each round every missing cell whose
``(known count in its window, rank)`` key is larger than that of every other missing cell in its
w x w window is filled (the rank is a seeded random permutation that breaks ties). Two cells of
one round are never inside each other's window, so filling them one after another or all at
once reads the same heights: the order is the same whichever way it is executed. The order is
"most known neighbours first" locally (within a window), not globally: a cell with few known
neighbours far away may be filled before a better-known one elsewhere, which cannot affect
either result.

Random numbers (identical for the vectorised code and ``test/fill_reference.py``): one
``rng.permutation(nx * ny)`` for the ranks, then per round, for the selected cells in increasing
flat index, ``n`` doubles ``rng.random()`` each (one block ``rng.random((cells, n))``), each
mapped to one of all valid w x w patch positions of the library (terrains concatenated in order,
positions in row-major order): ``pos = floor(u * total_positions)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
from scipy import ndimage

from terrain_perception.compiled import load_compiled
from terrain_perception.config import param

_LOG = logging.getLogger(__name__)


def _load_kernels():
    """The compiled rounds, choice step and viewshed (terrain_perception._fill_kernels), or
    None for the numpy code (``TERRAIN_FILL_NUMBA=0``, or numba missing: logged once)."""
    return load_compiled('_fill_kernels', 'TERRAIN_FILL_NUMBA', 'Fill-Terrain', _LOG)


_kernels = _load_kernels()


def use_compiled_kernels(enabled: Optional[bool] = True) -> bool:
    """Select the compiled rounds, choice step and viewshed (``True``), the numpy code
    (``False``) or the default (``None``) for the following fills and bounds, process-wide;
    returns whether compiled is on. Both give bitwise the same rounds and bounds, and fills
    equal within rounding (the same library samples; _fill_kernels.choose_block)."""
    global _kernels
    if enabled is None:
        _kernels = _load_kernels()
    elif enabled:
        from terrain_perception import _fill_kernels
        _kernels = _fill_kernels
    else:
        _kernels = None
    return _kernels is not None


FILL_METHODS = ('fill_terrain', 'texture_synthesis', 'constraints_as_heights', 'constant',
                'inpaint', 'shao_rows', 'none')


# --------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FillConfig:
    """Parameters of the fill methods. Windows are in cells (the library is at the map's
    resolution, so a cell count is what the algorithm really uses)."""

    method: str = param('fill_terrain', 'fill method: ' + ', '.join(FILL_METHODS),
                        choices=FILL_METHODS)
    window_cells: int = param(
        5, 'Fig. 6 window w [cells], odd; 5 cells at 5 mm is one LittleDog foot (2.5 cm)', 3, 31)
    samples: int = param(
        100, 'Fig. 6 n: random library patches drawn per missing cell [-]', 1, 100000)
    weight_sigma_cells: float = param(
        1.5, 'std of the Gaussian weighting matrix W [cells] (Efros-Leung use w/6.4; a wider '
        'one favours the window as a whole)', 0.1, 100.0)
    seed: int = param(0, 'seed of the random patch draws and the tie-breaking ranks', 0)
    batch_cells: int = param(
        4096, 'largest number of cells evaluated in one vectorised block (memory bound: '
        'batch * samples * w^2 doubles)', 1, 10 ** 7)
    inpaint_radius_cells: float = param(
        3.0, 'inpaint baseline: neighbourhood radius of cv2.inpaint [cells]', 1.0, 50.0)
    inpaint_flags: str = param(
        'ns', 'inpaint baseline: ns (Navier-Stokes, on float32 heights) or telea (on 16-bit '
        'heights: OpenCV 5.0 Telea is wrong on float32)', choices=('telea', 'ns'))
    shao_row_axis: int = param(
        1, 'Shao baseline: grid axis along which a "row" runs (1 = along y, i.e. a line of '
        'constant x, the grid analogue of an image row of a forward-looking camera)', 0, 1)


@dataclass(frozen=True)
class BoundsConfig:
    """Parameters of :func:`line_of_sight_bounds`."""

    step_cells: float = param(
        0.5, 'spacing of the samples along each ray footprint [cells]; <= 0.5 visits every '
        'cell a ray crosses except corner clips (which then just get no bound from that ray)',
        0.05, 1.0)
    margin_m: float = param(
        0.0, 'added to every bound [m]; > 0 tolerates noisy points or poses', 0.0, 1.0)
    center_radius_cells: float = param(
        0.5, 'a ray sample bounds a cell only within this Chebyshev distance of the cell '
        'centre [cells]; 0.5 = anywhere over the cell (flat-topped cells). On a surface '
        'interpolated between cell centres, a ray over a cell corner does not bound the centre '
        'height: a smaller radius (with a smaller step) keeps the bound valid', 0.01, 0.5)
    chunk_samples: int = param(
        4_000_000, 'ray samples processed per block (memory bound)', 1000, 10 ** 9)


@dataclass
class FillResult:
    """Output of a fill method.

    Attributes:
        heights: (nx, ny) float64 heights [m]; observed cells unchanged; NaN where the method
            leaves a cell unknown (only ``none``).
        filled: (nx, ny) bool, True where the height was synthesised.
        rounds: number of fill rounds (Fill-Terrain), 0 otherwise.
        choice: (nx, ny) int64 global library position chosen per filled cell (-1 elsewhere);
            Fill-Terrain only, for comparing implementations.
    """

    heights: np.ndarray
    filled: np.ndarray
    rounds: int = 0
    choice: Optional[np.ndarray] = None


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------
def check_heights(heights: np.ndarray, name: str = 'heights') -> np.ndarray:
    """float64 copy of a 2-D height map; ValueError on wrong shape, inf, or no known cell."""
    h = np.array(heights, dtype=np.float64)
    if h.ndim != 2 or h.size == 0:
        raise ValueError(f'{name} must be a non-empty 2-D (nx, ny) array, got shape {h.shape}')
    if np.isinf(h).any():
        raise ValueError(f'{name} contain +-inf in {int(np.isinf(h).sum())} cells; '
                         'use NaN for unknown cells')
    if not np.isfinite(h).any():
        raise ValueError(f'{name}: every cell is unknown, there is nothing to fill from')
    return h


def check_bounds(heights: np.ndarray, upper_bound: Optional[np.ndarray],
                 tol_m: float = 1e-6) -> np.ndarray:
    """float64 bound map (+inf = no bound) checked against the heights.

    Raises ValueError when the shapes differ, a bound is -inf, or an observed height lies more
    than ``tol_m`` above its bound (the bounds and the heights then cannot both be right).
    """
    if upper_bound is None:
        return np.full(heights.shape, np.inf)
    ub = np.array(upper_bound, dtype=np.float64)
    if ub.shape != heights.shape:
        raise ValueError(f'upper_bound has shape {ub.shape}, heights {heights.shape}')
    if np.isneginf(ub).any():
        raise ValueError('upper_bound contains -inf')
    ub = np.where(np.isnan(ub), np.inf, ub)
    with np.errstate(invalid='ignore'):
        bad = np.isfinite(heights) & (heights > ub + tol_m)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise ValueError(f'{int(bad.sum())} observed heights lie above their line-of-sight '
                         f'upper bound (e.g. cell [{i}, {j}]: height {heights[i, j]:.4f} m > '
                         f'bound {ub[i, j]:.4f} m)')
    return ub


# --------------------------------------------------------------------------------------------
# line-of-sight bounds
# --------------------------------------------------------------------------------------------
def _ray_samples(a, p, za, zp, t0, t1, full_len, step, nx, ny, chunk):
    """Yield (ray index, t, cell index (k, 2), z) for samples every ``step`` cells along each
    ray's x-y footprint between parameters t0 and t1 (both ends included), in memory chunks."""
    nsamp = np.maximum(np.ceil(full_len * (t1 - t0) / step).astype(np.int64), 1) + 1
    cums = np.cumsum(nsamp)
    start = 0
    while start < len(nsamp):
        base = cums[start - 1] if start else 0
        stop = max(int(np.searchsorted(cums, base + chunk, side='right')), start + 1)
        ns = nsamp[start:stop]
        rays = np.repeat(np.arange(start, stop), ns)
        first = np.repeat(np.cumsum(ns) - ns, ns)
        frac = (np.arange(rays.size) - first) / (nsamp[rays] - 1).astype(np.float64)
        t = t0[rays] + (t1[rays] - t0[rays]) * frac
        xy = a[rays] + t[:, None] * (p[rays] - a[rays])
        z = za[rays] + t * (zp[rays] - za[rays])
        yield rays, t, np.floor(xy).astype(np.int64), z
        start = stop


def line_of_sight_bounds(shape: Tuple[int, int], resolution_m: float, origin_xy: Sequence[float],
                         origins: np.ndarray, points: np.ndarray,
                         config: BoundsConfig = BoundsConfig(),
                         target: Optional[np.ndarray] = None,
                         ceiling_m: Optional[float] = None) -> np.ndarray:
    """Upper bounds H-bar [m] from rays camera -> observed point (paper 000, sec. III, Fig. 5).

    Args:
        shape: (nx, ny) of the grid.
        resolution_m: cell edge [m/cell].
        origin_xy: world (x, y) of the grid's minimum corner [m].
        origins: (N, 3) or (3,) camera positions [m] in the grid frame, one per ray or one for
            all.
        points: (N, 3) observed surface points [m] in the grid frame (NaN rows are skipped).
        config: sampling step, centre radius, safety margin, memory chunk.
        target: optional (nx, ny) bool: only these cells get bounds (the unobserved ones, say);
            the rest are NaN. Saves the reduction work, not the rasterisation.
        ceiling_m: optional height [m]: the part of each ray above it is skipped (a bound
            that high constrains nothing); cells crossed only there get no bound.

    Returns:
        (nx, ny) float64 bound [m]; NaN where no ray passed over the cell.
    """
    nx, ny = (int(v) for v in shape)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    org = np.asarray(origins, dtype=np.float64)
    if org.ndim == 1:
        org = np.broadcast_to(org.reshape(1, 3), pts.shape)
    org = org.reshape(-1, 3)
    if org.shape != pts.shape:
        raise ValueError(f'origins {org.shape} and points {pts.shape} do not pair up')
    if target is not None and np.shape(target) != (nx, ny):
        raise ValueError(f'target mask has shape {np.shape(target)}, the grid is {(nx, ny)}')
    ok = np.isfinite(pts).all(1) & np.isfinite(org).all(1)
    pts, org = pts[ok], org[ok]
    bound = np.full(nx * ny, np.inf)
    tgt = None if target is None else np.asarray(target, bool).ravel()
    if len(pts) == 0:
        return np.full((nx, ny), np.nan)
    o_xy = np.asarray(origin_xy, dtype=np.float64)
    # continuous cell coordinates: cell [i, j] spans [i, i+1) x [j, j+1)
    a = (org[:, :2] - o_xy) / resolution_m
    p = (pts[:, :2] - o_xy) / resolution_m
    za, zp = org[:, 2], pts[:, 2]
    t0 = np.zeros(len(pts))
    if ceiling_m is not None:
        dz = za - zp
        with np.errstate(divide='ignore', invalid='ignore'):
            t0 = np.where(dz > 0, np.clip((za - ceiling_m) / dz, 0.0, 1.0), 0.0)
    t1 = np.ones(len(pts))
    full_len = np.linalg.norm(p - a, axis=1)
    if tgt is not None:
        # coarse pass (1-cell steps) over the target grown by 2 cells: keep only the stretch
        # of each ray that can reach a target cell
        from scipy import ndimage
        near = ndimage.binary_dilation(tgt.reshape(nx, ny), np.ones((5, 5), bool)).ravel()
        lo, hi = np.full(len(pts), np.inf), np.full(len(pts), -np.inf)
        for rays, t, ij, _ in _ray_samples(a, p, za, zp, t0, t1, full_len, 1.0, nx, ny,
                                            config.chunk_samples):
            inside = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
            hit = np.zeros(len(t), bool)
            hit[inside] = near[ij[inside, 0] * ny + ij[inside, 1]]
            np.minimum.at(lo, rays[hit], t[hit])
            np.maximum.at(hi, rays[hit], t[hit])
        pad = 2.0 / np.maximum(full_len, 1e-9)          # two cells of slack either side
        use = np.isfinite(lo)
        t0 = np.where(use, np.maximum(t0, lo - pad), t0)
        t1 = np.where(use, np.minimum(1.0, hi + pad), t1)
        keep_rays = use & (t1 > t0)
        a, p, za, zp, t0, t1, full_len = (v[keep_rays] for v in (a, p, za, zp, t0, t1,
                                                                   full_len))
    end_cell = np.floor(p).astype(np.int64)
    for rays, t, ij, z in _ray_samples(a, p, za, zp, t0, t1, full_len, config.step_cells, nx,
                                        ny, config.chunk_samples):
        keep = ((ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
                & ~((ij[:, 0] == end_cell[rays, 0]) & (ij[:, 1] == end_cell[rays, 1])))
        if config.center_radius_cells < 0.5:
            xy = a[rays] + t[:, None] * (p[rays] - a[rays])
            keep &= (np.abs(xy - ij - 0.5) <= config.center_radius_cells).all(1)
        flat = ij[keep, 0] * ny + ij[keep, 1]
        zk = z[keep]
        if tgt is not None:
            sel = tgt[flat]
            flat, zk = flat[sel], zk[sel]
        np.minimum.at(bound, flat, zk)
    bound = bound.reshape(nx, ny) + config.margin_m
    return np.where(np.isfinite(bound), bound, np.nan)


def bounds_from_captures(heights: np.ndarray, resolution_m: float, origin_xy: Sequence[float],
                         camera_positions: np.ndarray, max_range_m: float = 1.0,
                         tol_m: float = 0.0, angular_step_rad: float = 0.0,
                         target: Optional[np.ndarray] = None,
                         camera_axes: Optional[np.ndarray] = None,
                         fov_half_angle_rad: float = np.pi,
                         range_step_cells: float = 0.5) -> np.ndarray:
    """Line-of-sight bounds [m] for a map that does not record which camera saw which cell.

    A viewshed per capture along a fan of rays: from each camera's x-y position, rays every
    ``angular_step_rad`` (default: half a cell at ``max_range_m``) are sampled every
    ``range_step_cells``; every sample takes the height of the cell it lies in (cells are flat
    tops). Along a ray with elevation slope ``s = (h - z_cam) / r``, an observed sample is seen
    when ``s`` is not below the steepest slope in front of it (within ``tol_m``): the classic
    horizon test, with only observed cells as occluders (an unobserved one cannot be
    detected). A sample in front of a seen sample lies under the line of sight to that cell's
    centre, so a target cell it falls in gets the bound ``z_cam + r * min(s_centre of the seen
    samples beyond)`` (``s_centre`` = slope to the seen cell's centre, ``r`` = distance to the
    target cell's centre: cell heights are the surface at cell centres); the
    minimum over samples and captures is kept. Only seen samples inside the view cone
    (``camera_axes``, ``fov_half_angle_rad``) and within ``max_range_m`` (3-D) count: a camera
    vouches only for what it looked at.

    Args:
        heights: (nx, ny) observed heights [m], NaN = unobserved.
        resolution_m, origin_xy: grid geometry [m].
        camera_positions: (K, 3) camera centres [m] in the grid frame.
        max_range_m: farthest 3-D distance [m] a capture is assumed to measure.
        tol_m: height tolerance [m] of the horizon test (map noise).
        angular_step_rad: azimuth step of the ray fan [rad]; 0 = automatic.
        target: optional (nx, ny) bool of the cells that want bounds (default: unobserved).
        camera_axes: optional (K, 3) viewing directions (optical z axes) in the grid frame.
        fov_half_angle_rad: half-angle of the view cone around each axis [rad].
        range_step_cells: sample spacing along each ray [cells].

    Returns:
        (nx, ny) float64 bounds [m]; NaN = no bound (and on non-target cells).
    """
    h = np.asarray(heights, np.float64)
    nx, ny = h.shape
    observed = np.isfinite(h)
    tgt = ~observed if target is None else np.asarray(target, bool)
    step = angular_step_rad if angular_step_rad > 0 else 0.5 * resolution_m / max_range_m
    o_xy = np.asarray(origin_xy, np.float64)
    cams = np.asarray(camera_positions, np.float64).reshape(-1, 3)
    axes = None
    if camera_axes is not None and fov_half_angle_rad < np.pi:
        axes = np.asarray(camera_axes, np.float64).reshape(-1, 3)
        if axes.shape != cams.shape:
            raise ValueError(f'camera_axes {axes.shape} and positions {cams.shape} differ')
        axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    cos_fov = np.cos(fov_half_angle_rad)
    rr = np.arange(1, int(np.ceil(max_range_m / (range_step_cells * resolution_m))) + 1) \
        * range_step_cells * resolution_m
    hflat = np.ascontiguousarray(h).ravel()
    tgt_flat = np.ascontiguousarray(tgt).ravel()
    bound = np.full(nx * ny, np.inf)
    for k, c in enumerate(cams):
        if not np.isfinite(c).all():
            continue
        az = np.arange(-np.pi, np.pi, step)
        if axes is not None:
            # keep azimuths whose vertical half-plane can meet the view cone at all: the
            # largest cosine to the axis in the half-plane is |(a_h cos(dphi), a_z)|
            a_h = np.hypot(axes[k, 0], axes[k, 1])
            cphi = np.cos(az - np.arctan2(axes[k, 1], axes[k, 0]))
            best = np.where(cphi > 0, np.hypot(a_h * cphi, axes[k, 2]), abs(axes[k, 2]))
            az = az[best >= cos_fov - 1e-9]
            if az.size == 0:
                continue
        if _kernels is not None:
            # the same per-sample arithmetic, ray by ray (bitwise equal; _fill_kernels)
            ax = axes[k] if axes is not None else np.zeros(3)
            _kernels.viewshed_bounds(hflat, nx, ny, float(o_xy[0]), float(o_xy[1]),
                                     float(resolution_m), np.ascontiguousarray(c),
                                     np.cos(az), np.sin(az), rr, float(tol_m),
                                     float(max_range_m), axes is not None,
                                     np.ascontiguousarray(ax), float(cos_fov), tgt_flat, bound)
            continue
        x = c[0] + np.cos(az)[:, None] * rr[None, :]              # (n_az, n_r)
        y = c[1] + np.sin(az)[:, None] * rr[None, :]
        i = np.floor((x - o_xy[0]) / resolution_m).astype(np.int64)
        j = np.floor((y - o_xy[1]) / resolution_m).astype(np.int64)
        inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        flat = np.where(inside, i * ny + j, 0)
        hz = np.where(inside, hflat[flat], np.nan)
        obs = np.isfinite(hz)
        slope = np.where(obs, (hz - c[2]) / rr, -np.inf)
        front = np.maximum.accumulate(slope, axis=1)
        front = np.concatenate([np.full((len(az), 1), -np.inf), front[:, :-1]], axis=1)
        seen = obs & (slope >= front - tol_m / rr)
        dz = np.where(obs, hz - c[2], 0.0)
        seen &= rr * rr + dz * dz <= max_range_m ** 2
        if axes is not None:
            d3 = np.sqrt(rr * rr + dz * dz)
            cosang = (np.cos(az)[:, None] * rr * axes[k, 0] + np.sin(az)[:, None] * rr
                      * axes[k, 1] + dz * axes[k, 2]) / d3
            seen &= cosang >= cos_fov
        # the line of sight ends on the seen cell's centre (where its height was measured),
        # not on the sample: a flat-topped cell seen at its near edge would otherwise give a
        # ray lower than the real one
        rcen = np.hypot(o_xy[0] + (i + 0.5) * resolution_m - c[0],
                        o_xy[1] + (j + 0.5) * resolution_m - c[1])
        with np.errstate(divide='ignore', invalid='ignore'):
            slope_end = (hz - c[2]) / rcen
        beyond = np.where(seen, slope_end, np.inf)[:, ::-1]
        beyond = np.minimum.accumulate(beyond, axis=1)[:, ::-1]
        beyond = np.concatenate([beyond[:, 1:], np.full((len(az), 1), np.inf)], axis=1)
        want = inside & np.isfinite(beyond) & tgt.ravel()[flat]
        # evaluated at the target cell's centre distance: the map's height of a cell is the
        # surface at its centre, and the line dips lowest at the far edge of a flat top
        np.minimum.at(bound, flat[want], (c[2] + rcen * beyond)[want])
    bound = np.where(tgt.ravel() & np.isfinite(bound), bound, np.nan)
    return bound.reshape(nx, ny)


# --------------------------------------------------------------------------------------------
# the library
# --------------------------------------------------------------------------------------------
class PatchLibrary:
    """All w x w patches of a list of fully known height maps, addressed by one global index.

    Position ``g`` (0 <= g < total) runs over the terrains in order and, inside a terrain, over
    patch corners ``(i, j)`` in row-major order.
    """

    def __init__(self, terrains: Sequence[np.ndarray], w: int,
                 bank_max_mb: float = 256.0) -> None:
        if w < 1 or w % 2 == 0:
            raise ValueError(f'window must be a positive odd number of cells, got {w}')
        if terrains is None or len(terrains) == 0:
            raise ValueError('the terrain library is empty')
        self.w = int(w)
        flats, self.starts, self.counts, self.pcols, self.strides, self.bases = [], [], [], [], \
            [], []
        total, base = 0, 0
        for k, t in enumerate(terrains):
            t = np.asarray(t, dtype=np.float64)
            if t.ndim != 2:
                raise ValueError(f'library terrain {k} is not 2-D (shape {t.shape})')
            if not np.isfinite(t).all():
                raise ValueError(f'library terrain {k} has {int((~np.isfinite(t)).sum())} '
                                 'unknown or infinite cells; the library must be fully known')
            if t.shape[0] < w or t.shape[1] < w:
                raise ValueError(f'library terrain {k} ({t.shape}) is smaller than the '
                                 f'{w}x{w} window')
            pr, pc = t.shape[0] - w + 1, t.shape[1] - w + 1
            self.starts.append(total)
            self.counts.append(pr * pc)
            self.pcols.append(pc)
            self.strides.append(t.shape[1])
            self.bases.append(base)
            flats.append(t.ravel())
            total += pr * pc
            base += t.size
        self.total = total
        self.flat = np.concatenate(flats)
        self.starts = np.asarray(self.starts, np.int64)
        self.pcols = np.asarray(self.pcols, np.int64)
        self.strides = np.asarray(self.strides, np.int64)
        self.bases = np.asarray(self.bases, np.int64)
        du, dv = np.meshgrid(np.arange(w), np.arange(w), indexing='ij')
        self._du, self._dv = du.ravel(), dv.ravel()
        # Every patch as one contiguous row: a sample is then one row copy instead of w*w
        # scattered reads (about 2x faster to gather), at total * w^2 * 8 bytes of memory.
        self.bank = None
        if total * w * w * 8 <= bank_max_mb * 1e6:
            from numpy.lib.stride_tricks import sliding_window_view
            self.bank = np.concatenate([
                sliding_window_view(np.asarray(t, np.float64), (w, w)).reshape(-1, w * w)
                for t in terrains])

    def positions(self, u: np.ndarray) -> np.ndarray:
        """Global patch positions from uniform doubles ``u`` in [0, 1)."""
        return np.minimum((u * self.total).astype(np.int64), self.total - 1)

    def patches(self, g: np.ndarray) -> np.ndarray:
        """Patches ``(..., w*w)`` (row-major) at global positions ``g`` ``(...)``."""
        g = np.asarray(g, np.int64)
        if self.bank is not None:
            return np.take(self.bank, g, axis=0)
        t = np.searchsorted(self.starts, g, side='right') - 1
        local = g - self.starts[t]
        i, j = np.divmod(local, self.pcols[t])
        corner = self.bases[t] + i * self.strides[t] + j
        idx = corner[..., None] + self._du * self.strides[t][..., None] + self._dv
        return self.flat[idx]


def gaussian_weights(w: int, sigma_cells: float) -> np.ndarray:
    """The w x w weighting matrix W of Fig. 6: a Gaussian of ``sigma_cells`` [cells]."""
    u = np.arange(w) - (w - 1) / 2.0
    g = np.exp(-0.5 * (u / sigma_cells) ** 2)
    return np.outer(g, g)


# --------------------------------------------------------------------------------------------
# Fill-Terrain
# --------------------------------------------------------------------------------------------
def select_round(known: np.ndarray, rank: np.ndarray, w: int,
                 todo: Optional[np.ndarray] = None,
                 box: Optional[np.ndarray] = None) -> np.ndarray:
    """Flat indices (ascending) of the cells filled in this round (see module docstring).

    A missing cell is selected when its key ``known_count * N + rank`` (N = cells in the map)
    beats every other missing cell in its w x w window; cells with no known cell in their
    window wait. ``todo`` (bool, optional) limits the candidates: other missing cells are left
    unknown and neither compete nor count as known. Works on the bounding box of the
    candidates plus the window margin; empty when no candidate has a known neighbour.
    ``box`` (optional int64 (4,), compiled code only): rows i0:i1, columns j0:j1 holding every
    candidate, tightened in place (fill_terrain passes the last round's).
    """
    if _kernels is not None:
        out = np.empty(known.size, np.int64)
        if box is None:
            box = np.array([0, known.shape[0], 0, known.shape[1]], np.int64)
        n = _kernels.select_round(known, known if todo is None else todo, todo is not None,
                                  rank, int(w), box, out)
        return out[:n]
    import cv2
    nx, ny = known.shape
    r = w // 2
    want = ~known if todo is None else todo & ~known
    miss_i = np.flatnonzero(want.any(1))
    miss_j = np.flatnonzero(want.any(0))
    if miss_i.size == 0:
        return np.zeros(0, np.int64)
    i0, i1 = max(miss_i[0] - r, 0), min(miss_i[-1] + r + 1, nx)
    j0, j1 = max(miss_j[0] - r, 0), min(miss_j[-1] + r + 1, ny)
    kn = known[i0:i1, j0:j1]
    # exact small-integer counts in float32; outside the grid counts as unknown
    count = cv2.boxFilter(kn.astype(np.float32), -1, (w, w), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    cand = want[i0:i1, j0:j1] & (count > 0.5)
    key = np.where(cand, np.rint(count).astype(np.float64) * known.size + rank[i0:i1, j0:j1],
                   -1.0)
    local_max = cv2.dilate(key, np.ones((w, w), np.uint8), borderType=cv2.BORDER_CONSTANT,
                           borderValue=-1.0)
    li, lj = np.nonzero(cand & (key == local_max))
    return (li + i0) * ny + (lj + j0)


def _choose(A, B, Abar, C, W):
    """Fig. 6 steps 2-3 for a block of S cells.

    A, B, Abar: (S, q) window heights, known mask, bounds (+inf = none); C: (S, n, q) library
    patches; W: (q,) weights. Returns the chosen heights (S,) and sample indices (S,).
    """
    B = B.astype(np.float64)
    m = B.sum(1)                                                        # (S,)
    Az = np.where(B > 0, A, 0.0)
    WB = W[None, :] * B
    # s_k = sum W B (C - A + b)^2, expanded so that C is only read by three reductions
    sums = np.matmul(C, np.stack([B, WB, WB * Az], -1))                # (S, n, 3)
    sum_bc, sum_wbc, sum_wbca = sums[..., 0], sums[..., 1], sums[..., 2]
    b = ((Az.sum(1))[:, None] - sum_bc) / m[:, None]                    # (S, n)
    sum_wbcc = np.einsum('snq,snq,sq->sn', C, C, WB)
    sum_wba = (WB * Az).sum(1)[:, None]
    sum_wbaa = (WB * Az * Az).sum(1)[:, None]
    s = (sum_wbcc - 2.0 * sum_wbca + sum_wbaa + 2.0 * b * (sum_wbc - sum_wba)
         + b * b * WB.sum(1)[:, None])
    centre = C.shape[2] // 2
    h = C[:, :, centre] + b
    if _kernels is not None:
        k = np.empty(len(b), np.int64)
        any_ok = np.empty(len(b), bool)
        c = np.ascontiguousarray
        _kernels.feasible_argmin(c(C), c(Abar), c(b), c(s), k, any_ok)
    else:
        # feasibility (v_k = 0) needs only the largest excess of the patch over the bound
        ok = np.ones(b.shape, bool)
        bounded = np.isfinite(Abar).any(1)
        if bounded.all():
            ok = (C - Abar[:, None, :]).max(2) + b <= 0.0
        elif bounded.any():
            excess = (C[bounded] - Abar[bounded][:, None, :]).max(2)   # (Sb, n)
            ok[bounded] = excess + b[bounded] <= 0.0
        any_ok = ok.any(1)
        k = np.argmin(np.where(ok, s, np.inf), 1)
    if not any_ok.all():
        bad = ~any_ok
        over = np.maximum(C[bad] + b[bad][:, :, None] - Abar[bad][:, None, :], 0.0)
        k[bad] = np.argmin(np.einsum('snq,snq->sn', over, over), 1)
    rows = np.arange(len(k))
    return h[rows, k], k


def fill_terrain(heights: np.ndarray, upper_bound: Optional[np.ndarray],
                 library: Sequence[np.ndarray], config: FillConfig = FillConfig(),
                 constrained: bool = True,
                 fill_mask: Optional[np.ndarray] = None) -> FillResult:
    """Fill every missing cell by Fill-Terrain (paper 000, Fig. 6), vectorised per round.

    Args:
        heights: (nx, ny) heights [m], NaN = missing; at least one cell known.
        upper_bound: (nx, ny) line-of-sight bounds [m], NaN/None = no bound.
        library: fully known height maps at the same resolution as ``heights``, or a
            :class:`PatchLibrary` built from them (reuse it across calls: building is ~0.1 s).
        config: window, samples, weighting, seed, batch size.
        constrained: False ignores the bounds (texture synthesis without constraints).
        fill_mask: optional (nx, ny) bool: fill only these missing cells; the other missing
            cells stay NaN and are never context. Cells of the mask that never get a known
            cell within their window (no context at all) stay NaN too. None = fill all (the
            random draws are then exactly those of the unmasked algorithm).

    Returns:
        :class:`FillResult` (heights float64, filled mask, rounds, chosen library positions).

    Raises:
        ValueError: bad heights/bounds/library (see :func:`check_heights`, :func:`check_bounds`,
            :class:`PatchLibrary`).
    """
    H = check_heights(heights)
    ub = check_bounds(H, upper_bound)
    if not constrained:
        ub = np.full(H.shape, np.inf)
    w = int(config.window_cells)
    lib = library if isinstance(library, PatchLibrary) else PatchLibrary(library, w)
    if lib.w != w:
        raise ValueError(f'the patch library was built for w = {lib.w}, the config asks {w}')
    r = w // 2
    nx, ny = H.shape
    known = np.isfinite(H)
    missing0 = ~known
    todo = None
    if fill_mask is not None:
        if np.shape(fill_mask) != H.shape:
            raise ValueError(f'fill_mask has shape {np.shape(fill_mask)}, heights {H.shape}')
        todo = missing0 & np.asarray(fill_mask, bool)
    rng = np.random.default_rng(config.seed)
    rank = rng.permutation(nx * ny).reshape(nx, ny)
    W = gaussian_weights(w, config.weight_sigma_cells).ravel()
    # padded views: outside the grid = unknown, no bound
    Hp = np.pad(np.where(known, H, 0.0), r)
    Kp = np.pad(known, r)
    Up = np.pad(ub, r, constant_values=np.inf)
    nyp = ny + 2 * r
    du, dv = np.meshgrid(np.arange(w), np.arange(w), indexing='ij')
    offs = (du * nyp + dv).ravel()
    Hpf, Kpf, Upf = Hp.ravel(), Kp.ravel(), Up.ravel()
    choice = np.full(nx * ny, -1, np.int64)
    rounds = 0
    n = int(config.samples)
    per_block = max(1, int(config.batch_cells))
    box = np.array([0, nx, 0, ny], np.int64)      # where candidates can still be
    while not known.all() if todo is None else (todo & ~known).any():
        sel = select_round(known, rank, w, todo, box)
        if sel.size == 0:            # only masked cells without any context are left
            break
        rounds += 1
        u = rng.random((len(sel), n))
        si, sj = np.divmod(sel, ny)
        corner = si * nyp + sj                      # window corner in padded coordinates
        for a in range(0, len(sel), per_block):
            blk = slice(a, a + per_block)
            g = lib.positions(u[blk])
            if _kernels is not None and lib.bank is not None:
                # compiled: windows and samples read in place (equal to _choose within
                # rounding; _fill_kernels.choose_block)
                hbest = np.empty(len(g))
                k = np.empty(len(g), np.int64)
                _kernels.choose_block(Hpf, Kpf, Upf, corner[blk], offs, lib.bank, g, W,
                                      hbest, k)
            else:
                idx = corner[blk, None] + offs[None, :]
                hbest, k = _choose(Hpf[idx], Kpf[idx], Upf[idx], lib.patches(g), W)
            cells = sel[blk]
            ci, cj = si[blk], sj[blk]
            Hpf[(ci + r) * nyp + cj + r] = hbest
            Kpf[(ci + r) * nyp + cj + r] = True
            choice[cells] = g[np.arange(len(k)), k]
        known.ravel()[sel] = True
    out = Hp[r:r + nx, r:r + ny].copy()
    filled = missing0 & known
    out[~known] = np.nan
    return FillResult(out, filled, rounds, choice.reshape(nx, ny))


# --------------------------------------------------------------------------------------------
# baselines (same interface)
# --------------------------------------------------------------------------------------------
def _nearest_fill(h: np.ndarray) -> np.ndarray:
    known = np.isfinite(h)
    _, (ii, jj) = ndimage.distance_transform_edt(~known, return_indices=True)
    return h[ii, jj]


def fill_constraints_as_heights(heights: np.ndarray,
                                upper_bound: Optional[np.ndarray]) -> FillResult:
    """Missing cells take their line-of-sight bound as height (Table I row 3); cells with no
    bound take the nearest bounded-or-observed value (Euclidean distance transform)."""
    H = check_heights(heights)
    ub = check_bounds(H, upper_bound)
    missing = ~np.isfinite(H)
    out = np.where(missing & np.isfinite(ub), ub, H)
    return FillResult(_nearest_fill(out), missing)


def fill_constant(heights: np.ndarray, value: Optional[float] = None) -> FillResult:
    """Missing cells take one constant [m]: ``value`` (the benchmark passes the optimum, the
    mean of the true missing heights) or, by default, the mean observed height."""
    H = check_heights(heights)
    missing = ~np.isfinite(H)
    c = float(np.nanmean(H)) if value is None else float(value)
    return FillResult(np.where(missing, c, H), missing)


def fill_inpaint(heights: np.ndarray, radius_cells: float = 3.0,
                 flags: str = 'ns') -> FillResult:
    """OpenCV inpainting of the missing heights without 8-bit quantisation.

    ``'ns'`` (Navier-Stokes) runs on float32 heights directly (cv2.inpaint accepts CV_32FC1),
    shifted by their mean so float32 keeps ~1e-8 m. ``'telea'`` runs on 16-bit heights scaled
    to the observed range (step = range / 65535, 1.5 um for a 10 cm range): OpenCV 5.0's Telea
    on CV_32F adds errors of about +-1 (in the image's units, whatever the scale), so its float
    path cannot be used (test_fill checks both paths against a flat surround).
    """
    import cv2
    H = check_heights(heights)
    missing = ~np.isfinite(H)
    mask = missing.astype(np.uint8)
    if flags == 'telea':
        lo, hi = float(np.nanmin(H)), float(np.nanmax(H))
        scale = 65535.0 / (hi - lo) if hi > lo else 1.0
        src = np.where(missing, 0.0, np.rint((H - lo) * scale)).astype(np.uint16)
        out = cv2.inpaint(src, mask, float(radius_cells), cv2.INPAINT_TELEA)
        res = out.astype(np.float64) / scale + lo
    elif flags == 'ns':
        off = float(np.nanmean(H))
        src = np.where(missing, 0.0, H - off).astype(np.float32)
        out = cv2.inpaint(src, mask, float(radius_cells), cv2.INPAINT_NS)
        res = out.astype(np.float64) + off
    else:
        raise ValueError(f'unknown inpaint method {flags!r}; use telea or ns')
    return FillResult(np.where(missing, res, H), missing)


def fill_shao_rows(heights: np.ndarray, axis: int = 1) -> FillResult:
    """Shao's row-neighbour fill (paper 002, sec. II-C): an empty cell takes the value of the
    nearest known cell in the same row (``axis`` = the direction a row runs; ties go to the
    lower index). Rows with no known cell at all, which the paper does not cover, take the
    nearest known cell in 2-D."""
    H = check_heights(heights)
    missing = ~np.isfinite(H)
    h = H if axis == 1 else H.T
    known = np.isfinite(h)
    n = h.shape[1]
    idx = np.arange(n)[None, :].repeat(h.shape[0], 0)
    prev = np.maximum.accumulate(np.where(known, idx, -1), axis=1)
    nxt = np.minimum.accumulate(np.where(known, idx, n)[:, ::-1], axis=1)[:, ::-1]
    dprev = np.where(prev >= 0, idx - prev, np.iinfo(np.int64).max)
    dnext = np.where(nxt < n, nxt - idx, np.iinfo(np.int64).max)
    src = np.where(dprev <= dnext, prev, nxt)
    rows = np.arange(h.shape[0])[:, None]
    has = (prev >= 0) | (nxt < n)
    out = np.where(has, h[rows, np.clip(src, 0, n - 1)], np.nan)
    out = out if axis == 1 else out.T
    if np.isnan(out).any():
        out = _nearest_fill(out)
    return FillResult(out, missing)


def fill(heights: np.ndarray, upper_bound: Optional[np.ndarray] = None,
         library: Optional[Sequence[np.ndarray]] = None,
         config: FillConfig = FillConfig(), constant: Optional[float] = None) -> FillResult:
    """Dispatch to ``config.method``; every method takes the same inputs.

    ``'none'`` leaves the map as it is (the "ignore missing heights" baseline: the cost
    function then ignores the missing cells). ``constant`` is the value for ``'constant'``.
    """
    method = config.method
    if method == 'fill_terrain':
        return fill_terrain(heights, upper_bound, library, config, True)
    if method == 'texture_synthesis':
        return fill_terrain(heights, upper_bound, library, config, False)
    if method == 'constraints_as_heights':
        return fill_constraints_as_heights(heights, upper_bound)
    if method == 'constant':
        return fill_constant(heights, constant)
    if method == 'inpaint':
        return fill_inpaint(heights, config.inpaint_radius_cells, config.inpaint_flags)
    if method == 'shao_rows':
        return fill_shao_rows(heights, config.shao_row_axis)
    if method == 'none':
        H = check_heights(heights)
        check_bounds(H, upper_bound)
        return FillResult(H, np.zeros(H.shape, bool))
    raise ValueError(f'unknown fill method {method!r}; use one of {FILL_METHODS}')


# --------------------------------------------------------------------------------------------
# incremental filling of a changing map (what terrain_fill_node runs)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RayConfig:
    """How :class:`TerrainFiller` reconstructs lines of sight from capture positions."""

    max_range_m: float = param(1.0, 'farthest observed cell paired with a capture position '
                               '[m] (the range the camera measures)', 0.05, 100.0)
    tol_m: float = param(0.0, 'an observed cell this far below the horizon still counts as '
                         'seen from a capture [m]; > 0 tolerates map noise but lets rays dip '
                         'below occluders (bounds up to tol_m too low)', 0.0, 1.0)
    angular_step_rad: float = param(0.0, 'azimuth bin of the per-capture viewshed [rad]; '
                                    '0 = half a cell at max_range_m', 0.0, 0.5)
    fov_half_angle_deg: float = param(
        40.0, 'only cells within this angle of a capture\'s optical axis are used for its '
        'bounds [deg] (LittleDog: 62 x 58 deg field of view, ~42 deg to the corners); 180 = '
        'all around', 1.0, 180.0)


BLIND_AREA_POLICIES = ('unknown', 'texture')


@dataclass(frozen=True)
class FillerConfig:
    """How :class:`TerrainFiller` updates its output when the map changes."""

    blind_area: str = param(
        'unknown', 'never-observed cells that no line of sight crossed (behind and under the '
        'robot, outside every view): unknown = left NaN (filled 0, cost NaN: the planner '
        'treats them as unobserved); texture = filled like the bounded ones (library texture '
        'with no constraint: invents rocks on flat ground)', choices=BLIND_AREA_POLICIES)
    refill_margin_cells: int = param(
        3, 'unobserved cells within this many cells of a changed cell (new height, new or '
        'tighter bound, new cell after a grid move) are refilled; the other fills are kept '
        'and act as context [cells] (w // 2 + 1: the cells whose window saw the change, and '
        'one ring more)', 0, 10000)
    whole_hole_cells: int = param(
        200, 'a touched hole (8-connected fillable region) of at most this many cells is '
        'refilled whole (no seam in small holes); larger ones only near the change [cells]',
        0, 10 ** 8)
    contact_support_radius_m: float = param(
        0.06, 'blind cells within this distance of a foot the robot stands on take the height '
              'of the plane through its stance feet (paper 002 treats the blind area as the '
              'ground plane; here only where the feet prove it), layer `contact` = 1; kept '
              'until observed [m] (0 = off)', 0.0, 10.0)


CONTACT = 'contact'
"""Output layer: 1 where the height is the plane through the robot's stance feet."""


def _contact_support(grid, feet: np.ndarray, radius_m: float) -> tuple:
    """``(mask, z)`` on ``grid``: cells within ``radius_m`` of a foot contact point
    ``feet`` (K >= 3, 3), and the least-squares plane ``z = a x + b y + c`` through the feet
    [m] (at least on the mask's cells; NaN outside the box around the feet)."""
    A = np.c_[feet[:, :2], np.ones(len(feet))]
    coef, *_ = np.linalg.lstsq(A, feet[:, 2], rcond=None)
    nx, ny = grid.shape
    r = grid.resolution_m
    x = grid.origin_xy[0] + (np.arange(nx) + 0.5) * r
    y = grid.origin_xy[1] + (np.arange(ny) + 0.5) * r
    mask = np.zeros((nx, ny), bool)
    z = np.full((nx, ny), np.nan)
    # Only the box of rows and columns within the radius of some foot along that axis can
    # hold a cell within the radius ((dx^2 + dy^2) >= dx^2 in floating point too); the cells
    # in it get the same arithmetic as over the whole grid (~7 ms on 300 x 300 cells).
    r2 = radius_m ** 2
    rows = np.flatnonzero(((x[:, None] - feet[:, 0]) ** 2 <= r2).any(1))
    cols = np.flatnonzero(((y[:, None] - feet[:, 1]) ** 2 <= r2).any(1))
    if rows.size and cols.size:
        box = slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)
        X, Y = np.meshgrid(x[box[0]], y[box[1]], indexing='ij')
        d2 = np.min((X[..., None] - feet[:, 0]) ** 2 + (Y[..., None] - feet[:, 1]) ** 2,
                    axis=-1)
        mask[box] = d2 <= r2
        z[box] = coef[0] * X + coef[1] * Y + coef[2]
    return mask, z


def _dilate(mask: np.ndarray, m: int) -> np.ndarray:
    """``mask`` dilated by a (2m+1) x (2m+1) square, outside the grid False: the same cells as
    ``ndimage.binary_dilation`` with that square, ~15x faster (OpenCV on bytes)."""
    import cv2
    m = min(int(m), max(mask.shape))            # a larger square reaches no further
    out = cv2.dilate(np.ascontiguousarray(mask, np.uint8),
                     np.ones((2 * m + 1, 2 * m + 1), np.uint8),
                     borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return out.view(bool)


def _pose_keys(poses: np.ndarray) -> list:
    """Hashable identity of each capture pose (micrometre / 1e-6 rounding)."""
    poses = np.asarray(poses, np.float64)
    flat = poses.reshape(len(poses), int(np.prod(poses.shape[1:])))
    return [np.round(p * 1e6).astype(np.int64).tobytes() for p in flat]


def _shift(a: np.ndarray, off_i: np.ndarray, shape: Tuple[int, int], fill=np.nan) -> np.ndarray:
    """``a`` (on a grid whose origin is ``off_i`` cells before the new one) on the new grid."""
    nx, ny = shape
    dst = np.full((nx, ny), fill, dtype=a.dtype)
    i0, j0 = max(off_i[0], 0), max(off_i[1], 0)
    i1 = min(off_i[0] + nx, a.shape[0])
    j1 = min(off_i[1] + ny, a.shape[1])
    if i1 > i0 and j1 > j0:
        dst[i0 - off_i[0]:i1 - off_i[0], j0 - off_i[1]:j1 - off_i[1]] = a[i0:i1, j0:j1]
    return dst


class TerrainFiller:
    """Keeps a filled copy of a changing height map and updates only what a change touches.

    The fill method is ``fill_config.method`` (Fill-Terrain by default; any baseline works).
    ``update(grid, camera_poses)`` returns a new :class:`~terrain_perception.grid.GridMap`
    with layers ``elevation`` (observed heights + filled ones; NaN = unknown), ``observed``
    (1 = measured; never set by filling), ``upper_bound`` (line-of-sight bound, NaN = none),
    ``filled`` (1 = synthesised) and ``cost`` (:func:`terrain_perception.features.cost_map`).

    Observed cells are those with ``observed == 1`` when the input has that layer, else those
    with a finite elevation. Bounds are the minimum of the input's ``upper_bound`` layer (if
    any) and those reconstructed from the capture poses (:func:`bounds_from_captures`).

    Incremental rules (the grid is a robot-centred window that moves by whole cells):

    * Bounds: a running-minimum bound layer is kept and moved with the grid origin; each
      update adds only the rays of capture poses not seen before (identified by their
      value), cast over the map of that update. A pose dropped from the list keeps its
      contribution (its lines of sight stay true). A resolution change or a move by a
      fraction of a cell starts over from every pose given.
    * Fill: unobserved cells within ``refill_margin_cells`` of a changed cell (new observed
      height, new or tighter bound, cell new after a move) are refilled; every other fill is
      kept and acts as known context.
    * Blind area (``filler_config.blind_area``): never-observed cells without any bound are
      left unknown by default, not textured.
    * Cost: recomputed on the bounding box of every changed height plus the cost windows'
      reach. ``last_region`` is that box ``(i0, i1, j0, j1)`` or None.

    Any ValueError leaves the previous state untouched.
    """

    def __init__(self, library: Sequence[np.ndarray], library_resolution_m: float,
                 fill_config: FillConfig = FillConfig(), cost_config=None,
                 bounds_config: BoundsConfig = BoundsConfig(),
                 ray_config: RayConfig = RayConfig(),
                 filler_config: FillerConfig = FillerConfig()) -> None:
        from terrain_perception.features import CostConfig
        self.fill_config = fill_config
        self.cost_config = cost_config if cost_config is not None else CostConfig()
        self.bounds_config = bounds_config
        self.ray_config = ray_config
        self.filler_config = filler_config
        if filler_config.blind_area not in BLIND_AREA_POLICIES:
            raise ValueError(f'unknown blind_area policy {filler_config.blind_area!r}; use '
                             f'one of {BLIND_AREA_POLICIES}')
        if not np.isfinite(library_resolution_m) or library_resolution_m <= 0:
            raise ValueError(f'library resolution must be positive, got {library_resolution_m}')
        self.library_resolution_m = float(library_resolution_m)
        self.library = PatchLibrary(library, fill_config.window_cells)
        self._prev = None
        self.last_region: Optional[Tuple[int, int, int, int]] = None
        self.last_refilled = 0
        self.last_new_captures = 0

    # -- inputs ----------------------------------------------------------------------------
    @staticmethod
    def observed_heights(grid) -> np.ndarray:
        """float64 heights of the observed cells, NaN elsewhere; ValueError on bad values."""
        from terrain_perception.grid import ELEVATION, OBSERVED
        if ELEVATION not in grid:
            raise ValueError(f'the grid has no {ELEVATION!r} layer (layers: '
                             f'{sorted(grid.layers)})')
        elev = np.asarray(grid[ELEVATION], np.float64)
        if OBSERVED in grid:
            obs = np.asarray(grid[OBSERVED])
            if not np.isin(obs[np.isfinite(obs)], (0.0, 1.0)).all() or np.isnan(obs).any():
                raise ValueError(f'the {OBSERVED!r} layer must hold only 0 and 1')
            mask = obs == 1.0
            bad = mask & ~np.isfinite(elev)
            if bad.any():
                i, j = np.argwhere(bad)[0]
                raise ValueError(f'{int(bad.sum())} cells marked observed have a NaN/inf '
                                 f'elevation (e.g. cell [{i}, {j}])')
        else:
            if np.isinf(elev).any():
                raise ValueError(f'elevation is +-inf in {int(np.isinf(elev).sum())} cells')
            mask = np.isfinite(elev)
        if not mask.any():
            raise ValueError('every cell is unknown: nothing observed to fill from')
        return np.where(mask, elev, np.nan)

    @staticmethod
    def _split_poses(camera_poses: np.ndarray):
        """(positions (K, 3), optical axes (K, 3) or None, raw poses) of the capture poses."""
        poses = np.asarray(camera_poses, np.float64)
        if poses.ndim == 3:
            if poses.shape[1:] != (4, 4):
                raise ValueError(f'camera poses must be (K, 4, 4) or (K, 3), got {poses.shape}')
            return poses[:, :3, 3], poses[:, :3, 2], poses
        poses = poses.reshape(-1, 3)
        return poses, None, poses

    def capture_bounds(self, grid, heights: np.ndarray, camera_poses: np.ndarray) -> np.ndarray:
        """Viewshed bounds [m] of the unobserved cells from these captures alone (NaN = none).

        ``camera_poses``: (K, 4, 4) T_grid_camera (optical frame) or (K, 3) positions."""
        cams, axes, _ = self._split_poses(camera_poses)
        if not len(cams):
            return np.full(heights.shape, np.nan)
        rc = self.ray_config
        return bounds_from_captures(heights, grid.resolution_m, grid.origin_xy, cams,
                                    rc.max_range_m, rc.tol_m, rc.angular_step_rad,
                                    target=~np.isfinite(heights), camera_axes=axes,
                                    fov_half_angle_rad=np.radians(rc.fov_half_angle_deg)
                                    ) + self.bounds_config.margin_m

    def bounds(self, grid, heights: np.ndarray, camera_poses: np.ndarray) -> np.ndarray:
        """Line-of-sight bounds [m] of the unobserved cells from every given capture (NaN =
        none) combined with the grid's ``upper_bound`` layer, checked; no state involved."""
        return self._combine(grid, heights, self.capture_bounds(grid, heights, camera_poses))

    @staticmethod
    def _combine(grid, heights: np.ndarray, los: np.ndarray) -> np.ndarray:
        from terrain_perception.grid import UPPER_BOUND
        ub = los
        if UPPER_BOUND in grid:
            given = np.asarray(grid[UPPER_BOUND], np.float64)
            check_bounds(heights, given)           # refuses bounds below observed heights
            ub = np.fmin(ub, np.where(np.isinf(given), np.nan, given))
        return np.where(np.isfinite(heights), np.nan, ub)

    # -- the update ------------------------------------------------------------------------
    def _aligned_prev(self, grid):
        """Previous arrays moved onto the new grid (NaN where new), or None."""
        prev = self._prev
        if prev is None or abs(prev['res'] - grid.resolution_m) > 1e-9:
            return None
        off = (np.asarray(grid.origin_xy) - np.asarray(prev['origin'])) / grid.resolution_m
        off_i = np.round(off).astype(int)
        if np.any(np.abs(off - off_i) > 1e-6):
            return None
        out = {k: _shift(prev[k], off_i, grid.shape)
               for k in ('obs', 'ub', 'los', 'elev', 'cost')}
        out['contact'] = _shift(prev['contact'], off_i, grid.shape, False)
        out['new'] = _shift(np.ones(prev['obs'].shape, bool), off_i, grid.shape, False) == 0
        out['keys'] = prev['keys']
        return out

    def update(self, grid, camera_poses: np.ndarray = np.zeros((0, 3)),
               stance_feet: Optional[np.ndarray] = None):
        """Fill ``grid`` (a GridMap) and return the output GridMap (see class docstring).

        ``camera_poses``: (K, 4, 4) capture poses T_grid_camera (optical frame, z = viewing
        direction) or (K, 3) positions (then every direction counts as looked at); all the
        captures the map holds, old ones included (only new ones cost work).
        ``stance_feet``: (4, 3) contact points the robot stands on (grid frame), or None: blind
        cells near them take the plane through them (``contact_support_radius_m``)."""
        from terrain_perception.features import cost_map, window_cells
        from terrain_perception.grid import (COST, ELEVATION, FILLED, OBSERVED, UPPER_BOUND,
                                             GridMap)
        if abs(grid.resolution_m - self.library_resolution_m) > 1e-9:
            raise ValueError(f'the grid has {grid.resolution_m:g} m cells but the terrain '
                             f'library {self.library_resolution_m:g} m; they must match')
        heights = self.observed_heights(grid)
        observed = np.isfinite(heights)
        prev = self._aligned_prev(grid)
        # bounds: the running minimum moved with the grid plus the rays of the new captures
        _, _, raw = self._split_poses(camera_poses)
        keys = _pose_keys(raw)
        old = set() if prev is None else prev['keys']
        new = np.array([k not in old for k in keys], bool)
        los = np.full(grid.shape, np.nan) if prev is None else prev['los']
        if new.any():
            los = np.fmin(los, self.capture_bounds(grid, heights, raw[new]))
        los = np.where(observed, np.nan, los)
        ub = self._combine(grid, heights, los)
        w = self.fill_config.window_cells
        fc = self.filler_config
        blind = ~observed & np.isnan(ub)
        # blind cells the feet vouch for: the plane through the stance feet, kept until seen
        contact = np.zeros(grid.shape, bool) if prev is None else prev['contact'] & ~observed
        contact_z = np.full(grid.shape, np.nan) if prev is None else \
            np.where(contact, prev['elev'], np.nan)
        if stance_feet is not None and fc.contact_support_radius_m > 0:
            feet = np.asarray(stance_feet, np.float64).reshape(-1, 3)
            if len(feet) >= 3 and np.all(np.isfinite(feet)):
                new_c, plane_z = _contact_support(grid, feet, fc.contact_support_radius_m)
                new_c &= blind & ~contact
                contact_z[new_c] = plane_z[new_c]
                contact |= new_c
        blind &= ~contact
        fillable = ~observed & ~blind & ~contact if fc.blind_area == 'unknown' else \
            ~observed & ~contact
        same = lambda a, b: (a == b) | (np.isnan(a) & np.isnan(b))  # noqa: E731
        if prev is None:
            refill = fillable
        else:
            # a tighter bound matters only where the kept fill now rises above it (or where a
            # cell had no bound before): a fill below the new bound is still a valid sample
            with np.errstate(invalid='ignore'):
                tighter = ~same(ub, prev['ub']) & (np.isnan(prev['ub']) | ~(prev['elev'] <= ub))
            changed = ~same(heights, prev['obs']) | tighter | prev['new']
            m = int(fc.refill_margin_cells)
            near = _dilate(changed, m) if changed.any() and m > 0 else changed
            # a fillable cell without a kept fill (new, or left unknown last time) is redone
            refill = fillable & (near | np.isnan(prev['elev']))
            if fc.whole_hole_cells > 0 and refill.any():
                labels, _ = ndimage.label(fillable, np.ones((3, 3), bool))
                sizes = np.bincount(labels.ravel())
                hit = np.unique(labels[refill])
                hit = hit[(hit > 0) & (sizes[hit] <= fc.whole_hole_cells)]
                refill |= np.isin(labels, hit)
        elev = np.where(observed, heights, np.nan)
        elev[contact] = contact_z[contact]
        if prev is not None:
            keep = fillable & ~refill
            elev[keep] = prev['elev'][keep]
        self_refilled = int(refill.sum())
        if refill.any():
            ii, jj = np.nonzero(refill)
            i0, i1 = max(ii.min() - w, 0), min(ii.max() + w + 1, grid.shape[0])
            j0, j1 = max(jj.min() - w, 0), min(jj.max() + w + 1, grid.shape[1])
            crop = elev[i0:i1, j0:j1].copy()
            crop[refill[i0:i1, j0:j1]] = np.nan
            if not np.isfinite(crop).any():
                crop = elev.copy()
                crop[refill] = np.nan
                i0, i1, j0, j1 = 0, grid.shape[0], 0, grid.shape[1]
            region = refill[i0:i1, j0:j1]
            # bounds constrain the cells being filled; kept fills are context, like observations
            ub_crop = np.where(region, ub[i0:i1, j0:j1], np.nan)
            if self.fill_config.method in ('fill_terrain', 'texture_synthesis'):
                res = fill_terrain(crop, ub_crop, self.library, self.fill_config,
                                   self.fill_config.method == 'fill_terrain', fill_mask=region)
            else:
                res = fill(crop, ub_crop, self.library, self.fill_config)
            elev[i0:i1, j0:j1][region] = res.heights[region]
        # cost: recompute where heights changed, plus the reach of the cost windows
        cc = self.cost_config
        reach = max(window_cells(cc.foot_window_m, grid.resolution_m),
                    window_cells(cc.leg_window_m, grid.resolution_m)) // 2 + 1
        if prev is None:
            cost = cost_map(elev, grid.resolution_m, cc).astype(np.float64)
            region_box = (0, grid.shape[0], 0, grid.shape[1])
        else:
            cost = prev['cost'].copy()
            moved = ~same(elev, prev['elev'])
            region_box = None
            if moved.any():
                ii, jj = np.nonzero(moved)
                r0, r1 = max(ii.min() - reach, 0), min(ii.max() + reach + 1, grid.shape[0])
                s0, s1 = max(jj.min() - reach, 0), min(jj.max() + reach + 1, grid.shape[1])
                c0, c1 = max(r0 - reach, 0), min(r1 + reach, grid.shape[0])
                d0, d1 = max(s0 - reach, 0), min(s1 + reach, grid.shape[1])
                sub = cost_map(elev[c0:c1, d0:d1], grid.resolution_m, cc)
                cost[r0:r1, s0:s1] = sub[r0 - c0:r1 - c0, s0 - d0:s1 - d0]
                region_box = (int(r0), int(r1), int(s0), int(s1))
        filled_mask = ~observed & ~contact & np.isfinite(elev)
        out = GridMap(grid.resolution_m, grid.origin_xy, grid.shape, {
            ELEVATION: elev, OBSERVED: observed.astype(np.float32), UPPER_BOUND: ub,
            FILLED: filled_mask.astype(np.float32), COST: cost,
            CONTACT: contact.astype(np.float32)},
            frame_id=grid.frame_id, stamp_s=grid.stamp_s)
        # commit the state only now: a ValueError above leaves it untouched
        self._prev = {'res': grid.resolution_m, 'origin': grid.origin_xy, 'obs': heights,
                      'ub': ub, 'los': los, 'elev': elev, 'cost': cost, 'keys': set(keys),
                      'contact': contact}
        self.last_region = region_box
        self.last_refilled = self_refilled
        self.last_new_captures = int(new.sum())
        return out
