"""Simulated world: heightfield placement, stereo rendering geometry, IMU gravity."""

from __future__ import annotations

import numpy as np
import pybullet
import pytest
from pybullet_utils.bullet_client import BulletClient

from terrain_perception.camera import PinholeCamera, StereoCamera
from terrain_perception.grid import ELEVATION, GridMap
from terrain_perception.sim.world import (ImuConfig, ImuModel, LightConfig, SimWorld,
                                          WorldConfig, ground_truth_disparity, render_camera,
                                          render_stereo, rock_texture)
from terrain_perception.terrain import make_course
from terrain_perception.transforms import make_T, quat_to_R, rpy_to_R

# base_link-like (x forward, z up) -> optical (z forward, x right, y down)
R_FWD_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
SMALL = WorldConfig(texture_size_px=256, texture_tile_m=0.25, ground_margin_m=1.0)


def camera_looking_forward(x, y, z, pitch_down_rad):
    return make_T(rpy_to_R(0.0, pitch_down_rad, 0.0) @ R_FWD_OPTICAL, [x, y, z])


@pytest.fixture
def client():
    c = BulletClient(pybullet.DIRECT)
    yield c
    c.disconnect()


@pytest.fixture(scope='module')
def course():
    return make_course('rocks-12cm', 5, resolution_m=0.01)


def test_heightfield_matches_grid_under_ray_casts(client, course):
    world = SimWorld(client, course, SMALL)
    xs, ys = course.cell_centers()
    rng = np.random.default_rng(1)
    i = rng.integers(0, course.shape[0], 4000)
    j = rng.integers(0, course.shape[1], 4000)
    got = world.ray_heights(np.column_stack([xs[i], ys[j]]))
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, course[ELEVATION][i, j], atol=1e-3)
    # between cell centres the triangles interpolate the grid (bilinear to within a mm)
    xy = np.column_stack([rng.uniform(xs[0], xs[-1], 2000), rng.uniform(ys[0], ys[-1], 2000)])
    assert np.percentile(np.abs(world.ray_heights(xy) - world.height_at(xy)), 95) < 1e-3
    # beyond the course: the flat floor at 0
    np.testing.assert_allclose(world.ray_heights(np.array([[-2.0, 0.0], [9.0, 3.0]])), 0.0,
                               atol=1e-6)


def test_heightfield_placement_for_an_asymmetric_grid(client):
    """A ramp on an off-centre grid: catches swapped axes and pybullet's AABB centring; its
    low end dips below 0 and the floor must not fill that pit."""
    x = np.arange(30)[:, None] * 0.004 + np.zeros((1, 17))
    y = np.arange(17)[None, :] * 0.001 + np.zeros((30, 1))
    grid = GridMap(0.02, (1.3, -0.7), (30, 17), {ELEVATION: -0.05 + x + y})
    world = SimWorld(client, grid, SMALL)
    xs, ys = grid.cell_centers()
    X, Y = np.meshgrid(xs, ys, indexing='ij')
    got = world.ray_heights(np.column_stack([X.ravel(), Y.ravel()])).reshape(X.shape)
    np.testing.assert_allclose(got, grid[ELEVATION], atol=1e-4)
    assert world.ray_heights(np.array([[0.0, 0.0]]))[0] == pytest.approx(-0.05, abs=1e-6)


def test_depth_and_projection_match_analytic_floor(client):
    """Over a flat floor the z-depth of every pixel is known in closed form."""
    flat = GridMap(0.05, (-1.0, -1.0), (40, 40), {ELEVATION: np.zeros((40, 40))})
    SimWorld(client, flat, SMALL)
    cam = PinholeCamera(160, 120, 130.0, 125.0, 83.0, 57.5)
    h, pitch = 0.4, np.radians(40.0)
    T = camera_looking_forward(0.0, 0.0, h, pitch)
    _, depth = render_camera(client, T, cam, 0.05, 20.0, LightConfig(shadow=False))
    rays = cam.rays() @ T[:3, :3].T          # world direction per pixel, z-component = dZ
    with np.errstate(divide='ignore'):
        t = np.where(rays[..., 2] < -1e-6, -h / rays[..., 2], np.nan)  # z-depth (ray z = 1)
    ok = np.isfinite(t) & (t < 3.0) & np.isfinite(depth)
    assert ok.mean() > 0.5
    rel = np.abs(depth[ok] - t[ok]) / t[ok]
    assert np.median(rel) < 1e-3 and np.percentile(rel, 99) < 5e-3
    # (a half-pixel shift in v alone gives a 0.5 % median error here: the test sees it)


def test_stereo_pair_shift_equals_ground_truth_disparity(client, course):
    """Left pixel (u, v) reappears in the right image at (u - fB/Z, v)."""
    SimWorld(client, course, SMALL)
    cam = PinholeCamera.from_fov(160, 120, 50.0)
    stereo = StereoCamera(cam, 0.05)
    T = camera_looking_forward(0.75, 0.05, 0.35, np.radians(40.0))
    left, right, depth = render_stereo(client, T, stereo, 0.05, 5.0, LightConfig(shadow=False))
    assert left.shape == right.shape == (120, 160, 3) and left.dtype == np.uint8
    disp = ground_truth_disparity(stereo, depth)
    L = left.mean(axis=2).astype(np.float64)
    R = right.mean(axis=2).astype(np.float64)
    r = 3
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(1000):
        u, v = rng.integers(30, 150), rng.integers(r, 120 - r)
        d = disp[v, u]
        if not np.isfinite(d) or u - d - 8 - r < 0:
            continue
        win = disp[v - r:v + r + 1, u - r:u + r + 1]
        if not np.all(np.isfinite(win)) or np.ptp(win) > 2.0:
            continue                     # skip occlusion edges
        patch = L[v - r:v + r + 1, u - r:u + r + 1]
        if patch.std() < 3.0:
            continue
        # sub-pixel SAD search over the row around the ground truth
        shifts = np.arange(-6.0, 6.01, 0.25)
        cols = u - d + shifts[:, None] + np.arange(-r, r + 1)[None, :]
        c0 = np.floor(cols).astype(int)
        a = cols - c0
        rows = R[v - r:v + r + 1]
        sampled = rows[:, c0] * (1 - a) + rows[:, c0 + 1] * a     # (2r+1, S, 2r+1)
        sad = np.abs(sampled - patch[:, None, :]).sum(axis=(0, 2))
        errors.append(shifts[np.argmin(sad)])
    errors = np.asarray(errors)
    assert len(errors) > 100
    assert np.median(np.abs(errors)) <= 0.25
    assert np.mean(np.abs(errors) <= 1.0) > 0.9


@pytest.mark.parametrize('cls_name, cam_x', [('rocks-12cm', 0.75), ('stones-15cm', 1.2)])
def test_rendered_surface_is_the_collision_surface(client, course, cls_name, cam_x):
    """Depth pixels back-projected into the world lie on the ray-cast (physics) terrain: the
    adaptive visual mesh (flat blocks merged, rough blocks at full resolution) is exact."""
    grid = course if cls_name == 'rocks-12cm' else make_course(cls_name, 2, resolution_m=0.01)
    world = SimWorld(client, grid, SMALL)
    cam = PinholeCamera.from_fov(160, 120, 50.0)
    T = camera_looking_forward(cam_x, 0.0, 0.35, np.radians(40.0))
    _, depth = render_camera(client, T, cam, 0.05, 5.0, LightConfig(shadow=False))
    pts = cam.depth_to_points(depth).reshape(-1, 3)
    pts = pts[np.isfinite(pts[:, 2])]
    world_pts = pts @ T[:3, :3].T + T[:3, 3]
    assert (world.height_at(world_pts[:, :2]) > 0.01).mean() > 0.05   # sees the rough part
    ground = world.ray_heights(world_pts[:, :2])
    err = np.abs(world_pts[:, 2] - ground)
    assert len(err) > 10000 and np.median(err) < 1e-3 and np.percentile(err, 90) < 5e-3


def test_texture_is_seeded_and_textured():
    a, b = rock_texture(3, 128), rock_texture(3, 128)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, rock_texture(4, 128))
    assert a.shape == (128, 128, 3) and a.dtype == np.uint8
    # texture at pixel scale: neighbouring texels differ
    assert np.mean(np.abs(np.diff(a.astype(int).mean(axis=2), axis=1))) > 2.0
    # tiles seamlessly: the wrap-around step is like any other step
    wrap = np.mean(np.abs(a[:, 0].astype(int) - a[:, -1].astype(int)))
    inner = np.mean(np.abs(np.diff(a.astype(int), axis=1)))
    assert wrap < 2.0 * inner


def test_imu_gravity_matches_base_orientation_at_rest(client):
    """A box resting on a 10 deg ramp: the IMU's gravity agrees with the simulator's pose."""
    n = 60
    slope = np.tan(np.radians(10.0))
    x = (np.arange(n) + 0.5) * 0.02
    ramp = np.repeat((x * slope)[:, None], n, axis=1)
    SimWorld(client, GridMap(0.02, (-0.6, -0.6), (n, n), {ELEVATION: ramp}), SMALL)
    client.setGravity(0, 0, -9.81)
    shape = client.createCollisionShape(client.GEOM_BOX, halfExtents=[0.1, 0.08, 0.03])
    box = client.createMultiBody(1.0, shape, basePosition=[0.0, 0.0, 0.2],
                                 baseOrientation=[0.0, -np.sin(np.radians(5)), 0.0,
                                                  np.cos(np.radians(5))])
    client.changeDynamics(box, -1, lateralFriction=2.0)
    T_base_imu = make_T(rpy_to_R(0.1, -0.2, 0.3), [0.05, 0.02, 0.01])
    imu = ImuModel(ImuConfig(), seed=1, T_base_imu=T_base_imu)
    dt = 1.0 / 240.0
    samples = []
    for k in range(720):
        client.stepSimulation()
        pos, quat = client.getBasePositionAndOrientation(box)
        v, w = client.getBaseVelocity(box)
        s = imu.update((k + 1) * dt, make_T(quat_to_R(quat), pos), v, w)
        if k >= 600:
            samples.append((s, make_T(quat_to_R(quat), pos)))
    s, T_wb = samples[-1]
    R_wi = (T_wb @ T_base_imu)[:3, :3]
    assert np.degrees(np.arccos(T_wb[2, 2])) == pytest.approx(10.0, abs=0.5)  # it lies on the ramp
    up_true = R_wi.T @ [0.0, 0.0, 1.0]                 # world up in the IMU frame
    acc = np.mean([x.linear_acceleration for x, _ in samples], axis=0)
    ang = np.degrees(np.arccos(np.clip(acc @ up_true / np.linalg.norm(acc), -1, 1)))
    assert ang < 0.5
    assert np.linalg.norm(acc) == pytest.approx(9.81, abs=0.1)
    up_reported = quat_to_R(s.orientation_xyzw).T @ [0.0, 0.0, 1.0]
    assert np.degrees(np.arccos(np.clip(up_reported @ up_true, -1, 1))) < 0.5
    assert np.linalg.norm(np.mean([x.angular_velocity for x, _ in samples], axis=0)) < 0.01


def test_imu_noise_is_seeded_and_bad_input_refused():
    T = np.eye(4)
    a = ImuModel(seed=7).update(0.0, T, np.zeros(3), np.zeros(3))
    b = ImuModel(seed=7).update(0.0, T, np.zeros(3), np.zeros(3))
    np.testing.assert_array_equal(a.linear_acceleration, b.linear_acceleration)
    imu = ImuModel(seed=7)
    imu.update(1.0, T, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match='increase'):
        imu.update(1.0, T, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match='finite'):
        imu.update(2.0, T, np.array([np.nan, 0, 0]), np.zeros(3))
    # a known acceleration shows up as specific force: 1 m/s^2 forward over 0.1 s
    quiet = ImuModel(ImuConfig(0.0, 0.0, 0.0, 0.0, 0.0), seed=0)
    quiet.update(0.0, T, np.zeros(3), np.zeros(3))
    s = quiet.update(0.1, T, np.array([0.1, 0.0, 0.0]), np.zeros(3))
    np.testing.assert_allclose(s.linear_acceleration, [1.0, 0.0, 9.81], atol=1e-9)


def test_imu_yaw_drifts_by_the_gyro_bias_while_roll_pitch_and_short_intervals_hold():
    """An attitude filter without a magnetometer: the reported yaw wanders by the integrated
    gyro bias (here its vertical part, the IMU level), roll and pitch stay true, and two
    readings half a second apart agree on the rotation between them to the noise."""
    T = make_T(rpy_to_R(0.0, 0.0, 0.4), [0.0, 0.0, 0.3])
    imu = ImuModel(ImuConfig(), seed=3)
    yaw_true = 0.4
    samples = []
    for k in range(6001):                          # 60 s at 100 Hz, yawing at 0.01 rad/s
        t = 0.01 * k
        T_k = make_T(rpy_to_R(0.0, 0.0, yaw_true + 0.01 * t), [0.0, 0.0, 0.3])
        samples.append((T_k, imu.update(t, T_k, np.zeros(3), np.array([0.0, 0.0, 0.01]))))
    T_end, s_end = samples[-1]
    R_rep = quat_to_R(s_end.orientation_xyzw)
    yaw_err = np.arctan2(R_rep[1, 0], R_rep[0, 0]) - np.arctan2(T_end[1, 0], T_end[0, 0])
    # the bias's vertical part over 60 s (the IMU frame is level here)
    assert yaw_err == pytest.approx(imu.gyro_bias[2] * 60.0, abs=0.005)
    assert abs(yaw_err) > 0.01                   # seed 3's bias: a drift that shows
    assert np.degrees(np.arccos(np.clip(R_rep[2, 2], -1, 1))) < 0.5     # still level
    (Ta, sa), (Tb, sb) = samples[3000], samples[3050]
    rel_rep = quat_to_R(sa.orientation_xyzw).T @ quat_to_R(sb.orientation_xyzw)
    rel_true = Ta[:3, :3].T @ Tb[:3, :3]
    ang = np.degrees(np.arccos(np.clip((np.trace(rel_rep.T @ rel_true) - 1) / 2, -1, 1)))
    assert ang < 0.5
    still = ImuModel(ImuConfig(yaw_drift=False), seed=3)
    for k in range(6001):
        s = still.update(0.01 * k, T, np.zeros(3), np.zeros(3))
    R_s = quat_to_R(s.orientation_xyzw)
    assert abs(np.arctan2(R_s[1, 0], R_s[0, 0]) - 0.4) < 0.01


def test_world_refuses_a_grid_without_elevation(client):
    with pytest.raises(ValueError, match='elevation'):
        SimWorld(client, GridMap(0.1, (0, 0), (4, 4), {'cost': np.zeros((4, 4))}))


# ---- SimSession (the bridge's ROS-free core) --------------------------------------------------
@pytest.fixture(scope='module')
def session():
    from terrain_perception.sim.session import SimSession, SimSessionConfig
    s = SimSession(SimSessionConfig(course_class='flat', image_scale=0.25, shadows=False,
                                    camera_rate_hz=4.0), world_cfg=SMALL)
    yield s
    s.close()


def test_session_refuses_bad_commands_and_keeps_the_last_one(session):
    names = list(session.model.joint_names)
    before = session.q_target.copy()
    q = before.copy()
    with pytest.raises(ValueError, match='unknown joint'):
        session.command(names[:11] + ['wing'], q[:12])
    q_nan = q.copy()
    q_nan[3] = np.nan
    with pytest.raises(ValueError, match='NaN'):
        session.command(names, q_nan)
    q_far = q.copy()
    q_far[5] = session.model.joint_lower[5] - 0.1
    with pytest.raises(ValueError, match=f'{names[5]} is outside its limits'):
        session.command(names, q_far)
    with pytest.raises(ValueError, match='twice'):
        session.command([names[0], names[0]], [0.0, 0.0])
    with pytest.raises(ValueError, match='non-decreasing'):
        session.command(names, np.stack([q, q]), times_s=[0.5, 0.1])
    np.testing.assert_array_equal(session.q_target, before)


def test_session_interpolates_a_trajectory_and_holds_its_end(session):
    names = list(session.model.joint_names)
    q0 = session.q_target.copy()
    q1 = q0.copy()
    q1[1] = np.clip(q0[1] + 0.1, session.model.joint_lower[1], session.model.joint_upper[1])
    t0 = session.t_s
    session.command(names[:3], np.stack([q0[:3], q1[:3]]), times_s=[0.0, 0.4])
    session.step(int(round(0.2 / session.dt_s)))
    frac = (session.t_s - session.dt_s - t0) / 0.4   # a step tracks the target at its start
    assert session.q_target[1] == pytest.approx(q0[1] + frac * (q1[1] - q0[1]), abs=1e-9)
    session.step(int(round(0.4 / session.dt_s)))
    assert session.q_target[1] == pytest.approx(q1[1])
    np.testing.assert_array_equal(session.q_target[3:], q0[3:])   # unnamed joints untouched
    session.command(names, q0)                                     # back to standing
    session.step(50)


def test_session_captures_at_the_camera_rate_and_on_request(session):
    if session.capture_due():        # a capture left due by earlier tests' stepping
        session.mark_captured()
    while not session.capture_due():  # to the next periodic slot, whatever the session's
        session.step(1)               # time (the test alone starts at 0, after others not)
    stamps = [session.render().stamp_s]
    stamps += _captures_until(session, stamps[0] + 1.0)       # a window just under 1 s
    assert len(stamps) == 4
    np.testing.assert_allclose(np.diff(stamps), 0.25, atol=session.dt_s + 1e-9)
    t_req = session.t_s + 0.1
    session.request_capture(t_req)
    first_due = None
    while first_due is None:
        session.step(1)
        if session.capture_due():
            first_due = session.t_s
    assert first_due == pytest.approx(min(t_req, stamps[-1] + 0.25), abs=session.dt_s)
    cap = session.render()
    assert cap.left.shape == (session.stereo.left.height, session.stereo.left.width, 3)
    np.testing.assert_allclose(cap.T_world_camera, session.robot.camera_pose())


def _captures_until(session, t_end):
    """Step ``session`` to just before ``t_end``, rendering every due capture: their stamps."""
    stamps = []
    while session.t_s + session.dt_s < t_end - 1e-9:
        session.step(1)
        if session.capture_due():
            stamps.append(round(session.render().stamp_s, 6))
    return stamps


def test_a_periodic_capture_right_behind_a_requested_one_is_skipped(session):
    # camera 4 Hz (period 0.25 s), periodic_min_gap 0.5: a periodic slot due within 0.125 s
    # after a requested capture is a near-duplicate and skipped; one 0.15 s after is kept.
    assert session.cfg.periodic_min_gap == 0.5
    _captures_until(session, session.t_s + 0.6)    # serves requests earlier tests left
    while not session.capture_due():                        # to the next periodic capture
        session.step(1)
    first = round(session.render().stamp_s, 6)
    session.request_capture(first + 0.2)                    # 0.05 s before the next slot
    got = _captures_until(session, first + 0.8)
    np.testing.assert_allclose(got, [first + 0.2, first + 0.5, first + 0.75],
                               atol=session.dt_s + 1e-9)    # first + 0.25 skipped
    session.request_capture(got[-1] + 0.1)                  # 0.15 s before the next slot
    got = _captures_until(session, got[-1] + 0.3)
    np.testing.assert_allclose(got, [first + 0.85, first + 1.0], atol=session.dt_s + 1e-9)


def test_a_request_for_a_time_already_captured_is_served_by_that_capture(session):
    # The controller's request for time t can arrive while the simulator renders the periodic
    # capture of t: that capture serves it (no second one a step later); a request for a later
    # time still gets its own.
    _captures_until(session, session.t_s + 0.6)    # serves requests earlier tests left
    while not session.capture_due():
        session.step(1)
    first = round(session.render().stamp_s, 6)
    served = session.requests_already_served
    session.request_capture(first)                          # arrives after that render
    session.request_capture(first - 0.1)
    assert session.requests_already_served == served + 2
    assert _captures_until(session, first + 0.3) == pytest.approx([first + 0.25],
                                                              abs=session.dt_s + 1e-9)
    session.request_capture(session.t_s + 0.02)             # a later time: its own capture
    got = _captures_until(session, session.t_s + 0.1)
    assert len(got) == 1 and session.requests_already_served == served + 2


def test_scaled_camera_keeps_the_lens():
    from terrain_perception.sim.session import scaled_camera
    cam = PinholeCamera.from_fov(512, 480, 50.0)
    half = scaled_camera(cam, 0.5)
    assert (half.width, half.height) == (256, 240)
    p = np.array([0.1, -0.05, 1.0])
    # the same ray lands on the same image position in pixel-edge coordinates
    np.testing.assert_allclose((half.project(p) + 0.5) * 2.0, cam.project(p) + 0.5, atol=1e-9)
