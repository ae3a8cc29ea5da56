"""Compiled (numba) kernels of :mod:`terrain_perception.patches`' hot steps.

:func:`terrain_perception.patches.find_patches` runs these instead of its numpy steps when numba
can be imported (the numpy steps stay the reference, see ``patches.use_compiled_kernels``):

* :func:`median_2x2_scaled` - step 4, the 2x2 median of the bilaterally scaled points (the scale
  applied on the fly). Bitwise identical to ``patches._median_2x2`` (same float32 operations).
* :func:`integral_moments` - step 7's integral images of point count, centred points, squares
  and products (``patches.IntegralMoments``) in one pass. Bitwise identical: the same float32
  centring and products, summed in float64 in OpenCV's ``integral`` order.
* :func:`sample_neighbourhoods` - step 11, the organized neighbourhood search, given the uniform
  draws that the caller takes from its generator exactly as the numpy step does. Bitwise
  identical to ``patches._sample_neighbourhoods`` (same float64 operations, in the same order).
* :func:`fit_paraboloids` - step 12, closed-form start and Levenberg-Marquardt, one patch at a
  time (each patch's loop stops on its own convergence, as in the batched numpy fit). Equal to
  ``patches._fit_paraboloids`` up to rounding: the numpy fit's sums are BLAS matmuls and its
  solves LAPACK's, whose summation order cannot be reproduced.

All kernels are compiled with ``cache=True`` (the machine code is cached next to this file, in
``__pycache__``) and ``nogil=True``; fastmath is off, so no operation is reordered or fused.
The four entry points have explicit signatures (C-contiguous arrays, read-only inputs), so
importing this module compiles them, or loads them from the cache: ~11 s once per machine and
version of this file (on the 2-core development VM; the fit is ~7 s of it), then ~0.4 s
(+0.25 s numba's import), before any frame is timed or processed.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

_JIT = dict(cache=True, nogil=True, error_model='numpy')

_f4_2d = types.float32[:, ::1]
_f8_1d, _f8_2d, _f8_3d = types.float64[::1], types.float64[:, ::1], types.float64[:, :, ::1]
_i8_1d = types.int64[::1]
# inputs only read: read-only arrays (writable ones convert; clouds from message buffers are not)
_in_f4_2d, _in_f4_3d = (types.Array(types.float32, n, 'C', readonly=True) for n in (2, 3))
_in_f8_2d, _in_f8_3d = (types.Array(types.float64, n, 'C', readonly=True) for n in (2, 3))
_in_f4_2d_any = types.Array(types.float32, 2, 'A', readonly=True)


# --------------------------------------------------------------------------------------------
# Step 4: 2x2 median of the scaled points
# --------------------------------------------------------------------------------------------

@njit(**_JIT)
def _median_of_valid(v, valid, buf):
    """Median of the valid entries of ``v`` (4,) (NaN sorted last, as ``np.sort``; NaN if
    none); ``buf``: scratch (4,)."""
    n = 0
    for i in range(4):
        if valid[i]:
            x = v[i]
            # insertion, NaN last
            j = n
            while j > 0 and (math.isnan(buf[j - 1]) and not math.isnan(x)
                             or buf[j - 1] > x):
                buf[j] = buf[j - 1]
                j -= 1
            buf[j] = x
            n += 1
    if n == 0:
        return np.float32(np.nan)
    if n % 2 == 1:
        return buf[n // 2]
    return np.float32(0.5) * (buf[n // 2 - 1] + buf[n // 2])


@njit(types.void(_in_f4_3d, _in_f4_2d, _f4_2d, _f4_2d, _f4_2d), **_JIT)
def median_2x2_scaled(cloud, scale, Dx, Dy, Dz):
    """2x2 block medians of the points ``cloud * scale[..., None]`` (``cloud`` (h, w, 3) and
    ``scale`` (h, w) float32, h and w >= 2 x the output's) into the float32 planes ``Dx, Dy,
    Dz`` (h/2, w/2). A point is valid when its scaled z is finite; a block's median is over its
    valid points (NaN if none). As ``patches._median_2x2``: blocks of four valid points take
    (max of the column-pair minima + min of the column-pair maxima) / 2 in float32."""
    h2, w2 = Dz.shape
    out = (Dx, Dy, Dz)
    half = np.float32(0.5)
    v = np.empty(4, np.float32)
    valid = np.empty(4, np.bool_)
    buf = np.empty(4, np.float32)
    for i in range(h2):
        r0 = 2 * i
        r1 = r0 + 1
        for j in range(w2):
            c0 = 2 * j
            c1 = c0 + 1
            s00 = scale[r0, c0]
            s01 = scale[r0, c1]
            s10 = scale[r1, c0]
            s11 = scale[r1, c1]
            z00 = cloud[r0, c0, 2] * s00
            z01 = cloud[r0, c1, 2] * s01
            z10 = cloud[r1, c0, 2] * s10
            z11 = cloud[r1, c1, 2] * s11
            if (math.isfinite(z00) and math.isfinite(z01) and math.isfinite(z10)
                    and math.isfinite(z11)):
                for k in range(3):
                    a = cloud[r0, c0, k] * s00      # top row: even, odd column
                    b = cloud[r0, c1, k] * s01
                    c = cloud[r1, c0, k] * s10      # bottom row
                    d = cloud[r1, c1, k] * s11
                    lo_t = a if a < b else b
                    hi_t = b if a < b else a
                    lo_b = c if c < d else d
                    hi_b = d if c < d else c
                    m = (lo_t if lo_t > lo_b else lo_b) + (hi_t if hi_t < hi_b else hi_b)
                    m = m * half
                    out[k][i, j] = m
            else:
                valid[0] = math.isfinite(z00)
                valid[1] = math.isfinite(z10)
                valid[2] = math.isfinite(z01)
                valid[3] = math.isfinite(z11)
                for k in range(3):
                    v[0] = cloud[r0, c0, k] * s00
                    v[1] = cloud[r1, c0, k] * s10
                    v[2] = cloud[r0, c1, k] * s01
                    v[3] = cloud[r1, c1, k] * s11
                    m = _median_of_valid(v, valid, buf)
                    out[k][i, j] = m


# --------------------------------------------------------------------------------------------
# Step 7: integral images
# --------------------------------------------------------------------------------------------

@njit(types.void(_in_f4_2d_any, _in_f4_2d_any, _in_f4_2d_any, types.float32, types.float32,
                 types.float32, types.int32[:, :, ::1], _f8_3d, _f8_3d, _f8_3d), **_JIT)
def integral_moments(x, y, z, ox, oy, oz, ii_n, ii_p, ii_q, ii_r):
    """Integral images (h + 1, w + 1, .) of the planes ``x, y, z`` (h, w) centred on ``(ox, oy,
    oz)``: ``ii_n`` the valid (finite z) point count, ``ii_p`` the centred points ``p``
    (float32), ``ii_q`` their squares (float64, exact), ``ii_r`` the float32 products
    ``(p_x p_y, p_y p_z, p_z p_x)``; invalid points count as 0. ``patches.IntegralMoments``
    builds the same images with OpenCV (``cv2.integral``: a running row sum added to the row
    above, in float64), bit for bit."""
    h, w = z.shape
    for c in range(w + 1):
        ii_n[0, c, 0] = 0
        for k in range(3):
            ii_p[0, c, k] = 0.0
            ii_q[0, c, k] = 0.0
            ii_r[0, c, k] = 0.0
    zero = np.float32(0.0)
    for i in range(h):
        ii_n[i + 1, 0, 0] = 0
        for k in range(3):
            ii_p[i + 1, 0, k] = 0.0
            ii_q[i + 1, 0, k] = 0.0
            ii_r[i + 1, 0, k] = 0.0
        sn = 0
        s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = 0.0
        for j in range(w):
            zz = z[i, j]
            if math.isfinite(zz):
                px = x[i, j] - ox
                py = y[i, j] - oy
                pz = zz - oz
                sn += 1
            else:
                px = py = pz = zero
            dx, dy, dz = np.float64(px), np.float64(py), np.float64(pz)
            s0 += dx
            s1 += dy
            s2 += dz
            s3 += dx * dx
            s4 += dy * dy
            s5 += dz * dz
            s6 += np.float64(px * py)
            s7 += np.float64(py * pz)
            s8 += np.float64(pz * px)
            ii_n[i + 1, j + 1, 0] = ii_n[i, j + 1, 0] + sn
            ii_p[i + 1, j + 1, 0] = ii_p[i, j + 1, 0] + s0
            ii_p[i + 1, j + 1, 1] = ii_p[i, j + 1, 1] + s1
            ii_p[i + 1, j + 1, 2] = ii_p[i, j + 1, 2] + s2
            ii_q[i + 1, j + 1, 0] = ii_q[i, j + 1, 0] + s3
            ii_q[i + 1, j + 1, 1] = ii_q[i, j + 1, 1] + s4
            ii_q[i + 1, j + 1, 2] = ii_q[i, j + 1, 2] + s5
            ii_r[i + 1, j + 1, 0] = ii_r[i, j + 1, 0] + s6
            ii_r[i + 1, j + 1, 1] = ii_r[i, j + 1, 1] + s7
            ii_r[i + 1, j + 1, 2] = ii_r[i, j + 1, 2] + s8


# --------------------------------------------------------------------------------------------
# Step 11: organized neighbourhood search
# --------------------------------------------------------------------------------------------

@njit(_i8_1d(_in_f4_3d, _in_f4_2d, _in_f8_2d, _in_f8_2d, _in_f8_3d, types.float64,
             types.float64, types.float64, _f8_3d), **_JIT)
def sample_neighbourhoods(cloud, scale, seeds_full, seed_pts, u, fx, fy, r, nb):
    """The first ``n_f`` draws within ``r`` of each seed, in draw order, as the planes ``nb``
    (4, n_s, n_f) float64: x, y, z of the filtered points ``cloud * scale`` (0 in unused slots)
    and the mask as 0/1. ``u`` (2, n_s, k): uniform draws in [0, 1), column offsets first, then
    row offsets; ``seeds_full`` (n_s, 2): seed pixels (row, column) at full resolution;
    ``seed_pts`` (n_s, 3) float64. Returns the points per seed. Same operations as
    ``patches._sample_neighbourhoods``."""
    h, w = scale.shape
    ns = seed_pts.shape[0]
    k = u.shape[2]
    nf = nb.shape[2]
    rr = r * r
    rfx = r * fx
    rfy = r * fy
    wmax = w - 1.0
    hmax = h - 1.0
    counts = np.zeros(ns, np.int64)
    for i in range(ns):
        sx, sy, sz = seed_pts[i, 0], seed_pts[i, 1], seed_pts[i, 2]
        hx = rfx / sz
        hx = hx if hx >= 1.0 else 1.0
        hy = rfy / sz
        hy = hy if hy >= 1.0 else 1.0
        col0 = seeds_full[i, 1]
        row0 = seeds_full[i, 0]
        m = np.int64(0)
        for j in range(k):
            if m == nf:
                break
            x = (u[0, i, j] * 2.0 - 1.0) * hx + col0
            x = min(max(np.rint(x), 0.0), wmax)
            y = (u[1, i, j] * 2.0 - 1.0) * hy + row0
            y = min(max(np.rint(y), 0.0), hmax)
            row = int(y)
            col = int(x)
            s = np.float64(scale[row, col])
            px = np.float64(cloud[row, col, 0]) * s
            py = np.float64(cloud[row, col, 1]) * s
            pz = np.float64(cloud[row, col, 2]) * s
            dx = px - sx
            dy = py - sy
            dz = pz - sz
            d2 = dx * dx
            d2 += dz * dz                               # (x, z, y: the numpy step's order)
            d2 += dy * dy
            if d2 <= rr:                                # False for NaN
                nb[0, i, m] = px
                nb[1, i, m] = py
                nb[2, i, m] = pz
                nb[3, i, m] = 1.0
                m += 1
        for j in range(m, nf):
            nb[0, i, j] = 0.0
            nb[1, i, j] = 0.0
            nb[2, i, j] = 0.0
            nb[3, i, j] = 0.0
        counts[i] = m
    return counts


# --------------------------------------------------------------------------------------------
# Step 12: paraboloid fit
# --------------------------------------------------------------------------------------------

@njit(**_JIT)
def smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (the formulas of
    ``patches._smallest_eigenvector_parts``, one matrix)."""
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    p = math.sqrt(max(p2 / 6.0, 1e-300))
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
           + a02 * (a01 * a12 - b11 * a02))
    r = min(max(det / (2.0 * p ** 3.0), -1.0), 1.0)
    lam = q + 2.0 * p * math.cos(math.acos(r) / 3.0 + 2.0 * math.pi / 3.0)
    d0, d1, d2 = a00 - lam, a11 - lam, a22 - lam
    c00, c01, c02 = a01 * a12 - a02 * d1, a02 * a01 - d0 * a12, d0 * d1 - a01 * a01
    c10, c11, c20 = a01 * d2 - a02 * a12, a02 * a02 - d0 * d2, d1 * d2 - a12 * a12
    s00, s01, s10 = c00 * c00, c01 * c01, c10 * c10
    n0 = (s00 + c02 * c02) + s01
    n1 = (s10 + s01) + c11 * c11
    n2 = (c20 * c20 + s00) + s10
    if n0 >= n1 and n0 >= n2:
        vx, vy, vz, vn = c00, c01, c02, n0
    elif n1 >= n2:
        vx, vy, vz, vn = c10, c11, -c01, n1
    else:
        vx, vy, vz, vn = c20, -c10, c00, n2
    vn = math.sqrt(vn)
    if vn == 0.0:                                       # isotropic: any direction
        return 0.0, 0.0, 1.0
    return vx / vn, vy / vn, vz / vn


@njit(**_JIT)
def _solve6(G, x):
    """Solve ``G[:6, :6] x = G[:6, 6]`` (G (7, 7), overwritten) by Gaussian elimination with
    partial pivoting; raises ``LinAlgError`` on an exactly singular matrix (as LAPACK's gesv)."""
    for c in range(6):
        p = c
        best = abs(G[c, c])
        for i in range(c + 1, 6):
            a = abs(G[i, c])
            if a > best:
                best = a
                p = i
        if best == 0.0:
            raise np.linalg.LinAlgError('Singular matrix')
        if p != c:
            for j in range(c, 7):
                t = G[c, j]
                G[c, j] = G[p, j]
                G[p, j] = t
        inv = 1.0 / G[c, c]
        for i in range(c + 1, 6):
            f = G[i, c] * inv
            if f != 0.0:
                for j in range(c + 1, 7):
                    G[i, j] -= f * G[c, j]
    for c in range(5, -1, -1):
        s = G[c, 6]
        for j in range(c + 1, 6):
            s -= G[c, j] * x[j]
        x[c] = s / G[c, c]


@njit(**_JIT)
def _gram7(A, n, G):
    """``G = A[:, :n] A[:, :n]^T`` (7 x 7, symmetric). A row at a time against all seven: seven
    independent sums per pass (one sum after another would wait on each addition)."""
    for a in range(7):
        s0 = s1 = s2 = s3 = s4 = s5 = s6 = 0.0
        for j in range(n):
            x = A[a, j]
            s0 += x * A[0, j]
            s1 += x * A[1, j]
            s2 += x * A[2, j]
            s3 += x * A[3, j]
            s4 += x * A[4, j]
            s5 += x * A[5, j]
            s6 += x * A[6, j]
        G[a, 0] = s0
        G[a, 1] = s1
        G[a, 2] = s2
        G[a, 3] = s3
        G[a, 4] = s4
        G[a, 5] = s5
        G[a, 6] = s6


@njit(**_JIT)
def _residuals(q, kx, ky, h, A, n):
    """Rows 0, 1 (``q_x^2 / 2``, ``q_y^2 / 2``) and 6 (the residuals
    ``0.5 (kx q_x^2 + ky q_y^2) - (q_z - h)``) of the LM rows ``A`` for the frame points ``q``
    (3, n); returns the squared residual sum."""
    cur = 0.0
    for j in range(n):
        a0 = q[0, j] * q[0, j] * 0.5
        a1 = q[1, j] * q[1, j] * 0.5
        A[0, j] = a0
        A[1, j] = a1
        rj = (a0 * kx + a1 * ky) - (q[2, j] - h)
        A[6, j] = rj
        cur += rj * rj
    return cur


@njit(**_JIT)
def _expmap(wx, wy, wz, E):
    """Rotation matrix of the rotation vector ``w`` into ``E`` (3, 3) (scipy's rotvec ->
    quaternion -> matrix formulas)."""
    angle = math.sqrt(wx * wx + wy * wy + wz * wz)
    if angle <= 1e-3:
        a2 = angle * angle
        scale = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
    else:
        scale = math.sin(angle / 2.0) / angle
    x, y, z, w = wx * scale, wy * scale, wz * scale, math.cos(angle / 2.0)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    E[0, 0] = x2 - y2 - z2 + w2
    E[0, 1] = 2.0 * (xy - zw)
    E[0, 2] = 2.0 * (xz + yw)
    E[1, 0] = 2.0 * (xy + zw)
    E[1, 1] = -x2 + y2 - z2 + w2
    E[1, 2] = 2.0 * (yz - xw)
    E[2, 0] = 2.0 * (xz - yw)
    E[2, 1] = 2.0 * (yz + xw)
    E[2, 2] = -x2 - y2 + z2 + w2


@njit(**_JIT)
def _matmul3(A, B, C):
    """``C = A B`` for 3x3 matrices (C distinct from A and B)."""
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(**_JIT)
def _kth_smallest(v, n, k):
    """The ``k``-th smallest of ``v[:n]`` (0-based; no NaN), by insertion sort (``v``
    reordered; n is small)."""
    for i in range(1, n):
        x = v[i]
        j = i
        while j > 0 and v[j - 1] > x:
            v[j] = v[j - 1]
            j -= 1
        v[j] = x
    return v[k]


@njit(types.void(_in_f8_3d, _in_f8_2d, types.int64, _f8_2d, _f8_3d, _f8_1d, _f8_1d, _f8_1d,
                 _f8_1d, _f8_1d, _i8_1d), **_JIT)
def fit_paraboloids(D, up, iterations, vertex, R_out, kx_out, ky_out, rms_alg, rms_euc,
                    radius, cnt_out):
    """Paraboloid fits (``patches._fit_paraboloids``) of the neighbourhoods ``D`` (4, P, n):
    x, y, z and the mask (0/1; masked points are ignored); ``up`` (P, 3): the direction each
    patch normal points to. Results into the output arrays (P, 3), (P, 3, 3), (P,) x 5 and the
    points per patch ``cnt_out`` (P,) int64."""
    npatch, n = D.shape[1], D.shape[2]
    d = np.empty((3, n))            # centred points of the patch (valid ones first)
    q = np.empty((3, n))            # frame coordinates, current state
    qn = np.empty((3, n))           # frame coordinates, candidate state
    A = np.empty((7, n))            # [J; r] rows, current state
    B = np.empty((7, n))            # candidate rows (0, 1, 6)
    G = np.empty((7, 7))
    x = np.empty(6)
    R = np.empty((3, 3))
    Rn = np.empty((3, 3))
    E = np.empty((3, 3))
    T = np.empty((3, 3))
    rad = np.empty(n)
    for p in range(npatch):
        # Valid points (compacted: masked points contribute exact zeros to every sum).
        m = np.int64(0)
        for j in range(n):
            if D[3, p, j] != 0.0:
                d[0, m] = D[0, p, j]
                d[1, m] = D[1, p, j]
                d[2, m] = D[2, p, j]
                m += 1
        cnt_out[p] = m
        fc = float(m)
        c0 = 0.0
        c1 = 0.0
        c2 = 0.0
        for j in range(m):
            c0 += d[0, j]
            c1 += d[1, j]
            c2 += d[2, j]
        c0 /= fc
        c1 /= fc
        c2 /= fc
        s00 = s01 = s02 = s11 = s12 = s22 = 0.0
        for j in range(m):
            dx = d[0, j] - c0
            dy = d[1, j] - c1
            dz = d[2, j] - c2
            d[0, j] = dx
            d[1, j] = dy
            d[2, j] = dz
            s00 += dx * dx
            s01 += dx * dy
            s02 += dx * dz
            s11 += dy * dy
            s12 += dy * dz
            s22 += dz * dz
        nx, ny, nz = smallest_eigenvector(s00 / fc, s01 / fc, s02 / fc, s11 / fc, s12 / fc,
                                          s22 / fc)
        if nx * up[p, 0] + ny * up[p, 1] + nz * up[p, 2] < 0.0:
            nx, ny, nz = -nx, -ny, -nz
        # PCA frame: z = normal, x = helper x normal (helper e_x, or e_y near e_x), y = z x x.
        if abs(nx) < 0.9:
            xx, xy, xz = 0.0, -nz, ny
        else:
            xx, xy, xz = nz, 0.0, -nx
        xn = math.sqrt(xx * xx + xy * xy + xz * xz)
        xx /= xn
        xy /= xn
        xz /= xn
        yx, yy, yz = ny * xz - nz * xy, nz * xx - nx * xz, nx * xy - ny * xx
        # Quadric z = a x^2 + b xy + c y^2 + d x + e y + f by the normal equations.
        for j in range(m):
            qx = xx * d[0, j] + xy * d[1, j] + xz * d[2, j]
            qy = yx * d[0, j] + yy * d[1, j] + yz * d[2, j]
            qz = nx * d[0, j] + ny * d[1, j] + nz * d[2, j]
            A[0, j] = qx * qx
            A[1, j] = qx * qy
            A[2, j] = qy * qy
            A[3, j] = qx
            A[4, j] = qy
            A[5, j] = 1.0
            A[6, j] = qz
        _gram7(A, m, G)
        tr = 0.0
        for i in range(6):
            tr += G[i, i]
        eps = 1e-9 * max(tr, 1e-12)
        for i in range(6):
            G[i, i] += eps
        _solve6(G, x)
        a, b, cc, ddx, ddy, f0 = x[0], x[1], x[2], x[3], x[4], x[5]
        tn = math.sqrt(1.0 + ddx * ddx + ddy * ddy)
        tx, ty, tz = -ddx / tn, -ddy / tn, 1.0 / tn
        f = -1.0 / (1.0 + tz)
        # Rt (the tilt to the quadric's normal at the origin), into E
        E[0, 0] = tx * (f * tx) + 1.0
        E[0, 1] = tx * (f * ty)
        E[1, 0] = ty * (f * tx)
        E[1, 1] = ty * (f * ty) + 1.0
        E[0, 2] = tx
        E[1, 2] = ty
        E[2, 0] = -tx
        E[2, 1] = -ty
        E[2, 2] = tz
        amc = a - cc
        theta = 0.5 * math.atan2(b, amc)
        ct, st = math.cos(theta), math.sin(theta)
        for i in range(3):                      # T = Rt Rz(theta)
            T[i, 0] = E[i, 0] * ct + E[i, 1] * st
            T[i, 1] = E[i, 1] * ct - E[i, 0] * st
            T[i, 2] = E[i, 2]
        for j in range(3):                      # R = Rp T, Rp = [x0 y0 n0]
            R[0, j] = xx * T[0, j] + yx * T[1, j] + nx * T[2, j]
            R[1, j] = xy * T[0, j] + yy * T[1, j] + ny * T[2, j]
            R[2, j] = xz * T[0, j] + yz * T[1, j] + nz * T[2, j]
        rho = math.sqrt(amc * amc + b * b)
        kx = (a + cc) + rho
        ky = (a + cc) - rho
        h = f0 * tz

        # Levenberg-Marquardt over (kx, ky, rotation, h): rows 0-4 of A are J, 5 is d r / d h
        # (1), 6 the residuals.
        for j in range(m):
            q[0, j] = R[0, 0] * d[0, j] + R[1, 0] * d[1, j] + R[2, 0] * d[2, j]
            q[1, j] = R[0, 1] * d[0, j] + R[1, 1] * d[1, j] + R[2, 1] * d[2, j]
            q[2, j] = R[0, 2] * d[0, j] + R[1, 2] * d[1, j] + R[2, 2] * d[2, j]
            A[5, j] = 1.0
        cur = _residuals(q, kx, ky, h, A, m)
        lam = 1e-3
        for _ in range(iterations):
            for j in range(m):
                gx = kx * q[0, j]
                gy = ky * q[1, j]
                A[2, j] = gy * q[2, j] + q[1, j]
                A[3, j] = -(gx * q[2, j] + q[0, j])
                A[4, j] = gx * q[1, j] - gy * q[0, j]
            _gram7(A, m, G)
            for i in range(6):
                G[i, i] = G[i, i] * (1.0 + lam) + 1e-12 * lam
            _solve6(G, x)                       # (the step is minus x)
            _expmap(-x[2], -x[3], -x[4], E)
            _matmul3(R, E, Rn)
            kxn, kyn, hn = kx - x[0], ky - x[1], h - x[5]
            for j in range(m):                  # E^T q
                qn[0, j] = E[0, 0] * q[0, j] + E[1, 0] * q[1, j] + E[2, 0] * q[2, j]
                qn[1, j] = E[0, 1] * q[0, j] + E[1, 1] * q[1, j] + E[2, 1] * q[2, j]
                qn[2, j] = E[0, 2] * q[0, j] + E[1, 2] * q[1, j] + E[2, 2] * q[2, j]
            new = _residuals(qn, kxn, kyn, hn, B, m)
            ok = new < cur
            go = (cur - new > 1e-3 * cur) or not ok     # rejected steps retry, more damped
            lam = min(max(lam * (0.1 if ok else 10.0), 1e-9), 1e9)
            go = go and lam < 1e9
            if ok:
                q, qn = qn, q
                for j in range(m):
                    A[0, j] = B[0, j]
                    A[1, j] = B[1, j]
                    A[6, j] = B[6, j]
                R, Rn = Rn, R
                kx, ky, h, cur = kxn, kyn, hn, new
            if not go:
                break
        # Outputs: kx <= ky by a +90 deg turn about the normal (x' = y, y' = -x).
        sr = 0.0
        se = 0.0
        for j in range(m):
            rj = A[6, j]
            sr += rj * rj
            g0 = kx * q[0, j]
            g1 = ky * q[1, j]
            re = rj / math.sqrt(g0 * g0 + g1 * g1 + 1.0)
            se += re * re
            rad[j] = math.sqrt(q[0, j] * q[0, j] + q[1, j] * q[1, j])
        rms_alg[p] = math.sqrt(sr / fc)
        rms_euc[p] = math.sqrt(se / fc)
        radius[p] = _kth_smallest(rad, m, int(math.floor(0.95 * (m - 1))))
        if kx > ky:
            for i in range(3):
                R_out[p, i, 0] = R[i, 1]
                R_out[p, i, 1] = -R[i, 0]
                R_out[p, i, 2] = R[i, 2]
            kx_out[p] = ky
            ky_out[p] = kx
        else:
            for i in range(3):
                for j in range(3):
                    R_out[p, i, j] = R[i, j]
            kx_out[p] = kx
            ky_out[p] = ky
        vertex[p, 0] = c0 + h * R[0, 2]
        vertex[p, 1] = c1 + h * R[1, 2]
        vertex[p, 2] = c2 + h * R[2, 2]
