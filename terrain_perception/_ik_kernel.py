"""Compiled (numba) leg inverse kinematics for :func:`terrain_perception.kinematics.solve_ik`.

The controller's checks (body shifts, swing heights, reach searches) and the planner's dry run
of them call ``solve_ik`` hundreds of times per plan on a few dozen targets each; the numpy
version spends most of that in per-call array overhead (~40 ufunc calls). This kernel does the
same arithmetic per leg in one loop. It is the numpy code's operations in the same order, so
results agree to the last bit wherever numpy's and LLVM's ``atan2``/``acos``/``sin``/``cos``
agree (``test/test_kinematics.py`` compares them; ``TERRAIN_IK_NUMBA=0`` selects the numpy
code). Compiled with an explicit signature and ``cache=True`` when imported.
"""

from __future__ import annotations

import math

from numba import njit, types

# codes of the first failed check, in the order solve_ik reports them
OK, NOT_IN_PLANE, TOO_FAR, TOO_CLOSE, OUT_OF_LIMITS = 0, 1, 2, 3, 4

_in3 = types.Array(types.float64, 3, 'C', readonly=True)
_in2 = types.Array(types.float64, 2, 'C', readonly=True)
_in1 = types.Array(types.float64, 1, 'C', readonly=True)
_SIG = types.void(_in3, _in2, _in1, types.float64, types.float64, _in1, _in3, types.float64,
                  types.float64, types.float64[:, :, ::1], types.int8[:, ::1])


@njit(cache=True, nogil=True, error_model='numpy', inline='always')
def _into_limits(v, lo, hi, eps_limit, two_pi):
    """The equivalent angle within [lo, hi] when ``v`` is outside and one exists (2 pi
    either way, -2 pi tried first, as solve_ik's numpy code); and whether it stays outside."""
    for k in (-1.0, 1.0):
        alt = v + two_pi * k
        if ((v < lo - eps_limit) or (v > hi + eps_limit)) and \
                (alt >= lo - eps_limit) and (alt <= hi + eps_limit):
            v = alt
    return v, (v < lo - eps_limit) or (v > hi + eps_limit)


@njit(_SIG, cache=True, nogil=True, error_model='numpy')
def solve_legs(p, hip, side_d, l1, l2, knee_sign, lim, eps_reach, eps_limit, q, code):
    """``p`` (n, 4, 3) foot centres in base_link -> ``q`` (n, 4, 3) angles (NaN where
    unreachable) and ``code`` (n, 4): OK or the first failed check."""
    two_pi = 2.0 * math.pi
    for i in range(p.shape[0]):
        for leg in range(4):
            x = p[i, leg, 0] - hip[leg, 0]
            y = p[i, leg, 1] - hip[leg, 1]
            z = p[i, leg, 2] - hip[leg, 2]
            d = side_d[leg]
            rho2 = y * y + z * z - d * d
            in_plane = rho2 >= -eps_reach
            r0 = rho2 if rho2 >= 0.0 or rho2 != rho2 else 0.0    # np.maximum(rho2, 0.0)
            h = -math.sqrt(r0)
            q0 = math.atan2(z, y) - math.atan2(h, d)
            q0 = (q0 + math.pi) % two_pi - math.pi
            a = -x
            b = -h
            L2 = a * a + b * b
            c2 = (L2 - l1 * l1 - l2 * l2) / (2.0 * l1 * l2)
            reach = math.sqrt(L2)
            too_far = reach > l1 + l2 + eps_reach
            too_close = reach < abs(l1 - l2) - eps_reach
            cc = c2                                             # np.clip(c2, -1, 1), NaN kept
            if cc < -1.0:
                cc = -1.0
            elif cc > 1.0:
                cc = 1.0
            q2 = knee_sign[leg] * math.acos(cc)
            q1 = math.atan2(a, b) - math.atan2(l2 * math.sin(q2), l1 + l2 * math.cos(q2))
            q0, out0 = _into_limits(q0, lim[leg, 0, 0], lim[leg, 0, 1], eps_limit, two_pi)
            q1, out1 = _into_limits(q1, lim[leg, 1, 0], lim[leg, 1, 1], eps_limit, two_pi)
            q2, out2 = _into_limits(q2, lim[leg, 2, 0], lim[leg, 2, 1], eps_limit, two_pi)
            if not in_plane:
                c = NOT_IN_PLANE
            elif too_far:
                c = TOO_FAR
            elif too_close:
                c = TOO_CLOSE
            elif out0 or out1 or out2:
                c = OUT_OF_LIMITS
            else:
                c = OK
            code[i, leg] = c
            if c != OK:
                q0 = q1 = q2 = math.nan
            q[i, leg, 0] = q0
            q[i, leg, 1] = q1
            q[i, leg, 2] = q2
