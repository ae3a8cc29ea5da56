"""Contact patches (paper 003): paraboloid fit, saliency filters, preprocessing, full pipeline."""

import dataclasses

import numpy as np
import pytest

from terrain_perception.camera import PinholeCamera
from terrain_perception.grid import GridMap
from terrain_perception.patches import (IntegralMoments, PatchConfig, _seed_band,
                                        bilateral_filter_cloud, find_patches, fit_paraboloids,
                                        fixation_point, gravity_in_camera, integral_normals,
                                        median_downsample_2x2, patch_filters, saliency,
                                        smallest_eigenvectors)
from terrain_perception.raycast import raycast_points
from terrain_perception.transforms import R_to_quat, rpy_to_R


def _sample_paraboloids(rng, n_patch, n_pts, radius, noise, kx, ky, symmetric=False):
    """Random poses; points uniform in a disc of the patch's local x-y plane (+ noise).
    ``symmetric``: every point (x, y) has its twin (-x, -y), so the data centre is the vertex."""
    Rs = np.stack([rpy_to_R(*rng.uniform(-0.6, 0.6, 3)) for _ in range(n_patch)])
    ts = rng.uniform(-1, 1, (n_patch, 3)) + [0, 0, 1.5]
    m = n_pts // 2 if symmetric else n_pts
    rad = radius * np.sqrt(rng.random((n_patch, m)))
    ang = rng.random((n_patch, m)) * 2 * np.pi
    x, y = rad * np.cos(ang), rad * np.sin(ang)
    if symmetric:
        x, y = np.concatenate([x, -x], 1), np.concatenate([y, -y], 1)
    z = 0.5 * (kx[:, None] * x * x + ky[:, None] * y * y)
    loc = np.stack([x, y, z], -1) + rng.normal(0, noise, (n_patch, n_pts, 3))
    pts = np.einsum('pij,pnj->pni', Rs, loc) + ts[:, None]
    return pts, Rs, ts


def _true_principal_curvatures(kx, ky, x, y):
    """Principal curvatures (min, max) of z = 0.5 (kx x^2 + ky y^2) at (x, y) (Monge patch)."""
    fx, fy = kx * x, ky * y
    W = np.sqrt(1 + fx * fx + fy * fy)
    first = np.stack([np.stack([1 + fx * fx, fx * fy], -1), np.stack([fx * fy, 1 + fy * fy], -1)],
                     -2)
    second = np.zeros_like(first)
    second[..., 0, 0], second[..., 1, 1] = kx / W, ky / W
    k = np.sort(np.linalg.eigvals(np.linalg.solve(first, second)).real, axis=-1)
    return k[..., 0], k[..., 1]


def _check_fit(fit, Rs, ts, kx, ky, k_tol, ang_tol_deg, z_tol):
    # The fitted vertex is where the patch sits on the data (the data centre); compare with the
    # true principal curvatures there (equal to kx, ky when the data centre is the vertex).
    assert np.all(fit.kx <= fit.ky)
    q = np.einsum('pji,pj->pi', Rs, fit.vertex - ts)
    k1, k2 = _true_principal_curvatures(kx, ky, q[:, 0], q[:, 1])
    np.testing.assert_allclose(fit.kx, k1, atol=k_tol)
    np.testing.assert_allclose(fit.ky, k2, atol=k_tol)
    # The vertex lies on the true surface, and the fitted normal is the true normal there.
    surf = 0.5 * (kx * q[:, 0] ** 2 + ky * q[:, 1] ** 2)
    assert np.abs(q[:, 2] - surf).max() < z_tol
    n_true_loc = np.stack([-kx * q[:, 0], -ky * q[:, 1], np.ones(len(q))], -1)
    n_true = np.einsum('pij,pj->pi', Rs, n_true_loc)
    n_true /= np.linalg.norm(n_true, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.einsum('pi,pi->p', n_true, fit.R[:, :, 2]), -1, 1)))
    assert ang.max() < ang_tol_deg
    # Principal x direction matches (up to sign) where the curvatures are well separated.
    sep = np.abs(kx - ky) > 8.0
    cosx = np.abs(np.einsum('pi,pi->p', Rs[:, :, 0], fit.R[:, :, 0]))
    assert np.degrees(np.arccos(np.clip(cosx[sep], -1, 1))).max() < 4 * ang_tol_deg
    # Frames are proper rotations.
    np.testing.assert_allclose(np.einsum('pji,pjk->pik', fit.R, fit.R),
                               np.broadcast_to(np.eye(3), fit.R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(fit.R), 1.0, atol=1e-9)


def test_paraboloid_fit_exact_data_recovers_curvatures_and_pose():
    rng = np.random.default_rng(1)
    kx = rng.uniform(-12, 2, 40)
    ky = kx + rng.uniform(0, 20, 40)
    pts, Rs, ts = _sample_paraboloids(rng, 40, 50, 0.1, 0.0, kx, ky, symmetric=True)
    fit = fit_paraboloids(pts, np.ones(pts.shape[:2], bool), Rs[:, :, 2], iterations=10)
    _check_fit(fit, Rs, ts, kx, ky, k_tol=1e-4, ang_tol_deg=1e-3, z_tol=1e-7)
    np.testing.assert_allclose(fit.vertex, ts, atol=1e-7)    # data centre = vertex here
    assert fit.rms_euclidean.max() < 1e-7


def test_paraboloid_fit_noisy_data_and_padding_mask():
    rng = np.random.default_rng(2)
    kx = rng.uniform(-12, 2, 60)
    ky = kx + rng.uniform(0, 20, 60)
    real, Rs, ts = _sample_paraboloids(rng, 60, 40, 0.1, 0.0005, kx, ky, symmetric=True)
    pts = np.concatenate([real, np.full((60, 10, 3), 1e3)], axis=1)   # padding rows: garbage
    mask = np.ones(pts.shape[:2], bool)
    mask[:, 40:] = False
    fit = fit_paraboloids(pts, mask, Rs[:, :, 2], iterations=6)
    _check_fit(fit, Rs, ts, kx, ky, k_tol=1.5, ang_tol_deg=1.0, z_tol=0.001)
    assert np.median(np.abs(np.r_[fit.kx - kx, fit.ky - ky])) < 0.4
    np.testing.assert_array_equal(fit.count, 40)
    # The residual estimates the noise along the normal (0.5 mm).
    assert 0.0003 < np.median(fit.rms_euclidean) < 0.0007


def test_paraboloid_fit_off_vertex_data_sits_on_the_surface():
    """Data not centred on the paraboloid's vertex: the patch is the osculating paraboloid at
    the data centre, so its vertex is on the surface and its curvatures are (up to the cubic
    terms it cannot represent) the surface's principal curvatures there."""
    rng = np.random.default_rng(8)
    kx = rng.uniform(-10, 0, 40)
    ky = kx + rng.uniform(0, 12, 40)
    pts, Rs, ts = _sample_paraboloids(rng, 40, 50, 0.1, 0.0, kx, ky)
    fit = fit_paraboloids(pts, np.ones(pts.shape[:2], bool), Rs[:, :, 2])
    q = np.einsum('pji,pj->pi', Rs, fit.vertex - ts)
    assert np.abs(q[:, 2] - 0.5 * (kx * q[:, 0] ** 2 + ky * q[:, 1] ** 2)).max() < 0.0005
    k1, k2 = _true_principal_curvatures(kx, ky, q[:, 0], q[:, 1])
    assert np.abs(np.r_[fit.kx - k1, fit.ky - k2]).max() < 1.0
    assert fit.rms_euclidean.max() < 0.001


def test_levenberg_marquardt_improves_on_the_closed_form_start():
    rng = np.random.default_rng(3)
    kx = np.full(30, -10.0)
    ky = np.full(30, 15.0)
    pts, Rs, _ = _sample_paraboloids(rng, 30, 50, 0.1, 0.0, kx, ky, symmetric=True)
    start = fit_paraboloids(pts, np.ones(pts.shape[:2], bool), Rs[:, :, 2], iterations=0)
    refined = fit_paraboloids(pts, np.ones(pts.shape[:2], bool), Rs[:, :, 2], iterations=8)
    assert np.all(refined.rms_algebraic <= start.rms_algebraic + 1e-12)
    assert refined.rms_algebraic.mean() < 0.5 * start.rms_algebraic.mean()


def test_fit_rejects_bad_input():
    with pytest.raises(ValueError, match='6 points'):
        fit_paraboloids(np.zeros((2, 5, 3)), np.ones((2, 5), bool), [0, 0, 1])
    with pytest.raises(ValueError, match=r'\(P, n, 3\)'):
        fit_paraboloids(np.zeros((2, 8)), np.ones((2, 8), bool), [0, 0, 1])


def test_curvature_and_residual_filters_keep_and_drop_hand_made_neighbourhoods():
    cfg = PatchConfig()                   # paper: kappa in [-13.6, 19.7] 1/m, d_max 0.01 m
    rng = np.random.default_rng(4)
    cases = {  # name: (kx, ky, noise [m], expected curvature_ok, expected residual_ok)
        'gentle bowl': (3.0, 5.0, 0.0005, True, True),
        'sharp bump': (-30.0, -25.0, 0.0005, False, True),
        'sharp dip': (10.0, 30.0, 0.0005, False, True),
        'saddle within limits': (-10.0, 15.0, 0.0005, True, True),
        'rubble': (0.0, 0.0, 0.03, None, False),
    }
    kx = np.array([c[0] for c in cases.values()])
    ky = np.array([c[1] for c in cases.values()])
    pts = []
    Rs = []
    for (a, b, noise, _, _) in cases.values():
        p, R, _ = _sample_paraboloids(rng, 1, 50, 0.1, noise, np.array([a]), np.array([b]))
        pts.append(p[0])
        Rs.append(R[0])
    fit = fit_paraboloids(np.stack(pts), np.ones((len(pts), 50), bool),
                          np.stack(Rs)[:, :, 2])
    curv_ok, res_ok = patch_filters(fit.kx, fit.ky, fit.rms_euclidean, cfg)
    for i, (name, (_, _, _, want_c, want_r)) in enumerate(cases.items()):
        if want_c is not None:
            assert curv_ok[i] == want_c, name
        assert res_ok[i] == want_r, name
    assert np.allclose(fit.kx[:4], kx[:4], atol=2.0) and np.allclose(fit.ky[:4], ky[:4], atol=2.0)


def test_smallest_eigenvectors_match_eigh():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(500, 3, 3))
    C = A @ A.transpose(0, 2, 1)
    v = smallest_eigenvectors(C)
    w, V = np.linalg.eigh(C)
    np.testing.assert_allclose(np.abs(np.einsum('pi,pi->p', v, V[:, :, 0])), 1.0, atol=1e-6)


def _plane_cloud(cam, T_world_cam, height_fn, res=0.005):
    """Organized cloud (camera frame) of the terrain z = height_fn(x, y), ray cast exactly
    against its 5 mm height map (terrain_perception.raycast)."""
    n = int(4.0 / res)
    grid = GridMap(res, (-1.0, -2.0), (n, n), {})
    xs, ys = grid.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    grid['elevation'] = height_fn(X, Y)
    return raycast_points(grid, cam, T_world_cam)


def _camera_pose(height=1.0, pitch_deg=45.0):
    # optical frame: z forward, x right, y down; camera looks along +x world, pitched down.
    R_body_opt = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    from terrain_perception.transforms import rot_y
    T = np.eye(4)
    T[:3, :3] = rot_y(np.radians(pitch_deg)) @ R_body_opt
    T[:3, 3] = [0.0, 0.0, height]
    return T


def test_gravity_and_fixation_point():
    # Camera looking level (optical z = world x): gravity is +y (down) in the optical frame.
    T = _camera_pose(pitch_deg=0.0)
    q_world_imu = R_to_quat(np.eye(3))
    g = gravity_in_camera(q_world_imu, T[:3, :3])
    np.testing.assert_allclose(g, [0, 1, 0], atol=1e-12)
    f = fixation_point(g, PatchConfig())
    np.testing.assert_allclose(f, [0, 1.0, 1.2], atol=1e-12)   # l_d down, l_f forward
    with pytest.raises(ValueError, match='quaternion'):
        gravity_in_camera([0, 0, 0, 0], np.eye(3))
    with pytest.raises(ValueError, match='gravity'):
        fixation_point([0, 0, 0], PatchConfig())


def test_bilateral_filter_smooths_noise_but_keeps_a_depth_step():
    rng = np.random.default_rng(6)
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    z = np.where(np.arange(64)[None, :] < 32, 1.0, 1.3) * np.ones((48, 1))
    noisy = z + rng.normal(0, 0.003, z.shape)
    cloud = cam.depth_to_points(noisy.astype(np.float32))
    cloud[10, 10] = np.nan
    out = bilateral_filter_cloud(cloud, PatchConfig(bilateral_sigma_depth_m=0.02))
    zf = out[..., 2]
    assert np.isnan(zf[10, 10]) and np.isfinite(zf).sum() == z.size - 1
    inner = np.s_[5:-5, 5:27]
    assert np.nanstd(zf[inner] - z[inner]) < 0.6 * np.std(noisy[inner] - z[inner])
    # No bleeding across the 0.3 m step: pixels next to it stay on their side.
    assert np.all(np.abs(zf[5:-5, 31] - 1.0) < 0.02) and np.all(np.abs(zf[5:-5, 32] - 1.3) < 0.02)
    # Points move along their rays: x/z and y/z are unchanged.
    ok = np.isfinite(zf)
    np.testing.assert_allclose((out[..., 0] / zf)[ok], (cloud[..., 0] / cloud[..., 2])[ok],
                               atol=1e-5)


def test_median_downsample_2x2_with_invalid_points():
    c = np.full((4, 4, 3), np.nan, np.float32)
    c[0, 0], c[0, 1], c[1, 0], c[1, 1] = [1, 1, 1], [2, 2, 2], [3, 3, 3], [10, 10, 10]
    c[0, 2], c[1, 3] = [5, 5, 5], [7, 7, 7]                 # two valid -> mean
    c[2, 0], c[2, 1], c[3, 1] = [1, 1, 1], [4, 4, 4], [9, 9, 9]   # three valid -> middle
    out = median_downsample_2x2(c)
    assert out.shape == (2, 2, 3)
    np.testing.assert_allclose(out[0, 0], 2.5)
    np.testing.assert_allclose(out[0, 1], 6.0)
    np.testing.assert_allclose(out[1, 0], 4.0)
    assert np.all(np.isnan(out[1, 1]))


def test_stage_one_shortcuts_and_fit_kernels_match_the_general_paths():
    """The shortcuts find_patches takes must not change results: the filter and median of a
    band known to hold only valid depths, the compiled rotation-vector kernels, the direct solve
    (which still raises on a singular matrix); invalid depths (NaN, 0, negative) stay invalid."""
    from terrain_perception import patches as pm
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(3)
    cfg = PatchConfig(bilateral_sigma_depth_m=0.01)
    cloud = np.zeros((40, 64, 3), np.float32)
    cloud[..., 2] = 0.3 + 0.02 * rng.random((40, 64))
    cloud[..., 0] = rng.normal(0, 0.1, (40, 64))
    cloud[..., 1] = rng.normal(0, 0.1, (40, 64))
    z = np.ascontiguousarray(cloud[..., 2])
    (a, sa), (b, sb) = [pm._filter_and_downsample(cloud, z, cfg, None, v) for v in (False, True)]
    assert all(np.array_equal(p, q) for p, q in zip(a, b)) and np.array_equal(sa, sb)
    holes = cloud.copy()
    holes[3, 5, 2], holes[7, 9, 2], holes[11, 13] = 0.0, -0.3, np.nan
    D = median_downsample_2x2(bilateral_filter_cloud(holes, cfg))
    assert np.isnan(bilateral_filter_cloud(holes, cfg)[[3, 7, 11], [5, 9, 13]]).all()
    assert np.isfinite(D).all()                     # each block still has valid points
    w = rng.normal(0, 0.01, (20, 3))
    w[0] = 0.0
    np.testing.assert_array_equal(pm._expmap(w), Rotation.from_rotvec(w).as_matrix())
    H = rng.normal(size=(5, 6, 6))
    H = H @ H.transpose(0, 2, 1) + np.eye(6)
    g = rng.normal(size=(5, 6, 1))
    np.testing.assert_array_equal(pm._solve(H, g), np.linalg.solve(H, g))
    with pytest.raises(np.linalg.LinAlgError):
        pm._solve(np.zeros((2, 6, 6)), g[:2])


def test_integral_normals_and_saliency_on_a_hand_made_scene():
    """Flat ground, a 60 deg ramp and a step: DoNG drops the ramp, DoN drops the step edge."""
    cam = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    T = _camera_pose(1.0, 45.0)

    def height(x, y):
        ramp = np.where((y > 0.25) & (x > 0.8) & (x < 1.4), np.tan(np.radians(60)) *
                        np.clip(x - 0.8, 0, 0.1), 0.0)
        step = np.where((y < -0.1) & (x > 1.0), 0.08, 0.0)
        return ramp + step

    D = _plane_cloud(cam, T, height)
    cfg = PatchConfig()
    mom = IntegralMoments(D)
    world = D.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    g = T[:3, :3].T @ np.array([0, 0, -1.0])

    def pixel_near(x, y):
        d = np.linalg.norm(world[..., :2] - [x, y], axis=-1)
        d[~np.isfinite(d)] = np.inf
        return np.unravel_index(np.argmin(d), d.shape)

    spots = {'flat': (1.1, 0.1), 'ramp face': (0.85, 0.35), 'step edge': (1.0, -0.25)}
    rc = np.array([pixel_near(*xy) for xy in spots.values()])
    N, Ns = integral_normals(D, rc[:, 0], rc[:, 1], cam.fx, cfg.patch_radius_m, mom)
    don, dong, keep = saliency(N, Ns, g, cfg)
    assert keep.tolist() == [True, False, False]
    assert np.degrees(dong[0]) < 1.0 and np.degrees(don[0]) < 1.0      # flat: normal is up
    assert np.degrees(dong[1]) > cfg.max_dong_deg                      # ramp fails DoNG
    assert np.degrees(don[2]) > cfg.max_don_deg                        # edge fails DoN


def _ramp_scene(noise_seed=7, random_seed=0):
    """Flat ground with a 60 deg ramp (foot at x = 1.0, crest at x = 1.15, for y > 0.2) where
    the fixation area is, seen from 1 m at 45 deg: (camera, T_world_cam, cloud, gravity, cfg)."""
    rng = np.random.default_rng(noise_seed)
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    T = _camera_pose(1.0, 45.0)

    def height(x, y):
        return np.where(y > 0.2, np.tan(np.radians(60)) * np.clip(x - 1.0, 0, 0.15), 0.0)

    cloud = _plane_cloud(cam, T, height)
    cloud += rng.normal(0, 0.001, cloud.shape).astype(np.float32) * cloud[..., 2:3]
    g = T[:3, :3].T @ np.array([0, 0, -1.0])
    return cam, T, cloud, g, PatchConfig(random_seed=random_seed)


def _near_ramp_edges(world_xy, margin):
    """Points within ``margin`` [m] (horizontally) of the ramp's foot, crest or side edge."""
    x, y = world_xy[:, 0], world_xy[:, 1]
    return (((y > 0.2 - margin) & ((np.abs(x - 1.0) < margin) | (np.abs(x - 1.15) < margin)))
            | ((np.abs(y - 0.2) < margin) & (x > 1.0 - margin)))


def test_find_patches_on_flat_ground_with_a_ramp():
    cam, T, cloud, g, cfg = _ramp_scene()
    p = find_patches(cloud, cam.fx, cam.fy, g, cfg)
    assert len(p) >= 80 and p.counts['seeds'] == cfg.max_seeds
    world_v = p.vertex @ T[:3, :3].T + T[:3, 3]
    world_n = np.einsum('ij,pj->pi', T[:3, :3], p.normal)
    # Patches lie on the floor or the ramp's plateau with their normals up, and all within R
    # (+ r) of the fixation point. None on the 60 deg face (DoNG); a few may sit in the concave
    # corner at its foot, which the paper's human-scale thresholds accept.
    # Next to the ramp's edges (foot, crest, side) a seed passes DoNG, but its paraboloid, fitted
    # over both sides of the edge, can tilt further and sit between floor and plateau (up to
    # ~50 deg, all within 2.5 cm of an edge over 48 random seeds). The checks below leave out
    # r/2 around the edges: the middle third of the 60 deg face stays in, so patches let
    # through by a broken DoNG filter would still fail them.
    near_edge = _near_ramp_edges(world_v, 0.5 * cfg.patch_radius_m)
    top = np.tan(np.radians(60)) * 0.15
    flat = (np.abs(world_v[:, 2]) < 0.005) | (np.abs(world_v[:, 2] - top) < 0.005)
    assert flat.mean() > 0.9
    assert not np.any((world_v[:, 2] > 0.03) & (world_v[:, 2] < top - 0.03) & ~near_edge)
    ang = np.degrees(np.arccos(np.clip(world_n[:, 2], -1, 1)))
    assert np.percentile(ang[flat], 90) < 2.0
    assert ang[~near_edge].max() <= cfg.max_dong_deg + 5.0
    assert np.all(np.linalg.norm(p.vertex - p.fixation, axis=1) < cfg.roi_radius_m
                  + cfg.patch_radius_m)
    np.testing.assert_allclose(p.fixation_distance, np.linalg.norm(p.vertex - p.fixation,
                                                                   axis=1))
    assert np.percentile(np.abs(np.r_[p.kx[flat], p.ky[flat]]), 90) < 3.0   # flat: ~0 1/m
    assert np.all(p.residual <= cfg.max_residual_m)
    assert np.all(np.degrees(p.dong) <= cfg.max_dong_deg)
    # The ramp (inside R) exists in the image but no patch sits on it.
    fix_w = T[:3, :3] @ p.fixation + T[:3, 3]
    assert np.hypot(*(fix_w[:2] - [1.07, 0.5])) < cfg.roi_radius_m
    assert not np.any((world_v[:, 1] > 0.2 + cfg.patch_radius_m)
                      & (world_v[:, 0] > 1.0) & (world_v[:, 0] < 1.15) & ~near_edge)
    # Same seed, same patches; map-frame transform keeps geometry.
    again = find_patches(cloud, cam.fx, cam.fy, g, cfg)
    np.testing.assert_array_equal(again.vertex, p.vertex)
    pm = p.transformed(T)
    np.testing.assert_allclose(pm.vertex, world_v)
    np.testing.assert_allclose(pm.gravity, [0, 0, -1], atol=1e-12)
    rim = pm.boundary(8)
    assert rim.shape == (len(p), 8, 3)
    # (level patches whose neighbourhood, radius r, does not reach an edge of the ramp)
    level = flat & (ang < 2.0) & ~_near_ramp_edges(world_v, cfg.patch_radius_m)
    assert np.all(np.abs(rim[level, :, 2] - pm.vertex[level, None, 2]) < 0.01)
    np.testing.assert_allclose(np.linalg.norm(rim[level, :, :2] - pm.vertex[level, None, :2],
                                              axis=-1),
                               np.broadcast_to(pm.radius[level, None], (level.sum(), 8)),
                               rtol=0.05)
    assert np.all((pm.radius > 0.5 * cfg.patch_radius_m) & (pm.radius < 1.2 * cfg.patch_radius_m))


def test_seed_region_of_the_row_band_matches_the_whole_frame():
    """Stages I-II run only on the rows _seed_band selects (a quadruped's camera sees far past
    its fixation point); the seed region (step 6) must be exactly the whole-frame one."""
    rng = np.random.default_rng(9)
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    T = _camera_pose(0.2, 35.0)

    def height(x, y):   # bumps and a 3 cm step across the view
        return (0.01 * np.sin(20 * x) * np.cos(17 * y) + 0.005 * np.sin(53 * x + 31 * y)
                + np.where(x > 0.35, 0.03, 0.0))

    cloud = _plane_cloud(cam, T, height)
    cloud += rng.normal(0, 0.001, cloud.shape).astype(np.float32) * cloud[..., 2:3]
    g = T[:3, :3].T @ np.array([0, 0, -1.0])
    cfg = PatchConfig(bilateral_sigma_depth_m=0.01, fixation_down_m=0.2, fixation_forward_m=0.16,
                      roi_radius_m=0.15, patch_radius_m=0.02, max_residual_m=0.002)
    fix = fixation_point(g, cfg)
    D = median_downsample_2x2(bilateral_filter_cloud(cloud, cfg))
    with np.errstate(invalid='ignore'):
        whole = np.count_nonzero(((D - fix) ** 2).sum(-1) <= cfg.roi_radius_m ** 2)
    a, b, _ = _seed_band(np.ascontiguousarray(cloud[..., 2]), fix, cam.fx, cam.fy, cfg)
    assert a >= 40                                            # the band is a real crop
    p = find_patches(cloud, cam.fx, cam.fy, g, cfg)
    assert whole > 1000 and p.counts['dtfp'] == whole
    assert p.counts['seeds'] == cfg.max_seeds and len(p) > 0


def test_find_patches_bad_and_empty_input():
    cfg = PatchConfig()
    with pytest.raises(ValueError, match='organized'):
        find_patches(np.zeros((100, 3), np.float32), 500, 500, [0, 1, 0], cfg)
    with pytest.raises(ValueError, match='focal'):
        find_patches(np.zeros((8, 8, 3), np.float32), 0.0, 500, [0, 1, 0], cfg)
    empty = find_patches(np.full((48, 64, 3), np.nan, np.float32), 50, 50, [0, 1, 0], cfg)
    assert len(empty) == 0 and empty.counts['dtfp'] == 0
    # Looking at the sky (no point near the fixation point): empty, counted, no exception.
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    far = cam.depth_to_points(np.full((48, 64), 30.0, np.float32))
    res = find_patches(far, 50, 50, [0, 1, 0], dataclasses.replace(cfg))
    assert len(res) == 0 and res.counts['seeds'] == 0


# --------------------------------------------------------------------------------------------
# Compiled kernels (numba) against the numpy reference steps
# --------------------------------------------------------------------------------------------

FIT_FIELDS = ('vertex', 'R', 'kx', 'ky', 'radius', 'residual', 'fixation_distance')
FIT_RTOL = 1e-9     # the fit's sums and solves round differently (BLAS / LAPACK vs loops)


@pytest.fixture
def kernel_selection():
    """The patches module with the kernel selection restored to the default afterwards."""
    from terrain_perception import patches as pm
    yield pm
    pm.use_compiled_kernels(None)


@pytest.fixture(scope='module')
def bench_frames():
    """Four frames of `terrain-bench plan` (rocks-6cm course seed 0, the robot's camera along the
    course, the bench's depth noise) and their gravity vectors, made as the bench makes them."""
    from terrain_perception.bench.plan import _depth_noise, load_profile
    from terrain_perception.raycast import HeightFieldScene
    from terrain_perception.robot_model import load_robot_model
    from terrain_perception.terrain import make_course
    from terrain_perception.transforms import make_T
    robot_name, cfg, _, _ = load_profile()
    robot = load_robot_model(robot_name)
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    grid = make_course('rocks-6cm', 0, 0.005)
    scene = HeightFieldScene(grid)
    x0, x1 = grid.metadata['rough_extent_xy'][:2]
    rng = np.random.default_rng(0)
    frames = []
    for k in range(4):
        x = x0 - 0.25 + (x1 - x0) * (k + 0.5) / 4
        yaw, y = rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2)
        c, s = np.cos(yaw), np.sin(yaw)
        T_base = make_T(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
                        [x, y, robot.standing_height_m + 0.03])
        depth = scene.depth_image(cam, T_base @ robot.T_base_camera)
        cloud = cam.depth_to_points(_depth_noise(depth, rng).astype(np.float32))
        R_imu_cam = robot.T_base_imu[:3, :3].T @ robot.T_base_camera[:3, :3]
        g = gravity_in_camera(R_to_quat(T_base[:3, :3] @ robot.T_base_imu[:3, :3]), R_imu_cam)
        frames.append((cloud, g))
    return cfg, cam, frames


def _with_holes(cloud, rng):
    """The cloud with 4 % NaN points, 2 % zero and 1 % negative depths and some 8x8 NaN holes."""
    c = cloud.copy()
    u = rng.random(c.shape[:2])
    c[u < 0.04] = np.nan
    c[(u >= 0.04) & (u < 0.06), 2] = 0.0
    c[(u >= 0.06) & (u < 0.07), 2] *= -1
    blk = rng.random((c.shape[0] // 8, c.shape[1] // 8)) < 0.05
    c[np.kron(blk, np.ones((8, 8), bool))] = np.nan
    return c


def _run_both(pm, cloud, fx, g, cfg):
    """find_patches with the numpy steps and with the compiled kernels, and the seeds each passed
    to the neighbourhood search."""
    seeds, out = [], []
    orig = pm._sample_neighbourhoods

    def spy(cloud_, scale, seeds_full, seed_pts, *a, **k):
        seeds.append((seeds_full.copy(), seed_pts.copy()))
        return orig(cloud_, scale, seeds_full, seed_pts, *a, **k)

    pm._sample_neighbourhoods = spy
    try:
        for compiled in (False, True):
            assert pm.use_compiled_kernels(compiled) == compiled
            seeds.append(None)
            out.append(find_patches(cloud, fx, fx, g, cfg))
    finally:
        pm._sample_neighbourhoods = orig
    s = [x for x in seeds if x is not None]
    return out, s


def _assert_same_patches(ref, new):
    assert new.counts == ref.counts
    assert len(new) == len(ref)
    np.testing.assert_array_equal(new.support_points, ref.support_points)
    np.testing.assert_array_equal(new.don, ref.don)          # seeds: stages I-III unchanged
    np.testing.assert_array_equal(new.dong, ref.dong)
    for f in FIT_FIELDS:
        a, b = getattr(ref, f), getattr(new, f)
        np.testing.assert_allclose(b, a, rtol=FIT_RTOL, atol=1e-12, err_msg=f)


def test_compiled_kernels_are_active():
    """numba is a pinned requirement: the pipeline must run compiled here (else the tests below
    would compare the numpy steps with themselves)."""
    from terrain_perception import patches as pm
    assert pm.compiled_kernels_active()


def test_compiled_kernels_match_the_numpy_steps_on_bench_frames(bench_frames, kernel_selection):
    """Bench frames, as they are and with NaN / 0 / negative depths and holes: identical counts,
    seeds, neighbourhood sizes, DoN / DoNG; fitted poses, curvatures, radii and residuals within
    1e-9 relative."""
    pm = kernel_selection
    cfg, cam, frames = bench_frames
    rng = np.random.default_rng(11)
    total = 0
    for cloud, g in frames:
        for c in (cloud, _with_holes(cloud, rng)):
            (ref, new), seeds = _run_both(pm, c, cam.fx, g, cfg)
            assert len(seeds) == 2 and ref.counts['seeds'] > 50
            np.testing.assert_array_equal(seeds[1][0], seeds[0][0])
            np.testing.assert_array_equal(seeds[1][1], seeds[0][1])
            _assert_same_patches(ref, new)
            total += len(ref)
    assert total > 300
    # A read-only, column-major cloud (e.g. a message buffer view) gives the same patches.
    cloud, g = frames[0]
    odd = np.asfortranarray(cloud)
    odd.setflags(write=False)
    a, b = find_patches(cloud, cam.fx, cam.fy, g, cfg), find_patches(odd, cam.fx, cam.fy, g, cfg)
    assert a.counts == b.counts
    np.testing.assert_array_equal(b.vertex, a.vertex)


def test_compiled_median_and_neighbourhoods_are_bitwise_the_numpy_steps(kernel_selection):
    """The 2x2 median of scaled points (incl. blocks with 1-3 valid points, none, and valid z with
    a NaN or infinite x) and the neighbourhood search (same draws) give identical arrays."""
    pm = kernel_selection
    from terrain_perception import _patch_kernels as K
    rng = np.random.default_rng(4)
    h, w = 60, 80
    cam = PinholeCamera(w, h, 300.0, 310.0, 39.5, 29.5)
    cloud = cam.depth_to_points((0.5 + 0.01 * rng.random((h, w))).astype(np.float32))
    u = rng.random((h, w))
    cloud[u < 0.15] = np.nan
    cloud[(u >= 0.15) & (u < 0.2), 2] = 0.0
    cloud[(u >= 0.2) & (u < 0.25), 2] *= -1
    cloud[10:14, 20:24] = np.nan                                   # blocks with no valid point
    scale = (1.0 + 0.01 * rng.normal(size=(h, w))).astype(np.float32)
    with np.errstate(invalid='ignore', divide='ignore'):
        scale[~(cloud[..., 2] > 0)] = np.float32(np.inf)           # as the filter leaves them
    with np.errstate(invalid='ignore'):
        valid = np.isfinite(cloud[..., 2] * scale)
    ref = pm._median_2x2(cloud, scale)
    new = [np.empty((h // 2, w // 2), np.float32) for _ in range(3)]
    K.median_2x2_scaled(cloud, scale, *new)
    n_valid = valid.reshape(h // 2, 2, w // 2, 2).sum((1, 3))
    assert set(np.unique(n_valid)) == {0, 1, 2, 3, 4}
    for a, b in zip(ref, new):
        np.testing.assert_array_equal(b, a)
    odd = cloud.copy()
    odd[5, 7, 0], odd[30, 41, 1] = np.nan, np.inf                  # valid z, bad x or y
    odd[31, 41] = np.nan
    ref = pm._median_2x2(odd, scale)
    K.median_2x2_scaled(odd, scale, *new)
    for a, b in zip(ref, new):
        np.testing.assert_array_equal(b, a)
    # Neighbourhoods: the same generator state gives the same planes and counts.
    cfg = PatchConfig(patch_radius_m=0.02, max_neighbours=20, neighbour_draws=3)
    good = np.argwhere(valid)[::37][:15]
    seeds_full = good + 0.5
    seed_pts = (cloud[good[:, 0], good[:, 1]] * scale[good[:, 0], good[:, 1], None]).astype(
        np.float64)
    with np.errstate(invalid='ignore'):                        # (0 x inf at invalid points)
        nb_ref, mask = pm._sample_neighbourhoods(cloud, scale, seeds_full, seed_pts, 300.0,
                                                 310.0, cfg, np.random.default_rng(8))
    nb_new, n_nb = pm._sample_neighbourhoods(cloud, scale, seeds_full, seed_pts, 300.0, 310.0,
                                             cfg, np.random.default_rng(8), None, K)
    np.testing.assert_array_equal(nb_new, nb_ref)
    np.testing.assert_array_equal(n_nb, mask.sum(1))
    assert 0 < n_nb.min() and n_nb.max() <= cfg.max_neighbours


def test_compiled_integral_images_are_bitwise_opencvs(bench_frames, kernel_selection):
    """The integral images of a downsampled bench frame's crop (a strided view, as find_patches
    passes), with and without invalid points, equal IntegralMoments' OpenCV ones bit for bit."""
    pm = kernel_selection
    from terrain_perception import _patch_kernels as K
    cfg, cam, frames = bench_frames
    D = median_downsample_2x2(bilateral_filter_cloud(frames[1][0], cfg))
    planes = [np.ascontiguousarray(D[..., k]) for k in range(3)]
    box = np.s_[60:200, 30:290]
    for holes in (False, True):
        if holes:
            rng = np.random.default_rng(2)
            bad = rng.random(planes[2].shape) < 0.05
            planes[2][bad] = np.nan
            odd = rng.random(planes[2].shape) < 0.01                 # x NaN, z finite (off
            odd[::2] = False                                          # the offset's rows)
            planes[0][odd] = np.nan
        views = [p[box] for p in planes]
        ref = pm.IntegralMoments._from_planes(*views)
        new = pm.IntegralMoments._from_planes(*views, None, K)
        assert new.shape == ref.shape and np.array_equal(new.offset, ref.offset)
        assert np.isfinite(ref.offset).all()
        for a, b in zip(ref.ii, new.ii):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(b, a)
        rows, cols = np.array([5, 70, 139]), np.array([0, 100, 259])
        for a, b in zip(ref.window_normals(rows, cols, np.array([3, 8, 20])),
                        new.window_normals(rows, cols, np.array([3, 8, 20]))):
            np.testing.assert_array_equal(b, a)


def test_compiled_fit_matches_the_numpy_fit(kernel_selection):
    """fit_paraboloids with masks holding padding anywhere, 0-10 LM iterations, one shared and
    per-patch up vectors: the same fits within 1e-9 relative."""
    pm = kernel_selection
    rng = np.random.default_rng(21)
    kx, ky = rng.uniform(-15, 15, 40), rng.uniform(-15, 15, 40)
    pts, Rs, ts = _sample_paraboloids(rng, 40, 50, 0.03, 0.0008, kx, ky)
    mask = rng.random((40, 50)) > 0.3
    mask[:, :8] = True
    pts[~mask] = rng.normal(size=(np.count_nonzero(~mask), 3))    # padding: ignored
    for its, up in ((0, Rs[:, :, 2]), (1, [0.0, 0.0, 1.0]), (6, Rs[:, :, 2]), (10, -Rs[:, :, 2])):
        fits = []
        for compiled in (False, True):
            pm.use_compiled_kernels(compiled)
            fits.append(fit_paraboloids(pts, mask, up, iterations=its))
        a, b = fits
        np.testing.assert_array_equal(b.count, a.count)
        for f in ('vertex', 'R', 'kx', 'ky', 'rms_algebraic', 'rms_euclidean', 'radius'):
            np.testing.assert_allclose(getattr(b, f), getattr(a, f), rtol=FIT_RTOL, atol=1e-12,
                                       err_msg=f'{f}, {its} iterations')


def test_without_numba_the_numpy_steps_run_with_one_warning(kernel_selection, monkeypatch,
                                                            caplog):
    """numba missing: one logged warning, then the numpy steps (same results as selecting them);
    TERRAIN_PATCHES_NUMBA=0 selects them without a warning."""
    import sys
    import terrain_perception
    pm = kernel_selection
    cfg = PatchConfig(bilateral_sigma_depth_m=0.01, fixation_down_m=0.2, fixation_forward_m=0.16,
                      roi_radius_m=0.15, patch_radius_m=0.02, max_residual_m=0.002)
    cam = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    T = _camera_pose(0.2, 35.0)
    cloud = _plane_cloud(cam, T, lambda x, y: 0.01 * np.sin(20 * x) * np.cos(17 * y))
    g = T[:3, :3].T @ np.array([0, 0, -1.0])
    pm.use_compiled_kernels(False)
    ref = find_patches(cloud, cam.fx, cam.fy, g, cfg)
    assert len(ref) > 0
    monkeypatch.setitem(sys.modules, 'numba', None)                 # import numba fails
    monkeypatch.delitem(sys.modules, 'terrain_perception._patch_kernels', raising=False)
    monkeypatch.delattr(terrain_perception, '_patch_kernels', raising=False)
    with caplog.at_level('WARNING', logger='terrain_perception.patches'):
        assert pm.use_compiled_kernels(None) is False
        runs = [find_patches(cloud, cam.fx, cam.fy, g, cfg) for _ in range(2)]
    warnings = [r for r in caplog.records if 'numba is not available' in r.getMessage()]
    assert len(warnings) == 1
    for p in runs:
        assert p.counts == ref.counts
        np.testing.assert_array_equal(p.vertex, ref.vertex)
    with pytest.raises(ImportError):
        pm.use_compiled_kernels(True)
    monkeypatch.undo()
    caplog.clear()
    monkeypatch.setenv('TERRAIN_PATCHES_NUMBA', '0')
    assert pm.use_compiled_kernels(None) is False and not pm.compiled_kernels_active()
    monkeypatch.delenv('TERRAIN_PATCHES_NUMBA')
    assert pm.use_compiled_kernels(None) is True
    assert not caplog.records
