"""Leg kinematics: FK/IK round trip over the reachable workspace, unreachable targets
reported (never clamped), Jacobian against finite differences, COM."""

import numpy as np
import pytest

from terrain_perception import kinematics as K
from terrain_perception.robot_model import load_robot_model

ROBOTS = ('littledog', 'frog')


@pytest.fixture(params=['compiled', 'numpy'])
def ik_impl(request):
    """Run a test with the compiled IK kernel and with the numpy code."""
    assert K.use_compiled_ik(request.param == 'compiled') == (request.param == 'compiled')
    yield request.param
    K.use_compiled_ik(None)


def _reachable_joint_samples(m, n, rng):
    """Joint angles within the limits on the IK's branch (knee direction of the profile,
    foot below the hip in the leg plane)."""
    lim = m.joint_limits
    q = rng.uniform(lim[..., 0], lim[..., 1], size=(n, 4, 3))
    q[..., 2] = np.where(m.knee_sign * q[..., 2] < 0, -q[..., 2], q[..., 2])
    q = np.clip(q, lim[..., 0], lim[..., 1])
    l1, l2 = m.thigh_length_m, m.shank_length_m
    zp = -l1 * np.cos(q[..., 1]) - l2 * np.cos(q[..., 1] + q[..., 2])
    keep = np.all(zp < -0.05 * (l1 + l2), axis=1)
    return q[keep]


@pytest.mark.parametrize('name', ROBOTS)
def test_ik_round_trip_over_workspace(name, ik_impl):
    m = load_robot_model(name)
    rng = np.random.default_rng(7)
    q = _reachable_joint_samples(m, 20000, rng)
    assert len(q) > 500
    p = K.forward(m, q)
    res = K.solve_ik(m, p)
    assert res.all_ok, res.reasons[:3]
    np.testing.assert_allclose(K.forward(m, res.q), p, atol=1e-6, rtol=0)
    # On this branch the joint solution is unique too.
    np.testing.assert_allclose(res.q, q, atol=1e-6)


@pytest.mark.parametrize('name', ROBOTS)
def test_unreachable_targets_are_reported_not_clamped(name, ik_impl):
    m = load_robot_model(name)
    feet = K.forward(m, K.standing_joint_angles(m))
    far = feet.copy()
    far[1, 2] -= 2.0 * m.leg_length_m           # RF far below its hip
    res = K.solve_ik(m, far)
    assert res.ok.tolist() == [True, False, True, True]
    assert np.all(np.isnan(res.q[1])) and np.all(np.isfinite(res.q[[0, 2, 3]]))
    assert len(res.reasons) == 1 and 'RF' in res.reasons[0] and 'beyond' in res.reasons[0]
    with pytest.raises(ValueError, match='RF'):
        K.inverse(m, far)
    # Inside the abduction-offset circle (foot at the hip).
    close = feet.copy()
    close[2] = m.hip_offsets[2]
    res = K.solve_ik(m, close)
    assert not res.ok[2] and 'LH' in ' '.join(res.reasons)
    # Reachable in length but needing a joint beyond its limit: foot far above the hip.
    up = feet.copy()
    up[0] = m.hip_offsets[0] + [0.0, m.abduction_offset_m, 0.8 * m.leg_length_m]
    res = K.solve_ik(m, up)
    assert not res.ok[0]
    # Batched input names the pose.
    res = K.solve_ik(m, np.stack([feet, far]))
    assert res.ok.tolist() == [[True] * 4, [True, False, True, True]]
    assert res.reasons[0].startswith('pose 1 leg RF')


@pytest.mark.parametrize('name', ROBOTS)
def test_compiled_ik_is_the_numpy_ik_to_the_bit(name):
    # Targets all over and beyond the workspace (every failure kind), NaN targets, a zero
    # leg-plane radius, batched and single poses: same ok, same reasons, the same angles bit for
    # bit where numpy's trigonometric ufuncs are the C library's (numba calls those); on a CPU
    # where numpy takes its own AVX-512 versions they differ in the last bits (measured: at
    # most 1.3e-15 rad), so the angles are compared to 1e-13 rad.
    m = load_robot_model(name)
    rng = np.random.default_rng(3)
    nom = K.forward(m, K.standing_joint_angles(m))
    p = nom + rng.normal(0.0, 0.6 * m.leg_length_m, (5000, 4, 3))
    p[10, 2] = np.nan
    p[11, 1, 1:] = m.hip_offsets[1, 1:] + [-m.abduction_offset_m, 0.0]   # rho2 == 0
    p[12, 0] = m.hip_offsets[0]                                            # inside the offset
    results = []
    for compiled in (False, True):
        K.use_compiled_ik(compiled)
        try:
            results.append((K.solve_ik(m, p), K.solve_ik(m, p[7]),
                            K.solve_ik(m, p[:50].reshape(5, 10, 4, 3), explain=False)))
        finally:
            K.use_compiled_ik(None)
    (a, a1, a5), (b, b1, b5) = results
    kinds = {r.split(': ')[1].split(' (')[0] for r in a.reasons}
    # the failure kinds occur (closer than |thigh - shank| only where the legs allow it)
    assert {'target beyond the leg length', 'solution outside the joint limits',
            'target inside the abduction offset circle'} <= kinds and 0.05 < a.ok.mean() < 0.5
    for x, y in ((a, b), (a1, b1), (a5, b5)):
        assert x.q.shape == y.q.shape and x.ok.shape == y.ok.shape
        assert np.array_equal(np.isnan(x.q), np.isnan(y.q))
        np.testing.assert_allclose(x.q, y.q, rtol=0.0, atol=1e-13, equal_nan=True)
        assert np.array_equal(x.ok, y.ok) and x.reasons == y.reasons
    assert not b.ok[10, 2] and np.isnan(b.q[10, 2]).all()


def test_ik_kernel_can_be_switched_off_by_environment():
    import subprocess
    import sys
    code = 'from terrain_perception import kinematics as K; print(K._ik is None)'
    out = [subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          env={**__import__('os').environ, 'TERRAIN_IK_NUMBA': v}).stdout.strip()
           for v in ('0', '1')]
    assert out == ['True', 'False']


def test_bad_shapes_are_refused():
    m = load_robot_model('littledog')
    with pytest.raises(ValueError, match='shape'):
        K.forward(m, np.zeros((3, 3)))
    with pytest.raises(ValueError, match='shape'):
        K.solve_ik(m, np.zeros(12))


@pytest.mark.parametrize('name', ROBOTS)
def test_jacobian_matches_finite_differences(name):
    m = load_robot_model(name)
    rng = np.random.default_rng(3)
    q = _reachable_joint_samples(m, 50, rng)
    J = K.jacobian(m, q)
    eps = 1e-6
    for j in range(3):
        dq = np.zeros(3)
        dq[j] = eps
        num = (K.forward(m, q + dq) - K.forward(m, q - dq)) / (2 * eps)
        np.testing.assert_allclose(J[..., j], num, atol=1e-7)


def test_com_is_mass_weighted_and_moves_with_a_leg():
    m = load_robot_model('littledog')
    q = K.standing_joint_angles(m)
    com = K.com_base(m, q)
    # Symmetric stance (mirror-symmetric legs): COM on the body's y = 0 plane, below the base.
    assert abs(com[1]) < 1e-12 and com[2] < 0
    # Swinging LF forward moves the COM forward by (leg mass share) x (foot displacement) order.
    feet = K.forward(m, q)
    feet[0, 0] += 0.05
    com2 = K.com_base(m, K.inverse(m, feet))
    leg_share = np.sum(m.link_masses_kg[1:]) / m.total_mass_kg
    assert 0.2 * leg_share * 0.05 < com2[0] - com[0] < leg_share * 0.05


def test_foot_forces_invert_the_static_torques():
    # tau = -J^T f for a known ground force on every foot; the estimate recovers f.
    m = load_robot_model('littledog')
    q = K.standing_joint_angles(m) + np.random.default_rng(0).normal(0, 0.1, (4, 3))
    f = np.array([[0.5, -0.2, 7.0], [0.0, 0.3, 5.0], [-0.4, 0.0, 9.0], [0.1, 0.1, 0.0]])
    tau = -(np.swapaxes(K.jacobian(m, q), -1, -2) @ f[..., None])[..., 0]
    np.testing.assert_allclose(K.foot_forces(m, q, tau), f, atol=1e-9)
    np.testing.assert_allclose(K.foot_forces(m, q.reshape(12), tau.reshape(12)), f, atol=1e-9)


def test_self_mask_covers_the_legs_and_not_the_ground_around_the_feet():
    m = load_robot_model('littledog')
    q = K.standing_joint_angles(m)
    lp = K.leg_points(m, q)                                 # (4, 4, 3) base frame
    T = np.eye(4)
    T[:3, 3] = [0.3, -0.1, 0.5]                            # any frame: the mask moves with it
    # points along every thigh and shank, 1 cm off the segment
    t = np.linspace(0.0, 1.0, 7)[:, None]
    on = np.concatenate([a + t * (b - a) + [0.0, 0.01, 0.0]
                         for leg in lp for a, b in ((leg[1], leg[2]), (leg[2], leg[3]))])
    feet = lp[:, 3]
    # ground 4 cm around each foot's contact point, and far ground
    ang = np.linspace(0, 2 * np.pi, 9)[:-1]
    ring = np.concatenate([f + np.c_[0.04 * np.cos(ang), 0.04 * np.sin(ang),
                                     np.full(8, -m.foot_radius_m)] for f in feet])
    far = np.array([[0.6, 0.0, feet[0, 2] - m.foot_radius_m], [np.nan, 0.0, 0.0]])
    pts = np.concatenate([on, ring, far]) + T[:3, 3]
    mask = K.self_mask(m, q, pts, T, margin_m=0.01)
    assert mask[:len(on)].all()
    assert not mask[len(on):].any()
    # organized input keeps its shape; a bad q is refused
    assert K.self_mask(m, q, pts[None, :4], T, 0.01).shape == (1, 4)
    with pytest.raises(ValueError):
        K.self_mask(m, np.zeros(5), pts, T, 0.01)


def test_self_mask_of_a_float32_cloud_equals_that_of_its_float64_values():
    """The bounding-box prefilter compares a float32 cloud (the node's clouds) against
    float64 bounds without widening it first: the mask is the one of the float64 copy (the
    earlier formulation), on an organized cloud around the legs with NaN holes."""
    m = load_robot_model('littledog')
    q = K.standing_joint_angles(m) + np.random.default_rng(3).normal(0, 0.05, (4, 3))
    T = np.eye(4)
    T[:3, 3] = [0.02, -0.01, 0.3]
    lp = K.leg_points(m, q)[:, 1:].reshape(-1, 3) + T[:3, 3]
    rng = np.random.default_rng(4)
    lo, hi = lp.min(axis=0) - 0.05, lp.max(axis=0) + 0.05
    cloud = rng.uniform(lo, hi, (120, 160, 3)).astype(np.float32)
    cloud[rng.random((120, 160)) < 0.1] = np.nan
    mask32 = K.self_mask(m, q, cloud, T, 0.015)
    mask64 = K.self_mask(m, q, cloud.astype(np.float64), T, 0.015)
    assert mask32.shape == (120, 160) and 500 < mask32.sum() < mask32.size // 2
    np.testing.assert_array_equal(mask32, mask64)
    flat = cloud.reshape(-1, 3)
    ints = np.round(flat[np.isfinite(flat).all(axis=1)][:50] * 100).astype(np.int64)  # widened
    np.testing.assert_array_equal(K.self_mask(m, q, ints, T, 1.0),
                                  K.self_mask(m, q, ints.astype(np.float64), T, 1.0))


@pytest.mark.parametrize('name', ['littledog', 'frog'])
def test_knees_sit_a_thigh_from_the_hip_and_a_shank_from_the_foot(name):
    """kinematics.leg_points' knee (the controller's shank check uses it): the thigh's length from the hip-flexion joint, the shank's from the
    foot centre, on the side knee_sign says (LittleDog: front knees behind, hind knees ahead
    of the foot)."""
    m = load_robot_model(name)
    rng = np.random.default_rng(3)
    lo, hi = m.joint_limits[..., 0], m.joint_limits[..., 1]
    q = lo + rng.uniform(size=(50, 4, 3)) * (hi - lo)
    kn, ft = K.leg_points(m, q)[..., 2, :], K.forward(m, q)
    np.testing.assert_allclose(np.linalg.norm(ft - kn, axis=-1), m.shank_length_m, atol=1e-12)
    side = np.array([1.0, -1.0, 1.0, -1.0]) * m.abduction_offset_m
    c0, s0 = np.cos(q[..., 0]), np.sin(q[..., 0])
    flexion = m.hip_offsets + np.stack([np.zeros_like(c0), c0 * side, s0 * side], -1)
    np.testing.assert_allclose(np.linalg.norm(kn - flexion, axis=-1), m.thigh_length_m,
                               atol=1e-12)
    stand = K.standing_joint_angles(m)
    ahead = (K.leg_points(m, stand)[:, 2] - K.forward(m, stand))[:, 0]
    assert np.all(np.sign(ahead) == m.knee_sign)
