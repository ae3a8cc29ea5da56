"""ICP mapper core: localisation, guards, fine map, moving window, bad input."""

import dataclasses

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from terrain_perception import mapping as mp
from terrain_perception import raycast as rc
from terrain_perception.camera import PinholeCamera
from terrain_perception.grid import ELEVATION, OBSERVED, VARIANCE, GridMap
from terrain_perception.robot_model import camera_mount
from terrain_perception.transforms import angle_between, make_T, rpy_to_R

T_BC = camera_mount(np.array([0.14, 0.0, 0.05]), np.radians(35.0))
CAM = PinholeCamera.from_fov(160, 120, 50.0)


def bumpy(origin=(-0.5, -1.0), shape=(500, 400), res=0.005, n=120, seed=1):
    """Smooth random terrain: a sum of Gaussian bumps and dips."""
    rng = np.random.default_rng(seed)
    g = GridMap.empty(res, origin, shape)
    xs, ys = g.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    H = np.zeros_like(X)
    x0, y0 = origin
    x1, y1 = x0 + shape[0] * res, y0 + shape[1] * res
    for _ in range(n):
        cx, cy = rng.uniform(x0, x1), rng.uniform(y0, y1)
        s, h = rng.uniform(0.03, 0.08), rng.uniform(-0.03, 0.04)
        H += h * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * s * s))
    g[ELEVATION] = H
    return g


def periodic(period=0.08, amp=0.02):
    g = GridMap.empty(0.005, (-0.5, -1.0), (500, 400))
    xs, ys = g.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    g[ELEVATION] = amp * np.sin(2 * np.pi * X / period) * np.sin(2 * np.pi * Y / period)
    return g


@pytest.fixture(scope='module')
def terrain():
    g = bumpy()
    return g, rc.HeightFieldScene(g)


def cloud_at(scene, T_map_base, cam=CAM):
    return cam.depth_to_points(scene.depth_image(cam, T_map_base @ T_BC))


T0 = make_T(np.eye(3), [0.0, 0.0, 0.2])
T1 = make_T(rpy_to_R(0.01, -0.02, 0.05), [0.05, 0.01, 0.21])


# pixel strides scaled to the small test camera (the defaults suit the 512x480 robot camera)
CONFIG = dataclasses.replace(mp.MapperConfig(), coarse_stride_px=4, fine_stride_px=1)


def first_mapper(scene, config=CONFIG):
    m = mp.IcpMapper(config, T_BC)
    u = m.update(cloud_at(scene, T0), T0, 0.0)
    assert u.accepted and u.fused
    return m


def snapshot(m):
    return ({k: v.copy() for k, v in m.fine.s.items()}, m.fine.origin_xy.copy(),
            m.coarse_points(), m.T_map_odom.copy(), m.capture_poses()[1].copy(),
            m.stamp_s, dict(m.counters))


def assert_unchanged(m, snap):
    stats, origin, coarse, T_mo, poses, stamp, counters = snap
    for k, v in stats.items():
        np.testing.assert_array_equal(m.fine.s[k], v, err_msg=f'fine statistic {k} changed')
    np.testing.assert_array_equal(m.fine.origin_xy, origin)
    np.testing.assert_array_equal(m.coarse_points(), coarse)
    np.testing.assert_array_equal(m.T_map_odom, T_mo)
    np.testing.assert_array_equal(m.capture_poses()[1], poses)
    assert m.stamp_s == stamp
    assert dict(m.counters) == counters


def pose_error(T_est, T_true):
    return (np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]),
            np.degrees(angle_between(T_est[:3, :3], T_true[:3, :3])))


def test_icp_recovers_a_known_6dof_offset(terrain):
    _, scene = terrain
    # the offset is larger than 5 cm of walking could drift: open the guard, test the solver
    m = first_mapper(scene, dataclasses.replace(CONFIG, max_correction_floor_m=0.05))
    offset = make_T(rpy_to_R(*np.radians([0.5, -0.4, 0.8])), [0.015, -0.01, 0.005])
    prior = offset @ T1  # dead reckoning wrong by 1.9 cm and ~1 deg in all six axes
    e_prior = pose_error(prior, T1)
    assert e_prior[0] > 0.015 and e_prior[1] > 0.9
    u = m.update(cloud_at(scene, T1), prior, 1.0)
    assert u.accepted, u.reason
    err_m, err_deg = pose_error(u.T_map_base, T1)
    assert err_m < 1e-3, f'translation error {err_m * 1e3:.2f} mm'
    assert err_deg < 0.1, f'rotation error {err_deg:.3f} deg'
    # the correction re-anchors dead reckoning: the same odometry now maps to the truth
    err_m2, _ = pose_error(m.T_map_odom @ prior, T1)
    assert err_m2 < 1e-3


def test_alignment_forced_into_a_wrong_minimum_is_rejected():
    # a periodic terrain (period 14 cm); the body slipped 9.5 cm while dead reckoning says it
    # stood still, so the prior is 2/3 of a period off
    g = periodic(period=0.14, amp=0.03)
    scene = rc.HeightFieldScene(g)
    truth = make_T(np.eye(3), [0.095, 0.0, 0.0]) @ T0
    prior = T0
    # unguarded, ICP settles on the wrong copy of the pattern, with a convincing fit
    loose = dataclasses.replace(CONFIG, max_correction_floor_m=10.0,
                                max_rotation_floor_deg=180.0)
    m_loose = first_mapper(scene, loose)
    u_loose = m_loose.update(cloud_at(scene, truth), prior, 1.0)
    assert u_loose.accepted and u_loose.fitness > 0.9
    # (a minimum at least 5 cm from the truth: near the prior or a period away, depending on
    # the model's voxels)
    assert pose_error(u_loose.T_map_base, truth)[0] > 0.05, 'test needs a real wrong minimum'
    # guarded: the correction is far beyond what 0 m of walking can drift -> rejected
    m = first_mapper(scene)
    snap = snapshot(m)
    u = m.update(cloud_at(scene, truth), prior, 1.0)
    assert not u.accepted and not u.fused
    assert 'correction' in u.reason
    assert m.counters['rejected_correction'] == 1
    np.testing.assert_allclose(u.T_map_base, prior, atol=1e-12)  # the prior is kept
    stats, origin, coarse, T_mo, poses, _, _ = snap
    np.testing.assert_array_equal(m.coarse_points(), coarse)
    for k, v in stats.items():
        np.testing.assert_array_equal(m.fine.s[k], v)
    np.testing.assert_array_equal(m.T_map_odom, T_mo)
    np.testing.assert_array_equal(m.capture_poses()[1], poses)



def test_after_a_disturbance_the_slip_the_icp_measures_is_accepted(terrain):
    """The body slid 4 cm (a foot off a stone) while dead reckoning says it stood still. The
    drift guard rejects the ICP's 4 cm correction; after the IMU reported free fall
    (note_disturbance) the same capture is accepted at the true pose, once: the next capture
    is guarded as before."""
    _, scene = terrain
    truth = make_T(np.eye(3), [0.04, 0.0, 0.0]) @ T1
    results = {}
    for disturbed in (False, True):
        m = first_mapper(scene)
        if disturbed:
            m.note_disturbance(0.5)
        u = m.update(cloud_at(scene, truth), T1, 1.0)
        results[disturbed] = (u.accepted, pose_error(u.T_map_base, truth)[0],
                              m.counters['accepted_after_disturbance'], m)
    assert not results[False][0] and results[False][1] > 0.035
    accepted, err, n, m = results[True]
    assert accepted and err < 2e-3 and n == 1, results[True][:3]
    # the exception is spent: a second slip without a disturbance is refused again
    again = make_T(np.eye(3), [0.04, 0.0, 0.0]) @ truth
    u = m.update(cloud_at(scene, again), T1, 2.0)           # odometry: still standing
    assert not u.accepted and 'correction' in u.reason
    with pytest.raises(ValueError, match='not finite'):
        m.note_disturbance(float('nan'))

def _slip_walk(scene, config, slips, step_m=0.015):
    """Captures along a walk in +x whose dead reckoning misses ``slips[i]`` [m] of x motion
    (a slip the IMU did not see): ``(mapper, [(update, true pose), ...])``."""
    m = first_mapper(scene, config)
    out = []
    for i, slip in enumerate(slips, start=1):
        odom = make_T(np.eye(3), [step_m * i, 0.0, 0.0]) @ T1
        truth = make_T(np.eye(3), [slip, 0.0, 0.0]) @ odom
        out.append((m.update(cloud_at(scene, truth), odom, float(i)), truth))
    return m, out


def test_a_slip_measured_by_three_captures_in_a_row_is_accepted(terrain):
    """Dead reckoning missed a 4 cm slide and no IMU saw it. The drift guard refuses the
    ICP's 4 cm correction; the third capture in a row that measures the same offset (1.5 cm
    steps: 3 cm of travel) is accepted at the true pose, and the next one is aligned normally.
    With confirmation off all of them are refused."""
    _, scene = terrain
    m, ups = _slip_walk(scene, CONFIG, [0.04] * 4)
    assert [u.accepted for u, _ in ups] == [False, False, True, True], [u.reason for u, _ in ups]
    assert 'correction' in ups[0][0].reason and m.counters['accepted_confirmed'] == 1
    for u, truth in ups[2:]:
        assert pose_error(u.T_map_base, truth)[0] < 2e-3
    assert ups[3][0].correction_m < 5e-3          # re-anchored: no correction needed any more
    # a refused update still says what ICP measured
    assert pose_error(ups[0][0].T_map_base_icp, ups[0][1])[0] < 3e-3
    # walking slowly (4 mm per capture), the run grows until it spans confirm_min_travel_m
    slow, ups_slow = _slip_walk(scene, CONFIG, [0.04] * 5, step_m=0.004)
    assert [u.accepted for u, _ in ups_slow] == [False, False, False, True, True]
    off, ups_off = _slip_walk(scene, dataclasses.replace(CONFIG, confirm_captures=0), [0.04] * 4)
    assert not any(u.accepted for u, _ in ups_off)
    assert off.counters['rejected_correction'] == 4 and off.counters['accepted_confirmed'] == 0


def test_the_confirmed_pose_is_the_prior_moved_by_the_mean_shift_and_turned_in_place():
    m = mp.IcpMapper(CONFIG, T_BC)
    prior = make_T(rpy_to_R(0.0, 0.0, np.radians(10.0)), [1.5, 0.5, 0.2])
    for yaw_deg, dy in ((1.0, 0.01), (2.0, 0.02), (3.0, 0.03)):
        C = make_T(rpy_to_R(0.0, 0.0, np.radians(yaw_deg)), [0.03, dy, 0.0])
        m._refused.append((C, np.eye(4)))
    T = m._mean_correction(prior)
    # 1.6 m from the map origin: a 2 deg turn about it would move the body by 5.6 cm
    np.testing.assert_allclose(T[:3, 3], [1.53, 0.52, 0.2], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], rpy_to_R(0.0, 0.0, np.radians(12.0)), atol=1e-9)


def test_corrections_that_disagree_or_a_robot_standing_still_confirm_nothing(terrain):
    """Corrections that move from capture to capture (3 cm apart, over the 2 cm tolerance) are not
    a slip; the same offset seen from the same place (no travel) repeats any wrong minimum, so
    it does not confirm either; nor does a slip larger than max_correction_confirmed_m."""
    _, scene = terrain
    m, ups = _slip_walk(scene, CONFIG, [0.04, 0.07, 0.04, 0.07])
    assert not any(u.accepted for u, _ in ups) and m.counters['accepted_confirmed'] == 0
    m, ups = _slip_walk(scene, CONFIG, [0.04] * 4, step_m=0.0)
    assert not any(u.accepted for u, _ in ups) and m.counters['accepted_confirmed'] == 0
    small = dataclasses.replace(CONFIG, max_correction_confirmed_m=0.03)
    m, ups = _slip_walk(scene, small, [0.04] * 4)
    assert not any(u.accepted for u, _ in ups) and m.counters['accepted_confirmed'] == 0


def test_misfit_alignments_rejected_by_fitness_and_by_residual(terrain):
    _, scene = terrain
    # (the guards alone: relocalisation off; a misfit would start it, tested below)
    loose = dataclasses.replace(CONFIG, max_correction_floor_m=10.0,
                                max_rotation_floor_deg=180.0, relocalise_captures=0)
    # far off: ICP ends where few points find a partner
    m = first_mapper(scene, loose)
    prior = make_T(rpy_to_R(0.0, 0.0, np.radians(40.0)), [0.2, 0.1, 0.0]) @ T1
    u = m.update(cloud_at(scene, T1), prior, 1.0)
    assert pose_error(u.T_map_base, T1)[0] > 0.05 and not u.accepted
    assert m.counters['rejected_fitness'] == 1, u.reason
    # after a few good alignments, an alignment whose residual is several times the noise floor
    # is refused: a cloud of other rocks seen from near the prior (most points find a partner,
    # none fits). A wrong minimum of the same terrain would do too, but where ICP ends from a
    # 25-35 deg prior differs between CPUs (session 47: this one converged from 25 deg on an
    # Intel Xeon and not on an AMD EPYC), so the test does not rest on one.
    m = first_mapper(scene, dataclasses.replace(loose, degeneracy_noise_gain=0.0))
    for k, dx in enumerate((0.01, 0.02, 0.03)):
        T = make_T(np.eye(3), [dx, 0.0, 0.0]) @ T0
        assert m.update(cloud_at(scene, T), T, 1.0 + k).accepted
    assert m.rmse_limit() < 0.003
    snap = snapshot(m)
    other_rocks = rc.HeightFieldScene(bumpy(seed=2))
    prior = make_T(rpy_to_R(0.0, 0.0, np.radians(5.0)), [0.03, -0.02, 0.0]) @ T1
    u = m.update(cloud_at(other_rocks, T1), prior, 5.0)
    assert not u.accepted and u.fitness >= loose.min_fitness
    assert m.counters['rejected_rmse'] == 1, u.reason
    snap[-1]['rejected_rmse'] = 1
    assert_unchanged(m, snap)


def test_fine_map_of_known_height_field_from_known_poses(terrain):
    g, scene = terrain
    poses = [make_T(rpy_to_R(0.0, 0.0, yaw), [x, y, 0.2])
             for x, y, yaw in [(0.0, 0.0, 0.0), (0.1, 0.05, 0.1), (0.2, -0.05, -0.1)]]
    for estimator, tol in (('plane', 0.5e-3), ('mean', 1.0e-3)):
        m = mp.IcpMapper(dataclasses.replace(CONFIG, fine_estimator=estimator),
                         T_BC)
        for k, T in enumerate(poses):
            fine, src = m.prepare(cloud_at(scene, T))
            m.fuse(fine, src, T @ T_BC, T, float(k))
        grid = m.fine_grid()
        h = grid[ELEVATION]
        obs = grid[OBSERVED] > 0
        assert obs.sum() > 5000
        xs, ys = grid.cell_centers()
        X, Y = np.meshgrid(xs, ys, indexing='ij')
        truth = rc.interpolate_height(g, np.stack([X, Y], -1))
        both = obs & np.isfinite(truth)
        rmse = np.sqrt(np.mean((h[both] - truth[both]) ** 2))
        assert rmse < tol, f'{estimator}: height RMSE {rmse * 1e3:.2f} mm'
        # empty cells stay unknown; statistics are consistent
        assert np.isnan(h[~obs]).all() and (grid['count'][~obs] == 0).all()
        assert (grid['min'][obs] <= grid['max'][obs]).all()
        assert (grid[VARIANCE][obs] >= 0).all() and (grid['count'][obs] >= 1).all()
        assert np.isin(grid['last_seen'][obs], [0.0, 1.0, 2.0]).all()
        assert np.any(grid['last_seen'][obs] == 2.0) and np.any(grid['last_seen'][obs] == 0.0)
        # every capture's camera pose is kept with the map
        stamps, cams = m.capture_poses()
        np.testing.assert_array_equal(stamps, [0.0, 1.0, 2.0])
        np.testing.assert_allclose(cams, [T @ T_BC for T in poses])
        assert len(grid.metadata['capture_poses']) == 3


def test_fine_map_shift_keeps_world_positions():
    f = mp.FineHeightMap(0.01, (50, 40), (1.0, 2.0))
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(1.0, 1.5, 5000), rng.uniform(2.0, 2.4, 5000),
                rng.uniform(0, 0.1, 5000)]
    f.add(pts, 1.0)
    before = f.to_grid()
    f.shift(7, -3)
    after = f.to_grid()
    assert after.origin_xy == pytest.approx((1.07, 1.97))
    probe = np.c_[rng.uniform(1.08, 1.49, 500), rng.uniform(2.0, 2.36, 500)]
    np.testing.assert_array_equal(after.sample(ELEVATION, probe),
                                  before.sample(ELEVATION, probe))
    assert np.isnan(after[ELEVATION][-7:, :]).all() and np.isnan(after[ELEVATION][:, :3]).all()


def test_memory_stays_bounded_over_a_long_walk():
    g = bumpy(origin=(-0.5, -0.6), shape=(950, 120), res=0.01, n=450, seed=3)
    scene = rc.HeightFieldScene(g)
    cam = PinholeCamera.from_fov(128, 96, 50.0)
    cfg = dataclasses.replace(CONFIG, fine_size_m=1.5, coarse_radius_m=1.0,
                              recenter_distance_m=0.2, max_capture_poses=30)
    m = mp.IcpMapper(cfg, T_BC)
    mem, npts = [], []
    xs = np.arange(0.0, 8.0, 0.1)
    for k, x in enumerate(xs):
        T = make_T(np.eye(3), [x, 0.0, 0.2])
        # fuse at the true pose: this test is about the moving window, not localisation
        fine, src = m.prepare(cloud_at(scene, T, cam))
        m.fuse(fine, src, T @ T_BC, T, float(k))
        mem.append(m.memory_bytes)
        npts.append(len(m.coarse_points()))
    assert m.counters['recentred'] > 15
    assert m.fine.shape == (150, 150)
    grid = m.fine_grid()
    cx, cy = grid.center_xy
    assert abs(cx - xs[-1]) <= 0.2 + 0.01 and abs(cy) <= 0.2 + 0.01
    # the coarse model only holds points near the robot
    pts = m.coarse_points()
    assert np.linalg.norm(pts[:, :2] - [xs[-1], 0.0], axis=1).max() <= 1.0 + 1e-9
    assert len(m.capture_poses()[0]) <= 30
    first, last = max(mem[: len(mem) // 4]), max(mem[len(mem) // 2:])
    assert last <= 1.25 * first, f'memory grew from {first} to {last} bytes'
    assert max(npts[len(npts) // 2:]) <= 1.25 * max(npts[: len(npts) // 4])
    # after many moves the map still matches the terrain where it was observed
    xs_c, ys_c = grid.cell_centers()
    X, Y = np.meshgrid(xs_c, ys_c, indexing='ij')
    truth = rc.interpolate_height(g, np.stack([X, Y], -1))
    h = grid[ELEVATION]
    ok = np.isfinite(h) & np.isfinite(truth)
    assert ok.sum() > 1000
    assert np.sqrt(np.mean((h[ok] - truth[ok]) ** 2)) < 1e-3


@pytest.mark.parametrize('bad, match', [
    (np.zeros((0, 3), np.float32), 'empty'),
    (np.full((120, 160, 3), np.nan, np.float32), 'no finite point'),
    (np.zeros((120, 160, 4), np.float32), 'shape'),
    (np.zeros((100, 2), np.float32), 'shape'),
    (np.ones((120, 160, 3), np.int16), 'floating'),
    (np.tile(np.array([0.0, 0.0, 0.5], np.float32), (20, 1)), 'valid points'),
])
def test_bad_clouds_leave_the_map_unchanged(terrain, bad, match):
    _, scene = terrain
    m = first_mapper(scene)
    snap = snapshot(m)
    with pytest.raises(ValueError, match=match):
        m.update(bad, T1, 1.0)
    assert_unchanged(m, snap)


def test_bad_poses_and_stamps_leave_the_map_unchanged(terrain):
    _, scene = terrain
    m = first_mapper(scene)
    m.update(cloud_at(scene, T1), T1, 5.0)
    snap = snapshot(m)
    good = cloud_at(scene, T1)
    nan_pose = T1.copy()
    nan_pose[0, 3] = np.nan
    skew = T1.copy()
    skew[:3, :3] *= 1.5
    cases = [((good, T1, 4.0), 'older than the map'),
             ((good, T1, float('nan')), 'stamp'),
             ((good, nan_pose, 6.0), 'finite 4x4'),
             ((good, skew, 6.0), 'orthonormal'),
             ((good, np.eye(3), 6.0), 'finite 4x4')]
    for args, match in cases:
        with pytest.raises(ValueError, match=match):
            m.update(*args)
        assert_unchanged(m, snap)
    with pytest.raises(ValueError, match='up vector'):
        m.update(good, T1, 6.0, up_camera=np.zeros(3))
    assert_unchanged(m, snap)


def test_odometry_gate_and_pose_buffer():
    gate = mp.OdometryGate(max_speed_m_s=1.0, max_yaw_rate_deg_s=90.0)
    gate.check(0.0, T0)
    gate.check(0.1, make_T(np.eye(3), [0.05, 0.0, 0.2]))
    with pytest.raises(ValueError, match='back in time'):
        gate.check(0.05, T0)
    with pytest.raises(ValueError, match='jumped'):
        gate.check(0.2, make_T(np.eye(3), [0.6, 0.0, 0.2]))
    with pytest.raises(ValueError, match='turned'):
        gate.check(0.2, make_T(rpy_to_R(0, 0, np.radians(40)), [0.06, 0.0, 0.2]))
    gate.check(0.2, make_T(np.eye(3), [0.07, 0.0, 0.2]))  # rejected samples were not kept

    buf = mp.PoseBuffer(max_len=5, max_extrapolation_s=0.1)
    buf.add(1.0, make_T(np.eye(3), [0.0, 0.0, 0.0]))
    buf.add(2.0, make_T(rpy_to_R(0, 0, 0.2), [1.0, 2.0, 0.0]))
    mid = buf.at(1.25)
    np.testing.assert_allclose(mid[:3, 3], [0.25, 0.5, 0.0])
    np.testing.assert_allclose(mid[:3, :3], rpy_to_R(0, 0, 0.05), atol=1e-12)
    with pytest.raises(ValueError, match='back in time'):
        buf.add(1.5, T0)
    with pytest.raises(ValueError, match='stale'):
        buf.at(2.5)
    with pytest.raises(ValueError, match='as old'):
        buf.at(0.5)


def test_roll_pitch_priors(terrain):
    _, scene = terrain
    # a plane seen by the camera gives the up direction in the camera frame
    flat = GridMap.empty(0.01, (-1.0, -1.0), (300, 200))
    flat[ELEVATION] = np.zeros(flat.shape)
    T = make_T(rpy_to_R(0.03, -0.02, 0.4), [0.0, 0.0, 0.2])
    pts = mp.valid_points(rc.raycast_points(flat, CAM, T @ T_BC))
    up = mp.ground_plane_up(pts, 0.002, 0.5)
    R_map_cam = (T @ T_BC)[:3, :3]
    assert np.degrees(np.arccos(np.clip((R_map_cam @ up)[2], -1, 1))) < 0.05
    # levelling a prior with 3 deg of roll error restores roll/pitch and keeps yaw
    tilted = rpy_to_R(np.radians(3.0), 0.0, 0.0) @ R_map_cam
    levelled = mp.level_rotation(tilted, up)
    assert np.degrees(angle_between(levelled, R_map_cam)) < 0.05
    # the mapper applies the gravity prior to its first capture
    cfg = dataclasses.replace(CONFIG, use_gravity_prior=True)
    m = mp.IcpMapper(cfg, T_BC)
    prior = make_T(rpy_to_R(np.radians(3.0), 0, 0)) @ T0
    u = m.update(cloud_at(scene, T0), prior, 0.0, up_camera=(T0 @ T_BC)[:3, :3].T @ [0, 0, 1])
    assert pose_error(u.T_map_base, T0)[1] < 0.05


def test_imu_attitude_prior_follows_a_slip_the_odometry_missed(terrain):
    # The body pivots 10 deg in yaw and pitches 3 deg in place (a foot slip); dead reckoning
    # still says T0. The IMU's attitude change since the first capture turns the prior.
    _, scene = terrain
    slip = rpy_to_R(0.0, np.radians(3.0), np.radians(10.0))
    truth = make_T(slip, T0[:3, 3])
    cloud = cloud_at(scene, truth)
    blind = first_mapper(scene, dataclasses.replace(CONFIG, use_imu_rotation_prior=False))
    u = blind.update(cloud, T0, 1.0, attitude=slip)
    assert not u.accepted or pose_error(u.T_map_base, truth)[1] > 5.0
    cfg = dataclasses.replace(CONFIG, use_imu_rotation_prior=True)
    m = mp.IcpMapper(cfg, T_BC)
    assert m.update(cloud_at(scene, T0), T0, 0.0, attitude=np.eye(3)).accepted
    snap = snapshot(m)
    for bad in (np.full((3, 3), np.nan), 2.0 * np.eye(3)):
        with pytest.raises(ValueError, match='attitude'):
            m.update(cloud, T0, 1.0, attitude=bad)
        assert_unchanged(m, snap)
    u = m.update(cloud, T0, 1.0, attitude=slip)
    assert u.accepted, u.reason
    err_m, err_deg = pose_error(u.T_map_base, truth)
    # (2.0 mm with the fixed-grid coarse model, 1.7 mm with Open3D's voxels)
    assert err_m < 2.5e-3 and err_deg < 0.2, (err_m, err_deg)
    # the correction re-anchors dead reckoning on the turned pose
    assert pose_error(m.T_map_odom @ T0, truth)[1] < 0.2


def test_node_yaml_holds_valid_mapper_parameters():
    import yaml
    from pathlib import Path
    from terrain_perception.config import load_config
    path = Path(__file__).resolve().parents[1] / 'config' / 'icp_mapper.yaml'
    section = yaml.safe_load(path.read_text())['icp_mapper']['ros__parameters']
    known = {f.name for f in dataclasses.fields(mp.MapperConfig)} | {
        'robot', 'map_frame', 'base_frame', 'use_coarse_cloud', 'odom_buffer_size',
        'odom_max_extrapolation_s', 'odom_max_speed_m_s', 'odom_max_yaw_rate_deg_s',
        'coarse_publish_every', 'diagnostics_period_s', 'self_filter_margin_m',
        'self_filter_max_gap_s', 'model_after_plan', 'model_wait_max_s'}
    assert set(section) <= known, set(section) - known
    cfg = load_config(mp.MapperConfig, path, 'icp_mapper')  # type and range checked
    assert cfg.fine_resolution_m == 0.01


def stereo_noise(cloud, fb, sigma_d, rng):
    """Scale each point along its ray by a depth error of sigma_z = Z^2 sigma_d / (f b)."""
    z = cloud[..., 2]
    dz = rng.normal(size=z.shape) * z * z * sigma_d / fb
    return cloud * ((z + dz) / z)[..., None]


def flat_scene():
    """A level plane: only z, roll and pitch are observable on it."""
    g = GridMap.empty(0.005, (-0.5, -1.0), (500, 400))
    g[ELEVATION] = np.zeros(g.shape)
    return rc.HeightFieldScene(g)


def test_flat_ground_keeps_the_prior_in_x_y_yaw():
    """On a plane only z, roll and pitch are observable: ICP must correct those and leave x, y
    and yaw at the prior, even with stereo-like depth noise tilting the model normals."""
    scene = flat_scene()
    rng = np.random.default_rng(4)
    fb = CAM.fx * 0.03
    cfg = dataclasses.replace(CONFIG, disparity_sigma_px=0.15)
    for gain, expect_kept in ((1.0, True), (0.0, False)):
        m = mp.IcpMapper(dataclasses.replace(cfg, degeneracy_noise_gain=gain), T_BC, fb)
        assert m.update(stereo_noise(cloud_at(scene, T0), fb, 0.15, rng), T0, 0.0).accepted
        # prior off in every direction: x, y, yaw (unobservable) and z, roll, pitch
        prior = make_T(rpy_to_R(0.01, -0.012, 0.03), [0.02, -0.015, 0.006]) @ T1
        u = m.update(stereo_noise(cloud_at(scene, T1), fb, 0.15, rng), prior, 1.0)
        cam, cam_prior, cam_true = u.T_map_camera, prior @ T_BC, T1 @ T_BC
        # rotation about the map's z axis between the estimate and the prior
        yaw = Rotation.from_matrix(cam[:3, :3] @ cam_prior[:3, :3].T).as_rotvec()[2]
        if not expect_kept:
            # without the noise floor the noisy normals pass as constraints in x, y or yaw
            assert u.n_degenerate < 3
            continue
        assert u.accepted and u.n_degenerate == 3, (u.n_degenerate, u.min_information,
                                                    u.information_limit)
        assert m.counters['degenerate_alignments'] == 1
        assert m.counters['directions_kept_at_prior'] == 3
        # (noisy normals mix a little of x, y into the roll / pitch eigenvectors)
        np.testing.assert_allclose(cam[:2, 3], cam_prior[:2, 3], atol=3e-3)
        assert abs(np.degrees(yaw)) < 0.3  # prior 1.7 deg off the truth
        # the observable ones go to the truth: height, and the up axis (roll, pitch)
        assert abs(cam[2, 3] - cam_true[2, 3]) < 3e-3  # prior 6 mm off
        def tilt(T):
            return np.arccos(np.clip(T[2, :3] @ cam_true[2, :3], -1, 1))
        assert tilt(cam) < 0.5 * tilt(cam_prior)


def test_noisy_flat_views_converge_in_few_iterations():
    """On flat ground with stereo noise, ICP slides along x, y and yaw, the directions the
    view does not constrain, by a fraction of a millimetre per iteration, and its
    correspondences trade places: stopping on the step alone took 33-52 iterations per
    capture here (the cap is 30 per phase). The first phase (only there for the residual's
    noise level) ends when that residual settles and either phase ends on a 2-cycle: at most
    25 iterations a capture, and the same outcome as the flat-ground test above: the
    observable height to the truth, x and y at the prior."""
    scene = flat_scene()
    rng = np.random.default_rng(4)
    fb = CAM.fx * 0.03
    m = mp.IcpMapper(dataclasses.replace(CONFIG, disparity_sigma_px=0.15), T_BC, fb)
    iterations = []
    real = mp.constrained_icp

    def counted(*args, **kwargs):
        res = real(*args, **kwargs)
        iterations.append(res.iterations)
        return res
    with pytest.MonkeyPatch.context() as mpatch:
        mpatch.setattr(mp, 'constrained_icp', counted)
        m.update(stereo_noise(cloud_at(scene, T0), fb, 0.15, rng), T0, 0.0)
        for k in range(1, 8):
            T = make_T(rpy_to_R(0.01, -0.02, 0.05 + 0.01 * k), [0.02 * k, 0.01, 0.21])
            prior = make_T(rpy_to_R(0.004, -0.005, 0.01), [0.01, -0.008, 0.004]) @ T
            u = m.update(stereo_noise(cloud_at(scene, T), fb, 0.15, rng), prior, float(k))
            assert u.accepted and u.n_degenerate == 3
            cam, cam_prior = u.T_map_camera, prior @ T_BC
            np.testing.assert_allclose(cam[:2, 3], cam_prior[:2, 3], atol=3e-3)
            assert abs(cam[2, 3] - (T @ T_BC)[2, 3]) < 3e-3      # prior 4 mm off
    assert len(iterations) == 7 and max(iterations) <= 25, iterations


def test_relocalisation_on_flat_ground_keeps_the_prior():
    """After a disturbance the mapper also aligns from starts 5 and 10 cm around the prior
    (multi_start_icp). On a plane every shift fits as well (to stereo noise), so it must keep
    the prior's ICP: x and y stay at the prior."""
    scene = flat_scene()
    rng = np.random.default_rng(5)
    fb = CAM.fx * 0.03
    m = mp.IcpMapper(dataclasses.replace(CONFIG, disparity_sigma_px=0.15), T_BC, fb)
    assert m.update(stereo_noise(cloud_at(scene, T0), fb, 0.15, rng), T0, 0.0).accepted
    m.note_disturbance(0.5)
    prior = make_T(np.eye(3), [0.02, -0.015, 0.0]) @ T1
    u = m.update(stereo_noise(cloud_at(scene, T1), fb, 0.15, rng), prior, 1.0)
    assert u.accepted and u.multi_start == 0, (u.reason, u.multi_start)
    assert m.counters['multi_start_alignments'] == 1 and m.counters['multi_start_moved'] == 0
    np.testing.assert_allclose(u.T_map_base[:2, 3], prior[:2, 3], atol=3e-3)


@pytest.fixture(scope='module')
def stones_walk():
    """FROG-I's depth clouds along 1 m of stones-15cm (the ICP benchmark's sequence, half-size
    images, 10 cm steps) with the true poses."""
    import argparse
    from terrain_perception.bench import icp as icp_bench
    p = argparse.ArgumentParser()
    icp_bench.add_arguments(p)
    args = p.parse_args(['--terrain', 'stones-15cm', '--robot', 'frog', '--start-x', '1.2',
                         '--distance', '1.0'])
    args.quick = True
    return icp_bench.build_sequence(args)


@pytest.mark.parametrize('slip', [(0.0, 0.07), (-0.05, -0.05)])
def test_relocalisation_finds_a_slide_beyond_the_icp_basin_on_stones(stones_walk, slip):
    """FROG-I slid 7 cm on the stones; dead reckoning missed it, the IMU saw the drop
    (note_disturbance). ICP from the prior ends in a wrong minimum about 7 cm off (its basin
    is ~3 cm); the relocalisation's starts around the prior find the true pose, and the
    capture is accepted there. Without disturbance or refusal, no multi-start runs."""
    seq = stones_walk
    T_true, clouds, k = seq['T_true'], seq['clouds'], 6
    errors = {}
    for captures in (5, 0):
        m = mp.IcpMapper(dataclasses.replace(seq['config'], relocalise_captures=captures),
                         seq['T_bc'])
        for j in range(k):
            assert m.update(clouds[j], T_true[j], float(j)).multi_start == -1
        odom = make_T(np.eye(3), [-slip[0], -slip[1], 0.0]) @ T_true[k]
        m.note_disturbance(k - 0.5)
        u = m.update(clouds[k], odom, float(k))
        errors[captures] = (u.accepted, u.multi_start,
                            float(np.linalg.norm(u.T_map_base[:2, 3] - T_true[k][:2, 3])))
    accepted, start, err = errors[5]
    assert accepted and start > 0 and err < 3e-3, errors
    assert errors[0][1] == -1 and errors[0][2] > 0.05, errors


def test_relocalisation_recovers_an_unseen_slide_on_stones(stones_walk):
    """From the fifth capture on, dead reckoning misses a 7 cm slide and no IMU reported it.
    ICP from the prior is a misfit (residual), which starts the relocalisation on that capture:
    it measures the slide, the drift guard refuses it twice and the third capture confirms it;
    from then on the estimate is within 1 cm. Without relocalisation every capture is refused
    as a misfit (then for fitness, the robot walking off the model) and stays 7 cm off."""
    seq = stones_walk
    T_true, clouds = seq['T_true'], seq['clouds']
    runs = {}
    for captures in (5, 0):
        m = mp.IcpMapper(dataclasses.replace(seq['config'], relocalise_captures=captures),
                         seq['T_bc'])
        ups = []
        for j, cloud in enumerate(clouds):
            slip = 0.07 if j >= 4 else 0.0
            odom = make_T(np.eye(3), [0.0, -slip, 0.0]) @ T_true[j]
            u = m.update(cloud, odom, float(j))
            ups.append((u, float(np.linalg.norm(u.T_map_base[:2, 3] - T_true[j][:2, 3]))))
        runs[captures] = (m, ups)
    m, ups = runs[5]
    assert [u.accepted for u, _ in ups[4:7]] == [False, False, True], [u.reason for u, _ in ups]
    assert all('correction' in u.reason and u.multi_start > 0 for u, _ in ups[4:6])
    assert ups[6][0].confirmed and m.counters['multi_start_moved'] >= 3
    assert max(e for _, e in ups[6:]) < 0.01, [e for _, e in ups]
    m_off, ups_off = runs[0]
    assert not any(u.accepted for u, _ in ups_off[4:])
    assert min(e for _, e in ups_off[4:]) > 0.06
    assert m_off.counters['multi_start_alignments'] == 0


def test_depth_weights_follow_the_stereo_noise_model():
    fb, sd, floor = 12.8, 0.15, 1e-4
    w = mp.depth_weights(np.array([0.3, 0.6, 1.2]), fb, sd, floor)
    sz = np.array([0.3, 0.6, 1.2]) ** 2 * sd / fb
    np.testing.assert_allclose(w, 1 / (sz ** 2 + floor ** 2))
    assert w[0] / w[1] == pytest.approx(16, rel=0.02)  # sigma_z ~ Z^2: weight ~ Z^-4
    np.testing.assert_array_equal(mp.depth_weights(np.array([0.3, 1.2]), None, sd, floor), 1.0)
    np.testing.assert_array_equal(mp.depth_weights(np.array([0.3, 1.2]), fb, 0.0, floor), 1.0)
    # a cell seen once near (precise) and many times far (noisy) follows the near sample
    f = mp.FineHeightMap(0.01, (4, 4), (0.0, 0.0))
    f.add(np.array([[0.015, 0.015, 0.100]]), 0.0, mp.depth_weights(np.array([0.3]), fb, sd,
                                                                     floor))
    far = np.c_[np.full(4, 0.015), np.full(4, 0.015), np.full(4, 0.140)]
    f.add(far, 1.0, mp.depth_weights(np.full(4, 1.2), fb, sd, floor))
    wn, wf = w[0], 4 * w[2]
    assert f.heights()[1, 1] == pytest.approx((0.1 * wn + 0.14 * wf) / (wn + wf))
    assert f.heights()[1, 1] < 0.101 and f.s['n'][1, 1] == 5  # the plain mean: 0.132


def test_a_capture_with_no_point_for_the_model_is_fused_without_one(terrain):
    """A capture none of whose points may enter the coarse model (a tumbling robot's camera
    sees only ground above its body or beyond the ICP range: stones-15cm blind seed 104 at
    4490a9f) leaves the model as it was; the mapper raised on the empty cloud and the node
    died. The capture's pose is still recorded."""
    g, scene = terrain
    m = mp.IcpMapper(CONFIG, T_BC)
    fine, src = m.prepare(cloud_at(scene, T0))
    m.fuse(fine, src, T0 @ T_BC, T0, 0.0)
    model = m.coarse_points()
    assert len(model) > 100
    far = np.array([[0.0, 0.0, 5.0], [0.1, 0.0, 6.0]])     # camera frame, past every range
    m.fuse(far, far, T1 @ T_BC, T1, 1.0)
    np.testing.assert_array_equal(m.coarse_points(), model)
    assert len(m.capture_poses()[0]) == 2


def test_points_seen_through_known_ground_are_not_fused(terrain):
    """Stereo mismatches far below the terrain. After a first capture, a second one holds a
    block of true points and a patch of points pushed 30 cm down along their rays (as a
    too-small disparity does). With the line-of-sight check the cells where the bad points
    land keep the truth (their rays pass through ground the map has seen); without it those
    cells sink."""
    g, scene = terrain
    results = {}
    for tol in (0.1, 0.0):
        # (the lone-cell filter off: it hides such sunk cells too, and this test is the ray's)
        m = mp.IcpMapper(dataclasses.replace(CONFIG, line_of_sight_tolerance_m=tol,
                                             isolated_max_count=0), T_BC)
        fine, src = m.prepare(cloud_at(scene, T0))
        m.fuse(fine, src, T0 @ T_BC, T0, 0.0)
        full = cloud_at(scene, T1)
        h, w = full.shape[:2]
        cloud = np.full_like(full, np.nan)
        cloud[-25:, :] = full[-25:, :]                            # true near-field points
        patch = np.s_[h // 2:h // 2 + 6, w // 2 - 3:w // 2 + 3]
        good = full[patch]
        cam_T = T1 @ T_BC
        up_cam = cam_T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        unit = good / np.linalg.norm(good, axis=-1, keepdims=True)
        cloud[patch] = good + (0.3 / -(unit @ up_cam))[..., None] * unit
        bad_world = cloud[patch].reshape(-1, 3) @ cam_T[:3, :3].T + cam_T[:3, 3]
        seen0 = np.isfinite(m.fine_grid().sample(ELEVATION, bad_world[:, :2]))
        assert seen0.sum() >= 12                     # the first capture observed most of them
        fine, src = m.prepare(cloud)
        m.fuse(fine, src, cam_T, T1, 1.0)
        got = m.fine_grid().sample(ELEVATION, bad_world[seen0, :2])
        truth = rc.interpolate_height(g, bad_world[seen0, :2])
        results[tol] = (float(np.max(np.abs(got - truth))),
                        int(m.counters['points_below_line_of_sight']))
    assert results[0.1][0] < 0.005 and results[0.1][1] == 36, results
    assert results[0.0][0] > 0.03 and results[0.0][1] == 0, results



def test_points_above_the_body_are_not_fused(terrain):
    """Stereo mismatches at the near end of the disparity search: in the top image rows, where
    the floor is far, a patch of pixels matched too close puts points a few centimetres under
    the camera (the 12-20 cm phantom cells of LittleDog's rocks-6cm loop maps). Above the
    body origin they are not fused, the cells keep no phantom; with the check off (100 m)
    they stand 10+ cm above the terrain."""
    g, scene = terrain
    results = {}
    for limit in (0.0, 100.0):
        m = mp.IcpMapper(dataclasses.replace(CONFIG, max_height_above_base_m=limit,
                                             isolated_max_count=0), T_BC)
        full = cloud_at(scene, T0)
        h, w = full.shape[:2]
        cloud = full.copy()
        patch = np.s_[2:8, w // 2 - 4:w // 2 + 4]          # top rows: far floor
        unit = full[patch] / np.linalg.norm(full[patch], axis=-1, keepdims=True)
        cloud[patch] = 0.12 * unit                           # 12 cm from the camera
        cam_T = T0 @ T_BC
        bad_world = cloud[patch].reshape(-1, 3) @ cam_T[:3, :3].T + cam_T[:3, 3]
        assert np.all(bad_world[:, 2] > T0[2, 3])           # above the body origin
        fine, src = m.prepare(cloud)
        m.fuse(fine, src, cam_T, T0, 0.0)
        got = m.fine_grid().sample(ELEVATION, bad_world[:, :2])
        truth = rc.interpolate_height(g, bad_world[:, :2])
        err = got - truth
        results[limit] = (float(np.nanmax(err)) if np.isfinite(err).any() else None,
                          int(m.counters['points_above_body']))
        # the rest of the capture is fused either way
        assert np.isfinite(m.fine_grid()[ELEVATION]).sum() > 500
    n_bad = 6 * 8
    assert results[0.0][1] == n_bad, results
    assert results[0.0][0] is None or results[0.0][0] < 0.01, results
    assert results[100.0][1] == 0 and results[100.0][0] > 0.1, results

def _noisy_capture(rng, n, origin=(0.0, 0.0), size=(0.6, 0.5)):
    """Seeded scene for the fine-map kernels: a sloped, bumpy surface with noise, samples off
    the window, a few gross outliers (the cell gate drops them) and clustered cells."""
    x = rng.uniform(origin[0] - 0.05, origin[0] + size[0] + 0.05, n)
    y = rng.uniform(origin[1] - 0.05, origin[1] + size[1] + 0.05, n)
    z = 0.1 + 0.05 * x - 0.03 * y + 0.01 * np.sin(40 * x) + rng.normal(0, 0.002, n)
    z[rng.random(n) < 0.01] += rng.choice([-0.2, 0.15], int(np.sum(rng.random(n) < 0.01)) or 1)[0]
    return np.c_[x, y, z]


@pytest.mark.parametrize('gate', [0.0, 0.015])
@pytest.mark.parametrize('weighted', [False, True])
def test_fine_map_kernels_equal_the_numpy_code(gate, weighted):
    """The compiled FineHeightMap.add / rays_below give bitwise the statistics and masks of the
    numpy reference (same float64 operations in the same order), over several captures, a
    window shift and weights; tolerance 0."""
    from terrain_perception import _mapping_kernels  # noqa: F401 (numba is a dependency)
    rng = np.random.default_rng(7)
    caps = [_noisy_capture(rng, 20000) for _ in range(4)]
    wts = [mp.depth_weights(rng.uniform(0.2, 1.5, len(c)), 12.8, 0.15, 0.003) if weighted
           else None for c in caps]
    maps, masks, layers = {}, {}, {}
    for compiled in (False, True):
        mp.use_compiled_kernels(compiled)
        try:
            f = mp.FineHeightMap(0.01, (60, 50), (0.0, 0.0), 'plane', gate)
            got = []
            for k, (c, w) in enumerate(zip(caps, wts)):
                if k == 2:
                    f.shift(3, -2)
                origin = np.array([0.3, -0.4, 0.5])
                got.append(f.rays_below(c, origin, 0.01))
                got.append(f.add(c, float(k), w))
            maps[compiled], masks[compiled] = f, got
            layers[compiled] = (f.heights(), f.to_grid().layers,
                                mp.FineHeightMap(0.01, (60, 50), (0.0, 0.0), 'mean').heights())
            f.estimator = 'mean'
            layers[compiled] += (f.heights(),)
            f.estimator = 'plane'
        finally:
            mp.use_compiled_kernels(None)
    for a, b in zip(layers[True], layers[False]):
        for x, y in (zip(a.values(), b.values()) if isinstance(a, dict) else [(a, b)]):
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)
    assert list(layers[True][1]) == list(layers[False][1])
    assert np.sum(np.isfinite(layers[True][0])) > 1000
    for k in mp.FineHeightMap._STATS:
        np.testing.assert_array_equal(maps[True].s[k], maps[False].s[k], err_msg=k)
    for a, b in zip(masks[True], masks[False]):
        np.testing.assert_array_equal(a, b)
    assert sum(np.sum(m) for m in masks[True][0::2]) > 0        # some rays were refused
    assert np.isnan(maps[True].heights()).sum() < maps[True].heights().size
    # an all-outside batch, an empty one, a NaN height and float32 input: the same answers
    odd = {}
    for compiled in (True, False):
        mp.use_compiled_kernels(compiled)
        try:
            f = mp.FineHeightMap(0.01, (10, 10), (0.0, 0.0), 'plane', gate)
            with np.errstate(invalid='ignore'):
                odd[compiled] = [
                    f.add(np.array([[5.0, 5.0, 0.0], [-0.5, 0.05, 0.0]]), 0.0),
                    f.add(np.zeros((0, 3)), 0.0),
                    f.rays_below(np.zeros((0, 3)), np.zeros(3), 0.01).tolist(),
                    f.add(np.array([[0.05, 0.05, np.nan], [0.05, 0.05, 0.1]]), 1.0),
                    f.add(np.array([[0.02, 0.03, 0.2], [0.02, 0.05, 0.3]], np.float32), 2.0),
                    {k: v.copy() for k, v in f.s.items()}]
        finally:
            mp.use_compiled_kernels(None)
    assert odd[True][:5] == odd[False][:5] and odd[True][0] == 0
    # cloud_height_normals: dense and sparse (missing neighbours) clouds, several half-widths
    for n_pts, hw in ((20000, 3), (2000, 2), (300, 3), (300, 1), (50, 0)):
        pts = _noisy_capture(rng, n_pts, size=(0.3, 0.2))
        got = {}
        for compiled in (True, False):
            mp.use_compiled_kernels(compiled)
            try:
                got[compiled] = mp.cloud_height_normals(pts, 0.01, hw)
            finally:
                mp.use_compiled_kernels(None)
        np.testing.assert_array_equal(got[True], got[False])
        assert n_pts < 1000 or np.isfinite(got[True]).all(axis=1).mean() > 0.5
    # valid_points: organized (strided) and (N, 3), float32 and float64, NaN / inf / edges
    cloud = rng.normal(0.5, 0.6, (40, 30, 3))
    cloud[rng.random((40, 30)) < 0.2, rng.integers(0, 3)] = np.nan
    cloud[rng.random((40, 30)) < 0.05, 2] = np.inf
    cloud[0, :4, 2] = [0.05, 1.5, np.float32(0.05), np.float32(1.5)]
    for arr in (cloud, cloud.astype(np.float32)):
        for stride in (1, 2, 3):
            for c in (arr, arr.reshape(-1, 3)):
                got = {}
                for compiled in (True, False):
                    mp.use_compiled_kernels(compiled)
                    try:
                        got[compiled] = mp.valid_points(c, 0.05, 1.5, stride)
                    finally:
                        mp.use_compiled_kernels(None)
                assert got[True].dtype == got[False].dtype == np.float64
                np.testing.assert_array_equal(got[True], got[False])
    for k in mp.FineHeightMap._STATS:
        np.testing.assert_array_equal(odd[True][5][k], odd[False][5][k], err_msg=k)


@pytest.mark.parametrize('min_neighbours,island_cells', [(2, 20), (0, 0), (3, 5), (8, 1)])
def test_isolated_cells_kernel_equals_the_numpy_code(min_neighbours, island_cells):
    """The compiled isolated_cells flags exactly the numpy reference's cells (neighbour count,
    the neighbours' median gate and the unsupported islands) on sparse, noisy maps with
    single-sample clusters, lone cells and NaN heights."""
    from terrain_perception import _mapping_kernels  # noqa: F401 (numba is a dependency)
    rng = np.random.default_rng(3)
    for trial in range(6):
        shape = (int(rng.integers(1, 60)), int(rng.integers(1, 70)))
        h = rng.normal(0.0, 0.03, shape)
        obs = rng.random(shape) < rng.uniform(0.05, 0.9)
        count = np.where(obs, rng.choice([1, 2, 3, 9], shape, p=[0.4, 0.2, 0.2, 0.2]), 0)
        h[rng.random(shape) < 0.03] += 0.3                  # mismatches above the gate
        h[rng.random(shape) < 0.02] = np.nan                # observed but no height
        grid = GridMap(0.01, (0.0, 0.0), shape, {
            ELEVATION: np.where(obs, h, np.nan).astype(np.float32),
            OBSERVED: obs.astype(np.float32), 'count': count.astype(np.float32)})
        got = {}
        for compiled in (True, False):
            mp.use_compiled_kernels(compiled)
            try:
                got[compiled] = mp.isolated_cells(grid, 2, min_neighbours, 0.05, island_cells)
            finally:
                mp.use_compiled_kernels(None)
        np.testing.assert_array_equal(got[True], got[False])
        if trial == 0:
            assert got[True].any() and not got[True].all()


def test_lone_single_sample_cells_are_published_unobserved_and_kept():
    """The graph test's failure shape: flat ground observed densely (4 samples per cell), a
    pair of single-sample cells 0.75 m below it off the observed area, a 2 x 2 cluster of them
    (each vouched for by three others, but none by a supported cell), one single-sample cell
    0.14 m above it inside, one single-sample cell at ground height on the area's edge, and a
    real 10 cm step observed 5 times (on a ground cell: 9 samples). The published map hides
    exactly the seven mismatches;
    their samples stay in the statistics (a later sample makes them count)."""
    m = mp.IcpMapper(CONFIG, T_BC)
    res = m.fine.resolution_m
    xs = (np.arange(40) + 0.5) * res                       # cells 0..39 from the origin
    X, Y = np.meshgrid(xs, xs[:20], indexing='ij')
    o = m.fine.origin_xy
    hole = (X.ravel() == xs[10]) & (Y.ravel() == xs[10])     # cell (10, 10) not seen
    ground = np.c_[X.ravel() + o[0], Y.ravel() + o[1], np.zeros(X.size)][~hole]
    m.fine.add(np.repeat(ground, 4, axis=0), 0.0)
    def cell(i, j, z, n=1):
        return np.repeat([[o[0] + (i + 0.5) * res, o[1] + (j + 0.5) * res, z]], n, axis=0)
    m.fine.add(np.r_[cell(30, 35, -0.75), cell(31, 35, -0.75),   # lone pair off the area
                     cell(30, 28, -0.67), cell(31, 28, -0.67),   # a 2 x 2 cluster of them,
                     cell(30, 29, -0.67), cell(31, 29, -0.67),   # 8 cells off the area
                     cell(10, 10, 0.14, 2),                       # inside, 2 samples
                     cell(20, 20, 0.001),                         # edge, ground height
                     cell(5, 19, 0.10, 5)], 1.0)                  # real step, 5 more samples
    g = m.fine_grid()
    obs = g[OBSERVED] > 0.5
    assert not obs[30, 35] and not obs[31, 35] and not obs[10, 10]
    assert not obs[30:32, 28:30].any()
    assert np.isnan(g[ELEVATION][[30, 31, 10], [35, 35, 10]]).all()
    assert obs[20, 20] and obs[5, 19] and g[ELEVATION][5, 19] > 0.01
    assert int(obs.sum()) == 40 * 20 - 1 + 1              # the ground - (10, 10) + edge cell
    assert m.counters['isolated_cells_hidden'] == 7
    # samples kept: the 0.14 m cell's two samples are in the statistics, and one more sample
    # at the same height makes it a 3-sample cell that is published
    m.fine.add(cell(10, 10, 0.14), 2.0)
    assert m.fine_grid()[OBSERVED][10, 10] > 0.5
    off = mp.IcpMapper(dataclasses.replace(CONFIG, isolated_max_count=0), T_BC)
    off.fine = m.fine
    assert off.fine_grid()[OBSERVED][30, 35] > 0.5


def _bumpy_view(n=2000, seed=0):
    """Points of a bumpy patch 0.3-0.9 m ahead of a camera at the origin-ish, with normals."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.3, 0.9, n)
    y = rng.uniform(-0.25, 0.25, n)
    a, k = 0.03, 12.0
    z = a * np.sin(k * x) * np.cos(k * y) - 0.3
    dzdx = a * k * np.cos(k * x) * np.cos(k * y)
    dzdy = -a * k * np.sin(k * x) * np.sin(k * y)
    nrm = np.column_stack([-dzdx, -dzdy, np.ones(n)])
    return np.column_stack([x, y, z]), nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def test_blend_yaw_moves_along_the_icp_valley_to_the_imu_yaw():
    """ICP's optimum with a wrong yaw sits in the cost valley (its translation compensates
    part of the yaw about the cloud); keeping none of its yaw must come back to the true pose,
    not merely turn the camera about its own origin."""
    pts, nrm = _bumpy_view()
    T_true = make_T(rpy_to_R(0.0, 0.6, 0.1), [0.05, -0.02, 0.02])
    T_prior = T_true.copy()                        # the IMU's rotation, dead reckoning 8 mm off
    T_prior[:3, 3] += [0.006, -0.005, 0.0]
    # ICP's answer: 1.5 deg of yaw error, the rest at the conditional minimum of the cost
    H, L = mp._information(T_true, pts, nrm, None)
    y = np.radians(1.5) * L
    x = np.zeros(6)
    x[2] = y
    other = [0, 1, 3, 4, 5]
    x[other] = -np.linalg.solve(H[np.ix_(other, other)], H[other, 2] * y)
    T_icp = mp._from_motion(x, T_true, L)
    assert np.linalg.norm(T_icp[:3, 3] - T_true[:3, 3]) > 0.005      # a real position error
    out = mp.blend_yaw(T_icp, T_prior, pts, nrm, 0.0)
    assert angle_between(out[:3, :3], T_true[:3, :3]) < np.radians(0.05)
    assert np.linalg.norm(out[:3, 3] - T_true[:3, 3]) < 0.5e-3
    # only turning the camera back about its origin leaves the translation error in place
    naive = T_icp.copy()
    naive[:3, :3] = T_prior[:3, :3]
    assert np.linalg.norm(naive[:3, 3] - T_true[:3, 3]) > 0.005
    # half the gain: half the yaw error, and gain 1 is ICP's pose untouched
    half = mp.blend_yaw(T_icp, T_prior, pts, nrm, 0.5)
    assert np.degrees(angle_between(half[:3, :3], T_true[:3, :3])) == pytest.approx(0.75,
                                                                                   abs=0.05)
    np.testing.assert_array_equal(mp.blend_yaw(T_icp, T_prior, pts, nrm, 1.0), T_icp)
    with pytest.raises(ValueError, match='gain'):
        mp.blend_yaw(T_icp, T_prior, pts, nrm, 1.5)


def test_a_voxel_keeps_the_mean_of_its_observations_up_to_the_weight_cap():
    """merge_voxels: a voxel seen 9 times at z = 2 mm and once at 6 mm sits at their mean
    (2.4 mm); Open3D's down-sampling of model + capture (coarse_fusion average) moves it
    half-way to the newest capture; with a cap of 1 the newest replaces it. Every voxel keeps
    one point, its count and the newest stamp."""
    xy = np.stack(np.meshgrid(np.arange(10) * 0.01 + 0.005, np.arange(10) * 0.01 + 0.005,
                              indexing='ij'), -1).reshape(-1, 2)
    def capture(z):
        return np.column_stack([xy, np.full(len(xy), z)])
    up = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    model = o3d.geometry.PointCloud()
    for k in range(9):
        model = mp.merge_voxels(model, capture(0.002), up, float(k), 0.01, 20.0)
    assert len(model.points) == 100
    np.testing.assert_allclose(np.asarray(model.colors)[:, :2], [[8.0, 9.0]] * 100)
    merged = mp.merge_voxels(model, capture(0.006), up, 9.0, 0.01, 20.0)
    assert len(merged.points) == 100
    np.testing.assert_allclose(np.asarray(merged.points)[:, 2], 0.0024, atol=1e-12)
    np.testing.assert_allclose(np.asarray(merged.colors)[:, :2], [[9.0, 10.0]] * 100)
    np.testing.assert_allclose(np.asarray(merged.normals), up)
    # cap 1: the stored count stays 1, so each capture moves the voxel half-way
    one = o3d.geometry.PointCloud()
    for k in range(9):
        one = mp.merge_voxels(one, capture(0.002), up, float(k), 0.01, 1.0)
    one = mp.merge_voxels(one, capture(0.006), up, 9.0, 0.01, 1.0)
    np.testing.assert_allclose(np.asarray(one.points)[:, 2], 0.004, atol=1e-12)
    one = mp.merge_voxels(one, capture(0.006), up, 10.0, 0.01, 1.0)
    np.testing.assert_allclose(np.asarray(one.points)[:, 2], 0.005, atol=1e-12)
    o3d_avg = (model + o3d.geometry.PointCloud(o3d.utility.Vector3dVector(capture(0.006)))
               ).voxel_down_sample(0.01)
    assert np.allclose(np.asarray(o3d_avg.points)[:, 2], 0.004)
    # a point in a new voxel joins the model; two capture points in one voxel are one sample
    two = np.array([[0.2012, 0.0, 0.012], [0.2018, 0.0, 0.018]])
    grown = mp.merge_voxels(merged, two, np.tile([0.0, 0.0, 1.0], (2, 1)), 11.0, 0.01, 20.0)
    assert len(grown.points) == 101
    new = np.asarray(grown.points)[np.asarray(grown.points)[:, 0] > 0.15]
    np.testing.assert_allclose(new, [[0.2015, 0.0, 0.015]])
    assert np.asarray(grown.colors)[np.asarray(grown.points)[:, 0] > 0.15][0, 1] == 1.0


def _drifting_imu_walk(scene, config, drift_deg_s, n=40, dt=1.0, step_m=0.01):
    """A walk along x with perfect odometry and an IMU whose yaw drifts at drift_deg_s; the
    mapper's updates (capture k at k * dt seconds)."""
    m = mp.IcpMapper(config, T_BC)
    ups = []
    for k in range(n):
        T = make_T(np.eye(3), [k * step_m, 0.0, 0.2])
        imu = rpy_to_R(0.0, 0.0, np.radians(drift_deg_s * k * dt))
        ups.append(m.update(cloud_at(scene, T), T, k * dt, attitude=imu))
    return m, ups


def test_the_imus_yaw_drift_is_measured_and_taken_out_of_the_prior(terrain):
    """The IMU's yaw drifts 0.1 deg/s (a gyro bias); ICP corrects it at every capture on the
    bumps. From half a window (15 s) of history the mapper knows the rate and turns the prior
    back by it: the priors' yaw errors shrink from 0.1 deg (a second of drift) to a few
    hundredths. Off (window 0): the rate stays 0 and every prior carries the second's
    drift."""
    _, scene = terrain
    cfg = dataclasses.replace(CONFIG, use_imu_rotation_prior=True)
    m, ups = _drifting_imu_walk(scene, cfg, 0.1)
    assert all(u.accepted and u.n_degenerate == 0 for u in ups), [u.reason for u in ups]
    assert m.imu_yaw_drift_deg_s == pytest.approx(0.1, abs=0.01)
    prior_err = [pose_error(u.T_map_base_prior, u.T_map_base)[1] for u in ups]
    assert np.median(prior_err[1:15]) > 0.08
    assert np.median(prior_err[20:]) < 0.03, prior_err
    off, ups_off = _drifting_imu_walk(scene, dataclasses.replace(cfg, imu_yaw_drift_window_s=0.0),
                                      0.1)
    assert off.imu_yaw_drift_deg_s == 0.0
    assert np.median([pose_error(u.T_map_base_prior, u.T_map_base)[1]
                      for u in ups_off[20:]]) > 0.08


def test_the_yaw_drift_estimate_holds_while_the_view_constrains_no_yaw():
    """The estimator alone: 5 captures/s whose ICP turned the IMU's yaw back by 0.02 deg
    each (0.1 deg/s). Nothing before half a window (15 s); then 0.1 deg/s. While the view is
    degenerate (ICP kept the yaw at the prior: corrections 0) the estimate is kept, where
    the window's sum would fall to 0; the first constrained capture after 20 s of that catches
    up the 2 deg, and the window's sum is again the rate."""
    m = mp.IcpMapper(CONFIG, T_BC)
    step = np.radians(-0.02)
    t = 0.0
    for k in range(80):
        t = 0.2 * k
        m._note_yaw_correction(t, step, True)
        if t < 15.0:
            assert m.imu_yaw_drift_deg_s == 0.0
    assert m.imu_yaw_drift_deg_s == pytest.approx(0.1, rel=0.02)
    for k in range(1, 101):
        m._note_yaw_correction(t + 0.2 * k, 0.0, False)
    assert m.imu_yaw_drift_deg_s == pytest.approx(0.1, rel=0.02)
    t += 20.2
    m._note_yaw_correction(t, np.radians(-2.02), True)
    assert m.imu_yaw_drift_deg_s == pytest.approx(0.1, rel=0.05)
    m2 = mp.IcpMapper(dataclasses.replace(CONFIG, imu_yaw_drift_max_deg_s=0.05), T_BC)
    for k in range(100):
        m2._note_yaw_correction(0.2 * k, step, True)
    assert m2.imu_yaw_drift_deg_s == pytest.approx(0.05)


def test_a_capture_that_does_not_know_its_yaw_cannot_set_the_drift_rate():
    """5 captures/s, 0.1 deg/s of drift, and at 20 s one capture whose yaw ICP got 1 deg
    wrong on a view that did not constrain every direction; the next capture's correction
    takes the error back out. That capture neither sets the rate nor starts a window: as it
    slides out of the 30 s window, a window starting between it and the next capture would
    hold the 1 deg return alone (0.1 - 0.033 deg/s)."""
    m = mp.IcpMapper(CONFIG, T_BC)
    drift = np.radians(-0.02)
    rates = []
    for k in range(300):
        t = 0.2 * k
        y, known = drift, True
        if k == 100:
            y, known = drift + np.radians(-1.0), False
        elif k == 101:
            y = drift + np.radians(1.0)
        m._note_yaw_correction(t, y, known)
        if t >= 15.0:
            rates.append(m.imu_yaw_drift_deg_s)
    np.testing.assert_allclose(rates, 0.1, rtol=0.01)


def test_a_deferred_coarse_model_gives_the_same_walk(terrain):
    """``defer_model``: the fine map and the capture poses are updated at once, the coarse
    model waits for finish_model (the node runs it after publishing) or, if nobody ran it,
    for the next alignment or a read of the model. Along a walk with 1 cm/capture of odometry
    error, half of the captures finished by hand and half left to the next capture, every
    pose, the coarse model and the fine map are bitwise those of the undeferred mapper."""
    _, scene = terrain
    cfg = dataclasses.replace(CONFIG, use_imu_rotation_prior=True)
    now, later = mp.IcpMapper(cfg, T_BC), mp.IcpMapper(cfg, T_BC)
    for k in range(12):
        T_true = make_T(rpy_to_R(0.0, 0.0, np.radians(2.0 * k)), [0.03 * k, 0.01 * k, 0.2])
        T_odom = make_T(T_true[:3, :3], T_true[:3, 3] + [0.01 * k, 0.0, 0.0])
        cloud = cloud_at(scene, T_true)
        n_model = len(now._model.points)      # the model of the captures before k
        a = now.update(cloud, T_odom, float(k), attitude=T_true[:3, :3])
        b = later.update(cloud, T_odom, float(k), attitude=T_true[:3, :3], defer_model=True)
        assert a.accepted and b.accepted and b.fused
        np.testing.assert_array_equal(a.T_map_base, b.T_map_base)
        # fine map and poses at once; the model still the last capture's
        np.testing.assert_array_equal(now.capture_poses()[1], later.capture_poses()[1])
        assert later.stamp_s == float(k) and later._pending_model is not None
        assert len(later._model.points) == n_model
        if k % 2:
            later.finish_model()
            assert later._pending_model is None and later._tree is not None
    for grid_a, grid_b in [(now.fine_grid(), later.fine_grid())]:
        for name in grid_a.layers:
            np.testing.assert_array_equal(grid_a[name], grid_b[name])
    np.testing.assert_array_equal(now.coarse_points(), later.coarse_points())
    np.testing.assert_array_equal(now.coarse_normals(), later.coarse_normals())
    assert len(now.coarse_points()) > 1000


def _model_with_steps(rng):
    """Voxel centroids of a bumpy floor with box-shaped stones (vertical faces: tall x-y
    columns), in the coarse model's form."""
    g, scene = bumpy(), None
    xs, ys = g.cell_centers()
    X, Y = np.meshgrid(xs[::2], ys[::2], indexing='ij')
    Z = g[ELEVATION][::2, ::2] + 0.12 * ((np.abs(X - 0.3) < 0.1) & (np.abs(Y + 0.2) < 0.1))
    floor = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    face = np.column_stack([np.full(300, 0.2), rng.uniform(-0.3, -0.1, 300),
                            rng.uniform(0.0, 0.12, 300)])
    pts = np.vstack([floor, face]) + rng.normal(0.0, 0.002, (len(floor) + 300, 3))
    return mp.voxel_centroids(pts, 0.01)


@pytest.mark.parametrize('bound', [0.04, 0.015, 0.11])
def test_model_index_answers_as_the_kdtree(bound):
    """The ICP's correspondence search (``ModelIndex``, columns of half the mapper's 4 cm
    bound, searched nearest first) gives scipy cKDTree's answer to ``query(p, k=1,
    distance_upper_bound=bound)`` for bounds below, at and above the one it was built for:
    the same found points, the same rows and bitwise the same distances, for queries on the
    surface, off it by up to twice the bound, exactly at the bound and off the model; on
    exact ties (a duplicated model point) the lowest row. A NaN query is refused by both."""
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(3)
    model = _model_with_steps(rng)
    index = mp.ModelIndex(model, 0.04)
    assert index.compiled, 'the compiled column search is what is under test'
    tree = cKDTree(model)
    q = np.vstack([model[rng.integers(len(model), size=3000)]
                   + rng.normal(0.0, s, (3000, 3)) for s in (0.0, 0.005, 0.02, 0.08)])
    at_bound = model[:50] + [bound, 0.0, 0.0]
    q = np.vstack([q, at_bound, [[50.0, 0.0, 0.0], [0.0, -50.0, 0.1]]])
    d_ref, i_ref = tree.query(q, k=1, distance_upper_bound=bound)
    d, i = index.query(q, k=1, distance_upper_bound=bound)
    found = np.isfinite(d_ref)
    assert 0.3 * len(q) < found.sum() < len(q) - 50
    np.testing.assert_array_equal(np.isfinite(d), found)
    np.testing.assert_array_equal(d, d_ref)
    np.testing.assert_array_equal(i, i_ref)
    assert np.all(i[~found] == len(model))
    # a duplicated model point: the same distance, the lower row
    dup = np.vstack([model, model[[10]]])
    d2, i2 = mp.ModelIndex(dup, 0.04).query(model[[10]] + 0.001, distance_upper_bound=bound)
    assert i2[0] == 10 and d2[0] == cKDTree(dup).query(model[[10]] + 0.001)[0][0]
    with pytest.raises(ValueError, match='finite'):
        index.query(np.array([[np.nan, 0.0, 0.0]]), distance_upper_bound=bound)


def test_model_index_falls_back_to_the_kdtree():
    """Without the compiled kernels, for k > 1 or no bound, and for a model spread over
    kilometres (too many columns), ``ModelIndex`` answers with a cKDTree: the same results."""
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(4)
    model = _model_with_steps(rng)
    q = model[:500] + rng.normal(0.0, 0.01, (500, 3))
    ref = cKDTree(model).query(q, k=1, distance_upper_bound=0.04)
    far = np.vstack([model, [[5000.0, 5000.0, 0.0]]])
    assert not mp.ModelIndex(far, 0.04).compiled
    for got in (mp.ModelIndex(far, 0.04).query(q, distance_upper_bound=0.04),):
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
    d3, i3 = mp.ModelIndex(model, 0.04).query(q, k=3)
    np.testing.assert_array_equal(i3, cKDTree(model).query(q, k=3)[1])
    try:
        mp.use_compiled_kernels(False)
        plain = mp.ModelIndex(model, 0.04)
        assert not plain.compiled
        got = plain.query(q, distance_upper_bound=0.04)
    finally:
        mp.use_compiled_kernels(None)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])


def test_a_walk_aligned_with_the_model_index_equals_the_kdtree_walk(terrain, monkeypatch):
    """The mapper's alignments with ``ModelIndex`` and with a cKDTree of the coarse model
    (the code before it): along a 12-capture walk with 1 cm/capture of odometry error, every
    pose and the fine map bitwise the same."""
    from scipy.spatial import cKDTree
    _, scene = terrain
    walk = []
    for k in range(12):
        T_true = make_T(rpy_to_R(0.0, 0.0, np.radians(2.0 * k)), [0.03 * k, 0.01 * k, 0.2])
        walk.append((cloud_at(scene, T_true),
                     make_T(T_true[:3, :3], T_true[:3, 3] + [0.01 * k, 0.0, 0.0]), T_true))

    searched = []
    real = mp.constrained_icp

    def spied(src, model, normals, tree, *args, **kw):
        searched.append(type(tree).__name__ + str(getattr(tree, 'compiled', '')))
        return real(src, model, normals, tree, *args, **kw)

    monkeypatch.setattr(mp, 'constrained_icp', spied)

    def run():
        searched.clear()
        m = mp.IcpMapper(CONFIG, T_BC)
        poses = [m.update(c, T_o, float(k), attitude=T_t[:3, :3]).T_map_base
                 for k, (c, T_o, T_t) in enumerate(walk)]
        return m, poses, set(searched)

    m_new, new, used = run()
    assert used == {'ModelIndexTrue'}
    monkeypatch.setattr(mp, 'ModelIndex', lambda pts, bound: cKDTree(pts))
    m_old, old, used = run()
    assert used == {'cKDTree'}
    for a, b in zip(new, old):
        np.testing.assert_array_equal(a, b)
    ga, gb = m_new.fine_grid(), m_old.fine_grid()
    for name in ga.layers:
        np.testing.assert_array_equal(ga[name], gb[name])


def _bumps_then_flat(edge_x=1.2):
    """bumpy() over x < edge_x - 0.1, fading to a level floor at edge_x and beyond."""
    g = bumpy(shape=(600, 400))
    xs, ys = g.cell_centers()
    X = np.meshgrid(xs, ys, indexing='ij')[0]
    g[ELEVATION] = g[ELEVATION] * np.clip((edge_x - X) / 0.1, 0.0, 1.0)
    return rc.HeightFieldScene(g)


def _overstating_walk(scene, config, stride=1.05, n=91, step_m=0.02, seed=7):
    """A walk along x whose odometry overstates every step by ``stride``; stereo-like depth
    noise. Returns the mapper and its updates with the true x of each capture."""
    rng = np.random.default_rng(seed)
    fb = CAM.fx * 0.03
    m = mp.IcpMapper(config, T_BC, fb)
    ups = []
    for k in range(n):
        x = step_m * k
        T = make_T(np.eye(3), [x, 0.0, 0.2])
        u = m.update(stereo_noise(cloud_at(scene, T), fb, config.disparity_sigma_px, rng),
                     make_T(np.eye(3), [stride * x, 0.0, 0.2]), float(k))
        ups.append((x, u))
    return m, ups


def test_the_odometry_scale_learnt_on_bumps_carries_the_prior_across_flat_ground():
    """Dead reckoning overstates every step by 5 % (it follows the commanded body path; the
    feet lag it). While the bumps are in view ICP measures x and the mapper learns the scale
    (1 / 1.05); once the view is level (x, y and yaw kept at the prior from x ~ 0.8 m) the
    prior carries the walk on at that scale: the estimate stays within millimetres where,
    with the scale off, it runs 5 % of the flat walk (~50 mm over 1 m) ahead."""
    scene = _bumps_then_flat()
    cfg = dataclasses.replace(CONFIG, disparity_sigma_px=0.01)
    m, ups = _overstating_walk(scene, cfg)
    assert all(u.accepted for _, u in ups), [u.reason for _, u in ups]
    flat = [(x, u) for x, u in ups if x >= 0.85]
    assert len(flat) > 40 and all(u.n_degenerate == 3 for _, u in flat), \
        [u.n_degenerate for _, u in flat]
    assert m.odometry_scale == pytest.approx(1.0 / 1.05, rel=0.01)
    err = [abs(u.T_map_base[0, 3] - x) for x, u in flat]
    assert max(err) < 0.006, err
    off, ups_off = _overstating_walk(scene, dataclasses.replace(cfg, odometry_scale_window_m=0.0))
    assert off.odometry_scale == 1.0
    err_off = abs(ups_off[-1][1].T_map_base[0, 3] - ups_off[-1][0])
    assert err_off > 0.04, err_off


def test_the_scale_counts_only_captures_whose_position_icp_measured_along_the_step():
    """``_note_scale`` by hand: the map's origin is the anchor; a capture 0.5 m on whose
    constrained directions hold x (the step) adds the step; one whose basis holds only z,
    roll and pitch (level ground) adds nothing and leaves the anchor; below
    odometry_scale_min_m nothing is applied; the scale is clipped to 1 +- max_error."""
    cfg = dataclasses.replace(CONFIG, odometry_scale_min_m=0.3, odometry_scale_max_error=0.1)
    m = mp.IcpMapper(cfg, T_BC)
    at = lambda x: make_T(np.eye(3), [x, 0.0, 0.2])
    m._note_scale(at(0.0), at(0.0), None)
    level = np.zeros((6, 3))
    level[0, 0] = level[1, 1] = level[5, 2] = 1.0       # roll, pitch (x L), z
    m._note_scale(at(0.2), at(0.25), level)             # not measured along x: ignored
    assert m._scale_odom_m == 0.0 and m.odometry_scale == 1.0
    m._note_scale(at(0.19), at(0.2), np.eye(6)[:, [0, 1, 3, 5]])   # x constrained, not y
    assert m._scale_odom_m == pytest.approx(0.2)
    assert m.odometry_scale == 1.0                      # 0.2 m < odometry_scale_min_m
    m._note_scale(at(0.38), at(0.4), None)
    w = np.exp(-0.2 / cfg.odometry_scale_window_m)
    assert m._scale_odom_m == pytest.approx(w * 0.2 + 0.2)
    assert m.odometry_scale == pytest.approx((w * 0.19 + 0.19) / (w * 0.2 + 0.2))
    m._note_scale(at(1.0), at(2.0), None)               # 50 % over: clipped
    assert m.odometry_scale == pytest.approx(0.9)


def test_open3ds_solver_does_not_teach_the_scale_on_level_ground():
    """Open3D's ICP (``icp_solver: open3d``) reports how many directions it kept at the prior,
    not which: on level ground (x, y and yaw kept) its captures add nothing to the scale."""
    scene = flat_scene()
    m = mp.IcpMapper(dataclasses.replace(CONFIG, icp_solver='open3d'), T_BC)
    for k in range(4):
        T = make_T(np.eye(3), [0.02 * k, 0.0, 0.2])
        u = m.update(cloud_at(scene, T), make_T(np.eye(3), [0.021 * k, 0.0, 0.2]), float(k))
        assert u.accepted
    assert u.n_degenerate == 3
    assert m._scale_odom_m == 0.0 and m.odometry_scale == 1.0
