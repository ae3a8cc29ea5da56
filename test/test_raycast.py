"""Height-map ray caster against analytic geometry."""

import numpy as np
import pytest

from terrain_perception import raycast as rc
from terrain_perception.camera import PinholeCamera
from terrain_perception.grid import ELEVATION, GridMap
from terrain_perception.transforms import make_T, rpy_to_R, transform_points

# base_link (x fwd, y left, z up) -> camera optical (z fwd, x right, y down)
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_pose(x, y, z, pitch_down_deg, yaw_deg=0.0, roll_deg=0.0):
    R = rpy_to_R(np.radians(roll_deg), np.radians(pitch_down_deg), np.radians(yaw_deg))
    return make_T(R @ R_BASE_OPTICAL, [x, y, z])


def grid_from(fn, res=0.01, origin=(-1.0, -1.5), shape=(300, 300)):
    g = GridMap.empty(res, origin, shape)
    xs, ys = g.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    g[ELEVATION] = fn(X, Y)
    return g


CAM = PinholeCamera.from_fov(160, 120, 60.0)


def test_plane_depth_matches_analytic_intersection():
    a, b, c = 0.05, -0.03, 0.02  # z = a x + b y + c
    g = grid_from(lambda X, Y: a * X + b * Y + c)
    T = camera_pose(0.0, 0.0, 0.4, 45.0, yaw_deg=10.0)
    depth, pts = rc.raycast(g, CAM, T)
    d = CAM.rays() @ T[:3, :3].T
    o = T[:3, 3]
    # o + t d on plane: o_z + t d_z = a (o_x + t d_x) + b (o_y + t d_y) + c
    t = (a * o[0] + b * o[1] + c - o[2]) / (d[..., 2] - a * d[..., 0] - b * d[..., 1])
    assert np.isfinite(depth).all(), 'every ray of a downward camera must hit the plane'
    assert np.abs(depth - t).max() < 2e-5
    assert np.allclose(pts[..., 2], depth, equal_nan=True)
    pw = transform_points(T, pts.reshape(-1, 3).astype(np.float64))
    assert np.abs(pw[:, 2] - (a * pw[:, 0] + b * pw[:, 1] + c)).max() < 2e-5


def test_smooth_terrain_within_a_fraction_of_a_millimetre():
    def f(X, Y):
        return 0.03 * np.sin(4.0 * X) * np.cos(3.0 * Y)

    g = grid_from(f, res=0.002, origin=(-0.2, -0.6), shape=(600, 600))
    T = camera_pose(-0.1, 0.0, 0.35, 40.0)
    pts = rc.raycast_points(g, CAM, T)
    pw = transform_points(T, pts.reshape(-1, 3).astype(np.float64))
    pw = pw[np.isfinite(pw[:, 0])]
    assert len(pw) > 0.7 * CAM.width * CAM.height
    # on the meshed surface (exactness of the caster) ...
    assert np.abs(pw[:, 2] - rc.interpolate_height(g, pw[:, :2])).max() < 1e-5
    # ... and on the true smooth surface (mesh + caster) well under a millimetre
    assert np.abs(pw[:, 2] - f(pw[:, 0], pw[:, 1])).max() < 2e-4


def test_holes_let_rays_through_and_upward_camera_sees_nothing():
    g = grid_from(lambda X, Y: np.zeros_like(X))
    T = camera_pose(0.0, 0.0, 0.3, 90.0)  # looking straight down
    full = rc.raycast_depth(g, CAM, T)
    assert np.nanmax(np.abs(full - 0.3)) < 1e-5 and np.isfinite(full).all()
    h = g[ELEVATION].copy()
    h[90:110, 140:160] = np.nan  # a hole right below the camera
    g[ELEVATION] = h
    holed = rc.raycast_depth(g, CAM, T)
    assert np.isnan(holed[CAM.height // 2, CAM.width // 2])
    assert np.isfinite(holed[0, 0])
    up = rc.raycast_depth(g, CAM, camera_pose(0.0, 0.0, 0.3, -60.0))
    assert np.isnan(up).all()
    far = rc.raycast_depth(g, CAM, camera_pose(0.0, 0.0, 0.3, 30.0), max_range_m=0.5)
    assert np.nanmax(far) <= 0.5 and np.isnan(far).any() and np.isfinite(far).any()


def test_visible_cells_respects_occlusion_and_field_of_view():
    def wall(X, Y):
        return np.where((X > 0.30) & (X < 0.34), 0.2, 0.0)

    g = grid_from(wall)
    T = camera_pose(0.0, 0.0, 0.25, 30.0)
    vis = rc.visible_cells(g, T, CAM)
    xs, ys = g.cell_centers()
    i_near = np.searchsorted(xs, 0.25)
    i_behind = np.searchsorted(xs, 0.45)
    j0 = np.searchsorted(ys, 0.0)
    assert vis[i_near, j0], 'ground in front of the wall is visible'
    assert vis[np.searchsorted(xs, 0.32), j0], 'the wall top is visible'
    assert not vis[i_behind, j0], 'ground right behind a 20 cm wall is hidden'
    assert not vis[np.searchsorted(xs, -0.5), j0], 'ground behind the camera is out of view'
    # agreement with the depth image: every pixel's hit cell is a visible cell
    pts = rc.raycast_points(g, CAM, T)
    pw = transform_points(T, pts.reshape(-1, 3).astype(np.float64))
    pw = pw[np.isfinite(pw[:, 0])]
    ij = g.world_to_index(pw[:, :2])
    # away from the wall's edges (where a hit cell's centre may sit on the other face)
    xc = pw[:, 0]
    ok = (np.abs(xc - 0.30) > 0.02) & (np.abs(xc - 0.34) > 0.02)
    assert vis[ij[ok, 0], ij[ok, 1]].mean() > 0.99


def test_bad_pose_raises():
    g = grid_from(lambda X, Y: np.zeros_like(X))
    with pytest.raises(ValueError, match='4x4'):
        rc.raycast(g, CAM, np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match='orthonormal'):
        rc.raycast(g, CAM, bad)
