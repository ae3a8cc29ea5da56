"""A perfect range sensor over a 2.5-D height map.

The terrain surface of a :class:`~terrain_perception.grid.GridMap` layer is defined here as the
triangle mesh through the cell centres ``(x_i, y_j, h[i, j])``: every 2x2 block of known cells
gives two triangles split along the ``[i, j] -> [i+1, j+1]`` diagonal (the same piecewise-linear
surface :func:`interpolate_height` evaluates). Cells that are NaN contribute no triangles, so rays
pass through unknown terrain. The outer half cell of the grid has no surface.

Rays are intersected with that mesh by Open3D's ``RaycastingScene`` (Embree BVH), so a depth image
is exact up to float32 rounding (~1e-6 m at a few metres), which is what the benchmarks and the
occlusion-fill node need from a "depth-buffer" camera.

Frames: ``T_world_camera`` maps camera-optical points (z forward, x right, y down) into the grid's
frame (``world``/``map``, z up). Depth is z-depth [m] along the optical axis, NaN where a ray hits
nothing (or hits beyond ``max_range_m``).
"""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import open3d as o3d

from terrain_perception.camera import PinholeCamera
from terrain_perception.grid import ELEVATION, GridMap

__all__ = ['HeightFieldScene', 'raycast', 'raycast_depth', 'raycast_points', 'visible_cells',
           'interpolate_height', 'frustum_footprint']


def _check_pose(T: np.ndarray, name: str = 'T_world_camera') -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f'{name} must be a finite 4x4 transform, got shape {T.shape}')
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-5:
        raise ValueError(f'{name} rotation is not orthonormal')
    return T


def interpolate_height(grid: GridMap, xy: np.ndarray, layer: str = ELEVATION) -> np.ndarray:
    """Height [m] of the piecewise-linear surface through the cell centres at world ``xy``.

    Uses the same triangulation as :class:`HeightFieldScene`. Args: ``xy`` ``(..., 2)`` [m] in
    the grid's frame. Returns float64 ``(...)``; NaN outside the meshed area or where one of the
    triangle's cells is unknown.
    """
    h = grid[layer]
    xy = np.asarray(xy, dtype=np.float64)
    r = grid.resolution_m
    f = (xy - np.asarray(grid.origin_xy)) / r - 0.5  # continuous index of cell centres
    i0 = np.floor(f[..., 0]).astype(np.int64)
    j0 = np.floor(f[..., 1]).astype(np.int64)
    fx = f[..., 0] - i0
    fy = f[..., 1] - j0
    nx, ny = grid.shape
    ok = (i0 >= 0) & (j0 >= 0) & (i0 < nx - 1) & (j0 < ny - 1)
    i0c = np.clip(i0, 0, max(nx - 2, 0))
    j0c = np.clip(j0, 0, max(ny - 2, 0))
    i1c = np.minimum(i0c + 1, nx - 1)
    j1c = np.minimum(j0c + 1, ny - 1)
    ha = h[i0c, j0c].astype(np.float64)
    hb = h[i1c, j0c].astype(np.float64)
    hc = h[i1c, j1c].astype(np.float64)
    hd = h[i0c, j1c].astype(np.float64)
    lower = fx >= fy  # triangle (a, b, c) below the diagonal, (a, c, d) above
    z = np.where(lower, ha + fx * (hb - ha) + fy * (hc - hb),
                 ha + fy * (hd - ha) + fx * (hc - hd))
    # the triangle used must be fully known
    known = np.where(lower, np.isfinite(ha) & np.isfinite(hb) & np.isfinite(hc),
                     np.isfinite(ha) & np.isfinite(hc) & np.isfinite(hd))
    return np.where(ok & known, z, np.nan)


def frustum_footprint(camera: PinholeCamera, T_world_camera: np.ndarray, z_lo: float,
                      z_hi: float, max_range_m: float) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """World x-y bounding box ``(lo, hi)`` [m] of the camera frustum inside the slab
    ``z_lo <= z <= z_hi``, truncated at z-depth ``max_range_m``.

    Returns None when the frustum never enters the slab, and ``(-inf, +inf)`` bounds when it
    is unbounded (a ray runs inside the slab forever and ``max_range_m`` is infinite).
    """
    T = _check_pose(T_world_camera)
    W, H = camera.width, camera.height
    u = np.concatenate([np.arange(W), np.full(H, W - 1), np.arange(W)[::-1], np.zeros(H)])
    v = np.concatenate([np.zeros(W), np.arange(H), np.full(W, H - 1), np.arange(H)[::-1]])
    # half-pixel outward so the border pixels' rays are inside the sampled boundary
    u = u + np.where(u <= camera.cx, -0.5, 0.5)
    v = v + np.where(v <= camera.cy, -0.5, 0.5)
    d = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    d = d @ T[:3, :3].T
    o = T[:3, 3]
    dz = d[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        t1 = (z_lo - o[2]) / dz
        t2 = (z_hi - o[2]) / dz
    flat = np.abs(dz) < 1e-12
    inside_now = z_lo <= o[2] <= z_hi
    lo = np.where(flat, 0.0 if inside_now else np.inf, np.maximum(0.0, np.minimum(t1, t2)))
    hi = np.where(flat, np.inf if inside_now else -np.inf,
                  np.minimum(max_range_m, np.maximum(t1, t2)))
    valid = lo <= hi
    if not np.any(valid) and not inside_now:
        return None
    if np.any(np.isinf(hi[valid])):
        return np.array([-np.inf, -np.inf]), np.array([np.inf, np.inf])
    pts = np.concatenate([o[None, :2] + lo[valid, None] * d[valid, :2],
                          o[None, :2] + hi[valid, None] * d[valid, :2]])
    if inside_now:
        pts = np.concatenate([pts, o[None, :2]])
    # far-face corners between sampled border rays: pad by the largest sample spacing
    gap = float(np.max(np.linalg.norm(np.diff(pts[: len(pts) // 2], axis=0), axis=1),
                       initial=0.0)) if len(pts) > 2 else 0.0
    return pts.min(axis=0) - gap, pts.max(axis=0) + gap


class HeightFieldScene:
    """A height-map layer as a triangle mesh ready for ray casting.

    Build once and cast many views of a static terrain (benchmarks, simulators); the module's
    functions build a scene cropped to one camera's view for one-off casts of a changing map.

    Args:
        grid: the height map (frame ``world``/``map``, z up).
        layer: layer name holding heights [m]; NaN cells are holes.
        bounds_xy: optional ``(lo, hi)`` world x-y box [m]; only cells inside (plus one cell of
            margin) are meshed.
        nthreads: Embree threads per cast (0 = all cores).
    """

    def __init__(self, grid: GridMap, layer: str = ELEVATION,
                 bounds_xy: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                 nthreads: int = 1) -> None:
        h = grid[layer]
        self.nthreads = int(nthreads)
        nx, ny = grid.shape
        i0, j0, i1, j1 = 0, 0, nx, ny
        if bounds_xy is not None:
            lo = np.asarray(bounds_xy[0], dtype=np.float64)
            hi = np.asarray(bounds_xy[1], dtype=np.float64)
            r = grid.resolution_m
            org = np.asarray(grid.origin_xy)
            a = np.floor((np.maximum(lo, org - r) - org) / r) - 1
            b = np.ceil((np.minimum(hi, org + np.asarray(grid.length_xy) + r) - org) / r) + 1
            i0, j0 = int(np.clip(a[0], 0, nx)), int(np.clip(a[1], 0, ny))
            i1, j1 = int(np.clip(b[0], 0, nx)), int(np.clip(b[1], 0, ny))
        sub = h[i0:i1, j0:j1]
        xs, ys = grid.cell_centers()
        xs, ys = xs[i0:i1], ys[j0:j1]
        # vertices relative to a local offset keep float32 rounding at the micrometre level
        self.offset = np.array([xs[0] if len(xs) else 0.0, ys[0] if len(ys) else 0.0, 0.0])
        self.n_triangles = 0
        self.z_range = (np.nan, np.nan)
        self._scene = o3d.t.geometry.RaycastingScene()
        if sub.shape[0] < 2 or sub.shape[1] < 2:
            return
        known = np.isfinite(sub)
        if not np.any(known):
            return
        self.z_range = (float(np.nanmin(sub)), float(np.nanmax(sub)))
        X, Y = np.meshgrid(xs - self.offset[0], ys - self.offset[1], indexing='ij')
        V = np.stack([X, Y, np.where(known, sub, 0.0)], -1).reshape(-1, 3).astype(np.float32)
        idx = np.arange(sub.size).reshape(sub.shape)
        a, b = idx[:-1, :-1], idx[1:, :-1]
        c, d = idx[1:, 1:], idx[:-1, 1:]
        ka, kb = known[:-1, :-1], known[1:, :-1]
        kc, kd = known[1:, 1:], known[:-1, 1:]
        m1, m2 = ka & kb & kc, ka & kc & kd
        F = np.concatenate([np.stack([a[m1], b[m1], c[m1]], 1),
                            np.stack([a[m2], c[m2], d[m2]], 1)]).astype(np.uint32)
        if len(F) == 0:
            return
        self.n_triangles = len(F)
        self._scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F))

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """First-hit parameter ``t`` per ray (hit = origin + t * direction), inf on a miss.

        Args: ``origins``, ``directions`` ``(..., 3)`` in the grid frame [m]; directions need not
        be unit length (``t`` is in units of their length). Returns float64 ``(...)``.
        """
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        shape = np.broadcast_shapes(origins.shape, directions.shape)
        if shape[-1] != 3:
            raise ValueError(f'rays need (..., 3) origins and directions, got {shape}')
        if self.n_triangles == 0:
            return np.full(shape[:-1], np.inf)
        rays = np.empty(shape[:-1] + (6,), np.float32)
        rays[..., :3] = origins - self.offset
        rays[..., 3:] = directions
        out = self._scene.cast_rays(o3d.core.Tensor(rays), nthreads=self.nthreads)
        return out['t_hit'].numpy().astype(np.float64)

    def depth_image(self, camera: PinholeCamera, T_world_camera: np.ndarray,
                    max_range_m: float = np.inf, min_range_m: float = 0.0) -> np.ndarray:
        """z-depth image ``(H, W)`` float32 [m] seen from ``T_world_camera``; NaN on a miss."""
        T = _check_pose(T_world_camera)
        d = camera.rays() @ T[:3, :3].T  # z-depth parametrisation: t is the depth
        t = self.cast(T[:3, 3], d)
        ok = np.isfinite(t) & (t <= max_range_m) & (t >= min_range_m)
        return np.where(ok, t, np.nan).astype(np.float32)


def _scene_for_view(grid: GridMap, camera: PinholeCamera, T_world_camera: np.ndarray,
                    layer: str, max_range_m: float, nthreads: int) -> Optional[HeightFieldScene]:
    h = grid[layer]
    if not np.any(np.isfinite(h)):
        return None
    box = frustum_footprint(camera, T_world_camera, float(np.nanmin(h)), float(np.nanmax(h)),
                            max_range_m)
    if box is None:
        return None
    if not np.all(np.isfinite(box[0])) or not np.all(np.isfinite(box[1])):
        box = None
    return HeightFieldScene(grid, layer, bounds_xy=box, nthreads=nthreads)


def raycast(grid: GridMap, camera: PinholeCamera, T_world_camera: np.ndarray,
            layer: str = ELEVATION, max_range_m: float = np.inf, min_range_m: float = 0.0,
            nthreads: int = 1) -> Tuple[np.ndarray, np.ndarray]:
    """Depth image and organized cloud a perfect range camera would see of a height map.

    Args:
        grid: height map; ``layer`` holds heights [m] in the grid frame (z up), NaN = hole.
        camera: pinhole intrinsics.
        T_world_camera: pose of the camera-optical frame in the grid frame (4x4).
        max_range_m, min_range_m: z-depth window [m]; hits outside are NaN.
        nthreads: Embree threads (0 = all cores).

    Returns:
        ``(depth, points)``: z-depth ``(H, W)`` float32 [m] and the organized cloud
        ``(H, W, 3)`` float32 [m] in the camera-optical frame, both NaN where nothing is hit.
    """
    T = _check_pose(T_world_camera)
    scene = _scene_for_view(grid, camera, T, layer, max_range_m, nthreads)
    if scene is None:
        depth = np.full((camera.height, camera.width), np.nan, np.float32)
    else:
        depth = scene.depth_image(camera, T, max_range_m, min_range_m)
    return depth, camera.depth_to_points(depth)


def raycast_depth(grid: GridMap, camera: PinholeCamera, T_world_camera: np.ndarray,
                  **kwargs) -> np.ndarray:
    """z-depth image ``(H, W)`` float32 [m], NaN on a miss (see :func:`raycast`)."""
    return raycast(grid, camera, T_world_camera, **kwargs)[0]


def raycast_points(grid: GridMap, camera: PinholeCamera, T_world_camera: np.ndarray,
                   **kwargs) -> np.ndarray:
    """Organized cloud ``(H, W, 3)`` float32 [m] in the camera frame (see :func:`raycast`)."""
    return raycast(grid, camera, T_world_camera, **kwargs)[1]


def visible_cells(grid: GridMap, T_world_camera: np.ndarray,
                  camera: Optional[PinholeCamera] = None, layer: str = ELEVATION,
                  max_range_m: float = np.inf, tol_m: float = 1e-3,
                  scene: Optional[HeightFieldScene] = None) -> np.ndarray:
    """Cells whose surface point is in direct line of sight of the camera.

    A known cell ``[i, j]`` is visible when the segment from the camera centre to its surface
    point ``(x_i, y_j, h[i, j])`` meets no other part of the surface first (within ``tol_m``),
    and, if ``camera`` is given, that point projects inside the image at z-depth in
    ``(0, max_range_m]``. Unknown (NaN) cells are never visible.

    Args:
        grid: the height map in the grid frame (z up).
        T_world_camera: camera pose (4x4, optical frame) in the grid frame.
        camera: optional intrinsics limiting visibility to the field of view.
        layer: heights layer [m].
        max_range_m: farthest z-depth [m] counted (only with ``camera``); without a camera, the
            farthest Euclidean distance [m].
        tol_m: distance [m] a hit may fall short of the cell's point and still count as it.
        scene: a prebuilt :class:`HeightFieldScene` of the same grid and layer (saves the build).

    Returns:
        bool ``(nx, ny)`` mask.
    """
    T = _check_pose(T_world_camera)
    h = grid[layer]
    out = np.zeros(grid.shape, bool)
    known = np.isfinite(h)
    if not np.any(known):
        return out
    xs, ys = grid.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    P = np.stack([X[known], Y[known], h[known].astype(np.float64)], -1)
    o = T[:3, 3]
    cand = np.ones(len(P), bool)
    if camera is not None:
        pc = (P - o) @ T[:3, :3]  # camera-frame coordinates
        z = pc[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            uv = camera.project(pc)
        cand = ((z > 0) & (z <= max_range_m) & (uv[:, 0] >= -0.5)
                & (uv[:, 0] <= camera.width - 0.5) & (uv[:, 1] >= -0.5)
                & (uv[:, 1] <= camera.height - 0.5))
    else:
        cand = np.linalg.norm(P - o, axis=1) <= max_range_m
    if not np.any(cand):
        return out
    if scene is None:
        lo = np.minimum(P[cand, :2].min(axis=0), o[:2])
        hi = np.maximum(P[cand, :2].max(axis=0), o[:2])
        scene = HeightFieldScene(grid, layer, bounds_xy=(lo, hi))
    d = P[cand] - o
    dist = np.linalg.norm(d, axis=1)
    t = scene.cast(o, d / dist[:, None])
    vis = t >= dist - tol_m  # blocked rays hit something before reaching the cell
    idx = np.flatnonzero(known.ravel())[cand]
    out.ravel()[idx[vis]] = True
    return out
