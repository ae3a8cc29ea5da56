"""Compiled (numba) kernel of :func:`terrain_perception.body_path.plan_body_path`'s headroom.

Every plan searches a body path over the map (the planner node: once per map). Before the
search, each lattice position the body may take needs the highest map cell under the body box
(the belly samples, up to ~340 of them for FROG-I's 0.4 m body) and the ground under its four
nominal feet (five samples each). The numpy code builds those gathers as ``(positions,
samples, 2)`` arrays: about a million points per plan for FROG-I on a 3 m map with the
route's corridor, 55-65 ms of its 80-90 ms plans on the stones (a profile of the planner on a
stones map). This kernel walks the same samples per position without the temporaries; the
planner's map callback on a FROG-I stones bag went 69.5 -> 40.8 ms CPU with it
(docs/BENCHMARKS.md ``pipeline-frog-s31``).

Same float64 operations in the same order as the numpy code (``(x - origin) / resolution``
floored per sample, the maximum over the belly samples, per foot the minimum over its samples
with NaN propagating as ``np.min`` does, then ``((f0 + f1) + f2) + f3`` / 4 as ``np.mean`` over
four values), so the results are bitwise equal (``test/test_body_path.py`` compares the two;
``TERRAIN_BODY_PATH_NUMBA=0`` selects the numpy code). Explicit signature and ``cache=True``:
importing compiles it once per machine, then loads it from ``__pycache__``.
"""

from __future__ import annotations

import math

from numba import njit, types

_in_f8_2d = types.Array(types.float64, 2, 'C', readonly=True)
_f8_1d = types.float64[::1]
_b1_1d = types.boolean[::1]
_SIG = types.void(_in_f8_2d, _in_f8_2d, _in_f8_2d, types.int64, types.float64, types.float64,
                  types.float64, _in_f8_2d, _in_f8_2d, _f8_1d, _f8_1d, _b1_1d)


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _cell(x, y, ox, oy, res, ni, nj):
    """Cell ``(i, j)`` of map point ``(x, y)`` as ``GridMap.world_to_index`` floors it, and
    whether it lies on the ``ni`` x ``nj`` grid."""
    i = int(math.floor((x - ox) / res))
    j = int(math.floor((y - oy) / res))
    return i, j, 0 <= i < ni and 0 <= j < nj


@njit(_SIG, cache=True, nogil=True, error_model='numpy')
def belly_and_ground(nodes, belly_xy, feet_xy, ring, ox, oy, res, top, elev,
                     top_max, ground, on_map):
    """Per body position ``nodes[k]`` (map frame): ``top_max[k]`` the maximum of ``top`` at
    ``nodes[k] + belly_xy`` (already rotated), ``ground[k]`` the mean over the feet of the
    minimum of ``elev`` over each foot's ``ring`` consecutive rows of ``feet_xy`` (NaN if any is
    NaN), ``on_map[k]`` whether every sample lies on the grid (else the other two are
    undefined)."""
    ni, nj = top.shape[0], top.shape[1]
    nf = feet_xy.shape[0] // ring
    for k in range(nodes.shape[0]):
        x, y = nodes[k, 0], nodes[k, 1]
        inside = True
        m = -math.inf
        for s in range(belly_xy.shape[0]):
            i, j, on = _cell(x + belly_xy[s, 0], y + belly_xy[s, 1], ox, oy, res, ni, nj)
            if not on:
                inside = False
                break
            v = top[i, j]
            if v > m:
                m = v
        total = 0.0
        if inside:
            for f in range(nf):
                lo = math.inf
                nan = False
                for r in range(ring):
                    s = f * ring + r
                    i, j, on = _cell(x + feet_xy[s, 0], y + feet_xy[s, 1], ox, oy, res, ni, nj)
                    if not on:
                        inside = False
                        break
                    v = elev[i, j]
                    if math.isnan(v):
                        nan = True
                    elif v < lo:
                        lo = v
                if not inside:
                    break
                foot = math.nan if nan else lo
                total = foot if f == 0 else total + foot
        top_max[k] = m
        ground[k] = total / nf
        on_map[k] = inside
