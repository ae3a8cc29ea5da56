"""The code that speed-ups replaced, kept verbatim as oracles (test_speedups.py).

Each function here is the previous implementation of one function of the package, copied
unchanged except for imports of the helpers it shares with the live module (those helpers were
not changed). A speed-up must give the same output as its entry here: bitwise where it does the
same arithmetic.
"""

from typing import Dict

import numpy as np
from scipy import ndimage

from terrain_perception import gait as gaitlib
from terrain_perception import kinematics
from terrain_perception.body_path import belly_samples
from terrain_perception.features import (CostConfig, _check_heights, _sep, _window_kernels,
                                         window_cells)
from terrain_perception.gait import _deepest_point, convex_order, support_margin
from terrain_perception.ground_plane import (GroundPlaneConfig, _lsq_plane, _three_distinct,
                                             plane_from_normal)
from terrain_perception.robot_model import LEG_NAMES
from terrain_perception.transforms import invert, transform_points
from terrain_ros.conversions import pose_to_matrix


def fit_ground_plane(points, config=GroundPlaneConfig(), rng=None):
    """terrain_perception.ground_plane.fit_ground_plane before the sample was drawn by index
    (commit cae4135)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 3:
        raise ValueError(f'ground plane needs at least 3 valid points, got {len(pts)}')
    rng = np.random.default_rng(config.seed) if rng is None else rng
    if len(pts) > config.sample_points:
        pts = pts[rng.choice(len(pts), config.sample_points, replace=False)]
    n_pts = len(pts)

    # m hypotheses at once: three distinct indices per row.
    tri = _three_distinct(rng, config.iterations, n_pts)
    p0, p1, p2 = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    normals = np.cross(p1 - p0, p2 - p0)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    if not ok.any():
        raise ValueError('ground plane: every sampled triple is degenerate (collinear points)')
    normals = normals[ok] / norms[ok, None]
    ds = -np.einsum('ij,ij->i', normals, p0[ok])
    # Orient every hypothesis so that the camera (the origin) is on its positive side.
    flip = np.where(ds < 0, -1.0, 1.0)
    normals *= flip[:, None]
    ds *= flip
    signed = pts @ normals.T + ds                           # (N, m')
    thr = config.inlier_threshold_m
    score = np.count_nonzero(np.abs(signed) < thr, axis=0).astype(np.float64)
    if config.below_penalty > 0:
        score -= config.below_penalty * np.count_nonzero(signed < -thr, axis=0)
    best = int(np.argmax(score))
    inl = pts[np.abs(signed[:, best]) < thr]

    # Least-squares refit on the best inlier set, then one re-selection of inliers with it.
    n, d = _lsq_plane(inl)
    inside = np.abs(pts @ n + d) < config.inlier_threshold_m
    if np.count_nonzero(inside) >= 3:
        n, d = _lsq_plane(pts[inside])
        inside = np.abs(pts @ n + d) < config.inlier_threshold_m
    count = int(np.count_nonzero(inside))
    ratio = count / n_pts
    if ratio < config.min_inlier_ratio:
        raise ValueError(f'ground plane: best plane holds only {100 * ratio:.1f}% of the '
                         f'points (< {100 * config.min_inlier_ratio:.1f}%)')
    return plane_from_normal(n, d, count, ratio)


def contact_support(grid, feet, radius_m):
    """terrain_perception.fill._contact_support before it worked on the box around the feet
    (commit cae4135)."""
    A = np.c_[feet[:, :2], np.ones(len(feet))]
    coef, *_ = np.linalg.lstsq(A, feet[:, 2], rcond=None)
    nx, ny = grid.shape
    r = grid.resolution_m
    x = grid.origin_xy[0] + (np.arange(nx) + 0.5) * r
    y = grid.origin_xy[1] + (np.arange(ny) + 0.5) * r
    X, Y = np.meshgrid(x, y, indexing='ij')
    d2 = np.min((X[..., None] - feet[:, 0]) ** 2 + (Y[..., None] - feet[:, 1]) ** 2, axis=-1)
    return d2 <= radius_m ** 2, coef[0] * X + coef[1] * Y + coef[2]


def dilate(mask, m):
    """What TerrainFiller.update did for the refill margin before fill._dilate (cae4135)."""
    return ndimage.binary_dilation(mask, np.ones((2 * m + 1, 2 * m + 1), bool))


def pose_matrices(poses):
    """TerrainFillNode's conversion of /map/capture_poses before its cache (cae4135)."""
    return np.array([pose_to_matrix(p) for p in poses]).reshape(-1, 4, 4)


# --- walking controller (the planner's dry run, check_footsteps) ---------------------------
# Methods of terrain_perception.controller.WalkingController at commit 633dc8f, as functions
# of the controller (test_speedups.py sets them on the class).


def ctl_shift_body(self, goal: np.ndarray, support: np.ndarray, margin: float, legs,
                   targets: np.ndarray, names: str, fore_aft: bool = False):
    """terrain_perception.controller.WalkingController._shift_body before the standing
    COM was cached per model (commit 633dc8f)."""
    m = self.model
    body = goal.copy()
    # Feet along the coming swing: the COG must keep the margin during all of it.
    taus = np.linspace(0.0, 1.0, 13)
    poses = np.repeat(self._feet[None], len(taus), axis=0)
    for k, leg in enumerate(legs):
        sw = self._swing_trajectory(self._feet[leg], targets[k],
                                    self._apex(self._feet[leg], targets[k]), 1.0, leg,
                                    fore_aft=fore_aft)
        poses[:, leg] = sw.position(taus * sw.total_s)
    nominal_off = transform_points(gaitlib.pose_to_T(goal), kinematics.com_base(
        m, kinematics.standing_joint_angles(m))[None])[0, :2] - goal[:2]
    mean, extra = nominal_off, 0.0
    for _ in range(3):
        body[2] = self._body_z(goal[2], body, poses, legs)
        offs = self._com_offsets(body, poses)
        if offs is not None:
            mean = 0.5 * (offs.min(axis=0) + offs.max(axis=0))
            extra = float(np.linalg.norm(offs - mean, axis=1).max())
        cog, got = gaitlib.project_into_support(goal[:2] + mean, support, margin + extra)
        body[:2] = cog - mean
    body[2] = self._body_z(goal[2], body, poses, legs)
    full_shift = True
    if not self._reachable(body, poses):
        full_shift = False
        # The full COG shift puts a foot out of reach (e.g. past the abduction limit):
        # shift less, towards the nominal body pose, as long as a margin remains.
        for alpha in (0.2, 0.4, 0.6, 0.8, 1.0):
            cand = body.copy()
            cand[:2] = body[:2] + alpha * (goal[:2] - body[:2])
            cand[2] = self._body_z(goal[2], cand, poses, legs)
            if self._reachable(cand, poses):
                body = cand
                break
        else:
            self._step_error(f'no body pose keeps every foot in reach while stepping '
                             f'{names}: ' + '; '.join(self.last_ik_reasons[:2]))
            return None
    return body, poses, full_shift


def ctl_shanks_clear(self, T: np.ndarray, q: np.ndarray) -> bool:
    """WalkingController._shanks_clear before the dry run's memo of the current stance's
    shank depth (633dc8f)."""
    tol = self.config.shank_max_penetration_m
    if tol < 0.0 or self.height is None or self._q_last is None:
        return True
    depth = self._shank_depth(T, q)
    now = self._shank_depth(gaitlib.pose_to_T(self._body),
                            np.asarray(self._q_last, dtype=float).reshape(4, 3))
    bad = depth > np.maximum(tol, now + 0.002)
    if not bad.any():
        return True
    i, k = np.argwhere(bad)[0]
    self.last_ik_reasons = [f'pose {i} leg {LEG_NAMES[k]}: shank {1000 * depth[i, k]:.0f} mm '
                            f'into the terrain']
    return False


def ctl_body_z(self, z_nominal: float, body: np.ndarray, poses: np.ndarray, legs) -> float:
    """WalkingController._body_z before the dry run's memo and the first height's IK on its
    own (633dc8f)."""
    m = self.model
    z_min = float(poses[:, legs, 2].max()) + m.foot_radius_m + \
        self.config.min_swing_hip_height * m.standing_height_m if len(legs) else -np.inf
    z = min(max(z_nominal, z_min, self._belly_z(body)), self._max_body_z(body, poses))
    cands = z + np.array([0.0] + [s * k * 0.004 for k in range(1, 11) for s in (1, -1)])
    R = gaitlib.pose_to_T(body)[:3, :3]
    centres = np.array(poses, dtype=float)
    centres[..., 2] += m.foot_radius_m
    base = np.array([body[0], body[1], 0.0])
    local = (centres[None] - base - cands[:, None, None, None] * np.array([0, 0, 1.0])) @ R
    ok = kinematics.solve_ik(m, local, explain=False).ok.all(axis=(1, 2))
    return float(cands[int(np.argmax(ok))]) if ok.any() else z


def ctl_belly_z(self, body: np.ndarray) -> float:
    """WalkingController._belly_z before the cached belly samples and the dry run's memo
    (633dc8f)."""
    c = self.config
    if c.belly_clearance_m < 0.0 or self.height is None:
        return -np.inf
    thick = float(self.model.body_size_m[2])
    U, V = belly_samples(self.model)[0][:, :2].T
    cy, sy = np.cos(body[3]), np.sin(body[3])
    pts = np.stack([body[0] + cy * U - sy * V, body[1] + sy * U + cy * V,
                    np.zeros_like(U)], axis=-1)
    in_map = transform_points(self.T_map_odom, pts)
    ground = gaitlib.terrain_height(self.height, in_map[:, :2]) - in_map[:, 2]  # in odom
    return float(ground.max()) + 0.5 * thick + c.belly_clearance_m


def ctl_apex(self, p0: np.ndarray, p1: np.ndarray) -> float:
    """WalkingController._apex before the dry run's memo (633dc8f)."""
    T = self.T_map_odom
    a, b = transform_points(T, p0[None])[0], transform_points(T, p1[None])[0]
    apex_map = gaitlib.swing_apex(a, b, self.height, self.clearance_m,
                                  corridor_m=1.5 * self.model.foot_radius_m,
                                  min_lift_m=self.model.swing_height_m)
    ends = np.array([[a[0], a[1], apex_map], [b[0], b[1], apex_map]])
    return float(transform_points(invert(T), ends)[:, 2].max())


def project_into_support(point_xy: np.ndarray, support_xy: np.ndarray,
                         margin_m: float) -> tuple:
    """terrain_perception.gait.project_into_support before it computed the point's
    margin once (633dc8f)."""
    p = np.asarray(point_xy, dtype=np.float64).reshape(2)
    poly = convex_order(support_xy)
    if len(poly) < 3:
        a, b = poly[0], poly[-1]
        ab = b - a
        t = np.clip((p - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0)
        return a + t * ab, 0.0
    if support_margin(p, poly) >= margin_m:
        return p, float(support_margin(p, poly))
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


# --- terrain features ------------------------------------------------------------------------
def kolter_features(heights: np.ndarray, resolution_m: float,
                    config: CostConfig = CostConfig()) -> Dict[str, np.ndarray]:
    """terrain_perception.features.kolter_features before the plane was fitted only under the
    cells of known height (commit 633dc8f)."""
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

    # Weighted least-squares plane a + b*u + c*v over the known cells of each window.
    mat = np.stack([np.stack([s0, su, sv], -1), np.stack([su, suu, suv], -1),
                    np.stack([sv, suv, svv], -1)], -2)
    rhs = np.stack([sh, shu, shv], -1)
    det = np.linalg.det(mat)
    solvable = (s0 >= 3) & (np.abs(det) > 1e-9 * np.maximum(s0, 1.0) ** 3)
    grad = np.zeros(h.shape + (2,))
    if solvable.any():
        sol = np.linalg.solve(mat[solvable], rhs[solvable][..., None])[..., 0]
        grad[solvable] = sol[:, 1:]
    # A window with too few known cells to fix a plane has no measurable slope: 0, not NaN, so
    # the other features still rank the cell.
    slope = np.hypot(grad[..., 0], grad[..., 1]) / resolution_m

    n = np.maximum(s0, 1.0)
    mean = sh / n
    roughness = np.sqrt(np.maximum(shh / n - mean * mean, 0.0))

    hmax = ndimage.maximum_filter(np.where(known, h, -np.inf), size=kl, mode='constant',
                                  cval=-np.inf)
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
