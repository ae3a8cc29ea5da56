"""Compiled (numba) kernels of the fill: :func:`terrain_perception.fill._choose`'s choice step
(two forms), the round selection and one capture's viewshed in
:func:`terrain_perception.fill.bounds_from_captures`.

Fill-Terrain (Fig. 6) picks, per missing cell, the feasible library sample (``v_k = 0``: the
shifted patch nowhere above the line-of-sight bound) with the smallest weighted error ``s_k``.
The numpy code builds an ``(S, n, w^2)`` difference array for the bound test and two more
``(S, n)`` temporaries for the masked argmin, per round of the fill; the terrain_fill node runs
~30 rounds of a few dozen cells per capture, so those passes and their call overhead were
about half of ``_choose``.

* :func:`feasible_argmin` - ``ok = max_q(C - A_bar) + b <= 0`` on the cells with any bound
  (True elsewhere), ``any(ok)`` and ``argmin(where(ok, s, inf))`` per cell, with numpy's
  semantics (a NaN difference makes a sample infeasible, as NaN <= 0 is False; argmin returns
  the first NaN, else the first smallest value).

Only comparisons, one subtraction and one addition per value, as the numpy code does: the
results are bitwise equal (``TERRAIN_FILL_NUMBA=0`` selects the numpy code;
``test/test_speedups.py`` compares the two on a walk). The sums of Fig. 6 stay in numpy (BLAS
matmul, einsum). fastmath is off. Explicit signatures and ``cache=True``: compiled once per
machine, then loaded from ``__pycache__``.

* :func:`choose_block` - the whole choice step of a block of cells, read in place from the
  padded maps and the patch bank (fill_terrain uses it whenever the library has a bank):
  per sample one pass over the window's known cells sums ``C``, ``W (C - A)``, ``W (C -
  A)^2``, and ``s = S2 + 2 b S1 + b^2 sum W``. That is not numpy's arithmetic (an expansion
  summed by BLAS matmul and einsum), so its heights equal ``_choose``'s within rounding
  (~1e-17 m), not bitwise; on the test walk every filled cell takes the same sample
  (``test/test_speedups.py``). ~1.3-1.8x on fill_terrain; ``feasible_argmin`` then serves
  only a library too large for a bank. It evaluates four samples at a time (session 53: each
  sample's sums in the same order as one at a time, bitwise the same; 1.4x).

* :func:`select_round` - the cells of a round (the numpy code: an OpenCV box filter of the
  known mask and a dilation of the keys over the candidates' bounding box, ~0.2 ms a round
  for ~30 rounds per capture): the same integer keys and comparisons on the wanted cells
  only, within the last round's box. The same cells.

* :func:`viewshed_bounds` - the horizon test along each ray of one capture's fan and the bound
  it gives the target cells, ray by ray (the numpy code builds ~20 ``(n_az, n_r)`` arrays, ~6
  ms per capture on the terrain_fill node's 3 m map). The same operations in the same order on
  each sample (the ray directions' cosines and sines come from numpy): bitwise equal, as
  ``test/test_speedups.py`` checks.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

_JIT = dict(cache=True, nogil=True, error_model='numpy')

_in_f8_2d = types.Array(types.float64, 2, 'C', readonly=True)
_in_f8_3d = types.Array(types.float64, 3, 'C', readonly=True)


@njit(cache=True, nogil=True, inline='always')
def _argmin_step(t, val, best, best_v, nan_seen):
    """One step ``t`` (0, 1, ...) of numpy's argmin as a scan: ``(best, best_v, nan_seen)``
    after seeing ``val``; the first NaN wins, else the first smallest value."""
    if nan_seen:
        return best, best_v, nan_seen
    if t == 0:
        return 0, val, math.isnan(val)
    if math.isnan(val):
        return t, best_v, True
    if val < best_v:
        return t, val, False
    return best, best_v, False


@njit(types.void(_in_f8_3d, _in_f8_2d, _in_f8_2d, _in_f8_2d, types.int64[::1],
                 types.boolean[::1]), **_JIT)
def feasible_argmin(C, Abar, b, s, k, any_ok):
    """For each cell i of C (S, n, q) patches, Abar (S, q) bounds (+inf = none), b and s
    (S, n): ``k[i]`` = argmin over samples of (s if feasible else +inf), ``any_ok[i]`` =
    whether any sample is feasible (see module docstring)."""
    S, n, q = C.shape
    for i in range(S):
        bounded = False
        for j in range(q):
            if math.isfinite(Abar[i, j]):
                bounded = True
                break
        best = 0
        best_v = 0.0
        nan_seen = False
        found = False
        for t in range(n):
            ok = True
            if bounded:
                mx = -math.inf
                bad = False
                for j in range(q):
                    v = C[i, t, j] - Abar[i, j]
                    if math.isnan(v):
                        bad = True
                    elif v > mx:
                        mx = v
                ok = (not bad) and mx + b[i, t] <= 0.0
            if ok:
                found = True
            val = s[i, t] if ok else math.inf
            best, best_v, nan_seen = _argmin_step(t, val, best, best_v, nan_seen)
        k[i] = best
        any_ok[i] = found


_in_f8_1d = types.Array(types.float64, 1, 'C', readonly=True)
_in_b1_1d = types.Array(types.boolean, 1, 'C', readonly=True)


@njit(types.void(_in_f8_1d, types.int64, types.int64, types.float64, types.float64,
                 types.float64, _in_f8_1d, _in_f8_1d, _in_f8_1d, _in_f8_1d, types.float64,
                 types.float64, types.boolean, _in_f8_1d, types.float64, _in_b1_1d,
                 types.float64[::1]), **_JIT)
def viewshed_bounds(hflat, nx, ny, ox, oy, res, c, ca, sa, rr, tol, max_range, use_axes, axis,
                    cos_fov, target, bound):
    """One capture's rays (see :func:`terrain_perception.fill.bounds_from_captures`): camera
    ``c`` (3,), ray directions ``(ca, sa)`` (n_az,) cos/sin, sample distances ``rr`` (n_r,),
    heights ``hflat`` (nx*ny, NaN = unobserved), view cone ``axis``/``cos_fov`` when
    ``use_axes``; lowers ``bound`` (nx*ny) where a target cell lies under a seen line of
    sight."""
    n_r = rr.shape[0]
    flat = np.empty(n_r, np.int64)
    inside = np.empty(n_r, np.bool_)
    hz = np.empty(n_r)
    rcen = np.empty(n_r)
    end = np.empty(n_r)             # slope to a seen sample's cell centre, +inf elsewhere
    max2 = max_range ** 2
    for a in range(ca.shape[0]):
        front = -math.inf
        for t in range(n_r):
            r = rr[t]
            x = c[0] + ca[a] * r
            y = c[1] + sa[a] * r
            i = np.int64(math.floor((x - ox) / res))
            j = np.int64(math.floor((y - oy) / res))
            ins = (i >= 0) and (i < nx) and (j >= 0) and (j < ny)
            f = i * ny + j if ins else 0
            h = hflat[f] if ins else math.nan
            inside[t] = ins
            flat[t] = f
            hz[t] = h
            obs = math.isfinite(h)
            slope = (h - c[2]) / r if obs else -math.inf
            seen = obs and (slope >= front - tol / r)
            if slope > front or math.isnan(slope):
                front = slope
            dz = h - c[2] if obs else 0.0
            seen = seen and (r * r + dz * dz <= max2)
            if use_axes:
                d3 = math.sqrt(r * r + dz * dz)
                cosang = (ca[a] * r * axis[0] + sa[a] * r * axis[1] + dz * axis[2]) / d3
                seen = seen and (cosang >= cos_fov)
            # the distance to the cell's centre, only where it is used (a seen sample's end
            # slope, a target cell's bound)
            rc = math.nan
            if seen or (ins and target[f]):
                rc = math.hypot(ox + (i + 0.5) * res - c[0], oy + (j + 0.5) * res - c[1])
            rcen[t] = rc
            end[t] = (h - c[2]) / rc if seen else math.inf
        # the smallest end slope strictly beyond each sample (numpy's minimum: NaN wins)
        beyond = math.inf
        for t in range(n_r - 1, -1, -1):
            if inside[t] and math.isfinite(beyond) and target[flat[t]]:
                v = c[2] + rcen[t] * beyond
                if v < bound[flat[t]] or math.isnan(v):
                    bound[flat[t]] = v
            e = end[t]
            if math.isnan(beyond) or math.isnan(e):
                beyond = math.nan
            elif e < beyond:
                beyond = e


_in_i8_1d = types.Array(types.int64, 1, 'C', readonly=True)
_in_i8_2d = types.Array(types.int64, 2, 'C', readonly=True)


@njit(types.void(_in_f8_1d, _in_b1_1d, _in_f8_1d, _in_i8_1d, _in_i8_1d, _in_f8_2d, _in_i8_2d,
                 _in_f8_1d, types.float64[::1], types.int64[::1]), **_JIT)
def choose_block(Hpf, Kpf, Upf, corner, offs, bank, g, W, h_out, k_out):
    """Fig. 6 steps 2-3 for a block of S cells, straight from the padded maps and the patch
    bank (no gathered ``(S, n, w^2)`` copy): cell ``i``'s window is ``corner[i] + offs``
    (q,) in the padded heights ``Hpf``, known mask ``Kpf`` and bounds ``Upf`` (+inf = none);
    its n samples are the bank rows ``g[i]``. Per sample, over the window's known cells, one
    pass sums ``C``, ``W (C - A)`` and ``W (C - A)^2``; the offset is ``b = (sum A - sum C) /
    |B|`` and the weighted error ``s = sum W (C - A + b)^2 = S2 + 2 b S1 + b^2 sum W`` (numpy's
    ``_choose`` expands it differently, into BLAS sums: equal within rounding, not bitwise).
    Feasibility as in numpy's code: a window with no finite bound has every sample feasible;
    otherwise a sample is when no cell has ``C + b`` above its bound (a NaN or -inf bound:
    none is). ``k_out[i]``: the feasible sample of least ``s`` (first on ties), or, when none
    is feasible, the one of least squared excess over the bounds; ``h_out[i] = C_k[centre] +
    b_k``. NaN follows numpy's argmin (the first NaN wins)."""
    S = corner.shape[0]
    n = g.shape[1]
    q = offs.shape[0]
    centre = q // 2
    flat = bank.ravel()
    kj = np.empty(q, np.int64)         # the window's known cells
    ka = np.empty(q)                   # their heights
    kw = np.empty(q)                   # their weights
    bj = np.empty(q, np.int64)         # its cells with a bound below +inf (-inf: none fits)
    ub = np.empty(q)
    b_all = np.empty(n)
    s0 = np.empty(n)                   # per sample: sum C, sum W (C - A), sum W (C - A)^2
    s1 = np.empty(n)
    s2 = np.empty(n)
    mx = np.empty(n)                   # and max (C - bound) over the bounded cells
    for i in range(S):
        nk = 0
        nb = 0
        sum_a = 0.0
        sum_w = 0.0
        nan_bound = False
        bounded = False                # numpy's test: some bound is finite
        for j in range(q):
            p = corner[i] + offs[j]
            if Kpf[p]:
                kj[nk] = j
                ka[nk] = Hpf[p]
                kw[nk] = W[j]
                sum_a += Hpf[p]
                sum_w += W[j]
                nk += 1
            u = Upf[p]
            if math.isnan(u):
                nan_bound = True
            elif u < math.inf:
                bj[nb] = j
                ub[nb] = u
                nb += 1
                if u > -math.inf:
                    bounded = True
        m = float(nk)
        check = bounded and not nan_bound
        # Four samples at a time: each sample's sums still run over the known cells in order
        # (the same numbers as one sample at a time, bit for bit), but the four samples'
        # additions do not wait on one another (1.4x on the loop's recorded blocks).
        t = 0
        while t + 4 <= n:
            r0 = g[i, t] * q
            r1 = g[i, t + 1] * q
            r2 = g[i, t + 2] * q
            r3 = g[i, t + 3] * q
            a0 = a1 = a2 = a3 = 0.0
            c0 = c1 = c2 = c3 = 0.0
            e0 = e1 = e2 = e3 = 0.0
            for k in range(nk):
                o = kj[k]
                a = ka[k]
                wk = kw[k]
                x0 = flat[r0 + o]
                x1 = flat[r1 + o]
                x2 = flat[r2 + o]
                x3 = flat[r3 + o]
                d0 = x0 - a
                d1 = x1 - a
                d2 = x2 - a
                d3 = x3 - a
                w0 = wk * d0
                w1 = wk * d1
                w2 = wk * d2
                w3 = wk * d3
                a0 += x0
                a1 += x1
                a2 += x2
                a3 += x3
                c0 += w0
                c1 += w1
                c2 += w2
                c3 += w3
                e0 += w0 * d0
                e1 += w1 * d1
                e2 += w2 * d2
                e3 += w3 * d3
            s0[t], s0[t + 1], s0[t + 2], s0[t + 3] = a0, a1, a2, a3
            s1[t], s1[t + 1], s1[t + 2], s1[t + 3] = c0, c1, c2, c3
            s2[t], s2[t + 1], s2[t + 2], s2[t + 3] = e0, e1, e2, e3
            if check:
                m0 = m1 = m2 = m3 = -math.inf
                for k in range(nb):
                    o = bj[k]
                    u = ub[k]
                    v = flat[r0 + o] - u
                    if v > m0:
                        m0 = v
                    v = flat[r1 + o] - u
                    if v > m1:
                        m1 = v
                    v = flat[r2 + o] - u
                    if v > m2:
                        m2 = v
                    v = flat[r3 + o] - u
                    if v > m3:
                        m3 = v
                mx[t], mx[t + 1], mx[t + 2], mx[t + 3] = m0, m1, m2, m3
            t += 4
        while t < n:                   # the last n % 4 samples
            r0 = g[i, t] * q
            a0 = c0 = e0 = 0.0
            for k in range(nk):
                x0 = flat[r0 + kj[k]]
                d0 = x0 - ka[k]
                w0 = kw[k] * d0
                a0 += x0
                c0 += w0
                e0 += w0 * d0
            s0[t], s1[t], s2[t] = a0, c0, e0
            if check:
                m0 = -math.inf
                for k in range(nb):
                    v = flat[r0 + bj[k]] - ub[k]
                    if v > m0:
                        m0 = v
                mx[t] = m0
            t += 1
        best = 0
        best_v = 0.0
        nan_seen = False
        found = False
        for t in range(n):
            b = (sum_a - s0[t]) / m
            b_all[t] = b
            s = s2[t] + 2.0 * b * s1[t] + b * b * sum_w
            ok = True
            if bounded:
                ok = check and mx[t] + b <= 0.0
            if ok:
                found = True
            val = s if ok else math.inf
            best, best_v, nan_seen = _argmin_step(t, val, best, best_v, nan_seen)
        if not found:
            # no feasible sample: the least squared excess over the bounds
            best = 0
            best_v = 0.0
            nan_seen = False
            for t in range(n):
                base = g[i, t] * q
                b = b_all[t]
                e = 0.0
                for j in range(q):
                    v = flat[base + j] + b - Upf[corner[i] + offs[j]]
                    if math.isnan(v):
                        e = math.nan
                    elif v > 0.0:
                        e += v * v
                best, best_v, nan_seen = _argmin_step(t, e, best, best_v, nan_seen)
        k_out[i] = best
        h_out[i] = flat[g[i, best] * q + centre] + b_all[best]


_in_b1_2d = types.Array(types.boolean, 2, 'C', readonly=True)


@njit(types.int64(_in_b1_2d, _in_b1_2d, types.boolean, _in_i8_2d, types.int64,
                  types.int64[::1], types.int64[::1]), **_JIT)
def select_round(known, todo, use_todo, rank, w, box, out):
    """:func:`terrain_perception.fill.select_round` in one pass: the missing cells (and in
    ``todo`` when ``use_todo``) with a known cell in their w x w window whose key ``count * N
    + rank`` beats every other such cell's in the window, as flat indices in row-major order
    into ``out``; returns how many. Integer keys, the same comparisons: the same cells as the
    OpenCV box filter and dilation of the numpy code. ``box`` (i0, i1, j0, j1), half-open:
    where the wanted cells can be (the whole map, or the last round's box: rounds only fill
    cells); set to the box they are in now."""
    nx, ny = known.shape
    r = w // 2
    big = nx * ny
    mi0, mi1, mj0, mj1 = nx, -1, ny, -1
    for i in range(max(box[0], 0), min(box[1], nx)):
        for j in range(max(box[2], 0), min(box[3], ny)):
            if not known[i, j] and (not use_todo or todo[i, j]):
                if i < mi0:
                    mi0 = i
                mi1 = i
                if j < mj0:
                    mj0 = j
                if j > mj1:
                    mj1 = j
    if mi1 < 0:
        box[0], box[1], box[2], box[3] = 0, 0, 0, 0
        return 0
    box[0], box[1], box[2], box[3] = mi0, mi1 + 1, mj0, mj1 + 1
    di, dj = mi1 - mi0 + 1, mj1 - mj0 + 1
    key = np.full((di, dj), -1, np.int64)
    for i in range(mi0, mi1 + 1):
        for j in range(mj0, mj1 + 1):
            if known[i, j] or (use_todo and not todo[i, j]):
                continue
            count = 0
            for a in range(max(i - r, 0), min(i + r + 1, nx)):
                for b in range(max(j - r, 0), min(j + r + 1, ny)):
                    if known[a, b]:
                        count += 1
            if count > 0:
                key[i - mi0, j - mj0] = count * big + rank[i, j]
    n = 0
    for i in range(di):
        for j in range(dj):
            k = key[i, j]
            if k < 0:
                continue
            best = True
            for a in range(max(i - r, 0), min(i + r + 1, di)):
                for b in range(max(j - r, 0), min(j + r + 1, dj)):
                    if key[a, b] > k:
                        best = False
                        break
                if not best:
                    break
            if best:
                out[n] = (i + mi0) * ny + (j + mj0)
                n += 1
    return n
