"""Gait building blocks: support polygons, COG targets, swing trajectories, footstep sequences.

Kolter et al. (paper 000, sec. IV): from footsteps, plan COG and foot trajectories that keep
static stability, then IK and PD joint control. Shao et al. (paper 002, sec. III): walk (crawl)
and trot gaits executed in a discontinuous manner -- the body moves while all four feet are on
the ground, then a leg (walk) or a diagonal pair (trot) swings -- with the COG kept inside the
support polygon and joint trajectories from cubic-spline interpolation.

Everything here is a pure function of numpy arrays. Positions in the world / odom frame [m],
legs indexed LF=0, RF=1, LH=2, RH=3.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Union

import numpy as np

from terrain_perception.grid import GridMap
from terrain_perception.robot_model import LEG_FRONT, LEG_NAMES, RobotModel

LF, RF, LH, RH = 0, 1, 2, 3
#: Statically stable crawl order (each swing is followed by the diagonally-opposite side's
#: front/hind leg): LH, LF, RH, RF.
CRAWL_ORDER = (LH, LF, RH, RF)
#: Trot pairs, swung together.
TROT_PAIRS = ((LF, RH), (RF, LH))

HeightFn = Union[Callable[[np.ndarray], np.ndarray], GridMap, None]


# -- timing -------------------------------------------------------------------------------
def min_jerk(s: np.ndarray) -> tuple:
    """Minimum-jerk blend ``(b, db/ds)`` for phase ``s`` in [0, 1] (clipped); b(0)=0, b(1)=1."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    b = s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s)
    db = 30.0 * s * s * (1.0 - s) ** 2
    return b, db


# -- support polygon ----------------------------------------------------------------------
def convex_order(poly_xy: np.ndarray) -> np.ndarray:
    """Vertices ``(N, 2)`` sorted counter-clockwise around their centroid."""
    p = np.asarray(poly_xy, dtype=np.float64).reshape(-1, 2)
    c = p.mean(axis=0)
    return p[np.argsort(np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0]))]


def support_margin(point_xy: np.ndarray, support_xy: np.ndarray) -> np.ndarray:
    """Signed distance [m] of points ``(..., 2)`` to the edges of a convex support polygon.

    Positive inside (distance to the nearest edge line), negative outside. With 2 support
    points (a line) the result is minus the distance to the segment.
    """
    pts = np.asarray(point_xy, dtype=np.float64)
    poly = convex_order(support_xy)
    if len(poly) < 3:
        a, b = poly[0], poly[-1]
        ab = b - a
        t = np.clip(((pts - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
        return -np.linalg.norm(pts - (a + t[..., None] * ab), axis=-1)
    e = np.roll(poly, -1, axis=0) - poly
    n = np.stack([-e[:, 1], e[:, 0]], axis=-1) / np.linalg.norm(e, axis=-1, keepdims=True)
    d = np.einsum('...kj,kj->...k', pts[..., None, :] - poly, n)
    return d.min(axis=-1)


def project_into_support(point_xy: np.ndarray, support_xy: np.ndarray,
                         margin_m: float) -> tuple:
    """Nearest point to ``point_xy`` that is at least ``margin_m`` inside the support polygon.

    Returns ``(target_xy, margin_achieved_m)``. If the polygon is too small for the margin
    the deepest point (largest margin) is returned with its smaller margin; with two support
    points (trot) the nearest point on the support segment is returned (margin 0).
    """
    p = np.asarray(point_xy, dtype=np.float64).reshape(2)
    poly = convex_order(support_xy)
    if len(poly) < 3:
        a, b = poly[0], poly[-1]
        ab = b - a
        t = np.clip((p - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0)
        return a + t * ab, 0.0
    inner = support_margin(p, poly)
    if inner >= margin_m:
        return p, float(inner)
    e = np.roll(poly, -1, axis=0) - poly
    n = np.stack([-e[:, 1], e[:, 0]], axis=-1) / np.linalg.norm(e, axis=-1, keepdims=True)
    off = np.einsum('kj,kj->k', poly, n) + margin_m      # half-planes n.x >= off
    # Vertices of the inset polygon: intersections of consecutive shifted edge lines.
    verts = []
    K = len(poly)
    for k in range(K):
        A = np.stack([n[k - 1], n[k]])
        try:
            verts.append(np.linalg.solve(A, np.array([off[k - 1], off[k]])))
        except np.linalg.LinAlgError:
            continue
    verts = np.array(verts)
    inside = np.all(verts @ n.T >= off - 1e-9, axis=1) if len(verts) else np.zeros(0, bool)
    if len(verts) < 3 or not np.all(inside):
        # The margin does not fit: take the point of maximum margin (a small LP over the
        # edge lines; for a triangle it is the incentre).
        deepest = _deepest_point(poly, n)
        return deepest, float(support_margin(deepest, poly))
    inset = convex_order(verts)
    # Nearest point on the inset polygon's boundary.
    a = inset
    b = np.roll(inset, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum('kj,kj->k', p - a, ab) / np.einsum('kj,kj->k', ab, ab), 0.0, 1.0)
    cand = a + t[:, None] * ab
    best = cand[np.argmin(np.linalg.norm(cand - p, axis=1))]
    return best, float(support_margin(best, poly))


def _deepest_point(poly: np.ndarray, n: np.ndarray) -> np.ndarray:
    from scipy.optimize import linprog
    # maximise r s.t. n_k . x - r >= n_k . v_k
    c = np.array([0.0, 0.0, -1.0])
    A = np.hstack([-n, np.ones((len(n), 1))])
    b = -np.einsum('kj,kj->k', poly, n)
    res = linprog(c, A_ub=A, b_ub=b, bounds=[(None, None)] * 3, method='highs')
    return res.x[:2] if res.success else poly.mean(axis=0)


# -- terrain under a swing ----------------------------------------------------------------
def terrain_height(height: HeightFn, xy: np.ndarray) -> np.ndarray:
    """Terrain height [m] at points ``(..., 2)`` from a callable or a GridMap's elevation.

    Unknown cells (NaN) and ``height=None`` give -inf, i.e. no constraint beyond the
    footholds themselves.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if height is None:
        return np.full(xy.shape[:-1], -np.inf)
    if isinstance(height, GridMap):
        from terrain_perception.grid import ELEVATION
        h = height.sample(ELEVATION, xy).astype(np.float64)
    else:
        h = np.asarray(height(xy), dtype=np.float64)
    return np.where(np.isfinite(h), h, -np.inf)


def swing_apex(p0: np.ndarray, p1: np.ndarray, height: HeightFn, clearance_m: float,
               corridor_m: float, min_lift_m: float, samples: int = 41) -> float:
    """Apex height [m] of a swing from contact point ``p0`` to ``p1`` (world).

    The apex clears the highest terrain within ``corridor_m`` of the straight x-y path by
    ``clearance_m`` and is at least ``min_lift_m`` above the higher foothold.
    """
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    s = np.linspace(0.0, 1.0, samples)
    line = p0[:2] + s[:, None] * (p1[:2] - p0[:2])
    d = p1[:2] - p0[:2]
    norm = np.linalg.norm(d)
    side = np.array([-d[1], d[0]]) / norm if norm > 1e-9 else np.array([0.0, 1.0])
    fwd = d / norm if norm > 1e-9 else np.array([1.0, 0.0])
    offsets = [np.zeros(2), corridor_m * side, -corridor_m * side,
               corridor_m * fwd, -corridor_m * fwd]
    pts = np.concatenate([line + o for o in offsets])
    h = terrain_height(height, pts).max()
    return float(max(max(p0[2], p1[2]) + min_lift_m, h + clearance_m))


@dataclass(frozen=True)
class SwingTrajectory:
    """Foot path lift -> traverse at the apex -> lower, each part minimum-jerk, then
    optionally a slow final approach.

    With ``approach_m`` > 0 the minimum-jerk lowering stops that far above ``p1`` and the foot
    covers the rest straight down at ``approach_speed_m_s``: ground higher than believed by
    up to ``approach_m`` is met at that speed instead of at the lowering's (1.875 x the drop
    over its time at the middle: 0.8 m/s for LittleDog's 4 cm in 0.09 s). The approach adds
    :attr:`approach_s` after ``duration_s``; :attr:`total_s` is the whole swing.

    Attributes:
        p0, p1: start and end foot positions (world) [m]; apex_z: traverse height [m];
        duration_s: time of lift, traverse and lowering; lift_fraction: share of that time for
        each vertical part; approach_m: height of the final approach above ``p1`` [m] (capped
        by the apex); approach_speed_m_s: its descent speed; lift_xy: the part of the
        horizontal move [m] made during the lift, on the lift's own curve (the foot rises
        diagonally), the rest crossing at the apex as usual; None = all of it at the apex.
    """

    p0: np.ndarray
    p1: np.ndarray
    apex_z: float
    duration_s: float
    lift_fraction: float = 0.25
    approach_m: float = 0.0
    approach_speed_m_s: float = 0.1
    lift_xy: Optional[np.ndarray] = None

    @staticmethod
    def duration_for_speed(vertical_m: float, horizontal_m: float, max_speed_m_s: float,
                           lift_fraction: float = 0.25) -> float:
        """Shortest ``duration_s`` whose lift and lowering (at most ``vertical_m`` each) and
        traverse (``horizontal_m``) stay under ``max_speed_m_s``: each part is minimum-jerk,
        peak speed 1.875 x distance / time, the vertical parts ``lift_fraction`` of the
        duration each and the traverse ``1 - 1.2 lift_fraction`` (:meth:`position`)."""
        f = float(lift_fraction)
        return 1.875 * max(vertical_m / f, horizontal_m / (1.0 - 1.2 * f)) / max_speed_m_s

    @property
    def approach_height_m(self) -> float:
        """The approach's actual height: ``approach_m`` but not above the apex."""
        return float(min(max(self.approach_m, 0.0),
                         max(float(self.apex_z) - float(np.asarray(self.p1)[2]), 0.0)))

    @property
    def approach_s(self) -> float:
        a = self.approach_height_m
        return a / self.approach_speed_m_s if a > 0.0 else 0.0

    @property
    def total_s(self) -> float:
        return self.duration_s + self.approach_s

    def position(self, t: np.ndarray) -> np.ndarray:
        """Foot position ``(..., 3)`` at times ``t`` [s] since the swing start (clipped to
        ``[0, total_s]``)."""
        t = np.asarray(t, dtype=np.float64)
        s = np.clip(t / self.duration_s, 0.0, 1.0)
        f = self.lift_fraction
        p0, p1 = np.asarray(self.p0, float), np.asarray(self.p1, float)
        a = self.approach_height_m
        up, _ = min_jerk(s / f)
        down, _ = min_jerk((s - (1.0 - f)) / f)
        # the traverse overlaps the vertical parts slightly so the foot leaves the ground
        # before moving forward and lands after stopping
        across, _ = min_jerk((s - 0.6 * f) / (1.0 - 1.2 * f))
        if self.lift_xy is None:
            xy = p0[:2] + across[..., None] * (p1[:2] - p0[:2])
        else:
            lead = np.asarray(self.lift_xy, dtype=np.float64)
            xy = (p0[:2] + up[..., None] * lead
                  + across[..., None] * (p1[:2] - p0[:2] - lead))
        z = np.where(s < 0.5, p0[2] + up * (self.apex_z - p0[2]),
                     self.apex_z + down * (p1[2] + a - self.apex_z))
        if a > 0.0:
            z = z - np.clip(t - self.duration_s, 0.0, self.approach_s) * self.approach_speed_m_s
        return np.concatenate([xy, z[..., None]], axis=-1)


# -- body pose from footholds -------------------------------------------------------------
def body_pose_from_feet(feet_xyz: np.ndarray, standing_height_m: float) -> tuple:
    """Nominal body ``(x, y, z, yaw)`` over four contact points ``(4, 3)`` (world).

    x-y = the feet centroid, z = mean foot height + standing height, yaw = direction from
    the hind-feet midpoint to the front-feet midpoint.
    """
    f = np.asarray(feet_xyz, dtype=np.float64)
    front = f[LEG_FRONT > 0].mean(axis=0)
    hind = f[LEG_FRONT < 0].mean(axis=0)
    yaw = float(np.arctan2(front[1] - hind[1], front[0] - hind[0]))
    c = f.mean(axis=0)
    return np.array([c[0], c[1], c[2] + standing_height_m, yaw])


def pose_to_T(xyzyaw: np.ndarray) -> np.ndarray:
    """4x4 pose from ``(x, y, z, yaw)`` (level) or ``(x, y, z, yaw, pitch, roll)``
    (``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    return poses_to_T(np.asarray(xyzyaw, dtype=float)[None])[0]


def poses_to_T(bodies: np.ndarray) -> np.ndarray:
    """``(n, 4, 4)`` poses of ``(n, 4)`` or ``(n, 6)`` body vectors (see :func:`pose_to_T`)."""
    b = np.asarray(bodies, dtype=float)
    n = len(b)
    cy, sy = np.cos(b[:, 3]), np.sin(b[:, 3])
    T = np.zeros((n, 4, 4))
    T[:, 3, 3] = 1.0
    T[:, :3, 3] = b[:, :3]
    if b.shape[1] < 6:
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = cy, -sy, sy, cy
        T[:, 2, 2] = 1.0
        return T
    cp, sp = np.cos(b[:, 4]), np.sin(b[:, 4])
    cr, sr = np.cos(b[:, 5]), np.sin(b[:, 5])
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = -sp, cp * sr, cp * cr
    return T


def body_tilt_from_feet(feet_xyz: np.ndarray, yaw: float, gain: float,
                        max_rad: float) -> tuple:
    """``(pitch, roll)`` [rad] that tilt the body ``gain`` of the way towards the plane of the
    four contact points ``(4, 3)``: front-hind and left-right height differences over their
    spacing along and across the heading ``yaw``, each capped at ``max_rad``. Positive pitch
    lowers the nose (front feet lower), positive roll raises the left side."""
    if gain <= 0.0:
        return 0.0, 0.0
    f = np.asarray(feet_xyz, dtype=np.float64)
    h, lat = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
    front, hind = f[LEG_FRONT > 0].mean(axis=0), f[LEG_FRONT < 0].mean(axis=0)
    left, right = f[[0, 2]].mean(axis=0), f[[1, 3]].mean(axis=0)
    dx = max(float((front[:2] - hind[:2]) @ h), 1e-3)
    dy = max(float((left[:2] - right[:2]) @ lat), 1e-3)
    pitch = -gain * np.arctan2(front[2] - hind[2], dx)
    roll = gain * np.arctan2(left[2] - right[2], dy)
    return (float(np.clip(pitch, -max_rad, max_rad)), float(np.clip(roll, -max_rad, max_rad)))


# -- footstep sequences -------------------------------------------------------------------
def nominal_feet_world(model: RobotModel, T_world_base: np.ndarray) -> np.ndarray:
    """``(4, 3)`` nominal contact points of a robot standing at ``T_world_base`` (level)."""
    return model.nominal_feet @ T_world_base[:3, :3].T + T_world_base[:3, 3]


def straight_footsteps(model: RobotModel, T_world_base: np.ndarray, distance_m: float,
                       step_m: Optional[float] = None, gait: str = 'walk',
                       height: HeightFn = None) -> tuple:
    """Footsteps walking ``distance_m`` straight ahead from a nominal stance.

    Every leg advances by ``step_m`` (default ``model.body_move_per_period_m``) per period,
    the last period shorter, so the final stance is the nominal one ``distance_m`` ahead.
    Crawl order LH, LF, RH, RF (walk) or diagonal pairs LF+RH, RF+LH (trot). With ``height``
    the footholds' z is set to the terrain height there.

    Returns ``(legs (N,) int, positions (N, 3) [m])``.
    """
    step = float(step_m or model.body_move_per_period_m)
    if step <= 0 or distance_m < 0:
        raise ValueError(f'step must be > 0 and distance >= 0, got {step}, {distance_m}')
    if step > model.max_step_length_m + 1e-9:
        raise ValueError(f'step {step} m exceeds max_step_length_m {model.max_step_length_m}')
    start = nominal_feet_world(model, T_world_base)
    fwd = T_world_base[:3, 0].copy()
    fwd[2] = 0.0
    fwd /= np.linalg.norm(fwd)
    n = int(np.ceil(distance_m / step - 1e-9))
    advances = np.minimum(step * np.arange(1, n + 1), distance_m)
    order = [leg for pair in TROT_PAIRS for leg in pair] if gait == 'trot' else CRAWL_ORDER
    legs, pos = [], []
    for a in advances:
        for leg in order:
            p = start[leg] + a * fwd
            legs.append(leg)
            pos.append(p)
    pos = np.array(pos).reshape(-1, 3)
    if height is not None and len(pos):
        h = terrain_height(height, pos[:, :2])
        pos[:, 2] = np.where(np.isfinite(h), h, pos[:, 2])
    return np.array(legs, dtype=int), pos


def leg_name(leg: int) -> str:
    """'LF', 'RF', 'LH' or 'RH'."""
    return LEG_NAMES[int(leg)]
