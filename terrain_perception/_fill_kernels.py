"""Compiled (numba) kernel of :func:`terrain_perception.fill._choose`'s choice step.

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
"""

from __future__ import annotations

import math

from numba import njit, types

_JIT = dict(cache=True, nogil=True, error_model='numpy')

_in_f8_2d = types.Array(types.float64, 2, 'C', readonly=True)
_in_f8_3d = types.Array(types.float64, 3, 'C', readonly=True)


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
            if nan_seen:
                continue
            if t == 0:
                best_v = val
                nan_seen = math.isnan(val)
            elif math.isnan(val):
                best = t
                nan_seen = True
            elif val < best_v:
                best = t
                best_v = val
        k[i] = best
        any_ok[i] = found
