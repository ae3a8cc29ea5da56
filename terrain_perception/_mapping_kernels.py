"""Compiled (numba) kernels of :class:`terrain_perception.mapping.FineHeightMap`'s per-capture
steps.

The ICP mapper fuses ~50k points per capture into the fine map; the numpy code spends most of
that in a dozen full-window ``bincount`` passes, ``ufunc.at`` and fancy-indexed gathers and
scatters of the 14 statistics. These kernels do the same arithmetic in one or two passes over
the points and one over the touched cells:

* :func:`fine_gate` - the window test and the per-capture outlier gate of
  ``FineHeightMap.add`` (two passes of per-cell weighted means, summed in point order as
  ``np.bincount`` does).
* :func:`fine_merge` - the per-cell batch sums (count, weight, centred height moments, plane
  sums, min, max) of the kept points, in point order, and their merge into the running
  statistics with ``add``'s formulas, operation for operation.
* :func:`rays_below` - ``FineHeightMap.rays_below``'s line-of-sight test per point.
* :func:`fine_heights`, :func:`fine_layers` - ``FineHeightMap.heights`` (per-cell plane
  estimator) and the float32 layers of ``FineHeightMap.to_grid``, one pass over the cells
  instead of ~40 full-window temporaries (the node publishes the map every capture).
* :func:`valid_points` - ``mapping.valid_points``' finiteness and depth-window test and the
  gather of an organized (strided) cloud, widened to float64.
* :func:`cloud_height_normals` - ``mapping.cloud_height_normals`` (the coarse model's normals
  of each capture) in one pass per step instead of ~30 temporaries.
* :func:`nearest_in_columns` - the ICP's correspondence search (``mapping.ModelIndex``): the
  nearest coarse-model point within a bound, by x-y columns searched nearest first; scipy's
  cKDTree is its reference (same rows, bitwise the same distances; ``test/test_mapping.py``).
* :func:`isolated_cells` - ``mapping.isolated_cells`` (the lone mismatches hidden from every
  published fine map): the neighbours' median and the islands' flood fill in two passes
  instead of a stack of neighbour gathers, ``np.nanmedian``, a dilation and a labelling
  (4.3 -> 1.3 ms on the demo's 300 x 300 map).

Same float64 operations in the same order, so the results are bitwise equal to the numpy code
(``mapping.FineHeightMap``, ``valid_points`` and ``cloud_height_normals`` keep it as the
reference, ``TERRAIN_MAPPING_NUMBA=0`` selects it; ``test/test_mapping.py`` compares the two).
The reference height of a fine-map batch (``np.mean``, pairwise summation) is left to numpy
between the two kernels. fastmath is off, so nothing is
reordered or fused. Explicit signatures and ``cache=True``: importing compiles them once per
machine (a few seconds), then loads them from ``__pycache__``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

_JIT = dict(cache=True, nogil=True, error_model='numpy')

_in_f8_1d = types.Array(types.float64, 1, 'C', readonly=True)
_in_f8_2d = types.Array(types.float64, 2, 'C', readonly=True)
_in_i8_1d = types.Array(types.int64, 1, 'C', readonly=True)
_in_b1_1d = types.Array(types.boolean, 1, 'C', readonly=True)
_f8_1d = types.float64[::1]
_i8_1d = types.int64[::1]
_b1_1d = types.boolean[::1]
_f8, _i8 = types.float64, types.int64


@njit(types.int64(_in_f8_2d, _in_f8_1d, _f8, _f8, _f8, _i8, _i8, _f8, _i8_1d, _b1_1d), **_JIT)
def fine_gate(points, wt, ox, oy, r, nx, ny, gate, lin, keep):
    """Cell index ``lin`` (N,) of each point of ``points`` (N, 3) on the ``nx`` x ``ny``
    window at ``(ox, oy)`` with cells ``r`` (-1 off the window), and ``keep`` (N,): on the
    window and, when ``gate`` > 0, within ``gate`` of its cell's weighted mean height in this
    batch (computed twice, the second time over the first pass's kept points only). Returns
    how many points fell on the window."""
    n_pts = points.shape[0]
    n_on = 0
    for k in range(n_pts):
        fi = math.floor((points[k, 0] - ox) / r)
        fj = math.floor((points[k, 1] - oy) / r)
        # float tests: floor(v) >= 0 iff v >= 0; NaN and +-inf are off the window
        if fi >= 0.0 and fi < nx and fj >= 0.0 and fj < ny:
            lin[k] = np.int64(fi) * ny + np.int64(fj)
            keep[k] = True
            n_on += 1
        else:
            lin[k] = -1
            keep[k] = False
    if gate <= 0.0 or n_on == 0:
        return n_on
    size = nx * ny
    cnt = np.zeros(size)
    sm = np.zeros(size)
    for _ in range(2):
        for k in range(n_pts):
            c = lin[k]
            if c >= 0 and keep[k]:
                cnt[c] += wt[k]
                sm[c] += wt[k] * points[k, 2]
        for k in range(n_pts):
            c = lin[k]
            if c >= 0:
                keep[k] = abs(points[k, 2] - sm[c] / cnt[c]) <= gate
        for k in range(n_pts):
            c = lin[k]
            if c >= 0:
                cnt[c] = 0.0
                sm[c] = 0.0
    return n_on


@njit(types.int64(_in_f8_2d, _in_f8_1d, _in_i8_1d, _in_b1_1d, _f8, _f8, _f8, _f8, _f8,
                  _f8_1d, _f8_1d, _f8_1d, _f8_1d, _f8_1d, _f8_1d, _f8_1d, _f8_1d, _f8_1d,
                  _f8_1d, _f8_1d, _f8_1d, _f8_1d, _f8_1d), **_JIT)
def fine_merge(points, wt, lin, keep, ox, oy, r, z0, stamp_s,
               s_n, s_w, s_mean, s_m2, s_min, s_max, s_last, s_sx, s_sy, s_sxx, s_sxy, s_syy,
               s_sxz, s_syz):
    """Fuse the kept points (``keep``, cells ``lin`` from :func:`fine_gate`) into the flat
    statistics ``s_*`` (``nx * ny``,) of ``FineHeightMap``; ``z0``: the reference height
    (mean of the kept heights). Returns the number of cells touched."""
    n_pts = points.shape[0]
    size = s_n.shape[0]
    slot = np.full(size, -1, np.int64)
    cells = np.empty(n_pts, np.int64)
    S = np.empty((n_pts, 10))
    nb = np.empty(n_pts)
    zmin = np.empty(n_pts)
    zmax = np.empty(n_pts)
    m = 0
    for k in range(n_pts):
        if not keep[k]:
            continue
        c = lin[k]
        q = slot[c]
        if q < 0:
            q = m
            slot[c] = q
            cells[q] = c
            for a in range(10):
                S[q, a] = 0.0
            nb[q] = 0.0
            zmin[q] = np.inf
            zmax[q] = -np.inf
            m += 1
        z = points[k, 2]
        w = wt[k]
        zs = z - z0
        fx = (points[k, 0] - ox) / r
        fy = (points[k, 1] - oy) / r
        dx = (fx - math.floor(fx) - 0.5) * r
        dy = (fy - math.floor(fy) - 0.5) * r
        S[q, 0] += w * 1.0
        S[q, 1] += w * zs
        S[q, 2] += w * (zs * zs)
        S[q, 3] += w * dx
        S[q, 4] += w * dy
        S[q, 5] += w * (dx * dx)
        S[q, 6] += w * (dx * dy)
        S[q, 7] += w * (dy * dy)
        S[q, 8] += w * (dx * zs)
        S[q, 9] += w * (dy * zs)
        nb[q] += 1.0
        # np.minimum / np.maximum: a NaN sticks
        if z < zmin[q] or z != z:
            zmin[q] = z
        if z > zmax[q] or z != z:
            zmax[q] = z
    for q in range(m):
        c = cells[q]
        wb = S[q, 0]
        mb_rel = S[q, 1] / wb
        mb = mb_rel + z0
        m2b = S[q, 2] - wb * mb_rel * mb_rel
        if m2b < 0.0:                                   # np.maximum(m2b, 0.0): NaN kept
            m2b = 0.0
        bx = S[q, 3]
        by = S[q, 4]
        bxz = S[q, 8] - mb_rel * bx
        byz = S[q, 9] - mb_rel * by
        wa = s_w[c]
        ma = s_mean[c]
        w = wa + wb
        delta = mb - ma
        new_mean = ma + delta * wb / w
        shift_a = ma - new_mean
        shift_b = mb - new_mean
        s_sxz[c] += shift_a * s_sx[c] + bxz + shift_b * bx
        s_syz[c] += shift_a * s_sy[c] + byz + shift_b * by
        s_sx[c] += bx
        s_sy[c] += by
        s_sxx[c] += S[q, 5]
        s_sxy[c] += S[q, 6]
        s_syy[c] += S[q, 7]
        s_m2[c] += m2b + delta * delta * wa * wb / w
        s_mean[c] = new_mean
        s_w[c] = w
        s_n[c] += nb[q]
        if zmin[q] < s_min[c] or zmin[q] != zmin[q]:
            s_min[c] = zmin[q]
        if zmax[q] > s_max[c] or zmax[q] != zmax[q]:
            s_max[c] = zmax[q]
        s_last[c] = stamp_s
    return m


@njit(types.void(_in_f8_2d, _in_f8_1d, _in_f8_1d, _f8, _in_f8_1d, _in_f8_1d, _f8, _f8, _f8,
                 _i8, _i8, _b1_1d), **_JIT)
def rays_below(points, origin, fractions, tolerance_m, s_n, s_mean, ox, oy, r, nx, ny, out):
    """``out`` (N,): the ray from ``origin`` to the point passes more than ``tolerance_m``
    below the mean height of an observed cell (``s_n > 0``) at one of ``fractions`` of its
    length (see ``FineHeightMap.rays_below``; ``out`` is left untouched where it does not)."""
    size = s_n.shape[0]
    top = -np.inf
    seen = False                                        # np.nanmax over the observed cells
    for c in range(size):
        if s_n[c] > 0.0 and s_mean[c] == s_mean[c]:
            if not seen or s_mean[c] > top:
                top = s_mean[c]
            seen = True
    if not seen:
        return
    ceiling = top - tolerance_m
    f_hi = fractions[0]
    for f in fractions:
        if f > f_hi:
            f_hi = f
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for k in range(points.shape[0]):
        if not (o2 + f_hi * (points[k, 2] - o2) < ceiling):
            continue
        d0 = points[k, 0] - o0
        d1 = points[k, 1] - o1
        d2 = points[k, 2] - o2
        bad = False
        for f in fractions:
            q0 = o0 + f * d0
            q1 = o1 + f * d1
            q2 = o2 + f * d2
            fi = math.floor((q0 - ox) / r)
            fj = math.floor((q1 - oy) / r)
            if fi >= 0.0 and fi < nx and fj >= 0.0 and fj < ny:
                c = np.int64(fi) * ny + np.int64(fj)
                if s_n[c] > 0.0 and q2 < s_mean[c] - tolerance_m:
                    bad = True
        if bad:
            out[k] = True


@njit(inline='always', **_JIT)
def _cell_height(n, w, mean, sx, sy, sxx, sxy, syy, sxz, syz, plane, r2, det_min):
    """``FineHeightMap.heights`` of one cell, its operations in its order."""
    seen = n > 0.0
    h = mean if seen else np.nan
    if not plane:
        return h
    nn = w if seen else 1.0
    mx = sx / nn
    my = sy / nn
    cxx = sxx / nn - mx * mx
    cxy = sxy / nn - mx * my
    cyy = syy / nn - my * my
    cxz = sxz / nn
    cyz = syz / nn
    det = cxx * cyy - cxy * cxy
    if seen and n >= 6.0 and cxx > r2 and cyy > r2 and det > det_min:
        gx = (cyy * cxz - cxy * cyz) / det
        gy = (cxx * cyz - cxy * cxz) / det
        return mean - gx * mx - gy * my
    return h


_stats_in = (_in_f8_1d,) * 14


@njit(types.void(*_stats_in, types.boolean, _f8, _f8, _f8_1d), **_JIT)
def fine_heights(s_n, s_w, s_mean, s_m2, s_min, s_max, s_last, s_sx, s_sy, s_sxx, s_sxy,
                 s_syy, s_sxz, s_syz, plane, r2, det_min, out):
    """``out`` (nx * ny,): ``FineHeightMap.heights`` (``plane``: the per-cell plane estimator,
    ``r2`` and ``det_min`` its spread thresholds)."""
    for c in range(s_n.shape[0]):
        out[c] = _cell_height(s_n[c], s_w[c], s_mean[c], s_sx[c], s_sy[c], s_sxx[c], s_sxy[c],
                              s_syy[c], s_sxz[c], s_syz[c], plane, r2, det_min)


_f4_1d = types.float32[::1]


@njit(types.void(*_stats_in, types.boolean, _f8, _f8, _f4_1d, _f4_1d, _f4_1d, _f4_1d, _f4_1d,
                 _f4_1d, _f4_1d), **_JIT)
def fine_layers(s_n, s_w, s_mean, s_m2, s_min, s_max, s_last, s_sx, s_sy, s_sxx, s_sxy, s_syy,
                s_sxz, s_syz, plane, r2, det_min, elev, obs, var, zmin, zmax, count, last):
    """The float32 layers of ``FineHeightMap.to_grid`` (elevation, observed, variance, min,
    max, count, last_seen; NaN where empty) in one pass over the cells."""
    nan = np.float32(np.nan)
    for c in range(s_n.shape[0]):
        n = s_n[c]
        seen = n > 0.0
        elev[c] = np.float32(_cell_height(n, s_w[c], s_mean[c], s_sx[c], s_sy[c], s_sxx[c],
                                          s_sxy[c], s_syy[c], s_sxz[c], s_syz[c], plane, r2,
                                          det_min))
        obs[c] = np.float32(1.0) if seen else np.float32(0.0)
        count[c] = np.float32(n)
        if seen:
            var[c] = np.float32(s_m2[c] / s_w[c])
            zmin[c] = np.float32(s_min[c])
            zmax[c] = np.float32(s_max[c])
            last[c] = np.float32(s_last[c])
        else:
            var[c] = nan
            zmin[c] = nan
            zmax[c] = nan
            last[c] = nan


@njit(inline='always', **_JIT)
def _keeps(cloud, i, j, lo, hi):
    x = np.float64(cloud[i, j, 0])
    y = np.float64(cloud[i, j, 1])
    z = np.float64(cloud[i, j, 2])
    return np.isfinite(x) and np.isfinite(y) and np.isfinite(z) and z >= lo and z <= hi


def _valid_points(cloud, lo, hi):
    # two passes (count, then fill) so the output is allocated once at its size
    H, W = cloud.shape[0], cloud.shape[1]
    n = 0
    for i in range(H):
        for j in range(W):
            if _keeps(cloud, i, j, lo, hi):
                n += 1
    out = np.empty((n, 3))
    k = 0
    for i in range(H):
        for j in range(W):
            if _keeps(cloud, i, j, lo, hi):
                for c in range(3):
                    out[k, c] = np.float64(cloud[i, j, c])
                k += 1
    return out


valid_points = njit([types.float64[:, ::1](types.Array(t, 3, 'A', readonly=True), _f8, _f8)
                     for t in (types.float32, types.float64)], **_JIT)(_valid_points)
valid_points.__doc__ = """Finite points of an organized cloud ``(H, W, 3)`` (any strides, float32 or
float64) with ``lo <= z <= hi`` (compared as float64), row-major, as float64 ``(M, 3)``: what
``mapping.valid_points`` gathers."""


@njit(types.float64[:, ::1](_in_f8_2d, _f8, _f8, _f8, _i8), **_JIT)
def cloud_height_normals(points, lo_x, lo_y, r, half_width):
    """``mapping.cloud_height_normals`` of finite points ``(N, 3)`` whose x-y minimum is
    ``(lo_x, lo_y)``: the mean-height grid (sums in point order, as ``np.bincount``), central
    differences over ``half_width`` .. 1 cells (the first that exists, as the numpy loop's
    ``np.where``) and the normalised ``(-gx, -gy, 1)`` (``np.linalg.norm``'s order)."""
    n_pts = points.shape[0]
    ii = np.empty(n_pts, np.int64)
    jj = np.empty(n_pts, np.int64)
    nx = 0
    ny = 0
    for k in range(n_pts):
        i = np.int64(math.floor((points[k, 0] - lo_x) / r))
        j = np.int64(math.floor((points[k, 1] - lo_y) / r))
        ii[k] = i
        jj[k] = j
        if i + 1 > nx:
            nx = i + 1
        if j + 1 > ny:
            ny = j + 1
    cnt = np.zeros(nx * ny, np.int64)
    sm = np.zeros(nx * ny)
    for k in range(n_pts):
        c = ii[k] * ny + jj[k]
        cnt[c] += 1
        sm[c] += points[k, 2]
    h = np.empty(nx * ny)
    for c in range(nx * ny):
        h[c] = sm[c] / np.float64(cnt[c])          # NaN where empty (0 / 0)
    out = np.empty((n_pts, 3))
    hw = max(1, half_width)
    for k in range(n_pts):
        i = min(max(ii[k], 0), nx - 1)
        j = min(max(jj[k], 0), ny - 1)
        gx = np.nan
        gy = np.nan
        for s in range(hw, 0, -1):
            ip = min(i + s, nx - 1)
            im = max(i - s, 0)
            jp = min(j + s, ny - 1)
            jm = max(j - s, 0)
            ex = (h[ip * ny + j] - h[im * ny + j]) / (np.float64(ip - im) * r)
            ey = (h[i * ny + jp] - h[i * ny + jm]) / (np.float64(jp - jm) * r)
            if gx != gx:
                gx = ex
            if gy != gy:
                gy = ey
        if ii[k] < 0 or ii[k] >= nx or jj[k] < 0 or jj[k] >= ny:
            gx = np.nan
        a = -gx
        b = -gy
        norm = math.sqrt((a * a + b * b) + 1.0 * 1.0)
        out[k, 0] = a / norm
        out[k, 1] = b / norm
        out[k, 2] = 1.0 / norm
    return out


_in_b1_2d = types.Array(types.boolean, 2, 'C', readonly=True)


@njit(types.void(_in_f8_2d, _in_b1_2d, _in_b1_2d, _i8, _f8, _i8, types.boolean[:, ::1]),
      **_JIT)
def isolated_cells(h, obs, few, min_neighbours, gate_m, island_cells, out):
    """``out`` (nx, ny): ``mapping.isolated_cells`` on the heights ``h``, the observed cells
    ``obs`` (finite heights) and the candidates ``few`` (observed, at most max_count samples).
    The neighbours' median is ``np.nanmedian``'s (the middle value, or the mean of the two
    middle ones); the islands are the 8-connected components of ``obs`` dilated by one cell
    (``ndimage.label`` of ``ndimage.binary_dilation``), found by a flood fill."""
    nx, ny = h.shape
    vals = np.empty(8)
    for i in range(nx):
        for j in range(ny):
            out[i, j] = False
            if not few[i, j]:
                continue
            n = 0
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    a, b = i + di, j + dj
                    if (di != 0 or dj != 0) and 0 <= a < nx and 0 <= b < ny and obs[a, b]:
                        # insertion sort: at most 8 values
                        v = h[a, b]
                        k = n
                        while k > 0 and vals[k - 1] > v:
                            vals[k] = vals[k - 1]
                            k -= 1
                        vals[k] = v
                        n += 1
            if n < min_neighbours:
                out[i, j] = True
            elif n > 0:
                med = vals[n // 2] if n % 2 == 1 else (vals[n // 2 - 1] + vals[n // 2]) / 2.0
                out[i, j] = abs(h[i, j] - med) > gate_m
    if island_cells <= 1:
        return
    # the dilated mask: a cell within one cell of an observed one
    dil = np.zeros((nx, ny), np.bool_)
    for i in range(nx):
        for j in range(ny):
            if obs[i, j]:
                for a in range(max(i - 1, 0), min(i + 2, nx)):
                    for b in range(max(j - 1, 0), min(j + 2, ny)):
                        dil[a, b] = True
    label = np.full((nx, ny), -1, np.int64)
    stack = np.empty(nx * ny, np.int64)
    members = np.empty(nx * ny, np.int64)
    for i0 in range(nx):
        for j0 in range(ny):
            if not dil[i0, j0] or label[i0, j0] >= 0:
                continue
            lab = i0 * ny + j0
            label[i0, j0] = lab
            stack[0] = lab
            top = 1
            m = 0
            size = 0
            supported = False
            while top > 0:
                top -= 1
                c = stack[top]
                i, j = c // ny, c % ny
                if obs[i, j]:
                    members[m] = c
                    m += 1
                    size += 1
                    if not few[i, j]:
                        supported = True
                for a in range(max(i - 1, 0), min(i + 2, nx)):
                    for b in range(max(j - 1, 0), min(j + 2, ny)):
                        if dil[a, b] and label[a, b] < 0:
                            label[a, b] = lab
                            stack[top] = a * ny + b
                            top += 1
            if size < island_cells and not supported:
                for k in range(m):
                    c = members[k]
                    if few[c // ny, c % ny]:
                        out[c // ny, c % ny] = True



@njit(inline='always', **_JIT)
def _nearest_first(c0, s):
    """The ``s``-th column (0, 1, ...) around column ``c0``, nearest first: c0, c0 - 1,
    c0 + 1, c0 - 2, ..."""
    return c0 + ((s + 1) // 2) * (1 if s % 2 == 0 else -1)


@njit(inline='always', **_JIT)
def _gap(a, q, origin, cell):
    """How far ``q`` lies outside column ``a``'s interval ``[origin + a cell, origin + (a + 1)
    cell]`` (0 inside), less 1e-9 m (a point's column comes from a rounded division)."""
    g = max(origin + a * cell - q, q - (origin + (a + 1) * cell), 0.0)
    return max(g - 1e-9, 0.0)


@njit(types.void(_in_f8_2d, _in_i8_1d, _in_i8_1d, _f8, _f8, _f8, _i8, _i8, _in_f8_2d, _f8,
                 _f8_1d, _i8_1d), **_JIT)
def nearest_in_columns(pts, order, starts, x0, y0, cell, nx, ny, query, bound, dist, idx):
    """The nearest of the model points ``pts`` (M, 3), sorted by the ``nx`` x ``ny`` columns
    of ``cell`` x ``cell`` from ``(x0, y0)`` (column ``c``: rows ``starts[c]:starts[c + 1]``,
    model row ``order[k]``), of each ``query`` point strictly within ``bound`` [m] (squared
    distances compared, as scipy's cKDTree does): ``dist`` its distance (inf: none), ``idx``
    its model row (M: none); among equally near points the lowest model row.

    A point within ``bound`` lies in the columns within ``reach = ceil(bound / cell)`` of the
    query's. They are visited nearest first (offsets 0, -1, +1, -2, ...) and a column is
    skipped when its x-y rectangle (less 1e-9 m: a point's column comes from a rounded
    division) is farther than the best squared distance so far, so only a tie or a nearer
    point can be skipped never. The squared distance is summed x, y, z from 0, as cKDTree's
    ``sqeuclidean_distance_double`` does for 3 dimensions."""
    n_model = pts.shape[0]
    bound2 = bound * bound
    reach = np.int64(math.ceil(bound / cell))
    for k in range(query.shape[0]):
        qx, qy, qz = query[k, 0], query[k, 1], query[k, 2]
        best = bound2               # only strictly nearer points are taken
        best_row = n_model
        fi = math.floor((qx - x0) / cell)
        fj = math.floor((qy - y0) / cell)
        # NaN or far off the columns: nothing within reach (float tests, no int overflow)
        if fi >= -reach and fi < nx + reach and fj >= -reach and fj < ny + reach:
            ci, cj = np.int64(fi), np.int64(fj)
            for sa in range(2 * reach + 1):
                a = _nearest_first(ci, sa)
                if a < 0 or a >= nx:
                    continue
                gx = _gap(a, qx, x0, cell)
                gx2 = gx * gx
                if gx2 > best:
                    continue
                for sb in range(2 * reach + 1):
                    b = _nearest_first(cj, sb)
                    if b < 0 or b >= ny:
                        continue
                    gy = _gap(b, qy, y0, cell)
                    if gx2 + gy * gy > best:
                        continue
                    c = a * ny + b
                    for r in range(starts[c], starts[c + 1]):
                        d = pts[r, 0] - qx
                        s = 0.0 + d * d
                        d = pts[r, 1] - qy
                        s += d * d
                        d = pts[r, 2] - qz
                        s += d * d
                        if s < best or (s == best and best_row < n_model
                                        and order[r] < best_row):
                            best = s
                            best_row = order[r]
        if best_row < n_model:
            dist[k] = math.sqrt(best)
            idx[k] = best_row
        else:
            dist[k] = math.inf
            idx[k] = n_model
