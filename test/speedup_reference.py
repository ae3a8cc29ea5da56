"""The code that speed-ups replaced, kept verbatim as oracles (test_speedups.py).

Each function here is the previous implementation of one function of the package, copied
unchanged except for imports of the helpers it shares with the live module (those helpers were
not changed). A speed-up must give the same output as its entry here: bitwise where it does the
same arithmetic.
"""

from typing import Dict, Optional

import numpy as np
from scipy import ndimage

from terrain_perception import gait as gaitlib
from terrain_perception import kinematics
from terrain_perception.body_path import belly_samples
from terrain_perception.footsteps import (_ACROSS, _EMPTY_AREA, _SAME_SIDE, LF, LH, RF, RH,
                                          _State, body_pose, flatness_cost, reachable,
                                          stance_in_reach)
from terrain_perception.features import (CostConfig, _check_heights, _sep, _window_kernels,
                                         window_cells)
from terrain_perception.gait import _deepest_point, convex_order, support_margin
from terrain_perception.grid import ELEVATION
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


# --- footstep planner (footsteps.py before session 49) --------------------------------------
# unsafe_cells with scipy.ndimage (not OpenCV); the FootstepPlanner methods below take the
# planner as ``self`` (set on the class by the test); _candidates reads self.patches[:2] (the
# planner keeps (vertices, radii, largest radius) now), otherwise verbatim.

def unsafe_cells(heights: np.ndarray, resolution_m: float, foot_radius_m: float,
                 max_slope_deg: float = 30.0, rms_fraction: float = 0.5,
                 window_m: float = 0.0) -> np.ndarray:
    """Cells where a ball foot of radius ``rho = foot_radius_m`` [m] is unsafe: within the
    square of half-side ``window_m`` (at least 2 cells; 0: ~2 rho) around the cell, the
    heights' RMS deviation from their least-squares plane exceeds ``rms_fraction * rho`` (an
    edge, a crack or a knob under the foot), or the plane is steeper than ``max_slope_deg`` (the
    friction limit with margin). Unknown cells and windows
    with unknown heights are not flagged (the caller masks unknown cells separately)."""
    from scipy import ndimage
    h = np.asarray(heights, dtype=np.float64)
    if window_m > 0:
        # at least 2 cells each side: a plane and its RMS fitted to 3 x 3 cells miss a roof's
        # ridge (on the closed loop's 1 cm map this keeps the 5 x 5 window of 2 foot radii)
        r = max(2, int(round(window_m / resolution_m)))
    else:
        r = max(1, int(round(2 * foot_radius_m / resolution_m)))
    u = np.arange(-r, r + 1, dtype=np.float64)
    n2 = float(len(u)) ** 2
    box = np.ones_like(u)

    def sep(a, k0, k1):
        a = ndimage.correlate1d(a, k0, axis=0, mode='nearest')
        return ndimage.correlate1d(a, k1, axis=1, mode='nearest')

    m = sep(h, box, box) / n2
    var = sep(h * h, box, box) / n2 - m * m
    su2 = float(np.mean(u * u))
    cu, cv = sep(h, u, box) / n2, sep(h, box, u) / n2
    rms = np.sqrt(np.maximum(var - (cu * cu + cv * cv) / su2, 0.0))
    slope = np.hypot(cu, cv) / su2 / resolution_m
    with np.errstate(invalid='ignore'):
        return (rms > rms_fraction * foot_radius_m) | (slope > np.tan(np.radians(max_slope_deg)))


def fs_area(self, foot_u: float, nom_u: float, nom_v: float, wL: float, A: float,
          lateral_m: Optional[float] = None, ground_z: Optional[float] = None):
    """Search area of one leg: along-track [foot + min_step, nominal + wL + 2A] (capped by the
    max step length), across-track nominal +- ``lateral_m`` (default lateral_search).
    ``ground_z`` (the stance's height) lets ``stride_centre: adaptive`` test the area's
    flatness; without it 'adaptive' centres as 'capped'. Returns (u, v, centre_u)."""
    res = self.grid.resolution_m
    lo = foot_u + self.cfg.min_step_m
    rule_hi = nom_u + wL + 2.0 * A
    hi = min(rule_hi, foot_u + self.robot.max_step_length_m)
    hi = max(hi, lo)
    us = np.arange(lo, hi + 0.5 * res, res) if hi > lo else np.array([lo])
    w = self.cfg.lateral_search_m if lateral_m is None else lateral_m
    vs = nom_v + np.arange(-w, w + 0.5 * res, res) if w > 0 else np.array([nom_v])
    U, V = np.meshgrid(us, vs, indexing='ij')
    u, v = U.ravel(), V.ravel()
    centre = 0.5 * (lo + hi)
    mode = self.cfg.stride_centre
    if mode == 'rule' or (mode == 'adaptive' and ground_z is not None
                          and self._area_flat(u, v, ground_z)):
        centre = min(0.5 * (lo + max(rule_hi, lo)), hi)
    return u, v, centre


def fs_area_flat(self, u: np.ndarray, v: np.ndarray, ground_z: float) -> bool:
    """Shao's flatness test (paper 002 Fig. 4) on the cells at along/across-track ``u, v``:
    all observed and ``|h - ground_z| + Dev(h) < trot_threshold_m``."""
    ij, inside = self._cells(self._to_map(u, v))
    h = self.grid[ELEVATION][ij[:, 0], ij[:, 1]]
    if not np.all(inside & np.isfinite(h)):
        return False
    fc = flatness_cost(h, ground_z, self._dev_at(ij))
    return bool(np.all(fc < self.cfg.trot_threshold_m))

#: half-width [cells] of the window of Shao's Dev computed at a time (the search areas of
#: one plan lie within a few tens of cells of each other)
_DEV_WINDOW = 40


def fs_area_cells(self, state: _State, leg: int, fu0: np.ndarray, wL0: float, A: float,
                Tb: np.ndarray, lateral_m: float):
    """The cells of ``leg``'s search area (half-width ``lateral_m``) that are allowed, keep
    the stance within the spread limits and are in reach from the body pose ``Tb``: ``(points
    (k, 3), u, v, cells (k, 2), area centre u)``, or ``(None, why not)``."""
    cfg, g = self.cfg, self.grid
    u, v, centre = self._area(fu0[leg], self.nom_u[leg], self.nom_v[leg], wL0, A,
                              lateral_m, float(np.mean(state.feet[:, 2])))
    xy = self._to_map(u, v)
    ij, inside = self._cells(xy)
    ok = inside & self.allowed[ij[:, 0], ij[:, 1]]
    # A step back onto the foot's own cell is no step.
    ok &= np.hypot(*(xy - state.feet[leg, :2]).T) >= 0.75 * g.resolution_m
    if not np.any(ok):
        return None, _EMPTY_AREA
    fu, fv = self._uv(state.feet)        # the stance along / across the walking line
    if cfg.max_leg_spread_m > 0:
        # No foot further ahead of its nominal place than the rearmost other foot by more
        # than the spread: a foot left behind (an obstacle in its area) holds the others
        # back instead of ending up out of reach once the COG has moved on.
        lag = np.delete(fu - self.nom_u, leg)
        ok &= u - self.nom_u[leg] <= lag.min() + cfg.max_leg_spread_m
        if not np.any(ok):
            return None, (f'its search area {cfg.max_leg_spread_m} m or more ahead of the '
                          'rearmost other foot')
    # The stance's length along the walking line, front foot to the hind foot on its side,
    # as a share of the nominal spacing: at least min_stance_length (a hind foot closing up
    # on a blocked front foot leaves a support polygon too short), at most
    # max_stance_length (a hind foot left far behind cannot swing within reach).
    mate = _SAME_SIDE[leg]
    spacing = abs(self.nom_u[mate] - self.nom_u[leg])
    hind = leg in (LH, RH)
    if cfg.min_stance_length > 0:
        gap = cfg.min_stance_length * spacing
        ok &= (u <= fu[mate] - gap) if hind else (u >= fu[mate] + gap)
        if not np.any(ok):
            return None, (f'no cell of its search area keeps the stance {gap:.3f} m long '
                          f'(the {LEG_NAMES[mate]} foot)')
    if cfg.max_stance_length > 0:
        span = cfg.max_stance_length * spacing
        ok &= (u >= fu[mate] - span) if hind else (u <= fu[mate] + span)
        if not np.any(ok):
            return None, (f'no cell of its search area keeps the stance within {span:.3f} m '
                          f'(the {LEG_NAMES[mate]} foot)')
    # The stance's width across the walking line, this foot to the other foot of its pair,
    # as a share of the nominal width: at least min_stance_width (a left foot stays left of
    # its pair's right foot by it; feet together under the body roll the robot over), at
    # most max_stance_width (spread wider, no body pose keeps every foot in reach).
    mate = _ACROSS[leg]
    width = abs(self.nom_v[mate] - self.nom_v[leg])
    if cfg.min_stance_width > 0:
        gap = cfg.min_stance_width * width
        ok &= (v >= fv[mate] + gap) if self.nom_v[leg] > self.nom_v[mate] else \
            (v <= fv[mate] - gap)
        if not np.any(ok):
            return None, (f'no cell of its search area keeps the stance {gap:.3f} m wide '
                          f'(the {LEG_NAMES[mate]} foot)')
    if cfg.max_stance_width > 0:
        span = cfg.max_stance_width * width
        ok &= np.abs(v - fv[mate]) <= span
        if not np.any(ok):
            return None, (f'no cell of its search area keeps the stance within {span:.3f} m '
                          f'wide (the {LEG_NAMES[mate]} foot)')
    xy, u, v, ij = xy[ok], u[ok], v[ok], ij[ok]
    z = g[ELEVATION][ij[:, 0], ij[:, 1]].astype(np.float64)
    pts = np.c_[xy, z]
    reach = reachable(self.robot, Tb, pts, np.full(len(pts), leg), cfg.reach_fraction)
    if not np.any(reach):
        return None, 'no cell of its search area is within reach'
    pts, u, v, ij = pts[reach], u[reach], v[reach], ij[reach]
    return pts, u, v, ij, centre


def fs_candidates(self, state: _State, leg: int, feet0: np.ndarray, wL0: float, A: float,
                Tb: np.ndarray):
    """Scored candidate footholds of ``leg`` (in its period's search area)."""
    cfg = self.cfg
    fu0, _ = self._uv(feet0)
    found = self._area_cells(state, leg, fu0, wL0, A, Tb, cfg.lateral_search_m)
    wide = cfg.blocked_lateral_search_m
    if wide > cfg.lateral_search_m and (
            found[0] is None or np.max(found[1]) < fu0[leg] + 0.5 * A):
        # Blocked: nothing half a stride ahead in the leg's lane (typically a rock filling
        # it). Inching up to the obstacle only lets the other legs close up on this one, so
        # search around it; the nominal-distance cost still prefers the lane.
        more = self._area_cells(state, leg, fu0, wL0, A, Tb, wide)
        if more[0] is None and more[1] == _EMPTY_AREA and leg in (LH, RH) and \
                cfg.empty_lane_lateral_search_m > wide:
            # A hind foot with not one foothold in the wider search either (unseen ground,
            # the start's blind area): wider still, to the cells beside the lane that the
            # front feet stood on. Not a front foot: ahead of it nothing was stood on.
            more = self._area_cells(state, leg, fu0, wL0, A, Tb,
                                    cfg.empty_lane_lateral_search_m)
        if more[0] is not None and (found[0] is None or np.max(more[1]) > np.max(found[1])):
            found = more
    if found[0] is None:
        return None, found[1]
    pts, u, v, ij, centre = found
    # The stance's heading after the step (hind feet's midpoint to the front feet's, as
    # the controller sets the body's yaw), against the plan's: a front foot stepping 6 cm
    # round a rock turns it 8 deg, and such steps added up to 60 deg on rocks-12cm (seed 0)
    # while each plan turned back by max_turn_rad only.
    err = self._heading_error(state.feet, leg, u, v)
    if cfg.max_heading_error_rad > 0:
        err0 = abs(float(self._heading_error(state.feet, leg, *self._uv(
            state.feet[leg:leg + 1]))[0]))
        keep = (np.abs(err) <= cfg.max_heading_error_rad) | (np.abs(err) <= err0 + 1e-9)
        if not np.any(keep):
            return None, (f'no foothold keeps the stance within '
                          f'{np.degrees(cfg.max_heading_error_rad):.0f} deg of the heading')
        pts, u, v, ij, err = pts[keep], u[keep], v[keep], ij[keep], err[keep]
    cost = self.cost[ij[:, 0], ij[:, 1]]
    omega = (cfg.distance_weight_gain * ((u - centre) ** 2 + (v - self.nom_v[leg]) ** 2)
             + A) / max(A, 1e-9)
    dz = np.abs(pts[:, 2] - float(np.mean(state.feet[:, 2])))
    # Distance from the stride-rule foothold (the area centre, paper 002 Fig. 4).
    d2 = (u - centre) ** 2 + (v - self.nom_v[leg]) ** 2
    short = np.maximum(centre - u, 0.0)
    J = omega * (np.maximum(cost, 0.0) + cfg.cost_offset + cfg.step_height_weight_per_m * dz
                 + cfg.nominal_weight_per_m2 * d2 + cfg.shortfall_weight_per_m2 * short ** 2
                 + cfg.heading_weight_per_rad2 * err ** 2)
    pidx = np.full(len(pts), -1)
    if self.patches is not None and cfg.patch_bonus > 0:
        pv, pr = self.patches[:2]
        d = np.linalg.norm(pts[:, None, :2] - pv[None, :, :2], axis=2) - pr[None]
        near = np.argmin(d, axis=1)
        hit = d[np.arange(len(pts)), near] <= 0
        pidx = np.where(hit, near, -1)
        J = np.where(hit, J * (1.0 - cfg.patch_bonus), J)
    if cfg.selection == 'nominal':
        J = omega
    elif cfg.selection == 'random':
        J = self._rng.random(len(J))
    order = np.argsort(J, kind='stable')[:cfg.candidates_per_step]
    return (pts[order], cost[order], J[order], pidx[order]), ''


def fs_heading_error(self, feet: np.ndarray, leg: int, u: np.ndarray,
                   v: np.ndarray) -> np.ndarray:
    """Heading of the stance ``feet`` with ``leg`` moved to each ``(u, v)`` (plan frame):
    the direction from the hind feet's midpoint to the front feet's, relative to the
    plan's heading [rad]."""
    fu, fv = self._uv(feet)
    FU = np.repeat(fu[None], len(u), axis=0)
    FV = np.repeat(fv[None], len(u), axis=0)
    FU[:, leg], FV[:, leg] = u, v
    du = FU[:, [LF, RF]].mean(axis=1) - FU[:, [LH, RH]].mean(axis=1)
    dv = FV[:, [LF, RF]].mean(axis=1) - FV[:, [LH, RH]].mean(axis=1)
    return np.arctan2(dv, du)


def fs_body_in_reach(self, body_xy, feet, yaw) -> Optional[np.ndarray]:
    """Body pose over ``feet`` at ``body_xy`` with every foot in reach: standing height
    first, then crouching (posture adjustment) down to ``min_crouch`` of it. With
    ``belly_clearance_m`` the body box's underside stays that far above the map: the
    body crouches no lower than that, and rises above the standing height when a rock
    under it needs it; None (``_belly_blocked`` set) when the legs cannot reach then."""
    h = self.robot.standing_height_m
    levels = np.linspace(1.0, self.cfg.min_crouch, 4)
    T = body_pose(body_xy, feet, yaw, self.robot)
    self._belly_blocked = False
    need = self._belly_need(T)
    if need > 0.0:
        levels = np.array([1.0 + need / h])
    elif np.isfinite(need):
        levels = levels[(1.0 - levels) * h <= -need]
    p = (feet + [0.0, 0.0, self.robot.foot_radius_m] - T[:3, 3]) @ T[:3, :3]
    # Lowering the base by dh along its own z raises every foot by dh in base_link.
    drop = (1.0 - levels) * h
    P = p[None] + drop[:, None, None] * np.array([0.0, 0.0, 1.0])
    # Distance check for all heights at once; IK level by level, usually one call.
    near = np.all(np.linalg.norm(P - np.array(self.robot.leg_plane_offsets), axis=-1)
                  <= self.cfg.reach_fraction * self.robot.leg_length_m, axis=1)
    k = next((int(i) for i in np.nonzero(near)[0]
              if stance_in_reach(self.robot, P[i:i + 1], self.cfg.reach_fraction).all()),
             None)
    if k is None:
        self._belly_blocked = need > 0.0 or len(levels) < 4
        return None
    self._last_crouch = float(levels[k])
    T = T.copy()
    T[:3, 3] -= drop[k] * T[:3, 2]
    return T


def fake_information(d: np.ndarray, w: np.ndarray, L: float) -> np.ndarray:
    """terrain_perception.mapping.fake_information before its closed form (session 52)."""
    F = np.zeros((6, 6))
    for a in (0, 1):
        e = np.zeros(3)
        e[a] = 1.0
        j = np.hstack([np.cross(d, e) / L, np.broadcast_to(e, d.shape)])
        F += (j * w[:, None]).T @ j
    return F


# terrain_perception._fill_kernels.choose_block before its loops were turned (sample by
# sample, each summing over the window's known cells; session 53), compiled here (no cache).
import math  # noqa: E402

from numba import njit, types  # noqa: E402

from terrain_perception._fill_kernels import _argmin_step  # noqa: E402

_JIT = dict(cache=False, nogil=True, error_model='numpy')
_in_f8_1d = types.Array(types.float64, 1, 'C', readonly=True)
_in_b1_1d = types.Array(types.boolean, 1, 'C', readonly=True)
_in_f8_2d = types.Array(types.float64, 2, 'C', readonly=True)
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
        best = 0
        best_v = 0.0
        nan_seen = False
        found = False
        for t in range(n):
            base = g[i, t] * q
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            for k in range(nk):
                c = flat[base + kj[k]]
                d = c - ka[k]
                wd = kw[k] * d
                s0 += c
                s1 += wd
                s2 += wd * d
            b = (sum_a - s0) / m
            b_all[t] = b
            s = s2 + 2.0 * b * s1 + b * b * sum_w
            ok = True
            if bounded:
                if nan_bound:
                    ok = False
                else:
                    mx = -math.inf
                    for k in range(nb):
                        v = flat[base + bj[k]] - ub[k]
                        if v > mx:
                            mx = v
                    ok = mx + b <= 0.0
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
