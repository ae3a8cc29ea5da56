"""Analytic leg kinematics of a 3-DOF quadruped leg, vectorised over legs (and poses).

Leg model (see :mod:`terrain_perception.robot_model`): the hip-abduction joint at
``hip_offsets[leg]`` rotates about base x; the hip-flexion joint sits ``abduction_offset_m``
outward and rotates about the leg's y; the knee ``thigh_length_m`` below it; the foot centre
``shank_length_m`` below the knee. All zero = leg straight down; positive flexion swings the
foot backward. In the leg plane (after abduction) the foot is at::

    x' = -l1 sin(q1) - l2 sin(q1 + q2),   y' = side * d,   z' = -l1 cos(q1) - l2 cos(q1 + q2)

and ``p_base = hip + Rx(q0) @ (x', y', z')``.

Positions are foot-sphere centres in ``base_link`` [m]; angles [rad]. Joint arrays are
``(..., 4, 3)`` = ``[..., leg, (abduction, flexion, knee)]``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np

from terrain_perception.compiled import load_compiled
from terrain_perception.robot_model import LEG_NAMES, LEG_SIDE, RobotModel

_EPS_REACH = 1e-9    # [m] tolerance on reach checks (numerical round-off only)
_EPS_LIMIT = 1e-9    # [rad] tolerance on joint limits
_LOG = logging.getLogger(__name__)


def _load_ik_kernel():
    """The compiled IK (terrain_perception._ik_kernel), or None for the numpy code
    (``TERRAIN_IK_NUMBA=0``, or numba missing: logged once)."""
    return load_compiled('_ik_kernel', 'TERRAIN_IK_NUMBA', 'leg IK', _LOG)


_ik = _load_ik_kernel()


def use_compiled_ik(enabled: Optional[bool] = True) -> bool:
    """Select the compiled IK (``True``), the numpy code (``False``) or the default (``None``)
    for the following :func:`solve_ik` calls, process-wide; returns whether compiled is on."""
    global _ik
    if enabled is None:
        _ik = _load_ik_kernel()
    elif enabled:
        from terrain_perception import _ik_kernel
        _ik = _ik_kernel
    else:
        _ik = None
    return _ik is not None


def _leg_arrays(model: RobotModel, q_or_p: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(q_or_p, dtype=np.float64)
    if a.shape[-2:] != (4, 3):
        raise ValueError(f'{what} must have shape (..., 4, 3), got {a.shape}')
    return a


def forward(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """Foot centres ``(..., 4, 3)`` in base_link [m] from joint angles ``(..., 4, 3)`` [rad]."""
    q = _leg_arrays(model, q, 'joint angles')
    l1, l2 = model.thigh_length_m, model.shank_length_m
    q0, q1, q2 = q[..., 0], q[..., 1], q[..., 2]
    xp = -l1 * np.sin(q1) - l2 * np.sin(q1 + q2)
    yp = np.broadcast_to(LEG_SIDE * model.abduction_offset_m, xp.shape)
    zp = -l1 * np.cos(q1) - l2 * np.cos(q1 + q2)
    c0, s0 = np.cos(q0), np.sin(q0)
    return np.stack([xp, c0 * yp - s0 * zp, s0 * yp + c0 * zp], axis=-1) + model.hip_offsets


def jacobian(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """``(..., 4, 3, 3)`` d(foot position in base_link)/d(joint angles), ``[leg, xyz, joint]``."""
    q = _leg_arrays(model, q, 'joint angles')
    l1, l2 = model.thigh_length_m, model.shank_length_m
    q0, q1, q2 = q[..., 0], q[..., 1], q[..., 2]
    s1, c1, s12, c12 = np.sin(q1), np.cos(q1), np.sin(q1 + q2), np.cos(q1 + q2)
    yp = np.broadcast_to(LEG_SIDE * model.abduction_offset_m, q0.shape)
    zp = -l1 * c1 - l2 * c12
    c0, s0 = np.cos(q0), np.sin(q0)
    J = np.zeros(q.shape[:-1] + (3, 3))
    # d/dq0 of Rx(q0) @ (x', y', z')
    J[..., 1, 0] = -s0 * yp - c0 * zp
    J[..., 2, 0] = c0 * yp - s0 * zp
    for col, (dx, dz) in ((1, (-l1 * c1 - l2 * c12, l1 * s1 + l2 * s12)),
                          (2, (-l2 * c12, l2 * s12))):
        J[..., 0, col] = dx
        J[..., 1, col] = -s0 * dz
        J[..., 2, col] = c0 * dz
    return J


def foot_forces(model: RobotModel, q: np.ndarray, tau: np.ndarray,
                J: np.ndarray = None) -> np.ndarray:
    """Ground reaction force on each foot ``(..., 4, 3)`` in base_link [N] from joint torques.

    Static balance of each leg: the motors' torques ``tau`` hold the ground's force ``f`` on
    the foot, ``tau = -J(q)^T f`` (leg weight and dynamics neglected: the legs are light), so
    ``f = -J^-T tau``. This is how a robot without foot sensors feels touchdown. ``tau``
    ``(..., 4, 3)`` or ``(..., 12)`` motor torques [N m]; a singular leg (straight knee) gives
    NaN for that leg. ``J``: :func:`jacobian` at ``q`` if the caller has it already.
    """
    q = _leg_arrays(model, np.asarray(q, dtype=np.float64).reshape(
        np.shape(q)[:-1] + (4, 3) if np.shape(q)[-1] == 12 else np.shape(q)), 'joint angles')
    t = np.asarray(tau, dtype=np.float64).reshape(q.shape)
    J = jacobian(model, q) if J is None else np.asarray(J, dtype=np.float64)
    JT = np.swapaxes(J, -1, -2)
    ok = np.abs(np.linalg.det(JT)) > 1e-9
    JT = np.where(ok[..., None, None], JT, np.eye(3))
    f = -np.linalg.solve(JT, t[..., None])[..., 0]
    return np.where(ok[..., None], f, np.nan)


@dataclass(frozen=True)
class IKResult:
    """Inverse kinematics outcome.

    Attributes:
        q: ``(..., 4, 3)`` joint angles [rad]; NaN for unreachable legs (never clamped).
        ok: ``(..., 4)`` True where the target is reachable within the joint limits.
        reasons: one message per unreachable leg (empty when all are reachable).
    """

    q: np.ndarray
    ok: np.ndarray
    reasons: tuple

    @property
    def all_ok(self) -> bool:
        return bool(np.all(self.ok))


def solve_ik(model: RobotModel, feet_base: np.ndarray, explain: bool = True) -> IKResult:
    """Joint angles placing the foot centres at ``feet_base`` ``(..., 4, 3)`` [m, base_link].

    Unreachable targets (too far, too close, inside the abduction offset, or needing a joint
    outside its limits) get NaN angles and ``ok = False`` with a reason naming the leg
    (``explain=False``: no reasons, for searches that only need ``ok``).
    """
    p = _leg_arrays(model, feet_base, 'foot targets')
    if _ik is not None:
        return _solve_ik_compiled(model, p, explain)
    l1, l2 = model.thigh_length_m, model.shank_length_m
    r = p - model.hip_offsets
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    d = np.broadcast_to(LEG_SIDE * model.abduction_offset_m, x.shape)
    rho2 = y * y + z * z - d * d
    in_plane = rho2 >= -_EPS_REACH
    h = -np.sqrt(np.maximum(rho2, 0.0))
    q0 = np.arctan2(z, y) - np.arctan2(h, d)
    q0 = (q0 + np.pi) % (2.0 * np.pi) - np.pi
    a, b = -x, -h
    L2 = a * a + b * b
    c2 = (L2 - l1 * l1 - l2 * l2) / (2.0 * l1 * l2)
    reach = np.sqrt(L2)
    too_far = reach > l1 + l2 + _EPS_REACH
    too_close = reach < abs(l1 - l2) - _EPS_REACH
    q2 = model.knee_sign * np.arccos(np.clip(c2, -1.0, 1.0))
    q1 = np.arctan2(a, b) - np.arctan2(l2 * np.sin(q2), l1 + l2 * np.cos(q2))
    q = np.stack([q0, q1, q2], axis=-1)
    lo, hi = model.joint_limits[..., 0], model.joint_limits[..., 1]
    # Limits may span more than 2 pi (LittleDog's hip flexion): use the equivalent angle
    # that lies within them when there is one.
    for k in (-1.0, 1.0):
        alt = q + 2.0 * np.pi * k
        use = ((q < lo - _EPS_LIMIT) | (q > hi + _EPS_LIMIT)) & (alt >= lo - _EPS_LIMIT) & \
            (alt <= hi + _EPS_LIMIT)
        q = np.where(use, alt, q)
    out_of_limits = np.any((q < lo - _EPS_LIMIT) | (q > hi + _EPS_LIMIT), axis=-1)
    ok = in_plane & ~too_far & ~too_close & ~out_of_limits
    q = np.where(ok[..., None], q, np.nan)

    reasons = []
    if explain and not np.all(ok):
        flat_ok = ok.reshape(-1, 4)
        checks = [(~in_plane, 'target inside the abduction offset circle'),
                  (too_far, 'target beyond the leg length'),
                  (too_close, 'target closer than |thigh - shank|'),
                  (out_of_limits, 'solution outside the joint limits')]
        flat_checks = [(c.reshape(-1, 4), msg) for c, msg in checks]
        for idx, leg in zip(*np.nonzero(~flat_ok)):
            why = next(msg for c, msg in flat_checks if c[idx, leg])
            where = f'pose {idx} ' if flat_ok.shape[0] > 1 else ''
            reasons.append(f'{where}leg {LEG_NAMES[leg]}: {why} '
                           f'(target {np.round(p.reshape(-1, 4, 3)[idx, leg], 4).tolist()} m)')
    return IKResult(q=q, ok=ok, reasons=tuple(reasons))


_IK_REASONS = {1: 'target inside the abduction offset circle',
               2: 'target beyond the leg length',
               3: 'target closer than |thigh - shank|',
               4: 'solution outside the joint limits'}


_ik_constants_cache: dict = {}


def _ik_constants(model: RobotModel) -> tuple:
    """The kernel's per-model arrays (models are frozen: computed once per model object)."""
    hit = _ik_constants_cache.get(id(model))
    if hit is not None and hit[0] is model:
        return hit[1]
    f8 = np.float64
    consts = (np.ascontiguousarray(model.hip_offsets, f8),
              np.ascontiguousarray(LEG_SIDE * model.abduction_offset_m, f8),
              float(model.thigh_length_m), float(model.shank_length_m),
              np.ascontiguousarray(np.broadcast_to(model.knee_sign, (4,)), f8),
              np.ascontiguousarray(np.broadcast_to(model.joint_limits, (4, 3, 2)), f8),
              _EPS_REACH, _EPS_LIMIT)
    if len(_ik_constants_cache) > 64:
        _ik_constants_cache.clear()
    _ik_constants_cache[id(model)] = (model, consts)
    return consts


def _solve_ik_compiled(model: RobotModel, p: np.ndarray, explain: bool) -> IKResult:
    flat = np.ascontiguousarray(p.reshape(-1, 4, 3))
    n = flat.shape[0]
    q = np.empty((n, 4, 3))
    code = np.empty((n, 4), np.int8)
    _ik.solve_legs(flat, *_ik_constants(model), q, code)
    ok = code == 0
    reasons = []
    if explain and not ok.all():
        for idx, leg in zip(*np.nonzero(~ok)):
            where = f'pose {idx} ' if n > 1 else ''
            reasons.append(f'{where}leg {LEG_NAMES[leg]}: {_IK_REASONS[int(code[idx, leg])]} '
                           f'(target {np.round(flat[idx, leg], 4).tolist()} m)')
    return IKResult(q=q.reshape(p.shape), ok=ok.reshape(p.shape[:-1]),
                    reasons=tuple(reasons))


def inverse(model: RobotModel, feet_base: np.ndarray) -> np.ndarray:
    """Like :func:`solve_ik` but raises ValueError naming every unreachable leg."""
    res = solve_ik(model, feet_base)
    if not res.all_ok:
        raise ValueError(f'{model.name}: unreachable foot targets: ' + '; '.join(res.reasons))
    return res.q


def feet_in_base(T_world_base: np.ndarray, feet_world: np.ndarray) -> np.ndarray:
    """Express world foot positions ``(..., 3)`` in a base frame given ``T_world_base``."""
    R, t = T_world_base[:3, :3], T_world_base[:3, 3]
    return (np.asarray(feet_world, dtype=np.float64) - t) @ R


def standing_joint_angles(model: RobotModel) -> np.ndarray:
    """``(4, 3)`` joint angles of the nominal stance (foot contact points at nominal_feet)."""
    feet = np.array(model.nominal_feet)
    feet[:, 2] += model.foot_radius_m
    return inverse(model, feet)


def leg_points(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """``(..., 4, 4, 3)`` hip-abduction origin, hip-flexion origin, knee and foot centre of each
    leg in base_link [m]."""
    q = _leg_arrays(model, q, 'joint angles')
    l1, l2 = model.thigh_length_m, model.shank_length_m
    q0, q1, q2 = q[..., 0], q[..., 1], q[..., 2]
    yp = np.broadcast_to(LEG_SIDE * model.abduction_offset_m, q0.shape)
    zero = np.zeros_like(q0)
    planar = [(zero, zero), (-l1 * np.sin(q1), -l1 * np.cos(q1)),
              (-l1 * np.sin(q1) - l2 * np.sin(q1 + q2), -l1 * np.cos(q1) - l2 * np.cos(q1 + q2))]
    c0, s0 = np.cos(q0), np.sin(q0)
    pts = [np.broadcast_to(model.hip_offsets, q.shape)]
    for xp, zp in planar:
        pts.append(np.stack([xp, c0 * yp - s0 * zp, s0 * yp + c0 * zp], axis=-1)
                   + model.hip_offsets)
    return np.stack(pts, axis=-2)


def self_mask(model: RobotModel, q: np.ndarray, points: np.ndarray,
              T_frame_base: np.ndarray, margin_m: float) -> np.ndarray:
    """Which of ``points`` ``(..., 3)`` (in a frame ``T_frame_base`` maps base_link into, e.g.
    the camera's) lie on the robot's own legs: within ``foot_radius_m + margin_m`` of a thigh
    (hip-flexion origin to knee) or shank (knee to foot centre) segment at joint angles ``q``
    ``(4, 3)``. A camera that sees the front legs would otherwise map them as terrain.

    NaN points are not masked. Cost: only points inside the legs' bounding box are tested
    (the box test runs on the input's own dtype against float64 bounds, i.e. on each
    coordinate's float64 value; only those points are widened to float64).
    """
    pts = np.asarray(points)
    if pts.dtype not in (np.float32, np.float64):
        pts = pts.astype(np.float64)
    if pts.shape[-1] != 3:
        raise ValueError(f'points must be (..., 3), got shape {pts.shape}')
    q = _leg_arrays(model, q, 'joint angles')
    if q.shape != (4, 3):
        raise ValueError(f'one joint configuration (4, 3) expected, got {q.shape}')
    lp = leg_points(model, q)[:, 1:]                       # hip-flexion origin, knee, foot
    T = np.asarray(T_frame_base, dtype=np.float64)
    lp = lp @ T[:3, :3].T + T[:3, 3]
    a = lp[:, :2].reshape(-1, 3)                           # segment starts (8, 3)
    b = lp[:, 1:].reshape(-1, 3)                           # segment ends
    r = model.foot_radius_m + float(margin_m)
    flat = pts.reshape(-1, 3)
    out = np.zeros(len(flat), dtype=bool)
    lo, hi = np.minimum(a, b).min(axis=0) - r, np.maximum(a, b).max(axis=0) + r
    with np.errstate(invalid='ignore'):
        # per coordinate, each on the survivors of the one before (np.all over axis 1 of an
        # (N, 3) mask is several times slower); lo[k], hi[k] are float64 scalars, so a float32
        # input is compared as float64. z first: in a camera frame it is the depth, and the
        # legs are near the camera
        cand = np.flatnonzero((flat[:, 2] >= lo[2]) & (flat[:, 2] <= hi[2]))
        for k in (0, 1):
            v = flat[cand, k]
            cand = cand[(v >= lo[k]) & (v <= hi[k])]
    if len(cand) == 0:
        return out.reshape(pts.shape[:-1])
    p = flat[cand].astype(np.float64, copy=False)
    ab = b - a
    t = np.clip(np.einsum('nkj,kj->nk', p[:, None, :] - a, ab)
                / np.maximum(np.einsum('kj,kj->k', ab, ab), 1e-12), 0.0, 1.0)
    d2 = np.sum((p[:, None, :] - (a + t[..., None] * ab)) ** 2, axis=-1)
    out[cand] = (d2 <= r * r).any(axis=1)
    return out.reshape(pts.shape[:-1])


def com_base(model: RobotModel, q: np.ndarray) -> np.ndarray:
    """Whole-robot centre of mass ``(..., 3)`` in base_link [m] for joint angles ``(..., 4, 3)``.

    Body mass at the base origin, hip links at their joint, thigh and shank masses at their
    segment midpoints (as in the generated URDF).
    """
    pts = leg_points(model, q)
    m_hip, m_thigh, m_shank = (float(m) for m in model.link_masses_kg)
    legs = (m_hip * pts[..., 0, :] + m_thigh * 0.5 * (pts[..., 1, :] + pts[..., 2, :])
            + m_shank * 0.5 * (pts[..., 2, :] + pts[..., 3, :])).sum(axis=-2)
    total = model.body_mass_kg + 4.0 * (m_hip + m_thigh + m_shank)
    return legs / total
