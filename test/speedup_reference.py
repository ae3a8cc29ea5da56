"""The code that speed-ups replaced, kept verbatim as oracles (test_speedups.py).

Each function here is the previous implementation of one function of the package, copied
unchanged except for imports of the helpers it shares with the live module (those helpers were
not changed). A speed-up must give the same output as its entry here: bitwise where it does the
same arithmetic.
"""

import numpy as np
from scipy import ndimage

from terrain_perception.ground_plane import (GroundPlaneConfig, _lsq_plane, _three_distinct,
                                             plane_from_normal)
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
