"""RANSAC ground plane of one stereo frame -> camera pitch ("visual angle") and height.

Paper 002 (Shao, Yang, Wang), section II-C: N points of the cloud are the sample set; m times,
three of them are drawn at random, the plane through them is computed and the sample points
closer than a threshold are counted as inliers; the largest inlier set is refitted by least
squares. The refit is the orthogonal (total) least-squares plane, i.e. the smallest singular
vector of the centred inliers, the least-squares plane that does not favour an axis.

Ours (``below_penalty`` > 0; 0 gives the paper's plain RANSAC): a hypothesis loses score for
every point clearly below it, since nothing is seen through the ground; this keeps RANSAC off
the tops of rock fields that hide most of the floor. The defaults (N 4000, m 400, 5 mm,
penalty 2) were chosen on simulated views (seeds 7-8, not the benchmark's); with real stereo
noise a larger threshold may be needed.

Frame: the left camera's optical frame (z forward, x right, y down). The plane is
``n . p + d = 0`` with the unit normal ``n`` pointing from the ground towards the camera, so
``d > 0`` is the camera's height above the plane. The pitch is the angle of the optical axis
below the plane (positive looking down): ``pitch = asin(-n_z)``.

All m hypotheses are scored at once on the (m, N) distance matrix; no Python loop over points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from terrain_perception.config import param


@dataclass(frozen=True)
class GroundPlaneConfig:
    """Parameters of the RANSAC ground-plane fit."""

    sample_points: int = param(4000, 'N: points drawn from the cloud as the sample set', 3,
                               1000000)
    iterations: int = param(400, 'm: random three-point hypotheses', 1, 100000)
    inlier_threshold_m: float = param(0.005, 'point-to-plane distance of an inlier [m]',
                                      1e-5, 10.0)
    min_inlier_ratio: float = param(0.1, 'a plane with a smaller share of inliers is refused '
                                    '[0..1]', 0.0, 1.0)
    below_penalty: float = param(
        2.0, 'score = inliers - below_penalty x points farther than the threshold below the '
        'plane (on the far side from the camera); 0 = plain RANSAC', 0.0, 100.0)
    seed: int = param(0, 'seed of the random generator (the fit is repeatable)', 0, 2**31 - 1)


@dataclass(frozen=True)
class GroundPlane:
    """A ground-plane estimate in the camera optical frame.

    Attributes:
        normal: ``(3,)`` unit normal from the ground towards the camera [-].
        d: plane offset [m] (``n . p + d = 0``); equals ``height_m``.
        pitch_rad: optical axis angle below the plane [rad].
        height_m: distance of the optical centre from the plane [m].
        inlier_ratio: share of sample points within the threshold of the refitted plane.
        inliers: number of those sample points.
    """

    normal: np.ndarray
    d: float
    pitch_rad: float
    height_m: float
    inlier_ratio: float
    inliers: int

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance [m] of points ``(..., 3)`` from the plane (positive camera side)."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.d


def plane_from_normal(normal: np.ndarray, d: float, inliers: int = 0,
                      inlier_ratio: float = 0.0) -> GroundPlane:
    """A :class:`GroundPlane` from ``n . p + d = 0`` in the camera frame, oriented and scaled
    so that the normal is a unit vector pointing towards the camera."""
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(n))
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f'plane normal must be non-zero, got {n}')
    n, d = n / norm, float(d) / norm
    if d < 0:
        n, d = -n, -d
    pitch = float(np.arcsin(np.clip(-n[2], -1.0, 1.0)))
    return GroundPlane(n, d, pitch, d, float(inlier_ratio), int(inliers))


def fit_ground_plane(points: np.ndarray, config: GroundPlaneConfig = GroundPlaneConfig(),
                     rng: Optional[np.random.Generator] = None) -> GroundPlane:
    """RANSAC + least-squares ground plane of a cloud in the camera frame.

    Args:
        points: ``(H, W, 3)`` or ``(N, 3)`` [m]; NaN points are ignored.
        config: sample size N, iterations m, inlier threshold.
        rng: random generator; ``np.random.default_rng(config.seed)`` if omitted.

    Raises:
        ValueError: fewer than three valid points, every hypothesis degenerate, or the best
            plane holds fewer than ``min_inlier_ratio`` of the sample.
    """
    pts = np.asarray(points)
    if pts.dtype not in (np.float32, np.float64):
        pts = pts.astype(np.float64)
    pts = pts.reshape(-1, 3)
    # The sample is drawn by index among the valid points and only its rows are widened to
    # float64 (exact from float32): a whole 640x480 cloud was copied twice for 4000 rows.
    # Finiteness is the same in either precision; tested per coordinate (np.all over an axis
    # of length 3 is slow).
    valid = np.isfinite(pts[:, 0]) & np.isfinite(pts[:, 1]) & np.isfinite(pts[:, 2])
    idx = np.flatnonzero(valid)
    if len(idx) < 3:
        raise ValueError(f'ground plane needs at least 3 valid points, got {len(idx)}')
    rng = np.random.default_rng(config.seed) if rng is None else rng
    if len(idx) > config.sample_points:
        idx = idx[rng.choice(len(idx), config.sample_points, replace=False)]
    pts = pts[idx].astype(np.float64, copy=False)
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
    signed = pts @ normals.T                                # (N, m')
    signed += ds
    thr = config.inlier_threshold_m
    # |s| < thr as two comparisons (the same test, without an (N, m') abs copy); counts
    # summed down the columns as int64 (count_nonzero over axis 0 is ~2x slower)
    near = signed < thr
    near &= signed > -thr
    score = near.sum(axis=0, dtype=np.int64).astype(np.float64)
    if config.below_penalty > 0:
        score -= config.below_penalty * (signed < -thr).sum(axis=0, dtype=np.int64)
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


def _three_distinct(rng: np.random.Generator, m: int, n: int) -> np.ndarray:
    """``(m, 3)`` indices in [0, n) with three distinct entries per row."""
    a = rng.integers(0, n, m)
    b = (a + rng.integers(1, n, m)) % n
    c = rng.integers(0, n - 2, m)
    # Map c into [0, n) \ {a, b}: skip over the two taken indices in increasing order.
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    c = c + (c >= lo)
    c = c + (c >= hi)
    return np.stack([a, b, c], axis=1)


def _lsq_plane(pts: np.ndarray):
    """Orthogonal least-squares plane ``(n, d)`` through ``(K, 3)`` points, K >= 3."""
    centroid = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    n = vt[-1]
    return n, -float(n @ centroid)


def camera_pitch_from_pose(T_world_cam: np.ndarray,
                           up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> float:
    """True pitch [rad] of a camera-optical frame: angle of its z axis below the plane whose
    normal is ``up`` (world frame)."""
    z = np.asarray(T_world_cam, dtype=np.float64)[:3, 2]
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    return float(np.arcsin(np.clip(-z @ u, -1.0, 1.0)))
